//! The SIMD slab test of one ray against the N child boxes of a [`TravNode`] (Kay &
//! Kajiya; Áfra 2013 §4), 8 lanes for MBVH8 and 4 for MBVH4.
//!
//! Per axis, the near plane's row (lower bound for a direction with a clear sign bit,
//! upper bound otherwise) is chosen once per ray, so a node costs 6 loads, 6 fused
//! multiply-adds `plane·inv - org·inv`, 6 min/max and one compare. Entry distances are
//! `max(near_x, near_y, near_z, tmin)` and exits `min(far_x, far_y, far_z, tfar)`, written
//! so that a NaN slab distance (0·∞, ∞-∞ for a ±0 direction component) is the *first*
//! operand of the x86 `min`/`max` and is therefore ignored: the interval can only grow.
//! See [`super::ray`] for why the planes are measured from moved origins.
//!
//! The multiply-add form rounds `org·inv` once, an error of 2^-24·|org|/|dir| in t, which
//! is 32 times smaller than the boxes' growth (and `mul_add` is fused only on AVX2's
//! 8-wide vectors; elsewhere its two roundings stay within the same bound).

use super::layout::TravNode;
use super::ray::SlabConsts;
use crate::simd::{FloatV, MaskV, Simd};

/// Marker for the node width N (4 or 8), carrying its slab test.
#[derive(Clone, Copy, Debug, Default)]
pub struct Lanes<const N: usize>;

/// The slab test of one node width.
pub trait SlabTest<const N: usize> {
    /// The ray's constants broadcast into registers.
    type Ray<S: Simd>: Copy;
    /// Broadcasts `r`.
    fn ray<S: Simd>(s: S, r: &SlabConsts) -> Self::Ray<S>;
    /// The mask of children whose (grown) box the ray enters within `[tmin, tfar]`, bit i
    /// for lane i, and every lane's entry distance (meaningful where the bit is set; `>=
    /// tmin`, never NaN). Entry distances are returned in the first N of 8 lanes.
    fn test<S: Simd>(s: S, r: &Self::Ray<S>, node: &TravNode<N>, tfar: f32) -> (u32, [f32; 8]);
}

/// [`SlabConsts`] in vector registers of width `V`: a plane's distance is one fused
/// multiply-add, `plane·inv - org·inv`.
#[derive(Clone, Copy, Debug)]
pub struct VRay<V> {
    inv: [V; 3],
    /// `-(near origin · inv)` per axis.
    near_oi: [V; 3],
    /// `-(far origin · inv)` per axis.
    far_oi: [V; 3],
    near: [usize; 3],
    far: [usize; 3],
    tmin: V,
}

macro_rules! slab_impl {
    ($n:literal, $f:ident, $splat:ident, $load:ident) => {
        impl SlabTest<$n> for Lanes<$n> {
            type Ray<S: Simd> = VRay<S::$f>;

            #[inline(always)]
            fn ray<S: Simd>(s: S, r: &SlabConsts) -> VRay<S::$f> {
                let v = |a: &[f32; 4]| [s.$splat(a[0]), s.$splat(a[1]), s.$splat(a[2])];
                let neg = |k: usize| (r.neg >> k & 1) as usize;
                VRay {
                    inv: v(&r.inv),
                    near_oi: v(&r.near_oi),
                    far_oi: v(&r.far_oi),
                    near: [3 * neg(0), 1 + 3 * neg(1), 2 + 3 * neg(2)],
                    far: [3 - 3 * neg(0), 4 - 3 * neg(1), 5 - 3 * neg(2)],
                    tmin: s.$splat(r.tmin),
                }
            }

            #[inline(always)]
            fn test<S: Simd>(
                s: S,
                r: &VRay<S::$f>,
                node: &TravNode<$n>,
                tfar: f32,
            ) -> (u32, [f32; 8]) {
                let p = &node.planes;
                let d = |row: usize, oi: S::$f, inv: S::$f| s.$load(&p[row]).mul_add(inv, oi);
                let nx = d(r.near[0], r.near_oi[0], r.inv[0]);
                let ny = d(r.near[1], r.near_oi[1], r.inv[1]);
                let nz = d(r.near[2], r.near_oi[2], r.inv[2]);
                let fx = d(r.far[0], r.far_oi[0], r.inv[0]);
                let fy = d(r.far[1], r.far_oi[1], r.inv[1]);
                let fz = d(r.far[2], r.far_oi[2], r.inv[2]);
                // Two levels instead of a chain of three. A NaN in the first operand of a
                // level drops its partner too, which only enlarges the interval.
                let tn = nx.max(ny).max(nz.max(r.tmin));
                let tf = fx.min(fy).min(fz.min(s.$splat(tfar)));
                let mask = tn.le(tf).bitmask();
                (mask, widen(tn.to_array()))
            }
        }
    };
}

slab_impl!(8, F8, splat_f8, load_f8);
slab_impl!(4, F4, splat_f4, load_f4);

/// The entry distances in the first lanes of an 8-array.
#[inline(always)]
fn widen<const N: usize>(a: [f32; N]) -> [f32; 8] {
    let mut out = [f32::INFINITY; 8];
    out[..N].copy_from_slice(&a);
    out
}
