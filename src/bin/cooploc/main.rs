//! The `cooploc` command line. Thin: parses and validates arguments into the library's config
//! types, calls the library, prints, and maps errors to an exit code.

mod args;
mod budget;
mod check;
mod config_file;
mod dataset;
mod demo;
mod experiment;
mod faults;
mod gcs;
mod keygen;
mod node;
mod replay;
mod signal;
mod sitl;
mod table;

use std::process::ExitCode;

/// mimalloc instead of the system allocator: the filters' small matrices (a measurement, a
/// snapshot, an update's diagnostics) are allocated and freed at every update, and glibc's
/// malloc and free were 5-6 % of the experiment and of replay. Numbers do not depend on it.
/// Built without its transparent huge pages (feature `no_thp`): with them, each time it gave
/// memory back and took it again the kernel zeroed 2 MiB pages, a second of system time in a
/// 50-run experiment where glibc's malloc took a quarter of that.
#[global_allocator]
static ALLOCATOR: mimalloc::MiMalloc = mimalloc::MiMalloc;

use clap::{CommandFactory, FromArgMatches, Subcommand};

#[derive(clap::Parser)]
#[command(name = "cooploc", version, about = "Decentralized cooperative localization of vehicle teams over MAVLink")]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand)]
enum Command {
    /// The cooperative network's byte budget: bytes per second per node and per team for a team
    /// size, state size, epoch rate, encoding and signing, and the highest epoch rate a SiK
    /// radio, Wi-Fi or an IP mesh carries.
    Budget(budget::Args),
    /// Connects to an autopilot as its companion would and says what arrives (messages, rates in
    /// the vehicle's time, components, clocks, signing) against what a vehicle profile needs,
    /// and the autopilot parameters to set.
    Check(check::Args),
    /// Real data sets: imports a UTIAS MRCLAM folder into a cooploc log, estimates its noise
    /// against the ground truth, and runs every method on it in three regimes.
    Dataset(dataset::Args),
    /// The paper scenario end to end on loopback: simulator, one node per vehicle, ground station
    /// (web page and Foxglove), one MCAP log under logs/, and the final error table per method.
    Demo(demo::Args),
    /// Monte Carlo reproduction of the paper's experiment: every method on the same simulated inputs.
    Experiment(experiment::Args),
    /// Fault injection on the node shells (deterministic, seeded): lost, delayed, reordered and damaged
    /// datagrams, lost vehicle frames, stalls, restarts, late joins and leaves; one table row per
    /// case (final error, NEES, disagreements detected and healed).
    Faults(faults::Args),
    /// The ground station: the team's estimates, 95% ellipses, truth and link health on a web
    /// page and on Foxglove's live WebSocket protocol.
    Gcs(gcs::Args),
    /// A new team key for signing the cooperative network, written to a file only its owner
    /// can read (every node refuses an unsigned network unless told --insecure).
    Keygen(keygen::Args),
    /// The per-vehicle companion: local filter on the vehicle's IMU and odometry, cooperative
    /// protocol with the other nodes, estimate back to the vehicle.
    Node(Box<node::Args>),
    /// Feeds a recorded log back through the filters: the recorded nodes bit for bit, or another
    /// method on the same inputs.
    Replay(replay::Args),
    /// Runs a scenario's vehicles as MAVLink systems (one UDP or serial link each), in simulated time.
    Sitl(sitl::Args),
}

fn main() -> ExitCode {
    // Output piped into a reader that stops early (`cooploc budget | head`) ends the process
    // quietly, as other Unix tools do, instead of a panic in println!.
    #[cfg(unix)]
    // SAFETY: restoring the default action of SIGPIPE before any thread starts.
    unsafe {
        libc::signal(libc::SIGPIPE, libc::SIG_DFL);
    }
    // Negative numbers are values wherever a number is taken (`--init-ned -150,20,0`,
    // `--origin-lon-deg -79.5`), in every subcommand.
    let command = Cli::command().allow_negative_numbers(true).mut_subcommands(|s| s.allow_negative_numbers(true));
    // `cooploc node --config FILE`: the file's options, then the command line's.
    let argv = match config_file::expand(std::env::args_os().collect(), "node", &command) {
        Ok(argv) => argv,
        Err(e) => {
            eprintln!("error: {e:#}");
            return ExitCode::FAILURE;
        }
    };
    let cli = match Cli::from_arg_matches(&command.get_matches_from(argv)) {
        Ok(cli) => cli,
        Err(e) => e.exit(),
    };
    tracing_subscriber::fmt()
        .with_writer(std::io::stderr)
        .with_env_filter(tracing_subscriber::EnvFilter::try_from_default_env().unwrap_or_else(|_| "warn".into()))
        .init();
    let result = match cli.command {
        Command::Budget(args) => budget::run(args),
        Command::Check(args) => check::run(args),
        Command::Dataset(args) => dataset::run_cmd(args),
        Command::Demo(args) => demo::run(args),
        Command::Keygen(args) => keygen::run(args),
        Command::Experiment(args) => experiment::run(args),
        Command::Faults(args) => faults::run(args),
        Command::Replay(args) => replay::run(args),
        Command::Gcs(args) => gcs::run_cmd(args),
        Command::Node(args) => node::run_cmd(*args),
        Command::Sitl(args) => sitl::run(args),
    };
    match result {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("error: {e:#}");
            ExitCode::FAILURE
        }
    }
}
