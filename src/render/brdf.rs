//! The BRDF of glTF 2.0's metallic-roughness materials (the specification's Appendix B,
//! with `KHR_materials_specular`'s weighting of the dielectric layer): a GGX
//! (Trowbridge–Reitz) specular lobe with the separable Smith visibility the appendix
//! gives, over a Lambertian diffuse lobe, mixed by Schlick's Fresnel term; a conductor
//! where the material is metallic.
//!
//! Everything is in a local frame where the shading normal is +Z, so that cosines are
//! plain `z` components. Sampling picks the specular lobe (visible normals, Heitz 2018) or
//! the cosine-weighted diffuse lobe by their estimated weights, and [`Bsdf::pdf`] is the
//! one-sample mixture density of both, as multiple importance sampling needs.

use glam::Vec3;
use std::f32::consts::PI;

/// The smallest GGX α: below it the lobe is a near-delta that f32 cannot evaluate.
const MIN_ALPHA: f32 = 1e-3;

/// A material evaluated at one surface point: what the BRDF needs.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Bsdf {
    /// Base colour (linear RGB).
    pub base: Vec3,
    /// Metalness in [0, 1].
    pub metallic: f32,
    /// GGX α = perceptual roughness².
    pub alpha: f32,
    /// `KHR_materials_specular`'s weight of the dielectric specular layer (0: diffuse).
    pub specular: f32,
    /// Normal-incidence reflectance of the dielectric layer: 0.04 (ior 1.5) times
    /// `specularColor`, at most 1.
    pub f0_dielectric: Vec3,
    /// Probability of sampling the specular lobe.
    p_specular: f32,
}

/// A sampled direction.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct BsdfSample {
    /// The incident (light) direction, local frame, unit.
    pub wi: Vec3,
    /// BRDF · cos θᵢ / pdf: the path throughput's factor.
    pub weight: Vec3,
    /// The mixture density of `wi` (solid angle).
    pub pdf: f32,
}

fn max3(v: Vec3) -> f32 {
    v.x.max(v.y).max(v.z)
}

fn luminance(v: Vec3) -> f32 {
    0.2126 * v.x + 0.7152 * v.y + 0.0722 * v.z
}

fn schlick(f0: Vec3, cos: f32) -> Vec3 {
    let m = (1.0 - cos.clamp(0.0, 1.0)).powi(5);
    f0 + (Vec3::ONE - f0) * m
}

impl Bsdf {
    /// The BRDF of base colour `base`, `metallic`, perceptual `roughness`, specular
    /// weight `specular` and `specular_color` (all as glTF defines them).
    pub fn new(
        base: Vec3,
        metallic: f32,
        roughness: f32,
        specular: f32,
        specular_color: Vec3,
    ) -> Bsdf {
        let metallic = metallic.clamp(0.0, 1.0);
        let r = roughness.clamp(0.0, 1.0);
        let specular = specular.clamp(0.0, 1.0);
        let f0_dielectric = (0.04 * specular_color).min(Vec3::ONE);
        // Lobe weights at normal incidence: what each lobe reflects there, roughly.
        let spec_w = (1.0 - metallic) * specular * max3(f0_dielectric) + metallic * max3(base);
        let diff_w = (1.0 - metallic) * luminance(base) * (1.0 - specular * max3(f0_dielectric));
        let p_specular = if spec_w <= 0.0 {
            0.0
        } else if diff_w <= 0.0 {
            1.0
        } else {
            (spec_w / (spec_w + diff_w)).clamp(0.1, 0.9)
        };
        Bsdf {
            base,
            metallic,
            alpha: (r * r).max(MIN_ALPHA),
            specular,
            f0_dielectric,
            p_specular,
        }
    }

    /// A purely Lambertian BRDF of albedo `albedo`.
    pub fn lambert(albedo: Vec3) -> Bsdf {
        Bsdf::new(albedo, 0.0, 1.0, 0.0, Vec3::ONE)
    }

    /// GGX normal distribution D(h) for a half vector of cosine `nh`.
    fn d(&self, nh: f32) -> f32 {
        if nh <= 0.0 {
            return 0.0;
        }
        let a2 = self.alpha * self.alpha;
        let k = nh * nh * (a2 - 1.0) + 1.0;
        a2 / (PI * k * k)
    }

    /// Smith's G1 for a direction of cosine `c` to the normal.
    fn g1(&self, c: f32) -> f32 {
        let a2 = self.alpha * self.alpha;
        2.0 * c / (c + (a2 + (1.0 - a2) * c * c).sqrt())
    }

    /// The appendix's visibility term V = G / (4 |n·l| |n·v|) of the separable Smith G.
    fn vis(&self, nl: f32, nv: f32) -> f32 {
        let a2 = self.alpha * self.alpha;
        let l = nl + (a2 + (1.0 - a2) * nl * nl).sqrt();
        let v = nv + (a2 + (1.0 - a2) * nv * nv).sqrt();
        1.0 / (l * v)
    }

    /// BRDF value f(wo, wi) (not times the cosine). Both directions in the local frame,
    /// pointing away from the surface; zero unless both are above it.
    pub fn eval(&self, wo: Vec3, wi: Vec3) -> Vec3 {
        let (nv, nl) = (wo.z, wi.z);
        if nv <= 0.0 || nl <= 0.0 {
            return Vec3::ZERO;
        }
        let h = (wo + wi).normalize_or_zero();
        self.value(nv, nl, wo.dot(h).max(0.0), self.d(h.z))
    }

    /// The BRDF's value for cosines `nv`, `nl` (both positive) and `vh`, and the
    /// microfacet density `d` of their half vector: [`Bsdf::eval`]'s and
    /// [`Bsdf::eval_pdf`]'s one formula.
    #[inline(always)]
    fn value(&self, nv: f32, nl: f32, vh: f32, d: f32) -> Vec3 {
        let spec = d * self.vis(nl, nv);
        let diffuse = self.base / PI;
        let fd = schlick(self.f0_dielectric, vh);
        let dielectric =
            diffuse * (1.0 - self.specular * max3(fd)) + Vec3::splat(spec) * self.specular * fd;
        let metal = schlick(self.base, vh) * spec;
        dielectric * (1.0 - self.metallic) + metal * self.metallic
    }

    /// Density of the visible-normal sampling of the specular lobe.
    fn pdf_specular(&self, wo: Vec3, wi: Vec3) -> f32 {
        let h = (wo + wi).normalize_or_zero();
        let vh = wo.dot(h);
        if vh <= 0.0 || wo.z <= 0.0 {
            return 0.0;
        }
        // D_v(h) = G1(v) max(0, v·h) D(h) / (n·v), and dwi/dh = 1 / (4 v·h).
        self.g1(wo.z) * self.d(h.z) / (4.0 * wo.z)
    }

    /// [`Bsdf::eval`] and [`Bsdf::pdf`] of one pair of directions at once, bit for bit
    /// theirs: the half vector and its microfacet density are found once (a scattering
    /// vertex needs both twice, for its light sample and its BRDF sample).
    pub fn eval_pdf(&self, wo: Vec3, wi: Vec3) -> (Vec3, f32) {
        let (nv, nl) = (wo.z, wi.z);
        if nv <= 0.0 || nl <= 0.0 {
            return (Vec3::ZERO, 0.0);
        }
        let h = (wo + wi).normalize_or_zero();
        let cos_vh = wo.dot(h);
        let d = self.d(h.z);
        let f = self.value(nv, nl, cos_vh.max(0.0), d);
        let ps = self.p_specular;
        // As `pdf_specular` tests it: a NaN cosine goes on to a NaN density.
        let spec_pdf = if ps > 0.0 && (cos_vh > 0.0 || cos_vh.is_nan()) {
            self.g1(nv) * d / (4.0 * nv)
        } else {
            0.0
        };
        (f, ps * spec_pdf + (1.0 - ps) * nl / PI)
    }

    /// The mixture density with which [`Bsdf::sample`] picks `wi`.
    pub fn pdf(&self, wo: Vec3, wi: Vec3) -> f32 {
        if wi.z <= 0.0 || wo.z <= 0.0 {
            return 0.0;
        }
        let ps = self.p_specular;
        let spec = if ps > 0.0 {
            self.pdf_specular(wo, wi)
        } else {
            0.0
        };
        ps * spec + (1.0 - ps) * wi.z / PI
    }

    /// Samples an incident direction for outgoing `wo` from uniform `u` (three numbers in
    /// [0, 1): the first picks the lobe). `None` when the sample falls below the surface.
    pub fn sample(&self, wo: Vec3, u: [f32; 3]) -> Option<BsdfSample> {
        if wo.z <= 0.0 {
            return None;
        }
        let wi = if u[0] < self.p_specular {
            let h = self.sample_visible_normal(wo, u[1], u[2]);
            let wi = 2.0 * wo.dot(h) * h - wo;
            wi.normalize_or_zero()
        } else {
            let r = u[1].sqrt();
            let phi = 2.0 * PI * u[2];
            Vec3::new(r * phi.cos(), r * phi.sin(), (1.0 - u[1]).max(0.0).sqrt())
        };
        if wi.z <= 0.0 {
            return None;
        }
        let (f, pdf) = self.eval_pdf(wo, wi);
        if !(pdf > 0.0 && pdf.is_finite()) {
            return None;
        }
        let weight = f * wi.z / pdf;
        weight.is_finite().then_some(BsdfSample { wi, weight, pdf })
    }

    /// A GGX visible normal for `wo` (Heitz 2018, "Sampling the GGX Distribution of
    /// Visible Normals").
    fn sample_visible_normal(&self, wo: Vec3, u1: f32, u2: f32) -> Vec3 {
        let a = self.alpha;
        let vh = Vec3::new(a * wo.x, a * wo.y, wo.z).normalize();
        let len2 = vh.x * vh.x + vh.y * vh.y;
        let t1 = if len2 > 0.0 {
            Vec3::new(-vh.y, vh.x, 0.0) / len2.sqrt()
        } else {
            Vec3::X
        };
        let t2 = vh.cross(t1);
        let r = u1.sqrt();
        let phi = 2.0 * PI * u2;
        let p1 = r * phi.cos();
        let s = 0.5 * (1.0 + vh.z);
        let p2 = (1.0 - s) * (1.0 - p1 * p1).max(0.0).sqrt() + s * r * phi.sin();
        let nh = p1 * t1 + p2 * t2 + (1.0 - p1 * p1 - p2 * p2).max(0.0).sqrt() * vh;
        Vec3::new(a * nh.x, a * nh.y, nh.z.max(1e-6)).normalize()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::render::rng::Pcg32;

    fn dir(theta: f32, phi: f32) -> Vec3 {
        Vec3::new(
            theta.sin() * phi.cos(),
            theta.sin() * phi.sin(),
            theta.cos(),
        )
    }

    fn materials() -> Vec<Bsdf> {
        vec![
            Bsdf::lambert(Vec3::new(0.8, 0.5, 0.2)),
            Bsdf::new(Vec3::new(0.9, 0.6, 0.3), 1.0, 0.3, 1.0, Vec3::ONE),
            Bsdf::new(Vec3::new(0.2, 0.7, 0.4), 0.0, 0.5, 1.0, Vec3::ONE),
            Bsdf::new(Vec3::splat(1.0), 0.5, 0.8, 1.0, Vec3::ONE),
            Bsdf::new(Vec3::splat(1.0), 0.0, 0.05, 1.0, Vec3::new(1.0, 0.5, 0.2)),
        ]
    }

    /// The fused evaluation gives exactly what the two separate ones give, for every
    /// material, above, at and below the surface, and for NaN, infinite and signed-zero
    /// components.
    #[test]
    fn eval_pdf_is_eval_and_pdf() {
        let mut rng = Pcg32::new(7, 3);
        for m in materials() {
            for _ in 0..2000 {
                let mut d = || {
                    let theta = rng.next_f32() * 1.7;
                    dir(theta, rng.next_f32() * 2.0 * PI)
                };
                let (wo, wi) = (d(), d());
                let odd = [f32::NAN, f32::INFINITY, 0.0, -0.0];
                let k = (rng.next_u32() % 4) as usize;
                let pairs = [
                    (wo, wi),
                    (wo, Vec3::new(wi.x, wi.y, 0.0)),
                    (wi, wo),
                    (Vec3::new(wo.x, wo.y, odd[k]), wi),
                    (wo, Vec3::new(odd[k], wi.y, wi.z)),
                ];
                // Equal bits, or NaN both.
                let same =
                    |a: f32, b: f32| a.to_bits() == b.to_bits() || (a.is_nan() && b.is_nan());
                for (wo, wi) in pairs {
                    let (f, pdf) = m.eval_pdf(wo, wi);
                    let (g, q) = (m.eval(wo, wi), m.pdf(wo, wi));
                    let mut values = f.to_array().into_iter().zip(g.to_array());
                    assert!(values.all(|(a, b)| same(a, b)), "{m:?} {wo} {wi}");
                    assert!(same(pdf, q), "{m:?} {wo} {wi}: {pdf} vs {q}");
                }
            }
        }
    }

    #[test]
    fn specular_factor_zero_is_lambertian() {
        let m = Bsdf::new(Vec3::new(0.3, 0.6, 0.9), 0.0, 0.2, 0.0, Vec3::ONE);
        let (wo, wi) = (dir(0.4, 0.1), dir(1.1, 2.0));
        let f = m.eval(wo, wi);
        assert!((f - Vec3::new(0.3, 0.6, 0.9) / PI).abs().max_element() < 1e-6);
    }

    #[test]
    fn brdf_is_reciprocal_and_zero_below_the_surface() {
        for m in materials() {
            for (a, b) in [((0.3, 0.0), (1.2, 2.5)), ((0.9, 1.0), (0.1, 4.0))] {
                let (wo, wi) = (dir(a.0, a.1), dir(b.0, b.1));
                let (f, g) = (m.eval(wo, wi), m.eval(wi, wo));
                assert!((f - g).abs().max_element() < 1e-4 * (1.0 + f.max_element()));
                assert_eq!(m.eval(wo, -wi), Vec3::ZERO);
            }
        }
    }

    /// The estimator ∫ f cos / pdf with the sampler's own directions agrees with a plain
    /// uniform-hemisphere estimate of the same integral (the albedo): sampling weights and
    /// densities are consistent.
    #[test]
    fn sampling_agrees_with_uniform_integration() {
        let mut rng = Pcg32::new(9, 1);
        for m in materials() {
            for theta in [0.2f32, 0.9, 1.3] {
                let wo = dir(theta, 0.7);
                let n = 200_000;
                let mut by_sampling = Vec3::ZERO;
                let mut uniform = Vec3::ZERO;
                for _ in 0..n {
                    let u = [rng.next_f32(), rng.next_f32(), rng.next_f32()];
                    if let Some(s) = m.sample(wo, u) {
                        by_sampling += s.weight;
                        let p = m.pdf(wo, s.wi);
                        assert!((p - s.pdf).abs() <= 1e-4 * p, "{p} vs {}", s.pdf);
                    }
                    // Uniform hemisphere: pdf 1/(2π).
                    let z = rng.next_f32();
                    let phi = 2.0 * PI * rng.next_f32();
                    let r = (1.0 - z * z).max(0.0).sqrt();
                    let wi = Vec3::new(r * phi.cos(), r * phi.sin(), z);
                    uniform += m.eval(wo, wi) * wi.z * 2.0 * PI;
                }
                let (a, b) = (by_sampling / n as f32, uniform / n as f32);
                // Energy: a Lambertian or a conductor never reflects more than it
                // receives. The appendix's dielectric mix can, a little, at grazing
                // angles (its diffuse weight uses each direction's own Fresnel term).
                if m.specular == 0.0 || m.metallic == 1.0 {
                    assert!(a.max_element() <= 1.01, "{m:?} {theta}: albedo {a}");
                }
                // Near-specular lobes make the uniform estimate noisy; compare loosely.
                let tol = if m.alpha < 0.05 { 0.1 } else { 0.02 };
                assert!(
                    (a - b).abs().max_element() < tol,
                    "{m:?} {theta}: {a} vs {b}"
                );
            }
        }
    }
}
