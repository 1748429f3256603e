//! Where a trace spends its time (Áfra 2012 §4 reports filtering / intersection /
//! partitioning shares): thread-time per phase and work counters, collected only when asked
//! for, because reading the clock around every step costs a few percent.

use std::sync::atomic::{AtomicU64, Ordering::Relaxed};
use std::time::Instant;

/// Counters of one trace (summed over threads).
#[derive(Debug, Default)]
pub struct Stats {
    /// Nanoseconds in ray filtering (including the copies made for forks).
    pub filter_ns: AtomicU64,
    /// Nanoseconds in leaf intersection.
    pub leaf_ns: AtomicU64,
    /// Nanoseconds in triangle partitioning, binning and ray sampling.
    pub split_ns: AtomicU64,
    /// Nanoseconds merging fork results back.
    pub merge_ns: AtomicU64,
    /// Ray/box tests.
    pub box_tests: AtomicU64,
    /// Ray/triangle tests.
    pub tri_tests: AtomicU64,
    /// Inner nodes.
    pub nodes: AtomicU64,
    /// Leaves.
    pub leaves: AtomicU64,
    /// Children given their parent's rays unfiltered (Nabata's skip).
    pub skips: AtomicU64,
    /// Nodes whose split used sample rays.
    pub sampled: AtomicU64,
    /// Nodes that used the binned split.
    pub binned: AtomicU64,
    /// Forks whose second child ran on another thread.
    pub forks_stolen: AtomicU64,
    /// Forks whose second child ran on the same thread.
    pub forks_local: AtomicU64,
    /// Nodes of the shared top levels (`top.rs`), partitioned once for all threads.
    pub top_nodes: AtomicU64,
}

/// Adds the time since `t0` to `into` (when timing).
#[inline]
pub fn lap(into: &AtomicU64, t0: Option<Instant>) {
    if let Some(t0) = t0 {
        into.fetch_add(t0.elapsed().as_nanos() as u64, Relaxed);
    }
}

impl Stats {
    /// Adds `n` to a counter.
    #[inline]
    pub fn add(c: &AtomicU64, n: u64) {
        c.fetch_add(n, Relaxed);
    }

    /// Counts a fork, by where its second half ran (on a thief when `migrated`).
    #[inline]
    pub fn fork(stats: Option<&Stats>, migrated: bool) {
        if let Some(s) = stats {
            let c = if migrated {
                &s.forks_stolen
            } else {
                &s.forks_local
            };
            Stats::add(c, 1);
        }
    }

    /// One line for stderr.
    pub fn summary(&self, name: &str, rays: usize, wall_s: f64) -> String {
        let g = |c: &AtomicU64| c.load(Relaxed);
        let (f, l, s, m) = (
            g(&self.filter_ns),
            g(&self.leaf_ns),
            g(&self.split_ns),
            g(&self.merge_ns),
        );
        let total = (f + l + s + m).max(1) as f64;
        let pct = |x: u64| 100.0 * x as f64 / total;
        format!(
            "{name}: {rays} rays in {:.1} ms: filter {:.0}% intersect {:.0}% partition {:.0}% \
             merge {:.0}% (thread-ms {:.1}); {:.1} box tests/ray, {:.1} tri tests/ray; \
             {} nodes ({} binned, {} sampled, {} skips), {} leaves; forks {} stolen {} local; {} shared top nodes",
            wall_s * 1e3,
            pct(f),
            pct(l),
            pct(s),
            pct(m),
            total / 1e6,
            g(&self.box_tests) as f64 / rays.max(1) as f64,
            g(&self.tri_tests) as f64 / rays.max(1) as f64,
            g(&self.nodes),
            g(&self.binned),
            g(&self.sampled),
            g(&self.skips),
            g(&self.leaves),
            g(&self.forks_stolen),
            g(&self.forks_local),
            g(&self.top_nodes),
        )
    }
}
