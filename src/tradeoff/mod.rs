//! `rayd tradeoff`: what each bit of accuracy costs. One scene is rendered by the `path`
//! integrator over a ladder of settings (samples per pixel, bounces, precision, build
//! quality, accelerator, DACRT's thresholds), each rung timed and compared with a reference
//! of many samples and bounces, and the rungs that nothing beats in both time and error
//! (the Pareto front) are marked.
//!
//! Every rung is a whole render job of [`crate::jobs`], run on a fresh [`Engine`] so that
//! it pays its own structure build as a first request would, and so that a rung's DACRT
//! settings are its engine's (the cache keys them, as everything that changes an answer
//! must be). A rung's time is what its frame costs: preparation (build or precompute),
//! trace and shade, without parsing the file or encoding the image. Images come back as
//! EXR, whose FLOAT channels hold the renderer's radiance bit for bit.
//!
//! Why a reference with another seed: each pixel's sample `s` owns a random stream seeded
//! from the seed and `s` (`proto/rendering.md`, "Determinism"), so a reference with the
//! rungs' seed would repeat their first samples and make every rung look better than it is.

pub mod measure;
pub mod report;

use std::sync::Arc;

use crate::accel::dacrt::DacrtTuning;
use crate::accel::{AccelKind, BuildQuality, Precision};
use crate::jobs::render::FrameInput;
use crate::jobs::{Engine, EngineOptions, FrameTimes, JobError, Limits, RenderRequest};
use crate::render::image::ImageFormat;
use crate::render::{AovSet, Integrator};
pub use measure::Errors;

/// Errors of a trade-off run.
#[derive(Debug, thiserror::Error)]
pub enum TradeoffError {
    /// A render failed.
    #[error(transparent)]
    Job(#[from] JobError),
    /// A rung's engine could not start its thread pool.
    #[error("cannot start the thread pool: {0}")]
    Pool(#[from] rayon::ThreadPoolBuildError),
    /// A render's EXR could not be read back (a bug of the encoder or the reader).
    #[error("reading back the EXR of {what}: {source}")]
    Exr {
        /// Which render.
        what: String,
        /// Why.
        source: exr::error::Error,
    },
    /// The settings cannot make a ladder.
    #[error("{0}")]
    Invalid(String),
    /// The plot could not be drawn or encoded.
    #[error("plot: {0}")]
    Plot(String),
}

/// Which setting a rung varies.
#[derive(
    Clone, Copy, Debug, PartialEq, Eq, Hash, PartialOrd, Ord, serde::Serialize, serde::Deserialize,
)]
#[serde(rename_all = "kebab-case")]
pub enum Axis {
    /// The base settings themselves; every other rung changes one thing from them.
    Base,
    /// Samples per pixel.
    Spp,
    /// Path bounces.
    Bounces,
    /// Russian roulette from the first, second or third scattering on.
    Roulette,
    /// Ray/triangle test: fast or watertight.
    Precision,
    /// BVH build quality.
    Build,
    /// The accelerator.
    Accel,
    /// DACRT's leaf and split thresholds, and when DACRT-sampled starts sampling.
    Dacrt,
}

impl Axis {
    /// Every axis a user may ask for, in ladder order: all but the base itself.
    pub fn walkable() -> &'static [Axis] {
        &<Axis as crate::names::Spelled>::ALL[1..]
    }
}

crate::spelled!(
    Axis,
    [
        Axis::Base,
        Axis::Spp,
        Axis::Bounces,
        Axis::Roulette,
        Axis::Precision,
        Axis::Build,
        Axis::Accel,
        Axis::Dacrt,
    ]
);

/// What to measure.
#[derive(Clone, Debug)]
pub struct Setup {
    /// The base render: size, camera, sky, seed, and the settings every rung but one keeps
    /// (its integrator is always `path`; format and AOVs are ignored).
    pub base: RenderRequest,
    /// DACRT settings of the base (the rungs of [`Axis::Dacrt`] change one from these).
    pub tuning: DacrtTuning,
    /// Threads of every render; 0: all cores.
    pub threads: usize,
    /// Animation time of the frame (`None`: the static pose).
    pub time: Option<f64>,
    /// Samples per pixel of the reference.
    pub reference_spp: u32,
    /// Bounces of the reference: at least the ladder's most, so that cutting paths short
    /// shows as error.
    pub reference_bounces: u32,
    /// Seed of the reference; must differ from the base's.
    pub reference_seed: u64,
    /// The rungs of [`Axis::Spp`].
    pub spp: Vec<u32>,
    /// The rungs of [`Axis::Bounces`].
    pub bounces: Vec<u32>,
    /// The rungs of [`Axis::Accel`].
    pub accels: Vec<AccelKind>,
    /// Which axes to walk (the base is always measured).
    pub axes: Vec<Axis>,
}

impl Setup {
    /// The defaults of `rayd tradeoff` around `base`.
    pub fn new(base: RenderRequest) -> Setup {
        Setup {
            base: RenderRequest {
                integrator: Integrator::Path,
                ..base
            },
            tuning: DacrtTuning::default(),
            threads: 0,
            time: None,
            reference_spp: 1024,
            reference_bounces: 8,
            reference_seed: base.seed.wrapping_add(0x9e37_79b9_7f4a_7c15),
            spp: vec![1, 2, 4, 8, 16, 32, 64],
            bounces: vec![0, 1, 2, 3, 4, 6, 8],
            // Every named core but the brute-force reference.
            accels: AccelKind::ALL
                .into_iter()
                .filter(|k| !matches!(k, AccelKind::Auto | AccelKind::Brute))
                .collect(),
            axes: Axis::walkable().to_vec(),
        }
    }
}

/// One render of the ladder: a setting changed from the base.
#[derive(Clone, Debug, PartialEq)]
pub struct Rung {
    /// What it varies.
    pub axis: Axis,
    /// The change, as `name=value` (`base` for the base).
    pub setting: String,
    /// The render.
    pub request: RenderRequest,
    /// Its DACRT settings.
    pub tuning: DacrtTuning,
}

/// The ladder of `setup`: the base first, then each asked-for axis's changes from it (a
/// value equal to the base's is not repeated), and notes on what was left out and why.
pub fn ladder(setup: &Setup) -> (Vec<Rung>, Vec<String>) {
    let base = RenderRequest {
        integrator: Integrator::Path,
        format: ImageFormat::Exr,
        aovs: AovSet::default(),
        ..setup.base.clone()
    };
    let mut rungs = vec![Rung {
        axis: Axis::Base,
        setting: "base".into(),
        request: base.clone(),
        tuning: setup.tuning,
    }];
    let mut notes = Vec::new();
    let mut push = |axis: Axis, setting: String, request: RenderRequest, tuning: DacrtTuning| {
        let rung = Rung {
            axis,
            setting,
            request,
            tuning,
        };
        if !rungs
            .iter()
            .any(|r| r.request == rung.request && r.tuning == rung.tuning)
        {
            rungs.push(rung);
        }
    };
    for &axis in &setup.axes {
        let with = |f: &dyn Fn(&mut RenderRequest)| {
            let mut r = base.clone();
            f(&mut r);
            r
        };
        match axis {
            Axis::Base => {}
            Axis::Spp => {
                for &spp in &setup.spp {
                    push(
                        axis,
                        format!("spp={spp}"),
                        with(&|r| r.spp = spp),
                        setup.tuning,
                    );
                }
            }
            Axis::Bounces => {
                for &b in &setup.bounces {
                    push(
                        axis,
                        format!("bounces={b}"),
                        with(&|r| r.bounces = b),
                        setup.tuning,
                    );
                }
            }
            Axis::Roulette => {
                // Roulette from each scattering the base's paths reach (at most the third):
                // earlier starts cut more paths short, saving time for noise.
                let last = base.bounces.min(3);
                if base.roulette.is_some() || last == 0 {
                    notes.push(format!(
                        "roulette: no rungs (the base has {} and {} bounces)",
                        if base.roulette.is_some() {
                            "roulette on"
                        } else {
                            "roulette off"
                        },
                        base.bounces
                    ));
                }
                if base.roulette.is_none() {
                    for k in 1..=last {
                        push(
                            axis,
                            format!("roulette={k}"),
                            with(&|r| r.roulette = Some(k)),
                            setup.tuning,
                        );
                    }
                }
            }
            Axis::Precision => {
                for p in [Precision::Fast, Precision::Watertight] {
                    push(
                        axis,
                        format!("precision={p}"),
                        with(&|r| r.precision = p),
                        setup.tuning,
                    );
                }
            }
            Axis::Build => {
                // Build quality only means something to the BVH cores.
                let accel = match base.accel {
                    AccelKind::Dacrt | AccelKind::DacrtSampled | AccelKind::Brute => {
                        AccelKind::Mbvh8
                    }
                    a => a,
                };
                for q in [BuildQuality::Fast, BuildQuality::Sah, BuildQuality::Sbvh] {
                    push(
                        axis,
                        format!("build={q}"),
                        with(&|r| {
                            r.build = q;
                            r.accel = accel;
                        }),
                        setup.tuning,
                    );
                }
            }
            Axis::Accel => {
                for &a in &setup.accels {
                    if !a.available() {
                        notes.push(format!("accel={a}: not in this build of rayd"));
                        continue;
                    }
                    push(
                        axis,
                        format!("accel={a}"),
                        with(&|r| r.accel = a),
                        setup.tuning,
                    );
                }
            }
            Axis::Dacrt => {
                for (setting, accel, tuning) in dacrt_rungs(setup.tuning) {
                    push(axis, setting, with(&|r| r.accel = accel), tuning);
                }
            }
        }
    }
    (rungs, notes)
}

/// DACRT's thresholds, one changed at a time around `t`: the leaf sizes and the SAH ratio
/// of `dacrt` (Áfra 2012), and the node size where `dacrt-sampled` starts sampling (Nabata
/// et al. 2013: 1000; ours 3000).
fn dacrt_rungs(t: DacrtTuning) -> Vec<(String, AccelKind, DacrtTuning)> {
    let mut out = Vec::new();
    let a = t.afra;
    for leaf_rays in [a.leaf_rays / 2, a.leaf_rays * 2, a.leaf_rays * 4] {
        let mut u = t;
        u.afra.leaf_rays = leaf_rays.max(1);
        out.push((format!("leaf_rays={leaf_rays}"), AccelKind::Dacrt, u));
    }
    for leaf_tris in [a.leaf_tris / 2, a.leaf_tris * 2] {
        let mut u = t;
        u.afra.leaf_tris = leaf_tris.max(2);
        out.push((format!("leaf_tris={leaf_tris}"), AccelKind::Dacrt, u));
    }
    for sah_ratio in [a.sah_ratio / 2.0, a.sah_ratio * 2.0] {
        let mut u = t;
        u.afra.sah_ratio = sah_ratio;
        out.push((format!("sah_ratio={sah_ratio}"), AccelKind::Dacrt, u));
    }
    let m = t.nabata.sampling.min_rays;
    for min_rays in [m / 3, m * 3] {
        let mut u = t;
        u.nabata.sampling.min_rays = min_rays;
        out.push((
            format!("sample_min_rays={min_rays}"),
            AccelKind::DacrtSampled,
            u,
        ));
    }
    out
}

/// One measured rung.
#[derive(Clone, Debug, PartialEq, serde::Serialize)]
pub struct Row {
    /// What it varies.
    pub axis: Axis,
    /// The change from the base.
    pub setting: String,
    /// Samples per pixel.
    pub spp: u32,
    /// Bounces.
    pub bounces: u32,
    /// The accelerator that ran.
    pub accel: &'static str,
    /// Build quality asked for.
    pub build: BuildQuality,
    /// Ray/triangle test.
    pub precision: Precision,
    /// What the frame cost: `prepare + trace + shade`.
    pub seconds: f64,
    /// Build or precompute.
    pub prepare_seconds: f64,
    /// Inside the intersector.
    pub trace_seconds: f64,
    /// Ray generation, shading and wave bookkeeping.
    pub shade_seconds: f64,
    /// Rays traced.
    pub rays: u64,
    /// Error against the reference.
    #[serde(flatten)]
    pub errors: Errors,
    /// On the Pareto front of (seconds, RMSE).
    pub pareto: bool,
}

/// The reference render.
#[derive(Clone, Debug, PartialEq, serde::Serialize)]
pub struct Reference {
    /// Samples per pixel.
    pub spp: u32,
    /// Bounces.
    pub bounces: u32,
    /// Seed.
    pub seed: u64,
    /// What its frame cost.
    pub seconds: f64,
    /// Mean radiance over pixels and channels.
    pub mean: f64,
}

/// A whole run.
#[derive(Clone, Debug, PartialEq, serde::Serialize)]
pub struct Report {
    /// The scene, as the caller named it.
    pub scene: String,
    /// Image width.
    pub width: u32,
    /// Image height.
    pub height: u32,
    /// Threads of every render.
    pub threads: usize,
    /// The reference.
    pub reference: Reference,
    /// The rungs, in ladder order.
    pub rows: Vec<Row>,
    /// What was left out, and why.
    pub notes: Vec<String>,
}

/// One render's result.
#[derive(Clone, Debug, PartialEq)]
pub struct Rendered {
    /// Linear radiance, row-major from the top.
    pub pixels: Vec<[f32; 3]>,
    /// Where the frame's time went.
    pub times: FrameTimes,
    /// Threads of the engine's pool.
    pub threads: usize,
}

/// Renders `request` of `frame` on a fresh engine with `tuning`, as one render job.
pub fn render_radiance(
    frame: &FrameInput,
    request: &RenderRequest,
    tuning: DacrtTuning,
    threads: usize,
    time: Option<f64>,
) -> Result<Rendered, TradeoffError> {
    let engine = Engine::new(EngineOptions {
        threads,
        tuning,
        limits: Limits {
            max_rays: usize::MAX,
            ..Limits::default()
        },
        ..EngineOptions::default()
    })?;
    let request = RenderRequest {
        format: ImageFormat::Exr,
        aovs: AovSet::default(),
        ..request.clone()
    };
    let copy = || FrameInput {
        geometry: frame.geometry.clone(),
        cameras: Arc::clone(&frame.cameras),
        surfaces: frame.surfaces.clone(),
    };
    let mut bytes = None;
    let report = engine.render(
        &request,
        &[time],
        &|_, _| Ok(copy()),
        &engine.detached(),
        &mut |_, b| {
            bytes = Some(b);
            Ok(())
        },
    )?;
    let what = || {
        format!(
            "spp={} bounces={} accel={}",
            request.spp, request.bounces, request.accel
        )
    };
    let bytes = bytes.ok_or_else(|| TradeoffError::Invalid(format!("{}: no image", what())))?;
    let pixels = read_exr_rgb(&bytes).map_err(|source| TradeoffError::Exr {
        what: what(),
        source,
    })?;
    let times = report.frames.into_iter().next().ok_or_else(|| {
        TradeoffError::Invalid(format!("{}: the render reported no frame", what()))
    })?;
    Ok(Rendered {
        pixels,
        times,
        threads: engine.threads(),
    })
}

/// The R, G, B channels of an EXR, row-major from the top.
fn read_exr_rgb(bytes: &[u8]) -> Result<Vec<[f32; 3]>, exr::error::Error> {
    use exr::prelude::*;
    let image = read()
        .no_deep_data()
        .largest_resolution_level()
        .rgba_channels(
            |size, _| {
                (
                    size.width(),
                    vec![[0.0f32; 3]; size.width() * size.height()],
                )
            },
            |(w, px): &mut (usize, Vec<[f32; 3]>), pos, (r, g, b, _a): (f32, f32, f32, f32)| {
                px[pos.y() * *w + pos.x()] = [r, g, b];
            },
        )
        .first_valid_layer()
        .all_attributes()
        .from_buffered(std::io::Cursor::new(bytes))?;
    Ok(image.layer_data.channel_data.pixels.1)
}

/// Runs the ladder of `setup` on `frame` (the scene at `setup.time`, with surfaces),
/// calling `on_row` after each rung (for progress), and marks the Pareto front.
pub fn run(
    scene: &str,
    frame: &FrameInput,
    setup: &Setup,
    on_row: &mut dyn FnMut(usize, usize, &Row),
) -> Result<Report, TradeoffError> {
    if setup.reference_seed == setup.base.seed {
        return Err(TradeoffError::Invalid(
            "the reference's seed must differ from the rungs' (it would repeat their samples)"
                .into(),
        ));
    }
    if frame.surfaces.is_none() {
        return Err(TradeoffError::Invalid(
            "the frame has no surfaces: `path` needs the scene's materials".into(),
        ));
    }
    let (rungs, notes) = ladder(setup);
    let most_bounces = rungs.iter().map(|r| r.request.bounces).max().unwrap_or(0);
    if setup.reference_bounces < most_bounces {
        return Err(TradeoffError::Invalid(format!(
            "the reference's {} bounces are fewer than a rung's {most_bounces}",
            setup.reference_bounces
        )));
    }
    let reference_request = RenderRequest {
        integrator: Integrator::Path,
        spp: setup.reference_spp,
        bounces: setup.reference_bounces,
        seed: setup.reference_seed,
        ..setup.base.clone()
    };
    let reference = render_radiance(
        frame,
        &reference_request,
        setup.tuning,
        setup.threads,
        setup.time,
    )?;
    let (threads, ref_times, reference) = (reference.threads, reference.times, reference.pixels);
    let mean = reference
        .iter()
        .flat_map(|p| p.iter().map(|&x| x as f64))
        .sum::<f64>()
        / (3 * reference.len()).max(1) as f64;
    let mut rows = Vec::with_capacity(rungs.len());
    for (k, rung) in rungs.iter().enumerate() {
        let Rendered {
            pixels, times: t, ..
        } = render_radiance(frame, &rung.request, rung.tuning, setup.threads, setup.time)?;
        let errors = measure::errors(&pixels, &reference).ok_or_else(|| {
            TradeoffError::Invalid(format!("{}: image size differs", rung.setting))
        })?;
        let row = Row {
            axis: rung.axis,
            setting: rung.setting.clone(),
            spp: rung.request.spp,
            bounces: rung.request.bounces,
            accel: t.accel,
            build: rung.request.build,
            precision: rung.request.precision,
            seconds: t.prepare_seconds + t.trace_seconds + t.shade_seconds,
            prepare_seconds: t.prepare_seconds,
            trace_seconds: t.trace_seconds,
            shade_seconds: t.shade_seconds,
            rays: t.rays,
            errors,
            pareto: false,
        };
        on_row(k, rungs.len(), &row);
        rows.push(row);
    }
    let points: Vec<(f64, f64)> = rows.iter().map(|r| (r.seconds, r.errors.rmse)).collect();
    for (row, on) in rows.iter_mut().zip(measure::pareto(&points)) {
        row.pareto = on;
    }
    Ok(Report {
        scene: scene.to_string(),
        width: setup.base.width,
        height: setup.base.height,
        threads,
        reference: Reference {
            spp: setup.reference_spp,
            bounces: setup.reference_bounces,
            seed: setup.reference_seed,
            seconds: ref_times.prepare_seconds + ref_times.trace_seconds + ref_times.shade_seconds,
            mean,
        },
        rows,
        notes,
    })
}
