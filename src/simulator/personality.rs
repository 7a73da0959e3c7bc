//! Autopilot personalities (`cooploc sitl --autopilot ardupilot|px4|cooploc`): what a simulated
//! vehicle sends as each autopilot would, and a checker of what the node sends back against
//! that autopilot's acceptance rules.
//!
//! | | cooploc (default) | ArduPilot Rover | PX4 |
//! |---|---|---|---|
//! | IMU | HIGHRES_IMU, the interval mean, every sample | RAW_IMU (int16 mG, mrad/s): the latest sample, `time_usec` at *send* time ([`ARDUPILOT_SEND_LATENCY_US`] later); 1 Hz until asked, at most 40 Hz (0.8 x Rover's 50 Hz loop) | HIGHRES_IMU averaged over its send interval (float, `fields_updated` 0x1fff); 50 Hz until asked, at most 200 Hz (IMU_INTEG_RATE) |
//! | odometer | ODOMETRY (BODY_FRD `vx`) | WHEEL_DISTANCE: two wheels' cumulative distance; 1 Hz until asked, at most 40 Hz | none from PX4: a wheel-odometry peripheral (compid [`WHEEL_ODOMETRY_COMPID`], its own sequence) sends ODOMETRY (estimator NAIVE) at every sample; PX4's own ODOMETRY is its EKF output (estimator AUTOPILOT, 10 Hz, from the truth) and that is what a rate request for ODOMETRY changes |
//! | time stamps | simulated time | since boot (each vehicle booted at its own time, [`boot_offset_us`]) | since boot |
//! | SYSTEM_TIME | none | 1 Hz: `time_unix_usec` 0 (no GNSS, as the real firmware measured), or with `--gnss-time` Unix time ([`SIM_UNIX_EPOCH_US`] + simulated time: a fix before GNSS was lost) against `time_boot_ms` | 1 Hz, Unix time (PX4 has it without GNSS) |
//! | rates | | SET_MESSAGE_INTERVAL for RAW_IMU and SYSTEM_TIME; DENIED for WHEEL_DISTANCE (ArduPilot has no interval entry for it), which only REQUEST_DATA_STREAM EXTRA1 (or `--stream-rate`, its MAVn_EXTRA1 parameter) paces; REQUEST_DATA_STREAM RAW_SENSORS, EXTRA1, EXTRA3 | SET_MESSAGE_INTERVAL; REQUEST_DATA_STREAM ignored |
//! | TIMESYNC | answered (boot clock in ns) | answered | answered |
//! | HEARTBEAT | autopilot GENERIC | ARDUPILOTMEGA | PX4 |
//!
//! Ranges (COOPLOC_RANGE) are stamped in the vehicle's clock too. What the node sends back is
//! checked by [`Checker`]: ArduPilot fuses ODOMETRY only with `frame_id` LOCAL_FRD and
//! `child_frame_id` BODY_FRD; PX4 takes pose frame LOCAL_NED (its EKF2 fuses a LOCAL_FRD or
//! LOCAL_FLU pose as one of unknown heading: no yaw alignment, no global position, no arming,
//! measured on its SIH; the personality counts it as ignored) with estimator_type UNKNOWN,
//! NAIVE, VISION or VIO, and falls back to its own noise parameters when
//! the pose covariance's diagonal is not finite. Both need a finite position and a unit
//! quaternion. Each ignored message is counted with its reason, and the rate of the accepted ones
//! is measured in the vehicle's clock.

use std::collections::BTreeMap;

use nalgebra::Vector3;

use crate::estimation::{ImuSample, OdometerSample, RangeSample, WheelSample};
use crate::protocol::MavMessage;
use crate::protocol::dialect::cooploc::{
    HighresImuUpdatedFlags, MavAutopilot, MavEstimatorType, MavFrame, MavType, ODOMETRY_DATA as Odometry, SYSTEM_TIME_DATA,
    WHEEL_DISTANCE_DATA,
};
use crate::protocol::wire;
use crate::sitl::TruthState;
use crate::time::TimeUs;

/// Unix time of simulated time zero, us (2026-11-18 11:06:40 UTC): what the personalities'
/// SYSTEM_TIME says.
pub const SIM_UNIX_EPOCH_US: u64 = 1_795_000_000_000_000;
/// ArduPilot stamps RAW_IMU when it sends it, this long after the sample, us.
pub const ARDUPILOT_SEND_LATENCY_US: u64 = 2_000;
/// Component id of PX4 vehicles' wheel-odometry peripheral (MAV_COMP_ID_PERIPHERAL).
pub const WHEEL_ODOMETRY_COMPID: u8 = 158;

/// Which autopilot a simulated vehicle behaves as.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum Autopilot {
    /// The simulator's own conventions (the paper's experiment over MAVLink).
    #[default]
    Cooploc,
    ArduPilot,
    Px4,
}

impl std::str::FromStr for Autopilot {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        match s {
            "cooploc" => Ok(Autopilot::Cooploc),
            "ardupilot" => Ok(Autopilot::ArduPilot),
            "px4" => Ok(Autopilot::Px4),
            _ => Err(format!("{s:?}: expected ardupilot, px4 or cooploc")),
        }
    }
}

impl Autopilot {
    pub fn name(self) -> &'static str {
        match self {
            Autopilot::Cooploc => "cooploc",
            Autopilot::ArduPilot => "ardupilot",
            Autopilot::Px4 => "px4",
        }
    }

    /// HEARTBEAT's autopilot field.
    pub fn mav_autopilot(self) -> MavAutopilot {
        match self {
            Autopilot::Cooploc => MavAutopilot::MAV_AUTOPILOT_GENERIC,
            Autopilot::ArduPilot => MavAutopilot::MAV_AUTOPILOT_ARDUPILOTMEGA,
            Autopilot::Px4 => MavAutopilot::MAV_AUTOPILOT_PX4,
        }
    }

    pub fn heartbeat(self) -> MavMessage {
        wire::heartbeat(MavType::MAV_TYPE_GROUND_ROVER, self.mav_autopilot())
    }

    /// Message id of the IMU stream.
    pub fn imu_message_id(self) -> u32 {
        match self {
            Autopilot::ArduPilot => 27,
            _ => 105,
        }
    }

    /// Message id of the odometer stream (a rate request for it changes it).
    pub fn odometer_message_id(self) -> Option<u32> {
        match self {
            Autopilot::Cooploc => Some(331),
            Autopilot::ArduPilot => Some(9000),
            // PX4's ODOMETRY is its EKF output; the wheel peripheral is not PX4's to pace
            Autopilot::Px4 => None,
        }
    }

    /// Shortest interval the autopilot streams a sensor at, us (requests below are accepted
    /// and capped, as the autopilots do).
    pub fn min_sensor_interval_us(self) -> u64 {
        match self {
            Autopilot::Cooploc => 1,
            Autopilot::ArduPilot => 25_000,
            Autopilot::Px4 => 5_000,
        }
    }

    /// Whether the vehicle stamps in its boot clock and sends SYSTEM_TIME.
    pub fn boot_clock(self) -> bool {
        self != Autopilot::Cooploc
    }
}

/// When vehicle `platform` booted, before simulated time zero, us (whole milliseconds, so that
/// SYSTEM_TIME maps its clock exactly): 20 s plus 7.919 s per platform id.
pub fn boot_offset_us(platform: u16) -> u64 {
    20_000_000 + 7_919_000 * u64::from(platform)
}

/// The state a personality keeps between samples.
#[derive(Debug, Clone)]
pub struct Personality {
    pub autopilot: Autopilot,
    boot_offset_us: u64,
    /// Sum of the IMU interval means since the last HIGHRES_IMU sent, and their count (PX4).
    imu_sum: (Vector3<f64>, Vector3<f64>, u32),
    /// Cumulative wheel distance, m (ArduPilot).
    wheel_m: f64,
    /// A wheeled robot's two wheels' cumulative distances (left, right), m, and the time of
    /// the last wheel sample.
    wheels_m: [f64; 2],
    wheel_t: TimeUs,
    odometer_period_s: f64,
    /// SYSTEM_TIME carries Unix time (see [`super::VehicleConfig::unix_time`]).
    unix_time: bool,
}

impl Personality {
    pub fn new(autopilot: Autopilot, platform: u16, odometer_period_us: u64, unix_time: bool) -> Self {
        Personality {
            unix_time,
            autopilot,
            boot_offset_us: if autopilot.boot_clock() { boot_offset_us(platform) } else { 0 },
            imu_sum: (Vector3::zeros(), Vector3::zeros(), 0),
            wheel_m: 0.0,
            wheels_m: [0.0; 2],
            wheel_t: TimeUs(0),
            odometer_period_s: odometer_period_us as f64 * 1e-6,
        }
    }

    /// Simulated time in the vehicle's clock, us.
    pub fn clock_us(&self, t: TimeUs) -> u64 {
        t.0 + self.boot_offset_us
    }

    /// Takes an IMU sample (every one of the world's).
    pub fn take_imu(&mut self, s: &ImuSample) {
        self.imu_sum.0 += s.specific_force_frd_m_s2;
        self.imu_sum.1 += s.angular_rate_frd_rad_s;
        self.imu_sum.2 += 1;
    }

    /// The IMU message sent now, at sample `s` (the latest).
    pub fn imu_message(&mut self, s: &ImuSample) -> MavMessage {
        let (f, w, n) = std::mem::replace(&mut self.imu_sum, (Vector3::zeros(), Vector3::zeros(), 0));
        match self.autopilot {
            Autopilot::Cooploc => wire::imu_to_highres(s),
            Autopilot::ArduPilot => wire::imu_to_raw_imu(s, self.clock_us(s.t) + ARDUPILOT_SEND_LATENCY_US, 0),
            Autopilot::Px4 => {
                let n = f64::from(n.max(1));
                let mean =
                    ImuSample { t: TimeUs(self.clock_us(s.t)), specific_force_frd_m_s2: f / n, angular_rate_frd_rad_s: w / n };
                let mut m = wire::imu_to_highres(&mean);
                if let MavMessage::HIGHRES_IMU(h) = &mut m {
                    // PX4 marks every field it fills (magnetometer, pressure, temperature too)
                    h.fields_updated = HighresImuUpdatedFlags::from_bits_truncate(0x1fff);
                }
                m
            }
        }
    }

    /// Takes an odometer sample (every one of the world's).
    pub fn take_odometer(&mut self, s: &OdometerSample) {
        self.wheel_m += s.speed_m_s * self.odometer_period_s;
    }

    /// The odometer message of the autopilot's odometer stream, at sample `s`.
    pub fn odometer_message(&self, s: &OdometerSample, sigma_m_s: f64) -> MavMessage {
        match self.autopilot {
            Autopilot::ArduPilot => {
                let mut distance = [0.0; 16];
                distance[0] = self.wheel_m;
                distance[1] = self.wheel_m;
                MavMessage::WHEEL_DISTANCE(WHEEL_DISTANCE_DATA { time_usec: self.clock_us(s.t), distance, count: 2 })
            }
            _ => {
                let mut m = wire::odometer_to_odometry(s, sigma_m_s);
                if let MavMessage::ODOMETRY(o) = &mut m {
                    o.time_usec = self.clock_us(s.t);
                    if self.autopilot == Autopilot::Px4 {
                        o.estimator_type = MavEstimatorType::MAV_ESTIMATOR_TYPE_NAIVE;
                    }
                }
                m
            }
        }
    }

    /// Takes a wheeled robot's wheel sample (every one of the world's): its two wheels turn
    /// the sample's mean speed plus and minus half the track times its yaw rate (turning right,
    /// the left wheel runs faster).
    pub fn take_wheel(&mut self, s: &WheelSample, track_m: f64) {
        let dt = s.t.secs_since(self.wheel_t);
        self.wheel_t = s.t;
        let half = 0.5 * s.yaw_rate_rad_s * track_m;
        self.wheels_m[0] += (s.speed_m_s + half) * dt;
        self.wheels_m[1] += (s.speed_m_s - half) * dt;
    }

    /// WHEEL_DISTANCE of the wheeled robot's two wheels, at its latest sample `s`.
    pub fn wheel_message(&self, s: &WheelSample) -> MavMessage {
        let mut distance = [0.0; 16];
        distance[..2].copy_from_slice(&self.wheels_m);
        MavMessage::WHEEL_DISTANCE(WHEEL_DISTANCE_DATA { time_usec: self.clock_us(s.t), distance, count: 2 })
    }

    /// A range this vehicle's radio measured, stamped in its clock.
    pub fn range_message(&self, r: &RangeSample, epoch: u32) -> MavMessage {
        wire::range_to_message(&RangeSample { t: TimeUs(self.clock_us(r.t)), ..*r }, epoch)
    }

    /// SYSTEM_TIME at simulated time `t`: without Unix time (ArduPilot that never had GNSS)
    /// `time_unix_usec` is 0.
    pub fn system_time(&self, t: TimeUs) -> MavMessage {
        MavMessage::SYSTEM_TIME(SYSTEM_TIME_DATA {
            time_unix_usec: if self.unix_time { SIM_UNIX_EPOCH_US + t.0 } else { 0 },
            time_boot_ms: ((self.clock_us(t) / 1000) % (1 << 32)) as u32,
        })
    }

    /// PX4's own EKF output as ODOMETRY (estimator AUTOPILOT): the truth, which no node may take
    /// for an odometer.
    pub fn autopilot_odometry(&self, truth: &TruthState) -> MavMessage {
        let nav = wire::Navigation {
            t: truth.t,
            position_ned_m: truth.pos_ned_m,
            velocity_ned_m_s: truth.vel_ned_m_s,
            attitude_frd_to_ned: truth.attitude,
            pose_covariance: nalgebra::Matrix6::from_element(f64::NAN),
            velocity_covariance_ned: nalgebra::Matrix3::from_element(f64::NAN),
        };
        let mut m = wire::navigation_to_odometry(&nav, self.clock_us(truth.t), 0, true);
        if let MavMessage::ODOMETRY(o) = &mut m {
            o.estimator_type = MavEstimatorType::MAV_ESTIMATOR_TYPE_AUTOPILOT;
        }
        m
    }
}

/// What the autopilot made of the node's ODOMETRY (see the module documentation).
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Checker {
    pub accepted: u64,
    /// Ignored messages by reason.
    pub ignored: BTreeMap<&'static str, u64>,
    /// Accepted, but the autopilot would use its own noise parameters (PX4: no covariance).
    pub without_covariance: u64,
    /// Accepted messages stamped more than a second ahead of the vehicle's clock when they
    /// arrived: no node can know a later time, so always a wrong clock.
    pub ahead_of_clock: u64,
    /// Accepted messages stamped more than a second behind the vehicle's clock when they
    /// arrived: a wrong clock (then nearly all of them), or a node that lagged its vehicle
    /// (then a few, where it stalled: faster than real time, a second of the vehicle's clock is
    /// a fraction of one of the node's).
    pub behind_clock: u64,
    /// First and last `time_usec` accepted (the vehicle's clock).
    pub first_us: Option<u64>,
    pub last_us: Option<u64>,
    /// GPS_INPUT messages a GPS driver would take (a 3D fix, a position on the Earth, a
    /// horizontal accuracy), and those it would not.
    pub gps_input_accepted: u64,
    pub gps_input_ignored: u64,
}

impl Checker {
    /// Checks one ODOMETRY from the node, received when the vehicle's clock read `now_us`:
    /// whether the autopilot would take it.
    pub fn check(&mut self, autopilot: Autopilot, m: &Odometry, now_us: u64) -> bool {
        if let Some(reason) = Self::refusal(autopilot, m) {
            *self.ignored.entry(reason).or_default() += 1;
            return false;
        }
        if autopilot == Autopilot::Px4 && [0, 6, 11].iter().any(|&k| !m.pose_covariance[k].is_finite()) {
            self.without_covariance += 1;
        }
        if m.time_usec > now_us.saturating_add(1_000_000) {
            self.ahead_of_clock += 1;
        } else if m.time_usec.saturating_add(1_000_000) < now_us {
            self.behind_clock += 1;
        }
        self.accepted += 1;
        self.first_us = Some(self.first_us.map_or(m.time_usec, |f| f.min(m.time_usec)));
        self.last_us = Some(self.last_us.map_or(m.time_usec, |l| l.max(m.time_usec)));
        true
    }

    /// Checks one GPS_INPUT from the node.
    pub fn check_gps_input(&mut self, m: &crate::protocol::dialect::cooploc::GPS_INPUT_DATA) {
        use crate::protocol::dialect::cooploc::GpsFixType;
        let fix = matches!(
            m.fix_type,
            GpsFixType::GPS_FIX_TYPE_3D_FIX
                | GpsFixType::GPS_FIX_TYPE_DGPS
                | GpsFixType::GPS_FIX_TYPE_RTK_FLOAT
                | GpsFixType::GPS_FIX_TYPE_RTK_FIXED
        );
        let on_earth = m.lat.unsigned_abs() <= 900_000_000 && m.lon.unsigned_abs() <= 1_800_000_000 && (m.lat, m.lon) != (0, 0);
        if fix && on_earth && m.horiz_accuracy.is_finite() && m.horiz_accuracy > 0.0 {
            self.gps_input_accepted += 1;
        } else {
            self.gps_input_ignored += 1;
        }
    }

    fn refusal(autopilot: Autopilot, m: &Odometry) -> Option<&'static str> {
        let q = nalgebra::Quaternion::new(m.q[0], m.q[1], m.q[2], m.q[3]);
        let finite = [m.x, m.y, m.z].iter().chain(&m.q).all(|v| v.is_finite());
        match autopilot {
            Autopilot::Cooploc => None,
            Autopilot::ArduPilot => {
                if m.frame_id != MavFrame::MAV_FRAME_LOCAL_FRD || m.child_frame_id != MavFrame::MAV_FRAME_BODY_FRD {
                    Some("frame_id must be LOCAL_FRD and child_frame_id BODY_FRD")
                } else if !finite || (q.norm() - 1.0).abs() > 1e-3 {
                    Some("position or quaternion not usable")
                } else {
                    None
                }
            }
            Autopilot::Px4 => {
                use MavEstimatorType::*;
                use MavFrame::*;
                if matches!(m.frame_id, MAV_FRAME_LOCAL_FRD | MAV_FRAME_LOCAL_FLU) {
                    Some(
                        "pose frame_id LOCAL_FRD or LOCAL_FLU: EKF2 fuses it without a heading reference (no yaw, no global position)",
                    )
                } else if m.frame_id != MAV_FRAME_LOCAL_NED {
                    Some("pose frame_id not LOCAL_NED")
                } else if !matches!(
                    m.estimator_type,
                    MAV_ESTIMATOR_TYPE_UNKNOWN | MAV_ESTIMATOR_TYPE_NAIVE | MAV_ESTIMATOR_TYPE_VISION | MAV_ESTIMATOR_TYPE_VIO
                ) {
                    Some("estimator_type not UNKNOWN, NAIVE, VISION or VIO")
                } else if !finite || (q.norm() - 1.0).abs() > 1e-3 {
                    Some("position or quaternion not usable")
                } else {
                    None
                }
            }
        }
    }

    /// Rate of the accepted messages in the vehicle's clock, Hz.
    pub fn rate_hz(&self) -> Option<f64> {
        match (self.first_us, self.last_us) {
            (Some(f), Some(l)) if l > f && self.accepted > 1 => Some((self.accepted - 1) as f64 / ((l - f) as f64 * 1e-6)),
            _ => None,
        }
    }
}

/// Ranging epochs: each epoch's time and its ranges.
pub type Epochs = Vec<(TimeUs, Vec<RangeSample>)>;

/// What a node decodes from the vehicles of run (`seed`, `run`) on `schedule`: the world's
/// samples sent as `autopilot` sends them with its streams at `rates` from boot (no rate
/// changed during the run), through the node's decoder for profile `inputs`, back in simulated
/// time (stamps mapped to Unix time less [`SIM_UNIX_EPOCH_US`]; offline there is no companion
/// clock, so the autopilots keep Unix time as after a GNSS fix, and `clock = "auto"` takes it). The offline experiment of the same
/// inputs a team of nodes sees over MAVLink, loss-free; truth as in the world's run.
pub fn decoded_run(
    world: &crate::sitl::World,
    seed: u64,
    run: u32,
    schedule: &str,
    autopilot: Autopilot,
    inputs: &crate::node::profile::Inputs,
    rates: &[(u32, f64)],
) -> Result<(crate::sitl::RunInputs, Epochs), String> {
    use crate::node::core::NodeInput;
    use crate::node::inputs::{VehicleEvent, VehicleInputs};
    use crate::node::profile::TeamClock;
    use crate::sitl::SimEvent;
    let mut run_inputs = world.run_inputs(seed, run);
    let ids = world.platform_ids();
    let origin = wire::GeoOrigin { lat_deg: world.scenario().latitude_deg, lon_deg: 0.0, alt_m: 0.0 };
    let mut cores = Vec::new();
    for &id in &ids {
        let mut cfg = super::vehicle_config(world, id, schedule, super::StreamDefaults::default(), origin, autopilot);
        // offline there is no companion clock: the autopilots keep Unix time (a GNSS fix before)
        cfg.unix_time = true;
        let mut core = super::VehicleCore::new(cfg).map_err(|e| e.to_string())?;
        for &(m, hz) in rates {
            core.preset_rate(m, hz)?;
        }
        cores.push(core);
    }
    let trajectories: Vec<_> =
        ids.iter().map(|&id| world.trajectory(id).cloned()).collect::<Result<_, _>>().map_err(|e| e.to_string())?;
    // A wheeled robot's decoder reads its two wheels as its drive, as its profile would say.
    let mut decoders: Vec<VehicleInputs> = ids
        .iter()
        .map(|&id| match (world.platform_model(id), world.scenario().wheels) {
            (crate::sitl::scenario::PlatformModel::Planar, Some(w)) => {
                VehicleInputs::new(inputs.planar_wheels(w.track_m)).wheel_drive()
            }
            _ => VehicleInputs::new(inputs.clone()),
        })
        .collect();
    let shift = if inputs.clock != TeamClock::Vehicle && autopilot.boot_clock() { SIM_UNIX_EPOCH_US } else { 0 };
    let at = |t: TimeUs| TimeUs(t.0.saturating_sub(shift));
    let (mut imu, mut odo): (Vec<Vec<ImuSample>>, Vec<Vec<OdometerSample>>) =
        (vec![Vec::new(); ids.len()], vec![Vec::new(); ids.len()]);
    let mut wheel: Vec<Vec<WheelSample>> = vec![Vec::new(); ids.len()];
    let mut ranges: BTreeMap<u64, Vec<RangeSample>> = BTreeMap::new();
    let mut out = Vec::new();
    let mut take = |i: usize, out: &mut Vec<super::Outgoing>, decoders: &mut Vec<VehicleInputs>| {
        for o in out.drain(..) {
            for event in decoders[i].decode(&o.message) {
                match event {
                    VehicleEvent::Input(NodeInput::Imu(s)) => imu[i].push(ImuSample { t: at(s.t), ..s }),
                    VehicleEvent::Input(NodeInput::Odometer(s)) => odo[i].push(OdometerSample { t: at(s.t), ..s }),
                    VehicleEvent::Input(NodeInput::Wheel(s)) => wheel[i].push(WheelSample { t: at(s.t), ..s }),
                    VehicleEvent::Input(NodeInput::OwnRange { range, .. }) => {
                        ranges.entry(at(range.t).0).or_default().push(RangeSample { t: at(range.t), ..range })
                    }
                    _ => {}
                }
            }
        }
    };
    let mut epoch = 0u32;
    for event in world.events(schedule, seed, run).map_err(|e| e.to_string())? {
        let t = event.time();
        for (i, (core, truth)) in cores.iter_mut().zip(&trajectories).enumerate() {
            core.advance_to(t, truth, &mut out);
            take(i, &mut out, &mut decoders);
        }
        match &event {
            SimEvent::Imu(id, s) => {
                let i = ids.iter().position(|p| p == id).expect("a platform");
                cores[i].on_imu(s, &mut out);
                take(i, &mut out, &mut decoders);
            }
            SimEvent::Odometer(id, s) => {
                let i = ids.iter().position(|p| p == id).expect("a platform");
                cores[i].on_odometer(s, &mut out);
                take(i, &mut out, &mut decoders);
            }
            SimEvent::Wheel(id, s) => {
                let i = ids.iter().position(|p| p == id).expect("a platform");
                cores[i].on_wheel(s, &mut out);
                take(i, &mut out, &mut decoders);
            }
            SimEvent::Ranges(t, rs) => {
                epoch += 1;
                for (i, core) in cores.iter_mut().enumerate() {
                    core.on_ranges(epoch, *t, rs, &mut out);
                    take(i, &mut out, &mut decoders);
                }
            }
        }
    }
    for (k, p) in run_inputs.platforms.iter_mut().enumerate() {
        p.imu = std::mem::take(&mut imu[k]);
        odo[k].sort_by_key(|s| s.t);
        p.odometer = std::mem::take(&mut odo[k]);
        p.wheel = std::mem::take(&mut wheel[k]);
    }
    let ranges = ranges
        .into_iter()
        .map(|(t, mut rs)| {
            rs.sort_by_key(|r| (r.from, r.to));
            (TimeUs(t), rs)
        })
        .collect();
    Ok((run_inputs, ranges))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::protocol::wire::Navigation;
    use nalgebra::{Matrix3, Matrix6, UnitQuaternion};

    fn nav() -> Navigation {
        Navigation {
            t: TimeUs(5_000_000),
            position_ned_m: Vector3::new(1.0, 2.0, 0.0),
            velocity_ned_m_s: Vector3::new(1.0, 0.0, 0.0),
            attitude_frd_to_ned: UnitQuaternion::identity(),
            pose_covariance: Matrix6::identity(),
            velocity_covariance_ned: Matrix3::identity(),
        }
    }

    #[test]
    fn the_nodes_odometry_passes_both_autopilots_and_wrong_frames_do_not() {
        // each autopilot's profile frame: ArduPilot LOCAL_FRD, PX4 LOCAL_NED (the same axes)
        let MavMessage::ODOMETRY(frd) = wire::navigation_to_odometry(&nav(), 5_000_000, 0, false) else { panic!() };
        let MavMessage::ODOMETRY(good) = wire::navigation_to_odometry(&nav(), 5_000_000, 0, true) else { panic!() };
        for (ap, m) in [(Autopilot::ArduPilot, &frd), (Autopilot::Px4, &good)] {
            let mut c = Checker::default();
            c.check(ap, m, 5_000_000);
            assert_eq!(
                (c.accepted, c.ignored.len(), c.without_covariance, c.ahead_of_clock, c.behind_clock),
                (1, 0, 0, 0, 0),
                "{ap:?}"
            );
        }
        // the other way round, neither: ArduPilot takes LOCAL_FRD only, PX4's EKF2 has no
        // heading from a LOCAL_FRD pose (measured on its SIH)
        let mut c = Checker::default();
        c.check(Autopilot::ArduPilot, &good, 5_000_000);
        c.check(Autopilot::Px4, &frd, 5_000_000);
        assert_eq!(c.accepted, 0);
        assert_eq!(c.ignored.values().sum::<u64>(), 2);
        assert!(c.ignored.keys().any(|r| r.contains("heading")), "{:?}", c.ignored);
        // an estimator PX4 routes elsewhere, a NaN position, a timestamp in another clock
        let mut mocap = good.clone();
        mocap.estimator_type = MavEstimatorType::MAV_ESTIMATOR_TYPE_MOCAP;
        let mut nan = good.clone();
        nan.x = f32::NAN;
        let mut c = Checker::default();
        c.check(Autopilot::Px4, &mocap, 5_000_000);
        c.check(Autopilot::Px4, &nan, 5_000_000);
        c.check(Autopilot::Px4, &good, 1_795_000_005_000_000);
        assert_eq!((c.accepted, c.ignored.values().sum::<u64>(), c.ahead_of_clock, c.behind_clock), (1, 2, 0, 1));
        // the other way round (a Unix stamp to a vehicle on its boot clock), and a second late
        let mut unix = good.clone();
        unix.time_usec = 1_795_000_005_000_000;
        c.check(Autopilot::Px4, &unix, 5_000_000);
        c.check(Autopilot::Px4, &good, 6_000_000);
        c.check(Autopilot::Px4, &good, 6_000_001);
        assert_eq!((c.accepted, c.ahead_of_clock, c.behind_clock), (4, 1, 2));
    }

    #[test]
    fn px4_averages_over_its_send_interval_and_ardupilot_sends_the_latest_sample_late() {
        let s = |t: u64, ax: f64| ImuSample {
            t: TimeUs(t),
            specific_force_frd_m_s2: Vector3::new(ax, 0.0, -9.8),
            angular_rate_frd_rad_s: Vector3::zeros(),
        };
        let mut px4 = Personality::new(Autopilot::Px4, 2, 50_000, true);
        for (k, ax) in [1.0, 2.0, 3.0, 6.0].into_iter().enumerate() {
            px4.take_imu(&s(5_000 * (k as u64 + 1), ax));
        }
        let MavMessage::HIGHRES_IMU(m) = px4.imu_message(&s(20_000, 6.0)) else { panic!() };
        assert_eq!((m.xacc, m.time_usec), (3.0, 20_000 + boot_offset_us(2)));
        let mut ap = Personality::new(Autopilot::ArduPilot, 1, 50_000, true);
        ap.take_imu(&s(25_000, 1.0));
        ap.take_imu(&s(50_000, 2.0));
        let MavMessage::RAW_IMU(m) = ap.imu_message(&s(50_000, 2.0)) else { panic!() };
        assert_eq!((m.xacc, m.zacc), (204, -999));
        assert_eq!(m.time_usec, 50_000 + boot_offset_us(1) + ARDUPILOT_SEND_LATENCY_US);
        // SYSTEM_TIME maps the boot clock to Unix time exactly
        let MavMessage::SYSTEM_TIME(st) = ap.system_time(TimeUs(3_000_000)) else { panic!() };
        assert_eq!(st.time_unix_usec - u64::from(st.time_boot_ms) * 1000, SIM_UNIX_EPOCH_US - boot_offset_us(1));
    }

    #[test]
    fn wheel_distance_accumulates_the_odometer() {
        let mut ap = Personality::new(Autopilot::ArduPilot, 1, 50_000, true);
        for k in 1..=20 {
            ap.take_odometer(&OdometerSample { t: TimeUs(50_000 * k), speed_m_s: 2.0 });
        }
        let MavMessage::WHEEL_DISTANCE(w) = ap.odometer_message(&OdometerSample { t: TimeUs(1_000_000), speed_m_s: 2.0 }, 0.1)
        else {
            panic!()
        };
        assert!((w.distance[0] - 2.0).abs() < 1e-12 && w.distance[1] == w.distance[0] && w.count == 2);
    }
}
