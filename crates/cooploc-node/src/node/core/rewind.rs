//! The rewind buffer of a node's core: its filter, the filter's checkpoints at recent instants
//! and the vehicle's inputs since the oldest of them. A joint update belongs to an epoch's time,
//! which is already past when the team's records are in; a local measurement (an odometer sample,
//! a GNSS fix) may arrive after the IMU sample that covers it. Both are written into the past here
//! and the inputs since are replayed to the present ([`Rewind::replay_from_checkpoint_at`],
//! [`Rewind::local`]).
//!
//! The instants the filter must stop at (the epochs' times) are *marks*: every IMU interval is cut
//! at them, and the filter is checkpointed there, so that an epoch's joint update finds the filter
//! exactly at its time. Other instants are checkpointed every [`CHECKPOINT_EVERY`]-th (a late
//! input replays from the last checkpoint before it). Checkpoints are boxed filters whose slots
//! are recycled ([`MAX_SPARE_CHECKPOINTS`]): a replay of seconds of 200 Hz samples allocates
//! nothing.
//!
//! Everything here is all or nothing: an IMU sample the filter refuses, or a replay that fails,
//! leaves the filter, its checkpoints and its open instant as they were.

use std::collections::{BTreeSet, VecDeque};

use crate::estimation::PlatformFilter;
use crate::estimation::fix::{FixOutcome, update_position_fix};
use crate::estimation::nav::{Drive, NavFilter};
use crate::estimation::{EstimationError, OdometerSample, PositionFixSample};
use crate::time::TimeUs;

/// How many freed checkpoint slots a node keeps for the next checkpoints (a slot is one
/// filter, under 9 kB for the INS).
pub(super) const MAX_SPARE_CHECKPOINTS: usize = 256;

/// A checkpoint is kept at every mark (epoch time) and at every `CHECKPOINT_EVERY`-th instant in
/// between (every 40 ms of a 200 Hz IMU): copying the filter at every instant cost more than
/// the occasional longer replay from the checkpoint before a late input. A replay from an older
/// checkpoint over the same inputs computes the same values bit for bit.
pub(super) const CHECKPOINT_EVERY: u32 = 8;

/// The filter at the end of an instant.
#[derive(Debug)]
struct Checkpoint {
    t: TimeUs,
    filter: Box<NavFilter>,
}

/// A local measurement of the vehicle's own: applied at its instant, after the drive sample.
#[derive(Debug, Clone, Copy, PartialEq)]
pub(super) enum Local {
    Odometer(OdometerSample),
    Fix(PositionFixSample),
}

impl Local {
    pub(super) fn t(&self) -> TimeUs {
        match self {
            Local::Odometer(s) => s.t,
            Local::Fix(s) => s.t,
        }
    }

    /// Applies it to `filter`: whether it was taken (a fix beyond its gate, or a sample the
    /// filter refuses, changes nothing).
    fn apply(&self, filter: &mut NavFilter) -> bool {
        match self {
            Local::Odometer(s) => filter.update_odometer(s).is_ok(),
            Local::Fix(s) => matches!(update_position_fix(filter, s), Ok(FixOutcome::Applied { .. })),
        }
    }
}

/// Local measurements the filter refused as their IMU sample came, by kind.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub(super) struct Refused {
    pub(super) odometer: u64,
    pub(super) fixes: u64,
}

/// A vehicle input kept for replays. A local measurement carries its [`Judgement`].
#[derive(Debug, Clone)]
enum Stamped {
    Drive(Drive),
    Local(Local, Judgement),
}

/// Whether the filter has judged a kept local measurement yet. A late or waiting one is judged
/// in the integration or replay that first reaches its instant, and counted there once. A GNSS
/// fix refused then stays refused in later replays, as one refused at its own instant is never
/// kept (an odometer sample, which only a value that is no number makes the filter refuse, is
/// offered again: the logs of earlier releases replay so).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Judgement {
    Pending,
    Taken,
    Refused,
}

impl Stamped {
    fn t(&self) -> TimeUs {
        match self {
            Stamped::Drive(s) => s.t(),
            Stamped::Local(s, _) => s.t(),
        }
    }

    /// Order within one instant: the IMU sample, then the local measurements.
    fn key(&self) -> (TimeUs, u8) {
        match self {
            Stamped::Drive(s) => (s.t(), 0),
            Stamped::Local(s, _) => (s.t(), 1),
        }
    }
}

/// What a replay writes into the checkpoint it starts from.
pub(super) enum WriteBack<'a> {
    Nothing,
    /// Our block of a joint update (`Psi` restarts).
    Joint(&'a crate::estimation::Correction),
    /// Noise added to our covariance (`Psi` goes on).
    Noise(&'a nalgebra::DMatrix<f64>),
    /// Our share of a joint update we took no part in but as a bystander (`Psi` goes on).
    Bystander(&'a crate::estimation::BystanderShare),
}

/// What became of a local measurement ([`Rewind::local`]).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(super) enum LocalFate {
    /// Far ahead of the vehicle's IMU, or older than anything kept: dropped.
    Unmatched,
    /// Applied at the open instant, its own.
    Applied,
    /// The filter refused it: dropped.
    Rejected,
    /// Ahead of the filter: kept until the IMU sample that covers it.
    Waits,
    /// Behind the filter: kept, and the filter rebuilt from the checkpoint before it (this many
    /// IMU samples replayed; `refused`: the filter refused it there).
    Late { replayed: u64, refused: bool },
}

/// How a replay went: the IMU samples it went through (those before a failure included) and
/// whether it completed (if not, nothing changed).
#[derive(Debug)]
#[must_use]
pub(super) struct Replay {
    pub(super) samples: u64,
    pub(super) result: Result<(), EstimationError>,
    /// Local measurements judged for the first time on the way, and refused.
    pub(super) refused: Refused,
}

impl Replay {
    fn failed(e: EstimationError) -> Self {
        Replay { samples: 0, result: Err(e), refused: Refused::default() }
    }
}

/// The filter, its checkpoints and the inputs since the oldest (see the module documentation).
#[derive(Debug)]
pub(super) struct Rewind {
    /// The filter now.
    pub(super) filter: NavFilter,
    /// Checkpoints at the end of instants, oldest first; never empty.
    history: VecDeque<Checkpoint>,
    /// Instants closed since the newest checkpoint without one of their own.
    unsaved: u32,
    /// Slots of checkpoints that left the history, written over in place by the next ones.
    spare: Vec<Box<NavFilter>>,
    /// Vehicle inputs after the oldest checkpoint, in time order (odometer samples ahead of the
    /// filter included: they wait for the IMU sample that covers them).
    inputs: VecDeque<Stamped>,
    /// Instants the filter must stop at (epoch times), newer than the oldest checkpoint.
    marks: BTreeSet<TimeUs>,
    /// The instant being filled (IMU sample seen, odometer may follow), not yet checkpointed.
    open_instant: Option<TimeUs>,
    /// The vehicle's stream has ended.
    ended: bool,
}

impl Rewind {
    /// A filter at its start: its one checkpoint.
    pub(super) fn new(filter: NavFilter) -> Self {
        let history = VecDeque::from([Checkpoint { t: filter.time(), filter: Box::new(filter.clone()) }]);
        Self {
            filter,
            history,
            unsaved: 0,
            spare: Vec::new(),
            inputs: VecDeque::new(),
            marks: BTreeSet::new(),
            open_instant: None,
            ended: false,
        }
    }

    /// The filter now becomes the one checkpoint, nothing older kept (a state restored into it).
    pub(super) fn restart_history(&mut self) {
        self.history = VecDeque::from([Checkpoint { t: self.filter.time(), filter: Box::new(self.filter.clone()) }]);
        self.unsaved = 0;
    }

    /// The filter's clock moved to `t` with no input or mark kept from before (a start long
    /// before the vehicle's clock: the initial state is for "now").
    pub(super) fn restart_clock(&mut self, t: TimeUs) {
        self.filter.restart_clock(t);
        self.restart_history();
        self.inputs.clear();
        self.marks.clear();
    }

    /// The oldest instant kept.
    pub(super) fn oldest(&self) -> TimeUs {
        self.history[0].t
    }

    /// Whether the vehicle's stream has ended.
    pub(super) fn ended(&self) -> bool {
        self.ended
    }

    /// The filter at the end of instant `t`, when it was checkpointed.
    pub(super) fn checkpoint_at(&self, t: TimeUs) -> Option<&NavFilter> {
        self.history.iter().rev().find(|c| c.t == t).map(|c| &*c.filter)
    }

    /// `t` becomes a mark (an epoch's time): the filter stops and is checkpointed there. A mark
    /// the filter has already passed without an instant there rebuilds it from the checkpoint
    /// before; returns the IMU samples replayed.
    pub(super) fn mark(&mut self, t: TimeUs) -> u64 {
        if t > self.oldest()
            && self.marks.insert(t)
            && t <= self.filter.time()
            && self.open_instant != Some(t)
            && self.checkpoint_at(t).is_none()
        {
            return self.rebuild_from_before(t).samples;
        }
        0
    }

    /// One IMU sample through the filter, kept for replays; returns the local measurements of
    /// its interval that the filter refused. On error nothing changes.
    pub(super) fn take_imu(&mut self, s: Drive) -> Result<Refused, EstimationError> {
        let refused = self.integrate(&s)?;
        self.insert_input(Stamped::Drive(s));
        Ok(refused)
    }

    /// One local measurement: applied now, kept for the IMU sample that covers it, or written
    /// into the past (see [`LocalFate`]). `max_lead_us`: how far ahead of the filter it may be.
    pub(super) fn local(&mut self, s: Local, max_lead_us: u64) -> LocalFate {
        let now = self.filter.time();
        if s.t().0 > now.0.saturating_add(max_lead_us) || s.t() <= self.oldest() {
            return LocalFate::Unmatched;
        }
        if self.open_instant == Some(s.t()) {
            let fate = if s.apply(&mut self.filter) { LocalFate::Applied } else { LocalFate::Rejected };
            if fate == LocalFate::Applied {
                self.insert_input(Stamped::Local(s, Judgement::Taken));
            }
            return fate;
        }
        self.insert_input(Stamped::Local(s, Judgement::Pending));
        if s.t() > now {
            return LocalFate::Waits;
        }
        // (the replay judges it: the only local measurement not judged behind the filter)
        let replay = self.rebuild_from_before(s.t());
        LocalFate::Late { replayed: replay.samples, refused: replay.refused != Refused::default() }
    }

    fn insert_input(&mut self, item: Stamped) {
        let key = item.key();
        if self.inputs.back().is_none_or(|last| last.key() <= key) {
            self.inputs.push_back(item);
        } else {
            let at = self.inputs.partition_point(|i| i.key() <= key);
            self.inputs.insert(at, item);
        }
    }

    /// One IMU sample through the filter: the interval up to it is cut at every mark, every
    /// local measurement and, for a gap, every step the filter takes; each piece holds the
    /// sample's rates; the local measurements of each instant are applied at its end.
    /// Checkpoints every instant it closes. Returns the local measurements judged here for the
    /// first time that the filter refused ([`Judgement`]). On error the filter, its checkpoints
    /// and its open instant are as they were (the filter is copied only when the interval is
    /// cut: one propagation that fails changes nothing by itself).
    fn integrate(&mut self, s: &Drive) -> Result<Refused, EstimationError> {
        let (history_len, open, unsaved) = (self.history.len(), self.open_instant, self.unsaved);
        self.integrate_pieces(s).map_err(|(e, before)| {
            if let Some(f) = before {
                self.filter = *f;
            }
            self.history.truncate(history_len);
            self.open_instant = open;
            self.unsaved = unsaved;
            e
        })
    }

    /// [`Self::integrate`]'s work; on error, the filter from before the first piece when there
    /// were several.
    fn integrate_pieces(&mut self, s: &Drive) -> Result<Refused, (EstimationError, Option<Box<NavFilter>>)> {
        let t0 = self.filter.time();
        let from = self.inputs.partition_point(|i| i.t() <= t0);
        // the local measurements of the interval: their places in `inputs`, and instants
        let locals: Vec<(usize, TimeUs)> = (from..self.inputs.len())
            .take_while(|&k| self.inputs[k].t() <= s.t())
            .filter(|&k| matches!(self.inputs[k], Stamped::Local(..)))
            .map(|k| (k, self.inputs[k].t()))
            .collect();
        let mut cuts: Vec<TimeUs> = self.marks.range(TimeUs(t0.0 + 1)..s.t()).copied().collect();
        cuts.extend(locals.iter().map(|&(_, t)| t).filter(|t| *t < s.t()));
        let step_us = ((self.filter.max_gap_s() * 1e6) as u64 / 2).max(1);
        if s.t().0 - t0.0 > 2 * step_us {
            let mut t = t0.0 + step_us;
            while t < s.t().0 {
                cuts.push(TimeUs(t));
                t += step_us;
            }
        }
        cuts.sort_unstable();
        cuts.dedup();
        cuts.push(s.t());
        let before = (cuts.len() > 1).then(|| Box::new(self.filter.clone()));
        let mut refused = Refused::default();
        for t in cuts {
            self.checkpoint_open();
            if let Err(e) = self.filter.propagate(&s.at(t)) {
                return Err((e, before));
            }
            self.open_instant = Some(t);
            for &(k, _) in locals.iter().filter(|&&(_, at)| at == t) {
                let Stamped::Local(o, judgement) = &mut self.inputs[k] else { continue };
                if matches!((*o, *judgement), (Local::Fix(_), Judgement::Refused)) {
                    continue;
                }
                let applied = o.apply(&mut self.filter);
                if *judgement == Judgement::Pending {
                    *judgement = if applied { Judgement::Taken } else { Judgement::Refused };
                    match (applied, o) {
                        (true, _) => {}
                        (false, Local::Odometer(_)) => refused.odometer += 1,
                        (false, Local::Fix(_)) => refused.fixes += 1,
                    }
                }
            }
        }
        Ok(refused)
    }

    /// Closes the open instant: its checkpoint when it is a mark, the end of the stream or the
    /// [`CHECKPOINT_EVERY`]-th since the last one.
    fn checkpoint_open(&mut self) {
        if let Some(t) = self.open_instant.take() {
            self.unsaved += 1;
            if self.unsaved < CHECKPOINT_EVERY && !self.ended && !self.marks.contains(&t) {
                return;
            }
            self.unsaved = 0;
            let slot = match self.spare.pop() {
                Some(mut slot) => {
                    (*slot).clone_from(&self.filter);
                    slot
                }
                None => Box::new(self.filter.clone()),
            };
            self.history.push_back(Checkpoint { t, filter: slot });
        }
    }

    /// The vehicle's stream has ended: the open instant is closed and checkpointed.
    pub(super) fn end(&mut self) {
        self.ended = true;
        self.checkpoint_open();
    }

    /// Forgets the checkpoints, inputs and marks older than `keep_from`, keeping the newest
    /// checkpoint at or before it (so that an instant at `keep_from` can still be rebuilt).
    pub(super) fn forget_before(&mut self, keep_from: u64) {
        while self.history.len() > 1 && self.history[0].t.0 < keep_from && self.history[1].t.0 <= keep_from {
            if let Some(old) = self.history.pop_front()
                && self.spare.len() < MAX_SPARE_CHECKPOINTS
            {
                self.spare.push(old.filter);
            }
        }
        let oldest = self.oldest();
        while self.inputs.front().is_some_and(|i| i.t() <= oldest) {
            self.inputs.pop_front();
        }
        while self.marks.first().is_some_and(|m| *m <= oldest) {
            self.marks.pop_first();
        }
    }

    /// Rebuilds the filter from the last checkpoint strictly before `t` (a late input or a new
    /// mark at `t`); returns the IMU samples replayed. Nothing changes when there is none or the
    /// replay fails.
    fn rebuild_from_before(&mut self, t: TimeUs) -> Replay {
        let Some(pos) = self.history.iter().rposition(|c| c.t < t) else {
            return Replay { samples: 0, result: Ok(()), refused: Refused::default() };
        };
        self.replay_from(pos, WriteBack::Nothing)
    }

    /// Restores the checkpoint at `t`, writes back `write_back`, and replays the inputs after
    /// `t`, rebuilding the checkpoints on the way. On error (no checkpoint at `t`, a write-back
    /// or a replay that fails) nothing changes.
    pub(super) fn replay_from_checkpoint_at(&mut self, t: TimeUs, write_back: WriteBack<'_>) -> Replay {
        let Some(pos) = self.history.iter().position(|c| c.t == t) else {
            return Replay::failed(EstimationError::NotApplicable("no checkpoint at the epoch's time"));
        };
        self.replay_from(pos, write_back)
    }

    /// Restores checkpoint `pos`, writes `write_back` into it (a joint update's correction, or
    /// noise), and replays every input after it, rebuilding the checkpoints on the way. On error
    /// nothing changes.
    fn replay_from(&mut self, pos: usize, write_back: WriteBack<'_>) -> Replay {
        let tc = self.history[pos].t;
        let mut f = self.history[pos].filter.clone();
        let written = match write_back {
            WriteBack::Nothing => Ok(()),
            WriteBack::Joint(c) => f.apply_joint(&c.dx, &c.p),
            WriteBack::Noise(q) => f.add_noise(q),
            WriteBack::Bystander(s) => f.apply_bystander(&s.a, &s.b),
        };
        if let Err(e) = written {
            return Replay::failed(e);
        }
        // What a failed replay puts back: the filter, the checkpoints it rebuilds (moved out,
        // not copied: a replay after an epoch rebuilds seconds of 200 Hz checkpoints), the
        // open instant.
        let saved_filter = std::mem::replace(&mut self.filter, (*f).clone());
        let saved_tail = self.history.split_off(pos);
        let (saved_open, saved_unsaved) = (self.open_instant, self.unsaved);
        self.history.push_back(Checkpoint { t: tc, filter: f });
        self.open_instant = None;
        self.unsaved = 0;
        let replay: Vec<Drive> = self
            .inputs
            .iter()
            .filter_map(|i| match i {
                Stamped::Drive(s) if s.t() > tc => Some(*s),
                _ => None,
            })
            .collect();
        let (mut samples, mut refused) = (0, Refused::default());
        for s in &replay {
            match self.integrate(s) {
                Ok(r) => {
                    refused.odometer += r.odometer;
                    refused.fixes += r.fixes;
                }
                Err(e) => {
                    self.filter = saved_filter;
                    self.history.truncate(pos);
                    self.history.extend(saved_tail);
                    self.open_instant = saved_open;
                    self.unsaved = saved_unsaved;
                    return Replay { samples, result: Err(e), refused };
                }
            }
            samples += 1;
        }
        // The checkpoints the replay rebuilt replace the saved ones: their slots are free.
        let room = MAX_SPARE_CHECKPOINTS.saturating_sub(self.spare.len());
        self.spare.extend(saved_tail.into_iter().map(|c| c.filter).take(room));
        if self.ended {
            self.checkpoint_open();
        }
        Replay { samples, result: Ok(()), refused }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::estimation::ImuSample;
    use crate::estimation::PlatformFilter;
    use crate::estimation::ins::{InsConfig, InsInitialSigma, InsState};
    use crate::estimation::nav::{NavModel, NavState};
    use nalgebra::{DMatrix, UnitQuaternion, Vector3};

    const T0: u64 = 1_000_000;

    /// An INS moving north at 5 m/s from t = 1 s.
    fn rewind() -> Rewind {
        let model = NavModel::Ins { config: InsConfig::default(), initial_sigma: InsInitialSigma::for_tests() };
        let state = InsState {
            pos_ned_m: Vector3::new(10.0, -4.0, 0.0),
            vel_ned_m_s: Vector3::new(5.0, 0.0, 0.0),
            att_frd_to_ned: UnitQuaternion::identity(),
            accel_bias_frd_m_s2: Vector3::zeros(),
            gyro_bias_frd_rad_s: Vector3::zeros(),
            odometer_scale_error: 0.0,
        };
        Rewind::new(NavFilter::new(model, TimeUs(T0), NavState::Ins(state)).unwrap())
    }

    fn at(ms: u64) -> TimeUs {
        TimeUs(T0 + ms * 1000)
    }

    /// The IMU sample ending `ms` after the start: a gentle push forward and a slow turn.
    fn imu(ms: u64) -> Drive {
        Drive::Imu(ImuSample {
            t: at(ms),
            specific_force_frd_m_s2: Vector3::new(0.2, 0.0, -9.80665),
            angular_rate_frd_rad_s: Vector3::new(0.0, 0.0, 0.02),
        })
    }

    fn odometer(ms: u64) -> OdometerSample {
        OdometerSample { t: at(ms), speed_m_s: 5.0 + 0.0002 * ms as f64 }
    }

    /// The whole filter, every bit of it (`f64`'s Debug is exact).
    fn bits(f: &NavFilter) -> String {
        format!("{f:?}")
    }

    /// 5 ms IMU samples up to `to_ms`.
    fn drive(r: &mut Rewind, from_ms: u64, to_ms: u64) {
        for ms in (from_ms..=to_ms).step_by(5) {
            r.take_imu(imu(ms)).unwrap();
        }
    }

    #[test]
    fn a_late_odometer_sample_rebuilds_the_filter_it_would_have_had_in_order() {
        let (mut in_order, mut late) = (rewind(), rewind());
        for ms in (5..=300).step_by(5) {
            in_order.take_imu(imu(ms)).unwrap();
            if ms % 20 == 0 {
                assert_eq!(in_order.local(Local::Odometer(odometer(ms)), 1_000_000), LocalFate::Applied, "{ms} ms");
            }
            late.take_imu(imu(ms)).unwrap();
        }
        assert_ne!(bits(&in_order.filter), bits(&late.filter), "the odometer changes the filter");
        for ms in (20..300).step_by(20) {
            let LocalFate::Late { replayed, refused: false } = late.local(Local::Odometer(odometer(ms)), 1_000_000) else {
                panic!("{ms} ms is late, and taken")
            };
            // from the checkpoint before it (every 8th instant) to the present
            assert!((1..=60).contains(&replayed), "{ms} ms: {replayed} samples replayed");
        }
        assert_eq!(late.local(Local::Odometer(odometer(300)), 1_000_000), LocalFate::Applied, "the open instant's own");
        assert_eq!(bits(&in_order.filter), bits(&late.filter));
        // Ahead of the filter: kept for the IMU sample that covers it; far ahead or too old: dropped.
        assert_eq!(late.local(Local::Odometer(odometer(310)), 1_000_000), LocalFate::Waits);
        assert_eq!(late.local(Local::Odometer(odometer(5_000)), 1_000_000), LocalFate::Unmatched);
        assert_eq!(
            late.local(Local::Odometer(OdometerSample { t: TimeUs(T0), speed_m_s: 5.0 }), 1_000_000),
            LocalFate::Unmatched
        );
        in_order.take_imu(imu(305)).unwrap();
        in_order.take_imu(imu(310)).unwrap();
        assert_eq!(in_order.local(Local::Odometer(odometer(310)), 1_000_000), LocalFate::Applied);
        drive(&mut late, 305, 310);
        assert_eq!(bits(&in_order.filter), bits(&late.filter), "the waiting sample is applied at its instant");
    }

    /// A GNSS fix `ms` after the start, where the vehicle was (about), `off_m` north of it.
    fn fix(ms: u64, off_m: f64) -> Local {
        let north = 10.0 + 5.0 * ms as f64 * 1e-3 + off_m;
        Local::Fix(PositionFixSample { t: at(ms), pos_ned_m: Vector3::new(north, -4.3, 0.0), sigma_h_m: 0.3, sigma_v_m: None })
    }

    #[test]
    fn a_late_gnss_fix_rebuilds_the_filter_and_one_beyond_its_gate_changes_nothing() {
        let (mut in_order, mut late) = (rewind(), rewind());
        for ms in (5..=400).step_by(5) {
            in_order.take_imu(imu(ms)).unwrap();
            if ms % 200 == 0 {
                assert_eq!(in_order.local(fix(ms, 0.0), 1_000_000), LocalFate::Applied, "{ms} ms");
            }
            late.take_imu(imu(ms)).unwrap();
        }
        assert_ne!(bits(&in_order.filter), bits(&late.filter), "the fix changes the filter");
        assert!(matches!(late.local(fix(200, 0.0), 1_000_000), LocalFate::Late { refused: false, .. }));
        assert_eq!(late.local(fix(400, 0.0), 1_000_000), LocalFate::Applied);
        assert_eq!(bits(&in_order.filter), bits(&late.filter));
        // 50 m off and late: judged in the replay it starts, refused, and said so (once: the
        // replay of a joint update after it judges it again without counting it)
        assert!(matches!(late.local(fix(300, 50.0), 1_000_000), LocalFate::Late { refused: true, .. }));
        assert_eq!(bits(&in_order.filter), bits(&late.filter), "nothing of it applied");
        let checkpoint = late.history[0].t;
        let again = late.replay_from_checkpoint_at(checkpoint, WriteBack::Nothing);
        assert!(again.result.is_ok() && again.refused == Refused::default());
        assert_eq!(bits(&in_order.filter), bits(&late.filter));
        // and a replay whose filter would now take it (its covariance grown by 10^4 m^2 of noise)
        // still leaves it out, as a fix refused at its own instant is
        let noise = DMatrix::identity(16, 16) * 1e4;
        let (mut with, mut without) = (late, in_order);
        assert!(with.replay_from_checkpoint_at(checkpoint, WriteBack::Noise(&noise)).result.is_ok());
        assert!(without.replay_from_checkpoint_at(checkpoint, WriteBack::Noise(&noise)).result.is_ok());
        assert_eq!(bits(&with.filter), bits(&without.filter), "the refused fix stayed out");
        let (mut late, mut in_order) = (with, without);
        // 50 m off at its instant: refused there
        in_order.take_imu(imu(405)).unwrap();
        late.take_imu(imu(405)).unwrap();
        assert_eq!(late.local(fix(405, 50.0), 1_000_000), LocalFate::Rejected);
        assert_eq!(bits(&in_order.filter), bits(&late.filter), "nothing of it applied");
        assert_eq!(late.local(fix(410, 50.0), 1_000_000), LocalFate::Waits);
        assert_eq!(late.take_imu(imu(410)).unwrap(), Refused { odometer: 0, fixes: 1 });
        assert_eq!(in_order.take_imu(imu(410)).unwrap(), Refused::default());
        assert_eq!(bits(&in_order.filter), bits(&late.filter));
    }

    #[test]
    fn a_mark_stops_the_filter_at_its_instant_even_when_it_comes_late() {
        let (mut early, mut late) = (rewind(), rewind());
        assert_eq!(early.mark(at(33)), 0, "ahead of the filter: nothing to replay");
        drive(&mut early, 5, 100);
        drive(&mut late, 5, 100);
        assert!(early.checkpoint_at(at(33)).is_some(), "the filter stopped at the mark, between two samples");
        assert!(late.checkpoint_at(at(33)).is_none());
        assert_ne!(bits(&early.filter), bits(&late.filter), "a cut interval integrates differently");
        let replayed = late.mark(at(33));
        assert!(replayed > 0 && replayed <= 20, "{replayed}");
        assert_eq!(late.checkpoint_at(at(33)).map(|f| f.time()), Some(at(33)));
        assert_eq!(bits(&early.filter), bits(&late.filter));
        assert_eq!(bits(early.checkpoint_at(at(33)).unwrap()), bits(late.checkpoint_at(at(33)).unwrap()));
        assert_eq!(late.mark(at(33)), 0, "a mark once");
        assert_eq!(late.mark(TimeUs(T0)), 0, "not at or before the oldest checkpoint");
    }

    #[test]
    fn a_write_back_in_the_past_reaches_the_present_and_a_failed_one_changes_nothing() {
        let mut r = rewind();
        let _ = r.mark(at(50));
        drive(&mut r, 5, 200);
        let before = bits(&r.filter);
        let p_before = r.filter.covariance()[(0, 0)];
        let dim = r.filter.dim();

        // No checkpoint at 51 ms; noise of the wrong size; a replay through a sample the filter
        // refuses: each fails, and nothing changed.
        let none = r.replay_from_checkpoint_at(at(51), WriteBack::Noise(&DMatrix::identity(dim, dim)));
        assert!(none.result.is_err() && none.samples == 0);
        let wrong = r.replay_from_checkpoint_at(at(50), WriteBack::Noise(&DMatrix::identity(dim + 1, dim + 1)));
        assert!(wrong.result.is_err() && wrong.samples == 0);
        assert_eq!(bits(&r.filter), before);

        let q = DMatrix::identity(dim, dim) * 4.0;
        let replay = r.replay_from_checkpoint_at(at(50), WriteBack::Noise(&q));
        assert!(replay.result.is_ok());
        assert_eq!(replay.samples, 30, "every sample after 50 ms");
        assert!(r.filter.covariance()[(0, 0)] > p_before + 3.0, "{} against {p_before}", r.filter.covariance()[(0, 0)]);
        assert_eq!(r.filter.time(), at(200));
    }

    #[test]
    fn an_imu_sample_the_filter_refuses_changes_nothing() {
        let mut r = rewind();
        let _ = r.mark(at(12));
        drive(&mut r, 5, 5);
        let (before, history) = (bits(&r.filter), r.history.len());
        let mut bad = imu(20);
        if let Drive::Imu(s) = &mut bad {
            s.specific_force_frd_m_s2.x = f64::NAN;
        }
        assert!(r.take_imu(bad).is_err());
        assert_eq!((bits(&r.filter), r.history.len(), r.open_instant), (before, history, Some(at(5))));
        drive(&mut r, 10, 20);
        assert!(r.checkpoint_at(at(12)).is_some());
    }

    #[test]
    fn forgetting_keeps_the_checkpoint_an_instant_needs_and_recycles_the_slots() {
        let mut r = rewind();
        drive(&mut r, 5, 2_000);
        assert!(r.spare.is_empty());
        let keep_from = at(1_502).0;
        r.forget_before(keep_from);
        assert!(
            r.history[0].t.0 <= keep_from && r.history[1].t.0 > keep_from,
            "{:?}",
            r.history.iter().map(|c| c.t).collect::<Vec<_>>()
        );
        assert!(r.inputs.front().is_some_and(|i| i.t() > r.oldest()));
        let freed = r.spare.len();
        assert!(freed > 0 && freed <= MAX_SPARE_CHECKPOINTS, "{freed}");
        // Every 8th instant checkpointed: the slots come back as the filter goes on.
        drive(&mut r, 2_005, 2_080);
        assert_eq!(r.spare.len(), freed - 2);
        // A replay from the oldest checkpoint still reaches the present.
        let oldest = r.oldest();
        let replay = r.replay_from_checkpoint_at(oldest, WriteBack::Nothing);
        assert!(replay.result.is_ok() && replay.samples > 100, "{:?}", replay.samples);
        r.end();
        assert!(r.ended() && r.checkpoint_at(at(2_080)).is_some(), "the last instant checkpointed at the end");
    }

    #[test]
    fn a_clock_restart_keeps_the_state_and_forgets_the_inputs() {
        let mut r = rewind();
        let _ = r.mark(at(40));
        drive(&mut r, 5, 20);
        let position = r.filter.position_ned_m();
        r.restart_clock(TimeUs(90_000_000));
        assert_eq!(r.filter.time(), TimeUs(90_000_000));
        assert_eq!(r.filter.position_ned_m(), position);
        assert_eq!((r.history.len(), r.inputs.len(), r.marks.len()), (1, 0, 0));
        assert_eq!(r.oldest(), TimeUs(90_000_000));
    }
}
