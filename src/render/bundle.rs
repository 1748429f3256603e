//! A material's textures stored texel by texel together.
//!
//! glTF materials usually read their base colour, metallic-roughness, normal and emissive
//! textures through one texture coordinate set, at one size and with one sampler
//! (DamagedHelmet's four are 2048² JPEGs). Stored apart, one shading point's four lookups
//! touch four images: four cache lines (and pages) per tap, most of them misses, and on
//! that scene half of a path frame's shading. Interleaved, each tap is one 16-byte record
//! holding the four texels, so a shading point reads a quarter of the lines. A bundle is
//! built only where that holds exactly, and its lookups do the arithmetic of
//! [`Pyramid::sample`] slot by slot, so images stay bit-identical.

use glam::{Vec2, Vec4};

use super::mipmap::{across_levels, Filtering, Pyramid};
use super::texture::{decode_tables, filter_level, Bilinear, Blend, SLOTS, SLOT_IS_COLOUR};
use crate::scene::Filter;

/// Fewest textures a bundle takes: its records hold four, so with three at most a quarter
/// of it is padding (with two, half would be).
pub const MIN_SLOTS: usize = 3;

/// One level: four 8-bit RGBA texels per position.
#[derive(Debug)]
struct Level {
    width: u32,
    height: u32,
    texels: Vec<[[u8; 4]; SLOTS]>,
}

/// Side, in texels, of the blocks of level 0 that [`Bundle::emission_black_at`] knows black.
const BLOCK: usize = 16;

impl Level {
    /// The bilinear taps at `uv` (wrapped by `wrap`); `None` where `uv` puts them
    /// nowhere (not finite), which [`filter_level`] reads as texel (0, 0). One computation
    /// for the lookup, its prefetch and the emissive block table.
    #[inline(always)]
    fn bilinear(&self, uv: Vec2, wrap: [crate::scene::Wrap; 2]) -> Option<Bilinear> {
        let (w, h) = (i64::from(self.width), i64::from(self.height));
        let x = uv.x * w as f32 - 0.5;
        let y = uv.y * h as f32 - 0.5;
        (x.is_finite() && y.is_finite()).then(|| Bilinear::at(x, y, (w, h), wrap))
    }
}

/// Up to four textures of equal size, levels and sampler, interleaved.
#[derive(Debug)]
pub struct Bundle {
    levels: Vec<Level>,
    log2_texels_per_unit: f32,
    filtering: Filtering,
    tex_coord: u32,
    present: [bool; SLOTS],
    /// Per [`BLOCK`] × [`BLOCK`] block of level 0, row by row, whether any emissive texel
    /// (slot 3) in it has a colour other than black; empty without an emissive texture.
    lit: Vec<bool>,
}

impl Bundle {
    /// The bundle of `slots` (base colour, metallic-roughness, normal, emissive: each a
    /// pyramid built for its slot's use, or `None`), all sampled with `filtering` and read
    /// through coordinate set `tex_coord`: `None` unless at least [`MIN_SLOTS`] are present
    /// and they have 8-bit texels and the same levels.
    pub fn of(
        slots: [Option<&Pyramid>; SLOTS],
        filtering: Filtering,
        tex_coord: u32,
    ) -> Option<Bundle> {
        let present = slots.map(|p| p.is_some());
        let first = slots.iter().flatten().next()?;
        if present.iter().filter(|&&p| p).count() < MIN_SLOTS {
            return None;
        }
        let count = first.levels().len();
        let mut levels = Vec::with_capacity(count);
        for k in 0..count {
            let base = &first.levels()[k];
            let (width, height) = (base.width(), base.height());
            let mut parts: [Option<&[[u8; 4]]>; SLOTS] = [None; SLOTS];
            for (part, p) in parts.iter_mut().zip(slots) {
                let Some(p) = p else { continue };
                let l = p.levels().get(k)?;
                if (l.width(), l.height()) != (width, height) || p.levels().len() != count {
                    return None;
                }
                *part = Some(l.rgba8()?);
            }
            let texels = (0..width as usize * height as usize)
                .map(|i| parts.map(|part| part.map_or([0; 4], |t| t[i])))
                .collect();
            levels.push(Level {
                width,
                height,
                texels,
            });
        }
        let lit = if present[3] {
            lit_blocks(&levels[0])
        } else {
            Vec::new()
        };
        Some(Bundle {
            levels,
            log2_texels_per_unit: first.log2_texels_per_unit(),
            filtering,
            tex_coord,
            present,
            lit,
        })
    }

    /// Whether a point lookup (level 0) of the emissive texture at `uv` reads black
    /// texels only, so that its colour is exactly black without reading them. Emission
    /// is read at level 0 by every light sample and every hit after a scattering
    /// (`Surfaces::finish`), and DamagedHelmet's emissive texture, 64 MiB of records at
    /// level 0 with the other three, is black but for its lamps: a block table of a few
    /// kilobytes answers most of those reads from cache. `false` where it cannot tell.
    pub fn emission_black_at(&self, uv: Vec2) -> bool {
        if self.lit.is_empty() {
            return false;
        }
        // The taps level 0 reads (`Bundle::level` with the magnification filter): the
        // bilinear four, a superset of the nearest one.
        let l = &self.levels[0];
        let Some(b) = l.bilinear(uv, self.filtering.wrap) else {
            return false;
        };
        let (xs, ys) = (b.x, b.y);
        let across = (l.width as usize).div_ceil(BLOCK);
        ys.iter().all(|&j| {
            xs.iter()
                .all(|&i| !self.lit[j as usize / BLOCK * across + i as usize / BLOCK])
        })
    }

    /// Bytes of texels held, every level (and the emissive block table).
    pub fn bytes(&self) -> usize {
        self.levels
            .iter()
            .map(|l| std::mem::size_of_val(&l.texels[..]))
            .sum::<usize>()
            + self.lit.len()
    }

    /// The coordinate set its textures read.
    pub fn tex_coord(&self) -> u32 {
        self.tex_coord
    }

    /// The four textures at `uv` for a footprint of `2^log2_width` units (`None` for the
    /// slots the bundle lacks): what [`Pyramid::sample`] of each gives, bit for bit.
    pub fn sample(&self, uv: Vec2, log2_width: f32) -> [Option<Vec4>; SLOTS] {
        let values = self.filtered(uv, log2_width, self.present);
        let mut out = [None; SLOTS];
        for s in 0..SLOTS {
            if self.present[s] {
                out[s] = Some(values[s]);
            }
        }
        out
    }

    /// Slot `slot` alone at `uv` (alpha tests and light sampling read one texture at
    /// level 0): the same value [`Bundle::sample`] gives it.
    pub fn sample_slot(&self, slot: usize, uv: Vec2, log2_width: f32) -> Option<Vec4> {
        let mut only = [false; SLOTS];
        only[slot] = *self.present.get(slot)?;
        only[slot].then(|| self.filtered(uv, log2_width, only)[slot])
    }

    /// Asks the caches for the records that [`Bundle::sample`] at `uv` and `log2_width`
    /// will read: the four taps of each level it filters (a superset for nearest
    /// filtering). Only a hint.
    #[inline]
    pub fn prefetch(&self, uv: Vec2, log2_width: f32) {
        let lod = log2_width + self.log2_texels_per_unit;
        across_levels(lod, &self.filtering, self.levels.len() - 1, |k, _| {
            let l = &self.levels[k];
            let Some(b) = l.bilinear(uv, self.filtering.wrap) else {
                return;
            };
            let base = l.texels.as_ptr();
            for row in b.y {
                for col in b.x {
                    let i = row as usize * l.width as usize + col as usize;
                    crate::simd::prefetch(base.wrapping_add(i).cast(), 1);
                }
            }
        })
    }

    /// The filtered values of the slots in `mask` (the others are left zero).
    #[inline]
    fn filtered(&self, uv: Vec2, log2_width: f32, mask: [bool; SLOTS]) -> [Vec4; SLOTS] {
        let lod = log2_width + self.log2_texels_per_unit;
        across_levels(lod, &self.filtering, self.levels.len() - 1, |k, filter| {
            self.level(k, uv, filter, mask)
        })
    }

    /// Level `k` at `uv` with `filter`, each slot in `mask` as
    /// [`super::texture::Texels::sample`] computes it. Bilinear lookups (nearly all) read
    /// the four records once and then filter slot by slot, which callgrind counts 13%
    /// cheaper than [`filter_level`] over `[Vec4; 4]` (BENCHMARKS.md §31: these lookups
    /// are about a quarter of a textured path frame's shading instructions).
    #[inline]
    fn level(&self, k: usize, uv: Vec2, filter: Filter, mask: [bool; SLOTS]) -> [Vec4; SLOTS] {
        let l = &self.levels[k];
        let tables = decode_tables();
        let slot = |p: &[[u8; 4]; SLOTS], s: usize| tables.decode(p[s], SLOT_IS_COLOUR[s]);
        let bilinear = match filter {
            Filter::Linear => l.bilinear(uv, self.filtering.wrap),
            Filter::Nearest => None,
        };
        let Some(b) = bilinear else {
            return filter_level(
                uv,
                (l.width, l.height),
                self.filtering.wrap,
                filter,
                |x, y| {
                    let p = &l.texels[y as usize * l.width as usize + x as usize];
                    std::array::from_fn(|s| if mask[s] { slot(p, s) } else { Vec4::ZERO })
                },
            );
        };
        let w = l.width as usize;
        let (row0, row1) = (b.y[0] as usize * w, b.y[1] as usize * w);
        let (x0, x1) = (b.x[0] as usize, b.x[1] as usize);
        let taps = [
            &l.texels[row0 + x0],
            &l.texels[row0 + x1],
            &l.texels[row1 + x0],
            &l.texels[row1 + x1],
        ];
        std::array::from_fn(|s| {
            if !mask[s] {
                return Vec4::ZERO;
            }
            let top = slot(taps[0], s).blend(slot(taps[1], s), b.fx);
            let bottom = slot(taps[2], s).blend(slot(taps[3], s), b.fx);
            top.blend(bottom, b.fy)
        })
    }
}

/// [`Bundle::lit`] of level `l`.
fn lit_blocks(l: &Level) -> Vec<bool> {
    let (w, h) = (l.width as usize, l.height as usize);
    let across = w.div_ceil(BLOCK);
    let mut lit = vec![false; across * h.div_ceil(BLOCK)];
    for (j, row) in l.texels.chunks_exact(w).enumerate() {
        for (i, t) in row.iter().enumerate() {
            if t[3][..3] != [0, 0, 0] {
                lit[j / BLOCK * across + i / BLOCK] = true;
            }
        }
    }
    lit
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::render::texture::Texels;
    use crate::scene::{Mipmap, Sampler, Wrap};

    /// An 8-bit image of `w` × `h` assorted codes, decoded from PNG bytes as glTF images
    /// are (so that its texels are 8-bit).
    fn image(w: u32, h: u32, seed: u32) -> Texels {
        let mut png = Vec::new();
        {
            let mut e = ::png::Encoder::new(&mut png, w, h);
            e.set_color(::png::ColorType::Rgba);
            let mut out = e.write_header().unwrap();
            let data: Vec<u8> = (0..w * h * 4)
                .map(|i| ((i * 2654435761u32.wrapping_add(seed)) >> 13) as u8)
                .collect();
            out.write_image_data(&data).unwrap();
        }
        Texels::decode(&png).unwrap()
    }

    /// An 8-bit image of `w` × `h` texels, texel `i` (row by row) `f(i)`.
    fn image_with(w: u32, h: u32, f: impl Fn(u32) -> [u8; 4]) -> Texels {
        let mut png = Vec::new();
        {
            let mut e = ::png::Encoder::new(&mut png, w, h);
            e.set_color(::png::ColorType::Rgba);
            let mut out = e.write_header().unwrap();
            let data: Vec<u8> = (0..w * h).flat_map(&f).collect();
            out.write_image_data(&data).unwrap();
        }
        Texels::decode(&png).unwrap()
    }

    /// Where the block table says a point lookup of the emissive texture is black, the
    /// lookup itself reads black (every sampler, coordinates outside [0, 1] included); it
    /// says so over most of a texture black but for two texels, and never at those.
    #[test]
    fn emission_known_black_is_black() {
        let (w, h) = (70, 40);
        let lit = [(3u32, 5u32), (69, 39)];
        let emissive = image_with(w, h, |i| {
            if lit.contains(&(i % w, i / w)) {
                [200, 0, 0, 255]
            } else {
                [0, 0, 0, 255]
            }
        });
        let other = image(w, h, 5);
        let pyramids = [
            Pyramid::new(other.clone(), true),
            Pyramid::new(other.clone(), false),
            Pyramid::new(other, false),
            Pyramid::new(emissive, true),
        ];
        for sampler in [
            Sampler::default(),
            Sampler {
                mag_filter: Some(Filter::Nearest),
                wrap_s: Wrap::MirroredRepeat,
                wrap_t: Wrap::ClampToEdge,
                ..Sampler::default()
            },
        ] {
            let f = Filtering::of(&sampler);
            let b = Bundle::of(pyramids.each_ref().map(Some), f, 0).unwrap();
            let mut black = 0;
            for i in 0..5000 {
                let uv = Vec2::new(
                    (i % 97) as f32 * 0.0127 - 0.1,
                    (i * 31 % 89) as f32 * 0.0131 - 0.1,
                );
                let value = b.sample_slot(3, uv, f32::NEG_INFINITY).unwrap();
                if b.emission_black_at(uv) {
                    black += 1;
                    assert_eq!(value.truncate(), glam::Vec3::ZERO, "{sampler:?} at {uv}");
                }
            }
            assert!(black > 4000, "{sampler:?}: black at {black} of 5000");
            for (x, y) in lit {
                let uv = Vec2::new((x as f32 + 0.5) / w as f32, (y as f32 + 0.5) / h as f32);
                assert!(
                    !b.emission_black_at(uv),
                    "{sampler:?} at the lit texel {uv}"
                );
            }
        }
        // Without an emissive texture it cannot tell.
        let f = Filtering::of(&Sampler::default());
        let b = Bundle::of(
            [
                Some(&pyramids[0]),
                Some(&pyramids[1]),
                Some(&pyramids[2]),
                None,
            ],
            f,
            0,
        )
        .unwrap();
        assert!(!b.emission_black_at(Vec2::new(0.5, 0.5)));
    }

    #[test]
    fn bundled_lookups_are_the_separate_lookups_bit_for_bit() {
        let (w, h) = (37, 20);
        let pyramids: Vec<Pyramid> = (0..SLOTS)
            .map(|s| Pyramid::new(image(w, h, s as u32 * 7919), SLOT_IS_COLOUR[s]))
            .collect();
        let samplers = [
            Sampler::default(),
            Sampler {
                min_filter: Some(Filter::Nearest),
                mipmap: Mipmap::Nearest,
                mag_filter: Some(Filter::Nearest),
                wrap_s: Wrap::MirroredRepeat,
                wrap_t: Wrap::ClampToEdge,
            },
            Sampler {
                min_filter: Some(Filter::Linear),
                mipmap: Mipmap::None,
                ..Sampler::default()
            },
        ];
        for sampler in samplers {
            let f = Filtering::of(&sampler);
            // Without the metallic-roughness texture, as a material may be.
            let slots = [
                Some(&pyramids[0]),
                None,
                Some(&pyramids[2]),
                Some(&pyramids[3]),
            ];
            let b = Bundle::of(slots, f, 0).unwrap();
            for i in 0..400 {
                let uv = Vec2::new(i as f32 * 0.0173 - 1.3, (i * 7 % 97) as f32 * 0.031 - 0.8);
                let log2_width = (i % 23) as f32 * 0.5 - 9.0;
                // Prefetching reads nothing and changes nothing, at any coordinates.
                b.prefetch(uv, log2_width);
                b.prefetch(uv * 1e30, -log2_width);
                b.prefetch(Vec2::NAN, log2_width);
                let got = b.sample(uv, log2_width);
                for s in 0..SLOTS {
                    let want = slots[s].map(|p| p.sample(uv, log2_width, &f, SLOT_IS_COLOUR[s]));
                    assert_eq!(got[s], want, "{sampler:?} slot {s} at {uv} {log2_width}");
                    assert_eq!(b.sample_slot(s, uv, log2_width), want);
                }
            }
        }
        // Textures of different sizes, or a lone texture, make no bundle.
        let other = Pyramid::new(image(w + 1, h, 1), false);
        let f = Filtering::of(&Sampler::default());
        assert!(Bundle::of([Some(&pyramids[0]), Some(&other), None, None], f, 0).is_none());
        assert!(Bundle::of([Some(&pyramids[0]), None, None, None], f, 0).is_none());
    }
}
