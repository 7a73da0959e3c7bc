//! The cooploc dialect on the wire: golden bytes for every custom message, and a cross-check in
//! both directions with pymavlink (an independent implementation generated from the same XML).
//!
//! Regenerate the golden file after a deliberate change of the dialect:
//! `COOPLOC_BLESS=1 cargo test --release --test dialect golden`.

mod common;

use std::path::{Path, PathBuf};
use std::process::Command;

use cooploc::protocol::MavMessage;
use cooploc::protocol::dialect::cooploc::{
    COOPLOC_EPOCH_DATA, COOPLOC_ESTIMATE_DATA, COOPLOC_RANGE_BEARING_DATA, COOPLOC_RANGE_DATA, COOPLOC_STATE_FRAGMENT_DATA,
    COOPLOC_STORE_FRAGMENT_DATA, CooplocEpochState, CooplocMethod,
};
use cooploc::protocol::wire::{from_frame, to_frame};
use mavlink_core::MavHeader;
use serde_json::{Value, json};

const HEADER: MavHeader = MavHeader { system_id: 7, component_id: 191, sequence: 42 };

/// One message of each custom kind, with field values that f32 represents exactly, and the same
/// fields by their XML names.
fn cases() -> Vec<(&'static str, MavMessage, Value)> {
    let data: Vec<u8> = (0..232u32).map(|i| (i * 7 % 256) as u8).collect();
    let mut participants = [0u16; 64];
    participants[..3].copy_from_slice(&[1, 2, 3]);
    vec![
        (
            "COOPLOC_STATE_FRAGMENT",
            MavMessage::COOPLOC_STATE_FRAGMENT(COOPLOC_STATE_FRAGMENT_DATA {
                time_usec: 100_000_000,
                epoch: 100,
                record_crc32: 0xDEAD_BEEF,
                record_len: 3176,
                platform: 2,
                frag_index: 3,
                frag_count: 14,
                data_len: 232,
                data: data.clone().try_into().unwrap(),
            }),
            json!({"time_usec": 100_000_000u64, "epoch": 100, "record_crc32": 0xDEAD_BEEFu32, "record_len": 3176, "platform": 2,
                   "frag_index": 3, "frag_count": 14, "data_len": 232, "data": data}),
        ),
        (
            "COOPLOC_RANGE",
            MavMessage::COOPLOC_RANGE(COOPLOC_RANGE_DATA {
                time_usec: 1_000_000,
                epoch: 1,
                distance: 212.375,
                sigma: 0.125,
                from_platform: 1,
                to_platform: 3,
            }),
            json!({"time_usec": 1_000_000, "epoch": 1, "distance": 212.375, "sigma": 0.125, "from_platform": 1, "to_platform": 3}),
        ),
        (
            "COOPLOC_RANGE_BEARING",
            MavMessage::COOPLOC_RANGE_BEARING(COOPLOC_RANGE_BEARING_DATA {
                time_usec: 1_248_444_189_599_000,
                range: 3.75,
                bearing: -0.25,
                observer: 1,
                target: 14,
                target_kind: 1,
            }),
            json!({"time_usec": 1_248_444_189_599_000u64, "range": 3.75, "bearing": -0.25, "observer": 1, "target": 14, "target_kind": 1}),
        ),
        (
            "COOPLOC_ESTIMATE",
            MavMessage::COOPLOC_ESTIMATE(COOPLOC_ESTIMATE_DATA {
                time_usec: 380_000_000,
                epoch: 380,
                x: 2250.5,
                y: 1000.25,
                z: -0.5,
                vx: 8.5,
                vy: 4.75,
                vz: 0.0,
                yaw: 0.5,
                pos_covariance: [4.0, 0.5, 0.0, 3.0, 0.0, 0.25],
                yaw_variance: 0.0009765625,
                nis: 1.5,
                platform: 3,
                method: CooplocMethod::COOPLOC_METHOD_DECENTRALIZED,
                participants: 3,
                ranges: 3,
            }),
            json!({"time_usec": 380_000_000u64, "epoch": 380, "x": 2250.5, "y": 1000.25, "z": -0.5, "vx": 8.5, "vy": 4.75, "vz": 0.0,
                   "yaw": 0.5, "pos_covariance": [4.0, 0.5, 0.0, 3.0, 0.0, 0.25], "yaw_variance": 0.0009765625, "nis": 1.5,
                   "platform": 3, "method": 2, "participants": 3, "ranges": 3}),
        ),
        (
            "COOPLOC_EPOCH",
            MavMessage::COOPLOC_EPOCH(COOPLOC_EPOCH_DATA {
                time_usec: 200_000_000,
                epoch: 200,
                announcer: 1,
                participants,
                count: 3,
                state: CooplocEpochState::COOPLOC_EPOCH_STATE_APPLIED,
                digest: 0x0123_4567_89ab_cdef,
            }),
            json!({"time_usec": 200_000_000u64, "epoch": 200, "announcer": 1, "count": 3, "participants": participants.to_vec(), "state": 1,
                   "digest": 0x0123_4567_89ab_cdefu64}),
        ),
        (
            "COOPLOC_EPOCH",
            MavMessage::COOPLOC_EPOCH(COOPLOC_EPOCH_DATA {
                time_usec: 210_000_000,
                epoch: 210,
                announcer: 3,
                participants,
                count: 2,
                state: CooplocEpochState::COOPLOC_EPOCH_STATE_STORE_WANTED,
                digest: 0x0fed_cba9_8765_4321,
            }),
            json!({"time_usec": 210_000_000u64, "epoch": 210, "announcer": 3, "count": 2, "participants": participants.to_vec(), "state": 4,
                   "digest": 0x0fed_cba9_8765_4321u64}),
        ),
        (
            "COOPLOC_STORE_FRAGMENT",
            MavMessage::COOPLOC_STORE_FRAGMENT(COOPLOC_STORE_FRAGMENT_DATA {
                time_usec: 210_000_000,
                epoch: 210,
                record_crc32: 0x0BAD_F00D,
                record_len: 6243,
                platform: 1,
                frag_index: 26,
                frag_count: 27,
                data_len: 211,
                data: data.clone().try_into().unwrap(),
            }),
            json!({"time_usec": 210_000_000u64, "epoch": 210, "record_crc32": 0x0BAD_F00Du32, "record_len": 6243, "platform": 1,
                   "frag_index": 26, "frag_count": 27, "data_len": 211, "data": data}),
        ),
    ]
}

fn golden_path() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/golden/dialect_frames.txt")
}

fn hex(bytes: &[u8]) -> String {
    bytes.iter().map(|b| format!("{b:02x}")).collect()
}

fn unhex(s: &str) -> Vec<u8> {
    (0..s.len()).step_by(2).map(|i| u8::from_str_radix(&s[i..i + 2], 16).unwrap()).collect()
}

fn golden() -> Vec<(String, String)> {
    std::fs::read_to_string(golden_path())
        .unwrap()
        .lines()
        .filter(|l| !l.starts_with('#') && !l.trim().is_empty())
        .map(|l| {
            let (name, hex) = l.split_once(' ').unwrap();
            (name.to_string(), hex.trim().to_string())
        })
        .collect()
}

#[test]
fn golden_bytes_and_rust_round_trip() {
    let encoded: Vec<(String, String)> =
        cases().into_iter().map(|(name, msg, _)| (name.to_string(), hex(&to_frame(HEADER, &msg)))).collect();
    if std::env::var_os("COOPLOC_BLESS").is_some() {
        let mut text = String::from(
            "# MAVLink 2 frames of every cooploc message (sysid 7, compid 191, seq 42), from tests/dialect.rs.\n\
             # Regenerate: COOPLOC_BLESS=1 cargo test --release --test dialect golden\n",
        );
        for (name, h) in &encoded {
            text.push_str(&format!("{name} {h}\n"));
        }
        std::fs::write(golden_path(), text).unwrap();
    }
    assert_eq!(encoded, golden(), "frames differ from tests/golden/dialect_frames.txt");
    for (name, msg, _) in cases() {
        let (header, back) = from_frame(&to_frame(HEADER, &msg)).unwrap();
        assert_eq!(header, HEADER, "{name}");
        assert_eq!(back, msg, "{name}");
    }
}

/// Rust-encoded frames decode in pymavlink to the same fields; pymavlink-encoded frames are the
/// same bytes (the golden ones) and decode in Rust to the same message.
#[test]
fn pymavlink_agrees_in_both_directions() {
    let Some(python) = common::python("the pymavlink cross-check") else { return };
    let root = Path::new(env!("CARGO_MANIFEST_DIR"));
    let cases = cases();
    let input: Vec<Value> = cases
        .iter()
        .map(|(name, msg, fields)| {
            json!({"name": name, "sysid": HEADER.system_id, "compid": HEADER.component_id, "seq": HEADER.sequence,
                   "fields": fields, "hex": hex(&to_frame(HEADER, msg))})
        })
        .collect();
    let dir = std::env::temp_dir().join(format!("cooploc-dialect-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let cases_path = dir.join("cases.json");
    std::fs::write(&cases_path, serde_json::to_string(&input).unwrap()).unwrap();
    let out = Command::new(&python)
        .arg(root.join("tests/python/mavlink_cross.py"))
        .arg(root.join("dialects/cooploc.xml"))
        .arg(&cases_path)
        .output()
        .expect("running the pymavlink cross-check");
    assert!(out.status.success(), "pymavlink script failed: {}", String::from_utf8_lossy(&out.stderr));
    let report: Value = serde_json::from_slice(&out.stdout).unwrap();
    let golden = golden();
    assert_eq!(golden.len(), cases.len());
    for (((name, msg, _), result), (gold_name, gold)) in cases.iter().zip(report["cases"].as_array().unwrap()).zip(&golden) {
        assert_eq!(result["name"], *name);
        assert_eq!(gold_name, name);
        assert!(result["decoded_equal"].as_bool().unwrap(), "{name}: pymavlink decoded differently: {}", result["mismatches"]);
        let py_hex = result["python_hex"].as_str().unwrap();
        assert_eq!(py_hex, gold, "{name}: pymavlink's frame differs from the golden bytes");
        let (_, back) = from_frame(&unhex(py_hex)).unwrap();
        assert_eq!(&back, msg, "{name}: Rust decodes pymavlink's frame differently");
    }
    let _ = std::fs::remove_dir_all(&dir);
}
