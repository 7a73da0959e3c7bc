//! The logs committed under logs/ (recorded by `cooploc demo`, see logs/README.md): replaying
//! each reproduces its recorded estimates bit for bit and its golden summary; the centralized
//! method on a log's inputs gives the experiment's numbers for that seed and run; the Python
//! `mcap` reader finds the documented channels and schemas; a node killed with SIGKILL leaves a
//! log that replays up to its last flush.

mod common;

use std::path::{Path, PathBuf};

use cooploc::estimation::Method;
use cooploc::experiment::run_filter;
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
}

/// Runs `cooploc sitl` at 5x, starts one dr node `wait_s` later with `extra` arguments and a log,
/// kills it with SIGKILL 3.5 s later, and replays the log: the log it leaves has no summary,
/// holds its traffic up to about a second before the kill, and every IMU sample logged after
/// the initialisation reaches the replayed filter. The log, read.
fn killed_node_log_replays(tag: &str, extra: &[&str], wait_s: f64) -> cooploc::recording::Log {
    use std::io::{BufRead, BufReader};
    use std::process::{Command, Stdio};
    let dir = std::env::temp_dir().join(format!("cooploc-{tag}-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let log_path = dir.join("node.mcap");
    let bin = env!("CARGO_BIN_EXE_cooploc");
    let root = env!("CARGO_MANIFEST_DIR");
    let mut sitl = Command::new(bin)
        .current_dir(root)
        .args(["sitl", "sitl/scenarios/paper.toml", "--speed", "5", "--base-port", "0", "--sim-state-hz", "5"])
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
    std::thread::sleep(std::time::Duration::from_secs_f64(wait_s));
    let mut node = Command::new(bin)
        .current_dir(root)
        .args([
            "node",
            "--scenario",
            "sitl/scenarios/paper.toml",
            "--id",
            "1",
            "--vehicle",
            &format!("udpout:{vehicle}"),
            "--method",
            "dr",
            "--team",
            "1",
            "--log",
        ])
        .arg(&log_path)
        .args(common::team_key_args())
        .args(extra)
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .spawn()
        .unwrap();
    std::thread::sleep(std::time::Duration::from_millis(3500));
    node.kill().unwrap(); // SIGKILL
    let killed_at_ns = cooploc::recording::wall_now_ns();
    node.wait().unwrap();
    let _ = sitl.kill();
    let _ = sitl.wait();
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
    let imu_logged = log
        .topic("/vehicle_1/mavlink/rx")
        .filter(|m| match cooploc::protocol::wire::from_any_frame(&m.data) {
            Ok((_, cooploc::protocol::MavMessage::HIGHRES_IMU(i))) => i.time_usec > t0,
            _ => false,
        })
        .count() as u64;
    eprintln!("IMU samples logged after the initialisation {imu_logged}, replayed {}", replays[0].imu_replayed);
    assert!(imu_logged > 1000);
    assert_eq!(replays[0].imu_replayed, imu_logged);
    let _ = std::fs::remove_dir_all(&dir);
    log
}
