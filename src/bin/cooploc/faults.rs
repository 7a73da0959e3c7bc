//! `cooploc faults`: the fault-injection table (see [`cooploc::experiment::faults`]).

use std::path::PathBuf;
use std::time::Instant;

use anyhow::{Context, bail};
use cooploc::experiment::faults::{CaseSummary, clock_offset_cases, large_team_cases, run_case, standard_cases, summarize};
use cooploc::sitl::world::World;
use rayon::prelude::*;

#[derive(clap::Args)]
pub struct Args {
    /// Scenario file (default: the paper's scenario, built in: sitl/scenarios/paper.toml).
    scenario: Option<PathBuf>,
    /// Seeded runs per case.
    #[arg(long, default_value_t = 20)]
    runs: u32,
    /// Seed (run k uses seed and k).
    #[arg(long, default_value_t = 1)]
    seed: u64,
    /// The nodes' method.
    #[arg(long, value_enum, default_value = "dcl")]
    method: crate::args::NodeMethodArg,
    /// Ranging schedule of the scenario.
    #[arg(long, default_value = "1hz")]
    schedule: String,
    /// Number format of the nodes' records.
    #[arg(long, value_enum, default_value = "f64")]
    encoding: crate::args::EncodingArg,
    /// Only the cases whose name contains this text.
    #[arg(long)]
    only: Option<String>,
    /// Every case with the nodes' messages packed into datagrams as the runner sends them on
    /// UDP, loss and delay striking whole datagrams (`Faults::packed`), as on real sockets.
    #[arg(long)]
    packed: bool,
    /// Run every case as `cooploc sitl --speed SPEED` runs the vehicles: the nodes' wall-clock
    /// timers (retries, epoch timeouts) and network delays last SPEED times longer in vehicle
    /// time (`Faults::speed`). 1: real time. Without it, each case's own (real time but for the
    /// cases named "5x real time").
    #[arg(long)]
    speed: Option<f64>,
    /// Every case with cooperative datagrams delayed uniformly in LO-HI ms (reordered), until the
    /// case's end of link faults (340 s of the paper scenario; a case without link faults gets
    /// them until then too). Without it, each case's own delays.
    #[arg(long, value_name = "LO-HI")]
    delay_ms: Option<String>,
    /// Run the nodes as an unsigned team (`cooploc node --insecure`): they believe nothing a
    /// record says of its sender, so they wait an epoch timeout for a restarted teammate's record
    /// that will never come (`Faults::unsigned`). Without it, as the signed default.
    #[arg(long)]
    unsigned: bool,
    /// Also write every case's summary as JSON here.
    #[arg(long)]
    json: Option<PathBuf>,
    /// A large team instead of the scenario's: N of its vehicles side by side (`--spacing-m`
    /// apart, radios reaching `--reach-m`, 1 Hz ranging, the scenario's duration or
    /// `--duration-s`), run through the large-team cases (loss-free; 10% loss; four members
    /// leaving and coming back; both) instead of the standard ones.
    #[arg(long, value_name = "N", value_parser = clap::value_parser!(u16).range(2..=64))]
    side_by_side: Option<u16>,
    /// With --side-by-side: the distance between neighbours, m.
    #[arg(long, default_value_t = 100.0, requires = "side_by_side")]
    spacing_m: f64,
    /// The radios' reach, m: two vehicles range only while at most this far apart (default:
    /// the scenario's; with --side-by-side, 310: three neighbours on each side).
    #[arg(long)]
    reach_m: Option<f64>,
    /// With --side-by-side: the run's length, s.
    #[arg(long, requires = "side_by_side")]
    duration_s: Option<f64>,
    /// The clock sweep instead of the standard cases: one node's team clock ahead of its
    /// teammates' by 1 to 100 ms (a TIMESYNC mapping or an NTP clock that is off), node 1's (which
    /// ranges) and then node 3's (which does not), its ranges on the profiles' 100 ms epoch grid;
    /// what each offset costs the team.
    #[arg(long, conflicts_with = "side_by_side")]
    clock_sweep: bool,
    /// Store bytes per second each answerer sends a left-out member (`cooploc node
    /// --store-bps`): a store larger than that in an epoch comes over several epochs. Default:
    /// the whole store at each answer.
    #[arg(long)]
    store_bps: Option<u64>,
}

pub fn run(args: Args) -> anyhow::Result<()> {
    let (method, encoding) = (args.method.0, args.encoding.0);
    if args.runs == 0 {
        bail!("--runs must be at least 1");
    }
    if let Some(speed) = args.speed.filter(|s| !(s.is_finite() && *s > 0.0)) {
        bail!("--speed {speed}: must be a positive number (1 is real time)");
    }
    let delay_ms = match &args.delay_ms {
        Some(text) => Some(
            text.split_once('-')
                .and_then(|(lo, hi)| Some((lo.trim().parse::<u64>().ok()?, hi.trim().parse::<u64>().ok()?)))
                .filter(|(lo, hi)| lo <= hi && *hi <= 60_000)
                .with_context(|| format!("--delay-ms {text:?}: expected LO-HI in ms, LO <= HI <= 60000, e.g. 0-1500"))?,
        ),
        None => None,
    };
    let mut scenario = crate::args::scenario_or_paper(args.scenario.as_deref())?;
    crate::args::limit_reach(&mut scenario, args.reach_m)?;
    if let Some(n) = args.side_by_side {
        let duration_s = args.duration_s.unwrap_or(scenario.duration_s);
        let reach_m = args.reach_m.unwrap_or(310.0);
        if !(args.spacing_m > 0.0 && duration_s > 0.0) {
            bail!("--spacing-m and --duration-s must be positive");
        }
        scenario = scenario.side_by_side(usize::from(n), args.spacing_m, reach_m, duration_s);
    }
    let world = World::new(&scenario)?;
    let duration_s = world.scenario().duration_s;
    let all_cases = match args.side_by_side {
        Some(n) => large_team_cases(usize::from(n), duration_s),
        None if args.clock_sweep => clock_offset_cases(),
        None => standard_cases(),
    };
    let (cases, too_long): (Vec<_>, Vec<_>) = all_cases
        .into_iter()
        .filter(|c| args.only.as_ref().is_none_or(|o| c.name.contains(o.as_str())))
        .partition(|c| c.faults.fits(duration_s));
    for c in &too_long {
        eprintln!("skipped {:?}: its outage ends after the scenario's {duration_s} s", c.name);
    }
    if cases.is_empty() {
        bail!("no case matches --only and fits the scenario's {duration_s} s");
    }
    let started = Instant::now();
    let mut summaries: Vec<CaseSummary> = Vec::new();
    for case in &cases {
        let runs: Vec<_> = (0..args.runs)
            .into_par_iter()
            .map(|run| {
                let faults = cooploc::experiment::faults::Faults {
                    packed: args.packed || case.faults.packed,
                    unsigned: args.unsigned || case.faults.unsigned,
                    speed: args.speed.unwrap_or(case.faults.speed),
                    delay_ms: delay_ms.unwrap_or(case.faults.delay_ms),
                    links_until_s: if delay_ms.is_some() && case.faults.links_until_s == 0.0 {
                        cooploc::experiment::faults::LINK_FAULTS_UNTIL_S
                    } else {
                        case.faults.links_until_s
                    },
                    store_bps: args.store_bps.unwrap_or(case.faults.store_bps),
                    ..case.faults.clone()
                };
                run_case(&world, &faults, method, &args.schedule, args.seed, run, encoding)
            })
            .collect::<Result<_, _>>()
            .with_context(|| format!("case {:?}", case.name))?;
        summaries.push(summarize(case.name, &runs));
    }
    println!(
        "cooploc faults: {} cases x {} runs, method {}, encoding {}, schedule {}, seed {}{}{}{}{}{} ({:.1} s)",
        cases.len(),
        args.runs,
        method.short_name(),
        encoding.name(),
        args.schedule,
        args.seed,
        if args.packed { ", packed datagrams" } else { "" },
        args.speed.map(|s| format!(", every case at {s}x real time")).unwrap_or_default(),
        delay_ms.map(|(lo, hi)| format!(", every case with delays of {lo}-{hi} ms")).unwrap_or_default(),
        args.side_by_side
            .map(|n| format!(", {n} vehicles side by side {} m apart, {duration_s} s", args.spacing_m))
            .unwrap_or_default(),
        world.scenario().ranging.max_range_m.map(|r| format!(", radios reaching {r} m")).unwrap_or_default(),
        started.elapsed().as_secs_f64()
    );
    if args.clock_sweep {
        print_clock_sweep(&summaries);
    } else {
        print_table(&summaries);
    }
    if let Some(path) = &args.json {
        std::fs::write(path, serde_json::to_string_pretty(&summaries)?).with_context(|| format!("writing {}", path.display()))?;
    }
    Ok(())
}

/// The clock sweep's table: what each offset costs, over the whole run and at its end.
fn print_clock_sweep(summaries: &[CaseSummary]) {
    let base = summaries.iter().find(|s| s.name == "fault-free").map(|s| (s.run_rms_m, s.final_rms_m));
    let rel = |v: f64, b: f64| format!("{:+.1}%", 100.0 * (v / b - 1.0));
    println!(
        "| case | whole-run RMS m | vs fault-free | final RMS m | vs fault-free | team NEES (95% band) | applied | partial | implausible | gated |"
    );
    println!("|---|---|---|---|---|---|---|---|---|---|");
    for s in summaries {
        let (run_rel, final_rel) =
            base.map_or((String::new(), String::new()), |(r, f)| (rel(s.run_rms_m, r), rel(s.final_rms_m, f)));
        println!(
            "| {} | {:.3} | {} | {:.3} | {} | {:.2} ({:.2}-{:.2}) | {} | {} | {} | {} |",
            s.name,
            s.run_rms_m,
            run_rel,
            s.final_rms_m,
            final_rel,
            s.team_nees,
            s.team_nees_band.0,
            s.team_nees_band.1,
            s.applied,
            s.partial,
            s.implausible,
            s.gated
        );
    }
}

/// The standard table (docs/robustness.md).
fn print_table(summaries: &[CaseSummary]) {
    let base = summaries.iter().find(|s| s.name == "fault-free").map(|s| s.final_rms_m);
    println!(
        "| case | final RMS m | vs fault-free | at fault end m | dead reckoning m | NEES per node | team NEES (95% band) | worse than DR | diverged / detected / not recovered | left out / stores adopted / bystood | heals | partial | failed | gated |"
    );
    println!("|---|---|---|---|---|---|---|---|---|---|---|---|---|---|");
    for s in summaries {
        let rel = base.map_or("".into(), |b| format!("{:+.0}%", 100.0 * (s.final_rms_m / b - 1.0)));
        println!(
            "| {} | {:.2} | {} | {:.2} | {:.2} | {:.2} | {:.2} ({:.2}-{:.2}) | {} | {} / {} / {} | {} / {} / {} | {} | {} | {} | {} |",
            s.name,
            s.final_rms_m,
            rel,
            s.fault_end_rms_m,
            s.dr_rms_m,
            s.avg_nees,
            s.team_nees,
            s.team_nees_band.0,
            s.team_nees_band.1,
            s.worse_than_dr,
            s.runs_diverged,
            s.runs_detected,
            s.runs_not_recovered,
            s.excluded,
            s.stores_adopted,
            s.bystood,
            s.heals,
            s.partial,
            s.failed,
            s.gated
        );
    }
}
