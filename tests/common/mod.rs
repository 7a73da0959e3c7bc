#![allow(dead_code)] // each test binary uses some of the helpers

//! Helpers shared by the integration tests.

/// The Python of the test virtualenv (`COOPLOC_PYTHON`, set by tests/run-all.sh). Under
/// `CI=true` a missing one fails the test; elsewhere the test says it skipped, naming `what`.
pub fn python(what: &str) -> Option<String> {
    match std::env::var("COOPLOC_PYTHON") {
        Ok(p) => Some(p),
        Err(_) if std::env::var("CI").as_deref() == Ok("true") => {
            panic!("COOPLOC_PYTHON is not set: run the tests through tests/run-all.sh")
        }
        Err(_) => {
            eprintln!("SKIPPED: {what} needs COOPLOC_PYTHON (tests/run-all.sh sets it)");
            None
        }
    }
}

/// Headless Chromium (`COOPLOC_CHROMIUM`, or `chromium` / `chromium-browser` on the PATH;
/// tests/run-all.sh installs Debian's package when it is missing). Under `CI=true` a missing
/// one fails the test; elsewhere the test says it skipped, naming `what`.
#[allow(dead_code)]
pub fn chromium(what: &str) -> Option<std::path::PathBuf> {
    let candidates = std::env::var_os("COOPLOC_CHROMIUM").map(std::path::PathBuf::from).into_iter().chain(
        std::env::var_os("PATH").into_iter().flat_map(|paths| {
            std::env::split_paths(&paths)
                .flat_map(|dir| ["chromium", "chromium-browser"].map(|name| dir.join(name)))
                .collect::<Vec<_>>()
        }),
    );
    for c in candidates {
        if c.is_file() {
            return Some(c);
        }
    }
    if std::env::var("CI").as_deref() == Ok("true") {
        panic!("{what} needs Chromium and none was found: tests/run-all.sh installs it (apt-get install chromium)");
    }
    eprintln!("SKIPPED: {what} needs Chromium (`apt-get install chromium`, or run tests/run-all.sh)");
    None
}

/// Spawns `cmd` in the repository root, forwarding its stdout lines to a channel (stderr is
/// dropped).
pub fn spawn_lines(cmd: std::process::Command) -> (std::process::Child, std::sync::mpsc::Receiver<String>) {
    spawn_lines_in(cmd, std::path::Path::new(env!("CARGO_MANIFEST_DIR")))
}

/// [`spawn_lines`] in folder `dir`.
pub fn spawn_lines_in(
    mut cmd: std::process::Command,
    dir: &std::path::Path,
) -> (std::process::Child, std::sync::mpsc::Receiver<String>) {
    use std::io::BufRead;
    let mut child =
        cmd.current_dir(dir).stdout(std::process::Stdio::piped()).stderr(std::process::Stdio::null()).spawn().unwrap();
    let out = child.stdout.take().unwrap();
    let (tx, rx) = std::sync::mpsc::channel();
    std::thread::spawn(move || {
        for line in std::io::BufReader::new(out).lines().map_while(Result::ok) {
            if tx.send(line).is_err() {
                break;
            }
        }
    });
    (child, rx)
}

/// The first line starting with `prefix` within `timeout` (the lines before it are skipped).
pub fn wait_line(rx: &std::sync::mpsc::Receiver<String>, prefix: &str, timeout: std::time::Duration) -> String {
    let deadline = std::time::Instant::now() + timeout;
    loop {
        let left = deadline.saturating_duration_since(std::time::Instant::now());
        match rx.recv_timeout(left) {
            Ok(line) if line.starts_with(prefix) => return line,
            Ok(_) => {}
            Err(e) => panic!("no line starting with {prefix:?}: {e}"),
        }
    }
}

/// Kills and reaps its processes when dropped (a failing test leaves none behind).
pub struct Kill(pub Vec<std::process::Child>);
impl Drop for Kill {
    fn drop(&mut self) {
        for c in &mut self.0 {
            let _ = c.kill();
            let _ = c.wait();
        }
    }
}

/// What `cooploc demo` writes by default, `logs/demo-<seed>-<run>.mcap` (ignored by git, like
/// in .gitignore): a user who ran the README's first command has one, and it is not a golden log.
pub fn demo_default(p: &std::path::Path) -> bool {
    let stem = p.file_stem().and_then(|s| s.to_str()).unwrap_or("");
    let parts: Vec<&str> = stem.split('-').collect();
    parts.len() == 3 && parts[0] == "demo" && parts[1..].iter().all(|x| !x.is_empty() && x.bytes().all(|b| b.is_ascii_digit()))
}

/// The logs of `dir` (logs/) that the replay tests hold to their golden summaries: every
/// `.mcap` there but the demo's default output, sorted.
pub fn committed_logs(dir: &std::path::Path) -> Vec<std::path::PathBuf> {
    let mut logs: Vec<std::path::PathBuf> = std::fs::read_dir(dir)
        .unwrap()
        .map(|e| e.unwrap().path())
        .filter(|p| p.extension().is_some_and(|e| e == "mcap"))
        .filter(|p| !demo_default(p))
        .collect();
    logs.sort();
    logs
}

/// The first arguments of a `cooploc node` of the paper scenario's simulated run: its scenario,
/// platform `id`, its vehicle at `vehicle` (a MAVLink URL).
pub fn paper_node_args(id: u16, vehicle: &str) -> Vec<String> {
    ["node", "--scenario", "sitl/scenarios/paper.toml", "--id", &id.to_string(), "--vehicle", vehicle].map(String::from).to_vec()
}

/// `--team-key FILE` for a test's node (or ground station): a node refuses an unsigned
/// cooperative network unless told --insecure. The file (a fixed passphrase) is written once
/// per test process, whole (renamed into place), so that tests running at once never read half
/// of it.
#[allow(dead_code)] // (not every test binary starts a node)
pub fn team_key_args() -> Vec<String> {
    let path = std::env::temp_dir().join(format!("cooploc-test-team-{}.key", std::process::id()));
    if !path.exists() {
        let tmp = path.with_extension(format!("{:?}.tmp", std::thread::current().id()).replace(['(', ')'], ""));
        std::fs::write(&tmp, "the passphrase of the tests' team\n").unwrap();
        std::fs::rename(&tmp, &path).unwrap();
    }
    vec!["--team-key".into(), path.display().to_string()]
}

/// The numbers of the first `[a, b, ...]` after `marker` in a line the binary printed
/// (`pos_ned_m [1.0, 2.0, 3.0]`).
#[allow(dead_code)] // (not every test binary reads one)
pub fn numbers_after(line: &str, marker: &str) -> Vec<f64> {
    let rest = line.split_once(marker).unwrap_or_else(|| panic!("no {marker:?} in {line:?}")).1;
    let inside = rest.split_once('[').and_then(|(_, r)| r.split_once(']')).unwrap_or_else(|| panic!("no [...] in {line:?}")).0;
    inside.split(',').map(|v| v.trim().parse().unwrap_or_else(|e| panic!("{v:?} in {line:?}: {e}"))).collect()
}
