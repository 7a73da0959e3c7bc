//! The ground station's tokio runner: owns the cooperative-network socket, the vehicle links,
//! the web server, the Foxglove server and the clock; feeds a [`GcsState`] and hands every
//! [`GcsEvent`] it returns to each [`GcsSink`].
//!
//! - **Cooperative network**: one UDP socket. HEARTBEAT (sysid 255, compid 190, MAV_TYPE_GCS,
//!   MAV_AUTOPILOT_INVALID) at 1 Hz to every peer: those given and every address a valid frame
//!   came from. A node learns the ground station from that heartbeat and then sends it
//!   everything it sends its peers.
//! - **Vehicle links** (optional, simulated vehicles): any MAVLink URL the mavlink crate opens
//!   (`udpout:HOST:PORT` as MAVProxy would); the ground station sends its HEARTBEAT there too
//!   (a simulator streams to whoever it heard) and reads raw frames.
//! - Each link has its own MAVLink sequence counter, as MAVLink expects.

use std::future::Future;
use std::net::SocketAddr;
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant, SystemTime, UNIX_EPOCH};

use mavlink_core::{AsyncMavConnection, MAVLinkMessageRaw, MavHeader};
use tokio::net::UdpSocket;

use super::foxglove_live::FoxglovePublisher;
use super::state::{GcsConfig, GcsCounters, GcsState};
use super::{GCS_COMPID, GCS_SYSID, GcsEvent, GcsSink, WallNs};
use crate::estimation::PlatformId;
use crate::protocol::MavMessage;
use crate::protocol::dialect::cooploc::{MavAutopilot, MavType};
use crate::protocol::wire;

/// Receive times: a monotonic clock anchored once to the system clock.
#[derive(Debug, Clone, Copy)]
pub struct Clock {
    start: Instant,
    start_unix_ns: u64,
}

impl Clock {
    pub fn new() -> Self {
        let start_unix_ns = SystemTime::now().duration_since(UNIX_EPOCH).map_or(0, |d| d.as_nanos() as u64);
        Clock { start: Instant::now(), start_unix_ns }
    }

    pub fn now(&self) -> WallNs {
        WallNs(self.start_unix_ns + self.start.elapsed().as_nanos() as u64)
    }
}

impl Default for Clock {
    fn default() -> Self {
        Self::new()
    }
}

/// Where the ground station listens and connects.
#[derive(Debug, Clone)]
pub struct GcsLinks {
    /// Local address of the cooperative-network socket (port 0: ephemeral).
    pub coop_bind: SocketAddr,
    /// Nodes known from the start.
    pub peers: Vec<SocketAddr>,
    /// Vehicle links: platform id and MAVLink URL.
    pub vehicles: Vec<(PlatformId, String)>,
    /// Web server address (port 0: ephemeral).
    pub http: SocketAddr,
    /// Foxglove WebSocket server address (port 0: ephemeral); `None`: no server.
    pub foxglove: Option<SocketAddr>,
    /// Stop when nothing has been heard for this long (after the first frame).
    pub idle_exit: Option<Duration>,
}

/// The addresses actually bound.
#[derive(Debug, Clone, Copy)]
pub struct Bound {
    pub coop: SocketAddr,
    pub http: SocketAddr,
    pub foxglove: Option<SocketAddr>,
}

/// What the ground station saw, when it stops.
#[derive(Debug, Clone)]
pub struct GcsSummary {
    pub counters: GcsCounters,
    pub vehicles: Vec<PlatformId>,
    pub peers: Vec<SocketAddr>,
    pub estimates: u64,
    pub truth_samples: u64,
}

/// The ground station's HEARTBEAT.
pub fn heartbeat() -> MavMessage {
    wire::heartbeat(MavType::MAV_TYPE_GCS, MavAutopilot::MAV_AUTOPILOT_INVALID)
}

/// One sequence counter per link.
#[derive(Default)]
struct Sequence(u8);

impl Sequence {
    fn next_header(&mut self) -> MavHeader {
        let header = MavHeader { system_id: u32::from(GCS_SYSID), component_id: GCS_COMPID, sequence: self.0 };
        self.0 = self.0.wrapping_add(1);
        header
    }
}

fn raw_bytes(raw: &MAVLinkMessageRaw) -> &[u8] {
    match raw {
        MAVLinkMessageRaw::V1(m) => m.raw_bytes(),
        MAVLinkMessageRaw::V2(m) => m.raw_bytes(),
    }
}

fn dispatch(sinks: &mut [Box<dyn GcsSink>], events: &[GcsEvent]) {
    for event in events {
        if let GcsEvent::Rejected { link, reason, .. } = event {
            tracing::debug!(%link, %reason, "input dropped");
        }
        for sink in sinks.iter_mut() {
            sink.on_event(event);
        }
    }
}

/// Why the ground station could not start (each names the address or link at fault).
#[derive(Debug, thiserror::Error)]
pub enum GcsError {
    #[error("binding the cooperative socket {addr}")]
    Coop { addr: SocketAddr, source: std::io::Error },
    #[error("binding the web server {addr}")]
    Http { addr: SocketAddr, source: std::io::Error },
    #[error("starting the Foxglove server on {addr}: {reason}")]
    Foxglove { addr: SocketAddr, reason: String },
    #[error("connecting to vehicle {id} at {url}")]
    Vehicle { id: PlatformId, url: String, source: std::io::Error },
}

/// The web server on `addr`: its bound address, the sender that stops it, its task.
async fn start_http(
    addr: SocketAddr,
    state: Arc<Mutex<GcsState>>,
    clock: Clock,
) -> Result<(SocketAddr, tokio::sync::oneshot::Sender<()>, tokio::task::JoinHandle<()>), GcsError> {
    let http_err = |source| GcsError::Http { addr, source };
    let listener = tokio::net::TcpListener::bind(addr).await.map_err(http_err)?;
    let http_addr = listener.local_addr().map_err(http_err)?;
    let (http_stop_tx, http_stop_rx) = tokio::sync::oneshot::channel::<()>();
    let app = super::http::router(state, clock);
    let http_task = tokio::spawn(async move {
        let serve = axum::serve(listener, app).with_graceful_shutdown(async move {
            let _ = http_stop_rx.await;
        });
        if let Err(e) = serve.await {
            tracing::warn!(error = %e, "web server stopped");
        }
    });
    Ok((http_addr, http_stop_tx, http_task))
}

/// The Foxglove server on `addr`, on a context of its own: its publisher, handle and address.
async fn start_foxglove(
    addr: SocketAddr,
    origin: wire::GeoOrigin,
) -> Result<(FoxglovePublisher, foxglove::WebSocketServerHandle, SocketAddr), GcsError> {
    let ctx = foxglove::Context::new();
    let publisher = FoxglovePublisher::new(ctx.clone(), origin);
    let handle = foxglove::WebSocketServer::new()
        .context(&ctx)
        .name("cooploc gcs")
        .bind(addr.ip().to_string(), addr.port())
        .start()
        .await
        .map_err(|e| GcsError::Foxglove { addr, reason: e.to_string() })?;
    let fox_addr = SocketAddr::new(addr.ip(), handle.port());
    Ok((publisher, handle, fox_addr))
}

/// A vehicle link: its id, the connection, its sequence counter.
type VehicleConn = (PlatformId, Arc<mavlink_core::AsyncConnection<MavMessage>>, Sequence);

/// Opens the vehicle links, each read on its own task (recv has no timeout): the links, the
/// reading tasks, and the channel their frames arrive on.
async fn open_vehicles(
    vehicles: &[(PlatformId, String)],
) -> Result<(Vec<VehicleConn>, Vec<tokio::task::JoinHandle<()>>, tokio::sync::mpsc::Receiver<(PlatformId, Vec<u8>)>), GcsError> {
    let (vtx, vrx) = tokio::sync::mpsc::channel::<(PlatformId, Vec<u8>)>(8192);
    let mut vehicle_conns = Vec::new();
    let mut readers = Vec::new();
    for (id, url) in vehicles {
        let conn = Arc::new(mavlink_core::connect_async::<MavMessage>(url).await.map_err(|source| GcsError::Vehicle {
            id: *id,
            url: url.clone(),
            source,
        })?);
        let (id, reader_conn, vtx) = (*id, conn.clone(), vtx.clone());
        readers.push(tokio::spawn(async move {
            loop {
                match reader_conn.recv_raw().await {
                    Ok(raw) => {
                        if vtx.send((id, raw_bytes(&raw).to_vec())).await.is_err() {
                            break;
                        }
                    }
                    Err(mavlink_core::error::MessageReadError::Io(e)) if e.kind() != std::io::ErrorKind::WouldBlock => {
                        tracing::warn!(vehicle = id, error = %e, "vehicle link read error");
                        tokio::time::sleep(Duration::from_millis(100)).await;
                    }
                    Err(_) => {}
                }
            }
        }));
        vehicle_conns.push((id, conn, Sequence::default()));
    }
    Ok((vehicle_conns, readers, vrx))
}

/// Runs the ground station until `shutdown` resolves (or the idle exit). `extra_sinks` receive
/// every event besides the Foxglove server (the recorder's hook). `bound` receives the bound
/// addresses once every server listens; `shared` is the state the web server reads.
pub async fn run(
    config: GcsConfig,
    links: GcsLinks,
    mut extra_sinks: Vec<Box<dyn GcsSink>>,
    bound: tokio::sync::oneshot::Sender<Bound>,
    shutdown: impl Future<Output = ()>,
) -> Result<GcsSummary, GcsError> {
    let clock = Clock::new();
    let origin = config.origin;
    let state = Arc::new(Mutex::new(GcsState::new(config)));
    let lock = || state.lock().unwrap_or_else(|e| e.into_inner());
    lock().start(clock.now());
    for p in &links.peers {
        lock().add_peer(*p);
    }

    let coop_err = |source| GcsError::Coop { addr: links.coop_bind, source };
    let coop = UdpSocket::bind(links.coop_bind).await.map_err(coop_err)?;
    let coop_addr = coop.local_addr().map_err(coop_err)?;

    let (http_addr, http_stop_tx, http_task) = start_http(links.http, state.clone(), clock).await?;
    let mut sinks: Vec<Box<dyn GcsSink>> = Vec::new();
    let foxglove = match links.foxglove {
        Some(addr) => {
            let (publisher, handle, fox_addr) = start_foxglove(addr, origin).await?;
            sinks.push(Box::new(publisher));
            Some((handle, fox_addr))
        }
        None => None,
    };
    sinks.append(&mut extra_sinks);

    let (mut vehicle_conns, readers, mut vrx) = open_vehicles(&links.vehicles).await?;

    let _ = bound.send(Bound { coop: coop_addr, http: http_addr, foxglove: foxglove.as_ref().map(|(_, a)| *a) });
    tracing::info!(coop = %coop_addr, http = %http_addr, "ground station started");

    let mut coop_seq = Sequence::default();
    // With a team key the heartbeat is signed (link id: the ground station's system id), so that
    // the nodes, which read only signed frames, learn where to send.
    let mut signer = lock().config().team_key.clone().map(|k| crate::protocol::signing::Signer::new(k, GCS_SYSID, 0));
    let hb = heartbeat();
    let mut tick = tokio::time::interval(Duration::from_millis(250));
    let mut ticks = 0u32;
    let mut last_heard: Option<Instant> = None;
    let mut buf = vec![0u8; 65536];
    tokio::pin!(shutdown);
    loop {
        let events = tokio::select! {
            _ = &mut shutdown => break,
            _ = tick.tick() => {
                if let (Some(idle), Some(last)) = (links.idle_exit, last_heard)
                    && last.elapsed() >= idle
                {
                    tracing::info!("nothing heard for {idle:?}: stopping");
                    break;
                }
                ticks += 1;
                if ticks % 4 == 1 {
                    let header = coop_seq.next_header();
                    let frame = match &mut signer {
                        Some(s) => s.frame(header, &hb, clock.now().0 / 1000),
                        None => wire::to_frame(header, &hb),
                    };
                    let peers: Vec<SocketAddr> = {
                        let mut st = lock();
                        st.expire_peers(clock.now());
                        st.peers().collect()
                    };
                    for p in peers {
                        let _ = coop.send_to(&frame, p).await;
                    }
                    for (_, conn, seq) in &mut vehicle_conns {
                        let _ = conn.send(&seq.next_header(), &hb).await;
                    }
                    let now = clock.now();
                    let st = lock();
                    if st.vehicles.is_empty() {
                        continue;
                    }
                    vec![GcsEvent::Health { rx: now, health: Box::new(st.health(now)) }]
                } else {
                    continue;
                }
            }
            r = coop.recv_from(&mut buf) => {
                let Ok((n, from)) = r else { continue };
                last_heard = Some(Instant::now());
                lock().on_coop_datagram(clock.now(), from, &buf[..n])
            }
            Some((id, bytes)) = vrx.recv() => {
                last_heard = Some(Instant::now());
                lock().on_vehicle_frame(clock.now(), id, &bytes)
            }
        };
        dispatch(&mut sinks, &events);
    }

    for r in readers {
        r.abort();
    }
    let _ = http_stop_tx.send(());
    let _ = tokio::time::timeout(Duration::from_secs(2), http_task).await;
    if let Some((handle, _)) = foxglove {
        let _ = tokio::time::timeout(Duration::from_secs(2), handle.stop().wait()).await;
    }
    let s = lock();
    Ok(GcsSummary {
        counters: s.counters,
        vehicles: s.vehicles.keys().copied().collect(),
        peers: s.peers().collect(),
        estimates: s.vehicles.values().map(|v| v.counts.estimates).sum(),
        truth_samples: s.vehicles.values().map(|v| v.counts.truth_samples).sum(),
    })
}
