//! The truth of one simulated vehicle and an estimate's error against it: the rules of the
//! ground station ([`super::state`]) and of the MAVProxy module (`cooploc.TruthTrack`), one code.
//! Pure values, no clock.
//!
//! - SIM_STATE carries no time: a sample waits for the vehicle time of the next timed frame of
//!   its link (HIGHRES_IMU, ODOMETRY; a simulator sends the clock-driven messages due at `t` just
//!   before its samples at `t`). One still waiting when the next SIM_STATE comes is placed at the
//!   last known time, or kept untimed (for a map) when no time is known yet.
//! - Timed samples are kept in time order, the last `history`: a time more than `restart_us`
//!   before the last is a restarted simulator (the track starts over), a smaller step back or an
//!   equal time is stale and dropped.
//! - An estimate's error: the truth interpolated linearly at its time between the bracketing
//!   samples (at most `max_gap_us` apart), the horizontal distance and the 3-D position NEES;
//!   [`ErrorState::Pending`] while the truth does not reach its time yet.

use std::collections::VecDeque;

use nalgebra::{Matrix3, Vector3};

use super::TruthPoint;
use crate::estimation::consistency::position_nees;
use crate::time::TimeUs;

/// An estimate's error against the truth at its time.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct TruthError {
    /// The truth interpolated at the estimate's time, NED.
    pub truth_ned_m: Vector3<f64>,
    /// Horizontal (N, E) distance, m.
    pub horizontal_m: f64,
    /// Position NEES over N, E, D (`None`: covariance not positive definite).
    pub nees: Option<f64>,
}

#[derive(Debug, Clone, Copy, PartialEq)]
pub enum ErrorState {
    /// The truth does not cover the estimate's time yet.
    Pending,
    Known(TruthError),
    /// No truth at that time (before the truth began, or across a gap).
    Unavailable,
}

/// What became of a truth sample.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Placed {
    /// Kept at its time; `restarted`: the track started over with it.
    Timed { point: TruthPoint, restarted: bool },
    /// Kept without a time (no timed frame yet): for a map only.
    Untimed(TruthPoint),
    /// A step back or a repeated time: dropped.
    Stale,
}

/// Counters of a track.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct TruthCounts {
    /// Samples kept, timed or not.
    pub samples: u64,
    pub stale: u64,
    pub restarts: u64,
    pub untimed: u64,
}

/// The truth of one vehicle (see the module documentation).
#[derive(Debug, Clone)]
pub struct TruthTrack {
    history: usize,
    restart_us: u64,
    max_gap_us: u64,
    timed: VecDeque<TruthPoint>,
    untimed: VecDeque<TruthPoint>,
    waiting: Option<TruthPoint>,
    last_time: Option<TimeUs>,
    pub counts: TruthCounts,
}

impl TruthTrack {
    /// At most `history` samples (2 at least), a restart at a step back beyond `restart_us`,
    /// interpolation across gaps of at most `max_gap_us`.
    pub fn new(history: usize, restart_us: u64, max_gap_us: u64) -> Self {
        TruthTrack {
            history: history.max(2),
            restart_us,
            max_gap_us,
            timed: VecDeque::new(),
            untimed: VecDeque::new(),
            waiting: None,
            last_time: None,
            counts: TruthCounts::default(),
        }
    }

    /// A SIM_STATE's sample (its `t` is ignored: it waits for a timed frame); what became of the
    /// one that was waiting, if any.
    pub fn sim_state(&mut self, point: TruthPoint) -> Option<Placed> {
        let placed = self.waiting.take().map(|mut w| {
            w.t = self.last_time;
            self.place(w)
        });
        self.waiting = Some(TruthPoint { t: None, ..point });
        placed
    }

    /// The vehicle time of a timed frame (HIGHRES_IMU, ODOMETRY): stamps the waiting sample.
    pub fn timed(&mut self, t: TimeUs) -> Option<Placed> {
        self.last_time = Some(t);
        let mut w = self.waiting.take()?;
        w.t = Some(t);
        Some(self.place(w))
    }

    fn place(&mut self, point: TruthPoint) -> Placed {
        let Some(t) = point.t else {
            self.counts.samples += 1;
            self.counts.untimed += 1;
            self.untimed.push_back(point);
            while self.untimed.len() > self.history {
                self.untimed.pop_front();
            }
            return Placed::Untimed(point);
        };
        let mut restarted = false;
        if let Some(last) = self.end() {
            if t < last && last.0 - t.0 > self.restart_us {
                self.counts.restarts += 1;
                self.timed.clear();
                restarted = true;
            } else if t <= last {
                self.counts.stale += 1;
                return Placed::Stale;
            }
        }
        self.counts.samples += 1;
        self.timed.push_back(point);
        while self.timed.len() > self.history {
            self.timed.pop_front();
        }
        Placed::Timed { point, restarted }
    }

    /// Forgets every sample (the origin changed).
    pub fn reset(&mut self) {
        self.timed.clear();
        self.untimed.clear();
        self.waiting = None;
    }

    /// The timed samples, in time order.
    pub fn samples(&self) -> &VecDeque<TruthPoint> {
        &self.timed
    }

    /// The samples kept without a time.
    pub fn untimed(&self) -> &VecDeque<TruthPoint> {
        &self.untimed
    }

    pub fn start(&self) -> Option<TimeUs> {
        self.timed.front().and_then(|p| p.t)
    }

    pub fn end(&self) -> Option<TimeUs> {
        self.timed.back().and_then(|p| p.t)
    }

    /// The truth position at `t`, interpolated linearly between the bracketing samples (at most
    /// `max_gap_us` apart); `None` outside the samples' span.
    pub fn truth_at(&self, t: TimeUs) -> Option<Vector3<f64>> {
        let idx = self.timed.partition_point(|p| p.t.is_some_and(|pt| pt < t));
        let after = self.timed.get(idx)?;
        let ta = after.t?;
        if ta == t {
            return Some(after.pos_ned_m);
        }
        let before = self.timed.get(idx.checked_sub(1)?)?;
        let tb = before.t?;
        if ta.0 - tb.0 > self.max_gap_us {
            return None;
        }
        let f = (t.0 - tb.0) as f64 / (ta.0 - tb.0) as f64;
        Some(before.pos_ned_m + (after.pos_ned_m - before.pos_ned_m) * f)
    }

    /// The error of an estimate at `t` (position NED, its 3x3 covariance) against the truth.
    pub fn judge(&self, t: TimeUs, pos_ned_m: &Vector3<f64>, cov: &Matrix3<f64>) -> ErrorState {
        if self.end().is_none_or(|end| t > end) {
            return ErrorState::Pending;
        }
        let Some(truth) = self.truth_at(t) else { return ErrorState::Unavailable };
        let diff = truth - pos_ned_m;
        ErrorState::Known(TruthError {
            truth_ned_m: truth,
            horizontal_m: diff.fixed_rows::<2>(0).norm(),
            nees: position_nees(&diff, cov),
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::gcs::WallNs;

    fn point(n: f64) -> TruthPoint {
        TruthPoint {
            t: None,
            rx: WallNs(0),
            pos_ned_m: Vector3::new(n, 2.0 * n, 0.0),
            vel_ned_m_s: Vector3::zeros(),
            yaw_rad: 0.0,
        }
    }

    #[test]
    fn a_sample_takes_the_next_timed_frames_time_and_interpolates() {
        let mut t = TruthTrack::new(16, 5_000_000, 1_000_000);
        assert_eq!(t.sim_state(point(100.0)), None);
        assert!(t.samples().is_empty(), "no time yet");
        assert!(matches!(t.timed(TimeUs(1_000_000)), Some(Placed::Timed { restarted: false, .. })));
        t.sim_state(point(101.0));
        t.timed(TimeUs(1_100_000));
        let mid = t.truth_at(TimeUs(1_050_000)).unwrap();
        assert!((mid - Vector3::new(100.5, 201.0, 0.0)).norm() < 1e-9);
        assert_eq!(t.truth_at(TimeUs(1_100_000)), Some(Vector3::new(101.0, 202.0, 0.0)));
        assert_eq!(t.truth_at(TimeUs(999_999)), None);
        let cov = Matrix3::identity();
        assert_eq!(t.judge(TimeUs(1_100_001), &Vector3::zeros(), &cov), ErrorState::Pending);
        let ErrorState::Known(e) = t.judge(TimeUs(1_050_000), &Vector3::new(100.5, 205.0, 0.0), &cov) else { panic!() };
        assert!((e.horizontal_m - 4.0).abs() < 1e-9 && (e.nees.unwrap() - 16.0).abs() < 1e-9);
        assert_eq!(t.judge(TimeUs(500_000), &Vector3::zeros(), &cov), ErrorState::Unavailable);
        // across a gap longer than the track's largest: none; an exact sample needs no bracket
        let mut narrow = TruthTrack::new(16, 5_000_000, 50_000);
        for (n, us) in [(1.0, 1_000_000), (2.0, 1_100_000)] {
            narrow.sim_state(point(n));
            narrow.timed(TimeUs(us));
        }
        assert_eq!(narrow.truth_at(TimeUs(1_050_000)), None);
        assert_eq!(narrow.judge(TimeUs(1_050_000), &Vector3::zeros(), &cov), ErrorState::Unavailable);
        assert!(narrow.truth_at(TimeUs(1_100_000)).is_some());
    }

    #[test]
    fn a_waiting_sample_is_placed_at_the_last_time_or_kept_untimed() {
        let mut t = TruthTrack::new(16, 5_000_000, 1_000_000);
        t.sim_state(point(1.0));
        assert!(matches!(t.sim_state(point(2.0)), Some(Placed::Untimed(_))));
        assert_eq!((t.counts.untimed, t.untimed().len()), (1, 1));
        t.timed(TimeUs(3_000_000));
        t.sim_state(point(3.0));
        // the next SIM_STATE before a timed frame: the waiting one at the last time, a repeat
        assert_eq!(t.sim_state(point(4.0)), Some(Placed::Stale));
        assert_eq!(t.counts.stale, 1);
    }

    #[test]
    fn a_step_back_is_stale_and_a_long_one_restarts_the_track() {
        let mut t = TruthTrack::new(3, 5_000_000, 1_000_000);
        for (k, ms) in [10_000u64, 11_000, 12_000, 13_000].iter().enumerate() {
            t.sim_state(point(k as f64));
            t.timed(TimeUs(ms * 1000));
        }
        assert_eq!(t.samples().len(), 3, "bounded");
        t.sim_state(point(9.0));
        assert_eq!(t.timed(TimeUs(12_500_000)), Some(Placed::Stale));
        t.sim_state(point(9.0));
        assert!(matches!(t.timed(TimeUs(1_000_000)), Some(Placed::Timed { restarted: true, .. })));
        assert_eq!((t.samples().len(), t.counts.restarts), (1, 1));
    }
}
