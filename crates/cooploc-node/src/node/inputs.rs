//! What an autopilot sends, as the node core's inputs: a sans-io decoder, driven by the vehicle
//! profile's `[inputs]` (see [`super::profile`]). The runner and `cooploc replay` both feed it
//! every frame from the vehicle, so a log replays through exactly the same conversions.
//!
//! - **IMU**: HIGHRES_IMU (its `id` must be the profile's `imu_id`; a message whose
//!   `fields_updated` does not mark the accelerometer and gyro fresh is a repeat and skipped),
//!   RAW_IMU (`id` too), SCALED_IMU, SCALED_IMU2, SCALED_IMU3 (int16 mG and mrad/s, converted in
//!   [`crate::protocol::wire`]). The core takes the mean over each interval: an *average* sample
//!   (PX4) is that already; two consecutive *instantaneous* samples (ArduPilot) are averaged
//!   (trapezoid), and a sample after a gap of more than [`MAX_TRAPEZOID_GAP_US`] is held over
//!   the gap. The rate actually arriving is measured; a change of more than a quarter is
//!   counted (the filter takes samples at any spacing).
//! - **Odometer**: ODOMETRY with a body-frame velocity, unless its estimator_type says it is the
//!   autopilot's own EKF output (refused: not a measurement); or WHEEL_DISTANCE, differentiated:
//!   the mean speed of the wheels over the interval between two messages, stamped at its
//!   middle, and with two wheels the differential-drive yaw rate. A wheel that runs backwards
//!   further or faster than a vehicle can, or a change of `count`, is a counter reset: counted,
//!   and the next interval starts from the new reading.
//! - **Wheels as the drive** (a planar robot, [`VehicleInputs::wheel_drive`]): each
//!   WHEEL_DISTANCE interval of the left and right wheel is a [`WheelSample`] (mean speed and
//!   yaw rate) stamped at the interval's *end*, the sample that carries the filter through it;
//!   IMU messages are counted and ignored, unless the profile says `yaw_rate = "gyro"`: then the
//!   IMU's z rate, averaged over each wheel interval, is its yaw rate (an interval waits up to
//!   [`MAX_GYRO_WAIT_US`] of wheel time for the gyro samples that cover it, then takes the
//!   wheels' own; an autopilot reboot drops what was waiting).
//! - **Time**: `time_boot_ms` (u32 milliseconds, wrapping after 49.7 days: unwrapped),
//!   `time_usec` since boot, and `time_usec` in Unix time (from 2001 on) alike. With a mapped
//!   team clock, stamps since boot are mapped to the team's Unix time: by the vehicle's
//!   SYSTEM_TIME (`clock = "unix"`; an autopilot without GNSS sends `time_unix_usec` 0 and gives
//!   no mapping), by the companion's clock through TIMESYNC ([`VehicleInputs::set_companion_offset`],
//!   measured by the runner, `clock = "companion"`), or by the first of the two that the
//!   autopilot supports (`clock = "auto"`: TIMESYNC, else SYSTEM_TIME after
//!   [`AUTO_CLOCK_WAIT_US`]). Until a mapping is known inputs are held, up to 10 s of them; a
//!   boot clock that goes back more than a second (three stamps in a row) is an autopilot
//!   reboot, and the mapping is taken again. With `epoch_grid_ms`, the vehicle's ranges are put
//!   on the nearest grid instant of the team's clock (two nodes' mappings differ a little; the
//!   grid makes them name an epoch by the same instant). [`VehicleInputs::to_vehicle_time`]
//!   maps back, for what the node sends.
//! - **Origin**: GPS_GLOBAL_ORIGIN, else HOME_POSITION, when the profile gives none.
//! - **GNSS fixes** (only once [`VehicleInputs::fuse_gnss`] gave the team's origin: the hand-over,
//!   `super::handover`): GPS_RAW_INT with a 3D fix, its position about the origin with the
//!   receiver's accuracy ([`wire::position_fix_from_gps_raw`]), stamped `time_usec` (the
//!   autopilot's boot clock when it received the fix) less the profile's `gnss_lag_ms`; a
//!   repeat of the fix last taken (same stamp) is dropped. A fix stamp is only looked at: it
//!   takes no part in the wrap and reboot detection, and a fix before the team clock is
//!   mapped, or more than [`MAX_FIX_AGE_US`] older than the newest stamp (a fix stamped in Unix
//!   time: than the newest stamp in the team's clock), is dropped (counted).

use nalgebra::Vector3;

use super::core::NodeInput;
use std::collections::VecDeque;

use super::profile::{ImuMessage, Inputs, OdometerMessage, SampleKind, TeamClock, YawRateSource};
use crate::estimation::{ImuSample, OdometerSample, PositionFixSample, WheelSample};
use crate::protocol::MavMessage;
use crate::protocol::dialect::cooploc::{COMMAND_ACK_DATA, MavEstimatorType};
use crate::protocol::wire::{self, GeoOrigin};
use crate::time::TimeUs;

/// Time stamps from this many microseconds on are Unix time (2001-09-09); below, time since boot.
pub const UNIX_TIME_FROM_US: u64 = 1_000_000_000_000_000;
/// Two instantaneous IMU samples further apart than this are not averaged.
pub const MAX_TRAPEZOID_GAP_US: u64 = 100_000;
/// A boot clock going back more than this, in [`REBOOT_CONFIRMATIONS`] stamps in a row, is a
/// reboot (less: a late or reordered frame).
const REBOOT_BACKSTEP_US: u64 = 1_000_000;
/// Half the range of a `time_boot_ms` stamp: a step back by more is a wrap, ahead by more a
/// frame from before the last wrap.
const HALF_WRAP_MS: u32 = 1 << 31;
const REBOOT_CONFIRMATIONS: u32 = 3;
/// Inputs stamped since boot are held this long (vehicle time) for a mapping to the team clock.
pub const MAX_HELD_US: u64 = 10_000_000;
/// With `clock = "auto"`, held inputs spanning this long (vehicle time) without a TIMESYNC
/// answer take SYSTEM_TIME's Unix time, when the autopilot has it.
pub const AUTO_CLOCK_WAIT_US: u64 = 3_000_000;
/// A GNSS fix stamped this much before the newest stamp of the vehicle is dropped, us.
pub const MAX_FIX_AGE_US: u64 = 2_000_000;
/// Two mappings of the boot clock further apart than this disagree (counted).
const CLOCK_DISAGREEMENT_US: i64 = 50_000;

/// Where the mapping from the vehicle's boot clock to the team's clock came from.
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum ClockSource {
    /// The autopilot's SYSTEM_TIME (its Unix time, from GNSS).
    SystemTime,
    /// The companion's clock, through TIMESYNC.
    Timesync,
}
/// Fastest a land vehicle's wheel turns, m/s (a faster change of a wheel's distance is a reset).
const MAX_WHEEL_SPEED_M_S: f64 = 60.0;
/// WHEEL_DISTANCE messages further apart than this give no speed (the interval restarts).
const MAX_WHEEL_INTERVAL_US: u64 = 1_100_000;

/// What one vehicle message meant.
#[derive(Debug, Clone, PartialEq)]
pub enum VehicleEvent {
    /// A sample or a range for the core.
    Input(NodeInput),
    /// The vehicle's origin (GPS_GLOBAL_ORIGIN or HOME_POSITION).
    Origin(GeoOrigin),
    /// A command acknowledgement for the node.
    Ack(COMMAND_ACK_DATA),
    /// Counted and dropped (the counters say why), or not an input at all.
    Nothing,
}

/// Counters of what the decoder used, bridged and refused.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct InputCounters {
    pub imu: u64,
    /// IMU messages of another IMU instance or another message than the profile's.
    pub imu_other: u64,
    /// HIGHRES_IMU whose `fields_updated` does not mark the accelerometer and gyro fresh.
    pub imu_not_updated: u64,
    /// IMU messages with unusable values (non-finite, saturated, implausible).
    pub imu_invalid: u64,
    /// IMU samples not after the previous one (duplicates, reordered frames).
    pub imu_out_of_order: u64,
    /// Times the arriving IMU rate changed by more than a quarter.
    pub imu_rate_changes: u64,
    pub odometer: u64,
    /// ODOMETRY that is the autopilot's own estimate (estimator_type AUTOPILOT), refused.
    pub odometry_from_autopilot: u64,
    pub odometer_invalid: u64,
    /// Wheel distance counters reset (or implausible jumps), bridged.
    pub wheel_resets: u64,
    /// WHEEL_DISTANCE intervals too long to give a speed.
    pub wheel_gaps: u64,
    pub ranges: u64,
    pub ranges_invalid: u64,
    /// `time_boot_ms` wraps (every 49.7 days of uptime).
    pub time_wraps: u64,
    /// Autopilot reboots (its boot clock went back, and stayed back).
    pub reboots: u64,
    /// Stamps more than a second behind the boot clock, not (yet) a reboot: dropped.
    pub stale_stamps: u64,
    /// Inputs dropped because no mapping gave the team clock within [`MAX_HELD_US`] (they are
    /// held until then).
    pub waiting_for_clock: u64,
    /// SYSTEM_TIME messages whose mapping disagrees with the one in use by more than 50 ms
    /// (with the companion's clock in use: the companion's clock and the autopilot's GNSS
    /// time disagree; is the companion's clock synchronised?).
    pub clock_disagreements: u64,
    /// SYSTEM_TIME messages without Unix time (`time_unix_usec` 0: an autopilot that never had
    /// GNSS).
    pub system_time_without_unix: u64,
    /// Range stamps moved to the epoch grid by more than a quarter of it (mappings that do
    /// not agree well enough for the grid).
    pub ranges_off_grid: u64,
    /// GNSS fixes decoded (with [`VehicleInputs::fuse_gnss`]).
    pub gnss_fixes: u64,
    /// GPS_RAW_INT with a 3D fix refused: no position or accuracy, far from the origin.
    pub gnss_invalid: u64,
    /// GNSS fixes dropped: before the team clock was mapped, or older than [`MAX_FIX_AGE_US`].
    pub gnss_stale: u64,
    /// GPS_RAW_INT repeating a fix already taken (its stamp not after the last one's: an
    /// autopilot that streams the message faster than its receiver's rate).
    pub gnss_repeats: u64,
    /// A planar robot's wheel intervals the yaw-rate gyro did not cover within
    /// [`MAX_GYRO_WAIT_US`]: the wheels' own yaw rate taken (two wheels), or the sample dropped.
    pub gyro_missing: u64,
}

/// Most gyro samples kept (10 s at 200 Hz).
const MAX_GYRO_KEPT: usize = 2000;
/// Most wheel intervals waiting for the gyro (whatever their stamps say).
const MAX_PENDING_WHEELS: usize = 64;

/// How long (vehicle time, by the wheels' stamps) a wheel interval waits for the gyro samples
/// that cover it.
pub const MAX_GYRO_WAIT_US: u64 = 500_000;

/// The decoder (see the module documentation).
#[derive(Debug, Clone)]
pub struct VehicleInputs {
    cfg: Inputs,
    /// The highest `time_boot_ms` seen and the wraps before it.
    boot_ms: Option<(u32, u64)>,
    /// The latest boot-clock stamp, us (reboot detection).
    last_boot_us: Option<u64>,
    /// Consecutive stamps far behind `last_boot_us`.
    backsteps: u32,
    /// Inputs stamped since boot waiting for the team clock (vehicle time, in order).
    held: Vec<VehicleEvent>,
    /// Team time minus boot time, us: the mapping in use.
    unix_offset_us: Option<i64>,
    /// Where the mapping in use came from.
    clock_source: Option<ClockSource>,
    /// The mapping SYSTEM_TIME gives (Unix time minus boot time, us), when it has Unix time.
    system_time_offset_us: Option<i64>,
    /// The previous IMU sample (instantaneous reading), team time.
    prev_imu: Option<(TimeUs, Vector3<f64>, Vector3<f64>)>,
    /// Established IMU interval (us) and the intervals since it last changed.
    imu_interval: Option<f64>,
    recent_intervals: Vec<u64>,
    /// Previous WHEEL_DISTANCE reading: team time, count, distances of the profile's wheels.
    prev_wheels: Option<(TimeUs, u8, Vec<f64>)>,
    /// The yaw rate of the last differential-drive interval, rad/s (FRD: positive turns right).
    pub last_wheel_yaw_rate_rad_s: Option<f64>,
    /// The wheels drive the navigation (a planar robot): each WHEEL_DISTANCE interval is a
    /// [`WheelSample`] stamped at its end, not an odometer sample at its middle.
    wheel_drive: bool,
    /// With a yaw-rate gyro: its samples (end of interval, mean z rate over the interval since
    /// the previous one), vehicle clock, oldest first.
    gyro: VecDeque<(TimeUs, f64)>,
    /// Wheel intervals waiting for the gyro: start, and the sample (with the wheels' yaw rate,
    /// NaN for one wheel).
    pending_wheels: VecDeque<(TimeUs, WheelSample)>,
    /// Events released by the last message beside the one it returns (wheel samples the gyro
    /// now covers).
    released: Vec<VehicleEvent>,
    /// The team's origin, once GNSS fixes are to be taken ([`Self::fuse_gnss`]).
    gnss_origin: Option<GeoOrigin>,
    /// The stamp of the last GNSS fix taken (`time_usec` as sent), and the reboots counted then.
    last_fix: Option<(u64, u64)>,
    pub counters: InputCounters,
}

impl VehicleInputs {
    pub fn new(cfg: Inputs) -> Self {
        VehicleInputs {
            cfg,
            boot_ms: None,
            last_boot_us: None,
            backsteps: 0,
            held: Vec::new(),
            unix_offset_us: None,
            clock_source: None,
            system_time_offset_us: None,
            prev_imu: None,
            imu_interval: None,
            recent_intervals: Vec::new(),
            prev_wheels: None,
            last_wheel_yaw_rate_rad_s: None,
            wheel_drive: false,
            gyro: VecDeque::new(),
            pending_wheels: VecDeque::new(),
            released: Vec::new(),
            gnss_origin: None,
            last_fix: None,
            counters: InputCounters::default(),
        }
    }

    /// From now on GPS_RAW_INT fixes are inputs: positions about `origin`, the team's frame (see
    /// the module documentation).
    pub fn fuse_gnss(&mut self, origin: GeoOrigin) {
        self.gnss_origin = Some(origin);
    }

    /// A GPS_RAW_INT as a fix for the core, when fixes are taken.
    fn gnss_fix(&mut self, m: &crate::protocol::dialect::cooploc::GPS_RAW_INT_DATA) -> VehicleEvent {
        let Some(origin) = self.gnss_origin else { return VehicleEvent::Nothing };
        if (m.fix_type as u8) < super::handover::FIX_3D {
            return VehicleEvent::Nothing;
        }
        let fix = match wire::position_fix_from_gps_raw(m, &origin) {
            Ok(fix) => fix,
            Err(_) => {
                self.counters.gnss_invalid += 1;
                return VehicleEvent::Nothing;
            }
        };
        let reboots = self.counters.reboots;
        if self.last_fix.is_some_and(|(last, at)| m.time_usec <= last && at == reboots) {
            self.counters.gnss_repeats += 1;
            return VehicleEvent::Nothing;
        }
        let us = m.time_usec.saturating_sub(u64::from(self.cfg.gnss_lag_ms) * 1000);
        // A fix is held to its age against the newest boot-clock stamp: in that clock, or, when
        // it is stamped in Unix time, against that stamp in the team's clock.
        let newest_us = if us >= UNIX_TIME_FROM_US {
            self.last_boot_us.and_then(|b| self.team_of_boot_us(b)).map(|t| t.0)
        } else {
            self.last_boot_us
        };
        let stale = newest_us.is_some_and(|newest| us.saturating_add(MAX_FIX_AGE_US) < newest);
        let t = if us >= UNIX_TIME_FROM_US { Some(TimeUs(us)) } else { self.team_of_boot_us(us) };
        match t {
            Some(t) if !stale => {
                self.counters.gnss_fixes += 1;
                self.last_fix = Some((m.time_usec, reboots));
                VehicleEvent::Input(NodeInput::PositionFix(PositionFixSample { t, ..fix }))
            }
            _ => {
                self.counters.gnss_stale += 1;
                VehicleEvent::Nothing
            }
        }
    }

    /// A planar robot's decoder: its wheels drive the navigation (see [`WheelSample`]).
    pub fn wheel_drive(mut self) -> Self {
        self.wheel_drive = true;
        self
    }

    /// The arriving IMU rate, Hz, once established.
    pub fn imu_rate_hz(&self) -> Option<f64> {
        self.imu_interval.map(|us| 1e6 / us)
    }

    /// Decodes one message from the vehicle's system: what it means, in the team's clock, and
    /// the inputs held while the team clock was unknown once a SYSTEM_TIME gives it (in order).
    pub fn decode(&mut self, msg: &MavMessage) -> Vec<VehicleEvent> {
        let event = self.decode_local(msg);
        let mut out = Vec::new();
        if let Some(o) = self.unix_offset_us {
            out.extend(self.held.drain(..).filter_map(|e| map_event(e, o)));
        }
        let mut events = std::mem::take(&mut self.released);
        events.push(event);
        for event in events {
            match event {
                VehicleEvent::Nothing => {}
                e if self.cfg.clock != TeamClock::Vehicle && event_time(&e).is_some_and(|t| t.0 < UNIX_TIME_FROM_US) => {
                    match self.unix_offset_us {
                        Some(o) => out.extend(map_event(e, o)),
                        None => {
                            self.hold(e);
                            if let Some(o) = self.unix_offset_us {
                                // the wait for TIMESYNC is over: SYSTEM_TIME maps what was held
                                out.extend(self.held.drain(..).filter_map(|e| map_event(e, o)));
                            }
                        }
                    }
                }
                e => out.push(e),
            }
        }
        let grid_us = u64::from(self.cfg.epoch_grid_ms) * 1000;
        for e in &mut out {
            if let VehicleEvent::Input(NodeInput::OwnRange { range, .. }) = e {
                let (t, off) = snap_to_grid(range.t, grid_us);
                range.t = t;
                self.counters.ranges_off_grid += u64::from(off);
            }
        }
        out
    }

    /// Holds an input stamped since boot until a mapping says what team time that is (at most
    /// [`MAX_HELD_US`] of them: older ones are dropped and counted). With `clock = "auto"`, a
    /// wait of [`AUTO_CLOCK_WAIT_US`] without TIMESYNC takes SYSTEM_TIME's mapping, if any.
    fn hold(&mut self, e: VehicleEvent) {
        let newest = event_time(&e).map_or(0, |t| t.0);
        self.held.push(e);
        while self.held.first().and_then(event_time).is_some_and(|t| t.0 + MAX_HELD_US < newest) {
            self.held.remove(0);
            self.counters.waiting_for_clock += 1;
        }
        let waited = self.held.first().and_then(event_time).is_some_and(|t| t.0 + AUTO_CLOCK_WAIT_US <= newest);
        if self.cfg.clock == TeamClock::Auto
            && waited
            && let Some(o) = self.system_time_offset_us
        {
            self.unix_offset_us = Some(o);
            self.clock_source = Some(ClockSource::SystemTime);
        }
    }

    /// The companion's clock minus the vehicle's boot clock, us, as TIMESYNC measured it (the
    /// runner's [`super::autopilot::TimeSync`]): the mapping with `clock = "companion"` or
    /// `"auto"` (ignored with the other clocks). A later call replaces it (the two crystals
    /// drift apart by tens of microseconds a second); inputs held for a mapping go out with the
    /// next message.
    pub fn set_companion_offset(&mut self, offset_us: i64) {
        if !matches!(self.cfg.clock, TeamClock::Companion | TeamClock::Auto) || self.clock_source == Some(ClockSource::SystemTime)
        {
            return;
        }
        self.unix_offset_us = Some(offset_us);
        self.clock_source = Some(ClockSource::Timesync);
    }

    /// Where the mapping to the team's clock in use came from (None: none yet, or the team
    /// clock is the vehicles' own).
    pub fn clock_source(&self) -> Option<ClockSource> {
        self.clock_source
    }

    /// Team time minus the vehicle's boot time, us, in use.
    pub fn clock_offset_us(&self) -> Option<i64> {
        self.unix_offset_us
    }

    /// [`Self::decode`] in the vehicle's own clock.
    fn decode_local(&mut self, msg: &MavMessage) -> VehicleEvent {
        let imu_message = matches!(
            msg,
            MavMessage::HIGHRES_IMU(_)
                | MavMessage::RAW_IMU(_)
                | MavMessage::SCALED_IMU(_)
                | MavMessage::SCALED_IMU2(_)
                | MavMessage::SCALED_IMU3(_)
        );
        if self.wheel_drive && imu_message && self.cfg.yaw_rate != YawRateSource::Gyro {
            // a planar robot navigates on its wheels alone
            self.counters.imu_other += 1;
            return VehicleEvent::Nothing;
        }
        let event = self.decode_imu_and_wheels(msg);
        match event {
            VehicleEvent::Input(NodeInput::Imu(s)) if self.wheel_drive => {
                // a planar robot's yaw-rate gyro: its z rate gives the wheel intervals' yaw rate
                self.take_gyro(s.t, s.angular_rate_frd_rad_s[2]);
                VehicleEvent::Nothing
            }
            e => e,
        }
    }

    /// [`Self::decode_local`] before a planar robot's gyro takes the IMU samples.
    fn decode_imu_and_wheels(&mut self, msg: &MavMessage) -> VehicleEvent {
        match msg {
            MavMessage::SYSTEM_TIME(m) => {
                self.system_time(m.time_unix_usec, m.time_boot_ms);
                VehicleEvent::Nothing
            }
            MavMessage::HIGHRES_IMU(m) => {
                if self.cfg.imu != ImuMessage::HighresImu || m.id != self.cfg.imu_id {
                    self.counters.imu_other += 1;
                    return VehicleEvent::Nothing;
                }
                if m.fields_updated.bits() & wire::HIGHRES_ACCEL_GYRO_FIELDS != wire::HIGHRES_ACCEL_GYRO_FIELDS {
                    self.counters.imu_not_updated += 1;
                    return VehicleEvent::Nothing;
                }
                let Some(t) = self.usec(m.time_usec) else { return VehicleEvent::Nothing };
                match wire::imu_from_highres(m) {
                    Ok(s) => self.imu(ImuSample { t, ..s }),
                    Err(_) => self.imu_invalid(),
                }
            }
            MavMessage::RAW_IMU(m) => {
                if self.cfg.imu != ImuMessage::RawImu || m.id != self.cfg.imu_id {
                    self.counters.imu_other += 1;
                    return VehicleEvent::Nothing;
                }
                let Some(t) = self.usec(m.time_usec) else { return VehicleEvent::Nothing };
                self.int16_imu("RAW_IMU", t, [m.xacc, m.yacc, m.zacc], [m.xgyro, m.ygyro, m.zgyro])
            }
            MavMessage::SCALED_IMU(m) => {
                self.scaled(ImuMessage::ScaledImu, m.time_boot_ms, [m.xacc, m.yacc, m.zacc], [m.xgyro, m.ygyro, m.zgyro])
            }
            MavMessage::SCALED_IMU2(m) => {
                self.scaled(ImuMessage::ScaledImu2, m.time_boot_ms, [m.xacc, m.yacc, m.zacc], [m.xgyro, m.ygyro, m.zgyro])
            }
            MavMessage::SCALED_IMU3(m) => {
                self.scaled(ImuMessage::ScaledImu3, m.time_boot_ms, [m.xacc, m.yacc, m.zacc], [m.xgyro, m.ygyro, m.zgyro])
            }
            MavMessage::ODOMETRY(m) => {
                if self.cfg.odometer != OdometerMessage::Odometry {
                    return VehicleEvent::Nothing;
                }
                if m.estimator_type == MavEstimatorType::MAV_ESTIMATOR_TYPE_AUTOPILOT {
                    self.counters.odometry_from_autopilot += 1;
                    return VehicleEvent::Nothing;
                }
                let Some(t) = self.usec(m.time_usec) else { return VehicleEvent::Nothing };
                match wire::odometer_from_odometry(m) {
                    Ok(s) => {
                        self.counters.odometer += 1;
                        VehicleEvent::Input(NodeInput::Odometer(OdometerSample { t, ..s }))
                    }
                    Err(_) => {
                        self.counters.odometer_invalid += 1;
                        VehicleEvent::Nothing
                    }
                }
            }
            MavMessage::GPS_RAW_INT(m) => self.gnss_fix(m),
            MavMessage::WHEEL_DISTANCE(m) => {
                if self.cfg.odometer != OdometerMessage::WheelDistance {
                    return VehicleEvent::Nothing;
                }
                let Some(t) = self.usec(m.time_usec) else { return VehicleEvent::Nothing };
                match wire::wheel_distances(m, &self.cfg.wheels) {
                    Ok(d) => self.wheels(t, m.count, d),
                    Err(_) => {
                        self.counters.odometer_invalid += 1;
                        VehicleEvent::Nothing
                    }
                }
            }
            MavMessage::COOPLOC_RANGE(m) => match wire::range_from_message(m) {
                Ok((epoch, r)) => {
                    let Some(t) = self.usec(r.t.0) else { return VehicleEvent::Nothing };
                    self.counters.ranges += 1;
                    VehicleEvent::Input(NodeInput::OwnRange { epoch, range: crate::estimation::RangeSample { t, ..r } })
                }
                Err(_) => {
                    self.counters.ranges_invalid += 1;
                    VehicleEvent::Nothing
                }
            },
            MavMessage::GPS_GLOBAL_ORIGIN(m) => origin(m.latitude, m.longitude, m.altitude),
            MavMessage::HOME_POSITION(m) => origin(m.latitude, m.longitude, m.altitude),
            MavMessage::COMMAND_ACK(m) => VehicleEvent::Ack(m.clone()),
            _ => VehicleEvent::Nothing,
        }
    }

    fn scaled(&mut self, which: ImuMessage, time_boot_ms: u32, acc: [i16; 3], gyro: [i16; 3]) -> VehicleEvent {
        if self.cfg.imu != which {
            self.counters.imu_other += 1;
            return VehicleEvent::Nothing;
        }
        let Some(t) = self.boot_ms(time_boot_ms) else { return VehicleEvent::Nothing };
        self.int16_imu(which.name(), t, acc, gyro)
    }

    fn int16_imu(&mut self, name: &'static str, t: TimeUs, acc: [i16; 3], gyro: [i16; 3]) -> VehicleEvent {
        match wire::imu_from_int16(name, t, acc, gyro) {
            Ok(s) => self.imu(s),
            Err(_) => self.imu_invalid(),
        }
    }

    fn imu_invalid(&mut self) -> VehicleEvent {
        self.counters.imu_invalid += 1;
        VehicleEvent::Nothing
    }

    fn imu(&mut self, s: ImuSample) -> VehicleEvent {
        let prev = self.prev_imu;
        if let Some((t0, _, _)) = prev
            && s.t <= t0
        {
            self.counters.imu_out_of_order += 1;
            return VehicleEvent::Nothing;
        }
        self.prev_imu = Some((s.t, s.specific_force_frd_m_s2, s.angular_rate_frd_rad_s));
        if let Some((t0, _, _)) = prev {
            self.track_rate(s.t.0 - t0.0);
        }
        self.counters.imu += 1;
        let sample = match (self.cfg.samples(), prev) {
            (SampleKind::Instantaneous, Some((t0, f0, w0))) if s.t.0 - t0.0 <= MAX_TRAPEZOID_GAP_US => ImuSample {
                t: s.t,
                specific_force_frd_m_s2: (f0 + s.specific_force_frd_m_s2) * 0.5,
                angular_rate_frd_rad_s: (w0 + s.angular_rate_frd_rad_s) * 0.5,
            },
            _ => s,
        };
        VehicleEvent::Input(NodeInput::Imu(sample))
    }

    /// Keeps the established IMU interval; 20 consecutive intervals off it by more than a quarter
    /// establish a new one.
    fn track_rate(&mut self, dt_us: u64) {
        const WINDOW: usize = 20;
        let dt = dt_us as f64;
        match self.imu_interval {
            Some(est) if (dt - est).abs() <= 0.25 * est => self.recent_intervals.clear(),
            _ => {
                self.recent_intervals.push(dt_us);
                if self.recent_intervals.len() >= WINDOW {
                    let mut v = std::mem::take(&mut self.recent_intervals);
                    v.sort_unstable();
                    if self.imu_interval.is_some() {
                        self.counters.imu_rate_changes += 1;
                    }
                    self.imu_interval = Some(v[v.len() / 2] as f64);
                }
            }
        }
    }

    fn wheels(&mut self, t: TimeUs, count: u8, d: Vec<f64>) -> VehicleEvent {
        let Some((t0, count0, d0)) = self.prev_wheels.replace((t, count, d.clone())) else {
            return VehicleEvent::Nothing;
        };
        if t <= t0 {
            // a reordered or repeated message: keep the later reading
            self.prev_wheels = Some((t0, count0, d0));
            self.counters.odometer_invalid += 1;
            return VehicleEvent::Nothing;
        }
        let dt_us = t.0 - t0.0;
        if dt_us > MAX_WHEEL_INTERVAL_US {
            self.counters.wheel_gaps += 1;
            return VehicleEvent::Nothing;
        }
        let dt = dt_us as f64 * 1e-6;
        let deltas: Vec<f64> = d.iter().zip(&d0).map(|(a, b)| a - b).collect();
        if count != count0 || deltas.iter().any(|x| x.abs() > MAX_WHEEL_SPEED_M_S * dt + 0.05) {
            self.counters.wheel_resets += 1;
            return VehicleEvent::Nothing;
        }
        let speed = deltas.iter().sum::<f64>() / deltas.len() as f64 / dt;
        self.last_wheel_yaw_rate_rad_s = match (deltas.as_slice(), self.cfg.wheel_track_m) {
            ([left, right], Some(track)) => Some((left - right) / track / dt),
            _ => None,
        };
        if self.wheel_drive {
            let yaw_rate = self.last_wheel_yaw_rate_rad_s;
            let sample = WheelSample { t, speed_m_s: speed, yaw_rate_rad_s: yaw_rate.unwrap_or(f64::NAN) };
            if self.cfg.yaw_rate == YawRateSource::Gyro {
                self.counters.odometer += 1;
                self.pending_wheels.push_back((t0, sample));
                self.release_wheels();
                return VehicleEvent::Nothing;
            }
            if yaw_rate.is_none() {
                // the profile is checked to name two wheels and a track for a planar robot
                self.counters.odometer_invalid += 1;
                return VehicleEvent::Nothing;
            }
            self.counters.odometer += 1;
            return VehicleEvent::Input(NodeInput::Wheel(sample));
        }
        self.counters.odometer += 1;
        VehicleEvent::Input(NodeInput::Odometer(OdometerSample { t: TimeUs(t0.0 + dt_us / 2), speed_m_s: speed }))
    }

    /// A gyro sample: the mean z rate over the interval since the previous one, ending at `t`.
    fn take_gyro(&mut self, t: TimeUs, z_rad_s: f64) {
        if self.gyro.back().is_some_and(|(last, _)| t <= *last) {
            return; // counted as out of order by the IMU path already
        }
        self.gyro.push_back((t, z_rad_s));
        self.release_wheels();
    }

    /// The mean gyro z rate over `(a, b]`, if the gyro samples cover it.
    fn gyro_mean(&self, a: TimeUs, b: TimeUs) -> Option<f64> {
        let first = self.gyro.front()?.0;
        if first > a || self.gyro.back()?.0 < b || b <= a {
            return None;
        }
        let mut sum = 0.0;
        let mut start = first;
        for &(end, z) in self.gyro.iter().skip(1) {
            let (lo, hi) = (start.max(a), end.min(b));
            if hi > lo {
                sum += z * (hi.0 - lo.0) as f64;
            }
            start = end;
        }
        Some(sum / (b.0 - a.0) as f64)
    }

    /// Emits (into `released`) the pending wheel intervals the gyro now covers, in order; one
    /// the gyro has not covered while the wheels moved on by [`MAX_GYRO_WAIT_US`] takes the
    /// wheels' yaw rate (or is dropped with one wheel). Forgets the gyro samples no interval needs.
    fn release_wheels(&mut self) {
        let newest = self.pending_wheels.back().map(|(_, s)| s.t);
        while let Some(&(t0, sample)) = self.pending_wheels.front() {
            let waited_enough = newest.is_some_and(|n| n.0 >= sample.t.0 + MAX_GYRO_WAIT_US);
            let yaw_rate = match self.gyro_mean(t0, sample.t) {
                Some(z) => z,
                None if waited_enough || self.pending_wheels.len() > MAX_PENDING_WHEELS => {
                    self.counters.gyro_missing += 1;
                    sample.yaw_rate_rad_s
                }
                None => break,
            };
            self.pending_wheels.pop_front();
            if yaw_rate.is_finite() {
                let s = WheelSample { yaw_rate_rad_s: yaw_rate, ..sample };
                self.released.push(VehicleEvent::Input(NodeInput::Wheel(s)));
            }
        }
        let keep_from = self.pending_wheels.front().map_or(newest.unwrap_or(TimeUs(0)), |(t0, _)| *t0);
        while self.gyro.len() > 1 && self.gyro[1].0 <= keep_from {
            self.gyro.pop_front();
        }
        while self.gyro.len() > MAX_GYRO_KEPT {
            self.gyro.pop_front();
        }
    }

    fn system_time(&mut self, unix_us: u64, boot_ms: u32) {
        if unix_us < UNIX_TIME_FROM_US {
            self.counters.system_time_without_unix += 1;
            return; // the autopilot has no Unix time (no GNSS fix yet, or never)
        }
        let boot_us = self.unwrap_boot_ms(boot_ms);
        if !self.note_boot(boot_us) {
            return;
        }
        let offset = unix_us as i64 - boot_us as i64;
        self.system_time_offset_us = Some(offset);
        match self.unix_offset_us {
            None if self.cfg.clock == TeamClock::Unix => {
                self.unix_offset_us = Some(offset);
                self.clock_source = Some(ClockSource::SystemTime);
            }
            Some(o) if (o - offset).abs() > CLOCK_DISAGREEMENT_US => self.counters.clock_disagreements += 1,
            _ => {}
        }
    }

    /// A `time_usec` stamp in the team's clock.
    fn usec(&mut self, us: u64) -> Option<TimeUs> {
        if us >= UNIX_TIME_FROM_US {
            return Some(TimeUs(us));
        }
        self.boot_us(us)
    }

    /// A `time_boot_ms` stamp of the vehicle in the team's clock, once the clock is mapped (the
    /// boot clock itself when the team clock is the vehicle's; None while a Unix mapping is not
    /// known yet), taken in as a stamp of the vehicle's (wraps and reboots followed).
    pub fn team_time_of_boot_ms(&mut self, ms: u32) -> Option<TimeUs> {
        let t = self.boot_ms(ms)?;
        self.team_of_boot_us(t.0)
    }

    /// The same without taking the stamp in: no wrap counted, no reboot detected, nothing
    /// counted (for an estimate the node only looks at, whose stamp may lag its samples').
    pub fn peek_team_time_of_boot_ms(&self, ms: u32) -> Option<TimeUs> {
        self.team_of_boot_us(((self.wraps_of(ms) << 32) + u64::from(ms)) * 1000)
    }

    /// A stamp since boot (us) in the team's clock, by the mapping known.
    fn team_of_boot_us(&self, us: u64) -> Option<TimeUs> {
        match self.cfg.clock {
            TeamClock::Vehicle => Some(TimeUs(us)),
            _ => self.unix_offset_us.and_then(|o| u64::try_from(us as i64 + o).ok()).map(TimeUs),
        }
    }

    /// A `time_boot_ms` stamp in the team's clock.
    fn boot_ms(&mut self, ms: u32) -> Option<TimeUs> {
        let us = self.unwrap_boot_ms(ms);
        self.boot_us(us)
    }

    /// How many times the 32-bit ms clock had wrapped at stamp `ms`, against the newest stamp
    /// seen (a late frame from before the last wrap is placed before it).
    fn wraps_of(&self, ms: u32) -> u64 {
        match self.boot_ms {
            None => 0,
            Some((last, wraps)) if ms < last && last - ms > HALF_WRAP_MS => wraps + 1,
            Some((last, wraps)) if ms > last && ms - last > HALF_WRAP_MS => wraps.saturating_sub(1),
            Some((_, wraps)) => wraps,
        }
    }

    /// A `time_boot_ms` stamp as microseconds since boot, unwrapped (it wraps every 2^32 ms),
    /// the newest stamp and the wraps noted.
    fn unwrap_boot_ms(&mut self, ms: u32) -> u64 {
        let wraps = self.wraps_of(ms);
        match self.boot_ms {
            None => self.boot_ms = Some((ms, 0)),
            Some((last, _)) if ms < last && last - ms > HALF_WRAP_MS => {
                self.counters.time_wraps += 1;
                self.boot_ms = Some((ms, wraps));
            }
            Some((last, before)) if ms > last && ms - last <= HALF_WRAP_MS => self.boot_ms = Some((ms, before)),
            // (a late frame, or one from before the last wrap)
            _ => {}
        }
        ((wraps << 32) + u64::from(ms)) * 1000
    }

    /// Notes a stamp since boot; false for a stale stamp (dropped). Detects reboots.
    fn note_boot(&mut self, us: u64) -> bool {
        if let Some(last) = self.last_boot_us
            && us + REBOOT_BACKSTEP_US < last
        {
            // one stamp far back is a frame stuck somewhere; several in a row, a reboot
            self.backsteps += 1;
            if self.backsteps < REBOOT_CONFIRMATIONS {
                self.counters.stale_stamps += 1;
                return false;
            }
            self.backsteps = 0;
            self.counters.reboots += 1;
            self.unix_offset_us = None;
            self.clock_source = None;
            self.system_time_offset_us = None;
            // held inputs of the boot before never get a Unix time
            self.counters.waiting_for_clock += self.held.len() as u64;
            self.held.clear();
            self.prev_imu = None;
            self.prev_wheels = None;
            // a gyro's samples and the wheel intervals waiting for them belong to the boot before
            self.gyro.clear();
            self.counters.gyro_missing += self.pending_wheels.len() as u64;
            self.pending_wheels.clear();
            self.boot_ms = None;
            self.last_boot_us = Some(us);
        } else {
            self.backsteps = 0;
            self.last_boot_us = Some(self.last_boot_us.map_or(us, |l| l.max(us)));
        }
        true
    }

    /// A stamp since boot, us (mapped to the team's clock on the way out, see [`Self::decode`]).
    fn boot_us(&mut self, us: u64) -> Option<TimeUs> {
        self.note_boot(us).then_some(TimeUs(us))
    }

    /// A team-clock time in the vehicle's own clock (`time_usec` since its boot when the team
    /// clock is Unix time and the mapping is known), for what the node sends to the autopilot.
    pub fn to_vehicle_time(&self, t: TimeUs) -> u64 {
        match (self.cfg.clock, self.unix_offset_us) {
            (TeamClock::Vehicle, _) | (_, None) => t.0,
            (_, Some(o)) => u64::try_from(t.0 as i64 - o).unwrap_or(0),
        }
    }
}

/// `t` on the nearest instant of a grid of `grid_us` (0: no grid), and whether it moved by more
/// than a quarter of the grid (mappings that disagree more than the grid allows).
pub fn snap_to_grid(t: TimeUs, grid_us: u64) -> (TimeUs, bool) {
    if grid_us == 0 {
        return (t, false);
    }
    let snapped = t.0.saturating_add(grid_us / 2) / grid_us * grid_us;
    (TimeUs(snapped), snapped.abs_diff(t.0) > grid_us / 4)
}

/// The time stamp of an input event.
fn event_time(e: &VehicleEvent) -> Option<TimeUs> {
    match e {
        VehicleEvent::Input(NodeInput::Imu(s)) => Some(s.t),
        VehicleEvent::Input(NodeInput::Odometer(s)) => Some(s.t),
        VehicleEvent::Input(NodeInput::PositionFix(s)) => Some(s.t),
        VehicleEvent::Input(NodeInput::Wheel(s)) => Some(s.t),
        VehicleEvent::Input(NodeInput::OwnRange { range, .. }) => Some(range.t),
        _ => None,
    }
}

/// An input stamped since boot moved to Unix time by `offset_us`.
fn map_event(e: VehicleEvent, offset_us: i64) -> Option<VehicleEvent> {
    let map = |t: TimeUs| u64::try_from(t.0 as i64 + offset_us).ok().map(TimeUs);
    Some(match e {
        VehicleEvent::Input(NodeInput::Imu(s)) => VehicleEvent::Input(NodeInput::Imu(ImuSample { t: map(s.t)?, ..s })),
        VehicleEvent::Input(NodeInput::Odometer(s)) => {
            VehicleEvent::Input(NodeInput::Odometer(OdometerSample { t: map(s.t)?, ..s }))
        }
        VehicleEvent::Input(NodeInput::Wheel(s)) => VehicleEvent::Input(NodeInput::Wheel(WheelSample { t: map(s.t)?, ..s })),
        VehicleEvent::Input(NodeInput::OwnRange { epoch, range }) => VehicleEvent::Input(NodeInput::OwnRange {
            epoch,
            range: crate::estimation::RangeSample { t: map(range.t)?, ..range },
        }),
        other => other,
    })
}

fn origin(lat_e7: i32, lon_e7: i32, alt_mm: i32) -> VehicleEvent {
    let lat = wire::e7_to_deg(lat_e7);
    let lon = wire::e7_to_deg(lon_e7);
    if lat.abs() > 90.0 || lon.abs() > 180.0 || (lat_e7 == 0 && lon_e7 == 0) {
        return VehicleEvent::Nothing;
    }
    VehicleEvent::Origin(GeoOrigin { lat_deg: lat, lon_deg: lon, alt_m: f64::from(alt_mm) * 1e-3 })
}

#[cfg(test)]
mod tests;
