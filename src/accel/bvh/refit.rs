//! Refitting: new positions for the same triangles, same tree topology. Leaf data is
//! re-gathered in parallel, then every box is recomputed bottom-up by a recursion that
//! hands disjoint subtrees (contiguous in depth-first order) to rayon tasks.
//!
//! Boxes after a refit are the tight boxes of the whole triangles below them, also for an
//! SBVH (whose clipped leaf boxes cannot be reproduced without the split planes): such a
//! tree stays correct but its nodes overlap more; rebuild when quality matters.
//!
//! The triangles left out of the tree (degenerate or non-finite) must stay out, and every
//! triangle in it must stay traceable; otherwise the refit is refused and the tree
//! untouched, because a triangle that becomes traceable would be missing from the tree.

use rayon::prelude::*;

use super::build::union;
use super::bvh2::{Bvh2, Bvh2Node, Bvh2Tri};
use super::wide::{Child, Mbvh, MultiTri, WideNode};
use super::{is_traceable, RefitError};
use crate::geometry::{Aabb, Triangle};

/// Subtrees with at least this many nodes are refitted as separate rayon tasks.
const PAR_REFIT: u32 = 256;

/// Checks that `triangles` can replace the positions of a tree built over `count`
/// triangles that left out `excluded` (ascending): shared by every structure that
/// refits, so that all of them refuse the same updates.
pub(crate) fn check(
    excluded: &[u32],
    count: usize,
    triangles: &[Triangle],
) -> Result<(), RefitError> {
    if triangles.len() != count {
        return Err(RefitError::Count {
            expected: count,
            got: triangles.len(),
        });
    }
    if let Some(&id) = excluded
        .iter()
        .find(|&&id| is_traceable(&triangles[id as usize]))
    {
        return Err(RefitError::Degeneracy { id });
    }
    // Same number left out and all of the old ones still out: the same set.
    let out = triangles.par_iter().filter(|t| !is_traceable(t)).count();
    if out != excluded.len() {
        let id = triangles
            .par_iter()
            .enumerate()
            .find_first(|(i, t)| !is_traceable(t) && excluded.binary_search(&(*i as u32)).is_err())
            .map_or(0, |(i, _)| i as u32);
        return Err(RefitError::Degeneracy { id });
    }
    Ok(())
}

impl<const N: usize> Mbvh<N> {
    /// Takes new positions for the same triangles (same count, same ids) and updates the
    /// multi-triangles and every box, keeping the topology. Refused (tree unchanged) when
    /// the count differs or a triangle moved between degenerate and not; rebuild then.
    pub fn refit(&mut self, triangles: &[Triangle]) -> Result<(), RefitError> {
        check(&self.excluded, self.triangles, triangles)?;
        self.tris.par_iter_mut().with_min_len(256).for_each(|mt| {
            for lane in 0..N {
                let id = mt.ids[lane];
                if id == MultiTri::<N>::PAD_ID {
                    break;
                }
                mt.set(lane, id, &triangles[id as usize]);
            }
        });
        refit_wide(&mut self.nodes, 0, &self.tris);
        self.clipped = false;
        Ok(())
    }
}

/// Box of a leaf's multi-triangles.
fn leaf_box<const N: usize>(mts: &[MultiTri<N>]) -> Aabb {
    let mut b = Aabb::EMPTY;
    for mt in mts {
        for lane in 0..mt.lanes() {
            for a in 0..3 {
                let v = [mt.v0[a][lane], mt.v1[a][lane], mt.v2[a][lane]];
                for x in v {
                    b.min[a] = b.min[a].min(x);
                    b.max[a] = b.max[a].max(x);
                }
            }
        }
    }
    b
}

/// Refits the subtree whose root is `nodes[0]` (global index `base`; `nodes` is exactly
/// the subtree) and returns its box.
fn refit_wide<const N: usize>(nodes: &mut [WideNode<N>], base: u32, mts: &[MultiTri<N>]) -> Aabb {
    let len = nodes.len() as u32;
    let (me, mut rest) = nodes.split_first_mut().expect("a subtree has a root");
    let lanes = me.lanes();
    // Inner children are in lane order with rising indices; each owns the slots up to
    // the next one (or the end of this subtree).
    let mut jobs: [Option<(&mut [WideNode<N>], u32)>; N] = std::array::from_fn(|_| None);
    let mut inner_idx = [u32::MAX; N];
    for (lane, idx) in inner_idx.iter_mut().enumerate().take(lanes) {
        if let Child::Inner(i) = Child::decode(me.child[lane]) {
            *idx = i;
        }
    }
    let mut next_start = base + 1;
    for lane in 0..lanes {
        let i = inner_idx[lane];
        if i == u32::MAX {
            continue;
        }
        debug_assert_eq!(i, next_start);
        let end = inner_idx[lane + 1..lanes]
            .iter()
            .copied()
            .find(|&j| j != u32::MAX)
            .unwrap_or(base + len);
        let (mine, tail) = std::mem::take(&mut rest).split_at_mut((end - i) as usize);
        rest = tail;
        jobs[lane] = Some((mine, i));
        next_start = end;
    }
    let mut boxes = [Aabb::EMPTY; N];
    if len >= PAR_REFIT && rayon::current_num_threads() > 1 {
        let found: Vec<(usize, Aabb)> = jobs
            .iter_mut()
            .enumerate()
            .filter_map(|(lane, j)| j.take().map(|(s, i)| (lane, s, i)))
            .collect::<Vec<_>>()
            .into_par_iter()
            .map(|(lane, s, i)| (lane, refit_wide(s, i, mts)))
            .collect();
        for (lane, b) in found {
            boxes[lane] = b;
        }
    } else {
        for (lane, j) in jobs.iter_mut().enumerate() {
            if let Some((s, i)) = j.take() {
                boxes[lane] = refit_wide(s, i, mts);
            }
        }
    }
    let mut all = Aabb::EMPTY;
    for (lane, b) in boxes.iter_mut().enumerate().take(lanes) {
        if let Child::Leaf { first, count } = Child::decode(me.child[lane]) {
            *b = leaf_box(&mts[first as usize..(first + count) as usize]);
        }
        me.set_lane_box(lane, b);
        all = union(&all, b);
    }
    all
}

impl Bvh2 {
    /// Takes new positions for the same triangles and updates the triangle records and
    /// every box, keeping the topology (and the child order, which may no longer be by
    /// area). Refused (tree unchanged) as [`Mbvh::refit`] is.
    pub fn refit(&mut self, triangles: &[Triangle]) -> Result<(), RefitError> {
        check(&self.excluded, self.triangles, triangles)?;
        self.tris
            .par_iter_mut()
            .with_min_len(1024)
            .for_each(|t| *t = Bvh2Tri::new(t.id, &triangles[t.id as usize]));
        if !self.nodes.is_empty() {
            refit_binary(&mut self.nodes, 0, &self.tris);
        }
        self.clipped = false;
        self.sorted = false;
        Ok(())
    }
}

/// Refits the subtree `nodes` (root first, global index `base`) and returns its box.
fn refit_binary(nodes: &mut [Bvh2Node], base: u32, tris: &[Bvh2Tri]) -> Aabb {
    let len = nodes.len() as u32;
    let (me, rest) = nodes.split_first_mut().expect("a subtree has a root");
    let b = if me.is_leaf() {
        let (first, count) = me.leaf_range();
        let mut b = Aabb::EMPTY;
        for t in &tris[first as usize..(first + count) as usize] {
            for p in [t.v0, t.v1, t.v2] {
                b.grow(p);
            }
        }
        b
    } else {
        let left_len = rest[0].skip - (base + 1);
        let (l, r) = rest.split_at_mut(left_len as usize);
        let right_base = base + 1 + left_len;
        let (lb, rb) = if len >= PAR_REFIT && rayon::current_num_threads() > 1 {
            rayon::join(
                || refit_binary(l, base + 1, tris),
                || refit_binary(r, right_base, tris),
            )
        } else {
            (
                refit_binary(l, base + 1, tris),
                refit_binary(r, right_base, tris),
            )
        };
        union(&lb, &rb)
    };
    me.min = b.min;
    me.max = b.max;
    b
}
