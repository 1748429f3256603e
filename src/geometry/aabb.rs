//! Axis-aligned bounding boxes.

/// An axis-aligned box; the empty box has `min = +inf`, `max = -inf` so that growing it by
/// any point gives that point.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Aabb {
    /// Lower corner.
    pub min: [f32; 3],
    /// Upper corner.
    pub max: [f32; 3],
}

impl Aabb {
    /// The empty box.
    pub const EMPTY: Aabb = Aabb {
        min: [f32::INFINITY; 3],
        max: [f32::NEG_INFINITY; 3],
    };

    /// Whether no point is inside.
    pub fn is_empty(&self) -> bool {
        (0..3).any(|k| self.min[k] > self.max[k])
    }

    /// Grows the box to contain `p`.
    #[inline]
    pub fn grow(&mut self, p: [f32; 3]) {
        for (k, x) in p.into_iter().enumerate() {
            self.min[k] = self.min[k].min(x);
            self.max[k] = self.max[k].max(x);
        }
    }

    /// Grows the box to contain `other`.
    #[inline]
    pub fn union(&mut self, other: &Aabb) {
        for k in 0..3 {
            self.min[k] = self.min[k].min(other.min[k]);
            self.max[k] = self.max[k].max(other.max[k]);
        }
    }

    /// Extent along each axis (zero for the empty box).
    pub fn extent(&self) -> [f32; 3] {
        if self.is_empty() {
            return [0.0; 3];
        }
        [
            self.max[0] - self.min[0],
            self.max[1] - self.min[1],
            self.max[2] - self.min[2],
        ]
    }

    /// Length of the diagonal (zero for the empty box).
    pub fn diagonal(&self) -> f32 {
        let e = self.extent();
        (e[0] as f64 * e[0] as f64 + e[1] as f64 * e[1] as f64 + e[2] as f64 * e[2] as f64).sqrt()
            as f32
    }

    /// Centre point.
    pub fn center(&self) -> [f32; 3] {
        [
            0.5 * (self.min[0] + self.max[0]),
            0.5 * (self.min[1] + self.max[1]),
            0.5 * (self.min[2] + self.max[2]),
        ]
    }

    /// Largest |coordinate| of the corners (0 for the empty box): the magnitude that sets
    /// the rounding error of anything computed from points inside.
    pub fn max_abs(&self) -> f32 {
        if self.is_empty() {
            return 0.0;
        }
        self.min
            .iter()
            .chain(&self.max)
            .fold(0.0f32, |m, x| m.max(x.abs()))
    }

    /// Surface area (zero for the empty box).
    pub fn area(&self) -> f32 {
        let e = self.extent();
        2.0 * (e[0] * e[1] + e[1] * e[2] + e[2] * e[0])
    }
}
