//! The node's tokio runner: owns the vehicle link, the cooperative-network socket and the
//! clock, converts messages with [`crate::protocol::wire`], and feeds a [`NodeCore`].
//!
//! - **Vehicle**: any MAVLink connection URL the mavlink crate opens (`udpout:HOST:PORT`,
//!   `udpin:HOST:PORT`, `tcpout:`, `tcpin:`, `serial:/dev/ttyX:BAUD`). Only messages from the
//!   vehicle's own system id are used: HIGHRES_IMU, ODOMETRY (body velocity) and the cooploc
//!   ranges its radio measured. The node sends HEARTBEAT (compid 191, ONBOARD_CONTROLLER) at 1 Hz
//!   and, after every cooperative update, its estimate as LOCAL_POSITION_NED.
//! - **Cooperative network**: one UDP socket. The node sends to every peer it knows: those given
//!   on the command line and every address a valid cooploc frame from another platform arrived
//!   from (so a node can be started knowing only one peer, and tests can use ephemeral ports).
//! - Bad input (malformed frames, NaN or absurd values, time going backwards, unknown platforms)
//!   is counted, logged and dropped; nothing from the network can panic the process.

use std::collections::BTreeSet;
use std::net::SocketAddr;
use std::sync::Arc;
use std::time::Duration;

use mavlink_core::{AsyncMavConnection, MavHeader};
use tokio::net::UdpSocket;

use super::core::{NodeCore, NodeInput, NodeOutput, NodeStats};
use crate::protocol::MavMessage;
use crate::protocol::dialect::cooploc::{HEARTBEAT_DATA, MavAutopilot, MavModeFlag, MavState, MavType};
use crate::protocol::wire;

/// MAVLink component id of a companion computer.
pub const COMPANION_COMPID: u8 = 191;

/// Where the node connects.
#[derive(Debug, Clone)]
pub struct Links {
    /// MAVLink URL of the vehicle.
    pub vehicle: String,
    /// Local address of the cooperative-network socket (port 0: ephemeral).
    pub coop_bind: SocketAddr,
    /// Peers known from the start.
    pub peers: Vec<SocketAddr>,
    /// Stop when the vehicle has been silent this long (after its first frame): the stream
    /// ended. The node then closes its last instant, broadcasts, listens to its peers for
    /// `grace`, runs the epochs still pending, and returns.
    pub idle_exit: Option<Duration>,
    pub grace: Duration,
}

/// What a node did, when it stops.
#[derive(Debug, Clone)]
pub struct NodeSummary {
    pub stats: NodeStats,
    pub estimate: wire::EstimateReport,
    pub vehicle_frames: u64,
    pub vehicle_rejected: u64,
    pub coop_frames: u64,
    pub coop_rejected: u64,
    pub peers: Vec<SocketAddr>,
}

async fn send_all(
    coop: &UdpSocket,
    peers: &BTreeSet<SocketAddr>,
    vehicle: &impl AsyncMavConnection<MavMessage>,
    next_header: &mut impl FnMut() -> MavHeader,
    outputs: Vec<NodeOutput>,
) {
    for output in outputs {
        match output {
            NodeOutput::ToPeers(msg) => {
                let frame = wire::to_frame(next_header(), &msg);
                for p in peers {
                    let _ = coop.send_to(&frame, p).await;
                }
            }
            NodeOutput::ToVehicle(msg) => {
                let _ = vehicle.send(&next_header(), &msg).await;
            }
        }
    }
}

fn heartbeat() -> MavMessage {
    MavMessage::HEARTBEAT(HEARTBEAT_DATA {
        custom_mode: 0,
        mavtype: MavType::MAV_TYPE_ONBOARD_CONTROLLER,
        autopilot: MavAutopilot::MAV_AUTOPILOT_INVALID,
        base_mode: MavModeFlag::empty(),
        system_status: MavState::MAV_STATE_ACTIVE,
        mavlink_version: 3,
    })
}

/// Runs a node until `shutdown` resolves or the vehicle link fails. `bound` receives the
/// cooperative socket's local address once it is bound.
pub async fn run(
    mut core: NodeCore,
    links: Links,
    bound: tokio::sync::oneshot::Sender<SocketAddr>,
    shutdown: impl std::future::Future<Output = ()>,
) -> anyhow::Result<NodeSummary> {
    use anyhow::Context as _;
    let id = core.id();
    let vehicle = Arc::new(
        mavlink_core::connect_async::<MavMessage>(&links.vehicle)
            .await
            .with_context(|| format!("connecting to the vehicle at {}", links.vehicle))?,
    );
    let coop =
        UdpSocket::bind(links.coop_bind).await.with_context(|| format!("binding the cooperative socket {}", links.coop_bind))?;
    let local = coop.local_addr()?;
    let _ = bound.send(local);
    tracing::info!(platform = id, vehicle = %links.vehicle, coop = %local, "node started");
    let mut peers: BTreeSet<SocketAddr> = links.peers.iter().copied().collect();

    // The vehicle link is read on its own task (the mavlink crate's recv has no timeout).
    let (vtx, mut vrx) = tokio::sync::mpsc::channel::<(MavHeader, MavMessage)>(4096);
    let reader = {
        let vehicle = vehicle.clone();
        tokio::spawn(async move {
            loop {
                match vehicle.recv().await {
                    Ok(frame) => {
                        if vtx.send(frame).await.is_err() {
                            break;
                        }
                    }
                    Err(mavlink_core::error::MessageReadError::Io(e)) if e.kind() != std::io::ErrorKind::WouldBlock => {
                        tracing::warn!(error = %e, "vehicle link read error");
                        tokio::time::sleep(Duration::from_millis(10)).await;
                    }
                    Err(_) => {}
                }
            }
        })
    };

    let mut seq: u8 = 0;
    let mut next_header = || {
        seq = seq.wrapping_add(1);
        MavHeader { system_id: u32::from(id), component_id: COMPANION_COMPID, sequence: seq }
    };
    let mut summary_counts = (0u64, 0u64, 0u64, 0u64);
    let mut tick = tokio::time::interval(Duration::from_millis(250));
    let mut beats = 0u32;
    let mut last_vehicle = tokio::time::Instant::now();
    let mut heard_vehicle = false;
    let mut ending: Option<tokio::time::Instant> = None;
    let mut buf = vec![0u8; 2048];
    tokio::pin!(shutdown);
    // Announce ourselves to the vehicle at once (a udpin peer learns our address from it).
    let _ = vehicle.send(&next_header(), &heartbeat()).await;
    loop {
        let inputs: Vec<NodeInput> = tokio::select! {
            _ = &mut shutdown => break,
            _ = tick.tick() => {
                if let (Some(idle), true, None) = (links.idle_exit, heard_vehicle, ending)
                    && last_vehicle.elapsed() >= idle
                {
                    tracing::info!(platform = id, "vehicle silent: closing the last instant");
                    ending = Some(tokio::time::Instant::now() + links.grace);
                    let out = core.end_of_input();
                    send_all(&coop, &peers, &*vehicle, &mut next_header, out).await;
                }
                if ending.is_some_and(|end| tokio::time::Instant::now() >= end) {
                    let out = core.run_pending();
                    send_all(&coop, &peers, &*vehicle, &mut next_header, out).await;
                    break;
                }
                beats += 1;
                if beats % 4 != 1 {
                    continue; // heartbeat at 1 Hz, idle checks at 4 Hz
                }
                let hb = heartbeat();
                let _ = vehicle.send(&next_header(), &hb).await;
                let frame = wire::to_frame(next_header(), &hb);
                for p in &peers {
                    let _ = coop.send_to(&frame, p).await;
                }
                continue;
            }
            frame = vrx.recv() => {
                let Some((header, msg)) = frame else { anyhow::bail!("vehicle link closed") };
                summary_counts.0 += 1;
                last_vehicle = tokio::time::Instant::now();
                heard_vehicle = true;
                if header.system_id != u32::from(id) {
                    summary_counts.1 += 1;
                    continue;
                }
                let input = match &msg {
                    MavMessage::HIGHRES_IMU(m) => wire::imu_from_highres(m).map(NodeInput::Imu).map_err(|e| e.to_string()),
                    MavMessage::ODOMETRY(m) => wire::odometer_from_odometry(m).map(NodeInput::Odometer).map_err(|e| e.to_string()),
                    MavMessage::COOPLOC_RANGE(m) => wire::range_from_message(m).map(|(epoch, range)| NodeInput::OwnRange { epoch, range }).map_err(|e| e.to_string()),
                    _ => continue,
                };
                match input {
                    Ok(i) => vec![i],
                    Err(e) => {
                        summary_counts.1 += 1;
                        tracing::debug!(platform = id, error = %e, "vehicle message dropped");
                        continue;
                    }
                }
            }
            r = coop.recv_from(&mut buf) => {
                let Ok((n, from)) = r else { continue };
                summary_counts.2 += 1;
                let frames = wire::frames(&buf[..n]);
                if frames.is_empty() {
                    summary_counts.3 += 1;
                    tracing::debug!(platform = id, %from, bytes = n, "cooperative datagram without a valid frame dropped");
                    continue;
                }
                let mut inputs = Vec::with_capacity(frames.len());
                for (header, msg) in frames {
                    if header.system_id == u32::from(id) {
                        continue; // our own traffic, looped back
                    }
                    if peers.insert(from) {
                        tracing::info!(platform = id, peer = %from, sysid = header.system_id, "new peer");
                    }
                    inputs.push(NodeInput::Peer(Box::new(msg)));
                }
                inputs
            }
        };
        for input in inputs {
            let out = core.handle(input);
            send_all(&coop, &peers, &*vehicle, &mut next_header, out).await;
        }
    }
    reader.abort();
    Ok(NodeSummary {
        stats: core.stats.clone(),
        estimate: core.estimate(),
        vehicle_frames: summary_counts.0,
        vehicle_rejected: summary_counts.1,
        coop_frames: summary_counts.2,
        coop_rejected: summary_counts.3,
        peers: peers.into_iter().collect(),
    })
}
