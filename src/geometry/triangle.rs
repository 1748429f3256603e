//! Triangles as the accelerators see them: three f32 world-space vertices.

use super::Aabb;

/// One triangle, laid out exactly as a TRI1 record (`v0, v1, v2` as 9 × f32).
#[repr(C)]
#[derive(Clone, Copy, Debug, PartialEq, Default)]
pub struct Triangle {
    /// The vertices, in the file's winding order.
    pub v: [[f32; 3]; 3],
}

const _: () = assert!(std::mem::size_of::<Triangle>() == 36);

impl Triangle {
    /// Bounding box of the three vertices.
    pub fn bounds(&self) -> Aabb {
        let mut b = Aabb::EMPTY;
        for p in self.v {
            b.grow(p);
        }
        b
    }

    /// Whether the triangle has zero area as stored in f32: the cross product of its edges,
    /// computed in f64 from the stored coordinates, is exactly zero (collinear or coincident
    /// vertices). The contract says such triangles are never hit; every accelerator leaves
    /// them out. f64 makes the test independent of the f32 rounding of the edge vectors for
    /// all but pathological exponent ranges. Inline: the builders call it once per
    /// triangle, and when a change elsewhere moved it out of their codegen unit the call
    /// cost a `fast` build of the dragon about 10%.
    #[inline]
    pub fn is_degenerate(&self) -> bool {
        let p = self.v.map(|q| q.map(f64::from));
        let e1 = [p[1][0] - p[0][0], p[1][1] - p[0][1], p[1][2] - p[0][2]];
        let e2 = [p[2][0] - p[0][0], p[2][1] - p[0][1], p[2][2] - p[0][2]];
        let n = [
            e1[1] * e2[2] - e1[2] * e2[1],
            e1[2] * e2[0] - e1[0] * e2[2],
            e1[0] * e2[1] - e1[1] * e2[0],
        ];
        n == [0.0; 3]
    }

    /// Geometric normal `(v1-v0) × (v2-v0)`, not normalised.
    pub fn normal(&self) -> [f32; 3] {
        super::cross(
            super::sub(self.v[1], self.v[0]),
            super::sub(self.v[2], self.v[0]),
        )
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn degeneracy() {
        let t = Triangle {
            v: [[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]],
        };
        assert!(!t.is_degenerate());
        let line = Triangle {
            v: [[0.0, 0.0, 0.0], [1.0, 1.0, 1.0], [2.0, 2.0, 2.0]],
        };
        assert!(line.is_degenerate());
        let point = Triangle { v: [[3.0; 3]; 3] };
        assert!(point.is_degenerate());
        // Tiny but not zero area stays a triangle.
        let tiny = Triangle {
            v: [[0.0, 0.0, 0.0], [1e-20, 0.0, 0.0], [0.0, 1e-20, 0.0]],
        };
        assert!(!tiny.is_degenerate());
    }
}
