//! Binned SAH object splits (32 bins per axis over reference centroids), the median
//! fallback, and the [`SahSplitter`] that adds SBVH spatial splits ([`super::sbvh`]) on
//! top of them.
//!
//! Binning and partitioning classify a reference with the same f32 arithmetic
//! ([`BinMap::bin`]), so the counts the sweep saw are exactly the counts the partition
//! makes, and a split never leaves a side empty.

use rayon::prelude::*;

use super::build::{
    bounds_of, fmax, fmin, half_area, intersect, inv_half_area, CostModel, Range, Ref, Splitter, B4,
};
use super::sbvh;
use crate::geometry::{Aabb, Triangle};

/// Bins per axis.
pub(crate) const BINS: usize = 32;

/// Ranges with at least this many references are binned in parallel.
const PAR_BIN: usize = 1 << 14;
/// References per parallel binning task.
const BIN_CHUNK: usize = 1 << 12;

/// Stich et al.'s α: spatial splits are tried when the best object split's children
/// overlap by more than this fraction of the root's surface area.
pub(crate) const SBVH_ALPHA: f64 = 1e-5;

/// Centroid bounds of a range (the binned splitters' per-range data).
#[derive(Clone, Copy, Debug)]
pub(crate) struct Centroids(pub Aabb);

impl Default for Centroids {
    fn default() -> Self {
        Centroids(Aabb::EMPTY)
    }
}

/// Maps a coordinate to one of a fixed number of bins along each axis. Axes without extent get
/// scale 0 and put everything in bin 0 (the sweep then finds no split on them).
#[derive(Clone, Copy, Debug, Default)]
pub(crate) struct BinMap {
    /// Coordinate of the lower edge of bin 0 (lane 3 unused, 0).
    pub lo: [f32; 4],
    /// Bins per unit length (lane 3 unused, 0).
    pub scale: [f32; 4],
    /// Bin width (spatial splits: the planes are `lo + i·width`).
    pub width: [f32; 3],
    /// Index of the last bin, as a float.
    pub last: f32,
}

impl BinMap {
    /// `bins` bins spanning `b`; `shrink` < 1 keeps the upper edge inside the last bin.
    pub fn new(b: &Aabb, bins: usize, shrink: f64) -> BinMap {
        let mut m = BinMap {
            lo: [b.min[0], b.min[1], b.min[2], 0.0],
            last: (bins - 1) as f32,
            ..BinMap::default()
        };
        for a in 0..3 {
            let ext = b.max[a] as f64 - b.min[a] as f64;
            if ext > 0.0 && ext.is_finite() {
                let s = (bins as f64 * shrink / ext) as f32;
                if s.is_finite() {
                    m.scale[a] = s;
                    m.width[a] = (ext / bins as f64) as f32;
                }
            }
        }
        m
    }

    /// Bin of coordinate `x` along `axis`, clamped to the valid bins.
    #[inline(always)]
    pub fn bin(&self, x: f32, axis: usize) -> usize {
        to_bin((x - self.lo[axis]) * self.scale[axis], self.last) as usize
    }

    /// Bins of a reference's centroid along the three axes: [`BinMap::bin`] of
    /// [`Ref::centroid`], computed on all lanes at once (the same IEEE operations per
    /// lane, so the results are identical).
    #[inline(always)]
    pub fn centroid_bins(&self, r: &Ref) -> [usize; 3] {
        let k = crate::simd::build4::centroid_bins(
            &r.lo,
            &r.hi,
            &self.lo,
            &self.scale,
            self.last,
            BINS as u32 - 1,
        );
        [k[0] as usize, k[1] as usize, k[2] as usize]
    }

    /// The largest centroid coordinate along `axis`, within the centroid bounds `cent`,
    /// whose bin is below `b` (1 ≤ `b` ≤ last bin). [`BinMap::bin`] is monotone, so
    /// `bin(c) < b` exactly when `c <= last_below(..)`: the partition compares one float
    /// instead of recomputing bins, and still agrees with the binning on every reference.
    /// Found by bisection over the ordered bit patterns of f32.
    pub fn last_below(&self, axis: usize, b: usize, cent: &Aabb) -> f32 {
        let (mut lo, mut hi) = (ordered(cent.min[axis]), ordered(cent.max[axis]));
        debug_assert!(self.bin(unordered(lo), axis) < b && self.bin(unordered(hi), axis) >= b);
        while hi - lo > 1 {
            let mid = lo + (hi - lo) / 2;
            if self.bin(unordered(mid), axis) < b {
                lo = mid;
            } else {
                hi = mid;
            }
        }
        unordered(lo)
    }

    /// The plane between bins `i - 1` and `i` along `axis`.
    #[inline]
    pub fn plane(&self, axis: usize, i: usize) -> f32 {
        self.lo[axis] + i as f32 * self.width[axis]
    }
}

/// Bin index of `f` (a coordinate in bin units from the lower edge): `⌊f⌋` clamped to
/// `0..=last` (at most `BINS - 1`), NaN to 0. Computed as round-to-nearest of `f − 0.5` through the f32
/// mantissa (adding 2^23 leaves the rounded integer in the low mantissa bits) instead of
/// a saturating float-to-int cast: this stays in vector registers when the compiler
/// does four lanes at once, and it is a monotone function of `f`, which is all binning
/// and partitioning need to agree.
#[inline(always)]
fn to_bin(f: f32, last: f32) -> u32 {
    let f = fmin(fmax(f - 0.5, 0.0), last);
    (f + 8_388_608.0).to_bits() & (BINS as u32 - 1)
}

/// Object bins: per-bin boxes and reference counts along each axis.
#[derive(Clone)]
pub(crate) struct ObjectBins {
    /// Box of the references whose centroid fell in each bin.
    pub boxes: [[B4; BINS]; 3],
    /// References per bin.
    pub count: [[u32; BINS]; 3],
}

impl ObjectBins {
    /// Empty bins.
    pub fn new() -> Self {
        ObjectBins {
            boxes: [[B4::EMPTY; BINS]; 3],
            count: [[0; BINS]; 3],
        }
    }

    /// Adds bins `o` to these.
    pub fn merge(mut self, o: Self) -> Self {
        for a in 0..3 {
            for i in 0..BINS {
                self.boxes[a][i].grow(&o.boxes[a][i]);
                self.count[a][i] += o.count[a][i];
            }
        }
        self
    }

    /// Bins `refs` by centroid.
    fn add(&mut self, refs: &[Ref], map: &BinMap) {
        if refs.len() < 256 {
            for r in refs {
                self.add_one(r, map);
            }
            return;
        }
        // Two sets of bins, alternating: consecutive references often land in the same
        // bin, and updating one bin twice in a row waits on the store of the first
        // update. Measured about twice as fast on long ranges.
        let mut other = ObjectBins::new();
        let mut pairs = refs.chunks_exact(2);
        for p in &mut pairs {
            self.add_one(&p[0], map);
            other.add_one(&p[1], map);
        }
        for r in pairs.remainder() {
            self.add_one(r, map);
        }
        *self = std::mem::replace(self, ObjectBins::new()).merge(other);
    }

    #[inline(always)]
    fn add_one(&mut self, r: &Ref, map: &BinMap) {
        let b = r.b4();
        let k = map.centroid_bins(r);
        for (a, &k) in k.iter().enumerate() {
            self.boxes[a][k].grow(&b);
            self.count[a][k] += 1;
        }
    }
}

/// Box of bins `..i` and of bins `i..`.
pub(crate) fn halves(boxes: &[B4], i: usize) -> (Aabb, Aabb) {
    let mut l = B4::EMPTY;
    let mut r = B4::EMPTY;
    for (j, b) in boxes.iter().enumerate() {
        if j < i {
            l.grow(b);
        } else {
            r.grow(b);
        }
    }
    (l.aabb(), r.aabb())
}

/// Half the surface area of a [`B4`] (f64, 0 when empty).
#[inline(always)]
pub(crate) fn half_area4(b: &B4) -> f64 {
    let e = [
        b.hi[0] as f64 - b.lo[0] as f64,
        b.hi[1] as f64 - b.lo[1] as f64,
        b.hi[2] as f64 - b.lo[2] as f64,
    ];
    if e[0] >= 0.0 && e[1] >= 0.0 && e[2] >= 0.0 {
        e[0] * e[1] + e[1] * e[2] + e[2] * e[0]
    } else {
        0.0
    }
}

/// Ranges of at most this many references are split by an exact SAH sweep over their
/// sorted centroids instead of bins: cheaper than clearing and sweeping 3 × 32 bins, and
/// exact. Most candidates are this small.
pub(crate) const SMALL: usize = 24;

/// Ranges of at most this many references (but more than [`SMALL`]) are binned with
/// `BINS / 2` bins: clearing and sweeping bins costs as much as binning them there.
const FEW: usize = 128;

/// The best split of a small range by an exact sweep: (cost S, left mask), where bit `i`
/// of the mask says that the reference at position `i` goes left.
fn exact_plan(refs: &[Ref], bounds: &Aabb, inv_area: f64, cost: &CostModel) -> Option<(f64, u32)> {
    if f32_areas(bounds) {
        exact_sweep::<true>(refs, inv_area, cost)
    } else {
        exact_sweep::<false>(refs, inv_area, cost)
    }
}

/// Whether areas of boxes inside `bounds` may be computed in f32: its size keeps them far
/// from overflow and underflow (nearly always; fewer instructions than f64). Otherwise
/// they are computed in f64.
fn f32_areas(bounds: &Aabb) -> bool {
    let e = bounds.extent();
    (1e-9..1e9).contains(&e[0].max(e[1]).max(e[2]))
}

/// Half the area of a non-empty box, in f32 (`F32`) or f64.
#[inline(always)]
fn area_of<const F32: bool>(b: &B4) -> f64 {
    if F32 {
        let e = crate::simd::build4::extent_xyz(&b.lo, &b.hi);
        (e[0] * e[1] + e[1] * e[2] + e[2] * e[0]) as f64
    } else {
        half_area4(b)
    }
}

fn exact_sweep<const F32: bool>(
    refs: &[Ref],
    inv_area: f64,
    cost: &CostModel,
) -> Option<(f64, u32)> {
    let n = refs.len();
    debug_assert!((2..=SMALL).contains(&n));
    let mut best: Option<(f64, usize, usize)> = None;
    let mut keys = [[0u64; SMALL]; 3];
    let mut r_area = [0.0f64; SMALL];
    for (a, keys) in keys.iter_mut().enumerate() {
        // Centroid in an order-preserving integer form, then position: a strict order.
        for (i, (k, r)) in keys.iter_mut().zip(refs).enumerate() {
            *k = ((ordered(r.centroid(a)) as u64) << 32) | i as u64;
        }
        let keys = &mut keys[..n];
        keys.sort_unstable();
        let at = |k: u64| refs[(k & 0xff) as usize].b4();
        let mut acc = B4::EMPTY;
        for k in (1..n).rev() {
            acc.grow(&at(keys[k]));
            r_area[k] = area_of::<F32>(&acc);
        }
        acc = B4::EMPTY;
        for k in 1..n {
            acc.grow(&at(keys[k - 1]));
            let s = (area_of::<F32>(&acc) * cost.blocks(k as u32)
                + r_area[k] * cost.blocks((n - k) as u32))
                * inv_area;
            if best.is_none_or(|b| s < b.0) {
                best = Some((s, a, k));
            }
        }
    }
    best.map(|(s, a, k)| {
        let mask = keys[a][..k]
            .iter()
            .fold(0u32, |m, &key| m | 1 << (key & 0xff));
        (s, mask)
    })
}

/// Maps an f32 to a u32 with the same order (for finite values).
#[inline(always)]
fn ordered(x: f32) -> u32 {
    let b = x.to_bits();
    if b >> 31 == 1 {
        !b
    } else {
        b | 1 << 31
    }
}

/// The inverse of [`ordered`].
#[inline(always)]
fn unordered(u: u32) -> f32 {
    f32::from_bits(if u >> 31 == 1 { u & !(1 << 31) } else { !u })
}

/// The cheapest split position along one axis.
#[derive(Clone, Copy, Debug)]
pub(crate) struct SweepBest {
    /// Bins `..bin` go left.
    pub bin: usize,
    /// Cost S of the split (normalised by the parent's area).
    pub s: f64,
    /// References on the left.
    pub nl: u32,
    /// References on the right.
    pub nr: u32,
}

/// Sweeps the bins of one axis: the split between bins `i-1` and `i` has `Σ enter[..i]`
/// references on the left and `Σ exit[i..]` on the right. `bounds` is the range's box
/// (it picks f32 or f64 areas, as [`exact_plan`] does).
pub(crate) fn sweep(
    boxes: &[B4],
    enter: &[u32],
    exit: &[u32],
    bounds: &Aabb,
    inv_area: f64,
    cost: &CostModel,
) -> Option<SweepBest> {
    if f32_areas(bounds) {
        sweep_with::<true>(boxes, enter, exit, inv_area, cost)
    } else {
        sweep_with::<false>(boxes, enter, exit, inv_area, cost)
    }
}

fn sweep_with<const F32: bool>(
    boxes: &[B4],
    enter: &[u32],
    exit: &[u32],
    inv_area: f64,
    cost: &CostModel,
) -> Option<SweepBest> {
    let bins = boxes.len();
    debug_assert!(bins <= BINS && enter.len() == bins && exit.len() == bins);
    let mut r_area = [0.0f64; BINS];
    let mut r_n = [0u32; BINS];
    let mut acc = B4::EMPTY;
    let mut n = 0;
    for i in (1..bins).rev() {
        acc.grow(&boxes[i]);
        n += exit[i];
        r_n[i] = n;
        if n > 0 {
            r_area[i] = area_of::<F32>(&acc);
        }
    }
    let mut best: Option<SweepBest> = None;
    acc = B4::EMPTY;
    n = 0;
    for i in 1..bins {
        acc.grow(&boxes[i - 1]);
        n += enter[i - 1];
        if n == 0 || r_n[i] == 0 {
            continue;
        }
        let s =
            (area_of::<F32>(&acc) * cost.blocks(n) + r_area[i] * cost.blocks(r_n[i])) * inv_area;
        if best.is_none_or(|b| s < b.s) {
            best = Some(SweepBest {
                bin: i,
                s,
                nl: n,
                nr: r_n[i],
            });
        }
    }
    best
}

/// Hoare partition of `refs` by `left`; returns how many went left (they come first).
pub(crate) fn partition(refs: &mut [Ref], left: impl Fn(&Ref) -> bool) -> usize {
    let mut i = 0;
    let mut j = refs.len();
    loop {
        while i < j && left(&refs[i]) {
            i += 1;
        }
        while i < j && !left(&refs[j - 1]) {
            j -= 1;
        }
        if i >= j {
            return i;
        }
        refs.swap(i, j - 1);
        i += 1;
        j -= 1;
    }
}

/// A split chosen for a range.
#[derive(Clone, Copy, Debug, Default)]
pub(crate) enum SahPlan {
    /// Median of the centroids along the widest centroid axis (identical centroids, or
    /// the depth guard).
    #[default]
    Median,
    /// Exact split of a small range: the references at the positions whose bit is set
    /// go left.
    Exact {
        /// Bit `i` set: the reference at position `i` goes left.
        mask: u32,
    },
    /// Object split: references whose centroid bin is below `bin` go left.
    Object {
        /// Split axis.
        axis: u8,
        /// First bin of the right side.
        bin: u8,
        /// The bins.
        map: BinMap,
    },
    /// Spatial split at the plane before spatial bin `bin` (SBVH).
    Spatial {
        /// Split axis.
        axis: u8,
        /// First bin of the right side.
        bin: u8,
        /// The spatial bins.
        map: BinMap,
        /// Box of the left side (for reference unsplitting).
        lbox: Aabb,
        /// Box of the right side.
        rbox: Aabb,
        /// References on the left, duplicates included.
        nl: u32,
        /// References on the right, duplicates included.
        nr: u32,
    },
}

/// Binned SAH object splits, with SBVH spatial splits when `spatial`.
pub(crate) struct SahSplitter<'a> {
    /// The scene (spatial splits clip triangles).
    pub tris: &'a [Triangle],
    /// Whether spatial splits are tried.
    pub spatial: bool,
    /// Overlap (half area) above which spatial splits are tried: α · root half-area.
    pub min_overlap: f64,
}

impl<'a> SahSplitter<'a> {
    /// A splitter for a scene whose references span `root`.
    pub fn new(tris: &'a [Triangle], spatial: bool, root: &Aabb) -> Self {
        SahSplitter {
            tris,
            spatial,
            min_overlap: SBVH_ALPHA * half_area(root),
        }
    }
}

/// The widest axis of `b`.
fn widest(b: &Aabb) -> usize {
    let e = b.extent();
    if e[0] >= e[1] && e[0] >= e[2] {
        0
    } else if e[1] >= e[2] {
        1
    } else {
        2
    }
}

/// A plan that is only taken when forced: costs nothing to compute, cost S = f64::MAX.
const FORCED_ONLY: f64 = f64::MAX;

impl Splitter for SahSplitter<'_> {
    type Info = Centroids;
    type Plan = SahPlan;

    fn plan(
        &self,
        refs: &[Ref],
        r: &Range<Centroids>,
        cost: &CostModel,
        median: bool,
    ) -> (SahPlan, f64) {
        if median {
            return (SahPlan::Median, FORCED_ONLY);
        }
        let inv_area = inv_half_area(&r.bounds);
        if refs.len() <= SMALL {
            return match exact_plan(refs, &r.bounds, inv_area, cost) {
                Some((s, mask)) => (SahPlan::Exact { mask }, s),
                None => (SahPlan::Median, FORCED_ONLY),
            };
        }
        let bins = if refs.len() <= FEW { BINS / 2 } else { BINS };
        let map = BinMap::new(&r.info.0, bins, 1.0 - 1e-6);
        let mut best: Option<(usize, SweepBest)> = None;
        let mut overlap = f64::INFINITY;
        if map.scale.iter().any(|&s| s > 0.0) {
            let mut serial;
            let parallel;
            let b = if refs.len() < PAR_BIN {
                serial = ObjectBins::new();
                serial.add(refs, &map);
                &serial
            } else {
                parallel = refs
                    .par_chunks(BIN_CHUNK)
                    .fold(ObjectBins::new, |mut b, c| {
                        b.add(c, &map);
                        b
                    })
                    .reduce(ObjectBins::new, ObjectBins::merge);
                &parallel
            };
            for a in 0..3 {
                if map.scale[a] == 0.0 {
                    continue;
                }
                if let Some(s) = sweep(
                    &b.boxes[a][..bins],
                    &b.count[a][..bins],
                    &b.count[a][..bins],
                    &r.bounds,
                    inv_area,
                    cost,
                ) {
                    if best.is_none_or(|(_, o)| s.s < o.s) {
                        best = Some((a, s));
                    }
                }
            }
            if let Some((a, s)) = best {
                let (l, rr) = halves(&b.boxes[a][..bins], s.bin);
                overlap = half_area(&intersect(&l, &rr));
            }
        }
        let mut out = best.map(|(a, s)| {
            (
                SahPlan::Object {
                    axis: a as u8,
                    bin: s.bin as u8,
                    map,
                },
                s.s,
            )
        });
        let room = r.cap - r.begin;
        if self.spatial && room > r.n() && overlap > self.min_overlap {
            if let Some((p, s)) = sbvh::spatial_plan(self.tris, refs, r, cost, inv_area, room) {
                if out.is_none_or(|(_, so)| s < so) {
                    out = Some((p, s));
                }
            }
        }
        out.unwrap_or((SahPlan::Median, FORCED_ONLY))
    }

    fn apply(
        &self,
        refs: &mut [Ref],
        r: &Range<Centroids>,
        plan: &SahPlan,
    ) -> [Range<Centroids>; 2] {
        let n = r.n() as usize;
        let mut bounds = None;
        let (mut nl, mut nr) = match *plan {
            SahPlan::Object { axis, bin, map } => {
                let (a, b) = (axis as usize, bin as usize);
                let t = map.last_below(a, b, &r.info.0);
                let (nl, bx) = partition_bounds::<true>(&mut refs[..n], |x| x.centroid(a) <= t);
                bounds = Some(bx);
                (nl, n - nl)
            }
            SahPlan::Spatial {
                axis,
                bin,
                map,
                lbox,
                rbox,
                nl,
                nr,
            } => sbvh::apply_spatial(
                self.tris,
                refs,
                n,
                axis as usize,
                bin as usize,
                &map,
                (lbox, rbox),
                (nl, nr),
            ),
            SahPlan::Exact { mask } => {
                for (i, r) in refs[..n].iter_mut().enumerate() {
                    r.set_aux((mask >> i) & 1);
                }
                let (nl, bx) = partition_bounds::<false>(&mut refs[..n], |x| x.aux() == 1);
                bounds = Some(bx);
                (nl, n - nl)
            }
            SahPlan::Median => (0, 0),
        };
        if nl == 0 || nr == 0 {
            // Median (also the fallback should numerics ever empty a side).
            let a = widest(&r.info.0);
            let mid = n / 2;
            refs[..n].select_nth_unstable_by(mid, |x, y| x.centroid(a).total_cmp(&y.centroid(a)));
            (nl, nr) = (mid, n - mid);
            bounds = None;
        }
        finish(refs, r, nl, nr, bounds)
    }
}

/// Box and centroid box of the left and of the right side of a partition.
type SideBounds = [(Aabb, Aabb); 2];

/// [`partition`] that also returns the boxes and centroid boxes of both sides, gathered
/// in the same pass (each reference is looked at once).
/// `CENT = false` skips the centroid boxes (left empty): ranges of at most [`SMALL`]
/// references never bin, so their halves do not need them.
fn partition_bounds<const CENT: bool>(
    refs: &mut [Ref],
    left: impl Fn(&Ref) -> bool,
) -> (usize, SideBounds) {
    // One accumulator per side and kind, as plain locals: indexing an array of them by
    // side kept them in memory (a load and a store per reference).
    let (mut lb, mut lc, mut rb, mut rc) = (B4::EMPTY, B4::EMPTY, B4::EMPTY, B4::EMPTY);
    #[inline(always)]
    fn add<const CENT: bool>(b: &mut B4, c: &mut B4, r: &Ref) {
        b.grow(&r.b4());
        if CENT {
            c.grow_centroid(r);
        }
    }
    let mut i = 0;
    let mut j = refs.len();
    loop {
        while i < j && left(&refs[i]) {
            add::<CENT>(&mut lb, &mut lc, &refs[i]);
            i += 1;
        }
        while i < j && !left(&refs[j - 1]) {
            add::<CENT>(&mut rb, &mut rc, &refs[j - 1]);
            j -= 1;
        }
        if i >= j {
            break;
        }
        refs.swap(i, j - 1);
        add::<CENT>(&mut lb, &mut lc, &refs[i]);
        add::<CENT>(&mut rb, &mut rc, &refs[j - 1]);
        i += 1;
        j -= 1;
    }
    (i, [(lb.aabb(), lc.aabb()), (rb.aabb(), rc.aabb())])
}

/// Makes the two halves once the left references are at `..nl` and the right ones at
/// `nl..nl + nr`: shares the free room in proportion to the counts (moving the right
/// references up) and computes the halves' boxes.
fn finish(
    refs: &mut [Ref],
    r: &Range<Centroids>,
    nl: usize,
    nr: usize,
    bounds: Option<SideBounds>,
) -> [Range<Centroids>; 2] {
    let used = nl + nr;
    let slack = refs.len() - used;
    let sl = (slack as u64 * nl as u64 / used as u64) as usize;
    if sl > 0 {
        refs.copy_within(nl..used, nl + sl);
    }
    let [(lb, lc), (rb, rc)] = bounds.unwrap_or_else(|| {
        [
            bounds_of(&refs[..nl]),
            bounds_of(&refs[nl + sl..nl + sl + nr]),
        ]
    });
    let mid = r.begin + (nl + sl) as u32;
    [
        Range {
            begin: r.begin,
            end: r.begin + nl as u32,
            cap: mid,
            bounds: lb,
            info: Centroids(lc),
        },
        Range {
            begin: mid,
            end: mid + nr as u32,
            cap: r.cap,
            bounds: rb,
            info: Centroids(rc),
        },
    ]
}

#[cfg(test)]
mod tests {
    use super::*;

    fn r(lo: [f32; 3], hi: [f32; 3]) -> Ref {
        Ref::new(0, &Aabb { min: lo, max: hi })
    }

    #[test]
    fn bins_cover_the_range_and_clamp() {
        let b = Aabb {
            min: [0.0, -1e30, 5.0],
            max: [1.0, 1e30, 5.0],
        };
        let m = BinMap::new(&b, BINS, 1.0 - 1e-6);
        assert_eq!(m.bin(0.0, 0), 0);
        assert_eq!(m.bin(1.0, 0), BINS - 1);
        assert_eq!(m.bin(-1e30, 1), 0);
        assert_eq!(m.bin(1e30, 1), BINS - 1);
        // The shrink factor puts the midpoint just below bin 16.
        assert_eq!(m.bin(0.0, 1), BINS / 2 - 1);
        // Flat axis: everything in bin 0.
        assert_eq!(m.scale[2], 0.0);
        assert_eq!(m.bin(5.0, 2), 0);
        // Out of range and NaN clamp.
        assert_eq!(m.bin(-5.0, 0), 0);
        assert_eq!(m.bin(f32::INFINITY, 0), BINS - 1);
        assert_eq!(m.bin(f32::NAN, 0), 0);
    }

    #[test]
    fn last_below_matches_the_bins() {
        let b = Aabb {
            min: [-3.0, 0.001, -1e20],
            max: [7.0, 0.002, 1e25],
        };
        let m = BinMap::new(&b, BINS, 1.0 - 1e-6);
        assert_eq!(unordered(ordered(-2.5)), -2.5);
        assert_eq!(unordered(ordered(0.0)), 0.0);
        for a in 0..3 {
            for bin in 1..BINS {
                let t = m.last_below(a, bin, &b);
                assert!(m.bin(t, a) < bin);
                let next = unordered(ordered(t) + 1);
                assert!(m.bin(next, a) >= bin, "axis {a} bin {bin}");
            }
        }
    }

    #[test]
    fn partition_is_stable_in_counts() {
        let mut refs: Vec<Ref> = (0..100)
            .map(|i| {
                let x = ((i * 37) % 100) as f32;
                r([x, 0.0, 0.0], [x + 1.0, 1.0, 1.0])
            })
            .collect();
        let nl = partition(&mut refs, |x| x.lo[0] < 30.0);
        assert_eq!(nl, 30);
        assert!(refs[..nl].iter().all(|x| x.lo[0] < 30.0));
        assert!(refs[nl..].iter().all(|x| x.lo[0] >= 30.0));
    }

    #[test]
    fn sweep_finds_the_gap() {
        // Two clusters: the split must fall between them.
        let mut refs = Vec::new();
        for i in 0..10 {
            let x = i as f32 * 0.01;
            refs.push(r([x, 0.0, 0.0], [x + 0.01, 0.01, 0.01]));
            refs.push(r([x + 10.0, 0.0, 0.0], [x + 10.01, 0.01, 0.01]));
        }
        let (bounds, cent) = bounds_of(&refs);
        let map = BinMap::new(&cent, BINS, 1.0 - 1e-6);
        let mut bins = ObjectBins::new();
        bins.add(&refs, &map);
        let cost = CostModel::new(1, 8, 1.0, 1.0);
        let s = sweep(
            &bins.boxes[0],
            &bins.count[0],
            &bins.count[0],
            &bounds,
            inv_half_area(&bounds),
            &cost,
        )
        .unwrap();
        assert_eq!((s.nl, s.nr), (10, 10));
        // Far cheaper than the leaf (cost 20).
        assert!(s.s < 0.5, "{}", s.s);
    }
}
