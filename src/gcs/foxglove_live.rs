//! The ground station's updates on Foxglove's live WebSocket protocol (the official `foxglove`
//! crate's server, subprotocol `foxglove.sdk.v1` / `foxglove.sdk.v1.1`).
//!
//! The channels are those of an MCAP log ([`crate::recording`]), with the same topics and the
//! same messages, built by the same functions ([`crate::view::foxglove`]), so that a live
//! session and a recorded one look the same in Foxglove (and `tools/foxglove/cooploc-layout.json`
//! fits both):
//!
//! | topic | schema | from |
//! |---|---|---|
//! | `/vehicle_<id>/location` | `foxglove.LocationFix` | each COOPLOC_ESTIMATE: latitude/longitude about the origin, covariance ENU (m^2), heading |
//! | `/vehicle_<id>/pose` | `foxglove.PoseInFrame` | each COOPLOC_ESTIMATE, frame `ned` |
//! | `/vehicle_<id>/ellipse` | `foxglove.SceneUpdate` | its 95 % horizontal ellipse and name, frame `ned` |
//! | `/vehicle_<id>/truth`, `/vehicle_<id>/truth_pose` | `foxglove.LocationFix`, `foxglove.PoseInFrame` | each timed SIM_STATE of a simulated vehicle |
//! | `/vehicle_<id>/estimate` | JSON `cooploc.Estimate` | time, epoch, method, NED position, yaw, NIS, 95 % ellipse |
//! | `/vehicle_<id>/error` | JSON `cooploc.TruthError` | error of an estimate against the truth, NEES |
//! | `/team/health` | JSON `cooploc.TeamHealth` | once a second: disagreements, heals, per node rate, bytes against the budget, loss, signing |
//! | `/tf` | `foxglove.FrameTransform` | `world` (ENU) -> `ned`, with the first message and then once a second |
//!
//! Log time and message timestamps are the receive time (the vehicle time is in the JSON and in
//! the metadata as `t_us`). Channels are created when first used, and the server advertises
//! them to connected clients then. Truth without a vehicle time (a link with no timed frames)
//! is shown on the page only.

use std::collections::BTreeMap;
use std::sync::Arc;

use foxglove::messages::{FrameTransform, LocationFix, PoseInFrame, SceneUpdate};
use foxglove::{Channel, Context, RawChannel, Schema};

use super::{GcsEvent, GcsSink, WallNs};
use crate::protocol::wire::GeoOrigin;
use crate::recording::{TruthSample, topics};
use crate::view::foxglove::{self as fx, ErrorJson, EstimateJson};

/// A wall-clock interval of the `/tf` republication, ns.
const TF_EVERY_NS: u64 = 1_000_000_000;

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

/// One channel per topic, created on first use.
#[derive(Default)]
struct Channels {
    locations: BTreeMap<String, Channel<LocationFix>>,
    poses: BTreeMap<String, Channel<PoseInFrame>>,
    scenes: BTreeMap<String, Channel<SceneUpdate>>,
    json: BTreeMap<String, Arc<RawChannel>>,
}

/// Publishes [`GcsEvent`]s on a Foxglove [`Context`] (served by a `WebSocketServer` on the same
/// context).
pub struct FoxglovePublisher {
    ctx: Arc<Context>,
    origin: GeoOrigin,
    channels: Channels,
    tf: Channel<FrameTransform>,
    last_tf: Option<u64>,
}

impl FoxglovePublisher {
    pub fn new(ctx: Arc<Context>, origin: GeoOrigin) -> Self {
        let tf = ctx.channel_builder(topics::TF).build::<FrameTransform>();
        FoxglovePublisher { ctx, origin, channels: Channels::default(), tf, last_tf: None }
    }

    pub fn context(&self) -> &Arc<Context> {
        &self.ctx
    }

    fn location(&mut self, topic: String, msg: &LocationFix, rx: WallNs) {
        let ctx = &self.ctx;
        self.channels
            .locations
            .entry(topic.clone())
            .or_insert_with(|| ctx.channel_builder(topic).build())
            .log_with_time(msg, rx.0);
    }

    fn pose(&mut self, topic: String, msg: &PoseInFrame, rx: WallNs) {
        let ctx = &self.ctx;
        self.channels.poses.entry(topic.clone()).or_insert_with(|| ctx.channel_builder(topic).build()).log_with_time(msg, rx.0);
    }

    fn scene(&mut self, topic: String, msg: &SceneUpdate, rx: WallNs) {
        let ctx = &self.ctx;
        self.channels.scenes.entry(topic.clone()).or_insert_with(|| ctx.channel_builder(topic).build()).log_with_time(msg, rx.0);
    }

    fn json<T: serde::Serialize>(&mut self, topic: String, name: &str, schema: &'static str, value: &T, rx: WallNs) {
        let channel = match self.channels.json.get(&topic) {
            Some(c) => c.clone(),
            None => {
                let Some(c) = json_channel(&self.ctx, topic.clone(), name, schema) else { return };
                self.channels.json.insert(topic, c.clone());
                c
            }
        };
        match serde_json::to_vec(value) {
            Ok(bytes) => channel.log_with_meta(&bytes, foxglove::PartialMetadata::with_log_time(rx.0)),
            Err(e) => tracing::warn!(error = %e, "foxglove message not encoded"),
        }
    }

    /// The `world` -> `ned` transform, with the first message and once a second after.
    fn maybe_tf(&mut self, rx: WallNs) {
        if self.last_tf.is_none_or(|t| rx.0.saturating_sub(t) >= TF_EVERY_NS) {
            self.tf.log_with_time(&fx::world_to_ned(rx.0), rx.0);
            self.last_tf = Some(rx.0);
        }
    }
}

impl GcsSink for FoxglovePublisher {
    fn on_event(&mut self, event: &GcsEvent) {
        match event {
            GcsEvent::Estimate { rx, vehicle, report, ellipse } => {
                let est = fx::position_estimate(report);
                if est.non_finite_field().is_some() {
                    return; // validated on the wire; kept as the recorder does
                }
                self.maybe_tf(*rx);
                let id = *vehicle;
                let origin = self.origin;
                self.location(topics::location(id), &fx::location_fix(&origin, id, &est, rx.0), *rx);
                self.pose(topics::pose(id), &fx::pose_in_ned(&est.pos_ned_m, est.yaw_rad, rx.0), *rx);
                self.scene(topics::ellipse(id), &fx::ellipse_update(id, &est, rx.0), *rx);
                let json = EstimateJson::of(report, ellipse.as_ref());
                self.json(topics::estimate(id), fx::ESTIMATE_SCHEMA_NAME, fx::ESTIMATE_SCHEMA, &json, *rx);
            }
            GcsEvent::Truth { rx, vehicle, point } => {
                let Some(t) = point.t else { return };
                let truth = TruthSample { t, pos_ned_m: point.pos_ned_m, yaw_rad: Some(point.yaw_rad) };
                self.maybe_tf(*rx);
                let origin = self.origin;
                self.location(topics::truth(*vehicle), &fx::truth_fix(&origin, *vehicle, &truth, rx.0), *rx);
                self.pose(topics::truth_pose(*vehicle), &fx::pose_in_ned(&truth.pos_ned_m, truth.yaw_rad, rx.0), *rx);
            }
            GcsEvent::Error { rx, vehicle, t, error } => {
                let json =
                    ErrorJson { vehicle: *vehicle, t_s: t.as_secs_f64(), horizontal_m: error.horizontal_m, nees: error.nees };
                self.json(topics::error(*vehicle), fx::ERROR_SCHEMA_NAME, fx::ERROR_SCHEMA, &json, *rx);
            }
            GcsEvent::Health { rx, health } => {
                self.json(topics::HEALTH.to_string(), fx::HEALTH_SCHEMA_NAME, fx::HEALTH_SCHEMA, health.as_ref(), *rx);
            }
            GcsEvent::Frame { .. } | GcsEvent::Range { .. } | GcsEvent::Epoch { .. } | GcsEvent::Rejected { .. } => {}
        }
    }
}
