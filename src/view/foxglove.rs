//! Estimates and truth as Foxglove well-known messages (pure functions, no I/O): what the
//! ground station's live server and every MCAP recorder publish, on the topics of
//! [`crate::recording::topics`].
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
//! [`ELLIPSE_THICKNESS_M`], labelled with the vehicle's name. Colours are the palette of
//! [`super::PALETTE`]: the estimate opaque, its ellipse at [`ELLIPSE_ALPHA`], the truth at
//! [`TRUTH_ALPHA`].

use foxglove::messages::{
    Color, FrameTransform, KeyValuePair, LocationFix, Pose, PoseInFrame, Quaternion, SceneEntity, SceneUpdate, SpherePrimitive,
    TextPrimitive, Timestamp, Vector3 as FxVector3, location_fix::PositionCovarianceType,
};
use nalgebra::{Matrix3, Vector3};
use serde::Serialize;

use crate::estimation::consistency::Ellipse95;
use crate::protocol::wire::{EstimateReport, GeoOrigin, ned_to_geodetic};
use crate::time::TimeUs;

/// Name of the local NED frame in the Foxglove messages.
pub const NED_FRAME: &str = "ned";
/// Name of Foxglove's display frame (ENU, z up), parent of [`NED_FRAME`].
pub const WORLD_FRAME: &str = "world";
pub use crate::estimation::consistency::CHI2_2DOF_95;
/// Vertical size of the drawn ellipse, m.
pub const ELLIPSE_THICKNESS_M: f64 = 0.05;
/// Opacity of an ellipse, and of a truth marker.
pub const ELLIPSE_ALPHA: f64 = 0.35;
pub const TRUTH_ALPHA: f64 = 0.5;

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

/// The colour of vehicle `id` ([`super::vehicle_rgb`]) with alpha `a`.
pub fn vehicle_color(id: u16, a: f64) -> Color {
    let [r, g, b] = super::vehicle_rgb(id);
    Color { r: f64::from(r) / 255.0, g: f64::from(g) / 255.0, b: f64::from(b) / 255.0, a }
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

/// A `foxglove.LocationFix` of a NED position about `origin` at filter time `t` (in the
/// metadata as `t_us`), in the frame `frame_id`; covariance, heading, velocity and colour unset.
fn fix(origin: &GeoOrigin, frame_id: String, pos_ned_m: &Vector3<f64>, t: TimeUs, wall_ns: u64) -> LocationFix {
    let g = ned_to_geodetic(origin, pos_ned_m);
    LocationFix {
        timestamp: Some(timestamp(wall_ns)),
        frame_id,
        latitude: g.lat_deg,
        longitude: g.lon_deg,
        altitude: g.alt_m,
        metadata: vec![KeyValuePair { key: "t_us".into(), value: t.0.to_string() }],
        ..Default::default()
    }
}

/// The estimate as a `foxglove.LocationFix` about `origin`, covariance KNOWN (ENU). The filter
/// time goes into the metadata as `t_us`.
pub fn location_fix(origin: &GeoOrigin, id: u16, est: &PositionEstimate, wall_ns: u64) -> LocationFix {
    LocationFix {
        position_covariance: row_major(&cov_ned_to_enu(&est.cov_ned_m2)),
        position_covariance_type: PositionCovarianceType::Known as i32,
        heading: est.yaw_rad,
        velocity: est.vel_ned_m_s.map(|v| FxVector3 { x: v[1], y: v[0], z: -v[2] }),
        color: Some(vehicle_color(id, 1.0)),
        ..fix(origin, format!("vehicle_{id}"), &est.pos_ned_m, est.t, wall_ns)
    }
}

/// The truth as a `foxglove.LocationFix` (no covariance: type UNKNOWN, zeros).
pub fn truth_fix(origin: &GeoOrigin, id: u16, truth: &TruthSample, wall_ns: u64) -> LocationFix {
    LocationFix {
        position_covariance: vec![0.0; 9],
        position_covariance_type: PositionCovarianceType::Unknown as i32,
        heading: truth.yaw_rad,
        color: Some(vehicle_color(id, TRUTH_ALPHA)),
        ..fix(origin, format!("vehicle_{id}_truth"), &truth.pos_ned_m, truth.t, wall_ns)
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
        color: Some(vehicle_color(id, ELLIPSE_ALPHA)),
    };
    let label = TextPrimitive {
        pose: Some(Pose { position: Some(fx_vector(&est.pos_ned_m)), orientation: Some(yaw_quaternion(0.0)) }),
        billboard: true,
        font_size: 14.0,
        scale_invariant: true,
        color: Some(vehicle_color(id, 1.0)),
        text: super::vehicle_name(id),
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
            texts: vec![label],
            ..Default::default()
        }],
    }
}

/// The estimate a node reports (COOPLOC_ESTIMATE), as a display draws it.
pub fn position_estimate(r: &EstimateReport) -> PositionEstimate {
    PositionEstimate {
        t: r.t,
        pos_ned_m: r.position_ned_m,
        cov_ned_m2: r.position_covariance_m2,
        yaw_rad: Some(r.yaw_rad),
        vel_ned_m_s: Some(r.velocity_ned_m_s),
    }
}

/// The JSON view of an estimate (`/vehicle_<id>/estimate`): what the page's vehicle card shows.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct EstimateJson {
    pub vehicle: u16,
    pub t_s: f64,
    pub epoch: u32,
    pub method: &'static str,
    pub north_m: f64,
    pub east_m: f64,
    pub down_m: f64,
    pub yaw_deg: f64,
    /// Null when no joint update has run.
    pub nis: Option<f64>,
    pub participants: u8,
    pub ranges: u8,
    pub semi_major_95_m: Option<f64>,
    pub semi_minor_95_m: Option<f64>,
    /// Bearing of the major axis from north towards east, degrees.
    pub major_bearing_95_deg: Option<f64>,
}

impl EstimateJson {
    pub fn of(r: &EstimateReport, ellipse: Option<&Ellipse95>) -> Self {
        let p = &r.position_ned_m;
        EstimateJson {
            vehicle: r.platform,
            t_s: r.t.as_secs_f64(),
            epoch: r.epoch,
            method: r.method.short_name(),
            north_m: p[0],
            east_m: p[1],
            down_m: p[2],
            yaw_deg: r.yaw_rad.to_degrees(),
            nis: r.nis.is_finite().then_some(r.nis),
            participants: r.participants,
            ranges: r.ranges,
            semi_major_95_m: ellipse.map(|e| e.semi_major_m),
            semi_minor_95_m: ellipse.map(|e| e.semi_minor_m),
            major_bearing_95_deg: ellipse.map(|e| e.major_bearing_deg),
        }
    }
}

/// JSON schema of [`EstimateJson`].
pub const ESTIMATE_SCHEMA_NAME: &str = "cooploc.Estimate";
pub const ESTIMATE_SCHEMA: &str = r#"{"type":"object","properties":{"vehicle":{"type":"integer"},"t_s":{"type":"number"},"epoch":{"type":"integer"},"method":{"type":"string"},"north_m":{"type":"number"},"east_m":{"type":"number"},"down_m":{"type":"number"},"yaw_deg":{"type":"number"},"nis":{"type":["number","null"]},"participants":{"type":"integer"},"ranges":{"type":"integer"},"semi_major_95_m":{"type":["number","null"]},"semi_minor_95_m":{"type":["number","null"]},"major_bearing_95_deg":{"type":["number","null"]}},"required":["vehicle","t_s","epoch","method","north_m","east_m","down_m","yaw_deg","nis","participants","ranges","semi_major_95_m","semi_minor_95_m","major_bearing_95_deg"]}"#;

/// The error of an estimate against the truth (`/vehicle_<id>/error`).
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct ErrorJson {
    pub vehicle: u16,
    pub t_s: f64,
    pub horizontal_m: f64,
    /// Position NEES over N, E, D (null: covariance not positive definite).
    pub nees: Option<f64>,
}

pub const ERROR_SCHEMA_NAME: &str = "cooploc.TruthError";
pub const ERROR_SCHEMA: &str = r#"{"type":"object","properties":{"vehicle":{"type":"integer"},"t_s":{"type":"number"},"horizontal_m":{"type":"number"},"nees":{"type":["number","null"]}},"required":["vehicle","t_s","horizontal_m","nees"]}"#;

/// JSON schema of [`super::health::HealthView`] (`/team/health`).
pub const HEALTH_SCHEMA_NAME: &str = "cooploc.TeamHealth";
pub const HEALTH_SCHEMA: &str = r#"{"type":"object","properties":{"rx_ns":{"type":"integer"},"last_epoch":{"type":["integer","null"]},"disagreements":{"type":"integer"},"heals":{"type":"integer"},"unhealed_since":{"type":["integer","null"]},"link_capacity_bytes_per_s":{"type":["number","null"]},"team_bytes_per_s":{"type":"number"},"team_load_pct":{"type":["number","null"]},"verifying":{"type":"boolean"},"nodes":{"type":"array","items":{"type":"object","properties":{"id":{"type":"integer"},"name":{"type":"string"},"color":{"type":"string"},"estimate_rate_hz":{"type":["number","null"]},"bytes_per_s":{"type":"number"},"budget_bytes_per_s":{"type":["number","null"]},"budget_used_pct":{"type":["number","null"]},"loss_pct":{"type":["number","null"]},"signed_frames":{"type":"integer"},"unsigned_frames":{"type":"integer"},"signing":{"type":"string"},"reports":{"type":"integer"},"outvoted":{"type":"integer"},"heals":{"type":"integer"},"partial":{"type":"integer"},"failed":{"type":"integer"},"store_wanted":{"type":"integer"}},"required":["id","name","color","estimate_rate_hz","bytes_per_s","budget_bytes_per_s","budget_used_pct","loss_pct","signed_frames","unsigned_frames","signing","reports","outvoted","heals","partial","failed","store_wanted"]}}},"required":["rx_ns","last_epoch","disagreements","heals","unhealed_since","link_capacity_bytes_per_s","team_bytes_per_s","team_load_pct","verifying","nodes"]}"#;

#[cfg(test)]
mod tests {
    use super::*;
    use approx::assert_relative_eq;
    use nalgebra::{Rotation3, UnitQuaternion};

    /// Every field the JSON channels carry is named (and required) by their schema.
    #[test]
    fn json_schemas_name_every_field() {
        use crate::estimation::Method;
        use crate::view::health::{EpochTally, HealthView, NodeHealth};
        fn keys(v: &serde_json::Value) -> Vec<String> {
            let mut k: Vec<String> = v.as_object().unwrap().keys().cloned().collect();
            k.sort();
            k
        }
        fn required(schema: &str, nodes: bool) -> Vec<String> {
            let js: serde_json::Value = serde_json::from_str(schema).unwrap();
            let js = if nodes { &js["properties"]["nodes"]["items"] } else { &js };
            let mut props = keys(&js["properties"]);
            let mut req: Vec<String> =
                js["required"].as_array().unwrap().iter().map(|v| v.as_str().unwrap().to_string()).collect();
            req.sort();
            props.sort();
            assert_eq!(props, req, "properties and required differ");
            req
        }
        let report = EstimateReport {
            platform: 2,
            t: TimeUs(1_500_000),
            epoch: 3,
            method: Method::Decentralized,
            position_ned_m: Vector3::new(1.0, 2.0, 3.0),
            velocity_ned_m_s: Vector3::zeros(),
            yaw_rad: 0.1,
            position_covariance_m2: Matrix3::identity(),
            yaw_variance_rad2: 0.01,
            nis: f64::NAN,
            participants: 3,
            ranges: 2,
        };
        let est = serde_json::to_value(EstimateJson::of(&report, None)).unwrap();
        assert_eq!(keys(&est), required(ESTIMATE_SCHEMA, false));
        assert!(est["nis"].is_null(), "NaN NIS is null");
        let err = serde_json::to_value(ErrorJson { vehicle: 2, t_s: 1.0, horizontal_m: 0.5, nees: None }).unwrap();
        assert_eq!(keys(&err), required(ERROR_SCHEMA, false));
        let node = NodeHealth {
            id: 2,
            name: "vehicle 2".into(),
            color: "#ff7f0e".into(),
            estimate_rate_hz: Some(1.0),
            bytes_per_s: 10.0,
            budget_bytes_per_s: None,
            budget_used_pct: None,
            loss_pct: None,
            signed_frames: 0,
            unsigned_frames: 1,
            signing: "unsigned",
            epochs: EpochTally::new().nodes.get(&2).copied().unwrap_or_default(),
        };
        let health = HealthView {
            rx_ns: 1,
            last_epoch: None,
            disagreements: 0,
            heals: 0,
            unhealed_since: None,
            link_capacity_bytes_per_s: None,
            team_bytes_per_s: 10.0,
            team_load_pct: None,
            verifying: false,
            nodes: vec![node],
        };
        let h = serde_json::to_value(&health).unwrap();
        assert_eq!(keys(&h), required(HEALTH_SCHEMA, false));
        assert_eq!(keys(&h["nodes"][0]), required(HEALTH_SCHEMA, true));
    }

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
