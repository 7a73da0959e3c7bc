//! Filter consistency statistics: NEES and chi-square acceptance bands.

use nalgebra::{DMatrix, DVector};
use statrs::distribution::{ChiSquared, ContinuousCDF};

use super::EstimationError;

/// Normalised estimation error squared `e^T P^-1 e` (Cholesky solve, no inverse).
pub fn nees(error: &DVector<f64>, p: &DMatrix<f64>) -> Result<f64, EstimationError> {
    let chol = nalgebra::Cholesky::new(p.clone()).ok_or(EstimationError::NotPositiveDefinite { what: "covariance in NEES" })?;
    Ok(error.dot(&chol.solve(error)))
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
