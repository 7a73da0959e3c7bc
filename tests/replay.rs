//! The logs committed under logs/ (recorded by `cooploc demo`, see logs/README.md): replaying
//! each reproduces its recorded estimates bit for bit and its golden summary; the centralized
//! method on a log's inputs gives the experiment's numbers for that seed and run; the Python
//! `mcap` reader finds the documented channels and schemas; a node killed with SIGKILL leaves a
//! log that replays up to its last flush; a node restarted with its state file restores it, and
//! its log replays.

mod common;

use std::path::{Path, PathBuf};

use cooploc::estimation::Method;
use cooploc::experiment::run_filter;
use cooploc::node::runner::NodeEvent;
use cooploc::recording::read_log;
use cooploc::replay::{RUN_METADATA_NAME, compare_methods, replay_nodes, world_of};

const METHODS: [Method; 5] =
    [Method::DeadReckoning, Method::NoPropagation, Method::Decentralized, Method::Centralized, Method::CovarianceIntersection];

fn committed_logs() -> Vec<PathBuf> {
    let logs = common::committed_logs(&Path::new(env!("CARGO_MANIFEST_DIR")).join("logs"));
    assert!(logs.len() >= 2, "logs/ should hold the demo's logs");
    logs
}

/// Final horizontal error and heading error of every platform under every method.
fn summary(log: &cooploc::recording::Log) -> serde_json::Value {
    let runs = compare_methods(log, &METHODS).unwrap();
    let mut out = serde_json::Map::new();
    for r in runs {
        let v: Vec<serde_json::Value> = r
            .platforms
            .iter()
            .map(|p| serde_json::json!({"id": p.id, "pos_err_m": p.final_error().pos_err_m, "heading_err_deg": p.final_error().heading_err_deg}))
            .collect();
        out.insert(r.method.short_name().to_string(), serde_json::Value::Array(v));
    }
    serde_json::Value::Object(out)
}

#[test]
fn committed_logs_replay_bit_for_bit_and_match_their_golden_summaries() {
    for path in committed_logs() {
        let log = read_log(&path).unwrap();
        assert!(log.is_complete(), "{}", path.display());
        let replays = replay_nodes(&log).unwrap();
        assert_eq!(replays.len(), 3, "{}", path.display());
        for r in &replays {
            assert!(!r.recorded.is_empty());
            assert!(r.matches(), "{}: node {} differs from its recording", path.display(), r.id);
        }
        let golden_path = path.with_extension("summary.json");
        let got = summary(&log);
        if std::env::var("COOPLOC_BLESS").is_ok() {
            std::fs::write(&golden_path, serde_json::to_string_pretty(&got).unwrap() + "\n").unwrap();
        }
        let want: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(&golden_path).unwrap()).unwrap();
        for m in METHODS {
            let (g, w) = (&got[m.short_name()], &want[m.short_name()]);
            for (a, b) in g.as_array().unwrap().iter().zip(w.as_array().unwrap()) {
                for key in ["pos_err_m", "heading_err_deg"] {
                    let (x, y) = (a[key].as_f64().unwrap(), b[key].as_f64().unwrap());
                    assert!((x - y).abs() <= 1e-9 * y.abs().max(1.0), "{} {m} {key}: {x} vs golden {y}", path.display());
                }
            }
        }
    }
}

/// The replay is a check that can fail, and its shell makes the node's start from the frames:
/// - node 1's vehicle frames of the first half of a committed log cut: the vehicle's first
///   sample then comes about 15 s after the state given at the start, and the replayed shell
///   refuses it as stale, as the node would have (the log says the node took it);
/// - one vehicle frame in 50 with a byte changed: its checksum refuses it, the filter misses
///   those samples, the estimates differ;
/// - a saved state attached that does not read: the replay refuses the log, naming it.
#[test]
fn a_tampered_log_does_not_replay_as_recorded() {
    let log = read_log(&committed_logs()[0]).unwrap();
    let topic = cooploc::recording::topics::frames(cooploc::recording::Link::Vehicle(1), cooploc::recording::Direction::Rx);
    let node1 = |log: &cooploc::recording::Log| replay_nodes(log).unwrap().into_iter().find(|r| r.id == 1).unwrap();
    let clean = node1(&log);
    assert!(clean.matches() && clean.recorded_starts.is_empty() && clean.replayed_starts.is_empty());

    let frames = log.topic(&topic).count();
    let mut cut = log.clone();
    let mut seen = 0;
    cut.messages.retain(|m| {
        seen += usize::from(m.topic() == topic);
        m.topic() != topic || seen > frames / 2
    });
    let r = node1(&cut);
    assert!(matches!(r.replayed_starts.first(), Some(NodeEvent::StartRefused { .. })), "{:?}", r.replayed_starts);
    assert!(!r.matches());

    let mut damaged = log.clone();
    for m in damaged.messages.iter_mut().filter(|m| m.topic() == topic).step_by(50) {
        let k = m.data.len() / 2;
        m.data[k] ^= 0x20;
    }
    let r = node1(&damaged);
    assert!(!r.matches(), "{} estimates, all as recorded", r.replayed.len());
    assert!(r.imu_replayed < clean.imu_replayed);

    let mut bad_state = log.clone();
    bad_state.attachments.push(cooploc::recording::LoggedAttachment {
        name: "saved-state.1.txt".into(),
        media_type: "text/plain".into(),
        log_time_ns: 0,
        create_time_ns: 0,
        data: b"format = 1\nplatform = \"one\"\n".to_vec(),
    });
    let err = replay_nodes(&bad_state).unwrap_err().to_string();
    assert!(err.contains("node 1") && err.contains("saved-state.1.txt"), "{err}");
}

/// The centralized EKF on a log's inputs against `run_filter` (what `cooploc experiment` runs)
/// on the world's own inputs for the same seed and run: the log holds the samples as sent (f32),
/// so they agree to the quantisation, stated here as 1 mm and 0.001 deg.
#[test]
fn centralized_on_a_log_gives_the_experiments_numbers() {
    for path in committed_logs() {
        let log = read_log(&path).unwrap();
        let world = world_of(&log).unwrap();
        let meta = &log.metadata_named(RUN_METADATA_NAME).unwrap().entries;
        let (seed, run): (u64, u32) = (meta["seed"].parse().unwrap(), meta["run"].parse().unwrap());
        let reference = run_filter(
            &world,
            &world.run_inputs(seed, run),
            &world.ranges(&meta["schedule"], seed, run).unwrap(),
            Method::Centralized,
        )
        .unwrap();
        let from_log = &compare_methods(&log, &[Method::Centralized]).unwrap()[0];
        for (a, b) in from_log.platforms.iter().zip(&reference.platforms) {
            let (a, b) = (a.final_error(), b.final_error());
            eprintln!("{} platform: log {:.4} m, experiment {:.4} m", path.display(), a.pos_err_m, b.pos_err_m);
            assert!((a.pos_err_m - b.pos_err_m).abs() < 1e-3, "{}: {} vs {}", path.display(), a.pos_err_m, b.pos_err_m);
            assert!((a.heading_err_deg - b.heading_err_deg).abs() < 1e-3);
        }
    }
}

#[test]
fn the_python_mcap_reader_finds_the_documented_channels_in_every_log() {
    let Some(python) = common::python("the Python mcap reader") else { return };
    for path in committed_logs() {
        let out = std::process::Command::new(&python)
            .arg(concat!(env!("CARGO_MANIFEST_DIR"), "/tests/python/log_check.py"))
            .arg(&path)
            .output()
            .unwrap();
        let text = String::from_utf8_lossy(&out.stdout);
        eprintln!("{text}{}", String::from_utf8_lossy(&out.stderr));
        assert!(out.status.success(), "{}", path.display());
        assert!(text.contains("log_check: OK"), "{}", path.display());
    }
}

/// A node recording its log is killed with SIGKILL: the log it leaves has no summary, holds its
/// traffic up to about a second before the kill, and replays (every logged IMU sample after
/// the initialisation reaches the replayed filter).
#[test]
fn a_node_killed_with_sigkill_leaves_a_log_that_replays() {
    killed_node_log_replays("kill", &[], 0.0);
}

/// A node started with a start state for the scenario's start (`--init-from-run`) while the
/// vehicle has been running for about 15 s refuses that stale state (it says so in its log) and
/// starts from SIM_STATE; its log replays the same way.
#[test]
fn a_node_that_refused_a_stale_start_state_leaves_a_log_that_replays() {
    let log = killed_node_log_replays("stale", &["--init-from-run", "1:0"], 3.0);
    let refused = log.topic("/vehicle_1/node/events").any(|m| {
        matches!(m.json::<cooploc::node::runner::NodeEvent>(), Ok(cooploc::node::runner::NodeEvent::StartRefused { .. }))
    });
    assert!(refused, "no StartRefused event in the log");
    // (the replayed shell refused it too, from the vehicle's first sample, and then started from
    // SIM_STATE: checked in killed_node_log_replays)
}

/// A node with `--state-file` is killed with SIGKILL and started again at once with the same
/// arguments (a start state for the scenario's start, by then stale), the simulator sending no
/// SIM_STATE, as a real vehicle sends none: the second node restores the state the first one
/// saved (its log holds the Restored event), the restored position is within 3 sigma of the
/// simulator's truth, and its log replays: every IMU sample logged after the restore reaches
/// the replayed filter.
#[test]
fn a_node_restarted_with_its_state_file_restores_it_and_its_log_replays() {
    let dir = std::env::temp_dir().join(format!("cooploc-restore-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let (state_file, log_path) = (dir.join("node1.state"), dir.join("node.mcap"));
    let state_arg = state_file.display().to_string();
    let args = ["--init-from-run", "1:0", "--state-file", &state_arg];
    let (mut sitl, vehicle) = SitlVehicle::start("0");
    let mut first = node_command(&vehicle, None, &args).spawn().unwrap();
    std::thread::sleep(std::time::Duration::from_millis(3000));
    first.kill().unwrap();
    first.wait().unwrap();
    let saved = cooploc::node::saved::SavedState::parse(&std::fs::read_to_string(&state_file).unwrap()).unwrap();
    let mut second = node_command(&vehicle, Some(&log_path), &args).spawn().unwrap();
    std::thread::sleep(std::time::Duration::from_millis(3500));
    second.kill().unwrap();
    second.wait().unwrap();
    sitl.stop();
    let log = read_log(&log_path).unwrap();
    let (restored, age_us) = log
        .topic("/vehicle_1/node/events")
        .find_map(|m| match m.json::<NodeEvent>() {
            Ok(NodeEvent::Restored { state, age_us }) => Some((state, age_us)),
            _ => None,
        })
        .expect("the second node restored its saved state");
    assert!(restored.t_us >= saved.t_us, "restored at {} us, saved at {} us", restored.t_us, saved.t_us);
    let world = cooploc::sitl::World::new(&cooploc::sitl::Scenario::from_toml_str(cooploc::sitl::PAPER_TOML).unwrap()).unwrap();
    let truth = world.trajectory(1).unwrap().truth_at(cooploc::time::TimeUs(restored.t_us)).pos_ned_m;
    let p = restored.covariance_matrix();
    let sigma = (p[(0, 0)] + p[(1, 1)]).sqrt();
    let err = (restored.nav_state().position_ned_m() - truth).xy().norm();
    eprintln!(
        "restored {:.2} s after it was saved: {err:.2} m from the truth, horizontal sigma {sigma:.2} m",
        age_us as f64 / 1e6
    );
    assert!(err <= 3.0 * sigma, "restored {err:.2} m from the truth, 3 sigma {:.2} m", 3.0 * sigma);
    assert!(age_us <= cooploc::node::saved::MAX_RESTORE_AGE_US);
    let replays = replay_nodes(&log).unwrap();
    let imu_logged = imu_logged_after(&log, restored.t_us);
    eprintln!("IMU samples logged after the restore {imu_logged}, replayed {}", replays[0].imu_replayed);
    assert!(imu_logged > 1000);
    assert_eq!(replays[0].imu_replayed, imu_logged);
    assert_replays_its_start_and_estimates(&replays[0]);
    assert!(
        matches!(replays[0].replayed_starts[..], [NodeEvent::Restored { .. }]),
        "the replayed shell restored the saved state"
    );
    let _ = std::fs::remove_dir_all(&dir);
}

/// `cooploc sitl` serving the paper scenario at 5x, SIM_STATE at `sim_state_hz`: the child and
/// vehicle 1's address.
struct SitlVehicle(std::process::Child);

impl SitlVehicle {
    fn start(sim_state_hz: &str) -> (SitlVehicle, String) {
        use std::io::{BufRead, BufReader};
        use std::process::{Command, Stdio};
        let mut sitl = Command::new(env!("CARGO_BIN_EXE_cooploc"))
            .current_dir(env!("CARGO_MANIFEST_DIR"))
            .args(["sitl", "sitl/scenarios/paper.toml", "--speed", "5", "--base-port", "0", "--sim-state-hz", sim_state_hz])
            .stdout(Stdio::piped())
            .stderr(Stdio::null())
            .spawn()
            .unwrap();
        let mut lines = BufReader::new(sitl.stdout.take().unwrap()).lines();
        let vehicle = loop {
            let line = lines.next().expect("sitl output").unwrap();
            if line.starts_with("vehicle 1 ") {
                break line.split_whitespace().last().unwrap().to_string();
            }
        };
        // (read on to its end: a closed pipe would end the simulator at its next line)
        std::thread::spawn(move || lines.for_each(drop));
        (SitlVehicle(sitl), vehicle)
    }

    fn stop(&mut self) {
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
}

impl Drop for SitlVehicle {
    fn drop(&mut self) {
        self.stop();
    }
}

/// One dr node of platform 1 on `vehicle`, with a log at `log` and `extra` arguments.
fn node_command(vehicle: &str, log: Option<&Path>, extra: &[&str]) -> std::process::Command {
    let mut node = std::process::Command::new(env!("CARGO_BIN_EXE_cooploc"));
    node.current_dir(env!("CARGO_MANIFEST_DIR"));
    node.args(["node", "--scenario", "sitl/scenarios/paper.toml", "--id", "1", "--vehicle", &format!("udpout:{vehicle}")]);
    node.args(["--method", "dr", "--team", "1"]);
    if let Some(log) = log {
        node.arg("--log").arg(log);
    }
    node.args(common::team_key_args()).args(extra);
    node.stdout(std::process::Stdio::null()).stderr(std::process::Stdio::null());
    node
}

/// Vehicle 1's IMU samples in `log` after `t_us`.
fn imu_logged_after(log: &cooploc::recording::Log, t_us: u64) -> u64 {
    log.topic("/vehicle_1/mavlink/rx")
        .filter(|m| match cooploc::protocol::wire::from_any_frame(&m.data) {
            Ok((_, cooploc::protocol::MavMessage::HIGHRES_IMU(i))) => i.time_usec > t_us,
            _ => false,
        })
        .count() as u64
}

/// Runs `cooploc sitl` at 5x, starts one dr node `wait_s` later with `extra` arguments and a log,
/// kills it with SIGKILL 3.5 s later, and replays the log: the log it leaves has no summary,
/// holds its traffic up to about a second before the kill, and every IMU sample logged after
/// the initialisation reaches the replayed filter. The log, read.
fn killed_node_log_replays(tag: &str, extra: &[&str], wait_s: f64) -> cooploc::recording::Log {
    let dir = std::env::temp_dir().join(format!("cooploc-{tag}-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let log_path = dir.join("node.mcap");
    let (mut sitl, vehicle) = SitlVehicle::start("5");
    std::thread::sleep(std::time::Duration::from_secs_f64(wait_s));
    let mut node = node_command(&vehicle, Some(&log_path), extra).spawn().unwrap();
    std::thread::sleep(std::time::Duration::from_millis(3500));
    node.kill().unwrap(); // SIGKILL
    let killed_at_ns = cooploc::recording::wall_now_ns();
    node.wait().unwrap();
    sitl.stop();
    let log = read_log(&log_path).unwrap();
    assert!(!log.is_complete(), "a killed recorder leaves no summary");
    let last_ns = log.messages.iter().map(|m| m.log_time_ns).max().expect("messages before the kill");
    let lost_s = (killed_at_ns - last_ns) as f64 * 1e-9;
    eprintln!("{} messages, the last {lost_s:.2} s before the kill, end {:?}", log.messages.len(), log.end);
    assert!(lost_s < 1.5, "{lost_s:.2} s lost (the recorder flushes every second)");
    let replays = replay_nodes(&log).unwrap();
    // The node initialised from the vehicle's SIM_STATE: the IMU samples after that instant.
    let t0 = log
        .topic("/vehicle_1/node/events")
        .find_map(|m| match m.json::<cooploc::node::runner::NodeEvent>() {
            Ok(cooploc::node::runner::NodeEvent::Init { t0_us, .. }) => Some(t0_us),
            _ => None,
        })
        .expect("the node initialised");
    let imu_logged = imu_logged_after(&log, t0);
    eprintln!("IMU samples logged after the initialisation {imu_logged}, replayed {}", replays[0].imu_replayed);
    assert!(imu_logged > 1000);
    assert_eq!(replays[0].imu_replayed, imu_logged);
    assert_replays_its_start_and_estimates(&replays[0]);
    let _ = std::fs::remove_dir_all(&dir);
    log
}

/// The replayed shell started as the node did (the same Init, StartRefused or Restored events,
/// made by the shell from the logged frames, not read from the log), and sent the estimates the
/// node sent, bit for bit: a log cut by a kill may end between an input and the estimate it
/// made, so the replay may hold one more.
fn assert_replays_its_start_and_estimates(r: &cooploc::replay::NodeReplay) {
    let kind = |e: &NodeEvent| match e {
        NodeEvent::Init { .. } => "Init",
        NodeEvent::StartRefused { .. } => "StartRefused",
        NodeEvent::Restored { .. } => "Restored",
        _ => "other",
    };
    let starts: Vec<&str> = r.replayed_starts.iter().map(kind).collect();
    eprintln!("replayed start {starts:?}; estimates recorded {}, replayed {}", r.recorded.len(), r.replayed.len());
    assert!(!r.recorded_starts.is_empty(), "the node started");
    assert_eq!(r.recorded_starts, r.replayed_starts);
    let whole =
        cooploc::replay::NodeReplay { replayed: r.replayed[..r.recorded.len().min(r.replayed.len())].to_vec(), ..r.clone() };
    assert!(whole.matches(), "the replayed estimates differ from the recorded ones");
    assert!(r.replayed.len() <= r.recorded.len() + 1);
}
