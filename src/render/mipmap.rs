//! MIP pyramids and the level a lookup reads.
//!
//! A camera pixel of a 640 × 480 frame of DamagedHelmet spans about four texels of its
//! 2048² textures, so full-resolution lookups alias (the pixel's few samples land on
//! unrelated texels) and each one misses the cache: the four textures are 64 MiB, twice
//! this machine's last-level cache, and texel loads were half a path frame's shading.
//! Reading the level whose texels match the lookup's footprint filters the texture over
//! what the pixel sees and touches a few MiB instead. glTF samplers say how: `minFilter`
//! names the filter within a level and whether to blend two levels; without one, as
//! renderers and viewers do, bilinear within a level and linear between levels.
//!
//! The footprint comes from a ray cone (Akenine-Möller et al., "Texture Level of Detail
//! Strategies for Real-Time Ray Tracing", *Ray Tracing Gems* ch. 20): camera rays start
//! with the pixel's angle, narrowed as pbrt-v4 narrows its ray differentials when several
//! samples share a pixel (by `1/√spp`, at most 8×: the box filter already averages them);
//! each scattering widens the cone by the sampled lobe's angular width, estimated from its
//! density (`1/√pdf`, as path differentials do: Suykens and Willems 2001). The width where
//! the cone meets a surface, over the cosine there, in units of the texture (the
//! triangle's texel-to-world area ratio), is the footprint; its log2 is the level.

use glam::{Vec2, Vec4};

use super::texture::{floor, Blend, Texels};
use crate::scene::{Filter, Mipmap, Sampler, Wrap};

/// How a texture is filtered: a glTF sampler, its absent filters made definite.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Filtering {
    /// Within level 0 when the footprint is at most a texel.
    pub mag: Filter,
    /// Within a level when minifying.
    pub min: Filter,
    /// Between levels when minifying.
    pub mipmap: Mipmap,
    /// Wraps along S and T.
    pub wrap: [Wrap; 2],
}

impl Filtering {
    /// The filtering of sampler `s`: an absent `magFilter` is bilinear, an absent
    /// `minFilter` trilinear (`LINEAR_MIPMAP_LINEAR`), and a `minFilter` of `NEAREST` or
    /// `LINEAR` reads level 0 alone, as glTF says.
    pub fn of(s: &Sampler) -> Filtering {
        let (min, mipmap) = match s.min_filter {
            None => (Filter::Linear, Mipmap::Linear),
            Some(f) => (f, s.mipmap),
        };
        Filtering {
            mag: s.mag_filter.unwrap_or(Filter::Linear),
            min,
            mipmap,
            wrap: [s.wrap_s, s.wrap_t],
        }
    }

    /// One filter at level 0 for every lookup, whatever its footprint (tests).
    pub fn single(filter: Filter, wrap: [Wrap; 2]) -> Filtering {
        Filtering {
            mag: filter,
            min: filter,
            mipmap: Mipmap::None,
            wrap,
        }
    }
}

/// An image and its MIP levels, each half the last, down to 1 × 1.
#[derive(Clone, Debug, PartialEq)]
pub struct Pyramid {
    /// Level 0 (the image) first.
    levels: Vec<Texels>,
    /// log2 of level 0's texels per unit of texture coordinate, geometric mean of the two
    /// axes: what turns a footprint in texture coordinates into one in texels.
    log2_texels_per_unit: f32,
}

impl Pyramid {
    /// The pyramid of `base`, filtered down in linear light when it is a colour texture
    /// (`srgb`).
    pub fn new(base: Texels, srgb: bool) -> Pyramid {
        let log2_texels_per_unit =
            0.5 * (f64::from(base.width()) * f64::from(base.height())).log2() as f32;
        let mut levels = vec![base];
        while let Some(next) = levels.last().and_then(|l| l.half(srgb)) {
            levels.push(next);
        }
        Pyramid {
            levels,
            log2_texels_per_unit,
        }
    }

    /// log2 of level 0's texels per unit of texture coordinate.
    pub fn log2_texels_per_unit(&self) -> f32 {
        self.log2_texels_per_unit
    }

    /// Bytes of texels held, every level.
    pub fn bytes(&self) -> usize {
        self.levels.iter().map(Texels::bytes).sum()
    }

    /// Its levels, level 0 first.
    pub fn levels(&self) -> &[Texels] {
        &self.levels
    }

    /// The value at `uv` for a footprint of `2^log2_width` texture-coordinate units.
    pub fn sample(&self, uv: Vec2, log2_width: f32, f: &Filtering, srgb: bool) -> Vec4 {
        let lod = log2_width + self.log2_texels_per_unit;
        across_levels(lod, f, self.levels.len() - 1, |k, filter| {
            self.levels[k].sample(uv, f.wrap, filter, srgb)
        })
    }
}

/// What a lookup at level of detail `lod` reads of levels `0..=last`, `level(k, filter)`
/// being level `k` filtered with `filter`: level 0 magnified when the footprint is at most
/// a texel (or undefined: NaN), otherwise as `f.mipmap` says: level 0, the nearest level,
/// or the blend of the two around `lod`.
#[inline(always)]
pub(crate) fn across_levels<T: Blend>(
    lod: f32,
    f: &Filtering,
    last: usize,
    level: impl Fn(usize, Filter) -> T,
) -> T {
    if lod.is_nan() || lod <= 0.0 {
        return level(0, f.mag);
    }
    match f.mipmap {
        Mipmap::None => level(0, f.min),
        Mipmap::Nearest => level(((lod - 0.5).ceil() as usize).min(last), f.min),
        Mipmap::Linear => {
            let l = floor(lod);
            let k = l as usize;
            if k >= last {
                return level(last, f.min);
            }
            level(k, f.min).blend(level(k + 1, f.min), lod - l)
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn grey_checker(n: u32) -> Texels {
        let texels = (0..n * n)
            .map(|i| {
                let v = ((i % n + i / n) % 2) as f32;
                [v, v, v, 1.0]
            })
            .collect();
        Texels::from_rgba(n, n, texels).unwrap()
    }

    fn trilinear() -> Filtering {
        Filtering::of(&Sampler::default())
    }

    #[test]
    fn levels_halve_down_to_one_texel_and_keep_the_mean() {
        let p = Pyramid::new(grey_checker(8), false);
        let sides: Vec<_> = p.levels().iter().map(|l| (l.width(), l.height())).collect();
        assert_eq!(sides, [(8, 8), (4, 4), (2, 2), (1, 1)]);
        let f = Filtering::single(Filter::Nearest, [Wrap::Repeat; 2]);
        for l in &p.levels()[1..] {
            let v = l.sample(Vec2::new(0.3, 0.6), f.wrap, Filter::Nearest, false);
            assert!((v.x - 0.5).abs() < 1e-6, "{v}");
        }
        // Odd sides: 5 × 3 → 2 × 1 → 1 × 1, every texel counted once.
        let odd =
            Texels::from_rgba(5, 3, (0..15).map(|i| [i as f32, 0.0, 0.0, 1.0]).collect()).unwrap();
        let p = Pyramid::new(odd, false);
        let sides: Vec<_> = p.levels().iter().map(|l| (l.width(), l.height())).collect();
        assert_eq!(sides, [(5, 3), (2, 1), (1, 1)]);
        // Texel i is i: the left texel of level 1 averages columns 0–1 of the three rows,
        // the right one columns 2–4.
        let at = |level: usize, u: f32| {
            p.levels()[level]
                .sample(Vec2::new(u, 0.5), f.wrap, Filter::Nearest, false)
                .x
        };
        assert_eq!(at(1, 0.25), 33.0 / 6.0);
        assert_eq!(at(1, 0.75), 72.0 / 9.0);
        assert_eq!(at(2, 0.5), (33.0 / 6.0 + 8.0) / 2.0);
    }

    #[test]
    fn colour_levels_average_light_not_codes() {
        // Black and white texels average to half the light, whose sRGB code is 188, not
        // to code 128 (a fifth of the light).
        let t = Texels::from_rgba(2, 1, vec![[0.0, 0.0, 0.0, 1.0], [1.0, 1.0, 1.0, 1.0]]).unwrap();
        let p = Pyramid::new(t, true);
        let f = Filtering::single(Filter::Nearest, [Wrap::Repeat; 2]);
        let v = p.levels()[1].sample(Vec2::splat(0.5), f.wrap, Filter::Nearest, true);
        assert!((v.x - 0.5).abs() < 1e-5, "{v}");
    }

    #[test]
    fn the_footprint_picks_the_level() {
        // Values that differ from level to level.
        let texels = (0..64 * 64u32)
            .map(|i| {
                let v = ((i % 64) * 7 + (i / 64) * 13) % 17;
                [v as f32 / 16.0, 0.0, 0.0, 1.0]
            })
            .collect();
        let p = Pyramid::new(Texels::from_rgba(64, 64, texels).unwrap(), false);
        let f = trilinear();
        let uv = Vec2::new(0.3, 0.7);
        // A point, or a footprint under a texel: level 0, bilinear, exactly as before.
        let base = p.levels()[0].sample(uv, f.wrap, Filter::Linear, false);
        assert_eq!(p.sample(uv, f32::NEG_INFINITY, &f, false), base);
        assert_eq!(p.sample(uv, (0.5f32 / 64.0).log2(), &f, false), base);
        assert_eq!(p.sample(uv, f32::NAN, &f, false), base);
        // A footprint of 4 texels reads level 2; 6 texels blends levels 2 and 3.
        let level = |k: usize| p.levels()[k].sample(uv, f.wrap, Filter::Linear, false);
        assert_eq!(p.sample(uv, (4.0f32 / 64.0).log2(), &f, false), level(2));
        let lod = 6.0f32.log2();
        let blend = level(2) * (3.0 - lod) + level(3) * (lod - 2.0);
        let got = p.sample(uv, (6.0f32 / 64.0).log2(), &f, false);
        assert!((got - blend).abs().max_element() < 1e-6, "{got} {blend}");
        assert_ne!(level(2), level(3));
        // Past the top: the 1 × 1 level.
        assert_eq!(p.sample(uv, 10.0, &f, false), level(6));
        // A sampler that names no mipmaps reads level 0 whatever the footprint.
        let flat = Filtering {
            mipmap: Mipmap::None,
            ..f
        };
        assert_eq!(p.sample(uv, 10.0, &flat, false), base);
        // Nearest mipmap: the closest level.
        let near = Filtering {
            mipmap: Mipmap::Nearest,
            ..f
        };
        assert_eq!(p.sample(uv, (3.0f32 / 64.0).log2(), &near, false), level(2));
        assert_eq!(p.sample(uv, (2.5f32 / 64.0).log2(), &near, false), level(1));
    }
}
