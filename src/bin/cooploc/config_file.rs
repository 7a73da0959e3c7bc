//! `cooploc node --config node.toml`: every node option in one TOML file, so that a vehicle
//! computer's service unit is one line. Each key is an option's long name (`vehicle_config` or
//! `vehicle-config`), each value what the option takes: a string or a number, `true` for a
//! flag, an array for a list (`team = [1, 2, 3]`, `peer = ["10.0.0.2:14600"]`). The file's
//! options go before the command line's, and an option given on the command line replaces the
//! file's (lists too). Relative paths in the file are relative to the file's folder. An
//! unknown key, a value of the wrong kind or a `config` key in the file is an error naming it.

use std::ffi::OsString;
use std::path::{Path, PathBuf};

use anyhow::{Context, bail};

/// Options whose values are paths (resolved against the config file's folder).
const PATH_KEYS: [&str; 7] = ["vehicle-config", "team-key", "vehicle-key", "signing-state", "state-file", "scenario", "log"];

/// `argv` with `--config FILE` (or `--config=FILE`) of subcommand `sub` replaced by the file's
/// options; other command lines come back unchanged.
pub fn expand(argv: Vec<OsString>, sub: &str, command: &clap::Command) -> anyhow::Result<Vec<OsString>> {
    if argv.get(1).is_none_or(|a| a != sub) {
        return Ok(argv);
    }
    let mut path: Option<(usize, usize, PathBuf)> = None;
    for (i, a) in argv.iter().enumerate().skip(2) {
        let Some(s) = a.to_str() else { continue };
        if s == "--" {
            break;
        }
        let found = if s == "--config" {
            let v = argv.get(i + 1).with_context(|| "--config: expected a FILE")?;
            Some((i, 2, PathBuf::from(v)))
        } else {
            s.strip_prefix("--config=").map(|v| (i, 1, PathBuf::from(v)))
        };
        if let Some(f) = found {
            if path.is_some() {
                bail!("--config: given twice");
            }
            path = Some(f);
        }
    }
    let Some((at, len, path)) = path else { return Ok(argv) };
    let text = std::fs::read_to_string(&path).with_context(|| format!("--config {}: cannot read it", path.display()))?;
    let given: Vec<String> = argv
        .iter()
        .filter_map(|a| a.to_str()?.strip_prefix("--").map(|s| s.split('=').next().unwrap_or(s).to_string()))
        .collect();
    let sub_command = command.find_subcommand(sub).with_context(|| format!("no subcommand {sub}"))?;
    let base = path.parent().map(Path::to_path_buf).unwrap_or_default();
    let from_file = file_args(&text, sub_command, &given, &base).with_context(|| format!("--config {}", path.display()))?;
    let mut out: Vec<OsString> = argv[..at].to_vec();
    out.extend(from_file.into_iter().map(OsString::from));
    out.extend(argv[at + len..].iter().cloned());
    Ok(out)
}

/// The options a config file's text stands for (keys given on the command line left out).
fn file_args(text: &str, command: &clap::Command, given: &[String], base: &Path) -> anyhow::Result<Vec<String>> {
    let table: toml::Table = toml::from_str(text).context("not valid TOML")?;
    let mut out = Vec::new();
    for (key, value) in &table {
        let flag = key.replace('_', "-");
        if flag == "config" {
            bail!("key `{key}`: a config file cannot name another one");
        }
        let Some(arg) = command.get_arguments().find(|a| a.get_long() == Some(flag.as_str())) else {
            let mut known: Vec<&str> = command.get_arguments().filter_map(|a| a.get_long()).filter(|l| *l != "config").collect();
            known.sort_unstable();
            bail!("unknown key `{key}` (the keys are the node's options: {})", known.join(", "));
        };
        if given.contains(&flag) {
            continue; // the command line's value replaces the file's
        }
        let takes_value = arg.get_action().takes_values();
        let scalar = |v: &toml::Value| -> anyhow::Result<String> {
            let text = match v {
                toml::Value::String(s) => s.clone(),
                toml::Value::Integer(i) => i.to_string(),
                toml::Value::Float(f) => f.to_string(),
                other => bail!("key `{key}`: expected a string or a number, got {}", other.type_str()),
            };
            Ok(if PATH_KEYS.contains(&flag.as_str()) { base.join(text).display().to_string() } else { text })
        };
        match value {
            toml::Value::Boolean(b) if !takes_value => {
                if *b {
                    out.push(format!("--{flag}"));
                }
            }
            toml::Value::Boolean(_) => bail!("key `{key}`: expected a value, not true or false"),
            _ if !takes_value => bail!("key `{key}`: a flag: true or false"),
            toml::Value::Array(items) => {
                let items: Vec<String> = items.iter().map(scalar).collect::<anyhow::Result<_>>()?;
                match arg.get_value_delimiter() {
                    Some(d) => out.push(format!("--{flag}={}", items.join(&d.to_string()))),
                    None => out.extend(items.iter().map(|v| format!("--{flag}={v}"))),
                }
            }
            toml::Value::Table(_) => bail!("key `{key}`: expected a value, not a table"),
            v => out.push(format!("--{flag}={}", scalar(v)?)),
        }
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[derive(clap::Parser)]
    struct Cli {
        #[command(subcommand)]
        sub: Sub,
    }
    #[derive(clap::Subcommand)]
    enum Sub {
        Node {
            #[arg(long)]
            id: u16,
            #[arg(long)]
            vehicle_config: Option<PathBuf>,
            #[arg(long, value_delimiter = ',')]
            team: Vec<u16>,
            #[arg(long = "peer")]
            peers: Vec<String>,
            #[arg(long)]
            no_range_echo: bool,
            #[arg(long)]
            config: Option<PathBuf>,
        },
    }

    fn run(text: &str, cli: &[&str]) -> anyhow::Result<Vec<String>> {
        use clap::CommandFactory;
        let dir = std::env::temp_dir().join(format!("cooploc-config-{}-{}", std::process::id(), text.len()));
        std::fs::create_dir_all(&dir).unwrap();
        let file = dir.join("node.toml");
        std::fs::write(&file, text).unwrap();
        let mut argv: Vec<OsString> =
            ["cooploc", "node", "--config", file.to_str().unwrap()].iter().map(OsString::from).collect();
        argv.extend(cli.iter().map(OsString::from));
        let out = expand(argv, "node", &Cli::command());
        let _ = std::fs::remove_dir_all(&dir);
        out.map(|v| v.into_iter().map(|s| s.into_string().unwrap()).collect())
    }

    #[test]
    fn a_file_stands_for_the_options_and_the_command_line_wins() {
        let got = run("id = 3\nteam = [1, 2, 3]\npeer = [\"a:1\", \"b:2\"]\nno_range_echo = true\n", &["--team", "1,3"]).unwrap();
        assert_eq!(&got[..2], ["cooploc", "node"]);
        assert!(got.contains(&"--id=3".to_string()));
        assert!(got.contains(&"--peer=a:1".to_string()) && got.contains(&"--peer=b:2".to_string()));
        assert!(got.contains(&"--no-range-echo".to_string()));
        // the command line's --team replaces the file's
        assert!(!got.iter().any(|a| a == "--team=1,2,3"));
        assert_eq!(&got[got.len() - 2..], ["--team", "1,3"]);
        use clap::Parser;
        let Sub::Node { id, team, peers, no_range_echo, .. } = Cli::try_parse_from(&got).unwrap().sub;
        assert_eq!((id, team, peers.len(), no_range_echo), (3, vec![1, 3], 2, true));
    }

    #[test]
    fn relative_paths_are_the_files_and_bad_keys_are_named() {
        let got = run("id = 1\nvehicle_config = \"rover.toml\"\n", &[]).unwrap();
        let vc = got.iter().find(|a| a.starts_with("--vehicle-config=")).unwrap();
        assert!(vc.ends_with("/rover.toml") && vc.contains("cooploc-config-"), "{vc}");
        let e = format!("{:#}", run("id = 1\nspeed = 3\n", &[]).unwrap_err());
        assert!(e.contains("unknown key `speed`") && e.contains("vehicle-config"), "{e}");
        let e = format!("{:#}", run("id = \"x\"\nno_range_echo = 1\n", &[]).unwrap_err());
        assert!(e.contains("`no_range_echo`: a flag"), "{e}");
        let e = format!("{:#}", run("config = \"x.toml\"\n", &[]).unwrap_err());
        assert!(e.contains("cannot name another"), "{e}");
        let e = format!("{:#}", run("id = [\n", &[]).unwrap_err());
        assert!(e.contains("not valid TOML"), "{e}");
        let e = format!("{:#}", run("[inputs]\nid = 1\n", &[]).unwrap_err());
        assert!(e.contains("unknown key `inputs`"), "{e}");
    }

    /// The example shipped for vehicle computers stands for options the node takes.
    #[test]
    fn the_shipped_example_is_a_valid_node_command() {
        use clap::CommandFactory;
        let example = concat!(env!("CARGO_MANIFEST_DIR"), "/docs/vehicle-computer/node.toml");
        let argv: Vec<OsString> = ["cooploc", "node", "--config", example].iter().map(OsString::from).collect();
        let command = crate::Cli::command();
        let expanded = expand(argv, "node", &command).unwrap();
        let m = command.try_get_matches_from(&expanded).unwrap_or_else(|e| panic!("{e}: {expanded:?}"));
        let (_, node) = m.subcommand().unwrap();
        assert_eq!(node.get_one::<u16>("id"), Some(&1));
        assert!(node.get_one::<PathBuf>("vehicle_config").unwrap().ends_with("docs/vehicle-computer/rover.toml"));
    }
}
