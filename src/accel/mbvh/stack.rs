//! The traversal stack of Áfra 2013 §4.1: entries are (entry distance, node id) pairs
//! packed into one `u64`, distance in the high half.
//!
//! Entry distances are `>= +0` (never NaN, `-0` is normalised away by [`super::ray`]),
//! and non-negative floats order like their bit patterns, so comparing keys as integers
//! compares distances (ties broken by the id bits, which is as good as any order). The
//! sorting networks keep the *nearest* entry on top (highest index), ready to pop.

/// Entries one stack holds. A closest-hit traversal keeps at most N − 1 entries per level
/// of the current path and trees are less than 96 levels deep (the builder's
/// `DEPTH_LIMIT + 32`), so 1024 entries cover N ≤ 8; the accelerators check this against
/// each tree's actual depth when they are made.
pub const STACK: usize = 1024;

/// A stack of packed entries, allocated once per chunk of rays.
pub type Stack = [u64; STACK];

/// Packs (distance, node id).
#[inline(always)]
pub fn key(dist: f32, id: i32) -> u64 {
    (u64::from(dist.to_bits()) << 32) | u64::from(id as u32)
}

/// The node id of a key.
#[inline(always)]
pub fn id(key: u64) -> i32 {
    key as u32 as i32
}

/// The distance bits of a key (compare with `f32::to_bits` of a non-negative float).
#[inline(always)]
pub fn dist_bits(key: u64) -> u32 {
    (key >> 32) as u32
}

/// Orders `s[a] >= s[b]` (one comparator of a sorting network; branch-free).
#[inline(always)]
fn cswap(s: &mut [u64], a: usize, b: usize) {
    let (x, y) = (s[a], s[b]);
    s[a] = x.max(y);
    s[b] = x.min(y);
}

/// Sorts the 3 top entries, nearest on top (3 comparators).
#[inline(always)]
pub fn sort_top3(s: &mut [u64]) {
    cswap(s, 0, 1);
    cswap(s, 1, 2);
    cswap(s, 0, 1);
}

/// Sorts the 4 top entries, nearest on top (5 comparators).
#[inline(always)]
pub fn sort_top4(s: &mut [u64]) {
    cswap(s, 0, 1);
    cswap(s, 2, 3);
    cswap(s, 0, 2);
    cswap(s, 1, 3);
    cswap(s, 1, 2);
}

/// Insertion sort of the top entries, nearest on top (the rare 5–N hit case).
#[inline(always)]
pub fn sort_top(s: &mut [u64]) {
    for i in 1..s.len() {
        let k = s[i];
        let mut j = i;
        while j > 0 && s[j - 1] < k {
            s[j] = s[j - 1];
            j -= 1;
        }
        s[j] = k;
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn networks_sort_descending() {
        // Every permutation of 3 and 4 distinct keys (and some with equal ones).
        let mut perms: Vec<Vec<u64>> = vec![vec![]];
        for n in 1..=5u64 {
            let mut next = Vec::new();
            for p in &perms {
                for pos in 0..=p.len() {
                    let mut q = p.clone();
                    q.insert(pos, n);
                    next.push(q);
                }
            }
            perms = next;
            for p in &perms {
                let mut want = p.clone();
                want.sort_by(|a, b| b.cmp(a));
                let mut got = p.clone();
                match got.len() {
                    3 => sort_top3(&mut got),
                    4 => sort_top4(&mut got),
                    _ => sort_top(&mut got),
                }
                assert_eq!(got, want, "{p:?}");
                let mut dup: Vec<u64> = p.iter().map(|x| x / 2).collect();
                let mut want: Vec<u64> = dup.clone();
                want.sort_by(|a, b| b.cmp(a));
                sort_top(&mut dup);
                assert_eq!(dup, want);
            }
        }
    }

    #[test]
    fn keys_order_by_distance() {
        let ds = [0.0f32, 1e-30, 0.5, 1.0, 3.0e8, f32::INFINITY];
        for w in ds.windows(2) {
            assert!(key(w[0], -5) < key(w[1], 0));
            assert!(key(w[0], 7) < key(w[1], 3));
        }
        assert_eq!(id(key(2.0, -123)), -123);
        assert_eq!(dist_bits(key(2.0, 9)), 2.0f32.to_bits());
    }
}
