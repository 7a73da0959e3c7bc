//! `cooploc demo`: arguments and printing around [`cooploc::demo`].

use std::net::SocketAddr;
use std::path::PathBuf;

use anyhow::{Context, bail};
use cooploc::demo::{DemoConfig, run_demo};

#[derive(clap::Args)]
pub struct Args {
    #[command(flatten)]
    sim: crate::args::SimRun,
    /// Times real time.
    #[arg(long, default_value_t = 20.0)]
    speed: f64,
    /// The nodes' method.
    #[arg(long, value_enum, default_value = "dcl")]
    method: crate::args::NodeMethodArg,
    /// The log (default: logs/demo-<seed>-<run>.mcap).
    #[arg(long)]
    log: Option<PathBuf>,
    /// The ground station's web page.
    #[arg(long, default_value = "127.0.0.1:8080")]
    http: SocketAddr,
    /// The ground station's Foxglove WebSocket server.
    #[arg(long, default_value = "127.0.0.1:8765")]
    foxglove: SocketAddr,
    /// Simulate only this many seconds (small logs).
    #[arg(long)]
    duration_s: Option<f64>,
}

pub fn run(args: Args) -> anyhow::Result<()> {
    let method = args.method.0;
    if !(args.speed.is_finite() && args.speed > 0.0) {
        bail!("--speed must be a positive number, got {}", args.speed);
    }
    if let Some(d) = args.duration_s
        && !(d.is_finite() && d > 0.0)
    {
        bail!("--duration-s must be a positive number of seconds, got {d}");
    }
    let log = args.log.clone().unwrap_or_else(|| PathBuf::from(format!("logs/demo-{}-{}.mcap", args.sim.seed, args.sim.run)));
    let cfg = DemoConfig {
        scenario: args.sim.scenario.clone(),
        seed: args.sim.seed,
        run: args.sim.run,
        schedule: args.sim.schedule.clone(),
        speed: args.speed,
        method,
        log,
        http: args.http,
        foxglove: Some(args.foxglove),
        duration_s: args.duration_s,
    };
    let rt = tokio::runtime::Builder::new_multi_thread().enable_all().build().context("starting the tokio runtime")?;
    let start = std::time::Instant::now();
    let report = rt.block_on(run_demo(cfg, |a| {
        println!(
            "cooploc demo: scenario {}, seed {}, run {}, {}x real time",
            crate::args::scenario_source(args.sim.scenario.as_deref()),
            args.sim.seed,
            args.sim.run,
            args.speed
        );
        println!("dashboard: http://{}/", a.http);
        if let Some(f) = a.foxglove {
            println!("foxglove:  ws://{f}");
        }
        for (id, v) in &a.vehicles {
            let node = a.nodes.iter().find(|(n, _)| n == id).map(|(_, n)| n.to_string()).unwrap_or_default();
            println!("vehicle {id}: udp {v}, node coop udp {node}");
        }
        println!("cooperative network signed with a key made for this run (the nodes and the ground station hold it)");
    }))?;
    println!(
        "finished in {:.1} s; log {} ({} messages)",
        start.elapsed().as_secs_f64(),
        report.log.display(),
        report.log_messages
    );
    for n in &report.nodes {
        let st = &n.stats;
        println!(
            "node {}: {} epochs applied, {} partial, {} dropped inputs, {} vehicle frames lost",
            n.estimate.as_ref().map_or(0, |e| e.platform),
            st.epochs_applied,
            st.epochs_partial,
            st.dropped_inputs(),
            n.vehicle_lost
        );
    }
    for r in &report.replays {
        println!(
            "replay of node {}: {} estimates, {}",
            r.id,
            r.recorded.len(),
            if r.matches() { "identical bit for bit" } else { "DIFFERENT" }
        );
    }
    println!("final errors per method (offline on the inputs the vehicles sent; the nodes ran {}):", method);
    crate::table::print_methods(&report.methods);
    Ok(())
}
