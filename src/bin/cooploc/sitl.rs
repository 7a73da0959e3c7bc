//! `cooploc sitl`: arguments validated into a [`SitlConfig`] before any I/O, then the runner.

use std::net::{IpAddr, SocketAddr, ToSocketAddrs};
use std::path::PathBuf;

use anyhow::{Context, bail};
use cooploc::estimation::PlatformId;
use cooploc::node::profile::VehicleProfile;
use cooploc::simulator::{self, Endpoint, Interval, SitlConfig, Speed, StreamDefaults};
use cooploc::sitl::world::World;
use cooploc::time::TimeUs;

#[derive(clap::Args)]
#[command(after_help = "\
Connecting (vehicle N listens on BIND:BASE_PORT+N and streams to every peer it has heard a MAVLink frame from):
  cooploc node --vehicle udpout:127.0.0.1:14541
  mavproxy.py --master=udpout:127.0.0.1:14541
A client that listens instead: --vehicle 1=udpout:127.0.0.1:14550 here, udpin:127.0.0.1:14550 on the client.
Timestamps, HEARTBEAT (1 Hz) and every rate are in simulated time: at --speed 10 the heartbeat comes 10 times a second.
The endpoints are printed one per line at start: `vehicle ID udp HOST:PORT [out HOST:PORT,..]` or `vehicle ID serial PATH BAUD`.")]
pub struct Args {
    #[command(flatten)]
    sim: crate::args::SimRun,
    /// Times real time: 1 = real time, 10 = ten times faster; `max` (or 0) = as fast as possible.
    /// Within 2% of real time the vehicles answer TIMESYNC (a clock of their own: 0.992 runs as
    /// PX4's SIH did), otherwise not.
    #[arg(long, default_value = "1", value_parser = parse_speed)]
    speed: Speed,
    /// Vehicle N listens on UDP port BASE_PORT + N (PX4 style); 0 = an ephemeral port each.
    #[arg(long, default_value_t = 14540)]
    base_port: u16,
    /// Address the vehicles' UDP sockets bind.
    #[arg(long, default_value = "127.0.0.1")]
    bind: IpAddr,
    /// A vehicle's link, repeatable: `ID=udpin:HOST:PORT` (listen there instead of the default),
    /// `ID=udpout:HOST:PORT` (also stream to that address, e.g. a ground station that listens),
    /// `ID=serial:PATH:BAUD`.
    #[arg(long = "vehicle", value_name = "ID=URL", value_parser = parse_vehicle_url)]
    vehicles: Vec<(PlatformId, VehicleUrl)>,
    /// A vehicle on a serial device or pseudo-terminal, repeatable: `ID=PATH:BAUD`.
    #[arg(long = "serial", value_name = "ID=PATH:BAUD", value_parser = parse_serial)]
    serials: Vec<(PlatformId, VehicleUrl)>,
    /// Hold the simulated clock at zero until every vehicle has a peer.
    #[arg(long)]
    wait_for_peers: bool,
    /// SIM_STATE (truth) rate, Hz; 0 disables it.
    #[arg(long, default_value_t = 10.0)]
    sim_state_hz: f64,
    /// Longitude of the local NED origin for SIM_STATE, deg (its latitude is the scenario's).
    #[arg(long, default_value_t = 0.0, allow_negative_numbers = true)]
    origin_lon_deg: f64,
    /// Probability that a frame a vehicle sends is lost (a lossy radio; seeded by --seed, --run
    /// and the platform, so a run is repeatable).
    #[arg(long, default_value_t = 0.0)]
    link_loss: f64,
    /// Behave as this autopilot: its message set, units, rates, time stamps and quirks, and its
    /// acceptance rules for the ODOMETRY the node sends back (ardupilot, px4 or cooploc).
    #[arg(long, default_value = "cooploc")]
    autopilot: simulator::Autopilot,
    /// A vehicle profile (sitl/vehicles/*.toml) whose vehicle part (sensors, initial
    /// uncertainty, filter, latitude, gravity, origin) replaces the scenario's: the vehicles the
    /// nodes will be told they run on.
    #[arg(long)]
    vehicle_config: Option<PathBuf>,
    /// A stream's rate at boot, repeatable: `MESSAGE=HZ` (RAW_IMU, HIGHRES_IMU, WHEEL_DISTANCE,
    /// ODOMETRY, SYSTEM_TIME, SIM_STATE), as an autopilot's stream-rate parameters set it;
    /// without it ArduPilot streams its sensors at 1 Hz and PX4 HIGHRES_IMU at 50 Hz until asked.
    #[arg(long = "stream-rate", value_name = "MESSAGE=HZ", value_parser = parse_stream_rate)]
    stream_rates: Vec<(u32, f64)>,
    /// The autopilots had a GNSS fix before GNSS was lost, and keep its Unix time: ArduPilot's
    /// SYSTEM_TIME then carries it. Without it ArduPilot's SYSTEM_TIME says 0, as the real
    /// firmware without GNSS does (PX4's carries Unix time either way).
    #[arg(long)]
    gnss_time: bool,
    /// With --gnss-time: the autopilots' GNSS fix goes at this simulated time (s): GPS_RAW_INT
    /// says no fix from then on, as on the real firmware after SIM_GPS1_ENABLE 0 (the hand-over
    /// start of `cooploc node --init-from-autopilot`)
    #[arg(long, requires = "gnss_time")]
    gnss_lost_at_s: Option<f64>,
    /// With --gnss-lost-at-s: the fix comes back at this simulated time (s), after the loss (the
    /// hand-back)
    #[arg(long, requires = "gnss_lost_at_s")]
    gnss_back_at_s: Option<f64>,
    /// With --gnss-lost-at-s: no loss but a glitch, from then to --gnss-back-at-s: the fix stays
    /// 3D and its position is this many metres north of the truth (ArduPilot SITL's
    /// SIM_GPS1_GLTCH_X); the ArduPilot personality's EKF flags it and resets to it as the real
    /// EKF3 did
    #[arg(long, requires = "gnss_lost_at_s")]
    gnss_glitch_m: Option<f64>,
}

pub(crate) fn parse_stream_rate(s: &str) -> Result<(u32, f64), String> {
    let (name, hz) = s.split_once('=').ok_or_else(|| format!("{s:?} is not MESSAGE=HZ"))?;
    let id = match name {
        "RAW_IMU" => 27,
        "HIGHRES_IMU" => 105,
        "WHEEL_DISTANCE" => 9000,
        "ODOMETRY" => 331,
        "SYSTEM_TIME" => 2,
        "SIM_STATE" => 108,
        _ => return Err(format!("{name:?}: one of RAW_IMU, HIGHRES_IMU, WHEEL_DISTANCE, ODOMETRY, SYSTEM_TIME, SIM_STATE")),
    };
    let hz: f64 = hz.parse().map_err(|_| format!("{hz:?} is not a rate in Hz"))?;
    if !(hz.is_finite() && hz > 0.0 && hz <= 10_000.0) {
        return Err(format!("{hz} Hz: must be in (0, 10000]"));
    }
    Ok((id, hz))
}

#[derive(Debug, Clone, PartialEq)]
enum VehicleUrl {
    UdpIn(SocketAddr),
    UdpOut(SocketAddr),
    Serial { path: String, baud: u32 },
}

fn parse_speed(s: &str) -> Result<Speed, String> {
    if s.eq_ignore_ascii_case("max") {
        return Ok(Speed::Max);
    }
    match s.parse::<f64>() {
        Ok(0.0) => Ok(Speed::Max),
        Ok(v) if v.is_finite() && v > 0.0 => Ok(Speed::Factor(v)),
        _ => Err(format!("expected a positive number or `max`, got {s:?}")),
    }
}

fn parse_id(s: &str) -> Result<PlatformId, String> {
    s.parse::<PlatformId>().map_err(|_| format!("platform id {s:?} is not a number in 0..=65535"))
}

fn parse_addr(s: &str) -> Result<SocketAddr, String> {
    s.to_socket_addrs()
        .map_err(|e| format!("{s:?} is not HOST:PORT ({e})"))?
        .next()
        .ok_or_else(|| format!("{s:?} resolves to no address"))
}

fn parse_serial_spec(s: &str) -> Result<VehicleUrl, String> {
    let (path, baud) = s.rsplit_once(':').ok_or_else(|| format!("{s:?} is not PATH:BAUD"))?;
    let baud: u32 =
        baud.parse().ok().filter(|&b| b > 0).ok_or_else(|| format!("baud rate {baud:?} is not a positive integer"))?;
    if path.is_empty() {
        return Err(format!("{s:?} has no device path"));
    }
    Ok(VehicleUrl::Serial { path: path.to_string(), baud })
}

fn parse_vehicle_url(s: &str) -> Result<(PlatformId, VehicleUrl), String> {
    let (id, url) = s.split_once('=').ok_or_else(|| format!("{s:?} is not ID=URL"))?;
    let id = parse_id(id)?;
    let url = if let Some(a) = url.strip_prefix("udpin:") {
        VehicleUrl::UdpIn(parse_addr(a)?)
    } else if let Some(a) = url.strip_prefix("udpout:") {
        VehicleUrl::UdpOut(parse_addr(a)?)
    } else if let Some(a) = url.strip_prefix("serial:") {
        parse_serial_spec(a)?
    } else {
        return Err(format!("{url:?}: expected udpin:HOST:PORT, udpout:HOST:PORT or serial:PATH:BAUD"));
    };
    Ok((id, url))
}

fn parse_serial(s: &str) -> Result<(PlatformId, VehicleUrl), String> {
    let (id, spec) = s.split_once('=').ok_or_else(|| format!("{s:?} is not ID=PATH:BAUD"))?;
    Ok((parse_id(id)?, parse_serial_spec(spec)?))
}

/// Everything checked, nothing opened.
struct Validated {
    world: World,
    config: SitlConfig,
}

fn validate(args: Args) -> anyhow::Result<Validated> {
    let mut scenario = crate::args::scenario_or_paper(args.sim.scenario.as_deref())?;
    let profile = match &args.vehicle_config {
        Some(path) => Some(VehicleProfile::from_path(path)?),
        None => None,
    };
    if let Some(p) = &profile {
        scenario.put_vehicle(&p.spec()).with_context(|| format!("the scenario with the vehicle of {}", p.name))?;
    }
    let world = World::new(&scenario)?;
    let ids = world.platform_ids();
    let schedule = match args.sim.schedule {
        Some(s) => {
            scenario.range_epochs(&s).context("--schedule")?;
            s
        }
        None => scenario.ranging.schedules.first().map(|s| s.name.clone()).context("the scenario has no ranging schedule")?,
    };
    if let Some(&bad) = ids.iter().find(|&&id| id == 0 || id > 255) {
        bail!("platform id {bad} cannot be a MAVLink system id (1..=255)");
    }
    let mut endpoints = simulator::default_endpoints(&ids, args.bind, args.base_port).context("--base-port")?;
    let mut udpin_set: Vec<PlatformId> = Vec::new();
    for (flag, (id, url)) in args.vehicles.iter().map(|v| ("--vehicle", v)).chain(args.serials.iter().map(|v| ("--serial", v))) {
        let Some((_, endpoint)) = endpoints.iter_mut().find(|(p, _)| p == id) else {
            bail!("{flag}: platform {id} is not in the scenario (it has {ids:?})");
        };
        match (url, &mut *endpoint) {
            (VehicleUrl::Serial { path, baud }, Endpoint::Udp { targets, .. })
                if targets.is_empty() && !udpin_set.contains(id) =>
            {
                *endpoint = Endpoint::Serial { path: path.clone(), baud: *baud };
            }
            (VehicleUrl::UdpIn(addr), Endpoint::Udp { bind, .. }) if !udpin_set.contains(id) => {
                *bind = *addr;
                udpin_set.push(*id);
            }
            (VehicleUrl::UdpOut(addr), Endpoint::Udp { targets, .. }) if !targets.contains(addr) => targets.push(*addr),
            _ => bail!("{flag}: platform {id} given conflicting links (one serial link, or one udpin and any udpout)"),
        }
    }
    let sim_state = if args.sim_state_hz == 0.0 {
        Interval::Disabled
    } else if args.sim_state_hz.is_finite() && args.sim_state_hz > 0.0 && args.sim_state_hz <= 1000.0 {
        Interval::Every((1e6 / args.sim_state_hz).round() as u64)
    } else {
        bail!("--sim-state-hz must be in [0, 1000], got {}", args.sim_state_hz);
    };
    if !(args.origin_lon_deg.is_finite() && (-180.0..=180.0).contains(&args.origin_lon_deg)) {
        bail!("--origin-lon-deg must be in [-180, 180], got {}", args.origin_lon_deg);
    }
    let config = SitlConfig {
        schedule,
        seed: args.sim.seed,
        run: args.sim.run,
        speed: args.speed,
        endpoints,
        wait_for_peers: args.wait_for_peers,
        streams: StreamDefaults { sim_state, ..StreamDefaults::default() },
        origin_lon_deg: args.origin_lon_deg,
        link_loss: args.link_loss,
        autopilot: args.autopilot,
        origin: profile.as_ref().and_then(VehicleProfile::geo_origin),
        stream_rates: args.stream_rates.clone(),
        gnss_time: args.gnss_time,
        gnss_lost_at: match args.gnss_lost_at_s {
            Some(s) if s.is_finite() && s >= 0.0 => Some(TimeUs::from_secs_f64(s)),
            Some(s) => anyhow::bail!("--gnss-lost-at-s: a time in seconds, at least 0, got {s}"),
            None => None,
        },
        gnss_back_at: match (args.gnss_back_at_s, args.gnss_lost_at_s) {
            (Some(b), Some(l)) if b.is_finite() && b > l => Some(TimeUs::from_secs_f64(b)),
            (Some(b), _) => anyhow::bail!("--gnss-back-at-s: a time in seconds after --gnss-lost-at-s, got {b}"),
            (None, _) => None,
        },
        gnss_glitch_m: match args.gnss_glitch_m {
            Some(m) if m.is_finite() && m.abs() <= 10_000.0 => Some(m),
            Some(m) => anyhow::bail!("--gnss-glitch-m: an offset in metres, at most 10 km, got {m}"),
            None => None,
        },
    };
    Ok(Validated { world, config })
}

pub fn run(args: Args) -> anyhow::Result<()> {
    let scenario_path = crate::args::scenario_source(args.sim.scenario.as_deref());
    let Validated { world, config } = validate(args)?;
    let runtime = tokio::runtime::Builder::new_multi_thread().enable_all().build().context("starting the tokio runtime")?;
    runtime.block_on(async move {
        let name = world.scenario().name.clone();
        let end = world.end();
        let (schedule, seed, run, speed) = (config.schedule.clone(), config.seed, config.run, config.speed);
        let sim = simulator::Simulator::bind(world, config).await?;
        println!(
            "cooploc sitl: scenario {name} ({}), schedule {schedule}, seed {seed}, run {run}, speed {}, {} s",
            scenario_path,
            match speed {
                Speed::Max => "max".to_string(),
                Speed::Factor(f) => format!("{f}"),
            },
            end.as_secs_f64()
        );
        for (id, endpoint) in sim.endpoints() {
            println!("vehicle {id} {endpoint}");
        }
        let report = sim.run(crate::signal::shutdown_signal()).await?;
        println!("stopped: {:?} at simulated {}", report.reason, report.sim_time);
        for v in &report.vehicles {
            let c = &v.counters;
            println!(
                "vehicle {} sent {} frames (heartbeat {}, highres_imu {}, odometry {}, sim_state {}, range {}), \
                 {} writes, {} unrouted; received {} frames, {} malformed, {} ignored; commands {} accepted, {} rejected, {} unsupported",
                v.platform,
                c.frames_sent,
                c.heartbeat_sent,
                c.highres_imu_sent,
                c.odometry_sent,
                c.sim_state_sent,
                c.range_sent,
                v.link.writes,
                v.link.unrouted,
                c.frames_received,
                c.malformed,
                c.ignored,
                c.commands_accepted,
                c.commands_rejected,
                c.commands_unsupported
            );
            if c.raw_imu_sent + c.wheel_distance_sent + c.system_time_sent > 0 {
                println!(
                    "vehicle {} also sent raw_imu {}, wheel_distance {}, system_time {}",
                    v.platform, c.raw_imu_sent, c.wheel_distance_sent, c.system_time_sent
                );
            }
            if c.origins_set > 0 {
                println!("vehicle {} origin set by SET_GPS_GLOBAL_ORIGIN", v.platform);
            }
            for set in &c.source_sets {
                println!("vehicle {} EKF source set {set} (MAV_CMD_SET_EKF_SOURCE_SET)", v.platform);
            }
            if let (Some(first), Some(last)) = (c.first_odometry_error_mm, c.last_odometry_error_mm) {
                println!(
                    "vehicle {} odometry first {:.3} last {:.3} m from the truth",
                    v.platform,
                    first as f64 * 1e-3,
                    last as f64 * 1e-3
                );
            }
            let k = &v.checker;
            if k.gps_input_accepted + k.gps_input_ignored > 0 {
                println!("vehicle {} gps_input_check accepted {} ignored {}", v.platform, k.gps_input_accepted, k.gps_input_ignored);
            }
            if k.accepted + k.ignored.values().sum::<u64>() > 0 {
                println!(
                    "vehicle {} odometry_check accepted {} ignored {} rate_hz {} without_covariance {} ahead_of_clock {} behind_clock {} reasons {:?}",
                    v.platform,
                    k.accepted,
                    k.ignored.values().sum::<u64>(),
                    k.rate_hz().map_or("-".into(), |r| format!("{r:.2}")),
                    k.without_covariance,
                    k.ahead_of_clock,
                    k.behind_clock,
                    k.ignored
                );
            }
        }
        anyhow::Ok(())
    })
}
