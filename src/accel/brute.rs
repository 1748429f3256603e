//! Brute force (placeholder).
use super::{Intersector, Precision, Query};
use crate::geometry::{Hit, Ray, Triangle};

/// Every ray against every triangle.
pub struct Brute {
    tris: Vec<Triangle>,
}

impl Brute {
    /// Builds.
    pub fn new(triangles: &[Triangle], _precision: Precision) -> Brute {
        Brute {
            tris: triangles.to_vec(),
        }
    }
}

impl Intersector for Brute {
    fn name(&self) -> &'static str {
        "brute"
    }
    fn trace(&self, rays: &[Ray], _query: Query, hits: &mut [Hit]) {
        for (r, h) in rays.iter().zip(hits.iter_mut()) {
            *h = Hit::MISS;
            for (i, t) in self.tris.iter().enumerate() {
                let e1 = crate::geometry::sub(t.v[1], t.v[0]);
                let e2 = crate::geometry::sub(t.v[2], t.v[0]);
                let p = crate::geometry::cross(r.dir, e2);
                let det = crate::geometry::dot(e1, p);
                if det == 0.0 {
                    continue;
                }
                let inv = 1.0 / det;
                let s = crate::geometry::sub(r.org, t.v[0]);
                let u = crate::geometry::dot(s, p) * inv;
                if !(0.0..=1.0).contains(&u) {
                    continue;
                }
                let q = crate::geometry::cross(s, e1);
                let v = crate::geometry::dot(r.dir, q) * inv;
                if v < 0.0 || u + v > 1.0 {
                    continue;
                }
                let tt = crate::geometry::dot(e2, q) * inv;
                if tt >= r.tmin && tt <= r.tmax && tt < h.t {
                    *h = Hit {
                        t: tt,
                        prim: i as u32,
                        u,
                        v,
                    };
                }
            }
        }
    }
    fn bytes(&self) -> usize {
        0
    }
}
