//! Animations: every channel is checked when the file loads (so whether a file loads does
//! not depend on the time asked for) and becomes a format-free [`Channel`]; sampling at a
//! time is the scene's ([`crate::scene::rig`] has the rules).

use gltf::json;
use gltf::json::accessor::Type;
use gltf::json::animation::{Interpolation, Property};
use gltf::json::validation::Checked;

use super::accessor::{rules, Data, Expect};
use super::GltfError;
use crate::scene::rig::{self, Channel, Target as Path};
use crate::scene::{AnimationInfo, SceneError};

/// The file's animations, checked.
pub(super) struct Animations {
    pub infos: Vec<AnimationInfo>,
    pub channels: Vec<Channel>,
}

fn bad(animation: usize, reason: String) -> GltfError {
    SceneError::BadAnimation { animation, reason }.into()
}

/// Checks every animation and reads its keyframes.
/// `morph_targets`: each mesh's number of morph targets, which a weights channel of a
/// node that instances the mesh must give a value each per keyframe.
pub(super) fn load(
    data: &mut Data<'_>,
    quantized: bool,
    morph_targets: &[usize],
) -> Result<Animations, GltfError> {
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
            // An unknown path (an extension's, or a channel without a node: see
            // `container::optional_fields_filled`) drives nothing rayd traces.
            let Checked::Valid(path) = ch.target.path else {
                continue;
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
                    let mesh = root.nodes[node].mesh.map(|m| m.value());
                    if let Some(m) = mesh {
                        let targets = morph_targets.get(m).copied().unwrap_or(0);
                        if layout.count != elements * targets {
                            return Err(bad(
                                ai,
                                format!(
                                    "channel {ci}: weights output accessor {a} has {} values, expected {} ({targets} morph targets of node {node}'s mesh {m} × {elements} keyframe elements)",
                                    layout.count,
                                    elements * targets
                                ),
                            ));
                        }
                    }
                    // A node without a mesh: the channel drives nothing, but its values
                    // must still be whole keyframes.
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
            let channel = Channel {
                animation: ai,
                channel: ci,
                node,
                target: path,
                interpolation: match interpolation {
                    Interpolation::Step => rig::Interpolation::Step,
                    Interpolation::Linear => rig::Interpolation::Linear,
                    Interpolation::CubicSpline => rig::Interpolation::CubicSpline,
                },
                input,
                output,
                width,
            };
            // The specification asks for unit quaternions; any non-zero one is normalised.
            if let Some(k) = channel.zero_rotation() {
                return Err(bad(
                    ai,
                    format!(
                        "channel {ci}: rotation keyframe {k} (output accessor {a}) has no length"
                    ),
                ));
            }
            channels.push(channel);
        }
    }
    Ok(Animations { infos, channels })
}
