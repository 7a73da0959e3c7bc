//! `cooploc gcs`: arguments validated into a [`GcsConfig`] and [`GcsLinks`] before any I/O, then
//! the runner.

use std::net::{SocketAddr, ToSocketAddrs};
use std::time::Duration;

use anyhow::{Context, bail};
use cooploc::estimation::PlatformId;
use cooploc::gcs::runner::{GcsLinks, run};
use cooploc::gcs::state::GcsConfig;
use cooploc::protocol::wire::GeoOrigin;

#[derive(clap::Args)]
#[command(after_help = "\
Prints, once bound: `gcs coop udp ADDR`, `gcs http http://ADDR/`, `gcs foxglove ws://ADDR`.
A node sends the ground station everything it sends its peers once it has heard from it: give the
nodes' cooperative addresses with --peer (the ground station's heartbeat introduces it), or give
the nodes the ground station's address as a --peer.
Truth of simulated vehicles: --vehicle 1=udpout:127.0.0.1:14541 (SIM_STATE of `cooploc sitl`).
With `cooploc sitl --wait-for-peers`, start the ground station after the nodes: its vehicle links count as peers.")]
pub struct Args {
    /// Record what the ground station receives (raw frames, truth) to this MCAP file.
    #[arg(long)]
    log: Option<std::path::PathBuf>,
    /// Local address of the cooperative-network socket.
    #[arg(long, default_value = "127.0.0.1:0")]
    coop: SocketAddr,
    /// A node's cooperative address, repeatable (more are learned from their traffic).
    #[arg(long = "peer", value_name = "ADDR", value_parser = parse_addr)]
    peers: Vec<SocketAddr>,
    /// A simulated vehicle's MAVLink link for truth (SIM_STATE), repeatable: ID=URL, e.g.
    /// 1=udpout:127.0.0.1:14541.
    #[arg(long = "vehicle", value_name = "ID=URL", value_parser = parse_vehicle)]
    vehicles: Vec<(PlatformId, String)>,
    /// Web page and JSON API address (port 0: ephemeral).
    #[arg(long, default_value = "127.0.0.1:8080", value_parser = parse_addr)]
    http: SocketAddr,
    /// Foxglove live WebSocket address (port 0: ephemeral).
    #[arg(long, default_value = "127.0.0.1:8765", value_parser = parse_addr)]
    foxglove: SocketAddr,
    /// Do not start the Foxglove server.
    #[arg(long)]
    no_foxglove: bool,
    /// Latitude of the team's NED origin, deg (default: the paper scenario's).
    #[arg(long, default_value_t = 34.7, allow_negative_numbers = true)]
    origin_lat_deg: f64,
    /// Longitude of the NED origin, deg (as `cooploc sitl --origin-lon-deg`).
    #[arg(long, default_value_t = 0.0, allow_negative_numbers = true)]
    origin_lon_deg: f64,
    /// Altitude of the NED origin, m.
    #[arg(long, default_value_t = 0.0, allow_negative_numbers = true)]
    origin_alt_m: f64,
    /// Estimates kept per vehicle.
    #[arg(long, default_value_t = 4096)]
    history: usize,
    /// Stop when nothing has been heard for this long (s, after the first frame); 0: run until Ctrl-C.
    #[arg(long, default_value_t = 0.0)]
    idle_exit_s: f64,
    /// The team's signing key (the nodes' --team-key file): only cooperative frames signed with
    /// it are read, and the ground station's heartbeat is signed with it. The ground station
    /// refuses to start without it, unless told --insecure.
    #[arg(long, value_name = "FILE")]
    team_key: Option<std::path::PathBuf>,
    /// Watch an unauthenticated cooperative network (no --team-key): anyone who can reach the
    /// ground station's port can show it vehicles, and its estimate requests go out unsigned.
    #[arg(long, conflicts_with = "team_key")]
    insecure: bool,
    /// Most vehicles shown (new system ids beyond it are refused and counted).
    #[arg(long, default_value_t = 64)]
    max_vehicles: usize,
    /// Payload bytes per second the shared cooperative link carries, all nodes together (e.g.
    /// 5400 for a SiK radio at 64 kbit/s; `cooploc budget` lists links): the health view shows
    /// each node's bytes against its share. Without it only the bytes are shown.
    #[arg(long, value_name = "BYTES_PER_S")]
    link_capacity: Option<f64>,
}

fn parse_addr(s: &str) -> Result<SocketAddr, String> {
    s.to_socket_addrs()
        .map_err(|e| format!("{s:?} is not HOST:PORT ({e})"))?
        .next()
        .ok_or_else(|| format!("{s:?} resolves to no address"))
}

fn parse_vehicle(s: &str) -> Result<(PlatformId, String), String> {
    let (id, url) = s.split_once('=').ok_or_else(|| format!("{s:?} is not ID=URL"))?;
    let id: PlatformId = id.parse().map_err(|_| format!("platform id {id:?} is not a number"))?;
    if id == 0 || id > 255 {
        return Err(format!("platform id {id}: a MAVLink system id is 1..=255"));
    }
    let known = ["udpin:", "udpout:", "udpbcast:", "tcpin:", "tcpout:", "serial:"];
    if !known.iter().any(|p| url.starts_with(p)) {
        return Err(format!("{url:?}: expected a MAVLink URL ({})", known.join(", ")));
    }
    Ok((id, url.to_string()))
}

struct Validated {
    config: GcsConfig,
    links: GcsLinks,
}

fn validate(args: Args) -> anyhow::Result<Validated> {
    if !(args.origin_lat_deg.is_finite() && (-89.0..=89.0).contains(&args.origin_lat_deg)) {
        bail!("--origin-lat-deg must be in [-89, 89], got {}", args.origin_lat_deg);
    }
    if !(args.origin_lon_deg.is_finite() && (-180.0..=180.0).contains(&args.origin_lon_deg)) {
        bail!("--origin-lon-deg must be in [-180, 180], got {}", args.origin_lon_deg);
    }
    if !args.origin_alt_m.is_finite() {
        bail!("--origin-alt-m must be finite");
    }
    if !args.idle_exit_s.is_finite() || args.idle_exit_s < 0.0 {
        bail!("--idle-exit-s {}: must be a non-negative number of seconds", args.idle_exit_s);
    }
    if args.history == 0 {
        bail!("--history must be at least 1");
    }
    let mut ids: Vec<PlatformId> = args.vehicles.iter().map(|(id, _)| *id).collect();
    ids.sort_unstable();
    if let Some(w) = ids.windows(2).find(|w| w[0] == w[1]) {
        bail!("--vehicle: platform {} given twice", w[0]);
    }
    if args.max_vehicles == 0 || args.max_vehicles > 255 {
        bail!("--max-vehicles {}: must be 1..=255 (MAVLink system ids)", args.max_vehicles);
    }
    if ids.len() > args.max_vehicles {
        bail!("{} --vehicle links but --max-vehicles {}", ids.len(), args.max_vehicles);
    }
    if let Some(c) = args.link_capacity
        && !(c.is_finite() && c > 0.0)
    {
        bail!("--link-capacity {c}: must be a positive number of bytes per second");
    }
    let team_key = match &args.team_key {
        Some(path) => Some(cooploc::protocol::signing::TeamKey::from_file(path).context("--team-key")?),
        None if args.insecure => None,
        None => bail!(
            "no --team-key: the ground station would show whatever anyone sends to its port as the team. Give it the \
             nodes' key file (--team-key FILE), or say --insecure to watch an unauthenticated network"
        ),
    };
    let config = GcsConfig {
        origin: GeoOrigin { lat_deg: args.origin_lat_deg, lon_deg: args.origin_lon_deg, alt_m: args.origin_alt_m },
        vehicles: ids,
        estimate_history: args.history,
        team_key,
        max_vehicles: args.max_vehicles,
        link_capacity_bytes_per_s: args.link_capacity,
        ..GcsConfig::default()
    };
    let links = GcsLinks {
        coop_bind: args.coop,
        peers: args.peers,
        vehicles: args.vehicles,
        http: args.http,
        foxglove: (!args.no_foxglove).then_some(args.foxglove),
        idle_exit: (args.idle_exit_s > 0.0).then(|| Duration::from_secs_f64(args.idle_exit_s)),
    };
    Ok(Validated { config, links })
}

pub fn run_cmd(args: Args) -> anyhow::Result<()> {
    let log = args.log.clone();
    let insecure = args.insecure;
    let Validated { config, links } = validate(args)?;
    let recorder = match &log {
        Some(path) => {
            let options = cooploc::recording::RecorderOptions { geo_origin: Some(config.origin), ..Default::default() };
            let rec = cooploc::recording::Recorder::create(path, options).with_context(|| format!("--log {}", path.display()))?;
            Some(std::sync::Arc::new(std::sync::Mutex::new(rec)))
        }
        None => None,
    };
    let run_recorder = recorder.clone();
    let rt = tokio::runtime::Builder::new_multi_thread().worker_threads(2).enable_all().build().context("starting tokio")?;
    let summary = rt.block_on(async move {
        let (tx, rx) = tokio::sync::oneshot::channel::<cooploc::gcs::runner::Bound>();
        let announce = tokio::spawn(async move {
            if let Ok(b) = rx.await {
                println!("gcs coop udp {}", b.coop);
                if insecure {
                    println!("gcs cooperative network UNAUTHENTICATED (--insecure): every frame is taken as it comes");
                }
                println!("gcs http http://{}/", b.http);
                if let Some(f) = b.foxglove {
                    println!("gcs foxglove ws://{f}");
                }
            }
        });
        let mut sinks: Vec<Box<dyn cooploc::gcs::GcsSink>> = Vec::new();
        if let Some(r) = &run_recorder {
            sinks.push(Box::new(cooploc::gcs::RecorderSink::new(r.clone())));
        }
        let summary = run(config, links, sinks, tx, crate::signal::shutdown_signal()).await;
        let _ = announce.await;
        summary
    })?;
    if let Some(rec) = recorder
        && let Ok(rec) = std::sync::Arc::try_unwrap(rec)
        && let Ok(rec) = rec.into_inner()
    {
        let stats = rec.finish()?;
        println!("gcs log {} messages", stats.messages_written);
    }
    let c = &summary.counters;
    println!(
        "gcs done: vehicles {:?} estimates {} truth_samples {} datagrams {} frames {} bad_datagrams {} rejected {} ignored {} peers {}",
        summary.vehicles,
        summary.estimates,
        summary.truth_samples,
        c.datagrams,
        c.frames,
        c.bad_datagrams,
        c.rejected,
        c.ignored,
        summary.peers.len()
    );
    println!(
        "gcs bounds: unauthenticated {} vehicles_refused {} sources_refused {} peers_refused {}",
        c.unauthenticated, c.vehicles_refused, c.sources_refused, c.peers_refused
    );
    Ok(())
}
