//! Ray records and ray filtering (Áfra 2012 §3.1).
//!
//! Rays live in one array of 32-byte records and are filtered by *moving the records*: the
//! rays that intersect a box are swapped to the front of the range, so a node's active rays
//! are always a prefix and are read strictly linearly (hardware prefetching does the rest).
//!
//! A record is RAY1's 32 bytes with `tmin` replaced by a slot index: the record has to carry
//! the ray's identity through the reordering, and RAY1 has no spare word. `tmin` is not
//! needed in the record: boxes are tested over `[0, tmax]`, which is conservative, and the
//! leaf tests compare against 0; a ray whose `tmin` is not 0 is flagged ([`TMIN_FLAG`]) and
//! its `tmin` is read from its hit slot (where the `u` field holds it while tracing), only
//! for the few groups that contain such rays.

use crate::geometry::{Aabb, Ray};

/// One active ray: origin, slot index (with [`TMIN_FLAG`]), direction, and the current end of
/// its interval — the distance of the best hit so far, or `-inf` once an `any` ray is done.
#[repr(C, align(32))]
#[derive(Clone, Copy, Debug, PartialEq, Default)]
pub struct RayRec {
    /// Origin.
    pub org: [f32; 3],
    /// Index of the ray's hit slot in the table of the task that owns this array, or'ed with
    /// [`TMIN_FLAG`] when the ray's `tmin` is not 0.
    pub slot: u32,
    /// Direction (not normalised).
    pub dir: [f32; 3],
    /// End of the interval still searched.
    pub tmax: f32,
}

const _: () = assert!(std::mem::size_of::<RayRec>() == 32);

/// Set in [`RayRec::slot`] when the ray's `tmin` is not 0 (its `tmin` is then in the slot).
pub const TMIN_FLAG: u32 = 1 << 31;
/// The bits of [`RayRec::slot`] that index the hit table.
pub const SLOT_MASK: u32 = TMIN_FLAG - 1;

impl RayRec {
    /// The record of ray `ray` whose hit goes to slot `slot`.
    #[inline]
    pub fn new(ray: &Ray, slot: u32) -> RayRec {
        let flag = if ray.tmin != 0.0 { TMIN_FLAG } else { 0 };
        RayRec {
            org: ray.org,
            slot: slot | flag,
            dir: ray.dir,
            tmax: ray.tmax,
        }
    }

    /// Index of the hit slot.
    #[inline(always)]
    pub fn index(&self) -> usize {
        (self.slot & SLOT_MASK) as usize
    }
}

/// Relative slack on the `t` comparisons of the box test: the triangle test's `t` and the
/// slab distances are rounded differently, and a ray must never be filtered out of a box
/// whose triangle `brute` would report at exactly the current `tmax` (ties decide by id).
const T_SLACK: f32 = 1.0 / 4096.0;

/// A box prepared for filtering: grown by a hair on every side so that a ray lying exactly in
/// a face plane (an axis-parallel ray through a triangle's edge) never produces `0 × ∞`,
/// and so that rounding in the slab distances cannot drop a ray that touches the box.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct FilterBox {
    /// Lower corner.
    pub min: [f32; 3],
    /// Upper corner.
    pub max: [f32; 3],
}

impl FilterBox {
    /// Prepares `b` (which must not be empty).
    pub fn new(b: &Aabb) -> FilterBox {
        let mut f = FilterBox {
            min: b.min,
            max: b.max,
        };
        for k in 0..3 {
            let m = b.min[k].abs().max(b.max[k].abs());
            let eps = m * (1.0 / (1 << 20) as f32) + f32::MIN_POSITIVE;
            f.min[k] = b.min[k] - eps;
            f.max[k] = b.max[k] + eps;
        }
        f
    }

    /// Whether the ray enters the box within `[0, tmax]` (scalar form; the 8-wide kernel
    /// computes exactly the same), and if so the entry distance.
    #[inline]
    pub fn entry(&self, org: [f32; 3], dir: [f32; 3], tmax: f32) -> Option<f32> {
        let mut near = 0.0f32;
        let mut far = tmax * (1.0 + T_SLACK);
        for k in 0..3 {
            let inv = 1.0 / dir[k];
            let t0 = (self.min[k] - org[k]) * inv;
            let t1 = (self.max[k] - org[k]) * inv;
            near = max_nan_left(min_nan_left(t0, t1), near);
            far = min_nan_left(max_nan_left(t0, t1), far);
        }
        (near <= far * (1.0 + T_SLACK)).then_some(near)
    }
}

/// `if a < b { a } else { b }`: the SIMD layer's `min` (b when either is NaN).
#[inline(always)]
fn min_nan_left(a: f32, b: f32) -> f32 {
    if a < b {
        a
    } else {
        b
    }
}

/// `if a > b { a } else { b }`: the SIMD layer's `max` (b when either is NaN).
#[inline(always)]
fn max_nan_left(a: f32, b: f32) -> f32 {
    if a > b {
        a
    } else {
        b
    }
}

/// The box-test mask of up to 8 records starting at `recs[0]` (bit i for `recs[i]`).
#[inline(always)]
fn mask8(b: &FilterBox, recs: &[RayRec]) -> u32 {
    let mut m = 0;
    for (i, r) in recs.iter().enumerate().take(8) {
        if b.entry(r.org, r.dir, r.tmax).is_some() {
            m |= 1 << i;
        }
    }
    m
}

/// Filters `rays` in place against `b`: the rays that enter the box move to the front;
/// returns how many. Unstable (order is not kept), 8 rays per step.
pub fn filter(rays: &mut [RayRec], b: &FilterBox) -> usize {
    let mut w = 0;
    let n = rays.len();
    let mut i = 0;
    while i < n {
        let end = (i + 8).min(n);
        let mut m = mask8(b, &rays[i..end]);
        while m != 0 {
            let lane = m.trailing_zeros() as usize;
            m &= m - 1;
            rays.swap(w, i + lane);
            w += 1;
        }
        i = end;
    }
    w
}

/// Appends the rays of `rays` that enter `b` to `out`, each with its hit slot renumbered to
/// the next slot of a task-local table; `link` receives, per copied ray, its position in
/// `rays` (the merge after the task writes back through it).
pub fn filter_copy(
    rays: &[RayRec],
    b: &FilterBox,
    out: &mut Vec<RayRec>,
    link: &mut Vec<u32>,
) -> usize {
    let n = rays.len();
    let mut i = 0;
    while i < n {
        let end = (i + 8).min(n);
        let mut m = mask8(b, &rays[i..end]);
        while m != 0 {
            let lane = m.trailing_zeros() as usize;
            m &= m - 1;
            let mut r = rays[i + lane];
            r.slot = (r.slot & TMIN_FLAG) | out.len() as u32;
            out.push(r);
            link.push((i + lane) as u32);
        }
        i = end;
    }
    out.len()
}

#[cfg(test)]
mod tests {
    use super::*;

    fn rec(org: [f32; 3], dir: [f32; 3], tmax: f32, slot: u32) -> RayRec {
        RayRec {
            org,
            slot,
            dir,
            tmax,
        }
    }

    fn unit() -> FilterBox {
        FilterBox::new(&Aabb {
            min: [0.0; 3],
            max: [1.0; 3],
        })
    }

    #[test]
    fn axis_parallel_rays_in_a_face_plane_are_kept() {
        let b = unit();
        for dir in [[1.0, 0.0, 0.0], [1.0, -0.0, 0.0], [-1.0, 0.0, -0.0]] {
            let org = if dir[0] > 0.0 {
                [-5.0, 0.0, 1.0]
            } else {
                [5.0, 1.0, 0.0]
            };
            assert!(b.entry(org, dir, f32::INFINITY).is_some(), "{dir:?}");
        }
        // Parallel and outside the slab: culled.
        assert!(b
            .entry([-5.0, 1.5, 0.5], [1.0, 0.0, 0.0], f32::INFINITY)
            .is_none());
    }

    #[test]
    fn tmax_culls_and_behind_culls() {
        let b = unit();
        assert!(b.entry([-5.0, 0.5, 0.5], [1.0, 0.0, 0.0], 4.0).is_none());
        let e = b.entry([-5.0, 0.5, 0.5], [1.0, 0.0, 0.0], 5.0).unwrap();
        assert!((e - 5.0).abs() < 1e-4, "{e}");
        assert!(b.entry([5.0, 0.5, 0.5], [1.0, 0.0, 0.0], 100.0).is_none());
        // Origin inside: entry at 0.
        assert_eq!(b.entry([0.5; 3], [0.0, 0.0, 1.0], 1.0), Some(0.0));
    }

    #[test]
    fn filter_moves_active_rays_to_the_front() {
        let b = unit();
        let mut rays: Vec<RayRec> = (0..21)
            .map(|i| {
                let y = if i % 3 == 0 { 0.5 } else { 3.0 };
                rec([-1.0, y, 0.5], [1.0, 0.0, 0.0], f32::INFINITY, i)
            })
            .collect();
        let n = filter(&mut rays, &b);
        assert_eq!(n, 7);
        let mut front: Vec<u32> = rays[..n].iter().map(|r| r.slot).collect();
        front.sort();
        assert_eq!(front, vec![0, 3, 6, 9, 12, 15, 18]);
        let mut all: Vec<u32> = rays.iter().map(|r| r.slot).collect();
        all.sort();
        assert_eq!(all, (0..21).collect::<Vec<_>>());
        let mut out = Vec::new();
        let mut link = Vec::new();
        filter_copy(&rays, &b, &mut out, &mut link);
        assert_eq!(out.len(), 7);
        assert!(out.iter().enumerate().all(|(i, r)| r.slot == i as u32));
        assert!(link.iter().all(|&p| (p as usize) < n));
    }
}
