//! Store synchronisation: how a node whose cross-covariance store diverged from its teammates'
//! gets theirs, and how it gives its own.
//!
//! A node *left out* of an epoch (its store not valid for the participants, see the core's
//! documentation) applies nothing and asks the participants for their store right after that
//! epoch (COOPLOC_EPOCH with STORE_WANTED). Its next broadcast waits for the store while one may
//! still come (an epoch timeout from the first request, and no other epoch resolved since),
//! asking again every retry interval. A participant answers with the store it kept after that
//! epoch (COOPLOC_STORE_FRAGMENT), only to a teammate that did not run the epoch with it, and at
//! most one store per retry interval in all: a request is a small message and a store a large
//! one, so nobody can make a node flood the network. Only the two participants with the lowest
//! ids answer (one answer may be lost; 63 copies of a 64-member team's 4 MB store would be a
//! flood of their own).
//!
//! A store goes as parts of at most [`PART_LEN`] bytes, each one fragment series
//! ([`crate::protocol::record::StorePart`]), so that a store of any size (up to
//! [`crate::protocol::record::MAX_STORE_LEN`]) can be sent: the asking node keeps every series
//! and every part that arrived, from either answerer (they hold the same store), while it still
//! wants the store, so that a repeated request fills what was lost instead of starting over.
//!
//! The asking node adopts a store only if it
//! asked for it, from a participant, nothing was resolved since, and it is valid for itself.
//!
//! This module holds the decisions and the state they need; the core sends and decodes.

use std::collections::{BTreeMap, VecDeque};

use crate::estimation::{CrossCovariances, PlatformId, StoreRef};
use crate::protocol::fragment::{Fragment, MAX_RECORD_LEN, PartPushed, Pushed, Reassembler, StoreAssembler};
use crate::protocol::record::{self, MAX_STORE_LEN, STORE_PART_HEADER, StateRecord, StoreSnapshot};
use crate::time::TimeUs;

/// Store snapshots kept for teammates that ask (the last epochs we took part in).
pub(super) const SNAPSHOTS_KEPT: usize = 4;
/// Snapshot bytes per part: a part and its header fill one fragment series.
pub(super) const PART_LEN: usize = MAX_RECORD_LEN - STORE_PART_HEADER;
/// Fragment series of a wanted store in progress at once (each at most 255 fragments).
const SERIES_IN_PROGRESS: usize = 256;
/// Participants that answer a request for a store: the ones with the lowest ids.
pub(super) const ANSWERERS: usize = 2;

/// Whether `me` answers a request for the store of the epoch `participants` ran: one of the
/// [`ANSWERERS`] lowest ids among them.
pub(super) fn answers(participants: &[PlatformId], me: PlatformId) -> bool {
    participants.contains(&me) && participants.iter().filter(|&&p| p < me).count() < ANSWERERS
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
    /// Wall time we asked first and last.
    since: u64,
    last_request: u64,
    /// The parts of the store that arrived.
    parts: StoreAssembler,
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
    wanted: Option<WantStore>,
    /// Wall time we last sent our store after each recent epoch.
    sent_at: BTreeMap<u32, u64>,
    reassembler: Reassembler,
}

impl StoreSync {
    pub(super) fn new() -> Self {
        Self {
            kept: VecDeque::new(),
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
        self.wanted = Some(WantStore { request, since: wall_us, last_request: wall_us, parts: StoreAssembler::default() });
    }

    /// Whether the next broadcast waits for the store we want: while `last_applied` (the last
    /// epoch resolved) is still its epoch and less than `timeout_us` passed since we first
    /// asked; the request is repeated every `retry_us`. Another epoch resolved since: the want
    /// is dropped.
    pub(super) fn awaiting(&mut self, last_applied: Option<u32>, wall_us: u64, timeout_us: u64, retry_us: u64) -> Awaiting {
        let Some(w) = self.wanted.as_mut() else { return Awaiting::No };
        let current = last_applied == Some(w.request.epoch);
        if !current {
            self.wanted = None;
            return Awaiting::No;
        }
        if wall_us >= w.since + timeout_us {
            return Awaiting::No;
        }
        if wall_us >= w.last_request + retry_us {
            w.last_request = wall_us;
            return Awaiting::Yes(Some(w.request.clone()));
        }
        Awaiting::Yes(None)
    }

    /// A fragment of a store from `from`: kept only when it is of the store we want, from one of
    /// its participants (nobody can make us hold another's bytes). None: not kept. Complete:
    /// the whole snapshot's bytes, from its parts (or in one series, as releases before parts
    /// sent it).
    pub(super) fn push_fragment(&mut self, from: PlatformId, f: &Fragment) -> Option<Pushed> {
        let w = self.wanted.as_mut()?;
        if w.request.epoch != f.epoch || !w.request.members.contains(&from) {
            return None;
        }
        let pushed = self.reassembler.push(f);
        self.reassembler.take_dropped();
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

    /// Our store after `epoch` for `to`, when we kept it (under that digest), `to` did not run
    /// the epoch with us, and we sent no store in the last `retry_us` (to anyone). Mark it
    /// [`Self::sent`] once it went.
    pub(super) fn answer(
        &self,
        epoch: u32,
        digest_before: u64,
        ran_with_us: bool,
        wall_us: u64,
        retry_us: u64,
    ) -> Option<(TimeUs, StoreSnapshot)> {
        let k = self.kept.iter().find(|k| k.epoch == epoch && k.digest_before == digest_before)?;
        let recently = self.sent_at.values().any(|&at| wall_us < at + retry_us);
        if ran_with_us || recently {
            return None;
        }
        Some((k.t, StoreSnapshot { epoch, digest_before, store: k.store.clone() }))
    }

    /// Our store after `epoch` went at `wall_us`; the epochs `remembered` before it are forgotten.
    pub(super) fn sent(&mut self, epoch: u32, wall_us: u64, remembered: u32) {
        self.sent_at.insert(epoch, wall_us);
        self.sent_at.retain(|e, _| e.saturating_add(remembered) > epoch);
    }

    /// A store offered by `from`: to be adopted when it is the one we asked for (its epoch, its
    /// digest before, from a participant), `last_applied` is still its epoch and it is
    /// `valid_for_us`. Adopting it ends the want.
    pub(super) fn offered(
        &mut self,
        from: PlatformId,
        snap: &StoreSnapshot,
        last_applied: Option<u32>,
        valid_for_us: bool,
    ) -> bool {
        let wanted = self.wanted.as_ref().is_some_and(|w| {
            w.request.epoch == snap.epoch && w.request.digest_before == snap.digest_before && w.request.members.contains(&from)
        });
        let adopt = wanted && last_applied == Some(snap.epoch) && valid_for_us;
        if adopt {
            self.wanted = None;
        }
        adopt
    }
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
            best = Some(StoreChoice { digest, members: holders.iter().map(|r| r.snapshot.id).collect(), refreshed });
        }
    }
    best
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::protocol::fragment::{Payload, fragment};
    use crate::protocol::record;
    use nalgebra::DMatrix;

    fn store(value: f64) -> CrossCovariances {
        CrossCovariances::from_parts(vec![((1, 2), DMatrix::from_element(2, 2, value))], Vec::new()).unwrap()
    }

    fn request(epoch: u32) -> StoreRequest {
        StoreRequest { epoch, t: TimeUs(u64::from(epoch) * 1_000_000), digest_before: 77, members: vec![1, 2] }
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
        assert!(answers(&[2, 5, 9], 2) && answers(&[2, 5, 9], 5) && !answers(&[2, 5, 9], 9));
        assert!(answers(&[9, 5, 2], 5), "whatever the order");
        assert!(!answers(&[2, 5, 9], 1), "not a participant");
        assert!(answers(&[4], 4));
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
        // request is repeated (what came is kept); then fragment 0 of part 0 comes again from 1
        // and part 1 whole from 2 (the same store: its part fits 1's).
        let (a0, a1) = (series(1, 0), series(1, 1));
        for f in a0.iter().skip(1).chain(a1.iter().skip(2)) {
            assert!(matches!(s.push_fragment(1, f), Some(Pushed::Stored | Pushed::Duplicate)));
        }
        s.want(request(5), 400_000);
        assert_eq!(s.push_fragment(2, &series(2, 0)[0]), Some(Pushed::Stored), "part 0 from 2, whole only with 2's own");
        let mut got = None;
        for f in series(1, 0).iter().take(1).chain(series(2, 1).iter()) {
            let from = if f.platform == 1 { 1 } else { 2 };
            if let Some(Pushed::Complete(rec)) = s.push_fragment(from, f) {
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
        assert!(s.answer(5, 99, false, 0, retry).is_none(), "not under another digest");
        assert!(s.answer(4, 77, false, 0, retry).is_none(), "not an epoch not kept");
        assert!(s.answer(5, 77, true, 0, retry).is_none(), "not to one that ran the epoch with us");
        let (t, snap) = s.answer(5, 77, false, 1_000_000, retry).expect("answered");
        assert_eq!((t, snap.epoch, snap.digest_before, snap.store.digest()), (TimeUs(5_000_000), 5, 77, store(0.5).digest()));
        s.sent(5, 1_000_000, 32);
        assert!(s.answer(6, 88, false, 1_200_000, retry).is_none(), "one store per retry interval, every epoch together");
        assert!(s.answer(6, 88, false, 1_300_000, retry).is_some());
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
        assert_eq!(s.awaiting(Some(6), 11_100_000, timeout, retry), Awaiting::No);
        assert!(s.wanted.is_none(), "another epoch resolved: no store of epoch 5 helps now");
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
        assert!(s.push_fragment(2, &frags[0]).is_none(), "nothing asked for: not held");
        assert!(!s.offered(2, &snap, Some(5), true));
        s.want(request(5), 0);
        assert!(s.push_fragment(3, &frags[0]).is_none(), "3 did not run the epoch");
        let pushed: Vec<Pushed> = frags.iter().filter_map(|f| s.push_fragment(2, f)).collect();
        assert!(matches!(pushed.last(), Some(Pushed::Complete(_))), "{pushed:?}");

        assert!(!s.offered(3, &snap, Some(5), true), "not from a participant");
        assert!(!s.offered(2, &StoreSnapshot { digest_before: 78, ..snap.clone() }, Some(5), true), "another digest");
        assert!(!s.offered(2, &snap, Some(6), true), "another epoch resolved since");
        assert!(!s.offered(2, &snap, Some(5), false), "not valid for us");
        assert!(s.offered(2, &snap, Some(5), true));
        assert!(!s.offered(2, &snap, Some(5), true), "once");
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
