//! The cooperative network's messages, typed: what a node, a ground station or the replay reads
//! from a peer, decoded and validated in one place ([`CoopMessage::decode`], through the field
//! checks of [`super::wire`]) from the MAVLink message. Each holder then checks what only it can:
//! that the platform a message claims is the system that sent it ([`CoopMessage::claimed_sender`]),
//! that it is a team member, that a fragment fits a record.

use super::MavMessage;
use super::fragment::Fragment;
use super::wire::{self, EpochAnnouncement, EstimateReport, WireError};
use crate::estimation::{PlatformId, RangeSample};

/// A message of the cooperative network, decoded and validated.
#[derive(Debug, Clone, PartialEq)]
pub enum CoopMessage {
    /// A fragment of a peer's state record (COOPLOC_STATE_FRAGMENT).
    StateFragment(Fragment),
    /// A fragment of a peer's cross-covariance store, sent to heal a teammate
    /// (COOPLOC_STORE_FRAGMENT).
    StoreFragment(Fragment),
    /// A range a peer's radio measured at `epoch` (COOPLOC_RANGE).
    Range { epoch: u32, range: RangeSample },
    /// Where a peer is with an epoch (COOPLOC_EPOCH or COOPLOC_EPOCH_SET).
    Epoch(EpochAnnouncement),
    /// A node's estimate (COOPLOC_ESTIMATE).
    Estimate(EstimateReport),
}

/// Which cooperative message (also for one that failed to decode).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum CoopKind {
    StateFragment,
    StoreFragment,
    Range,
    Epoch,
    Estimate,
}

impl CoopKind {
    /// The MAVLink message name.
    pub fn name(self) -> &'static str {
        match self {
            CoopKind::StateFragment => "COOPLOC_STATE_FRAGMENT",
            CoopKind::StoreFragment => "COOPLOC_STORE_FRAGMENT",
            CoopKind::Range => "COOPLOC_RANGE",
            CoopKind::Epoch => "COOPLOC_EPOCH",
            CoopKind::Estimate => "COOPLOC_ESTIMATE",
        }
    }

    /// The kind of a MAVLink message, when it is a cooperative one.
    pub fn of(msg: &MavMessage) -> Option<CoopKind> {
        Some(match msg {
            MavMessage::COOPLOC_STATE_FRAGMENT(_) => CoopKind::StateFragment,
            MavMessage::COOPLOC_STORE_FRAGMENT(_) => CoopKind::StoreFragment,
            MavMessage::COOPLOC_RANGE(_) => CoopKind::Range,
            MavMessage::COOPLOC_EPOCH(_) | MavMessage::COOPLOC_EPOCH_SET(_) => CoopKind::Epoch,
            MavMessage::COOPLOC_ESTIMATE(_) => CoopKind::Estimate,
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
            MavMessage::COOPLOC_RANGE(m) => wire::range_from_message(m).map(|(epoch, range)| CoopMessage::Range { epoch, range }),
            MavMessage::COOPLOC_EPOCH(m) => wire::epoch_from_message(m).map(CoopMessage::Epoch),
            MavMessage::COOPLOC_EPOCH_SET(m) => wire::epoch_set_from_message(m).map(CoopMessage::Epoch),
            MavMessage::COOPLOC_ESTIMATE(m) => wire::estimate_from_message(m).map(CoopMessage::Estimate),
            _ => return None,
        };
        Some(decoded.map_err(|error| CoopError { kind, error }))
    }

    pub fn kind(&self) -> CoopKind {
        match self {
            CoopMessage::StateFragment(_) => CoopKind::StateFragment,
            CoopMessage::StoreFragment(_) => CoopKind::StoreFragment,
            CoopMessage::Range { .. } => CoopKind::Range,
            CoopMessage::Epoch(_) => CoopKind::Epoch,
            CoopMessage::Estimate(_) => CoopKind::Estimate,
        }
    }

    /// The platform the message says it comes from (a fragment's platform, a range's measuring
    /// platform, an epoch's announcer, an estimate's platform): a receiver takes it only from
    /// that platform's own system.
    pub fn claimed_sender(&self) -> PlatformId {
        match self {
            CoopMessage::StateFragment(f) | CoopMessage::StoreFragment(f) => f.platform,
            CoopMessage::Range { range, .. } => range.from,
            CoopMessage::Epoch(a) => a.announcer,
            CoopMessage::Estimate(r) => r.platform,
        }
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
        assert_eq!((got.kind(), got.claimed_sender()), (CoopKind::Range, 3));
        assert!(matches!(got, CoopMessage::Range { epoch: 2, .. }));
        let hb = wire::heartbeat(MavType::MAV_TYPE_GCS, MavAutopilot::MAV_AUTOPILOT_INVALID);
        assert!(CoopMessage::decode(&hb).is_none());
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
