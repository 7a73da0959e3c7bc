//! A wheeled robot without an IMU in the navigation: a planar error-state filter driven by
//! wheel odometry (its forward speed and yaw rate, from the two wheels of a differential drive
//! or a yaw-rate gyro), on the team's clock.
//!
//! Error state `[dN, dE, dyaw]` (m, m, rad) in the team's NED frame (yaw from north, clockwise
//! seen from above); the height is fixed and known (a robot on level ground), not a state.
//!
//! A [`WheelSample`] holds the mean speed `v` and yaw rate `w` over the interval that ends at
//! its time, and the filter integrates each interval (or each piece of one, when the node cuts
//! it at an epoch) at the mid-point heading:
//!
//! ```text
//! yaw_m = yaw + w dt / 2
//! N += v cos(yaw_m) dt,   E += v sin(yaw_m) dt,   yaw += w dt
//! Phi = [1 0 -v sin(yaw_m) dt; 0 1 v cos(yaw_m) dt; 0 0 1]
//! Qd  = G diag(q_v, q_w) G^T / dt,  G = [cos(yaw_m) dt  -v sin(yaw_m) dt^2/2;
//!                                        sin(yaw_m) dt   v cos(yaw_m) dt^2/2;
//!                                        0               dt]
//! ```
//!
//! The input noise is a density (`q = sigma^2 T` for a sample of period `T` and standard
//! deviation `sigma`), so an interval cut in pieces (a node stops at every epoch) gets the speed
//! noise the whole interval would; the yaw-rate noise's effect on position and the mid-point
//! state differ from the uncut interval only at third order in the piece length (for 20 Hz
//! samples, far below the noise). A node and the offline experiment cut at the same instants,
//! so they agree exactly.

use nalgebra::{Matrix2, Matrix3, Matrix3x2, UnitQuaternion, Vector3};
use serde::{Deserialize, Serialize};

use super::EstimationError;
use super::inputs::WheelSample;
use super::unicycle::PlanarCore;
use crate::time::TimeUs;

/// Fastest a wheeled robot drives, m/s: a faster sample is refused.
pub const MAX_SPEED_M_S: f64 = 60.0;
/// Fastest it turns, rad/s.
pub const MAX_YAW_RATE_RAD_S: f64 = 10.0;

/// Longest interval one wheel sample may cover by default, s: WHEEL_DISTANCE at 1 Hz (an
/// autopilot's default stream rate) still drives the filter.
pub const DEFAULT_MAX_GAP_S: f64 = 1.1;

/// The planar filter's noise model and limits.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct PlanarConfig {
    /// White-noise density of the forward speed, m/s/sqrt(Hz) (a sample's sigma times the
    /// square root of its period).
    pub speed_noise_m_s_per_sqrt_hz: f64,
    /// White-noise density of the yaw rate, rad/s/sqrt(Hz).
    pub yaw_rate_noise_rad_s_per_sqrt_hz: f64,
    /// Longest interval one wheel sample may cover, s (a longer gap is a lost stream).
    pub max_gap_s: f64,
}

impl PlanarConfig {
    /// The densities of samples with standard deviations `sigma_speed_m_s` and
    /// `sigma_yaw_rate_rad_s` at `rate_hz`.
    pub fn from_sample_sigmas(sigma_speed_m_s: f64, sigma_yaw_rate_rad_s: f64, rate_hz: f64) -> Self {
        let root_t = (1.0 / rate_hz).sqrt();
        PlanarConfig {
            speed_noise_m_s_per_sqrt_hz: sigma_speed_m_s * root_t,
            yaw_rate_noise_rad_s_per_sqrt_hz: sigma_yaw_rate_rad_s * root_t,
            max_gap_s: DEFAULT_MAX_GAP_S,
        }
    }

    pub fn validate(&self) -> Result<(), EstimationError> {
        for (v, what) in [
            (self.speed_noise_m_s_per_sqrt_hz, "planar speed noise density"),
            (self.yaw_rate_noise_rad_s_per_sqrt_hz, "planar yaw-rate noise density"),
        ] {
            if !v.is_finite() || v < 0.0 {
                return Err(EstimationError::InvalidValue { what, value: v });
            }
        }
        if !self.max_gap_s.is_finite() || self.max_gap_s <= 0.0 {
            return Err(EstimationError::InvalidValue { what: "planar max_gap_s", value: self.max_gap_s });
        }
        Ok(())
    }
}

/// A planar robot's nominal state.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct PlanarState {
    /// Position in the team's NED frame, m; D is the fixed, known height.
    pub pos_ned_m: Vector3<f64>,
    /// Yaw from north, clockwise seen from above, rad.
    pub yaw_rad: f64,
}

/// Standard deviations of the initial errors.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct PlanarSigma {
    /// Per horizontal axis, m.
    pub pos_m: f64,
    pub yaw_rad: f64,
}

#[derive(Debug, Clone)]
pub struct PlanarFilter {
    config: PlanarConfig,
    t: TimeUs,
    /// Nominal `[N, E, yaw]` at the known height, covariance, `Psi`.
    core: PlanarCore,
    /// The last sample's speed and yaw rate, and its interval (for the reported velocity).
    last: (f64, f64, f64),
}

impl PlanarFilter {
    pub fn new(config: PlanarConfig, t0: TimeUs, initial: PlanarState, sigma: PlanarSigma) -> Result<Self, EstimationError> {
        config.validate()?;
        for (v, what) in [(sigma.pos_m, "initial planar position sigma"), (sigma.yaw_rad, "initial planar yaw sigma")] {
            if !v.is_finite() || v < 0.0 {
                return Err(EstimationError::InvalidValue { what, value: v });
            }
        }
        let p = Matrix3::from_diagonal(&Vector3::new(sigma.pos_m.powi(2), sigma.pos_m.powi(2), sigma.yaw_rad.powi(2)));
        let x = Vector3::new(initial.pos_ned_m[0], initial.pos_ned_m[1], initial.yaw_rad);
        Ok(Self { config, t: t0, core: PlanarCore::new(x, p, initial.pos_ned_m[2])?, last: (0.0, 0.0, 0.0) })
    }

    pub fn config(&self) -> &PlanarConfig {
        &self.config
    }

    /// Time of the last sample (or of the initialisation).
    pub fn time(&self) -> TimeUs {
        self.t
    }

    /// Moves the clock to `t` without propagating (see [`crate::estimation::ins::InsFilter::restart_clock`]).
    pub fn restart_clock(&mut self, t: TimeUs) {
        self.t = t;
    }

    pub fn state(&self) -> PlanarState {
        PlanarState { pos_ned_m: self.position_ned_m(), yaw_rad: self.yaw_rad() }
    }

    pub fn position_ned_m(&self) -> Vector3<f64> {
        let x = self.core.state();
        Vector3::new(x[0], x[1], self.core.height_d_m())
    }

    pub fn yaw_rad(&self) -> f64 {
        self.core.state()[2]
    }

    /// Velocity of the last sample, along the current heading, m/s.
    pub fn velocity_ned_m_s(&self) -> Vector3<f64> {
        let (s, c) = self.yaw_rad().sin_cos();
        Vector3::new(self.last.0 * c, self.last.0 * s, 0.0)
    }

    /// Covariance of that velocity: the speed noise of the last interval along the heading,
    /// and the speed times the yaw uncertainty across it.
    pub fn velocity_covariance_ned(&self) -> Matrix3<f64> {
        let dt = self.last.2.max(1e-3);
        let along = self.config.speed_noise_m_s_per_sqrt_hz.powi(2) / dt;
        let across = self.last.0.powi(2) * self.core.covariance3()[(2, 2)];
        let (s, c) = self.yaw_rad().sin_cos();
        let r = Matrix3x2::new(c, -s, s, c, 0.0, 0.0);
        r * Matrix2::new(along, 0.0, 0.0, across) * r.transpose()
    }

    /// Level attitude at the heading (a planar robot has no roll or pitch).
    pub fn attitude(&self) -> UnitQuaternion<f64> {
        UnitQuaternion::from_euler_angles(0.0, 0.0, self.yaw_rad())
    }

    pub fn covariance3(&self) -> Matrix3<f64> {
        self.core.covariance3()
    }

    /// Integrates the interval from the filter's time to `s.t` at the sample's speed and yaw
    /// rate (see the module documentation). On error nothing changes.
    pub fn propagate(&mut self, s: &WheelSample) -> Result<(), EstimationError> {
        if s.t < self.t {
            return Err(EstimationError::TimeWentBackwards { what: "wheel sample", from_us: self.t.0, to_us: s.t.0 });
        }
        let dt = s.t.secs_since(self.t);
        if dt == 0.0 {
            return Err(EstimationError::InvalidValue { what: "wheel time step (s)", value: dt });
        }
        if dt > self.config.max_gap_s {
            return Err(EstimationError::InvalidValue { what: "wheel sample gap (s)", value: dt });
        }
        let (v, w) = (s.speed_m_s, s.yaw_rate_rad_s);
        if !v.is_finite() || v.abs() > MAX_SPEED_M_S {
            return Err(EstimationError::InvalidValue { what: "wheel speed (m/s)", value: v });
        }
        if !w.is_finite() || w.abs() > MAX_YAW_RATE_RAD_S {
            return Err(EstimationError::InvalidValue { what: "wheel yaw rate (rad/s)", value: w });
        }
        let (sn, cs) = (self.yaw_rad() + 0.5 * w * dt).sin_cos();
        let phi = Matrix3::new(1.0, 0.0, -v * sn * dt, 0.0, 1.0, v * cs * dt, 0.0, 0.0, 1.0);
        let half_dt2 = 0.5 * dt * dt;
        let g = Matrix3x2::new(cs * dt, -v * sn * half_dt2, sn * dt, v * cs * half_dt2, 0.0, dt);
        let q = Matrix2::new(
            self.config.speed_noise_m_s_per_sqrt_hz.powi(2) / dt,
            0.0,
            0.0,
            self.config.yaw_rate_noise_rad_s_per_sqrt_hz.powi(2) / dt,
        );
        self.core.step(&phi, &(g * q * g.transpose()), &Vector3::new(v * cs * dt, v * sn * dt, w * dt));
        self.t = s.t;
        self.last = (v, w, dt);
        Ok(())
    }
}

super::unicycle::planar_platform_filter!(PlanarFilter);

#[cfg(test)]
mod tests {
    use super::*;
    use crate::estimation::PlatformFilter;
    use nalgebra::DMatrix;

    fn filter() -> PlanarFilter {
        let cfg = PlanarConfig::from_sample_sigmas(0.05, 0.01, 20.0);
        let init = PlanarState { pos_ned_m: Vector3::new(0.0, 0.0, -0.3), yaw_rad: 0.0 };
        PlanarFilter::new(cfg, TimeUs(0), init, PlanarSigma { pos_m: 0.01, yaw_rad: 0.001 }).unwrap()
    }

    #[test]
    fn drives_a_quarter_circle_at_any_sample_rate() {
        // 10 m radius, 0.1 rad/s: the mid-point heading makes 20 Hz samples close the arc.
        let (r, w) = (10.0, 0.1);
        let end_us = (std::f64::consts::FRAC_PI_2 / w * 1e6).round() as u64;
        let mut f = filter();
        let mut t = 0;
        while t < end_us {
            t = (t + 50_000).min(end_us);
            f.propagate(&WheelSample { t: TimeUs(t), speed_m_s: r * w, yaw_rate_rad_s: w }).unwrap();
        }
        let x = f.state();
        assert!((x.pos_ned_m[0] - r).abs() < 1e-3 && (x.pos_ned_m[1] - r).abs() < 1e-3, "{}", x.pos_ned_m);
        assert!((x.yaw_rad - std::f64::consts::FRAC_PI_2).abs() < 1e-6);
        assert_eq!(x.pos_ned_m[2], -0.3, "the height is held");
        let v = f.velocity_ned_m_s();
        assert!(v[0].abs() < 1e-6 && (v[1] - 1.0).abs() < 1e-9, "{v}");
    }

    #[test]
    fn cutting_an_interval_changes_neither_the_state_nor_the_noise() {
        // Speed noise only, a known heading: what the density model makes additive.
        let cfg = PlanarConfig { yaw_rate_noise_rad_s_per_sqrt_hz: 0.0, ..PlanarConfig::from_sample_sigmas(0.05, 0.0, 20.0) };
        let init = PlanarState { pos_ned_m: Vector3::zeros(), yaw_rad: 0.0 };
        let sigma = PlanarSigma { pos_m: 0.01, yaw_rad: 0.0 };
        let make = || PlanarFilter::new(cfg, TimeUs(0), init, sigma).unwrap();
        let (mut whole, mut cut) = (make(), make());
        let s = WheelSample { t: TimeUs(50_000), speed_m_s: 2.0, yaw_rate_rad_s: 0.0 };
        whole.propagate(&s).unwrap();
        cut.propagate(&WheelSample { t: TimeUs(20_000), ..s }).unwrap();
        cut.propagate(&s).unwrap();
        assert!((whole.position_ned_m() - cut.position_ned_m()).norm() < 1e-12);
        assert!((whole.covariance3() - cut.covariance3()).norm() < 1e-12, "{} vs {}", whole.covariance3(), cut.covariance3());
        // One 20 Hz sample with sigma 0.05 m/s adds (0.05 * 0.05)^2 along north.
        let added = whole.covariance3()[(0, 0)] - 1e-4;
        assert!((added - (0.05f64 * 0.05).powi(2)).abs() < 1e-12, "{added}");
    }

    #[test]
    fn refuses_bad_samples_and_keeps_its_state() {
        let mut f = filter();
        let before = f.state();
        for s in [
            WheelSample { t: TimeUs(0), speed_m_s: 1.0, yaw_rate_rad_s: 0.0 },
            WheelSample { t: TimeUs(1_200_000), speed_m_s: 1.0, yaw_rate_rad_s: 0.0 },
            WheelSample { t: TimeUs(50_000), speed_m_s: f64::NAN, yaw_rate_rad_s: 0.0 },
            WheelSample { t: TimeUs(50_000), speed_m_s: 100.0, yaw_rate_rad_s: 0.0 },
            WheelSample { t: TimeUs(50_000), speed_m_s: 1.0, yaw_rate_rad_s: 20.0 },
        ] {
            assert!(f.propagate(&s).is_err(), "{s:?}");
        }
        assert_eq!(f.state(), before);
        assert_eq!(f.time(), TimeUs(0));
    }

    #[test]
    fn psi_is_the_product_of_the_transitions() {
        let mut f = filter();
        let p0 = f.covariance3();
        let mut phis = Matrix3::identity();
        for k in 1..=10u64 {
            let yaw = f.yaw_rad();
            let (v, w, dt) = (1.5, 0.2, 0.05);
            let (sn, cs) = (yaw + 0.5 * w * dt).sin_cos();
            phis = Matrix3::new(1.0, 0.0, -v * sn * dt, 0.0, 1.0, v * cs * dt, 0.0, 0.0, 1.0) * phis;
            f.propagate(&WheelSample { t: TimeUs(k * 50_000), speed_m_s: v, yaw_rate_rad_s: w }).unwrap();
        }
        assert!((f.psi() - DMatrix::from_column_slice(3, 3, phis.as_slice())).norm() < 1e-12);
        assert!(f.covariance3()[(1, 1)] > p0[(1, 1)]);
    }
}
