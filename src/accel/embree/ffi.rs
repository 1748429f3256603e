//! The slice of Embree 3's C API that the peer uses, declared by hand.
//!
//! Written against the 3.13 headers (`rtcore_common.h`, `rtcore_device.h`,
//! `rtcore_scene.h`, `rtcore_geometry.h`, `rtcore_buffer.h`, `rtcore_ray.h`) with
//! `RTC_MAX_INSTANCE_LEVEL_COUNT == 1` and `RTC_MIN_WIDTH == 0`, the values Debian's
//! `rtcore_config.h` has; both change the layout of the structs below. Only what the peer
//! calls is declared, so a mismatch has few places to hide, and every struct carries
//! compile-time size, alignment and offset checks against the C layout.
//!
//! C enums are passed as `u32`: every enumerator used is non-negative and fits, and GCC gives
//! such enums the 4-byte `unsigned int` representation on the x86-64 and AArch64 ABIs.

use std::ffi::{c_char, c_uint, c_void};
use std::mem::{align_of, offset_of, size_of};

/// Opaque `struct RTCDeviceTy`.
#[repr(C)]
pub struct RTCDeviceTy {
    _opaque: [u8; 0],
}

/// Opaque `struct RTCSceneTy`.
#[repr(C)]
pub struct RTCSceneTy {
    _opaque: [u8; 0],
}

/// Opaque `struct RTCGeometryTy`.
#[repr(C)]
pub struct RTCGeometryTy {
    _opaque: [u8; 0],
}

/// `RTCDevice`.
pub type RTCDevice = *mut RTCDeviceTy;
/// `RTCScene`.
pub type RTCScene = *mut RTCSceneTy;
/// `RTCGeometry`.
pub type RTCGeometry = *mut RTCGeometryTy;

/// `RTC_INVALID_GEOMETRY_ID`: `(unsigned int)-1`.
pub const RTC_INVALID_GEOMETRY_ID: c_uint = c_uint::MAX;

/// `enum RTCError`.
pub type RTCError = c_uint;
/// No error.
pub const RTC_ERROR_NONE: RTCError = 0;
/// Unknown error.
pub const RTC_ERROR_UNKNOWN: RTCError = 1;
/// Invalid argument.
pub const RTC_ERROR_INVALID_ARGUMENT: RTCError = 2;
/// Invalid operation.
pub const RTC_ERROR_INVALID_OPERATION: RTCError = 3;
/// Out of memory.
pub const RTC_ERROR_OUT_OF_MEMORY: RTCError = 4;
/// The CPU lacks an ISA Embree was built to require.
pub const RTC_ERROR_UNSUPPORTED_CPU: RTCError = 5;
/// A memory monitor or progress callback cancelled the operation.
pub const RTC_ERROR_CANCELLED: RTCError = 6;

/// `enum RTCBuildQuality`.
pub type RTCBuildQuality = c_uint;
/// Morton builder: quickest build.
pub const RTC_BUILD_QUALITY_LOW: RTCBuildQuality = 0;
/// Binned SAH builder (Embree's default).
pub const RTC_BUILD_QUALITY_MEDIUM: RTCBuildQuality = 1;
/// SAH builder with spatial splits.
pub const RTC_BUILD_QUALITY_HIGH: RTCBuildQuality = 2;
/// Refits the existing BVH when only the vertex buffer changed (geometries only).
pub const RTC_BUILD_QUALITY_REFIT: RTCBuildQuality = 3;

/// `enum RTCGeometryType`.
pub type RTCGeometryType = c_uint;
/// Triangle mesh.
pub const RTC_GEOMETRY_TYPE_TRIANGLE: RTCGeometryType = 0;

/// `enum RTCBufferType`.
pub type RTCBufferType = c_uint;
/// Index buffer.
pub const RTC_BUFFER_TYPE_INDEX: RTCBufferType = 0;
/// Vertex buffer.
pub const RTC_BUFFER_TYPE_VERTEX: RTCBufferType = 1;

/// `enum RTCFormat`.
pub type RTCFormat = c_uint;
/// Three `unsigned int`s (`RTC_FORMAT_UINT = 0x5001`, then UINT2, UINT3).
pub const RTC_FORMAT_UINT3: RTCFormat = 0x5003;
/// Three `float`s (`RTC_FORMAT_FLOAT = 0x9001`, then FLOAT2, FLOAT3).
pub const RTC_FORMAT_FLOAT3: RTCFormat = 0x9003;

/// `enum RTCIntersectContextFlags`.
pub type RTCIntersectContextFlags = c_uint;
/// Optimise for incoherent rays: `(0 << 0)`, the value `rtcInitIntersectContext` sets.
pub const RTC_INTERSECT_CONTEXT_FLAG_INCOHERENT: RTCIntersectContextFlags = 0;

/// `RTCFilterFunctionN`: never set by the peer, declared for the context's layout.
pub type RTCFilterFunctionN = Option<unsafe extern "C" fn(args: *const c_void)>;

/// `RTCErrorFunction`: `void (*)(void* userPtr, enum RTCError code, const char* str)`.
pub type RTCErrorFunction =
    Option<unsafe extern "C" fn(user_ptr: *mut c_void, code: RTCError, message: *const c_char)>;

/// `RTCMemoryMonitorFunction`: `bool (*)(void* ptr, ssize_t bytes, bool post)`; `ptr` is the
/// user pointer given with it, `bytes` is negative for frees.
pub type RTCMemoryMonitorFunction =
    Option<unsafe extern "C" fn(user_ptr: *mut c_void, bytes: isize, post: bool) -> bool>;

/// `struct RTC_ALIGN(16) RTCRay`: one ray, in Embree's AoS layout.
#[repr(C, align(16))]
#[derive(Clone, Copy, Debug, Default)]
pub struct RTCRay {
    /// Origin x.
    pub org_x: f32,
    /// Origin y.
    pub org_y: f32,
    /// Origin z.
    pub org_z: f32,
    /// Start of the ray segment.
    pub tnear: f32,
    /// Direction x.
    pub dir_x: f32,
    /// Direction y.
    pub dir_y: f32,
    /// Direction z.
    pub dir_z: f32,
    /// Motion-blur time.
    pub time: f32,
    /// End of the segment; Embree sets it to the hit distance (or `-inf` when occluded).
    pub tfar: f32,
    /// Ray mask, ANDed with the geometry mask.
    pub mask: c_uint,
    /// Ray id (unused by Embree itself).
    pub id: c_uint,
    /// Ray flags (reserved).
    pub flags: c_uint,
}

/// `struct RTC_ALIGN(16) RTCHit`: what Embree writes for the closest hit.
#[repr(C, align(16))]
#[derive(Clone, Copy, Debug, Default)]
pub struct RTCHit {
    /// Geometric normal x (unnormalised).
    pub ng_x: f32,
    /// Geometric normal y.
    pub ng_y: f32,
    /// Geometric normal z.
    pub ng_z: f32,
    /// Barycentric weight of the triangle's second vertex.
    pub u: f32,
    /// Barycentric weight of the triangle's third vertex.
    pub v: f32,
    /// Primitive id within the geometry.
    pub prim_id: c_uint,
    /// Geometry id, `RTC_INVALID_GEOMETRY_ID` on a miss.
    pub geom_id: c_uint,
    /// Instance ids (`RTC_MAX_INSTANCE_LEVEL_COUNT` of them).
    pub inst_id: [c_uint; 1],
}

/// `struct RTCRayHit`: the in/out record of `rtcIntersect1`. The C struct has no alignment
/// attribute of its own but inherits 16 from its members; stated here as well.
#[repr(C, align(16))]
#[derive(Clone, Copy, Debug, Default)]
pub struct RTCRayHit {
    /// The ray; `tfar` comes back as the hit distance.
    pub ray: RTCRay,
    /// The hit.
    pub hit: RTCHit,
}

/// `struct RTCIntersectContext` for `RTC_MAX_INSTANCE_LEVEL_COUNT == 1` and
/// `RTC_MIN_WIDTH == 0`: no `instStackSize`, no `minWidthDistanceFactor`.
#[repr(C)]
#[derive(Clone, Copy, Debug)]
pub struct RTCIntersectContext {
    /// `enum RTCIntersectContextFlags`.
    pub flags: RTCIntersectContextFlags,
    /// Per-call filter function; null.
    pub filter: RTCFilterFunctionN,
    /// The instance-id stack.
    pub inst_id: [c_uint; 1],
}

impl RTCIntersectContext {
    /// What the header's inline `rtcInitIntersectContext` writes: incoherent flags, no
    /// filter, an empty instance stack.
    pub fn new() -> RTCIntersectContext {
        RTCIntersectContext {
            flags: RTC_INTERSECT_CONTEXT_FLAG_INCOHERENT,
            filter: None,
            inst_id: [RTC_INVALID_GEOMETRY_ID; 1],
        }
    }
}

// Layout checks against the C headers (x86-64 / AArch64 LP64), as printed by a C program
// using `sizeof`, `_Alignof` and `offsetof` on Debian's headers.
const _: () = {
    assert!(size_of::<RTCRay>() == 48 && align_of::<RTCRay>() == 16);
    assert!(offset_of!(RTCRay, tnear) == 12);
    assert!(offset_of!(RTCRay, dir_x) == 16);
    assert!(offset_of!(RTCRay, time) == 28);
    assert!(offset_of!(RTCRay, tfar) == 32);
    assert!(offset_of!(RTCRay, mask) == 36);
    assert!(offset_of!(RTCRay, flags) == 44);

    assert!(size_of::<RTCHit>() == 32 && align_of::<RTCHit>() == 16);
    assert!(offset_of!(RTCHit, u) == 12);
    assert!(offset_of!(RTCHit, v) == 16);
    assert!(offset_of!(RTCHit, prim_id) == 20);
    assert!(offset_of!(RTCHit, geom_id) == 24);
    assert!(offset_of!(RTCHit, inst_id) == 28);

    assert!(size_of::<RTCRayHit>() == 80 && align_of::<RTCRayHit>() == 16);
    assert!(offset_of!(RTCRayHit, hit) == 48);

    assert!(size_of::<RTCIntersectContext>() == 24 && align_of::<RTCIntersectContext>() == 8);
    assert!(offset_of!(RTCIntersectContext, filter) == 8);
    assert!(offset_of!(RTCIntersectContext, inst_id) == 16);

    // The filter slot must be exactly one nullable function pointer.
    assert!(size_of::<RTCFilterFunctionN>() == size_of::<*const c_void>());
    assert!(size_of::<RTCErrorFunction>() == size_of::<*const c_void>());
    assert!(size_of::<RTCMemoryMonitorFunction>() == size_of::<*const c_void>());
};

#[link(name = "embree3")]
extern "C" {
    /// Makes a device; `config` is a comma-separated option string or null.
    pub fn rtcNewDevice(config: *const c_char) -> RTCDevice;
    /// Releases a device reference.
    pub fn rtcReleaseDevice(device: RTCDevice);
    /// Returns and clears the device's first pending error (the thread's, for null).
    pub fn rtcGetDeviceError(device: RTCDevice) -> RTCError;
    /// Sets the callback Embree calls, with a message, on every error.
    pub fn rtcSetDeviceErrorFunction(
        device: RTCDevice,
        error: RTCErrorFunction,
        user_ptr: *mut c_void,
    );
    /// Sets the callback Embree calls on every allocation and free of the device.
    pub fn rtcSetDeviceMemoryMonitorFunction(
        device: RTCDevice,
        monitor: RTCMemoryMonitorFunction,
        user_ptr: *mut c_void,
    );

    /// Makes an empty scene.
    pub fn rtcNewScene(device: RTCDevice) -> RTCScene;
    /// Releases a scene reference.
    pub fn rtcReleaseScene(scene: RTCScene);
    /// Chooses the builder of the top-level BVH.
    pub fn rtcSetSceneBuildQuality(scene: RTCScene, quality: RTCBuildQuality);
    /// Attaches a geometry; returns its id in the scene.
    pub fn rtcAttachGeometry(scene: RTCScene, geometry: RTCGeometry) -> c_uint;
    /// Builds the scene's BVH; afterwards it may be traced from any thread.
    pub fn rtcCommitScene(scene: RTCScene);
    /// Traces one ray for its closest hit in `(tnear, tfar]`.
    pub fn rtcIntersect1(
        scene: RTCScene,
        context: *mut RTCIntersectContext,
        rayhit: *mut RTCRayHit,
    );
    /// Traces one ray for any hit; sets `tfar = -inf` if one is found.
    pub fn rtcOccluded1(scene: RTCScene, context: *mut RTCIntersectContext, ray: *mut RTCRay);

    /// Makes a geometry of the given type.
    pub fn rtcNewGeometry(device: RTCDevice, kind: RTCGeometryType) -> RTCGeometry;
    /// Releases a geometry reference.
    pub fn rtcReleaseGeometry(geometry: RTCGeometry);
    /// Chooses the builder of the geometry's BVH.
    pub fn rtcSetGeometryBuildQuality(geometry: RTCGeometry, quality: RTCBuildQuality);
    /// Allocates a buffer owned by the geometry (padded for 16-byte loads of the last
    /// element) and returns a pointer to fill it through, or null on failure.
    pub fn rtcSetNewGeometryBuffer(
        geometry: RTCGeometry,
        kind: RTCBufferType,
        slot: c_uint,
        format: RTCFormat,
        byte_stride: usize,
        item_count: usize,
    ) -> *mut c_void;
    /// Finishes the geometry's changes.
    pub fn rtcCommitGeometry(geometry: RTCGeometry);
    /// Marks a buffer of the geometry as modified (its contents were written in place).
    pub fn rtcUpdateGeometryBuffer(geometry: RTCGeometry, kind: RTCBufferType, slot: c_uint);
}

/// The header's name of an error code, for messages.
pub fn error_name(code: RTCError) -> &'static str {
    match code {
        RTC_ERROR_NONE => "RTC_ERROR_NONE",
        RTC_ERROR_UNKNOWN => "RTC_ERROR_UNKNOWN",
        RTC_ERROR_INVALID_ARGUMENT => "RTC_ERROR_INVALID_ARGUMENT",
        RTC_ERROR_INVALID_OPERATION => "RTC_ERROR_INVALID_OPERATION",
        RTC_ERROR_OUT_OF_MEMORY => "RTC_ERROR_OUT_OF_MEMORY",
        RTC_ERROR_UNSUPPORTED_CPU => "RTC_ERROR_UNSUPPORTED_CPU",
        RTC_ERROR_CANCELLED => "RTC_ERROR_CANCELLED",
        _ => "unknown RTCError code",
    }
}
