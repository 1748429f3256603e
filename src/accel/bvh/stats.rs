//! Tree statistics in the spirit of Áfra 2013 Tables 2 and 4: node and leaf counts, SIMD
//! utilisation of nodes and multi-triangles, SAH cost, depth and memory.

use serde::Serialize;

use super::build::half_area;
use super::bvh2::Bvh2;
use super::wide::{Child, Mbvh};
use crate::geometry::Aabb;

/// Statistics of one built tree.
///
/// The SAH cost uses the builder's model with K_T = K_I = 1: for an MBVH,
/// `Σ_nodes A(node)/A(root) + Σ_leaves ⌈T/N⌉·A(leaf)/A(root)` where A(node) is the area
/// of the union of its children's boxes (so the root costs 1); for [`Bvh2`],
/// `Σ_inner A/A(root) + Σ_leaves T·A/A(root)`. Lower is better; compare trees of the same
/// layout only.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct BvhStats {
    /// `mbvh8`, `mbvh4` or `bvh2`.
    pub layout: &'static str,
    /// Build quality (`fast`, `sah`, `sbvh`).
    pub quality: &'static str,
    /// Branching factor and multi-triangle width (2 and 1 for `bvh2`).
    pub width: usize,
    /// Triangles the tree was built over.
    pub triangles: usize,
    /// Triangles left out (degenerate or non-finite).
    pub excluded: usize,
    /// Triangle references in leaves; more than `triangles - excluded` when SBVH
    /// duplicated some.
    pub references: usize,
    /// Nodes: multi-nodes for an MBVH; inner nodes plus leaves for `bvh2`.
    pub nodes: usize,
    /// Leaves (leaf lanes of multi-nodes; leaf nodes of `bvh2`).
    pub leaves: usize,
    /// Average children per multi-node divided by N (Áfra's "node util"); 1 for `bvh2`.
    pub node_utilization: f64,
    /// Multi-triangles (triangle records for `bvh2`).
    pub multi_triangles: usize,
    /// Average lanes in use per multi-triangle divided by N (Áfra's "tri util").
    pub multi_triangle_utilization: f64,
    /// Average triangle references per leaf.
    pub avg_leaf_triangles: f64,
    /// SAH cost of the tree (see the type's documentation).
    pub sah_cost: f64,
    /// Deepest level (the root is level 1): multi-node levels for an MBVH.
    pub max_depth: usize,
    /// Average level of the leaves.
    pub avg_leaf_depth: f64,
    /// Bytes of nodes, triangle data and the excluded list.
    pub bytes: usize,
    /// `bytes / triangles`.
    pub bytes_per_triangle: f64,
}

fn ratio(a: f64, b: f64) -> f64 {
    if b > 0.0 {
        a / b
    } else {
        0.0
    }
}

impl<const N: usize> Mbvh<N> {
    /// Statistics of the tree.
    pub fn stats(&self) -> BvhStats {
        let root_area = half_area(&self.bounds());
        let inv = if root_area > 0.0 {
            1.0 / root_area
        } else {
            0.0
        };
        let (mut lanes, mut leaves, mut refs, mut max_depth, mut depth_sum) =
            (0usize, 0usize, 0usize, 0usize, 0usize);
        let mut sah = 0.0;
        let mut stack = vec![(0u32, 1usize)];
        while let Some((i, d)) = stack.pop() {
            let node = &self.nodes[i as usize];
            let k = node.lanes();
            lanes += k;
            max_depth = max_depth.max(d);
            sah += half_area(&node.bounds()) * inv;
            for lane in 0..k {
                match Child::decode(node.child[lane]) {
                    Child::Inner(c) => stack.push((c, d + 1)),
                    Child::Leaf { first, count } => {
                        leaves += 1;
                        depth_sum += d;
                        sah += count as f64 * half_area(&node.lane_box(lane)) * inv;
                        refs += self.tris[first as usize..(first + count) as usize]
                            .iter()
                            .map(|m| m.lanes())
                            .sum::<usize>();
                    }
                    Child::Empty => {}
                }
            }
        }
        let bytes = self.bytes();
        BvhStats {
            layout: if N == 8 { "mbvh8" } else { "mbvh4" },
            quality: self.quality.name(),
            width: N,
            triangles: self.triangles,
            excluded: self.excluded.len(),
            references: refs,
            nodes: self.nodes.len(),
            leaves,
            node_utilization: ratio(lanes as f64, (self.nodes.len() * N) as f64),
            multi_triangles: self.tris.len(),
            multi_triangle_utilization: ratio(refs as f64, (self.tris.len() * N) as f64),
            avg_leaf_triangles: ratio(refs as f64, leaves as f64),
            sah_cost: if refs > 0 { sah } else { 0.0 },
            max_depth,
            avg_leaf_depth: ratio(depth_sum as f64, leaves as f64),
            bytes,
            bytes_per_triangle: ratio(bytes as f64, self.triangles as f64),
        }
    }
}

impl Bvh2 {
    /// Statistics of the tree.
    pub fn stats(&self) -> BvhStats {
        let root = self.bounds();
        let root_area = half_area(&root);
        let inv = if root_area > 0.0 {
            1.0 / root_area
        } else {
            0.0
        };
        let (mut leaves, mut max_depth, mut depth_sum) = (0usize, 0usize, 0usize);
        let mut sah = 0.0;
        if !self.nodes.is_empty() {
            let mut stack = vec![(0u32, 1usize)];
            while let Some((i, d)) = stack.pop() {
                let node = &self.nodes[i as usize];
                let a = half_area(&Aabb {
                    min: node.min,
                    max: node.max,
                }) * inv;
                max_depth = max_depth.max(d);
                if node.is_leaf() {
                    leaves += 1;
                    depth_sum += d;
                    sah += node.leaf_range().1 as f64 * a;
                } else {
                    sah += a;
                    stack.push((i + 1, d + 1));
                    stack.push((self.nodes[i as usize + 1].skip, d + 1));
                }
            }
        }
        let bytes = self.bytes();
        let refs = self.tris.len();
        BvhStats {
            layout: "bvh2",
            quality: self.quality.name(),
            width: 2,
            triangles: self.triangles,
            excluded: self.excluded.len(),
            references: refs,
            nodes: self.nodes.len(),
            leaves,
            node_utilization: if self.nodes.is_empty() { 0.0 } else { 1.0 },
            multi_triangles: refs,
            multi_triangle_utilization: if refs > 0 { 1.0 } else { 0.0 },
            avg_leaf_triangles: ratio(refs as f64, leaves as f64),
            sah_cost: sah,
            max_depth,
            avg_leaf_depth: ratio(depth_sum as f64, leaves as f64),
            bytes,
            bytes_per_triangle: ratio(bytes as f64, self.triangles as f64),
        }
    }
}
