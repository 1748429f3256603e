//! Rendering: synchronous and format-free. It makes batches of rays, traces them with any
//! [`Intersector`] and shades the hits; `image` turns the result into PNG or OpenEXR bytes.
//!
//! Work goes in waves (all primary rays of a block of pixels, then all their secondary
//! rays), never ray by ray, because the batch cores (DACRT) only exist in that form and the
//! others lose nothing by it.

pub mod brdf;
pub mod camera;
pub mod image;
pub mod rng;
pub mod sampling;
pub mod surface;
pub mod texture;

use crate::accel::{Intersector, Query};
use crate::geometry::{dot, Hit, Ray, Triangle};
use camera::ViewCamera;
use glam::Vec3;
use rayon::prelude::*;
use rng::Pcg32;
use sampling::{basis, cosine_hemisphere, normalize};
use surface::{offset_ray, Surfaces};

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
    /// Samples per pixel (jittered within the pixel).
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

/// Pixels per wave: bounds the memory of one wave's rays and hits (about 12 MiB).
const WAVE_PIXELS: usize = 1 << 18;

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

/// How a caller drives a render's waves: each wave (a block of pixels for one sample,
/// with all its bounces) runs through [`Waves::run_wave`], where the caller may hold the
/// thread pool under a scheduler's lease, notice cancellation and report progress. Waves
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

/// Pixels of the first wave when waves are sized in seconds, before a rate is known.
const FIRST_WAVE_PIXELS: usize = 1 << 13;
/// The smallest wave.
const MIN_WAVE_PIXELS: usize = 1 << 10;

/// Renders `triangles` (the ones `accel` was built over) through `camera`, in waves driven
/// by `waves`. `scene_diagonal` sets the ambient-occlusion distance. `surfaces` holds the
/// materials and lights that `path` and the `albedo` and `normal` AOVs use; without it every
/// triangle has glTF's default material, face normals and no light but the sky.
pub fn render<W: Waves + ?Sized>(
    triangles: &[Triangle],
    accel: &dyn Intersector,
    camera: &ViewCamera,
    options: &RenderOptions,
    scene_diagonal: f32,
    surfaces: Option<&Surfaces>,
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
    let (w, h) = (options.width, options.height);
    let n = w as usize * h as usize;
    let spp = options.spp.max(1);
    let mut sum = vec![[0.0f32; 3]; n];
    let mut covered = vec![0u32; n];
    let mut primary = if options.aovs.is_empty() {
        Vec::new()
    } else {
        vec![Primary::MISS; n]
    };
    let mut stats = RenderStats::default();
    let total = n as f64 * spp as f64;
    let mut done = 0.0;
    let mut wave_pixels = if waves.wave_seconds().is_finite() {
        FIRST_WAVE_PIXELS
    } else {
        WAVE_PIXELS
    };
    let mut start = 0;
    while start < n {
        let end = (start + wave_pixels).min(n);
        let mut seconds = 0.0;
        for s in 0..spp {
            let t0 = std::time::Instant::now();
            let mut out = WaveOut {
                radiance: &mut sum[start..end],
                covered: &mut covered[start..end],
                primary: if s == 0 && !primary.is_empty() {
                    Some(&mut primary[start..end])
                } else {
                    None
                },
            };
            let stats = &mut stats;
            waves.run_wave(&mut || {
                render_wave(
                    Frame {
                        triangles,
                        accel,
                        camera,
                        options,
                        scene_diagonal,
                        surfaces,
                    },
                    (start, end, s),
                    &mut out,
                    stats,
                )
            })?;
            seconds += t0.elapsed().as_secs_f64();
            done += (end - start) as f64;
            waves.progress(done / total);
        }
        // Size the next block's waves from this block's rate.
        let target = waves.wave_seconds();
        wave_pixels = if target.is_finite() && seconds > 0.0 {
            let rate = (end - start) as f64 * spp as f64 / seconds;
            ((rate * target) as usize).clamp(MIN_WAVE_PIXELS, WAVE_PIXELS)
        } else {
            WAVE_PIXELS
        };
        start = end;
    }
    let inv = 1.0 / spp as f32;
    let pixels = sum.into_iter().map(|c| c.map(|x| x * inv)).collect();
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

/// What every wave of a frame reads.
#[derive(Clone, Copy)]
struct Frame<'a> {
    triangles: &'a [Triangle],
    accel: &'a dyn Intersector,
    camera: &'a ViewCamera,
    options: &'a RenderOptions,
    scene_diagonal: f32,
    surfaces: &'a Surfaces,
}

/// One wave: sample `s` of pixels `start..end`, accumulated into `out`.
fn render_wave(
    frame: Frame<'_>,
    (start, end, s): (usize, usize, u32),
    wave: &mut WaveOut<'_>,
    stats: &mut RenderStats,
) {
    let Frame {
        triangles,
        accel,
        camera,
        options,
        scene_diagonal,
        surfaces,
    } = frame;
    let w = options.width;
    let h = options.height;
    let trace = |rays: &[Ray], query: Query, hits: &mut [Hit], stats: &mut RenderStats| {
        let t0 = std::time::Instant::now();
        accel.trace(rays, query, hits);
        stats.trace_seconds += t0.elapsed().as_secs_f64();
        stats.rays += rays.len() as u64;
    };
    let mut rngs: Vec<Pcg32> = (start..end)
        .map(|p| Pcg32::new(options.seed ^ ((s as u64) << 40), p as u64))
        .collect();
    // Box filter: every sample, the first too, lies uniformly inside its pixel.
    let rays: Vec<Ray> = (start..end)
        .zip(&mut rngs)
        .map(|(p, rng)| {
            let (jx, jy) = (rng.next_f32() as f64, rng.next_f32() as f64);
            let (x, y) = ((p % w as usize) as f64, (p / w as usize) as f64);
            camera.ray(x + jx, y + jy, w, h)
        })
        .collect();
    let mut hits = vec![Hit::MISS; rays.len()];
    trace(&rays, Query::Closest, &mut hits, stats);
    for (c, hit) in wave.covered.iter_mut().zip(&hits) {
        *c += hit.is_hit() as u32;
    }
    if let Some(primary) = wave.primary.as_deref_mut() {
        for ((q, r), hit) in primary.iter_mut().zip(&rays).zip(&hits) {
            *q = if hit.is_hit() {
                let sp = surfaces.at(&triangles[hit.prim as usize], hit, Vec3::from(r.dir));
                Primary {
                    depth: hit.t,
                    normal: sp.ns.to_array(),
                    albedo: sp.bsdf.base.to_array(),
                    prim: hit.prim,
                }
            } else {
                Primary::MISS
            };
        }
    }
    let out = &mut *wave.radiance;
    match options.integrator {
        Integrator::Primary | Integrator::Normals => {
            for ((o, r), hit) in out.iter_mut().zip(&rays).zip(&hits) {
                let c = if hit.is_hit() {
                    let nrm = facing_normal(&triangles[hit.prim as usize], r.dir);
                    if options.integrator == Integrator::Primary {
                        let k = 0.1 + 0.9 * -dot(nrm, normalize(r.dir));
                        [k, k, k]
                    } else {
                        nrm.map(|x| 0.5 * x + 0.5)
                    }
                } else {
                    BACKGROUND
                };
                add(o, c, 1.0);
            }
        }
        Integrator::Ao => {
            let dist = scene_diagonal / 8.0;
            let mut idx = Vec::new();
            let mut ao_rays = Vec::new();
            for (i, (r, hit)) in rays.iter().zip(&hits).enumerate() {
                if hit.is_hit() {
                    let nrm = facing_normal(&triangles[hit.prim as usize], r.dir);
                    let rng = &mut rngs[i];
                    let d = cosine_hemisphere(nrm, rng.next_f32(), rng.next_f32());
                    ao_rays.push(Ray {
                        org: offset_ray(r.at(hit.t), nrm),
                        tmin: 0.0,
                        dir: d,
                        tmax: dist,
                    });
                    idx.push(i);
                } else {
                    add(&mut out[i], BACKGROUND, 1.0);
                }
            }
            let mut occ = vec![0u8; ao_rays.len()];
            let t0 = std::time::Instant::now();
            accel.occluded(&ao_rays, &mut occ);
            stats.trace_seconds += t0.elapsed().as_secs_f64();
            stats.rays += ao_rays.len() as u64;
            for (&i, &o) in idx.iter().zip(&occ) {
                let k = if o != 0 { 0.0 } else { 1.0 };
                add(&mut out[i], [k, k, k], 1.0);
            }
        }
        Integrator::Path => {
            let paths = rays
                .into_iter()
                .zip(hits)
                .zip(rngs)
                .enumerate()
                .map(|(i, ((ray, hit), rng))| PathState {
                    pixel: i,
                    ray,
                    hit,
                    throughput: Vec3::ONE,
                    rng,
                })
                .collect();
            trace_paths(frame, paths, out, stats);
        }
    }
}

/// A live path: its pixel in the wave, the ray it last followed and what that hit, what
/// it carries, and its pixel's random stream.
struct PathState {
    pixel: usize,
    ray: Ray,
    hit: Hit,
    throughput: Vec3,
    rng: Pcg32,
}

/// What shading one path vertex gives: radiance to add now, a shadow ray towards a light
/// with what it adds when unoccluded, and the continuing ray with its throughput.
#[derive(Default)]
struct Step {
    emitted: Vec3,
    shadow: Option<(Ray, Vec3)>,
    next: Option<(Ray, Vec3)>,
}

/// The `path` integrator over one wave, in batches: every live path is shaded in parallel
/// (each owns its random stream, so the thread count changes nothing), then all shadow rays
/// are traced as one batch and all continuing rays as another. Light reaches a path as
/// emission it hits (surfaces after any bounce, the sky on a miss) and, at each scattering,
/// by next-event estimation towards one punctual light picked uniformly (a delta light can
/// only be reached that way, so no weighting between the two is needed).
fn trace_paths(
    frame: Frame<'_>,
    mut live: Vec<PathState>,
    out: &mut [[f32; 3]],
    stats: &mut RenderStats,
) {
    let options = frame.options;
    let sky = Vec3::from(options.sky);
    let lights = &frame.surfaces.lights;
    for bounce in 0..=options.bounces {
        // A vertex reached after `bounce` scatterings may scatter once more.
        let scatter = bounce < options.bounces;
        let steps: Vec<Step> = live
            .par_iter_mut()
            .map(|p| shade_vertex(frame, p, scatter, sky, lights))
            .collect();
        let mut shadow_rays = Vec::new();
        let mut shadow_gain = Vec::new();
        let mut next = Vec::with_capacity(live.len());
        for (p, step) in live.into_iter().zip(steps) {
            add(&mut out[p.pixel], step.emitted.to_array(), 1.0);
            if let Some((ray, gain)) = step.shadow {
                shadow_rays.push(ray);
                shadow_gain.push((p.pixel, gain));
            }
            if let Some((ray, throughput)) = step.next {
                next.push(PathState {
                    ray,
                    throughput,
                    hit: Hit::MISS,
                    ..p
                });
            }
        }
        if !shadow_rays.is_empty() {
            let mut occluded = vec![0u8; shadow_rays.len()];
            let t0 = std::time::Instant::now();
            frame.accel.occluded(&shadow_rays, &mut occluded);
            stats.trace_seconds += t0.elapsed().as_secs_f64();
            stats.rays += shadow_rays.len() as u64;
            for (&(pixel, gain), &o) in shadow_gain.iter().zip(&occluded) {
                if o == 0 {
                    add(&mut out[pixel], gain.to_array(), 1.0);
                }
            }
        }
        if next.is_empty() {
            break;
        }
        let rays: Vec<Ray> = next.iter().map(|p| p.ray).collect();
        let mut hits = vec![Hit::MISS; rays.len()];
        let t0 = std::time::Instant::now();
        frame.accel.trace(&rays, Query::Closest, &mut hits);
        stats.trace_seconds += t0.elapsed().as_secs_f64();
        stats.rays += rays.len() as u64;
        for (p, h) in next.iter_mut().zip(hits) {
            p.hit = h;
        }
        live = next;
    }
}

/// Shades the vertex path `p` reached.
fn shade_vertex(
    frame: Frame<'_>,
    p: &mut PathState,
    scatter: bool,
    sky: Vec3,
    lights: &[surface::PunctualLight],
) -> Step {
    let thr = p.throughput;
    if !p.hit.is_hit() {
        return Step {
            emitted: thr * sky,
            ..Step::default()
        };
    }
    let dir = Vec3::from(p.ray.dir);
    let sp = frame
        .surfaces
        .at(&frame.triangles[p.hit.prim as usize], &p.hit, dir);
    let mut step = Step {
        emitted: thr * sp.emission,
        ..Step::default()
    };
    if !scatter {
        return step;
    }
    let pos = p.ray.at(p.hit.t);
    let (t, b) = basis(sp.ns.to_array());
    let (t, b, n) = (Vec3::from(t), Vec3::from(b), sp.ns);
    let local = |v: Vec3| Vec3::new(v.dot(t), v.dot(b), v.dot(n));
    let wo = local(-dir);
    let org = offset_ray(pos, sp.ng.to_array());
    if !lights.is_empty() {
        let j = p.rng.below(lights.len() as u32) as usize;
        if let Some(inc) = lights[j].incident(Vec3::from(pos)) {
            if inc.wi.dot(sp.ng) > 0.0 {
                let wi = local(inc.wi);
                let gain = thr
                    * sp.bsdf.eval(wo, wi)
                    * wi.z.max(0.0)
                    * inc.irradiance
                    * lights.len() as f32;
                if gain.max_element() > 0.0 && gain.is_finite() {
                    step.shadow = Some((
                        Ray {
                            org,
                            tmin: 0.0,
                            dir: inc.wi.to_array(),
                            tmax: inc.distance,
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
        // A direction under the geometric surface would leak through it.
        if wi.dot(sp.ng) > 0.0 {
            step.next = Some((
                Ray {
                    org,
                    tmin: 0.0,
                    dir: wi.to_array(),
                    tmax: f32::INFINITY,
                },
                thr * s.weight,
            ));
        }
    }
    step
}

#[inline]
fn add(o: &mut [f32; 3], c: [f32; 3], k: f32) {
    for j in 0..3 {
        o[j] += c[j] * k;
    }
}
