//! Primitives to world-space triangles: triangulation of every mode, morph targets and
//! skinning, all in f64, rounded to f32 once.

use std::collections::HashMap;
use std::rc::Rc;

use gltf::json;
use gltf::json::accessor::Type;
use gltf::json::mesh::{Mode, Semantic};
use gltf::json::validation::Checked;

use super::accessor::{rules, Data, Expect};
use super::math::{self, Mat4};
use super::GltfError;
use crate::geometry::Triangle;

/// A primitive decoded once and shared by every node that instances its mesh.
struct Prim {
    /// Vertex indices, three per triangle, in id order; all `< vertices`.
    corners: Vec<u32>,
    /// POSITION, 3 per vertex.
    positions: Rc<[f64]>,
    /// Per morph target, its POSITION deltas (3 per vertex) if it has any.
    targets: Vec<Option<Rc<[f64]>>>,
    /// `JOINTS_n`/`WEIGHTS_n` sets.
    skin_sets: Vec<SkinSet>,
}

/// One `JOINTS_n`/`WEIGHTS_n` pair, 4 values per vertex each.
struct SkinSet {
    joints: Rc<[f64]>,
    weights: Rc<[f64]>,
}

/// One node's use of a mesh.
pub(super) struct Instance<'s> {
    /// The node.
    pub node: usize,
    /// Its mesh.
    pub mesh: usize,
    /// The node's world transform.
    pub world: &'s Mat4,
    /// Its morph weights (missing ones are 0).
    pub weights: &'s [f64],
    /// For a skinned node, its skin and `jointWorld_j · inverseBind_j` per joint, which
    /// replace `world` for primitives that have joint sets (glTF: the skinned mesh node's
    /// own transform is ignored).
    pub joints: Option<(usize, &'s [Mat4])>,
}

/// Turns mesh instances into triangles, caching decoded primitives and skin matrices.
pub(super) struct Meshes {
    quantized: bool,
    prims: HashMap<(usize, usize), Rc<Prim>>,
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
    pub(super) fn new(quantized: bool) -> Meshes {
        Meshes {
            quantized,
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
    fn prim(
        &mut self,
        data: &mut Data<'_>,
        m: usize,
        pi: usize,
    ) -> Result<Option<Rc<Prim>>, GltfError> {
        if let Some(p) = self.prims.get(&(m, pi)) {
            return Ok(Some(p.clone()));
        }
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
        let prim = Rc::new(Prim {
            corners,
            positions,
            targets,
            skin_sets,
        });
        self.prims.insert((m, pi), prim.clone());
        Ok(Some(prim))
    }

    /// Appends the triangles of one mesh instance.
    pub(super) fn emit(
        &mut self,
        data: &mut Data<'_>,
        out: &mut Vec<Triangle>,
        instance: &Instance<'_>,
    ) -> Result<(), GltfError> {
        let &Instance {
            node,
            mesh: m,
            world,
            weights,
            joints,
        } = instance;
        for pi in 0..data.root.meshes[m].primitives.len() {
            let Some(prim) = self.prim(data, m, pi)? else {
                continue;
            };
            // Targets with a zero weight or without positions change nothing.
            let morphs: Vec<(f64, &[f64])> = prim
                .targets
                .iter()
                .zip(weights)
                .filter_map(|(d, &w)| d.as_deref().filter(|_| w != 0.0).map(|d| (w, d)))
                .collect();
            let skin = joints.filter(|_| !prim.skin_sets.is_empty());
            let position = |v: usize| -> Result<[f32; 3], GltfError> {
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
                let q = match skin {
                    None => math::transform_point(world, p),
                    Some((skin_index, mats)) => {
                        let mut s = [[0.0; 4]; 4];
                        for SkinSet {
                            joints: js,
                            weights: ws,
                        } in &prim.skin_sets
                        {
                            for k in 0..4 {
                                let w = ws[4 * v + k];
                                if w == 0.0 {
                                    continue;
                                }
                                let j = js[4 * v + k] as usize;
                                let Some(mat) = mats.get(j) else {
                                    return Err(GltfError::JointOutOfRange {
                                        mesh: m,
                                        primitive: pi,
                                        vertex: v,
                                        joint: j,
                                        skin: skin_index,
                                        joints: mats.len(),
                                    });
                                };
                                math::add_scaled(&mut s, w, mat);
                            }
                        }
                        math::transform_point(&s, p)
                    }
                };
                let f = q.map(|x| x as f32);
                if f.iter().any(|x| !x.is_finite()) {
                    return Err(GltfError::NonFiniteWorldPosition {
                        node,
                        mesh: m,
                        primitive: pi,
                        vertex: v,
                    });
                }
                Ok(f)
            };
            for c in prim.corners.chunks_exact(3) {
                out.push(Triangle {
                    v: [
                        position(c[0] as usize)?,
                        position(c[1] as usize)?,
                        position(c[2] as usize)?,
                    ],
                });
            }
        }
        Ok(())
    }
}

/// `jointWorld_j · inverseBind_j` for every joint of skin `s`.
pub(super) fn skin_matrices(
    data: &mut Data<'_>,
    s: usize,
    world: &[Mat4],
) -> Result<Vec<Mat4>, GltfError> {
    let skin = &data.root.skins[s];
    let bad = |reason: String| GltfError::BadSkin { skin: s, reason };
    for (k, j) in skin.joints.iter().enumerate() {
        if j.value() >= world.len() {
            return Err(GltfError::DanglingReference {
                from: format!("skin {s} joint {k}"),
                kind: "node",
                index: j.value(),
                count: world.len(),
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
    Ok(skin
        .joints
        .iter()
        .enumerate()
        .map(|(k, j)| {
            let jw = &world[j.value()];
            match &ibm {
                Some(v) => math::mul(jw, &math::from_cols(&v[16 * k..16 * k + 16])),
                None => *jw,
            }
        })
        .collect())
}
