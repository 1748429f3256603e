//! The node graph: references, parents, cycles, local and world transforms, and the
//! pre-order traversal of a scene that fixes the triangle ids.
//!
//! Choice: glTF requires the nodes to form disjoint strict trees (a node has at most one
//! parent) and a scene's `nodes` to be roots. rayd enforces this for the whole document,
//! not only the default scene: a node listed as a child twice (by one parent or two) is
//! [`GltfError::NodeMultipleParents`], a cycle is [`GltfError::NodeCycle`], and a scene root
//! that has a parent or is listed twice is refused. So every node is reached at most once,
//! a node's world transform is unique, and no traversal can loop or blow up.

use glam::{DMat4, DQuat, DVec3};
use gltf::json;

use super::GltfError;
use crate::scene::rig;

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
        // Refused whether or not an animation replaces it, so that whether a file loads
        // does not depend on the time it is posed at.
        if let Some(q) = node.rotation.filter(|_| node.matrix.is_none()) {
            if rig::normalize_quat(DQuat::from_array(q.0.map(f64::from))).is_none() {
                return Err(crate::scene::SceneError::BadNode {
                    node: i,
                    reason: "rotation is a zero or non-finite quaternion".to_string(),
                }
                .into());
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

/// Every node as the rig holds it: its stored local transform and its children.
///
/// A node with a `matrix` keeps it (animation does not apply to such a node); otherwise
/// its TRS, the stored rotation normalised in f64 so that a slightly off-unit quaternion
/// stays a rotation instead of a skew. A zero or non-finite rotation is kept as `None`:
/// it is an error when a pose needs it (see [`crate::scene::rig::Local`]).
pub(super) fn rig_nodes(root: &json::Root) -> Vec<rig::Node> {
    let vec3 = |v: [f32; 3]| DVec3::from_array(v.map(f64::from));
    root.nodes
        .iter()
        .map(|node| {
            let local = match node.matrix {
                Some(m) => rig::Local::Matrix(DMat4::from_cols_array(&m.map(f64::from))),
                None => {
                    let q = node.rotation.map_or([0.0, 0.0, 0.0, 1.0], |q| q.0);
                    let q = q.map(f64::from);
                    rig::Local::Trs {
                        translation: vec3(node.translation.unwrap_or([0.0; 3])),
                        rotation: rig::normalize_quat(DQuat::from_array(q)),
                        scale: vec3(node.scale.unwrap_or([1.0; 3])),
                    }
                }
            };
            rig::Node {
                local,
                children: node.children.iter().flatten().map(|c| c.value()).collect(),
            }
        })
        .collect()
}
