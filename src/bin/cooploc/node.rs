//! `cooploc node`: arguments, logging and the final summary around [`cooploc::node`].

use std::net::SocketAddr;
use std::path::PathBuf;
use std::time::Duration;

use anyhow::{Context, bail};
use cooploc::estimation::ins::InsState;
use cooploc::estimation::nav::NavState;
use cooploc::node::coop_link::{CoopSpec, Multicast};
use cooploc::node::core::{NodeConfig, NodeCore};
use cooploc::node::profile::VehicleProfile;
use cooploc::node::runner::{Links, LogStart, NodeInit, NodeLogHeader, RangeSource, metadata_name, run, vehicle_attachment_name};
use cooploc::protocol::wire::GeoOrigin;
use cooploc::recording::{Link, Recorder, RecorderOptions};
use cooploc::sitl::scenario::Scenario;
use cooploc::sitl::world::World;
use cooploc::time::TimeUs;
use nalgebra::{UnitQuaternion, Vector3};

/// Largest UDP payload over IPv4.
const MAX_UDP_PAYLOAD: usize = 65_507;

#[derive(clap::Args)]
pub struct Args {
    /// Every option below in one TOML file (`id = 1`, `vehicle = "tcpout:127.0.0.1:5760"`,
    /// `vehicle_config = "rover.toml"`, `team = [1, 2, 3]`, `peer = ["10.0.0.2:14600"]`, ...;
    /// paths relative to the file): a vehicle computer's service runs `cooploc node --config
    /// FILE`. An option also given on the command line takes the command line's value.
    #[arg(long, value_name = "FILE")]
    config: Option<PathBuf>,
    /// Platform id: the vehicle's MAVLink system id.
    #[arg(long)]
    id: u16,
    /// MAVLink URL of the vehicle (udpout:HOST:PORT, udpin:HOST:PORT, tcpout:, tcpin:, serial:/dev/ttyX:BAUD).
    #[arg(long)]
    vehicle: String,
    /// Local address of the cooperative-network socket (UDP).
    #[arg(long, default_value = "127.0.0.1:0")]
    coop_bind: SocketAddr,
    /// Multicast on the cooperative network: on, off, or auto (on when --coop-bind is not a
    /// loopback address and no --peer is given: the plug-and-play LAN set-up; a failed join is
    /// then said and the node goes on with the peers it learns). With `on`, given peers heard on
    /// the group get no unicast copy; the others (another subnet) do.
    #[arg(long, default_value = "auto", value_parser = ["auto", "on", "off"])]
    multicast: String,
    /// The multicast group (GROUP:PORT).
    #[arg(long, default_value_t = cooploc::node::coop_link::DEFAULT_GROUP)]
    multicast_group: std::net::SocketAddrV4,
    /// Hops a multicast datagram may cross (1: this subnet).
    #[arg(long, default_value_t = 1)]
    multicast_ttl: u32,
    /// Address of the interface to send and join the group on (default: --coop-bind's, or the
    /// kernel's choice when that is 0.0.0.0).
    #[arg(long, default_value_t = std::net::Ipv4Addr::UNSPECIFIED)]
    multicast_interface: std::net::Ipv4Addr,
    /// Most bytes in one UDP datagram: each batch of frames is packed into few datagrams (IP
    /// headers are 28 B a datagram); 0: one frame per datagram.
    #[arg(long, default_value_t = cooploc::protocol::budget::MAX_DATAGRAM)]
    datagram_bytes: usize,
    /// A serial telemetry radio as the cooperative link instead of UDP: PATH:BAUD (e.g.
    /// /dev/ttyUSB0:57600). Its firmware must share one channel among the team (multipoint).
    #[arg(long, value_name = "PATH:BAUD", conflicts_with_all = ["coop_bind", "peers", "multicast_group"])]
    coop_serial: Option<String>,
    /// Peer nodes' cooperative addresses (more are learned from their traffic).
    #[arg(long = "peer")]
    peers: Vec<SocketAddr>,
    /// Method.
    #[arg(long, value_enum, default_value = "dcl")]
    method: crate::args::NodeMethodArg,
    /// The vehicle profile (sitl/vehicles/*.toml): sensor figures, the messages to read, the
    /// rates to ask for, what to send back. Without it: the vehicle part of --scenario, as the
    /// simulator's vehicles are.
    #[arg(long)]
    vehicle_config: Option<PathBuf>,
    /// The team's signing key (MAVLink 2 signing on the cooperative network): a file whose first
    /// line is 64 hex digits or a passphrase (hashed with SHA-256, as MAVProxy's `signing setup`
    /// does). Every frame the node sends is signed; unsigned, wrongly signed and replayed frames
    /// are refused and counted. `cooploc keygen FILE` makes one. A node refuses to start
    /// without it, unless told --insecure.
    #[arg(long, value_name = "FILE")]
    team_key: Option<PathBuf>,
    /// Run on an unauthenticated cooperative network (no --team-key): anyone who can reach the
    /// node's port can send it records. The node then refuses records that the teammates'
    /// ranges contradict and both of two different records for one platform and epoch
    /// (`node::vetting`), but a forgery that fits the ranges still moves the team. For a lab,
    /// a simulation or a link that is private by other means.
    #[arg(long, conflicts_with = "team_key")]
    insecure: bool,
    /// Keep the signing timestamp in this file across restarts (read at start, written every
    /// 5 s and at the end, 15 s of headroom): a companion without a real-time clock, or whose
    /// clock stepped back, still signs above every timestamp it used and is not refused as a
    /// replay. Only with --team-key.
    #[arg(long, value_name = "FILE", requires = "team_key")]
    signing_state: Option<PathBuf>,
    /// Keep the navigation state in this file (written every second of the team clock and at
    /// the end, whole or not at all), so that a node restarted with the same arguments starts
    /// where its vehicle was: at the vehicle's first sample, a state saved by this platform
    /// about this origin at most 30 s before is restored, moved on at its velocity and its
    /// covariance grown by what a land vehicle can do meanwhile; it wins over a start state
    /// that is older or stale. Anything else in the file is refused with the reason and the
    /// node starts as without it.
    #[arg(long, value_name = "FILE")]
    state_file: Option<PathBuf>,
    /// Sign the vehicle link with this key (the same file format as --team-key; MAVProxy's
    /// `signing setup PASSPHRASE` on the autopilot's port): for an autopilot that refuses
    /// unsigned frames. Every frame to the vehicle is signed, only signed frames are taken.
    #[arg(long, value_name = "FILE")]
    vehicle_key: Option<PathBuf>,
    /// Scenario of a simulated run (`cooploc sitl`'s): the vehicle part without
    /// --vehicle-config, the team without --team, and --init-from-run. A node on a real vehicle
    /// names none: --vehicle-config and --team say all it needs.
    #[arg(long)]
    scenario: Option<PathBuf>,
    /// Number format of the broadcast matrices (compact: 16-bit correlation form, under a third
    /// of f64's bytes, for radios; see `cooploc budget`).
    #[arg(long, value_enum, default_value = "f64")]
    encoding: crate::args::EncodingArg,
    /// Platform ids of the team (every epoch waits for their records), this one included;
    /// default: the --scenario's platforms.
    #[arg(long, value_delimiter = ',')]
    team: Vec<u16>,
    /// How long (wall time) an epoch waits for missing records before it runs without them, ms.
    #[arg(long, default_value_t = 2000)]
    epoch_timeout_ms: u64,
    /// Interval (wall time) between retransmission requests while an epoch waits, ms, taken as
    /// given. Without it: 100 ms, shortened to a tenth of the epoch period in wall time when
    /// epochs come faster (a faster schedule, or a simulation faster than real time).
    #[arg(long)]
    retry_ms: Option<u64>,
    /// The team's ranging schedule, when it is periodic: an epoch every this many ms of the team
    /// clock, the same on every member. The node then knows each epoch from the one before, not
    /// first from its own ranges or a teammate's record (a member that ranges to nobody
    /// broadcasts with the others instead of after them).
    #[arg(long)]
    epoch_period_ms: Option<u64>,
    /// Airtime slots on one shared channel (a radio network) carrying this many bytes per second
    /// one way at real time, the same on every member: each member broadcasts its record in its
    /// own slot (by its place in the sorted team list, each as long as the largest record takes
    /// on the air), and nobody asks for a missing record before every slot has passed. Needs
    /// --epoch-period-ms: the slots and the range grace must fit in the period.
    #[arg(long, requires = "epoch_period_ms")]
    airtime_bps: Option<f64>,
    /// Store bytes per second this node sends a teammate that was left out and asks for the
    /// team's cross-covariance store (two members answer): a store larger than that in an
    /// epoch comes over several epochs, and the teammate brings it forward by them. Default:
    /// an eighth of --airtime-bps with it (the two answerers take a quarter of the channel
    /// while someone rejoins), else the whole store at each answer (a network that takes it at
    /// once).
    #[arg(long)]
    store_bps: Option<u64>,
    /// Vehicle time the node waits after an epoch's instant for its radio's ranges of that
    /// epoch before it broadcasts its record, ms (raise it when ranges reach the node late).
    #[arg(long, default_value_t = 100)]
    range_grace_ms: u64,
    /// Do not send each own range as a COOPLOC_RANGE besides the record (which carries them):
    /// saves about 48 bytes per range on links that count every byte; ground stations then show
    /// no range lines.
    #[arg(long)]
    no_range_echo: bool,
    /// Probability that the range gate rejects a good range (chi-square gate on each range's
    /// innovation); 0 turns the gate off.
    #[arg(long, default_value_t = 1e-6)]
    gate_probability: f64,
    /// Initial position N,E,D (m), with the other --init-* flags. Without it or --init-from-run,
    /// the node initialises from the vehicle's first SIM_STATE (simulated vehicles).
    #[arg(long, value_delimiter = ',', allow_hyphen_values = true, conflicts_with = "init_from_run")]
    init_ned: Vec<f64>,
    /// Start as `cooploc experiment` does for SEED:RUN of the --scenario (truth plus the initial
    /// errors it draws), at time zero.
    #[arg(long, value_name = "SEED:RUN", requires = "scenario")]
    init_from_run: Option<String>,
    /// The hand-over start: a vehicle that starts with GNSS flies on its autopilot's estimate;
    /// when the autopilot's GNSS fix goes (GPS_RAW_INT), the node starts from the autopilot's
    /// estimate (GLOBAL_POSITION_INT, ATTITUDE) and, if the profile says
    /// `takeover_source_set`, switches the autopilot's EKF to that source set. Needs the
    /// profile's [origin]
    #[arg(long, conflicts_with_all = ["init_ned", "init_from_run"])]
    init_from_autopilot: bool,
    /// Initial velocity N,E,D (m/s).
    #[arg(long, value_delimiter = ',', allow_hyphen_values = true, default_values_t = [0.0, 0.0, 0.0])]
    init_vel_ned: Vec<f64>,
    /// Initial roll, pitch, yaw (deg).
    #[arg(long, value_delimiter = ',', allow_hyphen_values = true, default_values_t = [0.0, 0.0, 0.0])]
    init_rpy_deg: Vec<f64>,
    /// Time of the initial state in the team's clock (us); the first IMU sample must come after
    /// it. Default: the first IMU (or wheel) sample's time, once the team clock is known (a
    /// vehicle started where the --init-* flags say).
    #[arg(long)]
    init_time_us: Option<u64>,
    /// Longitude of the local NED origin, deg, to read SIM_STATE positions (its latitude is the
    /// scenario's); the same as `cooploc sitl --origin-lon-deg`.
    #[arg(long, default_value_t = 0.0, allow_negative_numbers = true)]
    origin_lon_deg: f64,
    /// A ranging device on the companion (a UWB module), besides the vehicle link:
    /// `udpin:HOST:PORT` (datagrams to this address; port 0: any, printed) or
    /// `serial:PATH:BAUD`. One line per range, `RANGE,<epoch>,<to>,<range_m>,<sigma_m>,<t_us>`
    /// (`t_us` in the team's clock, 0: on arrival; see crates/cooploc-node/src/node/ranging.rs).
    #[arg(long, value_name = "URL")]
    ranges: Option<String>,
    /// Record every frame in and out, the estimates and the node's events to this MCAP file.
    #[arg(long)]
    log: Option<PathBuf>,
    /// Stop when the vehicle has been silent this long (s); 0: run until Ctrl-C.
    #[arg(long, default_value_t = 0.0)]
    idle_exit_s: f64,
}

pub fn run_cmd(args: Args) -> anyhow::Result<()> {
    let (method, encoding) = (args.method.0, args.encoding.0);
    if args.id == 0 || args.id > 255 {
        bail!("--id {}: a MAVLink system id is 1..=255", args.id);
    }
    if !args.idle_exit_s.is_finite() || args.idle_exit_s < 0.0 {
        bail!("--idle-exit-s {}: must be a non-negative number of seconds", args.idle_exit_s);
    }
    let from_run = match &args.init_from_run {
        Some(text) => {
            let parsed = text.split_once(':').and_then(|(a, b)| Some((a.parse::<u64>().ok()?, b.parse::<u32>().ok()?)));
            Some(parsed.with_context(|| format!("--init-from-run {text:?}: expected SEED:RUN, e.g. 1:0"))?)
        }
        None => None,
    };
    let from_cli = !args.init_ned.is_empty();
    if from_cli {
        for (name, v) in
            [("--init-ned", &args.init_ned), ("--init-vel-ned", &args.init_vel_ned), ("--init-rpy-deg", &args.init_rpy_deg)]
        {
            if v.len() != 3 || v.iter().any(|x| !x.is_finite()) {
                bail!("{name}: three finite numbers, comma separated");
            }
        }
    }
    let (team_key, vehicle_key) = keys(&args)?;
    // The scenario of a simulated run, if any; the profile: a bad one is refused before any
    // socket opens.
    let world = match &args.scenario {
        Some(path) => Some(World::new(&Scenario::from_path(path)?)?),
        None => None,
    };
    let profile = match (&args.vehicle_config, &world) {
        (Some(path), _) => VehicleProfile::from_path(path)?,
        (None, Some(world)) => VehicleProfile::from_spec(&world.scenario().vehicle_of(args.id)),
        (None, None) => bail!(
            "no vehicle profile: give --vehicle-config FILE (vehicle_config in --config; examples in sitl/vehicles/), or the --scenario of a simulated run"
        ),
    };
    // Without a latitude in the profile, the node takes the vehicle's origin (GPS_GLOBAL_ORIGIN
    // or HOME_POSITION) before it starts; the INS gets that latitude.
    let latitude = profile.latitude();
    let model = profile.nav_model(latitude.unwrap_or(0.0));
    let initial = initial_state(&args, from_run, from_cli, world.as_ref())?;
    let team = match (&world, args.team.is_empty()) {
        (_, false) => args.team.clone(),
        (Some(world), true) => world.platform_ids(),
        (None, true) => bail!("name the team: --team 1,2,3 (team = [1, 2, 3] in --config), this node's id among them"),
    };
    if !team.contains(&args.id) {
        bail!("--team {team:?} does not hold this node's --id {}", args.id);
    }
    let retry_ms = args.retry_ms.unwrap_or(100);
    if retry_ms == 0 || retry_ms >= args.epoch_timeout_ms {
        bail!("--retry-ms {retry_ms} must be positive and below --epoch-timeout-ms {}", args.epoch_timeout_ms);
    }
    if !(args.origin_lon_deg.is_finite() && (-180.0..=180.0).contains(&args.origin_lon_deg)) {
        bail!("--origin-lon-deg must be in [-180, 180], got {}", args.origin_lon_deg);
    }
    let (budget_team, budget_dim) = (team.len(), model.error_dim());
    let mut cfg = NodeConfig::for_model(args.id, method, model, encoding, team);
    cfg.epoch_timeout_us = args.epoch_timeout_ms * 1000;
    cfg.retry_us = retry_ms * 1000;
    cfg.retry_follows_cadence = args.retry_ms.is_none();
    cfg.range_grace_us = args.range_grace_ms * 1000;
    cfg.echo_ranges = !args.no_range_echo;
    cfg.gate_probability = args.gate_probability;
    cfg.epoch_period_us = args.epoch_period_ms.map(|ms| ms.saturating_mul(1000));
    cfg.slot_us = airtime_slot_us(&args, (budget_team, budget_dim, encoding))?;
    cfg.store_bps = args.store_bps.unwrap_or_else(|| args.airtime_bps.map_or(0, |bps| (bps / 8.0) as u64));
    // the grid the decoder puts the vehicle's ranges on (the profile's)
    cfg.range_snap_us = u64::from(profile.inputs.epoch_grid_ms) * 1000;
    // signed: every record the core sees is a teammate's own (the shell drops the others)
    cfg.authenticated_peers = args.team_key.is_some();
    let origin = profile.geo_origin().or(latitude.map(|lat_deg| GeoOrigin { lat_deg, lon_deg: args.origin_lon_deg, alt_m: 0.0 }));
    let recorder = open_log(&args, &cfg, &initial, origin, &profile)?;
    let init = node_init(&args, cfg, initial, origin)?;
    let coop = coop_spec(&args)?;
    let ranges = range_source(&args)?;
    let links = Links {
        vehicle: args.vehicle.clone(),
        coop,
        peers: args.peers.clone(),
        idle_exit: (args.idle_exit_s > 0.0).then(|| Duration::from_secs_f64(args.idle_exit_s)),
        grace: Duration::from_millis(500),
        profile: profile.clone(),
        team_key,
        signing_state: args.signing_state.clone(),
        state_file: args.state_file.clone(),
        vehicle_key,
        ranges,
    };
    let rt = tokio::runtime::Builder::new_current_thread().enable_all().build()?;
    let runner_recorder = recorder.clone();
    let summary = rt.block_on(async move {
        let (tx, rx) = tokio::sync::oneshot::channel();
        let id = args.id;
        let announce = tokio::spawn(async move {
            match rx.await {
                Ok(Some(addr)) => println!("node {id} coop udp {addr}"),
                Ok(None) => println!("node {id} coop serial"),
                Err(_) => {}
            }
        });
        if args.insecure {
            println!(
                "node {id} cooperative network UNAUTHENTICATED (--insecure): records are vetted against the team's ranges, nothing more"
            );
        }
        let shutdown = crate::signal::shutdown_signal();
        let summary = run(init, links, runner_recorder, tx, shutdown).await;
        let _ = announce.await;
        summary
    })?;
    if let Some(rec) = recorder
        && let Ok(rec) = std::sync::Arc::try_unwrap(rec)
    {
        let stats = rec.into_inner().map_err(|_| anyhow::anyhow!("recorder lock poisoned"))?.finish()?;
        println!("node {} log {} messages", args.id, stats.messages_written);
    }
    if let Some(o) = &summary.origin_from_vehicle {
        println!(
            "node {} origin from the vehicle: lat_deg {:.7} lon_deg {:.7} alt_m {:.3}",
            args.id, o.lat_deg, o.lon_deg, o.alt_m
        );
    }
    let Some(e) = &summary.estimate else {
        println!(
            "node {} done: never initialised (no {} from the vehicle); {} inputs ignored",
            args.id,
            if summary.origin_from_vehicle.is_none() && profile.latitude().is_none() {
                "GPS_GLOBAL_ORIGIN"
            } else if args.init_from_autopilot {
                "GNSS loss (GPS_RAW_INT) with an estimate (GLOBAL_POSITION_INT, ATTITUDE)"
            } else {
                "SIM_STATE"
            },
            summary.before_init
        );
        return Ok(());
    };
    print_summary(&args, &summary, e, &profile, (budget_team, budget_dim, encoding));
    Ok(())
}

/// How the node starts: from the given state, or waiting for what the vehicle gives (its
/// configuration checked now rather than when the vehicle has said what is missing).
fn node_init(
    args: &Args,
    cfg: NodeConfig,
    initial: Option<(Option<TimeUs>, InsState)>,
    origin: Option<GeoOrigin>,
) -> anyhow::Result<NodeInit> {
    Ok(match (initial, origin) {
        (Some((Some(t0), state)), Some(origin)) => {
            let state = NavState::for_model(&cfg.model, state);
            let core = Box::new(NodeCore::new(cfg, t0, state).context("node configuration")?);
            NodeInit::Given { core, origin }
        }
        (state, origin) => {
            // Checked now rather than when the vehicle has said what is missing.
            let at_rest = NavState::for_model(&cfg.model, InsState::at_rest(UnitQuaternion::identity()));
            NodeCore::new(cfg.clone(), TimeUs(0), at_rest).context("node configuration")?;
            if args.init_from_autopilot && origin.is_none() {
                bail!("--init-from-autopilot: the profile needs an [origin], the team's frame");
            }
            NodeInit::Pending { config: Box::new(cfg), origin, state, from_autopilot: args.init_from_autopilot }
        }
    })
}

/// The team's key (refused absent unless `--insecure`) and the autopilot's.
fn keys(
    args: &Args,
) -> anyhow::Result<(Option<cooploc::protocol::signing::TeamKey>, Option<cooploc::protocol::signing::TeamKey>)> {
    let team_key = match &args.team_key {
        Some(path) => Some(cooploc::protocol::signing::TeamKey::from_file(path).context("--team-key")?),
        None if args.insecure => None,
        None => bail!(
            "no --team-key: the cooperative network would be unauthenticated, and anyone who can reach this node's \
             port could move this vehicle's estimate. Give every node of the team the same key file (--team-key FILE; \
             `cooploc keygen FILE` makes one), or say --insecure to run without"
        ),
    };
    let vehicle_key = match &args.vehicle_key {
        Some(path) => Some(cooploc::protocol::signing::TeamKey::from_file(path).context("--vehicle-key")?),
        None => None,
    };
    Ok((team_key, vehicle_key))
}

/// What the node put on the cooperative network, against the byte budget of its team.
fn print_traffic(
    args: &Args,
    summary: &cooploc::node::runner::NodeSummary,
    e: &cooploc::protocol::wire::EstimateReport,
    (budget_team, budget_dim, encoding): (usize, usize, cooploc::protocol::record::Encoding),
) {
    let st = &summary.stats;
    let tx = &summary.coop_tx;
    let epochs = (st.epochs_applied + st.epochs_partial + st.epochs_skipped) as f64;
    let shape = cooploc::protocol::budget::TeamShape {
        team: budget_team,
        state_dim: budget_dim,
        ranges_per_node: (budget_team.saturating_sub(1)).min(6),
        epoch_hz: epochs / summary.wall_s.max(1e-9),
        encoding,
        signed: args.team_key.is_some(),
        echo_ranges: !args.no_range_echo,
    };
    let budget = cooploc::protocol::budget::epoch_frames(&shape)
        .map(|f| cooploc::protocol::budget::rates(&shape, &f, cooploc::protocol::budget::Medium::Radio).node_bytes_per_s)
        .unwrap_or(f64::NAN);
    println!(
        "node {} coop_tx frames {} frame_bytes {} datagrams {} bytes {} dropped {} rx_noise_bytes {} wall_s {:.1}: {:.0} B/s a copy, {:.0} B/s sent; budget {:.0} B/s a copy at {:.2} epochs/s",
        e.platform,
        tx.frames,
        tx.frame_bytes,
        tx.datagrams,
        tx.bytes,
        tx.dropped,
        summary.coop_noise_bytes,
        summary.wall_s,
        tx.frame_bytes as f64 / summary.wall_s.max(1e-9),
        tx.bytes as f64 / summary.wall_s.max(1e-9),
        budget,
        shape.epoch_hz
    );
}

/// The node's start state from the arguments: a scenario run's (`--init-from-run`), the command
/// line's (`--init-ned` ...), or none (the vehicle gives it).
fn initial_state(
    args: &Args,
    from_run: Option<(u64, u32)>,
    from_cli: bool,
    world: Option<&World>,
) -> anyhow::Result<Option<(Option<TimeUs>, InsState)>> {
    Ok(match (from_run, world) {
        (Some((seed, run)), Some(world)) => Some(
            cooploc::experiment::initial_state(world, seed, run, args.id)
                .map(|(t0, s)| (Some(t0), s))
                .with_context(|| format!("--init-from-run: platform {} is not in the scenario", args.id))?,
        ),
        (Some(_), None) => bail!("--init-from-run needs the --scenario of the run"),
        (None, _) if !from_cli => None,
        (None, _) => {
            let rpy = &args.init_rpy_deg;
            let state = InsState {
                pos_ned_m: Vector3::from_column_slice(&args.init_ned),
                vel_ned_m_s: Vector3::from_column_slice(&args.init_vel_ned),
                att_frd_to_ned: UnitQuaternion::from_euler_angles(rpy[0].to_radians(), rpy[1].to_radians(), rpy[2].to_radians()),
                accel_bias_frd_m_s2: Vector3::zeros(),
                gyro_bias_frd_rad_s: Vector3::zeros(),
                odometer_scale_error: 0.0,
            };
            Some((args.init_time_us.map(TimeUs), state))
        }
    })
}

/// The node's log (`--log`), with its header, the scenario and the vehicle profile attached.
fn open_log(
    args: &Args,
    cfg: &NodeConfig,
    initial: &Option<(Option<TimeUs>, InsState)>,
    origin: Option<GeoOrigin>,
    profile: &VehicleProfile,
) -> anyhow::Result<Option<cooploc::node::runner::SharedRecorder>> {
    Ok(match &args.log {
        Some(path) => {
            let options = RecorderOptions { geo_origin: origin, ..RecorderOptions::default() };
            let mut rec = Recorder::create(path, options).with_context(|| format!("--log {}", path.display()))?;
            let start = match &initial {
                Some((t0, state)) => LogStart::Given { t0: *t0, state: *state },
                None => LogStart::FromVehicle,
            };
            let meta = NodeLogHeader::new(cfg, start, args.init_from_autopilot, origin).to_metadata();
            rec.metadata(&metadata_name(args.id), meta)?;
            if let Some(path) = &args.scenario {
                let toml = std::fs::read(path).with_context(|| format!("reading {}", path.display()))?;
                rec.attachment("scenario.toml", "application/toml", &toml)?;
            }
            rec.attachment(&vehicle_attachment_name(args.id), "application/toml", profile.to_toml().as_bytes())?;
            rec.declare_link(Link::Vehicle(args.id as u8), args.vehicle.clone());
            Some(std::sync::Arc::new(std::sync::Mutex::new(rec)))
        }
        None => None,
    })
}

/// The cooperative link the arguments name: a serial radio, or UDP (multicast or not).
fn coop_spec(args: &Args) -> anyhow::Result<CoopSpec> {
    let coop = match &args.coop_serial {
        Some(text) => CoopSpec::serial(text).map_err(|e| anyhow::anyhow!("--coop-serial {e}"))?,
        None => {
            let on = match args.multicast.as_str() {
                "on" => Some(true),
                // auto: a LAN (IPv4, not loopback) set-up without peers; IPv6 stays unicast
                "auto" if args.coop_bind.is_ipv4() && !args.coop_bind.ip().is_loopback() && args.peers.is_empty() => Some(false),
                _ => None,
            };
            if on.is_some() && !args.coop_bind.is_ipv4() {
                bail!("--multicast: the cooperative socket must be IPv4 for multicast, not --coop-bind {}", args.coop_bind);
            }
            let multicast = on.map(|required| Multicast {
                group: args.multicast_group,
                ttl: args.multicast_ttl,
                interface: args.multicast_interface,
                required,
            });
            CoopSpec::Udp { bind: args.coop_bind, multicast, max_datagram: args.datagram_bytes }
        }
    };
    if args.datagram_bytes > MAX_UDP_PAYLOAD {
        bail!("--datagram-bytes {}: a UDP datagram carries at most {MAX_UDP_PAYLOAD} bytes", args.datagram_bytes);
    }
    if !args.multicast_group.ip().is_multicast() {
        bail!("--multicast-group {}: not a multicast address (224.0.0.0/4)", args.multicast_group);
    }
    if args.multicast_ttl == 0 || args.multicast_ttl > 255 {
        bail!("--multicast-ttl {}: 1..=255", args.multicast_ttl);
    }
    Ok(coop)
}

/// The ranging device on the companion (`--ranges`), its UDP socket bound now.
fn range_source(args: &Args) -> anyhow::Result<Option<RangeSource>> {
    Ok(match &args.ranges {
        None => None,
        Some(url) => Some(if let Some(rest) = url.strip_prefix("udpin:") {
            let addr: SocketAddr = rest.parse().with_context(|| format!("--ranges {url}: expected udpin:HOST:PORT"))?;
            let socket = std::net::UdpSocket::bind(addr).with_context(|| format!("--ranges {url}: binding"))?;
            println!("node {} ranges udp {}", args.id, socket.local_addr()?);
            RangeSource::Udp(std::sync::Arc::new(socket))
        } else if let Some(rest) = url.strip_prefix("serial:") {
            let (path, baud) = rest
                .rsplit_once(':')
                .and_then(|(p, b)| Some((p.to_string(), b.parse::<u32>().ok()?)))
                .with_context(|| format!("--ranges {url}: expected serial:PATH:BAUD"))?;
            RangeSource::Serial { path, baud }
        } else {
            bail!("--ranges {url}: expected udpin:HOST:PORT or serial:PATH:BAUD");
        }),
    })
}

/// The airtime slot of `--airtime-bps` (0 without it): every member computes the same from the
/// team's size, state, encoding and signing.
fn airtime_slot_us(
    args: &Args,
    (team, state_dim, encoding): (usize, usize, cooploc::protocol::record::Encoding),
) -> anyhow::Result<u64> {
    let Some(bps) = args.airtime_bps else { return Ok(0) };
    let shape = cooploc::protocol::budget::TeamShape {
        team,
        state_dim,
        ranges_per_node: 0,
        epoch_hz: 1.0,
        encoding,
        signed: args.team_key.is_some(),
        echo_ranges: false,
    };
    cooploc::protocol::budget::airtime_slot_us(&shape, bps).map_err(|e| anyhow::anyhow!("--airtime-bps: {e}"))
}

/// What the node did, printed when it stops (one line per subject, `node ID subject ...`).
fn print_summary(
    args: &Args,
    summary: &cooploc::node::runner::NodeSummary,
    e: &cooploc::protocol::wire::EstimateReport,
    profile: &VehicleProfile,
    (budget_team, budget_dim, encoding): (usize, usize, cooploc::protocol::record::Encoding),
) {
    if let Some((t0, p)) = &summary.sim_state_init {
        println!("node {} initialised from SIM_STATE: t {} pos_ned_m [{:.4}, {:.4}, {:.4}]", e.platform, t0.0, p[0], p[1], p[2]);
    }
    let st = &summary.stats;
    println!(
        "node {} done: t {} pos_ned_m [{:.4}, {:.4}, {:.4}] yaw_deg {:.5} epochs_applied {} epochs_partial {} epochs_skipped {} dropped_inputs {} vehicle_frames {} vehicle_lost {} vehicle_rejected {} vehicle_other_dialect {} coop_frames {} coop_rejected {} peers {}",
        e.platform,
        e.t.0,
        e.position_ned_m[0],
        e.position_ned_m[1],
        e.position_ned_m[2],
        e.yaw_rad.to_degrees(),
        st.epochs_applied,
        st.epochs_partial,
        st.epochs_skipped,
        st.dropped_inputs(),
        summary.vehicle_frames,
        summary.vehicle_lost,
        summary.vehicle_rejected,
        summary.vehicle_other_dialect,
        summary.coop_frames,
        summary.coop_rejected,
        summary.peers.len()
    );
    println!("node {} stats {:?}", e.platform, st);
    print_traffic(args, summary, e, (budget_team, budget_dim, encoding));
    let pc = &summary.peer_counters;
    println!(
        "node {} peers {} learned {} moved {} expired {} observers_refused {} resends {} resends_limited {}",
        e.platform,
        summary.peers.len(),
        pc.learned,
        pc.moved,
        pc.expired,
        pc.observers_refused,
        st.records_resent,
        st.resends_limited
    );
    println!(
        "node {} vetting records_contradicted {} records_rival {} flagged {:?}{}",
        e.platform,
        st.records_contradicted,
        st.records_rival,
        summary.flagged,
        if summary.flagged.is_empty() { "" } else { " (two different records under one platform id: someone else speaks as it)" }
    );
    if args.team_key.is_some() {
        let c = &summary.coop_signing;
        println!(
            "node {} signing accepted {} unsigned {} bad_signature {} replayed {} stale {} malformed {}",
            e.platform, c.accepted, c.unsigned, c.bad_signature, c.replayed, c.stale, c.malformed
        );
    }
    if let Some(c) = &summary.vehicle_signing {
        println!(
            "node {} vehicle_signing accepted {} unsigned {} bad_signature {} replayed {} stale {} malformed {}",
            e.platform, c.accepted, c.unsigned, c.bad_signature, c.replayed, c.stale, c.malformed
        );
    }
    println!(
        "node {} vehicle imu_rate_hz {} odometry_sent {} odometry_resets {} gps_input_sent {} inputs {:?}",
        e.platform,
        summary.imu_rate_hz.map_or("-".into(), |r| format!("{r:.1}")),
        summary.odometry_sent,
        summary.odometry_resets,
        summary.gps_input_sent,
        summary.inputs
    );
    for r in &summary.rate_requests {
        if r.rate_hz == 0.0 {
            println!("node {} rate request {} back at its default rate: {:?}", e.platform, r.message, r.outcome);
            continue;
        }
        match r.stream_group {
            Some((group, stream_id, sent)) => println!(
                "node {} rate request {} at {} Hz: {:?}; asked instead for ArduPilot's stream group {group} (REQUEST_DATA_STREAM {stream_id}, sent {sent} times), which paces all its messages",
                e.platform, r.message, r.rate_hz, r.outcome
            ),
            None => println!("node {} rate request {} at {} Hz: {:?}", e.platform, r.message, r.rate_hz, r.outcome),
        }
    }
    if let Some(c) = &summary.range_input {
        println!(
            "node {} range_input ranges {} other_lines {} malformed {} bad_peer {} too_long {} off_grid {}",
            e.platform, c.ranges, c.other_lines, c.malformed, c.bad_peer, c.too_long, c.off_grid
        );
    }
    if let Some(h) = &summary.hand_over {
        let p = h.started_at_ned_m;
        println!(
            "node {} hand_over started_at_ned_m [{:.2}, {:.2}, {:.2}] fixes {} fixes_rejected {} losses {} glitches {} returns {} navigating {} source_set {}",
            e.platform,
            p.x,
            p.y,
            p.z,
            h.fixes,
            h.fixes_rejected,
            h.losses,
            h.glitches,
            h.returns,
            h.navigating,
            h.source_set.map_or("not asked or unanswered".into(), |r| format!("{r:?}"))
        );
    }
    if let Some(o) = &summary.origin_offer {
        let state = match o.settled {
            Some((_, true)) if o.sets > 0 => "given (SET_GPS_GLOBAL_ORIGIN), the autopilot reports it",
            Some((_, true)) => "the autopilot's is the team's",
            Some((_, false)) => "the autopilot has its own (kept; positions sent back are in the profile's frame)",
            None if o.gave_up => "given, never taken: the autopilot reports no origin",
            None => "none reported yet",
        };
        println!("node {} origin {state} sets {}", e.platform, o.sets);
    }
    match summary.clock {
        Some((source, offset_us, rtt_us)) => println!(
            "node {} clock {} offset_us {offset_us} rtt_us {} timesync_requests {} timesync_refused {}",
            e.platform,
            match source {
                cooploc::node::inputs::ClockSource::Timesync => "companion (TIMESYNC)",
                cooploc::node::inputs::ClockSource::SystemTime => "autopilot (SYSTEM_TIME)",
            },
            rtt_us.map_or("-".into(), |r| r.to_string()),
            summary.timesync_requests,
            summary.timesync_refused
        ),
        None => println!(
            "node {} clock {} timesync_requests {} timesync_refused {}",
            e.platform,
            match profile.inputs.clock {
                cooploc::node::profile::TeamClock::Vehicle => "vehicle (shared stamps)",
                _ => "none mapped",
            },
            summary.timesync_requests,
            summary.timesync_refused
        ),
    }
}
