//! Leaf intersection (Áfra 2012 §3.3): the active rays of a leaf against its few triangles.
//! Triangles are the outer loop and rays the inner one in the sense that matters: each
//! triangle is rebuilt from the precompute once per block and then met by every active ray,
//! 8 rays per SIMD step (the records of a group are transposed once and then tested against
//! all the block's triangles).
//!
//! A group's best hits are kept in registers while the triangles are tested, then written
//! once per ray: `tmax` into the record (so the next box tests cull with it) and `(t, prim)`
//! into the ray's hit slot, which decides ties by the lowest id exactly as `brute` does (a
//! triangle at the same `t` as the slot's but with a lower id replaces it).
//!
//! Both tests are the SIMD layer's scalar tests (`accel::triangle`) transposed to 8 rays × 1
//! triangle with the *same operations in the same order* (no FMA), so `t` is bit-identical
//! to what `brute` computes for the same pair, and the final `u, v` come from the layer's
//! scalar test itself. The reported t of a ray's final hit is the layer's
//! [`TriTest::finish_t`], applied once per ray when the batch writes its records.

use crate::accel::triangle::{
    edges8, entry8, in_range8, mt_det_ok8, mt_in_range8, mt_rounded_zero8, MollerTrumbore,
    PreparedRay, TriTest,
};
use crate::accel::Precision;
use crate::geometry::{Hit, Ray, Triangle};
use crate::simd::{self, FloatV, IntV, Kernel, MaskV, Select, Simd};

use super::lanes::{Rays8, Transposer};
use super::rays::{RayRec, SLOT_MASK, TMIN_FLAG};
use super::tris::{decode, TriData};

/// No candidate yet (any real triangle id is lower).
const NONE: u32 = u32::MAX;

/// A triangle as a leaf holds it: the three points of the test (`p[i]` lanes 0–2; lanes 3–7
/// are 0 so a point loads as one vector and permutes per lane) and its id.
#[derive(Clone, Copy, Debug, Default)]
#[repr(C, align(32))]
pub struct LeafTri {
    p: [[f32; 8]; 3],
    id: u32,
}

/// A ray/triangle test in the form the leaves use: 8 rays against one triangle.
pub trait LeafTest: Copy + Send + Sync + 'static {
    /// The contract's precision.
    const PRECISION: Precision;
    /// The layer's test whose arithmetic this one transposes.
    type Scalar: TriTest;
    /// Per-group ray constants.
    type Lanes<S: Simd>: Copy;

    /// Computes the per-group constants of 8 rays.
    fn prep8<S: Simd>(s: S, r: &Rays8<S>) -> Self::Lanes<S>;

    /// Hit mask (within `[tmin, tmax]` per lane), `t`, `u` and `v` of the 8 rays against
    /// `tri` (`t, u, v` only meaningful where the mask is set).
    fn hit8<S: Simd>(s: S, r: &Self::Lanes<S>, tri: &LeafTri, tmin: S::F8, tmax: S::F8) -> Hit8<S>;

    /// The full hit (`t, u, v`) of `ray` on the triangle with vertices `v` as a core
    /// reports it: the layer's scalar test, then its reported t ([`TriTest::finish_t`]).
    fn full(ray: &Ray, v: [[f32; 3]; 3]) -> Option<(f32, f32, f32)> {
        let lane = Self::Scalar::lane_data(&Triangle { v });
        let r = PreparedRay::new(ray);
        Self::Scalar::intersect_lane(&r, &lane, r.tmax)
            .map(|h| (Self::Scalar::finish_t(ray, &lane, h.t), h.u, h.v))
    }
}

/// What [`LeafTest::hit8`] finds.
pub struct Hit8<S: Simd> {
    /// Lanes that hit within their interval.
    pub mask: S::M8,
    /// Ray parameter.
    pub t: S::F8,
    /// Barycentric weight of `v1`.
    pub u: S::F8,
    /// Barycentric weight of `v2`.
    pub v: S::F8,
}

impl<S: Simd> Hit8<S> {
    #[inline(always)]
    fn miss(mask: S::M8, zero: S::F8) -> Self {
        Hit8 {
            mask,
            t: zero,
            u: zero,
            v: zero,
        }
    }
}

/// Woop, Benthin & Wald 2013 (`precision=watertight`), 8 rays × 1 triangle.
///
/// Each ray has its own axis order (`kz` = the largest |dir| component, lowest index on
/// ties; `kx, ky` its cyclic successors, swapped when `dir[kz] < 0`, exactly as the scalar
/// test), so each lane picks its coordinates of the triangle's points with one permute per
/// coordinate; the choice itself is made once per group of rays.
#[derive(Clone, Copy, Debug, Default)]
pub struct Watertight;

/// Per-group constants of [`Watertight`].
#[derive(Clone, Copy)]
pub struct WtLanes<S: Simd> {
    /// Lane indices of `kx`, `ky`, `kz` (for permuting a triangle point).
    idx: [S::I8; 3],
    /// Origin permuted: `org[kx], org[ky], org[kz]`.
    org: [S::F8; 3],
    /// Shear `d[kx]/d[kz], d[ky]/d[kz], 1/d[kz]`.
    shear: [S::F8; 3],
    /// `1/d[kx], 1/d[ky]`, 0 where the component is ±0 (`triangle::inv`), for the
    /// decision t (`lift_t`).
    inv: [S::F8; 2],
}

impl LeafTest for Watertight {
    const PRECISION: Precision = Precision::Watertight;
    type Scalar = crate::accel::triangle::Watertight;
    type Lanes<S: Simd> = WtLanes<S>;

    #[inline(always)]
    fn prep8<S: Simd>(s: S, r: &Rays8<S>) -> WtLanes<S> {
        let [dx, dy, dz] = r.dir;
        let (ax, ay, az) = (dx.abs(), dy.abs(), dz.abs());
        let z0 = ax.ge(ay) & ax.ge(az);
        let z1 = ay.ge(az).andnot(z0);
        let pick = |x: S::F8, y: S::F8, z: S::F8| z0.select(x, z1.select(y, z));
        let ipick = |x: i32, y: i32, z: i32| {
            z0.select(s.splat_i8(x), z1.select(s.splat_i8(y), s.splat_i8(z)))
        };
        // kz = 0: (kx, ky) = (1, 2); kz = 1: (2, 0); kz = 2: (0, 1); then swapped where
        // dir[kz] < 0 (keeps the winding, as the scalar test does).
        let dkz = pick(dx, dy, dz);
        let neg = dkz.lt(s.splat_f8(0.0));
        let (dkx, dky) = (pick(dy, dz, dx), pick(dz, dx, dy));
        let (dkx, dky) = (neg.select(dky, dkx), neg.select(dkx, dky));
        // `triangle::inv`: 0 where the component is ±0.
        let zero = s.splat_f8(0.0);
        let inv = |d: S::F8| d.eq(zero).select(zero, s.splat_f8(1.0) / d);
        let (ikx, iky) = (ipick(1, 2, 0), ipick(2, 0, 1));
        let (ikx, iky) = (neg.select(iky, ikx), neg.select(ikx, iky));
        let [ox, oy, oz] = r.org;
        let (okx, oky) = (pick(oy, oz, ox), pick(oz, ox, oy));
        let (okx, oky) = (neg.select(oky, okx), neg.select(okx, oky));
        WtLanes {
            idx: [ikx, iky, ipick(0, 1, 2)],
            org: [okx, oky, pick(ox, oy, oz)],
            shear: [dkx / dkz, dky / dkz, s.splat_f8(1.0) / dkz],
            inv: [inv(dkx), inv(dky)],
        }
    }

    #[inline(always)]
    fn hit8<S: Simd>(s: S, r: &WtLanes<S>, tri: &LeafTri, tmin: S::F8, tmax: S::F8) -> Hit8<S> {
        let [ix, iy, iz] = r.idx;
        let [ox, oy, oz] = r.org;
        let [sx, sy, sz] = r.shear;
        let (p0, p1, p2) = (
            s.load_f8(&tri.p[0]),
            s.load_f8(&tri.p[1]),
            s.load_f8(&tri.p[2]),
        );
        // Vertex minus origin, `rel[i]` in the lane's order kx, ky, kz.
        let rel = |p: S::F8| [p.permute(ix) - ox, p.permute(iy) - oy, p.permute(iz) - oz];
        let rel = [rel(p0), rel(p1), rel(p2)];
        let [u, v, w] = edges8(s, &rel, sx, sy);
        let (a_z, b_z, c_z) = (rel[0][2], rel[1][2], rel[2][2]);
        let zero = s.splat_f8(0.0);
        let inside = u.min(v).min(w).ge(zero) | u.max(v).max(w).le(zero);
        if inside.none() {
            return Hit8::miss(inside, zero);
        }
        let det = u + v + w;
        let tt = u * (sz * a_z) + v * (sz * b_z) + w * (sz * c_z);
        let rcp = s.splat_f8(1.0) / det;
        let t = tt * rcp;
        // Lanes that left f32's normal range, decided again as the scalar test does.
        // (`rel` is live here anyway: the decision t's entry below reads it.)
        let (t, bu, bv, valid) = in_range8(
            s,
            || rel,
            r.shear,
            inside,
            [tt, det],
            t,
            v * rcp,
            w * rcp,
            // Lanes that `in_range` passes have a normal det; the others are decided again.
            inside,
        );
        let mask = valid & t.ge(tmin) & t.le(tmax);
        // The layer's decision t (`lift_t`), per ray.
        let t = entry8(s, &rel, r.inv).max(t);
        let mask = mask & t.le(tmax);
        Hit8 {
            mask,
            t,
            u: bu,
            v: bv,
        }
    }
}

/// Möller–Trumbore without culling (`precision=fast`), 8 rays × 1 triangle; edges rounded
/// to f32 once per triangle, as the layer stores them.
#[derive(Clone, Copy, Debug, Default)]
pub struct Moller;

/// Per-group constants of [`Moller`].
#[derive(Clone, Copy)]
pub struct MtLanes<S: Simd> {
    org: [S::F8; 3],
    dir: [S::F8; 3],
}

impl LeafTest for Moller {
    const PRECISION: Precision = Precision::Fast;
    type Scalar = MollerTrumbore;
    type Lanes<S: Simd> = MtLanes<S>;

    #[inline(always)]
    fn prep8<S: Simd>(_s: S, r: &Rays8<S>) -> MtLanes<S> {
        MtLanes {
            org: r.org,
            dir: r.dir,
        }
    }

    #[inline(always)]
    fn hit8<S: Simd>(s: S, r: &MtLanes<S>, tri: &LeafTri, tmin: S::F8, tmax: S::F8) -> Hit8<S> {
        let c = |i: usize, k: usize| s.splat_f8(tri.p[i][k]);
        let [dx, dy, dz] = r.dir;
        let (e2x, e2y, e2z) = (c(2, 0), c(2, 1), c(2, 2));
        let px = dy * e2z - dz * e2y;
        let py = dz * e2x - dx * e2z;
        let pz = dx * e2y - dy * e2x;
        let (e1x, e1y, e1z) = (c(1, 0), c(1, 1), c(1, 2));
        let det = e1x * px + e1y * py + e1z * pz;
        let mut det_ok = mt_det_ok8(s, det);
        let inv = s.splat_f8(1.0) / det;
        let sx = r.org[0] - c(0, 0);
        let sy = r.org[1] - c(0, 1);
        let sz = r.org[2] - c(0, 2);
        let un = sx * px + sy * py + sz * pz;
        let u = un * inv;
        let qx = sy * e1z - sz * e1y;
        let qy = sz * e1x - sx * e1z;
        let qz = sx * e1y - sy * e1x;
        let vn = dx * qx + dy * qy + dz * qz;
        let v = vn * inv;
        let zero = s.splat_f8(0.0);
        let inside = u.min(v).ge(zero) & (u + v).le(s.splat_f8(1.0));
        if det_ok.andnot(inside).all() {
            return Hit8::miss(inside, zero);
        }
        if !det_ok.all() {
            // The layer's rule for zero determinants at ordinary scales.
            let (e1, e2) = ([e1x, e1y, e1z], [e2x, e2y, e2z]);
            det_ok = det_ok | mt_rounded_zero8(s, det, r.dir, e1, e2);
            if det_ok.andnot(inside).all() {
                return Hit8::miss(inside, zero);
            }
        }
        let tn = e2x * qx + e2y * qy + e2z * qz;
        let t = tn * inv;
        // The layer's rule for lanes out of f32's range (`mt_in_range8`), lane for lane.
        let lanes = || ([0, 1, 2].map(|i| [0, 1, 2].map(|k| c(i, k))), r.org, r.dir);
        let (t, u, v, valid) = mt_in_range8(s, lanes, det_ok, inside, [un, vn, tn], [t, u, v]);
        Hit8 {
            mask: valid & t.ge(tmin) & t.le(tmax),
            t,
            u,
            v,
        }
    }
}

/// Where a leaf's best hits go.
pub trait Sink {
    /// The `tmin` of the ray with hit slot `index` (asked only for flagged rays).
    fn tmin(&self, index: usize) -> f32;
    /// Offers a ray's best hit of this leaf, found with the record's `tmax` at `old`
    /// (always the slot's `t`); returns the ray's new `tmax` (closest query).
    fn offer(&mut self, index: usize, hit: Hit, old: f32, any: bool) -> f32;
}

/// Merges a candidate hit into a hit slot: the contract's order (smaller `t`, then lower
/// id); with `any`, the first hit stays. Returns the slot's `t` afterwards.
#[inline(always)]
pub fn merge_slot(slot: &mut Hit, hit: Hit, any: bool) -> f32 {
    let take = if any {
        slot.prim == NONE
    } else {
        hit.t < slot.t || (hit.t == slot.t && hit.prim < slot.prim)
    };
    if take {
        *slot = hit;
    }
    slot.t
}

/// A task's hit slots (`t` = the best so far or the ray's `tmax`, `prim` = its triangle or
/// `u32::MAX`, `u, v` its barycentrics), and the `tmin` of its rays when any ray has a
/// `tmin` other than 0 (empty otherwise: flagged rays exist only when it is not).
pub struct Table<'t> {
    /// One slot per ray of the task.
    pub hits: &'t mut [Hit],
    /// `tmin` per slot, or empty.
    pub tmin: &'t [f32],
}

impl Sink for Table<'_> {
    #[inline(always)]
    fn tmin(&self, index: usize) -> f32 {
        self.tmin.get(index).copied().unwrap_or(0.0)
    }

    #[inline(always)]
    fn offer(&mut self, index: usize, hit: Hit, old: f32, any: bool) -> f32 {
        // The slot's `t` is the record's `tmax`: a strictly nearer hit (or an `any` ray's
        // first, after which the ray leaves) replaces the slot without reading it, so the
        // write does not wait for a cache miss. Only a tie at `tmax` needs the slot's id.
        if any || hit.t < old {
            self.hits[index] = hit;
            hit.t
        } else {
            merge_slot(&mut self.hits[index], hit, any)
        }
    }
}

/// Triangles rebuilt per block of a leaf.
const BLOCK: usize = 32;

/// Intersects `rays` with the triangles `ids`, updating the records and offering each ray's
/// best hit to `sink`. With `any`, a ray that hits is finished: its `tmax` becomes `-inf`,
/// which no box and no triangle test accepts.
pub fn leaf<T: LeafTest, S: Sink + ?Sized>(
    tris: &TriData,
    rays: &mut [RayRec],
    sink: &mut S,
    ids: &[u32],
    any: bool,
) {
    let mut block = [LeafTri::default(); BLOCK];
    for chunk in ids.chunks(BLOCK) {
        for (slot, &id) in block.iter_mut().zip(chunk) {
            let i = id as usize;
            let v = decode(&tris.boxes[i], &tris.extra[i]);
            let p = T::Scalar::lane_data(&Triangle { v });
            for (dst, src) in slot.p.iter_mut().zip(p) {
                dst[..3].copy_from_slice(&src);
            }
            slot.id = id;
        }
        simd::dispatch(
            simd::selected(),
            Groups::<T, S> {
                rays: &mut *rays,
                sink: &mut *sink,
                block: &block[..chunk.len()],
                any,
                test: std::marker::PhantomData,
            },
        );
    }
}

/// Every group of 8 rays against one block of triangles.
struct Groups<'a, T, S: ?Sized> {
    rays: &'a mut [RayRec],
    sink: &'a mut S,
    block: &'a [LeafTri],
    any: bool,
    test: std::marker::PhantomData<T>,
}

impl<T: LeafTest, K: Sink + ?Sized> Kernel for Groups<'_, T, K> {
    type Output = ();

    #[inline(always)]
    fn run<S: Simd>(self, s: S) {
        let tr = Transposer::new(s);
        let none = s.splat_i8(i32::MAX);
        let neg_inf = s.splat_f8(f32::NEG_INFINITY);
        let zero = s.splat_f8(0.0);
        for group in self.rays.chunks_mut(8) {
            let r = Rays8::load(s, &tr, group);
            let flagged = (r.slot & s.splat_i8(TMIN_FLAG as i32)).eq(s.splat_i8(0));
            let tmin = if (!flagged).any() {
                let mut a = [0.0f32; 8];
                for (x, rec) in a.iter_mut().zip(group.iter()) {
                    if rec.slot() & TMIN_FLAG != 0 {
                        *x = self.sink.tmin(rec.index());
                    }
                }
                s.load_f8(&a)
            } else {
                zero
            };
            let lanes = T::prep8(s, &r);
            let mut limit = r.tmax;
            let mut best_t = r.tmax;
            let (mut best_u, mut best_v) = (zero, zero);
            let mut best_id = none;
            for tri in self.block {
                let h = T::hit8(s, &lanes, tri, tmin, limit);
                if h.mask.none() {
                    continue;
                }
                let id = s.splat_i8(tri.id as i32);
                let take = h.mask & (h.t.lt(best_t) | id.lt(best_id));
                best_t = take.select(h.t, best_t);
                best_u = take.select(h.u, best_u);
                best_v = take.select(h.v, best_v);
                best_id = take.select(id, best_id);
                if self.any {
                    limit = take.select(neg_inf, limit);
                    if limit.eq(neg_inf).bitmask() & ((1 << group.len()) - 1)
                        == (1 << group.len()) - 1
                    {
                        break;
                    }
                } else {
                    limit = best_t;
                }
            }
            let found = !best_id.eq(none);
            let mut bits = found.bitmask() & ((1u32 << group.len()) - 1);
            if bits == 0 {
                continue;
            }
            let (ts, ids) = (best_t.to_array(), best_id.to_array());
            let (us, vs) = (best_u.to_array(), best_v.to_array());
            while bits != 0 {
                let lane = bits.trailing_zeros() as usize;
                bits &= bits - 1;
                let rec = &mut group[lane];
                let index = (rec.slot() & SLOT_MASK) as usize;
                let hit = Hit {
                    t: ts[lane],
                    prim: ids[lane] as u32,
                    u: us[lane],
                    v: vs[lane],
                };
                let t = self.sink.offer(index, hit, rec.tmax(), self.any);
                rec.set_tmax(if self.any { f32::NEG_INFINITY } else { t });
            }
        }
    }
}
