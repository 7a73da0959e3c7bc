//! Store synchronisation: how a node whose cross-covariance store diverged from its teammates'
//! gets theirs, and how it gives its own.
//!
//! A node *left out* of an epoch (its store not valid for the participants, see the core's
//! documentation) applies nothing and asks the participants for their store right after that
//! epoch (COOPLOC_EPOCH with STORE_WANTED). Its next broadcast waits for the store for an epoch
//! timeout from the first request, asking again every retry interval. A participant answers with
//! the store it kept after that epoch (COOPLOC_STORE_FRAGMENT), only to a teammate that did not
//! run the epoch with it, and at most once per retry interval in all: a request is a small
//! message and a store a large one, so nobody can make a node flood the network. Only the two
//! participants with the lowest ids answer (one answer may be lost; 63 copies of a 64-member
//! team's 4 MB store would be a flood of their own).
//!
//! **A store larger than the link carries in an epoch** (a 16-member team's 247 KB is half a
//! minute of a 64 kbit/s radio) is still taken whole:
//! - *Paced* ([`Answerer::per_answer`], from `NodeConfig::store_bps`): an answer is the next
//!   few fragments of the store, not all of it; the answerer keeps the store it is serving (and
//!   where it is in it) while it is asked for, even once newer epochs have pushed it out of the
//!   stores kept, and the second answerer starts half way through, so that the two send
//!   different fragments.
//! - *Acknowledged*: before each repeated request the asking node says what it holds of the
//!   store (COOPLOC_STORE_HELD: the parts whole, and the fragments of up to [`HELD_SERIES`]
//!   parts held in part), and a paced answer leaves out what every teammate asking holds. A
//!   fragment lost is sent again when the answerer's cursor comes to it, not after the whole
//!   store has gone round (ten members at 10% datagram loss: 1.15 times the loss-free cost,
//!   where it was 3.6). A teammate that said nothing (an older release, an unsigned team, or
//!   its word was lost) is sent everything.
//! - *Resumable across epochs*: the asking node keeps asking every retry interval while
//!   fragments come (a want dies after [`GIVE_UP_TIMEOUTS`] epoch timeouts without one). Its
//!   broadcasts meanwhile carry its old store, so the team leaves it out of the epochs that
//!   follow; it keeps the records each of those epochs ran on ([`LaterEpoch`], at most
//!   [`LATER_EPOCHS`]), and once the store has come whole it brings it forward by them, as the
//!   participants brought theirs (the core's `bring_forward`, checking each epoch's store
//!   digest), and adopts the result: the store the team holds now. An epoch in between that it
//!   cannot replay (one it took part in, a heal, one it did not hear) ends the want, as before.
//!
//! A store goes as parts of at most [`PART_LEN`] bytes, each one fragment series
//! ([`crate::protocol::record::StorePart`]), so that a store of any size (up to
//! [`crate::protocol::record::MAX_STORE_LEN`]) can be sent: the asking node keeps every series
//! and every part that arrived, from either answerer (they hold the same store), while it still
//! wants the store, so that a repeated request fills what was lost instead of starting over.
//!
//! The asking node adopts a store only if it asked for it, from a participant, nothing was
//! resolved since but the epochs it was left out of (which it brings the store forward by),
//! and the result is valid for itself. A store that is not ends the want: the next epoch it is
//! left out of asks afresh.
//!
//! This module holds the decisions and the state they need; the core sends and decodes.

use std::collections::{BTreeMap, VecDeque};

use crate::estimation::{CrossCovariances, PlatformId, StoreRef};
use crate::protocol::fragment::{Fragment, MAX_RECORD_LEN, PartPushed, Payload, Pushed, Reassembler, StoreAssembler, fragment};
use crate::protocol::record::{self, MAX_STORE_LEN, STORE_PART_HEADER, StateRecord, StoreSnapshot};
use crate::protocol::wire::{self, StoreHeld};
use crate::time::TimeUs;

/// Store snapshots kept for teammates that ask (the last epochs we took part in).
pub(super) const SNAPSHOTS_KEPT: usize = 4;
/// Snapshot bytes per part: a part and its header fill one fragment series.
pub(super) const PART_LEN: usize = MAX_RECORD_LEN - STORE_PART_HEADER;
/// Fragment series of a wanted store in progress at once (each at most 255 fragments).
const SERIES_IN_PROGRESS: usize = 256;
/// Participants that answer a request for a store: the ones with the lowest ids.
pub(super) const ANSWERERS: usize = 2;
/// Stores served at once (transfers in progress, paced): requests for many epochs pin at most
/// these; a request for another store waits until one of them is taken or given up.
const SERVED: usize = 4;
/// A store nobody asked for this long is no longer served, us of wall time.
const SERVE_IDLE_US: u64 = 4_000_000;
/// Epochs a left-out node keeps to bring a store that is still coming forward by.
pub(super) const LATER_EPOCHS: usize = 64;
/// A want with no fragment of its store for this many epoch timeouts is given up.
pub(super) const GIVE_UP_TIMEOUTS: u64 = 2;
/// Series held in part that a request describes at most (a COOPLOC_STORE_HELD each): those
/// furthest along. An answerer sends a series not described whole.
pub(super) const HELD_SERIES: usize = 8;

/// Whether `me` answers a request for the store of the epoch `participants` ran, and as which:
/// one of the [`ANSWERERS`] lowest ids among them (0: the lowest).
pub(super) fn answer_rank(participants: &[PlatformId], me: PlatformId) -> Option<usize> {
    let below = participants.iter().filter(|&&p| p < me).count();
    (participants.contains(&me) && below < ANSWERERS).then_some(below)
}

/// A request for our store after `epoch` (under `digest_before`) from `to`, which did or did not
/// run that epoch with us.
#[derive(Debug, Clone, Copy, PartialEq)]
pub(super) struct Asked {
    pub(super) to: PlatformId,
    pub(super) epoch: u32,
    pub(super) digest_before: u64,
    pub(super) ran_with_us: bool,
}

/// Who answers a request for a store, and how much of it goes in one answer.
#[derive(Debug, Clone, Copy, PartialEq)]
pub(super) struct Answerer {
    pub(super) id: PlatformId,
    /// Its [`answer_rank`]: a paced answerer starts this many [`ANSWERERS`]ths into the store.
    pub(super) rank: usize,
    /// Fragments per answer; 0: the whole store each time (not paced).
    pub(super) per_answer: usize,
}

/// A store being served to teammates that asked: its fragments, cut once (with the part each
/// one is of), where the next paced answer starts, and what each teammate asking said it holds.
#[derive(Debug, Clone)]
struct Serving {
    epoch: u32,
    digest_before: u64,
    fragments: Vec<(u16, Fragment)>,
    cursor: usize,
    last_asked: u64,
    askers: BTreeMap<PlatformId, Asker>,
}

impl Serving {
    /// Whether some teammate asking lacks fragment `j` (one that never said what it holds lacks
    /// everything).
    fn needed(&self, j: usize) -> bool {
        let (part, f) = &self.fragments[j];
        self.askers.values().any(|a| a.held.as_ref().is_none_or(|h| !h.iter().any(|x| x.holds(*part, f.record_crc32, f.index))))
    }
}

/// A teammate asking for a store we serve: what it said it holds since its last request
/// (`pending`), and at its last request, which the answers go by (None: it said nothing; it is
/// sent everything).
#[derive(Debug, Clone, Default)]
struct Asker {
    pending: Vec<StoreHeld>,
    held: Option<Vec<StoreHeld>>,
    last_asked: u64,
}

/// An epoch the team ran without us while we wanted a store: the records it ran on (each
/// carrying the store it ran from) and the members whose blocks were forgotten first. The store
/// we want is brought forward by these once it comes.
#[derive(Debug, Clone, PartialEq)]
pub(super) struct LaterEpoch {
    pub(super) epoch: u32,
    pub(super) records: Vec<StateRecord>,
    pub(super) refreshed: Vec<PlatformId>,
    /// The members that took part by their word alone (bystanders: no record, the same store).
    pub(super) bystanders: Vec<PlatformId>,
}

/// Our store right after an epoch we took part in, for teammates that ask.
#[derive(Debug, Clone)]
struct KeptStore {
    epoch: u32,
    t: TimeUs,
    /// The store's digest before the epoch (what the epoch's records carried).
    digest_before: u64,
    store: CrossCovariances,
}

/// The store we asked for after we were left out of an epoch.
#[derive(Debug, Clone)]
struct WantStore {
    request: StoreRequest,
    /// Wall time we asked first and last, and a fragment of the store last arrived.
    since: u64,
    last_request: u64,
    last_progress: Option<u64>,
    /// The parts of the store that arrived.
    parts: StoreAssembler,
    /// The epochs run without us since the store's, in order.
    later: Vec<LaterEpoch>,
}

impl WantStore {
    /// The last epoch resolved since we asked: the store's own, or the last one run without us.
    fn chain_end(&self) -> u32 {
        self.later.last().map_or(self.request.epoch, |l| l.epoch)
    }
}

/// A request for the store after `epoch` (at `t`), to the participants that ran it on a store
/// whose digest before it was `digest_before`.
#[derive(Debug, Clone, PartialEq)]
pub(super) struct StoreRequest {
    pub(super) epoch: u32,
    pub(super) t: TimeUs,
    pub(super) digest_before: u64,
    pub(super) members: Vec<PlatformId>,
}

/// Whether the next broadcast waits for a store ([`StoreSync::awaiting`]).
#[derive(Debug, Clone, PartialEq)]
pub(super) enum Awaiting {
    /// No store may come: go on.
    No,
    /// Wait; ask again when given.
    Yes(Option<StoreRequest>),
}

/// The stores kept and wanted (see the module documentation).
#[derive(Debug)]
pub(super) struct StoreSync {
    kept: VecDeque<KeptStore>,
    serving: VecDeque<Serving>,
    wanted: Option<WantStore>,
    /// Wall time we last sent our store after each recent epoch.
    sent_at: BTreeMap<u32, u64>,
    reassembler: Reassembler,
}

impl StoreSync {
    pub(super) fn new() -> Self {
        Self {
            kept: VecDeque::new(),
            serving: VecDeque::new(),
            wanted: None,
            sent_at: BTreeMap::new(),
            reassembler: Reassembler::keeping_each_record(SERIES_IN_PROGRESS),
        }
    }

    /// The stores kept: (epoch, store digest before it) of each.
    pub(super) fn kept(&self) -> impl Iterator<Item = (u32, u64)> + '_ {
        self.kept.iter().map(|k| (k.epoch, k.digest_before))
    }

    /// Keeps our store after `epoch` for teammates that may ask for it, when its snapshot is at
    /// most [`MAX_STORE_LEN`] bytes (beyond that a left-out node heals with the bound); the last
    /// [`SNAPSHOTS_KEPT`] are kept.
    pub(super) fn keep(&mut self, epoch: u32, t: TimeUs, digest_before: u64, store: &CrossCovariances, team: usize) {
        let bytes: usize = store.blocks().map(|(_, m)| 6 + m.len() * 8).sum::<usize>() + 32 + 14 * team;
        if bytes > MAX_STORE_LEN {
            return;
        }
        self.kept.push_back(KeptStore { epoch, t, digest_before, store: store.clone() });
        if self.kept.len() > SNAPSHOTS_KEPT {
            self.kept.pop_front();
        }
    }

    /// We were left out: we want the store of `request` from now (`wall_us`) on.
    pub(super) fn want(&mut self, request: StoreRequest, wall_us: u64) {
        if self.wanted.as_ref().is_some_and(|w| w.request == request) {
            return;
        }
        self.wanted = Some(WantStore {
            request,
            since: wall_us,
            last_request: wall_us,
            last_progress: None,
            parts: StoreAssembler::default(),
            later: Vec::new(),
        });
    }

    /// Whether we want a store (the records of an epoch run without us are worth keeping).
    pub(super) fn wanting(&self) -> bool {
        self.wanted.is_some()
    }

    /// We were left out of `later.epoch` too (or it ran without our record), `prev_run` being
    /// the epoch resolved before it: true when the store we already want is still worth having
    /// (nothing else was resolved since its chain's end, room is left, and either a fragment of
    /// it came or we asked less than `timeout_us` ago), and the epoch is kept to bring it
    /// forward by. False: ask afresh for this epoch's store.
    pub(super) fn carry_on(&mut self, prev_run: Option<u32>, later: LaterEpoch, wall_us: u64, timeout_us: u64) -> bool {
        let Some(w) = self.wanted.as_mut() else { return false };
        let answered = w.last_progress.is_some() || wall_us < w.since + timeout_us;
        if prev_run != Some(w.chain_end()) || w.later.len() >= LATER_EPOCHS || !answered {
            return false;
        }
        w.later.push(later);
        true
    }

    /// The store we want, while it is still worth waiting for: `last_run` (the last epoch
    /// resolved) ends its chain, and a fragment of it came (or we first asked) less than
    /// [`GIVE_UP_TIMEOUTS`] epoch timeouts ago. Otherwise the want is dropped.
    fn live(&mut self, last_run: Option<u32>, wall_us: u64, timeout_us: u64) -> Option<&mut WantStore> {
        let w = self.wanted.as_ref()?;
        let heard = w.last_progress.unwrap_or(w.since);
        if last_run != Some(w.chain_end()) || wall_us >= heard + GIVE_UP_TIMEOUTS * timeout_us {
            self.wanted = None;
        }
        self.wanted.as_mut()
    }

    /// Whether the next broadcast waits for the store we want: while it is [`Self::live`] and
    /// less than `timeout_us` passed since we first asked (after that our broadcast goes with
    /// the old store: the team leaves us out and we bring the store forward when it comes); the
    /// request is repeated every `retry_us`.
    pub(super) fn awaiting(&mut self, last_run: Option<u32>, wall_us: u64, timeout_us: u64, retry_us: u64) -> Awaiting {
        let Some(w) = self.live(last_run, wall_us, timeout_us) else { return Awaiting::No };
        if wall_us >= w.since + timeout_us {
            return Awaiting::No;
        }
        if wall_us >= w.last_request + retry_us {
            w.last_request = wall_us;
            return Awaiting::Yes(Some(w.request.clone()));
        }
        Awaiting::Yes(None)
    }

    /// The request to repeat now (every `retry_us` while the store we want is [`Self::live`],
    /// whether the broadcast waits for it or not).
    pub(super) fn ask(&mut self, last_run: Option<u32>, wall_us: u64, timeout_us: u64, retry_us: u64) -> Option<StoreRequest> {
        let w = self.live(last_run, wall_us, timeout_us)?;
        if wall_us < w.last_request + retry_us {
            return None;
        }
        w.last_request = wall_us;
        Some(w.request.clone())
    }

    /// A fragment of a store from `from`: kept only when it is of the store we want, from one of
    /// its participants (nobody can make us hold another's bytes). None: not kept. Complete:
    /// the whole snapshot's bytes, from its parts (or in one series, as releases before parts
    /// sent it).
    pub(super) fn push_fragment(&mut self, from: PlatformId, f: &Fragment, wall_us: u64) -> Option<Pushed> {
        let w = self.wanted.as_mut()?;
        if w.request.epoch != f.epoch || !w.request.members.contains(&from) {
            return None;
        }
        // The answerers send the same store: a series is put together from both (each part is
        // checked whole against its CRC, and the snapshot against its digest).
        let pushed = self.reassembler.push(&Fragment { platform: 0, ..f.clone() });
        self.reassembler.take_dropped();
        if !matches!(pushed, Pushed::Rejected(_)) {
            w.last_progress = Some(wall_us);
        }
        let Pushed::Complete(series) = pushed else { return Some(pushed) };
        Some(match record::decode_store_part(&series.bytes) {
            Ok(None) => Pushed::Complete(series),
            Ok(Some(part)) => match w.parts.push(part) {
                PartPushed::Stored => Pushed::Stored,
                PartPushed::Duplicate => Pushed::Duplicate,
                PartPushed::Rejected(why) => Pushed::Rejected(why),
                PartPushed::Complete(bytes) => Pushed::Complete(crate::protocol::fragment::Record { bytes, ..series }),
            },
            Err(_) => Pushed::Rejected("a store series that is neither a part nor a snapshot"),
        })
    }

    /// The fragments of our store after `epoch` that go to `to`, a teammate that asked, when we
    /// kept it (under that digest) or are serving it, and the teammate did not run the epoch
    /// with us: the whole store, when we answered nobody in the last `retry_us`; or paced, the
    /// next [`Answerer::per_answer`] of its fragments (round and round) that a teammate asking
    /// lacks (by what each said it holds before its request: [`Self::held_by`]), when we sent
    /// none of this store in the last `retry_us`, [`SERVED`] stores at most at once (teammates
    /// left out at different epochs each get theirs; fragments are broadcast, so those that
    /// want the same store share them). Mark it [`Self::sent`] once they went.
    pub(super) fn answer(&mut self, asked: Asked, me: Answerer, wall_us: u64, retry_us: u64) -> Option<Vec<Fragment>> {
        let Asked { to, epoch, digest_before, ran_with_us } = asked;
        let recently = |at: &u64| wall_us < at + retry_us;
        let recently =
            if me.per_answer == 0 { self.sent_at.values().any(recently) } else { self.sent_at.get(&epoch).is_some_and(recently) };
        if ran_with_us || recently {
            return None;
        }
        if me.per_answer == 0 {
            let k = self.kept.iter().find(|k| k.epoch == epoch && k.digest_before == digest_before)?;
            return Some(store_fragments(me.id, k, digest_before)?.into_iter().map(|(_, f)| f).collect());
        }
        self.serving.retain(|s| wall_us < s.last_asked.saturating_add(SERVE_IDLE_US));
        let i = match self.serving.iter().position(|s| s.epoch == epoch && s.digest_before == digest_before) {
            Some(i) => i,
            None => {
                let k = self.kept.iter().find(|k| k.epoch == epoch && k.digest_before == digest_before)?;
                if self.serving.len() >= SERVED {
                    return None;
                }
                let fragments = store_fragments(me.id, k, digest_before)?;
                let cursor = fragments.len() * me.rank.min(ANSWERERS - 1) / ANSWERERS;
                let askers = BTreeMap::new();
                self.serving.push_back(Serving { epoch, digest_before, fragments, cursor, last_asked: wall_us, askers });
                self.serving.len() - 1
            }
        };
        let s = &mut self.serving[i];
        s.last_asked = wall_us;
        let a = s.askers.entry(to).or_default();
        a.held = (!a.pending.is_empty()).then(|| std::mem::take(&mut a.pending));
        a.last_asked = wall_us;
        s.askers.retain(|_, a| wall_us < a.last_asked.saturating_add(SERVE_IDLE_US));
        let len = s.fragments.len();
        let (mut out, mut k) = (Vec::new(), 0);
        while k < len && out.len() < me.per_answer {
            let j = (s.cursor + k) % len;
            if s.needed(j) {
                out.push(s.fragments[j].1.clone());
            }
            k += 1;
        }
        s.cursor = (s.cursor + k) % len;
        (!out.is_empty()).then_some(out)
    }

    /// `from` says what it holds of a store we serve (COOPLOC_STORE_HELD): kept for the answer
    /// to its next request, when it asked for that store before (so at most a few per teammate
    /// asking).
    pub(super) fn held_by(&mut self, from: PlatformId, h: StoreHeld) {
        let Some(s) = self.serving.iter_mut().find(|s| s.epoch == h.epoch && s.digest_before == h.digest_before) else { return };
        if let Some(a) = s.askers.get_mut(&from)
            && a.pending.len() < HELD_SERIES
        {
            a.pending.push(h);
        }
    }

    /// What we hold of the store we want, for the teammates that answer (a COOPLOC_STORE_HELD
    /// each, sent before a repeated request): the parts whole, and the [`HELD_SERIES`] series
    /// furthest along held in part. None while we hold nothing of it.
    pub(super) fn held(&self, me: PlatformId) -> Vec<StoreHeld> {
        let Some(w) = self.wanted.as_ref() else { return Vec::new() };
        let r = &w.request;
        let whole = wire::bits_at(w.parts.held_parts().into_iter().map(usize::from));
        let base = StoreHeld { epoch: r.epoch, t: r.t, announcer: me, digest_before: r.digest_before, whole, series: None };
        let mut series: Vec<(u32, &[bool])> = self.reassembler.incomplete_series(r.epoch).filter(|(crc, _)| *crc != 0).collect();
        series.sort_by_key(|(_, have)| std::cmp::Reverse(have.iter().filter(|&&h| h).count()));
        let held = |have: &[bool]| wire::bits_at(have.iter().enumerate().filter(|(_, h)| **h).map(|(i, _)| i));
        let mut out: Vec<StoreHeld> = series
            .into_iter()
            .take(HELD_SERIES)
            .map(|(crc, have)| StoreHeld { series: Some((crc, held(have))), ..base.clone() })
            .collect();
        if out.is_empty() && whole != [0; 4] {
            out.push(base);
        }
        out
    }

    /// Our store after `epoch` went at `wall_us`; the epochs `remembered` before it are forgotten.
    pub(super) fn sent(&mut self, epoch: u32, wall_us: u64, remembered: u32) {
        self.sent_at.insert(epoch, wall_us);
        self.sent_at.retain(|e, _| e.saturating_add(remembered) > epoch);
    }

    /// A store offered by `from`: to be taken when it is the one we asked for (its epoch, its
    /// digest before, from a participant) and `last_run` still ends the want's chain (nothing
    /// else resolved since). Then the want ends, and the epochs run without us since the
    /// store's come back, to bring it forward by (in order; the core then checks it is valid for
    /// us).
    pub(super) fn offered(&mut self, from: PlatformId, snap: &StoreSnapshot, last_run: Option<u32>) -> Option<Vec<LaterEpoch>> {
        let w = self.wanted.as_ref()?;
        let asked = w.request.epoch == snap.epoch && w.request.digest_before == snap.digest_before;
        if !(asked && w.request.members.contains(&from) && last_run == Some(w.chain_end())) {
            return None;
        }
        self.wanted.take().map(|w| w.later)
    }
}

/// The fragments of the kept store `k` (as answerer `me`), in parts of one series each, with the
/// part each one is of.
fn store_fragments(me: PlatformId, k: &KeptStore, digest_before: u64) -> Option<Vec<(u16, Fragment)>> {
    let snap = StoreSnapshot { epoch: k.epoch, digest_before, store: k.store.clone() };
    let bytes = record::encode_store(&snap).ok()?;
    let mut out = Vec::new();
    for (index, part) in record::store_parts(&bytes, PART_LEN).ok()?.into_iter().enumerate() {
        let index = u16::try_from(index).ok()?;
        let frags = fragment(me, k.epoch, k.t.0, &part).ok()?;
        out.extend(frags.into_iter().map(|f| (index, Fragment { payload: Payload::Store, ..f })));
    }
    Some(out)
}

/// The records that share a store valid for every participant of an epoch (see
/// [`choose_store`]).
#[derive(Debug, Clone, PartialEq)]
pub(super) struct StoreChoice {
    pub(super) digest: u64,
    /// Platforms whose record carries that store (they run the epoch).
    pub(super) members: Vec<PlatformId>,
    /// Participants that started independently of the team after the store last saw them: their
    /// blocks are forgotten (their errors are uncorrelated with everyone's).
    pub(super) refreshed: Vec<PlatformId>,
    /// The members whose "no range" word carries that store: bystanders of the epoch.
    pub(super) bystanders: Vec<PlatformId>,
}

/// When the records of an epoch carry different store digests: the store, among theirs, that is
/// valid for every participant, if any. A store is valid for a participant when the reference
/// it holds for it is the participant's own (both saw the same last joint update of its Psi),
/// or when the participant started independently of the team after the store last saw it. The
/// store held by the most records wins (ties: the lowest digest); it must be held by two records
/// at least. Every node computes this from the records alone, so every node that holds the same
/// records makes the same choice.
pub(super) fn choose_store(records: &[StateRecord]) -> Option<StoreChoice> {
    let mut groups: BTreeMap<u64, Vec<&StateRecord>> = BTreeMap::new();
    for r in records {
        groups.entry(r.digest).or_default().push(r);
    }
    let mut best: Option<StoreChoice> = None;
    for (&digest, holders) in &groups {
        if holders.len() < 2 || best.as_ref().is_some_and(|b| b.members.len() >= holders.len()) {
            continue;
        }
        let refs: BTreeMap<PlatformId, StoreRef> = holders[0].refs.iter().copied().collect();
        let mut refreshed = Vec::new();
        let valid = records.iter().all(|r| {
            let id = r.snapshot.id;
            let held = refs.get(&id);
            if r.own_ref.is_fresh() {
                let stale = held.is_some_and(|h| h.epoch < r.own_ref.epoch);
                if stale {
                    refreshed.push(id);
                }
                held.is_none() || stale
            } else {
                held == Some(&r.own_ref)
            }
        });
        if valid {
            best = Some(StoreChoice {
                digest,
                members: holders.iter().map(|r| r.snapshot.id).collect(),
                refreshed,
                bystanders: Vec::new(),
            });
        }
    }
    best
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::protocol::record;
    use nalgebra::DMatrix;

    fn store(value: f64) -> CrossCovariances {
        CrossCovariances::from_parts(vec![((1, 2), DMatrix::from_element(2, 2, value))], Vec::new()).unwrap()
    }

    impl StoreSync {
        /// The fragments of `snap` as platform 2 sends them, named epoch `epoch`.
        fn series_of(snap: &StoreSnapshot, epoch: u32) -> Vec<Fragment> {
            let k = KeptStore { epoch, t: TimeUs(0), digest_before: snap.digest_before, store: snap.store.clone() };
            store_fragments(2, &k, snap.digest_before).unwrap().into_iter().map(|(_, f)| f).collect()
        }
    }

    fn request(epoch: u32) -> StoreRequest {
        StoreRequest { epoch, t: TimeUs(u64::from(epoch) * 1_000_000), digest_before: 77, members: vec![1, 2] }
    }

    /// A request from platform 3 (which did or did not run `epoch` with us).
    fn asked(epoch: u32, digest_before: u64, ran_with_us: bool) -> Asked {
        Asked { to: 3, epoch, digest_before, ran_with_us }
    }

    #[test]
    fn the_last_stores_are_kept_and_one_over_the_size_limit_is_not() {
        let mut s = StoreSync::new();
        for epoch in 1..=6 {
            s.keep(epoch, TimeUs(u64::from(epoch)), 100 + u64::from(epoch), &store(epoch as f64), 3);
        }
        assert_eq!(s.kept().collect::<Vec<_>>(), [(3, 103), (4, 104), (5, 105), (6, 106)]);
        // 60 platforms' 15-state blocks, 107 KB: more than one fragment series, kept.
        let blocks = (1..60u16).map(|i| ((i, i + 1), DMatrix::from_element(15, 15, 0.1))).collect();
        let large = CrossCovariances::from_parts(blocks, Vec::new()).unwrap();
        s.keep(7, TimeUs(7), 107, &large, 60);
        assert_eq!(s.kept().last(), Some((7, 107)));
        // 91 platforms' 4,095 blocks of 16 x 16, 8.4 MB: over the limit.
        let blocks = (1..=91u16).flat_map(|i| (i + 1..=91).map(move |j| ((i, j), DMatrix::from_element(16, 16, 0.1)))).collect();
        let huge = CrossCovariances::from_parts(blocks, Vec::new()).unwrap();
        s.keep(8, TimeUs(8), 108, &huge, 91);
        assert_eq!(s.kept().last(), Some((7, 107)));
    }

    #[test]
    fn the_two_participants_with_the_lowest_ids_answer() {
        assert_eq!([2, 5, 9].map(|me| answer_rank(&[2, 5, 9], me)), [Some(0), Some(1), None]);
        assert_eq!(answer_rank(&[9, 5, 2], 5), Some(1), "whatever the order");
        assert_eq!(answer_rank(&[2, 5, 9], 1), None, "not a participant");
        assert_eq!(answer_rank(&[4], 4), Some(0));
    }

    #[test]
    fn a_store_in_parts_is_kept_across_requests_and_taken_whole() {
        let blocks =
            (1..40u16).map(|i| ((i, i + 1), DMatrix::from_fn(16, 16, |r, c| (r * 16 + c) as f64 + f64::from(i)))).collect();
        let large = CrossCovariances::from_parts(blocks, Vec::new()).unwrap();
        let snap = StoreSnapshot { epoch: 5, digest_before: 77, store: large };
        let bytes = record::encode_store(&snap).unwrap();
        let parts = record::store_parts(&bytes, PART_LEN).unwrap();
        assert_eq!(parts.len(), 2, "{} bytes", bytes.len());
        let series = |from: PlatformId, k: usize| {
            let mut frags = fragment(from, 5, 5_000_000, &parts[k]).unwrap();
            frags.iter_mut().for_each(|f| f.payload = Payload::Store);
            frags
        };
        let mut s = StoreSync::new();
        s.want(request(5), 0);
        // The first answer, from 1, loses the first fragment of part 0 and two of part 1; the
        // request is repeated (what came is kept); then fragment 0 of part 0 comes from 2 (the
        // same store: its fragment fills 1's series) and the two of part 1 from 1 again.
        let (a0, a1) = (series(1, 0), series(1, 1));
        for f in a0.iter().skip(1).chain(a1.iter().skip(2)) {
            assert!(matches!(s.push_fragment(1, f, 0), Some(Pushed::Stored | Pushed::Duplicate)));
        }
        s.want(request(5), 400_000);
        assert_eq!(s.push_fragment(2, &series(2, 0)[0], 0), Some(Pushed::Stored), "part 0 whole with 2's fragment");
        let mut got = None;
        for f in a1.iter().take(2) {
            if let Some(Pushed::Complete(rec)) = s.push_fragment(1, f, 0) {
                got = Some(rec.bytes);
            }
        }
        assert_eq!(got.as_deref(), Some(&bytes[..]), "the parts kept across the second request");
        assert_eq!(record::decode_store(&got.unwrap()).unwrap(), snap);
    }

    #[test]
    fn a_store_goes_only_to_one_left_out_and_at_most_once_per_retry_interval() {
        let mut s = StoreSync::new();
        s.keep(5, TimeUs(5_000_000), 77, &store(0.5), 3);
        s.keep(6, TimeUs(6_000_000), 88, &store(0.6), 3);
        let retry = 300_000;
        let me = Answerer { id: 1, rank: 0, per_answer: 0 };
        assert!(s.answer(asked(5, 99, false), me, 0, retry).is_none(), "not under another digest");
        assert!(s.answer(asked(4, 77, false), me, 0, retry).is_none(), "not an epoch not kept");
        assert!(s.answer(asked(5, 77, true), me, 0, retry).is_none(), "not to one that ran the epoch with us");
        let frags = s.answer(asked(5, 77, false), me, 1_000_000, retry).expect("answered");
        let mut asker = StoreSync::new();
        asker.want(request(5), 0);
        let whole = frags.iter().find_map(|f| match asker.push_fragment(1, f, 0) {
            Some(Pushed::Complete(rec)) => Some(rec.bytes),
            _ => None,
        });
        let snap = record::decode_store(&whole.expect("the whole store in one answer")).unwrap();
        assert_eq!(
            (frags[0].time_usec, snap.epoch, snap.digest_before, snap.store.digest()),
            (5_000_000, 5, 77, store(0.5).digest())
        );
        s.sent(5, 1_000_000, 32);
        assert!(
            s.answer(asked(6, 88, false), me, 1_200_000, retry).is_none(),
            "one answer per retry interval, every epoch together"
        );
        assert!(s.answer(asked(6, 88, false), me, 1_300_000, retry).is_some());
        s.sent(6, 1_300_000, 32);
        s.sent(40, 2_000_000, 32);
        assert_eq!(s.sent_at.keys().copied().collect::<Vec<_>>(), [40], "epochs 32 behind forgotten");
    }

    #[test]
    fn a_left_out_node_waits_for_the_store_asks_again_and_gives_up() {
        let mut s = StoreSync::new();
        let (timeout, retry) = (1_000_000, 300_000);
        assert_eq!(s.awaiting(Some(5), 0, timeout, retry), Awaiting::No, "nothing wanted");
        s.want(request(5), 10_000_000);
        assert_eq!(s.awaiting(Some(5), 10_100_000, timeout, retry), Awaiting::Yes(None));
        assert_eq!(s.awaiting(Some(5), 10_300_000, timeout, retry), Awaiting::Yes(Some(request(5))), "asked again");
        assert_eq!(s.awaiting(Some(5), 10_400_000, timeout, retry), Awaiting::Yes(None));
        assert_eq!(s.awaiting(Some(5), 11_000_000, timeout, retry), Awaiting::No, "an epoch timeout after the first request");
        assert!(s.wanted.is_some(), "the store is still taken if it comes");
        assert_eq!(s.ask(Some(5), 11_000_000, timeout, retry), Some(request(5)), "and still asked for");
        assert_eq!(s.ask(Some(5), 11_100_000, timeout, retry), None, "every retry interval");
        assert_eq!(s.awaiting(Some(6), 11_100_000, timeout, retry), Awaiting::No);
        assert!(s.wanted.is_none(), "another epoch resolved (not one run without us): no store of epoch 5 helps now");

        // Nothing of the store came for two epoch timeouts: given up.
        s.want(request(7), 20_000_000);
        assert!(s.ask(Some(7), 21_900_000, timeout, retry).is_some());
        assert!(s.ask(Some(7), 22_000_000, timeout, retry).is_none());
        assert!(s.wanted.is_none(), "given up");
    }

    /// The left-out epochs that follow the store's keep a want alive, in order, while the store
    /// comes; another chain, or a want nothing came of, does not.
    #[test]
    fn a_store_still_coming_is_carried_on_through_the_epochs_run_without_us() {
        let (timeout, retry) = (1_000_000, 300_000);
        let later = |epoch| LaterEpoch { epoch, records: Vec::new(), refreshed: Vec::new(), bystanders: Vec::new() };
        let mut s = StoreSync::new();
        assert!(!s.carry_on(Some(5), later(6), 0, timeout), "nothing wanted");
        s.want(request(5), 10_000_000);
        assert!(!s.carry_on(Some(4), later(6), 10_500_000, timeout), "epoch 5 was not the last resolved before 6");
        assert!(s.carry_on(Some(5), later(6), 10_500_000, timeout));
        assert!(!s.carry_on(Some(5), later(7), 10_600_000, timeout), "6 is the chain's end now");
        assert_eq!(s.awaiting(Some(6), 10_600_000, timeout, retry), Awaiting::Yes(Some(request(5))), "epoch 6 keeps it alive");
        // A fragment of the store comes: the want lives on past the first timeout.
        let snap = StoreSnapshot { epoch: 5, digest_before: 77, store: store(0.5) };
        let mut frags = fragment(2, 5, 5_000_000, &record::encode_store(&snap).unwrap()).unwrap();
        frags.iter_mut().for_each(|f| f.payload = Payload::Store);
        assert!(s.push_fragment(2, &frags[0], 11_500_000).is_some());
        assert!(s.carry_on(Some(6), later(7), 11_900_000, timeout));
        assert!(s.ask(Some(7), 13_400_000, timeout, retry).is_some(), "two timeouts from the last fragment, not the request");
        let got = s.offered(2, &snap, Some(7)).expect("taken at the chain's end");
        assert_eq!(got.iter().map(|l| l.epoch).collect::<Vec<_>>(), [6, 7], "the epochs to bring it forward by, in order");

        // A want nothing came of in an epoch timeout: the next left-out epoch asks afresh.
        s.want(request(9), 30_000_000);
        assert!(!s.carry_on(Some(9), later(10), 31_000_000, timeout));
        // At most LATER_EPOCHS are kept.
        s.want(request(20), 40_000_000);
        assert!(s.push_fragment(2, &StoreSync::series_of(&snap, 20)[0], 40_000_000).is_some());
        for k in 0..LATER_EPOCHS as u32 {
            assert!(s.carry_on(Some(20 + k), later(21 + k), 40_000_001, timeout));
        }
        assert!(!s.carry_on(Some(20 + LATER_EPOCHS as u32), later(21 + LATER_EPOCHS as u32), 40_000_001, timeout));
    }

    /// Paced, each answer is the next fragments of the store, round and round; the second
    /// answerer starts half way through; a store being served is served on after newer ones
    /// pushed it out of the stores kept.
    #[test]
    fn a_paced_store_goes_a_few_fragments_an_answer_and_is_served_until_taken() {
        let blocks = (1..30u16).map(|i| ((i, i + 1), DMatrix::from_element(16, 16, f64::from(i)))).collect();
        let large = CrossCovariances::from_parts(blocks, Vec::new()).unwrap();
        let retry = 100_000;
        let (mut a, mut b) = (StoreSync::new(), StoreSync::new());
        a.keep(5, TimeUs(5_000_000), 77, &large, 30);
        b.keep(5, TimeUs(5_000_000), 77, &large, 30);
        let paced = |id, rank| Answerer { id, rank, per_answer: 20 };
        let mut asker = StoreSync::new();
        asker.want(request(5), 0);
        let (mut answers, mut whole) = (0, None);
        let mut first = Vec::new();
        for k in 0..100u64 {
            let wall = k * retry;
            for (s, id) in [(&mut a, 1), (&mut b, 2)] {
                let frags = s.answer(asked(5, 77, false), paced(id, usize::from(id) - 1), wall, retry).expect("served");
                assert!(frags.len() <= 20);
                if k == 0 {
                    first.push(frags[0].index);
                }
                s.sent(5, wall, 32);
                answers += 1;
                for f in &frags {
                    if let Some(Pushed::Complete(rec)) = asker.push_fragment(id, f, wall) {
                        whole = Some(rec.bytes);
                    }
                }
            }
            if whole.is_some() {
                break;
            }
            // newer stores push epoch 5 out of the kept ones: it is still served
            a.keep(6 + k as u32, TimeUs(6_000_000), 88, &store(0.1), 30);
        }
        assert_ne!(first[0], first[1], "the two answerers start at different fragments");
        let snap = record::decode_store(&whole.expect("the whole store")).unwrap();
        assert_eq!(snap.store.digest(), large.digest());
        let fragments = StoreSync::series_of(&StoreSnapshot { epoch: 5, digest_before: 77, store: large }, 5).len();
        assert!(answers * 20 < fragments + 40, "{answers} answers of 20 for {fragments} fragments: nothing sent twice");
        assert!(a.kept().all(|(e, _)| e != 5), "epoch 5 was served after it left the stores kept");
        // Nobody asks for 4 s: it is no longer served, nor kept.
        assert!(a.answer(asked(5, 77, false), paced(1, 0), 100 * retry + SERVE_IDLE_US, retry).is_none());
    }

    /// An asking node says what it holds before each repeated request (COOPLOC_STORE_HELD):
    /// the answerer sends only what it lacks, so that a fragment lost costs one resend, not a
    /// round of the whole store; with a second node asking that said nothing, everything goes.
    #[test]
    fn a_paced_answer_leaves_out_what_the_asking_node_holds() {
        let blocks = (1..30u16).map(|i| ((i, i + 1), DMatrix::from_element(16, 16, f64::from(i)))).collect();
        let large = CrossCovariances::from_parts(blocks, Vec::new()).unwrap();
        let retry = 100_000;
        let mut a = StoreSync::new();
        a.keep(5, TimeUs(5_000_000), 77, &large, 30);
        let me = Answerer { id: 1, rank: 0, per_answer: 20 };
        let all = StoreSync::series_of(&StoreSnapshot { epoch: 5, digest_before: 77, store: large.clone() }, 5);
        let fragments = all.len();
        assert!(fragments > 255, "{fragments}: two parts at least");
        let mut asker = StoreSync::new();
        asker.want(request(5), 0);
        assert!(asker.held(3).is_empty(), "nothing held: nothing to say");
        // Every third fragment of the first round is lost.
        let (mut sent, mut lost, mut whole, mut k) = (0, 0, None, 0u64);
        while whole.is_none() {
            assert!(k < 200, "the store never came whole");
            let wall = k * retry;
            for h in asker.held(3) {
                a.held_by(3, h);
            }
            let frags = a.answer(asked(5, 77, false), me, wall, retry).unwrap_or_default();
            a.sent(5, wall, 32);
            for f in &frags {
                sent += 1;
                if sent <= fragments && sent % 3 == 0 {
                    lost += 1;
                    continue;
                }
                match asker.push_fragment(1, f, wall) {
                    Some(Pushed::Complete(rec)) => whole = Some(rec.bytes),
                    Some(Pushed::Stored) => {}
                    other => panic!("fragment {} of a series sent again: {other:?}", f.index),
                }
            }
            k += 1;
        }
        assert_eq!(sent, fragments + lost, "every fragment once, and each one lost once more");
        assert_eq!(record::decode_store(&whole.unwrap()).unwrap().store.digest(), large.digest());

        // Two nodes ask: 3 says it holds the whole of part 0 and 4 says nothing: part 0 still goes.
        let mut b = StoreSync::new();
        b.keep(5, TimeUs(5_000_000), 77, &large, 30);
        let me = Answerer { per_answer: fragments, ..me };
        let part0 = StoreHeld {
            epoch: 5,
            t: TimeUs(5_000_000),
            announcer: 3,
            digest_before: 77,
            whole: wire::bits_at([0]),
            series: None,
        };
        assert_eq!(b.answer(asked(5, 77, false), me, 0, retry).map(|f| f.len()), Some(fragments), "nothing said yet");
        b.held_by(3, part0.clone());
        let four = Asked { to: 4, ..asked(5, 77, false) };
        assert_eq!(b.answer(four, me, retry, retry).map(|f| f.len()), Some(fragments), "4 said nothing: it lacks everything");
        b.held_by(3, part0.clone());
        b.held_by(4, StoreHeld { announcer: 4, ..part0.clone() });
        b.answer(asked(5, 77, false), me, 2 * retry, retry);
        let left = b.answer(four, me, 3 * retry, retry).expect("part 1");
        assert!(left.len() < fragments && left.iter().all(|f| f.record_crc32 != all[0].record_crc32), "part 0 left out");
        // A word on another store, or from a teammate that never asked, is not kept.
        b.held_by(9, part0.clone());
        b.held_by(3, StoreHeld { digest_before: 78, ..part0 });
        assert!(!b.serving[0].askers.contains_key(&9) && b.serving[0].askers[&3].pending.is_empty());
    }

    #[test]
    fn only_the_store_asked_for_from_a_participant_is_taken() {
        let mut s = StoreSync::new();
        let snap = StoreSnapshot { epoch: 5, digest_before: 77, store: store(0.5) };
        let bytes = record::encode_store(&snap).unwrap();
        let mut frags = fragment(2, 5, 5_000_000, &bytes).unwrap();
        for f in &mut frags {
            f.payload = Payload::Store;
        }
        assert!(s.push_fragment(2, &frags[0], 0).is_none(), "nothing asked for: not held");
        assert!(s.offered(2, &snap, Some(5)).is_none());
        s.want(request(5), 0);
        assert!(s.push_fragment(3, &frags[0], 0).is_none(), "3 did not run the epoch");
        let pushed: Vec<Pushed> = frags.iter().filter_map(|f| s.push_fragment(2, f, 0)).collect();
        assert!(matches!(pushed.last(), Some(Pushed::Complete(_))), "{pushed:?}");

        assert!(s.offered(3, &snap, Some(5)).is_none(), "not from a participant");
        assert!(s.offered(2, &StoreSnapshot { digest_before: 78, ..snap.clone() }, Some(5)).is_none(), "another digest");
        assert!(s.offered(2, &snap, Some(6)).is_none(), "another epoch resolved since");
        assert_eq!(s.offered(2, &snap, Some(5)), Some(Vec::new()));
        assert!(s.offered(2, &snap, Some(5)).is_none(), "once");
        assert_eq!(s.awaiting(Some(5), 1, 1_000_000, 300_000), Awaiting::No, "nothing to wait for once adopted");
    }

    /// A record of platform `id` holding the store `digest` with the references `refs`, its own
    /// Psi last reset by `own`.
    fn holder(id: PlatformId, digest: u64, own: StoreRef, refs: &[(PlatformId, StoreRef)]) -> StateRecord {
        use crate::estimation::{Geometry, Snapshot};
        StateRecord {
            snapshot: Snapshot {
                id,
                geometry: Geometry {
                    position_ned_m: nalgebra::Vector3::zeros(),
                    position_index: [Some(0), Some(1), None],
                    heading: None,
                },
                covariance: DMatrix::identity(3, 3),
                psi: DMatrix::identity(3, 3),
            },
            digest,
            own_ref: own,
            refs: refs.to_vec(),
            flags: 0,
            ranges: Vec::new(),
        }
    }

    #[test]
    fn the_store_chosen_is_the_largest_one_valid_for_every_participant() {
        let r = StoreRef::of_update(9, &[1, 2, 3], &[5, 5, 5]);
        let refs = [(1, r), (2, r), (3, r)];
        let all = [holder(1, 5, r, &refs), holder(2, 5, r, &refs), holder(3, 5, r, &refs)];
        let c = choose_store(&all).expect("one store");
        assert_eq!((c.digest, c.members, c.refreshed), (5, vec![1, 2, 3], vec![]));

        // Node 3 restarted (fresh, first heard at epoch 12, after the store last saw it at 9):
        // the others' store is still valid for it, its old blocks forgotten.
        let restarted = [holder(1, 5, r, &refs), holder(2, 5, r, &refs), holder(3, 0, StoreRef::fresh(12), &[])];
        let c = choose_store(&restarted).expect("the others' store");
        assert_eq!((c.digest, c.members, c.refreshed), (5, vec![1, 2], vec![3]));

        // Node 3 ran another update since (its Psi reset by it): the store does not know it.
        let other = StoreRef::of_update(10, &[3, 4], &[6, 6]);
        let diverged = [holder(1, 5, r, &refs), holder(2, 5, r, &refs), holder(3, 6, other, &[(3, other)])];
        assert!(choose_store(&diverged).is_none(), "no store valid for 3: everyone heals with the bound");

        // A store held by one record only is no choice; a larger valid group wins.
        let singles = [holder(1, 5, r, &refs), holder(2, 6, r, &refs), holder(3, 7, r, &refs)];
        assert!(choose_store(&singles).is_none());
        let refs4 = [(1, r), (2, r), (3, r), (4, r)];
        let groups = [
            holder(1, 5, r, &refs4),
            holder(2, 5, r, &refs4),
            holder(3, 8, r, &refs4),
            holder(4, 8, r, &refs4),
            holder(5, 8, StoreRef::fresh(3), &[]),
        ];
        let c = choose_store(&groups).expect("a store");
        assert_eq!((c.digest, c.members), (8, vec![3, 4, 5]));
    }
}
