//! `cooploc budget`: the cooperative network's bytes per second for a team, and the highest
//! epoch rate each kind of link carries (see [`cooploc::protocol::budget`]).

use anyhow::bail;
use cooploc::protocol::budget::{self, LinkKind, Medium, TeamShape};
use cooploc::protocol::record::Encoding;

#[derive(clap::Args)]
#[command(after_help = "Sizes are measured from the nodes' own encoders (a record of the given size, its \
fragments, the epoch report, the estimate, the range echoes, the heartbeat), not modelled. \
Resends after losses come on top.")]
pub struct Args {
    /// Team size.
    #[arg(long, default_value_t = 3)]
    team: usize,
    /// Error-state dimension of each member (16: the INS; 3: a planar robot).
    #[arg(long, default_value_t = 16)]
    state_dim: usize,
    /// Ranges each node measures per epoch (default: every teammate, at most 6).
    #[arg(long)]
    ranges: Option<usize>,
    /// Epochs per second.
    #[arg(long, default_value_t = 1.0)]
    epoch_hz: f64,
    /// Record encoding, or all of them.
    #[arg(long, value_enum, default_value = "all")]
    encoding: crate::args::EncodingsArg,
    /// The nodes run with --no-range-echo (ranges only inside the records).
    #[arg(long)]
    no_range_echo: bool,
    /// Also print the table of the highest epoch rate per link for 3, 8, 16 and 32 vehicles.
    #[arg(long)]
    table: bool,
}

fn shape(args: &Args, team: usize, encoding: Encoding, signed: bool) -> TeamShape {
    let ranges = args.ranges.unwrap_or((team - 1).min(6)).min(team - 1);
    TeamShape {
        team,
        state_dim: args.state_dim,
        ranges_per_node: ranges,
        epoch_hz: args.epoch_hz,
        encoding,
        signed,
        echo_ranges: !args.no_range_echo,
    }
}

fn medium_name(m: Medium) -> &'static str {
    match m {
        Medium::Radio => "radio, one copy",
        Medium::IpBroadcast { .. } => "IP multicast, packed",
        Medium::IpUnicast { .. } => "IP unicast to each peer, packed",
    }
}

fn hz(shape: &TeamShape, frames: &budget::EpochFrames, link: &LinkKind) -> String {
    match budget::max_epoch_hz(shape, frames, link) {
        Some(h) if h >= 100.0 => format!("{h:.0}"),
        Some(h) => format!("{h:.2}"),
        None => "0".into(),
    }
}

pub fn run(args: Args) -> anyhow::Result<()> {
    if !(1..=64).contains(&args.team) {
        bail!("--team {}: 1..=64 members", args.team);
    }
    if !(1..=cooploc::protocol::record::MAX_DIM).contains(&args.state_dim) {
        bail!("--state-dim {}: 1..={}", args.state_dim, cooploc::protocol::record::MAX_DIM);
    }
    if !(args.epoch_hz.is_finite() && args.epoch_hz > 0.0 && args.epoch_hz <= 100.0) {
        bail!("--epoch-hz {}: more than 0, at most 100", args.epoch_hz);
    }
    let encodings: Vec<Encoding> = args.encoding.encodings();
    let links = budget::standard_links();
    let team = args.team;
    let s0 = shape(&args, team, Encoding::F64, false);
    println!(
        "cooploc budget: {} vehicles, {} states, {} ranges each per epoch{}, {} epochs/s",
        team,
        args.state_dim,
        s0.ranges_per_node,
        if args.no_range_echo { " (not echoed)" } else { " (echoed as COOPLOC_RANGE)" },
        args.epoch_hz
    );
    println!();
    println!(
        "| encoding | signed | record B | frames/epoch | B/epoch/node | node B/s (radio) | team B/s (radio) | team B/s (IP multicast) | {} |",
        links.iter().map(|l| format!("max Hz {}", l.name)).collect::<Vec<_>>().join(" | ")
    );
    println!("|---|---|---|---|---|---|---|---|{}", "---|".repeat(links.len()));
    for &encoding in &encodings {
        for signed in [false, true] {
            let s = shape(&args, team, encoding, signed);
            let f = budget::epoch_frames(&s).map_err(anyhow::Error::msg)?;
            let radio = budget::rates(&s, &f, Medium::Radio);
            let multicast = budget::rates(&s, &f, Medium::IpBroadcast { packed: true });
            println!(
                "| {} | {} | {} | {} | {} | {:.0} | {:.0} | {:.0} | {} |",
                encoding.name(),
                if signed { "yes" } else { "no" },
                f.record_bytes,
                f.frames(),
                f.bytes(),
                radio.node_bytes_per_s,
                radio.team_bytes_per_s,
                multicast.team_bytes_per_s,
                links.iter().map(|l| hz(&s, &f, l)).collect::<Vec<_>>().join(" | ")
            );
        }
    }
    let s = shape(&args, team, *encodings.last().expect("one encoding"), true);
    let f = budget::epoch_frames(&s).map_err(anyhow::Error::msg)?;
    println!();
    println!("Per epoch and node ({}, signed):", s.encoding.name());
    for (kind, frames, bytes) in &f.kinds {
        println!("  {kind:<24} {frames:>3} frames {bytes:>6} B");
    }
    println!("  {:<24} {:>3} frame  {:>6} B a second", "HEARTBEAT", 1, f.heartbeat_bytes);
    println!();
    println!("Links (capacity of the shared channel, all nodes together):");
    for l in &links {
        println!("  {:<16} {:>8.0} B/s  {}: {}", l.name, l.capacity_bytes_per_s, medium_name(l.medium), l.source);
    }
    if args.table {
        println!();
        println!(
            "Highest epoch rate, Hz ({} states, ranges to every teammate up to 6, compact signed{}; f64 unsigned with echoes in brackets):",
            args.state_dim,
            if args.no_range_echo { " without echoes" } else { "" }
        );
        println!();
        println!("| vehicles | {} |", links.iter().map(|l| l.name).collect::<Vec<_>>().join(" | "));
        println!("|---|{}", "---|".repeat(links.len()));
        for n in [3usize, 8, 16, 32] {
            let after = shape(&args, n, Encoding::Compact, true);
            let before = TeamShape { echo_ranges: true, ..shape(&args, n, Encoding::F64, false) };
            let (fa, fb) = (
                budget::epoch_frames(&after).map_err(anyhow::Error::msg)?,
                budget::epoch_frames(&before).map_err(anyhow::Error::msg)?,
            );
            println!(
                "| {n} | {} |",
                links.iter().map(|l| format!("{} ({})", hz(&after, &fa, l), hz(&before, &fb, l))).collect::<Vec<_>>().join(" | ")
            );
        }
    }
    Ok(())
}
