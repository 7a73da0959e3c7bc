//! The cooploc Python package (python/, issue 35), installed into the test virtualenv by
//! tests/run-all.sh: tests/python/test_bindings.py (pytest) imports it by name and checks each function
//! against what the library computes here, and that bad input (a garbage or damaged frame, wrong
//! shapes and types) raises a Python exception instead of crashing. Under CI=true a missing
//! virtualenv or package fails the test.

mod common;

use std::process::Command;

use cooploc::estimation::Method;
use cooploc::estimation::consistency;
use cooploc::geodesy::{self, GeoOrigin, Geodetic};
use cooploc::protocol::dialect::cooploc::{MavAutopilot, MavType};
use cooploc::protocol::wire::{self, EstimateReport};
use cooploc::time::TimeUs;
use mavlink_core::MavHeader;
use nalgebra::{Matrix3, Vector3};
use serde_json::json;

fn header(system_id: u32, sequence: u8) -> MavHeader {
    MavHeader { system_id, component_id: 191, sequence }
}

fn hex(bytes: &[u8]) -> String {
    bytes.iter().map(|b| format!("{b:02x}")).collect()
}

fn estimate(platform: cooploc::estimation::PlatformId) -> EstimateReport {
    EstimateReport {
        platform,
        t: TimeUs(12_345_678),
        epoch: 17,
        method: Method::Decentralized,
        position_ned_m: Vector3::new(101.25, -42.5, 0.75),
        velocity_ned_m_s: Vector3::new(9.5, 3.25, 0.0),
        yaw_rad: 0.5,
        position_covariance_m2: Matrix3::new(4.0, 0.5, 0.0, 0.5, 2.25, 0.0, 0.0, 0.0, 1.0),
        yaw_variance_rad2: 1e-4,
        nis: 1.5,
        participants: 3,
        ranges: 6,
    }
}

fn frame(system_id: u32, sequence: u8, e: &EstimateReport) -> Vec<u8> {
    wire::to_frame(header(system_id, sequence), &wire::estimate_to_message(e))
}

#[test]
fn the_python_package_gives_the_library_s_results_and_refuses_bad_input() {
    let Some(python) = common::python("the cooploc Python package") else { return };
    let est = estimate(2);
    let heartbeat =
        wire::to_frame(header(2, 1), &wire::heartbeat(MavType::MAV_TYPE_ONBOARD_CONTROLLER, MavAutopilot::MAV_AUTOPILOT_INVALID));
    let mut datagram = b"\x00noise".to_vec();
    datagram.extend(frame(2, 0, &est));
    datagram.extend(b"\xfd\x09more noise");
    datagram.extend(&heartbeat);
    datagram.extend(frame(3, 7, &estimate(3)));
    let mut nan = estimate(2);
    nan.position_ned_m[0] = f64::NAN;
    let mut negative = estimate(2);
    negative.position_covariance_m2[(0, 0)] = -1.0;

    let (a, b, angle) = consistency::ellipse95_axes(4.0, 0.5, 2.25).unwrap();
    let nees_in = ([1.0, -2.0, 0.5], [4.0, 1.0, 0.5, 3.0, -0.25, 2.0]);
    let [nn, ne, nd, ee, ed, dd] = nees_in.1;
    let nees = consistency::position_nees(&Vector3::from(nees_in.0), &Matrix3::new(nn, ne, nd, ne, ee, ed, nd, ed, dd)).unwrap();
    let origin = GeoOrigin { lat_deg: 34.7, lon_deg: 179.99, alt_m: 12.0 };
    let geo = Geodetic { lat_deg: 34.701, lon_deg: -179.995, alt_m: 15.5 };
    let ned = geodesy::geodetic_to_ned(&origin, &geo);
    let back = geodesy::ned_to_geodetic(&origin, &Vector3::new(1234.5, -987.25, -3.5));
    let epoch = |announcer, participants: Vec<u16>| {
        let a = wire::EpochAnnouncement {
            epoch: 9,
            t: TimeUs(9_000_000),
            announcer,
            participants,
            state: wire::EpochState::COOPLOC_EPOCH_STATE_APPLIED,
            digest: 77,
            incomplete: Vec::new(),
        };
        hex(&wire::to_frame(header(2, 3), &wire::epoch_to_message(&a).unwrap()))
    };
    // The list form (COOPLOC_EPOCH), which can name a platform twice; epoch_to_message sends
    // a team within 64 ids as a bitmask (COOPLOC_EPOCH_SET).
    let epoch_list = |announcer, participants: Vec<u16>| {
        use cooploc::protocol::dialect::cooploc::COOPLOC_EPOCH_DATA;
        let mut list = [0u16; wire::MAX_PARTICIPANTS];
        list[..participants.len()].copy_from_slice(&participants);
        let m = COOPLOC_EPOCH_DATA {
            time_usec: 9_000_000,
            epoch: 9,
            announcer,
            count: participants.len() as u8,
            participants: list,
            state: wire::EpochState::COOPLOC_EPOCH_STATE_APPLIED,
            digest: 77,
        };
        hex(&wire::to_frame(header(2, 3), &cooploc::protocol::MavMessage::COOPLOC_EPOCH(m)))
    };
    let range = |from, range_m| {
        let r = cooploc::estimation::RangeSample { t: TimeUs(9_000_000), from, to: 1, range_m, sigma_m: 0.1 };
        hex(&wire::to_frame(header(2, 4), &wire::range_to_message(&r, 9)))
    };
    let c = &est.position_covariance_m2;
    let spec = json!({
        "palette": cooploc::view::PALETTE.map(|[r, g, b]| format!("{r:02x}{g:02x}{b:02x}")),
        "epoch_frame": epoch(2, vec![1, 2, 3]),
        "epoch_list_frame": epoch_list(2, vec![1, 2, 3]),
        "epoch_twice": epoch_list(2, vec![1, 2, 2]),
        "epoch_other_announcer": epoch(3, vec![1, 2, 3]),
        "range_frame": range(2, 25.0),
        "range_negative": range(2, -1.0),
        "range_other_system": range(3, 25.0),
        "version": env!("CARGO_PKG_VERSION"),
        "package_dir": concat!(env!("CARGO_MANIFEST_DIR"), "/python/cooploc"),
        "datagram": hex(&datagram),
        "datagram_frames": [[2, 191, 0, "COOPLOC_ESTIMATE"], [2, 191, 1, "HEARTBEAT"], [3, 191, 7, "COOPLOC_ESTIMATE"]],
        "estimate_frame": hex(&frame(2, 0, &est)),
        "estimate": {
            "platform": 2, "epoch": 17, "method": Method::Decentralized.short_name(),
            "position_ned_m": [est.position_ned_m[0], est.position_ned_m[1], est.position_ned_m[2]],
            "pos_covariance": [c[(0, 0)], c[(0, 1)], c[(0, 2)], c[(1, 1)], c[(1, 2)], c[(2, 2)]],
        },
        "estimate_wrong_system": hex(&frame(3, 0, &est)),
        "estimate_nan": hex(&frame(2, 0, &nan)),
        "estimate_negative_variance": hex(&frame(2, 0, &negative)),
        "heartbeat_frame": hex(&heartbeat),
        "ellipse_in": [4.0, 0.5, 2.25],
        "ellipse_out": [a, b, angle.to_degrees()],
        "nees_in": [nees_in.0, nees_in.1],
        "nees_out": nees,
        "origin": [origin.lat_deg, origin.lon_deg, origin.alt_m],
        "geo_in": [geo.lat_deg, geo.lon_deg, geo.alt_m],
        "geo_out": [ned[0], ned[1], ned[2]],
        "ned_in": [1234.5, -987.25, -3.5],
        "ned_out": [back.lat_deg, back.lon_deg, back.alt_m],
    });
    let dir = tempfile_dir("bindings");
    // A committed log, and its first 40 % (a writer killed mid-run), as the library reads them.
    let log_path = concat!(env!("CARGO_MANIFEST_DIR"), "/logs/demo-dcl-30s.mcap");
    let bytes = std::fs::read(log_path).unwrap();
    let cut_path = dir.join("cut.mcap");
    std::fs::write(&cut_path, &bytes[..bytes.len() * 2 / 5]).unwrap();
    let summary = |path: &std::path::Path| {
        let log = cooploc::recording::read_log(path).unwrap();
        let internals: Vec<serde_json::Value> = log.topic("/vehicle_1/internals").map(|m| m.json().unwrap()).collect();
        json!({
            "path": path,
            "messages": log.messages.len(),
            "complete": log.is_complete(),
            "coop_1_rx": log.topic("/coop/1/rx").count(),
            "internals_epochs": internals.iter().map(|v| v["epoch"].clone()).collect::<Vec<_>>(),
            "metadata": log.metadata.iter().map(|m| m.name.clone()).collect::<Vec<_>>(),
        })
    };
    let mut spec = spec;
    spec["log"] = summary(std::path::Path::new(log_path));
    spec["cut_log"] = summary(&cut_path);
    // The committed MRCLAM excerpt, decompressed, and the library's runs on it.
    let mrclam_dir = mrclam_excerpt(&dir);
    let ds = cooploc::dataset::mrclam::read_folder(&mrclam_dir).unwrap();
    let settings = cooploc::dataset::run::Settings::new(cooploc::dataset::noise::NoiseModel::mrclam());
    let mut runs = Vec::new();
    for regime in ["no-landmarks", "full-map"] {
        for method in ["dr", "dcl", "ci"] {
            let r = cooploc::dataset::run::Regime::from_name(regime).unwrap();
            let o = cooploc::dataset::run::run(&ds, &settings, r, Method::from_short_name(method).unwrap()).unwrap();
            runs.push(json!([regime, method, o.pos_rmse_m, o.heading_rmse_deg, o.avg_nees, o.epochs, o.robots.len()]));
        }
    }
    spec["mrclam"] = json!({ "dir": mrclam_dir, "runs": runs });
    // The committed log replayed, and three methods run on its inputs, as the library does it.
    let log = cooploc::recording::read_log(std::path::Path::new(log_path)).unwrap();
    let replays: Vec<serde_json::Value> = cooploc::replay::replay_nodes(&log)
        .unwrap()
        .iter()
        .map(|n| json!([n.id, n.matches(), n.imu_replayed, n.recorded.len(), n.recorded.last().map(|e| e.position_ned_m[0])]))
        .collect();
    let methods = [Method::DeadReckoning, Method::Decentralized, Method::CovarianceIntersection];
    let compared: Vec<serde_json::Value> = cooploc::replay::compare_methods(&log, &methods)
        .unwrap()
        .iter()
        .flat_map(|r| {
            r.platforms.iter().map(move |p| {
                let f = p.final_error();
                json!([r.method.short_name(), p.id, p.trace.len(), f.pos_err_m, f.heading_err_deg, p.final_nees])
            })
        })
        .collect();
    spec["replay"] = json!({ "nodes": replays, "compared": compared });
    // One run of the paper scenario and where the experiment's filter of each method ends: the
    // package's InsTeam, stepped from its arrays, must end there to the last bit.
    let paper = concat!(env!("CARGO_MANIFEST_DIR"), "/sitl/scenarios/paper.toml");
    let world = cooploc::sitl::World::new(&cooploc::sitl::Scenario::from_path(std::path::Path::new(paper)).unwrap()).unwrap();
    let (seed, run) = (3u64, 1u32);
    let inputs = world.run_inputs(seed, run);
    let epochs = world.ranges("1hz", seed, run).unwrap();
    let mut finals = serde_json::Map::new();
    for method in
        [Method::DeadReckoning, Method::NoPropagation, Method::Decentralized, Method::CovarianceIntersection, Method::Centralized]
    {
        let r = cooploc::experiment::run_filter(&world, &inputs, &epochs, method).unwrap();
        let positions: Vec<[f64; 3]> = r.platforms.iter().map(|p| p.final_position_ned_m.into()).collect();
        finals.insert(method.short_name().to_string(), json!(positions));
    }
    spec["ins_team"] = json!({ "scenario": paper, "seed": seed, "run": run, "schedule": "1hz", "final_positions": finals });
    // Each vehicle's series in the committed log and in its first 40 %, as the library reads them.
    let series = |path: &std::path::Path| -> serde_json::Value {
        let log = cooploc::recording::read_log(path).unwrap();
        cooploc::recording::series::vehicle_series(&log)
            .iter()
            .map(|v| {
                json!({
                    "id": v.id,
                    "estimate_n": v.estimate.pos_ned_m.len(),
                    "estimate_last": v.estimate.pos_ned_m.last(),
                    "estimate_yaw_last": v.estimate.yaw_rad.last(),
                    "truth_n": v.truth.pos_ned_m.len(),
                    "truth_last": v.truth.pos_ned_m.last(),
                    "epochs": v.updates.epoch,
                    "nis": v.updates.nis,
                    "undecodable": v.undecodable,
                })
            })
            .collect()
    };
    spec["log_series"] = json!({ "full": series(std::path::Path::new(log_path)), "cut": series(&cut_path) });
    spec["not_a_log"] = json!(concat!(env!("CARGO_MANIFEST_DIR"), "/README.md"));
    spec["no_file"] = json!(dir.join("absent.mcap"));
    let path = dir.join("spec.json");
    std::fs::write(&path, serde_json::to_vec(&spec).unwrap()).unwrap();
    let out = Command::new(&python)
        .args(["-m", "pytest", "-q", "-rf", "-p", "no:cacheprovider"])
        .arg(concat!(env!("CARGO_MANIFEST_DIR"), "/tests/python/test_bindings.py"))
        .env("COOPLOC_BINDINGS_SPEC", &path)
        .output()
        .expect("running pytest on tests/python/test_bindings.py");
    let text = format!("{}{}", String::from_utf8_lossy(&out.stdout), String::from_utf8_lossy(&out.stderr));
    println!("{text}");
    assert!(
        out.status.success(),
        "tests/python/test_bindings.py failed (are the package and pytest installed? bash tests/run-all.sh):\n{text}"
    );
    let _ = std::fs::remove_dir_all(&dir);
}

/// The committed MRCLAM excerpt (tests/data/mrclam_ds6_120s), decompressed into `dir`/mrclam.
fn mrclam_excerpt(dir: &std::path::Path) -> std::path::PathBuf {
    let mrclam_dir = dir.join("mrclam");
    std::fs::create_dir_all(&mrclam_dir).unwrap();
    for entry in std::fs::read_dir(concat!(env!("CARGO_MANIFEST_DIR"), "/tests/data/mrclam_ds6_120s")).unwrap() {
        let path = entry.unwrap().path();
        let Some(name) = path.file_name().and_then(|n| n.to_str()).and_then(|n| n.strip_suffix(".zst")) else { continue };
        std::fs::write(mrclam_dir.join(name), zstd::decode_all(std::fs::File::open(&path).unwrap()).unwrap()).unwrap();
    }
    mrclam_dir
}

/// The examples of examples/python run as a user runs them: the data set table prints the
/// library's figures for every method and regime (here on the committed excerpt), and the
/// paper's figure (3 runs) is written as a PNG.
#[test]
fn the_python_examples_print_the_library_s_table_and_draw_the_paper_s_figure() {
    let Some(python) = common::python("the Python examples") else { return };
    let dir = tempfile_dir("examples");
    let mrclam_dir = mrclam_excerpt(&dir);
    let example = |name: &str, args: &[&std::ffi::OsStr]| {
        let out = Command::new(&python)
            .arg(format!("{}/examples/python/{name}", env!("CARGO_MANIFEST_DIR")))
            .args(args)
            .output()
            .expect("running a Python example");
        let text = format!("{}{}", String::from_utf8_lossy(&out.stdout), String::from_utf8_lossy(&out.stderr));
        assert!(out.status.success(), "{name} failed:\n{text}");
        text
    };
    let table = example("dataset6_table.py", &[mrclam_dir.as_os_str()]);
    let ds = cooploc::dataset::mrclam::read_folder(&mrclam_dir).unwrap();
    let settings = cooploc::dataset::run::Settings::new(cooploc::dataset::noise::NoiseModel::mrclam());
    for regime in cooploc::dataset::run::Regime::ALL {
        for method in ["dr", "naive", "dcl", "ci", "centralized"] {
            let o = cooploc::dataset::run::run(&ds, &settings, regime, Method::from_short_name(method).unwrap()).unwrap();
            let row =
                format!("{:<13}{:<12}{:>7.3}{:>9.2}{:>9.2}", regime.name(), method, o.pos_rmse_m, o.heading_rmse_deg, o.avg_nees);
            assert!(table.lines().any(|l| l.starts_with(&row)), "no row {row:?} in:\n{table}");
        }
    }
    let png = dir.join("figure.png");
    let printed = example("paper_figure.py", &[png.as_os_str(), std::ffi::OsStr::new("3")]);
    let bytes = std::fs::read(&png).unwrap_or_default();
    assert!(bytes.starts_with(b"\x89PNG") && bytes.len() > 20_000, "no figure written:\n{printed}");
    assert!(printed.contains("decentralized") && printed.contains("dead-reckoning"), "{printed}");
    let _ = std::fs::remove_dir_all(&dir);
}

fn tempfile_dir(tag: &str) -> std::path::PathBuf {
    let dir = std::env::temp_dir().join(format!("cooploc-python-package-{tag}-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    dir
}
