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

use super::binning::{partition, sweep, BinMap, Bins, Centroids, SahPlan, SweepBest};
use super::build::{grow, half_area, intersect, union, CostModel, Range, Ref};
use crate::geometry::{Aabb, Triangle};

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

impl Bins {
    /// Spatial binning: each reference is chopped at the planes it crosses.
    fn add_spatial(&mut self, tris: &[Triangle], refs: &[Ref], map: &BinMap) {
        for r in refs {
            for a in 0..3 {
                if map.scale[a] == 0.0 {
                    continue;
                }
                let k0 = map.bin(r.lo[a], a);
                let k1 = map.bin(r.hi[a], a);
                self.enter[a][k0] += 1;
                self.exit[a][k1] += 1;
                if k0 == k1 {
                    grow(&mut self.boxes[a][k0], &r.lo, &r.hi);
                    continue;
                }
                let tri = &tris[r.id as usize];
                let mut piece = r.aabb();
                for k in k0..k1 {
                    let (left, right) = split_triangle(tri, a, map.plane(a, k + 1), &piece);
                    self.boxes[a][k] = union(&self.boxes[a][k], &left);
                    piece = right;
                }
                self.boxes[a][k1] = union(&self.boxes[a][k1], &piece);
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
    let map = BinMap::new(&r.bounds, 1.0);
    let bins = if refs.len() < PAR_SPATIAL {
        let mut b = Bins::new();
        b.add_spatial(tris, refs, &map);
        b
    } else {
        refs.par_chunks(PAR_SPATIAL / 4)
            .fold(Bins::new, |mut b, c| {
                b.add_spatial(tris, c, &map);
                b
            })
            .reduce(Bins::new, Bins::merge)
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
            inv_area,
            cost,
        ) {
            if s.nl + s.nr <= room && best.map_or(true, |(_, o)| s.s < o.s) {
                best = Some((a, s));
            }
        }
    }
    let (a, s) = best?;
    let (lbox, rbox) = bins.halves(a, s.bin);
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
            refs[i].aux = LEFT;
            continue;
        }
        if k0 >= bin {
            refs[i].aux = RIGHT;
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
            refs[i].aux = LEFT;
            lbox = lb;
            nr -= 1.0;
            continue;
        }
        if c_right < c_split {
            refs[i].aux = RIGHT;
            rbox = rb;
            nl -= 1.0;
            continue;
        }
        let (left, right) = split_triangle(&tris[r.id as usize], axis, plane, &b);
        if left.is_empty() {
            refs[i] = Ref {
                aux: RIGHT,
                ..Ref::new(r.id, &right)
            };
        } else if right.is_empty() {
            refs[i] = Ref {
                aux: LEFT,
                ..Ref::new(r.id, &left)
            };
        } else {
            refs[i] = Ref {
                aux: LEFT,
                ..Ref::new(r.id, &left)
            };
            refs[n + extra] = Ref {
                aux: RIGHT,
                ..Ref::new(r.id, &right)
            };
            extra += 1;
        }
    }
    let left = partition(&mut refs[..n], |x| x.aux == LEFT);
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
