//! `cooploc replay`: a recorded log (see [`crate::recording`]) fed back through the filters,
//! with no network and no clock.
//!
//! - [`replay_nodes`] rebuilds every node the log describes (metadata `cooploc.node.<id>`, the
//!   vehicle profile attached, or the scenario as `scenario.toml`) as the
//!   [`NodeShell`] it ran, and feeds the shell what the node's shell was fed: the frames it
//!   received from its vehicle and its peers, and its recorded events (polls with their wall
//!   time, the end of input, the clock's mappings, ranges), in file order. The shell makes the
//!   node's start itself (a given state checked against the vehicle's first sample, SIM_STATE,
//!   the origin, the hand-over, the saved state). Because the shell and its core are
//!   deterministic given those calls, the estimates are the recorded ones bit for bit and the
//!   node starts as it did; [`NodeReplay::matches`] checks both.
//! - [`compare_methods`] takes the inputs the vehicles actually sent (IMU, odometry, ranges, as
//!   logged) and runs any method offline on them, centralized included, when the log says which
//!   simulated run it is (metadata `cooploc.run`: seed and run), so that the truth is known.

use std::collections::BTreeMap;

use crate::estimation::nav::NavState;
use crate::estimation::{Method, PlatformId, RangeSample};
use crate::experiment::{FilterRun, run_filter};
use crate::node::core::{NodeConfig, NodeCore, NodeInput};
use crate::node::inputs::VehicleEvent;
use crate::node::log::{LogStart, NodeEvent, NodeLogHeader, events_topic, saved_state_attachment_name, vehicle_attachment_name};
use crate::node::peers::Source;
use crate::node::profile::VehicleProfile;
use crate::node::saved::SavedState;
use crate::node::shell::{NodeInit, NodeShell, Now, Record, ShellConfig, ShellOutput};
use crate::protocol::MavMessage;
use crate::protocol::framing::split_frames;
use crate::protocol::wire::{self, EstimateReport, GeoOrigin};
use crate::recording::{Direction, Link, Log, topics};
use crate::sitl::{Scenario, World};
use crate::time::TimeUs;

/// Name of the metadata record that says which simulated run a log holds.
pub const RUN_METADATA_NAME: &str = "cooploc.run";

/// Why a log cannot be replayed.
#[derive(Debug, thiserror::Error)]
pub enum ReplayError {
    #[error("the log has no scenario attachment (scenario.toml) and no vehicle profile for a node")]
    NoScenario,
    #[error("the log's scenario: {0}")]
    Scenario(String),
    #[error("metadata {record}: field {field}: {problem}")]
    Metadata { record: String, field: String, problem: String },
    #[error("the log describes no node (no cooploc.node.<id> metadata)")]
    NoNode,
    #[error("node {0}: {1}")]
    Node(PlatformId, String),
    #[error("the log does not say which simulated run it holds (no cooploc.run metadata): no truth to compare with")]
    NoRun,
    #[error("offline run: {0}")]
    Offline(String),
}

/// The scenario attached to a log, as a world.
pub fn world_of(log: &Log) -> Result<World, ReplayError> {
    let a = log.attachments.iter().find(|a| a.name == "scenario.toml").ok_or(ReplayError::NoScenario)?;
    let text = std::str::from_utf8(&a.data).map_err(|e| ReplayError::Scenario(e.to_string()))?;
    let scenario = Scenario::from_toml_str(text).map_err(|e| ReplayError::Scenario(e.to_string()))?;
    World::new(&scenario).map_err(|e| ReplayError::Scenario(e.to_string()))
}

/// Node `id`'s vehicle profile: the one attached to the log (`vehicle.<id>.toml`), or the
/// vehicle part of the scenario (logs of nodes that ran without `--vehicle-config`, or older).
pub fn profile_of(log: &Log, world: Option<&World>, id: PlatformId) -> Result<VehicleProfile, ReplayError> {
    match (log.attachments.iter().find(|a| a.name == vehicle_attachment_name(id)), world) {
        (Some(a), _) => {
            let text = std::str::from_utf8(&a.data).map_err(|e| ReplayError::Node(id, format!("vehicle profile: {e}")))?;
            VehicleProfile::from_toml_str(text).map_err(|e| ReplayError::Node(id, e.to_string()))
        }
        (None, Some(world)) => Ok(VehicleProfile::from_spec(&world.scenario().vehicle_of(id))),
        (None, None) => Err(ReplayError::NoScenario),
    }
}

fn field<T: std::str::FromStr>(record: &str, m: &BTreeMap<String, String>, name: &str) -> Result<T, ReplayError>
where
    T::Err: std::fmt::Display,
{
    let bad = |problem: String| ReplayError::Metadata { record: record.into(), field: name.into(), problem };
    m.get(name).ok_or_else(|| bad("missing".into()))?.parse::<T>().map_err(|e| bad(e.to_string()))
}

/// One node of the log, replayed.
#[derive(Debug, Clone)]
pub struct NodeReplay {
    pub id: PlatformId,
    pub method: Method,
    /// The estimates the node sent (COOPLOC_ESTIMATE on its cooperative link), in order.
    pub recorded: Vec<EstimateReport>,
    /// The estimates the replayed core produced.
    pub replayed: Vec<EstimateReport>,
    /// The replayed core's estimate at the end of the log.
    pub last: Option<EstimateReport>,
    /// IMU samples the replayed core took.
    pub imu_replayed: u64,
    /// How the node started (its Init, StartRefused and Restored events), as logged and as the
    /// replayed shell started.
    pub recorded_starts: Vec<NodeEvent>,
    pub replayed_starts: Vec<NodeEvent>,
}

impl NodeReplay {
    fn new(id: PlatformId, method: Method) -> Self {
        NodeReplay {
            id,
            method,
            recorded: Vec::new(),
            replayed: Vec::new(),
            last: None,
            imu_replayed: 0,
            recorded_starts: Vec::new(),
            replayed_starts: Vec::new(),
        }
    }

    /// Every estimate equal, bit for bit, and as many; the node started as it did.
    pub fn matches(&self) -> bool {
        self.recorded.len() == self.replayed.len()
            && self.recorded.iter().zip(&self.replayed).all(|(a, b)| estimate_bits(a) == estimate_bits(b))
            && self.recorded_starts == self.replayed_starts
    }
}

/// An estimate as the bytes it goes on the wire with (a fixed header): equality of these is
/// equality of what was sent.
fn estimate_bits(e: &EstimateReport) -> Vec<u8> {
    let header = mavlink_core::MavHeader { system_id: 1, component_id: 1, sequence: 0 };
    wire::to_frame(header, &wire::estimate_to_message(e))
}

/// The node ids the log describes.
pub fn node_ids(log: &Log) -> Vec<PlatformId> {
    let mut ids: Vec<PlatformId> =
        log.metadata.iter().filter_map(|m| m.name.strip_prefix("cooploc.node.")).filter_map(|s| s.parse().ok()).collect();
    ids.sort_unstable();
    ids.dedup();
    ids
}

/// Replays every node of the log (see the module documentation).
pub fn replay_nodes(log: &Log) -> Result<Vec<NodeReplay>, ReplayError> {
    let ids = node_ids(log);
    if ids.is_empty() {
        return Err(ReplayError::NoNode);
    }
    // A node on a real vehicle ran without a scenario: its profile is attached.
    let world = match world_of(log) {
        Ok(w) => Some(w),
        Err(ReplayError::NoScenario) => None,
        Err(e) => return Err(e),
    };
    // Nodes are independent of one another: one per core.
    use rayon::prelude::*;
    ids.into_par_iter().map(|id| replay_node(log, world.as_ref(), id)).collect()
}

/// What a node's log metadata (`cooploc.node.ID`) says about how it ran.
struct NodeHeader {
    method: Method,
    cfg: NodeConfig,
    profile: crate::node::profile::VehicleProfile,
    /// None: the vehicle gave it (its Init event says which).
    origin: Option<GeoOrigin>,
    start: LogStart,
    hand_over: Option<bool>,
}

fn node_header(log: &Log, world: Option<&World>, id: PlatformId) -> Result<NodeHeader, ReplayError> {
    let record = format!("cooploc.node.{id}");
    let m = &log.metadata_named(&record).expect("listed").entries;
    let header = NodeLogHeader::from_metadata(m).map_err(|e| ReplayError::Metadata {
        record: record.clone(),
        field: e.field,
        problem: e.problem,
    })?;
    let profile = profile_of(log, world, id)?;
    // No latitude in the profile: the node took the vehicle's origin (its Init event says which).
    let model = profile.nav_model(profile.latitude().unwrap_or(0.0));
    Ok(NodeHeader {
        method: header.method,
        cfg: header.config(model),
        profile,
        origin: header.origin,
        start: header.start,
        hand_over: header.hand_over,
    })
}

/// Whether a logged event is one of the node's start: made, refused or restored. The replayed
/// shell must make the same ones.
fn is_start(event: &NodeEvent) -> bool {
    matches!(event, NodeEvent::Init { .. } | NodeEvent::StartRefused { .. } | NodeEvent::Restored { .. })
}

/// The shell node `id` started as, from its header: given a state (with its time and origin:
/// checked against the vehicle's first sample), or waiting for what the vehicle gives, at the
/// autopilot's hand-over or not; offered the saved state the log holds. Its configuration is a
/// replay's: no key (the log holds the frames the node took), no peers, no ticks' chores, the
/// clock's mapping from the log's Clock events, its records given back.
fn shell_of(log: &Log, h: &NodeHeader, id: PlatformId) -> Result<NodeShell, String> {
    let events: Vec<NodeEvent> = log.topic(&events_topic(id)).filter_map(|m| m.json().ok()).collect();
    // (a log written before the header said it: the Init event holds the autopilot's state)
    let hand_over = h.hand_over.unwrap_or_else(|| events.iter().any(|e| matches!(e, NodeEvent::Init { state: Some(_), .. })));
    let restore = match log.attachments.iter().find(|a| a.name == saved_state_attachment_name(id)) {
        Some(a) => {
            let text = std::str::from_utf8(&a.data).map_err(|e| format!("{}: {e}", a.name))?;
            Some(SavedState::parse(text).map_err(|e| format!("{}: {e}", a.name))?)
        }
        None if events.iter().any(|e| matches!(e, NodeEvent::Restored { .. })) => {
            return Err("the node restored a saved state that the log does not hold (a log written before it was \
                        attached, saved-state.<id>.txt): its start cannot be replayed"
                .into());
        }
        None => None,
    };
    let cfg = h.cfg.clone();
    let init = match (&h.start, h.origin) {
        (LogStart::Given { t0: Some(t0), state }, Some(origin)) => {
            let state = NavState::for_model(&cfg.model, *state);
            NodeInit::Given { core: Box::new(NodeCore::new(cfg, *t0, state).map_err(|e| e.to_string())?), origin }
        }
        (LogStart::Given { t0, state }, origin) => {
            NodeInit::Pending { config: Box::new(cfg), origin, state: Some((*t0, *state)), from_autopilot: hand_over }
        }
        (LogStart::FromVehicle, origin) => {
            NodeInit::Pending { config: Box::new(cfg), origin, state: None, from_autopilot: hand_over }
        }
    };
    let config = ShellConfig { record: true, restore, clock_from_log: true, ..ShellConfig::bare(h.profile.clone()) };
    NodeShell::new(init, config, Now { wall_us: 0, unix_ns: 0 }).map_err(|e| e.to_string())
}

/// Node `id` replayed through the shell it ran (see the module documentation). Its inputs, in
/// file order: every vehicle frame and cooperative frame it logged as received; its polls (the
/// wall time its core saw), the end of its input and its last epochs; the clock mappings it
/// took and the ranges its ranging device gave. Unix time is each record's log time.
fn replay_node(log: &Log, world: Option<&World>, id: PlatformId) -> Result<NodeReplay, ReplayError> {
    let h = node_header(log, world, id)?;
    let node_err = |e: String| ReplayError::Node(id, e);
    let mut shell = shell_of(log, &h, id).map_err(node_err)?;
    let sysid = id as u8;
    let vehicle_rx = topics::frames(Link::Vehicle(sysid), Direction::Rx);
    let coop_rx = topics::frames(Link::Coop(sysid), Direction::Rx);
    let coop_tx = topics::frames(Link::Coop(sysid), Direction::Tx);
    let events = events_topic(id);
    let mut out = NodeReplay::new(id, h.method);
    let mut now = Now { wall_us: 0, unix_ns: 0 };
    for msg in &log.messages {
        let topic = msg.topic();
        now.unix_ns = i64::try_from(msg.log_time_ns).unwrap_or(i64::MAX);
        if topic == vehicle_rx {
            for frame in split_frames(&msg.data) {
                shell.vehicle_frame(frame, now).map_err(|e| node_err(e.to_string()))?;
            }
        } else if topic == coop_rx {
            shell.coop_datagram(&msg.data, Source::Radio, now);
        } else if topic == coop_tx {
            if let Ok((_, MavMessage::COOPLOC_ESTIMATE(e))) = wire::from_any_frame(&msg.data)
                && let Ok(r) = wire::estimate_from_message(&e)
            {
                out.recorded.push(r);
            }
            continue;
        } else if topic == events {
            match msg.json::<NodeEvent>().map_err(|e| node_err(format!("event: {e}")))? {
                NodeEvent::Poll { wall_us } => {
                    now.wall_us = wall_us;
                    shell.poll(now);
                }
                NodeEvent::EndOfInput => shell.end_of_input(now),
                NodeEvent::RunPending => shell.run_pending(now),
                NodeEvent::Clock { offset_us, rtt_us } => shell.logged_clock(offset_us, rtt_us),
                NodeEvent::Range { epoch, range } => shell.input(NodeInput::OwnRange { epoch, range }, now),
                start @ (NodeEvent::Init { .. } | NodeEvent::StartRefused { .. } | NodeEvent::Restored { .. }) => {
                    out.recorded_starts.push(start)
                }
            }
        } else {
            continue;
        }
        for output in shell.take_outputs() {
            match output {
                ShellOutput::Record(Record::Estimate(e)) => out.replayed.push(e),
                ShellOutput::Record(Record::Event(e)) if is_start(&e) => out.replayed_starts.push(e),
                _ => {}
            }
        }
    }
    out.last = shell.core().map(NodeCore::estimate);
    out.imu_replayed = shell.core().map_or(0, |c| c.stats.imu);
    Ok(out)
}

/// Every method's offline run on the inputs the vehicles sent, as logged (see the module
/// documentation). Needs every platform's vehicle link in the log and the `cooploc.run` metadata.
pub fn compare_methods(log: &Log, methods: &[Method]) -> Result<Vec<FilterRun>, ReplayError> {
    let world = world_of(log)?;
    let run_meta = log.metadata_named(RUN_METADATA_NAME).ok_or(ReplayError::NoRun)?;
    let seed: u64 = field(RUN_METADATA_NAME, &run_meta.entries, "seed")?;
    let run: u32 = field(RUN_METADATA_NAME, &run_meta.entries, "run")?;
    let mut inputs = world.run_inputs(seed, run);
    let mut ranges: BTreeMap<u64, Vec<RangeSample>> = BTreeMap::new();
    for p in &mut inputs.platforms {
        let topic = topics::frames(Link::Vehicle(p.id as u8), Direction::Rx);
        let (mut imu, mut odometer, mut wheel) = (Vec::new(), Vec::new(), Vec::new());
        let mut decoder = profile_of(log, Some(&world), p.id)?.decoder();
        for msg in log.topic(&topic) {
            let Ok((header, m)) = wire::from_any_frame(&msg.data) else { continue };
            if header.system_id != u32::from(p.id) {
                continue;
            }
            for event in decoder.decode(&m) {
                match event {
                    VehicleEvent::Input(NodeInput::Imu(s)) => imu.push(s),
                    VehicleEvent::Input(NodeInput::Odometer(s)) => odometer.push(s),
                    VehicleEvent::Input(NodeInput::Wheel(s)) => wheel.push(s),
                    VehicleEvent::Input(NodeInput::OwnRange { range, .. }) => ranges.entry(range.t.0).or_default().push(range),
                    _ => {}
                }
            }
        }
        odometer.sort_by_key(|s| s.t);
        if imu.is_empty() && wheel.is_empty() {
            return Err(ReplayError::Offline(format!("platform {}: no IMU or wheel samples on {topic}", p.id)));
        }
        p.imu = imu;
        p.odometer = odometer;
        p.wheel = wheel;
    }
    let ranges: Vec<(TimeUs, Vec<RangeSample>)> = ranges
        .into_iter()
        .map(|(t, mut rs)| {
            rs.sort_by_key(|r| (r.from, r.to));
            (TimeUs(t), rs)
        })
        .collect();
    methods
        .iter()
        .map(|&method| {
            let r = if method == Method::DeadReckoning { &[][..] } else { &ranges[..] };
            run_filter(&world, &inputs, r, method).map_err(|e| ReplayError::Offline(e.to_string()))
        })
        .collect()
}
