//! The one MAVLink framer: where frames start and end in a run of bytes (a datagram, a log
//! message, a serial read), whether each is whole and CRC-valid, and what it holds. Every reader
//! of MAVLink bytes in cooploc goes through [`frames`] (or [`frame_len`] for a frame's length
//! alone); each decides what to do with what it finds (a node stops at the first bad bytes of a
//! datagram, the ground station skips them, the simulator counts them).
//!
//! A frame is MAVLink 1 (`0xFE`) or 2 (`0xFD`, signature included when its incompat flag 1 is
//! set), whole, with a valid CRC for a message id of the cooploc dialect. Bytes that are not the
//! start of such a frame are skipped one at a time (as MAVLink parsers resynchronise) and
//! counted in [`Frames::skipped`].
//!
//! A frame of a message the dialect does not know (an autopilot's own dialect: ArduPilot's
//! EKF_STATUS_REPORT, AHRS, ...) cannot have its CRC checked (its CRC_EXTRA is unknown): it is
//! taken by the length its header declares, as mavlink-router does, when that length is all
//! there and is followed by the end of the bytes or by another start marker. It comes out as a
//! [`Frame`] with [`Frame::known`] false and an `Err` message: readers skip it, but its header
//! (sequence number, component) is seen, so it is never counted as loss and never stops the
//! frames behind it. A real autopilot sends such frames all the time; bytes that fail both
//! rules are still garbage.

use mavlink_core::{MavHeader, MavlinkVersion, Message};

use super::MavMessage;

/// Start markers of MAVLink 1 and 2 frames.
pub const STX_V1: u8 = 0xFE;
pub const STX_V2: u8 = 0xFD;
/// MAVLink 2's incompat flag of a signed frame.
pub const IFLAG_SIGNED: u8 = 0x01;
/// Bytes of a MAVLink 2 signature.
pub const SIGNATURE_LEN: usize = 13;

/// The length a frame starting at `bytes[0]` declares in its header (signature included), or why
/// there is none: not a start marker, or fewer bytes than a header's first three.
pub fn declared_len(bytes: &[u8]) -> Result<usize, &'static str> {
    let (&stx, rest) = bytes.split_first().ok_or("empty")?;
    let payload_len = usize::from(*rest.first().ok_or("shorter than a header")?);
    match stx {
        // v1: STX, len, seq, sysid, compid, msgid, payload, crc(2).
        STX_V1 => Ok(6 + payload_len + 2),
        // v2: STX, len, incompat, compat, seq, sysid, compid, msgid(3), payload, crc(2), signature.
        STX_V2 => {
            let incompat = *rest.get(1).ok_or("shorter than a header")?;
            Ok(10 + payload_len + 2 + if incompat & IFLAG_SIGNED != 0 { SIGNATURE_LEN } else { 0 })
        }
        _ => Err("first byte is not a MAVLink start marker (0xFE or 0xFD)"),
    }
}

/// Length of the frame at the start of `bytes`, if its header says so and it is all there (its
/// CRC unchecked).
pub fn frame_len(bytes: &[u8]) -> Option<usize> {
    declared_len(bytes).ok().filter(|&len| bytes.len() >= len)
}

/// One whole, CRC-valid frame found in a byte run.
#[derive(Debug, Clone, PartialEq)]
pub struct Frame<'a> {
    /// Where it starts in the run.
    pub offset: usize,
    /// Its bytes, signature included.
    pub bytes: &'a [u8],
    pub header: MavHeader,
    pub version: MavlinkVersion,
    pub message_id: u32,
    /// A MAVLink 2 frame with a signature (unverified here; see [`super::signing`]).
    pub signed: bool,
    /// The message id is in the dialect and the CRC checked; false: a frame of another
    /// dialect, taken by its length (see the module documentation).
    pub known: bool,
    /// The decoded message, or why its payload did not decode (or why it was not decoded).
    pub message: Result<MavMessage, String>,
}

impl Frame<'_> {
    /// The frame's message with its header, when it decoded.
    pub fn decoded(&self) -> Option<(MavHeader, MavMessage)> {
        self.message.as_ref().ok().map(|m| (self.header, m.clone()))
    }
}

/// The frames of a byte run, in order (see [`frames`]).
#[derive(Debug, Clone)]
pub struct Frames<'a> {
    bytes: &'a [u8],
    pos: usize,
    skipped: usize,
}

impl Frames<'_> {
    /// Bytes skipped so far: not the start of a whole, CRC-valid frame.
    pub fn skipped(&self) -> usize {
        self.skipped
    }
}

/// Every whole, CRC-valid MAVLink 1 or 2 frame of `bytes`, in order; other bytes are skipped.
pub fn frames(bytes: &[u8]) -> Frames<'_> {
    Frames { bytes, pos: 0, skipped: 0 }
}

impl<'a> Iterator for Frames<'a> {
    type Item = Frame<'a>;

    fn next(&mut self) -> Option<Frame<'a>> {
        while self.pos < self.bytes.len() {
            let rest = &self.bytes[self.pos..];
            if let Some(frame) = frame_at(rest, self.pos) {
                self.pos += frame.bytes.len();
                return Some(frame);
            }
            self.pos += 1;
            self.skipped += 1;
        }
        None
    }
}

/// Whether `id` is a message of the cooploc dialect.
pub fn known_message(id: u32) -> bool {
    MavMessage::default_message_from_id(id).is_some()
}

/// The frame starting exactly at `bytes[0]`, if it is whole and CRC-valid, or whole, of a
/// message the dialect does not know, and followed by the end of `bytes` or a start marker.
pub fn frame_at_start(bytes: &[u8]) -> Option<Frame<'_>> {
    frame_at(bytes, 0)
}

/// The frame starting exactly at `rest[0]` (see [`frame_at_start`]).
fn frame_at(rest: &[u8], offset: usize) -> Option<Frame<'_>> {
    let len = frame_len(rest)?;
    let bytes = &rest[..len];
    let payload_len = usize::from(bytes[1]);
    // Header fields by version; a MAVLink 2 frame with an incompatibility flag other than
    // "signed" (32-bit system ids, or one not defined) is not one of ours.
    let (version, header_len, message_id, header, signed) = match bytes[0] {
        STX_V1 => (
            MavlinkVersion::V1,
            6,
            u32::from(bytes[5]),
            MavHeader { system_id: u32::from(bytes[3]), component_id: bytes[4], sequence: bytes[2] },
            false,
        ),
        _ => {
            let incompat = bytes[2];
            if incompat & !IFLAG_SIGNED != 0 {
                return None;
            }
            (
                MavlinkVersion::V2,
                10,
                u32::from_le_bytes([bytes[7], bytes[8], bytes[9], 0]),
                MavHeader { system_id: u32::from(bytes[5]), component_id: bytes[6], sequence: bytes[4] },
                incompat & IFLAG_SIGNED != 0,
            )
        }
    };
    let crc_at = header_len + payload_len;
    let expected = u16::from_le_bytes([bytes[crc_at], bytes[crc_at + 1]]);
    if x25_crc(&bytes[1..crc_at], MavMessage::extra_crc(message_id)) != expected {
        // Another dialect's message, taken by its length only where the next byte agrees.
        let next_agrees = rest.get(len).is_none_or(|&b| b == STX_V1 || b == STX_V2);
        if known_message(message_id) || !next_agrees {
            return None;
        }
        let message = Err(format!("message id {message_id} is not in the cooploc dialect (skipped by its length)"));
        return Some(Frame { offset, bytes, header, version, message_id, signed, known: false, message });
    }
    let message = MavMessage::parse(version, message_id, &bytes[header_len..crc_at]).map_err(|e| e.to_string());
    Some(Frame { offset, bytes, header, version, message_id, signed, known: true, message })
}

/// One byte of MAVLink's checksum (CRC-16/MCRF4XX, "X.25"), as the MAVLink C library
/// accumulates it.
const fn x25_byte(crc: u16, b: u8) -> u16 {
    let mut t = b ^ (crc & 0xFF) as u8;
    t ^= t << 4;
    let t = t as u16;
    (crc >> 8) ^ (t << 8) ^ (t << 3) ^ (t >> 4)
}

/// `X25_TABLES[k][v]`: the register's change from the byte value `v` followed by `k` zero
/// bytes (the checksum is linear, so four bytes' effects are found independently and xored:
/// "slicing by 4").
const X25_TABLES: [[u16; 256]; 4] = {
    let mut t = [[0u16; 256]; 4];
    let mut v = 0;
    while v < 256 {
        t[0][v] = x25_byte(0, v as u8);
        let mut k = 1;
        while k < 4 {
            t[k][v] = x25_byte(t[k - 1][v], 0);
            k += 1;
        }
        v += 1;
    }
    t
};

/// MAVLink's checksum of `data` followed by the message's CRC extra byte: four bytes per step
/// by [`X25_TABLES`], the rest byte by byte (the same value as [`x25_byte`] over every byte;
/// tested against `mavlink_core`).
fn x25_crc(data: &[u8], extra: u8) -> u16 {
    let t = &X25_TABLES;
    let mut crc: u16 = 0xFFFF;
    let chunks = data.chunks_exact(4);
    let rest = chunks.remainder();
    for c in chunks {
        let lo = crc ^ u16::from_le_bytes([c[0], c[1]]);
        crc = t[3][usize::from(lo & 0xFF)] ^ t[2][usize::from(lo >> 8)] ^ t[1][usize::from(c[2])] ^ t[0][usize::from(c[3])];
    }
    for &b in rest {
        crc = x25_byte(crc, b);
    }
    x25_byte(crc, extra)
}

/// A MAVLink 2 frame (system 1, component 1, sequence `seq`) of message `id`, which the cooploc
/// dialect does not know, with a 9-byte payload and the checksum its own dialect would give
/// (CRC_EXTRA 0x5A): what an autopilot of another dialect sends. For tests.
/// Which link a raw frame travelled on, and the system id of the process that saw it (logs
/// name their frame channels by it: `cooploc::recording::topics::frames`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub enum Link {
    /// The link to the process's own vehicle (autopilot or simulator).
    Vehicle(u8),
    /// The cooperative network shared by the nodes and the ground station.
    Coop(u8),
}

/// Whether the process received or sent a frame.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub enum Direction {
    Rx,
    Tx,
}

impl Direction {
    /// `"rx"` or `"tx"`, as in the topics and the channel metadata.
    pub fn as_str(self) -> &'static str {
        match self {
            Direction::Rx => "rx",
            Direction::Tx => "tx",
        }
    }
}

/// One received MAVLink frame: its header, the message (None: a message of another dialect,
/// whose header still counts for the link's sequence numbers) and the frame's bytes (for the
/// log).
pub type Received = (MavHeader, Option<MavMessage>, Vec<u8>);

/// The MAVLink v1 and v2 frames of one datagram, in order, frames of messages outside the
/// dialect included (message None: skipped by their length, see [`frames`]);
/// reading stops at the first bytes that are not a frame (CRC, truncation, a payload that does
/// not decode).
pub fn split_frames(bytes: &[u8]) -> Vec<Received> {
    let mut out = Vec::new();
    let mut next = 0;
    for f in frames(bytes) {
        if f.offset != next {
            break; // bytes that were not a frame came first
        }
        let msg = match f.message {
            Ok(m) => Some(m),
            Err(_) if !f.known => None,
            Err(_) => break,
        };
        next = f.offset + f.bytes.len();
        out.push((f.header, msg, f.bytes.to_vec()));
    }
    out
}

/// A test's frame of a message outside the dialect (id `id`, not in it), sequence `seq`.
pub fn foreign_frame(seq: u8, id: u32) -> Vec<u8> {
    assert!(!known_message(id), "{id} is in the dialect");
    let payload = [1u8, 2, 3, 4, 5, 6, 7, 8, 9];
    let mut f = vec![STX_V2, payload.len() as u8, 0, 0, seq, 1, 1];
    f.extend_from_slice(&id.to_le_bytes()[..3]);
    f.extend_from_slice(&payload);
    let crc = x25_crc(&f[1..], 0x5A);
    f.extend_from_slice(&crc.to_le_bytes());
    f
}

/// A vehicle's HEARTBEAT frame (system 1, component 1) with sequence `seq`, for tests.
pub fn heartbeat_frame(seq: u8) -> Vec<u8> {
    use crate::protocol::dialect::cooploc::{MavAutopilot, MavType};
    let msg = super::wire::heartbeat(MavType::MAV_TYPE_GROUND_ROVER, MavAutopilot::MAV_AUTOPILOT_ARDUPILOTMEGA);
    super::wire::to_frame(MavHeader { system_id: 1, component_id: 1, sequence: seq }, &msg)
}

#[cfg(test)]
mod tests {
    use super::heartbeat_frame as hb;
    use super::*;

    /// A frame of another dialect is taken by its length, header and all, not decoded; the
    /// frames around it are whole. Followed by bytes that start no frame, it is garbage.
    #[test]
    fn a_frame_of_another_dialect_is_skipped_by_its_length() {
        let foreign = foreign_frame(2, 50_123);
        let run = [hb(1), foreign.clone(), hb(3)].concat();
        let mut it = frames(&run);
        let got: Vec<Frame<'_>> = it.by_ref().collect();
        assert_eq!(it.skipped(), 0);
        assert_eq!(
            got.iter().map(|f| (f.header.sequence, f.known, f.message.is_ok())).collect::<Vec<_>>(),
            [(1, true, true), (2, false, false), (3, true, true)]
        );
        assert_eq!((got[1].message_id, got[1].bytes), (50_123, &foreign[..]));
        assert!(got[1].message.as_ref().unwrap_err().contains("not in the cooploc dialect"));
        // at the end of the run, too
        assert_eq!(frames(&foreign).count(), 1);
        // followed by bytes that start no frame: not a frame (its length may be noise)
        let noisy = [foreign.clone(), b"xyz".to_vec(), hb(3)].concat();
        let got: Vec<u8> = frames(&noisy).map(|f| f.header.sequence).collect();
        assert_eq!(got, [3]);
        // a frame of the dialect with a bad checksum is still refused, never taken by length
        let mut bad = hb(5);
        let last = bad.len() - 1;
        bad[last] ^= 0x55;
        assert_eq!(frames(&[bad, hb(6)].concat()).map(|f| f.header.sequence).collect::<Vec<_>>(), [6]);
        // ArduPilot's own messages are in the dialect now
        for (id, name) in [(193, "EKF_STATUS_REPORT"), (164, "SIMSTATE"), (163, "AHRS"), (9000, "WHEEL_DISTANCE")] {
            assert!(known_message(id), "{name}");
        }
    }
    use crate::protocol::dialect::cooploc::{MavAutopilot, MavType};
    use crate::protocol::wire;

    #[test]
    fn frames_are_found_in_order_with_garbage_between_them_skipped_and_counted() {
        let run = [b"xx".to_vec(), hb(1), vec![0xFD, 3], hb(2), hb(3)[..5].to_vec()].concat();
        let mut it = frames(&run);
        let got: Vec<(usize, u8)> = it.by_ref().map(|f| (f.offset, f.header.sequence)).collect();
        let n = hb(1).len();
        assert_eq!(got, vec![(2, 1), (2 + n + 2, 2)]);
        assert_eq!(it.skipped(), 2 + 2 + 5, "two bytes before, two between, a cut frame after");
    }

    /// Our checksum is mavlink's, on any bytes and extra byte.
    #[test]
    fn the_checksum_is_mavlinks() {
        let mut x: u32 = 12345;
        for n in 0..300 {
            let data: Vec<u8> = (0..n)
                .map(|_| {
                    x = x.wrapping_mul(1_103_515_245).wrapping_add(12345);
                    (x >> 16) as u8
                })
                .collect();
            let extra = (n * 7) as u8;
            assert_eq!(x25_crc(&data, extra), mavlink_core::calculate_crc(&data, extra), "{n} bytes");
        }
    }

    /// A frame with a 32-bit system id (or an incompatibility flag not defined) is refused, as
    /// before; a signed one is whole and says so (see below).
    #[test]
    fn frames_with_flags_we_do_not_speak_are_refused() {
        for flag in [0x02u8, 0x04, 0x80] {
            let mut f = hb(3);
            f[2] |= flag;
            // A valid checksum over the changed header: only the flag is wrong.
            let crc_at = 10 + usize::from(f[1]);
            let crc = x25_crc(&f[1..crc_at], MavMessage::extra_crc(0));
            f[crc_at..crc_at + 2].copy_from_slice(&crc.to_le_bytes());
            assert_eq!(frames(&f).count(), 0, "incompat flag {flag:#x}");
        }
    }

    #[test]
    fn a_bad_crc_is_not_a_frame_and_lengths_come_from_the_header() {
        let mut f = hb(7);
        assert_eq!(frame_len(&f), Some(f.len()));
        assert_eq!(frame_len(&f[..f.len() - 1]), None);
        assert_eq!(declared_len(&f[..3]), Ok(f.len()));
        assert!(declared_len(b"\x00\x01").is_err());
        let last = f.len() - 1;
        f[last] ^= 0xFF;
        assert_eq!(frames(&f).count(), 0);
        let v1 = [0xFE, 9, 0, 1, 1, 0];
        assert_eq!(declared_len(&v1), Ok(6 + 9 + 2));
    }

    #[test]
    fn a_signed_frame_is_whole_with_its_signature_and_says_so() {
        use crate::protocol::signing::{Signer, TeamKey};
        let msg = wire::heartbeat(MavType::MAV_TYPE_GCS, MavAutopilot::MAV_AUTOPILOT_INVALID);
        let mut s = Signer::new(TeamKey::from_passphrase("k"), 1, 0);
        let signed = s.frame(MavHeader { system_id: 9, component_id: 1, sequence: 3 }, &msg, 1_700_000_000_000_000);
        let got: Vec<Frame<'_>> = frames(&signed).collect();
        assert_eq!(got.len(), 1);
        assert!(got[0].signed && got[0].bytes.len() == signed.len());
        assert_eq!(got[0].decoded().map(|(h, _)| h.system_id), Some(9));
        assert!(!frames(&hb(1)).next().unwrap().signed);
    }
}
