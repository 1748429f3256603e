//! `rayd bench`: every selected accelerator traces exactly the same rays, and the time spent
//! inside the intersector is all that is counted (Áfra 2013 §5).
//!
//! For each scene: a view (the scene's camera 0, a default framing view, or one given), a
//! *room* around the scene for interior views so that every ray hits and every bounce keeps
//! the full batch, and ray sets made once from a fixed seed: primary, ambient occlusion, and
//! the rays of diffuse bounces 1, 2 and 8. Each accelerator is built and traced single- and
//! multi-threaded, the median of several runs is reported, and its hits are checked against
//! a reference.

mod dynamic;
mod raysets;
mod report;
mod view;

use std::path::PathBuf;
use std::time::Instant;

use serde::Serialize;

use crate::accel::triangle::oracle_line_f64;
use crate::accel::{AccelKind, BuildOptions, BuildQuality, Intersector, Precision, Query};
use crate::geometry::{Hit, Ray, Triangle};
pub use crate::render::camera::CameraChoice;
pub use dynamic::{AutoPick, DynamicConfig, DynamicReport, DynamicScene, FrameSeries, Motion};
pub use raysets::{RaySet, SetKind};
pub use report::{render_csv, render_dynamic_table, render_table};
pub use view::{View, ViewKind};

/// Errors of a benchmark run.
#[derive(Debug, thiserror::Error)]
pub enum BenchError {
    /// A scene could not be loaded.
    #[error(transparent)]
    Format(#[from] crate::formats::FormatError),
    /// An accelerator could not be built.
    #[error(transparent)]
    Accel(#[from] crate::accel::AccelError),
    /// The camera is unusable.
    #[error(transparent)]
    Camera(#[from] crate::render::camera::CameraError),
    /// A thread pool could not be made.
    #[error("cannot start the thread pool: {0}")]
    Pool(#[from] rayon::ThreadPoolBuildError),
    /// The configuration is unusable.
    #[error("{0}")]
    Config(String),
    /// Writing a dump failed.
    #[error("{path}: {source}")]
    Io {
        /// The file.
        path: String,
        /// The OS error.
        source: std::io::Error,
    },
}

impl BenchError {
    /// The error, its message prefixed with the scene it concerns where it names none.
    fn of_scene(self, path: &std::path::Path) -> BenchError {
        match self {
            BenchError::Config(m) => BenchError::Config(format!("{}: {m}", path.display())),
            e => e,
        }
    }
}

/// What to measure.
#[derive(Clone, Debug)]
pub struct BenchConfig {
    /// Scene files.
    pub scenes: Vec<PathBuf>,
    /// Accelerators to measure (`auto` is resolved per scene).
    pub accels: Vec<AccelKind>,
    /// Ray sets to make and trace.
    pub sets: Vec<SetKind>,
    /// Views per scene.
    pub views: Vec<ViewKind>,
    /// Image width (rays per set = width × height).
    pub width: u32,
    /// Image height.
    pub height: u32,
    /// Camera.
    pub camera: CameraChoice,
    /// Timed runs per measurement; the median is reported.
    pub runs: usize,
    /// Thread counts to measure (0 = all cores).
    pub threads: Vec<usize>,
    /// Seed of the ray sets.
    pub seed: u64,
    /// Build quality for the BVH accelerators and Embree.
    pub build: BuildQuality,
    /// Ray/triangle test.
    pub precision: Precision,
    /// Reference accelerator (`auto`: brute on small scenes, embree on large ones).
    pub reference: AccelKind,
    /// Animation time.
    pub time: Option<f64>,
    /// Where to write each ray set (RAY1) and the reference hits (HIT1).
    pub dump: Option<PathBuf>,
}

impl Default for BenchConfig {
    fn default() -> Self {
        BenchConfig {
            scenes: Vec::new(),
            accels: vec![AccelKind::Auto],
            sets: SetKind::ALL.to_vec(),
            views: vec![ViewKind::Interior],
            width: 1024,
            height: 768,
            camera: CameraChoice::Auto,
            runs: 5,
            threads: vec![1, 0],
            seed: 1,
            build: BuildQuality::default(),
            precision: Precision::default(),
            reference: AccelKind::Auto,
            time: None,
            dump: None,
        }
    }
}

/// One accelerator × thread count × ray set.
#[derive(Clone, Debug, Serialize)]
pub struct Measurement {
    /// Accelerator name.
    pub accel: String,
    /// Threads used.
    pub threads: usize,
    /// Ray set name.
    pub set: String,
    /// Rays in the set.
    pub rays: usize,
    /// Median trace seconds.
    pub seconds: f64,
    /// Rays / median seconds / 1e6.
    pub mrays_per_s: f64,
    /// Every run's seconds, in order.
    pub runs: Vec<f64>,
    /// Fraction of rays whose answer matches the reference (same triangle, or the same t
    /// within 1e-5 relative; for AO the same occlusion).
    pub agreement: f64,
    /// Rays that do not match.
    pub disagreements: usize,
    /// Of those, the edge cases (see `edge_cases`); the rest are unexplained.
    pub edge_disagreements: usize,
    /// Traversal steps and triangle tests per ray, counted on up to the set's first
    /// 65,536 rays (`closest` sets of cores that count them; measured once, untimed).
    pub steps: Option<serde_json::Value>,
}

/// One accelerator × thread count build.
#[derive(Clone, Debug, Serialize)]
pub struct BuildMeasurement {
    /// Accelerator name.
    pub accel: String,
    /// Threads used.
    pub threads: usize,
    /// Median build seconds.
    pub seconds: f64,
    /// Bytes the accelerator holds.
    pub bytes: usize,
    /// The accelerator's structure statistics, if it has a structure.
    pub stats: Option<serde_json::Value>,
}

/// The results of one scene and view.
#[derive(Clone, Debug, Serialize)]
pub struct SceneReport {
    /// Scene file.
    pub scene: String,
    /// Triangles of the scene (without the room).
    pub triangles: usize,
    /// Triangles traced (with the room for interior views).
    pub traced_triangles: usize,
    /// `interior` or `exterior`.
    pub view: String,
    /// The camera used, in words.
    pub camera: String,
    /// The accelerator whose hits are the reference.
    pub reference: String,
    /// Rays per set.
    pub sets: Vec<(String, usize)>,
    /// Build times.
    pub builds: Vec<BuildMeasurement>,
    /// Trace times.
    pub results: Vec<Measurement>,
}

/// The whole run.
#[derive(Clone, Debug, Serialize)]
pub struct BenchReport {
    /// Logical cores of the machine.
    pub cores: usize,
    /// SIMD backend.
    pub simd: String,
    /// Width × height.
    pub resolution: [u32; 2],
    /// Runs per measurement.
    pub runs: usize,
    /// Build quality.
    pub build: String,
    /// Precision.
    pub precision: String,
    /// Seed.
    pub seed: u64,
    /// Per scene and view.
    pub scenes: Vec<SceneReport>,
}

fn median(v: &[f64]) -> f64 {
    let mut s = v.to_vec();
    s.sort_by(|a, b| a.total_cmp(b));
    if s.is_empty() {
        return 0.0;
    }
    let m = s.len() / 2;
    if s.len() % 2 == 1 {
        s[m]
    } else {
        0.5 * (s[m - 1] + s[m])
    }
}

fn pool(threads: usize) -> Result<rayon::ThreadPool, BenchError> {
    Ok(rayon::ThreadPoolBuilder::new()
        .num_threads(threads)
        .build()?)
}

/// Traces a set the way it is judged: AO with the `any` query answering occlusion only,
/// everything else `closest`.
fn trace_set(accel: &dyn Intersector, set: &RaySet, hits: &mut [Hit], flags: &mut [u8]) {
    if set.kind == SetKind::Ao {
        accel.occluded(&set.rays, flags);
    } else {
        accel.trace(&set.rays, Query::Closest, hits);
    }
}

/// Compares a trace of `set` with `reference` (one record per ray; for AO only whether
/// it hits): how many rays answer differently, and how many of those are explained by f32
/// rounding — one answer's triangle is met, by the ray's line, within rounding of its
/// boundary (see [`borderline`]), so that which of two neighbours (or neither) the ray
/// hits is decided by rounding. AO sets report only occlusion, so nothing there is
/// classified.
fn compare(
    set: &RaySet,
    hits: &[Hit],
    flags: &[u8],
    reference: &[Hit],
    triangles: &[Triangle],
) -> (usize, usize) {
    if set.kind == SetKind::Ao {
        let bad = flags
            .iter()
            .zip(reference)
            .filter(|(f, r)| (**f != 0) != r.is_hit())
            .count();
        return (bad, 0);
    }
    let (mut bad, mut explained) = (0, 0);
    for ((ray, h), r) in set.rays.iter().zip(hits).zip(reference) {
        if !same_answer(h, r) {
            bad += 1;
            explained += usize::from(
                [h, r]
                    .iter()
                    .any(|x| x.is_hit() && borderline(ray, &triangles[x.prim as usize])),
            );
        }
    }
    (bad, explained)
}

/// Whether `ray`'s line meets `tri` within rounding of its boundary: its barycentric margin
/// times its smallest altitude is at most `1e-5 × (largest coordinate)`, divided by the
/// cosine between the ray and the triangle's plane, since at grazing angles a rounding of
/// the position moves the crossing point along the plane by that much more.
fn borderline(ray: &Ray, tri: &Triangle) -> bool {
    let Some(h) = oracle_line_f64(ray, tri) else {
        return true;
    };
    let p = tri.v.map(|q| q.map(f64::from));
    let sub = |a: [f64; 3], b: [f64; 3]| [0, 1, 2].map(|k| b[k] - a[k]);
    let dot = |a: [f64; 3], b: [f64; 3]| a[0] * b[0] + a[1] * b[1] + a[2] * b[2];
    let (e1, e2) = (sub(p[0], p[1]), sub(p[0], p[2]));
    let n = [
        e1[1] * e2[2] - e1[2] * e2[1],
        e1[2] * e2[0] - e1[0] * e2[2],
        e1[0] * e2[1] - e1[1] * e2[0],
    ];
    let len = |d: [f64; 3]| dot(d, d).sqrt();
    let d = ray.dir.map(f64::from);
    let longest = len(e1).max(len(e2)).max(len(sub(p[1], p[2])));
    let altitude = len(n) / longest;
    let cos = (dot(n, d).abs() / (len(n) * len(d))).max(1e-9);
    let scale = p
        .iter()
        .flatten()
        .chain(&ray.org.map(f64::from))
        .fold(1.0f64, |m, x| m.max(x.abs()));
    let margin = h.u.min(h.v).min(1.0 - h.u - h.v).abs();
    margin * altitude <= 1e-5 * scale / cos
}

/// The same triangle, or the same distance (a tie between coplanar or adjacent triangles).
pub fn same_answer(a: &Hit, b: &Hit) -> bool {
    if a.prim == b.prim {
        return true;
    }
    if !a.is_hit() || !b.is_hit() {
        return false;
    }
    (a.t - b.t).abs() <= 1e-5 * a.t.abs().max(b.t.abs()).max(1e-30)
}

/// Brute force is the reference while it stays affordable (about 2·10^9 ray/triangle tests
/// a set); beyond that, Embree where it is built in.
fn auto_reference(triangles: usize, rays_per_set: usize) -> AccelKind {
    if (triangles as f64) * (rays_per_set as f64) <= 2e9 || !AccelKind::Embree.available() {
        AccelKind::Brute
    } else {
        AccelKind::Embree
    }
}

/// Runs the dynamic-geometry benchmark (`rayd bench --frames`); progress goes to stderr.
pub fn run_dynamic(config: &DynamicConfig) -> Result<DynamicReport, BenchError> {
    dynamic::run(config)
}

/// Runs the benchmark; progress goes to stderr.
pub fn run(config: &BenchConfig) -> Result<BenchReport, BenchError> {
    if config.scenes.is_empty() {
        return Err(BenchError::Config("no scene given".into()));
    }
    if config.runs == 0 || config.width == 0 || config.height == 0 {
        return Err(BenchError::Config(
            "--runs, --width and --height must be at least 1".into(),
        ));
    }
    // A set holds width × height rays: bounded as a trace's batch is (`--max-rays`).
    let max_rays = crate::jobs::Limits::default().max_rays as u64;
    let rays = u64::from(config.width) * u64::from(config.height);
    if rays > max_rays {
        return Err(BenchError::Config(format!(
            "--width × --height is {rays} rays a set, over the limit of {max_rays}"
        )));
    }
    for &k in &config.accels {
        if !k.available() {
            return Err(crate::accel::AccelError::Unavailable(k.name()).into());
        }
    }
    // Dumps are named for the scene file's stem: two scenes of one stem would overwrite
    // each other's.
    if config.dump.is_some() {
        for (i, a) in config.scenes.iter().enumerate() {
            if let Some(b) = config.scenes[..i]
                .iter()
                .find(|b| b.file_stem() == a.file_stem())
            {
                return Err(BenchError::Config(format!(
                    "--dump: {} and {} would write the same files (their names share a stem)",
                    b.display(),
                    a.display()
                )));
            }
        }
    }
    let mut report = BenchReport {
        cores: std::thread::available_parallelism().map_or(1, |n| n.get()),
        simd: crate::simd::selected().name().into(),
        resolution: [config.width, config.height],
        runs: config.runs,
        build: config.build.name().into(),
        precision: config.precision.name().into(),
        seed: config.seed,
        scenes: Vec::new(),
    };
    let all = pool(0)?;
    for path in &config.scenes {
        let scene =
            crate::formats::load_scene(path, &crate::formats::LoadOptions { time: config.time })?;
        for &view_kind in &config.views {
            let view = View::new(
                &scene,
                view_kind,
                &config.camera,
                config.width,
                config.height,
            )
            .map_err(|e| e.of_scene(path))?;
            let rays_per_set = config.width as usize * config.height as usize;
            let reference = match config.reference {
                AccelKind::Auto => auto_reference(view.triangles.len(), rays_per_set),
                k => k,
            };
            crate::note!(
                "bench: {} ({} triangles, {} view): making ray sets with {}",
                path.display(),
                scene.triangles.len(),
                view_kind.name(),
                reference.name()
            );
            let options = BuildOptions {
                quality: config.build,
                precision: config.precision,
                threads: all.current_num_threads(),
                dacrt: crate::accel::dacrt::DacrtTuning::from_env(),
            };
            let ref_accel =
                all.install(|| crate::accel::build(reference, &view.triangles, &options))?;
            let sets = all.install(|| {
                raysets::make_sets(&view, ref_accel.as_ref(), &config.sets, config.seed)
            });
            drop(ref_accel);
            if let Some(dir) = &config.dump {
                raysets::dump(dir, path, view_kind, &view.triangles, &sets)?;
            }
            let mut scene_report = SceneReport {
                scene: path.display().to_string(),
                triangles: scene.triangles.len(),
                traced_triangles: view.triangles.len(),
                view: view_kind.name().into(),
                camera: view.camera_description.clone(),
                reference: reference.name().into(),
                sets: sets
                    .iter()
                    .map(|s| (s.kind.name().to_string(), s.rays.len()))
                    .collect(),
                builds: Vec::new(),
                results: Vec::new(),
            };
            let rays_total: usize = sets.iter().map(|s| s.rays.len()).sum();
            // `auto` may resolve to a core also named, and `--threads 0` to a count also
            // named: each pair is measured once (session 31's review found both measured
            // twice, and the table printing the first's figures on both rows).
            let mut measured: Vec<(&'static str, usize)> = Vec::new();
            for &asked in &config.accels {
                for &threads in &config.threads {
                    let p = pool(threads)?;
                    let threads = p.current_num_threads();
                    let kind = asked.resolve(&crate::accel::auto::Job {
                        rays: rays_total,
                        batches: sets.len(),
                        triangles: view.triangles.len(),
                        threads,
                        quality: config.build,
                        geometry: crate::accel::auto::Geometry::New,
                        frames: 1,
                        arrival: 0.0,
                        first_hit: false,
                    });
                    if asked != kind {
                        crate::note!("bench: {} resolves to {}", asked.name(), kind.name());
                    }
                    if measured.contains(&(kind.name(), threads)) {
                        crate::note!(
                            "bench: {} on {threads} thread(s) is measured once",
                            kind.name()
                        );
                        continue;
                    }
                    measured.push((kind.name(), threads));
                    let options = BuildOptions { threads, ..options };
                    let mut build_times = Vec::new();
                    let mut accel = None;
                    for _ in 0..config.runs {
                        drop(accel.take());
                        let t0 = Instant::now();
                        let a =
                            p.install(|| crate::accel::build(kind, &view.triangles, &options))?;
                        build_times.push(t0.elapsed().as_secs_f64());
                        accel = Some(a);
                    }
                    let accel = accel.expect("runs >= 1");
                    scene_report.builds.push(BuildMeasurement {
                        accel: accel.name().into(),
                        threads,
                        seconds: median(&build_times),
                        bytes: accel.bytes(),
                        stats: accel.stats(),
                    });
                    for set in &sets {
                        let mut hits = vec![Hit::MISS; set.rays.len()];
                        let mut flags = vec![0u8; set.rays.len()];
                        let mut times = Vec::with_capacity(config.runs);
                        for _ in 0..config.runs {
                            let t0 = Instant::now();
                            p.install(|| trace_set(accel.as_ref(), set, &mut hits, &mut flags));
                            times.push(t0.elapsed().as_secs_f64());
                        }
                        let (bad, at_edges) =
                            compare(set, &hits, &flags, &set.reference, &view.triangles);
                        let steps = if set.kind == SetKind::Ao
                            || scene_report.results.iter().any(|m: &Measurement| {
                                m.accel == accel.name() && m.set == set.kind.name()
                            }) {
                            None
                        } else {
                            accel.count_steps(&set.rays[..set.rays.len().min(1 << 16)])
                        };
                        let secs = median(&times);
                        let m = Measurement {
                            accel: accel.name().into(),
                            threads,
                            set: set.kind.name().into(),
                            rays: set.rays.len(),
                            seconds: secs,
                            mrays_per_s: if secs > 0.0 {
                                set.rays.len() as f64 / secs / 1e6
                            } else {
                                0.0
                            },
                            runs: times,
                            agreement: if set.rays.is_empty() {
                                1.0
                            } else {
                                1.0 - bad as f64 / set.rays.len() as f64
                            },
                            disagreements: bad,
                            edge_disagreements: at_edges,
                            steps,
                        };
                        crate::note!(
                            "bench:   {:<14} {:>2} thr  {:<9} {:>8.3} Mray/s  agree {:.6}",
                            m.accel,
                            m.threads,
                            m.set,
                            m.mrays_per_s,
                            m.agreement
                        );
                        scene_report.results.push(m);
                    }
                }
            }
            report.scenes.push(scene_report);
        }
    }
    Ok(report)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn ray(org: [f32; 3], dir: [f32; 3]) -> Ray {
        Ray {
            org,
            tmin: 0.0,
            dir,
            tmax: f32::INFINITY,
        }
    }

    #[test]
    fn borderline_is_rounding_distance_from_the_boundary_allowing_for_grazing_angles() {
        let tri = Triangle {
            v: [[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]],
        };
        // Head-on through the middle: clearly inside.
        assert!(!borderline(&ray([0.25, 0.25, 1.0], [0.0, 0.0, -1.0]), &tri));
        // Head-on through the edge x = 0: decided by rounding.
        assert!(borderline(&ray([0.0, 0.5, 1.0], [0.0, 0.0, -1.0]), &tri));
        // Head-on, 1e-3 inside the edge: not borderline.
        assert!(!borderline(&ray([1e-3, 0.5, 1.0], [0.0, 0.0, -1.0]), &tri));
        // The same crossing point reached at a grazing angle (cos ≈ 1e-3): borderline.
        assert!(borderline(
            &ray([-999.999, 0.5, 1.0], [1.0, 0.0, -1e-3]),
            &tri
        ));
        // Parallel to the plane: never meets it, borderline by definition.
        assert!(borderline(&ray([0.25, 0.25, 1.0], [1.0, 0.0, 0.0]), &tri));
    }
}
