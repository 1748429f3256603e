//! Helpers shared by the integration tests: a seeded generator and the geometric
//! measures the agreement tests excuse disagreements by. Each test crate uses a part.
#![allow(dead_code)]

use rayd::geometry::{Hit, Ray, Triangle};

/// A render's waves run as they come, on the calling thread's pool, each sized to take
/// `wave_seconds` (infinite: as large as memory allows, as the command line has them; finite:
/// from the rate so far, as the service has them): the renderer's tests need no scheduler,
/// cancellation or progress.
pub struct InPlace {
    pub wave_seconds: f64,
}

/// The command line's waves: as large as memory allows.
pub const ALL_AT_ONCE: InPlace = InPlace {
    wave_seconds: f64::INFINITY,
};

impl rayd::render::Waves for InPlace {
    type Error = std::convert::Infallible;
    fn run_wave(&self, wave: &mut (dyn FnMut() + Send)) -> Result<(), Self::Error> {
        wave();
        Ok(())
    }
    fn wave_seconds(&self) -> f64 {
        self.wave_seconds
    }
    fn progress(&self, _fraction: f64) {}
}

/// SplitMix64: a small seeded generator, so that every test draws the same cases.
pub struct Rng(pub u64);

impl Rng {
    pub fn next(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        z ^ (z >> 31)
    }

    /// Uniform in [0, 1).
    pub fn unit(&mut self) -> f32 {
        (self.next() >> 40) as f32 / (1u64 << 24) as f32
    }

    /// Uniform in [-1, 1).
    pub fn sym(&mut self) -> f32 {
        2.0 * self.unit() - 1.0
    }

    /// Uniform in the cube [-s, s)³.
    pub fn vec(&mut self, s: f32) -> [f32; 3] {
        [self.sym() * s, self.sym() * s, self.sym() * s]
    }

    /// Uniform in 0..n.
    pub fn pick(&mut self, n: usize) -> usize {
        (self.next() % n as u64) as usize
    }
}

pub fn add(a: [f32; 3], b: [f32; 3]) -> [f32; 3] {
    [a[0] + b[0], a[1] + b[1], a[2] + b[2]]
}

/// `longest edge² / (2·area)` in f64: 1 for a fat triangle, huge for a sliver (whose f32 t
/// is cancellation noise).
pub fn sliver(tri: &Triangle) -> f64 {
    let v = tri.v.map(|p| p.map(f64::from));
    let e = |a: usize, b: usize| [v[b][0] - v[a][0], v[b][1] - v[a][1], v[b][2] - v[a][2]];
    let (e1, e2, e3) = (e(0, 1), e(0, 2), e(1, 2));
    let n = [
        e1[1] * e2[2] - e1[2] * e2[1],
        e1[2] * e2[0] - e1[0] * e2[2],
        e1[0] * e2[1] - e1[1] * e2[0],
    ];
    let len2 = |a: [f64; 3]| a[0] * a[0] + a[1] * a[1] + a[2] * a[2];
    len2(e1).max(len2(e2)).max(len2(e3)) / len2(n).sqrt()
}

/// [`sliver`] above which a triangle counts as one.
pub const SLIVER: f64 = 1e3;

/// Under `fast`, whether no tree can be expected to find the Möller–Trumbore hit of `ray`
/// on `tri` at `t`: the triangle is a sliver (its t is cancellation noise), or the hit
/// point lies outside the triangle's box by more than a small fraction of the slab test's
/// growth. Möller–Trumbore's t errs with the triangle's distance from the origin, not its
/// size (proto/semantics.md), so a small fat triangle far away (or a grazing ray) can put
/// it before the box; a tree then skips the box, as `fast` permits.
pub fn unreliable(tri: &Triangle, ray: &Ray, t: f32) -> bool {
    if sliver(tri) > SLIVER {
        return true;
    }
    let v = tri.v.map(|p| p.map(f64::from));
    let big = tri
        .v
        .iter()
        .flatten()
        .chain(&ray.org)
        .fold(0.0f64, |m, &x| m.max(f64::from(x).abs()));
    let margin = big * f64::from(2f32.powi(-22));
    (0..3).any(|k| {
        let p = f64::from(ray.org[k]) + f64::from(t) * f64::from(ray.dir[k]);
        let lo = v[0][k].min(v[1][k]).min(v[2][k]);
        let hi = v[0][k].max(v[1][k]).max(v[2][k]);
        p < lo - margin || p > hi + margin
    })
}

/// A hit's bits, for bit-for-bit comparisons.
pub fn bits(h: &Hit) -> [u32; 4] {
    [h.t.to_bits(), h.prim, h.u.to_bits(), h.v.to_bits()]
}
