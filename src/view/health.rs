//! The team's health as a display shows it, read from what the nodes broadcast (no clock, no
//! I/O): [`EpochTally`] turns COOPLOC_EPOCH reports into disagreement and healing counters,
//! and [`HealthView`] is what the page, the Foxglove channels and a log show.
//!
//! # Disagreements and healing, seen from outside
//!
//! After an epoch each node reports how it ran it (COOPLOC_EPOCH, state APPLIED, PARTIAL or
//! FAILED) with its participants and the digest of its cross-covariance store. Nodes that ran
//! the same epoch on the same records hold equal digests. So, per epoch:
//!
//! - once two or more nodes have reported it, the epoch **disagrees** when any two reports
//!   differ in digest or participants; each such epoch counts once in
//!   [`EpochTally::disagreements`];
//! - a node is **outvoted** at an epoch when its report differs from the majority's (the most
//!   common (digest, participants); a tie goes to the report of the lowest platform id); each
//!   node counts the epochs it was outvoted at;
//! - the team **heals** when, after a disagreeing epoch, a later epoch is reported by two or
//!   more nodes that all agree: [`EpochTally::heals`] counts each return to agreement, and
//!   [`EpochTally::unhealed_since`] names the disagreeing epoch while it lasts. Reports are
//!   judged as they arrive, so a heal whose epoch a late report shows disagreeing is withdrawn;
//! - a node's first report of an epoch counts, a repeat does not; its PARTIAL and FAILED
//!   reports and its STORE_WANTED announcements count once per epoch.
//!
//! The MAVProxy module (`python/cooploc/mavproxy.py`) applies the same rules. Memory
//! is bounded: the last [`EPOCHS_KEPT`] epochs and [`MAX_NODES`] nodes, whatever a sender claims.

use std::collections::{BTreeMap, BTreeSet};

use serde::Serialize;

use crate::estimation::PlatformId;
use crate::protocol::wire::{EpochAnnouncement, EpochState};

/// Epochs whose reports are kept (the oldest go first).
pub const EPOCHS_KEPT: usize = 256;
/// Nodes counted; reports of more are dropped.
pub const MAX_NODES: usize = 64;

/// What one node's reports and announcements added up to.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize)]
pub struct NodeEpochCounts {
    /// Its reports (first of each epoch).
    pub reports: u64,
    /// Epochs at which its report differs from the majority's (the majority judged again as
    /// reports arrive: a node outvoted by the first two reports and joined by the later ones is
    /// no longer counted).
    pub outvoted: u64,
    /// Heals its reports took part in: it reported the agreeing epoch that ended a disagreement
    /// (withdrawn with the heal).
    pub heals: u64,
    /// Epochs it ran without some expected member (PARTIAL).
    pub partial: u64,
    /// Joint updates it refused (FAILED).
    pub failed: u64,
    /// Epochs it was left out of and asked for a teammate's store (STORE_WANTED).
    pub store_wanted: u64,
}

type Report = (u64, Vec<PlatformId>);

/// The disagreement and healing counters of a team, from its COOPLOC_EPOCH messages.
#[derive(Debug, Clone, Default)]
pub struct EpochTally {
    /// Per epoch: each announcer's (digest, participants).
    reports: BTreeMap<u32, BTreeMap<PlatformId, Report>>,
    /// Per epoch: the nodes counted as outvoted there, and those that asked for a store.
    outvoted: BTreeMap<u32, BTreeSet<PlatformId>>,
    wanted: BTreeMap<u32, BTreeSet<PlatformId>>,
    disagreeing: BTreeSet<u32>,
    pub disagreements: u64,
    pub heals: u64,
    /// The latest disagreeing epoch not yet followed by an agreeing one.
    pub unhealed_since: Option<u32>,
    /// The epoch of the last heal (withdrawn when a late report shows it disagreeing too).
    last_heal: Option<u32>,
    /// The highest epoch reported.
    pub last_epoch: Option<u32>,
    pub nodes: BTreeMap<PlatformId, NodeEpochCounts>,
    /// Reports dropped: a node beyond [`MAX_NODES`], or an epoch older than every kept one.
    pub dropped: u64,
    /// Reports repeated (a retransmission; the first counts).
    pub repeats: u64,
}

/// What [`EpochTally::on_epoch`] made of one COOPLOC_EPOCH.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum EpochOutcome {
    /// A report (APPLIED, PARTIAL, FAILED), counted and judged.
    Report,
    /// A STORE_WANTED announcement, counted once per node and epoch.
    StoreWanted,
    /// A report or announcement seen before.
    Repeat,
    /// COLLECTING: not a report.
    Ignored,
    /// Beyond the bounds ([`MAX_NODES`], an epoch older than every kept one).
    Dropped,
}

impl EpochOutcome {
    pub fn name(self) -> &'static str {
        match self {
            EpochOutcome::Report => "report",
            EpochOutcome::StoreWanted => "store_wanted",
            EpochOutcome::Repeat => "repeat",
            EpochOutcome::Ignored => "ignored",
            EpochOutcome::Dropped => "dropped",
        }
    }
}

impl EpochTally {
    pub fn new() -> Self {
        Self::default()
    }

    /// Takes one validated COOPLOC_EPOCH (its announcer already checked against its sender).
    pub fn on_epoch(&mut self, a: &EpochAnnouncement) -> EpochOutcome {
        if !self.nodes.contains_key(&a.announcer) && self.nodes.len() >= MAX_NODES {
            self.dropped += 1;
            return EpochOutcome::Dropped;
        }
        match a.state {
            EpochState::COOPLOC_EPOCH_STATE_COLLECTING
            | EpochState::COOPLOC_EPOCH_STATE_NO_RECORD
            | EpochState::COOPLOC_EPOCH_STATE_NO_RANGE => {
                return EpochOutcome::Ignored;
            }
            EpochState::COOPLOC_EPOCH_STATE_STORE_WANTED => {
                let first = self.wanted.entry(a.epoch).or_default().insert(a.announcer);
                if first {
                    self.nodes.entry(a.announcer).or_default().store_wanted += 1;
                } else {
                    self.repeats += 1;
                }
                while self.wanted.len() > EPOCHS_KEPT {
                    self.wanted.pop_first();
                }
                return if first { EpochOutcome::StoreWanted } else { EpochOutcome::Repeat };
            }
            _ => {}
        }
        if self.reports.get(&a.epoch).is_some_and(|r| r.contains_key(&a.announcer)) {
            self.repeats += 1;
            return EpochOutcome::Repeat; // a retransmission: the first report counts
        }
        if self.reports.len() >= EPOCHS_KEPT
            && !self.reports.contains_key(&a.epoch)
            && self.reports.keys().next().is_some_and(|&oldest| a.epoch < oldest)
        {
            self.dropped += 1;
            return EpochOutcome::Dropped;
        }
        self.reports.entry(a.epoch).or_default().insert(a.announcer, (a.digest, a.participants.clone()));
        let counts = self.nodes.entry(a.announcer).or_default();
        counts.reports += 1;
        match a.state {
            EpochState::COOPLOC_EPOCH_STATE_PARTIAL => counts.partial += 1,
            EpochState::COOPLOC_EPOCH_STATE_FAILED => counts.failed += 1,
            _ => {}
        }
        while self.reports.len() > EPOCHS_KEPT {
            if let Some((old, _)) = self.reports.pop_first() {
                self.outvoted.remove(&old);
                self.disagreeing.remove(&old);
            }
        }
        self.last_epoch = self.last_epoch.max(Some(a.epoch));
        self.judge(a.epoch, a.announcer);
        EpochOutcome::Report
    }

    /// Epochs whose reports are held (at most [`EPOCHS_KEPT`]).
    pub fn epochs_held(&self) -> usize {
        self.reports.len()
    }

    fn add_heals(&mut self, epoch: u32, delta: i64, except: Option<PlatformId>) {
        let Some(reports) = self.reports.get(&epoch) else { return };
        for id in reports.keys().filter(|id| Some(**id) != except) {
            if let Some(c) = self.nodes.get_mut(id) {
                c.heals = c.heals.saturating_add_signed(delta);
            }
        }
    }

    fn judge(&mut self, epoch: u32, announcer: PlatformId) {
        let Some(reports) = self.reports.get(&epoch) else { return };
        if reports.len() < 2 {
            return;
        }
        let first = reports.values().next();
        let agree = reports.values().all(|r| Some(r) == first);
        if agree {
            if self.unhealed_since.is_some_and(|d| epoch > d) {
                self.heals += 1;
                self.unhealed_since = None;
                self.last_heal = Some(epoch);
                self.add_heals(epoch, 1, None);
            } else if self.last_heal == Some(epoch)
                && let Some(c) = self.nodes.get_mut(&announcer)
            {
                c.heals += 1; // one more node agrees with the healing epoch
            }
            return;
        }
        if self.disagreeing.insert(epoch) {
            self.disagreements += 1;
        }
        // The first reports of this epoch agreed and were taken for a heal: a late one says
        // otherwise, so the heal is withdrawn (and the team is unhealed since this epoch, below).
        if self.last_heal == Some(epoch) {
            self.heals -= 1;
            self.last_heal = None;
            self.add_heals(epoch, -1, Some(announcer));
        }
        if self.unhealed_since.is_none_or(|d| epoch > d) {
            self.unhealed_since = Some(epoch);
        }
        let Some(reports) = self.reports.get(&epoch) else { return };
        // The majority's report; reports iterate by platform id, so the first of the most
        // common ones is the lowest id's. Judged again at every report of the epoch.
        let mut votes: Vec<(&Report, usize)> = Vec::new();
        for r in reports.values() {
            match votes.iter_mut().find(|(v, _)| *v == r) {
                Some((_, n)) => *n += 1,
                None => votes.push((r, 1)),
            }
        }
        let most = votes.iter().map(|(_, n)| *n).max().unwrap_or(0);
        let Some(&(majority, _)) = votes.iter().find(|(_, n)| *n == most) else { return };
        let minority: BTreeSet<PlatformId> = reports.iter().filter(|(_, r)| *r != majority).map(|(id, _)| *id).collect();
        let counted = self.outvoted.entry(epoch).or_default();
        for id in counted.difference(&minority) {
            if let Some(c) = self.nodes.get_mut(id) {
                c.outvoted -= 1;
            }
        }
        for id in minority.difference(counted) {
            if let Some(c) = self.nodes.get_mut(id) {
                c.outvoted += 1;
            }
        }
        *counted = minority;
    }
}

/// One node's health, as every display shows it.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct NodeHealth {
    pub id: PlatformId,
    pub name: String,
    pub color: String,
    /// Estimates received per second over the rate window (None: fewer than two).
    pub estimate_rate_hz: Option<f64>,
    /// Bytes per second of its cooperative frames, as received.
    pub bytes_per_s: f64,
    /// Its share of the link's capacity (capacity / nodes heard), bytes per second, and its
    /// bytes against it, %; None without a link capacity.
    pub budget_bytes_per_s: Option<f64>,
    pub budget_used_pct: Option<f64>,
    /// Frames lost on the way, from the MAVLink sequence (None: too few frames).
    pub loss_pct: Option<f64>,
    /// Its cooperative frames that carried a MAVLink 2 signature, and those that did not.
    pub signed_frames: u64,
    pub unsigned_frames: u64,
    /// `signed`, `unsigned`, `mixed` or `none yet`.
    pub signing: &'static str,
    #[serde(flatten)]
    pub epochs: NodeEpochCounts,
}

/// The team's health.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct HealthView {
    /// Receive time, ns since the UNIX epoch.
    pub rx_ns: u64,
    pub last_epoch: Option<u32>,
    pub disagreements: u64,
    pub heals: u64,
    pub unhealed_since: Option<u32>,
    /// Payload bytes per second the shared cooperative link carries (`--link-capacity`).
    pub link_capacity_bytes_per_s: Option<f64>,
    pub team_bytes_per_s: f64,
    pub team_load_pct: Option<f64>,
    /// Whether the station itself verifies signatures (it holds the team key).
    pub verifying: bool,
    pub nodes: Vec<NodeHealth>,
}

/// How a node signs, from its frame counts.
pub fn signing_word(signed: u64, unsigned: u64) -> &'static str {
    match (signed, unsigned) {
        (0, 0) => "none yet",
        (_, 0) => "signed",
        (0, _) => "unsigned",
        _ => "mixed",
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn report(epoch: u32, announcer: PlatformId, digest: u64, participants: &[PlatformId]) -> EpochAnnouncement {
        EpochAnnouncement {
            epoch,
            t: crate::time::TimeUs(u64::from(epoch) * 1_000_000),
            announcer,
            participants: participants.to_vec(),
            state: EpochState::COOPLOC_EPOCH_STATE_APPLIED,
            digest,
            incomplete: Vec::new(),
        }
    }

    #[test]
    fn agree_disagree_disagree_agree_is_two_disagreements_and_one_heal() {
        let mut t = EpochTally::new();
        for id in 1..=3 {
            t.on_epoch(&report(1, id, 7, &[1, 2, 3]));
        }
        assert_eq!((t.disagreements, t.heals, t.unhealed_since), (0, 0, None));
        // Epochs 2 and 3: node 3 holds another store.
        for e in 2..=3 {
            t.on_epoch(&report(e, 1, 8, &[1, 2, 3]));
            t.on_epoch(&report(e, 2, 8, &[1, 2, 3]));
            t.on_epoch(&report(e, 3, 9, &[1, 2, 3]));
        }
        assert_eq!((t.disagreements, t.heals, t.unhealed_since), (2, 0, Some(3)));
        assert_eq!(t.nodes[&3].outvoted, 2);
        assert_eq!(t.nodes[&1].outvoted, 0);
        for id in 1..=3 {
            t.on_epoch(&report(4, id, 10, &[1, 2, 3]));
        }
        assert_eq!((t.disagreements, t.heals, t.unhealed_since, t.last_epoch), (2, 1, None, Some(4)));
        // A report repeated (a retransmission) changes nothing.
        t.on_epoch(&report(3, 3, 9, &[1, 2, 3]));
        assert_eq!((t.disagreements, t.nodes[&3].outvoted), (2, 2));
    }

    #[test]
    fn other_participants_disagree_and_a_tie_goes_to_the_lowest_id() {
        let mut t = EpochTally::new();
        t.on_epoch(&report(5, 2, 1, &[1, 2]));
        t.on_epoch(&report(5, 1, 1, &[1, 2, 3]));
        assert_eq!(t.disagreements, 1);
        assert_eq!((t.nodes[&1].outvoted, t.nodes[&2].outvoted), (0, 1));
    }

    #[test]
    fn one_report_alone_judges_nothing_and_states_are_counted() {
        let mut t = EpochTally::new();
        t.on_epoch(&report(1, 1, 1, &[1]));
        let mut partial = report(2, 1, 1, &[1]);
        partial.state = EpochState::COOPLOC_EPOCH_STATE_PARTIAL;
        t.on_epoch(&partial);
        let mut wanted = report(3, 2, 1, &[1]);
        wanted.state = EpochState::COOPLOC_EPOCH_STATE_STORE_WANTED;
        t.on_epoch(&wanted);
        let mut collecting = report(3, 2, 1, &[1]);
        collecting.state = EpochState::COOPLOC_EPOCH_STATE_COLLECTING;
        t.on_epoch(&collecting);
        // "no record from me" is an answer to a request, not a report of a run epoch
        let mut none = report(4, 3, 1, &[]);
        none.state = EpochState::COOPLOC_EPOCH_STATE_NO_RECORD;
        assert_eq!(t.on_epoch(&none), EpochOutcome::Ignored);
        assert_eq!((t.disagreements, t.heals), (0, 0));
        assert_eq!((t.nodes[&1].partial, t.nodes[&2].store_wanted, t.last_epoch), (1, 1, Some(2)));
    }

    #[test]
    fn memory_is_bounded_whatever_senders_claim() {
        let mut t = EpochTally::new();
        for e in 0..10_000u32 {
            t.on_epoch(&report(e, 1, 1, &[1]));
        }
        assert_eq!(t.reports.len(), EPOCHS_KEPT);
        t.on_epoch(&report(3, 1, 1, &[1]));
        assert_eq!(t.dropped, 1, "an epoch older than every kept one");
        for id in 0..200u16 {
            t.on_epoch(&report(20_000, id, 1, &[1]));
        }
        assert_eq!(t.nodes.len(), MAX_NODES);
    }

    /// The majority is judged again as reports arrive; heals are counted per node and withdrawn
    /// with the heal; repeats and the outcome of each message are told.
    #[test]
    fn the_majority_is_judged_again_and_heals_are_counted_per_node() {
        let mut t = EpochTally::new();
        assert_eq!(t.on_epoch(&report(1, 5, 1, &[4, 5, 6])), EpochOutcome::Report);
        t.on_epoch(&report(1, 4, 2, &[4, 5, 6]));
        assert_eq!((t.nodes[&4].outvoted, t.nodes[&5].outvoted), (0, 1), "a tie: the lowest id's");
        t.on_epoch(&report(1, 6, 1, &[4, 5, 6]));
        assert_eq!((t.nodes[&4].outvoted, t.nodes[&5].outvoted, t.nodes[&6].outvoted), (1, 0, 0));
        assert_eq!(t.on_epoch(&report(1, 6, 1, &[4, 5, 6])), EpochOutcome::Repeat);
        assert_eq!(t.repeats, 1);
        // epoch 2 agrees: a heal, one per reporting node; a third agreeing report adds one more
        t.on_epoch(&report(2, 4, 3, &[4, 5, 6]));
        t.on_epoch(&report(2, 5, 3, &[4, 5, 6]));
        assert_eq!((t.heals, t.nodes[&4].heals, t.nodes[&5].heals, t.nodes[&6].heals), (1, 1, 1, 0));
        t.on_epoch(&report(2, 6, 3, &[4, 5, 6]));
        assert_eq!(t.nodes[&6].heals, 1);
        assert_eq!(t.nodes[&4].reports, 2);
        // a later disagreeing report withdraws the heal from everyone who had it
        let mut late = EpochTally::new();
        for id in 1..=3 {
            late.on_epoch(&report(1, id, 7, &[1, 2, 3]));
        }
        late.on_epoch(&report(2, 1, 8, &[1, 2, 3]));
        late.on_epoch(&report(2, 3, 9, &[1, 2, 3]));
        late.on_epoch(&report(3, 1, 8, &[1, 2, 3]));
        late.on_epoch(&report(3, 2, 8, &[1, 2, 3]));
        assert_eq!((late.heals, late.nodes[&1].heals, late.nodes[&2].heals), (1, 1, 1));
        late.on_epoch(&report(3, 3, 9, &[1, 2, 3]));
        assert_eq!((late.heals, late.nodes[&1].heals, late.nodes[&2].heals, late.nodes[&3].heals), (0, 0, 0, 0));
        assert_eq!(late.unhealed_since, Some(3));
        let mut collecting = report(4, 1, 1, &[1]);
        collecting.state = EpochState::COOPLOC_EPOCH_STATE_COLLECTING;
        assert_eq!(late.on_epoch(&collecting), EpochOutcome::Ignored);
    }

    #[test]
    fn signing_words() {
        assert_eq!(
            [signing_word(0, 0), signing_word(3, 0), signing_word(0, 3), signing_word(1, 1)],
            ["none yet", "signed", "unsigned", "mixed"]
        );
    }
}
