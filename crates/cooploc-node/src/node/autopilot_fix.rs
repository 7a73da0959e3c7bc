//! The autopilot's own estimate, for a node that restarts (sans-io): the autopilot's EKF fused
//! the node's ODOMETRY until the node stopped, and went on on its own IMU (and compass) while it
//! was down, so at the restart its heading, and its position and velocity while it still
//! vouches for them, are the node's own estimate carried across the gap by sensors that
//! measured the motion. A saved state carried across the same gap at constant velocity knows
//! neither where the vehicle turned nor how far it went (issue 33, item 3; measured on the real
//! ArduPilot firmware in docs/real-autopilot.md).
//!
//! [`AutopilotEstimate`] follows ATTITUDE, GLOBAL_POSITION_INT and the EKF's status flags
//! (ArduPilot's EKF_STATUS_REPORT, PX4's ESTIMATOR_STATUS) and gives an [`AutopilotFix`]: the
//! heading when the EKF says its attitude is good; the horizontal position and velocity too when
//! it says its horizontal velocity and position are good (relative or absolute), not held
//! constant, and no GNSS glitch. Status flags carry no time: they are taken as of the newest
//! ATTITUDE or GLOBAL_POSITION_INT stamp seen before them (or the first one after), and vouch
//! for an estimate at most [`FIX_STALE_MS`] from it.
//!
//! What the real firmware does (ArduPilot 4.7 Rover, EKF3 on external navigation, the node
//! killed): EKF3 kept its horizontal position 0.04-0.23 m from the truth for 7 s, then said
//! flags 0x033f -> 0x0027 (attitude and velocity, no horizontal position) and fell back to DCM.

use nalgebra::Vector3;

use crate::protocol::MavMessage;
use crate::protocol::dialect::cooploc::{ATTITUDE_DATA, GLOBAL_POSITION_INT_DATA};
use crate::protocol::wire::{self, GeoOrigin};

/// The most an estimate and the status that vouches for it may be apart, ms.
pub const FIX_STALE_MS: u32 = 1_000;

/// What a status says, in one vocabulary for both autopilots.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Vouched {
    pub attitude: bool,
    pub horizontal: bool,
    /// The EKF says its GNSS glitches (its innovations fail): ArduPilot's EKF_GPS_GLITCHING
    /// (32768, while its position source is GNSS), PX4's ESTIMATOR_GPS_GLITCH (1024).
    pub gnss_glitch: bool,
    /// The raw flags, for the log.
    pub flags: u16,
}

/// The bits both autopilots' status flags share (EKF_STATUS_FLAGS, ESTIMATOR_STATUS_FLAGS).
const ATTITUDE: u16 = 1;
const VELOCITY_HORIZ: u16 = 2;
/// The bit of an absolute horizontal position (a relative one is 8).
pub const POS_HORIZ_ABS: u16 = 16;
const POS_HORIZ: u16 = 8 | POS_HORIZ_ABS; // relative or absolute
const CONST_POS_MODE: u16 = 128;

impl Vouched {
    /// ArduPilot's EKF_STATUS_REPORT flags: 1024 uninitialised, 32768 a GNSS glitch.
    pub fn ekf_status_report(flags: u16) -> Vouched {
        Vouched { gnss_glitch: flags & 32768 != 0, ..Self::of(flags, CONST_POS_MODE | 1024 | 32768) }
    }

    /// PX4's ESTIMATOR_STATUS flags: 1024 a GNSS glitch, 2048 an accelerometer error.
    pub fn estimator_status(flags: u16) -> Vouched {
        Vouched { gnss_glitch: flags & 1024 != 0, ..Self::of(flags, CONST_POS_MODE | 1024 | 2048) }
    }

    /// `bad`: the flags that withdraw everything.
    fn of(flags: u16, bad: u16) -> Vouched {
        let attitude = flags & ATTITUDE != 0 && flags & bad == 0;
        Vouched {
            attitude,
            horizontal: attitude && flags & VELOCITY_HORIZ != 0 && flags & POS_HORIZ != 0,
            gnss_glitch: false,
            flags,
        }
    }
}

/// The autopilot's estimate, as far as its EKF vouches for it.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct AutopilotFix {
    /// ATTITUDE's stamp (the autopilot's boot clock), ms.
    pub attitude_ms: u32,
    pub yaw_rad: f64,
    pub yaw_rate_rad_s: f64,
    pub horizontal: Option<HorizontalEstimate>,
    pub vouched: Vouched,
}

/// The horizontal position and velocity of GLOBAL_POSITION_INT in the node's NED frame.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct HorizontalEstimate {
    /// Its stamp (the autopilot's boot clock), ms.
    pub at_ms: u32,
    pub pos_ned_m: Vector3<f64>,
    pub vel_ned_m_s: Vector3<f64>,
}

impl AutopilotFix {
    /// The fix carried to the node's time: the heading `dt_attitude_s` after ATTITUDE at its
    /// yaw rate, the position `dt_position_s` after GLOBAL_POSITION_INT at its velocity.
    pub fn carried(&self, dt_attitude_s: f64, dt_position_s: f64) -> crate::estimation::coast::GapFix {
        use crate::estimation::coast::{GapFix, HorizontalFix};
        GapFix {
            yaw_rad: crate::estimation::unicycle::wrap_angle(self.yaw_rad + self.yaw_rate_rad_s * dt_attitude_s),
            horizontal: self.horizontal.map(|h| {
                let p = h.pos_ned_m + h.vel_ned_m_s * dt_position_s;
                HorizontalFix { pos_ne_m: [p.x, p.y], vel_ne_m_s: [h.vel_ned_m_s.x, h.vel_ned_m_s.y] }
            }),
        }
    }
}

/// Follows the autopilot's estimate and its status (see the module documentation).
#[derive(Debug, Clone, Default)]
pub struct AutopilotEstimate {
    position: Option<GLOBAL_POSITION_INT_DATA>,
    attitude: Option<ATTITUDE_DATA>,
    /// The last status and the stamp it is taken at (None until an estimate comes).
    status: Option<(Vouched, Option<u32>)>,
    latest_ms: Option<u32>,
    /// Estimates that were no numbers or no place (said, then the next one is waited for).
    pub refused: u64,
}

impl AutopilotEstimate {
    pub fn new() -> Self {
        Self::default()
    }

    /// Takes one of the autopilot's messages (any other is ignored).
    pub fn on_message(&mut self, msg: &MavMessage) {
        let stamp = match msg {
            MavMessage::GLOBAL_POSITION_INT(m) => {
                self.position = Some(m.clone());
                m.time_boot_ms
            }
            MavMessage::ATTITUDE(m) => {
                self.attitude = Some(m.clone());
                m.time_boot_ms
            }
            MavMessage::EKF_STATUS_REPORT(m) => {
                self.status = Some((Vouched::ekf_status_report(m.flags.bits()), self.latest_ms));
                return;
            }
            MavMessage::ESTIMATOR_STATUS(m) => {
                self.status = Some((Vouched::estimator_status(m.flags.bits()), self.latest_ms));
                return;
            }
            _ => return,
        };
        self.latest_ms = Some(self.latest_ms.map_or(stamp, |l| l.max(stamp)));
        if let Some((_, at @ None)) = &mut self.status {
            *at = Some(stamp);
        }
    }

    /// The estimate as far as the status vouches for it, in the frame of `origin`; None when
    /// there is no attitude, no status, or the status is not of this estimate, or vouches for
    /// nothing. An estimate that is no number or no place is refused with its reason.
    pub fn fix(&mut self, origin: &GeoOrigin) -> Result<Option<AutopilotFix>, String> {
        let (Some(a), Some((vouched, Some(at)))) = (self.attitude.clone(), self.status) else { return Ok(None) };
        if a.time_boot_ms.abs_diff(at) > FIX_STALE_MS || !vouched.attitude {
            return Ok(None);
        }
        if !(a.yaw.is_finite() && a.yawspeed.is_finite()) {
            self.refused += 1;
            self.attitude = None;
            return Err(format!("ATTITUDE yaw {} rad, yawspeed {} rad/s: no numbers", a.yaw, a.yawspeed));
        }
        let horizontal = match &self.position {
            Some(p) if vouched.horizontal && p.time_boot_ms.abs_diff(at) <= FIX_STALE_MS => {
                match wire::ins_state_from_autopilot(p, &a, origin) {
                    Ok(s) => {
                        Some(HorizontalEstimate { at_ms: p.time_boot_ms, pos_ned_m: s.pos_ned_m, vel_ned_m_s: s.vel_ned_m_s })
                    }
                    Err(e) => {
                        self.refused += 1;
                        self.position = None;
                        return Err(e.to_string());
                    }
                }
            }
            _ => None,
        };
        Ok(Some(AutopilotFix {
            attitude_ms: a.time_boot_ms,
            yaw_rad: f64::from(a.yaw),
            yaw_rate_rad_s: f64::from(a.yawspeed),
            horizontal,
            vouched,
        }))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::protocol::dialect::cooploc::{
        EKF_STATUS_REPORT_DATA, ESTIMATOR_STATUS_DATA, EkfStatusFlags, EstimatorStatusFlags,
    };

    const ORIGIN: GeoOrigin = GeoOrigin { lat_deg: -35.363261, lon_deg: 149.16523, alt_m: 584.0 };

    fn position(time_boot_ms: u32, north_m: f64) -> MavMessage {
        MavMessage::GLOBAL_POSITION_INT(GLOBAL_POSITION_INT_DATA {
            time_boot_ms,
            lat: wire::deg_to_e7(ORIGIN.lat_deg + north_m / 111_319.49),
            lon: wire::deg_to_e7(ORIGIN.lon_deg),
            alt: 584_000,
            vx: 200,
            vy: -50,
            ..Default::default()
        })
    }

    fn attitude(time_boot_ms: u32, yaw: f32) -> MavMessage {
        MavMessage::ATTITUDE(ATTITUDE_DATA { time_boot_ms, yaw, yawspeed: 0.1, ..Default::default() })
    }

    fn ekf(flags: u16) -> MavMessage {
        MavMessage::EKF_STATUS_REPORT(EKF_STATUS_REPORT_DATA {
            flags: EkfStatusFlags::from_bits_retain(flags),
            ..Default::default()
        })
    }

    #[test]
    fn the_real_firmwares_flags_read_as_it_meant_them() {
        // ArduPilot 4.7 Rover on external navigation, then 7 s after its ODOMETRY stopped
        let v = |attitude, horizontal, flags| Vouched { attitude, horizontal, gnss_glitch: false, flags };
        assert_eq!(Vouched::ekf_status_report(0x033f), v(true, true, 0x033f));
        assert_eq!(Vouched::ekf_status_report(0x0027), v(true, false, 0x0027));
        // uninitialised, a GNSS glitch, a position held constant: nothing
        for flags in [0x0400 | 0x033f, 0x8000 | 0x033f] {
            assert!(!Vouched::ekf_status_report(flags).attitude, "{flags:#x}");
        }
        assert!(!Vouched::ekf_status_report(0x0080 | 0x001f).horizontal);
        // the glitch, each autopilot's own bit
        assert!(Vouched::ekf_status_report(0x8000 | 0x033f).gnss_glitch);
        assert!(!Vouched::ekf_status_report(0x0400 | 0x033f).gnss_glitch, "uninitialised is no glitch");
        // PX4: 1024 is a glitch there, not "uninitialised"
        assert!(!Vouched::estimator_status(0x041f).attitude);
        assert!(Vouched::estimator_status(0x041f).gnss_glitch);
        assert!(!Vouched::estimator_status(0x801f).gnss_glitch);
        assert!(Vouched::estimator_status(0x001f).horizontal);
        assert!(!Vouched::estimator_status(0x0003).horizontal, "velocity without a position");
    }

    #[test]
    fn a_fix_needs_a_status_of_its_time_and_says_only_what_it_vouches_for() {
        let mut e = AutopilotEstimate::new();
        e.on_message(&position(10_000, 5.0));
        e.on_message(&attitude(10_010, 0.5));
        assert_eq!(e.fix(&ORIGIN), Ok(None), "no status yet");
        e.on_message(&ekf(0x033f));
        let fix = e.fix(&ORIGIN).unwrap().expect("a full fix");
        assert_eq!((fix.attitude_ms, fix.yaw_rad), (10_010, f64::from(0.5f32)));
        let h = fix.horizontal.expect("a vouched position");
        assert_eq!(h.at_ms, 10_000);
        assert!((h.pos_ned_m.xy() - nalgebra::Vector2::new(5.0, 0.0)).norm() < 0.02);
        assert!((h.vel_ned_m_s - Vector3::new(2.0, -0.5, 0.0)).norm() < 1e-9);
        // carried to the node's sample: 0.2 s after the attitude, 0.21 s after the position
        let g = fix.carried(0.2, 0.21);
        assert!((g.yaw_rad - (f64::from(0.5f32) + 0.1f32 as f64 * 0.2)).abs() < 1e-6);
        let p = g.horizontal.unwrap().pos_ne_m;
        assert!((p[0] - (h.pos_ned_m.x + 0.42)).abs() < 1e-9 && (p[1] - (h.pos_ned_m.y - 0.105)).abs() < 1e-9);
        // the EKF drops its position: the heading alone
        e.on_message(&attitude(10_100, 0.6));
        e.on_message(&ekf(0x0027));
        let fix = e.fix(&ORIGIN).unwrap().unwrap();
        assert_eq!((fix.yaw_rad, fix.horizontal), (f64::from(0.6f32), None));
        // a status long before the attitude vouches for nothing
        e.on_message(&attitude(12_000, 0.7));
        assert_eq!(e.fix(&ORIGIN), Ok(None));
        // a status before any estimate is taken at the first one's time
        let mut e = AutopilotEstimate::new();
        e.on_message(&ekf(0x033f));
        e.on_message(&attitude(500, 0.1));
        assert!(e.fix(&ORIGIN).unwrap().is_some());
    }

    #[test]
    fn estimates_that_are_no_numbers_or_no_place_are_refused_and_waited_past() {
        let mut e = AutopilotEstimate::new();
        e.on_message(&attitude(1_000, f32::NAN));
        e.on_message(&ekf(0x033f));
        assert!(e.fix(&ORIGIN).unwrap_err().contains("ATTITUDE"));
        assert_eq!(e.fix(&ORIGIN), Ok(None), "the bad attitude is dropped");
        e.on_message(&attitude(1_050, 0.2));
        e.on_message(&position(1_040, 500_000.0));
        assert!(e.fix(&ORIGIN).unwrap_err().contains("km from the origin"));
        let fix = e.fix(&ORIGIN).unwrap().unwrap();
        assert_eq!(fix.horizontal, None, "the far position dropped, the heading kept");
        assert_eq!(e.refused, 2);
        // PX4's status message is read with its own flags
        let mut e = AutopilotEstimate::new();
        e.on_message(&attitude(1_000, 0.3));
        e.on_message(&position(1_000, 1.0));
        e.on_message(&MavMessage::ESTIMATOR_STATUS(ESTIMATOR_STATUS_DATA {
            flags: EstimatorStatusFlags::from_bits_retain(0x001f),
            ..Default::default()
        }));
        assert!(e.fix(&ORIGIN).unwrap().unwrap().horizontal.is_some());
    }
}
