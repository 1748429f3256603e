//! The tunables of both DACRT accelerators, with the papers' values as defaults and an
//! environment override for each, so that every gain can be measured on its own from the
//! command line (`RAYD_DACRT_SAMPLE_SKIP=0 rayd bench ...`) without a rebuild.

/// Which of Nabata et al.'s three gains are on (each can be measured alone, as §5 does).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Sampling {
    /// Choose the split plane by the sampled cost (eq. 2) instead of the SAH.
    pub cost: bool,
    /// Visit first the child that more sample rays reach first (§4.3).
    pub order: bool,
    /// Give a child its parent's rays unfiltered when more than half the sample rays enter
    /// it (eq. 5–6).
    pub skip: bool,
    /// Sample rays per node (Nabata: 100).
    pub samples: usize,
    /// Sample only nodes with more active rays than this (Nabata: 1000).
    pub min_rays: usize,
    /// Cost of a ray/box test relative to a ray/triangle test (`C_bv / C_tri` of eq. 5),
    /// for the skip decision of children that will be leaves.
    pub box_cost: f32,
    /// Weight of the SAH's area ratio in the sampled hit probability, in sample rays
    /// (`sampling::sampled_cost`; 0: the paper's cost).
    pub prior: f32,
}

impl Sampling {
    /// No sampling: Áfra 2012.
    pub const OFF: Sampling = Sampling {
        cost: false,
        order: false,
        skip: false,
        samples: 100,
        min_rays: 1000,
        box_cost: 1.0,
        prior: 0.0,
    };

    /// All three gains: Nabata et al. 2013, with two settings measured here rather than
    /// taken from the paper (callgrind instruction counts, dragon interior view, 1024×768,
    /// primary and diffuse2 rays): sampling starts at 3000 active rays, not 1000 (the
    /// paper's frames had 16M rays; in a 0.8M-ray batch the 100 samples of a node of a
    /// few thousand rays cost about what its filtering does), and the SAH prior weighs 200
    /// sample rays (with 100 samples and a weight of 50 the sampled cost chose worse
    /// planes than the SAH alone).
    pub const ALL: Sampling = Sampling {
        cost: true,
        order: true,
        skip: true,
        samples: 100,
        min_rays: 3000,
        box_cost: 1.0,
        prior: 200.0,
    };

    /// Whether any gain is on.
    pub fn enabled(&self) -> bool {
        self.cost || self.order || self.skip
    }
}

/// What a fork splits (see `parallel.rs`).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum ForkSplit {
    /// Two coherent halves of the rays traverse the same node at once.
    Rays,
    /// The two children run at once, each on a copy of its rays.
    Tris,
}

/// How the recursion uses several threads (see `parallel.rs`).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Parallelism {
    /// Master switch (off: one thread whatever the pool).
    pub enabled: bool,
    /// Nodes with at least this many active rays filter them data-parallel, in place,
    /// instead of forking. Off by default (ray-split forks from the root cost only a second
    /// partitioning of the top few nodes, while a data-parallel filter moves misplaced
    /// records a second time at every node); with triangle-split forks the trace lowers it
    /// to a quarter of the fork budget, so that forks are small enough to fit several at
    /// once.
    pub data_min_rays: usize,
    /// Nodes with fewer than `data_min_rays` but at least this many active rays hand their
    /// second child to another thread (with a copy of its rays).
    pub fork_min_rays: usize,
    /// Ray records that forks may copy at once, as a fraction of the batch.
    pub fork_budget: f32,
    /// Triangle ranges at least this long are binned and partitioned data-parallel.
    pub data_min_tris: usize,
    /// Data-parallel passes split their ranges down to pieces of this many elements.
    pub grain: usize,
    /// What forks split.
    pub split: ForkSplit,
    /// With several threads, the triangles are partitioned once for all threads down to
    /// nodes of this many triangles before the batch's rays are split (`top.rs`), so that
    /// the halves do not partition the top levels twice. 0: off (each half partitions
    /// everything it reaches).
    pub top_min_tris: usize,
}

impl Default for Parallelism {
    fn default() -> Self {
        Parallelism {
            enabled: true,
            data_min_rays: usize::MAX,
            fork_min_rays: 1 << 10,
            fork_budget: 0.125,
            data_min_tris: 1 << 13,
            grain: 1 << 14,
            split: ForkSplit::Rays,
            top_min_tris: 1 << 12,
        }
    }
}

/// Every tunable of the traversal.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct DacrtOptions {
    /// A node with fewer active rays than this is a leaf (Áfra: 8).
    pub leaf_rays: usize,
    /// A node with fewer triangles than this is a leaf (Áfra: 8).
    pub leaf_tris: usize,
    /// Above this ratio of active rays to triangles a node is split by binning (SAH or the
    /// sampled cost), below it at the middle (Áfra: 1–2 best; Nabata: 1.5).
    pub sah_ratio: f32,
    /// Bin all three axes for the binned splits, not only the widest centroid axis
    /// (Áfra's choice): better splits where huge triangles (a room's walls) share nodes
    /// with small ones, for three times the binning.
    pub all_axes: bool,
    /// The binned splits also consider separating the triangles whose box has more than
    /// this fraction of the node's surface area from the others (0: off; not in the
    /// papers). See `split::Bins::empty_on`.
    pub big_fraction: f32,
    /// Cost of a traversal step relative to a ray/triangle test, for the SAH's leaf
    /// decision.
    pub traversal_cost: f32,
    /// The SAH may end the recursion only for nodes of at most this many triangles (a
    /// greedy SAH stop on a big node would make a huge leaf).
    pub sah_stop_max: usize,
    /// Filter both children in one pass (a three-way partition), and after the first child
    /// filter only its rays again for the second (not in the papers; off: Áfra's two full
    /// passes).
    pub two_box: bool,
    /// Nabata's gains.
    pub sampling: Sampling,
    /// Threads.
    pub parallel: Parallelism,
    /// Collect the time split (filtering, intersection, partitioning) and print it to stderr
    /// after every trace.
    pub stats: bool,
}

impl DacrtOptions {
    /// Áfra 2012.
    pub fn afra() -> DacrtOptions {
        DacrtOptions {
            leaf_rays: 8,
            leaf_tris: 16,
            sah_ratio: 1.5,
            all_axes: false,
            big_fraction: 0.1,
            traversal_cost: 1.0,
            sah_stop_max: 32,
            two_box: false,
            sampling: Sampling::OFF,
            parallel: Parallelism::default(),
            stats: false,
        }
    }

    /// Nabata et al. 2013.
    pub fn nabata() -> DacrtOptions {
        DacrtOptions {
            sampling: Sampling::ALL,
            ..DacrtOptions::afra()
        }
    }

    /// Applies the `RAYD_DACRT_*` environment overrides (see [`DacrtOptions::apply`]).
    pub fn with_env(self) -> DacrtOptions {
        self.apply(|k| std::env::var(k).ok())
    }

    /// Applies overrides from `get(name)`: `RAYD_DACRT_LEAF_RAYS`, `_LEAF_TRIS`,
    /// `_SAH_RATIO`, `_ALL_AXES` (0/1), `_BIG_FRACTION`, `_TRAVERSAL_COST`, `_TWO_BOX` (0/1), `_SAMPLES`, `_SAMPLE_MIN_RAYS`, `_BOX_COST`, `_SAMPLE_PRIOR`, `_SAMPLE_COST`,
    /// `_SAMPLE_ORDER`, `_SAMPLE_SKIP` (0/1; only where sampling is on), `_PARALLEL` (0/1),
    /// `_DATA_MIN_RAYS`, `_FORK_MIN_RAYS`, `_FORK_BUDGET`, `_DATA_MIN_TRIS`, `_GRAIN`, `_FORK_SPLIT` (rays/tris), `_TOP_MIN_TRIS`, `_STATS` (0/1).
    /// Unparsable values are ignored.
    pub fn apply(mut self, get: impl Fn(&str) -> Option<String>) -> DacrtOptions {
        fn num<T: std::str::FromStr>(v: Option<String>, into: &mut T) {
            if let Some(x) = v.and_then(|s| s.trim().parse().ok()) {
                *into = x;
            }
        }
        fn flag(v: Option<String>, into: &mut bool) {
            match v.as_deref().map(str::trim) {
                Some("0") | Some("false") | Some("off") => *into = false,
                Some("1") | Some("true") | Some("on") => *into = true,
                _ => {}
            }
        }
        let g = |k: &str| get(&format!("RAYD_DACRT_{k}"));
        num(g("LEAF_RAYS"), &mut self.leaf_rays);
        num(g("LEAF_TRIS"), &mut self.leaf_tris);
        num(g("SAH_RATIO"), &mut self.sah_ratio);
        num(g("TRAVERSAL_COST"), &mut self.traversal_cost);
        flag(g("ALL_AXES"), &mut self.all_axes);
        num(g("BIG_FRACTION"), &mut self.big_fraction);
        num(g("SAH_STOP_MAX"), &mut self.sah_stop_max);
        flag(g("TWO_BOX"), &mut self.two_box);
        num(g("SAMPLES"), &mut self.sampling.samples);
        num(g("SAMPLE_MIN_RAYS"), &mut self.sampling.min_rays);
        num(g("BOX_COST"), &mut self.sampling.box_cost);
        num(g("SAMPLE_PRIOR"), &mut self.sampling.prior);
        if self.sampling.enabled() {
            flag(g("SAMPLE_COST"), &mut self.sampling.cost);
            flag(g("SAMPLE_ORDER"), &mut self.sampling.order);
            flag(g("SAMPLE_SKIP"), &mut self.sampling.skip);
        }
        flag(g("PARALLEL"), &mut self.parallel.enabled);
        num(g("DATA_MIN_RAYS"), &mut self.parallel.data_min_rays);
        num(g("FORK_MIN_RAYS"), &mut self.parallel.fork_min_rays);
        num(g("FORK_BUDGET"), &mut self.parallel.fork_budget);
        num(g("DATA_MIN_TRIS"), &mut self.parallel.data_min_tris);
        num(g("GRAIN"), &mut self.parallel.grain);
        match g("FORK_SPLIT").as_deref().map(str::trim) {
            Some("rays") => self.parallel.split = ForkSplit::Rays,
            Some("tris") => self.parallel.split = ForkSplit::Tris,
            _ => {}
        }
        num(g("TOP_MIN_TRIS"), &mut self.parallel.top_min_tris);
        flag(g("STATS"), &mut self.stats);
        self.leaf_rays = self.leaf_rays.max(1);
        self.leaf_tris = self.leaf_tris.max(2);
        self.sampling.samples = self.sampling.samples.max(1);
        self.parallel.grain = self.parallel.grain.max(8);
        self
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn overrides_apply_and_sampling_switches_only_where_on() {
        let env = |k: &str| match k {
            "RAYD_DACRT_LEAF_RAYS" => Some("16".to_string()),
            "RAYD_DACRT_SAMPLE_SKIP" => Some("0".to_string()),
            "RAYD_DACRT_SAH_RATIO" => Some("nonsense".to_string()),
            _ => None,
        };
        let a = DacrtOptions::afra().apply(env);
        assert_eq!(a.leaf_rays, 16);
        assert_eq!(a.sah_ratio, 1.5);
        assert!(!a.sampling.enabled());
        let n = DacrtOptions::nabata().apply(env);
        assert!(n.sampling.cost && n.sampling.order && !n.sampling.skip);
    }
}

/// The settings of both DACRT cores, resolved once where the process starts (the command
/// line, the service) and passed to every build, so that a structure's settings are part of
/// its options and not read from the environment behind the caller's back.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct DacrtTuning {
    /// `dacrt`'s settings (Áfra 2012).
    pub afra: DacrtOptions,
    /// `dacrt-sampled`'s settings (Nabata et al. 2013).
    pub nabata: DacrtOptions,
}

impl Default for DacrtTuning {
    /// The papers' settings, as measured here (no environment).
    fn default() -> Self {
        DacrtTuning {
            afra: DacrtOptions::afra(),
            nabata: DacrtOptions::nabata(),
        }
    }
}

impl DacrtTuning {
    /// The defaults with the process's `RAYD_DACRT_*` overrides ([`DacrtOptions::apply`]).
    pub fn from_env() -> DacrtTuning {
        let d = DacrtTuning::default();
        DacrtTuning {
            afra: d.afra.with_env(),
            nabata: d.nabata.with_env(),
        }
    }

    /// A fingerprint of every setting, for cache keys: equal settings give equal values.
    pub fn fingerprint(&self) -> u64 {
        use std::hash::{Hash, Hasher};
        // Every field is a number or a flag; their Debug text names and spells each one.
        let mut h = std::collections::hash_map::DefaultHasher::new();
        format!("{self:?}").hash(&mut h);
        h.finish()
    }
}
