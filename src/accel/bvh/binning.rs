//! Binned SAH object splits (32 bins per axis over reference centroids), the median
//! fallback, and the [`SahSplitter`] that adds SBVH spatial splits ([`super::sbvh`]) on
//! top of them.
//!
//! Binning and partitioning classify a reference with the same f32 arithmetic
//! ([`BinMap::bin`]), so the counts the sweep saw are exactly the counts the partition
//! makes, and a split never leaves a side empty.

use rayon::prelude::*;

use super::build::{
    bounds_of, grow, half_area, intersect, inv_half_area, union, CostModel, Range, Ref, Splitter,
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

/// Maps a coordinate to one of [`BINS`] bins along each axis. Axes without extent get
/// scale 0 and put everything in bin 0 (the sweep then finds no split on them).
#[derive(Clone, Copy, Debug, Default)]
pub(crate) struct BinMap {
    /// Coordinate of the lower edge of bin 0.
    pub lo: [f32; 3],
    /// Bins per unit length.
    pub scale: [f32; 3],
    /// Bin width (spatial splits: the planes are `lo + i·width`).
    pub width: [f32; 3],
}

impl BinMap {
    /// Bins spanning `b`; `shrink` < 1 keeps the upper edge inside the last bin.
    pub fn new(b: &Aabb, shrink: f64) -> BinMap {
        let mut m = BinMap {
            lo: b.min,
            ..BinMap::default()
        };
        for a in 0..3 {
            let ext = b.max[a] as f64 - b.min[a] as f64;
            if ext > 0.0 && ext.is_finite() {
                let s = (BINS as f64 * shrink / ext) as f32;
                if s.is_finite() {
                    m.scale[a] = s;
                    m.width[a] = (ext / BINS as f64) as f32;
                }
            }
        }
        m
    }

    /// Bin of coordinate `x` along `axis`, clamped to the valid bins.
    #[inline(always)]
    pub fn bin(&self, x: f32, axis: usize) -> usize {
        let k = ((x - self.lo[axis]) * self.scale[axis]) as i32;
        k.clamp(0, BINS as i32 - 1) as usize
    }

    /// The plane between bins `i - 1` and `i` along `axis`.
    #[inline]
    pub fn plane(&self, axis: usize, i: usize) -> f32 {
        self.lo[axis] + i as f32 * self.width[axis]
    }
}

/// Per-bin boxes and reference counts along each axis. For object bins `enter` is the
/// count and `exit` is unused; for spatial bins (SBVH) a reference enters at the bin of
/// its lower corner and exits at the bin of its upper corner.
#[derive(Clone)]
pub(crate) struct Bins {
    /// Box of what fell in each bin.
    pub boxes: [[Aabb; BINS]; 3],
    /// References starting in each bin.
    pub enter: [[u32; BINS]; 3],
    /// References ending in each bin (spatial bins only).
    pub exit: [[u32; BINS]; 3],
}

impl Bins {
    /// Empty bins.
    pub fn new() -> Bins {
        Bins {
            boxes: [[Aabb::EMPTY; BINS]; 3],
            enter: [[0; BINS]; 3],
            exit: [[0; BINS]; 3],
        }
    }

    /// Adds bins `o` to these.
    pub fn merge(mut self, o: Bins) -> Bins {
        for a in 0..3 {
            for i in 0..BINS {
                self.boxes[a][i] = union(&self.boxes[a][i], &o.boxes[a][i]);
                self.enter[a][i] += o.enter[a][i];
                self.exit[a][i] += o.exit[a][i];
            }
        }
        self
    }

    /// Object binning of `refs` by centroid.
    fn add_objects(&mut self, refs: &[Ref], map: &BinMap) {
        for r in refs {
            for a in 0..3 {
                let k = map.bin(r.centroid(a), a);
                grow(&mut self.boxes[a][k], &r.lo, &r.hi);
                self.enter[a][k] += 1;
            }
        }
    }

    /// Box of bins `..i` and of bins `i..` along `axis`.
    pub fn halves(&self, axis: usize, i: usize) -> (Aabb, Aabb) {
        let mut l = Aabb::EMPTY;
        let mut r = Aabb::EMPTY;
        for (j, b) in self.boxes[axis].iter().enumerate() {
            if j < i {
                l = union(&l, b);
            } else {
                r = union(&r, b);
            }
        }
        (l, r)
    }
}

/// Object bins of `refs`, in parallel for long ranges.
fn object_bins(refs: &[Ref], map: &BinMap) -> Bins {
    if refs.len() < PAR_BIN {
        let mut b = Bins::new();
        b.add_objects(refs, map);
        return b;
    }
    refs.par_chunks(BIN_CHUNK)
        .fold(Bins::new, |mut b, c| {
            b.add_objects(c, map);
            b
        })
        .reduce(Bins::new, Bins::merge)
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
/// references on the left and `Σ exit[i..]` on the right.
pub(crate) fn sweep(
    boxes: &[Aabb; BINS],
    enter: &[u32; BINS],
    exit: &[u32; BINS],
    inv_area: f64,
    cost: &CostModel,
) -> Option<SweepBest> {
    let mut r_area = [0.0f64; BINS];
    let mut r_n = [0u32; BINS];
    let mut acc = Aabb::EMPTY;
    let mut n = 0;
    for i in (1..BINS).rev() {
        acc = union(&acc, &boxes[i]);
        n += exit[i];
        r_area[i] = half_area(&acc);
        r_n[i] = n;
    }
    let mut best: Option<SweepBest> = None;
    acc = Aabb::EMPTY;
    n = 0;
    for i in 1..BINS {
        acc = union(&acc, &boxes[i - 1]);
        n += enter[i - 1];
        if n == 0 || r_n[i] == 0 {
            continue;
        }
        let s = (half_area(&acc) * cost.blocks(n) + r_area[i] * cost.blocks(r_n[i])) * inv_area;
        if best.map_or(true, |b| s < b.s) {
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
        let map = BinMap::new(&r.info.0, 1.0 - 1e-6);
        let mut best: Option<(usize, SweepBest)> = None;
        let mut bins = None;
        if map.scale.iter().any(|&s| s > 0.0) {
            let b = object_bins(refs, &map);
            for a in 0..3 {
                if map.scale[a] == 0.0 {
                    continue;
                }
                if let Some(s) = sweep(&b.boxes[a], &b.enter[a], &b.enter[a], inv_area, cost) {
                    if best.map_or(true, |(_, o)| s.s < o.s) {
                        best = Some((a, s));
                    }
                }
            }
            bins = Some(b);
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
        if self.spatial && room > r.n() {
            let overlap = match (best, &bins) {
                (Some((a, s)), Some(b)) => {
                    let (l, rr) = b.halves(a, s.bin);
                    half_area(&intersect(&l, &rr))
                }
                _ => f64::INFINITY,
            };
            if overlap > self.min_overlap {
                if let Some((p, s)) = sbvh::spatial_plan(self.tris, refs, r, cost, inv_area, room) {
                    if out.map_or(true, |(_, so)| s < so) {
                        out = Some((p, s));
                    }
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
        let (mut nl, mut nr) = match *plan {
            SahPlan::Object { axis, bin, map } => {
                let (a, b) = (axis as usize, bin as usize);
                let nl = partition(&mut refs[..n], |x| map.bin(x.centroid(a), a) < b);
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
            SahPlan::Median => (0, 0),
        };
        if nl == 0 || nr == 0 {
            // Median (also the fallback should numerics ever empty a side).
            let a = widest(&r.info.0);
            let mid = n / 2;
            refs[..n].select_nth_unstable_by(mid, |x, y| x.centroid(a).total_cmp(&y.centroid(a)));
            (nl, nr) = (mid, n - mid);
        }
        finish(refs, r, nl, nr)
    }
}

/// Makes the two halves once the left references are at `..nl` and the right ones at
/// `nl..nl + nr`: shares the free room in proportion to the counts (moving the right
/// references up) and computes the halves' boxes.
fn finish(refs: &mut [Ref], r: &Range<Centroids>, nl: usize, nr: usize) -> [Range<Centroids>; 2] {
    let used = nl + nr;
    let slack = refs.len() - used;
    let sl = (slack as u64 * nl as u64 / used as u64) as usize;
    if sl > 0 {
        refs.copy_within(nl..used, nl + sl);
    }
    let (lb, lc) = bounds_of(&refs[..nl]);
    let (rb, rc) = bounds_of(&refs[nl + sl..nl + sl + nr]);
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
        let m = BinMap::new(&b, 1.0 - 1e-6);
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
        let map = BinMap::new(&cent, 1.0 - 1e-6);
        let bins = object_bins(&refs, &map);
        let cost = CostModel {
            width: 1,
            max_leaf: 8,
            k_t: 1.0,
            k_i: 1.0,
        };
        let s = sweep(
            &bins.boxes[0],
            &bins.enter[0],
            &bins.enter[0],
            inv_half_area(&bounds),
            &cost,
        )
        .unwrap();
        assert_eq!((s.nl, s.nr), (10, 10));
        // Far cheaper than the leaf (cost 20).
        assert!(s.s < 0.5, "{}", s.s);
    }
}
