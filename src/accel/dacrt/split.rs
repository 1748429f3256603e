//! Triangle partitioning (Áfra 2012 §3.2; Nabata et al. 2013 §4.2): the two children of a
//! node are made by partitioning its slice of the id array in place.
//!
//! Both methods split the *centroids of the triangle boxes* on the axis where the node's
//! centroid box is widest, and both compute each child's box and centroid box while they
//! sweep, so that no later pass over the triangles is needed:
//!
//! - **middle**: at the centre of the centroid box; one pass.
//! - **binned**: 32 bins (Wald 2007); one pass fills the bins, a sweep over the 31 planes
//!   picks one — by the surface-area heuristic, or by Nabata's sampled cost (eq. 2) where
//!   the hit probabilities of the candidate boxes are measured with sample rays (see
//!   `sampling.rs`) — and a second pass partitions.

use crate::geometry::Aabb;

use super::tris::TriBox;
use crate::simd::{self, FloatV, Kernel, Simd};

/// Number of bins of the binned splits (Áfra: 32).
pub const BINS: usize = 32;

/// Candidates of one binning: the `BINS - 1` planes and the size candidate.
pub const CANDIDATES: usize = BINS;

/// What a traversal step knows about a set of triangles.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Node {
    /// Union of the triangles' boxes.
    pub bounds: Aabb,
    /// Bounds of the triangles' box centroids.
    pub cents: Aabb,
}

/// A partition: `ids[..mid]` went left, `ids[mid..]` right.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Parts {
    /// Number of triangles on the left.
    pub mid: usize,
    /// The left child.
    pub left: Node,
    /// The right child.
    pub right: Node,
}

/// The axis of the widest centroid extent and that extent.
pub fn split_axis(cents: &Aabb) -> (usize, f32) {
    let e = cents.extent();
    let axis = if e[0] >= e[1] && e[0] >= e[2] {
        0
    } else if e[1] >= e[2] {
        1
    } else {
        2
    };
    (axis, e[axis])
}

/// Running bounds of one side of a partition: the triangle boxes' union and their
/// centroids' bounds.
#[derive(Clone, Copy, Debug)]
pub struct Acc {
    lo: [f32; 4],
    hi: [f32; 4],
    clo: [f32; 4],
    chi: [f32; 4],
}

impl Acc {
    /// Nothing yet.
    pub const EMPTY: Acc = Acc {
        lo: [f32::INFINITY; 4],
        hi: [f32::NEG_INFINITY; 4],
        clo: [f32::INFINITY; 4],
        chi: [f32::NEG_INFINITY; 4],
    };

    /// Adds one triangle box.
    #[inline(always)]
    pub fn add(&mut self, b: &TriBox) {
        for k in 0..4 {
            let c = 0.5 * b.min[k] + 0.5 * b.max[k];
            self.lo[k] = self.lo[k].min(b.min[k]);
            self.hi[k] = self.hi[k].max(b.max[k]);
            self.clo[k] = self.clo[k].min(c);
            self.chi[k] = self.chi[k].max(c);
        }
    }

    /// Adds another accumulator.
    #[inline(always)]
    pub fn merge(&mut self, o: &Acc) {
        for k in 0..4 {
            self.lo[k] = self.lo[k].min(o.lo[k]);
            self.hi[k] = self.hi[k].max(o.hi[k]);
            self.clo[k] = self.clo[k].min(o.clo[k]);
            self.chi[k] = self.chi[k].max(o.chi[k]);
        }
    }

    fn bounds(&self) -> Aabb {
        Aabb {
            min: [self.lo[0], self.lo[1], self.lo[2]],
            max: [self.hi[0], self.hi[1], self.hi[2]],
        }
    }

    /// The node these bounds describe.
    pub fn node(&self) -> Node {
        Node {
            bounds: self.bounds(),
            cents: Aabb {
                min: [self.clo[0], self.clo[1], self.clo[2]],
                max: [self.chi[0], self.chi[1], self.chi[2]],
            },
        }
    }
}

/// [`Acc`] in 4-wide registers: a triangle box is one vector per corner.
struct AccV<S: Simd> {
    lo: S::F4,
    hi: S::F4,
    clo: S::F4,
    chi: S::F4,
}

impl<S: Simd> AccV<S> {
    #[inline(always)]
    fn load(s: S, a: &Acc) -> Self {
        AccV {
            lo: s.load_f4(&a.lo),
            hi: s.load_f4(&a.hi),
            clo: s.load_f4(&a.clo),
            chi: s.load_f4(&a.chi),
        }
    }

    /// Adds one box: the same arithmetic as [`Acc::add`] (the centroid is
    /// `0.5·min + 0.5·max`, and coordinates are never NaN, so the layer's min/max agree
    /// with `f32::min`/`max`).
    #[inline(always)]
    fn add(&mut self, s: S, half: S::F4, b: &TriBox) {
        let (mn, mx) = (s.load_f4(&b.min), s.load_f4(&b.max));
        let c = half * mn + half * mx;
        self.lo = self.lo.min(mn);
        self.hi = self.hi.max(mx);
        self.clo = self.clo.min(c);
        self.chi = self.chi.max(c);
    }

    #[inline(always)]
    fn store(&self) -> Acc {
        let a = |v: S::F4| -> [f32; 4] { v.to_array() };
        Acc {
            lo: a(self.lo),
            hi: a(self.hi),
            clo: a(self.clo),
            chi: a(self.chi),
        }
    }
}

/// The partition as a SIMD kernel (the box accumulation is what is vectorised).
struct PartitionK<'a, F> {
    boxes: &'a [TriBox],
    ids: &'a mut [u32],
    left: F,
}

impl<F: Fn(&TriBox) -> bool> Kernel for PartitionK<'_, F> {
    type Output = (usize, Acc, Acc);

    #[inline(always)]
    fn run<S: Simd>(self, s: S) -> Self::Output {
        let half = s.splat_f4(0.5);
        let mut l = AccV::load(s, &Acc::EMPTY);
        let mut r = AccV::load(s, &Acc::EMPTY);
        let ids = self.ids;
        let mut w = 0;
        for i in 0..ids.len() {
            let id = ids[i];
            let b = &self.boxes[id as usize];
            if (self.left)(b) {
                l.add(s, half, b);
                ids[i] = ids[w];
                ids[w] = id;
                w += 1;
            } else {
                r.add(s, half, b);
            }
        }
        (w, l.store(), r.store())
    }
}

/// Partitions `ids` in place by `left(box)` (those first), accumulating both sides' boxes;
/// returns the size of the left side and both accumulators.
#[inline(always)]
pub fn partition_acc(
    boxes: &[TriBox],
    ids: &mut [u32],
    left: impl Fn(&TriBox) -> bool,
) -> (usize, Acc, Acc) {
    simd::dispatch(simd::selected(), PartitionK { boxes, ids, left })
}

/// Filling bins as a SIMD kernel.
struct FillK<'a> {
    bins: &'a mut Bins,
    boxes: &'a [TriBox],
    ids: &'a [u32],
}

impl Kernel for FillK<'_> {
    type Output = ();

    #[inline(always)]
    fn run<S: Simd>(self, s: S) {
        let half = s.splat_f4(0.5);
        let bins = self.bins;
        let sized = bins.big_thr.is_finite();
        let mut big = AccV::load(s, &bins.big.0);
        let mut small = AccV::load(s, &bins.small.0);
        for &id in self.ids {
            let b = &self.boxes[id as usize];
            let k = bins.bin(b);
            let mut a = AccV::load(s, &bins.acc[k]);
            a.add(s, half, b);
            bins.acc[k] = a.store();
            bins.count[k] += 1;
            if sized {
                if bins.is_big(b) {
                    big.add(s, half, b);
                    bins.big.1 += 1;
                } else {
                    small.add(s, half, b);
                    bins.small.1 += 1;
                }
            }
        }
        bins.big.0 = big.store();
        bins.small.0 = small.store();
    }
}

#[inline(always)]
fn partition_by(boxes: &[TriBox], ids: &mut [u32], left: impl Fn(&TriBox) -> bool) -> Parts {
    let (mid, l, r) = partition_acc(boxes, ids, left);
    Parts {
        mid,
        left: l.node(),
        right: r.node(),
    }
}

/// The middle plane of a node: axis, pivot, and whether the comparison is `<=` (when the
/// centre rounds onto the lower end). `None` when the centroids all coincide.
pub fn middle_plane(node: &Node) -> Option<(usize, f32, bool)> {
    let (axis, extent) = split_axis(&node.cents);
    if extent.is_nan() || extent <= 0.0 {
        return None;
    }
    let (lo, hi) = (node.cents.min[axis], node.cents.max[axis]);
    let pivot = 0.5 * lo + 0.5 * hi;
    Some((axis, pivot, pivot == lo))
}

/// Middle partitioning: splits the centroid box at its centre on its widest axis. `None` when
/// the centroids all coincide (nothing to split).
pub fn middle(boxes: &[TriBox], ids: &mut [u32], node: &Node) -> Option<Parts> {
    let (axis, pivot, le) = middle_plane(node)?;
    // With adjacent floats the centre may round onto the lower end; then "<=" still separates.
    let p = if le {
        partition_by(boxes, ids, |b| b.centroid(axis) <= pivot)
    } else {
        partition_by(boxes, ids, |b| b.centroid(axis) < pivot)
    };
    (p.mid > 0 && p.mid < ids.len()).then_some(p)
}

/// The binning of one node: per bin, the boxes and count of the triangles whose centroid
/// falls in it.
pub struct Bins {
    axis: usize,
    lo: f32,
    scale: f32,
    acc: [Acc; BINS],
    count: [u32; BINS],
    /// Half-area above which a triangle box counts as big (`+inf`: no size candidate).
    big_thr: f32,
    /// The big triangles' bounds and count, and the others'.
    big: (Acc, u32),
    small: (Acc, u32),
}

/// Half the surface area of a triangle box.
#[inline(always)]
fn half_area(b: &TriBox) -> f32 {
    let (x, y, z) = (
        b.max[0] - b.min[0],
        b.max[1] - b.min[1],
        b.max[2] - b.min[2],
    );
    x * y + y * z + z * x
}

impl Bins {
    /// The bin of a triangle box.
    #[inline(always)]
    pub fn bin(&self, b: &TriBox) -> usize {
        let x = (b.centroid(self.axis) - self.lo) * self.scale;
        // `as` saturates (and maps NaN to 0), so the clamp keeps every value in range.
        (x as i32).clamp(0, BINS as i32 - 1) as usize
    }

    /// Empty bins over the node's centroid box on its widest axis. `None` when the
    /// centroids all coincide.
    pub fn empty(node: &Node) -> Option<Bins> {
        Bins::empty_on(node, split_axis(&node.cents).0, 0.0)
    }

    /// Empty bins over the node's centroid box on `axis`. `None` when the centroids all
    /// coincide on that axis. With `big > 0`, one more candidate separates the triangles
    /// whose box has more than `big` times the node's surface area from the others: a
    /// centroid plane cannot isolate a few huge triangles (a room's walls) from many small
    /// ones, and until they are isolated every box that holds one is as big as they are.
    pub fn empty_on(node: &Node, axis: usize, big: f32) -> Option<Bins> {
        let extent = node.cents.max[axis] - node.cents.min[axis];
        if extent.is_nan() || extent <= 0.0 {
            return None;
        }
        Some(Bins {
            axis,
            lo: node.cents.min[axis],
            scale: BINS as f32 * (1.0 - 1.0 / 65536.0) / extent,
            acc: [Acc::EMPTY; BINS],
            count: [0; BINS],
            big_thr: if big > 0.0 {
                0.5 * big * node.bounds.area()
            } else {
                f32::INFINITY
            },
            big: (Acc::EMPTY, 0),
            small: (Acc::EMPTY, 0),
        })
    }

    /// Whether a triangle box counts as big for the size candidate.
    #[inline(always)]
    pub fn is_big(&self, b: &TriBox) -> bool {
        half_area(b) > self.big_thr
    }

    /// Adds the triangles `ids`.
    pub fn fill(&mut self, boxes: &[TriBox], ids: &[u32]) {
        simd::dispatch(
            simd::selected(),
            FillK {
                bins: self,
                boxes,
                ids,
            },
        );
    }

    /// Adds another binning of the same node.
    pub fn merge(&mut self, o: &Bins) {
        for k in 0..BINS {
            self.acc[k].merge(&o.acc[k]);
            self.count[k] += o.count[k];
        }
        self.big.0.merge(&o.big.0);
        self.big.1 += o.big.1;
        self.small.0.merge(&o.small.0);
        self.small.1 += o.small.1;
    }

    /// Bins `ids` on `axis` (see [`Bins::empty_on`] for `big`). `None` when the centroids
    /// all coincide on it.
    pub fn new(boxes: &[TriBox], ids: &[u32], node: &Node, axis: usize, big: f32) -> Option<Bins> {
        let mut bins = Bins::empty_on(node, axis, big)?;
        bins.fill(boxes, ids);
        Some(bins)
    }

    /// [`CANDIDATES`] candidates: for each plane `j < BINS - 1` (between bin `j` and
    /// `j+1`) the left and right boxes and counts, then the size candidate (big triangles
    /// left; empty when there is none).
    pub fn candidates(&self) -> Vec<Candidate> {
        let mut out = Vec::with_capacity(CANDIDATES);
        self.candidates_into(&mut out);
        out
    }

    /// [`Bins::candidates`], appended to `out`.
    pub fn candidates_into(&self, out: &mut Vec<Candidate>) {
        let mut right = [Acc::EMPTY; BINS];
        let mut rc = [0u32; BINS];
        let mut a = Acc::EMPTY;
        let mut c = 0;
        for j in (1..BINS).rev() {
            a.merge(&self.acc[j]);
            c += self.count[j];
            right[j] = a;
            rc[j] = c;
        }
        let mut l = Acc::EMPTY;
        let mut lc = 0;
        for j in 0..BINS - 1 {
            l.merge(&self.acc[j]);
            lc += self.count[j];
            out.push(Candidate {
                left: l.bounds(),
                right: right[j + 1].bounds(),
                n_left: lc as usize,
                n_right: rc[j + 1] as usize,
            });
        }
        out.push(Candidate {
            left: self.big.0.bounds(),
            right: self.small.0.bounds(),
            n_left: self.big.1 as usize,
            n_right: self.small.1 as usize,
        });
    }

    /// Whether candidate `j` sends box `b` left.
    #[inline(always)]
    pub fn goes_left(&self, j: usize, b: &TriBox) -> bool {
        if j == BINS - 1 {
            self.is_big(b)
        } else {
            self.bin(b) <= j
        }
    }

    /// Partitions `ids` by candidate `j`.
    pub fn partition(&self, boxes: &[TriBox], ids: &mut [u32], j: usize) -> Parts {
        if j == BINS - 1 {
            partition_by(boxes, ids, |b| self.is_big(b))
        } else {
            partition_by(boxes, ids, |b| self.bin(b) <= j)
        }
    }
}

/// One candidate plane of a binning.
#[derive(Clone, Copy, Debug)]
pub struct Candidate {
    /// Union of the left triangles' boxes.
    pub left: Aabb,
    /// Union of the right triangles' boxes.
    pub right: Aabb,
    /// Triangles on the left.
    pub n_left: usize,
    /// Triangles on the right.
    pub n_right: usize,
}

/// The SAH choice among `cands`: the plane minimising `A_L·N_L + A_R·N_R`, and that cost
/// divided by the parent's area (so `C_T + cost` compares with the leaf cost `N`).
pub fn sah(cands: &[Candidate], parent: &Aabb) -> Option<(usize, f32)> {
    let pa = parent.area();
    let mut best: Option<(usize, f32)> = None;
    for (j, c) in cands.iter().enumerate() {
        if c.n_left == 0 || c.n_right == 0 {
            continue;
        }
        let cost = c.left.area() * c.n_left as f32 + c.right.area() * c.n_right as f32;
        if best.is_none_or(|(_, b)| cost < b) {
            best = Some((j, cost));
        }
    }
    best.map(|(j, c)| (j, if pa > 0.0 { c / pa } else { c }))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::accel::dacrt::tris::encode;
    use crate::geometry::Triangle;

    fn tri_at(x: f32) -> Triangle {
        Triangle {
            v: [[x, 0.0, 0.0], [x + 0.5, 0.0, 0.0], [x, 0.5, 0.0]],
        }
    }

    fn setup(xs: &[f32]) -> (Vec<TriBox>, Vec<u32>, Node) {
        let boxes: Vec<TriBox> = xs.iter().map(|&x| encode(&tri_at(x)).0).collect();
        let mut bounds = Aabb::EMPTY;
        let mut cents = Aabb::EMPTY;
        for b in &boxes {
            bounds.grow([b.min[0], b.min[1], b.min[2]]);
            bounds.grow([b.max[0], b.max[1], b.max[2]]);
            cents.grow([b.centroid(0), b.centroid(1), b.centroid(2)]);
        }
        let ids = (0..boxes.len() as u32).collect();
        (boxes, ids, Node { bounds, cents })
    }

    #[test]
    fn middle_splits_and_bounds_children() {
        let (boxes, mut ids, node) = setup(&[0.0, 10.0, 1.0, 9.0, 2.0]);
        let p = middle(&boxes, &mut ids, &node).unwrap();
        assert_eq!(p.mid, 3);
        let mut l = ids[..3].to_vec();
        l.sort();
        assert_eq!(l, vec![0, 2, 4]);
        assert_eq!(p.left.bounds.max[0], 2.5);
        assert_eq!(p.right.bounds.min[0], 9.0);
        assert_eq!(p.right.cents.min[0], 9.25);
    }

    #[test]
    fn coincident_centroids_do_not_split() {
        let (boxes, mut ids, node) = setup(&[1.0, 1.0, 1.0]);
        assert!(middle(&boxes, &mut ids, &node).is_none());
        assert!(Bins::new(&boxes, &ids, &node, 0, 0.0).is_none());
    }

    #[test]
    fn adjacent_floats_still_split() {
        let a = 1.0f32;
        let b = f32::from_bits(a.to_bits() + 1);
        let (boxes, mut ids, node) = setup(&[a, b]);
        let p = middle(&boxes, &mut ids, &node).unwrap();
        assert_eq!(p.mid, 1);
    }

    #[test]
    fn sah_separates_clusters() {
        let xs: Vec<f32> = (0..20)
            .map(|i| {
                if i < 10 {
                    i as f32 * 0.01
                } else {
                    100.0 + i as f32 * 0.01
                }
            })
            .collect();
        let (boxes, mut ids, node) = setup(&xs);
        let bins = Bins::new(&boxes, &ids, &node, 0, 0.0).unwrap();
        let cands = bins.candidates();
        let (j, cost) = sah(&cands, &node.bounds).unwrap();
        assert_eq!(cands[j].n_left, 10);
        assert!(cost < 20.0);
        let p = bins.partition(&boxes, &mut ids, j);
        assert_eq!(p.mid, 10);
        assert!(ids[..10].iter().all(|&i| i < 10));
    }
}
