//! Animations: every channel is checked when the file loads (so whether a file loads does
//! not depend on the time asked for), and evaluated at a time `t` on request.
//!
//! Rules, from the glTF 2.0 specification (§3.11 and Appendix C):
//! - `t` is clamped to each sampler's input range;
//! - STEP holds the value of the last keyframe at or before `t`;
//! - LINEAR interpolates translations, scales and weights linearly, and rotations by slerp
//!   of the normalised keyframe quaternions along the shorter arc;
//! - CUBICSPLINE is the Hermite spline through `(in-tangent, value, out-tangent)` triples,
//!   tangents scaled by the keyframe interval; rotations are normalised afterwards.
//!
//! When several channels (of one or several animations) drive the same node property, the
//! last one in file order (animations in order, then channels in order) wins.

use std::rc::Rc;

use gltf::json;
use gltf::json::accessor::Type;
use gltf::json::animation::{Interpolation, Property};
use gltf::json::validation::Checked;

use super::accessor::{rules, Data, Expect};
use super::math;
use super::GltfError;
use crate::scene::AnimationInfo;

/// The node property a channel drives.
#[derive(Clone, Copy, Debug, PartialEq)]
enum Path {
    Translation,
    Rotation,
    Scale,
    Weights,
}

/// One checked channel with its sampler's data.
struct Channel {
    animation: usize,
    channel: usize,
    node: usize,
    path: Path,
    interpolation: Interpolation,
    input: Rc<[f64]>,
    output: Rc<[f64]>,
    /// Values per keyframe element: 3, 4, or the number of morph weights.
    width: usize,
}

/// A node's animated local state at one time; `None` keeps the stored value.
#[derive(Clone, Debug, Default)]
pub(super) struct NodePose {
    pub translation: Option<[f64; 3]>,
    pub rotation: Option<[f64; 4]>,
    pub scale: Option<[f64; 3]>,
    pub weights: Option<Vec<f64>>,
}

/// The file's animations, checked.
pub(super) struct Animations {
    pub infos: Vec<AnimationInfo>,
    channels: Vec<Channel>,
}

fn bad(animation: usize, reason: String) -> GltfError {
    GltfError::BadAnimation { animation, reason }
}

/// Checks every animation and reads its keyframes.
pub(super) fn load(data: &mut Data<'_>, quantized: bool) -> Result<Animations, GltfError> {
    let root: &json::Root = data.root;
    let mut infos = Vec::with_capacity(root.animations.len());
    let mut channels = Vec::new();
    for (ai, anim) in root.animations.iter().enumerate() {
        let mut inputs = Vec::with_capacity(anim.samplers.len());
        let mut duration = 0.0f64;
        for (si, sampler) in anim.samplers.iter().enumerate() {
            let a = sampler.input.value();
            data.accessor(a, &|| format!("animation {ai} sampler {si} input"))?;
            let expect = Expect {
                what: format!("input of animation {ai} sampler {si}"),
                types: &[Type::Scalar],
                components: rules::FLOAT,
            };
            let (input, _) = data.read_as(a, &expect)?;
            if input.is_empty() {
                return Err(bad(
                    ai,
                    format!("sampler {si} has no keyframes (accessor {a})"),
                ));
            }
            for (k, w) in input.windows(2).enumerate() {
                if w[1] < w[0] {
                    return Err(bad(
                        ai,
                        format!(
                            "sampler {si}: keyframe times decrease at keyframe {} ({} after {}) in accessor {a}",
                            k + 1,
                            w[1],
                            w[0]
                        ),
                    ));
                }
            }
            if let Some(k) = input.iter().position(|v| !v.is_finite()) {
                return Err(bad(
                    ai,
                    format!("sampler {si}: keyframe time {k} in accessor {a} is not finite"),
                ));
            }
            duration = duration.max(input[input.len() - 1]);
            inputs.push(input);
        }
        infos.push(AnimationInfo {
            name: anim.name.clone().unwrap_or_default(),
            duration,
        });
        for (ci, ch) in anim.channels.iter().enumerate() {
            let si = ch.sampler.value();
            let Some(sampler) = anim.samplers.get(si) else {
                return Err(GltfError::DanglingReference {
                    from: format!("animation {ai} channel {ci}"),
                    kind: "sampler",
                    index: si,
                    count: anim.samplers.len(),
                });
            };
            let node = ch.target.node.value();
            if node >= root.nodes.len() {
                return Err(GltfError::DanglingReference {
                    from: format!("animation {ai} channel {ci}"),
                    kind: "node",
                    index: node,
                    count: root.nodes.len(),
                });
            }
            // An unknown path (an extension's) drives nothing rayd traces.
            let Checked::Valid(path) = ch.target.path else {
                continue;
            };
            let Checked::Valid(interpolation) = sampler.interpolation else {
                return Err(bad(
                    ai,
                    format!("sampler {si} has an invalid interpolation"),
                ));
            };
            let (path, ty, components) = match path {
                Property::Translation => (
                    Path::Translation,
                    Type::Vec3,
                    if quantized {
                        rules::QUANTIZED
                    } else {
                        rules::FLOAT
                    },
                ),
                Property::Scale => (
                    Path::Scale,
                    Type::Vec3,
                    if quantized {
                        rules::QUANTIZED
                    } else {
                        rules::FLOAT
                    },
                ),
                Property::Rotation => (Path::Rotation, Type::Vec4, rules::NORMALIZED_OR_FLOAT),
                Property::MorphTargetWeights => {
                    (Path::Weights, Type::Scalar, rules::NORMALIZED_OR_FLOAT)
                }
            };
            let a = sampler.output.value();
            data.accessor(a, &|| format!("animation {ai} sampler {si} output"))?;
            let expect = Expect {
                what: format!("output of animation {ai} sampler {si} ({path:?})"),
                types: match ty {
                    Type::Vec3 => &[Type::Vec3],
                    Type::Vec4 => &[Type::Vec4],
                    _ => &[Type::Scalar],
                },
                components,
            };
            let (output, layout) = data.read_as(a, &expect)?;
            let input = inputs[si].clone();
            let per_key = if interpolation == Interpolation::CubicSpline {
                3
            } else {
                1
            };
            let elements = input.len() * per_key;
            let width = match path {
                Path::Weights => {
                    if layout.count == 0 || layout.count % elements != 0 {
                        return Err(bad(
                            ai,
                            format!(
                                "channel {ci}: weights output accessor {a} has {} values, not a multiple of {elements} keyframe elements",
                                layout.count
                            ),
                        ));
                    }
                    layout.count / elements
                }
                _ => {
                    if layout.count != elements {
                        return Err(bad(
                            ai,
                            format!(
                                "channel {ci}: output accessor {a} has {} elements, expected {elements} for {} keyframes",
                                layout.count,
                                input.len()
                            ),
                        ));
                    }
                    ty.multiplicity()
                }
            };
            if let Some(k) = output.iter().position(|v| !v.is_finite()) {
                return Err(bad(
                    ai,
                    format!("channel {ci}: output accessor {a} value {k} is not finite"),
                ));
            }
            channels.push(Channel {
                animation: ai,
                channel: ci,
                node,
                path,
                interpolation,
                input,
                output,
                width,
            });
        }
    }
    Ok(Animations { infos, channels })
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

    fn unit_quat(&self, k: usize) -> Result<[f64; 4], GltfError> {
        let v = self.value(k);
        math::normalize_quat([v[0], v[1], v[2], v[3]]).ok_or_else(|| {
            bad(
                self.animation,
                format!(
                    "channel {}: rotation keyframe {k} is a zero quaternion",
                    self.channel
                ),
            )
        })
    }

    /// The channel's value at `t`.
    fn sample(&self, t: f64) -> Result<Vec<f64>, GltfError> {
        let n = self.input.len();
        let t = t.max(self.input[0]).min(self.input[n - 1]);
        // The last keyframe at or before t; times are non-decreasing, so the next keyframe
        // (if any) is strictly after t and the interval below is positive.
        let k = self.input.partition_point(|&x| x <= t).saturating_sub(1);
        let rotation = self.path == Path::Rotation;
        let hold = || -> Result<Vec<f64>, GltfError> {
            Ok(if rotation {
                self.unit_quat(k)?.to_vec()
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
                Ok(math::slerp(self.unit_quat(k)?, self.unit_quat(k + 1)?, s).to_vec())
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
                    let q = math::normalize_quat([v[0], v[1], v[2], v[3]]).ok_or_else(|| {
                        bad(
                            self.animation,
                            format!(
                                "channel {}: the rotation spline passes through zero at t = {t}",
                                self.channel
                            ),
                        )
                    })?;
                    Ok(q.to_vec())
                } else {
                    Ok(v)
                }
            }
        }
    }
}

impl Animations {
    /// Every node's animated local state at time `t` (seconds), all animations applied.
    pub(super) fn evaluate(&self, t: f64, nodes: usize) -> Result<Vec<NodePose>, GltfError> {
        let mut poses = vec![NodePose::default(); nodes];
        for ch in &self.channels {
            let v = ch.sample(t)?;
            let pose = &mut poses[ch.node];
            match ch.path {
                Path::Translation => pose.translation = Some([v[0], v[1], v[2]]),
                Path::Scale => pose.scale = Some([v[0], v[1], v[2]]),
                Path::Rotation => pose.rotation = Some([v[0], v[1], v[2], v[3]]),
                Path::Weights => pose.weights = Some(v),
            }
        }
        Ok(poses)
    }
}
