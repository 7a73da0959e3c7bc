//! `cooploc demo`: the paper scenario end to end on loopback, in one process: the simulator,
//! one node per vehicle and the ground station, each on its own sockets exactly as the separate
//! commands would be, sharing one MCAP log. At the end the log is read back: every node is
//! replayed (its estimates must come out bit for bit) and every method is run offline on the
//! inputs the vehicles sent, for the final error table.

use std::net::SocketAddr;
use std::path::PathBuf;
use std::sync::{Arc, Mutex};
use std::time::Duration;

use crate::estimation::{Method, PlatformId};
use crate::experiment::{FilterRun, initial_state};
use crate::gcs::GcsSink;
use crate::gcs::runner::{GcsLinks, run as run_gcs};
use crate::gcs::state::GcsConfig;
use crate::node::core::{NodeConfig, NodeCore};
use crate::node::runner::{
    Links, LogStart, NodeInit, NodeLogHeader, NodeSummary, SharedRecorder, metadata_name, run as run_node,
};
use crate::protocol::record::Encoding;
use crate::protocol::wire::GeoOrigin;
use crate::recording::{Link, Recorder, RecorderOptions, read_log};
use crate::replay::{NodeReplay, RUN_METADATA_NAME, compare_methods, replay_nodes};
use crate::simulator::{BoundEndpoint, Interval, Simulator, SitlConfig, Speed, StreamDefaults, default_endpoints};
use crate::sitl::scenario::PAPER_TOML;
use crate::sitl::{Scenario, World};

/// What stopped the demo: a setting, or the step that failed and why.
#[derive(Debug, thiserror::Error)]
pub enum DemoError {
    #[error("{0}")]
    Invalid(String),
    #[error("{what}: {source}")]
    Step {
        what: String,
        #[source]
        source: Box<dyn std::error::Error + Send + Sync>,
    },
}

/// Names the step a failure happened in (the demo's `?`s).
trait Step<T> {
    fn step(self, what: impl Into<String>) -> Result<T, DemoError>;
}

impl<T, E: Into<Box<dyn std::error::Error + Send + Sync>>> Step<T> for Result<T, E> {
    fn step(self, what: impl Into<String>) -> Result<T, DemoError> {
        self.map_err(|e| DemoError::Step { what: what.into(), source: e.into() })
    }
}

impl<T> Step<T> for Option<T> {
    fn step(self, what: impl Into<String>) -> Result<T, DemoError> {
        self.ok_or_else(|| DemoError::Invalid(what.into()))
    }
}

/// What to run.
#[derive(Debug, Clone)]
pub struct DemoConfig {
    /// The scenario file; None: the paper's, built in (`sitl::scenario::PAPER_TOML`).
    pub scenario: Option<PathBuf>,
    pub seed: u64,
    pub run: u32,
    pub schedule: Option<String>,
    pub speed: f64,
    pub method: Method,
    pub log: PathBuf,
    pub http: SocketAddr,
    pub foxglove: Option<SocketAddr>,
    /// Stop the simulation at this simulated time, s (a short log); None: the whole scenario.
    pub duration_s: Option<f64>,
}

/// Where the live views are, once everything listens.
#[derive(Debug, Clone)]
pub struct DemoAddresses {
    pub http: SocketAddr,
    pub foxglove: Option<SocketAddr>,
    pub vehicles: Vec<(PlatformId, SocketAddr)>,
    pub nodes: Vec<(PlatformId, SocketAddr)>,
}

/// The outcome.
#[derive(Debug, Clone)]
pub struct DemoReport {
    pub nodes: Vec<NodeSummary>,
    pub replays: Vec<NodeReplay>,
    /// Every method offline on the logged inputs.
    pub methods: Vec<FilterRun>,
    pub log: PathBuf,
    pub log_messages: u64,
}

/// The scenario, cut to the demo's duration: itself, as text for the log, its world, and the
/// ranging schedule.
fn load_scenario(cfg: &DemoConfig) -> Result<(Scenario, String, World, String), DemoError> {
    let toml = match &cfg.scenario {
        Some(path) => std::fs::read(path).step(format!("reading {}", path.display()))?,
        None => PAPER_TOML.as_bytes().to_vec(),
    };
    let mut scenario =
        Scenario::from_toml_str(std::str::from_utf8(&toml).step("the scenario is not UTF-8")?).step("the scenario")?;
    if let Some(d) = cfg.duration_s {
        if !(d.is_finite() && d > 0.0) {
            return Err(DemoError::Invalid(format!("the duration must be a positive number of seconds, got {d}")));
        }
        scenario.duration_s = scenario.duration_s.min(d);
        for schedule in &mut scenario.ranging.schedules {
            if let Some(at) = &mut schedule.at_s {
                at.retain(|&t| t <= d);
            }
        }
    }
    let scenario_text = toml::to_string(&scenario).step("re-encoding the scenario")?;
    let world = World::new(&scenario).step("the scenario")?;
    let schedule = match cfg.schedule.clone() {
        Some(s) => {
            scenario.range_epochs(&s).step(format!("ranging schedule {s:?}"))?;
            s
        }
        None => scenario.ranging.schedules.first().map(|s| s.name.clone()).step("the scenario has no ranging schedule")?,
    };
    Ok((scenario, scenario_text, world, schedule))
}

/// The demo's log, with the run's metadata and the scenario attached.
fn open_log(cfg: &DemoConfig, schedule: &str, origin: GeoOrigin, scenario_text: &str) -> Result<SharedRecorder, DemoError> {
    if let Some(dir) = cfg.log.parent() {
        std::fs::create_dir_all(dir).step(format!("creating {}", dir.display()))?;
    }
    let mut rec = Recorder::create(&cfg.log, RecorderOptions { geo_origin: Some(origin), ..RecorderOptions::default() })
        .step(format!("creating the log {}", cfg.log.display()))?;
    rec.metadata(
        RUN_METADATA_NAME,
        [
            ("seed".to_string(), cfg.seed.to_string()),
            ("run".to_string(), cfg.run.to_string()),
            ("schedule".to_string(), schedule.to_string()),
            ("speed".to_string(), cfg.speed.to_string()),
            ("command".to_string(), std::env::args().collect::<Vec<_>>().join(" ")),
        ]
        .into(),
    )
    .step("the log")?;
    rec.attachment("scenario.toml", "application/toml", scenario_text.as_bytes()).step("the log")?;
    let recorder: SharedRecorder = Arc::new(Mutex::new(rec));
    Ok(recorder)
}

/// Runs the demo; `ready` is called once every server listens.
pub async fn run_demo(cfg: DemoConfig, ready: impl FnOnce(&DemoAddresses)) -> Result<DemoReport, DemoError> {
    let (scenario, scenario_text, world, schedule) = load_scenario(&cfg)?;
    let origin = GeoOrigin { lat_deg: scenario.latitude_deg, lon_deg: 0.0, alt_m: 0.0 };
    let recorder = open_log(&cfg, &schedule, origin, &scenario_text)?;

    // The simulator, on ephemeral ports, holding its clock until every vehicle has a node.
    let ids = world.platform_ids();
    let endpoints = default_endpoints(&ids, "127.0.0.1".parse().expect("an address"), 0).step("the vehicles' endpoints")?;
    let sitl = SitlConfig {
        schedule: schedule.clone(),
        seed: cfg.seed,
        run: cfg.run,
        speed: Speed::Factor(cfg.speed),
        endpoints,
        wait_for_peers: true,
        streams: StreamDefaults { sim_state: Interval::Every(500_000), ..StreamDefaults::default() },
        origin_lon_deg: origin.lon_deg,
        link_loss: 0.0,
        autopilot: Default::default(),
        origin: None,
        stream_rates: Vec::new(),
        gnss_time: false,
        gnss_lost_at: None,
        gnss_back_at: None,
        gnss_glitch_m: None,
    };
    let sim = Simulator::bind(world.clone(), sitl).await.step("starting the simulator")?;
    let vehicles: Vec<(PlatformId, SocketAddr)> = sim
        .endpoints()
        .into_iter()
        .filter_map(|(id, e)| match e {
            BoundEndpoint::Udp { local, .. } => Some((id, local)),
            BoundEndpoint::Serial { .. } => None,
        })
        .collect();

    // One node per vehicle, each knowing the nodes started before it.
    let mut node_addrs: Vec<(PlatformId, SocketAddr)> = Vec::new();
    let mut node_tasks = Vec::new();
    let (stop_tx, stop_rx) = tokio::sync::watch::channel(false);
    // Secure by default, as on vehicles: the demo's team signs its cooperative network with a
    // key made for this run (the nodes and the ground station share it in memory).
    let team_key = crate::protocol::signing::TeamKey::generate().map_err(|e| DemoError::Invalid(e.to_string()))?;
    for &(id, addr) in &vehicles {
        let (t0, state) = initial_state(&world, cfg.seed, cfg.run, id).step(format!("platform {id}'s initial state"))?;
        // an INS vehicle or a wheeled robot, as the scenario says
        let model = crate::experiment::nav_model(&world, id);
        let mut node_cfg = NodeConfig::for_model(id, cfg.method, model, Encoding::F64, ids.clone());
        node_cfg.authenticated_peers = true; // (the demo's team is signed)
        let meta = NodeLogHeader::new(&node_cfg, LogStart::Given { t0: Some(t0), state }, false, Some(origin)).to_metadata();
        {
            let mut r = recorder.lock().map_err(|_| DemoError::Invalid("recorder lock poisoned".into()))?;
            r.metadata(&metadata_name(id), meta).step("the log")?;
            r.declare_link(Link::Vehicle(id as u8), format!("udpout:{addr}"));
        }
        let state = crate::estimation::nav::NavState::for_model(&model, state);
        let core = NodeCore::new(node_cfg, t0, state).step("node configuration")?;
        let links = Links {
            vehicle: format!("udpout:{addr}"),
            coop: crate::node::coop_link::CoopSpec::udp("127.0.0.1:0".parse().expect("an address")),
            peers: node_addrs.iter().map(|(_, a)| *a).collect(),
            idle_exit: Some(Duration::from_millis(1500)),
            grace: Duration::from_millis(500),
            profile: crate::node::profile::VehicleProfile::from_spec(&scenario.vehicle_of(id)),
            team_key: Some(team_key.clone()),
            signing_state: None,
            state_file: None,
            vehicle_key: None,
            ranges: None,
        };
        let (bound_tx, bound_rx) = tokio::sync::oneshot::channel();
        let mut stop = stop_rx.clone();
        let shutdown = async move {
            let _ = stop.wait_for(|s| *s).await;
        };
        node_tasks.push(tokio::spawn(run_node(
            NodeInit::Ready(Box::new(core)),
            links,
            Some(recorder.clone()),
            bound_tx,
            shutdown,
        )));
        node_addrs.push((id, bound_rx.await.step("a node did not start")?.step("a demo node has a UDP address")?));
    }

    // The ground station, after the nodes (its vehicle links would start the clock).
    let gcs_cfg = GcsConfig { origin, vehicles: ids.clone(), team_key: Some(team_key), ..GcsConfig::default() };
    let gcs_links = GcsLinks {
        coop_bind: "127.0.0.1:0".parse().expect("an address"),
        peers: node_addrs.iter().map(|(_, a)| *a).collect(),
        vehicles: vehicles.iter().map(|(id, a)| (*id, format!("udpout:{a}"))).collect(),
        http: cfg.http,
        foxglove: cfg.foxglove,
        idle_exit: None,
    };
    let (gcs_bound_tx, gcs_bound_rx) = tokio::sync::oneshot::channel();
    let (gcs_stop_tx, gcs_stop_rx) = tokio::sync::oneshot::channel::<()>();
    let sink: Box<dyn GcsSink> = Box::new(crate::gcs::RecorderSink::beside_nodes(recorder.clone()));
    let gcs_task = tokio::spawn(run_gcs(gcs_cfg, gcs_links, vec![sink], gcs_bound_tx, async move {
        let _ = gcs_stop_rx.await;
    }));
    let gcs_bound = gcs_bound_rx.await.step("the ground station did not start")?;
    ready(&DemoAddresses {
        http: gcs_bound.http,
        foxglove: gcs_bound.foxglove,
        vehicles: vehicles.clone(),
        nodes: node_addrs.clone(),
    });

    let sim_report = sim.run(std::future::pending::<()>()).await.step("the simulator")?;
    tracing::info!(reason = ?sim_report.reason, "simulation finished");
    let mut nodes = Vec::new();
    for task in node_tasks {
        // Every node stops by itself once its vehicle is silent (idle exit).
        match tokio::time::timeout(Duration::from_secs(30), task).await {
            Ok(joined) => nodes.push(joined.step("a node task panicked")?.step("a node")?),
            Err(_) => {
                let _ = stop_tx.send(true);
                return Err(DemoError::Invalid("a node did not stop within 30 s of the end of the simulation".into()));
            }
        }
    }
    tokio::time::sleep(Duration::from_millis(700)).await; // the ground station's last page refresh
    let _ = gcs_stop_tx.send(());
    let _ = gcs_task.await;
    let rec = Arc::try_unwrap(recorder).map_err(|_| DemoError::Invalid("the log is still in use".into()))?;
    let stats =
        rec.into_inner().map_err(|_| DemoError::Invalid("recorder lock poisoned".into()))?.finish().step("closing the log")?;

    // Read the log back: replay every node, run every method on what the vehicles sent.
    let log = read_log(&cfg.log).step(format!("reading back {}", cfg.log.display()))?;
    let replays = replay_nodes(&log).step("replaying the nodes")?;
    let methods = compare_methods(
        &log,
        &[
            Method::DeadReckoning,
            Method::NoPropagation,
            Method::Decentralized,
            Method::Centralized,
            Method::CovarianceIntersection,
        ],
    )
    .step("running every method on the logged inputs")?;
    Ok(DemoReport { nodes, replays, methods, log: cfg.log.clone(), log_messages: stats.messages_written })
}
