//! A filter's state carried across a gap in which nothing was measured: a node that was down
//! (killed, rebooted) while its vehicle went on moving, restarted from the state it last saved.
//! Without the IMU or wheel samples of the gap the motion cannot be integrated; the state is
//! extrapolated at constant velocity and its covariance grows by what a vehicle within
//! [`CoastBounds`] could have done meanwhile. Pure math, no I/O.
//!
//! INS (the error state of [`ins`](super::ins)): position `+= v T`; the covariance goes through
//! `Phi = [I T I; 0 I]` on position and velocity, plus, per NED axis, the covariance of an unknown
//! constant acceleration of standard deviation `a` over `T`,
//! `a^2 [T^4/4, T^3/2; T^3/2, T^2]` (position, velocity), and `(omega T)^2` on the heading error.
//! Biases and the odometer scale are kept as they were. Planar robot (`[N, E, yaw]`, no velocity
//! in its state): the position is kept, `(s T)^2` is added per horizontal axis and `(omega T)^2` to
//! the yaw.
//!
//! [`coast_to_fix`]: the same, when another estimator ran across the gap (the autopilot's EKF,
//! which kept fusing the node's output until it stopped and then went on on its own IMU): its
//! heading, and its position and velocity when it vouches for them, replace the extrapolated
//! ones, grown by that estimator's drift ([`GapDrift`]) instead of the land bounds.

use nalgebra::DMatrix;

use super::EstimationError;
use super::ins::{ATT, ERROR_DIM, POS, VEL};
use super::nav::NavState;

/// What a vehicle can do while its node is down, one standard deviation.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct CoastBounds {
    /// Acceleration per NED axis, m/s^2.
    pub accel_m_s2: f64,
    /// Yaw rate, rad/s.
    pub yaw_rate_rad_s: f64,
    /// Speed (the planar robot, whose state has no velocity), m/s.
    pub speed_m_s: f64,
}

impl CoastBounds {
    /// A land vehicle manoeuvring: 2 m/s^2 (a car braking firmly or turning at 10 m/s with
    /// 0.2 rad/s), 0.5 rad/s of yaw rate, 5 m/s for a wheeled robot.
    pub const LAND: CoastBounds = CoastBounds { accel_m_s2: 2.0, yaw_rate_rad_s: 0.5, speed_m_s: 5.0 };

    fn check(&self) -> Result<(), EstimationError> {
        non_negative(&[
            ("coast acceleration bound", self.accel_m_s2),
            ("coast yaw-rate bound", self.yaw_rate_rad_s),
            ("coast speed bound", self.speed_m_s),
        ])
    }
}

/// `state` and its error covariance `p` carried `gap_s` seconds ahead with nothing measured.
pub fn coast(
    state: &NavState,
    p: &DMatrix<f64>,
    gap_s: f64,
    bounds: &CoastBounds,
) -> Result<(NavState, DMatrix<f64>), EstimationError> {
    bounds.check()?;
    if !(gap_s.is_finite() && gap_s >= 0.0) {
        return Err(EstimationError::InvalidValue { what: "coast gap (s)", value: gap_s });
    }
    let t = gap_s;
    match state {
        NavState::Ins(s) => {
            check_shape(p, ERROR_DIM)?;
            let mut phi = DMatrix::<f64>::identity(ERROR_DIM, ERROR_DIM);
            for i in 0..3 {
                phi[(POS + i, VEL + i)] = t;
            }
            let mut q = DMatrix::<f64>::zeros(ERROR_DIM, ERROR_DIM);
            let a2 = bounds.accel_m_s2.powi(2);
            for i in 0..3 {
                q[(POS + i, POS + i)] = a2 * t.powi(4) / 4.0;
                q[(POS + i, VEL + i)] = a2 * t.powi(3) / 2.0;
                q[(VEL + i, POS + i)] = a2 * t.powi(3) / 2.0;
                q[(VEL + i, VEL + i)] = a2 * t * t;
            }
            q[(ATT + 2, ATT + 2)] = (bounds.yaw_rate_rad_s * t).powi(2);
            let mut out = *s;
            out.pos_ned_m += s.vel_ned_m_s * t;
            Ok((NavState::Ins(out), symmetric(&phi * p * phi.transpose() + q)))
        }
        NavState::Planar(s) => {
            check_shape(p, 3)?;
            let mut grown = p.clone();
            let d = (bounds.speed_m_s * t).powi(2);
            grown[(0, 0)] += d;
            grown[(1, 1)] += d;
            grown[(2, 2)] += (bounds.yaw_rate_rad_s * t).powi(2);
            Ok((NavState::Planar(*s), grown))
        }
    }
}

/// What an estimator that kept running across the gap says at its end: the autopilot's EKF,
/// which fused the node's estimate until the node stopped and then went on on its own IMU (and
/// compass, and whatever else it has). Its heading, and its horizontal position and velocity
/// when it vouches for them, are the node's own estimate carried across the gap by a sensor
/// that measured the motion, so they replace the extrapolated ones, and their errors are the
/// saved state's plus what that sensor drifts by over the gap ([`GapDrift`]), not what a land
/// vehicle could have done meanwhile ([`CoastBounds`]).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct GapFix {
    /// Heading (yaw from north, clockwise seen from above), rad.
    pub yaw_rad: f64,
    /// Horizontal position and velocity, when the estimator vouches for its position.
    pub horizontal: Option<HorizontalFix>,
}

/// A horizontal position (N, E, m) and velocity (N, E, m/s) in the node's NED frame.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct HorizontalFix {
    pub pos_ne_m: [f64; 2],
    pub vel_ne_m_s: [f64; 2],
}

/// What the estimator that carried the state across a gap adds to its error, one standard
/// deviation: a strapdown IMU's residual gyro bias and angle random walk on the heading, its
/// residual accelerometer bias and tilt error on the horizontal acceleration.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct GapDrift {
    /// Heading drift rate (a residual gyro bias), rad/s.
    pub yaw_rate_rad_s: f64,
    /// Heading random walk, rad/sqrt(s).
    pub yaw_walk_rad_per_sqrt_s: f64,
    /// Heading error that does not grow with the gap: how far the estimator's heading may sit
    /// from the node's (its own filtering, or a compass that took over), rad.
    pub yaw_floor_rad: f64,
    /// Horizontal acceleration error, m/s^2 (the planar robot, whose state has no velocity: a
    /// speed noise density, m/s/sqrt(Hz), the position a random walk of it).
    pub accel_m_s2: f64,
}

impl GapDrift {
    /// The drift of an IMU with the noise and the initial (residual) errors `model` assumes: the
    /// INS's gyro bias about D and its angle random walk; its heading sigma as the floor; its
    /// accelerometer bias and the acceleration its roll/pitch sigma tilts gravity into. The
    /// planar robot (no IMU in its model): its yaw-rate noise as the walk, its yaw sigma as the
    /// floor, its speed noise as the horizontal error.
    pub fn of_model(model: &super::nav::NavModel) -> GapDrift {
        use super::nav::NavModel;
        match model {
            NavModel::Ins { config, initial_sigma } => {
                let ab = initial_sigma.accel_bias_frd_m_s2;
                let tilt = initial_sigma.att_ned_rad.x.max(initial_sigma.att_ned_rad.y);
                GapDrift {
                    yaw_rate_rad_s: initial_sigma.gyro_bias_frd_rad_s.z,
                    yaw_walk_rad_per_sqrt_s: config.gyro_noise_density_rad_s_per_sqrt_hz,
                    yaw_floor_rad: initial_sigma.att_ned_rad.z,
                    accel_m_s2: (ab.x.max(ab.y).powi(2) + (config.gravity_m_s2 * tilt).powi(2)).sqrt(),
                }
            }
            NavModel::Planar { config, initial_sigma } => GapDrift {
                yaw_rate_rad_s: 0.0,
                yaw_walk_rad_per_sqrt_s: config.yaw_rate_noise_rad_s_per_sqrt_hz,
                yaw_floor_rad: initial_sigma.yaw_rad,
                accel_m_s2: config.speed_noise_m_s_per_sqrt_hz,
            },
        }
    }

    fn check(&self) -> Result<(), EstimationError> {
        non_negative(&[
            ("gap drift yaw rate", self.yaw_rate_rad_s),
            ("gap drift yaw walk", self.yaw_walk_rad_per_sqrt_s),
            ("gap drift yaw floor", self.yaw_floor_rad),
            ("gap drift acceleration", self.accel_m_s2),
        ])
    }
}

/// `state` and `p` carried `gap_s` seconds ahead as [`coast`] does, then given what `fix` says
/// at the end of the gap: the heading replaced by the fix's, its variance grown by `drift`
/// instead of the land bound's yaw rate (`P_psi + (b T)^2 + w^2 T + f^2`); the INS velocity
/// turned with the heading (a land vehicle moves where it points). With a horizontal fix, the
/// position and velocity replaced too and grown by `drift`'s acceleration instead of `land`'s
/// (`a^2 [T^4/4, T^3/2; T^3/2, T^2]` per axis); without one, they keep `land`'s growth.
pub fn coast_to_fix(
    state: &NavState,
    p: &DMatrix<f64>,
    gap_s: f64,
    land: &CoastBounds,
    drift: &GapDrift,
    fix: &GapFix,
) -> Result<(NavState, DMatrix<f64>), EstimationError> {
    drift.check()?;
    let mut numbers = vec![("fix heading", fix.yaw_rad)];
    if let Some(h) = &fix.horizontal {
        numbers.extend([("fix position", h.pos_ne_m[0]), ("fix position", h.pos_ne_m[1])]);
        numbers.extend([("fix velocity", h.vel_ne_m_s[0]), ("fix velocity", h.vel_ne_m_s[1])]);
    }
    if let Some((what, value)) = numbers.into_iter().find(|(_, v)| !v.is_finite()) {
        return Err(EstimationError::InvalidValue { what, value });
    }
    let t = gap_s;
    let bounds = match fix.horizontal {
        Some(_) => CoastBounds {
            accel_m_s2: drift.accel_m_s2,
            yaw_rate_rad_s: drift.yaw_rate_rad_s,
            // (the planar robot: (s T)^2 = n^2 T)
            speed_m_s: if t > 0.0 { drift.accel_m_s2 / t.sqrt() } else { 0.0 },
        },
        None => CoastBounds { yaw_rate_rad_s: drift.yaw_rate_rad_s, ..*land },
    };
    let (coasted, mut p) = coast(state, p, gap_s, &bounds)?;
    let heading = match coasted {
        NavState::Ins(_) => super::ins::HEADING_INDEX,
        NavState::Planar(_) => 2,
    };
    p[(heading, heading)] += drift.yaw_walk_rad_per_sqrt_s.powi(2) * t + drift.yaw_floor_rad.powi(2);
    let out = match coasted {
        NavState::Ins(mut s) => {
            let (roll, pitch, yaw) = s.att_frd_to_ned.euler_angles();
            s.att_frd_to_ned = nalgebra::UnitQuaternion::from_euler_angles(roll, pitch, fix.yaw_rad);
            match &fix.horizontal {
                Some(h) => {
                    s.pos_ned_m.x = h.pos_ne_m[0];
                    s.pos_ned_m.y = h.pos_ne_m[1];
                    s.vel_ned_m_s.x = h.vel_ne_m_s[0];
                    s.vel_ned_m_s.y = h.vel_ne_m_s[1];
                }
                None => {
                    let turn = nalgebra::Rotation3::from_axis_angle(&nalgebra::Vector3::z_axis(), fix.yaw_rad - yaw);
                    s.vel_ned_m_s = turn * s.vel_ned_m_s;
                }
            }
            NavState::Ins(s)
        }
        NavState::Planar(mut s) => {
            s.yaw_rad = fix.yaw_rad;
            if let Some(h) = &fix.horizontal {
                s.pos_ned_m.x = h.pos_ne_m[0];
                s.pos_ned_m.y = h.pos_ne_m[1];
            }
            NavState::Planar(s)
        }
    };
    Ok((out, p))
}

/// Every value finite and at least zero, or the first that is not, named.
fn non_negative(values: &[(&'static str, f64)]) -> Result<(), EstimationError> {
    match values.iter().find(|(_, v)| !(v.is_finite() && *v >= 0.0)) {
        Some(&(what, value)) => Err(EstimationError::InvalidValue { what, value }),
        None => Ok(()),
    }
}

fn check_shape(p: &DMatrix<f64>, n: usize) -> Result<(), EstimationError> {
    let what = "coasted covariance";
    if p.nrows() != n {
        return Err(EstimationError::DimensionMismatch { what, expected: n, got: p.nrows() });
    }
    if p.ncols() != n {
        return Err(EstimationError::DimensionMismatch { what, expected: n, got: p.ncols() });
    }
    if p.iter().any(|v| !v.is_finite()) {
        return Err(EstimationError::NonFinite { what });
    }
    Ok(())
}

/// `(m + m^T) / 2`: the rounding of a product kept out of the symmetry every filter checks.
fn symmetric(m: DMatrix<f64>) -> DMatrix<f64> {
    (&m + m.transpose()) * 0.5
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::estimation::ins::InsState;
    use crate::estimation::planar::PlanarState;
    use nalgebra::{UnitQuaternion, Vector3};

    fn ins_state() -> InsState {
        InsState {
            pos_ned_m: Vector3::new(100.0, -50.0, 0.0),
            vel_ned_m_s: Vector3::new(8.0, 6.0, 0.0),
            att_frd_to_ned: UnitQuaternion::from_euler_angles(0.0, 0.0, 0.6435),
            accel_bias_frd_m_s2: Vector3::new(1e-3, -2e-3, 0.0),
            gyro_bias_frd_rad_s: Vector3::new(1e-5, 0.0, -1e-5),
            odometer_scale_error: 0.01,
        }
    }

    fn spd16() -> DMatrix<f64> {
        // a dense, well-conditioned covariance with position-velocity correlation
        let a = DMatrix::from_fn(ERROR_DIM, ERROR_DIM, |r, c| ((r * 7 + c * 3) % 11) as f64 * 0.01);
        &a * a.transpose() + DMatrix::identity(ERROR_DIM, ERROR_DIM) * 0.05
    }

    #[test]
    fn a_zero_gap_changes_nothing() {
        let (s, p) = (NavState::Ins(ins_state()), spd16());
        let (s2, p2) = coast(&s, &p, 0.0, &CoastBounds::LAND).unwrap();
        assert_eq!(s2, s);
        assert!((p2 - p).amax() < 1e-15);
    }

    #[test]
    fn the_ins_moves_on_at_its_velocity_and_grows_by_the_bounds() {
        let (s, p) = (NavState::Ins(ins_state()), spd16());
        let t = 3.0;
        let b = CoastBounds { accel_m_s2: 2.0, yaw_rate_rad_s: 0.5, speed_m_s: 5.0 };
        let (NavState::Ins(out), grown) = coast(&s, &p, t, &b).unwrap() else { panic!("an INS state stays one") };
        assert!((out.pos_ned_m - Vector3::new(124.0, -32.0, 0.0)).norm() < 1e-12);
        assert_eq!(out.vel_ned_m_s, ins_state().vel_ned_m_s);
        assert_eq!(out.att_frd_to_ned, ins_state().att_frd_to_ned);
        assert_eq!(out.accel_bias_frd_m_s2, ins_state().accel_bias_frd_m_s2);
        // position variance: P_pp + 2 T P_pv + T^2 P_vv + a^2 T^4 / 4, on every axis
        for i in 0..3 {
            let expected = p[(i, i)] + 2.0 * t * p[(i, 3 + i)] + t * t * p[(3 + i, 3 + i)] + 4.0 * t.powi(4) / 4.0;
            assert!((grown[(i, i)] - expected).abs() < 1e-12, "axis {i}: {} vs {expected}", grown[(i, i)]);
            let vel = p[(3 + i, 3 + i)] + 4.0 * t * t;
            assert!((grown[(3 + i, 3 + i)] - vel).abs() < 1e-12);
        }
        assert!((grown[(8, 8)] - (p[(8, 8)] + (0.5 * t).powi(2))).abs() < 1e-12);
        // roll, pitch and the biases are untouched
        for i in [6, 7, 9, 10, 11, 12, 13, 14, 15] {
            assert!((grown[(i, i)] - p[(i, i)]).abs() < 1e-12, "index {i}");
        }
        // symmetric and positive definite
        assert_eq!(grown, grown.transpose());
        assert!(grown.clone().cholesky().is_some());
    }

    #[test]
    fn the_added_ins_noise_is_that_of_an_unknown_constant_acceleration() {
        // With P = 0, position and velocity errors are a T^2/2 and a T of one draw of a: fully
        // correlated, so the 2 x 2 block per axis is singular.
        let p = DMatrix::zeros(ERROR_DIM, ERROR_DIM);
        let (_, q) = coast(&NavState::Ins(ins_state()), &p, 2.0, &CoastBounds::LAND).unwrap();
        for i in 0..3 {
            let det = q[(i, i)] * q[(3 + i, 3 + i)] - q[(i, 3 + i)] * q[(3 + i, i)];
            assert!(det.abs() < 1e-9 * q[(i, i)] * q[(3 + i, 3 + i)]);
            assert!((q[(i, i)].sqrt() - 2.0 * 4.0 / 2.0).abs() < 1e-12);
            assert!((q[(3 + i, 3 + i)].sqrt() - 2.0 * 2.0).abs() < 1e-12);
        }
    }

    #[test]
    fn the_planar_robot_keeps_its_pose_and_widens_by_its_speed() {
        let s = NavState::Planar(PlanarState { pos_ned_m: Vector3::new(1.0, 2.0, 0.0), yaw_rad: 0.3 });
        let p = DMatrix::from_diagonal(&nalgebra::DVector::from_vec(vec![0.01, 0.02, 0.001]));
        let (s2, p2) = coast(&s, &p, 4.0, &CoastBounds::LAND).unwrap();
        assert_eq!(s2, s);
        assert!((p2[(0, 0)] - (0.01 + 400.0)).abs() < 1e-12);
        assert!((p2[(1, 1)] - (0.02 + 400.0)).abs() < 1e-12);
        assert!((p2[(2, 2)] - (0.001 + 4.0)).abs() < 1e-12);
    }

    #[test]
    fn bad_gaps_bounds_and_shapes_are_refused() {
        let (s, p) = (NavState::Ins(ins_state()), spd16());
        for gap in [-1.0, f64::NAN, f64::INFINITY] {
            assert!(coast(&s, &p, gap, &CoastBounds::LAND).is_err(), "gap {gap}");
        }
        let bad = CoastBounds { accel_m_s2: f64::NAN, ..CoastBounds::LAND };
        assert!(coast(&s, &p, 1.0, &bad).is_err());
        assert!(coast(&s, &DMatrix::identity(3, 3), 1.0, &CoastBounds::LAND).is_err());
        let planar = NavState::Planar(PlanarState { pos_ned_m: Vector3::zeros(), yaw_rad: 0.0 });
        assert!(coast(&planar, &p, 1.0, &CoastBounds::LAND).is_err());
    }

    const DRIFT: GapDrift =
        GapDrift { yaw_rate_rad_s: 1e-3, yaw_walk_rad_per_sqrt_s: 1e-4, yaw_floor_rad: 0.035, accel_m_s2: 0.1 };

    #[test]
    fn a_heading_fix_replaces_the_heading_and_turns_the_velocity_and_the_position_keeps_the_land_bound() {
        let (s, p) = (NavState::Ins(ins_state()), spd16());
        let t = 10.0;
        let fix = GapFix { yaw_rad: 1.2, horizontal: None };
        let (NavState::Ins(out), grown) = coast_to_fix(&s, &p, t, &CoastBounds::LAND, &DRIFT, &fix).unwrap() else {
            panic!("an INS state stays one")
        };
        let (_, land) = coast(&s, &p, t, &CoastBounds::LAND).unwrap();
        let (roll, pitch, yaw) = out.att_frd_to_ned.euler_angles();
        assert!((yaw - 1.2).abs() < 1e-12 && roll.abs() < 1e-12 && pitch.abs() < 1e-12);
        // the heading: its own variance, the drift over the gap and the floor, not (0.5 rad/s x 10 s)^2
        let expected = p[(8, 8)] + (1e-3 * t).powi(2) + 1e-8 * t + 0.035f64.powi(2);
        assert!((grown[(8, 8)] - expected).abs() < 1e-12, "{} vs {expected}", grown[(8, 8)]);
        assert!(land[(8, 8)] > 24.0);
        // the velocity turned to the new heading, its speed kept; the position extrapolated as before
        assert!(
            (out.vel_ned_m_s - Vector3::new(10.0 * 1.2f64.cos(), 10.0 * 1.2f64.sin(), 0.0)).norm() < 2e-5,
            "{}",
            out.vel_ned_m_s
        ); // (the state's yaw 0.6435 is atan2(6, 8) to 1e-6)
        assert!((out.pos_ned_m - Vector3::new(180.0, 10.0, 0.0)).norm() < 1e-9);
        for i in 0..6 {
            assert!((grown[(i, i)] - land[(i, i)]).abs() < 1e-9, "index {i}: the land bound");
        }
        assert_eq!(grown, grown.transpose());
        assert!(grown.clone().cholesky().is_some());
    }

    #[test]
    fn a_horizontal_fix_replaces_position_and_velocity_and_grows_them_by_the_drift_alone() {
        let (s, p) = (NavState::Ins(ins_state()), spd16());
        let t = 5.0;
        let h = HorizontalFix { pos_ne_m: [141.5, -18.25], vel_ne_m_s: [-1.5, 2.0] };
        let fix = GapFix { yaw_rad: -0.4, horizontal: Some(h) };
        let (NavState::Ins(out), grown) = coast_to_fix(&s, &p, t, &CoastBounds::LAND, &DRIFT, &fix).unwrap() else { panic!() };
        assert_eq!((out.pos_ned_m.x, out.pos_ned_m.y, out.pos_ned_m.z), (141.5, -18.25, ins_state().pos_ned_m.z));
        assert_eq!((out.vel_ned_m_s.x, out.vel_ned_m_s.y), (-1.5, 2.0), "the fix's velocity, not the turned one");
        assert!((out.att_frd_to_ned.euler_angles().2 + 0.4).abs() < 1e-12);
        for i in 0..2 {
            let expected = p[(i, i)] + 2.0 * t * p[(i, 3 + i)] + t * t * p[(3 + i, 3 + i)] + 0.01 * t.powi(4) / 4.0;
            assert!((grown[(i, i)] - expected).abs() < 1e-12, "axis {i}");
            assert!((grown[(3 + i, 3 + i)] - (p[(3 + i, 3 + i)] + 0.01 * t * t)).abs() < 1e-12);
        }
        // the biases and the odometer scale untouched
        for i in 9..16 {
            assert!((grown[(i, i)] - p[(i, i)]).abs() < 1e-12, "index {i}");
        }
    }

    #[test]
    fn the_planar_robot_takes_the_fix_with_its_own_noise() {
        let s = NavState::Planar(PlanarState { pos_ned_m: Vector3::new(1.0, 2.0, 0.0), yaw_rad: 0.3 });
        let p = DMatrix::from_diagonal(&nalgebra::DVector::from_vec(vec![0.01, 0.02, 0.001]));
        let drift = GapDrift { yaw_rate_rad_s: 0.0, yaw_walk_rad_per_sqrt_s: 0.01, yaw_floor_rad: 0.02, accel_m_s2: 0.05 };
        let h = HorizontalFix { pos_ne_m: [3.0, 4.0], vel_ne_m_s: [0.0, 0.0] };
        let (NavState::Planar(out), grown) =
            coast_to_fix(&s, &p, 4.0, &CoastBounds::LAND, &drift, &GapFix { yaw_rad: -2.0, horizontal: Some(h) }).unwrap()
        else {
            panic!()
        };
        assert_eq!((out.pos_ned_m, out.yaw_rad), (Vector3::new(3.0, 4.0, 0.0), -2.0));
        assert!((grown[(0, 0)] - (0.01 + 0.0025 * 4.0)).abs() < 1e-12, "a random walk of the speed noise");
        assert!((grown[(2, 2)] - (0.001 + 1e-4 * 4.0 + 4e-4)).abs() < 1e-12);
        // without a horizontal fix the position keeps the land bound (5 m/s x 4 s)
        let (NavState::Planar(out), grown) =
            coast_to_fix(&s, &p, 4.0, &CoastBounds::LAND, &drift, &GapFix { yaw_rad: -2.0, horizontal: None }).unwrap()
        else {
            panic!()
        };
        assert_eq!(out.pos_ned_m, Vector3::new(1.0, 2.0, 0.0));
        assert!((grown[(0, 0)] - 400.01).abs() < 1e-9);
    }

    #[test]
    fn a_fix_or_a_drift_that_is_no_number_is_refused() {
        let (s, p) = (NavState::Ins(ins_state()), spd16());
        let bad_yaw = GapFix { yaw_rad: f64::NAN, horizontal: None };
        assert!(coast_to_fix(&s, &p, 1.0, &CoastBounds::LAND, &DRIFT, &bad_yaw).is_err());
        let h = HorizontalFix { pos_ne_m: [0.0, f64::INFINITY], vel_ne_m_s: [0.0, 0.0] };
        assert!(coast_to_fix(&s, &p, 1.0, &CoastBounds::LAND, &DRIFT, &GapFix { yaw_rad: 0.0, horizontal: Some(h) }).is_err());
        let drift = GapDrift { yaw_floor_rad: -0.1, ..DRIFT };
        assert!(coast_to_fix(&s, &p, 1.0, &CoastBounds::LAND, &drift, &GapFix { yaw_rad: 0.0, horizontal: None }).is_err());
    }

    #[test]
    fn an_imus_drift_comes_from_the_models_residual_errors() {
        use crate::estimation::ins::{InsConfig, InsInitialSigma};
        let mut initial_sigma = InsInitialSigma::for_tests();
        initial_sigma.gyro_bias_frd_rad_s.z = 8.7e-4;
        initial_sigma.att_ned_rad = Vector3::new(0.0087, 0.0087, 0.035);
        initial_sigma.accel_bias_frd_m_s2 = Vector3::new(0.049, 0.049, 0.049);
        let config = InsConfig::default();
        let d = GapDrift::of_model(&crate::estimation::nav::NavModel::Ins { config, initial_sigma });
        assert_eq!((d.yaw_rate_rad_s, d.yaw_floor_rad), (8.7e-4, 0.035));
        assert_eq!(d.yaw_walk_rad_per_sqrt_s, config.gyro_noise_density_rad_s_per_sqrt_hz);
        let tilt = config.gravity_m_s2 * 0.0087;
        assert!((d.accel_m_s2 - (0.049f64.powi(2) + tilt * tilt).sqrt()).abs() < 1e-12);
    }
}
