//! The command line itself: what clap accepts before any command runs.

use std::process::Command;

fn run(args: &[&str]) -> (Option<i32>, String) {
    let out = Command::new(env!("CARGO_BIN_EXE_cooploc")).args(args).output().unwrap();
    (out.status.code(), format!("{}{}", String::from_utf8_lossy(&out.stdout), String::from_utf8_lossy(&out.stderr)))
}

/// A negative number is a value, in a list (`--init-ned -150,20,0`) or alone, in every
/// subcommand: the error that follows is about what is really wrong.
#[test]
fn negative_numbers_are_values_everywhere() {
    let (code, out) = run(&["node", "--init-ned", "-150,20,0", "--init-vel-ned", "-1,0,0"]);
    assert_eq!(code, Some(2), "{out}");
    assert!(!out.contains("unexpected argument"), "{out}");
    assert!(out.contains("--id <ID>"), "the missing arguments are named: {out}");
    let (code, out) = run(&["budget", "--epoch-hz", "-1"]);
    assert_eq!(code, Some(1), "{out}");
    assert!(out.contains("--epoch-hz -1: more than 0"), "the command's own check refuses it: {out}");
    let (code, out) = run(&["gcs", "--origin-lon-deg", "-79.5", "--no-such-flag"]);
    assert_eq!(code, Some(2), "{out}");
    assert!(out.contains("'--no-such-flag'") && !out.contains("'-79.5'"), "{out}");
}

/// The one binary (a node on a vehicle computer too) links no system font library: the plots
/// draw with an embedded font (plotters' pure-Rust ab_glyph), not fontconfig and freetype.
#[test]
fn the_binary_needs_no_font_libraries() {
    let out = match Command::new("ldd").arg(env!("CARGO_BIN_EXE_cooploc")).output() {
        Ok(out) => out,
        Err(e) if std::env::var_os("CI").is_none() => {
            eprintln!("skipped: ldd not found ({e})");
            return;
        }
        Err(e) => panic!("ldd is needed under CI: {e}"),
    };
    let libs = String::from_utf8_lossy(&out.stdout);
    assert!(out.status.success(), "{libs}");
    for lib in ["fontconfig", "freetype", "libpng", "libexpat"] {
        assert!(!libs.contains(lib), "the binary links {lib}:\n{libs}");
    }
}

/// Secure by default: a node refuses an unsigned cooperative network unless told --insecure by
/// name, and says how to make a key; `cooploc keygen` makes one only its owner can read, never
/// over an existing file, and a node starts with it.
#[test]
fn a_node_needs_a_team_key_or_insecure_by_name_and_keygen_makes_one() {
    let profile = concat!(env!("CARGO_MANIFEST_DIR"), "/sitl/vehicles/ardupilot-rover.toml");
    let node = ["node", "--id", "1", "--team", "1", "--vehicle", "udpout:127.0.0.1:9", "--vehicle-config", profile];
    let node =
        [&node[..], &["--init-ned", "0,0,0", "--init-vel-ned", "0,0,0", "--init-rpy-deg", "0,0,0", "--idle-exit-s", "0.3"]]
            .concat();
    let (code, out) = run(&node);
    assert_eq!(code, Some(1), "{out}");
    assert!(out.contains("no --team-key") && out.contains("cooploc keygen") && out.contains("--insecure"), "{out}");
    let (code, out) = run(&[&node[..], &["--insecure", "--team-key", "x"]].concat());
    assert_eq!(code, Some(2), "--insecure and a key at once: {out}");

    let dir = std::env::temp_dir().join(format!("cooploc-keygen-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let key = dir.join("team.key");
    let _ = std::fs::remove_file(&key);
    let (code, out) = run(&["keygen", key.to_str().unwrap()]);
    assert_eq!(code, Some(0), "{out}");
    let text = std::fs::read_to_string(&key).unwrap();
    assert_eq!(text.trim_end().len(), 48, "{text:?}");
    #[cfg(unix)]
    {
        use std::os::unix::fs::PermissionsExt;
        assert_eq!(std::fs::metadata(&key).unwrap().permissions().mode() & 0o777, 0o600);
    }
    let (code, out) = run(&["keygen", key.to_str().unwrap()]);
    assert_eq!(code, Some(1), "an existing key is not overwritten: {out}");
    assert_eq!(std::fs::read_to_string(&key).unwrap(), text);
    // With the key the node starts (it waits for its vehicle, which never comes: stopped here).
    let mut child = Command::new(env!("CARGO_BIN_EXE_cooploc"))
        .args([&node[..], &["--team-key", key.to_str().unwrap()]].concat())
        .stdout(std::process::Stdio::piped())
        .spawn()
        .unwrap();
    let mut first = String::new();
    std::io::BufRead::read_line(&mut std::io::BufReader::new(child.stdout.take().unwrap()), &mut first).unwrap();
    let _ = child.kill();
    let _ = child.wait();
    assert!(first.starts_with("node 1 coop udp "), "the node started: {first:?}");
    let _ = std::fs::remove_dir_all(&dir);
}

/// The ground station, like a node, refuses an unauthenticated cooperative network unless told
/// --insecure by name, and says so when it is.
#[test]
fn a_ground_station_needs_a_team_key_or_insecure_by_name() {
    let (code, out) = run(&["gcs", "--coop", "127.0.0.1:0", "--http", "127.0.0.1:0", "--no-foxglove"]);
    assert_eq!(code, Some(1), "{out}");
    assert!(out.contains("no --team-key") && out.contains("--insecure"), "{out}");
    let (code, out) = run(&["gcs", "--team-key", "/nonexistent/team.key", "--insecure"]);
    assert_eq!(code, Some(2), "a key and --insecure conflict: {out}");
    use std::io::BufRead;
    let mut gcs = Command::new(env!("CARGO_BIN_EXE_cooploc"))
        .args(["gcs", "--coop", "127.0.0.1:0", "--http", "127.0.0.1:0", "--no-foxglove", "--insecure"])
        .stdout(std::process::Stdio::piped())
        .stderr(std::process::Stdio::null())
        .spawn()
        .unwrap();
    let lines: Vec<String> = std::io::BufReader::new(gcs.stdout.take().unwrap())
        .lines()
        .map_while(Result::ok)
        .take_while(|l| !l.starts_with("gcs http"))
        .collect();
    let _ = gcs.kill();
    let _ = gcs.wait();
    assert!(lines.iter().any(|l| l.contains("gcs cooperative network UNAUTHENTICATED (--insecure)")), "{lines:?}");
}

/// `cooploc faults --side-by-side N` takes 2 to 64 vehicles, its spacing only with it, and
/// positive distances; `--reach-m` (any scenario, `experiment` too) a positive distance: each
/// refusal names what is wrong, and nothing runs.
#[test]
fn a_large_team_fault_run_refuses_what_cannot_be() {
    let (code, out) = run(&["faults", "--side-by-side", "65"]);
    assert_eq!(code, Some(2), "{out}");
    assert!(out.contains("--side-by-side") && out.contains("65"), "{out}");
    let (code, out) = run(&["faults", "--spacing-m", "200"]);
    assert_eq!(code, Some(2), "{out}");
    assert!(out.contains("--side-by-side"), "the geometry needs the team: {out}");
    let (code, out) = run(&["faults", "--side-by-side", "4", "--spacing-m", "-5"]);
    assert_eq!(code, Some(1), "{out}");
    assert!(out.contains("--spacing-m and --duration-s must be positive"), "{out}");
    for command in ["faults", "experiment"] {
        let (code, out) = run(&[command, "--reach-m", "-5"]);
        assert_eq!(code, Some(1), "{out}");
        assert!(out.contains("--reach-m -5: the radios' reach must be a positive distance in m"), "{out}");
    }
}
