//! The node shell: everything a node does between its sockets and its [`NodeCore`], with no
//! sockets and no clocks (sans-io). Bytes, frames and clock readings go in; messages for the
//! vehicle, cooperative frames for the link and records for the log come out, in the order they
//! must be acted on ([`ShellOutput`]).
//!
//! The shell owns:
//! - the cooperative datagram: split into frames, or checked against the team key (only what
//!   the key signed is logged and taken), the sender learned into the [`PeerTable`], the
//!   node's own looped-back traffic dropped;
//! - the vehicle's frames: its system id checked, sequence gaps counted, TIMESYNC answered and
//!   sampled, the origin offer, the rate requests and their acknowledgements, decoding into the
//!   core's inputs ([`VehicleInputs`]);
//! - the start: the origin and the initial state (given, from SIM_STATE, or from the
//!   autopilot's estimate once it has GNSS, [`super::handover`]: then the GNSS fixes go to the
//!   core, and ODOMETRY and the EKF source set follow the take-over and the hand-back), a
//!   given state refused when the
//!   vehicle's first sample shows it stale; a saved state restored, given the autopilot's own
//!   estimate when its EKF vouches for it ([`super::autopilot_fix`]);
//! - the clock ticks: polls of the core, heartbeats, peer expiry, the signing state, the frozen
//!   process, the end of the vehicle's stream;
//! - what goes back: ODOMETRY, GPS_INPUT and LOCAL_POSITION_NED to the vehicle, the core's
//!   messages signed and packed for the cooperative link.
//!
//! The tokio runner (`cooploc::node::runner`) only reads the sockets, calls the shell and carries out
//! its outputs. Wall time reaches the core only through recorded polls, so a log replays
//! exactly.

use super::autopilot::{
    GpsInputOutput, OdometryOutput, OriginOffer, RateOutcome, RateRequest, RateRequests, TimeSync, TimesyncReply,
};
use super::autopilot_fix::{AutopilotEstimate, FIX_STALE_MS};
use super::core::{NodeConfig, NodeCore, NodeInput, NodeOutput, NodeStats};
use super::error::NodeError;
use super::handover::{Handover, HandoverEvent};
use super::inputs::{ClockSource, InputCounters, VehicleEvent, VehicleInputs};
use super::log::{CoopUpdateRecord, NodeEvent};
use super::peers::Source;
use super::peers::{Heard, PeerCounters, PeerTable};
use super::profile::{TeamClock, VehicleProfile};
use super::saved::{SAVE_EVERY_US, SavedState};
use crate::estimation::PlatformId;
use crate::estimation::coast::{CoastBounds, GapFix};
use crate::estimation::ins::InsState;
use crate::estimation::nav::NavState;
use crate::protocol::MavMessage;
use crate::protocol::dialect::cooploc::{MavAutopilot, MavCmd, MavResult, MavType};
use crate::protocol::framing::Received;
use crate::protocol::framing::{Direction, Link};
use crate::protocol::signing::{Signer, SigningCounters, TeamKey, Verifier};
use crate::protocol::wire;
use crate::time::TimeUs;
use mavlink_core::MavHeader;
use std::net::SocketAddr;
use std::time::Duration;

/// How far (vehicle time) the vehicle's first sample may be after the time of a given start
/// state ([`NodeInit::Given`]) for the state to be trusted, us.
pub const STALE_START_US: u64 = 10_000_000;

/// How long (team clock, from the vehicle's first sample) a node with a saved state waits for its
/// autopilot's estimate before restoring without it, us (the rate requests for it, sent first,
/// are answered within a round trip; a refusal ends the wait at once).
pub const FIX_WAIT_US: u64 = 3_000_000;

/// What the autopilot's estimate says at a sample, carried to it, with its EKF flags; or why it
/// is not used.
type FixOutcome = Result<(GapFix, u16), String>;

/// ATTITUDE's message id.
const ATTITUDE_ID: u32 = 30;

/// What a node with a saved state asks its autopilot for, at 10 Hz, until the restore is decided
/// (then at the autopilot's default rate again: ATTITUDE, GLOBAL_POSITION_INT and
/// EKF_STATUS_REPORT are at most 40 + 40 + 38 B of MAVLink 2 frames, 1.18 kB/s at 10 Hz, a fifth
/// of a 57,600-baud telemetry link's 5.76 kB/s).
const FIX_MESSAGES: [(&str, u32); 4] =
    [("ATTITUDE", ATTITUDE_ID), ("GLOBAL_POSITION_INT", 33), ("EKF_STATUS_REPORT", 193), ("ESTIMATOR_STATUS", 230)];

/// How often the signing state is written (heartbeats).
pub const SIGNING_STATE_EVERY: u32 = 5;

/// The runner ticks the shell this often.
pub const TICK: Duration = Duration::from_millis(25);

/// Ticks this far apart mean the process itself was frozen (SIGSTOP, a stalled machine), us.
const FROZEN_TICK_GAP_US: u64 = 500_000;

/// A new TIMESYNC mapping replaces the one in use when they differ by more than this, us.
const CLOCK_UPDATE_US: i64 = 200;

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
    /// `from_autopilot`: the state comes from the autopilot's own estimate once it has GNSS (the
    /// hand-over, [`super::handover`]), not from SIM_STATE.
    Pending {
        config: Box<NodeConfig>,
        origin: Option<wire::GeoOrigin>,
        state: Option<(Option<TimeUs>, InsState)>,
        from_autopilot: bool,
    },
}

/// A node still waiting for its origin or its initial state.
#[derive(Debug)]
struct Pending {
    config: NodeConfig,
    origin: Option<wire::GeoOrigin>,
    /// The initial state and its time (None: the last IMU sample's).
    state: Option<(Option<TimeUs>, InsState)>,
    from_autopilot: bool,
}

/// What the shell is told at the start, besides how the node starts.
#[derive(Debug, Clone)]
pub struct ShellConfig {
    /// The vehicle: which messages to read, what to ask for and send back.
    pub profile: VehicleProfile,
    /// The team's signing key (None: unsigned cooperative traffic).
    pub team_key: Option<TeamKey>,
    /// The signing timestamp to sign above (the signing state file's, 0 without one).
    pub signing_resume_after: u64,
    /// Peers known from the start.
    pub peers: Vec<SocketAddr>,
    /// End when the vehicle has been silent this long (after its first frame), then listen to
    /// the peers for `grace` and run the epochs still pending.
    pub idle_exit: Option<Duration>,
    pub grace: Duration,
    /// A ranging device on the companion feeds [`NodeShell::range_bytes`].
    pub ranges: bool,
    /// The cooperative link is UDP: frames also go to every unicast peer (a serial radio has
    /// none).
    pub unicast: bool,
    /// A log is kept: the shell gives [`ShellOutput::Record`]s.
    pub record: bool,
    /// The state the node saved before (its state file, read and checked): restored at the
    /// vehicle's first sample when plausible ([`super::saved`]).
    pub restore: Option<SavedState>,
    /// Keep the navigation state: the shell gives [`ShellOutput::NavState`] every
    /// [`SAVE_EVERY_US`] of the team clock.
    pub save_state: bool,
    /// The shell is fed a log (`cooploc replay`): the mapping of the vehicle's clock to the
    /// team's comes from the log's Clock events ([`NodeShell::logged_clock`]), not from TIMESYNC
    /// answers, whose readings of the companion's clock the log does not hold.
    pub clock_from_log: bool,
}

impl ShellConfig {
    /// A configuration for `profile` with nothing around the node: unsigned, no peers, no idle
    /// end, no ranging device, no unicast, no log, no saved state, the clock mapped live (what
    /// the fault harness, a replay and the tests start from, setting what they need).
    pub fn bare(profile: VehicleProfile) -> Self {
        ShellConfig {
            profile,
            team_key: None,
            signing_resume_after: 0,
            peers: Vec::new(),
            idle_exit: None,
            grace: Duration::ZERO,
            ranges: false,
            unicast: false,
            record: false,
            restore: None,
            save_state: false,
            clock_from_log: false,
        }
    }
}

/// The two clocks of the companion, read by the runner at each call.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Now {
    /// Monotonic wall time since the node started, us.
    pub wall_us: u64,
    /// The companion's Unix time, ns (signing timestamps, TIMESYNC, the team clock of
    /// `clock = "companion"`).
    pub unix_ns: i64,
}

impl Now {
    fn unix_us(self) -> u64 {
        u64::try_from(self.unix_ns / 1000).unwrap_or(0)
    }
}

/// Something for the log.
#[derive(Debug, Clone)]
pub enum Record {
    Event(NodeEvent),
    Frame {
        link: Link,
        dir: Direction,
        bytes: Vec<u8>,
    },
    /// An estimate the node broadcast, as it went on the wire
    /// ([`wire::EstimateReport::as_sent`]).
    Estimate(wire::EstimateReport),
    /// The internals of a joint update.
    Update(Box<CoopUpdateRecord>),
}

/// What the runner must do, in order.
#[derive(Debug, Clone)]
pub enum ShellOutput {
    /// Send a message to the vehicle (the vehicle link frames it, and signs it when signed).
    Vehicle { header: MavHeader, msg: MavMessage },
    /// Send cooperative frames, in order: onto the group or the radio, and to these unicast
    /// peers. Report what went out with [`NodeShell::sent`].
    Coop { frames: Vec<Vec<u8>>, unicast: Vec<SocketAddr> },
    /// Write to the log.
    Record(Record),
    /// Keep this signing state (the text of the signing state file).
    SigningState(String),
    /// Keep this navigation state (the text of the state file, [`super::saved`]).
    NavState(String),
}

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

/// What the links know that the shell does not, for the summary.
#[derive(Debug, Clone, Default)]
pub struct LinkFacts {
    /// Bytes of a serial radio's stream that were no valid frame.
    pub coop_noise_bytes: u64,
    /// Batches a serial radio could not take.
    pub coop_dropped: u64,
    /// What signing accepted and refused on a signed vehicle link.
    pub vehicle_signing: Option<SigningCounters>,
    /// How long the node ran, s.
    pub wall_s: f64,
}

/// The hand-over, at the end: where the node started, the GNSS fixes its filter took, the
/// losses and returns of the fix after the start, and the autopilot's answer to the last
/// source-set command.
#[derive(Debug, Clone, PartialEq)]
pub struct HandOverSummary {
    pub started_at_ned_m: nalgebra::Vector3<f64>,
    pub source_set: Option<MavResult>,
    pub fixes: u64,
    pub fixes_rejected: u64,
    pub losses: u64,
    pub returns: u64,
    /// Losses that were GNSS glitches the autopilot's EKF reported (the fix stayed).
    pub glitches: u64,
    /// The node navigates the vehicle now (GNSS gone).
    pub navigating: bool,
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
    /// With the hand-over (`init_from_autopilot`): see [`HandOverSummary`].
    pub hand_over: Option<HandOverSummary>,
}

/// One sequence counter per link (MAVLink numbers each link on its own) and the signer.
struct Sequences {
    coop: u8,
    vehicle: u8,
    /// Signs the cooperative frames, when the team has a key.
    signer: Option<Signer>,
}

/// The next header of a link whose counter is `seq`, from system `sysid`.
fn next_header(seq: &mut u8, sysid: u8) -> MavHeader {
    *seq = seq.wrapping_add(1);
    MavHeader { system_id: u32::from(sysid), component_id: wire::COMPANION_COMPID, sequence: *seq }
}

/// The vehicle's frames counted: received, from another system, of another dialect, and the
/// autopilot's sequence numbers ([`crate::protocol::sequence`]: the loss, late frames).
#[derive(Debug, Clone, Copy, Default)]
struct VehicleCounts {
    frames: u64,
    rejected: u64,
    other_dialect: u64,
    seq: crate::protocol::sequence::SequenceTracker,
}

/// The team clock's state: TIMESYNC and what the node last said about the clock.
struct Clock {
    wanted: bool,
    timesync: TimeSync,
    said: Option<ClockSource>,
    rtt_us: Option<i64>,
    reboots_seen: u64,
}

/// The autopilot's answers and outputs.
struct Autopilot {
    rates: RateRequests,
    odometry: Option<OdometryOutput>,
    gps_input: Option<GpsInputOutput>,
    local_position_ned: bool,
    profile_origin: Option<wire::GeoOrigin>,
    origin_offer: Option<OriginOffer>,
    origin_checked: bool,
    origin_from_vehicle: Option<wire::GeoOrigin>,
    /// MAV_CMD_SET_EKF_SOURCE_SET after a hand-over start: (set, tries, next wall time).
    source_set: Option<(u8, u32, u64)>,
    source_set_result: Option<MavResult>,
    takeover_source_set: Option<u8>,
    gnss_source_set: u8,
    /// ODOMETRY also while the autopilot navigates on GNSS (the profile's `odometry_with_gnss`).
    odometry_with_gnss: bool,
}

/// The sans-io node: see the module documentation.
pub struct NodeShell {
    id: PlatformId,
    sysid: u8,
    config: ShellConfig,
    core: Option<NodeCore>,
    pending: Option<Pending>,
    /// A given start state, checked against the vehicle's first sample: (origin, its time).
    given_start: Option<(wire::GeoOrigin, TimeUs)>,
    /// The saved state, until the first sample decides whether it is restored.
    restore: Option<SavedState>,
    /// The origin of the filter's NED frame, once the node has its state.
    nav_origin: Option<wire::GeoOrigin>,
    /// When the navigation state was last given to be saved (team clock).
    saved_at: Option<TimeUs>,
    handover: Option<Handover>,
    hand_over_state: Option<InsState>,
    /// The hand-over: GNSS is gone and the node navigates the vehicle (ODOMETRY goes out).
    taken_over: bool,
    /// The autopilot's estimate, followed while a saved state waits to be restored, and the
    /// vehicle's first sample (team clock) since when it has waited.
    fix: Option<AutopilotEstimate>,
    fix_wait_from: Option<TimeUs>,
    last_imu_t: Option<TimeUs>,
    before_init: u64,
    sim_state_init: Option<(TimeUs, nalgebra::Vector3<f64>)>,
    decoder: VehicleInputs,
    autopilot: Autopilot,
    clock: Clock,
    range_lines: Option<super::ranging::RangeLines>,
    peers: PeerTable,
    seqs: Sequences,
    verifier: Option<Verifier>,
    vehicle: VehicleCounts,
    coop_frames: u64,
    coop_rejected: u64,
    tx: CoopTx,
    beats: u32,
    last_tick_us: u64,
    last_vehicle_us: u64,
    heard_vehicle: bool,
    ending_at_us: Option<u64>,
    out: Vec<ShellOutput>,
}

fn heartbeat() -> MavMessage {
    wire::heartbeat(MavType::MAV_TYPE_ONBOARD_CONTROLLER, MavAutopilot::MAV_AUTOPILOT_INVALID)
}

impl NodeShell {
    /// A shell for a node that starts as `init` says, at `now`. Its first output is a
    /// HEARTBEAT to the vehicle (a `udpin` autopilot learns the node's address from it).
    pub fn new(init: NodeInit, config: ShellConfig, now: Now) -> Result<Self, NodeError> {
        let team = match &init {
            NodeInit::Ready(core) | NodeInit::Given { core, .. } => core.config().team.clone(),
            NodeInit::Pending { config, .. } => config.team.clone(),
        };
        let given_start = match &init {
            NodeInit::Given { core, origin } => Some((*origin, core.filter().time())),
            _ => None,
        };
        let nav_origin = given_start.map(|(o, _)| o);
        let restore = config.restore.clone();
        let (id, core, pending) = match init {
            NodeInit::Ready(core) | NodeInit::Given { core, .. } => (core.id(), Some(*core), None),
            NodeInit::Pending { config, origin, state, from_autopilot } => {
                (config.id, None, Some(Pending { config: *config, origin, state, from_autopilot }))
            }
        };
        let sysid = u8::try_from(id).map_err(|_| {
            NodeError::Invalid(format!("platform id {id}: a node's platform id is a MAVLink system id (1..=255)"))
        })?;
        let profile = &config.profile;
        let handover = pending.as_ref().is_some_and(|p| p.from_autopilot).then(Handover::new);
        let mut rates = RateRequests::new(profile, sysid);
        if handover.is_some() {
            // the autopilot's fix and estimate, fresh at the loss
            rates.add("GPS_RAW_INT", 24, 5.0);
            rates.add("GLOBAL_POSITION_INT", 33, 10.0);
            rates.add("ATTITUDE", 30, 10.0);
        }
        let fix = config.restore.is_some().then(AutopilotEstimate::new);
        if fix.is_some() && profile.inputs.request_rates {
            // first, so that an autopilot that has none says so before the IMU's first sample
            // has waited long
            // (EKF_STATUS_REPORT is ArduPilot's, ESTIMATOR_STATUS PX4's: each refuses the other)
            for (name, id) in FIX_MESSAGES.iter().rev() {
                rates.add_first(name, *id, 10.0);
            }
        }
        let profile_origin = profile.geo_origin();
        let autopilot = Autopilot {
            rates,
            odometry: OdometryOutput::new(profile.output.odometry_rate_hz, profile.output.odometry_frame),
            gps_input: GpsInputOutput::new(profile.output.gps_input_rate_hz, profile_origin),
            local_position_ned: profile.output.local_position_ned,
            profile_origin,
            origin_offer: if profile.output.set_origin { OriginOffer::new(profile_origin, sysid) } else { None },
            origin_checked: false,
            origin_from_vehicle: None,
            source_set: None,
            source_set_result: None,
            takeover_source_set: profile.output.takeover_source_set,
            gnss_source_set: profile.output.gnss_source_set,
            odometry_with_gnss: profile.output.odometry_with_gnss,
        };
        let clock = Clock {
            wanted: matches!(profile.inputs.clock, TeamClock::Companion | TeamClock::Auto) && !config.clock_from_log,
            timesync: TimeSync::default(),
            said: None,
            rtt_us: None,
            reboots_seen: 0,
        };
        let range_lines = config.ranges.then(|| super::ranging::RangeLines::new(id, profile.inputs.epoch_grid_ms));
        let signer = config.team_key.clone().map(|k| Signer::new(k, sysid, config.signing_resume_after));
        let mut shell = NodeShell {
            id,
            sysid,
            decoder: profile.decoder(),
            peers: PeerTable::new(id, &team, &config.peers),
            verifier: config.team_key.clone().map(Verifier::new),
            config,
            core,
            pending,
            given_start,
            restore,
            nav_origin,
            saved_at: None,
            handover,
            hand_over_state: None,
            taken_over: false,
            fix,
            fix_wait_from: None,
            last_imu_t: None,
            before_init: 0,
            sim_state_init: None,
            autopilot,
            clock,
            range_lines,
            seqs: Sequences { coop: 0, vehicle: 0, signer },
            vehicle: VehicleCounts::default(),
            coop_frames: 0,
            coop_rejected: 0,
            tx: CoopTx::default(),
            beats: 0,
            last_tick_us: now.wall_us,
            last_vehicle_us: now.wall_us,
            heard_vehicle: false,
            ending_at_us: None,
            out: Vec::new(),
        };
        let header = next_header(&mut shell.seqs.vehicle, shell.sysid);
        shell.out.push(ShellOutput::Vehicle { header, msg: heartbeat() });
        Ok(shell)
    }

    /// The node's platform id.
    pub fn id(&self) -> PlatformId {
        self.id
    }

    /// The core, once the node has its initial state.
    pub fn core(&self) -> Option<&NodeCore> {
        self.core.as_ref()
    }

    /// What the runner must do now, in order.
    pub fn take_outputs(&mut self) -> Vec<ShellOutput> {
        std::mem::take(&mut self.out)
    }

    /// What went out of one [`ShellOutput::Coop`].
    pub fn sent(&mut self, datagrams: u64, bytes: u64) {
        self.tx.datagrams += datagrams;
        self.tx.bytes += bytes;
    }

    /// The signing state to keep at the end (None: unsigned).
    pub fn signing_state(&self) -> Option<String> {
        self.seqs.signer.as_ref().map(crate::protocol::signing::state_text)
    }

    fn record(&mut self, record: Record) {
        if self.config.record {
            self.out.push(ShellOutput::Record(record));
        }
    }

    fn event(&mut self, event: NodeEvent) {
        self.record(Record::Event(event));
    }

    /// Sends one message to the vehicle (and logs it).
    fn send_vehicle(&mut self, msg: MavMessage) {
        let header = next_header(&mut self.seqs.vehicle, self.sysid);
        if self.config.record {
            self.record(Record::Frame {
                link: Link::Vehicle(self.sysid),
                dir: Direction::Tx,
                bytes: wire::to_frame(header, &msg),
            });
        }
        self.out.push(ShellOutput::Vehicle { header, msg });
    }

    /// The next cooperative frame of `msg`, signed when the team has a key.
    fn coop_frame(&mut self, msg: &MavMessage, now: Now) -> Vec<u8> {
        let header = next_header(&mut self.seqs.coop, self.sysid);
        let frame = match &mut self.seqs.signer {
            Some(s) => s.frame(header, msg, now.unix_us()),
            None => wire::to_frame(header, msg),
        };
        self.tx.frames += 1;
        self.tx.frame_bytes += frame.len() as u64;
        frame
    }

    /// Cooperative frames (in order) to the group and every unicast peer, or onto the radio.
    fn send_peers(&mut self, frames: Vec<Vec<u8>>) {
        if frames.is_empty() {
            return;
        }
        let unicast = if self.config.unicast { self.peers.addresses() } else { Vec::new() };
        self.out.push(ShellOutput::Coop { frames, unicast });
    }

    /// The core's outputs: its messages framed for the team (a record's first fragment alone,
    /// ahead of the rest), its estimate too, and to the vehicle as LOCAL_POSITION_NED when the
    /// profile asks for it, all to the log.
    fn core_outputs(&mut self, outputs: Vec<NodeOutput>, now: Now) {
        let mut frames = Vec::new();
        for output in outputs {
            let (msg, estimate) = match output {
                NodeOutput::ToPeers(msg) => (msg, None),
                // (logged and given to the vehicle as it goes on the wire; one no receiver would
                // take goes to neither)
                NodeOutput::Estimate(e) => {
                    let wanted = self.autopilot.local_position_ned || self.config.record;
                    (wire::estimate_to_message(&e), wanted.then(|| e.as_sent().ok()).flatten())
                }
                NodeOutput::Update(u) => {
                    self.record(Record::Update(u));
                    continue;
                }
            };
            let frame = self.coop_frame(&msg, now);
            if self.config.record {
                self.record(Record::Frame { link: Link::Coop(self.sysid), dir: Direction::Tx, bytes: frame.clone() });
            }
            if crate::protocol::budget::goes_alone(&msg) {
                self.send_peers(std::mem::take(&mut frames));
                self.send_peers(vec![frame]);
                continue;
            }
            frames.push(frame);
            if let Some(e) = estimate {
                if self.autopilot.local_position_ned {
                    let boot_ms = (self.decoder.to_vehicle_time(e.t) / 1000) as u32;
                    self.send_vehicle(wire::estimate_to_local_position(&e, boot_ms));
                }
                self.record(Record::Estimate(e));
            }
        }
        self.send_peers(frames);
    }

    /// A clock tick (every [`TICK`]): requests to the vehicle, a poll of the core, the heartbeat
    /// and peer expiry at 1 Hz, the end of the vehicle's stream. Returns false when the node is
    /// done (the grace after the vehicle went silent is over).
    pub fn tick(&mut self, now: Now) -> bool {
        // A tick long after the last one: this process was frozen (SIGSTOP, a stalled machine).
        // The silence was ours, not the vehicle's: start its idle clock again.
        let gap = now.wall_us.saturating_sub(self.last_tick_us);
        if gap > FROZEN_TICK_GAP_US {
            tracing::warn!(platform = self.id, gap_ms = gap / 1000, "node was frozen");
            self.last_vehicle_us = now.wall_us;
        }
        self.last_tick_us = now.wall_us;
        if let (Some(idle), true, None) = (self.config.idle_exit, self.heard_vehicle, self.ending_at_us)
            && now.wall_us.saturating_sub(self.last_vehicle_us) >= idle.as_micros() as u64
        {
            tracing::info!(platform = self.id, "vehicle silent: closing the last instant");
            self.ending_at_us = Some(now.wall_us + self.config.grace.as_micros() as u64);
            self.end_of_input(now);
        }
        self.requests(now);
        self.poll(now);
        if self.ending_at_us.is_some_and(|end| now.wall_us >= end) {
            self.run_pending(now);
            return false;
        }
        self.beats += 1;
        if self.beats % 40 == 1 {
            // heartbeat at 1 Hz, timeouts and idle checks at 40 Hz
            let hb = heartbeat();
            let header = next_header(&mut self.seqs.vehicle, self.sysid);
            self.out.push(ShellOutput::Vehicle { header, msg: hb.clone() });
            let frame = self.coop_frame(&hb, now);
            self.peers.expire(now.wall_us);
            self.send_peers(vec![frame]);
            if (self.beats / 40).is_multiple_of(SIGNING_STATE_EVERY)
                && let Some(state) = self.signing_state()
            {
                self.out.push(ShellOutput::SigningState(state));
            }
        }
        true
    }

    /// Wall time reaches the core only through recorded polls, so that a replay is exact: on
    /// the ticks, and here, before any input read while the ticks are late (this process was
    /// frozen and its sockets hold what came meanwhile: the core must see the freeze before
    /// that). The poll is logged ahead of the input, where a replay meets it. The tick's own
    /// clock is left as it was: the next tick still sees the freeze.
    fn catch_up(&mut self, now: Now) {
        if self.core.is_some() && now.wall_us.saturating_sub(self.last_tick_us) > FROZEN_TICK_GAP_US {
            self.event(NodeEvent::Poll { wall_us: now.wall_us });
            let out = self.core.as_mut().map(|c| c.poll(now.wall_us)).unwrap_or_default();
            self.core_outputs(out, now);
        }
    }

    /// The core's timers at `now` (retries, epoch timeouts), without the tick's chores
    /// (requests to the vehicle, heartbeats): what the fault harness calls between events.
    pub fn poll(&mut self, now: Now) {
        self.last_tick_us = now.wall_us;
        if self.core.is_some() {
            self.event(NodeEvent::Poll { wall_us: now.wall_us });
            let out = self.core.as_mut().map(|c| c.poll(now.wall_us)).unwrap_or_default();
            self.core_outputs(out, now);
        }
    }

    /// The vehicle's stream ended: the node closes its last instant and broadcasts.
    pub fn end_of_input(&mut self, now: Now) {
        if self.core.is_some() {
            self.event(NodeEvent::EndOfInput);
            let out = self.core.as_mut().map(NodeCore::end_of_input).unwrap_or_default();
            self.core_outputs(out, now);
        }
    }

    /// Runs the epochs still open with what is there (the end of a run).
    pub fn run_pending(&mut self, now: Now) {
        if self.core.is_some() {
            self.event(NodeEvent::RunPending);
            let out = self.core.as_mut().map(NodeCore::run_pending).unwrap_or_default();
            self.core_outputs(out, now);
        }
    }

    /// A vehicle sample or an own range already decoded (the fault harness holds samples, not
    /// frames); none before the node has its state.
    pub fn input(&mut self, input: NodeInput, now: Now) {
        self.catch_up(now);
        self.feed(vec![input], now);
    }

    /// What the node asks of the vehicle on a tick: rates, the origin, the EKF source set,
    /// TIMESYNC.
    fn requests(&mut self, now: Now) {
        if self.heard_vehicle
            && let Some(cmd) = self.autopilot.rates.poll(now.wall_us)
        {
            self.send_vehicle(cmd);
        }
        if self.heard_vehicle
            && let Some(m) = self.autopilot.origin_offer.as_mut().and_then(|o| o.poll(now.wall_us))
        {
            self.send_vehicle(m);
        }
        if let Some((set, tries, next)) = self.autopilot.source_set
            && now.wall_us >= next
        {
            self.autopilot.source_set = (tries < 3).then_some((set, tries + 1, now.wall_us + 1_000_000));
            self.send_vehicle(super::handover::ekf_source_set(set, self.sysid));
        }
        if self.heard_vehicle
            && self.clock.wanted
            && let Some(req) = self.clock.timesync.poll(now.wall_us, now.unix_ns, self.sysid)
        {
            self.send_vehicle(req);
        }
        if self.clock.wanted && self.decoder.clock_source() == Some(ClockSource::Timesync) && self.clock.timesync.drifts() {
            self.follow_clock(now);
        }
    }

    /// One frame from the vehicle link. Fails only when the node cannot be made from the state
    /// the vehicle gave (its configuration refused).
    pub fn vehicle_frame(&mut self, frame: Received, now: Now) -> Result<(), NodeError> {
        let (header, msg, bytes) = frame;
        self.catch_up(now);
        if self.config.record {
            self.record(Record::Frame { link: Link::Vehicle(self.sysid), dir: Direction::Rx, bytes });
        }
        self.vehicle.frames += 1;
        self.last_vehicle_us = now.wall_us;
        self.heard_vehicle = true;
        if header.system_id != u32::from(self.id) {
            self.vehicle.rejected += 1;
            return Ok(());
        }
        if header.component_id == 1 {
            self.vehicle.seq.observe(header.sequence);
        }
        // A message of the autopilot's own dialect: its sequence number counted above, nothing
        // for the node in it.
        let Some(msg) = msg else {
            self.vehicle.other_dialect += 1;
            return Ok(());
        };
        if let (MavMessage::EKF_STATUS_REPORT(m), Some(offer)) = (&msg, self.autopilot.origin_offer.as_mut()) {
            offer.on_ekf_status(m.flags.bits());
        }
        if let MavMessage::TIMESYNC(m) = &msg {
            self.on_timesync(m, (header.system_id as u8, header.component_id), now);
            return Ok(());
        }
        if let Some(fix) = self.fix.as_mut() {
            fix.on_message(&msg);
        }
        self.on_handover(&msg);
        self.on_sim_state(&msg);
        self.try_init()?;
        if matches!(msg, MavMessage::SIM_STATE(_)) {
            return Ok(());
        }
        let inputs = self.decode(&msg, now);
        self.feed(inputs, now);
        if let (Some(h), Some(core)) = (self.handover.as_mut(), self.core.as_ref()) {
            // what the filter's gate made of the GNSS fixes: the hand-back after a glitch
            h.judged(core.stats.fixes, core.stats.fixes_rejected);
        }
        Ok(())
    }

    fn on_timesync(&mut self, m: &crate::protocol::dialect::cooploc::TIMESYNC_DATA, from: (u8, u8), now: Now) {
        match self.clock.timesync.on_message(m, now.unix_ns, from, self.decoder.clock_offset_us()) {
            TimesyncReply::Answer(answer) => self.send_vehicle(MavMessage::TIMESYNC(answer)),
            TimesyncReply::Sample if self.clock.wanted => self.follow_clock(now),
            _ => {}
        }
    }

    /// The TIMESYNC mapping at `now` replaces the one in use when they differ by more than
    /// [`CLOCK_UPDATE_US`]: at each answer, and on every tick while the autopilot's clock runs at
    /// a rate of its own (the mapping then moves in steps of that size, not of a second's drift).
    fn follow_clock(&mut self, now: Now) {
        if let Some((offset_us, rtt_us)) = self.clock.timesync.offset_at_us(now.unix_ns)
            && self.decoder.clock_offset_us().is_none_or(|o| (o - offset_us).abs() > CLOCK_UPDATE_US)
            && self.decoder.clock_source() != Some(ClockSource::SystemTime)
        {
            self.take_clock(offset_us, rtt_us);
        }
    }

    /// The vehicle's clock mapped to the team's from here on (companion time minus boot time,
    /// and the round trip it was measured over).
    fn take_clock(&mut self, offset_us: i64, rtt_us: i64) {
        self.event(NodeEvent::Clock { offset_us, rtt_us });
        self.decoder.set_companion_offset(offset_us);
        self.clock.rtt_us = Some(rtt_us);
    }

    /// A Clock event of the log being replayed ([`ShellConfig::clock_from_log`]): the mapping
    /// the node took at this point.
    pub fn logged_clock(&mut self, offset_us: i64, rtt_us: i64) {
        self.take_clock(offset_us, rtt_us);
    }

    /// The hand-over: the start from the autopilot's estimate once it has GNSS, the take-over
    /// when GNSS goes and the hand-back when it returns (`super::handover`).
    fn on_handover(&mut self, msg: &MavMessage) {
        let id = self.id;
        let Some(h) = self.handover.as_mut() else { return };
        let origin = match (&self.pending, &self.nav_origin) {
            (Some(Pending { origin: Some(o), .. }), _) | (None, Some(o)) => *o,
            _ => return,
        };
        match h.on_message(msg, &origin) {
            Some(HandoverEvent::Start { time_boot_ms, state: s }) => {
                let Some(Pending { state: state @ None, from_autopilot: true, .. }) = self.pending.as_mut() else { return };
                match self.decoder.team_time_of_boot_ms(time_boot_ms) {
                    Some(t0) => {
                        tracing::info!(platform = id, pos = ?s.pos_ned_m, gnss = !h.lost(), "starting from the autopilot's estimate");
                        *state = Some((Some(t0), *s));
                        self.hand_over_state = Some(*s);
                    }
                    None => {
                        tracing::warn!(platform = id, "the autopilot's estimate before the team clock is known: waiting for it");
                        h.retry();
                    }
                }
            }
            Some(HandoverEvent::NoEstimate) => {
                tracing::warn!(platform = id, "GNSS, and no estimate of the autopilot's to start from yet")
            }
            Some(HandoverEvent::Lost) => {
                tracing::info!(platform = id, glitch = h.lost_to_glitch(), "GNSS lost: the team's filter takes over")
            }
            Some(HandoverEvent::Back) => tracing::info!(platform = id, "GNSS back: handing back to the autopilot's own"),
            None => {}
        }
        // the source set follows who navigates, once the node has its start
        let lost = h.lost();
        if self.hand_over_state.is_some() && lost != self.taken_over {
            self.taken_over = lost;
            let (takeover, gnss) = (self.autopilot.takeover_source_set, self.autopilot.gnss_source_set);
            let set = if lost { takeover } else { takeover.map(|_| gnss) };
            if let Some(set) = set {
                self.autopilot.source_set = Some((set, 0, 0));
            }
        }
    }

    /// A simulated vehicle's true state, for a node that waits for it.
    fn on_sim_state(&mut self, msg: &MavMessage) {
        let (
            MavMessage::SIM_STATE(m),
            Some(Pending { origin: Some(origin), state: state @ None, from_autopilot: false, .. }),
            Some(t0),
        ) = (msg, self.pending.as_mut(), self.last_imu_t)
        else {
            return;
        };
        // (before the team clock maps the IMU's stamps there is no time to start at)
        match wire::ins_state_from_sim_state(m, origin) {
            Ok(s) => {
                *state = Some((Some(t0), s));
                self.sim_state_init = Some((t0, s.pos_ned_m));
            }
            Err(e) => {
                self.vehicle.rejected += 1;
                tracing::warn!(platform = self.id, error = %e, "SIM_STATE refused for initialisation");
            }
        }
    }

    /// Makes the core once the origin and the state (and its time) are known.
    fn try_init(&mut self) -> Result<(), NodeError> {
        if self.restore.is_some() && self.fix_wait_from.is_some() {
            return Ok(()); // the saved state waits for the autopilot's estimate: it comes first
        }
        let Some(Pending { config, origin: Some(origin), state: Some((t0, state)), .. }) = &self.pending else {
            return Ok(());
        };
        let Some(t0) = t0.or(self.last_imu_t) else { return Ok(()) };
        let made = NodeCore::new(config.clone(), t0, NavState::for_model(&config.model, *state))?;
        tracing::info!(platform = self.id, t0 = %t0, pos = ?made.filter().position_ned_m(), lat_deg = origin.lat_deg, "initialised");
        let o = self.autopilot.origin_from_vehicle.map(|o| [o.lat_deg, o.lon_deg, o.alt_m]);
        let start = self.hand_over_state.as_ref().map(super::log::StartState::of);
        let origin = *origin;
        self.event(NodeEvent::Init { t0_us: t0.0, origin: o, state: start });
        self.core = Some(made);
        self.nav_origin = Some(origin);
        if self.handover.is_some() {
            // the hand-over start: the team's filter runs on the autopilot's GNSS fixes
            self.decoder.fuse_gnss(origin);
        }
        self.pending = None;
        Ok(())
    }

    /// Decodes a vehicle message into the core's inputs (none before the node has its state).
    fn decode(&mut self, msg: &MavMessage, now: Now) -> Vec<NodeInput> {
        let id = self.id;
        let mut inputs = Vec::new();
        let events = self.decoder.decode(msg);
        if self.decoder.counters.reboots != self.clock.reboots_seen {
            // the autopilot's boot clock started again: the TIMESYNC answers are of the boot before
            self.clock.reboots_seen = self.decoder.counters.reboots;
            self.clock.timesync.reset();
            self.clock.said = None;
            tracing::warn!(platform = id, "the autopilot rebooted: mapping its clock again");
        }
        if self.decoder.clock_source() != self.clock.said {
            self.clock.said = self.decoder.clock_source();
            match self.clock.said {
                Some(ClockSource::Timesync) => tracing::info!(
                    platform = id,
                    offset_us = self.decoder.clock_offset_us(),
                    rtt_us = self.clock.rtt_us,
                    "team clock: the companion's clock, mapped to the autopilot's boot clock by TIMESYNC"
                ),
                Some(ClockSource::SystemTime) => tracing::info!(
                    platform = id,
                    offset_us = self.decoder.clock_offset_us(),
                    "team clock: the autopilot's Unix time (SYSTEM_TIME, from GNSS)"
                ),
                None => {}
            }
        }
        for event in events {
            match event {
                VehicleEvent::Input(input) => {
                    let restored = self.check_restore(&input, now);
                    if self.restore.is_none() && self.fix.take().is_some() {
                        self.fix_messages_back_to_default();
                    }
                    self.check_given_start(&input);
                    if self.core.is_none() || restored {
                        self.last_imu_t = input.drive_time().or(self.last_imu_t);
                        self.before_init += 1;
                    } else {
                        inputs.push(input);
                    }
                }
                VehicleEvent::Ack(ack) => self.on_ack(&ack),
                VehicleEvent::Origin(o) => self.on_origin(o, msg),
                VehicleEvent::Nothing => {}
            }
        }
        inputs
    }

    /// The saved state against the vehicle's first sample (once the origin is known): restored
    /// when it is for this platform, model and origin, newer than a given start state, and at
    /// most [`super::saved::MAX_RESTORE_AGE_US`] old; refused with its reason otherwise. True when the core
    /// was made from it at this sample's time (the sample itself then only marks the start).
    fn check_restore(&mut self, input: &NodeInput, now: Now) -> bool {
        let id = self.id;
        let Some(t1) = input.drive_time() else { return false };
        if self.restore.is_none() {
            return false;
        }
        let (origin, config) = match (&self.given_start, &self.pending, &self.core) {
            (Some((origin, _)), _, Some(core)) => (*origin, core.config().clone()),
            (None, Some(Pending { origin: Some(origin), from_autopilot: false, config, .. }), _) => (*origin, config.clone()),
            // (the vehicle's origin is not known yet: decided at a later sample)
            (None, Some(Pending { origin: None, from_autopilot: false, .. }), _) => return false,
            // a node made ready by its caller, one that starts at the autopilot's hand-over, or
            // one its vehicle's SIM_STATE started before its first sample
            _ => {
                if self.restore.take().is_some() {
                    let why = if self.core.is_some() {
                        "the node had its state before the vehicle's first sample"
                    } else {
                        "the node starts from the autopilot's estimate (the hand-over: once it has held a fix, or at once after a loss)"
                    };
                    println!("node {id} saved state not used: {why}");
                }
                return false;
            }
        };
        let Some(saved) = self.restore.as_ref() else { return false };
        if let Some((_, t0)) = self.given_start
            && t0.0 >= saved.t_us
            && t1.0 <= t0.0.saturating_add(STALE_START_US)
        {
            println!("node {id} saved state of t {} not used: the given start state (t {t0}) is newer", saved.t_us);
            self.restore = None;
            return false;
        }
        let refused = |why: String| {
            println!("node {id} saved state refused: {why}");
            tracing::warn!(platform = id, why, "saved state refused");
            false
        };
        if let Some(why) = saved.wall_age_refusal(now.unix_us()) {
            self.restore = None;
            return refused(why);
        }
        // (a state refused anyway is refused at once, not after the wait for the autopilot)
        let plain = match saved.restore_at(id, &config.model, &origin, t1, &CoastBounds::LAND) {
            Ok(restored) => restored,
            Err(why) => {
                self.restore = None;
                return refused(why);
            }
        };
        let Some(fix) = self.fix_at(t1, &origin) else { return false };
        let Some(saved) = self.restore.take() else { return false };
        let coasted = |why: &str| format!("carried at constant velocity ({why})");
        let ((state, p), taken) = match &fix {
            Ok((g, flags)) => match saved.restore_to_fix(id, &config.model, &origin, t1, &CoastBounds::LAND, g) {
                Ok(restored) if g.horizontal.is_some() => {
                    (restored, format!("the autopilot's heading, position and velocity (its EKF flags {flags:#06x})"))
                }
                Ok(restored) => {
                    (restored, format!("the autopilot's heading (its EKF flags {flags:#06x}: no horizontal position)"))
                }
                Err(why) => (plain, coasted(&format!("the autopilot's estimate: {why}"))),
            },
            Err(why) => (plain, coasted(why)),
        };
        let core = match NodeCore::restored(config, t1, state, &p) {
            Ok(core) => core,
            Err(e) => return refused(e.to_string()),
        };
        let age_us = t1.0 - saved.t_us;
        let sigma = (p[(0, 0)] + p[(1, 1)]).sqrt();
        let heading = core.filter().output_covariances().yaw_variance().sqrt().to_degrees();
        println!(
            "node {id} restored from its saved state of t {} ({:.3} s before the vehicle's sample): {taken}; pos_ned_m {:?}, horizontal sigma {sigma:.2} m, heading sigma {heading:.1} deg",
            saved.t_us,
            age_us as f64 / 1e6,
            core.filter().position_ned_m().as_slice()
        );
        tracing::info!(platform = id, age_s = age_us as f64 / 1e6, sigma_m = sigma, "restored from the saved state");
        let state = SavedState::of(id, &origin, core.filter());
        self.event(NodeEvent::Restored { state, age_us });
        self.core = Some(core);
        self.nav_origin = Some(origin);
        self.given_start = None;
        self.pending = None;
        true
    }

    /// What the autopilot's estimate says at `t1` (a sample's time), carried to it, with its EKF
    /// flags; Err with the reason it is not used. None: wait for it (the vehicle's first sample
    /// was less than [`FIX_WAIT_US`] ago and the autopilot has not refused ATTITUDE).
    fn fix_at(&mut self, t1: TimeUs, origin: &wire::GeoOrigin) -> Option<FixOutcome> {
        let Some(estimate) = self.fix.as_mut() else { return Some(Err("no state to restore".into())) };
        let id = self.id;
        let mut why = "no estimate its EKF vouches for".to_string();
        match estimate.fix(origin) {
            Ok(Some(f)) => {
                // (looked at, not taken in: a stamp a second behind the samples is no reboot)
                let decoder = &self.decoder;
                let age_s = |ms: u32| decoder.peek_team_time_of_boot_ms(ms).map(|t| (t1.0 as f64 - t.0 as f64) / 1e6);
                let stale = f64::from(FIX_STALE_MS) / 1e3;
                match age_s(f.attitude_ms) {
                    Some(dt) if dt.abs() <= stale => {
                        let mut f = f;
                        let dtp = match f.horizontal {
                            Some(h) => age_s(h.at_ms).filter(|d| d.abs() <= stale),
                            None => None,
                        };
                        if dtp.is_none() {
                            f.horizontal = None;
                        }
                        return Some(Ok((f.carried(dt, dtp.unwrap_or(0.0)), f.vouched.flags)));
                    }
                    Some(dt) => why = format!("its estimate is {dt:.1} s from the sample"),
                    None => why = "its clock is not mapped yet".into(),
                }
            }
            Ok(None) => {}
            Err(e) => {
                tracing::warn!(platform = id, error = %e, "the autopilot's estimate refused");
                why = e;
            }
        }
        if self.given_start.is_some() {
            // a state given with its time is judged at the first sample, as it always was
            return Some(Err(why));
        }
        let first = *self.fix_wait_from.get_or_insert(t1);
        let refused =
            self.autopilot.rates.requests.iter().any(|r| {
                r.message_id == ATTITUDE_ID && matches!(r.outcome, Some(RateOutcome::Refused(_) | RateOutcome::Unanswered))
            });
        if refused {
            return Some(Err("the autopilot sends no ATTITUDE".into()));
        }
        if t1.0 < first.0.saturating_add(FIX_WAIT_US) {
            return None;
        }
        Some(Err(format!("{why} after {:.0} s", FIX_WAIT_US as f64 / 1e6)))
    }

    /// The restore is decided: what the node asked for its sake goes back to the autopilot's
    /// default rates (unless the hand-over start still needs ATTITUDE and GLOBAL_POSITION_INT).
    fn fix_messages_back_to_default(&mut self) {
        if self.handover.is_some() {
            return;
        }
        let rates = &mut self.autopilot.rates;
        for (name, id) in FIX_MESSAGES {
            let asked = rates.requests.iter().any(|r| {
                r.message_id == id
                    && r.rate_hz > 0.0
                    && !matches!(r.outcome, Some(RateOutcome::Refused(_) | RateOutcome::Unanswered))
            });
            if asked {
                rates.add_default(name, id);
            }
        }
    }

    /// A given start state against the vehicle's first sample: refused when stale.
    fn check_given_start(&mut self, input: &NodeInput) {
        let id = self.id;
        if let Some(t) = input.drive_time()
            && let Some((origin, t0)) = self.given_start.take()
            && t.0 > t0.0.saturating_add(STALE_START_US)
            && let Some(refused) = self.core.take()
        {
            let late_s = (t.0 - t0.0) as f64 / 1e6;
            println!(
                "node {id} start state refused: given for t {t0}, the vehicle is at {t} ({late_s:.1} s later): stale; waiting for SIM_STATE"
            );
            tracing::warn!(platform = id, late_s, "the given start state is stale: waiting for SIM_STATE");
            self.event(NodeEvent::StartRefused { given_t0_us: t0.0, vehicle_t_us: t.0 });
            self.pending =
                Some(Pending { config: refused.config().clone(), origin: Some(origin), state: None, from_autopilot: false });
        }
    }

    fn on_ack(&mut self, ack: &crate::protocol::dialect::cooploc::COMMAND_ACK_DATA) {
        let id = self.id;
        if ack.command == MavCmd::MAV_CMD_SET_EKF_SOURCE_SET && self.autopilot.source_set.is_some() {
            self.autopilot.source_set = None;
            self.autopilot.source_set_result = Some(ack.result);
            tracing::info!(platform = id, result = ?ack.result, "the autopilot answered the EKF source-set switch");
        }
        if let Some(r) = self.autopilot.rates.on_ack(ack) {
            match &r.outcome {
                Some(RateOutcome::Accepted) => {
                    tracing::info!(platform = id, message = r.message, rate_hz = r.rate_hz, "the autopilot accepted the rate")
                }
                other => {
                    tracing::warn!(platform = id, message = r.message, rate_hz = r.rate_hz, outcome = ?other, "the autopilot refused the rate; navigating on what it sends")
                }
            }
        }
    }

    /// The vehicle's origin (the EKF's: HOME_POSITION is where it armed, elsewhere).
    fn on_origin(&mut self, o: wire::GeoOrigin, msg: &MavMessage) {
        let id = self.id;
        let ap = &mut self.autopilot;
        let geo = wire::Geodetic { lat_deg: o.lat_deg, lon_deg: o.lon_deg, alt_m: o.alt_m };
        if let Some(offer) = ap.origin_offer.as_mut()
            && offer.settled.is_none()
            && matches!(msg, MavMessage::GPS_GLOBAL_ORIGIN(_))
        {
            let ours = offer.on_origin(o);
            tracing::info!(platform = id, ours, lat_deg = o.lat_deg, lon_deg = o.lon_deg, "the autopilot has an origin");
            if let (false, Some(team), Some(odometry)) = (ours, ap.profile_origin, ap.odometry.as_mut()) {
                // its own (from its GNSS): ODOMETRY goes out in its frame
                odometry.set_frame_offset(wire::geodetic_to_ned(&team, &geo));
            }
        }
        if let Some(Pending { config, origin: origin @ None, .. }) = &mut self.pending {
            tracing::info!(platform = id, lat_deg = o.lat_deg, lon_deg = o.lon_deg, alt_m = o.alt_m, "origin from the vehicle");
            config.model.set_latitude(o.lat_deg);
            *origin = Some(o);
            ap.origin_from_vehicle = Some(o);
            ap.origin_checked = true;
        }
        if let (Some(mine), false) = (ap.profile_origin, ap.origin_checked) {
            ap.origin_checked = true;
            let apart = wire::geodetic_to_ned(&mine, &geo).xy().norm();
            if apart > 1000.0 {
                tracing::warn!(
                    platform = id,
                    apart_m = apart,
                    "the vehicle's origin is far from the profile's [origin]: positions sent back are in the profile's frame"
                );
            }
        }
    }

    /// Bytes from the ranging device on the companion, read at `arrival_us` (Unix time, us).
    pub fn range_bytes(&mut self, bytes: &[u8], arrival_us: u64, now: Now) {
        self.catch_up(now);
        let Some(lines) = self.range_lines.as_mut() else { return };
        let ranges = lines.push(bytes, arrival_us);
        let mut inputs = Vec::new();
        for (epoch, range) in ranges {
            // recorded before it is taken: replay takes the same
            self.event(NodeEvent::Range { epoch, range });
            if self.core.is_some() {
                inputs.push(NodeInput::OwnRange { epoch, range });
            } else {
                self.before_init += 1;
            }
        }
        self.feed(inputs, now);
    }

    /// One datagram from the cooperative link (a serial radio: one frame), from `from`.
    pub fn coop_datagram(&mut self, bytes: &[u8], from: Source, now: Now) {
        if bytes.is_empty() && from == Source::Radio {
            return; // no whole frame in these bytes yet
        }
        self.catch_up(now);
        self.coop_frames += 1;
        let id = self.id;
        let frames = match &mut self.verifier {
            // only what the team key signed is logged and taken (a replay sees the same)
            Some(v) => {
                let got = v.datagram(bytes, now.unix_us());
                if !got.refused.is_empty() {
                    tracing::debug!(platform = id, %from, refused = ?got.refused, "cooperative frames refused by signing");
                }
                if self.config.record {
                    for span in &got.spans {
                        self.out.push(ShellOutput::Record(Record::Frame {
                            link: Link::Coop(self.sysid),
                            dir: Direction::Rx,
                            bytes: bytes[span.clone()].to_vec(),
                        }));
                    }
                }
                got.frames
            }
            // Every frame of the datagram (a packed batch holds several), logged as taken: the
            // log and the core see the same frames.
            None => {
                let mut frames = Vec::new();
                for (header, msg, frame) in crate::protocol::framing::split_frames(bytes) {
                    self.record(Record::Frame { link: Link::Coop(self.sysid), dir: Direction::Rx, bytes: frame });
                    frames.extend(msg.map(|m| (header, m)));
                }
                frames
            }
        };
        if frames.is_empty() {
            self.coop_rejected += 1;
            tracing::debug!(platform = id, %from, bytes = bytes.len(), "cooperative datagram without a valid frame dropped");
            return;
        }
        let mut inputs = Vec::with_capacity(frames.len());
        for (header, msg) in frames {
            if header.system_id == u32::from(id) {
                continue; // our own traffic, looped back
            }
            let gcs = matches!(&msg, MavMessage::HEARTBEAT(hb) if hb.mavtype == MavType::MAV_TYPE_GCS);
            if let Some(addr) = from.addr() {
                match self.peers.heard(self.peers.sender(header.system_id, gcs), addr, now.wall_us) {
                    Heard::New => tracing::info!(platform = id, peer = %from, sysid = header.system_id, "new peer"),
                    Heard::Moved => tracing::info!(platform = id, peer = %from, sysid = header.system_id, "peer moved"),
                    Heard::Refused => tracing::debug!(platform = id, peer = %from, "ground station refused: observer table full"),
                    Heard::Known | Heard::Ignored => {}
                }
                if matches!(from, Source::Group(_)) {
                    self.peers.heard_on_group(addr, now.wall_us);
                }
            }
            let Ok(from) = PlatformId::try_from(header.system_id) else { continue };
            inputs.push(NodeInput::Peer { from, msg: Box::new(msg) });
        }
        self.feed(inputs, now);
    }

    /// Inputs to the core, and what goes back to the vehicle after them.
    fn feed(&mut self, inputs: Vec<NodeInput>, now: Now) {
        if inputs.is_empty() || self.core.is_none() {
            return;
        }
        let mut out = Vec::new();
        let Some(core) = self.core.as_mut() else { return };
        let vehicle_input = inputs.iter().any(|i| i.drive_time().is_some());
        for input in inputs {
            out.extend(core.handle(input));
        }
        // (the navigation solution only when something goes back to the vehicle: not on every
        // IMU sample of a node that sends nothing back)
        // (with the hand-over, only once the node has taken over: before, the autopilot
        // navigates on its GNSS; ODOMETRY from the start with `odometry_with_gnss`, which its
        // EKF leaves out until the take-over switches its source set)
        let navigates = self.handover.is_none() || self.taken_over;
        let odometry = navigates || self.autopilot.odometry_with_gnss && self.hand_over_state.is_some();
        if vehicle_input && odometry && (self.autopilot.odometry.is_some() || self.autopilot.gps_input.is_some()) {
            let nav = core.navigation();
            let decoder = &self.decoder;
            let odo = self.autopilot.odometry.as_mut().and_then(|o| o.poll(&nav, |t| decoder.to_vehicle_time(t)));
            let gps = match self.autopilot.gps_input.as_mut() {
                Some(g) if navigates => g.poll(&nav, |t| decoder.to_vehicle_time(t)),
                _ => None,
            };
            for msg in odo.into_iter().chain(gps) {
                self.send_vehicle(msg);
            }
        }
        self.core_outputs(out, now);
        self.maybe_save_state(now);
    }

    /// Gives the navigation state to be saved, every [`SAVE_EVERY_US`] of the team clock.
    fn maybe_save_state(&mut self, now: Now) {
        if !self.config.save_state {
            return;
        }
        let (Some(core), Some(origin)) = (&self.core, &self.nav_origin) else { return };
        let t = core.filter().time();
        if self.saved_at.is_some_and(|at| t.0 < at.0.saturating_add(SAVE_EVERY_US)) {
            return;
        }
        self.saved_at = Some(t);
        let saved = SavedState::of(self.id, origin, core.filter()).written_at(now.unix_us());
        self.out.push(ShellOutput::NavState(saved.to_text()));
    }

    /// The navigation state to keep at the end, written `now` (None: not kept, or no state yet).
    pub fn nav_state(&self, now: Now) -> Option<String> {
        let (Some(core), Some(origin)) = (&self.core, &self.nav_origin) else { return None };
        self.config.save_state.then(|| SavedState::of(self.id, origin, core.filter()).written_at(now.unix_us()).to_text())
    }

    /// What the node did, with what the links know.
    pub fn summary(&self, links: LinkFacts) -> NodeSummary {
        let core = self.core.as_ref();
        let ap = &self.autopilot;
        NodeSummary {
            stats: core.map(|c| c.stats.clone()).unwrap_or_default(),
            flagged: core.map(|c| c.flagged().iter().copied().collect()).unwrap_or_default(),
            estimate: core.map(NodeCore::estimate),
            before_init: self.before_init,
            sim_state_init: self.sim_state_init,
            vehicle_frames: self.vehicle.frames,
            vehicle_rejected: self.vehicle.rejected,
            vehicle_other_dialect: self.vehicle.other_dialect,
            vehicle_lost: self.vehicle.seq.lost,
            coop_frames: self.coop_frames,
            coop_rejected: self.coop_rejected,
            coop_noise_bytes: links.coop_noise_bytes,
            coop_signing: self.verifier.as_ref().map(|v| v.counters.clone()).unwrap_or_default(),
            vehicle_signing: links.vehicle_signing,
            peers: self.peers.addresses(),
            peer_counters: self.peers.counters,
            coop_tx: CoopTx { dropped: links.coop_dropped, ..self.tx },
            wall_s: links.wall_s,
            inputs: self.decoder.counters.clone(),
            imu_rate_hz: self.decoder.imu_rate_hz(),
            rate_requests: ap.rates.requests.clone(),
            odometry_sent: ap.odometry.as_ref().map_or(0, |o| o.sent),
            odometry_resets: ap.odometry.as_ref().map_or(0, |o| o.reset_counter),
            gps_input_sent: ap.gps_input.as_ref().map_or(0, |g| g.sent),
            origin_from_vehicle: ap.origin_from_vehicle,
            clock: self
                .decoder
                .clock_source()
                .zip(self.decoder.clock_offset_us())
                .map(|(source, offset)| (source, offset, if source == ClockSource::Timesync { self.clock.rtt_us } else { None })),
            timesync_requests: self.clock.timesync.requests,
            timesync_refused: self.clock.timesync.refused,
            range_input: self.range_lines.as_ref().map(|l| l.counters.clone()),
            origin_offer: ap.origin_offer.clone(),
            hand_over: self.hand_over_state.map(|s| HandOverSummary {
                started_at_ned_m: s.pos_ned_m,
                source_set: ap.source_set_result,
                fixes: self.core.as_ref().map_or(0, |c| c.stats.fixes),
                fixes_rejected: self.core.as_ref().map_or(0, |c| c.stats.fixes_rejected),
                losses: self.handover.as_ref().map_or(0, |h| h.losses),
                returns: self.handover.as_ref().map_or(0, |h| h.returns),
                glitches: self.handover.as_ref().map_or(0, |h| h.glitches),
                navigating: self.taken_over,
            }),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::estimation::Method;
    use crate::protocol::record::Encoding;
    use cooploc_sitl::sitl::{PAPER_TOML, Scenario, World};

    const UNIX_NS: i64 = 1_800_000_000_000_000_000;

    fn at(ms: u64) -> Now {
        Now { wall_us: ms * 1000, unix_ns: UNIX_NS + ms as i64 * 1_000_000 }
    }

    fn addr(port: u16) -> Source {
        Source::Unicast(SocketAddr::from(([127, 0, 0, 1], port)))
    }

    /// Node 1 of the paper's team, initialised, with a log.
    fn shell(key: Option<TeamKey>, idle_exit: Option<Duration>) -> NodeShell {
        let scenario = Scenario::from_toml_str(PAPER_TOML).unwrap();
        let world = World::new(&scenario).unwrap();
        let model = VehicleProfile::from_spec(&scenario.vehicle()).nav_model(scenario.latitude_deg);
        let init = world.initial_estimate(1, 0, 1).unwrap();
        let (t0, state) = (init.truth.t, crate::estimation::nav::NavState::for_model(&model, init.ins_state()));
        let cfg = NodeConfig::for_model(1, Method::Decentralized, model, Encoding::F64, world.platform_ids());
        let core = NodeCore::new(cfg, t0, state).unwrap();
        let config = ShellConfig {
            team_key: key,
            idle_exit,
            grace: Duration::from_secs(1),
            record: true,
            ..bare_config(VehicleProfile::from_spec(&scenario.vehicle()))
        };
        NodeShell::new(NodeInit::Ready(Box::new(core)), config, at(0)).unwrap()
    }

    /// A shell configuration for `profile`: unsigned, no log, no peers, no saved state, UDP.
    fn bare_config(profile: VehicleProfile) -> ShellConfig {
        ShellConfig { unicast: true, ..ShellConfig::bare(profile) }
    }

    fn frame(sysid: u32, compid: u8, seq: u8, msg: &MavMessage) -> Vec<u8> {
        wire::to_frame(MavHeader { system_id: sysid, component_id: compid, sequence: seq }, msg)
    }

    fn vehicle_frame(sysid: u32, seq: u8) -> Received {
        let msg = wire::heartbeat(MavType::MAV_TYPE_GROUND_ROVER, MavAutopilot::MAV_AUTOPILOT_ARDUPILOTMEGA);
        let bytes = frame(sysid, 1, seq, &msg);
        (MavHeader { system_id: sysid, component_id: 1, sequence: seq }, Some(msg), bytes)
    }

    fn summary(s: &NodeShell) -> NodeSummary {
        s.summary(LinkFacts::default())
    }

    fn coop_outputs(out: &[ShellOutput]) -> Vec<(&Vec<Vec<u8>>, &Vec<SocketAddr>)> {
        out.iter()
            .filter_map(|o| match o {
                ShellOutput::Coop { frames, unicast } => Some((frames, unicast)),
                _ => None,
            })
            .collect()
    }

    #[test]
    fn a_shell_says_heartbeat_to_its_vehicle_first_and_refuses_an_id_that_is_no_system_id() {
        let mut s = shell(None, None);
        let out = s.take_outputs();
        assert!(
            matches!(out.as_slice(), [ShellOutput::Vehicle { header, msg: MavMessage::HEARTBEAT(_) }] if header.system_id == 1 && header.component_id == wire::COMPANION_COMPID)
        );

        let scenario = Scenario::from_toml_str(PAPER_TOML).unwrap();
        let mut cfg = NodeConfig::for_model(
            300,
            Method::Decentralized,
            VehicleProfile::from_spec(&scenario.vehicle()).nav_model(scenario.latitude_deg),
            Encoding::F64,
            vec![300, 2],
        );
        cfg.id = 300;
        let config = bare_config(VehicleProfile::from_spec(&scenario.vehicle()));
        let init = NodeInit::Pending { config: Box::new(cfg), origin: None, state: None, from_autopilot: false };
        let err = NodeShell::new(init, config, at(0)).err().expect("platform 300 refused");
        assert!(err.to_string().contains("platform id 300"), "{err}");
    }

    /// Bytes that are no frame, a frame cut short, a frame whose checksum is wrong: each
    /// datagram is counted and refused, nothing reaches the core, nothing is logged, nothing
    /// panics.
    #[test]
    fn garbage_truncated_and_corrupted_datagrams_are_counted_and_feed_nothing() {
        let mut s = shell(None, None);
        s.take_outputs();
        let hb = frame(2, 191, 0, &wire::heartbeat(MavType::MAV_TYPE_ONBOARD_CONTROLLER, MavAutopilot::MAV_AUTOPILOT_INVALID));
        let mut corrupted = hb.clone();
        let last = corrupted.len() - 1;
        corrupted[last] ^= 0x55;
        let garbage: Vec<u8> = (0..200u32).map(|i| (i.wrapping_mul(2_654_435_761) >> 13) as u8).collect();
        for bytes in [&garbage[..], &hb[..hb.len() - 3], &corrupted[..], &[0xFD][..], &[][..]] {
            s.coop_datagram(bytes, addr(7002), at(10));
        }
        let got = summary(&s);
        assert_eq!((got.coop_frames, got.coop_rejected), (5, 5));
        assert!(got.peers.is_empty(), "no peer learned from garbage: {:?}", got.peers);
        assert!(s.take_outputs().is_empty(), "nothing logged or sent for garbage");
        assert_eq!(s.core().unwrap().stats, NodeStats::default(), "the core saw nothing");
    }

    /// A teammate's frame teaches the shell where it is, and the next cooperative output goes
    /// there too; the node's own frames looped back teach nothing.
    #[test]
    fn a_teammate_is_learned_and_sent_to_and_the_nodes_own_traffic_is_not() {
        let mut s = shell(None, None);
        s.take_outputs();
        let hb = wire::heartbeat(MavType::MAV_TYPE_ONBOARD_CONTROLLER, MavAutopilot::MAV_AUTOPILOT_INVALID);
        s.coop_datagram(&frame(1, 191, 0, &hb), addr(7001), at(5));
        assert!(summary(&s).peers.is_empty(), "its own traffic, looped back");
        s.coop_datagram(&frame(2, 191, 0, &hb), addr(7002), at(6));
        s.coop_datagram(&frame(42, 191, 0, &hb), addr(7042), at(7));
        assert_eq!(summary(&s).peers, [SocketAddr::from(([127, 0, 0, 1], 7002))], "a team member, not a stranger");
        s.take_outputs();
        assert!(s.tick(at(25)));
        let out = s.take_outputs();
        let coop = coop_outputs(&out);
        assert_eq!(coop.len(), 1, "the heartbeat: {out:?}");
        assert_eq!(coop[0].1, &[SocketAddr::from(([127, 0, 0, 1], 7002))]);
        assert!(out.iter().any(|o| matches!(o, ShellOutput::Vehicle { msg: MavMessage::HEARTBEAT(_), .. })));
    }

    /// With a team key the shell takes only what the key signed, and logs only that; what it
    /// sends is signed and a teammate's verifier takes it.
    #[test]
    fn a_signed_shell_takes_and_logs_only_signed_frames_and_signs_its_own() {
        let key = TeamKey::from_passphrase("shell test");
        let mut s = shell(Some(key.clone()), None);
        s.take_outputs();
        let hb = wire::heartbeat(MavType::MAV_TYPE_ONBOARD_CONTROLLER, MavAutopilot::MAV_AUTOPILOT_INVALID);
        let header = MavHeader { system_id: 2, component_id: 191, sequence: 0 };
        s.coop_datagram(&wire::to_frame(header, &hb), addr(7002), at(5));
        let other = Signer::new(TeamKey::from_passphrase("another team"), 2, 0).frame(header, &hb, at(5).unix_us());
        s.coop_datagram(&other, addr(7002), at(6));
        assert!(s.take_outputs().is_empty(), "nothing refused is logged");
        let got = summary(&s);
        assert_eq!((got.coop_rejected, got.coop_signing.unsigned, got.coop_signing.bad_signature), (2, 1, 1));
        assert!(got.peers.is_empty());

        let signed = Signer::new(key.clone(), 2, 0).frame(header, &hb, at(7).unix_us());
        s.coop_datagram(&signed, addr(7002), at(7));
        let out = s.take_outputs();
        assert!(
            matches!(out.as_slice(), [ShellOutput::Record(Record::Frame { dir: Direction::Rx, bytes, .. })] if *bytes == signed)
        );
        assert_eq!(summary(&s).peers.len(), 1);

        assert!(s.tick(at(25)));
        let out = s.take_outputs();
        let mut verifier = Verifier::new(key);
        let coop = coop_outputs(&out);
        let got = verifier.datagram(&coop[0].0[0], at(26).unix_us());
        assert_eq!((got.frames.len(), got.refused.len()), (1, 0), "the shell's heartbeat is signed with the team key");
    }

    /// Frames from another system are refused; a gap in the autopilot's sequence numbers is
    /// loss, and a frame that arrives behind the last one was counted in its gap and is not.
    #[test]
    fn vehicle_sequence_gaps_count_as_loss_and_a_late_frame_does_not() {
        let mut s = shell(None, None);
        for seq in [250, 251, 252, 255, 1] {
            s.vehicle_frame(vehicle_frame(1, seq), at(1)).unwrap();
        }
        assert_eq!(summary(&s).vehicle_lost, 2 + 1, "253, 254 and 0 missing");
        s.vehicle_frame(vehicle_frame(1, 254), at(2)).unwrap();
        s.vehicle_frame(vehicle_frame(7, 2), at(2)).unwrap();
        let got = summary(&s);
        assert_eq!((got.vehicle_lost, got.vehicle_frames, got.vehicle_rejected), (2, 7, 1));
    }

    /// The node ends when its vehicle has been silent for the idle time and the grace after it;
    /// a process frozen longer than that is not a silent vehicle.
    #[test]
    fn a_silent_vehicle_ends_the_node_after_the_grace_and_a_frozen_process_does_not() {
        let ends = |frozen: bool| {
            let mut s = shell(None, Some(Duration::from_secs(1)));
            s.vehicle_frame(vehicle_frame(1, 0), at(0)).unwrap();
            let mut ms = 0;
            while ms < 20_000 {
                ms += if frozen && ms == 500 { 4_000 } else { 25 };
                if !s.tick(at(ms)) {
                    let out = s.take_outputs();
                    assert!(out.iter().any(|o| matches!(o, ShellOutput::Record(Record::Event(NodeEvent::RunPending)))));
                    return ms;
                }
            }
            panic!("never ended");
        };
        assert_eq!(ends(false), 2_000, "1 s of silence, then 1 s of grace");
        assert_eq!(ends(true), 4_500 + 2_000, "the silence starts again after the freeze");
    }

    /// A frame read after a freeze (the ticks late): the core is polled at the frame's wall
    /// time first, and the poll is logged ahead of the frame, where a replay meets it; the
    /// tick's clock is left, so the next frame before a tick is preceded by a poll too, and the
    /// next tick still sees the freeze.
    #[test]
    fn a_frame_read_after_a_freeze_is_logged_behind_the_poll_that_came_first() {
        let mut s = shell(None, Some(Duration::from_secs(1)));
        assert!(s.tick(at(25)));
        s.take_outputs();
        s.vehicle_frame(vehicle_frame(1, 0), at(50)).unwrap();
        let out = s.take_outputs();
        assert!(matches!(out.as_slice(), [ShellOutput::Record(Record::Frame { dir: Direction::Rx, .. })]), "no freeze: {out:?}");
        for (seq, ms) in [(1, 2_000), (2, 2_001)] {
            s.vehicle_frame(vehicle_frame(1, seq), at(ms)).unwrap();
            let out = s.take_outputs();
            let wall_us = ms * 1000;
            assert!(
                matches!(out.as_slice(), [ShellOutput::Record(Record::Event(NodeEvent::Poll { wall_us: w })), ShellOutput::Record(Record::Frame { dir: Direction::Rx, .. }), ..] if *w == wall_us),
                "at {ms} ms: {out:?}"
            );
        }
        // The freeze restarts the vehicle's idle clock at the tick (1 s of silence from 2,025 ms,
        // not from the frame at 2,001 ms): no end of input at 3,010 ms.
        assert!(s.tick(at(2_025)));
        s.take_outputs();
        assert!(s.tick(at(3_010)));
        let out = s.take_outputs();
        assert!(!out.iter().any(|o| matches!(o, ShellOutput::Record(Record::Event(NodeEvent::EndOfInput)))), "{out:?}");
    }

    /// A shell fed a log takes the vehicle clock's mapping from the log's Clock events, and
    /// neither asks the vehicle for TIMESYNC nor maps the clock from its answers; a node's shell
    /// asks.
    #[test]
    fn a_shell_fed_a_log_takes_the_clock_from_it_and_asks_the_vehicle_for_none() {
        let scenario = Scenario::from_toml_str(PAPER_TOML).unwrap();
        let mut profile = VehicleProfile::from_spec(&scenario.vehicle());
        profile.inputs.clock = TeamClock::Companion;
        let model = profile.nav_model(scenario.latitude_deg);
        let world = World::new(&scenario).unwrap();
        let init = world.initial_estimate(1, 0, 1).unwrap();
        let (t0, state) = (init.truth.t, crate::estimation::nav::NavState::for_model(&model, init.ins_state()));
        let timesync_requests = |clock_from_log: bool| {
            let cfg = NodeConfig::for_model(1, Method::Decentralized, model, Encoding::F64, world.platform_ids());
            let core = NodeCore::new(cfg, t0, state).unwrap();
            let config = ShellConfig { record: true, clock_from_log, ..bare_config(profile.clone()) };
            let mut s = NodeShell::new(NodeInit::Ready(Box::new(core)), config, at(0)).unwrap();
            s.vehicle_frame(vehicle_frame(1, 0), at(1)).unwrap();
            for ms in 1..=80 {
                assert!(s.tick(at(ms * 25)));
            }
            let out = s.take_outputs();
            (s, out.iter().filter(|o| matches!(o, ShellOutput::Vehicle { msg: MavMessage::TIMESYNC(_), .. })).count())
        };
        let (_, asked) = timesync_requests(false);
        assert!(asked > 0, "a node's shell asks its vehicle for TIMESYNC");
        let (mut s, asked) = timesync_requests(true);
        assert_eq!(asked, 0, "a replay's shell asks nothing");
        assert_eq!(summary(&s).clock, None);
        s.logged_clock(1_700_000_000_000_000, 900);
        let out = s.take_outputs();
        assert!(
            matches!(
                out.as_slice(),
                [ShellOutput::Record(Record::Event(NodeEvent::Clock { offset_us: 1_700_000_000_000_000, rtt_us: 900 }))]
            ),
            "{out:?}"
        );
        assert_eq!(summary(&s).clock, Some((ClockSource::Timesync, 1_700_000_000_000_000, Some(900))));
    }

    /// A node restarted with a saved state 10 s old, on an ArduPilot rover whose EKF3 kept
    /// going: it waits for the autopilot's estimate, and takes its heading (and its position and
    /// velocity when EKF_STATUS_REPORT vouches for them) instead of the saved state carried at
    /// constant velocity; without an estimate it restores as before after [`FIX_WAIT_US`].
    #[test]
    fn a_restored_state_takes_the_autopilots_heading_and_position_as_far_as_its_ekf_vouches() {
        use crate::protocol::dialect::cooploc::{
            ATTITUDE_DATA, EKF_STATUS_REPORT_DATA, EkfStatusFlags, GLOBAL_POSITION_INT_DATA, RAW_IMU_DATA,
        };
        let text = include_str!("../../../../sitl/vehicles/ardupilot-rover.toml")
            .replace("clock = \"auto\"", "clock = \"vehicle\"")
            .replace("epoch_grid_ms = 100", "epoch_grid_ms = 0");
        let profile = VehicleProfile::from_toml_str(&text).unwrap();
        let origin = profile.geo_origin().unwrap();
        let model = profile.nav_model(origin.lat_deg);
        let (yaw0, t_saved) = (0.3f64, 60_000_000);
        let state = InsState {
            pos_ned_m: nalgebra::Vector3::new(10.0, 20.0, 0.0),
            vel_ned_m_s: nalgebra::Vector3::new(2.0 * yaw0.cos(), 2.0 * yaw0.sin(), 0.0),
            att_frd_to_ned: nalgebra::UnitQuaternion::from_euler_angles(0.0, 0.0, yaw0),
            accel_bias_frd_m_s2: nalgebra::Vector3::zeros(),
            gyro_bias_frd_rad_s: nalgebra::Vector3::zeros(),
            odometer_scale_error: 0.0,
        };
        let filter = crate::estimation::nav::NavFilter::new(model, TimeUs(t_saved), NavState::for_model(&model, state)).unwrap();
        let saved = SavedState::of(3, &origin, &filter);
        let start = |restore: Option<SavedState>| {
            let cfg = NodeConfig::for_model(3, Method::Decentralized, model, Encoding::F64, vec![1, 2, 3]);
            let config = ShellConfig { restore, ..bare_config(profile.clone()) };
            // the start pose of its configuration, 40 m away, given without a time
            let mut configured = state;
            configured.pos_ned_m = nalgebra::Vector3::new(-10.0, 60.0, 0.0);
            let init = NodeInit::Pending {
                config: Box::new(cfg),
                origin: Some(origin),
                state: Some((None, configured)),
                from_autopilot: false,
            };
            NodeShell::new(init, config, at(0)).unwrap()
        };
        let send = |s: &mut NodeShell, seq: &mut u8, msg: MavMessage| {
            *seq = seq.wrapping_add(1);
            let header = MavHeader { system_id: 3, component_id: 1, sequence: *seq };
            s.vehicle_frame((header, Some(msg.clone()), frame(3, 1, *seq, &msg)), at(1)).unwrap();
        };
        let imu = |t_us: u64| MavMessage::RAW_IMU(RAW_IMU_DATA { time_usec: t_us, zacc: -1000, ..Default::default() });
        let estimate = |flags: u16| {
            [
                MavMessage::ATTITUDE(ATTITUDE_DATA { time_boot_ms: 70_000, yaw: 1.0, yawspeed: 0.05, ..Default::default() }),
                MavMessage::GLOBAL_POSITION_INT(GLOBAL_POSITION_INT_DATA {
                    time_boot_ms: 70_000,
                    lat: wire::deg_to_e7(origin.lat_deg + 30.0 / 111_319.49),
                    lon: wire::deg_to_e7(origin.lon_deg),
                    alt: (origin.alt_m * 1000.0) as i32,
                    vx: 100,
                    vy: 150,
                    ..Default::default()
                }),
                MavMessage::EKF_STATUS_REPORT(EKF_STATUS_REPORT_DATA {
                    flags: EkfStatusFlags::from_bits_retain(flags),
                    ..Default::default()
                }),
            ]
        };
        let yaw_sigma_deg = |s: &NodeShell| s.core().unwrap().filter().output_covariances().yaw_variance().sqrt().to_degrees();
        let horizontal_sigma = |s: &NodeShell| {
            let p = s.core().unwrap().filter().output_covariances().position();
            (p[(0, 0)] + p[(1, 1)]).sqrt()
        };

        // EKF3 without a horizontal position (0x0027): the heading alone
        let mut s = start(Some(saved.clone()));
        let mut seq = 0;
        send(&mut s, &mut seq, imu(69_900_000));
        assert!(s.core().is_none(), "the first sample waits for the autopilot's estimate");
        send(&mut s, &mut seq, imu(69_925_000));
        assert!(s.core().is_none(), "and does not start from the configured pose meanwhile");
        for m in estimate(0x0027) {
            send(&mut s, &mut seq, m);
        }
        send(&mut s, &mut seq, imu(70_100_000));
        let f = s.core().expect("restored").filter();
        assert_eq!(f.time(), TimeUs(70_100_000));
        assert!((f.yaw_rad() - (1.0 + 0.05 * 0.1)).abs() < 1e-6, "the autopilot's heading at the sample: {}", f.yaw_rad());
        assert!(yaw_sigma_deg(&s) < 3.0, "the saved heading's, the gyro's drift over 10 s and the floor: {}", yaw_sigma_deg(&s));
        let coasted = nalgebra::Vector2::new(10.0, 20.0) + nalgebra::Vector2::new(2.0 * yaw0.cos(), 2.0 * yaw0.sin()) * 10.1;
        assert!((f.position_ned_m().xy() - coasted).norm() < 1e-6, "the position extrapolated: {}", f.position_ned_m());
        assert!(horizontal_sigma(&s) > 100.0, "with the land bound");
        assert!((f.velocity_ned_m_s().xy().norm() - 2.0).abs() < 1e-9, "the speed kept");
        assert!(
            (f.velocity_ned_m_s().y.atan2(f.velocity_ned_m_s().x) - f.yaw_rad()).abs() < 1e-6,
            "pointing where the rover points"
        );

        // EKF3 still on its position (0x033f): position and velocity too, drift-sized
        let mut s = start(Some(saved.clone()));
        let mut seq = 0;
        for m in estimate(0x033f) {
            send(&mut s, &mut seq, m);
        }
        send(&mut s, &mut seq, imu(70_100_000));
        let f = s.core().expect("restored at once: the estimate was there").filter();
        assert!((f.position_ned_m().xy() - nalgebra::Vector2::new(30.0 + 0.1, 0.15)).norm() < 0.02, "{}", f.position_ned_m());
        assert!((f.velocity_ned_m_s().xy() - nalgebra::Vector2::new(1.0, 1.5)).norm() < 1e-9);
        assert!(horizontal_sigma(&s) < 15.0, "the IMU's drift over 10 s, not a land vehicle's: {}", horizontal_sigma(&s));
        // what it asked for at 10 Hz goes back to the autopilot's default rates, after the rest
        let requests: Vec<(&str, f64)> = summary(&s).rate_requests.iter().map(|r| (r.message, r.rate_hz)).collect();
        assert_eq!(
            requests,
            [
                ("ATTITUDE", 10.0),
                ("GLOBAL_POSITION_INT", 10.0),
                ("EKF_STATUS_REPORT", 10.0),
                ("ESTIMATOR_STATUS", 10.0),
                ("RAW_IMU", 40.0),
                ("WHEEL_DISTANCE", 20.0),
                ("ATTITUDE", 0.0),
                ("GLOBAL_POSITION_INT", 0.0),
                ("EKF_STATUS_REPORT", 0.0),
                ("ESTIMATOR_STATUS", 0.0)
            ]
        );

        // no estimate at all: restored as before, 3 s after the first sample
        let mut s = start(Some(saved));
        let mut seq = 0;
        send(&mut s, &mut seq, imu(69_900_000));
        send(&mut s, &mut seq, imu(69_900_000 + FIX_WAIT_US - 25_000));
        assert!(s.core().is_none());
        send(&mut s, &mut seq, imu(69_900_000 + FIX_WAIT_US));
        assert!(yaw_sigma_deg(&s) > 100.0, "the heading carried 12.9 s with the land bound: {}", yaw_sigma_deg(&s));
        // and a node without a saved state starts from its configured pose at once
        let mut s = start(None);
        let mut seq = 0;
        send(&mut s, &mut seq, imu(69_900_000));
        send(&mut s, &mut seq, imu(69_925_000));
        assert!((s.core().expect("started").filter().position_ned_m().xy() - nalgebra::Vector2::new(-10.0, 60.0)).norm() < 0.1); // (25 ms at 2 m/s)
    }
}
