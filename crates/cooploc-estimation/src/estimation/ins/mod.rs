//! Strapdown INS for a land vehicle: an error-state EKF with odometer and non-holonomic
//! constraints, implementing [`PlatformFilter`].
//!
//! # Frames and model
//!
//! - Navigation frame `n`: a local NED tangent frame fixed to the Earth at the configured
//!   latitude `L` (flat Earth): constant gravity `g^n = [0, 0, g]` (plumb-bob gravity, the
//!   centrifugal part included), Earth rate `w_ie^n = Omega [cos L, 0, -sin L]`,
//!   `Omega = 7.292115e-5 rad/s`, no transport rate (the frame does not move with the vehicle).
//! - Body frame `b`: FRD. `R = R_nb` maps body to navigation, `v^n = R v^b`.
//! - Yaw: heading of the body x axis from north, clockwise seen from above,
//!   `yaw = atan2(R[1,0], R[0,0])` ([`yaw_of`]).
//!
//! Nominal state ([`InsState`]): position `p^n`, velocity `v^n`, attitude `q_nb`, accelerometer
//! bias `b_a`, gyro bias `b_g` and odometer scale-factor error `k` (the odometer reads
//! `(1 + k)` times the forward speed).
//!
//! # Error state (16)
//!
//! | index | symbol | meaning | unit |
//! |---|---|---|---|
//! | 0..3 ([`POS`]) | `dp` | position error, NED | m |
//! | 3..6 ([`VEL`]) | `dv` | velocity error, NED | m/s |
//! | 6..9 ([`ATT`]) | `phi` | attitude error, navigation frame: `R_true = Exp(phi) R_est` | rad |
//! | 9..12 ([`ACCEL_BIAS`]) | `db_a` | accelerometer bias error, body | m/s^2 |
//! | 12..15 ([`GYRO_BIAS`]) | `db_g` | gyro bias error, body | rad/s |
//! | 15 ([`ODO_SCALE`]) | `dk` | odometer scale-factor error | 1 |
//!
//! `true = estimate + error` for every block but the attitude. A positive `phi_D` (index 8,
//! [`HEADING_INDEX`]) turns the true body clockwise seen from above with respect to the
//! estimate: the true yaw is the estimated yaw plus `phi_D` (exactly so for a level vehicle).
//!
//! # Mechanization (one [`ImuSample`], mean rates over `dt = t_k - t_{k-1}`)
//!
//! ```text
//! dth_k = (w_m - b_g) dt                      dv_k = (f_m - b_a) dt
//! dth_c = dth_k + 1/12 dth_{k-1} x dth_k                                  (two-sample coning)
//! dv_c  = dv_k + 1/2 dth_k x dv_k + 1/12 (dth_{k-1} x dv_k + dv_{k-1} x dth_k)   (rotation, sculling)
//! zeta  = w_ie^n dt                                                       (nav-frame rotation)
//! dv_sf = (I - 1/2 [zeta x]) R_{k-1} dv_c
//! v_mid = v_{k-1} + 1/2 (dv_sf + g^n dt)
//! v_k   = v_{k-1} + dv_sf + (g^n - 2 w_ie^n x v_mid) dt
//! p_k   = p_{k-1} + 1/2 (v_{k-1} + v_k) dt
//! q_k   = Exp(-zeta) q_{k-1} Exp(dth_c)                                    (renormalised)
//! ```
//!
//! The first sample after construction has no previous interval: its previous increments are
//! taken as zero (the same as assuming the rates were constant: the coning and sculling terms
//! then vanish). `(I - 1/2 [zeta x])` transforms the velocity increment with the attitude at
//! mid-interval rather than at its start: without it, a vehicle at rest would see a spurious
//! `1/2 (w_ie x g) dt` per step (a 6e-9 m/s step at 200 Hz that adds up to 0.2 m in 10 min). The
//! Coriolis term uses the mid-interval velocity for the same reason (second-order accuracy).
//!
//! # Error dynamics
//!
//! ```text
//! d(dp)/dt   = dv
//! d(dv)/dt   = -[f^n x] phi - 2 [w_ie^n x] dv - R db_a - R n_a        f^n = R (f_m - b_a)
//! d(phi)/dt  = -[w_ie^n x] phi - R db_g - R n_g
//! d(db_a)/dt = n_ba,   d(db_g)/dt = n_bg,   d(dk)/dt = 0
//! ```
//!
//! discretised per IMU step as `Phi = I + F dt` (with `R = R_{k-1}`), `Qd = diag(0, q_a dt I,
//! q_g dt I, q_ba dt I, q_bg dt I, 0)` where the `q` are the (isotropic) power spectral densities
//! of the configured noise densities, so `R diag(q) R^T = q I`. The time update computes
//! `P <- Phi P Phi^T + Qd` and `Psi <- Phi Psi` blockwise (never a dense 16x16 product).
//!
//! # Odometer and non-holonomic constraints
//!
//! One 3-row measurement per odometer sample, applied at the filter's current time (the caller
//! propagates the IMU up to the odometer sample first; a small offset between the two is not
//! rejected): `z = [speed, 0, 0]`, `h = [(1 + k) v^b_x, v^b_y, v^b_z]`, `v^b = R^T v^n`, with
//!
//! ```text
//! dh/d(dv)  = R^T                (row 0 times (1 + k))
//! dh/d(phi) = R^T [v^n x]        (row 0 times (1 + k))
//! dh/d(dk)  = [v^b_x, 0, 0]^T
//! ```
//!
//! # Error reset
//!
//! After every update the estimated error `dx` is injected (`p += dp`, `v += dv`,
//! `R <- Exp(phi_hat) R`, `b_a += db_a`, `b_g += db_g`, `k += dk`) and the error restarts at zero.
//! The reset Jacobian `G` is the identity but for its attitude block, which is the left Jacobian
//! of SO(3) at the injected correction: `G_phi = J_l(phi_hat) = I + 1/2 [phi_hat x] + O(|phi_hat|^2)`
//! (see [`reset_jacobian`] for the derivation). Then `P <- G P G^T` and `Psi <- G Psi`.

use nalgebra::{DMatrix, DVector, Matrix3, SMatrix, SVector, UnitQuaternion, Vector3};
use serde::{Deserialize, Serialize};

use super::platform::{Geometry, Heading, PlatformFilter, PlatformId, Snapshot, check_joint_writeback};
use super::{EstimationError, ImuSample, LinearizedMeasurement, OdometerSample, UpdateDiagnostics, kalman};
use crate::time::TimeUs;

mod local_update;

#[cfg(test)]
mod tests;

/// Error-state dimension.
pub const ERROR_DIM: usize = 16;
/// First index of the position error (N, E, D), m.
pub const POS: usize = 0;
/// First index of the velocity error (N, E, D), m/s.
pub const VEL: usize = 3;
/// First index of the attitude error `phi` (N, E, D axes of the navigation frame), rad.
pub const ATT: usize = 6;
/// First index of the accelerometer bias error (body F, R, D), m/s^2.
pub const ACCEL_BIAS: usize = 9;
/// First index of the gyro bias error (body F, R, D), rad/s.
pub const GYRO_BIAS: usize = 12;
/// Index of the odometer scale-factor error.
pub const ODO_SCALE: usize = 15;
/// Index of the error whose positive value increases yaw (`phi_D`).
pub const HEADING_INDEX: usize = ATT + 2;

/// Earth rotation rate (WGS-84), rad/s.
pub const EARTH_RATE_RAD_S: f64 = 7.292_115e-5;
/// Standard gravity, m/s^2.
pub const STANDARD_GRAVITY_M_S2: f64 = 9.806_65;

/// A 16x16 matrix over the error state.
pub type Matrix16 = SMatrix<f64, ERROR_DIM, ERROR_DIM>;
/// A vector over the error state.
/// Measurement Jacobians of the 16-state error: any number of rows, 16 columns.
type Rows16 = nalgebra::OMatrix<f64, nalgebra::Dyn, nalgebra::Const<ERROR_DIM>>;
pub type Vector16 = SVector<f64, ERROR_DIM>;

/// Largest specific force accepted, m/s^2 (50 g); beyond it a sample is rejected as absurd.
pub const MAX_SPECIFIC_FORCE_M_S2: f64 = 50.0 * STANDARD_GRAVITY_M_S2;
/// Largest angular rate accepted, rad/s.
pub const MAX_ANGULAR_RATE_RAD_S: f64 = 40.0;

fn default_gravity() -> f64 {
    STANDARD_GRAVITY_M_S2
}
fn default_sigma_odometer() -> f64 {
    0.2
}
fn default_sigma_nhc() -> f64 {
    0.05
}
fn default_max_imu_gap() -> f64 {
    0.5
}

/// Configuration of the INS filter. Noise densities are one-sided amplitude spectral densities,
/// the same on every axis.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct InsConfig {
    /// Latitude of the navigation-frame origin, degrees (sets the Earth-rate vector).
    pub latitude_deg: f64,
    /// Gravity magnitude, m/s^2 (default 9.80665).
    #[serde(default = "default_gravity")]
    pub gravity_m_s2: f64,
    /// Accelerometer white noise (velocity random walk), m/s^2/sqrt(Hz) = m/s/sqrt(s).
    pub accel_noise_density_m_s2_per_sqrt_hz: f64,
    /// Gyro white noise (angle random walk), rad/s/sqrt(Hz) = rad/sqrt(s).
    pub gyro_noise_density_rad_s_per_sqrt_hz: f64,
    /// Accelerometer bias random walk, m/s^3/sqrt(Hz) = (m/s^2)/sqrt(s) (default 0: constant bias).
    #[serde(default)]
    pub accel_bias_random_walk_m_s3_per_sqrt_hz: f64,
    /// Gyro bias random walk, rad/s^2/sqrt(Hz) = (rad/s)/sqrt(s) (default 0: constant bias).
    #[serde(default)]
    pub gyro_bias_random_walk_rad_s2_per_sqrt_hz: f64,
    /// Standard deviation of the odometer speed, m/s (default 0.2).
    #[serde(default = "default_sigma_odometer")]
    pub sigma_odometer_m_s: f64,
    /// Standard deviation of the lateral (body y) velocity constraint, m/s (default 0.05).
    #[serde(default = "default_sigma_nhc")]
    pub sigma_nhc_lateral_m_s: f64,
    /// Standard deviation of the vertical (body z) velocity constraint, m/s (default 0.05).
    #[serde(default = "default_sigma_nhc")]
    pub sigma_nhc_vertical_m_s: f64,
    /// Longest accepted interval between IMU samples, s (default 0.5).
    #[serde(default = "default_max_imu_gap")]
    pub max_imu_gap_s: f64,
    /// Propagate the covariance and `Psi` once every this many IMU samples (default 1: every
    /// sample). The nominal state integrates every sample regardless; over the interval the
    /// transition is `I + sum(F_k dt_k)` and the noise `Q sum(dt_k)`, which drops only
    /// second-order terms in `F dt` (as PX4's EKF2 or PSINS do at a filter rate below the IMU
    /// rate). Any update first brings the covariance to the present.
    #[serde(default = "default_covariance_decimation")]
    pub covariance_decimation: u32,
}

fn default_covariance_decimation() -> u32 {
    1
}

impl Default for InsConfig {
    /// An automotive-grade MEMS IMU (VRW 0.06 m/s/sqrt(h), ARW 0.2 deg/sqrt(h)) at the equator,
    /// constant biases, and the default odometer and constraint sigmas.
    fn default() -> Self {
        Self {
            latitude_deg: 0.0,
            gravity_m_s2: default_gravity(),
            accel_noise_density_m_s2_per_sqrt_hz: 1.0e-3,
            gyro_noise_density_rad_s_per_sqrt_hz: 5.8e-5,
            accel_bias_random_walk_m_s3_per_sqrt_hz: 0.0,
            gyro_bias_random_walk_rad_s2_per_sqrt_hz: 0.0,
            sigma_odometer_m_s: default_sigma_odometer(),
            sigma_nhc_lateral_m_s: default_sigma_nhc(),
            sigma_nhc_vertical_m_s: default_sigma_nhc(),
            max_imu_gap_s: default_max_imu_gap(),
            covariance_decimation: default_covariance_decimation(),
        }
    }
}

impl InsConfig {
    /// Checks every field; the error names the field and its value.
    pub fn validate(&self) -> Result<(), EstimationError> {
        let lat = self.latitude_deg;
        if !lat.is_finite() || lat.abs() > 90.0 {
            return Err(EstimationError::InvalidValue { what: "latitude_deg", value: lat });
        }
        let positive = [
            (self.gravity_m_s2, "gravity_m_s2"),
            (self.sigma_odometer_m_s, "sigma_odometer_m_s"),
            (self.sigma_nhc_lateral_m_s, "sigma_nhc_lateral_m_s"),
            (self.sigma_nhc_vertical_m_s, "sigma_nhc_vertical_m_s"),
            (self.max_imu_gap_s, "max_imu_gap_s"),
        ];
        for (value, what) in positive {
            if !value.is_finite() || value <= 0.0 {
                return Err(EstimationError::InvalidValue { what, value });
            }
        }
        if self.covariance_decimation == 0 {
            return Err(EstimationError::InvalidValue { what: "covariance_decimation", value: 0.0 });
        }
        let non_negative = [
            (self.accel_noise_density_m_s2_per_sqrt_hz, "accel_noise_density_m_s2_per_sqrt_hz"),
            (self.gyro_noise_density_rad_s_per_sqrt_hz, "gyro_noise_density_rad_s_per_sqrt_hz"),
            (self.accel_bias_random_walk_m_s3_per_sqrt_hz, "accel_bias_random_walk_m_s3_per_sqrt_hz"),
            (self.gyro_bias_random_walk_rad_s2_per_sqrt_hz, "gyro_bias_random_walk_rad_s2_per_sqrt_hz"),
        ];
        for (value, what) in non_negative {
            if !value.is_finite() || value < 0.0 {
                return Err(EstimationError::InvalidValue { what, value });
            }
        }
        Ok(())
    }

    /// Earth rotation rate in the navigation frame, rad/s.
    pub fn earth_rate_ned_rad_s(&self) -> Vector3<f64> {
        let (s, c) = self.latitude_deg.to_radians().sin_cos();
        EARTH_RATE_RAD_S * Vector3::new(c, 0.0, -s)
    }

    /// Gravity in the navigation frame, m/s^2.
    pub fn gravity_ned_m_s2(&self) -> Vector3<f64> {
        Vector3::new(0.0, 0.0, self.gravity_m_s2)
    }
}

/// The nominal state of the INS.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct InsState {
    /// Position relative to the navigation-frame origin, NED, m.
    pub pos_ned_m: Vector3<f64>,
    /// Velocity relative to the Earth, NED, m/s.
    pub vel_ned_m_s: Vector3<f64>,
    /// Attitude, body FRD to NED: `v_ned = att_frd_to_ned * v_frd`.
    pub att_frd_to_ned: UnitQuaternion<f64>,
    /// Accelerometer bias, body FRD, m/s^2 (measured = true + bias).
    pub accel_bias_frd_m_s2: Vector3<f64>,
    /// Gyro bias, body FRD, rad/s (measured = true + bias).
    pub gyro_bias_frd_rad_s: Vector3<f64>,
    /// Odometer scale-factor error (the odometer reads `(1 + k)` times the forward speed).
    pub odometer_scale_error: f64,
}

impl InsState {
    /// At rest at the origin with attitude `att_frd_to_ned`, zero biases and scale error.
    pub fn at_rest(att_frd_to_ned: UnitQuaternion<f64>) -> Self {
        Self {
            pos_ned_m: Vector3::zeros(),
            vel_ned_m_s: Vector3::zeros(),
            att_frd_to_ned,
            accel_bias_frd_m_s2: Vector3::zeros(),
            gyro_bias_frd_rad_s: Vector3::zeros(),
            odometer_scale_error: 0.0,
        }
    }

    fn is_finite(&self) -> bool {
        let q = self.att_frd_to_ned.as_ref();
        self.pos_ned_m.iter().all(|v| v.is_finite())
            && self.vel_ned_m_s.iter().all(|v| v.is_finite())
            && q.coords.iter().all(|v| v.is_finite())
            && self.accel_bias_frd_m_s2.iter().all(|v| v.is_finite())
            && self.gyro_bias_frd_rad_s.iter().all(|v| v.is_finite())
            && self.odometer_scale_error.is_finite()
    }

    /// This state with the error `dx` injected (`true = estimate + error`, `R <- Exp(phi) R`).
    /// Fails, returning nothing, when the result is not finite.
    pub fn injected(&self, dx: &Vector16) -> Result<InsState, EstimationError> {
        let phi = dx.fixed_rows::<3>(ATT).into_owned();
        let q = UnitQuaternion::from_scaled_axis(phi) * self.att_frd_to_ned;
        let out = InsState {
            pos_ned_m: self.pos_ned_m + dx.fixed_rows::<3>(POS),
            vel_ned_m_s: self.vel_ned_m_s + dx.fixed_rows::<3>(VEL),
            att_frd_to_ned: UnitQuaternion::new_normalize(q.into_inner()),
            accel_bias_frd_m_s2: self.accel_bias_frd_m_s2 + dx.fixed_rows::<3>(ACCEL_BIAS),
            gyro_bias_frd_rad_s: self.gyro_bias_frd_rad_s + dx.fixed_rows::<3>(GYRO_BIAS),
            odometer_scale_error: self.odometer_scale_error + dx[ODO_SCALE],
        };
        if out.is_finite() { Ok(out) } else { Err(EstimationError::NonFinite { what: "INS state after error injection" }) }
    }
}

/// Initial one-sigma uncertainty of each error block (the initial covariance is diagonal).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct InsInitialSigma {
    /// Position, N/E/D, m.
    pub pos_ned_m: Vector3<f64>,
    /// Velocity, N/E/D, m/s.
    pub vel_ned_m_s: Vector3<f64>,
    /// Attitude error about the N/E/D axes, rad (about N and E: roll and pitch of a vehicle
    /// heading north; about D: yaw).
    pub att_ned_rad: Vector3<f64>,
    /// Accelerometer bias per body axis, m/s^2.
    pub accel_bias_frd_m_s2: Vector3<f64>,
    /// Gyro bias per body axis, rad/s.
    pub gyro_bias_frd_rad_s: Vector3<f64>,
    /// Odometer scale-factor error.
    pub odometer_scale: f64,
}

impl InsInitialSigma {
    /// 1 m, 0.1 m/s, 0.01 rad, 0.01 m/s^2, 1e-4 rad/s and 0.01 on every axis: a start for tests
    /// that need one, not a vehicle's.
    pub fn for_tests() -> Self {
        InsInitialSigma {
            pos_ned_m: Vector3::repeat(1.0),
            vel_ned_m_s: Vector3::repeat(0.1),
            att_ned_rad: Vector3::repeat(0.01),
            accel_bias_frd_m_s2: Vector3::repeat(0.01),
            gyro_bias_frd_rad_s: Vector3::repeat(1e-4),
            odometer_scale: 0.01,
        }
    }

    /// The diagonal covariance these sigmas describe; fails on a negative or non-finite sigma.
    pub fn covariance(&self) -> Result<Matrix16, EstimationError> {
        let mut sigma = Vector16::zeros();
        let blocks = [
            (POS, self.pos_ned_m, "initial position sigma"),
            (VEL, self.vel_ned_m_s, "initial velocity sigma"),
            (ATT, self.att_ned_rad, "initial attitude sigma"),
            (ACCEL_BIAS, self.accel_bias_frd_m_s2, "initial accelerometer bias sigma"),
            (GYRO_BIAS, self.gyro_bias_frd_rad_s, "initial gyro bias sigma"),
        ];
        for (i, s, what) in blocks {
            for (axis, &v) in s.iter().enumerate() {
                if !v.is_finite() || v < 0.0 {
                    return Err(EstimationError::InvalidValue { what, value: v });
                }
                sigma[i + axis] = v;
            }
        }
        let k = self.odometer_scale;
        if !k.is_finite() || k < 0.0 {
            return Err(EstimationError::InvalidValue { what: "initial odometer scale sigma", value: k });
        }
        sigma[ODO_SCALE] = k;
        Ok(Matrix16::from_diagonal(&sigma.component_mul(&sigma)))
    }
}

/// Yaw of an attitude (body FRD to NED): heading of the body x axis from north, clockwise seen
/// from above, `atan2(R[1,0], R[0,0])`, in [-pi, pi].
pub fn yaw_of(q: &UnitQuaternion<f64>) -> f64 {
    let (w, x, y, z) = (q.w, q.i, q.j, q.k);
    let r10 = 2.0 * (x * y + w * z);
    let r00 = 1.0 - 2.0 * (y * y + z * z);
    r10.atan2(r00)
}

/// The attitude error `phi` with `R_true = Exp(phi) R_est`, in the navigation frame (rad): what
/// the filter's attitude error state estimates. Its D component is the yaw error (true minus
/// estimated) for a level vehicle.
pub fn attitude_error_ned(true_q: &UnitQuaternion<f64>, est_q: &UnitQuaternion<f64>) -> Vector3<f64> {
    (true_q * est_q.inverse()).scaled_axis()
}

/// The reset Jacobian `G` of injecting the error correction `dx_hat` (identity but for the
/// attitude block).
///
/// Derivation for this filter's left (navigation-frame) attitude error. Before the reset,
/// `R_true = Exp(phi) R_est` and the update estimates `phi = phi_hat + d` with `d` the remaining
/// error. The reset sets `R_new = Exp(phi_hat) R_est`, so the new error `phi+`, defined by
/// `R_true = Exp(phi+) R_new`, is
///
/// ```text
/// Exp(phi+) = Exp(phi_hat + d) Exp(-phi_hat) = Exp(J_l(phi_hat) d) Exp(phi_hat) Exp(-phi_hat)
///           = Exp(J_l(phi_hat) d)        =>   G_phi = d(phi+)/d(d) = J_l(phi_hat)
/// ```
///
/// using the left Jacobian of SO(3), `Exp(a + b) ~= Exp(J_l(a) b) Exp(a)`, with
/// `J_l(a) = I + (1 - cos t)/t^2 [a x] + (t - sin t)/t^3 [a x]^2`, `t = |a|`. To first order
/// `G_phi = I + 1/2 [phi_hat x]`: the *plus* sign of Sola (2017, "Quaternion kinematics for the
/// error-state Kalman filter", section 7.2) for a global (left, `Exp(phi) R`) error, not the
/// minus sign of his local (right, `R Exp(dtheta)`) error, where the roles of the two factors are
/// swapped. (The first-order BCH check: `log(Exp(a) Exp(b)) ~= a + b + 1/2 a x b` with
/// `a = phi_hat + d`, `b = -phi_hat` gives `phi+ ~= d + 1/2 phi_hat x d`.) The unit tests check
/// `G` against a numerical derivative of this very map.
pub fn reset_jacobian(dx_hat: &Vector16) -> Matrix16 {
    let mut g = Matrix16::identity();
    g.fixed_view_mut::<3, 3>(ATT, ATT).copy_from(&so3_left_jacobian(&dx_hat.fixed_rows::<3>(ATT).into_owned()));
    g
}

/// Left Jacobian of SO(3) (see [`reset_jacobian`]).
fn so3_left_jacobian(a: &Vector3<f64>) -> Matrix3<f64> {
    let t2 = a.norm_squared();
    let t = t2.sqrt();
    let (c1, c2) = if t < 1e-4 {
        // Series, accurate to rounding for t < 1e-4.
        (0.5 - t2 / 24.0, 1.0 / 6.0 - t2 / 120.0)
    } else {
        ((1.0 - t.cos()) / t2, (t - t.sin()) / (t2 * t))
    };
    let s = a.cross_matrix();
    Matrix3::identity() + s * c1 + s * s * c2
}

/// A 3x3 block, row-major (`b[i][j]` is row `i`, column `j`).
type Block = [[f64; 3]; 3];

fn block(m: &Matrix3<f64>) -> Block {
    [[m.m11, m.m12, m.m13], [m.m21, m.m22, m.m23], [m.m31, m.m32, m.m33]]
}

/// The columns of a 16x16 matrix (nalgebra's column-major storage): `c[j][i]` is row `i`,
/// column `j`.
type Columns = [[f64; ERROR_DIM]; ERROR_DIM];

/// The nonzero blocks of `F dt` (the continuous error dynamics times the step).
#[derive(Debug, Clone, Copy, PartialEq)]
struct FdtBlocks {
    /// `d(dp)/d(dv) dt = dt I`.
    pv: f64,
    /// `-2 [w_ie x] dt`.
    vv: Block,
    /// `-[f^n x] dt`.
    vphi: Block,
    /// `-[w_ie x] dt`.
    phiphi: Block,
    /// `-R dt`: both the velocity row's `db_a` block and the attitude row's `db_g` block.
    neg_r: Block,
}

impl FdtBlocks {
    /// `F dt` for the step `dt` from attitude `r` (body to NED), specific force `f_n` in NED
    /// and Earth rate `w_ie`.
    fn new(dt: f64, r: &Matrix3<f64>, f_n: &Vector3<f64>, w_ie: &Vector3<f64>) -> Self {
        let neg_wie_dt = w_ie.cross_matrix() * -dt;
        Self {
            pv: dt,
            vv: block(&(neg_wie_dt * 2.0)),
            vphi: block(&(f_n.cross_matrix() * -dt)),
            phiphi: block(&neg_wie_dt),
            neg_r: block(&(r * -dt)),
        }
    }

    /// The sum of two steps' `F dt` (first-order transition over both).
    fn add(&self, o: &FdtBlocks) -> FdtBlocks {
        let add = |a: &Block, b: &Block| std::array::from_fn(|i| std::array::from_fn(|j| a[i][j] + b[i][j]));
        FdtBlocks {
            pv: self.pv + o.pv,
            vv: add(&self.vv, &o.vv),
            vphi: add(&self.vphi, &o.vphi),
            phiphi: add(&self.phiphi, &o.phiphi),
            neg_r: add(&self.neg_r, &o.neg_r),
        }
    }

    /// The dense `F dt` (tests).
    #[cfg(test)]
    fn dense(&self) -> Matrix16 {
        let m = |b: &Block| Matrix3::from_fn(|i, j| b[i][j]);
        let mut f = Matrix16::zeros();
        f.fixed_view_mut::<3, 3>(POS, VEL).copy_from(&(Matrix3::identity() * self.pv));
        f.fixed_view_mut::<3, 3>(VEL, VEL).copy_from(&m(&self.vv));
        f.fixed_view_mut::<3, 3>(VEL, ATT).copy_from(&m(&self.vphi));
        f.fixed_view_mut::<3, 3>(VEL, ACCEL_BIAS).copy_from(&m(&self.neg_r));
        f.fixed_view_mut::<3, 3>(ATT, ATT).copy_from(&m(&self.phiphi));
        f.fixed_view_mut::<3, 3>(ATT, GYRO_BIAS).copy_from(&m(&self.neg_r));
        f
    }
}

#[inline(always)]
fn dot3(a: &[f64; 3], b: &[f64; 3]) -> f64 {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}

/// Rows 0..9 of `(I + F dt) c` for one column `c`, written into `o` (whose other rows are left
/// alone): the nonzero 3x3 blocks of `F dt` on the 3-row slabs of `c`.
#[inline(always)]
fn phi_rows(f: &FdtBlocks, c: &[f64; ERROR_DIM], o: &mut [f64; ERROR_DIM]) {
    let v = [c[VEL], c[VEL + 1], c[VEL + 2]];
    let a = [c[ATT], c[ATT + 1], c[ATT + 2]];
    let ba = [c[ACCEL_BIAS], c[ACCEL_BIAS + 1], c[ACCEL_BIAS + 2]];
    let bg = [c[GYRO_BIAS], c[GYRO_BIAS + 1], c[GYRO_BIAS + 2]];
    for i in 0..3 {
        o[POS + i] = c[POS + i] + f.pv * v[i];
        o[VEL + i] = v[i] + dot3(&f.vv[i], &v) + dot3(&f.vphi[i], &a) + dot3(&f.neg_r[i], &ba);
        o[ATT + i] = a[i] + dot3(&f.phiphi[i], &a) + dot3(&f.neg_r[i], &bg);
    }
}

/// `out = m (I + F dt)^T`: column `c` of the product is `m[:, c] + sum_k F dt[c, k] m[:, k]`, a
/// few contiguous 16-long column updates (only columns 0..9 differ from `m`).
#[inline(always)]
fn times_phi_transpose(f: &FdtBlocks, m: &Columns, out: &mut Columns) {
    out[ACCEL_BIAS..].copy_from_slice(&m[ACCEL_BIAS..]);
    for i in 0..3 {
        let mut dv = m[VEL + i];
        let mut dphi = m[ATT + i];
        for j in 0..3 {
            let (vv, vphi, nr, pp) = (f.vv[i][j], f.vphi[i][j], f.neg_r[i][j], f.phiphi[i][j]);
            let (cv, cphi, cba, cbg) = (&m[VEL + j], &m[ATT + j], &m[ACCEL_BIAS + j], &m[GYRO_BIAS + j]);
            for r in 0..ERROR_DIM {
                dv[r] += vv * cv[r] + vphi * cphi[r] + nr * cba[r];
                dphi[r] += pp * cphi[r] + nr * cbg[r];
            }
        }
        let (cp, cv) = (&m[POS + i], &m[VEL + i]);
        let dp = &mut out[POS + i];
        for r in 0..ERROR_DIM {
            dp[r] = cp[r] + f.pv * cv[r];
        }
        out[VEL + i] = dv;
        out[ATT + i] = dphi;
    }
}

/// False when an entry is NaN or infinite, by a branch-free sum (NaN and infinities propagate
/// through it). One add per value where [`kalman::all_finite`] takes a subtraction and an add,
/// and stricter: a sum that overflows also reads as non-finite, so a covariance with entries
/// near `f64::MAX` (diverged anyway) is refused too.
#[inline(always)]
fn sum_is_finite(m: &Columns) -> bool {
    let mut acc = [0.0; ERROR_DIM];
    for c in m {
        for (a, v) in acc.iter_mut().zip(c) {
            *a += v;
        }
    }
    acc.iter().sum::<f64>().is_finite()
}

/// `Phi P Phi^T + diag(qd)` for `Phi = I + F dt` and a symmetric `P`, never forming a dense
/// product:
///
/// - `B = P Phi^T` (columns 0..9 change, contiguous column updates);
/// - `Phi B` differs from `B` in rows 0..9 only. Its top-left 9x9 block is `Phi` applied to
///   columns 0..9 of `B` (symmetrised after); its bottom-left block is `B`'s as is; its
///   top-right block is the transpose of the bottom-left (the result is symmetric); its
///   bottom-right block is `P`'s.
#[allow(clippy::needless_range_loop)] // (i, j) and (j, i) pairs: indices read clearer than iterators
#[inline(always)]
fn propagate_covariance_body(f: &FdtBlocks, p: &Matrix16, qd_diag: &Vector16, out: &mut Matrix16) {
    const TOP: usize = ACCEL_BIAS; // rows 0..9 are the ones Phi changes
    times_phi_transpose(f, &p.data.0, &mut out.data.0);
    let m = &mut out.data.0;
    for c in m.iter_mut().take(TOP) {
        let b = *c;
        phi_rows(f, &b, c);
    }
    for j in 0..TOP {
        for i in (j + 1)..TOP {
            let v = 0.5 * (m[j][i] + m[i][j]);
            m[j][i] = v;
            m[i][j] = v;
        }
        for i in TOP..ERROR_DIM {
            m[i][j] = m[j][i];
        }
    }
    for (j, q) in qd_diag.iter().enumerate() {
        m[j][j] += q;
    }
}

// The covariance step compiled twice: for the baseline x86-64 (SSE2) and for AVX2, chosen at
// run time (see `dense::has_avx2`). Separate multiplies and adds either way (Rust never fuses
// them), so both round alike; only the vector width differs.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
fn covariance_step_avx2(
    f: &FdtBlocks,
    p: &Matrix16,
    qd_diag: &Vector16,
    p_out: &mut Matrix16,
    psi_t: Option<(&Matrix16, &mut Matrix16)>,
) -> Result<(), &'static str> {
    covariance_step_body(f, p, qd_diag, p_out, psi_t)
}

#[inline(always)]
fn covariance_step_body(
    f: &FdtBlocks,
    p: &Matrix16,
    qd_diag: &Vector16,
    p_out: &mut Matrix16,
    psi_t: Option<(&Matrix16, &mut Matrix16)>,
) -> Result<(), &'static str> {
    propagate_covariance_body(f, p, qd_diag, p_out);
    if !sum_is_finite(&p_out.data.0) {
        return Err("propagated INS covariance");
    }
    if let Some((m, out)) = psi_t {
        times_phi_transpose(f, &m.data.0, &mut out.data.0);
        if !sum_is_finite(&out.data.0) {
            return Err("propagated INS Psi");
        }
    }
    Ok(())
}

/// One covariance step: `p_out = Phi P Phi^T + diag(qd)` (see [`propagate_covariance_body`])
/// and, when given, `Psi^T` advanced to `Psi^T Phi^T` (every entry of the outputs written).
/// The error names the first output that is not finite.
fn covariance_step_into(
    f: &FdtBlocks,
    p: &Matrix16,
    qd_diag: &Vector16,
    p_out: &mut Matrix16,
    psi_t: Option<(&Matrix16, &mut Matrix16)>,
) -> Result<(), &'static str> {
    #[cfg(target_arch = "x86_64")]
    if crate::estimation::dense::has_avx2() {
        // SAFETY: the processor has AVX2 (checked just above).
        return unsafe { covariance_step_avx2(f, p, qd_diag, p_out, psi_t) };
    }
    covariance_step_body(f, p, qd_diag, p_out, psi_t)
}

/// An error naming `what` when an entry of `m` is not finite or their sum overflows (by
/// [`sum_is_finite`], branch-free).
fn check_finite16(m: &Matrix16, what: &'static str) -> Result<(), EstimationError> {
    if sum_is_finite(&m.data.0) { Ok(()) } else { Err(EstimationError::NonFinite { what }) }
}

/// `Phi P Phi^T + diag(qd)` (for tests: not checked for finiteness).
#[cfg(test)]
fn propagate_covariance(f: &FdtBlocks, p: &Matrix16, qd_diag: &Vector16) -> Matrix16 {
    let mut out = Matrix16::zeros();
    let _ = covariance_step_into(f, p, qd_diag, &mut out, None);
    out
}

/// `M (I + F dt)^T` (for tests).
#[cfg(test)]
fn times_phi_transpose_matrix(f: &FdtBlocks, m: &Matrix16) -> Matrix16 {
    let mut out = Matrix16::zeros();
    times_phi_transpose(f, &m.data.0, &mut out.data.0);
    out
}

/// A 16x16 matrix kept in two slots, one of them current: a step computes the next value into
/// the spare slot and, once it is checked, makes that slot current. No temporary to zero and
/// no copy back (the covariance and `Psi` steps run at 50 Hz per vehicle for every method of
/// every Monte Carlo run), and on error the current value is untouched. Equality and `Debug`
/// see the current value only: the spare slot is scratch.
#[derive(Clone, Copy)]
struct Slots {
    m: [Matrix16; 2],
    cur: usize,
}

impl Slots {
    fn new(m: Matrix16) -> Self {
        Self { m: [m, Matrix16::zeros()], cur: 0 }
    }

    fn get(&self) -> &Matrix16 {
        &self.m[self.cur]
    }

    fn set(&mut self, m: Matrix16) {
        self.m[self.cur] = m;
    }

    /// The current value and the spare slot.
    fn split(&mut self) -> (&Matrix16, &mut Matrix16) {
        let [a, b] = &mut self.m;
        if self.cur == 0 { (a, b) } else { (b, a) }
    }

    fn spare_mut(&mut self) -> &mut Matrix16 {
        &mut self.m[1 - self.cur]
    }

    /// Makes the spare slot current.
    fn commit(&mut self) {
        self.cur = 1 - self.cur;
    }

    /// `*self = *other` as far as anyone can tell (the current value), in half the bytes.
    fn copy_current_from(&mut self, other: &Slots) {
        self.cur = other.cur;
        self.m[other.cur] = other.m[other.cur];
    }
}

impl PartialEq for Slots {
    fn eq(&self, other: &Self) -> bool {
        self.get() == other.get()
    }
}

impl std::fmt::Debug for Slots {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        self.get().fmt(f)
    }
}

/// The INS error-state EKF of one land vehicle. Plain values only (`Copy`): a node's
/// checkpoint is one copy of it ([`InsFilter::copy_from`], which leaves out the scratch).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct InsFilter {
    config: InsConfig,
    w_ie_n: Vector3<f64>,
    g_n: Vector3<f64>,
    /// Diagonal of `Qd / dt` (continuous PSDs per error component).
    q_psd: Vector16,
    t: TimeUs,
    x: InsState,
    p: Slots,
    /// `Psi` transposed: its time update `Psi^T <- Psi^T Phi^T` is then a sequence of
    /// contiguous column operations.
    psi_t: Slots,
    track_psi: bool,
    /// Bias-corrected increments of the previous IMU interval (zero before the first).
    prev_dtheta: Vector3<f64>,
    prev_dv: Vector3<f64>,
    /// IMU steps whose covariance propagation is still to be applied: summed `F dt`, summed
    /// `dt`, count (see [`InsConfig::covariance_decimation`]).
    pending: Option<(FdtBlocks, f64, u32)>,
    /// The Earth's rotation over the last step's `dt` (its bits), as a quaternion.
    earth_turn: Option<(u64, UnitQuaternion<f64>)>,
}

impl InsFilter {
    /// `*self = *other`, the spare slots of the covariance and `Psi` (scratch) left out: a
    /// node's checkpoint at every instant, in about half the bytes of a whole copy.
    pub fn copy_from(&mut self, other: &InsFilter) {
        let InsFilter { config, w_ie_n, g_n, q_psd, t, x, p, psi_t, track_psi, prev_dtheta, prev_dv, pending, earth_turn } =
            other;
        self.config = *config;
        self.w_ie_n = *w_ie_n;
        self.g_n = *g_n;
        self.q_psd = *q_psd;
        self.t = *t;
        self.x = *x;
        self.p.copy_current_from(p);
        self.psi_t.copy_current_from(psi_t);
        self.track_psi = *track_psi;
        self.prev_dtheta = *prev_dtheta;
        self.prev_dv = *prev_dv;
        self.pending = *pending;
        self.earth_turn = *earth_turn;
    }

    /// A filter at time `t0` with nominal state `initial` and a diagonal initial covariance.
    pub fn new(
        config: InsConfig,
        t0: TimeUs,
        initial: InsState,
        initial_sigma: InsInitialSigma,
    ) -> Result<Self, EstimationError> {
        config.validate()?;
        // A deserialised quaternion need not be unit: normalise (a zero one becomes NaN here).
        let mut x = initial;
        x.att_frd_to_ned = UnitQuaternion::new_normalize(x.att_frd_to_ned.into_inner());
        if !x.is_finite() {
            return Err(EstimationError::NonFinite { what: "initial INS state" });
        }
        let p = initial_sigma.covariance()?;
        let mut q_psd = Vector16::zeros();
        let blocks = [
            (VEL, config.accel_noise_density_m_s2_per_sqrt_hz),
            (ATT, config.gyro_noise_density_rad_s_per_sqrt_hz),
            (ACCEL_BIAS, config.accel_bias_random_walk_m_s3_per_sqrt_hz),
            (GYRO_BIAS, config.gyro_bias_random_walk_rad_s2_per_sqrt_hz),
        ];
        for (i, density) in blocks {
            q_psd.fixed_rows_mut::<3>(i).fill(density * density);
        }
        Ok(Self {
            w_ie_n: config.earth_rate_ned_rad_s(),
            g_n: config.gravity_ned_m_s2(),
            config,
            q_psd,
            t: t0,
            x,
            p: Slots::new(p),
            psi_t: Slots::new(Matrix16::identity()),
            track_psi: true,
            prev_dtheta: Vector3::zeros(),
            prev_dv: Vector3::zeros(),
            pending: None,
            earth_turn: None,
        })
    }

    pub fn config(&self) -> &InsConfig {
        &self.config
    }

    /// Time of the last IMU sample (or of the initialisation).
    pub fn time(&self) -> TimeUs {
        self.t
    }

    /// Moves the filter's clock to `t` without propagating: for a filter initialised at a time
    /// that turns out not to be the vehicle's (a node started late with an initial state meant
    /// for "now"). The state and covariance are kept; the previous IMU increments are forgotten.
    pub fn restart_clock(&mut self, t: TimeUs) {
        self.t = t;
        self.prev_dtheta = Vector3::zeros();
        self.prev_dv = Vector3::zeros();
    }

    /// The nominal state.
    pub fn state(&self) -> &InsState {
        &self.x
    }

    /// Yaw from north, clockwise seen from above, rad.
    pub fn yaw_rad(&self) -> f64 {
        yaw_of(&self.x.att_frd_to_ned)
    }

    pub fn position_ned_m(&self) -> Vector3<f64> {
        self.x.pos_ned_m
    }

    pub fn velocity_ned_m_s(&self) -> Vector3<f64> {
        self.x.vel_ned_m_s
    }

    /// Attitude, body FRD to NED.
    pub fn attitude(&self) -> UnitQuaternion<f64> {
        self.x.att_frd_to_ned
    }

    /// Error covariance `P`.
    pub fn covariance16(&self) -> Matrix16 {
        self.current().0
    }

    /// Recursive coefficient matrix `Psi` (identity while not tracked).
    pub fn psi16(&self) -> Matrix16 {
        self.current().1.transpose()
    }

    /// Checks an IMU sample against the filter's time and physical bounds; returns `dt` in s.
    /// Covariance and transposed `Psi` at the current time: the stored ones with any pending
    /// propagation applied (see [`InsConfig::covariance_decimation`]). Changes nothing.
    fn current(&self) -> (Matrix16, Matrix16) {
        match &self.pending {
            None => (*self.p.get(), *self.psi_t.get()),
            Some((fdt, sum_dt, _)) => {
                let (mut p, mut psi_t) = (Matrix16::zeros(), *self.psi_t.get());
                let _ = self.propagated_into(fdt, *sum_dt, &mut p, self.track_psi.then_some(&mut psi_t));
                (p, psi_t)
            }
        }
    }

    /// The stored covariance carried over `fdt` (`sum_dt` s of process noise) into `p`, and the
    /// transposed `Psi` into `psi_t` when given; the error names the first that is not finite.
    fn propagated_into(
        &self,
        fdt: &FdtBlocks,
        sum_dt: f64,
        p: &mut Matrix16,
        psi_t: Option<&mut Matrix16>,
    ) -> Result<(), EstimationError> {
        covariance_step_into(fdt, self.p.get(), &(self.q_psd * sum_dt), p, psi_t.map(|out| (self.psi_t.get(), out)))
            .map_err(|what| EstimationError::NonFinite { what })
    }

    /// Applies the pending propagation over `fdt` (computed into the spare slots and checked
    /// before they are made current: on error nothing changes).
    fn apply_propagation(&mut self, fdt: &FdtBlocks, sum_dt: f64) -> Result<(), EstimationError> {
        let qd = self.q_psd * sum_dt;
        let (p, p_next) = self.p.split();
        let psi_t = if self.track_psi { Some(self.psi_t.split()) } else { None };
        covariance_step_into(fdt, p, &qd, p_next, psi_t).map_err(|what| EstimationError::NonFinite { what })?;
        self.p.commit();
        if self.track_psi {
            self.psi_t.commit();
        }
        self.pending = None;
        Ok(())
    }

    /// Applies any pending covariance propagation.
    fn flush(&mut self) -> Result<(), EstimationError> {
        if let Some((fdt, sum_dt, _)) = self.pending {
            self.apply_propagation(&fdt, sum_dt)?;
        }
        Ok(())
    }

    fn check_imu(&self, s: &ImuSample) -> Result<f64, EstimationError> {
        if s.t < self.t {
            return Err(EstimationError::TimeWentBackwards { what: "IMU sample", from_us: self.t.0, to_us: s.t.0 });
        }
        let dt = s.t.secs_since(self.t);
        if dt == 0.0 {
            return Err(EstimationError::InvalidValue { what: "IMU time step (s)", value: dt });
        }
        if dt > self.config.max_imu_gap_s {
            return Err(EstimationError::InvalidValue { what: "IMU sample gap (s)", value: dt });
        }
        kalman::check_finite(&s.specific_force_frd_m_s2, "IMU specific force")?;
        kalman::check_finite(&s.angular_rate_frd_rad_s, "IMU angular rate")?;
        let f = s.specific_force_frd_m_s2.norm();
        if f > MAX_SPECIFIC_FORCE_M_S2 {
            return Err(EstimationError::InvalidValue { what: "IMU specific force magnitude (m/s^2)", value: f });
        }
        let w = s.angular_rate_frd_rad_s.norm();
        if w > MAX_ANGULAR_RATE_RAD_S {
            return Err(EstimationError::InvalidValue { what: "IMU angular rate magnitude (rad/s)", value: w });
        }
        Ok(dt)
    }

    /// One IMU step: mechanization, covariance and `Psi` (see the module documentation). On
    /// error nothing changes.
    pub fn propagate(&mut self, s: &ImuSample) -> Result<(), EstimationError> {
        let dt = self.check_imu(s)?;
        let x = &self.x;
        let w_b = s.angular_rate_frd_rad_s - x.gyro_bias_frd_rad_s;
        let f_b = s.specific_force_frd_m_s2 - x.accel_bias_frd_m_s2;
        let dtheta = w_b * dt;
        let dv = f_b * dt;
        let dtheta_c = dtheta + self.prev_dtheta.cross(&dtheta) / 12.0;
        let dv_c = dv + 0.5 * dtheta.cross(&dv) + (self.prev_dtheta.cross(&dv) + self.prev_dv.cross(&dtheta)) / 12.0;

        let r = x.att_frd_to_ned.to_rotation_matrix().into_inner();
        let zeta = self.w_ie_n * dt;
        let dv_body_n = r * dv_c;
        let dv_sf = dv_body_n - 0.5 * zeta.cross(&dv_body_n);
        let dv_no_coriolis = dv_sf + self.g_n * dt;
        let v_mid = x.vel_ned_m_s + 0.5 * dv_no_coriolis;
        let vel = x.vel_ned_m_s + dv_no_coriolis - 2.0 * dt * self.w_ie_n.cross(&v_mid);
        let pos = x.pos_ned_m + 0.5 * dt * (x.vel_ned_m_s + vel);
        // The Earth's turn over `dt` (the same for every step of a steady IMU rate: computed
        // once, and kept only once the step succeeds).
        let earth_turn = match self.earth_turn {
            Some((bits, q)) if bits == dt.to_bits() => q,
            _ => UnitQuaternion::from_scaled_axis(-zeta),
        };
        let x = &self.x;
        let q = earth_turn * x.att_frd_to_ned * UnitQuaternion::from_scaled_axis(dtheta_c);
        let att = UnitQuaternion::new_normalize(q.into_inner());

        let fdt = FdtBlocks::new(dt, &r, &(r * f_b), &self.w_ie_n);
        let pending = match &self.pending {
            Some((acc, sum_dt, n)) => (acc.add(&fdt), sum_dt + dt, n + 1),
            None => (fdt, dt, 1),
        };

        let next = InsState { pos_ned_m: pos, vel_ned_m_s: vel, att_frd_to_ned: att, ..*x };
        if !next.is_finite() {
            return Err(EstimationError::NonFinite { what: "propagated INS state" });
        }
        if pending.2 >= self.config.covariance_decimation {
            let (fdt, sum_dt, _) = pending;
            self.apply_propagation(&fdt, sum_dt)?;
        } else {
            self.pending = Some(pending);
        }
        self.earth_turn = Some((dt.to_bits(), earth_turn));
        self.x = next;
        self.t = s.t;
        self.prev_dtheta = dtheta;
        self.prev_dv = dv;
        Ok(())
    }

    /// The odometer speed and the two non-holonomic constraints (zero lateral and vertical body
    /// velocity), linearised about the current estimate. Applied at the filter's current time:
    /// the caller propagates the IMU up to the sample time first. Changes nothing.
    pub fn odometer_measurement(&self, s: &OdometerSample) -> Result<LinearizedMeasurement, EstimationError> {
        if !s.speed_m_s.is_finite() {
            return Err(EstimationError::NonFinite { what: "odometer speed" });
        }
        let x = &self.x;
        let rt = x.att_frd_to_ned.to_rotation_matrix().into_inner().transpose();
        let vb = rt * x.vel_ned_m_s;
        let scale = 1.0 + x.odometer_scale_error;
        let mut h = DMatrix::zeros(3, ERROR_DIM);
        let mut h_v = rt;
        let mut h_phi = rt * x.vel_ned_m_s.cross_matrix();
        h_v.row_mut(0).scale_mut(scale);
        h_phi.row_mut(0).scale_mut(scale);
        h.fixed_view_mut::<3, 3>(0, VEL).copy_from(&h_v);
        h.fixed_view_mut::<3, 3>(0, ATT).copy_from(&h_phi);
        h[(0, ODO_SCALE)] = vb.x;
        let predicted = odometer_prediction(x);
        let residual = DVector::from_column_slice((Vector3::new(s.speed_m_s, 0.0, 0.0) - predicted).as_slice());
        let c = &self.config;
        let r = DMatrix::from_diagonal(&DVector::from_vec(vec![
            c.sigma_odometer_m_s.powi(2),
            c.sigma_nhc_lateral_m_s.powi(2),
            c.sigma_nhc_vertical_m_s.powi(2),
        ]));
        let meas = LinearizedMeasurement { h, residual, r };
        meas.validate(ERROR_DIM)?;
        Ok(meas)
    }

    /// [`Self::odometer_measurement`] applied as a local update.
    pub fn update_odometer(&mut self, s: &OdometerSample) -> Result<UpdateDiagnostics, EstimationError> {
        let meas = self.odometer_measurement(s)?;
        self.update_local(&meas)
    }
}

/// Predicted odometer and constraint measurement `h = [(1 + k) v^b_x, v^b_y, v^b_z]` of a state.
fn odometer_prediction(x: &InsState) -> Vector3<f64> {
    let vb = x.att_frd_to_ned.inverse_transform_vector(&x.vel_ned_m_s);
    Vector3::new((1.0 + x.odometer_scale_error) * vb.x, vb.y, vb.z)
}

fn to_vector16(v: &DVector<f64>) -> Vector16 {
    Vector16::from_column_slice(v.as_slice())
}

#[cfg(test)]
fn to_matrix16(m: &DMatrix<f64>) -> Matrix16 {
    Matrix16::from_column_slice(m.as_slice())
}

fn to_dmatrix(m: &Matrix16) -> DMatrix<f64> {
    DMatrix::from_column_slice(ERROR_DIM, ERROR_DIM, m.as_slice())
}

/// `G P G^T` for a reset Jacobian from [`reset_jacobian`], which differs from the identity only in
/// its attitude block: only the attitude rows and columns of `P` change (tests; the filter
/// resets in place).
#[cfg(test)]
fn reset_covariance(g: &Matrix16, p: &Matrix16) -> Matrix16 {
    let mut out = *p;
    reset_covariance_in_place(&g.fixed_view::<3, 3>(ATT, ATT).into_owned(), &mut out);
    out
}

/// `P <- G P G^T`, symmetrised, in place, for the attitude block `g_att` of a reset Jacobian:
/// the attitude rows times `g_att`, then the attitude columns times `g_att^T`, then
/// `(P + P^T) / 2` entry by entry (each pair's sum computed once, in either order alike).
#[allow(clippy::needless_range_loop)] // (i, j) and (j, i) pairs: indices read clearer than iterators
fn reset_covariance_in_place(g_att: &Matrix3<f64>, p: &mut Matrix16) {
    let rows = g_att * p.fixed_rows::<3>(ATT);
    p.fixed_rows_mut::<3>(ATT).copy_from(&rows);
    let cols = p.fixed_columns::<3>(ATT) * g_att.transpose();
    p.fixed_columns_mut::<3>(ATT).copy_from(&cols);
    let m = &mut p.data.0;
    for j in 0..ERROR_DIM {
        m[j][j] = 0.5 * (m[j][j] + m[j][j]);
        for i in (j + 1)..ERROR_DIM {
            let v = 0.5 * (m[j][i] + m[i][j]);
            m[j][i] = v;
            m[i][j] = v;
        }
    }
}

impl InsFilter {
    /// [`PlatformFilter::update_local`] on nalgebra's dynamic-size routines, for any number of
    /// rows (the caller has validated `meas` and flushed pending propagation).
    fn update_local_general(&mut self, meas: &LinearizedMeasurement) -> Result<UpdateDiagnostics, EstimationError> {
        let m = meas.len();
        let h = Rows16::from_fn(m, |r, c| meas.h[(r, c)]);
        let p = *self.p.get();
        let psi_t = *self.psi_t.get();
        let hp = &h * p;
        let mut s = DMatrix::from_fn(m, m, |r, c| hp.row(r).dot(&h.row(c))) + &meas.r;
        kalman::symmetrize(&mut s);
        let chol = nalgebra::Cholesky::new(s.clone())
            .ok_or(EstimationError::NotPositiveDefinite { what: "innovation covariance H P H^T + R" })?;
        let l = chol.l();
        let not_pd = EstimationError::NotPositiveDefinite { what: "innovation covariance factor" };
        let w = l.solve_lower_triangular(&hp).ok_or(not_pd.clone())?;
        let white = l.solve_lower_triangular(&meas.residual).ok_or(not_pd.clone())?;
        let dx: Vector16 = w.tr_mul(&white);
        *self.p.spare_mut() = p - w.tr_mul(&w);
        if self.track_psi {
            // Psi is stored transposed: Psi^T+ = Psi^T - (L^-1 H Psi)^T W.
            let z = l.solve_lower_triangular(&(&h * psi_t.transpose())).ok_or(not_pd)?;
            *self.psi_t.spare_mut() = psi_t - z.tr_mul(&w);
        }
        self.finish_local_update(&dx)?;
        let nis = white.norm_squared();
        Ok(UpdateDiagnostics { innovation: meas.residual.clone(), innovation_cov: s, nis })
    }

    /// The end of both local-update paths, which leave `P+` (and, when `Psi` is tracked,
    /// `Psi^T+`) in the spare slots: the error reset of the state, of `P+` and of `Psi^T+` (its
    /// attitude columns times `G_att^T`), each checked; then all three made current together (on
    /// error nothing changes).
    fn finish_local_update(&mut self, dx: &Vector16) -> Result<(), EstimationError> {
        let x = self.x.injected(dx)?;
        let g_att = reset_jacobian(dx).fixed_view::<3, 3>(ATT, ATT).into_owned();
        let p = self.p.spare_mut();
        reset_covariance_in_place(&g_att, p);
        check_finite16(p, "INS covariance after reset")?;
        if self.track_psi {
            let psi_t = self.psi_t.spare_mut();
            let cols = psi_t.fixed_columns::<3>(ATT) * g_att.transpose();
            psi_t.fixed_columns_mut::<3>(ATT).copy_from(&cols);
            check_finite16(psi_t, "INS Psi after update")?;
        }
        self.x = x;
        self.p.commit();
        if self.track_psi {
            self.psi_t.commit();
        }
        Ok(())
    }
}

impl PlatformFilter for InsFilter {
    fn dim(&self) -> usize {
        ERROR_DIM
    }

    fn covariance(&self) -> DMatrix<f64> {
        to_dmatrix(&self.current().0)
    }

    fn psi(&self) -> DMatrix<f64> {
        to_dmatrix(&self.current().1.transpose())
    }

    /// Covariance and `Psi` from one look at the current ones (the trait's default asks for
    /// each, each applying any pending propagation): the centralized EKF takes a snapshot of
    /// every platform ten times a second.
    fn snapshot(&self, id: PlatformId) -> Snapshot {
        let snapshot = |p: &Matrix16, psi_t: &Matrix16| Snapshot {
            id,
            geometry: self.geometry(),
            covariance: to_dmatrix(p),
            psi: DMatrix::from_fn(ERROR_DIM, ERROR_DIM, |r, c| psi_t[(c, r)]),
        };
        match self.pending {
            None => snapshot(self.p.get(), self.psi_t.get()),
            Some(_) => {
                let (p, psi_t) = self.current();
                snapshot(&p, &psi_t)
            }
        }
    }

    fn geometry(&self) -> Geometry {
        Geometry {
            position_ned_m: self.x.pos_ned_m,
            position_index: [Some(POS), Some(POS + 1), Some(POS + 2)],
            heading: Some(Heading { yaw_rad: self.yaw_rad(), index: HEADING_INDEX }),
        }
    }

    /// The optimal-gain update. With `S = L L^T` and `W = L^-1 H P`: `P+ = P - W^T W` (the
    /// optimal-gain covariance as a symmetric downdate, equal to the Joseph form for the
    /// optimal gain), `dx = W^T L^-1 r`, and `Psi+ = (I - K H) Psi = Psi - W^T L^-1 (H Psi)` with
    /// `K = W^T L^-1`; then the error reset: `P <- G P G^T`, `Psi <- G Psi`. Measurements of up
    /// to [`local_update::MAX_ROWS`] rows (all an INS node fuses) take the fixed-size path, the
    /// same results bit for bit.
    fn update_local(&mut self, meas: &LinearizedMeasurement) -> Result<UpdateDiagnostics, EstimationError> {
        meas.validate(ERROR_DIM)?;
        self.flush()?;
        if meas.len() <= local_update::MAX_ROWS { self.update_local_small(meas) } else { self.update_local_general(meas) }
    }

    fn apply_joint(&mut self, dx: &DVector<f64>, p: &DMatrix<f64>) -> Result<(), EstimationError> {
        check_joint_writeback(ERROR_DIM, dx, p)?;
        let dx = to_vector16(dx);
        let x = self.x.injected(&dx)?;
        let g = reset_jacobian(&dx);
        let spare = self.p.spare_mut();
        spare.copy_from_slice(p.as_slice());
        reset_covariance_in_place(&g.fixed_view::<3, 3>(ATT, ATT).into_owned(), spare);
        check_finite16(spare, "INS covariance after reset")?;
        self.x = x;
        self.p.commit();
        // The joint update started from the covariance at the present (pending steps included).
        self.pending = None;
        self.psi_t.set(if self.track_psi { g.transpose() } else { Matrix16::identity() });
        Ok(())
    }

    fn apply_bystander(&mut self, a: &DVector<f64>, b: &DMatrix<f64>) -> Result<(), EstimationError> {
        self.flush()?;
        let p = DMatrix::from_column_slice(ERROR_DIM, ERROR_DIM, self.p.get().as_slice());
        let psi = DMatrix::from_column_slice(ERROR_DIM, ERROR_DIM, self.psi_t.get().transpose().as_slice());
        let (dx, p) = crate::estimation::platform::bystander_posterior(&p, &psi, a, b)?;
        self.p.spare_mut().copy_from_slice(p.as_slice());
        if self.track_psi {
            let now = *self.psi_t.get();
            *self.psi_t.spare_mut() = now;
        }
        // The injection's error reset, of P and of Psi, as after a local update.
        self.finish_local_update(&to_vector16(&dx))
    }

    fn add_noise(&mut self, q: &DMatrix<f64>) -> Result<(), EstimationError> {
        crate::estimation::platform::check_noise(ERROR_DIM, q)?;
        self.flush()?;
        let now = *self.p.get();
        let spare = self.p.spare_mut();
        *spare = now + Matrix16::from_column_slice(q.as_slice());
        check_finite16(spare, "INS covariance after added noise")?;
        self.p.commit();
        Ok(())
    }

    /// Off: `Psi` is no longer updated and stays at the identity.
    fn set_track_psi(&mut self, on: bool) {
        self.track_psi = on;
        if !on {
            self.psi_t.set(Matrix16::identity());
        }
    }
}
