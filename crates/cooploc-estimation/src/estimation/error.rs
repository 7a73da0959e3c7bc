//! The one error type of the estimation core. Every variant names what was wrong; an update that
//! returns an error has left the filter exactly as it was.

use super::PlatformId;

#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum EstimationError {
    /// An input (sample, measurement, matrix) held NaN or an infinity.
    #[error("non-finite value in {what}")]
    NonFinite { what: &'static str },
    /// A matrix that must be positive definite could not be factorised.
    #[error("{what} is not positive definite (Cholesky factorisation failed)")]
    NotPositiveDefinite { what: &'static str },
    /// Matrix or vector sizes disagree.
    #[error("dimension mismatch in {what}: expected {expected}, got {got}")]
    DimensionMismatch { what: &'static str, expected: usize, got: usize },
    /// A value outside its physical or configured range (negative sigma, zero time step, ...).
    #[error("invalid {what}: {value}")]
    InvalidValue { what: &'static str, value: f64 },
    /// A sample older than the filter's current time.
    #[error("time went backwards in {what}: {from_us} us -> {to_us} us")]
    TimeWentBackwards { what: &'static str, from_us: u64, to_us: u64 },
    /// A measurement names a platform that is not part of the event.
    #[error("unknown platform {0}")]
    UnknownPlatform(PlatformId),
    /// The same platform appears twice where each may appear once.
    #[error("platform {0} appears more than once")]
    DuplicatePlatform(PlatformId),
    /// A measurement the platform's model cannot take (a bearing to a platform without heading,
    /// a range between co-located platforms, ...).
    #[error("measurement not applicable: {0}")]
    NotApplicable(&'static str),
}
