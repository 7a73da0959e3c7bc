//! Real data: the committed excerpt of MRCLAM data set 6 (`tests/data/mrclam_ds6_120s`, the first
//! 120 s of all five robots, source in its README) imported, written as a cooploc log, read back
//! and run through every method in every regime; the summary against a golden file. Bad data
//! (a missing file, a truncated line, time going backwards, an unknown barcode, bytes that are
//! not text) through the binary: an error naming file and line, or counted, never a panic.
//!
//! The noise identification (from the innovations, no ground truth) on the excerpt: it lowers
//! its cost and reads no truth beyond the start poses.
//!
//! Regenerate the golden summary after a deliberate change of the model or the noise figures:
//! `COOPLOC_BLESS=1 cargo test --release --test dataset golden`.

mod common;

use std::path::{Path, PathBuf};
use std::process::Command;

use cooploc::dataset::run::{Regime, Settings, run};
use cooploc::dataset::{log, mrclam};
use cooploc::estimation::Method;

fn data_dir() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/data/mrclam_ds6_120s")
}

/// The excerpt decompressed into a fresh folder named after `tag`.
fn excerpt(tag: &str) -> PathBuf {
    let dir = std::env::temp_dir().join(format!("cooploc-mrclam-{tag}-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).unwrap();
    let mut files = 0;
    for entry in std::fs::read_dir(data_dir()).unwrap() {
        let path = entry.unwrap().path();
        let Some(name) = path.file_name().and_then(|n| n.to_str()).and_then(|n| n.strip_suffix(".zst")) else { continue };
        let bytes = zstd::decode_all(std::fs::File::open(&path).unwrap()).unwrap();
        std::fs::write(dir.join(name), bytes).unwrap();
        files += 1;
    }
    assert_eq!(files, 17, "the excerpt has the 17 files of a data set");
    dir
}

fn summary_line(o: &cooploc::dataset::run::Outcome) -> String {
    format!(
        "{} {}: pos {:.4} m, hdg {:.3} deg, nees {:.3} (hdg {:.3}), in95 {:.4}, landmarks {}/{} w<.5 {}, teammates {}/{} w<.5 {}, epochs {}, scored {}, masked {}",
        o.regime.name(),
        o.method.short_name(),
        o.pos_rmse_m,
        o.heading_rmse_deg,
        o.avg_nees,
        o.avg_nees_heading,
        o.in_bound_share,
        o.landmark_updates,
        o.landmark_gated,
        o.landmark_weight_below_half,
        o.robot_updates,
        o.robot_gated,
        o.robot_weight_below_half,
        o.epochs,
        o.samples,
        o.masked
    )
}

#[test]
fn golden_summary_of_every_method_on_the_excerpt_after_a_log_round_trip() {
    let dir = excerpt("golden");
    let ds = mrclam::read_folder(&dir).unwrap();
    assert_eq!(ds.robots.len(), 5);
    assert_eq!(ds.landmarks.len(), 15);
    let mut lines = vec![format!("excerpt: {:.3} s", ds.t_end.secs_since(ds.t0))];
    for r in &ds.robots {
        lines.push(format!(
            "robot {}: {} commands, {} observations, {} truth poses",
            r.id,
            r.commands.len(),
            r.observations.len(),
            r.truth.len()
        ));
    }
    lines.push(format!("counts: {:?}", ds.counts));

    // Through a log and back: what replay runs on.
    let path = dir.join("excerpt.mcap");
    let noise = cooploc::dataset::noise::NoiseModel::mrclam();
    log::write(&ds, &noise, &path, None).unwrap();
    let read = cooploc::recording::read_log(&path).unwrap();
    let logged = log::read(&read).unwrap();
    assert_eq!(logged.rejected_frames, 0);
    assert_eq!(logged.noise, noise);
    let back = &logged.dataset;
    assert_eq!((back.t0, back.t_end, &back.counts, &back.landmarks), (ds.t0, ds.t_end, &ds.counts, &ds.landmarks));
    for (a, b) in ds.robots.iter().zip(&back.robots) {
        assert_eq!(a.commands.len(), b.commands.len());
        assert_eq!(a.observations.len(), b.observations.len());
        assert_eq!(a.truth.len(), b.truth.len());
        for (x, y) in a.commands.iter().zip(&b.commands) {
            assert_eq!(x.t, y.t);
            assert!(
                (x.speed_m_s - y.speed_m_s).abs() < 1e-7 && (x.yaw_rate_rad_s - y.yaw_rate_rad_s).abs() < 1e-7,
                "f32 on the wire"
            );
        }
        for (x, y) in a.observations.iter().zip(&b.observations) {
            assert_eq!((x.t, x.target), (y.t, y.target));
        }
        for (x, y) in a.truth.iter().zip(&b.truth) {
            assert_eq!(x.t, y.t);
            assert!((x.n_m - y.n_m).abs() < 1e-12 && (x.e_m - y.e_m).abs() < 1e-12 && (x.yaw_rad - y.yaw_rad).abs() < 1e-9);
        }
    }

    let settings = Settings::new(logged.noise);
    let mut outcomes = Vec::new();
    for regime in Regime::ALL {
        for method in Method::ALL {
            let o = run(back, &settings, regime, method).unwrap();
            lines.push(summary_line(&o));
            outcomes.push(o);
        }
    }
    let get = |r: Regime, m: Method| outcomes.iter().find(|o| o.regime == r && o.method == m).unwrap();
    // The paper's exactness on real data: with every robot in every epoch and no local
    // measurement, the decentralized filter is the centralized one.
    let (d, c) = (get(Regime::NoLandmarks, Method::Decentralized), get(Regime::NoLandmarks, Method::Centralized));
    assert!((d.pos_rmse_m - c.pos_rmse_m).abs() < 1e-9 && (d.avg_nees - c.avg_nees).abs() < 1e-6, "{d:?} vs {c:?}");
    assert!(d.epochs > 0 && d.robot_updates > 0, "the excerpt has teammate observations");
    // Dead reckoning uses no observation: the same run in every regime.
    let dr: Vec<f64> = Regime::ALL.iter().map(|&r| get(r, Method::DeadReckoning).pos_rmse_m).collect();
    assert!(dr.iter().all(|&v| v == dr[0]), "{dr:?}");
    // Landmarks help: with the full map every cooperative method beats dead reckoning.
    for m in [Method::NoPropagation, Method::Decentralized, Method::Centralized, Method::CovarianceIntersection] {
        assert!(get(Regime::FullMap, m).pos_rmse_m < dr[0], "{m}");
    }

    let text = lines.join("\n") + "\n";
    let golden = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/golden/mrclam_excerpt.txt");
    if std::env::var_os("COOPLOC_BLESS").is_some() {
        std::fs::write(&golden, &text).unwrap();
    }
    let expected = std::fs::read_to_string(&golden).expect("tests/golden/mrclam_excerpt.txt (COOPLOC_BLESS=1 to write it)");
    assert_eq!(text, expected, "the summary differs from tests/golden/mrclam_excerpt.txt");
    std::fs::remove_dir_all(&dir).unwrap();
}

/// The noise identification reads no ground truth beyond each robot's start pose: the same
/// figures with every later truth pose moved 100 m, and a lower innovation cost than its start.
#[test]
fn identification_lowers_the_innovation_cost_and_reads_no_ground_truth() {
    use cooploc::dataset::identify::{MAX_CORRELATION_S, Options, fit_correlation, identify, start};
    let dir = excerpt("identify");
    let ds = mrclam::read_folder(&dir).unwrap().excerpt(60.0);
    // Every ground-truth pose but each robot's first moved by 100 m.
    let truth_moved = |ds: &cooploc::dataset::Dataset| {
        let mut moved = ds.clone();
        for r in &mut moved.robots {
            for p in r.truth.iter_mut().skip(1) {
                p.n_m += 100.0;
                p.e_m -= 100.0;
            }
        }
        moved
    };
    let moved = truth_moved(&ds);
    let base = cooploc::dataset::noise::NoiseModel::mrclam();
    let opts = Options { max_iterations: 2, ..Options::default() };
    let a = identify(&ds, &start(&base), &opts).unwrap();
    let b = identify(&moved, &start(&base), &opts).unwrap();
    assert_eq!(a.best.model, b.best.model);
    assert_eq!(a.best.cost, b.best.cost);
    assert!(a.best.cost < a.start.cost - 1.0, "{} vs {}", a.best.cost, a.start.cost);
    // The likelihood search (19 candidates an iteration), then the correlation time: the fresh
    // observations' NIS with white errors, its bisection (20 steps) and the NIS at the time found;
    // or the first alone when white errors are already consistent.
    // (On this minute, two iterations from round figures leave the sigmas so small that even
    // the longest correlation time leaves the fresh NIS above 1; the fit says so.)
    let (t, nis, white) = (a.best.model.observation_correlation_s, a.fresh_nis, a.fresh_nis_white);
    assert_eq!((t, nis), (b.best.model.observation_correlation_s, b.fresh_nis));
    let search = 1 + 2 * 19;
    if white <= 1.0 {
        assert!(t == 0.0 && nis == white && a.evaluations == search + 1);
    } else if t == MAX_CORRELATION_S {
        assert!(nis > 1.0 && nis < white && a.evaluations == search + 2, "white {white}, at {t} s {nis}");
    } else {
        assert!((nis - 1.0).abs() < 1e-3 && a.evaluations == search + 23, "white {white}, at {t} s {nis}");
    }
    // From the committed figures (white errors), on the whole excerpt, the bisection: the fresh
    // NIS made 1.
    let white_model = cooploc::dataset::noise::NoiseModel { observation_correlation_s: 0.0, ..base };
    let whole = mrclam::read_folder(&dir).unwrap();
    let fit = fit_correlation(&whole, &white_model).unwrap();
    assert!(fit.white_nis > 1.0, "{fit:?}");
    assert!(fit.correlation_s > 0.0 && fit.correlation_s < MAX_CORRELATION_S && (fit.nis - 1.0).abs() < 1e-3, "{fit:?}");
    assert_eq!(fit, fit_correlation(&truth_moved(&whole), &white_model).unwrap());
    std::fs::remove_dir_all(&dir).unwrap();
}

fn cooploc(args: &[&str]) -> std::process::Output {
    Command::new(env!("CARGO_BIN_EXE_cooploc")).args(args).output().unwrap()
}

/// The table line of `regime method` in a command's output.
fn table_line(out: &str, regime: &str, method: &str) -> String {
    out.lines()
        .find(|l| {
            let mut w = l.split_whitespace();
            w.next() == Some(regime) && w.next() == Some(method)
        })
        .unwrap_or_else(|| panic!("no {regime} {method} line in:\n{out}"))
        .to_string()
}

#[test]
fn the_import_and_the_replay_of_its_log_print_the_same_table() {
    let dir = excerpt("replay");
    let log_path = dir.join("ds.mcap");
    let import = cooploc(&["dataset", "mrclam", dir.to_str().unwrap(), "--out", log_path.to_str().unwrap(), "--method", "all"]);
    let import_out = String::from_utf8_lossy(&import.stdout).into_owned();
    assert!(import.status.success(), "{import_out}\n{}", String::from_utf8_lossy(&import.stderr));
    assert!(import_out.contains("dropped: 0 observations of unknown barcodes"), "{import_out}");
    let replay = cooploc(&["replay", log_path.to_str().unwrap(), "--method", "all"]);
    let replay_out = String::from_utf8_lossy(&replay.stdout).into_owned();
    assert!(replay.status.success(), "{replay_out}\n{}", String::from_utf8_lossy(&replay.stderr));
    for regime in ["no-landmarks", "map-blind", "full-map"] {
        for method in ["dr", "naive", "dcl", "centralized", "ci"] {
            // Everything but the runtime column (the third field from the end).
            let strip = |l: String| {
                let mut w: Vec<String> = l.split_whitespace().map(str::to_string).collect();
                w.remove(w.len() - 3);
                w
            };
            assert_eq!(strip(table_line(&import_out, regime, method)), strip(table_line(&replay_out, regime, method)));
        }
    }
    std::fs::remove_dir_all(&dir).unwrap();
}

/// Runs the import on `dir` and returns (exit code, stdout, stderr).
fn import(dir: &Path) -> (Option<i32>, String, String) {
    let out = cooploc(&["dataset", "mrclam", dir.to_str().unwrap()]);
    (out.status.code(), String::from_utf8_lossy(&out.stdout).into_owned(), String::from_utf8_lossy(&out.stderr).into_owned())
}

fn lines_in(path: &Path) -> usize {
    std::fs::read_to_string(path).unwrap().lines().count()
}

fn append(path: &Path, line: &str) {
    use std::io::Write;
    std::fs::OpenOptions::new().append(true).open(path).unwrap().write_all(line.as_bytes()).unwrap();
}

#[test]
fn bad_data_gets_an_error_naming_file_and_line_or_is_counted() {
    let dir = excerpt("bad");
    let (code, out, _) = import(&dir);
    assert_eq!(code, Some(0), "{out}");

    // A missing file.
    let measurement = dir.join("Robot3_Measurement.dat");
    let saved = std::fs::read(&measurement).unwrap();
    std::fs::remove_file(&measurement).unwrap();
    let (code, _, err) = import(&dir);
    assert_eq!(code, Some(1), "an error, not a panic: {err}");
    assert!(err.contains("Robot3_Measurement.dat") && err.contains("No such file"), "{err}");
    std::fs::write(&measurement, &saved).unwrap();

    // A truncated line.
    let odometry = dir.join("Robot2_Odometry.dat");
    let saved = std::fs::read(&odometry).unwrap();
    let n = lines_in(&odometry);
    append(&odometry, "1248444296.000 \t  0.08\r\n");
    let (code, _, err) = import(&dir);
    assert_eq!(code, Some(1), "{err}");
    assert!(err.contains(&format!("Robot2_Odometry.dat:{}: 2 fields, expected 3", n + 1)), "{err}");
    std::fs::write(&odometry, &saved).unwrap();

    // Time going backwards.
    let truth = dir.join("Robot4_Groundtruth.dat");
    let saved = std::fs::read(&truth).unwrap();
    let n = lines_in(&truth);
    append(&truth, "1248444200.000 \t 1.0 \t 1.0 \t 0.0 \r\n");
    let (code, _, err) = import(&dir);
    assert_eq!(code, Some(1), "{err}");
    assert!(err.contains(&format!("Robot4_Groundtruth.dat:{}: time 1248444200 s is before", n + 1)), "{err}");
    std::fs::write(&truth, &saved).unwrap();

    // A time far in the future (a damaged digit): refused, not scored for years at 10 Hz.
    let meas1 = dir.join("Robot1_Measurement.dat");
    let saved = std::fs::read(&meas1).unwrap();
    append(&meas1, "2248444296.000 \t  14 \t  1.5 \t 0.1 \r\n");
    let (code, _, err) = import(&dir);
    assert_eq!(code, Some(1), "{err}");
    assert!(err.contains("Robot1_Measurement.dat: its last time 2248444296 s"), "{err}");
    std::fs::write(&meas1, &saved).unwrap();

    // Bytes that are not text.
    std::fs::write(dir.join("Barcodes.dat"), b"# header\n1 5\n\xff\xfe\n").unwrap();
    let (code, _, err) = import(&dir);
    assert_eq!(code, Some(1), "{err}");
    assert!(err.contains("Barcodes.dat: not text"), "{err}");
    std::fs::write(
        dir.join("Barcodes.dat"),
        zstd::decode_all(std::fs::File::open(data_dir().join("Barcodes.dat.zst")).unwrap()).unwrap(),
    )
    .unwrap();

    // An unknown barcode and a self-observation: counted and dropped, the import goes on.
    let meas5 = dir.join("Robot5_Measurement.dat");
    append(&meas5, "1248444296.000 \t  99 \t  1.5 \t 0.1 \r\n1248444296.100 \t  23 \t  1.5 \t 0.1 \r\n");
    let (code, out, err) = import(&dir);
    assert_eq!(code, Some(0), "{err}");
    assert!(out.contains("dropped: 1 observations of unknown barcodes (robot 5 barcode 99 x1), 1 self-observations"), "{out}");
    std::fs::remove_dir_all(&dir).unwrap();
}

#[test]
fn a_log_that_is_not_a_data_set_or_is_damaged_is_refused_by_name() {
    let dir = excerpt("badlog");
    let ds = mrclam::read_folder(&dir).unwrap();
    let path = dir.join("ds.mcap");
    log::write(&ds.excerpt(20.0), &cooploc::dataset::noise::NoiseModel::mrclam(), &path, None).unwrap();
    // Cut the file in half: the reader keeps what is before the damage; the replay says so
    // and runs on what it has, or refuses by name, and never panics.
    let bytes = std::fs::read(&path).unwrap();
    std::fs::write(&path, &bytes[..bytes.len() / 2]).unwrap();
    let out = cooploc(&["replay", path.to_str().unwrap(), "--method", "dr"]);
    assert!(matches!(out.status.code(), Some(0) | Some(1)), "{out:?}");
    let text = format!("{}{}", String::from_utf8_lossy(&out.stdout), String::from_utf8_lossy(&out.stderr));
    assert!(!text.contains("panicked"), "{text}");
    std::fs::remove_dir_all(&dir).unwrap();
}

/// The data set log opens in the Python `mcap` reader and every raw frame decodes in pymavlink:
/// the commands and observations the Rust reader reads, with the same first observation.
#[test]
fn independent_readers_open_the_data_set_log() {
    let Some(python) = common::python("the data set log check") else { return };
    let dir = excerpt("python");
    let ds = mrclam::read_folder(&dir).unwrap();
    let path = dir.join("ds.mcap");
    let view = {
        let mut s = Settings::new(cooploc::dataset::noise::NoiseModel::mrclam());
        s.keep_track = true;
        run(&ds, &s, Regime::MapBlind, Method::Decentralized).unwrap()
    };
    log::write(&ds, &cooploc::dataset::noise::NoiseModel::mrclam(), &path, Some(&view)).unwrap();
    let out = Command::new(&python)
        .arg(Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/python/dataset_log_check.py"))
        .arg(Path::new(env!("CARGO_MANIFEST_DIR")).join("dialects/cooploc.xml"))
        .arg(&path)
        .output()
        .unwrap();
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let report: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    for r in &ds.robots {
        let got = &report["robots"][r.id.to_string()];
        assert_eq!(got["bad"], 0, "robot {}: {got}", r.id);
        assert_eq!(got["ODOMETRY"], r.commands.len(), "robot {}", r.id);
        assert_eq!(got["COOPLOC_RANGE_BEARING"], r.observations.len(), "robot {}", r.id);
        assert_eq!(got["truth"], r.truth.len(), "robot {}", r.id);
        let track = &view.track.iter().find(|t| t.0 == r.id).unwrap().1;
        assert_eq!(got["pose"], track.len(), "robot {}: the estimates shown", r.id);
        let o = &r.observations[0];
        let first = &got["first_observation"];
        assert_eq!(first["time_usec"], o.t.0);
        assert_eq!(first["observer"], r.id);
        assert!((first["range"].as_f64().unwrap() - o.range_m).abs() < 1e-6);
        assert!((first["bearing"].as_f64().unwrap() - o.bearing_rad).abs() < 1e-6);
        let (target, kind) = match o.target {
            cooploc::dataset::Target::Robot(id) => (id, 0),
            cooploc::dataset::Target::Landmark(id) => (id, 1),
        };
        assert_eq!((first["target"].as_u64().unwrap(), first["target_kind"].as_u64().unwrap()), (u64::from(target), kind));
    }
    std::fs::remove_dir_all(&dir).unwrap();
}
