//! The node's tokio runner: owns the vehicle link, the cooperative-network socket and the
//! clock, converts messages with [`crate::protocol::wire`], and feeds a [`NodeCore`].
//!
//! - **Vehicle**: a MAVLink connection URL (`udpout:HOST:PORT`, `udpin:HOST:PORT`, `tcpout:`,
//!   `tcpin:`, `serial:/dev/ttyX:BAUD`; see [`super::vehicle_link`]: UDP links get a large
//!   receive buffer, and lost frames are counted from sequence gaps). Only messages from the
//!   vehicle's own system id are used, decoded by [`super::inputs`] as the vehicle profile says
//!   (the IMU and odometer messages, SYSTEM_TIME, the cooploc ranges its radio measured). The
//!   node sends HEARTBEAT (compid 191, ONBOARD_CONTROLLER) at 1 Hz, its rate requests
//!   ([`super::autopilot`]), ODOMETRY at the profile's rate and, after every cooperative
//!   update, LOCAL_POSITION_NED.
//! - **Cooperative network**: a [`super::coop_link::CoopLink`]: a UDP socket (with a multicast
//!   group, optionally) or a serial radio. Each batch of outputs goes out as one call, packed
//!   into few datagrams. Over UDP the node sends to the group and to every unicast peer of its
//!   [`super::peers::PeerTable`]: those given on the command line, the last address of each team
//!   member a valid frame came from (so a node can be started knowing only one peer, and tests
//!   can use ephemeral ports) and a few ground stations that sent their HEARTBEAT; learned
//!   addresses expire, strangers are never sent to, and those that hear the group get no
//!   unicast copy.
//! - Bad input (malformed frames, NaN or absurd values, time going backwards, unknown platforms)
//!   is counted, logged and dropped; nothing from the network can panic the process.

use super::error::NodeError;
use std::net::SocketAddr;
use std::sync::Arc;
use std::time::Duration;

use super::autopilot::{
    GpsInputOutput, OdometryOutput, OriginOffer, RateOutcome, RateRequest, RateRequests, TimeSync, TimesyncReply,
};
use super::coop_link::{CoopLink, CoopSpec, Source};
use super::core::{NodeConfig, NodeCore, NodeInput, NodeOutput, NodeStats};
use super::inputs::{ClockSource, InputCounters, VehicleEvent, VehicleInputs};
use super::peers::{Heard, PeerCounters, PeerTable};
use super::profile::TeamClock;
use super::profile::VehicleProfile;
use super::vehicle_link::{Received, VehicleLink};
use crate::estimation::PlatformId;
use crate::estimation::ins::InsState;
use crate::estimation::nav::NavState;
use crate::protocol::MavMessage;
use crate::protocol::dialect::cooploc::{MavAutopilot, MavType};
use crate::protocol::signing::{Signer, SigningCounters, TeamKey, Verifier};
use crate::protocol::wire;
use crate::recording::{Direction, Link, wall_now_ns};
use crate::time::TimeUs;
use mavlink_core::MavHeader;

pub use super::log::{
    NODE_EVENT_SCHEMA, NODE_EVENT_SCHEMA_NAME, NodeEvent, events_topic, metadata_name, node_metadata, vehicle_attachment_name,
};
pub use crate::protocol::wire::COMPANION_COMPID;
pub use crate::recording::SharedRecorder;

fn record_event(rec: &Option<SharedRecorder>, id: PlatformId, event: &NodeEvent) {
    if let Some(r) = rec
        && let Ok(mut r) = r.lock()
    {
        let _ = r.json_message(&events_topic(id), NODE_EVENT_SCHEMA_NAME, NODE_EVENT_SCHEMA, wall_now_ns(), event);
        let _ = r.maybe_flush(std::time::Instant::now());
    }
}

fn record_frame(rec: &Option<SharedRecorder>, link: Link, dir: Direction, bytes: &[u8]) {
    if let Some(r) = rec
        && let Ok(mut r) = r.lock()
    {
        let _ = r.frame(link, dir, wall_now_ns(), bytes);
        let _ = r.maybe_flush(std::time::Instant::now());
    }
}

/// How far (vehicle time) the vehicle's first sample may be after the time of a given start
/// state ([`NodeInit::Given`]) for the state to be trusted, us.
pub const STALE_START_US: u64 = 10_000_000;

/// How the node gets its initial state.
#[derive(Debug)]
pub enum NodeInit {
    /// Already initialised.
    Ready(Box<NodeCore>),
    /// Initialised from a state given with its time (the command line), about `origin`: trusted
    /// only if the vehicle's first sample comes at most [`STALE_START_US`] after that time. A
    /// later one means the state is stale (a supervisor restarted the node with the arguments of
    /// its first start, while the vehicle went on): the node then refuses it, says so, and waits
    /// for a state as [`NodeInit::Pending`] does (SIM_STATE).
    Given { core: Box<NodeCore>, origin: wire::GeoOrigin },
    /// Waiting for what it lacks. `origin` None: the vehicle's GPS_GLOBAL_ORIGIN (or
    /// HOME_POSITION) gives it, and its latitude goes into the INS configuration. `state` None:
    /// the first SIM_STATE the vehicle sends after the origin is known (simulated vehicles): its
    /// position about the origin, NED velocity and attitude, at the time of the last IMU sample
    /// before it, once the team clock maps the vehicle's stamps. A state without a time is
    /// taken at the last IMU (or wheel) sample before the origin and the team clock are known
    /// (a real vehicle started where its configuration says).
    ///
    /// `from_autopilot`: the state comes from the autopilot's own estimate when its GNSS goes
    /// (the hand-over start, [`super::handover`]), not from SIM_STATE.
    Pending {
        config: Box<NodeConfig>,
        origin: Option<wire::GeoOrigin>,
        state: Option<(Option<TimeUs>, InsState)>,
        from_autopilot: bool,
    },
}

/// Where the node connects.
#[derive(Debug, Clone)]
pub struct Links {
    /// MAVLink URL of the vehicle.
    pub vehicle: String,
    /// The cooperative link: a UDP socket's local address (port 0: ephemeral), its multicast
    /// group and datagram size, or a serial radio.
    pub coop: CoopSpec,
    /// Peers known from the start.
    pub peers: Vec<SocketAddr>,
    /// Stop when the vehicle has been silent this long (after its first frame): the stream
    /// ended. The node then closes its last instant, broadcasts, listens to its peers for
    /// `grace`, runs the epochs still pending, and returns.
    pub idle_exit: Option<Duration>,
    pub grace: Duration,
    /// The vehicle: which messages to read, what to ask for and send back.
    pub profile: VehicleProfile,
    /// The team's signing key: every cooperative frame sent is signed with it, and only frames
    /// signed with it are taken (see [`crate::protocol::signing`]). None: unsigned, as before.
    pub team_key: Option<TeamKey>,
    /// Where the signing timestamp is kept across restarts (read at start, written every
    /// [`SIGNING_STATE_EVERY`] and at the end): a node whose clock is behind after a reboot
    /// still signs above every timestamp it used, so its peers do not take it for a replay.
    pub signing_state: Option<std::path::PathBuf>,
    /// The vehicle link's signing key (the autopilot's), when its port is signed.
    pub vehicle_key: Option<TeamKey>,
    /// A ranging device on the companion ([`super::ranging`]), besides the vehicle link.
    pub ranges: Option<RangeSource>,
}

/// Where a ranging device's stream comes from.
#[derive(Debug, Clone)]
pub enum RangeSource {
    /// Datagrams to this socket (bound by the caller, so that it can say where).
    Udp(Arc<std::net::UdpSocket>),
    /// A serial line.
    Serial { path: String, baud: u32 },
}

/// Reads a ranging device on its own task: each read with the companion's Unix time (us) it
/// arrived at.
fn spawn_range_reader(source: RangeSource) -> Result<tokio::sync::mpsc::Receiver<(Vec<u8>, u64)>, NodeError> {
    use tokio::io::AsyncReadExt as _;
    let (tx, rx) = tokio::sync::mpsc::channel::<(Vec<u8>, u64)>(1024);
    let now_us = || (unix_now_ns() / 1000) as u64;
    match source {
        RangeSource::Udp(socket) => {
            let std_socket = socket.try_clone().map_err(NodeError::io("the ranging socket"))?;
            std_socket.set_nonblocking(true).map_err(NodeError::io("the ranging socket"))?;
            let socket = tokio::net::UdpSocket::from_std(std_socket).map_err(NodeError::io("the ranging socket"))?;
            tokio::spawn(async move {
                let mut buf = vec![0u8; 65_536];
                loop {
                    match socket.recv_from(&mut buf).await {
                        Ok((n, _)) => {
                            if tx.send((buf[..n].to_vec(), now_us())).await.is_err() {
                                return;
                            }
                        }
                        Err(e) => {
                            tracing::warn!(error = %e, "ranging socket read error");
                            tokio::time::sleep(Duration::from_millis(100)).await;
                        }
                    }
                }
            });
        }
        RangeSource::Serial { path, baud } => {
            use tokio_serial::SerialPortBuilderExt as _;
            let mut port = tokio_serial::new(&path, baud)
                .open_native_async()
                .map_err(|e| NodeError::Invalid(format!("opening the ranging device {path} at {baud} baud: {e}")))?;
            tokio::spawn(async move {
                let mut buf = vec![0u8; 4096];
                loop {
                    match port.read(&mut buf).await {
                        Ok(0) => tokio::time::sleep(Duration::from_millis(10)).await,
                        Ok(n) => {
                            if tx.send((buf[..n].to_vec(), now_us())).await.is_err() {
                                return;
                            }
                        }
                        Err(e) => {
                            tracing::warn!(error = %e, "ranging device read error");
                            tokio::time::sleep(Duration::from_millis(100)).await;
                        }
                    }
                }
            });
        }
    }
    Ok(rx)
}

/// How often the signing state file is written (heartbeats).
pub const SIGNING_STATE_EVERY: u32 = 5;

/// Reads a signing state file: 0 when it does not exist yet.
pub fn load_signing_state(path: &std::path::Path) -> Result<u64, NodeError> {
    match std::fs::read_to_string(path) {
        Ok(text) => crate::protocol::signing::parse_state(&text)
            .map_err(|e| NodeError::Invalid(format!("signing state {}: {e}", path.display()))),
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => Ok(0),
        Err(e) => Err(NodeError::io(format!("signing state {}", path.display()))(e)),
    }
}

/// Writes a signing state file whole or not at all (a temporary file renamed over it).
pub fn save_signing_state(path: &std::path::Path, signer: &Signer) -> std::io::Result<()> {
    let tmp = path.with_extension("tmp");
    std::fs::write(&tmp, crate::protocol::signing::state_text(signer))?;
    std::fs::rename(&tmp, path)
}

/// What a node did, when it stops.
#[derive(Debug, Clone)]
pub struct NodeSummary {
    pub stats: NodeStats,
    /// Platforms whose id came with two different records for one epoch (see
    /// [`crate::node::vetting`]).
    pub flagged: Vec<crate::estimation::PlatformId>,
    /// None when the node never got its initial state.
    pub estimate: Option<wire::EstimateReport>,
    /// Vehicle inputs received before the initial state (waiting for SIM_STATE).
    pub before_init: u64,
    /// Time and position of the initialisation from SIM_STATE, when it happened.
    pub sim_state_init: Option<(TimeUs, nalgebra::Vector3<f64>)>,
    pub vehicle_frames: u64,
    /// Vehicle frames from another system id (another vehicle, a ground station), not used.
    pub vehicle_rejected: u64,
    /// Vehicle frames of messages outside the dialect (the autopilot's own dialect), skipped by
    /// their length.
    pub vehicle_other_dialect: u64,
    /// Vehicle frames lost on the link, from gaps in the vehicle's MAVLink sequence numbers.
    pub vehicle_lost: u64,
    pub coop_frames: u64,
    pub coop_rejected: u64,
    /// Bytes of a serial radio's stream that were no valid frame (noise, damaged frames).
    pub coop_noise_bytes: u64,
    /// What signing accepted and refused (unsigned, another key, replayed, stale; all zero without a team key).
    pub coop_signing: SigningCounters,
    /// What signing accepted and refused on a signed UDP vehicle link.
    pub vehicle_signing: Option<SigningCounters>,
    pub peers: Vec<SocketAddr>,
    /// Peers learned, moved, expired and ground stations refused (table full).
    pub peer_counters: PeerCounters,
    /// What went out on the cooperative network, and over how long (wall time).
    pub coop_tx: CoopTx,
    pub wall_s: f64,
    /// What the vehicle's messages gave (see [`InputCounters`]).
    pub inputs: InputCounters,
    /// The IMU rate that arrived, Hz.
    pub imu_rate_hz: Option<f64>,
    /// How each rate request ended.
    pub rate_requests: Vec<RateRequest>,
    /// ODOMETRY messages sent to the autopilot, and their last reset counter.
    pub odometry_sent: u64,
    pub odometry_resets: u8,
    /// GPS_INPUT messages sent to the autopilot.
    pub gps_input_sent: u64,
    /// The origin the vehicle gave, when the profile had none.
    pub origin_from_vehicle: Option<wire::GeoOrigin>,
    /// Where the team clock's mapping came from, the mapping (team time minus the vehicle's
    /// boot time, us) and, through TIMESYNC, the round trip of the answer it came from (us).
    pub clock: Option<(ClockSource, i64, Option<i64>)>,
    /// TIMESYNC requests sent and answers refused (not ours, too slow).
    pub timesync_requests: u64,
    pub timesync_refused: u64,
    /// What the ranging device's stream held (None: no device).
    pub range_input: Option<super::ranging::RangeInputCounters>,
    /// The team's origin offered to an autopilot without one (None: the profile has no
    /// `[origin]`, or says `set_origin = false`).
    pub origin_offer: Option<OriginOffer>,
    /// A hand-over start: where the node started (NED, m) and how the autopilot answered the
    /// EKF source-set switch (None: not asked, or unanswered).
    pub hand_over: Option<(nalgebra::Vector3<f64>, Option<crate::protocol::dialect::cooploc::MavResult>)>,
}

/// The companion's clock, Unix time in ns (the team clock of `clock = "companion"`).
fn unix_now_ns() -> i64 {
    std::time::SystemTime::now().duration_since(std::time::UNIX_EPOCH).map_or(0, |d| d.as_nanos() as i64)
}

/// A new TIMESYNC mapping replaces the one in use when they differ by more than this, us.
const CLOCK_UPDATE_US: i64 = 200;

/// What the node put on the cooperative network.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct CoopTx {
    /// Frames, and their bytes once each (what a broadcast medium carries).
    pub frames: u64,
    pub frame_bytes: u64,
    /// Datagrams sent (a frame goes to each peer) and their payload bytes.
    pub datagrams: u64,
    pub bytes: u64,
    /// Batches a serial radio could not take (its write queue was full).
    pub dropped: u64,
}

struct Sequences {
    tx: CoopTx,
    sysid: u32,
    coop: u8,
    vehicle: u8,
    /// Signs the cooperative frames, when the team has a key.
    signer: Option<Signer>,
}

impl Sequences {
    fn coop(&mut self) -> MavHeader {
        self.coop = self.coop.wrapping_add(1);
        MavHeader { system_id: self.sysid, component_id: COMPANION_COMPID, sequence: self.coop }
    }

    /// The next cooperative frame of `msg`, signed when the team has a key.
    fn coop_frame(&mut self, msg: &MavMessage) -> Vec<u8> {
        let header = self.coop();
        let frame = match &mut self.signer {
            Some(s) => s.frame(header, msg, wall_now_ns() / 1000),
            None => wire::to_frame(header, msg),
        };
        self.tx.frames += 1;
        self.tx.frame_bytes += frame.len() as u64;
        frame
    }

    fn vehicle(&mut self) -> MavHeader {
        self.vehicle = self.vehicle.wrapping_add(1);
        MavHeader { system_id: self.sysid, component_id: COMPANION_COMPID, sequence: self.vehicle }
    }
}

/// Sends one message to the vehicle (and logs it).
async fn to_vehicle(vehicle: &VehicleLink, seqs: &mut Sequences, rec: &Option<SharedRecorder>, sysid: u8, msg: &MavMessage) {
    let header = seqs.vehicle();
    record_frame(rec, Link::Vehicle(sysid), Direction::Tx, &wire::to_frame(header, msg));
    vehicle.send(&header, msg).await;
}

/// The node's outputs to the vehicle: LOCAL_POSITION_NED after each cooperative update (when the
/// profile asks for it), stamped in the vehicle's clock.
struct VehicleOutputs<'a> {
    local_position_ned: bool,
    clock: &'a VehicleInputs,
}

#[allow(clippy::too_many_arguments)]
async fn send_all(
    coop: &CoopLink,
    peers: &PeerTable,
    vehicle: &VehicleLink,
    seqs: &mut Sequences,
    outputs: Vec<NodeOutput>,
    rec: &Option<SharedRecorder>,
    sysid: u8,
    vout: &VehicleOutputs<'_>,
) {
    let mut frames = Vec::new();
    for output in outputs {
        match output {
            NodeOutput::ToPeers(msg) => {
                let frame = seqs.coop_frame(&msg);
                record_frame(rec, Link::Coop(sysid), Direction::Tx, &frame);
                // A record's first fragment goes alone, ahead of the rest (budget::goes_alone).
                if crate::protocol::budget::goes_alone(&msg) {
                    send_to_peers(coop, peers, &std::mem::take(&mut frames), &mut seqs.tx).await;
                    send_to_peers(coop, peers, &[frame], &mut seqs.tx).await;
                    continue;
                }
                frames.push(frame);
                if let MavMessage::COOPLOC_ESTIMATE(m) = &msg
                    && vout.local_position_ned
                    && let Ok(e) = wire::estimate_from_message(m)
                {
                    let boot_ms = (vout.clock.to_vehicle_time(e.t) / 1000) as u32;
                    to_vehicle(vehicle, seqs, rec, sysid, &wire::estimate_to_local_position(&e, boot_ms)).await;
                }
                if let (Some(r), MavMessage::COOPLOC_ESTIMATE(m)) = (rec, &msg)
                    && let Ok(e) = wire::estimate_from_message(m)
                    && let Ok(mut r) = r.lock()
                {
                    let _ = r.estimate(e.platform, wall_now_ns(), &crate::view::foxglove::position_estimate(&e));
                }
            }
            NodeOutput::Update(u) => {
                if let Some(r) = rec
                    && let Ok(mut r) = r.lock()
                {
                    let _ = super::log::record_update(&mut r, wall_now_ns(), &u);
                }
            }
        }
    }
    send_to_peers(coop, peers, &frames, &mut seqs.tx).await;
}

/// Sends cooperative frames (in order) to the group and every unicast peer, or onto the radio,
/// counting what went out.
async fn send_to_peers(coop: &CoopLink, peers: &PeerTable, frames: &[Vec<u8>], tx: &mut CoopTx) {
    let unicast = match coop {
        CoopLink::Udp { .. } => peers.addresses(),
        CoopLink::Serial { .. } => Vec::new(),
    };
    let sent = coop.send(frames, &unicast).await;
    tx.datagrams += sent.datagrams;
    tx.bytes += sent.bytes;
}

fn heartbeat() -> MavMessage {
    wire::heartbeat(MavType::MAV_TYPE_ONBOARD_CONTROLLER, MavAutopilot::MAV_AUTOPILOT_INVALID)
}

/// Receive buffer asked for the cooperative socket: a burst of state records (14 fragments per
/// platform per epoch) must not overflow it while the node is busy (the kernel caps it at
/// net.core.rmem_max).
const COOP_RECV_BUFFER: usize = 4 << 20;

/// Ticks come every 25 ms; a gap this long between two means the process itself was frozen.
const FROZEN_TICK_GAP: Duration = Duration::from_millis(500);

/// Runs a node until `shutdown` resolves or the vehicle link fails. `bound` receives the
/// cooperative socket's local address once it is bound (None: a serial radio).
pub async fn run(
    init: NodeInit,
    links: Links,
    recorder: Option<SharedRecorder>,
    bound: tokio::sync::oneshot::Sender<Option<SocketAddr>>,
    shutdown: impl std::future::Future<Output = ()>,
) -> Result<NodeSummary, NodeError> {
    let team = match &init {
        NodeInit::Ready(core) | NodeInit::Given { core, .. } => core.config().team.clone(),
        NodeInit::Pending { config, .. } => config.team.clone(),
    };
    // A given start state, checked against the vehicle's first sample: (origin, its time).
    let mut given_start = match &init {
        NodeInit::Given { core, origin } => Some((*origin, core.filter().time())),
        _ => None,
    };
    let (id, mut core, mut pending_init) = match init {
        NodeInit::Ready(core) | NodeInit::Given { core, .. } => (core.id(), Some(*core), None),
        NodeInit::Pending { config, origin, state, from_autopilot } => {
            (config.id, None, Some((*config, origin, state, from_autopilot)))
        }
    };
    let mut handover = pending_init.as_ref().is_some_and(|p| p.3).then(super::handover::Handover::new);
    // MAV_CMD_SET_EKF_SOURCE_SET after a hand-over start: (set, tries, next wall time)
    let mut source_set: Option<(u8, u32, u64)> = None;
    // The origin came from the vehicle (recorded with the Init event, for replay).
    let mut origin_from_vehicle: Option<wire::GeoOrigin> = None;
    let sysid = u8::try_from(id)
        .map_err(|_| NodeError::Invalid(format!("platform id {id}: a node's platform id is a MAVLink system id (1..=255)")))?;
    let mut last_imu_t: Option<TimeUs> = None;
    let mut before_init = 0u64;
    let mut sim_state_init = None;
    let (mut last_vehicle_seq, mut vehicle_lost): (Option<u8>, u64) = (None, 0);
    let mut vehicle_other_dialect = 0u64;
    let clock = std::time::Instant::now();
    let wall_us = move || clock.elapsed().as_micros() as u64;
    let mut vehicle = VehicleLink::open(&links.vehicle).await?;
    if let Some(key) = &links.vehicle_key {
        vehicle.sign(key, sysid);
    }
    let vehicle = Arc::new(vehicle);
    if let Some(granted) = vehicle.recv_buffer() {
        tracing::info!(platform = id, bytes = granted, "vehicle socket receive buffer");
    }
    let coop = CoopLink::open(&links.coop, COOP_RECV_BUFFER).await?;
    let _ = bound.send(coop.local_addr());
    tracing::info!(platform = id, vehicle = %links.vehicle, coop = %coop.describe(), "node started");
    let mut peers = PeerTable::new(id, &team, &links.peers);
    let mut decoder = links.profile.decoder();
    let mut rates = RateRequests::new(&links.profile, sysid);
    if handover.is_some() {
        // the autopilot's fix and estimate, fresh at the loss
        rates.add("GPS_RAW_INT", 24, 5.0);
        rates.add("GLOBAL_POSITION_INT", 33, 10.0);
        rates.add("ATTITUDE", 30, 10.0);
    }
    let mut odometry = OdometryOutput::new(links.profile.output.odometry_rate_hz, links.profile.output.odometry_frame);
    let lpn = links.profile.output.local_position_ned;
    let mut gps_input = GpsInputOutput::new(links.profile.output.gps_input_rate_hz, links.profile.geo_origin());
    let profile_origin = links.profile.geo_origin();
    let mut vehicle_origin_checked = false;
    let mut origin_offer = if links.profile.output.set_origin { OriginOffer::new(profile_origin, sysid) } else { None };
    // The team clock through TIMESYNC (clock = "companion" or "auto").
    let timesync_wanted = matches!(links.profile.inputs.clock, TeamClock::Companion | TeamClock::Auto);
    let mut timesync = TimeSync::default();
    let mut clock_said: Option<ClockSource> = None;
    // A ranging device beside the vehicle link.
    let mut range_lines = links.ranges.as_ref().map(|_| super::ranging::RangeLines::new(id, links.profile.inputs.epoch_grid_ms));
    let mut range_rx = match links.ranges.clone() {
        Some(source) => Some(spawn_range_reader(source)?),
        None => None,
    };
    let mut clock_rtt_us: Option<i64> = None;
    let mut reboots_seen = 0u64;
    let mut hand_over_state: Option<InsState> = None;
    let mut source_set_result = None;

    // The vehicle link is read on its own task (a serial or TCP read has no timeout).
    let (vtx, mut vrx) = tokio::sync::mpsc::channel::<Received>(4096);
    let reader = {
        let vehicle = vehicle.clone();
        tokio::spawn(async move {
            let mut buf = vec![0u8; 65_536];
            loop {
                match vehicle.recv(&mut buf).await {
                    Ok(frames) => {
                        for frame in frames {
                            if vtx.send(frame).await.is_err() {
                                return;
                            }
                        }
                    }
                    Err(e) => {
                        tracing::warn!(error = %e, "vehicle link read error");
                        tokio::time::sleep(Duration::from_millis(10)).await;
                    }
                }
            }
        })
    };

    // MAVLink numbers each link on its own: one sequence counter per link.
    // the link id is the node's system id: one signing stream per node
    let resume_after = match (&links.team_key, &links.signing_state) {
        (Some(_), Some(path)) => load_signing_state(path)?,
        _ => 0,
    };
    let signer = links.team_key.clone().map(|k| Signer::new(k, sysid, resume_after));
    let save_state = |seqs: &Sequences| {
        if let (Some(path), Some(signer)) = (&links.signing_state, &seqs.signer)
            && let Err(e) = save_signing_state(path, signer)
        {
            tracing::warn!(path = %path.display(), error = %e, "could not save the signing state");
        }
    };
    let mut verifier = links.team_key.clone().map(Verifier::new);
    let mut seqs = Sequences { tx: CoopTx::default(), sysid: u32::from(id), coop: 0, vehicle: 0, signer };
    let mut summary_counts = (0u64, 0u64, 0u64, 0u64);
    let mut tick = tokio::time::interval(Duration::from_millis(25));
    let mut beats = 0u32;
    let mut last_vehicle = tokio::time::Instant::now();
    let mut last_tick = tokio::time::Instant::now();
    let mut heard_vehicle = false;
    let mut ending: Option<tokio::time::Instant> = None;
    let mut buf = vec![0u8; 65_536];
    tokio::pin!(shutdown);
    // Announce ourselves to the vehicle at once (a udpin peer learns our address from it).
    vehicle.send(&seqs.vehicle(), &heartbeat()).await;
    loop {
        let inputs: Vec<NodeInput> = tokio::select! {
            _ = &mut shutdown => break,
            _ = tick.tick() => {
                // A tick long after the last one: this process was frozen (SIGSTOP, a stalled
                // machine). The silence was ours, not the vehicle's: start its idle clock again.
                let now_tick = tokio::time::Instant::now();
                if now_tick.duration_since(last_tick) > FROZEN_TICK_GAP {
                    tracing::warn!(platform = id, gap_ms = now_tick.duration_since(last_tick).as_millis() as u64, "node was frozen");
                    last_vehicle = now_tick;
                }
                last_tick = now_tick;
                if let (Some(idle), true, None) = (links.idle_exit, heard_vehicle, ending)
                    && last_vehicle.elapsed() >= idle
                {
                    tracing::info!(platform = id, "vehicle silent: closing the last instant");
                    ending = Some(tokio::time::Instant::now() + links.grace);
                    if let Some(core) = core.as_mut() {
                        record_event(&recorder, id, &NodeEvent::EndOfInput);
                        let out = core.end_of_input();
                        send_all(&coop, &peers, &vehicle, &mut seqs, out, &recorder, sysid, &VehicleOutputs { local_position_ned: lpn, clock: &decoder }).await;
                    }
                }
                if heard_vehicle && let Some(cmd) = rates.poll(wall_us()) {
                    to_vehicle(&vehicle, &mut seqs, &recorder, sysid, &cmd).await;
                }
                if heard_vehicle && let Some(m) = origin_offer.as_mut().and_then(|o| o.poll(wall_us())) {
                    to_vehicle(&vehicle, &mut seqs, &recorder, sysid, &m).await;
                }
                if let Some((set, tries, next)) = source_set
                    && wall_us() >= next
                {
                    source_set = (tries < 3).then_some((set, tries + 1, wall_us() + 1_000_000));
                    to_vehicle(&vehicle, &mut seqs, &recorder, sysid, &super::handover::ekf_source_set(set, sysid)).await;
                }
                if heard_vehicle && timesync_wanted && let Some(req) = timesync.poll(wall_us(), unix_now_ns(), sysid) {
                    to_vehicle(&vehicle, &mut seqs, &recorder, sysid, &req).await;
                }
                if let Some(core) = core.as_mut() {
                    let now = wall_us();
                    record_event(&recorder, id, &NodeEvent::Poll { wall_us: now });
                    let out = core.poll(now);
                    send_all(&coop, &peers, &vehicle, &mut seqs, out, &recorder, sysid, &VehicleOutputs { local_position_ned: lpn, clock: &decoder }).await;
                }
                if ending.is_some_and(|end| tokio::time::Instant::now() >= end) {
                    if let Some(core) = core.as_mut() {
                        record_event(&recorder, id, &NodeEvent::RunPending);
                        let out = core.run_pending();
                        send_all(&coop, &peers, &vehicle, &mut seqs, out, &recorder, sysid, &VehicleOutputs { local_position_ned: lpn, clock: &decoder }).await;
                    }
                    break;
                }
                beats += 1;
                if beats % 40 != 1 {
                    continue; // heartbeat at 1 Hz, timeouts and idle checks at 40 Hz
                }
                let hb = heartbeat();
                vehicle.send(&seqs.vehicle(), &hb).await;
                let frame = seqs.coop_frame(&hb);
                peers.expire(wall_us());
                send_to_peers(&coop, &peers, &[frame], &mut seqs.tx).await;
                if (beats / 40).is_multiple_of(SIGNING_STATE_EVERY) {
                    save_state(&seqs);
                }
                continue;
            }
            frame = vrx.recv() => {
                let Some((header, msg, bytes)) = frame else { return Err(NodeError::VehicleClosed) };
                record_frame(&recorder, Link::Vehicle(sysid), Direction::Rx, &bytes);
                summary_counts.0 += 1;
                last_vehicle = tokio::time::Instant::now();
                heard_vehicle = true;
                if header.system_id != u32::from(id) {
                    summary_counts.1 += 1;
                    continue;
                }
                if header.component_id == 1 {
                    // A gap is loss; a frame from behind the last one (reordered on the way) was
                    // counted lost in its gap and is not.
                    match last_vehicle_seq.map(|last| header.sequence.wrapping_sub(last)) {
                        None => last_vehicle_seq = Some(header.sequence),
                        Some(0) => {}
                        Some(ahead) if ahead < 128 => {
                            vehicle_lost += u64::from(ahead - 1);
                            last_vehicle_seq = Some(header.sequence);
                        }
                        Some(_) => vehicle_lost = vehicle_lost.saturating_sub(1),
                    }
                }
                // A message of the autopilot's own dialect: its sequence number counted above,
                // nothing for the node in it.
                let Some(msg) = msg else {
                    vehicle_other_dialect += 1;
                    continue;
                };
                if let (MavMessage::EKF_STATUS_REPORT(m), Some(offer)) = (&msg, origin_offer.as_mut()) {
                    offer.on_ekf_status(m.flags.bits());
                }
                if let MavMessage::TIMESYNC(m) = &msg {
                    match timesync.on_message(m, unix_now_ns(), (header.system_id as u8, header.component_id), decoder.clock_offset_us()) {
                        TimesyncReply::Answer(answer) => to_vehicle(&vehicle, &mut seqs, &recorder, sysid, &MavMessage::TIMESYNC(answer)).await,
                        TimesyncReply::Sample if timesync_wanted => {
                            if let Some((offset_us, rtt_us)) = timesync.offset_us()
                                && decoder.clock_offset_us().is_none_or(|o| (o - offset_us).abs() > CLOCK_UPDATE_US)
                                && decoder.clock_source() != Some(ClockSource::SystemTime)
                            {
                                record_event(&recorder, id, &NodeEvent::Clock { offset_us, rtt_us });
                                decoder.set_companion_offset(offset_us);
                                clock_rtt_us = Some(rtt_us);
                            }
                        }
                        _ => {}
                    }
                    continue;
                }
                if let Some(h) = handover.as_mut()
                    && let Some((_, Some(origin), state @ None, true)) = &mut pending_init
                {
                    match h.on_message(&msg, origin) {
                        Some(super::handover::HandoverEvent::GnssLost { time_boot_ms, state: s }) => match decoder.team_time_of_boot_ms(time_boot_ms) {
                            Some(t0) => {
                                tracing::info!(platform = id, pos = ?s.pos_ned_m, "GNSS lost: starting from the autopilot's estimate");
                                *state = Some((Some(t0), *s));
                                hand_over_state = Some(*s);
                                if let Some(set) = links.profile.output.takeover_source_set {
                                    source_set = Some((set, 0, 0));
                                }
                            }
                            None => {
                                tracing::warn!(platform = id, "GNSS lost before the team clock is known: waiting for it");
                                h.retry();
                            }
                        },
                        Some(super::handover::HandoverEvent::GnssLostWithoutEstimate) => {
                            tracing::warn!(platform = id, "GNSS lost, and no estimate of the autopilot's to start from yet")
                        }
                        None => {}
                    }
                }
                if let MavMessage::SIM_STATE(m) = &msg
                    && let Some((_, Some(origin), state @ None, false)) = &mut pending_init
                    && let Some(t0) = last_imu_t
                {
                    // (before the team clock maps the IMU's stamps there is no time to start at)
                    match wire::ins_state_from_sim_state(m, origin) {
                        Ok(s) => {
                            *state = Some((Some(t0), s));
                            sim_state_init = Some((t0, s.pos_ned_m));
                        }
                        Err(e) => {
                            summary_counts.1 += 1;
                            tracing::warn!(platform = id, error = %e, "SIM_STATE refused for initialisation");
                        }
                    }
                }
                if let Some((config, Some(origin), Some((t0, state)), _)) = &pending_init
                    && let Some(t0) = t0.or(last_imu_t)
                {
                    let made = NodeCore::new(config.clone(), t0, NavState::for_model(&config.model, *state))?;
                    tracing::info!(platform = id, t0 = %t0, pos = ?made.filter().position_ned_m(), lat_deg = origin.lat_deg, "initialised");
                    let o = origin_from_vehicle.map(|o| [o.lat_deg, o.lon_deg, o.alt_m]);
                    let start = hand_over_state.as_ref().map(super::log::StartState::of);
                    record_event(&recorder, id, &NodeEvent::Init { t0_us: t0.0, origin: o, state: start });
                    core = Some(made);
                    pending_init = None;
                }
                if matches!(msg, MavMessage::SIM_STATE(_)) {
                    continue;
                }
                let mut inputs = Vec::new();
                let events = decoder.decode(&msg);
                if decoder.counters.reboots != reboots_seen {
                    // the autopilot's boot clock started again: the TIMESYNC answers are of the boot before
                    reboots_seen = decoder.counters.reboots;
                    timesync.reset();
                    clock_said = None;
                    tracing::warn!(platform = id, "the autopilot rebooted: mapping its clock again");
                }
                if decoder.clock_source() != clock_said {
                    clock_said = decoder.clock_source();
                    match clock_said {
                        Some(ClockSource::Timesync) => tracing::info!(platform = id, offset_us = decoder.clock_offset_us(), rtt_us = clock_rtt_us, "team clock: the companion's clock, mapped to the autopilot's boot clock by TIMESYNC"),
                        Some(ClockSource::SystemTime) => tracing::info!(platform = id, offset_us = decoder.clock_offset_us(), "team clock: the autopilot's Unix time (SYSTEM_TIME, from GNSS)"),
                        None => {}
                    }
                }
                for event in events {
                    match event {
                        VehicleEvent::Input(input) => {
                            if let Some(t) = input.drive_time()
                                && let Some((origin, t0)) = given_start.take()
                                && t.0 > t0.0.saturating_add(STALE_START_US)
                                && let Some(refused) = core.take()
                            {
                                let late_s = (t.0 - t0.0) as f64 / 1e6;
                                println!(
                                    "node {id} start state refused: given for t {t0}, the vehicle is at {t} ({late_s:.1} s later): stale; waiting for SIM_STATE"
                                );
                                tracing::warn!(platform = id, late_s, "the given start state is stale: waiting for SIM_STATE");
                                record_event(&recorder, id, &NodeEvent::StartRefused { given_t0_us: t0.0, vehicle_t_us: t.0 });
                                pending_init = Some((refused.config().clone(), Some(origin), None, false));
                            }
                            if core.is_none() {
                                last_imu_t = input.drive_time().or(last_imu_t);
                                before_init += 1;
                            } else {
                                inputs.push(input);
                            }
                        }
                        VehicleEvent::Ack(ack) => {
                            if ack.command == crate::protocol::dialect::cooploc::MavCmd::MAV_CMD_SET_EKF_SOURCE_SET && source_set.is_some() {
                                source_set = None;
                                source_set_result = Some(ack.result);
                                tracing::info!(platform = id, result = ?ack.result, "the autopilot answered the EKF source-set switch");
                            }
                            if let Some(r) = rates.on_ack(&ack) {
                                match &r.outcome {
                                    Some(RateOutcome::Accepted) => tracing::info!(platform = id, message = r.message, rate_hz = r.rate_hz, "the autopilot accepted the rate"),
                                    other => tracing::warn!(platform = id, message = r.message, rate_hz = r.rate_hz, outcome = ?other, "the autopilot refused the rate; navigating on what it sends"),
                                }
                            }
                        }
                        VehicleEvent::Origin(o) => {
                            // (the EKF's origin: HOME_POSITION is where it armed, elsewhere)
                            if let Some(offer) = origin_offer.as_mut()
                                && offer.settled.is_none()
                                && matches!(msg, MavMessage::GPS_GLOBAL_ORIGIN(_))
                            {
                                let ours = offer.on_origin(o);
                                tracing::info!(platform = id, ours, lat_deg = o.lat_deg, lon_deg = o.lon_deg, "the autopilot has an origin");
                                if let (false, Some(team), Some(odometry)) = (ours, profile_origin, odometry.as_mut()) {
                                    // its own (from its GNSS): ODOMETRY goes out in its frame
                                    odometry.set_frame_offset(wire::geodetic_to_ned(&team, &wire::Geodetic { lat_deg: o.lat_deg, lon_deg: o.lon_deg, alt_m: o.alt_m }));
                                }
                            }
                            if let Some((config, origin @ None, _, _)) = &mut pending_init {
                                tracing::info!(platform = id, lat_deg = o.lat_deg, lon_deg = o.lon_deg, alt_m = o.alt_m, "origin from the vehicle");
                                config.model.set_latitude(o.lat_deg);
                                *origin = Some(o);
                                origin_from_vehicle = Some(o);
                                vehicle_origin_checked = true;
                            }
                            if let (Some(mine), false) = (profile_origin, vehicle_origin_checked) {
                                vehicle_origin_checked = true;
                                let apart = wire::geodetic_to_ned(&mine, &wire::Geodetic { lat_deg: o.lat_deg, lon_deg: o.lon_deg, alt_m: o.alt_m }).xy().norm();
                                if apart > 1000.0 {
                                    tracing::warn!(platform = id, apart_m = apart, "the vehicle's origin is far from the profile's [origin]: positions sent back are in the profile's frame");
                                }
                            }
                        }
                        VehicleEvent::Nothing => {}
                    }
                }
                if inputs.is_empty() {
                    continue;
                }
                inputs
            }
            Some((bytes, arrival_us)) = async { range_rx.as_mut()?.recv().await }, if range_rx.is_some() => {
                let Some(lines) = range_lines.as_mut() else { continue };
                let mut inputs = Vec::new();
                for (epoch, range) in lines.push(&bytes, arrival_us) {
                    // recorded before it is taken: replay takes the same
                    record_event(&recorder, id, &NodeEvent::Range { epoch, range });
                    if core.is_some() {
                        inputs.push(NodeInput::OwnRange { epoch, range });
                    } else {
                        before_init += 1;
                    }
                }
                if inputs.is_empty() {
                    continue;
                }
                inputs
            }
            r = coop.recv(&mut buf) => {
                let (n, from) = match r {
                    Ok(got) => got,
                    Err(e) if e.kind() == std::io::ErrorKind::BrokenPipe => return Err(NodeError::io("the cooperative radio")(e)),
                    Err(_) => continue,
                };
                if n == 0 && from == Source::Radio {
                    continue; // no whole frame in these bytes yet
                }
                summary_counts.2 += 1;
                let frames = match &mut verifier {
                    // only what the team key signed is logged and taken (a replay sees the same)
                    Some(v) => {
                        let got = v.datagram(&buf[..n], wall_now_ns() / 1000);
                        if !got.refused.is_empty() {
                            tracing::debug!(platform = id, %from, refused = ?got.refused, "cooperative frames refused by signing");
                        }
                        for span in &got.spans {
                            record_frame(&recorder, Link::Coop(sysid), Direction::Rx, &buf[span.clone()]);
                        }
                        got.frames
                    }
                    // Every frame of the datagram (a packed batch holds several), logged as
                    // taken: the log and the core see the same frames.
                    None => super::vehicle_link::split_frames(&buf[..n])
                        .into_iter()
                        .filter_map(|(header, msg, bytes)| {
                            record_frame(&recorder, Link::Coop(sysid), Direction::Rx, &bytes);
                            Some((header, msg?))
                        })
                        .collect(),
                };
                if frames.is_empty() {
                    summary_counts.3 += 1;
                    tracing::debug!(platform = id, %from, bytes = n, "cooperative datagram without a valid frame dropped");
                    continue;
                }
                let mut inputs = Vec::with_capacity(frames.len());
                for (header, msg) in frames {
                    if header.system_id == u32::from(id) {
                        continue; // our own traffic, looped back
                    }
                    let gcs = matches!(&msg, MavMessage::HEARTBEAT(hb) if hb.mavtype == MavType::MAV_TYPE_GCS);
                    if let Some(addr) = from.addr() {
                        match peers.heard(peers.sender(header.system_id, gcs), addr, wall_us()) {
                            Heard::New => tracing::info!(platform = id, peer = %from, sysid = header.system_id, "new peer"),
                            Heard::Moved => tracing::info!(platform = id, peer = %from, sysid = header.system_id, "peer moved"),
                            Heard::Refused => tracing::debug!(platform = id, peer = %from, "ground station refused: observer table full"),
                            Heard::Known | Heard::Ignored => {}
                        }
                        if matches!(from, Source::Group(_)) {
                            peers.heard_on_group(addr, wall_us());
                        }
                    }
                    let Ok(from) = PlatformId::try_from(header.system_id) else { continue };
                    inputs.push(NodeInput::Peer { from, msg: Box::new(msg) });
                }
                inputs
            }
        };
        let Some(core) = core.as_mut() else { continue };
        // Wall time reaches the core only through recorded polls, so a replay is exact: on the
        // ticks, and before a frame read while the ticks are late (this process was frozen and
        // its sockets hold what came meanwhile: the core must see the freeze before that).
        let mut out = Vec::new();
        if last_tick.elapsed() > FROZEN_TICK_GAP {
            let now = wall_us();
            record_event(&recorder, id, &NodeEvent::Poll { wall_us: now });
            out.extend(core.poll(now));
        }
        let vehicle_input = inputs.iter().any(|i| i.drive_time().is_some());
        for input in inputs {
            out.extend(core.handle(input));
        }
        if vehicle_input {
            let nav = core.navigation();
            let odo = odometry.as_mut().and_then(|o| o.poll(&nav, |t| decoder.to_vehicle_time(t)));
            let gps = gps_input.as_mut().and_then(|g| g.poll(&nav, |t| decoder.to_vehicle_time(t)));
            for msg in odo.iter().chain(&gps) {
                to_vehicle(&vehicle, &mut seqs, &recorder, sysid, msg).await;
            }
        }
        send_all(
            &coop,
            &peers,
            &vehicle,
            &mut seqs,
            out,
            &recorder,
            sysid,
            &VehicleOutputs { local_position_ned: lpn, clock: &decoder },
        )
        .await;
    }
    reader.abort();
    save_state(&seqs);
    Ok(NodeSummary {
        stats: core.as_ref().map(|c| c.stats.clone()).unwrap_or_default(),
        flagged: core.as_ref().map(|c| c.flagged().iter().copied().collect()).unwrap_or_default(),
        estimate: core.as_ref().map(NodeCore::estimate),
        before_init,
        sim_state_init,
        vehicle_frames: summary_counts.0,
        vehicle_rejected: summary_counts.1,
        vehicle_other_dialect,
        vehicle_lost,
        coop_frames: summary_counts.2,
        coop_rejected: summary_counts.3,
        coop_noise_bytes: coop.noise_bytes(),
        coop_signing: verifier.map(|v| v.counters).unwrap_or_default(),
        vehicle_signing: vehicle.signing_counters(),
        peers: peers.addresses(),
        peer_counters: peers.counters,
        coop_tx: CoopTx { dropped: coop.dropped(), ..seqs.tx },
        wall_s: clock.elapsed().as_secs_f64(),
        inputs: decoder.counters.clone(),
        imu_rate_hz: decoder.imu_rate_hz(),
        rate_requests: rates.requests.clone(),
        odometry_sent: odometry.as_ref().map_or(0, |o| o.sent),
        odometry_resets: odometry.as_ref().map_or(0, |o| o.reset_counter),
        gps_input_sent: gps_input.as_ref().map_or(0, |g| g.sent),
        origin_from_vehicle,
        clock: decoder
            .clock_source()
            .zip(decoder.clock_offset_us())
            .map(|(source, offset)| (source, offset, if source == ClockSource::Timesync { clock_rtt_us } else { None })),
        timesync_requests: timesync.requests,
        timesync_refused: timesync.refused,
        range_input: range_lines.map(|l| l.counters),
        origin_offer,
        hand_over: hand_over_state.map(|s| (s.pos_ned_m, source_set_result)),
    })
}
