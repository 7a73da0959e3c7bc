//! `cooploc dataset mrclam DIR [--out LOG] [--method M] [--regime R] [--estimate-noise]`: see
//! [`cooploc::dataset`].

use std::path::PathBuf;
use std::time::Instant;

use anyhow::{Context, bail};
use cooploc::dataset::noise::{self, NoiseModel};
use cooploc::dataset::run::{Outcome, Regime, Settings, broadcast_bytes, nees_band, run, run_all};
use cooploc::dataset::{Dataset, log, mrclam};
use cooploc::estimation::{Method, PlatformId};

#[derive(clap::Args)]
pub struct Args {
    #[command(subcommand)]
    kind: Kind,
}

#[derive(clap::Subcommand)]
enum Kind {
    /// A UTIAS MRCLAM data set folder (Barcodes.dat, Landmark_Groundtruth.dat,
    /// RobotN_{Odometry,Measurement,Groundtruth}.dat).
    Mrclam(MrclamArgs),
}

#[derive(clap::Args)]
struct MrclamArgs {
    /// The data set folder.
    dir: PathBuf,
    /// Write the data set as a cooploc MCAP log here (then `cooploc replay LOG --method all`).
    #[arg(long)]
    out: Option<PathBuf>,
    /// Run these methods (comma separated, or all) and print the table; with --out the runs
    /// read the log back, so the table is the replay's.
    #[arg(long, value_enum, value_delimiter = ',')]
    method: Vec<crate::args::MethodsArg>,
    /// Regimes to run (comma separated, or all).
    #[arg(long, value_enum, value_delimiter = ',', default_value = "all")]
    regime: Vec<crate::args::RegimesArg>,
    /// The robots that see landmarks in the map-blind regime.
    #[arg(long, value_delimiter = ',', default_value = "1,2")]
    map_robots: Vec<PlatformId>,
    /// A noise model file instead of the committed MRCLAM figures (src/dataset/mrclam_noise.toml).
    #[arg(long)]
    noise: Option<PathBuf>,
    /// Print the noise figures estimated from this folder against its ground truth.
    #[arg(long)]
    estimate_noise: bool,
    /// With --out: the method whose estimates the log shows beside the truth (map-blind regime).
    #[arg(long, value_enum, default_value = "dcl")]
    view: crate::args::MethodArg,
    /// With --out: inputs and truth only, no estimates.
    #[arg(long)]
    no_view: bool,
    /// Only the first SECONDS of the data set (from its first ground-truth time).
    #[arg(long)]
    excerpt: Option<f64>,
    /// Identify the noise model from the data's own innovations (no ground truth; see
    /// src/dataset/identify.rs), print it and run with it. The figures it does not identify
    /// (gate, Huber threshold, priors, first estimates) come from --noise or the committed file.
    #[arg(long)]
    identify: bool,
    /// With --identify: identify on this stretch only, FROM:TO seconds from the start.
    #[arg(long, value_parser = parse_span, requires = "identify")]
    identify_span: Option<(f64, f64)>,
    /// Run and score on this stretch only, FROM:TO seconds from the start (each robot starts at
    /// its first ground-truth pose in it).
    #[arg(long, value_parser = parse_span)]
    span: Option<(f64, f64)>,
    /// With --identify: write the identified noise model here (TOML, for --noise).
    #[arg(long, requires = "identify")]
    write_noise: Option<PathBuf>,
}

fn parse_span(s: &str) -> Result<(f64, f64), String> {
    let (a, b) = s.split_once(':').ok_or_else(|| format!("{s}: expected FROM:TO in seconds"))?;
    let a: f64 = a.trim().parse().map_err(|_| format!("{s}: FROM is not a number"))?;
    let b: f64 = b.trim().parse().map_err(|_| format!("{s}: TO is not a number"))?;
    if !(a.is_finite() && b.is_finite() && a >= 0.0 && b > a) {
        return Err(format!("{s}: expected 0 <= FROM < TO"));
    }
    Ok((a, b))
}

pub fn run_cmd(args: Args) -> anyhow::Result<()> {
    match args.kind {
        Kind::Mrclam(a) => mrclam_cmd(a),
    }
}

fn mrclam_cmd(a: MrclamArgs) -> anyhow::Result<()> {
    let start = Instant::now();
    let mut ds = mrclam::read_folder(&a.dir)?;
    if let Some(s) = a.excerpt {
        if !(s.is_finite() && s > 0.0) {
            bail!("--excerpt {s}: expected a positive number of seconds");
        }
        ds = ds.excerpt(s);
    }
    let read_s = start.elapsed().as_secs_f64();
    let mut noise = match &a.noise {
        Some(p) => {
            let text = std::fs::read_to_string(p).with_context(|| format!("reading {}", p.display()))?;
            NoiseModel::from_toml_str(&text).map_err(|e| anyhow::anyhow!("{}: {e}", p.display()))?
        }
        None => NoiseModel::mrclam(),
    };
    print_summary(&ds);
    println!("read in {read_s:.2} s");
    if a.estimate_noise {
        print_noise_estimate(&ds, noise.stale_command_s);
    }
    if a.identify {
        let on = match a.identify_span {
            Some((from, to)) => ds.window(from, to),
            None => ds.clone(),
        };
        noise = identify_noise(&on, &noise, a.identify_span, a.write_noise.as_deref())?;
    } else {
        println!(
            "noise model: {}",
            match &a.noise {
                Some(p) => format!("{} (--noise)", p.display()),
                None => "the committed src/dataset/mrclam_noise.toml (identified on data set 6 from its innovations)".into(),
            }
        );
    }
    if let Some((from, to)) = a.span {
        ds = ds.window(from, to);
        println!("running on {from:.0}-{to:.0} s ({:.1} s)", ds.t_end.secs_since(ds.t0));
    }
    let mut ds_for_runs = ds;
    let mut noise_for_runs = noise;
    if let Some(out) = &a.out {
        let t = Instant::now();
        let view = if a.no_view {
            None
        } else {
            let mut settings = Settings::new(noise);
            settings.map_robots = a.map_robots.clone();
            settings.keep_track = true;
            Some(run(&ds_for_runs, &settings, Regime::MapBlind, a.view.0)?)
        };
        let n = log::write(&ds_for_runs, &noise, out, view.as_ref()).with_context(|| format!("writing {}", out.display()))?;
        let size = std::fs::metadata(out).map(|m| m.len()).unwrap_or(0);
        println!("wrote {} ({n} messages, {:.1} MB) in {:.2} s", out.display(), size as f64 / 1e6, t.elapsed().as_secs_f64());
        if !a.method.is_empty() {
            let t = Instant::now();
            let read = cooploc::recording::read_log(out).with_context(|| format!("reading back {}", out.display()))?;
            let logged = log::read(&read)?;
            println!("read back in {:.2} s ({} frames rejected)", t.elapsed().as_secs_f64(), logged.rejected_frames);
            ds_for_runs = logged.dataset;
            noise_for_runs = logged.noise;
        }
    }
    if !a.method.is_empty() {
        let methods = crate::args::methods_of(&a.method);
        let regimes = crate::args::regimes_of(&a.regime);
        let mut settings = Settings::new(noise_for_runs);
        settings.map_robots = a.map_robots.clone();
        evaluate(&ds_for_runs, &settings, &regimes, &methods)?;
    }
    println!("total {:.2} s", start.elapsed().as_secs_f64());
    Ok(())
}

fn identify_noise(
    ds: &Dataset,
    base: &NoiseModel,
    span: Option<(f64, f64)>,
    write: Option<&std::path::Path>,
) -> anyhow::Result<NoiseModel> {
    use cooploc::dataset::identify;
    let t = Instant::now();
    let id = identify::identify(ds, &identify::start(base), &identify::Options::default())?;
    let (s, b) = (&id.start, &id.best);
    println!(
        "noise identified from the innovations of dcl (full map) on {}: maximum likelihood, no ground truth (src/dataset/identify.rs)",
        match span {
            Some((from, to)) => format!("{from:.0}-{to:.0} s"),
            None => "the whole data set".into(),
        }
    );
    println!(
        "  {} iterations, {} runs, {:.1} s; -log likelihood {:.1} -> {:.1}; NIS per scalar landmarks {:.2} -> {:.2}, teammates {:.2} -> {:.2}; gated landmarks {} -> {} of {}, teammates {} -> {} of {}",
        id.iterations,
        id.evaluations,
        t.elapsed().as_secs_f64(),
        s.cost,
        b.cost,
        s.landmark_nis,
        b.landmark_nis,
        s.robot_nis,
        b.robot_nis,
        s.landmark_gated,
        b.landmark_gated,
        b.landmark_gated + b.landmark_used,
        s.robot_gated,
        b.robot_gated,
        b.robot_gated + b.robot_used
    );
    for line in identify::describe(&id) {
        println!("  {line}");
    }
    if let Some(path) = write {
        let mut text = format!(
            "# Identified by cooploc dataset --identify on {} (maximum likelihood on the innovations, no ground truth)\n",
            ds.name
        );
        text.push_str(&toml::to_string(&b.model)?);
        std::fs::write(path, text).with_context(|| format!("writing {}", path.display()))?;
        println!("  written to {}", path.display());
    }
    Ok(b.model)
}

fn print_summary(ds: &Dataset) {
    let span = ds.t_end.secs_since(ds.t0);
    println!("data set {}: {} robots, {} landmarks, {span:.1} s", ds.name, ds.robots.len(), ds.landmarks.len());
    for r in &ds.robots {
        let lm = r.observations.iter().filter(|o| matches!(o.target, cooploc::dataset::Target::Landmark(_))).count();
        let truth_end = r.truth.last().map_or(0.0, |p| p.t.secs_since(ds.t0));
        let gaps: Vec<String> = r
            .truth
            .windows(2)
            .filter(|w| w[1].t.0 - w[0].t.0 > cooploc::dataset::MAX_TRUTH_GAP_US)
            .map(|w| format!("{:.2} s at {:.1} s", w[1].t.secs_since(w[0].t), w[0].t.secs_since(ds.t0)))
            .collect();
        println!(
            "  robot {}: {} commands, {} observations ({lm} of landmarks, {} of teammates), {} truth poses to {truth_end:.1} s{}",
            r.id,
            r.commands.len(),
            r.observations.len(),
            r.observations.len() - lm,
            r.truth.len(),
            if gaps.is_empty() { String::new() } else { format!(", truth gaps masked: {}", gaps.join(", ")) }
        );
    }
    let c = &ds.counts;
    let unknown: Vec<String> = c.unknown_barcodes.iter().map(|(r, b, n)| format!("robot {r} barcode {b} x{n}")).collect();
    println!(
        "  dropped: {} observations of unknown barcodes{}, {} self-observations; merged: {} repeated command stamps, {} repeated truth stamps",
        c.unknown_barcode_total(),
        if unknown.is_empty() { String::new() } else { format!(" ({})", unknown.join(", ")) },
        c.self_observation_total(),
        c.repeated_command_times.iter().map(|x| x.1).sum::<usize>(),
        c.repeated_truth_times.iter().map(|x| x.1).sum::<usize>(),
    );
}

fn print_noise_estimate(ds: &Dataset, stale: f64) {
    let e = noise::estimate(ds, stale, 1.0);
    let line = |name: &str, s: &noise::Stat, unit: &str| {
        println!(
            "  {name:<18} n {:>6}  outliers {:>4}  mean {:>+9.4} {unit}  sigma {:>8.4} {unit}",
            s.n, s.outliers, s.mean, s.sigma
        )
    };
    println!("noise estimated against the ground truth:");
    line("landmark range", &e.landmark_range_m, "m");
    line("landmark bearing", &e.landmark_bearing_rad, "rad");
    line("teammate range", &e.robot_range_m, "m");
    line("teammate bearing", &e.robot_bearing_rad, "rad");
    line("1-s distance", &e.window_distance_m, "m");
    line("1-s heading", &e.window_heading_rad, "rad");
    println!(
        "  densities: speed {:.5} m/s/sqrt(Hz), yaw rate {:.5} rad/s/sqrt(Hz); travelled {:+.1}% of the commanded distance",
        e.speed_density(),
        e.yaw_rate_density(),
        100.0 * e.window_distance_m.mean / e.window_commanded_m
    );
    for w in [2.0, 5.0, 10.0, 20.0] {
        let e = noise::estimate(ds, stale, w);
        println!(
            "  over {w:>4.0}-s windows: distance sigma {:.4} m, heading sigma {:.4} rad ({} outliers of {}): densities {:.5}, {:.5}",
            e.window_distance_m.sigma,
            e.window_heading_rad.sigma,
            e.window_heading_rad.outliers,
            e.window_heading_rad.n + e.window_heading_rad.outliers,
            e.speed_density(),
            e.yaw_rate_density()
        );
    }
}

/// `used/gated (share)/weighted below one half`.
fn counts(used: usize, gated: usize, below_half: usize) -> String {
    let all = (used + gated).max(1) as f64;
    format!("{used}/{gated} ({:.2}%)/{below_half}", 100.0 * gated as f64 / all)
}

/// Runs every (regime, method) pair in parallel and prints the table; returns the outcomes with
/// their runtimes (s).
pub fn evaluate(
    ds: &Dataset,
    settings: &Settings,
    regimes: &[Regime],
    methods: &[Method],
) -> anyhow::Result<Vec<(Outcome, f64)>> {
    let t = Instant::now();
    let results = run_all(ds, settings, regimes, methods)?;
    let (lo, hi) = nees_band(ds.robots.len());
    let span = ds.t_end.secs_since(ds.t0);
    println!(
        "every method on {} ({span:.0} s, scored every {:.1} s against the ground truth; map-blind: landmarks for robots {:?}; NEES of [dN, dE, dyaw], 95% band of the team mean {lo:.2}-{hi:.2}):",
        ds.name,
        settings.score_period_us as f64 / 1e6,
        settings.map_robots
    );
    println!(
        "{:<13}{:<12}{:>7}{:>9}{:>9}{:>15}{:>8}{:>27}{:>27}{:>8}{:>7}{:>8}{:>7}",
        "regime",
        "method",
        "pos m",
        "hdg deg",
        "NEES",
        "(pos, hdg)",
        "in 95%",
        "landmarks used/gated/w<.5",
        "teammates used/gated/w<.5",
        "epochs",
        "s",
        "dcl kB",
        "B/s"
    );
    for (o, secs) in &results {
        let bytes = if o.method == Method::Decentralized {
            let b = broadcast_bytes(ds.robots.len(), o.epochs, o.robot_updates + o.robot_gated).map_err(anyhow::Error::msg)?;
            (format!("{:.0}", b as f64 / 1e3), format!("{:.0}", b as f64 / span))
        } else {
            ("-".into(), "-".into())
        };
        println!(
            "{:<13}{:<12}{:>7.3}{:>9.2}{:>9.2}{:>15}{:>7.1}%{:>27}{:>27}{:>8}{:>7.2}{:>8}{:>7}",
            o.regime.name(),
            o.method.short_name(),
            o.pos_rmse_m,
            o.heading_rmse_deg,
            o.avg_nees,
            format!("{:.1}, {:.1}", o.avg_nees_position, o.avg_nees_heading),
            100.0 * o.in_bound_share,
            counts(o.landmark_updates, o.landmark_gated, o.landmark_weight_below_half),
            counts(o.robot_updates, o.robot_gated, o.robot_weight_below_half),
            o.epochs,
            secs,
            bytes.0,
            bytes.1
        );
    }
    println!(
        "gate: chi-square, false-rejection probability {} per observation{}; w<.5: applied with a Huber weight under 0.5",
        settings.noise.gate_probability,
        match settings.noise.huber() {
            Some(c) => format!("; Huber weights above NIS {c} (range and bearing)"),
            None => ", no Huber weighting".into(),
        }
    );
    if let Some((o, _)) = results.first() {
        let masked: Vec<String> =
            o.robots.iter().filter(|r| r.masked > 0).map(|r| format!("robot {} {}", r.id, r.masked)).collect();
        println!(
            "scored {} robot-instants; masked (no ground truth): {}",
            o.samples,
            if masked.is_empty() { "none".into() } else { masked.join(", ") }
        );
    }
    let refused: usize = results.iter().map(|r| r.0.refused).sum();
    if refused > 0 {
        println!("updates refused as numerically unusable: {refused}");
    }
    println!("{} runs in {:.2} s", results.len(), t.elapsed().as_secs_f64());
    Ok(results)
}
