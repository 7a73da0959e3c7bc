//! Cutting a state record into COOPLOC_STATE_FRAGMENT payloads and putting it back together.
//!
//! Fragments may arrive duplicated, reordered, interleaved with other platforms' and other
//! epochs', or not at all. The [`Reassembler`] keeps at most a fixed number of partial records
//! (oldest epoch evicted first) and hands out a record only when every fragment has arrived, the
//! fragments agree on the record's length, count and CRC-32, and the CRC-32 of the reassembled
//! bytes matches. Anything else is reported, never used.

use std::collections::BTreeMap;

use crate::estimation::PlatformId;

/// Data bytes per fragment (the `data` array of COOPLOC_STATE_FRAGMENT).
pub const FRAGMENT_DATA: usize = 232;
/// Largest record: 255 fragments.
pub const MAX_RECORD_LEN: usize = FRAGMENT_DATA * 255;

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
    /// `data_len` bytes of the record from offset `index * FRAGMENT_DATA`.
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
    #[error("record of {0} bytes is empty or longer than {MAX_RECORD_LEN}")]
    RecordLength(usize),
}

/// Cuts `record` into fragments.
pub fn fragment(platform: PlatformId, epoch: u32, time_usec: u64, record: &[u8]) -> Result<Vec<Fragment>, FragmentError> {
    if record.is_empty() || record.len() > MAX_RECORD_LEN || record.len() > u16::MAX as usize {
        return Err(FragmentError::RecordLength(record.len()));
    }
    let crc = crc32fast::hash(record);
    let count = record.len().div_ceil(FRAGMENT_DATA);
    Ok(record
        .chunks(FRAGMENT_DATA)
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
    have: Vec<bool>,
    received: usize,
    bytes: Vec<u8>,
}

/// Reassembles records from fragments with bounded memory.
#[derive(Debug)]
pub struct Reassembler {
    max_partials: usize,
    partials: BTreeMap<(u32, PlatformId), Partial>,
    /// Records completed recently, so that late duplicates are recognised (bounded like partials).
    done: BTreeMap<(u32, PlatformId), u32>,
    dropped: Vec<Incomplete>,
}

impl Reassembler {
    /// Keeps at most `max_partials` records in progress (each at most [`MAX_RECORD_LEN`] bytes).
    pub fn new(max_partials: usize) -> Self {
        Self { max_partials: max_partials.max(1), partials: BTreeMap::new(), done: BTreeMap::new(), dropped: Vec::new() }
    }

    /// Records in progress.
    pub fn in_progress(&self) -> usize {
        self.partials.len()
    }

    /// Records dropped incomplete since the last call (taken).
    pub fn take_dropped(&mut self) -> Vec<Incomplete> {
        std::mem::take(&mut self.dropped)
    }

    /// Drops every record in progress for epochs before `epoch` (their time has passed) and
    /// reports them as incomplete.
    pub fn expire_before(&mut self, epoch: u32) {
        let old: Vec<_> = self.partials.keys().filter(|(e, _)| *e < epoch).copied().collect();
        for key in old {
            self.drop_partial(key, "expired");
        }
        self.done.retain(|(e, _), _| *e >= epoch);
    }

    fn drop_partial(&mut self, key: (u32, PlatformId), reason: &'static str) {
        if let Some(p) = self.partials.remove(&key) {
            self.dropped.push(Incomplete { platform: key.1, epoch: key.0, received: p.received, count: p.count, reason });
        }
    }

    /// Takes one fragment.
    pub fn push(&mut self, f: &Fragment) -> Pushed {
        let len = f.record_len as usize;
        let count = f.count as usize;
        if len == 0 || count == 0 || count != len.div_ceil(FRAGMENT_DATA) {
            return Pushed::Rejected("record length and fragment count disagree");
        }
        let index = f.index as usize;
        if index >= count {
            return Pushed::Rejected("fragment index beyond the count");
        }
        let expected_len = if index + 1 == count { len - index * FRAGMENT_DATA } else { FRAGMENT_DATA };
        if f.data.len() != expected_len {
            return Pushed::Rejected("fragment data length does not fit the record length");
        }
        let key = (f.epoch, f.platform);
        if self.done.get(&key) == Some(&f.record_crc32) {
            return Pushed::Duplicate;
        }
        if let Some(p) = self.partials.get(&key)
            && (p.crc != f.record_crc32 || p.len != len || p.count != count || p.time_usec != f.time_usec)
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
                    have: vec![false; count],
                    received: 0,
                    bytes: vec![0; len],
                },
            );
        }
        let p = self.partials.get_mut(&key).expect("inserted");
        if p.have[index] {
            let o = index * FRAGMENT_DATA;
            return if p.bytes[o..o + f.data.len()] == f.data[..] {
                Pushed::Duplicate
            } else {
                self.drop_partial(key, "a fragment arrived twice with different data");
                Pushed::Rejected("a fragment arrived twice with different data")
            };
        }
        let o = index * FRAGMENT_DATA;
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
