//! Tests of the recorder and the reader together: round trips of every channel kind, cut and
//! damaged files, a writer that dies without finishing, failing sinks.

use std::cell::RefCell;
use std::collections::BTreeMap;
use std::io::{Cursor, Write};
use std::rc::Rc;
use std::time::{Duration, Instant};

use foxglove::messages::{FrameTransform, LocationFix, PoseInFrame, SceneUpdate};
use nalgebra::{Matrix3, Vector3};
use proptest::prelude::*;

use super::internals::tests::{sample_stats, sample_update};
use super::*;
use crate::node::log::CoopUpdateRecord;
use crate::time::TimeUs;

// ---- helpers ----

/// A byte sink the test can look into while the recorder owns it.
#[derive(Clone, Default)]
struct SharedBuf(Rc<RefCell<Vec<u8>>>);

impl SharedBuf {
    fn len(&self) -> usize {
        self.0.borrow().len()
    }
    fn bytes(&self) -> Vec<u8> {
        self.0.borrow().clone()
    }
}

impl Write for SharedBuf {
    fn write(&mut self, buf: &[u8]) -> std::io::Result<usize> {
        self.0.borrow_mut().extend_from_slice(buf);
        Ok(buf.len())
    }
    fn flush(&mut self) -> std::io::Result<()> {
        Ok(())
    }
}

/// A sink that fails once `limit` bytes were written.
struct FailAfter {
    written: usize,
    limit: usize,
}

impl Write for FailAfter {
    fn write(&mut self, buf: &[u8]) -> std::io::Result<usize> {
        if self.written + buf.len() > self.limit {
            return Err(std::io::Error::new(std::io::ErrorKind::StorageFull, "disk full"));
        }
        self.written += buf.len();
        Ok(buf.len())
    }
    fn flush(&mut self) -> std::io::Result<()> {
        Ok(())
    }
}

/// A MAVLink v2 HEARTBEAT-sized frame whose payload carries `n` (the framing is what the
/// recorder checks; the CRC is not).
fn frame(n: u32, sysid: u8) -> Vec<u8> {
    let mut f = vec![0xFD, 9, 0, 0, (n % 256) as u8, sysid, 1, 0, 0, 0];
    f.extend(n.to_le_bytes());
    f.extend([0, 0, 0, 0, 0]);
    f.extend([0x12, 0x34]);
    f
}

fn frame_number(data: &[u8]) -> u32 {
    u32::from_le_bytes(data[10..14].try_into().unwrap())
}

const ORIGIN: GeoOrigin = GeoOrigin { lat_deg: 47.397742, lon_deg: 8.545594, alt_m: 488.0 };
const T0_NS: u64 = 1_750_000_000_000_000_000;

fn estimate() -> PositionEstimate {
    #[rustfmt::skip]
    let cov = Matrix3::new(
        4.0, 0.5, 0.0,
        0.5, 1.0, 0.0,
        0.0, 0.0, 9.0,
    );
    PositionEstimate {
        t: TimeUs(12_500_000),
        pos_ned_m: Vector3::new(120.0, -35.0, -2.0),
        cov_ned_m2: cov,
        yaw_rad: Some(0.3),
        vel_ned_m_s: Some(Vector3::new(1.5, 0.2, 0.0)),
    }
}

fn truth() -> TruthSample {
    TruthSample { t: TimeUs(12_500_000), pos_ned_m: Vector3::new(121.0, -34.5, -2.0), yaw_rad: Some(0.31) }
}

/// Writes one message of every kind; returns the raw frames written, in order.
fn write_every_kind<W: Write>(rec: &mut Recorder<W>) -> Vec<(String, Vec<u8>)> {
    rec.declare_link(Link::Vehicle(2), "udpin:0.0.0.0:14540");
    rec.declare_link(Link::Coop(2), "0.0.0.0:14600");
    let mut frames = Vec::new();
    for (i, (link, dir)) in [
        (Link::Vehicle(2), Direction::Rx),
        (Link::Vehicle(2), Direction::Tx),
        (Link::Coop(2), Direction::Rx),
        (Link::Coop(2), Direction::Tx),
    ]
    .into_iter()
    .enumerate()
    {
        let f = frame(i as u32, 2);
        rec.frame(link, dir, T0_NS + i as u64, &f).unwrap();
        frames.push((topics::frames(link, dir), f));
    }
    rec.estimate(2, T0_NS + 10, &estimate()).unwrap();
    rec.truth(2, T0_NS + 11, &truth()).unwrap();
    super::record_update(rec, T0_NS + 12, &sample_update()).unwrap();
    rec.link_stats(T0_NS + 13, &sample_stats()).unwrap();
    rec.metadata("config", BTreeMap::from([("sysid".to_string(), "2".to_string())])).unwrap();
    rec.attachment("scenario.toml", "application/toml", b"[world]\nvehicles = 3\n").unwrap();
    frames
}

fn options() -> RecorderOptions {
    RecorderOptions { geo_origin: Some(ORIGIN), ..RecorderOptions::default() }
}

/// A log's bytes, and for each flush the file length then and the number of messages written by then.
type ChunkedLog = (Vec<u8>, Vec<(usize, u64)>);

/// A log of `n` frames with a flush every `every` frames.
fn chunked_log(n: u32, every: u32) -> ChunkedLog {
    let buf = SharedBuf::default();
    let mut rec = Recorder::new(buf.clone(), RecorderOptions { flush_interval: Duration::from_secs(3600), ..options() }).unwrap();
    let mut flushes = vec![(buf.len(), 0)];
    for i in 0..n {
        rec.frame(Link::Coop(1), if i % 3 == 0 { Direction::Tx } else { Direction::Rx }, T0_NS + u64::from(i), &frame(i, 1))
            .unwrap();
        if (i + 1) % every == 0 {
            rec.flush().unwrap();
            flushes.push((buf.len(), u64::from(i + 1)));
        }
    }
    rec.finish().unwrap();
    (buf.bytes(), flushes)
}

fn read_bytes(bytes: &[u8]) -> Result<Log, ReadError> {
    read_log_from(LogReader::new(Cursor::new(bytes)))
}

// ---- round trip ----

#[test]
fn every_channel_kind_round_trips() {
    let dir = tempdir();
    let path = dir.join("every.mcap");
    let mut rec = Recorder::create(&path, options()).unwrap();
    let frames = write_every_kind(&mut rec);
    let stats = rec.finish().unwrap();
    assert_eq!(stats.messages_written, 4 + 4 + 2 + 2, "frames, estimate (location, tf, pose, ellipse), truth (2), json (2)");
    assert_eq!(stats.failure, None);

    let log = read_log(&path).unwrap();
    assert!(log.is_complete(), "{:?}", log.end);

    // Raw frames: byte for byte, schemaless, with the documented metadata.
    for (topic, bytes) in &frames {
        let msgs: Vec<_> = log.topic(topic).collect();
        assert_eq!(msgs.len(), 1, "{topic}");
        let m = msgs[0];
        assert_eq!(&m.data, bytes);
        assert_eq!(m.channel.message_encoding, MAVLINK_FRAME_ENCODING);
        assert!(m.channel.schema.is_none());
        assert_eq!(m.channel.metadata["dialect"], "cooploc");
        assert_eq!(m.channel.metadata["direction"], if topic.ends_with("rx") { "rx" } else { "tx" });
        let link = if topic.starts_with("/coop") { "0.0.0.0:14600" } else { "udpin:0.0.0.0:14540" };
        assert_eq!(m.channel.metadata["link"], link);
        assert_eq!(m.log_time_ns, m.publish_time_ns);
    }

    // Foxglove channels: schema names, protobuf, decodable, the values that went in.
    let one = |topic: &str| {
        let v: Vec<_> = log.topic(topic).collect();
        assert_eq!(v.len(), 1, "{topic}");
        v[0].clone()
    };
    let check_schema = |m: &LoggedMessage, name: &str| {
        let s = m.channel.schema.as_ref().unwrap_or_else(|| panic!("{} has no schema", m.topic()));
        assert_eq!((s.name.as_str(), s.encoding.as_str()), (name, "protobuf"), "{}", m.topic());
        assert_eq!(m.channel.message_encoding, "protobuf");
        assert!(!s.data.is_empty());
    };
    let loc = one("/vehicle_2/location");
    check_schema(&loc, "foxglove.LocationFix");
    let fix: LocationFix = loc.protobuf().unwrap();
    let g = crate::protocol::wire::ned_to_geodetic(&ORIGIN, &estimate().pos_ned_m);
    assert_eq!((fix.latitude, fix.longitude, fix.altitude), (g.lat_deg, g.lon_deg, g.alt_m));
    assert_eq!(fix.position_covariance, vec![1.0, 0.5, 0.0, 0.5, 4.0, 0.0, 0.0, 0.0, 9.0]);
    assert_eq!(fix.position_covariance_type, 3, "KNOWN");
    assert_eq!(loc.log_time_ns, T0_NS + 10);

    let pose = one("/vehicle_2/pose");
    check_schema(&pose, "foxglove.PoseInFrame");
    let p: PoseInFrame = pose.protobuf().unwrap();
    assert_eq!(p.frame_id, "ned");
    let pos = p.pose.unwrap().position.unwrap();
    assert_eq!((pos.x, pos.y, pos.z), (120.0, -35.0, -2.0));

    let ell = one("/vehicle_2/ellipse");
    check_schema(&ell, "foxglove.SceneUpdate");
    let s: SceneUpdate = ell.protobuf().unwrap();
    assert_eq!(s.entities[0].id, "vehicle_2_ellipse");
    let size = s.entities[0].spheres[0].size.unwrap();
    let (major, minor, _) = crate::view::foxglove::ellipse_axes(4.0, 0.5, 1.0);
    assert_eq!((size.x, size.y), (2.0 * major, 2.0 * minor));

    let tf: Vec<_> = log.topic(topics::TF).collect();
    assert_eq!(tf.len(), 1, "one /tf per chunk");
    check_schema(tf[0], "foxglove.FrameTransform");
    let tf: FrameTransform = tf[0].protobuf().unwrap();
    assert_eq!((tf.parent_frame_id.as_str(), tf.child_frame_id.as_str()), ("world", "ned"));

    let t = one("/vehicle_2/truth");
    check_schema(&t, "foxglove.LocationFix");
    assert_eq!(t.protobuf::<LocationFix>().unwrap().position_covariance_type, 0);
    check_schema(&one("/vehicle_2/truth_pose"), "foxglove.PoseInFrame");

    // JSON channels.
    let internals = one("/vehicle_2/internals");
    assert_eq!(internals.channel.message_encoding, "json");
    let schema = internals.channel.schema.as_ref().unwrap();
    assert_eq!((schema.name.as_str(), schema.encoding.as_str()), ("cooploc.CoopUpdate", "jsonschema"));
    serde_json::from_slice::<serde_json::Value>(&schema.data).unwrap();
    assert_eq!(internals.json::<CoopUpdateRecord>().unwrap(), sample_update());
    let stats_msg = one("/links/stats");
    assert_eq!(stats_msg.channel.schema.as_ref().unwrap().name, "cooploc.LinkStats");
    assert_eq!(stats_msg.json::<LinkStatsRecord>().unwrap(), sample_stats());

    // Metadata and attachments, from the data section and from the summary.
    let header = log.metadata_named(LOG_METADATA_NAME).unwrap();
    assert_eq!(header.entries["format_version"], FORMAT_VERSION.to_string());
    assert_eq!(log.metadata_named("config").unwrap().entries["sysid"], "2");
    assert_eq!(log.attachments.len(), 1);
    assert_eq!(log.attachments[0].data, b"[world]\nvehicles = 3\n");
    assert_eq!(log.attachments[0].media_type, "application/toml");

    let index = read_index(&path).unwrap();
    assert_eq!(index.message_count, stats.messages_written);
    assert_eq!(index.topic_counts["/coop/2/rx"], 1);
    assert_eq!(index.channels.len(), log.channels.len());
    assert_eq!(index.metadata, log.metadata);
    assert_eq!(index.attachments, log.attachments);
    assert_eq!((index.start_ns, index.end_ns), (T0_NS, T0_NS + 13));

    // Per-topic reading.
    let mut reader = LogReader::open(&path).unwrap().with_topics(["/coop/2/rx", "/links/stats"]);
    let topics: Vec<String> = reader.by_ref().map(|m| m.unwrap().topic().to_string()).collect();
    assert_eq!(topics, ["/coop/2/rx", "/links/stats"]);
    assert_eq!(reader.end(), Some(&LogEnd::Complete));
    assert_eq!(reader.messages_read(), stats.messages_written);
}

#[test]
fn without_a_geo_origin_there_is_no_location() {
    let buf = SharedBuf::default();
    let mut rec = Recorder::new(buf.clone(), RecorderOptions::default()).unwrap();
    rec.estimate(4, T0_NS, &estimate()).unwrap();
    rec.truth(4, T0_NS, &truth()).unwrap();
    rec.finish().unwrap();
    let log = read_bytes(&buf.bytes()).unwrap();
    let topics: Vec<&str> = log.messages.iter().map(|m| m.topic()).collect();
    assert_eq!(topics, ["/tf", "/vehicle_4/pose", "/vehicle_4/ellipse", "/vehicle_4/truth_pose"]);
}

// ---- refusing bad input, failing sinks, flush timing ----

#[test]
fn bad_inputs_are_refused_and_the_recorder_goes_on() {
    let buf = SharedBuf::default();
    let mut rec = Recorder::new(buf.clone(), options()).unwrap();
    let err = rec.frame(Link::Coop(1), Direction::Rx, T0_NS, b"hello").unwrap_err();
    assert!(matches!(err, RecorderError::NotAFrame { .. }), "{err}");
    assert!(err.to_string().contains("/coop/1/rx"), "{err}");
    let mut two = frame(1, 1);
    two.extend(frame(2, 1));
    assert!(rec.frame(Link::Coop(1), Direction::Rx, T0_NS, &two).is_err());
    let mut est = estimate();
    est.cov_ned_m2[(1, 1)] = f64::NAN;
    let err = rec.estimate(1, T0_NS, &est).unwrap_err();
    assert!(matches!(err, RecorderError::NonFinite { field: "cov_ned_m2", .. }), "{err}");
    rec.frame(Link::Coop(1), Direction::Rx, T0_NS, &frame(3, 1)).unwrap();
    assert!(!rec.is_failed());
    assert_eq!(rec.stats().rejected, 3);
    rec.finish().unwrap();
    assert_eq!(read_bytes(&buf.bytes()).unwrap().messages.len(), 1);
}

#[test]
fn a_write_error_fails_the_recorder_once_without_panicking() {
    // Enough room for the header and the first flush, not for long.
    let mut rec = Recorder::new(FailAfter { written: 0, limit: 600 }, options()).unwrap();
    let mut first_error = None;
    for i in 0..200 {
        if let Err(e) = rec.frame(Link::Coop(1), Direction::Rx, T0_NS, &frame(i, 1)) {
            first_error.get_or_insert(e);
        }
        if i % 10 == 9
            && let Err(e) = rec.flush()
        {
            first_error.get_or_insert(e);
        }
    }
    let first_error = first_error.expect("the sink filled up");
    assert!(matches!(first_error, RecorderError::Write { .. }), "{first_error}");
    assert!(first_error.to_string().contains("disk full"), "{first_error}");
    assert!(rec.is_failed());
    assert!(rec.stats().dropped > 0);
    assert!(rec.stats().failure.as_deref().unwrap().contains("disk full"));
    assert!(matches!(rec.frame(Link::Coop(1), Direction::Rx, T0_NS, &frame(0, 1)), Err(RecorderError::Failed { .. })));
    assert!(matches!(rec.finish(), Err(RecorderError::Failed { .. })));
}

#[test]
fn flushes_when_the_interval_has_passed() {
    let buf = SharedBuf::default();
    let mut rec = Recorder::new(buf.clone(), options()).unwrap();
    let flushes = rec.stats().flushes;
    let start = Instant::now();
    rec.frame(Link::Coop(1), Direction::Rx, T0_NS, &frame(0, 1)).unwrap();
    assert_eq!(rec.stats().messages_flushed, 0);
    let len = buf.len();
    assert!(!rec.maybe_flush(start).unwrap());
    assert!(rec.maybe_flush(start + Duration::from_millis(1100)).unwrap());
    assert_eq!(rec.stats().flushes, flushes + 1);
    assert_eq!(rec.stats().messages_flushed, 1);
    assert!(buf.len() > len, "the chunk reached the sink");
    // A zero interval flushes on every write.
    rec.set_flush_interval(Duration::ZERO);
    rec.frame(Link::Coop(1), Direction::Rx, T0_NS, &frame(1, 1)).unwrap();
    assert_eq!(rec.stats().messages_flushed, 2);
}

// ---- cut, killed and damaged files ----

#[test]
fn a_cut_file_reads_a_prefix_up_to_its_last_complete_chunk() {
    let (bytes, flushes) = chunked_log(3000, 60);
    let full = read_bytes(&bytes).unwrap();
    assert!(full.is_complete());
    assert_eq!(full.messages.len(), 3000);
    let mut cuts: Vec<usize> = (0..bytes.len()).step_by(997).collect();
    // Right at and around each flush boundary too.
    cuts.extend(flushes.iter().flat_map(|&(len, _)| [len.saturating_sub(1), len, len + 1]));
    cuts.push(bytes.len() - 1);
    for cut in cuts {
        let cut_bytes = &bytes[..cut.min(bytes.len())];
        let log = read_bytes(cut_bytes).unwrap_or_else(|e| panic!("cut at {cut}: {e}"));
        assert_eq!(log.end, LogEnd::Truncated, "cut at {cut}");
        let n = log.messages.len();
        assert_eq!(log.messages[..], full.messages[..n], "cut at {cut}: not a prefix");
        // Everything flushed before the cut is there.
        let flushed = flushes.iter().filter(|&&(len, _)| len <= cut).map(|&(_, n)| n).max().unwrap_or(0);
        assert!(n as u64 >= flushed, "cut at {cut}: {n} messages, {flushed} were flushed before it");
        if cut >= flushes[0].0 {
            assert!(log.metadata_named(LOG_METADATA_NAME).is_some(), "cut at {cut}");
        }
        // The streaming reader says the same, as one final error.
        let items: Vec<_> = LogReader::new(Cursor::new(cut_bytes)).collect();
        let (last, msgs) = items.split_last().unwrap();
        assert_eq!(msgs.len(), n);
        match last {
            Err(ReadError::Truncated { messages_read, .. }) => assert_eq!(*messages_read as usize, n),
            other => panic!("cut at {cut}: {other:?}"),
        }
    }
}

#[test]
fn a_writer_killed_after_a_flush_leaves_what_it_flushed() {
    let dir = tempdir();
    let path = dir.join("killed.mcap");
    let mut rec = Recorder::create(&path, RecorderOptions { flush_interval: Duration::from_secs(3600), ..options() }).unwrap();
    rec.attachment("scenario.toml", "application/toml", b"x = 1").unwrap();
    for i in 0..500 {
        rec.frame(Link::Vehicle(3), Direction::Rx, T0_NS + u64::from(i), &frame(i, 3)).unwrap();
    }
    rec.flush().unwrap();
    for i in 500..520 {
        rec.frame(Link::Vehicle(3), Direction::Rx, T0_NS + u64::from(i), &frame(i, 3)).unwrap();
    }
    // SIGKILL: no finish, no drop, buffers lost.
    std::mem::forget(rec);

    let log = read_log(&path).unwrap();
    assert_eq!(log.end, LogEnd::Truncated);
    let numbers: Vec<u32> = log.messages.iter().map(|m| frame_number(&m.data)).collect();
    assert_eq!(numbers, (0..500).collect::<Vec<_>>());
    assert!(log.metadata_named(LOG_METADATA_NAME).is_some());
    assert_eq!(log.attachments[0].data, b"x = 1");
    let err = read_index(&path).unwrap_err();
    assert!(matches!(err, ReadError::NoSummary { .. }), "{err}");
    assert!(err.to_string().contains("killed"), "{err}");
}

#[test]
fn garbage_is_not_an_mcap_file() {
    let err = read_bytes(b"this is a text file, not a log\n").unwrap_err();
    assert!(matches!(err, ReadError::NotMcap), "{err}");
    assert!(err.to_string().contains("not an MCAP file"));
    let dir = tempdir();
    let path = dir.join("garbage.mcap");
    std::fs::write(&path, vec![0x42; 5000]).unwrap();
    assert!(matches!(read_log(&path), Err(ReadError::NotMcap)));
    assert!(matches!(read_index(&path), Err(ReadError::NotMcap)));
    assert!(matches!(read_log(dir.join("missing.mcap")), Err(ReadError::Open { .. })));
    // An empty file, or only part of the magic: a log cut before anything was in it.
    assert_eq!(read_bytes(b"").unwrap().end, LogEnd::Truncated);
    assert_eq!(read_bytes(b"\x89MC").unwrap().end, LogEnd::Truncated);
}

#[test]
fn a_damaged_chunk_stops_the_read_before_it() {
    let (mut bytes, flushes) = chunked_log(600, 100);
    // A byte of the third chunk's compressed data (after its opcode, length and 44-byte header).
    bytes[flushes[2].0 + 9 + 44 + 8] ^= 0x55;
    let log = read_bytes(&bytes).unwrap();
    assert!(matches!(log.end, LogEnd::Corrupt { .. }), "{:?}", log.end);
    assert_eq!(log.messages.len(), 200);
}

// ---- never panics ----

fn small_log() -> &'static ChunkedLog {
    static LOG: std::sync::OnceLock<ChunkedLog> = std::sync::OnceLock::new();
    LOG.get_or_init(|| chunked_log(300, 25))
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(300))]

    #[test]
    fn random_bytes_never_panic(bytes in proptest::collection::vec(any::<u8>(), 0..4096), with_magic in any::<bool>()) {
        let mut data = if with_magic { b"\x89MCAP0\r\n".to_vec() } else { Vec::new() };
        data.extend(bytes);
        let _ = read_bytes(&data);
        let n = LogReader::new(Cursor::new(&data)).filter(Result::is_err).count();
        prop_assert!(n <= 1, "at most one error, at the end");
    }

    #[test]
    fn cut_and_damaged_logs_never_panic(cut in 0usize..1_000_000, flips in proptest::collection::vec((any::<usize>(), any::<u8>()), 0..4)) {
        let (bytes, _) = small_log();
        let full = read_bytes(bytes).unwrap();
        let mut data = bytes[..cut % (bytes.len() + 1)].to_vec();
        let damaged = !flips.is_empty() && !data.is_empty();
        if !data.is_empty() {
            for (at, x) in &flips {
                let i = at % data.len();
                data[i] ^= x | 1;
            }
        }
        match read_bytes(&data) {
            Ok(log) => {
                if !damaged {
                    // Undamaged: always a prefix of the full log.
                    prop_assert_eq!(&log.messages[..], &full.messages[..log.messages.len()]);
                }
            }
            Err(e) => prop_assert!(damaged, "undamaged cut gave {}", e),
        }
    }
}

#[test]
fn a_dropped_recorder_still_finishes_its_file_and_can_move_between_threads() {
    fn assert_send<T: Send>() {}
    assert_send::<Recorder>();
    let dir = tempdir();
    let path = dir.join("dropped.mcap");
    let mut rec = Recorder::create(&path, options()).unwrap();
    rec.frame(Link::Coop(1), Direction::Tx, T0_NS, &frame(0, 1)).unwrap();
    drop(rec);
    let log = read_log(&path).unwrap();
    assert!(log.is_complete(), "{:?}", log.end);
    assert_eq!(log.messages.len(), 1);
    assert_eq!(read_index(&path).unwrap().message_count, 1);
}

// ---- a temporary directory without another dependency ----

struct TempDir(std::path::PathBuf);

impl std::ops::Deref for TempDir {
    type Target = std::path::Path;
    fn deref(&self) -> &std::path::Path {
        &self.0
    }
}

impl Drop for TempDir {
    fn drop(&mut self) {
        let _ = std::fs::remove_dir_all(&self.0);
    }
}

fn tempdir() -> TempDir {
    use std::sync::atomic::{AtomicU32, Ordering};
    static N: AtomicU32 = AtomicU32::new(0);
    let dir = std::env::temp_dir().join(format!("cooploc-rec-{}-{}", std::process::id(), N.fetch_add(1, Ordering::Relaxed)));
    std::fs::create_dir_all(&dir).unwrap();
    TempDir(dir)
}
