//! The hand-over, sans-io: a vehicle that starts with GNSS navigates on its autopilot's own
//! estimate while it has GNSS; the team's filters run beside it on the same fixes, and take over
//! when GNSS goes.
//!
//! [`Handover`] follows the autopilot's GNSS fix (GPS_RAW_INT `fix_type`) and its estimate
//! (GLOBAL_POSITION_INT, ATTITUDE):
//! - once the autopilot has held a 3D fix for [`START_AFTER`] GPS_RAW_INT messages in a row and
//!   its EKF's last status (ArduPilot's EKF_STATUS_REPORT, PX4's ESTIMATOR_STATUS; none needed
//!   from an autopilot that sends neither) vouches for its attitude, horizontal velocity and
//!   absolute horizontal position, or it has lost a fix it had before the node could start, it
//!   says [`HandoverEvent::Start`] with
//!   the autopilot's latest estimate: the node initialises from it, at its time, and from then
//!   on takes each GNSS fix as a local update of its filter (`crate::estimation::fix`), so its
//!   filter, its recursive coefficient matrix and the team's epochs run while GNSS is there;
//! - when the fix is gone for [`LOST_AFTER`] messages in a row, [`Handover::lost`] turns true:
//!   the node takes over (its ODOMETRY, and the autopilot asked to change its EKF source set:
//!   ArduPilot's MAV_CMD_SET_EKF_SOURCE_SET, from a set on GNSS to one on external navigation,
//!   as ArduPilot's own source-switching scripts do). Its estimate then is the one it ran on
//!   the same fixes the autopilot had, so what the autopilot fuses does not step by more than
//!   the two filters differ;
//! - when a fix is back for [`BACK_AFTER`] messages in a row, `lost` turns false again: the node
//!   hands back (the source set on GNSS) and takes the fixes again.

use super::autopilot_fix::{POS_HORIZ_ABS, Vouched};
use crate::estimation::ins::InsState;
use crate::protocol::MavMessage;
use crate::protocol::dialect::cooploc::{ATTITUDE_DATA, COMMAND_LONG_DATA, GLOBAL_POSITION_INT_DATA, MavCmd};
use crate::protocol::wire::{self, GeoOrigin};

/// GPS_RAW_INT messages without a 3D fix, in a row, that make a loss (one is a glitch).
pub const LOST_AFTER: u32 = 2;
/// GPS_RAW_INT messages with a 3D fix, in a row, before the node starts from the autopilot's
/// estimate (1 s at the 5 Hz the node asks for: the autopilot's EKF has taken the fix).
pub const START_AFTER: u32 = 5;
/// GPS_RAW_INT messages with a 3D fix, in a row, after a loss before GNSS counts as back (2 s at
/// 5 Hz: a fix that comes and goes is not handed back to).
pub const BACK_AFTER: u32 = 10;
/// GLOBAL_POSITION_INT and ATTITUDE further apart than this (of the autopilot's boot clock) are
/// no estimate to start from, ms.
pub const STALE_MS: u32 = 1_000;
/// GPS_RAW_INT `fix_type` of a 3D fix.
pub const FIX_3D: u8 = 3;

/// What the autopilot's messages say about the hand-over.
#[derive(Debug, Clone, PartialEq)]
pub enum HandoverEvent {
    /// Start from the autopilot's estimate, stamped in its boot clock (ms).
    Start { time_boot_ms: u32, state: Box<InsState> },
    /// A start is due but the autopilot's estimate is missing or unusable (said, then the node
    /// waits for a fresh one).
    NoEstimate,
    /// The fix is gone: the node takes over.
    Lost,
    /// The fix is back: the node hands back.
    Back,
}

/// Follows the autopilot's fix and estimate (see the module documentation).
#[derive(Debug, Clone, Default)]
pub struct Handover {
    had_fix: bool,
    fixes_in_row: u32,
    without_fix: u32,
    lost: bool,
    started: bool,
    position: Option<GLOBAL_POSITION_INT_DATA>,
    attitude: Option<ATTITUDE_DATA>,
    /// The EKF's last status, if it sends one.
    status: Option<Vouched>,
    /// Estimates refused (no position, not finite, far from the origin).
    pub refused: u64,
    /// Losses of the fix after the start, and returns.
    pub losses: u64,
    pub returns: u64,
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
                    self.fixes_in_row = self.fixes_in_row.saturating_add(1);
                    if self.lost && self.fixes_in_row >= BACK_AFTER {
                        // (back before the node could start: nothing to hand back)
                        self.lost = false;
                        if self.started {
                            self.returns += 1;
                            return Some(HandoverEvent::Back);
                        }
                    }
                } else {
                    self.fixes_in_row = 0;
                    self.without_fix = self.without_fix.saturating_add(1);
                    if self.had_fix && !self.lost && self.without_fix >= LOST_AFTER {
                        self.lost = true;
                        if self.started {
                            self.losses += 1;
                            return Some(HandoverEvent::Lost);
                        }
                    }
                }
            }
            MavMessage::GLOBAL_POSITION_INT(m) => self.position = Some(m.clone()),
            MavMessage::ATTITUDE(m) => self.attitude = Some(m.clone()),
            MavMessage::EKF_STATUS_REPORT(m) => self.status = Some(Vouched::ekf_status_report(m.flags.bits())),
            MavMessage::ESTIMATOR_STATUS(m) => self.status = Some(Vouched::estimator_status(m.flags.bits())),
            _ => return None,
        }
        // (ArduPilot reports a position before its EKF has taken the fix: on the real firmware,
        // at its first fix, its start's latitude and longitude with an altitude of 0.05 m)
        let vouched = self.status.is_none_or(|v| v.horizontal && v.flags & POS_HORIZ_ABS != 0);
        if self.started || !(self.lost || self.fixes_in_row >= START_AFTER && vouched) {
            return None;
        }
        let (Some(p), Some(a)) = (&self.position, &self.attitude) else { return None };
        if p.time_boot_ms.abs_diff(a.time_boot_ms) > STALE_MS {
            return None; // one of them is old: the next message of the other brings them together
        }
        match wire::ins_state_from_autopilot(p, a, origin) {
            Ok(state) => {
                self.started = true;
                Some(HandoverEvent::Start { time_boot_ms: p.time_boot_ms.max(a.time_boot_ms), state: Box::new(state) })
            }
            Err(e) => {
                self.refused += 1;
                tracing::warn!(error = %e, "the autopilot's estimate cannot start the node");
                self.position = None;
                Some(HandoverEvent::NoEstimate)
            }
        }
    }

    /// The start it gave could not be taken (the team clock is not mapped yet): the next fresh
    /// estimate gives it again.
    pub fn retry(&mut self) {
        self.started = false;
    }

    /// The fix is gone (after one was seen), and not back yet: the node navigates the vehicle.
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

    /// `n` GPS_RAW_INT messages of `fix_type`: the events they gave.
    fn fixes(h: &mut Handover, fix_type: GpsFixType, n: usize) -> Vec<HandoverEvent> {
        (0..n).filter_map(|_| h.on_message(&fix(fix_type), &ORIGIN)).collect()
    }

    #[test]
    fn the_node_starts_once_the_autopilot_has_held_a_fix_takes_over_when_it_goes_and_hands_back() {
        let mut h = Handover::new();
        for m in [position(1_000, 5.0), attitude(1_010, 0.5)] {
            assert_eq!(h.on_message(&m, &ORIGIN), None, "no fix yet");
        }
        assert_eq!(fixes(&mut h, GpsFixType::GPS_FIX_TYPE_3D_FIX, START_AFTER as usize - 1), vec![]);
        // a fix lost for one message starts the count again
        assert_eq!(fixes(&mut h, GpsFixType::GPS_FIX_TYPE_NO_FIX, 1), vec![]);
        assert_eq!(fixes(&mut h, GpsFixType::GPS_FIX_TYPE_3D_FIX, START_AFTER as usize - 1), vec![]);
        let Some(HandoverEvent::Start { time_boot_ms, state }) = h.on_message(&fix(GpsFixType::GPS_FIX_TYPE_3D_FIX), &ORIGIN)
        else {
            panic!("a start")
        };
        assert_eq!(time_boot_ms, 1_010);
        assert!((state.pos_ned_m - nalgebra::Vector3::new(5.0, 0.0, 0.0)).norm() < 0.02, "{}", state.pos_ned_m);
        assert!((state.vel_ned_m_s - nalgebra::Vector3::new(1.5, -0.2, 0.0)).norm() < 1e-9);
        assert!((state.att_frd_to_ned.euler_angles().2 - 0.5).abs() < 1e-6);
        assert!(!h.lost());
        // once
        assert_eq!(h.on_message(&position(1_100, 5.2), &ORIGIN), None);
        // one message without a fix is a glitch; two in a row a loss
        assert_eq!(fixes(&mut h, GpsFixType::GPS_FIX_TYPE_NO_FIX, 1), vec![]);
        assert_eq!(fixes(&mut h, GpsFixType::GPS_FIX_TYPE_3D_FIX, 1), vec![]);
        assert_eq!(fixes(&mut h, GpsFixType::GPS_FIX_TYPE_NO_GPS, LOST_AFTER as usize + 5), vec![HandoverEvent::Lost]);
        assert!(h.lost());
        // a fix that comes back for less than BACK_AFTER messages is not handed back to
        assert_eq!(fixes(&mut h, GpsFixType::GPS_FIX_TYPE_3D_FIX, BACK_AFTER as usize - 1), vec![]);
        assert_eq!(fixes(&mut h, GpsFixType::GPS_FIX_TYPE_NO_FIX, 1), vec![]);
        assert!(h.lost());
        assert_eq!(fixes(&mut h, GpsFixType::GPS_FIX_TYPE_3D_FIX, BACK_AFTER as usize + 3), vec![HandoverEvent::Back]);
        assert!(!h.lost());
        assert_eq!(fixes(&mut h, GpsFixType::GPS_FIX_TYPE_NO_FIX, LOST_AFTER as usize), vec![HandoverEvent::Lost]);
        assert_eq!((h.losses, h.returns), (2, 1));
    }

    /// The real ArduPilot firmware at its first fix: EKF_STATUS_REPORT 0x00a7 (attitude, velocity,
    /// vertical position, constant-position mode) and GLOBAL_POSITION_INT at its origin's
    /// latitude and longitude with an altitude of 0.05 m; a node started from that began 584 m
    /// under the ground. It starts once the EKF says 0x033f (horizontal position, absolute).
    #[test]
    fn the_start_waits_for_the_ekf_to_vouch_for_an_absolute_position() {
        use crate::protocol::dialect::cooploc::{EKF_STATUS_REPORT_DATA, EkfStatusFlags};
        let status = |flags: u16| {
            MavMessage::EKF_STATUS_REPORT(EKF_STATUS_REPORT_DATA {
                flags: EkfStatusFlags::from_bits_truncate(flags),
                ..Default::default()
            })
        };
        let mut h = Handover::new();
        h.on_message(&status(0x00a7), &ORIGIN);
        h.on_message(&position(9_951, 0.0), &ORIGIN);
        h.on_message(&attitude(9_951, 0.5), &ORIGIN);
        assert_eq!(fixes(&mut h, GpsFixType::GPS_FIX_TYPE_3D_FIX, 3 * START_AFTER as usize), vec![]);
        // relative only: not yet
        assert_eq!(h.on_message(&status(0x00a7 & !0x80 | 0x08), &ORIGIN), None);
        let Some(HandoverEvent::Start { .. }) = h.on_message(&status(0x033f), &ORIGIN) else { panic!("a start") };
    }

    #[test]
    fn a_node_that_comes_up_after_the_loss_starts_at_once_and_is_taken_over() {
        let mut h = Handover::new();
        assert_eq!(fixes(&mut h, GpsFixType::GPS_FIX_TYPE_3D_FIX, 2), vec![]);
        h.on_message(&position(1_000, 5.0), &ORIGIN);
        assert_eq!(fixes(&mut h, GpsFixType::GPS_FIX_TYPE_NO_FIX, LOST_AFTER as usize), vec![], "no attitude yet");
        assert!(h.lost());
        let Some(HandoverEvent::Start { time_boot_ms, state }) = h.on_message(&attitude(1_010, 0.5), &ORIGIN) else {
            panic!("a start")
        };
        assert_eq!(time_boot_ms, 1_010);
        assert!((state.pos_ned_m.x - 5.0).abs() < 0.02);
        assert!(h.lost(), "lost before it started: no Lost event, the node reads lost()");
        // back before the node could start: no longer lost, and no Back to hand back
        let mut back = h.clone();
        back.retry();
        back.attitude = None;
        assert_eq!(fixes(&mut back, GpsFixType::GPS_FIX_TYPE_3D_FIX, BACK_AFTER as usize), vec![]);
        assert!(!back.lost());
        assert_eq!(back.returns, 0);
        // unless the node could not take it (its clock not mapped yet): then the next estimate
        h.retry();
        let Some(HandoverEvent::Start { time_boot_ms, .. }) = h.on_message(&attitude(1_110, 0.5), &ORIGIN) else {
            panic!("a start again")
        };
        assert_eq!(time_boot_ms, 1_110);
    }

    #[test]
    fn no_fix_from_power_on_starts_nothing_and_stale_or_bad_estimates_start_nothing() {
        let mut h = Handover::new();
        h.on_message(&position(1_000, 5.0), &ORIGIN);
        h.on_message(&attitude(1_000, 0.0), &ORIGIN);
        assert_eq!(fixes(&mut h, GpsFixType::GPS_FIX_TYPE_NO_GPS, 10), vec![]);
        assert!(!h.lost(), "never had a fix: the other start (configured state) is the node's");
        // an attitude 5 s older than the position: waits for a fresh one
        let mut h = Handover::new();
        h.on_message(&attitude(1_000, 0.0), &ORIGIN);
        h.on_message(&position(6_000, 0.0), &ORIGIN);
        assert_eq!(fixes(&mut h, GpsFixType::GPS_FIX_TYPE_RTK_FIXED, START_AFTER as usize + 2), vec![]);
        assert!(matches!(h.on_message(&attitude(6_020, 0.1), &ORIGIN), Some(HandoverEvent::Start { .. })));
        // a position of 0, 0 (none yet) or 200 km away is refused, said once per estimate
        let mut h = Handover::new();
        h.on_message(&attitude(1_000, 0.0), &ORIGIN);
        h.on_message(&position(1_000, 200_000.0), &ORIGIN);
        assert_eq!(fixes(&mut h, GpsFixType::GPS_FIX_TYPE_3D_FIX, START_AFTER as usize + 2), vec![HandoverEvent::NoEstimate]);
        assert_eq!(h.refused, 1);
        assert_eq!(h.on_message(&attitude(1_040, 0.0), &ORIGIN), None, "no position until a new one");
        let Some(HandoverEvent::Start { state, .. }) = h.on_message(&position(1_050, 3.0), &ORIGIN) else { panic!() };
        assert!((state.pos_ned_m.x - 3.0).abs() < 0.02);
        // NaN attitude: refused
        let mut h = Handover::new();
        h.on_message(&attitude(1_000, f32::NAN), &ORIGIN);
        h.on_message(&position(1_000, 0.0), &ORIGIN);
        assert_eq!(fixes(&mut h, GpsFixType::GPS_FIX_TYPE_3D_FIX, START_AFTER as usize), vec![HandoverEvent::NoEstimate]);
    }

    #[test]
    fn the_source_set_command_names_the_set() {
        let MavMessage::COMMAND_LONG(c) = ekf_source_set(2, 3) else { panic!() };
        assert_eq!((c.command, c.param1, c.target_system, c.target_component), (MavCmd::MAV_CMD_SET_EKF_SOURCE_SET, 2.0, 3, 1));
    }
}
