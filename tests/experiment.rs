//! The paper's experiment end to end: the world and the INS agree on the physics, and the
//! `cooploc experiment` command reproduces the paper's comparisons on the paper scenario.

use std::process::Command;

use cooploc::estimation::ins::{InsConfig, InsFilter, InsInitialSigma, InsState};
use cooploc::estimation::unicycle::wrap_angle;
use cooploc::sitl::{PAPER_TOML, Scenario, World};
use nalgebra::Vector3;

/// With every sensor error set to zero, the unaided INS rides the truth of every paper path
/// (turns, speed changes, Earth rotation) for the whole 380 s to centimetres: the mechanization
/// (coning, sculling, rotation corrections) and the world's IMU model are the same physics.
#[test]
fn noise_free_ins_stays_on_the_truth_to_centimetres() {
    let mut scenario = Scenario::from_toml_str(PAPER_TOML).unwrap();
    let s = &mut scenario.sensors;
    s.accel_bias_ug = 0.0;
    s.accel_noise_ug_per_sqrt_hz = 0.0;
    s.gyro_bias_deg_h = 0.0;
    s.gyro_arw_deg_per_sqrt_h = 0.0;
    let world = World::new(&scenario).unwrap();
    let config = InsConfig { latitude_deg: scenario.latitude_deg, gravity_m_s2: scenario.gravity_m_s2, ..InsConfig::default() };
    let sigma = InsInitialSigma {
        pos_ned_m: Vector3::repeat(0.1),
        vel_ned_m_s: Vector3::repeat(0.1),
        att_ned_rad: Vector3::repeat(1e-3),
        accel_bias_frd_m_s2: Vector3::repeat(1e-3),
        gyro_bias_frd_rad_s: Vector3::repeat(1e-5),
        odometer_scale: 0.0,
    };
    for id in world.platform_ids() {
        let traj = world.trajectory(id).unwrap();
        let t0 = traj.truth_at(cooploc::time::TimeUs(0));
        let state = InsState {
            pos_ned_m: t0.pos_ned_m,
            vel_ned_m_s: t0.vel_ned_m_s,
            att_frd_to_ned: t0.attitude,
            ..InsState::at_rest(t0.attitude)
        };
        let mut ins = InsFilter::new(config, t0.t, state, sigma).unwrap();
        let mut worst = (0.0f64, 0.0f64);
        for s in world.imu(1, 0, id).unwrap() {
            ins.propagate(&s).unwrap();
            if s.t.0 % 1_000_000 == 0 {
                let truth = traj.truth_at(s.t);
                worst.0 = worst.0.max((truth.pos_ned_m - ins.position_ned_m()).norm());
                worst.1 = worst.1.max(wrap_angle(truth.yaw_rad - ins.yaw_rad()).abs());
            }
        }
        assert_eq!(ins.time(), world.end());
        assert!(worst.0 < 0.02, "platform {id}: position error up to {:.4} m", worst.0);
        assert!(worst.1 < 1e-6, "platform {id}: yaw error up to {:.2e} rad", worst.1);
    }
}

fn cooploc() -> Command {
    Command::new(env!("CARGO_BIN_EXE_cooploc"))
}

/// The paper's experiment as the README runs it (50 runs, seed 1), checked on the command's own
/// JSON output: dead reckoning in the paper's 6-12 m band with heading error near 0.5 deg (the
/// INS, its error model and the world are right), decentralized equal to centralized within 5%
/// in position RMS, and covariance transfer better than none over four events.
#[test]
fn paper_experiment_reproduces_the_papers_comparisons() {
    let out = run_paper_experiment("paper", 50, 1);
    let json: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(out.join("summary.json")).unwrap()).unwrap();
    let schedule = |name: &str| json["schedules"].as_array().unwrap().iter().find(|s| s["schedule"] == name).unwrap().clone();
    let avg = |s: &serde_json::Value, method: &str, field: &str| {
        let m = s["methods"].as_array().unwrap().iter().find(|m| m["method"] == method).unwrap();
        let ps = m["platforms"].as_array().unwrap();
        ps.iter().map(|p| p[field].as_f64().unwrap()).sum::<f64>() / ps.len() as f64
    };
    let hz = schedule("1hz");
    let dr_pos = avg(&hz, "dead-reckoning", "final_pos_err_mean_m");
    let dr_hdg = avg(&hz, "dead-reckoning", "final_heading_err_rms_deg");
    assert!((6.0..=12.0).contains(&dr_pos), "dead reckoning final position error {dr_pos:.2} m outside the paper's 6-12 m");
    assert!((0.35..=0.65).contains(&dr_hdg), "dead reckoning heading error {dr_hdg:.3} deg not near 0.5 deg");
    for s in [&hz, &schedule("four-events")] {
        let dcl = avg(s, "decentralized", "final_pos_err_rms_m");
        let cen = avg(s, "centralized", "final_pos_err_rms_m");
        assert!((dcl - cen).abs() <= 0.05 * cen, "decentralized {dcl:.3} m vs centralized {cen:.3} m (position RMS)");
    }
    let four = schedule("four-events");
    let dcl = avg(&four, "decentralized", "final_pos_err_mean_m");
    let naive = avg(&four, "no-propagation", "final_pos_err_mean_m");
    assert!(dcl < naive, "four events: decentralized {dcl:.2} m should beat no-propagation {naive:.2} m");
    let cl = avg(&hz, "decentralized", "final_pos_err_mean_m");
    assert!(cl < 0.7 * dr_pos, "1 Hz: cooperative {cl:.2} m vs dead reckoning {dr_pos:.2} m");
    let _ = std::fs::remove_dir_all(&out);
}

/// Runs `cooploc experiment` on the paper scenario (`--no-plots`) into a fresh temporary
/// folder named by `tag`; returns the folder. Fails the test with the command's stderr.
fn run_paper_experiment(tag: &str, runs: u32, seed: u64) -> std::path::PathBuf {
    let out = tempfile_dir(tag);
    let (runs, seed) = (runs.to_string(), seed.to_string());
    let status = cooploc()
        .args(["experiment", "sitl/scenarios/paper.toml", "--runs", &runs, "--seed", &seed, "--no-plots", "--out"])
        .arg(&out)
        .current_dir(env!("CARGO_MANIFEST_DIR"))
        .output()
        .unwrap();
    assert!(status.status.success(), "{}", String::from_utf8_lossy(&status.stderr));
    out
}

fn tempfile_dir(tag: &str) -> std::path::PathBuf {
    let dir = std::env::temp_dir().join(format!("cooploc-test-{tag}-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    dir
}

/// The commands that take a scenario run from any folder: without one they use the paper's,
/// built into the binary, with the same results as the file in the repository (the real
/// firmware showed a node that could not start outside the repository; an installed `cooploc
/// experiment` or `faults` could not either).
#[test]
fn without_a_scenario_file_the_commands_run_the_built_in_paper_scenario_from_any_folder() {
    let empty = tempfile_dir("empty-folder");
    let ours = run_paper_experiment("from-file", 1, 3);
    let out = cooploc()
        .args(["experiment", "--runs", "1", "--seed", "3", "--no-plots", "--out", "out"])
        .current_dir(&empty)
        .output()
        .unwrap();
    let stdout = String::from_utf8_lossy(&out.stdout);
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    assert!(stdout.contains("built in"), "the output says which scenario ran: {stdout}");
    for file in ["final_errors.csv", "error_curves.csv"] {
        let (a, b) = (std::fs::read(ours.join(file)).unwrap(), std::fs::read(empty.join("out").join(file)).unwrap());
        assert!(a == b, "{file} differs between the built-in scenario and sitl/scenarios/paper.toml");
    }
    let faults = cooploc().args(["faults", "--runs", "1", "--only", "fault-free"]).current_dir(&empty).output().unwrap();
    assert!(faults.status.success(), "{}", String::from_utf8_lossy(&faults.stderr));
    let missing = cooploc().args(["faults", "--runs", "1", "no-such.toml"]).current_dir(&empty).output().unwrap();
    assert!(!missing.status.success() && String::from_utf8_lossy(&missing.stderr).contains("no-such.toml"));
    let _ = std::fs::remove_dir_all(&empty);
    let _ = std::fs::remove_dir_all(&ours);
}

/// A broken scenario file is refused with a message that names the field, and nothing is run.
#[test]
fn bad_scenario_files_name_the_field() {
    let dir = tempfile_dir("bad");
    let cases = [
        ("missing field", PAPER_TOML.replacen("duration_s = 380.0", "", 1), "duration_s"),
        ("negative rate", PAPER_TOML.replacen("imu_rate_hz = 200.0", "imu_rate_hz = -200.0", 1), "imu_rate_hz"),
        ("unknown key", PAPER_TOML.replacen("[sensors]", "[sensors]\ngyro_bais_deg_h = 3.0", 1), "gyro_bais_deg_h"),
    ];
    for (what, text, field) in cases {
        assert_ne!(text, PAPER_TOML, "{what}: the edit must change the file");
        let path = dir.join("bad.toml");
        std::fs::write(&path, text).unwrap();
        let out = cooploc()
            .args(["experiment", "--runs", "1", "--no-plots", "--out"])
            .arg(dir.join("out"))
            .arg(&path)
            .output()
            .unwrap();
        assert!(!out.status.success(), "{what}: accepted");
        let stderr = String::from_utf8_lossy(&out.stderr);
        assert!(stderr.contains(field), "{what}: error does not name {field}: {stderr}");
        assert!(!dir.join("out").exists(), "{what}: wrote results anyway");
    }
    let _ = std::fs::remove_dir_all(&dir);
}

/// The experiment's outputs are those of the code before the speed work, bit for bit: every
/// speed-up must leave every number alone (tests/golden/experiment-paper-3runs-seed7/README.md).
#[test]
fn experiment_outputs_are_unchanged_bit_for_bit() {
    use sha2::Digest;
    let golden = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/golden/experiment-paper-3runs-seed7");
    let out = run_paper_experiment("golden", 3, 7);
    let curves = std::fs::read(out.join("error_curves.csv")).unwrap();
    let digest: String = sha2::Sha256::digest(&curves).iter().map(|b| format!("{b:02x}")).collect();
    let bless = std::env::var_os("COOPLOC_BLESS").is_some();
    if bless {
        for f in ["summary.json", "final_errors.csv"] {
            std::fs::copy(out.join(f), golden.join(f)).unwrap();
        }
        std::fs::write(golden.join("error_curves.csv.sha256"), format!("{digest}  error_curves.csv\n")).unwrap();
    }
    for f in ["summary.json", "final_errors.csv"] {
        let (got, want) = (std::fs::read_to_string(out.join(f)).unwrap(), std::fs::read_to_string(golden.join(f)).unwrap());
        if let Some((i, (g, w))) = got.lines().zip(want.lines()).enumerate().find(|(_, (g, w))| g != w) {
            panic!("{f} line {}: got `{g}`, golden `{w}`", i + 1);
        }
        assert_eq!(got.len(), want.len(), "{f}: same lines but different length");
    }
    let want = std::fs::read_to_string(golden.join("error_curves.csv.sha256")).unwrap();
    assert_eq!(want.split_whitespace().next(), Some(digest.as_str()), "error_curves.csv differs from the golden digest");
    let _ = std::fs::remove_dir_all(&out);
}

/// A Monte Carlo keeps its first run whole (the one plotted) and of every other run its final
/// samples; its curves are the sums of every run in run order, whatever order the parallel runs
/// finish in: the summary equals the one made from every run whole.
#[test]
fn the_monte_carlo_keeps_the_plotted_run_whole_and_sums_the_others_in_order() {
    use cooploc::estimation::Method;
    use cooploc::experiment::report::{CurveSums, summarize};
    use cooploc::experiment::{ExperimentSpec, InputSource, run_experiment, run_once};
    let world = World::new(&Scenario::from_toml_str(PAPER_TOML).unwrap()).unwrap();
    let spec = ExperimentSpec {
        runs: 6,
        seed: 7,
        methods: vec![Method::DeadReckoning, Method::Decentralized],
        schedules: vec!["four-events".into()],
        source: InputSource::World,
    };
    let mc = run_experiment(&world, &spec, &|| {}).unwrap();
    assert_eq!(mc.runs.iter().map(|r| r.run).collect::<Vec<_>>(), [0, 1, 2, 3, 4, 5]);
    let whole: Vec<_> = (0..spec.runs).map(|run| run_once(&world, &spec, run).unwrap()).collect();
    let mut sums = CurveSums::default();
    for (r, alone) in mc.runs.iter().zip(&whole) {
        sums.add(alone);
        for p in r.schedules.iter().flat_map(|(_, runs)| runs).flat_map(|fr| &fr.platforms) {
            let expected = if r.run == 0 { (3801, 3801) } else { (1, 0) };
            assert_eq!((p.trace.len(), p.track_ne_m.len()), expected, "run {}", r.run);
        }
        let mut trimmed = alone.clone();
        if r.run > 0 {
            trimmed.keep_final_only();
        }
        assert_eq!(r, &trimmed, "run {}", r.run);
    }
    assert_eq!(mc.curves, sums);
    assert_eq!(summarize(&spec, &mc.runs, &mc.curves), summarize(&spec, &whole, &sums));
    // The curves come from the sums: the first run's alone give another summary.
    let mut one = CurveSums::default();
    one.add(&whole[0]);
    assert_ne!(summarize(&spec, &whole[..1], &one), summarize(&spec, &whole, &sums));
}
