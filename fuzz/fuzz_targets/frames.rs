//! Fuzz target over cooploc's MAVLink frame parser, the wire conversions, the fragment
//! reassembler and the state-record decoder. See `fuzz/README.md`.
//!
//! Every input is read three ways, all in one run:
//!
//! 1. **A MAVLink byte stream.** `wire::from_frame` on the whole input (the API as a caller uses
//!    it: the first valid frame after any garbage), then on every candidate frame that starts at
//!    a 0xFD byte (the candidate's length taken from its header: 1 + 9 header bytes, 3 more with
//!    the 32-bit system id flag 0x02, + payload + 2 CRC, + 13 with the signed flag 0x01). A
//!    candidate that parses is skipped over whole; one that does not is also decoded
//!    *checksum-blind* (its payload handed to the dialect's `parse` under its message id), so
//!    that the conversions are reached without the fuzzer having to forge a CRC-16. Every
//!    COOPLOC_STATE_FRAGMENT goes through `wire::fragment_from_message` into one
//!    `Reassembler::new(8)`; every completed record goes to `record::decode`; COOPLOC_RANGE,
//!    COOPLOC_EPOCH, COOPLOC_ESTIMATE, HIGHRES_IMU and ODOMETRY go through their
//!    `wire::*_from_message` conversions.
//! 2. **A script of reassembler operations** (format below), on a second `Reassembler::new(8)`,
//!    with fragments built directly from the bytes, so that reassembly (reordering, duplicates,
//!    eviction, supersession, expiry, CRC-32 failures, completion) is reached without frames.
//! 3. **A state record**: `record::decode` of the whole input.
//!
//! Besides "no panic", the target checks properties (an `assert!` that fails is a finding):
//! each accepted message converts back to the wire and reads back to the same value (as sent);
//! each decoded record re-encodes to the same bytes (but for the yaw of a record without a
//! heading) and decodes to the same snapshot; a record cut by `fragment::fragment` and pushed in
//! any order, with duplicates, comes out exactly once and unchanged; the reassembler never holds
//! more than its bound, and hands out only records whose CRC-32, length, platform and epoch are
//! those of the fragments.
//!
//! Operation script (interpretation 2): a sequence of operations, each an opcode byte `op`,
//! dispatched on `op % 8`, and its operands; a missing operand byte reads as 0, a missing data
//! byte ends the script.
//!
//! | op % 8 | operation | operands |
//! |---|---|---|
//! | 0 | `expire_before(e % 8)` | e |
//! | 1 | `take_dropped` | |
//! | 2, 3 | synthetic fragment of a deterministic record | flags, platform % 4, epoch % 8, len u16, seed, index, [count] |
//! | 4, 5 | raw fragment | platform % 4, epoch % 8, time % 2, crc u32, len u16, index, count, data_len, data |
//! | 6 | whole record from the input, cut and pushed in any order | platform % 4, epoch % 8, len u16, record bytes (zero-padded), pushes n, n index bytes |
//! | 7 | fragment of consistent shape with data and CRC from the input | platform % 4, epoch % 8, time % 2, crc u32, len u16 (1 + len % 1200), index, data |
//!
//! Synthetic flags: bit 0 time_usec, bit 1 full u16 length (else 1 + len % 700), bit 2 raw
//! index (else index % count), bit 3 corrupt the CRC, bit 4 raw count byte follows, bit 5 one
//! data byte short, bit 6 flip the first data byte.

#![no_main]

use cooploc::protocol::dialect::cooploc::MavMessage;
use cooploc::protocol::fragment::{self, FRAGMENT_DATA, Fragment, MAX_RECORD_LEN, Payload, Pushed, Reassembler};
use cooploc::protocol::record::{self, Encoding};
use cooploc::protocol::wire;
use libfuzzer_sys::fuzz_target;
use mavlink_core::{MavlinkVersion, Message};

/// Reassembler bound used by both interpretations.
const MAX_PARTIALS: usize = 8;
/// Operations read from one input (interpretation 2).
const MAX_OPS: usize = 512;

fuzz_target!(|data: &[u8]| {
    let mut frames = Reassembler::new(MAX_PARTIALS);
    stream(data, &mut frames);
    drain(&mut frames);

    let mut ops = Reassembler::new(MAX_PARTIALS);
    script(data, &mut ops);
    drain(&mut ops);

    check_record(0, data);
});

// ---- interpretation 1: a MAVLink byte stream ----

fn stream(data: &[u8], re: &mut Reassembler) {
    if let Ok((_, msg)) = wire::from_frame(data) {
        handle(&msg, re);
    }
    let mut i = 0;
    while i < data.len() {
        let Some(off) = data[i..].iter().position(|&b| b == 0xFD) else { break };
        i += off;
        let rest = &data[i..];
        if rest.len() < 10 {
            // Too short for a header: the reader must report the end, not panic.
            let _ = wire::from_frame(rest);
            break;
        }
        let payload_len = rest[1] as usize;
        let incompat = rest[2];
        let header = if incompat & 0x02 != 0 { 12 } else { 9 };
        let signature = if incompat & 0x01 != 0 { 13 } else { 0 };
        let frame_len = 1 + header + payload_len + 2 + signature;
        let candidate = &rest[..frame_len.min(rest.len())];
        if let Ok((_, msg)) = wire::from_frame(candidate) {
            handle(&msg, re);
            i += candidate.len();
            continue;
        }
        // Checksum-blind: what the conversions would make of this payload had the CRC matched.
        if rest.len() >= 1 + header {
            let id_at = 1 + header - 3;
            let msgid = u32::from_le_bytes([rest[id_at], rest[id_at + 1], rest[id_at + 2], 0]);
            let payload = &rest[1 + header..(1 + header + payload_len).min(rest.len())];
            if let Ok(msg) = MavMessage::parse(MavlinkVersion::V2, msgid, payload) {
                handle(&msg, re);
            }
        }
        i += 1;
    }
}

fn handle(msg: &MavMessage, re: &mut Reassembler) {
    let _ = wire::message_id(msg);
    match msg {
        MavMessage::COOPLOC_STATE_FRAGMENT(d) => {
            if let Ok(f) = wire::fragment_from_message(d) {
                assert!(!f.data.is_empty() && f.data.len() <= FRAGMENT_DATA);
                let Ok(MavMessage::COOPLOC_STATE_FRAGMENT(back)) = wire::fragment_to_message(&f) else {
                    panic!("fragment_to_message made another message")
                };
                assert_eq!(wire::fragment_from_message(&back).as_ref(), Ok(&f), "fragment round trip");
                push(re, &f);
            }
        }
        MavMessage::COOPLOC_RANGE(d) => {
            if let Ok((epoch, r)) = wire::range_from_message(d) {
                assert!(r.range_m.is_finite() && r.range_m >= 0.0 && r.sigma_m.is_finite() && r.sigma_m > 0.0);
                assert_ne!(r.from, r.to);
                let MavMessage::COOPLOC_RANGE(back) = wire::range_to_message(&r, epoch) else { panic!("range_to_message") };
                assert_eq!(wire::range_from_message(&back), Ok((epoch, wire::range_as_sent(&r))), "range round trip");
            }
        }
        MavMessage::COOPLOC_EPOCH(_) | MavMessage::COOPLOC_EPOCH_SET(_) => {
            if let Some(Ok(a)) = wire::epoch_of(msg) {
                assert!(a.participants.len() <= wire::MAX_PARTICIPANTS && a.incomplete.len() <= wire::MAX_INCOMPLETE);
                let back = wire::epoch_to_message(&a).expect("an announcement read from the wire fits the wire");
                let back = wire::epoch_of(&back).expect("an epoch announcement").expect("valid");
                // The list form carries no incomplete records: the rest must come back as it was.
                let sent_as_list = back.incomplete.is_empty() && !a.incomplete.is_empty();
                if !sent_as_list {
                    assert_eq!(back, a, "epoch round trip");
                }
            }
        }
        MavMessage::COOPLOC_ESTIMATE(d) => {
            if let Ok(e) = wire::estimate_from_message(d) {
                assert!(e.position_ned_m.iter().chain(e.velocity_ned_m_s.iter()).all(|v| v.is_finite()));
                assert!(e.position_covariance_m2.iter().all(|v| v.is_finite()));
                assert!(e.yaw_rad.is_finite() && e.yaw_variance_rad2 >= 0.0);
                let MavMessage::COOPLOC_ESTIMATE(back) = wire::estimate_to_message(&e) else { panic!("estimate_to_message") };
                let mut again = wire::estimate_from_message(&back).expect("estimate round trip");
                let mut first = e;
                // NaN means "no joint update yet" and is not equal to itself.
                if first.nis.is_nan() && again.nis.is_nan() {
                    first.nis = 0.0;
                    again.nis = 0.0;
                }
                assert_eq!(again, first, "estimate round trip");
            }
        }
        MavMessage::COOPLOC_STORE_HELD(d) => {
            if let Ok(h) = wire::store_held_from_message(d) {
                let MavMessage::COOPLOC_STORE_HELD(back) = wire::store_held_to_message(&h) else { panic!("store_held_to_message") };
                assert_eq!(wire::store_held_from_message(&back), Ok(h), "store held round trip");
            }
        }
        MavMessage::HIGHRES_IMU(d) => {
            if let Ok(s) = wire::imu_from_highres(d) {
                let back = wire::imu_to_highres(&s);
                let MavMessage::HIGHRES_IMU(back) = back else { panic!("imu_to_highres") };
                assert_eq!(wire::imu_from_highres(&back), Ok(wire::imu_as_sent(&s)), "HIGHRES_IMU round trip");
            }
        }
        MavMessage::ODOMETRY(d) => {
            if let Ok(s) = wire::odometer_from_odometry(d) {
                assert!(s.speed_m_s.is_finite() && s.speed_m_s.abs() <= 200.0);
                let MavMessage::ODOMETRY(back) = wire::odometer_to_odometry(&s, 0.5) else { panic!("odometer_to_odometry") };
                assert_eq!(wire::odometer_from_odometry(&back), Ok(wire::odometer_as_sent(&s)), "ODOMETRY round trip");
            }
        }
        _ => {}
    }
}

// ---- the reassembler, shared by interpretations 1 and 2 ----

/// Pushes one fragment, checks the reassembler's promises, decodes a completed record.
fn push(re: &mut Reassembler, f: &Fragment) -> Pushed {
    let pushed = re.push(f);
    assert!(re.in_progress() <= MAX_PARTIALS, "{} records in progress, bound {MAX_PARTIALS}", re.in_progress());
    if let Pushed::Complete(r) = &pushed {
        assert_eq!((r.platform, r.epoch, r.time_usec), (f.platform, f.epoch, f.time_usec));
        assert_eq!(r.bytes.len(), f.record_len as usize);
        assert!(!r.bytes.is_empty() && r.bytes.len() <= MAX_RECORD_LEN);
        assert_eq!(crc32fast::hash(&r.bytes), f.record_crc32);
        let o = f.index as usize * FRAGMENT_DATA;
        assert_eq!(&r.bytes[o..o + f.data.len()], &f.data[..], "the completing fragment's data is in the record");
        check_record(r.platform, &r.bytes);
    }
    pushed
}

fn drain(re: &mut Reassembler) {
    for d in re.take_dropped() {
        assert!(d.count >= 1 && d.received <= d.count, "{d:?}");
    }
    assert!(re.take_dropped().is_empty());
}

/// `record::decode`, and if it accepts the bytes: encode(decode(bytes)) gives the bytes back
/// (the yaw of a record without a heading is written as 0) and decodes to the same snapshot.
fn check_record(platform: u16, bytes: &[u8]) {
    let Ok(s) = record::decode(platform, bytes) else { return };
    let n = s.dim();
    assert!((1..=record::MAX_DIM).contains(&n));
    let encoding = if bytes[1] == 0 { Encoding::F64 } else { Encoding::F32 };
    assert_eq!(bytes.len(), record::record_len(n, encoding));
    let again = record::encode(&s, encoding).expect("a decoded snapshot encodes");
    let mut expected = bytes.to_vec();
    if s.geometry.heading.is_none() {
        expected[32..40].copy_from_slice(&0.0f64.to_le_bytes());
    }
    assert_eq!(again, expected, "encode(decode(record)) differs from the record");
    assert_eq!(record::decode(platform, &again), Ok(s), "decode(encode(snapshot)) differs");
}

// ---- interpretation 2: a script of reassembler operations ----

struct Reader<'a> {
    data: &'a [u8],
}

impl Reader<'_> {
    fn next(&mut self) -> Option<u8> {
        let (&b, rest) = self.data.split_first()?;
        self.data = rest;
        Some(b)
    }
    fn u8(&mut self) -> u8 {
        self.next().unwrap_or(0)
    }
    fn u16(&mut self) -> u16 {
        u16::from_le_bytes([self.u8(), self.u8()])
    }
    fn u32(&mut self) -> u32 {
        u32::from_le_bytes([self.u8(), self.u8(), self.u8(), self.u8()])
    }
    /// Up to `n` bytes (fewer at the end of the input).
    fn take(&mut self, n: usize) -> &[u8] {
        let (head, rest) = self.data.split_at(n.min(self.data.len()));
        self.data = rest;
        head
    }
}

/// A deterministic record of `len` bytes for `seed`, so that separate fragments of it agree.
fn synthetic(seed: u8, len: usize) -> Vec<u8> {
    (0..len).map(|k| (seed as usize).wrapping_mul(131).wrapping_add(k.wrapping_mul(7)).wrapping_add(k >> 8) as u8).collect()
}

fn script(data: &[u8], re: &mut Reassembler) {
    let mut r = Reader { data };
    for _ in 0..MAX_OPS {
        let Some(op) = r.next() else { break };
        match op % 8 {
            0 => {
                re.expire_before(u32::from(r.u8() % 8));
                assert!(re.in_progress() <= MAX_PARTIALS);
            }
            1 => drain(re),
            2 | 3 => {
                let flags = r.u8();
                let platform = u16::from(r.u8() % 4);
                let epoch = u32::from(r.u8() % 8);
                let len_raw = r.u16();
                let len = if flags & 2 != 0 { len_raw as usize } else { 1 + len_raw as usize % 700 };
                let seed = r.u8();
                let index_raw = r.u8();
                let count_true = len.div_ceil(FRAGMENT_DATA);
                let index = if flags & 4 != 0 { index_raw as usize } else { index_raw as usize % count_true.max(1) };
                let count = if flags & 16 != 0 { r.u8() } else { count_true.min(255) as u8 };
                let record = synthetic(seed, len);
                let crc = crc32fast::hash(&record) ^ u32::from(flags & 8 != 0);
                let start = (index * FRAGMENT_DATA).min(len);
                let mut chunk = record[start..(start + FRAGMENT_DATA).min(len)].to_vec();
                if flags & 32 != 0 {
                    chunk.pop();
                }
                if flags & 64 != 0
                    && let Some(b) = chunk.first_mut()
                {
                    *b ^= 0x5A;
                }
                let f = Fragment {
                    platform,
                    epoch,
                    time_usec: u64::from(flags & 1),
                    record_crc32: crc,
                    record_len: len as u16,
                    index: index as u8,
                    count,
                    data: chunk,
                    payload: Payload::Record,
                };
                push(re, &f);
            }
            4 | 5 => {
                let platform = u16::from(r.u8() % 4);
                let epoch = u32::from(r.u8() % 8);
                let time_usec = u64::from(r.u8() % 2);
                let record_crc32 = r.u32();
                let record_len = r.u16();
                let index = r.u8();
                let count = r.u8();
                let data_len = r.u8() as usize;
                let data = r.take(data_len).to_vec();
                push(
                    re,
                    &Fragment {
                        platform,
                        epoch,
                        time_usec,
                        record_crc32,
                        record_len,
                        index,
                        count,
                        data,
                        payload: Payload::Record,
                    },
                );
            }
            6 => whole_record(&mut r, re),
            _ => {
                let platform = u16::from(r.u8() % 4);
                let epoch = u32::from(r.u8() % 8);
                let time_usec = u64::from(r.u8() % 2);
                let record_crc32 = r.u32();
                let len = 1 + r.u16() as usize % 1200;
                let count = len.div_ceil(FRAGMENT_DATA);
                let index = r.u8() as usize % count;
                let expected = if index + 1 == count { len - index * FRAGMENT_DATA } else { FRAGMENT_DATA };
                let data = r.take(expected).to_vec();
                let f = Fragment {
                    platform,
                    epoch,
                    time_usec,
                    record_crc32,
                    record_len: len as u16,
                    index: index as u8,
                    count: count as u8,
                    data,
                    payload: Payload::Record,
                };
                push(re, &f);
            }
        }
    }
}

/// Op 6: a record taken from the input (zero-padded to its length) is cut by
/// `fragment::fragment`, its fragments pushed into a fresh reassembler in the order the input
/// gives, duplicates allowed, then all of them in order: the record must come out exactly once,
/// unchanged, and nothing may be rejected. The same fragments then go to the shared reassembler.
fn whole_record(r: &mut Reader<'_>, shared: &mut Reassembler) {
    let platform = u16::from(r.u8() % 4);
    let epoch = u32::from(r.u8() % 8);
    let len = r.u16() as usize;
    let mut record = r.take(len).to_vec();
    record.resize(len, 0);
    let fragments = match fragment::fragment(platform, epoch, 1_000, &record) {
        Ok(f) => f,
        Err(_) => {
            assert!(record.is_empty() || record.len() > MAX_RECORD_LEN, "fragment() refused a {len}-byte record");
            return;
        }
    };
    assert!(record.len() <= MAX_RECORD_LEN);
    assert_eq!(fragments.len(), len.div_ceil(FRAGMENT_DATA));
    assert_eq!(fragments.iter().map(|f| f.data.len()).sum::<usize>(), len);

    let pushes = r.u8() as usize;
    let order: Vec<usize> = r.take(pushes).iter().map(|&b| b as usize % fragments.len()).collect();
    let mut fresh = Reassembler::new(1);
    let mut completed = 0;
    for i in order.iter().copied().chain(0..fragments.len()) {
        match fresh.push(&fragments[i]) {
            Pushed::Complete(rec) => {
                completed += 1;
                assert_eq!(rec.bytes, record, "reassembled record differs");
                assert_eq!((rec.platform, rec.epoch, rec.time_usec), (platform, epoch, 1_000));
            }
            Pushed::Stored | Pushed::Duplicate => {}
            Pushed::Rejected(why) => panic!("a fragment of a well-formed record was rejected: {why}"),
        }
    }
    assert_eq!(completed, 1, "the record must complete exactly once");
    assert!(fresh.take_dropped().is_empty());
    check_record(platform, &record);
    for i in order {
        push(shared, &fragments[i]);
    }
}
