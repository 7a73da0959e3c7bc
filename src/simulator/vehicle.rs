//! The sans-io core of one simulated vehicle: which message is due when, what a command
//! changes, and what goes back. No sockets and no clock: the caller passes the simulated time
//! and the vehicle's truth trajectory in, and collects [`Outgoing`] messages.
//!
//! Time is the simulated time everywhere: the HEARTBEAT every simulated second, SIM_STATE at its
//! interval of simulated time, sample-driven streams decimated by their sample timestamps. At
//! `--speed 1` that is wall time; at other speeds every rate scales with the speed.

use mavlink_core::MavHeader;

use crate::estimation::{ImuSample, OdometerSample, PlatformId, RangeSample};
use crate::protocol::MavMessage;
use crate::protocol::dialect::cooploc::{
    AUTOPILOT_VERSION_DATA, COMMAND_ACK_DATA, HEARTBEAT_DATA, MESSAGE_INTERVAL_DATA, MavAutopilot, MavCmd, MavModeFlag,
    MavProtocolCapability, MavResult, MavState, MavType,
};
use crate::protocol::wire::{self, GeoOrigin};
use crate::sitl::Trajectory;
use crate::time::TimeUs;

/// Component id of every simulated vehicle (MAV_COMP_ID_AUTOPILOT1).
pub const COMPONENT_ID: u8 = 1;

/// Shortest interval a periodic (clock-driven) stream accepts, us (1 kHz).
pub const MIN_PERIODIC_INTERVAL_US: u64 = 1_000;

/// The messages a vehicle streams.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum Stream {
    Heartbeat,
    HighresImu,
    Odometry,
    SimState,
    Range,
}

impl Stream {
    pub const ALL: [Stream; 5] = [Stream::Heartbeat, Stream::HighresImu, Stream::Odometry, Stream::SimState, Stream::Range];

    /// The MAVLink message id.
    pub fn message_id(self) -> u32 {
        match self {
            Stream::Heartbeat => 0,
            Stream::HighresImu => 105,
            Stream::Odometry => 331,
            Stream::SimState => 108,
            Stream::Range => 61001,
        }
    }

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
    streams: [StreamState; 5],
    last_imu: Option<ImuSample>,
    last_odometer: Option<OdometerSample>,
    last_ranges: Vec<(u32, RangeSample)>,
    counters: VehicleCounters,
}

/// A platform that cannot be a MAVLink system.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("platform id {0} cannot be a MAVLink system id (1..=255)")]
pub struct BadSystemId(pub PlatformId);

impl VehicleCore {
    pub fn new(config: VehicleConfig) -> Result<VehicleCore, BadSystemId> {
        let sysid = u8::try_from(config.platform).ok().filter(|&s| s != 0).ok_or(BadSystemId(config.platform))?;
        let d = config.defaults;
        let state = |default| StreamState { default, current: default, next_due_us: 0, last_sent_us: None };
        let mut streams = [state(Interval::Every(1_000_000)); 5];
        streams[Stream::HighresImu.index()] = state(d.highres_imu);
        streams[Stream::Odometry.index()] = state(d.odometry);
        streams[Stream::SimState.index()] = state(d.sim_state);
        streams[Stream::Range.index()] = state(d.range);
        Ok(VehicleCore {
            config,
            sysid,
            sequence: 0,
            streams,
            last_imu: None,
            last_odometer: None,
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
        self.counters.frames_sent += 1;
        match &message {
            MavMessage::HEARTBEAT(_) => self.counters.heartbeat_sent += 1,
            MavMessage::HIGHRES_IMU(_) => self.counters.highres_imu_sent += 1,
            MavMessage::ODOMETRY(_) => self.counters.odometry_sent += 1,
            MavMessage::SIM_STATE(_) => self.counters.sim_state_sent += 1,
            MavMessage::COOPLOC_RANGE(_) => self.counters.range_sent += 1,
            _ => {}
        }
        out.push(Outgoing { destination, header, message });
    }

    fn heartbeat() -> MavMessage {
        MavMessage::HEARTBEAT(HEARTBEAT_DATA {
            custom_mode: 0,
            mavtype: MavType::MAV_TYPE_GROUND_ROVER,
            autopilot: MavAutopilot::MAV_AUTOPILOT_GENERIC,
            base_mode: MavModeFlag::empty(),
            system_status: MavState::MAV_STATE_ACTIVE,
            mavlink_version: 3,
        })
    }

    fn sim_state(&self, t: TimeUs, truth: &Trajectory) -> MavMessage {
        wire::truth_to_sim_state(&truth.truth_at(t), &self.config.origin, self.config.gravity_m_s2)
    }

    /// Earliest simulated time at which a clock-driven message (HEARTBEAT, SIM_STATE) is due.
    pub fn next_periodic_due(&self) -> Option<TimeUs> {
        [Stream::Heartbeat, Stream::SimState]
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
            for stream in [Stream::Heartbeat, Stream::SimState] {
                let st = self.streams[stream.index()];
                let Interval::Every(interval) = st.current else { continue };
                if st.next_due_us != due.0 {
                    continue;
                }
                let message = match stream {
                    Stream::Heartbeat => Self::heartbeat(),
                    _ => self.sim_state(due, truth),
                };
                self.emit(Destination::AllPeers, message, out);
                let st = &mut self.streams[stream.index()];
                st.last_sent_us = Some(due.0);
                st.next_due_us = due.0 + interval;
            }
        }
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
        if self.sample_due(Stream::HighresImu, s.t.0) {
            self.emit(Destination::AllPeers, wire::imu_to_highres(s), out);
        }
    }

    /// An odometer sample of this vehicle: ODOMETRY (body-frame velocity) if due.
    pub fn on_odometer(&mut self, s: &OdometerSample, out: &mut Vec<Outgoing>) {
        self.last_odometer = Some(*s);
        if self.sample_due(Stream::Odometry, s.t.0) {
            self.emit(Destination::AllPeers, wire::odometer_to_odometry(s, self.config.odometer_sigma_m_s), out);
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
                self.emit(Destination::AllPeers, wire::range_to_message(&r, epoch), out);
            }
        }
    }

    /// Handles one datagram (or any byte run holding whole frames): every MAVLink 1 or 2 frame
    /// in it. Returns whether it held at least one valid frame (the runner learns peers from
    /// that). A run with none counts as malformed.
    pub fn on_bytes(&mut self, now: TimeUs, bytes: &[u8], truth: &Trajectory, out: &mut Vec<Outgoing>) -> bool {
        let mut reader = mavlink_core::MavlinkReader::new(bytes);
        let mut valid = false;
        loop {
            match reader.read_any_message::<MavMessage>() {
                Ok((header, message)) => {
                    valid = true;
                    self.on_message(now, header, &message, truth, out);
                }
                Err(mavlink_core::error::MessageReadError::Io(_)) => break,
                Err(mavlink_core::error::MessageReadError::Parse(e)) => {
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

    /// Executes a command: its result and the messages that follow the acknowledgement.
    fn command(&mut self, now: TimeUs, command: MavCmd, p: &[f32; 7], truth: &Trajectory) -> (MavResult, Vec<MavMessage>) {
        use MavResult::*;
        match command {
            MavCmd::MAV_CMD_SET_MESSAGE_INTERVAL => {
                let Some(stream) = message_id_param(p[0]).and_then(Stream::from_message_id) else {
                    return (MAV_RESULT_DENIED, vec![]);
                };
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
            _ => (MAV_RESULT_UNSUPPORTED, vec![]),
        }
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
            let us = (interval_us as f64).round().max(1.0) as u64;
            if !stream.sample_driven() && us < MIN_PERIODIC_INTERVAL_US {
                return Err(());
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
        let interval_us = match Stream::from_message_id(id as u32) {
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
        let not_yet = (MAV_RESULT_TEMPORARILY_REJECTED, vec![]);
        match id {
            AUTOPILOT_VERSION => (MAV_RESULT_ACCEPTED, vec![self.autopilot_version()]),
            MESSAGE_INTERVAL => match message_id_param(param2).and_then(|id| u16::try_from(id).ok()) {
                Some(id) => (MAV_RESULT_ACCEPTED, vec![self.message_interval(id)]),
                None => (MAV_RESULT_DENIED, vec![]),
            },
            _ => match Stream::from_message_id(id) {
                Some(Stream::Heartbeat) => (MAV_RESULT_ACCEPTED, vec![Self::heartbeat()]),
                Some(Stream::SimState) => (MAV_RESULT_ACCEPTED, vec![self.sim_state(now, truth)]),
                Some(Stream::HighresImu) => match self.last_imu {
                    Some(s) => (MAV_RESULT_ACCEPTED, vec![wire::imu_to_highres(&s)]),
                    None => not_yet,
                },
                Some(Stream::Odometry) => match self.last_odometer {
                    Some(s) => (MAV_RESULT_ACCEPTED, vec![wire::odometer_to_odometry(&s, self.config.odometer_sigma_m_s)]),
                    None => not_yet,
                },
                Some(Stream::Range) if self.last_ranges.is_empty() => not_yet,
                Some(Stream::Range) => {
                    (MAV_RESULT_ACCEPTED, self.last_ranges.iter().map(|(epoch, r)| wire::range_to_message(r, *epoch)).collect())
                }
                None => (MAV_RESULT_DENIED, vec![]),
            },
        }
    }

    fn autopilot_version(&self) -> MavMessage {
        MavMessage::AUTOPILOT_VERSION(AUTOPILOT_VERSION_DATA {
            capabilities: MavProtocolCapability::MAV_PROTOCOL_CAPABILITY_MAVLINK2
                | MavProtocolCapability::MAV_PROTOCOL_CAPABILITY_COMMAND_INT,
            uid: u64::from(self.sysid),
            ..Default::default()
        })
    }
}

/// A message id carried in a float parameter: a whole number in 0..=16777215 (24-bit ids).
fn message_id_param(v: f32) -> Option<u32> {
    ((0.0..=16_777_215.0).contains(&v) && v.fract() == 0.0).then_some(v as u32)
}
