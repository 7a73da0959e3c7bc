//! A generic linear-Gaussian platform (paper Eq. 1): `x_k = Phi x_{k-1} + w`, `z = H x + v`.
//!
//! It is the simplest state chain there is, used to check the cooperative algebra exactly
//! (property tests against a brute-force joint filter) and available to users whose platform
//! model is linear.

use nalgebra::{DMatrix, DVector, Vector3};

use super::platform::{Geometry, PlatformFilter, check_joint_writeback};
use super::{EstimationError, LinearizedMeasurement, UpdateDiagnostics, kalman};

#[derive(Debug, Clone)]
pub struct LinearPlatform {
    x: DVector<f64>,
    p: DMatrix<f64>,
    psi: DMatrix<f64>,
    position_index: [Option<usize>; 3],
}

impl LinearPlatform {
    /// A platform with initial estimate `x0`, covariance `p0`, and the state indices that hold
    /// its N, E, D position (used by range measurements).
    pub fn new(x0: DVector<f64>, p0: DMatrix<f64>, position_index: [Option<usize>; 3]) -> Result<Self, EstimationError> {
        let n = x0.len();
        check_joint_writeback(n, &x0, &p0)?;
        for &i in position_index.iter().flatten() {
            if i >= n {
                return Err(EstimationError::DimensionMismatch { what: "position index", expected: n, got: i });
            }
        }
        Ok(Self { x: x0, p: p0, psi: DMatrix::identity(n, n), position_index })
    }

    pub fn state(&self) -> &DVector<f64> {
        &self.x
    }

    /// Time update with transition `phi` and discrete process noise `qd`.
    pub fn propagate(&mut self, phi: &DMatrix<f64>, qd: &DMatrix<f64>) -> Result<(), EstimationError> {
        let mut p = self.p.clone();
        let mut psi = self.psi.clone();
        kalman::propagate(&mut p, &mut psi, phi, qd)?;
        self.x = phi * &self.x;
        self.p = p;
        self.psi = psi;
        Ok(())
    }

    /// The measurement `z = H x + v` linearised (trivially) about the estimate.
    pub fn linearize(
        &self,
        h: &DMatrix<f64>,
        z: &DVector<f64>,
        r: &DMatrix<f64>,
    ) -> Result<LinearizedMeasurement, EstimationError> {
        if h.ncols() != self.x.len() || h.nrows() != z.len() {
            return Err(EstimationError::DimensionMismatch {
                what: "measurement matrix",
                expected: self.x.len(),
                got: h.ncols(),
            });
        }
        let residual = z - h * &self.x;
        let meas = LinearizedMeasurement { h: h.clone(), residual, r: r.clone() };
        meas.validate(self.x.len())?;
        Ok(meas)
    }
}

impl PlatformFilter for LinearPlatform {
    fn dim(&self) -> usize {
        self.x.len()
    }
    fn covariance(&self) -> DMatrix<f64> {
        self.p.clone()
    }
    fn psi(&self) -> DMatrix<f64> {
        self.psi.clone()
    }
    fn geometry(&self) -> Geometry {
        let mut pos = Vector3::zeros();
        for (axis, idx) in self.position_index.iter().enumerate() {
            if let Some(i) = idx {
                pos[axis] = self.x[*i];
            }
        }
        Geometry { position_ned_m: pos, position_index: self.position_index, heading: None }
    }
    fn update_local(&mut self, meas: &LinearizedMeasurement) -> Result<UpdateDiagnostics, EstimationError> {
        let up = kalman::local_update(&self.p, meas)?;
        self.x += &up.dx;
        self.p = up.p;
        self.psi = &up.i_minus_kh * &self.psi;
        Ok(up.diagnostics)
    }
    fn apply_joint(&mut self, dx: &DVector<f64>, p: &DMatrix<f64>) -> Result<(), EstimationError> {
        check_joint_writeback(self.x.len(), dx, p)?;
        self.x += dx;
        self.p = p.clone();
        self.psi = DMatrix::identity(self.x.len(), self.x.len());
        Ok(())
    }
    fn apply_bystander(&mut self, a: &DVector<f64>, b: &DMatrix<f64>) -> Result<(), EstimationError> {
        let (dx, p) = super::platform::bystander_posterior(&self.p, &self.psi, a, b)?;
        self.x += dx;
        self.p = p;
        Ok(())
    }
}
