//! The ray record (RAY1's 32 bytes) and the contract's validity rules.

/// One ray, laid out exactly as a RAY1 record (OptiX Prime's ORIGIN_TMIN_DIRECTION_TMAX).
///
/// The hit interval is the closed `[tmin, tmax]` in units of `dir`'s length; `dir` need
/// not be normalised. `tmin > tmax` is an empty interval and never hits.
#[repr(C)]
#[derive(Clone, Copy, Debug, PartialEq, Default, bytemuck::Pod, bytemuck::Zeroable)]
pub struct Ray {
    /// Origin.
    pub org: [f32; 3],
    /// Start of the hit interval (>= 0 for a valid ray).
    pub tmin: f32,
    /// Direction; not necessarily unit length, never zero for a valid ray.
    pub dir: [f32; 3],
    /// End of the hit interval; `+inf` allowed.
    pub tmax: f32,
}

const _: () = assert!(std::mem::size_of::<Ray>() == 32);

/// Why a ray is invalid under the contract (§2).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum RayError {
    /// A NaN or infinite origin component.
    NonFiniteOrigin,
    /// A NaN or infinite direction component.
    NonFiniteDirection,
    /// All three direction components are ±0.
    ZeroDirection,
    /// `tmin` is negative or NaN.
    BadTmin,
    /// `tmax` is NaN.
    NanTmax,
}

impl std::fmt::Display for RayError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(match self {
            RayError::NonFiniteOrigin => "origin has a NaN or infinite component",
            RayError::NonFiniteDirection => "direction has a NaN or infinite component",
            RayError::ZeroDirection => "direction is zero",
            RayError::BadTmin => "tmin is negative or NaN",
            RayError::NanTmax => "tmax is NaN",
        })
    }
}

/// Rays as a reader hands them on, with what reading them learned: a reader that checks
/// each ray while it is still in cache ([`Ray::is_valid`], a few instructions per ray) spares
/// the consumer a second pass over memory that has gone cold.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct RaySegment {
    /// The rays, in order.
    pub rays: Vec<Ray>,
    /// Every ray passed [`Ray::is_valid`]. `false` says nothing: check them
    /// ([`Ray::validate_batch`]).
    pub all_valid: bool,
}

impl RaySegment {
    /// Rays nobody has checked yet.
    pub fn unchecked(rays: Vec<Ray>) -> RaySegment {
        RaySegment {
            rays,
            all_valid: false,
        }
    }

    /// [`Ray::validate_batch`] of the rays, which a segment its reader vouched for skips.
    pub fn validate(&mut self, replace_invalid: bool) -> Option<InvalidRays> {
        if self.all_valid {
            None
        } else {
            Ray::validate_batch(&mut self.rays, replace_invalid)
        }
    }
}

/// Summary of the invalid rays in a batch: enough for the contract's error message.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct InvalidRays {
    /// Index of the first invalid ray.
    pub first_index: usize,
    /// Why that ray is invalid.
    pub first_reason: RayError,
    /// How many rays of the batch are invalid.
    pub count: usize,
}

impl InvalidRays {
    /// Adds what a check of a later part of the batch found (`later`, its indices counted
    /// from `offset`) to the summary so far: the first bad ray stays the first.
    pub fn absorb(summary: &mut Option<InvalidRays>, later: Option<InvalidRays>, offset: usize) {
        let Some(later) = later else { return };
        match summary {
            Some(first) => first.count += later.count,
            None => {
                *summary = Some(InvalidRays {
                    first_index: offset + later.first_index,
                    ..later
                })
            }
        }
    }
}

impl std::fmt::Display for InvalidRays {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(
            f,
            "{} invalid ray(s); the first is ray {}: {}",
            self.count, self.first_index, self.first_reason
        )
    }
}

impl Ray {
    /// A ray whose interval is empty: every accelerator answers it with a miss. Used in place
    /// of invalid rays under `invalid=miss`.
    pub const EMPTY: Ray = Ray {
        org: [0.0; 3],
        tmin: 1.0,
        dir: [1.0, 0.0, 0.0],
        tmax: 0.0,
    };

    /// Checks this ray against the contract's validity rules.
    pub fn check(&self) -> Result<(), RayError> {
        if !self.org.iter().all(|c| c.is_finite()) {
            return Err(RayError::NonFiniteOrigin);
        }
        if !self.dir.iter().all(|c| c.is_finite()) {
            return Err(RayError::NonFiniteDirection);
        }
        if self.dir.iter().all(|&c| c == 0.0) {
            return Err(RayError::ZeroDirection);
        }
        if self.tmin.is_nan() || self.tmin < 0.0 {
            return Err(RayError::BadTmin);
        }
        if self.tmax.is_nan() {
            return Err(RayError::NanTmax);
        }
        Ok(())
    }

    /// Validates a batch. With `replace_invalid` every invalid ray is replaced by
    /// [`Ray::EMPTY`] (so it is answered as a miss) and the summary is still returned;
    /// otherwise the rays are left untouched but for [`Ray::bound_tmax`].
    pub fn validate_batch(rays: &mut [Ray], replace_invalid: bool) -> Option<InvalidRays> {
        let mut summary: Option<InvalidRays> = None;
        // Almost every batch is valid: blocks that pass the branch-free test (which the
        // compiler vectorises) are skipped, and only a block with a bad ray is read again
        // ray by ray for the reason.
        const BLOCK: usize = 64;
        for (b, block) in rays.chunks_mut(BLOCK).enumerate() {
            let valid = block.iter_mut().fold(true, |all, r| {
                r.bound_tmax();
                all & r.is_valid()
            });
            if valid {
                continue;
            }
            Self::validate_slowly(block, b * BLOCK, replace_invalid, &mut summary);
        }
        summary
    }

    /// Makes a `tmax` of +inf the largest finite f32: the same interval for every finite
    /// t, and no hit at t = +inf, which a test whose t overflows (a direction of 1e-40,
    /// say) would otherwise report, against the contract's miss (t = +inf) and
    /// `proto/semantics.md` (a hit's t is finite). Done once as rays are read (by the
    /// RAY1 reader and [`Ray::validate_batch`]), so that no core tests for it. A NaN
    /// `tmax` (an invalid ray) is left as it is.
    #[inline]
    pub fn bound_tmax(&mut self) {
        if self.tmax == f32::INFINITY {
            self.tmax = f32::MAX;
        }
    }

    /// Whether [`Ray::check`] passes, computed without branches.
    #[inline]
    pub fn is_valid(&self) -> bool {
        const EXP: u32 = 0x7f80_0000;
        let finite = |x: f32| x.to_bits() & EXP != EXP;
        let [d0, d1, d2] = self.dir;
        let [o0, o1, o2] = self.org;
        finite(o0)
            & finite(o1)
            & finite(o2)
            & finite(d0)
            & finite(d1)
            & finite(d2)
            & ((d0.to_bits() | d1.to_bits() | d2.to_bits()) & !(1 << 31) != 0)
            & (self.tmin >= 0.0)
            & !self.tmax.is_nan()
    }

    /// [`Ray::validate_batch`] of one block whose first ray has index `first`, ray by ray.
    fn validate_slowly(
        rays: &mut [Ray],
        first: usize,
        replace_invalid: bool,
        summary: &mut Option<InvalidRays>,
    ) {
        for (i, ray) in rays.iter_mut().enumerate() {
            let i = first + i;
            if let Err(reason) = ray.check() {
                match summary {
                    Some(s) => s.count += 1,
                    None => {
                        *summary = Some(InvalidRays {
                            first_index: i,
                            first_reason: reason,
                            count: 1,
                        })
                    }
                }
                if replace_invalid {
                    *ray = Ray::EMPTY;
                }
            }
        }
    }

    /// The point at parameter `t`.
    #[inline]
    pub fn at(&self, t: f32) -> [f32; 3] {
        [
            self.org[0] + t * self.dir[0],
            self.org[1] + t * self.dir[1],
            self.org[2] + t * self.dir[2],
        ]
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn ray() -> Ray {
        Ray {
            org: [0.0; 3],
            tmin: 0.0,
            dir: [0.0, 0.0, 1.0],
            tmax: f32::INFINITY,
        }
    }

    #[test]
    fn each_rule_has_its_own_reason() {
        assert_eq!(ray().check(), Ok(()));
        let mut r = ray();
        r.org[1] = f32::NAN;
        assert_eq!(r.check(), Err(RayError::NonFiniteOrigin));
        let mut r = ray();
        r.dir[2] = f32::INFINITY;
        assert_eq!(r.check(), Err(RayError::NonFiniteDirection));
        let mut r = ray();
        r.dir = [0.0, -0.0, 0.0];
        assert_eq!(r.check(), Err(RayError::ZeroDirection));
        let mut r = ray();
        r.tmin = -1e-30;
        assert_eq!(r.check(), Err(RayError::BadTmin));
        let mut r = ray();
        r.tmin = f32::NAN;
        assert_eq!(r.check(), Err(RayError::BadTmin));
        let mut r = ray();
        r.tmax = f32::NAN;
        assert_eq!(r.check(), Err(RayError::NanTmax));
        // Allowed edge cases: empty intervals and infinite tmin.
        let mut r = ray();
        r.tmin = f32::INFINITY;
        r.tmax = 1.0;
        assert_eq!(r.check(), Ok(()));
        r.tmax = -5.0;
        assert_eq!(r.check(), Ok(()));
    }

    #[test]
    fn the_branch_free_test_agrees_with_check() {
        let specials = [
            0.0,
            -0.0,
            1.0,
            -2.5,
            f32::MIN_POSITIVE / 4.0,
            -f32::MIN_POSITIVE / 4.0,
            f32::MAX,
            f32::INFINITY,
            f32::NEG_INFINITY,
            f32::NAN,
            -f32::NAN,
        ];
        let mut rays = Vec::new();
        for &a in &specials {
            for &b in &specials {
                for field in 0..8 {
                    let mut r = ray();
                    match field {
                        0 => r.org = [a, 1.0, b],
                        1 => r.dir = [a, b, 0.0],
                        2 => r.dir = [0.0, a, b],
                        3 => (r.tmin, r.tmax) = (a, b),
                        4 => (r.org[1], r.dir[2]) = (a, b),
                        5 => (r.dir[0], r.tmin) = (a, b),
                        6 => (r.dir, r.tmax) = ([0.0, 0.0, a], b),
                        _ => (r.org[2], r.tmin) = (a, b),
                    }
                    assert_eq!(r.is_valid(), r.check().is_ok(), "{r:?}");
                    rays.push(r);
                }
            }
        }
        // And the blocked batch check finds the same first ray and count as ray by ray.
        let mut slow = None;
        Ray::validate_slowly(&mut rays.clone(), 0, false, &mut slow);
        assert_eq!(Ray::validate_batch(&mut rays, false), slow);
        assert!(slow.is_some_and(|s| s.count > 100));
    }

    #[test]
    fn batch_reports_first_index_and_count() {
        let mut rays = vec![ray(); 10];
        rays[3].tmax = f32::NAN;
        rays[7].dir = [0.0; 3];
        let s = Ray::validate_batch(&mut rays, false).unwrap();
        assert_eq!(
            (s.first_index, s.count, s.first_reason),
            (3, 2, RayError::NanTmax)
        );
        assert!(rays[3].tmax.is_nan());
        Ray::validate_batch(&mut rays, true).unwrap();
        assert_eq!(rays[3], Ray::EMPTY);
        assert_eq!(rays[7], Ray::EMPTY);
        assert!(Ray::validate_batch(&mut rays, false).is_none());
    }
}
