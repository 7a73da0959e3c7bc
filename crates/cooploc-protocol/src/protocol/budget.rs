//! The byte budget of the cooperative network: what a team sends, per node and in all, for a
//! team size, state size, epoch rate, record encoding and signing, and the highest epoch rate a
//! link carries. Pure computation, no I/O (the `cooploc budget` command prints it).
//!
//! The sizes are not modelled: every message is built by the encoders the nodes use (a record
//! of the given size with realistic, non-zero values cut into fragments, the epoch report, the
//! estimate, the range echoes, the heartbeat), framed as MAVLink 2, signed when asked, and
//! measured. Per node and epoch a node sends (see `node::core`): its record's fragments, one
//! COOPLOC_EPOCH_SET report, one COOPLOC_ESTIMATE and one COOPLOC_RANGE per range its radio
//! measured (the echo for ground stations; the joint update takes ranges from the record); and
//! one HEARTBEAT a second. Resends (after a loss) come on top: the fragments a teammate missed,
//! plus its COOPLOC_EPOCH_SET request ([`rates_with_loss`]).
//!
//! On a **broadcast** medium (a radio network, IP multicast) one copy of a frame reaches the
//! whole team, so the channel carries the sum of what the nodes send. With **unicast** IP each
//! frame goes to every peer: a node sends `team - 1` copies (and the air of a shared Wi-Fi cell
//! carries them all). IP adds 28 bytes (IPv4 and UDP headers) per datagram: one frame per
//! datagram, or (what `cooploc node` does) each batch of frames the node sends at once packed
//! into datagrams of at most 1,472 bytes (Ethernet's MTU less the headers) by [`pack`]: the
//! record's first fragment alone (it makes the epoch known to a node that measured no range:
//! on a slow link a whole packed record takes a third of a second to leave), its other
//! fragments, each range echo, the epoch report with the estimate.

use nalgebra::{DMatrix, Vector3};

use super::MavMessage;
use super::fragment::fragment;
use super::record::{Encoding, StateRecord, encode_record};
use super::signing::{Signer, TeamKey};
use super::wire::{self, EpochAnnouncement, EpochState, EstimateReport};
use crate::estimation::{Geometry, Heading, Method, PlatformId, RangeSample, Snapshot, StoreRef};
use crate::time::TimeUs;

/// IPv4 and UDP headers per datagram.
pub const IP_UDP_OVERHEAD: usize = 28;
/// Largest UDP payload that fits an Ethernet frame (1500 - 28).
pub const MAX_DATAGRAM: usize = 1472;

/// What a team is and how it talks.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct TeamShape {
    pub team: usize,
    /// Error-state dimension of each member (16: the INS; 3: a planar robot).
    pub state_dim: usize,
    /// Ranges each node's radio measures per epoch (at most `team - 1`).
    pub ranges_per_node: usize,
    pub epoch_hz: f64,
    pub encoding: Encoding,
    pub signed: bool,
    /// Each range also sent as a COOPLOC_RANGE (`cooploc node` does unless `--no-range-echo`).
    pub echo_ranges: bool,
}

/// The frames one node sends for one epoch, by kind: (kind, frames, bytes).
#[derive(Debug, Clone, PartialEq)]
pub struct EpochFrames {
    pub record_bytes: usize,
    pub kinds: Vec<(&'static str, usize, usize)>,
    pub heartbeat_bytes: usize,
    /// Frame sizes of one epoch in the batches the node sends them in (each batch packed into
    /// datagrams of its own): the record's first fragment alone, its other fragments, each
    /// echoed range as it is measured, the epoch's report with the estimate after the update.
    pub batches: Vec<Vec<usize>>,
}

impl EpochFrames {
    pub fn frames(&self) -> usize {
        self.kinds.iter().map(|k| k.1).sum()
    }
    pub fn bytes(&self) -> usize {
        self.kinds.iter().map(|k| k.2).sum()
    }
    /// Datagrams of one epoch, packed (each batch on its own) or one frame each.
    pub fn datagrams(&self, packed: bool) -> usize {
        self.batches.iter().map(|b| datagrams(b, packed)).sum()
    }
    /// Datagrams of one record (its first fragment alone, the rest packed).
    pub fn record_datagrams(&self, packed: bool) -> usize {
        let batches = if self.kinds[0].1 > 1 { 2 } else { 1 };
        self.batches[..batches].iter().map(|b| datagrams(b, packed)).sum()
    }
}

/// How frames travel.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Medium {
    /// A serial radio network: one copy reaches every node, no IP headers.
    Radio,
    /// UDP multicast or broadcast: one copy, IP headers.
    IpBroadcast { packed: bool },
    /// UDP to every peer: `team - 1` copies, IP headers.
    IpUnicast { packed: bool },
}

impl Medium {
    /// Copies of each frame a node sends in a team of `team`, and for IP whether frames are
    /// packed (None: no IP headers).
    fn copies_and_packing(self, team: usize) -> (f64, Option<bool>) {
        match self {
            Medium::Radio => (1.0, None),
            Medium::IpBroadcast { packed } => (1.0, Some(packed)),
            Medium::IpUnicast { packed } => (team.saturating_sub(1).max(1) as f64, Some(packed)),
        }
    }
}

/// Bytes per second on the network.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Rates {
    /// What one node puts on the network per second (all copies, all headers).
    pub node_bytes_per_s: f64,
    /// What the shared channel carries per second for the whole team.
    pub team_bytes_per_s: f64,
    pub node_datagrams_per_s: f64,
}

/// A deterministic stream of plausible values (no zero bytes to truncate).
struct Values(u64);

impl Values {
    fn next(&mut self) -> f64 {
        self.0 ^= self.0 << 13;
        self.0 ^= self.0 >> 7;
        self.0 ^= self.0 << 17;
        (self.0 >> 11) as f64 / (1u64 << 53) as f64 * 2.0 - 1.0
    }
}

/// A record of platform 1 of `shape`'s size with realistic values.
fn sample_record(shape: &TeamShape) -> StateRecord {
    let n = shape.state_dim.max(1);
    let mut v = Values(0x2545_f491_4f6c_dd1d);
    let l = DMatrix::from_fn(n, n + 2, |_, _| v.next());
    let covariance = &l * l.transpose() + DMatrix::identity(n, n) * 0.1;
    let psi = DMatrix::from_fn(n, n, |r, c| if r == c { 1.0 + 0.01 * v.next() } else { 0.05 * v.next() });
    let snapshot = Snapshot {
        id: 1,
        geometry: Geometry {
            position_ned_m: Vector3::new(123.4, -56.7, -8.9),
            position_index: [Some(0), Some(1.min(n - 1)), Some(2.min(n - 1))],
            heading: Some(Heading { yaw_rad: 0.3, index: n - 1 }),
        },
        covariance,
        psi,
    };
    let members = shape.team.clamp(1, super::record::MAX_REFS) as PlatformId;
    StateRecord {
        snapshot,
        digest: 0x0123_4567_89ab_cdef,
        own_ref: StoreRef { epoch: 1000, token: 0xfeed_beef },
        refs: (1..=members).map(|p| (p, StoreRef { epoch: 1000, token: 0xfeed_0000 + u64::from(p) })).collect(),
        flags: 0,
        ranges: (0..shape.ranges_per_node.min(super::record::MAX_RANGES))
            .map(|k| RangeSample { t: TimeUs(1_000_000_000), from: 1, to: 2 + k as PlatformId, range_m: 187.25, sigma_m: 0.1 })
            .collect(),
    }
}

/// The frames one node sends per epoch for `shape`, measured from the real encoders.
pub fn epoch_frames(shape: &TeamShape) -> Result<EpochFrames, String> {
    let mut signer = shape.signed.then(|| Signer::new(TeamKey::from_passphrase("budget"), 1, 0));
    let mut seq = 0u8;
    let mut frame = |msg: &MavMessage| -> usize {
        seq = seq.wrapping_add(1);
        let header = mavlink_core::MavHeader { system_id: 1, component_id: 191, sequence: seq };
        match &mut signer {
            Some(s) => s.frame(header, msg, 1_700_000_000_000_000).len(),
            None => wire::to_frame(header, msg).len(),
        }
    };
    let rec = sample_record(shape);
    let bytes = encode_record(&rec, shape.encoding).map_err(|e| e.to_string())?;
    let frags = fragment(1, 1000, 1_000_000_000, &bytes).map_err(|e| e.to_string())?;
    let mut record_sizes = Vec::new();
    for f in &frags {
        record_sizes.push(frame(&wire::fragment_to_message(f).map_err(|e| e.to_string())?));
    }
    let record_frames = (frags.len(), record_sizes.iter().sum());
    let participants: Vec<PlatformId> = (1..=shape.team.min(wire::MAX_PARTICIPANTS) as PlatformId).collect();
    let report = EpochAnnouncement {
        epoch: 1000,
        t: TimeUs(1_000_000_000),
        announcer: 1,
        participants,
        state: EpochState::COOPLOC_EPOCH_STATE_APPLIED,
        digest: 0x0123_4567_89ab_cdef,
        incomplete: Vec::new(),
    };
    let epoch = frame(&wire::epoch_to_message(&report).map_err(|e| e.to_string())?);
    let estimate = frame(&wire::estimate_to_message(&EstimateReport {
        platform: 1,
        t: TimeUs(1_000_000_000),
        epoch: 1000,
        method: Method::Decentralized,
        position_ned_m: Vector3::new(123.4, -56.7, -8.9),
        velocity_ned_m_s: Vector3::new(1.5, 0.25, -0.125),
        yaw_rad: 0.3,
        position_covariance_m2: nalgebra::Matrix3::new(2.0, 0.1, 0.01, 0.1, 2.5, 0.02, 0.01, 0.02, 4.0),
        yaw_variance_rad2: 1e-4,
        nis: 1.7,
        participants: shape.team.min(255) as u8,
        ranges: shape.ranges_per_node.min(255) as u8,
    }));
    let echoed = if shape.echo_ranges { &rec.ranges[..] } else { &[] };
    let range_sizes: Vec<usize> = echoed.iter().map(|r| frame(&wire::range_to_message(r, 1000))).collect();
    let heartbeat = frame(&wire::heartbeat(
        super::dialect::cooploc::MavType::MAV_TYPE_ONBOARD_CONTROLLER,
        super::dialect::cooploc::MavAutopilot::MAV_AUTOPILOT_INVALID,
    ));
    // The record's first fragment goes alone, ahead of the rest (see `node::runner`): a node
    // that measured no range learns the epoch from it.
    let rest = record_sizes.split_off(1);
    let mut batches = vec![record_sizes];
    if !rest.is_empty() {
        batches.push(rest);
    }
    batches.extend(range_sizes.iter().map(|&r| vec![r]));
    batches.push(vec![epoch, estimate]);
    Ok(EpochFrames {
        record_bytes: bytes.len(),
        kinds: vec![
            ("COOPLOC_STATE_FRAGMENT", record_frames.0, record_frames.1),
            ("COOPLOC_RANGE", range_sizes.len(), range_sizes.iter().sum()),
            ("COOPLOC_EPOCH_SET", 1, epoch),
            ("COOPLOC_ESTIMATE", 1, estimate),
        ],
        heartbeat_bytes: heartbeat,
        batches,
    })
}

/// A member's airtime slot on a shared channel of `bytes_per_s` (one way, every member's share
/// of it in turn), us: the time its largest record takes on the air, the record of a member that
/// ranged to every teammate (`shape.ranges_per_node` is not used). Every member of a team computes
/// the same slot: it depends on the team's size, state, encoding and signing only.
pub fn airtime_slot_us(shape: &TeamShape, bytes_per_s: f64) -> Result<u64, String> {
    if !(bytes_per_s.is_finite() && bytes_per_s > 0.0) {
        return Err(format!("a channel rate must be positive, got {bytes_per_s} B/s"));
    }
    let largest = TeamShape { ranges_per_node: shape.team.saturating_sub(1).min(super::record::MAX_RANGES), ..*shape };
    let frames = epoch_frames(&largest)?;
    Ok((frames.kinds[0].2 as f64 * 1e6 / bytes_per_s).ceil() as u64)
}

/// Datagrams that carry `sizes` (frames in order), packed up to [`MAX_DATAGRAM`] bytes or one
/// frame each: as many as [`pack`] makes.
pub fn datagrams(sizes: &[usize], packed: bool) -> usize {
    packing(sizes, if packed { MAX_DATAGRAM } else { 0 }).len()
}

/// Whether a node sends `msg` in a datagram of its own, ahead of the rest of its batch: a
/// record's first fragment (of several), so that it makes the epoch known to a node that measured
/// no range before the whole record has crossed a slow link ([`epoch_frames`] counts it so). The
/// runner's rule, and the fault harness's.
pub fn goes_alone(msg: &MavMessage) -> bool {
    matches!(msg, MavMessage::COOPLOC_STATE_FRAGMENT(f) if f.frag_index == 0 && f.frag_count > 1)
}

/// Where each datagram of `sizes` packed up to `max` bytes starts (frames in order, each whole;
/// a new datagram when the next frame would not fit; `max` 0: one frame each).
pub fn packing(sizes: &[usize], max: usize) -> Vec<usize> {
    let (mut starts, mut fill) = (Vec::new(), usize::MAX);
    for (i, &s) in sizes.iter().enumerate() {
        if fill.saturating_add(s) > max {
            starts.push(i);
            fill = 0;
        }
        fill += s;
    }
    starts
}

/// `frames` (in order) packed into datagrams of at most `max` bytes: the node's sending rule,
/// the one [`datagrams`] counts. A frame is never split (a frame larger than `max` travels
/// alone); `max` 0 sends one frame per datagram.
pub fn pack(frames: &[Vec<u8>], max: usize) -> Vec<Vec<u8>> {
    let sizes: Vec<usize> = frames.iter().map(Vec::len).collect();
    let starts = packing(&sizes, max);
    let ends = starts.iter().skip(1).copied().chain([frames.len()]);
    starts.iter().zip(ends).map(|(&a, b)| frames[a..b].concat()).collect()
}

/// Bytes per second for `shape` on `medium`.
pub fn rates(shape: &TeamShape, frames: &EpochFrames, medium: Medium) -> Rates {
    let per_epoch = frames.bytes() as f64;
    let hb = frames.heartbeat_bytes as f64;
    let mavlink = per_epoch * shape.epoch_hz + hb;
    let (copies, ip) = medium.copies_and_packing(shape.team);
    let (dgrams, overhead) = match ip {
        None => (0.0, 0.0),
        Some(packed) => {
            let d = frames.datagrams(packed) as f64 * shape.epoch_hz + 1.0;
            (d, d * IP_UDP_OVERHEAD as f64)
        }
    };
    let node = copies * (mavlink + overhead);
    Rates { node_bytes_per_s: node, team_bytes_per_s: node * shape.team as f64, node_datagrams_per_s: copies * dgrams }
}

/// Expected transmissions of a record beyond the first, per epoch, when each datagram is lost
/// with probability `loss` independently: a receiver misses a record sent in `datagrams`
/// datagrams with `q = 1 - (1 - loss)^datagrams`; the sender sends it again while any of its
/// `peers` misses it (each asks with a COOPLOC_EPOCH), so the expected number of resends is
/// `sum over t >= 1 of 1 - (1 - q^t)^peers`.
pub fn expected_resends(loss: f64, datagrams: usize, peers: usize) -> f64 {
    let q = 1.0 - (1.0 - loss.clamp(0.0, 0.999)).powi(datagrams as i32);
    (1..=200).map(|t| 1.0 - (1.0 - q.powi(t)).powi(peers as i32)).sum()
}

/// [`rates`] with the resends and requests that losing `loss` of the datagrams costs. A node
/// that misses part of a record says which fragments it holds (COOPLOC_EPOCH_SET), and the
/// sender resends only the others: each datagram of the record is sent again while any peer
/// misses it ([`expected_resends`] of one datagram, times the record's bytes). Every round of
/// requests until every peer holds the whole record ([`expected_resends`] of the record's
/// datagrams) costs one request from a node that missed something (counted here, by symmetry,
/// as this node's). Approximate where a peer missed every datagram (it asks for the whole
/// record, whose other datagrams may go to peers that had them).
pub fn rates_with_loss(shape: &TeamShape, frames: &EpochFrames, medium: Medium, loss: f64) -> Rates {
    let base = rates(shape, frames, medium);
    let (record_frames, record_bytes) = (frames.kinds[0].1, frames.kinds[0].2);
    let request_bytes = frames.kinds.iter().find(|k| k.0 == "COOPLOC_EPOCH_SET").map_or(0, |k| k.2);
    let (copies, ip) = medium.copies_and_packing(shape.team);
    let record_datagrams = match ip {
        Some(true) => frames.record_datagrams(true),
        _ => record_frames,
    };
    let peers = shape.team.saturating_sub(1);
    let rounds = expected_resends(loss, record_datagrams, peers) * shape.epoch_hz;
    let each_datagram = expected_resends(loss, 1, peers) * shape.epoch_hz;
    let extra_datagrams = if ip.is_some() { each_datagram * record_datagrams as f64 + rounds } else { 0.0 };
    let extra =
        copies * (each_datagram * record_bytes as f64 + rounds * request_bytes as f64 + extra_datagrams * IP_UDP_OVERHEAD as f64);
    Rates {
        node_bytes_per_s: base.node_bytes_per_s + extra,
        team_bytes_per_s: base.team_bytes_per_s + extra * shape.team as f64,
        node_datagrams_per_s: base.node_datagrams_per_s + copies * extra_datagrams,
    }
}

/// A link and what it carries.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct LinkKind {
    pub name: &'static str,
    /// Payload bytes per second the shared channel carries, all nodes together.
    pub capacity_bytes_per_s: f64,
    pub medium: Medium,
    /// Where the figure comes from.
    pub source: &'static str,
}

/// The links of the budget table.
pub fn standard_links() -> Vec<LinkKind> {
    vec![
        LinkKind {
            name: "SiK 64 kbit/s",
            capacity_bytes_per_s: 5_400.0,
            medium: Medium::Radio,
            source: "measured one-way throughput at the default air rate, ECC off (3,200 B/s with ECC)",
        },
        LinkKind {
            name: "SiK 250 kbit/s",
            capacity_bytes_per_s: 21_000.0,
            medium: Medium::Radio,
            source: "31,250 B/s raw times the 64 kbit/s radio's 0.675 efficiency (estimated, not measured)",
        },
        LinkKind {
            name: "Wi-Fi multicast",
            capacity_bytes_per_s: 375_000.0,
            medium: Medium::IpBroadcast { packed: true },
            source: "802.11g multicast at its 6 Mbit/s basic rate, half of it usable (assumed)",
        },
        LinkKind {
            name: "IP mesh unicast",
            capacity_bytes_per_s: 625_000.0,
            medium: Medium::IpUnicast { packed: true },
            source: "a 5 Mbit/s share of a MANET mesh radio, every peer sent its own copy (assumed)",
        },
    ]
}

/// The highest epoch rate `link` carries for `shape` (its own `epoch_hz` ignored), Hz: the
/// heartbeats first, the rest for epochs. None when the heartbeats alone fill it.
pub fn max_epoch_hz(shape: &TeamShape, frames: &EpochFrames, link: &LinkKind) -> Option<f64> {
    let at = |hz: f64| rates(&TeamShape { epoch_hz: hz, ..*shape }, frames, link.medium).team_bytes_per_s;
    let (base, slope) = (at(0.0), at(1.0) - at(0.0));
    (base < link.capacity_bytes_per_s && slope > 0.0).then(|| (link.capacity_bytes_per_s - base) / slope)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn shape(team: usize, encoding: Encoding, signed: bool) -> TeamShape {
        TeamShape { team, state_dim: 16, ranges_per_node: 2, epoch_hz: 1.0, encoding, signed, echo_ranges: true }
    }

    /// Every member computes the same slot (its own ranges do not count: the largest record's),
    /// the time the record's frames take at the rate; a rate that is not positive is refused.
    #[test]
    fn an_airtime_slot_is_the_largest_record_on_the_air() {
        let team = shape(3, Encoding::Compact, true);
        let slot = airtime_slot_us(&team, 5_400.0).unwrap();
        for ranges in [0, 1, 2] {
            assert_eq!(airtime_slot_us(&TeamShape { ranges_per_node: ranges, ..team }, 5_400.0).unwrap(), slot);
        }
        let largest = epoch_frames(&team).unwrap().kinds[0].2; // two ranges: every teammate
        assert_eq!(slot, (largest as f64 * 1e6 / 5_400.0).ceil() as u64);
        assert!(airtime_slot_us(&team, 21_000.0).unwrap() * 3 < slot, "a faster channel, a shorter slot");
        assert!(airtime_slot_us(&shape(8, Encoding::Compact, true), 5_400.0).unwrap() > slot, "more refs and ranges");
        for bad in [0.0, -1.0, f64::NAN, f64::INFINITY] {
            assert!(airtime_slot_us(&team, bad).unwrap_err().contains("positive"), "{bad}");
        }
    }

    #[test]
    fn sizes_follow_the_record_layout_and_signing_adds_13_bytes_a_frame() {
        let plain = epoch_frames(&shape(3, Encoding::F64, false)).unwrap();
        let signed = epoch_frames(&shape(3, Encoding::F64, true)).unwrap();
        // 40 header + (136 + 256) x 8 + 23 trailer + 3 refs x 14 + 2 ranges x 10.
        assert_eq!(plain.record_bytes, 40 + 392 * 8 + 23 + 3 * 14 + 2 * 10);
        assert_eq!(plain.kinds[0].1, plain.record_bytes.div_ceil(crate::protocol::fragment::FRAGMENT_CHUNK));
        assert_eq!(signed.bytes(), plain.bytes() + 13 * plain.frames());
        let compact = epoch_frames(&shape(3, Encoding::Compact, false)).unwrap();
        assert_eq!(compact.record_bytes, 40 + crate::protocol::compact::len(16) + 23 + 3 * 14 + 2 * 10);
        assert!(compact.bytes() * 2 < plain.bytes(), "{} against {}", compact.bytes(), plain.bytes());
    }

    #[test]
    fn unicast_sends_a_copy_per_peer_and_packing_saves_headers() {
        let s = shape(8, Encoding::F32, true);
        let f = epoch_frames(&s).unwrap();
        let radio = rates(&s, &f, Medium::Radio);
        let bcast = rates(&s, &f, Medium::IpBroadcast { packed: false });
        let packed = rates(&s, &f, Medium::IpBroadcast { packed: true });
        let uni = rates(&s, &f, Medium::IpUnicast { packed: true });
        assert_eq!(radio.node_bytes_per_s, (f.bytes() + f.heartbeat_bytes) as f64);
        assert_eq!(bcast.node_bytes_per_s - radio.node_bytes_per_s, 28.0 * (f.frames() + 1) as f64);
        assert!(packed.node_datagrams_per_s < bcast.node_datagrams_per_s);
        assert_eq!(uni.node_bytes_per_s, 7.0 * packed.node_bytes_per_s);
        assert_eq!(uni.team_bytes_per_s, 8.0 * uni.node_bytes_per_s);
        // 1000 + 400 + 72 fill one datagram exactly; 1472 a second; 1 a third.
        assert_eq!(datagrams(&[1000, 400, 72, 1472, 1], true), 3);
        assert_eq!(datagrams(&[1000, 400, 73], true), 2);
    }

    #[test]
    fn losses_cost_resends_as_the_geometric_rounds_say() {
        assert_eq!(expected_resends(0.0, 5, 2), 0.0);
        // One peer, one datagram: resends = q + q^2 + ... = q / (1 - q).
        assert!((expected_resends(0.1, 1, 1) - 0.1 / 0.9).abs() < 1e-12);
        let s = shape(3, Encoding::Compact, true);
        let f = epoch_frames(&s).unwrap();
        let m = Medium::IpUnicast { packed: false };
        assert_eq!(rates_with_loss(&s, &f, m, 0.0), rates(&s, &f, m));
        assert!(rates_with_loss(&s, &f, m, 0.02).node_bytes_per_s > rates(&s, &f, m).node_bytes_per_s);
    }

    #[test]
    fn the_highest_epoch_rate_fills_the_link_exactly() {
        let s = shape(3, Encoding::Compact, true);
        let f = epoch_frames(&s).unwrap();
        for link in standard_links() {
            let hz = max_epoch_hz(&s, &f, &link).unwrap();
            let used = rates(&TeamShape { epoch_hz: hz, ..s }, &f, link.medium).team_bytes_per_s;
            assert!((used - link.capacity_bytes_per_s).abs() < 1e-6 * link.capacity_bytes_per_s, "{}", link.name);
        }
    }
}
