//! Primitives to the rig's vertex data: triangulation of every mode, morph targets, joint
//! sets and (for renders) shading attributes, all checked. Placing them in world space is
//! the scene's ([`crate::scene::rig`]), in f64, rounded to f32 once.

use std::collections::HashMap;
use std::sync::Arc;

use glam::DMat4;
use gltf::json;
use gltf::json::accessor::Type;
use gltf::json::mesh::{Mode, Semantic};
use gltf::json::validation::Checked;

use super::accessor::{rules, Data, Expect};
use super::GltfError;
use crate::scene::rig::{Primitive, Skin, SkinSet};
use crate::scene::SceneError;

/// Pose-independent shading attributes of a primitive (renders only).
#[derive(Default)]
pub(super) struct PrimShading {
    /// The primitive's material, if it names one.
    pub material: Option<usize>,
    /// TEXCOORD_0, two per vertex.
    pub uv0: Option<Arc<[f64]>>,
    /// TEXCOORD_1, two per vertex.
    pub uv1: Option<Arc<[f64]>>,
    /// COLOR_0 and its width (3 or 4 per vertex).
    pub colors: Option<(Arc<[f64]>, usize)>,
}

/// A decoded primitive with its shading attributes.
pub(super) struct Decoded {
    pub prim: Arc<Primitive>,
    pub shading: Arc<PrimShading>,
}

/// A decoded primitive as cached: `None` for one without positions.
type Cached = Option<(Arc<Primitive>, Arc<PrimShading>)>;

/// An attribute's values and its accessor type.
type Values = Option<(Arc<[f64]>, Type)>;

/// Decodes primitives once each and shares them between instances.
pub(super) struct Meshes {
    quantized: bool,
    /// Whether shading attributes are decoded too.
    shading: bool,
    prims: HashMap<(usize, usize), Cached>,
}

/// Each mesh's number of morph targets, checked as glTF requires: every primitive of a
/// mesh has the same number, and the mesh's `weights` and those of every node that
/// instances it have one per target. (Weights of the wrong length would be read from the
/// wrong targets' places.)
pub(super) fn morph_target_counts(root: &json::Root) -> Result<Vec<usize>, GltfError> {
    let mut counts = Vec::with_capacity(root.meshes.len());
    for (m, mesh) in root.meshes.iter().enumerate() {
        let targets = |p: &json::mesh::Primitive| p.targets.as_ref().map_or(0, Vec::len);
        let count = mesh.primitives.first().map_or(0, targets);
        if let Some((pi, p)) = mesh
            .primitives
            .iter()
            .enumerate()
            .find(|(_, p)| targets(p) != count)
        {
            return Err(bad_prim(
                m,
                pi,
                format!(
                    "has {} morph targets, but primitive 0 has {count} (every primitive of a mesh must have as many)",
                    targets(p)
                ),
            ));
        }
        if let Some(w) = mesh.weights.as_ref().filter(|w| w.len() != count) {
            return Err(GltfError::BadMesh {
                mesh: m,
                reason: format!(
                    "has {} weights for {count} morph targets (one each, as glTF requires)",
                    w.len()
                ),
            });
        }
        counts.push(count);
    }
    for (n, node) in root.nodes.iter().enumerate() {
        let (Some(w), Some(m)) = (&node.weights, node.mesh) else {
            continue;
        };
        // The mesh reference was checked with the node graph.
        let count = counts.get(m.value()).copied().unwrap_or(0);
        if w.len() != count {
            return Err(crate::scene::SceneError::BadNode {
                node: n,
                reason: format!(
                    "has {} weights, but its mesh {} has {count} morph targets (one each, as glTF requires)",
                    w.len(),
                    m.value()
                ),
            }
            .into());
        }
    }
    Ok(counts)
}

fn bad_prim(mesh: usize, primitive: usize, reason: String) -> GltfError {
    GltfError::BadPrimitive {
        mesh,
        primitive,
        reason,
    }
}

fn attribute(p: &json::mesh::Primitive, s: Semantic) -> Option<usize> {
    p.attributes.get(&Checked::Valid(s)).map(|a| a.value())
}

/// Triangles a mode makes from `n` vertices (or indices).
fn triangles_for(mode: Mode, n: usize) -> usize {
    match mode {
        Mode::Triangles => n / 3,
        Mode::TriangleStrip | Mode::TriangleFan => n.saturating_sub(2),
        Mode::Points | Mode::Lines | Mode::LineLoop | Mode::LineStrip => 0,
    }
}

impl Meshes {
    pub(super) fn new(quantized: bool, shading: bool) -> Meshes {
        Meshes {
            quantized,
            shading,
            prims: HashMap::new(),
        }
    }

    fn position_rules(&self) -> &'static [(json::accessor::ComponentType, Option<bool>)] {
        if self.quantized {
            rules::QUANTIZED
        } else {
            rules::FLOAT
        }
    }

    /// Triangles of mesh `m` from the document alone (no data read), checking what it
    /// looks at. Lets the loader bound the output before allocating it.
    pub(super) fn triangle_count(&self, data: &Data<'_>, m: usize) -> Result<u64, GltfError> {
        let mesh = &data.root.meshes[m];
        let mut total = 0u64;
        for (pi, p) in mesh.primitives.iter().enumerate() {
            let Checked::Valid(mode) = p.mode else {
                return Err(bad_prim(m, pi, "invalid mode".to_string()));
            };
            // A primitive without positions is not drawn (glTF 2.0 §3.7.2.1).
            let Some(pos) = attribute(p, Semantic::Positions) else {
                continue;
            };
            let n = match p.indices {
                Some(ia) => {
                    let ia = ia.value();
                    data.accessor(ia, &|| format!("mesh {m} primitive {pi} indices"))?;
                    data.layout_as(ia, &self.indices_expect(m, pi))?.count
                }
                None => {
                    data.accessor(pos, &|| format!("mesh {m} primitive {pi} POSITION"))?;
                    data.layout_as(pos, &self.position_expect(m, pi))?.count
                }
            };
            total += triangles_for(mode, n) as u64;
        }
        Ok(total)
    }

    fn indices_expect(&self, m: usize, pi: usize) -> Expect {
        Expect {
            what: format!("indices of mesh {m} primitive {pi}"),
            types: &[Type::Scalar],
            components: rules::INDICES,
        }
    }

    fn position_expect(&self, m: usize, pi: usize) -> Expect {
        Expect {
            what: format!("POSITION of mesh {m} primitive {pi}"),
            types: &[Type::Vec3],
            components: self.position_rules(),
        }
    }

    /// Decodes primitive `pi` of mesh `m` (once); `None` when it has no positions.
    pub(super) fn prim(
        &mut self,
        data: &mut Data<'_>,
        m: usize,
        pi: usize,
    ) -> Result<Option<Decoded>, GltfError> {
        if let Some(p) = self.prims.get(&(m, pi)) {
            return Ok(p.clone().map(|(prim, shading)| Decoded { prim, shading }));
        }
        let decoded = self.decode(data, m, pi)?;
        self.prims.insert((m, pi), decoded.clone());
        Ok(decoded.map(|(prim, shading)| Decoded { prim, shading }))
    }

    fn decode(&self, data: &mut Data<'_>, m: usize, pi: usize) -> Result<Cached, GltfError> {
        let p = &data.root.meshes[m].primitives[pi];
        let Some(pos_a) = attribute(p, Semantic::Positions) else {
            return Ok(None);
        };
        let Checked::Valid(mode) = p.mode else {
            return Err(bad_prim(m, pi, "invalid mode".to_string()));
        };
        data.accessor(pos_a, &|| format!("mesh {m} primitive {pi} POSITION"))?;
        let (positions, pl) = data.read_as(pos_a, &self.position_expect(m, pi))?;
        if let Some(k) = positions.iter().position(|v| !v.is_finite()) {
            return Err(GltfError::NonFinitePosition {
                accessor: pos_a,
                element: k / 3,
            });
        }
        let vertices = pl.count;
        // The sequence the mode walks: the indices, or 0..vertices.
        let seq: Vec<u32> = match p.indices {
            Some(ia) => {
                let ia = ia.value();
                data.accessor(ia, &|| format!("mesh {m} primitive {pi} indices"))?;
                let (idx, _) = data.read_as(ia, &self.indices_expect(m, pi))?;
                let mut seq = Vec::with_capacity(idx.len());
                for (slot, &v) in idx.iter().enumerate() {
                    // Index values are integers below 2^32, exact in f64.
                    if v as usize >= vertices {
                        return Err(GltfError::IndexOutOfRange {
                            mesh: m,
                            primitive: pi,
                            accessor: ia,
                            slot,
                            index: v as u64,
                            vertices,
                        });
                    }
                    seq.push(v as u32);
                }
                seq
            }
            None => {
                if vertices > u32::MAX as usize {
                    return Err(bad_prim(m, pi, "too many vertices".to_string()));
                }
                (0..vertices as u32).collect()
            }
        };
        let t = triangles_for(mode, seq.len());
        let mut corners = Vec::with_capacity(3 * t);
        for i in 0..t {
            let tri = match mode {
                Mode::Triangles => [seq[3 * i], seq[3 * i + 1], seq[3 * i + 2]],
                Mode::TriangleStrip => [seq[i], seq[i + 1 + i % 2], seq[i + 2 - i % 2]],
                Mode::TriangleFan => [seq[i + 1], seq[i + 2], seq[0]],
                _ => break,
            };
            corners.extend_from_slice(&tri);
        }
        let mut targets = Vec::new();
        for (ti, target) in p.targets.iter().flatten().enumerate() {
            let Some(ta) = target.positions.map(|a| a.value()) else {
                targets.push(None);
                continue;
            };
            data.accessor(ta, &|| format!("mesh {m} primitive {pi} morph target {ti}"))?;
            let expect = Expect {
                what: format!("POSITION of morph target {ti} of mesh {m} primitive {pi}"),
                types: &[Type::Vec3],
                components: if self.quantized {
                    rules::QUANTIZED_DELTA
                } else {
                    rules::FLOAT
                },
            };
            let (d, l) = data.read_as(ta, &expect)?;
            if l.count != vertices {
                return Err(bad_prim(
                    m,
                    pi,
                    format!(
                        "morph target {ti} has {} positions but the primitive has {vertices}",
                        l.count
                    ),
                ));
            }
            if let Some(k) = d.iter().position(|v| !v.is_finite()) {
                return Err(GltfError::NonFinitePosition {
                    accessor: ta,
                    element: k / 3,
                });
            }
            targets.push(Some(d));
        }
        let mut skin_sets = Vec::new();
        for (sem, a) in &p.attributes {
            let Checked::Valid(Semantic::Joints(set)) = sem else {
                continue;
            };
            let ja = a.value();
            let Some(wa) = attribute(p, Semantic::Weights(*set)) else {
                return Err(bad_prim(
                    m,
                    pi,
                    format!("JOINTS_{set} has no WEIGHTS_{set}"),
                ));
            };
            data.accessor(ja, &|| format!("mesh {m} primitive {pi} JOINTS_{set}"))?;
            data.accessor(wa, &|| format!("mesh {m} primitive {pi} WEIGHTS_{set}"))?;
            let (joints, jl) = data.read_as(
                ja,
                &Expect {
                    what: format!("JOINTS_{set} of mesh {m} primitive {pi}"),
                    types: &[Type::Vec4],
                    components: rules::JOINTS,
                },
            )?;
            let (weights, wl) = data.read_as(
                wa,
                &Expect {
                    what: format!("WEIGHTS_{set} of mesh {m} primitive {pi}"),
                    types: &[Type::Vec4],
                    components: rules::WEIGHTS,
                },
            )?;
            if jl.count != vertices || wl.count != vertices {
                return Err(bad_prim(
                    m,
                    pi,
                    format!(
                        "JOINTS_{set}/WEIGHTS_{set} have {}/{} elements but the primitive has {vertices} vertices",
                        jl.count, wl.count
                    ),
                ));
            }
            if let Some(k) = weights.iter().position(|v| !v.is_finite()) {
                return Err(GltfError::BadAccessor {
                    accessor: wa,
                    reason: format!("weight of vertex {} is not finite", k / 4),
                });
            }
            // Joint numbers are integers below 2^16, exact in u32.
            let joints: Arc<[u32]> = joints.iter().map(|&j| j as u32).collect();
            skin_sets.push(SkinSet { joints, weights });
        }
        for sem in p.attributes.keys() {
            if let Checked::Valid(Semantic::Weights(set)) = sem {
                if attribute(p, Semantic::Joints(*set)).is_none() {
                    return Err(bad_prim(
                        m,
                        pi,
                        format!("WEIGHTS_{set} has no JOINTS_{set}"),
                    ));
                }
            }
        }
        let mut prim = Primitive {
            corners: corners.into(),
            positions,
            targets,
            skin_sets,
            ..Primitive::default()
        };
        let mut shading = PrimShading::default();
        if self.shading {
            self.decode_shading(data, m, pi, vertices, &mut prim, &mut shading)?;
        }
        Ok(Some((Arc::new(prim), Arc::new(shading))))
    }

    /// Reads one optional vertex attribute, checked against its use and the vertex count.
    #[allow(clippy::too_many_arguments)]
    fn attribute_values(
        &self,
        data: &mut Data<'_>,
        m: usize,
        pi: usize,
        vertices: usize,
        a: Option<usize>,
        name: &str,
        types: &'static [Type],
        components: &'static [(json::accessor::ComponentType, Option<bool>)],
    ) -> Result<Values, GltfError> {
        let Some(a) = a else { return Ok(None) };
        data.accessor(a, &|| format!("mesh {m} primitive {pi} {name}"))?;
        let expect = Expect {
            what: format!("{name} of mesh {m} primitive {pi}"),
            types,
            components,
        };
        let (v, l) = data.read_as(a, &expect)?;
        if l.count != vertices {
            return Err(bad_prim(
                m,
                pi,
                format!(
                    "{name} has {} elements but the primitive has {vertices} vertices",
                    l.count
                ),
            ));
        }
        if v.iter().any(|x| !x.is_finite()) {
            return Err(GltfError::BadAccessor {
                accessor: a,
                reason: format!("{name} has a non-finite value"),
            });
        }
        Ok(Some((v, l.ty)))
    }

    /// Normals, tangents (with their morph deltas), texture coordinates, colours and the
    /// material of a primitive.
    fn decode_shading(
        &self,
        data: &mut Data<'_>,
        m: usize,
        pi: usize,
        vertices: usize,
        prim: &mut Primitive,
        shading: &mut PrimShading,
    ) -> Result<(), GltfError> {
        let p = &data.root.meshes[m].primitives[pi];
        let q = self.quantized;
        let normal_rules = if q {
            rules::QUANTIZED_NORMAL
        } else {
            rules::FLOAT
        };
        let uv_rules = if q { rules::QUANTIZED } else { rules::TEXCOORD };
        let attrs = [
            attribute(p, Semantic::Normals),
            attribute(p, Semantic::Tangents),
            attribute(p, Semantic::TexCoords(0)),
            attribute(p, Semantic::TexCoords(1)),
            attribute(p, Semantic::Colors(0)),
        ];
        let targets: Vec<[Option<usize>; 2]> = p
            .targets
            .iter()
            .flatten()
            .map(|t| [t.normals.map(|a| a.value()), t.tangents.map(|a| a.value())])
            .collect();
        shading.material = match p.material.map(|x| x.value()) {
            Some(i) if i >= data.root.materials.len() => {
                return Err(bad_prim(
                    m,
                    pi,
                    format!(
                        "refers to material {i}, but the file has {}",
                        data.root.materials.len()
                    ),
                ))
            }
            material => material,
        };
        let vec3 = &[Type::Vec3];
        let vec4 = &[Type::Vec4];
        let vec2 = &[Type::Vec2];
        let read = |data: &mut Data<'_>, a, name: &str, types, comps| {
            self.attribute_values(data, m, pi, vertices, a, name, types, comps)
        };
        prim.normals = read(data, attrs[0], "NORMAL", vec3, normal_rules)?.map(|v| v.0);
        prim.tangents = read(data, attrs[1], "TANGENT", vec4, normal_rules)?.map(|v| v.0);
        shading.uv0 = read(data, attrs[2], "TEXCOORD_0", vec2, uv_rules)?.map(|v| v.0);
        shading.uv1 = read(data, attrs[3], "TEXCOORD_1", vec2, uv_rules)?.map(|v| v.0);
        shading.colors = read(
            data,
            attrs[4],
            "COLOR_0",
            &[Type::Vec3, Type::Vec4],
            rules::COLOR,
        )?
        .map(|(v, ty)| (v, if ty == Type::Vec3 { 3 } else { 4 }));
        let delta_rules = if q {
            rules::QUANTIZED_DELTA
        } else {
            rules::FLOAT
        };
        for (ti, [na, ta]) in targets.into_iter().enumerate() {
            let n = read(
                data,
                na,
                &format!("NORMAL of morph target {ti}"),
                vec3,
                delta_rules,
            )?;
            let t = read(
                data,
                ta,
                &format!("TANGENT of morph target {ti}"),
                vec3,
                delta_rules,
            )?;
            prim.normal_targets.push(n.map(|v| v.0));
            prim.tangent_targets.push(t.map(|v| v.0));
        }
        Ok(())
    }

    /// Checks that every weighted joint of `prim`'s vertices (in corner order, the order
    /// triangles are placed) exists in skin `s` of `joints` joints.
    pub(super) fn check_joints(
        prim: &Primitive,
        m: usize,
        pi: usize,
        s: usize,
        joints: usize,
    ) -> Result<(), GltfError> {
        for &v in prim.corners.iter() {
            let v = v as usize;
            for set in &prim.skin_sets {
                for k in 0..4 {
                    let j = set.joints[4 * v + k] as usize;
                    if set.weights[4 * v + k] != 0.0 && j >= joints {
                        return Err(SceneError::JointOutOfRange {
                            mesh: m,
                            primitive: pi,
                            vertex: v,
                            joint: j,
                            skin: s,
                            joints,
                        }
                        .into());
                    }
                }
            }
        }
        Ok(())
    }
}

/// Skin `s`'s joints and inverse bind matrices, checked; `nodes` is the node count.
pub(super) fn load_skin(data: &mut Data<'_>, s: usize, nodes: usize) -> Result<Skin, GltfError> {
    let skin = &data.root.skins[s];
    let bad = |reason: String| GltfError::BadSkin { skin: s, reason };
    for (k, j) in skin.joints.iter().enumerate() {
        if j.value() >= nodes {
            return Err(GltfError::DanglingReference {
                from: format!("skin {s} joint {k}"),
                kind: "node",
                index: j.value(),
                count: nodes,
            });
        }
    }
    let ibm = match skin.inverse_bind_matrices {
        // Missing inverse bind matrices are identities (glTF 2.0 §3.7.3.1).
        None => None,
        Some(a) => {
            let a = a.value();
            data.accessor(a, &|| format!("skin {s} inverseBindMatrices"))?;
            let (v, l) = data.read_as(
                a,
                &Expect {
                    what: format!("inverseBindMatrices of skin {s}"),
                    types: &[Type::Mat4],
                    components: rules::FLOAT,
                },
            )?;
            if l.count < skin.joints.len() {
                return Err(bad(format!(
                    "inverseBindMatrices accessor {a} has {} matrices for {} joints",
                    l.count,
                    skin.joints.len()
                )));
            }
            if v.iter().any(|x| !x.is_finite()) {
                return Err(bad(format!(
                    "inverseBindMatrices accessor {a} has a non-finite value"
                )));
            }
            Some(v)
        }
    };
    Ok(Skin {
        joints: skin.joints.iter().map(|j| j.value()).collect(),
        inverse_bind: ibm.map(|v| {
            (0..skin.joints.len())
                .map(|k| DMat4::from_cols_slice(&v[16 * k..16 * k + 16]))
                .collect()
        }),
    })
}
