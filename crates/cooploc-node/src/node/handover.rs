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
//! - when the fix is gone for [`LOST_AFTER`] messages in a row, or the autopilot's EKF reports a
//!   GNSS glitch (its fix still 3D: the receiver's position is wrong and the EKF's innovations
//!   fail; ArduPilot's EKF_GPS_GLITCHING, PX4's ESTIMATOR_GPS_GLITCH), [`Handover::lost`] turns true:
//!   the node takes over (its ODOMETRY, and the autopilot asked to change its EKF source set:
//!   ArduPilot's MAV_CMD_SET_EKF_SOURCE_SET, from a set on GNSS to one on external navigation,
//!   as ArduPilot's own source-switching scripts do). Its estimate then is the one it ran on
//!   the same fixes the autopilot had, so what the autopilot fuses does not step by more than
//!   the two filters differ;
//! - when a fix is back for [`BACK_AFTER`] messages in a row, `lost` turns false again: the node
//!   hands back (the source set on GNSS) and takes the fixes again. After a glitch the fix never
//!   went, and the autopilot cannot say when its GNSS is right again (ArduPilot reports the
//!   glitch only while its position source is GNSS, and the take-over switched it away): the
//!   node's own filter judges, through its gate, every fix while it navigates
//!   ([`Handover::judged`]), and hands back once it has taken [`BACK_AFTER`] in a row, none
//!   refused, and the autopilot's last status reports no glitch.

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
    /// The loss was a glitch the EKF reported (the fix stayed).
    glitch_loss: bool,
    /// Fixes the node's filter took in a row, none refused by its gate since, and the totals
    /// (taken, refused) it last said.
    gate_takes_in_row: u32,
    judged: (u64, u64),
    /// Estimates refused (no position, not finite, far from the origin).
    pub refused: u64,
    /// Losses of the fix after the start (glitches included), and returns.
    pub losses: u64,
    pub returns: u64,
    /// Losses that were glitches the EKF reported.
    pub glitches: u64,
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
                    let trusted = !self.glitch_loss || self.gate_takes_in_row >= BACK_AFTER && !self.glitching();
                    if self.lost && self.fixes_in_row >= BACK_AFTER && trusted {
                        // (back before the node could start: nothing to hand back)
                        self.lost = false;
                        self.glitch_loss = false;
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
        if self.glitching() && self.started && !self.lost {
            // (before the start a glitch only delays it: the status does not vouch)
            self.lost = true;
            self.glitch_loss = true;
            self.gate_takes_in_row = 0;
            self.losses += 1;
            self.glitches += 1;
            return Some(HandoverEvent::Lost);
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

    /// The fix is gone (after one was seen), or the EKF reported it glitching, and GNSS is not
    /// back yet: the node navigates the vehicle.
    pub fn lost(&self) -> bool {
        self.lost
    }

    /// The node navigates because the EKF reported a glitch (the fix stayed).
    pub fn lost_to_glitch(&self) -> bool {
        self.lost && self.glitch_loss
    }

    /// The autopilot's last status says its GNSS glitches.
    fn glitching(&self) -> bool {
        self.status.is_some_and(|v| v.gnss_glitch)
    }

    /// What the node's filter has done with the GNSS fixes so far: `taken` and `refused` (by
    /// its gate) in all. A refusal starts the count of fixes taken in a row again (of several
    /// judged since the last call, the order is not known: counted as refused last).
    pub fn judged(&mut self, taken: u64, refused: u64) {
        let (taken_before, refused_before) = self.judged;
        if refused > refused_before {
            self.gate_takes_in_row = 0;
        } else {
            let more = u32::try_from(taken.saturating_sub(taken_before)).unwrap_or(u32::MAX);
            self.gate_takes_in_row = self.gate_takes_in_row.saturating_add(more);
        }
        self.judged = (taken, refused);
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

    /// ArduPilot's EKF_STATUS_REPORT with `flags`.
    fn ekf(flags: u16) -> MavMessage {
        use crate::protocol::dialect::cooploc::{EKF_STATUS_REPORT_DATA, EkfStatusFlags};
        MavMessage::EKF_STATUS_REPORT(EKF_STATUS_REPORT_DATA {
            flags: EkfStatusFlags::from_bits_retain(flags),
            ..Default::default()
        })
    }

    /// PX4's ESTIMATOR_STATUS with `flags`.
    fn px4(flags: u16) -> MavMessage {
        use crate::protocol::dialect::cooploc::{ESTIMATOR_STATUS_DATA, EstimatorStatusFlags};
        MavMessage::ESTIMATOR_STATUS(ESTIMATOR_STATUS_DATA {
            flags: EstimatorStatusFlags::from_bits_retain(flags),
            ..Default::default()
        })
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
        let mut h = Handover::new();
        h.on_message(&ekf(0x00a7), &ORIGIN);
        h.on_message(&position(9_951, 0.0), &ORIGIN);
        h.on_message(&attitude(9_951, 0.5), &ORIGIN);
        assert_eq!(fixes(&mut h, GpsFixType::GPS_FIX_TYPE_3D_FIX, 3 * START_AFTER as usize), vec![]);
        // relative only: not yet
        assert_eq!(h.on_message(&ekf(0x00a7 & !0x80 | 0x08), &ORIGIN), None);
        let Some(HandoverEvent::Start { .. }) = h.on_message(&ekf(0x033f), &ORIGIN) else { panic!("a start") };
    }

    /// A GNSS glitch (the receiver's position jumps, its fix stays 3D): the EKF's report of it
    /// takes over; the hand-back waits for the node's own filter to take BACK_AFTER fixes in a
    /// row and the EKF to report no glitch.
    #[test]
    fn a_glitch_the_ekf_reports_is_taken_over_and_handed_back_when_the_nodes_gate_takes_the_fixes_again() {
        for (good, glitch) in [(ekf(0x033f), ekf(0x833f)), (px4(0x003f), px4(0x043f))] {
            let mut h = Handover::new();
            h.on_message(&good, &ORIGIN);
            h.on_message(&position(1_000, 5.0), &ORIGIN);
            h.on_message(&attitude(1_000, 0.0), &ORIGIN);
            assert!(matches!(
                fixes(&mut h, GpsFixType::GPS_FIX_TYPE_3D_FIX, START_AFTER as usize)[..],
                [HandoverEvent::Start { .. }]
            ));
            let (mut taken, mut refused) = (0, 0);
            let mut judge = |h: &mut Handover, t: u64, r: u64| {
                (taken, refused) = (taken + t, refused + r);
                h.judged(taken, refused);
            };
            judge(&mut h, 20, 0);
            assert_eq!(h.on_message(&glitch, &ORIGIN), Some(HandoverEvent::Lost));
            assert_eq!(h.on_message(&glitch, &ORIGIN), None, "once");
            assert!(h.lost() && h.lost_to_glitch());
            // the fix stays 3D and the node's gate refuses the glitched fixes: no hand-back
            for _ in 0..3 * BACK_AFTER {
                judge(&mut h, 0, 1);
                assert_eq!(h.on_message(&fix(GpsFixType::GPS_FIX_TYPE_3D_FIX), &ORIGIN), None);
            }
            // the glitch ends; the node's gate takes the fixes again, but one is refused midway
            h.on_message(&good, &ORIGIN);
            for k in 0..2 * BACK_AFTER - 2 {
                judge(&mut h, 1, u64::from(k == BACK_AFTER - 2));
                assert_eq!(h.on_message(&fix(GpsFixType::GPS_FIX_TYPE_3D_FIX), &ORIGIN), None, "fix {k}");
            }
            // BACK_AFTER taken in a row, yet the EKF still says glitch (PX4 checks its GNSS while
            // not on it): not yet
            h.on_message(&glitch, &ORIGIN);
            judge(&mut h, 1, 0);
            assert_eq!(h.on_message(&fix(GpsFixType::GPS_FIX_TYPE_3D_FIX), &ORIGIN), None);
            h.on_message(&good, &ORIGIN);
            assert_eq!(h.on_message(&fix(GpsFixType::GPS_FIX_TYPE_3D_FIX), &ORIGIN), Some(HandoverEvent::Back));
            assert!(!h.lost());
            assert_eq!((h.losses, h.glitches, h.returns), (1, 1, 1));
            // a loss of the fix after that hands back on the fix alone, as before
            assert_eq!(fixes(&mut h, GpsFixType::GPS_FIX_TYPE_NO_FIX, LOST_AFTER as usize), vec![HandoverEvent::Lost]);
            assert_eq!(fixes(&mut h, GpsFixType::GPS_FIX_TYPE_3D_FIX, BACK_AFTER as usize), vec![HandoverEvent::Back]);
            assert_eq!((h.losses, h.glitches, h.returns), (2, 1, 2));
        }
    }

    #[test]
    fn a_glitch_before_the_start_only_delays_it() {
        let mut h = Handover::new();
        h.on_message(&ekf(0x833f), &ORIGIN);
        h.on_message(&position(1_000, 5.0), &ORIGIN);
        h.on_message(&attitude(1_000, 0.0), &ORIGIN);
        assert_eq!(fixes(&mut h, GpsFixType::GPS_FIX_TYPE_3D_FIX, 2 * START_AFTER as usize), vec![]);
        assert!(!h.lost());
        assert!(matches!(h.on_message(&ekf(0x033f), &ORIGIN), Some(HandoverEvent::Start { .. })));
        assert!(!h.lost());
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
