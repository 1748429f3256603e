//! Render jobs: one image, or one per animation time, in waves the scheduler can
//! interleave with other work.

use std::sync::Arc;
use std::time::Instant;

use super::cache::LightKey;
use super::engine::Source;
use super::{seconds_since, Control, Engine, Geometry, JobError, Limits};
use crate::accel::{AccelKind, BuildQuality, Precision};
use crate::render::camera::{CameraChoice, ViewCamera};
use crate::render::image::{encode, ImageFormat};
use crate::render::surface::Surfaces;
use crate::render::texture::{at_once, DecodedOnce, Steps};
use crate::render::{AovSet, Integrator, RenderOptions, Waves};
use crate::scene::Camera;

/// What to render (the options of `rayd render` and of the render route's body, less the
/// scene, version and times, which say which geometry).
#[derive(Clone, Debug, PartialEq)]
pub struct RenderRequest {
    /// Image width in pixels.
    pub width: u32,
    /// Image height in pixels.
    pub height: u32,
    /// Samples per pixel.
    pub spp: u32,
    /// What a pixel shows.
    pub integrator: Integrator,
    /// Path bounces.
    pub bounces: u32,
    /// The camera.
    pub camera: CameraChoice,
    /// Seed of every random choice.
    pub seed: u64,
    /// Output format.
    pub format: ImageFormat,
    /// The accelerator (`auto` resolves per frame).
    pub accel: AccelKind,
    /// Build quality of the BVH accelerators.
    pub build: BuildQuality,
    /// Ray/triangle test.
    pub precision: Precision,
    /// Radiance of the constant environment of `path` (linear RGB, each finite and ≥ 0).
    pub sky: [f32; 3],
    /// AOV channels to add (EXR only).
    pub aovs: AovSet,
    /// How a frame over moved geometry gets its BVH: refit or rebuild.
    pub update: super::Update,
    /// Russian roulette of `path` from this scattering on (`None`: off).
    pub roulette: Option<u32>,
}

impl Default for RenderRequest {
    fn default() -> Self {
        RenderRequest {
            width: 640,
            height: 480,
            spp: 1,
            integrator: Integrator::Primary,
            bounces: 2,
            camera: CameraChoice::Auto,
            seed: 0,
            format: ImageFormat::Png,
            accel: AccelKind::Auto,
            build: BuildQuality::Sah,
            precision: Precision::Watertight,
            sky: [1.0; 3],
            aovs: AovSet::default(),
            update: super::Update::Auto,
            roulette: None,
        }
    }
}

impl RenderRequest {
    /// Checks the request against `limits`, naming the field that does not fit.
    pub fn check(&self, limits: &Limits, frames: usize) -> Result<(), JobError> {
        let side = |what: &'static str, v: u32| {
            if v == 0 {
                Err(JobError::Invalid {
                    field: what,
                    detail: "must be at least 1".into(),
                })
            } else if v > limits.max_side {
                Err(JobError::Limit {
                    what,
                    value: v as u64,
                    limit: limits.max_side as u64,
                })
            } else {
                Ok(())
            }
        };
        side("width", self.width)?;
        side("height", self.height)?;
        let pixels = self.width as u64 * self.height as u64;
        if pixels > limits.max_pixels {
            return Err(JobError::Limit {
                what: "pixels",
                value: pixels,
                limit: limits.max_pixels,
            });
        }
        if self.spp == 0 {
            return Err(JobError::Invalid {
                field: "spp",
                detail: "must be at least 1".into(),
            });
        }
        if let Some(x) = self.sky.iter().find(|x| !(x.is_finite() && **x >= 0.0)) {
            return Err(JobError::Invalid {
                field: "sky",
                detail: format!("{x} is not a finite radiance of at least 0"),
            });
        }
        if !self.aovs.is_empty() && self.format != ImageFormat::Exr {
            return Err(JobError::Invalid {
                field: "aov",
                detail: format!(
                    "AOVs are EXR channels; the {} output has none (ask for exr)",
                    self.format
                ),
            });
        }
        if self.roulette == Some(0) {
            return Err(JobError::Invalid {
                field: "roulette",
                detail: "the first scattering that roulette may end is 1 or later".into(),
            });
        }
        let checks = [
            ("spp", self.spp as u64, limits.max_spp as u64),
            ("bounces", self.bounces as u64, limits.max_bounces as u64),
            (
                "roulette",
                self.roulette.unwrap_or(0) as u64,
                limits.max_bounces as u64,
            ),
            ("frames", frames as u64, limits.max_frames as u64),
        ];
        for (what, value, limit) in checks {
            if value > limit {
                return Err(JobError::Limit { what, value, limit });
            }
        }
        Ok(())
    }

    /// Whether frames need their scene's materials, shading attributes and lights: `path`
    /// shades with them and the `albedo` and `normal` AOVs show them.
    pub fn needs_surfaces(&self) -> bool {
        self.integrator == Integrator::Path || self.aovs.albedo || self.aovs.normal
    }

    /// Trace calls one frame makes (camera rays per sample, plus one per AO sample or path
    /// bounce) per wave, and rays in all, for `auto`'s model.
    /// Rays and trace calls of a frame whose camera rays are the fraction `seen` of its
    /// pixels' (those that can see the scene's bounds). A path continues past a bounce
    /// only if its ray hits again, which is taken to happen with the same chance `seen`:
    /// 1 inside a scene (every path lives to `bounces`), a fraction around an object seen
    /// from outside (session 31's review: `W·H·spp·(1 + 2·bounces)` counted 5.7 times the
    /// rays a render of Suzanne traced, and `auto` picked DACRT at 1.3–2.2× `mbvh8`'s
    /// time).
    fn work(&self, seen: f64) -> (usize, usize) {
        let seen = seen.clamp(0.0, 1.0);
        // Continuation and shadow rays per bounce, each bounce reached with chance seen^k.
        let bounces: f64 = (0..self.bounces).map(|k| seen.powi(k as i32)).sum();
        let (per_sample, batches) = match self.integrator {
            Integrator::Ao => (2.0, 2),
            Integrator::Path => (1.0 + 2.0 * bounces, 1 + 2 * self.bounces as usize),
            _ => (1.0, 1),
        };
        let camera = self.width as f64 * self.height as f64 * seen * f64::from(self.spp);
        (
            ((camera * per_sample) as usize).max(1),
            self.spp as usize * batches,
        )
    }
}

/// The scene as one frame needs it.
pub struct FrameInput {
    /// World-space triangles at the frame's time.
    pub geometry: Geometry,
    /// The scene's cameras at that time.
    pub cameras: Arc<Vec<Option<Camera>>>,
    /// Materials, shading attributes and lights at that time, when the request needs them
    /// ([`RenderRequest::needs_surfaces`]); `None`: glTF's default material everywhere.
    pub surfaces: Option<Arc<Surfaces>>,
}

impl FrameInput {
    /// The frame of `scene`, already posed at the frame's time, under `key`; with
    /// `surfaces` (the request [`RenderRequest::needs_surfaces`]) its materials, shading
    /// attributes and lights too. `rayd render` and `rayd tradeoff` make their frames here.
    pub fn of_scene(
        scene: &crate::scene::Scene,
        key: super::GeometryKey,
        surfaces: bool,
    ) -> Result<FrameInput, JobError> {
        let textures = DecodedOnce::default();
        FrameInput::of_scene_with(
            scene,
            key,
            surfaces.then_some(&textures),
            &at_once::<JobError>,
        )
    }

    /// [`FrameInput::of_scene`] for one frame of a sequence, its work done in `step`'s
    /// steps (a [`Control`]'s on the pool): `textures`, when the request needs surfaces,
    /// holds the textures an earlier frame decoded, or decodes them now, in steps of their
    /// own ([`DecodedOnce::get_in_steps`]).
    pub fn of_scene_with(
        scene: &crate::scene::Scene,
        key: super::GeometryKey,
        textures: Option<&DecodedOnce>,
        step: &Steps<'_, JobError>,
    ) -> Result<FrameInput, JobError> {
        let decoded = match textures {
            Some(t) => Some(
                t.get_in_steps(scene, step)?
                    .map_err(|e| JobError::Geometry(format!("{}: {e}", key.scene)))?,
            ),
            None => None,
        };
        let mut input = None;
        step(&mut || {
            input = Some(FrameInput {
                geometry: Geometry {
                    key: key.clone(),
                    triangles: Arc::new(scene.triangles.clone()),
                    forgets: 0,
                },
                cameras: Arc::new(scene.cameras.clone()),
                surfaces: decoded.map(|t| Arc::new(Surfaces::with_textures(scene, t.clone()))),
            })
        })?;
        Ok(input.expect("the step ran"))
    }
}

/// What [`Engine::render`] asks for each frame's scene: called with the frame's time and
/// the job's control, it does its work in the control's steps.
pub type FrameAt<'a> = dyn Fn(Option<f64>, &Control) -> Result<FrameInput, JobError> + Sync + 'a;

/// Where one frame's time went.
#[derive(Clone, Debug, PartialEq, serde::Serialize)]
pub struct FrameTimes {
    /// The animation time (`None`: the static pose).
    pub time: Option<f64>,
    /// Seconds to evaluate the scene at that time.
    pub evaluate_seconds: f64,
    /// Seconds to build, refit or precompute the structure (0 when cached).
    pub prepare_seconds: f64,
    /// Seconds inside the intersector.
    pub trace_seconds: f64,
    /// Everything else of the frame: ray generation, shading, wave bookkeeping.
    pub shade_seconds: f64,
    /// Seconds to encode the image.
    pub encode_seconds: f64,
    /// The accelerator used (what `auto` chose).
    pub accel: &'static str,
    /// Where the structure came from.
    pub structure: Source,
    /// Rays traced.
    pub rays: u64,
}

/// What a render did.
#[derive(Clone, Debug, PartialEq, serde::Serialize)]
pub struct RenderReport {
    /// Image width.
    pub width: u32,
    /// Image height.
    pub height: u32,
    /// Samples per pixel.
    pub spp: u32,
    /// The integrator.
    pub integrator: Integrator,
    /// The output format.
    pub format: ImageFormat,
    /// Threads of the pool.
    pub threads: usize,
    /// Rays traced, all frames.
    pub rays: u64,
    /// Seconds of structure preparation, all frames.
    pub build_seconds: f64,
    /// Seconds inside the intersector, all frames.
    pub trace_seconds: f64,
    /// Seconds from the first frame's start to the last image, all included.
    pub render_seconds: f64,
    /// Per frame.
    pub frames: Vec<FrameTimes>,
}

/// Maps one frame's progress into the job's.
struct FrameWaves<'a> {
    control: &'a Control,
    frame: usize,
    frames: usize,
}

impl Waves for FrameWaves<'_> {
    type Error = JobError;
    fn run_wave(&self, wave: &mut (dyn FnMut() + Send)) -> Result<(), JobError> {
        self.control.step(wave)
    }
    fn wave_seconds(&self) -> f64 {
        self.control.wave_seconds()
    }
    fn progress(&self, fraction: f64) {
        self.control
            .progress((self.frame as f64 + fraction) / self.frames as f64);
    }
}

impl Engine {
    /// Renders one image per entry of `times`, asking `frame_at` for each time's scene,
    /// and hands each encoded image to `emit` (frame index, bytes) as soon as it is done.
    /// Every CPU step runs on the pool under `control`'s lease; cancellation stops the job
    /// within one wave. `frame_at` is called on the caller's thread with `control`, and
    /// runs its own work in `control`'s steps: a scene's textures take several (one per
    /// group of images), so that a request arriving meanwhile waits for one image, not all.
    pub fn render(
        &self,
        request: &RenderRequest,
        times: &[Option<f64>],
        frame_at: &FrameAt<'_>,
        control: &Control,
        emit: &mut dyn FnMut(usize, Vec<u8>) -> Result<(), JobError>,
    ) -> Result<RenderReport, JobError> {
        request.check(self.limits(), times.len())?;
        let t_all = Instant::now();
        let mut frames = Vec::with_capacity(times.len());
        for (k, &time) in times.iter().enumerate() {
            let t0 = Instant::now();
            let input = frame_at(time, control)?;
            let evaluate_seconds = seconds_since(t0);
            let g = &input.geometry;
            let aspect = request.width as f64 / request.height as f64;
            let bounds = crate::scene::bounds_of(&g.triangles);
            let camera = ViewCamera::choose_from(&request.camera, &input.cameras, bounds, aspect)?;
            // Only pixels that can see the scene send rays (`render::render`): the cost
            // model hears of theirs.
            let (w, h) = (request.width, request.height);
            let seen = bounds.map_or(1.0, |b| {
                camera.pixel_rect(&b, w, h).len() as f64 / (f64::from(w) * f64::from(h))
            });
            let (rays, batches) = request.work(seen);
            let kind = self.resolve(
                request.accel,
                g,
                request.build,
                request.precision,
                rays,
                batches,
                times.len() - k,
                0.0,
                false,
            );
            let prepared = control.step(|| {
                self.structure(
                    g,
                    kind,
                    request.build,
                    request.precision,
                    rays,
                    batches,
                    request.update,
                )
            })??;
            let options = RenderOptions {
                width: request.width,
                height: request.height,
                spp: request.spp,
                integrator: request.integrator,
                bounces: request.bounces,
                seed: request.seed,
                sky: request.sky,
                aovs: request.aovs,
                roulette: request.roulette,
                light_sampling: true,
            };
            let waves = FrameWaves {
                control,
                frame: k,
                frames: times.len(),
            };
            let t1 = Instant::now();
            // A path frame's light table, kept for later jobs of the same positions.
            let lights = match (&input.surfaces, request.integrator) {
                (Some(surfaces), Integrator::Path) => {
                    let key = LightKey {
                        geometry: g.key.clone(),
                        sky: options.sky.map(f32::to_bits),
                        light_sampling: options.light_sampling,
                    };
                    Some(self.lights().get_or_build(
                        key,
                        || crate::render::light_table(&g.triangles, surfaces, &options, &waves),
                        || self.keeps(g),
                    )?)
                }
                _ => None,
            };
            let (image, stats) = crate::render::render(
                &g.triangles,
                prepared.accel.as_ref(),
                &camera,
                &options,
                bounds.as_ref(),
                input.surfaces.as_deref(),
                lights.as_deref(),
                &waves,
            )?;
            let render_seconds = seconds_since(t1);
            let t2 = Instant::now();
            let bytes = control.step(|| encode(&image, request.format))??;
            let encode_seconds = seconds_since(t2);
            emit(k, bytes)?;
            frames.push(FrameTimes {
                time,
                evaluate_seconds,
                prepare_seconds: prepared.build_seconds,
                trace_seconds: stats.trace_seconds,
                shade_seconds: (render_seconds - stats.trace_seconds).max(0.0),
                encode_seconds,
                accel: prepared.accel.name(),
                structure: prepared.source,
                rays: stats.rays,
            });
        }
        control.progress(1.0);
        Ok(RenderReport {
            width: request.width,
            height: request.height,
            spp: request.spp,
            integrator: request.integrator,
            format: request.format,
            threads: self.threads(),
            rays: frames.iter().map(|f| f.rays).sum(),
            build_seconds: frames.iter().map(|f| f.prepare_seconds).sum(),
            trace_seconds: frames.iter().map(|f| f.trace_seconds).sum(),
            render_seconds: seconds_since(t_all),
            frames,
        })
    }
}

/// The times of `--frames START:END:STEP` (contract §4): START + k·STEP for k = 0 …
/// ⌊(END − START)/STEP + 1e-9⌋.
/// Errors name the part at fault (`frames.step`, …), as the request's field paths do.
pub fn frame_times(start: f64, end: f64, step: f64, limit: usize) -> Result<Vec<f64>, JobError> {
    let bad = |field: &'static str, detail: &str| JobError::Invalid {
        field,
        detail: detail.to_string(),
    };
    for (field, x) in [
        ("frames.start", start),
        ("frames.end", end),
        ("frames.step", step),
    ] {
        if !x.is_finite() {
            return Err(bad(field, "must be a finite number of seconds"));
        }
    }
    if step <= 0.0 {
        return Err(bad("frames.step", "must be positive"));
    }
    if end < start {
        return Err(bad("frames.end", "must not be before start"));
    }
    let k = ((end - start) / step + 1e-9).floor();
    if k + 1.0 > limit as f64 {
        // A count past 2^53 is no longer an integer f64 holds exactly: say how large.
        if k + 1.0 >= 9_007_199_254_740_992.0 {
            let count = if k.is_finite() {
                format!("{:.3e}", k + 1.0)
            } else {
                "more than 1.8e308".to_string()
            };
            return Err(bad(
                "frames.step",
                &format!("makes {count} frames, over the limit of {limit}"),
            ));
        }
        return Err(JobError::Limit {
            what: "frames",
            value: (k + 1.0) as u64,
            limit: limit as u64,
        });
    }
    Ok((0..=k as usize).map(|i| start + i as f64 * step).collect())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn frame_times_follow_the_contract() {
        assert_eq!(frame_times(0.0, 1.0, 0.5, 100).unwrap(), [0.0, 0.5, 1.0]);
        // END included when it falls on a step, despite rounding.
        assert_eq!(frame_times(0.0, 0.3, 0.1, 100).unwrap().len(), 4);
        assert_eq!(frame_times(0.0, 0.95, 0.5, 100).unwrap(), [0.0, 0.5]);
        assert!(frame_times(0.0, 1.0, 0.0, 100).is_err());
        assert!(frame_times(1.0, 0.0, 0.1, 100).is_err());
        assert!(matches!(
            frame_times(0.0, 1e6, 1.0, 100),
            Err(JobError::Limit {
                what: "frames",
                value: 1_000_001,
                ..
            })
        ));
        // Past 2^53 a count is no integer to print: the step is at fault, and says how many.
        match frame_times(0.0, 1e9, 1e-9, 100) {
            Err(JobError::Invalid { field, detail }) => {
                assert_eq!(field, "frames.step");
                assert!(detail.contains("1.000e18 frames"), "{detail}");
            }
            other => panic!("{other:?}"),
        }
        for (args, field) in [
            ((f64::NAN, 1.0, 1.0), "frames.start"),
            ((0.0, f64::INFINITY, 1.0), "frames.end"),
            ((0.0, 1.0, -1.0), "frames.step"),
            ((2.0, 1.0, 1.0), "frames.end"),
        ] {
            match frame_times(args.0, args.1, args.2, 100) {
                Err(JobError::Invalid { field: f, .. }) => assert_eq!(f, field, "{args:?}"),
                other => panic!("{args:?}: {other:?}"),
            }
        }
    }

    #[test]
    fn limits_name_the_field() {
        let l = Limits {
            max_pixels: 100,
            ..Limits::default()
        };
        let r = RenderRequest {
            width: 20,
            height: 20,
            ..Default::default()
        };
        assert!(matches!(
            r.check(&l, 1),
            Err(JobError::Limit { what: "pixels", .. })
        ));
        let r = RenderRequest {
            spp: 0,
            ..Default::default()
        };
        assert!(matches!(
            r.check(&Limits::default(), 1),
            Err(JobError::Invalid { field: "spp", .. })
        ));
    }
}
