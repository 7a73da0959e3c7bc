//! A robot driven by its *commands* (what a robot without odometry logs, as the MRCLAM robots
//! do): a planar error-state filter whose motion model learns how the robot executes them.
//!
//! Error state `[dN, dE, dyaw, ds, db]` ([`DIM`] = 5) in the team's NED frame (yaw from north,
//! clockwise seen from above): position, heading, the **speed scale** `s` (the robot travels
//! `(1 + s)` times the commanded distance) and the **yaw-rate bias** `b` (it turns at the commanded
//! rate plus `b`, rad/s, while it is commanded to move). Both are random walks (densities
//! [`CommandedConfig::speed_scale_walk_per_sqrt_s`], [`CommandedConfig::yaw_rate_bias_walk_rad_s_per_sqrt_s`];
//! zero makes them constants to be learnt). The height is fixed and known, not a state.
//!
//! A [`WheelSample`] holds the commanded speed `v` and yaw rate `w` over the interval that ends
//! at its time; `m = 1` when the robot is commanded to move (`v != 0` or `w != 0`), else 0:
//! a robot commanded to stand still stands still (no bias, no white noise), as a command-driven
//! robot does.
//!
//! ```text
//! u = (1 + s) v,  r = w + m b,  yaw_m = yaw + r dt / 2
//! N += u cos(yaw_m) dt,  E += u sin(yaw_m) dt,  yaw += r dt
//! Phi = I + [0 0 -l_E  v cos dt  -m u sin dt^2/2;
//!            0 0  l_N  v sin dt   m u cos dt^2/2;
//!            0 0  0    0          m dt;   0 (s, b rows)]
//! Qd  = m G diag(q_v, q_w) G^T / dt + diag(0, 0, 0, q_s dt, q_b dt)
//! ```
//!
//! with `G` the planar filter's (see [`super::planar`]) and the lever `l = (l_N, l_E)` either the
//! step's own displacement (the ordinary EKF Jacobian) or, with **first-estimate Jacobians**
//! ([`CommandedConfig::first_estimates`]), the new position minus the *first estimate* of the
//! position at the step's start: the prior at that instant, before any update at it. With the
//! lever taken this way, and every measurement Jacobian of a relative observation taken at
//! the first estimates too ([`CommandedFilter::linearization_position_ned_m`]), the products
//! of the Jacobians keep the team's unobservable directions (a common translation, and a common
//! rotation about the origin: `[I, J p; 0, 1; 0, 0]` per robot, `J` the quarter turn)
//! unobservable, so that without landmarks the filter gains no spurious information about the
//! absolute heading: the first-estimates EKF of Huang, Mourikis and Roumeliotis
//! (ISER 2008; Autonomous Robots 2011) for cooperative localization. The nominal state still
//! moves with every update; only the Jacobians use the first estimates. A measurement of the
//! absolute pose (a landmark) removes those directions: the caller may then re-anchor the first
//! estimate on the corrected position ([`CommandedFilter::reanchor_first_estimate`]; the data-set
//! runs re-anchor every robot after every update once the team has seen a landmark).
//!
//! The filter implements [`PlatformFilter`] like every platform model, so every cooperative
//! method runs it unchanged, and its recursive coefficient matrix is the product of these
//! `Phi` and the local updates' `I - K H` (paper Eq. 10), the speed-scale and bias columns
//! included.

use nalgebra::{DMatrix, DVector, SMatrix, SVector, Vector2, Vector3};
use serde::{Deserialize, Serialize};

use super::inputs::WheelSample;
use super::planar::{MAX_SPEED_M_S, MAX_YAW_RATE_RAD_S};
use super::platform::{Geometry, Heading, PlatformFilter, check_joint_writeback};
use super::unicycle::wrap_angle;
use super::{EstimationError, LinearizedMeasurement, UpdateDiagnostics, kalman};
use crate::time::TimeUs;

/// Error-state dimension.
pub const DIM: usize = 5;
/// Index of the speed scale in the error state.
pub const SPEED_SCALE: usize = 3;
/// Index of the yaw-rate bias in the error state.
pub const YAW_RATE_BIAS: usize = 4;

/// The error-state matrices.
pub type Mat5 = SMatrix<f64, DIM, DIM>;
type Vec5 = SVector<f64, DIM>;

/// The noise model and options of a [`CommandedFilter`].
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct CommandedConfig {
    /// White-noise density of the executed forward speed while moving, m/s/sqrt(Hz).
    pub speed_noise_m_s_per_sqrt_hz: f64,
    /// White-noise density of the executed yaw rate while moving, rad/s/sqrt(Hz).
    pub yaw_rate_noise_rad_s_per_sqrt_hz: f64,
    /// Random-walk density of the speed scale, 1/sqrt(s).
    pub speed_scale_walk_per_sqrt_s: f64,
    /// Random-walk density of the yaw-rate bias, rad/s/sqrt(s).
    pub yaw_rate_bias_walk_rad_s_per_sqrt_s: f64,
    /// Longest interval one sample may cover, s.
    pub max_gap_s: f64,
    /// First-estimate Jacobians (module documentation).
    pub first_estimates: bool,
}

impl CommandedConfig {
    pub fn validate(&self) -> Result<(), EstimationError> {
        for (v, what) in [
            (self.speed_noise_m_s_per_sqrt_hz, "commanded speed noise density"),
            (self.yaw_rate_noise_rad_s_per_sqrt_hz, "commanded yaw-rate noise density"),
            (self.speed_scale_walk_per_sqrt_s, "speed-scale walk density"),
            (self.yaw_rate_bias_walk_rad_s_per_sqrt_s, "yaw-rate bias walk density"),
        ] {
            if !v.is_finite() || v < 0.0 {
                return Err(EstimationError::InvalidValue { what, value: v });
            }
        }
        if !self.max_gap_s.is_finite() || self.max_gap_s <= 0.0 {
            return Err(EstimationError::InvalidValue { what: "commanded max_gap_s", value: self.max_gap_s });
        }
        Ok(())
    }
}

/// Standard deviations of the initial errors.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct CommandedSigma {
    /// Per horizontal axis, m.
    pub pos_m: f64,
    pub yaw_rad: f64,
    /// Of the speed scale (dimensionless: 0.1 is 10%).
    pub speed_scale: f64,
    pub yaw_rate_bias_rad_s: f64,
}

/// One propagation step, not yet applied.
struct Step {
    phi: Mat5,
    qd: Mat5,
    new_pos: Vector2<f64>,
    dyaw: f64,
}

/// A command-driven robot (module documentation).
#[derive(Debug, Clone)]
pub struct CommandedFilter {
    config: CommandedConfig,
    t: TimeUs,
    /// Nominal `[N, E, yaw, s, b]`.
    x: Vec5,
    p: Mat5,
    psi: Mat5,
    track_psi: bool,
    height_d_m: f64,
    /// The first estimate of the position at the current time (the prior before any update).
    first_pos: Vector2<f64>,
}

impl CommandedFilter {
    /// A robot at `pos_ned_m` (its D the fixed height) and `yaw_rad`, speed scale and bias zero.
    pub fn new(
        config: CommandedConfig,
        t0: TimeUs,
        pos_ned_m: Vector3<f64>,
        yaw_rad: f64,
        sigma: CommandedSigma,
    ) -> Result<Self, EstimationError> {
        config.validate()?;
        for (v, what) in [
            (sigma.pos_m, "initial position sigma"),
            (sigma.yaw_rad, "initial yaw sigma"),
            (sigma.speed_scale, "initial speed-scale sigma"),
            (sigma.yaw_rate_bias_rad_s, "initial yaw-rate bias sigma"),
        ] {
            if !v.is_finite() || v < 0.0 {
                return Err(EstimationError::InvalidValue { what, value: v });
            }
        }
        kalman::check_finite(&pos_ned_m, "initial position")?;
        if !yaw_rad.is_finite() {
            return Err(EstimationError::NonFinite { what: "initial yaw" });
        }
        let x = Vec5::from([pos_ned_m[0], pos_ned_m[1], wrap_angle(yaw_rad), 0.0, 0.0]);
        let p = Mat5::from_diagonal(&Vec5::from([
            sigma.pos_m.powi(2),
            sigma.pos_m.powi(2),
            sigma.yaw_rad.powi(2),
            sigma.speed_scale.powi(2),
            sigma.yaw_rate_bias_rad_s.powi(2),
        ]));
        Ok(Self {
            config,
            t: t0,
            x,
            p,
            psi: Mat5::identity(),
            track_psi: true,
            height_d_m: pos_ned_m[2],
            first_pos: Vector2::new(x[0], x[1]),
        })
    }

    pub fn config(&self) -> &CommandedConfig {
        &self.config
    }

    /// Time of the last sample (or of the initialisation).
    pub fn time(&self) -> TimeUs {
        self.t
    }

    pub fn position_ned_m(&self) -> Vector3<f64> {
        Vector3::new(self.x[0], self.x[1], self.height_d_m)
    }

    pub fn yaw_rad(&self) -> f64 {
        self.x[2]
    }

    /// The estimated speed scale `s` (travels `1 + s` times the commanded distance).
    pub fn speed_scale(&self) -> f64 {
        self.x[SPEED_SCALE]
    }

    /// The estimated yaw-rate bias, rad/s.
    pub fn yaw_rate_bias_rad_s(&self) -> f64 {
        self.x[YAW_RATE_BIAS]
    }

    /// Nominal `[N, E, yaw, s, b]`.
    pub fn state(&self) -> [f64; DIM] {
        self.x.into()
    }

    /// The position the Jacobians of relative measurements are to be taken at: the first
    /// estimate with [`CommandedConfig::first_estimates`], else the current estimate.
    pub fn linearization_position_ned_m(&self) -> Vector3<f64> {
        if self.config.first_estimates {
            Vector3::new(self.first_pos[0], self.first_pos[1], self.height_d_m)
        } else {
            self.position_ned_m()
        }
    }

    /// Takes the current position as the first estimate at this instant. For a measurement that
    /// makes the absolute pose observable (a landmark of known position): the unobservable
    /// directions the first estimates protect are gone, and a first estimate far from the
    /// corrected one would only add linearization error to the next steps.
    pub fn reanchor_first_estimate(&mut self) {
        self.first_pos = Vector2::new(self.x[0], self.x[1]);
    }

    /// Covariance of `[dN, dE, dyaw]`.
    pub fn pose_covariance(&self) -> nalgebra::Matrix3<f64> {
        self.p.fixed_view::<3, 3>(0, 0).into_owned()
    }

    /// Integrates the interval from the filter's time to `s.t` at the sample's command (module
    /// documentation). On error nothing changes.
    pub fn propagate(&mut self, s: &WheelSample) -> Result<(), EstimationError> {
        let step = self.step(s)?;
        let p = step.phi * self.p * step.phi.transpose() + step.qd;
        self.p = 0.5 * (p + p.transpose());
        if self.track_psi {
            self.psi = step.phi * self.psi;
        }
        self.x[0] = step.new_pos[0];
        self.x[1] = step.new_pos[1];
        self.x[2] = wrap_angle(self.x[2] + step.dyaw);
        self.first_pos = step.new_pos;
        self.t = s.t;
        Ok(())
    }

    /// The transition `Phi` and the process noise `Qd` that [`CommandedFilter::propagate`]
    /// would apply for `s`, without applying them (for a brute-force reference).
    pub fn transition(&self, s: &WheelSample) -> Result<(Mat5, Mat5), EstimationError> {
        self.step(s).map(|st| (st.phi, st.qd))
    }

    fn step(&self, s: &WheelSample) -> Result<Step, EstimationError> {
        if s.t < self.t {
            return Err(EstimationError::TimeWentBackwards { what: "command sample", from_us: self.t.0, to_us: s.t.0 });
        }
        let dt = s.t.secs_since(self.t);
        if dt == 0.0 {
            return Err(EstimationError::InvalidValue { what: "command time step (s)", value: dt });
        }
        if dt > self.config.max_gap_s {
            return Err(EstimationError::InvalidValue { what: "command sample gap (s)", value: dt });
        }
        let (v, w) = (s.speed_m_s, s.yaw_rate_rad_s);
        if !v.is_finite() || v.abs() > MAX_SPEED_M_S {
            return Err(EstimationError::InvalidValue { what: "commanded speed (m/s)", value: v });
        }
        if !w.is_finite() || w.abs() > MAX_YAW_RATE_RAD_S {
            return Err(EstimationError::InvalidValue { what: "commanded yaw rate (rad/s)", value: w });
        }
        let m = if v != 0.0 || w != 0.0 { 1.0 } else { 0.0 };
        let u = (1.0 + self.x[SPEED_SCALE]) * v;
        let r = w + m * self.x[YAW_RATE_BIAS];
        let (sn, cs) = (self.x[2] + 0.5 * r * dt).sin_cos();
        let new_pos = Vector2::new(self.x[0] + u * cs * dt, self.x[1] + u * sn * dt);
        let lever =
            if self.config.first_estimates { new_pos - self.first_pos } else { new_pos - Vector2::new(self.x[0], self.x[1]) };
        let half_dt2 = 0.5 * dt * dt;
        let mut phi = Mat5::identity();
        phi[(0, 2)] = -lever[1];
        phi[(1, 2)] = lever[0];
        phi[(0, SPEED_SCALE)] = v * cs * dt;
        phi[(1, SPEED_SCALE)] = v * sn * dt;
        phi[(0, YAW_RATE_BIAS)] = -m * u * sn * half_dt2;
        phi[(1, YAW_RATE_BIAS)] = m * u * cs * half_dt2;
        phi[(2, YAW_RATE_BIAS)] = m * dt;
        let mut qd = Mat5::zeros();
        if m > 0.0 {
            let g =
                SMatrix::<f64, DIM, 2>::new(cs * dt, -u * sn * half_dt2, sn * dt, u * cs * half_dt2, 0.0, dt, 0.0, 0.0, 0.0, 0.0);
            let q = nalgebra::Matrix2::new(
                self.config.speed_noise_m_s_per_sqrt_hz.powi(2) / dt,
                0.0,
                0.0,
                self.config.yaw_rate_noise_rad_s_per_sqrt_hz.powi(2) / dt,
            );
            qd += g * q * g.transpose();
        }
        qd[(SPEED_SCALE, SPEED_SCALE)] += self.config.speed_scale_walk_per_sqrt_s.powi(2) * dt;
        qd[(YAW_RATE_BIAS, YAW_RATE_BIAS)] += self.config.yaw_rate_bias_walk_rad_s_per_sqrt_s.powi(2) * dt;
        Ok(Step { phi, qd, new_pos, dyaw: r * dt })
    }

    fn inject(&mut self, dx: &[f64]) {
        for (x, d) in self.x.iter_mut().zip(dx) {
            *x += d;
        }
        self.x[2] = wrap_angle(self.x[2]);
    }
}

impl PlatformFilter for CommandedFilter {
    fn dim(&self) -> usize {
        DIM
    }
    fn covariance(&self) -> DMatrix<f64> {
        DMatrix::from_column_slice(DIM, DIM, self.p.as_slice())
    }
    fn psi(&self) -> DMatrix<f64> {
        DMatrix::from_column_slice(DIM, DIM, self.psi.as_slice())
    }
    fn geometry(&self) -> Geometry {
        Geometry {
            position_ned_m: self.position_ned_m(),
            position_index: [Some(0), Some(1), None],
            heading: Some(Heading { yaw_rad: self.x[2], index: 2 }),
        }
    }
    fn update_local(&mut self, meas: &LinearizedMeasurement) -> Result<UpdateDiagnostics, EstimationError> {
        let up = kalman::local_update(&self.covariance(), meas)?;
        self.inject(up.dx.as_slice());
        self.p = Mat5::from_column_slice(up.p.as_slice());
        if self.track_psi {
            self.psi = Mat5::from_column_slice(up.i_minus_kh.as_slice()) * self.psi;
        }
        Ok(up.diagnostics)
    }
    fn apply_joint(&mut self, dx: &DVector<f64>, p: &DMatrix<f64>) -> Result<(), EstimationError> {
        check_joint_writeback(DIM, dx, p)?;
        self.inject(dx.as_slice());
        self.p = Mat5::from_column_slice(p.as_slice());
        self.psi = Mat5::identity();
        Ok(())
    }
    fn apply_bystander(&mut self, a: &DVector<f64>, b: &DMatrix<f64>) -> Result<(), EstimationError> {
        let p = DMatrix::from_column_slice(DIM, DIM, self.p.as_slice());
        let psi = DMatrix::from_column_slice(DIM, DIM, self.psi.as_slice());
        let (dx, p) = super::platform::bystander_posterior(&p, &psi, a, b)?;
        self.inject(dx.as_slice());
        self.p = Mat5::from_column_slice(p.as_slice());
        Ok(())
    }
    fn set_track_psi(&mut self, on: bool) {
        self.track_psi = on;
        if !on {
            self.psi = Mat5::identity();
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn config(first_estimates: bool) -> CommandedConfig {
        CommandedConfig {
            speed_noise_m_s_per_sqrt_hz: 0.01,
            yaw_rate_noise_rad_s_per_sqrt_hz: 0.02,
            speed_scale_walk_per_sqrt_s: 1e-3,
            yaw_rate_bias_walk_rad_s_per_sqrt_s: 1e-4,
            max_gap_s: 1.0,
            first_estimates,
        }
    }

    fn sigma() -> CommandedSigma {
        CommandedSigma { pos_m: 0.01, yaw_rad: 0.01, speed_scale: 0.1, yaw_rate_bias_rad_s: 0.01 }
    }

    fn filter(first_estimates: bool) -> CommandedFilter {
        CommandedFilter::new(config(first_estimates), TimeUs(0), Vector3::new(1.0, 2.0, 0.0), 0.3, sigma()).unwrap()
    }

    #[test]
    fn a_known_scale_and_bias_drive_the_nominal_state() {
        let mut f = filter(false);
        f.x[SPEED_SCALE] = -0.1;
        f.x[YAW_RATE_BIAS] = 0.05;
        // Straight command for 2 s: 0.9 m/s along a heading that turns at 0.05 rad/s.
        for k in 1..=2000u64 {
            f.propagate(&WheelSample { t: TimeUs(k * 1000), speed_m_s: 1.0, yaw_rate_rad_s: 0.0 }).unwrap();
        }
        assert!((f.yaw_rad() - 0.4).abs() < 1e-9, "{}", f.yaw_rad());
        // Arc of radius 0.9 / 0.05 = 18 m from yaw 0.3 to 0.4.
        let (rad, a0, a1) = (18.0, 0.3f64, 0.4f64);
        let n = 1.0 + rad * (a1.sin() - a0.sin());
        let e = 2.0 - rad * (a1.cos() - a0.cos());
        assert!((f.position_ned_m()[0] - n).abs() < 1e-6 && (f.position_ned_m()[1] - e).abs() < 1e-6);
        // Standing still: no bias, no noise.
        let (x, p) = (f.state(), f.pose_covariance());
        f.propagate(&WheelSample { t: TimeUs(3_000_000), speed_m_s: 0.0, yaw_rate_rad_s: 0.0 }).unwrap();
        assert_eq!(&f.state()[..3], &x[..3]);
        assert!((f.pose_covariance() - p).norm() < 1e-15);
    }

    #[test]
    fn the_transition_is_the_derivative_of_the_step() {
        // Phi (without first estimates) against finite differences of the nominal step.
        let base = {
            let mut f = filter(false);
            f.x[SPEED_SCALE] = 0.05;
            f.x[YAW_RATE_BIAS] = -0.02;
            f
        };
        let s = WheelSample { t: TimeUs(200_000), speed_m_s: 0.5, yaw_rate_rad_s: 0.3 };
        let mut f = base.clone();
        f.propagate(&s).unwrap();
        let phi = f.psi();
        for k in 0..DIM {
            let mut g = base.clone();
            g.x[k] += 1e-7;
            g.propagate(&s).unwrap();
            for row in 0..DIM {
                let numeric = (g.x[row] - f.x[row]) / 1e-7;
                assert!((numeric - phi[(row, k)]).abs() < 1e-6, "row {row} col {k}: {numeric} vs {}", phi[(row, k)]);
            }
        }
    }

    #[test]
    fn first_estimates_keep_the_rotation_direction_unobservable() {
        // N(p) = [J p; 1; 0; 0] for a rotation about the origin: Phi N(p_first_k) must be
        // N(p_first_k+1), also when an update moved the estimate in between.
        let mut f = filter(true);
        let rot = |p: Vector3<f64>| DVector::from_vec(vec![-p[1], p[0], 1.0, 0.0, 0.0]);
        for k in 1..=20u64 {
            let before = rot(f.linearization_position_ned_m());
            let psi0 = f.psi();
            f.propagate(&WheelSample { t: TimeUs(k * 100_000), speed_m_s: 0.4, yaw_rate_rad_s: 0.2 }).unwrap();
            let phi = f.psi() * psi0.try_inverse().unwrap();
            let after = rot(f.linearization_position_ned_m());
            assert!((&phi * &before - &after).norm() < 1e-9, "step {k}");
            if k % 5 == 0 {
                // An update moves the nominal position; the first estimate stays.
                let h = DMatrix::from_row_slice(1, DIM, &[1.0, 0.0, 0.0, 0.0, 0.0]);
                let m =
                    LinearizedMeasurement { h, residual: DVector::from_element(1, 0.05), r: DMatrix::from_element(1, 1, 1e-4) };
                let lin = f.linearization_position_ned_m();
                f.update_local(&m).unwrap();
                f.psi = Mat5::identity();
                assert!(f.position_ned_m()[0] > lin[0] + 0.01);
                assert_eq!(f.linearization_position_ned_m(), lin);
            }
        }
        // Without first estimates the same sequence breaks it after the first update.
        let g = filter(false);
        assert_eq!(g.linearization_position_ned_m(), g.position_ned_m());
    }

    #[test]
    fn refuses_bad_samples_and_keeps_its_state() {
        let mut f = filter(true);
        let before = f.state();
        for s in [
            WheelSample { t: TimeUs(0), speed_m_s: 1.0, yaw_rate_rad_s: 0.0 },
            WheelSample { t: TimeUs(1_200_000), speed_m_s: 1.0, yaw_rate_rad_s: 0.0 },
            WheelSample { t: TimeUs(50_000), speed_m_s: f64::NAN, yaw_rate_rad_s: 0.0 },
            WheelSample { t: TimeUs(50_000), speed_m_s: 1.0, yaw_rate_rad_s: 20.0 },
        ] {
            assert!(f.propagate(&s).is_err(), "{s:?}");
        }
        assert_eq!(f.state(), before);
        let bad = CommandedConfig { speed_scale_walk_per_sqrt_s: -1.0, ..config(true) };
        assert!(CommandedFilter::new(bad, TimeUs(0), Vector3::zeros(), 0.0, sigma()).is_err());
    }
}
