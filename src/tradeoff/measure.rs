//! How far an image is from its reference, which settings are worth their time, and how
//! fast the error falls: the arithmetic of `rayd tradeoff`, kept apart from rendering so
//! that it can be tested on numbers alone.

/// The error of an image against a reference of the same size, over every pixel and
/// channel of the linear radiance.
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize)]
pub struct Errors {
    /// Root of the mean squared difference.
    pub rmse: f64,
    /// Mean of `(x − r)² / (r² + ε)` with ε = [`REL_EPSILON`]: every pixel counts by its
    /// error relative to its brightness, so dark corners weigh as much as the sky (the
    /// measure of Rousselle et al.'s denoising papers).
    pub rel_mse: f64,
    /// `10 log10(1 / MSE)`, decibels, with the peak at radiance 1 (the default sky's);
    /// infinite for identical images.
    pub psnr: f64,
}

/// The ε of [`Errors::rel_mse`], which keeps black reference pixels from dividing by 0.
pub const REL_EPSILON: f64 = 1e-2;

/// Compares `image` with `reference`, pixel by pixel; `None` when their lengths differ or
/// either is empty.
pub fn errors(image: &[[f32; 3]], reference: &[[f32; 3]]) -> Option<Errors> {
    if image.len() != reference.len() || image.is_empty() {
        return None;
    }
    let (mut se, mut rel) = (0.0f64, 0.0f64);
    for (x, r) in image.iter().zip(reference) {
        for c in 0..3 {
            let (x, r) = (x[c] as f64, r[c] as f64);
            let d2 = (x - r) * (x - r);
            se += d2;
            rel += d2 / (r * r + REL_EPSILON);
        }
    }
    let n = 3.0 * image.len() as f64;
    let mse = se / n;
    Some(Errors {
        rmse: mse.sqrt(),
        rel_mse: rel / n,
        psnr: if mse > 0.0 {
            -10.0 * mse.log10()
        } else {
            f64::INFINITY
        },
    })
}

/// Errors closer than this, relative to the larger, are the same error: rungs whose images
/// differ in a few last bits (`precision=fast` against `watertight`) measured RMSEs 1e-7
/// apart, and the slower of the two was starred for it (session 31's review), while a CSV
/// reader saw two equal values.
pub const SAME_ERROR: f64 = 1e-6;

/// Which of `points` (time, error) are on the Pareto front: no other point is as fast and
/// as accurate with one of the two strictly better, errors within [`SAME_ERROR`] of each
/// other counting as equal. Ties (equal time and error) are all on it. Points with a
/// non-finite coordinate are never on it.
pub fn pareto(points: &[(f64, f64)]) -> Vec<bool> {
    let same = |a: f64, b: f64| (a - b).abs() <= SAME_ERROR * a.abs().max(b.abs());
    points
        .iter()
        .map(|&(t, e)| {
            t.is_finite()
                && e.is_finite()
                && !points.iter().any(|&(t2, e2)| {
                    let as_accurate = e2 <= e || same(e, e2);
                    let more_accurate = e2 < e && !same(e, e2);
                    t2.is_finite()
                        && e2.is_finite()
                        && t2 <= t
                        && as_accurate
                        && (t2 < t || more_accurate)
                })
        })
        .collect()
}

/// The least-squares slope of `ln y` against `ln x`: for Monte Carlo error against samples
/// per pixel, −0.5. `None` with fewer than two usable points (both coordinates positive and
/// finite) or when every usable x is the same.
pub fn log_log_slope(points: &[(f64, f64)]) -> Option<f64> {
    let logs: Vec<(f64, f64)> = points
        .iter()
        .filter(|(x, y)| *x > 0.0 && *y > 0.0 && x.is_finite() && y.is_finite())
        .map(|(x, y)| (x.ln(), y.ln()))
        .collect();
    if logs.len() < 2 {
        return None;
    }
    let n = logs.len() as f64;
    let mx = logs.iter().map(|p| p.0).sum::<f64>() / n;
    let my = logs.iter().map(|p| p.1).sum::<f64>() / n;
    let sxx: f64 = logs.iter().map(|p| (p.0 - mx) * (p.0 - mx)).sum();
    let sxy: f64 = logs.iter().map(|p| (p.0 - mx) * (p.1 - my)).sum();
    (sxx > 0.0).then_some(sxy / sxx)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn errors_of_a_known_difference() {
        let r = vec![[1.0f32, 0.0, 0.5]; 4];
        let x = vec![[1.5f32, 0.0, 0.5]; 4];
        let e = errors(&x, &r).unwrap();
        // One channel in three is off by 0.5.
        assert!((e.rmse - (0.25f64 / 3.0).sqrt()).abs() < 1e-12);
        assert!((e.rel_mse - 0.25 / (1.0 + REL_EPSILON) / 3.0).abs() < 1e-12);
        assert!((e.psnr - -10.0 * (0.25f64 / 3.0).log10()).abs() < 1e-9);
        assert_eq!(errors(&r, &r).unwrap().psnr, f64::INFINITY);
        assert_eq!(errors(&r, &r[..3]), None);
        assert_eq!(errors(&[], &[]), None);
    }

    #[test]
    fn pareto_keeps_what_nothing_beats() {
        let pts = [
            (1.0, 10.0), // fastest
            (2.0, 5.0),  // on the front
            (3.0, 6.0),  // beaten by (2, 5)
            (2.0, 5.0),  // a tie stays
            (4.0, 1.0),  // most accurate
            (5.0, 1.0),  // as accurate as (4, 1), slower
            (f64::NAN, 0.0),
        ];
        assert_eq!(pareto(&pts), [true, true, false, true, true, false, false]);
        // An error smaller by float noise does not buy a slower rung a place.
        let noise = [
            (1.0, 0.012_686_73),
            (1.5, 0.012_686_73 * (1.0 - 1e-7)),
            (3.0, 0.001),
        ];
        assert_eq!(pareto(&noise), [true, false, true]);
    }

    #[test]
    fn slope_of_a_power_law() {
        let pts: Vec<(f64, f64)> = [1.0, 4.0, 16.0, 64.0]
            .iter()
            .map(|&x: &f64| (x, 3.0 * x.powf(-0.5)))
            .collect();
        assert!((log_log_slope(&pts).unwrap() + 0.5).abs() < 1e-12);
        assert_eq!(log_log_slope(&[(1.0, 1.0)]), None);
        assert_eq!(log_log_slope(&[(2.0, 1.0), (2.0, 3.0)]), None);
        assert_eq!(log_log_slope(&[(0.0, 1.0), (-1.0, 3.0)]), None);
    }
}
