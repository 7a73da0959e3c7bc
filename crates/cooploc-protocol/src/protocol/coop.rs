//! The cooperative network's messages, typed: what a node, a ground station or the replay reads
//! from a peer, decoded and validated in one place ([`CoopMessage::decode`], through the field
//! checks of [`super::wire`]) from the MAVLink message. Each holder then checks what only it can:
//! that the platform a message claims is the system that sent it ([`CoopMessage::claimed_sender`]),
//! that it is a team member, that a fragment fits a record.

use super::MavMessage;
use super::fragment::Fragment;
use super::wire::{self, EpochAnnouncement, EstimateReport, MessageRequest, StoreHeld, WireError};
use crate::estimation::{PlatformId, RangeSample};

/// A message of the cooperative network, decoded and validated.
#[derive(Debug, Clone, PartialEq)]
pub enum CoopMessage {
    /// A fragment of a peer's state record (COOPLOC_STATE_FRAGMENT).
    StateFragment(Fragment),
    /// A fragment of a peer's cross-covariance store, sent to heal a teammate
    /// (COOPLOC_STORE_FRAGMENT).
    StoreFragment(Fragment),
    /// What a node that asks for a store holds of it (COOPLOC_STORE_HELD).
    StoreHeld(StoreHeld),
    /// A range a peer's radio measured at `epoch` (COOPLOC_RANGE).
    Range { epoch: u32, range: RangeSample },
    /// Where a peer is with an epoch (COOPLOC_EPOCH or COOPLOC_EPOCH_SET).
    Epoch(EpochAnnouncement),
    /// A node's estimate (COOPLOC_ESTIMATE).
    Estimate(EstimateReport),
    /// A ground station asks a node for a message (MAV_CMD_REQUEST_MESSAGE).
    MessageRequest(MessageRequest),
}

/// Which cooperative message (also for one that failed to decode).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum CoopKind {
    StateFragment,
    StoreFragment,
    StoreHeld,
    Range,
    Epoch,
    Estimate,
    MessageRequest,
}

impl CoopKind {
    /// The MAVLink message name.
    pub fn name(self) -> &'static str {
        match self {
            CoopKind::StateFragment => "COOPLOC_STATE_FRAGMENT",
            CoopKind::StoreFragment => "COOPLOC_STORE_FRAGMENT",
            CoopKind::StoreHeld => "COOPLOC_STORE_HELD",
            CoopKind::Range => "COOPLOC_RANGE",
            CoopKind::Epoch => "COOPLOC_EPOCH",
            CoopKind::Estimate => "COOPLOC_ESTIMATE",
            CoopKind::MessageRequest => "MAV_CMD_REQUEST_MESSAGE",
        }
    }

    /// The kind of a MAVLink message, when it is a cooperative one.
    pub fn of(msg: &MavMessage) -> Option<CoopKind> {
        Some(match msg {
            MavMessage::COOPLOC_STATE_FRAGMENT(_) => CoopKind::StateFragment,
            MavMessage::COOPLOC_STORE_FRAGMENT(_) => CoopKind::StoreFragment,
            MavMessage::COOPLOC_STORE_HELD(_) => CoopKind::StoreHeld,
            MavMessage::COOPLOC_RANGE(_) => CoopKind::Range,
            MavMessage::COOPLOC_EPOCH(_) | MavMessage::COOPLOC_EPOCH_SET(_) => CoopKind::Epoch,
            MavMessage::COOPLOC_ESTIMATE(_) => CoopKind::Estimate,
            m if wire::message_request_from(m).is_some() => CoopKind::MessageRequest,
            _ => return None,
        })
    }
}

/// A cooperative message that failed its field checks.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
#[error("{error}")]
pub struct CoopError {
    pub kind: CoopKind,
    pub error: WireError,
}

impl CoopMessage {
    /// The cooperative message `msg` is, checked field by field; `None` when it is not one
    /// (heartbeats, commands, a vehicle's messages).
    pub fn decode(msg: &MavMessage) -> Option<Result<CoopMessage, CoopError>> {
        let kind = CoopKind::of(msg)?;
        let decoded = match msg {
            MavMessage::COOPLOC_STATE_FRAGMENT(m) => wire::fragment_from_message(m).map(CoopMessage::StateFragment),
            MavMessage::COOPLOC_STORE_FRAGMENT(m) => wire::store_fragment_from_message(m).map(CoopMessage::StoreFragment),
            MavMessage::COOPLOC_STORE_HELD(m) => wire::store_held_from_message(m).map(CoopMessage::StoreHeld),
            MavMessage::COOPLOC_RANGE(m) => wire::range_from_message(m).map(|(epoch, range)| CoopMessage::Range { epoch, range }),
            MavMessage::COOPLOC_EPOCH(m) => wire::epoch_from_message(m).map(CoopMessage::Epoch),
            MavMessage::COOPLOC_EPOCH_SET(m) => wire::epoch_set_from_message(m).map(CoopMessage::Epoch),
            MavMessage::COOPLOC_ESTIMATE(m) => wire::estimate_from_message(m).map(CoopMessage::Estimate),
            m => return wire::message_request_from(m).map(|r| Ok(CoopMessage::MessageRequest(r))),
        };
        Some(decoded.map_err(|error| CoopError { kind, error }))
    }

    pub fn kind(&self) -> CoopKind {
        match self {
            CoopMessage::StateFragment(_) => CoopKind::StateFragment,
            CoopMessage::StoreFragment(_) => CoopKind::StoreFragment,
            CoopMessage::StoreHeld(_) => CoopKind::StoreHeld,
            CoopMessage::Range { .. } => CoopKind::Range,
            CoopMessage::Epoch(_) => CoopKind::Epoch,
            CoopMessage::Estimate(_) => CoopKind::Estimate,
            CoopMessage::MessageRequest(_) => CoopKind::MessageRequest,
        }
    }

    /// The platform the message says it comes from (a fragment's platform, a range's measuring
    /// platform, an epoch's announcer, an estimate's platform): a receiver takes it only from
    /// that platform's own system. None: a ground station's request, which claims no platform.
    pub fn claimed_sender(&self) -> Option<PlatformId> {
        Some(match self {
            CoopMessage::StateFragment(f) | CoopMessage::StoreFragment(f) => f.platform,
            CoopMessage::Range { range, .. } => range.from,
            CoopMessage::Epoch(a) => a.announcer,
            CoopMessage::StoreHeld(h) => h.announcer,
            CoopMessage::Estimate(r) => r.platform,
            CoopMessage::MessageRequest(_) => return None,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::protocol::dialect::cooploc::{MavAutopilot, MavType};
    use crate::time::TimeUs;

    #[test]
    fn messages_decode_to_their_kind_and_claimed_sender_and_others_are_not_cooperative() {
        let range = RangeSample { t: TimeUs(2_000_000), from: 3, to: 1, range_m: 12.5, sigma_m: 0.5 };
        let m = wire::range_to_message(&range, 2);
        let got = CoopMessage::decode(&m).unwrap().unwrap();
        assert_eq!((got.kind(), got.claimed_sender()), (CoopKind::Range, Some(3)));
        assert!(matches!(got, CoopMessage::Range { epoch: 2, .. }));
        let hb = wire::heartbeat(MavType::MAV_TYPE_GCS, MavAutopilot::MAV_AUTOPILOT_INVALID);
        assert!(CoopMessage::decode(&hb).is_none());
    }

    /// A ground station's MAV_CMD_REQUEST_MESSAGE (COMMAND_LONG or COMMAND_INT) is a cooperative
    /// message claiming no platform: for a node when addressed to its system (or 0) and its
    /// component (or 0); it asks for the estimate only by COOPLOC_ESTIMATE's id. Another command
    /// is not cooperative.
    #[test]
    fn a_ground_stations_request_is_decoded_with_its_address_and_claims_no_platform() {
        use crate::protocol::dialect::cooploc::{COMMAND_INT_DATA, COMMAND_LONG_DATA, MavCmd};
        let long = |target_system, target_component, param1| {
            MavMessage::COMMAND_LONG(COMMAND_LONG_DATA {
                command: MavCmd::MAV_CMD_REQUEST_MESSAGE,
                param1,
                target_system,
                target_component,
                ..Default::default()
            })
        };
        let id = wire::ESTIMATE_MESSAGE_ID as f32;
        let got = CoopMessage::decode(&long(2, wire::COMPANION_COMPID, id)).unwrap().unwrap();
        assert_eq!((got.kind(), got.claimed_sender()), (CoopKind::MessageRequest, None));
        let CoopMessage::MessageRequest(r) = got else { panic!("{got:?}") };
        assert!(r.is_for(2) && !r.is_for(3) && r.asks_estimate());
        let request = |m: &MavMessage| match CoopMessage::decode(m) {
            Some(Ok(CoopMessage::MessageRequest(r))) => r,
            other => panic!("{other:?}"),
        };
        assert!(request(&long(0, 0, id)).is_for(3), "to everyone");
        assert!(!request(&long(2, 1, id)).is_for(2), "to the autopilot");
        assert!(!request(&long(2, 0, 33.0)).asks_estimate());
        assert!(!request(&long(2, 0, f32::NAN)).asks_estimate());
        let int = MavMessage::COMMAND_INT(COMMAND_INT_DATA {
            command: MavCmd::MAV_CMD_REQUEST_MESSAGE,
            param1: id,
            target_system: 2,
            ..Default::default()
        });
        assert!(request(&int).is_for(2) && request(&int).asks_estimate());
        let arm =
            MavMessage::COMMAND_LONG(COMMAND_LONG_DATA { command: MavCmd::MAV_CMD_COMPONENT_ARM_DISARM, ..Default::default() });
        assert!(CoopMessage::decode(&arm).is_none());
    }

    #[test]
    fn a_message_that_fails_its_checks_says_which_and_why() {
        let range = RangeSample { t: TimeUs(2_000_000), from: 3, to: 1, range_m: 12.5, sigma_m: 0.5 };
        let MavMessage::COOPLOC_RANGE(mut m) = wire::range_to_message(&range, 2) else { unreachable!() };
        m.distance = f32::NAN;
        let err = CoopMessage::decode(&MavMessage::COOPLOC_RANGE(m)).unwrap().unwrap_err();
        assert_eq!(err.kind, CoopKind::Range);
        assert!(err.to_string().contains("COOPLOC_RANGE.distance"), "{err}");
    }
}
