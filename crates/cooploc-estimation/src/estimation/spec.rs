//! A vehicle described in numbers: its sensors' error figures, the filters' initial uncertainty
//! and tuning, its wheels (a planar robot), in the unit-bearing TOML keys that both a scenario
//! (`sitl::scenario`, the simulated world) and a vehicle profile (`node::profile`, a real
//! vehicle) use. Here, below both, so that neither needs the other: a scenario gives a
//! [`VehicleSpec`] and takes one, a profile is made from one and gives one.
//!
//! The checks here are the ones both share (finite, positive, non-negative); a profile adds its
//! own (plausible figures for a real sensor), a scenario its own (periods on the microsecond grid).

use serde::{Deserialize, Serialize};

/// One micro-g in m/s^2 (standard gravity 9.80665 m/s^2).
pub const MICRO_G_M_S2: f64 = 9.80665e-6;
/// One deg/h in rad/s.
pub const DEG_PER_H_RAD_S: f64 = std::f64::consts::PI / 180.0 / 3600.0;
/// One deg/sqrt(h) in rad/sqrt(s).
pub const DEG_PER_SQRT_H_RAD_PER_SQRT_S: f64 = std::f64::consts::PI / 180.0 / 60.0;

/// A field with a value outside its allowed range, named by its path in the file.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
#[error("invalid field `{field}`: {reason}")]
pub struct InvalidField {
    pub field: String,
    pub reason: String,
}

impl InvalidField {
    pub fn new(field: impl Into<String>, reason: impl Into<String>) -> Self {
        InvalidField { field: field.into(), reason: reason.into() }
    }
}

/// `v` is finite.
pub fn finite(field: &str, v: f64) -> Result<(), InvalidField> {
    if v.is_finite() { Ok(()) } else { Err(InvalidField::new(field, format!("must be finite, got {v}"))) }
}

/// `v` is finite and above zero.
pub fn positive(field: &str, v: f64) -> Result<(), InvalidField> {
    if v.is_finite() && v > 0.0 { Ok(()) } else { Err(InvalidField::new(field, format!("must be positive, got {v}"))) }
}

/// `v` is finite and not below zero.
pub fn non_negative(field: &str, v: f64) -> Result<(), InvalidField> {
    if v.is_finite() && v >= 0.0 { Ok(()) } else { Err(InvalidField::new(field, format!("must be non-negative, got {v}"))) }
}

/// One vehicle as a scenario simulates it and a profile describes it: what it navigates with and
/// the figures of its sensors and filters. `sensors` and `filter` are an INS vehicle's, `wheels`
/// a planar robot's; a scenario's vehicle has all three of the scenario's, and
/// `sitl::Scenario::put_vehicle` replaces only those given.
#[derive(Debug, Clone, PartialEq)]
pub struct VehicleSpec {
    /// Short name, for logs and reports.
    pub name: String,
    /// Latitude of the local frame, deg (the Earth-rate vector); `None` where not known yet.
    pub latitude_deg: Option<f64>,
    /// Magnitude of gravity, m/s^2.
    pub gravity_m_s2: f64,
    pub model: PlatformModel,
    pub sensors: Option<Sensors>,
    pub initial: InitialUncertainty,
    pub filter: Option<FilterTuning>,
    pub wheels: Option<Wheels>,
}

/// The wheel odometry of a wheeled robot without IMU: a differential drive whose two wheels'
/// distances give, over each interval, the mean forward speed and yaw rate.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Wheels {
    /// Rate of the wheel samples, Hz.
    pub rate_hz: f64,
    /// White noise on each sample's mean forward speed, m/s.
    pub speed_sigma_m_s: f64,
    /// White noise on each sample's mean yaw rate, deg/s.
    pub yaw_rate_sigma_deg_s: f64,
    /// Distance between the two wheels, m (what WHEEL_DISTANCE's two counters are apart).
    pub track_m: f64,
}

/// What a platform navigates with.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum PlatformModel {
    /// An IMU (strapdown INS) and an odometer.
    #[default]
    Ins,
    /// A wheeled robot: wheel odometry only (`[wheels]`), a planar filter.
    Planar,
}

/// Sensor error models, the same for every platform (each platform draws its own errors).
#[derive(Debug, Clone, Copy, PartialEq, Default, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Sensors {
    /// IMU sample rate, Hz. Each sample is the mean over its interval.
    pub imu_rate_hz: f64,
    /// Accelerometer constant bias: per-axis standard deviation of the per-run draw, micro-g.
    pub accel_bias_ug: f64,
    /// Accelerometer white noise density, micro-g/sqrt(Hz).
    pub accel_noise_ug_per_sqrt_hz: f64,
    /// Accelerometer bias instability as a random walk, micro-g/sqrt(s). Zero: constant bias.
    #[serde(default)]
    pub accel_bias_walk_ug_per_sqrt_s: f64,
    /// Gyro constant bias: per-axis standard deviation of the per-run draw, deg/h.
    pub gyro_bias_deg_h: f64,
    /// Gyro angle random walk, deg/sqrt(h).
    pub gyro_arw_deg_per_sqrt_h: f64,
    /// Gyro bias instability as a random walk, (deg/h)/sqrt(s). Zero: constant bias.
    #[serde(default)]
    pub gyro_bias_walk_deg_h_per_sqrt_s: f64,
    /// Odometer sample rate, Hz.
    pub odometer_rate_hz: f64,
    /// Odometer white noise on the forward speed, m/s.
    pub odometer_sigma_m_s: f64,
    /// Odometer scale factor error: standard deviation of the per-run draw (dimensionless).
    pub odometer_scale_sigma: f64,
}

/// Standard deviations of the filters' initial estimate errors; the world draws each run's
/// initial errors from them, and a filter initialises its covariance with them.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct InitialUncertainty {
    /// Per NED axis, m.
    pub position_sigma_m: f64,
    /// Per NED axis, m/s.
    pub velocity_sigma_m_s: f64,
    /// Roll and pitch, deg.
    pub roll_pitch_sigma_deg: f64,
    /// Yaw, deg.
    pub yaw_sigma_deg: f64,
}

/// Filter tuning that is not a sensor property.
#[derive(Debug, Clone, Copy, PartialEq, Default, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct FilterTuning {
    /// Non-holonomic constraint: body-right (lateral) velocity is zero with this sigma, m/s.
    pub nhc_lateral_sigma_m_s: f64,
    /// Non-holonomic constraint: body-down velocity is zero with this sigma, m/s.
    pub nhc_vertical_sigma_m_s: f64,
    /// Rate of the INS covariance (and Psi) propagation, Hz; must divide the IMU rate. Absent:
    /// the IMU rate (every sample).
    #[serde(default)]
    pub covariance_rate_hz: Option<f64>,
}
