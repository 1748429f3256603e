//! The moving part of a scene: the node graph with its animation channels, skins and morph
//! targets, and the one routine that turns them into world-space triangles at a time `t`.
//!
//! Why it exists: without it every new animation time re-parsed the file. A [`Rig`] holds,
//! format-free, exactly what placing the triangles needs, so [`Rig::pose`] can run at any
//! time without the file. The loader builds one for every scene and uses it for the static
//! pose too (one code path, so the loaded pose and an evaluated pose cannot drift apart);
//! it keeps it in the [`super::Scene`] only when the file animates.
//!
//! Arithmetic is f64 throughout and rounded once to f32. The order of operations is fixed:
//! `T·R·S` by [`DMat4::from_scale_rotation_translation`], products by glam's `DMat4 * DMat4`
//! and points by [`DMat4::transform_point3`] (each sums its terms left to right, as the
//! loader always did), and quaternion normalisation divides by the length rather than
//! multiplying by its reciprocal. glam's own `DQuat::slerp` and `normalize` are not used:
//! they multiply by reciprocals and switch to lerp at another threshold, which moves
//! positions in the last bit; [`slerp`] keeps the loader's formula. Rules of sampling
//! (glTF 2.0 §3.11, Appendix C): `t` is clamped to each sampler's input range; STEP holds
//! the last keyframe at or before `t`; LINEAR lerps, and slerps rotations along the
//! shorter arc; CUBICSPLINE is the Hermite spline with tangents scaled by the keyframe
//! interval, rotations normalised afterwards. Where several channels drive one property,
//! the last in file order wins.

use std::sync::Arc;

use glam::{DMat3, DMat4, DQuat, DVec3, Vec3, Vec4};

use super::{Camera, Projection, SceneError};
use crate::geometry::Triangle;

/// How a sampler interpolates between keyframes.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Interpolation {
    /// Hold the last keyframe at or before `t`.
    Step,
    /// Linear (slerp for rotations).
    Linear,
    /// Cubic Hermite spline through (in-tangent, value, out-tangent) triples.
    CubicSpline,
}

/// The node property a channel drives.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Target {
    /// Translation (3 values per keyframe).
    Translation,
    /// Rotation quaternion `(x, y, z, w)` (4 values per keyframe).
    Rotation,
    /// Scale (3 values per keyframe).
    Scale,
    /// Morph target weights (`width` values per keyframe).
    Weights,
}

/// One animation channel with its sampler's keyframes, checked by the loader: times are
/// finite and non-decreasing, values finite, and `output` holds `width` values per
/// keyframe element (three elements per keyframe for CUBICSPLINE).
#[derive(Clone, Debug)]
pub struct Channel {
    /// Index of its animation in the file (for error messages).
    pub animation: usize,
    /// Index of the channel in its animation (for error messages).
    pub channel: usize,
    /// The node it drives.
    pub node: usize,
    /// The property it drives.
    pub target: Target,
    /// The sampler's interpolation.
    pub interpolation: Interpolation,
    /// Keyframe times, seconds; never empty.
    pub input: Arc<[f64]>,
    /// Keyframe values.
    pub output: Arc<[f64]>,
    /// Values per keyframe element: 3, 4, or the number of morph weights.
    pub width: usize,
}

/// A node's stored local transform.
#[derive(Clone, Debug)]
pub enum Local {
    /// A `matrix`: never animated (glTF forbids animating a node that has one).
    Matrix(DMat4),
    /// Translation, rotation, scale; animated values replace stored ones.
    Trs {
        /// Stored translation.
        translation: DVec3,
        /// Stored rotation, normalised in f64; `None` when the file's is zero or not
        /// finite (an error only if the pose needs it, i.e. no channel replaces it).
        rotation: Option<DQuat>,
        /// Stored scale.
        scale: DVec3,
    },
}

/// A node of the graph (every node of the file, reachable or not: skins may use any).
#[derive(Clone, Debug)]
pub struct Node {
    /// Its stored local transform.
    pub local: Local,
    /// Its children, in order.
    pub children: Vec<usize>,
}

/// A skin: its joints and their inverse bind matrices.
#[derive(Clone, Debug)]
pub struct Skin {
    /// Joint nodes.
    pub joints: Vec<usize>,
    /// One per joint; `None` means identities (glTF 2.0 §3.7.3.1).
    pub inverse_bind: Option<Vec<DMat4>>,
}

/// One `JOINTS_n`/`WEIGHTS_n` pair, four per vertex each.
#[derive(Clone, Debug)]
pub struct SkinSet {
    /// Joint numbers (indices into the skin's joints).
    pub joints: Arc<[u32]>,
    /// Weights, as the accessor decodes them (f64: normalised integers are not f32-exact).
    pub weights: Arc<[f64]>,
}

/// A primitive's vertex data, decoded once and shared by every node instancing its mesh.
#[derive(Clone, Debug, Default)]
pub struct Primitive {
    /// Vertex indices, three per triangle, in id order; all below the vertex count.
    pub corners: Arc<[u32]>,
    /// POSITION, three per vertex.
    pub positions: Arc<[f64]>,
    /// Per morph target, its POSITION deltas (three per vertex) if it has any.
    pub targets: Vec<Option<Arc<[f64]>>>,
    /// `JOINTS_n`/`WEIGHTS_n` sets; joints are checked against the skin by the loader.
    pub skin_sets: Vec<SkinSet>,
    /// NORMAL (three per vertex), when shading data was asked for and the file has it.
    pub normals: Option<Arc<[f64]>>,
    /// Per morph target, its NORMAL deltas.
    pub normal_targets: Vec<Option<Arc<[f64]>>>,
    /// TANGENT (four per vertex, `w` the handedness), when asked for and present.
    pub tangents: Option<Arc<[f64]>>,
    /// Per morph target, its TANGENT deltas (three per vertex).
    pub tangent_targets: Vec<Option<Arc<[f64]>>>,
}

impl Primitive {
    /// Number of vertices.
    pub fn vertices(&self) -> usize {
        self.positions.len() / 3
    }
}

/// One node's use of a mesh.
#[derive(Clone, Debug)]
pub struct Instance {
    /// The node.
    pub node: usize,
    /// Its mesh (for error messages).
    pub mesh: usize,
    /// Its skin, for primitives that have joint sets (glTF: the skinned mesh node's own
    /// transform is then ignored).
    pub skin: Option<usize>,
    /// Static morph weights: the node's, else the mesh's, else none (all zero).
    pub weights: Vec<f64>,
    /// The mesh's primitives that have positions, with their index in the mesh.
    pub primitives: Vec<(usize, Arc<Primitive>)>,
}

/// What the scene's pre-order walk meets, in id order.
#[derive(Clone, Debug)]
pub enum Item {
    /// A mesh instance: its triangles come next in id order.
    Mesh(Instance),
    /// A camera on a node.
    Camera {
        /// The node.
        node: usize,
        /// Its index in the file's `cameras`.
        index: usize,
        /// Its clipping planes (`Camera::clip`).
        clip: [f64; 2],
        /// Its projection.
        projection: Projection,
    },
    /// A KHR_lights_punctual light on a node (the n-th `Light` item is `Scene::lights[n]`).
    Light {
        /// The node.
        node: usize,
    },
}

/// The node graph, animation channels, skins and mesh instances of a scene.
#[derive(Clone, Debug, Default)]
pub struct Rig {
    /// Every node of the file.
    pub nodes: Vec<Node>,
    /// Nodes without a parent.
    pub roots: Vec<usize>,
    /// Animation channels, animations in order, then channels in order.
    pub channels: Vec<Channel>,
    /// Skins of the file (`None` for skins no instance uses).
    pub skins: Vec<Option<Skin>>,
    /// Mesh instances, cameras and lights in the default scene's pre-order.
    pub items: Vec<Item>,
    /// How many cameras the file has (placed or not).
    pub camera_count: usize,
    /// Whether the scene's shading data has a normal per vertex (then poses carry them).
    pub normals: bool,
    /// Whether the scene's shading data has a tangent per vertex.
    pub tangents: bool,
}

/// What a pose computes besides positions.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum Compute {
    /// World positions (and cameras and lights): all a ray batch needs.
    #[default]
    Positions,
    /// Positions plus world-space shading normals and tangents, for rendering.
    PositionsAndNormals,
}

/// A scene's placement at one time.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Pose {
    /// Triangles in id order, world space.
    pub triangles: Vec<Triangle>,
    /// Unit world normals per shading vertex (see [`super::Shading`]); zero where the file
    /// has none. Empty unless asked for and the scene has normals.
    pub normals: Vec<Vec3>,
    /// World tangents per shading vertex, `w` the handedness; zero where absent.
    pub tangents: Vec<Vec4>,
    /// With normals: the triangles whose front face is wound clockwise, one bit each
    /// (see [`super::Shading::mirrored`]); empty when there are none.
    pub mirrored: Vec<u64>,
    /// Whether the pose was computed with [`Compute::PositionsAndNormals`].
    pub shaded: bool,
    /// Cameras by the file's index (`Scene::cameras`).
    pub cameras: Vec<Option<Camera>>,
    /// Light-to-world transforms, one per `Scene::lights` entry.
    pub lights: Vec<DMat4>,
}

/// A node's animated local state at one time; `None` keeps the stored value.
#[derive(Clone, Debug, Default)]
struct NodePose {
    translation: Option<DVec3>,
    rotation: Option<DQuat>,
    scale: Option<DVec3>,
    weights: Option<Vec<f64>>,
}

/// `q / |q|`; `None` for a zero or non-finite quaternion, which names no rotation.
///
/// Divides by the length (glam's `normalize` multiplies by its reciprocal, which rounds
/// differently); the length is glam's, summing x², y², z², w² in that order.
pub fn normalize_quat(q: DQuat) -> Option<DQuat> {
    let n = q.length();
    if n.is_finite() && n > 0.0 {
        Some(q / n)
    } else {
        None
    }
}

/// Spherical linear interpolation from `a` to `b` (both unit) along the shorter arc.
///
/// The angle between them is `2·atan2(|a − b|, |a + b|)`, which keeps its precision at
/// small angles, where `acos(a·b)` loses half the digits; so the slerp weights
/// `sin((1 − s)θ) / sin θ` and `sin(sθ) / sin θ` are accurate down to θ = 0, where they are
/// `1 − s` and `s`. (A normalised lerp below some angle, as glam's `DQuat::slerp` and this
/// function once used, is off by up to 8 f32 ULPs of a vertex near 3.6° between keys.)
pub fn slerp(a: DQuat, b: DQuat, s: f64) -> DQuat {
    // q and −q are the same rotation: flip one so the path is the short one.
    let b = if a.dot(b) < 0.0 { -b } else { b };
    let theta = 2.0 * (a - b).length().atan2((a + b).length());
    let sin = theta.sin();
    let (wa, wb) = if sin > 0.0 {
        (((1.0 - s) * theta).sin() / sin, (s * theta).sin() / sin)
    } else {
        (1.0 - s, s)
    };
    normalize_quat(a * wa + b * wb).unwrap_or(a)
}

fn bad_animation(ch: &Channel, reason: String) -> SceneError {
    SceneError::BadAnimation {
        animation: ch.animation,
        reason: format!("channel {}: {reason}", ch.channel),
    }
}

impl Channel {
    /// Keyframe element `i` (for CUBICSPLINE, `3k + 0/1/2` is in-tangent/value/out-tangent).
    fn element(&self, i: usize) -> &[f64] {
        &self.output[i * self.width..(i + 1) * self.width]
    }

    fn value(&self, k: usize) -> &[f64] {
        match self.interpolation {
            Interpolation::CubicSpline => self.element(3 * k + 1),
            _ => self.element(k),
        }
    }

    fn quat(v: &[f64]) -> DQuat {
        DQuat::from_xyzw(v[0], v[1], v[2], v[3])
    }

    fn unit_quat(&self, k: usize) -> Result<DQuat, SceneError> {
        normalize_quat(Self::quat(self.value(k))).ok_or_else(|| {
            bad_animation(self, format!("rotation keyframe {k} is a zero quaternion"))
        })
    }

    /// The first keyframe of a rotation channel whose quaternion has no length (zero, or
    /// one whose length over- or underflows): it names no rotation, so the loader refuses
    /// it rather than fail at the first time that samples it. `None` for other targets.
    pub fn zero_rotation(&self) -> Option<usize> {
        if self.target != Target::Rotation {
            return None;
        }
        (0..self.input.len()).find(|&k| self.unit_quat(k).is_err())
    }

    /// The channel's value at `t`: 3 values, a unit quaternion's 4, or `width` weights.
    fn sample(&self, t: f64) -> Result<Vec<f64>, SceneError> {
        let n = self.input.len();
        let t = t.max(self.input[0]).min(self.input[n - 1]);
        // The last keyframe at or before t; times are non-decreasing, so the next keyframe
        // (if any) is strictly after t and the interval below is positive.
        let k = self.input.partition_point(|&x| x <= t).saturating_sub(1);
        let rotation = self.target == Target::Rotation;
        let hold = || -> Result<Vec<f64>, SceneError> {
            Ok(if rotation {
                self.unit_quat(k)?.to_array().to_vec()
            } else {
                self.value(k).to_vec()
            })
        };
        if k + 1 >= n {
            return hold();
        }
        let (t0, t1) = (self.input[k], self.input[k + 1]);
        let td = t1 - t0;
        let s = if td > 0.0 { (t - t0) / td } else { 1.0 };
        match self.interpolation {
            Interpolation::Step => hold(),
            Interpolation::Linear if rotation => {
                Ok(slerp(self.unit_quat(k)?, self.unit_quat(k + 1)?, s)
                    .to_array()
                    .to_vec())
            }
            Interpolation::Linear => {
                let (a, b) = (self.value(k), self.value(k + 1));
                Ok(a.iter().zip(b).map(|(a, b)| a + s * (b - a)).collect())
            }
            Interpolation::CubicSpline => {
                let p0 = self.element(3 * k + 1);
                let m0 = self.element(3 * k + 2); // out-tangent of k
                let p1 = self.element(3 * (k + 1) + 1);
                let m1 = self.element(3 * (k + 1)); // in-tangent of k+1
                let (s2, s3) = (s * s, s * s * s);
                let h00 = 2.0 * s3 - 3.0 * s2 + 1.0;
                let h10 = s3 - 2.0 * s2 + s;
                let h01 = -2.0 * s3 + 3.0 * s2;
                let h11 = s3 - s2;
                let v: Vec<f64> = (0..self.width)
                    .map(|i| h00 * p0[i] + h10 * td * m0[i] + h01 * p1[i] + h11 * td * m1[i])
                    .collect();
                if rotation {
                    // A spline between two unit keyframes can pass through zero (q to −q
                    // with flat tangents, at the middle); there it names no rotation, and
                    // the nearer keyframe stands in, so that every time has a pose.
                    let q = match normalize_quat(Self::quat(&v)) {
                        Some(q) => q,
                        None => self.unit_quat(if s < 0.5 { k } else { k + 1 })?,
                    };
                    Ok(q.to_array().to_vec())
                } else {
                    Ok(v)
                }
            }
        }
    }
}

/// `m`'s 3×3 part for normals: the inverse transpose, zero for a singular matrix (a
/// flattened instance has no meaningful normal; zero means "use the face normal").
fn normal_matrix(m: &DMat4) -> DMat3 {
    DMat3::from_mat4(*m).inverse_or_zero().transpose()
}

/// Rounds a direction to a unit f32 vector; zero stays zero.
fn unit_f32(v: DVec3) -> Vec3 {
    let n = v.length();
    if n.is_finite() && n > 0.0 {
        (v / n).as_vec3()
    } else {
        Vec3::ZERO
    }
}

fn vec3_at(a: &[f64], v: usize) -> DVec3 {
    DVec3::new(a[3 * v], a[3 * v + 1], a[3 * v + 2])
}

impl Rig {
    /// Every node's animated local state at `t`, all channels applied in file order.
    fn sample(&self, t: f64) -> Result<Vec<NodePose>, SceneError> {
        let mut poses = vec![NodePose::default(); self.nodes.len()];
        for ch in &self.channels {
            let v = ch.sample(t)?;
            let pose = &mut poses[ch.node];
            match ch.target {
                Target::Translation => pose.translation = Some(DVec3::new(v[0], v[1], v[2])),
                Target::Scale => pose.scale = Some(DVec3::new(v[0], v[1], v[2])),
                Target::Rotation => pose.rotation = Some(Channel::quat(&v)),
                Target::Weights => pose.weights = Some(v),
            }
        }
        Ok(poses)
    }

    /// Local transforms at the sampled poses (`None`: the stored ones).
    fn locals(&self, poses: Option<&[NodePose]>) -> Result<Vec<DMat4>, SceneError> {
        let mut out = Vec::with_capacity(self.nodes.len());
        for (i, node) in self.nodes.iter().enumerate() {
            let bad = |reason: &str| SceneError::BadNode {
                node: i,
                reason: reason.to_string(),
            };
            let pose = poses.map(|p| &p[i]);
            let m = match &node.local {
                Local::Matrix(m) => *m,
                Local::Trs {
                    translation,
                    rotation,
                    scale,
                } => {
                    let t = pose.and_then(|p| p.translation).unwrap_or(*translation);
                    let s = pose.and_then(|p| p.scale).unwrap_or(*scale);
                    let q = match pose.and_then(|p| p.rotation) {
                        Some(q) => q,
                        None => rotation
                            .ok_or_else(|| bad("rotation is a zero or non-finite quaternion"))?,
                    };
                    DMat4::from_scale_rotation_translation(s, q, t)
                }
            };
            if !m.is_finite() {
                return Err(bad("transform has a non-finite value"));
            }
            out.push(m);
        }
        Ok(out)
    }

    /// World transforms: parent's world · local, roots at their local.
    fn worlds(&self, local: &[DMat4]) -> Vec<DMat4> {
        let mut world = vec![DMat4::IDENTITY; self.nodes.len()];
        let mut stack = self.roots.clone();
        for &r in &stack {
            world[r] = local[r];
        }
        while let Some(i) = stack.pop() {
            for &c in &self.nodes[i].children {
                world[c] = world[i] * local[c];
                stack.push(c);
            }
        }
        world
    }

    /// Checks the channels and local transforms of the pose at `t` (`None`: the stored
    /// one) without placing anything: the errors a load reports before decoding meshes.
    pub fn check_transforms(&self, t: Option<f64>) -> Result<(), SceneError> {
        if let Some(t) = t.filter(|t| !t.is_finite()) {
            return Err(SceneError::BadTime(t));
        }
        let poses = t.map(|t| self.sample(t)).transpose()?;
        self.locals(poses.as_deref()).map(|_| ())
    }

    /// The pose at time `t` (`None`: the stored, static pose), written into `out` (its
    /// buffers are reused). `t` must be finite.
    pub fn pose(&self, t: Option<f64>, compute: Compute, out: &mut Pose) -> Result<(), SceneError> {
        if let Some(t) = t.filter(|t| !t.is_finite()) {
            return Err(SceneError::BadTime(t));
        }
        let poses = match t {
            Some(t) => Some(self.sample(t)?),
            None => None,
        };
        let locals = self.locals(poses.as_deref())?;
        let world = self.worlds(&locals);
        let normals = compute == Compute::PositionsAndNormals;
        out.triangles.clear();
        out.normals.clear();
        out.tangents.clear();
        out.mirrored.clear();
        out.shaded = normals;
        out.cameras.clear();
        out.cameras.resize(self.camera_count, None);
        out.lights.clear();
        let mut skins: Vec<Option<Vec<DMat4>>> = vec![None; self.skins.len()];
        for item in &self.items {
            match item {
                Item::Mesh(instance) => {
                    let weights = poses
                        .as_ref()
                        .and_then(|p| p[instance.node].weights.as_deref())
                        .unwrap_or(&instance.weights);
                    let joints = match instance.skin {
                        Some(s) => {
                            if skins[s].is_none() {
                                skins[s] = Some(self.skin_matrices(s, &world));
                            }
                            skins[s].as_deref().map(|j| (s, j))
                        }
                        None => None,
                    };
                    for (pi, prim) in &instance.primitives {
                        let placed = Placement {
                            instance,
                            primitive: *pi,
                            prim,
                            world: &world[instance.node],
                            weights,
                            joints: joints.filter(|_| !prim.skin_sets.is_empty()),
                        };
                        let first = out.triangles.len();
                        placed.positions(&mut out.triangles)?;
                        if normals {
                            placed.shading(self, &mut out.normals, &mut out.tangents);
                            placed.mirrored(first, &mut out.mirrored);
                        }
                    }
                }
                // A camera that an earlier node placed stays where that node put it.
                Item::Camera { index, .. } if out.cameras[*index].is_some() => {}
                Item::Camera {
                    node,
                    index,
                    projection,
                    clip,
                } => {
                    // Each local transform is finite, but a chain of large scales can
                    // overflow.
                    let w = world[*node];
                    if !w.is_finite() {
                        return Err(SceneError::BadNode {
                            node: *node,
                            reason: "the camera's world transform is not finite".to_string(),
                        });
                    }
                    out.cameras[*index] = Some(Camera {
                        to_world: w.to_cols_array_2d(),
                        projection: *projection,
                        clip: *clip,
                    });
                }
                Item::Light { node } => out.lights.push(world[*node]),
            }
        }
        Ok(())
    }

    /// `jointWorld_j · inverseBind_j` for every joint of skin `s`.
    fn skin_matrices(&self, s: usize, world: &[DMat4]) -> Vec<DMat4> {
        let Some(skin) = &self.skins[s] else {
            return Vec::new();
        };
        skin.joints
            .iter()
            .enumerate()
            .map(|(k, &j)| match &skin.inverse_bind {
                Some(ibm) => world[j] * ibm[k],
                None => world[j],
            })
            .collect()
    }

    /// Bytes held: keyframes, vertex data (each shared buffer once), nodes and skins.
    pub fn bytes(&self) -> usize {
        use std::collections::HashSet;
        let mut seen: HashSet<usize> = HashSet::new();
        let mut total = 0usize;
        let mut add = |ptr: usize, bytes: usize| {
            if seen.insert(ptr) {
                total += bytes;
            }
        };
        for ch in &self.channels {
            add(
                ch.input.as_ptr() as usize,
                std::mem::size_of_val(&*ch.input),
            );
            add(
                ch.output.as_ptr() as usize,
                std::mem::size_of_val(&*ch.output),
            );
        }
        for item in &self.items {
            let Item::Mesh(instance) = item else { continue };
            add(
                instance.weights.as_ptr() as usize,
                instance.weights.len() * 8,
            );
            for (_, p) in &instance.primitives {
                add(Arc::as_ptr(p) as usize, std::mem::size_of::<Primitive>());
                add(p.corners.as_ptr() as usize, p.corners.len() * 4);
                let f64s = std::iter::once(Some(&p.positions))
                    .chain(p.targets.iter().map(Option::as_ref))
                    .chain(std::iter::once(p.normals.as_ref()))
                    .chain(p.normal_targets.iter().map(Option::as_ref))
                    .chain(std::iter::once(p.tangents.as_ref()))
                    .chain(p.tangent_targets.iter().map(Option::as_ref))
                    .flatten();
                for a in f64s {
                    add(a.as_ptr() as usize, a.len() * 8);
                }
                for set in &p.skin_sets {
                    add(set.joints.as_ptr() as usize, set.joints.len() * 4);
                    add(set.weights.as_ptr() as usize, set.weights.len() * 8);
                }
            }
        }
        let nodes: usize = self
            .nodes
            .iter()
            .map(|n| std::mem::size_of::<Node>() + n.children.len() * 8)
            .sum();
        let skins: usize = self
            .skins
            .iter()
            .flatten()
            .map(|s| s.joints.len() * 8 + s.inverse_bind.as_ref().map_or(0, |m| m.len() * 128))
            .sum();
        total
            + nodes
            + skins
            + self.items.len() * std::mem::size_of::<Item>()
            + self.channels.len() * std::mem::size_of::<Channel>()
    }
}

/// One primitive of one instance, with the transforms of the pose.
struct Placement<'a> {
    instance: &'a Instance,
    primitive: usize,
    prim: &'a Primitive,
    world: &'a DMat4,
    weights: &'a [f64],
    /// The skin and its joint matrices, when the primitive is skinned.
    joints: Option<(usize, &'a [DMat4])>,
}

impl Placement<'_> {
    /// Targets with a zero weight or without data change nothing.
    fn morphs<'d>(&self, targets: &'d [Option<Arc<[f64]>>]) -> Vec<(f64, &'d [f64])> {
        targets
            .iter()
            .zip(self.weights)
            .filter_map(|(d, &w)| d.as_deref().filter(|_| w != 0.0).map(|d| (w, d)))
            .collect()
    }

    /// Vertex `v`'s skinning matrix `Σ w_k · joint_k`.
    fn skin_matrix(&self, mats: &[DMat4], skin: usize, v: usize) -> Result<DMat4, SceneError> {
        let mut s = DMat4::ZERO;
        for set in &self.prim.skin_sets {
            for k in 0..4 {
                let w = set.weights[4 * v + k];
                if w == 0.0 {
                    continue;
                }
                let j = set.joints[4 * v + k] as usize;
                let Some(mat) = mats.get(j) else {
                    return Err(SceneError::JointOutOfRange {
                        mesh: self.instance.mesh,
                        primitive: self.primitive,
                        vertex: v,
                        joint: j,
                        skin,
                        joints: mats.len(),
                    });
                };
                s += *mat * w;
            }
        }
        Ok(s)
    }

    /// Appends the primitive's triangles.
    fn positions(&self, out: &mut Vec<Triangle>) -> Result<(), SceneError> {
        let prim = self.prim;
        let morphs = self.morphs(&prim.targets);
        let position = |v: usize| -> Result<[f32; 3], SceneError> {
            let mut p = [
                prim.positions[3 * v],
                prim.positions[3 * v + 1],
                prim.positions[3 * v + 2],
            ];
            for &(w, d) in &morphs {
                for k in 0..3 {
                    p[k] += w * d[3 * v + k];
                }
            }
            let p = DVec3::from_array(p);
            let q = match self.joints {
                None => self.world.transform_point3(p),
                Some((skin, mats)) => self.skin_matrix(mats, skin, v)?.transform_point3(p),
            };
            let f = q.as_vec3().to_array();
            if f.iter().any(|x| !x.is_finite()) {
                return Err(SceneError::NonFiniteWorldPosition {
                    node: self.instance.node,
                    mesh: self.instance.mesh,
                    primitive: self.primitive,
                    vertex: v,
                });
            }
            Ok(f)
        };
        out.reserve(prim.corners.len() / 3);
        for c in prim.corners.chunks_exact(3) {
            out.push(Triangle {
                v: [
                    position(c[0] as usize)?,
                    position(c[1] as usize)?,
                    position(c[2] as usize)?,
                ],
            });
        }
        Ok(())
    }

    /// Marks in `bits` the primitive's triangles (the first has id `first`) whose
    /// transform mirrors (negative determinant), where the primitive has no `NORMAL`:
    /// glTF winds their front faces clockwise, so their face normal is the reverse of
    /// the one their vertex order gives. A skinned triangle takes its first vertex's
    /// skinning matrix. With `NORMAL` the stored normals say which side is in front.
    fn mirrored(&self, first: usize, bits: &mut Vec<u64>) {
        let prim = self.prim;
        if prim.normals.is_some() {
            return;
        }
        let mirrors = |m: &DMat4| DMat3::from_mat4(*m).determinant() < 0.0;
        let triangles = prim.corners.len() / 3;
        match self.joints {
            None if mirrors(self.world) => {
                (first..first + triangles).for_each(|id| super::set_bit(bits, id));
            }
            None => {}
            Some((skin, mats)) => {
                for (k, c) in prim.corners.chunks_exact(3).enumerate() {
                    // A joint the skin lacks was refused when the positions were placed.
                    let m = self.skin_matrix(mats, skin, c[0] as usize);
                    if m.is_ok_and(|m| mirrors(&m)) {
                        super::set_bit(bits, first + k);
                    }
                }
            }
        }
    }

    /// Appends one world normal and tangent per vertex (zero where the file has none), if
    /// the scene keeps them.
    fn shading(&self, rig: &Rig, normals: &mut Vec<Vec3>, tangents: &mut Vec<Vec4>) {
        let prim = self.prim;
        let n = prim.vertices();
        let fixed = DMat3::from_mat4(*self.world);
        let fixed_normal = normal_matrix(self.world);
        let matrix = |v: usize| -> (DMat3, DMat3) {
            match self.joints {
                // A joint the skin lacks was refused when the positions were placed.
                Some((skin, mats)) => match self.skin_matrix(mats, skin, v) {
                    Ok(s) => (DMat3::from_mat4(s), normal_matrix(&s)),
                    Err(_) => (DMat3::ZERO, DMat3::ZERO),
                },
                None => (fixed, fixed_normal),
            }
        };
        if rig.normals {
            match &prim.normals {
                None => normals.extend(std::iter::repeat_n(Vec3::ZERO, n)),
                Some(base) => {
                    let morphs = self.morphs(&prim.normal_targets);
                    for v in 0..n {
                        let mut d = vec3_at(base, v);
                        for &(w, t) in &morphs {
                            d += vec3_at(t, v) * w;
                        }
                        normals.push(unit_f32(matrix(v).1 * d));
                    }
                }
            }
        }
        if rig.tangents {
            match &prim.tangents {
                None => tangents.extend(std::iter::repeat_n(Vec4::ZERO, n)),
                Some(base) => {
                    let morphs = self.morphs(&prim.tangent_targets);
                    for v in 0..n {
                        let mut d = DVec3::new(base[4 * v], base[4 * v + 1], base[4 * v + 2]);
                        for &(w, t) in &morphs {
                            d += vec3_at(t, v) * w;
                        }
                        let m = matrix(v).0;
                        // A mirroring transform flips the bitangent cross(n, t).
                        let hand = if m.determinant() < 0.0 { -1.0 } else { 1.0 };
                        let w = (base[4 * v + 3] * hand) as f32;
                        tangents.push(unit_f32(m * d).extend(w));
                    }
                }
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn close(a: &[f64], b: &[f64]) -> bool {
        a.iter().zip(b).all(|(x, y)| (x - y).abs() < 1e-12)
    }

    #[test]
    fn trs_matches_composition() {
        // 90° about +Z maps +X to +Y.
        let h = std::f64::consts::FRAC_1_SQRT_2;
        let q = DQuat::from_xyzw(0.0, 0.0, h, h);
        let m =
            DMat4::from_scale_rotation_translation(DVec3::splat(2.0), q, DVec3::new(1.0, 2.0, 3.0));
        let p = m.transform_point3(DVec3::X);
        assert!(close(&p.to_array(), &[1.0, 4.0, 3.0]), "{p:?}");
        let t = DMat4::from_translation(DVec3::new(1.0, 2.0, 3.0));
        let rs = DMat4::from_scale_rotation_translation(DVec3::splat(2.0), q, DVec3::ZERO);
        assert!(close(&m.to_cols_array(), &(t * rs).to_cols_array()));
    }

    #[test]
    fn slerp_halfway_and_short_arc() {
        let h = std::f64::consts::FRAC_1_SQRT_2;
        let a = DQuat::IDENTITY;
        let b = DQuat::from_xyzw(0.0, 0.0, h, h); // 90° about z
        let m = slerp(a, b, 0.5);
        let s = (std::f64::consts::PI / 8.0).sin();
        let c = (std::f64::consts::PI / 8.0).cos();
        assert!(close(&m.to_array(), &[0.0, 0.0, s, c]), "{m:?}");
        // −b is the same rotation: the result must be the same up to sign.
        let m2 = slerp(a, -b, 0.5);
        assert!(close(&m2.to_array(), &m.to_array()), "{m2:?}");
    }

    /// At small angles between keys the slerp is still the rotation by `s` of the angle:
    /// a normalised lerp there was off by 1e-6 (8 f32 ULPs) of a vertex a unit away.
    #[test]
    fn slerp_is_exact_at_small_angles() {
        for degrees in [1e-9, 1e-4, 0.5, 2.0, 3.58, 3.7, 20.0] {
            let angle = f64::to_radians(degrees);
            let about_z = |a: f64| DQuat::from_xyzw(0.0, 0.0, (a / 2.0).sin(), (a / 2.0).cos());
            for s in [0.1, 0.3, 0.5, 0.9] {
                let m = slerp(about_z(0.0), about_z(angle), s);
                let want = about_z(s * angle);
                let err = (m - want).length();
                assert!(err < 1e-15, "{degrees}° at {s}: {err:e}");
            }
        }
        assert_eq!(
            slerp(DQuat::IDENTITY, DQuat::IDENTITY, 0.25),
            DQuat::IDENTITY
        );
    }

    #[test]
    fn zero_quaternion_is_no_rotation() {
        assert!(normalize_quat(DQuat::from_xyzw(0.0, 0.0, 0.0, 0.0)).is_none());
        assert!(normalize_quat(DQuat::from_xyzw(f64::NAN, 0.0, 0.0, 1.0)).is_none());
        let q = normalize_quat(DQuat::from_xyzw(0.0, 0.0, 0.0, 2.0)).unwrap();
        assert_eq!(q, DQuat::IDENTITY);
    }

    /// A rotation spline from q to −q with flat tangents passes through zero halfway; the
    /// nearer keyframe stands in there, so every time still has a pose.
    #[test]
    fn a_rotation_spline_through_zero_holds_the_nearer_keyframe() {
        let q = [0.0, 0.0, 0.6, 0.8];
        let mut output = vec![];
        for v in [q, q.map(|x: f64| -x)] {
            output.extend([0.0; 4]);
            output.extend(v);
            output.extend([0.0; 4]);
        }
        let ch = Channel {
            animation: 0,
            channel: 0,
            node: 0,
            target: Target::Rotation,
            interpolation: Interpolation::CubicSpline,
            input: vec![0.0, 1.0].into(),
            output: output.into(),
            width: 4,
        };
        assert_eq!(ch.sample(0.5).unwrap(), vec![0.0, 0.0, -0.6, -0.8]);
        let at = ch.sample(0.25).unwrap();
        assert!(
            at.iter().zip(q).all(|(a, b)| (a - b).abs() < 1e-12),
            "{at:?}"
        );
    }

    /// One triangle on a node whose translation moves linearly from 0 to 10 over 1 s.
    fn moving_triangle() -> Rig {
        let prim = Primitive {
            corners: vec![0, 1, 2].into(),
            positions: vec![0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0, 0.0].into(),
            normals: Some(vec![0.0, 0.0, 2.0, 0.0, 0.0, 1.0, 0.0, 0.0, 1.0].into()),
            ..Primitive::default()
        };
        Rig {
            nodes: vec![Node {
                local: Local::Trs {
                    translation: DVec3::ZERO,
                    rotation: Some(DQuat::IDENTITY),
                    scale: DVec3::new(1.0, 1.0, -1.0),
                },
                children: vec![],
            }],
            roots: vec![0],
            channels: vec![Channel {
                animation: 0,
                channel: 0,
                node: 0,
                target: Target::Translation,
                interpolation: Interpolation::Linear,
                input: vec![0.0, 1.0].into(),
                output: vec![0.0, 0.0, 0.0, 10.0, 0.0, 0.0].into(),
                width: 3,
            }],
            skins: vec![],
            items: vec![Item::Mesh(Instance {
                node: 0,
                mesh: 0,
                skin: None,
                weights: vec![],
                primitives: vec![(0, Arc::new(prim))],
            })],
            camera_count: 0,
            normals: true,
            tangents: false,
        }
    }

    #[test]
    fn pose_moves_with_time_and_clamps() {
        let rig = moving_triangle();
        let mut pose = Pose::default();
        for (t, x) in [
            (None, 0.0),
            (Some(-1.0), 0.0),
            (Some(0.25), 2.5),
            (Some(7.0), 10.0),
        ] {
            rig.pose(t, Compute::PositionsAndNormals, &mut pose)
                .unwrap();
            assert_eq!(pose.triangles.len(), 1);
            assert_eq!(
                pose.triangles[0].v[1],
                [x as f32 + 1.0, 0.0, 0.0],
                "t={t:?}"
            );
            // The mirror in z flips the normal, which is normalised.
            assert_eq!(pose.normals, vec![Vec3::new(0.0, 0.0, -1.0); 3]);
        }
        rig.pose(Some(0.5), Compute::Positions, &mut pose).unwrap();
        assert!(pose.normals.is_empty());
        let e = rig
            .pose(Some(f64::INFINITY), Compute::Positions, &mut pose)
            .unwrap_err();
        assert!(matches!(e, SceneError::BadTime(_)), "{e}");
    }

    /// glTF winds a mirrored placement's front faces clockwise: a primitive without
    /// `NORMAL` under a negative determinant is marked, one with normals is not (its
    /// normals say which side is in front), nor one placed without a mirror.
    #[test]
    fn mirrored_triangles_without_normals_are_marked() {
        let mut rig = moving_triangle();
        let mut pose = Pose::default();
        rig.pose(None, Compute::PositionsAndNormals, &mut pose)
            .unwrap();
        assert!(pose.mirrored.is_empty() && pose.shaded);
        let Item::Mesh(inst) = &mut rig.items[0] else {
            unreachable!()
        };
        let mut prim = (*inst.primitives[0].1).clone();
        prim.normals = None;
        inst.primitives[0].1 = Arc::new(prim.clone());
        // The same primitive twice: only the second's placement mirrors.
        rig.nodes.push(Node {
            local: Local::Trs {
                translation: DVec3::ZERO,
                rotation: Some(DQuat::IDENTITY),
                scale: DVec3::ONE,
            },
            children: vec![],
        });
        rig.roots.push(1);
        rig.items.insert(
            0,
            Item::Mesh(Instance {
                node: 1,
                mesh: 0,
                skin: None,
                weights: vec![],
                primitives: vec![(0, Arc::new(prim))],
            }),
        );
        rig.pose(Some(0.5), Compute::PositionsAndNormals, &mut pose)
            .unwrap();
        assert_eq!(pose.mirrored, vec![0b10]);
        rig.pose(Some(0.5), Compute::Positions, &mut pose).unwrap();
        assert!(pose.mirrored.is_empty() && !pose.shaded);
    }

    #[test]
    fn overflow_is_an_error_naming_the_vertex() {
        let mut rig = moving_triangle();
        rig.channels[0].output = vec![0.0, 0.0, 0.0, 1e300, 0.0, 0.0].into();
        let mut pose = Pose::default();
        let e = rig
            .pose(Some(0.5), Compute::Positions, &mut pose)
            .unwrap_err();
        assert_eq!(
            e.to_string(),
            "node 0 mesh 0 primitive 0: vertex 0 is not finite in world space"
        );
    }
}
