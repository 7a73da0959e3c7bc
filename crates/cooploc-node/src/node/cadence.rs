//! How often a waiting node asks again: its retry interval, in wall time, follows the team's
//! epoch cadence.
//!
//! A node waits for its teammates' records of an epoch, asking again (COOPLOC_EPOCH
//! COLLECTING, record resends) every retry interval; epochs run strictly in order, so an epoch
//! that takes longer than the time between two epochs to resolve holds up every later one, and
//! once the backlog reaches the epoch timeout the team runs epochs partial and heals them with
//! the covariance-intersection bound, each heal inflating every covariance. How many times a
//! node can ask within one epoch is what decides whether loss costs information.
//!
//! A fixed interval in wall time gives the paper's team (1 Hz ranging at real time) ten tries per
//! epoch with the default 100 ms, but a simulation at 5x real time (or a team ranging at 5 Hz)
//! two: measured with `cooploc faults --speed 5` (the paper scenario, 30% datagram loss, packed
//! datagrams), 30 m final error against the 2.5 m of the same case at real time, and as bad with
//! three `cooploc node` processes behind a lossy relay. So the interval is the configured one at
//! most, and at most a [`RETRIES_PER_EPOCH`]th of the epoch period in wall time: the period the
//! last resolved epochs had in vehicle time, divided by how fast vehicle time runs against the
//! wall clock (measured over windows of at least [`RATE_WINDOW_US`] of wall time), never below
//! [`MIN_RETRY_US`] (the resends must not storm). The default (100 ms) is exactly a tenth of the
//! paper's 1 s period at real time: there nothing changes. An interval an operator set
//! (`cooploc node --retry-ms`, `NodeConfig::retry_follows_cadence` false) is taken as given.
//!
//! The same holds for the history of checkpoints an epoch needs (`NodeConfig::history_us`,
//! 4 s of vehicle time): a node learns of an epoch from its teammates' messages (a node without
//! a ranging device only so), which under loss takes up to an epoch timeout of *wall* time; at
//! 5x real time 4 s of vehicle time are 0.8 s of wall time, and a node that heard of an epoch
//! later than that could not take part (measured: node 3 of the paper team, which has no
//! radio of its own, sent 348 of 380 records at 50% loss). So the history kept is the
//! configured one times the clock rate, up to [`MAX_HISTORY_SCALE`] times.
//!
//! Pure: the node core feeds it its wall clock, its filter's (vehicle) time and the epochs it
//! resolves.

use crate::time::TimeUs;

/// Tries per epoch period the interval allows at least (the default 100 ms is a tenth of the
/// paper's 1 s period).
pub const RETRIES_PER_EPOCH: u64 = 10;
/// The shortest retry interval, us: a few datagram round trips on a LAN.
pub const MIN_RETRY_US: u64 = 5_000;
/// The shortest wall time over which the vehicle clock's rate is measured, us.
pub const RATE_WINDOW_US: u64 = 1_000_000;
/// Rates above this (vehicle time against wall time) are taken as this: a node catching up on a
/// backlog runs through vehicle time much faster than any simulation does.
pub const MAX_RATE: f64 = 100.0;

/// The most the history kept is lengthened by a fast vehicle clock (memory: at 200 Hz, 40 s of
/// inputs and checkpoints with the default 4 s).
pub const MAX_HISTORY_SCALE: f64 = 10.0;

/// The epoch cadence as this node sees it.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Cadence {
    /// (wall, vehicle) at the start of the current measuring window, us.
    window: Option<(u64, u64)>,
    /// Vehicle time per wall time over the last complete window (None: not measured yet).
    rate: Option<f64>,
    /// The last epoch resolved and its time.
    last_epoch: Option<(u32, TimeUs)>,
    /// Vehicle time between the last two resolved epochs, per epoch, us.
    period_us: Option<u64>,
}

impl Cadence {
    pub fn new() -> Self {
        Self::default()
    }

    /// The wall clock and the vehicle's time (the filter's), both us, as the node sees them now.
    /// Either going backwards starts a new window (a restarted vehicle clock).
    pub fn observe_clock(&mut self, wall_us: u64, vehicle_us: u64) {
        match self.window {
            Some((w0, v0)) if wall_us >= w0 && vehicle_us >= v0 => {
                if wall_us - w0 >= RATE_WINDOW_US {
                    self.rate = Some((vehicle_us - v0) as f64 / (wall_us - w0) as f64);
                    self.window = Some((wall_us, vehicle_us));
                }
            }
            _ => self.window = Some((wall_us, vehicle_us)),
        }
    }

    /// An epoch was resolved (run, skipped or left out of). Consecutive resolved epochs give
    /// the period; epochs out of order are ignored.
    pub fn observe_epoch(&mut self, epoch: u32, t: TimeUs) {
        if let Some((e0, t0)) = self.last_epoch {
            if epoch <= e0 || t <= t0 {
                return;
            }
            self.period_us = Some((t.0 - t0.0) / u64::from(epoch - e0));
        }
        self.last_epoch = Some((epoch, t));
    }

    /// Vehicle time per wall time, as last measured (None before a whole window).
    pub fn rate(&self) -> Option<f64> {
        self.rate
    }

    /// The epoch period in vehicle time, us (None before two epochs were resolved).
    pub fn period_us(&self) -> Option<u64> {
        self.period_us
    }

    /// The retry interval now, us: `configured` at most, a [`RETRIES_PER_EPOCH`]th of the epoch
    /// period in wall time at most, [`MIN_RETRY_US`] at least (or `configured`, if that is less).
    /// A vehicle clock slower than the wall clock does not lengthen it.
    pub fn retry_us(&self, configured: u64) -> u64 {
        let (Some(period), Some(rate)) = (self.period_us, self.rate) else { return configured };
        let wall_period = period as f64 / rate.clamp(1.0, MAX_RATE);
        let per_try = (wall_period / RETRIES_PER_EPOCH as f64) as u64;
        per_try.clamp(MIN_RETRY_US.min(configured), configured)
    }

    /// The history to keep now, us of vehicle time: `configured` (meant as wall time) times the
    /// vehicle clock's rate, the rate taken between 1 and [`MAX_HISTORY_SCALE`].
    pub fn history_us(&self, configured: u64) -> u64 {
        let scale = self.rate.unwrap_or(1.0).clamp(1.0, MAX_HISTORY_SCALE);
        (configured as f64 * scale) as u64
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Feeds `secs` of wall time in 10 ms polls, vehicle time running `rate` times faster,
    /// resolving an epoch every `period_s` of vehicle time.
    fn run(c: &mut Cadence, rate: f64, period_s: f64, secs: f64) {
        let mut next_epoch = 1u32;
        for k in 0..=(secs * 100.0) as u64 {
            let wall = k * 10_000;
            let vehicle = (wall as f64 * rate) as u64;
            c.observe_clock(wall, vehicle);
            while (f64::from(next_epoch) * period_s * 1e6) as u64 <= vehicle {
                c.observe_epoch(next_epoch, TimeUs((f64::from(next_epoch) * period_s * 1e6) as u64));
                next_epoch += 1;
            }
        }
    }

    #[test]
    fn the_paper_cadence_at_real_time_keeps_the_default() {
        let mut c = Cadence::new();
        run(&mut c, 1.0, 1.0, 5.0);
        assert_eq!(c.period_us(), Some(1_000_000));
        assert!((c.rate().unwrap() - 1.0).abs() < 1e-9);
        assert_eq!(c.retry_us(100_000), 100_000);
        assert_eq!(c.history_us(4_000_000), 4_000_000);
    }

    #[test]
    fn a_faster_clock_keeps_a_longer_history_up_to_the_bound() {
        let mut c = Cadence::new();
        assert_eq!(c.history_us(4_000_000), 4_000_000, "not measured yet");
        run(&mut c, 5.0, 1.0, 2.0);
        assert_eq!(c.history_us(4_000_000), 20_000_000);
        let mut fast = Cadence::new();
        run(&mut fast, 50.0, 1.0, 2.0);
        assert_eq!(fast.history_us(4_000_000), 40_000_000);
        let mut slow = Cadence::new();
        run(&mut slow, 0.5, 1.0, 2.0);
        assert_eq!(slow.history_us(4_000_000), 4_000_000);
    }

    #[test]
    fn a_faster_clock_or_a_faster_schedule_shortens_it_to_ten_tries_an_epoch() {
        let mut sim = Cadence::new();
        run(&mut sim, 5.0, 1.0, 5.0);
        assert_eq!(sim.retry_us(100_000), 20_000, "5x real time, 1 Hz");
        let mut fast = Cadence::new();
        run(&mut fast, 1.0, 0.2, 5.0);
        assert_eq!(fast.retry_us(100_000), 20_000, "real time, 5 Hz");
        let mut slow = Cadence::new();
        run(&mut slow, 0.5, 1.0, 5.0);
        assert_eq!(slow.retry_us(100_000), 100_000, "half real time: never longer than configured");
    }

    #[test]
    fn it_never_goes_below_the_floor_or_above_the_configured_interval() {
        let mut c = Cadence::new();
        run(&mut c, 1000.0, 10.0, 3.0);
        assert_eq!(c.retry_us(100_000), 10_000, "rates above MAX_RATE count as MAX_RATE: 10 s / 100 / 10");
        let mut c = Cadence::new();
        run(&mut c, 1.0, 0.01, 3.0);
        assert_eq!(c.retry_us(100_000), MIN_RETRY_US, "100 Hz at real time: 1 ms, floored");
        assert_eq!(c.retry_us(2_000), 2_000, "a configured interval below the floor stays");
        assert_eq!(c.retry_us(1), 1);
    }

    #[test]
    fn nothing_changes_before_it_has_measured_and_odd_input_is_ignored() {
        let mut c = Cadence::new();
        assert_eq!(c.retry_us(100_000), 100_000);
        c.observe_epoch(5, TimeUs(5_000_000));
        c.observe_epoch(4, TimeUs(4_000_000));
        c.observe_epoch(6, TimeUs(5_000_000));
        assert_eq!(c.period_us(), None, "older epochs and epochs at the same time give no period");
        c.observe_epoch(8, TimeUs(5_600_000));
        assert_eq!(c.period_us(), Some(200_000), "a gap of ids: the period per epoch");
        assert_eq!(c.retry_us(100_000), 100_000, "no rate measured yet");
        c.observe_clock(10_000_000, 50_000_000);
        c.observe_clock(10_500_000, 60_000_000);
        assert_eq!(c.rate(), None, "half a window");
        c.observe_clock(9_000_000, 70_000_000);
        c.observe_clock(9_999_999, 71_000_000);
        assert_eq!(c.rate(), None, "the wall clock went back: a new window");
        c.observe_clock(10_000_000, 71_000_001);
        assert!((c.rate().unwrap() - 1.0).abs() < 1e-5);
    }
}
