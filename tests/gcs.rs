//! `cooploc gcs` as a process, fed from the test over UDP on 127.0.0.1 (ephemeral ports only):
//!
//! - synthetic cooperative traffic of three platforms (COOPLOC_ESTIMATE and HEARTBEAT frames built
//!   with `cooploc::protocol::wire`, with sequence gaps) shows up in `GET /api/state` with the
//!   right positions and loss, and the ground station heartbeats every node it learned;
//! - the page in headless Chromium lists every vehicle (and a screenshot goes to
//!   `target/gcs-screenshot.png`), with truth from fake vehicle links (SIM_STATE, HIGHRES_IMU);
//! - a Foxglove WebSocket client in Python (`tests/python/foxglove_ws_check.py`) sees the
//!   documented channels and receives a vehicle's LocationFix live.

mod common;

use std::io::{BufRead, BufReader, Read, Write};
use std::net::{SocketAddr, TcpStream, UdpSocket};
use std::process::{Child, Command, Stdio};
use std::sync::mpsc;
use std::time::{Duration, Instant};

use cooploc::estimation::Method;
use cooploc::protocol::MavMessage;
use cooploc::protocol::dialect::cooploc::{HIGHRES_IMU_DATA, MavAutopilot, MavType, SIM_STATE_DATA};
use cooploc::protocol::wire::{self, EstimateReport, GeoOrigin};
use cooploc::time::TimeUs;
use mavlink_core::MavHeader;
use nalgebra::{Matrix3, Vector3};
use serde_json::Value;

const NODE_COMPID: u8 = 191;
const ORIGIN: GeoOrigin = GeoOrigin { lat_deg: 34.7, lon_deg: 0.0, alt_m: 0.0 };

struct Gcs {
    child: Child,
    lines: mpsc::Receiver<String>,
    coop: SocketAddr,
    http: SocketAddr,
    foxglove: String,
}

impl Drop for Gcs {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

fn wait_line(rx: &mpsc::Receiver<String>, prefix: &str, timeout: Duration) -> String {
    let deadline = Instant::now() + timeout;
    loop {
        match rx.recv_timeout(deadline.saturating_duration_since(Instant::now())) {
            Ok(line) if line.starts_with(prefix) => return line,
            Ok(_) => {}
            Err(e) => panic!("cooploc gcs printed no line starting with {prefix:?}: {e}"),
        }
    }
}

fn start_gcs(extra: &[String]) -> Gcs {
    let mut cmd = Command::new(env!("CARGO_BIN_EXE_cooploc"));
    cmd.args(["gcs", "--coop", "127.0.0.1:0", "--http", "127.0.0.1:0", "--foxglove", "127.0.0.1:0", "--idle-exit-s", "60"]);
    cmd.args(extra);
    if !extra.iter().any(|a| a == "--team-key") {
        // (these tests' fake vehicles and nodes send unsigned frames)
        cmd.arg("--insecure");
    }
    let mut child = cmd.stdout(Stdio::piped()).stderr(Stdio::inherit()).spawn().expect("starting cooploc gcs");
    let out = child.stdout.take().unwrap();
    let (tx, lines) = mpsc::channel();
    std::thread::spawn(move || {
        for line in BufReader::new(out).lines().map_while(Result::ok) {
            if tx.send(line).is_err() {
                break;
            }
        }
    });
    let word = |line: String| line.split_whitespace().last().unwrap().to_string();
    let coop = word(wait_line(&lines, "gcs coop udp ", Duration::from_secs(30))).parse().unwrap();
    let http_url = word(wait_line(&lines, "gcs http ", Duration::from_secs(30)));
    let http = http_url.trim_start_matches("http://").trim_end_matches('/').parse().unwrap();
    let foxglove = word(wait_line(&lines, "gcs foxglove ", Duration::from_secs(30)));
    Gcs { child, lines, coop, http, foxglove }
}

/// A tiny blocking HTTP/1.1 GET: status and body.
fn http_get(addr: SocketAddr, path: &str) -> (u16, String) {
    let mut s = TcpStream::connect_timeout(&addr, Duration::from_secs(5)).expect("connecting to the web server");
    s.set_read_timeout(Some(Duration::from_secs(10))).unwrap();
    write!(s, "GET {path} HTTP/1.1\r\nHost: {addr}\r\nConnection: close\r\n\r\n").unwrap();
    let mut raw = Vec::new();
    s.read_to_end(&mut raw).unwrap();
    let text = String::from_utf8_lossy(&raw).to_string();
    let (head, body) = text.split_once("\r\n\r\n").expect("an HTTP response");
    let status = head.split_whitespace().nth(1).and_then(|c| c.parse().ok()).expect("a status code");
    let body = if head.to_ascii_lowercase().contains("transfer-encoding: chunked") {
        let mut out = String::new();
        let mut rest = body;
        while let Some((size, tail)) = rest.split_once("\r\n") {
            let n = usize::from_str_radix(size.trim(), 16).unwrap_or(0);
            if n == 0 {
                break;
            }
            out.push_str(&tail[..n]);
            rest = &tail[n + 2..];
        }
        out
    } else {
        body.to_string()
    };
    (status, body)
}

fn api_state(gcs: &Gcs) -> Value {
    let (status, body) = http_get(gcs.http, "/api/state");
    assert_eq!(status, 200, "{body}");
    serde_json::from_str(&body).expect("JSON")
}

/// Polls `/api/state` until `ok` holds (returns that state) or panics with the last one.
fn wait_state(gcs: &Gcs, what: &str, ok: impl Fn(&Value) -> bool) -> Value {
    let deadline = Instant::now() + Duration::from_secs(30);
    loop {
        let state = api_state(gcs);
        if ok(&state) {
            return state;
        }
        if Instant::now() > deadline {
            panic!("/api/state never showed {what}: {state:#}");
        }
        std::thread::sleep(Duration::from_millis(100));
    }
}

fn report(platform: u16, t_s: f64, pos: Vector3<f64>, cov: Matrix3<f64>) -> EstimateReport {
    EstimateReport {
        platform,
        t: TimeUs::from_secs_f64(t_s),
        epoch: t_s as u32,
        method: Method::Decentralized,
        position_ned_m: pos,
        velocity_ned_m_s: Vector3::new(8.0, 2.0, 0.0),
        yaw_rad: 0.25,
        position_covariance_m2: cov,
        yaw_variance_rad2: 1e-5,
        nis: 1.5,
        participants: 3,
        ranges: 2,
    }
}

fn frame(sysid: u8, compid: u8, seq: u8, msg: &MavMessage) -> Vec<u8> {
    wire::to_frame(MavHeader { system_id: u32::from(sysid), component_id: compid, sequence: seq }, msg)
}

fn node_heartbeat() -> MavMessage {
    wire::heartbeat(MavType::MAV_TYPE_ONBOARD_CONTROLLER, MavAutopilot::MAV_AUTOPILOT_INVALID)
}

fn udp() -> UdpSocket {
    let s = UdpSocket::bind("127.0.0.1:0").unwrap();
    s.set_read_timeout(Some(Duration::from_secs(5))).unwrap();
    s
}

fn f(v: &Value) -> f64 {
    v.as_f64().unwrap_or_else(|| panic!("not a number: {v}"))
}

#[test]
fn api_state_shows_three_vehicles_with_their_positions_and_loss() {
    let gcs = start_gcs(&[]);
    let cov = Matrix3::new(4.0, 0.5, 0.0, 0.5, 1.0, 0.0, 0.0, 0.0, 9.0);
    // Each platform's frames (a heartbeat every fifth slot, estimates otherwise) carry the
    // sequence numbers below; the missing ones are the loss the ground station must see.
    let plans: [(u8, Vec<u8>, f64); 3] = [
        (1, (0..20).collect(), 0.0),
        // 4, 9, 14 and 19 missing (24 is never followed, so it is not seen as lost): 4 of 24.
        (2, (0..24).filter(|q| q % 5 != 4).collect(), 4.0 / 24.0),
        // Across the wrap: 250 and 3 missing: 2 of 22.
        (3, (245..=255).chain(0..=10).filter(|&q| q != 250 && q != 3).collect(), 2.0 / 22.0),
    ];
    let sockets: Vec<UdpSocket> = plans.iter().map(|_| udp()).collect();
    let mut finals = Vec::new();
    for ((id, seqs, _), sock) in plans.iter().zip(&sockets) {
        let mut last = Vector3::zeros();
        for (k, &q) in seqs.iter().enumerate() {
            let msg = if k % 5 == 0 {
                node_heartbeat()
            } else {
                last = Vector3::new(100.0 * f64::from(*id) + k as f64, -50.0 * f64::from(*id) + 0.5 * k as f64, -1.0);
                wire::estimate_to_message(&report(u16::from(*id), k as f64, last, cov))
            };
            sock.send_to(&frame(*id, NODE_COMPID, q, &msg), gcs.coop).unwrap();
            std::thread::sleep(Duration::from_millis(2));
        }
        finals.push((*id, last));
    }
    sockets[0].send_to(b"not a MAVLink frame", gcs.coop).unwrap();

    let state = wait_state(&gcs, "three vehicles and all frames", |s| {
        let frames: u64 = s["links"].as_array().map_or(0, |l| l.iter().map(|x| x["packets"].as_u64().unwrap_or(0)).sum());
        s["vehicles"].as_array().is_some_and(|v| v.len() == 3) && frames == 60 && s["counters"]["bad_datagrams"] == 1
    });
    for (id, pos) in &finals {
        let v = state["vehicles"].as_array().unwrap().iter().find(|v| v["id"] == *id).unwrap();
        let p = &v["estimate"]["pos_ned_m"];
        for i in 0..3 {
            assert!((f(&p[i]) - pos[i]).abs() < 1e-4, "vehicle {id}: {p} against {pos:?}");
        }
        // 95% ellipse of [[4, .5], [.5, 1]]: eigenvalues 2.5 +- sqrt(2.25 + .25).
        let el = &v["estimate"]["ellipse95"];
        let major = (5.991_464_547 * (2.5 + 2.5f64.sqrt())).sqrt();
        assert!((f(&el["semi_major_m"]) - major).abs() < 1e-4, "{el}");
    }
    for (id, _, loss) in &plans {
        let link = state["links"].as_array().unwrap().iter().find(|l| l["sysid"] == *id && l["link"] == "coop").unwrap();
        assert_eq!(link["compid"], NODE_COMPID);
        assert_eq!(link["mav_type"], "ONBOARD_CONTROLLER");
        assert!((f(&link["loss_pct"]) - 100.0 * loss).abs() < 1e-9, "platform {id}: {link}");
        assert!(f(&link["bytes_per_s"]) > 0.0, "{link}");
    }
    assert_eq!(state["gcs"]["peers"].as_array().unwrap().len(), 3);
    // The ground station learned each node from its traffic and heartbeats it (1 Hz).
    for sock in &sockets {
        let mut buf = [0u8; 512];
        let deadline = Instant::now() + Duration::from_secs(10);
        let hb = loop {
            let (n, _) = sock.recv_from(&mut buf).expect("a heartbeat from the ground station");
            if let Some((h, MavMessage::HEARTBEAT(hb))) = wire::frames(&buf[..n]).into_iter().next() {
                break (h, hb);
            }
            assert!(Instant::now() < deadline, "no heartbeat");
        };
        assert_eq!((hb.0.system_id, hb.0.component_id), (255, 190));
        assert_eq!((hb.1.mavtype, hb.1.autopilot), (MavType::MAV_TYPE_GCS, MavAutopilot::MAV_AUTOPILOT_INVALID));
    }
    let (status, page) = http_get(gcs.http, "/");
    assert_eq!(status, 200);
    assert!(page.contains("<canvas id=\"map\"") && page.contains("/api/state"), "the page polls the API");
    assert!(!page.contains("http://") && !page.contains("https://"), "the page loads nothing from the network");
    drop(gcs);
}

/// Truth of vehicle `id` at `t_s` (a gentle S-curve northwards, 10 m/s), NED.
fn truth_pos(id: u16, t_s: f64) -> Vector3<f64> {
    let k = f64::from(id);
    Vector3::new(10.0 * t_s - 40.0 * k, 180.0 * (k - 2.0) + 60.0 * (t_s / 25.0 + k).sin(), 0.0)
}

/// A fake simulated vehicle link: waits for the ground station's heartbeat, then streams
/// SIM_STATE just before the HIGHRES_IMU sample of the same time, as `cooploc sitl` does.
struct FakeVehicle {
    id: u16,
    sock: UdpSocket,
    gcs: Option<SocketAddr>,
    seq: u8,
}

impl FakeVehicle {
    fn send(&mut self, msg: &MavMessage) {
        let to = *self.gcs.get_or_insert_with(|| {
            let mut buf = [0u8; 512];
            let (_, from) = self.sock.recv_from(&mut buf).expect("the ground station's heartbeat on the vehicle link");
            from
        });
        self.seq = self.seq.wrapping_add(1);
        self.sock.send_to(&frame(self.id as u8, 1, self.seq, msg), to).unwrap();
    }

    fn truth_step(&mut self, t_s: f64) {
        let p = truth_pos(self.id, t_s);
        let g = wire::ned_to_geodetic(&ORIGIN, &p);
        let v = (truth_pos(self.id, t_s + 0.01) - p) / 0.01;
        self.send(&MavMessage::SIM_STATE(SIM_STATE_DATA {
            q1: 1.0,
            lat: g.lat_deg as f32,
            lon: g.lon_deg as f32,
            alt: g.alt_m as f32,
            lat_int: wire::deg_to_e7(g.lat_deg),
            lon_int: wire::deg_to_e7(g.lon_deg),
            vn: v[0] as f32,
            ve: v[1] as f32,
            yaw: v[1].atan2(v[0]) as f32,
            ..Default::default()
        }));
        self.send(&MavMessage::HIGHRES_IMU(HIGHRES_IMU_DATA {
            time_usec: TimeUs::from_secs_f64(t_s).0,
            zacc: -9.8,
            ..Default::default()
        }));
    }
}

/// Feeds three vehicles for `seconds` of vehicle time: truth at 5 Hz on their links, estimates
/// at 1 Hz (drifting from the truth, growing covariance) on the cooperative network.
fn feed_team(gcs: &Gcs, vehicles: &mut [FakeVehicle], seconds: u32) {
    TeamFeed::new(vehicles).run(gcs, vehicles, 0, seconds, Duration::from_millis(3));
}

/// The nodes of [`feed_team`], kept between spans of vehicle time.
struct TeamFeed {
    nodes: Vec<UdpSocket>,
    seq: u8,
}

impl TeamFeed {
    fn new(vehicles: &[FakeVehicle]) -> Self {
        TeamFeed { nodes: vehicles.iter().map(|_| udp()).collect(), seq: 0 }
    }

    /// Vehicle time `from_s` to `to_s` (both included), `pause` between 0.2-s steps.
    fn run(&mut self, gcs: &Gcs, vehicles: &mut [FakeVehicle], from_s: u32, to_s: u32, pause: Duration) {
        for step in (from_s * 5)..=(to_s * 5) {
            let t = f64::from(step) / 5.0;
            for v in vehicles.iter_mut() {
                v.truth_step(t);
            }
            if step % 5 == 0 {
                for (v, node) in vehicles.iter().zip(&self.nodes) {
                    let k = f64::from(v.id);
                    let drift = Vector3::new(0.04 * t * (1.3 * k).cos(), 0.05 * t * (0.7 * k).sin(), 0.0);
                    let wiggle = Vector3::new((0.9 * t + k).sin(), (1.1 * t + 2.0 * k).cos(), 0.0) * 0.8;
                    let sigma = 1.0 + 0.03 * t;
                    let cov = Matrix3::new(
                        sigma * sigma * (1.0 + 0.3 * k),
                        0.4 * sigma * sigma,
                        0.0,
                        0.4 * sigma * sigma,
                        sigma * sigma,
                        0.0,
                        0.0,
                        0.0,
                        0.5,
                    );
                    let r = report(v.id, t, truth_pos(v.id, t) + drift + wiggle, cov);
                    node.send_to(&frame(v.id as u8, NODE_COMPID, self.seq, &wire::estimate_to_message(&r)), gcs.coop).unwrap();
                }
                self.seq = self.seq.wrapping_add(1);
            }
            std::thread::sleep(pause);
        }
    }
}

fn fake_vehicles(ids: &[u16]) -> (Vec<FakeVehicle>, Vec<String>) {
    let vehicles: Vec<FakeVehicle> = ids.iter().map(|&id| FakeVehicle { id, sock: udp(), gcs: None, seq: 0 }).collect();
    let args = vehicles
        .iter()
        .flat_map(|v| ["--vehicle".to_string(), format!("{}=udpout:{}", v.id, v.sock.local_addr().unwrap())])
        .collect();
    (vehicles, args)
}

fn target_dir() -> std::path::PathBuf {
    std::path::Path::new(env!("CARGO_TARGET_TMPDIR")).parent().unwrap().to_path_buf()
}

#[test]
fn page_in_headless_chromium_lists_every_vehicle() {
    let Some(chromium) = common::chromium("the ground station's browser test") else { return };
    let (mut vehicles, args) = fake_vehicles(&[1, 2, 3]);
    let gcs = start_gcs(&args);
    feed_team(&gcs, &mut vehicles, 90);
    let state = wait_state(&gcs, "three vehicles with errors against truth", |s| {
        s["vehicles"].as_array().is_some_and(|v| {
            v.len() == 3 && v.iter().all(|v| v["errors"].as_array().is_some_and(|e| e.len() >= 85) && v["truth"].is_object())
        })
    });
    // The errors are those the test built in: drift plus wiggle, at most about 6 m here.
    for v in state["vehicles"].as_array().unwrap() {
        let e = f(&v["error"]["horizontal_m"]);
        assert!(e > 0.0 && e < 8.0, "vehicle {}: error {e}", v["id"]);
        assert!(v["error"]["nees"].is_number());
        assert!(v["counts"]["link_imu_frames"].as_u64().unwrap() >= 450);
    }

    // What the page showed, next to the screenshot (for working on the page without the test).
    let (_, body) = http_get(gcs.http, "/api/state");
    std::fs::write(target_dir().join("gcs-state.json"), body).unwrap();
    let url = format!("http://{}/", gcs.http);
    let run = |extra: &[&str]| {
        let profile = tempdir("gcs-chromium");
        let out = Command::new(&chromium)
            .args(["--headless", "--no-sandbox", "--disable-gpu", "--no-first-run", "--disable-background-networking"])
            .args(["--disable-component-update", "--disable-sync", "--hide-scrollbars", "--virtual-time-budget=5000"])
            .arg(format!("--user-data-dir={}", profile.display()))
            .args(extra)
            .arg(&url)
            .stdin(Stdio::null())
            .output()
            .expect("running chromium");
        let _ = std::fs::remove_dir_all(&profile);
        out
    };
    let dom = run(&["--dump-dom"]);
    let html = String::from_utf8_lossy(&dom.stdout);
    assert!(dom.status.success(), "chromium failed: {}", String::from_utf8_lossy(&dom.stderr));
    for id in 1..=3 {
        assert!(html.contains(&format!("id=\"vehicle-{id}\"")), "vehicle {id} missing from the rendered page:\n{html}");
        assert!(html.contains(&format!("id=\"plot-{id}\"")), "error plot of vehicle {id} missing");
    }
    assert!(html.contains("ONBOARD_CONTROLLER") || html.contains("<table>"), "link table rendered");

    let shot = target_dir().join("gcs-screenshot.png");
    let _ = std::fs::remove_file(&shot);
    let out = run(&[&format!("--screenshot={}", shot.display()), "--window-size=1400,900"]);
    assert!(out.status.success(), "chromium screenshot failed: {}", String::from_utf8_lossy(&out.stderr));
    let png = std::fs::read(&shot).expect("the screenshot");
    assert!(png.starts_with(b"\x89PNG") && png.len() > 20_000, "a real picture ({} bytes)", png.len());
    eprintln!("screenshot: {}", shot.display());
}

/// One view everywhere: for one run of three vehicles (truth links and estimates), the web
/// page's JSON, the live Foxglove channels (read by an independent Python client) and the
/// Foxglove channels of the ground station's MCAP log (`--log`) carry the same colour per
/// vehicle, the same frames and transform, and the same 95 % ellipses; the page's ellipse of
/// each newest estimate is the one Foxglove draws (tests/python/view_agreement_check.py).
#[test]
fn page_live_foxglove_and_log_show_the_same_colours_frames_and_ellipses() {
    let Some(python) = common::python("the view agreement test") else { return };
    let dir = tempdir("gcs-views");
    let log = dir.join("gcs.mcap");
    let (mut vehicles, mut args) = fake_vehicles(&[1, 2, 3]);
    args.extend(["--log".to_string(), log.display().to_string(), "--link-capacity".to_string(), "5400".to_string()]);
    let mut gcs = start_gcs(&args);
    let mut feed = TeamFeed::new(&vehicles);
    // The first seconds make the channels; the client subscribes to every one it is told of.
    feed.run(&gcs, &mut vehicles, 0, 2, Duration::from_millis(3));
    wait_state(&gcs, "three vehicles", |s| s["vehicles"].as_array().is_some_and(|v| v.len() == 3));
    let script = concat!(env!("CARGO_MANIFEST_DIR"), "/tests/python/view_agreement_check.py");
    let live = dir.join("live.json");
    let mut listener = Command::new(&python)
        .args([script, "listen", &gcs.foxglove])
        .arg(&live)
        .args(["--vehicles", "1,2,3", "--until-t", "30"])
        .stdout(Stdio::piped())
        .stderr(Stdio::inherit())
        .spawn()
        .expect("running the Foxglove listener");
    let mut lines = BufReader::new(listener.stdout.take().unwrap()).lines();
    let first = lines.next().and_then(Result::ok).unwrap_or_default();
    assert_eq!(first, "subscribed", "the listener subscribed");
    // About 3 s of wall time, so that the once-a-second health reaches both.
    feed.run(&gcs, &mut vehicles, 3, 30, Duration::from_millis(20));
    let status = listener.wait().expect("the listener");
    for line in lines.map_while(Result::ok) {
        eprintln!("{line}");
    }
    assert!(status.success(), "the live listener did not see every vehicle reach t = 30 s");
    let (code, state) = http_get(gcs.http, "/api/state");
    assert_eq!(code, 200);
    let state_path = dir.join("state.json");
    std::fs::write(&state_path, &state).unwrap();
    // Ctrl-C: the ground station finishes its log.
    let pid = gcs.child.id().to_string();
    assert!(Command::new("kill").args(["-INT", &pid]).status().unwrap().success());
    let deadline = Instant::now() + Duration::from_secs(20);
    while gcs.child.try_wait().unwrap().is_none() {
        assert!(Instant::now() < deadline, "cooploc gcs did not stop on SIGINT");
        std::thread::sleep(Duration::from_millis(50));
    }
    let out = Command::new(&python).args([script, "compare"]).arg(&live).arg(&state_path).arg(&log).output().unwrap();
    let text = String::from_utf8_lossy(&out.stdout);
    eprintln!("{text}{}", String::from_utf8_lossy(&out.stderr));
    assert!(out.status.success(), "the three views disagree");
    for id in 1..=3 {
        assert!(text.contains(&format!("PASS vehicle {id}: one colour on the page, live and in the log")));
        assert!(text.contains(&format!("PASS vehicle {id}: the page's ellipse is the one Foxglove draws")));
    }
    let _ = std::fs::remove_dir_all(&dir);
}

fn tempdir(prefix: &str) -> std::path::PathBuf {
    let nanos = std::time::SystemTime::now().duration_since(std::time::UNIX_EPOCH).unwrap().as_nanos();
    let dir = std::env::temp_dir().join(format!("{prefix}-{}-{nanos}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    dir
}

#[test]
fn foxglove_client_receives_live_locations() {
    let Some(python) = common::python("the Foxglove WebSocket client test") else { return };
    let gcs = start_gcs(&[]);
    let node = udp();
    let cov = Matrix3::new(4.0, 0.5, 0.25, 0.5, 1.0, -0.5, 0.25, -0.5, 9.0);
    let pos = Vector3::new(321.5, -123.25, -2.0);
    let send = |t: f64, seq: u8| {
        for id in 1..=3u16 {
            let p = pos + Vector3::new(f64::from(id) * 100.0, 0.0, 0.0);
            node.send_to(&frame(id as u8, NODE_COMPID, seq, &wire::estimate_to_message(&report(id, t, p, cov))), gcs.coop)
                .unwrap();
        }
    };
    // First estimates: the ground station creates the vehicles' channels.
    send(1.0, 0);
    wait_state(&gcs, "three vehicles", |s| s["vehicles"].as_array().is_some_and(|v| v.len() == 3));
    let expect = wire::ned_to_geodetic(&ORIGIN, &(pos + Vector3::new(200.0, 0.0, 0.0)));
    let script = concat!(env!("CARGO_MANIFEST_DIR"), "/tests/python/foxglove_ws_check.py");
    let mut child = Command::new(python)
        .arg(script)
        .arg(&gcs.foxglove)
        .args(["--vehicle", "2", "--vehicles", "1,2,3"])
        .arg(format!("--lat={:.9}", expect.lat_deg))
        .arg(format!("--lon={:.9}", expect.lon_deg))
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .expect("running the Python client");
    // Live traffic while the client connects and subscribes.
    let deadline = Instant::now() + Duration::from_secs(60);
    let mut seq = 1u8;
    let status = loop {
        if let Some(status) = child.try_wait().unwrap() {
            break status;
        }
        assert!(Instant::now() < deadline, "the Foxglove client did not finish");
        send(1.0 + f64::from(seq) * 0.1, seq);
        seq = seq.wrapping_add(1);
        std::thread::sleep(Duration::from_millis(100));
    };
    let mut out = String::new();
    let mut err = String::new();
    child.stdout.take().unwrap().read_to_string(&mut out).unwrap();
    child.stderr.take().unwrap().read_to_string(&mut err).unwrap();
    eprintln!("{out}{err}");
    assert!(status.success(), "foxglove_ws_check.py failed");
    let result: Value = serde_json::from_str(out.lines().last().unwrap_or("")).expect("the client's JSON summary");
    assert!(result["subprotocol"].as_str().unwrap().starts_with("foxglove.sdk.v1"));
    // The covariance went out as ENU: EE, EN, E(-D) / NE, NN, N(-D) / ...
    let c: Vec<f64> = result["covariance_enu"].as_array().unwrap().iter().map(f).collect();
    assert_eq!(c, vec![1.0, 0.5, 0.5, 0.5, 4.0, -0.25, 0.5, -0.25, 9.0]);
    let _ = gcs.lines.try_recv();
}

/// `cooploc gcs --team-key`: only signed cooperative frames make vehicles (an unsigned forger's
/// estimates for platforms 7 and 8 and a replay of a genuine frame are refused and counted), the
/// ground station's own heartbeat is signed with the team key (so nodes that read only signed
/// frames learn it), and /api/state reports the signing counters.
#[test]
fn a_signed_ground_station_reads_only_the_teams_frames() {
    use cooploc::protocol::signing::{Signer, TeamKey, Verifier};
    let dir = tempdir("cooploc-gcs-key");
    let key_path = dir.join("team.key");
    std::fs::write(&key_path, "the team's passphrase\n").unwrap();
    let key = TeamKey::from_passphrase("the team's passphrase");
    let gcs = start_gcs(&["--team-key".into(), key_path.display().to_string()]);
    let cov = Matrix3::identity();
    let unix_us = || std::time::SystemTime::now().duration_since(std::time::UNIX_EPOCH).unwrap().as_micros() as u64;
    let mut team: Vec<(u8, UdpSocket, Signer)> = (1..=3).map(|id| (id, udp(), Signer::new(key.clone(), id, 0))).collect();
    let forger = udp();
    let mut genuine = Vec::new();
    for member in team.iter_mut() {
        for k in 0..5u8 {
            let msg = wire::estimate_to_message(&report(u16::from(member.0), f64::from(k), Vector3::new(1.0, 2.0, 0.0), cov));
            let header = MavHeader { system_id: u32::from(member.0), component_id: NODE_COMPID, sequence: k };
            let signed = member.2.frame(header, &msg, unix_us());
            member.1.send_to(&signed, gcs.coop).unwrap();
            genuine.push(signed);
            for fake in [7u8, 8] {
                let msg = wire::estimate_to_message(&report(u16::from(fake), f64::from(k), Vector3::zeros(), cov));
                forger.send_to(&frame(fake, NODE_COMPID, k, &msg), gcs.coop).unwrap();
            }
        }
        member.1.send_to(&node_heartbeat_signed(&mut member.2, member.0, unix_us()), gcs.coop).unwrap();
    }
    forger.send_to(&genuine[0], gcs.coop).unwrap(); // a replay
    let state = wait_state(&gcs, "three signed vehicles", |s| {
        s["vehicles"].as_array().is_some_and(|v| v.len() == 3) && s["gcs"]["signing"]["replayed"] == 1
    });
    let ids: Vec<u64> = state["vehicles"].as_array().unwrap().iter().map(|v| v["id"].as_u64().unwrap()).collect();
    assert_eq!(ids, vec![1, 2, 3], "only the team's vehicles: {state}");
    let sg = &state["gcs"]["signing"];
    assert_eq!((sg["accepted"].as_u64(), sg["unsigned"].as_u64()), (Some(18), Some(30)), "{sg}");
    assert_eq!(state["counters"]["unauthenticated"], 31, "{}", state["counters"]);
    // The ground station's heartbeat to a peer it learned is signed with the team key.
    let listener = udp();
    let mut member = Signer::new(key.clone(), 4, 0);
    listener.send_to(&node_heartbeat_signed(&mut member, 4, unix_us()), gcs.coop).unwrap();
    let mut verifier = Verifier::new(key);
    let mut buf = [0u8; 512];
    let deadline = Instant::now() + Duration::from_secs(10);
    loop {
        let (n, _) = listener.recv_from(&mut buf).expect("a heartbeat from the ground station");
        let got = verifier.datagram(&buf[..n], unix_us());
        if let Some((h, MavMessage::HEARTBEAT(_))) = got.frames.first() {
            assert_eq!(h.system_id, 255);
            break;
        }
        assert!(Instant::now() < deadline, "no signed heartbeat: refused {:?}", got.refused);
    }
    let _ = std::fs::remove_dir_all(&dir);
}

fn node_heartbeat_signed(s: &mut cooploc::protocol::signing::Signer, id: u8, unix_us: u64) -> Vec<u8> {
    s.frame(MavHeader { system_id: u32::from(id), component_id: NODE_COMPID, sequence: 9 }, &node_heartbeat(), unix_us)
}

/// The Foxglove layout users import (`tools/foxglove/cooploc-layout.json`) names only channels
/// cooploc publishes (live and in logs), only fields their schemas have, the palette's colours,
/// and a layout tree whose panels all exist.
#[test]
fn the_foxglove_layout_names_what_cooploc_publishes() {
    use cooploc::recording::topics;
    use cooploc::view::foxglove::{ERROR_SCHEMA, ESTIMATE_SCHEMA, HEALTH_SCHEMA};
    let text = std::fs::read_to_string(concat!(env!("CARGO_MANIFEST_DIR"), "/tools/foxglove/cooploc-layout.json")).unwrap();
    let layout: Value = serde_json::from_str(&text).expect("the layout is JSON");
    let configs = layout["configById"].as_object().expect("configById");
    // The panel tree references panels that exist, and every panel is placed.
    fn leaves(v: &Value, out: &mut Vec<String>) {
        match v {
            Value::String(s) => out.push(s.clone()),
            Value::Object(o) => ["first", "second"].iter().for_each(|k| leaves(&o[*k], out)),
            other => panic!("layout node {other}"),
        }
    }
    let mut placed = Vec::new();
    leaves(&layout["layout"], &mut placed);
    placed.sort();
    let mut ids: Vec<String> = configs.keys().cloned().collect();
    ids.sort();
    assert_eq!(placed, ids);
    let mut published: Vec<String> = vec![topics::TF.into(), topics::HEALTH.into()];
    for id in 1..=3u16 {
        published.extend([
            topics::location(id),
            topics::truth(id),
            topics::pose(id),
            topics::truth_pose(id),
            topics::ellipse(id),
            topics::estimate(id),
            topics::error(id),
        ]);
    }
    let fields = |schema: &str, nodes: bool| -> Vec<String> {
        let js: Value = serde_json::from_str(schema).unwrap();
        let props = if nodes { &js["properties"]["nodes"]["items"]["properties"] } else { &js["properties"] };
        props.as_object().unwrap().keys().cloned().collect()
    };
    let mut named = 0;
    for (panel, cfg) in configs {
        let mut topics_here: Vec<String> = Vec::new();
        for key in ["topicColors", "topics"] {
            if let Some(o) = cfg[key].as_object() {
                topics_here.extend(o.keys().cloned());
            }
        }
        for key in ["followTopic", "topicPath"] {
            if let Some(t) = cfg[key].as_str() {
                topics_here.push(t.to_string());
            }
        }
        for path in cfg["paths"].as_array().into_iter().flatten() {
            let value = path["value"].as_str().unwrap();
            let (topic, field) = value.split_once('.').unwrap();
            topics_here.push(topic.to_string());
            let (schema_fields, last) = if topic == topics::HEALTH {
                (fields(HEALTH_SCHEMA, true), field.rsplit('.').next().unwrap())
            } else if topic.ends_with("/estimate") {
                (fields(ESTIMATE_SCHEMA, false), field)
            } else {
                assert!(topic.ends_with("/error"), "{panel}: plot of {topic}");
                (fields(ERROR_SCHEMA, false), field)
            };
            assert!(schema_fields.iter().any(|f| f == last), "{panel}: {value}: no field {last}");
            let label = path["label"].as_str().unwrap();
            let id: u16 = label.trim_start_matches("vehicle ").parse().unwrap();
            assert_eq!(path["color"].as_str().unwrap(), cooploc::view::vehicle_hex(id), "{panel}: {label}'s colour");
        }
        for t in &topics_here {
            assert!(published.contains(t), "{panel}: {t} is not a channel cooploc publishes");
            named += 1;
        }
        if let Some(colors) = cfg["topicColors"].as_object() {
            for id in 1..=3u16 {
                assert_eq!(colors[&topics::location(id)].as_str().unwrap(), cooploc::view::vehicle_hex(id));
            }
        }
    }
    assert!(named >= 20, "the layout shows the team ({named} topics)");
}
