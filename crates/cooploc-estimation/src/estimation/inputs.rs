//! Sensor samples as a MAVLink vehicle delivers them, in the core's units and frames. The
//! simulator produces them, the protocol layer decodes them from HIGHRES_IMU / ODOMETRY and the
//! cooploc range message, and the filters consume them: one set of types for all three.

use nalgebra::Vector3;
use serde::{Deserialize, Serialize};

use super::platform::PlatformId;
use crate::time::TimeUs;

/// One IMU sample (HIGHRES_IMU): the mean specific force and angular rate over the sample
/// interval that ends at `t`, body FRD.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct ImuSample {
    pub t: TimeUs,
    /// Specific force (acceleration minus gravity), m/s^2; about [0, 0, -9.8] at rest.
    pub specific_force_frd_m_s2: Vector3<f64>,
    /// Angular rate relative to inertial space, rad/s.
    pub angular_rate_frd_rad_s: Vector3<f64>,
}

/// One odometer sample (ODOMETRY, body-frame x velocity): forward speed at `t`.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct OdometerSample {
    pub t: TimeUs,
    pub speed_m_s: f64,
}

/// An absolute position fix (a GNSS receiver's, GPS_RAW_INT) in the team's NED frame: where the
/// vehicle was at `t`, with the receiver's one-sigma accuracy, horizontal and (when it gives
/// one) vertical. Applied as a local update ([`super::fix`]).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct PositionFixSample {
    pub t: TimeUs,
    pub pos_ned_m: Vector3<f64>,
    /// Horizontal one-sigma, m, on north and on east.
    pub sigma_h_m: f64,
    /// Vertical one-sigma, m; `None`: the fix's height is not used.
    pub sigma_v_m: Option<f64>,
}

impl PositionFixSample {
    /// Finite position; sigmas above 0 and at most [`super::fix::MAX_FIX_SIGMA_M`].
    pub fn validate(&self) -> Result<(), crate::estimation::EstimationError> {
        use crate::estimation::EstimationError;
        if !self.pos_ned_m.iter().all(|v| v.is_finite()) {
            return Err(EstimationError::NonFinite { what: "position fix" });
        }
        for sigma in std::iter::once(self.sigma_h_m).chain(self.sigma_v_m) {
            if !(sigma > 0.0 && sigma <= super::fix::MAX_FIX_SIGMA_M) {
                return Err(EstimationError::InvalidValue { what: "position fix sigma, m", value: sigma });
            }
        }
        Ok(())
    }
}

/// One wheel-odometry drive sample of a planar robot: the mean forward speed and yaw rate over
/// the interval that ends at `t` (WHEEL_DISTANCE of a differential drive, differentiated).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct WheelSample {
    pub t: TimeUs,
    pub speed_m_s: f64,
    /// Yaw rate, rad/s, positive turning right (clockwise seen from above).
    pub yaw_rate_rad_s: f64,
}

/// One inter-platform range (the cooploc range message).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct RangeSample {
    pub t: TimeUs,
    /// Platform whose radio measured.
    pub from: PlatformId,
    /// Platform ranged to.
    pub to: PlatformId,
    pub range_m: f64,
    pub sigma_m: f64,
}

/// A motion command (a robot's commanded forward and angular speed, as MRCLAM logs them), in
/// force from `t` until the next one (or until it goes stale).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Command {
    pub t: TimeUs,
    pub speed_m_s: f64,
    /// Yaw rate, rad/s, positive clockwise seen from above (NED).
    pub yaw_rate_rad_s: f64,
}

/// What a camera observation saw (a data set's range and bearing).
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord, Hash)]
pub enum Target {
    /// A teammate (its platform id).
    Robot(PlatformId),
    /// A landmark of known position (its subject number).
    Landmark(u16),
}
