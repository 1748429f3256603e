//! Built accelerators, kept between jobs and shared by concurrent ones.
//!
//! The key holds everything that changes a structure's answers or its speed: which
//! positions ([`GeometryKey`]: scene, version, time), the accelerator, its build quality,
//! the precision, the SIMD backend and the DACRT settings. Entries are `Arc`s: a trace
//! holds its structure for as long as it runs, whatever the cache evicts meanwhile, and a
//! new geometry version is refitted into a copy ([`crate::accel::Intersector::refit_copy`])
//! so that traces of the old version keep answering from the old one.
//!
//! The cache is bounded by a memory budget and evicts the least recently used entries.
//! It does not make concurrent misses of one key wait for a single build: builds run on the
//! rayon pool, where blocking one worker on another's build can deadlock the pool; the
//! scheduler already runs one step at a time, so a duplicate build can only happen between
//! two steps, and the second finds the first's entry.

use std::collections::HashMap;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex};

use super::GeometryKey;
use crate::accel::{AccelKind, BuildQuality, Intersector, Precision};

/// What a cached structure is.
#[derive(Clone, Debug, PartialEq, Eq, Hash)]
pub struct StructureKey {
    /// The positions it was built over.
    pub geometry: GeometryKey,
    /// The accelerator (resolved: never `auto`).
    pub accel: AccelKind,
    /// Build quality (only BVH cores and Embree use it; others keep the default).
    pub quality: BuildQuality,
    /// Ray/triangle test.
    pub precision: Precision,
    /// SIMD backend the structure traces with.
    pub simd: &'static str,
    /// [`crate::accel::dacrt::DacrtTuning::fingerprint`] for the DACRT cores, else 0.
    pub tuning: u64,
}

impl StructureKey {
    /// Whether `other` is the same kind of structure over other positions of the same
    /// scene: something a refit can start from.
    fn same_family(&self, other: &StructureKey) -> bool {
        self.geometry.scene == other.geometry.scene
            && self.geometry != other.geometry
            && self.accel == other.accel
            && self.quality == other.quality
            && self.precision == other.precision
            && self.simd == other.simd
            && self.tuning == other.tuning
    }
}

struct Entry {
    accel: Arc<dyn Intersector>,
    bytes: usize,
    last_used: u64,
}

#[derive(Default)]
struct State {
    entries: HashMap<StructureKey, Entry>,
    bytes: usize,
    clock: u64,
}

/// Counters for `/metrics` and reports.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, serde::Serialize)]
pub struct CacheStats {
    /// Lookups that found their structure.
    pub hits: u64,
    /// Lookups that did not.
    pub misses: u64,
    /// Entries held.
    pub entries: usize,
    /// Bytes held (the structures' own, beyond the positions).
    pub bytes: usize,
    /// The budget.
    pub budget: usize,
}

/// The cache (see the module docs).
pub struct StructureCache {
    budget: usize,
    state: Mutex<State>,
    hits: AtomicU64,
    misses: AtomicU64,
}

impl StructureCache {
    /// A cache that holds at most `budget` bytes of structures.
    pub fn new(budget: usize) -> StructureCache {
        StructureCache {
            budget,
            state: Mutex::new(State::default()),
            hits: AtomicU64::new(0),
            misses: AtomicU64::new(0),
        }
    }

    fn lock(&self) -> std::sync::MutexGuard<'_, State> {
        self.state.lock().unwrap_or_else(|e| e.into_inner())
    }

    /// The structure for `key`, if held; counts a hit or a miss.
    pub fn get(&self, key: &StructureKey) -> Option<Arc<dyn Intersector>> {
        let mut s = self.lock();
        s.clock += 1;
        let now = s.clock;
        match s.entries.get_mut(key) {
            Some(e) => {
                e.last_used = now;
                self.hits.fetch_add(1, Ordering::Relaxed);
                Some(Arc::clone(&e.accel))
            }
            None => {
                self.misses.fetch_add(1, Ordering::Relaxed);
                None
            }
        }
    }

    /// Whether `key` is held, without counting or touching it (for `auto`'s model).
    pub fn contains(&self, key: &StructureKey) -> bool {
        self.lock().entries.contains_key(key)
    }

    /// The most recently used structure of the same kind over other positions of the same
    /// scene: a refit of it gives `key`'s structure.
    pub fn refittable(&self, key: &StructureKey) -> Option<Arc<dyn Intersector>> {
        let s = self.lock();
        s.entries
            .iter()
            .filter(|(k, _)| key.same_family(k))
            .max_by_key(|(_, e)| e.last_used)
            .map(|(_, e)| Arc::clone(&e.accel))
    }

    /// Keeps `accel` under `key`, evicting least recently used entries to stay within the
    /// budget. A structure larger than the whole budget is not kept.
    pub fn insert(&self, key: StructureKey, accel: Arc<dyn Intersector>) {
        let bytes = accel.bytes();
        if bytes > self.budget {
            return;
        }
        let mut s = self.lock();
        s.clock += 1;
        let now = s.clock;
        if let Some(old) = s.entries.insert(
            key,
            Entry {
                accel,
                bytes,
                last_used: now,
            },
        ) {
            s.bytes -= old.bytes;
        }
        s.bytes += bytes;
        while s.bytes > self.budget {
            let Some(oldest) = s
                .entries
                .iter()
                .min_by_key(|(_, e)| e.last_used)
                .map(|(k, _)| k.clone())
            else {
                break;
            };
            let e = s.entries.remove(&oldest).expect("just found");
            s.bytes -= e.bytes;
        }
    }

    /// Drops every structure of `scene` (the scene was deleted).
    pub fn forget_scene(&self, scene: &str) {
        let mut s = self.lock();
        let gone: Vec<_> = s
            .entries
            .keys()
            .filter(|k| &*k.geometry.scene == scene)
            .cloned()
            .collect();
        for k in gone {
            let e = s.entries.remove(&k).expect("just listed");
            s.bytes -= e.bytes;
        }
    }

    /// Counters and sizes.
    pub fn stats(&self) -> CacheStats {
        let s = self.lock();
        CacheStats {
            hits: self.hits.load(Ordering::Relaxed),
            misses: self.misses.load(Ordering::Relaxed),
            entries: s.entries.len(),
            bytes: s.bytes,
            budget: self.budget,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::accel::{build, BuildOptions};
    use crate::geometry::Triangle;

    fn key(version: u32) -> StructureKey {
        StructureKey {
            geometry: GeometryKey::new("s", version, None),
            accel: AccelKind::Mbvh8,
            quality: BuildQuality::Sah,
            precision: Precision::Watertight,
            simd: "scalar",
            tuning: 0,
        }
    }

    fn structure(n: usize) -> Arc<dyn Intersector> {
        let tris: Vec<Triangle> = (0..n)
            .map(|i| Triangle {
                v: [
                    [i as f32, 0.0, 0.0],
                    [i as f32 + 1.0, 0.0, 0.0],
                    [i as f32, 1.0, 0.0],
                ],
            })
            .collect();
        Arc::from(build(AccelKind::Mbvh8, &tris, &BuildOptions::default()).unwrap())
    }

    #[test]
    fn hits_misses_and_refittable() {
        let c = StructureCache::new(1 << 30);
        assert!(c.get(&key(1)).is_none());
        c.insert(key(1), structure(100));
        assert!(c.get(&key(1)).is_some());
        assert!(
            c.refittable(&key(1)).is_none(),
            "the same positions are no refit"
        );
        assert!(c.refittable(&key(2)).is_some());
        let st = c.stats();
        assert_eq!((st.hits, st.misses, st.entries), (1, 1, 1));
        c.forget_scene("s");
        assert_eq!(c.stats().entries, 0);
        assert_eq!(c.stats().bytes, 0);
    }

    #[test]
    fn the_budget_evicts_the_least_recently_used() {
        let one = structure(1000).bytes();
        let c = StructureCache::new(2 * one + one / 2);
        c.insert(key(1), structure(1000));
        c.insert(key(2), structure(1000));
        assert!(c.get(&key(1)).is_some()); // 2 is now the oldest
        c.insert(key(3), structure(1000));
        assert!(c.contains(&key(1)) && c.contains(&key(3)) && !c.contains(&key(2)));
        assert!(c.stats().bytes <= c.stats().budget);
    }
}
