//! The `fast` build: references sorted along a Morton curve, linked into a binary radix
//! tree whose boxes are computed bottom-up, which the multi-node construction then
//! collapses with the same cost functions as the SAH build. Nothing is binned, so each
//! split costs O(1) instead of a pass over the range.
//!
//! Codes have 10 bits per axis over the centroid bounds (30 bits, three 10-bit radix
//! passes). A range whose references all share one code is split at its middle.
//!
//! The radix tree over n sorted references has n − 1 inner nodes; the node of the range
//! split between references `s − 1` and `s` is stored at index `s − 1`. Each boundary is
//! split exactly once, so the slots are distinct, and a subtree over `[b, e)` owns exactly
//! the slots `b .. e − 1` — which lets the two halves be built in parallel on disjoint
//! slices.

use rayon::prelude::*;

use super::build::{fmax, fmin, half_area, inv_half_area, union, CostModel, Range, Ref, Splitter};
use crate::geometry::Aabb;

/// The `info` of a single-reference range (which has no split).
pub(crate) const NO_SPLIT: u32 = u32::MAX;

/// Ranges with at least this many references link their halves in parallel.
const PAR_LINK: usize = 1 << 12;

/// An inner node of the radix tree.
#[derive(Clone, Copy, Debug)]
pub(crate) struct MNode {
    /// Box of the node's references.
    pub bounds: Aabb,
    /// Split position of the left child's range, or [`NO_SPLIT`] for one reference.
    pub split_l: u32,
    /// Split position of the right child's range, or [`NO_SPLIT`].
    pub split_r: u32,
}

/// Spreads the low 10 bits of `v` to every third bit.
fn spread(v: u32) -> u32 {
    let mut x = v & 0x3ff;
    x = (x | (x << 16)) & 0x0300_00ff;
    x = (x | (x << 8)) & 0x0300_f00f;
    x = (x | (x << 4)) & 0x030c_30c3;
    x = (x | (x << 2)) & 0x0924_9249;
    x
}

/// Morton code of a point quantised to 1024 cells per axis of `cent`.
fn code(r: &Ref, lo: &[f32; 3], scale: &[f32; 3]) -> u32 {
    // Floor of the cell coordinate, clamped to 0..=1023, through the f32 mantissa (see
    // `binning::to_bin`): no saturating float-to-int conversion.
    let q: [u32; 3] = std::array::from_fn(|a| {
        let f = fmin(fmax((r.centroid(a) - lo[a]) * scale[a] - 0.5, 0.0), 1023.0);
        (f + 8_388_608.0).to_bits() & 1023
    });
    (spread(q[0]) << 2) | (spread(q[1]) << 1) | spread(q[2])
}

/// LSD radix sort of `keys` by their upper 32 bits (the Morton code; the lower 32 bits
/// carry the reference's index and keep equal codes in index order).
fn radix_sort(keys: &mut Vec<u64>) {
    let mut tmp = vec![0u64; keys.len()];
    // The three digits' histograms in one pass over the keys.
    let mut counts = [[0usize; 1024]; 3];
    for &k in keys.iter() {
        for (pass, count) in counts.iter_mut().enumerate() {
            count[((k >> (32 + 10 * pass)) & 1023) as usize] += 1;
        }
    }
    for (pass, count) in counts.iter_mut().enumerate() {
        let shift = 32 + 10 * pass;
        if count.contains(&keys.len()) {
            continue;
        }
        let mut sum = 0;
        for c in count.iter_mut() {
            let v = *c;
            *c = sum;
            sum += v;
        }
        for &k in keys.iter() {
            let d = ((k >> shift) & 1023) as usize;
            tmp[count[d]] = k;
            count[d] += 1;
        }
        std::mem::swap(keys, &mut tmp);
    }
}

/// Sorts `refs` along the Morton curve of their centroids (bounds `cent`) and links the
/// radix tree. Returns the tree and the root's split position.
pub(crate) fn sort_and_link(refs: &mut Vec<Ref>, cent: &Aabb, parallel: bool) -> (Vec<MNode>, u32) {
    let n = refs.len();
    if n < 2 {
        return (Vec::new(), NO_SPLIT);
    }
    let mut scale = [0.0f32; 3];
    for (a, s) in scale.iter_mut().enumerate() {
        let ext = cent.max[a] as f64 - cent.min[a] as f64;
        if ext > 0.0 && ext.is_finite() {
            let v = (1024.0 * (1.0 - 1e-6) / ext) as f32;
            if v.is_finite() {
                *s = v;
            }
        }
    }
    let mut keys: Vec<u64> = refs
        .par_iter()
        .enumerate()
        .map(|(i, r)| ((code(r, &cent.min, &scale) as u64) << 32) | i as u64)
        .collect();
    radix_sort(&mut keys);
    let sorted: Vec<Ref> = keys
        .par_iter()
        .map(|&k| refs[(k & 0xffff_ffff) as usize])
        .collect();
    *refs = sorted;
    let codes: Vec<u32> = keys.par_iter().map(|&k| (k >> 32) as u32).collect();
    drop(keys);
    let mut nodes = vec![
        MNode {
            bounds: Aabb::EMPTY,
            split_l: NO_SPLIT,
            split_r: NO_SPLIT,
        };
        n - 1
    ];
    let (_, root) = link(&codes, refs, &mut nodes, 0, parallel);
    (nodes, root)
}

/// Links the radix tree over `codes` (references `refs`, starting at global index `base`)
/// into `nodes` (its slots `base .. base + n - 1`). Returns the box and split position.
fn link(
    codes: &[u32],
    refs: &[Ref],
    nodes: &mut [MNode],
    base: u32,
    parallel: bool,
) -> (Aabb, u32) {
    let n = codes.len();
    if n == 1 {
        return (refs[0].aabb(), NO_SPLIT);
    }
    let (first, last) = (codes[0], codes[n - 1]);
    let s = if first == last {
        n / 2
    } else {
        let bit = 31 - (first ^ last).leading_zeros();
        codes.partition_point(|&c| c & (1 << bit) == 0)
    };
    let (ln, rest) = nodes.split_at_mut(s - 1);
    let (me, rn) = rest
        .split_first_mut()
        .expect("a range of two or more has a node");
    // Single references are answered here rather than by a call (half the calls).
    let mut left = move || {
        if s == 1 {
            (refs[0].aabb(), NO_SPLIT)
        } else {
            link(&codes[..s], &refs[..s], ln, base, parallel)
        }
    };
    let mut right = move || {
        if n - s == 1 {
            (refs[n - 1].aabb(), NO_SPLIT)
        } else {
            link(&codes[s..], &refs[s..], rn, base + s as u32, parallel)
        }
    };
    let ((lb, ls), (rb, rs)) = if parallel && n >= PAR_LINK {
        rayon::join(left, right)
    } else {
        (left(), right())
    };
    *me = MNode {
        bounds: union(&lb, &rb),
        split_l: ls,
        split_r: rs,
    };
    (me.bounds, base + s as u32)
}

/// The halves of a radix tree node, ready to become candidates.
#[derive(Clone, Copy, Debug)]
pub(crate) struct MortonPlan {
    s: u32,
    lb: Aabb,
    rb: Aabb,
    li: u32,
    ri: u32,
}

impl Default for MortonPlan {
    fn default() -> Self {
        MortonPlan {
            s: 0,
            lb: Aabb::EMPTY,
            rb: Aabb::EMPTY,
            li: NO_SPLIT,
            ri: NO_SPLIT,
        }
    }
}

/// Splits ranges where the radix tree does.
pub(crate) struct MortonSplitter<'a> {
    /// The radix tree.
    pub nodes: &'a [MNode],
}

impl Splitter for MortonSplitter<'_> {
    type Info = u32;
    type Plan = MortonPlan;

    fn plan(
        &self,
        refs: &[Ref],
        r: &Range<u32>,
        cost: &CostModel,
        _median: bool,
    ) -> (MortonPlan, f64) {
        let s = r.info;
        let node = &self.nodes[(s - 1) as usize];
        let (nl, nr) = (s - r.begin, r.end - s);
        let lb = if nl == 1 {
            refs[0].aabb()
        } else {
            self.nodes[(node.split_l - 1) as usize].bounds
        };
        let rb = if nr == 1 {
            refs[refs.len() - 1].aabb()
        } else {
            self.nodes[(node.split_r - 1) as usize].bounds
        };
        let cost_s = (half_area(&lb) * cost.blocks(nl) + half_area(&rb) * cost.blocks(nr))
            * inv_half_area(&r.bounds);
        (
            MortonPlan {
                s,
                lb,
                rb,
                li: node.split_l,
                ri: node.split_r,
            },
            cost_s,
        )
    }

    fn apply(&self, _refs: &mut [Ref], r: &Range<u32>, p: &MortonPlan) -> [Range<u32>; 2] {
        [
            Range {
                begin: r.begin,
                end: p.s,
                cap: p.s,
                bounds: p.lb,
                info: p.li,
            },
            Range {
                begin: p.s,
                end: r.end,
                cap: r.end,
                bounds: p.rb,
                info: p.ri,
            },
        ]
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn spread_interleaves() {
        assert_eq!(spread(0b1), 0b1);
        assert_eq!(spread(0b11), 0b1001);
        assert_eq!(spread(0x3ff), 0x0924_9249);
    }

    #[test]
    fn radix_sorts_by_code_then_index() {
        let mut keys: Vec<u64> = (0..5000u64)
            .map(|i| (((i * 7919) % 1_000_003) << 32 & 0x3fff_ffff_0000_0000) | i)
            .collect();
        let mut want = keys.clone();
        want.sort_unstable();
        radix_sort(&mut keys);
        assert_eq!(keys, want);
    }
}
