//! The state record of paper Step 3.2: what one platform broadcasts at a ranging epoch (its
//! nominal position and heading, the indices of those in its error state, its error covariance
//! and its recursive coefficient matrix), as bytes, and back.
//!
//! Layout, little endian:
//!
//! | offset | type | field |
//! |---|---|---|
//! | 0 | u8 | record version (1) |
//! | 1 | u8 | encoding of the matrices: 0 = f64, 1 = f32 (`COOPLOC_STATE_ENCODING`) |
//! | 2 | u16 | error-state dimension `n` (1..=64) |
//! | 4 | i8 x 3 | error-state index of the N, E, D position (-1: not a state) |
//! | 7 | i8 | error-state index of the heading (-1: none) |
//! | 8 | f64 x 3 | nominal position, NED, m |
//! | 32 | f64 | nominal yaw, rad (0 when there is no heading) |
//! | 40 | n(n+1)/2 values | covariance, upper triangle, row major |
//! | .. | n*n values | recursive coefficient matrix Psi, row major |
//!
//! **Quantisation rule.** Every node, the sender included, runs the joint update on the snapshot
//! that [`decode`] returns for the bytes that went on the wire, never on its own unrounded
//! values, so that all nodes compute the same posterior bit for bit. With f64 the round trip is
//! exact; with f32 the covariance and Psi are rounded (half the bytes), and the covariance is
//! rebuilt symmetric from its upper triangle.

use nalgebra::{DMatrix, Vector3};

use crate::estimation::{Geometry, Heading, PlatformId, Snapshot};

/// Record format version.
pub const RECORD_VERSION: u8 = 1;
/// Largest error-state dimension a record may carry.
pub const MAX_DIM: usize = 64;
const HEADER_LEN: usize = 40;

/// Number format of the matrices on the wire.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum Encoding {
    F64 = 0,
    F32 = 1,
}

impl Encoding {
    fn width(self) -> usize {
        match self {
            Encoding::F64 => 8,
            Encoding::F32 => 4,
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
}

/// Bytes of a record of dimension `n` in `encoding`.
pub fn record_len(n: usize, encoding: Encoding) -> usize {
    HEADER_LEN + (n * (n + 1) / 2 + n * n) * encoding.width()
}

fn index_byte(i: Option<usize>) -> i8 {
    i.map_or(-1, |v| v as i8)
}

/// Serialises a snapshot. Fails on a dimension above [`MAX_DIM`] or a non-finite value.
pub fn encode(s: &Snapshot, encoding: Encoding) -> Result<Vec<u8>, RecordError> {
    let n = s.dim();
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
    let mut put = |v: f64| match encoding {
        Encoding::F64 => out.extend_from_slice(&v.to_le_bytes()),
        Encoding::F32 => out.extend_from_slice(&(v as f32).to_le_bytes()),
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
    Ok(out)
}

/// Reads a record back into the snapshot of platform `id`: exactly the values that went on the
/// wire. Any malformed input is an error, never a panic.
pub fn decode(id: PlatformId, bytes: &[u8]) -> Result<Snapshot, RecordError> {
    if bytes.len() < HEADER_LEN {
        return Err(RecordError::TooShort { got: bytes.len(), need: HEADER_LEN });
    }
    if bytes[0] != RECORD_VERSION {
        return Err(RecordError::Version(bytes[0]));
    }
    let encoding = match bytes[1] {
        0 => Encoding::F64,
        1 => Encoding::F32,
        e => return Err(RecordError::Encoding(e)),
    };
    let n = u16::from_le_bytes([bytes[2], bytes[3]]) as usize;
    if n == 0 || n > MAX_DIM {
        return Err(RecordError::Dimension(n));
    }
    let expected = record_len(n, encoding);
    if bytes.len() != expected {
        return Err(RecordError::LengthMismatch { got: bytes.len(), expected });
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
    let w = encoding.width();
    let value_at = |k: usize| {
        let o = HEADER_LEN + k * w;
        match encoding {
            Encoding::F64 => f64_at(o),
            Encoding::F32 => f32::from_le_bytes(bytes[o..o + 4].try_into().expect("4 bytes")) as f64,
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
    if !position.iter().all(|v| v.is_finite()) || !yaw.is_finite() {
        return Err(RecordError::NonFinite("position or heading"));
    }
    if !covariance.iter().chain(psi.iter()).all(|v| v.is_finite()) {
        return Err(RecordError::NonFinite("covariance or Psi"));
    }
    Ok(Snapshot {
        id,
        geometry: Geometry {
            position_ned_m: position,
            position_index,
            heading: heading_index.map(|index| Heading { yaw_rad: yaw, index }),
        },
        covariance,
        psi,
    })
}
