//! The protocol layer on its own: state records, fragmentation and reassembly, and the
//! quantisation rule that keeps every node bit-identical.

use cooploc::estimation::linear::LinearPlatform;
use cooploc::estimation::{CoopMeasurement, CrossCovariances, CrossMode, PlatformFilter, Snapshot, cooperative_update};
use cooploc::protocol::fragment::{
    FRAGMENT_CHUNK, FRAGMENT_DATA, Fragment, MAX_RADIO_FRAME, Pushed, Reassembler, fragment, fragment_in_chunks,
};
use cooploc::protocol::record::{self, Encoding, RecordError};
use nalgebra::{DMatrix, DVector};
use proptest::prelude::*;

fn snapshot(id: u16, n: usize, x: f64) -> Snapshot {
    let mut x0 = DVector::zeros(n);
    x0[0] = x;
    x0[1] = 0.5 * x;
    let a = DMatrix::from_fn(n, n, |r, c| ((r * 7 + c * 3 + id as usize) % 11) as f64 * 0.013 + 1e-9);
    let p = &a * a.transpose() + DMatrix::identity(n, n) * 0.37;
    let mut s = LinearPlatform::new(x0, p, [Some(0), Some(1), None]).unwrap().snapshot(id);
    s.psi += DMatrix::from_fn(n, n, |r, c| (r as f64 - c as f64) * 1.0e-3 / 3.0);
    s
}

#[test]
fn records_round_trip_exactly_in_f64_and_idempotently_in_f32() {
    let s = snapshot(4, 16, 1234.5678);
    let bytes = record::encode(&s, Encoding::F64).unwrap();
    assert_eq!(bytes.len(), record::record_len(16, Encoding::F64));
    assert_eq!(record::decode(4, &bytes).unwrap(), s, "f64 is exact");
    let bytes32 = record::encode(&s, Encoding::F32).unwrap();
    assert_eq!(bytes32.len(), record::record_len(16, Encoding::F32));
    let sent = record::decode(4, &bytes32).unwrap();
    assert_ne!(sent.covariance, s.covariance, "f32 rounds");
    assert!((&sent.covariance - &s.covariance).amax() < 1e-6 * s.covariance.amax());
    assert_eq!(sent.covariance, sent.covariance.transpose(), "rebuilt symmetric");
    assert_eq!(sent.geometry.position_ned_m, s.geometry.position_ned_m, "positions always go as f64");
    // What went on the wire, sent again, is the same bytes: nothing drifts.
    assert_eq!(record::encode(&sent, Encoding::F32).unwrap(), bytes32);
}

#[test]
fn malformed_records_are_errors() {
    let bytes = record::encode(&snapshot(1, 5, 3.0), Encoding::F64).unwrap();
    assert!(matches!(record::decode(1, &bytes[..10]), Err(RecordError::TooShort { .. })));
    assert!(matches!(record::decode(1, &bytes[..bytes.len() - 1]), Err(RecordError::LengthMismatch { .. })));
    let mut b = bytes.clone();
    b[0] = 9;
    assert_eq!(record::decode(1, &b), Err(RecordError::Version(9)));
    let mut b = bytes.clone();
    b[1] = 7;
    assert_eq!(record::decode(1, &b), Err(RecordError::Encoding(7)));
    let mut b = bytes.clone();
    b[5] = 5; // position index 5 in a 5-state record
    assert!(matches!(record::decode(1, &b), Err(RecordError::Index { .. })));
    let mut b = bytes.clone();
    b[2..4].copy_from_slice(&0u16.to_le_bytes());
    assert_eq!(record::decode(1, &b), Err(RecordError::Dimension(0)));
    let mut b = bytes.clone();
    b[40..48].copy_from_slice(&f64::NAN.to_le_bytes());
    assert!(matches!(record::decode(1, &b), Err(RecordError::NonFinite(_))));
    let mut nan = snapshot(1, 5, 3.0);
    nan.psi[(2, 2)] = f64::INFINITY;
    assert!(record::encode(&nan, Encoding::F64).is_err());
}

/// Delivers `order` (indices into `frags`, repeats allowed) and returns what completed.
fn deliver(r: &mut Reassembler, frags: &[Fragment], order: &[usize]) -> Vec<Vec<u8>> {
    let mut done = Vec::new();
    for &i in order {
        match r.push(&frags[i]) {
            Pushed::Complete(rec) => done.push(rec.bytes),
            Pushed::Rejected(why) => panic!("valid fragment rejected: {why}"),
            Pushed::Stored | Pushed::Duplicate => {}
        }
    }
    done
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(512))]

    /// Any permutation, duplication or loss pattern yields the exact record (every fragment
    /// arrived) or nothing (some did not), for two records interleaved.
    #[test]
    /// The two records are cut at chunk sizes of their own (a node of an older release cut at
    /// 232 bytes): the receiver takes each record's from its fragments.
    fn reassembly_is_exact_or_incomplete(
        len_a in 1usize..4000,
        len_b in 1usize..4000,
        chunk_a in 16usize..=FRAGMENT_DATA,
        chunk_b in prop_oneof![Just(FRAGMENT_CHUNK), Just(FRAGMENT_DATA), 16usize..=FRAGMENT_DATA],
        seed in any::<u64>(),
        picks in proptest::collection::vec((any::<bool>(), any::<u16>()), 0..80),
    ) {
        let mk = |len: usize, salt: u64| (0..len).map(|i| ((i as u64).wrapping_mul(2654435761) ^ salt ^ seed) as u8).collect::<Vec<u8>>();
        let (ra, rb) = (mk(len_a, 1), mk(len_b, 2));
        let fa = fragment_in_chunks(1, 10, 1_000_000, &ra, chunk_a).unwrap();
        let fb = fragment_in_chunks(2, 10, 1_000_000, &rb, chunk_b).unwrap();
        let mut all = fa.clone();
        all.extend(fb.iter().cloned());
        let order: Vec<usize> = picks.iter().map(|(_, k)| *k as usize % all.len()).collect();
        let mut r = Reassembler::new(4);
        let done = deliver(&mut r, &all, &order);
        let got_a = (0..fa.len()).all(|i| order.contains(&i));
        let got_b = (fa.len()..all.len()).all(|i| order.contains(&i));
        let expected: Vec<&Vec<u8>> = [(got_a, &ra), (got_b, &rb)].into_iter().filter(|(g, _)| *g).map(|(_, r)| r).collect();
        prop_assert_eq!(done.len(), expected.len());
        for rec in &done {
            prop_assert!(expected.contains(&rec), "a completed record differs from what was sent");
        }
        prop_assert_eq!(r.in_progress(), usize::from(!got_a && order.iter().any(|&i| i < fa.len())) + usize::from(!got_b && order.iter().any(|&i| i >= fa.len())));
    }

    /// A corrupted fragment never yields a record.
    #[test]
    fn corrupted_data_never_completes(len in 2usize..3000, which in any::<u16>(), bit in 0u8..8) {
        let rec: Vec<u8> = (0..len).map(|i| (i * 31 % 251) as u8).collect();
        let mut frags = fragment(3, 1, 5, &rec).unwrap();
        let k = which as usize % frags.len();
        let j = which as usize % frags[k].data.len();
        frags[k].data[j] ^= 1 << bit;
        let mut r = Reassembler::new(2);
        for f in &frags {
            prop_assert!(!matches!(r.push(f), Pushed::Complete(_)));
        }
        let dropped = r.take_dropped();
        prop_assert_eq!(dropped.len(), 1);
        prop_assert_eq!(dropped[0].reason, "CRC-32 mismatch");
    }
}

#[test]
fn memory_is_bounded_and_old_epochs_expire() {
    let rec = vec![7u8; 3 * FRAGMENT_CHUNK + 5];
    let mut r = Reassembler::new(5);
    for epoch in 0..100u32 {
        for platform in 0..4u16 {
            let frags = fragment(platform, epoch, 0, &rec).unwrap();
            r.push(&frags[0]);
            assert!(r.in_progress() <= 5);
        }
    }
    let dropped = r.take_dropped();
    assert_eq!(dropped.len(), 400 - 5, "all but the newest five were evicted");
    assert!(dropped.iter().all(|d| d.reason == "evicted for room" && d.received == 1 && d.count == 4));
    r.expire_before(100);
    assert_eq!(r.in_progress(), 0);
    assert_eq!(r.take_dropped().len(), 5);
    // A fragment whose header contradicts itself is rejected, not stored.
    let mut f = fragment(1, 1, 0, &rec).unwrap()[1].clone();
    f.count = 9;
    assert!(matches!(r.push(&f), Pushed::Rejected(_)));
    f.count = 4;
    // 150 bytes in a fragment before the last: 617 bytes would take 5 such chunks, not 4.
    f.data.truncate(150);
    assert!(matches!(r.push(&f), Pushed::Rejected(_)));
    assert_eq!(r.in_progress(), 0);
}

/// The receiver takes each record's chunk size from its fragments, whichever arrives first, and
/// refuses fragments that no chunk size makes into one record.
#[test]
fn a_record_cut_at_any_chunk_size_reassembles_and_contradictions_are_refused() {
    let rec: Vec<u8> = (0..1041u32).map(|i| (i * 13 % 251) as u8 + 1).collect();
    for chunk in [5, 17, 100, FRAGMENT_CHUNK, 205, FRAGMENT_DATA] {
        let frags = fragment_in_chunks(4, 9, 9_000_000, &rec, chunk).unwrap();
        assert_eq!(frags.len(), rec.len().div_ceil(chunk));
        // The last fragment first: its chunk size comes from the record length and count.
        let mut r = Reassembler::new(2);
        let order: Vec<usize> = (0..frags.len()).rev().collect();
        assert_eq!(deliver(&mut r, &frags, &order), vec![rec.clone()], "chunk {chunk}");
    }
    assert!(fragment_in_chunks(4, 9, 0, &rec, 4).is_err(), "1041 bytes in 4-byte chunks is more than 255 fragments");

    let frags = fragment_in_chunks(4, 9, 9_000_000, &rec, 100).unwrap();
    let mut r = Reassembler::new(2);
    // A last fragment whose length no whole chunk count leaves: 1041 - 40 = 1001 is not 10 chunks.
    let mut last = frags[10].clone();
    last.data.truncate(40);
    assert_eq!(r.push(&last), Pushed::Rejected("fragment data length does not fit the record length"));
    // A middle fragment of another chunk size than the count says.
    let mut mid = frags[3].clone();
    mid.data.extend_from_slice(&[0; 20]);
    assert_eq!(r.push(&mid), Pushed::Rejected("record length and fragment count disagree"));
    // Over the array: refused before anything else.
    mid.data.resize(FRAGMENT_DATA + 1, 1);
    assert!(matches!(r.push(&mid), Pushed::Rejected(_)));
    // The same record cut again at 232 bytes while a 100-byte cut is in progress (a sender
    // restarted on a release with the older chunk): the newer cut supersedes, the bytes stay
    // right.
    assert_eq!(r.push(&frags[0]), Pushed::Stored);
    let old = fragment_in_chunks(4, 9, 9_000_000, &rec, FRAGMENT_DATA).unwrap();
    let mut got = None;
    for f in &old {
        if let Pushed::Complete(done) = r.push(f) {
            got = Some(done.bytes);
        }
    }
    assert_eq!(got, Some(rec.clone()));
    assert_eq!(
        r.take_dropped().iter().map(|d| d.reason).collect::<Vec<_>>(),
        ["superseded by a different record for the same epoch"]
    );
}

/// No frame cooploc sends on the cooperative link is longer than a SiK radio's packet, signed:
/// a state or store fragment cut at [`FRAGMENT_CHUNK`] bytes with no zero to trim (the
/// worst case), and every other message of the dialect at its full length.
#[test]
fn every_frame_on_the_cooperative_link_fits_a_radio_packet_signed() {
    use cooploc::protocol::MavMessage;
    use cooploc::protocol::dialect::cooploc::*;
    use cooploc::protocol::fragment::Payload;
    use cooploc::protocol::signing::{Signer, TeamKey};
    use cooploc::protocol::wire::fragment_to_message;
    use mavlink_core::{MavHeader, Message, MessageData};
    let header = MavHeader { system_id: 200, component_id: 191, sequence: 255 };
    let mut signer = Signer::new(TeamKey::from_passphrase("radio"), 200, 0);
    let rec = vec![0xFFu8; 3 * FRAGMENT_CHUNK];
    for payload in [Payload::Record, Payload::Store] {
        for mut f in fragment(0xFFFF, u32::MAX, u64::MAX, &rec).unwrap() {
            f.payload = payload;
            let frame = signer.frame(header, &fragment_to_message(&f).unwrap(), 1_800_000_000_000_000);
            assert_eq!(frame.len(), MAX_RADIO_FRAME, "{payload:?}: a whole chunk with nothing to trim fills the packet");
        }
    }
    // The rest at their full payload (10 header, 2 checksum and 13 signature bytes around it).
    let full = [
        (COOPLOC_RANGE_DATA::NAME, COOPLOC_RANGE_DATA::ENCODED_LEN),
        (COOPLOC_ESTIMATE_DATA::NAME, COOPLOC_ESTIMATE_DATA::ENCODED_LEN),
        (COOPLOC_EPOCH_DATA::NAME, COOPLOC_EPOCH_DATA::ENCODED_LEN),
        (COOPLOC_EPOCH_SET_DATA::NAME, COOPLOC_EPOCH_SET_DATA::ENCODED_LEN),
        (COOPLOC_RANGE_BEARING_DATA::NAME, COOPLOC_RANGE_BEARING_DATA::ENCODED_LEN),
        (COOPLOC_STORE_HELD_DATA::NAME, COOPLOC_STORE_HELD_DATA::ENCODED_LEN),
        ("HEARTBEAT", HEARTBEAT_DATA::ENCODED_LEN),
    ];
    for (name, len) in full {
        assert!(10 + len + 2 + 13 <= MAX_RADIO_FRAME, "{name}: {} B signed", 10 + len + 15);
    }
    // Every message of the cooploc dialect is one of those (ids 61000 to 61007).
    for id in 61000..61100 {
        let known = (61000..=61007).contains(&id);
        assert_eq!(MavMessage::default_message_from_id(id).is_some(), known, "message {id}: add it above");
    }
}

/// Three nodes exchange f32 records. Each runs the joint update on the decoded broadcasts, its
/// own included, and all three get the same bits; a sender that kept its own unrounded state
/// would not.
#[test]
fn quantisation_rule_keeps_nodes_bit_identical() {
    let snaps: Vec<Snapshot> = (0..3u16).map(|i| snapshot(i, 6, 40.0 * i as f64 + 3.0)).collect();
    let wire: Vec<Vec<u8>> = snaps.iter().map(|s| record::encode(s, Encoding::F32).unwrap()).collect();
    let ranges = vec![
        CoopMeasurement::Range { from: 0, to: 1, range_m: 44.7, sigma_m: 0.1 },
        CoopMeasurement::Range { from: 1, to: 2, range_m: 44.9, sigma_m: 0.1 },
    ];
    let mut outcomes = Vec::new();
    for _node in 0..3 {
        let received: Vec<Snapshot> = wire.iter().enumerate().map(|(i, b)| record::decode(i as u16, b).unwrap()).collect();
        outcomes.push(
            cooperative_update(&mut CrossCovariances::new(), &received, &ranges, CrossMode::Propagate).unwrap().corrections,
        );
    }
    assert_eq!(outcomes[0], outcomes[1]);
    assert_eq!(outcomes[0], outcomes[2]);
    let mut own = snaps.iter().enumerate().map(|(i, _)| record::decode(i as u16, &wire[i]).unwrap()).collect::<Vec<_>>();
    own[0] = snaps[0].clone();
    let selfish = cooperative_update(&mut CrossCovariances::new(), &own, &ranges, CrossMode::Propagate).unwrap().corrections;
    assert_ne!(selfish, outcomes[0], "using unrounded own values would break bit-identity");
}

/// Bytes on the wire, MAVLink framing included, for one 16-state INS platform per cooperative
/// event, against streaming its raw sensors to a central node. Prints the figures docs/protocol.md
/// quotes (`cargo test --release --test protocol wire_budget -- --nocapture`).
#[test]
fn wire_budget() {
    use cooploc::estimation::{ImuSample, OdometerSample, RangeSample};
    use cooploc::protocol::wire::{fragment_to_message, imu_to_highres, odometer_to_odometry, range_to_message, to_frame};
    use cooploc::time::TimeUs;
    use mavlink_core::MavHeader;
    let header = MavHeader { system_id: 1, component_id: 191, sequence: 0 };
    let frames_len = |msgs: &[cooploc::protocol::MavMessage]| msgs.iter().map(|m| to_frame(header, m).len()).sum::<usize>();
    use cooploc::estimation::StoreRef;
    use cooploc::protocol::record::{StateRecord, StoreSnapshot, encode_record, encode_store};
    let snap = snapshot(1, 16, 1234.5);
    // A record of the paper's team: three references in the store, no range.
    let r = StoreRef { epoch: 7, token: 0x1234 };
    let three =
        StateRecord { snapshot: snap, digest: 1, own_ref: r, refs: vec![(1, r), (2, r), (3, r)], flags: 0, ranges: Vec::new() };
    let mut per_event = Vec::new();
    for enc in [Encoding::F64, Encoding::F32] {
        let rec = encode_record(&three, enc).unwrap();
        let msgs: Vec<_> = fragment(1, 7, 7_000_000, &rec).unwrap().iter().map(|f| fragment_to_message(f).unwrap()).collect();
        per_event.push((enc, rec.len(), msgs.len(), frames_len(&msgs)));
    }
    let range = RangeSample { t: TimeUs(7_000_000), from: 1, to: 2, range_m: 212.37, sigma_m: 0.1 };
    let range_bytes = frames_len(&[range_to_message(&range, 7)]);
    let imu = ImuSample {
        t: TimeUs(5_000),
        specific_force_frd_m_s2: nalgebra::Vector3::new(0.1, 0.2, -9.8),
        angular_rate_frd_rad_s: nalgebra::Vector3::new(0.001, -0.002, 0.05),
    };
    let imu_bytes = frames_len(&[imu_to_highres(&imu)]);
    let odo_bytes = frames_len(&[odometer_to_odometry(&OdometerSample { t: TimeUs(100_000), speed_m_s: 10.0 }, 0.2)]);
    let raw_per_s = 200 * imu_bytes + 10 * odo_bytes;
    // The store a left-out node asks for: three 16-state platforms, three blocks.
    let block = DMatrix::from_element(16, 16, 1e-3);
    let store = CrossCovariances::from_parts(
        vec![((1, 2), block.clone()), ((1, 3), block.clone()), ((2, 3), block)],
        vec![(1, r), (2, r), (3, r)],
    )
    .unwrap();
    let store_bytes = encode_store(&StoreSnapshot { epoch: 7, digest_before: 1, store }).unwrap();
    let store_frags: Vec<_> = fragment(1, 7, 7_000_000, &store_bytes)
        .unwrap()
        .into_iter()
        .map(|mut f| {
            f.payload = cooploc::protocol::fragment::Payload::Store;
            fragment_to_message(&f).unwrap()
        })
        .collect();
    eprintln!(
        "store snapshot of 3 platforms: {} B in {} fragments = {} B on the wire",
        store_bytes.len(),
        store_frags.len(),
        frames_len(&store_frags)
    );
    assert!(matches!(store_frags[0], cooploc::protocol::MavMessage::COOPLOC_STORE_FRAGMENT(_)));
    for (enc, rec, n, bytes) in &per_event {
        eprintln!("state broadcast, {enc:?}: record {rec} B in {n} fragments = {bytes} B on the wire per platform per event");
    }
    eprintln!("one COOPLOC_RANGE frame: {range_bytes} B; with the paper's 3 platforms each platform sends at most 2 per event");
    eprintln!(
        "raw sensors to a central node: HIGHRES_IMU {imu_bytes} B x 200 Hz + ODOMETRY {odo_bytes} B x 10 Hz = {raw_per_s} B/s per platform"
    );
    let (_, _, _, f64_bytes) = per_event[0];
    let (_, _, _, f32_bytes) = per_event[1];
    assert!(f32_bytes < f64_bytes * 6 / 10, "f32 roughly halves the broadcast");
    assert!(f64_bytes + 2 * range_bytes < raw_per_s, "one event per second costs less than streaming raw sensors");
}

/// A record carries the sender's store digest, its flags and the ranges its radio measured;
/// all come back exactly (ranges as f32, what every node uses), and malformed trailers are
/// errors that name the problem.
#[test]
fn records_carry_digest_flags_and_ranges() {
    use cooploc::estimation::RangeSample;
    use cooploc::estimation::StoreRef;
    use cooploc::protocol::record::{FLAG_FRESH, MAX_RANGES, StateRecord, decode_record, encode_record};
    use cooploc::time::TimeUs;
    let t = TimeUs(7_000_000);
    let ranges: Vec<RangeSample> = (2..5u16)
        .map(|to| RangeSample { t, from: 1, to, range_m: 100.0 + f64::from(to) / 3.0, sigma_m: 0.1 })
        .map(|r| cooploc::protocol::wire::range_as_sent(&r))
        .collect();
    let rec = StateRecord {
        snapshot: snapshot(1, 16, 12.5),
        digest: 0xdead_beef_0123_4567,
        own_ref: StoreRef { epoch: 41, token: 0x0123_4567_89ab_cdef },
        refs: Vec::new(),
        flags: FLAG_FRESH,
        ranges,
    };
    for enc in [Encoding::F64, Encoding::F32] {
        let bytes = encode_record(&rec, enc).unwrap();
        assert_eq!(bytes.len(), record::record_len(16, enc) + 3 * 10);
        let back = decode_record(1, t, &bytes).unwrap();
        assert_eq!((back.digest, back.own_ref, back.flags, &back.ranges), (rec.digest, rec.own_ref, rec.flags, &rec.ranges));
        // Cut inside the ranges, or a count that promises more: a length error.
        assert!(matches!(decode_record(1, t, &bytes[..bytes.len() - 1]), Err(RecordError::LengthMismatch { .. })));
        let mut more = bytes.clone();
        let count_at = record::record_len(16, enc) - 1;
        more[count_at] = 4;
        assert!(matches!(decode_record(1, t, &more), Err(RecordError::LengthMismatch { .. })));
        let mut flags = bytes.clone();
        flags[count_at - 2] = 0x80;
        assert_eq!(decode_record(1, t, &flags), Err(RecordError::Flags(0x80)));
        flags[count_at - 2] = 0x08;
        assert_eq!(decode_record(1, t, &flags), Err(RecordError::Flags(0x08)));
        // The epochs the sender asks the team to pass over (0-3) come back, beside FRESH.
        for skip in 0..=record::MAX_SKIP {
            let asks = StateRecord { flags: record::with_skip(FLAG_FRESH, skip), ..rec.clone() };
            let back = decode_record(1, t, &encode_record(&asks, enc).unwrap()).unwrap();
            assert_eq!((record::skip_of(back.flags), back.flags & FLAG_FRESH), (skip, FLAG_FRESH));
        }
        assert_eq!(record::skip_of(record::with_skip(0, 9)), record::MAX_SKIP, "at most MAX_SKIP");
        // A range to the sender itself, or a negative sigma, is refused.
        let mut selfie = bytes.clone();
        selfie[count_at + 1..count_at + 3].copy_from_slice(&1u16.to_le_bytes());
        assert!(matches!(decode_record(1, t, &selfie), Err(RecordError::Range { index: 0, .. })));
        let mut sigma = bytes.clone();
        sigma[count_at + 7..count_at + 11].copy_from_slice(&(-0.1f32).to_le_bytes());
        assert!(matches!(decode_record(1, t, &sigma), Err(RecordError::Range { index: 0, .. })));
    }
    // References: they come back exactly; out of order, or more than a team, they are refused.
    let refs = vec![(1, StoreRef { epoch: 40, token: 7 }), (3, StoreRef { epoch: 12, token: 9 })];
    let with_refs = StateRecord { refs: refs.clone(), ..rec.clone() };
    let bytes = encode_record(&with_refs, Encoding::F64).unwrap();
    assert_eq!(bytes.len(), record::record_len(16, Encoding::F64) + 2 * 14 + 3 * 10);
    assert_eq!(decode_record(1, t, &bytes).unwrap(), with_refs);
    let swapped = StateRecord { refs: vec![refs[1], refs[0]], ..rec.clone() };
    assert_eq!(encode_record(&swapped, Encoding::F64), Err(RecordError::RefOrder));
    let mut swapped_bytes = bytes.clone();
    let refs_at = record::record_len(16, Encoding::F64) - 1; // first reference, after its count
    swapped_bytes[refs_at..refs_at + 2].copy_from_slice(&5u16.to_le_bytes());
    assert_eq!(decode_record(1, t, &swapped_bytes), Err(RecordError::RefOrder));
    let mut count = bytes.clone();
    count[refs_at - 1] = 200;
    assert_eq!(decode_record(1, t, &count), Err(RecordError::TooManyRefs(200)));
    let too_many = StateRecord { ranges: vec![rec.ranges[0]; MAX_RANGES + 1], ..rec.clone() };
    assert_eq!(encode_record(&too_many, Encoding::F32), Err(RecordError::TooManyRanges(MAX_RANGES + 1)));
    let foreign = StateRecord { ranges: vec![RangeSample { from: 2, ..rec.ranges[0] }], ..rec };
    assert!(matches!(encode_record(&foreign, Encoding::F32), Err(RecordError::Range { index: 0, .. })));
}

/// A store snapshot (what a node left out of an epoch takes from its teammates) comes back bit for
/// bit with the digest it claims; a snapshot whose bytes do not give that digest, or whose blocks
/// are not ordered pairs of one shape per platform, is refused with the reason.
#[test]
fn store_snapshots_round_trip_and_refuse_what_does_not_add_up() {
    use cooploc::estimation::{StoreError, StoreRef};
    use cooploc::protocol::record::{StoreSnapshot, decode_store, encode_store};
    use nalgebra::DMatrix;
    let block = |seed: f64| DMatrix::from_fn(16, 16, |r, c| (seed + r as f64 * 0.37 - c as f64 * 0.11).sin() * 1e-3);
    let store = CrossCovariances::from_parts(
        vec![((1, 2), block(1.0)), ((1, 3), block(2.0)), ((2, 3), block(3.0))],
        vec![(1, StoreRef { epoch: 9, token: 11 }), (2, StoreRef { epoch: 9, token: 11 }), (3, StoreRef::fresh(4))],
    )
    .unwrap();
    let snap = StoreSnapshot { epoch: 9, digest_before: 0xabc, store: store.clone() };
    let bytes = encode_store(&snap).unwrap();
    assert_eq!(bytes.len(), 21 + 1 + 3 * 14 + 2 + 3 * (6 + 16 * 16 * 8));
    let back = decode_store(&bytes).unwrap();
    assert_eq!(back, snap);
    assert_eq!(back.store.digest(), store.digest());
    // One bit of one value changed: the digest it carries no longer matches.
    let mut flipped = bytes.clone();
    let last = flipped.len() - 1;
    flipped[last] ^= 1;
    assert_eq!(decode_store(&flipped), Err(RecordError::StoreDigest));
    // Truncated, or with bytes left over.
    assert!(matches!(decode_store(&bytes[..bytes.len() - 8]), Err(RecordError::TooShort { .. })));
    let mut longer = bytes.clone();
    longer.push(0);
    assert!(matches!(decode_store(&longer), Err(RecordError::LengthMismatch { .. })));
    // Blocks that do not make a store.
    assert_eq!(CrossCovariances::from_parts(vec![((2, 1), block(1.0))], vec![]), Err(StoreError::Pair(2, 1)));
    let small = DMatrix::zeros(15, 16);
    assert_eq!(
        CrossCovariances::from_parts(vec![((1, 2), block(1.0)), ((1, 3), small)], vec![]),
        Err(StoreError::Shape(1, 3, 15, 16))
    );
    let mut nan = block(1.0);
    nan[(3, 3)] = f64::NAN;
    assert_eq!(CrossCovariances::from_parts(vec![((1, 2), nan)], vec![]), Err(StoreError::NonFinite(1, 2)));
    // The references count in the digest: a store that saw another update differs.
    let mut other = store.clone();
    other.set_reference(3, StoreRef { epoch: 9, token: 11 });
    assert_ne!(other.digest(), store.digest());
}

/// A store snapshot of any size goes as parts, each one fragment series: parts from two senders
/// of the same store, in any order, with duplicates, some series lost and sent again, give the
/// exact snapshot; a part of another snapshot, a contradicting or corrupted part never does.
#[test]
fn store_parts_reassemble_from_any_sender_in_any_order_and_refuse_contradictions() {
    use cooploc::protocol::fragment::{PartPushed, StoreAssembler};
    use cooploc::protocol::record::{MAX_STORE_LEN, STORE_PART_HEADER, STORE_VERSION, decode_store_part, store_parts};
    let snapshot: Vec<u8> = std::iter::once(STORE_VERSION).chain((1..130_000u32).map(|i| (i * 7 % 253) as u8)).collect();
    let parts = store_parts(&snapshot, 50_000).unwrap();
    assert_eq!(parts.len(), 3);
    assert!(parts.iter().all(|p| p.len() <= 50_000 + STORE_PART_HEADER));
    // Each part as one fragment series, from sender 2 or 3, reassembled in a scrambled order.
    let mut series = Reassembler::keeping_each_record(8);
    let mut store = StoreAssembler::default();
    let mut frags: Vec<Fragment> = Vec::new();
    for (k, p) in parts.iter().enumerate() {
        frags.extend(fragment(2 + (k % 2) as u16, 5, 0, p).unwrap());
    }
    // A few of the first sender's fragments lost the first time, sent again after the rest.
    let order: Vec<usize> =
        (0..frags.len()).filter(|i| i % 97 != 3).rev().chain((0..frags.len()).filter(|i| i % 97 == 3)).chain([0, 1]).collect();
    let mut done = None;
    for i in order {
        if let Pushed::Complete(rec) = series.push(&frags[i]) {
            let part = decode_store_part(&rec.bytes).unwrap().expect("a part");
            match store.push(part) {
                PartPushed::Complete(bytes) => done = Some(bytes),
                PartPushed::Stored => {}
                other => panic!("{other:?}"),
            }
        }
    }
    assert_eq!(done.as_deref(), Some(&snapshot[..]));
    assert_eq!(store.in_progress(), 0);

    // A whole snapshot (what releases before parts sent) is told apart from a part.
    assert_eq!(decode_store_part(&snapshot).unwrap(), None);
    let part = |k: usize| decode_store_part(&parts[k]).unwrap().unwrap();
    let mut s = StoreAssembler::default();
    assert_eq!(s.push(part(0)), PartPushed::Stored);
    assert_eq!(s.push(part(0)), PartPushed::Duplicate);
    let mut other = part(1);
    other.bytes[7] ^= 1;
    assert_eq!(s.push(other.clone()), PartPushed::Stored, "a corrupted part looks fine alone");
    assert_eq!(s.push(part(2)), PartPushed::Rejected("the parts together fail the snapshot's CRC-32"));
    let mut short = part(1);
    short.bytes.truncate(10);
    assert_eq!(s.push(short), PartPushed::Rejected("snapshot length and part count disagree"));
    // Parts of a third and a fourth snapshot at once: only two are assembled.
    let mut s = StoreAssembler::default();
    for crc in 0..StoreAssembler::CANDIDATES as u32 {
        assert_eq!(s.push(cooploc::protocol::record::StorePart { crc32: crc, ..part(0) }), PartPushed::Stored);
    }
    assert_eq!(
        s.push(cooploc::protocol::record::StorePart { crc32: 99, ..part(0) }),
        PartPushed::Rejected("parts of too many different snapshots")
    );
    // Headers that cannot be: beyond the count, over the size limit, an unknown version.
    let mut bad = parts[1].clone();
    bad[1..3].copy_from_slice(&7u16.to_le_bytes());
    assert!(decode_store_part(&bad).unwrap_err().to_string().contains("index beyond the count"));
    let mut huge = parts[1].clone();
    huge[5..9].copy_from_slice(&(MAX_STORE_LEN as u32 + 1).to_le_bytes());
    assert!(decode_store_part(&huge).unwrap_err().to_string().contains("more than"));
    assert!(decode_store_part(&[9, 0, 0]).is_err());
    assert!(store_parts(&vec![1u8; MAX_STORE_LEN + 1], 50_000).is_err());
}
