//! `cooploc check`: what an autopilot sends a companion, against what a vehicle profile needs,
//! and the autopilot parameters to set, sans-io. The caller feeds it every frame it reads
//! (header, message or a frame of another dialect, signed or not, the wall time in us) and the
//! TIMESYNC answers it measured; [`Survey::report`] says what arrived and [`advice`] what to do.
//!
//! Rates are in the vehicle's own time where it says it (SYSTEM_TIME's `time_boot_ms` over the
//! window: a simulator running faster than real time is measured as its vehicles see it), in
//! wall time otherwise.

use std::collections::BTreeMap;

use mavlink_core::Message as _;

use super::profile::{ImuMessage, OdometerMessage, TeamClock, VehicleProfile};
use crate::protocol::MavMessage;
use crate::protocol::dialect::cooploc::{MavAutopilot, MavType};

/// One message id as it arrived.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Arrivals {
    pub name: String,
    pub count: u64,
    /// Wall time of the first and the last, us.
    pub first_us: u64,
    pub last_us: u64,
    /// (system, component) ids it came from.
    pub sources: std::collections::BTreeSet<(u32, u8)>,
}

/// What an autopilot's link carried (see the module documentation).
#[derive(Debug, Clone, Default)]
pub struct Survey {
    pub messages: BTreeMap<u32, Arrivals>,
    /// HEARTBEATs: (system, component) -> (type, autopilot).
    pub components: BTreeMap<(u32, u8), (MavType, MavAutopilot)>,
    first_wall_us: Option<u64>,
    last_wall_us: u64,
    /// The first and the last SYSTEM_TIME.
    system_time: Option<(SystemTimeSeen, SystemTimeSeen)>,
    pub signed_frames: u64,
    pub unsigned_frames: u64,
    /// AUTOPILOT_VERSION's flight_sw_version, when it answered with one.
    pub flight_sw_version: Option<u32>,
    /// ODOMETRY an odometer gives (not the autopilot's own EKF output, which a node refuses).
    pub odometer_odometry: u64,
    /// The quickest TIMESYNC round trip, us, and the answers.
    pub timesync_rtt_us: Option<i64>,
    pub timesync_answers: u64,
}

/// One SYSTEM_TIME as it arrived.
#[derive(Debug, Clone, Copy, PartialEq)]
struct SystemTimeSeen {
    wall_us: u64,
    time_boot_ms: u32,
    time_unix_usec: u64,
}

/// One message id's arrivals, summed up.
#[derive(Debug, Clone, PartialEq)]
pub struct MessageRate {
    pub id: u32,
    pub name: String,
    pub count: u64,
    /// Between its first and last arrival, Hz of the vehicle's clock when known.
    pub hz: f64,
    /// (system, component) ids it came from.
    pub sources: Vec<(u32, u8)>,
}

/// What [`Survey::report`] found.
#[derive(Debug, Clone, PartialEq)]
pub struct Report {
    /// Seconds of the window, wall and vehicle (SYSTEM_TIME), when known.
    pub wall_s: f64,
    pub vehicle_s: Option<f64>,
    pub rates: Vec<MessageRate>,
    /// The autopilot (the first component 1 HEARTBEAT that is not a ground station or companion).
    pub autopilot: Option<(u32, MavAutopilot, MavType)>,
    /// Whether SYSTEM_TIME carried Unix time.
    pub unix_time: Option<bool>,
    /// Frames of messages outside the dialect.
    pub other_dialect: u64,
    /// Lines comparing what arrived with the profile: (ok, text).
    pub checks: Vec<(bool, String)>,
}

impl Survey {
    /// Takes one frame: its header, its message (None: another dialect's, with its id), whether
    /// it was signed, and the wall time (us) it arrived.
    pub fn frame(&mut self, header: mavlink_core::MavHeader, msg: Option<&MavMessage>, id: u32, signed: bool, wall_us: u64) {
        self.first_wall_us.get_or_insert(wall_us);
        self.last_wall_us = self.last_wall_us.max(wall_us);
        if signed {
            self.signed_frames += 1;
        } else {
            self.unsigned_frames += 1;
        }
        let entry = self.messages.entry(id).or_default();
        if entry.count == 0 {
            entry.first_us = wall_us;
        }
        entry.last_us = wall_us;
        entry.count += 1;
        entry.sources.insert((header.system_id, header.component_id));
        entry.name = msg.map_or_else(|| format!("(id {id}, not in the dialect)"), |m| m.message_name().to_string());
        match msg {
            Some(MavMessage::HEARTBEAT(h)) => {
                self.components.insert((header.system_id, header.component_id), (h.mavtype, h.autopilot));
            }
            Some(MavMessage::SYSTEM_TIME(t)) => {
                let now = SystemTimeSeen { wall_us, time_boot_ms: t.time_boot_ms, time_unix_usec: t.time_unix_usec };
                self.system_time = Some(self.system_time.map_or((now, now), |(first, _)| (first, now)));
            }
            Some(MavMessage::AUTOPILOT_VERSION(v)) if v.flight_sw_version != 0 => {
                self.flight_sw_version = Some(v.flight_sw_version)
            }
            Some(MavMessage::ODOMETRY(o))
                if o.estimator_type != crate::protocol::dialect::cooploc::MavEstimatorType::MAV_ESTIMATOR_TYPE_AUTOPILOT =>
            {
                self.odometer_odometry += 1
            }
            _ => {}
        }
    }

    /// A TIMESYNC answer to a request of ours, with its round trip (us).
    pub fn timesync(&mut self, rtt_us: i64) {
        self.timesync_answers += 1;
        self.timesync_rtt_us = Some(self.timesync_rtt_us.map_or(rtt_us, |r| r.min(rtt_us)));
    }

    /// What arrived, checked against `profile` (the messages it reads, their rates, its clock).
    pub fn report(&self, profile: Option<&VehicleProfile>) -> Report {
        let wall_s = self.first_wall_us.map_or(0.0, |f| (self.last_wall_us - f) as f64 * 1e-6);
        // how fast the vehicle's clock runs against the wall's (1 at real time), from the
        // first and last SYSTEM_TIME: the window in the vehicle's time
        let ratio = self.system_time.and_then(|(a, b)| {
            let vehicle = f64::from(b.time_boot_ms.wrapping_sub(a.time_boot_ms)) * 1e-3;
            let wall = (b.wall_us - a.wall_us) as f64 * 1e-6;
            (vehicle > 0.5 && wall > 0.1).then_some(vehicle / wall)
        });
        let vehicle_s = ratio.map(|r| wall_s * r);
        let ratio = ratio.unwrap_or(1.0);
        let rates = self
            .messages
            .iter()
            .map(|(&id, a)| MessageRate {
                id,
                name: a.name.clone(),
                count: a.count,
                hz: rate(a, ratio),
                sources: a.sources.iter().copied().collect(),
            })
            .collect();
        let autopilot = self
            .components
            .iter()
            .find(|((_, c), (t, _))| *c == 1 && !matches!(t, MavType::MAV_TYPE_GCS | MavType::MAV_TYPE_ONBOARD_CONTROLLER))
            .map(|(&(s, _), &(t, a))| (s, a, t));
        let unix_time = self.system_time.map(|(_, last)| last.time_unix_usec >= super::inputs::UNIX_TIME_FROM_US);
        let other_dialect = self.messages.iter().filter(|(_, a)| a.name.starts_with("(id ")).map(|(_, a)| a.count).sum();
        let mut report = Report { wall_s, vehicle_s, rates, autopilot, unix_time, other_dialect, checks: Vec::new() };
        if let Some(p) = profile {
            report.checks = self.checks(p, ratio, unix_time);
        }
        report
    }

    fn checks(&self, p: &VehicleProfile, ratio: f64, unix_time: Option<bool>) -> Vec<(bool, String)> {
        let mut out = Vec::new();
        let mut want = |id: u32, name: &str, hz: f64, what: &str| {
            let mut got = self.messages.get(&id).map_or(0.0, |a| rate(a, ratio));
            if id == 331 {
                // only an odometer's ODOMETRY counts (the autopilot's own EKF output is refused)
                let all = self.messages.get(&id).map_or(0, |a| a.count).max(1);
                got *= self.odometer_odometry as f64 / all as f64;
            }
            let ok = got >= 0.8 * hz;
            let how = if got == 0.0 {
                "none arrives"
            } else if ok {
                "enough"
            } else if p.inputs.request_rates {
                "the node will ask for it"
            } else {
                "too slow, and the profile says request_rates = false"
            };
            out.push((ok, format!("{what}: {name} at {got:.1} Hz, the profile wants {hz} Hz: {how}")));
        };
        if let Some(s) = &p.sensors {
            let imu = p.inputs.imu;
            want(imu.message_id(), imu.name(), s.imu_rate_hz, "IMU");
            match p.inputs.odometer {
                OdometerMessage::WheelDistance => want(9000, "WHEEL_DISTANCE", s.odometer_rate_hz, "odometer"),
                OdometerMessage::Odometry => want(331, "ODOMETRY", s.odometer_rate_hz, "odometer"),
                OdometerMessage::None => {}
            }
        }
        if let Some(w) = &p.wheels {
            want(9000, "WHEEL_DISTANCE", w.rate_hz, "wheels");
            if p.inputs.yaw_rate == super::profile::YawRateSource::Gyro {
                let imu: ImuMessage = p.inputs.imu;
                want(imu.message_id(), imu.name(), w.rate_hz, "yaw-rate gyro");
            }
        }
        let timesync = self.timesync_answers > 0;
        let (ok, text) = match (p.inputs.clock, unix_time, timesync) {
            (TeamClock::Vehicle, _, _) => (true, "clock: vehicle (the stamps are shared as they are)".to_string()),
            (TeamClock::Unix, Some(true), _) => (true, "clock: unix, and SYSTEM_TIME carries Unix time".into()),
            (TeamClock::Unix, _, true) => (
                false,
                "clock: unix, but SYSTEM_TIME has no Unix time (no GNSS): the node would never start; use clock = \"auto\" (TIMESYNC answers)".into(),
            ),
            (TeamClock::Unix, _, false) => (false, "clock: unix, but SYSTEM_TIME has no Unix time and TIMESYNC goes unanswered".into()),
            (TeamClock::Companion | TeamClock::Auto, _, true) => (
                true,
                format!(
                    "clock: {}: TIMESYNC answered ({} answers, quickest round trip {} us): the companion's clock is the team's (keep it synchronised: NTP or PTP)",
                    if p.inputs.clock == TeamClock::Auto { "auto" } else { "companion" },
                    self.timesync_answers,
                    self.timesync_rtt_us.unwrap_or(0)
                ),
            ),
            (TeamClock::Auto, Some(true), false) => {
                (true, "clock: auto: TIMESYNC unanswered, SYSTEM_TIME's Unix time will be taken".into())
            }
            (_, _, false) => (false, format!("clock: {:?}: TIMESYNC unanswered and no Unix time: no team clock", p.inputs.clock)),
        };
        out.push((ok, text));
        out
    }
}

/// A message's rate between its first and last arrival, Hz of the vehicle's clock (`ratio`:
/// vehicle seconds per wall second).
fn rate(a: &Arrivals, ratio: f64) -> f64 {
    let wall_s = (a.last_us - a.first_us) as f64 * 1e-6;
    if a.count < 2 || wall_s <= 0.0 { 0.0 } else { (a.count - 1) as f64 / (wall_s * ratio) }
}

/// The autopilot parameters a node on `profile` needs, for the autopilot and firmware version
/// `version` (AUTOPILOT_VERSION's flight_sw_version: major in its top byte): (name, value, why).
pub fn advice(autopilot: MavAutopilot, version: Option<u32>, profile: &VehicleProfile) -> Vec<(String, String, String)> {
    let major_minor = version.map(|v| ((v >> 24) & 0xFF, (v >> 16) & 0xFF));
    let mut out: Vec<(String, String, String)> = Vec::new();
    let mut add = |name: &str, value: String, why: &str| out.push((name.to_string(), value, why.to_string()));
    let wheels = profile.inputs.odometer == OdometerMessage::WheelDistance || profile.wheels.is_some();
    let odo_hz = profile.sensors.map(|s| s.odometer_rate_hz).or(profile.wheels.map(|w| w.rate_hz)).unwrap_or(0.0);
    match autopilot {
        MavAutopilot::MAV_AUTOPILOT_ARDUPILOTMEGA => {
            // 4.7 renamed SYSID_THISMAV and the SRn_ stream rates (MAVn_, n = port + 1)
            let new_names = major_minor.is_none_or(|v| v >= (4, 7));
            let (sysid, extra1) = if new_names { ("MAV_SYSID", "MAVn_EXTRA1") } else { ("SYSID_THISMAV", "SRn_EXTRA1") };
            add(sysid, "the node's --id".into(), "one system id per vehicle; the node speaks as it, compid 191");
            add("SERIALn_PROTOCOL", "2".into(), "MAVLink 2 on the companion's port");
            if profile.output.odometry_rate_hz > 0.0 {
                add("VISO_TYPE", "1".into(), "MAVLink external navigation (3 is ModalAI's VOXL)");
                add("EK3_SRC1_POSXY", "6".into(), "position from ExternalNav (the node's ODOMETRY)");
                add("EK3_SRC1_VELXY", "6".into(), "velocity from ExternalNav");
                add("EK3_SRC1_YAW", "6".into(), "yaw from ExternalNav");
            }
            if profile.output.gps_input_rate_hz > 0.0 {
                add("GPS1_TYPE", "14".into(), "GPS_INPUT from the node");
            }
            if wheels {
                add("WENC_TYPE / WENC2_TYPE", "the encoders' type".into(), "WHEEL_DISTANCE is sent only with wheel encoders");
                add(
                    "WENC_POS_Y / WENC2_POS_Y",
                    "the wheels' lateral positions".into(),
                    "the profile's wheel_track_m is their difference",
                );
                add(
                    extra1,
                    format!("{}", odo_hz.round()),
                    "WHEEL_DISTANCE has no message interval of its own: its stream group's rate (the node also asks by REQUEST_DATA_STREAM)",
                );
            }
        }
        MavAutopilot::MAV_AUTOPILOT_PX4 => {
            add("MAV_n_MODE", "2".into(), "onboard mode on the companion's link");
            if profile.inputs.imu == ImuMessage::HighresImu {
                let hz = profile.sensors.map_or(200.0, |s| s.imu_rate_hz);
                add("IMU_INTEG_RATE", format!("{}", hz.max(200.0)), "HIGHRES_IMU at the profile's rate");
            }
            if profile.output.odometry_rate_hz > 0.0 {
                add("EKF2_EV_CTRL", "15".into(), "horizontal and vertical position, velocity and yaw from the node's ODOMETRY");
                add("EKF2_HGT_REF", "3".into(), "height from vision (or keep the barometer)");
                add("EKF2_GPS_CTRL", "0".into(), "no GNSS");
                add("EKF2_EV_DELAY", "the link's latency, ms".into(), "ODOMETRY arrives after its time stamp");
            }
        }
        _ => {}
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::protocol::dialect::cooploc::{HEARTBEAT_DATA, SYSTEM_TIME_DATA};
    use mavlink_core::MavHeader;

    fn profile() -> VehicleProfile {
        VehicleProfile::from_path(concat!(env!("CARGO_MANIFEST_DIR"), "/../../sitl/vehicles/ardupilot-rover.toml")).unwrap()
    }

    /// An ArduPilot without GNSS at its 1 Hz defaults, for 10 s of its clock (5 s of wall time:
    /// a simulator at 2x): rates in its time, the checks against the ArduPilot profile.
    #[test]
    fn an_autopilot_at_its_defaults_falls_short_of_the_profile_and_says_why() {
        let mut s = Survey::default();
        let h = |c| MavHeader { system_id: 1, component_id: c, sequence: 0 };
        let hb = MavMessage::HEARTBEAT(HEARTBEAT_DATA {
            mavtype: MavType::MAV_TYPE_GROUND_ROVER,
            autopilot: MavAutopilot::MAV_AUTOPILOT_ARDUPILOTMEGA,
            ..Default::default()
        });
        for k in 0..=10u64 {
            let wall = k * 500_000;
            s.frame(h(1), Some(&hb), 0, false, wall);
            let st = MavMessage::SYSTEM_TIME(SYSTEM_TIME_DATA { time_unix_usec: 0, time_boot_ms: 60_000 + 1000 * k as u32 });
            s.frame(h(1), Some(&st), 2, false, wall);
            s.frame(h(1), None, 50_123, false, wall);
        }
        let r = s.report(Some(&profile()));
        assert_eq!(r.vehicle_s, Some(10.0));
        assert_eq!(r.autopilot, Some((1, MavAutopilot::MAV_AUTOPILOT_ARDUPILOTMEGA, MavType::MAV_TYPE_GROUND_ROVER)));
        assert_eq!(r.unix_time, Some(false));
        assert_eq!(r.other_dialect, 11);
        let hb_rate = r.rates.iter().find(|x| x.id == 0).unwrap().hz;
        assert!((hb_rate - 1.0).abs() < 1e-9, "one a second of the vehicle's clock: {hb_rate}");
        // no IMU, no wheels, no clock yet
        assert!(r.checks.iter().all(|(ok, _)| !ok), "{:?}", r.checks);
        assert!(r.checks[0].1.contains("RAW_IMU at 0.0 Hz") && r.checks[0].1.contains("none arrives"), "{:?}", r.checks);
        // TIMESYNC answers: the companion's clock will do
        s.timesync(15_000);
        s.timesync(900);
        let r = s.report(Some(&profile()));
        let clock = &r.checks.last().unwrap();
        assert!(clock.0 && clock.1.contains("round trip 900 us"), "{clock:?}");
        // 4.7's names, and the stream group for the wheels
        let a = advice(MavAutopilot::MAV_AUTOPILOT_ARDUPILOTMEGA, Some(0x0407_0000), &profile());
        let names: Vec<&str> = a.iter().map(|(n, _, _)| n.as_str()).collect();
        assert!(names.contains(&"MAV_SYSID") && names.contains(&"MAVn_EXTRA1") && names.contains(&"VISO_TYPE"), "{names:?}");
        assert_eq!(a.iter().find(|(n, _, _)| n == "VISO_TYPE").unwrap().1, "1");
        let old = advice(MavAutopilot::MAV_AUTOPILOT_ARDUPILOTMEGA, Some(0x0406_0000), &profile());
        assert!(old.iter().any(|(n, _, _)| n == "SYSID_THISMAV") && old.iter().any(|(n, _, _)| n == "SRn_EXTRA1"));
    }
}
