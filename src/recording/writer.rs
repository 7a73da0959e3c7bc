//! [`Recorder`]: writes the log described in [`crate::recording`].
//!
//! The MCAP writer buffers the current chunk in memory (`disable_seeking`), so the file only
//! ever holds complete chunks: whatever a kill interrupts is at most the chunk being written.
//! Every write checks the wall clock and, once [`RecorderOptions::flush_interval`] has passed
//! since the last flush, closes the chunk and flushes the file to the operating system
//! ([`mcap::Writer::flush`] finishes the chunk, then flushes the stream). That survives SIGKILL
//! (the data is in the kernel), not a power cut (no fsync).

use std::borrow::Cow;
use std::collections::{BTreeMap, HashMap};
use std::fs::File;
use std::io::{BufWriter, Write};
use std::path::Path;
use std::time::{Duration, Instant};

use mcap::records::MessageHeader;
use mcap::write::NoSeek;
use serde::Serialize;

use super::internals::{LINK_STATS_SCHEMA, LINK_STATS_SCHEMA_NAME, LinkStatsRecord};
use super::{DIALECT, Direction, FORMAT_VERSION, LOG_METADATA_NAME, Link, MAVLINK_FRAME_ENCODING, topics, wall_now_ns};
use crate::protocol::wire::GeoOrigin;
use crate::view::foxglove::{self as fx, PositionEstimate, TruthSample};

/// How a [`Recorder`] writes.
#[derive(Debug, Clone, PartialEq)]
pub struct RecorderOptions {
    /// Longest wall time between two flushes while messages arrive (the most a kill loses).
    pub flush_interval: Duration,
    /// Where the NED origin is on the Earth; `None`: no `location` / `truth` LocationFix messages.
    pub geo_origin: Option<GeoOrigin>,
    /// Uncompressed size at which a chunk is closed before the flush interval ends, bytes.
    pub chunk_size: u64,
    /// zstd level (0: zstd's default, 3).
    pub zstd_level: u32,
}

impl Default for RecorderOptions {
    fn default() -> Self {
        RecorderOptions { flush_interval: Duration::from_secs(1), geo_origin: None, chunk_size: 1 << 20, zstd_level: 0 }
    }
}

/// Counters of a [`Recorder`].
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct RecorderStats {
    /// Messages handed to the MCAP writer.
    pub messages_written: u64,
    /// Of those, the ones in the file as of the last flush (what a kill now would keep).
    pub messages_flushed: u64,
    pub flushes: u64,
    /// Wall time of the last flush, ns since the UNIX epoch.
    pub last_flush_wall_ns: u64,
    /// Inputs refused (not a MAVLink frame, non-finite estimate); the recorder goes on.
    pub rejected: u64,
    /// Messages not recorded because the recorder had failed.
    pub dropped: u64,
    /// The write error that stopped the recorder, if one did.
    pub failure: Option<String>,
}

/// Why a recording call did not record.
#[derive(Debug, thiserror::Error)]
pub enum RecorderError {
    #[error("cannot create the log file {path}: {source}")]
    Create { path: String, source: std::io::Error },
    #[error("writing the MCAP log {target} failed, nothing more is recorded in it: {}", error_chain(.source))]
    Write { target: String, source: mcap::McapError },
    #[error("the MCAP log {target} stopped after an earlier write error ({first_error})")]
    Failed { target: String, first_error: String },
    #[error("refused a frame for {topic} ({len} bytes): not one MAVLink frame: {reason}")]
    NotAFrame { topic: String, len: usize, reason: &'static str },
    #[error("refused a message for {topic}: {field} is not finite")]
    NonFinite { topic: String, field: &'static str },
    #[error("cannot encode the {schema} message for {topic}: {reason}")]
    Encode { topic: String, schema: String, reason: String },
}

/// An error and its sources, `a: b: c` (mcap's I/O error does not show its cause itself).
fn error_chain(e: &dyn std::error::Error) -> String {
    let mut s = e.to_string();
    let mut source = e.source();
    while let Some(inner) = source {
        s.push_str(": ");
        s.push_str(&inner.to_string());
        source = inner.source();
    }
    s
}

/// What a new channel is made of.
struct ChannelSpec {
    schema: Option<(String, String, Cow<'static, [u8]>)>,
    message_encoding: String,
    metadata: BTreeMap<String, String>,
}

/// Writes one MCAP log (see [`crate::recording`] for its channels). Not thread safe by design:
/// one task owns it.
///
/// Each recording call returns `Err` when it recorded nothing; the recorder logs and counts
/// that itself, so a caller that does not care may ignore the result. After a write error the
/// recorder is *failed*: it has logged the error once (tracing), stops writing (the file keeps
/// what was flushed) and counts further messages as dropped.
///
/// Dropping a recorder without [`Recorder::finish`] still finishes the file (the MCAP writer
/// does it on drop, ignoring errors).
pub struct Recorder<W: Write = BufWriter<File>> {
    /// `None` once failed.
    writer: Option<mcap::Writer<NoSeek<W>>>,
    target: String,
    options: RecorderOptions,
    channels: HashMap<String, u16>,
    sequences: HashMap<u16, u32>,
    link_names: HashMap<Link, String>,
    last_flush: Instant,
    tf_in_chunk: bool,
    stats: RecorderStats,
}

impl Recorder<BufWriter<File>> {
    /// Creates (or truncates) the file at `path` and starts a log in it.
    pub fn create(path: impl AsRef<Path>, options: RecorderOptions) -> Result<Self, RecorderError> {
        let path = path.as_ref();
        let target = path.display().to_string();
        let file = File::create(path).map_err(|source| RecorderError::Create { path: target.clone(), source })?;
        Self::with_target(BufWriter::with_capacity(64 * 1024, file), target, options)
    }
}

impl<W: Write> Recorder<W> {
    /// Starts a log on any byte sink (a file, a buffer in tests).
    pub fn new(writer: W, options: RecorderOptions) -> Result<Self, RecorderError> {
        Self::with_target(writer, "<stream>".into(), options)
    }

    fn with_target(writer: W, target: String, options: RecorderOptions) -> Result<Self, RecorderError> {
        let write_options = mcap::WriteOptions::new()
            .compression(Some(mcap::Compression::Zstd))
            .compression_level(options.zstd_level)
            // Chunks are small (one second): a thread pool per writer buys nothing.
            .compression_threads(0)
            .chunk_size(Some(options.chunk_size))
            .use_chunks(true)
            // Build each chunk in memory and write it whole: the file never holds half a chunk.
            .disable_seeking(true)
            .library(format!("cooploc {} (mcap-rs 0.26)", env!("CARGO_PKG_VERSION")));
        let mcap_writer = write_options
            .create(NoSeek::new(writer))
            .map_err(|source| RecorderError::Write { target: target.clone(), source })?;
        let mut rec = Recorder {
            writer: Some(mcap_writer),
            target,
            options,
            channels: HashMap::new(),
            sequences: HashMap::new(),
            link_names: HashMap::new(),
            last_flush: Instant::now(),
            tf_in_chunk: false,
            stats: RecorderStats::default(),
        };
        let header = BTreeMap::from([
            ("format_version".to_string(), FORMAT_VERSION.to_string()),
            ("crate_version".to_string(), env!("CARGO_PKG_VERSION").to_string()),
        ]);
        rec.metadata(LOG_METADATA_NAME, header)?;
        rec.flush()?;
        Ok(rec)
    }

    /// The file path (or `<stream>`), for messages.
    pub fn target(&self) -> &str {
        &self.target
    }

    pub fn stats(&self) -> &RecorderStats {
        &self.stats
    }

    pub fn options(&self) -> &RecorderOptions {
        &self.options
    }

    /// Whether a write error stopped the recorder.
    pub fn is_failed(&self) -> bool {
        self.writer.is_none()
    }

    /// Sets the origin of the `location` / `truth` LocationFix messages from now on.
    pub fn set_geo_origin(&mut self, origin: Option<GeoOrigin>) {
        self.options.geo_origin = origin;
    }

    /// Sets the longest wall time between two flushes from now on.
    pub fn set_flush_interval(&mut self, interval: Duration) {
        self.options.flush_interval = interval;
    }

    /// Names the link (URL or socket address) that goes into the metadata of `link`'s frame
    /// channels. Call it before the first frame of that link: channels are created on first use.
    pub fn declare_link(&mut self, link: Link, name: impl Into<String>) {
        self.link_names.insert(link, name.into());
    }

    /// Records one raw MAVLink frame (exactly one complete v1 or v2 frame, as on the wire) that
    /// the process received (`Rx`) or sent (`Tx`) at `wall_ns`.
    pub fn frame(&mut self, link: Link, dir: Direction, wall_ns: u64, frame: &[u8]) -> Result<(), RecorderError> {
        let topic = topics::frames(link, dir);
        if let Err(reason) = super::mavlink_frame_len(frame) {
            self.stats.rejected += 1;
            return Err(RecorderError::NotAFrame { topic, len: frame.len(), reason });
        }
        let link_name = self.link_names.get(&link).cloned().unwrap_or_default();
        self.write(
            &topic,
            || ChannelSpec {
                schema: None,
                message_encoding: MAVLINK_FRAME_ENCODING.into(),
                metadata: BTreeMap::from([
                    ("link".to_string(), link_name),
                    ("dialect".to_string(), DIALECT.to_string()),
                    ("direction".to_string(), dir.as_str().to_string()),
                ]),
            },
            wall_ns,
            frame,
        )?;
        self.after_write()
    }

    /// Records vehicle `id`'s estimate: `/vehicle_<id>/pose`, `/vehicle_<id>/ellipse`, and
    /// `/vehicle_<id>/location` when a geo origin is set.
    pub fn estimate(&mut self, id: u16, wall_ns: u64, est: &PositionEstimate) -> Result<(), RecorderError> {
        if let Some(field) = est.non_finite_field() {
            self.stats.rejected += 1;
            return Err(RecorderError::NonFinite { topic: topics::pose(id), field });
        }
        if let Some(origin) = self.options.geo_origin {
            self.foxglove_unflushed(&topics::location(id), wall_ns, &fx::location_fix(&origin, id, est, wall_ns))?;
        }
        self.write_tf(wall_ns)?;
        self.foxglove_unflushed(&topics::pose(id), wall_ns, &fx::pose_in_ned(&est.pos_ned_m, est.yaw_rad, wall_ns))?;
        self.foxglove_unflushed(&topics::ellipse(id), wall_ns, &fx::ellipse_update(id, est, wall_ns))?;
        self.after_write()
    }

    /// Records vehicle `id`'s true position: `/vehicle_<id>/truth_pose`, and
    /// `/vehicle_<id>/truth` when a geo origin is set.
    pub fn truth(&mut self, id: u16, wall_ns: u64, truth: &TruthSample) -> Result<(), RecorderError> {
        if !truth.pos_ned_m.iter().all(|v| v.is_finite()) || !truth.yaw_rad.is_none_or(f64::is_finite) {
            self.stats.rejected += 1;
            return Err(RecorderError::NonFinite { topic: topics::truth_pose(id), field: "truth" });
        }
        if let Some(origin) = self.options.geo_origin {
            self.foxglove_unflushed(&topics::truth(id), wall_ns, &fx::truth_fix(&origin, id, truth, wall_ns))?;
        }
        self.write_tf(wall_ns)?;
        let pose = fx::pose_in_ned(&truth.pos_ned_m, truth.yaw_rad, wall_ns);
        self.foxglove_unflushed(&topics::truth_pose(id), wall_ns, &pose)?;
        self.after_write()
    }

    /// Records the process's link statistics on `/links/stats`.
    pub fn link_stats(&mut self, wall_ns: u64, stats: &LinkStatsRecord) -> Result<(), RecorderError> {
        self.json_message(topics::LINK_STATS, LINK_STATS_SCHEMA_NAME, LINK_STATS_SCHEMA, wall_ns, stats)
    }

    /// Records any Foxglove well-known message (protobuf) on `topic`.
    pub fn foxglove_message<T: foxglove::Encode>(&mut self, topic: &str, wall_ns: u64, msg: &T) -> Result<(), RecorderError> {
        self.foxglove_unflushed(topic, wall_ns, msg)?;
        self.after_write()
    }

    /// Records `value` as JSON on `topic`, whose schema is the JSON schema `schema` named `schema_name`.
    pub fn json_message<T: Serialize>(
        &mut self,
        topic: &str,
        schema_name: &str,
        schema: &str,
        wall_ns: u64,
        value: &T,
    ) -> Result<(), RecorderError> {
        let data = match serde_json::to_vec(value) {
            Ok(d) => d,
            Err(e) => {
                self.stats.rejected += 1;
                return Err(RecorderError::Encode { topic: topic.into(), schema: schema_name.into(), reason: e.to_string() });
            }
        };
        let spec = || ChannelSpec {
            schema: Some((schema_name.to_string(), "jsonschema".to_string(), Cow::Owned(schema.as_bytes().to_vec()))),
            message_encoding: "json".into(),
            metadata: BTreeMap::new(),
        };
        self.write(topic, spec, wall_ns, &data)?;
        self.after_write()
    }

    /// Writes a metadata record `name` (e.g. the node's configuration).
    pub fn metadata(&mut self, name: &str, entries: BTreeMap<String, String>) -> Result<(), RecorderError> {
        let writer = self.writer_or_drop()?;
        let res = writer.write_metadata(&mcap::records::Metadata { name: name.into(), metadata: entries });
        self.check(res)?;
        self.after_write()
    }

    /// Writes an attachment (e.g. the scenario TOML, media type `application/toml`), stamped
    /// with the wall clock now.
    pub fn attachment(&mut self, name: &str, media_type: &str, data: &[u8]) -> Result<(), RecorderError> {
        let now = wall_now_ns();
        let writer = self.writer_or_drop()?;
        let res = writer.attach(&mcap::Attachment {
            log_time: now,
            create_time: now,
            name: name.into(),
            media_type: media_type.into(),
            data: Cow::Borrowed(data),
        });
        self.check(res)?;
        self.after_write()
    }

    /// Flushes if [`RecorderOptions::flush_interval`] has passed since the last flush at `now`;
    /// returns whether it did. Every recording call runs this with the current time; a runner
    /// also calls it from a timer, so that the last messages before a quiet period reach the file.
    pub fn maybe_flush(&mut self, now: Instant) -> Result<bool, RecorderError> {
        if now.saturating_duration_since(self.last_flush) < self.options.flush_interval {
            return Ok(false);
        }
        self.flush_at(now)?;
        Ok(true)
    }

    /// Closes the current chunk and flushes the file now.
    pub fn flush(&mut self) -> Result<(), RecorderError> {
        self.flush_at(Instant::now())
    }

    /// Writes the summary and flushes: the file is complete. Returns the final counters.
    pub fn finish(mut self) -> Result<RecorderStats, RecorderError> {
        let Some(mut writer) = self.writer.take() else {
            return Err(self.failed_error());
        };
        let result = writer.finish().and_then(|_| writer.into_inner().flush().map_err(mcap::McapError::from));
        match result {
            Ok(()) => {
                self.stats.messages_flushed = self.stats.messages_written;
                self.stats.flushes += 1;
                self.stats.last_flush_wall_ns = wall_now_ns();
                Ok(self.stats)
            }
            Err(source) => {
                tracing::error!(log = %self.target, error = %error_chain(&source), "finishing the MCAP log failed");
                Err(RecorderError::Write { target: self.target, source })
            }
        }
    }

    // ---- internals ----

    fn flush_at(&mut self, now: Instant) -> Result<(), RecorderError> {
        let writer = self.writer.as_mut().ok_or_else(|| Self::failed_error_of(&self.target, &self.stats))?;
        let res = writer.flush();
        self.check(res)?;
        self.last_flush = now;
        self.tf_in_chunk = false;
        self.stats.flushes += 1;
        self.stats.messages_flushed = self.stats.messages_written;
        self.stats.last_flush_wall_ns = wall_now_ns();
        Ok(())
    }

    fn after_write(&mut self) -> Result<(), RecorderError> {
        self.maybe_flush(Instant::now()).map(|_| ())
    }

    /// The `/tf` transform, once per chunk.
    fn write_tf(&mut self, wall_ns: u64) -> Result<(), RecorderError> {
        if !self.tf_in_chunk {
            self.foxglove_unflushed(topics::TF, wall_ns, &fx::world_to_ned(wall_ns))?;
            self.tf_in_chunk = true;
        }
        Ok(())
    }

    fn foxglove_unflushed<T: foxglove::Encode>(&mut self, topic: &str, wall_ns: u64, msg: &T) -> Result<(), RecorderError> {
        let schema = T::get_schema();
        let mut data = Vec::with_capacity(msg.encoded_len().unwrap_or(256));
        if let Err(e) = msg.encode(&mut data) {
            self.stats.rejected += 1;
            let schema = schema.map_or_else(String::new, |s| s.name);
            return Err(RecorderError::Encode { topic: topic.into(), schema, reason: e.to_string() });
        }
        let spec = || ChannelSpec {
            schema: schema.map(|s| (s.name, s.encoding, s.data)),
            message_encoding: T::get_message_encoding(),
            metadata: BTreeMap::new(),
        };
        self.write(topic, spec, wall_ns, &data)
    }

    /// Writes one message, creating its channel on first use; does not flush.
    fn write(&mut self, topic: &str, spec: impl FnOnce() -> ChannelSpec, wall_ns: u64, data: &[u8]) -> Result<(), RecorderError> {
        let channel_id = match self.channels.get(topic) {
            Some(&id) => id,
            None => {
                let spec = spec();
                let writer = self.writer_or_drop()?;
                let res = (|| {
                    let schema_id = match &spec.schema {
                        Some((name, encoding, data)) => writer.add_schema(name, encoding, data)?,
                        None => 0,
                    };
                    writer.add_channel(schema_id, topic, &spec.message_encoding, &spec.metadata)
                })();
                let id = self.check(res)?;
                self.channels.insert(topic.to_string(), id);
                id
            }
        };
        let sequence = self.sequences.entry(channel_id).or_insert(0);
        let header = MessageHeader { channel_id, sequence: *sequence, log_time: wall_ns, publish_time: wall_ns };
        *sequence = sequence.wrapping_add(1);
        let writer = self.writer_or_drop()?;
        let res = writer.write_to_known_channel(&header, data);
        self.check(res)?;
        self.stats.messages_written += 1;
        Ok(())
    }

    fn writer_or_drop(&mut self) -> Result<&mut mcap::Writer<NoSeek<W>>, RecorderError> {
        match self.writer.as_mut() {
            Some(w) => Ok(w),
            None => {
                self.stats.dropped += 1;
                Err(Self::failed_error_of(&self.target, &self.stats))
            }
        }
    }

    /// Passes a result through; on error the recorder fails (once, logged).
    fn check<T>(&mut self, res: mcap::McapResult<T>) -> Result<T, RecorderError> {
        res.map_err(|source| {
            let chain = error_chain(&source);
            tracing::error!(log = %self.target, error = %chain, "writing the MCAP log failed; nothing more is recorded in it");
            self.stats.failure = Some(chain);
            self.stats.dropped += 1;
            // Hand the stream back without writing a summary onto a broken file; what was flushed stays.
            if let Some(writer) = self.writer.take() {
                drop(writer.into_inner());
            }
            RecorderError::Write { target: self.target.clone(), source }
        })
    }

    fn failed_error(&self) -> RecorderError {
        Self::failed_error_of(&self.target, &self.stats)
    }

    fn failed_error_of(target: &str, stats: &RecorderStats) -> RecorderError {
        RecorderError::Failed { target: target.to_string(), first_error: stats.failure.clone().unwrap_or_default() }
    }
}
