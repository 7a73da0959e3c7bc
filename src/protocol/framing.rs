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

use mavlink_core::{MAVLinkMessageRaw, MavHeader, MavlinkReader, MavlinkVersion, Message};

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
    /// The decoded message, or why its payload did not decode.
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

/// The frame starting exactly at `rest[0]`, if whole and CRC-valid.
fn frame_at(rest: &[u8], offset: usize) -> Option<Frame<'_>> {
    let len = frame_len(rest)?;
    let bytes = &rest[..len];
    let raw = MavlinkReader::new(bytes).read_any_raw_message::<MavMessage>().ok()?;
    let (raw_bytes, version, signed) = match &raw {
        MAVLinkMessageRaw::V1(m) => (m.raw_bytes(), MavlinkVersion::V1, false),
        MAVLinkMessageRaw::V2(m) => (m.raw_bytes(), MavlinkVersion::V2, m.incompatibility_flags() & IFLAG_SIGNED != 0),
    };
    // The reader resynchronises on its own: only a frame that starts here and fills `len` is it.
    if raw_bytes.len() != len || raw_bytes[0] != bytes[0] {
        return None;
    }
    let header = MavHeader { system_id: raw.system_id(), component_id: raw.component_id(), sequence: raw.sequence() };
    let message = MavMessage::parse(version, raw.message_id(), raw.payload()).map_err(|e| e.to_string());
    Some(Frame { offset, bytes, header, version, message_id: raw.message_id(), signed, message })
}

/// A vehicle's HEARTBEAT frame (system 1, component 1) with sequence `seq`, for tests.
#[cfg(test)]
pub(crate) fn heartbeat_frame(seq: u8) -> Vec<u8> {
    use crate::protocol::dialect::cooploc::{MavAutopilot, MavType};
    let msg = super::wire::heartbeat(MavType::MAV_TYPE_GROUND_ROVER, MavAutopilot::MAV_AUTOPILOT_ARDUPILOTMEGA);
    super::wire::to_frame(MavHeader { system_id: 1, component_id: 1, sequence: seq }, &msg)
}

#[cfg(test)]
mod tests {
    use super::heartbeat_frame as hb;
    use super::*;
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
