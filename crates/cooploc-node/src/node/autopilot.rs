//! The node's conversation with its autopilot, sans-io: asking for the message rates the
//! profile wants, and feeding the estimate back as ODOMETRY at a steady rate.
//!
//! - [`RateRequests`]: one MAV_CMD_SET_MESSAGE_INTERVAL (COMMAND_LONG to the autopilot,
//!   component 1) at a time, since a COMMAND_ACK does not say which message it answers;
//!   resent after [`ACK_TIMEOUT_US`] of wall time without an answer, given up after
//!   [`MAX_TRIES`]. Each request ends accepted, refused (with the autopilot's MAV_RESULT) or
//!   unanswered; the node navigates on whatever arrives in every case, and says which.
//!   A message the autopilot refuses to pace by SET_MESSAGE_INTERVAL (ArduPilot answers DENIED
//!   for WHEEL_DISTANCE: it has no message-interval entry for it) is asked for again the old
//!   way, by REQUEST_DATA_STREAM for the stream group that carries it on ArduPilot
//!   ([`ardupilot_stream_group`]); that request has no answer, so it is sent
//!   [`MAX_TRIES`] times, and it paces every message of the group (said in the summary).
//! - [`TimeSync`]: MAVLink TIMESYNC exchanges with the autopilot, which map its boot clock to the
//!   companion's own clock (Unix time, kept by NTP or PTP): the team clock of a vehicle without
//!   GNSS (see [`super::inputs`]).
//! - [`OdometryOutput`]: ODOMETRY every `1 / odometry_rate_hz` of vehicle time (between epochs
//!   too), stamped in the vehicle's clock; its `reset_counter` steps when the estimate jumps by
//!   more than its motion and uncertainty explain (a large cooperative correction), so that the
//!   autopilot's EKF resets to it instead of rejecting it.

use nalgebra::Vector3;

use super::profile::{OdometerMessage, VehicleProfile};
use crate::protocol::MavMessage;
// REQUEST_DATA_STREAM is deprecated in common.xml, and still the only way ArduPilot paces
// some of its messages (WHEEL_DISTANCE).
use crate::protocol::dialect::cooploc::{COMMAND_ACK_DATA, COMMAND_LONG_DATA, MavCmd, MavResult, TIMESYNC_DATA};
#[allow(deprecated)]
use crate::protocol::dialect::cooploc::{MavDataStream, REQUEST_DATA_STREAM_DATA};
use crate::protocol::wire::{self, Navigation};
use crate::time::TimeUs;

/// Wall time a rate request waits for its COMMAND_ACK, us.
pub const ACK_TIMEOUT_US: u64 = 1_000_000;
/// Tries per rate request.
pub const MAX_TRIES: u32 = 3;
/// WHEEL_DISTANCE's message id.
const WHEEL_DISTANCE_ID: u32 = 9000;
/// ODOMETRY's message id.
const ODOMETRY_ID: u32 = 331;

/// How one rate request ended.
#[derive(Debug, Clone, PartialEq)]
pub enum RateOutcome {
    Accepted,
    /// The autopilot answered with this result (DENIED, UNSUPPORTED, FAILED, ...).
    Refused(MavResult),
    /// No COMMAND_ACK after [`MAX_TRIES`] tries.
    Unanswered,
}

/// One message rate the node asks for.
#[derive(Debug, Clone, PartialEq)]
pub struct RateRequest {
    pub message: &'static str,
    pub message_id: u32,
    pub rate_hz: f64,
    pub outcome: Option<RateOutcome>,
    /// After a refusal: the ArduPilot stream group asked for by REQUEST_DATA_STREAM instead
    /// (its name and MAV_DATA_STREAM id), and how many times it was sent.
    pub stream_group: Option<(&'static str, u8, u32)>,
    tries: u32,
    sent_wall_us: Option<u64>,
}

/// The ArduPilot stream group (REQUEST_DATA_STREAM's MAV_DATA_STREAM id) that carries a
/// message, for the messages a node reads (ArduPilot's GCS_Common.cpp stream tables:
/// RAW_SENSORS holds RAW_IMU and SCALED_IMU2/3, EXTRA1 WHEEL_DISTANCE, EXTRA3 SYSTEM_TIME).
pub fn ardupilot_stream_group(message_id: u32) -> Option<(&'static str, u8)> {
    match message_id {
        27 | 116 | 129 => Some(("RAW_SENSORS", 1)),
        WHEEL_DISTANCE_ID => Some(("EXTRA1", 10)),
        2 => Some(("EXTRA3", 12)),
        _ => None,
    }
}

/// The rate requests of a profile, one in flight at a time.
#[derive(Debug, Clone)]
pub struct RateRequests {
    target_system: u8,
    pub requests: Vec<RateRequest>,
}

impl RateRequests {
    /// The IMU and odometer messages at the profile's `[sensors]` rates, or a planar robot's
    /// WHEEL_DISTANCE at its `[wheels]` rate (none if the profile says `request_rates = false`).
    pub fn new(profile: &VehicleProfile, target_system: u8) -> Self {
        let mut requests = Vec::new();
        if profile.inputs.request_rates {
            if let Some(sensors) = &profile.sensors {
                let imu = profile.inputs.imu;
                requests.push(RateRequest::new(imu.name(), imu.message_id(), sensors.imu_rate_hz));
                let odo = match profile.inputs.odometer {
                    OdometerMessage::WheelDistance => Some(("WHEEL_DISTANCE", WHEEL_DISTANCE_ID)),
                    OdometerMessage::Odometry => Some(("ODOMETRY", ODOMETRY_ID)),
                    OdometerMessage::None => None,
                };
                if let Some((name, id)) = odo {
                    requests.push(RateRequest::new(name, id, sensors.odometer_rate_hz));
                }
            }
            // a planar robot: its wheels at the rate of [wheels], its gyro (if it has one) at
            // 50 Hz or the wheels' rate if higher
            if let Some(wheels) = &profile.wheels {
                requests.push(RateRequest::new("WHEEL_DISTANCE", WHEEL_DISTANCE_ID, wheels.rate_hz));
                if profile.inputs.yaw_rate == super::profile::YawRateSource::Gyro {
                    let imu = profile.inputs.imu;
                    requests.push(RateRequest::new(imu.name(), imu.message_id(), wheels.rate_hz.max(50.0)));
                }
            }
        }
        RateRequests { target_system, requests }
    }

    /// Asks for one more message at `rate_hz` (after the profile's).
    pub fn add(&mut self, name: &'static str, message_id: u32, rate_hz: f64) {
        self.requests.push(RateRequest::new(name, message_id, rate_hz));
    }

    /// Asks for a message at the autopilot's own default rate again (MAV_CMD_SET_MESSAGE_INTERVAL
    /// with an interval of 0), when what the node asked for it is no longer needed.
    pub fn add_default(&mut self, name: &'static str, message_id: u32) {
        self.requests.push(RateRequest::new(name, message_id, 0.0));
    }

    /// Asks for one more message at `rate_hz` before every other not yet sent.
    pub fn add_first(&mut self, name: &'static str, message_id: u32, rate_hz: f64) {
        let at = self.requests.iter().position(|r| r.outcome.is_none() && r.tries == 0).unwrap_or(self.requests.len());
        self.requests.insert(at, RateRequest::new(name, message_id, rate_hz));
    }

    fn current(&mut self) -> Option<&mut RateRequest> {
        self.requests.iter_mut().find(|r| r.outcome.is_none())
    }

    /// The command to send now, if any (the first unanswered request, when it is due; then
    /// the stream-group requests of the refused ones, [`MAX_TRIES`] times each,
    /// [`ACK_TIMEOUT_US`] apart).
    pub fn poll(&mut self, wall_us: u64) -> Option<MavMessage> {
        let target_system = self.target_system;
        // a message the autopilot refused to pace has no rate of ours to take back
        let refused = |r: &RateRequest| matches!(r.outcome, Some(RateOutcome::Refused(_) | RateOutcome::Unanswered));
        if let Some(at) = self.requests.iter().position(|r| r.outcome.is_none())
            && self.requests[at].rate_hz == 0.0
            && self.requests[..at].iter().any(|r| r.message_id == self.requests[at].message_id && refused(r))
        {
            self.requests.remove(at);
            return self.poll(wall_us);
        }
        let Some(r) = self.current() else {
            return self.poll_stream_groups(wall_us);
        };
        if let Some(sent) = r.sent_wall_us {
            if wall_us < sent + ACK_TIMEOUT_US {
                return None;
            }
            if r.tries >= MAX_TRIES {
                r.outcome = Some(RateOutcome::Unanswered);
                tracing::warn!(
                    message = r.message,
                    rate_hz = r.rate_hz,
                    "the autopilot did not answer the rate request; navigating on what it sends"
                );
                return self.poll(wall_us);
            }
        }
        r.tries += 1;
        r.sent_wall_us = Some(wall_us);
        Some(MavMessage::COMMAND_LONG(COMMAND_LONG_DATA {
            command: MavCmd::MAV_CMD_SET_MESSAGE_INTERVAL,
            param1: r.message_id as f32,
            // (0: the autopilot's default)
            param2: if r.rate_hz > 0.0 { (1e6 / r.rate_hz) as f32 } else { 0.0 },
            target_system,
            target_component: 1,
            confirmation: (r.tries - 1) as u8,
            ..Default::default()
        }))
    }

    /// REQUEST_DATA_STREAM for the next refused request with a stream group, when due.
    #[allow(deprecated)]
    fn poll_stream_groups(&mut self, wall_us: u64) -> Option<MavMessage> {
        let target_system = self.target_system;
        let r = self.requests.iter_mut().find(|r| r.stream_group.is_some_and(|(_, _, sent)| sent < MAX_TRIES))?;
        if r.sent_wall_us.is_some_and(|sent| wall_us < sent + ACK_TIMEOUT_US) {
            return None;
        }
        let (name, id, sent) = r.stream_group?;
        r.stream_group = Some((name, id, sent + 1));
        r.sent_wall_us = Some(wall_us);
        Some(MavMessage::REQUEST_DATA_STREAM(REQUEST_DATA_STREAM_DATA {
            req_message_rate: r.rate_hz.round().clamp(1.0, 50.0) as u16,
            target_system,
            target_component: 1,
            req_stream_id: num_traits::FromPrimitive::from_u8(id).unwrap_or(MavDataStream::MAV_DATA_STREAM_ALL),
            start_stop: 1,
        }))
    }

    /// Takes a COMMAND_ACK; returns the request it settled.
    pub fn on_ack(&mut self, ack: &COMMAND_ACK_DATA) -> Option<RateRequest> {
        if ack.command != MavCmd::MAV_CMD_SET_MESSAGE_INTERVAL {
            return None;
        }
        let r = self.current()?;
        r.sent_wall_us?;
        match ack.result {
            MavResult::MAV_RESULT_IN_PROGRESS => return None,
            MavResult::MAV_RESULT_ACCEPTED => r.outcome = Some(RateOutcome::Accepted),
            other => {
                r.outcome = Some(RateOutcome::Refused(other));
                r.stream_group = ardupilot_stream_group(r.message_id).map(|(name, id)| (name, id, 0));
                r.sent_wall_us = None;
            }
        }
        Some(r.clone())
    }

    /// Every request has ended.
    pub fn done(&self) -> bool {
        self.requests.iter().all(|r| r.outcome.is_some())
    }
}

impl RateRequest {
    fn new(message: &'static str, message_id: u32, rate_hz: f64) -> Self {
        RateRequest { message, message_id, rate_hz, outcome: None, stream_group: None, tries: 0, sent_wall_us: None }
    }
}

/// TIMESYNC requests sent while no mapping is known, apart (wall time), us.
pub const TIMESYNC_FAST_US: u64 = 200_000;
/// TIMESYNC requests sent once a mapping is known, apart, us (and [`TIMESYNC_FAST_US`] while the
/// autopilot's clock wanders faster than [`WANDER_FAST`]: a mapping is as good as its newest
/// answer is recent).
pub const TIMESYNC_SLOW_US: u64 = 1_000_000;
/// A clock that wanders faster than this (1 ms a second, the team's 10 ms in ten seconds) is
/// asked five times a second.
pub const WANDER_FAST: f64 = 1e-3;
/// The newest answers the mapping's offset comes from (the quickest of them).
const TIMESYNC_WINDOW: usize = 16;
/// Answers kept for the rate (a longer span: a rate is what moves over time).
const RATE_WINDOW: usize = 64;
/// Answers the rate fit needs, at least, and the time they must span (companion clock), ns.
const RATE_FIT_MIN_ANSWERS: usize = 4;
const RATE_FIT_MIN_SPAN_NS: i64 = 3_000_000_000;
/// The largest rate difference believed between the two clocks (crystals differ by tens of
/// parts per million; PX4's SIH ran 0.8% and 1.9% slow on two days): beyond it the clock is
/// broken, and the quickest answer alone gives the mapping. (At 2% SIH's 1.9% crossed it now and
/// then, and each time the mapping fell back on an answer up to 16 s old: steps of 0.3 s.)
pub const TIMESYNC_MAX_RATE: f64 = 0.1;
/// An answer slower than this (round trip) is not used, us.
pub const TIMESYNC_MAX_RTT_US: i64 = 500_000;
/// Requests remembered (an answer must echo one of them).
const TIMESYNC_SENT_KEPT: usize = 32;

/// The companion's clock against the autopilot's boot clock by MAVLink TIMESYNC (sans-io: the
/// caller passes its clock's Unix time, ns).
///
/// A request carries `ts1` = the companion's time of sending, `tc1` = 0; ArduPilot and PX4
/// answer with `tc1` = their boot time (ns) when the request arrived and `ts1` echoed. If the
/// answer comes back at companion time `t4`, the autopilot's instant `tc1` is taken as the
/// middle of the round trip: offset = (ts1 + t4) / 2 - tc1 (companion time minus boot time),
/// wrong by at most half the round trip (by half the difference of the two ways' delays). The
/// two clocks need not run at the same rate (PX4's SIH ran 0.992 times real time; crystals
/// differ by tens of parts per million), so the offset moves: of the last [`TIMESYNC_WINDOW`]
/// answers (one a second) the quickest gives the offset (the least delayed by queues: an answer
/// is good to half its round trip), and a line fitted to them all, each weighted by its round
/// trip, gives the rate at which the offset moves: the mapping is the quickest answer's offset
/// moved on at that rate to the newest answer. A clock that also wanders off any line (a
/// simulator's lockstep: PX4's SIH by tens of milliseconds a second) makes an old answer worth
/// less than a recent one: the answer chosen is the one whose round trip and age, at the rate
/// the offset wanders, promise the smallest error ([`TimeSync::offset_at_us`]). (The line's own offset, an average over answers
/// whose two ways differ, was 3 times worse than the quickest answer's with equal rates.) An offset taken from the quickest answer alone lagged by the rate difference
/// times its age: up to 0.1 s on SIH, past the 50 ms at which a team's epochs split. Too few
/// answers, or too short a span, or a rate beyond [`TIMESYNC_MAX_RATE`]: the quickest answer
/// alone.
#[derive(Debug, Clone, Default)]
pub struct TimeSync {
    next_due_wall_us: u64,
    sent: std::collections::VecDeque<i64>,
    /// (round trip, offset, companion time of the answer's middle), ns, newest last.
    answers: std::collections::VecDeque<(i64, i64, i64)>,
    /// The line through the answers and the wander beyond it, fitted at each answer (a node
    /// maps its clock on every tick while it drifts: 40 fits a second of the same answers).
    fitted: (Option<(i64, f64)>, f64),
    /// Answers that echo no request of ours, or are too slow or implausible.
    pub refused: u64,
    pub requests: u64,
}

impl TimeSync {
    /// A request to send now, if due (`wall_us`: the node's monotonic clock, `unix_ns`: the
    /// companion's clock).
    pub fn poll(&mut self, wall_us: u64, unix_ns: i64, target_system: u8) -> Option<MavMessage> {
        if wall_us < self.next_due_wall_us {
            return None;
        }
        let interval = if self.answers.is_empty() || self.wanders() { TIMESYNC_FAST_US } else { TIMESYNC_SLOW_US };
        self.next_due_wall_us = wall_us + interval;
        self.sent.push_back(unix_ns);
        if self.sent.len() > TIMESYNC_SENT_KEPT {
            self.sent.pop_front();
        }
        self.requests += 1;
        Some(MavMessage::TIMESYNC(TIMESYNC_DATA { tc1: 0, ts1: unix_ns, target_system, target_component: 1 }))
    }

    /// Takes a TIMESYNC from the autopilot, received at companion time `unix_ns`: an answer to
    /// one of our requests gives a sample; a request of the autopilot's (`tc1` 0) gets an answer
    /// in the clock the node stamps what it sends the autopilot with: the autopilot's own boot
    /// clock, by the mapping in use (`boot_offset_us`: team time minus boot time), its `ts1`
    /// echoed; none while no mapping is known. PX4 converts the `time_usec` of what it receives
    /// from a system whose TIMESYNC it has converged on, by the offset it measured: answered in
    /// the companion's Unix time, it moved the node's ODOMETRY (stamped in its boot time) by
    /// decades and stopped fusing it (measured on PX4's SIH). Answered in its own clock, the
    /// offset it finds is about zero.
    pub fn on_message(
        &mut self,
        m: &TIMESYNC_DATA,
        unix_ns: i64,
        source: (u8, u8),
        boot_offset_us: Option<i64>,
    ) -> TimesyncReply {
        if m.tc1 == 0 {
            let Some(offset_us) = boot_offset_us else { return TimesyncReply::Nothing };
            return TimesyncReply::Answer(TIMESYNC_DATA {
                tc1: unix_ns - offset_us * 1000,
                ts1: m.ts1,
                target_system: source.0,
                target_component: source.1,
            });
        }
        let Some(at) = self.sent.iter().position(|&ts| ts == m.ts1) else {
            self.refused += 1;
            return TimesyncReply::Nothing;
        };
        self.sent.remove(at);
        let rtt = unix_ns - m.ts1;
        if !(0..=TIMESYNC_MAX_RTT_US * 1000).contains(&rtt) || m.tc1 < 0 {
            self.refused += 1;
            return TimesyncReply::Nothing;
        }
        let offset = m.ts1 + rtt / 2 - m.tc1;
        self.answers.push_back((rtt, offset, m.ts1 + rtt / 2));
        if self.answers.len() > RATE_WINDOW {
            self.answers.pop_front();
        }
        let line = self.fit_line();
        self.fitted = (line, self.fit_wander(line.map_or(0.0, |(_, rate)| rate)));
        TimesyncReply::Sample
    }

    /// The mapping (companion time minus boot time, us) at the newest answer, and the quickest
    /// round trip (us): see the type's documentation.
    pub fn offset_us(&self) -> Option<(i64, i64)> {
        self.offset_at_us(self.answers.back()?.2)
    }

    /// The same at companion time `unix_ns`.
    pub fn offset_at_us(&self, unix_ns: i64) -> Option<(i64, i64)> {
        let (line, wander) = self.fitted;
        let rate = line.map_or(0.0, |(_, rate)| rate);
        // the answer whose offset, moved on to now, is expected to be off the least
        let expected_error = |a: &(i64, i64, i64)| a.0 as f64 / 2.0 + wander * (unix_ns - a.2).abs() as f64;
        let recent = self.answers.iter().skip(self.answers.len().saturating_sub(TIMESYNC_WINDOW));
        let &(rtt, offset, at) = recent.min_by(|a, b| expected_error(a).total_cmp(&expected_error(b)))?;
        let moved = (rate * (unix_ns - at) as f64).round() as i64;
        Some((offset.saturating_add(moved).div_euclid(1000), rtt / 1000))
    }

    /// How fast the offset wanders off the line (ns per ns): over the last
    /// [`TIMESYNC_WINDOW`] answers, the median of what it moved between two answers beyond
    /// `rate`, less what their round trips allow. A crystal's clock does not wander (0: the
    /// quickest answer gives the offset, however old); a simulator's lockstep does (PX4's SIH
    /// wandered by tens of milliseconds a second, and a recent answer is then worth more).
    fn fit_wander(&self, rate: f64) -> f64 {
        let recent: Vec<&(i64, i64, i64)> =
            self.answers.iter().skip(self.answers.len().saturating_sub(TIMESYNC_WINDOW)).collect();
        let mut rates: Vec<f64> = recent
            .windows(2)
            .filter(|w| w[1].2 > w[0].2)
            .map(|w| {
                let dt = (w[1].2 - w[0].2) as f64;
                let beyond = ((w[1].1 - w[0].1) as f64 - rate * dt).abs() - (w[0].0 + w[1].0) as f64 / 2.0;
                beyond.max(0.0) / dt
            })
            .collect();
        if rates.is_empty() {
            return 0.0;
        }
        rates.sort_by(f64::total_cmp);
        rates[rates.len() / 2]
    }

    /// Whether the two clocks run at rates told apart (the mapping moves between answers).
    pub fn drifts(&self) -> bool {
        self.rate_fit().is_some()
    }

    /// Whether the autopilot's clock wanders faster than [`WANDER_FAST`].
    pub fn wanders(&self) -> bool {
        self.fitted.1 > WANDER_FAST
    }

    /// The line through the answers: (offset at the newest answer, ns; rate, the offset's
    /// change per ns of the companion's clock), when there are enough of them over long enough
    /// and the rate is believable (at most [`TIMESYNC_MAX_RATE`]) and told apart from none (three
    /// times its standard error, each answer taken as good to half its round trip: equal
    /// crystals give no rate at all, and the quickest answer alone, rather than noise).
    pub fn rate_fit(&self) -> Option<(i64, f64)> {
        self.fitted.0
    }

    fn fit_line(&self) -> Option<(i64, f64)> {
        let (newest, first) = (self.answers.back()?.2, self.answers.front()?);
        if self.answers.len() < RATE_FIT_MIN_ANSWERS || newest - first.2 < RATE_FIT_MIN_SPAN_NS {
            return None;
        }
        // Weighted least squares about the newest answer and the first offset (numbers small
        // enough for f64): an answer is good to half its round trip, which weighs it (a slow
        // one, queued behind a busy loop, counts for little).
        let o0 = first.1;
        let (mut sw, mut sx, mut sy, mut sxx, mut sxy) = (0.0, 0.0, 0.0, 0.0, 0.0);
        for &(rtt, offset, t) in &self.answers {
            let w = 1.0 / (rtt as f64 / 2.0 + 10_000.0).powi(2); // (its error, ns, to the -2)
            let (x, y) = ((t - newest) as f64, (offset - o0) as f64);
            sw += w;
            sx += w * x;
            sy += w * y;
            sxx += w * x * x;
            sxy += w * x * y;
        }
        let denominator = sw * sxx - sx * sx;
        if denominator <= 0.0 {
            return None;
        }
        let rate = (sw * sxy - sx * sy) / denominator;
        let at_newest = (sy - rate * sx) / sw;
        let rate_sigma = (sw / denominator).sqrt(); // 1 / sum w (x - mean x)^2, square root
        (rate.abs() <= TIMESYNC_MAX_RATE && rate.abs() > 3.0 * rate_sigma).then(|| (o0 + at_newest.round() as i64, rate))
    }

    /// Forgets every answer (the autopilot rebooted: its boot clock started again).
    pub fn reset(&mut self) {
        self.answers.clear();
        self.fitted = (None, 0.0);
        self.sent.clear();
        self.next_due_wall_us = 0;
    }
}

/// Wall time between the node's questions for the autopilot's origin, us.
pub const ORIGIN_ASK_US: u64 = 2_000_000;
/// Wall time the node waits for the autopilot's own origin before it gives the team's, us.
pub const ORIGIN_WAIT_US: u64 = 5_000_000;
/// Wall time between SET_GPS_GLOBAL_ORIGIN while the autopilot still reports none, us.
pub const ORIGIN_SET_EVERY_US: u64 = 5_000_000;
/// SET_GPS_GLOBAL_ORIGIN sent at most this many times.
pub const ORIGIN_MAX_SETS: u32 = 5;
/// GPS_GLOBAL_ORIGIN's id, for MAV_CMD_REQUEST_MESSAGE.
const GPS_GLOBAL_ORIGIN_ID: u32 = 49;

/// Gives the autopilot the team's origin when it has none, sans-io. An autopilot that never had
/// GNSS has no origin (ArduPilot and PX4 alike): its EKF fuses ODOMETRY as a local position, but
/// it reports no global position and takes no AUTO or GUIDED waypoint in latitude and
/// longitude. The node asks for GPS_GLOBAL_ORIGIN (MAV_CMD_REQUEST_MESSAGE 49; ArduPilot answers
/// ACCEPTED and sends nothing when it has none), and when none has come [`ORIGIN_WAIT_US`] after
/// the first question it sends SET_GPS_GLOBAL_ORIGIN with the profile's `[origin]`, the frame its
/// ODOMETRY is in, every [`ORIGIN_SET_EVERY_US`] until the autopilot reports an origin (at most
/// [`ORIGIN_MAX_SETS`] times). An origin the autopilot reports first (from its own GNSS) is
/// never overwritten.
#[derive(Debug, Clone)]
pub struct OriginOffer {
    origin: wire::GeoOrigin,
    target_system: u8,
    first_ask_wall_us: Option<u64>,
    next_ask_wall_us: u64,
    last_set_wall_us: Option<u64>,
    /// SET_GPS_GLOBAL_ORIGIN sent.
    pub sets: u32,
    /// The origin the autopilot reported, and whether it was ours (within [`ORIGIN_SAME_M`]).
    pub settled: Option<(wire::GeoOrigin, bool)>,
    /// Every SET_GPS_GLOBAL_ORIGIN went unheeded.
    pub gave_up: bool,
    /// ArduPilot's EKF_STATUS_REPORT seen, and whether its EKF has initialised: an origin set
    /// before its cores initialise is lost with their start (measured on ArduRover's SITL), so
    /// none is sent while it reports itself uninitialised.
    ekf: Option<bool>,
}

/// An autopilot's origin this close to the team's is the team's, m.
pub const ORIGIN_SAME_M: f64 = 1.0;

impl OriginOffer {
    /// None without a team origin (the node then takes the autopilot's).
    pub fn new(origin: Option<wire::GeoOrigin>, target_system: u8) -> Option<Self> {
        Some(OriginOffer {
            origin: origin?,
            target_system,
            first_ask_wall_us: None,
            next_ask_wall_us: 0,
            last_set_wall_us: None,
            sets: 0,
            settled: None,
            gave_up: false,
            ekf: None,
        })
    }

    /// The message to send now, if any.
    pub fn poll(&mut self, wall_us: u64) -> Option<MavMessage> {
        if self.settled.is_some() || self.gave_up {
            return None;
        }
        let first = *self.first_ask_wall_us.get_or_insert(wall_us);
        let set_due = wall_us >= first + ORIGIN_WAIT_US
            && self.ekf != Some(false)
            && self.sets < ORIGIN_MAX_SETS
            && self.last_set_wall_us.is_none_or(|last| wall_us >= last + ORIGIN_SET_EVERY_US);
        if set_due {
            self.sets += 1;
            self.last_set_wall_us = Some(wall_us);
            // asked again soon after: ArduPilot sends no GPS_GLOBAL_ORIGIN on its own on every link
            self.next_ask_wall_us = wall_us + ORIGIN_ASK_US / 2;
            if self.sets == 1 {
                tracing::info!(
                    lat_deg = self.origin.lat_deg,
                    lon_deg = self.origin.lon_deg,
                    alt_m = self.origin.alt_m,
                    "the autopilot reports no origin: giving it the team's (SET_GPS_GLOBAL_ORIGIN)"
                );
            }
            return Some(wire::set_gps_global_origin(&self.origin, self.target_system));
        }
        if self.sets >= ORIGIN_MAX_SETS && self.last_set_wall_us.is_some_and(|last| wall_us >= last + ORIGIN_SET_EVERY_US) {
            if !self.gave_up {
                self.gave_up = true;
                tracing::warn!(sets = self.sets, "the autopilot took none of the origins sent: it reports no global position");
            }
            return None;
        }
        if wall_us < self.next_ask_wall_us {
            return None;
        }
        self.next_ask_wall_us = wall_us + ORIGIN_ASK_US;
        Some(MavMessage::COMMAND_LONG(COMMAND_LONG_DATA {
            command: MavCmd::MAV_CMD_REQUEST_MESSAGE,
            param1: GPS_GLOBAL_ORIGIN_ID as f32,
            target_system: self.target_system,
            target_component: 1,
            ..Default::default()
        }))
    }

    /// ArduPilot's EKF_STATUS_REPORT `flags`: initialised once it has an attitude
    /// (EKF_ATTITUDE) and no longer says EKF_UNINITIALIZED.
    pub fn on_ekf_status(&mut self, flags: u16) {
        self.ekf = Some(flags & 0x0001 != 0 && flags & 0x0400 == 0);
    }

    /// The autopilot reported its origin (GPS_GLOBAL_ORIGIN): nothing more to give. Returns
    /// whether it is the team's.
    pub fn on_origin(&mut self, o: wire::GeoOrigin) -> bool {
        let apart =
            wire::geodetic_to_ned(&self.origin, &wire::Geodetic { lat_deg: o.lat_deg, lon_deg: o.lon_deg, alt_m: o.alt_m })
                .xy()
                .norm();
        let ours = apart <= ORIGIN_SAME_M;
        if self.settled.is_none() {
            self.settled = Some((o, ours));
        }
        ours
    }
}

/// What a TIMESYNC from the autopilot asks of the node.
#[derive(Debug, Clone, PartialEq)]
pub enum TimesyncReply {
    /// A new sample of the mapping ([`TimeSync::offset_us`]).
    Sample,
    /// The autopilot's own request: send this answer (as a TIMESYNC).
    Answer(TIMESYNC_DATA),
    Nothing,
}

/// ODOMETRY to the autopilot at a steady vehicle-time rate (see the module documentation).
#[derive(Debug, Clone)]
pub struct OdometryOutput {
    period_us: u64,
    next: Option<TimeUs>,
    last: Option<(TimeUs, Vector3<f64>, Vector3<f64>)>,
    pub reset_counter: u8,
    pub sent: u64,
    /// The autopilot's origin in the team's frame (NED, m), when it has its own (from its GNSS):
    /// positions go out in the autopilot's frame, as its EKF takes them.
    frame_offset_ned_m: Vector3<f64>,
    /// The pose frame is called LOCAL_NED (PX4) rather than LOCAL_FRD (ArduPilot).
    ned: bool,
}

impl OdometryOutput {
    /// None when the rate is 0 (off).
    pub fn new(rate_hz: f64, frame: crate::node::profile::OdometryFrame) -> Option<Self> {
        (rate_hz > 0.0).then(|| OdometryOutput {
            ned: frame == crate::node::profile::OdometryFrame::LocalNed,
            period_us: (1e6 / rate_hz).round() as u64,
            next: None,
            last: None,
            reset_counter: 0,
            sent: 0,
            frame_offset_ned_m: Vector3::zeros(),
        })
    }

    /// The autopilot's local frame has its origin at `offset` in the team's (its own GNSS origin).
    pub fn set_frame_offset(&mut self, offset_ned_m: Vector3<f64>) {
        self.frame_offset_ned_m = offset_ned_m;
    }

    /// The ODOMETRY due now that the filter is at `nav.t`, if any; `to_vehicle` maps the team
    /// clock to the vehicle's.
    pub fn poll(&mut self, nav: &Navigation, to_vehicle: impl Fn(TimeUs) -> u64) -> Option<MavMessage> {
        if self.next.is_some_and(|next| nav.t < next) {
            return None;
        }
        // the next one a whole number of periods on (a gap is not made up with a burst)
        let base = self.next.unwrap_or(nav.t).0;
        let periods = (nav.t.0.saturating_sub(base)) / self.period_us + 1;
        self.next = Some(TimeUs(base + periods * self.period_us));
        if let Some((t0, p0, v0)) = self.last {
            let dt = nav.t.0.saturating_sub(t0.0) as f64 * 1e-6;
            let unexplained = (nav.position_ned_m - p0 - v0 * dt).norm();
            let sigma = nav.pose_covariance.fixed_view::<3, 3>(0, 0).trace().max(0.0).sqrt();
            if unexplained > 3.0 * sigma + 0.5 {
                self.reset_counter = self.reset_counter.wrapping_add(1);
            }
        }
        self.last = Some((nav.t, nav.position_ned_m, nav.velocity_ned_m_s));
        self.sent += 1;
        if self.frame_offset_ned_m != Vector3::zeros() {
            let shifted = Navigation { position_ned_m: nav.position_ned_m - self.frame_offset_ned_m, ..nav.clone() };
            return Some(wire::navigation_to_odometry(&shifted, to_vehicle(nav.t), self.reset_counter, self.ned));
        }
        Some(wire::navigation_to_odometry(nav, to_vehicle(nav.t), self.reset_counter, self.ned))
    }
}

/// GPS_INPUT to the autopilot at a steady vehicle-time rate.
#[derive(Debug, Clone)]
pub struct GpsInputOutput {
    period_us: u64,
    next: Option<TimeUs>,
    origin: crate::protocol::wire::GeoOrigin,
    pub sent: u64,
}

impl GpsInputOutput {
    /// None when the rate is 0 (off) or there is no origin.
    pub fn new(rate_hz: f64, origin: Option<crate::protocol::wire::GeoOrigin>) -> Option<Self> {
        let origin = origin?;
        (rate_hz > 0.0).then(|| GpsInputOutput { period_us: (1e6 / rate_hz).round() as u64, next: None, origin, sent: 0 })
    }

    /// The GPS_INPUT due now, if any; `to_vehicle` maps the team clock to the vehicle's. The GPS
    /// time goes with it when the team's clock is Unix time.
    pub fn poll(&mut self, nav: &Navigation, to_vehicle: impl Fn(TimeUs) -> u64) -> Option<MavMessage> {
        let unix = nav.t.0 >= super::inputs::UNIX_TIME_FROM_US;
        if self.next.is_some_and(|next| nav.t < next) {
            return None;
        }
        let base = self.next.unwrap_or(nav.t).0;
        let periods = (nav.t.0.saturating_sub(base)) / self.period_us + 1;
        self.next = Some(TimeUs(base + periods * self.period_us));
        self.sent += 1;
        let gps_time = unix.then(|| wire::gps_week_time(nav.t.0));
        Some(wire::navigation_to_gps_input(nav, &self.origin, to_vehicle(nav.t), gps_time))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::protocol::dialect::cooploc::MavFrame;
    use cooploc_sitl::sitl::{PAPER_TOML, Scenario};
    use nalgebra::{Matrix3, Matrix6, UnitQuaternion};

    fn profile() -> VehicleProfile {
        let mut p = VehicleProfile::from_spec(&Scenario::from_toml_str(PAPER_TOML).unwrap().vehicle());
        p.inputs.request_rates = true;
        p
    }

    fn ack(result: MavResult) -> COMMAND_ACK_DATA {
        COMMAND_ACK_DATA { command: MavCmd::MAV_CMD_SET_MESSAGE_INTERVAL, result, ..Default::default() }
    }

    #[test]
    fn a_request_for_the_default_rate_sends_an_interval_of_zero_and_comes_first_when_asked_first() {
        let mut r = RateRequests::new(&profile(), 3);
        r.add_first("ATTITUDE", 30, 10.0);
        r.add_default("ATTITUDE", 30);
        let Some(MavMessage::COMMAND_LONG(c)) = r.poll(0) else { panic!("a request") };
        assert_eq!((c.param1, c.param2), (30.0, 100_000.0), "the one asked first goes first");
        r.on_ack(&ack(MavResult::MAV_RESULT_ACCEPTED));
        let last = r.requests.last().unwrap();
        assert_eq!((last.message_id, last.rate_hz), (30, 0.0));
        let mut sent = Vec::new();
        for k in 1..10 {
            if let Some(MavMessage::COMMAND_LONG(c)) = r.poll(k * 100_000) {
                sent.push((c.param1, c.param2));
                r.on_ack(&ack(MavResult::MAV_RESULT_ACCEPTED));
            }
        }
        assert_eq!(sent.last(), Some(&(30.0, 0.0)), "0 us: the autopilot's own default, last: {sent:?}");
        // one it refused is not asked back: the default request ends as the refusal did
        let mut r = RateRequests::new(&profile(), 3);
        r.add_first("ESTIMATOR_STATUS", 230, 10.0);
        r.add_default("ESTIMATOR_STATUS", 230);
        r.poll(0);
        r.on_ack(&ack(MavResult::MAV_RESULT_DENIED));
        let mut sent = Vec::new();
        for k in 1..10 {
            if let Some(MavMessage::COMMAND_LONG(c)) = r.poll(k * 100_000) {
                sent.push(c.param1);
                r.on_ack(&ack(MavResult::MAV_RESULT_ACCEPTED));
            }
        }
        assert!(!sent.contains(&230.0), "{sent:?}");
        assert!(r.requests.iter().all(|q| q.message_id != 230 || q.rate_hz > 0.0), "dropped: {:?}", r.requests);
    }

    #[test]
    fn rate_requests_go_one_at_a_time_and_end_accepted_refused_or_unanswered() {
        let mut r = RateRequests::new(&profile(), 3);
        let Some(MavMessage::COMMAND_LONG(c)) = r.poll(0) else { panic!("a request") };
        assert_eq!((c.param1, c.param2, c.target_system, c.target_component), (105.0, 5000.0, 3, 1));
        // nothing else while it waits for its answer
        assert_eq!(r.poll(500_000), None);
        // an ack for another command is not ours
        let other = COMMAND_ACK_DATA { command: MavCmd::MAV_CMD_REQUEST_MESSAGE, ..Default::default() };
        assert_eq!(r.on_ack(&other), None);
        assert_eq!(r.on_ack(&ack(MavResult::MAV_RESULT_ACCEPTED)).unwrap().outcome, Some(RateOutcome::Accepted));
        // then the odometer; refused
        let Some(MavMessage::COMMAND_LONG(c)) = r.poll(600_000) else { panic!("the second request") };
        assert_eq!(c.param1, 331.0);
        assert_eq!(
            r.on_ack(&ack(MavResult::MAV_RESULT_DENIED)).unwrap().outcome,
            Some(RateOutcome::Refused(MavResult::MAV_RESULT_DENIED))
        );
        assert!(r.done());
        assert_eq!(r.poll(10_000_000), None);
    }

    #[test]
    fn an_autopilot_that_never_answers_gets_three_tries() {
        let mut r = RateRequests::new(&profile(), 1);
        let mut sent = 0;
        for k in 0..100 {
            if r.poll(k * 100_000).is_some() {
                sent += 1;
            }
        }
        assert_eq!(sent, 2 * MAX_TRIES, "three tries for each of the two");
        assert!(r.requests.iter().all(|q| q.outcome == Some(RateOutcome::Unanswered)));
    }

    /// ArduPilot refuses SET_MESSAGE_INTERVAL for WHEEL_DISTANCE (DENIED, as its SITL does): the
    /// node asks for the stream group that carries it (EXTRA1), three times a second apart, as
    /// REQUEST_DATA_STREAM has no answer.
    #[test]
    #[allow(deprecated)]
    fn a_refused_wheel_distance_is_asked_for_by_its_stream_group() {
        let mut p = VehicleProfile::from_toml_str(
            &std::fs::read_to_string(concat!(env!("CARGO_MANIFEST_DIR"), "/../../sitl/vehicles/ardupilot-rover.toml")).unwrap(),
        )
        .unwrap();
        p.inputs.request_rates = true;
        let mut r = RateRequests::new(&p, 2);
        let Some(MavMessage::COMMAND_LONG(c)) = r.poll(0) else { panic!() };
        assert_eq!(c.param1, 27.0);
        r.on_ack(&ack(MavResult::MAV_RESULT_ACCEPTED));
        let Some(MavMessage::COMMAND_LONG(c)) = r.poll(10) else { panic!() };
        assert_eq!(c.param1, 9000.0);
        let settled = r.on_ack(&ack(MavResult::MAV_RESULT_DENIED)).unwrap();
        assert_eq!(settled.stream_group, Some(("EXTRA1", 10, 0)));
        let mut sent = Vec::new();
        for k in 0..50u64 {
            if let Some(m) = r.poll(20 + k * 100_000) {
                sent.push((k, m));
            }
        }
        assert_eq!(sent.len() as u32, MAX_TRIES, "{sent:?}");
        assert_eq!(sent.iter().map(|(k, _)| *k).collect::<Vec<_>>(), [0, 10, 20]);
        let MavMessage::REQUEST_DATA_STREAM(q) = &sent[0].1 else { panic!("{:?}", sent[0]) };
        assert_eq!(
            (q.req_stream_id as u8, q.req_message_rate, q.start_stop, q.target_system, q.target_component),
            (10, 20, 1, 2, 1)
        );
        assert_eq!(r.requests[1].stream_group, Some(("EXTRA1", 10, MAX_TRIES)));
        // a message without a stream group (PX4's HIGHRES_IMU) is only refused
        assert_eq!(ardupilot_stream_group(105), None);
        assert_eq!(ardupilot_stream_group(27), Some(("RAW_SENSORS", 1)));
    }

    fn timesync_answer(ts1: i64, tc1: i64) -> TIMESYNC_DATA {
        TIMESYNC_DATA { tc1, ts1, target_system: 1, target_component: 191 }
    }

    /// The mapping is the middle of the round trip of the quickest answer in the window; foreign,
    /// late and negative answers are refused; the autopilot's own requests are answered.
    #[test]
    fn timesync_maps_the_boot_clock_by_the_quickest_answer() {
        let mut ts = TimeSync::default();
        let unix = 1_795_000_000_000_000_000i64; // ns
        let boot_at = |u: i64| u - unix + 42_000_000_000; // the autopilot booted 42 s before `unix`
        // first request at once, the next 200 ms later while nothing is known
        let Some(MavMessage::TIMESYNC(q)) = ts.poll(0, unix, 1) else { panic!() };
        assert_eq!((q.tc1, q.ts1, q.target_system, q.target_component), (0, unix, 1, 1));
        assert_eq!(ts.poll(100_000, unix + 100_000_000, 1), None);
        // an answer after 2 ms whose way out took 1.5 ms: the autopilot stamped it at unix + 1.5 ms
        assert_eq!(
            ts.on_message(&timesync_answer(unix, boot_at(unix + 1_500_000)), unix + 2_000_000, (1, 1), None),
            TimesyncReply::Sample
        );
        let (offset, rtt) = ts.offset_us().unwrap();
        assert_eq!(rtt, 2_000);
        // wrong by half the difference of the two ways (0.5 ms)
        assert_eq!(offset, (unix - 42_000_000_000) / 1000 - 500);
        // a quicker one (0.2 ms, symmetric) wins; a slower one later does not
        let Some(MavMessage::TIMESYNC(q)) = ts.poll(200_000, unix + 200_000_000, 1) else { panic!() };
        ts.on_message(&timesync_answer(q.ts1, boot_at(q.ts1 + 100_000)), q.ts1 + 200_000, (1, 1), None);
        let Some(MavMessage::TIMESYNC(q)) = ts.poll(1_200_000, unix + 1_200_000_000, 1) else { panic!() };
        ts.on_message(&timesync_answer(q.ts1, boot_at(q.ts1 + 4_000_000)), q.ts1 + 9_000_000, (1, 1), None);
        assert_eq!(ts.offset_us().unwrap(), ((unix - 42_000_000_000) / 1000, 200));
        // not ours, answered twice, too slow, negative: refused
        assert_eq!(ts.on_message(&timesync_answer(unix + 5, 77), unix + 10, (1, 1), None), TimesyncReply::Nothing);
        assert_eq!(ts.on_message(&timesync_answer(q.ts1, 1), q.ts1 + 10, (1, 1), None), TimesyncReply::Nothing);
        let Some(MavMessage::TIMESYNC(q)) = ts.poll(2_200_000, unix + 2_200_000_000, 1) else { panic!() };
        assert_eq!(ts.on_message(&timesync_answer(q.ts1, 5), q.ts1 + 900_000_000, (1, 1), None), TimesyncReply::Nothing);
        let Some(MavMessage::TIMESYNC(q)) = ts.poll(3_200_000, unix + 3_200_000_000, 1) else { panic!() };
        assert_eq!(ts.on_message(&timesync_answer(q.ts1, -5), q.ts1 + 1000, (1, 1), None), TimesyncReply::Nothing);
        assert_eq!(ts.refused, 4);
        // the autopilot's own request: unanswered while no mapping is in use, then answered in
        // its own boot clock by that mapping (the clock the node stamps ODOMETRY in), its ts1
        // echoed, addressed to it
        assert_eq!(ts.on_message(&timesync_answer(99, 0), unix + 7, (1, 1), None), TimesyncReply::Nothing);
        let offset_us = (unix - 42_000_000_000) / 1000;
        let TimesyncReply::Answer(a) = ts.on_message(&timesync_answer(99, 0), unix + 7, (1, 1), Some(offset_us)) else {
            panic!()
        };
        assert_eq!((a.tc1, a.ts1, a.target_system, a.target_component), (boot_at(unix + 7), 99, 1, 1));
        // a reboot forgets every answer
        ts.reset();
        assert_eq!(ts.offset_us(), None);
    }

    /// An autopilot whose clock runs at `rate` times the companion's (PX4's SIH ran at 0.992),
    /// asked once a second for 120 s, answering after delays of 0.2-20 ms each way (one in eight
    /// held 100 ms more, as by a busy loop): the worst error of the mapping at each answer, from
    /// the 16th on (ns), and the last rate fitted.
    fn mapping_error(rate: f64) -> (i64, i64, Option<f64>) {
        let mut ts = TimeSync::default();
        let c0 = 1_795_000_000_000_000_000i64;
        let boot = |c: i64| ((c - c0) as f64 * rate) as i64 + 42_000_000_000;
        let mut lcg = 12345u64;
        let mut delay = || {
            lcg = lcg.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
            let u = (lcg >> 33) as f64 / (1u64 << 31) as f64;
            let spike = if (lcg >> 20).is_multiple_of(8) { 100_000_000 } else { 0 };
            200_000 + (u * 19_800_000.0) as i64 + spike
        };
        let (mut worst_fit, mut worst_quickest) = (0i64, 0i64);
        for k in 0..120i64 {
            let c = c0 + k * 1_000_000_000;
            let Some(MavMessage::TIMESYNC(q)) = ts.poll((k as u64) * 1_000_000, c, 1) else { panic!("no request at {k} s") };
            let (out, back) = (delay(), delay());
            assert_eq!(
                ts.on_message(&timesync_answer(q.ts1, boot(c + out)), c + out + back, (1, 1), None),
                TimesyncReply::Sample
            );
            let mid = c + (out + back) / 2;
            let truth = mid - boot(mid);
            let (offset_us, _) = ts.offset_us().unwrap();
            // (the mapping before: the quickest of the last 16 answers, as it was)
            let quickest = ts.answers.iter().rev().take(TIMESYNC_WINDOW).min_by_key(|a| a.0).unwrap().1;
            if k >= 16 {
                worst_fit = worst_fit.max((offset_us * 1000 - truth).abs());
                worst_quickest = worst_quickest.max((quickest - truth).abs());
            }
        }
        (worst_fit, worst_quickest, ts.rate_fit().map(|(_, r)| r))
    }

    /// The mapping follows a rate difference between the two clocks: with SIH's 0.8% it stays
    /// within a millisecond where the quickest answer alone was off by tens of milliseconds
    /// (past the 25-50 ms at which a team's epochs split); with equal rates it is as good as the
    /// quickest answer (half its round trip).
    #[test]
    fn timesync_follows_a_clock_that_runs_at_another_rate() {
        let (fit, quickest, rate) = mapping_error(0.992);
        eprintln!("rate 0.992: worst {fit} ns, the quickest answer alone {quickest} ns, rate {rate:?}");
        assert!((rate.unwrap() - 0.008).abs() < 1e-4, "rate {rate:?}");
        assert!(fit < 5_000_000, "the mapping was off by {fit} ns");
        assert!(quickest > 20_000_000, "the quickest answer alone was off by only {quickest} ns");
        // crystals 20 ppm apart: no rate told apart from the answers' noise, the quickest answer
        let (fit, quickest, rate) = mapping_error(1.0 + 20e-6);
        eprintln!("rate 1.00002: worst {fit} ns, the quickest answer alone {quickest} ns, rate {rate:?}");
        assert_eq!(rate, None);
        assert!(fit <= quickest + 1000, "{fit} / {quickest} ns");
        // (neither clock wanders: asked once a second)
        let mut steady = TimeSync::default();
        for k in 0..20u64 {
            let c = 1_795_000_000_000_000_000i64 + (k as i64) * 1_000_000_000;
            let Some(MavMessage::TIMESYNC(q)) = steady.poll(k * 1_000_000, c, 1) else { panic!() };
            steady.on_message(&timesync_answer(q.ts1, c + 300_000 - 1_000_000_000), c + 500_000, (1, 1), None);
        }
        assert!(!steady.wanders());
        assert!(steady.poll(19_000_000 + TIMESYNC_FAST_US, 0, 1).is_none());
        // too few quick answers, or a span too short: no fit, the quickest answer
        let mut ts = TimeSync::default();
        let Some(MavMessage::TIMESYNC(q)) = ts.poll(0, 5_000_000_000, 1) else { panic!() };
        ts.on_message(&timesync_answer(q.ts1, 7), q.ts1 + 1_000_000, (1, 1), None);
        assert_eq!(ts.rate_fit(), None);
        assert_eq!(ts.offset_us(), Some(((q.ts1 + 500_000 - 7) / 1000, 1000)));
    }

    /// A clock that wanders, as PX4's SIH did under its lockstep (1.6% slow on average, its
    /// offset a random walk of about 15 ms a second on top), over a quick link (0.1-2 ms round
    /// trips): the mapping a second after each answer (what the node uses until the next one),
    /// against the next answer's offset. The quickest answer of 16 moved on at the rate is up to
    /// 16 s old; the one chosen for its round trip and age is recent.
    #[test]
    fn timesync_prefers_a_recent_answer_when_the_clock_wanders() {
        let mut lcg = 99u64;
        let mut uniform = || {
            lcg = lcg.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
            (lcg >> 11) as f64 / (1u64 << 53) as f64
        };
        let c0 = 1_795_000_000_000_000_000i64;
        let (mut ts, mut walk) = (TimeSync::default(), 0.0f64);
        let (mut chosen, mut quickest) = (Vec::new(), Vec::new());
        for k in 0..150i64 {
            let c = c0 + k * 1_000_000_000;
            walk += 15e6 * ((0..12).map(|_| uniform()).sum::<f64>() - 6.0); // N(0, 15 ms)
            let boot = |at: i64| ((at - c0) as f64 * 0.984 + walk) as i64 + 42_000_000_000;
            let (out, back) = ((100_000.0 + uniform() * 900_000.0) as i64, (100_000.0 + uniform() * 900_000.0) as i64);
            let truth = c + out - boot(c + out);
            if k >= 20 {
                let (offset_us, _) = ts.offset_at_us(c + out).unwrap();
                chosen.push((offset_us * 1000 - truth) as f64);
                let recent = ts.answers.iter().rev().take(TIMESYNC_WINDOW);
                let q = recent.min_by_key(|a| a.0).unwrap();
                let rate = ts.rate_fit().map_or(0.0, |(_, r)| r);
                quickest.push(q.1 as f64 + rate * (c + out - q.2) as f64 - truth as f64);
            }
            let Some(MavMessage::TIMESYNC(q)) = ts.poll((k as u64) * 1_000_000, c, 1) else { panic!() };
            ts.on_message(&timesync_answer(q.ts1, boot(c + out)), c + out + back, (1, 1), None);
        }
        let rms = |v: &[f64]| (v.iter().map(|e| e * e).sum::<f64>() / v.len() as f64).sqrt() / 1e6;
        eprintln!(
            "a wandering clock, a second ahead: {:.1} ms RMS, the quickest answer moved on {:.1} ms",
            rms(&chosen),
            rms(&quickest)
        );
        // a second of the walk (15 ms) is what any mapping a second old is off, at least
        assert!(rms(&chosen) < 1.2 * 15.0, "{} ms", rms(&chosen));
        assert!(rms(&quickest) > 1.5 * rms(&chosen), "{} against {} ms", rms(&chosen), rms(&quickest));
        // and it is asked five times a second
        assert!(ts.wanders());
        assert!(ts.poll(149_000_000 + TIMESYNC_FAST_US, c0, 1).is_some());
    }

    fn nav(t: u64, n: f64) -> Navigation {
        Navigation {
            t: TimeUs(t),
            position_ned_m: Vector3::new(n, 0.0, 0.0),
            velocity_ned_m_s: Vector3::new(10.0, 0.0, 0.0),
            attitude_frd_to_ned: UnitQuaternion::from_euler_angles(0.0, 0.0, 0.5),
            pose_covariance: Matrix6::identity() * 0.01,
            velocity_covariance_ned: Matrix3::identity() * 0.04,
        }
    }

    #[test]
    fn odometry_goes_out_at_its_rate_in_the_frames_autopilots_fuse() {
        let mut o = OdometryOutput::new(20.0, crate::node::profile::OdometryFrame::LocalFrd).unwrap();
        let mut times = Vec::new();
        // a 200 Hz filter for one second
        for k in 0..200u64 {
            let t = 1_000_000 + k * 5_000;
            if let Some(MavMessage::ODOMETRY(m)) = o.poll(&nav(t, 10.0 * k as f64 * 0.005), |t| t.0 - 1_000_000) {
                assert_eq!(m.frame_id, MavFrame::MAV_FRAME_LOCAL_FRD);
                assert_eq!(m.child_frame_id, MavFrame::MAV_FRAME_BODY_FRD);
                // body velocity: 10 m/s north seen from a vehicle heading 0.5 rad
                assert!((m.vx - 10.0 * 0.5f32.cos()).abs() < 1e-4 && (m.vy + 10.0 * 0.5f32.sin()).abs() < 1e-4);
                assert!((m.pose_covariance[0] - 0.01).abs() < 1e-7 && (m.pose_covariance[20] - 0.01).abs() < 1e-7);
                assert!((m.velocity_covariance[0] - 0.04).abs() < 1e-7 && m.velocity_covariance[15].is_nan());
                assert_eq!(m.reset_counter, 0);
                times.push(m.time_usec);
            }
        }
        assert_eq!(times.len(), 20);
        assert!(times.windows(2).all(|w| w[1] - w[0] == 50_000), "{times:?}");
        // PX4's profile names the same axes LOCAL_NED (EKF2 takes LOCAL_FRD as unknown heading)
        let mut px4 = OdometryOutput::new(20.0, crate::node::profile::OdometryFrame::LocalNed).unwrap();
        let Some(MavMessage::ODOMETRY(m)) = px4.poll(&nav(1_000_000, 0.0), |t| t.0) else { panic!() };
        assert_eq!((m.frame_id, m.child_frame_id), (MavFrame::MAV_FRAME_LOCAL_NED, MavFrame::MAV_FRAME_BODY_FRD));
        assert_eq!(times[0], 0, "stamped in the vehicle's clock");
        // a 40 m correction is a reset, not motion
        let Some(MavMessage::ODOMETRY(m)) = o.poll(&nav(2_000_000, 50.0), |t| t.0) else { panic!() };
        assert_eq!(m.reset_counter, 1);
    }

    #[test]
    fn gps_input_carries_the_position_about_the_origin_its_accuracy_and_gps_time() {
        use crate::protocol::wire::GeoOrigin;
        let origin = GeoOrigin { lat_deg: -35.363262, lon_deg: 149.165237, alt_m: 584.0 };
        let mut g = GpsInputOutput::new(5.0, Some(origin)).unwrap();
        let unix = 1_795_000_000_000_000u64;
        let mut n = nav(unix, 111.0);
        n.pose_covariance[(0, 0)] = 4.0; // 2 m north sigma, 0.1 m east
        let Some(MavMessage::GPS_INPUT(m)) = g.poll(&n, |t| t.0 - unix + 60_000_000) else { panic!() };
        assert_eq!(m.time_usec, 60_000_000);
        let back = crate::protocol::wire::geodetic_to_ned(
            &origin,
            &crate::protocol::wire::Geodetic {
                lat_deg: crate::protocol::wire::e7_to_deg(m.lat),
                lon_deg: crate::protocol::wire::e7_to_deg(m.lon),
                alt_m: f64::from(m.alt),
            },
        );
        assert!((back - n.position_ned_m).norm() < 0.02, "{back}");
        assert!((m.horiz_accuracy - 2.0).abs() < 1e-6 && (m.vert_accuracy - 0.1).abs() < 1e-6);
        assert_eq!(m.fix_type, crate::protocol::dialect::cooploc::GpsFixType::GPS_FIX_TYPE_3D_FIX);
        // 2026-11-18 11:06:40 UTC: 397 weeks after the week-2048 rollover of 2019-04-07
        assert_eq!(m.time_week, 2445);
        assert_eq!(m.time_week_ms, 299_218_000, "Wednesday 11:06:58 GPS time (18 leap seconds ahead of UTC)");
        assert_eq!(m.yaw, (0.5f64.to_degrees() * 100.0).round() as u16);
        // at 5 Hz: the next one 200 ms on
        assert!(g.poll(&nav(unix + 100_000, 112.0), |t| t.0).is_none());
        assert!(g.poll(&nav(unix + 200_000, 113.0), |t| t.0).is_some());
        // a team clock that is not Unix time gives no GPS time
        let mut g = GpsInputOutput::new(5.0, Some(origin)).unwrap();
        let Some(MavMessage::GPS_INPUT(m)) = g.poll(&nav(5_000_000, 0.0), |t| t.0) else { panic!() };
        assert_eq!((m.time_week, m.time_week_ms), (0, 0));
    }

    const TEAM_ORIGIN: crate::protocol::wire::GeoOrigin =
        crate::protocol::wire::GeoOrigin { lat_deg: -35.363261, lon_deg: 149.16523, alt_m: 584.0 };

    fn is_origin_question(m: &Option<MavMessage>) -> bool {
        matches!(m, Some(MavMessage::COMMAND_LONG(c)) if c.command == MavCmd::MAV_CMD_REQUEST_MESSAGE && c.param1 == 49.0 && c.target_system == 7)
    }

    #[test]
    #[allow(deprecated)]
    fn an_autopilot_without_an_origin_is_given_the_teams() {
        let mut o = OriginOffer::new(Some(TEAM_ORIGIN), 7).unwrap();
        // asks first, and again every 2 s
        assert!(is_origin_question(&o.poll(1_000)));
        assert!(o.poll(1_500_000).is_none());
        assert!(is_origin_question(&o.poll(3_000_000)));
        assert!(o.poll(4_000_000).is_none());
        // no answer 5 s after the first question: the team's origin, in degE7 and mm
        let Some(MavMessage::SET_GPS_GLOBAL_ORIGIN(m)) = o.poll(5_001_000) else { panic!("SET_GPS_GLOBAL_ORIGIN") };
        assert_eq!((m.latitude, m.longitude, m.altitude, m.target_system), (-353632610, 1491652300, 584000, 7));
        assert_eq!(o.sets, 1);
        // then asks whether it took, sooner than before
        assert!(is_origin_question(&o.poll(6_001_000)));
        assert!(o.poll(7_000_000).is_none());
        // unheeded: sent again 5 s on
        assert!(matches!(o.poll(10_001_000), Some(MavMessage::SET_GPS_GLOBAL_ORIGIN(_))));
        // the autopilot reports it (within a degE7 rounding): settled, silent from then on
        assert!(o.on_origin(crate::protocol::wire::GeoOrigin { lat_deg: -35.3632610, lon_deg: 149.1652300, alt_m: 584.0 }));
        assert!(o.settled.is_some_and(|(_, ours)| ours));
        for t in (10_002_000..60_000_000).step_by(500_000) {
            assert!(o.poll(t).is_none(), "{t}");
        }
    }

    #[test]
    #[allow(deprecated)]
    fn no_origin_is_given_to_an_ekf_that_has_not_initialised() {
        let mut o = OriginOffer::new(Some(TEAM_ORIGIN), 7).unwrap();
        assert!(is_origin_question(&o.poll(0)));
        // ArduPilot's EKF says it is uninitialised: questions only
        o.on_ekf_status(0x0400);
        for t in (1_000_000..20_000_000).step_by(100_000) {
            let m = o.poll(t);
            assert!(m.is_none() || is_origin_question(&m), "{t}: {m:?}");
        }
        assert_eq!(o.sets, 0);
        // initialised (attitude, velocities, ...): given at once
        o.on_ekf_status(0x00a7);
        assert!(matches!(o.poll(20_000_000), Some(MavMessage::SET_GPS_GLOBAL_ORIGIN(_))));
    }

    #[test]
    fn an_origin_the_autopilot_has_is_never_overwritten() {
        let mut o = OriginOffer::new(Some(TEAM_ORIGIN), 7).unwrap();
        assert!(is_origin_question(&o.poll(0)));
        // its own GNSS origin, 100 m east of the team's, answers the question
        let theirs = crate::protocol::wire::GeoOrigin { lat_deg: -35.363261, lon_deg: 149.16633, alt_m: 584.0 };
        assert!(!o.on_origin(theirs));
        for t in (0..60_000_000).step_by(250_000) {
            assert!(o.poll(t).is_none(), "{t}");
        }
        // and a node without a team origin offers none
        assert!(OriginOffer::new(None, 7).is_none());
    }

    #[test]
    #[allow(deprecated)]
    fn an_autopilot_that_never_takes_the_origin_is_left_alone_after_a_few_tries() {
        let mut o = OriginOffer::new(Some(TEAM_ORIGIN), 7).unwrap();
        let mut sets = 0;
        let mut questions = 0;
        for t in (0..120_000_000u64).step_by(100_000) {
            match o.poll(t) {
                Some(MavMessage::SET_GPS_GLOBAL_ORIGIN(_)) => sets += 1,
                m if is_origin_question(&m) => questions += 1,
                None => {}
                Some(other) => panic!("{other:?}"),
            }
        }
        assert_eq!(sets, ORIGIN_MAX_SETS);
        assert!(o.gave_up);
        // about 30 s of questions (every 2 s, with one sooner after each set), then silence
        assert!((12..=20).contains(&questions), "{questions}");
    }
}
