//! Spatial splits (Stich, Friedrich & Dietrich 2009, "Spatial splits in bounding volume
//! hierarchies"): references are chopped at bin planes so that a node's children need not
//! overlap; a reference that straddles the chosen plane is either duplicated (one clipped
//! piece per side) or, when that is cheaper, left whole on one side (reference
//! unsplitting).
//!
//! Clipping is conservative: the points where triangle edges cross a plane are computed in
//! f64 and rounded outwards to f32, so a clipped box always contains the part of the
//! triangle it stands for and no ray can slip between the two pieces of a split triangle.

use rayon::prelude::*;

use super::binning::{halves, partition, sweep, BinMap, Centroids, SahPlan, SweepBest};
use super::build::{grow, half_area, intersect, union, CostModel, Range, Ref, B4};
use crate::geometry::{Aabb, Triangle};

/// Spatial bins per axis. 16, not 32: chopping a reference costs per bin it spans; with
/// 32 the whole SBVH build took about 40% longer for a SAH cost only 0.6% lower (dragon,
/// MBVH8).
pub(crate) const SPATIAL_BINS: usize = 16;

/// Ranges with at least this many references are spatially binned in parallel.
const PAR_SPATIAL: usize = 1 << 12;

/// The next f32 towards +inf.
fn next_up(x: f32) -> f32 {
    if x.is_nan() || x == f32::INFINITY {
        return x;
    }
    if x == 0.0 {
        return f32::from_bits(1);
    }
    let b = x.to_bits();
    f32::from_bits(if x > 0.0 { b + 1 } else { b - 1 })
}

/// The next f32 towards -inf.
fn next_down(x: f32) -> f32 {
    -next_up(-x)
}

/// Splits triangle `tri`, restricted to `clip`, at `x[axis] = plane`: boxes of the parts
/// on either side (either may be [`Aabb::EMPTY`]). Both are conservative.
pub(crate) fn split_triangle(tri: &Triangle, axis: usize, plane: f32, clip: &Aabb) -> (Aabb, Aabb) {
    let mut l = Aabb::EMPTY;
    let mut r = Aabb::EMPTY;
    for i in 0..3 {
        let p = tri.v[i];
        let q = tri.v[(i + 1) % 3];
        let (pa, qa) = (p[axis], q[axis]);
        if pa <= plane {
            grow(&mut l, &p, &p);
        }
        if pa >= plane {
            grow(&mut r, &p, &p);
        }
        if (pa < plane && qa > plane) || (pa > plane && qa < plane) {
            let t = (plane as f64 - pa as f64) / (qa as f64 - pa as f64);
            let mut lo = [plane; 3];
            let mut hi = [plane; 3];
            for j in 0..3 {
                if j != axis {
                    let x = (p[j] as f64 + t * (q[j] as f64 - p[j] as f64)) as f32;
                    lo[j] = next_down(x);
                    hi[j] = next_up(x);
                }
            }
            grow(&mut l, &lo, &hi);
            grow(&mut r, &lo, &hi);
        }
    }
    (intersect(&l, clip), intersect(&r, clip))
}

/// Spatial bins: per-bin boxes of the chopped references, and how many references start
/// (`enter`) and end (`exit`) in each bin.
#[derive(Clone)]
struct SpatialBins {
    boxes: [[B4; SPATIAL_BINS]; 3],
    enter: [[u32; SPATIAL_BINS]; 3],
    exit: [[u32; SPATIAL_BINS]; 3],
}

impl SpatialBins {
    fn new() -> Self {
        SpatialBins {
            boxes: [[B4::EMPTY; SPATIAL_BINS]; 3],
            enter: [[0; SPATIAL_BINS]; 3],
            exit: [[0; SPATIAL_BINS]; 3],
        }
    }

    fn merge(mut self, o: Self) -> Self {
        for a in 0..3 {
            for i in 0..SPATIAL_BINS {
                self.boxes[a][i].grow(&o.boxes[a][i]);
                self.enter[a][i] += o.enter[a][i];
                self.exit[a][i] += o.exit[a][i];
            }
        }
        self
    }

    /// Spatial binning: each reference is chopped at the bin planes it crosses. The piece
    /// in a bin is the box of the triangle's part inside that bin's slab — its vertices
    /// there and the cross-sections at the slab's two planes — cut to the reference's box.
    /// With the vertices sorted along the axis, the cross-section at a plane is the
    /// segment between the long edge and one of the two short edges, so each plane costs
    /// two interpolations, shared by the slabs on either side. This only estimates costs,
    /// so it runs in plain f32; the split finally made clips conservatively
    /// ([`split_triangle`]).
    fn add(&mut self, tris: &[Triangle], refs: &[Ref], map: &BinMap) {
        for r in refs {
            let rb = r.b4();
            let tri = &tris[r.id() as usize];
            let tv = tri.v.map(|p| [p[0], p[1], p[2], 0.0]);
            for a in 0..3 {
                if map.scale[a] == 0.0 {
                    continue;
                }
                let k0 = map.bin(r.lo[a], a);
                let k1 = map.bin(r.hi[a], a);
                self.enter[a][k0] += 1;
                self.exit[a][k1] += 1;
                if k0 == k1 {
                    self.boxes[a][k0].grow(&rb);
                    continue;
                }
                // Vertices sorted along the axis: lo, mid, hi.
                let mut v = [&tv[0], &tv[1], &tv[2]];
                if v[0][a] > v[1][a] {
                    v.swap(0, 1);
                }
                if v[1][a] > v[2][a] {
                    v.swap(1, 2);
                }
                if v[0][a] > v[1][a] {
                    v.swap(0, 1);
                }
                let kv = v.map(|p| map.bin(p[a], a).clamp(k0, k1));
                // (The interpolated point's own coordinate is only about `x`; good enough
                // for an estimate, and a write to a variable lane would stall the loop.)
                let lerp = |p: &[f32; 4], q: &[f32; 4], x: f32| -> [f32; 4] {
                    let d = q[a] - p[a];
                    let t = if d > 0.0 {
                        ((x - p[a]) / d).clamp(0.0, 1.0)
                    } else {
                        0.0
                    };
                    std::array::from_fn(|k| p[k] + t * (q[k] - p[k]))
                };
                // `cur` collects the piece of slab k, starting from the cross-section
                // at its left plane.
                let mut cur = B4::EMPTY;
                for k in k0..=k1 {
                    for (p, &kp) in v.iter().zip(&kv) {
                        if kp == k {
                            cur.grow(&B4::point(**p));
                        }
                    }
                    let mut seg = B4::EMPTY;
                    if k < k1 {
                        let x = map.plane(a, k + 1);
                        let f = if x < v[1][a] {
                            lerp(v[0], v[1], x)
                        } else {
                            lerp(v[1], v[2], x)
                        };
                        seg = B4::point(lerp(v[0], v[2], x));
                        seg.grow(&B4::point(f));
                        cur.grow(&seg);
                    }
                    if let Some(piece) = cur.intersect(&rb) {
                        self.boxes[a][k].grow(&piece);
                    }
                    cur = seg;
                }
            }
        }
    }
}

/// The best spatial split of range `r` (references `refs`), if one fits in `room` slots.
pub(crate) fn spatial_plan(
    tris: &[Triangle],
    refs: &[Ref],
    r: &Range<Centroids>,
    cost: &CostModel,
    inv_area: f64,
    room: u32,
) -> Option<(SahPlan, f64)> {
    let map = BinMap::new(&r.bounds, SPATIAL_BINS, 1.0);
    let bins = if refs.len() < PAR_SPATIAL {
        let mut b = SpatialBins::new();
        b.add(tris, refs, &map);
        b
    } else {
        refs.par_chunks(PAR_SPATIAL / 4)
            .fold(SpatialBins::new, |mut b, c| {
                b.add(tris, c, &map);
                b
            })
            .reduce(SpatialBins::new, SpatialBins::merge)
    };
    let mut best: Option<(usize, SweepBest)> = None;
    for a in 0..3 {
        if map.scale[a] == 0.0 {
            continue;
        }
        if let Some(s) = sweep(
            &bins.boxes[a],
            &bins.enter[a],
            &bins.exit[a],
            &r.bounds,
            inv_area,
            cost,
        ) {
            if s.nl + s.nr <= room && best.is_none_or(|(_, o)| s.s < o.s) {
                best = Some((a, s));
            }
        }
    }
    let (a, s) = best?;
    let (lbox, rbox) = halves(&bins.boxes[a], s.bin);
    Some((
        SahPlan::Spatial {
            axis: a as u8,
            bin: s.bin as u8,
            map,
            lbox,
            rbox,
            nl: s.nl,
            nr: s.nr,
        },
        s.s,
    ))
}

/// Carries out a spatial split of the `n` references at the front of `refs`: references
/// left of the plane go left, right of it go right, straddlers are unsplit (whole, to one
/// side) when Stich et al.'s cost test says so, else clipped, with their right pieces
/// appended after the `n` references. Returns (left, right) counts; the left references
/// end up at `..left`, the right ones at `left..left + right`.
#[allow(clippy::too_many_arguments)]
pub(crate) fn apply_spatial(
    tris: &[Triangle],
    refs: &mut [Ref],
    n: usize,
    axis: usize,
    bin: usize,
    map: &BinMap,
    (mut lbox, mut rbox): (Aabb, Aabb),
    (nl, nr): (u32, u32),
) -> (usize, usize) {
    const LEFT: u32 = 0;
    const RIGHT: u32 = 1;
    let plane = map.plane(axis, bin);
    let (mut nl, mut nr) = (nl as f64, nr as f64);
    let mut extra = 0;
    for i in 0..n {
        let r = refs[i];
        let k0 = map.bin(r.lo[axis], axis);
        let k1 = map.bin(r.hi[axis], axis);
        if k1 < bin {
            refs[i].set_aux(LEFT);
            continue;
        }
        if k0 >= bin {
            refs[i].set_aux(RIGHT);
            continue;
        }
        // Reference unsplitting (linear counts: the ⌈T/N⌉ steps would hide the gain).
        let b = r.aabb();
        let lb = union(&lbox, &b);
        let rb = union(&rbox, &b);
        let c_split = half_area(&lbox) * nl + half_area(&rbox) * nr;
        let c_left = half_area(&lb) * nl + half_area(&rbox) * (nr - 1.0);
        let c_right = half_area(&lbox) * (nl - 1.0) + half_area(&rb) * nr;
        if c_left < c_split && c_left <= c_right {
            refs[i].set_aux(LEFT);
            lbox = lb;
            nr -= 1.0;
            continue;
        }
        if c_right < c_split {
            refs[i].set_aux(RIGHT);
            rbox = rb;
            nl -= 1.0;
            continue;
        }
        let id = r.id();
        let (left, right) = split_triangle(&tris[id as usize], axis, plane, &b);
        let with = |b: &Aabb, side: u32| {
            let mut x = Ref::new(id, b);
            x.set_aux(side);
            x
        };
        if left.is_empty() {
            refs[i] = with(&right, RIGHT);
        } else if right.is_empty() {
            refs[i] = with(&left, LEFT);
        } else {
            refs[i] = with(&left, LEFT);
            refs[n + extra] = with(&right, RIGHT);
            extra += 1;
        }
    }
    let left = partition(&mut refs[..n], |x| x.aux() == LEFT);
    (left, n - left + extra)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn ulp_steps() {
        assert!(next_up(1.0) > 1.0);
        assert!(next_down(1.0) < 1.0);
        assert!(next_up(-1.0) > -1.0);
        assert!(next_down(0.0) < 0.0);
        assert_eq!(next_up(f32::MAX), f32::INFINITY);
    }

    #[test]
    fn split_pieces_cover_the_triangle() {
        let t = Triangle {
            v: [[0.0, 0.0, 0.0], [3.0, 1.0, 0.5], [1.0, 3.0, -0.5]],
        };
        let b = t.bounds();
        for &plane in &[0.1f32, 0.7, 1.0, 1.3, 2.9] {
            let (l, r) = split_triangle(&t, 0, plane, &b);
            assert!(l.max[0] <= plane && r.min[0] >= plane);
            // Dense samples of the triangle fall in one of the pieces.
            for i in 0..=40 {
                for j in 0..=(40 - i) {
                    let (u, v) = (i as f64 / 40.0, j as f64 / 40.0);
                    let p: [f32; 3] = std::array::from_fn(|k| {
                        ((1.0 - u - v) * t.v[0][k] as f64
                            + u * t.v[1][k] as f64
                            + v * t.v[2][k] as f64) as f32
                    });
                    let inside = |bx: &Aabb| (0..3).all(|k| bx.min[k] <= p[k] && p[k] <= bx.max[k]);
                    // Rounding of the sample itself: allow one ulp on the split axis.
                    let near = (p[0] - plane).abs() <= f32::EPSILON * plane.abs().max(1.0);
                    assert!(inside(&l) || inside(&r) || near, "{p:?} at plane {plane}");
                }
            }
        }
        // A plane that misses gives one empty piece.
        let (l, r) = split_triangle(&t, 0, 5.0, &b);
        assert_eq!(l, b);
        assert!(r.is_empty());
    }
}
