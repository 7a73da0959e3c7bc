//! The node's protocol (paper section 3.3) as a sans-io state machine.
//!
//! Time is the vehicle's: the timestamps of its IMU samples. The core keeps a checkpoint of its
//! filter at the end of every instant (after the IMU sample and any odometer sample of that
//! time) for the last `history_s` seconds, and every input since the oldest checkpoint.
//!
//! A ranging epoch `e` at time `t_e` becomes known to the node from its own vehicle's ranges,
//! from peers' ranges, fragments or announcements. Then:
//!
//! 1. **Broadcast** (Step 3): once the filter has finished instant `t_e`, the node encodes its
//!    checkpoint at `t_e` as a state record, fragments it to its peers, and keeps the *decoded*
//!    record as its own broadcast (quantisation rule). Ranges its own vehicle measured are
//!    forwarded to the peers, as sent.
//! 2. **Joint update** (Steps 4-5): when its filter passes `t_e + epoch_wait`, the node takes the
//!    complete records of that epoch (its own included; platforms whose record is incomplete are
//!    left out and counted) and the ranges among those platforms, sorted by platform id so that
//!    every node builds the same joint problem, and runs the method's update.
//! 3. **Back to the present**: it restores its checkpoint at `t_e`, writes back its own share of
//!    the update, and re-propagates every IMU and odometer input buffered since `t_e`. The result
//!    is exactly what a filter that had the update at `t_e` would hold now.

use std::collections::{BTreeMap, VecDeque};

use crate::estimation::ci::ci_update;
use crate::estimation::ins::{InsConfig, InsFilter, InsInitialSigma, InsState};
use crate::estimation::{
    CoopMeasurement, Correction, CrossCovariances, CrossMode, EstimationError, ImuSample, Method, OdometerSample, PlatformFilter,
    PlatformId, RangeSample, Snapshot, cooperative_update,
};
use crate::protocol::MavMessage;
use crate::protocol::fragment::{Pushed, Reassembler, fragment};
use crate::protocol::record::{self, Encoding};
use crate::protocol::wire;
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
    /// How long after an epoch (vehicle time) the node waits for the broadcasts before running
    /// the joint update with what is complete.
    pub epoch_wait_us: u64,
    /// How much history (checkpoints and inputs) the node keeps, seconds of vehicle time.
    pub history_us: u64,
}

/// Why a node configuration is refused.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum NodeConfigError {
    #[error("method {0} needs a central computer; a node runs dr, naive, dcl or ci")]
    Method(Method),
    #[error("epoch wait ({wait_us} us) must be shorter than the history kept ({history_us} us)")]
    Wait { wait_us: u64, history_us: u64 },
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
    /// A message from the cooperative network.
    Peer(Box<MavMessage>),
}

/// What the node sends out.
#[derive(Debug, Clone, PartialEq)]
pub enum NodeOutput {
    ToPeers(MavMessage),
    ToVehicle(MavMessage),
}

/// Counters of everything the node did and dropped.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct NodeStats {
    pub imu: u64,
    pub odometer: u64,
    pub rejected_inputs: u64,
    pub records_sent: u64,
    pub records_received: u64,
    pub fragments_rejected: u64,
    pub records_incomplete: u64,
    pub records_undecodable: u64,
    pub ranges_rejected: u64,
    pub late_messages: u64,
    pub epochs_applied: u64,
    pub epochs_skipped: u64,
    pub replayed_inputs: u64,
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
    broadcast: bool,
    ranges: BTreeMap<(PlatformId, PlatformId), RangeSample>,
    records: BTreeMap<PlatformId, Snapshot>,
}

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
    reassembler: Reassembler,
    cross: CrossCovariances,
    last_event: Option<(u32, f64, u8, u8)>,
    pub stats: NodeStats,
}

impl NodeCore {
    /// A node whose filter starts at `t0` from `initial`.
    pub fn new(cfg: NodeConfig, t0: TimeUs, initial: InsState) -> Result<Self, NodeConfigError> {
        if !matches!(
            cfg.method,
            Method::DeadReckoning | Method::NoPropagation | Method::Decentralized | Method::CovarianceIntersection
        ) {
            return Err(NodeConfigError::Method(cfg.method));
        }
        if cfg.epoch_wait_us >= cfg.history_us {
            return Err(NodeConfigError::Wait { wait_us: cfg.epoch_wait_us, history_us: cfg.history_us });
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
            reassembler: Reassembler::new(256),
            cross: CrossCovariances::new(),
            last_event: None,
            stats: NodeStats::default(),
        })
    }

    pub fn id(&self) -> PlatformId {
        self.cfg.id
    }

    /// The filter as of the last input.
    pub fn filter(&self) -> &InsFilter {
        &self.filter
    }

    /// Takes one input; returns what to send.
    pub fn handle(&mut self, input: NodeInput) -> Vec<NodeOutput> {
        let mut out = Vec::new();
        match input {
            NodeInput::Imu(s) => {
                if s.t <= self.filter.time() {
                    self.stats.rejected_inputs += 1;
                    return out;
                }
                self.close_instant(&mut out);
                match self.filter.propagate(&s) {
                    Ok(()) => {
                        self.stats.imu += 1;
                        self.inputs.push_back(Stamped::Imu(s));
                        self.open_instant = Some(s.t);
                    }
                    Err(_) => self.stats.rejected_inputs += 1,
                }
            }
            NodeInput::Odometer(s) => {
                // Applied at the filter's current time, which the odometer sample must match.
                if self.open_instant != Some(s.t) {
                    self.stats.rejected_inputs += 1;
                    return out;
                }
                match self.filter.update_odometer(&s) {
                    Ok(_) => {
                        self.stats.odometer += 1;
                        self.inputs.push_back(Stamped::Odometer(s));
                    }
                    Err(_) => self.stats.rejected_inputs += 1,
                }
            }
            NodeInput::OwnRange { epoch, range } => {
                if range.from != self.cfg.id || range.to == self.cfg.id {
                    self.stats.ranges_rejected += 1;
                    return out;
                }
                let sent = wire::range_as_sent(&range);
                out.push(NodeOutput::ToPeers(wire::range_to_message(&sent, epoch)));
                self.add_range(epoch, sent);
                self.broadcast_due(&mut out);
            }
            NodeInput::Peer(msg) => {
                self.peer_message(*msg);
                self.broadcast_due(&mut out);
            }
        }
        out
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

    fn peer_message(&mut self, msg: MavMessage) {
        match msg {
            MavMessage::COOPLOC_STATE_FRAGMENT(m) => {
                let Ok(f) = wire::fragment_from_message(&m) else {
                    self.stats.fragments_rejected += 1;
                    return;
                };
                if f.platform == self.cfg.id {
                    return; // our own broadcast, echoed by multicast
                }
                match self.reassembler.push(&f) {
                    Pushed::Complete(rec) => match record::decode(rec.platform, &rec.bytes) {
                        Ok(snapshot) => {
                            self.stats.records_received += 1;
                            if let Some(e) = self.learn_epoch(rec.epoch, TimeUs(rec.time_usec)) {
                                e.records.insert(rec.platform, snapshot);
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
                Ok((epoch, r)) if r.from != self.cfg.id => self.add_range(epoch, r),
                Ok(_) => {}
                Err(_) => self.stats.ranges_rejected += 1,
            },
            MavMessage::COOPLOC_EPOCH(m) => {
                if let Ok(a) = wire::epoch_from_message(&m) {
                    self.learn_epoch(a.epoch, a.t);
                }
            }
            _ => {}
        }
    }

    fn checkpoint_at(&self, t: TimeUs) -> Option<&InsFilter> {
        self.history.iter().rev().find(|(tc, _)| *tc == t).map(|(_, f)| f)
    }

    /// Broadcasts the record of every known epoch whose instant is checkpointed.
    fn broadcast_due(&mut self, out: &mut Vec<NodeOutput>) {
        let due: Vec<(u32, TimeUs)> =
            self.epochs.iter().filter(|(_, e)| !e.broadcast).filter_map(|(k, e)| e.t.map(|t| (*k, t))).collect();
        for (epoch, t) in due {
            let Some(f) = self.checkpoint_at(t) else { continue };
            let snapshot = f.snapshot(self.cfg.id);
            let sent = record::encode(&snapshot, self.cfg.encoding).ok().and_then(|bytes| {
                let frags = fragment(self.cfg.id, epoch, t.0, &bytes).ok()?;
                Some((record::decode(self.cfg.id, &bytes).ok()?, frags))
            });
            let e = self.epochs.get_mut(&epoch).expect("listed");
            e.broadcast = true;
            if let Some((own, frags)) = sent {
                out.extend(frags.iter().filter_map(|f| wire::fragment_to_message(f).ok()).map(NodeOutput::ToPeers));
                e.records.insert(self.cfg.id, own);
                self.stats.records_sent += 1;
            }
        }
    }

    /// The open instant is complete: checkpoint it, broadcast what is due, run what is ripe.
    fn close_instant(&mut self, out: &mut Vec<NodeOutput>) {
        let Some(t) = self.open_instant.take() else { return };
        self.history.push_back((t, self.filter.clone()));
        self.broadcast_due(out);
        let ripe: Vec<u32> = self
            .epochs
            .iter()
            .filter(|(_, e)| e.t.is_some_and(|te| te.0 + self.cfg.epoch_wait_us <= t.0))
            .map(|(k, _)| *k)
            .collect();
        for epoch in ripe {
            self.run_epoch(epoch, out);
        }
        // Forget what is older than the history window (keeping at least one checkpoint).
        let horizon = t.0.saturating_sub(self.cfg.history_us);
        while self.history.len() > 1 && self.history[0].0.0 < horizon {
            self.history.pop_front();
        }
        let oldest = self.history[0].0;
        while self.inputs.front().is_some_and(|i| i.t() <= oldest) {
            self.inputs.pop_front();
        }
        self.reassembler.expire_before(self.last_applied.map_or(0, |l| l + 1));
    }

    fn run_epoch(&mut self, epoch: u32, out: &mut Vec<NodeOutput>) {
        let Some(e) = self.epochs.remove(&epoch) else { return };
        self.last_applied = Some(epoch);
        let Some(t) = e.t else { return };
        let mut snapshots: Vec<Snapshot> = e.records.into_values().collect(); // sorted by platform id
        let participants: Vec<PlatformId> = snapshots.iter().map(|s| s.id).collect();
        let ranges: Vec<CoopMeasurement> = e
            .ranges
            .values()
            .filter(|r| participants.contains(&r.from) && participants.contains(&r.to))
            .map(|r| CoopMeasurement::Range { from: r.from, to: r.to, range_m: r.range_m, sigma_m: r.sigma_m })
            .collect();
        let own_index = participants.iter().position(|&p| p == self.cfg.id);
        if own_index.is_none() || ranges.is_empty() || self.cfg.method == Method::DeadReckoning {
            self.stats.epochs_skipped += 1;
            return;
        }
        let result: Result<(Vec<Correction>, f64), EstimationError> = match self.cfg.method {
            Method::NoPropagation => cooperative_update(&mut CrossCovariances::new(), &snapshots, &ranges, CrossMode::Ignore)
                .map(|o| (o.corrections, o.diagnostics.nis)),
            Method::Decentralized => cooperative_update(&mut self.cross, &snapshots, &ranges, CrossMode::Propagate)
                .map(|o| (o.corrections, o.diagnostics.nis)),
            Method::CovarianceIntersection => ci_update(&snapshots, &ranges).map(|c| (c, f64::NAN)),
            Method::DeadReckoning | Method::Centralized => unreachable!("refused at construction"),
        };
        let Ok((corrections, nis)) = result else {
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
        self.last_event = Some((epoch, nis, participants.len() as u8, ranges.len() as u8));
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
    /// (deliver the result to the peers before [`NodeCore::run_pending`]).
    pub fn end_of_input(&mut self) -> Vec<NodeOutput> {
        let mut out = Vec::new();
        if let Some(t) = self.open_instant.take() {
            self.history.push_back((t, self.filter.clone()));
        }
        self.broadcast_due(&mut out);
        out
    }

    /// Runs every epoch still waiting, with the records and ranges that have arrived.
    pub fn run_pending(&mut self) -> Vec<NodeOutput> {
        let mut out = Vec::new();
        let pending: Vec<u32> = self.epochs.keys().copied().collect();
        for epoch in pending {
            self.run_epoch(epoch, &mut out);
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
