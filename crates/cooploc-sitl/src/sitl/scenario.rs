//! Scenario files: every number the simulated world uses, in TOML, with unit-bearing key names.
//!
//! A scenario is parsed with serde (`deny_unknown_fields` everywhere, so a misspelt key is an
//! error that names it) and then validated; a validation error names the offending field by its
//! path in the file, e.g. `sensors.imu_rate_hz` or `platforms[1].segments[0].duration_s`.
//!
//! Times: the world runs on whole microseconds ([`TimeUs`]). Every sensor period, the scenario
//! duration and every ranging epoch must therefore be a whole number of microseconds; the duration
//! and the ranging epochs must in addition fall on the IMU sample grid (multiples of the IMU
//! period), so that a ranging event happens exactly when an IMU sample ends. Segment durations
//! need only be whole microseconds: the truth IMU quadrature splits at segment boundaries.

use std::path::Path;

use serde::{Deserialize, Serialize};

use crate::estimation::PlatformId;
use crate::estimation::spec::{self, InvalidField};
pub use crate::estimation::spec::{FilterTuning, InitialUncertainty, PlatformModel, Sensors, VehicleSpec, Wheels};
use crate::time::TimeUs;

/// What can be wrong with a scenario.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum ScenarioError {
    /// The file could not be read.
    #[error("cannot read scenario {path}: {message}")]
    Io { path: String, message: String },
    /// Not TOML, or not the scenario's shape (the message names an unknown key or a missing field).
    #[error("cannot parse scenario {path}: {message}")]
    Parse { path: String, message: String },
    /// A value outside its allowed range.
    #[error("invalid scenario field `{field}`: {reason}")]
    Invalid { field: String, reason: String },
    /// A ranging schedule name that the scenario does not define.
    #[error("unknown ranging schedule `{name}` (the scenario defines: {available})")]
    UnknownSchedule { name: String, available: String },
    /// A platform id that the scenario does not define.
    #[error("unknown platform id {0}")]
    UnknownPlatform(PlatformId),
}

pub(crate) fn invalid(field: impl Into<String>, reason: impl Into<String>) -> ScenarioError {
    ScenarioError::Invalid { field: field.into(), reason: reason.into() }
}

/// A whole scenario: the world, its sensors, its ranging schedules, its platforms, and the
/// filters' initial uncertainty and tuning.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Scenario {
    /// Short name, for reports.
    pub name: String,
    /// Length of the run, s. Must be a multiple of the IMU period.
    pub duration_s: f64,
    /// Latitude of the local tangent plane, degrees (sets the Earth-rate vector).
    pub latitude_deg: f64,
    /// Magnitude of the constant gravity vector `[0, 0, g]` in NED, m/s^2.
    #[serde(default = "default_gravity")]
    pub gravity_m_s2: f64,
    /// Rate at which [`World::run_inputs`](super::World::run_inputs) records truth for error
    /// evaluation, Hz (truth at any instant is also available directly).
    pub truth_rate_hz: f64,
    pub sensors: Sensors,
    pub ranging: Ranging,
    pub initial: InitialUncertainty,
    pub filter: FilterTuning,
    /// Wheel odometry of the wheeled robots (platforms with `model = "planar"`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub wheels: Option<Wheels>,
    pub platforms: Vec<PlatformSpec>,
}

fn default_gravity() -> f64 {
    9.80665
}

/// Inter-platform ranging: one noise level, any number of named schedules.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Ranging {
    /// White noise on each range, m.
    pub sigma_m: f64,
    /// The radios' reach, m: two platforms range only while they are at most this far apart
    /// (large teams, where each member reaches a few neighbours). Absent: every pair ranges.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub max_range_m: Option<f64>,
    pub schedules: Vec<RangeSchedule>,
}

/// When ranging happens: either periodically (`every_s` from `start_s`, up to the end of the
/// run) or at an explicit list of instants (`at_s`). Exactly one of the two forms.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct RangeSchedule {
    pub name: String,
    /// Period, s.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub every_s: Option<f64>,
    /// First epoch of a periodic schedule, s (default: one period after the start).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub start_s: Option<f64>,
    /// Explicit epochs, s, strictly increasing.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub at_s: Option<Vec<f64>>,
    /// A periodic schedule's radio timing jitter, s: epoch `k` moves by a fixed pseudo-random
    /// offset in `[-jitter_s, jitter_s]` (whole microseconds, the same in every run), so epochs
    /// fall between IMU samples as real ranging rounds do. Less than half the period.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub jitter_s: Option<f64>,
}

/// One vehicle: its id and its truth profile.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct PlatformSpec {
    /// Platform id (its MAVLink system id).
    pub id: PlatformId,
    /// `"ins"` (the default) or `"planar"` (a wheeled robot: needs `[wheels]`).
    #[serde(default, skip_serializing_if = "is_ins")]
    pub model: PlatformModel,
    /// Initial position in the local NED frame, m. D stays constant (level ground).
    pub start_ned_m: [f64; 3],
    /// Initial yaw, deg from north, clockwise seen from above.
    pub start_yaw_deg: f64,
    /// Initial forward speed, m/s.
    pub start_speed_m_s: f64,
    /// Consecutive segments of constant longitudinal acceleration and yaw rate. Together they
    /// must cover the scenario's duration.
    pub segments: Vec<Segment>,
}

/// A stretch of constant longitudinal acceleration and yaw rate.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Segment {
    pub duration_s: f64,
    /// Rate of change of forward speed, m/s^2.
    pub accel_m_s2: f64,
    /// Rate of change of yaw, deg/s (positive turns right, seen from above).
    pub yaw_rate_deg_s: f64,
}

fn is_ins(m: &PlatformModel) -> bool {
    *m == PlatformModel::Ins
}

impl Scenario {
    /// This scenario's vehicles and sensors as a team of `n` driving north side by side,
    /// `spacing_m` apart, at 10 m/s for `duration_s`, radios reaching `reach_m` (a large team
    /// spread out: each vehicle ranges to its neighbours only), ranging at 1 Hz only. The
    /// platforms take the first platform's settings; ids 1 to `n`.
    pub fn side_by_side(&self, n: usize, spacing_m: f64, reach_m: f64, duration_s: f64) -> Scenario {
        let mut s = self.clone();
        s.name = format!("side-by-side-{n}");
        s.duration_s = duration_s;
        s.ranging.max_range_m = Some(reach_m);
        s.ranging.schedules.retain(|r| r.name == "1hz");
        let template = s.platforms[0].clone();
        s.platforms = (0..n)
            .map(|i| PlatformSpec {
                id: i as PlatformId + 1,
                start_ned_m: [0.0, spacing_m * i as f64, 0.0],
                start_yaw_deg: 0.0,
                start_speed_m_s: 10.0,
                segments: vec![Segment { duration_s, accel_m_s2: 0.0, yaw_rate_deg_s: 0.0 }],
                ..template.clone()
            })
            .collect();
        s
    }

    /// The scenario's vehicle, as its INS platforms are: its sensors, initial uncertainty,
    /// filter tuning, latitude and gravity.
    pub fn vehicle(&self) -> VehicleSpec {
        VehicleSpec {
            name: self.name.clone(),
            latitude_deg: Some(self.latitude_deg),
            gravity_m_s2: self.gravity_m_s2,
            model: PlatformModel::Ins,
            sensors: Some(self.sensors),
            initial: self.initial,
            filter: Some(self.filter),
            wheels: None,
        }
    }

    /// Platform `id`'s vehicle: [`Self::vehicle`], or for a wheeled robot (`model = "planar"`)
    /// the scenario's `[wheels]` without IMU or INS tuning.
    pub fn vehicle_of(&self, id: PlatformId) -> VehicleSpec {
        let mut v = self.vehicle();
        let planar = self.platforms.iter().any(|q| q.id == id && q.model == PlatformModel::Planar);
        if let (true, Some(w)) = (planar, self.wheels) {
            v.model = PlatformModel::Planar;
            v.sensors = None;
            v.filter = None;
            v.wheels = Some(w);
        }
        v
    }

    /// Puts a vehicle into the scenario: its sensors, filter tuning and wheels (those it gives),
    /// initial uncertainty, latitude (if known) and gravity replace the scenario's, so that the
    /// simulated vehicles are the ones the nodes are told they run on. The result is validated
    /// as a scenario (sensor periods on the microsecond grid, epochs on the IMU grid).
    pub fn put_vehicle(&mut self, v: &VehicleSpec) -> Result<(), ScenarioError> {
        if let Some(lat) = v.latitude_deg {
            self.latitude_deg = lat;
        }
        self.gravity_m_s2 = v.gravity_m_s2;
        if let Some(sensors) = v.sensors {
            self.sensors = sensors;
        }
        if let Some(filter) = v.filter {
            self.filter = filter;
        }
        if v.wheels.is_some() {
            self.wheels = v.wheels;
        }
        self.initial = v.initial;
        self.validate()
    }

    /// Reads, parses and validates a scenario file.
    pub fn from_path(path: impl AsRef<Path>) -> Result<Scenario, ScenarioError> {
        let path = path.as_ref();
        let text = std::fs::read_to_string(path)
            .map_err(|e| ScenarioError::Io { path: path.display().to_string(), message: e.to_string() })?;
        Self::parse(&text, &path.display().to_string())
    }

    /// Parses and validates a scenario held in a string.
    pub fn from_toml_str(text: &str) -> Result<Scenario, ScenarioError> {
        Self::parse(text, "<string>")
    }

    fn parse(text: &str, path: &str) -> Result<Scenario, ScenarioError> {
        let scenario: Scenario =
            toml::from_str(text).map_err(|e| ScenarioError::Parse { path: path.to_string(), message: e.to_string() })?;
        scenario.validate()?;
        Ok(scenario)
    }

    /// Checks every value; the first problem found is returned, naming its field.
    pub fn validate(&self) -> Result<(), ScenarioError> {
        if self.name.trim().is_empty() {
            return Err(invalid("name", "must not be empty"));
        }
        let s = &self.sensors;
        let imu_period_us = period_us("sensors.imu_rate_hz", s.imu_rate_hz)?;
        positive("sensors.odometer_rate_hz", s.odometer_rate_hz)?;
        if s.odometer_rate_hz > 1e4 {
            return Err(invalid("sensors.odometer_rate_hz", format!("must be at most 10 kHz, got {}", s.odometer_rate_hz)));
        }
        period_us("truth_rate_hz", self.truth_rate_hz)?;
        let duration_us = whole_us("duration_s", self.duration_s)?;
        if duration_us == 0 {
            return Err(invalid("duration_s", format!("must be positive, got {}", self.duration_s)));
        }
        on_grid("duration_s", duration_us, imu_period_us)?;
        if !self.latitude_deg.is_finite() || self.latitude_deg.abs() > 90.0 {
            return Err(invalid("latitude_deg", format!("must be within [-90, 90], got {}", self.latitude_deg)));
        }
        positive("gravity_m_s2", self.gravity_m_s2)?;
        for (field, v) in [
            ("sensors.accel_bias_ug", s.accel_bias_ug),
            ("sensors.accel_noise_ug_per_sqrt_hz", s.accel_noise_ug_per_sqrt_hz),
            ("sensors.accel_bias_walk_ug_per_sqrt_s", s.accel_bias_walk_ug_per_sqrt_s),
            ("sensors.gyro_bias_deg_h", s.gyro_bias_deg_h),
            ("sensors.gyro_arw_deg_per_sqrt_h", s.gyro_arw_deg_per_sqrt_h),
            ("sensors.gyro_bias_walk_deg_h_per_sqrt_s", s.gyro_bias_walk_deg_h_per_sqrt_s),
            ("sensors.odometer_sigma_m_s", s.odometer_sigma_m_s),
            ("sensors.odometer_scale_sigma", s.odometer_scale_sigma),
            ("ranging.sigma_m", self.ranging.sigma_m),
            ("initial.position_sigma_m", self.initial.position_sigma_m),
            ("initial.velocity_sigma_m_s", self.initial.velocity_sigma_m_s),
            ("initial.roll_pitch_sigma_deg", self.initial.roll_pitch_sigma_deg),
            ("initial.yaw_sigma_deg", self.initial.yaw_sigma_deg),
            ("filter.nhc_lateral_sigma_m_s", self.filter.nhc_lateral_sigma_m_s),
            ("filter.nhc_vertical_sigma_m_s", self.filter.nhc_vertical_sigma_m_s),
        ] {
            non_negative(field, v)?;
        }
        if let Some(rate) = self.filter.covariance_rate_hz {
            let period = period_us("filter.covariance_rate_hz", rate)?;
            if period % imu_period_us != 0 {
                return Err(invalid(
                    "filter.covariance_rate_hz",
                    format!("must divide the IMU rate {} Hz evenly, got {rate}", s.imu_rate_hz),
                ));
            }
        }
        if let Some(reach) = self.ranging.max_range_m
            && !(reach.is_finite() && reach > 0.0)
        {
            return Err(invalid("ranging.max_range_m", format!("must be a positive distance in m, got {reach}")));
        }
        for (i, sched) in self.ranging.schedules.iter().enumerate() {
            let field = format!("ranging.schedules[{i}]");
            if sched.name.trim().is_empty() {
                return Err(invalid(format!("{field}.name"), "must not be empty"));
            }
            if self.ranging.schedules[..i].iter().any(|o| o.name == sched.name) {
                return Err(invalid(format!("{field}.name"), format!("duplicate schedule name `{}`", sched.name)));
            }
            sched.epochs_checked(&field, duration_us, imu_period_us)?;
        }
        if let Some(w) = &self.wheels {
            period_us("wheels.rate_hz", w.rate_hz)?;
            if w.rate_hz < 1.0 {
                return Err(invalid(
                    "wheels.rate_hz",
                    format!("at least 1 Hz (a wheel sample drives at most 1.1 s), got {}", w.rate_hz),
                ));
            }
            if w.rate_hz > 1000.0 {
                return Err(invalid("wheels.rate_hz", format!("must be at most 1 kHz, got {}", w.rate_hz)));
            }
            non_negative("wheels.speed_sigma_m_s", w.speed_sigma_m_s)?;
            non_negative("wheels.yaw_rate_sigma_deg_s", w.yaw_rate_sigma_deg_s)?;
            positive("wheels.track_m", w.track_m)?;
        }
        if self.platforms.is_empty() {
            return Err(invalid("platforms", "at least one platform is required"));
        }
        if let Some(i) = self.platforms.iter().position(|p| p.model == PlatformModel::Planar)
            && self.wheels.is_none()
        {
            return Err(invalid(format!("platforms[{i}].model"), "a planar platform needs a [wheels] section"));
        }
        for (i, p) in self.platforms.iter().enumerate() {
            let field = format!("platforms[{i}]");
            if self.platforms[..i].iter().any(|o| o.id == p.id) {
                return Err(invalid(format!("{field}.id"), format!("duplicate platform id {}", p.id)));
            }
            p.validate(&field, duration_us)?;
        }
        Ok(())
    }

    /// How many IMU samples one INS covariance step spans (`filter.covariance_rate_hz`).
    pub fn covariance_decimation(&self) -> u32 {
        match self.filter.covariance_rate_hz {
            Some(rate) => (rate_to_period_us(rate) / self.imu_period_us()).max(1) as u32,
            None => 1,
        }
    }

    /// IMU sample period.
    pub fn imu_period_us(&self) -> u64 {
        rate_to_period_us(self.sensors.imu_rate_hz)
    }

    /// Odometer sample period.
    pub fn odometer_period_us(&self) -> u64 {
        rate_to_period_us(self.sensors.odometer_rate_hz)
    }

    /// Truth recording period.
    pub fn truth_period_us(&self) -> u64 {
        rate_to_period_us(self.truth_rate_hz)
    }

    /// End of the run.
    pub fn end(&self) -> TimeUs {
        TimeUs::from_secs_f64(self.duration_s)
    }

    /// The ranging schedule called `name`.
    pub fn schedule(&self, name: &str) -> Result<&RangeSchedule, ScenarioError> {
        self.ranging.schedules.iter().find(|s| s.name == name).ok_or_else(|| ScenarioError::UnknownSchedule {
            name: name.to_string(),
            available: self.ranging.schedules.iter().map(|s| s.name.as_str()).collect::<Vec<_>>().join(", "),
        })
    }

    /// The epochs of the ranging schedule called `name`, in increasing order.
    pub fn range_epochs(&self, name: &str) -> Result<Vec<TimeUs>, ScenarioError> {
        let i = self.ranging.schedules.iter().position(|s| s.name == name);
        let sched = self.schedule(name)?;
        let field = format!("ranging.schedules[{}]", i.unwrap_or_default());
        sched.epochs_checked(&field, whole_us("duration_s", self.duration_s)?, self.imu_period_us())
    }
}

impl RangeSchedule {
    fn epochs_checked(&self, field: &str, duration_us: u64, imu_period_us: u64) -> Result<Vec<TimeUs>, ScenarioError> {
        let epochs_us: Vec<u64> = match (&self.every_s, &self.at_s) {
            (Some(_), Some(_)) | (None, None) => {
                return Err(invalid(field, "give exactly one of `every_s` (periodic) or `at_s` (explicit epochs)"));
            }
            (None, Some(at)) => {
                if self.jitter_s.is_some() {
                    return Err(invalid(format!("{field}.jitter_s"), "only a periodic schedule (`every_s`) has a jitter"));
                }
                if self.start_s.is_some() {
                    return Err(invalid(format!("{field}.start_s"), "only a periodic schedule (`every_s`) has a start"));
                }
                let mut out = Vec::with_capacity(at.len());
                for (k, &t) in at.iter().enumerate() {
                    let f = format!("{field}.at_s[{k}]");
                    let us = whole_us(&f, t)?;
                    if let Some(&prev) = out.last()
                        && us <= prev
                    {
                        return Err(invalid(
                            f,
                            format!("epochs must be strictly increasing, got {t} after {}", prev as f64 * 1e-6),
                        ));
                    }
                    on_grid(&f, us, imu_period_us)?;
                    within(&f, us, duration_us)?;
                    out.push(us);
                }
                out
            }
            (Some(every), None) => {
                let f_every = format!("{field}.every_s");
                let every_us = whole_us(&f_every, *every)?;
                if every_us == 0 {
                    return Err(invalid(f_every, format!("must be positive, got {every}")));
                }
                let jitter_us = match self.jitter_s {
                    None => 0,
                    Some(j) => {
                        let f = format!("{field}.jitter_s");
                        let us = whole_us(&f, j)?;
                        if us == 0 || 2 * us >= every_us {
                            return Err(invalid(f, format!("must be positive and under half the period, got {j}")));
                        }
                        us
                    }
                };
                if jitter_us == 0 {
                    on_grid(&f_every, every_us, imu_period_us)?;
                }
                let start_us = match self.start_s {
                    Some(s) => {
                        let f = format!("{field}.start_s");
                        let us = whole_us(&f, s)?;
                        if jitter_us == 0 {
                            on_grid(&f, us, imu_period_us)?;
                        }
                        within(&f, us, duration_us)?;
                        if us <= jitter_us {
                            return Err(invalid(f, "must be later than the jitter"));
                        }
                        us
                    }
                    None => every_us,
                };
                (0..)
                    .map(|k| (start_us + k * every_us + jitter_offset_us(k, jitter_us)).saturating_sub(jitter_us))
                    .take_while(|&t| t <= duration_us)
                    .collect()
            }
        };
        Ok(epochs_us.into_iter().map(TimeUs).collect())
    }
}

impl PlatformSpec {
    fn validate(&self, field: &str, duration_us: u64) -> Result<(), ScenarioError> {
        for (k, v) in self.start_ned_m.iter().enumerate() {
            finite(&format!("{field}.start_ned_m[{k}]"), *v)?;
        }
        finite(&format!("{field}.start_yaw_deg"), self.start_yaw_deg)?;
        non_negative(&format!("{field}.start_speed_m_s"), self.start_speed_m_s)?;
        if self.segments.is_empty() {
            return Err(invalid(format!("{field}.segments"), "at least one segment is required"));
        }
        let mut covered_us = 0u64;
        let mut speed = self.start_speed_m_s;
        for (k, seg) in self.segments.iter().enumerate() {
            let f = format!("{field}.segments[{k}]");
            let us = whole_us(&format!("{f}.duration_s"), seg.duration_s)?;
            if us == 0 {
                return Err(invalid(format!("{f}.duration_s"), format!("must be positive, got {}", seg.duration_s)));
            }
            finite(&format!("{f}.accel_m_s2"), seg.accel_m_s2)?;
            finite(&format!("{f}.yaw_rate_deg_s"), seg.yaw_rate_deg_s)?;
            speed += seg.accel_m_s2 * us as f64 * 1e-6;
            // Speed is linear within a segment, so checking the ends is enough.
            if speed < -1e-9 {
                return Err(invalid(
                    format!("{f}.accel_m_s2"),
                    format!("speed would become negative ({speed:.3} m/s at the end of this segment)"),
                ));
            }
            covered_us += us;
        }
        if covered_us < duration_us {
            return Err(invalid(
                format!("{field}.segments"),
                format!("cover {} s, the scenario lasts {} s", covered_us as f64 * 1e-6, duration_us as f64 * 1e-6),
            ));
        }
        Ok(())
    }
}

impl From<InvalidField> for ScenarioError {
    fn from(e: InvalidField) -> Self {
        ScenarioError::Invalid { field: e.field, reason: e.reason }
    }
}

pub(crate) fn finite(field: &str, v: f64) -> Result<(), ScenarioError> {
    Ok(spec::finite(field, v)?)
}

pub(crate) fn positive(field: &str, v: f64) -> Result<(), ScenarioError> {
    Ok(spec::positive(field, v)?)
}

pub(crate) fn non_negative(field: &str, v: f64) -> Result<(), ScenarioError> {
    Ok(spec::non_negative(field, v)?)
}

/// Seconds to whole microseconds, refusing negative values and fractions of a microsecond.
fn whole_us(field: &str, s: f64) -> Result<u64, ScenarioError> {
    non_negative(field, s)?;
    let us = s * 1e6;
    if us > 1e15 {
        return Err(invalid(field, format!("too large, got {s}")));
    }
    if (us - us.round()).abs() > 1e-3 {
        return Err(invalid(field, format!("must be a whole number of microseconds, got {s}")));
    }
    Ok(us.round() as u64)
}

/// A sensor rate to its period in whole microseconds.
fn period_us(field: &str, rate_hz: f64) -> Result<u64, ScenarioError> {
    positive(field, rate_hz)?;
    let us = 1e6 / rate_hz;
    if us < 1.0 - 1e-9 || (us - us.round()).abs() > 1e-6 * us {
        return Err(invalid(field, format!("the period 1/rate must be a whole number of microseconds, got {rate_hz} Hz")));
    }
    Ok(us.round() as u64)
}

fn rate_to_period_us(rate_hz: f64) -> u64 {
    (1e6 / rate_hz).round() as u64
}

/// A fixed pseudo-random offset in `[0, 2 * jitter_us]` for epoch `k` (splitmix64 of `k`).
fn jitter_offset_us(k: u64, jitter_us: u64) -> u64 {
    if jitter_us == 0 {
        return 0;
    }
    let mut z = k.wrapping_add(0x9e37_79b9_7f4a_7c15);
    z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
    z ^= z >> 31;
    z % (2 * jitter_us + 1)
}

fn on_grid(field: &str, us: u64, imu_period_us: u64) -> Result<(), ScenarioError> {
    if us.is_multiple_of(imu_period_us) {
        Ok(())
    } else {
        Err(invalid(
            field,
            format!("must be a multiple of the IMU period ({} s), got {} s", imu_period_us as f64 * 1e-6, us as f64 * 1e-6),
        ))
    }
}

fn within(field: &str, us: u64, duration_us: u64) -> Result<(), ScenarioError> {
    if us <= duration_us {
        Ok(())
    } else {
        Err(invalid(field, format!("must be within the run (0 to {} s), got {} s", duration_us as f64 * 1e-6, us as f64 * 1e-6)))
    }
}

/// The scenario of the paper's experiment (section 4, Table 1), as shipped in
/// `sitl/scenarios/paper.toml`.
pub const PAPER_TOML: &str = include_str!("../../../../sitl/scenarios/paper.toml");

/// The paper scenario with unsynchronised sensors (100 Hz IMU, 15 Hz odometer, ranging jitter),
/// as shipped in `sitl/scenarios/async.toml`.
pub const ASYNC_TOML: &str = include_str!("../../../../sitl/scenarios/async.toml");
/// A mixed team: two INS vehicles and two wheeled robots (sitl/scenarios/mixed.toml).
pub const MIXED_TOML: &str = include_str!("../../../../sitl/scenarios/mixed.toml");

/// A small valid scenario for tests: two platforms, 10 s.
pub const SMALL_TOML: &str = r#"
name = "small"
duration_s = 10.0
latitude_deg = 34.7
gravity_m_s2 = 9.80665
truth_rate_hz = 10.0

[sensors]
imu_rate_hz = 200.0
accel_bias_ug = 500.0
accel_noise_ug_per_sqrt_hz = 100.0
gyro_bias_deg_h = 3.0
gyro_arw_deg_per_sqrt_h = 1.2
odometer_rate_hz = 10.0
odometer_sigma_m_s = 0.2
odometer_scale_sigma = 0.01

[ranging]
sigma_m = 0.1
[[ranging.schedules]]
name = "1hz"
every_s = 1.0
start_s = 1.0
[[ranging.schedules]]
name = "two-events"
at_s = [1.0, 5.0]

[initial]
position_sigma_m = 0.1
velocity_sigma_m_s = 0.05
roll_pitch_sigma_deg = 0.01
yaw_sigma_deg = 0.05

[filter]
nhc_lateral_sigma_m_s = 0.1
nhc_vertical_sigma_m_s = 0.1

[[platforms]]
id = 1
start_ned_m = [0.0, 0.0, 0.0]
start_yaw_deg = 30.0
start_speed_m_s = 10.0
segments = [
  { duration_s = 3.0, accel_m_s2 = 0.5, yaw_rate_deg_s = 0.0 },
  { duration_s = 4.0, accel_m_s2 = -0.3, yaw_rate_deg_s = 6.0 },
  { duration_s = 3.0, accel_m_s2 = 0.0, yaw_rate_deg_s = -4.0 },
]

[[platforms]]
id = 2
start_ned_m = [50.0, -80.0, -1.0]
start_yaw_deg = 170.0
start_speed_m_s = 8.0
segments = [{ duration_s = 10.0, accel_m_s2 = 0.2, yaw_rate_deg_s = -3.0 }]
"#;

#[cfg(test)]
pub(crate) mod tests {
    use super::*;

    pub(crate) use super::SMALL_TOML as SMALL;

    fn err_of(text: &str) -> ScenarioError {
        Scenario::from_toml_str(text).expect_err("scenario should be rejected")
    }

    fn field_of(text: &str) -> String {
        match err_of(text) {
            ScenarioError::Invalid { field, .. } => field,
            other => panic!("expected an Invalid error, got {other}"),
        }
    }

    #[test]
    fn small_and_paper_scenarios_validate() {
        let s = Scenario::from_toml_str(SMALL).unwrap();
        assert_eq!(s.platforms.len(), 2);
        assert_eq!(s.imu_period_us(), 5_000);
        assert_eq!(s.range_epochs("1hz").unwrap().len(), 10);
        assert_eq!(s.range_epochs("two-events").unwrap(), vec![TimeUs(1_000_000), TimeUs(5_000_000)]);

        let paper = Scenario::from_toml_str(PAPER_TOML).unwrap();
        assert_eq!(paper.platforms.len(), 3);
        assert_eq!(paper.duration_s, 380.0);
        assert_eq!(paper.sensors.imu_rate_hz, 200.0);
        assert_eq!(paper.ranging.sigma_m, 0.1);
        let one_hz = paper.range_epochs("1hz").unwrap();
        assert_eq!(one_hz.first(), Some(&TimeUs(1_000_000)));
        assert_eq!(one_hz.len(), 380);
        let four: Vec<f64> = paper.range_epochs("four-events").unwrap().iter().map(|t| t.as_secs_f64()).collect();
        assert_eq!(four, vec![1.0, 100.0, 200.0, 300.0]);
    }

    #[test]
    fn paper_scenario_stays_within_the_brief() {
        // Speeds 8-12 m/s, yaw rates <= 6 deg/s, accelerations <= 1 m/s^2.
        let paper = Scenario::from_toml_str(PAPER_TOML).unwrap();
        for p in &paper.platforms {
            let mut v = p.start_speed_m_s;
            assert!((8.0..=12.0).contains(&v), "platform {} starts at {v} m/s", p.id);
            for seg in &p.segments {
                assert!(seg.yaw_rate_deg_s.abs() <= 6.0 && seg.accel_m_s2.abs() <= 1.0);
                v += seg.accel_m_s2 * seg.duration_s;
                assert!((8.0 - 1e-9..=12.0 + 1e-9).contains(&v), "platform {} reaches {v} m/s", p.id);
            }
            let total: f64 = p.segments.iter().map(|s| s.duration_s).sum();
            assert!((total - paper.duration_s).abs() < 1e-9, "platform {} profile lasts {total} s", p.id);
        }
    }

    #[test]
    fn missing_field_is_named() {
        let text = SMALL.replace("odometer_sigma_m_s = 0.2\n", "");
        let e = err_of(&text);
        assert!(matches!(e, ScenarioError::Parse { .. }), "{e}");
        assert!(e.to_string().contains("odometer_sigma_m_s"), "{e}");
    }

    #[test]
    fn unknown_key_is_named() {
        let text = SMALL.replace("gyro_bias_deg_h = 3.0", "gyro_bias_deg_h = 3.0\ngyro_bais_deg_h = 3.0");
        let e = err_of(&text);
        assert!(matches!(e, ScenarioError::Parse { .. }), "{e}");
        assert!(e.to_string().contains("gyro_bais_deg_h"), "{e}");
        // Nested tables deny unknown keys too.
        let text = SMALL.replace("{ duration_s = 10.0,", "{ duration_s = 10.0, jerk = 1.0,");
        assert!(err_of(&text).to_string().contains("jerk"));
    }

    #[test]
    fn negative_rate_is_named() {
        let e = err_of(&SMALL.replace("imu_rate_hz = 200.0", "imu_rate_hz = -200.0"));
        assert_eq!(field_of(&SMALL.replace("imu_rate_hz = 200.0", "imu_rate_hz = -200.0")), "sensors.imu_rate_hz");
        assert!(e.to_string().contains("sensors.imu_rate_hz") && e.to_string().contains("-200"), "{e}");
        assert_eq!(field_of(&SMALL.replace("odometer_rate_hz = 10.0", "odometer_rate_hz = 0.0")), "sensors.odometer_rate_hz");
        assert_eq!(field_of(&SMALL.replace("imu_rate_hz = 200.0", "imu_rate_hz = 300.0")), "sensors.imu_rate_hz");
    }

    #[test]
    fn off_grid_epoch_is_named() {
        let e = err_of(&SMALL.replace("at_s = [1.0, 5.0]", "at_s = [1.0, 5.0025]"));
        assert!(e.to_string().contains("ranging.schedules[1].at_s[1]"), "{e}");
        assert!(e.to_string().contains("IMU period"), "{e}");
        assert_eq!(field_of(&SMALL.replace("at_s = [1.0, 5.0]", "at_s = [1.0, 11.0]")), "ranging.schedules[1].at_s[1]");
        assert_eq!(field_of(&SMALL.replace("at_s = [1.0, 5.0]", "at_s = [5.0, 1.0]")), "ranging.schedules[1].at_s[1]");
        assert_eq!(field_of(&SMALL.replace("every_s = 1.0", "every_s = 0.0021")), "ranging.schedules[0].every_s");
        assert_eq!(field_of(&SMALL.replace("at_s = [1.0, 5.0]", "at_s = [1.0]\nevery_s = 2.0")), "ranging.schedules[1]");
    }

    #[test]
    fn other_invalid_values_are_named() {
        assert_eq!(field_of(&SMALL.replace("sigma_m = 0.1", "sigma_m = -0.1")), "ranging.sigma_m");
        assert_eq!(field_of(&SMALL.replace("duration_s = 10.0\n", "duration_s = 10.0025\n")), "duration_s");
        assert_eq!(field_of(&SMALL.replace("id = 2", "id = 1")), "platforms[1].id");
        assert_eq!(
            field_of(&SMALL.replace("{ duration_s = 3.0, accel", "{ duration_s = 0.0, accel")),
            "platforms[0].segments[0].duration_s"
        );
        assert_eq!(field_of(&SMALL.replace("accel_m_s2 = -0.3", "accel_m_s2 = -4.0")), "platforms[0].segments[1].accel_m_s2");
        assert_eq!(field_of(&SMALL.replace("{ duration_s = 10.0,", "{ duration_s = 9.0,")), "platforms[1].segments");
        assert_eq!(field_of(&SMALL.replace("latitude_deg = 34.7", "latitude_deg = 134.7")), "latitude_deg");
        let no_segments =
            SMALL.replace("segments = [{ duration_s = 10.0, accel_m_s2 = 0.2, yaw_rate_deg_s = -3.0 }]", "segments = []");
        assert_eq!(field_of(&no_segments), "platforms[1].segments");
    }

    #[test]
    fn covariance_rate_must_divide_the_imu_rate() {
        let with = |rate: &str| {
            SMALL.replace("nhc_vertical_sigma_m_s = 0.1", &format!("nhc_vertical_sigma_m_s = 0.1\ncovariance_rate_hz = {rate}"))
        };
        assert_eq!(Scenario::from_toml_str(&with("50.0")).unwrap().covariance_decimation(), 4);
        assert_eq!(Scenario::from_toml_str(SMALL).unwrap().covariance_decimation(), 1);
        assert_eq!(field_of(&with("30.0")), "filter.covariance_rate_hz");
        assert_eq!(field_of(&with("-50.0")), "filter.covariance_rate_hz");
    }

    #[test]
    fn gravity_defaults_and_unknown_schedule_is_reported() {
        let s = Scenario::from_toml_str(&SMALL.replace("gravity_m_s2 = 9.80665\n", "")).unwrap();
        assert_eq!(s.gravity_m_s2, 9.80665);
        let e = s.range_epochs("2hz").unwrap_err();
        assert!(e.to_string().contains("2hz") && e.to_string().contains("1hz, two-events"), "{e}");
    }

    #[test]
    fn from_path_reports_the_path() {
        let e = Scenario::from_path("/nonexistent/cooploc-scenario.toml").unwrap_err();
        assert!(matches!(e, ScenarioError::Io { .. }) && e.to_string().contains("/nonexistent/cooploc-scenario.toml"), "{e}");
        let path = concat!(env!("CARGO_MANIFEST_DIR"), "/../../sitl/scenarios/paper.toml");
        assert_eq!(Scenario::from_path(path).unwrap(), Scenario::from_toml_str(PAPER_TOML).unwrap());
    }
}
