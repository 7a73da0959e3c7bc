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

/// Bytes received over the last `window_ns`.
#[derive(Debug, Clone)]
pub struct RateWindow {
    window_ns: u64,
    samples: VecDeque<(WallNs, u64)>,
    sum: u64,
}

impl RateWindow {
    pub fn new(window_ns: u64) -> Self {
        RateWindow { window_ns: window_ns.max(1), samples: VecDeque::new(), sum: 0 }
    }

    pub fn push(&mut self, rx: WallNs, bytes: u64) {
        self.samples.push_back((rx, bytes));
        self.sum += bytes;
        self.prune(rx);
    }

    fn prune(&mut self, now: WallNs) {
        while let Some(&(t, b)) = self.samples.front() {
            if now.0.saturating_sub(t.0) <= self.window_ns {
                break;
            }
            self.samples.pop_front();
            self.sum -= b;
        }
    }

    /// Bytes per second over the window ending at `now` (over the time since `since` when that is
    /// shorter, so that a new source does not read low).
    pub fn bytes_per_s(&self, now: WallNs, since: WallNs) -> f64 {
        let sum: u64 = self.samples.iter().filter(|(t, _)| now.0.saturating_sub(t.0) <= self.window_ns).map(|(_, b)| b).sum();
        let span_ns = self.window_ns.min(now.0.saturating_sub(since.0)).max(1_000_000_000 / 10);
        sum as f64 / (span_ns as f64 * 1e-9)
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
}
