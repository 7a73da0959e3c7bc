//! The node's protocol (paper section 3.3) as a sans-io state machine, made to survive the real
//! world: lost and late frames, sensors that are not synchronised with the IMU, stalls,
//! restarts, late joiners and hostile input.
//!
//! # Time
//!
//! Time is the vehicle's: the timestamps of its samples. The core keeps every vehicle input
//! (IMU and odometer samples, in time order) since its oldest checkpoint, and checkpoints of its
//! filter at the ends of *instants* for the last `history_us` (every epoch's instant and every
//! few in between; an instant between checkpoints is rebuilt by replaying from the one before
//! it, to the same bits). An instant ends at an IMU
//! sample's time, at an odometer sample's time and at every ranging epoch's time: an IMU
//! interval `(t_prev, t]` that contains such a time is split there (its rates held over both
//! pieces), so measurements are applied at their own instants whatever the IMU rate. A sample
//! that arrives late (an odometer sample older than the filter, an epoch learned after the
//! vehicle passed its time) is inserted and the filter rebuilt from the checkpoint before it: the
//! result is the same as if it had come in order. Gaps in the IMU stream (lost frames) are
//! bridged by propagating in steps the filter takes, holding the next sample; a node therefore
//! never misses an epoch because of its own vehicle link.
//!
//! # An epoch
//!
//! A ranging epoch `e` at time `t_e` becomes known from the node's own ranges or from peers, or,
//! with a periodic schedule ([`NodeConfig::epoch_period_us`]), from the epoch before it as the
//! filter passes that one. Epochs run strictly in order. Then:
//!
//! 1. **Broadcast** (Step 3): once the filter has passed `t_e` by `range_grace_us` (so that the
//!    vehicle's ranges of the epoch are in) and every earlier epoch is resolved, the node sends
//!    its *record*: its checkpoint at `t_e`, the digest of its cross-covariance store, whether it
//!    is fresh (independent of every teammate), and the ranges its radio measured. It keeps the
//!    decoded record as its own (quantisation rule). A record is the sender's whole share of the
//!    joint problem: nodes that hold the same records solve the same problem. With airtime
//!    slots ([`NodeConfig::slot_us`]) the node broadcasts its slot later (its place in the
//!    sorted team times the slot), and the wait below starts only when every slot is over.
//!    On a signed team, a node that measured no range at the epoch, that no record ranged at
//!    the epoch before and that asks for nothing to be passed over says "no range"
//!    (COOPLOC_EPOCH_STATE_NO_RANGE, with its store digest) in place of its record: one small
//!    message for the record's fragments. It keeps the record, and sends it once a teammate's
//!    record of the epoch ranges it (its state is then in the joint problem); a teammate that
//!    asks while it lacks the word is sent the word again. (Believed from signed peers only, as
//!    NO_RECORD: a forger's word for a genuine member would have the team run without it.)
//!    A node whose filter is an epoch timeout of wall time or more behind `t_e` (its range
//!    grace aside), and further behind than at its last broadcast, asks the team in its
//!    record's flags to pass over the next epochs (one, and one more for every further half
//!    timeout, three at most: [`record::skip_of`]); every node that runs the epoch on the same
//!    records (two at least; a left-out member's record does not count, since some nodes hold
//!    it and others not) passes over the most any of them asks: nothing sent, nothing
//!    applied, so the stores stay exact. A team whose epochs take longer to resolve than they
//!    come thus runs fewer of them instead of falling behind until every epoch times out and
//!    is healed with the bound (50% datagram loss with 0-1 s of latency at 1 Hz: 303.80 m final
//!    RMS before, 6.11 m after, `cooploc faults --only "coop loss 50%, packed datagrams"
//!    --delay-ms 0-1000`).
//! 2. **Agreement**: the node waits for the record of every expected team member (or its word,
//!    unless a record ranges it), sending a
//!    COOPLOC_EPOCH (COLLECTING, the records it holds) every `retry_us` of wall time; a member
//!    not listed resends its record, or, when it resolved the epoch without one (passed it over,
//!    was away), answers NO_RECORD, and a signed team stops waiting for it. The retry interval
//!    follows the team's epoch cadence (at most `retry_us`, at most a tenth of the epoch period
//!    in wall time: [`super::cadence`]), unless configured not to.
//!    After `epoch_timeout_us` it runs without the missing members, marks them absent until
//!    they speak again (a record or a fragment of one for an epoch still open, a COOPLOC_EPOCH
//!    of a recent epoch), and says so (PARTIAL). Unless a peer already reported it ran the
//!    epoch (APPLIED or PARTIAL, with another member at least): then the node runs it on the
//!    records of the largest set so reported, not on its own, waiting one more timeout for
//!    those it lacks (asked for meanwhile), and as a bystander if that set leaves it out. A
//!    node that times out is late; the peers that held every record ran on all of them without
//!    waiting, and the late node follows them instead of splitting the team's stores (in
//!    16-member teams with 10% loss and four members leaving and coming back, following and
//!    waiting again for a member that speaks turned 322 heals in five runs into none). A
//!    missing member heard collecting an earlier epoch since our broadcast is behind, not gone
//!    (it waits for a member we found absent; its record of this epoch comes once it has run
//!    that one): it too is waited for one timeout more, so that the two do not run the epoch on
//!    different sets (of 200 runs of the paper team with 10% loss, 0-300 ms of delay and node
//!    3 leaving, 7 healed without this, 3 before resends were limited by what they carry, none
//!    with it).
//! 3. **Joint update** (Steps 4-5), on the records sorted by platform id. If every record carries
//!    the same store digest, the exact method runs (the store and the Psi of each record),
//!    among the members the epoch's ranges involve: a member no range involves is a
//!    *bystander*, its state out of the joint problem; it takes its share of the update
//!    ([`crate::estimation::BystanderShare`], through its own Psi, which goes on) and every
//!    node updates the store's blocks between the bystanders, so that the team ends where the
//!    update on every record would (`tests/equivalence.rs`, to 1e-9; the paper's team with
//!    radios that reach 400 m, 90 bystander epochs of 380, gives the same final errors to the
//!    6 digits of the experiment's output). A member whose word stands is a bystander too when
//!    its word carries the store the epoch runs on, and left out (it takes that store
//!    afterwards) when not. If the records' digests differ, the stores have diverged (a node
//!    missed an epoch, ran it on other records, restarted).
//!    Every node sees the same records, so every node makes the same choice:
//!    - if a store held by two records or more is *valid for every participant* (the store's
//!      reference for each, the joint update that last reset its Psi, is the participant's own;
//!      or the participant started independently after the store last saw it), its holders run
//!      the exact method among themselves and the others are *left out*: they apply nothing
//!      (their Psi keeps accumulating, so that store stays right for them), ask the holders for
//!      their store right after the epoch (STORE_WANTED, answered by the two lowest-id holders
//!      with the store in parts of COOPLOC_STORE_FRAGMENT series, paced to
//!      [`NodeConfig::store_bps`], the fragments a repeated request says are held
//!      (COOPLOC_STORE_HELD) left out, see [`store_sync`]), and adopt it, brought forward by the
//!      epochs they were left out of while it came; the team is exact again from the next epoch
//!      on. A node that took the store after its record of an epoch went (the record carried
//!      the store before) is left out of that epoch too, and brings the store forward by it
//!      instead of asking for another;
//!    - else every node *heals* with the covariance-intersection bound of
//!      [`crate::estimation::coop`] (cross blocks dropped, each participant's covariance divided
//!      by its weight), which is consistent whatever the true cross-covariances were; after it
//!      the stores agree again and the exact method resumes.
//!
//!    Ranges whose innovation fails a chi-square gate are left out (every node leaves out the
//!    same ones). An update that fails is retried with the bound; one that fails again is not
//!    applied, and said so (FAILED).
//! 4. **Back to the present**: the node restores its checkpoint at `t_e`, writes back its own
//!    share, and replays every input since.
//! 5. **Report**: a COOPLOC_EPOCH (APPLIED, PARTIAL or FAILED) with the participants and the
//!    digest of the store after the epoch. A peer that ran the same epoch with another set or
//!    another digest counts a disagreement; the next epoch's records heal it.
//!
//! # Guards
//!
//! Nothing one message says is obeyed blindly: IMU samples that jump the clock are held until
//! the stream confirms the jump; odometer samples and epochs far ahead of the filter, epochs
//! whose id does not fit their time, records with a covariance that is not positive
//! semi-definite are refused and counted. A wall-clock jump (the node was frozen) does not time
//! out the epochs that were waiting.
//!
//! # Ground stations
//!
//! A ground station (any system outside the team) may ask a node for its estimate now:
//! MAV_CMD_REQUEST_MESSAGE with param1 = 61002 (COOPLOC_ESTIMATE), to system 0 or the node's id,
//! component 0 or 191. The node answers with a COMMAND_ACK to the requester and the estimate to
//! every peer, at most once per [`ESTIMATE_REQUEST_INTERVAL_US`]; nothing else a ground station
//! sends reaches the filter.
//!
//! Wall time enters only through [`NodeCore::poll`] (timeouts and retries); a run whose
//! messages all arrive is therefore deterministic and independent of timing.

mod rewind;
mod store_sync;

use std::collections::{BTreeMap, BTreeSet, VecDeque};

use super::cadence::Cadence;
use super::log::{CoopUpdateRecord, RangeRecord};
use crate::estimation::ci::ci_update;
use crate::estimation::ins::{InsConfig, InsInitialSigma};
use crate::estimation::nav::{Drive, NavFilter, NavModel, NavState};
use crate::estimation::{
    BoundScope, BystanderShare, CoopMeasurement, Correction, CrossCovariances, CrossMode, EstimationError, ImuSample, JointPrior,
    Method, OdometerSample, PlatformFilter, PlatformId, PositionFixSample, RangeSample, StoreRef, UpdateOptions, WheelSample,
    cooperative_update_with,
};
use crate::protocol::MavMessage;
use crate::protocol::coop::{CoopKind, CoopMessage};
use crate::protocol::dialect::cooploc::{MavCmd, MavResult};
use crate::protocol::fragment::{MAX_RADIO_FRAME, Pushed, Reassembler, fragment};
use crate::protocol::record::{self, Encoding, FLAG_FRESH, StateRecord};
use crate::protocol::wire::{self, EpochState};
use crate::time::TimeUs;
use rewind::{Local, LocalFate, Rewind, WriteBack};
use store_sync::{Awaiting, LaterEpoch, StoreChoice, StoreRequest, StoreSync, choose_store};

/// How a node runs.
#[derive(Debug, Clone)]
pub struct NodeConfig {
    pub id: PlatformId,
    /// One of dead reckoning, no-propagation, decentralized, covariance intersection (the
    /// centralized EKF needs a centre).
    pub method: Method,
    /// The navigation model: the INS, or the planar robot of a wheeled vehicle without IMU.
    pub model: NavModel,
    pub encoding: Encoding,
    /// Every platform of the team, this one included: the records an epoch waits for.
    /// Messages from other platforms are counted and dropped.
    pub team: Vec<PlatformId>,
    /// Wall time a node waits for missing records before it runs an epoch without them, us.
    pub epoch_timeout_us: u64,
    /// Wall time between COOPLOC_EPOCH messages while waiting (retransmission requests), us.
    pub retry_us: u64,
    /// The retry interval follows the team's epoch cadence ([`super::cadence`]: at most
    /// `retry_us`, at most a tenth of the epoch period in wall time). False: `retry_us` as set
    /// (an operator who chose the interval, e.g. for a radio's air time).
    pub retry_follows_cadence: bool,
    /// How much history (checkpoints and the inputs after them) the node keeps, vehicle time, us
    /// (more when the vehicle's clock runs faster than the wall clock: [`super::cadence`]).
    pub history_us: u64,
    /// An epoch still open this long (vehicle time) after its instant is run with what is
    /// there, so that memory stays bounded whatever the network does, us.
    pub max_lag_us: u64,
    /// Vehicle time the node waits after an epoch's instant before it broadcasts, so that the
    /// ranges its vehicle measured at the epoch have arrived, us.
    pub range_grace_us: u64,
    /// Epochs and odometer samples further ahead of the filter than this are refused, us.
    pub max_lead_us: u64,
    /// Probability that the range gate rejects a range of a consistent filter (0: no gate).
    pub gate_probability: f64,
    /// The initial state is independent of every teammate's error (initialised from the vehicle,
    /// a survey or a scenario, not from a teammate's estimate).
    pub independent_start: bool,
    /// Send each own range as a COOPLOC_RANGE too (for ground stations and logs: the joint
    /// update takes ranges from the records). Off on links that count every byte.
    pub echo_ranges: bool,
    /// Every record that reaches this core is its sender's own (a signed team: `cooploc node`
    /// sets it with `--team-key`; the fault harness, whose network carries only its nodes'
    /// records). What a record says of its sender is then believed before vetting: a teammate
    /// whose record of a later epoch says it first broadcast after the epoch we wait on (it
    /// restarted) is not waited for, nor one that answers our request for its record "no
    /// record" (COOPLOC_EPOCH_STATE_NO_RECORD). False on an unsigned team, where a forger could
    /// say the same of a genuine teammate.
    pub authenticated_peers: bool,
    /// The team's ranging schedule, when it is periodic: an epoch every `epoch_period_us` of the
    /// team clock, ids consecutive. A node then knows the next epoch from the last one it knows
    /// (id + 1, a period later) as its filter passes that one, instead of hearing of it first
    /// from its own ranges or a teammate's record: a member that ranges to nobody broadcasts
    /// with the others, not after them. Every member must be told the same period (a member told
    /// none learns the epochs as before). None: no schedule.
    pub epoch_period_us: Option<u64>,
    /// Airtime on a shared channel (a radio): the member at position `k` of the sorted `team`
    /// broadcasts its record `k * slot_us` of the team clock after the epoch is due, and no
    /// member asks for a missing record before every slot has passed (the retransmission clock
    /// starts when the plan has run). Every member computes the same plan from the team list.
    /// 0: everyone at once, asking from its own broadcast on.
    pub slot_us: u64,
    /// The grid the vehicle's ranges are put on (the profile's `inputs.epoch_grid_ms`), us. A
    /// range of this node's vehicle that names an epoch the node already knows at an instant one
    /// grid step or less away is taken at the known instant (`NodeStats::ranges_restamped`),
    /// not refused: near the middle between two grid instants two nodes' clock mappings,
    /// microseconds apart, can put the same ranging on neighbouring instants, and the epoch's
    /// id, which the ranging system gave both, says which it is. Only on a signed team
    /// ([`NodeConfig::authenticated_peers`]): on an unsigned one the known instant may be a
    /// forger's bare claim, which must not move the node's own ranges. 0: no grid, an own range
    /// at another instant is refused like any claim.
    pub range_snap_us: u64,
    /// Store bytes per second of wall time each answerer sends a teammate that asked for it
    /// ([`store_sync`]: the next fragments of the store at each answer, once per retry
    /// interval; the asking node brings the store forward by the epochs that passed meanwhile).
    /// 0: the whole store at each answer (a network that takes it at once).
    pub store_bps: u64,
}

impl NodeConfig {
    /// A configuration with the defaults of `cooploc node`: 2 s timeout, 100 ms retries, 4 s of
    /// history, 120 s of maximum lag, 100 ms range grace, 30 s maximum lead, a range gate at
    /// one false rejection in a million.
    pub fn new(
        id: PlatformId,
        method: Method,
        ins: InsConfig,
        initial_sigma: InsInitialSigma,
        encoding: Encoding,
        team: Vec<PlatformId>,
    ) -> Self {
        Self::for_model(id, method, NavModel::Ins { config: ins, initial_sigma }, encoding, team)
    }

    /// The same defaults for any navigation model.
    pub fn for_model(id: PlatformId, method: Method, model: NavModel, encoding: Encoding, team: Vec<PlatformId>) -> Self {
        Self {
            id,
            method,
            model,
            encoding,
            team,
            epoch_timeout_us: 2_000_000,
            retry_us: 100_000,
            retry_follows_cadence: true,
            history_us: 4_000_000,
            max_lag_us: 120_000_000,
            range_grace_us: 100_000,
            max_lead_us: 30_000_000,
            gate_probability: 1e-6,
            independent_start: true,
            echo_ranges: true,
            authenticated_peers: false,
            epoch_period_us: None,
            slot_us: 0,
            range_snap_us: 0,
            store_bps: 0,
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
    #[error("the range grace ({grace_us} us) must be shorter than the history kept ({history_us} us)")]
    Grace { grace_us: u64, history_us: u64 },
    #[error("the gate probability {0} must be in [0, 1)")]
    Gate(f64),
    #[error(
        "the schedule does not fit: the range grace ({grace_us} us) and {members} airtime slots of {slot_us} us take {plan_us} us, which must be less than the epoch period ({period_us} us, at least {min_period_us} us) and the history kept ({history_us} us)"
    )]
    Schedule { period_us: u64, min_period_us: u64, grace_us: u64, members: usize, slot_us: u64, plan_us: u64, history_us: u64 },
    #[error(transparent)]
    Filter(#[from] EstimationError),
}

/// What the node feeds in.
#[derive(Debug, Clone, PartialEq)]
pub enum NodeInput {
    /// What drives an INS node.
    Imu(ImuSample),
    /// What drives a planar node (a wheeled robot without IMU).
    Wheel(WheelSample),
    Odometer(OdometerSample),
    /// A GNSS fix of the node's own vehicle (before GNSS is lost, or a teammate that keeps it).
    PositionFix(PositionFixSample),
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

impl NodeInput {
    /// The time of a sample that drives the filter (IMU or wheels), if this is one.
    pub fn drive_time(&self) -> Option<TimeUs> {
        match self {
            NodeInput::Imu(s) => Some(s.t),
            NodeInput::Wheel(s) => Some(s.t),
            _ => None,
        }
    }
}

/// What the node sends out.
#[derive(Debug, Clone, PartialEq)]
// A message is moved once, to the runner: boxing it would allocate for every one sent.
#[allow(clippy::large_enum_variant)]
pub enum NodeOutput {
    ToPeers(MavMessage),
    /// Our estimate, to the team (the shell sends it as COOPLOC_ESTIMATE, in f32) and, as the
    /// profile says, to the vehicle: after each joint update, and to a ground station that asks.
    Estimate(wire::EstimateReport),
    /// The internals of a joint update just run (for logs).
    Update(Box<CoopUpdateRecord>),
}

/// Counters of everything the node did, refused and dropped.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct NodeStats {
    pub imu: u64,
    pub odometer: u64,
    /// IMU samples not after the filter's time, or refused by the filter.
    pub imu_rejected: u64,
    /// Gaps in the IMU stream longer than the filter takes, bridged by holding the next sample.
    pub imu_gaps_bridged: u64,
    /// IMU samples that jumped the clock and were not confirmed by the samples after them.
    pub imu_clock_jumps_refused: u64,
    /// The filter's clock moved to the first IMU sample (a start long after the initial time).
    pub clock_restarts: u64,
    /// Odometer samples that arrived after the filter had passed their time, applied by replay.
    pub odometer_late: u64,
    /// Odometer samples older than the history, or implausibly far ahead of the IMU.
    pub odometer_unmatched: u64,
    /// Odometer samples the filter refused (gated or invalid).
    pub odometer_rejected: u64,
    /// GNSS fixes taken (applied, or waiting for the IMU sample that covers them), as
    /// `odometer` counts odometer samples.
    pub fixes: u64,
    /// GNSS fixes beyond their gate (or invalid): not applied.
    pub fixes_rejected: u64,
    /// GNSS fixes older than the history, or implausibly far ahead of the IMU.
    pub fixes_unmatched: u64,
    pub records_sent: u64,
    pub records_resent: u64,
    /// Of those, resends of only the fragments a teammate said it lacked (COOPLOC_EPOCH_SET's
    /// incomplete records), and the fragments they carried.
    pub resends_partial: u64,
    pub fragments_resent: u64,
    /// With airtime slots: first requests for a whole record of ours, not answered until
    /// repeated (a shared channel may have delivered them after the record).
    pub requests_deferred: u64,
    /// Resend requests not answered: the epoch's record was resent less than half a retry
    /// interval ago, or [`RESENDS_PER_RETRY`] records' worth went out in the last retry interval, or
    /// (airtime slots) our broadcast of it may still be on the air.
    pub resends_limited: u64,
    pub records_received: u64,
    /// Records refused: not decodable, or a covariance that is not positive semi-definite.
    pub records_implausible: u64,
    /// Records refused at their epoch because most of the ranges the teammates measured to
    /// that platform contradict them (`node::vetting`, rule 1).
    pub records_contradicted: u64,
    /// Epochs at which a platform had two different records or more still standing: all
    /// refused (`node::vetting`, rule 2), the platform flagged.
    pub records_rival: u64,
    pub fragments_rejected: u64,
    pub records_incomplete: u64,
    pub records_undecodable: u64,
    pub ranges_rejected: u64,
    /// Ranges left out of a joint update by the chi-square gate.
    pub ranges_gated: u64,
    /// Own ranges that came after the node had broadcast that epoch's record.
    pub ranges_late: u64,
    /// Own ranges taken at their epoch's known instant, a grid step away from their own
    /// ([`NodeConfig::range_snap_us`]).
    pub ranges_restamped: u64,
    /// Messages from platforms outside the team.
    pub unknown_platforms: u64,
    pub late_messages: u64,
    /// Epoch claims refused: too far ahead, an id that does not fit its time, a conflicting time.
    pub epochs_implausible: u64,
    /// Of those, the claims naming an epoch known at another instant (two nodes' clock mappings
    /// put one range on neighbouring instants of the epoch grid, or a forgery).
    pub epochs_misnamed: u64,
    /// Of those, the claims (and open epochs, once a later one ran) whose id does not fit its
    /// time among the epochs known.
    pub epochs_unfit: u64,
    /// Of those, the claims more than `max_lead_us` ahead of the filter: a far-future forgery, or
    /// this node's filter behind its teammates' (a loaded machine): a later claim of the same
    /// epoch is taken once the filter is there. The rest are naming disagreements or forgeries.
    pub epochs_ahead: u64,
    pub epoch_messages_sent: u64,
    pub epochs_applied: u64,
    /// Epochs run without every expected member (timeout, lag bound, end of input, or a member
    /// whose record would never come: `epochs_not_waited`).
    pub epochs_partial: u64,
    /// The longest wall time from our broadcast of an epoch to its joint update, us.
    pub longest_wait_us: u64,
    /// Of the partial epochs, the ones run without waiting for a teammate that first broadcast
    /// after them (it restarted or joined since: its record would never come), as soon as its
    /// record of a later epoch said so ([`NodeConfig::authenticated_peers`]).
    pub epochs_not_waited: u64,
    /// Epochs with nothing to apply (no range among the participants, dead reckoning), or from
    /// before the node's start.
    pub epochs_skipped: u64,
    /// Joint updates refused twice (exact and bound): nothing applied.
    pub epochs_failed: u64,
    /// Epochs a peer reported with another set of records or another store digest.
    pub epoch_disagreements: u64,
    /// Epochs whose records carried different store digests: the stores had diverged.
    pub store_mismatches: u64,
    /// Joint updates run with the covariance-intersection bound (store mismatch with no valid
    /// store among the records, or a failed exact update).
    pub heals: u64,
    /// Epochs this node was left out of because its store was not valid for the participants
    /// (it then asks them for theirs).
    pub epochs_excluded: u64,
    /// Epochs the others ran without us while we were frozen, run as they did (our store only).
    pub epochs_bystood: u64,
    /// Epochs applied (counted in `epochs_applied`) in which no range involved us: the joint
    /// update ran among those the ranges involve, and we took our share of it as a bystander.
    pub epochs_unranged: u64,
    /// Epochs known from the team's periodic schedule before anything else said them
    /// ([`NodeConfig::epoch_period_us`]).
    pub epochs_scheduled: u64,
    /// Epochs whose timeout passed after a peer reported it ran them: waited for and run on
    /// the set of records the peer ran them on, not on the ones we held then ([`NodeCore`]
    /// docs, step 2).
    pub epochs_followed: u64,
    /// Epochs passed over because a record of the epoch before asked the team to (its sender
    /// had fallen behind the epochs: [`NodeCore`] docs, step 1), and our records that asked.
    pub epochs_strided: u64,
    pub skips_asked: u64,
    /// Teammates' requests for our record of an epoch we resolved without one, answered
    /// "no record" (COOPLOC_EPOCH_STATE_NO_RECORD), and such answers that ended a wait of ours
    /// for a teammate's record.
    pub no_record_said: u64,
    pub no_record_heard: u64,
    /// Our "no range" words (COOPLOC_EPOCH_STATE_NO_RANGE) sent in place of a record, and sent
    /// again to a teammate that asked; such words heard from teammates; our records sent after
    /// a word all the same because a teammate's record ranged us.
    pub no_range_said: u64,
    pub no_range_said_again: u64,
    pub no_range_heard: u64,
    pub records_released: u64,
    /// Answers to a teammate that asked for our store (the whole store, or paced, a piece of
    /// it), the store fragments they carried, and stores adopted from a teammate.
    pub stores_sent: u64,
    pub store_fragments_sent: u64,
    pub stores_adopted: u64,
    /// Epochs run without us while a store came that it was brought forward by when adopted.
    pub store_epochs_replayed: u64,
    /// Store snapshots refused: not asked for, stale, not valid for this node, undecodable.
    pub stores_refused: u64,
    /// Ground-station requests for our estimate answered, and refused (too soon after the last
    /// answer, or asking for another message).
    pub estimate_requests: u64,
    pub estimate_requests_refused: u64,
    /// Wall-clock jumps (the node was frozen) credited to the waiting epochs.
    pub freezes: u64,
    /// Times our horizontal position covariance was widened because, for [`REINIT_AFTER_EPOCHS`]
    /// epochs in a row, the vetting refused our record or the gate refused every range that
    /// involved us (see [`own_ranges_verdict`]).
    pub reinitialised: u64,
    pub replayed_inputs: u64,
}

impl NodeStats {
    /// Inputs from the vehicle that did not reach the filter.
    pub fn dropped_inputs(&self) -> u64 {
        self.imu_rejected
            + self.odometer_unmatched
            + self.odometer_rejected
            + self.imu_gaps_bridged
            + self.imu_clock_jumps_refused
    }
}

#[derive(Debug)]
struct Epoch {
    t: TimeUs,
    /// Wall time of our broadcast, once sent.
    broadcast_at: Option<u64>,
    /// Wall time a fragment of a record we lack last arrived (the wait is making progress).
    progress_at: u64,
    last_status_at: u64,
    early_request_sent: bool,
    /// Ranges our vehicle measured at this epoch (they go into our record).
    own_ranges: Vec<RangeSample>,
    records: BTreeMap<PlatformId, StateRecord>,
    /// Records for a platform that differ from the one in `records` (a forger's, or a
    /// relabelled replay), at most [`MAX_RIVALS`] each: the epoch vets them all.
    rivals: BTreeMap<PlatformId, Vec<StateRecord>>,
    /// Records the vetting refused while the epoch waited (contradicted by the teammates'
    /// ranges): not taken again when resent, and their platform waited for as if missing.
    refused: Vec<StateRecord>,
    /// Records and rivals held when the epoch was last vetted.
    vetted_at: usize,
    /// Open while (or just after) we were frozen: the others may have run it without us, so
    /// we wait for how they ran it before we run it.
    after_freeze: bool,
    /// The largest set of participants a peer reported it ran this epoch on (APPLIED or
    /// PARTIAL, the peer among them).
    peer_ran: Option<Vec<PlatformId>>,
    /// Its timeout passed after a peer reported it: run (or waited for) on the peer's set.
    followed: bool,
    /// With airtime slots: the wall time every member's slot had passed (the wait's start).
    plan_over_at: Option<u64>,
    /// With airtime slots: we broadcast after our slot had passed (the epoch before resolved
    /// late), when every member late alike sends at once.
    broadcast_late: bool,
    /// Members that said they have no record of this epoch and will send none: not waited for.
    no_record: BTreeSet<PlatformId>,
    /// Members that said "no range" in place of their record (ours too when we did), with the
    /// store digest they hold: their share is in unless a record ranges them.
    words: BTreeMap<PlatformId, u64>,
    /// Our record and its fragments, held back while our "no range" stands: sent once a
    /// teammate's record ranges us.
    withheld: Option<(StateRecord, Vec<MavMessage>)>,
}

impl Epoch {
    fn new(t: TimeUs) -> Self {
        Self {
            t,
            broadcast_at: None,
            progress_at: 0,
            last_status_at: 0,
            early_request_sent: false,
            own_ranges: Vec::new(),
            records: BTreeMap::new(),
            rivals: BTreeMap::new(),
            refused: Vec::new(),
            vetted_at: 0,
            after_freeze: false,
            peer_ran: None,
            followed: false,
            plan_over_at: None,
            broadcast_late: false,
            no_record: BTreeSet::new(),
            words: BTreeMap::new(),
            withheld: None,
        }
    }

    /// Whether a record held ranges `p`: its record is then needed, its word not enough.
    fn ranges_to(&self, p: PlatformId) -> bool {
        self.records.values().any(|r| r.ranges.iter().any(|x| x.to == p))
    }

    /// Whether `p`'s share of the epoch is in: its record, or its word no record contradicts.
    fn has(&self, p: PlatformId) -> bool {
        self.records.contains_key(&p) || (self.words.contains_key(&p) && !self.ranges_to(p))
    }

    /// The members whose share is in (what a COLLECTING status lists).
    fn settled(&self) -> Vec<PlatformId> {
        let mut s: BTreeSet<PlatformId> = self.records.keys().copied().collect();
        s.extend(self.words.keys().copied().filter(|&p| !self.ranges_to(p)));
        s.into_iter().collect()
    }

    /// Every record held, per platform: the first one and its rivals (what the vetting decides
    /// among).
    fn candidates(&self) -> BTreeMap<PlatformId, Vec<StateRecord>> {
        let mut c: BTreeMap<PlatformId, Vec<StateRecord>> = self.records.iter().map(|(&p, r)| (p, vec![r.clone()])).collect();
        for (p, rivals) in &self.rivals {
            c.entry(*p).or_default().extend(rivals.iter().cloned());
        }
        c
    }
}

/// Different records kept per platform and epoch besides the first (more are counted, not kept).
const MAX_RIVALS: usize = 3;

/// Shortest wall time between two answers to estimate requests, us.
pub const ESTIMATE_REQUEST_INTERVAL_US: u64 = 200_000;

/// Longest IMU gap the node bridges (a longer one is refused: the navigation is lost).
const MAX_BRIDGED_GAP_US: u64 = 60_000_000;

/// IMU samples after a clock jump that must continue from it before it is believed.
const JUMP_CONFIRMATIONS: usize = 3;

/// A wall-clock step between two polls longer than this is a freeze of the node itself.
const FREEZE_US: u64 = 1_000_000;

/// Most record resends in one retry interval, every epoch together, counted in records' worth
/// of fragments: a resend goes to every peer, so no stream of requests (forged, replayed or from
/// a confused peer) makes a node send more than this many records' worth per retry interval
/// besides its own broadcasts. A resend of only the fragments a teammate lacks costs its share
/// of a record, so that a large team's many small requests are all answered within the same
/// bytes (counted as one resend each, 63 teammates each lacking a few different fragments of a
/// 64-member record were served four at a time, and the epochs timed out); a "no record" answer
/// costs a whole record.
pub const RESENDS_PER_RETRY: usize = 4;

/// The unit [`RESENDS_PER_RETRY`] is counted in: a whole record's worth.
const RECORD_COST: u32 = 1024;

/// [`RESENDS_PER_RETRY`] in [`RECORD_COST`] units.
const RESENDS_LIMIT: u32 = RESENDS_PER_RETRY as u32 * RECORD_COST;

/// The fragments of one epoch's record resent since `at` (wall time): asked again within half a
/// retry interval, only the fragments not among them go.
#[derive(Debug, Clone)]
struct ResendWindow {
    at: u64,
    fragments: BTreeSet<u8>,
}

/// Epochs remembered after they are run (resends and agreement checks).
const EPOCHS_REMEMBERED: usize = 32;

/// The longest wait for missing records, in epoch timeouts, while fragments keep arriving.
const MAX_WAIT_FACTOR: u64 = 5;

/// The longest wait, in epoch timeouts from our broadcast, for the records a peer reported it
/// ran an epoch on that we lack (after that we run on ours).
const FOLLOW_WAIT_FACTOR: u64 = 2;

/// A record this many epochs behind the last one run still shows its sender is in step.
const RECENT_EPOCHS: u32 = 3;

/// The widest gap below an epoch that a node in step waits for ([`NodeCore::waits_for_a_gap`]).
const MAX_GAP_IN_STEP: u32 = 16;

/// Most epochs per second of vehicle time an epoch id may run ahead of the last one run.
const MAX_EPOCH_RATE_HZ: u64 = 100;

/// Whether two epochs (id, time) can both be true: the later id at the later time, and ids
/// advancing no faster than [`MAX_EPOCH_RATE_HZ`].
fn epochs_fit(a: (u32, TimeUs), b: (u32, TimeUs)) -> bool {
    let ((lo, tlo), (hi, thi)) = if a.0 <= b.0 { (a, b) } else { (b, a) };
    lo == hi && tlo == thi || hi > lo && thi > tlo && u64::from(hi - lo) <= (thi.0 - tlo.0) * MAX_EPOCH_RATE_HZ / 1_000_000 + 1
}

/// The last joint update a node applied: what its estimate reports (`epoch`, the update's NIS,
/// how many participants and ranges it ran on).
#[derive(Debug, Clone, Copy)]
struct LastEvent {
    epoch: u32,
    nis: f64,
    participants: u8,
    ranges: u8,
}

/// Whether `p`'s "no range" word stands among the epoch's `records`: none of them is its own,
/// and none ranges it.
fn word_stands(records: &[StateRecord], p: PlatformId) -> bool {
    !records.iter().any(|r| r.snapshot.id == p || r.ranges.iter().any(|x| x.to == p))
}

/// A joint update's result for this node: its own correction (none when it was a bystander),
/// its share as a bystander (when the store knows it), the platforms of the records that were
/// bystanders (their `Psi` goes on), the update's diagnostics (none for covariance
/// intersection) and the ranges the gate left out.
struct JointResult {
    own: Option<Correction>,
    share: Option<BystanderShare>,
    bystanders: Vec<PlatformId>,
    diagnostics: Option<crate::estimation::UpdateDiagnostics>,
    gated: Vec<usize>,
}

/// An epoch that was run: its time, the records it ran on and the store digest after it.
#[derive(Debug, Clone)]
struct RanOn {
    epoch: u32,
    participants: Vec<PlatformId>,
    digest: u64,
}

/// Epochs in a row whose ranges all contradict a node (its record refused by the vetting, or
/// every range involving it refused by the gate) before it widens its horizontal position
/// covariance (see [`own_ranges_verdict`]).
pub const REINIT_AFTER_EPOCHS: u32 = 3;

/// What an epoch's gate did with the ranges that involve one platform.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum OwnRanges {
    /// No range of the epoch involves it: no evidence either way.
    NoneInvolveUs,
    /// The gate let at least one of them through.
    SomeAccepted,
    /// The gate refused all of them; the largest misfit, `| |p_from - p_to| - range |` on the
    /// records' positions, m.
    AllRefused { residual_m: f64 },
}

/// Whether the gate of an epoch refused every range that involves `id` (`gated`: indices into
/// `ranges`; `records`: the epoch's, for the positions). A platform whose every range is refused
/// while its teammates' ranges among themselves pass is the one whose state is wrong: its
/// covariance claims a position the ranges contradict far beyond it, and a gate that refuses them
/// for ever keeps the truth away (issue 33, item 3). When that lasts [`REINIT_AFTER_EPOCHS`]
/// epochs, the node widens its horizontal position covariance by the misfit
/// ([`widen_horizontal`]), so that the next epochs' ranges pass the gate and pull it back.
/// Every platform's verdict follows from the records alone; each node acts on its own only.
pub fn own_ranges_verdict(id: PlatformId, records: &[StateRecord], ranges: &[RangeSample], gated: &[usize]) -> OwnRanges {
    let position = |p: PlatformId| records.iter().find(|r| r.snapshot.id == p).map(|r| r.snapshot.geometry.position_ned_m);
    let mut verdict = OwnRanges::NoneInvolveUs;
    for (i, r) in ranges.iter().enumerate().filter(|(_, r)| r.from == id || r.to == id) {
        if !gated.contains(&i) {
            return OwnRanges::SomeAccepted;
        }
        let misfit = match (position(r.from), position(r.to)) {
            (Some(a), Some(b)) => ((a - b).norm() - r.range_m).abs(),
            _ => 0.0,
        };
        let largest = match verdict {
            OwnRanges::AllRefused { residual_m } => residual_m.max(misfit),
            _ => misfit,
        };
        verdict = OwnRanges::AllRefused { residual_m: largest };
    }
    verdict
}

/// Adds `residual_m^2` to the variances of the north and east position errors (`index`: the
/// state's position indices). Adding a positive semi-definite term to one platform's own block
/// leaves its cross-covariances with the team as they are and keeps the joint covariance
/// positive semi-definite: the store stays exact, the platform only claims to know less.
pub fn widen_horizontal(p: &mut nalgebra::DMatrix<f64>, index: &[Option<usize>; 3], residual_m: f64) {
    for &i in index[..2].iter().flatten() {
        if i < p.nrows() {
            p[(i, i)] += residual_m * residual_m;
        }
    }
}

/// The node's state machine.
#[derive(Debug)]
pub struct NodeCore {
    cfg: NodeConfig,
    /// The filter, its checkpoints and the vehicle's inputs since the oldest.
    rewind: Rewind,
    /// IMU samples after a clock jump, waiting for confirmation.
    jump: Vec<Drive>,
    epochs: BTreeMap<u32, Epoch>,
    /// Id and time of the last epoch resolved.
    last_applied: Option<(u32, TimeUs)>,
    /// The last epoch resolved other than by passing it over (the store a left-out node asked
    /// for stays right across epochs the team passed over: nothing was applied at them).
    last_run: Option<u32>,
    /// Our fragments of recent epochs, for resends.
    sent: VecDeque<(u32, Vec<MavMessage>)>,
    /// Wall times and costs (in [`RECORD_COST`] units) of the resends and "no record" answers
    /// of the last retry interval, and the last resend of each epoch still remembered (the rate
    /// limits).
    resent_at: VecDeque<(u64, u32)>,
    epoch_resent: BTreeMap<u32, ResendWindow>,
    /// Wall time we last said "no record" of each epoch (within half a retry interval).
    no_record_said_at: BTreeMap<u32, u64>,
    /// Our "no range" words of recent epochs (epoch, time, digest), for teammates that ask for
    /// them after we ran the epoch, and when we last said each (within half a retry interval).
    words_said: VecDeque<(u32, TimeUs, u64)>,
    word_said_at: BTreeMap<u32, u64>,
    /// Whether a record of the last epoch we ran ranged us: we then send our record at the
    /// next epoch even without ranges of our own (a member the others range, as one of the
    /// paper team's vehicles, would otherwise send a word and then its record every epoch).
    ranged_last: bool,
    /// With airtime slots: the teammates that asked once for a whole record of ours, by epoch
    /// (the request may have been stale; answered when repeated).
    asked_once: BTreeSet<(u32, PlatformId)>,
    /// With airtime slots: until when (wall time) our broadcast of an epoch may still be on the
    /// air; a resend asked for before then is not sent.
    on_air_until: BTreeMap<u32, u64>,
    /// What recent epochs ran on.
    ran_on: VecDeque<RanOn>,
    /// Epochs up to this one are passed over: a record of the last epoch run asked for it.
    skip_through: Option<u32>,
    /// How far the filter was past the epoch's time (less the range grace) at our last
    /// broadcast, vehicle us.
    behind_at_broadcast: Option<u64>,
    absent: BTreeSet<PlatformId>,
    /// Wall time of the last message heard from each member.
    heard_at: BTreeMap<PlatformId, u64>,
    /// The last epoch each member said it was collecting, and when (wall time): a member still
    /// collecting an earlier epoch than one we wait on is behind, and its record of ours comes
    /// once it has run its own (a record carries the store after the epoch before).
    collecting: BTreeMap<PlatformId, (u32, u64)>,
    /// With airtime slots: the last wall time the shared channel was known busy: a message of
    /// any kind heard from another system then, or our own record still on the air (the earliest
    /// its air time could end: we hear nothing while we send).
    channel_busy_at: u64,
    /// Platforms whose id came with two different records for one epoch (a forger's, or a
    /// relabelled replay): flagged for the operator, for the rest of the run.
    flagged: BTreeSet<PlatformId>,
    /// Since when (wall time) the lowest epoch known is not the one after the last resolved:
    /// an epoch in between that we have not heard of yet.
    gap_since: Option<u64>,
    /// The last epoch id [`Self::schedule_next`] took up (learned or refused), so that it tries
    /// each id once.
    scheduled_up_to: Option<u32>,
    /// Wall time the last epoch was resolved (run or passed over).
    resolved_at: Option<u64>,
    /// Wall time a teammate's record fragment or epoch report last arrived.
    team_said_at: Option<u64>,
    /// Wall clock, us, as last given to [`NodeCore::poll`].
    wall_us: u64,
    /// Wall time we woke from the last freeze of our own.
    woke_at: Option<u64>,
    /// Wall time of the last answer to a ground station's estimate request.
    last_estimate_answer: Option<u64>,
    reassembler: Reassembler,
    cross: CrossCovariances,
    /// Independent of every teammate and no epoch applied yet.
    fresh: bool,
    /// The joint update that last reset our Psi (None: none since the start).
    own_ref: Option<StoreRef>,
    /// The first epoch we broadcast (our reference while we have applied none).
    born: Option<u32>,
    /// The stores we kept for teammates that ask, and the one we want.
    stores: StoreSync,
    /// The epoch cadence the retry interval follows.
    cadence: Cadence,
    gate: Option<[f64; 3]>,
    /// Epochs in a row whose ranges all contradicted us: our record refused by the vetting, or
    /// every range involving us refused by the gate.
    contradicted_epochs: u32,
    /// The last joint update applied, as the estimate reports it.
    last_event: Option<LastEvent>,
    pub stats: NodeStats,
}

impl NodeCore {
    /// A node whose filter starts at `t0` from `initial`.
    pub fn new(mut cfg: NodeConfig, t0: TimeUs, initial: impl Into<NavState>) -> Result<Self, NodeConfigError> {
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
        if cfg.range_grace_us >= cfg.history_us {
            return Err(NodeConfigError::Grace { grace_us: cfg.range_grace_us, history_us: cfg.history_us });
        }
        if !(0.0..1.0).contains(&cfg.gate_probability) {
            return Err(NodeConfigError::Gate(cfg.gate_probability));
        }
        let plan_us = (cfg.team.len() as u64).saturating_mul(cfg.slot_us).saturating_add(cfg.range_grace_us);
        let min_period_us = 1_000_000 / MAX_EPOCH_RATE_HZ;
        let fits = plan_us < cfg.history_us && cfg.epoch_period_us.is_none_or(|p| p >= min_period_us && plan_us < p);
        if !fits {
            return Err(NodeConfigError::Schedule {
                period_us: cfg.epoch_period_us.unwrap_or(0),
                min_period_us,
                grace_us: cfg.range_grace_us,
                members: cfg.team.len(),
                slot_us: cfg.slot_us,
                plan_us,
                history_us: cfg.history_us,
            });
        }
        let mut filter = NavFilter::new(cfg.model, t0, initial.into())?;
        filter.set_track_psi(cfg.method.needs_psi());
        let gate = UpdateOptions::gate_for_probability(cfg.gate_probability);
        Ok(Self {
            fresh: cfg.independent_start,
            cfg,
            rewind: Rewind::new(filter),
            jump: Vec::new(),
            epochs: BTreeMap::new(),
            last_applied: None,
            last_run: None,
            sent: VecDeque::new(),
            resent_at: VecDeque::new(),
            epoch_resent: BTreeMap::new(),
            no_record_said_at: BTreeMap::new(),
            words_said: VecDeque::new(),
            word_said_at: BTreeMap::new(),
            ranged_last: true,
            asked_once: BTreeSet::new(),
            on_air_until: BTreeMap::new(),
            ran_on: VecDeque::new(),
            skip_through: None,
            behind_at_broadcast: None,
            absent: BTreeSet::new(),
            heard_at: BTreeMap::new(),
            collecting: BTreeMap::new(),
            channel_busy_at: 0,
            flagged: BTreeSet::new(),
            gap_since: None,
            scheduled_up_to: None,
            resolved_at: None,
            team_said_at: None,
            wall_us: 0,
            woke_at: None,
            last_estimate_answer: None,
            reassembler: Reassembler::new(256),
            cross: CrossCovariances::new(),
            own_ref: None,
            born: None,
            stores: StoreSync::new(),
            cadence: Cadence::new(),
            gate,
            contradicted_epochs: 0,
            last_event: None,
            stats: NodeStats::default(),
        })
    }

    /// A node whose filter starts at `t0` from `initial` with the error covariance `p` (a state
    /// restored from disk, [`super::saved`]) instead of the model's initial one.
    pub fn restored(cfg: NodeConfig, t0: TimeUs, initial: NavState, p: &nalgebra::DMatrix<f64>) -> Result<Self, NodeConfigError> {
        let mut core = Self::new(cfg, t0, initial)?;
        let dim = core.rewind.filter.dim();
        if p.nrows() != dim || p.ncols() != dim {
            return Err(EstimationError::DimensionMismatch { what: "restored covariance", expected: dim, got: p.nrows() }.into());
        }
        if !crate::estimation::kalman::is_psd(p, 1e-9) {
            return Err(EstimationError::NotApplicable("a restored covariance must be positive semi-definite").into());
        }
        // A write-back of no correction: the covariance replaced, Psi the identity (as at a start).
        core.rewind.filter.apply_joint(&nalgebra::DVector::zeros(dim), p)?;
        core.rewind.restart_history();
        Ok(core)
    }

    pub fn id(&self) -> PlatformId {
        self.cfg.id
    }

    pub fn config(&self) -> &NodeConfig {
        &self.cfg
    }

    /// The filter as of the last input.
    pub fn filter(&self) -> &NavFilter {
        &self.rewind.filter
    }

    /// Team members currently not waited for (they missed an epoch and have not sent a record
    /// since).
    pub fn absent(&self) -> impl Iterator<Item = PlatformId> + '_ {
        self.absent.iter().copied()
    }

    /// The digest of the cross-covariance store (0 for methods that keep none): equal on every
    /// node that ran the same epochs on the same records.
    pub fn store_digest(&self) -> u64 {
        if self.cfg.method == Method::Decentralized { self.cross.digest() } else { 0 }
    }

    /// The cross-covariance store (with the references it holds).
    pub fn store(&self) -> &CrossCovariances {
        &self.cross
    }

    /// The stores kept for teammates that may ask: (epoch, store digest before it) of each.
    pub fn kept_stores(&self) -> impl Iterator<Item = (u32, u64)> + '_ {
        self.stores.kept()
    }

    /// Platforms whose id came with two different records for one epoch (see
    /// [`super::vetting`]): someone else speaks as them, or replays their records.
    pub fn flagged(&self) -> &BTreeSet<PlatformId> {
        &self.flagged
    }

    /// The last epoch resolved (run, or passed over), if any.
    pub fn last_epoch(&self) -> Option<u32> {
        self.last_applied.map(|(e, _)| e)
    }

    /// Takes one input; returns what to send.
    pub fn handle(&mut self, input: NodeInput) -> Vec<NodeOutput> {
        let mut out = Vec::new();
        match input {
            NodeInput::Imu(s) => self.vehicle_drive(Drive::Imu(s), &mut out),
            NodeInput::Wheel(s) => self.vehicle_drive(Drive::Wheel(s), &mut out),
            NodeInput::Odometer(s) => self.vehicle_local(Local::Odometer(s), &mut out),
            NodeInput::PositionFix(s) => self.vehicle_local(Local::Fix(s), &mut out),
            NodeInput::OwnRange { epoch, range } => {
                if range.from != self.cfg.id || range.to == self.cfg.id || !self.in_team(range.to) {
                    self.stats.ranges_rejected += 1;
                    return out;
                }
                let mut sent = wire::range_as_sent(&range);
                if !(sent.range_m.is_finite() && sent.range_m >= 0.0 && sent.sigma_m.is_finite() && sent.sigma_m > 0.0) {
                    self.stats.ranges_rejected += 1;
                    return out;
                }
                if let Some(known) = self.epochs.get(&epoch).map(|e| e.t)
                    && known != sent.t
                    && known.0.abs_diff(sent.t.0) <= self.cfg.range_snap_us
                    && self.cfg.authenticated_peers
                {
                    sent.t = known;
                    self.stats.ranges_restamped += 1;
                }
                if let Some(e) = self.learn_epoch(epoch, sent.t) {
                    if e.broadcast_at.is_some() {
                        self.stats.ranges_late += 1;
                    } else if e.own_ranges.len() < record::MAX_RANGES {
                        e.own_ranges.push(sent);
                        // For ground stations and logs: the joint problem takes it from our record.
                        if self.cfg.echo_ranges {
                            out.push(NodeOutput::ToPeers(wire::range_to_message(&sent, epoch)));
                        }
                    } else {
                        self.stats.ranges_rejected += 1;
                    }
                }
                self.advance(&mut out);
            }
            NodeInput::Peer { from, msg } => {
                self.peer_message(from, *msg, &mut out);
                self.advance(&mut out);
            }
        }
        out
    }

    // ---- the vehicle's inputs ----

    fn vehicle_drive(&mut self, s: Drive, out: &mut Vec<NodeOutput>) {
        let now = self.rewind.filter.time();
        if s.t() <= now || !self.rewind.filter.takes(&s) {
            self.stats.imu_rejected += 1;
            return;
        }
        let max_gap_us = (self.rewind.filter.max_gap_s() * 1e6) as u64;
        let gap = s.t().0 - now.0;
        if gap > max_gap_us {
            if self.stats.imu == 0 {
                // A start long before the vehicle's clock: the initial state is for "now".
                self.rewind.restart_clock(s.t());
                self.stats.clock_restarts += 1;
                self.stats.imu += 1;
                return;
            }
            // A jump: believed once the samples after it continue from it.
            let continues = self.jump.last().is_some_and(|last| s.t() > last.t() && s.t().0 - last.t().0 <= max_gap_us);
            if !continues {
                self.stats.imu_clock_jumps_refused += self.jump.len() as u64;
                self.jump.clear();
            }
            self.jump.push(s);
            if self.jump.len() < JUMP_CONFIRMATIONS {
                return;
            }
            if gap > MAX_BRIDGED_GAP_US {
                // Too long to bridge: the navigation is lost; refuse and say so.
                self.stats.imu_rejected += self.jump.len() as u64;
                self.jump.clear();
                return;
            }
            self.stats.imu_gaps_bridged += 1;
            for s in std::mem::take(&mut self.jump) {
                self.take_imu(s);
            }
            self.after_input(out);
            return;
        }
        self.stats.imu_clock_jumps_refused += self.jump.len() as u64;
        self.jump.clear();
        self.take_imu(s);
        self.after_input(out);
    }

    fn take_imu(&mut self, s: Drive) {
        match self.rewind.take_imu(s) {
            Ok(refused) => {
                self.stats.imu += 1;
                self.stats.odometer_rejected += refused.odometer;
                self.stats.fixes_rejected += refused.fixes;
            }
            Err(_) => self.stats.imu_rejected += 1,
        }
    }

    /// A local measurement of our own vehicle (an odometer sample, a GNSS fix): a local update
    /// at its time, or written into the past when late ([`rewind::Rewind::local`]). Counted by
    /// kind: taken (applied or waiting), refused, unmatched (far ahead of the IMU, or older than
    /// anything kept).
    fn vehicle_local(&mut self, s: Local, out: &mut Vec<NodeOutput>) {
        let fate = self.rewind.local(s, self.cfg.max_lead_us.min(1_000_000));
        let st = &mut self.stats;
        let (taken, refused_count, unmatched) = match s {
            Local::Odometer(_) => (&mut st.odometer, &mut st.odometer_rejected, &mut st.odometer_unmatched),
            Local::Fix(_) => (&mut st.fixes, &mut st.fixes_rejected, &mut st.fixes_unmatched),
        };
        match fate {
            LocalFate::Unmatched => {
                *unmatched += 1;
                return;
            }
            LocalFate::Applied | LocalFate::Waits => *taken += 1,
            LocalFate::Rejected => *refused_count += 1,
            LocalFate::Late { replayed, refused } => {
                *taken += u64::from(!refused);
                *refused_count += u64::from(refused);
                st.odometer_late += u64::from(matches!(s, Local::Odometer(_)));
                st.replayed_inputs += replayed;
            }
        }
        self.after_input(out);
    }

    /// After a vehicle input: broadcast and run what is due, forget what is older than the
    /// history (except what open epochs need).
    fn after_input(&mut self, out: &mut Vec<NodeOutput>) {
        self.advance(out);
        let horizon = self.rewind.filter.time().0.saturating_sub(self.cadence.history_us(self.cfg.history_us));
        let keep_from = self.epochs.values().map(|e| e.t.0).min().unwrap_or(u64::MAX).min(horizon);
        self.rewind.forget_before(keep_from);
    }

    /// Gives the core the wall clock (us, any monotonic origin): runs the timeouts and sends the
    /// retransmission requests that are due. Call it every few tens of milliseconds. A step of
    /// more than a second is the node's own freeze: the epochs that were waiting do not count it.
    pub fn poll(&mut self, wall_us: u64) -> Vec<NodeOutput> {
        let step = wall_us.saturating_sub(self.wall_us);
        if self.wall_us > 0 && step > FREEZE_US {
            self.stats.freezes += 1;
            self.woke_at = Some(wall_us);
            for e in self.epochs.values_mut() {
                e.broadcast_at = e.broadcast_at.map(|b| b + step);
                e.progress_at = e.progress_at.saturating_add(step);
                e.after_freeze = true;
            }
        }
        self.wall_us = self.wall_us.max(wall_us);
        self.cadence.observe_clock(self.wall_us, self.rewind.filter.time().0);
        let mut out = Vec::new();
        self.advance(&mut out);
        out
    }

    /// The retry interval now, us: the configured one, shortened to the epoch cadence
    /// ([`Cadence::retry_us`]).
    /// With airtime slots, never shorter than a slot and a quarter in wall time: the time a
    /// status and the record it asks for take on the air.
    fn retry_us(&self) -> u64 {
        let base = if self.cfg.retry_follows_cadence { self.cadence.retry_us(self.cfg.retry_us) } else { self.cfg.retry_us };
        if self.cfg.slot_us == 0 { base } else { base.max(self.to_wall_us(self.cfg.slot_us + self.cfg.slot_us / 4)) }
    }

    /// `vehicle_us` of the team clock in wall time, at the vehicle clock's measured rate (real
    /// time until measured).
    fn to_wall_us(&self, vehicle_us: u64) -> u64 {
        (vehicle_us as f64 / self.cadence.rate().unwrap_or(1.0).clamp(1e-3, super::cadence::MAX_RATE)) as u64
    }

    /// The epochs after the one at `t` our record asks the team to pass over: none while the
    /// filter is less than an epoch timeout of wall time behind `t` (its range grace aside), or
    /// no further behind than at our last broadcast (catching up: the backlog of one late epoch
    /// goes as the next ones run quickly); then one, and one more for every further half
    /// timeout, at most [`record::MAX_SKIP`]. A team keeping up asks for nothing; see the module
    /// docs, step 1.
    fn skip_to_ask(&mut self, t: TimeUs) -> u8 {
        let behind = self.rewind.filter.time().0.saturating_sub(t.0.saturating_add(self.cfg.range_grace_us));
        let growing = self.behind_at_broadcast.replace(behind).is_some_and(|last| last < behind);
        if !growing || self.cadence.rate().is_none() || self.rewind.ended() {
            return 0;
        }
        let half_timeout = (self.cfg.epoch_timeout_us / 2).max(1);
        let halves = (self.to_wall_us(behind) / half_timeout).saturating_sub(1);
        u8::try_from(halves).unwrap_or(u8::MAX).min(record::MAX_SKIP)
    }

    fn in_team(&self, p: PlatformId) -> bool {
        self.cfg.team.binary_search(&p).is_ok()
    }

    /// Not resolved yet, and not older than an epoch we have broadcast already (our record of
    /// that one does not carry an update at this one: we cannot take part in both).
    fn is_open(&self, epoch: u32) -> bool {
        self.last_applied.is_none_or(|(last, _)| epoch > last) && self.sent.back().is_none_or(|(last, _)| epoch >= *last)
    }

    /// Registers epoch `epoch` at `t` if the claim is plausible: not resolved yet, not far ahead
    /// of the filter, an id that fits its time among the epochs known, and no other time
    /// already known for it. A new epoch's instant becomes a mark (the filter is rebuilt when it
    /// has passed it already).
    fn learn_epoch(&mut self, epoch: u32, t: TimeUs) -> Option<&mut Epoch> {
        if !self.is_open(epoch) || self.stats.imu == 0 {
            // Resolved already, or the vehicle's clock is not known yet.
            self.stats.late_messages += 1;
            return None;
        }
        if let Some(known) = self.epochs.get(&epoch) {
            if known.t != t {
                self.stats.epochs_implausible += 1;
                self.stats.epochs_misnamed += 1;
                return None;
            }
            return self.epochs.get_mut(&epoch);
        }
        let ahead = t.0 > self.rewind.filter.time().0.saturating_add(self.cfg.max_lead_us);
        // Against the last epoch run, and the nearest open epochs that hold a record (a bare
        // claim, which anyone can make, is no evidence against another).
        let fits = |e: u32, te: TimeUs| epochs_fit((e, te), (epoch, t));
        let backed = |x: &&Epoch| !x.records.is_empty();
        let consistent = self.last_applied.is_none_or(|(e, te)| fits(e, te))
            && self.epochs.range(..epoch).rev().find(|(_, x)| backed(x)).is_none_or(|(&e, x)| fits(e, x.t))
            && self.epochs.range(epoch + 1..).find(|(_, x)| backed(x)).is_none_or(|(&e, x)| fits(e, x.t));
        if ahead || !consistent {
            self.stats.epochs_implausible += 1;
            self.stats.epochs_ahead += u64::from(ahead);
            self.stats.epochs_unfit += u64::from(!ahead);
            return None;
        }
        let mut fresh_epoch = Epoch::new(t);
        fresh_epoch.after_freeze = self.woke_at.is_some_and(|w| self.wall_us < w + self.cfg.epoch_timeout_us);
        self.epochs.insert(epoch, fresh_epoch);
        self.stats.replayed_inputs += self.rewind.mark(t);
        self.epochs.get_mut(&epoch)
    }

    /// A record's covariance must be positive semi-definite (to the rounding of its encoding).
    fn plausible(rec: &StateRecord) -> bool {
        rec.snapshot.validate().is_ok() && crate::estimation::kalman::is_psd(&rec.snapshot.covariance, 1e-6)
    }

    /// A fragment from `from`, if it is that platform's (counted as rejected otherwise).
    fn fragment_of(
        &mut self,
        from: PlatformId,
        f: crate::protocol::fragment::Fragment,
    ) -> Option<crate::protocol::fragment::Fragment> {
        if f.platform == from {
            Some(f)
        } else {
            self.stats.fragments_rejected += 1;
            None
        }
    }

    fn peer_message(&mut self, from: PlatformId, msg: MavMessage, out: &mut Vec<NodeOutput>) {
        if from != self.cfg.id {
            self.channel_busy_at = self.channel_busy_at.max(self.wall_us);
        }
        // Heartbeats, ground stations' other messages: nothing for the protocol.
        let Some(decoded) = CoopMessage::decode(&msg) else { return };
        if let Ok(CoopMessage::MessageRequest(r)) = &decoded {
            // (a ground station's: from outside the team)
            if r.is_for(self.cfg.id) {
                self.estimate_request(from, r.asks_estimate(), out);
            }
            return;
        }
        let kind = match &decoded {
            Ok(m) => m.kind(),
            Err(e) => e.kind,
        };
        if kind == CoopKind::Estimate || from == self.cfg.id {
            return; // estimates are for ground stations; our own traffic looped back
        }
        if !self.in_team(from) {
            self.stats.unknown_platforms += 1;
            return;
        }
        self.heard_at.insert(from, self.wall_us);
        let m = match decoded {
            Ok(m) => {
                if matches!(m.kind(), CoopKind::StateFragment | CoopKind::Epoch) {
                    self.team_said_at = Some(self.wall_us);
                }
                m
            }
            Err(e) => {
                match e.kind {
                    CoopKind::StateFragment | CoopKind::StoreFragment => self.stats.fragments_rejected += 1,
                    CoopKind::Range => self.stats.ranges_rejected += 1,
                    CoopKind::Epoch | CoopKind::StoreHeld | CoopKind::Estimate | CoopKind::MessageRequest => {}
                }
                return;
            }
        };
        match m {
            CoopMessage::StateFragment(f) => {
                let Some(f) = self.fragment_of(from, f) else { return };
                match self.reassembler.push(&f) {
                    Pushed::Complete(rec) => match record::decode_record(rec.platform, TimeUs(rec.time_usec), &rec.bytes) {
                        Ok(r) if Self::plausible(&r) && r.ranges.iter().all(|x| self.in_team(x.to)) => {
                            self.stats.records_received += 1;
                            // A record of a recent epoch shows the member is back in step: it is
                            // waited for again from the next epoch on, whether or not this one
                            // was still open (the same rule on every node, so that they agree
                            // on the team again after a stall, a restart or a late join).
                            let recent = self.last_applied.is_none_or(|(last, _)| rec.epoch.saturating_add(RECENT_EPOCHS) > last);
                            if let Some(e) = self.learn_epoch(rec.epoch, TimeUs(rec.time_usec)) {
                                match e.records.get(&rec.platform) {
                                    _ if e.refused.contains(&r) => {}
                                    None => {
                                        e.records.insert(rec.platform, r);
                                    }
                                    Some(first) if *first == r => {}
                                    Some(_) => {
                                        let rivals = e.rivals.entry(rec.platform).or_default();
                                        if !rivals.contains(&r) && rivals.len() < MAX_RIVALS {
                                            rivals.push(r);
                                        }
                                        self.flagged.insert(rec.platform);
                                    }
                                }
                                self.absent.remove(&rec.platform);
                            } else if recent {
                                self.absent.remove(&rec.platform);
                            }
                        }
                        Ok(_) => self.stats.records_implausible += 1,
                        Err(_) => self.stats.records_undecodable += 1,
                    },
                    Pushed::Rejected(_) => self.stats.fragments_rejected += 1,
                    Pushed::Stored => {
                        // A record's first fragment makes its epoch known (as a peer's range
                        // does): a node that measured no range of the epoch broadcasts without
                        // waiting for a whole record to cross a slow radio. And its sender is
                        // back: waited for again, already for this epoch (a member found absent
                        // whose record some teammates receive whole and we only in part would
                        // otherwise be run without here and with there).
                        let wall = self.wall_us;
                        if let Some(e) = self.learn_epoch(f.epoch, TimeUs(f.time_usec)) {
                            e.progress_at = wall;
                            self.absent.remove(&f.platform);
                        }
                    }
                    Pushed::Duplicate => {}
                }
                self.stats.records_incomplete += self.reassembler.take_dropped().len() as u64;
            }
            CoopMessage::StoreFragment(f) => {
                let Some(f) = self.fragment_of(from, f) else { return };
                // Only fragments of a store we asked for are kept.
                match self.stores.push_fragment(from, &f, self.wall_us) {
                    Some(Pushed::Complete(rec)) => match record::decode_store(&rec.bytes) {
                        Ok(snap) if snap.epoch == f.epoch => self.receive_store(from, snap),
                        Ok(_) | Err(_) => self.stats.stores_refused += 1,
                    },
                    Some(Pushed::Rejected(_)) => self.stats.fragments_rejected += 1,
                    Some(Pushed::Stored | Pushed::Duplicate) | None => {}
                }
            }
            // The joint problem takes ranges from records; a peer's range only makes the epoch
            // known early.
            CoopMessage::Range { epoch, range: r } => {
                if r.from == from && self.in_team(r.to) {
                    self.learn_epoch(epoch, r.t);
                } else {
                    self.stats.ranges_rejected += 1;
                }
            }
            CoopMessage::Epoch(a) => self.epoch_message(from, a, out),
            // What a teammate asking for a store we serve holds of it: its own word only, and
            // only on a signed team ([`NodeConfig::authenticated_peers`]): a forger speaking for
            // it could make us leave out what it lacks, as long as it kept on.
            CoopMessage::StoreHeld(h) if h.announcer == from && self.cfg.authenticated_peers => self.stores.held_by(from, h),
            CoopMessage::StoreHeld(_) | CoopMessage::Estimate(_) | CoopMessage::MessageRequest(_) => {}
        }
    }

    /// A teammate's COOPLOC_EPOCH (dropped unless its announcer is the sender): a request for our
    /// store, its records held while it waits (what to resend), or what it ran an epoch on
    /// (agreement, and what a node that times out follows).
    fn epoch_message(&mut self, from: PlatformId, a: wire::EpochAnnouncement, out: &mut Vec<NodeOutput>) {
        if a.announcer != from {
            return;
        }
        // A member that speaks of a recent epoch is back (it may be waiting for our
        // store before it broadcasts): waited for again, as by the teammates that got
        // its last record when we did not.
        if self.last_applied.is_none_or(|(last, _)| a.epoch.saturating_add(RECENT_EPOCHS) > last) {
            self.absent.remove(&from);
        }
        if a.state == EpochState::COOPLOC_EPOCH_STATE_STORE_WANTED {
            if let Some(rank) = store_sync::answer_rank(&a.participants, self.cfg.id) {
                self.send_store(from, a.epoch, a.digest, rank, out);
            }
            return;
        }
        if a.state == EpochState::COOPLOC_EPOCH_STATE_NO_RECORD {
            // The member resolved this epoch without a record: waiting for one is waiting for
            // nothing. (A record of it that we hold still counts: it was sent, after all.) Not
            // believed from unsigned peers, as a record's word on its sender is not
            // ([`NodeConfig::authenticated_peers`]): a forger could say it of a genuine member.
            if self.cfg.authenticated_peers
                && let Some(e) = self.epochs.get_mut(&a.epoch)
                && e.t == a.t
                && !e.records.contains_key(&from)
                && e.no_record.insert(from)
            {
                self.stats.no_record_heard += 1;
            }
            return;
        }
        if a.state == EpochState::COOPLOC_EPOCH_STATE_NO_RANGE {
            // A member's word in place of its record: its share is in unless a record ranges
            // it. Believed from signed peers only, as "no record" is: a forger's word for a
            // genuine member would have the team run the epoch without its record.
            let wall = self.wall_us;
            if self.cfg.authenticated_peers
                && let Some(e) = self.learn_epoch(a.epoch, a.t)
                && e.t == a.t
                && !e.records.contains_key(&from)
                && e.words.insert(from, a.digest).is_none()
            {
                e.progress_at = wall;
                self.stats.no_range_heard += 1;
            }
            return;
        }
        if a.state == EpochState::COOPLOC_EPOCH_STATE_COLLECTING {
            self.collecting.insert(from, (a.epoch, self.wall_us));
            self.learn_epoch(a.epoch, a.t);
        } else if let Some(ours) = self.ran_on.iter().find(|r| r.epoch == a.epoch) {
            if ours.participants != a.participants || ours.digest != a.digest {
                self.stats.epoch_disagreements += 1;
            }
        } else if let Some(e) = self.epochs.get_mut(&a.epoch)
            && a.participants.len() >= 2
            && e.peer_ran.as_ref().is_none_or(|ran| a.participants.len() > ran.len())
            && matches!(a.state, EpochState::COOPLOC_EPOCH_STATE_APPLIED | EpochState::COOPLOC_EPOCH_STATE_PARTIAL)
            && a.participants.contains(&from)
        {
            e.peer_ran = Some(a.participants.clone());
        }
        let reported = a.state != EpochState::COOPLOC_EPOCH_STATE_COLLECTING;
        if reported
            && let Some(e) = self.epochs.get_mut(&a.epoch)
            && e.broadcast_at.is_some()
            && !e.early_request_sent
            && a.participants.iter().any(|p| !e.has(*p))
        {
            // A peer ran the epoch on records we lack: ask for them now rather than
            // at the next retry.
            e.early_request_sent = true;
            e.last_status_at = self.wall_us;
            let (t, held) = (e.t, e.settled());
            let digest = self.store_digest();
            self.send_status(a.epoch, t, held, EpochState::COOPLOC_EPOCH_STATE_COLLECTING, digest, out);
        }
        if !a.participants.contains(&self.cfg.id) && a.state == EpochState::COOPLOC_EPOCH_STATE_COLLECTING {
            let held = a.incomplete.iter().find(|h| h.platform == self.cfg.id).copied();
            // With airtime slots, a teammate that holds nothing of our record may have asked
            // before our record reached it: a shared channel delivers in order, and its request
            // came behind our record. Answered when it asks again (it still lacks the record a
            // retry interval later); a request that was stale is followed by its report instead.
            if self.answer_with_word(a.epoch, out) {
                return;
            }
            let sent = self.sent.iter().any(|(e, _)| *e == a.epoch);
            if self.cfg.slot_us > 0 && held.is_none() && sent && self.asked_once.insert((a.epoch, from)) {
                self.stats.requests_deferred += 1;
                return;
            }
            if !sent && self.resolved_before(a.epoch) {
                self.say_no_record(a.epoch, a.t, out);
                return;
            }
            self.resend(a.epoch, held, out);
        }
    }

    /// A ground station asked for our estimate (MAV_CMD_REQUEST_MESSAGE for COOPLOC_ESTIMATE):
    /// the estimate now, to every peer, and an ACCEPTED acknowledgement; at most one answer per
    /// [`ESTIMATE_REQUEST_INTERVAL_US`] of wall time (the next ones are TEMPORARILY_REJECTED), so
    /// that a flood of requests cannot turn the node into an amplifier. A request for another
    /// message is UNSUPPORTED. The filter is not touched.
    fn estimate_request(&mut self, from: PlatformId, asks_estimate: bool, out: &mut Vec<NodeOutput>) {
        let too_soon = self.last_estimate_answer.is_some_and(|at| self.wall_us < at + ESTIMATE_REQUEST_INTERVAL_US);
        let result = match (asks_estimate, too_soon) {
            (false, _) => MavResult::MAV_RESULT_UNSUPPORTED,
            (true, true) => MavResult::MAV_RESULT_TEMPORARILY_REJECTED,
            (true, false) => MavResult::MAV_RESULT_ACCEPTED,
        };
        let to = (u8::try_from(from).unwrap_or(0), 0);
        out.push(NodeOutput::ToPeers(wire::command_ack(MavCmd::MAV_CMD_REQUEST_MESSAGE, result, to)));
        if result == MavResult::MAV_RESULT_ACCEPTED {
            self.stats.estimate_requests += 1;
            self.last_estimate_answer = Some(self.wall_us);
            out.push(NodeOutput::Estimate(self.estimate()));
        } else {
            self.stats.estimate_requests_refused += 1;
        }
    }

    /// Sends our record of `epoch` again, or only the fragments a teammate lacks when it said
    /// which it holds (`held`): a fragment at most once per half retry interval for one epoch,
    /// open or run, and at most [`RESENDS_PER_RETRY`] records' worth per retry interval in all.
    fn resend(&mut self, epoch: u32, held: Option<wire::HeldFragments>, out: &mut Vec<NodeOutput>) {
        let answered = self.answers_this_interval();
        let Some((_, frags)) = self.sent.iter().find(|(e, _)| *e == epoch) else { return };
        let (wall, retry) = (self.wall_us, self.retry_us());
        if self.epoch_resent.get(&epoch).is_some_and(|w| wall >= w.at + retry / 2) {
            self.epoch_resent.remove(&epoch);
        }
        let window = self.epoch_resent.get(&epoch);
        let index = |m: &MavMessage| match m {
            MavMessage::COOPLOC_STATE_FRAGMENT(f) => f.frag_index,
            _ => 0,
        };
        let fresh: Vec<&MavMessage> = frags
            .iter()
            .filter(|m| held.is_none_or(|h| !h.holds(index(m))) && window.is_none_or(|w| !w.fragments.contains(&index(m))))
            .collect();
        // With airtime slots: not while our broadcast may still be on the air.
        let on_air = self.on_air_until.get(&epoch).is_some_and(|&until| wall < until);
        let cost = (fresh.len() as u32 * RECORD_COST).div_ceil(frags.len().max(1) as u32);
        if fresh.is_empty() || on_air || answered + cost > RESENDS_LIMIT {
            self.stats.resends_limited += 1;
            return;
        }
        self.resent_at.push_back((wall, cost));
        let w = self.epoch_resent.entry(epoch).or_insert(ResendWindow { at: wall, fragments: BTreeSet::new() });
        w.fragments.extend(fresh.iter().map(|m| index(m)));
        if fresh.len() < frags.len() {
            self.stats.resends_partial += 1;
        }
        self.stats.fragments_resent += fresh.len() as u64;
        out.extend(fresh.into_iter().cloned().map(NodeOutput::ToPeers));
        self.stats.records_resent += 1;
    }

    /// What the resends and "no record" answers sent in the last retry interval cost, in
    /// [`RECORD_COST`] units (the older ones are forgotten).
    fn answers_this_interval(&mut self) -> u32 {
        let (wall, retry) = (self.wall_us, self.retry_us());
        while self.resent_at.front().is_some_and(|&(at, _)| wall >= at + retry) {
            self.resent_at.pop_front();
        }
        self.resent_at.iter().map(|&(_, cost)| cost).sum()
    }

    /// Whether `epoch` is behind us: resolved (run, passed over, skipped while we were away or
    /// before our history, run as a bystander), or agreed to be passed over before we broadcast
    /// it. Without a record of ours in `sent`, none will come.
    fn resolved_before(&self, epoch: u32) -> bool {
        let open = self.epochs.get(&epoch);
        let resolved = open.is_none() && !self.is_open(epoch);
        resolved || (self.agreed_to_pass_over(epoch) && open.is_none_or(|e| e.broadcast_at.is_none()))
    }

    /// Tells the team we have no record of `epoch` at `t` and will send none (a teammate asked
    /// for it): once per epoch per half retry interval, within the resends' own limit of
    /// [`RESENDS_PER_RETRY`] per retry interval.
    fn say_no_record(&mut self, epoch: u32, t: TimeUs, out: &mut Vec<NodeOutput>) {
        let (wall, retry) = (self.wall_us, self.retry_us());
        let answered = self.answers_this_interval();
        self.no_record_said_at.retain(|_, at| wall < *at + retry / 2);
        if self.no_record_said_at.contains_key(&epoch) || answered + RECORD_COST > RESENDS_LIMIT {
            self.stats.resends_limited += 1;
            return;
        }
        self.resent_at.push_back((wall, RECORD_COST));
        self.no_record_said_at.insert(epoch, wall);
        self.stats.no_record_said += 1;
        let digest = self.store_digest();
        self.send_status(epoch, t, Vec::new(), EpochState::COOPLOC_EPOCH_STATE_NO_RECORD, digest, out);
    }

    fn checkpoint_at(&self, t: TimeUs) -> Option<&NavFilter> {
        self.rewind.checkpoint_at(t)
    }

    /// Whether epoch `epoch`, the lowest open one, waits (a timeout at most, from when the gap
    /// was first seen) for an epoch before it that we have not heard of. Epoch ids are
    /// consecutive: one we have not heard of lies before this one, and our record of this one
    /// would not carry its update, so we wait for it to become known rather than broadcast too
    /// early. Not after a longer silence (our radio was out of range, we were dead): those epochs
    /// are over, and waiting would only make us late for this one. Epochs the team agreed to
    /// pass over are no gap: nobody says them.
    ///
    /// A node *in step* (it had resolved an epoch within a timeout when it saw the gap) waits
    /// for a wider gap: its team resolves epochs more slowly than the vehicles move (a lossy
    /// link at 5x), a node that measures no range learns the epochs in between only from its
    /// teammates, and those messages were lost. Broadcasting this one at once would leave the
    /// team waiting a timeout for our records of the ones in between, which we could then no
    /// longer send (50% datagram loss, packed, 5x: 85 partial epochs in 20 runs).
    ///
    /// A node *back from a silence* (no epoch resolved for a timeout) that has not heard its team
    /// since knows only the epochs of range echoes (or its own ranges), which go out as the
    /// vehicles measure them, while the team may be resolving epochs well behind (a link with
    /// loss and 0-300 ms of delay at 5x: 13). Broadcasting the newest would close every epoch
    /// before it to us, and the team would wait a timeout for our records of those, epoch after
    /// epoch. The team's reports, every retry interval, name the epoch it is at: it waits for
    /// one.
    fn waits_for_a_gap(&mut self, epoch: u32) -> bool {
        let timeout = self.cfg.epoch_timeout_us;
        let seen = self.gap_since.unwrap_or(self.wall_us);
        let in_step = self.resolved_at.is_some_and(|at| seen < at.saturating_add(timeout));
        let widest = if in_step { MAX_GAP_IN_STEP } else { RECENT_EPOCHS };
        let unheard =
            !in_step && self.resolved_at.is_some_and(|at| self.team_said_at.is_none_or(|said| said < at.saturating_add(timeout)));
        let gap = self.last_applied.is_some_and(|(last, _)| {
            let last = last.max(self.skip_through.unwrap_or(0));
            epoch > last.saturating_add(1) && (epoch <= last.saturating_add(widest) || unheard)
        });
        gap && self.wall_us < *self.gap_since.get_or_insert(self.wall_us) + timeout
    }

    /// Broadcasts, resolves and retries until nothing more can be done now. Epochs go strictly
    /// in order: only the lowest open epoch is broadcast or run.
    fn advance(&mut self, out: &mut Vec<NodeOutput>) {
        self.schedule_next();
        self.ask_for_store(out);
        while let Some((&epoch, e)) = self.epochs.first_key_value() {
            let t = e.t;
            if e.broadcast_at.is_none() && self.agreed_to_pass_over(epoch) {
                // A record of the epoch before asked the team to pass this one over.
                self.pass_over(epoch);
                continue;
            }
            if e.broadcast_at.is_none() {
                if self.waits_for_a_gap(epoch) {
                    return;
                }
                self.gap_since = None;
                if self.awaiting_store(out) {
                    return;
                }
                if t <= self.rewind.oldest() && self.checkpoint_at(t).is_none() {
                    // Before our start or beyond our history: we cannot take part.
                    self.stats.epochs_skipped += 1;
                    self.finish_epoch(epoch);
                    continue;
                }
                let due = self.rewind.ended() || self.rewind.filter.time().0 >= self.slot_start_us(t);
                if !due || self.checkpoint_at(t).is_none() {
                    if due {
                        // Passed and no instant at `t` (the rebuild failed): cannot take part.
                        self.stats.epochs_skipped += 1;
                        self.finish_epoch(epoch);
                        continue;
                    }
                    return;
                }
                self.broadcast(epoch, t, out);
                continue;
            }
            // Records the teammates' ranges contradict are refused now, and their platform
            // waited for again (its genuine record may still come: a forger's came first).
            self.sift(epoch);
            self.release_withheld(epoch, out);
            let waiting_on_plan = self.epochs.get(&epoch).is_some_and(|e| e.plan_over_at.is_none());
            if self.cfg.slot_us > 0 && waiting_on_plan && self.plan_over(epoch) {
                let wall = self.wall_us;
                if let Some(e) = self.epochs.get_mut(&epoch) {
                    // every record should be in: ask for the missing ones now
                    e.plan_over_at = Some(wall);
                    e.last_status_at = 0;
                }
            }
            let Some(e) = self.epochs.get(&epoch) else { continue };
            // Members found absent are not waited for until a recent record of theirs arrives
            // (waiting for them briefly was tried: it makes nodes race on the set they run),
            // nor a restarted one whose record of this epoch will never come.
            let (missing, not_coming): (Vec<PlatformId>, Vec<PlatformId>) = self
                .cfg
                .team
                .iter()
                .copied()
                .filter(|p| !self.absent.contains(p) && !e.has(*p))
                .partition(|&p| !self.born_after(epoch, p) && !e.no_record.contains(&p));
            let complete = missing.is_empty();
            if !complete && self.cfg.slot_us > 0 && e.plan_over_at.is_none() {
                // Slots still to come: nothing is missing yet.
                return;
            }
            // The timeout runs from our broadcast (with slots, from the end of the plan), or
            // from the last fragment of a missing record (a lossy link still delivering), up to
            // MAX_WAIT_FACTOR timeouts in all.
            let since = e.broadcast_at.unwrap_or(0).max(e.plan_over_at.unwrap_or(0));
            let waited = self.wall_us.saturating_sub(since.max(e.progress_at));
            let waited_in_all = self.wall_us.saturating_sub(since);
            let lagging = self.rewind.filter.time().0.saturating_sub(t.0) >= self.cfg.max_lag_us;
            // After a freeze of our own: how did the others run this epoch? Without us, we run
            // it as they did, as a bystander; with us, or if nobody says within a timeout, as
            // usual.
            if let Some(ran) = e.peer_ran.clone().filter(|p| e.after_freeze && !p.contains(&self.cfg.id)) {
                if ran.iter().all(|p| e.has(*p)) || waited >= self.cfg.epoch_timeout_us || lagging {
                    self.run_bystander(epoch, &ran);
                    continue;
                }
            } else if e.after_freeze && e.peer_ran.is_none() {
                if waited >= self.cfg.epoch_timeout_us || lagging {
                    // Nobody said: they were not ahead of us (a stall of the whole machine
                    // froze them too). One timeout per freeze at most: run as usual from now on.
                    self.woke_at = None;
                    for x in self.epochs.values_mut() {
                        x.after_freeze = false;
                    }
                    continue;
                }
                self.ask_again(epoch, out);
                return;
            }
            if complete {
                if !not_coming.is_empty() {
                    self.stats.epochs_not_waited += 1;
                }
                self.run_epoch(epoch, !not_coming.is_empty(), out);
            } else if waited >= self.cfg.epoch_timeout_us
                || waited_in_all >= MAX_WAIT_FACTOR * self.cfg.epoch_timeout_us
                || lagging
            {
                // A peer ran it already: on the records it ran, not on ours, so that the stores
                // stay equal. Its records we lack are waited for (asked for) one timeout more.
                let follow = e.peer_ran.clone();
                let lacking = follow.as_ref().is_some_and(|ran| ran.iter().any(|p| !e.has(*p)));
                if follow.is_some()
                    && let Some(e) = self.epochs.get_mut(&epoch)
                    && !std::mem::replace(&mut e.followed, true)
                {
                    self.stats.epochs_followed += 1;
                }
                // A missing member still collecting an earlier epoch since our broadcast is behind,
                // not gone (it waited longer for a member we found absent): its record comes once
                // it has run that epoch. Waited for one timeout more, as a followed epoch's
                // records are, so that the two of us do not run this epoch on different sets.
                let behind =
                    missing.iter().any(|p| self.collecting.get(p).is_some_and(|&(their, at)| their < epoch && at >= since));
                if (lacking || behind) && waited_in_all < FOLLOW_WAIT_FACTOR * self.cfg.epoch_timeout_us && !lagging {
                    self.ask_again(epoch, out);
                    return;
                }
                // Absent: the members we have not heard from at all while we waited. One still
                // talking is alive on a lossy link: it is waited for again at the next epoch.
                let silent = missing.into_iter().filter(|p| self.heard_at.get(p).is_none_or(|&h| h < since));
                self.absent.extend(silent);
                if let Some(ran) = follow.filter(|_| !lacking) {
                    if ran.contains(&self.cfg.id) {
                        let partial = self.cfg.team.iter().any(|p| !ran.contains(p));
                        self.run_epoch_on(epoch, partial, Some(&ran), out);
                    } else {
                        self.run_bystander(epoch, &ran);
                    }
                    continue;
                }
                self.run_epoch(epoch, true, out);
            } else {
                self.ask_again(epoch, out);
                return;
            }
        }
    }

    /// The next epoch of a periodic schedule ([`NodeConfig::epoch_period_us`]): learned as the
    /// filter passes the newest epoch known at or before it (id + 1, a period later), once per
    /// id. Not from an epoch more than a period behind the filter (the team stopped ranging, or
    /// we were away): the next epoch then comes from the team again. Not after the vehicle's
    /// input ended (an epoch it never reaches would be passed over, and the next scheduled).
    fn schedule_next(&mut self) {
        let Some(period) = self.cfg.epoch_period_us.filter(|_| !self.rewind.ended()) else { return };
        let now = self.rewind.filter.time();
        let newest = self
            .epochs
            .iter()
            .map(|(&e, x)| (e, x.t))
            .chain(self.last_applied)
            .filter(|&(_, t)| t <= now)
            .max_by_key(|&(e, _)| e);
        let Some((e, t)) = newest else { return };
        let next = e.saturating_add(1);
        if self.scheduled_up_to.is_some_and(|s| s >= next)
            || self.epochs.contains_key(&next)
            || now.0 >= t.0.saturating_add(period.saturating_mul(2))
        {
            return;
        }
        self.scheduled_up_to = Some(next);
        if self.learn_epoch(next, TimeUs(t.0.saturating_add(period))).is_some() {
            self.stats.epochs_scheduled += 1;
        }
    }

    /// When we broadcast our record of the epoch at `t`, team clock, us: the range grace after
    /// it, and with airtime slots our place in the sorted team times the slot.
    fn slot_start_us(&self, t: TimeUs) -> u64 {
        let k = self.cfg.team.binary_search(&self.cfg.id).unwrap_or(0) as u64;
        t.0.saturating_add(self.cfg.range_grace_us + k * self.cfg.slot_us)
    }

    /// When every member's slot of the epoch at `t` has passed, team clock, us.
    fn plan_end_us(&self, t: TimeUs) -> u64 {
        t.0 + self.cfg.range_grace_us + self.cfg.team.len() as u64 * self.cfg.slot_us
    }

    /// Every member's record of `epoch` should have arrived by now, if nothing was lost: the
    /// filter has passed the end of the plan by a quarter slot; if we broadcast late (the team
    /// running late sends everything at once, as soon as the epoch before is resolved), the air
    /// time of every slot and one more has passed since; no fragment of a missing record came
    /// for a quarter slot; and nothing at all came for a quarter slot, or every slot's air time
    /// and one more have passed since our broadcast (a shared radio delivers what it holds in
    /// order: while it is busy, a missing record may still be queued behind what it carries).
    fn plan_over(&self, epoch: u32) -> bool {
        let Some(e) = self.epochs.get(&epoch) else { return true };
        let margin = self.cfg.slot_us / 4;
        let late_air_us = self.to_wall_us((self.cfg.team.len() as u64 + 1) * self.cfg.slot_us);
        let aired_all = self.wall_us >= e.broadcast_at.unwrap_or(0).saturating_add(late_air_us);
        let aired = !e.broadcast_late || aired_all;
        let idle = self.wall_us >= self.channel_busy_at.saturating_add(self.to_wall_us(margin));
        let quiet = self.wall_us >= e.progress_at.saturating_add(self.to_wall_us(margin)) && (idle || aired_all);
        self.rewind.ended() || self.rewind.filter.time().0 >= self.plan_end_us(e.t) + margin && aired && quiet
    }

    /// Teammate `p` first broadcast after `epoch` (it restarted, or joined, since): its record
    /// of a later epoch, from before any joint update, carries the epoch it first broadcast as
    /// its own reference's ([`Self::broadcast`]), and a node broadcasts its epochs in order, so
    /// its record of `epoch` will never come. Believed only from authenticated records
    /// ([`NodeConfig::authenticated_peers`]): on an unsigned team a forger's record of a later
    /// epoch, claiming to be `p`'s, would say the same and end the wait for `p`'s genuine one.
    fn born_after(&self, epoch: u32, p: PlatformId) -> bool {
        self.cfg.authenticated_peers
            && self
                .epochs
                .range(epoch.saturating_add(1)..)
                .any(|(_, later)| later.records.get(&p).is_some_and(|r| r.own_ref.before_any_update() && r.own_ref.epoch > epoch))
    }

    /// While we wait for records of `epoch`: our COLLECTING status (the records we hold, a
    /// retransmission request for the others) once per retry interval.
    fn ask_again(&mut self, epoch: u32, out: &mut Vec<NodeOutput>) {
        let retry = self.retry_us();
        let Some(e) = self.epochs.get_mut(&epoch) else { return };
        if self.wall_us < e.last_status_at + retry {
            return;
        }
        e.last_status_at = self.wall_us;
        let (t, held): (TimeUs, Vec<PlatformId>) = (e.t, e.settled());
        let digest = self.store_digest();
        self.send_status(epoch, t, held, EpochState::COOPLOC_EPOCH_STATE_COLLECTING, digest, out);
    }

    /// The request for a store still coming, repeated every retry interval (after our first
    /// epoch timeout too: the store is brought forward when it comes).
    fn ask_for_store(&mut self, out: &mut Vec<NodeOutput>) {
        if let Some(r) = self.stores.ask(self.last_run, self.wall_us, self.cfg.epoch_timeout_us, self.retry_us()) {
            self.ask_for_store_again(r, out);
        }
    }

    /// A repeated request for the store `r`: on a signed team what we hold of it first
    /// (COOPLOC_STORE_HELD, so that the answerers send only what is missing; an unsigned team
    /// does not believe it), then the request.
    fn ask_for_store_again(&mut self, r: StoreRequest, out: &mut Vec<NodeOutput>) {
        let held = if self.cfg.authenticated_peers { self.stores.held(self.cfg.id) } else { Vec::new() };
        for h in held {
            out.push(NodeOutput::ToPeers(wire::store_held_to_message(&h)));
        }
        self.send_status(r.epoch, r.t, r.members, EpochState::COOPLOC_EPOCH_STATE_STORE_WANTED, r.digest_before, out);
    }

    /// While a store we asked for may still come (an epoch timeout from the first request, and
    /// nothing resolved since but the epochs it is brought forward by), the next broadcast
    /// waits for it: our record would otherwise carry the old store, and we would be left out
    /// again. The request is repeated every retry interval meanwhile.
    fn awaiting_store(&mut self, out: &mut Vec<NodeOutput>) -> bool {
        let last = self.last_run;
        match self.stores.awaiting(last, self.wall_us, self.cfg.epoch_timeout_us, self.retry_us()) {
            Awaiting::No => false,
            Awaiting::Yes(ask) => {
                if let Some(r) = ask {
                    self.ask_for_store_again(r, out);
                }
                true
            }
        }
    }

    fn send_status(
        &mut self,
        epoch: u32,
        t: TimeUs,
        participants: Vec<PlatformId>,
        state: EpochState,
        digest: u64,
        out: &mut Vec<NodeOutput>,
    ) {
        // While collecting: the fragments we hold of records still incomplete, so that their
        // senders resend only the rest.
        let incomplete = if state == EpochState::COOPLOC_EPOCH_STATE_COLLECTING {
            self.reassembler
                .incomplete(epoch)
                .filter(|(p, have)| !participants.contains(p) && have.len() <= wire::MAX_HELD_FRAGMENTS)
                .map(|(platform, have)| wire::HeldFragments {
                    platform,
                    held: have.iter().enumerate().filter(|(_, h)| **h).fold(0, |m, (i, _)| m | 1 << i),
                })
                .take(wire::MAX_INCOMPLETE)
                .collect()
        } else {
            Vec::new()
        };
        let a = wire::EpochAnnouncement { epoch, t, announcer: self.cfg.id, participants, state, digest, incomplete };
        if let Ok(m) = wire::epoch_to_message(&a) {
            out.push(NodeOutput::ToPeers(m));
            self.stats.epoch_messages_sent += 1;
        }
    }

    /// Broadcasts our record of `epoch` (our checkpoint at `t`, our store digest, our ranges).
    fn broadcast(&mut self, epoch: u32, t: TimeUs, out: &mut Vec<NodeOutput>) {
        let snapshot = self.checkpoint_at(t).expect("checked").snapshot(self.cfg.id);
        let born = *self.born.get_or_insert(epoch);
        // Before our first joint update: fresh as of our first broadcast if we started
        // independently of the team, else a reference no store holds (we may be correlated with
        // anyone: only the bound is safe).
        let own_ref =
            self.own_ref.unwrap_or(if self.cfg.independent_start { StoreRef::fresh(born) } else { StoreRef::unplaced(born) });
        let refs = self.cross.references().collect();
        // With airtime slots: sent after our slot had passed (the team is late: every member
        // sends at once), and until when it may still be on the air (every slot and one more;
        // in our slot, the slot and one of margin for what went before us).
        let slot = self.cfg.slot_us;
        let late = slot > 0 && self.rewind.filter.time().0 > self.slot_start_us(t) + slot / 4;
        let on_air_us = self.to_wall_us(if late { (self.cfg.team.len() as u64 + 1) * slot } else { 2 * slot });
        let skip = self.skip_to_ask(t);
        self.stats.skips_asked += u64::from(skip > 0);
        let fresh = if self.fresh { FLAG_FRESH } else { 0 };
        // "No range" in place of our record: the decentralized method on a signed team (the
        // word is believed from signed peers only), nothing measured, no epochs to ask to pass
        // over, and nobody ranged us at the last epoch.
        let may_say_no_range =
            self.cfg.method == Method::Decentralized && self.cfg.authenticated_peers && skip == 0 && !self.ranged_last;
        let e = self.epochs.get_mut(&epoch).expect("open");
        let word = may_say_no_range && e.own_ranges.is_empty();
        let ours = StateRecord {
            snapshot,
            digest: if self.cfg.method == Method::Decentralized { self.cross.digest() } else { 0 },
            own_ref,
            refs,
            flags: record::with_skip(fresh, skip),
            ranges: std::mem::take(&mut e.own_ranges),
        };
        let sent = record::encode_record(&ours, self.cfg.encoding).ok().and_then(|bytes| {
            let frags = fragment(self.cfg.id, epoch, t.0, &bytes).ok()?;
            let msgs: Vec<MavMessage> = frags.iter().filter_map(|f| wire::fragment_to_message(f).ok()).collect();
            Some((record::decode_record(self.cfg.id, t, &bytes).ok()?, msgs))
        });
        let wall = self.wall_us;
        e.broadcast_at = Some(wall);
        e.last_status_at = wall;
        e.broadcast_late = late;
        if let Some((own, msgs)) = sent {
            if word {
                // Held back: sent if a teammate's record ranges us (see `release_withheld`).
                let digest = own.digest;
                e.words.insert(self.cfg.id, digest);
                e.withheld = Some((own, msgs));
                self.words_said.push_back((epoch, t, digest));
                if self.words_said.len() > EPOCHS_REMEMBERED {
                    self.words_said.pop_front();
                }
                self.stats.no_range_said += 1;
                self.send_status(epoch, t, Vec::new(), EpochState::COOPLOC_EPOCH_STATE_NO_RANGE, digest, out);
                return;
            }
            out.extend(msgs.iter().cloned().map(NodeOutput::ToPeers));
            e.records.insert(self.cfg.id, own);
            if slot > 0 {
                self.on_air_until.insert(epoch, wall + on_air_us);
                self.channel_busy_at = self.channel_busy_at.max(wall + self.to_wall_us(slot));
            }
            self.remember_sent(epoch, msgs);
        }
    }

    /// Keeps our fragments of `epoch` for resends (the last [`EPOCHS_REMEMBERED`] epochs').
    fn remember_sent(&mut self, epoch: u32, msgs: Vec<MavMessage>) {
        self.stats.records_sent += 1;
        self.sent.push_back((epoch, msgs));
        if self.sent.len() > EPOCHS_REMEMBERED
            && let Some((old, _)) = self.sent.pop_front()
        {
            self.epoch_resent.remove(&old);
            self.asked_once.retain(|(e, _)| *e > old);
            self.on_air_until.remove(&old);
        }
    }

    /// Our record of `epoch`, held back while our "no range" stood, sent after all once a
    /// teammate's record ranges us (its record is then needed: the ranges involve us).
    fn release_withheld(&mut self, epoch: u32, out: &mut Vec<NodeOutput>) {
        let id = self.cfg.id;
        let Some(e) = self.epochs.get_mut(&epoch).filter(|e| e.withheld.is_some() && e.ranges_to(id)) else { return };
        let Some((own, msgs)) = e.withheld.take() else { return };
        e.words.remove(&id);
        e.records.insert(id, own);
        out.extend(msgs.iter().cloned().map(NodeOutput::ToPeers));
        self.stats.records_released += 1;
        self.remember_sent(epoch, msgs);
    }

    /// A teammate asked for our record of `epoch` while it lacks our "no range" word: the word
    /// again, when we said one in its place and still do (at most once per half retry
    /// interval). False when our answer is not a word.
    fn answer_with_word(&mut self, epoch: u32, out: &mut Vec<NodeOutput>) -> bool {
        let id = self.cfg.id;
        let open = self.epochs.get(&epoch).map(|e| (e.t, e.withheld.is_some(), e.words.get(&id).copied()));
        let word = match open {
            Some((t, true, Some(digest))) => Some((t, digest)),
            Some(_) => None,
            None if self.sent.iter().any(|(e, _)| *e == epoch) => None,
            None => self.words_said.iter().find(|w| w.0 == epoch).map(|&(_, t, d)| (t, d)),
        };
        let Some((t, digest)) = word else { return false };
        let (wall, retry) = (self.wall_us, self.retry_us());
        self.word_said_at.retain(|_, at| wall < *at + retry / 2);
        if let std::collections::btree_map::Entry::Vacant(v) = self.word_said_at.entry(epoch) {
            v.insert(wall);
            self.stats.no_range_said_again += 1;
            self.send_status(epoch, t, Vec::new(), EpochState::COOPLOC_EPOCH_STATE_NO_RANGE, digest, out);
        }
        true
    }

    /// Forgets an epoch that was run or passed over. It becomes the last one resolved only if its
    /// id fits its time after the previous one: a claim nobody backed (a forged far epoch id
    /// that came up only because nothing contradicted it) cannot close every later epoch.
    fn finish_epoch(&mut self, epoch: u32) {
        let Some(e) = self.epochs.remove(&epoch) else { return };
        if self.last_applied.is_none_or(|last| epochs_fit(last, (epoch, e.t))) {
            let last = (epoch, e.t);
            self.last_applied = Some(last);
            self.last_run = Some(epoch);
            self.resolved_at = Some(self.wall_us);
            self.cadence.observe_epoch(epoch, e.t);
            self.reassembler.expire_before(epoch.saturating_add(1));
            // Claims that cannot follow this epoch are forgotten now: left open, a forged far
            // epoch would pin the history (and memory) at its time for ever.
            let open = self.epochs.len();
            self.epochs.retain(|&id, x| epochs_fit(last, (id, x.t)));
            self.stats.epochs_implausible += (open - self.epochs.len()) as u64;
            self.stats.epochs_unfit += (open - self.epochs.len()) as u64;
        } else {
            self.stats.epochs_implausible += 1;
            self.stats.epochs_unfit += 1;
        }
    }

    /// Once `epoch` holds a record of every member it waits for: refuses, for good, the records
    /// the vetting finds contradicted by the teammates' ranges (a rival of a refused record
    /// takes its place; a platform left without one is waited for again).
    fn sift(&mut self, epoch: u32) {
        let Some(e) = self.epochs.get_mut(&epoch) else { return };
        let held = e.records.len() + e.rivals.values().map(Vec::len).sum::<usize>();
        let complete = self.cfg.team.iter().all(|p| self.absent.contains(p) || e.records.contains_key(p));
        if !complete || held == e.vetted_at || held < 2 {
            return;
        }
        let v = super::vetting::vet(e.candidates());
        for r in v.contradicted {
            let p = r.snapshot.id;
            if p == self.cfg.id {
                continue; // our own is not waited for again: the epoch decides (see vetted)
            }
            if e.records.get(&p) == Some(&r) {
                e.records.remove(&p);
            } else if let Some(rivals) = e.rivals.get_mut(&p) {
                rivals.retain(|x| *x != r);
            }
            if !e.records.contains_key(&p)
                && let Some(next) = e.rivals.get_mut(&p).filter(|x| !x.is_empty()).map(|x| x.remove(0))
            {
                e.records.insert(p, next);
            }
            e.rivals.retain(|_, x| !x.is_empty());
            e.refused.push(r);
            self.stats.records_contradicted += 1;
        }
        e.vetted_at = e.records.len() + e.rivals.values().map(Vec::len).sum::<usize>();
    }

    /// The records `epoch` runs on: those held, less the ones [`super::vetting::vet`] refuses
    /// (contradicted by the teammates' ranges, or rivals), counted. Our own record may be
    /// among the refused (our state is far from where the teammates range us): we then sit the
    /// epoch out, as the others do without us.
    fn vetted(&mut self, epoch: u32) -> Vec<StateRecord> {
        let Some(e) = self.epochs.get(&epoch) else { return Vec::new() };
        if e.rivals.is_empty() && e.records.len() < 2 {
            return e.records.values().cloned().collect();
        }
        let v = super::vetting::vet(e.candidates());
        self.stats.records_contradicted += v.contradicted.len() as u64;
        self.stats.records_rival += v.rivals.len() as u64;
        v.accepted
    }

    /// The joint update of `epoch` on the records held (see the module docs), then the report.
    fn run_epoch(&mut self, epoch: u32, partial: bool, out: &mut Vec<NodeOutput>) {
        self.run_epoch_on(epoch, partial, None, out);
    }

    /// [`Self::run_epoch`] on the records of `only` when given (those a peer ran it on).
    fn run_epoch_on(&mut self, epoch: u32, partial: bool, only: Option<&[PlatformId]>, out: &mut Vec<NodeOutput>) {
        let Some(e) = self.epochs.get(&epoch) else { return };
        let t = e.t;
        if let Some(at) = e.broadcast_at {
            self.stats.longest_wait_us = self.stats.longest_wait_us.max(self.wall_us.saturating_sub(at));
        }
        let ours = e.records.get(&self.cfg.id).cloned();
        let mut words = e.words.clone();
        let mut records = self.vetted(epoch); // sorted by platform id
        if let Some(only) = only {
            records.retain(|r| only.contains(&r.snapshot.id));
        }
        // The words that stand: of members without a record here that no record ranges.
        words.retain(|p, _| only.is_none_or(|o| o.contains(p)) && word_stands(&records, *p));
        let prev_run = self.last_run;
        self.finish_epoch(epoch);
        if let Some(ours) = ours.filter(|o| !records.iter().any(|r| r.snapshot.id == o.snapshot.id)) {
            self.refused_own_record(t, ours, &records);
        }
        if partial {
            self.stats.epochs_partial += 1;
        }
        let dcl = self.cfg.method == Method::Decentralized;
        let agree = records.windows(2).all(|w| w[0].digest == w[1].digest);
        if dcl && !agree {
            self.stats.store_mismatches += 1;
        }
        // Diverged stores: the records that share a store valid for everyone run the exact
        // method; the others are left out and take that store afterwards.
        let digest_before = self.store_digest();
        let mut choice = if dcl && !agree { choose_store(&records) } else { None };
        if let Some(c) = &choice {
            records.retain(|r| c.members.contains(&r.snapshot.id));
        }
        // The epochs to pass over are those the records the epoch runs on ask for: a left-out
        // member's record, which some nodes hold and others not, does not count.
        self.pass_over_after(epoch, &records);
        self.ranged_last = records.iter().any(|r| r.ranges.iter().any(|x| x.to == self.cfg.id));
        let bystanders = self.word_bystanders(&words, &records, agree, &mut choice);
        let record_ids: Vec<PlatformId> = records.iter().map(|r| r.snapshot.id).collect();
        if let Some(c) = &choice {
            if c.members.contains(&self.cfg.id) || bystanders.contains(&self.cfg.id) {
                for &k in &c.refreshed {
                    self.cross.forget(k);
                }
            } else {
                self.leave_out(epoch, t, c, prev_run, &records, out);
                return;
            }
        }
        let exact = agree || choice.is_some();
        let mut participants = record_ids.clone();
        participants.extend(&bystanders);
        participants.sort_unstable();
        let ranges: Vec<RangeSample> =
            records.iter().flat_map(|r| r.ranges.iter().filter(|x| record_ids.contains(&x.to)).copied()).collect();
        let measurements: Vec<CoopMeasurement> = ranges.iter().map(CoopMeasurement::from).collect();
        let own_index = participants.iter().position(|&p| p == self.cfg.id);
        if dcl && exact && own_index.is_none() && self.stores.wanting() {
            // Run without our record (it came late, or we waited for a store): a store still
            // coming is brought forward by it.
            let later = LaterEpoch { epoch, records: records.clone(), refreshed: Vec::new(), bystanders: bystanders.clone() };
            self.stores.carry_on(prev_run, later, self.wall_us, self.cfg.epoch_timeout_us);
        }
        let nothing_to_do =
            own_index.is_none() || self.cfg.method == Method::DeadReckoning || (measurements.is_empty() && (exact || !dcl));
        let mut state = if partial { EpochState::COOPLOC_EPOCH_STATE_PARTIAL } else { EpochState::COOPLOC_EPOCH_STATE_APPLIED };
        let mut applied = None;
        if nothing_to_do {
            self.stats.epochs_skipped += 1;
        } else {
            let snapshots: Vec<_> = records.iter().map(|r| r.snapshot.clone()).collect();
            // Every participant takes a weight in a heal: a member that has never applied an
            // epoch may still be correlated with those that used its record (nodes that ran an
            // epoch on different sets), so its FRESH flag is no proof of independence.
            match self.joint_update(&snapshots, &measurements, exact, Vec::new(), bystanders) {
                Ok(result) => {
                    if dcl {
                        // Every participant's Psi restarts here, on every node that ran this
                        // (a bystander's goes on).
                        let digests: Vec<u64> = records.iter().map(|r| r.digest).collect();
                        let r = StoreRef::of_update(epoch, &record_ids, &digests);
                        for p in record_ids.iter().filter(|p| !result.bystanders.contains(p)) {
                            self.cross.set_reference(*p, r);
                        }
                    }
                    applied = Some(result);
                }
                Err(_) => {
                    self.stats.epochs_failed += 1;
                    state = EpochState::COOPLOC_EPOCH_STATE_FAILED;
                }
            }
        }
        if let Some(JointResult { mut own, share, diagnostics: diag, gated, .. }) = applied {
            self.stats.ranges_gated += gated.len() as u64;
            if let Some(residual_m) = self.time_to_widen(own_ranges_verdict(self.cfg.id, &records, &ranges, &gated))
                && let Some(ours) = records.iter().find(|r| r.snapshot.id == self.cfg.id)
                && let Some(own) = own.as_mut()
            {
                widen_horizontal(&mut own.p, &ours.snapshot.geometry.position_index, residual_m);
            }
            // A bystander the store does not know is uncorrelated with every participant: it
            // has nothing to take.
            let write_back = match (&own, &share) {
                (Some(c), _) => WriteBack::Joint(c),
                (None, Some(s)) => WriteBack::Bystander(s),
                (None, None) => WriteBack::Nothing,
            };
            let took = !matches!(write_back, WriteBack::Nothing);
            if took && self.replay_from_epoch(t, write_back).is_err() {
                // Our filter could not take its share: the store no longer matches it. Dropping
                // the store makes the next epoch's digests differ, and the team heals.
                self.cross.clear();
                self.stats.epochs_failed += 1;
                state = EpochState::COOPLOC_EPOCH_STATE_FAILED;
            } else {
                self.stats.epochs_applied += 1;
                if own.is_none() {
                    self.stats.epochs_unranged += 1;
                }
                self.fresh &= !took;
                if dcl {
                    self.own_ref = self.cross.reference(self.cfg.id);
                }
                self.report_update(epoch, t, &participants, &ranges, &gated, diag, out);
            }
        }
        if dcl && own_index.is_some() {
            self.stores.keep(epoch, t, digest_before, &self.cross, self.cfg.team.len());
        }
        let digest = self.remember_run(epoch, participants.clone());
        if own_index.is_some() {
            self.send_status(epoch, t, participants, state, digest, out);
        }
    }

    /// The bystanders by word of an epoch run on `records` (`agree`: their stores agree; else
    /// `choice`, the store chosen, if any): of the members whose word stands (`words`), those
    /// that hold the store the epoch runs on. The others' words are left out (they take that
    /// store afterwards), counted as a store mismatch; when ours is one of them, `choice`
    /// becomes the store that leaves us out, as a record of ours would be.
    fn word_bystanders(
        &mut self,
        words: &BTreeMap<PlatformId, u64>,
        records: &[StateRecord],
        agree: bool,
        choice: &mut Option<StoreChoice>,
    ) -> Vec<PlatformId> {
        let dcl = self.cfg.method == Method::Decentralized;
        let run_digest = match choice {
            Some(c) => Some(c.digest),
            None if dcl && agree => records.first().map(|r| r.digest),
            None => None,
        };
        let bystanders: Vec<PlatformId> = words.iter().filter(|&(_, d)| Some(*d) == run_digest).map(|(&p, _)| p).collect();
        if agree && run_digest.is_some() && bystanders.len() < words.len() {
            self.stats.store_mismatches += 1;
        }
        let ours_left_out = words.contains_key(&self.cfg.id) && !bystanders.contains(&self.cfg.id);
        match (choice.as_mut(), run_digest) {
            (Some(c), _) => c.bystanders = bystanders.clone(),
            (None, Some(digest)) if ours_left_out => {
                let members = records.iter().map(|r| r.snapshot.id).collect();
                *choice = Some(StoreChoice { digest, members, refreshed: Vec::new(), bystanders: bystanders.clone() });
            }
            (None, _) => {}
        }
        bystanders
    }

    /// Counts an epoch's verdict on the ranges that involve us (see [`own_ranges_verdict`]);
    /// the misfit to widen by when [`REINIT_AFTER_EPOCHS`] verdicts in a row said they all
    /// contradict us.
    fn time_to_widen(&mut self, verdict: OwnRanges) -> Option<f64> {
        match verdict {
            OwnRanges::NoneInvolveUs => None,
            OwnRanges::SomeAccepted => {
                self.contradicted_epochs = 0;
                None
            }
            OwnRanges::AllRefused { residual_m } => {
                self.contradicted_epochs += 1;
                (self.contradicted_epochs >= REINIT_AFTER_EPOCHS).then(|| {
                    self.contradicted_epochs = 0;
                    self.stats.reinitialised += 1;
                    residual_m
                })
            }
        }
    }

    /// The vetting refused our own record of the epoch at `t` (the teammates' ranges contradict
    /// where it says we are): we sit the epoch out. Every such epoch counts as one whose ranges
    /// all contradict us; when it is time, our horizontal covariance is widened at `t` by the
    /// misfit (noise added: our `Psi` goes on) and the filter replayed to the present, so that
    /// our next record is believed and the ranges bring us back.
    fn refused_own_record(&mut self, t: TimeUs, ours: StateRecord, accepted: &[StateRecord]) {
        let id = self.cfg.id;
        let mut all = accepted.to_vec();
        all.push(ours);
        let member = |p: PlatformId| all.iter().any(|r| r.snapshot.id == p);
        let ranges: Vec<RangeSample> = all
            .iter()
            .flat_map(|r| r.ranges.iter())
            .filter(|x| (x.from == id && member(x.to)) || (x.to == id && member(x.from)))
            .copied()
            .collect();
        let every: Vec<usize> = (0..ranges.len()).collect();
        let Some(residual_m) = self.time_to_widen(own_ranges_verdict(id, &all, &ranges, &every)) else { return };
        let Some(ours) = all.last() else { return };
        let n = ours.snapshot.covariance.nrows();
        let mut q = nalgebra::DMatrix::zeros(n, n);
        widen_horizontal(&mut q, &ours.snapshot.geometry.position_index, residual_m);
        if self.replay_from_epoch(t, WriteBack::Noise(&q)).is_err() {
            self.stats.epochs_failed += 1;
        }
    }

    /// Whether the team agreed to pass `epoch` over ([`Self::pass_over_after`]).
    fn agreed_to_pass_over(&self, epoch: u32) -> bool {
        self.skip_through.is_some_and(|s| epoch <= s)
    }

    /// Passes `epoch` over as the team agreed ([`Self::pass_over_after`]): nothing sent, nothing
    /// applied.
    fn pass_over(&mut self, epoch: u32) {
        let last_run = self.last_run;
        self.finish_epoch(epoch);
        self.last_run = last_run;
        self.stats.epochs_strided += 1;
    }

    /// Every node that runs `epoch` on `records` passes over the same epochs after it: the most
    /// any of them asks ([`record::skip_of`]). Not a node that runs it on its own record alone
    /// (the others left it out, or it heard none of theirs): passing over epochs by itself would
    /// only put it out of step with a team that runs them.
    fn pass_over_after(&mut self, epoch: u32, records: &[StateRecord]) {
        let joint = records.len() >= 2;
        let skip = if joint { records.iter().map(|r| record::skip_of(r.flags)).max().unwrap_or(0) } else { 0 };
        self.skip_through = (skip > 0).then(|| epoch.saturating_add(u32::from(skip)));
    }

    /// Runs `epoch` as the others did without us (we were frozen): nothing applied to our own
    /// filter (our Psi keeps accumulating), but our store takes the update they made, exactly as
    /// they computed it, when it was theirs before the epoch. Else our store falls behind, and we
    /// are left out at the next epoch and take theirs.
    fn run_bystander(&mut self, epoch: u32, ran: &[PlatformId]) {
        if !self.epochs.contains_key(&epoch) {
            return;
        }
        let words: Vec<PlatformId> = self.epochs.get(&epoch).map(|e| e.words.keys().copied().collect()).unwrap_or_default();
        let mut records = self.vetted(epoch);
        records.retain(|r| ran.contains(&r.snapshot.id));
        // The members they ran it on whose word we hold and no record ranges: bystanders.
        let bystanders: Vec<PlatformId> = words.into_iter().filter(|p| ran.contains(p) && word_stands(&records, *p)).collect();
        let prev_run = self.last_run;
        self.finish_epoch(epoch);
        self.pass_over_after(epoch, &records);
        self.stats.epochs_bystood += 1;
        let mut participants: Vec<PlatformId> = records.iter().map(|r| r.snapshot.id).collect();
        participants.extend(&bystanders);
        participants.sort_unstable();
        let ours = self.store_digest();
        let dcl = self.cfg.method == Method::Decentralized;
        let later = LaterEpoch { epoch, records, refreshed: Vec::new(), bystanders };
        if dcl && participants == ran && later.records.iter().all(|r| r.digest == ours) {
            self.bring_forward(&later);
        } else if dcl && participants == ran {
            // Our store is not theirs: one still coming is brought forward by this epoch.
            self.stores.carry_on(prev_run, later, self.wall_us, self.cfg.epoch_timeout_us);
        }
        self.remember_run(epoch, participants);
    }

    /// Applies to our store what the participants of `later` applied to theirs: the members
    /// whose blocks they forgot first, then their joint update on their records (nothing when
    /// they ranged nobody among them), every participant's reference reset. False when a record
    /// carries another store than ours or the update fails: our store is then not theirs.
    fn bring_forward(&mut self, later: &LaterEpoch) -> bool {
        let ours = self.store_digest();
        if later.records.iter().any(|r| r.digest != ours) {
            return false;
        }
        for &k in &later.refreshed {
            self.cross.forget(k);
        }
        let participants: Vec<PlatformId> = later.records.iter().map(|r| r.snapshot.id).collect();
        let measurements: Vec<CoopMeasurement> = later
            .records
            .iter()
            .flat_map(|r| r.ranges.iter().filter(|x| participants.contains(&x.to)))
            .map(CoopMeasurement::from)
            .collect();
        if measurements.is_empty() {
            return true;
        }
        let snapshots: Vec<_> = later.records.iter().map(|r| r.snapshot.clone()).collect();
        let Ok((_, bystanders)) = self.store_update(&snapshots, &measurements, true, Vec::new(), later.bystanders.clone()) else {
            return false;
        };
        let digests: Vec<u64> = later.records.iter().map(|r| r.digest).collect();
        let r = StoreRef::of_update(later.epoch, &participants, &digests);
        for p in participants.iter().filter(|p| !bystanders.contains(p)) {
            self.cross.set_reference(*p, r);
        }
        true
    }

    /// Remembers what `epoch` ran on and our store digest after it (agreement checks, resends);
    /// returns that digest.
    fn remember_run(&mut self, epoch: u32, participants: Vec<PlatformId>) -> u64 {
        let digest = self.store_digest();
        self.ran_on.push_back(RanOn { epoch, participants, digest });
        if self.ran_on.len() > EPOCHS_REMEMBERED {
            self.ran_on.pop_front();
        }
        digest
    }

    /// We were left out of `epoch` (our store is not valid for its participants, who ran it on
    /// `records`; `prev_run` was resolved before it): nothing is applied, and we ask them for
    /// their store after it, unless a store we asked for earlier is still coming: that one is
    /// brought forward by this epoch when it comes.
    fn leave_out(
        &mut self,
        epoch: u32,
        t: TimeUs,
        c: &StoreChoice,
        prev_run: Option<u32>,
        records: &[StateRecord],
        out: &mut Vec<NodeOutput>,
    ) {
        self.stats.epochs_excluded += 1;
        // The epoch's records are copied only where they are kept or replayed.
        let later =
            || LaterEpoch { epoch, records: records.to_vec(), refreshed: c.refreshed.clone(), bystanders: c.bystanders.clone() };
        if self.cfg.method == Method::Decentralized && self.store_digest() == c.digest && self.bring_forward(&later()) {
            // The store we took after our record went (which carried the one before): brought
            // forward by this epoch as its participants brought theirs, we are back at the next.
            self.stats.store_epochs_replayed += 1;
            self.remember_run(epoch, c.members.clone());
            return;
        }
        if self.stores.wanting() && self.stores.carry_on(prev_run, later(), self.wall_us, self.cfg.epoch_timeout_us) {
            return;
        }
        let request = StoreRequest { epoch, t, digest_before: c.digest, members: c.members.clone() };
        self.stores.want(request, self.wall_us);
        self.send_status(epoch, t, c.members.clone(), EpochState::COOPLOC_EPOCH_STATE_STORE_WANTED, c.digest, out);
    }

    /// Sends our store after `epoch` to `to`, a teammate that asked (as answerer `rank`): only
    /// one that did not run that epoch with us, at most once per retry interval (in all; paced,
    /// per store, [`store_sync`]'s few at once): a request is a small message and a store a
    /// large one, so nobody can make us flood the network. Paced to [`NodeConfig::store_bps`].
    fn send_store(&mut self, to: PlatformId, epoch: u32, digest_before: u64, rank: usize, out: &mut Vec<NodeOutput>) {
        let ran_with_us = self.ran_on.iter().any(|r| r.epoch == epoch && r.participants.contains(&to));
        let retry = self.retry_us();
        // at most one radio frame's bytes per fragment
        let per_interval = self.cfg.store_bps.saturating_mul(retry) / 1_000_000 / MAX_RADIO_FRAME as u64;
        let per_answer = if self.cfg.store_bps == 0 { 0 } else { per_interval.max(1) as usize };
        let me = store_sync::Answerer { id: self.cfg.id, rank, per_answer };
        let asked = store_sync::Asked { to, epoch, digest_before, ran_with_us };
        let Some(frags) = self.stores.answer(asked, me, self.wall_us, retry) else { return };
        for f in &frags {
            if let Ok(m) = wire::fragment_to_message(f) {
                out.push(NodeOutput::ToPeers(m));
            }
        }
        self.stores.sent(epoch, self.wall_us, EPOCHS_REMEMBERED as u32);
        self.stats.stores_sent += 1;
        self.stats.store_fragments_sent += frags.len() as u64;
    }

    /// A store snapshot arrived: adopted if it is the one we asked for and nothing was resolved
    /// since but the epochs run without us; brought forward by those epochs first, and then
    /// valid for us (refused if an epoch does not follow, or it is not: the want ends either way,
    /// and the next epoch we are left out of asks afresh).
    fn receive_store(&mut self, from: PlatformId, snap: record::StoreSnapshot) {
        let Some(later) = self.stores.offered(from, &snap, self.last_run) else {
            self.stats.stores_refused += 1;
            return;
        };
        let ours = std::mem::replace(&mut self.cross, snap.store);
        let forward = later.iter().all(|l| self.bring_forward(l));
        let valid = match self.own_ref {
            Some(r) => self.cross.reference(self.cfg.id) == Some(r),
            None => self.cross.reference(self.cfg.id).is_none() && self.cfg.independent_start,
        };
        if !(forward && valid) {
            self.cross = ours;
            self.stats.stores_refused += 1;
            return;
        }
        self.stats.stores_adopted += 1;
        self.stats.store_epochs_replayed += later.len() as u64;
    }

    /// The method's joint update: exact when the stores agree, else (or when the exact one
    /// fails) the bound. Returns our correction, the diagnostics and the gated measurements.
    fn joint_update(
        &mut self,
        snapshots: &[crate::estimation::Snapshot],
        measurements: &[CoopMeasurement],
        agree: bool,
        independent: Vec<PlatformId>,
        words: Vec<PlatformId>,
    ) -> Result<JointResult, EstimationError> {
        let own = |corrections: Vec<Correction>, id| corrections.into_iter().find(|c| c.id == id);
        let id = self.cfg.id;
        let unknown = EstimationError::UnknownPlatform(id);
        match self.cfg.method {
            Method::NoPropagation => {
                let opts = UpdateOptions { gate_chi2: self.gate, ..UpdateOptions::new(CrossMode::Ignore) };
                let o = cooperative_update_with(&mut CrossCovariances::new(), snapshots, measurements, &opts)?;
                let c = own(o.corrections, id).ok_or(unknown)?;
                Ok(JointResult {
                    own: Some(c),
                    share: None,
                    bystanders: Vec::new(),
                    diagnostics: Some(o.diagnostics),
                    gated: o.gated,
                })
            }
            Method::Decentralized => {
                let (o, bystanders) = self.store_update(snapshots, measurements, agree, independent, words)?;
                let share = o.bystanders.iter().find(|s| s.id == id).cloned();
                let c = own(o.corrections, id);
                if c.is_none() && !bystanders.contains(&id) {
                    return Err(unknown);
                }
                Ok(JointResult { own: c, share, bystanders, diagnostics: Some(o.diagnostics), gated: o.gated })
            }
            Method::CovarianceIntersection => {
                let c = own(ci_update(snapshots, measurements)?, id).ok_or(unknown)?;
                Ok(JointResult { own: Some(c), share: None, bystanders: Vec::new(), diagnostics: None, gated: Vec::new() })
            }
            Method::DeadReckoning | Method::Centralized => Err(EstimationError::NotApplicable("no joint update")),
        }
    }

    /// The decentralized joint update on our store: exact when the stores agree (retried with
    /// the bound if it fails), else the bound. The exact one runs among the records' platforms
    /// that the ranges involve, each other one a bystander that takes its share
    /// ([`crate::estimation::split_ranged`]; returned, with the outcome): the same result as
    /// with every record, without the bystanders' states in the joint problem. The members
    /// whose word stands (`words`: no record, the same store) are bystanders too. The bound
    /// runs on every record.
    fn store_update(
        &mut self,
        snapshots: &[crate::estimation::Snapshot],
        measurements: &[CoopMeasurement],
        agree: bool,
        independent: Vec<PlatformId>,
        words: Vec<PlatformId>,
    ) -> Result<(crate::estimation::EventOutcome, Vec<PlatformId>), EstimationError> {
        let exact = UpdateOptions { gate_chi2: self.gate, ..UpdateOptions::new(CrossMode::Propagate) };
        let bound = UpdateOptions { prior: JointPrior::Bound { independent, scope: BoundScope::Position }, ..exact.clone() };
        if agree {
            let (ranged, mut bystanders) = crate::estimation::split_ranged(snapshots, measurements);
            bystanders.extend(words);
            bystanders.sort_unstable();
            let opts = UpdateOptions { bystanders, ..exact };
            if let Ok(o) = cooperative_update_with(&mut self.cross, &ranged, measurements, &opts) {
                return Ok((o, opts.bystanders));
            }
        }
        let o = cooperative_update_with(&mut self.cross, snapshots, measurements, &bound)?;
        if !o.weights.is_empty() {
            self.stats.heals += 1;
        }
        Ok((o, Vec::new()))
    }

    #[allow(clippy::too_many_arguments)]
    fn report_update(
        &mut self,
        epoch: u32,
        t: TimeUs,
        participants: &[PlatformId],
        ranges: &[RangeSample],
        gated: &[usize],
        diag: Option<crate::estimation::UpdateDiagnostics>,
        out: &mut Vec<NodeOutput>,
    ) {
        let used: Vec<&RangeSample> = ranges.iter().enumerate().filter(|(i, _)| !gated.contains(i)).map(|(_, r)| r).collect();
        let nis = diag.as_ref().map_or(f64::NAN, |d| d.nis);
        self.last_event = Some(LastEvent { epoch, nis, participants: participants.len() as u8, ranges: used.len() as u8 });
        out.push(NodeOutput::Update(Box::new(CoopUpdateRecord {
            vehicle: self.cfg.id,
            epoch,
            t_us: t.0,
            participants: participants.to_vec(),
            ranges: used.iter().map(|r| RangeRecord { from: r.from, to: r.to, range_m: r.range_m, sigma_m: r.sigma_m }).collect(),
            innovation: diag.as_ref().map(|d| d.innovation.iter().copied().collect()).unwrap_or_default(),
            innovation_sigma: diag
                .as_ref()
                .map(|d| d.innovation_cov.diagonal().iter().map(|v| v.sqrt()).collect())
                .unwrap_or_default(),
            nis,
            nis_dof: used.len() as u32,
            nees: None,
            nees_dof: None,
        })));
        out.push(NodeOutput::Estimate(self.estimate()));
    }

    /// Restores the checkpoint at `t`, writes back the correction, and replays the inputs after
    /// `t`, rebuilding the checkpoints on the way.
    fn replay_from_epoch(&mut self, t: TimeUs, write_back: WriteBack<'_>) -> Result<(), EstimationError> {
        let replay = self.rewind.replay_from_checkpoint_at(t, write_back);
        self.stats.replayed_inputs += replay.samples;
        // (none: every local measurement behind the filter has been judged already)
        self.stats.odometer_rejected += replay.refused.odometer;
        self.stats.fixes_rejected += replay.refused.fixes;
        replay.result
    }

    /// The vehicle's stream has ended: closes the open instant and broadcasts what is due
    /// (deliver the result to the peers; epochs then run as their records arrive, or at
    /// [`NodeCore::run_pending`]).
    pub fn end_of_input(&mut self) -> Vec<NodeOutput> {
        let mut out = Vec::new();
        self.rewind.end();
        self.advance(&mut out);
        out
    }

    /// Runs every epoch still open, in order, with the records that have arrived (the end of a
    /// run: nothing more will come).
    pub fn run_pending(&mut self) -> Vec<NodeOutput> {
        let mut out = Vec::new();
        while let Some((&epoch, e)) = self.epochs.first_key_value() {
            if e.broadcast_at.is_none() && self.agreed_to_pass_over(epoch) {
                self.pass_over(epoch);
            } else if e.broadcast_at.is_none() && self.checkpoint_at(e.t).is_some() {
                self.broadcast(epoch, e.t, &mut out);
            } else if e.broadcast_at.is_some() {
                let complete = self.cfg.team.iter().all(|p| self.absent.contains(p) || e.records.contains_key(p));
                self.run_epoch(epoch, !complete, &mut out);
            } else {
                self.stats.epochs_skipped += 1;
                self.finish_epoch(epoch);
            }
        }
        out
    }

    /// The node's current navigation solution (what it feeds back to its autopilot).
    pub fn navigation(&self) -> wire::Navigation {
        let f = &self.rewind.filter;
        let cov = f.output_covariances();
        wire::Navigation {
            t: f.time(),
            position_ned_m: f.position_ned_m(),
            velocity_ned_m_s: f.velocity_ned_m_s(),
            attitude_frd_to_ned: f.attitude(),
            pose_covariance: cov.pose,
            velocity_covariance_ned: cov.velocity_ned,
        }
    }

    /// The estimate report of the node's current state.
    pub fn estimate(&self) -> wire::EstimateReport {
        let f = &self.rewind.filter;
        let cov = f.output_covariances();
        let LastEvent { epoch, nis, participants, ranges } =
            self.last_event.unwrap_or(LastEvent { epoch: 0, nis: f64::NAN, participants: 0, ranges: 0 });
        wire::EstimateReport {
            platform: self.cfg.id,
            t: f.time(),
            epoch,
            method: self.cfg.method,
            position_ned_m: f.position_ned_m(),
            velocity_ned_m_s: f.velocity_ned_m_s(),
            yaw_rad: f.yaw_rad(),
            position_covariance_m2: cov.position(),
            yaw_variance_rad2: cov.yaw_variance(),
            nis,
            participants,
            ranges,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::estimation::ins::InsState;
    use nalgebra::{UnitQuaternion, Vector3};

    fn config(id: PlatformId, team: Vec<PlatformId>) -> NodeConfig {
        let model = NavModel::Ins { config: InsConfig::default(), initial_sigma: InsInitialSigma::for_tests() };
        NodeConfig::for_model(id, Method::Decentralized, model, Encoding::F64, team)
    }

    fn start() -> NavState {
        NavState::Ins(InsState {
            pos_ned_m: Vector3::zeros(),
            vel_ned_m_s: Vector3::zeros(),
            att_frd_to_ned: UnitQuaternion::identity(),
            accel_bias_frd_m_s2: Vector3::zeros(),
            gyro_bias_frd_rad_s: Vector3::zeros(),
            odometer_scale_error: 0.0,
        })
    }

    fn refused(cfg: NodeConfig) -> NodeConfigError {
        NodeCore::new(cfg, TimeUs(0), start()).expect_err("refused")
    }

    /// The wall clock at `t_us` (not at the `first` sample) and an IMU sample at rest then.
    fn step_at_rest(core: &mut NodeCore, t_us: u64, first: bool) -> Vec<NodeOutput> {
        let s = ImuSample {
            t: TimeUs(t_us),
            specific_force_frd_m_s2: Vector3::new(0.0, 0.0, -9.8),
            angular_rate_frd_rad_s: Vector3::zeros(),
        };
        let mut out = if first { Vec::new() } else { core.poll(t_us) };
        out.extend(core.handle(NodeInput::Imu(s)));
        out
    }

    /// Notes, per epoch, when (s) the first fragment of our record among `out` went out at `t_us`.
    fn first_fragments(out: Vec<NodeOutput>, t_us: u64, sent: &mut BTreeMap<u32, f64>) {
        for o in out {
            if let NodeOutput::ToPeers(MavMessage::COOPLOC_STATE_FRAGMENT(f)) = o {
                sent.entry(f.epoch).or_insert(t_us as f64 / 1e6);
            }
        }
    }

    /// Teammate `from` announces `epoch` (at `epoch` seconds) in `state`, holding `participants`.
    fn announce(
        core: &mut NodeCore,
        from: PlatformId,
        epoch: u32,
        participants: Vec<PlatformId>,
        state: EpochState,
    ) -> Vec<NodeOutput> {
        let a = wire::EpochAnnouncement {
            epoch,
            t: TimeUs(u64::from(epoch) * 1_000_000),
            announcer: from,
            participants,
            state,
            digest: 0,
            incomplete: Vec::new(),
        };
        core.handle(NodeInput::Peer { from, msg: Box::new(wire::epoch_to_message(&a).unwrap()) })
    }

    #[test]
    fn a_core_refuses_a_configuration_that_cannot_work_and_says_why() {
        assert!(NodeCore::new(config(2, vec![3, 1, 2]), TimeUs(0), start()).is_ok());
        assert!(matches!(
            refused(NodeConfig { method: Method::Centralized, ..config(1, vec![1, 2]) }),
            NodeConfigError::Method(_)
        ));
        for team in [vec![2, 3], vec![1, 2, 2], (1..=300).collect()] {
            assert!(matches!(refused(config(1, team)), NodeConfigError::Team { id: 1, .. }));
        }
        let timing = refused(NodeConfig { retry_us: 2_000_000, ..config(1, vec![1, 2]) });
        assert!(timing.to_string().contains("2000000 us"), "{timing}");
        assert!(matches!(refused(NodeConfig { retry_us: 0, ..config(1, vec![1, 2]) }), NodeConfigError::Timing { .. }));
        assert!(matches!(
            refused(NodeConfig { range_grace_us: 4_000_000, ..config(1, vec![1, 2]) }),
            NodeConfigError::Grace { .. }
        ));
        for p in [1.0, -0.1, f64::NAN] {
            assert!(matches!(refused(NodeConfig { gate_probability: p, ..config(1, vec![1, 2]) }), NodeConfigError::Gate(_)));
        }
    }

    /// An own range that names an epoch the node knows at a neighbouring grid instant (two
    /// nodes' clock mappings put one ranging on either side of the middle between two grid
    /// instants) is taken at the known instant when the node has a range grid and a signed team;
    /// without a grid, further than a grid step, or on an unsigned team (the known instant may
    /// be a forger's), it is refused as before, and a teammate's claim is never moved.
    #[test]
    fn an_own_range_a_grid_step_from_its_known_epoch_is_taken_at_the_known_instant() {
        let range = |t_us: u64| NodeInput::OwnRange {
            epoch: 5,
            range: crate::estimation::RangeSample { t: TimeUs(t_us), from: 1, to: 2, range_m: 10.0, sigma_m: 0.1 },
        };
        for (snap_us, own_us, signed, taken) in [
            (100_000, 5_100_000, true, true),
            (100_000, 4_900_000, true, true),
            (0, 5_100_000, true, false),
            (100_000, 5_200_000, true, false),
            (100_000, 5_100_000, false, false),
        ] {
            let cfg = NodeConfig { range_snap_us: snap_us, authenticated_peers: signed, ..config(1, vec![1, 2, 3]) };
            let mut core = NodeCore::new(cfg, TimeUs(0), start()).unwrap();
            step_at_rest(&mut core, 10_000, true);
            // Teammate 2 names epoch 5 at 5 s first.
            announce(&mut core, 2, 5, vec![2], EpochState::COOPLOC_EPOCH_STATE_COLLECTING);
            assert_eq!(core.epochs.get(&5).map(|e| e.t), Some(TimeUs(5_000_000)));
            core.handle(range(own_us));
            let e = core.epochs.get(&5).unwrap();
            let case = format!("grid {snap_us} us, own range at {own_us} us, signed {signed}");
            assert_eq!(e.t, TimeUs(5_000_000), "the epoch keeps its instant: {case}");
            if taken {
                assert_eq!(e.own_ranges.iter().map(|r| r.t).collect::<Vec<_>>(), vec![TimeUs(5_000_000)], "{case}");
                assert_eq!((core.stats.ranges_restamped, core.stats.epochs_misnamed), (1, 0), "{case}");
            } else {
                assert!(e.own_ranges.is_empty(), "{case}");
                assert_eq!((core.stats.ranges_restamped, core.stats.epochs_misnamed), (0, 1), "{case}");
            }
        }
        // A teammate's claim at a neighbouring instant is refused, grid or not.
        let cfg = NodeConfig { range_snap_us: 100_000, authenticated_peers: true, ..config(1, vec![1, 2, 3]) };
        let mut core = NodeCore::new(cfg, TimeUs(0), start()).unwrap();
        step_at_rest(&mut core, 10_000, true);
        core.handle(range(5_000_000));
        let a = wire::EpochAnnouncement {
            epoch: 5,
            t: TimeUs(5_100_000),
            announcer: 3,
            participants: vec![3],
            state: EpochState::COOPLOC_EPOCH_STATE_COLLECTING,
            digest: 0,
            incomplete: Vec::new(),
        };
        core.handle(NodeInput::Peer { from: 3, msg: Box::new(wire::epoch_to_message(&a).unwrap()) });
        assert_eq!((core.epochs[&5].t, core.stats.epochs_misnamed, core.stats.ranges_restamped), (TimeUs(5_000_000), 1, 0));
    }

    /// What a node follows at a timeout ([`NodeCore::advance`]): the largest set a peer reported
    /// it ran the epoch on, the peer among them, two members at least (a member back from a leave
    /// reports the epoch it ran alone, `[4]`, and a first version that followed the first report
    /// led ten nodes of a sixteen-member team to run on that). And a member found absent is
    /// waited for again once it speaks of a recent epoch.
    #[test]
    fn a_node_follows_the_largest_set_a_peer_ran_and_waits_again_for_a_member_that_speaks() {
        let mut core = NodeCore::new(config(1, vec![1, 2, 3, 4]), TimeUs(0), start()).unwrap();
        let say = |core: &mut NodeCore, from: PlatformId, epoch: u32, participants: Vec<PlatformId>, state: EpochState| {
            announce(core, from, epoch, participants, state);
        };
        let ran = |core: &NodeCore| core.epochs.get(&5).and_then(|e| e.peer_ran.clone());
        // One IMU sample: the vehicle's clock is known, epochs can become known.
        let rest = ImuSample {
            t: TimeUs(10_000),
            specific_force_frd_m_s2: Vector3::new(0.0, 0.0, -9.8),
            angular_rate_frd_rad_s: Vector3::zeros(),
        };
        core.handle(NodeInput::Imu(rest));
        say(&mut core, 2, 5, vec![2], EpochState::COOPLOC_EPOCH_STATE_COLLECTING);
        assert!(core.epochs.contains_key(&5), "the epoch became known");
        say(&mut core, 4, 5, vec![4], EpochState::COOPLOC_EPOCH_STATE_APPLIED);
        assert_eq!(ran(&core), None, "a lone run is nothing to follow");
        say(&mut core, 2, 5, vec![2, 3], EpochState::COOPLOC_EPOCH_STATE_PARTIAL);
        assert_eq!(ran(&core), Some(vec![2, 3]));
        say(&mut core, 3, 5, vec![1, 2, 4], EpochState::COOPLOC_EPOCH_STATE_APPLIED);
        assert_eq!(ran(&core), Some(vec![2, 3]), "a set without its reporter");
        say(&mut core, 3, 5, vec![2, 3, 4], EpochState::COOPLOC_EPOCH_STATE_COLLECTING);
        assert_eq!(ran(&core), Some(vec![2, 3]), "what a peer holds is not what it ran");
        say(&mut core, 4, 5, vec![1, 2, 3, 4], EpochState::COOPLOC_EPOCH_STATE_APPLIED);
        assert_eq!(ran(&core), Some(vec![1, 2, 3, 4]), "the largest");
        say(&mut core, 2, 5, vec![2, 3], EpochState::COOPLOC_EPOCH_STATE_APPLIED);
        assert_eq!(ran(&core), Some(vec![1, 2, 3, 4]), "a smaller set does not replace it");

        core.absent.extend([3, 4]);
        core.last_applied = Some((20, TimeUs(20_000_000)));
        say(&mut core, 3, 10, vec![3], EpochState::COOPLOC_EPOCH_STATE_STORE_WANTED);
        assert!(core.absent.contains(&3), "an epoch long over says nothing of now");
        say(&mut core, 3, 19, vec![1, 2], EpochState::COOPLOC_EPOCH_STATE_STORE_WANTED);
        say(&mut core, 2, 21, vec![2, 4], EpochState::COOPLOC_EPOCH_STATE_COLLECTING);
        assert_eq!(core.absent().collect::<Vec<_>>(), vec![4], "3 spoke of a recent epoch; 4 did not speak");
    }

    /// While it waits, a node says which fragments it holds of a record still incomplete (its
    /// COLLECTING status as COOPLOC_EPOCH_SET), so that the sender resends only the rest; a
    /// record it holds whole is a participant, not an incomplete one.
    #[test]
    fn a_waiting_node_says_which_fragments_it_holds_of_an_incomplete_record() {
        let mut core = NodeCore::new(config(1, vec![1, 2, 3]), TimeUs(0), start()).unwrap();
        let record: Vec<u8> = (0..3000u32).map(|i| (i * 7 % 251) as u8).collect();
        let frags = crate::protocol::fragment::fragment(2, 5, 5_000_000, &record).unwrap();
        assert!(frags.len() > 8);
        let mut statuses = Vec::new();
        for k in 1..=600u64 {
            let t = k * 10_000;
            let mut out = step_at_rest(&mut core, t, k == 1);
            if t == 5_000_000 {
                out.extend(announce(&mut core, 3, 5, vec![3], EpochState::COOPLOC_EPOCH_STATE_COLLECTING));
                for i in [0, 2, 8] {
                    let msg = wire::fragment_to_message(&frags[i]).unwrap();
                    out.extend(core.handle(NodeInput::Peer { from: 2, msg: Box::new(msg) }));
                }
            }
            statuses.extend(out.iter().filter_map(|o| match o {
                NodeOutput::ToPeers(m) => wire::epoch_of(m).and_then(Result::ok).filter(|a| a.epoch == 5),
                _ => None,
            }));
        }
        let asked: Vec<_> = statuses.iter().filter(|a| a.state == EpochState::COOPLOC_EPOCH_STATE_COLLECTING).collect();
        assert!(!asked.is_empty(), "the node asked for what it lacks: {statuses:?}");
        for a in asked {
            assert_eq!(a.participants, vec![1], "only our own record is whole");
            assert_eq!(a.incomplete, vec![wire::HeldFragments { platform: 2, held: 0b1_0000_0101 }]);
        }
    }

    /// With airtime slots a teammate's first request for the whole of our record waits for a
    /// second one (on a shared channel it may have been sent before our record reached it, and
    /// delivered after it); a request that names the fragments held is answered at once, with
    /// the fragments missing; and a request also counts as busy air for our own asking.
    #[test]
    fn with_slots_a_request_for_a_whole_record_is_answered_when_it_comes_again() {
        let slot = 200_000;
        let cfg = NodeConfig { epoch_period_us: Some(1_000_000), slot_us: slot, ..config(1, vec![1, 2, 3]) };
        let mut core = NodeCore::new(cfg, TimeUs(0), start()).unwrap();
        core.last_applied = Some((4, TimeUs(4_000_000)));
        let mut count = 0usize;
        for k in 1..=560u64 {
            let out = step_at_rest(&mut core, k * 10_000, k == 1);
            count += out
                .iter()
                .filter(|o| matches!(o, NodeOutput::ToPeers(MavMessage::COOPLOC_STATE_FRAGMENT(f)) if f.epoch == 5))
                .count();
        }
        assert!(count > 2, "our record of epoch 5 went out in our slot: {count} fragments");
        let ask = |core: &mut NodeCore, from: PlatformId, incomplete: Vec<wire::HeldFragments>| -> Vec<u8> {
            let a = wire::EpochAnnouncement {
                epoch: 5,
                t: TimeUs(5_000_000),
                announcer: from,
                participants: vec![from],
                state: EpochState::COOPLOC_EPOCH_STATE_COLLECTING,
                digest: 0,
                incomplete,
            };
            let out = core.handle(NodeInput::Peer { from, msg: Box::new(wire::epoch_to_message(&a).unwrap()) });
            assert_eq!(core.channel_busy_at, core.wall_us);
            out.iter()
                .filter_map(|o| match o {
                    NodeOutput::ToPeers(MavMessage::COOPLOC_STATE_FRAGMENT(f)) if f.epoch == 5 => Some(f.frag_index),
                    _ => None,
                })
                .collect()
        };
        assert_eq!(ask(&mut core, 2, vec![]), Vec::<u8>::new(), "the first request for the whole record waits");
        assert_eq!(core.stats.requests_deferred, 1);
        let all_but_0 = ((1u32 << count) - 1) & !1;
        assert_eq!(ask(&mut core, 3, vec![wire::HeldFragments { platform: 1, held: all_but_0 }]), vec![0]);
        assert_eq!(ask(&mut core, 2, vec![]), (1..count as u8).collect::<Vec<_>>(), "asked again: the rest of it");
        assert_eq!((core.stats.requests_deferred, core.stats.resends_partial), (1, 2), "{:?}", core.stats);
    }

    /// A periodic schedule and airtime slots ([`NodeConfig::epoch_period_us`],
    /// [`NodeConfig::slot_us`]): a node learns the next epoch as its filter passes the last one,
    /// from nothing but the schedule; it broadcasts in its slot (grace plus its place in the
    /// team times the slot), and asks for missing records once the filter has passed the plan's
    /// end by a quarter slot; having broadcast late (after its slot), only once every slot's air
    /// time and one more have passed since.
    #[test]
    fn a_scheduled_node_knows_the_next_epoch_and_keeps_to_its_slot() {
        let slot = 200_000;
        let slotted = |id: PlatformId, period: Option<u64>| NodeConfig {
            epoch_period_us: period,
            slot_us: slot,
            ..config(id, vec![1, 2, 3])
        };
        let say = |core: &mut NodeCore, epoch: u32| announce(core, 2, epoch, vec![2], EpochState::COOPLOC_EPOCH_STATE_COLLECTING);
        // IMU samples every 10 ms up to 7 s, the wall clock running with them; a teammate says
        // epoch `said` when the filter is at `said_at`: when the node broadcast epoch 5, and when
        // it first asked for the records it lacks
        let run = |core: &mut NodeCore, said: u32, said_at: u64| -> (Option<f64>, Option<f64>) {
            let (mut sent_at, mut asked_at) = (None, None);
            core.last_applied = Some((said - 1, TimeUs(u64::from(said - 1) * 1_000_000)));
            for k in 1..=700u64 {
                let t = k * 10_000;
                let mut out = step_at_rest(core, t, k == 1);
                if t == said_at {
                    out.extend(say(core, said));
                }
                if t == 3_990_000 && said == 4 {
                    assert!(!core.epochs.contains_key(&5), "not before the filter passes epoch 4");
                }
                if t == 4_010_000 && said == 4 {
                    assert_eq!(core.epochs.get(&5).map(|e| e.t), Some(TimeUs(5_000_000)), "epoch 5 from the schedule");
                    // epoch 4 resolved (without the others, who are not here): what matters is 5
                    core.epochs.remove(&4);
                    core.last_applied = Some((4, TimeUs(4_000_000)));
                }
                for o in out {
                    match o {
                        NodeOutput::ToPeers(MavMessage::COOPLOC_STATE_FRAGMENT(f)) if f.epoch == 5 => {
                            sent_at.get_or_insert(t as f64 / 1e6);
                        }
                        NodeOutput::ToPeers(m) if wire::epoch_of(&m).is_some() => {
                            let a = wire::epoch_of(&m).unwrap().unwrap();
                            if a.epoch == 5 && a.state == EpochState::COOPLOC_EPOCH_STATE_COLLECTING {
                                asked_at.get_or_insert(t as f64 / 1e6);
                            }
                        }
                        _ => {}
                    }
                }
            }
            (sent_at, asked_at)
        };
        // told epoch 4 early, the rest from the schedule (node 3's slot starts at 5.5 s, the plan
        // ends at 5.7 s)
        for (id, broadcast_s, first_ask_s) in [(1, 5.1, 5.75), (3, 5.5, 5.75)] {
            let mut core = NodeCore::new(slotted(id, Some(1_000_000)), TimeUs(0), start()).unwrap();
            assert_eq!(run(&mut core, 4, 20_000), (Some(broadcast_s), Some(first_ask_s)), "node {id}");
            assert!(core.stats.epochs_scheduled >= 2, "epochs 5 and 6: {}", core.stats.epochs_scheduled);
        }
        // without the schedule, told epoch 5 only at 5.3 s, after node 1's slot: it broadcasts at
        // once and waits for every slot's air time and one more
        let mut core = NodeCore::new(slotted(1, None), TimeUs(0), start()).unwrap();
        assert_eq!(run(&mut core, 5, 5_300_000), (Some(5.3), Some(6.1)));
        assert_eq!(core.stats.epochs_scheduled, 0);
        // the plan must fit in the period, and the period must not be shorter than the
        // fastest epoch rate allows
        for (period, slot) in [(1_000_000, 300_000), (5_000, 0)] {
            let cfg = NodeConfig { epoch_period_us: Some(period), slot_us: slot, ..config(1, vec![1, 2, 3]) };
            let e = refused(cfg);
            assert!(matches!(e, NodeConfigError::Schedule { .. }) && e.to_string().contains("slots"), "{e}");
        }
    }

    /// The epochs the team passes over are those the records an epoch runs on ask for: the
    /// record of a member left out of it (its store not valid for the others), which some
    /// nodes hold and others not, does not count. (In a 16-member team paced at 10% loss, a
    /// left-out member waiting for its store asked; the nodes that held its record passed two
    /// epochs over and four that did not ran the first: the team split, and healed.)
    #[test]
    fn a_left_out_members_request_to_pass_epochs_over_does_not_count() {
        use crate::estimation::{Geometry, Snapshot};
        let record = |id: PlatformId, digest: u64, skip: u8| StateRecord {
            snapshot: Snapshot {
                id,
                geometry: Geometry {
                    position_ned_m: Vector3::new(f64::from(id) * 10.0, 0.0, 0.0),
                    position_index: [Some(0), Some(1), None],
                    heading: None,
                },
                covariance: nalgebra::DMatrix::identity(3, 3),
                psi: nalgebra::DMatrix::identity(3, 3),
            },
            digest,
            own_ref: StoreRef::fresh(0),
            refs: Vec::new(),
            flags: record::with_skip(FLAG_FRESH, skip),
            ranges: Vec::new(),
        };
        let run = |third_digest_differs: bool| {
            let mut core = NodeCore::new(config(1, vec![1, 2, 3]), TimeUs(0), start()).unwrap();
            let ours = core.store_digest();
            let mut e = Epoch::new(TimeUs(5_000_000));
            e.broadcast_at = Some(0);
            let third = if third_digest_differs { ours ^ 1 } else { ours };
            e.records = BTreeMap::from([(1, record(1, ours, 0)), (2, record(2, ours, 0)), (3, record(3, third, 2))]);
            core.epochs.insert(5, e);
            let mut out = Vec::new();
            core.run_epoch(5, false, &mut out);
            (core.stats.store_mismatches, core.stats.epochs_excluded, core.skip_through)
        };
        assert_eq!(run(false), (0, 0, Some(7)), "3 runs the epoch with us: its request counts");
        assert_eq!(run(true), (1, 0, None), "3 is left out (we are not): its request does not count");
    }

    /// Epochs the team agreed to pass over ([`NodeCore::pass_over_after`]: a record of epoch 4
    /// asked for two) are no gap a later epoch waits for, and nothing is sent for them. Node 3,
    /// which measures no range, learns every epoch from its teammates: told epoch 7 after
    /// epoch 4, it would otherwise wait an epoch timeout for epochs 5 and 6, which nobody will
    /// ever say, at every stride (what a first version of the rule did: `cooploc faults` with
    /// 50% loss and 0-1 s of latency left 2-3 runs in 20 unrecovered). Told epoch 5 after all
    /// (a teammate that has not heard of the stride), it passes it over, and the last epoch it
    /// ran stays the one a store it asked for is checked against.
    #[test]
    fn epochs_the_team_passes_over_are_no_gap_and_nothing_is_sent_for_them() {
        let say = |core: &mut NodeCore, epoch: u32| announce(core, 2, epoch, vec![2], EpochState::COOPLOC_EPOCH_STATE_COLLECTING);
        // IMU samples every 10 ms, the wall clock running with them; epoch 5 said at 5.2 s
        // (when `say_five`), epoch 7 at 7.2 s, until `until_s`: the epochs node 3 sent a fragment
        // of, each with when it first did
        let run = |core: &mut NodeCore, say_five: bool, until_s: u64| -> BTreeMap<u32, f64> {
            let mut sent = BTreeMap::new();
            core.last_applied = Some((4, TimeUs(4_000_000)));
            core.last_run = Some(4);
            for k in 1..=until_s * 100 {
                let t = k * 10_000;
                let mut out = step_at_rest(core, t, k == 1);
                if t == 5_200_000 && say_five {
                    out.extend(say(core, 5));
                }
                if t == 7_200_000 {
                    out.extend(say(core, 7));
                }
                first_fragments(out, t, &mut sent);
            }
            sent
        };
        // without the agreement, epoch 7 waits the 2 s timeout for 5 and 6
        let mut alone = NodeCore::new(config(3, vec![1, 2, 3]), TimeUs(0), start()).unwrap();
        assert_eq!(run(&mut alone, false, 12), BTreeMap::from([(7, 9.2)]));
        // with it, at once, and nothing for the epochs passed over
        let mut agreed = NodeCore::new(config(3, vec![1, 2, 3]), TimeUs(0), start()).unwrap();
        agreed.skip_through = Some(6);
        assert_eq!(run(&mut agreed, false, 12), BTreeMap::from([(7, 7.2)]));
        assert_eq!(agreed.stats.epochs_strided, 0, "5 and 6 never became known");
        let mut told = NodeCore::new(config(3, vec![1, 2, 3]), TimeUs(0), start()).unwrap();
        told.skip_through = Some(6);
        let sent = run(&mut told, true, 8);
        assert_eq!(sent, BTreeMap::from([(7, 7.2)]), "5 passed over, 7 at once");
        assert_eq!(told.stats.epochs_strided, 1);
        assert!(!told.epochs.contains_key(&5));
        // epoch 7 is still open (nobody answers: it times out at 9.2 s): the last epoch run is
        // still 4
        assert_eq!(told.last_run, Some(4));
    }

    /// A node in step (it resolved an epoch within the last timeout) that hears of an epoch
    /// more than [`RECENT_EPOCHS`] past the last one it resolved waits for the ones in between
    /// (its team is behind the vehicles, and their echoes were lost), as it does for a narrower
    /// gap: broadcasting at once would leave the team waiting a timeout for its records of
    /// those, which it could then no longer send (`cooploc faults --only "loss 50%, packed,
    /// 5x"`: 85 partial epochs and 2 diverged runs in 20, none with the rule). After a silence
    /// it does not wait once it has heard its team (here the report that names epoch 8): those
    /// epochs are over.
    #[test]
    fn a_node_in_step_waits_for_the_epochs_before_a_later_one_it_heard_of() {
        // node 3 resolved epoch 4 (t = 4 s) at wall time `resolved_s`; IMU samples every 10 ms,
        // the wall clock running with them; epoch 8 said at 8.2 s, epoch 5 at 8.4 s when
        // `say_five` (still within the 4 s of history a record can be made from): the epochs
        // node 3 sent a fragment of, each with when it first did
        let run = |resolved_s: Option<u64>, say_five: bool| -> BTreeMap<u32, f64> {
            let mut core = NodeCore::new(config(3, vec![1, 2, 3]), TimeUs(0), start()).unwrap();
            let mut sent = BTreeMap::new();
            core.last_applied = Some((4, TimeUs(4_000_000)));
            core.last_run = Some(4);
            core.resolved_at = resolved_s.map(|s| s * 1_000_000);
            for k in 1..=1_200 {
                let t = k * 10_000;
                let mut out = step_at_rest(&mut core, t, k == 1);
                for (at, epoch) in [(8_200_000, 8), (8_400_000, 5)] {
                    if t == at && (epoch != 5 || say_five) {
                        out.extend(announce(&mut core, 2, epoch, vec![2], EpochState::COOPLOC_EPOCH_STATE_COLLECTING));
                    }
                }
                first_fragments(out, t, &mut sent);
            }
            sent
        };
        // in step (epoch 4 resolved at 7 s): epoch 8 waits; told epoch 5, it goes at once
        assert_eq!(run(Some(7), true).first_key_value(), Some((&5, &8.4)));
        // nobody says the epochs between: epoch 8 after the 2 s gap wait
        assert_eq!(run(Some(7), false), BTreeMap::from([(8, 10.2)]));
        // after a silence (epoch 4 resolved at 5 s, or never by this run), at once
        assert_eq!(run(Some(5), false), BTreeMap::from([(8, 8.2)]));
        assert_eq!(run(None, false), BTreeMap::from([(8, 8.2)]));
    }

    /// The "no record" answers among `out`: (epoch, participants named).
    fn no_records(out: &[NodeOutput]) -> Vec<(u32, usize)> {
        out.iter()
            .filter_map(|o| match o {
                NodeOutput::ToPeers(m) => wire::epoch_of(m).and_then(Result::ok),
                NodeOutput::Estimate(_) | NodeOutput::Update(_) => None,
            })
            .filter(|a| a.state == EpochState::COOPLOC_EPOCH_STATE_NO_RECORD)
            .map(|a| (a.epoch, a.participants.len()))
            .collect()
    }

    #[test]
    fn asked_for_a_record_it_never_sent_a_node_says_none_will_come() {
        // node 2 resolved epochs up to 9 and sent no record of any (it was away, say)
        let mut core = NodeCore::new(config(2, vec![1, 2, 3]), TimeUs(0), start()).unwrap();
        core.last_applied = Some((9, TimeUs(9_000_000)));
        step_at_rest(&mut core, 10_000_000, true);
        let collecting = EpochState::COOPLOC_EPOCH_STATE_COLLECTING;
        // node 1 waits for node 2's record of epoch 8: told at once that none will come
        let out = announce(&mut core, 1, 8, vec![1], collecting);
        assert_eq!(no_records(&out), vec![(8, 0)]);
        // node 3 asks within half a retry interval: the answer went to every peer already
        assert_eq!(no_records(&announce(&mut core, 3, 8, vec![3], collecting)), vec![]);
        // a request that holds our record, or one for an epoch not resolved yet: no answer
        assert_eq!(no_records(&announce(&mut core, 1, 7, vec![1, 2], collecting)), vec![]);
        assert_eq!(no_records(&announce(&mut core, 1, 11, vec![1], collecting)), vec![]);
        assert_eq!(core.stats.no_record_said, 1);
        // asked again a retry interval later: answered again (the first answer may be lost)
        let later = 10_000_000 + core.retry_us();
        step_at_rest(&mut core, later, false);
        assert_eq!(no_records(&announce(&mut core, 1, 8, vec![1], collecting)), vec![(8, 0)]);
    }

    /// Node 1 of [1, 3] learns epoch 5 from node 3 at 4 s, broadcasts its record and waits for
    /// node 3's; at 5.5 s `tell` delivers what node 3 says. The wall time node 1 resolves epoch 5
    /// (if within 8 s), and its core.
    fn wait_for_node_3(signed: bool, tell: &dyn Fn(&mut NodeCore)) -> (Option<f64>, NodeCore) {
        let cfg = NodeConfig { authenticated_peers: signed, ..config(1, vec![1, 3]) };
        let mut core = NodeCore::new(cfg, TimeUs(0), start()).unwrap();
        for k in 1..=800 {
            let t = k * 10_000;
            step_at_rest(&mut core, t, k == 1);
            if t == 4_000_000 {
                announce(&mut core, 3, 5, vec![], EpochState::COOPLOC_EPOCH_STATE_COLLECTING);
            }
            if t == 5_500_000 {
                tell(&mut core);
            }
            if core.last_epoch() == Some(5) {
                return (Some(t as f64 / 1e6), core);
            }
        }
        (None, core)
    }

    #[test]
    fn a_signed_teammate_that_says_it_has_no_record_is_not_waited_for() {
        // at 5.5 s node 3 says it has none (when `told`): the wall time node 1 resolves 5
        let run = |told: bool, signed: bool| -> Option<f64> {
            let tell = |core: &mut NodeCore| {
                if told {
                    announce(core, 3, 5, vec![], EpochState::COOPLOC_EPOCH_STATE_NO_RECORD);
                }
            };
            wait_for_node_3(signed, &tell).0
        };
        assert_eq!(run(true, true), Some(5.5));
        // not told: the epoch timeout (2 s) from the broadcast; nor when told on an unsigned
        // team, where anyone could have said it
        for (told, signed) in [(false, true), (true, false)] {
            let waited = run(told, signed).expect("resolved at the timeout");
            assert!(waited > 7.0, "told {told}, signed {signed}: resolved at {waited} s");
        }
    }

    /// A teammate's "no range" in place of its record settles it, on a signed team only: node 1
    /// of [1, 3] stops waiting for node 3 when node 3 says it; an unsigned team waits the
    /// timeout out (anyone could have said it), and no word is counted.
    #[test]
    fn a_signed_teammates_no_range_settles_it_an_unsigned_ones_does_not() {
        let no_range = |core: &mut NodeCore| {
            let a = wire::EpochAnnouncement {
                epoch: 5,
                t: TimeUs(5_000_000),
                announcer: 3,
                participants: Vec::new(),
                state: EpochState::COOPLOC_EPOCH_STATE_NO_RANGE,
                digest: core.store_digest(),
                incomplete: Vec::new(),
            };
            core.handle(NodeInput::Peer { from: 3, msg: Box::new(wire::epoch_to_message(&a).unwrap()) });
        };
        let run = |signed: bool| {
            let (at, core) = wait_for_node_3(signed, &no_range);
            (at, core.stats.no_range_heard)
        };
        assert_eq!(run(true), (Some(5.5), 1));
        let (waited, heard) = run(false);
        assert!(waited.expect("resolved at the timeout") > 7.0 && heard == 0, "unsigned: {waited:?}, {heard} heard");
    }

    /// Back from a silence (no epoch resolved for a timeout), a node that knows a later epoch
    /// only from a range echo waits for its team to say which epoch it is at, rather than
    /// broadcast the later one and close every epoch before it to itself (`cooploc faults
    /// --only "leaves for 60 s, 10%" --speed 5`: node 3 came back with its team 13 epochs
    /// behind the echoes; 4 runs of 20 did not recover, 1 with the rule, none since the "no
    /// record" answer).
    #[test]
    fn a_node_back_from_a_silence_waits_to_hear_which_epoch_its_team_is_at() {
        // node 3 resolved epoch 4 at wall time 4.5 s and heard its team then; IMU samples every
        // 10 ms, the wall clock running with them; node 2's echo of its range at epoch 12 comes
        // at 12.2 s, and node 2's report of epoch 10 (collecting) at 12.3 s when `team_says`:
        // the epochs node 3 sent a fragment of, each with when it first did
        let run = |team_says: bool| -> BTreeMap<u32, f64> {
            let mut core = NodeCore::new(config(3, vec![1, 2, 3]), TimeUs(0), start()).unwrap();
            let mut sent = BTreeMap::new();
            core.last_applied = Some((4, TimeUs(4_000_000)));
            core.last_run = Some(4);
            (core.resolved_at, core.team_said_at) = (Some(4_500_000), Some(4_500_000));
            for k in 1..=1_500 {
                let t = k * 10_000;
                let mut out = step_at_rest(&mut core, t, k == 1);
                if t == 12_200_000 {
                    let r = RangeSample { t: TimeUs(12_000_000), from: 2, to: 1, range_m: 10.0, sigma_m: 0.1 };
                    let msg = Box::new(wire::range_to_message(&r, 12));
                    out.extend(core.handle(NodeInput::Peer { from: 2, msg }));
                }
                if t == 12_300_000 && team_says {
                    out.extend(announce(&mut core, 2, 10, vec![2], EpochState::COOPLOC_EPOCH_STATE_COLLECTING));
                }
                first_fragments(out, t, &mut sent);
            }
            sent
        };
        // the team says it is at epoch 10: node 3 broadcasts that one first, as soon as it hears
        assert_eq!(run(true).first_key_value(), Some((&10, &12.3)));
        // nobody says: epoch 12 after the 2 s wait
        assert_eq!(run(false), BTreeMap::from([(12, 14.2)]));
    }

    #[test]
    fn epochs_fit_when_the_later_id_comes_later_and_ids_advance_at_most_at_the_rate() {
        let at = |s: u64| TimeUs(s * 1_000_000);
        assert!(epochs_fit((5, at(10)), (5, at(10))), "the same epoch");
        assert!(!epochs_fit((5, at(10)), (5, at(11))), "one id at two times");
        assert!(!epochs_fit((5, at(10)), (6, at(10))), "two ids at one time");
        assert!(epochs_fit((5, at(10)), (6, at(11))));
        assert!(epochs_fit((6, at(11)), (5, at(10))), "in either order");
        assert!(!epochs_fit((5, at(11)), (6, at(10))), "a later id at an earlier time");
        let rate = MAX_EPOCH_RATE_HZ as u32;
        assert!(epochs_fit((5, at(10)), (5 + rate + 1, at(11))), "the rate, and one for rounding");
        assert!(!epochs_fit((5, at(10)), (5 + rate + 2, at(11))), "faster than the rate");
        assert!(!epochs_fit((0, at(0)), (u32::MAX, at(1))), "a far-future id");
    }
}
