//! A map bounded by the bytes of what it holds, which evicts its least recently used
//! entries: the bookkeeping that the engine's caches of built structures
//! ([`super::cache::StructureCache`]) and decoded textures ([`super::cache::TextureCache`])
//! and the service's parsed scenes and evaluated geometry share. It is not synchronised;
//! each cache keeps it behind its own lock.

use std::collections::HashMap;
use std::hash::Hash;

struct Slot<V> {
    value: V,
    bytes: usize,
    last_used: u64,
}

/// Entries of `V` under keys `K`, each with its size in bytes, at most `budget` bytes in all.
pub struct Lru<K, V> {
    budget: usize,
    /// Whether an entry larger than the budget is kept (alone) rather than refused.
    keep_one: bool,
    entries: HashMap<K, Slot<V>>,
    bytes: usize,
    clock: u64,
}

impl<K: Eq + Hash + Clone, V> Lru<K, V> {
    /// An empty map that holds at most `budget` bytes.
    pub fn new(budget: usize) -> Lru<K, V> {
        Lru {
            budget,
            keep_one: false,
            entries: HashMap::new(),
            bytes: 0,
            clock: 0,
        }
    }

    /// An empty map that holds at most `budget` bytes, or its one most recently used entry
    /// when that alone is larger: for what every request needs again (a scene too large
    /// for the budget is still kept while it is the one in use).
    pub fn keeping_one(budget: usize) -> Lru<K, V> {
        Lru {
            keep_one: true,
            ..Lru::new(budget)
        }
    }

    /// The entry under `key`, now the most recently used.
    pub fn get(&mut self, key: &K) -> Option<&V> {
        self.clock += 1;
        let now = self.clock;
        let slot = self.entries.get_mut(key)?;
        slot.last_used = now;
        Some(&slot.value)
    }

    /// Whether `key` is held (its recency unchanged).
    pub fn contains(&self, key: &K) -> bool {
        self.entries.contains_key(key)
    }

    /// Keeps `value` of `bytes` bytes under `key` (replacing what was there), then evicts
    /// the least recently used entries until the map is within its budget. A value larger
    /// than the whole budget is not kept (`false`), unless the map keeps one
    /// ([`Lru::keeping_one`]): then it is kept alone.
    pub fn insert(&mut self, key: K, value: V, bytes: usize) -> bool {
        if bytes > self.budget && !self.keep_one {
            return false;
        }
        self.clock += 1;
        let slot = Slot {
            value,
            bytes,
            last_used: self.clock,
        };
        if let Some(old) = self.entries.insert(key, slot) {
            self.bytes -= old.bytes;
        }
        self.bytes += bytes;
        while self.bytes > self.budget && self.entries.len() > 1 {
            // The new entry is the most recent, so another goes first.
            let Some(oldest) = self
                .entries
                .iter()
                .min_by_key(|(_, s)| s.last_used)
                .map(|(k, _)| k.clone())
            else {
                break;
            };
            self.remove(&oldest);
        }
        true
    }

    fn remove(&mut self, key: &K) {
        if let Some(s) = self.entries.remove(key) {
            self.bytes -= s.bytes;
        }
    }

    /// Drops every entry whose key `drop` picks.
    pub fn remove_where(&mut self, drop: impl Fn(&K) -> bool) {
        let gone: Vec<K> = self.entries.keys().filter(|k| drop(k)).cloned().collect();
        for k in &gone {
            self.remove(k);
        }
    }

    /// The most recently used entry whose key `pick` picks (its recency unchanged).
    pub fn most_recent(&self, pick: impl Fn(&K) -> bool) -> Option<&V> {
        self.entries
            .iter()
            .filter(|(k, _)| pick(k))
            .max_by_key(|(_, s)| s.last_used)
            .map(|(_, s)| &s.value)
    }

    /// Entries held.
    pub fn len(&self) -> usize {
        self.entries.len()
    }

    /// Bytes held.
    pub fn bytes(&self) -> usize {
        self.bytes
    }

    /// The budget.
    pub fn budget(&self) -> usize {
        self.budget
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn evicts_the_least_recently_used_to_stay_within_the_budget() {
        let mut m = Lru::new(10);
        assert!(m.insert("a", 1, 4));
        assert!(m.insert("b", 2, 4));
        // Touching "a" makes "b" the oldest.
        assert_eq!(m.get(&"a"), Some(&1));
        assert!(m.insert("c", 3, 4));
        assert!(!m.contains(&"b") && m.contains(&"a") && m.contains(&"c"));
        assert_eq!((m.len(), m.bytes()), (2, 8));
        // Replacing an entry counts its new size, not both.
        assert!(m.insert("a", 9, 6));
        assert_eq!((m.len(), m.bytes()), (2, 10));
        // Too large for the whole budget: not kept, and nothing evicted for it.
        assert!(!m.insert("d", 4, 11));
        assert_eq!((m.len(), m.bytes()), (2, 10));
        assert_eq!(m.most_recent(|_| true), Some(&9));
        assert_eq!(m.most_recent(|k| *k == "c"), Some(&3));
        m.remove_where(|k| *k == "a");
        assert_eq!((m.len(), m.bytes()), (1, 4));
        m.remove_where(|_| true);
        assert!(m.len() == 0 && m.bytes() == 0 && m.budget() == 10);
    }

    #[test]
    fn keeping_one_keeps_the_newest_alone_when_it_is_too_large() {
        let mut m = Lru::keeping_one(10);
        assert!(m.insert("a", 1, 4));
        assert!(m.insert("b", 2, 4));
        assert!(m.insert("big", 3, 25));
        assert_eq!((m.len(), m.bytes()), (1, 25));
        assert_eq!(m.get(&"big"), Some(&3));
        // The next entry evicts it as usual.
        assert!(m.insert("c", 4, 4));
        assert_eq!((m.len(), m.bytes()), (1, 4));
    }

    #[test]
    fn a_zero_budget_keeps_nothing_but_empty_entries() {
        let mut m = Lru::new(0);
        assert!(!m.insert(1, "x", 1));
        assert!(m.insert(2, "y", 0));
        assert_eq!(m.get(&2), Some(&"y"));
        assert_eq!(m.get(&1), None);
    }
}
