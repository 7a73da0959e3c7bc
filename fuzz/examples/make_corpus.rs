//! Writes the structured seed corpus of the `frames` fuzz target: real MAVLink 2 frames of every
//! message the target converts, made with cooploc's own `wire::to_frame` and conversions, and a
//! 16-state state record (`record::encode`) cut with `fragment::fragment`.
//!
//! ```text
//! cd fuzz && cargo run --example make_corpus -- corpus/frames
//! ```
//!
//! The corpus folder is not committed (`/fuzz/corpus` is ignored): this program is.

use std::path::{Path, PathBuf};

use cooploc::estimation::{Geometry, Heading, ImuSample, Method, OdometerSample, RangeSample, Snapshot};
use cooploc::protocol::MavMessage;
use cooploc::protocol::fragment::{self, Fragment};
use cooploc::protocol::record::{self, Encoding};
use cooploc::protocol::wire::{self, EpochAnnouncement, EstimateReport};
use cooploc::time::TimeUs;
use mavlink_core::{MavHeader, Message, calculate_crc};
use nalgebra::{DMatrix, Matrix3, Vector3};

fn header(system_id: u32, sequence: u8) -> MavHeader {
    MavHeader { system_id, component_id: 191, sequence }
}

/// A plausible broadcast of dimension `n`: SPD covariance, non-trivial Psi, position at states
/// 0..3 and the heading at state `n / 2` (none for n < 4).
fn snapshot(id: u16, n: usize) -> Snapshot {
    let a = DMatrix::from_fn(n, n, |r, c| ((r * 7 + c * 3) % 11) as f64 * 0.01 - 0.05);
    let covariance = &a * a.transpose() + DMatrix::from_fn(n, n, |r, c| if r == c { 0.5 + r as f64 * 0.1 } else { 0.0 });
    let psi = DMatrix::from_fn(n, n, |r, c| if r == c { 1.0 } else { ((r + 2 * c) % 5) as f64 * 0.001 });
    let position_index = [Some(0), (n > 1).then_some(1), (n > 2).then_some(2)];
    let heading = (n >= 4).then_some(Heading { yaw_rad: 0.7, index: n / 2 });
    Snapshot { id, geometry: Geometry { position_ned_m: Vector3::new(120.5, -33.25, -1.5), position_index, heading }, covariance, psi }
}

fn fragment_frames(fragments: &[Fragment], system_id: u32, seq: &mut u8) -> Vec<Vec<u8>> {
    fragments
        .iter()
        .map(|f| {
            *seq = seq.wrapping_add(1);
            wire::to_frame(header(system_id, *seq), &wire::fragment_to_message(f).expect("fragments from fragment() fit"))
        })
        .collect()
}

/// The same frame with the signed flag and a 13-byte (unchecked) signature: the CRC is made anew
/// because it covers the flags.
fn signed(frame: &[u8], msg: &MavMessage) -> Vec<u8> {
    let mut out = frame.to_vec();
    out[2] |= 0x01;
    let crc_at = out.len() - 2;
    let crc = calculate_crc(&out[1..crc_at], MavMessage::extra_crc(msg.message_id()));
    out[crc_at..].copy_from_slice(&crc.to_le_bytes());
    out.extend_from_slice(&[7, 1, 2, 3, 4, 5, 6, 0xA1, 0xA2, 0xA3, 0xA4, 0xA5, 0xA6]);
    out
}

fn main() {
    let dir: PathBuf = std::env::args_os().nth(1).map(PathBuf::from).unwrap_or_else(|| PathBuf::from("corpus/frames"));
    std::fs::create_dir_all(&dir).expect("create the corpus folder");
    let mut written = 0;
    let mut write = |name: &str, bytes: &[u8]| {
        std::fs::write(Path::new(&dir).join(name), bytes).expect("write a seed");
        written += 1;
    };
    let mut seq = 0u8;

    // State records: 16 states in f64 (3176 bytes, 14 fragments) and f32 (1608 bytes, 7), and a
    // 2-state one (one fragment).
    let big = snapshot(2, 16);
    let rec64 = record::encode(&big, Encoding::F64).expect("encode f64");
    let rec32 = record::encode(&big, Encoding::F32).expect("encode f32");
    let small = record::encode(&snapshot(3, 2), Encoding::F64).expect("encode n=2");
    assert_eq!(record::decode(2, &rec64).as_ref(), Ok(&big));
    let frags64 = fragment::fragment(2, 7, 7_000_000, &rec64).expect("fragment f64");
    let frags32 = fragment::fragment(2, 8, 8_000_000, &rec32).expect("fragment f32");
    let frags_small = fragment::fragment(3, 8, 8_000_000, &small).expect("fragment n=2");
    let f64_frames = fragment_frames(&frags64, 2, &mut seq);
    let f32_frames = fragment_frames(&frags32, 2, &mut seq);
    let small_frames = fragment_frames(&frags_small, 3, &mut seq);
    write("record16_f64_in_order", &f64_frames.concat());
    write("record16_f32_in_order", &f32_frames.concat());
    write("record2_f64_single_fragment", &small_frames.concat());
    write("fragment_single", &f32_frames[3]);
    // Reordered, with a duplicate and a fragment of another platform's record between.
    let mut shuffled: Vec<Vec<u8>> = f32_frames.iter().rev().cloned().collect();
    shuffled.insert(3, f32_frames[1].clone());
    shuffled.insert(5, small_frames[0].clone());
    write("record16_f32_reversed_dup_interleaved", &shuffled.concat());
    // The bare records, for the target's third reading (record::decode of the whole input).
    write("record16_f32_bare", &rec32);
    write("record2_f64_bare", &small);

    // One frame of every other converted message.
    let range = RangeSample { t: TimeUs(7_000_000), from: 2, to: 5, range_m: 42.125, sigma_m: 0.3 };
    let range_msg = wire::range_to_message(&range, 7);
    let epoch_msg = wire::epoch_to_message(&EpochAnnouncement {
        epoch: 7,
        t: TimeUs(7_000_000),
        announcer: 1,
        participants: vec![1, 2, 3, 5],
        state: wire::EpochState::COOPLOC_EPOCH_STATE_COLLECTING,
        digest: 0x0123_4567_89ab_cdef,
        incomplete: Vec::new(),
    })
    .expect("epoch message");
    let estimate_msg = wire::estimate_to_message(&EstimateReport {
        platform: 2,
        t: TimeUs(7_010_000),
        epoch: 7,
        method: Method::Decentralized,
        position_ned_m: Vector3::new(120.5, -33.25, -1.5),
        velocity_ned_m_s: Vector3::new(1.5, 0.25, 0.0),
        yaw_rad: 0.7,
        position_covariance_m2: Matrix3::new(0.5, 0.01, 0.0, 0.01, 0.6, 0.0, 0.0, 0.0, 0.2),
        yaw_variance_rad2: 0.001,
        nis: 2.5,
        participants: 4,
        ranges: 3,
    });
    let imu_msg = wire::imu_to_highres(&ImuSample {
        t: TimeUs(7_002_500),
        specific_force_frd_m_s2: Vector3::new(0.1, -0.05, -9.81),
        angular_rate_frd_rad_s: Vector3::new(0.001, 0.002, 0.05),
    });
    let odometry_msg = wire::odometer_to_odometry(&OdometerSample { t: TimeUs(7_005_000), speed_m_s: 1.5 }, 0.05);
    let singles: [(&str, &MavMessage); 5] = [
        ("range", &range_msg),
        ("epoch", &epoch_msg),
        ("estimate", &estimate_msg),
        ("highres_imu", &imu_msg),
        ("odometry", &odometry_msg),
    ];
    let mut mixed = Vec::new();
    for (name, msg) in singles {
        seq = seq.wrapping_add(1);
        let frame = wire::to_frame(header(2, seq), msg);
        write(name, &frame);
        write(&format!("{name}_signed"), &signed(&frame, msg));
        mixed.extend_from_slice(&frame);
    }
    // A 32-bit system id (incompatibility flag 0x02) on one frame.
    write("range_sysid32", &wire::to_frame(header(70_000, 1), &range_msg));

    // A radio's view of one epoch: announcement, ranges, garbage, a record in fragments, an
    // estimate, sensor frames.
    let mut epoch_stream = wire::to_frame(header(1, 1), &epoch_msg);
    epoch_stream.extend_from_slice(&mixed);
    epoch_stream.extend_from_slice(&[0x00, 0xFD, 0x03, 0x55]);
    for f in &small_frames {
        epoch_stream.extend_from_slice(f);
    }
    for f in &f32_frames[..2] {
        epoch_stream.extend_from_slice(f);
    }
    write("epoch_stream", &epoch_stream);

    // Seeds of the target's second reading (the operation script): op 6 with the 2-state record
    // pushed as fragment 0 twice, then op 6 with the 16-state f32 record pushed in reverse.
    let mut script = vec![6u8, 3, 8];
    script.extend_from_slice(&(small.len() as u16).to_le_bytes());
    script.extend_from_slice(&small);
    script.extend_from_slice(&[2, 0, 0]);
    script.extend_from_slice(&[6, 2, 8]);
    script.extend_from_slice(&(rec32.len() as u16).to_le_bytes());
    script.extend_from_slice(&rec32);
    script.push(frags32.len() as u8);
    script.extend((0..frags32.len() as u8).rev());
    // and op 2 (synthetic fragments) for two fragments of one 300-byte record, op 0, op 1.
    script.extend_from_slice(&[2, 0, 1, 3, 43, 1, 9, 0, 2, 0, 1, 3, 43, 1, 9, 1, 0, 4, 1]);
    write("script_records", &script);

    println!("{written} seeds in {}", dir.display());
}
