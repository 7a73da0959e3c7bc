//! The ground station's MCAP recording: a [`GcsSink`] that writes what the station receives on
//! the cooperative network (raw frames, `/coop/255/rx`), the truth it sees, and the same
//! Foxglove channels its live server publishes ([`super::foxglove_live`]): each estimate's
//! location, pose and ellipse, its JSON view, its error against the truth, and the team's
//! health, built by the same functions ([`crate::view::foxglove`]).

use super::{GCS_SYSID, GcsEvent, GcsSink};
use crate::recording::{Direction, Link as LogLink, TruthSample, topics};
use crate::view::foxglove::{self as fx, ErrorJson, EstimateJson};

/// Records what the ground station receives on the cooperative network and what it shows.
pub struct RecorderSink {
    recorder: crate::recording::SharedRecorder,
    /// Also the estimates' location, pose and ellipse (off when the nodes write theirs into the
    /// same log, as in `cooploc demo`).
    estimate_views: bool,
}

impl RecorderSink {
    /// The ground station's own log: everything it receives and shows.
    pub fn new(recorder: crate::recording::SharedRecorder) -> Self {
        RecorderSink { recorder, estimate_views: true }
    }

    /// A log the nodes write too (their estimates' location, pose and ellipse): the station adds
    /// its frames, the truth, the estimates' JSON, the errors and the health.
    pub fn beside_nodes(recorder: crate::recording::SharedRecorder) -> Self {
        RecorderSink { recorder, estimate_views: false }
    }
}

impl GcsSink for RecorderSink {
    fn on_event(&mut self, event: &GcsEvent) {
        let Ok(mut r) = self.recorder.lock() else { return };
        // A refused message is counted by the recorder (its stats); the station goes on.
        let _ = match event {
            GcsEvent::Frame { rx, link: super::Link::Coop, bytes, .. } => {
                r.frame(LogLink::Coop(GCS_SYSID), Direction::Rx, rx.0, bytes)
            }
            GcsEvent::Truth { rx, vehicle, point } => match point.t {
                Some(t) => r.truth(*vehicle, rx.0, &TruthSample { t, pos_ned_m: point.pos_ned_m, yaw_rad: Some(point.yaw_rad) }),
                None => Ok(()),
            },
            GcsEvent::Estimate { rx, vehicle, report, ellipse } => {
                let views = if self.estimate_views { r.estimate(*vehicle, rx.0, &fx::position_estimate(report)) } else { Ok(()) };
                views.and_then(|()| {
                    let json = EstimateJson::of(report, ellipse.as_ref());
                    r.json_message(&topics::estimate(*vehicle), fx::ESTIMATE_SCHEMA_NAME, fx::ESTIMATE_SCHEMA, rx.0, &json)
                })
            }
            GcsEvent::Error { rx, vehicle, t, error } => {
                let json =
                    ErrorJson { vehicle: *vehicle, t_s: t.as_secs_f64(), horizontal_m: error.horizontal_m, nees: error.nees };
                r.json_message(&topics::error(*vehicle), fx::ERROR_SCHEMA_NAME, fx::ERROR_SCHEMA, rx.0, &json)
            }
            GcsEvent::Health { rx, health } => {
                r.json_message(topics::HEALTH, fx::HEALTH_SCHEMA_NAME, fx::HEALTH_SCHEMA, rx.0, health.as_ref())
            }
            _ => Ok(()),
        };
        let _ = r.maybe_flush(std::time::Instant::now());
    }
}
