//! Eight ray records as eight SIMD lanes: the transposition from the records' array layout
//! (one record per 8-wide vector) to one vector per field, and the slab test of 8 rays
//! against one box. Both the filtering and the leaves start from here (Áfra 2012 §3.1: "we
//! again leverage the SIMD-friendly layout of the rays to quickly transpose the values").
//!
//! Everything is generic over the SIMD layer's backend and `#[inline(always)]`, so it
//! compiles inside the calling kernel's target features.

use crate::simd::{FloatV, Select, Simd};

use super::rays::{FilterBox, RayRec};

/// Lane indices for one butterfly stage of the transposition: each lane's partner at
/// distance `d`.
#[derive(Clone, Copy)]
pub struct Transposer<S: Simd> {
    swap: [S::I8; 3],
    keep: [S::M8; 3],
}

impl<S: Simd> Transposer<S> {
    /// The constants (made once per kernel call).
    #[inline(always)]
    pub fn new(s: S) -> Self {
        Transposer {
            swap: [
                s.load_i8(&[4, 5, 6, 7, 0, 1, 2, 3]),
                s.load_i8(&[2, 3, 0, 1, 6, 7, 4, 5]),
                s.load_i8(&[1, 0, 3, 2, 5, 4, 7, 6]),
            ],
            keep: [
                s.mask8(0b0000_1111),
                s.mask8(0b0011_0011),
                s.mask8(0b0101_0101),
            ],
        }
    }

    /// One exchange: `a` keeps its `keep` lanes and takes `b`'s partners elsewhere, `b` the
    /// other way round.
    #[inline(always)]
    fn pair(&self, stage: usize, a: S::F8, b: S::F8) -> (S::F8, S::F8) {
        let (p, m) = (self.swap[stage], self.keep[stage]);
        (m.select(a, b.permute(p)), m.select(a.permute(p), b))
    }

    /// Transposes an 8×8 block: `rows[i]` lane `j` becomes `out[j]` lane `i`. Three
    /// butterfly stages (4, 2, 1 lanes apart) of two permutes and two blends per pair.
    /// Spelled out (no loops, no array indexing) so that the block stays in registers.
    #[inline(always)]
    pub fn transpose(&self, rows: [S::F8; 8]) -> [S::F8; 8] {
        let [r0, r1, r2, r3, r4, r5, r6, r7] = rows;
        let (r0, r4) = self.pair(0, r0, r4);
        let (r1, r5) = self.pair(0, r1, r5);
        let (r2, r6) = self.pair(0, r2, r6);
        let (r3, r7) = self.pair(0, r3, r7);
        let (r0, r2) = self.pair(1, r0, r2);
        let (r1, r3) = self.pair(1, r1, r3);
        let (r4, r6) = self.pair(1, r4, r6);
        let (r5, r7) = self.pair(1, r5, r7);
        let (r0, r1) = self.pair(2, r0, r1);
        let (r2, r3) = self.pair(2, r2, r3);
        let (r4, r5) = self.pair(2, r4, r5);
        let (r6, r7) = self.pair(2, r6, r7);
        [r0, r1, r2, r3, r4, r5, r6, r7]
    }
}

/// Fields of 8 rays, one vector each.
#[derive(Clone, Copy)]
pub struct Rays8<S: Simd> {
    /// Origin.
    pub org: [S::F8; 3],
    /// Direction.
    pub dir: [S::F8; 3],
    /// End of the interval.
    pub tmax: S::F8,
    /// The slot words (bits of [`RayRec::slot`]).
    pub slot: S::I8,
}

impl<S: Simd> Rays8<S> {
    /// Loads 1 to 8 records; missing lanes repeat the first record (callers mask them).
    #[inline(always)]
    pub fn load(s: S, tr: &Transposer<S>, recs: &[RayRec]) -> Self {
        match <&[RayRec; 8]>::try_from(recs) {
            Ok(full) => Self::load8(s, tr, full),
            Err(_) => {
                let mut pad = [recs[0]; 8];
                pad[..recs.len()].copy_from_slice(recs);
                Self::load8(s, tr, &pad)
            }
        }
    }

    /// Loads 8 records.
    #[inline(always)]
    pub fn load8(s: S, tr: &Transposer<S>, r: &[RayRec; 8]) -> Self {
        let rows = [
            s.load_f8(&r[0].0),
            s.load_f8(&r[1].0),
            s.load_f8(&r[2].0),
            s.load_f8(&r[3].0),
            s.load_f8(&r[4].0),
            s.load_f8(&r[5].0),
            s.load_f8(&r[6].0),
            s.load_f8(&r[7].0),
        ];
        let c = tr.transpose(rows);
        Rays8 {
            org: [c[0], c[1], c[2]],
            slot: c[3].to_bits(),
            dir: [c[4], c[5], c[6]],
            tmax: c[7],
        }
    }
}

/// The box constants of the 8-wide slab test.
#[derive(Clone, Copy)]
pub struct Box8<S: Simd> {
    min: [S::F8; 3],
    max: [S::F8; 3],
    zero: S::F8,
    slack: S::F8,
}

impl<S: Simd> Box8<S> {
    /// Broadcasts `b`.
    #[inline(always)]
    pub fn new(s: S, b: &FilterBox) -> Self {
        Box8 {
            min: [
                s.splat_f8(b.min[0]),
                s.splat_f8(b.min[1]),
                s.splat_f8(b.min[2]),
            ],
            max: [
                s.splat_f8(b.max[0]),
                s.splat_f8(b.max[1]),
                s.splat_f8(b.max[2]),
            ],
            zero: s.splat_f8(0.0),
            slack: s.splat_f8(1.0 + super::rays::T_SLACK),
        }
    }

    /// The lanes whose ray enters the box within `[0, tmax]`, and their entry distances:
    /// exactly [`FilterBox::entry`], lane by lane.
    #[inline(always)]
    pub fn test(&self, r: &Rays8<S>) -> (S::M8, S::F8) {
        let mut near = self.zero;
        let mut far = r.tmax * self.slack;
        for k in 0..3 {
            let inv = r.dir[k].recip();
            let t0 = (self.min[k] - r.org[k]) * inv;
            let t1 = (self.max[k] - r.org[k]) * inv;
            near = t0.min(t1).max(near);
            far = t0.max(t1).min(far);
        }
        (near.le(far * self.slack), near)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::simd::{dispatch, Backend, Kernel};

    struct T;
    impl Kernel for T {
        type Output = [[f32; 8]; 8];
        #[inline(always)]
        fn run<S: Simd>(self, s: S) -> Self::Output {
            let tr = Transposer::new(s);
            let rows: [S::F8; 8] =
                std::array::from_fn(|i| s.load_f8(&std::array::from_fn(|j| (10 * i + j) as f32)));
            tr.transpose(rows).map(|v| v.to_array())
        }
    }

    #[test]
    fn transpose_is_a_transpose_on_every_backend() {
        for b in Backend::supported() {
            let out = dispatch(b, T);
            for (j, col) in out.iter().enumerate() {
                for (i, &x) in col.iter().enumerate() {
                    assert_eq!(x, (10 * i + j) as f32, "{b}");
                }
            }
        }
    }
}
