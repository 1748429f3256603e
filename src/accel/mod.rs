//! Everything that answers "what does this ray hit?".
//!
//! Every core answers the same batch verb, [`Intersector::trace`], because DACRT exists only
//! as a batch algorithm; single-ray cores loop inside it. Cores are chosen by [`AccelKind`]
//! and made by [`build`]. They parallelise on the rayon pool they are called in, so the
//! caller bounds the threads by installing a pool.

pub mod auto;
pub mod brute;
pub mod bvh;
pub mod dacrt;
#[cfg(feature = "embree")]
pub mod embree;
pub mod mbvh;
pub mod packet;
pub mod tiny_dir;
pub mod triangle;

use crate::geometry::{Hit, Ray, Triangle};

/// The accelerators of the contract (§3). Their names are the serde names below, used by
/// the command line, JSON and query strings alike ([`crate::names`]).
#[derive(
    Clone, Copy, Debug, PartialEq, Eq, Hash, Default, serde::Serialize, serde::Deserialize,
)]
#[serde(rename_all = "kebab-case")]
pub enum AccelKind {
    /// The one expected to be fastest for the job.
    #[default]
    Auto,
    /// Every ray against every triangle: the reference.
    Brute,
    /// Multi-BVH, 8 wide, single-ray ordered traversal (Áfra 2013).
    Mbvh8,
    /// Multi-BVH, 4 wide, single-ray ordered traversal.
    Mbvh4,
    /// Binary BVH with skip pointers, packets of 4 rays (Geimer & Müller).
    Bvh2,
    /// Intel Embree 3 (cargo feature `embree`): the peer.
    Embree,
    /// Divide-and-conquer ray tracing, no acceleration structure (Áfra 2012).
    Dacrt,
    /// DACRT with ray sampling (Nabata et al. 2013).
    DacrtSampled,
}

impl AccelKind {
    /// Every kind, in the order they are listed to users.
    pub const ALL: [AccelKind; 8] = [
        AccelKind::Auto,
        AccelKind::Brute,
        AccelKind::Mbvh8,
        AccelKind::Mbvh4,
        AccelKind::Bvh2,
        AccelKind::Dacrt,
        AccelKind::DacrtSampled,
        AccelKind::Embree,
    ];

    /// The contract's name.
    pub fn name(self) -> &'static str {
        crate::names::Spelled::name(self)
    }

    /// Parses the contract's name.
    pub fn parse(s: &str) -> Option<AccelKind> {
        crate::names::Spelled::parse_name(s).ok()
    }

    /// Whether this core traces a batch faster per ray the more rays it holds: DACRT's two,
    /// which partition the triangles anew for every batch. Callers that choose batch sizes
    /// (the renderer's waves, the service's streamed traces) make them as large as they can
    /// for these; the per-ray cores answer each ray alone.
    pub fn large_batches(self) -> bool {
        matches!(self, AccelKind::Dacrt | AccelKind::DacrtSampled)
    }

    /// Whether this build of rayd has the accelerator.
    pub fn available(self) -> bool {
        self != AccelKind::Embree || cfg!(feature = "embree")
    }

    /// What this kind runs as for `job`: `auto` becomes the accelerator its cost model
    /// expects to finish first ([`auto::choose`]); every other kind is itself.
    pub fn resolve(self, job: &auto::Job) -> AccelKind {
        match self {
            AccelKind::Auto => auto::choose(job),
            k => k,
        }
    }
}

crate::spelled!(AccelKind, AccelKind::ALL);

/// Which hit a query wants.
#[derive(
    Clone, Copy, Debug, PartialEq, Eq, Hash, Default, serde::Serialize, serde::Deserialize,
)]
#[serde(rename_all = "kebab-case")]
pub enum Query {
    /// The smallest t; among equal t, the lowest triangle id.
    #[default]
    Closest,
    /// Some hit in the interval.
    Any,
}

impl Query {
    /// The contract's name.
    pub fn name(self) -> &'static str {
        crate::names::Spelled::name(self)
    }
}

crate::spelled!(Query, [Query::Closest, Query::Any]);

/// Which ray/triangle test the cores use.
#[derive(
    Clone, Copy, Debug, PartialEq, Eq, Hash, Default, serde::Serialize, serde::Deserialize,
)]
#[serde(rename_all = "kebab-case")]
pub enum Precision {
    /// Möller–Trumbore: fewer operations, may miss or double-hit along shared edges.
    Fast,
    /// Woop, Benthin & Wald 2013: no ray slips through a shared edge.
    #[default]
    Watertight,
}

impl Precision {
    /// The contract's name.
    pub fn name(self) -> &'static str {
        crate::names::Spelled::name(self)
    }
}

crate::spelled!(Precision, [Precision::Fast, Precision::Watertight]);

/// Build quality of the BVH accelerators (Embree: LOW, MEDIUM, HIGH).
#[derive(
    Clone, Copy, Debug, PartialEq, Eq, Hash, Default, serde::Serialize, serde::Deserialize,
)]
#[serde(rename_all = "kebab-case")]
pub enum BuildQuality {
    /// Quickest build.
    Fast,
    /// Binned SAH.
    #[default]
    Sah,
    /// Spatial splits.
    Sbvh,
}

impl BuildQuality {
    /// The contract's name.
    pub fn name(self) -> &'static str {
        crate::names::Spelled::name(self)
    }
}

crate::spelled!(
    BuildQuality,
    [BuildQuality::Fast, BuildQuality::Sah, BuildQuality::Sbvh]
);

/// How to build an accelerator.
#[derive(Clone, Copy, Debug, PartialEq, Default)]
pub struct BuildOptions {
    /// Build quality (BVH accelerators and Embree).
    pub quality: BuildQuality,
    /// Ray/triangle test.
    pub precision: Precision,
    /// Threads the accelerator may use; 0 means all cores. Cores that use rayon take the
    /// pool they are called in; Embree needs the number when its device is made.
    pub threads: usize,
    /// Settings of the two DACRT cores. Explicit rather than read from the environment
    /// at build time, so that everything that changes a structure's answers or speed is in
    /// the options (and in the service cache's key).
    pub dacrt: dacrt::DacrtTuning,
}

/// Errors of building an accelerator.
#[derive(Debug, thiserror::Error)]
pub enum AccelError {
    /// The accelerator is not compiled into this binary.
    #[error("accelerator '{0}' is not available in this build (rebuild with --features {0})")]
    Unavailable(&'static str),
    /// The accelerator's library failed.
    #[error("{accel}: {message}")]
    Backend {
        /// Which accelerator.
        accel: &'static str,
        /// What went wrong.
        message: String,
    },
    /// [`Intersector::refit`] refused the new positions; the accelerator is unchanged and
    /// the caller should build a new one over them.
    #[error("{accel}: refit refused: {reason}")]
    Refit {
        /// Which accelerator.
        accel: &'static str,
        /// Why: a different triangle count (expected, got), a triangle that changed
        /// between degenerate and not (its id), or no refit at all in this accelerator.
        reason: bvh::RefitError,
    },
}

impl AccelError {
    /// The refusal of `accel` for `reason`.
    pub fn refit(accel: &'static str, reason: bvh::RefitError) -> AccelError {
        AccelError::Refit { accel, reason }
    }
}

/// A built accelerator: answers batches of rays.
pub trait Intersector: Send + Sync {
    /// The contract's name of this accelerator.
    fn name(&self) -> &'static str;

    /// Traces `rays` and writes one hit per ray, in order, into `hits`
    /// (`hits.len() == rays.len()`). Rays must be valid (see [`Ray::check`]); empty
    /// intervals miss.
    ///
    /// With [`Query::Any`] the record describes whichever hit was found first.
    fn trace(&self, rays: &[Ray], query: Query, hits: &mut [Hit]);

    /// Writes 1 for each ray that hits anything in its interval, else 0: the `any` query
    /// when nobody asked for hit fields (HIT1's `occluded` format), so cores that can stop
    /// without computing t, id or barycentrics (Embree's `rtcOccluded1`) do so.
    fn occluded(&self, rays: &[Ray], out: &mut [u8]) {
        let mut hits = vec![Hit::MISS; rays.len()];
        self.trace(rays, Query::Any, &mut hits);
        for (o, h) in out.iter_mut().zip(&hits) {
            *o = u8::from(h.is_hit());
        }
    }

    /// Bytes this accelerator holds beyond the scene's positions.
    fn bytes(&self) -> usize;

    /// [`AccelKind::large_batches`] of this core's kind, for callers that hold the core
    /// itself (the renderer).
    fn large_batches(&self) -> bool {
        AccelKind::parse(self.name()).is_some_and(AccelKind::large_batches)
    }

    /// Takes new world positions for the same triangles (same count, same ids): a TRI1
    /// geometry update, or the next time of an animation. It exists because a frame of
    /// moving geometry should cost a refit (one pass over the triangles and the nodes),
    /// not a build.
    ///
    /// After `Ok`, every query answers for the new positions exactly as a fresh build
    /// over them would answer (for the BVH cores: bit-identical hits, since the leaves
    /// run the same test on the same data). The structure's topology is kept, so its
    /// boxes loosen as triangles move away from where the build grouped them, and an SBVH
    /// loses its clipped leaf boxes (see the notes of `bvh::Mbvh::refit`): traversal gets
    /// slower, never wrong; rebuild when that matters.
    ///
    /// On `Err` ([`AccelError::Refit`]: another triangle count, a triangle that moved
    /// between degenerate and traceable, or an accelerator that cannot refit) nothing
    /// changed: the old positions still answer, and the caller builds a new accelerator.
    fn refit(&mut self, triangles: &[Triangle]) -> Result<(), AccelError> {
        let _ = triangles;
        Err(AccelError::refit(self.name(), bvh::RefitError::Unsupported))
    }

    /// A refitted copy: what [`Intersector::refit`] would make of this structure, as a new
    /// accelerator, leaving this one untouched. A structure shared by concurrent traces
    /// (the service's cache) cannot be refitted in place while old-version traces run on
    /// it; a copy of the nodes costs one memcpy, far less than a build. `Err` as `refit`,
    /// for cores whose precompute is itself the build (DACRT, `brute`) or that cannot copy.
    fn refit_copy(&self, triangles: &[Triangle]) -> Result<Box<dyn Intersector>, AccelError> {
        let _ = triangles;
        Err(AccelError::refit(self.name(), bvh::RefitError::Unsupported))
    }

    /// About how much slower this structure traces than it did when it was built, after
    /// the refits since (its surface-area cost now over its cost as built): a refit over
    /// positions that moved triangles far from where the build grouped them can slow a
    /// trace a hundredfold. 1 for structures that are never refitted.
    fn refit_slowdown(&self) -> f64 {
        1.0
    }

    /// Traversal steps and triangle tests per `closest` ray over `rays` (Áfra 2013,
    /// Table 4), for cores whose traversal counts them; run on the calling thread, untimed,
    /// so that `rayd bench` can print them beside the rates. `None` for the others.
    fn count_steps(&self, rays: &[Ray]) -> Option<serde_json::Value> {
        let _ = rays;
        None
    }

    /// Structure statistics (node counts, SIMD utilisation, bytes per triangle…) for
    /// `rayd info --accel` and `rayd bench`; `None` for cores without a structure.
    fn stats(&self) -> Option<serde_json::Value> {
        None
    }
}

/// Builds the accelerator `kind` over `triangles` (`auto` must be resolved first).
pub fn build(
    kind: AccelKind,
    triangles: &[Triangle],
    options: &BuildOptions,
) -> Result<Box<dyn Intersector>, AccelError> {
    match kind {
        AccelKind::Brute => Ok(Box::new(brute::Brute::new(triangles, options.precision))),
        AccelKind::Auto | AccelKind::Mbvh8 => {
            Ok(Box::new(mbvh::Mbvh8Core::build(triangles, options)))
        }
        AccelKind::Mbvh4 => Ok(Box::new(mbvh::Mbvh4Core::build(triangles, options))),
        AccelKind::Bvh2 => Ok(Box::new(packet::Bvh2Packet::build(triangles, options))),
        AccelKind::Dacrt => Ok(Box::new(dacrt::Dacrt::with_options(
            "dacrt",
            triangles,
            options.precision,
            options.dacrt.afra,
        ))),
        AccelKind::DacrtSampled => Ok(Box::new(dacrt::Dacrt::with_options(
            "dacrt-sampled",
            triangles,
            options.precision,
            options.dacrt.nabata,
        ))),
        #[cfg(feature = "embree")]
        AccelKind::Embree => Ok(Box::new(embree::Embree::new(triangles, options)?)),
        #[cfg(not(feature = "embree"))]
        AccelKind::Embree => Err(AccelError::Unavailable("embree")),
    }
}
