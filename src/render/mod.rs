//! Rendering: synchronous and format-free. It makes batches of rays, traces them with any
//! [`Intersector`] and shades the hits; `image` turns the result into PNG or OpenEXR bytes.
//!
//! Work goes in waves (all primary rays of a block of pixels, then all their secondary
//! rays), never ray by ray, because the batch cores (DACRT) only exist in that form and the
//! others lose nothing by it.

pub mod camera;
pub mod image;
pub mod rng;
pub mod sampling;

use crate::accel::{Intersector, Query};
use crate::geometry::{dot, Hit, Ray, Triangle};
use camera::ViewCamera;
use rng::Pcg32;
use sampling::{cosine_hemisphere, normalize};

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
    /// Diffuse path tracing under a white sky, white-grey Lambertian surfaces.
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
        }
    }
}

/// A linear-light RGB image.
#[derive(Clone, Debug, PartialEq)]
pub struct Image {
    /// Width in pixels.
    pub width: u32,
    /// Height in pixels.
    pub height: u32,
    /// Row-major pixels, top row first.
    pub pixels: Vec<[f32; 3]>,
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
const ALBEDO: f32 = 0.7;

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
/// by `waves`. `scene_diagonal` sets the ambient-occlusion distance.
pub fn render<W: Waves + ?Sized>(
    triangles: &[Triangle],
    accel: &dyn Intersector,
    camera: &ViewCamera,
    options: &RenderOptions,
    scene_diagonal: f32,
    waves: &W,
) -> Result<(Image, RenderStats), W::Error> {
    let (w, h) = (options.width, options.height);
    let n = w as usize * h as usize;
    let spp = options.spp.max(1);
    let mut sum = vec![[0.0f32; 3]; n];
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
            let out = &mut sum[start..end];
            let stats = &mut stats;
            waves.run_wave(&mut || {
                render_wave(
                    triangles,
                    accel,
                    camera,
                    options,
                    scene_diagonal,
                    (start, end, s),
                    out,
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
    Ok((
        Image {
            width: w,
            height: h,
            pixels,
        },
        stats,
    ))
}

/// One wave: sample `s` of pixels `start..end`, accumulated into `out`.
#[allow(clippy::too_many_arguments)]
fn render_wave(
    triangles: &[Triangle],
    accel: &dyn Intersector,
    camera: &ViewCamera,
    options: &RenderOptions,
    scene_diagonal: f32,
    (start, end, s): (usize, usize, u32),
    out: &mut [[f32; 3]],
    stats: &mut RenderStats,
) {
    let w = options.width;
    let h = options.height;
    let spp = options.spp.max(1);
    let trace = |rays: &[Ray], query: Query, hits: &mut [Hit], stats: &mut RenderStats| {
        let t0 = std::time::Instant::now();
        accel.trace(rays, query, hits);
        stats.trace_seconds += t0.elapsed().as_secs_f64();
        stats.rays += rays.len() as u64;
    };
    let mut rngs: Vec<Pcg32> = (start..end)
        .map(|p| Pcg32::new(options.seed ^ ((s as u64) << 40), p as u64))
        .collect();
    let rays: Vec<Ray> = (start..end)
        .zip(&mut rngs)
        .map(|(p, rng)| {
            let (jx, jy) = if spp == 1 {
                (0.5, 0.5)
            } else {
                (rng.next_f32() as f64, rng.next_f32() as f64)
            };
            let (x, y) = ((p % w as usize) as f64, (p / w as usize) as f64);
            camera.ray(x + jx, y + jy, w, h)
        })
        .collect();
    let mut hits = vec![Hit::MISS; rays.len()];
    trace(&rays, Query::Closest, &mut hits, stats);
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
                        org: offset_origin(r.at(hit.t), nrm),
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
            // Throughput per live path; paths that leave the scene add the sky.
            let mut live: Vec<(usize, Ray, Hit, f32)> = rays
                .iter()
                .zip(&hits)
                .enumerate()
                .map(|(i, (r, hit))| (i, *r, *hit, 1.0))
                .collect();
            for bounce in 0..=options.bounces {
                let mut next_rays = Vec::new();
                let mut next_meta = Vec::new();
                for &(i, r, hit, thr) in &live {
                    if !hit.is_hit() {
                        add(&mut out[i], [1.0; 3], thr);
                        continue;
                    }
                    if bounce == options.bounces {
                        continue;
                    }
                    let nrm = facing_normal(&triangles[hit.prim as usize], r.dir);
                    let rng = &mut rngs[i];
                    let d = cosine_hemisphere(nrm, rng.next_f32(), rng.next_f32());
                    next_rays.push(Ray {
                        org: offset_origin(r.at(hit.t), nrm),
                        tmin: 0.0,
                        dir: d,
                        tmax: f32::INFINITY,
                    });
                    next_meta.push((i, thr * ALBEDO));
                }
                if next_rays.is_empty() {
                    break;
                }
                let mut next_hits = vec![Hit::MISS; next_rays.len()];
                trace(&next_rays, Query::Closest, &mut next_hits, stats);
                live = next_meta
                    .into_iter()
                    .zip(next_rays)
                    .zip(next_hits)
                    .map(|(((i, thr), r), hit)| (i, r, hit, thr))
                    .collect();
            }
        }
    }
}

#[inline]
fn add(o: &mut [f32; 3], c: [f32; 3], k: f32) {
    for j in 0..3 {
        o[j] += c[j] * k;
    }
}
