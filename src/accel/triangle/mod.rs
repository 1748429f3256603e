//! The ray/triangle tests every accelerator uses, in the contract's two precisions:
//! [`MollerTrumbore`] (`fast`) and [`Watertight`] (Woop, Benthin & Wald 2013).
//!
//! Each test exists twice with *identical arithmetic*: a scalar one (1 ray × 1 triangle) and
//! an 8-wide one (1 ray × 8 triangles in the SoA "multi-triangle" [`Tri8`], Áfra 2013),
//! generic over the SIMD backend. Neither uses FMA (`mul_add`): every operation is an
//! IEEE-rounded add/sub/mul/div in the same order, so **every backend and the scalar test
//! give bit-identical t, u, v and hit decisions**. That costs a few instructions on AVX2 but
//! buys reproducible results across machines and keeps the watertight test watertight (its
//! edge functions must be exactly antisymmetric for a shared edge, which a fused
//! `a·b - c·d` is not).
//!
//! The 8-wide tests return only the hit mask and t; the winner's barycentrics are recomputed
//! by the scalar test on that one triangle ([`TriTest::intersect1`]), which by the identity
//! above reproduces the 8-wide t exactly. Traversals thus never carry u, v through their
//! inner loops. Cores whose per-ray cost matters use [`TriTest::intersect8_uv`] instead,
//! which also returns the 8-wide u, v (bit-identical to the scalar ones) so that no scalar
//! test runs at the end.
//!
//! Hit rules (contract §2): t in the closed `[tmin, tmax]`, no culling, a zero determinant
//! never hits. The interval test is done on the *final* t (`T · (1/det)`), not on `T`
//! against `det·tmin`, so that a reported t always lies inside the ray's interval.
//! The watertight test then reports, for the one hit a query returns, a better-conditioned
//! t ([`TriTest::finish_t`], [`refined_t`]); the decision and the `(t, id)` order use the
//! test's own t, in every core alike.
//! `tmin > tmax` is empty; [`PreparedRay::is_empty`] lets callers skip such rays, and the
//! tests themselves never hit for them unless rounding collapses the interval (callers skip).
//!
//! [`oracle`] holds the float64 reference used by the tests of every accelerator.

mod moller;
pub mod oracle;
#[cfg(test)]
pub(crate) mod tests;
mod watertight;

pub use moller::{mt_det_ok8, mt_in_range8, mt_rounded_zero8, MollerTrumbore};
pub use oracle::{oracle_closest_f64, oracle_f64, oracle_line_f64, OracleHit};
pub use watertight::{edges8, entry8, in_range8, lift_t, refined_t, Watertight};

use super::{tiny_dir, Precision};
use crate::geometry::{Ray, Triangle};
use crate::simd::Simd;
use std::fmt::Debug;
use std::marker::PhantomData;

/// A ray with the per-ray constants of both tests precomputed, so that per-triangle work is
/// minimal.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct PreparedRay {
    /// Origin.
    pub org: [f32; 3],
    /// Direction (not normalised).
    pub dir: [f32; 3],
    /// Interval start.
    pub tmin: f32,
    /// Interval end (may be `+inf`).
    pub tmax: f32,
    /// Watertight axis permutation `[kx, ky, kz]`: `kz` is the axis of the largest |dir|
    /// component (lowest index on ties); `kx`, `ky` follow cyclically and are swapped when
    /// `dir[kz] < 0`, so the winding (hence the sign convention) is preserved.
    pub k: [usize; 3],
    /// Watertight shear `[Sx, Sy, Sz] = [dir[kx]/dir[kz], dir[ky]/dir[kz], 1/dir[kz]]`.
    pub shear: [f32; 3],
}

impl PreparedRay {
    /// Precomputes the constants of `ray`.
    #[inline]
    pub fn new(ray: &Ray) -> PreparedRay {
        // A ray whose direction is below `tiny_dir::TINY` is tested as its scaled twin
        // (`accel::tiny_dir`): its t in units of `2^-e·t`, which [`TriTest::finish_t`]
        // scales back.
        let twin;
        let ray = match tiny_dir::ray_exponent(ray.dir) {
            0 => ray,
            e => {
                twin = tiny_dir::scaled_ray(ray, e);
                &twin
            }
        };
        let d = ray.dir;
        let a = d.map(f32::abs);
        let kz = if a[0] >= a[1] && a[0] >= a[2] {
            0
        } else if a[1] >= a[2] {
            1
        } else {
            2
        };
        let mut kx = (kz + 1) % 3;
        let mut ky = (kx + 1) % 3;
        if d[kz] < 0.0 {
            std::mem::swap(&mut kx, &mut ky);
        }
        PreparedRay {
            org: ray.org,
            dir: d,
            tmin: ray.tmin,
            tmax: ray.tmax,
            k: [kx, ky, kz],
            shear: [d[kx] / d[kz], d[ky] / d[kz], 1.0 / d[kz]],
        }
    }

    /// Whether the interval `[tmin, tmax]` is empty (or NaN): such rays miss everything.
    #[inline]
    pub fn is_empty(&self) -> bool {
        // Written as a partial_cmp so that a NaN bound also counts as empty.
        !matches!(
            self.tmin.partial_cmp(&self.tmax),
            Some(std::cmp::Ordering::Less | std::cmp::Ordering::Equal)
        )
    }
}

/// A [`PreparedRay`] broadcast into 8-wide registers for the 8-wide tests.
pub struct PreparedRay8<S: Simd> {
    /// Origin.
    pub org: [S::F8; 3],
    /// Direction.
    pub dir: [S::F8; 3],
    /// Origin permuted by `k`: `[org[kx], org[ky], org[kz]]`.
    pub org_k: [S::F8; 3],
    /// Interval start.
    pub tmin: S::F8,
    /// Watertight axis permutation (see [`PreparedRay::k`]).
    pub k: [usize; 3],
    /// Watertight shear (see [`PreparedRay::shear`]).
    pub shear: [S::F8; 3],
    /// [`inv`] of `dir[kx]` and `dir[ky]`, for the decision t ([`lift_t`]); scalars, which
    /// the test broadcasts from memory: two more vector registers held across the
    /// traversal cost more in spills than the loads.
    pub inv_k: [f32; 2],
}

impl<S: Simd> Clone for PreparedRay8<S> {
    fn clone(&self) -> Self {
        *self
    }
}
impl<S: Simd> Copy for PreparedRay8<S> {}

impl<S: Simd> PreparedRay8<S> {
    /// Broadcasts `r`.
    #[inline(always)]
    pub fn new(s: S, r: &PreparedRay) -> Self {
        // Spelled out rather than `array::map`, which is not always inlined and would then
        // run the vector constructors outside the kernel's target features.
        let v = |a: [f32; 3]| [s.splat_f8(a[0]), s.splat_f8(a[1]), s.splat_f8(a[2])];
        let [kx, ky, kz] = r.k;
        PreparedRay8 {
            org: v(r.org),
            dir: v(r.dir),
            org_k: v([r.org[kx], r.org[ky], r.org[kz]]),
            tmin: s.splat_f8(r.tmin),
            k: r.k,
            shear: v(r.shear),
            inv_k: [inv(r.dir[kx]), inv(r.dir[ky])],
        }
    }
}

/// `1 / d`, or 0 where `d` is ±0 (such an axis then gives the decision t's entry ±0, below
/// every hit; see [`lift_t`]).
#[inline(always)]
pub fn inv(d: f32) -> f32 {
    if d == 0.0 {
        0.0
    } else {
        1.0 / d
    }
}

/// The id of padding lanes (never hit).
pub const PAD_ID: u32 = u32::MAX;

/// Up to 8 triangles in SoA layout ("multi-triangle"): `p[i][axis][lane]`, plus their ids.
///
/// The meaning of `p` depends on the test `T`: [`Watertight`] stores the vertices
/// `v0, v1, v2`; [`MollerTrumbore`] stores `v0, e1 = v1-v0, e2 = v2-v0` (edges rounded to f32
/// once, at build time). Padding lanes hold [`TriTest::PAD`] (NaN coordinates, or for
/// Möller–Trumbore a NaN `v0` with finite edges), which no test ever reports as a hit, and
/// the id [`PAD_ID`]. 320 bytes, 32-byte aligned (five cache lines).
#[repr(C, align(32))]
pub struct Tri8<T> {
    /// Coordinates: `p[i][axis][lane]`.
    pub p: [[[f32; 8]; 3]; 3],
    /// Triangle ids (contract §1) per lane; [`PAD_ID`] for padding.
    pub ids: [u32; 8],
    test: PhantomData<T>,
}

const _: () = assert!(std::mem::size_of::<Tri8<Watertight>>() == 320);

impl<T> Clone for Tri8<T> {
    fn clone(&self) -> Self {
        Tri8 {
            p: self.p,
            ids: self.ids,
            test: PhantomData,
        }
    }
}

impl<T> Debug for Tri8<T> {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Tri8")
            .field("p", &self.p)
            .field("ids", &self.ids)
            .finish()
    }
}

impl<T: TriTest> Tri8<T> {
    /// Packs up to 8 `(id, triangle)` pairs; the remaining lanes are padding.
    ///
    /// # Panics
    /// With more than 8 triangles.
    pub fn pack(tris: &[(u32, Triangle)]) -> Tri8<T> {
        assert!(tris.len() <= 8, "a Tri8 holds at most 8 triangles");
        let mut pack = Tri8 {
            p: T::PAD.map(|point| point.map(|c| [c; 8])),
            ids: [PAD_ID; 8],
            test: PhantomData,
        };
        for (lane, (id, tri)) in tris.iter().enumerate() {
            pack.set(lane, *id, tri);
        }
        pack
    }

    /// Writes triangle `tri` with id `id` into lane `lane`, as [`TriTest::lane_data`]
    /// stores it.
    #[inline]
    pub fn set(&mut self, lane: usize, id: u32, tri: &Triangle) {
        let d = T::lane_data(tri);
        for (i, point) in d.iter().enumerate() {
            for (axis, &c) in point.iter().enumerate() {
                self.p[i][axis][lane] = c;
            }
        }
        self.ids[lane] = id;
    }

    /// Re-reads every real lane from `tris` (indexed by triangle id) through
    /// [`TriTest::lane_data`]: after new positions for the same triangles, the pack holds
    /// exactly what [`Tri8::pack`] would store for them, so refitted structures run the
    /// same leaf test on the same data as fresh ones. Padding lanes stay padding.
    ///
    /// # Panics
    /// If a lane's id is out of range of `tris`.
    pub fn regather(&mut self, tris: &[Triangle]) {
        for lane in 0..8 {
            let id = self.ids[lane];
            if id != PAD_ID {
                self.set(lane, id, &tris[id as usize]);
            }
        }
    }

    /// Lane `lane`'s data as the scalar test takes it (`p[i][axis]`).
    ///
    /// Nine loads, spelled out: `array::map` on `self.p` copied the whole pack (a
    /// `memcpy` of 288 bytes) and ran out of line, which callgrind showed costing more
    /// than the watertight t's refinement itself.
    #[inline(always)]
    pub fn lane(&self, lane: usize) -> [[f32; 3]; 3] {
        let p = &self.p;
        let l = lane & 7;
        [
            [p[0][0][l], p[0][1][l], p[0][2][l]],
            [p[1][0][l], p[1][1][l], p[1][2][l]],
            [p[2][0][l], p[2][1][l], p[2][2][l]],
        ]
    }

    /// The contract's closest among the lanes set in `bits` (an 8-wide hit mask as
    /// [`crate::simd::MaskV::bitmask`] gives it) with ray parameters `t`: smallest t, ties to
    /// the lowest triangle id. Traversals that keep a running best `(t, id)` compare it
    /// with this lane's `(t, ids[lane])` the same way (passing `tmax = best t` to
    /// [`TriTest::intersect8`] keeps equal-t lanes, so a lower id can still win).
    #[inline]
    pub fn best_lane(&self, bits: u32, t: &[f32; 8]) -> Option<usize> {
        let mut best: Option<usize> = None;
        let mut rest = bits & 0xff;
        while rest != 0 {
            let lane = rest.trailing_zeros() as usize;
            rest &= rest - 1;
            best = match best {
                Some(b) if (t[b], self.ids[b]) <= (t[lane], self.ids[lane]) => Some(b),
                _ => Some(lane),
            };
        }
        best
    }

    /// Number of real (non-padding) lanes.
    pub fn len(&self) -> usize {
        self.ids.iter().filter(|&&id| id != PAD_ID).count()
    }

    /// Whether every lane is padding.
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }
}

/// Packs the non-degenerate triangles of `tris` (ids = their indices) into [`Tri8`]s in id
/// order; degenerate triangles are left out (contract: never hit).
pub fn pack_all<T: TriTest>(tris: &[Triangle]) -> Vec<Tri8<T>> {
    let live: Vec<(u32, Triangle)> = tris
        .iter()
        .enumerate()
        .filter(|(_, t)| !t.is_degenerate())
        .map(|(i, t)| (i as u32, *t))
        .collect();
    live.chunks(8).map(Tri8::pack).collect()
}

/// A hit of one ray on one triangle: the hit point is `(1-u-v)·v0 + u·v1 + v·v2`.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct TriHit {
    /// Ray parameter, in `[tmin, tmax]`.
    pub t: f32,
    /// Barycentric weight of `v1`.
    pub u: f32,
    /// Barycentric weight of `v2`.
    pub v: f32,
}

/// The lanes of `bad` decided again, one by one, by `decide` (a lane's index to its hit,
/// `None` for a miss), merged into the others' `t, u, v` and validity (a miss's t becomes
/// `+inf`). The shared half of both tests' cold paths: [`Watertight`]'s rescaled lanes and
/// [`MollerTrumbore`]'s redecided ones, each called from a `#[cold]` function of its test.
#[inline(always)]
pub(crate) fn merge_lanes8<S: Simd>(
    s: S,
    bad: u32,
    [t, u, v]: [S::F8; 3],
    valid: S::M8,
    mut decide: impl FnMut(usize) -> Option<TriHit>,
) -> (S::F8, S::F8, S::F8, S::M8) {
    use crate::simd::{FloatV, Select};
    let (mut t, mut u, mut v) = (t.to_array(), u.to_array(), v.to_array());
    let one = s.splat_f8(1.0);
    let mut ok = valid.select(one, s.splat_f8(0.0)).to_array();
    for lane in (0..8).filter(|l| bad >> l & 1 == 1) {
        match decide(lane) {
            Some(h) => (t[lane], u[lane], v[lane], ok[lane]) = (h.t, h.u, h.v, 1.0),
            None => (t[lane], ok[lane]) = (f32::INFINITY, 0.0),
        }
    }
    (
        s.load_f8(&t),
        s.load_f8(&u),
        s.load_f8(&v),
        s.load_f8(&ok).eq(one),
    )
}

/// A ray/triangle test in its scalar and 8-wide forms, which agree bit for bit.
pub trait TriTest: Copy + Default + Debug + Send + Sync + 'static {
    /// The contract's precision this test implements.
    const PRECISION: Precision;

    /// What a padding lane of a [`Tri8`] holds (as [`TriTest::lane_data`] would store it):
    /// data that no test reports as a hit. NaN unless the test says otherwise.
    const PAD: [[f32; 3]; 3] = [[f32::NAN; 3]; 3];

    /// The three points stored per triangle (see [`Tri8`]).
    fn lane_data(tri: &Triangle) -> [[f32; 3]; 3];

    /// The t a query reports for the hit at the test's `t` on the triangle with lane data
    /// `p`: called once per query, by every core at the place it writes its record (and by
    /// [`intersect`]), never inside the search, so that hit decisions and the `(t, id)`
    /// order stay the test's own. `ray` is the ray as given (its `tmax`, not a running
    /// best). For Möller–Trumbore the test's t, for the watertight test [`refined_t`],
    /// each first scaled back where the ray was tested as its scaled twin
    /// ([`tiny_dir::unscaled_hit_t`]). u and v are the test's.
    #[inline(always)]
    fn finish_t(ray: &Ray, p: &[[f32; 3]; 3], t: f32) -> f32 {
        let _ = p;
        tiny_dir::unscaled_hit_t(ray, t)
    }

    /// Scalar test on one triangle given as [`TriTest::lane_data`], interval
    /// `[ray.tmin, tmax]`.
    fn intersect_lane(ray: &PreparedRay, p: &[[f32; 3]; 3], tmax: f32) -> Option<TriHit>;

    /// 8-wide test: the mask of lanes hit within `[ray.tmin, tmax]` (per lane) and their t
    /// (meaningless where the mask is clear). Bit-identical to [`TriTest::intersect1`] per
    /// lane, on every backend.
    fn intersect8<S: Simd>(
        s: S,
        ray: &PreparedRay8<S>,
        tri: &Tri8<Self>,
        tmax: S::F8,
    ) -> (S::M8, S::F8);

    /// [`TriTest::intersect8`] that also returns every lane's barycentrics `(u, v)`
    /// (meaningless where the mask is clear), bit-identical to [`TriTest::intersect1`]'s:
    /// a traversal keeps the winner's u, v as it goes instead of re-running the scalar
    /// test at the end. The extra work is two multiplications where a lane is inside.
    fn intersect8_uv<S: Simd>(
        s: S,
        ray: &PreparedRay8<S>,
        tri: &Tri8<Self>,
        tmax: S::F8,
    ) -> (S::M8, S::F8, S::F8, S::F8);

    /// Scalar test on lane `lane` of `tri` (used to get the winner's u, v after an 8-wide
    /// search).
    #[inline]
    fn intersect1(ray: &PreparedRay, tri: &Tri8<Self>, lane: usize, tmax: f32) -> Option<TriHit> {
        Self::intersect_lane(ray, &tri.lane(lane), tmax)
    }

    /// Scalar test on a triangle, interval `[ray.tmin, ray.tmax]`.
    #[inline]
    fn intersect_triangle(ray: &PreparedRay, tri: &Triangle) -> Option<TriHit> {
        if tri.is_degenerate() {
            return None;
        }
        Self::intersect_lane(ray, &Self::lane_data(tri), ray.tmax)
    }
}

/// The hit of `ray` on one triangle as a core reports it: the scalar test of `precision`,
/// then [`TriTest::finish_t`] (a convenience for callers that hold a [`Precision`] value
/// rather than a test type).
pub fn intersect(precision: Precision, ray: &Ray, tri: &Triangle) -> Option<TriHit> {
    fn finish<T: TriTest>(ray: &Ray, tri: &Triangle, h: TriHit) -> TriHit {
        TriHit {
            t: T::finish_t(ray, &T::lane_data(tri), h.t),
            ..h
        }
    }
    let h = intersect_unrefined(precision, ray, tri)?;
    Some(match precision {
        Precision::Fast => finish::<MollerTrumbore>(ray, tri, h),
        Precision::Watertight => finish::<Watertight>(ray, tri, h),
    })
}

/// The test's own hit of `ray` on one triangle, before [`TriTest::finish_t`]: what the
/// cores decide and order by (tests compare the `(t, id)` order with it).
pub fn intersect_unrefined(precision: Precision, ray: &Ray, tri: &Triangle) -> Option<TriHit> {
    let r = PreparedRay::new(ray);
    if r.is_empty() {
        return None;
    }
    match precision {
        Precision::Fast => MollerTrumbore::intersect_triangle(&r, tri),
        Precision::Watertight => Watertight::intersect_triangle(&r, tri),
    }
}
