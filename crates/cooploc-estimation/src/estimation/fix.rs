//! An absolute position fix (a GNSS receiver's) as a local update of one platform's filter.
//!
//! A vehicle that has GNSS before it loses it (or one teammate that keeps it) runs its filter on
//! the fixes: each is a local update (paper Eqs. 4-5), so its `I - K H` goes into the recursive
//! coefficient matrix like any other, and the decentralized method stays exact (the property
//! tests in `team.rs`). The measurement is the position in the team's NED frame: north and east,
//! and down when the fix gives a vertical sigma and the platform has a height state (a planar
//! robot has none: its height is known).
//!
//! A fix is gated: one whose normalised innovation squared is beyond the 99.9% point of the
//! chi-square law of its dimension ([`GATE_CHI2_999`]) is refused, not applied (a multipath
//! jump or a receiver that still reports a fix it has lost). Nothing changes when a fix is
//! refused.

use nalgebra::{DMatrix, DVector};

use super::error::EstimationError;
use super::inputs::PositionFixSample;
use super::kalman::{LinearizedMeasurement, symmetrize};
use super::platform::PlatformFilter;

/// The 99.9% points of the chi-square law with 1, 2 and 3 degrees of freedom.
pub const GATE_CHI2_999: [f64; 3] = [10.828, 13.816, 16.266];

/// Largest sigma a fix may give, m (a receiver's "unknown" is refused, not trusted).
pub const MAX_FIX_SIGMA_M: f64 = 1_000.0;

/// What became of a fix.
#[derive(Debug, Clone, PartialEq)]
pub enum FixOutcome {
    /// Applied; its normalised innovation squared.
    Applied { nis: f64 },
    /// Beyond the gate: not applied.
    Gated { nis: f64 },
}

/// The fix as a measurement of `f`'s position, linearised about its estimate. Changes nothing.
pub fn position_fix_measurement<F: PlatformFilter + ?Sized>(
    f: &F,
    s: &PositionFixSample,
) -> Result<LinearizedMeasurement, EstimationError> {
    s.validate()?;
    let g = f.geometry();
    let vertical = s.sigma_v_m.is_some();
    let axes: Vec<(usize, usize, f64)> = (0..3)
        .filter(|&axis| axis < 2 || vertical)
        .filter_map(|axis| {
            g.position_index[axis].map(|i| (axis, i, if axis < 2 { s.sigma_h_m } else { s.sigma_v_m.unwrap_or(0.0) }))
        })
        .collect();
    if axes.len() < 2 {
        return Err(EstimationError::NotApplicable("a position fix for a platform without a horizontal position"));
    }
    let n = f.dim();
    let mut h = DMatrix::zeros(axes.len(), n);
    let mut residual = DVector::zeros(axes.len());
    let mut r = DMatrix::zeros(axes.len(), axes.len());
    for (row, &(axis, index, sigma)) in axes.iter().enumerate() {
        h[(row, index)] = 1.0;
        residual[row] = s.pos_ned_m[axis] - g.position_ned_m[axis];
        r[(row, row)] = sigma * sigma;
    }
    let meas = LinearizedMeasurement { h, residual, r };
    meas.validate(n)?;
    Ok(meas)
}

/// The normalised innovation squared of `meas` against covariance `p`.
pub fn nis(p: &DMatrix<f64>, meas: &LinearizedMeasurement) -> Result<f64, EstimationError> {
    let mut s = &meas.h * p * meas.h.transpose() + &meas.r;
    symmetrize(&mut s);
    let chol =
        nalgebra::Cholesky::new(s).ok_or(EstimationError::NotPositiveDefinite { what: "position fix innovation covariance" })?;
    Ok(meas.residual.dot(&chol.solve(&meas.residual)))
}

/// Applies the fix to `f` unless the gate refuses it (see the module documentation). On error,
/// and when gated, nothing changes.
pub fn update_position_fix<F: PlatformFilter + ?Sized>(f: &mut F, s: &PositionFixSample) -> Result<FixOutcome, EstimationError> {
    let meas = position_fix_measurement(f, s)?;
    let nis = nis(&f.covariance(), &meas)?;
    if nis > GATE_CHI2_999[meas.len() - 1] {
        return Ok(FixOutcome::Gated { nis });
    }
    let d = f.update_local(&meas)?;
    Ok(FixOutcome::Applied { nis: d.nis })
}

#[cfg(test)]
mod tests {
    use nalgebra::Vector3;

    use super::*;
    use crate::estimation::linear::LinearPlatform;
    use crate::time::TimeUs;

    fn fix(n: f64, e: f64, d: f64, sigma_v: Option<f64>) -> PositionFixSample {
        PositionFixSample { t: TimeUs(1_000_000), pos_ned_m: Vector3::new(n, e, d), sigma_h_m: 0.5, sigma_v_m: sigma_v }
    }

    /// A 3-D position platform at the origin with 4 m of uncertainty on each axis.
    fn platform() -> LinearPlatform {
        LinearPlatform::new(DVector::zeros(3), DMatrix::identity(3, 3) * 16.0, [Some(0), Some(1), Some(2)]).unwrap()
    }

    #[test]
    fn a_fix_measures_the_position_axes_it_has() {
        let f = platform();
        let m = position_fix_measurement(&f, &fix(1.0, -2.0, 3.0, None)).unwrap();
        assert_eq!(m.len(), 2, "no vertical sigma: north and east only");
        assert_eq!(m.residual.as_slice(), &[1.0, -2.0]);
        assert_eq!(m.r[(1, 1)], 0.25);
        let m = position_fix_measurement(&f, &fix(1.0, -2.0, 3.0, Some(2.0))).unwrap();
        assert_eq!(m.len(), 3);
        assert_eq!(m.residual[2], 3.0);
        assert_eq!(m.r[(2, 2)], 4.0);
        for (row, col) in [(0, 0), (1, 1), (2, 2)] {
            assert_eq!(m.h[(row, col)], 1.0);
        }
        assert_eq!(m.h.sum(), 3.0);
    }

    #[test]
    fn a_fix_pulls_the_estimate_and_shrinks_the_covariance_by_the_kalman_weights() {
        let mut f = platform();
        let out = update_position_fix(&mut f, &fix(2.0, 0.0, 0.0, None)).unwrap();
        // P = 16, R = 0.25: the gain is 16 / 16.25, the posterior variance 16 * 0.25 / 16.25.
        let FixOutcome::Applied { nis } = out else { panic!("{out:?}") };
        assert!((nis - 4.0 / 16.25).abs() < 1e-12, "{nis}");
        let g = f.geometry();
        assert!((g.position_ned_m.x - 2.0 * 16.0 / 16.25).abs() < 1e-12);
        assert!((f.covariance()[(0, 0)] - 16.0 * 0.25 / 16.25).abs() < 1e-12);
        assert_eq!(f.covariance()[(2, 2)], 16.0, "the vertical was not measured");
    }

    #[test]
    fn a_fix_beyond_the_gate_is_refused_and_changes_nothing() {
        let mut f = platform();
        let before = (f.geometry().position_ned_m, f.covariance());
        // 16.25 m^2 of innovation variance per axis: 15 m is a NIS of 13.8 on one axis alone.
        let out = update_position_fix(&mut f, &fix(15.0, 3.0, 0.0, None)).unwrap();
        assert!(matches!(out, FixOutcome::Gated { nis } if nis > GATE_CHI2_999[1]), "{out:?}");
        assert_eq!((f.geometry().position_ned_m, f.covariance()), before);
        // just inside the gate it is taken
        let out = update_position_fix(&mut f, &fix(14.0, 0.0, 0.0, None)).unwrap();
        assert!(matches!(out, FixOutcome::Applied { .. }), "{out:?}");
    }

    #[test]
    fn a_bad_fix_is_an_error_that_names_it() {
        let mut f = platform();
        for (s, what) in [
            (PositionFixSample { sigma_h_m: 0.0, ..fix(0.0, 0.0, 0.0, None) }, "position fix sigma"),
            (PositionFixSample { sigma_h_m: 5_000.0, ..fix(0.0, 0.0, 0.0, None) }, "position fix sigma"),
            (PositionFixSample { sigma_v_m: Some(f64::NAN), ..fix(0.0, 0.0, 0.0, None) }, "position fix sigma"),
            (fix(f64::INFINITY, 0.0, 0.0, None), "position fix"),
        ] {
            let e = update_position_fix(&mut f, &s).unwrap_err().to_string();
            assert!(e.contains(what), "{e}");
        }
        assert_eq!(f.covariance()[(0, 0)], 16.0);
    }
}
