//! Cameras that turn pixel positions into primary rays: the scene's own glTF cameras, a
//! look-at camera from the command line, or a default view that frames the scene.

use crate::geometry::{Aabb, Ray};
use crate::scene::{Camera, Projection, Scene};

/// Which camera a render or benchmark uses.
#[derive(Clone, Debug, PartialEq, Default)]
pub enum CameraChoice {
    /// Neither a scene camera nor a look-at one was named: a default view framing the
    /// bounds, even when the scene has cameras (`proto/rendering.md`, "Camera").
    #[default]
    Auto,
    /// The scene's camera with this index.
    Scene(usize),
    /// A look-at camera.
    LookAt {
        /// Eye.
        eye: [f64; 3],
        /// Point looked at.
        target: [f64; 3],
        /// Up vector.
        up: [f64; 3],
        /// Vertical field of view in degrees.
        fov: f64,
    },
}

/// A camera ready to make rays: an orthonormal frame and a projection.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ViewCamera {
    eye: [f64; 3],
    right: [f64; 3],
    up: [f64; 3],
    forward: [f64; 3],
    kind: ViewKind,
    /// Clipping planes' distances along `forward` ([`Camera::clip`]); `[0, inf]` but for
    /// a glTF camera that has them.
    clip: [f64; 2],
}

#[derive(Clone, Copy, Debug, PartialEq)]
enum ViewKind {
    /// Half-extents of the image plane at distance 1 (tan of half the field of view).
    Perspective { half_w: f64, half_h: f64 },
    /// Half-extents of the view volume in world units.
    Orthographic { half_w: f64, half_h: f64 },
}

/// Errors in a camera description.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum CameraError {
    /// `--camera INDEX` names a camera the scene does not have.
    #[error("camera {index} does not exist (the scene has {count} camera(s))")]
    NoSuchCamera {
        /// Requested index.
        index: usize,
        /// Cameras in the scene.
        count: usize,
    },
    /// `--camera INDEX` names a camera of the file that no node of the scene places.
    #[error("camera {index} is placed by no node of the scene")]
    NotPlaced {
        /// Requested index.
        index: usize,
    },
    /// Eye equals target, up is parallel to the view direction, or a value is not finite.
    #[error("degenerate camera: {0}")]
    Degenerate(&'static str),
    /// The field of view is outside (0, 180) degrees.
    #[error("field of view {0} degrees is outside (0, 180)")]
    BadFov(f64),
}

/// [`CameraError::Degenerate`]'s reason when the eye is the target: a caller that names
/// the input at fault (the service's `field`) tells it from the others by this.
pub const EYE_AT_TARGET: &str = "eye equals target";

fn sub(a: [f64; 3], b: [f64; 3]) -> [f64; 3] {
    [a[0] - b[0], a[1] - b[1], a[2] - b[2]]
}

fn cross(a: [f64; 3], b: [f64; 3]) -> [f64; 3] {
    [
        a[1] * b[2] - a[2] * b[1],
        a[2] * b[0] - a[0] * b[2],
        a[0] * b[1] - a[1] * b[0],
    ]
}

fn dot(a: [f64; 3], b: [f64; 3]) -> f64 {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}

fn norm(v: [f64; 3]) -> f64 {
    dot(v, v).sqrt()
}

/// `v` divided by its length `l` (from [`norm`]), where that is a positive number.
fn unit_from(v: [f64; 3], l: f64) -> Option<[f64; 3]> {
    (l > 0.0 && l.is_finite()).then(|| [v[0] / l, v[1] / l, v[2] / l])
}

/// `v` made unit length; `None` for a zero or non-finite `v`. A vector whose length
/// overflows or underflows f64 (an `up` of `1e300, 1e300, 0` or `1e-300, 1e-300, 0`) is
/// scaled by its largest component first; others take the plain path, whose rounding
/// every rendered image depends on.
fn unit(v: [f64; 3]) -> Option<[f64; 3]> {
    unit_from(v, norm(v)).or_else(|| {
        let m = v.iter().fold(0.0f64, |m, x| m.max(x.abs()));
        if !(m > 0.0 && m.is_finite()) {
            return None;
        }
        let s = v.map(|x| x / m);
        unit_from(s, norm(s))
    })
}

impl ViewCamera {
    /// A perspective camera at `eye` looking at `target`, `fov_deg` the vertical field of
    /// view, for an image of the given aspect (width / height).
    pub fn look_at(
        eye: [f64; 3],
        target: [f64; 3],
        up: [f64; 3],
        fov_deg: f64,
        aspect: f64,
    ) -> Result<ViewCamera, CameraError> {
        if !(fov_deg > 0.0 && fov_deg < 180.0) {
            return Err(CameraError::BadFov(fov_deg));
        }
        if !eye.iter().chain(&target).chain(&up).all(|x| x.is_finite()) {
            return Err(CameraError::Degenerate("eye, target and up must be finite"));
        }
        // Camera rays are f32: an eye or target beyond its range would start them at
        // infinity.
        if !eye
            .iter()
            .chain(&target)
            .all(|x| x.abs() <= f32::MAX as f64)
        {
            return Err(CameraError::Degenerate(
                "eye and target must lie within f32's range (|x| <= 3.4e38), as rays do",
            ));
        }
        let forward = unit(sub(target, eye)).ok_or(CameraError::Degenerate(EYE_AT_TARGET))?;
        let right = unit(cross(forward, up)).ok_or(CameraError::Degenerate(
            "up is parallel to the view direction",
        ))?;
        let up = cross(right, forward);
        let half_h = (fov_deg.to_radians() * 0.5).tan();
        Ok(ViewCamera {
            eye,
            right,
            up,
            forward,
            kind: ViewKind::Perspective {
                half_w: half_h * aspect,
                half_h,
            },
            clip: NO_CLIP,
        })
    }

    /// The scene's glTF camera; `aspect` is used when the camera gives none (and always for
    /// the image plane's width, so pixels stay square).
    pub fn from_scene(camera: &Camera, aspect: f64) -> Result<ViewCamera, CameraError> {
        let m = camera.to_world;
        let col = |c: usize| [m[c][0], m[c][1], m[c][2]];
        let right = unit(col(0)).ok_or(CameraError::Degenerate("camera transform is singular"))?;
        let up = unit(col(1)).ok_or(CameraError::Degenerate("camera transform is singular"))?;
        let back = unit(col(2)).ok_or(CameraError::Degenerate("camera transform is singular"))?;
        let kind = match camera.projection {
            Projection::Perspective { yfov, .. } => {
                if !(yfov > 0.0 && yfov < std::f64::consts::PI) {
                    return Err(CameraError::BadFov(yfov.to_degrees()));
                }
                let half_h = (yfov * 0.5).tan();
                ViewKind::Perspective {
                    half_w: half_h * aspect,
                    half_h,
                }
            }
            Projection::Orthographic { ymag, .. } => ViewKind::Orthographic {
                half_w: ymag.abs() * aspect,
                half_h: ymag.abs(),
            },
        };
        Ok(ViewCamera {
            eye: col(3),
            right,
            up,
            forward: [-back[0], -back[1], -back[2]],
            kind,
            clip: camera.clip,
        })
    }

    /// A default view that frames `bounds`: looking at its centre from the front-right and a
    /// little above (direction `(0.55, 0.35, 1)`), up +Y, 45° vertical field of view, far
    /// enough that the bounding sphere fits with 5 % margin in the narrower of the image's
    /// two fields of view (a portrait image's is the horizontal one). The sphere is the
    /// scene's at any size: only one too small for the centre's f32 precision (or empty) is
    /// widened, to a millionth of the centre's largest coordinate.
    pub fn framing(bounds: &Aabb, aspect: f64) -> ViewCamera {
        let c = bounds.center().map(f64::from);
        let far = c.iter().fold(0.0f64, |m, x| m.max(x.abs()));
        let radius = (0.5 * bounds.diagonal() as f64).max(far * 1e-6);
        let radius = if radius > 0.0 && radius.is_finite() {
            radius
        } else {
            1e-3
        };
        let fov: f64 = 45.0;
        let half_v = fov.to_radians() * 0.5;
        let half_h = (half_v.tan() * aspect).atan();
        let dist = radius / half_v.min(half_h).sin() * 1.05;
        let dir = unit([0.55, 0.35, 1.0]).expect("constant is not zero");
        let eye = [
            c[0] + dir[0] * dist,
            c[1] + dir[1] * dist,
            c[2] + dir[2] * dist,
        ];
        ViewCamera::look_at(eye, c, [0.0, 1.0, 0.0], fov, aspect)
            .expect("framing camera is never degenerate")
    }

    /// The camera `choice` names for `scene`, for an image of the given aspect.
    pub fn choose(
        choice: &CameraChoice,
        scene: &Scene,
        aspect: f64,
    ) -> Result<ViewCamera, CameraError> {
        ViewCamera::choose_from(choice, &scene.cameras, scene.bounds(), aspect)
    }

    /// The camera `choice` names among `cameras`, framing `bounds` by default.
    pub fn choose_from(
        choice: &CameraChoice,
        cameras: &[Option<Camera>],
        bounds: Option<Aabb>,
        aspect: f64,
    ) -> Result<ViewCamera, CameraError> {
        match choice {
            CameraChoice::Scene(index) => {
                let cam = cameras.get(*index).ok_or(CameraError::NoSuchCamera {
                    index: *index,
                    count: cameras.len(),
                })?;
                let cam = cam
                    .as_ref()
                    .ok_or(CameraError::NotPlaced { index: *index })?;
                ViewCamera::from_scene(cam, aspect)
            }
            CameraChoice::LookAt {
                eye,
                target,
                up,
                fov,
            } => ViewCamera::look_at(*eye, *target, *up, *fov, aspect),
            CameraChoice::Auto => match bounds {
                Some(b) => Ok(ViewCamera::framing(&b, aspect)),
                None => {
                    ViewCamera::look_at([0.0, 0.0, 1.0], [0.0; 3], [0.0, 1.0, 0.0], 45.0, aspect)
                }
            },
        }
    }

    /// The pixels of a `width` × `height` image whose camera rays may reach `bounds`: every
    /// ray through a pixel outside misses every triangle inside, so a renderer can give
    /// that pixel what a miss gives without making or tracing its rays. The box's corners
    /// are projected onto the image plane and the rectangle around them is widened by
    /// [`RECT_MARGIN`] pixels, and the box by a relative [`RECT_PAD`], which covers the
    /// rays' rounding to f32 many times over. Where a corner lies on or behind the eye's
    /// plane (a perspective camera inside or beside the box), or anything is not finite,
    /// the whole image.
    pub fn pixel_rect(&self, bounds: &Aabb, width: u32, height: u32) -> PixelRect {
        let full = PixelRect::full(width, height);
        if bounds.is_empty() {
            return PixelRect::EMPTY;
        }
        let (lo, hi) = (bounds.min.map(f64::from), bounds.max.map(f64::from));
        let scale = self.eye.iter().fold(
            f64::from(bounds.max_abs().max(bounds.diagonal())),
            |m, e| m.max(e.abs()),
        );
        let pad = RECT_PAD * scale;
        let (half_w, half_h, perspective) = match self.kind {
            ViewKind::Perspective { half_w, half_h } => (half_w, half_h, true),
            ViewKind::Orthographic { half_w, half_h } => (half_w, half_h, false),
        };
        let dot = |a: [f64; 3], b: [f64; 3]| a[0] * b[0] + a[1] * b[1] + a[2] * b[2];
        let (mut x_lo, mut x_hi) = (f64::INFINITY, f64::NEG_INFINITY);
        let (mut y_lo, mut y_hi) = (f64::INFINITY, f64::NEG_INFINITY);
        for corner in 0..8 {
            let c: [f64; 3] = std::array::from_fn(|k| {
                if corner >> k & 1 == 0 {
                    lo[k] - pad
                } else {
                    hi[k] + pad
                }
            });
            let d = sub(c, self.eye);
            let (a, b) = if perspective {
                let z = dot(d, self.forward);
                // On or behind the eye's plane, or NaN: the whole image.
                if z.partial_cmp(&(1e-9 * norm(d))) != Some(std::cmp::Ordering::Greater) {
                    return full;
                }
                (dot(d, self.right) / z, dot(d, self.up) / z)
            } else {
                (dot(d, self.right), dot(d, self.up))
            };
            // The inverse of `rays`' mapping from pixels to the image plane.
            let x = (a / half_w + 1.0) * 0.5 * f64::from(width);
            let y = (1.0 - b / half_h) * 0.5 * f64::from(height);
            x_lo = x_lo.min(x);
            x_hi = x_hi.max(x);
            y_lo = y_lo.min(y);
            y_hi = y_hi.max(y);
        }
        if ![x_lo, x_hi, y_lo, y_hi].iter().all(|v| v.is_finite()) {
            return full;
        }
        // Pixel `i` covers [i, i + 1): the columns from the one holding `x_lo` to the
        // one holding `x_hi`, each side widened by the margin, then clipped to the image.
        let span = |lo: f64, hi: f64, n: u32| {
            let first = (lo.floor() - RECT_MARGIN).max(0.0);
            let last = (hi.floor() + RECT_MARGIN).min(f64::from(n) - 1.0);
            if first > last {
                (0, 0)
            } else {
                (first as u32, last as u32 + 1)
            }
        };
        let (x0, x1) = span(x_lo, x_hi, width);
        let (y0, y1) = span(y_lo, y_hi, height);
        if x0 == x1 || y0 == y1 {
            return PixelRect::EMPTY;
        }
        PixelRect { x0, x1, y0, y1 }
    }

    /// Where the camera is.
    pub fn eye(&self) -> [f64; 3] {
        self.eye
    }

    /// The primary ray through image position `(x, y)` in pixels (x right, y down, pixel
    /// centres at +0.5) of a `width` × `height` image; unit direction, `[0, inf]`.
    #[inline]
    pub fn ray(&self, x: f64, y: f64, width: u32, height: u32) -> Ray {
        self.rays(&[x], &[y], width, height)[0]
    }

    /// The ray cone of a pixel of an image `height` pixels high: its width at the eye and
    /// its spread angle (radians) — an angle for a perspective camera, a width for an
    /// orthographic one. What texture lookups filter over ([`super::mipmap`]).
    pub fn pixel_cone(&self, height: u32) -> (f32, f32) {
        let h = f64::from(height.max(1));
        match self.kind {
            ViewKind::Perspective { half_h, .. } => (0.0, (2.0 * half_h / h) as f32),
            ViewKind::Orthographic { half_h, .. } => ((2.0 * half_h / h) as f32, 0.0),
        }
    }

    /// [`ViewCamera::ray`] of `N` image positions, each lane computed exactly as a lone
    /// ray is, but stage by stage across the lanes, so that the rays' latency chains (two
    /// divisions, then a square root and three more divisions, each waiting on the last)
    /// overlap. One at a time, a path render's camera rays cost about 140 cycles each,
    /// most of them waiting on that chain; [`RAYS_AT_ONCE`] at a time they overlap.
    pub fn rays<const N: usize>(
        &self,
        x: &[f64; N],
        y: &[f64; N],
        width: u32,
        height: u32,
    ) -> [Ray; N] {
        let (w, h) = (width as f64, height as f64);
        let (half_w, half_h) = match self.kind {
            ViewKind::Perspective { half_w, half_h } => (half_w, half_h),
            ViewKind::Orthographic { half_w, half_h } => (half_w, half_h),
        };
        // Plain loops over the lanes rather than `std::array::from_fn`, whose closures the
        // compiler sometimes leaves out of line: sixteen calls per group of rays.
        let (mut a, mut b) = ([0.0f64; N], [0.0f64; N]);
        for i in 0..N {
            a[i] = (2.0 * x[i] / w - 1.0) * half_w;
            b[i] = (1.0 - 2.0 * y[i] / h) * half_h;
        }
        // The image-plane point: a direction from the eye, or an origin beside it.
        let mut p = [[0.0f64; 3]; N];
        let base = match self.kind {
            ViewKind::Perspective { .. } => self.forward,
            ViewKind::Orthographic { .. } => self.eye,
        };
        for i in 0..N {
            for k in 0..3 {
                p[i][k] = base[k] + a[i] * self.right[k] + b[i] * self.up[k];
            }
        }
        let mut out = [Ray::EMPTY; N];
        match self.kind {
            ViewKind::Perspective { .. } => {
                let mut l = [0.0f64; N];
                for i in 0..N {
                    l[i] = norm(p[i]);
                }
                let clipped = self.clip != NO_CLIP;
                for i in 0..N {
                    let d = unit_from(p[i], l[i]).unwrap_or(self.forward);
                    out[i] = ray(self.eye, d);
                    // The planes are at distances along the view axis: along this ray they
                    // are farther by 1 / cos of its angle to the axis.
                    if clipped {
                        let cos = dot(d, self.forward);
                        out[i].tmin = (self.clip[0] / cos) as f32;
                        out[i].tmax = (self.clip[1] / cos) as f32;
                    }
                }
            }
            ViewKind::Orthographic { .. } => {
                for i in 0..N {
                    out[i] = ray(p[i], self.forward);
                    out[i].tmin = self.clip[0] as f32;
                    out[i].tmax = self.clip[1] as f32;
                }
            }
        }
        out
    }
}

/// The clipping of a camera without planes: all of each ray.
const NO_CLIP: [f64; 2] = [0.0, f64::INFINITY];

/// A camera ray from `org` along `dir`, rounded once to f32.
#[inline(always)]
fn ray(org: [f64; 3], dir: [f64; 3]) -> Ray {
    Ray {
        org: [org[0] as f32, org[1] as f32, org[2] as f32],
        tmin: 0.0,
        dir: [dir[0] as f32, dir[1] as f32, dir[2] as f32],
        tmax: f32::INFINITY,
    }
}

/// Pixels by which [`ViewCamera::pixel_rect`] widens the projected box on every side.
const RECT_MARGIN: f64 = 2.0;
/// How much [`ViewCamera::pixel_rect`] grows the box, relative to the largest coordinate
/// in play (box, eye or diagonal): far more than f32 rounding moves a ray or a hit.
const RECT_PAD: f64 = 1e-4;

/// A rectangle of pixels: columns `x0..x1` of rows `y0..y1`.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct PixelRect {
    /// First column.
    pub x0: u32,
    /// One past the last column.
    pub x1: u32,
    /// First row.
    pub y0: u32,
    /// One past the last row.
    pub y1: u32,
}

impl PixelRect {
    /// No pixel.
    pub const EMPTY: PixelRect = PixelRect {
        x0: 0,
        x1: 0,
        y0: 0,
        y1: 0,
    };

    /// Every pixel of a `width` × `height` image.
    pub fn full(width: u32, height: u32) -> PixelRect {
        PixelRect {
            x0: 0,
            x1: width,
            y0: 0,
            y1: height,
        }
    }

    /// How many pixels it holds.
    pub fn len(&self) -> usize {
        (self.x1 - self.x0) as usize * (self.y1 - self.y0) as usize
    }

    /// Whether it holds no pixel.
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// The columns of row `y` inside it (an empty range where the row is outside).
    #[inline]
    pub fn columns(&self, y: u32) -> std::ops::Range<usize> {
        if (self.y0..self.y1).contains(&y) {
            self.x0 as usize..self.x1 as usize
        } else {
            0..0
        }
    }

    /// Whether pixel `(x, y)` is inside.
    #[inline]
    pub fn contains(&self, x: u32, y: u32) -> bool {
        (self.x0..self.x1).contains(&x) && (self.y0..self.y1).contains(&y)
    }

    /// How many of the first `index` pixels of a `width`-wide image, in row order, are
    /// inside.
    pub fn inside_before(&self, index: usize, width: usize) -> usize {
        if width == 0 || self.is_empty() {
            return 0;
        }
        let (y, x) = (index / width, index % width);
        let (x0, x1, y0, y1) = (
            self.x0 as usize,
            self.x1 as usize,
            self.y0 as usize,
            self.y1 as usize,
        );
        let rows = y.clamp(y0, y1) - y0;
        let part = if (y0..y1).contains(&y) {
            x.clamp(x0, x1) - x0
        } else {
            0
        };
        rows * (x1 - x0) + part
    }

    /// Where a run of pixels from `start` (row order, a `width`-wide image) that holds
    /// `count` pixels inside ends (exclusive): the index of the inside pixel after them.
    /// `None` where fewer than `count + 1` inside pixels lie at or after `start`: the run
    /// goes on to the image's end.
    pub fn end_after(&self, start: usize, count: usize, width: usize) -> Option<usize> {
        let k = self.inside_before(start, width) + count;
        if k >= self.len() {
            return None;
        }
        let cols = (self.x1 - self.x0) as usize;
        Some((self.y0 as usize + k / cols) * width + self.x0 as usize + k % cols)
    }
}

/// How many rays [`ViewCamera::rays`] makes at once.
pub const RAYS_AT_ONCE: usize = 8;

#[cfg(test)]
mod tests {
    use super::*;

    /// `inside_before` and `end_after` against counting pixel by pixel, for rectangles
    /// inside, at the edges of and empty within a 7 × 5 image.
    #[test]
    fn pixels_inside_are_counted_and_runs_end_where_they_should() {
        let (w, h) = (7u32, 5u32);
        let rects = [
            PixelRect::full(w, h),
            PixelRect::EMPTY,
            PixelRect {
                x0: 2,
                x1: 5,
                y0: 1,
                y1: 4,
            },
            PixelRect {
                x0: 0,
                x1: 1,
                y0: 4,
                y1: 5,
            },
            PixelRect {
                x0: 6,
                x1: 7,
                y0: 0,
                y1: 5,
            },
        ];
        let n = (w * h) as usize;
        for r in rects {
            let inside = |i: usize| r.contains(i as u32 % w, i as u32 / w);
            let before = |i: usize| (0..i).filter(|&j| inside(j)).count();
            for i in 0..=n {
                assert_eq!(r.inside_before(i, w as usize), before(i), "{r:?} {i}");
            }
            for start in 0..n {
                for count in 1..=r.len() + 1 {
                    let end = r.end_after(start, count, w as usize);
                    // The first index past `start` whose run holds `count` inside pixels,
                    // and holding one more would need the pixel at it.
                    let want =
                        (start + 1..n).find(|&e| before(e) - before(start) == count && inside(e));
                    assert_eq!(end, want, "{r:?} start {start} count {count}");
                }
            }
        }
    }

    /// An `up` whose length overflows or underflows f64 is a direction all the same; an
    /// eye beyond f32's range is refused for what it is, not as "eye equals target".
    #[test]
    fn extreme_but_valid_vectors_make_cameras_and_others_say_why_not() {
        let along_z = |up: [f64; 3]| ViewCamera::look_at([0.0, 0.0, 5.0], [0.0; 3], up, 45.0, 1.0);
        for up in [
            [1e300, 1e300, 0.0],
            [1e-300, 1e-300, 0.0],
            [0.0, 1e-320, 0.0],
        ] {
            let cam = along_z(up).unwrap_or_else(|e| panic!("{up:?}: {e}"));
            let u = cam.up;
            assert!(
                (norm(u) - 1.0).abs() < 1e-12 && u[2].abs() < 1e-12,
                "{up:?}: {u:?}"
            );
        }
        let ordinary = along_z([0.0, 1.0, 0.0]).unwrap();
        assert_eq!(ordinary.up, [0.0, 1.0, 0.0]);
        let far = ViewCamera::look_at([0.0, 0.0, 1e308], [0.0; 3], [0.0, 1.0, 0.0], 45.0, 1.0);
        match far {
            Err(CameraError::Degenerate(why)) => assert!(why.contains("f32's range"), "{why}"),
            other => panic!("{:?}", other.map(|_| ())),
        }
        match along_z([0.0, 0.0, 1e300]) {
            Err(CameraError::Degenerate(why)) => assert!(why.contains("parallel"), "{why}"),
            other => panic!("{:?}", other.map(|_| ())),
        }
    }

    /// Two perspective cameras: an ordinary one, and a wide one far from the origin.
    fn perspective_cameras() -> [ViewCamera; 2] {
        [
            ViewCamera::look_at(
                [0.3, -1.0, 5.0],
                [0.1, 0.2, -0.7],
                [0.0, 1.0, 0.0],
                37.0,
                1.3,
            )
            .unwrap(),
            ViewCamera::look_at([1e4, 2e-3, -7.0], [0.0; 3], [0.0, 0.0, 1.0], 120.0, 0.5).unwrap(),
        ]
    }

    #[test]
    fn rays_at_once_are_the_single_rays_bit_for_bit() {
        let cams = perspective_cameras();
        let mut rng = crate::render::rng::Pcg32::new(12345, 0);
        let mut next = || rng.next_f32() as f64;
        for cam in &cams {
            for _ in 0..200 {
                let x: [f64; RAYS_AT_ONCE] = std::array::from_fn(|_| next() * 641.0);
                let y: [f64; RAYS_AT_ONCE] = std::array::from_fn(|_| next() * 481.0);
                let many = cam.rays(&x, &y, 640, 480);
                for i in 0..RAYS_AT_ONCE {
                    let one = cam.ray(x[i], y[i], 640, 480);
                    assert_eq!(
                        bytemuck::bytes_of(&many[i]),
                        bytemuck::bytes_of(&one),
                        "lane {i}"
                    );
                }
            }
        }
    }

    /// Whether `ray` meets `b` at all (a slab test in f64, NaN counted as a meeting).
    fn meets(ray: &Ray, b: &Aabb) -> bool {
        let (mut t0, mut t1) = (f64::from(ray.tmin), f64::from(ray.tmax));
        for k in 0..3 {
            let (o, d) = (f64::from(ray.org[k]), f64::from(ray.dir[k]));
            let (lo, hi) = (f64::from(b.min[k]), f64::from(b.max[k]));
            if d == 0.0 {
                if o < lo || o > hi {
                    return false;
                }
                continue;
            }
            let (a, c) = ((lo - o) / d, (hi - o) / d);
            t0 = t0.max(a.min(c));
            t1 = t1.min(a.max(c));
        }
        t0.partial_cmp(&t1) != Some(std::cmp::Ordering::Greater)
    }

    #[test]
    fn no_ray_outside_the_pixel_rect_meets_the_box() {
        let ortho = Camera {
            to_world: [
                [0.0, 0.0, -1.0, 0.0],
                [0.0, 1.0, 0.0, 0.0],
                [1.0, 0.0, 0.0, 0.0],
                [9.0, 0.5, 0.2, 1.0],
            ],
            projection: Projection::Orthographic {
                xmag: 4.0,
                ymag: 3.0,
            },
            clip: NO_CLIP,
        };
        let [near, far] = perspective_cameras();
        let cams = [
            near,
            far,
            ViewCamera::from_scene(&ortho, 640.0 / 480.0).unwrap(),
        ];
        let boxes = [
            Aabb {
                min: [-0.5, -0.2, -1.0],
                max: [0.4, 0.3, -0.6],
            },
            Aabb {
                min: [-30.0, -1.0, -2.0],
                max: [-29.0, 1.0, 2.0],
            },
            Aabb {
                min: [1.0, 1.0, 1.0],
                max: [1.0, 1.0, 1.0],
            },
        ];
        let (w, h) = (160, 120);
        let mut rng = crate::render::rng::Pcg32::new(777, 1);
        let mut culled = 0;
        for cam in &cams {
            for b in &boxes {
                let rect = cam.pixel_rect(b, w, h);
                for y in 0..h {
                    for x in 0..w {
                        if rect.contains(x, y) {
                            continue;
                        }
                        culled += 1;
                        // The pixel's corners and a few points inside.
                        for k in 0..6 {
                            let (jx, jy) = match k {
                                0 => (0.0, 0.0),
                                1 => (0.999_999, 0.999_999),
                                _ => (rng.next_f32() as f64, rng.next_f32() as f64),
                            };
                            let r = cam.ray(f64::from(x) + jx, f64::from(y) + jy, w, h);
                            assert!(!meets(&r, b), "{cam:?} {b:?} pixel {x},{y} {rect:?}");
                        }
                    }
                }
            }
        }
        assert!(culled > 0);
        // A small box in the middle of the view: a small rectangle around the middle.
        let cam =
            ViewCamera::look_at([0.0, 0.0, 10.0], [0.0; 3], [0.0, 1.0, 0.0], 45.0, 1.0).unwrap();
        let small = Aabb {
            min: [-0.5; 3],
            max: [0.5; 3],
        };
        let rect = cam.pixel_rect(&small, 200, 200);
        assert!(rect.contains(100, 100) && rect.x1 - rect.x0 < 40 && rect.y1 - rect.y0 < 40);
        // The eye inside the box, or the box behind it: every pixel.
        let around = Aabb {
            min: [-20.0; 3],
            max: [20.0; 3],
        };
        assert_eq!(cam.pixel_rect(&around, 200, 200), PixelRect::full(200, 200));
        let behind = Aabb {
            min: [-1.0, -1.0, 11.0],
            max: [1.0, 1.0, 12.0],
        };
        assert_eq!(cam.pixel_rect(&behind, 200, 200), PixelRect::full(200, 200));
        // Off to the side: no pixel.
        let aside = Aabb {
            min: [100.0, -1.0, -1.0],
            max: [101.0, 1.0, 1.0],
        };
        assert_eq!(cam.pixel_rect(&aside, 200, 200), PixelRect::EMPTY);
        assert_eq!(cam.pixel_rect(&Aabb::EMPTY, 200, 200), PixelRect::EMPTY);
    }

    #[test]
    fn look_at_centre_ray_points_at_target() {
        let cam =
            ViewCamera::look_at([0.0, 0.0, 5.0], [0.0; 3], [0.0, 1.0, 0.0], 60.0, 1.5).unwrap();
        let r = cam.ray(50.0, 50.0, 100, 100);
        assert_eq!(r.org, [0.0, 0.0, 5.0]);
        assert!((r.dir[2] + 1.0).abs() < 1e-6 && r.dir[0].abs() < 1e-6);
        // Top-left pixel goes left and up.
        let r = cam.ray(0.0, 0.0, 100, 100);
        assert!(r.dir[0] < 0.0 && r.dir[1] > 0.0);
        // Vertical half angle is 30°.
        let r = cam.ray(50.0, 0.0, 100, 100);
        assert!((r.dir[1] / -r.dir[2] - (30f32).to_radians().tan()).abs() < 1e-5);
    }

    #[test]
    fn degenerate_inputs_are_errors() {
        let e = ViewCamera::look_at([1.0; 3], [1.0; 3], [0.0, 1.0, 0.0], 45.0, 1.0);
        assert!(matches!(e, Err(CameraError::Degenerate(_))));
        let e = ViewCamera::look_at([0.0; 3], [0.0, 1.0, 0.0], [0.0, 1.0, 0.0], 45.0, 1.0);
        assert!(matches!(e, Err(CameraError::Degenerate(_))));
        let e = ViewCamera::look_at([0.0; 3], [0.0, 0.0, 1.0], [0.0, 1.0, 0.0], 180.0, 1.0);
        assert!(matches!(e, Err(CameraError::BadFov(_))));
    }

    #[test]
    fn gltf_camera_looks_down_minus_z() {
        let cam = Camera {
            to_world: [
                [1.0, 0.0, 0.0, 0.0],
                [0.0, 1.0, 0.0, 0.0],
                [0.0, 0.0, 1.0, 0.0],
                [1.0, 2.0, 3.0, 1.0],
            ],
            projection: Projection::Perspective {
                yfov: 0.8,
                aspect: None,
            },
            clip: NO_CLIP,
        };
        let v = ViewCamera::from_scene(&cam, 1.0).unwrap();
        let r = v.ray(0.5, 0.5, 1, 1);
        assert_eq!(r.org, [1.0, 2.0, 3.0]);
        assert_eq!(r.dir, [0.0, 0.0, -1.0]);
        assert_eq!((r.tmin, r.tmax), (0.0, f32::INFINITY));
        // Clipping planes are distances along the view axis: a ray at an angle θ to it
        // meets them 1 / cos θ farther along itself.
        let clipped = ViewCamera::from_scene(
            &Camera {
                clip: [0.5, 20.0],
                ..cam
            },
            1.0,
        )
        .unwrap();
        let r = clipped.ray(0.5, 0.5, 1, 1);
        assert_eq!((r.tmin, r.tmax), (0.5, 20.0));
        let r = clipped.ray(0.0, 0.5, 1, 1);
        let cos = -f64::from(r.dir[2]);
        assert!(cos < 0.95);
        assert!((f64::from(r.tmin) - 0.5 / cos).abs() < 1e-6, "{r:?}");
        assert!((f64::from(r.tmax) - 20.0 / cos).abs() < 1e-4, "{r:?}");
        let ortho = ViewCamera::from_scene(
            &Camera {
                projection: Projection::Orthographic {
                    xmag: 1.0,
                    ymag: 1.0,
                },
                clip: [0.5, 20.0],
                ..cam
            },
            1.0,
        )
        .unwrap();
        let r = ortho.ray(0.0, 0.5, 1, 1);
        assert_eq!((r.tmin, r.tmax), (0.5, 20.0));
    }

    /// The angle (radians) between the view's axis and the direction to `p`, and the
    /// half-angle of the image's narrower field of view.
    fn off_axis(cam: &ViewCamera, p: [f64; 3], w: u32, h: u32) -> (f64, f64) {
        let axis = cam.ray(f64::from(w) / 2.0, f64::from(h) / 2.0, w, h).dir;
        let edge_x = cam.ray(0.0, f64::from(h) / 2.0, w, h).dir;
        let edge_y = cam.ray(f64::from(w) / 2.0, 0.0, w, h).dir;
        let angle =
            |a: [f32; 3], b: [f64; 3]| (dot(a.map(f64::from), b) / norm(b)).clamp(-1.0, 1.0).acos();
        let e = cam.eye();
        let to_p = [p[0] - e[0], p[1] - e[1], p[2] - e[2]];
        let half = |d: [f32; 3]| angle(axis, d.map(f64::from));
        (angle(axis, to_p), half(edge_x).min(half(edge_y)))
    }

    #[test]
    fn framing_fits_the_bounds_in_portrait_and_at_any_size() {
        for (w, h) in [(100, 100), (20, 100), (100, 20)] {
            let mut shares = Vec::new();
            for scale in [1e-5f32, 1e-3, 1.0, 1e3] {
                let b = Aabb {
                    min: [0.0, 0.0, 0.0],
                    max: [scale, scale, scale],
                };
                let cam = ViewCamera::framing(&b, f64::from(w) / f64::from(h));
                // Every corner of the box lies inside the narrower field of view.
                let mut widest: f64 = 0.0;
                for k in 0..8 {
                    let corner = [0, 1, 2].map(|a| {
                        if k >> a & 1 == 1 {
                            f64::from(scale)
                        } else {
                            0.0
                        }
                    });
                    let (off, half) = off_axis(&cam, corner, w, h);
                    assert!(
                        off < half,
                        "{scale} {w}x{h}: corner {k} at {off}, edge at {half}"
                    );
                    widest = widest.max(off / half);
                }
                shares.push(widest);
            }
            // The same share of the view at every size.
            let first = shares[0];
            assert!(
                shares.iter().all(|a| (a - first).abs() < 1e-3),
                "{w}x{h}: {shares:?}"
            );
        }
    }

    #[test]
    fn framing_sees_the_box_centre() {
        let b = Aabb {
            min: [-1.0, 0.0, -2.0],
            max: [3.0, 1.0, 2.0],
        };
        let cam = ViewCamera::framing(&b, 1.0);
        let r = cam.ray(0.5, 0.5, 1, 1);
        let c = b.center();
        let to_c = [c[0] - r.org[0], c[1] - r.org[1], c[2] - r.org[2]];
        let l = crate::geometry::dot(to_c, to_c).sqrt();
        assert!((crate::geometry::dot(to_c, r.dir) / l - 1.0).abs() < 1e-5);
    }
}
