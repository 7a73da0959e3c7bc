//! MCAP logs: what a cooploc process records, and how to read it back.
//!
//! Every process (a node, the ground station) can record each MAVLink frame it sends or
//! receives, its decoded estimates and its filter internals into one [MCAP](https://mcap.dev)
//! file. The file opens in [Foxglove](https://foxglove.dev) (map, 3-D and plot panels), and the
//! replay and the tests read it back with [`LogReader`] / [`read_log`].
//!
//! - [`Recorder`] (writer): zstd-compressed chunks, indexed, with a summary written by
//!   [`Recorder::finish`]. It closes the current chunk and flushes the file at least every
//!   [`RecorderOptions::flush_interval`] (1 s) of wall time, checked on every write; a runner
//!   also calls [`Recorder::maybe_flush`] from a timer so that quiet periods are flushed too. A
//!   process killed with SIGKILL therefore leaves a file readable up to its last flush. A write
//!   error never panics: the recorder turns *failed*, logs it once (tracing) and counts what it
//!   drops.
//! - [`LogReader`] / [`read_log`] (reader): every message in file order, optionally for some
//!   topics only, plus metadata and attachments, tolerant of a truncated or damaged file (it
//!   yields everything before the damage, then one [`ReadError::Truncated`] or
//!   [`ReadError::Corrupt`] that says how far it got). [`read_index`] reads the summary
//!   (channels, counts, metadata, attachments) without scanning the messages and says
//!   [`ReadError::NoSummary`] when the writer never finished (killed).
//!
//! # Channels
//!
//! `<sysid>` is the MAVLink system id of the recording process (a node: its vehicle's; the
//! ground station: 255). `<id>` is a vehicle's platform id (its system id). All times are wall
//! clock nanoseconds since the UNIX epoch: `log_time` is when the process received, sent or
//! computed the data, and `publish_time` is the same value. Filter time (`t_us`, the vehicle's
//! clock) is inside the payloads where it matters.
//!
//! | topic | message encoding | schema (encoding) | one message is |
//! |---|---|---|---|
//! | `/vehicle_<sysid>/mavlink/rx`, `/vehicle_<sysid>/mavlink/tx` | `mavlink.frame` | none (id 0) | one MAVLink frame on the vehicle link |
//! | `/coop/<sysid>/rx`, `/coop/<sysid>/tx` | `mavlink.frame` | none (id 0) | one MAVLink frame on the cooperative network |
//! | `/vehicle_<id>/location` | `protobuf` | `foxglove.LocationFix` (`protobuf`) | estimate: lat/lon/alt, ENU covariance (KNOWN) |
//! | `/vehicle_<id>/pose` | `protobuf` | `foxglove.PoseInFrame` (`protobuf`) | estimate: NED position and yaw in frame `ned` |
//! | `/vehicle_<id>/ellipse` | `protobuf` | `foxglove.SceneUpdate` (`protobuf`) | 95 % horizontal position ellipse in frame `ned` |
//! | `/vehicle_<id>/truth` | `protobuf` | `foxglove.LocationFix` (`protobuf`) | truth (simulation): lat/lon/alt |
//! | `/vehicle_<id>/truth_pose` | `protobuf` | `foxglove.PoseInFrame` (`protobuf`) | truth: NED position and yaw in frame `ned` |
//! | `/tf` | `protobuf` | `foxglove.FrameTransform` (`protobuf`) | the fixed transform `world` (ENU, z up) -> `ned` |
//! | `/vehicle_<id>/internals` | `json` | `cooploc.CoopUpdate` (`jsonschema`) | one cooperative update: [`crate::node::log::CoopUpdateRecord`] |
//! | `/links/stats` | `json` | `cooploc.LinkStats` (`jsonschema`) | per-peer packet counts, loss, rates: [`LinkStatsRecord`] |
//!
//! **`mavlink.frame`** (an encoding of our own; MCAP has no registered MAVLink encoding): the
//! message data is exactly one complete MAVLink v1 (`0xFE`) or v2 (`0xFD`) frame as it was on
//! the wire, signature included when present; the recorder refuses anything else. The channel
//! metadata is `{"link": "<url or socket address>", "dialect": "cooploc", "direction": "rx"|"tx"}`.
//! Frames are recorded before they are parsed, so frames of unknown messages are kept too.
//!
//! **Foxglove channels** carry the well-known schemas of the `foxglove` crate (protobuf, with
//! their `FileDescriptorSet` as the schema data), so Foxglove's map panel shows the
//! `LocationFix`es and its 3-D panel (display frame `world`) the poses and ellipses. Positions
//! become latitude/longitude about the [`GeoOrigin`] given in [`RecorderOptions::geo_origin`]
//! with the project's flat-Earth conversion ([`crate::protocol::wire::ned_to_geodetic`]); with
//! no origin no `location` messages are written. The `/tf` transform is written again in every
//! flushed chunk, so a reader that starts anywhere finds it.
//!
//! **JSON channels** carry the serde structs of [`internals`] (each with a JSON schema), which
//! the ground station and the replay deserialize as they are.
//!
//! **Metadata and attachments**: [`Recorder::new`] writes a metadata record `cooploc` with
//! `{"format_version", "crate_version"}`; processes add theirs with [`Recorder::metadata`]
//! (e.g. the configuration) and [`Recorder::attachment`] (e.g. the scenario TOML).
//!
//! The same description, for people, is in `logs/README.md`.

pub mod internals;
mod reader;
pub mod series;
mod writer;

pub use crate::view::foxglove::{PositionEstimate, TruthSample};
pub use internals::{LinkStatsRecord, PeerLinkStats, record_update};

/// A recorder shared by the processes of one log (the demo puts every node and the ground station
/// in one file).
pub type SharedRecorder = std::sync::Arc<std::sync::Mutex<Recorder>>;
pub use reader::{
    ChannelInfo, Log, LogEnd, LogIndex, LogReader, LoggedAttachment, LoggedMessage, LoggedMetadata, ReadError, ReadOptions,
    SchemaInfo, read_index, read_log, read_log_from,
};
pub use writer::{Recorder, RecorderError, RecorderOptions, RecorderStats};

pub use crate::protocol::wire::GeoOrigin;

/// Version of the log layout described above; stored in the `cooploc` metadata record.
pub const FORMAT_VERSION: u32 = 1;
/// Message encoding of the raw frame channels.
pub const MAVLINK_FRAME_ENCODING: &str = "mavlink.frame";
/// Dialect named in the raw frame channels' metadata.
pub const DIALECT: &str = "cooploc";
/// Name of the metadata record the recorder writes first.
pub const LOG_METADATA_NAME: &str = "cooploc";

pub use crate::protocol::framing::{Direction, Link};

/// The topic names of the log, in one place.
pub mod topics {
    use super::{Direction, Link};

    /// The fixed `world` -> `ned` transform.
    pub const TF: &str = "/tf";
    /// Link statistics of the recording process.
    pub const LINK_STATS: &str = "/links/stats";

    /// `/vehicle_<sysid>/mavlink/{rx,tx}` or `/coop/<sysid>/{rx,tx}`.
    pub fn frames(link: Link, dir: Direction) -> String {
        match link {
            Link::Vehicle(sysid) => format!("/vehicle_{sysid}/mavlink/{}", dir.as_str()),
            Link::Coop(sysid) => format!("/coop/{sysid}/{}", dir.as_str()),
        }
    }
    /// `/vehicle_<id>/location`: the estimate as a `foxglove.LocationFix`.
    pub fn location(id: u16) -> String {
        format!("/vehicle_{id}/location")
    }
    /// `/vehicle_<id>/pose`: the estimate as a `foxglove.PoseInFrame`.
    pub fn pose(id: u16) -> String {
        format!("/vehicle_{id}/pose")
    }
    /// `/vehicle_<id>/ellipse`: the 95 % position ellipse as a `foxglove.SceneUpdate`.
    pub fn ellipse(id: u16) -> String {
        format!("/vehicle_{id}/ellipse")
    }
    /// `/vehicle_<id>/truth`: the true position as a `foxglove.LocationFix`.
    pub fn truth(id: u16) -> String {
        format!("/vehicle_{id}/truth")
    }
    /// `/vehicle_<id>/truth_pose`: the true pose as a `foxglove.PoseInFrame`.
    pub fn truth_pose(id: u16) -> String {
        format!("/vehicle_{id}/truth_pose")
    }
    /// `/vehicle_<id>/estimate`: the ground station's JSON view of each estimate
    /// ([`crate::view::foxglove::EstimateJson`]).
    pub fn estimate(id: u16) -> String {
        format!("/vehicle_{id}/estimate")
    }
    /// `/vehicle_<id>/error`: the error of an estimate against the truth
    /// ([`crate::view::foxglove::ErrorJson`]).
    pub fn error(id: u16) -> String {
        format!("/vehicle_{id}/error")
    }
    /// The team's health, once a second ([`crate::view::health::HealthView`]).
    pub const HEALTH: &str = "/team/health";
    /// `/vehicle_<id>/internals`: one JSON [`crate::node::log::CoopUpdateRecord`] per update.
    pub fn internals(id: u16) -> String {
        format!("/vehicle_{id}/internals")
    }
}

/// The wall clock now, in nanoseconds since the UNIX epoch (0 if the clock is before 1970).
pub fn wall_now_ns() -> u64 {
    std::time::SystemTime::now().duration_since(std::time::UNIX_EPOCH).map_or(0, |d| d.as_nanos() as u64)
}

/// Length of the MAVLink frame that `bytes` must be exactly, from its header, or why `bytes`
/// is not one complete v1 or v2 frame.
pub fn mavlink_frame_len(bytes: &[u8]) -> Result<usize, &'static str> {
    let expected = crate::protocol::framing::declared_len(bytes)?;
    match bytes.len().cmp(&expected) {
        std::cmp::Ordering::Equal => Ok(expected),
        std::cmp::Ordering::Less => Err("shorter than the length in its header"),
        std::cmp::Ordering::Greater => Err("longer than the length in its header (more than one frame?)"),
    }
}

#[cfg(test)]
mod tests;
