//! Helpers shared by the integration tests: a seeded generator and the geometric
//! measures the agreement tests excuse disagreements by. Each test crate uses a part.
#![allow(dead_code)]

use rayd::geometry::{Hit, Triangle};

/// A render's waves all run at once, on the calling thread's pool: the renderer's tests need
/// no scheduler, cancellation or progress.
pub struct AllAtOnce;

impl rayd::render::Waves for AllAtOnce {
    type Error = std::convert::Infallible;
    fn run_wave(&self, wave: &mut (dyn FnMut() + Send)) -> Result<(), Self::Error> {
        wave();
        Ok(())
    }
    fn wave_seconds(&self) -> f64 {
        f64::INFINITY
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

/// A hit's bits, for bit-for-bit comparisons.
pub fn bits(h: &Hit) -> [u32; 4] {
    [h.t.to_bits(), h.prim, h.u.to_bits(), h.v.to_bits()]
}
