//! `cooploc gcs`: the ground station of the cooperative network.
//!
//! A MAVLink system (sysid 255, compid 190 MAV_COMP_ID_MISSIONPLANNER, HEARTBEAT as
//! MAV_TYPE_GCS / MAV_AUTOPILOT_INVALID at 1 Hz) that listens to the nodes on the cooperative
//! network (every COOPLOC_ESTIMATE, COOPLOC_RANGE, COOPLOC_STATE_FRAGMENT, COOPLOC_EPOCH and
//! HEARTBEAT they send to their peers) and, for simulated vehicles, to the vehicles' own links
//! (SIM_STATE as truth), and shows the team:
//!
//! - [`state`]: the sans-io core, [`state::GcsState`]: bytes and receive times in, per-vehicle
//!   tracks (estimates, 95% ellipses, truth, error against truth, NEES), per-source link
//!   statistics and [`GcsEvent`]s out. No sockets, no clock.
//! - [`link`]: link statistics (sequence-gap loss, byte rate over a sliding window).
//! - [`http`]: the web page (`GET /`) and its JSON (`GET /api/state`).
//! - [`foxglove_live`]: the Foxglove live WebSocket server (the log's channels, built by
//!   [`crate::view`]).
//! - [`log`]: the station's MCAP log ([`RecorderSink`]), with the same channels.
//! - [`runner`]: the tokio runner that owns the sockets and the timers and hands every
//!   [`GcsEvent`] to each [`GcsSink`] (the Foxglove server, the log).

pub mod foxglove_live;
pub mod http;
pub mod link;
pub mod log;
pub mod runner;
pub mod state;
pub mod truth;

use std::net::SocketAddr;

use nalgebra::Vector3;

use crate::estimation::PlatformId;
use crate::estimation::RangeSample;
use crate::protocol::wire::{EpochAnnouncement, EstimateReport};
use crate::time::TimeUs;
pub use link::Link;
pub use log::RecorderSink;
use state::{Ellipse95, TruthError};

/// MAVLink system id of the ground station (254 when another GCS already uses 255).
pub const GCS_SYSID: u8 = 255;
/// MAV_COMP_ID_MISSIONPLANNER.
pub const GCS_COMPID: u8 = 190;

/// Receive time: nanoseconds since the Unix epoch, from a monotonic clock anchored once to the
/// system clock at start (so it never goes backwards). Vehicle time is a [`TimeUs`].
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord, Hash, Default)]
pub struct WallNs(pub u64);

impl WallNs {
    pub fn as_secs_f64(self) -> f64 {
        self.0 as f64 * 1e-9
    }
}

/// A truth sample of a simulated vehicle (SIM_STATE), in the team's local NED frame.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct TruthPoint {
    /// Vehicle time. SIM_STATE carries none: it is the time of the next timed frame of the same
    /// link (see [`state`]); `None` when the link has no timed frames.
    pub t: Option<TimeUs>,
    pub rx: WallNs,
    pub pos_ned_m: Vector3<f64>,
    pub vel_ned_m_s: Vector3<f64>,
    pub yaw_rad: f64,
}

/// Every update the ground station decodes, produced once by [`state::GcsState`] and handed to
/// every sink (the Foxglove server, a recorder).
#[derive(Debug, Clone, PartialEq)]
pub enum GcsEvent {
    /// A valid MAVLink frame, as received (raw bytes, for a raw-frame log).
    Frame { rx: WallNs, link: Link, from: Option<SocketAddr>, sysid: u32, compid: u8, message_id: u32, bytes: Vec<u8> },
    /// A node's estimate (COOPLOC_ESTIMATE) with its 95% horizontal ellipse.
    Estimate { rx: WallNs, vehicle: PlatformId, report: EstimateReport, ellipse: Option<Ellipse95> },
    /// A truth sample of a simulated vehicle.
    Truth { rx: WallNs, vehicle: PlatformId, point: TruthPoint },
    /// The error of an estimate against the truth interpolated at its time (known once the truth
    /// has covered that time, so it may come after later estimates).
    Error { rx: WallNs, vehicle: PlatformId, t: TimeUs, error: TruthError },
    /// A range a node forwarded (COOPLOC_RANGE).
    Range { rx: WallNs, epoch: u32, range: RangeSample },
    /// An epoch announcement (COOPLOC_EPOCH).
    Epoch { rx: WallNs, announcement: EpochAnnouncement },
    /// The team's health, once a second (the runner's timer; see [`state::GcsState::health`]).
    Health { rx: WallNs, health: Box<crate::view::health::HealthView> },
    /// A frame that was dropped: no valid MAVLink in a datagram, or a message that failed
    /// validation (reason names the field).
    Rejected { rx: WallNs, link: Link, reason: String },
}

/// A consumer of [`GcsEvent`]s (the Foxglove server; the MCAP recorder).
pub trait GcsSink: Send {
    fn on_event(&mut self, event: &GcsEvent);
}
