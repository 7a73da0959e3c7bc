//! The ground station's sans-io core: bytes and receive times in, tracks, statistics and
//! [`GcsEvent`]s out. No sockets and no clock; tested without either.
//!
//! - **Cooperative network** ([`GcsState::on_coop_datagram`]): every valid MAVLink 2 (or 1) frame
//!   of a datagram is counted against its source (sysid, compid) and its sender's address
//!   becomes a peer (as a node learns its peers). COOPLOC_ESTIMATE feeds the vehicle's track;
//!   COOPLOC_RANGE, COOPLOC_EPOCH and COOPLOC_STATE_FRAGMENT are counted and passed on.
//! - **Vehicle links** ([`GcsState::on_vehicle_frame`]): SIM_STATE of the vehicle's own system
//!   id is its truth, converted to the team's NED frame about [`GcsConfig::origin`]. SIM_STATE
//!   has no timestamp: a sample is stamped with the vehicle time of the next timed frame of the
//!   same link (HIGHRES_IMU or ODOMETRY), since a simulator sends the clock-driven messages due
//!   at `t` just before its samples at `t` (`cooploc sitl` does). HIGHRES_IMU is otherwise only
//!   counted.
//! - **Error against truth**: the horizontal distance between an estimate and the truth
//!   interpolated linearly at the estimate's time, and the 3-D position NEES
//!   `e^T P^-1 e`. Computed once the truth covers that time (bracketing samples at most
//!   [`GcsConfig::max_truth_gap_us`] apart).
//! - **Health** ([`GcsState::health`]): disagreements and healing from the COOPLOC_EPOCH
//!   reports ([`crate::view::health::EpochTally`]), and per node its estimate rate, its bytes per
//!   second against its share of `link_capacity_bytes_per_s`, its loss and whether its frames are
//!   signed.
//! - **Bad input** (a datagram without a valid frame, a message that fails the wire
//!   validation, an estimate claiming another platform's id) is counted and dropped, never a
//!   panic. A vehicle time that jumps back by more than [`GcsConfig::restart_us`] is a restarted
//!   source: its track starts over. A smaller step back is a stale message and is dropped.

use std::collections::{BTreeMap, BTreeSet, VecDeque};
use std::net::SocketAddr;

use mavlink_core::Message;
use nalgebra::{Matrix2, Vector3};
use serde::Serialize;

use super::link::{LinkStats, RateWindow, SourceKey};
pub use super::truth::{ErrorState, TruthError};
use super::truth::{Placed, TruthTrack};
use super::{GCS_COMPID, GCS_SYSID, GcsEvent, Link, TruthPoint, WallNs};
use crate::estimation::PlatformId;
use crate::protocol::MavMessage;
use crate::protocol::coop::CoopMessage;
use crate::protocol::signing::{SigningCounters, TeamKey, Verifier};
use crate::protocol::wire::{self, EstimateReport, GeoOrigin};
use crate::time::TimeUs;
use crate::view::VehicleStyle;
use crate::view::health::{EpochTally, HealthView, NodeHealth, signing_word};

pub use crate::estimation::consistency::{CHI2_2DOF_95, Ellipse95, ellipse95, position_nees};

/// Window of the estimate rate, ns.
pub const ESTIMATE_RATE_WINDOW_NS: u64 = 10_000_000_000;

/// Tuning of the ground station's memory and checks.
#[derive(Debug, Clone, PartialEq)]
pub struct GcsConfig {
    /// Where the team's NED origin sits (SIM_STATE latitude/longitude to NED).
    pub origin: GeoOrigin,
    /// Vehicles with a link of their own (known before they are heard).
    pub vehicles: Vec<PlatformId>,
    /// Estimates kept per vehicle.
    pub estimate_history: usize,
    /// Timed truth samples kept per vehicle.
    pub truth_history: usize,
    /// Window of the byte rates, ns.
    pub rate_window_ns: u64,
    /// Largest gap between two truth samples the error interpolates across, us.
    pub max_truth_gap_us: u64,
    /// A vehicle time this much earlier than the last is a restarted source, us.
    pub restart_us: u64,
    /// The team's signing key: only cooperative frames signed with it are read (see
    /// [`crate::protocol::signing`]); None: every valid frame is.
    pub team_key: Option<TeamKey>,
    /// Most vehicles shown; a new system id beyond them is refused (counted).
    pub max_vehicles: usize,
    /// Most (link, system, component) sources with statistics.
    pub max_sources: usize,
    /// Most learned peers (addresses heartbeats go to); silent ones expire after `peer_expiry_ns`.
    pub max_peers: usize,
    pub peer_expiry_ns: u64,
    /// Payload bytes per second the shared cooperative link carries (the health view shows
    /// each node's bytes against its share); None: not known.
    pub link_capacity_bytes_per_s: Option<f64>,
}

impl Default for GcsConfig {
    fn default() -> Self {
        GcsConfig {
            origin: GeoOrigin { lat_deg: 34.7, lon_deg: 0.0, alt_m: 0.0 },
            vehicles: Vec::new(),
            estimate_history: 4096,
            truth_history: 8192,
            rate_window_ns: 5_000_000_000,
            max_truth_gap_us: 1_000_000,
            restart_us: 5_000_000,
            team_key: None,
            max_vehicles: 64,
            max_sources: 1024,
            max_peers: 64,
            peer_expiry_ns: 30_000_000_000,
            link_capacity_bytes_per_s: None,
        }
    }
}

/// Whole-station counters.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize)]
pub struct GcsCounters {
    /// Datagrams from the cooperative network and frames read from vehicle links.
    pub datagrams: u64,
    pub bytes: u64,
    /// Valid MAVLink frames.
    pub frames: u64,
    /// Datagrams with no valid MAVLink frame.
    pub bad_datagrams: u64,
    /// Valid frames whose message failed the wire validation (or claimed another platform).
    pub rejected: u64,
    /// Stale messages (vehicle time going back a little) and frames from other systems on a
    /// vehicle link.
    pub ignored: u64,
    /// Our own frames seen again (looped back).
    pub own: u64,
    /// Cooperative frames refused by signing (unsigned, another key, replayed, stale).
    pub unauthenticated: u64,
    /// Messages of a new vehicle beyond `max_vehicles`, frames of a new source beyond
    /// `max_sources`, new peers beyond `max_peers`: dropped, so no sender can grow the tables.
    pub vehicles_refused: u64,
    pub sources_refused: u64,
    pub peers_refused: u64,
}

/// An estimate as kept in a vehicle's history.
#[derive(Debug, Clone, PartialEq)]
pub struct EstimatePoint {
    pub rx: WallNs,
    pub report: EstimateReport,
    pub ellipse: Option<Ellipse95>,
    pub error: ErrorState,
}

/// Per-vehicle counters.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize)]
pub struct VehicleCounts {
    pub estimates: u64,
    pub stale_estimates: u64,
    pub restarts: u64,
    pub state_fragments: u64,
    /// Store snapshot fragments (COOPLOC_STORE_FRAGMENT): the node healing a teammate.
    pub store_fragments: u64,
    pub ranges: u64,
    pub epochs: u64,
    /// Frames of its own vehicle link, all messages.
    pub link_frames: u64,
    pub link_imu_frames: u64,
    pub truth_samples: u64,
    pub stale_truth: u64,
}

/// What the ground station knows of one vehicle.
#[derive(Debug, Clone)]
pub struct Vehicle {
    pub id: PlatformId,
    /// Has a truth link (`--vehicle`).
    pub has_link: bool,
    pub estimates: VecDeque<EstimatePoint>,
    /// Its truth (SIM_STATE stamped by the link's timed frames): [`super::truth`].
    pub truth: TruthTrack,
    /// When the first estimate came, and the estimates received over the rate window (one
    /// "byte" each).
    estimate_rate: Option<(WallNs, RateWindow)>,
    pub counts: VehicleCounts,
}

impl Vehicle {
    fn new(id: PlatformId, config: &GcsConfig) -> Self {
        Vehicle {
            id,
            has_link: false,
            estimates: VecDeque::new(),
            truth: TruthTrack::new(config.truth_history, config.restart_us, config.max_truth_gap_us),
            estimate_rate: None,
            counts: VehicleCounts::default(),
        }
    }

    pub fn latest_estimate(&self) -> Option<&EstimatePoint> {
        self.estimates.back()
    }

    /// The truth position at `t`, interpolated linearly between the bracketing samples;
    /// `None` outside the truth's span.
    pub fn truth_at(&self, t: TimeUs) -> Option<Vector3<f64>> {
        self.truth.truth_at(t)
    }
}

/// The ground station's state.
#[derive(Debug, Clone)]
pub struct GcsState {
    config: GcsConfig,
    started: Option<WallNs>,
    pub vehicles: BTreeMap<PlatformId, Vehicle>,
    pub links: BTreeMap<SourceKey, LinkStats>,
    /// Given peers (kept) and learned ones with the time they were last heard (expiring).
    given_peers: BTreeSet<SocketAddr>,
    peers: BTreeMap<SocketAddr, WallNs>,
    verifier: Option<Verifier>,
    /// Disagreements and healing, from the nodes' epoch reports.
    pub tally: EpochTally,
    pub counters: GcsCounters,
}

fn message_name(m: &Result<MavMessage, String>) -> &'static str {
    match m {
        Ok(m) => m.message_name(),
        Err(_) => "UNPARSED",
    }
}

impl GcsState {
    pub fn new(config: GcsConfig) -> Self {
        let mut vehicles = BTreeMap::new();
        for &id in &config.vehicles {
            let mut v = Vehicle::new(id, &config);
            v.has_link = true;
            vehicles.insert(id, v);
        }
        let verifier = config.team_key.clone().map(Verifier::new);
        GcsState {
            config,
            started: None,
            vehicles,
            links: BTreeMap::new(),
            given_peers: BTreeSet::new(),
            peers: BTreeMap::new(),
            verifier,
            tally: EpochTally::new(),
            counters: GcsCounters::default(),
        }
    }

    pub fn config(&self) -> &GcsConfig {
        &self.config
    }

    /// Peers of the cooperative network: given ones and the addresses valid (with a team key:
    /// signed) frames came from recently, at most `max_peers` of those.
    pub fn peers(&self) -> impl Iterator<Item = SocketAddr> + '_ {
        self.given_peers.iter().copied().chain(self.peers.keys().copied().filter(|a| !self.given_peers.contains(a)))
    }

    /// Adds a given peer (never expires); true if it is new.
    pub fn add_peer(&mut self, addr: SocketAddr) -> bool {
        self.given_peers.insert(addr)
    }

    /// What signing accepted and refused (None without a team key).
    pub fn signing(&self) -> Option<&SigningCounters> {
        self.verifier.as_ref().map(|v| &v.counters)
    }

    /// Forgets learned peers silent for longer than `peer_expiry_ns`.
    pub fn expire_peers(&mut self, now: WallNs) {
        let expiry = self.config.peer_expiry_ns;
        self.peers.retain(|_, at| now.0.saturating_sub(at.0) <= expiry);
    }

    fn learn_peer(&mut self, addr: SocketAddr, rx: WallNs) {
        if let Some(at) = self.peers.get_mut(&addr) {
            *at = rx;
            return;
        }
        if self.given_peers.contains(&addr) {
            return;
        }
        self.expire_peers(rx);
        if self.peers.len() >= self.config.max_peers {
            self.counters.peers_refused += 1;
            return;
        }
        self.peers.insert(addr, rx);
    }

    /// Whether `id` has (or may now get) a place in the vehicle table.
    fn admit(&mut self, id: PlatformId) -> bool {
        if self.vehicles.contains_key(&id) {
            return true;
        }
        if self.vehicles.len() >= self.config.max_vehicles {
            self.counters.vehicles_refused += 1;
            return false;
        }
        let v = Vehicle::new(id, &self.config);
        self.vehicles.insert(id, v);
        true
    }

    /// Marks the start (for the uptime); the first input does it otherwise.
    pub fn start(&mut self, rx: WallNs) {
        self.started.get_or_insert(rx);
    }

    fn vehicle(&mut self, id: PlatformId) -> &mut Vehicle {
        let config = &self.config;
        self.vehicles.entry(id).or_insert_with(|| Vehicle::new(id, config))
    }

    /// A datagram from the cooperative network.
    pub fn on_coop_datagram(&mut self, rx: WallNs, from: SocketAddr, bytes: &[u8]) -> Vec<GcsEvent> {
        self.on_bytes(rx, Link::Coop, Some(from), bytes)
    }

    /// A frame (or any bytes) read from the link of vehicle `vehicle`.
    pub fn on_vehicle_frame(&mut self, rx: WallNs, vehicle: PlatformId, bytes: &[u8]) -> Vec<GcsEvent> {
        self.on_bytes(rx, Link::Vehicle(vehicle), None, bytes)
    }

    fn on_bytes(&mut self, rx: WallNs, link: Link, from: Option<SocketAddr>, bytes: &[u8]) -> Vec<GcsEvent> {
        self.start(rx);
        self.counters.datagrams += 1;
        self.counters.bytes += bytes.len() as u64;
        // With a team key only signed cooperative frames are read, as the nodes do.
        let accepted: Vec<u8>;
        let bytes = match (&mut self.verifier, link) {
            (Some(v), Link::Coop) => {
                let got = v.datagram(bytes, rx.0 / 1000);
                self.counters.unauthenticated += got.refused.len() as u64;
                if got.spans.is_empty() {
                    return vec![GcsEvent::Rejected {
                        rx,
                        link,
                        reason: format!("no frame signed with the team key: {:?}", got.refused),
                    }];
                }
                accepted = got.spans.iter().flat_map(|r| bytes[r.clone()].iter().copied()).collect();
                &accepted[..]
            }
            _ => bytes,
        };
        let mut events = Vec::new();
        let mut found = false;
        for f in crate::protocol::framing::frames(bytes) {
            found = true;
            let (sysid, compid, seq, message_id) = (f.header.system_id, f.header.component_id, f.header.sequence, f.message_id);
            self.counters.frames += 1;
            if sysid == u32::from(GCS_SYSID) && compid == GCS_COMPID {
                self.counters.own += 1;
                continue;
            }
            let window = self.config.rate_window_ns;
            let key = SourceKey { link, sysid, compid };
            if !self.links.contains_key(&key) && self.links.len() >= self.config.max_sources {
                self.counters.sources_refused += 1;
            } else {
                let stats = self.links.entry(key).or_insert_with(|| LinkStats::new(rx, window));
                stats.observe(rx, seq, f.bytes.len(), message_name(&f.message), from, f.signed);
            }
            if let (Link::Coop, Some(addr)) = (link, from) {
                self.learn_peer(addr, rx);
            }
            events.push(GcsEvent::Frame { rx, link, from, sysid, compid, message_id, bytes: f.bytes.to_vec() });
            let message = match f.message {
                Ok(m) => m,
                Err(e) => {
                    self.reject(rx, link, format!("message {message_id} from {sysid}/{compid}: {e}"), &mut events);
                    continue;
                }
            };
            if let MavMessage::HEARTBEAT(hb) = &message
                && let Some(stats) = self.links.get_mut(&SourceKey { link, sysid, compid })
            {
                stats.mav_type = Some(format!("{:?}", hb.mavtype).trim_start_matches("MAV_TYPE_").to_string());
            }
            match link {
                Link::Coop => self.on_coop_message(rx, sysid, message, &mut events),
                Link::Vehicle(id) => self.on_vehicle_message(rx, id, sysid, message, &mut events),
            }
        }
        if !found {
            self.counters.bad_datagrams += 1;
            events.push(GcsEvent::Rejected { rx, link, reason: format!("{} bytes without a valid MAVLink frame", bytes.len()) });
        }
        events
    }

    fn reject(&mut self, rx: WallNs, link: Link, reason: String, events: &mut Vec<GcsEvent>) {
        self.counters.rejected += 1;
        events.push(GcsEvent::Rejected { rx, link, reason });
    }

    fn on_coop_message(&mut self, rx: WallNs, sysid: u32, message: MavMessage, events: &mut Vec<GcsEvent>) {
        let Some(decoded) = CoopMessage::decode(&message) else { return };
        let m = match decoded {
            Ok(m) => m,
            Err(e) => return self.reject(rx, Link::Coop, e.to_string(), events),
        };
        if let Some(claimed) = m.claimed_sender()
            && u32::from(claimed) != sysid
        {
            let reason = format!("{} of platform {claimed} sent by system {sysid}", m.kind().name());
            return self.reject(rx, Link::Coop, reason, events);
        }
        match m {
            CoopMessage::Estimate(report) => self.on_estimate(rx, report, events),
            CoopMessage::Range { epoch, range } => {
                if self.admit(range.from) {
                    self.vehicle(range.from).counts.ranges += 1;
                    events.push(GcsEvent::Range { rx, epoch, range });
                }
            }
            CoopMessage::Epoch(announcement) => {
                if self.admit(announcement.announcer) {
                    self.vehicle(announcement.announcer).counts.epochs += 1;
                    self.tally.on_epoch(&announcement);
                    events.push(GcsEvent::Epoch { rx, announcement });
                }
            }
            CoopMessage::StateFragment(f) => {
                if self.admit(f.platform) {
                    self.vehicle(f.platform).counts.state_fragments += 1;
                }
            }
            CoopMessage::StoreFragment(f) => {
                if self.admit(f.platform) {
                    self.vehicle(f.platform).counts.store_fragments += 1;
                }
            }
            // (a ground station's request to a node, and what a node asking for a store holds of
            // it: nothing for this one)
            CoopMessage::MessageRequest(_) | CoopMessage::StoreHeld(_) => {}
        }
    }

    fn on_estimate(&mut self, rx: WallNs, report: EstimateReport, events: &mut Vec<GcsEvent>) {
        let (history, restart_us) = (self.config.estimate_history, self.config.restart_us);
        if !self.admit(report.platform) {
            return;
        }
        let v = self.vehicle(report.platform);
        if let Some(last) = v.estimates.back().map(|e| e.report.t)
            && report.t < last
        {
            if last.0 - report.t.0 > restart_us {
                v.counts.restarts += 1;
                v.estimates.clear();
            } else {
                v.counts.stale_estimates += 1;
                self.counters.ignored += 1;
                return;
            }
        }
        let c = &report.position_covariance_m2;
        let ellipse = ellipse95(&Matrix2::new(c[(0, 0)], c[(0, 1)], c[(1, 0)], c[(1, 1)]));
        v.counts.estimates += 1;
        v.estimate_rate.get_or_insert_with(|| (rx, RateWindow::new(ESTIMATE_RATE_WINDOW_NS))).1.push(rx, 1);
        let vehicle = report.platform;
        events.push(GcsEvent::Estimate { rx, vehicle, report: report.clone(), ellipse });
        v.estimates.push_back(EstimatePoint { rx, report, ellipse, error: ErrorState::Pending });
        while v.estimates.len() > history.max(1) {
            v.estimates.pop_front();
        }
        resolve_errors(v, rx, events);
    }

    fn on_vehicle_message(&mut self, rx: WallNs, id: PlatformId, sysid: u32, message: MavMessage, events: &mut Vec<GcsEvent>) {
        if sysid != u32::from(id) {
            self.counters.ignored += 1;
            return;
        }
        let origin = self.config.origin;
        let v = self.vehicle(id);
        v.has_link = true;
        v.counts.link_frames += 1;
        let timed = match &message {
            MavMessage::HIGHRES_IMU(m) => {
                v.counts.link_imu_frames += 1;
                Some(TimeUs(m.time_usec))
            }
            MavMessage::ODOMETRY(m) => Some(TimeUs(m.time_usec)),
            MavMessage::SIM_STATE(m) => {
                let truth = match wire::sim_state_from_message(m, &origin) {
                    Ok(t) => t,
                    Err(e) => {
                        self.reject(rx, Link::Vehicle(id), e.to_string(), events);
                        return;
                    }
                };
                let point = TruthPoint {
                    t: None,
                    rx,
                    pos_ned_m: truth.pos_ned_m,
                    vel_ned_m_s: truth.vel_ned_m_s,
                    yaw_rad: truth.yaw_rad,
                };
                // A sample still waiting for its time is placed at the last known time.
                let placed = self.vehicle(id).truth.sim_state(point);
                self.placed(rx, id, placed, events);
                None
            }
            _ => None,
        };
        if let Some(t) = timed {
            let placed = self.vehicle(id).truth.timed(t);
            self.placed(rx, id, placed, events);
        }
    }

    /// Counts what became of a truth sample, says so, and resolves the errors it allows.
    fn placed(&mut self, rx: WallNs, id: PlatformId, placed: Option<Placed>, events: &mut Vec<GcsEvent>) {
        let v = self.vehicle(id);
        match placed {
            None => {}
            Some(Placed::Stale) => {
                v.counts.stale_truth += 1;
                self.counters.ignored += 1;
            }
            Some(Placed::Untimed(point)) => {
                v.counts.truth_samples += 1;
                events.push(GcsEvent::Truth { rx, vehicle: id, point });
            }
            Some(Placed::Timed { point, restarted }) => {
                v.counts.truth_samples += 1;
                v.counts.restarts += u64::from(restarted);
                events.push(GcsEvent::Truth { rx, vehicle: id, point });
                resolve_errors(v, rx, events);
            }
        }
    }

    /// The team's health now: disagreements and healing from the epoch reports, and per node
    /// its estimate rate, its bytes per second against its share of the link, its loss and its
    /// signing (the node's frames on the cooperative network, every component of its system).
    pub fn health(&self, now: WallNs) -> HealthView {
        let capacity = self.config.link_capacity_bytes_per_s.filter(|c| c.is_finite() && *c > 0.0);
        let share = capacity.map(|c| c / self.vehicles.len().max(1) as f64);
        let nodes: Vec<NodeHealth> = self
            .vehicles
            .values()
            .map(|v| {
                let sources = self.links.iter().filter(|(k, _)| k.link == Link::Coop && k.sysid == u32::from(v.id));
                let (mut bytes_per_s, mut signed, mut unsigned, mut lost, mut received) = (0.0, 0, 0, 0, 0);
                for (_, s) in sources {
                    bytes_per_s += s.rate.bytes_per_s(now, s.first_heard);
                    (signed, unsigned) = (signed + s.signed, unsigned + s.unsigned);
                    (lost, received) = (lost + s.seq.lost, received + s.seq.received);
                }
                let style = VehicleStyle::of(v.id);
                NodeHealth {
                    id: v.id,
                    name: style.name,
                    color: style.color,
                    estimate_rate_hz: v
                        .estimate_rate
                        .as_ref()
                        .filter(|_| v.counts.estimates >= 2)
                        .map(|(first, w)| w.bytes_per_s(now, *first)),
                    bytes_per_s,
                    budget_bytes_per_s: share,
                    budget_used_pct: share.map(|b| 100.0 * bytes_per_s / b),
                    loss_pct: (received >= 2).then(|| 100.0 * lost as f64 / (received + lost) as f64),
                    signed_frames: signed,
                    unsigned_frames: unsigned,
                    signing: signing_word(signed, unsigned),
                    epochs: self.tally.nodes.get(&v.id).copied().unwrap_or_default(),
                }
            })
            .collect();
        let team_bytes_per_s: f64 = nodes.iter().map(|n| n.bytes_per_s).sum();
        HealthView {
            rx_ns: now.0,
            last_epoch: self.tally.last_epoch,
            disagreements: self.tally.disagreements,
            heals: self.tally.heals,
            unhealed_since: self.tally.unhealed_since,
            link_capacity_bytes_per_s: capacity,
            team_bytes_per_s,
            team_load_pct: capacity.map(|c| 100.0 * team_bytes_per_s / c),
            verifying: self.verifier.is_some(),
            nodes,
        }
    }

    /// The JSON the web page polls. Series are thinned to at most `max_points` points each.
    pub fn snapshot(&self, now: WallNs, max_points: usize) -> StateJson {
        let since = |t: WallNs| now.0.saturating_sub(t.0) as f64 * 1e-9;
        let vehicles = self.vehicles.values().map(|v| vehicle_json(v, now, max_points)).collect();
        let links = self
            .links
            .iter()
            .map(|(k, s)| LinkJson {
                link: k.link.to_string(),
                sysid: k.sysid,
                compid: k.compid,
                addr: s.last_addr.map(|a| a.to_string()),
                mav_type: s.mav_type.clone(),
                packets: s.packets,
                bytes: s.bytes,
                bytes_per_s: s.rate.bytes_per_s(now, s.first_heard),
                lost: s.seq.lost,
                late: s.seq.late,
                restarts: s.seq.restarts,
                loss_pct: s.seq.loss_fraction().map(|f| f * 100.0),
                last_heard_s_ago: since(s.last_heard),
                messages: s.messages.iter().map(|(k, v)| (k.to_string(), *v)).collect(),
            })
            .collect();
        StateJson {
            gcs: GcsInfo {
                sysid: GCS_SYSID,
                compid: GCS_COMPID,
                uptime_s: self.started.map_or(0.0, since),
                peers: self.peers().map(|p| p.to_string()).collect(),
                signing: self.signing().cloned(),
            },
            origin: OriginJson {
                lat_deg: self.config.origin.lat_deg,
                lon_deg: self.config.origin.lon_deg,
                alt_m: self.config.origin.alt_m,
            },
            counters: self.counters,
            health: self.health(now),
            vehicles,
            links,
        }
    }
}

/// Computes the errors of the newest estimates that the truth now covers.
fn resolve_errors(v: &mut Vehicle, rx: WallNs, events: &mut Vec<GcsEvent>) {
    if v.truth.end().is_none() {
        return;
    }
    let start = v.truth.start();
    let mut found = Vec::new();
    for e in v.estimates.iter_mut().rev() {
        if !matches!(e.error, ErrorState::Pending) {
            break;
        }
        let t = e.report.t;
        e.error = v.truth.judge(t, &e.report.position_ned_m, &e.report.position_covariance_m2);
        match e.error {
            ErrorState::Pending => continue,
            ErrorState::Known(error) => found.push((t, error)),
            ErrorState::Unavailable => {
                if start.is_some_and(|t0| t < t0) {
                    break; // older estimates are before the truth too
                }
            }
        }
    }
    for (t, error) in found.into_iter().rev() {
        events.push(GcsEvent::Error { rx, vehicle: v.id, t, error });
    }
}

/// At most `max` items of `items`, evenly spaced, the last one always included.
fn thin<T>(items: Vec<T>, max: usize) -> Vec<T> {
    let n = items.len();
    if n <= max.max(2) {
        return items;
    }
    let step = n.div_ceil(max.max(2) - 1);
    items.into_iter().enumerate().filter(|(i, _)| i % step == 0 || *i == n - 1).map(|(_, x)| x).collect()
}

fn vehicle_json(v: &Vehicle, now: WallNs, max_points: usize) -> VehicleJson {
    let estimate = v.latest_estimate().map(|e| {
        let r = &e.report;
        let c = &r.position_covariance_m2;
        EstimateJson {
            t_s: r.t.as_secs_f64(),
            epoch: r.epoch,
            method: r.method.short_name(),
            pos_ned_m: [r.position_ned_m[0], r.position_ned_m[1], r.position_ned_m[2]],
            vel_ned_m_s: [r.velocity_ned_m_s[0], r.velocity_ned_m_s[1], r.velocity_ned_m_s[2]],
            yaw_deg: r.yaw_rad.to_degrees(),
            cov_ne_m2: [c[(0, 0)], c[(0, 1)], c[(1, 1)]],
            sigma_d_m: c[(2, 2)].max(0.0).sqrt(),
            nis: r.nis,
            participants: r.participants,
            ranges: r.ranges,
            ellipse95: e.ellipse,
            age_s: now.0.saturating_sub(e.rx.0) as f64 * 1e-9,
        }
    });
    let latest_error = v.estimates.iter().rev().find_map(|e| match e.error {
        ErrorState::Known(err) => Some(ErrorJson {
            t_s: e.report.t.as_secs_f64(),
            horizontal_m: err.horizontal_m,
            nees: err.nees,
            truth_ned_m: [err.truth_ned_m[0], err.truth_ned_m[1], err.truth_ned_m[2]],
        }),
        _ => None,
    });
    let track = v.estimates.iter().map(|e| [e.report.t.as_secs_f64(), e.report.position_ned_m[0], e.report.position_ned_m[1]]);
    let errors = v
        .estimates
        .iter()
        .filter_map(|e| match e.error {
            ErrorState::Known(err) => Some([e.report.t.as_secs_f64(), err.horizontal_m, err.nees.unwrap_or(f64::NAN)]),
            _ => None,
        })
        .collect();
    let sigma = v.estimates.iter().filter_map(|e| e.ellipse.map(|el| [e.report.t.as_secs_f64(), el.semi_major_m])).collect();
    let truth_src = if v.truth.samples().is_empty() { v.truth.untimed() } else { v.truth.samples() };
    let truth_track =
        truth_src.iter().map(|p| [p.t.map_or(f64::NAN, |t| t.as_secs_f64()), p.pos_ned_m[0], p.pos_ned_m[1]]).collect();
    let truth = truth_src.back().map(|p| TruthJson {
        t_s: p.t.map(|t| t.as_secs_f64()),
        pos_ned_m: [p.pos_ned_m[0], p.pos_ned_m[1], p.pos_ned_m[2]],
        yaw_deg: p.yaw_rad.to_degrees(),
        speed_m_s: p.vel_ned_m_s.norm(),
    });
    VehicleJson {
        id: v.id,
        style: VehicleStyle::of(v.id),
        has_link: v.has_link,
        estimate,
        error: latest_error,
        truth,
        track: thin(track.collect(), max_points),
        truth_track: thin(truth_track, max_points),
        errors: thin(errors, max_points),
        sigma95: thin(sigma, max_points),
        counts: v.counts,
    }
}

// ---- the JSON of `GET /api/state` ----

#[derive(Debug, Clone, Serialize)]
pub struct StateJson {
    pub gcs: GcsInfo,
    pub origin: OriginJson,
    pub counters: GcsCounters,
    pub health: HealthView,
    pub vehicles: Vec<VehicleJson>,
    pub links: Vec<LinkJson>,
}

#[derive(Debug, Clone, Serialize)]
pub struct GcsInfo {
    pub sysid: u8,
    pub compid: u8,
    pub uptime_s: f64,
    pub peers: Vec<String>,
    /// What signing accepted and refused; null without a team key.
    pub signing: Option<SigningCounters>,
}

#[derive(Debug, Clone, Serialize)]
pub struct OriginJson {
    pub lat_deg: f64,
    pub lon_deg: f64,
    pub alt_m: f64,
}

#[derive(Debug, Clone, Serialize)]
pub struct VehicleJson {
    pub id: PlatformId,
    /// Name and colour, as every display shows them.
    pub style: VehicleStyle,
    pub has_link: bool,
    pub estimate: Option<EstimateJson>,
    /// Error of the newest estimate the truth covers.
    pub error: Option<ErrorJson>,
    /// Newest truth sample.
    pub truth: Option<TruthJson>,
    /// Estimates: `[t_s, north_m, east_m]`.
    pub track: Vec<[f64; 3]>,
    /// Truth: `[t_s (null if unknown), north_m, east_m]`.
    pub truth_track: Vec<[f64; 3]>,
    /// `[t_s, horizontal_error_m, position_nees (null if unknown)]`.
    pub errors: Vec<[f64; 3]>,
    /// `[t_s, semi_major_95_m]`.
    pub sigma95: Vec<[f64; 2]>,
    pub counts: VehicleCounts,
}

#[derive(Debug, Clone, Serialize)]
pub struct EstimateJson {
    pub t_s: f64,
    pub epoch: u32,
    pub method: &'static str,
    pub pos_ned_m: [f64; 3],
    pub vel_ned_m_s: [f64; 3],
    pub yaw_deg: f64,
    /// NN, NE, EE.
    pub cov_ne_m2: [f64; 3],
    pub sigma_d_m: f64,
    /// NaN (none yet) is null.
    pub nis: f64,
    pub participants: u8,
    pub ranges: u8,
    pub ellipse95: Option<Ellipse95>,
    /// Seconds since it was received.
    pub age_s: f64,
}

#[derive(Debug, Clone, Serialize)]
pub struct ErrorJson {
    pub t_s: f64,
    pub horizontal_m: f64,
    pub nees: Option<f64>,
    pub truth_ned_m: [f64; 3],
}

#[derive(Debug, Clone, Serialize)]
pub struct TruthJson {
    pub t_s: Option<f64>,
    pub pos_ned_m: [f64; 3],
    pub yaw_deg: f64,
    pub speed_m_s: f64,
}

#[derive(Debug, Clone, Serialize)]
pub struct LinkJson {
    /// `coop` or `vehicle ID`.
    pub link: String,
    pub sysid: u32,
    pub compid: u8,
    pub addr: Option<String>,
    pub mav_type: Option<String>,
    pub packets: u64,
    pub bytes: u64,
    pub bytes_per_s: f64,
    pub lost: u64,
    /// Frames that came after a later one, and restarts of the sender's numbering
    /// ([`crate::protocol::sequence`]).
    pub late: u64,
    pub restarts: u64,
    pub loss_pct: Option<f64>,
    pub last_heard_s_ago: f64,
    pub messages: BTreeMap<String, u64>,
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::estimation::Method;
    use crate::protocol::dialect::cooploc::{HIGHRES_IMU_DATA, SIM_STATE_DATA};
    use mavlink_core::MavHeader;
    use nalgebra::Matrix3;

    const NODE_COMPID: u8 = 191;

    fn s(x: f64) -> WallNs {
        WallNs((1_700_000_000.0e9 + x * 1e9) as u64)
    }

    fn addr(port: u16) -> SocketAddr {
        SocketAddr::from(([127, 0, 0, 1], port))
    }

    fn report(platform: PlatformId, t_us: u64, n: f64, e: f64, cov: Matrix3<f64>) -> EstimateReport {
        EstimateReport {
            platform,
            t: TimeUs(t_us),
            epoch: 1,
            method: Method::Decentralized,
            position_ned_m: Vector3::new(n, e, 0.0),
            velocity_ned_m_s: Vector3::new(1.0, 0.0, 0.0),
            yaw_rad: 0.1,
            position_covariance_m2: cov,
            yaw_variance_rad2: 1e-4,
            nis: f64::NAN,
            participants: 3,
            ranges: 2,
        }
    }

    fn frame(sysid: u8, compid: u8, seq: u8, msg: &MavMessage) -> Vec<u8> {
        wire::to_frame(MavHeader { system_id: u32::from(sysid), component_id: compid, sequence: seq }, msg)
    }

    fn estimate_frame(seq: u8, r: &EstimateReport) -> Vec<u8> {
        frame(r.platform as u8, NODE_COMPID, seq, &wire::estimate_to_message(r))
    }

    fn close(a: f64, b: f64, tol: f64) -> bool {
        (a - b).abs() <= tol
    }

    /// The health as the station sees it on a bad network: a forged epoch report (announcer 2
    /// sent by system 9) is rejected and moves nothing; a lost report leaves an epoch unjudged;
    /// a late, disagreeing report withdraws the heal its epoch's first reports made; repeats
    /// count once; sequence gaps are loss; the budget share and the signing follow the frames.
    #[test]
    fn health_under_forged_lost_late_and_repeated_reports() {
        use crate::protocol::dialect::cooploc::CooplocEpochState as St;
        let mut gcs = GcsState::new(GcsConfig { link_capacity_bytes_per_s: Some(3000.0), ..GcsConfig::default() });
        let mut seq = [0u8; 10];
        let mut send = |gcs: &mut GcsState, sysid: u8, epoch: u32, announcer: u16, digest: u64, at: f64| {
            let a = wire::EpochAnnouncement {
                epoch,
                t: TimeUs(u64::from(epoch) * 1_000_000),
                announcer,
                participants: vec![1, 2, 3],
                state: St::COOPLOC_EPOCH_STATE_APPLIED,
                digest,
                incomplete: Vec::new(),
            };
            let n = &mut seq[usize::from(sysid)];
            // Node 3 loses every other frame on the way.
            *n = n.wrapping_add(if sysid == 3 { 2 } else { 1 });
            let f = frame(sysid, NODE_COMPID, *n, &wire::epoch_to_message(&a).unwrap());
            gcs.on_coop_datagram(s(at), addr(14_000 + u16::from(sysid)), &f)
        };
        for id in 1..=3u8 {
            send(&mut gcs, id, 1, u16::from(id), 7, 1.0);
        }
        // Epoch 2: node 3 holds another store. A forger tells the station node 2 agrees with it.
        send(&mut gcs, 1, 2, 1, 8, 2.0);
        let forged = send(&mut gcs, 9, 2, 2, 9, 2.0);
        assert!(matches!(forged.last(), Some(GcsEvent::Rejected { .. })), "{forged:?}");
        send(&mut gcs, 2, 2, 2, 8, 2.0);
        send(&mut gcs, 3, 2, 3, 9, 2.1);
        send(&mut gcs, 3, 2, 3, 9, 2.2); // repeated
        // Epoch 3: nodes 1 and 2 agree first (a heal), node 3's late report disagrees.
        send(&mut gcs, 1, 3, 1, 10, 3.0);
        send(&mut gcs, 2, 3, 2, 10, 3.0);
        assert_eq!(gcs.health(s(3.0)).heals, 1);
        send(&mut gcs, 3, 3, 3, 11, 3.5);
        // Epoch 4: node 2's report is lost; one report alone judges nothing.
        send(&mut gcs, 1, 4, 1, 12, 4.0);
        let h = gcs.health(s(4.0));
        assert_eq!((h.disagreements, h.heals, h.unhealed_since, h.last_epoch), (2, 0, Some(3), Some(4)));
        let node = |id: u16| h.nodes.iter().find(|n| n.id == id).unwrap().clone();
        assert_eq!((node(1).epochs.outvoted, node(3).epochs.outvoted), (0, 2));
        assert!(!h.nodes.iter().any(|n| n.id == 9), "the forger is no node");
        let loss3 = node(3).loss_pct.unwrap();
        // Four frames received, three lost between them (before the first is not known).
        assert!((loss3 - 300.0 / 7.0).abs() < 1e-9 && node(1).loss_pct == Some(0.0), "loss {loss3}");
        assert_eq!((node(1).signing, node(1).unsigned_frames), ("unsigned", 4));
        assert_eq!(node(1).budget_bytes_per_s, Some(1000.0), "a third of the capacity each");
        assert!(node(1).bytes_per_s > 0.0 && h.team_load_pct.unwrap() > 0.0);
        // Then the team agrees again: healed.
        for id in 1..=3u8 {
            send(&mut gcs, id, 5, u16::from(id), 13, 5.0);
        }
        let h = gcs.health(s(5.0));
        assert_eq!((h.heals, h.unhealed_since), (1, None));
    }

    #[test]
    fn ellipse_axes_match_a_hand_computation() {
        // [[5, 2], [2, 2]]: eigenvalues (7 +- sqrt(9 + 16)) / 2 = 6 and 1; the major axis is the
        // eigenvector (2, 1) (N, E): atan(1/2) = 26.565 deg east of north.
        let e = ellipse95(&Matrix2::new(5.0, 2.0, 2.0, 2.0)).unwrap();
        assert!(close(e.semi_major_m, (5.991_464_547 * 6.0f64).sqrt(), 1e-8), "{e:?}");
        assert!(close(e.semi_major_m, 5.995_731, 1e-5));
        assert!(close(e.semi_minor_m, 2.447_747, 1e-5));
        assert!(close(e.major_bearing_deg, 26.565_051, 1e-5));
        // Uncorrelated, larger east variance: major axis east (90 deg), axes 2.4477 * (2, 1).
        let e = ellipse95(&Matrix2::new(1.0, 0.0, 0.0, 4.0)).unwrap();
        assert!(close(e.major_bearing_deg, 90.0, 1e-9) && close(e.semi_major_m, 2.0 * 2.447_746_83, 1e-6));
        // Negative correlation: major axis north-west (-45 deg); eigenvalues 4 and 2.
        let e = ellipse95(&Matrix2::new(3.0, -1.0, -1.0, 3.0)).unwrap();
        assert!(close(e.major_bearing_deg, -45.0, 1e-9));
        assert!(close(e.semi_major_m, (CHI2_2DOF_95 * 4.0).sqrt(), 1e-12));
        assert!(close(e.semi_minor_m, (CHI2_2DOF_95 * 2.0).sqrt(), 1e-12));
        // A circle, a degenerate line, and garbage.
        let e = ellipse95(&Matrix2::new(2.0, 0.0, 0.0, 2.0)).unwrap();
        assert!(close(e.semi_major_m, e.semi_minor_m, 1e-12) && close(e.major_bearing_deg, 0.0, 1e-12));
        assert_eq!(ellipse95(&Matrix2::new(1.0, 1.0, 1.0, 1.0)).unwrap().semi_minor_m, 0.0);
        assert!(ellipse95(&Matrix2::new(f64::NAN, 0.0, 0.0, 1.0)).is_none());
        assert!(ellipse95(&Matrix2::new(-1.0, 0.0, 0.0, -1.0)).is_none());
        assert!(close(CHI2_2DOF_95, -2.0 * 0.05f64.ln(), 1e-12));
    }

    #[test]
    fn estimates_make_vehicles_and_links_count_loss_from_sequence_gaps() {
        let mut gcs = GcsState::new(GcsConfig::default());
        let cov = Matrix3::from_diagonal(&Vector3::new(4.0, 1.0, 9.0));
        // Vehicle 1: sequence 250..=255, 0..=3 with 253 and 1 missing (2 lost of 10, across the wrap).
        let seqs: Vec<u8> = (250u8..=255).chain(0..=3).filter(|&q| q != 253 && q != 1).collect();
        for (k, &q) in seqs.iter().enumerate() {
            let r = report(1, 1_000_000 * (k as u64 + 1), 10.0 + k as f64, -5.0, cov);
            let events = gcs.on_coop_datagram(s(k as f64 * 0.1), addr(5001), &estimate_frame(q, &r));
            assert!(events.iter().any(|e| matches!(e, GcsEvent::Estimate { vehicle: 1, .. })));
            assert!(events.iter().any(|e| matches!(e, GcsEvent::Frame { message_id: 61002, .. })));
        }
        // Vehicle 2: two frames in one datagram, no loss.
        let mut both = estimate_frame(7, &report(2, 1_000_000, 1.0, 2.0, cov));
        both.extend(estimate_frame(8, &report(2, 2_000_000, 3.0, 4.0, cov)));
        gcs.on_coop_datagram(s(1.0), addr(5002), &both);

        let v1 = &gcs.vehicles[&1];
        assert_eq!(v1.counts.estimates, 8);
        let last = v1.latest_estimate().unwrap();
        assert_eq!(last.report.position_ned_m[0], 17.0);
        let el = last.ellipse.unwrap();
        assert!(close(el.semi_major_m, (CHI2_2DOF_95 * 4.0).sqrt(), 1e-6) && close(el.major_bearing_deg, 0.0, 1e-9));
        let l1 = &gcs.links[&SourceKey { link: Link::Coop, sysid: 1, compid: NODE_COMPID }];
        assert_eq!((l1.packets, l1.seq.lost, l1.seq.late), (8, 2, 0));
        assert!(close(l1.seq.loss_fraction().unwrap(), 0.2, 1e-12));
        assert_eq!(l1.last_addr, Some(addr(5001)));
        let l2 = &gcs.links[&SourceKey { link: Link::Coop, sysid: 2, compid: NODE_COMPID }];
        assert_eq!((l2.packets, l2.seq.lost), (2, 0));
        assert_eq!(gcs.peers().collect::<Vec<_>>(), vec![addr(5001), addr(5002)]);

        let snap = gcs.snapshot(s(1.5), 100);
        assert_eq!(snap.vehicles.iter().map(|v| v.id).collect::<Vec<_>>(), vec![1, 2]);
        assert_eq!(snap.vehicles[1].estimate.as_ref().unwrap().pos_ned_m, [3.0, 4.0, 0.0]);
        let link1 = snap.links.iter().find(|l| l.sysid == 1).unwrap();
        assert!(close(link1.loss_pct.unwrap(), 20.0, 1e-9));
        assert_eq!(link1.messages["COOPLOC_ESTIMATE"], 8);
        let json = serde_json::to_string(&snap).unwrap();
        assert!(json.contains("\"nis\":null"), "NaN NIS is null in the JSON");
    }

    fn sim_state(origin: &GeoOrigin, pos: Vector3<f64>) -> MavMessage {
        let g = wire::ned_to_geodetic(origin, &pos);
        MavMessage::SIM_STATE(SIM_STATE_DATA {
            lat: g.lat_deg as f32,
            lon: g.lon_deg as f32,
            alt: g.alt_m as f32,
            lat_int: wire::deg_to_e7(g.lat_deg),
            lon_int: wire::deg_to_e7(g.lon_deg),
            vn: 10.0,
            q1: 1.0,
            ..Default::default()
        })
    }

    fn imu(t_us: u64) -> MavMessage {
        MavMessage::HIGHRES_IMU(HIGHRES_IMU_DATA { time_usec: t_us, zacc: -9.8, ..Default::default() })
    }

    #[test]
    fn error_interpolates_the_truth_at_the_estimate_time() {
        let cfg = GcsConfig { vehicles: vec![3], ..GcsConfig::default() };
        let origin = cfg.origin;
        let mut gcs = GcsState::new(cfg);
        let link = |gcs: &mut GcsState, seq: u8, msg: &MavMessage| gcs.on_vehicle_frame(s(seq as f64), 3, &frame(3, 1, seq, msg));
        // Truth at 1.0 s: (100, 200, 0); at 1.1 s: (101, 202, 0). SIM_STATE comes just before
        // the IMU sample of its time, which stamps it.
        link(&mut gcs, 0, &sim_state(&origin, Vector3::new(100.0, 200.0, 0.0)));
        assert!(gcs.vehicles[&3].truth.samples().is_empty(), "no time yet");
        link(&mut gcs, 1, &imu(1_000_000));
        // An estimate at 1.05 s arrives before the truth covers it: error pending.
        let cov = Matrix3::from_diagonal(&Vector3::new(4.0, 1.0, 1.0));
        let r = report(3, 1_050_000, 100.5 + 3.0, 201.0 - 4.0, cov);
        let events = gcs.on_coop_datagram(s(2.0), addr(6000), &estimate_frame(0, &r));
        assert!(!events.iter().any(|e| matches!(e, GcsEvent::Error { .. })));
        link(&mut gcs, 2, &imu(1_005_000));
        link(&mut gcs, 3, &sim_state(&origin, Vector3::new(101.0, 202.0, 0.0)));
        let events = link(&mut gcs, 4, &imu(1_100_000));
        let truth: Vec<_> =
            events.iter().filter_map(|e| if let GcsEvent::Truth { point, .. } = e { Some(*point) } else { None }).collect();
        assert_eq!(truth.len(), 1);
        assert_eq!(truth[0].t, Some(TimeUs(1_100_000)));
        let errors: Vec<_> = events
            .iter()
            .filter_map(|e| if let GcsEvent::Error { t, error, .. } = e { Some((*t, *error)) } else { None })
            .collect();
        assert_eq!(errors.len(), 1, "{events:?}");
        let (t, err) = errors[0];
        assert_eq!(t, TimeUs(1_050_000));
        // Truth at 1.05 s is the midpoint (100.5, 201); the estimate is 3 m north and 4 m west of it
        // (degE7 quantisation of SIM_STATE: about 1 cm).
        assert!(close(err.truth_ned_m[0], 100.5, 0.02) && close(err.truth_ned_m[1], 201.0, 0.02), "{err:?}");
        assert!(close(err.horizontal_m, 5.0, 0.02), "{err:?}");
        // NEES = 3^2/4 + 4^2/1 + 0 = 18.25.
        assert!(close(err.nees.unwrap(), 18.25, 0.1), "{err:?}");
        let snap = gcs.snapshot(s(5.0), 100);
        let v = &snap.vehicles[0];
        assert!(v.has_link && v.error.is_some() && v.errors.len() == 1 && v.truth_track.len() == 2);
        assert_eq!(gcs.vehicles[&3].counts.link_imu_frames, 3);
        // Outside the truth's span: no error; across a gap longer than max_truth_gap_us: none.
        // (gaps: gcs::truth's tests)
        assert!(gcs.vehicles[&3].truth_at(TimeUs(900_000)).is_none());
        assert!(gcs.vehicles[&3].truth_at(TimeUs(1_200_000)).is_none());
    }

    #[test]
    fn nees_by_cholesky() {
        let p = Matrix3::new(4.0, 1.0, 0.0, 1.0, 2.0, 0.0, 0.0, 0.0, 1.0);
        let e = Vector3::new(1.0, -1.0, 2.0);
        let direct = (e.transpose() * p.try_inverse().unwrap() * e)[0];
        assert!(close(position_nees(&e, &p).unwrap(), direct, 1e-12));
        assert!(position_nees(&e, &Matrix3::from_diagonal(&Vector3::new(1.0, 1.0, 0.0))).is_none());
    }

    #[test]
    fn bad_frames_are_counted_and_dropped() {
        let mut gcs = GcsState::new(GcsConfig::default());
        let cov = Matrix3::identity();
        // Garbage, an empty datagram, a truncated frame, a frame with a flipped bit.
        let good = estimate_frame(0, &report(1, 1_000_000, 1.0, 1.0, cov));
        let mut flipped = good.clone();
        flipped[20] ^= 0x10;
        for bad in [&b"hello, not mavlink"[..], &[], &good[..good.len() - 3], &flipped] {
            let events = gcs.on_coop_datagram(s(0.0), addr(7000), bad);
            assert!(matches!(events.as_slice(), [GcsEvent::Rejected { .. }]), "{events:?}");
        }
        assert_eq!(gcs.counters.bad_datagrams, 4);
        assert!(gcs.vehicles.is_empty() && gcs.peers().next().is_none(), "nothing learned from garbage");
        // A valid frame carrying a NaN position, and an estimate claiming another platform.
        let nan = estimate_frame(1, &report(1, 1_000_000, f64::NAN, 1.0, cov));
        gcs.on_coop_datagram(s(0.1), addr(7000), &nan);
        let mut spoof = report(2, 1_000_000, 1.0, 1.0, cov);
        spoof.platform = 2;
        let spoofed = frame(9, NODE_COMPID, 0, &wire::estimate_to_message(&spoof));
        gcs.on_coop_datagram(s(0.2), addr(7000), &spoofed);
        assert_eq!(gcs.counters.rejected, 2);
        assert!(gcs.vehicles.is_empty());
        // Garbage around a good frame: the frame is used.
        let mut wrapped = b"xx".to_vec();
        wrapped.extend(&good);
        wrapped.extend(b"yy");
        gcs.on_coop_datagram(s(0.3), addr(7000), &wrapped);
        assert_eq!(gcs.vehicles[&1].counts.estimates, 1);
        // Our own heartbeat, looped back, is not a source.
        gcs.on_coop_datagram(s(0.4), addr(7001), &frame(GCS_SYSID, GCS_COMPID, 0, &crate::gcs::runner::heartbeat()));
        assert_eq!(gcs.counters.own, 1);
        assert!(!gcs.links.keys().any(|k| k.sysid == u32::from(GCS_SYSID)));
        // Pseudo-random bytes and mutilated frames never panic.
        let mut x: u64 = 0x9e37_79b9_7f4a_7c15;
        for i in 0..2000 {
            let mut d = good.clone();
            d.extend(frame(1, 1, i as u8, &sim_state(&GcsConfig::default().origin, Vector3::new(1.0, 2.0, 3.0))));
            for _ in 0..(i % 7) {
                x ^= x << 13;
                x ^= x >> 7;
                x ^= x << 17;
                let k = (x as usize) % d.len();
                d[k] = (x >> 32) as u8;
            }
            d.truncate(((x >> 20) as usize) % (d.len() + 1));
            gcs.on_coop_datagram(s(1.0), addr(7002), &d);
            gcs.on_vehicle_frame(s(1.0), 1, &d);
        }
    }

    #[test]
    fn stale_estimates_are_dropped_and_a_restart_starts_over() {
        let mut gcs = GcsState::new(GcsConfig::default());
        let cov = Matrix3::identity();
        for (q, t) in [(0u8, 10_000_000u64), (1, 11_000_000), (2, 10_500_000), (3, 1_000_000)] {
            gcs.on_coop_datagram(s(q as f64), addr(7100), &estimate_frame(q, &report(4, t, 0.0, 0.0, cov)));
        }
        let v = &gcs.vehicles[&4];
        assert_eq!((v.counts.estimates, v.counts.stale_estimates, v.counts.restarts), (3, 1, 1));
        assert_eq!(v.estimates.len(), 1, "the restart cleared the history");
        assert_eq!(v.latest_estimate().unwrap().report.t, TimeUs(1_000_000));
    }

    #[test]
    fn histories_are_bounded_and_series_thinned() {
        let mut gcs = GcsState::new(GcsConfig { estimate_history: 50, ..GcsConfig::default() });
        for k in 0..200u64 {
            let r = report(1, 1_000_000 * (k + 1), k as f64, 0.0, Matrix3::identity());
            gcs.on_coop_datagram(s(k as f64), addr(7200), &estimate_frame(k as u8, &r));
        }
        assert_eq!(gcs.vehicles[&1].estimates.len(), 50);
        let snap = gcs.snapshot(s(300.0), 20);
        let track = &snap.vehicles[0].track;
        assert!(track.len() <= 20 && track.len() >= 10, "{}", track.len());
        assert_eq!(track.last().unwrap()[1], 199.0, "the newest point is kept");
        assert_eq!(thin((0..5).collect(), 10), vec![0, 1, 2, 3, 4]);
    }

    /// Spoofed sources cannot grow the ground station: every system id sends an estimate, a
    /// range, an epoch and a fragment series claiming other platforms, from a thousand ports.
    /// Messages that claim a platform other than their sender are refused; the vehicle table
    /// stops at `max_vehicles`, the peers at `max_peers`, and silent peers expire.
    #[test]
    fn spoofed_vehicles_and_peers_are_bounded() {
        use crate::estimation::RangeSample;
        let mut gcs = GcsState::new(GcsConfig::default());
        let cov = Matrix3::identity();
        let mut port = 20_000u16;
        for sysid in 1..=254u8 {
            let claims = u16::from(sysid).wrapping_mul(7) % 200 + 300; // platforms that do not exist
            let range = RangeSample { t: TimeUs(1_000_000), from: claims, to: 1, range_m: 5.0, sigma_m: 0.1 };
            let r = wire::range_to_message(&range, 1);
            for msg in [wire::estimate_to_message(&report(u16::from(sysid), 1_000_000, 1.0, 1.0, cov)), r] {
                port += 1;
                gcs.on_coop_datagram(s(0.0), addr(port), &frame(sysid, NODE_COMPID, 0, &msg));
            }
        }
        let c = gcs.counters;
        assert_eq!(gcs.vehicles.len(), 64, "{c:?}");
        assert_eq!(c.vehicles_refused, 254 - 64);
        assert_eq!(c.rejected, 254, "every range claiming another platform refused: {c:?}");
        assert_eq!(gcs.peers().count(), 64);
        assert_eq!(c.peers_refused, 2 * 254 - 64);
        assert!(gcs.snapshot(s(0.0), 100).vehicles.len() <= 64);
        // Thirty seconds later the learned peers have expired; a given one stays.
        gcs.add_peer(addr(9999));
        gcs.expire_peers(s(31.0));
        assert_eq!(gcs.peers().collect::<Vec<_>>(), vec![addr(9999)]);
    }

    /// With a team key the ground station reads only signed cooperative frames: an unsigned
    /// estimate and one signed with another key make no vehicle; the team's does, and its
    /// replay is refused.
    #[test]
    fn with_a_team_key_only_signed_frames_are_read() {
        use crate::protocol::signing::{Signer, TeamKey};
        let key = TeamKey::from_passphrase("team");
        let mut gcs = GcsState::new(GcsConfig { team_key: Some(key.clone()), ..GcsConfig::default() });
        let cov = Matrix3::identity();
        let msg = wire::estimate_to_message(&report(1, 1_000_000, 1.0, 1.0, cov));
        let header = MavHeader { system_id: 1, component_id: NODE_COMPID, sequence: 0 };
        let now_us = s(0.0).0 / 1000;
        let unsigned = frame(1, NODE_COMPID, 0, &msg);
        let wrong = Signer::new(TeamKey::from_passphrase("not the team"), 1, 0).frame(header, &msg, now_us);
        let good = Signer::new(key, 1, 0).frame(header, &msg, now_us);
        for bad in [&unsigned, &wrong] {
            let events = gcs.on_coop_datagram(s(0.0), addr(7000), bad);
            assert!(matches!(events.as_slice(), [GcsEvent::Rejected { .. }]), "{events:?}");
        }
        assert!(gcs.vehicles.is_empty() && gcs.peers().next().is_none(), "nothing learned from unsigned frames");
        gcs.on_coop_datagram(s(0.1), addr(7000), &good);
        assert_eq!(gcs.vehicles[&1].counts.estimates, 1);
        gcs.on_coop_datagram(s(0.2), addr(7001), &good);
        assert_eq!(gcs.vehicles[&1].counts.estimates, 1, "a replayed frame is refused");
        let signing = gcs.signing().unwrap();
        assert_eq!((signing.accepted, signing.unsigned, signing.bad_signature, signing.replayed), (1, 1, 1, 1));
        assert_eq!(gcs.counters.unauthenticated, 3);
        assert_eq!(gcs.snapshot(s(0.3), 100).gcs.signing.as_ref().map(|c| c.accepted), Some(1));
    }
}
