//! The top levels of the recursion, partitioned once for all threads.
//!
//! With several threads a batch starts as a ray split: one group of rays per thread, all
//! traversing the same root at once (`Dacrt::groups`). Without sharing, each group
//! partitions the triangles of every node it reaches on its own, and near the root every
//! group reaches every node, so the partitioning of the top levels — the longest triangle
//! ranges — is done once per group.
//! Here the triangles are partitioned once, before the split, down to nodes of
//! [`super::Parallelism::top_min_tris`] triangles, with both subtrees of every node built
//! at once (task parallelism) and the longest ranges binned and partitioned data-parallel
//! (`parallel::bins_par`, `partition_bins_par`). Every group then receives a copy of the
//! partitioned id array and this tree, and its steps in the top levels only order the
//! children, decide the skips and filter rays; below the tree they partition their own
//! copy as before.
//!
//! The partitions are those a single-threaded step would choose from the same inputs
//! ([`choose`]): the binned SAH, or Nabata's sampled cost with sample rays drawn from the
//! whole batch and kept, per child, to those that enter its box. The active-ray count
//! that picks binning over the middle split is estimated from the samples (the batch's
//! count scaled by the fraction of sample rays that enter the node). Which triangle lands
//! in which leaf never changes what a ray hits, so the answers stay those of `brute`.

use super::rays::{filter, FilterBox, RayRec};
use super::split::{Node, Parts};
use super::traverse::{choose, Ctx};

/// One node of the shared top levels: its partition and the children's, where they are
/// big enough to be shared too.
#[derive(Debug)]
pub struct Top {
    /// How the node's id range splits (the ids are already in this order).
    pub parts: Parts,
    /// Left and right subtrees.
    kids: [Option<Box<Top>>; 2],
}

impl Top {
    /// The children's shared partitions, left then right.
    pub fn kids(&self) -> [Option<&Top>; 2] {
        [self.kids[0].as_deref(), self.kids[1].as_deref()]
    }

    /// Nodes in this tree.
    pub fn count(&self) -> usize {
        1 + self
            .kids()
            .iter()
            .flatten()
            .map(|k| k.count())
            .sum::<usize>()
    }
}

/// Partitions `ids` (the triangles of `node`) down to nodes of fewer than `min_tris`
/// triangles and returns the tree of partitions, or `None` when the node is not split.
/// `rays` estimates the node's active rays; `samples` are sample rays that enter the node
/// (drawn whether or not sampling is on: they also estimate the rays of each child).
pub fn build(
    ctx: &Ctx,
    samples: &[RayRec],
    rays: usize,
    ids: &mut [u32],
    node: &Node,
    min_tris: usize,
) -> Option<Top> {
    let t = ids.len();
    if t < min_tris.max(ctx.opts.leaf_tris) || rays < ctx.opts.leaf_rays || samples.is_empty() {
        return None;
    }
    let (parts, _) = choose(ctx, samples, rays, ids, node)?;
    let (ids_l, ids_r) = ids.split_at_mut(parts.mid);
    let side = |ids: &mut [u32], child: &Node| {
        let mut own = samples.to_vec();
        let m = filter(&mut own, &FilterBox::new(&child.bounds));
        own.truncate(m);
        // The node's rays scaled by the fraction of its samples entering the child: a
        // child no sample enters is left to the threads (few rays reach it, if any).
        let rays = (rays as u64 * m as u64 / samples.len().max(1) as u64) as usize;
        build(ctx, &own, rays, ids, child, min_tris)
    };
    let (l, r) = rayon::join(|| side(ids_l, &parts.left), || side(ids_r, &parts.right));
    Some(Top {
        parts,
        kids: [l.map(Box::new), r.map(Box::new)],
    })
}
