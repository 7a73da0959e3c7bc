use super::*;
use crate::protocol::wire;

const T0_US: u64 = 1_795_000_000_000_000;

fn header(system_id: u32) -> MavHeader {
    MavHeader { system_id, component_id: 191, sequence: 7 }
}

fn heartbeat() -> MavMessage {
    wire::heartbeat(
        crate::protocol::dialect::cooploc::MavType::MAV_TYPE_ONBOARD_CONTROLLER,
        crate::protocol::dialect::cooploc::MavAutopilot::MAV_AUTOPILOT_INVALID,
    )
}

#[test]
fn keys_from_a_passphrase_hex_or_file() {
    // SHA-256("secret"), as MAVProxy's `signing setup secret` makes it
    let k = TeamKey::from_passphrase("secret");
    let hex = "2bb80d537b1da3e38bd30361aa855686bde0eacd7162fef6a25fe97bf527a25b";
    assert_eq!(TeamKey::from_hex(hex), Some(k.clone()));
    assert_eq!(TeamKey::from_hex("2bb8"), None);
    let dir = std::env::temp_dir().join(format!("cooploc-key-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    for (text, want) in [(format!("{hex}\n"), k.clone()), ("  secret  \nignored".into(), k.clone())] {
        std::fs::write(dir.join("k"), text).unwrap();
        assert_eq!(TeamKey::from_file(&dir.join("k")).unwrap(), want);
    }
    std::fs::write(dir.join("k"), "\n").unwrap();
    assert!(matches!(TeamKey::from_file(&dir.join("k")), Err(KeyError::Empty(_))));
    assert!(matches!(TeamKey::from_file(&dir.join("missing")), Err(KeyError::Io { .. })));
    assert_eq!(format!("{k:?}"), "TeamKey(..)", "a key is never printed");
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn generated_keys_and_passphrases_differ_and_a_passphrase_is_never_read_as_hex() {
    let (a, b) = (TeamKey::generate().unwrap(), TeamKey::generate().unwrap());
    assert_ne!(a.bytes(), b.bytes());
    let (p, q) = (TeamKey::new_passphrase().unwrap(), TeamKey::new_passphrase().unwrap());
    assert_ne!(p, q);
    assert_eq!(p.len(), 48);
    assert!(p.bytes().all(|c| c.is_ascii_lowercase() || c.is_ascii_digit()), "{p}");
    assert!(TeamKey::from_hex(&p).is_none());
    // A key file holding it is that passphrase's key (MAVProxy's `signing setup`).
    let path = std::env::temp_dir().join(format!("cooploc-keygen-{}", std::process::id()));
    std::fs::write(&path, format!("{p}\n")).unwrap();
    assert_eq!(TeamKey::from_file(&path).unwrap().bytes(), TeamKey::from_passphrase(&p).bytes());
    let _ = std::fs::remove_file(&path);
}

#[test]
fn a_signed_frame_is_accepted_once_and_its_bytes_are_the_frame_plus_13() {
    let key = TeamKey::from_passphrase("team");
    let mut signer = Signer::new(key.clone(), 3, 0);
    let mut v = Verifier::new(key);
    let unsigned = wire::to_frame(header(2), &heartbeat());
    let signed = signer.frame(header(2), &heartbeat(), T0_US);
    assert_eq!(signed.len(), unsigned.len() + 13);
    assert_eq!(signed[2], IFLAG_SIGNED);
    assert_eq!(signed[signed.len() - 13], 3, "the link id");
    let got = v.datagram(&signed, T0_US);
    assert_eq!((got.frames.len(), got.refused.len()), (1, 0));
    assert_eq!(got.frames[0].0, header(2));
    assert_eq!(got.frames[0].1, heartbeat());
    assert_eq!(got.spans, vec![0..signed.len()]);
    // the same bytes again: a replay
    assert_eq!(v.datagram(&signed, T0_US).refused, vec![Refusal::Replayed]);
    // the reader of unsigned frames still reads a signed one (the ground station's tools do)
    assert_eq!(wire::from_frame(&signed).unwrap().1, heartbeat());
    // timestamps increase even when the clock does not
    let a = signer.last_timestamp();
    let again = signer.frame(header(2), &heartbeat(), T0_US - 5_000_000);
    assert_eq!(signer.last_timestamp(), a + 1);
    assert_eq!(v.datagram(&again, T0_US).frames.len(), 1);
    assert_eq!(v.counters.accepted, 2);
    assert_eq!(v.counters.replayed, 1);
}

#[test]
fn unsigned_forged_altered_and_stale_frames_are_refused_and_counted() {
    let key = TeamKey::from_passphrase("team");
    let mut v = Verifier::new(key.clone());
    let unsigned = wire::to_frame(header(2), &heartbeat());
    assert_eq!(v.datagram(&unsigned, T0_US).refused, vec![Refusal::Unsigned]);
    let mut other = Signer::new(TeamKey::from_passphrase("not the team"), 0, 0);
    assert_eq!(v.datagram(&other.frame(header(2), &heartbeat(), T0_US), T0_US).refused, vec![Refusal::BadSignature]);
    // a genuine frame with one byte of its header changed (the sender's system id) and its CRC
    // made right again: the signature covers the header
    let mut signer = Signer::new(key.clone(), 0, 0);
    let genuine = signer.frame(header(2), &heartbeat(), T0_US);
    let mut forged = genuine.clone();
    forged[5] = 9;
    let n = forged.len() - 13;
    let crc = crc_x25(&forged[1..n - 2], <MavMessage as Message>::extra_crc(0));
    forged[n - 2..n].copy_from_slice(&crc.to_le_bytes());
    assert_eq!(v.datagram(&forged, T0_US).refused, vec![Refusal::BadSignature]);
    // a CRC that does not match: not a frame at all
    let mut broken = genuine.clone();
    broken[n - 1] ^= 0xff;
    assert_eq!(v.datagram(&broken, T0_US).refused, vec![Refusal::Malformed]);
    assert!(v.datagram(&genuine, T0_US).refused.is_empty());
    // a new stream signed two minutes ago (a recording replayed to a fresh node): stale
    let mut fresh = Verifier::new(key.clone());
    let mut old = Signer::new(key, 1, 0);
    let frame = old.frame(header(3), &heartbeat(), T0_US - 120_000_000);
    assert_eq!(fresh.datagram(&frame, T0_US).refused, vec![Refusal::Stale]);
    let c = &v.counters;
    assert_eq!((c.unsigned, c.bad_signature, c.malformed, c.accepted), (1, 2, 1, 1));
    assert_eq!(c.refused(), 4);
}

#[test]
fn a_datagram_of_several_frames_and_garbage() {
    let key = TeamKey::from_passphrase("team");
    let mut signer = Signer::new(key.clone(), 0, 0);
    let mut v = Verifier::new(key);
    let mut bytes = vec![0x00, 0x13, 0x37];
    bytes.extend(signer.frame(header(1), &heartbeat(), T0_US));
    bytes.extend(wire::to_frame(header(1), &heartbeat()));
    bytes.extend(signer.frame(header(1), &heartbeat(), T0_US));
    bytes.extend([0xfd, 0x09]); // a cut frame
    let got = v.datagram(&bytes, T0_US);
    assert_eq!(got.frames.len(), 2);
    assert_eq!(got.refused, vec![Refusal::Malformed, Refusal::Unsigned, Refusal::Malformed]);
    for span in &got.spans {
        assert_eq!(wire::from_frame(&bytes[span.clone()]).unwrap().1, heartbeat(), "each span is one whole frame");
    }
}

#[test]
fn the_stream_table_is_bounded() {
    let key = TeamKey::from_passphrase("team");
    let mut v = Verifier::new(key.clone());
    for link in 0..=255u8 {
        for sys in 1..=5u32 {
            let mut s = Signer::new(key.clone(), link, 0);
            assert_eq!(v.datagram(&s.frame(header(sys), &heartbeat(), T0_US), T0_US).frames.len(), 1);
        }
    }
    assert_eq!(v.streams.len(), MAX_STREAMS);
    assert_eq!(v.counters.accepted, 256 * 5);
}

/// CRC-16/MCRF4XX (MAVLink's X.25) of `bytes` then `extra`.
fn crc_x25(bytes: &[u8], extra: u8) -> u16 {
    let mut crc: u16 = 0xffff;
    for &b in bytes.iter().chain(std::iter::once(&extra)) {
        let mut tmp = b ^ (crc & 0xff) as u8;
        tmp ^= tmp << 4;
        crc = (crc >> 8) ^ (u16::from(tmp) << 8) ^ (u16::from(tmp) << 3) ^ (u16::from(tmp) >> 4);
    }
    crc
}

/// Frames overtaken on the way (UDP jitter) are taken once each; a repeat of any of them, and a
/// frame older than the reordering window, are refused as replays.
#[test]
fn reordered_frames_are_accepted_once_and_replays_still_refused() {
    let key = TeamKey::from_passphrase("team");
    let mut signer = Signer::new(key.clone(), 1, 0);
    let mut v = Verifier::new(key);
    // 20 frames 10 ms apart, delivered in a scrambled order (up to 100 ms late).
    let frames: Vec<Vec<u8>> = (0..20).map(|k| signer.frame(header(1), &heartbeat(), T0_US + k * 10_000)).collect();
    let order = [3, 0, 1, 2, 7, 4, 5, 6, 12, 8, 9, 10, 11, 19, 13, 14, 15, 16, 17, 18];
    for &k in &order {
        assert!(v.datagram(&frames[k], T0_US + 300_000).refused.is_empty(), "frame {k}");
    }
    assert_eq!(v.counters.accepted, 20);
    for f in &frames {
        assert_eq!(v.datagram(f, T0_US + 300_000).refused, vec![Refusal::Replayed]);
    }
    // A frame held back longer than the window: refused, though never seen.
    let late = signer.frame(header(1), &heartbeat(), T0_US + 400_000);
    let newer = signer.frame(header(1), &heartbeat(), T0_US + 400_000 + 2_500_000);
    assert!(v.datagram(&newer, T0_US + 3_000_000).refused.is_empty());
    assert_eq!(v.datagram(&late, T0_US + 3_000_000).refused, vec![Refusal::Replayed]);
    assert_eq!(v.counters.replayed, 21);
}

/// A node whose clock stepped back across a restart (no RTC, a bad NTP step) resumes above its
/// saved timestamp and is accepted; without the state its frames are refused as replays.
#[test]
fn a_restart_with_the_clock_behind_is_accepted_with_the_saved_state_only() {
    let key = TeamKey::from_passphrase("team");
    let mut verifier = Verifier::new(key.clone());
    let (before, after) = (1_800_000_000_000_000u64, 1_800_000_000_000_000u64 - 30_000_000); // 30 s back
    let mut first = Signer::new(key.clone(), 3, 0);
    for k in 0..10 {
        let f = first.frame(header(3), &heartbeat(), before + k * 100_000);
        assert_eq!(verifier.datagram(&f, before + k * 100_000).frames.len(), 1);
    }
    let saved = parse_state(&state_text(&first)).unwrap();
    assert!(saved > first.last_timestamp());
    // Restarted without the state: the clock is 30 s behind the stream's last timestamp.
    let mut forgetful = Signer::new(key.clone(), 3, 0);
    let f = forgetful.frame(header(3), &heartbeat(), after);
    assert_eq!(verifier.datagram(&f, before + 1_000_000).refused, vec![Refusal::Replayed]);
    // Restarted from the state: every frame accepted, each once.
    let mut resumed = Signer::new(key, 3, saved);
    for k in 0..10 {
        let f = resumed.frame(header(3), &heartbeat(), after + k * 100_000);
        let got = verifier.datagram(&f, before + 1_000_000 + k * 100_000);
        assert_eq!((got.frames.len(), got.refused.len()), (1, 0), "frame {k}");
        assert_eq!(verifier.datagram(&f, before + 1_000_000 + k * 100_000).refused, vec![Refusal::Replayed]);
    }
    for bad in ["", "abc", "-5", "281474976710656"] {
        assert!(parse_state(bad).unwrap_err().contains(bad), "{bad:?}");
    }
}
