//! `cooploc sitl` end to end: the simulator on 127.0.0.1 with ephemeral ports, in-process as a
//! tokio task (and once as the real binary), against plain UDP client sockets. Assertions are on
//! what arrives (decoded values, simulated timestamps, counts), never on timing; every wait is
//! bounded.

mod common;

use std::net::SocketAddr;
use std::time::Duration;

use cooploc::estimation::PlatformId;
use cooploc::protocol::MavMessage;
use cooploc::protocol::dialect::cooploc::{
    COMMAND_LONG_DATA, HEARTBEAT_DATA, MavAutopilot, MavCmd, MavResult, MavState, MavType,
};
use cooploc::protocol::wire::{self, GeoOrigin};
use cooploc::simulator::{BoundEndpoint, Interval, SimReport, Simulator, SitlConfig, Speed, StopReason, StreamDefaults};
use cooploc::sitl::{Scenario, World};
use cooploc::time::TimeUs;
use mavlink_core::MavHeader;
use tokio::net::UdpSocket;
use tokio::sync::oneshot;
use tokio::task::JoinHandle;

/// Three vehicles, 3 s, IMU 200 Hz, odometer 10 Hz, ranging every second.
const TINY: &str = r#"
name = "tiny"
duration_s = 3.0
latitude_deg = 34.7
gravity_m_s2 = 9.80665
truth_rate_hz = 10.0

[sensors]
imu_rate_hz = 200.0
accel_bias_ug = 500.0
accel_noise_ug_per_sqrt_hz = 100.0
gyro_bias_deg_h = 3.0
gyro_arw_deg_per_sqrt_h = 1.2
odometer_rate_hz = 10.0
odometer_sigma_m_s = 0.2
odometer_scale_sigma = 0.01

[ranging]
sigma_m = 0.1
[[ranging.schedules]]
name = "1hz"
every_s = 1.0
start_s = 1.0

[initial]
position_sigma_m = 0.1
velocity_sigma_m_s = 0.05
roll_pitch_sigma_deg = 0.01
yaw_sigma_deg = 0.05

[filter]
nhc_lateral_sigma_m_s = 0.1
nhc_vertical_sigma_m_s = 0.1

[[platforms]]
id = 1
start_ned_m = [0.0, 0.0, 0.0]
start_yaw_deg = 30.0
start_speed_m_s = 10.0
segments = [{ duration_s = 3.0, accel_m_s2 = 0.5, yaw_rate_deg_s = 4.0 }]

[[platforms]]
id = 2
start_ned_m = [50.0, -80.0, -1.0]
start_yaw_deg = 170.0
start_speed_m_s = 8.0
segments = [{ duration_s = 3.0, accel_m_s2 = 0.2, yaw_rate_deg_s = -3.0 }]

[[platforms]]
id = 3
start_ned_m = [-120.0, 40.0, 0.0]
start_yaw_deg = -60.0
start_speed_m_s = 9.0
segments = [{ duration_s = 3.0, accel_m_s2 = 0.0, yaw_rate_deg_s = 0.0 }]
"#;

const SEED: u64 = 7;
const RUN: u32 = 2;
const TIMEOUT: Duration = Duration::from_secs(30);

fn world() -> World {
    World::new(&Scenario::from_toml_str(TINY).unwrap()).unwrap()
}

fn config(world: &World, speed: Speed) -> SitlConfig {
    SitlConfig {
        schedule: "1hz".into(),
        seed: SEED,
        run: RUN,
        speed,
        endpoints: cooploc::simulator::default_endpoints(&world.platform_ids(), "127.0.0.1".parse().unwrap(), 0).unwrap(),
        wait_for_peers: true,
        streams: StreamDefaults::default(),
        origin_lon_deg: 10.0,
        link_loss: 0.0,
        autopilot: Default::default(),
        origin: None,
        stream_rates: Vec::new(),
        gnss_time: false,
        gnss_lost_at: None,
        gnss_back_at: None,
        gnss_glitch_m: None,
    }
}

/// A client socket with a large receive buffer (the simulator at full speed outruns a reader).
fn client_socket() -> UdpSocket {
    let s = socket2::Socket::new(socket2::Domain::IPV4, socket2::Type::DGRAM, None).unwrap();
    let _ = s.set_recv_buffer_size(4 << 20);
    // A whole 3 s run of one vehicle (~700 frames) must fit: Linux caps the size at
    // net.core.rmem_max (4 MiB on the machines we test on).
    assert!(s.recv_buffer_size().unwrap() >= 1 << 20, "raise net.core.rmem_max to at least 1 MiB for these tests");
    s.bind(&"127.0.0.1:0".parse::<SocketAddr>().unwrap().into()).unwrap();
    s.set_nonblocking(true).unwrap();
    UdpSocket::from_std(s.into()).unwrap()
}

const GCS: MavHeader = MavHeader { system_id: 255, component_id: 190, sequence: 0 };

fn frame(msg: &MavMessage) -> Vec<u8> {
    wire::to_frame(GCS, msg)
}

fn gcs_heartbeat() -> MavMessage {
    MavMessage::HEARTBEAT(HEARTBEAT_DATA {
        mavtype: MavType::MAV_TYPE_GCS,
        autopilot: MavAutopilot::MAV_AUTOPILOT_INVALID,
        system_status: MavState::MAV_STATE_ACTIVE,
        mavlink_version: 3,
        ..Default::default()
    })
}

fn command(target: u8, command: MavCmd, param1: f32, param2: f32) -> MavMessage {
    MavMessage::COMMAND_LONG(COMMAND_LONG_DATA {
        command,
        param1,
        param2,
        target_system: target,
        target_component: 1,
        ..Default::default()
    })
}

struct Started {
    endpoints: Vec<(PlatformId, SocketAddr)>,
    handle: JoinHandle<SimReport>,
    _stop: oneshot::Sender<()>,
}

async fn start(world: World, config: SitlConfig) -> Started {
    let sim = Simulator::bind(world, config).await.unwrap();
    let endpoints = sim
        .endpoints()
        .into_iter()
        .map(|(id, e)| match e {
            BoundEndpoint::Udp { local, .. } => {
                assert_ne!(local.port(), 0);
                (id, local)
            }
            other => panic!("unexpected endpoint {other}"),
        })
        .collect();
    let (stop, stopped) = oneshot::channel::<()>();
    let handle = tokio::spawn(async move {
        sim.run(async {
            let _ = stopped.await;
        })
        .await
        .unwrap()
    });
    Started { endpoints, handle, _stop: stop }
}

/// Frames received in a datagram but not yet returned, per client socket (the simulator puts
/// several stream frames in one datagram, as PX4 does).
type Queued = std::collections::VecDeque<(MavHeader, MavMessage)>;
static PENDING: std::sync::Mutex<Vec<(std::net::SocketAddr, Queued)>> = std::sync::Mutex::new(Vec::new());

fn pending_pop(sock: &UdpSocket) -> Option<(MavHeader, MavMessage)> {
    let addr = sock.local_addr().unwrap();
    PENDING.lock().unwrap().iter_mut().find(|(a, _)| *a == addr).and_then(|(_, q)| q.pop_front())
}

/// Every frame of one datagram: all of it must be valid frames.
fn datagram_frames(bytes: &[u8]) -> Vec<(MavHeader, MavMessage)> {
    let frames = wire::frames(bytes);
    let len: usize = frames.iter().map(|(h, m)| wire::to_frame(*h, m).len()).sum();
    assert!(!frames.is_empty() && len == bytes.len(), "a datagram of {} bytes with {} bytes of valid frames", bytes.len(), len);
    frames
}

/// Receives one frame (bounded wait).
async fn recv(sock: &UdpSocket) -> (MavHeader, MavMessage) {
    if let Some(f) = pending_pop(sock) {
        return f;
    }
    let mut buf = [0u8; 2048];
    let (n, _) = tokio::time::timeout(TIMEOUT, sock.recv_from(&mut buf)).await.expect("a frame within the timeout").unwrap();
    let mut frames = std::collections::VecDeque::from(datagram_frames(&buf[..n]));
    let first = frames.pop_front().unwrap();
    let addr = sock.local_addr().unwrap();
    let mut pending = PENDING.lock().unwrap();
    match pending.iter_mut().find(|(a, _)| *a == addr) {
        Some((_, q)) => q.extend(frames),
        None => pending.push((addr, frames)),
    }
    first
}

/// Receives until `pred` matches, returning everything received (bounded).
async fn recv_until(sock: &UdpSocket, mut pred: impl FnMut(&MavMessage) -> bool) -> Vec<(MavHeader, MavMessage)> {
    let mut got = Vec::new();
    loop {
        let f = recv(sock).await;
        let done = pred(&f.1);
        got.push(f);
        if done {
            return got;
        }
    }
}

/// Everything already queued on the socket (the simulator has finished: loopback delivery is
/// complete when `send_to` returns).
fn drain(sock: &UdpSocket) -> Vec<(MavHeader, MavMessage)> {
    let mut buf = [0u8; 2048];
    let mut got = Vec::new();
    while let Some(f) = pending_pop(sock) {
        got.push(f);
    }
    loop {
        match sock.try_recv_from(&mut buf) {
            Ok((n, _)) => got.extend(datagram_frames(&buf[..n])),
            Err(e) if e.kind() == std::io::ErrorKind::WouldBlock => return got,
            Err(e) => panic!("{e}"),
        }
    }
}

fn ack_of(m: &MavMessage) -> Option<(MavCmd, MavResult)> {
    match m {
        MavMessage::COMMAND_ACK(a) => Some((a.command, a.result)),
        _ => None,
    }
}

/// Reads frames until a COMMAND_ACK and returns it with what followed it up to the next
/// non-reply frame is not needed: the ACK and the frames received before it.
async fn expect_ack(sock: &UdpSocket) -> (MavCmd, MavResult) {
    let got = recv_until(sock, |m| ack_of(m).is_some()).await;
    ack_of(&got.last().unwrap().1).unwrap()
}

#[test]
fn geodetic_conversion_round_trips_to_the_millimetre() {
    let origin = GeoOrigin { lat_deg: 34.7, lon_deg: 10.0, alt_m: 0.0 };
    for ned in [[0.0, 0.0, 0.0], [3000.0, -2500.0, -1.0], [-4000.0, 4000.0, 2.0]] {
        let ned = nalgebra::Vector3::from(ned);
        let g = wire::ned_to_geodetic(&origin, &ned);
        assert!((wire::geodetic_to_ned(&origin, &g) - ned).norm() < 1e-6);
        // Through the 1e-7 deg integers: about a centimetre.
        let q = wire::Geodetic {
            lat_deg: wire::e7_to_deg(wire::deg_to_e7(g.lat_deg)),
            lon_deg: wire::e7_to_deg(wire::deg_to_e7(g.lon_deg)),
            ..g
        };
        assert!((wire::geodetic_to_ned(&origin, &q) - ned).norm() < 0.015);
    }
    // 1 km north is 1/111.3 deg of latitude.
    let g = wire::ned_to_geodetic(&origin, &nalgebra::Vector3::new(1000.0, 0.0, 0.0));
    assert!((g.lat_deg - 34.7 - 1000.0 / 111_319.49).abs() < 1e-6);
    // Longitudes wrap.
    let far = GeoOrigin { lon_deg: 179.9999, ..origin };
    let g = wire::ned_to_geodetic(&far, &nalgebra::Vector3::new(0.0, 100.0, 0.0));
    assert!(g.lon_deg < -179.0);
    assert!((wire::geodetic_to_ned(&far, &g)[1] - 100.0).abs() < 1e-6);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn every_vehicle_streams_exactly_its_world_samples() {
    let world = world();
    let started = start(world.clone(), config(&world, Speed::Max)).await;
    let mut clients = Vec::new();
    for &(id, addr) in &started.endpoints {
        let sock = client_socket();
        if id == 1 {
            // Garbage first: counted, ignored, and not taken for a peer.
            sock.send_to(b"hello, this is not MAVLink", addr).await.unwrap();
            sock.send_to(&[0xFD, 9, 0, 0, 0, 1, 1, 0, 0, 0, 1, 2, 3], addr).await.unwrap();
        }
        sock.send_to(&frame(&gcs_heartbeat()), addr).await.unwrap();
        clients.push((id, sock));
    }
    let report = tokio::time::timeout(TIMEOUT, started.handle).await.expect("the run ends").unwrap();
    assert_eq!(report.reason, StopReason::EndOfScenario);
    assert_eq!(report.sim_time, TimeUs(3_000_000));

    let inputs = world.run_inputs(SEED, RUN);
    let ranges = world.ranges("1hz", SEED, RUN).unwrap();
    let origin = GeoOrigin { lat_deg: 34.7, lon_deg: 10.0, alt_m: 0.0 };
    let mut ranges_seen = 0;
    for (id, sock) in &clients {
        let frames = drain(sock);
        let p = inputs.platforms.iter().find(|p| p.id == *id).unwrap();
        // Headers: this vehicle's sysid, compid 1, sequence numbers without a gap.
        for (k, (h, _)) in frames.iter().enumerate() {
            assert_eq!((h.system_id, h.component_id), (u32::from(*id), 1));
            assert_eq!(h.sequence, frames[0].0.sequence.wrapping_add(k as u8), "frame {k} of vehicle {id}");
        }
        let heartbeats: Vec<&HEARTBEAT_DATA> = frames
            .iter()
            .filter_map(|(_, m)| match m {
                MavMessage::HEARTBEAT(h) => Some(h),
                _ => None,
            })
            .collect();
        assert_eq!(heartbeats.len(), 4, "t = 0, 1, 2, 3 s");
        for h in heartbeats {
            assert_eq!(h.mavtype, MavType::MAV_TYPE_GROUND_ROVER);
            assert_eq!(h.system_status, MavState::MAV_STATE_ACTIVE);
        }
        let imu: Vec<_> = frames
            .iter()
            .filter_map(|(_, m)| match m {
                MavMessage::HIGHRES_IMU(d) => Some(wire::imu_from_highres(d).unwrap()),
                _ => None,
            })
            .collect();
        let want: Vec<_> = p.imu.iter().map(wire::imu_as_sent).collect();
        assert_eq!(imu.len(), 600);
        assert_eq!(imu, want, "vehicle {id}: HIGHRES_IMU = the world's IMU samples as f32, in order");
        let odo: Vec<_> = frames
            .iter()
            .filter_map(|(_, m)| match m {
                MavMessage::ODOMETRY(d) => Some(wire::odometer_from_odometry(d).unwrap()),
                _ => None,
            })
            .collect();
        assert_eq!(odo, p.odometer.iter().map(wire::odometer_as_sent).collect::<Vec<_>>());
        assert_eq!(odo.len(), 30);
        let got_ranges: Vec<_> = frames
            .iter()
            .filter_map(|(_, m)| match m {
                MavMessage::COOPLOC_RANGE(d) => Some(wire::range_from_message(d).unwrap()),
                _ => None,
            })
            .collect();
        let want_ranges: Vec<_> = ranges
            .iter()
            .enumerate()
            .flat_map(|(k, (_, rs))| rs.iter().filter(|r| r.from == *id).map(move |r| (k as u32 + 1, wire::range_as_sent(r))))
            .collect();
        ranges_seen += got_ranges.len();
        assert_eq!(got_ranges, want_ranges, "vehicle {id}: the ranges its radio measured, epochs from 1");
        // SIM_STATE at 10 Hz from t = 0: truth at k * 100 ms, to the centimetre of 1e-7 deg.
        let traj = world.trajectory(*id).unwrap();
        let sims: Vec<_> = frames
            .iter()
            .filter_map(|(_, m)| match m {
                MavMessage::SIM_STATE(d) => Some(d.clone()),
                _ => None,
            })
            .collect();
        assert_eq!(sims.len(), 31);
        for (k, s) in sims.iter().enumerate() {
            let truth = traj.truth_at(TimeUs(k as u64 * 100_000));
            let pos = wire::sim_state_position_ned(s, &origin).unwrap();
            assert!((pos - truth.pos_ned_m).norm() < 0.02, "vehicle {id} SIM_STATE {k}: {pos} vs {}", truth.pos_ned_m);
            assert!(((s.vn as f64) - truth.vel_ned_m_s[0]).abs() < 1e-4);
            assert!(((s.yaw as f64) - truth.yaw_rad).abs() < 1e-5);
            assert!((s.q1 as f64 - truth.attitude.w).abs() < 1e-6);
        }
        let v = report.vehicles.iter().find(|v| v.platform == *id).unwrap();
        assert_eq!(v.counters.frames_sent as usize, frames.len());
        assert_eq!(v.counters.malformed, if *id == 1 { 2 } else { 0 }, "vehicle {id}");
        assert_eq!(v.counters.frames_received, 1);
        assert_eq!(v.link.unrouted, 0);
    }
    // Each range of each epoch went out once, from the vehicle that measured it.
    assert_eq!(ranges_seen, ranges.iter().map(|(_, r)| r.len()).sum::<usize>());
    assert_eq!(ranges_seen, 9);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn commands_are_acknowledged_and_change_the_streams() {
    let world = world();
    let started = start(world.clone(), config(&world, Speed::Max)).await;
    let (a1, a2) = (started.endpoints[0].1, started.endpoints[1].1);
    let (c1, c2, c3) = (client_socket(), client_socket(), client_socket());
    // The clock holds at zero until all three vehicles have a peer: vehicle 1 is configured first.
    let send = async |msg: MavMessage| c1.send_to(&frame(&msg), a1).await.unwrap();
    send(command(1, MavCmd::MAV_CMD_SET_MESSAGE_INTERVAL, 105.0, 20_000.0)).await;
    assert_eq!(expect_ack(&c1).await, (MavCmd::MAV_CMD_SET_MESSAGE_INTERVAL, MavResult::MAV_RESULT_ACCEPTED));
    send(command(1, MavCmd::MAV_CMD_SET_MESSAGE_INTERVAL, 108.0, -1.0)).await;
    assert_eq!(expect_ack(&c1).await.1, MavResult::MAV_RESULT_ACCEPTED, "SIM_STATE disabled");
    // Absurd or unsupported requests are refused, never acted on.
    for (id, interval, why) in [
        (105.0, -5.0, "negative interval other than -1"),
        (105.0, f32::NAN, "NaN interval"),
        (105.0, 1e12, "beyond i32 microseconds"),
        (108.0, 10.0, "a clock-driven stream above 1 kHz"),
        (0.0, 100_000.0, "HEARTBEAT stays at 1 Hz"),
        (9999.0, 100_000.0, "not a stream of this vehicle"),
        (105.5, 100_000.0, "not a message id"),
    ] {
        send(command(1, MavCmd::MAV_CMD_SET_MESSAGE_INTERVAL, id, interval)).await;
        assert_eq!(expect_ack(&c1).await.1, MavResult::MAV_RESULT_DENIED, "{why}");
    }
    send(command(1, MavCmd::MAV_CMD_NAV_WAYPOINT, 0.0, 0.0)).await;
    assert_eq!(expect_ack(&c1).await, (MavCmd::MAV_CMD_NAV_WAYPOINT, MavResult::MAV_RESULT_UNSUPPORTED));
    // Addressed to another system: no answer (the next ACK is the one of the request below).
    send(command(2, MavCmd::MAV_CMD_SET_MESSAGE_INTERVAL, 105.0, -1.0)).await;
    // REQUEST_MESSAGE: AUTOPILOT_VERSION, the interval just set, SIM_STATE now (t = 0), an IMU
    // sample before there is one.
    send(command(1, MavCmd::MAV_CMD_REQUEST_MESSAGE, 148.0, 0.0)).await;
    let (h, m) = recv(&c1).await;
    assert_eq!(ack_of(&m), Some((MavCmd::MAV_CMD_REQUEST_MESSAGE, MavResult::MAV_RESULT_ACCEPTED)));
    assert_eq!((h.system_id, h.component_id), (1, 1));
    let MavMessage::COMMAND_ACK(ack) = &m else { unreachable!() };
    assert_eq!((ack.target_system, ack.target_component), (255, 190));
    assert!(matches!(recv(&c1).await.1, MavMessage::AUTOPILOT_VERSION(_)));
    send(command(1, MavCmd::MAV_CMD_REQUEST_MESSAGE, 244.0, 105.0)).await;
    assert_eq!(expect_ack(&c1).await.1, MavResult::MAV_RESULT_ACCEPTED);
    match recv(&c1).await.1 {
        MavMessage::MESSAGE_INTERVAL(i) => assert_eq!((i.message_id, i.interval_us), (105, 20_000)),
        other => panic!("{other:?}"),
    }
    send(command(1, MavCmd::MAV_CMD_REQUEST_MESSAGE, 108.0, 0.0)).await;
    assert_eq!(expect_ack(&c1).await.1, MavResult::MAV_RESULT_ACCEPTED);
    let MavMessage::SIM_STATE(s) = recv(&c1).await.1 else { panic!("SIM_STATE expected") };
    let origin = GeoOrigin { lat_deg: 34.7, lon_deg: 10.0, alt_m: 0.0 };
    let truth0 = world.trajectory(1).unwrap().truth_at(TimeUs(0));
    assert!((wire::sim_state_position_ned(&s, &origin).unwrap() - truth0.pos_ned_m).norm() < 0.02);
    send(command(1, MavCmd::MAV_CMD_REQUEST_MESSAGE, 105.0, 0.0)).await;
    assert_eq!(expect_ack(&c1).await.1, MavResult::MAV_RESULT_TEMPORARILY_REJECTED, "no IMU sample yet");
    // Now the other vehicles get their peers and the clock starts.
    c2.send_to(&frame(&gcs_heartbeat()), a2).await.unwrap();
    c3.send_to(&frame(&gcs_heartbeat()), started.endpoints[2].1).await.unwrap();
    let report = tokio::time::timeout(TIMEOUT, started.handle).await.expect("the run ends").unwrap();

    let frames = drain(&c1);
    let t: Vec<u64> = frames
        .iter()
        .filter_map(|(_, m)| match m {
            MavMessage::HIGHRES_IMU(d) => Some(d.time_usec),
            _ => None,
        })
        .collect();
    // The first sample, then every 20 ms: 151 of the 600.
    assert_eq!(t[0], 5_000);
    assert!(t[1..].windows(2).all(|w| w[1] - w[0] == 20_000), "{t:?}");
    assert_eq!((t[1], t.len()), (20_000, 151));
    assert!(!frames.iter().any(|(_, m)| matches!(m, MavMessage::SIM_STATE(_))), "SIM_STATE disabled on vehicle 1");
    let others = drain(&c2);
    assert_eq!(others.iter().filter(|(_, m)| matches!(m, MavMessage::HIGHRES_IMU(_))).count(), 600, "vehicle 2 unchanged");
    assert_eq!(others.iter().filter(|(_, m)| matches!(m, MavMessage::SIM_STATE(_))).count(), 31);
    let v1 = &report.vehicles[0];
    assert_eq!(v1.counters.commands_accepted, 5);
    assert_eq!(v1.counters.commands_rejected, 8);
    assert_eq!(v1.counters.commands_unsupported, 1);
    assert_eq!(v1.counters.ignored, 1, "the command for system 2");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn interval_change_mid_run_takes_effect_from_the_next_sample() {
    let world = world();
    let started = start(world.clone(), config(&world, Speed::Factor(2.0))).await;
    let clients: Vec<UdpSocket> = (0..3).map(|_| client_socket()).collect();
    for (c, (_, addr)) in clients.iter().zip(&started.endpoints) {
        c.send_to(&frame(&gcs_heartbeat()), *addr).await.unwrap();
    }
    let c1 = &clients[0];
    let a1 = started.endpoints[0].1;
    // Default rate first: 40 samples 5 ms apart.
    let mut before = Vec::new();
    while before.len() < 40 {
        if let MavMessage::HIGHRES_IMU(d) = recv(c1).await.1 {
            before.push(d.time_usec);
        }
    }
    assert!(before.windows(2).all(|w| w[1] - w[0] == 5_000));
    c1.send_to(&frame(&command(1, MavCmd::MAV_CMD_SET_MESSAGE_INTERVAL, 105.0, 50_000.0)), a1).await.unwrap();
    let upto_ack = recv_until(c1, |m| ack_of(m).is_some()).await;
    assert_eq!(ack_of(&upto_ack.last().unwrap().1), Some((MavCmd::MAV_CMD_SET_MESSAGE_INTERVAL, MavResult::MAV_RESULT_ACCEPTED)));
    let last_before = upto_ack
        .iter()
        .filter_map(|(_, m)| match m {
            MavMessage::HIGHRES_IMU(d) => Some(d.time_usec),
            _ => None,
        })
        .chain(before.last().copied())
        .max()
        .unwrap();
    let report = tokio::time::timeout(TIMEOUT, started.handle).await.expect("the run ends").unwrap();
    assert_eq!(report.reason, StopReason::EndOfScenario);
    let after: Vec<u64> = drain(c1)
        .iter()
        .filter_map(|(_, m)| match m {
            MavMessage::HIGHRES_IMU(d) => Some(d.time_usec),
            _ => None,
        })
        .collect();
    assert!(!after.is_empty(), "the command arrived before the end of the run");
    assert_eq!(after[0], last_before + 50_000, "20 Hz from the last sample sent at 200 Hz");
    assert!(after.windows(2).all(|w| w[1] - w[0] == 50_000), "{after:?}");
}

#[test]
fn sitl_binary_prints_its_endpoints_serves_and_stops_at_the_end() {
    use std::io::{BufRead, BufReader};
    let dir = std::env::temp_dir().join(format!("cooploc-sitl-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let path = dir.join("tiny.toml");
    std::fs::write(&path, TINY).unwrap();
    let bin = env!("CARGO_BIN_EXE_cooploc");

    // Validation before any I/O: each error names the bad argument.
    for (args, needle) in [
        (vec!["--speed=-1"], "--speed"),
        (vec!["--speed", "fast"], "--speed"),
        (vec!["--vehicle", "9=udpout:127.0.0.1:14550"], "platform 9"),
        (vec!["--vehicle", "1=tcp:127.0.0.1:1"], "--vehicle"),
        (vec!["--serial", "1=/dev/null:fast"], "--serial"),
        (vec!["--base-port", "65534"], "--base-port"),
        (vec!["--schedule", "never"], "never"),
        (vec!["--sim-state-hz=-3"], "--sim-state-hz"),
    ] {
        let out = std::process::Command::new(bin).arg("sitl").arg(&path).args(&args).output().unwrap();
        assert!(!out.status.success(), "{args:?}");
        let err = String::from_utf8_lossy(&out.stderr);
        assert!(err.contains(needle), "{args:?}: {err}");
    }

    let mut child = std::process::Command::new(bin)
        .arg("sitl")
        .arg(&path)
        .args(["--base-port", "0", "--speed", "max", "--wait-for-peers", "--seed", "7", "--run", "2"])
        .stdout(std::process::Stdio::piped())
        .stderr(std::process::Stdio::null())
        .spawn()
        .unwrap();
    let (tx, rx) = std::sync::mpsc::channel();
    let stdout = child.stdout.take().unwrap();
    std::thread::spawn(move || {
        for line in BufReader::new(stdout).lines() {
            if tx.send(line.unwrap()).is_err() {
                return;
            }
        }
    });
    let mut endpoints = Vec::new();
    while endpoints.len() < 3 {
        let line = rx.recv_timeout(TIMEOUT).expect("the endpoints are printed");
        let words: Vec<&str> = line.split_whitespace().collect();
        if let ["vehicle", id, "udp", addr] = words[..] {
            endpoints.push((id.parse::<u8>().unwrap(), addr.parse::<SocketAddr>().unwrap()));
        }
    }
    assert_eq!(endpoints.iter().map(|e| e.0).collect::<Vec<_>>(), vec![1, 2, 3]);
    let rt = tokio::runtime::Builder::new_current_thread().enable_all().build().unwrap();
    rt.block_on(async {
        let socks: Vec<UdpSocket> = (0..3).map(|_| client_socket()).collect();
        for (s, (_, addr)) in socks.iter().zip(&endpoints) {
            s.send_to(&frame(&gcs_heartbeat()), *addr).await.unwrap();
        }
        for (s, (id, _)) in socks.iter().zip(&endpoints) {
            let (h, m) = recv_until(s, |m| matches!(m, MavMessage::HEARTBEAT(_))).await.pop().unwrap();
            assert_eq!((h.system_id, h.component_id), (u32::from(*id), 1));
            let MavMessage::HEARTBEAT(hb) = m else { unreachable!() };
            assert_eq!(hb.mavtype, MavType::MAV_TYPE_GROUND_ROVER);
        }
    });
    // End of the scenario: a clean exit with a summary per vehicle.
    let mut summary = Vec::new();
    while let Ok(line) = rx.recv_timeout(TIMEOUT) {
        summary.push(line);
    }
    let status = child.wait().unwrap();
    assert!(status.success());
    assert!(summary.iter().any(|l| l.starts_with("stopped: EndOfScenario")), "{summary:?}");
    assert!(summary.iter().any(|l| l.starts_with("vehicle 1 sent") && l.contains("highres_imu 600")), "{summary:?}");
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn stream_defaults_are_every_sample_and_10_hz_truth() {
    let d = StreamDefaults::default();
    assert_eq!(d.highres_imu, Interval::EverySample);
    assert_eq!(d.sim_state, Interval::Every(100_000));
}

/// Reads frames from a blocking byte stream until `pred` matches (bounded by TIMEOUT).
fn read_until<R: std::io::Read>(
    reader: &mut mavlink_core::MavlinkReader<R>,
    mut pred: impl FnMut(&MavMessage) -> bool,
) -> Vec<(MavHeader, MavMessage)> {
    let deadline = std::time::Instant::now() + TIMEOUT;
    let mut got = Vec::new();
    while std::time::Instant::now() < deadline {
        match reader.read_any_message::<MavMessage>() {
            Ok(f) => {
                let done = pred(&f.1);
                got.push(f);
                if done {
                    return got;
                }
            }
            // The port's read timeout: try again until the deadline.
            Err(mavlink_core::error::MessageReadError::Io(e)) if e.kind() == std::io::ErrorKind::TimedOut => {}
            Err(e) => panic!("{e}"),
        }
    }
    panic!("nothing matched within {TIMEOUT:?}");
}

#[cfg(unix)]
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_vehicle_on_a_pseudo_terminal_streams_and_answers_commands_and_ctrl_c_stops_the_run() {
    use serialport::SerialPort;
    use std::io::Write;
    let (master, slave) = serialport::TTYPort::pair().expect("a pseudo-terminal pair");
    let path = slave.name().expect("the slave's path");
    let world = world();
    let mut cfg = config(&world, Speed::Factor(1.0));
    cfg.wait_for_peers = false;
    cfg.endpoints[0].1 = cooploc::simulator::Endpoint::Serial { path: path.clone(), baud: 921_600 };
    let sim = Simulator::bind(world.clone(), cfg).await.unwrap();
    assert_eq!(sim.endpoints()[0].1.to_string(), format!("serial {path} 921600"));
    let (stop, stopped) = oneshot::channel::<()>();
    let handle = tokio::spawn(sim.run(async {
        let _ = stopped.await;
    }));
    let client = tokio::task::spawn_blocking(move || {
        let mut writer = master.try_clone_native().unwrap();
        let mut reader = mavlink_core::MavlinkReader::new(master);
        let got = read_until(&mut reader, |m| matches!(m, MavMessage::HEARTBEAT(_)));
        let (h, _) = got.last().unwrap();
        assert_eq!((h.system_id, h.component_id), (1, 1));
        // Garbage on the line, then a command: the garbage is skipped.
        writer.write_all(b"\x00\xff line noise \xfd\x03").unwrap();
        writer.write_all(&frame(&command(1, MavCmd::MAV_CMD_SET_MESSAGE_INTERVAL, 105.0, 100_000.0))).unwrap();
        let got = read_until(&mut reader, |m| ack_of(m).is_some());
        assert_eq!(ack_of(&got.last().unwrap().1), Some((MavCmd::MAV_CMD_SET_MESSAGE_INTERVAL, MavResult::MAV_RESULT_ACCEPTED)));
        // Then 10 Hz IMU.
        let mut t = Vec::new();
        read_until(&mut reader, |m| {
            if let MavMessage::HIGHRES_IMU(d) = m {
                t.push(d.time_usec);
            }
            t.len() == 3
        });
        assert!(t.windows(2).all(|w| w[1] - w[0] == 100_000), "{t:?}");
    });
    tokio::time::timeout(TIMEOUT, client).await.expect("the client finishes").unwrap();
    stop.send(()).unwrap();
    let report = tokio::time::timeout(TIMEOUT, handle).await.expect("the run stops").unwrap().unwrap();
    assert_eq!(report.reason, StopReason::Shutdown);
    assert!(report.sim_time < TimeUs(3_000_000));
    let v1 = &report.vehicles[0];
    assert_eq!(v1.counters.commands_accepted, 1);
    assert_eq!(v1.link.dropped, 0);
}

/// pymavlink (an independent implementation, its own common.xml) as a `udpout` client: it sees
/// the vehicle's HEARTBEAT, gets its SET_MESSAGE_INTERVAL acknowledged, and the rate changes.
const PYMAVLINK_CLIENT: &str = r#"
import os, sys
os.environ["MAVLINK20"] = "1"
from pymavlink import mavutil
m = mavutil.mavlink_connection("udpout:" + sys.argv[1], source_system=255, source_component=190)
m.mav.heartbeat_send(mavutil.mavlink.MAV_TYPE_GCS, mavutil.mavlink.MAV_AUTOPILOT_INVALID, 0, 0, 0)
hb = m.recv_match(type="HEARTBEAT", blocking=True, timeout=20)
assert hb is not None and hb.get_srcSystem() == 1 and hb.get_srcComponent() == 1 and hb.type == 10, hb
m.mav.command_long_send(1, 1, mavutil.mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, 0, 105, 50000, 0, 0, 0, 0, 0)
last = None
while True:
    msg = m.recv_match(blocking=True, timeout=20)
    assert msg is not None, "no COMMAND_ACK"
    if msg.get_type() == "COMMAND_ACK":
        assert msg.command == 511 and msg.result == 0 and msg.target_system == 255, msg
        break
    if msg.get_type() == "HIGHRES_IMU":
        last = msg.time_usec
after = []
while len(after) < 5:
    msg = m.recv_match(type="HIGHRES_IMU", blocking=True, timeout=20)
    assert msg is not None, "no HIGHRES_IMU after the ACK"
    after.append(msg.time_usec)
times = ([last] if last is not None else []) + after
assert all(b - a == 50000 for a, b in zip(times, times[1:])), times
print("ok", after[0])
"#;

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn pymavlink_connects_with_udpout_and_a_listener_gets_udpout_targets() {
    let Some(python) = common::python("the pymavlink client") else { return };
    let world = world();
    // Vehicles 2 and 3 stream to a listener that never sends (their `udpout` target).
    let listener = client_socket();
    let mut cfg = config(&world, Speed::Factor(2.0));
    for (_, e) in cfg.endpoints.iter_mut().skip(1) {
        let cooploc::simulator::Endpoint::Udp { targets, .. } = e else { unreachable!() };
        targets.push(listener.local_addr().unwrap());
    }
    let started = start(world, cfg).await;
    let port = started.endpoints[0].1.to_string();
    // The script bounds each of its own waits.
    let out = tokio::task::spawn_blocking(move || {
        std::process::Command::new(&python).arg("-c").arg(PYMAVLINK_CLIENT).arg(&port).output().unwrap()
    });
    let out = tokio::time::timeout(TIMEOUT * 4, out).await.expect("pymavlink finishes").unwrap();
    assert!(out.status.success(), "{}{}", String::from_utf8_lossy(&out.stdout), String::from_utf8_lossy(&out.stderr));
    assert!(String::from_utf8_lossy(&out.stdout).starts_with("ok"));
    let report = tokio::time::timeout(TIMEOUT, started.handle).await.unwrap().unwrap();
    assert_eq!(report.vehicles[0].counters.commands_accepted, 1);
    let mut senders: Vec<u32> =
        drain(&listener).iter().filter(|(_, m)| matches!(m, MavMessage::HEARTBEAT(_))).map(|(h, _)| h.system_id).collect();
    senders.sort();
    assert_eq!(senders, vec![2, 2, 2, 2, 3, 3, 3, 3], "every heartbeat of vehicles 2 and 3, none of vehicle 1");
}

/// What a node does: the mavlink crate's own `udpout` connection (Rust, our dialect) to a
/// vehicle's port. It sends first; the vehicle then streams to it.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_mavlink_crates_udpout_connection_is_served() {
    use mavlink::AsyncMavConnection;
    let world = world();
    let mut cfg = config(&world, Speed::Factor(1.0));
    // Only vehicle 1 matters here; the others stream to nobody.
    cfg.wait_for_peers = false;
    let started = start(world, cfg).await;
    let conn = mavlink::connect_async::<MavMessage>(&format!("udpout:{}", started.endpoints[0].1)).await.unwrap();
    conn.send(&GCS, &gcs_heartbeat()).await.unwrap();
    conn.send(&GCS, &command(1, MavCmd::MAV_CMD_REQUEST_MESSAGE, 148.0, 0.0)).await.unwrap();
    let mut seen = (false, false, false);
    while !(seen.0 && seen.1 && seen.2) {
        let (h, m) = tokio::time::timeout(TIMEOUT, conn.recv()).await.expect("a frame").unwrap();
        assert_eq!(h.system_id, 1);
        match m {
            MavMessage::COMMAND_ACK(a) => {
                assert_eq!((a.command, a.result), (MavCmd::MAV_CMD_REQUEST_MESSAGE, MavResult::MAV_RESULT_ACCEPTED));
                seen.0 = true;
            }
            MavMessage::AUTOPILOT_VERSION(_) => seen.1 = true,
            MavMessage::HIGHRES_IMU(_) => seen.2 = true,
            _ => {}
        }
    }
}
