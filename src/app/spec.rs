//! The request bodies and parameters of the service, in the contract's spelling, and their
//! resolution into engine requests. Every field is checked here, before any work starts.

use serde::{Deserialize, Serialize};

use super::AppError;
use crate::accel::{AccelKind, BuildQuality, Precision, Query};
use crate::formats::HitFormat;
use crate::jobs::{InvalidPolicy, RenderRequest, TraceRequest};
use crate::render::camera::CameraChoice;
use crate::render::image::ImageFormat;
use crate::render::{Aov, AovSet, Integrator};

/// The trace route's query string: the options of `rayd trace`, plus which geometry.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct TraceParams {
    /// `closest` or `any`.
    pub query: Query,
    /// Hit fields to return.
    pub hit: HitFormat,
    /// Accelerator.
    pub accel: AccelKind,
    /// Build quality.
    pub build: BuildQuality,
    /// Ray/triangle test.
    pub precision: Precision,
    /// Animation time of version 1 (seconds); absent: the static pose.
    pub time: Option<f64>,
    /// Geometry version; absent: the latest.
    pub version: Option<u32>,
    /// What to do with invalid rays.
    pub invalid: InvalidPolicy,
}

impl TraceParams {
    /// The engine's request.
    pub fn request(&self) -> TraceRequest {
        TraceRequest {
            query: self.query,
            hit: self.hit,
            accel: self.accel,
            build: self.build,
            precision: self.precision,
            invalid: self.invalid,
        }
    }
}

/// Animation times of a render: `start + k·step` up to `end` (contract §4).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct FramesSpec {
    /// First time, seconds.
    pub start: f64,
    /// Last time (included when it falls on a step).
    pub end: f64,
    /// Step, seconds (> 0).
    pub step: f64,
}

fn default_width() -> u32 {
    640
}
fn default_height() -> u32 {
    480
}
fn default_spp() -> u32 {
    1
}
fn default_bounces() -> u32 {
    2
}
fn default_priority() -> u8 {
    50
}

/// The render route's body: the options of `rayd render` in JSON (contract §5).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct RenderSpec {
    /// Image width.
    #[serde(default = "default_width")]
    pub width: u32,
    /// Image height.
    #[serde(default = "default_height")]
    pub height: u32,
    /// Samples per pixel.
    #[serde(default = "default_spp")]
    pub spp: u32,
    /// What a pixel shows.
    #[serde(default)]
    pub integrator: Integrator,
    /// Path bounces.
    #[serde(default = "default_bounces")]
    pub bounces: u32,
    /// A camera of the scene, by index.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub camera: Option<usize>,
    /// Look-at camera: eye.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub eye: Option<[f64; 3]>,
    /// Look-at camera: target.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub target: Option<[f64; 3]>,
    /// Look-at camera: up (default `[0, 1, 0]`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub up: Option<[f64; 3]>,
    /// Look-at camera: vertical field of view, degrees (default 45).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub fov: Option<f64>,
    /// `png` or `exr`.
    #[serde(default)]
    pub format: ImageFormat,
    /// Accelerator.
    #[serde(default)]
    pub accel: AccelKind,
    /// Build quality.
    #[serde(default)]
    pub build: BuildQuality,
    /// Ray/triangle test.
    #[serde(default)]
    pub precision: Precision,
    /// Animation time of version 1.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub time: Option<f64>,
    /// Geometry version (default: the latest at submission).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub version: Option<u32>,
    /// Seed.
    #[serde(default)]
    pub seed: u64,
    /// Constant environment radiance (default `[1, 1, 1]`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub sky: Option<[f32; 3]>,
    /// AOV channels for EXR output (each at most once).
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub aov: Vec<Aov>,
    /// Russian roulette of `path` from this scattering on (absent: off).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub roulette: Option<u32>,
    /// Animation times: one image per time.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub frames: Option<FramesSpec>,
    /// How each frame over moved geometry gets its BVH: `auto`, `refit` or `rebuild`.
    #[serde(default)]
    pub update: crate::jobs::Update,
    /// 0–100, higher first.
    #[serde(default = "default_priority")]
    pub priority: u8,
    /// A URL to POST the finished job to (checked against the server's allow-list at
    /// submission, by the app, not here: resolving it again after a restart must not fail).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub callback: Option<String>,
}

/// A field the body spells right but whose value the service cannot run: out of its range,
/// against another field, or not a view a camera can make. The body parsed, so this is the
/// contract's "well-formed but invalid" (422), as a value past a configured limit is; 400
/// stays for bodies that do not parse into a request (syntax, a type, an unknown field).
fn bad(field: &'static str, detail: impl Into<String>) -> AppError {
    AppError::Unprocessable {
        field,
        detail: detail.into(),
    }
}

impl RenderSpec {
    /// The engine's request and the frame times, or the first field that is wrong.
    pub fn resolve(
        &self,
        max_frames: usize,
    ) -> Result<(RenderRequest, Vec<Option<f64>>), AppError> {
        if self.priority > 100 {
            return Err(bad(
                "priority",
                format!("{} is not in 0..=100", self.priority),
            ));
        }
        let camera = match (self.camera, self.eye, self.target) {
            (Some(_), Some(_), _) | (Some(_), _, Some(_)) => {
                return Err(bad("camera", "give either camera or eye/target, not both"))
            }
            (Some(i), None, None) => CameraChoice::Scene(i),
            (None, Some(eye), Some(target)) => {
                let fov = self.fov.unwrap_or(45.0);
                let up = self.up.unwrap_or([0.0, 1.0, 0.0]);
                // Points within f32's range: the scene is f32, and a camera past it sees
                // nothing (its rays start at infinity).
                for (field, v) in [("eye", eye), ("target", target), ("up", up)] {
                    if v.iter()
                        .any(|x| !(x.is_finite() && x.abs() <= f32::MAX as f64))
                    {
                        return Err(bad(
                            field,
                            "components must be finite numbers in f32's range",
                        ));
                    }
                }
                if !(fov.is_finite() && fov > 0.0 && fov < 180.0) {
                    return Err(bad("fov", format!("{fov} is not in (0, 180) degrees")));
                }
                // The view itself, as the job would make it: a degenerate one is this
                // request's error, not the job's.
                use crate::render::camera::{CameraError, ViewCamera, EYE_AT_TARGET};
                if let Err(e) = ViewCamera::look_at(eye, target, up, fov, 1.0) {
                    let field = match e {
                        CameraError::Degenerate(EYE_AT_TARGET) => "target",
                        CameraError::BadFov(_) => "fov",
                        _ => "up",
                    };
                    return Err(bad(field, e.to_string()));
                }
                CameraChoice::LookAt {
                    eye,
                    target,
                    up,
                    fov,
                }
            }
            (None, Some(_), None) => return Err(bad("target", "eye needs a target")),
            (None, None, Some(_)) => return Err(bad("eye", "target needs an eye")),
            (None, None, None) => CameraChoice::Auto,
        };
        // `up` and `fov` shape a look-at camera only: elsewhere they would be ignored.
        if !matches!(camera, CameraChoice::LookAt { .. }) {
            for (field, given) in [("fov", self.fov.is_some()), ("up", self.up.is_some())] {
                if given {
                    return Err(bad(
                        field,
                        "applies only to a look-at camera (with eye and target)",
                    ));
                }
            }
        }
        if let Some(t) = self.time {
            if !t.is_finite() {
                return Err(bad("time", "must be a finite number of seconds"));
            }
        }
        let sky = self.sky.unwrap_or([1.0; 3]);
        if let Some(x) = sky.iter().find(|x| !(x.is_finite() && **x >= 0.0)) {
            return Err(bad(
                "sky",
                format!("{x} is not a finite radiance of at least 0"),
            ));
        }
        if let Some(a) = Aov::repeated(&self.aov) {
            return Err(bad("aov", format!("'{a}' is listed twice")));
        }
        let aovs = AovSet::of(&self.aov);
        if !aovs.is_empty() && self.format != ImageFormat::Exr {
            return Err(bad(
                "aov",
                format!(
                    "AOVs are EXR channels; the {} output has none (ask for exr)",
                    self.format
                ),
            ));
        }
        let times = match (&self.frames, self.time) {
            (Some(_), Some(_)) => {
                return Err(bad("frames", "give either frames or time, not both"))
            }
            (Some(f), None) => crate::jobs::render::frame_times(f.start, f.end, f.step, max_frames)
                .map_err(|e| match e {
                    crate::jobs::JobError::Invalid { field, detail } => bad(field, detail),
                    other => bad("frames", other.to_string()),
                })?
                .into_iter()
                .map(Some)
                .collect(),
            (None, t) => vec![t],
        };
        Ok((
            RenderRequest {
                width: self.width,
                height: self.height,
                spp: self.spp,
                integrator: self.integrator,
                bounces: self.bounces,
                camera,
                seed: self.seed,
                format: self.format,
                accel: self.accel,
                build: self.build,
                precision: self.precision,
                sky,
                aovs,
                update: self.update,
                roulette: self.roulette,
            },
            times,
        ))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn defaults_are_the_cli_defaults() {
        let s: RenderSpec = serde_json::from_str("{}").unwrap();
        let (r, times) = s.resolve(100).unwrap();
        assert_eq!(r, RenderRequest::default());
        assert_eq!(times, [None]);
        assert_eq!(s.priority, 50);
    }

    #[test]
    fn cameras_that_cannot_be_made_are_refused_by_field() {
        let field = |json: &str| match serde_json::from_str::<RenderSpec>(json).unwrap().resolve(1)
        {
            Err(AppError::Unprocessable { field, .. }) => field,
            other => panic!("{json}: {other:?}"),
        };
        assert_eq!(field(r#"{"eye":[0,0,1],"target":[0,0,1]}"#), "target");
        assert_eq!(
            field(r#"{"eye":[0,0,1],"target":[0,0,0],"up":[0,0,2]}"#),
            "up"
        );
        assert_eq!(
            field(r#"{"eye":[0,0,1],"target":[0,0,0],"up":[0,0,0]}"#),
            "up"
        );
        assert_eq!(field(r#"{"eye":[1e39,0,1],"target":[0,0,0]}"#), "eye");
        assert_eq!(
            field(r#"{"eye":[0,0,1],"target":[0,0,0],"fov":180}"#),
            "fov"
        );
        assert_eq!(field(r#"{"fov":30}"#), "fov");
        assert_eq!(field(r#"{"camera":0,"up":[0,1,0]}"#), "up");
        let ok = r#"{"eye":[0,0,1],"target":[0,0,0],"up":[0,1,0],"fov":30}"#;
        assert!(serde_json::from_str::<RenderSpec>(ok)
            .unwrap()
            .resolve(1)
            .is_ok());
    }

    #[test]
    fn fields_are_checked_by_name() {
        let e = serde_json::from_str::<RenderSpec>(r#"{"widht": 3}"#).unwrap_err();
        assert!(e.to_string().contains("widht"), "{e}");
        let s: RenderSpec = serde_json::from_str(r#"{"eye":[0,0,1]}"#).unwrap();
        assert!(matches!(
            s.resolve(1),
            Err(AppError::Unprocessable {
                field: "target",
                ..
            })
        ));
        let s: RenderSpec =
            serde_json::from_str(r#"{"frames":{"start":0,"end":1,"step":0.25},"format":"exr"}"#)
                .unwrap();
        let (r, times) = s.resolve(100).unwrap();
        assert_eq!(times.len(), 5);
        assert_eq!(r.format, ImageFormat::Exr);
    }
}
