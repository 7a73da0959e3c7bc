//! `cooploc replay`: a recorded log (see [`crate::recording`]) fed back through the filters,
//! with no network and no clock.
//!
//! - [`replay_nodes`] rebuilds every node the log describes (metadata `cooploc.node.<id>`, the
//!   scenario attached as `scenario.toml`) and calls its core exactly as the node did: the frames
//!   it received from its vehicle and its peers, and its recorded events (clock ticks, end of
//!   input), in file order. Because the core is deterministic given those calls, the estimates
//!   it produces are the recorded ones bit for bit; [`NodeReplay::matches`] checks it.
//! - [`compare_methods`] takes the inputs the vehicles actually sent (IMU, odometry, ranges, as
//!   logged) and runs any method offline on them, centralized included, when the log says which
//!   simulated run it is (metadata `cooploc.run`: seed and run), so that the truth is known.

use std::collections::BTreeMap;

use crate::estimation::nav::NavState;
use crate::estimation::{Method, PlatformId, RangeSample};
use crate::experiment::{FilterRun, run_filter};
use crate::node::core::{NodeConfig, NodeCore, NodeInput, NodeOutput};
use crate::node::inputs::VehicleEvent;
use crate::node::log::{LogStart, NodeEvent, NodeLogHeader, events_topic, vehicle_attachment_name};
use crate::node::profile::VehicleProfile;
use crate::protocol::MavMessage;
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
}

impl NodeReplay {
    /// Every estimate equal, bit for bit, and as many.
    pub fn matches(&self) -> bool {
        self.recorded.len() == self.replayed.len()
            && self.recorded.iter().zip(&self.replayed).all(|(a, b)| estimate_bits(a) == estimate_bits(b))
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
    Ok(NodeHeader { method: header.method, cfg: header.config(model), profile, origin: header.origin, start: header.start })
}

/// The core a node made at its Init event: at `t0_us`, about the origin the vehicle gave or the
/// log's, from the hand-over state, the given state (`start`, unless refused) or the last
/// SIM_STATE.
fn core_at_init(
    h: &NodeHeader,
    init: (u64, Option<[f64; 3]>, Option<crate::node::log::StartState>),
    start: &LogStart,
    last_sim_state: Option<&crate::protocol::dialect::cooploc::SIM_STATE_DATA>,
) -> Result<(NodeCore, GeoOrigin), String> {
    let (t0_us, from_vehicle, hand_over) = init;
    let mut cfg = h.cfg.clone();
    let origin = match (from_vehicle, h.origin) {
        (Some([lat_deg, lon_deg, alt_m]), _) => {
            cfg.model.set_latitude(lat_deg);
            GeoOrigin { lat_deg, lon_deg, alt_m }
        }
        (None, Some(o)) => o,
        (None, None) => return Err("Init event without the vehicle's origin".into()),
    };
    let state = match (start, hand_over) {
        // the hand-over start: the autopilot's estimate, as logged
        (_, Some(hand_over)) => hand_over.state(),
        (LogStart::Given { state, .. }, None) => *state,
        (LogStart::FromVehicle, None) => {
            let s = last_sim_state.ok_or("Init event before any SIM_STATE")?;
            wire::ins_state_from_sim_state(s, &origin).map_err(|e| e.to_string())?
        }
    };
    let state = NavState::for_model(&cfg.model, state);
    Ok((NodeCore::new(cfg, TimeUs(t0_us), state).map_err(|e| e.to_string())?, origin))
}

fn replay_node(log: &Log, world: Option<&World>, id: PlatformId) -> Result<NodeReplay, ReplayError> {
    let h = node_header(log, world, id)?;
    let node_err = |e: String| ReplayError::Node(id, e);
    let (method, cfg, origin) = (h.method, &h.cfg, h.origin);
    let mut start = h.start.clone();
    let mut core = match (&start, origin) {
        (LogStart::Given { t0: Some(t0), state }, Some(_)) => {
            let state = NavState::for_model(&cfg.model, *state);
            Some(NodeCore::new(cfg.clone(), *t0, state).map_err(|e| node_err(e.to_string()))?)
        }
        _ => None,
    };
    let sysid = id as u8;
    let vehicle_rx = topics::frames(Link::Vehicle(sysid), Direction::Rx);
    let coop_rx = topics::frames(Link::Coop(sysid), Direction::Rx);
    let coop_tx = topics::frames(Link::Coop(sysid), Direction::Tx);
    let events = events_topic(id);
    let mut out = NodeReplay { id, method, recorded: Vec::new(), replayed: Vec::new(), last: None, imu_replayed: 0 };
    let mut last_sim_state = None;
    let mut decoder = h.profile.decoder();
    for msg in &log.messages {
        let topic = msg.topic();
        let outputs = if topic == vehicle_rx {
            let Ok((header, m)) = wire::from_any_frame(&msg.data) else { continue };
            if header.system_id != u32::from(id) {
                continue;
            }
            if let MavMessage::SIM_STATE(s) = &m {
                last_sim_state = Some(s.clone());
            }
            if matches!(m, MavMessage::SIM_STATE(_)) {
                continue;
            }
            // every frame goes through the decoder, as in the node (it keeps state)
            let Some(core) = core.as_mut() else {
                decoder.decode(&m);
                continue;
            };
            let mut outputs = Vec::new();
            for event in decoder.decode(&m) {
                if let VehicleEvent::Input(input) = event {
                    outputs.extend(core.handle(input));
                }
            }
            outputs
        } else if topic == coop_rx {
            let Ok((header, m)) = wire::from_any_frame(&msg.data) else { continue };
            let (Some(core), Ok(from)) = (core.as_mut(), PlatformId::try_from(header.system_id)) else { continue };
            if from == id {
                continue;
            }
            core.handle(NodeInput::Peer { from, msg: Box::new(m) })
        } else if topic == coop_tx {
            if let Ok((_, MavMessage::COOPLOC_ESTIMATE(e))) = wire::from_any_frame(&msg.data)
                && let Ok(r) = wire::estimate_from_message(&e)
            {
                out.recorded.push(r);
            }
            continue;
        } else if topic == events {
            let event: NodeEvent = msg.json().map_err(|e| node_err(format!("event: {e}")))?;
            match (event, core.as_mut()) {
                (NodeEvent::Clock { offset_us, .. }, _) => {
                    decoder.set_companion_offset(offset_us);
                    continue;
                }
                (NodeEvent::Range { epoch, range }, Some(c)) => c.handle(NodeInput::OwnRange { epoch, range }),
                (NodeEvent::StartRefused { .. }, _) => {
                    // the given state was stale: the node waited for SIM_STATE (its Init event)
                    core = None;
                    start = LogStart::FromVehicle;
                    continue;
                }
                (NodeEvent::Restored { state, .. }, _) => {
                    // the node started from its saved state: the core as it made it
                    let mut cfg = cfg.clone();
                    cfg.model.set_latitude(state.origin[0]);
                    let (t0, nav, p) = (TimeUs(state.t_us), state.nav_state(), state.covariance_matrix());
                    core = Some(NodeCore::restored(cfg, t0, nav, &p).map_err(|e| node_err(e.to_string()))?);
                    continue;
                }
                (NodeEvent::Init { t0_us, origin: from_vehicle, state: hand_over }, None) => {
                    let hand_over_start = hand_over.is_some();
                    let init = (t0_us, from_vehicle, hand_over);
                    let (made, origin) = core_at_init(&h, init, &start, last_sim_state.as_ref()).map_err(node_err)?;
                    if hand_over_start {
                        // as the node: the team's filter runs on the autopilot's GNSS fixes
                        decoder.fuse_gnss(origin);
                    }
                    core = Some(made);
                    continue;
                }
                (NodeEvent::Poll { wall_us }, Some(c)) => c.poll(wall_us),
                (NodeEvent::EndOfInput, Some(c)) => c.end_of_input(),
                (NodeEvent::RunPending, Some(c)) => c.run_pending(),
                _ => continue,
            }
        } else {
            continue;
        };
        for o in outputs {
            if let NodeOutput::ToPeers(MavMessage::COOPLOC_ESTIMATE(e)) = o
                && let Ok(r) = wire::estimate_from_message(&e)
            {
                out.replayed.push(r);
            }
        }
    }
    out.last = core.as_ref().map(NodeCore::estimate);
    out.imu_replayed = core.as_ref().map_or(0, |c| c.stats.imu);
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
