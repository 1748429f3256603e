//! Directions for secondary rays: cosine-weighted hemispheres around a surface normal.

/// Normalises a vector (f32). Returns the input for a zero vector.
#[inline]
pub fn normalize(v: [f32; 3]) -> [f32; 3] {
    let l = (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt();
    if l > 0.0 {
        [v[0] / l, v[1] / l, v[2] / l]
    } else {
        v
    }
}

/// Two unit vectors completing `n` (unit) to a right-handed orthonormal basis, without a
/// branch on the dominant axis (Duff et al. 2017's construction).
#[inline]
pub fn basis(n: [f32; 3]) -> ([f32; 3], [f32; 3]) {
    let sign = 1.0f32.copysign(n[2]);
    let a = -1.0 / (sign + n[2]);
    let b = n[0] * n[1] * a;
    (
        [1.0 + sign * n[0] * n[0] * a, sign * b, -sign * n[0]],
        [b, sign + n[1] * n[1] * a, -n[1]],
    )
}

/// A cosine-weighted direction on the hemisphere around unit normal `n`, from two uniform
/// numbers in [0, 1).
#[inline]
pub fn cosine_hemisphere(n: [f32; 3], u1: f32, u2: f32) -> [f32; 3] {
    let r = u1.sqrt();
    let phi = 2.0 * std::f32::consts::PI * u2;
    let (x, y) = (r * phi.cos(), r * phi.sin());
    let z = (1.0 - u1).max(0.0).sqrt();
    let (t, b) = basis(n);
    normalize([
        x * t[0] + y * b[0] + z * n[0],
        x * t[1] + y * b[1] + z * n[1],
        x * t[2] + y * b[2] + z * n[2],
    ])
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::geometry::dot;

    #[test]
    fn hemisphere_directions_are_unit_and_above_the_surface() {
        let mut rng = crate::render::rng::Pcg32::new(1, 2);
        for n in [
            [0.0, 0.0, 1.0],
            [0.0, 0.0, -1.0],
            normalize([1.0, -2.0, 0.5]),
        ] {
            let mut mean_cos = 0.0;
            for _ in 0..4000 {
                let d = cosine_hemisphere(n, rng.next_f32(), rng.next_f32());
                assert!((dot(d, d) - 1.0).abs() < 1e-5);
                assert!(dot(d, n) >= -1e-6);
                mean_cos += dot(d, n) / 4000.0;
            }
            // E[cos θ] = 2/3 under a cosine-weighted density.
            assert!((mean_cos - 2.0 / 3.0).abs() < 0.02, "{mean_cos}");
        }
    }
}
