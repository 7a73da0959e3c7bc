//! The sans-io core of one simulated vehicle: which message is due when, what a command
//! changes, and what goes back. No sockets and no clock: the caller passes the simulated time
//! and the vehicle's truth trajectory in, and collects [`Outgoing`] messages.
//!
//! Time is the simulated time everywhere: the HEARTBEAT every simulated second, SIM_STATE at its
//! interval of simulated time, sample-driven streams decimated by their sample timestamps. At
//! `--speed 1` that is wall time; at other speeds every rate scales with the speed.

use mavlink_core::MavHeader;

use super::params::{ParamQuery, ParamTable, param_name};
use super::personality::{Autopilot, Checker, Personality, WHEEL_ODOMETRY_COMPID};
use crate::estimation::{ImuSample, OdometerSample, PlatformId, RangeSample, WheelSample};
use crate::protocol::MavMessage;
use crate::protocol::dialect::cooploc::{
    AUTOPILOT_VERSION_DATA, COMMAND_ACK_DATA, MESSAGE_INTERVAL_DATA, MavCmd, MavProtocolCapability, MavResult, TIMESYNC_DATA,
};
use crate::protocol::wire::{self, GeoOrigin};
use crate::sitl::Trajectory;
use crate::time::TimeUs;

/// Component id of every simulated vehicle (MAV_COMP_ID_AUTOPILOT1).
pub const COMPONENT_ID: u8 = 1;

/// WHEEL_DISTANCE's message id.
const WHEEL_DISTANCE_ID: u32 = 9000;

/// The streams sent on the simulated clock (the others at sensor samples).
/// ArduPilot's own TIMESYNC requests, every this much of its clock (measured on ArduRover 4.7).
const ARDUPILOT_TIMESYNC_EVERY_US: u64 = 10_000_000;
const CLOCK_STREAMS: [Stream; 5] =
    [Stream::Heartbeat, Stream::SimState, Stream::SystemTime, Stream::AutopilotOdometry, Stream::Estimate];

/// Shortest interval a periodic (clock-driven) stream accepts, us (1 kHz).
pub const MIN_PERIODIC_INTERVAL_US: u64 = 1_000;
/// ArduPilot SITL's GPS: its fixes arrive this old (`SIM_GPS1_LAG_MS`, default 100 ms), us ...
const GPS_LAG_US: u64 = 100_000;
/// ... at this interval (`SIM_GPS1_HZ`, default 5 Hz), us ...
const GPS_INTERVAL_US: u64 = 200_000;
/// ... and report this accuracy, horizontal and vertical (`SIM_GPS1_ACC`, default 0.3 m), mm.
const GPS_ACCURACY_MM: u32 = 300;

/// The messages a vehicle streams.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum Stream {
    Heartbeat,
    /// The IMU: HIGHRES_IMU (cooploc, PX4) or RAW_IMU (ArduPilot).
    HighresImu,
    /// The odometer: ODOMETRY (cooploc), WHEEL_DISTANCE (ArduPilot), a wheel peripheral's
    /// ODOMETRY (PX4).
    Odometry,
    SimState,
    Range,
    /// SYSTEM_TIME (ArduPilot, PX4).
    SystemTime,
    /// The autopilot's own EKF output as ODOMETRY (PX4).
    AutopilotOdometry,
    /// The autopilot's GNSS fix and its own estimate: GPS_RAW_INT, GLOBAL_POSITION_INT and
    /// ATTITUDE together (ArduPilot, PX4).
    Estimate,
}

impl Stream {
    pub const ALL: [Stream; 8] = [
        Stream::Heartbeat,
        Stream::HighresImu,
        Stream::Odometry,
        Stream::SimState,
        Stream::Range,
        Stream::SystemTime,
        Stream::AutopilotOdometry,
        Stream::Estimate,
    ];

    /// The MAVLink message id (the simulator's own personality; see [`VehicleCore::stream_of`]).
    pub fn message_id(self) -> u32 {
        match self {
            Stream::Heartbeat => 0,
            Stream::HighresImu => 105,
            Stream::Odometry => 331,
            Stream::SimState => 108,
            Stream::Range => 61001,
            Stream::SystemTime => 2,
            Stream::AutopilotOdometry => 331,
            Stream::Estimate => 33,
        }
    }

    /// The stream of message `id` under the simulator's own personality.
    pub fn from_message_id(id: u32) -> Option<Stream> {
        Stream::ALL.into_iter().find(|s| s.message_id() == id)
    }

    /// Sent at the samples of a sensor (decimated), rather than on the simulated clock.
    pub fn sample_driven(self) -> bool {
        matches!(self, Stream::HighresImu | Stream::Odometry | Stream::Range)
    }

    fn index(self) -> usize {
        self as usize
    }
}

/// How often a stream goes out.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Interval {
    Disabled,
    /// At every sample of its sensor (sample-driven streams only).
    EverySample,
    /// At most once per this many microseconds of simulated time.
    Every(u64),
}

/// Default intervals of a vehicle's streams.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct StreamDefaults {
    pub highres_imu: Interval,
    pub odometry: Interval,
    pub sim_state: Interval,
    pub range: Interval,
}

impl Default for StreamDefaults {
    /// Every IMU, odometer and range sample; SIM_STATE at 10 Hz.
    fn default() -> Self {
        StreamDefaults {
            highres_imu: Interval::EverySample,
            odometry: Interval::EverySample,
            sim_state: Interval::Every(100_000),
            range: Interval::EverySample,
        }
    }
}

/// What a vehicle core needs to know about itself and its world.
#[derive(Debug, Clone, PartialEq)]
pub struct VehicleConfig {
    pub platform: PlatformId,
    pub defaults: StreamDefaults,
    /// Where the NED origin is (SIM_STATE latitude/longitude).
    pub origin: GeoOrigin,
    pub gravity_m_s2: f64,
    /// Odometer white noise, for the ODOMETRY velocity covariance.
    pub odometer_sigma_m_s: f64,
    pub imu_period_us: u64,
    pub odometer_period_us: u64,
    /// Ranging period of a periodic schedule (reported by MESSAGE_INTERVAL), if any.
    pub range_period_us: Option<u64>,
    /// Which autopilot the vehicle behaves as.
    pub autopilot: Autopilot,
    /// A wheeled robot without IMU (a planar platform): the distance between its two wheels, m.
    /// Its odometer stream is WHEEL_DISTANCE whatever the autopilot, and it sends no IMU.
    pub wheel_track_m: Option<f64>,
    /// The autopilot has Unix time (a GNSS fix before it was lost, or PX4, whose SYSTEM_TIME
    /// carries it without GNSS): SYSTEM_TIME's `time_unix_usec`. Without it, 0 (ArduPilot
    /// without GNSS, as measured on its SITL).
    pub unix_time: bool,
    /// It has GNSS from power-on (an origin, a fix); `gnss_lost_at`: until then (simulated time).
    pub gnss: bool,
    pub gnss_lost_at: Option<TimeUs>,
    /// After `gnss_lost_at`: the fix is back from then on.
    pub gnss_back_at: Option<TimeUs>,
    /// From `gnss_lost_at` to `gnss_back_at` the fix stays 3D but its position is this far north
    /// of the truth, m: a glitch (ArduPilot SITL's SIM_GPS1_GLTCH_X), not a loss. The EKF as
    /// ArduPilot's EKF3 did on its SITL with 33 m ([`glitch_flagged`]).
    pub gnss_glitch_m: Option<f64>,
}

/// ArduPilot's EKF3 at a GNSS glitch of 33 m on its SITL (one run, three rovers, alike to 0.2 s):
/// EKF_GPS_GLITCHING 1.1-1.3 s after the offset came, the position reset to the glitched GNSS
/// 10 s after it, the flag cleared 10 s after the reset; and the same again when the offset went.
/// The flag is raised only while the EKF's position source is GNSS (`AP_NavEKF3_Control.cpp`).
/// The personality models the EKF that never leaves GNSS (no take-over): once a node switches it
/// to external navigation (ArduPilot's source set 2), the glitch is over for the EKF: it
/// navigates on the node's ODOMETRY, and when it is handed back, GNSS agrees with it (not
/// modelled: a take-over after the reset, whose hand-back would meet a jump).
const GLITCH_FLAG_AFTER_US: u64 = 1_300_000;
const GLITCH_RESET_AFTER_US: u64 = 10_000_000;
const GLITCH_CLEARED_AFTER_US: u64 = 20_000_000;

/// Whether the EKF on GNSS flags a glitch at `t`, for a glitch from `from` to `to` (each jump of
/// the receiver's position, in and out, is one).
fn glitch_flagged(t: TimeUs, from: TimeUs, to: TimeUs) -> bool {
    [from, to].iter().any(|jump| t.0 >= jump.0 + GLITCH_FLAG_AFTER_US && t.0 < jump.0 + GLITCH_CLEARED_AFTER_US)
}

/// Where an outgoing message goes.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Destination {
    /// Every peer of the vehicle's link (streams).
    AllPeers,
    /// Only the sender of the message being handled (command acknowledgements, one-shot
    /// replies to REQUEST_MESSAGE).
    Requester,
}

/// A message the vehicle sends, with its header (sysid, compid 1, the vehicle's sequence).
#[derive(Debug, Clone, PartialEq)]
pub struct Outgoing {
    pub destination: Destination,
    pub header: MavHeader,
    pub message: MavMessage,
}

impl Outgoing {
    /// The MAVLink 2 frame.
    pub fn to_frame(&self) -> Vec<u8> {
        wire::to_frame(self.header, &self.message)
    }
}

/// What a vehicle has done, for logs and tests.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct VehicleCounters {
    /// Frames produced (each counted once, however many peers it went to).
    pub frames_sent: u64,
    pub heartbeat_sent: u64,
    pub highres_imu_sent: u64,
    pub odometry_sent: u64,
    pub sim_state_sent: u64,
    pub range_sent: u64,
    pub raw_imu_sent: u64,
    pub wheel_distance_sent: u64,
    pub system_time_sent: u64,
    /// Valid MAVLink frames received.
    pub frames_received: u64,
    /// Datagrams with no valid MAVLink frame (garbage, unknown ids, bad CRC) and frames that
    /// failed to decode.
    pub malformed: u64,
    /// Valid frames not handled: not addressed to this vehicle, or a message it does not act on.
    pub ignored: u64,
    pub commands_accepted: u64,
    /// Commands answered DENIED or TEMPORARILY_REJECTED.
    pub commands_rejected: u64,
    /// Commands answered UNSUPPORTED.
    pub commands_unsupported: u64,
    /// PARAM_REQUEST_LIST, PARAM_REQUEST_READ and PARAM_SET addressed to this vehicle.
    pub param_requests: u64,
    /// SET_GPS_GLOBAL_ORIGIN taken (the vehicle had no origin).
    pub origins_set: u64,
    /// The EKF source sets switched to by MAV_CMD_SET_EKF_SOURCE_SET (ArduPilot), in order (a
    /// repeat of the set in use not counted).
    pub source_sets: Vec<u8>,
    /// The horizontal distance from the truth of the first ODOMETRY taken, mm (after a
    /// hand-over: the step in what the autopilot navigates on).
    pub first_odometry_error_mm: Option<u64>,
    /// ... and of the last one, mm.
    pub last_odometry_error_mm: Option<u64>,
}

#[derive(Debug, Clone, Copy)]
struct StreamState {
    default: Interval,
    current: Interval,
    /// Next simulated time at which the stream may send.
    next_due_us: u64,
    /// Time of the last sample or message sent.
    last_sent_us: Option<u64>,
}

/// One simulated vehicle's MAVLink behaviour.
#[derive(Debug, Clone)]
pub struct VehicleCore {
    config: VehicleConfig,
    sysid: u8,
    sequence: u8,
    streams: [StreamState; 8],
    last_imu: Option<ImuSample>,
    last_odometer: Option<OdometerSample>,
    last_wheel: Option<WheelSample>,
    last_ranges: Vec<(u32, RangeSample)>,
    counters: VehicleCounters,
    personality: Personality,
    checker: Checker,
    /// Sequence of the wheel-odometry peripheral (its own component).
    peripheral_sequence: u8,
    params: ParamTable,
    /// The vehicle answers TIMESYNC: its clock runs at real time, or within
    /// [`super::runner::NEAR_REAL_TIME`] of it, as a real autopilot's or a real simulator's clock
    /// does (PX4's SIH ran at 0.992); a simulator holding its clock at zero for its peers, or
    /// running much faster or slower, says no: an answer would map its clock to the companion's
    /// wrongly.
    answers_timesync: bool,
    /// The EKF origin the vehicle reports (GPS_GLOBAL_ORIGIN): with GNSS (`gnss`) its
    /// fix's, which is the scenario's origin here; without, none until a SET_GPS_GLOBAL_ORIGIN
    /// gives one, as on the real ArduPilot (measured: REQUEST_MESSAGE 49 answered ACCEPTED with
    /// no message, "EKF3 IMU0 origin set" after SET_GPS_GLOBAL_ORIGIN, then the origin on request).
    ekf_origin: Option<(i32, i32, i32)>,
    /// What the autopilot's EKF holds of the node's estimate: the error of the last ODOMETRY
    /// it took (position, yaw) and when it arrived. Without GNSS its estimate is the truth plus
    /// that error, held (its IMU is perfect here; the real EKF3 drifted 0.04-0.23 m in the 7 s
    /// after the node's ODOMETRY stopped), and its horizontal position is vouched for
    /// [`EKF_DEAD_RECKONING_US`] after it.
    odometry_error: Option<(TimeUs, nalgebra::Vector3<f64>, f64)>,
}

/// How long the EKF vouches for its horizontal position after the last ODOMETRY, without GNSS,
/// us: the real ArduPilot 4.7 Rover's EKF3 kept it for 7 s, then said flags 0x033f -> 0x0027
/// (docs/real-autopilot.md).
pub const EKF_DEAD_RECKONING_US: u64 = 7_000_000;

/// A platform that cannot be a MAVLink system.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("platform id {0} cannot be a MAVLink system id (1..=255)")]
pub struct BadSystemId(pub PlatformId);

impl VehicleCore {
    pub fn new(config: VehicleConfig) -> Result<VehicleCore, BadSystemId> {
        let sysid = u8::try_from(config.platform).ok().filter(|&s| s != 0).ok_or(BadSystemId(config.platform))?;
        let d = config.defaults;
        let state = |default| StreamState { default, current: default, next_due_us: 0, last_sent_us: None };
        let mut streams = [state(Interval::Every(1_000_000)); 8];
        let (imu, odometry, system_time, autopilot_odometry) = match config.autopilot {
            Autopilot::Cooploc => (d.highres_imu, d.odometry, Interval::Disabled, Interval::Disabled),
            // stream groups at 1 Hz until a ground station or the node asks for more
            Autopilot::ArduPilot => {
                (Interval::Every(1_000_000), Interval::Every(1_000_000), Interval::Every(1_000_000), Interval::Disabled)
            }
            // onboard mode: HIGHRES_IMU at 50 Hz; the wheel peripheral at its own rate
            Autopilot::Px4 => {
                (Interval::Every(20_000), Interval::EverySample, Interval::Every(1_000_000), Interval::Every(100_000))
            }
        };
        streams[Stream::HighresImu.index()] = state(imu);
        streams[Stream::Odometry.index()] = state(odometry);
        streams[Stream::SimState.index()] = state(d.sim_state);
        streams[Stream::Range.index()] = state(d.range);
        streams[Stream::SystemTime.index()] = state(system_time);
        streams[Stream::AutopilotOdometry.index()] = state(autopilot_odometry);
        // the GNSS fix and the autopilot's estimate at 1 Hz, as the firmware's default streams
        let estimate = if config.autopilot == Autopilot::Cooploc { Interval::Disabled } else { Interval::Every(1_000_000) };
        streams[Stream::Estimate.index()] = state(estimate);
        let personality = Personality::new(config.autopilot, config.platform, config.odometer_period_us, config.unix_time);
        let o = config.origin;
        let ekf_origin =
            config.gnss.then(|| (wire::deg_to_e7(o.lat_deg), wire::deg_to_e7(o.lon_deg), (o.alt_m * 1e3).round() as i32));
        Ok(VehicleCore {
            ekf_origin,
            odometry_error: None,
            params: ParamTable::for_vehicle(&config, sysid),
            personality,
            checker: Checker::default(),
            peripheral_sequence: 0,
            answers_timesync: true,
            config,
            sysid,
            sequence: 0,
            streams,
            last_imu: None,
            last_odometer: None,
            last_wheel: None,
            last_ranges: Vec::new(),
            counters: VehicleCounters::default(),
        })
    }

    pub fn platform(&self) -> PlatformId {
        self.config.platform
    }

    pub fn system_id(&self) -> u8 {
        self.sysid
    }

    pub fn counters(&self) -> &VehicleCounters {
        &self.counters
    }

    /// What the vehicle's autopilot made of the ODOMETRY it received.
    pub fn checker(&self) -> &Checker {
        &self.checker
    }

    /// Sets a stream's rate before the run, as an autopilot's parameters do at boot (ArduPilot's
    /// SRn_/MAVn_ rates, PX4's `mavlink stream -r`): the same rules and caps as
    /// SET_MESSAGE_INTERVAL. Fails for a message this vehicle does not stream or a bad rate.
    pub fn preset_rate(&mut self, message_id: u32, rate_hz: f64) -> Result<(), String> {
        let stream = self
            .stream_of(message_id)
            .ok_or_else(|| format!("message {message_id} is not a stream of a {} vehicle", self.config.autopilot.name()))?;
        if !(rate_hz.is_finite() && rate_hz > 0.0) {
            return Err(format!("rate {rate_hz} Hz: must be positive"));
        }
        self.set_interval(TimeUs(0), stream, (1e6 / rate_hz) as f32).map_err(|()| format!("rate {rate_hz} Hz refused"))
    }

    /// Whether the vehicle answers TIMESYNC (see the field).
    pub fn set_answers_timesync(&mut self, answers: bool) {
        self.answers_timesync = answers;
    }

    /// The stream a message id stands for, under this vehicle's personality.
    pub fn stream_of(&self, id: u32) -> Option<Stream> {
        let ap = self.config.autopilot;
        match id {
            _ if id == ap.imu_message_id() => Some(Stream::HighresImu),
            9000 if self.config.wheel_track_m.is_some() => Some(Stream::Odometry),
            _ if Some(id) == ap.odometer_message_id() && self.config.wheel_track_m.is_none() => Some(Stream::Odometry),
            331 if ap == Autopilot::Px4 => Some(Stream::AutopilotOdometry),
            2 if ap.boot_clock() => Some(Stream::SystemTime),
            24 | 30 | 33 if ap != Autopilot::Cooploc => Some(Stream::Estimate),
            0 | 108 | 61001 => Stream::from_message_id(id),
            _ => None,
        }
    }

    /// The current interval of a stream.
    pub fn interval(&self, stream: Stream) -> Interval {
        self.streams[stream.index()].current
    }

    /// Counts a datagram or byte run that held no usable frame.
    pub fn count_malformed(&mut self) {
        self.counters.malformed += 1;
    }

    fn emit(&mut self, destination: Destination, message: MavMessage, out: &mut Vec<Outgoing>) {
        let header = MavHeader { system_id: u32::from(self.sysid), component_id: COMPONENT_ID, sequence: self.sequence };
        self.sequence = self.sequence.wrapping_add(1);
        self.count_and_push(destination, header, message, out);
    }

    /// A message from the vehicle's wheel-odometry peripheral (its own component and sequence).
    fn emit_peripheral(&mut self, message: MavMessage, out: &mut Vec<Outgoing>) {
        let header = MavHeader {
            system_id: u32::from(self.sysid),
            component_id: WHEEL_ODOMETRY_COMPID,
            sequence: self.peripheral_sequence,
        };
        self.peripheral_sequence = self.peripheral_sequence.wrapping_add(1);
        self.count_and_push(Destination::AllPeers, header, message, out);
    }

    fn count_and_push(&mut self, destination: Destination, header: MavHeader, message: MavMessage, out: &mut Vec<Outgoing>) {
        self.counters.frames_sent += 1;
        match &message {
            MavMessage::HEARTBEAT(_) => self.counters.heartbeat_sent += 1,
            MavMessage::HIGHRES_IMU(_) => self.counters.highres_imu_sent += 1,
            MavMessage::ODOMETRY(_) => self.counters.odometry_sent += 1,
            MavMessage::SIM_STATE(_) => self.counters.sim_state_sent += 1,
            MavMessage::COOPLOC_RANGE(_) => self.counters.range_sent += 1,
            MavMessage::RAW_IMU(_) => self.counters.raw_imu_sent += 1,
            MavMessage::WHEEL_DISTANCE(_) => self.counters.wheel_distance_sent += 1,
            MavMessage::SYSTEM_TIME(_) => self.counters.system_time_sent += 1,
            _ => {}
        }
        out.push(Outgoing { destination, header, message });
    }

    fn heartbeat(&self) -> MavMessage {
        self.config.autopilot.heartbeat()
    }

    fn sim_state(&self, t: TimeUs, truth: &Trajectory) -> MavMessage {
        let tr = truth.truth_at(t);
        // On level ground: forward acceleration, the turn's centripetal term, a yaw rate.
        let motion = wire::TrueMotion {
            pos_ned_m: tr.pos_ned_m,
            vel_ned_m_s: tr.vel_ned_m_s,
            attitude: tr.attitude,
            body_accel_m_s2: nalgebra::Vector3::new(tr.accel_m_s2, tr.speed_m_s * tr.yaw_rate_rad_s, 0.0),
            body_rate_rad_s: nalgebra::Vector3::new(0.0, 0.0, tr.yaw_rate_rad_s),
        };
        wire::truth_to_sim_state(&motion, &self.config.origin, self.config.gravity_m_s2)
    }

    /// Earliest simulated time at which a clock-driven message (HEARTBEAT, SIM_STATE) is due.
    pub fn next_periodic_due(&self) -> Option<TimeUs> {
        CLOCK_STREAMS
            .into_iter()
            .filter_map(|s| {
                let st = &self.streams[s.index()];
                matches!(st.current, Interval::Every(_)).then_some(st.next_due_us)
            })
            .min()
            .map(TimeUs)
    }

    /// Emits every clock-driven message due at or before `now`, each stamped with its own due
    /// time (SIM_STATE holds the truth at that time), in time order.
    pub fn advance_to(&mut self, now: TimeUs, truth: &Trajectory, out: &mut Vec<Outgoing>) {
        while let Some(due) = self.next_periodic_due().filter(|d| *d <= now) {
            for stream in CLOCK_STREAMS {
                let st = self.streams[stream.index()];
                let Interval::Every(interval) = st.current else { continue };
                if st.next_due_us != due.0 {
                    continue;
                }
                if stream == Stream::Estimate {
                    for message in self.estimate(due, truth) {
                        self.emit(Destination::AllPeers, message, out);
                    }
                    if self.config.autopilot == Autopilot::ArduPilot {
                        let status = self.ekf_status(due);
                        self.emit(Destination::AllPeers, status, out);
                    }
                    let st = &mut self.streams[stream.index()];
                    st.last_sent_us = Some(due.0);
                    st.next_due_us = due.0 + interval;
                    continue;
                }
                let message = match stream {
                    Stream::Heartbeat => self.heartbeat(),
                    Stream::SystemTime => self.personality.system_time(due),
                    Stream::AutopilotOdometry => self.personality.autopilot_odometry(&truth.truth_at(due)),
                    _ => self.sim_state(due, truth),
                };
                self.emit(Destination::AllPeers, message, out);
                if stream == Stream::Heartbeat && self.config.autopilot == Autopilot::ArduPilot && self.answers_timesync {
                    // its own TIMESYNC requests, every 10 s of its clock (measured), for the
                    // companion to answer
                    let clock_us = self.personality.clock_us(due);
                    if clock_us / ARDUPILOT_TIMESYNC_EVERY_US != clock_us.saturating_sub(interval) / ARDUPILOT_TIMESYNC_EVERY_US {
                        let request = MavMessage::TIMESYNC(TIMESYNC_DATA {
                            tc1: 0,
                            ts1: (clock_us as i64).saturating_mul(1000),
                            target_system: 0,
                            target_component: 0,
                        });
                        self.emit(Destination::AllPeers, request, out);
                    }
                }
                let st = &mut self.streams[stream.index()];
                st.last_sent_us = Some(due.0);
                st.next_due_us = due.0 + interval;
            }
        }
    }

    /// ArduPilot's EKF_STATUS_REPORT at `t`: an attitude and velocities, and a horizontal
    /// position once it has an origin and something to hold it (a GNSS fix, or the node's
    /// ODOMETRY in the last [`EKF_DEAD_RECKONING_US`]). (The real EKF3 reports itself
    /// uninitialised for 1-2 s after boot; the personality's vehicles booted 20 s or more before
    /// the simulation starts.)
    fn ekf_status(&self, t: TimeUs) -> MavMessage {
        use crate::protocol::dialect::cooploc::{EKF_STATUS_REPORT_DATA, EkfStatusFlags};
        let mut flags = EkfStatusFlags::EKF_ATTITUDE
            | EkfStatusFlags::EKF_VELOCITY_HORIZ
            | EkfStatusFlags::EKF_VELOCITY_VERT
            | EkfStatusFlags::EKF_POS_VERT_ABS;
        let aided =
            self.gnss_fix(t) || self.odometry_error.is_some_and(|(at, _, _)| t.0 <= at.0.saturating_add(EKF_DEAD_RECKONING_US));
        if self.ekf_origin.is_some() && aided {
            flags |= EkfStatusFlags::EKF_POS_HORIZ_REL | EkfStatusFlags::EKF_POS_HORIZ_ABS;
        }
        if let Some((from, to, _)) = self.glitch()
            && self.glitch_followed()
            && glitch_flagged(t, from, to)
        {
            flags |= EkfStatusFlags::from_bits_retain(0x8000); // EKF_GPS_GLITCHING (ardupilotmega)
        }
        MavMessage::EKF_STATUS_REPORT(EKF_STATUS_REPORT_DATA { flags, ..Default::default() })
    }

    /// Whether a sample-driven stream sends the sample taken at `t`.
    fn sample_due(&mut self, stream: Stream, t: u64) -> bool {
        let st = &mut self.streams[stream.index()];
        let send = match st.current {
            Interval::Disabled => false,
            Interval::EverySample => true,
            Interval::Every(interval) => {
                if t >= st.next_due_us {
                    st.next_due_us += interval;
                    if st.next_due_us <= t {
                        // After a gap (or at the start), restart the grid here instead of bursting.
                        st.next_due_us = t + interval;
                    }
                    true
                } else {
                    false
                }
            }
        };
        if send {
            st.last_sent_us = Some(t);
        }
        send
    }

    /// An IMU sample of this vehicle: HIGHRES_IMU if the stream's interval says so.
    pub fn on_imu(&mut self, s: &ImuSample, out: &mut Vec<Outgoing>) {
        self.last_imu = Some(*s);
        self.personality.take_imu(s);
        if self.sample_due(Stream::HighresImu, s.t.0) {
            let m = self.personality.imu_message(s);
            self.emit(Destination::AllPeers, m, out);
        }
    }

    /// An odometer sample of this vehicle: ODOMETRY (body-frame velocity) if due.
    pub fn on_odometer(&mut self, s: &OdometerSample, out: &mut Vec<Outgoing>) {
        self.last_odometer = Some(*s);
        self.personality.take_odometer(s);
        if self.sample_due(Stream::Odometry, s.t.0) {
            let m = self.personality.odometer_message(s, self.config.odometer_sigma_m_s);
            if self.config.autopilot == Autopilot::Px4 {
                self.emit_peripheral(m, out);
            } else {
                self.emit(Destination::AllPeers, m, out);
            }
        }
    }

    /// A wheel sample of this wheeled robot: WHEEL_DISTANCE (the two wheels' cumulative
    /// distances) if due, from the odometer's component.
    pub fn on_wheel(&mut self, s: &WheelSample, out: &mut Vec<Outgoing>) {
        let track = self.config.wheel_track_m.unwrap_or(0.5);
        self.personality.take_wheel(s, track);
        self.last_wheel = Some(*s);
        if self.sample_due(Stream::Odometry, s.t.0) {
            let m = self.personality.wheel_message(s);
            if self.config.autopilot == Autopilot::Px4 {
                self.emit_peripheral(m, out);
            } else {
                self.emit(Destination::AllPeers, m, out);
            }
        }
    }

    /// A ranging epoch (numbered from 1): COOPLOC_RANGE for each range this vehicle's radio
    /// measured (`from` = this platform). Ranges measured by others are not this vehicle's.
    pub fn on_ranges(&mut self, epoch: u32, t: TimeUs, ranges: &[RangeSample], out: &mut Vec<Outgoing>) {
        let mine: Vec<(u32, RangeSample)> =
            ranges.iter().filter(|r| r.from == self.config.platform).map(|r| (epoch, *r)).collect();
        if mine.is_empty() {
            return;
        }
        self.last_ranges = mine;
        if self.sample_due(Stream::Range, t.0) {
            for i in 0..self.last_ranges.len() {
                let (epoch, r) = self.last_ranges[i];
                let m = self.personality.range_message(&r, epoch);
                self.emit(Destination::AllPeers, m, out);
            }
        }
    }

    /// Handles one datagram (or any byte run holding whole frames): every MAVLink 1 or 2 frame
    /// in it. Returns whether it held at least one valid frame (the runner learns peers from
    /// that). A run with none counts as malformed.
    pub fn on_bytes(&mut self, now: TimeUs, bytes: &[u8], truth: &Trajectory, out: &mut Vec<Outgoing>) -> bool {
        let mut valid = false;
        for frame in crate::protocol::framing::frames(bytes) {
            match frame.message {
                Ok(message) => {
                    valid = true;
                    self.on_message(now, frame.header, &message, truth, out);
                }
                Err(e) => {
                    tracing::debug!(platform = self.config.platform, error = %e, "undecodable frame");
                    self.counters.malformed += 1;
                }
            }
        }
        if !valid {
            self.counters.malformed += 1;
        }
        valid
    }

    /// Handles one decoded message from a peer.
    pub fn on_message(
        &mut self,
        now: TimeUs,
        header: MavHeader,
        message: &MavMessage,
        truth: &Trajectory,
        out: &mut Vec<Outgoing>,
    ) {
        self.counters.frames_received += 1;
        let (command, params, target) = match message {
            MavMessage::ODOMETRY(m) => {
                if self.checker.check(self.config.autopilot, m, self.personality.clock_us(now)) {
                    self.take_odometry(now, m, truth);
                }
                return;
            }
            MavMessage::GPS_INPUT(m) => {
                self.checker.check_gps_input(m);
                return;
            }
            MavMessage::PARAM_REQUEST_LIST(m) => {
                self.on_param_request(ParamQuery::All, (m.target_system, m.target_component), out);
                return;
            }
            MavMessage::PARAM_REQUEST_READ(m) => {
                let query = match u16::try_from(m.param_index) {
                    Ok(i) => ParamQuery::Index(i),
                    Err(_) => match param_name(&m.param_id) {
                        Some(name) => ParamQuery::Name(name),
                        None => {
                            self.counters.ignored += 1;
                            return;
                        }
                    },
                };
                self.on_param_request(query, (m.target_system, m.target_component), out);
                return;
            }
            // Read-only: the answer is the unchanged value.
            MavMessage::PARAM_SET(m) => {
                match param_name(&m.param_id) {
                    Some(name) => self.on_param_request(ParamQuery::Name(name), (m.target_system, m.target_component), out),
                    None => self.counters.ignored += 1,
                }
                return;
            }
            MavMessage::TIMESYNC(m) => {
                // A request (tc1 0) is answered with the vehicle's boot clock in ns, as
                // ArduPilot and PX4 do; their answers to requests of their own are not ours.
                if m.tc1 == 0 && self.answers_timesync {
                    let tc1 = (self.personality.clock_us(now) as i64).saturating_mul(1000);
                    let answer = MavMessage::TIMESYNC(TIMESYNC_DATA {
                        tc1,
                        ts1: m.ts1,
                        target_system: u8::try_from(header.system_id).unwrap_or(0),
                        target_component: header.component_id,
                    });
                    self.emit(Destination::Requester, answer, out);
                } else {
                    self.counters.ignored += 1;
                }
                return;
            }
            #[allow(deprecated)] // for MAV_CMD_DO_SET_GLOBAL_ORIGIN; the message is what autopilots take
            MavMessage::SET_GPS_GLOBAL_ORIGIN(m) => {
                // ArduPilot and PX4 take it when their EKF has no origin yet (and say nothing)
                if (m.target_system == 0 || m.target_system == self.sysid) && self.ekf_origin.is_none() {
                    self.ekf_origin = Some((m.latitude, m.longitude, m.altitude));
                    self.counters.origins_set += 1;
                } else {
                    self.counters.ignored += 1;
                }
                return;
            }
            #[allow(deprecated)] // ArduPilot's stream groups
            MavMessage::REQUEST_DATA_STREAM(m) => {
                let for_us = (m.target_system == 0 || m.target_system == self.sysid)
                    && (m.target_component == 0 || m.target_component == COMPONENT_ID);
                if self.config.autopilot != Autopilot::ArduPilot || !for_us {
                    self.counters.ignored += 1; // PX4 does not support it
                    return;
                }
                self.stream_group(now, m.req_stream_id as u8, m.req_message_rate, m.start_stop);
                return;
            }
            MavMessage::COMMAND_LONG(c) => (
                c.command,
                [c.param1, c.param2, c.param3, c.param4, c.param5, c.param6, c.param7],
                (c.target_system, c.target_component),
            ),
            MavMessage::COMMAND_INT(c) => (
                c.command,
                [c.param1, c.param2, c.param3, c.param4, c.x as f32, c.y as f32, c.z],
                (c.target_system, c.target_component),
            ),
            _ => {
                self.counters.ignored += 1;
                return;
            }
        };
        let for_us = (target.0 == 0 || target.0 == self.sysid) && (target.1 == 0 || target.1 == COMPONENT_ID);
        if !for_us {
            self.counters.ignored += 1;
            return;
        }
        let (result, replies) = self.command(now, command, &params, truth);
        match result {
            MavResult::MAV_RESULT_ACCEPTED => self.counters.commands_accepted += 1,
            MavResult::MAV_RESULT_UNSUPPORTED => self.counters.commands_unsupported += 1,
            _ => self.counters.commands_rejected += 1,
        }
        tracing::debug!(
            platform = self.config.platform,
            from_sysid = header.system_id,
            from_compid = header.component_id,
            ?command,
            param1 = params[0],
            param2 = params[1],
            ?result,
            "command"
        );
        let ack = MavMessage::COMMAND_ACK(COMMAND_ACK_DATA {
            command,
            result,
            target_system: u8::try_from(header.system_id).unwrap_or(0),
            target_component: header.component_id,
            ..Default::default()
        });
        self.emit(Destination::Requester, ack, out);
        for reply in replies {
            self.emit(Destination::Requester, reply, out);
        }
    }

    /// Answers a parameter request addressed to this vehicle (system 0 or ours, component 0 or 1).
    fn on_param_request(&mut self, query: ParamQuery<'_>, target: (u8, u8), out: &mut Vec<Outgoing>) {
        if !((target.0 == 0 || target.0 == self.sysid) && (target.1 == 0 || target.1 == COMPONENT_ID)) {
            self.counters.ignored += 1;
            return;
        }
        self.counters.param_requests += 1;
        for reply in self.params.answer(query) {
            self.emit(Destination::Requester, reply, out);
        }
    }

    /// The vehicle's parameter table.
    pub fn params(&self) -> &ParamTable {
        &self.params
    }

    /// Executes a command: its result and the messages that follow the acknowledgement.
    fn command(&mut self, now: TimeUs, command: MavCmd, p: &[f32; 7], truth: &Trajectory) -> (MavResult, Vec<MavMessage>) {
        use MavResult::*;
        match command {
            MavCmd::MAV_CMD_SET_MESSAGE_INTERVAL => {
                if self.config.autopilot == Autopilot::ArduPilot && message_id_param(p[0]) == Some(WHEEL_DISTANCE_ID) {
                    // "No ap_message for mavlink id (9000)": only its stream group paces it
                    return (MAV_RESULT_DENIED, vec![]);
                }
                let Some(stream) = message_id_param(p[0]).and_then(|id| self.stream_of(id)) else {
                    return (MAV_RESULT_DENIED, vec![]);
                };
                if self.config.autopilot == Autopilot::ArduPilot
                    && p[1] > 0.0
                    && f64::from(p[1]) < self.config.autopilot.min_sensor_interval_us() as f64
                {
                    // "Requested rate for message ID 27 too fast. Increase SCHED_LOOP_RATE": the
                    // old rate stays (REQUEST_DATA_STREAM caps instead)
                    return (MAV_RESULT_DENIED, vec![]);
                }
                match self.set_interval(now, stream, p[1]) {
                    Ok(()) => (MAV_RESULT_ACCEPTED, vec![]),
                    Err(()) => (MAV_RESULT_DENIED, vec![]),
                }
            }
            #[allow(deprecated)] // still sent by ground stations
            MavCmd::MAV_CMD_GET_MESSAGE_INTERVAL => {
                let Some(id) = message_id_param(p[0]).and_then(|id| u16::try_from(id).ok()) else {
                    return (MAV_RESULT_DENIED, vec![]);
                };
                (MAV_RESULT_ACCEPTED, vec![self.message_interval(id)])
            }
            MavCmd::MAV_CMD_REQUEST_MESSAGE => {
                let Some(id) = message_id_param(p[0]) else { return (MAV_RESULT_DENIED, vec![]) };
                self.request_message(now, id, p[1], truth)
            }
            // ArduPilot's EKF source sets 1-3 (EK3_SRCn_*)
            MavCmd::MAV_CMD_SET_EKF_SOURCE_SET if self.config.autopilot == Autopilot::ArduPilot => {
                if (1.0..=3.0).contains(&p[0]) && p[0].fract() == 0.0 {
                    if self.counters.source_sets.last() != Some(&(p[0] as u8)) {
                        self.counters.source_sets.push(p[0] as u8);
                    }
                    (MAV_RESULT_ACCEPTED, vec![])
                } else {
                    (MAV_RESULT_DENIED, vec![])
                }
            }
            _ => (MAV_RESULT_UNSUPPORTED, vec![]),
        }
    }

    /// ArduPilot's REQUEST_DATA_STREAM: every stream of the group at `rate_hz` (0 or `start_stop`
    /// 0: off), capped as SET_MESSAGE_INTERVAL caps; no answer. RAW_SENSORS carries the IMU
    /// (RAW_IMU), EXTRA1 WHEEL_DISTANCE, EXTRA3 SYSTEM_TIME, ALL every one of them.
    fn stream_group(&mut self, now: TimeUs, group: u8, rate_hz: u16, start_stop: u8) {
        const ALL: u8 = 0;
        const RAW_SENSORS: u8 = 1;
        const EXTRA1: u8 = 10;
        const EXTRA3: u8 = 12;
        let streams: &[Stream] = match group {
            ALL => &[Stream::HighresImu, Stream::Odometry, Stream::SystemTime],
            RAW_SENSORS => &[Stream::HighresImu],
            EXTRA1 => &[Stream::Odometry],
            EXTRA3 => &[Stream::SystemTime],
            _ => {
                self.counters.ignored += 1;
                return;
            }
        };
        let interval_us = if start_stop == 0 || rate_hz == 0 { -1.0 } else { 1e6 / f32::from(rate_hz) };
        for &stream in streams {
            let _ = self.set_interval(now, stream, interval_us);
        }
        self.counters.commands_accepted += 1;
    }

    /// MAV_CMD_SET_MESSAGE_INTERVAL's param2: interval in us, -1 disables, 0 restores the
    /// default. Anything else negative, not finite, beyond i32 microseconds, or (for a
    /// clock-driven stream) under [`MIN_PERIODIC_INTERVAL_US`] is refused. HEARTBEAT stays at 1 Hz.
    fn set_interval(&mut self, now: TimeUs, stream: Stream, interval_us: f32) -> Result<(), ()> {
        if !interval_us.is_finite() {
            return Err(());
        }
        let st = self.streams[stream.index()];
        let new = if interval_us == -1.0 {
            Interval::Disabled
        } else if interval_us == 0.0 {
            st.default
        } else if interval_us < 0.0 || interval_us as f64 > i32::MAX as f64 {
            return Err(());
        } else {
            let mut us = (interval_us as f64).round().max(1.0) as u64;
            if !stream.sample_driven() && us < MIN_PERIODIC_INTERVAL_US {
                return Err(());
            }
            if matches!(stream, Stream::HighresImu | Stream::Odometry) {
                // accepted, and capped at what the autopilot can do
                us = us.max(self.config.autopilot.min_sensor_interval_us());
            }
            Interval::Every(us)
        };
        if stream == Stream::Heartbeat && new != st.default {
            return Err(());
        }
        let st = &mut self.streams[stream.index()];
        st.current = new;
        if let Interval::Every(us) = new {
            // Continue from the last message sent, so the new interval holds from the next one on.
            // A clock-driven stream never goes back in time; a sample-driven one sends its next
            // sample once `us` has passed since the last one.
            let floor = if stream.sample_driven() { 0 } else { now.0 };
            st.next_due_us = st.last_sent_us.map_or(floor, |last| (last + us).max(floor));
        }
        Ok(())
    }

    /// MESSAGE_INTERVAL for `id`: -1 disabled, 0 not a stream of this vehicle.
    fn message_interval(&self, id: u16) -> MavMessage {
        let interval_us = match self.stream_of(id as u32) {
            None => 0,
            Some(stream) => match self.streams[stream.index()].current {
                Interval::Disabled => -1,
                Interval::Every(us) => us.min(i32::MAX as u64) as i32,
                Interval::EverySample => {
                    let period = match stream {
                        Stream::HighresImu => Some(self.config.imu_period_us),
                        Stream::Odometry => Some(self.config.odometer_period_us),
                        _ => self.config.range_period_us,
                    };
                    period.map_or(0, |p| p.min(i32::MAX as u64) as i32)
                }
            },
        };
        MavMessage::MESSAGE_INTERVAL(MESSAGE_INTERVAL_DATA { interval_us, message_id: id })
    }

    fn request_message(&mut self, now: TimeUs, id: u32, param2: f32, truth: &Trajectory) -> (MavResult, Vec<MavMessage>) {
        use MavResult::*;
        const AUTOPILOT_VERSION: u32 = 148;
        const MESSAGE_INTERVAL: u32 = 244;
        const GPS_GLOBAL_ORIGIN: u32 = 49;
        let not_yet = (MAV_RESULT_TEMPORARILY_REJECTED, vec![]);
        match id {
            AUTOPILOT_VERSION => (MAV_RESULT_ACCEPTED, vec![self.autopilot_version()]),
            // accepted either way; the message only when there is an origin
            GPS_GLOBAL_ORIGIN => (MAV_RESULT_ACCEPTED, self.gps_global_origin().into_iter().collect()),
            MESSAGE_INTERVAL => match message_id_param(param2).and_then(|id| u16::try_from(id).ok()) {
                Some(id) => (MAV_RESULT_ACCEPTED, vec![self.message_interval(id)]),
                None => (MAV_RESULT_DENIED, vec![]),
            },
            _ => match self.stream_of(id) {
                Some(Stream::Heartbeat) => (MAV_RESULT_ACCEPTED, vec![self.heartbeat()]),
                Some(Stream::SystemTime) => (MAV_RESULT_ACCEPTED, vec![self.personality.system_time(now)]),
                Some(Stream::AutopilotOdometry) => {
                    (MAV_RESULT_ACCEPTED, vec![self.personality.autopilot_odometry(&truth.truth_at(now))])
                }
                Some(Stream::SimState) => (MAV_RESULT_ACCEPTED, vec![self.sim_state(now, truth)]),
                Some(Stream::Estimate) => {
                    let [fix, position, attitude] = self.estimate(now, truth);
                    (
                        MAV_RESULT_ACCEPTED,
                        vec![match id {
                            24 => fix,
                            30 => attitude,
                            _ => position,
                        }],
                    )
                }
                Some(Stream::HighresImu) => match self.last_imu {
                    Some(s) => (MAV_RESULT_ACCEPTED, vec![self.personality.clone().imu_message(&s)]),
                    None => not_yet,
                },
                Some(Stream::Odometry) if self.config.wheel_track_m.is_some() => match self.last_wheel {
                    Some(s) => (MAV_RESULT_ACCEPTED, vec![self.personality.wheel_message(&s)]),
                    None => not_yet,
                },
                Some(Stream::Odometry) => match self.last_odometer {
                    Some(s) => (MAV_RESULT_ACCEPTED, vec![self.personality.odometer_message(&s, self.config.odometer_sigma_m_s)]),
                    None => not_yet,
                },
                Some(Stream::Range) if self.last_ranges.is_empty() => not_yet,
                Some(Stream::Range) => (
                    MAV_RESULT_ACCEPTED,
                    self.last_ranges.iter().map(|(epoch, r)| self.personality.range_message(r, *epoch)).collect(),
                ),
                None => (MAV_RESULT_DENIED, vec![]),
            },
        }
    }

    /// The error of an ODOMETRY the autopilot took at `now` (its position about the scenario's
    /// origin: the node's frame when the EKF's origin is the team's), against the truth at its
    /// time stamp.
    fn take_odometry(&mut self, now: TimeUs, m: &crate::protocol::dialect::cooploc::ODOMETRY_DATA, truth: &Trajectory) {
        let behind = self.personality.clock_us(now).saturating_sub(m.time_usec);
        let tr = truth.truth_at(TimeUs(now.0.saturating_sub(behind)));
        let q = nalgebra::UnitQuaternion::from_quaternion(nalgebra::Quaternion::new(
            f64::from(m.q[0]),
            f64::from(m.q[1]),
            f64::from(m.q[2]),
            f64::from(m.q[3]),
        ));
        let pos = nalgebra::Vector3::new(f64::from(m.x), f64::from(m.y), f64::from(m.z));
        let yaw_error = crate::estimation::unicycle::wrap_angle(q.euler_angles().2 - tr.attitude.euler_angles().2);
        self.odometry_error = Some((now, pos - tr.pos_ned_m, yaw_error));
        let error_mm = ((pos - tr.pos_ned_m).xy().norm() * 1e3).round() as u64;
        self.counters.first_odometry_error_mm.get_or_insert(error_mm);
        self.counters.last_odometry_error_mm = Some(error_mm);
    }

    /// Whether the EKF has a GNSS fix at `t` (a glitch keeps it).
    fn gnss_fix(&self, t: TimeUs) -> bool {
        self.config.gnss
            && (self.config.gnss_glitch_m.is_some()
                || self.config.gnss_lost_at.is_none_or(|lost| t < lost)
                || self.config.gnss_back_at.is_some_and(|back| t >= back))
    }

    /// The glitch (from, to, metres north), if the vehicle has one.
    fn glitch(&self) -> Option<(TimeUs, TimeUs, f64)> {
        let (from, m) = (self.config.gnss_lost_at?, self.config.gnss_glitch_m?);
        Some((from, self.config.gnss_back_at.unwrap_or(TimeUs(u64::MAX / 2)), m))
    }

    /// The EKF has stayed on GNSS (no source set asked for): it follows a glitch as EKF3 did.
    fn glitch_followed(&self) -> bool {
        self.counters.source_sets.is_empty()
    }

    /// The autopilot's fix and estimate at `t`: on GNSS, exact; without, the truth plus the
    /// error of the last ODOMETRY it took (the truth when it took none), while the fix says none.
    fn estimate(&self, t: TimeUs, truth: &Trajectory) -> [MavMessage; 3] {
        let tr = truth.truth_at(t);
        let mut motion = wire::TrueMotion {
            pos_ned_m: tr.pos_ned_m,
            vel_ned_m_s: tr.vel_ned_m_s,
            attitude: tr.attitude,
            body_accel_m_s2: nalgebra::Vector3::zeros(),
            body_rate_rad_s: nalgebra::Vector3::new(0.0, 0.0, tr.yaw_rate_rad_s),
        };
        let fix = self.gnss_fix(t);
        // on GNSS at a glitch: the EKF refuses the jump, then resets to it (and back when it
        // goes); on external navigation it navigates on the node's ODOMETRY, as without a fix
        let glitch = self.glitch().filter(|_| fix);
        let on_gnss = fix && !(glitch.is_some() && self.counters.source_sets.last() == Some(&2));
        if let Some((from, to, north_m)) = glitch
            && self.glitch_followed()
            && t.0 >= from.0 + GLITCH_RESET_AFTER_US
            && t.0 < to.0 + GLITCH_RESET_AFTER_US
        {
            motion.pos_ned_m.x += north_m;
        }
        if let (false, Some((_, pos_error, yaw_error))) = (on_gnss, self.odometry_error) {
            let turn = nalgebra::UnitQuaternion::from_axis_angle(&nalgebra::Vector3::z_axis(), yaw_error);
            motion.pos_ned_m += pos_error;
            motion.vel_ned_m_s = turn * motion.vel_ned_m_s;
            motion.attitude = turn * motion.attitude;
        }
        let time_boot_ms = ((self.personality.clock_us(t) / 1000) % (1 << 32)) as u32;
        let mut out = wire::truth_to_autopilot_estimate(&motion, &self.config.origin, time_boot_ms, fix);
        if let (true, MavMessage::GPS_RAW_INT(g)) = (fix, &mut out[0]) {
            // as ArduPilot's SITL GPS: the true position SIM_GPS1_LAG_MS old, stamped when the
            // autopilot received it (`last_fix_time_ms`, ms), with SIM_GPS1_ACC's accuracy
            // (SIM_GPS1_HZ: a new fix every 200 ms; a faster stream repeats the last)
            let clock = self.personality.clock_us(t);
            let since_fix = clock % GPS_INTERVAL_US;
            let lagged = truth.truth_at(TimeUs(t.0.saturating_sub(since_fix + GPS_LAG_US)));
            let mut at = lagged.pos_ned_m;
            if let Some((from, to, north_m)) = glitch
                && t >= from
                && t < to
            {
                at.x += north_m;
            }
            let geo = wire::ned_to_geodetic(&self.config.origin, &at);
            g.lat = wire::deg_to_e7(geo.lat_deg);
            g.lon = wire::deg_to_e7(geo.lon_deg);
            g.alt = (geo.alt_m * 1e3).round() as i32;
            g.time_usec = clock - since_fix;
            g.h_acc = GPS_ACCURACY_MM;
            g.v_acc = GPS_ACCURACY_MM;
        }
        out
    }

    /// The EKF origin, if it has one.
    fn gps_global_origin(&self) -> Option<MavMessage> {
        let (latitude, longitude, altitude) = self.ekf_origin?;
        Some(MavMessage::GPS_GLOBAL_ORIGIN(crate::protocol::dialect::cooploc::GPS_GLOBAL_ORIGIN_DATA {
            latitude,
            longitude,
            altitude,
            time_usec: 0,
        }))
    }

    /// The origin its EKF reports (degE7, degE7, mm), if any.
    pub fn ekf_origin(&self) -> Option<(i32, i32, i32)> {
        self.ekf_origin
    }

    fn autopilot_version(&self) -> MavMessage {
        MavMessage::AUTOPILOT_VERSION(AUTOPILOT_VERSION_DATA {
            capabilities: MavProtocolCapability::MAV_PROTOCOL_CAPABILITY_MAVLINK2
                | MavProtocolCapability::MAV_PROTOCOL_CAPABILITY_COMMAND_INT,
            uid: u64::from(self.sysid),
            // the firmware the ArduPilot personality was checked against (4.7.0-dev); the others
            // say none
            flight_sw_version: if self.config.autopilot == Autopilot::ArduPilot { 0x0407_0000 } else { 0 },
            ..Default::default()
        })
    }
}

/// A message id carried in a float parameter: a whole number in 0..=16777215 (24-bit ids).
fn message_id_param(v: f32) -> Option<u32> {
    ((0.0..=16_777_215.0).contains(&v) && v.fract() == 0.0).then_some(v as u32)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::protocol::dialect::cooploc::{COMMAND_INT_DATA, COMMAND_LONG_DATA};
    use crate::sitl::scenario::SMALL_TOML as SMALL;
    use crate::sitl::{Scenario, World};

    fn world() -> World {
        World::new(&Scenario::from_toml_str(SMALL).unwrap()).unwrap()
    }

    /// Vehicle 1 as the ArduPilot firmware without GNSS: no Unix time, no origin.
    fn ardupilot_without_gnss() -> VehicleCore {
        VehicleCore::new(VehicleConfig { autopilot: Autopilot::ArduPilot, unix_time: false, gnss: false, ..core(1).config })
            .unwrap()
    }

    fn core(platform: PlatformId) -> VehicleCore {
        VehicleCore::new(VehicleConfig {
            platform,
            defaults: StreamDefaults::default(),
            origin: GeoOrigin { lat_deg: 34.7, lon_deg: 0.0, alt_m: 0.0 },
            gravity_m_s2: 9.80665,
            odometer_sigma_m_s: 0.2,
            imu_period_us: 5_000,
            odometer_period_us: 100_000,
            range_period_us: Some(1_000_000),
            autopilot: Autopilot::Cooploc,
            wheel_track_m: None,
            unix_time: true,
            gnss: true,
            gnss_lost_at: None,
            gnss_back_at: None,
            gnss_glitch_m: None,
        })
        .unwrap()
    }

    const GCS: MavHeader = MavHeader { system_id: 255, component_id: 190, sequence: 0 };

    fn long(target_system: u8, command: MavCmd, param1: f32, param2: f32) -> MavMessage {
        MavMessage::COMMAND_LONG(COMMAND_LONG_DATA {
            command,
            param1,
            param2,
            target_system,
            target_component: 1,
            ..Default::default()
        })
    }

    /// Sends a command, returns the ACK's result and the replies after it.
    fn ask(c: &mut VehicleCore, w: &World, msg: MavMessage) -> Option<(MavResult, Vec<MavMessage>)> {
        let mut out = Vec::new();
        c.on_message(TimeUs(0), GCS, &msg, w.trajectory(c.platform()).unwrap(), &mut out);
        let mut it = out.into_iter();
        let first = it.next()?;
        assert_eq!(first.destination, Destination::Requester);
        let MavMessage::COMMAND_ACK(ack) = first.message else { panic!("ACK first, got {:?}", first.message) };
        assert_eq!((ack.target_system, ack.target_component), (255, 190));
        Some((ack.result, it.map(|o| o.message).collect()))
    }

    #[test]
    fn parameters_are_served_to_the_requester_and_never_written() {
        use crate::protocol::dialect::cooploc::{PARAM_REQUEST_LIST_DATA, PARAM_REQUEST_READ_DATA, PARAM_SET_DATA};
        let w = world();
        let mut c = core(2);
        let ask = |c: &mut VehicleCore, msg: MavMessage| {
            let mut out = Vec::new();
            c.on_message(TimeUs(0), GCS, &msg, w.trajectory(c.platform()).unwrap(), &mut out);
            assert!(out.iter().all(|o| o.destination == Destination::Requester));
            out.into_iter()
                .map(|o| match o.message {
                    MavMessage::PARAM_VALUE(v) => (param_name(&v.param_id).unwrap().to_string(), v.param_value),
                    other => panic!("not a PARAM_VALUE: {other:?}"),
                })
                .collect::<Vec<_>>()
        };
        let list = |target_system| MavMessage::PARAM_REQUEST_LIST(PARAM_REQUEST_LIST_DATA { target_system, target_component: 1 });
        let all = ask(&mut c, list(2));
        assert_eq!(all.len(), c.params().len());
        assert!(all.contains(&("SYSID_THISMAV".to_string(), 2.0)));
        assert!(ask(&mut c, list(3)).is_empty(), "another system's request");
        let by_name = MavMessage::PARAM_REQUEST_READ(PARAM_REQUEST_READ_DATA {
            param_index: -1,
            target_system: 2,
            target_component: 1,
            param_id: "SYSID_THISMAV".into(),
        });
        assert_eq!(ask(&mut c, by_name), vec![("SYSID_THISMAV".to_string(), 2.0)]);
        let set = MavMessage::PARAM_SET(PARAM_SET_DATA {
            param_value: 9.0,
            target_system: 2,
            target_component: 1,
            param_id: "SYSID_THISMAV".into(),
            ..Default::default()
        });
        assert_eq!(ask(&mut c, set.clone()), vec![("SYSID_THISMAV".to_string(), 2.0)], "read-only: the unchanged value");
        assert_eq!(ask(&mut c, set), vec![("SYSID_THISMAV".to_string(), 2.0)]);
        assert_eq!(c.counters().param_requests, 4, "the request for system 3 is not ours");
    }

    fn personality_core(autopilot: Autopilot) -> VehicleCore {
        let mut c = core(1);
        c = VehicleCore::new(VehicleConfig { autopilot, ..c.config.clone() }).unwrap();
        c
    }

    /// What the real ArduPilot Rover SITL did (GNSS off): SYSTEM_TIME without Unix time,
    /// SET_MESSAGE_INTERVAL DENIED for WHEEL_DISTANCE (only its stream group paces it),
    /// TIMESYNC answered with the boot clock in ns.
    #[test]
    #[allow(deprecated)]
    fn the_ardupilot_personality_behaves_as_the_real_firmware_without_gnss() {
        use crate::protocol::dialect::cooploc::{MavDataStream, REQUEST_DATA_STREAM_DATA};
        let w = world();
        let truth = w.trajectory(1).unwrap();
        let mut ap = ardupilot_without_gnss();
        let mut out = Vec::new();
        ap.advance_to(TimeUs(1_000_000), truth, &mut out);
        let st =
            out.iter().find_map(|o| if let MavMessage::SYSTEM_TIME(m) = &o.message { Some(m.clone()) } else { None }).unwrap();
        assert_eq!(st.time_unix_usec, 0, "no GNSS, no Unix time");
        assert!(st.time_boot_ms > 0);
        assert_eq!(
            ask(&mut ap, &w, long(1, MavCmd::MAV_CMD_SET_MESSAGE_INTERVAL, 9000.0, 50_000.0)).unwrap().0,
            MavResult::MAV_RESULT_DENIED
        );
        assert_eq!(ap.interval(Stream::Odometry), Interval::Every(1_000_000), "still the 1 Hz default");
        // REQUEST_DATA_STREAM EXTRA1 at 20 Hz paces it; no answer
        let req = |id: MavDataStream, rate: u16, start_stop: u8| {
            MavMessage::REQUEST_DATA_STREAM(REQUEST_DATA_STREAM_DATA {
                req_message_rate: rate,
                target_system: 1,
                target_component: 1,
                req_stream_id: id,
                start_stop,
            })
        };
        let mut out = Vec::new();
        ap.on_message(TimeUs(0), GCS, &req(MavDataStream::MAV_DATA_STREAM_EXTRA1, 20, 1), truth, &mut out);
        assert!(out.is_empty());
        assert_eq!(ap.interval(Stream::Odometry), Interval::Every(50_000));
        // RAW_SENSORS at 100 Hz: capped at 40 Hz as ArduPilot caps
        ap.on_message(TimeUs(0), GCS, &req(MavDataStream::MAV_DATA_STREAM_RAW_SENSORS, 100, 1), truth, &mut out);
        assert_eq!(ap.interval(Stream::HighresImu), Interval::Every(25_000));
        ap.on_message(TimeUs(0), GCS, &req(MavDataStream::MAV_DATA_STREAM_EXTRA1, 20, 0), truth, &mut out);
        assert_eq!(ap.interval(Stream::Odometry), Interval::Disabled);
        // PX4 ignores REQUEST_DATA_STREAM
        let mut px4 = personality_core(Autopilot::Px4);
        let before = px4.interval(Stream::HighresImu);
        px4.on_message(TimeUs(0), GCS, &req(MavDataStream::MAV_DATA_STREAM_RAW_SENSORS, 10, 1), truth, &mut out);
        assert_eq!(px4.interval(Stream::HighresImu), before);
        // TIMESYNC: the boot clock in ns at the request, ts1 echoed, to the requester
        let sync = MavMessage::TIMESYNC(TIMESYNC_DATA { tc1: 0, ts1: 123_456, target_system: 1, target_component: 1 });
        let mut out = Vec::new();
        ap.on_message(TimeUs(2_000_000), GCS, &sync, truth, &mut out);
        let [o] = out.as_slice() else { panic!("{out:?}") };
        let MavMessage::TIMESYNC(a) = &o.message else { panic!() };
        assert_eq!(o.destination, Destination::Requester);
        let boot_ns = (2_000_000 + super::super::personality::boot_offset_us(1)) as i64 * 1000;
        assert_eq!((a.tc1, a.ts1, a.target_system, a.target_component), (boot_ns, 123_456, 255, 190));
        // an answer (tc1 set) is not a request; a vehicle whose clock is held answers nothing
        let mut out = Vec::new();
        ap.on_message(TimeUs(0), GCS, &MavMessage::TIMESYNC(TIMESYNC_DATA { tc1: 5, ..Default::default() }), truth, &mut out);
        ap.set_answers_timesync(false);
        ap.on_message(TimeUs(0), GCS, &sync, truth, &mut out);
        assert!(out.is_empty());
    }

    #[test]
    fn personalities_map_message_ids_to_their_streams_and_cap_the_rates() {
        let w = world();
        let mut ap = personality_core(Autopilot::ArduPilot);
        // ArduPilot streams its IMU at 1 Hz until asked; 200 Hz is denied (its real firmware:
        // "Increase SCHED_LOOP_RATE"), 40 Hz (0.8 x its 50 Hz loop) accepted
        assert_eq!(ap.interval(Stream::HighresImu), Interval::Every(1_000_000));
        assert_eq!(
            ask(&mut ap, &w, long(1, MavCmd::MAV_CMD_SET_MESSAGE_INTERVAL, 27.0, 5_000.0)).unwrap().0,
            MavResult::MAV_RESULT_DENIED
        );
        assert_eq!(ap.interval(Stream::HighresImu), Interval::Every(1_000_000));
        assert_eq!(
            ask(&mut ap, &w, long(1, MavCmd::MAV_CMD_SET_MESSAGE_INTERVAL, 27.0, 25_000.0)).unwrap().0,
            MavResult::MAV_RESULT_ACCEPTED
        );
        assert_eq!(ap.interval(Stream::HighresImu), Interval::Every(25_000));
        // HIGHRES_IMU is not an ArduPilot Rover stream here; WHEEL_DISTANCE is its odometer
        assert_eq!(
            ask(&mut ap, &w, long(1, MavCmd::MAV_CMD_SET_MESSAGE_INTERVAL, 105.0, 5_000.0)).unwrap().0,
            MavResult::MAV_RESULT_DENIED
        );
        assert_eq!(ap.stream_of(9000), Some(Stream::Odometry));
        let times = imu_times(&mut ap, (1..=40).map(|k| k * 5_000));
        assert!(
            times.len() == 9 && times.windows(2).skip(1).all(|w| w[1] - w[0] == 25_000),
            "200 Hz samples sent at 40 Hz: {times:?}"
        );
        // RAW_IMU is stamped when sent: in the vehicle's boot clock, after the sample
        assert_eq!(
            times[1],
            25_000 + super::super::personality::boot_offset_us(1) + super::super::personality::ARDUPILOT_SEND_LATENCY_US
        );
        // PX4: HIGHRES_IMU at 50 Hz until asked; a request for ODOMETRY paces its own EKF output
        let mut px4 = personality_core(Autopilot::Px4);
        assert_eq!(px4.interval(Stream::HighresImu), Interval::Every(20_000));
        assert_eq!(px4.stream_of(331), Some(Stream::AutopilotOdometry));
        assert_eq!(
            ask(&mut px4, &w, long(1, MavCmd::MAV_CMD_SET_MESSAGE_INTERVAL, 105.0, 1_000.0)).unwrap().0,
            MavResult::MAV_RESULT_ACCEPTED
        );
        assert_eq!(px4.interval(Stream::HighresImu), Interval::Every(5_000));
        assert!(px4.preset_rate(27, 40.0).is_err(), "RAW_IMU is not a PX4 stream here");
    }

    fn imu(t: u64) -> ImuSample {
        ImuSample {
            t: TimeUs(t),
            specific_force_frd_m_s2: nalgebra::Vector3::zeros(),
            angular_rate_frd_rad_s: nalgebra::Vector3::zeros(),
        }
    }

    fn imu_times(c: &mut VehicleCore, samples: impl Iterator<Item = u64>) -> Vec<u64> {
        let mut out = Vec::new();
        samples.for_each(|t| c.on_imu(&imu(t), &mut out));
        out.iter()
            .filter_map(|o| match &o.message {
                MavMessage::HIGHRES_IMU(d) => Some(d.time_usec),
                MavMessage::RAW_IMU(d) => Some(d.time_usec),
                _ => None,
            })
            .collect()
    }

    #[test]
    fn platform_ids_outside_mavlink_system_ids_are_refused() {
        for id in [0, 256, 1000] {
            let mut cfg = core(1).config.clone();
            cfg.platform = id;
            assert_eq!(VehicleCore::new(cfg).unwrap_err(), BadSystemId(id));
        }
        assert_eq!(core(255).system_id(), 255);
    }

    #[test]
    fn heartbeat_and_sim_state_follow_the_simulated_clock_with_increasing_sequence() {
        let w = world();
        let mut c = core(2);
        let mut out = Vec::new();
        c.advance_to(TimeUs(2_050_000), w.trajectory(2).unwrap(), &mut out);
        let hb = out.iter().filter(|o| matches!(o.message, MavMessage::HEARTBEAT(_))).count();
        let sim = out.iter().filter(|o| matches!(o.message, MavMessage::SIM_STATE(_))).count();
        assert_eq!((hb, sim), (3, 21), "heartbeats at 0, 1, 2 s; SIM_STATE every 100 ms from 0");
        for (k, o) in out.iter().enumerate() {
            assert_eq!((o.header.system_id, o.header.component_id, o.header.sequence), (2, 1, k as u8));
            assert_eq!(o.destination, Destination::AllPeers);
        }
        assert_eq!(c.next_periodic_due(), Some(TimeUs(2_100_000)));
        out.clear();
        c.advance_to(TimeUs(2_050_000), w.trajectory(2).unwrap(), &mut out);
        assert!(out.is_empty(), "nothing twice");
    }

    #[test]
    fn intervals_decimate_samples_and_keep_the_mean_rate() {
        let w = world();
        let mut c = core(1);
        assert_eq!(imu_times(&mut c, (1..=4).map(|k| k * 5_000)), vec![5_000, 10_000, 15_000, 20_000]);
        assert_eq!(
            ask(&mut c, &w, long(1, MavCmd::MAV_CMD_SET_MESSAGE_INTERVAL, 105.0, 7_000.0)).unwrap().0,
            MavResult::MAV_RESULT_ACCEPTED
        );
        // 7 ms on a 5 ms grid, from 7 ms after the last one sent (20 ms): the mean rate holds.
        let t = imu_times(&mut c, (5..1005).map(|k| k * 5_000));
        assert_eq!(t[0], 30_000);
        assert!((t.len() as f64 - (5_020_000.0 - 27_000.0) / 7_000.0).abs() <= 1.0, "{}", t.len());
        assert!(t.windows(2).all(|w| (5_000..=10_000).contains(&(w[1] - w[0]))));
        // Slower than the sensor: every sample.
        ask(&mut c, &w, long(1, MavCmd::MAV_CMD_SET_MESSAGE_INTERVAL, 105.0, 1.0)).unwrap();
        assert_eq!(imu_times(&mut c, (1005..1010).map(|k| k * 5_000)).len(), 5);
        // -1 disables, 0 restores the default.
        ask(&mut c, &w, long(1, MavCmd::MAV_CMD_SET_MESSAGE_INTERVAL, 105.0, -1.0)).unwrap();
        assert_eq!(c.interval(Stream::HighresImu), Interval::Disabled);
        assert!(imu_times(&mut c, (1010..1020).map(|k| k * 5_000)).is_empty());
        ask(&mut c, &w, long(1, MavCmd::MAV_CMD_SET_MESSAGE_INTERVAL, 105.0, 0.0)).unwrap();
        assert_eq!(c.interval(Stream::HighresImu), Interval::EverySample);
        assert_eq!(imu_times(&mut c, (1020..1030).map(|k| k * 5_000)).len(), 10);
    }

    #[test]
    fn bad_requests_are_denied_and_change_nothing() {
        let w = world();
        let mut c = core(1);
        for (id, interval) in [
            (105.0, -2.0),
            (105.0, f32::NEG_INFINITY),
            (105.0, f32::NAN),
            (105.0, 3e9),
            (108.0, 999.0),
            (0.0, 2_000_000.0),
            (-1.0, 1000.0),
            (f32::NAN, 1000.0),
            (1e30, 1000.0),
            (33.0, 1000.0),
        ] {
            let (result, replies) = ask(&mut c, &w, long(1, MavCmd::MAV_CMD_SET_MESSAGE_INTERVAL, id, interval)).unwrap();
            assert_eq!(result, MavResult::MAV_RESULT_DENIED, "message {id}, interval {interval}");
            assert!(replies.is_empty());
        }
        for s in Stream::ALL {
            assert_eq!(c.interval(s), c.streams[s.index()].default, "{s:?} unchanged");
        }
        // The heartbeat accepts its own 1 Hz and the default.
        assert_eq!(
            ask(&mut c, &w, long(1, MavCmd::MAV_CMD_SET_MESSAGE_INTERVAL, 0.0, 1e6)).unwrap().0,
            MavResult::MAV_RESULT_ACCEPTED
        );
        assert_eq!(ask(&mut c, &w, long(1, MavCmd::MAV_CMD_DO_SET_MODE, 1.0, 0.0)).unwrap().0, MavResult::MAV_RESULT_UNSUPPORTED);
        assert_eq!(c.counters().commands_rejected, 10);
        assert_eq!(c.counters().commands_unsupported, 1);
    }

    #[test]
    fn commands_for_others_are_ignored_and_command_int_works_too() {
        let w = world();
        let mut c = core(1);
        assert!(ask(&mut c, &w, long(2, MavCmd::MAV_CMD_SET_MESSAGE_INTERVAL, 105.0, -1.0)).is_none());
        let mut other_component = long(1, MavCmd::MAV_CMD_SET_MESSAGE_INTERVAL, 105.0, -1.0);
        if let MavMessage::COMMAND_LONG(d) = &mut other_component {
            d.target_component = 191;
        }
        assert!(ask(&mut c, &w, other_component).is_none());
        assert_eq!(c.counters().ignored, 2);
        assert_eq!(c.interval(Stream::HighresImu), Interval::EverySample);
        // Broadcast (target 0) and COMMAND_INT.
        let int = MavMessage::COMMAND_INT(COMMAND_INT_DATA {
            command: MavCmd::MAV_CMD_SET_MESSAGE_INTERVAL,
            param1: 331.0,
            param2: 500_000.0,
            ..Default::default()
        });
        assert_eq!(ask(&mut c, &w, int).unwrap().0, MavResult::MAV_RESULT_ACCEPTED);
        assert_eq!(c.interval(Stream::Odometry), Interval::Every(500_000));
        let (r, replies) = ask(&mut c, &w, long(0, MavCmd::MAV_CMD_REQUEST_MESSAGE, 244.0, 331.0)).unwrap();
        assert_eq!(r, MavResult::MAV_RESULT_ACCEPTED);
        assert_eq!(replies, vec![MavMessage::MESSAGE_INTERVAL(MESSAGE_INTERVAL_DATA { interval_us: 500_000, message_id: 331 })]);
        let (_, replies) = ask(&mut c, &w, long(0, MavCmd::MAV_CMD_REQUEST_MESSAGE, 244.0, 105.0)).unwrap();
        assert_eq!(replies, vec![MavMessage::MESSAGE_INTERVAL(MESSAGE_INTERVAL_DATA { interval_us: 5_000, message_id: 105 })]);
    }

    #[test]
    #[allow(deprecated)]
    fn an_autopilot_without_gnss_has_no_origin_until_one_is_given() {
        use crate::protocol::dialect::cooploc::SET_GPS_GLOBAL_ORIGIN_DATA;
        let w = world();
        let truth = w.trajectory(1).unwrap();
        let mut ap = ardupilot_without_gnss();
        // asked for: accepted, and nothing follows (as the real ArduRover answers)
        let (r, replies) = ask(&mut ap, &w, long(1, MavCmd::MAV_CMD_REQUEST_MESSAGE, 49.0, 0.0)).unwrap();
        assert_eq!((r, replies.len()), (MavResult::MAV_RESULT_ACCEPTED, 0));
        let set = |lat, target_system| {
            MavMessage::SET_GPS_GLOBAL_ORIGIN(SET_GPS_GLOBAL_ORIGIN_DATA {
                latitude: lat,
                longitude: 1491652300,
                altitude: 584_000,
                target_system,
                time_usec: 0,
            })
        };
        // another vehicle's origin is not ours
        let mut out = Vec::new();
        ap.on_message(TimeUs(0), GCS, &set(-353632610, 2), truth, &mut out);
        assert_eq!(ap.ekf_origin(), None);
        ap.on_message(TimeUs(0), GCS, &set(-353632610, 1), truth, &mut out);
        assert!(out.is_empty(), "taken without a word");
        let (_, replies) = ask(&mut ap, &w, long(1, MavCmd::MAV_CMD_REQUEST_MESSAGE, 49.0, 0.0)).unwrap();
        let [MavMessage::GPS_GLOBAL_ORIGIN(o)] = replies.as_slice() else { panic!("{replies:?}") };
        assert_eq!((o.latitude, o.longitude, o.altitude), (-353632610, 1491652300, 584_000));
        // an origin it has is kept
        ap.on_message(TimeUs(0), GCS, &set(-340000000, 1), truth, &mut out);
        assert_eq!(ap.ekf_origin(), Some((-353632610, 1491652300, 584_000)));
        // with GNSS: its fix's origin from the start
        let mut gnss = core(1);
        let (_, replies) = ask(&mut gnss, &w, long(1, MavCmd::MAV_CMD_REQUEST_MESSAGE, 49.0, 0.0)).unwrap();
        assert!(matches!(replies.as_slice(), [MavMessage::GPS_GLOBAL_ORIGIN(_)]));
    }

    #[test]
    fn the_ardupilot_personality_reports_its_ekf_and_asks_for_timesync_as_the_firmware_does() {
        let w = world();
        let truth = w.trajectory(1).unwrap();
        let mut ap = ardupilot_without_gnss();
        let mut out = Vec::new();
        ap.advance_to(TimeUs(25_000_000), truth, &mut out);
        let flags: Vec<_> = out
            .iter()
            .filter_map(|o| if let MavMessage::EKF_STATUS_REPORT(m) = &o.message { Some(m.flags.bits()) } else { None })
            .collect();
        // 1 Hz: an attitude, and no horizontal position without an origin
        assert!(flags.len() >= 24, "{flags:?}");
        assert!(flags.iter().all(|f| f & 0x0001 != 0 && f & 0x0418 == 0), "{flags:?}");
        // its own TIMESYNC requests every 10 s of its clock (booted 27.9 s before the simulation:
        // at 30.9, 40.9 and 50.9 s of it in these 25 s), its boot time in ns
        let requests: Vec<i64> =
            out.iter().filter_map(|o| if let MavMessage::TIMESYNC(m) = &o.message { Some(m.ts1) } else { None }).collect();
        assert_eq!(requests, [30_919_000_000, 40_919_000_000, 50_919_000_000]);
        // with an origin, a horizontal position
        let mut gnss = core(1);
        gnss.config.autopilot = Autopilot::ArduPilot;
        let MavMessage::EKF_STATUS_REPORT(m) = gnss.ekf_status(TimeUs(1_000_000)) else { panic!() };
        assert_eq!(m.flags.bits() & 0x0018, 0x0018);
    }

    /// A 33 m glitch from 60 s to 120 s, as the real EKF3 met it (SIM_GPS1_GLTCH_X 0.0003 on
    /// ArduPilot's SITL): the fix stays 3D and jumps; the EKF flags it 1.3 s later, resets to it
    /// at 10 s, clears at 20 s, and the same when it goes; a take-over (source set 2) ends it
    /// for the EKF.
    #[test]
    fn a_glitch_jumps_the_fix_and_the_ardupilot_ekf_flags_and_follows_it_as_the_firmware_did() {
        let w = world();
        let truth = w.trajectory(1).unwrap();
        let mut ap = core(1);
        ap.config.autopilot = Autopilot::ArduPilot;
        (ap.config.gnss_lost_at, ap.config.gnss_back_at, ap.config.gnss_glitch_m) =
            (Some(TimeUs(60_000_000)), Some(TimeUs(120_000_000)), Some(33.0));
        let glitch = |ap: &VehicleCore, s: f64| {
            let t = TimeUs::from_secs_f64(s);
            let MavMessage::EKF_STATUS_REPORT(m) = ap.ekf_status(t) else { panic!() };
            let [MavMessage::GPS_RAW_INT(g), MavMessage::GLOBAL_POSITION_INT(p), _] = ap.estimate(t, truth) else { panic!() };
            // (to 10 m: the fix is up to 0.3 s old, the vehicle moving)
            let north = |lat: i32| {
                let m = (f64::from(lat) * 1e-7 - ap.config.origin.lat_deg) * 111_000.0 - truth.truth_at(t).pos_ned_m.x;
                (m / 10.0).round() * 10.0 + 0.0
            };
            (m.flags.bits() & 0x8000 != 0, g.fix_type as u8, north(g.lat), north(p.lat))
        };
        // (flagged, fix type, GPS_RAW_INT's and GLOBAL_POSITION_INT's error north, m)
        assert_eq!(glitch(&ap, 59.0), (false, 3, 0.0, 0.0));
        assert_eq!(glitch(&ap, 61.0), (false, 3, 30.0, 0.0), "not flagged yet");
        assert_eq!(glitch(&ap, 62.0), (true, 3, 30.0, 0.0), "flagged, the jump refused");
        assert_eq!(glitch(&ap, 71.0), (true, 3, 30.0, 30.0), "reset to it");
        assert_eq!(glitch(&ap, 81.0), (false, 3, 30.0, 30.0), "cleared: the EKF is on the glitch");
        assert_eq!(glitch(&ap, 122.0), (true, 3, 0.0, 30.0), "the jump back, flagged and refused");
        assert_eq!(glitch(&ap, 131.0), (true, 3, 0.0, 0.0));
        assert_eq!(glitch(&ap, 141.0), (false, 3, 0.0, 0.0));
        // a node takes over at 62 s: the EKF off GNSS, no flag, its estimate the truth (no
        // ODOMETRY yet) and no reset to the glitch; handed back, none either
        let (r, _) = ask(&mut ap, &w, long(1, MavCmd::MAV_CMD_SET_EKF_SOURCE_SET, 2.0, 0.0)).unwrap();
        assert_eq!(r, MavResult::MAV_RESULT_ACCEPTED);
        assert_eq!(glitch(&ap, 71.0), (false, 3, 30.0, 0.0));
        ask(&mut ap, &w, long(1, MavCmd::MAV_CMD_SET_EKF_SOURCE_SET, 1.0, 0.0)).unwrap();
        assert_eq!(glitch(&ap, 122.0), (false, 3, 0.0, 0.0));
    }

    /// Without GNSS the autopilot's estimate is the node's last ODOMETRY carried on (its error
    /// held), vouched for 7 s after it as the real EKF3's was; before any, the truth without a
    /// horizontal position.
    #[test]
    fn without_gnss_the_ardupilot_personality_carries_the_nodes_last_odometry_and_vouches_for_it_7_s() {
        #[allow(deprecated)]
        use crate::protocol::dialect::cooploc::{MavEstimatorType, MavFrame, ODOMETRY_DATA, SET_GPS_GLOBAL_ORIGIN_DATA};
        let w = world();
        let truth = w.trajectory(1).unwrap();
        let mut ap = ardupilot_without_gnss();
        let mut out = Vec::new();
        #[allow(deprecated)]
        let origin =
            MavMessage::SET_GPS_GLOBAL_ORIGIN(SET_GPS_GLOBAL_ORIGIN_DATA { target_system: 1, latitude: 1, ..Default::default() });
        ap.on_message(TimeUs(0), GCS, &origin, truth, &mut out);
        let estimate_at = |ap: &VehicleCore, t: u64| {
            let [_, MavMessage::GLOBAL_POSITION_INT(_), MavMessage::ATTITUDE(a)] = ap.estimate(TimeUs(t), truth) else {
                panic!()
            };
            let MavMessage::EKF_STATUS_REPORT(s) = ap.ekf_status(TimeUs(t)) else { panic!() };
            (f64::from(a.yaw), s.flags.bits())
        };
        let true_yaw = |t: u64| truth.truth_at(TimeUs(t)).attitude.euler_angles().2;
        let (yaw, flags) = estimate_at(&ap, 10_000_000);
        assert!((yaw - true_yaw(10_000_000)).abs() < 1e-6 && flags & 0x0018 == 0, "no ODOMETRY yet: {flags:#x}");
        // the node's ODOMETRY at 10 s: 3 m north and 0.2 rad off
        let tr = truth.truth_at(TimeUs(10_000_000));
        let q = nalgebra::UnitQuaternion::from_axis_angle(&nalgebra::Vector3::z_axis(), 0.2) * tr.attitude;
        let odometry = MavMessage::ODOMETRY(ODOMETRY_DATA {
            time_usec: ap.personality.clock_us(TimeUs(10_000_000)),
            frame_id: MavFrame::MAV_FRAME_LOCAL_FRD,
            child_frame_id: MavFrame::MAV_FRAME_BODY_FRD,
            x: (tr.pos_ned_m.x + 3.0) as f32,
            y: tr.pos_ned_m.y as f32,
            z: tr.pos_ned_m.z as f32,
            q: [q.w as f32, q.i as f32, q.j as f32, q.k as f32],
            estimator_type: MavEstimatorType::MAV_ESTIMATOR_TYPE_VISION,
            ..Default::default()
        });
        ap.on_message(TimeUs(10_000_000), GCS, &odometry, truth, &mut out);
        for t in [10_000_000, 15_000_000, 17_000_000] {
            let (yaw, flags) = estimate_at(&ap, t);
            assert!((crate::estimation::unicycle::wrap_angle(yaw - true_yaw(t)) - 0.2).abs() < 1e-5, "t {t}: the error held");
            assert_eq!(flags & 0x0018, 0x0018, "t {t}: vouched");
            let [_, MavMessage::GLOBAL_POSITION_INT(p), _] = ap.estimate(TimeUs(t), truth) else { panic!() };
            let g = wire::Geodetic {
                lat_deg: wire::e7_to_deg(p.lat),
                lon_deg: wire::e7_to_deg(p.lon),
                alt_m: f64::from(p.alt) * 1e-3,
            };
            let north = wire::geodetic_to_ned(&ap.config.origin, &g).x - truth.truth_at(TimeUs(t)).pos_ned_m.x;
            assert!((north - 3.0).abs() < 0.1, "t {t}: {north}");
        }
        assert_eq!(estimate_at(&ap, 17_000_001).1 & 0x0018, 0, "7 s on: no horizontal position");
    }

    #[test]
    fn ranges_are_sent_by_the_measuring_platform_only() {
        let r = |from, to| RangeSample { t: TimeUs(1_000_000), from, to, range_m: 100.0, sigma_m: 0.1 };
        let ranges = [r(1, 2), r(1, 3), r(2, 3)];
        for (platform, want) in [(1, 2), (2, 1), (3, 0)] {
            let mut c = core(platform);
            let mut out = Vec::new();
            c.on_ranges(4, TimeUs(1_000_000), &ranges, &mut out);
            assert_eq!(out.len(), want);
            for o in &out {
                let MavMessage::COOPLOC_RANGE(d) = &o.message else { panic!() };
                assert_eq!((d.from_platform, d.epoch), (platform, 4));
            }
        }
    }

    #[test]
    fn garbage_is_counted_and_valid_frames_in_one_datagram_are_all_handled() {
        let w = world();
        let truth = w.trajectory(1).unwrap();
        let mut c = core(1);
        let mut out = Vec::new();
        for junk in [&b""[..], b"\xfd", b"not mavlink at all", &[0xFE; 300]] {
            assert!(!c.on_bytes(TimeUs(0), junk, truth, &mut out));
        }
        assert_eq!(c.counters().malformed, 4);
        assert!(out.is_empty());
        let mut two = wire::to_frame(GCS, &long(1, MavCmd::MAV_CMD_REQUEST_MESSAGE, 0.0, 0.0));
        two.extend(b"junk between");
        two.extend(wire::to_frame(GCS, &long(1, MavCmd::MAV_CMD_REQUEST_MESSAGE, 148.0, 0.0)));
        assert!(c.on_bytes(TimeUs(0), &two, truth, &mut out));
        assert_eq!(c.counters().frames_received, 2);
        assert_eq!(out.len(), 4, "two ACKs, a HEARTBEAT and an AUTOPILOT_VERSION");
    }
}
