//! Cutting a state record into COOPLOC_STATE_FRAGMENT payloads and putting it back together.
//!
//! Fragments may arrive duplicated, reordered, interleaved with other platforms' and other
//! epochs', or not at all.
//!
//! A record is cut into chunks of [`FRAGMENT_CHUNK`] bytes (the last one shorter), so that a
//! signed fragment frame is at most [`MAX_RADIO_FRAME`] bytes on the wire: the dialect's `data`
//! array holds [`FRAGMENT_DATA`] bytes, and MAVLink 2 drops a payload's trailing zeros, so the
//! unused end of the array never goes on the air. The receiver does not assume the chunk size:
//! every fragment gives its record's (a fragment that is not the last carries `data_len` bytes
//! of a whole chunk; the last one ends the record), so records cut at any chunk size up to the
//! array's (those of logs written before the chunk shrank from 232 bytes) reassemble alike.
//!
//! The [`Reassembler`] keeps at most a fixed number of partial records
//! (oldest epoch evicted first) and hands out a record only when every fragment has arrived, the
//! fragments agree on the record's length, count and CRC-32, and the CRC-32 of the reassembled
//! bytes matches. Anything else is reported, never used.

use std::collections::BTreeMap;

use crate::estimation::PlatformId;

/// Size of the `data` array of COOPLOC_STATE_FRAGMENT and COOPLOC_STORE_FRAGMENT: the most a
/// fragment can carry.
pub const FRAGMENT_DATA: usize = 232;
/// The largest MAVLink frame a SiK radio's MAVLink framing keeps whole in one packet (its
/// packets hold 252 bytes): no frame cooploc sends is longer, signed.
pub const MAX_RADIO_FRAME: usize = 252;
/// Record bytes per fragment as sent: a signed fragment frame is 10 header bytes, 23 bytes of
/// fields before the data, the data, 2 checksum bytes and 13 signature bytes, at most
/// [`MAX_RADIO_FRAME`].
pub const FRAGMENT_CHUNK: usize = MAX_RADIO_FRAME - 10 - 23 - 2 - 13;
/// Largest record sent: 255 fragments of [`FRAGMENT_CHUNK`] bytes.
pub const MAX_RECORD_LEN: usize = FRAGMENT_CHUNK * 255;

/// The fields of one COOPLOC_STATE_FRAGMENT, independent of the generated message type.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Fragment {
    pub platform: PlatformId,
    pub epoch: u32,
    pub time_usec: u64,
    pub record_crc32: u32,
    pub record_len: u16,
    pub index: u8,
    pub count: u8,
    /// `data_len` bytes of the record from offset `index * chunk`, where the chunk is the
    /// record's (every fragment but the last carries a whole one).
    pub data: Vec<u8>,
    /// What the series carries.
    pub payload: Payload,
}

/// What a series of fragments carries (`COOPLOC_FRAGMENT_KIND`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum Payload {
    /// A state record (see [`crate::protocol::record`]).
    #[default]
    Record,
    /// A cross-covariance store snapshot (see [`crate::protocol::record::StoreSnapshot`]).
    Store,
}

/// Why a record cannot be fragmented.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum FragmentError {
    #[error("record of {0} bytes is empty or longer than 255 fragments")]
    RecordLength(usize),
}

/// Cuts `record` into fragments of [`FRAGMENT_CHUNK`] bytes.
pub fn fragment(platform: PlatformId, epoch: u32, time_usec: u64, record: &[u8]) -> Result<Vec<Fragment>, FragmentError> {
    fragment_in_chunks(platform, epoch, time_usec, record, FRAGMENT_CHUNK)
}

/// Cuts `record` into fragments of `chunk` bytes (1 to [`FRAGMENT_DATA`]; what older nodes sent:
/// 232).
pub fn fragment_in_chunks(
    platform: PlatformId,
    epoch: u32,
    time_usec: u64,
    record: &[u8],
    chunk: usize,
) -> Result<Vec<Fragment>, FragmentError> {
    let chunk = chunk.clamp(1, FRAGMENT_DATA);
    if record.is_empty() || record.len() > chunk * 255 || record.len() > u16::MAX as usize {
        return Err(FragmentError::RecordLength(record.len()));
    }
    let crc = crc32fast::hash(record);
    let count = record.len().div_ceil(chunk);
    Ok(record
        .chunks(chunk)
        .enumerate()
        .map(|(i, chunk)| Fragment {
            platform,
            epoch,
            time_usec,
            record_crc32: crc,
            record_len: record.len() as u16,
            index: i as u8,
            count: count as u8,
            data: chunk.to_vec(),
            payload: Payload::Record,
        })
        .collect())
}

/// A fully received, checked record.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Record {
    pub platform: PlatformId,
    pub epoch: u32,
    pub time_usec: u64,
    pub bytes: Vec<u8>,
}

/// What happened to one fragment.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Pushed {
    /// Stored; the record is not complete yet.
    Stored,
    /// Already had it.
    Duplicate,
    /// This fragment completed the record.
    Complete(Record),
    /// The fragment contradicts itself or the record's other fragments (reason given); dropped.
    Rejected(&'static str),
}

/// A record that was dropped before completing.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Incomplete {
    pub platform: PlatformId,
    pub epoch: u32,
    pub received: usize,
    pub count: usize,
    /// Why: evicted for room, superseded, reassembled bytes failing the CRC, or expired.
    pub reason: &'static str,
}

#[derive(Debug)]
struct Partial {
    time_usec: u64,
    crc: u32,
    len: usize,
    count: usize,
    /// Record bytes per fragment (the last one's fewer).
    chunk: usize,
    have: Vec<bool>,
    received: usize,
    bytes: Vec<u8>,
}

/// The chunk size of a record of `len` bytes in `count` fragments, from fragment `index` of `n`
/// bytes: a fragment before the last carries a whole chunk; the last one the rest, which the
/// chunks before it must leave (at least one byte, at most a chunk). None: the fragment cannot be
/// of such a record.
pub(crate) fn record_chunk(len: usize, count: usize, index: usize, n: usize) -> Option<usize> {
    if index + 1 < count {
        return Some(n);
    }
    if count == 1 {
        return (n == len).then_some(n);
    }
    let before = len.checked_sub(n).filter(|&b| b > 0 && b % (count - 1) == 0)?;
    let chunk = before / (count - 1);
    (n <= chunk).then_some(chunk)
}

/// A record in progress: epoch, platform, and its CRC-32 when each record is kept apart.
type Key = (u32, PlatformId, u32);

/// Reassembles records from fragments with bounded memory.
#[derive(Debug)]
pub struct Reassembler {
    max_partials: usize,
    /// Whether records of one platform and epoch with different CRC-32s are different records
    /// (the parts of a store) rather than a restarted sender's newer one.
    by_record: bool,
    partials: BTreeMap<Key, Partial>,
    /// Records completed recently, so that late duplicates are recognised (bounded like partials).
    done: BTreeMap<Key, u32>,
    dropped: Vec<Incomplete>,
}

impl Reassembler {
    /// Keeps at most `max_partials` records in progress (each at most 255 fragments); a record
    /// of a platform and epoch that differs from the one in progress supersedes it.
    pub fn new(max_partials: usize) -> Self {
        Self {
            max_partials: max_partials.max(1),
            by_record: false,
            partials: BTreeMap::new(),
            done: BTreeMap::new(),
            dropped: Vec::new(),
        }
    }

    /// As [`Self::new`], but records of one platform and epoch with different CRC-32s are all
    /// kept (the parts of a store snapshot, see [`StoreAssembler`]).
    pub fn keeping_each_record(max_partials: usize) -> Self {
        Self { by_record: true, ..Self::new(max_partials) }
    }

    /// Records in progress.
    pub fn in_progress(&self) -> usize {
        self.partials.len()
    }

    /// The records of `epoch` in progress: each one's platform and the fragments held of it
    /// (`true` at the index of each fragment received), by platform.
    pub fn incomplete(&self, epoch: u32) -> impl Iterator<Item = (PlatformId, &[bool])> {
        self.partials.range((epoch, 0, 0)..=(epoch, PlatformId::MAX, u32::MAX)).map(|(k, p)| (k.1, &p.have[..]))
    }

    /// The records of `epoch` in progress, with each one's CRC-32 and the fragments held of it
    /// (the store parts being put together: [`Self::keeping_each_record`]).
    pub fn incomplete_series(&self, epoch: u32) -> impl Iterator<Item = (u32, &[bool])> {
        self.partials.range((epoch, 0, 0)..=(epoch, PlatformId::MAX, u32::MAX)).map(|(_, p)| (p.crc, &p.have[..]))
    }

    /// Records dropped incomplete since the last call (taken).
    pub fn take_dropped(&mut self) -> Vec<Incomplete> {
        std::mem::take(&mut self.dropped)
    }

    /// Drops every record in progress for epochs before `epoch` (their time has passed) and
    /// reports them as incomplete.
    pub fn expire_before(&mut self, epoch: u32) {
        let old: Vec<_> = self.partials.keys().filter(|(e, _, _)| *e < epoch).copied().collect();
        for key in old {
            self.drop_partial(key, "expired");
        }
        self.done.retain(|(e, _, _), _| *e >= epoch);
    }

    fn drop_partial(&mut self, key: Key, reason: &'static str) {
        if let Some(p) = self.partials.remove(&key) {
            self.dropped.push(Incomplete { platform: key.1, epoch: key.0, received: p.received, count: p.count, reason });
        }
    }

    /// Takes one fragment.
    pub fn push(&mut self, f: &Fragment) -> Pushed {
        let len = f.record_len as usize;
        let count = f.count as usize;
        let index = f.index as usize;
        let n = f.data.len();
        if len == 0 || count == 0 || n == 0 || n > FRAGMENT_DATA {
            return Pushed::Rejected("fragment data length does not fit the record length");
        }
        if index >= count {
            return Pushed::Rejected("fragment index beyond the count");
        }
        let Some(chunk) = record_chunk(len, count, index, n) else {
            return Pushed::Rejected("fragment data length does not fit the record length");
        };
        if chunk > FRAGMENT_DATA || count != len.div_ceil(chunk) {
            return Pushed::Rejected("record length and fragment count disagree");
        }
        let key = (f.epoch, f.platform, if self.by_record { f.record_crc32 } else { 0 });
        if self.done.get(&key) == Some(&f.record_crc32) {
            return Pushed::Duplicate;
        }
        if let Some(p) = self.partials.get(&key)
            && (p.crc != f.record_crc32 || p.len != len || p.count != count || p.chunk != chunk || p.time_usec != f.time_usec)
        {
            // The same platform and epoch with another record: the sender restarted the epoch.
            // Keep the newer one.
            self.drop_partial(key, "superseded by a different record for the same epoch");
        }
        if !self.partials.contains_key(&key) {
            while self.partials.len() >= self.max_partials {
                let oldest = *self.partials.keys().next().expect("non-empty");
                if oldest.0 > f.epoch {
                    return Pushed::Rejected("older than every record in progress and no room");
                }
                self.drop_partial(oldest, "evicted for room");
            }
            self.partials.insert(
                key,
                Partial {
                    time_usec: f.time_usec,
                    crc: f.record_crc32,
                    len,
                    count,
                    chunk,
                    have: vec![false; count],
                    received: 0,
                    bytes: vec![0; len],
                },
            );
        }
        let p = self.partials.get_mut(&key).expect("inserted");
        if p.have[index] {
            let o = index * chunk;
            return if p.bytes[o..o + f.data.len()] == f.data[..] {
                Pushed::Duplicate
            } else {
                self.drop_partial(key, "a fragment arrived twice with different data");
                Pushed::Rejected("a fragment arrived twice with different data")
            };
        }
        let o = index * chunk;
        p.bytes[o..o + f.data.len()].copy_from_slice(&f.data);
        p.have[index] = true;
        p.received += 1;
        if p.received < p.count {
            return Pushed::Stored;
        }
        let p = self.partials.remove(&key).expect("present");
        if crc32fast::hash(&p.bytes) != p.crc {
            self.dropped.push(Incomplete {
                platform: key.1,
                epoch: key.0,
                received: p.received,
                count: p.count,
                reason: "CRC-32 mismatch",
            });
            return Pushed::Rejected("CRC-32 mismatch");
        }
        self.done.insert(key, p.crc);
        while self.done.len() > 4 * self.max_partials {
            let oldest = *self.done.keys().next().expect("non-empty");
            self.done.remove(&oldest);
        }
        Pushed::Complete(Record { platform: key.1, epoch: key.0, time_usec: p.time_usec, bytes: p.bytes })
    }
}

/// What happened to one store part ([`StoreAssembler::push`]).
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum PartPushed {
    /// Kept; the snapshot is not complete yet.
    Stored,
    /// Already had it.
    Duplicate,
    /// This part completed the snapshot: its bytes, CRC-32 checked.
    Complete(Vec<u8>),
    /// The part contradicts itself or the snapshot's other parts (reason given); dropped.
    Rejected(&'static str),
}

/// Parts of one snapshot (count, length, CRC-32 agree).
#[derive(Debug, Clone)]
struct PartsOf {
    count: u16,
    total_len: u32,
    crc32: u32,
    /// Snapshot bytes per part (the last one's fewer).
    part_len: usize,
    got: BTreeMap<u16, Vec<u8>>,
}

/// Puts a store snapshot back together from its parts (see
/// [`crate::protocol::record::StorePart`]), whichever participant each came from and in any
/// order, keeping what arrived until the snapshot is whole: a part lost costs that part's
/// resend, not the snapshot's. At most [`StoreAssembler::CANDIDATES`] different snapshots at
/// once (a part of a further one is refused), each at most
/// [`crate::protocol::record::MAX_STORE_LEN`] bytes, filled only by what arrived.
#[derive(Debug, Clone, Default)]
pub struct StoreAssembler {
    candidates: Vec<PartsOf>,
}

impl StoreAssembler {
    /// Different snapshots assembled at once.
    pub const CANDIDATES: usize = 2;

    /// Takes one part.
    pub fn push(&mut self, p: crate::protocol::record::StorePart) -> PartPushed {
        let (count, index, total) = (usize::from(p.count), usize::from(p.index), p.total_len as usize);
        let Some(part_len) = record_chunk(total, count, index, p.bytes.len()) else {
            return PartPushed::Rejected("part length does not fit the snapshot's length");
        };
        if count != total.div_ceil(part_len) {
            return PartPushed::Rejected("snapshot length and part count disagree");
        }
        let same = |c: &PartsOf| c.count == p.count && c.total_len == p.total_len && c.crc32 == p.crc32;
        let k = match self.candidates.iter().position(same) {
            Some(k) => k,
            None if self.candidates.len() < Self::CANDIDATES => {
                self.candidates.push(PartsOf {
                    count: p.count,
                    total_len: p.total_len,
                    crc32: p.crc32,
                    part_len,
                    got: BTreeMap::new(),
                });
                self.candidates.len() - 1
            }
            None => return PartPushed::Rejected("parts of too many different snapshots"),
        };
        let c = &mut self.candidates[k];
        if c.part_len != part_len {
            return PartPushed::Rejected("part length differs from the snapshot's other parts");
        }
        if let Some(have) = c.got.get(&p.index) {
            return if *have == p.bytes {
                PartPushed::Duplicate
            } else {
                PartPushed::Rejected("a part arrived twice with different bytes")
            };
        }
        c.got.insert(p.index, p.bytes);
        if c.got.len() < count {
            return PartPushed::Stored;
        }
        let c = self.candidates.remove(k);
        let whole: Vec<u8> = c.got.into_values().flatten().collect();
        if whole.len() != total || crc32fast::hash(&whole) != c.crc32 {
            return PartPushed::Rejected("the parts together fail the snapshot's CRC-32");
        }
        PartPushed::Complete(whole)
    }

    /// Snapshots in progress.
    pub fn in_progress(&self) -> usize {
        self.candidates.len()
    }

    /// The indices of the parts held of the snapshot in progress furthest along (none when
    /// none is).
    pub fn held_parts(&self) -> Vec<u16> {
        self.candidates.iter().max_by_key(|c| c.got.len()).map(|c| c.got.keys().copied().collect()).unwrap_or_default()
    }
}
