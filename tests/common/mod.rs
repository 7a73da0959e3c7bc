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

/// A test's own folder in the temporary directory (`NAME-PID`), made at once and removed with
/// what is in it when dropped, a failing test's unwinding included: runs leave nothing behind.
#[allow(dead_code)] // (not every test binary writes files)
pub struct TempDir(pub std::path::PathBuf);
#[allow(dead_code)]
impl TempDir {
    pub fn new(name: &str) -> Self {
        let dir = std::env::temp_dir().join(format!("{name}-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap_or_else(|e| panic!("cannot make {}: {e}", dir.display()));
        Self(dir)
    }
    pub fn join(&self, name: impl AsRef<std::path::Path>) -> std::path::PathBuf {
        self.0.join(name)
    }
}
impl Drop for TempDir {
    fn drop(&mut self) {
        let _ = std::fs::remove_dir_all(&self.0);
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
/// cooperative network unless told --insecure. The file (a fixed passphrase) is one for every
/// test process (one file left in the temporary directory, not one per process), written whole
/// (renamed into place), so that tests running at once never read half of it.
#[allow(dead_code)] // (not every test binary starts a node)
pub fn team_key_args() -> Vec<String> {
    let path = std::env::temp_dir().join("cooploc-test-team.key");
    if !path.exists() {
        let writer = format!("{}-{:?}", std::process::id(), std::thread::current().id()).replace(['(', ')'], "");
        let tmp = path.with_extension(format!("{writer}.tmp"));
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

/// What a spy on the network sends on seeing a datagram from node `k` to node `j`: datagrams
/// that reach `j` first, from `k`'s address (a forger who can spoof the source), never lost.
#[allow(dead_code)] // (not every test binary has a spy)
pub type Spy = Box<dyn FnMut(usize, usize, &[u8]) -> Vec<Vec<u8>> + Send>;

/// A lossy network between the nodes' cooperative sockets: proxy socket `j` stands for node `j`
/// towards the others. A datagram from node `k` to proxy `j` goes on to node `j` from proxy `k`
/// (so node `j` sees node `k` at proxy `k`), or is dropped with probability `loss` (seeded per
/// proxy). A [`Spy`] sees every datagram before the loss and may inject its own.
#[allow(dead_code)] // (not every test binary uses it)
pub struct LossyNet {
    proxies: Vec<std::sync::Arc<std::net::UdpSocket>>,
    real: std::sync::Arc<std::sync::Mutex<Vec<Option<std::net::SocketAddr>>>>,
    stop: std::sync::Arc<std::sync::atomic::AtomicBool>,
    pub forwarded: std::sync::Arc<std::sync::atomic::AtomicU64>,
    pub dropped: std::sync::Arc<std::sync::atomic::AtomicU64>,
    pub injected: std::sync::Arc<std::sync::atomic::AtomicU64>,
}

#[allow(dead_code)]
impl LossyNet {
    pub fn new(n: usize, loss: f64, seed: u64) -> Self {
        Self::with_spy(n, loss, seed, None)
    }

    pub fn with_spy(n: usize, loss: f64, seed: u64, spy: Option<Spy>) -> Self {
        use rand::{Rng, SeedableRng};
        use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
        use std::sync::{Arc, Mutex};
        let proxies: Vec<Arc<std::net::UdpSocket>> =
            (0..n).map(|_| Arc::new(std::net::UdpSocket::bind("127.0.0.1:0").unwrap())).collect();
        let real = Arc::new(Mutex::new(vec![None; n]));
        let stop = Arc::new(AtomicBool::new(false));
        let counters = || Arc::new(AtomicU64::new(0));
        let (forwarded, dropped, injected) = (counters(), counters(), counters());
        let spy = Arc::new(Mutex::new(spy));
        for j in 0..n {
            let (proxies, real, stop, spy) = (proxies.clone(), real.clone(), stop.clone(), spy.clone());
            let (forwarded, dropped, injected) = (forwarded.clone(), dropped.clone(), injected.clone());
            std::thread::spawn(move || {
                let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed ^ j as u64);
                let me = &proxies[j];
                me.set_read_timeout(Some(std::time::Duration::from_millis(100))).unwrap();
                let mut buf = [0u8; 65536];
                while !stop.load(Ordering::Relaxed) {
                    let Ok((len, from)) = me.recv_from(&mut buf) else { continue };
                    let addrs = real.lock().unwrap().clone();
                    let (Some(k), Some(Some(to))) = (addrs.iter().position(|a| *a == Some(from)), addrs.get(j)) else { continue };
                    if let Some(spy) = spy.lock().unwrap().as_mut() {
                        for extra in spy(k, j, &buf[..len]) {
                            let _ = proxies[k].send_to(&extra, to);
                            injected.fetch_add(1, Ordering::Relaxed);
                        }
                    }
                    if rng.random::<f64>() < loss {
                        dropped.fetch_add(1, Ordering::Relaxed);
                        continue;
                    }
                    let _ = proxies[k].send_to(&buf[..len], to);
                    forwarded.fetch_add(1, Ordering::Relaxed);
                }
            });
        }
        Self { proxies, real, stop, forwarded, dropped, injected }
    }

    /// Where the nodes send to reach node `j`.
    pub fn proxy(&self, j: usize) -> String {
        self.proxies[j].local_addr().unwrap().to_string()
    }

    /// Node `j`'s real cooperative address (from its `coop udp` line).
    pub fn set_real(&self, j: usize, addr: &str) {
        self.real.lock().unwrap()[j] = Some(addr.parse().unwrap());
    }

    /// (forwarded, dropped, injected) datagrams so far.
    pub fn counts(&self) -> (u64, u64, u64) {
        use std::sync::atomic::Ordering::Relaxed;
        (self.forwarded.load(Relaxed), self.dropped.load(Relaxed), self.injected.load(Relaxed))
    }
}

impl Drop for LossyNet {
    fn drop(&mut self) {
        self.stop.store(true, std::sync::atomic::Ordering::Relaxed);
    }
}

/// `--init-ned`, `--init-vel-ned` and `--init-rpy-deg` for a node starting from `state`, to the
/// last bit (17 significant digits), so that a node started from the experiment's initial state
/// runs what the experiment runs.
#[allow(dead_code)] // (not every test binary starts a node from a state)
pub fn init_state_args(state: &cooploc::estimation::ins::InsState) -> Vec<String> {
    let v3 = |v: nalgebra::Vector3<f64>| format!("{:.17e},{:.17e},{:.17e}", v[0], v[1], v[2]);
    let (r, p, y) = state.att_frd_to_ned.euler_angles();
    vec![
        format!("--init-ned={}", v3(state.pos_ned_m)),
        format!("--init-vel-ned={}", v3(state.vel_ned_m_s)),
        format!("--init-rpy-deg={:.17e},{:.17e},{:.17e}", r.to_degrees(), p.to_degrees(), y.to_degrees()),
    ]
}
