//! Link statistics of one MAVLink source (system id, component id) on one link: packets, bytes
//! per second over a sliding window, loss estimated from sequence-number gaps, last heard.
//! Pure values: the caller passes the receive time in.

use std::collections::{BTreeMap, VecDeque};
use std::net::SocketAddr;

use serde::Serialize;

use super::WallNs;
use crate::estimation::PlatformId;

/// Which link a frame came in on.
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord, Hash, Serialize)]
#[serde(tag = "kind", content = "vehicle", rename_all = "snake_case")]
pub enum Link {
    /// The cooperative network (UDP, shared with the nodes).
    Coop,
    /// The MAVLink link to a vehicle (`--vehicle ID=URL`), by platform id.
    Vehicle(PlatformId),
}

impl std::fmt::Display for Link {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Link::Coop => write!(f, "coop"),
            Link::Vehicle(id) => write!(f, "vehicle {id}"),
        }
    }
}

/// A MAVLink source on a link.
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord, Hash)]
pub struct SourceKey {
    pub link: Link,
    pub sysid: u32,
    pub compid: u8,
}

pub use crate::protocol::sequence::SequenceTracker;

/// Amounts (bytes, frames, estimates) received over the last `window_ns`, in buckets of a
/// fortieth of the window: memory bounded at any rate (at most 41 buckets), whatever a sender
/// floods. The ground station's rates and the MAVProxy module's (`cooploc.RateWindow`).
#[derive(Debug, Clone)]
pub struct RateWindow {
    window_ns: u64,
    bucket_ns: u64,
    /// (bucket index: receive time / bucket_ns, amount), oldest first.
    buckets: VecDeque<(u64, u64)>,
    first: Option<WallNs>,
}

/// Buckets a window is cut into.
const RATE_BUCKETS: u64 = 40;

impl RateWindow {
    pub fn new(window_ns: u64) -> Self {
        let window_ns = window_ns.max(RATE_BUCKETS);
        RateWindow { window_ns, bucket_ns: window_ns / RATE_BUCKETS, buckets: VecDeque::new(), first: None }
    }

    pub fn push(&mut self, rx: WallNs, amount: u64) {
        self.first.get_or_insert(rx);
        let i = rx.0 / self.bucket_ns;
        match self.buckets.back_mut() {
            Some((last, sum)) if *last == i => *sum = sum.saturating_add(amount),
            // (a receive time before the last bucket's joins it: the window only moves forward)
            Some((last, sum)) if *last > i => *sum = sum.saturating_add(amount),
            _ => self.buckets.push_back((i, amount)),
        }
        self.prune(rx);
    }

    /// Whether bucket `i` ended before the window that ends at `now`.
    fn gone(&self, i: u64, now: WallNs) -> bool {
        (i + 1).saturating_mul(self.bucket_ns) <= now.0.saturating_sub(self.window_ns)
    }

    fn prune(&mut self, now: WallNs) {
        while let Some(&(i, _)) = self.buckets.front() {
            if !self.gone(i, now) {
                break;
            }
            self.buckets.pop_front();
        }
    }

    /// The amount over the window ending at `now` (to a bucket).
    pub fn total(&self, now: WallNs) -> u64 {
        self.buckets.iter().filter(|(i, _)| !self.gone(*i, now)).map(|(_, a)| a).sum()
    }

    /// Amount per second over the window ending at `now` (over the time since `since` when that
    /// is shorter, at least 0.1 s, so that a new source does not read low).
    pub fn bytes_per_s(&self, now: WallNs, since: WallNs) -> f64 {
        let span_ns = self.window_ns.min(now.0.saturating_sub(since.0)).max(1_000_000_000 / 10);
        self.total(now) as f64 / (span_ns as f64 * 1e-9)
    }

    /// [`Self::bytes_per_s`] since the first amount (0 before it).
    pub fn per_s(&self, now: WallNs) -> f64 {
        self.first.map_or(0.0, |first| self.bytes_per_s(now, first))
    }

    /// Buckets held (bounded by the window, not by the rate).
    pub fn buckets(&self) -> usize {
        self.buckets.len()
    }
}

/// What is known of one source on one link.
#[derive(Debug, Clone)]
pub struct LinkStats {
    pub first_heard: WallNs,
    pub last_heard: WallNs,
    pub packets: u64,
    pub bytes: u64,
    pub seq: SequenceTracker,
    pub rate: RateWindow,
    /// Last UDP address the source was heard from (cooperative network).
    pub last_addr: Option<SocketAddr>,
    /// Frames per message name.
    pub messages: BTreeMap<&'static str, u64>,
    /// MAV_TYPE of its last HEARTBEAT, if any.
    pub mav_type: Option<String>,
    /// Frames that carried a MAVLink 2 signature, and frames that did not.
    pub signed: u64,
    pub unsigned: u64,
}

impl LinkStats {
    pub fn new(rx: WallNs, window_ns: u64) -> Self {
        LinkStats {
            first_heard: rx,
            last_heard: rx,
            packets: 0,
            bytes: 0,
            seq: SequenceTracker::default(),
            rate: RateWindow::new(window_ns),
            last_addr: None,
            messages: BTreeMap::new(),
            mav_type: None,
            signed: 0,
            unsigned: 0,
        }
    }

    /// One valid frame of `bytes` bytes with sequence number `seq`, signed or not.
    pub fn observe(&mut self, rx: WallNs, seq: u8, bytes: usize, name: &'static str, from: Option<SocketAddr>, signed: bool) {
        self.last_heard = self.last_heard.max(rx);
        if signed {
            self.signed += 1;
        } else {
            self.unsigned += 1;
        }
        self.packets += 1;
        self.bytes += bytes as u64;
        self.seq.observe(seq);
        self.rate.push(rx, bytes as u64);
        if from.is_some() {
            self.last_addr = from;
        }
        *self.messages.entry(name).or_insert(0) += 1;
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn rate_over_the_window() {
        let s = |x: f64| WallNs((x * 1e9) as u64);
        let mut w = RateWindow::new(2_000_000_000);
        for i in 0..50 {
            w.push(s(i as f64 * 0.1), 100); // 1000 B/s for 5 s
        }
        let r = w.bytes_per_s(s(4.9), s(0.0));
        assert!((r - 1000.0).abs() <= 55.0, "{r}");
        // Silent for 10 s: nothing in the window.
        assert_eq!(w.bytes_per_s(s(15.0), s(0.0)), 0.0);
        // A source heard for 0.5 s is rated over 0.5 s, not the whole window.
        let mut w = RateWindow::new(2_000_000_000);
        for i in 0..5 {
            w.push(s(10.0 + i as f64 * 0.1), 100);
        }
        let r = w.bytes_per_s(s(10.5), s(10.0));
        assert!((r - 1000.0).abs() < 1e-6, "{r}");
    }

    #[test]
    fn a_flood_holds_a_bounded_number_of_buckets() {
        let mut w = RateWindow::new(10_000_000_000);
        for i in 0..1_000_000u64 {
            w.push(WallNs(i * 20_000), 1); // 50,000 a second for 20 s
        }
        assert!(w.buckets() <= 41, "{}", w.buckets());
        let r = w.per_s(WallNs(20_000_000_000));
        assert!((r - 50_000.0).abs() < 50_000.0 / 40.0 + 1.0, "{r}");
        assert_eq!(RateWindow::new(1_000).per_s(WallNs(5)), 0.0);
    }
}
