//! The node's peer table: where its cooperative traffic goes. Sans-io (addresses and wall
//! times in, addresses out), bounded whatever the network sends.
//!
//! - **Given peers** (`--peer`) are kept for the whole run.
//! - **Team members** are learned from the frames they send: one address per member of the team
//!   (the last one a frame of theirs came from, so a restarted node on a new port is followed),
//!   never one for a system id outside the team. With a team key only signed frames get here.
//! - **Observers** (ground stations) are learned from their HEARTBEAT (MAV_TYPE_GCS): at most
//!   [`MAX_OBSERVERS`]; when the table is full a new one is refused (counted), never swapped
//!   for an old one, so a flood of heartbeats from many ports cannot take the slots of the
//!   ground station already listening.
//! - Learned addresses silent for [`PeerTable::expiry_us`] are forgotten.
//! - **On a multicast group** an address whose frames came through the group
//!   ([`PeerTable::heard_on_group`]) hears the group too: it is not also sent to by unicast (one
//!   copy per frame on the LAN), until it has been silent on the group for the expiry. A given
//!   peer that is never heard on the group (another subnet) is always sent to.
//!
//! So a frame sent to a node makes it send to at most `team - 1 + MAX_OBSERVERS + given`
//! addresses, and a stranger can make it send nothing it would not send anyway.

use std::collections::BTreeMap;
use std::net::SocketAddr;

use crate::estimation::PlatformId;

/// Most ground stations a node sends to besides its team and its given peers.
pub const MAX_OBSERVERS: usize = 4;
/// Learned addresses silent this long are forgotten (wall time, us).
pub const PEER_EXPIRY_US: u64 = 30_000_000;

/// What one received frame says about its sender.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Sender {
    /// A frame whose system id is a member of the team (not this node).
    Member(PlatformId),
    /// A ground station's HEARTBEAT.
    Observer,
    /// Anything else: not a reason to send to that address.
    Other,
}

/// What [`PeerTable::heard`] did.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Heard {
    /// A new address to send to.
    New,
    /// A member's address changed (it restarted on another port).
    Moved,
    /// Known already (its silence clock restarted), or a given peer.
    Known,
    /// The observer table is full.
    Refused,
    /// Not a peer.
    Ignored,
}

/// Counters of the table.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, serde::Serialize)]
pub struct PeerCounters {
    pub learned: u64,
    pub moved: u64,
    pub expired: u64,
    pub observers_refused: u64,
}

/// The peer table.
#[derive(Debug, Clone)]
pub struct PeerTable {
    given: Vec<SocketAddr>,
    team: Vec<PlatformId>,
    own: PlatformId,
    members: BTreeMap<PlatformId, (SocketAddr, u64)>,
    observers: BTreeMap<SocketAddr, u64>,
    /// Learned addresses heard on the multicast group, and when last.
    on_group: BTreeMap<SocketAddr, u64>,
    pub expiry_us: u64,
    pub counters: PeerCounters,
}

impl PeerTable {
    /// A table for node `own` of `team` that starts with the `given` peers.
    pub fn new(own: PlatformId, team: &[PlatformId], given: &[SocketAddr]) -> Self {
        let mut g = given.to_vec();
        g.sort();
        g.dedup();
        PeerTable {
            given: g,
            team: team.to_vec(),
            own,
            members: BTreeMap::new(),
            observers: BTreeMap::new(),
            on_group: BTreeMap::new(),
            expiry_us: PEER_EXPIRY_US,
            counters: PeerCounters::default(),
        }
    }

    /// Classifies a received frame's sender: `sysid`, and whether the frame is a ground
    /// station's HEARTBEAT.
    pub fn sender(&self, sysid: u32, gcs_heartbeat: bool) -> Sender {
        match PlatformId::try_from(sysid) {
            Ok(p) if p != self.own && self.team.contains(&p) => Sender::Member(p),
            _ if gcs_heartbeat => Sender::Observer,
            _ => Sender::Other,
        }
    }

    /// A frame from `sender` came from `addr` at wall time `now_us`.
    pub fn heard(&mut self, sender: Sender, addr: SocketAddr, now_us: u64) -> Heard {
        match sender {
            Sender::Member(p) => match self.members.insert(p, (addr, now_us)) {
                Some((old, _)) if old == addr => Heard::Known,
                Some(_) => {
                    self.counters.moved += 1;
                    Heard::Moved
                }
                None if self.given.contains(&addr) => Heard::Known,
                None => {
                    self.counters.learned += 1;
                    Heard::New
                }
            },
            Sender::Observer => {
                if let Some(at) = self.observers.get_mut(&addr) {
                    *at = now_us;
                    return Heard::Known;
                }
                if self.given.contains(&addr) {
                    return Heard::Known;
                }
                self.expire(now_us);
                if self.observers.len() >= MAX_OBSERVERS {
                    self.counters.observers_refused += 1;
                    return Heard::Refused;
                }
                self.observers.insert(addr, now_us);
                self.counters.learned += 1;
                Heard::New
            }
            Sender::Other => Heard::Ignored,
        }
    }

    /// The frame just [`heard`](Self::heard) from `addr` came through the multicast group:
    /// a peer that hears the group is not sent to by unicast.
    pub fn heard_on_group(&mut self, addr: SocketAddr, now_us: u64) {
        if self.known(&addr) {
            self.on_group.insert(addr, now_us);
        }
    }

    /// Forgets learned addresses silent for longer than the expiry.
    pub fn expire(&mut self, now_us: u64) {
        let expiry = self.expiry_us;
        let fresh = |at: u64| now_us.saturating_sub(at) <= expiry;
        let before = self.members.len() + self.observers.len();
        self.members.retain(|_, (_, at)| fresh(*at));
        self.observers.retain(|_, at| fresh(*at));
        self.counters.expired += (before - self.members.len() - self.observers.len()) as u64;
        let on_group = std::mem::take(&mut self.on_group);
        self.on_group = on_group.into_iter().filter(|(a, at)| fresh(*at) && self.known(a)).collect();
    }

    /// A given, member or observer address.
    fn known(&self, addr: &SocketAddr) -> bool {
        self.given.contains(addr) || self.members.values().any(|(a, _)| a == addr) || self.observers.contains_key(addr)
    }

    /// Every address to send to by unicast, each once: given, members, observers, less those
    /// that hear the multicast group.
    pub fn addresses(&self) -> Vec<SocketAddr> {
        let mut out = Vec::new();
        for a in self.given.iter().copied().chain(self.members.values().map(|(a, _)| *a)).chain(self.observers.keys().copied()) {
            if !out.contains(&a) && !self.on_group.contains_key(&a) {
                out.push(a);
            }
        }
        out
    }
}

/// Where a received run of frames came from.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Source {
    /// A unicast datagram from this address.
    Unicast(SocketAddr),
    /// A datagram to the multicast group, from this (the sender's unicast) address.
    Group(SocketAddr),
    /// The serial radio (no address: everyone on the channel hears everything).
    Radio,
}

impl Source {
    /// The sender's address, when there is one.
    pub fn addr(self) -> Option<SocketAddr> {
        match self {
            Source::Unicast(a) | Source::Group(a) => Some(a),
            Source::Radio => None,
        }
    }
}

impl std::fmt::Display for Source {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Source::Unicast(a) => write!(f, "{a}"),
            Source::Group(a) => write!(f, "{a} (group)"),
            Source::Radio => write!(f, "radio"),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn addr(port: u16) -> SocketAddr {
        SocketAddr::from(([127, 0, 0, 1], port))
    }

    fn table() -> PeerTable {
        PeerTable::new(1, &[1, 2, 3], &[addr(9000)])
    }

    #[test]
    fn members_are_learned_once_each_and_followed_when_they_move() {
        let mut t = table();
        assert_eq!(t.heard(t.sender(2, false), addr(5002), 0), Heard::New);
        assert_eq!(t.heard(t.sender(2, false), addr(5002), 10), Heard::Known);
        assert_eq!(t.heard(t.sender(2, false), addr(6002), 20), Heard::Moved);
        assert_eq!(t.addresses(), vec![addr(9000), addr(6002)], "one address per member: the last");
        assert_eq!(t.heard(t.sender(3, false), addr(9000), 20), Heard::Known, "a given peer is not learned twice");
        assert_eq!(t.addresses(), vec![addr(9000), addr(6002)]);
    }

    #[test]
    fn strangers_and_our_own_id_are_never_peers() {
        let mut t = table();
        for sysid in [1, 4, 200, 255, 70_000] {
            assert_eq!(t.heard(t.sender(sysid, false), addr(7000 + sysid as u16 % 1000), 0), Heard::Ignored, "sysid {sysid}");
        }
        assert_eq!(t.addresses(), vec![addr(9000)]);
    }

    #[test]
    fn a_heartbeat_flood_from_many_ports_takes_at_most_the_observer_slots() {
        let mut t = table();
        let gcs = t.sender(255, true);
        assert_eq!(t.heard(gcs, addr(14550), 0), Heard::New);
        for port in 20_000..20_500 {
            t.heard(gcs, addr(port), 1_000);
        }
        let a = t.addresses();
        assert_eq!(a.len(), 1 + MAX_OBSERVERS, "{a:?}");
        assert!(a.contains(&addr(14550)), "the ground station listening first keeps its slot");
        assert_eq!(t.counters.observers_refused, 500 - (MAX_OBSERVERS as u64 - 1));
        // A member is never crowded out by observers.
        assert_eq!(t.heard(t.sender(3, false), addr(5003), 1_000), Heard::New);
        assert!(t.addresses().contains(&addr(5003)));
    }

    #[test]
    fn silent_learned_addresses_expire_given_ones_stay() {
        let mut t = table();
        t.heard(t.sender(2, false), addr(5002), 0);
        t.heard(t.sender(255, true), addr(14550), 0);
        t.heard(t.sender(3, false), addr(5003), PEER_EXPIRY_US);
        t.expire(PEER_EXPIRY_US + 1);
        assert_eq!(t.addresses(), vec![addr(9000), addr(5003)]);
        assert_eq!(t.counters.expired, 2);
        // After expiry a flood's slots free up for a real ground station again.
        assert_eq!(t.heard(t.sender(255, true), addr(14550), PEER_EXPIRY_US + 2), Heard::New);
    }

    #[test]
    fn peers_that_hear_the_group_get_no_unicast_copy_until_they_fall_silent_on_it() {
        let mut t = table();
        t.heard(t.sender(2, false), addr(5002), 0);
        t.heard_on_group(addr(5002), 0);
        t.heard(t.sender(3, false), addr(5003), 0); // only by unicast (another subnet)
        t.heard(t.sender(255, true), addr(14550), 0);
        t.heard_on_group(addr(14550), 0);
        assert_eq!(t.addresses(), vec![addr(9000), addr(5003)], "the group carries 2 and the ground station");
        // A stranger's address on the group is not remembered.
        t.heard_on_group(addr(6666), 0);
        assert!(!t.on_group.contains_key(&addr(6666)));
        // A given peer heard on the group gets no unicast copy either.
        t.heard(t.sender(2, false), addr(9000), 1);
        t.heard_on_group(addr(9000), 1);
        assert!(!t.addresses().contains(&addr(9000)));
        // 2 keeps talking by unicast only (its group membership broke): after the expiry it is
        // sent to by unicast again.
        t.heard(t.sender(2, false), addr(5002), 2);
        t.heard(t.sender(2, false), addr(5002), PEER_EXPIRY_US + 10);
        t.expire(PEER_EXPIRY_US + 10);
        assert!(t.addresses().contains(&addr(5002)));
        assert!(t.addresses().contains(&addr(9000)), "silent on the group: the given peer is sent to again");
    }
}
