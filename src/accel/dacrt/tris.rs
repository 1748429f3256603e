//! The per-frame triangle precompute (Áfra 2012 §3.2–3.3): one 32-byte AABB per triangle in a
//! SIMD-friendly layout, plus 16 bytes of complementary data from which the triangle is
//! rebuilt exactly. 48 bytes per triangle in all, against 36 for the raw vertices and 32 for
//! the boxes alone: the partitioning passes, which dominate triangle traffic, read only the
//! boxes, and a leaf rebuilds its few triangles once for many rays.
//!
//! Reconstruction: on each axis the box already holds the smallest and the largest of the
//! three vertex coordinates; the complementary record holds the third ("middle") coordinate
//! and, in a 12-bit order code, which vertex holds the minimum and which the maximum. The
//! rebuilt vertices are bit-identical to the input, so the leaf tests compute exactly what
//! `brute` computes on the original triangles.

use rayon::prelude::*;

use crate::geometry::{Aabb, Triangle};

/// A triangle's bounding box, each corner padded to 16 bytes so that it loads as one 4-wide
/// vector (Áfra 2012 §3.2). 32 bytes, 32-byte aligned: one box never straddles a cache line.
#[repr(C, align(32))]
#[derive(Clone, Copy, Debug, PartialEq, Default)]
pub struct TriBox {
    /// Smallest vertex coordinate per axis; lane 3 is 0.
    pub min: [f32; 4],
    /// Largest vertex coordinate per axis; lane 3 is 0.
    pub max: [f32; 4],
}

const _: () = assert!(std::mem::size_of::<TriBox>() == 32);

impl TriBox {
    /// The centroid of the box on `axis`, computed as `0.5·min + 0.5·max` so that it
    /// cannot overflow for coordinates near `f32::MAX`. Every pass uses this one formula, so
    /// a triangle is always classified the same way.
    #[inline(always)]
    pub fn centroid(&self, axis: usize) -> f32 {
        0.5 * self.min[axis] + 0.5 * self.max[axis]
    }
}

/// What the box does not say about a triangle: the middle coordinate per axis and the order
/// code (bits `4k..4k+2`: the vertex holding the minimum on axis `k`; bits `4k+2..4k+4`: the
/// vertex holding the maximum; the remaining vertex holds `mid[k]`). 16 bytes.
#[repr(C, align(16))]
#[derive(Clone, Copy, Debug, PartialEq, Default)]
pub struct TriExtra {
    /// The coordinate per axis that is neither the box's minimum nor its maximum.
    pub mid: [f32; 3],
    /// Which vertex holds the minimum and which the maximum, per axis.
    pub code: u32,
}

const _: () = assert!(std::mem::size_of::<TriExtra>() == 16);

/// Splits one triangle into its box and complementary record.
pub fn encode(tri: &Triangle) -> (TriBox, TriExtra) {
    let mut b = TriBox::default();
    let mut e = TriExtra::default();
    for k in 0..3 {
        let c = [tri.v[0][k], tri.v[1][k], tri.v[2][k]];
        // The vertex with the smallest coordinate (lowest index on ties), then the largest
        // among the other two, so that the two are always distinct vertices.
        let lo = if c[1] < c[0] && c[1] <= c[2] {
            1
        } else if c[2] < c[0] && c[2] < c[1] {
            2
        } else {
            0
        };
        let (a, bb) = match lo {
            0 => (1, 2),
            1 => (0, 2),
            _ => (0, 1),
        };
        let hi = if c[bb] > c[a] { bb } else { a };
        let mid = 3 - lo - hi;
        b.min[k] = c[lo];
        b.max[k] = c[hi];
        e.mid[k] = c[mid];
        e.code |= ((lo as u32) | (hi as u32) << 2) << (4 * k);
    }
    (b, e)
}

/// Rebuilds the triangle from its box and complementary record (bit-exact).
#[inline(always)]
pub fn decode(b: &TriBox, e: &TriExtra) -> [[f32; 3]; 3] {
    let mut v = [[0.0f32; 3]; 3];
    for k in 0..3 {
        let lo = (e.code >> (4 * k)) & 3;
        let hi = (e.code >> (4 * k + 2)) & 3;
        for (i, vert) in v.iter_mut().enumerate() {
            let i = i as u32;
            vert[k] = if i == lo {
                b.min[k]
            } else if i == hi {
                b.max[k]
            } else {
                e.mid[k]
            };
        }
    }
    v
}

/// The whole frame's precompute: boxes, complementary data, which triangles can be hit, and
/// the root node's boxes.
pub struct TriData {
    /// One box per triangle, indexed by triangle id.
    pub boxes: Vec<TriBox>,
    /// One complementary record per triangle, indexed by triangle id.
    pub extra: Vec<TriExtra>,
    /// Ids of the degenerate triangles (contract: never hit), ascending; usually empty, so
    /// the id array of a trace is the identity with these left out.
    pub degenerate: Vec<u32>,
    /// Bounds of the non-degenerate triangles.
    pub bounds: Aabb,
    /// Bounds of their box centroids.
    pub centroids: Aabb,
}

impl TriData {
    /// Precomputes `tris` on the current rayon pool.
    pub fn new(tris: &[Triangle]) -> TriData {
        const CHUNK: usize = 4096;
        let mut boxes = vec![TriBox::default(); tris.len()];
        let mut extra = vec![TriExtra::default(); tris.len()];
        let parts: Vec<(Aabb, Aabb, Vec<u32>)> = boxes
            .par_chunks_mut(CHUNK)
            .zip(extra.par_chunks_mut(CHUNK))
            .zip(tris.par_chunks(CHUNK))
            .enumerate()
            .map(|(c, ((bs, es), ts))| {
                let mut bounds = Aabb::EMPTY;
                let mut cents = Aabb::EMPTY;
                let mut degenerate = Vec::new();
                for (i, ((b, e), t)) in bs.iter_mut().zip(es.iter_mut()).zip(ts).enumerate() {
                    (*b, *e) = encode(t);
                    if t.is_degenerate() {
                        degenerate.push((c * CHUNK + i) as u32);
                        continue;
                    }
                    bounds.grow([b.min[0], b.min[1], b.min[2]]);
                    bounds.grow([b.max[0], b.max[1], b.max[2]]);
                    cents.grow([b.centroid(0), b.centroid(1), b.centroid(2)]);
                }
                (bounds, cents, degenerate)
            })
            .collect();
        let mut bounds = Aabb::EMPTY;
        let mut centroids = Aabb::EMPTY;
        let mut degenerate = Vec::new();
        for (b, c, d) in parts {
            bounds.union(&b);
            centroids.union(&c);
            degenerate.extend(d);
        }
        TriData {
            boxes,
            extra,
            degenerate,
            bounds,
            centroids,
        }
    }

    /// Number of triangles that can be hit.
    pub fn live(&self) -> usize {
        self.boxes.len() - self.degenerate.len()
    }

    /// Fills `ids` (length [`TriData::live`]) with the ids of the triangles that can be hit,
    /// ascending: the id array a trace partitions in place.
    pub fn fill_ids(&self, ids: &mut [u32]) {
        debug_assert_eq!(ids.len(), self.live());
        if self.degenerate.is_empty() {
            ids.par_chunks_mut(1 << 16)
                .enumerate()
                .for_each(|(c, chunk)| {
                    let base = (c << 16) as u32;
                    for (i, id) in chunk.iter_mut().enumerate() {
                        *id = base + i as u32;
                    }
                });
            return;
        }
        let mut skip = self.degenerate.iter().peekable();
        let mut out = ids.iter_mut();
        for id in 0..self.boxes.len() as u32 {
            if skip.peek() == Some(&&id) {
                skip.next();
                continue;
            }
            if let Some(slot) = out.next() {
                *slot = id;
            }
        }
    }

    /// Bytes held.
    pub fn bytes(&self) -> usize {
        self.boxes.capacity() * std::mem::size_of::<TriBox>()
            + self.extra.capacity() * std::mem::size_of::<TriExtra>()
            + self.degenerate.capacity() * 4
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn decode_is_exact_for_every_order_and_tie() {
        let vals = [-1.5f32, 0.0, -0.0, 2.25, 2.25];
        for &a in &vals {
            for &b in &vals {
                for &c in &vals {
                    let tri = Triangle {
                        v: [[a, b, c], [b, c, a], [c, a, 7.0]],
                    };
                    let (bx, ex) = encode(&tri);
                    let back = decode(&bx, &ex);
                    assert_eq!(
                        back.map(|p| p.map(f32::to_bits)),
                        tri.v.map(|p| p.map(f32::to_bits)),
                        "{tri:?}"
                    );
                    assert!((0..3).all(|k| bx.min[k] <= bx.max[k]));
                }
            }
        }
    }

    #[test]
    fn root_boxes_leave_out_degenerate_triangles() {
        let tris = vec![
            Triangle {
                v: [[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]],
            },
            Triangle {
                v: [[5.0, 5.0, 5.0], [6.0, 6.0, 6.0], [7.0, 7.0, 7.0]],
            },
        ];
        let d = TriData::new(&tris);
        assert_eq!(d.degenerate, vec![1]);
        assert_eq!(d.bounds.max, [1.0, 1.0, 0.0]);
        let mut ids = vec![0; d.live()];
        d.fill_ids(&mut ids);
        assert_eq!(ids, vec![0]);
    }
}
