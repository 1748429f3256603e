//! The node graph: references, parents, cycles, local and world transforms, and the
//! pre-order traversal of a scene that fixes the triangle ids.
//!
//! Choice: glTF requires the nodes to form disjoint strict trees (a node has at most one
//! parent) and a scene's `nodes` to be roots. rayd enforces this for the whole document,
//! not only the default scene: a node listed as a child twice (by one parent or two) is
//! [`GltfError::NodeMultipleParents`], a cycle is [`GltfError::NodeCycle`], and a scene root
//! that has a parent or is listed twice is refused. So every node is reached at most once,
//! a node's world transform is unique, and no traversal can loop or blow up.

use gltf::json;

use super::animation::NodePose;
use super::math::{self, Mat4};
use super::GltfError;

/// Checks every node's references and the tree shape; returns each node's parent.
pub(super) fn check(root: &json::Root) -> Result<Vec<Option<usize>>, GltfError> {
    let n = root.nodes.len();
    let mut parent: Vec<Option<usize>> = vec![None; n];
    for (i, node) in root.nodes.iter().enumerate() {
        let refs = [
            ("mesh", node.mesh.map(|m| m.value()), root.meshes.len()),
            ("camera", node.camera.map(|c| c.value()), root.cameras.len()),
            ("skin", node.skin.map(|s| s.value()), root.skins.len()),
        ];
        for (kind, index, count) in refs {
            if let Some(index) = index.filter(|&x| x >= count) {
                return Err(GltfError::DanglingReference {
                    from: format!("node {i}"),
                    kind,
                    index,
                    count,
                });
            }
        }
        for c in node.children.iter().flatten() {
            let c = c.value();
            if c >= n {
                return Err(GltfError::DanglingReference {
                    from: format!("node {i} (children)"),
                    kind: "node",
                    index: c,
                    count: n,
                });
            }
            if let Some(first) = parent[c] {
                return Err(GltfError::NodeMultipleParents {
                    node: c,
                    first,
                    second: i,
                });
            }
            parent[c] = Some(i);
        }
    }
    // Every node reachable from a parentless node is in a tree; with one parent each, any
    // node left over sits on, or hangs below, a cycle.
    let mut reached = vec![false; n];
    let mut stack: Vec<usize> = (0..n).filter(|&i| parent[i].is_none()).collect();
    while let Some(i) = stack.pop() {
        reached[i] = true;
        stack.extend(root.nodes[i].children.iter().flatten().map(|c| c.value()));
    }
    if let Some(start) = (0..n).find(|&i| !reached[i]) {
        // Walk up until a node repeats: that node is on the cycle.
        let mut seen = vec![false; n];
        let mut i = start;
        while !seen[i] {
            seen[i] = true;
            // Unreached nodes always have a parent, else they would be roots.
            i = parent[i].unwrap_or(i);
        }
        let first = i;
        let mut cycle = vec![first];
        let mut j = parent[first].unwrap_or(first);
        while j != first {
            cycle.push(j);
            j = parent[j].unwrap_or(first);
        }
        // Parent pointers run child → parent; show the cycle parent → child, from its
        // lowest node so that the message does not depend on where the walk started.
        cycle.reverse();
        let lowest = (0..cycle.len()).min_by_key(|&k| cycle[k]).unwrap_or(0);
        cycle.rotate_left(lowest);
        cycle.push(cycle[0]);
        return Err(GltfError::NodeCycle { nodes: cycle });
    }
    Ok(parent)
}

/// The nodes of scene `s` in pre-order (node, then its children in order).
pub(super) fn scene_order(
    root: &json::Root,
    s: usize,
    parent: &[Option<usize>],
) -> Result<Vec<usize>, GltfError> {
    let scene = &root.scenes[s];
    let mut listed = vec![false; root.nodes.len()];
    for r in &scene.nodes {
        let r = r.value();
        if r >= root.nodes.len() {
            return Err(GltfError::DanglingReference {
                from: format!("scene {s}"),
                kind: "node",
                index: r,
                count: root.nodes.len(),
            });
        }
        if let Some(p) = parent[r] {
            return Err(GltfError::BadSceneRoot {
                scene: s,
                node: r,
                reason: format!("it is a child of node {p}, so it would be reached twice"),
            });
        }
        if listed[r] {
            return Err(GltfError::BadSceneRoot {
                scene: s,
                node: r,
                reason: "it is listed more than once".to_string(),
            });
        }
        listed[r] = true;
    }
    // An explicit stack: hierarchies can be deeper than the thread's stack.
    let mut order = Vec::new();
    let mut stack: Vec<usize> = scene.nodes.iter().rev().map(|r| r.value()).collect();
    while let Some(i) = stack.pop() {
        order.push(i);
        if let Some(children) = &root.nodes[i].children {
            stack.extend(children.iter().rev().map(|c| c.value()));
        }
    }
    Ok(order)
}

fn vec3(v: [f32; 3]) -> [f64; 3] {
    v.map(f64::from)
}

/// Node `i`'s local transform: its `matrix` as stored (animation does not apply to a node
/// with a matrix), else `T·R·S` with animated values replacing stored ones.
pub(super) fn local_matrix(
    i: usize,
    node: &json::Node,
    pose: Option<&NodePose>,
) -> Result<Mat4, GltfError> {
    let bad = |reason: &str| GltfError::BadNode {
        node: i,
        reason: reason.to_string(),
    };
    let m = if let Some(m) = node.matrix {
        let v = m.map(f64::from);
        math::from_cols(&v)
    } else {
        let t = pose
            .and_then(|p| p.translation)
            .unwrap_or_else(|| vec3(node.translation.unwrap_or([0.0; 3])));
        let s = pose
            .and_then(|p| p.scale)
            .unwrap_or_else(|| vec3(node.scale.unwrap_or([1.0; 3])));
        let q = match pose.and_then(|p| p.rotation) {
            Some(q) => q,
            None => {
                let q = node.rotation.map_or([0.0, 0.0, 0.0, 1.0], |q| q.0);
                // Stored rotations must be unit; normalising (in f64) keeps a slightly
                // off-unit quaternion a rotation instead of a skew.
                math::normalize_quat(q.map(f64::from))
                    .ok_or_else(|| bad("rotation is a zero or non-finite quaternion"))?
            }
        };
        math::from_trs(t, q, s)
    };
    if m.iter().flatten().any(|v| !v.is_finite()) {
        return Err(bad("transform has a non-finite value"));
    }
    Ok(m)
}

/// World transforms of every node: parent's world · local, roots at identity.
pub(super) fn world_matrices(
    root: &json::Root,
    parent: &[Option<usize>],
    local: &[Mat4],
) -> Vec<Mat4> {
    let n = root.nodes.len();
    let mut world = vec![math::IDENTITY; n];
    let mut stack: Vec<usize> = (0..n).filter(|&i| parent[i].is_none()).collect();
    for &r in &stack {
        world[r] = local[r];
    }
    while let Some(i) = stack.pop() {
        for c in root.nodes[i].children.iter().flatten() {
            let c = c.value();
            world[c] = math::mul(&world[i], &local[c]);
            stack.push(c);
        }
    }
    world
}
