//! The ground station's MCAP recording: a [`GcsSink`] that writes what the station receives on
//! the cooperative network (raw frames, `/coop/255/rx`) and the truth it sees.

use super::{GCS_SYSID, GcsEvent, GcsSink};
use crate::recording::{Direction, Link as LogLink, TruthSample};

/// Records what the ground station receives on the cooperative network and the truth it sees.
pub struct RecorderSink(pub crate::node::runner::SharedRecorder);

impl GcsSink for RecorderSink {
    fn on_event(&mut self, event: &GcsEvent) {
        let Ok(mut r) = self.0.lock() else { return };
        match event {
            GcsEvent::Frame { rx, link: super::Link::Coop, bytes, .. } => {
                let _ = r.frame(LogLink::Coop(GCS_SYSID), Direction::Rx, rx.0, bytes);
            }
            GcsEvent::Truth { rx, vehicle, point } => {
                if let Some(t) = point.t {
                    let _ = r.truth(*vehicle, rx.0, &TruthSample { t, pos_ned_m: point.pos_ned_m, yaw_rad: Some(point.yaw_rad) });
                }
            }
            _ => {}
        }
        let _ = r.maybe_flush(std::time::Instant::now());
    }
}
