//! The whole system on loopback: `cooploc sitl` serves the paper scenario's three vehicles over
//! MAVLink (ephemeral ports, accelerated), three `cooploc node` processes run the decentralized
//! protocol among themselves over UDP with no hub, and each node's final estimate is compared with
//! `cooploc experiment`'s run of the same method on the same world, seed, run and schedule, fed the
//! samples as they went on the wire (f32). Stated tolerance: 1 mm in position.

use std::process::{Child, Command};
use std::sync::mpsc;
use std::time::Duration;

mod common;

use common::{Kill, LossyNet, spawn_lines, wait_line};

use cooploc::estimation::Method;
use cooploc::experiment::{initial_state, run_filter};
use cooploc::protocol::wire;
use cooploc::sitl::{PAPER_TOML, Scenario, World};

fn bin() -> Command {
    Command::new(env!("CARGO_BIN_EXE_cooploc"))
}

/// The numbers between the first `[` and `]` of a node's output line (its position).
fn bracket(line: &str) -> Vec<f64> {
    let inside = line.split('[').nth(1).unwrap().split(']').next().unwrap();
    inside.split(',').map(|v| v.trim().parse().unwrap()).collect()
}

/// Field `name` of a node's `stats` line (its `NodeStats`, Debug-printed).
fn stat(stats: &str, name: &str) -> u64 {
    stats.split(&format!("{name}: ")).nth(1).unwrap().split(|c: char| !c.is_ascii_digit()).next().unwrap().parse().unwrap()
}

/// Horizontal distance between a node's `done` line position and `truth` (NED, m).
fn horizontal_error(line: &str, truth: nalgebra::Vector3<f64>) -> f64 {
    let pos = bracket(line);
    ((truth[0] - pos[0]).powi(2) + (truth[1] - pos[1]).powi(2)).sqrt()
}

/// `cooploc sitl` on the paper scenario (seed 1, run 0) at 20x real time on ephemeral ports,
/// holding its clock until every vehicle has a peer, with `extra` arguments; the vehicles'
/// addresses by platform, and its output (kept open until the test ends).
fn start_sitl(
    world: &World,
    schedule: &str,
    extra: &[&str],
) -> (Child, mpsc::Receiver<String>, std::collections::BTreeMap<u16, String>) {
    let mut sitl = bin();
    sitl.args(["sitl", "sitl/scenarios/paper.toml", "--seed", "1", "--run", "0", "--schedule", schedule, "--speed", "20"]);
    sitl.args(["--base-port", "0", "--wait-for-peers", "--sim-state-hz", "1"]);
    sitl.args(extra);
    let (child, out) = spawn_lines(sitl);
    let mut vehicle_addr = std::collections::BTreeMap::new();
    for _ in world.platform_ids() {
        let line = wait_line(&out, "vehicle ", Duration::from_secs(30));
        let words: Vec<&str> = line.split_whitespace().collect();
        vehicle_addr.insert(words[1].parse::<u16>().unwrap(), words.last().unwrap().to_string());
    }
    (child, out, vehicle_addr)
}

/// The unsigned team (`--insecure`) under the same forger as the signed one below: the forged
/// records (100 m off, confident) are refused by the vetting (contradicted by the teammates'
/// ranges, or rivals of the genuine record) and every node ends where the clean experiment
/// does, within max(5 cm, 1% of its final error).
#[test]
fn sitl_and_three_nodes_match_the_experiment() {
    three_nodes_against_the_experiment(false);
}

/// The same team with a signing key (`--team-key`), under attack: while it runs, a forger sends
/// every node COOPLOC_RANGE frames claiming to come from platform 2 with a range 300 m off, and
/// the same frames signed with another key. Every forged frame is refused and counted, and the
/// team's estimates equal the clean experiment's to the millimetre.
#[test]
fn a_signed_team_refuses_forged_frames_and_matches_the_experiment() {
    three_nodes_against_the_experiment(true);
}

/// A frame claiming to come from platform 2: a range to platform 1 of `epoch` at its time.
fn forged_range(epoch: u32, signer: Option<&mut cooploc::protocol::signing::Signer>) -> Vec<u8> {
    let range = cooploc::estimation::RangeSample {
        t: cooploc::time::TimeUs(u64::from(epoch) * 1_000_000),
        from: 2,
        to: 1,
        range_m: 300.0,
        sigma_m: 0.1,
    };
    let msg = wire::range_to_message(&range, epoch);
    let header = mavlink_core::MavHeader { system_id: 2, component_id: 191, sequence: 0 };
    match signer {
        Some(s) => {
            let now = std::time::SystemTime::now().duration_since(std::time::UNIX_EPOCH).unwrap().as_micros() as u64;
            s.frame(header, &msg, now)
        }
        None => wire::to_frame(header, &msg),
    }
}

/// A state record claiming to come from platform 2 for `epoch`, its position 100 m off, as
/// COOPLOC_STATE_FRAGMENT frames (valid fragments and CRC-32).
fn forged_record(epoch: u32, mut signer: Option<&mut cooploc::protocol::signing::Signer>) -> Vec<Vec<u8>> {
    use cooploc::estimation::{Geometry, Heading, Snapshot, StoreRef};
    use cooploc::protocol::record::{Encoding, StateRecord, encode_record};
    let n = 16;
    let snapshot = Snapshot {
        id: 2,
        geometry: Geometry {
            position_ned_m: nalgebra::Vector3::new(100.0, 0.0, 0.0),
            position_index: [Some(0), Some(1), Some(2)],
            heading: Some(Heading { yaw_rad: 0.0, index: 8 }),
        },
        covariance: nalgebra::DMatrix::identity(n, n) * 0.01,
        psi: nalgebra::DMatrix::identity(n, n),
    };
    let rec =
        StateRecord { snapshot, digest: 0, own_ref: StoreRef::fresh(epoch), refs: Vec::new(), flags: 0, ranges: Vec::new() };
    let bytes = encode_record(&rec, Encoding::F64).unwrap();
    let t = u64::from(epoch) * 1_000_000;
    cooploc::protocol::fragment::fragment(2, epoch, t, &bytes)
        .unwrap()
        .iter()
        .map(|f| {
            let msg = wire::fragment_to_message(f).unwrap();
            let header = mavlink_core::MavHeader { system_id: 2, component_id: 191, sequence: f.index };
            match signer.as_deref_mut() {
                Some(s) => {
                    let now = std::time::SystemTime::now().duration_since(std::time::UNIX_EPOCH).unwrap().as_micros() as u64;
                    s.frame(header, &msg, now)
                }
                None => wire::to_frame(header, &msg),
            }
        })
        .collect()
}

fn three_nodes_against_the_experiment(signed: bool) {
    let world = World::new(&Scenario::from_toml_str(PAPER_TOML).unwrap()).unwrap();
    let (seed, run, schedule) = (1u64, 0u32, "1hz");
    let dir = std::env::temp_dir().join(format!("cooploc-system-{signed}-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let (sitl_child, _sitl_out, vehicle_addr) = start_sitl(&world, schedule, &[]);
    let mut children = Kill(vec![sitl_child]);
    let mut node_outputs = Vec::new();
    let mut coop_addrs: Vec<String> = Vec::new();
    for id in world.platform_ids() {
        let (t0, state) = initial_state(&world, seed, run, id).unwrap();
        let mut node = bin();
        node.args(common::paper_node_args(id, &format!("udpout:{}", vehicle_addr[&id])));
        node.args(["--method", "dcl", "--idle-exit-s", "1.5", "--init-time-us", &t0.0.to_string()]);
        if signed {
            node.args(common::team_key_args());
        } else {
            node.arg("--insecure");
        }
        node.args(common::init_state_args(&state));
        for peer in &coop_addrs {
            node.args(["--peer", peer]);
        }
        let (child, out) = spawn_lines(node);
        children.0.push(child);
        let line = wait_line(&out, &format!("node {id} coop udp "), Duration::from_secs(30));
        coop_addrs.push(line.split_whitespace().last().unwrap().to_string());
        node_outputs.push((id, out));
    }
    // The forger: unsigned frames and frames signed with another key, at every node, while the
    // team runs (380 s at 20x: one forged epoch every 50 ms of wall time): a range and a whole
    // state record (fragments and CRC valid, position 100 m off) claiming to be platform 2's.
    let stop = std::sync::Arc::new(std::sync::atomic::AtomicBool::new(false));
    let forger = {
        let (targets, stop) = (coop_addrs.clone(), stop.clone());
        std::thread::spawn(move || {
            let socket = std::net::UdpSocket::bind("127.0.0.1:0").unwrap();
            let key = cooploc::protocol::signing::TeamKey::from_passphrase("not the team's");
            let mut wrong = cooploc::protocol::signing::Signer::new(key, 2, 0);
            let started = std::time::Instant::now();
            let mut sent = 0u64;
            while !stop.load(std::sync::atomic::Ordering::Relaxed) {
                let epoch = 1 + (started.elapsed().as_secs_f64() * 20.0) as u32;
                for t in &targets {
                    let _ = socket.send_to(&forged_range(epoch, None), t);
                    let _ = socket.send_to(&forged_range(epoch, Some(&mut wrong)), t);
                    sent += 2;
                    for frame in forged_record(epoch, None).into_iter().chain(forged_record(epoch, Some(&mut wrong))) {
                        let _ = socket.send_to(&frame, t);
                        sent += 1;
                    }
                }
                std::thread::sleep(Duration::from_millis(50));
            }
            sent
        })
    };
    // Unsigned, anyone may talk to the team: a flood of ground-station heartbeats from 300
    // ports gets at most MAX_OBSERVERS of them sent to by each node (before, every port became
    // a peer for ever and got the node's whole traffic).
    let flood: Vec<std::net::UdpSocket> = if signed {
        Vec::new()
    } else {
        let hb = cooploc::gcs::runner::heartbeat();
        (0..300)
            .map(|k| {
                let s = std::net::UdpSocket::bind("127.0.0.1:0").unwrap();
                s.set_nonblocking(true).unwrap();
                let frame = wire::to_frame(mavlink_core::MavHeader { system_id: 200, component_id: 190, sequence: k as u8 }, &hb);
                for t in &coop_addrs {
                    s.send_to(&frame, t).unwrap();
                }
                s
            })
            .collect()
    };
    // 380 s at 20x: about 19 s, plus the nodes' idle exit.
    let mut finals = Vec::new();
    for (k, (id, out)) in node_outputs.iter().enumerate() {
        let line = wait_line(out, &format!("node {id} done:"), Duration::from_secs(240));
        let pos = bracket(&line);
        let count = |name: &str| -> u64 {
            line.split(&format!(" {name} ")).nth(1).unwrap().split_whitespace().next().unwrap().parse().unwrap()
        };
        let applied = count("epochs_applied");
        let stats = wait_line(out, &format!("node {id} stats"), Duration::from_secs(5));
        eprintln!("{line}\n{stats}");
        assert_eq!(count("dropped_inputs"), 0, "node {id} dropped vehicle input");
        assert_eq!(count("vehicle_lost"), 0, "node {id} lost vehicle frames");
        assert_eq!(count("epochs_partial"), 0, "node {id} ran epochs without every team member");
        assert!(stats.contains("epoch_disagreements: 0,"), "node {id}: {stats}");
        let peers = wait_line(out, &format!("node {id} peers"), Duration::from_secs(5));
        eprintln!("{peers}");
        let vetting = wait_line(out, &format!("node {id} vetting"), Duration::from_secs(5));
        eprintln!("{vetting}");
        let vetted = |name: &str| -> u64 {
            vetting.split(&format!(" {name} ")).nth(1).unwrap().split_whitespace().next().unwrap().parse().unwrap()
        };
        if signed {
            assert_eq!(vetted("records_contradicted") + vetted("records_rival"), 0, "signing kept the forgeries out: {vetting}");
        } else if *id != 2 {
            // (node 2 takes nothing under its own id: the forger speaks as platform 2)
            assert!(
                vetted("records_contradicted") + vetted("records_rival") > 10,
                "node {id} took the forged records in: {vetting}"
            );
        }
        if signed {
            let signing = wait_line(out, &format!("node {id} signing"), Duration::from_secs(5));
            eprintln!("{signing}");
            let n = |name: &str| -> u64 {
                signing.split(&format!(" {name} ")).nth(1).unwrap().split_whitespace().next().unwrap().parse().unwrap()
            };
            assert!(n("unsigned") > 100 && n("bad_signature") > 100, "the forged frames were refused: {signing}");
            assert!(n("accepted") > 1000, "the team's own frames were taken: {signing}");
            assert_eq!(n("replayed") + n("stale") + n("malformed"), 0, "{signing}");
        }

        let n = |name: &str| -> u64 {
            peers.split(&format!(" {name} ")).nth(1).unwrap().split_whitespace().next().unwrap().parse().unwrap()
        };
        // Signed: the two teammates. Unsigned: also at most MAX_OBSERVERS of the flood, and the
        // forger speaking as platform 2 takes 2's learned slot (the table's bound: one address
        // per member, the given peers, MAX_OBSERVERS), so node k (k peers given) may send to
        // its given peers besides.
        let max_peers = 2 + if signed { 0 } else { cooploc::node::peers::MAX_OBSERVERS as u64 + k as u64 };
        assert!(n("peers") <= max_peers, "node {id}: {peers}");
        if !signed {
            assert!(n("observers_refused") >= 290, "node {id}: the flood was refused: {peers}");
        }
        finals.push((*id, pos, applied));
    }
    // The flood's sockets: at most MAX_OBSERVERS of them heard from each node.
    let mut heard = 0;
    for s in &flood {
        let mut buf = [0u8; 2048];
        if s.recv_from(&mut buf).is_ok() {
            heard += 1;
        }
    }
    eprintln!("{heard} of {} flooding sockets were sent to", flood.len());
    assert!(heard <= 3 * cooploc::node::peers::MAX_OBSERVERS, "{heard} flooding sockets got traffic");
    stop.store(true, std::sync::atomic::Ordering::Relaxed);
    let sent = forger.join().unwrap();
    eprintln!("forger sent {sent} frames");
    let _ = std::fs::remove_dir_all(&dir);
    // The experiment on the same world, fed what went on the wire.
    let mut inputs = world.run_inputs(seed, run);
    for p in &mut inputs.platforms {
        p.imu.iter_mut().for_each(|s| *s = wire::imu_as_sent(s));
        p.odometer.iter_mut().for_each(|s| *s = wire::odometer_as_sent(s));
    }
    let ranges: Vec<_> = world
        .ranges(schedule, seed, run)
        .unwrap()
        .into_iter()
        .map(|(t, rs)| (t, rs.iter().map(wire::range_as_sent).collect()))
        .collect();
    let dcl = run_filter(&world, &inputs, &ranges, Method::Decentralized).unwrap();
    let dr = run_filter(&world, &inputs, &[], Method::DeadReckoning).unwrap();
    let (mut node_err, mut dr_err) = (0.0, 0.0);
    for (k, (id, pos, applied)) in finals.iter().enumerate() {
        let truth = inputs.platforms[k].truth.last().unwrap().pos_ned_m;
        let e = dcl.platforms[k].final_error().pos_err_ne_m;
        let reference = [truth[0] - e[0], truth[1] - e[1]];
        eprintln!(
            "node {id}: {applied} epochs, final N/E {:.4} {:.4}, experiment {:.4} {:.4}",
            pos[0], pos[1], reference[0], reference[1]
        );
        assert!(*applied >= 379, "node {id} applied only {applied} epochs");
        // Signed, the forgeries never reach the filter: the experiment to the millimetre.
        // Unsigned, a forged record that fits the ranges closely enough (100 m off from where
        // platform 2 is, when it passes there) costs platform 2 that epoch.
        let tolerance = if signed { 1e-3 } else { (0.01 * e[0].hypot(e[1])).max(0.05) };
        assert!(
            (pos[0] - reference[0]).abs() < tolerance && (pos[1] - reference[1]).abs() < tolerance,
            "node {id} differs from the experiment by more than {tolerance} m"
        );
        node_err += ((truth[0] - pos[0]).powi(2) + (truth[1] - pos[1]).powi(2)).sqrt();
        dr_err += dr.platforms[k].final_error().pos_err_m;
    }
    assert!(
        node_err < dr_err,
        "decentralized nodes {node_err:.2} m should beat dead reckoning {dr_err:.2} m (sum over platforms)"
    );
    drop(children);
}

/// Bridges two pseudo-terminal pairs (master to master), so that two processes each open a
/// slave as their serial device: a serial cable between them.
#[cfg(unix)]
fn serial_cable() -> (String, String, Vec<std::thread::JoinHandle<()>>) {
    use serialport::SerialPort;
    use std::io::{Read, Write};
    let (a_master, a_slave) = serialport::TTYPort::pair().expect("a pseudo-terminal pair");
    let (b_master, b_slave) = serialport::TTYPort::pair().expect("a pseudo-terminal pair");
    let (a_path, b_path) = (a_slave.name().unwrap(), b_slave.name().unwrap());
    // The slaves stay open in the test (a pty whose slave is closed reads EIO on its master).
    std::mem::forget(a_slave);
    std::mem::forget(b_slave);
    let copy = |mut from: serialport::TTYPort, mut to: serialport::TTYPort| {
        std::thread::spawn(move || {
            from.set_timeout(Duration::from_millis(200)).unwrap();
            let mut buf = [0u8; 4096];
            loop {
                match from.read(&mut buf) {
                    Ok(0) => return,
                    Ok(n) => {
                        if to.write_all(&buf[..n]).is_err() {
                            return;
                        }
                    }
                    Err(e) if e.kind() == std::io::ErrorKind::TimedOut => {}
                    Err(_) => return,
                }
            }
        })
    };
    let threads =
        vec![copy(a_master.try_clone_native().unwrap(), b_master.try_clone_native().unwrap()), copy(b_master, a_master)];
    (a_path, b_path, threads)
}

/// A node whose vehicle is on a serial line (a pseudo-terminal pair), initialised from the
/// vehicle's SIM_STATE rather than from the command line, dead reckoning the whole scenario.
#[cfg(unix)]
#[test]
fn a_node_on_a_serial_line_initialises_from_sim_state() {
    let world = World::new(&Scenario::from_toml_str(PAPER_TOML).unwrap()).unwrap();
    let (vehicle_end, node_end, _threads) = serial_cable();
    let mut sitl = bin();
    sitl.args(["sitl", "sitl/scenarios/paper.toml", "--seed", "1", "--run", "0", "--speed", "20", "--base-port", "0"]);
    sitl.args(["--serial", &format!("1={vehicle_end}:921600"), "--sim-state-hz", "5"]);
    let mut node = bin();
    node.args([
        "node",
        "--scenario",
        "sitl/scenarios/paper.toml",
        "--id",
        "1",
        "--vehicle",
        &format!("serial:{node_end}:921600"),
        "--method",
        "dr",
        "--team",
        "1",
    ]);
    node.args(common::team_key_args());
    node.args(["--idle-exit-s", "1.5"]);
    // The node first: it must be listening when the vehicle's first SIM_STATE goes out.
    let (node_child, node_out) = spawn_lines(node);
    let mut children = Kill(vec![node_child]);
    wait_line(&node_out, "node 1 coop udp ", Duration::from_secs(30));
    let (sitl_child, _sitl_out) = spawn_lines(sitl);
    children.0.push(sitl_child);
    let done = wait_line(&node_out, "node 1 initialised from SIM_STATE", Duration::from_secs(120));
    let number = |line: &str, key: &str| -> f64 {
        line.split(&format!(" {key} ")).nth(1).unwrap().split_whitespace().next().unwrap().trim_end_matches(',').parse().unwrap()
    };
    let t0 = number(&done, "t") as u64;
    let init = bracket(&done);
    let truth = world.trajectory(1).unwrap().truth_at(cooploc::time::TimeUs(t0)).pos_ned_m;
    let init_err = ((init[0] - truth[0]).powi(2) + (init[1] - truth[1]).powi(2)).sqrt();
    eprintln!("{done}\ntruth at t0: {truth:?}, horizontal error {init_err:.3} m");
    // SIM_STATE has no time field: the node takes the last IMU sample's time (at most one IMU
    // period, 5 ms, earlier; a few cm at the scenario's speeds) and 1e-7 deg positions.
    assert!(init_err < 0.1, "initial position {init_err:.3} m from the truth");
    let line = wait_line(&node_out, "node 1 done:", Duration::from_secs(120));
    eprintln!("{line}");
    let count = |name: &str| -> u64 { number(&line, name) as u64 };
    assert_eq!((count("dropped_inputs"), count("vehicle_lost")), (0, 0), "{line}");
    let fin = bracket(&line);
    let truth_end = world.trajectory(1).unwrap().truth_at(world.end()).pos_ned_m;
    let err = ((fin[0] - truth_end[0]).powi(2) + (fin[1] - truth_end[1]).powi(2)).sqrt();
    let inputs = world.run_inputs(1, 0);
    let dr = run_filter(&world, &inputs, &[], Method::DeadReckoning).unwrap().platforms[0].final_error().pos_err_m;
    eprintln!("final error {err:.2} m; the experiment's dead reckoning (its own initial errors) {dr:.2} m");
    // Same sensors, a better start: the drift is of the experiment's size, not more.
    assert!(err < 2.0 * dr, "final error {err:.2} m against {dr:.2} m");
}

/// MAVProxy (pinned in the test virtualenv) on a simulated vehicle's endpoint and on a node's
/// cooperative socket: it sees both heartbeats, and its SET_MESSAGE_INTERVAL is acknowledged.
#[test]
fn mavproxy_sees_the_vehicle_and_the_node_and_gets_its_command_acknowledged() {
    let Some(python) = common::python("the MAVProxy test") else { return };
    let mut sitl = bin();
    sitl.args(["sitl", "sitl/scenarios/paper.toml", "--speed", "1", "--base-port", "0", "--sim-state-hz", "1"]);
    let (sitl_child, sitl_out) = spawn_lines(sitl);
    let mut children = Kill(vec![sitl_child]);
    let mut vehicle = String::new();
    for _ in 0..3 {
        let line = wait_line(&sitl_out, "vehicle ", Duration::from_secs(30));
        if line.starts_with("vehicle 2 ") {
            vehicle = line.split_whitespace().last().unwrap().to_string();
        }
    }
    let mut node = bin();
    node.args([
        "node",
        "--scenario",
        "sitl/scenarios/paper.toml",
        "--id",
        "2",
        "--vehicle",
        &format!("udpout:{vehicle}"),
        "--init-from-run",
        "1:0",
    ]);
    // MAVProxy's `signing setup` signs and checks every master link alike, the simulated
    // vehicle's (unsigned) too: this node runs unsigned, by name
    node.arg("--insecure");
    let (node_child, node_out) = spawn_lines(node);
    children.0.push(node_child);
    let node_line = wait_line(&node_out, "node 2 coop udp ", Duration::from_secs(30));
    let node_addr = node_line.split_whitespace().last().unwrap().to_string();
    let out = Command::new(python)
        .arg(concat!(env!("CARGO_MANIFEST_DIR"), "/tests/python/mavproxy_check.py"))
        .args([&vehicle, &node_addr])
        .output()
        .expect("running tests/python/mavproxy_check.py");
    let text = String::from_utf8_lossy(&out.stdout);
    eprintln!("{text}\n{}", String::from_utf8_lossy(&out.stderr));
    assert!(out.status.success(), "the MAVProxy check failed");
    assert!(text.contains("heartbeat 2:1 type 10"), "the vehicle's heartbeat (ground rover)");
    assert!(text.contains("heartbeat 2:191 type 18"), "the node's heartbeat (onboard controller)");
    assert!(text.contains("ack 511 result 0 from 2:1"), "SET_MESSAGE_INTERVAL accepted by the vehicle");
    drop(children);
}

/// The real world on loopback: the simulator's radios lose 1% of the vehicles' frames, the
/// cooperative network loses 10% of the datagrams, and node 3 is killed at about 114 s and
/// restarted (from its vehicle's SIM_STATE) 20 s later. No node diverges: each ends within a few
/// metres, better than dead reckoning on the team; the restart is detected (store digests
/// differ) and handled (the restarted node takes the others' store, or the team heals). The team
/// signs its traffic: the restarted node, same key and link id, is accepted by its peers (its
/// new signing timestamps follow its old ones), and nothing is refused.
#[test]
fn lossy_links_and_a_restarted_node_do_not_break_the_team() {
    let world = World::new(&Scenario::from_toml_str(PAPER_TOML).unwrap()).unwrap();
    let (seed, run, schedule, speed) = (1u64, 0u32, "1hz", 20.0);
    let key_dir = common::TempDir::new("cooploc-restart-key");
    let key_path = key_dir.join("team.key");
    std::fs::write(&key_path, "0123456789abcdef0123456789abcdef0123456789abcdef0123456789abcdef\n").unwrap();
    let (sitl_child, _sitl_out, vehicle_addr) = start_sitl(&world, schedule, &["--link-loss", "0.01"]);
    let mut children = Kill(vec![sitl_child]);
    let ids = world.platform_ids();
    let net = LossyNet::new(ids.len(), 0.10, 7);
    let node_cmd = |k: usize, id: u16| {
        let mut node = bin();
        node.args(common::paper_node_args(id, &format!("udpout:{}", vehicle_addr[&id])));
        // The protocol's clocks scaled with the simulation (20x): 200 ms retries and a 4 s
        // timeout in vehicle time.
        node.args(["--method", "dcl", "--idle-exit-s", "1.5", "--retry-ms", "10", "--epoch-timeout-ms", "200"]);
        node.arg("--team-key").arg(&key_path);
        for j in (0..ids.len()).filter(|&j| j != k) {
            node.args(["--peer", &net.proxy(j)]);
        }
        node
    };
    let mut outs = Vec::new();
    for (k, &id) in ids.iter().enumerate() {
        let (child, out) = spawn_lines(node_cmd(k, id));
        children.0.push(child);
        let line = wait_line(&out, &format!("node {id} coop udp "), Duration::from_secs(30));
        net.set_real(k, line.split_whitespace().last().unwrap());
        outs.push(out);
    }
    // Node 3 dies at about 114 s of vehicle time and comes back 20 s later, from SIM_STATE.
    std::thread::sleep(Duration::from_secs_f64(114.0 / speed));
    let dead = children.0.len() - 1;
    children.0[dead].kill().unwrap();
    children.0[dead].wait().unwrap();
    std::thread::sleep(Duration::from_secs_f64(20.0 / speed));
    let (child, out) = spawn_lines(node_cmd(2, 3));
    children.0.push(child);
    let line = wait_line(&out, "node 3 coop udp ", Duration::from_secs(30));
    net.set_real(2, line.split_whitespace().last().unwrap());
    outs[2] = out;

    let inputs = world.run_inputs(seed, run);
    let dr = run_filter(&world, &inputs, &[], Method::DeadReckoning).unwrap();
    let (mut node_err, mut dr_err, mut detections, mut restart_handled) = (0.0, 0.0, 0u64, 0u64);
    let mut diverged = Vec::new();
    for (k, (&id, out)) in ids.iter().zip(&outs).enumerate() {
        let line = wait_line(out, &format!("node {id} done:"), Duration::from_secs(240));
        let stats = wait_line(out, &format!("node {id} stats"), Duration::from_secs(5));
        let signing = wait_line(out, &format!("node {id} signing"), Duration::from_secs(5));
        eprintln!("{line}\n{stats}\n{signing}");
        let signed = |name: &str| -> u64 {
            signing.split(&format!(" {name} ")).nth(1).unwrap().split_whitespace().next().unwrap().parse().unwrap()
        };
        assert!(signed("accepted") > 500, "{signing}");
        let refused = ["unsigned", "bad_signature", "replayed", "stale", "malformed"].map(signed);
        assert_eq!(refused.iter().sum::<u64>(), 0, "nothing of the team's was refused: {signing}");
        let err = horizontal_error(&line, inputs.platforms[k].truth.last().unwrap().pos_ned_m);
        let field = |name: &str| stat(&stats, name);
        detections += field("store_mismatches") + field("epoch_disagreements");
        if id == 3 {
            restart_handled = field("stores_adopted") + field("heals");
        }
        let dr_k = dr.platforms[k].final_error().pos_err_m;
        eprintln!("node {id}: final horizontal error {err:.2} m, dead reckoning {dr_k:.2} m, heals {}", field("heals"));
        if err >= dr_k + 5.0 {
            // Every node's lines are printed before the test fails (a failure seen on one node
            // is explained by the others' counters).
            diverged.push(format!("node {id} diverged: {err:.2} m against dead reckoning's {dr_k:.2} m"));
        }
        node_err += err;
        dr_err += dr_k;
    }
    let (fw, dropped) =
        (net.forwarded.load(std::sync::atomic::Ordering::Relaxed), net.dropped.load(std::sync::atomic::Ordering::Relaxed));
    eprintln!(
        "cooperative datagrams: {fw} forwarded, {dropped} dropped; team error {node_err:.2} m, dead reckoning {dr_err:.2} m"
    );
    assert!(diverged.is_empty(), "{diverged:?}");
    assert!(dropped * 100 >= (fw + dropped) * 8, "the network lost about 10%");
    assert!(detections > 0, "the restart was not detected");
    assert!(restart_handled > 0, "the restarted node neither took the others' store nor healed");
    assert!(node_err < dr_err, "the team ({node_err:.2} m) should beat dead reckoning ({dr_err:.2} m)");
    drop(children);
}

/// A node frozen (SIGSTOP) for 1.5 s of wall time, 30 s of vehicle time at 20x, while the
/// simulator and its teammates go on: it does not exit on its idle timer when it wakes (the
/// silence was its own), it catches up on what waited in its sockets, runs the epochs the others
/// ran without it as a bystander where it can, and every node ends near the fault-free result.
/// Its log replays bit for bit, the freeze in it (polls 1.5 s apart). (That a poll forced by
/// the freeze is logged ahead of the frame that found it is the shell's unit test: in these
/// runs the estimates came out the same with the two logged the other way round.)
#[test]
fn a_frozen_node_wakes_up_and_catches_up() {
    let log_dir = std::env::temp_dir().join(format!("cooploc-frozen-{}", std::process::id()));
    std::fs::create_dir_all(&log_dir).unwrap();
    let log_path = log_dir.join("node3.mcap");
    let world = World::new(&Scenario::from_toml_str(PAPER_TOML).unwrap()).unwrap();
    let (seed, run, schedule, speed) = (1u64, 0u32, "1hz", 20.0);
    let (sitl_child, _sitl_out, vehicle_addr) = start_sitl(&world, schedule, &[]);
    let mut children = Kill(vec![sitl_child]);
    let ids = world.platform_ids();
    let net = LossyNet::new(ids.len(), 0.0, 3);
    let mut outs = Vec::new();
    for (k, &id) in ids.iter().enumerate() {
        let mut node = bin();
        node.args(common::paper_node_args(id, &format!("udpout:{}", vehicle_addr[&id])));
        node.args(["--method", "dcl", "--idle-exit-s", "1.0", "--retry-ms", "10", "--epoch-timeout-ms", "200"]);
        node.args(common::team_key_args());
        for j in (0..ids.len()).filter(|&j| j != k) {
            node.args(["--peer", &net.proxy(j)]);
        }
        if id == 3 {
            node.args(["--log", log_path.to_str().unwrap()]);
        }
        let (child, out) = spawn_lines(node);
        children.0.push(child);
        let line = wait_line(&out, &format!("node {id} coop udp "), Duration::from_secs(30));
        net.set_real(k, line.split_whitespace().last().unwrap());
        outs.push(out);
    }
    // Node 3 freezes at about 150 s of vehicle time, for longer than its idle timer.
    std::thread::sleep(Duration::from_secs_f64(150.0 / speed));
    let pid = children.0[3].id().to_string();
    let signal = |sig: &str| assert!(Command::new("kill").args([sig, &pid]).status().unwrap().success(), "kill {sig}");
    signal("-STOP");
    std::thread::sleep(Duration::from_secs_f64(1.5));
    signal("-CONT");

    let inputs = world.run_inputs(seed, run);
    let dr = run_filter(&world, &inputs, &[], Method::DeadReckoning).unwrap();
    let dcl = run_filter(&world, &inputs, &world.ranges(schedule, seed, run).unwrap(), Method::Decentralized).unwrap();
    for (k, (&id, out)) in ids.iter().zip(&outs).enumerate() {
        let line = wait_line(out, &format!("node {id} done:"), Duration::from_secs(240));
        let stats = wait_line(out, &format!("node {id} stats"), Duration::from_secs(5));
        eprintln!("{line}\n{stats}");
        assert!(line.contains("t 380000000"), "node {id} stopped before the end of the run: {line}");
        let err = horizontal_error(&line, inputs.platforms[k].truth.last().unwrap().pos_ned_m);
        let (dr_k, dcl_k) = (dr.platforms[k].final_error().pos_err_m, dcl.platforms[k].final_error().pos_err_m);
        let field = |name: &str| stat(&stats, name);
        eprintln!(
            "node {id}: final error {err:.2} m (fault-free dcl {dcl_k:.2} m, dead reckoning {dr_k:.2} m); freezes {}, bystood {}, \
             left out {}, stores adopted {}, heals {}",
            field("freezes"),
            field("epochs_bystood"),
            field("epochs_excluded"),
            field("stores_adopted"),
            field("heals")
        );
        assert!(err < dr_k + 5.0, "node {id} diverged: {err:.2} m against dead reckoning's {dr_k:.2} m");
        if id == 3 {
            assert!(field("freezes") >= 1, "node 3 did not notice its freeze");
            assert!(field("epochs_bystood") >= 1, "node 3 ran no epoch as a bystander after its freeze");
        }
    }
    drop(children);
    let log = cooploc::recording::read_log(&log_path).unwrap();
    let polls: Vec<u64> = log
        .topic("/vehicle_3/node/events")
        .filter_map(|m| match m.json::<cooploc::node::runner::NodeEvent>() {
            Ok(cooploc::node::runner::NodeEvent::Poll { wall_us }) => Some(wall_us),
            _ => None,
        })
        .collect();
    let longest = polls.windows(2).map(|w| w[1].saturating_sub(w[0])).max().unwrap_or(0);
    eprintln!("node 3's log: {} polls, the longest gap {:.2} s", polls.len(), longest as f64 / 1e6);
    assert!(longest >= 1_000_000, "the freeze is not in the log");
    let replays = cooploc::replay::replay_nodes(&log).unwrap();
    let r = &replays[0];
    eprintln!("node 3 replayed: {} estimates recorded, {} replayed", r.recorded.len(), r.replayed.len());
    assert!(r.recorded.len() > 100);
    assert!(r.matches(), "node 3's log does not replay bit for bit");
    let _ = std::fs::remove_dir_all(&log_dir);
}

/// `--signing-state`: a node keeps its signing timestamp in a file (above every timestamp it
/// used, ahead of the clock by the headroom), written while it runs and when it stops; a file
/// that is not a timestamp is refused at start, naming the file.
#[test]
fn a_node_keeps_its_signing_timestamp_across_restarts() {
    let dir = std::env::temp_dir().join(format!("cooploc-signing-state-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let key = dir.join("team.key");
    std::fs::write(&key, "a passphrase the team shares\n").unwrap();
    let state = dir.join("signing.state");
    let node = |state: &std::path::Path| {
        let mut node = bin();
        node.args([
            "node",
            "--scenario",
            "sitl/scenarios/paper.toml",
            "--id",
            "2",
            "--vehicle",
            "udpout:127.0.0.1:9",
            "--init-from-run",
            "1:0",
            "--team-key",
        ]);
        node.arg(&key).arg("--signing-state").arg(state);
        node
    };
    let now_ts = || {
        let us = std::time::SystemTime::now().duration_since(std::time::UNIX_EPOCH).unwrap().as_micros() as u64;
        cooploc::protocol::signing::timestamp_of(us)
    };
    let read = || cooploc::protocol::signing::parse_state(&std::fs::read_to_string(&state).unwrap()).unwrap();
    let started = now_ts();
    let (child, out) = spawn_lines(node(&state));
    let mut children = Kill(vec![child]);
    wait_line(&out, "node 2 coop udp ", Duration::from_secs(30));
    // Written at the first heartbeat, while it runs.
    let deadline = std::time::Instant::now() + Duration::from_secs(10);
    while !state.exists() && std::time::Instant::now() < deadline {
        std::thread::sleep(Duration::from_millis(50));
    }
    let first = read();
    assert!(first > started + cooploc::protocol::signing::STATE_HEADROOM, "{first} against the clock's {started}");
    assert!(first < now_ts() + cooploc::protocol::signing::STATE_HEADROOM + 100_000, "{first}: more headroom than asked");
    let pid = children.0[0].id().to_string();
    assert!(Command::new("kill").args(["-INT", &pid]).status().unwrap().success());
    let _ = children.0[0].wait();
    let last = read();
    assert!(last >= first, "the state never goes back: {last} after {first}");
    // A second run starts above it: its state is higher again.
    let (child, out) = spawn_lines(node(&state));
    children.0.push(child);
    wait_line(&out, "node 2 coop udp ", Duration::from_secs(30));
    std::thread::sleep(Duration::from_millis(300));
    let pid = children.0[1].id().to_string();
    assert!(Command::new("kill").args(["-INT", &pid]).status().unwrap().success());
    let _ = children.0[1].wait();
    assert!(read() > last, "the restarted node signs above its saved timestamp");
    // Garbage is refused, naming the file.
    let bad = dir.join("bad.state");
    std::fs::write(&bad, "yesterday\n").unwrap();
    let out = node(&bad).output().unwrap();
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success() && err.contains("bad.state") && err.contains("yesterday"), "{err}");
    let _ = std::fs::remove_dir_all(&dir);
}

/// The MAVProxy module (`python/cooploc/mavproxy.py`, `module load cooploc`) in the pinned
/// MAVProxy, headless, against `cooploc sitl` and three nodes on loopback: it loads, its `cooploc
/// status` lists the three vehicles with estimates equal field for field to the COOPLOC_ESTIMATE
/// each node logged itself, `cooploc refresh` gets every node's acknowledgement, and MAVProxy still
/// sees the vehicles' heartbeats and fetches their parameters (it is not disturbed). The script
/// also checks the module's pure functions (ellipse, agreement counters, loss, origin).
#[test]
fn mavproxy_module_shows_the_team_as_the_nodes_sent_it() {
    let Some(python) = common::python("the MAVProxy module test") else { return };
    let out = Command::new(python)
        .arg(concat!(env!("CARGO_MANIFEST_DIR"), "/tests/python/mavproxy_module_check.py"))
        .arg(env!("CARGO_BIN_EXE_cooploc"))
        .current_dir(env!("CARGO_MANIFEST_DIR"))
        .output()
        .expect("running tests/python/mavproxy_module_check.py");
    let text = String::from_utf8_lossy(&out.stdout);
    eprintln!("{text}\n{}", String::from_utf8_lossy(&out.stderr));
    assert!(out.status.success(), "the MAVProxy module check failed");
    assert!(text.contains(" 0 failed"), "every check passed");
    for id in 1..=3 {
        assert!(
            text.contains(&format!("PASS vehicle {id}: printed estimate equals the node's COOPLOC_ESTIMATE field for field")),
            "vehicle {id} checked against its node's log"
        );
    }
}
