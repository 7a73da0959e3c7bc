//! Estimates and truth as Foxglove well-known messages (pure functions, no I/O).
//!
//! cooploc works in a local NED frame (metres, z down) with yaw measured clockwise from north.
//! Foxglove expects:
//! - `foxglove.LocationFix`: latitude/longitude/altitude, and a position covariance in **ENU**
//!   (East, North, Up), row-major 3x3. [`cov_ned_to_enu`] permutes and flips the NED covariance.
//! - `foxglove.PoseInFrame` / `foxglove.SceneUpdate`: positions in a named frame. We use frame
//!   `ned` (x north, y east, z down, as cooploc) and publish one `foxglove.FrameTransform`
//!   `world` -> `ned` ([`world_to_ned`]) so that the 3-D panel, whose display frame `world` has
//!   z up, shows the vehicles the right way up.
//!
//! The 95 % ellipse is the horizontal (N, E) marginal of the position covariance: semi-axes
//! `sqrt(chi2_2(0.95) * lambda_i)` along its eigenvectors, drawn as a sphere flattened to
//! [`ELLIPSE_THICKNESS_M`].

use foxglove::messages::{
    Color, FrameTransform, KeyValuePair, LocationFix, Pose, PoseInFrame, Quaternion, SceneEntity, SceneUpdate, SpherePrimitive,
    Timestamp, Vector3 as FxVector3, location_fix::PositionCovarianceType,
};
use nalgebra::{Matrix3, Vector3};

use crate::protocol::wire::{GeoOrigin, ned_to_geodetic};
use crate::time::TimeUs;

/// Name of the local NED frame in the Foxglove messages.
pub const NED_FRAME: &str = "ned";
/// Name of Foxglove's display frame (ENU, z up), parent of [`NED_FRAME`].
pub const WORLD_FRAME: &str = "world";
pub use crate::estimation::consistency::CHI2_2DOF_95;
/// Vertical size of the drawn ellipse, m.
pub const ELLIPSE_THICKNESS_M: f64 = 0.05;

/// A vehicle's position estimate, as the recorder takes it.
#[derive(Debug, Clone, PartialEq)]
pub struct PositionEstimate {
    /// Filter time of the estimate (the vehicle's clock).
    pub t: TimeUs,
    pub pos_ned_m: Vector3<f64>,
    /// Covariance of `pos_ned_m`, m^2.
    pub cov_ned_m2: Matrix3<f64>,
    /// Heading, rad, clockwise from north (None: the platform has no heading).
    pub yaw_rad: Option<f64>,
    pub vel_ned_m_s: Option<Vector3<f64>>,
}

impl PositionEstimate {
    /// Which field is not finite, if any.
    pub(crate) fn non_finite_field(&self) -> Option<&'static str> {
        if !self.pos_ned_m.iter().all(|v| v.is_finite()) {
            Some("pos_ned_m")
        } else if !self.cov_ned_m2.iter().all(|v| v.is_finite()) {
            Some("cov_ned_m2")
        } else if !self.yaw_rad.is_none_or(f64::is_finite) {
            Some("yaw_rad")
        } else if !self.vel_ned_m_s.is_none_or(|v| v.iter().all(|x| x.is_finite())) {
            Some("vel_ned_m_s")
        } else {
            None
        }
    }
}

/// A vehicle's true position (simulation), as the recorder takes it.
#[derive(Debug, Clone, PartialEq)]
pub struct TruthSample {
    pub t: TimeUs,
    pub pos_ned_m: Vector3<f64>,
    pub yaw_rad: Option<f64>,
}

/// A Foxglove timestamp from nanoseconds since the UNIX epoch (saturates past 2106).
pub fn timestamp(wall_ns: u64) -> Timestamp {
    let sec = wall_ns / 1_000_000_000;
    match u32::try_from(sec) {
        Ok(sec) => Timestamp::new(sec, (wall_ns % 1_000_000_000) as u32),
        Err(_) => Timestamp::MAX,
    }
}

/// A colour per vehicle (a ten-colour palette, by id), with alpha `a`.
pub fn vehicle_color(id: u16, a: f64) -> Color {
    const PALETTE: [(f64, f64, f64); 10] = [
        (0.122, 0.467, 0.706),
        (1.000, 0.498, 0.055),
        (0.173, 0.627, 0.173),
        (0.839, 0.153, 0.157),
        (0.580, 0.404, 0.741),
        (0.549, 0.337, 0.294),
        (0.890, 0.467, 0.761),
        (0.498, 0.498, 0.498),
        (0.737, 0.741, 0.133),
        (0.090, 0.745, 0.812),
    ];
    let (r, g, b) = PALETTE[id as usize % PALETTE.len()];
    Color { r, g, b, a }
}

/// The NED covariance expressed in ENU: `E = N_e`, `N = N_n`, `U = -D`.
pub fn cov_ned_to_enu(cov_ned: &Matrix3<f64>) -> Matrix3<f64> {
    #[rustfmt::skip]
    let t = Matrix3::new(
        0.0, 1.0, 0.0,
        1.0, 0.0, 0.0,
        0.0, 0.0, -1.0,
    );
    t * cov_ned * t.transpose()
}

/// Row-major elements of a 3x3 matrix.
fn row_major(m: &Matrix3<f64>) -> Vec<f64> {
    (0..3).flat_map(|r| (0..3).map(move |c| m[(r, c)])).collect()
}

/// Quaternion of a rotation by `yaw` about the z axis.
fn yaw_quaternion(yaw_rad: f64) -> Quaternion {
    let h = 0.5 * yaw_rad;
    Quaternion { x: 0.0, y: 0.0, z: h.sin(), w: h.cos() }
}

fn fx_vector(v: &Vector3<f64>) -> FxVector3 {
    FxVector3 { x: v[0], y: v[1], z: v[2] }
}

/// The estimate as a `foxglove.LocationFix` about `origin`, covariance KNOWN (ENU). The filter
/// time goes into the metadata as `t_us`.
pub fn location_fix(origin: &GeoOrigin, id: u16, est: &PositionEstimate, wall_ns: u64) -> LocationFix {
    let g = ned_to_geodetic(origin, &est.pos_ned_m);
    LocationFix {
        timestamp: Some(timestamp(wall_ns)),
        frame_id: format!("vehicle_{id}"),
        latitude: g.lat_deg,
        longitude: g.lon_deg,
        altitude: g.alt_m,
        position_covariance: row_major(&cov_ned_to_enu(&est.cov_ned_m2)),
        position_covariance_type: PositionCovarianceType::Known as i32,
        heading: est.yaw_rad,
        velocity: est.vel_ned_m_s.map(|v| FxVector3 { x: v[1], y: v[0], z: -v[2] }),
        color: Some(vehicle_color(id, 1.0)),
        metadata: vec![KeyValuePair { key: "t_us".into(), value: est.t.0.to_string() }],
    }
}

/// The truth as a `foxglove.LocationFix` (no covariance: type UNKNOWN, zeros).
pub fn truth_fix(origin: &GeoOrigin, id: u16, truth: &TruthSample, wall_ns: u64) -> LocationFix {
    let g = ned_to_geodetic(origin, &truth.pos_ned_m);
    LocationFix {
        timestamp: Some(timestamp(wall_ns)),
        frame_id: format!("vehicle_{id}_truth"),
        latitude: g.lat_deg,
        longitude: g.lon_deg,
        altitude: g.alt_m,
        position_covariance: vec![0.0; 9],
        position_covariance_type: PositionCovarianceType::Unknown as i32,
        heading: truth.yaw_rad,
        velocity: None,
        color: Some(Color { r: 0.1, g: 0.1, b: 0.1, a: 1.0 }),
        metadata: vec![KeyValuePair { key: "t_us".into(), value: truth.t.0.to_string() }],
    }
}

/// A NED position and yaw (0 when unknown) as a `foxglove.PoseInFrame` in frame `ned`.
pub fn pose_in_ned(pos_ned_m: &Vector3<f64>, yaw_rad: Option<f64>, wall_ns: u64) -> PoseInFrame {
    PoseInFrame {
        timestamp: Some(timestamp(wall_ns)),
        frame_id: NED_FRAME.into(),
        pose: Some(Pose { position: Some(fx_vector(pos_ned_m)), orientation: Some(yaw_quaternion(yaw_rad.unwrap_or(0.0))) }),
    }
}

/// The fixed transform from Foxglove's `world` (ENU) to `ned`: a half turn about (1, 1, 0)/sqrt 2,
/// which maps (N, E, D) to (E, N, -U).
pub fn world_to_ned(wall_ns: u64) -> FrameTransform {
    let s = std::f64::consts::FRAC_1_SQRT_2;
    FrameTransform {
        timestamp: Some(timestamp(wall_ns)),
        parent_frame_id: WORLD_FRAME.into(),
        child_frame_id: NED_FRAME.into(),
        translation: Some(FxVector3 { x: 0.0, y: 0.0, z: 0.0 }),
        rotation: Some(Quaternion { x: s, y: s, z: 0.0, w: 0.0 }),
    }
}

/// Semi-axes (major, minor, m) of the 95 % ellipse of a horizontal 2x2 covariance
/// `[[nn, ne], [ne, ee]]`, and the angle of the major axis from north towards east, rad
/// ([`crate::estimation::consistency::ellipse95_axes`]); a covariance that lost its
/// definiteness draws as a point.
pub fn ellipse_axes(nn: f64, ne: f64, ee: f64) -> (f64, f64, f64) {
    crate::estimation::consistency::ellipse95_axes(nn, ne, ee).unwrap_or((0.0, 0.0, 0.0))
}

/// The 95 % horizontal ellipse of the estimate as a `foxglove.SceneUpdate` with one entity
/// `vehicle_<id>_ellipse` (replaced by each update) in frame `ned`.
pub fn ellipse_update(id: u16, est: &PositionEstimate, wall_ns: u64) -> SceneUpdate {
    let c = &est.cov_ned_m2;
    let (major, minor, angle) = ellipse_axes(c[(0, 0)], c[(0, 1)], c[(1, 1)]);
    let sphere = SpherePrimitive {
        pose: Some(Pose { position: Some(fx_vector(&est.pos_ned_m)), orientation: Some(yaw_quaternion(angle)) }),
        size: Some(FxVector3 { x: 2.0 * major, y: 2.0 * minor, z: ELLIPSE_THICKNESS_M }),
        color: Some(vehicle_color(id, 0.35)),
    };
    SceneUpdate {
        deletions: vec![],
        entities: vec![SceneEntity {
            timestamp: Some(timestamp(wall_ns)),
            frame_id: NED_FRAME.into(),
            id: format!("vehicle_{id}_ellipse"),
            lifetime: None,
            frame_locked: false,
            metadata: vec![KeyValuePair { key: "t_us".into(), value: est.t.0.to_string() }],
            spheres: vec![sphere],
            ..Default::default()
        }],
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use approx::assert_relative_eq;
    use nalgebra::{Rotation3, UnitQuaternion};

    #[test]
    fn enu_covariance_permutes_and_flips() {
        #[rustfmt::skip]
        let ned = Matrix3::new(
            4.0, 1.0, 0.5,
            1.0, 9.0, -0.3,
            0.5, -0.3, 16.0,
        );
        let enu = cov_ned_to_enu(&ned);
        assert_eq!(enu[(0, 0)], 9.0); // E-E
        assert_eq!(enu[(1, 1)], 4.0); // N-N
        assert_eq!(enu[(2, 2)], 16.0); // U-U
        assert_eq!(enu[(0, 1)], 1.0); // E-N
        assert_eq!(enu[(0, 2)], 0.3); // E-U = -(E-D)
        assert_eq!(enu[(1, 2)], -0.5); // N-U = -(N-D)
        assert_eq!(row_major(&enu)[1], enu[(0, 1)]);
        assert_eq!(row_major(&enu)[5], enu[(1, 2)]);
    }

    #[test]
    fn world_to_ned_maps_ned_axes_to_enu() {
        let q = world_to_ned(0).rotation.unwrap();
        let q = UnitQuaternion::from_quaternion(nalgebra::Quaternion::new(q.w, q.x, q.y, q.z));
        // A point 1 m north, 2 m east, 3 m down is at E = 2, N = 1, U = -3 in the world.
        let p = q.transform_vector(&Vector3::new(1.0, 2.0, 3.0));
        assert_relative_eq!(p, Vector3::new(2.0, 1.0, -3.0), epsilon = 1e-12);
    }

    #[test]
    fn yaw_quaternion_turns_north_to_east() {
        let q = yaw_quaternion(std::f64::consts::FRAC_PI_2);
        let q = UnitQuaternion::from_quaternion(nalgebra::Quaternion::new(q.w, q.x, q.y, q.z));
        assert_relative_eq!(q.transform_vector(&Vector3::x()), Vector3::y(), epsilon = 1e-12);
    }

    #[test]
    fn ellipse_axes_match_an_eigen_decomposition() {
        // Axes 3 m and 1 m (1 sigma), major axis 30 degrees east of north.
        let th = 30f64.to_radians();
        let r = Rotation3::from_axis_angle(&Vector3::z_axis(), th);
        let d = Matrix3::from_diagonal(&Vector3::new(9.0, 1.0, 0.0));
        let c = r.matrix() * d * r.matrix().transpose();
        let (major, minor, angle) = ellipse_axes(c[(0, 0)], c[(0, 1)], c[(1, 1)]);
        assert_relative_eq!(major, 3.0 * CHI2_2DOF_95.sqrt(), epsilon = 1e-9);
        assert_relative_eq!(minor, CHI2_2DOF_95.sqrt(), epsilon = 1e-9);
        assert_relative_eq!(angle, th, epsilon = 1e-9);
        // A circle: equal axes; an indefinite matrix: the negative axis is zero.
        let (a, b, _) = ellipse_axes(2.0, 0.0, 2.0);
        assert_relative_eq!(a, b);
        assert_eq!(ellipse_axes(1.0, 0.0, -1.0).1, 0.0);
    }

    #[test]
    fn location_fix_about_the_origin() {
        let origin = GeoOrigin { lat_deg: 48.0, lon_deg: 11.0, alt_m: 500.0 };
        let est = PositionEstimate {
            t: TimeUs(5_000_000),
            pos_ned_m: Vector3::new(100.0, 0.0, -10.0),
            cov_ned_m2: Matrix3::from_diagonal(&Vector3::new(4.0, 1.0, 9.0)),
            yaw_rad: Some(0.5),
            vel_ned_m_s: Some(Vector3::new(1.0, 2.0, 0.0)),
        };
        let fix = location_fix(&origin, 2, &est, 1_700_000_000_123_456_789);
        assert!(fix.latitude > 48.0 && fix.latitude < 48.001);
        assert_relative_eq!(fix.longitude, 11.0);
        assert_relative_eq!(fix.altitude, 510.0);
        assert_eq!(fix.position_covariance, vec![1.0, 0.0, 0.0, 0.0, 4.0, 0.0, 0.0, 0.0, 9.0]);
        assert_eq!(fix.position_covariance_type, PositionCovarianceType::Known as i32);
        let v = fix.velocity.unwrap();
        assert_eq!((v.x, v.y, v.z), (2.0, 1.0, 0.0));
        let ts = fix.timestamp.unwrap();
        assert_eq!((ts.sec(), ts.nsec()), (1_700_000_000, 123_456_789));
        assert_eq!(timestamp(u64::MAX), Timestamp::MAX);
    }
}
