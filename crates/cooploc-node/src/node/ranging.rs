//! A ranging device on the companion (a UWB module on a serial line or behind a UDP bridge),
//! besides the vehicle link: its stream, sans-io. Ranging radios are usually wired to the
//! companion, not the autopilot, and speak no MAVLink; `cooploc node --ranges URL` reads them.
//!
//! # The stream format
//!
//! One ASCII line per range, fields separated by commas, ended by `\n` (a `\r` before it is
//! ignored), at most [`MAX_LINE`] bytes:
//!
//! ```text
//! RANGE,<epoch>,<to>,<range_m>,<sigma_m>,<t_us>
//! RANGE,1042,2,37.412,0.10,1795000001000000
//! ```
//!
//! - `epoch`: the ranging epoch's number on the team's schedule (u32);
//! - `to`: the platform id ranged to (1..=255, not this node's own: the device measures from its
//!   own vehicle);
//! - `range_m`, `sigma_m`: the range and its standard deviation, m (finite; the range at least 0
//!   and below 100 km, the sigma above 0 and at most 100 m);
//! - `t_us`: when it was measured, in the team's clock (Unix time in microseconds, as the
//!   companion's clock keeps it), or `0`: stamped on arrival with the companion's clock.
//!
//! Lines of any other kind (a module's banner, its status lines) are counted and skipped; a
//! `RANGE` line with a bad field is counted by what is wrong and dropped; nothing in the stream
//! can stop or steer the node beyond one range. With an epoch grid, the time goes to the nearest
//! grid instant, as the vehicle link's ranges do ([`super::inputs::snap_to_grid`]).

use crate::estimation::{PlatformId, RangeSample};
use crate::time::TimeUs;

/// Longest line kept, bytes (a longer one is noise: dropped whole).
pub const MAX_LINE: usize = 200;
/// Farthest range taken, m.
const MAX_RANGE_M: f64 = 100_000.0;
/// Largest sigma taken, m.
const MAX_SIGMA_M: f64 = 100.0;

/// What the ranging stream held.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct RangeInputCounters {
    pub ranges: u64,
    /// Lines that are not ranges (another kind, empty).
    pub other_lines: u64,
    /// `RANGE` lines with a field missing, unreadable or out of its bounds.
    pub malformed: u64,
    /// Ranges to this node itself or to platform 0.
    pub bad_peer: u64,
    /// Lines longer than [`MAX_LINE`] (or not text), dropped whole.
    pub too_long: u64,
    /// Stamps moved to the epoch grid by more than a quarter of it.
    pub off_grid: u64,
}

/// Cuts a ranging device's byte stream into ranges (see the module documentation).
#[derive(Debug, Clone)]
pub struct RangeLines {
    own: PlatformId,
    grid_us: u64,
    buf: Vec<u8>,
    /// The line being dropped for its length, until its end.
    dropping: bool,
    pub counters: RangeInputCounters,
}

impl RangeLines {
    /// The stream of node `own`'s device, its ranges put on a grid of `epoch_grid_ms` (0: none).
    pub fn new(own: PlatformId, epoch_grid_ms: u32) -> Self {
        RangeLines {
            own,
            grid_us: u64::from(epoch_grid_ms) * 1000,
            buf: Vec::new(),
            dropping: false,
            counters: RangeInputCounters::default(),
        }
    }

    /// Takes the next bytes (a datagram or a serial read), which arrived when the companion's
    /// clock read `arrival_us` (Unix time, us): the ranges of the lines they complete, in order.
    pub fn push(&mut self, bytes: &[u8], arrival_us: u64) -> Vec<(u32, RangeSample)> {
        let mut out = Vec::new();
        for &b in bytes {
            if b == b'\n' {
                let line = std::mem::take(&mut self.buf);
                if std::mem::take(&mut self.dropping) {
                    continue;
                }
                if let Some(r) = self.line(&line, arrival_us) {
                    out.push(r);
                }
            } else if self.dropping {
                continue;
            } else if self.buf.len() >= MAX_LINE {
                self.buf.clear();
                self.dropping = true;
                self.counters.too_long += 1;
            } else {
                self.buf.push(b);
            }
        }
        out
    }

    fn line(&mut self, line: &[u8], arrival_us: u64) -> Option<(u32, RangeSample)> {
        let Ok(text) = std::str::from_utf8(line) else {
            self.counters.too_long += 1;
            return None;
        };
        let text = text.trim_end_matches('\r').trim();
        let Some(fields) = text.strip_prefix("RANGE,") else {
            self.counters.other_lines += 1;
            return None;
        };
        let Some((epoch, to, range_m, sigma_m, t_us)) = parse(fields) else {
            self.counters.malformed += 1;
            return None;
        };
        if to == 0 || to == self.own {
            self.counters.bad_peer += 1;
            return None;
        }
        let t = if t_us == 0 { arrival_us } else { t_us };
        let (t, off) = super::inputs::snap_to_grid(TimeUs(t), self.grid_us);
        if off {
            self.counters.off_grid += 1;
        }
        self.counters.ranges += 1;
        Some((epoch, RangeSample { t, from: self.own, to, range_m, sigma_m }))
    }
}

/// The five fields after `RANGE,`, checked.
fn parse(fields: &str) -> Option<(u32, PlatformId, f64, f64, u64)> {
    let mut it = fields.split(',').map(str::trim);
    let epoch = it.next()?.parse::<u32>().ok()?;
    let to = it.next()?.parse::<u8>().ok()?;
    let range_m = it.next()?.parse::<f64>().ok().filter(|r| r.is_finite() && (0.0..MAX_RANGE_M).contains(r))?;
    let sigma_m = it.next()?.parse::<f64>().ok().filter(|s| s.is_finite() && *s > 0.0 && *s <= MAX_SIGMA_M)?;
    let t_us = it.next()?.parse::<u64>().ok()?;
    if it.next().is_some() {
        return None;
    }
    Some((epoch, PlatformId::from(to), range_m, sigma_m, t_us))
}

/// One range as its device would write it (for tests and emulators).
pub fn range_line(epoch: u32, r: &RangeSample) -> String {
    format!("RANGE,{epoch},{},{},{},{}\n", r.to, r.range_m, r.sigma_m, r.t.0)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn lines_become_ranges_whatever_the_chunks() {
        let r = RangeSample { t: TimeUs(1_795_000_001_000_000), from: 1, to: 2, range_m: 37.412, sigma_m: 0.1 };
        let text = format!("UWB module v1.2 ready\r\n{}RANGE,7,3,12.5,0.2,0\r\n", range_line(1042, &r));
        for cut in 0..=text.len() {
            let mut d = RangeLines::new(1, 0);
            let mut got = d.push(&text.as_bytes()[..cut], 55);
            got.extend(d.push(&text.as_bytes()[cut..], 77));
            assert_eq!(got.len(), 2, "cut at {cut}");
            assert_eq!(got[0], (1042, r));
            // stamped on arrival: the bytes that completed it
            let arrival = if cut == text.len() { 55 } else { 77 };
            assert_eq!(got[1].1, RangeSample { t: TimeUs(arrival), from: 1, to: 3, range_m: 12.5, sigma_m: 0.2 });
            assert_eq!(d.counters.other_lines, 1);
            assert_eq!(d.counters.ranges, 2);
        }
    }

    #[test]
    fn bad_lines_are_counted_by_what_is_wrong_and_never_stop_the_stream() {
        let mut d = RangeLines::new(1, 100);
        let bad = [
            "RANGE,1,2,NaN,0.1,5",
            "RANGE,1,2,-1,0.1,5",
            "RANGE,1,2,5,0,5",
            "RANGE,1,2,5,1000,5",
            "RANGE,-1,2,5,0.1,5",
            "RANGE,1,256,5,0.1,5",
            "RANGE,1,2,5,0.1",
            "RANGE,1,2,5,0.1,5,9",
            "RANGE,1,2,1e400,0.1,5",
        ];
        let mut text = bad.join("\n");
        text.push('\n');
        text.push_str("RANGE,1,1,5,0.1,5\nRANGE,1,0,5,0.1,5\n");
        text.push_str(&"x".repeat(5 * MAX_LINE));
        text.push_str("\n\u{ff}\u{fe}\n");
        text.push_str("RANGE,9,2,5,0.1,1795000001030000\n");
        let got = d.push(text.as_bytes(), 0);
        assert_eq!(d.counters.malformed, bad.len() as u64);
        assert_eq!(d.counters.bad_peer, 2);
        assert_eq!(d.counters.too_long, 1);
        // the one good range, on the 100 ms grid (30 ms off: more than a quarter of it)
        assert_eq!(got.len(), 1);
        assert_eq!(got[0].1.t, TimeUs(1_795_000_001_000_000));
        assert_eq!(d.counters.off_grid, 1);
    }
}
