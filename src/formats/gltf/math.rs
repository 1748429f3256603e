//! The little f64 linear algebra the loader needs: column-major 4×4 affine matrices and
//! unit quaternions. Everything is f64 so that a world position is rounded to f32 only once.

/// Column-major 4×4 matrix: `m[column][row]`, the layout of glTF's `matrix` and of
/// [`crate::scene::Camera::to_world`].
pub(super) type Mat4 = [[f64; 4]; 4];

/// The identity matrix.
pub(super) const IDENTITY: Mat4 = [
    [1.0, 0.0, 0.0, 0.0],
    [0.0, 1.0, 0.0, 0.0],
    [0.0, 0.0, 1.0, 0.0],
    [0.0, 0.0, 0.0, 1.0],
];

/// `a · b`.
pub(super) fn mul(a: &Mat4, b: &Mat4) -> Mat4 {
    let mut out = [[0.0; 4]; 4];
    for (c, col) in out.iter_mut().enumerate() {
        for (r, v) in col.iter_mut().enumerate() {
            *v = (0..4).map(|k| a[k][r] * b[c][k]).sum();
        }
    }
    out
}

/// `m · (p, 1)`, keeping x, y, z. glTF node matrices are affine (they must decompose into
/// TRS), so the bottom row is not used: no perspective divide.
#[inline]
pub(super) fn transform_point(m: &Mat4, p: [f64; 3]) -> [f64; 3] {
    [
        m[0][0] * p[0] + m[1][0] * p[1] + m[2][0] * p[2] + m[3][0],
        m[0][1] * p[0] + m[1][1] * p[1] + m[2][1] * p[2] + m[3][1],
        m[0][2] * p[0] + m[1][2] * p[1] + m[2][2] * p[2] + m[3][2],
    ]
}

/// `a + w·b`, element-wise.
pub(super) fn add_scaled(a: &mut Mat4, w: f64, b: &Mat4) {
    for c in 0..4 {
        for r in 0..4 {
            a[c][r] += w * b[c][r];
        }
    }
}

/// A matrix from 16 column-major values.
pub(super) fn from_cols(v: &[f64]) -> Mat4 {
    let mut m = [[0.0; 4]; 4];
    for c in 0..4 {
        for r in 0..4 {
            m[c][r] = v[c * 4 + r];
        }
    }
    m
}

/// `T · R · S` from a translation, a unit quaternion `(x, y, z, w)` and a scale.
pub(super) fn from_trs(t: [f64; 3], q: [f64; 4], s: [f64; 3]) -> Mat4 {
    let [x, y, z, w] = q;
    let r = [
        [
            1.0 - 2.0 * (y * y + z * z),
            2.0 * (x * y + z * w),
            2.0 * (x * z - y * w),
        ],
        [
            2.0 * (x * y - z * w),
            1.0 - 2.0 * (x * x + z * z),
            2.0 * (y * z + x * w),
        ],
        [
            2.0 * (x * z + y * w),
            2.0 * (y * z - x * w),
            1.0 - 2.0 * (x * x + y * y),
        ],
    ];
    [
        [r[0][0] * s[0], r[0][1] * s[0], r[0][2] * s[0], 0.0],
        [r[1][0] * s[1], r[1][1] * s[1], r[1][2] * s[1], 0.0],
        [r[2][0] * s[2], r[2][1] * s[2], r[2][2] * s[2], 0.0],
        [t[0], t[1], t[2], 1.0],
    ]
}

/// `q / |q|`; `None` for a zero or non-finite quaternion, which names no rotation.
pub(super) fn normalize_quat(q: [f64; 4]) -> Option<[f64; 4]> {
    let n = q.iter().map(|v| v * v).sum::<f64>().sqrt();
    if n.is_finite() && n > 0.0 {
        Some(q.map(|v| v / n))
    } else {
        None
    }
}

/// Spherical linear interpolation from `a` to `b` (both unit) along the shorter arc.
pub(super) fn slerp(a: [f64; 4], b: [f64; 4], s: f64) -> [f64; 4] {
    let mut d: f64 = (0..4).map(|i| a[i] * b[i]).sum();
    // q and −q are the same rotation: flip one so the path is the short one.
    let b = if d < 0.0 {
        d = -d;
        b.map(|v| -v)
    } else {
        b
    };
    let (wa, wb) = if d > 0.9995 {
        // Nearly parallel: sin θ ≈ 0, so the slerp weights are ill-conditioned; a normalised
        // lerp differs from slerp by far less than f32 rounding here.
        (1.0 - s, s)
    } else {
        let theta = d.acos();
        let sin = theta.sin();
        (((1.0 - s) * theta).sin() / sin, (s * theta).sin() / sin)
    };
    let q = [0, 1, 2, 3].map(|i| wa * a[i] + wb * b[i]);
    normalize_quat(q).unwrap_or(a)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn close(a: &[f64], b: &[f64]) -> bool {
        a.iter().zip(b).all(|(x, y)| (x - y).abs() < 1e-12)
    }

    #[test]
    fn trs_matches_composition() {
        // 90° about +Z maps +X to +Y.
        let h = std::f64::consts::FRAC_1_SQRT_2;
        let m = from_trs([1.0, 2.0, 3.0], [0.0, 0.0, h, h], [2.0, 2.0, 2.0]);
        let p = transform_point(&m, [1.0, 0.0, 0.0]);
        assert!(close(&p, &[1.0, 4.0, 3.0]), "{p:?}");
        let t = from_trs([1.0, 2.0, 3.0], [0.0, 0.0, 0.0, 1.0], [1.0; 3]);
        let rs = from_trs([0.0; 3], [0.0, 0.0, h, h], [2.0; 3]);
        let m2 = mul(&t, &rs);
        for c in 0..4 {
            assert!(close(&m[c], &m2[c]));
        }
    }

    #[test]
    fn slerp_halfway_and_short_arc() {
        let h = std::f64::consts::FRAC_1_SQRT_2;
        let a = [0.0, 0.0, 0.0, 1.0];
        let b = [0.0, 0.0, h, h]; // 90° about z
        let m = slerp(a, b, 0.5);
        let s = (std::f64::consts::PI / 8.0).sin();
        let c = (std::f64::consts::PI / 8.0).cos();
        assert!(close(&m, &[0.0, 0.0, s, c]), "{m:?}");
        // −b is the same rotation: the result must be the same up to sign.
        let m2 = slerp(a, b.map(|v| -v), 0.5);
        assert!(close(&m2, &m), "{m2:?}");
    }
}
