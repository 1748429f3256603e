//! `rayd bench --frames N`: geometry that changes every frame.
//!
//! Each frame gets new positions for the same triangles (an animation at the frame's time,
//! or a procedural twist of a static scene), and every strategy pays what a real frame
//! costs: its per-frame preparation (`build_seconds`: a BVH rebuild, a refit of the
//! first frame's BVH, or DACRT's precompute) plus tracing the frame's rays. The same rays
//! are traced by every strategy in the same run, for several rays-per-frame counts, so
//! the table shows where a structure's build stops paying for itself (Áfra 2012's
//! argument for DACRT) and how a refitted tree's tracing decays as the geometry moves
//! away from the pose it was built for (Áfra 2013's refit question).
//!
//! The room of the interior view is set around the box of all frames, so every frame's
//! rays still hit. Bounce rays are made once, on the first frame, and traced against every
//! frame (they stay incoherent rays inside the room; only their origins no longer lie
//! exactly on the moved surfaces).

use std::path::{Path, PathBuf};
use std::time::Instant;

use serde::Serialize;

use super::raysets::{make_sets, occlusion_hits, SetKind};
use super::view::View;
use super::{compare, median, pool, trace_set, BenchError, CameraChoice, ViewKind};
use crate::accel::auto::{self, Geometry, Job};
use crate::accel::{self, AccelKind, BuildOptions, BuildQuality, Intersector, Precision};
use crate::formats::{load_scene, LoadOptions};
use crate::geometry::{Aabb, Hit, Triangle};
use crate::scene::Scene;

/// How the geometry moves from frame to frame.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Motion {
    /// The scene's animations, sampled evenly over the longest one; a twist for scenes
    /// without animations.
    Auto,
    /// The scene's own animations (skins, morph weights, node transforms).
    Animation,
    /// A twist about the vertical axis through the scene's centre, growing linearly from
    /// nothing on the first frame to a quarter turn (top against bottom) on the last: a
    /// deformation that stretches and turns triangles, the hard case for a refit.
    Twist,
}

impl Motion {
    /// The command line's name.
    pub fn name(self) -> &'static str {
        match self {
            Motion::Auto => "auto",
            Motion::Animation => "animation",
            Motion::Twist => "twist",
        }
    }

    /// Parses the command line's name.
    pub fn parse(s: &str) -> Option<Motion> {
        [Motion::Auto, Motion::Animation, Motion::Twist]
            .into_iter()
            .find(|m| m.name() == s)
    }
}

/// What to measure.
#[derive(Clone, Debug)]
pub struct DynamicConfig {
    /// Scene files.
    pub scenes: Vec<PathBuf>,
    /// Accelerators; the BVH ones and Embree are measured rebuilding every frame and
    /// refitting the first frame's structure.
    pub accels: Vec<AccelKind>,
    /// Ray sets traced each frame.
    pub sets: Vec<SetKind>,
    /// Rays per frame (each made as a square image of about that many pixels).
    pub rays_per_frame: Vec<usize>,
    /// Frames.
    pub frames: usize,
    /// How the geometry moves.
    pub motion: Motion,
    /// Thread counts (0 = all cores).
    pub threads: Vec<usize>,
    /// Camera.
    pub camera: CameraChoice,
    /// Build quality of the BVH accelerators and Embree.
    pub build: BuildQuality,
    /// Ray/triangle test.
    pub precision: Precision,
    /// Seed of the ray sets.
    pub seed: u64,
}

/// One strategy × thread count × rays per frame × set, over all frames.
#[derive(Clone, Debug, Serialize)]
pub struct FrameSeries {
    /// Accelerator name.
    pub accel: String,
    /// `rebuild` (every frame), `refit` (the first frame's structure) or `update` (DACRT's
    /// precompute).
    pub mode: String,
    /// Threads used.
    pub threads: usize,
    /// Ray set.
    pub set: String,
    /// Rays per frame.
    pub rays: usize,
    /// Per frame: preparation seconds (for `refit`, frame 0 is the initial build).
    pub update_seconds: Vec<f64>,
    /// Per frame: trace seconds.
    pub trace_seconds: Vec<f64>,
    /// Median over the frames (from frame 1 for `refit`) of preparation seconds.
    pub median_update_seconds: f64,
    /// Median trace seconds, same frames.
    pub median_trace_seconds: f64,
    /// Median of update + trace, same frames: the cost of one frame.
    pub median_frame_seconds: f64,
    /// Fraction of rays, over all frames, whose answer matches the first strategy's.
    pub agreement: f64,
}

/// The results of one scene.
#[derive(Clone, Debug, Serialize)]
pub struct DynamicScene {
    /// Scene file.
    pub scene: String,
    /// Scene triangles (without the room's 12).
    pub triangles: usize,
    /// The motion used, in words.
    pub motion: String,
    /// Frames.
    pub frames: usize,
    /// Every series.
    pub series: Vec<FrameSeries>,
    /// `auto`'s pick for every measured situation, against the fastest measured one.
    pub auto: Vec<AutoPick>,
    /// The situations where `auto` picks a strategy that was not measured (`brute` is
    /// measured only when named), which [`DynamicScene::auto`] therefore cannot score.
    pub auto_unmeasured: Vec<String>,
}

/// What `auto` would have run in one measured situation, and what that cost.
#[derive(Clone, Debug, Serialize)]
pub struct AutoPick {
    /// Ray set.
    pub set: String,
    /// Threads.
    pub threads: usize,
    /// Rays per frame.
    pub rays: usize,
    /// `new` (every frame builds from nothing) or `refittable` (the last frame's structure
    /// may be refitted).
    pub geometry: String,
    /// `auto`'s choice, as `accel mode`.
    pub picked: String,
    /// The fastest measured candidate.
    pub fastest: String,
    /// Median frame seconds of the pick.
    pub picked_seconds: f64,
    /// Median frame seconds of the fastest.
    pub fastest_seconds: f64,
}

/// `auto`'s candidates in a situation: our cores' strategies that apply (Embree is a peer,
/// never picked), as (accel, mode) of the measured series.
fn candidates(refittable: bool) -> &'static [(&'static str, &'static str)] {
    if refittable {
        &[
            ("mbvh8", "refit"),
            ("dacrt", "update"),
            ("dacrt-sampled", "update"),
            ("brute", "update"),
        ]
    } else {
        &[
            ("mbvh8", "rebuild"),
            ("dacrt", "update"),
            ("dacrt-sampled", "update"),
            ("brute", "update"),
        ]
    }
}

/// Scores `auto` on every (set, threads, rays, geometry) of `series` where its pick and at
/// least one other candidate were measured; the situations whose pick was not measured are
/// listed apart, never dropped silently.
fn score_auto(
    series: &[FrameSeries],
    triangles: usize,
    quality: BuildQuality,
) -> (Vec<AutoPick>, Vec<String>) {
    let mut out = Vec::new();
    let mut unmeasured = Vec::new();
    let mut cells: Vec<(String, usize, usize)> = Vec::new();
    for f in series {
        let c = (f.set.clone(), f.threads, f.rays);
        if !cells.contains(&c) {
            cells.push(c);
        }
    }
    for (set, threads, rays) in cells {
        for refittable in [false, true] {
            let measured: Vec<&FrameSeries> = candidates(refittable)
                .iter()
                .filter_map(|&(a, m)| {
                    series.iter().find(|f| {
                        f.accel == a
                            && f.mode == m
                            && f.set == set
                            && f.threads == threads
                            && f.rays == rays
                    })
                })
                .collect();
            if measured.len() < 2 {
                continue;
            }
            let job = Job {
                rays,
                batches: 1,
                triangles: triangles + 12,
                threads,
                quality,
                geometry: if refittable {
                    Geometry::Refittable
                } else {
                    Geometry::New
                },
                // Each measured frame stands alone: "new" rebuilds every frame.
                frames: 1,
                arrival: 0.0,
                first_hit: false,
            };
            let pick = auto::choose(&job);
            let geometry = if refittable { "refittable" } else { "new" };
            let Some(p) = measured.iter().find(|f| f.accel == pick.name()) else {
                unmeasured.push(format!(
                    "{set}, {threads} thread(s), {rays} rays, {geometry}: auto picks {}, not measured",
                    pick.name()
                ));
                continue;
            };
            let best = measured
                .iter()
                .min_by(|a, b| a.median_frame_seconds.total_cmp(&b.median_frame_seconds))
                .expect("two or more");
            out.push(AutoPick {
                set: set.clone(),
                threads,
                rays,
                geometry: geometry.into(),
                picked: format!("{} {}", p.accel, p.mode),
                fastest: format!("{} {}", best.accel, best.mode),
                picked_seconds: p.median_frame_seconds,
                fastest_seconds: best.median_frame_seconds,
            });
        }
    }
    (out, unmeasured)
}

/// The whole run.
#[derive(Clone, Debug, Serialize)]
pub struct DynamicReport {
    /// Logical cores of the machine.
    pub cores: usize,
    /// SIMD backend.
    pub simd: String,
    /// Build quality.
    pub build: String,
    /// Precision.
    pub precision: String,
    /// Per scene.
    pub scenes: Vec<DynamicScene>,
}

/// Rotates `p` about the vertical axis through `c` by an angle growing with height.
fn twist(p: [f32; 3], c: [f32; 3], y0: f32, height: f32, turn: f64) -> [f32; 3] {
    let h = if height > 0.0 {
        ((p[1] - y0) / height) as f64
    } else {
        0.0
    };
    let a = turn * h;
    let (s, co) = a.sin_cos();
    let (x, z) = ((p[0] - c[0]) as f64, (p[2] - c[2]) as f64);
    [
        (c[0] as f64 + co * x - s * z) as f32,
        p[1],
        (c[2] as f64 + s * x + co * z) as f32,
    ]
}

/// The scene's triangles on every frame, and the motion in words.
fn frames_of(
    path: &Path,
    scene: &Scene,
    motion: Motion,
    frames: usize,
) -> Result<(Vec<Vec<Triangle>>, String), BenchError> {
    let duration = scene
        .animations
        .iter()
        .map(|a| a.duration)
        .fold(0.0f64, f64::max);
    let animated = duration > 0.0;
    let motion = match motion {
        Motion::Auto if animated => Motion::Animation,
        Motion::Auto => Motion::Twist,
        Motion::Animation if !animated => {
            return Err(BenchError::Config(format!(
                "{}: --motion animation needs a scene with animations",
                path.display()
            )))
        }
        m => m,
    };
    let n = frames.max(1);
    let step = |f: usize| f as f64 / (n.max(2) - 1) as f64;
    if motion == Motion::Animation {
        let mut out = Vec::with_capacity(n);
        for f in 0..n {
            let s = load_scene(
                path,
                &LoadOptions {
                    time: Some(duration * step(f)),
                },
            )?;
            if s.triangles.len() != scene.triangles.len() {
                return Err(BenchError::Config(format!(
                    "{}: the triangle count changes over the animation",
                    path.display()
                )));
            }
            out.push(s.triangles);
        }
        return Ok((out, format!("animation, {n} frames over {duration:.3} s")));
    }
    let b = scene.bounds().ok_or_else(|| {
        BenchError::Config(format!(
            "{}: the scene has no triangles to benchmark",
            path.display()
        ))
    })?;
    let c = b.center();
    let height = b.max[1] - b.min[1];
    let out = (0..n)
        .map(|f| {
            let turn = std::f64::consts::FRAC_PI_2 * step(f);
            scene
                .triangles
                .iter()
                .map(|t| Triangle {
                    v: t.v.map(|p| twist(p, c, b.min[1], height, turn)),
                })
                .collect()
        })
        .collect();
    Ok((out, format!("twist, {n} frames from 0 to 90 degrees")))
}

/// The box of every frame's triangles.
fn bounds_of(frames: &[Vec<Triangle>]) -> Aabb {
    let mut b = Aabb::EMPTY;
    for t in frames.iter().flatten() {
        b.union(&t.bounds());
    }
    b
}

/// How one strategy prepares a frame.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Mode {
    Rebuild,
    Refit,
    Update,
}

impl Mode {
    fn name(self) -> &'static str {
        match self {
            Mode::Rebuild => "rebuild",
            Mode::Refit => "refit",
            Mode::Update => "update",
        }
    }
}

/// The strategies measured for `kinds`, in order, each once. `auto` stands for the
/// strategies it chooses among on moving geometry (`mbvh8` rebuilt and refitted, `dacrt`
/// and `dacrt-sampled`; `brute` only when named, as it would take hours on a large
/// scene), so that its pick is measured and scored against them (`bench --frames N` with
/// the default `--accel auto` measured nothing).
fn strategies(kinds: &[AccelKind]) -> Vec<(AccelKind, Mode)> {
    let mut out = Vec::new();
    let mut add = |s: (AccelKind, Mode)| {
        if !out.contains(&s) {
            out.push(s);
        }
    };
    for &k in kinds {
        match k {
            AccelKind::Dacrt | AccelKind::DacrtSampled | AccelKind::Brute => add((k, Mode::Update)),
            AccelKind::Auto => {
                add((AccelKind::Mbvh8, Mode::Rebuild));
                add((AccelKind::Mbvh8, Mode::Refit));
                add((AccelKind::Dacrt, Mode::Update));
                add((AccelKind::DacrtSampled, Mode::Update));
            }
            _ => {
                add((k, Mode::Rebuild));
                add((k, Mode::Refit));
            }
        }
    }
    out
}

/// Runs the dynamic benchmark; progress goes to stderr.
pub fn run(config: &DynamicConfig) -> Result<DynamicReport, BenchError> {
    if config.scenes.is_empty() {
        return Err(BenchError::Config("no scene given".into()));
    }
    if config.frames < 2 {
        return Err(BenchError::Config("--frames must be at least 2".into()));
    }
    if config.rays_per_frame.is_empty() || config.rays_per_frame.contains(&0) {
        return Err(BenchError::Config(
            "--rays-per-frame needs counts of at least 1".into(),
        ));
    }
    // Bounded as a render's frames and a trace's batch are.
    let limits = crate::jobs::Limits::default();
    if config.frames > limits.max_frames {
        return Err(BenchError::Config(format!(
            "--frames {} is over the limit of {}",
            config.frames, limits.max_frames
        )));
    }
    if let Some(&n) = config.rays_per_frame.iter().find(|&&n| n > limits.max_rays) {
        return Err(BenchError::Config(format!(
            "--rays-per-frame {n} is over the limit of {} rays a batch",
            limits.max_rays
        )));
    }
    for &k in &config.accels {
        if !k.available() {
            return Err(crate::accel::AccelError::Unavailable(k.name()).into());
        }
    }
    let all = pool(0)?;
    let mut report = DynamicReport {
        cores: std::thread::available_parallelism().map_or(1, |n| n.get()),
        simd: crate::simd::selected().name().into(),
        build: config.build.name().into(),
        precision: config.precision.name().into(),
        scenes: Vec::new(),
    };
    for path in &config.scenes {
        let scene = load_scene(path, &LoadOptions { time: None })?;
        let (frames, motion) = frames_of(path, &scene, config.motion, config.frames)?;
        let bounds = bounds_of(&frames);
        if bounds.is_empty() {
            return Err(BenchError::Config(format!(
                "{}: the scene has no triangles to benchmark",
                path.display()
            )));
        }
        crate::note!(
            "bench: {} ({} triangles), {motion}",
            path.display(),
            scene.triangles.len()
        );
        let mut out = DynamicScene {
            scene: path.display().to_string(),
            triangles: scene.triangles.len(),
            motion,
            frames: frames.len(),
            series: Vec::new(),
            auto: Vec::new(),
            auto_unmeasured: Vec::new(),
        };
        // The first frame's pose, for the view (the room comes from all frames' bounds).
        let first = Scene {
            triangles: frames[0].clone(),
            ..scene
        };
        for &target in &config.rays_per_frame {
            let side = (target as f64).sqrt().round().max(1.0) as u32;
            let view = View::around(
                &first,
                bounds,
                ViewKind::Interior,
                &config.camera,
                side,
                side,
            )?;
            let room = view.triangles[first.triangles.len()..].to_vec();
            let with_room = |f: &[Triangle]| {
                let mut t = f.to_vec();
                t.extend_from_slice(&room);
                t
            };
            let options = BuildOptions {
                quality: BuildQuality::Sah,
                precision: config.precision,
                threads: all.current_num_threads(),
                dacrt: crate::accel::dacrt::DacrtTuning::from_env(),
            };
            let maker =
                all.install(|| accel::build(AccelKind::Mbvh8, &view.triangles, &options))?;
            let sets = all.install(|| make_sets(&view, maker.as_ref(), &config.sets, config.seed));
            drop(maker);
            let frame_tris: Vec<Vec<Triangle>> = frames.iter().map(|f| with_room(f)).collect();
            for &threads in &config.threads {
                let p = pool(threads)?;
                let threads = p.current_num_threads();
                let options = BuildOptions {
                    quality: config.build,
                    precision: config.precision,
                    threads,
                    dacrt: crate::accel::dacrt::DacrtTuning::from_env(),
                };
                // The first strategy's answers, per set and frame, for the agreement.
                let mut reference: Vec<Vec<Vec<Hit>>> = Vec::new();
                for (si, &(kind, mode)) in strategies(&config.accels).iter().enumerate() {
                    let mut update = Vec::with_capacity(frames.len());
                    let mut trace: Vec<Vec<f64>> = vec![Vec::new(); sets.len()];
                    let mut agree = vec![(0usize, 0usize); sets.len()];
                    let mut current: Option<Box<dyn Intersector>> = None;
                    let mut refused = None;
                    for (f, tris) in frame_tris.iter().enumerate() {
                        let ok = if let (Some(a), Mode::Refit) = (current.as_mut(), mode) {
                            let t0 = Instant::now();
                            let r = p.install(|| a.refit(tris));
                            update.push(t0.elapsed().as_secs_f64());
                            r
                        } else {
                            drop(current.take());
                            let t0 = Instant::now();
                            let a = p.install(|| accel::build(kind, tris, &options))?;
                            update.push(t0.elapsed().as_secs_f64());
                            current = Some(a);
                            Ok(())
                        };
                        if let Err(e) = ok {
                            refused = Some(e);
                            break;
                        }
                        let a = current.as_deref().expect("prepared above");
                        for (k, set) in sets.iter().enumerate() {
                            let mut hits = vec![Hit::MISS; set.rays.len()];
                            let mut flags = vec![0u8; set.rays.len()];
                            let t0 = Instant::now();
                            p.install(|| trace_set(a, set, &mut hits, &mut flags));
                            trace[k].push(t0.elapsed().as_secs_f64());
                            if si == 0 {
                                if reference.len() <= k {
                                    reference.push(Vec::new());
                                }
                                reference[k].push(if set.kind == SetKind::Ao {
                                    occlusion_hits(&flags)
                                } else {
                                    hits
                                });
                            } else {
                                let r = &reference[k][f];
                                agree[k].0 += compare(set, &hits, &flags, r, tris).0;
                            }
                            agree[k].1 += set.rays.len();
                        }
                    }
                    if let Some(e) = refused {
                        crate::note!("bench:   {} refit skipped: {e}", kind.name());
                        continue;
                    }
                    let from = usize::from(mode == Mode::Refit);
                    for (k, set) in sets.iter().enumerate() {
                        let frame: Vec<f64> = (from..frames.len())
                            .map(|f| update[f] + trace[k][f])
                            .collect();
                        let s = FrameSeries {
                            accel: kind.name().into(),
                            mode: mode.name().into(),
                            threads,
                            set: set.kind.name().into(),
                            rays: set.rays.len(),
                            median_update_seconds: median(&update[from..]),
                            median_trace_seconds: median(&trace[k][from..]),
                            median_frame_seconds: median(&frame),
                            update_seconds: update.clone(),
                            trace_seconds: trace[k].clone(),
                            agreement: if agree[k].1 == 0 {
                                1.0
                            } else {
                                1.0 - agree[k].0 as f64 / agree[k].1 as f64
                            },
                        };
                        crate::note!(
                            "bench:   {:<14} {:<7} {:>2} thr {:<9} {:>8} rays  prep {:>8.2} ms  trace {:>8.2} ms  frame {:>8.2} ms",
                            s.accel,
                            s.mode,
                            s.threads,
                            s.set,
                            s.rays,
                            s.median_update_seconds * 1e3,
                            s.median_trace_seconds * 1e3,
                            s.median_frame_seconds * 1e3
                        );
                        out.series.push(s);
                    }
                }
            }
        }
        (out.auto, out.auto_unmeasured) = score_auto(&out.series, out.triangles, config.build);
        report.scenes.push(out);
    }
    Ok(report)
}
