//! MAVLink 2 message signing (<https://mavlink.io/en/guide/message_signing.html>) for the
//! cooperative network, sans-io: the caller gives the clock.
//!
//! A team shares one 32-byte secret key ([`TeamKey`]: from a passphrase, hashed with SHA-256 as
//! MAVProxy's `signing setup` and pymavlink derive it, or 64 hex digits). Every frame a node sends
//! is signed ([`Signer`]): the incompatibility flag `SIGNED`, then 13 bytes after the CRC: the
//! link id, a 48-bit timestamp (10 us units since 2015-01-01 00:00 UTC, strictly increasing per
//! signer) and the first 6 bytes of `SHA-256(key, frame, link id, timestamp)`. The signature covers
//! every byte of the frame, header (system id, sequence, message id) and payload (a record's
//! platform, epoch and time) alike: a frame changed in transit fails.
//!
//! A [`Verifier`] accepts a frame only if it is signed with the team key and its timestamp has
//! not been accepted before on its stream (link id, system id, component id). The MAVLink guide
//! asks for a timestamp newer than the last one; over UDP with jitter that refuses every frame
//! overtaken by a later one (measured in `tests/netns.rs`: with 5 +- 3 ms of jitter the nodes
//! refused half of each other's frames as replays and ran 3 epochs of 380). So a verifier keeps,
//! per stream, the timestamps it accepted in the last [`REORDER_WINDOW`] (2 s, at most
//! [`REORDER_KEEP`] of them): a frame up to 2 s older than the stream's newest is accepted once,
//! a repeat of one it holds or anything older is refused as a replay. A stream seen for the first
//! time must not be more than a minute older than the newest timestamp known (the local clock,
//! or the newest accepted). Unsigned frames, frames signed with another key,
//! replayed or stale frames and malformed bytes are refused and counted ([`SigningCounters`]).
//! The stream table is bounded ([`MAX_STREAMS`]); only authenticated frames enter it.

use std::collections::HashMap;

use mavlink_core::{MAVLinkV2MessageRaw, MavHeader, MavlinkVersion, Message};
use sha2::{Digest, Sha256};

use super::MavMessage;
use super::framing::{IFLAG_SIGNED, SIGNATURE_LEN};

/// Unix time of the signing epoch, 2015-01-01 00:00:00 UTC, s.
const SIGNING_EPOCH_UNIX_S: u64 = 1_420_070_400;
/// Most streams a verifier remembers (the oldest is forgotten beyond).
pub const MAX_STREAMS: usize = 1024;
/// A new stream may be this much older than the newest timestamp known (one minute), 10 us.
const NEW_STREAM_WINDOW: u64 = 60 * 100_000;
/// A frame may be this much older than its stream's newest and still be taken (once), 10 us:
/// two seconds of reordering.
pub const REORDER_WINDOW: u64 = 2 * 100_000;
/// Most timestamps kept per stream inside the window (a faster stream's window shrinks).
pub const REORDER_KEEP: usize = 1024;

/// What a verifier remembers of one stream: every timestamp above `floor` it accepted.
#[derive(Debug, Clone)]
struct Stream {
    newest: u64,
    /// Timestamps at or below this are refused (out of the window, or forgotten for room).
    floor: u64,
    seen: std::collections::BTreeSet<u64>,
}

impl Stream {
    fn new(ts: u64) -> Self {
        Stream { newest: ts, floor: ts.saturating_sub(REORDER_WINDOW), seen: std::collections::BTreeSet::new() }
    }

    fn fresh(&self, ts: u64) -> bool {
        ts > self.floor && !self.seen.contains(&ts)
    }

    fn accept(&mut self, ts: u64) {
        self.seen.insert(ts);
        self.newest = self.newest.max(ts);
        self.floor = self.floor.max(self.newest.saturating_sub(REORDER_WINDOW));
        while self.seen.len() > REORDER_KEEP {
            let oldest = self.seen.pop_first().expect("non-empty");
            self.floor = self.floor.max(oldest);
        }
        let floor = self.floor;
        self.seen.retain(|&t| t > floor);
    }
}
/// Bytes of a MAVLink 2 header.
const HEADER_LEN: usize = 10;

/// The team's secret key.
#[derive(Clone, PartialEq, Eq)]
pub struct TeamKey([u8; 32]);

impl std::fmt::Debug for TeamKey {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str("TeamKey(..)")
    }
}

/// Why a key could not be read.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum KeyError {
    #[error("cannot read the team key file {path}: {message}")]
    Io { path: String, message: String },
    #[error("the team key file {0} is empty: give 64 hex digits or a passphrase")]
    Empty(String),
    #[error("no random source to make a key from: {0}")]
    NoRandom(String),
}

impl TeamKey {
    /// The 32 key bytes (for the mavlink crate's own signing on stream links).
    pub fn bytes(&self) -> [u8; 32] {
        self.0
    }

    /// SHA-256 of the passphrase (MAVProxy's `signing setup PASSPHRASE`, pymavlink's convention).
    pub fn from_passphrase(passphrase: &str) -> Self {
        TeamKey(Sha256::digest(passphrase.as_bytes()).into())
    }

    /// The raw 32 bytes.
    pub fn from_bytes(key: [u8; 32]) -> Self {
        TeamKey(key)
    }

    /// A key file: its first line, 64 hex digits (the key itself) or else a passphrase.
    pub fn from_file(path: &std::path::Path) -> Result<Self, KeyError> {
        let text = std::fs::read_to_string(path)
            .map_err(|e| KeyError::Io { path: path.display().to_string(), message: e.to_string() })?;
        let line = text.lines().next().unwrap_or("").trim();
        if line.is_empty() {
            return Err(KeyError::Empty(path.display().to_string()));
        }
        Ok(Self::from_hex(line).unwrap_or_else(|| Self::from_passphrase(line)))
    }

    /// A new key from the operating system's random source.
    pub fn generate() -> Result<Self, KeyError> {
        use rand::TryRngCore;
        let mut key = [0u8; 32];
        rand::rngs::OsRng.try_fill_bytes(&mut key).map_err(|e| KeyError::NoRandom(e.to_string()))?;
        Ok(TeamKey(key))
    }

    /// A new passphrase for a team key file (`cooploc keygen`): 48 characters of a 32-letter
    /// alphabet (240 bits) from the operating system's random source. A passphrase rather than
    /// the 64 hex digits of the key, so that MAVProxy's `signing setup PASSPHRASE` (SHA-256 of
    /// it, as [`TeamKey::from_passphrase`]) makes the same key.
    pub fn new_passphrase() -> Result<String, KeyError> {
        use rand::TryRngCore;
        const ALPHABET: &[u8; 32] = b"abcdefghijkmnpqrstuvwxyz23456789";
        let mut bytes = [0u8; 48];
        rand::rngs::OsRng.try_fill_bytes(&mut bytes).map_err(|e| KeyError::NoRandom(e.to_string()))?;
        Ok(bytes.iter().map(|b| ALPHABET[usize::from(b & 31)] as char).collect())
    }

    /// 64 hex digits, if that is what `s` is.
    pub fn from_hex(s: &str) -> Option<Self> {
        if s.len() != 64 || !s.bytes().all(|b| b.is_ascii_hexdigit()) {
            return None;
        }
        let mut key = [0u8; 32];
        for (i, k) in key.iter_mut().enumerate() {
            *k = u8::from_str_radix(&s[2 * i..2 * i + 2], 16).ok()?;
        }
        Some(TeamKey(key))
    }
}

/// A signing timestamp (10 us units since 2015-01-01 UTC) of Unix time `unix_us`.
pub fn timestamp_of(unix_us: u64) -> u64 {
    unix_us.saturating_sub(SIGNING_EPOCH_UNIX_S * 1_000_000) / 10
}

fn signature(key: &TeamKey, signed_part: &[u8], link_and_timestamp: &[u8]) -> [u8; 6] {
    let mut h = Sha256::new();
    h.update(key.0);
    h.update(signed_part);
    h.update(link_and_timestamp);
    let d = h.finalize();
    let mut out = [0u8; 6];
    out.copy_from_slice(&d[..6]);
    out
}

/// Signs what one node sends.
#[derive(Debug, Clone)]
pub struct Signer {
    key: TeamKey,
    link_id: u8,
    last: u64,
}

/// Headroom written into a signing state file above the last timestamp used (15 s, 10 us units):
/// the state is saved every few seconds, and a node that dies between two saves must still
/// resume above every timestamp it sent.
pub const STATE_HEADROOM: u64 = 1_500_000;

/// The text of a signing state file: the timestamp a restarted signer must stay above.
pub fn state_text(signer: &Signer) -> String {
    format!("{}\n", signer.last_timestamp() + STATE_HEADROOM)
}

/// Reads a signing state file's text (as [`state_text`] wrote it).
pub fn parse_state(text: &str) -> Result<u64, String> {
    let t = text.trim();
    t.parse::<u64>()
        .ok()
        .filter(|&v| v < 1 << 48)
        .ok_or_else(|| format!("{t:?} is not a signing timestamp (a whole number below 2^48)"))
}

impl Signer {
    /// A signer on link `link_id` whose timestamps will be after `after` (the last one a previous
    /// run of this node used, so that a restart with a clock behind is not taken for a replay).
    pub fn new(key: TeamKey, link_id: u8, after: u64) -> Self {
        Signer { key, link_id, last: after }
    }

    /// The last timestamp used.
    pub fn last_timestamp(&self) -> u64 {
        self.last
    }

    /// `msg` as one signed MAVLink 2 frame, at Unix time `unix_us`.
    pub fn frame(&mut self, header: MavHeader, msg: &MavMessage, unix_us: u64) -> Vec<u8> {
        let mut raw = MAVLinkV2MessageRaw::new();
        raw.serialize_message_for_signing(header, msg);
        self.last = timestamp_of(unix_us).max(self.last + 1);
        let mut bytes = raw.raw_bytes().to_vec();
        let n = bytes.len() - SIGNATURE_LEN;
        bytes[n] = self.link_id;
        bytes[n + 1..n + 7].copy_from_slice(&self.last.to_le_bytes()[..6]);
        let sig = signature(&self.key, &bytes[..n], &bytes[n..n + 7]);
        bytes[n + 7..].copy_from_slice(&sig);
        bytes
    }
}

/// Why a frame was refused.
#[derive(Debug, Clone, Copy, PartialEq, Eq, thiserror::Error)]
pub enum Refusal {
    #[error("not signed")]
    Unsigned,
    #[error("signature does not match the team key")]
    BadSignature,
    #[error("timestamp not newer than its stream's last (a replay)")]
    Replayed,
    #[error("a new stream more than a minute behind the clock")]
    Stale,
    #[error("not a valid MAVLink 2 frame of the dialect")]
    Malformed,
}

/// What a verifier accepted and refused.
#[derive(Debug, Clone, Default, PartialEq, Eq, serde::Serialize)]
pub struct SigningCounters {
    pub accepted: u64,
    pub unsigned: u64,
    pub bad_signature: u64,
    pub replayed: u64,
    pub stale: u64,
    pub malformed: u64,
}

impl SigningCounters {
    pub fn refused(&self) -> u64 {
        self.unsigned + self.bad_signature + self.replayed + self.stale + self.malformed
    }
}

/// What a verifier made of one datagram.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Verified {
    /// The accepted frames, in order.
    pub frames: Vec<(MavHeader, MavMessage)>,
    /// Where each accepted frame lies in the datagram (for logs: the bytes as received).
    pub spans: Vec<std::ops::Range<usize>>,
    /// Why each of the others was refused.
    pub refused: Vec<Refusal>,
}

/// Checks what a node receives (see the module documentation).
#[derive(Debug, Clone)]
pub struct Verifier {
    key: TeamKey,
    /// What was accepted per (link id, system id, component id).
    streams: HashMap<(u8, u8, u8), Stream>,
    /// The newest timestamp known: the local clock or the newest accepted.
    newest: u64,
    pub counters: SigningCounters,
}

impl Verifier {
    pub fn new(key: TeamKey) -> Self {
        Verifier { key, streams: HashMap::new(), newest: 0, counters: SigningCounters::default() }
    }

    /// Every frame in a datagram (or byte run), at Unix time `unix_us`: the accepted ones in
    /// order, and why each of the others was refused. Bytes that do not start a frame are
    /// skipped (counted once per run of them).
    pub fn datagram(&mut self, bytes: &[u8], unix_us: u64) -> Verified {
        let mut out = Verified::default();
        let refused = &mut out.refused;
        let mut at = 0;
        let mut skipping = false;
        while at < bytes.len() {
            if bytes[at] != mavlink_core::MAV_STX_V2 {
                if !skipping {
                    refused.push(self.count(Refusal::Malformed));
                    skipping = true;
                }
                at += 1;
                continue;
            }
            match self.frame(&bytes[at..], unix_us) {
                Ok((frame, len)) => {
                    out.frames.push(frame);
                    out.spans.push(at..at + len);
                    at += len;
                    skipping = false;
                }
                Err((Refusal::Malformed, _)) => {
                    if !skipping {
                        refused.push(self.count(Refusal::Malformed));
                        skipping = true;
                    }
                    at += 1;
                }
                Err((why, len)) => {
                    refused.push(self.count(why));
                    at += len;
                    skipping = false;
                }
            }
        }
        out
    }

    fn count(&mut self, why: Refusal) -> Refusal {
        let c = &mut self.counters;
        match why {
            Refusal::Unsigned => c.unsigned += 1,
            Refusal::BadSignature => c.bad_signature += 1,
            Refusal::Replayed => c.replayed += 1,
            Refusal::Stale => c.stale += 1,
            Refusal::Malformed => c.malformed += 1,
        }
        why
    }

    /// The frame at the start of `bytes` and its length, or why it is refused (and how many
    /// bytes to skip).
    #[allow(clippy::type_complexity)]
    fn frame(&mut self, bytes: &[u8], unix_us: u64) -> Result<((MavHeader, MavMessage), usize), (Refusal, usize)> {
        if bytes.len() < HEADER_LEN + 2 {
            return Err((Refusal::Malformed, 1));
        }
        let flags = bytes[2];
        let signed = flags & IFLAG_SIGNED != 0;
        if flags & !IFLAG_SIGNED != 0 {
            return Err((Refusal::Malformed, 1));
        }
        // bytes[0] is MAVLink 2's start marker: the length its header declares, if all there.
        let Some(len) = super::framing::frame_len(bytes) else {
            return Err((Refusal::Malformed, 1));
        };
        let mut buf = [0u8; mavlink_core::consts::MAX_FRAME_SIZE];
        buf[..len].copy_from_slice(&bytes[..len]);
        let raw = MAVLinkV2MessageRaw::from_bytes_unparsed(buf);
        if MavMessage::default_message_from_id(raw.message_id()).is_none() || !raw.has_valid_crc::<MavMessage>() {
            return Err((Refusal::Malformed, 1));
        }
        if !signed {
            return Err((Refusal::Unsigned, len));
        }
        let n = len - SIGNATURE_LEN;
        let link = bytes[n];
        let mut ts_bytes = [0u8; 8];
        ts_bytes[..6].copy_from_slice(&bytes[n + 1..n + 7]);
        let ts = u64::from_le_bytes(ts_bytes);
        if signature(&self.key, &bytes[..n], &bytes[n..n + 7]) != bytes[n + 7..len] {
            return Err((Refusal::BadSignature, len));
        }
        self.newest = self.newest.max(timestamp_of(unix_us));
        let stream = (link, bytes[5], bytes[6]);
        match self.streams.get(&stream) {
            Some(s) if !s.fresh(ts) => return Err((Refusal::Replayed, len)),
            None if ts + NEW_STREAM_WINDOW < self.newest => return Err((Refusal::Stale, len)),
            _ => {}
        }
        let decoded =
            MavMessage::parse(MavlinkVersion::V2, raw.message_id(), raw.payload()).map_err(|_| (Refusal::Malformed, 1))?;
        if !self.streams.contains_key(&stream) && self.streams.len() >= MAX_STREAMS {
            let oldest = self.streams.iter().min_by_key(|(_, s)| s.newest).map(|(k, _)| *k);
            if let Some(k) = oldest {
                self.streams.remove(&k);
            }
        }
        self.streams.entry(stream).or_insert_with(|| Stream::new(ts)).accept(ts);
        self.newest = self.newest.max(ts);
        self.counters.accepted += 1;
        let header = MavHeader { system_id: u32::from(bytes[5]), component_id: bytes[6], sequence: bytes[4] };
        Ok(((header, decoded), len))
    }
}

#[cfg(test)]
mod tests;
