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
        for (what, value) in [
            ("coast acceleration bound", self.accel_m_s2),
            ("coast yaw-rate bound", self.yaw_rate_rad_s),
            ("coast speed bound", self.speed_m_s),
        ] {
            if !(value.is_finite() && value >= 0.0) {
                return Err(EstimationError::InvalidValue { what, value });
            }
        }
        Ok(())
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
}
