//! The `cooploc` command line. Thin: parses and validates arguments into the library's config
//! types, calls the library, prints, and maps errors to an exit code.

mod experiment_cmd;
mod sitl_cmd;

use std::process::ExitCode;

use clap::{Parser, Subcommand};

#[derive(Parser)]
#[command(name = "cooploc", version, about = "Decentralized cooperative localization of vehicle teams over MAVLink")]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand)]
enum Command {
    /// Monte Carlo reproduction of the paper's experiment: every method on the same simulated inputs.
    Experiment(experiment_cmd::Args),
    /// Runs a scenario's vehicles as MAVLink systems (one UDP or serial link each), in simulated time.
    Sitl(sitl_cmd::Args),
}

fn main() -> ExitCode {
    let cli = Cli::parse();
    let result = match cli.command {
        Command::Experiment(args) => experiment_cmd::run(args),
        Command::Sitl(args) => sitl_cmd::run(args),
    };
    match result {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("error: {e:#}");
            ExitCode::FAILURE
        }
    }
}
