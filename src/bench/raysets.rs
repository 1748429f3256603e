//! The ray sets of a benchmark, made once from a fixed seed so that every accelerator
//! traces exactly the same rays.

use std::path::Path;

use rayon::prelude::*;

use super::{BenchError, View, ViewKind};
use crate::accel::{Intersector, Query};
use crate::formats::binary;
use crate::geometry::{Hit, Ray, Triangle};
use crate::render::rng::Pcg32;
use crate::render::sampling::cosine_hemisphere;
use crate::render::{facing_normal, offset_origin};

/// A kind of ray set (Áfra 2013, Table 3).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum SetKind {
    /// One ray per pixel through the pixel centre.
    Primary,
    /// One cosine-weighted `any` ray per primary hit, 1/8 of the scene diagonal long.
    Ao,
    /// The rays of diffuse bounce 1 (from the primary hits).
    Diffuse1,
    /// The rays of diffuse bounce 2.
    Diffuse2,
    /// The rays of diffuse bounce 8.
    Diffuse8,
}

impl SetKind {
    /// Every set, in report order.
    pub const ALL: [SetKind; 5] = [
        SetKind::Primary,
        SetKind::Ao,
        SetKind::Diffuse1,
        SetKind::Diffuse2,
        SetKind::Diffuse8,
    ];

    /// The command line's name.
    pub fn name(self) -> &'static str {
        match self {
            SetKind::Primary => "primary",
            SetKind::Ao => "ao",
            SetKind::Diffuse1 => "diffuse1",
            SetKind::Diffuse2 => "diffuse2",
            SetKind::Diffuse8 => "diffuse8",
        }
    }

    /// Parses the command line's name.
    pub fn parse(s: &str) -> Option<SetKind> {
        SetKind::ALL.into_iter().find(|k| k.name() == s)
    }

    /// For diffuse sets, which bounce.
    fn bounce(self) -> Option<u32> {
        match self {
            SetKind::Diffuse1 => Some(1),
            SetKind::Diffuse2 => Some(2),
            SetKind::Diffuse8 => Some(8),
            _ => None,
        }
    }
}

/// A ray set with the reference's answers.
pub struct RaySet {
    /// Which set.
    pub kind: SetKind,
    /// The rays.
    pub rays: Vec<Ray>,
    /// The reference accelerator's hits (`closest`; for AO, any hit marks occlusion).
    pub reference: Vec<Hit>,
}

/// Occlusion flags as hit records (any hit counts; its fields are not kept), so that AO
/// answers can be compared like the others.
pub(super) fn occlusion_hits(flags: &[u8]) -> Vec<Hit> {
    flags
        .iter()
        .map(|&f| {
            if f != 0 {
                Hit {
                    t: 0.0,
                    prim: 0,
                    u: 0.0,
                    v: 0.0,
                }
            } else {
                Hit::MISS
            }
        })
        .collect()
}

/// A cosine-weighted ray leaving the hit `hit` of `ray`, drawn from the stream of `index`.
fn bounce_ray(view: &View, ray: &Ray, hit: &Hit, seed: u64, index: usize, tmax: f32) -> Ray {
    let n = facing_normal(&view.triangles[hit.prim as usize], ray.dir);
    let mut rng = Pcg32::new(seed, index as u64);
    let d = cosine_hemisphere(n, rng.next_f32(), rng.next_f32());
    Ray {
        org: offset_origin(ray.at(hit.t), n),
        tmin: 0.0,
        dir: d,
        tmax,
    }
}

/// Makes the requested sets with `tracer` (also the reference). Paths go on from every hit
/// without Russian roulette; rays that miss leave the batch (never, in interior views).
pub fn make_sets(
    view: &View,
    tracer: &dyn Intersector,
    kinds: &[SetKind],
    seed: u64,
) -> Vec<RaySet> {
    let (w, h) = (view.width, view.height);
    let primary: Vec<Ray> = (0..w as usize * h as usize)
        .into_par_iter()
        .map(|p| {
            let (x, y) = ((p % w as usize) as f64 + 0.5, (p / w as usize) as f64 + 0.5);
            view.camera.ray(x, y, w, h)
        })
        .collect();
    let mut primary_hits = vec![Hit::MISS; primary.len()];
    tracer.trace(&primary, Query::Closest, &mut primary_hits);
    let mut out = Vec::new();
    if kinds.contains(&SetKind::Primary) {
        out.push(RaySet {
            kind: SetKind::Primary,
            rays: primary.clone(),
            reference: primary_hits.clone(),
        });
    }
    if kinds.contains(&SetKind::Ao) {
        let dist = view.diagonal / 8.0;
        let rays: Vec<Ray> = primary
            .par_iter()
            .zip(&primary_hits)
            .enumerate()
            .filter(|(_, (_, h))| h.is_hit())
            .map(|(i, (r, h))| bounce_ray(view, r, h, seed ^ 0xA0, i, dist))
            .collect();
        let mut flags = vec![0u8; rays.len()];
        tracer.occluded(&rays, &mut flags);
        let reference = occlusion_hits(&flags);
        out.push(RaySet {
            kind: SetKind::Ao,
            rays,
            reference,
        });
    }
    let deepest = kinds.iter().filter_map(|k| k.bounce()).max().unwrap_or(0);
    let (mut rays, mut hits) = (primary, primary_hits);
    for bounce in 1..=deepest {
        let next: Vec<Ray> = rays
            .par_iter()
            .zip(&hits)
            .enumerate()
            .filter(|(_, (_, h))| h.is_hit())
            .map(|(i, (r, h))| {
                bounce_ray(
                    view,
                    r,
                    h,
                    seed.wrapping_add(bounce as u64),
                    i,
                    f32::INFINITY,
                )
            })
            .collect();
        let mut next_hits = vec![Hit::MISS; next.len()];
        tracer.trace(&next, Query::Closest, &mut next_hits);
        rays = next;
        hits = next_hits;
        if let Some(&kind) = kinds.iter().find(|k| k.bounce() == Some(bounce)) {
            out.push(RaySet {
                kind,
                rays: rays.clone(),
                reference: hits.clone(),
            });
        }
    }
    out.sort_by_key(|s| SetKind::ALL.iter().position(|k| *k == s.kind));
    out
}

/// Writes every set as `<scene>-<view>-<set>.ray` (RAY1) and the reference hits as
/// `….hit` (HIT1; AO sets in the `occluded` format), and the triangles they were traced
/// against as `<scene>-<view>.tri` (TRI1): the hits' ids name those, which in an interior
/// view are the scene's followed by the room's walls.
pub fn dump(
    dir: &Path,
    scene: &Path,
    view: ViewKind,
    traced: &[Triangle],
    sets: &[RaySet],
) -> Result<(), BenchError> {
    let io = |path: &Path, source| BenchError::Io {
        path: path.display().to_string(),
        source,
    };
    if dir.exists() && !dir.is_dir() {
        return Err(BenchError::Config(format!(
            "--dump {}: exists and is not a directory",
            dir.display()
        )));
    }
    std::fs::create_dir_all(dir).map_err(|e| io(dir, e))?;
    let stem = scene
        .file_stem()
        .and_then(|s| s.to_str())
        .unwrap_or("scene");
    // The triangles the sets were traced against, whose ids the hits name: the scene's
    // (same ids) and then, in an interior view, the room's walls around it.
    let tri_path = dir.join(format!("{stem}-{}.tri", view.name()));
    std::fs::write(&tri_path, binary::write_tri(traced)).map_err(|e| io(&tri_path, e))?;
    for set in sets {
        let base = format!("{stem}-{}-{}", view.name(), set.kind.name());
        let ray_path = dir.join(format!("{base}.ray"));
        std::fs::write(&ray_path, binary::write_rays(&set.rays)).map_err(|e| io(&ray_path, e))?;
        let format = if set.kind == SetKind::Ao {
            binary::HitFormat::Occluded
        } else {
            binary::HitFormat::TPrimUv
        };
        let hit_path = dir.join(format!("{base}.hit"));
        std::fs::write(&hit_path, binary::write_hits(&set.reference, format))
            .map_err(|e| io(&hit_path, e))?;
    }
    Ok(())
}
