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
use crate::simd::{self, Kernel, MaskV, Simd};

use super::lanes::{Box8, Rays8, Transposer};

/// One active ray, as the 8 lanes of one SIMD vector: origin (lanes 0–2), slot word (lane 3,
/// as bits: the index of the ray's hit slot in the table of the task that owns this array,
/// or'ed with [`TMIN_FLAG`] when the ray's `tmin` is not 0), direction (lanes 4–6), and the
/// current end of its interval (lane 7) — the distance of the best hit so far, or `-inf`
/// once an `any` ray is done.
#[repr(C, align(32))]
#[derive(Clone, Copy, Debug, PartialEq, Default)]
pub struct RayRec(pub [f32; 8]);

const _: () = assert!(std::mem::size_of::<RayRec>() == 32);

/// Set in the slot word when the ray's `tmin` is not 0 (its `tmin` is then in the slot).
pub const TMIN_FLAG: u32 = 1 << 31;
/// The bits of the slot word that index the hit table.
pub const SLOT_MASK: u32 = TMIN_FLAG - 1;

impl RayRec {
    /// The record of ray `ray` whose hit goes to slot `slot`.
    #[inline]
    pub fn new(ray: &Ray, slot: u32) -> RayRec {
        let flag = if ray.tmin != 0.0 { TMIN_FLAG } else { 0 };
        let (o, d) = (ray.org, ray.dir);
        RayRec([
            o[0],
            o[1],
            o[2],
            f32::from_bits(slot | flag),
            d[0],
            d[1],
            d[2],
            ray.tmax,
        ])
    }

    /// Origin.
    #[inline(always)]
    pub fn org(&self) -> [f32; 3] {
        [self.0[0], self.0[1], self.0[2]]
    }

    /// Direction.
    #[inline(always)]
    pub fn dir(&self) -> [f32; 3] {
        [self.0[4], self.0[5], self.0[6]]
    }

    /// End of the interval still searched.
    #[inline(always)]
    pub fn tmax(&self) -> f32 {
        self.0[7]
    }

    /// Sets the end of the interval.
    #[inline(always)]
    pub fn set_tmax(&mut self, t: f32) {
        self.0[7] = t;
    }

    /// The slot word (index and [`TMIN_FLAG`]).
    #[inline(always)]
    pub fn slot(&self) -> u32 {
        self.0[3].to_bits()
    }

    /// Moves the ray to hit slot `index`, keeping its flag.
    #[inline(always)]
    pub fn set_index(&mut self, index: u32) {
        self.0[3] = f32::from_bits((self.slot() & TMIN_FLAG) | index);
    }

    /// Index of the hit slot.
    #[inline(always)]
    pub fn index(&self) -> usize {
        (self.slot() & SLOT_MASK) as usize
    }
}

/// Relative slack on the `t` comparisons of the box test: the triangle test's `t` and the
/// slab distances are rounded differently, and a ray must never be filtered out of a box
/// whose triangle `brute` would report at exactly the current `tmax` (ties decide by id).
pub(super) const T_SLACK: f32 = 1.0 / 4096.0;

/// A box prepared for filtering, grown on every side by `2^-12` of its largest extent plus
/// `2^-20` of its coordinates' magnitude (and never by less than the smallest normal
/// float), for three reasons:
///
/// - a ray lying exactly in a face plane (an axis-parallel ray through a triangle's edge)
///   must not produce `0 × ∞` in the slab test;
/// - rounding in the slab distances must not drop a ray that touches the box;
/// - the triangle test's `t` has an absolute error that grows with the triangle's size,
///   not with `t`: a huge triangle (here 10⁴ long) met a unit away can be reported by
///   `brute` at a `t` whose point lies visibly outside the triangle's own box (a flat box
///   at `y = 0` reported at `y = −0.15`). Culling that ray by `tmax` against the exact box
///   would then disagree with `brute`; the margin, proportional to the box's extent, keeps
///   such hits inside. It costs nothing measurable in culling.
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
        let e = b.extent();
        let size = e[0].max(e[1]).max(e[2]) * (1.0 / 4096.0);
        for k in 0..3 {
            let m = b.min[k].abs().max(b.max[k].abs());
            let eps = size + m * (1.0 / (1 << 20) as f32) + f32::MIN_POSITIVE;
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

/// Runs `each(base, bits)` for every group of 8 records of `rays` (fewer in the last one)
/// with the bits of the rays that enter `b`.
struct Groups<'a, F> {
    rays: &'a [RayRec],
    b: &'a FilterBox,
    each: F,
}

impl<F: FnMut(usize, u32)> Kernel for Groups<'_, F> {
    type Output = ();

    #[inline(always)]
    fn run<S: Simd>(mut self, s: S) {
        let tr = Transposer::new(s);
        let bx = Box8::new(s, self.b);
        for (g, recs) in self.rays.chunks(8).enumerate() {
            let r = Rays8::load(s, &tr, recs);
            let bits = bx.test(&r).0.bitmask() & ((1u32 << recs.len()) - 1);
            (self.each)(8 * g, bits);
        }
    }
}

/// The in-place filter as one kernel: masks 8 rays at a time and swaps the active ones to
/// the front with whole-record (32-byte) moves, all under the backend's target features.
struct Filter<'a> {
    rays: &'a mut [RayRec],
    b: &'a FilterBox,
}

impl Kernel for Filter<'_> {
    type Output = usize;

    #[inline(always)]
    fn run<S: Simd>(self, s: S) -> usize {
        let tr = Transposer::new(s);
        let bx = Box8::new(s, self.b);
        let rays = self.rays;
        let n = rays.len();
        let mut w = 0;
        let mut base = 0;
        while base < n {
            let len = (n - base).min(8);
            let r = Rays8::load(s, &tr, &rays[base..base + len]);
            let mut bits = bx.test(&r).0.bitmask() & ((1u32 << len) - 1);
            if bits == 0xFF && w == base {
                w += 8;
            } else {
                while bits != 0 {
                    let lane = bits.trailing_zeros() as usize;
                    bits &= bits - 1;
                    let i = base + lane;
                    if i != w {
                        rays.swap(w, i);
                    }
                    w += 1;
                }
            }
            base += len;
        }
        w
    }
}

/// Filters `rays` in place against `b`: the rays that enter the box move to the front;
/// returns how many. Unstable (order is not kept), 8 rays per SIMD step.
pub fn filter(rays: &mut [RayRec], b: &FilterBox) -> usize {
    simd::dispatch(simd::selected(), Filter { rays, b })
}

/// [`filter`] towards the back: the rays that enter `b` move to the *end* of `rays`;
/// returns how many.
struct FilterBack<'a> {
    rays: &'a mut [RayRec],
    b: &'a FilterBox,
}

impl Kernel for FilterBack<'_> {
    type Output = usize;

    #[inline(always)]
    fn run<S: Simd>(self, s: S) -> usize {
        let tr = Transposer::new(s);
        let bx = Box8::new(s, self.b);
        let rays = self.rays;
        let n = rays.len();
        let mut w = n;
        let mut end = n;
        while end > 0 {
            let len = end.min(8);
            let base = end - len;
            let r = Rays8::load(s, &tr, &rays[base..end]);
            let mut bits = bx.test(&r).0.bitmask() & ((1u32 << len) - 1);
            if bits == 0xFF && w == end {
                w -= 8;
            } else {
                while bits != 0 {
                    let lane = 31 - bits.leading_zeros() as usize;
                    bits &= !(1 << lane);
                    w -= 1;
                    let i = base + lane;
                    if i != w {
                        rays.swap(w, i);
                    }
                }
            }
            end = base;
        }
        n - w
    }
}

/// Filters `rays` in place against `b`, moving the rays that enter it to the *end*;
/// returns how many.
pub fn filter_back(rays: &mut [RayRec], b: &FilterBox) -> usize {
    simd::dispatch(simd::selected(), FilterBack { rays, b })
}

/// Both children's filtering in one pass: a three-way partition.
struct Filter2<'a> {
    rays: &'a mut [RayRec],
    first: &'a FilterBox,
    second: &'a FilterBox,
}

impl Kernel for Filter2<'_> {
    type Output = (usize, usize);

    #[inline(always)]
    fn run<S: Simd>(self, s: S) -> (usize, usize) {
        let tr = Transposer::new(s);
        let (b1, b2) = (Box8::new(s, self.first), Box8::new(s, self.second));
        let rays = self.rays;
        let n = rays.len();
        // [0, a): enter the first box; [a, b): only the second; [b, i): neither.
        let (mut a, mut b) = (0, 0);
        let mut base = 0;
        while base < n {
            let len = (n - base).min(8);
            let r = Rays8::load(s, &tr, &rays[base..base + len]);
            let valid = (1u32 << len) - 1;
            let one = b1.test(&r).0.bitmask() & valid;
            let two = b2.test(&r).0.bitmask() & valid & !one;
            if one == 0xFF && a == base {
                a += 8;
                b += 8;
            } else {
                let mut bits = one | two;
                while bits != 0 {
                    let lane = bits.trailing_zeros() as usize;
                    bits &= bits - 1;
                    let i = base + lane;
                    if one >> lane & 1 == 1 {
                        // i -> a, a -> b, b -> i (a <= b <= i): one three-cycle.
                        let r = rays[i];
                        rays[i] = rays[b];
                        rays[b] = rays[a];
                        rays[a] = r;
                        a += 1;
                    } else if i != b {
                        rays.swap(b, i);
                    }
                    b += 1;
                }
            }
            base += len;
        }
        (a, b - a)
    }
}

/// Filters `rays` in place against two boxes at once: the rays that enter `first` move to
/// the front, those that enter only `second` right after them. Returns both counts. This
/// is what lets the second child be filtered, after the first child's recursion, only
/// among the first child's rays (the others' `tmax` has not changed).
pub fn filter2(rays: &mut [RayRec], first: &FilterBox, second: &FilterBox) -> (usize, usize) {
    simd::dispatch(
        simd::selected(),
        Filter2 {
            rays,
            first,
            second,
        },
    )
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
    simd::dispatch(
        simd::selected(),
        Groups {
            rays,
            b,
            each: |base: usize, mut bits: u32| {
                while bits != 0 {
                    let lane = bits.trailing_zeros() as usize;
                    bits &= bits - 1;
                    let mut r = rays[base + lane];
                    r.set_index(out.len() as u32);
                    out.push(r);
                    link.push((base + lane) as u32);
                }
            },
        },
    );
    out.len()
}

#[cfg(test)]
mod tests {
    use super::*;

    fn rec(org: [f32; 3], dir: [f32; 3], tmax: f32, slot: u32) -> RayRec {
        RayRec::new(
            &Ray {
                org,
                tmin: 0.0,
                dir,
                tmax,
            },
            slot,
        )
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
        // The box is grown by 2^-12 of its extent (see `FilterBox`).
        assert!((e - 5.0).abs() <= 1.0 / 4096.0 + 1e-5, "{e}");
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
        let mut front: Vec<u32> = rays[..n].iter().map(|r| r.slot()).collect();
        front.sort();
        assert_eq!(front, vec![0, 3, 6, 9, 12, 15, 18]);
        let mut all: Vec<u32> = rays.iter().map(|r| r.slot()).collect();
        all.sort();
        assert_eq!(all, (0..21).collect::<Vec<_>>());
        let mut out = Vec::new();
        let mut link = Vec::new();
        filter_copy(&rays, &b, &mut out, &mut link);
        // Towards the back.
        let m = filter_back(&mut rays, &b);
        assert_eq!(m, 7);
        let mut back: Vec<u32> = rays[21 - m..].iter().map(|r| r.slot()).collect();
        back.sort();
        assert_eq!(back, vec![0, 3, 6, 9, 12, 15, 18]);
        // Two boxes: y = 0.5 rays enter the unit box, y = 3 rays enter the second.
        let b2 = FilterBox::new(&Aabb {
            min: [0.0, 2.5, 0.0],
            max: [1.0, 3.5, 1.0],
        });
        let (a, only2) = filter2(&mut rays, &b, &b2);
        assert_eq!((a, only2), (7, 14));
        assert!(rays[..7].iter().all(|r| r.slot() % 3 == 0));
        assert!(rays[7..].iter().all(|r| r.slot() % 3 != 0));
        assert_eq!(out.len(), 7);
        assert!(out.iter().enumerate().all(|(i, r)| r.slot() == i as u32));
        assert!(link.iter().all(|&p| (p as usize) < n));
    }
}

#[cfg(test)]
mod speed {
    use super::*;

    /// Raw filter throughput by working-set size (run with `--ignored --nocapture`).
    #[test]
    #[ignore]
    fn filter_throughput() {
        let mut s = 1u64;
        let mut rnd = || {
            s = s
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            ((s >> 40) as f32 / (1u64 << 24) as f32) * 2.0 - 1.0
        };
        let b = FilterBox::new(&Aabb {
            min: [-0.5, -0.5, -0.5],
            max: [0.5, 0.5, 0.5],
        });
        for n in [1 << 10, 1 << 14, 1 << 18, 1 << 20] {
            let mut rays: Vec<RayRec> = (0..n)
                .map(|i| {
                    RayRec::new(
                        &Ray {
                            org: [rnd() * 2.0, rnd() * 2.0, -3.0],
                            tmin: 0.0,
                            dir: [rnd() * 0.1, rnd() * 0.1, 1.0],
                            tmax: f32::INFINITY,
                        },
                        i,
                    )
                })
                .collect();
            let reps = (1 << 24) / n as usize;
            let t0 = std::time::Instant::now();
            let mut act = 0;
            for _ in 0..reps {
                act += filter(&mut rays, &b);
            }
            let dt = t0.elapsed().as_secs_f64();
            println!(
                "n={n}: {:.2} ns/ray, {:.0}% active",
                dt * 1e9 / (reps * n as usize) as f64,
                100.0 * act as f64 / (reps * n as usize) as f64
            );
        }
    }
}
