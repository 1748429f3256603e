//! Structural checks of built trees, for tests and for benchmarks that validate before
//! they time. They walk the whole tree, so they are slow; they report the first broken
//! invariant.
//!
//! Checked for both layouts: every node is reached exactly once from the root; child
//! boxes lie inside their parent's box and, except for SBVH trees before a refit, equal
//! the union of what lies below them; leaves hold at most 2N (MBVH) or
//! [`BVH2_MAX_LEAF`](super::bvh2::BVH2_MAX_LEAF) triangles with the exact stored
//! positions; every traceable triangle appears in exactly one leaf (SBVH: at least once,
//! and every point of it lies in the box of a leaf that holds it), and no excluded one
//! does. MBVH: empty lanes are invalid boxes with [`Child::EMPTY`], padding lanes are
//! finite point triangles with [`MultiTri::PAD_ID`]. BVH2: skip pointers nest exactly
//! (each node's skip is the end of its subtree, leaves skip to the next node) and the
//! larger child comes first.

use super::build::{half_area, union};
use super::bvh2::{Bvh2, BVH2_MAX_LEAF};
use super::is_traceable;
use super::wide::{Child, Mbvh, MultiTri};
use crate::accel::BuildQuality;
use crate::geometry::{Aabb, Triangle};

type Check = Result<(), String>;

fn contains(outer: &Aabb, inner: &Aabb) -> bool {
    (0..3).all(|a| outer.min[a] <= inner.min[a] && inner.max[a] <= outer.max[a])
}

fn valid_box(b: &Aabb) -> bool {
    (0..3).all(|a| b.min[a].is_finite() && b.max[a].is_finite() && b.min[a] <= b.max[a])
}

fn same_bits(a: &Triangle, b: &Triangle) -> bool {
    a.v.iter()
        .flatten()
        .zip(b.v.iter().flatten())
        .all(|(x, y)| x.to_bits() == y.to_bits())
}

/// Checks the excluded list against the scene.
fn check_excluded(excluded: &[u32], count: usize, tris: &[Triangle]) -> Check {
    if tris.len() != count {
        return Err(format!(
            "built over {count} triangles, checked against {}",
            tris.len()
        ));
    }
    if excluded.windows(2).any(|w| w[0] >= w[1]) {
        return Err("excluded ids not strictly ascending".into());
    }
    let out: Vec<u32> = (0..tris.len() as u32)
        .filter(|&i| !is_traceable(&tris[i as usize]))
        .collect();
    if out != excluded {
        return Err("excluded ids differ from the non-traceable triangles".into());
    }
    Ok(())
}

/// Checks how often each triangle appears (`seen`; more than once only with `dups`) and,
/// for clipped trees, that the leaf boxes holding a triangle cover it (`boxes[id]`).
fn check_coverage(
    seen: &[u32],
    tris: &[Triangle],
    dups: bool,
    clipped: bool,
    boxes: &[Vec<Aabb>],
) -> Check {
    for (id, (&n, t)) in seen.iter().zip(tris).enumerate() {
        let want = is_traceable(t);
        match (want, n) {
            (false, 0) => {}
            (false, _) => return Err(format!("excluded triangle {id} is in a leaf")),
            (true, 0) => return Err(format!("triangle {id} is in no leaf")),
            (true, 1) => {}
            (true, _) if dups => {}
            (true, n) => return Err(format!("triangle {id} is in {n} leaves")),
        }
        if clipped && want {
            // Sample the triangle: every sample must lie in one of its leaf boxes.
            const BARY: [[f64; 3]; 10] = [
                [1.0, 0.0, 0.0],
                [0.0, 1.0, 0.0],
                [0.0, 0.0, 1.0],
                [0.5, 0.5, 0.0],
                [0.0, 0.5, 0.5],
                [0.5, 0.0, 0.5],
                [1.0 / 3.0, 1.0 / 3.0, 1.0 / 3.0],
                [0.7, 0.2, 0.1],
                [0.1, 0.7, 0.2],
                [0.2, 0.1, 0.7],
            ];
            for w in BARY {
                let p: [f64; 3] = std::array::from_fn(|a| {
                    w[0] * t.v[0][a] as f64 + w[1] * t.v[1][a] as f64 + w[2] * t.v[2][a] as f64
                });
                let inside = boxes[id].iter().any(|b| {
                    (0..3).all(|a| {
                        let tol = p[a].abs() * 1e-9 + 1e-30;
                        b.min[a] as f64 - tol <= p[a] && p[a] <= b.max[a] as f64 + tol
                    })
                });
                if !inside {
                    return Err(format!(
                        "point {p:?} of triangle {id} is in none of its leaf boxes"
                    ));
                }
            }
        }
    }
    Ok(())
}

impl<const N: usize> Mbvh<N> {
    /// Checks every structural invariant against the triangles the tree was built (or
    /// last refitted) with; `Err` says which one broke, and where.
    pub fn validate(&self, triangles: &[Triangle]) -> Result<(), String> {
        check_excluded(&self.excluded, self.triangles, triangles)?;
        let n = self.nodes.len();
        if n == 0 {
            return Err("no root node".into());
        }
        let mut reached = vec![false; n];
        let mut mt_used = vec![false; self.tris.len()];
        let mut seen = vec![0u32; triangles.len()];
        let mut boxes: Vec<Vec<Aabb>> = if self.clipped {
            vec![Vec::new(); triangles.len()]
        } else {
            Vec::new()
        };
        let mut stack: Vec<(usize, Option<Aabb>)> = vec![(0, None)];
        while let Some((i, parent)) = stack.pop() {
            if std::mem::replace(&mut reached[i], true) {
                return Err(format!("node {i} is reached twice"));
            }
            let node = &self.nodes[i];
            let k = node.lanes();
            if i != 0 && k < 2 {
                return Err(format!("inner node {i} has {k} children"));
            }
            if node.pad != [0; N] {
                return Err(format!("node {i} has non-zero padding"));
            }
            for lane in k..N {
                let b = node.lane_box(lane);
                if node.child[lane] != Child::EMPTY
                    || b.min != [f32::INFINITY; 3]
                    || b.max != [f32::NEG_INFINITY; 3]
                {
                    return Err(format!(
                        "empty lane {lane} of node {i} is not an invalid box"
                    ));
                }
            }
            let own = node.bounds();
            if let Some(pb) = parent {
                if !contains(&pb, &own) {
                    return Err(format!("node {i} sticks out of its parent's box"));
                }
                if !self.clipped && pb != own {
                    return Err(format!("parent's box of node {i} is not tight"));
                }
            }
            for lane in 0..k {
                let b = node.lane_box(lane);
                if !valid_box(&b) {
                    return Err(format!("lane {lane} of node {i} has box {b:?}"));
                }
                match Child::decode(node.child[lane]) {
                    Child::Inner(c) => {
                        let c = c as usize;
                        if c <= i || c >= n {
                            return Err(format!("node {i} lane {lane}: bad child index {c}"));
                        }
                        stack.push((c, Some(b)));
                    }
                    Child::Leaf { first, count } => {
                        if !(1..=2).contains(&count) {
                            return Err(format!(
                                "leaf at node {i} lane {lane} has {count} multi-triangles"
                            ));
                        }
                        let (f, e) = (first as usize, (first + count) as usize);
                        if e > self.tris.len() {
                            return Err(format!("leaf at node {i} lane {lane} is out of range"));
                        }
                        let mut leaf = Aabb::EMPTY;
                        let mut ids = Vec::new();
                        for (m, used_flag) in mt_used.iter_mut().enumerate().take(e).skip(f) {
                            if std::mem::replace(used_flag, true) {
                                return Err(format!("multi-triangle {m} is in two leaves"));
                            }
                            let mt = &self.tris[m];
                            let used = mt.lanes();
                            if used == 0 {
                                return Err(format!("multi-triangle {m} is empty"));
                            }
                            for l in 0..N {
                                let t = mt.get(l);
                                if l >= used {
                                    let p = t.v[0];
                                    if mt.ids[l] != MultiTri::<N>::PAD_ID
                                        || !p.iter().all(|x| x.is_finite())
                                        || t.v[1] != p
                                        || t.v[2] != p
                                    {
                                        return Err(format!(
                                            "padding lane {l} of multi-triangle {m}"
                                        ));
                                    }
                                    continue;
                                }
                                let id = mt.ids[l] as usize;
                                if id >= triangles.len() || !same_bits(&t, &triangles[id]) {
                                    return Err(format!(
                                        "lane {l} of multi-triangle {m} is not triangle {id}"
                                    ));
                                }
                                seen[id] += 1;
                                ids.push(id);
                                let tb = triangles[id].bounds();
                                if self.clipped {
                                    if !valid_box(&super::build::intersect(&tb, &b)) {
                                        return Err(format!("triangle {id} misses its leaf box"));
                                    }
                                    boxes[id].push(b);
                                }
                                leaf = union(&leaf, &tb);
                            }
                        }
                        ids.sort_unstable();
                        if ids.windows(2).any(|w| w[0] == w[1]) {
                            return Err(format!(
                                "leaf at node {i} lane {lane} holds a triangle twice"
                            ));
                        }
                        if self.clipped {
                            if !contains(&leaf, &b) {
                                return Err(format!(
                                    "leaf box at node {i} lane {lane} exceeds its triangles"
                                ));
                            }
                        } else if leaf != b {
                            return Err(format!("leaf box at node {i} lane {lane} is not tight"));
                        }
                    }
                    Child::Empty => return Err(format!("lane {lane} of node {i} is empty")),
                }
            }
        }
        if let Some(i) = reached.iter().position(|&r| !r) {
            return Err(format!("node {i} is unreachable"));
        }
        if let Some(m) = mt_used.iter().position(|&u| !u) {
            return Err(format!("multi-triangle {m} is in no leaf"));
        }
        check_coverage(
            &seen,
            triangles,
            self.quality == BuildQuality::Sbvh,
            self.clipped,
            &boxes,
        )
    }
}

impl Bvh2 {
    /// Checks every structural invariant (see the module documentation) against the
    /// triangles the tree was built (or last refitted) with.
    pub fn validate(&self, triangles: &[Triangle]) -> Result<(), String> {
        check_excluded(&self.excluded, self.triangles, triangles)?;
        let mut seen = vec![0u32; triangles.len()];
        let mut boxes: Vec<Vec<Aabb>> = if self.clipped {
            vec![Vec::new(); triangles.len()]
        } else {
            Vec::new()
        };
        let mut tri_used = vec![false; self.tris.len()];
        if self.nodes.is_empty() {
            if !self.tris.is_empty() {
                return Err("triangle records without nodes".into());
            }
        } else {
            let mut v = Walk {
                t: self,
                triangles,
                seen: &mut seen,
                boxes: &mut boxes,
                tri_used: &mut tri_used,
            };
            let end = v.walk(0, None, 0)?;
            if end as usize != self.nodes.len() || self.nodes[0].skip != end {
                return Err(format!(
                    "root subtree ends at {end} of {}",
                    self.nodes.len()
                ));
            }
            if let Some(t) = tri_used.iter().position(|&u| !u) {
                return Err(format!("triangle record {t} is in no leaf"));
            }
        }
        check_coverage(
            &seen,
            triangles,
            self.quality == BuildQuality::Sbvh,
            self.clipped,
            &boxes,
        )
    }
}

struct Walk<'a> {
    t: &'a Bvh2,
    triangles: &'a [Triangle],
    seen: &'a mut [u32],
    boxes: &'a mut [Vec<Aabb>],
    tri_used: &'a mut [bool],
}

impl Walk<'_> {
    /// Checks the subtree at `i` and returns the index one past it.
    fn walk(&mut self, i: u32, parent: Option<Aabb>, depth: u32) -> Result<u32, String> {
        let nodes = &self.t.nodes;
        if i as usize >= nodes.len() || depth > 256 {
            return Err(format!("node index {i} out of range"));
        }
        let node = &nodes[i as usize];
        let b = node.aabb();
        if !valid_box(&b) {
            return Err(format!("node {i} has box {b:?}"));
        }
        if let Some(pb) = parent {
            if !contains(&pb, &b) {
                return Err(format!("node {i} sticks out of its parent's box"));
            }
        }
        if node.is_leaf() {
            if node.skip != i + 1 {
                return Err(format!("leaf {i} skips to {}", node.skip));
            }
            let (first, count) = node.leaf_range();
            if !(1..=BVH2_MAX_LEAF).contains(&count) || (first + count) as usize > self.t.tris.len()
            {
                return Err(format!("leaf {i} has triangles {first}+{count}"));
            }
            let mut leaf = Aabb::EMPTY;
            let mut ids = Vec::new();
            for r in first..first + count {
                if std::mem::replace(&mut self.tri_used[r as usize], true) {
                    return Err(format!("triangle record {r} is in two leaves"));
                }
                let rec = &self.t.tris[r as usize];
                let id = rec.id as usize;
                if id >= self.triangles.len() || !same_bits(&rec.triangle(), &self.triangles[id]) {
                    return Err(format!("record {r} is not triangle {id}"));
                }
                self.seen[id] += 1;
                ids.push(id);
                let tb = self.triangles[id].bounds();
                if self.t.clipped {
                    self.boxes[id].push(b);
                }
                leaf = union(&leaf, &tb);
            }
            ids.sort_unstable();
            if ids.windows(2).any(|w| w[0] == w[1]) {
                return Err(format!("leaf {i} holds a triangle twice"));
            }
            if self.t.clipped {
                if !contains(&leaf, &b) {
                    return Err(format!("leaf {i} box exceeds its triangles"));
                }
            } else if leaf != b {
                return Err(format!("leaf {i} box is not tight"));
            }
            return Ok(i + 1);
        }
        let l = i + 1;
        let l_end = self.walk(l, Some(b), depth + 1)?;
        if nodes[l as usize].skip != l_end {
            return Err(format!(
                "node {l} skips to {} not {l_end}",
                nodes[l as usize].skip
            ));
        }
        let r = l_end;
        let r_end = self.walk(r, Some(b), depth + 1)?;
        if nodes[r as usize].skip != r_end || node.skip != r_end {
            return Err(format!("node {r} or {i} skips wrongly"));
        }
        let (lb, rb) = (nodes[l as usize].aabb(), nodes[r as usize].aabb());
        if !self.t.clipped && union(&lb, &rb) != b {
            return Err(format!("box of node {i} is not tight"));
        }
        if self.t.sorted && half_area(&lb) < half_area(&rb) {
            return Err(format!("children of node {i} are not ordered by area"));
        }
        Ok(r_end)
    }
}
