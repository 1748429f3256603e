//! Ray sampling (Nabata et al. 2013 §4.1–4.4): a few active rays are tested against the
//! candidate child boxes of a node, and what they say — how many enter each box, and which
//! box of a pair each reaches first — chooses the split plane (eq. 2), the order of the
//! children, and whether a child needs its rays filtered at all (eq. 5–6).
//!
//! One sample ray is tested against 8 boxes per SIMD step: the 31 left and 31 right boxes
//! of a binning are laid out so that the left and right box of plane `j` share a lane, and
//! the per-plane counts stay in vector registers' worth of arrays.

use crate::geometry::Aabb;
use crate::simd::{self, FloatV, IntV, Kernel, MaskV, Select, Simd};

use super::lanes::{Box8, Rays8, Transposer};
use super::rays::{FilterBox, RayRec, T_SLACK};
use super::split::Candidate;

/// What the sample rays say about one pair of child boxes (Nabata Algorithm 2).
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct Sampled {
    /// Sample rays entering the left box.
    pub hits_left: u32,
    /// Sample rays entering the right box.
    pub hits_right: u32,
    /// Sample rays that reach the left box first (or only the left box).
    pub nearer_left: u32,
    /// Sample rays that reach the right box first (or only the right box).
    pub nearer_right: u32,
}

/// Boxes per group (one SIMD vector).
const W: usize = 8;

/// Up to `G · 8` pairs of boxes in SoA groups: `lo[g][side][axis][lane]`,
/// `hi[g][side][axis][lane]` for the left (`side 0`) and right (`side 1`) box of each
/// pair, and which lanes hold a box at all (an empty box is never entered; no placeholder
/// coordinates could say so, since the slab test treats an inverted box as a box).
struct Pairs {
    lo: Vec<[[[f32; W]; 3]; 2]>,
    hi: Vec<[[[f32; W]; 3]; 2]>,
    valid: Vec<[u32; 2]>,
}

impl Pairs {
    fn new(pairs: &[(Aabb, Aabb)]) -> Pairs {
        let groups = pairs.len().div_ceil(W);
        // Padding lanes hold an empty box: no ray enters it.
        let mut lo = vec![[[[0.0; W]; 3]; 2]; groups];
        let mut hi = vec![[[[0.0; W]; 3]; 2]; groups];
        let mut valid = vec![[0u32; 2]; groups];
        for (j, (l, r)) in pairs.iter().enumerate() {
            for (side, b) in [l, r].into_iter().enumerate() {
                if b.is_empty() {
                    continue;
                }
                let f = FilterBox::new(b);
                for k in 0..3 {
                    lo[j / W][side][k][j % W] = f.min[k];
                    hi[j / W][side][k][j % W] = f.max[k];
                }
                valid[j / W][side] |= 1 << (j % W);
            }
        }
        Pairs { lo, hi, valid }
    }
}

/// The counting kernel: every sample ray against every pair. Groups of 8 pairs are the
/// outer loop, so that a group's 12 box vectors and its 4 counters stay in registers while
/// the sample rays (prepared once: origin, reciprocal direction, far limit) stream past.
struct Count<'a> {
    pairs: &'a Pairs,
    samples: &'a [RayRec],
}

impl Kernel for Count<'_> {
    type Output = Vec<[[i32; W]; 4]>;

    #[inline(always)]
    fn run<S: Simd>(self, s: S) -> Self::Output {
        let groups = self.pairs.lo.len();
        let mut counts = vec![[[0i32; W]; 4]; groups];
        // The same values the scalar test computes: `1 / d` per axis and `tmax · slack`.
        let pre: Vec<[f32; 7]> = self
            .samples
            .iter()
            .map(|r| {
                let (o, d) = (r.org(), r.dir());
                [
                    o[0],
                    o[1],
                    o[2],
                    1.0 / d[0],
                    1.0 / d[1],
                    1.0 / d[2],
                    r.tmax() * (1.0 + T_SLACK),
                ]
            })
            .collect();
        let zero = s.splat_f8(0.0);
        let inf = s.splat_f8(f32::INFINITY);
        let one = s.splat_i8(1);
        let nil = s.splat_i8(0);
        let slack = s.splat_f8(1.0 + T_SLACK);
        for (g, out) in counts.iter_mut().enumerate() {
            let p = self.pairs;
            // Spelled out, no closures: they would not inherit the kernel's target features.
            let (l, h) = (&p.lo[g], &p.hi[g]);
            let lo = [
                [
                    s.load_f8(&l[0][0]),
                    s.load_f8(&l[0][1]),
                    s.load_f8(&l[0][2]),
                ],
                [
                    s.load_f8(&l[1][0]),
                    s.load_f8(&l[1][1]),
                    s.load_f8(&l[1][2]),
                ],
            ];
            let hi = [
                [
                    s.load_f8(&h[0][0]),
                    s.load_f8(&h[0][1]),
                    s.load_f8(&h[0][2]),
                ],
                [
                    s.load_f8(&h[1][0]),
                    s.load_f8(&h[1][1]),
                    s.load_f8(&h[1][2]),
                ],
            ];
            let valid = [s.mask8(p.valid[g][0]), s.mask8(p.valid[g][1])];
            let mut c = [nil; 4];
            for r in &pre {
                let org = [s.splat_f8(r[0]), s.splat_f8(r[1]), s.splat_f8(r[2])];
                let inv = [s.splat_f8(r[3]), s.splat_f8(r[4]), s.splat_f8(r[5])];
                let far0 = s.splat_f8(r[6]);
                let mut near = [zero; 2];
                let mut hit = valid;
                for side in 0..2 {
                    let mut n = zero;
                    let mut f = far0;
                    for k in 0..3 {
                        let t0 = (lo[side][k] - org[k]) * inv[k];
                        let t1 = (hi[side][k] - org[k]) * inv[k];
                        n = t0.min(t1).max(n);
                        f = t0.max(t1).min(f);
                    }
                    hit[side] = n.le(f * slack) & valid[side];
                    near[side] = hit[side].select(n, inf);
                }
                c[0] = c[0] + hit[0].select(one, nil);
                c[1] = c[1] + hit[1].select(one, nil);
                c[2] = c[2] + near[0].lt(near[1]).select(one, nil);
                c[3] = c[3] + near[1].lt(near[0]).select(one, nil);
            }
            *out = [
                c[0].to_array(),
                c[1].to_array(),
                c[2].to_array(),
                c[3].to_array(),
            ];
        }
        counts
    }
}

/// Tests `samples` against every pair of boxes; one [`Sampled`] per pair.
pub fn sample_pairs(samples: &[RayRec], pairs: &[(Aabb, Aabb)]) -> Vec<Sampled> {
    let p = Pairs::new(pairs);
    let counts = simd::dispatch(simd::selected(), Count { pairs: &p, samples });
    (0..pairs.len())
        .map(|j| {
            let c = &counts[j / W];
            let l = j % W;
            Sampled {
                hits_left: c[0][l] as u32,
                hits_right: c[1][l] as u32,
                nearer_left: c[2][l] as u32,
                nearer_right: c[3][l] as u32,
            }
        })
        .collect()
}

/// One pair against the sample rays, 8 rays per step (the filter's own box test): with a
/// single pair, lanes over rays do 8 times the useful work of lanes over boxes.
struct CountOne<'a> {
    samples: &'a [RayRec],
    left: &'a Aabb,
    right: &'a Aabb,
}

impl Kernel for CountOne<'_> {
    type Output = Sampled;

    #[inline(always)]
    fn run<S: Simd>(self, s: S) -> Sampled {
        let tr = Transposer::new(s);
        // An empty box is never entered; it keeps a placeholder box and a zero mask.
        let keep = [self.left, self.right].map(|b| if b.is_empty() { 0 } else { 0xFF });
        let fb =
            [self.left, self.right].map(|b| FilterBox::new(if b.is_empty() { &UNIT } else { b }));
        let (bl, br) = (Box8::new(s, &fb[0]), Box8::new(s, &fb[1]));
        let inf = s.splat_f8(f32::INFINITY);
        let mut out = Sampled::default();
        // No closures here: they would not inherit the kernel's target features.
        for recs in self.samples.chunks(8) {
            let r = Rays8::load(s, &tr, recs);
            let valid = (1u32 << recs.len()) - 1;
            let (ml, nl) = bl.test(&r);
            let (mr, nr) = br.test(&r);
            let hl = ml & s.mask8(valid & keep[0]);
            let hr = mr & s.mask8(valid & keep[1]);
            let (nl, nr) = (hl.select(nl, inf), hr.select(nr, inf));
            out.hits_left += hl.bitmask().count_ones();
            out.hits_right += hr.bitmask().count_ones();
            out.nearer_left += nl.lt(nr).bitmask().count_ones();
            out.nearer_right += nr.lt(nl).bitmask().count_ones();
        }
        out
    }
}

/// Stands in for an empty box in [`CountOne`] (whose lanes are masked off).
const UNIT: Aabb = Aabb {
    min: [0.0; 3],
    max: [1.0; 3],
};

/// Tests the sample rays against one pair of boxes.
pub fn sample_pair(samples: &[RayRec], left: &Aabb, right: &Aabb) -> Sampled {
    simd::dispatch(
        simd::selected(),
        CountOne {
            samples,
            left,
            right,
        },
    )
}

/// Nabata's sampled cost (eq. 2): the plane minimising `α_L·N_L + α_R·N_R`, where `α` is the
/// fraction of sample rays entering the candidate box; with what the samples said about it.
///
/// With `prior > 0`, `α` is smoothed towards the surface-area ratio `p` of the SAH as if
/// `prior` more rays had been sampled from SAH's uniform distribution:
/// `α = (hits + prior·p) / (samples + prior)`. With 100 samples, many candidates get
/// `α = 1` on both sides (every sample ray enters both boxes, as when the camera is inside
/// them) and eq. 2 then cannot tell them apart at all; the prior breaks such ties by area.
/// `prior = 0` is the paper's cost.
pub fn sampled_cost(
    cands: &[Candidate],
    samples: &[RayRec],
    parent: &Aabb,
    prior: f32,
) -> Option<(usize, Sampled)> {
    let pairs: Vec<(Aabb, Aabb)> = cands.iter().map(|c| (c.left, c.right)).collect();
    let sampled = sample_pairs(samples, &pairs);
    let pa = parent.area().max(f32::MIN_POSITIVE);
    let ns = samples.len() as f32;
    let alpha = |hits: u32, b: &Aabb| (hits as f32 + prior * (b.area() / pa)) / (ns + prior);
    let mut best: Option<(usize, f32, Sampled)> = None;
    for (j, (c, s)) in cands.iter().zip(sampled).enumerate() {
        if c.n_left == 0 || c.n_right == 0 {
            continue;
        }
        let cost = alpha(s.hits_left, &c.left) * c.n_left as f32
            + alpha(s.hits_right, &c.right) * c.n_right as f32;
        if best.as_ref().is_none_or(|&(_, b, _)| cost < b) {
            best = Some((j, cost, s));
        }
    }
    best.map(|(j, _, s)| (j, s))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::geometry::Ray;

    fn ray(org: [f32; 3], dir: [f32; 3]) -> RayRec {
        RayRec::new(
            &Ray {
                org,
                tmin: 0.0,
                dir,
                tmax: f32::INFINITY,
            },
            0,
        )
    }

    #[test]
    fn counts_match_the_scalar_box_test() {
        let bx = |x: f32| Aabb {
            min: [x, 0.0, 0.0],
            max: [x + 1.0, 1.0, 1.0],
        };
        let pairs: Vec<(Aabb, Aabb)> = (0..11)
            .map(|i| (bx(i as f32), bx(i as f32 + 0.5)))
            .chain([(Aabb::EMPTY, bx(3.0))])
            .collect();
        let samples: Vec<RayRec> = (0..37)
            .map(|i| {
                let y = (i % 5) as f32 * 0.3;
                ray(
                    [-2.0 + (i % 7) as f32, y, 0.5],
                    [if i % 2 == 0 { 1.0 } else { -1.0 }, 0.0, 0.0],
                )
            })
            .collect();
        let got = sample_pairs(&samples, &pairs);
        for (p, g) in pairs.iter().zip(&got) {
            let mut want = Sampled::default();
            for r in &samples {
                let e = |b: &Aabb| {
                    if b.is_empty() {
                        None
                    } else {
                        FilterBox::new(b).entry(r.org(), r.dir(), r.tmax())
                    }
                };
                let (dl, dr) = (e(&p.0), e(&p.1));
                want.hits_left += u32::from(dl.is_some());
                want.hits_right += u32::from(dr.is_some());
                let (dl, dr) = (dl.unwrap_or(f32::INFINITY), dr.unwrap_or(f32::INFINITY));
                want.nearer_left += u32::from(dl < dr);
                want.nearer_right += u32::from(dr < dl);
            }
            assert_eq!(*g, want, "{p:?}");
            assert_eq!(sample_pair(&samples, &p.0, &p.1), want, "{p:?}");
        }
    }
}
