//! The traversal format of the `bvh2` accelerator: the builder's depth-first skip-pointer
//! nodes (Geimer & Müller §3.3) with each leaf's triangles (at most 8) pre-gathered into
//! one [`Tri8`] pack of the chosen triangle test.

use crate::accel::bvh;
use crate::accel::triangle::{Tri8, TriTest};

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
        let b = tree.bounds();
        let scale = if b.is_empty() {
            0.0
        } else {
            b.min
                .iter()
                .chain(&b.max)
                .fold(0.0f32, |m, x| m.max(x.abs()))
        };
        PacketTree {
            nodes,
            packs,
            scale,
        }
    }

    /// Bytes held.
    pub fn bytes(&self) -> usize {
        self.nodes.capacity() * std::mem::size_of::<PacketNode>()
            + self.packs.capacity() * std::mem::size_of::<Tri8<T>>()
    }
}
