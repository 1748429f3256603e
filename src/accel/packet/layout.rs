//! The traversal format of the `bvh2` accelerator: the builder's depth-first skip-pointer
//! nodes (Geimer & Müller §3.3) with each leaf's triangles (at most 8) pre-gathered into
//! one [`Tri8`] pack of the chosen triangle test.

use rayon::prelude::*;

use crate::accel::bvh::{self, RefitError};
use crate::accel::triangle::{Tri8, TriTest, PAD_ID};
use crate::geometry::{Aabb, Triangle};

/// One node: its box, its skip pointer and its leaf pack. 32 bytes, aligned so that no
/// node straddles a cache line (Geimer & Müller §3.3).
#[repr(C, align(32))]
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct PacketNode {
    /// Lower corner of the node's box.
    pub min: [f32; 3],
    /// Index of the first node after this node's subtree (where traversal goes when the
    /// box is missed; for a leaf, the next node).
    pub skip: u32,
    /// Upper corner.
    pub max: [f32; 3],
    /// 0 for an inner node (its children follow it, the larger one first); for a leaf,
    /// the index of its pack plus one.
    pub pack: u32,
}

const _: () = assert!(std::mem::size_of::<PacketNode>() == 32);

/// Nodes and leaf packs of one tree.
#[derive(Clone, Debug)]
pub struct PacketTree<T> {
    /// Nodes in depth-first order, root first; empty for a scene with nothing to hit.
    pub nodes: Vec<PacketNode>,
    /// One pack per leaf, in leaf order.
    pub packs: Vec<Tri8<T>>,
    /// Largest |coordinate| of the tree's bounds (see `mbvh::ray::BoxRay`).
    pub scale: f32,
    /// Triangles the tree was built over (all ids): a refit must bring as many.
    pub triangles: usize,
    /// Ids left out of the tree (degenerate or non-finite), ascending: a refit must
    /// leave exactly these out.
    pub excluded: Vec<u32>,
    /// [`PacketTree::cost`] as built, measured by the first refit and kept by the later
    /// ones, to measure how far they drifted.
    pub built_cost: Option<f64>,
}

impl<T> PacketTree<T> {
    /// The tree's surface-area cost over its root's area, each node's half area counted
    /// once (see `mbvh::layout::TravTree::cost`). 0 for an empty or flat tree.
    pub fn cost(&self) -> f64 {
        let Some(root) = self.nodes.first() else {
            return 0.0;
        };
        let node_box = |n: &PacketNode| Aabb {
            min: n.min,
            max: n.max,
        };
        let area = bvh::half_area(&node_box(root));
        if !(area > 0.0 && area.is_finite()) {
            return 0.0;
        }
        self.nodes
            .iter()
            .map(|n| bvh::half_area(&node_box(n)))
            .sum::<f64>()
            / area
    }

    /// [`PacketTree::cost`] now over the cost as built ([`bvh::drift`]).
    pub fn slowdown(&self) -> f64 {
        bvh::drift(self.cost(), self.built_cost)
    }
}

impl<T: TriTest> PacketTree<T> {
    /// Converts the builder's tree.
    ///
    /// # Panics
    /// If a leaf holds more than 8 triangles (the builder makes at most 8).
    pub fn from_bvh2(tree: &bvh::Bvh2) -> Self {
        let tris = tree.tris();
        let mut packs = Vec::new();
        let nodes = tree
            .nodes()
            .iter()
            .map(|n| {
                let pack = if n.is_leaf() {
                    let (first, count) = n.leaf_range();
                    let lanes: Vec<_> = tris[first as usize..(first + count) as usize]
                        .iter()
                        .map(|t| (t.id, t.triangle()))
                        .collect();
                    packs.push(Tri8::pack(&lanes));
                    packs.len() as u32
                } else {
                    0
                };
                PacketNode {
                    min: n.min,
                    skip: n.skip,
                    max: n.max,
                    pack,
                }
            })
            .collect();
        PacketTree {
            nodes,
            packs,
            scale: tree.bounds().max_abs(),
            triangles: tree.triangle_count(),
            excluded: tree.excluded().to_vec(),
            built_cost: None,
        }
    }

    /// Takes new positions for the same triangles in place, as
    /// `mbvh::TravTree::refit` does: packs re-gathered by id in parallel, boxes
    /// recomputed bottom-up with the two subtrees of large nodes as rayon tasks, `scale`
    /// updated. The child order (larger area first) is kept even where it no longer
    /// holds; it only affects speed. Refused, tree unchanged, as `bvh::Bvh2::refit` is.
    pub fn refit(&mut self, triangles: &[Triangle]) -> Result<(), RefitError> {
        bvh::check_refit(&self.excluded, self.triangles, triangles)?;
        if self.built_cost.is_none() {
            self.built_cost = Some(self.cost());
        }
        self.packs
            .par_iter_mut()
            .with_min_len(64)
            .for_each(|p| p.regather(triangles));
        let bounds = if self.nodes.is_empty() {
            Aabb::EMPTY
        } else {
            refit_nodes(&mut self.nodes, 0, &self.packs, triangles)
        };
        self.scale = bounds.max_abs();
        Ok(())
    }

    /// Bytes held.
    pub fn bytes(&self) -> usize {
        self.nodes.capacity() * std::mem::size_of::<PacketNode>()
            + self.packs.capacity() * std::mem::size_of::<Tri8<T>>()
            + self.excluded.capacity() * std::mem::size_of::<u32>()
    }
}

/// Subtrees with at least this many nodes are refitted as separate rayon tasks.
const PAR_REFIT: usize = 512;

/// Refits the subtree `nodes` (root first, global index `base`, exactly the subtree) and
/// returns its box.
fn refit_nodes<T: Send + Sync>(
    nodes: &mut [PacketNode],
    base: usize,
    packs: &[Tri8<T>],
    triangles: &[Triangle],
) -> Aabb {
    let len = nodes.len();
    let (me, rest) = nodes.split_first_mut().expect("a subtree has a root");
    let b = if me.pack != 0 {
        let mut b = Aabb::EMPTY;
        for &id in &packs[me.pack as usize - 1].ids {
            if id != PAD_ID {
                for &v in &triangles[id as usize].v {
                    b.grow(v);
                }
            }
        }
        b
    } else {
        // The left child follows this node; the right one starts at the left's skip.
        let left_len = rest[0].skip as usize - (base + 1);
        let (l, r) = rest.split_at_mut(left_len);
        let right_base = base + 1 + left_len;
        let (lb, rb) = if len >= PAR_REFIT && rayon::current_num_threads() > 1 {
            rayon::join(
                || refit_nodes(l, base + 1, packs, triangles),
                || refit_nodes(r, right_base, packs, triangles),
            )
        } else {
            (
                refit_nodes(l, base + 1, packs, triangles),
                refit_nodes(r, right_base, packs, triangles),
            )
        };
        let mut b = lb;
        b.union(&rb);
        b
    };
    me.min = b.min;
    me.max = b.max;
    b
}
