//! The node's tokio runner: owns the vehicle link, the cooperative-network socket, the ranging
//! device and the clock, and drives a [`NodeShell`] (which holds everything else, sans-io):
//! bytes and clock readings in, the shell's outputs carried out in order. What the node does at
//! its links (the shell decides, the runner carries it out):
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

use super::coop_link::CoopLink;
pub use super::coop_link::CoopSpec;
use super::error::NodeError;
use super::files::{load_nav_state, load_signing_state, save_whole};
use super::shell::{LinkFacts, NodeShell, Now, Record, ShellConfig, ShellOutput, TICK};
use super::vehicle_link::{Received, VehicleLink};
use crate::protocol::signing::TeamKey;
use crate::recording::wall_now_ns;
use std::net::SocketAddr;
use std::sync::Arc;
use std::time::Duration;

pub use super::log::{
    LogStart, NODE_EVENT_SCHEMA, NODE_EVENT_SCHEMA_NAME, NodeEvent, NodeLogHeader, events_topic, metadata_name,
    saved_state_attachment_name, vehicle_attachment_name,
};
pub use super::profile::VehicleProfile;
pub use super::range_link::RangeSource;
use super::range_link::spawn_range_reader;
pub use super::shell::{CoopTx, NodeInit, NodeSummary, SIGNING_STATE_EVERY, STALE_START_US};
pub use crate::protocol::wire::COMPANION_COMPID;
pub use crate::recording::SharedRecorder;

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
    /// Where the navigation state is kept across restarts ([`super::saved`]): read at start (a
    /// state at most [`super::saved::MAX_RESTORE_AGE_US`] older than the vehicle's first sample
    /// is restored), written every [`super::saved::SAVE_EVERY_US`] of the team clock and at the
    /// end, whole or not at all.
    pub state_file: Option<std::path::PathBuf>,
    /// The vehicle link's signing key (the autopilot's), when its port is signed.
    pub vehicle_key: Option<TeamKey>,
    /// A ranging device on the companion ([`super::ranging`]), besides the vehicle link.
    pub ranges: Option<RangeSource>,
}

/// Receive buffer asked for the cooperative socket: a burst of state records (14 fragments per
/// platform per epoch) must not overflow it while the node is busy (the kernel caps it at
/// net.core.rmem_max).
const COOP_RECV_BUFFER: usize = 4 << 20;

/// Writes one record to the log.
fn record(rec: &SharedRecorder, id: u16, record: Record) {
    let Ok(mut r) = rec.lock() else { return };
    let now = wall_now_ns();
    let _ = match record {
        Record::Event(event) => r.json_message(&events_topic(id), NODE_EVENT_SCHEMA_NAME, NODE_EVENT_SCHEMA, now, &event),
        Record::Frame { link, dir, bytes } => r.frame(link, dir, now, &bytes),
        Record::Estimate(e) => r.estimate(e.platform, now, &crate::view::foxglove::position_estimate(&e)),
        Record::Update(u) => crate::recording::record_update(&mut r, now, &u),
    };
    let _ = r.maybe_flush(std::time::Instant::now());
}

/// The links a shell's outputs go to.
struct Io<'a> {
    vehicle: &'a VehicleLink,
    coop: &'a CoopLink,
    recorder: &'a Option<SharedRecorder>,
    signing_state: Option<&'a std::path::Path>,
    state_file: Option<&'a std::path::Path>,
}

impl Io<'_> {
    /// Carries out the shell's outputs, in order.
    async fn carry_out(&self, shell: &mut NodeShell) {
        for output in shell.take_outputs() {
            match output {
                ShellOutput::Vehicle { header, msg } => self.vehicle.send(&header, &msg).await,
                ShellOutput::Coop { frames, unicast } => {
                    let sent = self.coop.send(&frames, &unicast).await;
                    shell.sent(sent.datagrams, sent.bytes);
                }
                ShellOutput::Record(r) => {
                    if let Some(rec) = self.recorder {
                        record(rec, shell.id(), r);
                    }
                }
                ShellOutput::SigningState(text) => self.save(&text),
                ShellOutput::NavState(text) => self.save_nav(&text),
            }
        }
    }

    fn save(&self, text: &str) {
        if let Some(path) = self.signing_state
            && let Err(e) = save_whole(path, text)
        {
            tracing::warn!(path = %path.display(), error = %e, "could not save the signing state");
        }
    }

    fn save_nav(&self, text: &str) {
        if let Some(path) = self.state_file
            && let Err(e) = save_whole(path, text)
        {
            tracing::warn!(path = %path.display(), error = %e, "could not save the navigation state");
        }
    }
}

/// Reads the vehicle link on its own task (a serial or TCP read has no timeout).
fn spawn_vehicle_reader(vehicle: Arc<VehicleLink>) -> (tokio::task::JoinHandle<()>, tokio::sync::mpsc::Receiver<Received>) {
    let (vtx, vrx) = tokio::sync::mpsc::channel::<Received>(4096);
    let task = tokio::spawn(async move {
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
    });
    (task, vrx)
}

/// The shell's configuration from the links and the files kept across restarts (the signing
/// timestamp to sign above, the navigation state to restore).
fn shell_config(links: &Links, init: &NodeInit, record: bool) -> Result<ShellConfig, NodeError> {
    let signing_resume_after = match (&links.team_key, &links.signing_state) {
        (Some(_), Some(path)) => load_signing_state(path)?,
        _ => 0,
    };
    let restore = match (&links.state_file, init) {
        (Some(path), NodeInit::Given { core, .. } | NodeInit::Ready(core)) => load_nav_state(path, core.id()),
        (Some(path), NodeInit::Pending { config, .. }) => load_nav_state(path, config.id),
        (None, _) => None,
    };
    Ok(ShellConfig {
        profile: links.profile.clone(),
        team_key: links.team_key.clone(),
        signing_resume_after,
        peers: links.peers.clone(),
        idle_exit: links.idle_exit,
        grace: links.grace,
        ranges: links.ranges.is_some(),
        unicast: matches!(links.coop, CoopSpec::Udp { .. }),
        record,
        restore,
        save_state: links.state_file.is_some(),
        clock_from_log: false,
    })
}

/// Runs a node until `shutdown` resolves or the vehicle link fails. `bound` receives the
/// cooperative socket's local address once it is bound (None: a serial radio).
pub async fn run(
    init: NodeInit,
    links: Links,
    recorder: Option<SharedRecorder>,
    bound: tokio::sync::oneshot::Sender<Option<SocketAddr>>,
    shutdown: impl std::future::Future<Output = ()>,
) -> Result<NodeSummary, NodeError> {
    let clock = std::time::Instant::now();
    let now = move || Now { wall_us: clock.elapsed().as_micros() as u64, unix_ns: wall_now_ns() as i64 };
    let config = shell_config(&links, &init, recorder.is_some())?;
    let saved = config.restore.as_ref().map(|s| s.to_text());
    let mut shell = NodeShell::new(init, config, now())?;
    let id = shell.id();
    if let (Some(text), Some(Ok(mut r))) = (saved, recorder.as_ref().map(|r| r.lock())) {
        // what the shell was offered to restore, for a replay to offer its shell
        let _ = r.attachment(&saved_state_attachment_name(id), "text/plain", text.as_bytes());
    }
    let mut vehicle = VehicleLink::open(&links.vehicle).await?;
    if let Some(key) = &links.vehicle_key {
        vehicle.sign(key, id as u8); // (the shell checked that the id is a system id)
    }
    let vehicle = Arc::new(vehicle);
    if let Some(granted) = vehicle.recv_buffer() {
        tracing::info!(platform = id, bytes = granted, "vehicle socket receive buffer");
    }
    let coop = CoopLink::open(&links.coop, COOP_RECV_BUFFER).await?;
    let _ = bound.send(coop.local_addr());
    tracing::info!(platform = id, vehicle = %links.vehicle, coop = %coop.describe(), "node started");
    let mut range_rx = match links.ranges.clone() {
        Some(source) => Some(spawn_range_reader(source)?),
        None => None,
    };
    let (reader, mut vrx) = spawn_vehicle_reader(vehicle.clone());
    let io = Io {
        vehicle: &vehicle,
        coop: &coop,
        recorder: &recorder,
        signing_state: links.signing_state.as_deref(),
        state_file: links.state_file.as_deref(),
    };
    let mut tick = tokio::time::interval(TICK);
    let mut buf = vec![0u8; 65_536];
    tokio::pin!(shutdown);
    // the shell's first output: a HEARTBEAT to the vehicle (a udpin peer learns our address from it)
    io.carry_out(&mut shell).await;
    loop {
        let go = tokio::select! {
            _ = &mut shutdown => break,
            _ = tick.tick() => shell.tick(now()),
            frame = vrx.recv() => {
                let Some(frame) = frame else { return Err(NodeError::VehicleClosed) };
                shell.vehicle_frame(frame, now())?;
                true
            }
            Some((bytes, arrival_us)) = async { range_rx.as_mut()?.recv().await }, if range_rx.is_some() => {
                shell.range_bytes(&bytes, arrival_us, now());
                true
            }
            r = coop.recv(&mut buf) => match r {
                Ok((n, from)) => {
                    shell.coop_datagram(&buf[..n], from, now());
                    true
                }
                Err(e) if e.kind() == std::io::ErrorKind::BrokenPipe => return Err(NodeError::io("the cooperative radio")(e)),
                Err(_) => true,
            },
        };
        io.carry_out(&mut shell).await;
        if !go {
            break;
        }
    }
    reader.abort();
    if let Some(state) = shell.signing_state() {
        io.save(&state);
    }
    if let Some(state) = shell.nav_state(now()) {
        io.save_nav(&state);
    }
    Ok(shell.summary(LinkFacts {
        coop_noise_bytes: coop.noise_bytes(),
        coop_dropped: coop.dropped(),
        vehicle_signing: vehicle.signing_counters(),
        wall_s: clock.elapsed().as_secs_f64(),
    }))
}
