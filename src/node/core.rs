//! The node's protocol (paper section 3.3) as a sans-io state machine.
//!
//! Time is the vehicle's: the timestamps of its IMU samples. The core keeps a checkpoint of its
//! filter at the end of every instant (after the IMU sample and any odometer sample of that
//! time) for the last `history_s` seconds, the checkpoints at the times of the epochs still open,
//! and every input since the oldest checkpoint.
//!
//! A ranging epoch `e` at time `t_e` becomes known to the node from its own vehicle's ranges,
//! from peers' ranges, fragments or epoch messages. Epochs are run strictly in order. Then:
//!
//! 1. **Broadcast** (Step 3): once the filter has finished instant `t_e` and every earlier epoch
//!    is resolved (so the record carries their updates), the node encodes its checkpoint at `t_e`
//!    as a state record, fragments it to its peers, and keeps the *decoded* record as its own
//!    broadcast (quantisation rule). Ranges its own vehicle measured are forwarded, as sent.
//! 2. **Agreement**: the paper's update is exact only if every node runs it on the same records,
//!    so the node waits until it holds the complete record of every expected team member (the
//!    team minus members found absent). While it waits it sends, every `retry` of wall time, a
//!    COOPLOC_EPOCH listing the records it holds; a node that is not listed resends its record
//!    (lost fragments, or a peer that learned its address late). After `epoch_timeout` of wall
//!    time it runs without the missing members, marks them absent until a record of theirs
//!    arrives for an epoch still open, and says so (state PARTIAL, counted): the nodes may then disagree, which they detect
//!    from each other's APPLIED/PARTIAL messages (`epoch_disagreements`).
//! 3. **Joint update** (Steps 4-5): the complete records of the epoch and the ranges among those
//!    platforms, sorted by platform id so that every node builds the same joint problem.
//! 4. **Back to the present**: it restores its checkpoint at `t_e`, writes back its own share of
//!    the update, and re-propagates every IMU and odometer input buffered since `t_e`. The result
//!    is exactly what a filter that had the update at `t_e` would hold now.
//!
//! Wall time enters only through [`NodeCore::poll`] (timeouts and retries); a run whose
//! messages all arrive is therefore deterministic and independent of timing.

use std::collections::{BTreeMap, BTreeSet, VecDeque};

use crate::estimation::ci::ci_update;
use crate::estimation::ins::{InsConfig, InsFilter, InsInitialSigma, InsState};
use crate::estimation::{
    CoopMeasurement, Correction, CrossCovariances, CrossMode, EstimationError, ImuSample, Method, OdometerSample, PlatformFilter,
    PlatformId, RangeSample, Snapshot, cooperative_update,
};
use crate::protocol::MavMessage;
use crate::protocol::fragment::{Pushed, Reassembler, fragment};
use crate::protocol::record::{self, Encoding};
use crate::protocol::wire::{self, EpochState};
use crate::recording::{CoopUpdateRecord, RangeRecord};
use crate::time::TimeUs;

/// How a node runs.
#[derive(Debug, Clone)]
pub struct NodeConfig {
    pub id: PlatformId,
    /// One of dead reckoning, no-propagation, decentralized, covariance intersection (the
    /// centralized EKF needs a centre).
    pub method: Method,
    pub ins: InsConfig,
    pub initial_sigma: InsInitialSigma,
    pub encoding: Encoding,
    /// Every platform of the team, this one included: the records an epoch waits for.
    /// Messages from other platforms are counted and dropped.
    pub team: Vec<PlatformId>,
    /// Wall time a node waits for missing records before it runs an epoch without them, us.
    pub epoch_timeout_us: u64,
    /// Wall time between COOPLOC_EPOCH messages while waiting (retransmission requests), us.
    pub retry_us: u64,
    /// How much history (checkpoints of every instant) the node keeps, vehicle time, us.
    pub history_us: u64,
    /// An epoch still open this long (vehicle time) after its instant is run with what is
    /// there, so that memory stays bounded whatever the network does, us.
    pub max_lag_us: u64,
}

impl NodeConfig {
    /// A configuration with the defaults of `cooploc node`: 2 s timeout, 100 ms retries, 4 s of
    /// history, 120 s of maximum lag.
    pub fn new(
        id: PlatformId,
        method: Method,
        ins: InsConfig,
        initial_sigma: InsInitialSigma,
        encoding: Encoding,
        team: Vec<PlatformId>,
    ) -> Self {
        Self {
            id,
            method,
            ins,
            initial_sigma,
            encoding,
            team,
            epoch_timeout_us: 2_000_000,
            retry_us: 100_000,
            history_us: 4_000_000,
            max_lag_us: 120_000_000,
        }
    }
}

/// Why a node configuration is refused.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum NodeConfigError {
    #[error("method {0} needs a central computer; a node runs dr, naive, dcl or ci")]
    Method(Method),
    #[error("the team {team:?} must list this node's platform {id}, at most {max} platforms, none twice")]
    Team { id: PlatformId, team: Vec<PlatformId>, max: usize },
    #[error("the retry interval ({retry_us} us) must be positive and shorter than the epoch timeout ({timeout_us} us)")]
    Timing { retry_us: u64, timeout_us: u64 },
    #[error(transparent)]
    Filter(#[from] EstimationError),
}

/// What the node feeds in.
#[derive(Debug, Clone, PartialEq)]
pub enum NodeInput {
    Imu(ImuSample),
    Odometer(OdometerSample),
    /// A range the node's own vehicle measured (its radio), with its epoch id.
    OwnRange {
        epoch: u32,
        range: RangeSample,
    },
    /// A message from the cooperative network, with the system id of its sender.
    Peer {
        from: PlatformId,
        msg: Box<MavMessage>,
    },
}

/// What the node sends out.
#[derive(Debug, Clone, PartialEq)]
pub enum NodeOutput {
    ToPeers(MavMessage),
    ToVehicle(MavMessage),
    /// The internals of a joint update just run (for logs).
    Update(Box<CoopUpdateRecord>),
}

/// Counters of everything the node did and dropped.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct NodeStats {
    pub imu: u64,
    pub odometer: u64,
    /// IMU samples not after the filter's time, or refused by the filter.
    pub imu_rejected: u64,
    /// Gaps in the IMU stream longer than the filter takes, bridged by holding the next sample.
    pub imu_gaps_bridged: u64,
    /// Odometer samples without an IMU sample of the same time (lost or reordered input).
    pub odometer_unmatched: u64,
    /// Odometer samples the filter refused (gated or invalid).
    pub odometer_rejected: u64,
    pub records_sent: u64,
    pub records_resent: u64,
    pub records_received: u64,
    pub fragments_rejected: u64,
    pub records_incomplete: u64,
    pub records_undecodable: u64,
    pub ranges_rejected: u64,
    /// Messages from platforms outside the team.
    pub unknown_platforms: u64,
    pub late_messages: u64,
    pub epoch_messages_sent: u64,
    pub epochs_applied: u64,
    /// Epochs run without every expected member (timeout, lag bound or end of input).
    pub epochs_partial: u64,
    pub epochs_skipped: u64,
    /// Epochs a peer ran on another set of records than this node.
    pub epoch_disagreements: u64,
    pub replayed_inputs: u64,
}

impl NodeStats {
    /// Inputs from the vehicle that did not reach the filter.
    pub fn dropped_inputs(&self) -> u64 {
        self.imu_rejected + self.odometer_unmatched + self.odometer_rejected + self.imu_gaps_bridged
    }
}

#[derive(Debug, Clone)]
enum Stamped {
    Imu(ImuSample),
    Odometer(OdometerSample),
}

impl Stamped {
    fn t(&self) -> TimeUs {
        match self {
            Stamped::Imu(s) => s.t,
            Stamped::Odometer(s) => s.t,
        }
    }
}

#[derive(Debug, Default)]
struct Epoch {
    t: Option<TimeUs>,
    /// Wall time of our broadcast, once sent.
    broadcast_at: Option<u64>,
    last_status_at: u64,
    last_resend_at: Option<u64>,
    early_request_sent: bool,
    ranges: BTreeMap<(PlatformId, PlatformId), RangeSample>,
    records: BTreeMap<PlatformId, Snapshot>,
}

/// Longest IMU gap the node bridges (a longer one is refused: the navigation is lost).
const MAX_BRIDGED_GAP_US: u64 = 60_000_000;

/// Epochs remembered after they are run (resends and agreement checks).
const EPOCHS_REMEMBERED: usize = 32;

/// The node's state machine.
#[derive(Debug)]
pub struct NodeCore {
    cfg: NodeConfig,
    filter: InsFilter,
    /// Checkpoints at the end of instants, oldest first.
    history: VecDeque<(TimeUs, InsFilter)>,
    /// Inputs after the oldest checkpoint, in order.
    inputs: VecDeque<Stamped>,
    /// The instant being filled (IMU sample seen, odometer may follow), not yet checkpointed.
    open_instant: Option<TimeUs>,
    epochs: BTreeMap<u32, Epoch>,
    last_applied: Option<u32>,
    /// Our fragments of recent epochs, for resends.
    sent: VecDeque<(u32, Vec<MavMessage>)>,
    /// The record sets recent epochs ran on.
    ran_on: VecDeque<(u32, Vec<PlatformId>)>,
    absent: BTreeSet<PlatformId>,
    /// Wall clock, us, as last given to [`NodeCore::poll`].
    wall_us: u64,
    reassembler: Reassembler,
    cross: CrossCovariances,
    last_event: Option<(u32, f64, u8, u8)>,
    pub stats: NodeStats,
}

impl NodeCore {
    /// A node whose filter starts at `t0` from `initial`.
    pub fn new(mut cfg: NodeConfig, t0: TimeUs, initial: InsState) -> Result<Self, NodeConfigError> {
        if !matches!(
            cfg.method,
            Method::DeadReckoning | Method::NoPropagation | Method::Decentralized | Method::CovarianceIntersection
        ) {
            return Err(NodeConfigError::Method(cfg.method));
        }
        cfg.team.sort_unstable();
        let duplicate = cfg.team.windows(2).any(|w| w[0] == w[1]);
        if !cfg.team.contains(&cfg.id) || duplicate || cfg.team.len() > wire::MAX_PARTICIPANTS {
            return Err(NodeConfigError::Team { id: cfg.id, team: cfg.team, max: wire::MAX_PARTICIPANTS });
        }
        if cfg.retry_us == 0 || cfg.retry_us >= cfg.epoch_timeout_us {
            return Err(NodeConfigError::Timing { retry_us: cfg.retry_us, timeout_us: cfg.epoch_timeout_us });
        }
        let mut filter = InsFilter::new(cfg.ins, t0, initial, cfg.initial_sigma)?;
        filter.set_track_psi(cfg.method.needs_psi());
        let history = VecDeque::from([(t0, filter.clone())]);
        Ok(Self {
            cfg,
            filter,
            history,
            inputs: VecDeque::new(),
            open_instant: None,
            epochs: BTreeMap::new(),
            last_applied: None,
            sent: VecDeque::new(),
            ran_on: VecDeque::new(),
            absent: BTreeSet::new(),
            wall_us: 0,
            reassembler: Reassembler::new(256),
            cross: CrossCovariances::new(),
            last_event: None,
            stats: NodeStats::default(),
        })
    }

    pub fn id(&self) -> PlatformId {
        self.cfg.id
    }

    pub fn config(&self) -> &NodeConfig {
        &self.cfg
    }

    /// The filter as of the last input.
    pub fn filter(&self) -> &InsFilter {
        &self.filter
    }

    /// Team members currently not waited for (they missed an epoch and have not sent a record
    /// since).
    pub fn absent(&self) -> impl Iterator<Item = PlatformId> + '_ {
        self.absent.iter().copied()
    }

    /// Takes one input; returns what to send.
    pub fn handle(&mut self, input: NodeInput) -> Vec<NodeOutput> {
        let mut out = Vec::new();
        match input {
            NodeInput::Imu(s) => {
                if s.t <= self.filter.time() {
                    self.stats.imu_rejected += 1;
                    return out;
                }
                // A gap the filter refuses (lost samples): bridge it holding this sample's
                // measurements, in steps the filter takes, rather than stop navigating.
                let gap_us = s.t.0 - self.filter.time().0;
                let step_us = ((self.cfg.ins.max_imu_gap_s * 1e6) as u64 / 2).max(1);
                if gap_us > 2 * step_us && gap_us <= MAX_BRIDGED_GAP_US {
                    self.stats.imu_gaps_bridged += 1;
                    let mut t = self.filter.time().0 + step_us;
                    while t < s.t.0 {
                        self.imu(ImuSample { t: TimeUs(t), ..s }, &mut out);
                        t += step_us;
                    }
                }
                self.imu(s, &mut out);
            }
            NodeInput::Odometer(s) => {
                // Applied at the filter's current time, which the odometer sample must match.
                if self.open_instant != Some(s.t) {
                    self.stats.odometer_unmatched += 1;
                    return out;
                }
                match self.filter.update_odometer(&s) {
                    Ok(_) => {
                        self.stats.odometer += 1;
                        self.inputs.push_back(Stamped::Odometer(s));
                    }
                    Err(_) => self.stats.odometer_rejected += 1,
                }
            }
            NodeInput::OwnRange { epoch, range } => {
                if range.from != self.cfg.id || range.to == self.cfg.id || !self.in_team(range.to) {
                    self.stats.ranges_rejected += 1;
                    return out;
                }
                let sent = wire::range_as_sent(&range);
                out.push(NodeOutput::ToPeers(wire::range_to_message(&sent, epoch)));
                self.add_range(epoch, sent);
                self.advance(&mut out);
            }
            NodeInput::Peer { from, msg } => {
                self.peer_message(from, *msg, &mut out);
                self.advance(&mut out);
            }
        }
        out
    }

    fn imu(&mut self, s: ImuSample, out: &mut Vec<NodeOutput>) {
        self.close_instant(out);
        match self.filter.propagate(&s) {
            Ok(()) => {
                self.stats.imu += 1;
                self.inputs.push_back(Stamped::Imu(s));
                self.open_instant = Some(s.t);
            }
            Err(_) => self.stats.imu_rejected += 1,
        }
    }

    /// Gives the core the wall clock (us, any monotonic origin): runs the timeouts and sends the
    /// retransmission requests that are due. Call it every few tens of milliseconds.
    pub fn poll(&mut self, wall_us: u64) -> Vec<NodeOutput> {
        self.wall_us = self.wall_us.max(wall_us);
        let mut out = Vec::new();
        self.advance(&mut out);
        out
    }

    fn in_team(&self, p: PlatformId) -> bool {
        self.cfg.team.binary_search(&p).is_ok()
    }

    fn is_open(&self, epoch: u32) -> bool {
        self.last_applied.is_none_or(|last| epoch > last)
    }

    fn learn_epoch(&mut self, epoch: u32, t: TimeUs) -> Option<&mut Epoch> {
        if !self.is_open(epoch) {
            self.stats.late_messages += 1;
            return None;
        }
        let e = self.epochs.entry(epoch).or_default();
        match e.t {
            None => e.t = Some(t),
            Some(known) if known != t => return None,
            Some(_) => {}
        }
        Some(e)
    }

    fn add_range(&mut self, epoch: u32, r: RangeSample) {
        if let Some(e) = self.learn_epoch(epoch, r.t) {
            e.ranges.insert((r.from, r.to), r);
        }
    }

    fn peer_message(&mut self, from: PlatformId, msg: MavMessage, out: &mut Vec<NodeOutput>) {
        let cooploc =
            matches!(msg, MavMessage::COOPLOC_STATE_FRAGMENT(_) | MavMessage::COOPLOC_RANGE(_) | MavMessage::COOPLOC_EPOCH(_));
        if !cooploc || from == self.cfg.id {
            return; // heartbeats, estimates, ground stations; our own traffic looped back
        }
        if !self.in_team(from) {
            self.stats.unknown_platforms += 1;
            return;
        }
        match msg {
            MavMessage::COOPLOC_STATE_FRAGMENT(m) => {
                let Ok(f) = wire::fragment_from_message(&m) else {
                    self.stats.fragments_rejected += 1;
                    return;
                };
                if f.platform != from {
                    self.stats.fragments_rejected += 1;
                    return;
                }
                match self.reassembler.push(&f) {
                    Pushed::Complete(rec) => match record::decode(rec.platform, &rec.bytes) {
                        Ok(snapshot) => {
                            self.stats.records_received += 1;
                            if let Some(e) = self.learn_epoch(rec.epoch, TimeUs(rec.time_usec)) {
                                e.records.insert(rec.platform, snapshot);
                                // Back in step (a record for an epoch still open): waited for again.
                                self.absent.remove(&rec.platform);
                            }
                        }
                        Err(_) => self.stats.records_undecodable += 1,
                    },
                    Pushed::Rejected(_) => self.stats.fragments_rejected += 1,
                    Pushed::Stored | Pushed::Duplicate => {}
                }
                self.stats.records_incomplete += self.reassembler.take_dropped().len() as u64;
            }
            MavMessage::COOPLOC_RANGE(m) => match wire::range_from_message(&m) {
                Ok((epoch, r)) if r.from == from && self.in_team(r.to) => self.add_range(epoch, r),
                Ok(_) | Err(_) => self.stats.ranges_rejected += 1,
            },
            MavMessage::COOPLOC_EPOCH(m) => {
                let Ok(a) = wire::epoch_from_message(&m) else { return };
                if a.announcer != from {
                    return;
                }
                if a.state == EpochState::COOPLOC_EPOCH_STATE_COLLECTING {
                    self.learn_epoch(a.epoch, a.t);
                } else if let Some((_, ours)) = self.ran_on.iter().find(|(e, _)| *e == a.epoch) {
                    if *ours != a.participants {
                        self.stats.epoch_disagreements += 1;
                    }
                } else if let Some(e) = self.epochs.get_mut(&a.epoch)
                    && e.broadcast_at.is_some()
                    && !e.early_request_sent
                    && a.participants.iter().any(|p| !e.records.contains_key(p))
                {
                    // A peer ran the epoch on records we lack: ask for them now rather than
                    // at the next retry.
                    e.early_request_sent = true;
                    e.last_status_at = self.wall_us;
                    let (t, held) = (e.t.unwrap_or(a.t), e.records.keys().copied().collect());
                    self.send_status(a.epoch, t, held, EpochState::COOPLOC_EPOCH_STATE_COLLECTING, out);
                }
                if !a.participants.contains(&self.cfg.id) && a.state == EpochState::COOPLOC_EPOCH_STATE_COLLECTING {
                    self.resend(a.epoch, out);
                }
            }
            _ => {}
        }
    }

    /// Sends our record of `epoch` again (at most once per half retry interval).
    fn resend(&mut self, epoch: u32, out: &mut Vec<NodeOutput>) {
        let Some((_, frags)) = self.sent.iter().find(|(e, _)| *e == epoch) else { return };
        if let Some(e) = self.epochs.get_mut(&epoch) {
            if e.last_resend_at.is_some_and(|at| self.wall_us < at + self.cfg.retry_us / 2) {
                return;
            }
            e.last_resend_at = Some(self.wall_us);
        }
        out.extend(frags.iter().cloned().map(NodeOutput::ToPeers));
        self.stats.records_resent += 1;
    }

    fn checkpoint_at(&self, t: TimeUs) -> Option<&InsFilter> {
        self.history.iter().rev().find(|(tc, _)| *tc == t).map(|(_, f)| f)
    }

    /// Broadcasts, resolves and retries until nothing more can be done now. Epochs go strictly
    /// in order: only the lowest open epoch is broadcast or run.
    fn advance(&mut self, out: &mut Vec<NodeOutput>) {
        while let Some((&epoch, e)) = self.epochs.first_key_value() {
            let Some(t) = e.t else {
                self.epochs.remove(&epoch);
                continue;
            };
            if e.broadcast_at.is_none() {
                if t < self.history[0].0 {
                    // Before our start or beyond our history: we cannot take part.
                    self.stats.epochs_skipped += 1;
                    self.finish_epoch(epoch);
                    continue;
                }
                if self.checkpoint_at(t).is_none() {
                    // Not there yet (wait), or passed without an instant at `t` (a lost IMU
                    // sample): we cannot take part; the peers time out on us.
                    let passed = self.history.back().is_some_and(|(tc, _)| *tc > t);
                    if passed {
                        self.stats.epochs_skipped += 1;
                        self.finish_epoch(epoch);
                        continue;
                    }
                    return;
                }
                self.broadcast(epoch, t, out);
                continue;
            }
            let expected: Vec<PlatformId> = self.cfg.team.iter().copied().filter(|p| !self.absent.contains(p)).collect();
            let complete = expected.iter().all(|p| e.records.contains_key(p));
            let waited = self.wall_us.saturating_sub(e.broadcast_at.unwrap_or(0));
            let lagging = self.filter.time().0.saturating_sub(t.0) >= self.cfg.max_lag_us;
            if complete {
                self.run_epoch(epoch, false, out);
            } else if waited >= self.cfg.epoch_timeout_us || lagging {
                let missing: Vec<PlatformId> = expected.into_iter().filter(|p| !e.records.contains_key(p)).collect();
                self.absent.extend(missing);
                self.run_epoch(epoch, true, out);
            } else {
                if self.wall_us >= e.last_status_at + self.cfg.retry_us {
                    let held: Vec<PlatformId> = e.records.keys().copied().collect();
                    self.epochs.get_mut(&epoch).expect("first").last_status_at = self.wall_us;
                    self.send_status(epoch, t, held, EpochState::COOPLOC_EPOCH_STATE_COLLECTING, out);
                }
                return;
            }
        }
    }

    fn send_status(
        &mut self,
        epoch: u32,
        t: TimeUs,
        participants: Vec<PlatformId>,
        state: EpochState,
        out: &mut Vec<NodeOutput>,
    ) {
        let a = wire::EpochAnnouncement { epoch, t, announcer: self.cfg.id, participants, state };
        if let Ok(m) = wire::epoch_to_message(&a) {
            out.push(NodeOutput::ToPeers(m));
            self.stats.epoch_messages_sent += 1;
        }
    }

    /// Broadcasts our record of `epoch` (our checkpoint at `t`).
    fn broadcast(&mut self, epoch: u32, t: TimeUs, out: &mut Vec<NodeOutput>) {
        let snapshot = self.checkpoint_at(t).expect("checked").snapshot(self.cfg.id);
        let sent = record::encode(&snapshot, self.cfg.encoding).ok().and_then(|bytes| {
            let frags = fragment(self.cfg.id, epoch, t.0, &bytes).ok()?;
            let msgs: Vec<MavMessage> = frags.iter().filter_map(|f| wire::fragment_to_message(f).ok()).collect();
            Some((record::decode(self.cfg.id, &bytes).ok()?, msgs))
        });
        let wall = self.wall_us;
        let e = self.epochs.get_mut(&epoch).expect("open");
        e.broadcast_at = Some(wall);
        e.last_status_at = wall;
        if let Some((own, msgs)) = sent {
            out.extend(msgs.iter().cloned().map(NodeOutput::ToPeers));
            e.records.insert(self.cfg.id, own);
            self.stats.records_sent += 1;
            self.sent.push_back((epoch, msgs));
            if self.sent.len() > EPOCHS_REMEMBERED {
                self.sent.pop_front();
            }
        }
    }

    fn finish_epoch(&mut self, epoch: u32) {
        self.epochs.remove(&epoch);
        self.last_applied = Some(self.last_applied.map_or(epoch, |l| l.max(epoch)));
        self.reassembler.expire_before(epoch + 1);
    }

    /// The open instant is complete: checkpoint it, broadcast and run what is due, forget what
    /// is older than the history (except the checkpoints of open epochs).
    fn close_instant(&mut self, out: &mut Vec<NodeOutput>) {
        let Some(t) = self.open_instant.take() else { return };
        self.history.push_back((t, self.filter.clone()));
        self.advance(out);
        let horizon = t.0.saturating_sub(self.cfg.history_us);
        let keep_from = self.epochs.values().filter_map(|e| e.t).map(|te| te.0).min().unwrap_or(u64::MAX).min(horizon);
        while self.history.len() > 1 && self.history[0].0.0 < keep_from {
            self.history.pop_front();
        }
        let oldest = self.history[0].0;
        while self.inputs.front().is_some_and(|i| i.t() <= oldest) {
            self.inputs.pop_front();
        }
    }

    fn run_epoch(&mut self, epoch: u32, partial: bool, out: &mut Vec<NodeOutput>) {
        let Some(e) = self.epochs.get(&epoch) else { return };
        let Some(t) = e.t else { return };
        let mut snapshots: Vec<Snapshot> = e.records.values().cloned().collect(); // sorted by platform id
        let participants: Vec<PlatformId> = snapshots.iter().map(|s| s.id).collect();
        let ranges: Vec<CoopMeasurement> = e
            .ranges
            .values()
            .filter(|r| participants.contains(&r.from) && participants.contains(&r.to))
            .map(|r| CoopMeasurement::Range { from: r.from, to: r.to, range_m: r.range_m, sigma_m: r.sigma_m })
            .collect();
        self.finish_epoch(epoch);
        if partial {
            self.stats.epochs_partial += 1;
        }
        let state = if partial { EpochState::COOPLOC_EPOCH_STATE_PARTIAL } else { EpochState::COOPLOC_EPOCH_STATE_APPLIED };
        self.ran_on.push_back((epoch, participants.clone()));
        if self.ran_on.len() > EPOCHS_REMEMBERED {
            self.ran_on.pop_front();
        }
        if participants.contains(&self.cfg.id) {
            self.send_status(epoch, t, participants.clone(), state, out);
        }
        let own_index = participants.iter().position(|&p| p == self.cfg.id);
        if own_index.is_none() || ranges.is_empty() || self.cfg.method == Method::DeadReckoning {
            self.stats.epochs_skipped += 1;
            return;
        }
        type Diag = Option<crate::estimation::kalman::UpdateDiagnostics>;
        let result: Result<(Vec<Correction>, Diag), EstimationError> = match self.cfg.method {
            Method::NoPropagation => cooperative_update(&mut CrossCovariances::new(), &snapshots, &ranges, CrossMode::Ignore)
                .map(|o| (o.corrections, Some(o.diagnostics))),
            Method::Decentralized => cooperative_update(&mut self.cross, &snapshots, &ranges, CrossMode::Propagate)
                .map(|o| (o.corrections, Some(o.diagnostics))),
            Method::CovarianceIntersection => ci_update(&snapshots, &ranges).map(|c| (c, None)),
            Method::DeadReckoning | Method::Centralized => unreachable!("refused at construction"),
        };
        let Ok((corrections, diag)) = result else {
            self.stats.epochs_skipped += 1;
            return;
        };
        snapshots.clear();
        let own = corrections.into_iter().find(|c| c.id == self.cfg.id).expect("own record took part");
        if self.rewind_and_replay(t, &own).is_err() {
            self.stats.epochs_skipped += 1;
            return;
        }
        self.stats.epochs_applied += 1;
        let nis = diag.as_ref().map_or(f64::NAN, |d| d.nis);
        self.last_event = Some((epoch, nis, participants.len() as u8, ranges.len() as u8));
        out.push(NodeOutput::Update(Box::new(CoopUpdateRecord {
            vehicle: self.cfg.id,
            epoch,
            t_us: t.0,
            participants: participants.clone(),
            ranges: ranges
                .iter()
                .filter_map(|r| match r {
                    CoopMeasurement::Range { from, to, range_m, sigma_m } => {
                        Some(RangeRecord { from: *from, to: *to, range_m: *range_m, sigma_m: *sigma_m })
                    }
                    _ => None,
                })
                .collect(),
            innovation: diag.as_ref().map(|d| d.innovation.iter().copied().collect()).unwrap_or_default(),
            innovation_sigma: diag
                .as_ref()
                .map(|d| d.innovation_cov.diagonal().iter().map(|v| v.sqrt()).collect())
                .unwrap_or_default(),
            nis,
            nis_dof: ranges.len() as u32,
            nees: None,
            nees_dof: None,
        })));
        let report = self.estimate();
        out.push(NodeOutput::ToPeers(wire::estimate_to_message(&report)));
        out.push(NodeOutput::ToVehicle(wire::estimate_to_local_position(&report)));
    }

    /// Restores the checkpoint at `t`, writes back the correction, and replays the inputs after
    /// `t`, rebuilding the checkpoints on the way.
    fn rewind_and_replay(&mut self, t: TimeUs, own: &Correction) -> Result<(), EstimationError> {
        let Some(pos) = self.history.iter().position(|(tc, _)| *tc == t) else {
            return Err(EstimationError::NotApplicable("no checkpoint at the epoch's time"));
        };
        let mut f = self.history[pos].1.clone();
        f.apply_joint(&own.dx, &own.p)?;
        let mut history: VecDeque<(TimeUs, InsFilter)> = self.history.drain(..pos).collect();
        history.push_back((t, f.clone()));
        let mut open: Option<TimeUs> = None;
        let replay: Vec<Stamped> = self.inputs.iter().filter(|i| i.t() > t).cloned().collect();
        for input in &replay {
            match input {
                Stamped::Imu(s) => {
                    if let Some(tc) = open.take() {
                        history.push_back((tc, f.clone()));
                    }
                    f.propagate(s)?;
                    open = Some(s.t);
                }
                Stamped::Odometer(s) => {
                    f.update_odometer(s)?;
                }
            }
            self.stats.replayed_inputs += 1;
        }
        // The instant still open stays open (it is checkpointed when it closes).
        if let (Some(tc), Some(now)) = (open, self.open_instant) {
            debug_assert_eq!(tc, now);
        } else if let Some(tc) = open {
            history.push_back((tc, f.clone()));
        }
        self.history = history;
        self.filter = f;
        Ok(())
    }

    /// The vehicle's stream has ended: closes the open instant and broadcasts what is due
    /// (deliver the result to the peers; epochs then run as their records arrive, or at
    /// [`NodeCore::run_pending`]).
    pub fn end_of_input(&mut self) -> Vec<NodeOutput> {
        let mut out = Vec::new();
        if let Some(t) = self.open_instant.take() {
            self.history.push_back((t, self.filter.clone()));
        }
        self.advance(&mut out);
        out
    }

    /// Runs every epoch still open, in order, with the records that have arrived (the end of a
    /// run: nothing more will come).
    pub fn run_pending(&mut self) -> Vec<NodeOutput> {
        let mut out = Vec::new();
        while let Some((&epoch, e)) = self.epochs.first_key_value() {
            match e.t {
                Some(t) if e.broadcast_at.is_none() && self.checkpoint_at(t).is_some() => self.broadcast(epoch, t, &mut out),
                Some(_) if e.broadcast_at.is_some() => {
                    let complete = self.cfg.team.iter().all(|p| self.absent.contains(p) || e.records.contains_key(p));
                    self.run_epoch(epoch, !complete, &mut out);
                }
                _ => {
                    self.stats.epochs_skipped += 1;
                    self.finish_epoch(epoch);
                }
            }
        }
        out
    }

    /// The estimate report of the node's current state.
    pub fn estimate(&self) -> wire::EstimateReport {
        let f = &self.filter;
        let p = f.covariance16();
        let (epoch, nis, participants, ranges) = self.last_event.unwrap_or((0, f64::NAN, 0, 0));
        wire::EstimateReport {
            platform: self.cfg.id,
            t: f.time(),
            epoch,
            method: self.cfg.method,
            position_ned_m: f.position_ned_m(),
            velocity_ned_m_s: f.velocity_ned_m_s(),
            yaw_rad: f.yaw_rad(),
            position_covariance_m2: p.fixed_view::<3, 3>(0, 0).into_owned(),
            yaw_variance_rad2: p[(8, 8)],
            nis,
            participants,
            ranges,
        }
    }
}
