//! MAVLink 2 signing against an independent implementation (pymavlink, as MAVProxy uses it):
//! frames pymavlink signs with the team's passphrase are accepted by cooploc's verifier, and the
//! frames cooploc signs are accepted by pymavlink; a wrong key or no signature is refused by both.

mod common;

use std::process::Command;
use std::time::{SystemTime, UNIX_EPOCH};

use cooploc::protocol::MavMessage;
use cooploc::protocol::dialect::cooploc::{MavAutopilot, MavType};
use cooploc::protocol::signing::{Refusal, Signer, TeamKey, Verifier};
use cooploc::protocol::wire;
use mavlink_core::MavHeader;

fn hex(bytes: &[u8]) -> String {
    bytes.iter().map(|b| format!("{b:02x}")).collect()
}

fn unhex(s: &str) -> Vec<u8> {
    (0..s.len()).step_by(2).map(|i| u8::from_str_radix(&s[i..i + 2], 16).unwrap()).collect()
}

#[test]
fn cooploc_and_pymavlink_accept_each_others_signed_frames() {
    let Some(python) = common::python("the pymavlink signing check") else { return };
    let now_us = SystemTime::now().duration_since(UNIX_EPOCH).unwrap().as_micros() as u64;
    let heartbeat = wire::heartbeat(MavType::MAV_TYPE_ONBOARD_CONTROLLER, MavAutopilot::MAV_AUTOPILOT_INVALID);
    let header = MavHeader { system_id: 2, component_id: 191, sequence: 0 };
    let ours = Signer::new(TeamKey::from_passphrase("cooploc team"), 1, 0).frame(header, &heartbeat, now_us);
    let wrong_key = Signer::new(TeamKey::from_passphrase("someone else"), 1, 0).frame(header, &heartbeat, now_us);
    let unsigned = wire::to_frame(header, &heartbeat);
    let root = env!("CARGO_MANIFEST_DIR");
    let out = Command::new(python)
        .arg(format!("{root}/tests/python/signing_interop.py"))
        .args(["cooploc team", &hex(&ours), &hex(&wrong_key), &hex(&unsigned)])
        .output()
        .unwrap();
    let stdout = String::from_utf8_lossy(&out.stdout);
    assert!(out.status.success(), "{stdout} {}", String::from_utf8_lossy(&out.stderr));
    let lines: Vec<&str> = stdout.lines().collect();
    assert_eq!(lines.len(), 4, "{stdout}");
    assert_eq!(lines[1], "ok HEARTBEAT 2", "pymavlink accepts cooploc's signature");
    assert!(lines[2].starts_with("refused"), "pymavlink refuses another key: {}", lines[2]);
    assert!(lines[3].starts_with("refused"), "pymavlink refuses an unsigned frame: {}", lines[3]);

    let theirs = unhex(lines[0].strip_prefix("frame ").unwrap());
    let mut v = Verifier::new(TeamKey::from_passphrase("cooploc team"));
    let got = v.datagram(&theirs, now_us);
    assert!(got.refused.is_empty(), "{:?}", got.refused);
    assert_eq!(got.frames.len(), 1);
    assert_eq!((got.frames[0].0.system_id, got.frames[0].0.component_id), (7, 191));
    assert!(matches!(got.frames[0].1, MavMessage::HEARTBEAT(_)));
    assert_eq!(v.datagram(&theirs, now_us).refused, vec![Refusal::Replayed]);
    let mut other = Verifier::new(TeamKey::from_passphrase("someone else"));
    assert_eq!(other.datagram(&theirs, now_us).refused, vec![Refusal::BadSignature]);
}
