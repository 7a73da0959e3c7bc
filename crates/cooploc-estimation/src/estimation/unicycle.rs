//! A planar unicycle robot: error state `[dN, dE, dyaw]` (metres, metres, radians), driven by a
//! measured or commanded forward speed and yaw rate, in the team's NED frame (yaw from north,
//! clockwise seen from above). Its height is fixed and known (not a state).
//!
//! Discrete model over a step `dt` with speed `v` and yaw rate `w` (Euler, as a wheel-odometry
//! robot integrates):
//!
//! ```text
//! N += v cos(yaw) dt,   E += v sin(yaw) dt,   yaw += w dt
//! Phi = [1 0 -v sin(yaw) dt; 0 1 v cos(yaw) dt; 0 0 1]
//! Qd  = G diag(sigma_v^2, sigma_w^2) G^T,  G = [cos(yaw) dt 0; sin(yaw) dt 0; 0 dt]
//! ```

use nalgebra::{DMatrix, DVector, Matrix2, Matrix3, Matrix3x2, Vector3};
use serde::{Deserialize, Serialize};

use super::platform::{Geometry, Heading, PlatformFilter, check_joint_writeback, check_noise};
use super::{EstimationError, LinearizedMeasurement, UpdateDiagnostics, kalman};

/// Wraps an angle to (-pi, pi].
pub fn wrap_angle(a: f64) -> f64 {
    let two_pi = std::f64::consts::TAU;
    let mut w = a.rem_euclid(two_pi);
    if w > std::f64::consts::PI {
        w -= two_pi;
    }
    w
}

/// Noise of the inputs that drive the model, as standard deviations of the values used.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct UnicycleNoise {
    /// Standard deviation of the speed input, m/s.
    pub sigma_speed_m_s: f64,
    /// Standard deviation of the yaw-rate input, rad/s.
    pub sigma_yaw_rate_rad_s: f64,
}

/// Implements [`PlatformFilter`] for a planar model by handing every call to its `core`
/// ([`PlanarCore`]).
macro_rules! planar_platform_filter {
    ($model:ty) => {
        impl $crate::estimation::platform::PlatformFilter for $model {
            fn dim(&self) -> usize {
                3
            }
            fn covariance(&self) -> nalgebra::DMatrix<f64> {
                self.core.covariance()
            }
            fn psi(&self) -> nalgebra::DMatrix<f64> {
                self.core.psi()
            }
            fn geometry(&self) -> $crate::estimation::platform::Geometry {
                self.core.geometry()
            }
            fn update_local(
                &mut self,
                meas: &$crate::estimation::LinearizedMeasurement,
            ) -> Result<$crate::estimation::UpdateDiagnostics, $crate::estimation::EstimationError> {
                self.core.update_local(meas)
            }
            fn apply_joint(
                &mut self,
                dx: &nalgebra::DVector<f64>,
                p: &nalgebra::DMatrix<f64>,
            ) -> Result<(), $crate::estimation::EstimationError> {
                self.core.apply_joint(dx, p)
            }
            fn apply_bystander(
                &mut self,
                a: &nalgebra::DVector<f64>,
                b: &nalgebra::DMatrix<f64>,
            ) -> Result<(), $crate::estimation::EstimationError> {
                self.core.apply_bystander(a, b)
            }
            fn set_track_psi(&mut self, on: bool) {
                self.core.set_track_psi(on)
            }
        }
    };
}
pub(crate) use planar_platform_filter;

/// The error state both planar models share: nominal `[N, E, yaw]` at a fixed, known height,
/// its covariance and `Psi`, and the cooperative layer's view of them ([`PlatformFilter`]). A
/// model supplies only its propagation ([`PlanarCore::step`]).
#[derive(Debug, Clone)]
pub struct PlanarCore {
    /// Nominal `[N, E, yaw]`.
    x: Vector3<f64>,
    p: Matrix3<f64>,
    psi: Matrix3<f64>,
    height_d_m: f64,
    track_psi: bool,
}

impl PlanarCore {
    /// At `[N, E, yaw]` with covariance `p0` and height `height_d_m` (checked finite).
    pub fn new(x0: Vector3<f64>, p0: Matrix3<f64>, height_d_m: f64) -> Result<Self, EstimationError> {
        kalman::check_finite(&x0, "initial planar state")?;
        kalman::check_finite(&p0, "initial planar covariance")?;
        if !height_d_m.is_finite() {
            return Err(EstimationError::InvalidValue { what: "height", value: height_d_m });
        }
        let mut x = x0;
        x[2] = wrap_angle(x[2]);
        Ok(Self { x, p: p0, psi: Matrix3::identity(), height_d_m, track_psi: true })
    }

    /// Nominal `[N, E, yaw]`.
    pub fn state(&self) -> Vector3<f64> {
        self.x
    }

    pub fn height_d_m(&self) -> f64 {
        self.height_d_m
    }

    pub fn covariance3(&self) -> Matrix3<f64> {
        self.p
    }

    /// One propagation: `P <- Phi P Phi^T + Qd`, `Psi <- Phi Psi`, the nominal state moved by
    /// `dx` (yaw wrapped).
    pub fn step(&mut self, phi: &Matrix3<f64>, qd: &Matrix3<f64>, dx: &Vector3<f64>) {
        let p = phi * self.p * phi.transpose() + qd;
        self.p = 0.5 * (p + p.transpose());
        if self.track_psi {
            self.psi = phi * self.psi;
        }
        self.inject(dx);
    }

    fn inject(&mut self, dx: &Vector3<f64>) {
        self.x += dx;
        self.x[2] = wrap_angle(self.x[2]);
    }
}

impl PlatformFilter for PlanarCore {
    fn dim(&self) -> usize {
        3
    }
    fn covariance(&self) -> DMatrix<f64> {
        DMatrix::from_column_slice(3, 3, self.p.as_slice())
    }
    fn psi(&self) -> DMatrix<f64> {
        DMatrix::from_column_slice(3, 3, self.psi.as_slice())
    }
    fn geometry(&self) -> Geometry {
        Geometry {
            position_ned_m: Vector3::new(self.x[0], self.x[1], self.height_d_m),
            position_index: [Some(0), Some(1), None],
            heading: Some(Heading { yaw_rad: self.x[2], index: 2 }),
        }
    }
    fn update_local(&mut self, meas: &LinearizedMeasurement) -> Result<UpdateDiagnostics, EstimationError> {
        let up = kalman::local_update(&self.covariance(), meas)?;
        self.inject(&Vector3::new(up.dx[0], up.dx[1], up.dx[2]));
        self.p = Matrix3::from_column_slice(up.p.as_slice());
        if self.track_psi {
            self.psi = Matrix3::from_column_slice(up.i_minus_kh.as_slice()) * self.psi;
        }
        Ok(up.diagnostics)
    }
    fn add_noise(&mut self, q: &DMatrix<f64>) -> Result<(), EstimationError> {
        check_noise(3, q)?;
        self.p += Matrix3::from_column_slice(q.as_slice());
        Ok(())
    }
    fn apply_joint(&mut self, dx: &DVector<f64>, p: &DMatrix<f64>) -> Result<(), EstimationError> {
        check_joint_writeback(3, dx, p)?;
        self.inject(&Vector3::new(dx[0], dx[1], dx[2]));
        self.p = Matrix3::from_column_slice(p.as_slice());
        self.psi = Matrix3::identity();
        Ok(())
    }
    fn apply_bystander(&mut self, a: &DVector<f64>, b: &DMatrix<f64>) -> Result<(), EstimationError> {
        let p = DMatrix::from_column_slice(3, 3, self.p.as_slice());
        let psi = DMatrix::from_column_slice(3, 3, self.psi.as_slice());
        let (dx, p) = super::platform::bystander_posterior(&p, &psi, a, b)?;
        self.inject(&Vector3::new(dx[0], dx[1], dx[2]));
        self.p = Matrix3::from_column_slice(p.as_slice());
        Ok(())
    }
    fn set_track_psi(&mut self, on: bool) {
        self.track_psi = on;
        if !on {
            self.psi = Matrix3::identity();
        }
    }
}

#[derive(Debug, Clone)]
pub struct UnicycleFilter {
    core: PlanarCore,
    noise: UnicycleNoise,
}

impl UnicycleFilter {
    /// A robot at `[N, E, yaw]` with covariance `p0`, at a fixed down coordinate `height_d_m`.
    pub fn new(x0: Vector3<f64>, p0: Matrix3<f64>, height_d_m: f64, noise: UnicycleNoise) -> Result<Self, EstimationError> {
        for (v, what) in [(noise.sigma_speed_m_s, "speed sigma"), (noise.sigma_yaw_rate_rad_s, "yaw-rate sigma")] {
            if !v.is_finite() || v < 0.0 {
                return Err(EstimationError::InvalidValue { what, value: v });
            }
        }
        Ok(Self { core: PlanarCore::new(x0, p0, height_d_m)?, noise })
    }

    /// Nominal `[N, E, yaw]`.
    pub fn state(&self) -> Vector3<f64> {
        self.core.state()
    }

    /// Propagates over `dt_s` with forward speed `speed_m_s` and yaw rate `yaw_rate_rad_s`.
    pub fn propagate(&mut self, speed_m_s: f64, yaw_rate_rad_s: f64, dt_s: f64) -> Result<(), EstimationError> {
        for (v, what) in [(speed_m_s, "unicycle speed"), (yaw_rate_rad_s, "unicycle yaw rate"), (dt_s, "unicycle time step")] {
            if !v.is_finite() {
                return Err(EstimationError::NonFinite { what });
            }
        }
        if dt_s < 0.0 {
            return Err(EstimationError::InvalidValue { what: "unicycle time step", value: dt_s });
        }
        let (s, c) = self.core.state()[2].sin_cos();
        let phi = Matrix3::new(1.0, 0.0, -speed_m_s * s * dt_s, 0.0, 1.0, speed_m_s * c * dt_s, 0.0, 0.0, 1.0);
        let g = Matrix3x2::new(c * dt_s, 0.0, s * dt_s, 0.0, 0.0, dt_s);
        let q = Matrix2::new(self.noise.sigma_speed_m_s.powi(2), 0.0, 0.0, self.noise.sigma_yaw_rate_rad_s.powi(2));
        let dx = Vector3::new(speed_m_s * c * dt_s, speed_m_s * s * dt_s, yaw_rate_rad_s * dt_s);
        self.core.step(&phi, &(g * q * g.transpose()), &dx);
        Ok(())
    }
}

planar_platform_filter!(UnicycleFilter);

#[cfg(test)]
mod tests {
    use super::*;

    /// A bystander's share on a planar core: `Psi a` injected (yaw wrapped), `P - Psi b Psi^T`
    /// taken, `Psi` kept; an indefinite result is refused and changes nothing.
    #[test]
    fn a_bystanders_share_is_taken_through_psi_and_keeps_it() {
        let p0 = Matrix3::new(4.0, 0.5, 0.1, 0.5, 3.0, 0.2, 0.1, 0.2, 0.5);
        let mut c = PlanarCore::new(Vector3::new(1.0, 2.0, 3.1), p0, -0.3).unwrap();
        let phi = Matrix3::new(1.0, 0.0, -0.4, 0.0, 1.0, 0.9, 0.0, 0.0, 1.0);
        c.step(&phi, &(Matrix3::identity() * 0.01), &Vector3::zeros());
        let (p1, psi, x1) = (c.p, c.psi, c.x);
        assert_ne!(psi, Matrix3::identity());
        let a = DVector::from_column_slice(&[0.1, -0.2, 0.1]);
        let b = DMatrix::from_column_slice(3, 3, &[0.5, 0.1, 0.0, 0.1, 0.4, 0.05, 0.0, 0.05, 0.1]);
        c.apply_bystander(&a, &b).unwrap();
        let psi_d = DMatrix::from_column_slice(3, 3, psi.as_slice());
        let dx = &psi_d * &a;
        let want = DMatrix::from_column_slice(3, 3, p1.as_slice()) - &psi_d * &b * psi_d.transpose();
        assert!((DMatrix::from_column_slice(3, 3, c.p.as_slice()) - want).amax() < 1e-12);
        assert_eq!(c.psi, psi);
        assert!((c.x[0] - x1[0] - dx[0]).abs() < 1e-12 && (c.x[1] - x1[1] - dx[1]).abs() < 1e-12);
        assert!((c.x[2] - wrap_angle(x1[2] + dx[2])).abs() < 1e-12);
        let before = (c.p, c.psi, c.x);
        assert!(c.apply_bystander(&a, &(b * 100.0)).is_err());
        assert_eq!((c.p, c.psi, c.x), before);
    }

    #[test]
    fn wraps_angles() {
        use std::f64::consts::PI;
        assert!((wrap_angle(3.0 * PI) - PI).abs() < 1e-12);
        assert!((wrap_angle(-PI) - PI).abs() < 1e-12);
        assert!((wrap_angle(0.5) - 0.5).abs() < 1e-15);
        assert!((wrap_angle(-7.0) - (-7.0 + 2.0 * PI)).abs() < 1e-12);
    }

    #[test]
    fn drives_a_quarter_circle_and_grows_uncertainty() {
        let noise = UnicycleNoise { sigma_speed_m_s: 0.1, sigma_yaw_rate_rad_s: 0.01 };
        let mut f = UnicycleFilter::new(Vector3::zeros(), Matrix3::identity() * 1e-6, 0.0, noise).unwrap();
        let r = 10.0;
        let w = 0.1;
        let n = 100_000;
        let dt = (std::f64::consts::FRAC_PI_2 / w) / n as f64;
        for _ in 0..n {
            f.propagate(r * w, w, dt).unwrap();
        }
        let x = f.state();
        assert!((x[0] - r).abs() < 1e-3 && (x[1] - r).abs() < 1e-3, "{x}");
        assert!((x[2] - std::f64::consts::FRAC_PI_2).abs() < 1e-9);
        assert!(f.core.covariance3()[(0, 0)] > 1e-4 && f.core.covariance3()[(2, 2)] > 1e-6);
        assert!(f.propagate(f64::NAN, 0.0, 0.1).is_err());
        assert_eq!(f.state(), x, "a rejected input leaves the state alone");
    }
}
