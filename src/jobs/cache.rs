//! Built accelerators and decoded textures, kept between jobs and shared by concurrent
//! ones.
//!
//! A structure's key holds everything that changes a structure's answers or its speed: which
//! positions ([`GeometryKey`]: scene, version, time), the accelerator, its build quality,
//! the precision, the SIMD backend and the DACRT settings. Entries are `Arc`s: a trace
//! holds its structure for as long as it runs, whatever the cache evicts meanwhile, and a
//! new geometry version is refitted into a copy ([`crate::accel::Intersector::refit_copy`])
//! so that traces of the old version keep answering from the old one.
//!
//! Each cache is bounded by a memory budget and evicts the least recently used entries
//! ([`Lru`]). The structure cache does not make concurrent misses of one key wait for a single build: builds run on the
//! rayon pool, where blocking one worker on another's build can deadlock the pool; the
//! scheduler already runs one step at a time, so a duplicate build can only happen between
//! two steps, and the second finds the first's entry.

use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex};

use super::lru::Lru;
use super::GeometryKey;
use crate::accel::{AccelKind, BuildQuality, Intersector, Precision};
use crate::render::lights::LightSampler;
use crate::render::texture::TextureSet;

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

/// Counters for `/metrics` and reports.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, serde::Serialize)]
pub struct CacheStats {
    /// Lookups that found their entry.
    pub hits: u64,
    /// Lookups that did not.
    pub misses: u64,
    /// Entries held.
    pub entries: usize,
    /// Bytes held (the entries' own: a structure's beyond the positions, a scene's texels).
    pub bytes: usize,
    /// The budget.
    pub budget: usize,
}

/// An [`Lru`] behind a lock, with hit and miss counters.
struct Counted<K, V> {
    lru: Mutex<Lru<K, V>>,
    hits: AtomicU64,
    misses: AtomicU64,
}

impl<K: Eq + std::hash::Hash + Clone, V: Clone> Counted<K, V> {
    fn new(budget: usize) -> Self {
        Counted {
            lru: Mutex::new(Lru::new(budget)),
            hits: AtomicU64::new(0),
            misses: AtomicU64::new(0),
        }
    }

    fn lock(&self) -> std::sync::MutexGuard<'_, Lru<K, V>> {
        self.lru.lock().unwrap_or_else(|e| e.into_inner())
    }

    /// The entry for `key`: a held one (a hit), or `make`'s (a miss), kept when its
    /// `bytes` fit the budget. Made outside the lock, so that other keys' lookups go on
    /// meanwhile; concurrent misses of one key both make it, and the second to finish
    /// replaces the first's entry with an equal one.
    /// `keep` is asked under the lock, after making: whether the entry may still be kept.
    fn get_or_make<E>(
        &self,
        key: K,
        make: impl FnOnce() -> Result<V, E>,
        bytes: impl FnOnce(&V) -> usize,
        keep: impl FnOnce() -> bool,
    ) -> Result<V, E> {
        if let Some(v) = self.get(&key) {
            return Ok(v);
        }
        let v = make()?;
        let size = bytes(&v);
        let mut lru = self.lock();
        if keep() {
            lru.insert(key, v.clone(), size);
        }
        Ok(v)
    }

    /// The entry for `key`, if held; counts a hit or a miss.
    fn get(&self, key: &K) -> Option<V> {
        let found = self.lock().get(key).cloned();
        let counter = if found.is_some() {
            &self.hits
        } else {
            &self.misses
        };
        counter.fetch_add(1, Ordering::Relaxed);
        found
    }

    fn stats(&self) -> CacheStats {
        let l = self.lock();
        CacheStats {
            hits: self.hits.load(Ordering::Relaxed),
            misses: self.misses.load(Ordering::Relaxed),
            entries: l.len(),
            bytes: l.bytes(),
            budget: l.budget(),
        }
    }
}

/// Built structures under their [`StructureKey`]s.
pub struct StructureCache(Counted<StructureKey, Arc<dyn Intersector>>);

impl StructureCache {
    /// A cache that holds at most `budget` bytes of structures.
    pub fn new(budget: usize) -> StructureCache {
        StructureCache(Counted::new(budget))
    }

    /// The structure for `key`, if held; counts a hit or a miss.
    pub fn get(&self, key: &StructureKey) -> Option<Arc<dyn Intersector>> {
        self.0.get(key)
    }

    /// Whether `key` is held, without counting or touching it (for `auto`'s model).
    pub fn contains(&self, key: &StructureKey) -> bool {
        self.0.lock().contains(key)
    }

    /// The most recently used structure of the same kind over other positions of the same
    /// scene: a refit of it gives `key`'s structure.
    pub fn refittable(&self, key: &StructureKey) -> Option<Arc<dyn Intersector>> {
        self.0.lock().most_recent(|k| key.same_family(k)).cloned()
    }

    /// Keeps `accel` under `key`, evicting least recently used entries to stay within the
    /// budget. A structure larger than the whole budget is not kept.
    pub fn insert(&self, key: StructureKey, accel: Arc<dyn Intersector>) {
        self.insert_if(key, accel, || true);
    }

    /// [`StructureCache::insert`] if `keep`, asked under the cache's lock (so that a
    /// [`StructureCache::forget_scene`] cannot come between the answer and the insert).
    pub fn insert_if(
        &self,
        key: StructureKey,
        accel: Arc<dyn Intersector>,
        keep: impl FnOnce() -> bool,
    ) {
        let bytes = accel.bytes();
        let mut lru = self.0.lock();
        if keep() {
            lru.insert(key, accel, bytes);
        }
    }

    /// Drops every structure of `scene` (the scene was deleted).
    pub fn forget_scene(&self, scene: &str) {
        self.0.lock().remove_where(|k| &*k.geometry.scene == scene);
    }

    /// Counters and sizes.
    pub fn stats(&self) -> CacheStats {
        self.0.stats()
    }
}

/// Scenes' decoded textures (MIP pyramids and interleaved bundles), under the scene's id,
/// kept between render jobs. Decoding DamagedHelmet's four 2048² JPEGs and building their
/// levels takes far longer than rendering a small frame of it (BENCHMARKS.md §26), and
/// neither a new geometry version nor an animation time changes a texel, so a scene's
/// textures serve every later job that shades it. Concurrent first jobs of one scene may
/// both decode; the second to finish replaces the first's entry with an equal one.
pub struct TextureCache(Counted<Arc<str>, Arc<TextureSet>>);

impl TextureCache {
    /// A cache that holds at most `budget` bytes of texels.
    pub fn new(budget: usize) -> TextureCache {
        TextureCache(Counted::new(budget))
    }

    /// The textures of scene `scene`: held ones (a hit), or `decode`'s, which are kept
    /// when they fit the budget (a miss).
    pub fn get_or_decode<E>(
        &self,
        scene: &str,
        decode: impl FnOnce() -> Result<TextureSet, E>,
    ) -> Result<Arc<TextureSet>, E> {
        self.0.get_or_make(
            Arc::from(scene),
            || decode().map(Arc::new),
            |t| t.bytes(),
            || true,
        )
    }

    /// Drops scene `scene`'s textures (the scene was deleted).
    pub fn forget_scene(&self, scene: &str) {
        self.0.lock().remove_where(|k| &**k == scene);
    }

    /// Counters and sizes.
    pub fn stats(&self) -> CacheStats {
        self.0.stats()
    }
}

/// What a kept light table was built for: the positions, the sky and whether emitters and
/// sky are sampled (`light_sampling`). The surfaces are the scene's (its id is in the
/// geometry key), the same for every job of the scene.
#[derive(Clone, Debug, PartialEq, Eq, Hash)]
pub struct LightKey {
    /// The positions.
    pub geometry: GeometryKey,
    /// The sky's radiance, as bits.
    pub sky: [u32; 3],
    /// Whether emissive triangles and the sky are in the table.
    pub light_sampling: bool,
}

/// Path-traced frames' light tables ([`LightSampler`]), kept between render jobs of the
/// same positions: weighing a textured scene's emitters reads their emissive texels, as
/// many instructions as a small frame's texture lookups (BENCHMARKS.md §30).
pub struct LightCache(Counted<LightKey, Arc<LightSampler>>);

impl LightCache {
    /// A cache that holds at most `budget` bytes of tables.
    pub fn new(budget: usize) -> LightCache {
        LightCache(Counted::new(budget))
    }

    /// The table for `key`: a held one (a hit) or `build`'s (a miss), kept when it fits
    /// and `keep` (asked under the cache's lock after the build) says it may be.
    pub fn get_or_build<E>(
        &self,
        key: LightKey,
        build: impl FnOnce() -> Result<LightSampler, E>,
        keep: impl FnOnce() -> bool,
    ) -> Result<Arc<LightSampler>, E> {
        self.0
            .get_or_make(key, || build().map(Arc::new), |t| t.bytes(), keep)
    }

    /// Drops scene `scene`'s tables (the scene was deleted).
    pub fn forget_scene(&self, scene: &str) {
        self.0.lock().remove_where(|k| &*k.geometry.scene == scene);
    }

    /// Counters and sizes.
    pub fn stats(&self) -> CacheStats {
        self.0.stats()
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
    fn textures_are_decoded_once_per_scene_within_the_budget() {
        let c = TextureCache::new(1 << 20);
        let decodes = std::cell::Cell::new(0);
        let decode = || -> Result<TextureSet, ()> {
            decodes.set(decodes.get() + 1);
            Ok(TextureSet::default())
        };
        let a = c.get_or_decode("s", decode).unwrap();
        let b = c.get_or_decode("s", decode).unwrap();
        assert!(Arc::ptr_eq(&a, &b));
        c.get_or_decode("t", decode).unwrap();
        assert_eq!(decodes.get(), 2);
        let st = c.stats();
        assert_eq!((st.hits, st.misses, st.entries), (1, 2, 2));
        // A failed decode keeps nothing and returns its error.
        assert!(c
            .get_or_decode("u", || Err::<TextureSet, _>("bad"))
            .is_err());
        assert_eq!(c.stats().entries, 2);
        c.forget_scene("s");
        assert_eq!(c.stats().entries, 1);
        c.get_or_decode("s", decode).unwrap();
        assert_eq!(decodes.get(), 3);
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
