//! The state record of paper Step 3.2: what one platform broadcasts at a ranging epoch (its
//! nominal position and heading, the indices of those in its error state, its error covariance
//! and its recursive coefficient matrix), as bytes, and back.
//!
//! Layout, little endian:
//!
//! | offset | type | field |
//! |---|---|---|
//! | 0 | u8 | record version (3) |
//! | 1 | u8 | encoding of the matrices: 0 = f64, 1 = f32, 2 = compact (`COOPLOC_STATE_ENCODING`) |
//! | 2 | u16 | error-state dimension `n` (1..=64) |
//! | 4 | i8 x 3 | error-state index of the N, E, D position (-1: not a state) |
//! | 7 | i8 | error-state index of the heading (-1: none) |
//! | 8 | f64 x 3 | nominal position, NED, m |
//! | 32 | f64 | nominal yaw, rad (0 when there is no heading) |
//! | 40 | n(n+1)/2 values | covariance, upper triangle, row major (compact: see [`super::compact`]) |
//! | .. | n*n values | recursive coefficient matrix Psi, row major (compact: see [`super::compact`]) |
//! | .. | u64 | digest of the sender's cross-covariance store before this epoch (0: none kept) |
//! | .. | u32, u64 | the sender's own reference: the epoch and token of the joint update that last reset its Psi (token 0: it started independently of the team, first heard of at that epoch) |
//! | .. | u8 | flags: bit 0 `FRESH` (initialised independently of every teammate, no epoch applied yet); bits 1-2 the epochs after this one the sender asks the team to pass over, 0-3 ([`skip_of`]); the other bits 0 |
//! | .. | u8 | number `m` of references in the sender's store (0..=64) |
//! | .. | m x (u16, u32, u64) | each: platform, epoch, token (ascending platform ids) |
//! | .. | u8 | number `k` of ranges the sender's radio measured at this epoch (0..=32) |
//! | .. | k x (u16, f32, f32) | each range: platform ranged to, distance m, sigma m |
//!
//! The trailer makes a record the sender's whole contribution to the epoch's joint problem: its
//! state, its ranges, the digest every receiver compares with its own store, and the references
//! that tell every receiver whether the sender's store is valid for the participants (each
//! participant's own reference equal to the one the store holds for it). A node that holds
//! a platform's record therefore holds that platform's ranges too, resends included, and nodes
//! that hold the same records solve the same problem.
//!
//! **Quantisation rule.** Every node, the sender included, runs the joint update on the snapshot
//! that [`decode`] returns for the bytes that went on the wire, never on its own unrounded
//! values, so that all nodes compute the same posterior bit for bit. With f64 the round trip is
//! exact; with f32 the covariance and Psi are rounded (half the bytes), and the covariance is
//! rebuilt symmetric from its upper triangle; the compact encoding (under a third of the f64 matrix bytes)
//! sends the covariance in correlation form as 16-bit fixed point with a rounding bound added
//! back, so that what a receiver decodes is never smaller than what the sender holds.

use nalgebra::{DMatrix, Vector3};

use crate::estimation::{CrossCovariances, Geometry, Heading, PlatformId, RangeSample, Snapshot, StoreError, StoreRef};
use crate::time::TimeUs;

/// Record format version.
pub const RECORD_VERSION: u8 = 3;
/// Most ranges one record carries.
pub const MAX_RANGES: usize = 32;
/// Fixed trailer bytes: digest, own reference, flags, reference count, range count.
const TRAILER_LEN: usize = 8 + 12 + 1 + 1 + 1;
const RANGE_LEN: usize = 10;
const REF_LEN: usize = 14;
/// Most references one record (or store) carries: one per team member.
pub const MAX_REFS: usize = 64;
/// Record flag: the sender was initialised independently of every teammate and has run no
/// epoch since (a fresh or late joiner): its error is uncorrelated with everyone's.
pub const FLAG_FRESH: u8 = 1;
/// Record flags, bits 1-2: how many epochs after this one the sender asks the team to pass over
/// (it is falling behind the epochs: see the node core's docs). Every node that runs the epoch
/// on the same records passes over the most any of them asks.
pub const FLAG_SKIP_MASK: u8 = 0b110;
const FLAG_SKIP_SHIFT: u8 = 1;
/// The most epochs one record can ask the team to pass over.
pub const MAX_SKIP: u8 = FLAG_SKIP_MASK >> FLAG_SKIP_SHIFT;
/// Every flag a record may carry.
const KNOWN_FLAGS: u8 = FLAG_FRESH | FLAG_SKIP_MASK;

/// The epochs after this one that a record's `flags` ask the team to pass over.
pub fn skip_of(flags: u8) -> u8 {
    (flags & FLAG_SKIP_MASK) >> FLAG_SKIP_SHIFT
}

/// `flags` asking the team to pass over `skip` epochs ([`MAX_SKIP`] at most).
pub fn with_skip(flags: u8, skip: u8) -> u8 {
    (flags & !FLAG_SKIP_MASK) | (skip.min(MAX_SKIP) << FLAG_SKIP_SHIFT)
}
/// Largest error-state dimension a record may carry.
pub const MAX_DIM: usize = 64;
const HEADER_LEN: usize = 40;

/// Number format of the matrices on the wire.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum Encoding {
    F64 = 0,
    F32 = 1,
    /// 16-bit fixed point in correlation form (see [`super::compact`]).
    Compact = 2,
}

impl Encoding {
    /// Every encoding, in wire order.
    pub const ALL: [Encoding; 3] = [Encoding::F64, Encoding::F32, Encoding::Compact];

    /// Its name on the command line and in tables.
    pub fn name(self) -> &'static str {
        match self {
            Encoding::F64 => "f64",
            Encoding::F32 => "f32",
            Encoding::Compact => "compact",
        }
    }

    /// Parses a command-line name.
    pub fn from_name(s: &str) -> Option<Encoding> {
        Encoding::ALL.into_iter().find(|e| e.name() == s)
    }

    fn width(self) -> usize {
        match self {
            Encoding::F64 => 8,
            Encoding::F32 | Encoding::Compact => 4,
        }
    }
}

/// Why a record could not be built or read.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum RecordError {
    #[error("state record too short: {got} bytes, need {need}")]
    TooShort { got: usize, need: usize },
    #[error("state record has {got} bytes, {expected} expected for its dimension and encoding")]
    LengthMismatch { got: usize, expected: usize },
    #[error("unsupported state record version {0}")]
    Version(u8),
    #[error("unknown state encoding {0}")]
    Encoding(u8),
    #[error("state dimension {0} outside 1..={MAX_DIM}")]
    Dimension(usize),
    #[error("state index {index} out of range for dimension {dim}")]
    Index { index: i8, dim: usize },
    #[error("non-finite value in the state record ({0})")]
    NonFinite(&'static str),
    #[error("state record carries {0} ranges, at most {MAX_RANGES}")]
    TooManyRanges(usize),
    #[error("state record range {index} is not usable: {why}")]
    Range { index: usize, why: &'static str },
    #[error("state record has unknown flags {0:#04x}")]
    Flags(u8),
    #[error("{0} store references, at most {MAX_REFS}")]
    TooManyRefs(usize),
    #[error("store references are not in ascending platform order")]
    RefOrder,
    #[error("store snapshot: {0}")]
    Store(StoreError),
    #[error("store snapshot's blocks and references do not give the digest it claims")]
    StoreDigest,
    #[error("store snapshot of {0} bytes, more than {MAX_STORE_LEN} or 65,535 parts")]
    StoreLength(usize),
    #[error("store part: {0}")]
    StorePart(&'static str),
}

/// One platform's contribution to an epoch: its state, the digest of its cross-covariance
/// store before the epoch, its flags and the ranges its radio measured.
#[derive(Debug, Clone, PartialEq)]
pub struct StateRecord {
    pub snapshot: Snapshot,
    pub digest: u64,
    /// The joint update that last reset the sender's Psi (see [`StoreRef`]).
    pub own_ref: StoreRef,
    /// The references held in the sender's store, ascending platform ids.
    pub refs: Vec<(PlatformId, StoreRef)>,
    pub flags: u8,
    /// Ranges measured by this platform (`from` = its id), at the epoch's time.
    pub ranges: Vec<RangeSample>,
}

/// Bytes of a record of dimension `n` in `encoding` carrying no range and no reference.
pub fn record_len(n: usize, encoding: Encoding) -> usize {
    matrices_end(n, encoding) + TRAILER_LEN
}

fn matrices_end(n: usize, encoding: Encoding) -> usize {
    match encoding {
        Encoding::Compact => HEADER_LEN + super::compact::len(n),
        _ => HEADER_LEN + (n * (n + 1) / 2 + n * n) * encoding.width(),
    }
}

fn index_byte(i: Option<usize>) -> i8 {
    i.map_or(-1, |v| v as i8)
}

/// Serialises a snapshot alone (no digest, no flag, no range).
pub fn encode(s: &Snapshot, encoding: Encoding) -> Result<Vec<u8>, RecordError> {
    let rec = StateRecord {
        snapshot: s.clone(),
        digest: 0,
        own_ref: StoreRef::fresh(0),
        refs: Vec::new(),
        flags: 0,
        ranges: Vec::new(),
    };
    encode_record(&rec, encoding)
}

/// Serialises a record. Fails on a dimension above [`MAX_DIM`], a non-finite value, more than
/// [`MAX_RANGES`] ranges or a range that does not start at the record's platform. Ranges are
/// written as f32 (see [`crate::protocol::wire::range_as_sent`]).
pub fn encode_record(rec: &StateRecord, encoding: Encoding) -> Result<Vec<u8>, RecordError> {
    let s = &rec.snapshot;
    let n = s.dim();
    if rec.ranges.len() > MAX_RANGES {
        return Err(RecordError::TooManyRanges(rec.ranges.len()));
    }
    if rec.flags & !KNOWN_FLAGS != 0 {
        return Err(RecordError::Flags(rec.flags));
    }
    check_refs(&rec.refs)?;
    for (index, r) in rec.ranges.iter().enumerate() {
        check_range(index, s.id, r.to, r.range_m, r.sigma_m)?;
        if r.from != s.id {
            return Err(RecordError::Range { index, why: "measured by another platform" });
        }
    }
    if n == 0 || n > MAX_DIM {
        return Err(RecordError::Dimension(n));
    }
    if s.psi.nrows() != n || s.psi.ncols() != n || s.covariance.ncols() != n {
        return Err(RecordError::Dimension(n));
    }
    let g = &s.geometry;
    if !g.position_ned_m.iter().all(|v| v.is_finite()) || g.heading.is_some_and(|h| !h.yaw_rad.is_finite()) {
        return Err(RecordError::NonFinite("position or heading"));
    }
    if !s.covariance.iter().chain(s.psi.iter()).all(|v| v.is_finite()) {
        return Err(RecordError::NonFinite("covariance or Psi"));
    }
    let mut out = Vec::with_capacity(record_len(n, encoding));
    out.push(RECORD_VERSION);
    out.push(encoding as u8);
    out.extend_from_slice(&(n as u16).to_le_bytes());
    for i in g.position_index {
        out.push(index_byte(i) as u8);
    }
    out.push(index_byte(g.heading.map(|h| h.index)) as u8);
    for v in g.position_ned_m.iter().chain(std::iter::once(&g.heading.map_or(0.0, |h| h.yaw_rad))) {
        out.extend_from_slice(&v.to_le_bytes());
    }
    if encoding == Encoding::Compact {
        super::compact::put(&mut out, &s.covariance, &s.psi);
    } else {
        let mut put = |v: f64| match encoding {
            Encoding::F32 => out.extend_from_slice(&(v as f32).to_le_bytes()),
            _ => out.extend_from_slice(&v.to_le_bytes()),
        };
        for r in 0..n {
            for c in r..n {
                put(s.covariance[(r, c)]);
            }
        }
        for r in 0..n {
            for c in 0..n {
                put(s.psi[(r, c)]);
            }
        }
    }
    out.extend_from_slice(&rec.digest.to_le_bytes());
    out.extend_from_slice(&rec.own_ref.epoch.to_le_bytes());
    out.extend_from_slice(&rec.own_ref.token.to_le_bytes());
    out.push(rec.flags);
    put_refs(&mut out, &rec.refs);
    out.push(rec.ranges.len() as u8);
    for r in &rec.ranges {
        out.extend_from_slice(&r.to.to_le_bytes());
        out.extend_from_slice(&(r.range_m as f32).to_le_bytes());
        out.extend_from_slice(&(r.sigma_m as f32).to_le_bytes());
    }
    Ok(out)
}

fn check_range(index: usize, from: PlatformId, to: PlatformId, range_m: f64, sigma_m: f64) -> Result<(), RecordError> {
    let why = if to == from {
        "a range to the sender itself"
    } else if !(range_m.is_finite() && range_m >= 0.0) {
        "distance not finite and non-negative"
    } else if !(sigma_m.is_finite() && sigma_m > 0.0) {
        "sigma not finite and positive"
    } else {
        return Ok(());
    };
    Err(RecordError::Range { index, why })
}

/// Reads a record back into the snapshot of platform `id` (see [`decode_record`]).
pub fn decode(id: PlatformId, bytes: &[u8]) -> Result<Snapshot, RecordError> {
    decode_record(id, TimeUs(0), bytes).map(|r| r.snapshot)
}

/// Reads a record of platform `id` back: exactly the values that went on the wire; its ranges
/// are stamped `t` (the epoch's time, carried by the fragments). Any malformed input is an
/// error, never a panic.
pub fn decode_record(id: PlatformId, t: TimeUs, bytes: &[u8]) -> Result<StateRecord, RecordError> {
    if bytes.len() < HEADER_LEN {
        return Err(RecordError::TooShort { got: bytes.len(), need: HEADER_LEN });
    }
    if bytes[0] != RECORD_VERSION {
        return Err(RecordError::Version(bytes[0]));
    }
    let encoding = match bytes[1] {
        0 => Encoding::F64,
        1 => Encoding::F32,
        2 => Encoding::Compact,
        e => return Err(RecordError::Encoding(e)),
    };
    let n = u16::from_le_bytes([bytes[2], bytes[3]]) as usize;
    if n == 0 || n > MAX_DIM {
        return Err(RecordError::Dimension(n));
    }
    let end = matrices_end(n, encoding);
    if bytes.len() < end + TRAILER_LEN {
        return Err(RecordError::LengthMismatch { got: bytes.len(), expected: end + TRAILER_LEN });
    }
    let digest = u64::from_le_bytes(bytes[end..end + 8].try_into().expect("8 bytes"));
    let own_ref = StoreRef {
        epoch: u32::from_le_bytes(bytes[end + 8..end + 12].try_into().expect("4 bytes")),
        token: u64::from_le_bytes(bytes[end + 12..end + 20].try_into().expect("8 bytes")),
    };
    let flags = bytes[end + 20];
    if flags & !KNOWN_FLAGS != 0 {
        return Err(RecordError::Flags(flags));
    }
    let (refs, o) = get_refs(bytes, end + 21)?;
    let k = *bytes.get(o).ok_or(RecordError::TooShort { got: bytes.len(), need: o + 1 })? as usize;
    if k > MAX_RANGES {
        return Err(RecordError::TooManyRanges(k));
    }
    let expected = o + 1 + k * RANGE_LEN;
    if bytes.len() != expected {
        return Err(RecordError::LengthMismatch { got: bytes.len(), expected });
    }
    let mut ranges = Vec::with_capacity(k);
    for index in 0..k {
        let o = o + 1 + index * RANGE_LEN;
        let to = u16::from_le_bytes([bytes[o], bytes[o + 1]]);
        let range_m = f32::from_le_bytes(bytes[o + 2..o + 6].try_into().expect("4 bytes")) as f64;
        let sigma_m = f32::from_le_bytes(bytes[o + 6..o + 10].try_into().expect("4 bytes")) as f64;
        check_range(index, id, to, range_m, sigma_m)?;
        ranges.push(RangeSample { t, from: id, to, range_m, sigma_m });
    }
    let index = |b: u8| -> Result<Option<usize>, RecordError> {
        match b as i8 {
            -1 => Ok(None),
            i if i >= 0 && (i as usize) < n => Ok(Some(i as usize)),
            i => Err(RecordError::Index { index: i, dim: n }),
        }
    };
    let position_index = [index(bytes[4])?, index(bytes[5])?, index(bytes[6])?];
    let heading_index = index(bytes[7])?;
    let f64_at = |o: usize| f64::from_le_bytes(bytes[o..o + 8].try_into().expect("8 bytes"));
    let position = Vector3::new(f64_at(8), f64_at(16), f64_at(24));
    let yaw = f64_at(32);
    let (covariance, psi) = if encoding == Encoding::Compact {
        super::compact::get(&bytes[HEADER_LEN..end], n).map_err(|e| match e {
            super::compact::CompactError::Scale => RecordError::NonFinite("compact sigma or Psi scale"),
            super::compact::CompactError::OutOfRange => RecordError::NonFinite("compact value -32768"),
            super::compact::CompactError::Inflation => RecordError::NonFinite("compact inflation above its bound"),
        })?
    } else {
        let w = encoding.width();
        let value_at = |k: usize| {
            let o = HEADER_LEN + k * w;
            match encoding {
                Encoding::F32 => f32::from_le_bytes(bytes[o..o + 4].try_into().expect("4 bytes")) as f64,
                _ => f64_at(o),
            }
        };
        let mut covariance = DMatrix::zeros(n, n);
        let mut k = 0;
        for r in 0..n {
            for c in r..n {
                let v = value_at(k);
                covariance[(r, c)] = v;
                covariance[(c, r)] = v;
                k += 1;
            }
        }
        let mut psi = DMatrix::zeros(n, n);
        for r in 0..n {
            for c in 0..n {
                psi[(r, c)] = value_at(k);
                k += 1;
            }
        }
        (covariance, psi)
    };
    if !position.iter().all(|v| v.is_finite()) || !yaw.is_finite() {
        return Err(RecordError::NonFinite("position or heading"));
    }
    if !covariance.iter().chain(psi.iter()).all(|v| v.is_finite()) {
        return Err(RecordError::NonFinite("covariance or Psi"));
    }
    let snapshot = Snapshot {
        id,
        geometry: Geometry {
            position_ned_m: position,
            position_index,
            heading: heading_index.map(|index| Heading { yaw_rad: yaw, index }),
        },
        covariance,
        psi,
    };
    Ok(StateRecord { snapshot, digest, own_ref, refs, flags, ranges })
}

fn check_refs(refs: &[(PlatformId, StoreRef)]) -> Result<(), RecordError> {
    if refs.len() > MAX_REFS {
        return Err(RecordError::TooManyRefs(refs.len()));
    }
    if refs.windows(2).any(|w| w[0].0 >= w[1].0) {
        return Err(RecordError::RefOrder);
    }
    Ok(())
}

fn put_refs(out: &mut Vec<u8>, refs: &[(PlatformId, StoreRef)]) {
    out.push(refs.len() as u8);
    for (p, r) in refs {
        out.extend_from_slice(&p.to_le_bytes());
        out.extend_from_slice(&r.epoch.to_le_bytes());
        out.extend_from_slice(&r.token.to_le_bytes());
    }
}

/// Reads a reference list at `o`; returns it and the offset after it.
fn get_refs(bytes: &[u8], o: usize) -> Result<(Vec<(PlatformId, StoreRef)>, usize), RecordError> {
    let m = *bytes.get(o).ok_or(RecordError::TooShort { got: bytes.len(), need: o + 1 })? as usize;
    if m > MAX_REFS {
        return Err(RecordError::TooManyRefs(m));
    }
    let end = o + 1 + m * REF_LEN;
    if bytes.len() < end {
        return Err(RecordError::TooShort { got: bytes.len(), need: end });
    }
    let refs: Vec<(PlatformId, StoreRef)> = (0..m)
        .map(|i| {
            let b = &bytes[o + 1 + i * REF_LEN..];
            let p = u16::from_le_bytes([b[0], b[1]]);
            let epoch = u32::from_le_bytes(b[2..6].try_into().expect("4 bytes"));
            let token = u64::from_le_bytes(b[6..14].try_into().expect("8 bytes"));
            (p, StoreRef { epoch, token })
        })
        .collect();
    check_refs(&refs)?;
    Ok((refs, end))
}

/// A node's cross-covariance store right after an epoch, sent to a teammate whose own store was
/// not valid for it (see `node::core`). Layout, little endian: u8 version (1), u32 epoch, u64
/// digest of the store before the epoch, u64 digest after it, the references (u8 count, then
/// (u16, u32, u64) each), u16 number of blocks, then each block: u16 i, u16 j (i < j), u8 rows,
/// u8 columns, rows x columns f64 row major. Blocks are always f64: the receiver must hold the
/// very bits the sender holds, or its digest would differ.
#[derive(Debug, Clone, PartialEq)]
pub struct StoreSnapshot {
    pub epoch: u32,
    pub digest_before: u64,
    pub store: CrossCovariances,
}

/// Store snapshot format version.
pub const STORE_VERSION: u8 = 1;

/// Serialises a store snapshot.
pub fn encode_store(s: &StoreSnapshot) -> Result<Vec<u8>, RecordError> {
    let refs: Vec<(PlatformId, StoreRef)> = s.store.references().collect();
    check_refs(&refs)?;
    let blocks: Vec<_> = s.store.blocks().collect();
    let mut out = Vec::with_capacity(32 + blocks.len() * (6 + 16 * 16 * 8));
    out.push(STORE_VERSION);
    out.extend_from_slice(&s.epoch.to_le_bytes());
    out.extend_from_slice(&s.digest_before.to_le_bytes());
    out.extend_from_slice(&s.store.digest().to_le_bytes());
    put_refs(&mut out, &refs);
    out.extend_from_slice(&(blocks.len() as u16).to_le_bytes());
    for ((i, j), m) in blocks {
        if m.nrows() > MAX_DIM || m.ncols() > MAX_DIM {
            return Err(RecordError::Dimension(m.nrows().max(m.ncols())));
        }
        out.extend_from_slice(&i.to_le_bytes());
        out.extend_from_slice(&j.to_le_bytes());
        out.push(m.nrows() as u8);
        out.push(m.ncols() as u8);
        for r in 0..m.nrows() {
            for c in 0..m.ncols() {
                out.extend_from_slice(&m[(r, c)].to_le_bytes());
            }
        }
    }
    Ok(out)
}

/// Reads a store snapshot back, checking its shape, its values and that its blocks and
/// references give the digest it claims.
pub fn decode_store(bytes: &[u8]) -> Result<StoreSnapshot, RecordError> {
    const HEAD: usize = 1 + 4 + 8 + 8;
    if bytes.len() < HEAD {
        return Err(RecordError::TooShort { got: bytes.len(), need: HEAD });
    }
    if bytes[0] != STORE_VERSION {
        return Err(RecordError::Version(bytes[0]));
    }
    let epoch = u32::from_le_bytes(bytes[1..5].try_into().expect("4 bytes"));
    let digest_before = u64::from_le_bytes(bytes[5..13].try_into().expect("8 bytes"));
    let digest_after = u64::from_le_bytes(bytes[13..21].try_into().expect("8 bytes"));
    let (refs, mut o) = get_refs(bytes, HEAD)?;
    let count = bytes.get(o..o + 2).ok_or(RecordError::TooShort { got: bytes.len(), need: o + 2 })?;
    let count = u16::from_le_bytes([count[0], count[1]]) as usize;
    o += 2;
    let mut blocks = Vec::with_capacity(count.min(4096));
    for _ in 0..count {
        let head = bytes.get(o..o + 6).ok_or(RecordError::TooShort { got: bytes.len(), need: o + 6 })?;
        let (i, j) = (u16::from_le_bytes([head[0], head[1]]), u16::from_le_bytes([head[2], head[3]]));
        let (rows, cols) = (head[4] as usize, head[5] as usize);
        if rows == 0 || cols == 0 || rows > MAX_DIM || cols > MAX_DIM {
            return Err(RecordError::Dimension(rows.max(cols)));
        }
        o += 6;
        let end = o + rows * cols * 8;
        let data = bytes.get(o..end).ok_or(RecordError::TooShort { got: bytes.len(), need: end })?;
        let m = DMatrix::from_row_iterator(
            rows,
            cols,
            data.chunks_exact(8).map(|c| f64::from_le_bytes(c.try_into().expect("8 bytes"))),
        );
        blocks.push(((i, j), m));
        o = end;
    }
    if o != bytes.len() {
        return Err(RecordError::LengthMismatch { got: bytes.len(), expected: o });
    }
    let store = CrossCovariances::from_parts(blocks, refs).map_err(RecordError::Store)?;
    if store.digest() != digest_after {
        return Err(RecordError::StoreDigest);
    }
    Ok(StoreSnapshot { epoch, digest_before, store })
}

/// Store part format version (a whole snapshot starts with [`STORE_VERSION`]).
pub const STORE_PART_VERSION: u8 = 2;
/// Bytes of a store part's header.
pub const STORE_PART_HEADER: usize = 1 + 2 + 2 + 4 + 4;
/// Largest store snapshot a node sends or assembles (8 MiB: a 64-member team of 16-state
/// platforms holds 2,016 blocks, 4.1 MB).
pub const MAX_STORE_LEN: usize = 8 << 20;

/// One part of a store snapshot. A snapshot (see [`encode_store`]) goes as parts so that a store
/// of any size fits the fragment series (255 fragments each): each part is one series of
/// COOPLOC_STORE_FRAGMENT. Layout, little endian: u8 version (2), u16 index, u16 count, u32
/// length of the whole snapshot, u32 CRC-32 of it, then the part's bytes: every part but the
/// last carries the same number of bytes, the last one the rest. Participants of an epoch hold
/// the same store, so a part from any of them fits the others'.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct StorePart {
    pub index: u16,
    pub count: u16,
    pub total_len: u32,
    pub crc32: u32,
    pub bytes: Vec<u8>,
}

/// Cuts an encoded snapshot into parts of at most `part_len` snapshot bytes each, every part
/// with its header.
pub fn store_parts(snapshot: &[u8], part_len: usize) -> Result<Vec<Vec<u8>>, RecordError> {
    let part_len = part_len.max(1);
    let count = snapshot.len().div_ceil(part_len);
    if snapshot.is_empty() || snapshot.len() > MAX_STORE_LEN || count > u16::MAX as usize {
        return Err(RecordError::StoreLength(snapshot.len()));
    }
    let crc = crc32fast::hash(snapshot);
    Ok(snapshot
        .chunks(part_len)
        .enumerate()
        .map(|(i, bytes)| {
            let mut out = Vec::with_capacity(STORE_PART_HEADER + bytes.len());
            out.push(STORE_PART_VERSION);
            out.extend_from_slice(&(i as u16).to_le_bytes());
            out.extend_from_slice(&(count as u16).to_le_bytes());
            out.extend_from_slice(&(snapshot.len() as u32).to_le_bytes());
            out.extend_from_slice(&crc.to_le_bytes());
            out.extend_from_slice(bytes);
            out
        })
        .collect())
}

/// Reads a store series' bytes: a part (Some), or a whole snapshot as releases before parts sent
/// it (None: decode it with [`decode_store`]).
pub fn decode_store_part(bytes: &[u8]) -> Result<Option<StorePart>, RecordError> {
    match bytes.first() {
        None => Err(RecordError::TooShort { got: 0, need: 1 }),
        Some(&STORE_VERSION) => Ok(None),
        Some(&STORE_PART_VERSION) => {
            if bytes.len() <= STORE_PART_HEADER {
                return Err(RecordError::TooShort { got: bytes.len(), need: STORE_PART_HEADER + 1 });
            }
            let index = u16::from_le_bytes([bytes[1], bytes[2]]);
            let count = u16::from_le_bytes([bytes[3], bytes[4]]);
            let total_len = u32::from_le_bytes(bytes[5..9].try_into().expect("4 bytes"));
            let crc32 = u32::from_le_bytes(bytes[9..13].try_into().expect("4 bytes"));
            if total_len as usize > MAX_STORE_LEN {
                return Err(RecordError::StoreLength(total_len as usize));
            }
            if index >= count {
                return Err(RecordError::StorePart("index beyond the count"));
            }
            let part = &bytes[STORE_PART_HEADER..];
            if part.len() > total_len as usize {
                return Err(RecordError::StorePart("longer than the whole snapshot"));
            }
            Ok(Some(StorePart { index, count, total_len, crc32, bytes: part.to_vec() }))
        }
        Some(&v) => Err(RecordError::Version(v)),
    }
}
