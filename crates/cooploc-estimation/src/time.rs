//! Timestamps. MAVLink carries time as microseconds in a `u64` (`time_usec`); so does cooploc,
//! end to end. Durations for the math are derived once, here, in seconds.

use serde::{Deserialize, Serialize};

/// A point in time in microseconds (simulated or vehicle boot time, as the source defines it).
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord, Hash, Default, Serialize, Deserialize)]
pub struct TimeUs(pub u64);

impl TimeUs {
    /// Builds a timestamp from seconds, rounded to the nearest microsecond.
    /// Negative or non-finite seconds saturate to zero.
    pub fn from_secs_f64(s: f64) -> Self {
        if s.is_finite() && s > 0.0 { TimeUs((s * 1e6).round() as u64) } else { TimeUs(0) }
    }

    /// Seconds since time zero.
    pub fn as_secs_f64(self) -> f64 {
        self.0 as f64 * 1e-6
    }

    /// Signed seconds from `earlier` to `self` (negative when time went backwards).
    pub fn secs_since(self, earlier: TimeUs) -> f64 {
        if self.0 >= earlier.0 { (self.0 - earlier.0) as f64 * 1e-6 } else { -((earlier.0 - self.0) as f64 * 1e-6) }
    }
}

impl std::fmt::Display for TimeUs {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "{:.6} s", self.as_secs_f64())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn conversions_round_trip_and_sign() {
        let t = TimeUs::from_secs_f64(1.234_567_4);
        assert_eq!(t, TimeUs(1_234_567));
        assert!((t.as_secs_f64() - 1.234_567).abs() < 1e-12);
        assert!((TimeUs(1_000_000).secs_since(TimeUs(1_500_000)) + 0.5).abs() < 1e-12);
        assert_eq!(TimeUs::from_secs_f64(f64::NAN), TimeUs(0));
        assert_eq!(TimeUs::from_secs_f64(-3.0), TimeUs(0));
    }
}
