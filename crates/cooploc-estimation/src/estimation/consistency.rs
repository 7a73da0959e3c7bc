//! Filter consistency statistics: NEES, chi-square acceptance bands, and the 95% confidence
//! ellipse of a horizontal position (what every display draws: the ground station's page, its
//! live Foxglove channels and the logs' Foxglove channels all take it from here).

use nalgebra::{DMatrix, DVector, Matrix2, Matrix3, Vector3};
use serde::Serialize;
use statrs::distribution::{ChiSquared, ContinuousCDF};

use super::EstimationError;

/// Normalised estimation error squared `e^T P^-1 e` (Cholesky solve, no inverse).
pub fn nees(error: &DVector<f64>, p: &DMatrix<f64>) -> Result<f64, EstimationError> {
    let chol = nalgebra::Cholesky::new(p.clone()).ok_or(EstimationError::NotPositiveDefinite { what: "covariance in NEES" })?;
    Ok(error.dot(&chol.solve(error)))
}

/// 3-D position NEES `e^T P^-1 e` by Cholesky; `None` unless `P` is positive definite.
pub fn position_nees(error_ned_m: &Vector3<f64>, cov_m2: &Matrix3<f64>) -> Option<f64> {
    let chol = cov_m2.cholesky()?;
    let v = error_ned_m.dot(&chol.solve(error_ned_m));
    v.is_finite().then_some(v)
}

/// 95% quantile of the chi-square distribution with 2 degrees of freedom: `-2 ln(0.05)`.
pub const CHI2_2DOF_95: f64 = 5.991_464_547_107_979;

/// The 95% confidence ellipse of a horizontal (N, E) position.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct Ellipse95 {
    pub semi_major_m: f64,
    pub semi_minor_m: f64,
    /// Direction of the major axis: from north towards east (clockwise seen from above), in
    /// (-90, 90] degrees.
    pub major_bearing_deg: f64,
}

/// Semi-axes (major, minor, m) of the 95% ellipse of the horizontal covariance
/// `[[nn, ne], [ne, ee]]` (`sqrt(5.991 lambda)` of its eigenvalues), and the direction of the
/// major axis from north towards east, rad, in (-pi/2, pi/2]. `None` for non-finite entries or
/// a negative largest eigenvalue; a slightly negative smaller one (rounding) gives a zero minor
/// axis.
pub fn ellipse95_axes(nn: f64, ne: f64, ee: f64) -> Option<(f64, f64, f64)> {
    if !(nn.is_finite() && ne.is_finite() && ee.is_finite()) {
        return None;
    }
    let mean = 0.5 * (nn + ee);
    let radius = (0.5 * (nn - ee)).hypot(ne);
    let (major, minor) = (mean + radius, (mean - radius).max(0.0));
    if major < 0.0 {
        return None;
    }
    let mut angle = 0.5 * (2.0 * ne).atan2(nn - ee);
    if angle <= -std::f64::consts::FRAC_PI_2 {
        angle += std::f64::consts::PI;
    }
    Some(((CHI2_2DOF_95 * major).sqrt(), (CHI2_2DOF_95 * minor).sqrt(), angle))
}

/// [`ellipse95_axes`] of a 2x2 N/E covariance (m^2; its off-diagonal entries averaged).
pub fn ellipse95(cov_ne_m2: &Matrix2<f64>) -> Option<Ellipse95> {
    let ne = 0.5 * (cov_ne_m2[(0, 1)] + cov_ne_m2[(1, 0)]);
    let (semi_major_m, semi_minor_m, angle) = ellipse95_axes(cov_ne_m2[(0, 0)], ne, cov_ne_m2[(1, 1)])?;
    Some(Ellipse95 { semi_major_m, semi_minor_m, major_bearing_deg: angle.to_degrees() })
}

/// The 95% quantile of chi-square with `dof` degrees of freedom (infinite for no degree).
pub fn chi2_95(dof: usize) -> f64 {
    ChiSquared::new(dof as f64).map(|d| d.inverse_cdf(0.95)).unwrap_or(f64::INFINITY)
}

/// Two-sided acceptance band for the average of `runs` independent NEES values of a
/// `dim`-dimensional consistent estimator: `[chi2_{a/2}(runs dim), chi2_{1-a/2}(runs dim)] / runs`.
/// NaNs when there is no degree of freedom or the confidence is not in (0, 1).
pub fn average_nees_band(dim: usize, runs: usize, confidence: f64) -> (f64, f64) {
    let dof = (dim * runs) as f64;
    match ChiSquared::new(dof) {
        Ok(chi) if confidence > 0.0 && confidence < 1.0 => {
            let alpha = 1.0 - confidence;
            (chi.inverse_cdf(alpha / 2.0) / runs as f64, chi.inverse_cdf(1.0 - alpha / 2.0) / runs as f64)
        }
        _ => (f64::NAN, f64::NAN),
    }
}

#[cfg(test)]
mod tests {
    #[test]
    fn chi2_95_and_the_ellipse_match_hand_values() {
        assert!((chi2_95(2) - CHI2_2DOF_95).abs() < 1e-9);
        assert!((chi2_95(3) - 7.814_727_903).abs() < 1e-6);
        assert!(chi2_95(0).is_infinite());
        // Axis-aligned, major along east.
        let (major, minor, angle) = ellipse95_axes(1.0, 0.0, 4.0).unwrap();
        assert!((major - (4.0 * CHI2_2DOF_95).sqrt()).abs() < 1e-12 && (minor - CHI2_2DOF_95.sqrt()).abs() < 1e-12);
        assert!((angle - std::f64::consts::FRAC_PI_2).abs() < 1e-12, "in (-pi/2, pi/2]: {angle}");
        assert!(ellipse95_axes(f64::NAN, 0.0, 1.0).is_none() && ellipse95_axes(-1.0, 0.0, -1.0).is_none());
    }

    use super::*;

    #[test]
    fn band_matches_tables() {
        // chi2 with 100 dof: 2.5% = 74.222, 97.5% = 129.561 (standard tables).
        let (lo, hi) = average_nees_band(2, 50, 0.95);
        assert!((lo * 50.0 - 74.222).abs() < 1e-2, "{lo}");
        assert!((hi * 50.0 - 129.561).abs() < 1e-2, "{hi}");
    }

    #[test]
    fn degenerate_band_is_nan_not_a_panic() {
        assert!(average_nees_band(0, 10, 0.95).0.is_nan());
        assert!(average_nees_band(3, 10, 1.5).1.is_nan());
    }

    #[test]
    fn nees_of_unit_error() {
        let p = DMatrix::from_diagonal(&DVector::from_vec(vec![4.0, 1.0]));
        let e = DVector::from_vec(vec![2.0, 1.0]);
        assert!((nees(&e, &p).unwrap() - 2.0).abs() < 1e-12);
    }
}
