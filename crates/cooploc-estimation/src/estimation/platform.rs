//! What the cooperative layer needs from a platform's own filter (its "state chain", paper
//! Step 1), whatever model that filter runs.
//!
//! Every platform filter is an error-state filter: it carries a nominal state, the covariance
//! `P` of the error state, and the recursive coefficient matrix `Psi` (paper Eq. 10), the
//! product of every factor that has multiplied its error state since its last joint update:
//!
//! - a time update multiplies it by `Phi` (Eq. 3);
//! - a local measurement update multiplies it by `I - K H` (Eq. 6);
//! - an error reset (injecting the error into the nominal state and zeroing it) multiplies it
//!   by the reset Jacobian `G`, and `P` becomes `G P G^T`;
//! - a joint update (cooperative event, or a centralized EKF step) sets it back to `G`
//!   (the identity when the model's reset is trivial), because the cross-covariances are
//!   stored anew at that instant.
//!
//! Between two joint updates, the cross-covariance of platforms `i` and `j` is then
//! `P_ij(now) = Psi_i C_ij Psi_j^T` where `C_ij` is what was stored (see `coop`).

use nalgebra::{DMatrix, DVector, Vector3};

use super::{EstimationError, LinearizedMeasurement, UpdateDiagnostics};

/// A platform's identity on the team (its MAVLink system id on the wire).
pub type PlatformId = u16;

/// Heading of a platform and where its error lives in the error state.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Heading {
    /// Yaw from north, clockwise seen from above (NED), radians.
    pub yaw_rad: f64,
    /// Error-state index whose positive error increases yaw.
    pub index: usize,
}

/// Where a platform is and how its error state maps onto that position.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Geometry {
    /// Nominal position in the team's local NED frame, metres.
    pub position_ned_m: Vector3<f64>,
    /// Error-state index of the N, E and D position errors; `None` when the model does not
    /// estimate that axis (a planar robot's height).
    pub position_index: [Option<usize>; 3],
    /// Heading, for models that have one (bearing measurements need it).
    pub heading: Option<Heading>,
}

/// What a platform broadcasts at a ranging epoch (paper Step 3.2): its nominal geometry, its
/// own error covariance and its recursive coefficient matrix.
#[derive(Debug, Clone, PartialEq)]
pub struct Snapshot {
    pub id: PlatformId,
    pub geometry: Geometry,
    pub covariance: DMatrix<f64>,
    pub psi: DMatrix<f64>,
}

impl Snapshot {
    /// Error-state dimension.
    pub fn dim(&self) -> usize {
        self.covariance.nrows()
    }

    /// Checks sizes, finiteness and index ranges.
    pub fn validate(&self) -> Result<(), EstimationError> {
        let n = self.dim();
        for (m, what) in [(&self.covariance, "broadcast covariance"), (&self.psi, "broadcast Psi")] {
            if m.nrows() != n || m.ncols() != n {
                return Err(EstimationError::DimensionMismatch { what, expected: n, got: m.ncols() });
            }
            super::kalman::check_finite(m, what)?;
        }
        super::kalman::check_finite(&self.geometry.position_ned_m, "broadcast position")?;
        let bad_index = self.geometry.position_index.iter().flatten().chain(self.geometry.heading.as_ref().map(|h| &h.index));
        for &i in bad_index {
            if i >= n {
                return Err(EstimationError::DimensionMismatch { what: "broadcast state index", expected: n, got: i });
            }
        }
        if let Some(h) = self.geometry.heading
            && !h.yaw_rad.is_finite()
        {
            return Err(EstimationError::NonFinite { what: "broadcast heading" });
        }
        Ok(())
    }
}

/// A platform's own filter, as the cooperative layer and the team runner see it.
pub trait PlatformFilter {
    /// Error-state dimension.
    fn dim(&self) -> usize;
    /// Error covariance `P` (a copy).
    fn covariance(&self) -> DMatrix<f64>;
    /// Recursive coefficient matrix `Psi` (a copy).
    fn psi(&self) -> DMatrix<f64>;
    /// Nominal position and heading, and their error-state indices.
    fn geometry(&self) -> Geometry;
    /// Applies a measurement of this platform's own error state: correction injected into the
    /// nominal state, Joseph-form covariance, `Psi <- G (I - K H) Psi`. On error nothing changes.
    fn update_local(&mut self, meas: &LinearizedMeasurement) -> Result<UpdateDiagnostics, EstimationError>;
    /// Writes back this platform's block of a joint update: injects `dx`, takes `p` as its
    /// covariance, and restarts `Psi` (paper Step 5). On error nothing changes.
    fn apply_joint(&mut self, dx: &DVector<f64>, p: &DMatrix<f64>) -> Result<(), EstimationError>;
    /// Takes this platform's share of a joint update it did not broadcast for, as a bystander
    /// ([`crate::estimation::coop::BystanderShare`]): injects `Psi a`, takes `P - Psi b Psi^T`
    /// as its covariance, and keeps `Psi` (times the reset Jacobian of the injection, as a local
    /// update does), so that its store blocks stay in the coordinates of its store reference.
    /// On error nothing changes. Filters that do not support it say so.
    fn apply_bystander(&mut self, _a: &DVector<f64>, _b: &DMatrix<f64>) -> Result<(), EstimationError> {
        Err(EstimationError::NotApplicable("this filter cannot take a bystander's share of a joint update"))
    }
    /// Turns the bookkeeping of `Psi` on or off. A method that never reconstructs
    /// cross-covariances (dead reckoning, no-propagation, covariance intersection) may save the
    /// work; the default keeps it on.
    fn set_track_psi(&mut self, _on: bool) {}
    /// Adds `q` (positive semi-definite, `dim x dim`) to the covariance, as process noise would:
    /// `Psi` is left as it is, so the cross-covariances the team reconstructs from it stay
    /// exact and only this platform's own uncertainty grows. On error nothing changes. Filters
    /// that do not support it say so.
    fn add_noise(&mut self, _q: &DMatrix<f64>) -> Result<(), EstimationError> {
        Err(EstimationError::NotApplicable("this filter cannot add noise to its covariance"))
    }

    /// The broadcast of paper Step 3.2.
    fn snapshot(&self, id: PlatformId) -> Snapshot {
        Snapshot { id, geometry: self.geometry(), covariance: self.covariance(), psi: self.psi() }
    }
}

impl<T: PlatformFilter + ?Sized> PlatformFilter for Box<T> {
    fn dim(&self) -> usize {
        (**self).dim()
    }
    fn covariance(&self) -> DMatrix<f64> {
        (**self).covariance()
    }
    fn psi(&self) -> DMatrix<f64> {
        (**self).psi()
    }
    fn geometry(&self) -> Geometry {
        (**self).geometry()
    }
    fn snapshot(&self, id: PlatformId) -> Snapshot {
        (**self).snapshot(id)
    }
    fn update_local(&mut self, meas: &LinearizedMeasurement) -> Result<UpdateDiagnostics, EstimationError> {
        (**self).update_local(meas)
    }
    fn add_noise(&mut self, q: &DMatrix<f64>) -> Result<(), EstimationError> {
        (**self).add_noise(q)
    }
    fn apply_joint(&mut self, dx: &DVector<f64>, p: &DMatrix<f64>) -> Result<(), EstimationError> {
        (**self).apply_joint(dx, p)
    }
    fn apply_bystander(&mut self, a: &DVector<f64>, b: &DMatrix<f64>) -> Result<(), EstimationError> {
        (**self).apply_bystander(a, b)
    }
    fn set_track_psi(&mut self, on: bool) {
        (**self).set_track_psi(on)
    }
}

/// Validates the write-back arguments of [`PlatformFilter::apply_joint`] for a state of size `n`.
pub fn check_joint_writeback(n: usize, dx: &DVector<f64>, p: &DMatrix<f64>) -> Result<(), EstimationError> {
    if dx.len() != n {
        return Err(EstimationError::DimensionMismatch { what: "joint correction", expected: n, got: dx.len() });
    }
    if p.nrows() != n || p.ncols() != n {
        return Err(EstimationError::DimensionMismatch { what: "joint posterior block", expected: n, got: p.nrows() });
    }
    super::kalman::check_finite(dx, "joint correction")?;
    super::kalman::check_finite(p, "joint posterior block")
}

/// A bystander's correction and posterior covariance ([`PlatformFilter::apply_bystander`]):
/// `(Psi a, P - Psi b Psi^T)`, checked (sizes, finite, the posterior symmetric positive
/// semi-definite).
pub fn bystander_posterior(
    p: &DMatrix<f64>,
    psi: &DMatrix<f64>,
    a: &DVector<f64>,
    b: &DMatrix<f64>,
) -> Result<(DVector<f64>, DMatrix<f64>), EstimationError> {
    let n = p.nrows();
    if a.len() != n {
        return Err(EstimationError::DimensionMismatch { what: "bystander's correction", expected: n, got: a.len() });
    }
    if b.nrows() != n || b.ncols() != n {
        return Err(EstimationError::DimensionMismatch { what: "bystander's covariance reduction", expected: n, got: b.nrows() });
    }
    super::kalman::check_finite(a, "bystander's correction")?;
    super::kalman::check_finite(b, "bystander's covariance reduction")?;
    let dx = psi * a;
    let mut post = p - psi * b * psi.transpose();
    super::kalman::symmetrize(&mut post);
    if !super::kalman::is_psd(&post, 1e-9) {
        return Err(EstimationError::NotPositiveDefinite { what: "a bystander's posterior covariance" });
    }
    Ok((dx, post))
}

/// Validates the argument of [`PlatformFilter::add_noise`] for a state of size `n`: square of
/// that size, finite, symmetric positive semi-definite.
pub fn check_noise(n: usize, q: &DMatrix<f64>) -> Result<(), EstimationError> {
    if q.nrows() != n || q.ncols() != n {
        return Err(EstimationError::DimensionMismatch { what: "added noise", expected: n, got: q.nrows() });
    }
    super::kalman::check_finite(q, "added noise")?;
    let asymmetry = (q - q.transpose()).amax();
    if asymmetry > 1e-12 * q.amax() || !super::kalman::is_psd(q, 1e-9) {
        return Err(EstimationError::NotApplicable("added noise must be positive semi-definite"));
    }
    Ok(())
}
