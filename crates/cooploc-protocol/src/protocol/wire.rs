//! Conversions between the generated MAVLink messages and the core's types: units,
//! quantisation and packing happen here and nowhere else.
//!
//! Every conversion from the wire validates what it reads (finite numbers, physical ranges,
//! array lengths) and returns a [`WireError`] naming the field instead of panicking. Every
//! conversion to the wire that rounds (f64 to f32) has a `*_as_sent` companion that returns
//! the value as the receivers will see it, so that the sender can use exactly that
//! (quantisation rule, see [`super::record`]).

use mavlink_core::{MavHeader, MavlinkVersion, Message};
use nalgebra::{Matrix3, Vector3};

use super::dialect::cooploc::{
    ATTITUDE_DATA, COMMAND_ACK_DATA, COOPLOC_EPOCH_DATA, COOPLOC_EPOCH_SET_DATA, COOPLOC_ESTIMATE_DATA,
    COOPLOC_RANGE_BEARING_DATA, COOPLOC_RANGE_DATA, COOPLOC_STATE_FRAGMENT_DATA, COOPLOC_STORE_FRAGMENT_DATA,
    COOPLOC_STORE_HELD_DATA, CooplocEpochState, CooplocMethod, GLOBAL_POSITION_INT_DATA, HEARTBEAT_DATA, HIGHRES_IMU_DATA,
    LOCAL_POSITION_NED_DATA, MavAutopilot, MavCmd, MavEstimatorType, MavFrame, MavMessage, MavModeFlag, MavResult, MavState,
    MavType, ODOMETRY_DATA, RAW_IMU_DATA, SCALED_IMU2_DATA, SIM_STATE_DATA, WHEEL_DISTANCE_DATA,
};
use super::fragment::{FRAGMENT_DATA, Fragment, Payload};
use crate::estimation::{ImuSample, Method, OdometerSample, PlatformId, RangeSample};
use crate::time::TimeUs;

/// A message from the wire that cannot be used.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum WireError {
    #[error("{message}.{field}: {reason}")]
    Field { message: &'static str, field: &'static str, reason: String },
    #[error("MAVLink frame: {0}")]
    Frame(String),
}

fn bad(message: &'static str, field: &'static str, reason: impl Into<String>) -> WireError {
    WireError::Field { message, field, reason: reason.into() }
}

fn finite(message: &'static str, field: &'static str, v: f32) -> Result<f64, WireError> {
    if v.is_finite() { Ok(v as f64) } else { Err(bad(message, field, format!("not finite ({v})"))) }
}

/// Serialises a message as one MAVLink 2 frame.
pub fn to_frame(header: MavHeader, msg: &MavMessage) -> Vec<u8> {
    let mut out = Vec::with_capacity(mavlink_core::consts::MAX_FRAME_SIZE);
    // Writing into a Vec cannot fail.
    mavlink_core::write_v2_msg(&mut out, header, msg).expect("writing to a Vec");
    out
}

/// The first MAVLink 2 frame in `bytes` (any bytes before it are skipped), decoded
/// ([`super::framing`]).
pub fn from_frame(bytes: &[u8]) -> Result<(MavHeader, MavMessage), WireError> {
    decoded(super::framing::frames(bytes).find(|f| f.version == MavlinkVersion::V2))
}

/// The first MAVLink 1 or 2 frame in `bytes`, decoded ([`super::framing`]).
pub fn from_any_frame(bytes: &[u8]) -> Result<(MavHeader, MavMessage), WireError> {
    decoded(super::framing::frames(bytes).next())
}

fn decoded(frame: Option<super::framing::Frame<'_>>) -> Result<(MavHeader, MavMessage), WireError> {
    let frame = frame.ok_or_else(|| WireError::Frame("no whole MAVLink frame with a valid CRC".into()))?;
    frame.message.map(|m| (frame.header, m)).map_err(WireError::Frame)
}

/// A HEARTBEAT of an active system of type `mavtype` (vehicle, companion, ground station).
pub fn heartbeat(mavtype: MavType, autopilot: MavAutopilot) -> MavMessage {
    MavMessage::HEARTBEAT(HEARTBEAT_DATA {
        custom_mode: 0,
        mavtype,
        autopilot,
        base_mode: MavModeFlag::empty(),
        system_status: MavState::MAV_STATE_ACTIVE,
        mavlink_version: 3,
    })
}

/// MAVLink component id of a cooploc node (MAV_COMP_ID_ONBOARD_COMPUTER).
pub const COMPANION_COMPID: u8 = 191;

/// Message id of COOPLOC_ESTIMATE, the message a ground station may ask a node for.
pub const ESTIMATE_MESSAGE_ID: u32 = 61002;

/// A ground station's request on the cooperative network: MAV_CMD_REQUEST_MESSAGE (COMMAND_LONG
/// or COMMAND_INT), to a system and component (0: any), for the message `param1` names.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct MessageRequest {
    pub target_system: u8,
    pub target_component: u8,
    pub param1: f32,
}

impl MessageRequest {
    /// Whether it is addressed to the node of platform `node` (system 0 or `node`, component 0
    /// or [`COMPANION_COMPID`]).
    pub fn is_for(&self, node: PlatformId) -> bool {
        (self.target_system == 0 || u16::from(self.target_system) == node)
            && (self.target_component == 0 || self.target_component == COMPANION_COMPID)
    }

    /// Whether it asks for COOPLOC_ESTIMATE (a node answers any other UNSUPPORTED).
    pub fn asks_estimate(&self) -> bool {
        self.param1.is_finite() && self.param1 == ESTIMATE_MESSAGE_ID as f32
    }
}

/// The MAV_CMD_REQUEST_MESSAGE `msg` is, if it is one.
pub fn message_request_from(msg: &MavMessage) -> Option<MessageRequest> {
    let (command, param1, target_system, target_component) = match msg {
        MavMessage::COMMAND_LONG(c) => (c.command, c.param1, c.target_system, c.target_component),
        MavMessage::COMMAND_INT(c) => (c.command, c.param1, c.target_system, c.target_component),
        _ => return None,
    };
    (command == MavCmd::MAV_CMD_REQUEST_MESSAGE).then_some(MessageRequest { target_system, target_component, param1 })
}

/// The COMMAND_ACK a node sends `to` (system, component) for `command`.
pub fn command_ack(command: MavCmd, result: MavResult, to: (u8, u8)) -> MavMessage {
    MavMessage::COMMAND_ACK(COMMAND_ACK_DATA {
        command,
        result,
        target_system: to.0,
        target_component: to.1,
        ..Default::default()
    })
}

/// Every valid MAVLink 2 frame in `bytes` (a datagram may carry several), in order; what is not
/// a valid frame is skipped.
pub fn frames(bytes: &[u8]) -> Vec<(MavHeader, MavMessage)> {
    super::framing::frames(bytes).filter(|f| f.version == MavlinkVersion::V2).filter_map(|f| f.decoded()).collect()
}

/// Message id of a message (for counters and logs).
pub fn message_id(msg: &MavMessage) -> u32 {
    msg.message_id()
}

// ---- state fragments ----

/// A fragment as COOPLOC_STATE_FRAGMENT; fails on empty data or more than [`FRAGMENT_DATA`] bytes.
pub fn fragment_to_message(f: &Fragment) -> Result<MavMessage, WireError> {
    if f.data.is_empty() || f.data.len() > FRAGMENT_DATA {
        return Err(bad("COOPLOC_STATE_FRAGMENT", "data_len", format!("{} outside 1..={FRAGMENT_DATA}", f.data.len())));
    }
    let mut data = [0u8; FRAGMENT_DATA];
    data[..f.data.len()].copy_from_slice(&f.data);
    let m = COOPLOC_STATE_FRAGMENT_DATA {
        time_usec: f.time_usec,
        epoch: f.epoch,
        record_crc32: f.record_crc32,
        record_len: f.record_len,
        platform: f.platform,
        frag_index: f.index,
        frag_count: f.count,
        data_len: f.data.len() as u8,
        data,
    };
    Ok(match f.payload {
        Payload::Record => MavMessage::COOPLOC_STATE_FRAGMENT(m),
        Payload::Store => MavMessage::COOPLOC_STORE_FRAGMENT(same_fields!(m, COOPLOC_STORE_FRAGMENT_DATA)),
    })
}

/// COOPLOC_STATE_FRAGMENT and COOPLOC_STORE_FRAGMENT have the same fields: one as the other.
macro_rules! same_fields {
    ($m:expr, $to:ident) => {
        $to {
            time_usec: $m.time_usec,
            epoch: $m.epoch,
            record_crc32: $m.record_crc32,
            record_len: $m.record_len,
            platform: $m.platform,
            frag_index: $m.frag_index,
            frag_count: $m.frag_count,
            data_len: $m.data_len,
            data: $m.data,
        }
    };
}
use same_fields;

pub fn fragment_from_message(m: &COOPLOC_STATE_FRAGMENT_DATA) -> Result<Fragment, WireError> {
    fragment_from_fields("COOPLOC_STATE_FRAGMENT", Payload::Record, m)
}

/// A COOPLOC_STORE_FRAGMENT (same fields as a state fragment) as a [`Fragment`] of a store.
pub fn store_fragment_from_message(m: &COOPLOC_STORE_FRAGMENT_DATA) -> Result<Fragment, WireError> {
    fragment_from_fields("COOPLOC_STORE_FRAGMENT", Payload::Store, &same_fields!(m, COOPLOC_STATE_FRAGMENT_DATA))
}

fn fragment_from_fields(msg: &'static str, payload: Payload, m: &COOPLOC_STATE_FRAGMENT_DATA) -> Result<Fragment, WireError> {
    let n = m.data_len as usize;
    if n == 0 || n > FRAGMENT_DATA {
        return Err(bad(msg, "data_len", format!("{n} outside 1..={FRAGMENT_DATA}")));
    }
    Ok(Fragment {
        platform: m.platform,
        epoch: m.epoch,
        time_usec: m.time_usec,
        record_crc32: m.record_crc32,
        record_len: m.record_len,
        index: m.frag_index,
        count: m.frag_count,
        data: m.data[..n].to_vec(),
        payload,
    })
}

// ---- ranges ----

/// A measured range as COOPLOC_RANGE (distance and sigma as f32).
pub fn range_to_message(r: &RangeSample, epoch: u32) -> MavMessage {
    MavMessage::COOPLOC_RANGE(COOPLOC_RANGE_DATA {
        time_usec: r.t.0,
        epoch,
        distance: r.range_m as f32,
        sigma: r.sigma_m as f32,
        from_platform: r.from,
        to_platform: r.to,
    })
}

/// A COOPLOC_RANGE as a range sample and its epoch.
pub fn range_from_message(m: &COOPLOC_RANGE_DATA) -> Result<(u32, RangeSample), WireError> {
    const MSG: &str = "COOPLOC_RANGE";
    let range_m = finite(MSG, "distance", m.distance)?;
    if range_m < 0.0 {
        return Err(bad(MSG, "distance", format!("negative ({range_m} m)")));
    }
    let sigma_m = finite(MSG, "sigma", m.sigma)?;
    if sigma_m <= 0.0 {
        return Err(bad(MSG, "sigma", format!("must be positive, got {sigma_m} m")));
    }
    if m.from_platform == m.to_platform {
        return Err(bad(MSG, "to_platform", format!("equals from_platform ({})", m.from_platform)));
    }
    Ok((m.epoch, RangeSample { t: TimeUs(m.time_usec), from: m.from_platform, to: m.to_platform, range_m, sigma_m }))
}

/// A range and bearing a platform measured (COOPLOC_RANGE_BEARING).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct RangeBearingReport {
    pub t: TimeUs,
    pub observer: PlatformId,
    pub target: crate::estimation::inputs::Target,
    pub range_m: f64,
    /// From the observer's heading, clockwise seen from above, rad.
    pub bearing_rad: f64,
}

/// Farthest a range-and-bearing sensor is believed, m.
pub const MAX_RANGE_BEARING_M: f64 = 10_000.0;

pub fn range_bearing_to_message(r: &RangeBearingReport) -> MavMessage {
    use crate::estimation::inputs::Target;
    let (target, target_kind) = match r.target {
        Target::Robot(id) => (id, 0),
        Target::Landmark(id) => (id, 1),
    };
    MavMessage::COOPLOC_RANGE_BEARING(COOPLOC_RANGE_BEARING_DATA {
        time_usec: r.t.0,
        range: r.range_m as f32,
        bearing: r.bearing_rad as f32,
        observer: r.observer,
        target,
        target_kind,
    })
}

/// A COOPLOC_RANGE_BEARING, checked: finite, a positive range under [`MAX_RANGE_BEARING_M`], a
/// bearing within one turn, a known target kind, no platform observing itself.
pub fn range_bearing_from_message(m: &COOPLOC_RANGE_BEARING_DATA) -> Result<RangeBearingReport, WireError> {
    use crate::estimation::inputs::Target;
    const MSG: &str = "COOPLOC_RANGE_BEARING";
    let range_m = finite(MSG, "range", m.range)?;
    if !(range_m > 0.0 && range_m <= MAX_RANGE_BEARING_M) {
        return Err(bad(MSG, "range", format!("{range_m} m is not in (0, {MAX_RANGE_BEARING_M}] m")));
    }
    let bearing_rad = finite(MSG, "bearing", m.bearing)?;
    if bearing_rad.abs() > std::f64::consts::TAU {
        return Err(bad(MSG, "bearing", format!("{bearing_rad} rad is more than one turn")));
    }
    let target = match m.target_kind {
        0 if m.target == m.observer => return Err(bad(MSG, "target", format!("equals observer ({})", m.observer))),
        0 => Target::Robot(m.target),
        1 => Target::Landmark(m.target),
        k => return Err(bad(MSG, "target_kind", format!("{k}: expected 0 (teammate) or 1 (landmark)"))),
    };
    Ok(RangeBearingReport { t: TimeUs(m.time_usec), observer: m.observer, target, range_m, bearing_rad })
}

/// A motion command (forward speed and yaw rate, what a robot was told to do) as ODOMETRY:
/// body-frame (BODY_FRD) velocity `vx` and `yawspeed` (z down: positive turning right),
/// estimator type NAIVE (open loop), pose unknown (NaN).
pub fn command_to_odometry(c: &crate::estimation::inputs::Command) -> MavMessage {
    body_velocity_odometry(c.t, c.speed_m_s, c.yaw_rate_rad_s, [f32::NAN; 21], MavEstimatorType::MAV_ESTIMATOR_TYPE_NAIVE)
}

/// ODOMETRY as a motion command (see [`command_to_odometry`]), checked against the planar
/// robot's limits.
pub fn command_from_odometry(m: &ODOMETRY_DATA) -> Result<crate::estimation::inputs::Command, WireError> {
    const MSG: &str = "ODOMETRY";
    if !matches!(m.child_frame_id, MavFrame::MAV_FRAME_BODY_FRD) {
        return Err(bad(MSG, "child_frame_id", format!("{:?}: a command is a body-frame (BODY_FRD) velocity", m.child_frame_id)));
    }
    let speed_m_s = finite(MSG, "vx", m.vx)?;
    if speed_m_s.abs() > crate::estimation::planar::MAX_SPEED_M_S {
        return Err(bad(MSG, "vx", format!("{speed_m_s} m/s is not a wheeled robot's speed")));
    }
    let yaw_rate_rad_s = finite(MSG, "yawspeed", m.yawspeed)?;
    if yaw_rate_rad_s.abs() > crate::estimation::planar::MAX_YAW_RATE_RAD_S {
        return Err(bad(MSG, "yawspeed", format!("{yaw_rate_rad_s} rad/s is not a wheeled robot's yaw rate")));
    }
    Ok(crate::estimation::inputs::Command { t: TimeUs(m.time_usec), speed_m_s, yaw_rate_rad_s })
}

/// The range as every receiver will see it (f32 on the wire): what the measuring node uses too.
pub fn range_as_sent(r: &RangeSample) -> RangeSample {
    RangeSample { range_m: r.range_m as f32 as f64, sigma_m: r.sigma_m as f32 as f64, ..*r }
}

// ---- epoch announcement ----

/// A node's view of an epoch: the platforms whose complete record it holds (collecting) or used
/// (applied, partial). See COOPLOC_EPOCH and COOPLOC_EPOCH_SET in dialects/cooploc.xml.
#[derive(Debug, Clone, PartialEq)]
pub struct EpochAnnouncement {
    pub epoch: u32,
    pub t: TimeUs,
    pub announcer: PlatformId,
    pub participants: Vec<PlatformId>,
    pub state: EpochState,
    /// The announcer's store digest (see COOPLOC_EPOCH.digest); 0 when it keeps none.
    pub digest: u64,
    /// While collecting: the fragments the announcer holds of records still incomplete (at most
    /// [`MAX_INCOMPLETE`]), so that their senders resend only what is missing. Carried by
    /// COOPLOC_EPOCH_SET only: an announcement sent as COOPLOC_EPOCH goes without them (its
    /// senders then resend whole records).
    pub incomplete: Vec<HeldFragments>,
}

/// The fragments a node holds of one platform's record still incomplete: bit `i` of `held` is
/// fragment `i` (COOPLOC_EPOCH_SET.incomplete and .held).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct HeldFragments {
    pub platform: PlatformId,
    pub held: u32,
}

impl HeldFragments {
    /// Whether fragment `index` is held.
    pub fn holds(&self, index: u8) -> bool {
        index < 32 && self.held & (1 << index) != 0
    }
}

/// Where a node is with an epoch (COOPLOC_EPOCH_STATE).
pub type EpochState = CooplocEpochState;

/// Most participants one COOPLOC_EPOCH can name.
pub const MAX_PARTICIPANTS: usize = 64;
/// Most incomplete records one COOPLOC_EPOCH_SET describes.
pub const MAX_INCOMPLETE: usize = 4;
/// Most fragments of a record whose holding COOPLOC_EPOCH_SET can describe.
pub const MAX_HELD_FRAGMENTS: usize = 32;

/// An epoch announcement as a message: COOPLOC_EPOCH_SET (participants as a bitmask, incomplete
/// records described) when every participant and incomplete record's platform lies within 64 of
/// the lowest of them, COOPLOC_EPOCH (the list, no incomplete records) otherwise.
pub fn epoch_to_message(a: &EpochAnnouncement) -> Result<MavMessage, WireError> {
    if a.participants.len() > MAX_PARTICIPANTS {
        return Err(bad("COOPLOC_EPOCH", "participants", format!("{} > {MAX_PARTICIPANTS}", a.participants.len())));
    }
    if a.incomplete.len() > MAX_INCOMPLETE {
        return Err(bad("COOPLOC_EPOCH_SET", "incomplete", format!("{} > {MAX_INCOMPLETE}", a.incomplete.len())));
    }
    let ids = || a.participants.iter().copied().chain(a.incomplete.iter().map(|h| h.platform));
    let base = ids().min().unwrap_or(a.announcer);
    if ids().all(|p| p - base < 64) {
        let mut set = COOPLOC_EPOCH_SET_DATA {
            time_usec: a.t.0,
            epoch: a.epoch,
            announcer: a.announcer,
            base,
            participants: a.participants.iter().fold(0u64, |m, p| m | 1 << (p - base)),
            state: a.state,
            digest: a.digest,
            incomplete: [0; MAX_INCOMPLETE],
            held: [0; MAX_INCOMPLETE],
        };
        for (k, h) in a.incomplete.iter().enumerate() {
            set.incomplete[k] = (h.platform - base + 1) as u8;
            set.held[k] = h.held;
        }
        return Ok(MavMessage::COOPLOC_EPOCH_SET(set));
    }
    let mut participants = [0u16; MAX_PARTICIPANTS];
    participants[..a.participants.len()].copy_from_slice(&a.participants);
    Ok(MavMessage::COOPLOC_EPOCH(COOPLOC_EPOCH_DATA {
        time_usec: a.t.0,
        epoch: a.epoch,
        announcer: a.announcer,
        participants,
        count: a.participants.len() as u8,
        state: a.state,
        digest: a.digest,
    }))
}

/// The epoch announcement `msg` carries, in either form; None for any other message.
pub fn epoch_of(msg: &MavMessage) -> Option<Result<EpochAnnouncement, WireError>> {
    match msg {
        MavMessage::COOPLOC_EPOCH(m) => Some(epoch_from_message(m)),
        MavMessage::COOPLOC_EPOCH_SET(m) => Some(epoch_set_from_message(m)),
        _ => None,
    }
}

pub fn epoch_from_message(m: &COOPLOC_EPOCH_DATA) -> Result<EpochAnnouncement, WireError> {
    let n = m.count as usize;
    if n > MAX_PARTICIPANTS {
        return Err(bad("COOPLOC_EPOCH", "count", format!("{n} > {MAX_PARTICIPANTS}")));
    }
    let participants = m.participants[..n].to_vec();
    for (i, p) in participants.iter().enumerate() {
        if participants[..i].contains(p) {
            return Err(bad("COOPLOC_EPOCH", "participants", format!("platform {p} listed twice")));
        }
    }
    Ok(EpochAnnouncement {
        epoch: m.epoch,
        t: TimeUs(m.time_usec),
        announcer: m.announcer,
        participants,
        state: m.state,
        digest: m.digest,
        incomplete: Vec::new(),
    })
}

pub fn epoch_set_from_message(m: &COOPLOC_EPOCH_SET_DATA) -> Result<EpochAnnouncement, WireError> {
    let id = |offset: u64, field| {
        u16::try_from(u64::from(m.base) + offset)
            .map_err(|_| bad("COOPLOC_EPOCH_SET", field, format!("platform {} + {offset} beyond 65535", m.base)))
    };
    let participants =
        (0..64).filter(|k| m.participants & (1 << k) != 0).map(|k| id(k, "participants")).collect::<Result<_, _>>()?;
    let mut incomplete: Vec<HeldFragments> = Vec::new();
    for (&k, &held) in m.incomplete.iter().zip(&m.held) {
        match k {
            0 if held != 0 => return Err(bad("COOPLOC_EPOCH_SET", "held", format!("fragments {held:#x} held of no platform"))),
            0 => {}
            65.. => return Err(bad("COOPLOC_EPOCH_SET", "incomplete", format!("offset {k} > 64"))),
            _ => {
                let platform = id(u64::from(k) - 1, "incomplete")?;
                if incomplete.iter().any(|h| h.platform == platform) {
                    return Err(bad("COOPLOC_EPOCH_SET", "incomplete", format!("platform {platform} listed twice")));
                }
                incomplete.push(HeldFragments { platform, held });
            }
        }
    }
    Ok(EpochAnnouncement {
        epoch: m.epoch,
        t: TimeUs(m.time_usec),
        announcer: m.announcer,
        participants,
        state: m.state,
        digest: m.digest,
        incomplete,
    })
}

// ---- store held ----

/// What a node that asks for a store holds of it already (COOPLOC_STORE_HELD): the parts it
/// holds whole and, of one part it holds in part (a fragment series, named by its CRC-32), the
/// fragments. The answerers send only what is missing.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct StoreHeld {
    pub epoch: u32,
    pub t: TimeUs,
    pub announcer: PlatformId,
    /// The store's digest before the epoch (as the request's).
    pub digest_before: u64,
    /// Bit k (of element k / 64): part k held whole.
    pub whole: Bits256,
    /// A series held in part: its CRC-32 and the fragments held (bit i: fragment i).
    pub series: Option<(u32, Bits256)>,
}

/// 256 flags, bit k in element k / 64 (COOPLOC_STORE_HELD's whole and held).
pub type Bits256 = [u64; 4];

/// Whether flag `k` of `bits` is set.
pub fn bit(bits: &Bits256, k: usize) -> bool {
    k < 256 && bits[k / 64] & (1 << (k % 64)) != 0
}

/// The flags set at `indices` (those beyond 255 are not).
pub fn bits_at(indices: impl IntoIterator<Item = usize>) -> Bits256 {
    let mut bits = [0; 4];
    for k in indices.into_iter().filter(|&k| k < 256) {
        bits[k / 64] |= 1 << (k % 64);
    }
    bits
}

impl StoreHeld {
    /// Whether the node holds fragment `index` of the series `crc32`, which is part `part` of
    /// the store (whole, or that fragment of it).
    pub fn holds(&self, part: u16, crc32: u32, index: u8) -> bool {
        bit(&self.whole, usize::from(part)) || self.series.is_some_and(|(c, held)| c == crc32 && bit(&held, usize::from(index)))
    }
}

pub fn store_held_to_message(h: &StoreHeld) -> MavMessage {
    let (series_crc32, held) = h.series.unwrap_or((0, [0; 4]));
    MavMessage::COOPLOC_STORE_HELD(COOPLOC_STORE_HELD_DATA {
        time_usec: h.t.0,
        digest: h.digest_before,
        whole: h.whole,
        held,
        epoch: h.epoch,
        series_crc32,
        announcer: h.announcer,
    })
}

pub fn store_held_from_message(m: &COOPLOC_STORE_HELD_DATA) -> Result<StoreHeld, WireError> {
    let series = match (m.series_crc32, m.held) {
        (0, [0, 0, 0, 0]) => None,
        (0, held) => return Err(bad("COOPLOC_STORE_HELD", "held", format!("fragments {held:x?} held of no series"))),
        // a series has at most 255 fragments (indices 0 to 254)
        (_, held) if bit(&held, 255) => return Err(bad("COOPLOC_STORE_HELD", "held", "fragment 255 (a series has at most 255)")),
        (crc, held) => Some((crc, held)),
    };
    Ok(StoreHeld {
        epoch: m.epoch,
        t: TimeUs(m.time_usec),
        announcer: m.announcer,
        digest_before: m.digest,
        whole: m.whole,
        series,
    })
}

// ---- estimate report ----

/// What a node reports after each event, for ground stations and logs.
#[derive(Debug, Clone, PartialEq)]
pub struct EstimateReport {
    pub platform: PlatformId,
    pub t: TimeUs,
    pub epoch: u32,
    pub method: Method,
    pub position_ned_m: Vector3<f64>,
    pub velocity_ned_m_s: Vector3<f64>,
    pub yaw_rad: f64,
    pub position_covariance_m2: Matrix3<f64>,
    pub yaw_variance_rad2: f64,
    /// NIS of the last joint update (NaN: none yet).
    pub nis: f64,
    pub participants: u8,
    pub ranges: u8,
}

fn method_to_wire(m: Method) -> CooplocMethod {
    match m {
        Method::DeadReckoning => CooplocMethod::COOPLOC_METHOD_DEAD_RECKONING,
        Method::NoPropagation => CooplocMethod::COOPLOC_METHOD_NO_PROPAGATION,
        Method::Decentralized => CooplocMethod::COOPLOC_METHOD_DECENTRALIZED,
        Method::Centralized => CooplocMethod::COOPLOC_METHOD_CENTRALIZED,
        Method::CovarianceIntersection => CooplocMethod::COOPLOC_METHOD_COVARIANCE_INTERSECTION,
    }
}

fn method_from_wire(m: CooplocMethod) -> Method {
    match m {
        CooplocMethod::COOPLOC_METHOD_DEAD_RECKONING => Method::DeadReckoning,
        CooplocMethod::COOPLOC_METHOD_NO_PROPAGATION => Method::NoPropagation,
        CooplocMethod::COOPLOC_METHOD_DECENTRALIZED => Method::Decentralized,
        CooplocMethod::COOPLOC_METHOD_CENTRALIZED => Method::Centralized,
        CooplocMethod::COOPLOC_METHOD_COVARIANCE_INTERSECTION => Method::CovarianceIntersection,
    }
}

pub fn estimate_to_message(e: &EstimateReport) -> MavMessage {
    MavMessage::COOPLOC_ESTIMATE(estimate_data(e))
}

impl EstimateReport {
    /// The estimate as COOPLOC_ESTIMATE carries it (f32; the covariance from its upper
    /// triangle), checked as a receiver checks it: what a node logs and gives its vehicle, so
    /// that its log, its vehicle and its teammates see the same numbers. Err: an estimate no
    /// receiver would take (not finite, a negative variance).
    pub fn as_sent(&self) -> Result<EstimateReport, WireError> {
        estimate_from_message(&estimate_data(self))
    }
}

fn estimate_data(e: &EstimateReport) -> COOPLOC_ESTIMATE_DATA {
    let c = &e.position_covariance_m2;
    COOPLOC_ESTIMATE_DATA {
        time_usec: e.t.0,
        epoch: e.epoch,
        x: e.position_ned_m[0] as f32,
        y: e.position_ned_m[1] as f32,
        z: e.position_ned_m[2] as f32,
        vx: e.velocity_ned_m_s[0] as f32,
        vy: e.velocity_ned_m_s[1] as f32,
        vz: e.velocity_ned_m_s[2] as f32,
        yaw: e.yaw_rad as f32,
        pos_covariance: [c[(0, 0)], c[(0, 1)], c[(0, 2)], c[(1, 1)], c[(1, 2)], c[(2, 2)]].map(|v| v as f32),
        yaw_variance: e.yaw_variance_rad2 as f32,
        nis: e.nis as f32,
        platform: e.platform,
        method: method_to_wire(e.method),
        participants: e.participants,
        ranges: e.ranges,
    }
}

pub fn estimate_from_message(m: &COOPLOC_ESTIMATE_DATA) -> Result<EstimateReport, WireError> {
    const MSG: &str = "COOPLOC_ESTIMATE";
    let position = Vector3::new(finite(MSG, "x", m.x)?, finite(MSG, "y", m.y)?, finite(MSG, "z", m.z)?);
    let velocity = Vector3::new(finite(MSG, "vx", m.vx)?, finite(MSG, "vy", m.vy)?, finite(MSG, "vz", m.vz)?);
    let mut cov = [0.0; 6];
    for (o, v) in cov.iter_mut().zip(m.pos_covariance) {
        *o = finite(MSG, "pos_covariance", v)?;
    }
    let c = Matrix3::new(cov[0], cov[1], cov[2], cov[1], cov[3], cov[4], cov[2], cov[4], cov[5]);
    if c[(0, 0)] < 0.0 || c[(1, 1)] < 0.0 || c[(2, 2)] < 0.0 {
        return Err(bad(MSG, "pos_covariance", "negative variance"));
    }
    let yaw_variance = finite(MSG, "yaw_variance", m.yaw_variance)?;
    if yaw_variance < 0.0 {
        return Err(bad(MSG, "yaw_variance", "negative"));
    }
    Ok(EstimateReport {
        platform: m.platform,
        t: TimeUs(m.time_usec),
        epoch: m.epoch,
        method: method_from_wire(m.method),
        position_ned_m: position,
        velocity_ned_m_s: velocity,
        yaw_rad: finite(MSG, "yaw", m.yaw)?,
        position_covariance_m2: c,
        yaw_variance_rad2: yaw_variance,
        nis: m.nis as f64,
        participants: m.participants,
        ranges: m.ranges,
    })
}

/// The estimate as LOCAL_POSITION_NED, the standard message autopilots and ground stations show,
/// stamped `time_boot_ms` in the vehicle's own clock.
pub fn estimate_to_local_position(e: &EstimateReport, time_boot_ms: u32) -> MavMessage {
    MavMessage::LOCAL_POSITION_NED(LOCAL_POSITION_NED_DATA {
        time_boot_ms,
        x: e.position_ned_m[0] as f32,
        y: e.position_ned_m[1] as f32,
        z: e.position_ned_m[2] as f32,
        vx: e.velocity_ned_m_s[0] as f32,
        vy: e.velocity_ned_m_s[1] as f32,
        vz: e.velocity_ned_m_s[2] as f32,
    })
}

/// A node's navigation solution, as fed back to its autopilot.
#[derive(Debug, Clone, PartialEq)]
pub struct Navigation {
    pub t: TimeUs,
    pub position_ned_m: Vector3<f64>,
    pub velocity_ned_m_s: Vector3<f64>,
    pub attitude_frd_to_ned: nalgebra::UnitQuaternion<f64>,
    /// Covariance of position (N, E, D) and attitude error (small rotations about N, E, D).
    pub pose_covariance: nalgebra::Matrix6<f64>,
    /// Covariance of the NED velocity.
    pub velocity_covariance_ned: Matrix3<f64>,
}

/// The 21 upper-triangle entries of a symmetric 6x6 matrix, row by row (MAVLink's layout).
fn upper_triangle(m: &nalgebra::Matrix6<f64>) -> [f32; 21] {
    let mut out = [0.0f32; 21];
    let mut k = 0;
    for r in 0..6 {
        for c in r..6 {
            out[k] = m[(r, c)] as f32;
            k += 1;
        }
    }
    out
}

/// The navigation solution as ODOMETRY the way ArduPilot and PX4 fuse it: `frame_id` the
/// node's NED frame as the autopilot names it (`ned`: LOCAL_NED, PX4's; else LOCAL_FRD,
/// ArduPilot's only one, whose axes are the local frame's: north, east, down),
/// `child_frame_id` BODY_FRD (velocity in the body frame, rotated by `q`), `q` the body
/// attitude, the pose covariance in (x, y, z, roll, pitch, yaw) (the attitude errors about
/// N, E, D rotated into roll and pitch about the body's heading), the body velocity's
/// covariance (angular rates unknown: NaN), stamped `time_usec` in the vehicle's clock.
pub fn navigation_to_odometry(n: &Navigation, time_usec: u64, reset_counter: u8, ned: bool) -> MavMessage {
    let r = n.attitude_frd_to_ned.to_rotation_matrix();
    let v_body = r.inverse() * n.velocity_ned_m_s;
    let (_, _, yaw) = n.attitude_frd_to_ned.euler_angles();
    let (s, c) = yaw.sin_cos();
    // small NED tilt errors to roll/pitch errors of a level vehicle heading `yaw`
    let mut j = nalgebra::Matrix6::<f64>::identity();
    j.fixed_view_mut::<3, 3>(3, 3).copy_from(&Matrix3::new(c, s, 0.0, -s, c, 0.0, 0.0, 0.0, 1.0));
    let pose = j * n.pose_covariance * j.transpose();
    let mut vel = nalgebra::Matrix6::<f64>::zeros();
    vel.fixed_view_mut::<3, 3>(0, 0).copy_from(&(r.matrix().transpose() * n.velocity_covariance_ned * r.matrix()));
    let mut velocity_covariance = upper_triangle(&vel);
    for k in [15, 18, 20] {
        velocity_covariance[k] = f32::NAN;
    }
    let q = n.attitude_frd_to_ned.quaternion();
    MavMessage::ODOMETRY(ODOMETRY_DATA {
        time_usec,
        frame_id: if ned { MavFrame::MAV_FRAME_LOCAL_NED } else { MavFrame::MAV_FRAME_LOCAL_FRD },
        child_frame_id: MavFrame::MAV_FRAME_BODY_FRD,
        x: n.position_ned_m[0] as f32,
        y: n.position_ned_m[1] as f32,
        z: n.position_ned_m[2] as f32,
        q: [q.w as f32, q.i as f32, q.j as f32, q.k as f32],
        vx: v_body[0] as f32,
        vy: v_body[1] as f32,
        vz: v_body[2] as f32,
        rollspeed: f32::NAN,
        pitchspeed: f32::NAN,
        yawspeed: f32::NAN,
        pose_covariance: upper_triangle(&pose),
        velocity_covariance,
        reset_counter,
        estimator_type: MavEstimatorType::MAV_ESTIMATOR_TYPE_UNKNOWN,
        quality: 0,
    })
}

/// Unix time of the GPS epoch (1980-01-06), s, and GPS time's lead over UTC (leap seconds since
/// then: 18, unchanged since 2017).
const GPS_EPOCH_UNIX_S: u64 = 315_964_800;
const GPS_LEAP_S: u64 = 18;

/// GPS week and time of week (ms) of a Unix time in microseconds.
pub fn gps_week_time(unix_us: u64) -> (u16, u32) {
    let gps_ms = (unix_us / 1000).saturating_sub(GPS_EPOCH_UNIX_S * 1000) + GPS_LEAP_S * 1000;
    const WEEK_MS: u64 = 7 * 24 * 3600 * 1000;
    ((gps_ms / WEEK_MS) as u16, (gps_ms % WEEK_MS) as u32)
}

/// The navigation solution as GPS_INPUT (ArduPilot's GPS type 14, MAV): the position as latitude,
/// longitude and altitude about `origin`, the NED velocity, and its accuracies (1 sigma: the
/// horizontal one is the larger axis of the position covariance) instead of dilutions of
/// precision (HDOP and VDOP are flagged ignored), a 3D fix, satellites unknown (255), the yaw in
/// centidegrees (36000 = north). `gps_time` (week, ms of week) when the team's clock is Unix time.
pub fn navigation_to_gps_input(n: &Navigation, origin: &GeoOrigin, time_usec: u64, gps_time: Option<(u16, u32)>) -> MavMessage {
    use super::dialect::cooploc::{GPS_INPUT_DATA, GpsFixType, GpsInputIgnoreFlags};
    let g = ned_to_geodetic(origin, &n.position_ned_m);
    let p = n.pose_covariance.fixed_view::<2, 2>(0, 0).into_owned();
    let horizontal = p.symmetric_eigenvalues().max().max(0.0).sqrt();
    let vertical = n.pose_covariance[(2, 2)].max(0.0).sqrt();
    let speed = n.velocity_covariance_ned.fixed_view::<2, 2>(0, 0).symmetric_eigenvalues().max().max(0.0).sqrt();
    let (_, _, yaw) = n.attitude_frd_to_ned.euler_angles();
    let cdeg = (yaw.to_degrees().rem_euclid(360.0) * 100.0).round() as u16;
    let (week, week_ms) = gps_time.unwrap_or((0, 0));
    MavMessage::GPS_INPUT(GPS_INPUT_DATA {
        time_usec,
        gps_id: 0,
        ignore_flags: GpsInputIgnoreFlags::GPS_INPUT_IGNORE_FLAG_HDOP | GpsInputIgnoreFlags::GPS_INPUT_IGNORE_FLAG_VDOP,
        time_week_ms: week_ms,
        time_week: week,
        fix_type: GpsFixType::GPS_FIX_TYPE_3D_FIX,
        lat: deg_to_e7(g.lat_deg),
        lon: deg_to_e7(g.lon_deg),
        alt: g.alt_m as f32,
        hdop: 0.0,
        vdop: 0.0,
        vn: n.velocity_ned_m_s[0] as f32,
        ve: n.velocity_ned_m_s[1] as f32,
        vd: n.velocity_ned_m_s[2] as f32,
        speed_accuracy: speed as f32,
        horiz_accuracy: horizontal as f32,
        vert_accuracy: vertical as f32,
        satellites_visible: u8::MAX,
        yaw: if cdeg == 0 { 36000 } else { cdeg },
    })
}

// ---- vehicle sensor streams ----

/// Largest plausible specific force and angular rate from a vehicle (beyond: a corrupt sample).
const MAX_ACCEL_M_S2: f64 = 50.0 * 9.80665;
const MAX_RATE_RAD_S: f64 = 40.0;

/// HIGHRES_IMU (body FRD, m/s^2 and rad/s) as an IMU sample.
pub fn imu_from_highres(m: &HIGHRES_IMU_DATA) -> Result<ImuSample, WireError> {
    const MSG: &str = "HIGHRES_IMU";
    let f = Vector3::new(finite(MSG, "xacc", m.xacc)?, finite(MSG, "yacc", m.yacc)?, finite(MSG, "zacc", m.zacc)?);
    let w = Vector3::new(finite(MSG, "xgyro", m.xgyro)?, finite(MSG, "ygyro", m.ygyro)?, finite(MSG, "zgyro", m.zgyro)?);
    imu_checked(MSG, TimeUs(m.time_usec), f, w)
}

/// HIGHRES_IMU `fields_updated` bits of the accelerometer and gyro (xacc..zgyro).
pub const HIGHRES_ACCEL_GYRO_FIELDS: u16 = 0b11_1111;

/// One mG in m/s^2 (ArduPilot scales RAW_IMU and SCALED_IMU* with standard gravity).
pub const MILLI_G_M_S2: f64 = 9.80665e-3;

fn imu_checked(msg: &'static str, t: TimeUs, f: Vector3<f64>, w: Vector3<f64>) -> Result<ImuSample, WireError> {
    if f.norm() > MAX_ACCEL_M_S2 {
        return Err(bad(msg, "xacc", format!("specific force {:.1} m/s^2 beyond 50 g", f.norm())));
    }
    if w.norm() > MAX_RATE_RAD_S {
        return Err(bad(msg, "xgyro", format!("angular rate {:.1} rad/s beyond {MAX_RATE_RAD_S}", w.norm())));
    }
    Ok(ImuSample { t, specific_force_frd_m_s2: f, angular_rate_frd_rad_s: w })
}

/// The int16 IMU messages (RAW_IMU as ArduPilot fills it, SCALED_IMU, SCALED_IMU2/3): body FRD
/// acceleration in mG and angular rate in mrad/s, as an IMU sample at `t` (the caller maps the
/// message's own time field). An int16 at its extreme (-32768 or 32767) is a saturated or
/// missing axis and refused.
pub fn imu_from_int16(msg: &'static str, t: TimeUs, acc_mg: [i16; 3], gyro_mrad_s: [i16; 3]) -> Result<ImuSample, WireError> {
    const NAMES: [&str; 6] = ["xacc", "yacc", "zacc", "xgyro", "ygyro", "zgyro"];
    for (k, v) in acc_mg.iter().chain(&gyro_mrad_s).enumerate() {
        if *v == i16::MIN || *v == i16::MAX {
            return Err(bad(msg, NAMES[k], format!("{v}: saturated")));
        }
    }
    let f = Vector3::from(acc_mg.map(|v| f64::from(v) * MILLI_G_M_S2));
    let w = Vector3::from(gyro_mrad_s.map(|v| f64::from(v) * 1e-3));
    imu_checked(msg, t, f, w)
}

/// An IMU sample as RAW_IMU the way ArduPilot sends it (mG, mrad/s, rounded), at `time_usec`.
pub fn imu_to_raw_imu(s: &ImuSample, time_usec: u64, id: u8) -> MavMessage {
    let (f, w) = int16_axes(s);
    MavMessage::RAW_IMU(RAW_IMU_DATA {
        time_usec,
        xacc: f[0],
        yacc: f[1],
        zacc: f[2],
        xgyro: w[0],
        ygyro: w[1],
        zgyro: w[2],
        id,
        ..Default::default()
    })
}

/// An IMU sample as SCALED_IMU2 (mG, mrad/s), at `time_boot_ms`.
pub fn imu_to_scaled_imu2(s: &ImuSample, time_boot_ms: u32) -> MavMessage {
    let (f, w) = int16_axes(s);
    MavMessage::SCALED_IMU2(SCALED_IMU2_DATA {
        time_boot_ms,
        xacc: f[0],
        yacc: f[1],
        zacc: f[2],
        xgyro: w[0],
        ygyro: w[1],
        zgyro: w[2],
        ..Default::default()
    })
}

fn int16_axes(s: &ImuSample) -> ([i16; 3], [i16; 3]) {
    let q = |v: f64| v.round().clamp(-32767.0, 32766.0) as i16;
    ([0, 1, 2].map(|k| q(s.specific_force_frd_m_s2[k] / MILLI_G_M_S2)), [0, 1, 2].map(|k| q(s.angular_rate_frd_rad_s[k] * 1e3)))
}

/// WHEEL_DISTANCE's cumulative distances of `wheels`, m, checked (count, finite, plausible).
pub fn wheel_distances(m: &WHEEL_DISTANCE_DATA, wheels: &[u8]) -> Result<Vec<f64>, WireError> {
    const MSG: &str = "WHEEL_DISTANCE";
    let count = m.count as usize;
    if count > 16 {
        return Err(bad(MSG, "count", format!("{count} wheels, at most 16")));
    }
    wheels
        .iter()
        .map(|&w| {
            let w = w as usize;
            if w >= count {
                return Err(bad(MSG, "count", format!("{count} wheels: no wheel {w}")));
            }
            let d = m.distance[w];
            if !d.is_finite() || d.abs() > 1e9 {
                return Err(bad(MSG, "distance", format!("wheel {w}: {d} m")));
            }
            Ok(d)
        })
        .collect()
}

/// An IMU sample as HIGHRES_IMU with the accelerometer and gyro fields marked updated.
pub fn imu_to_highres(s: &ImuSample) -> MavMessage {
    let f = s.specific_force_frd_m_s2.map(|v| v as f32);
    let w = s.angular_rate_frd_rad_s.map(|v| v as f32);
    MavMessage::HIGHRES_IMU(HIGHRES_IMU_DATA {
        time_usec: s.t.0,
        xacc: f[0],
        yacc: f[1],
        zacc: f[2],
        xgyro: w[0],
        ygyro: w[1],
        zgyro: w[2],
        fields_updated: super::dialect::cooploc::HighresImuUpdatedFlags::from_bits_truncate(0b11_1111),
        ..Default::default()
    })
}

/// The sample as receivers see it (f32 on the wire).
pub fn imu_as_sent(s: &ImuSample) -> ImuSample {
    ImuSample {
        t: s.t,
        specific_force_frd_m_s2: s.specific_force_frd_m_s2.map(|v| v as f32 as f64),
        angular_rate_frd_rad_s: s.angular_rate_frd_rad_s.map(|v| v as f32 as f64),
    }
}

/// ODOMETRY with a body-frame velocity (child frame BODY_FRD) as an odometer sample: the forward
/// speed `vx`.
pub fn odometer_from_odometry(m: &ODOMETRY_DATA) -> Result<OdometerSample, WireError> {
    const MSG: &str = "ODOMETRY";
    if !matches!(m.child_frame_id, MavFrame::MAV_FRAME_BODY_FRD) {
        return Err(bad(
            MSG,
            "child_frame_id",
            format!("{:?}: cooploc reads the body-frame (BODY_FRD) velocity", m.child_frame_id),
        ));
    }
    let speed = finite(MSG, "vx", m.vx)?;
    if speed.abs() > 200.0 {
        return Err(bad(MSG, "vx", format!("{speed} m/s is not a land vehicle's speed")));
    }
    Ok(OdometerSample { t: TimeUs(m.time_usec), speed_m_s: speed })
}

/// An odometer sample as ODOMETRY: body-frame velocity (x forward), pose and rates unknown (NaN).
pub fn odometer_to_odometry(s: &OdometerSample, sigma_m_s: f64) -> MavMessage {
    // Only vx is measured; vy and vz are zero by the vehicle's non-holonomic constraint (their
    // uncertainty is the filter's tuning, not the odometer's), angular rates are not reported.
    let mut velocity_covariance = [0.0f32; 21];
    velocity_covariance[0] = (sigma_m_s * sigma_m_s) as f32;
    body_velocity_odometry(s.t, s.speed_m_s, f64::NAN, velocity_covariance, MavEstimatorType::default())
}

/// ODOMETRY with only a body-frame (BODY_FRD) forward speed and yaw rate (NaN: not reported):
/// pose unknown (NaN), vy and vz zero.
fn body_velocity_odometry(
    t: TimeUs,
    vx_m_s: f64,
    yaw_rate_rad_s: f64,
    velocity_covariance: [f32; 21],
    estimator_type: MavEstimatorType,
) -> MavMessage {
    MavMessage::ODOMETRY(ODOMETRY_DATA {
        time_usec: t.0,
        frame_id: MavFrame::MAV_FRAME_LOCAL_NED,
        child_frame_id: MavFrame::MAV_FRAME_BODY_FRD,
        x: f32::NAN,
        y: f32::NAN,
        z: f32::NAN,
        q: [f32::NAN, 0.0, 0.0, 0.0],
        vx: vx_m_s as f32,
        vy: 0.0,
        vz: 0.0,
        rollspeed: f32::NAN,
        pitchspeed: f32::NAN,
        yawspeed: yaw_rate_rad_s as f32,
        pose_covariance: [f32::NAN; 21],
        velocity_covariance,
        estimator_type,
        ..Default::default()
    })
}

/// The sample as receivers see it (f32 on the wire).
pub fn odometer_as_sent(s: &OdometerSample) -> OdometerSample {
    OdometerSample { t: s.t, speed_m_s: s.speed_m_s as f32 as f64 }
}

// ---- geodetic position and simulator truth ----

// The team's origin and the NED <-> geodetic conversion live in [`crate::geodesy`]; the wire
// conversions below use them (and callers may name them from here).
pub use crate::geodesy::{EARTH_RADIUS_M, GeoOrigin, Geodetic, geodetic_to_ned, ned_to_geodetic};

/// Degrees as MAVLink's `degE7` integer (rounded; saturates outside the i32 range).
pub fn deg_to_e7(deg: f64) -> i32 {
    (deg * 1e7).round() as i32
}

pub fn e7_to_deg(v: i32) -> f64 {
    v as f64 * 1e-7
}

/// SET_GPS_GLOBAL_ORIGIN: the team's origin for an autopilot that has none (no GNSS fix ever).
/// `time_usec` 0: ArduPilot and PX4 ignore it. The message is deprecated in common.xml since
/// 2025-04 for MAV_CMD_DO_SET_GLOBAL_ORIGIN, which ArduPilot 4.7 takes too; the message is what
/// both ArduPilot and PX4 releases in the field take.
#[allow(deprecated)]
pub fn set_gps_global_origin(o: &GeoOrigin, target_system: u8) -> MavMessage {
    MavMessage::SET_GPS_GLOBAL_ORIGIN(crate::protocol::dialect::cooploc::SET_GPS_GLOBAL_ORIGIN_DATA {
        latitude: deg_to_e7(o.lat_deg),
        longitude: deg_to_e7(o.lon_deg),
        altitude: (o.alt_m * 1e3).round() as i32,
        target_system,
        time_usec: 0,
    })
}

/// A vehicle's true motion, as SIM_STATE carries it (a simulator fills it from its world).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct TrueMotion {
    pub pos_ned_m: Vector3<f64>,
    pub vel_ned_m_s: Vector3<f64>,
    /// Body (FRD) to NED rotation.
    pub attitude: nalgebra::UnitQuaternion<f64>,
    /// Kinematic acceleration in the body frame (FRD), m/s^2, gravity not included.
    pub body_accel_m_s2: Vector3<f64>,
    /// Angular rate relative to the Earth in the body frame, rad/s.
    pub body_rate_rad_s: Vector3<f64>,
}

/// An autopilot's own estimate as it reports it (GPS_RAW_INT, GLOBAL_POSITION_INT and ATTITUDE,
/// stamped `time_boot_ms` of its clock), here exact: a simulated autopilot on GNSS. `fix`: the
/// GNSS fix it has (a 3D fix, or none). What the node's hand-over start reads
/// (`cooploc::node::handover`).
pub fn truth_to_autopilot_estimate(truth: &TrueMotion, origin: &GeoOrigin, time_boot_ms: u32, fix: bool) -> [MavMessage; 3] {
    use super::dialect::cooploc::{GPS_RAW_INT_DATA, GpsFixType};
    let g = ned_to_geodetic(origin, &truth.pos_ned_m);
    let v = truth.vel_ned_m_s * 100.0;
    let (roll, pitch, yaw) = truth.attitude.euler_angles();
    let (lat, lon) = (deg_to_e7(g.lat_deg), deg_to_e7(g.lon_deg));
    let alt = (g.alt_m * 1e3).round() as i32;
    [
        MavMessage::GPS_RAW_INT(GPS_RAW_INT_DATA {
            fix_type: if fix { GpsFixType::GPS_FIX_TYPE_3D_FIX } else { GpsFixType::GPS_FIX_TYPE_NO_FIX },
            lat: if fix { lat } else { 0 },
            lon: if fix { lon } else { 0 },
            alt: if fix { alt } else { 0 },
            satellites_visible: if fix { 12 } else { 0 },
            eph: u16::MAX,
            epv: u16::MAX,
            vel: u16::MAX,
            cog: u16::MAX,
            ..Default::default()
        }),
        MavMessage::GLOBAL_POSITION_INT(GLOBAL_POSITION_INT_DATA {
            time_boot_ms,
            lat,
            lon,
            alt,
            relative_alt: (-truth.pos_ned_m.z * 1e3).round() as i32,
            vx: v.x.round() as i16,
            vy: v.y.round() as i16,
            vz: v.z.round() as i16,
            hdg: ((yaw.to_degrees().rem_euclid(360.0)) * 100.0).round() as u16 % 36000,
        }),
        MavMessage::ATTITUDE(ATTITUDE_DATA {
            time_boot_ms,
            roll: roll as f32,
            pitch: pitch as f32,
            yaw: yaw as f32,
            rollspeed: truth.body_rate_rad_s.x as f32,
            pitchspeed: truth.body_rate_rad_s.y as f32,
            yawspeed: truth.body_rate_rad_s.z as f32,
        }),
    ]
}

/// Simulator truth as SIM_STATE: attitude quaternion (body FRD to NED, q1 = w) and Euler angles,
/// position as latitude/longitude (both the float and the 1e-7 deg integer fields) and altitude,
/// NED velocity, and body-frame specific force (the kinematic acceleration minus gravity) and
/// angular rate relative to the Earth (the vehicle's own motion, without the Earth-rate term the
/// IMU senses). Standard deviations are zero: this is the truth.
pub fn truth_to_sim_state(truth: &TrueMotion, origin: &GeoOrigin, gravity_m_s2: f64) -> MavMessage {
    let q = truth.attitude.quaternion();
    let (roll, pitch, yaw) = truth.attitude.euler_angles();
    let g = ned_to_geodetic(origin, &truth.pos_ned_m);
    let v = truth.vel_ned_m_s;
    let f_body = truth.body_accel_m_s2 - truth.attitude.inverse_transform_vector(&Vector3::new(0.0, 0.0, gravity_m_s2));
    let w = truth.body_rate_rad_s;
    MavMessage::SIM_STATE(SIM_STATE_DATA {
        q1: q.w as f32,
        q2: q.i as f32,
        q3: q.j as f32,
        q4: q.k as f32,
        roll: roll as f32,
        pitch: pitch as f32,
        yaw: yaw as f32,
        xacc: f_body[0] as f32,
        yacc: f_body[1] as f32,
        zacc: f_body[2] as f32,
        xgyro: w[0] as f32,
        ygyro: w[1] as f32,
        zgyro: w[2] as f32,
        lat: g.lat_deg as f32,
        lon: g.lon_deg as f32,
        alt: g.alt_m as f32,
        std_dev_horz: 0.0,
        std_dev_vert: 0.0,
        vn: v[0] as f32,
        ve: v[1] as f32,
        vd: v[2] as f32,
        lat_int: deg_to_e7(g.lat_deg),
        lon_int: deg_to_e7(g.lon_deg),
    })
}

/// A simulator's truth (SIM_STATE) in the local NED frame: every field the node and the ground
/// station use, checked.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SimStateTruth {
    pub pos_ned_m: Vector3<f64>,
    pub vel_ned_m_s: Vector3<f64>,
    pub att_frd_to_ned: nalgebra::UnitQuaternion<f64>,
    /// The message's own yaw field, rad.
    pub yaw_rad: f64,
}

/// A SIM_STATE about `origin`, checked: position as [`sim_state_position_ned`], finite velocity,
/// yaw and attitude, a unit attitude quaternion (within 1e-3).
pub fn sim_state_from_message(m: &SIM_STATE_DATA, origin: &GeoOrigin) -> Result<SimStateTruth, WireError> {
    const MSG: &str = "SIM_STATE";
    let pos_ned_m = sim_state_position_ned(m, origin)?;
    let vel_ned_m_s = Vector3::new(finite(MSG, "vn", m.vn)?, finite(MSG, "ve", m.ve)?, finite(MSG, "vd", m.vd)?);
    let yaw_rad = finite(MSG, "yaw", m.yaw)?;
    let q = nalgebra::Quaternion::new(
        finite(MSG, "q1", m.q1)?,
        finite(MSG, "q2", m.q2)?,
        finite(MSG, "q3", m.q3)?,
        finite(MSG, "q4", m.q4)?,
    );
    if (q.norm() - 1.0).abs() >= 1e-3 {
        return Err(bad(MSG, "q1", format!("attitude quaternion norm {} is not 1", q.norm())));
    }
    Ok(SimStateTruth { pos_ned_m, vel_ned_m_s, att_frd_to_ned: nalgebra::UnitQuaternion::from_quaternion(q), yaw_rad })
}

/// A node's initial state from a SIM_STATE (simulated vehicles): its position, velocity and
/// attitude, zero biases and scale error.
pub fn ins_state_from_sim_state(m: &SIM_STATE_DATA, origin: &GeoOrigin) -> Result<crate::estimation::ins::InsState, WireError> {
    let s = sim_state_from_message(m, origin)?;
    Ok(crate::estimation::ins::InsState {
        pos_ned_m: s.pos_ned_m,
        vel_ned_m_s: s.vel_ned_m_s,
        att_frd_to_ned: s.att_frd_to_ned,
        accel_bias_frd_m_s2: Vector3::zeros(),
        gyro_bias_frd_rad_s: Vector3::zeros(),
        odometer_scale_error: 0.0,
    })
}

/// The autopilot's own estimate as an initial state in the local NED frame of `origin`: position
/// and velocity from GLOBAL_POSITION_INT (degE7, mm above mean sea level, cm/s NED), attitude from
/// ATTITUDE (rad). Biases zero. The node's hand-over start (`cooploc::node::handover`).
pub fn ins_state_from_autopilot(
    p: &GLOBAL_POSITION_INT_DATA,
    a: &ATTITUDE_DATA,
    origin: &GeoOrigin,
) -> Result<crate::estimation::ins::InsState, WireError> {
    let pos = position_about("GLOBAL_POSITION_INT", (p.lat, p.lon, p.alt), origin)?;
    let vel = Vector3::new(f64::from(p.vx), f64::from(p.vy), f64::from(p.vz)) * 0.01;
    let (roll, pitch, yaw) =
        (finite("ATTITUDE", "roll", a.roll)?, finite("ATTITUDE", "pitch", a.pitch)?, finite("ATTITUDE", "yaw", a.yaw)?);
    Ok(crate::estimation::ins::InsState {
        pos_ned_m: pos,
        vel_ned_m_s: vel,
        att_frd_to_ned: nalgebra::UnitQuaternion::from_euler_angles(roll, pitch, yaw),
        accel_bias_frd_m_s2: Vector3::zeros(),
        gyro_bias_frd_rad_s: Vector3::zeros(),
        odometer_scale_error: 0.0,
    })
}

/// A latitude, longitude (1e-7 deg) and altitude (mm) of message `msg` in the local NED frame of
/// `origin`. Refused: outside the globe, 0, 0 (no position), more than 100 km from the origin.
fn position_about(msg: &'static str, (lat, lon, alt_mm): (i32, i32, i32), origin: &GeoOrigin) -> Result<Vector3<f64>, WireError> {
    let (lat_deg, lon_deg) = (e7_to_deg(lat), e7_to_deg(lon));
    if !(-90.0..=90.0).contains(&lat_deg) || !(-180.0..=180.0).contains(&lon_deg) || (lat == 0 && lon == 0) {
        return Err(bad(msg, "lat", format!("{lat_deg}, {lon_deg}: no position")));
    }
    let pos = geodetic_to_ned(origin, &Geodetic { lat_deg, lon_deg, alt_m: f64::from(alt_mm) * 1e-3 });
    if pos.xy().norm() > 100_000.0 {
        return Err(bad(msg, "lat", format!("{:.0} km from the origin", pos.xy().norm() * 1e-3)));
    }
    Ok(pos)
}

/// Horizontal one-sigma per unit of HDOP, m, for a GPS_RAW_INT without `h_acc` (a receiver
/// that gives only its dilution of precision: a typical single-frequency user range error).
pub const GNSS_UERE_M: f64 = 3.0;

/// A GPS_RAW_INT with a 3D fix (or better) as a position fix in the local NED frame of `origin`,
/// its time left at 0 (the caller maps `time_usec`, the autopilot's boot clock on ArduPilot and
/// PX4). The horizontal sigma is `h_acc`, else HDOP (`eph`) times [`GNSS_UERE_M`]; the vertical
/// one `v_acc` when given (else the height is not used). Refused: no 3D fix, no position, no
/// accuracy at all, more than 100 km from the origin.
pub fn position_fix_from_gps_raw(
    m: &super::dialect::cooploc::GPS_RAW_INT_DATA,
    origin: &GeoOrigin,
) -> Result<crate::estimation::PositionFixSample, WireError> {
    const MSG: &str = "GPS_RAW_INT";
    if (m.fix_type as u8) < 3 {
        return Err(bad(MSG, "fix_type", format!("{:?}: no 3D fix", m.fix_type)));
    }
    let pos = position_about(MSG, (m.lat, m.lon, m.alt), origin)?;
    let sigma_h_m = if m.h_acc > 0 {
        f64::from(m.h_acc) * 1e-3
    } else if m.eph != u16::MAX && m.eph > 0 {
        f64::from(m.eph) * 0.01 * GNSS_UERE_M
    } else {
        return Err(bad(MSG, "h_acc", "no accuracy (h_acc 0, eph unknown)"));
    };
    let fix = crate::estimation::PositionFixSample {
        t: TimeUs(0),
        pos_ned_m: pos,
        sigma_h_m,
        sigma_v_m: (m.v_acc > 0).then(|| f64::from(m.v_acc) * 1e-3),
    };
    fix.validate().map_err(|e| bad(MSG, "h_acc", e.to_string()))?;
    Ok(fix)
}

/// The position of a SIM_STATE (the integer fields when set, as MAVLink prescribes) in the local
/// NED frame of `origin`.
pub fn sim_state_position_ned(m: &SIM_STATE_DATA, origin: &GeoOrigin) -> Result<Vector3<f64>, WireError> {
    const MSG: &str = "SIM_STATE";
    let lat_deg = if m.lat_int != 0 { e7_to_deg(m.lat_int) } else { finite(MSG, "lat", m.lat)? };
    let lon_deg = if m.lon_int != 0 { e7_to_deg(m.lon_int) } else { finite(MSG, "lon", m.lon)? };
    if !(-90.0..=90.0).contains(&lat_deg) {
        return Err(bad(MSG, "lat_int", format!("{lat_deg} deg outside [-90, 90]")));
    }
    let alt_m = finite(MSG, "alt", m.alt)?;
    Ok(geodetic_to_ned(origin, &Geodetic { lat_deg, lon_deg, alt_m }))
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A GPS_RAW_INT as the real ArduPilot firmware sends it (Rover 4.7.0-dev 90700977, SITL,
    /// a 3D fix at its first position; captured from a node's log): its MAVLink 2 payload trimmed
    /// to 40 bytes after `v_acc`.
    const ARDUPILOT_GPS_RAW_INT: &str =
        "fd280000a40101180000f8119600000000009efeebeacbcee85840e908007900c80000000000060a40e908002c0100002c011447";

    #[test]
    fn the_real_firmwares_gps_raw_int_is_a_fix_with_its_accuracy() {
        let bytes: Vec<u8> = (0..ARDUPILOT_GPS_RAW_INT.len())
            .step_by(2)
            .map(|i| u8::from_str_radix(&ARDUPILOT_GPS_RAW_INT[i..i + 2], 16).unwrap())
            .collect();
        let (_, MavMessage::GPS_RAW_INT(m)) = from_any_frame(&bytes).unwrap() else { panic!("not GPS_RAW_INT") };
        assert_eq!((m.time_usec, m.alt, m.h_acc, m.v_acc, m.eph), (9_835_000, 584_000, 300, 300, 121));
        let origin = GeoOrigin { lat_deg: -35.363261, lon_deg: 149.16523, alt_m: 584.0 };
        let fix = position_fix_from_gps_raw(&m, &origin).unwrap();
        assert_eq!((fix.sigma_h_m, fix.sigma_v_m), (0.3, Some(0.3)));
        assert!(fix.pos_ned_m.norm() < 0.05, "{:?}", fix.pos_ned_m);
    }

    /// An estimate as sent is what a receiver decodes from its frame (f32, the covariance's
    /// upper triangle), and sending it again changes nothing; one no receiver would take is
    /// refused.
    #[test]
    fn an_estimate_as_sent_is_what_a_receiver_decodes() {
        let mut c = Matrix3::new(2.1, 0.3, 0.01, 0.31, 1.7, 0.02, 0.01, 0.02, 0.5);
        c[(1, 0)] = 0.300_000_1; // (a lower triangle the wire does not carry)
        let e = EstimateReport {
            platform: 3,
            t: TimeUs(12_345_678),
            epoch: 41,
            method: Method::Decentralized,
            position_ned_m: Vector3::new(259.612_612_345_678, 150.096_1, -0.123_456_789),
            velocity_ned_m_s: Vector3::new(8.671_921_696, 5.029_6, -0.000_47),
            yaw_rad: 0.612_345_678_9,
            position_covariance_m2: c,
            yaw_variance_rad2: 1.234_567_89e-4,
            nis: f64::NAN,
            participants: 3,
            ranges: 2,
        };
        let frame = to_frame(MavHeader { system_id: 3, component_id: COMPANION_COMPID, sequence: 0 }, &estimate_to_message(&e));
        let (_, MavMessage::COOPLOC_ESTIMATE(m)) = from_any_frame(&frame).unwrap() else { panic!("not COOPLOC_ESTIMATE") };
        let received = estimate_from_message(&m).unwrap();
        let sent = e.as_sent().unwrap();
        let bits = |r: &EstimateReport| {
            let mut v: Vec<u64> = r.position_ned_m.iter().chain(r.velocity_ned_m_s.iter()).map(|x| x.to_bits()).collect();
            v.extend(r.position_covariance_m2.iter().map(|x| x.to_bits()));
            v.extend([r.yaw_rad, r.yaw_variance_rad2, r.nis].map(f64::to_bits));
            v
        };
        assert_eq!(bits(&sent), bits(&received));
        assert_eq!((sent.platform, sent.t, sent.epoch, sent.participants, sent.ranges), (3, e.t, 41, 3, 2));
        assert_ne!(sent.position_ned_m, e.position_ned_m, "f32 on the wire");
        assert_eq!(sent.position_covariance_m2[(1, 0)], sent.position_covariance_m2[(0, 1)]);
        assert_eq!(bits(&sent.as_sent().unwrap()), bits(&sent));
        let nan = EstimateReport { position_ned_m: Vector3::new(f64::NAN, 0.0, 0.0), ..e.clone() };
        assert!(nan.as_sent().is_err());
        let mut negative = e;
        negative.position_covariance_m2[(0, 0)] = -1.0;
        assert!(negative.as_sent().is_err());
    }

    fn sim_state() -> SIM_STATE_DATA {
        let origin = GeoOrigin { lat_deg: 43.0, lon_deg: -79.0, alt_m: 0.0 };
        let g = ned_to_geodetic(&origin, &Vector3::new(10.0, -5.0, 0.0));
        SIM_STATE_DATA {
            q1: 1.0,
            lat_int: deg_to_e7(g.lat_deg),
            lon_int: deg_to_e7(g.lon_deg),
            vn: 2.0,
            yaw: 0.5,
            ..Default::default()
        }
    }

    #[test]
    fn a_sim_state_is_checked_field_by_field() {
        let origin = GeoOrigin { lat_deg: 43.0, lon_deg: -79.0, alt_m: 0.0 };
        let ok = sim_state_from_message(&sim_state(), &origin).unwrap();
        assert!((ok.pos_ned_m - Vector3::new(10.0, -5.0, 0.0)).norm() < 0.02, "{}", ok.pos_ned_m);
        assert_eq!((ok.vel_ned_m_s[0], ok.yaw_rad), (2.0, 0.5));
        for (field, m) in [
            ("vn", SIM_STATE_DATA { vn: f32::NAN, ..sim_state() }),
            ("yaw", SIM_STATE_DATA { yaw: f32::INFINITY, ..sim_state() }),
            ("q1", SIM_STATE_DATA { q1: 0.5, ..sim_state() }),
            ("q3", SIM_STATE_DATA { q3: f32::NAN, ..sim_state() }),
        ] {
            let e = sim_state_from_message(&m, &origin).unwrap_err().to_string();
            assert!(e.starts_with(&format!("SIM_STATE.{field}:")), "{e}");
        }
        let s = ins_state_from_sim_state(&sim_state(), &origin).unwrap();
        assert_eq!(s.vel_ned_m_s, ok.vel_ned_m_s);
        assert_eq!(s.odometer_scale_error, 0.0);
    }

    fn announcement(participants: Vec<PlatformId>, incomplete: Vec<HeldFragments>) -> EpochAnnouncement {
        EpochAnnouncement {
            epoch: 7,
            t: TimeUs(7_000_000),
            announcer: 2,
            participants,
            state: EpochState::COOPLOC_EPOCH_STATE_COLLECTING,
            digest: 0xfeed,
            incomplete,
        }
    }

    fn signed_len(m: &MavMessage) -> usize {
        // A MAVLink 2 frame: 10 header and 2 CRC bytes, the payload with its trailing zeros
        // trimmed, 13 signature bytes.
        let mut payload = [0u8; 255];
        let n = m.ser(MavlinkVersion::V2, &mut payload);
        12 + n + 13
    }

    #[test]
    fn an_epoch_announcement_goes_as_a_bitmask_within_64_ids_and_as_a_list_beyond() {
        let held = |platform, held| HeldFragments { platform, held };
        let a = announcement(vec![1, 2, 64], vec![held(3, 0b101101)]);
        let m = epoch_to_message(&a).unwrap();
        assert!(matches!(&m, MavMessage::COOPLOC_EPOCH_SET(s) if s.base == 1 && s.participants == 1 | 2 | 1 << 63));
        assert_eq!(epoch_of(&m), Some(Ok(a)));
        // No incomplete record: the trailing arrays are trimmed (58 bytes signed; the list form
        // keeps its 64-entry array whole before the digest).
        let applied = EpochAnnouncement { state: EpochState::COOPLOC_EPOCH_STATE_APPLIED, ..announcement(vec![1, 2, 3], vec![]) };
        let plain = epoch_to_message(&applied).unwrap();
        assert_eq!(signed_len(&plain), 58);
        // Ids more than 63 apart: the list, without the incomplete records.
        let far = EpochAnnouncement { digest: u64::MAX, ..announcement(vec![1, 65], vec![held(3, 1)]) };
        let m = epoch_to_message(&far).unwrap();
        assert!(matches!(m, MavMessage::COOPLOC_EPOCH(_)));
        assert_eq!(signed_len(&m), 177);
        assert_eq!(epoch_of(&m), Some(Ok(EpochAnnouncement { incomplete: vec![], ..far })));
        // Near the top of the id space, and nobody at all.
        let top = announcement(vec![u16::MAX - 1, u16::MAX], vec![]);
        assert_eq!(epoch_of(&epoch_to_message(&top).unwrap()), Some(Ok(top)));
        let empty = announcement(vec![], vec![]);
        assert_eq!(epoch_of(&epoch_to_message(&empty).unwrap()), Some(Ok(empty)));
        let five = announcement(vec![1], (2..7).map(|p| held(p, 1)).collect());
        assert!(epoch_to_message(&five).unwrap_err().to_string().contains("COOPLOC_EPOCH_SET.incomplete"));
        assert!(held(3, 1 << 31).holds(31) && !held(3, 1 << 31).holds(30) && !held(3, u32::MAX).holds(32));
    }

    #[test]
    fn an_epoch_set_is_checked_field_by_field() {
        let MavMessage::COOPLOC_EPOCH_SET(ok) = epoch_to_message(&announcement(vec![1, 2], vec![])).unwrap() else {
            unreachable!()
        };
        for (field, m) in [
            ("participants", COOPLOC_EPOCH_SET_DATA { base: u16::MAX, participants: 0b10, ..ok.clone() }),
            ("held", COOPLOC_EPOCH_SET_DATA { held: [0, 5, 0, 0], ..ok.clone() }),
            ("incomplete", COOPLOC_EPOCH_SET_DATA { incomplete: [65, 0, 0, 0], held: [1, 0, 0, 0], ..ok.clone() }),
            ("incomplete", COOPLOC_EPOCH_SET_DATA { incomplete: [3, 3, 0, 0], held: [1, 2, 0, 0], ..ok.clone() }),
            ("incomplete", COOPLOC_EPOCH_SET_DATA { base: u16::MAX, participants: 1, incomplete: [2, 0, 0, 0], ..ok.clone() }),
        ] {
            let e = epoch_set_from_message(&m).unwrap_err().to_string();
            assert!(e.starts_with(&format!("COOPLOC_EPOCH_SET.{field}:")), "{field}: {e}");
        }
    }

    /// What a node asking for a store holds goes as it was; it holds a fragment when it holds
    /// that part whole or that fragment of that series; a mask without a series, or naming a
    /// 256th fragment, is refused.
    #[test]
    fn what_a_node_holds_of_a_store_round_trips_and_is_checked() {
        let h = StoreHeld {
            epoch: 7,
            t: TimeUs(7_000_000),
            announcer: 3,
            digest_before: 0xDEAD_BEEF,
            whole: bits_at([0, 2, 200, 300]),
            series: Some((0x1234_5678, bits_at([0, 63, 64, 254]))),
        };
        assert_eq!(h.whole, [0b101, 0, 0, 1 << 8], "bit 300 is beyond the mask");
        let MavMessage::COOPLOC_STORE_HELD(m) = store_held_to_message(&h) else { unreachable!() };
        assert_eq!(store_held_from_message(&m), Ok(h.clone()));
        let none = StoreHeld { series: None, ..h.clone() };
        let MavMessage::COOPLOC_STORE_HELD(n) = store_held_to_message(&none) else { unreachable!() };
        assert_eq!((n.series_crc32, n.held), (0, [0; 4]));
        assert_eq!(store_held_from_message(&n), Ok(none));
        assert!(h.holds(2, 1, 9) && h.holds(1, 0x1234_5678, 64) && h.holds(1, 0x1234_5678, 254));
        assert!(!h.holds(1, 0x1234_5678, 65) && !h.holds(1, 0x1234_5679, 64) && !h.holds(3, 0, 0));
        for (field, bad) in [
            ("held", COOPLOC_STORE_HELD_DATA { series_crc32: 0, ..m.clone() }),
            ("held", COOPLOC_STORE_HELD_DATA { held: [0, 0, 0, 1 << 63], ..m.clone() }),
        ] {
            let e = store_held_from_message(&bad).unwrap_err().to_string();
            assert!(e.starts_with(&format!("COOPLOC_STORE_HELD.{field}:")), "{field}: {e}");
        }
    }
}
