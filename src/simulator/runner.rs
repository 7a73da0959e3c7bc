//! The tokio runner of `cooploc sitl` (see the module above): the links, the clock, the
//! vehicles' sans-io cores driven in simulated time.

use std::future::Future;
use std::net::SocketAddr;
use std::sync::Arc;
use std::time::Duration;

use mavlink_core::MavHeader;
use tokio::io::AsyncWriteExt;
use tokio::net::UdpSocket;
use tokio::sync::mpsc;
use tokio::task::JoinHandle;
use tokio::time::Instant;

use super::personality::{Autopilot, Checker};
use super::vehicle::{Destination, Outgoing, StreamDefaults, VehicleConfig, VehicleCore, VehicleCounters};
use crate::estimation::PlatformId;
use crate::protocol::MavMessage;
use crate::protocol::wire::GeoOrigin;
use crate::sitl::{ScenarioError, SimEvent, World};
use crate::time::TimeUs;

/// How far from real time (as a fraction) the vehicles' clocks still answer TIMESYNC: within
/// it they are real clocks at a rate of their own (`cooploc sitl --speed 0.992` runs as PX4's SIH
/// did), beyond it a simulated time no companion clock follows.
pub const NEAR_REAL_TIME: f64 = 0.02;
/// Most heard UDP peers a vehicle streams to (the least recently heard is dropped first).
pub const MAX_UDP_PEERS: usize = 8;
/// A heard UDP peer silent for this long (wall time) is no longer streamed to.
pub const UDP_PEER_TIMEOUT: Duration = Duration::from_secs(30);

/// How fast simulated time runs.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Speed {
    /// This many times real time (1 = real time).
    Factor(f64),
    /// As fast as the links take it.
    Max,
}

/// One vehicle's link.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Endpoint {
    /// Bind `bind`; stream to `targets` and to the peers heard.
    Udp { bind: SocketAddr, targets: Vec<SocketAddr> },
    /// A serial device or pseudo-terminal.
    Serial { path: String, baud: u32 },
}

/// A link as it was opened (real port numbers).
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum BoundEndpoint {
    Udp { local: SocketAddr, targets: Vec<SocketAddr> },
    Serial { path: String, baud: u32 },
}

impl std::fmt::Display for BoundEndpoint {
    /// `udp 127.0.0.1:14541`, `udp 127.0.0.1:40000 out 127.0.0.1:14550,...`, `serial /dev/pts/3 57600`.
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            BoundEndpoint::Udp { local, targets } => {
                write!(f, "udp {local}")?;
                if !targets.is_empty() {
                    let t: Vec<String> = targets.iter().map(|a| a.to_string()).collect();
                    write!(f, " out {}", t.join(","))?;
                }
                Ok(())
            }
            BoundEndpoint::Serial { path, baud } => write!(f, "serial {path} {baud}"),
        }
    }
}

/// Everything a simulator run needs besides the world.
#[derive(Debug, Clone, PartialEq)]
pub struct SitlConfig {
    pub schedule: String,
    pub seed: u64,
    pub run: u32,
    pub speed: Speed,
    /// One link per platform of the world.
    pub endpoints: Vec<(PlatformId, Endpoint)>,
    /// Hold the clock at zero until every vehicle has a peer (a target, a serial link, or a
    /// heard frame). Commands received meanwhile apply from the start.
    pub wait_for_peers: bool,
    pub streams: StreamDefaults,
    /// Longitude of the NED origin, deg (its latitude is the scenario's).
    pub origin_lon_deg: f64,
    /// Probability that a frame a vehicle sends is lost on its link (a lossy radio), drawn from
    /// a generator seeded by the run's seed and the platform; 0 for a perfect link.
    pub link_loss: f64,
    /// Which autopilot every vehicle behaves as.
    pub autopilot: Autopilot,
    /// The NED origin (a vehicle profile's); None: the scenario's latitude and `origin_lon_deg`.
    pub origin: Option<GeoOrigin>,
    /// Stream rates set at boot, `(message id, Hz)`, for every vehicle (see
    /// [`VehicleCore::preset_rate`]).
    pub stream_rates: Vec<(u32, f64)>,
    /// The autopilots had a GNSS fix before GNSS was lost: ArduPilot's SYSTEM_TIME carries Unix
    /// time (without it, 0, as on the real firmware without GNSS; PX4's always does).
    pub gnss_time: bool,
    /// With `gnss_time`: the GNSS fix goes at this simulated time (the autopilots keep their Unix
    /// time and origin, and report no fix).
    pub gnss_lost_at: Option<TimeUs>,
    /// After `gnss_lost_at`: the fix comes back at this simulated time.
    pub gnss_back_at: Option<TimeUs>,
    /// From `gnss_lost_at` to `gnss_back_at`: no loss but a glitch, the fix's position this far
    /// north of the truth, m.
    pub gnss_glitch_m: Option<f64>,
}

/// What can stop a simulator.
#[derive(Debug, thiserror::Error)]
pub enum SimError {
    #[error(transparent)]
    Scenario(#[from] ScenarioError),
    #[error("{0}")]
    Config(String),
    #[error("vehicle {platform}: cannot open {what}: {source}")]
    Open { platform: PlatformId, what: String, source: std::io::Error },
}

/// Why a run ended.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum StopReason {
    EndOfScenario,
    Shutdown,
}

/// Link counters of one vehicle.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct LinkCounters {
    /// Datagrams or serial writes that went out (one frame may go to several peers).
    pub writes: u64,
    pub write_errors: u64,
    /// Frames produced while the vehicle had no peer.
    pub unrouted: u64,
    /// Frames dropped because the serial writer was behind.
    pub dropped: u64,
    /// Frames dropped on purpose (`link_loss`).
    pub lost: u64,
    pub datagrams_received: u64,
}

/// One vehicle at the end of a run.
#[derive(Debug, Clone, PartialEq)]
pub struct VehicleReport {
    pub platform: PlatformId,
    pub endpoint: BoundEndpoint,
    pub counters: VehicleCounters,
    pub link: LinkCounters,
    /// What the vehicle's autopilot made of the ODOMETRY it received.
    pub checker: Checker,
}

/// The end of a run.
#[derive(Debug, Clone, PartialEq)]
pub struct SimReport {
    pub reason: StopReason,
    /// Simulated time reached.
    pub sim_time: TimeUs,
    pub vehicles: Vec<VehicleReport>,
}

/// The configuration of platform `id`'s vehicle core in `world`.
pub fn vehicle_config(
    world: &World,
    id: PlatformId,
    schedule: &str,
    defaults: StreamDefaults,
    origin: GeoOrigin,
    autopilot: Autopilot,
) -> VehicleConfig {
    let scenario = world.scenario();
    VehicleConfig {
        platform: id,
        defaults,
        origin,
        gravity_m_s2: scenario.gravity_m_s2,
        odometer_sigma_m_s: scenario.sensors.odometer_sigma_m_s,
        imu_period_us: scenario.imu_period_us(),
        // a wheeled robot's odometer stream is its wheels
        odometer_period_us: match (world.platform_model(id), scenario.wheels) {
            (crate::sitl::scenario::PlatformModel::Planar, Some(w)) => TimeUs::from_secs_f64(1.0 / w.rate_hz).0,
            _ => TimeUs::from_secs_f64(1.0 / scenario.sensors.odometer_rate_hz).0,
        },
        range_period_us: scenario
            .ranging
            .schedules
            .iter()
            .find(|s| s.name == schedule)
            .and_then(|s| s.every_s)
            .map(|p| TimeUs::from_secs_f64(p).0),
        autopilot,
        wheel_track_m: match world.platform_model(id) {
            crate::sitl::scenario::PlatformModel::Planar => scenario.wheels.map(|w| w.track_m),
            crate::sitl::scenario::PlatformModel::Ins => None,
        },
        // ArduPilot has Unix time only from a GNSS fix ([`SitlConfig::gnss_time`])
        unix_time: autopilot != Autopilot::ArduPilot,
        // the autopilots have GNSS only when told (`--gnss-time`); the simulator's own vehicles
        // report none of it
        gnss: autopilot == Autopilot::Cooploc,
        gnss_lost_at: None,
        gnss_back_at: None,
        gnss_glitch_m: None,
    }
}

/// Default endpoints: every platform on UDP `bind_ip:base_port + id` (port 0: ephemeral).
pub fn default_endpoints(
    ids: &[PlatformId],
    bind_ip: std::net::IpAddr,
    base_port: u16,
) -> Result<Vec<(PlatformId, Endpoint)>, SimError> {
    ids.iter()
        .map(|&id| {
            let port = if base_port == 0 {
                0
            } else {
                u16::try_from(u32::from(base_port) + u32::from(id))
                    .map_err(|_| SimError::Config(format!("--base-port {base_port} + platform id {id} is beyond port 65535")))?
            };
            Ok((id, Endpoint::Udp { bind: SocketAddr::new(bind_ip, port), targets: Vec::new() }))
        })
        .collect()
}

enum Inbound {
    Datagram { vehicle: usize, from: SocketAddr, bytes: Vec<u8> },
    Message { vehicle: usize, header: MavHeader, message: Box<MavMessage> },
    Malformed { vehicle: usize },
    LinkClosed { vehicle: usize, reason: String },
}

struct UdpLink {
    socket: Arc<UdpSocket>,
    targets: Vec<SocketAddr>,
    heard: Vec<(SocketAddr, std::time::Instant)>,
    /// Stream frames not sent yet: several frames go in one datagram, as PX4 does, until
    /// [`BATCH_BYTES`] or until the simulator waits (so batching adds no latency).
    batch: Vec<u8>,
}

/// Most bytes of stream frames in one datagram (below an Ethernet MTU).
const BATCH_BYTES: usize = 1200;

enum Link {
    Udp(UdpLink),
    Serial(mpsc::Sender<Vec<u8>>),
}

struct VehicleIo {
    platform: PlatformId,
    endpoint: BoundEndpoint,
    link: Link,
    counters: LinkCounters,
    /// The simulated radio's loss: probability and its generator.
    loss: Option<(f64, rand_chacha::ChaCha8Rng)>,
}

impl VehicleIo {
    fn connected(&self) -> bool {
        match &self.link {
            Link::Udp(u) => !u.targets.is_empty() || !u.heard.is_empty(),
            Link::Serial(_) => true,
        }
    }

    fn hear(&mut self, from: SocketAddr) {
        let Link::Udp(u) = &mut self.link else { return };
        let now = std::time::Instant::now();
        if let Some(p) = u.heard.iter_mut().find(|(a, _)| *a == from) {
            p.1 = now;
            return;
        }
        if u.targets.contains(&from) {
            return;
        }
        if u.heard.len() >= MAX_UDP_PEERS {
            let oldest = u.heard.iter().enumerate().min_by_key(|(_, (_, t))| *t).map(|(i, _)| i).unwrap_or(0);
            let (gone, _) = u.heard.remove(oldest);
            tracing::info!(platform = self.platform, peer = %gone, "peer dropped (too many peers)");
        }
        tracing::info!(platform = self.platform, peer = %from, "new peer");
        u.heard.push((from, now));
    }

    /// Sends the batched stream frames to every peer.
    async fn send_batch(&mut self) {
        let Link::Udp(u) = &mut self.link else { return };
        if u.batch.is_empty() {
            return;
        }
        for addr in u.targets.iter().chain(u.heard.iter().map(|(a, _)| a)) {
            match u.socket.send_to(&u.batch, addr).await {
                Ok(_) => self.counters.writes += 1,
                Err(e) => {
                    self.counters.write_errors += 1;
                    tracing::debug!(platform = self.platform, peer = %addr, error = %e, "send failed");
                }
            }
        }
        u.batch.clear();
    }

    fn forget_silent_peers(&mut self) {
        let Link::Udp(u) = &mut self.link else { return };
        let platform = self.platform;
        u.heard.retain(|(a, t)| {
            let keep = t.elapsed() < UDP_PEER_TIMEOUT;
            if !keep {
                tracing::info!(platform, peer = %a, "peer silent, forgotten");
            }
            keep
        });
    }

    async fn send(&mut self, frame: &[u8], destination: Destination, requester: Option<SocketAddr>) {
        if let Some((p, rng)) = &mut self.loss
            && rand::Rng::random::<f64>(rng) < *p
        {
            self.counters.lost += 1;
            return;
        }
        match &mut self.link {
            Link::Udp(u) => {
                let peers: Vec<SocketAddr> = match (destination, requester) {
                    (Destination::Requester, Some(addr)) => vec![addr],
                    _ => {
                        if u.targets.is_empty() && u.heard.is_empty() {
                            self.counters.unrouted += 1;
                            return;
                        }
                        if u.batch.len() + frame.len() > BATCH_BYTES {
                            self.send_batch().await;
                        }
                        let Link::Udp(u) = &mut self.link else { unreachable!("udp") };
                        u.batch.extend_from_slice(frame);
                        return;
                    }
                };
                for addr in peers {
                    match u.socket.send_to(frame, addr).await {
                        Ok(_) => self.counters.writes += 1,
                        Err(e) => {
                            self.counters.write_errors += 1;
                            tracing::debug!(platform = self.platform, peer = %addr, error = %e, "send failed");
                        }
                    }
                }
            }
            Link::Serial(tx) => match tx.try_send(frame.to_vec()) {
                Ok(()) => self.counters.writes += 1,
                Err(_) => self.counters.dropped += 1,
            },
        }
    }
}

/// The simulator: links opened, ready to run.
pub struct Simulator {
    world: World,
    config: SitlConfig,
    cores: Vec<VehicleCore>,
    io: Vec<VehicleIo>,
    inbound: mpsc::Receiver<Inbound>,
    /// Receive tasks (aborted at the end).
    tasks: Vec<JoinHandle<()>>,
    /// Serial writer tasks (drained at the end).
    writers: Vec<JoinHandle<()>>,
    /// When the paced clock started, and its speed.
    paced_start: Option<(Instant, f64)>,
}

impl Simulator {
    /// Validates the configuration against the world and opens every link (nothing is sent yet).
    pub async fn bind(world: World, config: SitlConfig) -> Result<Simulator, SimError> {
        let ids = world.platform_ids();
        // The schedule must exist.
        world.scenario().range_epochs(&config.schedule)?;
        if let Speed::Factor(s) = config.speed
            && !(s.is_finite() && s > 0.0)
        {
            return Err(SimError::Config(format!("speed must be a positive number or max, got {s}")));
        }
        if !(0.0..1.0).contains(&config.link_loss) {
            return Err(SimError::Config(format!("link loss must be in [0, 1), got {}", config.link_loss)));
        }
        for (id, _) in &config.endpoints {
            if !ids.contains(id) {
                return Err(SimError::Config(format!("endpoint for platform {id}, which the scenario does not have")));
            }
        }
        let scenario = world.scenario();
        let origin =
            config.origin.unwrap_or(GeoOrigin { lat_deg: scenario.latitude_deg, lon_deg: config.origin_lon_deg, alt_m: 0.0 });
        let (tx, inbound) = mpsc::channel(4096);
        let mut cores = Vec::new();
        let mut io = Vec::new();
        let mut tasks = Vec::new();
        let mut writers = Vec::new();
        for (index, &id) in ids.iter().enumerate() {
            let mut vehicle = vehicle_config(&world, id, &config.schedule, config.streams, origin, config.autopilot);
            vehicle.unix_time |= config.gnss_time;
            vehicle.gnss |= config.gnss_time;
            vehicle.gnss_lost_at = config.gnss_lost_at;
            vehicle.gnss_back_at = config.gnss_back_at;
            vehicle.gnss_glitch_m = config.gnss_glitch_m;
            let core = VehicleCore::new(vehicle).map_err(|e| SimError::Config(e.to_string()))?;
            let mut core = core;
            for &(message_id, hz) in &config.stream_rates {
                core.preset_rate(message_id, hz).map_err(|e| SimError::Config(format!("--stream-rate: {e}")))?;
            }
            let mut matching = config.endpoints.iter().filter(|(p, _)| *p == id);
            let endpoint = match (matching.next(), matching.next()) {
                (Some((_, e)), None) => e.clone(),
                (None, _) => return Err(SimError::Config(format!("no endpoint for platform {id}"))),
                (Some(_), Some(_)) => return Err(SimError::Config(format!("two endpoints for platform {id}"))),
            };
            let (link, bound) = open_link(index, id, &endpoint, tx.clone(), &mut tasks, &mut writers).await?;
            cores.push(core);
            let loss = (config.link_loss > 0.0).then(|| {
                let seed = config.seed ^ (u64::from(config.run) << 32) ^ (u64::from(id) << 48) ^ 0x1055;
                (config.link_loss, <rand_chacha::ChaCha8Rng as rand::SeedableRng>::seed_from_u64(seed))
            });
            io.push(VehicleIo { platform: id, endpoint: bound, link, counters: LinkCounters::default(), loss });
        }
        Ok(Simulator { world, config, cores, io, inbound, tasks, writers, paced_start: None })
    }

    /// Every vehicle's link, in platform id order.
    pub fn endpoints(&self) -> Vec<(PlatformId, BoundEndpoint)> {
        self.io.iter().map(|v| (v.platform, v.endpoint.clone())).collect()
    }

    /// Runs the scenario to its end, or until `shutdown` completes.
    pub async fn run(mut self, shutdown: impl Future<Output = ()>) -> Result<SimReport, SimError> {
        let mut shutdown = std::pin::pin!(shutdown);
        let mut out = Vec::new();
        let mut sim_now = TimeUs(0);
        let world = self.world.clone();
        let trajectories: Vec<_> =
            self.cores.iter().map(|c| world.trajectory(c.platform()).cloned()).collect::<Result<_, _>>()?;

        // Start gate.
        if self.config.wait_for_peers {
            self.cores.iter_mut().for_each(|c| c.set_answers_timesync(false));
            tracing::info!("waiting for a peer on every vehicle");
            while !self.io.iter().all(|v| v.connected()) {
                tokio::select! {
                    biased;
                    _ = &mut shutdown => return Ok(self.finish(StopReason::Shutdown, sim_now).await),
                    msg = self.inbound.recv() => match msg {
                        Some(msg) => self.handle_inbound(msg, sim_now, &trajectories, &mut out).await,
                        None => break,
                    },
                }
            }
        }
        if let Speed::Factor(_) = self.config.speed {
            // Simulated time zero at a whole second of Unix time: a ranging schedule on whole
            // seconds of simulated time is then on whole seconds of the companions' clocks, as
            // a real team's schedule is (the nodes' `epoch_grid_ms`).
            let into_second = std::time::SystemTime::now().duration_since(std::time::UNIX_EPOCH).map_or(0, |d| d.subsec_nanos());
            let deadline = Instant::now() + Duration::from_nanos(u64::from(1_000_000_000 - into_second));
            if !self.serve_until(deadline, &mut shutdown, sim_now, &trajectories, &mut out).await {
                return Ok(self.finish(StopReason::Shutdown, sim_now).await);
            }
        }
        // (near real time, the vehicles' clocks are real clocks running at a rate of their own,
        // as PX4's SIH ran at 0.992: their TIMESYNC answers are what a node's mapping must follow)
        let real_time = matches!(self.config.speed, Speed::Factor(s) if (s - 1.0).abs() <= NEAR_REAL_TIME);
        self.cores.iter_mut().for_each(|c| c.set_answers_timesync(real_time));
        tracing::info!(schedule = %self.config.schedule, seed = self.config.seed, run = self.config.run, speed = ?self.config.speed, "simulation started");
        let wall_start = Instant::now();
        self.paced_start = match self.config.speed {
            Speed::Factor(speed) => Some((wall_start, speed)),
            Speed::Max => None,
        };
        let events = world.events(&self.config.schedule, self.config.seed, self.config.run)?;
        let ids: Vec<PlatformId> = self.cores.iter().map(|c| c.platform()).collect();
        let index_of = |id: PlatformId| ids.iter().position(|&p| p == id);
        let mut epoch = 0u32;
        for (n, event) in events.enumerate() {
            let t = event.time();
            // Pacing: wait for the event's wall time, serving the links meanwhile.
            if let Speed::Factor(speed) = self.config.speed {
                let deadline = wall_start + Duration::from_secs_f64(t.as_secs_f64() / speed);
                if deadline > Instant::now() {
                    self.send_batches().await;
                }
                if !self.serve_until(deadline, &mut shutdown, sim_now, &trajectories, &mut out).await {
                    return Ok(self.finish(StopReason::Shutdown, sim_now).await);
                }
            }
            if n % 64 == 0 {
                self.send_batches().await;
                // Serve the links even when behind schedule or at full speed.
                while let Ok(msg) = self.inbound.try_recv() {
                    self.handle_inbound(msg, sim_now, &trajectories, &mut out).await;
                }
                tokio::select! {
                    biased;
                    _ = &mut shutdown => return Ok(self.finish(StopReason::Shutdown, sim_now).await),
                    _ = tokio::task::yield_now() => {}
                }
            }
            if n % 4096 == 0 {
                self.send_batches().await;
                self.io.iter_mut().for_each(VehicleIo::forget_silent_peers);
            }
            sim_now = t;
            for (i, truth) in trajectories.iter().enumerate() {
                self.cores[i].advance_to(t, truth, &mut out);
                self.flush(i, &mut out, None).await;
            }
            match &event {
                SimEvent::Imu(id, s) => {
                    if let Some(i) = index_of(*id) {
                        self.cores[i].on_imu(s, &mut out);
                        self.flush(i, &mut out, None).await;
                    }
                }
                SimEvent::Odometer(id, s) => {
                    if let Some(i) = index_of(*id) {
                        self.cores[i].on_odometer(s, &mut out);
                        self.flush(i, &mut out, None).await;
                    }
                }
                SimEvent::Wheel(id, s) => {
                    if let Some(i) = index_of(*id) {
                        self.cores[i].on_wheel(s, &mut out);
                        self.flush(i, &mut out, None).await;
                    }
                }
                SimEvent::Ranges(t, ranges) => {
                    epoch += 1;
                    for i in 0..self.cores.len() {
                        self.cores[i].on_ranges(epoch, *t, ranges, &mut out);
                        self.flush(i, &mut out, None).await;
                    }
                }
            }
        }
        let end = world.end();
        for (i, truth) in trajectories.iter().enumerate() {
            self.cores[i].advance_to(end, truth, &mut out);
            self.flush(i, &mut out, None).await;
        }
        Ok(self.finish(StopReason::EndOfScenario, end).await)
    }

    /// Serves the links until `deadline`; false when `shutdown` came first.
    async fn serve_until(
        &mut self,
        deadline: Instant,
        shutdown: &mut std::pin::Pin<&mut impl Future<Output = ()>>,
        now: TimeUs,
        trajectories: &[crate::sitl::Trajectory],
        out: &mut Vec<Outgoing>,
    ) -> bool {
        loop {
            tokio::select! {
                biased;
                _ = shutdown.as_mut() => return false,
                _ = tokio::time::sleep_until(deadline) => return true,
                Some(msg) = self.inbound.recv() => self.handle_inbound(msg, now, trajectories, out).await,
            }
        }
    }

    async fn handle_inbound(
        &mut self,
        msg: Inbound,
        now: TimeUs,
        trajectories: &[crate::sitl::Trajectory],
        out: &mut Vec<Outgoing>,
    ) {
        // Paced, the vehicles' clocks read the wall clock's simulated time (a TIMESYNC answer
        // says when the request arrived), not the last event's.
        let now = match self.paced_start {
            Some((start, speed)) => now.max(TimeUs::from_secs_f64(start.elapsed().as_secs_f64() * speed)),
            None => now,
        };
        match msg {
            Inbound::Datagram { vehicle, from, bytes } => {
                self.io[vehicle].counters.datagrams_received += 1;
                if self.cores[vehicle].on_bytes(now, &bytes, &trajectories[vehicle], out) {
                    self.io[vehicle].hear(from);
                } else {
                    tracing::debug!(platform = self.io[vehicle].platform, peer = %from, len = bytes.len(), "datagram without a valid MAVLink frame dropped");
                }
                self.flush(vehicle, out, Some(from)).await;
            }
            Inbound::Message { vehicle, header, message } => {
                self.cores[vehicle].on_message(now, header, &message, &trajectories[vehicle], out);
                self.flush(vehicle, out, None).await;
            }
            Inbound::Malformed { vehicle } => self.cores[vehicle].count_malformed(),
            Inbound::LinkClosed { vehicle, reason } => {
                tracing::warn!(platform = self.io[vehicle].platform, %reason, "link closed");
            }
        }
    }

    async fn flush(&mut self, vehicle: usize, out: &mut Vec<Outgoing>, requester: Option<SocketAddr>) {
        for o in out.drain(..) {
            let frame = o.to_frame();
            self.io[vehicle].send(&frame, o.destination, requester).await;
        }
    }

    async fn send_batches(&mut self) {
        for io in &mut self.io {
            io.send_batch().await;
        }
    }

    async fn finish(mut self, reason: StopReason, sim_time: TimeUs) -> SimReport {
        self.send_batches().await;
        for task in &self.tasks {
            task.abort();
        }
        let vehicles: Vec<VehicleReport> = self
            .cores
            .iter()
            .zip(self.io)
            .map(|(core, io)| VehicleReport {
                platform: core.platform(),
                endpoint: io.endpoint,
                counters: core.counters().clone(),
                link: io.counters,
                checker: core.checker().clone(),
            })
            .collect();
        // The links are gone with `self.io`: serial writers finish what is queued, within bounds.
        for w in self.writers {
            if tokio::time::timeout(Duration::from_secs(2), w).await.is_err() {
                tracing::warn!("serial writer did not drain within 2 s");
            }
        }
        for v in &vehicles {
            tracing::info!(platform = v.platform, counters = ?v.counters, link = ?v.link, "vehicle done");
        }
        tracing::info!(?reason, sim_time = %sim_time, "simulation stopped");
        SimReport { reason, sim_time, vehicles }
    }
}

async fn open_link(
    index: usize,
    platform: PlatformId,
    endpoint: &Endpoint,
    tx: mpsc::Sender<Inbound>,
    tasks: &mut Vec<JoinHandle<()>>,
    writers: &mut Vec<JoinHandle<()>>,
) -> Result<(Link, BoundEndpoint), SimError> {
    match endpoint {
        Endpoint::Udp { bind, targets } => {
            let socket =
                UdpSocket::bind(bind).await.map_err(|source| SimError::Open { platform, what: format!("udp {bind}"), source })?;
            let local = socket.local_addr().map_err(|source| SimError::Open { platform, what: format!("udp {bind}"), source })?;
            let socket = Arc::new(socket);
            let rx_socket = socket.clone();
            tasks.push(tokio::spawn(async move {
                let mut buf = vec![0u8; 65_536];
                loop {
                    match rx_socket.recv_from(&mut buf).await {
                        Ok((n, from)) => {
                            let msg = Inbound::Datagram { vehicle: index, from, bytes: buf[..n].to_vec() };
                            if tx.send(msg).await.is_err() {
                                return;
                            }
                        }
                        // ICMP errors from a vanished peer surface here: not fatal.
                        Err(e)
                            if matches!(
                                e.kind(),
                                std::io::ErrorKind::ConnectionRefused | std::io::ErrorKind::ConnectionReset
                            ) =>
                        {
                            tracing::debug!(platform, error = %e, "udp receive error")
                        }
                        Err(e) => {
                            let _ = tx.send(Inbound::LinkClosed { vehicle: index, reason: e.to_string() }).await;
                            return;
                        }
                    }
                }
            }));
            let link = UdpLink { socket, targets: targets.clone(), heard: Vec::new(), batch: Vec::new() };
            Ok((Link::Udp(link), BoundEndpoint::Udp { local, targets: targets.clone() }))
        }
        Endpoint::Serial { path, baud } => {
            let what = format!("serial {path}");
            let port = tokio_serial::SerialPortBuilderExt::open_native_async(tokio_serial::new(path, *baud))
                .map_err(|e| SimError::Open { platform, what: what.clone(), source: e.into() })?;
            let (read_half, mut write_half) = tokio::io::split(port);
            tasks.push(tokio::spawn(async move {
                let mut reader = mavlink_core::AsyncMavlinkReader::new(read_half);
                loop {
                    let msg = match reader.read_any_message::<MavMessage>().await {
                        Ok((header, message)) => Inbound::Message { vehicle: index, header, message: Box::new(message) },
                        Err(mavlink_core::error::MessageReadError::Parse(_)) => Inbound::Malformed { vehicle: index },
                        Err(e) => {
                            let _ = tx.send(Inbound::LinkClosed { vehicle: index, reason: e.to_string() }).await;
                            return;
                        }
                    };
                    if tx.send(msg).await.is_err() {
                        return;
                    }
                }
            }));
            let (wtx, mut wrx) = mpsc::channel::<Vec<u8>>(4096);
            writers.push(tokio::spawn(async move {
                while let Some(frame) = wrx.recv().await {
                    if let Err(e) = write_half.write_all(&frame).await {
                        tracing::warn!(platform, error = %e, "serial write failed");
                        return;
                    }
                }
            }));
            Ok((Link::Serial(wtx), BoundEndpoint::Serial { path: path.clone(), baud: *baud }))
        }
    }
}
