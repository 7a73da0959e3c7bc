//! The vehicle profile (`cooploc node --vehicle-config FILE.toml`): everything a node must know
//! about the vehicle it runs on, and nothing about the world around it.
//!
//! The vehicle part has the same keys as a scenario's (both read [`crate::estimation::spec`]):
//! `latitude_deg`, `gravity_m_s2`, `[sensors]` (IMU and odometer noise and bias figures, and the
//! rates the node asks for), `[initial]` (initial uncertainty) and `[filter]` (non-holonomic
//! constraints, covariance rate). A scenario's vehicle part *is* a profile
//! ([`VehicleProfile::from_spec`] of `sitl::Scenario::vehicle_of`), so the simulator and the node
//! read one format. A profile
//! adds what only a real vehicle has:
//!
//! - `model`: `"ins"` (the default: the autopilot streams its IMU and the node runs the strapdown
//!   INS, with `[sensors]` and `[filter]`) or `"planar"` (a wheeled robot without IMU in the
//!   navigation: the node runs the planar filter of [`crate::estimation::planar`] on the
//!   differential drive's WHEEL_DISTANCE, with the scenario's `[wheels]` section: rate, speed
//!   and yaw-rate noise, track; no `[sensors]` or `[filter]`). With `[inputs] yaw_rate = "gyro"`
//!   the yaw rate comes from the z rate of the IMU message `imu` names (a yaw-rate gyro; the
//!   `[wheels]` yaw-rate figure is then the gyro's), the wheels give the speed.
//! - `[origin]`: the geodetic point of the local NED frame (`lat_deg`, `lon_deg`, `alt_m`).
//!   The node compares it with the vehicle's GPS_GLOBAL_ORIGIN and HOME_POSITION and warns when
//!   they are far apart. Without `[origin]` or `latitude_deg` the node waits for the vehicle's
//!   GPS_GLOBAL_ORIGIN (or HOME_POSITION) before it starts, and its INS takes that latitude.
//! - `[inputs]`: which messages carry the IMU (`imu`: `highres_imu`, `raw_imu`, `scaled_imu`,
//!   `scaled_imu2`, `scaled_imu3`; `imu_id` for HIGHRES_IMU and RAW_IMU; `imu_samples`:
//!   `average` over the interval as PX4 sends, or `instantaneous` as ArduPilot does), the
//!   odometer (`odometer`: `odometry` for a wheel or odometer source's body velocity,
//!   `wheel_distance` for cumulative wheel distances with `wheels` and `wheel_track_m`, or
//!   `none`), the team clock (`clock`: `vehicle` when the vehicles' time stamps already share a
//!   clock, `unix` when they count from each autopilot's boot and SYSTEM_TIME maps them to Unix
//!   time, `companion` for the companion computer's clock mapped to the autopilot's boot clock
//!   by TIMESYNC, `auto` for the companion's clock when the autopilot answers TIMESYNC and
//!   SYSTEM_TIME's otherwise), the grid of the ranging epochs' instants (`epoch_grid_ms`), and
//!   whether to ask for the rates (`request_rates`).
//! - `[output]`: what the node sends back to the autopilot: ODOMETRY at `odometry_rate_hz`
//!   (0: none), LOCAL_POSITION_NED after every cooperative update (`local_position_ned`), and
//!   GPS_INPUT at `gps_input_rate_hz` (0, the default: none; ArduPilot's path for an absolute
//!   position, needs `[origin]`).
//!
//! Every key is checked (an unknown one is an error naming it), every value is validated with
//! its field named (`sensors.accel_noise_ug_per_sqrt_hz: ...`), and figures no real sensor can
//! have (zero or absurd noise) are refused, all before any socket opens. The examples in
//! `sitl/vehicles/` are a PX4 rover, an ArduPilot Rover and a wheeled robot without IMU.

use std::path::Path;

use nalgebra::Vector3;
use serde::{Deserialize, Serialize};

use crate::estimation::ins::{InsConfig, InsInitialSigma};
use crate::estimation::nav::NavModel;
use crate::estimation::planar::{DEFAULT_MAX_GAP_S, PlanarConfig, PlanarSigma};
use crate::estimation::spec::{
    DEG_PER_H_RAD_S, DEG_PER_SQRT_H_RAD_PER_SQRT_S, InvalidField, MICRO_G_M_S2, finite, non_negative, positive,
};
pub use crate::estimation::spec::{FilterTuning, InitialUncertainty, PlatformModel, Sensors, VehicleSpec, Wheels};
use crate::node::inputs::VehicleInputs;
use crate::protocol::wire::GeoOrigin;

/// Why a profile is refused.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum ProfileError {
    #[error("cannot read vehicle profile {path}: {message}")]
    Io { path: String, message: String },
    /// Not TOML, or not the profile's shape (the message names an unknown key or a missing field).
    #[error("cannot parse vehicle profile {path}: {message}")]
    Parse { path: String, message: String },
    #[error("invalid vehicle profile field `{field}`: {reason}")]
    Invalid { field: String, reason: String },
}

impl From<InvalidField> for ProfileError {
    fn from(e: InvalidField) -> Self {
        ProfileError::Invalid { field: e.field, reason: e.reason }
    }
}

fn invalid(field: impl Into<String>, reason: impl Into<String>) -> ProfileError {
    ProfileError::Invalid { field: field.into(), reason: reason.into() }
}

/// A vehicle profile (see the module documentation).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct VehicleProfile {
    /// Short name, for logs and reports.
    pub name: String,
    /// Latitude of the local frame, deg (the Earth-rate vector). Optional when `[origin]` gives
    /// it or the vehicle will.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub latitude_deg: Option<f64>,
    /// Magnitude of gravity, m/s^2.
    #[serde(default = "default_gravity")]
    pub gravity_m_s2: f64,
    /// `ins` (the default) or `planar`.
    #[serde(default)]
    pub model: PlatformModel,
    /// The IMU and odometer (an INS vehicle).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub sensors: Option<Sensors>,
    pub initial: InitialUncertainty,
    /// Non-holonomic constraints and covariance rate (an INS vehicle).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub filter: Option<FilterTuning>,
    /// The wheel odometry (a planar robot).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub wheels: Option<Wheels>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub origin: Option<OriginSpec>,
    #[serde(default)]
    pub inputs: Inputs,
    #[serde(default)]
    pub output: Output,
}

fn default_gravity() -> f64 {
    9.80665
}

/// The geodetic origin of the local NED frame.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct OriginSpec {
    pub lat_deg: f64,
    pub lon_deg: f64,
    #[serde(default)]
    pub alt_m: f64,
}

/// The message that carries the IMU.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum ImuMessage {
    /// HIGHRES_IMU (float SI units, `time_usec`; PX4's stream, ArduPilot's on request).
    HighresImu,
    /// RAW_IMU (int16 mG and mrad/s, `time_usec`; ArduPilot's first IMU).
    RawImu,
    /// SCALED_IMU (int16 mG and mrad/s, `time_boot_ms`).
    ScaledImu,
    /// SCALED_IMU2 (ArduPilot's second IMU).
    ScaledImu2,
    /// SCALED_IMU3.
    ScaledImu3,
}

impl ImuMessage {
    /// The MAVLink message id.
    pub fn message_id(self) -> u32 {
        match self {
            ImuMessage::HighresImu => 105,
            ImuMessage::RawImu => 27,
            ImuMessage::ScaledImu => 26,
            ImuMessage::ScaledImu2 => 116,
            ImuMessage::ScaledImu3 => 129,
        }
    }

    /// How the autopilots that send this message sample it: PX4's HIGHRES_IMU averages over
    /// its integration window; ArduPilot's RAW_IMU and SCALED_IMU* are the latest sample.
    pub fn default_samples(self) -> SampleKind {
        match self {
            ImuMessage::HighresImu => SampleKind::Average,
            _ => SampleKind::Instantaneous,
        }
    }

    pub fn name(self) -> &'static str {
        match self {
            ImuMessage::HighresImu => "HIGHRES_IMU",
            ImuMessage::RawImu => "RAW_IMU",
            ImuMessage::ScaledImu => "SCALED_IMU",
            ImuMessage::ScaledImu2 => "SCALED_IMU2",
            ImuMessage::ScaledImu3 => "SCALED_IMU3",
        }
    }
}

/// What one IMU message's values stand for.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum SampleKind {
    /// The mean over the interval since the previous sample (integrated IMU, PX4).
    Average,
    /// The value at the time stamp (ArduPilot): the node takes the mean of two consecutive
    /// samples as the mean over their interval (trapezoid).
    Instantaneous,
}

/// The message that carries the odometer.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum OdometerMessage {
    /// ODOMETRY with a body-frame (BODY_FRD) velocity from a wheel or odometer source. ODOMETRY
    /// whose estimator_type is AUTOPILOT (the autopilot's own EKF output, as PX4 sends) is
    /// refused: it is not an independent measurement.
    Odometry,
    /// WHEEL_DISTANCE (id 9000): cumulative distance per wheel, differentiated.
    WheelDistance,
    /// No odometer (the non-holonomic constraints alone bound the velocity).
    None,
}

/// Which clock the team's time stamps share.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum TeamClock {
    /// The vehicles' time stamps already share one clock (the simulator; autopilots that stamp
    /// in Unix time).
    Vehicle,
    /// Each autopilot counts from its own boot; the node maps its stamps to Unix time with the
    /// vehicle's SYSTEM_TIME (time_unix_usec against time_boot_ms). Stamps already in Unix time
    /// are used as they are. An autopilot has Unix time only from a GNSS fix (or a ground
    /// station that set it): ArduPilot without GNSS sends `time_unix_usec` 0 for ever.
    Unix,
    /// The companion computer's own clock (Unix time, kept by NTP or PTP; see docs/node.md on
    /// time without GNSS), mapped to the autopilot's boot clock with MAVLink TIMESYNC
    /// exchanges (ArduPilot and PX4 answer them with their boot time in ns): needs no GNSS.
    Companion,
    /// The companion's clock when the autopilot answers TIMESYNC, else SYSTEM_TIME's Unix time
    /// once [`crate::node::inputs::AUTO_CLOCK_WAIT_US`] of vehicle time has passed without an
    /// answer; the choice is said in the log.
    Auto,
}

/// Where the node's inputs come from.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Inputs {
    #[serde(default = "default_imu")]
    pub imu: ImuMessage,
    /// The IMU instance (HIGHRES_IMU and RAW_IMU `id`) to use; the others are counted and
    /// ignored.
    #[serde(default)]
    pub imu_id: u8,
    /// Default: the message's usual meaning ([`ImuMessage::default_samples`]).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub imu_samples: Option<SampleKind>,
    #[serde(default = "default_odometer")]
    pub odometer: OdometerMessage,
    /// WHEEL_DISTANCE indices: one wheel, or the left and the right wheel of a differential
    /// drive.
    #[serde(default = "default_wheels")]
    pub wheels: Vec<u8>,
    /// Distance between the two wheels, m (yaw rate of a differential drive).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub wheel_track_m: Option<f64>,
    #[serde(default = "default_clock")]
    pub clock: TeamClock,
    /// Grid of the ranging epochs' instants in the team's clock, ms (0: none). With a clock
    /// mapped from another one (`unix`, `companion`, `auto`) two nodes map the same instant a
    /// little apart (a TIMESYNC mapping is good to a fraction of the link's round trip); the
    /// ranges the vehicle reports are put on the nearest grid instant, so that every node
    /// names an epoch by the same instant as long as the mappings agree to half the grid. The
    /// team's ranging schedule must be on the grid (a 1 Hz schedule on whole seconds is).
    #[serde(default)]
    pub epoch_grid_ms: u32,
    /// Ask the autopilot for the IMU and odometer rates of `[sensors]` (SET_MESSAGE_INTERVAL).
    #[serde(default = "yes")]
    pub request_rates: bool,
    /// A planar robot's yaw rate: from its two wheels, or from the z rate of the IMU message
    /// `imu` names (a yaw-rate gyro; the wheels then give the speed only).
    #[serde(default)]
    pub yaw_rate: YawRateSource,
    /// How much older a GNSS fix is than its GPS_RAW_INT stamp, ms (the hand-over's fixes): the
    /// autopilot stamps a fix when it receives it, the receiver's own latency before (ArduPilot
    /// SITL: `SIM_GPS1_LAG_MS`, 100 ms by default; a u-blox M8 about 100-120 ms).
    #[serde(default)]
    pub gnss_lag_ms: u32,
}

/// Where a planar robot's yaw rate comes from.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum YawRateSource {
    /// The difference of the left and right wheels over the track.
    #[default]
    Wheels,
    /// The IMU's z rate, averaged over each wheel interval (its bias and the Earth's rate are
    /// not estimated: the planar model has no bias state).
    Gyro,
}

impl Inputs {
    /// These inputs for a wheeled robot: WHEEL_DISTANCE of wheels 0 (left) and 1 (right),
    /// `track_m` apart, the clock and rate requests kept.
    pub fn planar_wheels(&self, track_m: f64) -> Inputs {
        Inputs { odometer: OdometerMessage::WheelDistance, wheels: vec![0, 1], wheel_track_m: Some(track_m), ..self.clone() }
    }
}

fn default_imu() -> ImuMessage {
    ImuMessage::HighresImu
}
fn default_odometer() -> OdometerMessage {
    OdometerMessage::Odometry
}
fn default_wheels() -> Vec<u8> {
    vec![0]
}
fn default_clock() -> TeamClock {
    TeamClock::Vehicle
}
fn yes() -> bool {
    true
}

fn one() -> u8 {
    1
}

impl Default for Inputs {
    fn default() -> Self {
        Inputs {
            imu: default_imu(),
            imu_id: 0,
            imu_samples: None,
            odometer: default_odometer(),
            wheels: default_wheels(),
            wheel_track_m: None,
            clock: default_clock(),
            epoch_grid_ms: 0,
            request_rates: true,
            yaw_rate: YawRateSource::Wheels,
            gnss_lag_ms: 0,
        }
    }
}

impl Inputs {
    /// How the IMU messages' values are read.
    pub fn samples(&self) -> SampleKind {
        self.imu_samples.unwrap_or(self.imu.default_samples())
    }
}

/// What the node sends back to the autopilot.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Output {
    /// ODOMETRY (child frame BODY_FRD, pose frame `odometry_frame`), vehicle time, Hz; 0: none.
    #[serde(default = "default_odometry_rate")]
    pub odometry_rate_hz: f64,
    /// The ODOMETRY pose frame: `local_frd` for ArduPilot (it refuses any other), `local_ned`
    /// for PX4 (EKF2 fuses a LOCAL_FRD pose as one of unknown heading: no yaw alignment, no
    /// global position, no arming; measured on its SIH). Both mean the node's NED axes.
    #[serde(default)]
    pub odometry_frame: OdometryFrame,
    /// LOCAL_POSITION_NED after every cooperative update (ground stations show it).
    #[serde(default = "yes")]
    pub local_position_ned: bool,
    /// GPS_INPUT (ArduPilot's GPS type 14) with the estimate as an absolute position about
    /// `[origin]`, vehicle time, Hz; 0: none.
    #[serde(default)]
    pub gps_input_rate_hz: f64,
    /// Give an autopilot that reports no origin (no GNSS since power-on) the `[origin]`, by
    /// SET_GPS_GLOBAL_ORIGIN ([`super::autopilot::OriginOffer`]), so that it reports a global
    /// position and takes waypoints; an origin it has is never overwritten.
    #[serde(default = "yes")]
    pub set_origin: bool,
    /// When the node takes over at a GNSS loss (`cooploc node --init-from-autopilot`), switch
    /// the autopilot's EKF to this source set (ArduPilot's MAV_CMD_SET_EKF_SOURCE_SET: the set
    /// whose EK3_SRCn_* say ExternalNav, e.g. 2), and back to `gnss_source_set` when it hands
    /// back; none: the autopilot switches by itself.
    #[serde(default)]
    pub takeover_source_set: Option<u8>,
    /// The source set on GNSS that the node hands back to (1-3; default 1).
    #[serde(default = "one")]
    pub gnss_source_set: u8,
    /// With the hand-over: ODOMETRY also while the autopilot still navigates on GNSS (needs
    /// `takeover_source_set`). ArduPilot's EKF3 fuses only the sources of its selected set, so it
    /// ignores them until the take-over switches to the ExternalNav set, and its "VisOdom: not
    /// healthy" arming check passes meanwhile (without them it refuses to arm, as measured on its
    /// SITL). Not for an autopilot whose EKF fuses whatever comes (PX4's EKF2 would fuse the
    /// node's GNSS-aided estimate beside the same GNSS).
    #[serde(default)]
    pub odometry_with_gnss: bool,
}

/// The pose frame of the ODOMETRY a node sends (see [`Output::odometry_frame`]).
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Deserialize, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum OdometryFrame {
    #[default]
    LocalFrd,
    LocalNed,
}

fn default_odometry_rate() -> f64 {
    20.0
}

impl Default for Output {
    fn default() -> Self {
        Output {
            odometry_rate_hz: default_odometry_rate(),
            odometry_frame: OdometryFrame::LocalFrd,
            local_position_ned: true,
            gps_input_rate_hz: 0.0,
            set_origin: true,
            takeover_source_set: None,
            gnss_source_set: 1,
            odometry_with_gnss: false,
        }
    }
}

/// Bounds no real sensor of a land vehicle exceeds: a figure beyond them is a unit mistake.
const MAX_ACCEL_BIAS_UG: f64 = 200_000.0;
const MAX_ACCEL_NOISE_UG_PER_SQRT_HZ: f64 = 20_000.0;
const MAX_GYRO_BIAS_DEG_H: f64 = 36_000.0;
const MAX_GYRO_ARW_DEG_PER_SQRT_H: f64 = 60.0;
const MAX_IMU_RATE_HZ: f64 = 2_000.0;

impl VehicleProfile {
    /// Reads, parses and validates a profile file.
    pub fn from_path(path: impl AsRef<Path>) -> Result<Self, ProfileError> {
        let path = path.as_ref();
        let text = std::fs::read_to_string(path)
            .map_err(|e| ProfileError::Io { path: path.display().to_string(), message: e.to_string() })?;
        Self::parse(&text, &path.display().to_string())
    }

    /// Parses and validates a profile held in a string.
    pub fn from_toml_str(text: &str) -> Result<Self, ProfileError> {
        Self::parse(text, "<string>")
    }

    fn parse(text: &str, path: &str) -> Result<Self, ProfileError> {
        let p: VehicleProfile =
            toml::from_str(text).map_err(|e| ProfileError::Parse { path: path.to_string(), message: e.to_string() })?;
        p.validate()?;
        Ok(p)
    }

    /// A vehicle's profile from its description (a simulated vehicle's: `sitl::Scenario::vehicle_of`),
    /// as the simulator's vehicles speak: HIGHRES_IMU averages, ODOMETRY, one clock, rates
    /// already streamed; a planar robot reads WHEEL_DISTANCE's wheels 0 and 1.
    pub fn from_spec(v: &VehicleSpec) -> Self {
        let mut inputs = Inputs { request_rates: false, ..Inputs::default() };
        if let (PlatformModel::Planar, Some(w)) = (v.model, v.wheels) {
            inputs = inputs.planar_wheels(w.track_m);
        }
        VehicleProfile {
            name: v.name.clone(),
            latitude_deg: v.latitude_deg,
            gravity_m_s2: v.gravity_m_s2,
            model: v.model,
            sensors: v.sensors,
            initial: v.initial,
            filter: v.filter,
            wheels: v.wheels,
            origin: None,
            inputs,
            output: Output::default(),
        }
    }

    /// The vehicle this profile describes (`sitl::Scenario::put_vehicle` puts it into a
    /// scenario: `cooploc sitl --vehicle-config`).
    pub fn spec(&self) -> VehicleSpec {
        VehicleSpec {
            name: self.name.clone(),
            latitude_deg: self.latitude(),
            gravity_m_s2: self.gravity_m_s2,
            model: self.model,
            sensors: self.sensors,
            initial: self.initial,
            filter: self.filter,
            wheels: self.wheels,
        }
    }

    /// The profile as TOML (attached to logs so that replay reads the same profile).
    pub fn to_toml(&self) -> String {
        toml::to_string(self).unwrap_or_default()
    }

    /// Checks every value; the first problem found is returned, naming its field. A profile
    /// describes a real vehicle, so it is stricter than a scenario: sensor noise must be
    /// positive and plausible.
    pub fn validate(&self) -> Result<(), ProfileError> {
        if self.name.trim().is_empty() {
            return Err(invalid("name", "must not be empty"));
        }
        positive("gravity_m_s2", self.gravity_m_s2)?;
        if !(9.7..=9.9).contains(&self.gravity_m_s2) {
            return Err(invalid("gravity_m_s2", format!("{} m/s^2 is not the Earth's gravity (9.78-9.84)", self.gravity_m_s2)));
        }
        for (field, v) in [
            ("initial.position_sigma_m", self.initial.position_sigma_m),
            ("initial.velocity_sigma_m_s", self.initial.velocity_sigma_m_s),
            ("initial.roll_pitch_sigma_deg", self.initial.roll_pitch_sigma_deg),
            ("initial.yaw_sigma_deg", self.initial.yaw_sigma_deg),
        ] {
            non_negative(field, v)?;
        }
        match self.model {
            PlatformModel::Ins => self.validate_ins()?,
            PlatformModel::Planar => self.validate_planar()?,
        }
        self.validate_rest()
    }

    /// A wheeled robot: `[wheels]` with plausible figures, WHEEL_DISTANCE of two wheels, no IMU.
    fn validate_planar(&self) -> Result<(), ProfileError> {
        if self.sensors.is_some() {
            return Err(invalid("sensors", "a planar robot has no IMU in its navigation: give [wheels], not [sensors]"));
        }
        if self.filter.is_some() {
            return Err(invalid("filter", "a planar robot has no INS to tune: remove [filter]"));
        }
        let Some(w) = &self.wheels else {
            return Err(invalid(
                "wheels",
                "a planar robot needs [wheels] (rate_hz, speed_sigma_m_s, yaw_rate_sigma_deg_s, track_m)",
            ));
        };
        positive("wheels.rate_hz", w.rate_hz)?;
        if w.rate_hz < 1.0 {
            return Err(invalid(
                "wheels.rate_hz",
                format!("at least 1 Hz (a wheel sample drives at most 1.1 s), got {}", w.rate_hz),
            ));
        }
        if w.rate_hz > MAX_IMU_RATE_HZ {
            return Err(invalid("wheels.rate_hz", format!("must be at most {MAX_IMU_RATE_HZ} Hz, got {}", w.rate_hz)));
        }
        for (field, v, max) in [
            ("wheels.speed_sigma_m_s", w.speed_sigma_m_s, 5.0),
            ("wheels.yaw_rate_sigma_deg_s", w.yaw_rate_sigma_deg_s, 90.0),
            ("wheels.track_m", w.track_m, 10.0),
        ] {
            positive(field, v)
                .map_err(|_| invalid(field, format!("must be positive (real wheels have noise and width), got {v}")))?;
            if v > max {
                return Err(invalid(
                    field,
                    format!("{v} is beyond any wheeled robot (at most {max}); check the unit in the key name"),
                ));
            }
        }
        let i = &self.inputs;
        let gyro = i.yaw_rate == YawRateSource::Gyro;
        if i.odometer != OdometerMessage::WheelDistance || !(i.wheels.len() == 2 || gyro && i.wheels.len() == 1) {
            return Err(invalid(
                "inputs.odometer",
                "a planar robot is driven by WHEEL_DISTANCE of its left and right wheels (one wheel with yaw_rate = \"gyro\"): odometer = \"wheel_distance\", wheels = [left, right]",
            ));
        }
        if let Some(track) = i.wheel_track_m
            && (track - w.track_m).abs() > 1e-9
        {
            return Err(invalid(
                "inputs.wheel_track_m",
                format!("{track} m differs from wheels.track_m {} m; give one", w.track_m),
            ));
        }
        Ok(())
    }

    /// An INS vehicle: `[sensors]` and `[filter]` with figures a real IMU can have.
    fn validate_ins(&self) -> Result<(), ProfileError> {
        if self.inputs.yaw_rate != YawRateSource::Wheels {
            return Err(invalid("inputs.yaw_rate", "a planar robot's (model = \"planar\"): an INS takes the whole IMU"));
        }
        if self.wheels.is_some() {
            return Err(invalid(
                "wheels",
                "[wheels] is a planar robot's: set model = \"planar\" (and drop [sensors] and [filter])",
            ));
        }
        let Some(s) = &self.sensors else {
            return Err(invalid("sensors", "an INS vehicle needs [sensors] (its IMU and odometer figures)"));
        };
        let Some(filter) = &self.filter else {
            return Err(invalid("filter", "an INS vehicle needs [filter] (its non-holonomic constraints)"));
        };
        positive("sensors.imu_rate_hz", s.imu_rate_hz)?;
        if s.imu_rate_hz > MAX_IMU_RATE_HZ {
            return Err(invalid("sensors.imu_rate_hz", format!("must be at most {MAX_IMU_RATE_HZ} Hz, got {}", s.imu_rate_hz)));
        }
        positive("sensors.odometer_rate_hz", s.odometer_rate_hz)?;
        if s.odometer_rate_hz > MAX_IMU_RATE_HZ {
            return Err(invalid(
                "sensors.odometer_rate_hz",
                format!("must be at most {MAX_IMU_RATE_HZ} Hz, got {}", s.odometer_rate_hz),
            ));
        }
        for (field, v, max) in [
            ("sensors.accel_bias_ug", s.accel_bias_ug, MAX_ACCEL_BIAS_UG),
            ("sensors.accel_noise_ug_per_sqrt_hz", s.accel_noise_ug_per_sqrt_hz, MAX_ACCEL_NOISE_UG_PER_SQRT_HZ),
            ("sensors.gyro_bias_deg_h", s.gyro_bias_deg_h, MAX_GYRO_BIAS_DEG_H),
            ("sensors.gyro_arw_deg_per_sqrt_h", s.gyro_arw_deg_per_sqrt_h, MAX_GYRO_ARW_DEG_PER_SQRT_H),
        ] {
            positive(field, v)
                .map_err(|_| invalid(field, format!("must be positive (a real sensor has noise and bias), got {v}")))?;
            if v > max {
                return Err(invalid(
                    field,
                    format!("{v} is beyond any real IMU (at most {max}); check the unit in the key name"),
                ));
            }
        }
        for (field, v) in [
            ("sensors.accel_bias_walk_ug_per_sqrt_s", s.accel_bias_walk_ug_per_sqrt_s),
            ("sensors.gyro_bias_walk_deg_h_per_sqrt_s", s.gyro_bias_walk_deg_h_per_sqrt_s),
            ("sensors.odometer_scale_sigma", s.odometer_scale_sigma),
            ("filter.nhc_lateral_sigma_m_s", filter.nhc_lateral_sigma_m_s),
            ("filter.nhc_vertical_sigma_m_s", filter.nhc_vertical_sigma_m_s),
        ] {
            non_negative(field, v)?;
        }
        if self.inputs.odometer != OdometerMessage::None {
            positive("sensors.odometer_sigma_m_s", s.odometer_sigma_m_s)?;
        } else {
            non_negative("sensors.odometer_sigma_m_s", s.odometer_sigma_m_s)?;
        }
        if s.odometer_scale_sigma > 0.5 {
            return Err(invalid(
                "sensors.odometer_scale_sigma",
                format!("{} is a fraction (0.01 = 1%), at most 0.5", s.odometer_scale_sigma),
            ));
        }
        if let Some(rate) = filter.covariance_rate_hz {
            positive("filter.covariance_rate_hz", rate)?;
            if rate > s.imu_rate_hz {
                return Err(invalid(
                    "filter.covariance_rate_hz",
                    format!("{rate} Hz is above the IMU rate {} Hz", s.imu_rate_hz),
                ));
            }
        }
        Ok(())
    }

    /// What every profile has: latitude, origin, inputs, output.
    fn validate_rest(&self) -> Result<(), ProfileError> {
        if let Some(lat) = self.latitude_deg {
            finite("latitude_deg", lat)?;
            if lat.abs() > 90.0 {
                return Err(invalid("latitude_deg", format!("must be within [-90, 90], got {lat}")));
            }
        }
        if let Some(o) = &self.origin {
            finite("origin.lat_deg", o.lat_deg)?;
            finite("origin.lon_deg", o.lon_deg)?;
            finite("origin.alt_m", o.alt_m)?;
            if o.lat_deg.abs() > 90.0 {
                return Err(invalid("origin.lat_deg", format!("must be within [-90, 90], got {}", o.lat_deg)));
            }
            if o.lon_deg.abs() > 180.0 {
                return Err(invalid("origin.lon_deg", format!("must be within [-180, 180], got {}", o.lon_deg)));
            }
            if let Some(lat) = self.latitude_deg
                && (lat - o.lat_deg).abs() > 1e-6
            {
                return Err(invalid(
                    "latitude_deg",
                    format!("{lat} differs from origin.lat_deg {}; give one of them", o.lat_deg),
                ));
            }
        }
        let i = &self.inputs;
        if i.imu_id != 0 && !matches!(i.imu, ImuMessage::HighresImu | ImuMessage::RawImu) {
            return Err(invalid(
                "inputs.imu_id",
                format!("{} carries no IMU id; use scaled_imu2/3 for the others", i.imu.name()),
            ));
        }
        if i.odometer == OdometerMessage::WheelDistance {
            if i.wheels.is_empty() || i.wheels.len() > 2 {
                return Err(invalid("inputs.wheels", format!("one wheel or a left and a right wheel, got {:?}", i.wheels)));
            }
            if i.wheels.iter().any(|&w| w >= 16) {
                return Err(invalid("inputs.wheels", format!("WHEEL_DISTANCE has wheels 0..=15, got {:?}", i.wheels)));
            }
            if i.wheels.len() == 2 && i.wheels[0] == i.wheels[1] {
                return Err(invalid("inputs.wheels", "the left and the right wheel must differ"));
            }
        }
        if i.epoch_grid_ms > 10_000 {
            return Err(invalid("inputs.epoch_grid_ms", format!("0 (none) up to 10000 ms, got {}", i.epoch_grid_ms)));
        }
        if i.gnss_lag_ms > 1_000 {
            return Err(invalid("inputs.gnss_lag_ms", format!("0 up to 1000 ms, got {}", i.gnss_lag_ms)));
        }
        if i.epoch_grid_ms > 0 && i.clock == TeamClock::Vehicle {
            return Err(invalid(
                "inputs.epoch_grid_ms",
                "only with a mapped team clock (unix, companion, auto): vehicle time stamps are shared as they are",
            ));
        }
        if let Some(track) = i.wheel_track_m {
            positive("inputs.wheel_track_m", track)?;
            if i.wheels.len() != 2 {
                return Err(invalid("inputs.wheel_track_m", "needs two wheels in inputs.wheels"));
            }
        }
        let o = &self.output;
        non_negative("output.odometry_rate_hz", o.odometry_rate_hz)?;
        if o.odometry_rate_hz > 0.0 && !(4.0..=200.0).contains(&o.odometry_rate_hz) {
            return Err(invalid(
                "output.odometry_rate_hz",
                format!("0 (off) or 4-200 Hz (ArduPilot ignores ODOMETRY below 4 Hz), got {}", o.odometry_rate_hz),
            ));
        }
        non_negative("output.gps_input_rate_hz", o.gps_input_rate_hz)?;
        if o.gps_input_rate_hz > 50.0 {
            return Err(invalid("output.gps_input_rate_hz", format!("0 (off) or up to 50 Hz, got {}", o.gps_input_rate_hz)));
        }
        if o.gps_input_rate_hz > 0.0 && self.origin.is_none() {
            return Err(invalid(
                "output.gps_input_rate_hz",
                "GPS_INPUT needs [origin] (positions go out as latitude and longitude)",
            ));
        }
        for (field, set) in
            [("output.takeover_source_set", o.takeover_source_set), ("output.gnss_source_set", Some(o.gnss_source_set))]
        {
            if set.is_some_and(|s| !(1..=3).contains(&s)) {
                return Err(invalid(field, format!("an EKF source set, 1-3, got {}", set.unwrap_or(0))));
            }
        }
        if o.takeover_source_set == Some(o.gnss_source_set) {
            return Err(invalid("output.gnss_source_set", "the set handed back to must not be the take-over's"));
        }
        if o.odometry_with_gnss && (o.takeover_source_set.is_none() || o.odometry_rate_hz == 0.0) {
            return Err(invalid(
                "output.odometry_with_gnss",
                "needs takeover_source_set and odometry_rate_hz: ODOMETRY beside GNSS is safe only for an EKF whose \
                 selected source set leaves it out until the take-over",
            ));
        }
        Ok(())
    }

    /// The latitude the INS uses: `latitude_deg` or the origin's; None: the vehicle's.
    pub fn latitude(&self) -> Option<f64> {
        self.latitude_deg.or(self.origin.map(|o| o.lat_deg))
    }

    /// The configured origin, if any.
    pub fn geo_origin(&self) -> Option<GeoOrigin> {
        self.origin.map(|o| GeoOrigin { lat_deg: o.lat_deg, lon_deg: o.lon_deg, alt_m: o.alt_m })
    }

    /// How many IMU samples one covariance step spans at the configured rates.
    pub fn covariance_decimation(&self) -> u32 {
        match (self.filter.and_then(|f| f.covariance_rate_hz), &self.sensors) {
            (Some(rate), Some(s)) => ((s.imu_rate_hz / rate).round() as u32).max(1),
            _ => 1,
        }
    }

    /// The navigation model the node runs, at latitude `latitude_deg` (the INS's Earth rate).
    pub fn nav_model(&self, latitude_deg: f64) -> NavModel {
        match (self.model, self.wheels) {
            (PlatformModel::Planar, Some(w)) => NavModel::Planar {
                config: PlanarConfig {
                    max_gap_s: DEFAULT_MAX_GAP_S,
                    ..PlanarConfig::from_sample_sigmas(w.speed_sigma_m_s, w.yaw_rate_sigma_deg_s.to_radians(), w.rate_hz)
                },
                initial_sigma: PlanarSigma {
                    pos_m: self.initial.position_sigma_m,
                    yaw_rad: self.initial.yaw_sigma_deg.to_radians(),
                },
            },
            _ => {
                let (config, initial_sigma) = self.ins_settings(latitude_deg);
                NavModel::Ins { config, initial_sigma }
            }
        }
    }

    /// The decoder of this vehicle's messages: a planar robot's wheels drive its filter.
    pub fn decoder(&self) -> VehicleInputs {
        match (self.model, self.wheels) {
            (PlatformModel::Planar, Some(w)) => {
                let track = self.inputs.wheel_track_m.unwrap_or(w.track_m);
                VehicleInputs::new(Inputs { wheel_track_m: Some(track), ..self.inputs.clone() }).wheel_drive()
            }
            _ => VehicleInputs::new(self.inputs.clone()),
        }
    }

    /// The INS noise model and initial uncertainty, at latitude `latitude_deg` (a validated INS
    /// profile has `[sensors]` and `[filter]`; without them, zero figures).
    pub fn ins_settings(&self, latitude_deg: f64) -> (InsConfig, InsInitialSigma) {
        let s = &self.sensors.unwrap_or_default();
        let filter = self.filter.unwrap_or_default();
        let config = InsConfig {
            latitude_deg,
            gravity_m_s2: self.gravity_m_s2,
            accel_noise_density_m_s2_per_sqrt_hz: s.accel_noise_ug_per_sqrt_hz * MICRO_G_M_S2,
            gyro_noise_density_rad_s_per_sqrt_hz: s.gyro_arw_deg_per_sqrt_h * DEG_PER_SQRT_H_RAD_PER_SQRT_S,
            accel_bias_random_walk_m_s3_per_sqrt_hz: s.accel_bias_walk_ug_per_sqrt_s * MICRO_G_M_S2,
            gyro_bias_random_walk_rad_s2_per_sqrt_hz: s.gyro_bias_walk_deg_h_per_sqrt_s * DEG_PER_H_RAD_S,
            sigma_odometer_m_s: s.odometer_sigma_m_s,
            sigma_nhc_lateral_m_s: filter.nhc_lateral_sigma_m_s,
            sigma_nhc_vertical_m_s: filter.nhc_vertical_sigma_m_s,
            max_imu_gap_s: 0.5,
            covariance_decimation: self.covariance_decimation(),
        };
        let i = &self.initial;
        let rp = i.roll_pitch_sigma_deg.to_radians();
        let sigma = InsInitialSigma {
            pos_ned_m: Vector3::repeat(i.position_sigma_m),
            vel_ned_m_s: Vector3::repeat(i.velocity_sigma_m_s),
            att_ned_rad: Vector3::new(rp, rp, i.yaw_sigma_deg.to_radians()),
            accel_bias_frd_m_s2: Vector3::repeat(s.accel_bias_ug * MICRO_G_M_S2),
            gyro_bias_frd_rad_s: Vector3::repeat(s.gyro_bias_deg_h * DEG_PER_H_RAD_S),
            odometer_scale: s.odometer_scale_sigma,
        };
        (config, sigma)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use cooploc_sitl::sitl::{PAPER_TOML, Scenario, World};

    fn example(name: &str) -> String {
        std::fs::read_to_string(format!("{}/../../sitl/vehicles/{name}.toml", env!("CARGO_MANIFEST_DIR"))).unwrap()
    }

    #[test]
    fn the_examples_are_valid() {
        for name in ["px4-rover", "ardupilot-rover", "wheeled-robot"] {
            let p = VehicleProfile::from_toml_str(&example(name)).unwrap_or_else(|e| panic!("{name}: {e}"));
            assert_eq!(p.name, name);
        }
    }

    #[test]
    fn a_scenario_is_a_profile_with_the_same_ins_settings() {
        let scenario = Scenario::from_toml_str(PAPER_TOML).unwrap();
        let world = World::new(&scenario).unwrap();
        let p = VehicleProfile::from_spec(&scenario.vehicle());
        p.validate().unwrap();
        // the same figures the simulator draws its sensor errors from
        let m = world.sensor_model();
        let (c, s) = p.ins_settings(scenario.latitude_deg);
        assert_eq!(c.accel_noise_density_m_s2_per_sqrt_hz, m.accel_noise_density_m_s2_per_sqrt_hz);
        assert_eq!(c.gyro_noise_density_rad_s_per_sqrt_hz, m.gyro_arw_rad_per_sqrt_s);
        assert_eq!(c.accel_bias_random_walk_m_s3_per_sqrt_hz, m.accel_bias_walk_m_s2_per_sqrt_s);
        assert_eq!(c.gyro_bias_random_walk_rad_s2_per_sqrt_hz, m.gyro_bias_walk_rad_s_per_sqrt_s);
        assert_eq!(c.sigma_odometer_m_s, m.odometer_sigma_m_s);
        assert_eq!(c.covariance_decimation, scenario.covariance_decimation());
        assert_eq!(s.accel_bias_frd_m_s2[0], m.accel_bias_sigma_m_s2);
        assert_eq!(s.gyro_bias_frd_rad_s[2], m.gyro_bias_sigma_rad_s);
        assert_eq!(s.odometer_scale, m.odometer_scale_sigma);
        // and it survives the trip through TOML (logs carry it)
        assert_eq!(VehicleProfile::from_toml_str(&p.to_toml()).unwrap(), p);
    }

    fn with(edit: &str, replace: &str) -> Result<VehicleProfile, ProfileError> {
        let text = example("px4-rover");
        assert!(text.contains(edit), "{edit}");
        VehicleProfile::from_toml_str(&text.replacen(edit, replace, 1))
    }

    fn field_of(r: Result<VehicleProfile, ProfileError>) -> String {
        match r {
            Err(ProfileError::Invalid { field, .. }) => field,
            other => panic!("expected an invalid field, got {other:?}"),
        }
    }

    #[test]
    fn bad_profiles_name_their_field() {
        let unknown = with("[inputs]", "[inputs]\nimu_rate = 3").unwrap_err();
        assert!(matches!(&unknown, ProfileError::Parse { message, .. } if message.contains("imu_rate")), "{unknown}");
        let gyro = "gyro_arw_deg_per_sqrt_h = ";
        assert_eq!(field_of(with(gyro, "gyro_arw_deg_per_sqrt_h = 0.0 #")), "sensors.gyro_arw_deg_per_sqrt_h");
        assert_eq!(field_of(with(gyro, "gyro_arw_deg_per_sqrt_h = 5000.0 #")), "sensors.gyro_arw_deg_per_sqrt_h");
        assert_eq!(
            field_of(with("accel_noise_ug_per_sqrt_hz = ", "accel_noise_ug_per_sqrt_hz = -1 #")),
            "sensors.accel_noise_ug_per_sqrt_hz"
        );
        assert_eq!(field_of(with("imu_rate_hz = ", "imu_rate_hz = 0 #")), "sensors.imu_rate_hz");
        assert_eq!(field_of(with("odometry_rate_hz = ", "odometry_rate_hz = 2 #")), "output.odometry_rate_hz");
        assert_eq!(field_of(with("lat_deg = ", "lat_deg = 95 #")), "origin.lat_deg");
        assert_eq!(field_of(with("gravity_m_s2 = ", "gravity_m_s2 = 1.0 #")), "gravity_m_s2");
        let bad_msg = with("imu = \"highres_imu\"", "imu = \"highres\"").unwrap_err();
        assert!(bad_msg.to_string().contains("highres"), "{bad_msg}");
        // ODOMETRY beside GNSS only for an EKF whose source set leaves it out
        let output = "[output]\n";
        assert_eq!(field_of(with(output, "[output]\nodometry_with_gnss = true\n")), "output.odometry_with_gnss");
        with(output, "[output]\nodometry_with_gnss = true\ntakeover_source_set = 2\n").unwrap();
        // source sets are 1-3, and the hand-back's is not the take-over's
        assert_eq!(field_of(with(output, "[output]\ntakeover_source_set = 4\n")), "output.takeover_source_set");
        assert_eq!(field_of(with(output, "[output]\ngnss_source_set = 0\n")), "output.gnss_source_set");
        assert_eq!(field_of(with(output, "[output]\ntakeover_source_set = 1\n")), "output.gnss_source_set");
        let p = with(output, "[output]\ntakeover_source_set = 1\ngnss_source_set = 3\n").unwrap();
        assert_eq!((p.output.takeover_source_set, p.output.gnss_source_set), (Some(1), 3));
    }

    #[test]
    fn a_planar_profile_has_wheels_and_no_imu() {
        let text = example("wheeled-robot");
        let edit = |a: &str, b: &str| {
            assert!(text.contains(a), "{a}");
            VehicleProfile::from_toml_str(&text.replacen(a, b, 1))
        };
        let p = edit("", "").unwrap();
        let NavModel::Planar { config, initial_sigma } = p.nav_model(0.0) else { panic!("a planar model") };
        // 1 deg/s per 20 Hz sample: a density of 1 deg/s / sqrt(20 Hz)
        assert!((config.yaw_rate_noise_rad_s_per_sqrt_hz - 1f64.to_radians() / 20f64.sqrt()).abs() < 1e-15);
        assert!((initial_sigma.yaw_rad - 2f64.to_radians()).abs() < 1e-15);
        assert_eq!(RateRequestsView::of(&p), vec![("WHEEL_DISTANCE", 20.0)]);
        let wheels = &text[text.find("\n[wheels]").unwrap()..text.find("\n[initial]").unwrap()];
        assert_eq!(field_of(edit(wheels, "")), "wheels", "no [wheels]");
        assert!(matches!(edit("\n[wheels]", "\n[unused]"), Err(ProfileError::Parse { .. })), "an unknown section");
        assert_eq!(field_of(edit("speed_sigma_m_s = 0.05", "speed_sigma_m_s = 0.0")), "wheels.speed_sigma_m_s");
        assert_eq!(field_of(edit("yaw_rate_sigma_deg_s = 1.0", "yaw_rate_sigma_deg_s = 500.0")), "wheels.yaw_rate_sigma_deg_s");
        assert_eq!(field_of(edit("track_m = 0.5", "track_m = -0.5")), "wheels.track_m");
        assert_eq!(field_of(edit("odometer = \"wheel_distance\"", "odometer = \"odometry\"")), "inputs.odometer");
        assert_eq!(field_of(edit("wheels = [0, 1]", "wheels = [0]")), "inputs.odometer");
        assert_eq!(field_of(edit("wheels = [0, 1]", "wheels = [0, 1]\nwheel_track_m = 0.4")), "inputs.wheel_track_m");
        let sensors = example("px4-rover");
        let block = &sensors[sensors.find("[sensors]").unwrap()..sensors.find("[initial]").unwrap()];
        assert_eq!(
            field_of(VehicleProfile::from_toml_str(&format!("{text}\n{block}"))),
            "sensors",
            "[sensors] on a planar robot"
        );
        // and an INS vehicle with [wheels] is told to say model = "planar"
        let ins = example("px4-rover");
        assert_eq!(field_of(VehicleProfile::from_toml_str(&format!("{ins}\n{wheels}"))), "wheels");
        assert_eq!(field_of(with("[inputs]", "[inputs]\nyaw_rate = \"gyro\"")), "inputs.yaw_rate", "an INS with a yaw-rate gyro");
        // a robot with a yaw-rate gyro may read one wheel; it asks for the gyro too
        let gyro = edit("wheels = [0, 1]", "wheels = [0]\nyaw_rate = \"gyro\"\nimu = \"scaled_imu2\"").unwrap();
        assert_eq!(RateRequestsView::of(&gyro), vec![("WHEEL_DISTANCE", 20.0), ("SCALED_IMU2", 50.0)]);
        let no_sensors = ins.replacen("[sensors]", "[unused_sensors]", 1);
        assert!(VehicleProfile::from_toml_str(&no_sensors).is_err());
    }

    /// The rate requests a profile makes, as (message, Hz).
    struct RateRequestsView;
    impl RateRequestsView {
        fn of(p: &VehicleProfile) -> Vec<(&'static str, f64)> {
            crate::node::autopilot::RateRequests::new(p, 1).requests.iter().map(|r| (r.message, r.rate_hz)).collect()
        }
    }

    #[test]
    fn wheel_distance_needs_sensible_wheels() {
        let text = example("ardupilot-rover");
        let edit = |a: &str, b: &str| {
            assert!(text.contains(a), "{a}");
            VehicleProfile::from_toml_str(&text.replacen(a, b, 1))
        };
        assert_eq!(field_of(edit("wheels = [0, 1]", "wheels = [0, 0]")), "inputs.wheels");
        assert_eq!(field_of(edit("wheels = [0, 1]", "wheels = [0, 16]")), "inputs.wheels");
        assert_eq!(field_of(edit("wheels = [0, 1]", "wheels = [0, 1, 2]")), "inputs.wheels");
        assert_eq!(field_of(edit("wheel_track_m = ", "wheel_track_m = -0.3 #")), "inputs.wheel_track_m");
    }
}
