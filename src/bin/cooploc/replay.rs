//! `cooploc replay LOG [--method M]`: see [`cooploc::replay`].

use std::path::PathBuf;

use anyhow::{Context, bail};
use cooploc::estimation::Method;
use cooploc::recording::{LogEnd, read_log};
use cooploc::replay::{compare_methods, replay_nodes};

#[derive(clap::Args)]
pub struct Args {
    /// The MCAP log (from `cooploc demo` or `cooploc node --log`).
    log: PathBuf,
    /// Run this method offline on the logged inputs besides replaying the recorded nodes; `all`
    /// runs every method. A data set's log (from `cooploc dataset`) has no nodes: every method
    /// (or the one named) runs on it in every regime.
    #[arg(long, value_enum)]
    method: Option<crate::args::MethodsArg>,
}

pub fn run(args: Args) -> anyhow::Result<()> {
    let start = std::time::Instant::now();
    let log = read_log(&args.log).with_context(|| format!("reading {}", args.log.display()))?;
    match &log.end {
        LogEnd::Complete => {}
        other => println!("log {}: read up to the damage ({other:?}): {} messages", args.log.display(), log.messages.len()),
    }
    if cooploc::dataset::log::is_dataset_log(&log) {
        return replay_dataset(&log, args.method, start);
    }
    let replays = replay_nodes(&log)?;
    let mut exact = true;
    for r in &replays {
        let ok = r.matches();
        exact &= ok;
        let last =
            r.last.as_ref().map(|e| format!("[{:.4}, {:.4}]", e.position_ned_m[0], e.position_ned_m[1])).unwrap_or_default();
        println!(
            "node {} ({}): {} recorded estimates, {} replayed, {}; final N/E {last}",
            r.id,
            r.method.short_name(),
            r.recorded.len(),
            r.replayed.len(),
            if ok { "identical bit for bit" } else { "DIFFERENT" }
        );
    }
    let methods: Vec<Method> = args.method.map(crate::args::MethodsArg::methods).unwrap_or_default();
    if !methods.is_empty() {
        let runs = compare_methods(&log, &methods)?;
        println!("final errors, offline on the logged inputs:");
        crate::table::print_methods(&runs);
    }
    println!("replayed {} messages in {:.2} s", log.messages.len(), start.elapsed().as_secs_f64());
    if !exact {
        bail!("a replayed node differs from its recording");
    }
    Ok(())
}

/// A data set's log: the methods over its inputs in every regime, scored against its truth.
fn replay_dataset(
    log: &cooploc::recording::Log,
    method: Option<crate::args::MethodsArg>,
    start: std::time::Instant,
) -> anyhow::Result<()> {
    use cooploc::dataset::run::{Regime, Settings};
    let logged = cooploc::dataset::log::read(log)?;
    let ds = &logged.dataset;
    println!(
        "data set log {}: {} robots, {} landmarks, {:.1} s ({} frames rejected)",
        ds.name,
        ds.robots.len(),
        ds.landmarks.len(),
        ds.t_end.secs_since(ds.t0),
        logged.rejected_frames
    );
    let methods = method.unwrap_or(crate::args::MethodsArg::All).methods();
    crate::dataset::evaluate(ds, &Settings::new(logged.noise), &Regime::ALL, &methods)?;
    println!("replayed {} messages in {:.2} s", log.messages.len(), start.elapsed().as_secs_f64());
    Ok(())
}
