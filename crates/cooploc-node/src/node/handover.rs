//! The hand-over start, sans-io: a vehicle that starts with GNSS navigates on its autopilot's
//! own estimate until GNSS goes; the node then starts from that estimate and the autopilot
//! switches to the node's ODOMETRY.
//!
//! [`Handover`] follows the autopilot's GNSS fix (GPS_RAW_INT `fix_type`) and its estimate
//! (GLOBAL_POSITION_INT, ATTITUDE). When a fix it has seen (3D or better) is gone for
//! [`LOST_AFTER`] GPS_RAW_INT messages in a row, it says [`HandoverEvent::GnssLost`] once, with
//! the autopilot's latest estimate: the node initialises from it, at its time, so the first
//! ODOMETRY it sends continues the estimate the autopilot was flying on (no step), and asks
//! the autopilot to change its EKF source set (ArduPilot: MAV_CMD_SET_EKF_SOURCE_SET, from a
//! set on GNSS to one on external navigation), as ArduPilot's own source-switching scripts do.
//!
//! What it does not do (yet): follow the autopilot's estimate with the team's filters running
//! before the loss (the node starts at the loss), or hand back when GNSS returns.

use crate::estimation::ins::InsState;
use crate::protocol::MavMessage;
use crate::protocol::dialect::cooploc::{ATTITUDE_DATA, COMMAND_LONG_DATA, GLOBAL_POSITION_INT_DATA, MavCmd};
use crate::protocol::wire::{self, GeoOrigin};

/// GPS_RAW_INT messages without a 3D fix, in a row, that make a loss (one is a glitch).
pub const LOST_AFTER: u32 = 2;
/// GLOBAL_POSITION_INT and ATTITUDE older than this (of the autopilot's boot clock) at the loss
/// are no estimate to start from, ms.
pub const STALE_MS: u32 = 1_000;
/// GPS_RAW_INT `fix_type` of a 3D fix.
const FIX_3D: u8 = 3;

/// What the autopilot's messages say about the hand-over.
#[derive(Debug, Clone, PartialEq)]
pub enum HandoverEvent {
    /// GNSS is gone: start from the autopilot's estimate, stamped in its boot clock (ms).
    GnssLost { time_boot_ms: u32, state: Box<InsState> },
    /// GNSS is gone but the autopilot's estimate is missing or stale (said, then the node waits
    /// for a fresh one).
    GnssLostWithoutEstimate,
}

/// Follows the autopilot's fix and estimate (see the module documentation).
#[derive(Debug, Clone, Default)]
pub struct Handover {
    had_fix: bool,
    without_fix: u32,
    lost: bool,
    started: bool,
    position: Option<GLOBAL_POSITION_INT_DATA>,
    attitude: Option<ATTITUDE_DATA>,
    /// Estimates refused (no position, not finite, far from the origin).
    pub refused: u64,
}

impl Handover {
    pub fn new() -> Self {
        Self::default()
    }

    /// Takes one of the autopilot's messages; `origin` is the team's frame.
    pub fn on_message(&mut self, msg: &MavMessage, origin: &GeoOrigin) -> Option<HandoverEvent> {
        match msg {
            MavMessage::GPS_RAW_INT(m) => {
                if (m.fix_type as u8) >= FIX_3D {
                    self.had_fix = true;
                    self.without_fix = 0;
                    return None;
                }
                self.without_fix = self.without_fix.saturating_add(1);
                if self.had_fix && !self.lost && self.without_fix >= LOST_AFTER {
                    self.lost = true;
                }
            }
            MavMessage::GLOBAL_POSITION_INT(m) => self.position = Some(m.clone()),
            MavMessage::ATTITUDE(m) => self.attitude = Some(m.clone()),
            _ => return None,
        }
        if !self.lost || self.started {
            return None;
        }
        let (Some(p), Some(a)) = (&self.position, &self.attitude) else { return None };
        if p.time_boot_ms.abs_diff(a.time_boot_ms) > STALE_MS {
            return None; // one of them is old: the next message of the other brings them together
        }
        match wire::ins_state_from_autopilot(p, a, origin) {
            Ok(state) => {
                self.started = true;
                Some(HandoverEvent::GnssLost { time_boot_ms: p.time_boot_ms.max(a.time_boot_ms), state: Box::new(state) })
            }
            Err(e) => {
                self.refused += 1;
                tracing::warn!(error = %e, "the autopilot's estimate cannot start the node");
                self.position = None;
                Some(HandoverEvent::GnssLostWithoutEstimate)
            }
        }
    }

    /// The start it gave could not be taken (the team clock is not mapped yet): the next fresh
    /// estimate gives it again.
    pub fn retry(&mut self) {
        self.started = false;
    }

    /// GNSS has been lost (after a fix).
    pub fn lost(&self) -> bool {
        self.lost
    }
}

/// ArduPilot's MAV_CMD_SET_EKF_SOURCE_SET: the EKF's sources from set `set` (1-3) on.
pub fn ekf_source_set(set: u8, target_system: u8) -> MavMessage {
    MavMessage::COMMAND_LONG(COMMAND_LONG_DATA {
        command: MavCmd::MAV_CMD_SET_EKF_SOURCE_SET,
        param1: f32::from(set),
        target_system,
        target_component: 1,
        ..Default::default()
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::protocol::dialect::cooploc::{GPS_RAW_INT_DATA, GpsFixType};

    const ORIGIN: GeoOrigin = GeoOrigin { lat_deg: -35.363261, lon_deg: 149.16523, alt_m: 584.0 };

    fn fix(fix_type: GpsFixType) -> MavMessage {
        MavMessage::GPS_RAW_INT(GPS_RAW_INT_DATA { fix_type, ..Default::default() })
    }

    fn position(time_boot_ms: u32, north_m: f64) -> MavMessage {
        let (lat, lon) = (ORIGIN.lat_deg + north_m / 111_319.49, ORIGIN.lon_deg);
        MavMessage::GLOBAL_POSITION_INT(GLOBAL_POSITION_INT_DATA {
            time_boot_ms,
            lat: wire::deg_to_e7(lat),
            lon: wire::deg_to_e7(lon),
            alt: 584_000,
            vx: 150,
            vy: -20,
            ..Default::default()
        })
    }

    fn attitude(time_boot_ms: u32, yaw: f32) -> MavMessage {
        MavMessage::ATTITUDE(ATTITUDE_DATA { time_boot_ms, yaw, ..Default::default() })
    }

    #[test]
    fn the_node_starts_from_the_autopilots_estimate_when_gnss_goes() {
        let mut h = Handover::new();
        for m in [fix(GpsFixType::GPS_FIX_TYPE_3D_FIX), position(1_000, 5.0), attitude(1_010, 0.5)] {
            assert_eq!(h.on_message(&m, &ORIGIN), None, "a fix: nothing to do");
        }
        // one message without a fix is a glitch
        assert_eq!(h.on_message(&fix(GpsFixType::GPS_FIX_TYPE_NO_FIX), &ORIGIN), None);
        assert_eq!(h.on_message(&fix(GpsFixType::GPS_FIX_TYPE_3D_FIX), &ORIGIN), None);
        assert_eq!(h.on_message(&fix(GpsFixType::GPS_FIX_TYPE_NO_FIX), &ORIGIN), None);
        assert!(!h.lost());
        // two in a row: lost; the estimate it has starts the node
        let Some(HandoverEvent::GnssLost { time_boot_ms, state }) = h.on_message(&fix(GpsFixType::GPS_FIX_TYPE_NO_GPS), &ORIGIN)
        else {
            panic!("a start")
        };
        assert_eq!(time_boot_ms, 1_010);
        assert!((state.pos_ned_m - nalgebra::Vector3::new(5.0, 0.0, 0.0)).norm() < 0.02, "{}", state.pos_ned_m);
        assert!((state.vel_ned_m_s - nalgebra::Vector3::new(1.5, -0.2, 0.0)).norm() < 1e-9);
        assert!((state.att_frd_to_ned.euler_angles().2 - 0.5).abs() < 1e-6);
        // once
        assert_eq!(h.on_message(&position(1_100, 5.2), &ORIGIN), None);
        assert_eq!(h.on_message(&fix(GpsFixType::GPS_FIX_TYPE_NO_FIX), &ORIGIN), None);
        // unless the node could not take it (its clock not mapped yet): then the next estimate
        h.retry();
        let Some(HandoverEvent::GnssLost { time_boot_ms, state }) = h.on_message(&attitude(1_110, 0.5), &ORIGIN) else {
            panic!("a start again")
        };
        assert_eq!(time_boot_ms, 1_110);
        assert!((state.pos_ned_m.x - 5.2).abs() < 0.02);
    }

    #[test]
    fn no_fix_from_power_on_is_not_a_loss_and_stale_or_bad_estimates_start_nothing() {
        let mut h = Handover::new();
        for _ in 0..10 {
            assert_eq!(h.on_message(&fix(GpsFixType::GPS_FIX_TYPE_NO_GPS), &ORIGIN), None);
        }
        assert!(!h.lost(), "never had a fix: the other start (configured state) is the node's");
        // lost with an attitude 5 s older than the position: waits for a fresh one
        let mut h = Handover::new();
        h.on_message(&fix(GpsFixType::GPS_FIX_TYPE_RTK_FIXED), &ORIGIN);
        h.on_message(&attitude(1_000, 0.0), &ORIGIN);
        h.on_message(&position(6_000, 0.0), &ORIGIN);
        h.on_message(&fix(GpsFixType::GPS_FIX_TYPE_NO_FIX), &ORIGIN);
        assert_eq!(h.on_message(&fix(GpsFixType::GPS_FIX_TYPE_NO_FIX), &ORIGIN), None);
        assert!(h.lost());
        assert!(matches!(h.on_message(&attitude(6_020, 0.1), &ORIGIN), Some(HandoverEvent::GnssLost { .. })));
        // a position of 0, 0 (none yet) or 200 km away is refused, said once per estimate
        let mut h = Handover::new();
        h.on_message(&fix(GpsFixType::GPS_FIX_TYPE_3D_FIX), &ORIGIN);
        h.on_message(&attitude(1_000, 0.0), &ORIGIN);
        h.on_message(&position(1_000, 200_000.0), &ORIGIN);
        h.on_message(&fix(GpsFixType::GPS_FIX_TYPE_NO_FIX), &ORIGIN);
        assert_eq!(h.on_message(&fix(GpsFixType::GPS_FIX_TYPE_NO_FIX), &ORIGIN), Some(HandoverEvent::GnssLostWithoutEstimate));
        assert_eq!(h.refused, 1);
        assert_eq!(h.on_message(&attitude(1_040, 0.0), &ORIGIN), None, "no position until a new one");
        let Some(HandoverEvent::GnssLost { state, .. }) = h.on_message(&position(1_050, 3.0), &ORIGIN) else { panic!() };
        assert!((state.pos_ned_m.x - 3.0).abs() < 0.02);
        // NaN attitude: refused
        let mut h = Handover::new();
        h.on_message(&fix(GpsFixType::GPS_FIX_TYPE_3D_FIX), &ORIGIN);
        h.on_message(&attitude(1_000, f32::NAN), &ORIGIN);
        h.on_message(&position(1_000, 0.0), &ORIGIN);
        h.on_message(&fix(GpsFixType::GPS_FIX_TYPE_NO_FIX), &ORIGIN);
        assert_eq!(h.on_message(&fix(GpsFixType::GPS_FIX_TYPE_NO_FIX), &ORIGIN), Some(HandoverEvent::GnssLostWithoutEstimate));
    }

    #[test]
    fn the_source_set_command_names_the_set() {
        let MavMessage::COMMAND_LONG(c) = ekf_source_set(2, 3) else { panic!() };
        assert_eq!((c.command, c.param1, c.target_system, c.target_component), (MavCmd::MAV_CMD_SET_EKF_SOURCE_SET, 2.0, 3, 1));
    }
}
