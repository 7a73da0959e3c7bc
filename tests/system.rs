//! The whole system on loopback: `cooploc sitl` serves the paper scenario's three vehicles over
//! MAVLink (ephemeral ports, accelerated), three `cooploc node` processes run the decentralized
//! protocol among themselves over UDP with no hub, and each node's final estimate is compared with
//! `cooploc experiment`'s run of the same method on the same world, seed, run and schedule, fed the
//! samples as they went on the wire (f32). Stated tolerance: 1 mm in position.

use std::io::{BufRead, BufReader};
use std::process::{Child, Command, Stdio};
use std::sync::mpsc;
use std::time::Duration;

use cooploc::estimation::Method;
use cooploc::experiment::{initial_state, run_filter};
use cooploc::protocol::wire;
use cooploc::sitl::{PAPER_TOML, Scenario, World};

fn bin() -> Command {
    Command::new(env!("CARGO_BIN_EXE_cooploc"))
}

/// Spawns `cmd`, forwarding its stdout lines to a channel.
fn spawn_lines(mut cmd: Command) -> (Child, mpsc::Receiver<String>) {
    let mut child = cmd.current_dir(env!("CARGO_MANIFEST_DIR")).stdout(Stdio::piped()).stderr(Stdio::null()).spawn().unwrap();
    let out = child.stdout.take().unwrap();
    let (tx, rx) = mpsc::channel();
    std::thread::spawn(move || {
        for line in BufReader::new(out).lines().map_while(Result::ok) {
            if tx.send(line).is_err() {
                break;
            }
        }
    });
    (child, rx)
}

fn wait_line(rx: &mpsc::Receiver<String>, prefix: &str, timeout: Duration) -> String {
    let deadline = std::time::Instant::now() + timeout;
    loop {
        let left = deadline.saturating_duration_since(std::time::Instant::now());
        match rx.recv_timeout(left) {
            Ok(line) if line.starts_with(prefix) => return line,
            Ok(_) => {}
            Err(e) => panic!("no line starting with {prefix:?}: {e}"),
        }
    }
}

struct Kill(Vec<Child>);
impl Drop for Kill {
    fn drop(&mut self) {
        for c in &mut self.0 {
            let _ = c.kill();
            let _ = c.wait();
        }
    }
}

#[test]
fn sitl_and_three_nodes_match_the_experiment() {
    let world = World::new(&Scenario::from_toml_str(PAPER_TOML).unwrap()).unwrap();
    let (seed, run, schedule) = (1u64, 0u32, "1hz");
    let mut sitl = bin();
    sitl.args(["sitl", "sitl/scenarios/paper.toml", "--seed", "1", "--run", "0", "--schedule", schedule, "--speed", "20"]);
    sitl.args(["--base-port", "0", "--wait-for-peers", "--sim-state-hz", "1"]);
    let (sitl_child, sitl_out) = spawn_lines(sitl);
    let mut children = Kill(vec![sitl_child]);
    let mut vehicle_addr = std::collections::BTreeMap::new();
    for _ in world.platform_ids() {
        let line = wait_line(&sitl_out, "vehicle ", Duration::from_secs(30));
        let words: Vec<&str> = line.split_whitespace().collect();
        vehicle_addr.insert(words[1].parse::<u16>().unwrap(), words.last().unwrap().to_string());
    }
    let mut node_outputs = Vec::new();
    let mut coop_addrs: Vec<String> = Vec::new();
    for id in world.platform_ids() {
        let (t0, state) = initial_state(&world, seed, run, id).unwrap();
        let (r, p, y) = state.att_frd_to_ned.euler_angles();
        let mut node = bin();
        node.args(["node", "--id", &id.to_string(), "--vehicle", &format!("udpout:{}", vehicle_addr[&id])]);
        node.args(["--method", "dcl", "--idle-exit-s", "1.5", "--init-time-us", &t0.0.to_string()]);
        let v3 = |v: nalgebra::Vector3<f64>| format!("{:.17e},{:.17e},{:.17e}", v[0], v[1], v[2]);
        node.arg(format!("--init-ned={}", v3(state.pos_ned_m)));
        node.arg(format!("--init-vel-ned={}", v3(state.vel_ned_m_s)));
        node.arg(format!("--init-rpy-deg={:.17e},{:.17e},{:.17e}", r.to_degrees(), p.to_degrees(), y.to_degrees()));
        for peer in &coop_addrs {
            node.args(["--peer", peer]);
        }
        let (child, out) = spawn_lines(node);
        children.0.push(child);
        let line = wait_line(&out, &format!("node {id} coop udp "), Duration::from_secs(30));
        coop_addrs.push(line.split_whitespace().last().unwrap().to_string());
        node_outputs.push((id, out));
    }
    // 380 s at 20x: about 19 s, plus the nodes' idle exit.
    let mut finals = Vec::new();
    for (id, out) in &node_outputs {
        let line = wait_line(out, &format!("node {id} done:"), Duration::from_secs(240));
        let inside = line.split('[').nth(1).unwrap().split(']').next().unwrap();
        let pos: Vec<f64> = inside.split(',').map(|v| v.trim().parse().unwrap()).collect();
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
        finals.push((*id, pos, applied));
    }
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
        assert!(
            (pos[0] - reference[0]).abs() < 1e-3 && (pos[1] - reference[1]).abs() < 1e-3,
            "node {id} differs from the experiment"
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
