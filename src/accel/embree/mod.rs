//! The `embree` peer: Intel Embree 3 (Debian's `libembree3`) behind [`Intersector`].
//!
//! Embree is the yardstick the home-grown cores are measured against, so it runs in the
//! configuration Embree itself recommends for single incoherent rays: one triangle geometry,
//! `rtcIntersect1`/`rtcOccluded1` per ray, flush-to-zero and denormals-are-zero set on the
//! tracing threads. It is a *peer*, not a reference: it keeps Embree's own interval rule
//! (a hit needs `tnear < t <= tfar`, so a hit exactly at `tmin` is not reported) and its own
//! tie order between triangles at equal t; `precision` is ignored because Embree has a
//! single triangle test in this configuration.
//!
//! The binding is a hand-written FFI (the private `ffi` module) to keep the dependency
//! surface at one system library. This module is the only place in the crate besides the
//! SIMD layer that may use `unsafe`; every block says why it is sound.
//!
//! Threads: `BuildOptions::threads` becomes Embree's `threads=N` device option, which bounds
//! the build (measured: a 300k-triangle HIGH build uses 1.00 CPU-seconds per wall-second
//! with `threads=1` and 1.97 with `threads=2` on two cores). Debian's Embree schedules with
//! TBB, whose thread limits are process-wide, so devices alive at the same time with
//! different limits may affect each other's build parallelism (never their results).
//! Tracing runs on the caller's rayon pool like every other core.

#![allow(unsafe_code)]

mod ffi;

use std::ffi::{c_char, c_void, CStr, CString};
use std::ptr::NonNull;
use std::sync::atomic::{AtomicIsize, Ordering};
use std::sync::Mutex;

use rayon::prelude::*;

use super::{AccelError, BuildOptions, BuildQuality, Intersector, Query};
use crate::geometry::{Hit, Ray, Triangle};

/// Rays per rayon task. Each task pays for one MXCSR save/set/restore and one context;
/// 256 single-ray traversals (tens of microseconds) make that negligible while leaving
/// enough tasks for work stealing to even out incoherent batches.
const CHUNK: usize = 256;

/// A committed Embree scene over the triangles it was built from, ready to trace from any
/// thread.
///
/// Field order is drop order: the scene goes before the device that made it, and the
/// callback state outlives both because Embree may call back while releasing them.
pub struct Embree {
    /// The triangle geometry and its vertex buffer, for refits (`None` for an empty
    /// scene). Released before the scene (which holds its own reference).
    mesh: Option<Mesh>,
    scene: SceneHandle,
    /// Held only to be released after the scene (Embree also keeps the device alive
    /// through the scene's own reference; owning it makes the order explicit).
    _device: DeviceHandle,
    state: Box<DeviceState>,
    /// Triangles given, for the fallback byte estimate and the refit's count check.
    triangles: usize,
}

/// The geometry attached to the scene and the vertex buffer Embree allocated for it.
struct Mesh {
    geometry: GeometryHandle,
    /// `9·T` f32, owned by the geometry (alive while `geometry` is).
    vertices: NonNull<f32>,
}

// SAFETY: `Embree` holds raw Embree handles (and a pointer into a buffer the geometry owns,
// written only through `&mut self` in `refit`). Embree objects are reference-counted with
// atomic counters and may be released from any thread, so moving the owner is sound (Send).
// After `rtcCommitScene` returns, the scene is immutable and Embree documents
// `rtcIntersect1`/`rtcOccluded1` as safe to call concurrently from any number of threads on
// it (each call has its own context and ray record, which live on the caller's stack);
// nothing reachable through `&Embree` mutates the scene, so sharing references is sound
// (Sync). `DeviceState` is atomics and a mutex, Sync by construction.
unsafe impl Send for Embree {}
// SAFETY: see the `Send` impl above.
unsafe impl Sync for Embree {}

/// What Embree's callbacks write: shared with the device through a user pointer, so it lives
/// in a `Box` whose address stays fixed while the device exists.
#[derive(Default)]
struct DeviceState {
    /// Bytes the device holds now, summed from the memory monitor (frees are negative).
    bytes: AtomicIsize,
    /// The message of the first error since the last [`DeviceState::take_message`].
    message: Mutex<Option<String>>,
}

impl DeviceState {
    fn take_message(&self) -> Option<String> {
        self.message
            .lock()
            .unwrap_or_else(|poisoned| poisoned.into_inner())
            .take()
    }
}

/// Embree's error callback: keeps the first message until it is reported.
///
/// # Safety
/// `user_ptr` must point at a live `DeviceState`; `message` must be null or a C string.
unsafe extern "C" fn on_error(user_ptr: *mut c_void, _code: ffi::RTCError, message: *const c_char) {
    if user_ptr.is_null() || message.is_null() {
        return;
    }
    // SAFETY: the caller (Embree) passes back the pointer registered in `Embree::new`, a
    // `Box<DeviceState>` that outlives the device; `message` is a NUL-terminated string
    // valid for the duration of the call.
    let (state, text) = unsafe {
        (
            &*(user_ptr as *const DeviceState),
            CStr::from_ptr(message).to_string_lossy(),
        )
    };
    let mut slot = state
        .message
        .lock()
        .unwrap_or_else(|poisoned| poisoned.into_inner());
    if slot.is_none() {
        *slot = Some(text.into_owned());
    }
}

/// Embree's memory monitor: keeps a running total; never refuses an allocation.
///
/// # Safety
/// `user_ptr` must point at a live `DeviceState`.
unsafe extern "C" fn on_memory(user_ptr: *mut c_void, bytes: isize, _post: bool) -> bool {
    if !user_ptr.is_null() {
        // SAFETY: as in `on_error`, the registered pointer to a `Box<DeviceState>` that
        // outlives the device.
        let state = unsafe { &*(user_ptr as *const DeviceState) };
        state.bytes.fetch_add(bytes, Ordering::Relaxed);
    }
    true
}

/// Owns one device reference.
struct DeviceHandle(NonNull<ffi::RTCDeviceTy>);

impl Drop for DeviceHandle {
    fn drop(&mut self) {
        // SAFETY: the handle came from a successful `rtcNewDevice` and this is its only
        // release; scenes and geometries made from it hold their own references.
        unsafe { ffi::rtcReleaseDevice(self.0.as_ptr()) }
    }
}

/// Owns one scene reference.
struct SceneHandle(NonNull<ffi::RTCSceneTy>);

impl Drop for SceneHandle {
    fn drop(&mut self) {
        // SAFETY: the handle came from a successful `rtcNewScene` and this is its only
        // release; no trace can be running, since tracing borrows the owner.
        unsafe { ffi::rtcReleaseScene(self.0.as_ptr()) }
    }
}

/// Owns one geometry reference (the scene takes its own on attach).
struct GeometryHandle(NonNull<ffi::RTCGeometryTy>);

impl Drop for GeometryHandle {
    fn drop(&mut self) {
        // SAFETY: the handle came from a successful `rtcNewGeometry` and this is its only
        // release.
        unsafe { ffi::rtcReleaseGeometry(self.0.as_ptr()) }
    }
}

/// Embree's build quality for the contract's `build`.
fn quality(q: BuildQuality) -> ffi::RTCBuildQuality {
    match q {
        BuildQuality::Fast => ffi::RTC_BUILD_QUALITY_LOW,
        BuildQuality::Sah => ffi::RTC_BUILD_QUALITY_MEDIUM,
        BuildQuality::Sbvh => ffi::RTC_BUILD_QUALITY_HIGH,
    }
}

/// The device option string for `threads` (0: Embree's default, every core).
fn device_config(threads: usize) -> String {
    if threads == 0 {
        String::new()
    } else {
        format!("threads={threads}")
    }
}

fn backend(message: String) -> AccelError {
    AccelError::Backend {
        accel: "embree",
        message,
    }
}

/// Embree's pending error on `device` (with the message its callback left in `state`), as
/// the error of the call `what`; Ok when there is none.
fn pending_error(device: &DeviceHandle, state: &DeviceState, what: &str) -> Result<(), AccelError> {
    // SAFETY: `device` is live for as long as its handle exists.
    let code = unsafe { ffi::rtcGetDeviceError(device.0.as_ptr()) };
    let message = state.take_message();
    if code == ffi::RTC_ERROR_NONE && message.is_none() {
        return Ok(());
    }
    let mut text = format!("{what} failed: {}", ffi::error_name(code));
    if let Some(m) = message {
        text.push_str(": ");
        text.push_str(&m);
    }
    Err(backend(text))
}

/// The error of a call that returned null: Embree's pending error if it set one.
fn failed(checked: Result<(), AccelError>, what: &str) -> AccelError {
    match checked {
        Err(e) => e,
        Ok(()) => backend(format!("{what} returned null")),
    }
}

impl Embree {
    /// Builds a committed scene of one triangle geometry whose primitive ids are the
    /// triangle ids, on a new device limited to `options.threads` threads (0: all).
    ///
    /// The triangles are copied into Embree-owned buffers, so `triangles` need not outlive
    /// the result. Fails with [`AccelError::Backend`] when Embree does, naming the error
    /// code and the call that raised it.
    pub fn new(triangles: &[Triangle], options: &BuildOptions) -> Result<Embree, AccelError> {
        Embree::with_config(triangles, options, &device_config(options.threads))
    }

    /// [`Embree::new`] with a raw device option string (tests use it to reach the error
    /// path of device creation).
    fn with_config(
        triangles: &[Triangle],
        options: &BuildOptions,
        config: &str,
    ) -> Result<Embree, AccelError> {
        let config = CString::new(config)
            .map_err(|_| backend("device configuration contains a NUL byte".into()))?;
        // Index buffers are u32; one vertex per corner keeps the vertex buffer a plain copy
        // of the TRI1 layout, so 3·T must fit.
        let vertex_count = triangles
            .len()
            .checked_mul(3)
            .filter(|&n| u32::try_from(n).is_ok())
            .ok_or_else(|| {
                backend(format!(
                    "{} triangles exceed Embree's 32-bit vertex indices",
                    triangles.len()
                ))
            })?;

        // SAFETY: `config` is a NUL-terminated string that lives across the call.
        let raw = unsafe { ffi::rtcNewDevice(config.as_ptr()) };
        let device = match NonNull::new(raw) {
            Some(d) => DeviceHandle(d),
            None => {
                // SAFETY: with a null device, Embree returns the calling thread's error of
                // the failed device creation.
                let code = unsafe { ffi::rtcGetDeviceError(std::ptr::null_mut()) };
                return Err(backend(format!(
                    "rtcNewDevice(\"{}\") failed: {}",
                    config.to_string_lossy(),
                    ffi::error_name(code)
                )));
            }
        };
        let state = Box::<DeviceState>::default();
        let user_ptr = &*state as *const DeviceState as *mut c_void;
        // SAFETY: `device` is live; `user_ptr` points into `state`, which the returned
        // `Embree` keeps (and drops after the device); the callbacks match Embree's
        // signatures and touch only that state.
        unsafe {
            ffi::rtcSetDeviceErrorFunction(device.0.as_ptr(), Some(on_error), user_ptr);
            ffi::rtcSetDeviceMemoryMonitorFunction(device.0.as_ptr(), Some(on_memory), user_ptr);
        }
        let check = |what: &str| pending_error(&device, &state, what);

        // SAFETY: `device` is live.
        let scene = NonNull::new(unsafe { ffi::rtcNewScene(device.0.as_ptr()) })
            .map(SceneHandle)
            .ok_or_else(|| failed(check("rtcNewScene"), "rtcNewScene"))?;
        let q = quality(options.quality);
        // SAFETY: `scene` is live and not yet committed.
        unsafe { ffi::rtcSetSceneBuildQuality(scene.0.as_ptr(), q) };
        check("rtcSetSceneBuildQuality")?;

        // An empty scene has no geometry at all: Embree answers every ray with a miss, and a
        // triangle geometry with zero-sized buffers is not needed.
        let mut mesh = None;
        if !triangles.is_empty() {
            // SAFETY: `device` is live.
            let geometry = NonNull::new(unsafe {
                ffi::rtcNewGeometry(device.0.as_ptr(), ffi::RTC_GEOMETRY_TYPE_TRIANGLE)
            })
            .map(GeometryHandle)
            .ok_or_else(|| failed(check("rtcNewGeometry"), "rtcNewGeometry"))?;
            let g = geometry.0.as_ptr();
            // SAFETY: `g` is a live, uncommitted triangle geometry.
            unsafe { ffi::rtcSetGeometryBuildQuality(g, q) };

            // Vertex buffer: the triangles' corners in TRI1 order, 12-byte FLOAT3 items.
            // Embree over-allocates new vertex buffers so 16-byte loads of the last vertex
            // stay inside the allocation.
            // SAFETY: `g` is live; the stride is a multiple of 4 as Embree requires.
            let vertices = unsafe {
                ffi::rtcSetNewGeometryBuffer(
                    g,
                    ffi::RTC_BUFFER_TYPE_VERTEX,
                    0,
                    ffi::RTC_FORMAT_FLOAT3,
                    12,
                    vertex_count,
                )
            } as *mut f32;
            if vertices.is_null() {
                let what = "rtcSetNewGeometryBuffer(vertex)";
                return Err(failed(check(what), what));
            }
            // SAFETY: Embree returned a buffer of at least `vertex_count` 12-byte items,
            // aligned to at least 16 bytes, that nothing else references yet; `Triangle` is
            // `repr(C)` nine f32, so the triangles are exactly `9·T` contiguous f32.
            unsafe {
                std::ptr::copy_nonoverlapping(
                    triangles.as_ptr() as *const f32,
                    vertices,
                    vertex_count * 3,
                );
            }

            // SAFETY: as for the vertex buffer; UINT3 items are 12 bytes.
            let indices = unsafe {
                ffi::rtcSetNewGeometryBuffer(
                    g,
                    ffi::RTC_BUFFER_TYPE_INDEX,
                    0,
                    ffi::RTC_FORMAT_UINT3,
                    12,
                    triangles.len(),
                )
            } as *mut u32;
            if indices.is_null() {
                let what = "rtcSetNewGeometryBuffer(index)";
                return Err(failed(check(what), what));
            }
            // SAFETY: Embree returned room for `3·T` u32, suitably aligned and unaliased.
            let indices = unsafe { std::slice::from_raw_parts_mut(indices, vertex_count) };
            for (i, slot) in indices.iter_mut().enumerate() {
                // Fits: `vertex_count` was checked against u32 above.
                *slot = i as u32;
            }

            // SAFETY: `g` is live and its buffers are filled; attaching gives the scene its
            // own reference, so dropping `geometry` afterwards only drops ours.
            unsafe {
                ffi::rtcCommitGeometry(g);
                ffi::rtcAttachGeometry(scene.0.as_ptr(), g);
            }
            check("rtcCommitGeometry/rtcAttachGeometry")?;
            mesh = Some(Mesh {
                geometry,
                vertices: NonNull::new(vertices).expect("checked above"),
            });
        }

        // SAFETY: `scene` is live; this builds the BVH (on Embree's threads) and makes the
        // scene immutable and traceable from any thread.
        unsafe { ffi::rtcCommitScene(scene.0.as_ptr()) };
        check("rtcCommitScene")?;

        Ok(Embree {
            mesh,
            scene,
            _device: device,
            state,
            triangles: triangles.len(),
        })
    }

    /// Closest hit of one ray (Embree's rules), or the miss.
    #[inline]
    fn intersect(&self, context: &mut ffi::RTCIntersectContext, ray: &Ray) -> Hit {
        if !reaches_embree(ray) {
            return Hit::MISS;
        }
        let mut rayhit = ffi::RTCRayHit {
            ray: to_embree(ray),
            hit: ffi::RTCHit {
                prim_id: ffi::RTC_INVALID_GEOMETRY_ID,
                geom_id: ffi::RTC_INVALID_GEOMETRY_ID,
                inst_id: [ffi::RTC_INVALID_GEOMETRY_ID],
                ..Default::default()
            },
        };
        // SAFETY: the scene is committed and immutable (see the Sync impl); `context` and
        // `rayhit` are exclusively borrowed, properly initialised and 8/16-byte aligned as
        // the C structs demand (checked in `ffi`).
        unsafe { ffi::rtcIntersect1(self.scene.0.as_ptr(), context, &mut rayhit) };
        if rayhit.hit.geom_id == ffi::RTC_INVALID_GEOMETRY_ID {
            Hit::MISS
        } else {
            Hit {
                t: rayhit.ray.tfar,
                prim: rayhit.hit.prim_id,
                u: rayhit.hit.u,
                v: rayhit.hit.v,
            }
        }
    }

    /// Whether one ray hits anything in its interval (Embree's rules).
    #[inline]
    fn occluded1(&self, context: &mut ffi::RTCIntersectContext, ray: &Ray) -> bool {
        if !reaches_embree(ray) {
            return false;
        }
        let mut r = to_embree(ray);
        // SAFETY: as in `intersect`, with an `RTCRay` record.
        unsafe { ffi::rtcOccluded1(self.scene.0.as_ptr(), context, &mut r) };
        r.tfar == f32::NEG_INFINITY
    }
}

/// Embree's bound on coordinates (`FLT_LARGE`, 1.844e18): its ray check asserts that every
/// origin and direction component lies within it.
const EMBREE_LARGE: f32 = 1.844e18;

/// Whether `ray` may be handed to Embree: its interval holds some t and starts at 0 or
/// later, and its origin and direction pass Embree's own ray checks (`RayK::valid` and
/// `tnear >= 0`, assertions in Debian's build, which abort the process). Other rays miss without reaching it: the contract calls them
/// invalid, and a library caller who did not validate still gets an answer, as from every
/// core.
#[inline]
fn reaches_embree(ray: &Ray) -> bool {
    !empty_interval(ray)
        && ray.tmin >= 0.0
        && ray
            .org
            .iter()
            .chain(&ray.dir)
            .all(|c| c.abs() <= EMBREE_LARGE)
}

/// Whether `[tmin, tmax]` holds no t at all: `tmin > tmax`, `tmin = +inf`, or a NaN bound.
/// Such rays miss without reaching Embree, which documents no behaviour for them.
#[inline]
fn empty_interval(ray: &Ray) -> bool {
    #[allow(clippy::neg_cmp_op_on_partial_ord)] // NaN must count as empty
    let ordered = !(ray.tmin <= ray.tmax);
    ordered || ray.tmin == f32::INFINITY
}

/// The RAY1 record as Embree's: all geometry visible (mask all ones), time 0.
#[inline]
fn to_embree(ray: &Ray) -> ffi::RTCRay {
    ffi::RTCRay {
        org_x: ray.org[0],
        org_y: ray.org[1],
        org_z: ray.org[2],
        tnear: ray.tmin,
        dir_x: ray.dir[0],
        dir_y: ray.dir[1],
        dir_z: ray.dir[2],
        time: 0.0,
        tfar: ray.tmax,
        mask: u32::MAX,
        id: 0,
        flags: 0,
    }
}

impl Intersector for Embree {
    fn name(&self) -> &'static str {
        "embree"
    }

    /// Both queries use `rtcIntersect1`: `any` must report hit fields, which
    /// `rtcOccluded1` does not compute, and the closest hit is a valid any-hit.
    fn trace(&self, rays: &[Ray], _query: Query, hits: &mut [Hit]) {
        let n = rays.len().min(hits.len());
        hits[..n]
            .par_chunks_mut(CHUNK)
            .zip(rays[..n].par_chunks(CHUNK))
            .for_each(|(hits, rays)| {
                let _mxcsr = FlushDenormals::set();
                let mut context = ffi::RTCIntersectContext::new();
                for (hit, ray) in hits.iter_mut().zip(rays) {
                    *hit = self.intersect(&mut context, ray);
                }
            });
    }

    fn occluded(&self, rays: &[Ray], out: &mut [u8]) {
        let n = rays.len().min(out.len());
        out[..n]
            .par_chunks_mut(CHUNK)
            .zip(rays[..n].par_chunks(CHUNK))
            .for_each(|(out, rays)| {
                let _mxcsr = FlushDenormals::set();
                let mut context = ffi::RTCIntersectContext::new();
                for (o, ray) in out.iter_mut().zip(rays) {
                    *o = u8::from(self.occluded1(&mut context, ray));
                }
            });
    }

    /// What Embree's memory monitor says the device holds after the build: BVH nodes,
    /// Embree's triangle leaves and the vertex and index buffers (its own copy of the
    /// positions, which the scene's positions do not include). If the monitor saw nothing
    /// (it is Embree's own bookkeeping, not a guarantee), the buffers alone: 48 bytes per
    /// triangle.
    fn bytes(&self) -> usize {
        let monitored = self.state.bytes.load(Ordering::Relaxed);
        if monitored > 0 {
            monitored as usize
        } else {
            self.triangles * (36 + 12)
        }
    }

    /// Writes the new positions into Embree's vertex buffer and recommits, which
    /// rebuilds Embree's BVH at the build's quality; what this saves over a new
    /// `Embree` is device, scene and buffer setup. Setting the geometry's quality to
    /// `RTC_BUILD_QUALITY_REFIT` before the commit was tried and measured: on the static
    /// single-level scene this peer uses, the commit took as long as a build (dragon,
    /// 100k triangles: 79 ms vs 84 ms), so it is not done; Embree's refitting is meant
    /// for scenes made with `RTC_SCENE_FLAG_DYNAMIC`, whose different BVH would change
    /// what the peer traces with. Only another triangle count is refused. An Embree failure during the commit is an
    /// [`AccelError::Backend`] and leaves the scene unusable.
    fn refit(&mut self, triangles: &[Triangle]) -> Result<(), AccelError> {
        if triangles.len() != self.triangles {
            let reason = crate::accel::bvh::RefitError::Count {
                expected: self.triangles,
                got: triangles.len(),
            };
            return Err(AccelError::refit(self.name(), reason));
        }
        let Some(mesh) = &self.mesh else {
            return Ok(());
        };
        let g = mesh.geometry.0.as_ptr();
        // SAFETY: the vertex buffer holds `9·T` f32 (allocated for `3·T` FLOAT3 items by
        // `with_config`) and lives as long as the geometry, which `mesh` holds; `&mut self`
        // means no trace reads the scene meanwhile; `Triangle` is `repr(C)` nine f32 and
        // the count was checked above. The geometry is live, so the calls on it and on
        // the scene are valid; the commits rebuild and make the scene immutable again.
        unsafe {
            std::ptr::copy_nonoverlapping(
                triangles.as_ptr() as *const f32,
                mesh.vertices.as_ptr(),
                triangles.len() * 9,
            );
            ffi::rtcUpdateGeometryBuffer(g, ffi::RTC_BUFFER_TYPE_VERTEX, 0);
            ffi::rtcCommitGeometry(g);
            ffi::rtcCommitScene(self.scene.0.as_ptr());
        }
        let device = &self._device;
        pending_error(device, &self.state, "refit (rtcCommitScene)")
    }
}

/// Sets MXCSR's flush-to-zero and denormals-are-zero bits for the current thread, as Embree
/// asks of threads that trace, and restores the previous MXCSR when dropped so the rest of
/// rayd keeps IEEE denormals. A no-op off x86-64.
struct FlushDenormals {
    #[cfg(target_arch = "x86_64")]
    saved: u32,
}

/// MXCSR bit 15 (FZ) and bit 6 (DAZ).
#[cfg(target_arch = "x86_64")]
const FTZ_DAZ: u32 = (1 << 15) | (1 << 6);

#[cfg(target_arch = "x86_64")]
fn read_mxcsr() -> u32 {
    let mut value: u32 = 0;
    // SAFETY: `stmxcsr` stores the 4-byte MXCSR to the given address, which is a live,
    // aligned local; SSE is baseline on x86-64.
    unsafe {
        std::arch::asm!(
            "stmxcsr [{}]",
            in(reg) &mut value as *mut u32,
            options(nostack, preserves_flags)
        );
    }
    value
}

#[cfg(target_arch = "x86_64")]
fn write_mxcsr(value: u32) {
    // SAFETY: `ldmxcsr` loads MXCSR from a live local. Callers pass a value read from MXCSR
    // with at most the FZ and DAZ bits added, both defined on every x86-64 CPU, so no
    // reserved bit is set (which would fault).
    unsafe {
        std::arch::asm!(
            "ldmxcsr [{}]",
            in(reg) &value as *const u32,
            options(nostack, preserves_flags, readonly)
        );
    }
}

impl FlushDenormals {
    #[inline]
    fn set() -> FlushDenormals {
        #[cfg(target_arch = "x86_64")]
        {
            let saved = read_mxcsr();
            write_mxcsr(saved | FTZ_DAZ);
            FlushDenormals { saved }
        }
        #[cfg(not(target_arch = "x86_64"))]
        FlushDenormals {}
    }
}

impl Drop for FlushDenormals {
    #[inline]
    fn drop(&mut self) {
        #[cfg(target_arch = "x86_64")]
        write_mxcsr(self.saved);
    }
}

#[cfg(all(test, feature = "embree"))]
mod tests {
    use super::*;

    fn tri(v: [[f32; 3]; 3]) -> Triangle {
        Triangle { v }
    }

    fn ray(org: [f32; 3], dir: [f32; 3], tmin: f32, tmax: f32) -> Ray {
        Ray {
            org,
            tmin,
            dir,
            tmax,
        }
    }

    /// Distance in units in the last place between two finite f32 of the same sign.
    fn ulps(a: f32, b: f32) -> u32 {
        a.to_bits().abs_diff(b.to_bits())
    }

    #[test]
    fn context_matches_rtc_init_intersect_context() {
        let c = ffi::RTCIntersectContext::new();
        assert_eq!(c.flags, 0);
        assert!(c.filter.is_none());
        assert_eq!(c.inst_id, [u32::MAX]);
    }

    #[test]
    fn error_names_follow_the_header() {
        assert_eq!(
            ffi::error_name(ffi::RTC_ERROR_INVALID_ARGUMENT),
            "RTC_ERROR_INVALID_ARGUMENT"
        );
        assert_eq!(ffi::error_name(99), "unknown RTCError code");
    }

    #[cfg(target_arch = "x86_64")]
    #[test]
    fn flush_denormals_is_scoped() {
        let before = read_mxcsr();
        {
            let _g = FlushDenormals::set();
            assert_eq!(read_mxcsr() & FTZ_DAZ, FTZ_DAZ);
            // With DAZ the smallest denormal reads as zero.
            let tiny = std::hint::black_box(f32::from_bits(1));
            assert_eq!(std::hint::black_box(tiny * 1.0), 0.0);
        }
        assert_eq!(read_mxcsr(), before);
        let tiny = std::hint::black_box(f32::from_bits(1));
        assert_ne!(std::hint::black_box(tiny * 1.0), 0.0);
    }

    #[test]
    fn bad_device_config_is_a_backend_error() {
        let err = Embree::with_config(&[], &BuildOptions::default(), "threads=notanumber")
            .err()
            .expect("Embree must refuse the option");
        let text = err.to_string();
        assert!(text.starts_with("embree: rtcNewDevice"), "{text}");
        assert!(text.contains("RTC_ERROR_"), "{text}");
    }

    #[test]
    fn device_errors_carry_code_and_message() {
        // Declared before the device so that it is dropped after it, even on a panic.
        let state = Box::<DeviceState>::default();
        // SAFETY: a null config asks for Embree's defaults.
        let device = DeviceHandle(
            NonNull::new(unsafe { ffi::rtcNewDevice(std::ptr::null()) }).expect("device"),
        );
        let user_ptr = &*state as *const DeviceState as *mut c_void;
        // SAFETY: as in `Embree::with_config`; `state` outlives `device` (drop order).
        unsafe { ffi::rtcSetDeviceErrorFunction(device.0.as_ptr(), Some(on_error), user_ptr) };
        assert!(pending_error(&device, &state, "nothing").is_ok());
        // 77 is no geometry type: Embree refuses it and reports through both channels.
        // SAFETY: `device` is live; an invalid type yields null, not UB.
        let g = unsafe { ffi::rtcNewGeometry(device.0.as_ptr(), 77) };
        assert!(g.is_null());
        let text = pending_error(&device, &state, "rtcNewGeometry")
            .unwrap_err()
            .to_string();
        assert!(
            text.starts_with("embree: rtcNewGeometry failed: RTC_ERROR_"),
            "{text}"
        );
        assert!(
            text.len() > "embree: rtcNewGeometry failed: RTC_ERROR_X".len(),
            "{text}"
        );
        // The error was consumed.
        assert!(pending_error(&device, &state, "again").is_ok());
    }

    #[test]
    fn empty_intervals_never_reach_embree() {
        let r = |tmin, tmax| ray([0.0; 3], [1.0, 0.0, 0.0], tmin, tmax);
        assert!(empty_interval(&r(2.0, 1.0)));
        assert!(empty_interval(&r(f32::INFINITY, f32::INFINITY)));
        assert!(empty_interval(&r(0.0, f32::NAN)));
        assert!(!empty_interval(&r(1.0, 1.0)));
        assert!(!empty_interval(&r(0.0, f32::INFINITY)));
        // Coordinates Embree's ray check refuses (NaN fails every comparison).
        let mut bad = r(0.0, 1.0);
        assert!(reaches_embree(&bad));
        bad.org[1] = f32::NAN;
        assert!(!reaches_embree(&bad));
        bad.org[1] = 0.0;
        bad.dir[2] = f32::NEG_INFINITY;
        assert!(!reaches_embree(&bad));
        assert!(!reaches_embree(&r(-1.0, 1.0)));
    }

    #[test]
    fn monitor_counts_buffers_and_bvh() {
        let tris: Vec<Triangle> = (0..1000)
            .map(|i| {
                let x = i as f32;
                tri([[x, 0.0, 0.0], [x + 1.0, 0.0, 0.0], [x, 1.0, 0.0]])
            })
            .collect();
        let e = Embree::new(&tris, &BuildOptions::default()).unwrap();
        // At least the vertex and index buffers (48 bytes a triangle).
        assert!(e.bytes() >= 48 * 1000, "{}", e.bytes());
        assert!(e.state.bytes.load(Ordering::Relaxed) > 0);
    }

    #[test]
    fn empty_scene_misses() {
        let e = Embree::new(&[], &BuildOptions::default()).unwrap();
        let rays = [ray([0.0; 3], [0.0, 0.0, 1.0], 0.0, f32::INFINITY)];
        let mut hits = [Hit {
            t: 0.0,
            prim: 0,
            u: 1.0,
            v: 1.0,
        }];
        e.trace(&rays, Query::Closest, &mut hits);
        assert_eq!(hits[0], Hit::MISS);
        let mut occ = [7u8];
        e.occluded(&rays, &mut occ);
        assert_eq!(occ[0], 0);
    }

    #[test]
    fn one_triangle_through_the_ffi() {
        let e = Embree::new(
            &[tri([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])],
            &BuildOptions::default(),
        )
        .unwrap();
        let mut ctx = ffi::RTCIntersectContext::new();
        let h = e.intersect(
            &mut ctx,
            &ray([0.25, 0.5, -2.0], [0.0, 0.0, 1.0], 0.0, 10.0),
        );
        // Embree divides with an approximate reciprocal refined by one Newton step, so the
        // exact 2, 1/4, 1/2 come back within an ulp or two, not bit-exact.
        assert_eq!(h.prim, 0);
        assert!(ulps(h.t, 2.0) <= 2, "{h:?}");
        assert!(ulps(h.u, 0.25) <= 2 && ulps(h.v, 0.5) <= 2, "{h:?}");
        assert!(e.occluded1(
            &mut ctx,
            &ray([0.25, 0.5, -2.0], [0.0, 0.0, 1.0], 0.0, 10.0)
        ));
        assert!(!e.occluded1(&mut ctx, &ray([0.25, 0.5, -2.0], [0.0, 0.0, 1.0], 0.0, 1.5)));
    }
}
