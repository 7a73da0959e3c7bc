//! `cooploc experiment`: arguments, progress bar and printing around [`cooploc::experiment`].

use std::path::PathBuf;
use std::time::Instant;

use anyhow::{Context, bail};
use cooploc::estimation::Method;
use cooploc::experiment::report::{self, Tracks};
use cooploc::experiment::{ExperimentSpec, InputSource, run_experiment};
use cooploc::node::autopilot::RateRequests;
use cooploc::node::profile::{Inputs, VehicleProfile};
use cooploc::sitl::world::World;

#[derive(clap::Args)]
pub struct Args {
    /// Scenario file (default: the paper's scenario, built in: sitl/scenarios/paper.toml).
    scenario: Option<PathBuf>,
    /// Number of Monte Carlo runs.
    #[arg(long, default_value_t = 50)]
    runs: u32,
    /// Seed of the whole experiment (run k uses seed and k).
    #[arg(long, default_value_t = 1)]
    seed: u64,
    /// Directory for summary.json, the CSV files and the plots.
    #[arg(long, default_value = "experiment-out")]
    out: PathBuf,
    /// Methods, comma separated.
    #[arg(long, value_enum, value_delimiter = ',', default_value = "dr,naive,dcl,centralized,ci")]
    methods: Vec<crate::args::MethodArg>,
    /// The radios' reach, m: two vehicles range only while at most this far apart (default:
    /// the scenario's).
    #[arg(long)]
    reach_m: Option<f64>,
    /// Ranging schedules of the scenario, comma separated (default: all of them).
    #[arg(long, value_delimiter = ',')]
    schedules: Vec<String>,
    /// Worker threads (default: all cores).
    #[arg(long)]
    threads: Option<usize>,
    /// Skip the plots (tables, CSV and JSON only).
    #[arg(long)]
    no_plots: bool,
    /// A vehicle profile (sitl/vehicles/*.toml) whose vehicle replaces the scenario's.
    #[arg(long)]
    vehicle_config: Option<PathBuf>,
    /// Feed the filters what this autopilot sends (ardupilot, px4, cooploc), as the node
    /// decodes it with the profile (needs --vehicle-config).
    #[arg(long)]
    autopilot: Option<cooploc::simulator::Autopilot>,
    /// The autopilot's stream rates, repeatable `MESSAGE=HZ` (default: the rates the profile
    /// asks for, as if the request had landed at boot).
    #[arg(long = "stream-rate", value_name = "MESSAGE=HZ", value_parser = crate::sitl::parse_stream_rate)]
    stream_rates: Vec<(u32, f64)>,
}

pub fn run(args: Args) -> anyhow::Result<()> {
    let mut methods = Vec::new();
    for &crate::args::MethodArg(method) in &args.methods {
        if methods.contains(&method) {
            bail!("method {method} given twice");
        }
        methods.push(method);
    }
    let mut scenario = crate::args::scenario_or_paper(args.scenario.as_deref())?;
    crate::args::limit_reach(&mut scenario, args.reach_m)?;
    // A vehicle profile replaces the scenario's vehicle; an autopilot sends its samples.
    let source = match (&args.vehicle_config, args.autopilot) {
        (Some(path), autopilot) => {
            let profile = VehicleProfile::from_path(path)?;
            scenario
                .put_vehicle(&profile.spec())
                .with_context(|| format!("the scenario with the vehicle of {}", profile.name))?;
            match autopilot {
                Some(autopilot) => {
                    let rates = if args.stream_rates.is_empty() {
                        let asked = VehicleProfile {
                            inputs: Inputs { request_rates: true, ..profile.inputs.clone() },
                            ..profile.clone()
                        };
                        RateRequests::new(&asked, 1).requests.iter().map(|r| (r.message_id, r.rate_hz)).collect()
                    } else {
                        args.stream_rates.clone()
                    };
                    InputSource::Autopilot { autopilot, inputs: profile.inputs.clone(), rates }
                }
                None => InputSource::World,
            }
        }
        (None, Some(_)) => bail!("--autopilot needs --vehicle-config (the profile says how the node reads the autopilot)"),
        (None, None) => InputSource::World,
    };
    let world = World::new(&scenario)?;
    let schedules = if args.schedules.is_empty() {
        scenario.ranging.schedules.iter().map(|s| s.name.clone()).collect()
    } else {
        args.schedules.clone()
    };
    let spec = ExperimentSpec { runs: args.runs, seed: args.seed, methods, schedules, source };
    if let Some(n) = args.threads {
        rayon::ThreadPoolBuilder::new().num_threads(n).build_global().context("setting the thread count")?;
    }

    let bar = indicatif::ProgressBar::new(u64::from(spec.runs));
    bar.set_style(
        indicatif::ProgressStyle::with_template("{elapsed_precise} [{bar:40}] {pos}/{len} runs, eta {eta}")
            .expect("valid template")
            .progress_chars("=> "),
    );
    let started = Instant::now();
    let monte_carlo = run_experiment(&world, &spec, &|| bar.inc(1))?;
    bar.finish_and_clear();
    let elapsed = started.elapsed();
    let results = &monte_carlo.runs;

    let summaries = report::summarize(&spec, results, &monte_carlo.curves);
    println!(
        "cooploc experiment: scenario {} ({}), {} runs, seed {}, {} threads, {:.1} s",
        scenario.name,
        crate::args::scenario_source(args.scenario.as_deref()),
        spec.runs,
        spec.seed,
        rayon::current_num_threads(),
        elapsed.as_secs_f64()
    );
    println!("position error = horizontal distance to truth at the end of the run; heading error = yaw error\n");
    for s in &summaries {
        println!("{}", report::table(s));
    }

    let mut tracks = Tracks::default();
    for id in world.platform_ids() {
        let truth = world.truth_samples(id)?;
        tracks.truth.push((id, truth.iter().map(|s| [s.pos_ned_m[0], s.pos_ned_m[1]]).collect()));
    }
    if let Some((_, runs)) = results[0].schedules.first() {
        for fr in runs.iter().filter(|r| matches!(r.method, Method::DeadReckoning | Method::Decentralized)) {
            for p in &fr.platforms {
                tracks.estimated.push((fr.method, p.id, p.track_ne_m.clone()));
            }
        }
    }
    let written = if args.no_plots {
        report::write_all(&args.out, &spec, &scenario.name, results, &summaries, &Tracks::default(), false)?
    } else {
        report::write_all(&args.out, &spec, &scenario.name, results, &summaries, &tracks, true)?
    };
    println!("wrote:");
    for p in written {
        println!("  {}", p.display());
    }
    Ok(())
}
