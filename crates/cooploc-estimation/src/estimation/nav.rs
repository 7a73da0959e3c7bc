//! The navigation filter a node runs, whatever its vehicle: the strapdown INS of
//! [`ins`](super::ins) (a vehicle whose autopilot streams its IMU) or the planar robot of
//! [`planar`](super::planar) (a wheeled robot whose only motion sensor is its wheel odometry). One type, so that the node, the offline
//! experiment and replay handle mixed teams with one code path.
//!
//! A filter is driven by [`Drive`] samples, each the mean of its interval `(t_prev, t]` (IMU
//! samples for the INS, wheel samples for the planar robot); a sample of the other kind is
//! refused with [`EstimationError::NotApplicable`].

use nalgebra::{DMatrix, DVector, Matrix3, Matrix6, UnitQuaternion, Vector3};

use super::ins::{InsConfig, InsFilter, InsInitialSigma, InsState};
use super::planar::{PlanarConfig, PlanarFilter, PlanarSigma, PlanarState};
use super::{
    EstimationError, Geometry, ImuSample, LinearizedMeasurement, OdometerSample, PlatformFilter, PlatformId, Snapshot,
    UpdateDiagnostics, WheelSample,
};
use crate::time::TimeUs;

/// Which model a platform runs, with its noise model and initial uncertainty.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum NavModel {
    Ins { config: InsConfig, initial_sigma: InsInitialSigma },
    Planar { config: PlanarConfig, initial_sigma: PlanarSigma },
}

impl NavModel {
    /// Longest interval one drive sample may cover, s.
    pub fn max_gap_s(&self) -> f64 {
        match self {
            NavModel::Ins { config, .. } => config.max_imu_gap_s,
            NavModel::Planar { config, .. } => config.max_gap_s,
        }
    }

    /// Sets the latitude the INS takes the Earth rate at (known once the vehicle says where it
    /// is); the planar robot has no use for it.
    pub fn set_latitude(&mut self, latitude_deg: f64) {
        if let NavModel::Ins { config, .. } = self {
            config.latitude_deg = latitude_deg;
        }
    }

    /// `"ins"` or `"planar"`, as profiles and logs name it.
    pub fn name(&self) -> &'static str {
        match self {
            NavModel::Ins { .. } => "ins",
            NavModel::Planar { .. } => "planar",
        }
    }

    /// Dimension of the error state (what a record carries).
    pub fn error_dim(&self) -> usize {
        match self {
            NavModel::Ins { .. } => super::ins::ERROR_DIM,
            NavModel::Planar { .. } => 3,
        }
    }
}

/// A platform's initial nominal state.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum NavState {
    Ins(InsState),
    Planar(PlanarState),
}

impl From<InsState> for NavState {
    fn from(s: InsState) -> Self {
        NavState::Ins(s)
    }
}

impl From<PlanarState> for NavState {
    fn from(s: PlanarState) -> Self {
        NavState::Planar(s)
    }
}

impl NavState {
    pub fn position_ned_m(&self) -> Vector3<f64> {
        match self {
            NavState::Ins(s) => s.pos_ned_m,
            NavState::Planar(s) => s.pos_ned_m,
        }
    }

    /// The state a `model` starts from, taken from an INS-style estimate (position, velocity,
    /// attitude): the planar robot keeps the position and the heading.
    pub fn for_model(model: &NavModel, s: InsState) -> NavState {
        match model {
            NavModel::Ins { .. } => NavState::Ins(s),
            NavModel::Planar { .. } => {
                NavState::Planar(PlanarState { pos_ned_m: s.pos_ned_m, yaw_rad: s.att_frd_to_ned.euler_angles().2 })
            }
        }
    }
}

/// One sample that drives a filter through its interval.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Drive {
    Imu(ImuSample),
    Wheel(WheelSample),
}

impl Drive {
    pub fn t(&self) -> TimeUs {
        match self {
            Drive::Imu(s) => s.t,
            Drive::Wheel(s) => s.t,
        }
    }

    /// The same rates, ending at `t` (a piece of the interval).
    pub fn at(&self, t: TimeUs) -> Drive {
        match self {
            Drive::Imu(s) => Drive::Imu(ImuSample { t, ..*s }),
            Drive::Wheel(s) => Drive::Wheel(WheelSample { t, ..*s }),
        }
    }
}

/// The INS or the planar robot.
#[derive(Debug)]
// A node clones its filter into a checkpoint at every instant: boxing the INS would add an
// allocation to each, for the common case, to save memory in the rare one.
#[allow(clippy::large_enum_variant)]
pub enum NavFilter {
    Ins(InsFilter),
    Planar(PlanarFilter),
}

impl Clone for NavFilter {
    fn clone(&self) -> Self {
        match self {
            NavFilter::Ins(f) => NavFilter::Ins(*f),
            NavFilter::Planar(f) => NavFilter::Planar(f.clone()),
        }
    }

    /// In place: an INS over an INS is one copy of its values, its scratch left out (a node's
    /// checkpoint at every instant is written this way into a recycled slot).
    fn clone_from(&mut self, source: &Self) {
        match (self, source) {
            (NavFilter::Ins(to), NavFilter::Ins(from)) => to.copy_from(from),
            (NavFilter::Planar(to), NavFilter::Planar(from)) => to.clone_from(from),
            (to, from) => *to = from.clone(),
        }
    }
}

const WRONG_DRIVE: EstimationError = EstimationError::NotApplicable("a drive sample of another model");

impl NavFilter {
    /// A filter of `model` at `t0` from `initial`; the state must be of the model's kind.
    pub fn new(model: NavModel, t0: TimeUs, initial: NavState) -> Result<Self, EstimationError> {
        match (model, initial) {
            (NavModel::Ins { config, initial_sigma }, NavState::Ins(s)) => {
                Ok(NavFilter::Ins(InsFilter::new(config, t0, s, initial_sigma)?))
            }
            (NavModel::Planar { config, initial_sigma }, NavState::Planar(s)) => {
                Ok(NavFilter::Planar(PlanarFilter::new(config, t0, s, initial_sigma)?))
            }
            _ => Err(EstimationError::NotApplicable("an initial state of another model")),
        }
    }

    /// The INS, when this is one.
    pub fn ins(&self) -> Option<&InsFilter> {
        match self {
            NavFilter::Ins(f) => Some(f),
            NavFilter::Planar(_) => None,
        }
    }

    pub fn planar(&self) -> Option<&PlanarFilter> {
        match self {
            NavFilter::Planar(f) => Some(f),
            NavFilter::Ins(_) => None,
        }
    }

    pub fn time(&self) -> TimeUs {
        match self {
            NavFilter::Ins(f) => f.time(),
            NavFilter::Planar(f) => f.time(),
        }
    }

    pub fn restart_clock(&mut self, t: TimeUs) {
        match self {
            NavFilter::Ins(f) => f.restart_clock(t),
            NavFilter::Planar(f) => f.restart_clock(t),
        }
    }

    /// Longest interval one drive sample may cover, s.
    pub fn max_gap_s(&self) -> f64 {
        match self {
            NavFilter::Ins(f) => f.config().max_imu_gap_s,
            NavFilter::Planar(f) => f.config().max_gap_s,
        }
    }

    /// Propagates to `s.t` with the sample's rates. On error nothing changes.
    pub fn propagate(&mut self, s: &Drive) -> Result<(), EstimationError> {
        match (self, s) {
            (NavFilter::Ins(f), Drive::Imu(s)) => f.propagate(s),
            (NavFilter::Planar(f), Drive::Wheel(s)) => f.propagate(s),
            _ => Err(WRONG_DRIVE),
        }
    }

    /// Whether `s` is the kind of sample this filter is driven by.
    pub fn takes(&self, s: &Drive) -> bool {
        matches!((self, s), (NavFilter::Ins(_), Drive::Imu(_)) | (NavFilter::Planar(_), Drive::Wheel(_)))
    }

    /// The odometer measurement (the INS; the planar robot's wheels are its drive, not a
    /// measurement).
    pub fn odometer_measurement(&self, s: &OdometerSample) -> Result<LinearizedMeasurement, EstimationError> {
        match self {
            NavFilter::Ins(f) => f.odometer_measurement(s),
            NavFilter::Planar(_) => Err(EstimationError::NotApplicable("an odometer sample for a planar robot")),
        }
    }

    pub fn update_odometer(&mut self, s: &OdometerSample) -> Result<UpdateDiagnostics, EstimationError> {
        match self {
            NavFilter::Ins(f) => f.update_odometer(s),
            NavFilter::Planar(_) => Err(EstimationError::NotApplicable("an odometer sample for a planar robot")),
        }
    }

    pub fn position_ned_m(&self) -> Vector3<f64> {
        match self {
            NavFilter::Ins(f) => f.position_ned_m(),
            NavFilter::Planar(f) => f.position_ned_m(),
        }
    }

    pub fn velocity_ned_m_s(&self) -> Vector3<f64> {
        match self {
            NavFilter::Ins(f) => f.velocity_ned_m_s(),
            NavFilter::Planar(f) => f.velocity_ned_m_s(),
        }
    }

    pub fn yaw_rad(&self) -> f64 {
        match self {
            NavFilter::Ins(f) => f.yaw_rad(),
            NavFilter::Planar(f) => f.yaw_rad(),
        }
    }

    /// Body FRD to NED (level at the heading for the planar robot).
    pub fn attitude(&self) -> UnitQuaternion<f64> {
        match self {
            NavFilter::Ins(f) => f.attitude(),
            NavFilter::Planar(f) => f.attitude(),
        }
    }

    /// The covariances a node reports, from one read of the filter's covariance (the INS's
    /// applies its pending decimated steps on every read). The planar robot's height, roll and
    /// pitch are not estimated: their variances are [`PLANAR_UNESTIMATED_VARIANCE`].
    pub fn output_covariances(&self) -> NavCovariances {
        let mut pose = Matrix6::zeros();
        let velocity_ned = match self {
            NavFilter::Ins(f) => {
                let p = f.covariance16();
                for (r, pr) in [(0, 0), (3, 6)] {
                    for (c, pc) in [(0, 0), (3, 6)] {
                        pose.fixed_view_mut::<3, 3>(r, c).copy_from(&p.fixed_view::<3, 3>(pr, pc));
                    }
                }
                p.fixed_view::<3, 3>(3, 3).into_owned()
            }
            NavFilter::Planar(f) => {
                let p = f.covariance3();
                for (r, pr) in [(0, 0), (1, 1), (5, 2)] {
                    for (c, pc) in [(0, 0), (1, 1), (5, 2)] {
                        pose[(r, c)] = p[(pr, pc)];
                    }
                }
                for i in [2, 3, 4] {
                    pose[(i, i)] = PLANAR_UNESTIMATED_VARIANCE;
                }
                f.velocity_covariance_ned()
            }
        };
        NavCovariances { pose, velocity_ned }
    }
}

/// What a node reports of its filter's covariance.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct NavCovariances {
    /// Position NED and attitude error about N, E, D: what ODOMETRY's pose covariance carries.
    pub pose: Matrix6<f64>,
    pub velocity_ned: Matrix3<f64>,
}

impl NavCovariances {
    /// Position NED, m^2.
    pub fn position(&self) -> Matrix3<f64> {
        self.pose.fixed_view::<3, 3>(0, 0).into_owned()
    }

    /// Yaw, rad^2.
    pub fn yaw_variance(&self) -> f64 {
        self.pose[(5, 5)]
    }
}

/// Variance reported for what a planar robot does not estimate (its height, roll and pitch:
/// level ground is assumed), m^2 or rad^2: 0.1 m and about 6 degrees.
pub const PLANAR_UNESTIMATED_VARIANCE: f64 = 0.01;

impl PlatformFilter for NavFilter {
    fn dim(&self) -> usize {
        match self {
            NavFilter::Ins(f) => f.dim(),
            NavFilter::Planar(f) => f.dim(),
        }
    }
    fn covariance(&self) -> DMatrix<f64> {
        match self {
            NavFilter::Ins(f) => f.covariance(),
            NavFilter::Planar(f) => f.covariance(),
        }
    }
    fn psi(&self) -> DMatrix<f64> {
        match self {
            NavFilter::Ins(f) => f.psi(),
            NavFilter::Planar(f) => f.psi(),
        }
    }
    fn geometry(&self) -> Geometry {
        match self {
            NavFilter::Ins(f) => f.geometry(),
            NavFilter::Planar(f) => f.geometry(),
        }
    }
    fn snapshot(&self, id: PlatformId) -> Snapshot {
        match self {
            NavFilter::Ins(f) => f.snapshot(id),
            NavFilter::Planar(f) => f.snapshot(id),
        }
    }
    fn update_local(&mut self, meas: &LinearizedMeasurement) -> Result<UpdateDiagnostics, EstimationError> {
        match self {
            NavFilter::Ins(f) => f.update_local(meas),
            NavFilter::Planar(f) => f.update_local(meas),
        }
    }
    fn apply_joint(&mut self, dx: &DVector<f64>, p: &DMatrix<f64>) -> Result<(), EstimationError> {
        match self {
            NavFilter::Ins(f) => f.apply_joint(dx, p),
            NavFilter::Planar(f) => f.apply_joint(dx, p),
        }
    }
    fn apply_bystander(&mut self, a: &DVector<f64>, b: &DMatrix<f64>) -> Result<(), EstimationError> {
        match self {
            NavFilter::Ins(f) => f.apply_bystander(a, b),
            NavFilter::Planar(f) => f.apply_bystander(a, b),
        }
    }
    fn set_track_psi(&mut self, on: bool) {
        match self {
            NavFilter::Ins(f) => f.set_track_psi(on),
            NavFilter::Planar(f) => f.set_track_psi(on),
        }
    }
    fn add_noise(&mut self, q: &DMatrix<f64>) -> Result<(), EstimationError> {
        match self {
            NavFilter::Ins(f) => f.add_noise(q),
            NavFilter::Planar(f) => f.add_noise(q),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_filter_takes_its_own_drive_only() {
        let model = NavModel::Planar {
            config: PlanarConfig::from_sample_sigmas(0.05, 0.01, 20.0),
            initial_sigma: PlanarSigma { pos_m: 1.0, yaw_rad: 0.01 },
        };
        let ins = InsState::at_rest(UnitQuaternion::from_euler_angles(0.0, 0.0, 0.7));
        let state = NavState::for_model(&model, ins);
        assert!(matches!(state, NavState::Planar(s) if (s.yaw_rad - 0.7).abs() < 1e-12));
        assert!(NavFilter::new(model, TimeUs(0), NavState::Ins(ins)).is_err(), "a state of another model");
        let mut f = NavFilter::new(model, TimeUs(0), state).unwrap();
        let imu = Drive::Imu(ImuSample {
            t: TimeUs(10_000),
            specific_force_frd_m_s2: Vector3::new(0.0, 0.0, -9.8),
            angular_rate_frd_rad_s: Vector3::zeros(),
        });
        assert!(!f.takes(&imu));
        assert_eq!(f.propagate(&imu), Err(WRONG_DRIVE));
        let wheel = Drive::Wheel(WheelSample { t: TimeUs(50_000), speed_m_s: 1.0, yaw_rate_rad_s: 0.0 });
        assert!(f.takes(&wheel));
        f.propagate(&wheel.at(TimeUs(25_000))).unwrap();
        f.propagate(&wheel).unwrap();
        assert!((f.position_ned_m()[0] - 0.05 * 0.7f64.cos()).abs() < 1e-12);
        assert!(f.update_odometer(&OdometerSample { t: TimeUs(50_000), speed_m_s: 1.0 }).is_err());
        assert_eq!(f.dim(), 3);
        let c = f.output_covariances();
        assert_eq!(c.pose[(5, 5)], f.covariance()[(2, 2)]);
        assert_eq!(c.position()[(2, 2)], PLANAR_UNESTIMATED_VARIANCE);
    }

    /// Writing a filter over another in place (a node's checkpoint slot) leaves what a fresh
    /// copy would be, for every pair of models.
    #[test]
    fn clone_from_is_a_copy_for_every_pair_of_models() {
        let planar = NavModel::Planar {
            config: PlanarConfig::from_sample_sigmas(0.05, 0.01, 20.0),
            initial_sigma: PlanarSigma { pos_m: 1.0, yaw_rad: 0.01 },
        };
        let sigma = crate::estimation::ins::InsInitialSigma::for_tests();
        let ins = NavModel::Ins { config: InsConfig::default(), initial_sigma: sigma };
        let at_rest = InsState::at_rest(UnitQuaternion::from_euler_angles(0.0, 0.0, 0.3));
        let make = |model: &NavModel, t: u64| NavFilter::new(*model, TimeUs(t), NavState::for_model(model, at_rest)).unwrap();
        let filters = [make(&ins, 0), make(&ins, 5), make(&planar, 0), make(&planar, 7)];
        for to in &filters {
            for from in &filters {
                let mut slot = to.clone();
                slot.clone_from(from);
                assert_eq!(format!("{slot:?}"), format!("{from:?}"));
            }
        }
    }
}
