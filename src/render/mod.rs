//! Rendering: synchronous and format-free. It makes batches of rays, traces them with any
//! [`Intersector`] and shades the hits; `image` turns the result into PNG or OpenEXR bytes.
//!
//! Work goes in waves (all primary rays of a block of pixels, then all their secondary
//! rays), never ray by ray, because the batch cores (DACRT) only exist in that form and the
//! others lose nothing by it.

pub mod brdf;
pub mod bundle;
pub mod camera;
pub mod image;
pub mod lights;
pub mod mipmap;
pub mod rng;
pub mod sampling;
pub mod surface;
pub mod texture;

use crate::accel::{Intersector, Query};
use crate::geometry::{dot, Aabb, Hit, Ray, Triangle};
use camera::{PixelRect, ViewCamera, RAYS_AT_ONCE};
use glam::Vec3;
use lights::{power_heuristic, LightPick, LightSampler};
use rayon::prelude::*;
use rng::Pcg32;
use sampling::{basis, cosine_hemisphere, normalize};
use surface::{offset_ray, surface_point, Located, Presence, Surfaces};

/// What a pixel shows.
#[derive(
    Clone, Copy, Debug, PartialEq, Eq, Hash, Default, serde::Serialize, serde::Deserialize,
)]
#[serde(rename_all = "kebab-case")]
pub enum Integrator {
    /// Primary rays with a light at the eye: brightness is |cos| of the view angle.
    #[default]
    Primary,
    /// The geometric normal, facing the viewer, mapped to colour.
    Normals,
    /// Ambient occlusion: cosine-weighted `any` rays of 1/8 of the scene diagonal.
    Ao,
    /// Path tracing through the scene's glTF materials, lit by its punctual lights, its
    /// emitters and the constant sky.
    Path,
}

impl Integrator {
    /// Every integrator.
    pub const ALL: [Integrator; 4] = [
        Integrator::Primary,
        Integrator::Normals,
        Integrator::Ao,
        Integrator::Path,
    ];

    /// The contract's name.
    pub fn name(self) -> &'static str {
        crate::names::Spelled::name(self)
    }

    /// Parses the contract's name.
    pub fn parse(s: &str) -> Option<Integrator> {
        crate::names::Spelled::parse_name(s).ok()
    }
}

crate::spelled!(Integrator, Integrator::ALL);

/// An arbitrary output variable: extra per-pixel data of the primary hit, written as EXR
/// channels (`proto/rendering.md`, "Output").
#[derive(
    Clone, Copy, Debug, PartialEq, Eq, Hash, PartialOrd, Ord, serde::Serialize, serde::Deserialize,
)]
#[serde(rename_all = "kebab-case")]
pub enum Aov {
    /// `depth.Z`: distance from the camera ray's origin to the hit (+inf where none).
    Depth,
    /// `normal.X/Y/Z`: the world-space shading normal, turned towards the camera (0 where
    /// nothing is hit).
    Normal,
    /// `albedo.R/G/B`: the surface's base colour (0 where nothing is hit).
    Albedo,
    /// `prim.id`: the hit triangle's id (`u32::MAX` where none).
    Prim,
}

impl Aov {
    /// Every AOV.
    pub const ALL: [Aov; 4] = [Aov::Depth, Aov::Normal, Aov::Albedo, Aov::Prim];

    /// The first AOV that `list` names a second time: a request lists each at most once,
    /// on the command line as in JSON (`uniqueItems`).
    pub fn repeated(list: &[Aov]) -> Option<Aov> {
        list.iter()
            .enumerate()
            .find_map(|(i, a)| list[..i].contains(a).then_some(*a))
    }
}

crate::spelled!(Aov, Aov::ALL);

/// Which AOVs a render keeps (a set; order and repetition of a request do not matter).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Hash)]
pub struct AovSet {
    /// `depth`.
    pub depth: bool,
    /// `normal`.
    pub normal: bool,
    /// `albedo`.
    pub albedo: bool,
    /// `prim`.
    pub prim: bool,
}

impl AovSet {
    /// The set of `list`.
    pub fn of(list: &[Aov]) -> AovSet {
        let has = |a| list.contains(&a);
        AovSet {
            depth: has(Aov::Depth),
            normal: has(Aov::Normal),
            albedo: has(Aov::Albedo),
            prim: has(Aov::Prim),
        }
    }

    /// Whether no AOV is asked for.
    pub fn is_empty(&self) -> bool {
        *self == AovSet::default()
    }

    /// The members, in [`Aov::ALL`]'s order.
    pub fn list(&self) -> Vec<Aov> {
        let on = [self.depth, self.normal, self.albedo, self.prim];
        Aov::ALL
            .into_iter()
            .zip(on)
            .filter_map(|(a, on)| on.then_some(a))
            .collect()
    }
}

/// How to render.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct RenderOptions {
    /// Image width in pixels.
    pub width: u32,
    /// Image height in pixels.
    pub height: u32,
    /// Samples per pixel (a shifted Hammersley set within the pixel: [`pixel_sample`]).
    pub spp: u32,
    /// What to compute.
    pub integrator: Integrator,
    /// Bounces for `path` (diffuse bounces after the primary hit).
    pub bounces: u32,
    /// Seed of every random choice; the same seed gives the same image.
    pub seed: u64,
    /// Radiance of the constant environment `path` sees (linear RGB).
    pub sky: [f32; 3],
    /// AOVs to keep.
    pub aovs: AovSet,
    /// Russian roulette for `path`: `Some(k)` lets paths end at random from their k-th
    /// scattering on (k ≥ 1), weighting survivors up; `None` follows every path to
    /// `bounces`.
    pub roulette: Option<u32>,
    /// Whether `path` samples emissive triangles and the sky by next-event estimation
    /// (weighted against BRDF sampling by MIS). `false` leaves them to BRDF sampling
    /// alone: unbiased but noisier, the reference that tests hold MIS to. Punctual lights
    /// are sampled either way, since nothing else can reach them. Library-only: the CLI and
    /// the service always sample lights.
    pub light_sampling: bool,
}

impl Default for RenderOptions {
    fn default() -> Self {
        RenderOptions {
            width: 640,
            height: 480,
            spp: 1,
            integrator: Integrator::Primary,
            bounces: 2,
            seed: 0,
            sky: [1.0; 3],
            aovs: AovSet::default(),
            roulette: None,
            light_sampling: true,
        }
    }
}

/// A rendered frame: linear-light RGB radiance, coverage and the AOVs asked for, each
/// row-major with the top row first.
#[derive(Clone, Debug, PartialEq)]
pub struct Image {
    /// Width in pixels.
    pub width: u32,
    /// Height in pixels.
    pub height: u32,
    /// Radiance: the mean of the pixel's samples (box filter).
    pub pixels: Vec<[f32; 3]>,
    /// Coverage: the fraction of the pixel's samples whose camera ray hit a triangle. A
    /// matte, not a compositing alpha: the radiance is not premultiplied by it, and it
    /// holds what misses see (background or sky) too.
    pub alpha: Vec<f32>,
    /// The AOVs asked for.
    pub aovs: Aovs,
}

/// Per-pixel AOV buffers, `Some` for those asked for. They describe one surface point per
/// pixel, the primary hit of the pixel's sample 0, so that a pixel's depth, normal, albedo
/// and triangle id agree with each other (a mean of ids would mean nothing).
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Aovs {
    /// Hit distance along the unit camera ray; +inf where it misses.
    pub depth: Option<Vec<f32>>,
    /// World-space unit shading normal facing the camera; 0 where it misses.
    pub normal: Option<Vec<[f32; 3]>>,
    /// Base colour of the surface (linear RGB); 0 where it misses.
    pub albedo: Option<Vec<[f32; 3]>>,
    /// Triangle id; `u32::MAX` where it misses.
    pub prim: Option<Vec<u32>>,
}

/// What the primary hit of a pixel's sample 0 shows, for the AOVs.
#[derive(Clone, Copy, Debug, PartialEq)]
struct Primary {
    depth: f32,
    normal: [f32; 3],
    albedo: [f32; 3],
    prim: u32,
}

impl Primary {
    const MISS: Primary = Primary {
        depth: f32::INFINITY,
        normal: [0.0; 3],
        albedo: [0.0; 3],
        prim: u32::MAX,
    };
}

/// Counters of one render, returned with the image.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct RenderStats {
    /// Rays traced, all kinds.
    pub rays: u64,
    /// Seconds spent inside the intersector.
    pub trace_seconds: f64,
}

/// Paths per wave for a core that wants large batches (DACRT): bounds the memory of one
/// wave's rays and hits (about 12 MiB).
const WAVE_PATHS: usize = 1 << 18;

/// Paths per wave for the per-ray cores. A wave's buffers (paths, rays, hits, shading
/// steps: 180–350 bytes a pixel) are written fresh the first time, and every new page is
/// a fault that serialises on the process's memory map; waves an eighth of DACRT's size
/// touch an eighth of the memory and reuse it, and its passes stay in cache. Path renders
/// of 640×480 took 0.80–0.95× the time with a quarter (2^16), the trace itself 0.95–1.18×;
/// an eighth, once the rays and hits lived beside the paths, took 0.85–1.00× the shading
/// time of a quarter, the trace unchanged (BENCHMARKS §19).
const BVH_WAVE_PATHS: usize = 1 << 15;

const BACKGROUND: [f32; 3] = [0.05, 0.06, 0.08];

/// The unit geometric normal of the hit triangle, turned to face against the ray.
#[inline]
pub fn facing_normal(tri: &Triangle, dir: [f32; 3]) -> [f32; 3] {
    let n = normalize(tri.normal());
    if dot(n, dir) > 0.0 {
        [-n[0], -n[1], -n[2]]
    } else {
        n
    }
}

/// A point just off the surface at `hit` on the side `n` faces, so the next ray does not
/// hit the same triangle again: the offset scales with the point's magnitude, which keeps it
/// above f32 rounding far from the origin.
#[inline]
pub fn offset_origin(p: [f32; 3], n: [f32; 3]) -> [f32; 3] {
    let scale = 1e-4 * (1.0 + p[0].abs().max(p[1].abs()).max(p[2].abs()));
    [
        p[0] + n[0] * scale,
        p[1] + n[1] * scale,
        p[2] + n[2] * scale,
    ]
}

/// How a caller drives a render's waves: each wave (a block of pixels for a run of
/// [`SAMPLES_AT_ONCE`] samples, with all their bounces) runs through [`Waves::run_wave`],
/// where the caller may hold the thread pool under a scheduler's lease, notice
/// cancellation and report progress. Waves
/// are sized to last about [`Waves::wave_seconds`]; how the pixels are split into waves
/// never changes the image, since each pixel and sample owns its random stream.
pub trait Waves: Sync {
    /// Why a render stopped early.
    type Error;
    /// Runs one wave, or refuses to (the job was cancelled).
    fn run_wave(&self, wave: &mut (dyn FnMut() + Send)) -> Result<(), Self::Error>;
    /// Seconds the next wave should take (infinite: as large as memory allows).
    fn wave_seconds(&self) -> f64;
    /// The fraction of the render done, 0 to 1.
    fn progress(&self, fraction: f64);
}

/// Paths of the first wave when waves are sized in seconds, before a rate is known.
const FIRST_WAVE_PATHS: usize = 1 << 13;
/// The smallest wave.
const MIN_WAVE_PATHS: usize = 1 << 10;

/// Samples of a pixel that one wave takes together, its paths side by side. The samples
/// of a pixel mostly hit the same surface: shaded one after another, their texture reads
/// find the texels the first one brought into cache, where a wave per sample read them
/// again from memory a whole image later. The runs are fixed (samples 0–3, 4–7, …), so a
/// pixel's sum adds the same terms in the same order however waves are sized.
const SAMPLES_AT_ONCE: u32 = 4;

/// The light table of a `path` frame ([`LightSampler::new`]), built on the pool as a
/// step of its own: weighing textured emitters reads their textures.
pub fn light_table<W: Waves + ?Sized>(
    triangles: &[Triangle],
    surfaces: &Surfaces,
    options: &RenderOptions,
    waves: &W,
) -> Result<LightSampler, W::Error> {
    let mut built = None;
    waves.run_wave(&mut || {
        built = Some(LightSampler::new(
            triangles,
            surfaces,
            Vec3::from(options.sky),
            options.light_sampling,
        ))
    })?;
    Ok(built.expect("run_wave runs its step or returns the error"))
}

/// Renders `triangles` (the ones `accel` was built over) through `camera`, in waves driven
/// by `waves`. `bounds`, a box around `triangles` (`None`: not known), tells which pixels'
/// camera rays can hit anything; only those are traced. `surfaces` holds the
/// materials and lights that `path` and the `albedo` and `normal` AOVs use; without it every
/// triangle has glTF's default material, face normals and no light but the sky. `lights`
/// is a `path` frame's light table when the caller kept the one an earlier frame of the
/// same positions, surfaces, `sky` and `light_sampling` built ([`light_table`]); `None`
/// builds it.
#[allow(clippy::too_many_arguments)]
pub fn render<W: Waves + ?Sized>(
    triangles: &[Triangle],
    accel: &dyn Intersector,
    camera: &ViewCamera,
    options: &RenderOptions,
    bounds: Option<&Aabb>,
    surfaces: Option<&Surfaces>,
    lights: Option<&LightSampler>,
    waves: &W,
) -> Result<(Image, RenderStats), W::Error> {
    let fallback;
    let surfaces = match surfaces {
        Some(s) => s,
        None => {
            fallback = Surfaces::default();
            &fallback
        }
    };
    let own;
    let lights = if options.integrator != Integrator::Path {
        own = LightSampler::default();
        &own
    } else if let Some(given) = lights {
        given
    } else {
        own = light_table(triangles, surfaces, options, waves)?;
        &own
    };
    let (w, h) = (options.width, options.height);
    let n = w as usize * h as usize;
    let spp = options.spp.max(1);
    // The ambient-occlusion distance comes from the triangles themselves, whatever box the
    // caller gave.
    let scene_diagonal = match options.integrator {
        Integrator::Ao => crate::scene::bounds_of(triangles).map_or(1.0, |b| b.diagonal()),
        _ => 1.0,
    };
    // Pixels outside it see what a miss sees, without a ray (`render_wave`).
    let visible = bounds.map_or(PixelRect::full(w, h), |b| camera.pixel_rect(b, w, h));
    // Each sample adds its share (radiance / spp), so the sum is the pixel's mean, and it
    // stays finite wherever the samples are (a sky of 3e38 over 4 samples: a sum of the
    // samples themselves would overflow). f64 sums would do as well, but their buffer's
    // page faults cost a small frame a tenth of its shading (BENCHMARKS §33).
    let mut sum = vec![[0.0f32; 3]; n];
    // On the pool as well: outside a wave, rayon would use its global pool, whose threads
    // (one per core) `--threads` does not bound.
    waves.run_wave(&mut || fill_misses(&mut sum, visible, w as usize, options))?;
    let mut covered = vec![0u32; n];
    let mut primary = if options.aovs.is_empty() {
        Vec::new()
    } else {
        vec![Primary::MISS; n]
    };
    let mut stats = RenderStats::default();
    // Progress and wave sizes count the pixels inside `visible`: only they trace rays,
    // and a row of sky above the scene costs next to nothing (counted by all pixels, a
    // helmet frame read 0.25 done after 1% of its time, and a wave of sky rows made the
    // rate, and so the next wave, several times too large).
    let inside = |start: usize, end: usize| {
        visible.inside_before(end, w as usize) - visible.inside_before(start, w as usize)
    };
    let total = visible.len() as f64 * spp as f64;
    let mut done = 0.0;
    let run = spp.min(SAMPLES_AT_ONCE);
    let max_paths = if accel.large_batches() {
        WAVE_PATHS
    } else {
        BVH_WAVE_PATHS
    };
    // A wave's pixels inside each take `run` paths.
    let pixels_for = |paths: usize| (paths.clamp(MIN_WAVE_PATHS, max_paths) / run as usize).max(1);
    let mut wave_pixels = pixels_for(if waves.wave_seconds().is_finite() {
        FIRST_WAVE_PATHS
    } else {
        max_paths
    });
    let mut scratch = Scratch::default();
    let mut start = 0;
    while start < n {
        // A wave's pixels are numbered from its start in u32 (`render_wave`).
        let end = visible
            .end_after(start, wave_pixels, w as usize)
            .map_or(n, |e| e.min(n))
            .min(start + u32::MAX as usize);
        let traced = inside(start, end);
        let mut seconds = 0.0;
        for first in (0..spp).step_by(run as usize) {
            let samples = first..(first + run).min(spp);
            let t0 = std::time::Instant::now();
            let mut out = WaveOut {
                radiance: &mut sum[start..end],
                covered: &mut covered[start..end],
                primary: if first == 0 && !primary.is_empty() {
                    Some(&mut primary[start..end])
                } else {
                    None
                },
            };
            let stats = &mut stats;
            let scratch = &mut scratch;
            let taken = samples.len();
            waves.run_wave(&mut || {
                render_wave(
                    Frame {
                        triangles,
                        accel,
                        camera,
                        options,
                        scene_diagonal,
                        visible,
                        surfaces,
                        lights,
                    },
                    (start, end, samples.clone()),
                    &mut out,
                    scratch,
                    stats,
                )
            })?;
            seconds += t0.elapsed().as_secs_f64();
            done += (traced * taken) as f64;
            waves.progress(if total > 0.0 {
                done / total
            } else {
                end as f64 / n as f64
            });
        }
        // Size the next block's waves from this block's rate.
        let target = waves.wave_seconds();
        if traced > 0 {
            wave_pixels = pixels_for(if target.is_finite() && seconds > 0.0 {
                let rate = traced as f64 * spp as f64 / seconds;
                (rate * target) as usize
            } else {
                max_paths
            });
        }
        start = end;
    }
    let pixels = sum;
    let inv = 1.0 / spp as f32;
    let alpha = covered.into_iter().map(|k| k as f32 * inv).collect();
    let a = options.aovs;
    let keep = |on: bool| on.then_some(&primary);
    let aovs = Aovs {
        depth: keep(a.depth).map(|p| p.iter().map(|q| q.depth).collect()),
        normal: keep(a.normal).map(|p| p.iter().map(|q| q.normal).collect()),
        albedo: keep(a.albedo).map(|p| p.iter().map(|q| q.albedo).collect()),
        prim: keep(a.prim).map(|p| p.iter().map(|q| q.prim).collect()),
    };
    Ok((
        Image {
            width: w,
            height: h,
            pixels,
            alpha,
            aovs,
        },
        stats,
    ))
}

/// Where one wave accumulates: its pixels' slices of the frame's buffers.
struct WaveOut<'a> {
    /// Sums of the samples' radiance.
    radiance: &'a mut [[f32; 3]],
    /// Samples whose camera ray hit.
    covered: &'a mut [u32],
    /// The primary hits, on sample 0 when AOVs are asked for.
    primary: Option<&'a mut [Primary]>,
}

/// Buffers that every wave of a frame reuses. A wave's paths, rays, hits and shading
/// results are tens of MiB; allocated afresh for each wave and bounce, each of them is
/// page-faulted in and cleared by the kernel again (a sixth of a path frame's time, by
/// `perf`), so they live here across the frame and only grow.
#[derive(Default)]
struct Scratch {
    /// The wave's pixels (from its first) whose camera rays are traced, in order.
    pixels: Vec<u32>,
    paths: Paths,
    steps: Vec<Step>,
    trace: TraceBufs,
    shadows: Shadows,
}

/// A wave's live paths as three lists in step: each path's state, the ray it follows and
/// what that ray hit. The rays and hits are the very buffers the intersector reads and
/// writes, so tracing every live path copies nothing in or out (with the rays inside the
/// paths, gathering them and scattering the hits back cost a tenth of a path frame's
/// shading), and the passes that read only hits or rays read 16 or 32 bytes a path.
#[derive(Default)]
struct Paths {
    state: Vec<PathState>,
    rays: Vec<Ray>,
    hits: Vec<Hit>,
}

impl Paths {
    /// Moves path `from` to place `to` (`to <= from`), over a path that ended: the
    /// compaction of a wave's live paths, done in the same pass as the gathering. The hits
    /// stay where they are: the next trace rewrites them all.
    fn move_down(&mut self, from: usize, to: usize) {
        if from != to {
            self.state.swap(to, from);
            self.rays.swap(to, from);
        }
    }

    /// Keeps the first `n` paths.
    fn truncate(&mut self, n: usize) {
        self.state.truncate(n);
        self.rays.truncate(n);
    }

    fn is_empty(&self) -> bool {
        self.state.is_empty()
    }
}

/// One bounce's shadow rays, what each adds when unoccluded, and its pixel in the wave.
#[derive(Default)]
struct Shadows {
    rays: Vec<Ray>,
    gain: Vec<Vec3>,
    pixel: Vec<usize>,
}

/// The rays, hits and indices of one batch sent to the intersector.
#[derive(Default)]
struct TraceBufs {
    rays: Vec<Ray>,
    hits: Vec<Hit>,
    idx: Vec<usize>,
    occluded: Vec<u8>,
}

/// What every wave of a frame reads.
#[derive(Clone, Copy)]
struct Frame<'a> {
    triangles: &'a [Triangle],
    accel: &'a dyn Intersector,
    camera: &'a ViewCamera,
    options: &'a RenderOptions,
    scene_diagonal: f32,
    /// The pixels whose camera rays may hit a triangle ([`ViewCamera::pixel_rect`]).
    visible: PixelRect,
    surfaces: &'a Surfaces,
    lights: &'a LightSampler,
}

impl Frame<'_> {
    /// Closest hits of `rays`, counted in `stats`.
    fn trace(&self, rays: &[Ray], hits: &mut [Hit], stats: &mut RenderStats) {
        let t0 = std::time::Instant::now();
        self.accel.trace(rays, Query::Closest, hits);
        stats.trace_seconds += t0.elapsed().as_secs_f64();
        stats.rays += rays.len() as u64;
    }
}

/// Seed key of the per-pixel shift of the sample pattern, kept apart from the samples'
/// own streams (which key on the sample number in bits 40 and up).
const SHIFT_KEY: u64 = 0x5eed_0f5a_a71e_d5e7;

/// Surfaces passed through by one ray before the next one found stops it, at most; past
/// that the last one found does (a bound on the work, far beyond any real foliage).
const MAX_LAYERS: u32 = 64;

/// Where sample `s` of `spp` of pixel `p` lies in its pixel, in [0, 1)²: point `s` of the
/// `spp`-point Hammersley set (`s / spp`, base-2 radical inverse of `s`), shifted toroidally
/// by a random offset of the pixel (Cranley–Patterson rotation). The shift makes every
/// sample uniform in the pixel, so the box filter is unbiased, and the set spreads a
/// pixel's samples evenly (stratified in x, a (0, m, 2)-net when `spp` is a power of 2).
/// It depends only on the seed, pixel and sample, never on how waves split the work.
pub fn pixel_sample(seed: u64, p: usize, s: u32, spp: u32) -> (f64, f64) {
    let mut shift = Pcg32::new(seed ^ SHIFT_KEY, p as u64);
    let (dx, dy) = (shift.next_f32() as f64, shift.next_f32() as f64);
    let x = s as f64 / spp.max(1) as f64;
    let y = s.reverse_bits() as f64 * (1.0 / 4_294_967_296.0);
    (wrap_unit(x + dx), wrap_unit(y + dy))
}

/// `v.fract()` for `v` in [0, 2), which the shift's sums are: the same value (`v − 1` is
/// exact there), without the call to `trunc` that `fract` compiles to on x86-64's
/// baseline (no SSE4.1 rounding), a measurable part of a path render's camera rays.
#[inline]
fn wrap_unit(v: f64) -> f64 {
    debug_assert!((0.0..2.0).contains(&v));
    if v >= 1.0 {
        v - 1.0
    } else {
        v
    }
}

/// One wave: `samples` (a run of at most [`SAMPLES_AT_ONCE`]) of pixels `start..end`,
/// accumulated into `wave`.
fn render_wave(
    frame: Frame<'_>,
    (start, end, samples): (usize, usize, std::ops::Range<u32>),
    wave: &mut WaveOut<'_>,
    scratch: &mut Scratch,
    stats: &mut RenderStats,
) {
    let Frame {
        triangles,
        camera,
        options,
        scene_diagonal,
        visible,
        surfaces,
        ..
    } = frame;
    let (w, h) = (options.width as usize, options.height as usize);
    let spp = options.spp.max(1);
    let Scratch {
        pixels,
        paths,
        steps,
        trace,
        shadows,
    } = scratch;
    // Only the pixels whose camera rays can reach the scene get rays and paths; the others
    // already hold every sample's miss ([`fill_misses`]).
    let run = samples.len();
    pixels.clear();
    for y in start / w..=(end - 1) / w {
        let row = (y * w).max(start)..((y + 1) * w).min(end);
        let cols = visible.columns(y as u32);
        let lit = (y * w + cols.start).max(row.start)..(y * w + cols.end).min(row.end);
        pixels.extend(lit.map(|p| (p - start) as u32));
    }
    // Path `j` is sample `samples.start + j % run` of pixel `pixels[j / run]`: a pixel's
    // samples side by side.
    let lane = |j: usize| (pixels[j / run] as usize, samples.start + (j % run) as u32);
    // The camera rays first, straight into the paths' ray list, a group of paths at a time
    // (the last group padded with its last path), then the paths. Every ray is written, so
    // the list keeps the last wave's rays rather than being cleared and filled again, one
    // thread writing a megabyte a wave.
    paths.rays.resize(pixels.len() * run, Ray::EMPTY);
    paths
        .rays
        .par_chunks_mut(RAYS_AT_ONCE)
        .enumerate()
        .for_each(|(k, group)| {
            let first = k * RAYS_AT_ONCE;
            let mut lanes = [(0usize, 0u32); RAYS_AT_ONCE];
            for (i, slot) in lanes.iter_mut().enumerate() {
                let j = (first + i).min(first + group.len() - 1);
                let (i, s) = lane(j);
                *slot = (start + i, s);
            }
            camera_rays(camera, options, &lanes, group)
        });
    // Each sample's cone covers its share of the pixel: the box filter averages the
    // pixel's samples (pbrt-v4's scale of ray differentials, 1/√spp and at most 8×).
    let (width, spread) = camera.pixel_cone(h as u32);
    let share = (1.0 / (spp as f32).sqrt()).max(0.125);
    let cone = Cone {
        width: width * share,
        spread: spread * share,
    };
    paths.state.clear();
    paths
        .state
        .par_extend(paths.rays.par_iter().enumerate().map(|(j, ray)| {
            let (i, s) = lane(j);
            let rng = Pcg32::new(options.seed ^ ((s as u64) << 40), (start + i) as u64);
            PathState::new(i, ray, rng, cone)
        }));
    trace_closest(frame, paths, trace, stats);
    // A pixel's camera rays are `run` side by side: read its hits beside the pixel list,
    // not each path's (much larger) state.
    for (&pixel, hits) in pixels.iter().zip(paths.hits.chunks(run)) {
        wave.covered[pixel as usize] += hits.iter().filter(|h| h.is_hit()).count() as u32;
    }
    if let Some(primary) = wave.primary.as_deref_mut() {
        // Sample 0 of each pixel: the first of its run.
        let lanes = paths.state.par_iter().zip(&paths.rays[..]);
        let found: Vec<Primary> = lanes
            .zip(&paths.hits[..])
            .step_by(run)
            .map(|((p, ray), hit)| {
                if hit.is_hit() {
                    let tri = &triangles[hit.prim as usize];
                    let width = p.cone.width_at(p.travelled + hit.t);
                    let sp = surfaces.at(tri, hit, Vec3::from(ray.dir), width);
                    Primary {
                        depth: p.travelled + hit.t,
                        normal: sp.ns.to_array(),
                        albedo: sp.bsdf.base.to_array(),
                        prim: hit.prim,
                    }
                } else {
                    Primary::MISS
                }
            })
            .collect();
        for (&pixel, q) in pixels.iter().zip(found) {
            primary[pixel as usize] = q;
        }
    }
    let out = &mut *wave.radiance;
    let weight = sample_weight(options);
    match options.integrator {
        Integrator::Primary | Integrator::Normals => {
            let lanes = paths.rays.par_iter().zip(&paths.hits[..]);
            let shown: Vec<[f32; 3]> = lanes
                .map(|(r, hit)| {
                    if hit.is_hit() {
                        let nrm = facing_normal(&triangles[hit.prim as usize], r.dir);
                        if options.integrator == Integrator::Primary {
                            let k = 0.1 + 0.9 * -dot(nrm, normalize(r.dir));
                            [k, k, k]
                        } else {
                            nrm.map(|x| 0.5 * x + 0.5)
                        }
                    } else {
                        BACKGROUND
                    }
                })
                .collect();
            for (p, c) in paths.state.iter().zip(shown) {
                add(&mut out[p.pixel], c, weight);
            }
        }
        Integrator::Ao => {
            let dist = scene_diagonal / 8.0;
            let mut idx = Vec::new();
            let mut ao_rays = Vec::new();
            let lanes = paths.state.iter_mut().zip(&paths.rays).zip(&paths.hits);
            for ((p, r), hit) in lanes {
                if hit.is_hit() {
                    let tri = &triangles[hit.prim as usize];
                    let nrm = facing_normal(tri, r.dir);
                    let d = cosine_hemisphere(nrm, p.rng.next_f32(), p.rng.next_f32());
                    ao_rays.push(Ray {
                        org: offset_ray(surface_point(tri, hit.u, hit.v), nrm, tri),
                        tmin: 0.0,
                        dir: d,
                        tmax: dist,
                    });
                    idx.push(p.pixel);
                } else {
                    add(&mut out[p.pixel], BACKGROUND, weight);
                }
            }
            let mut open = vec![Vec3::ONE; ao_rays.len()];
            trace_shadows(frame, &mut ao_rays, &mut open, trace, stats);
            for (&i, k) in idx.iter().zip(&open) {
                add(&mut out[i], k.to_array(), weight);
            }
        }
        Integrator::Path => trace_paths(frame, paths, out, steps, trace, shadows, stats),
    }
}

/// The camera rays of `lanes` (pixel, sample), at most `RAYS_AT_ONCE`, into `group`. Out
/// of line, so that how the camera's f64 stages compile does not depend on what the
/// pool's loop inlines around them.
#[inline(never)]
fn camera_rays(
    camera: &ViewCamera,
    options: &RenderOptions,
    lanes: &[(usize, u32); RAYS_AT_ONCE],
    group: &mut [Ray],
) {
    let (w, h) = (options.width, options.height);
    let spp = options.spp.max(1);
    let (mut x, mut y) = ([0.0; RAYS_AT_ONCE], [0.0; RAYS_AT_ONCE]);
    for (i, &(p, s)) in lanes.iter().enumerate() {
        let (jx, jy) = pixel_sample(options.seed, p, s, spp);
        x[i] = (p % w as usize) as f64 + jx;
        y[i] = (p / w as usize) as f64 + jy;
    }
    let rays = camera.rays(&x, &y, w, h);
    group.copy_from_slice(&rays[..group.len()]);
}

/// A live path (its ray and hit are in [`Paths`]' lists beside it): its pixel in the wave,
/// what it carries, its pixel's random stream, and what multiple importance sampling needs of
/// the vertex it last scattered at.
struct PathState {
    pixel: usize,
    throughput: Vec3,
    rng: Pcg32,
    /// Distance from the segment's start to `ray`'s origin: surfaces passed through since
    /// the last scattering (or the camera).
    travelled: f32,
    /// The last scattering vertex.
    prev_pos: Vec3,
    /// Its shading normal.
    prev_ns: Vec3,
    /// The BRDF-sampling density of the segment's direction there; 0 for camera rays,
    /// whose emitter hits take no MIS weight.
    prev_pdf: f32,
    /// Whether `hit` still awaits its presence test (alpha).
    pending: bool,
    /// The ray cone of the segment, from its start.
    cone: Cone,
}

impl PathState {
    fn new(pixel: usize, ray: &Ray, rng: Pcg32, cone: Cone) -> PathState {
        PathState {
            pixel,
            throughput: Vec3::ONE,
            rng,
            travelled: 0.0,
            prev_pos: Vec3::from(ray.org),
            prev_ns: Vec3::ZERO,
            prev_pdf: 0.0,
            pending: false,
            cone,
        }
    }
}

/// A ray cone (*Ray Tracing Gems* ch. 20): how wide a path's ray is where it starts and
/// how fast it widens, so that a texture lookup can filter over what the ray stands for
/// ([`mipmap`]).
#[derive(Clone, Copy, Debug)]
struct Cone {
    /// Width at the segment's start.
    width: f32,
    /// Spread angle, radians.
    spread: f32,
}

impl Cone {
    /// Width `distance` along the segment.
    fn width_at(self, distance: f32) -> f32 {
        self.width + self.spread * distance
    }

    /// The cone of a ray scattered where this one is `width` wide into a direction of
    /// density `pdf`: the lobe widens it by about the angle that a solid angle of `1/pdf`
    /// subtends (a diffuse bounce by more than a radian, a mirror-like one by little).
    fn scattered(self, width: f32, pdf: f32) -> Cone {
        Cone {
            width,
            spread: self.spread + pdf.sqrt().recip(),
        }
    }
}

/// The continuation of `ray` past the surface of `hit`: from just behind it (offset along
/// the geometric normal, as every secondary ray), with what is left of its length.
fn beyond(triangles: &[Triangle], ray: &Ray, hit: &Hit) -> Ray {
    let tri = &triangles[hit.prim as usize];
    let n = facing_normal(tri, ray.dir);
    Ray {
        org: offset_ray(surface_point(tri, hit.u, hit.v), [-n[0], -n[1], -n[2]], tri),
        tmin: 0.0,
        dir: ray.dir,
        tmax: (ray.tmax - hit.t).max(0.0),
    }
}

/// Traces every path's ray to the first surface that is there: closest hits as one
/// batch, then, where the scene has `MASK` or `BLEND` materials, the rays whose hit is cut
/// away (or passed by the stochastic `BLEND` test, with probability 1 − alpha from the
/// path's own stream) continue behind it in another batch, until none is left. The cores
/// know nothing of materials; only the waves do.
fn trace_closest(
    frame: Frame<'_>,
    paths: &mut Paths,
    bufs: &mut TraceBufs,
    stats: &mut RenderStats,
) {
    // The intersector writes every hit: the list keeps what it held rather than being
    // filled again on one thread.
    paths.hits.resize(paths.rays.len(), Hit::MISS);
    frame.trace(&paths.rays, &mut paths.hits, stats);
    if !frame.surfaces.has_alpha() {
        return;
    }
    let Paths { state, rays, hits } = paths;
    state.par_iter_mut().zip(&hits[..]).for_each(|(p, h)| {
        p.pending = h.is_hit();
    });
    let TraceBufs {
        rays: batch,
        hits: found,
        idx,
        ..
    } = bufs;
    for _ in 0..MAX_LAYERS {
        let lanes = state.par_iter_mut().zip(&mut rays[..]).zip(&hits[..]);
        lanes
            .filter(|((p, _), _)| p.pending)
            .for_each(|((p, ray), hit)| {
                let passes = match frame.surfaces.presence(hit) {
                    Presence::Opaque => false,
                    Presence::Cut => true,
                    Presence::Blend(alpha) => p.rng.next_f32() >= alpha,
                };
                if passes {
                    p.travelled += hit.t;
                    *ray = beyond(frame.triangles, ray, hit);
                } else {
                    p.pending = false;
                }
            });
        batch.clear();
        idx.clear();
        for (i, _) in state.iter().enumerate().filter(|(_, p)| p.pending) {
            batch.push(rays[i]);
            idx.push(i);
        }
        if batch.is_empty() {
            return;
        }
        found.clear();
        found.resize(batch.len(), Hit::MISS);
        frame.trace(batch, found, stats);
        for (&i, h) in idx.iter().zip(found.iter()) {
            hits[i] = *h;
            state[i].pending = h.is_hit();
        }
    }
    for p in state.iter_mut() {
        p.pending = false;
    }
}

/// Traces shadow rays and scales each `gain` by what reaches its end: 0 where an opaque
/// surface blocks it. Without `MASK` or `BLEND` materials that is one `occluded` batch.
/// With them, closest hits in batches, as [`trace_closest`] does, but deterministic: a cut
/// surface lets the ray on, a `BLEND` one multiplies the gain by 1 − alpha (the expected
/// value of the stochastic test, without its noise), and an opaque one stops it.
fn trace_shadows(
    frame: Frame<'_>,
    rays: &mut [Ray],
    gains: &mut [Vec3],
    bufs: &mut TraceBufs,
    stats: &mut RenderStats,
) {
    if rays.is_empty() {
        return;
    }
    if !frame.surfaces.has_alpha() {
        let occluded = &mut bufs.occluded;
        occluded.clear();
        occluded.resize(rays.len(), 0);
        let t0 = std::time::Instant::now();
        frame.accel.occluded(rays, occluded);
        stats.trace_seconds += t0.elapsed().as_secs_f64();
        stats.rays += rays.len() as u64;
        gains.par_iter_mut().zip(&occluded[..]).for_each(|(g, &o)| {
            if o != 0 {
                *g = Vec3::ZERO;
            }
        });
        return;
    }
    let mut active: Vec<usize> = (0..rays.len()).collect();
    let mut batch = Vec::with_capacity(rays.len());
    for _ in 0..MAX_LAYERS {
        batch.clear();
        batch.extend(active.iter().map(|&i| rays[i]));
        let mut hits = vec![Hit::MISS; batch.len()];
        frame.trace(&batch, &mut hits, stats);
        let passed: Vec<Option<f32>> = hits
            .par_iter()
            .map(|h| {
                if !h.is_hit() {
                    return None;
                }
                match frame.surfaces.presence(h) {
                    Presence::Opaque => Some(0.0),
                    Presence::Cut => Some(1.0),
                    Presence::Blend(alpha) => Some(1.0 - alpha),
                }
            })
            .collect();
        let mut next = Vec::new();
        for ((&i, h), pass) in active.iter().zip(&hits).zip(passed) {
            match pass {
                None => {}
                Some(k) if k <= 0.0 => gains[i] = Vec3::ZERO,
                Some(k) => {
                    gains[i] *= k;
                    rays[i] = beyond(frame.triangles, &rays[i], h);
                    next.push(i);
                }
            }
        }
        if next.is_empty() {
            return;
        }
        active = next;
    }
    for i in active {
        gains[i] = Vec3::ZERO;
    }
}

/// What shading one path vertex gives besides the continuation, which it writes into the
/// path itself: radiance to add now, and a shadow ray towards a light with what it adds
/// when unoccluded. Kept small (64 bytes): every vertex of a wave writes one and the
/// gathering after the shading reads them all.
#[derive(Default)]
struct Step {
    emitted: Vec3,
    shadow: Option<(Ray, Vec3)>,
    /// Whether the path scattered into a continuing ray (its new state is in the path).
    continues: bool,
}

const _: () = assert!(
    std::mem::size_of::<Step>() <= 64,
    "a Step fits a cache line"
);

/// The `path` integrator over one wave, in batches: every live path is shaded in parallel
/// (each owns its random stream, so the thread count changes nothing), then all shadow rays
/// are traced as one batch and all continuing rays as another. Light reaches a path in
/// two ways, weighted against each other by multiple importance sampling: as emission its
/// BRDF-sampled rays hit (emissive surfaces, the sky on a miss), and, at each scattering,
/// by next-event estimation towards one light that [`LightSampler`] picks (a punctual
/// light, a point on an emissive triangle or a sky direction).
fn trace_paths(
    frame: Frame<'_>,
    live: &mut Paths,
    out: &mut [[f32; 3]],
    steps: &mut Vec<Step>,
    bufs: &mut TraceBufs,
    shadows: &mut Shadows,
    stats: &mut RenderStats,
) {
    let options = frame.options;
    let weight = sample_weight(options);
    let sky = Vec3::from(options.sky);
    for bounce in 0..=options.bounces {
        // A vertex reached after `bounce` scatterings may scatter once more.
        let scatter = bounce < options.bounces;
        // Every step is written: the list only grows, and keeps the last wave's steps
        // rather than being cleared and filled again on one thread.
        let n = live.state.len();
        if steps.len() < n {
            steps.resize_with(n, Step::default);
        }
        let steps = &mut steps[..n];
        steps
            .par_chunks_mut(SHADE_CHUNK)
            .zip(live.state.par_chunks_mut(SHADE_CHUNK))
            .zip(live.rays.par_chunks_mut(SHADE_CHUNK))
            .zip(live.hits.par_chunks(SHADE_CHUNK))
            .for_each(|(((steps, state), rays), hits)| {
                shade_run(frame, steps, state, rays, hits, (bounce, scatter, sky))
            });
        shadows.rays.clear();
        shadows.gain.clear();
        shadows.pixel.clear();
        // One pass over the shaded vertices, in path order: emitted light to the pixels
        // (every path of a wave is a distinct pixel, so the order of these adds is fixed),
        // shadow rays to their list, and the paths that go on (they became their
        // continuations while shaded) moved down over the ended ones.
        let mut kept = 0;
        for (i, step) in steps.iter().enumerate() {
            let pixel = live.state[i].pixel;
            if step.emitted != Vec3::ZERO {
                add(&mut out[pixel], step.emitted.to_array(), weight);
            }
            if let Some((ray, gain)) = step.shadow {
                shadows.rays.push(ray);
                shadows.gain.push(gain);
                shadows.pixel.push(pixel);
            }
            if step.continues {
                live.move_down(i, kept);
                kept += 1;
            }
        }
        live.truncate(kept);
        trace_shadows(frame, &mut shadows.rays, &mut shadows.gain, bufs, stats);
        for (&pixel, gain) in shadows.pixel.iter().zip(shadows.gain.iter()) {
            if gain.max_element() > 0.0 {
                add(&mut out[pixel], gain.to_array(), weight);
            }
        }
        if live.is_empty() {
            break;
        }
        trace_closest(frame, live, bufs, stats);
    }
}

/// Paths a shading task takes at once: the run [`shade_run`] prefetches along.
const SHADE_CHUNK: usize = 256;

/// How many vertices ahead of the one it shades [`shade_run`] locates a hit and
/// prefetches its texels: enough for a miss to arrive (about 100 ns, half a vertex's
/// shading) without crowding the cache's fill buffers (up to eight lines a vertex).
const SHADE_AHEAD: usize = 4;

/// Shades a run of path vertices ([`shade_vertex`] each, in order), each hit located and
/// its texels prefetched [`SHADE_AHEAD`] vertices before it is shaded.
fn shade_run(
    frame: Frame<'_>,
    steps: &mut [Step],
    state: &mut [PathState],
    rays: &mut [Ray],
    hits: &[Hit],
    (bounce, scatter, sky): (u32, bool, Vec3),
) {
    // A vertex after a scattering reads emission at level 0 (`Surfaces::locate`).
    let scattered = bounce > 0;
    let locate = |p: &PathState, ray: &Ray, hit: &Hit| {
        hit.is_hit().then(|| {
            let tri = &frame.triangles[hit.prim as usize];
            let width = p.cone.width_at(p.travelled + hit.t);
            let l = frame
                .surfaces
                .locate(tri, hit, Vec3::from(ray.dir), width, scattered);
            frame.surfaces.prefetch(&l);
            l
        })
    };
    let n = steps.len();
    if scattered && !scatter {
        // A path's last vertex after a scattering only adds what it emits.
        for i in 0..n {
            steps[i] = last_vertex(frame, &state[i], &rays[i], &hits[i], sky);
        }
        return;
    }
    let mut ahead: [Option<Located>; SHADE_AHEAD] = [None; SHADE_AHEAD];
    for (i, slot) in ahead.iter_mut().enumerate().take(n) {
        *slot = locate(&state[i], &rays[i], &hits[i]);
    }
    for i in 0..n {
        let here = ahead[i % SHADE_AHEAD].take();
        let next = i + SHADE_AHEAD;
        if next < n {
            ahead[next % SHADE_AHEAD] = locate(&state[next], &rays[next], &hits[next]);
        }
        let (p, ray, hit) = (&mut state[i], &mut rays[i], &hits[i]);
        steps[i] = shade_vertex(frame, p, ray, hit, here, bounce, scatter, sky);
    }
}

/// Shades the vertex path `p` reached after `bounce` scatterings: its `ray` found `hit`,
/// `located` on its surface ([`Surfaces::locate`]; `None` for a miss). A path that scatters
/// on becomes its continuation in place (`p` and `ray`).
#[allow(clippy::too_many_arguments)]
#[inline(always)]
fn shade_vertex(
    frame: Frame<'_>,
    p: &mut PathState,
    ray: &mut Ray,
    hit: &Hit,
    located: Option<Located>,
    bounce: u32,
    scatter: bool,
    sky: Vec3,
) -> Step {
    let thr = p.throughput;
    let dir = Vec3::from(ray.dir);
    let lights = frame.lights;
    let Some(located) = located else {
        return Step {
            emitted: sky_seen(frame, p, dir, sky),
            ..Step::default()
        };
    };
    let tri = &frame.triangles[hit.prim as usize];
    let width = p.cone.width_at(p.travelled + hit.t);
    let sp = frame.surfaces.finish(tri, &located);
    let pos = Vec3::from(surface_point(tri, hit.u, hit.v));
    let mut step = Step {
        emitted: emission_seen(frame, p, hit, pos, sp.emission, sp.ng.dot(dir).abs()),
        ..Step::default()
    };
    if !scatter {
        return step;
    }
    let (t, b) = basis(sp.ns.to_array());
    let (t, b, n) = (Vec3::from(t), Vec3::from(b), sp.ns);
    let local = |v: Vec3| Vec3::new(v.dot(t), v.dot(b), v.dot(n));
    let wo = local(-dir);
    let org = offset_ray(pos.to_array(), sp.ng.to_array(), tri);
    if !lights.is_empty() {
        let u = [
            p.rng.next_f32(),
            p.rng.next_f32(),
            p.rng.next_f32(),
            p.rng.next_f32(),
        ];
        // (direction, distance, radiance or irradiance over the pick's density, and the
        // light density for MIS: infinite for delta lights, which BRDF sampling misses).
        let sample = match lights.pick(frame.triangles, u) {
            Some(LightPick::Punctual { index, prob }) => frame.surfaces.lights[index]
                .incident(pos)
                .map(|inc| (inc.wi, inc.distance, inc.irradiance / prob, f32::INFINITY)),
            Some(LightPick::Triangle {
                prim,
                b,
                normal,
                point,
                pdf_area,
            }) => {
                // Aim at a point just off the emitter on the vertex's side, so the shadow
                // ray does not hit the emitter itself.
                let side = if normal.dot(pos - point) < 0.0 {
                    -normal
                } else {
                    normal
                };
                let emitter = &frame.triangles[prim as usize];
                let target = Vec3::from(offset_ray(point.to_array(), side.to_array(), emitter));
                let d = target - Vec3::from(org);
                let dist = d.length();
                let wi = d / dist;
                let cos_light = normal.dot(wi).abs();
                let pdf = pdf_area * dist * dist / cos_light;
                // Only a point the vertex can receive from is read (its texel is often a
                // cache miss).
                let seen = dist > 0.0 && pdf > 0.0 && pdf.is_finite() && wi.dot(sp.ng) > 0.0;
                seen.then(|| {
                    (
                        wi,
                        dist,
                        frame.surfaces.emission_at(prim as usize, b) / pdf,
                        pdf,
                    )
                })
                .filter(|&(_, _, li, _)| li != Vec3::ZERO)
            }
            Some(LightPick::Sky) => {
                let wi = Vec3::from(cosine_hemisphere(sp.ns.to_array(), u[1], u[2]));
                let pdf = lights.sky_pdf(sp.ns, wi);
                (pdf > 0.0).then(|| (wi, f32::INFINITY, sky / pdf, pdf))
            }
            None => None,
        };
        if let Some((wi_world, distance, li, light_pdf)) = sample {
            if wi_world.dot(sp.ng) > 0.0 {
                let wi = local(wi_world);
                let (f, pdf) = sp.bsdf.eval_pdf(wo, wi);
                let weight = if light_pdf.is_infinite() {
                    1.0
                } else {
                    power_heuristic(light_pdf, pdf)
                };
                let gain = thr * f * wi.z.max(0.0) * li * weight;
                if gain.max_element() > 0.0 && gain.is_finite() {
                    step.shadow = Some((
                        Ray {
                            org,
                            tmin: 0.0,
                            dir: wi_world.to_array(),
                            tmax: distance,
                        },
                        gain,
                    ));
                }
            }
        }
    }
    let u = [p.rng.next_f32(), p.rng.next_f32(), p.rng.next_f32()];
    if let Some(s) = sp.bsdf.sample(wo, u) {
        let wi = (t * s.wi.x + b * s.wi.y + n * s.wi.z).normalize_or_zero();
        let mut throughput = thr * s.weight;
        // Russian roulette from the `roulette`-th scattering on: a path continues with
        // probability min(0.95, its largest throughput component), and its weight is
        // divided by that, which keeps the estimate unbiased.
        let survives = match frame.options.roulette {
            Some(start) if bounce + 1 >= start => {
                let q = throughput.max_element().min(0.95);
                if q > 0.0 && p.rng.next_f32() < q {
                    throughput /= q;
                    true
                } else {
                    false
                }
            }
            _ => true,
        };
        // A direction under the geometric surface would leak through it.
        if survives && wi.dot(sp.ng) > 0.0 {
            // The path becomes its continuation in place (its pixel stays).
            *ray = Ray {
                org,
                tmin: 0.0,
                dir: wi.to_array(),
                tmax: f32::INFINITY,
            };
            p.throughput = throughput;
            p.cone = p.cone.scattered(width, s.pdf);
            p.travelled = 0.0;
            p.prev_pos = pos;
            p.prev_ns = sp.ns;
            p.prev_pdf = s.pdf;
            step.continues = true;
        }
    }
    step
}

/// What path `p`'s last vertex adds after a scattering, which is all that shading it
/// gives: its ray's `hit` emission, or the sky `sky` on a miss. The same values
/// [`shade_vertex`] finds (emission after a scattering is read at level 0), without the
/// surface point's other textures, normal and BRDF, which no one would read: with two
/// bounces a third of a path frame's vertices are last ones.
#[inline(always)]
fn last_vertex(frame: Frame<'_>, p: &PathState, ray: &Ray, hit: &Hit, sky: Vec3) -> Step {
    let dir = Vec3::from(ray.dir);
    let emitted = if hit.is_hit() {
        let tri = &frame.triangles[hit.prim as usize];
        let b = [1.0 - hit.u - hit.v, hit.u, hit.v];
        let emission = frame
            .surfaces
            .emission_after_scattering(hit.prim as usize, b);
        if emission == Vec3::ZERO {
            Vec3::ZERO
        } else {
            let pos = Vec3::from(surface_point(tri, hit.u, hit.v));
            let face = Vec3::from(tri.normal()).normalize_or_zero();
            emission_seen(frame, p, hit, pos, emission, face.dot(dir).abs())
        }
    } else {
        sky_seen(frame, p, dir, sky)
    };
    Step {
        emitted,
        ..Step::default()
    }
}

/// What the sky adds to path `p` whose ray of direction `dir` missed: weighted against
/// the chance that light sampling at its last scattering found the direction.
#[inline(always)]
fn sky_seen(frame: Frame<'_>, p: &PathState, dir: Vec3, sky: Vec3) -> Vec3 {
    let w = if p.prev_pdf > 0.0 {
        power_heuristic(p.prev_pdf, frame.lights.sky_pdf(p.prev_ns, dir))
    } else {
        1.0
    };
    p.throughput * sky * w
}

/// What a hit surface emitting `emission` at `pos` adds to path `p`, its ray meeting the
/// surface at cosine `cos` to the geometric normal: weighted against the chance that
/// light sampling at the path's last scattering picked the point.
#[inline(always)]
fn emission_seen(
    frame: Frame<'_>,
    p: &PathState,
    hit: &Hit,
    pos: Vec3,
    emission: Vec3,
    cos: f32,
) -> Vec3 {
    let mut emitted = p.throughput * emission;
    if p.prev_pdf > 0.0 && emitted != Vec3::ZERO {
        let dist = (pos - p.prev_pos).length();
        let light_pdf = frame.lights.triangle_pdf(hit.prim, dist, cos);
        emitted *= power_heuristic(p.prev_pdf, light_pdf);
    }
    emitted
}

/// Gives each pixel outside `visible` the sum of `spp` camera rays that miss: the sky for
/// `path`, the background otherwise, added one sample at a time as a traced miss adds it, so
/// the image is bit for bit the one that tracing them would give. Done once, in parallel,
/// instead of in every wave.
fn fill_misses(sum: &mut [[f32; 3]], visible: PixelRect, w: usize, options: &RenderOptions) {
    let miss = match options.integrator {
        Integrator::Path => options.sky,
        _ => BACKGROUND,
    };
    let mut total = [0.0f32; 3];
    for _ in 0..options.spp.max(1) {
        add(&mut total, miss, sample_weight(options));
    }
    if total == [0.0; 3] || w == 0 {
        return;
    }
    sum.par_chunks_mut(w).enumerate().for_each(|(y, row)| {
        let cols = visible.columns(y as u32);
        row[..cols.start].fill(total);
        row[cols.end..].fill(total);
    });
}

#[inline]
fn add(o: &mut [f32; 3], c: [f32; 3], k: f32) {
    for j in 0..3 {
        o[j] += c[j] * k;
    }
}

/// What one sample adds to its pixel's mean, per unit of its radiance: 1 / spp.
#[inline]
fn sample_weight(options: &RenderOptions) -> f32 {
    1.0 / options.spp.max(1) as f32
}
