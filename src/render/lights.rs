//! Next-event estimation for `path`: which light a scattering vertex samples, and the
//! density with which it would have sampled a direction that BRDF sampling found instead,
//! so that the two strategies are combined by multiple importance sampling (Veach's power
//! heuristic, β = 2).
//!
//! Three kinds of light, each a category picked with equal probability among those the
//! frame has: the punctual lights (one picked uniformly; a delta light can only be reached
//! this way, so its sample has weight 1), the emissive triangles (one picked with
//! probability proportional to its power, its mean emission over its area
//! ([`Surfaces::mean_emission`]: factor × strength × the emissive texture's mean) × area,
//! then a point uniform in its area), and the constant sky (a cosine-weighted direction
//! about the shading normal). Emissive triangles and the sky are also found by BRDF sampling, and
//! [`LightSampler::triangle_pdf`] and [`LightSampler::sky_pdf`] give the light-sampling
//! density of such a find. The table is built once per frame; a lookup allocates nothing.

use glam::Vec3;
use rayon::prelude::*;
use std::f32::consts::PI;

use super::surface::Surfaces;
use crate::geometry::Triangle;

/// Luminance weights (Rec. 709) that rank emitters by power.
fn luminance(v: Vec3) -> f32 {
    0.2126 * v.x + 0.7152 * v.y + 0.0722 * v.z
}

/// One emissive triangle of the frame.
#[derive(Clone, Copy, Debug)]
struct Emitter {
    /// Its triangle id.
    prim: u32,
    /// Probability of picking it among the emitters.
    pmf: f32,
    /// Its area.
    area: f32,
}

/// The frame's lights, ready to sample.
#[derive(Clone, Debug, Default)]
pub struct LightSampler {
    /// Emissive triangles in id order (so a hit's entry is found by binary search).
    emitters: Vec<Emitter>,
    /// Cumulative pick probabilities of `emitters`, the last one 1.
    cdf: Vec<f32>,
    /// Number of punctual lights.
    punctual: usize,
    /// Probability of each category: punctual, triangles, sky.
    p_punctual: f32,
    p_triangles: f32,
    p_sky: f32,
}

/// What a light sample picked.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum LightPick {
    /// Punctual light `index`, picked with probability `prob`.
    Punctual {
        /// Index into [`Surfaces::lights`].
        index: usize,
        /// Its pick probability.
        prob: f32,
    },
    /// A point on an emissive triangle.
    Triangle {
        /// The triangle.
        prim: u32,
        /// Barycentric weights of the point (1 − u − v, u, v).
        b: [f32; 3],
        /// The triangle's unit normal (either side).
        normal: Vec3,
        /// The point.
        point: Vec3,
        /// Density of the point per unit area, pick probabilities included.
        pdf_area: f32,
    },
    /// The sky, in a cosine-weighted direction about the shading normal.
    Sky,
}

impl LightSampler {
    /// The lights of a frame: `surfaces`' punctual lights and emissive triangles among
    /// `triangles`, and the sky when `sky` is not black; only the punctual lights when
    /// `area` is false (emitters and sky are then left to BRDF sampling).
    pub fn new(triangles: &[Triangle], surfaces: &Surfaces, sky: Vec3, area: bool) -> LightSampler {
        // Each triangle's power on the pool (a textured emitter reads 16 texels), then
        // the totals in id order, so the table is the same on any number of threads.
        let emitters: Vec<Emitter> = if area {
            triangles
                .par_iter()
                .enumerate()
                .filter_map(|(prim, tri)| {
                    let e = surfaces.mean_emission(prim);
                    if e == Vec3::ZERO {
                        return None;
                    }
                    let area = 0.5 * Vec3::from(tri.normal()).length();
                    let power = luminance(e).max(e.max_element() * 1e-3) * area;
                    (power > 0.0 && power.is_finite()).then_some(Emitter {
                        prim: prim as u32,
                        pmf: power,
                        area,
                    })
                })
                .collect()
        } else {
            Vec::new()
        };
        let total: f64 = emitters.iter().map(|e| e.pmf as f64).sum();
        let mut cdf = Vec::with_capacity(emitters.len());
        let mut run = 0.0f64;
        // (`pmf` holds each emitter's power until the table's steps replace it below.)
        for e in &emitters {
            run += e.pmf as f64;
            cdf.push((run / total) as f32);
        }
        if let Some(last) = cdf.last_mut() {
            *last = 1.0;
        }
        // An emitter whose f32 step of the table is 0 (a probability under about 6e-8,
        // which textured weights make possible) can never be picked: it leaves the table,
        // so that `triangle_pdf` answers 0 for it as well and BRDF sampling alone finds it.
        let mut prev = 0.0f32;
        let (mut emitters, cdf): (Vec<Emitter>, Vec<f32>) = emitters
            .into_iter()
            .zip(cdf)
            .filter(|&(_, c)| {
                let keep = c > prev;
                prev = prev.max(c);
                keep
            })
            .unzip();
        // Each emitter's density is the step of the table that picks it, which rounding
        // makes differ from its share of the power by up to a few percent for faint ones:
        // the estimate stays unbiased only if the two agree.
        let mut prev = 0.0f32;
        for (e, &c) in emitters.iter_mut().zip(&cdf) {
            e.pmf = c - prev;
            prev = c;
        }
        let punctual = surfaces.lights.len();
        let has = [
            punctual > 0,
            !emitters.is_empty(),
            area && sky.max_element() > 0.0,
        ];
        let k = has.iter().filter(|&&h| h).count().max(1) as f32;
        let p = |h: bool| if h { 1.0 / k } else { 0.0 };
        LightSampler {
            emitters,
            cdf,
            punctual,
            p_punctual: p(has[0]),
            p_triangles: p(has[1]),
            p_sky: p(has[2]),
        }
    }

    /// Bytes held: the table and its cumulative probabilities.
    pub fn bytes(&self) -> usize {
        std::mem::size_of::<Self>()
            + std::mem::size_of_val(&self.emitters[..])
            + std::mem::size_of_val(&self.cdf[..])
    }

    /// Whether there is anything to sample.
    pub fn is_empty(&self) -> bool {
        self.p_punctual + self.p_triangles + self.p_sky == 0.0
    }

    /// Picks a light from uniform `u` (four numbers in [0, 1)): the category, then the
    /// light in it, then a point on it (triangles).
    pub fn pick(&self, triangles: &[Triangle], u: [f32; 4]) -> Option<LightPick> {
        let mut c = u[0];
        if c < self.p_punctual {
            let n = self.punctual;
            let index = ((u[1] * n as f32) as usize).min(n - 1);
            return Some(LightPick::Punctual {
                index,
                prob: self.p_punctual / n as f32,
            });
        }
        c -= self.p_punctual;
        if c < self.p_triangles {
            let k = self
                .cdf
                .partition_point(|&x| x <= u[1])
                .min(self.cdf.len() - 1);
            let e = self.emitters[k];
            let tri = triangles.get(e.prim as usize)?;
            // Uniform in the triangle: the square-root warp.
            let su = u[2].sqrt();
            let b = [1.0 - su, u[3] * su, su * (1.0 - u[3])];
            let v = tri.v.map(Vec3::from);
            let point = v[0] * b[0] + v[1] * b[1] + v[2] * b[2];
            let normal = Vec3::from(tri.normal()).normalize_or_zero();
            return Some(LightPick::Triangle {
                prim: e.prim,
                b,
                normal,
                point,
                pdf_area: self.p_triangles * e.pmf / e.area,
            });
        }
        (self.p_sky > 0.0).then_some(LightPick::Sky)
    }

    /// The solid-angle density with which light sampling picks the direction towards a
    /// point of triangle `prim` at distance `dist`, seen at cosine `cos_light` to its
    /// normal; 0 where the triangle is not an emitter.
    pub fn triangle_pdf(&self, prim: u32, dist: f32, cos_light: f32) -> f32 {
        if self.p_triangles == 0.0 || cos_light <= 0.0 {
            return 0.0;
        }
        match self.emitters.binary_search_by_key(&prim, |e| e.prim) {
            Ok(k) => {
                let e = self.emitters[k];
                self.p_triangles * e.pmf / e.area * dist * dist / cos_light
            }
            Err(_) => 0.0,
        }
    }

    /// The solid-angle density with which light sampling picks sky direction `wi` at a
    /// vertex of shading normal `ns` (both unit).
    pub fn sky_pdf(&self, ns: Vec3, wi: Vec3) -> f32 {
        self.p_sky * ns.dot(wi).max(0.0) / PI
    }
}

/// Veach's power heuristic (β = 2): the weight of a sample of density `a` against a
/// competing strategy of density `b`.
#[inline]
pub fn power_heuristic(a: f32, b: f32) -> f32 {
    let (a2, b2) = (a * a, b * b);
    if a2 + b2 > 0.0 && (a2 + b2).is_finite() {
        a2 / (a2 + b2)
    } else if a.is_infinite() {
        1.0
    } else {
        0.0
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::scene::Material;

    fn tri(a: [f32; 3], b: [f32; 3], c: [f32; 3]) -> Triangle {
        Triangle { v: [a, b, c] }
    }

    #[test]
    fn emitters_are_picked_by_power_and_points_are_uniform() {
        // Triangle 0 is dark, 1 emits 1 over area 0.5, 2 emits 3 over area 2.
        let tris = vec![
            tri([0.0; 3], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]),
            tri([0.0; 3], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]),
            tri([0.0; 3], [2.0, 0.0, 0.0], [0.0, 2.0, 0.0]),
        ];
        let mut shading = crate::scene::Shading::flat(3);
        shading.materials = vec![0, 1, 2];
        let emit = |e: f32| Material {
            emissive_factor: [e; 3],
            ..Material::default()
        };
        let s = Surfaces::from_parts(
            shading,
            vec![emit(0.0), emit(1.0), emit(3.0)],
            Default::default(),
            Vec::new(),
        );
        let l = LightSampler::new(&tris, &s, Vec3::ZERO, true);
        let mut rng = crate::render::rng::Pcg32::new(1, 1);
        let mut count = [0u32; 3];
        let mut mean_b = [0.0f64; 3];
        let n = 40_000;
        for _ in 0..n {
            let u = [0.0, rng.next_f32(), rng.next_f32(), rng.next_f32()];
            match l.pick(&tris, u).unwrap() {
                LightPick::Triangle {
                    prim, b, pdf_area, ..
                } => {
                    count[prim as usize] += 1;
                    // Powers 0.5 and 6 of 6.5; density = pick probability / area.
                    let expect = if prim == 1 {
                        (0.5 / 6.5) / 0.5
                    } else {
                        (6.0 / 6.5) / 2.0
                    };
                    assert!((pdf_area - expect).abs() < 1e-5, "{prim}: {pdf_area}");
                    for k in 0..3 {
                        mean_b[k] += b[k] as f64 / n as f64;
                    }
                }
                other => panic!("{other:?}"),
            }
        }
        assert_eq!(count[0], 0);
        let share = count[2] as f64 / n as f64;
        assert!((share - 6.0 / 6.5).abs() < 0.01, "{share}");
        // Uniform in area: every barycentric weight has mean 1/3.
        for m in mean_b {
            assert!((m - 1.0 / 3.0).abs() < 0.01, "{mean_b:?}");
        }
        assert_eq!(l.triangle_pdf(0, 1.0, 1.0), 0.0);
        assert!((l.triangle_pdf(2, 2.0, 0.5) - (6.0 / 6.5) / 2.0 * 8.0).abs() < 1e-4);
    }

    /// The density of a faint emitter is the probability the table really picks it with:
    /// its step of the f32 table, not its share of the power, which rounding makes differ
    /// by percents when one emitter outshines the rest a millionfold.
    #[test]
    fn emitter_densities_are_the_steps_of_the_pick_table() {
        let n = 201;
        let tris: Vec<Triangle> = (0..n)
            .map(|_| tri([0.0; 3], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]))
            .collect();
        let mut shading = crate::scene::Shading::flat(n);
        shading.materials = (0..n as u32).collect();
        let materials = (0..n)
            .map(|k| Material {
                emissive_factor: [if k == 0 { 1.0 } else { 1e-6 }; 3],
                ..Material::default()
            })
            .collect();
        let s = Surfaces::from_parts(shading, materials, Default::default(), Vec::new());
        let l = LightSampler::new(&tris, &s, Vec3::ZERO, true);
        assert!(l.emitters.len() > 1, "faint emitters kept");
        let mut prev = 0.0f32;
        let mut total = 0.0f64;
        for (e, &c) in l.emitters.iter().zip(&l.cdf) {
            // dist 1, cos 1: the area density times the area is the pick probability.
            let p = l.triangle_pdf(e.prim, 1.0, 1.0) * e.area / l.p_triangles;
            assert!(
                (p - (c - prev)).abs() <= 1e-6 * (c - prev),
                "{}: {p} against {}",
                e.prim,
                c - prev
            );
            prev = c;
            total += p as f64;
        }
        assert!((total - 1.0).abs() < 1e-6, "{total}");
    }

    #[test]
    fn emitters_are_weighed_by_their_emissive_texture() {
        use crate::render::mipmap::Filtering;
        use crate::render::texture::{Texels, TextureSet};
        use crate::scene::{Filter, TextureRef, Wrap};
        use glam::Vec2;
        // One material, emissive factor 2, whose texture is black on its left half and
        // white on its right. Triangle 0 maps into the black half, 1 into the white half,
        // 2 across both (a quarter of its area on the white side).
        let t = tri([0.0; 3], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]);
        let tris = vec![t; 3];
        let mut shading = crate::scene::Shading::flat(3);
        shading.materials = vec![0; 3];
        let uv = |u: f32, v: f32| Vec2::new(u, v);
        shading.uv0 = vec![
            uv(0.0, 0.0),
            uv(0.4, 0.0),
            uv(0.0, 1.0),
            uv(0.6, 0.0),
            uv(1.0, 0.0),
            uv(0.6, 1.0),
            uv(0.0, 0.0),
            uv(1.0, 0.0),
            uv(0.0, 1.0),
        ];
        let material = Material {
            emissive_factor: [2.0; 3],
            emissive_texture: Some(TextureRef {
                texture: 0,
                tex_coord: 0,
                transform: None,
            }),
            ..Material::default()
        };
        let texels =
            Texels::from_rgba(2, 1, vec![[0.0, 0.0, 0.0, 1.0], [1.0, 1.0, 1.0, 1.0]]).unwrap();
        let textures = TextureSet::from_texels(vec![(
            texels,
            Filtering::single(Filter::Nearest, [Wrap::ClampToEdge; 2]),
        )]);
        let s = Surfaces::from_parts(shading, vec![material], textures, Vec::new());
        assert_eq!(s.mean_emission(0), Vec3::ZERO);
        assert_eq!(s.mean_emission(1), Vec3::splat(2.0));
        assert_eq!(s.mean_emission(2), Vec3::splat(0.5));
        let l = LightSampler::new(&tris, &s, Vec3::ZERO, true);
        let mut rng = crate::render::rng::Pcg32::new(3, 1);
        let mut count = [0u32; 3];
        for _ in 0..10_000 {
            let u = [0.0, rng.next_f32(), rng.next_f32(), rng.next_f32()];
            if let Some(LightPick::Triangle { prim, .. }) = l.pick(&tris, u) {
                count[prim as usize] += 1;
            }
        }
        // Powers 0, 2 and 0.5 (equal areas): no sample is spent on the black triangle,
        // which BRDF sampling alone then finds with the whole MIS weight.
        assert_eq!(count[0], 0);
        let share = count[1] as f64 / 10_000.0;
        assert!((share - 0.8).abs() < 0.02, "{count:?}");
        assert_eq!(l.triangle_pdf(0, 1.0, 1.0), 0.0);
        assert!(l.triangle_pdf(2, 1.0, 1.0) > 0.0);
    }

    #[test]
    fn an_emitter_too_faint_for_the_table_leaves_it() {
        // Powers 1 and 1e-10: the faint one's f32 step of the table is 0, so it could
        // never be picked; it must not keep a light density either.
        let t = tri([0.0; 3], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]);
        let mut shading = crate::scene::Shading::flat(2);
        shading.materials = vec![0, 1];
        let emit = |e: f32| Material {
            emissive_factor: [e; 3],
            ..Material::default()
        };
        let s = Surfaces::from_parts(
            shading,
            vec![emit(1.0), emit(1e-10)],
            Default::default(),
            Vec::new(),
        );
        let l = LightSampler::new(&[t, t], &s, Vec3::ZERO, true);
        assert!(l.triangle_pdf(0, 1.0, 1.0) > 0.0);
        assert_eq!(l.triangle_pdf(1, 1.0, 1.0), 0.0);
        for u in [0.0, 0.5, 1.0 - f32::EPSILON] {
            match l.pick(&[t, t], [0.0, u, 0.5, 0.5]) {
                Some(LightPick::Triangle { prim, .. }) => assert_eq!(prim, 0),
                other => panic!("{other:?}"),
            }
        }
    }

    #[test]
    fn categories_share_the_picks() {
        let s = Surfaces::default_material(0, Vec::new());
        let l = LightSampler::new(&[], &s, Vec3::ONE, true);
        assert_eq!(l.pick(&[], [0.3, 0.0, 0.0, 0.0]), Some(LightPick::Sky));
        assert!((l.sky_pdf(Vec3::Z, Vec3::Z) - 1.0 / PI).abs() < 1e-6);
        let dark = LightSampler::new(&[], &s, Vec3::ZERO, true);
        assert!(dark.is_empty());
        assert_eq!(power_heuristic(1.0, 1.0), 0.5);
        assert_eq!(power_heuristic(0.0, 0.0), 0.0);
    }
}
