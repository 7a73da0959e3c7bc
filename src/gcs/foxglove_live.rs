//! The ground station's updates on Foxglove's live WebSocket protocol (the official `foxglove`
//! crate's server, subprotocol `foxglove.sdk.v1` / `foxglove.sdk.v1.1`), with well-known schemas
//! so that the Foxglove app's Map, 3D and Plot panels show them as they are:
//!
//! | topic | schema | from |
//! |---|---|---|
//! | `/vehicle_<id>/location` | `foxglove.LocationFix` | each COOPLOC_ESTIMATE: latitude/longitude about the origin, covariance ENU (m^2), heading |
//! | `/vehicle_<id>/truth` | `foxglove.LocationFix` | each SIM_STATE of a simulated vehicle |
//! | `/vehicle_<id>/error` | JSON (`t_s`, `horizontal_m`, `nees`) | error of an estimate against the truth |
//! | `/vehicle_<id>/estimate` | JSON (time, epoch, NED position, yaw, NIS, 95% ellipse) | each COOPLOC_ESTIMATE |
//! | `/team/scene` | `foxglove.SceneUpdate` | estimates (sphere), 95% ellipses (flat cylinder), truth (cube), labels, in frame `map` (x east, y north, z up, about the origin) |
//!
//! Log time and message timestamps are the receive time (the vehicle time is in the JSON and in
//! the LocationFix metadata as `vehicle_time_us`). Channels are created when a vehicle is first
//! heard, and the server advertises them to connected clients then.

use std::collections::BTreeMap;
use std::sync::Arc;

use foxglove::messages::{
    Color, CubePrimitive, CylinderPrimitive, KeyValuePair, LocationFix, Pose, Quaternion, SceneEntity, SceneUpdate,
    SpherePrimitive, TextPrimitive, Timestamp, Vector3 as FoxVector3, location_fix::PositionCovarianceType,
};
use foxglove::{Channel, Context, RawChannel, Schema};
use nalgebra::{Matrix3, Vector3};

use super::state::Ellipse95;
use super::{GcsEvent, GcsSink, TruthPoint, WallNs};
use crate::estimation::PlatformId;
use crate::protocol::wire::{self, EstimateReport, GeoOrigin};

/// Vehicle colours, shared with the web page (by platform id).
pub const PALETTE: [(u8, u8, u8); 8] = [
    (0x1f, 0x77, 0xb4),
    (0xd6, 0x27, 0x28),
    (0x2c, 0xa0, 0x2c),
    (0x94, 0x67, 0xbd),
    (0xff, 0x7f, 0x0e),
    (0x17, 0xbe, 0xcf),
    (0x8c, 0x56, 0x4b),
    (0xe3, 0x77, 0xc2),
];

fn color(id: PlatformId, a: f64) -> Color {
    let (r, g, b) = PALETTE[(usize::from(id).wrapping_sub(1)) % PALETTE.len()];
    Color { r: f64::from(r) / 255.0, g: f64::from(g) / 255.0, b: f64::from(b) / 255.0, a }
}

fn timestamp(rx: WallNs) -> Timestamp {
    Timestamp::new((rx.0 / 1_000_000_000).min(u64::from(u32::MAX)) as u32, (rx.0 % 1_000_000_000) as u32)
}

/// NED covariance as ENU, row major (LocationFix's convention).
pub fn ned_cov_to_enu(c: &Matrix3<f64>) -> [f64; 9] {
    // ENU = T NED with T = [[0,1,0],[1,0,0],[0,0,-1]].
    let t = Matrix3::new(0.0, 1.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, -1.0);
    let e = t * c * t.transpose();
    [e[(0, 0)], e[(0, 1)], e[(0, 2)], e[(1, 0)], e[(1, 1)], e[(1, 2)], e[(2, 0)], e[(2, 1)], e[(2, 2)]]
}

fn enu(p: &Vector3<f64>) -> FoxVector3 {
    FoxVector3 { x: p[1], y: p[0], z: -p[2] }
}

fn yaw_quat(angle_from_x_ccw_rad: f64) -> Quaternion {
    let h = 0.5 * angle_from_x_ccw_rad;
    Quaternion { x: 0.0, y: 0.0, z: h.sin(), w: h.cos() }
}

/// The LocationFix of an estimate.
pub fn estimate_location(origin: &GeoOrigin, rx: WallNs, r: &EstimateReport) -> LocationFix {
    let g = wire::ned_to_geodetic(origin, &r.position_ned_m);
    let v = &r.velocity_ned_m_s;
    LocationFix {
        timestamp: Some(timestamp(rx)),
        frame_id: format!("vehicle_{}", r.platform),
        latitude: g.lat_deg,
        longitude: g.lon_deg,
        altitude: g.alt_m,
        position_covariance: ned_cov_to_enu(&r.position_covariance_m2).to_vec(),
        position_covariance_type: PositionCovarianceType::Known as i32,
        heading: Some(r.yaw_rad),
        velocity: Some(FoxVector3 { x: v[1], y: v[0], z: -v[2] }),
        color: Some(color(r.platform, 1.0)),
        metadata: vec![KeyValuePair { key: "vehicle_time_us".into(), value: r.t.0.to_string() }],
    }
}

fn truth_location(origin: &GeoOrigin, vehicle: PlatformId, p: &TruthPoint) -> LocationFix {
    let g = wire::ned_to_geodetic(origin, &p.pos_ned_m);
    let v = &p.vel_ned_m_s;
    LocationFix {
        timestamp: Some(timestamp(p.rx)),
        frame_id: format!("vehicle_{vehicle}_truth"),
        latitude: g.lat_deg,
        longitude: g.lon_deg,
        altitude: g.alt_m,
        position_covariance: vec![0.0; 9],
        position_covariance_type: PositionCovarianceType::Unknown as i32,
        heading: Some(p.yaw_rad),
        velocity: Some(FoxVector3 { x: v[1], y: v[0], z: -v[2] }),
        color: Some(Color { a: 0.5, ..color(vehicle, 1.0) }),
        metadata: p.t.map(|t| KeyValuePair { key: "vehicle_time_us".into(), value: t.0.to_string() }).into_iter().collect(),
    }
}

fn estimate_entities(rx: WallNs, r: &EstimateReport, ellipse: Option<Ellipse95>) -> Vec<SceneEntity> {
    let id = r.platform;
    let pos = enu(&r.position_ned_m);
    let entity = |name: &str| SceneEntity {
        timestamp: Some(timestamp(rx)),
        frame_id: "map".into(),
        id: format!("vehicle_{id}/{name}"),
        ..Default::default()
    };
    let mut marker = entity("estimate");
    marker.spheres.push(SpherePrimitive {
        pose: Some(Pose { position: Some(pos), orientation: Some(yaw_quat(0.0)) }),
        size: Some(FoxVector3 { x: 4.0, y: 4.0, z: 4.0 }),
        color: Some(color(id, 1.0)),
    });
    marker.texts.push(TextPrimitive {
        pose: Some(Pose { position: Some(FoxVector3 { z: pos.z + 8.0, ..pos }), orientation: Some(yaw_quat(0.0)) }),
        billboard: true,
        font_size: 14.0,
        scale_invariant: true,
        color: Some(color(id, 1.0)),
        text: format!("vehicle {id}"),
    });
    let mut out = vec![marker];
    if let Some(e) = ellipse {
        let mut ell = entity("ellipse95");
        // The major axis is `bearing` from north towards east: (pi/2 - bearing) from east (x).
        let angle = std::f64::consts::FRAC_PI_2 - e.major_bearing_deg.to_radians();
        ell.cylinders.push(CylinderPrimitive {
            pose: Some(Pose { position: Some(pos), orientation: Some(yaw_quat(angle)) }),
            size: Some(FoxVector3 { x: 2.0 * e.semi_major_m, y: 2.0 * e.semi_minor_m.max(0.01), z: 0.2 }),
            bottom_scale: 1.0,
            top_scale: 1.0,
            color: Some(color(id, 0.3)),
        });
        out.push(ell);
    }
    out
}

fn truth_entity(vehicle: PlatformId, p: &TruthPoint) -> SceneEntity {
    SceneEntity {
        timestamp: Some(timestamp(p.rx)),
        frame_id: "map".into(),
        id: format!("vehicle_{vehicle}/truth"),
        cubes: vec![CubePrimitive {
            pose: Some(Pose { position: Some(enu(&p.pos_ned_m)), orientation: Some(yaw_quat(0.0)) }),
            size: Some(FoxVector3 { x: 3.0, y: 3.0, z: 3.0 }),
            color: Some(Color { r: 0.15, g: 0.15, b: 0.15, a: 0.8 }),
        }],
        ..Default::default()
    }
}

struct VehicleChannels {
    location: Channel<LocationFix>,
    truth: Channel<LocationFix>,
    estimate: Arc<RawChannel>,
    error: Arc<RawChannel>,
}

const ESTIMATE_SCHEMA: &str = r#"{"type":"object","properties":{"vehicle":{"type":"integer"},"t_s":{"type":"number"},"epoch":{"type":"integer"},"north_m":{"type":"number"},"east_m":{"type":"number"},"down_m":{"type":"number"},"yaw_deg":{"type":"number"},"nis":{"type":["number","null"]},"participants":{"type":"integer"},"ranges":{"type":"integer"},"semi_major_95_m":{"type":["number","null"]},"semi_minor_95_m":{"type":["number","null"]}}}"#;
const ERROR_SCHEMA: &str = r#"{"type":"object","properties":{"vehicle":{"type":"integer"},"t_s":{"type":"number"},"horizontal_m":{"type":"number"},"nees":{"type":["number","null"]}}}"#;

fn json_channel(ctx: &Arc<Context>, topic: String, name: &str, schema: &'static str) -> Option<Arc<RawChannel>> {
    let channel = ctx
        .channel_builder(topic)
        .message_encoding("json")
        .schema(Schema::new(name, "jsonschema", schema.as_bytes()))
        .build_raw();
    match channel {
        Ok(c) => Some(c),
        Err(e) => {
            tracing::warn!(error = %e, "foxglove channel not created");
            None
        }
    }
}

/// Publishes [`GcsEvent`]s on a Foxglove [`Context`] (served by a `WebSocketServer` on the same
/// context; an MCAP writer on it would record the same channels).
pub struct FoxglovePublisher {
    ctx: Arc<Context>,
    origin: GeoOrigin,
    vehicles: BTreeMap<PlatformId, VehicleChannels>,
    scene: Channel<SceneUpdate>,
}

impl FoxglovePublisher {
    pub fn new(ctx: Arc<Context>, origin: GeoOrigin) -> Self {
        let scene = ctx.channel_builder("/team/scene").build::<SceneUpdate>();
        FoxglovePublisher { ctx, origin, vehicles: BTreeMap::new(), scene }
    }

    pub fn context(&self) -> &Arc<Context> {
        &self.ctx
    }

    fn channels(&mut self, id: PlatformId) -> Option<&VehicleChannels> {
        if !self.vehicles.contains_key(&id) {
            let ctx = &self.ctx;
            let channels = VehicleChannels {
                location: ctx.channel_builder(format!("/vehicle_{id}/location")).build::<LocationFix>(),
                truth: ctx.channel_builder(format!("/vehicle_{id}/truth")).build::<LocationFix>(),
                estimate: json_channel(ctx, format!("/vehicle_{id}/estimate"), "cooploc.Estimate", ESTIMATE_SCHEMA)?,
                error: json_channel(ctx, format!("/vehicle_{id}/error"), "cooploc.TruthError", ERROR_SCHEMA)?,
            };
            self.vehicles.insert(id, channels);
        }
        self.vehicles.get(&id)
    }
}

fn finite_or_null(v: f64) -> serde_json::Value {
    if v.is_finite() { serde_json::json!(v) } else { serde_json::Value::Null }
}

impl GcsSink for FoxglovePublisher {
    fn on_event(&mut self, event: &GcsEvent) {
        match event {
            GcsEvent::Estimate { rx, vehicle, report, ellipse } => {
                let origin = self.origin;
                let Some(ch) = self.channels(*vehicle) else { return };
                ch.location.log_with_time(&estimate_location(&origin, *rx, report), rx.0);
                let p = &report.position_ned_m;
                let json = serde_json::json!({
                    "vehicle": vehicle,
                    "t_s": report.t.as_secs_f64(),
                    "epoch": report.epoch,
                    "north_m": p[0], "east_m": p[1], "down_m": p[2],
                    "yaw_deg": report.yaw_rad.to_degrees(),
                    "nis": finite_or_null(report.nis),
                    "participants": report.participants,
                    "ranges": report.ranges,
                    "semi_major_95_m": ellipse.map(|e| e.semi_major_m),
                    "semi_minor_95_m": ellipse.map(|e| e.semi_minor_m),
                });
                ch.estimate.log_with_meta(json.to_string().as_bytes(), foxglove::PartialMetadata::with_log_time(rx.0));
                let update = SceneUpdate { deletions: vec![], entities: estimate_entities(*rx, report, *ellipse) };
                self.scene.log_with_time(&update, rx.0);
            }
            GcsEvent::Truth { rx, vehicle, point } => {
                let origin = self.origin;
                let Some(ch) = self.channels(*vehicle) else { return };
                ch.truth.log_with_time(&truth_location(&origin, *vehicle, point), rx.0);
                let update = SceneUpdate { deletions: vec![], entities: vec![truth_entity(*vehicle, point)] };
                self.scene.log_with_time(&update, rx.0);
            }
            GcsEvent::Error { rx, vehicle, t, error } => {
                let Some(ch) = self.channels(*vehicle) else { return };
                let json = serde_json::json!({
                    "vehicle": vehicle,
                    "t_s": t.as_secs_f64(),
                    "horizontal_m": error.horizontal_m,
                    "nees": error.nees,
                });
                ch.error.log_with_meta(json.to_string().as_bytes(), foxglove::PartialMetadata::with_log_time(rx.0));
            }
            _ => {}
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn covariance_goes_to_enu() {
        // NN 4, NE 1, ND 0.5, EE 9, ED -2, DD 16.
        let c = Matrix3::new(4.0, 1.0, 0.5, 1.0, 9.0, -2.0, 0.5, -2.0, 16.0);
        let e = ned_cov_to_enu(&c);
        // EE, EN, E(-D); NE, NN, N(-D); ...
        assert_eq!(e, [9.0, 1.0, 2.0, 1.0, 4.0, -0.5, 2.0, -0.5, 16.0]);
    }
}
