//! `cooploc keygen FILE`: a new team key file (a 240-bit passphrase from the operating system's
//! random source; the key is its SHA-256, as MAVProxy's `signing setup` makes it), only its
//! owner can read. The same file goes to every node of the team (`--team-key`) and to the
//! ground station.

use std::io::Write;
use std::path::PathBuf;

use anyhow::Context;

#[derive(clap::Args)]
pub struct Args {
    /// Where to write the key (refused if it exists: a team's key is not overwritten by mistake).
    file: PathBuf,
}

pub fn run(args: Args) -> anyhow::Result<()> {
    let passphrase = cooploc::protocol::signing::TeamKey::new_passphrase()?;
    let mut options = std::fs::OpenOptions::new();
    options.write(true).create_new(true);
    #[cfg(unix)]
    std::os::unix::fs::OpenOptionsExt::mode(&mut options, 0o600);
    let mut file = options.open(&args.file).with_context(|| format!("cannot create {}", args.file.display()))?;
    writeln!(file, "{passphrase}")
        .and_then(|()| file.sync_all())
        .with_context(|| format!("cannot write {}", args.file.display()))?;
    println!(
        "team key written to {} (a passphrase, readable by its owner only): give every node of the team the same file \
         (--team-key) and the ground station (cooploc gcs --team-key; in MAVProxy, `signing setup` followed by the file's line)",
        args.file.display()
    );
    Ok(())
}
