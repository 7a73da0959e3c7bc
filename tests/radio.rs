//! A serial telemetry radio as the cooperative link: each node opens a pseudo-terminal as its
//! radio (`--coop-serial /dev/pts/N:57600`), and a radio network in the test joins them: one
//! shared channel (a multipoint SiK or mesh firmware), half duplex, at an air rate, with noise.
//!
//! ```text
//!  node 1 -- pty --\                             /-- pty -- node 2
//!                   >-- the air: one channel ---<
//!  node 3 -- pty --/   (rate, noise, buffers)
//! ```
//!
//! What a node writes is cut into packets on MAVLink frame boundaries (a radio's MAVLink
//! framing: a whole frame per packet, so that packets from two senders interleave only between
//! frames; SiK does this for frames up to its 252-byte packet and cuts a longer frame, which the
//! test counts and refuses: no frame cooploc sends is longer), queued (a radio buffers a few kilobytes and
//! drops what does not fit), sent one at a time at the air rate, each byte hit by noise with a
//! small probability (no firmware error correction), and delivered to every other radio. The nodes cut the byte stream back into frames, drop what noise
//! damaged, and ask for what they missed. Two teams, each told the team's schedule and the
//! channel's rate (each node sends in its own airtime slot): the paper scenario at 1 Hz on a
//! 64 kbit/s SiK (about 5,400 B/s at real time, 84% loaded), at 2x with the air rate scaled by
//! 2, and eight vehicles side by side ranging every 2 s on a 250 kbit/s SiK (about 21,000 B/s)
//! at 2x. Every node applies at least 99% of the epochs and knows them from the schedule, and the
//! bytes each node put on the air equal `cooploc budget`'s radio figure within 10% (issue 36's
//! bar). `COOPLOC_RADIO_SPEED` and `COOPLOC_RADIO_BPS` run the paper team at another speed-up
//! or rate (docs/protocol.md, "Airtime slots").
//! A third run takes one of the eight out of reach for a while: back, it takes the team's store,
//! paced, over several epochs, and nobody heals.

#![cfg(unix)]

use std::collections::VecDeque;
use std::io::{Read, Write};
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

mod common;

use common::{Kill, spawn_lines, wait_line};
use cooploc::estimation::Method;
use cooploc::experiment::{initial_state, run_filter};
use cooploc::protocol::budget::{self, Medium, TeamShape};
use cooploc::protocol::record::Encoding;
use cooploc::protocol::wire;
use cooploc::sitl::{PAPER_TOML, Scenario, World};
use serialport::SerialPort;

/// The largest packet on the air: SiK's.
const PACKET: usize = cooploc::protocol::fragment::MAX_RADIO_FRAME;
/// What a radio buffers before it drops (bytes).
const RADIO_BUFFER: usize = 8 * 1024;

/// Cuts whole MAVLink frames off the front of `pending` as packets (by the length byte, as a
/// radio's MAVLink framing does; bytes before a start marker go as a packet of their own); a
/// frame longer than a packet is cut into packets as SiK does (counted in `cut`).
fn packets(pending: &mut Vec<u8>, cut: &AtomicU64) -> Vec<Vec<u8>> {
    let mut out = Vec::new();
    loop {
        let Some(start) = pending.iter().position(|&b| b == 0xFD || b == 0xFE) else {
            if !pending.is_empty() {
                out.push(std::mem::take(pending));
            }
            return out;
        };
        if start > 0 {
            out.push(pending.drain(..start).collect());
        }
        let Some(&len) = pending.get(1) else { return out };
        let Some(&flags) = pending.get(2) else { return out };
        let len = match pending[0] {
            0xFE => 8 + usize::from(len),
            _ => 12 + usize::from(len) + if flags & 1 != 0 { 13 } else { 0 },
        };
        if pending.len() < len {
            return out;
        }
        if len > PACKET {
            cut.fetch_add(1, Ordering::Relaxed);
        }
        let frame: Vec<u8> = pending.drain(..len).collect();
        out.extend(frame.chunks(PACKET).map(<[u8]>::to_vec));
    }
}

/// Packets waiting for the channel: (sending radio, bytes), in order.
type Air = VecDeque<(usize, Vec<u8>)>;

/// What the air did, per radio.
#[derive(Default)]
struct AirStats {
    /// Bytes each radio was given by its node.
    written: Vec<AtomicU64>,
    /// Bytes dropped because the radio's buffer was full.
    overflow: AtomicU64,
    /// Bytes noise changed.
    corrupted: AtomicU64,
    /// Frames longer than a packet, which the radio cut in two (interleavable with others').
    cut: AtomicU64,
}

/// A radio out of reach of the others for a while: (its index, from, until), wall time after the
/// instant set in the lock (when every node is up), each edge put off until the air has been
/// quiet for [`QUIET`] (between two epochs' traffic). What it sends reaches nobody (and takes no
/// air time), what they send does not reach it.
type Away = Option<(usize, Duration, Duration, Arc<std::sync::OnceLock<Instant>>)>;

/// How long the air must have been quiet for an outage to begin or end. (Cut in the middle of an
/// epoch's records, the member and the team run that epoch on different sets, and no store is
/// valid for both: the whole team heals with the bound, as docs/robustness.md says; a test of
/// the store's transfer must not hang on where the cut fell.)
const QUIET: Duration = Duration::from_millis(150);

/// A radio network of `n` pseudo-terminals on one channel of `rate` bytes per second, each byte
/// corrupted with probability `noise`, one radio perhaps `away` for a while. Returns the device
/// paths the nodes open, the statistics and a flag that stops the threads.
fn radio_network(n: usize, rate: f64, noise: f64, away: Away) -> (Vec<String>, Arc<AirStats>, Arc<AtomicBool>) {
    let stats = Arc::new(AirStats { written: (0..n).map(|_| AtomicU64::new(0)).collect(), ..Default::default() });
    let stop = Arc::new(AtomicBool::new(false));
    let queue: Arc<Mutex<Air>> = Arc::default();
    let mut masters = Vec::new();
    let mut paths = Vec::new();
    for k in 0..n {
        let (master, slave) = serialport::TTYPort::pair().expect("a pseudo-terminal pair");
        paths.push(slave.name().unwrap());
        // The slave stays open (a pty whose slave is closed reads EIO on its master).
        std::mem::forget(slave);
        let mut reader = master.try_clone_native().unwrap();
        masters.push(master);
        let (queue, stats, stop) = (queue.clone(), stats.clone(), stop.clone());
        std::thread::spawn(move || {
            reader.set_timeout(Duration::from_millis(100)).unwrap();
            let mut buf = [0u8; 4096];
            let mut pending: Vec<u8> = Vec::new();
            while !stop.load(Ordering::Relaxed) {
                match reader.read(&mut buf) {
                    Ok(0) => return,
                    Ok(got) => {
                        stats.written[k].fetch_add(got as u64, Ordering::Relaxed);
                        pending.extend_from_slice(&buf[..got]);
                        let mut q = queue.lock().unwrap();
                        let mut mine: usize = q.iter().filter(|(from, _)| *from == k).map(|(_, p)| p.len()).sum();
                        for packet in packets(&mut pending, &stats.cut) {
                            if mine + packet.len() > RADIO_BUFFER {
                                stats.overflow.fetch_add(packet.len() as u64, Ordering::Relaxed);
                            } else {
                                mine += packet.len();
                                q.push_back((k, packet));
                            }
                        }
                    }
                    Err(e) if e.kind() == std::io::ErrorKind::TimedOut => {}
                    Err(_) => return,
                }
            }
        });
    }
    {
        let (stats, stop) = (stats.clone(), stop.clone());
        std::thread::spawn(move || {
            // A small deterministic generator for the noise (xorshift).
            let mut x: u64 = 0x9E37_79B9_7F4A_7C15;
            let mut uniform = move || {
                x ^= x << 13;
                x ^= x >> 7;
                x ^= x << 17;
                (x >> 11) as f64 / (1u64 << 53) as f64
            };
            let mut air_free = Instant::now();
            // the outage: not yet, on, over
            let (mut phase, mut last_packet) = (0, Instant::now());
            while !stop.load(Ordering::Relaxed) {
                if let Some((r, from, until, zero)) = &away
                    && let Some(z) = zero.get()
                    && last_packet.elapsed() >= QUIET
                    && phase < 2
                    && z.elapsed() >= if phase == 0 { *from } else { *until }
                {
                    phase += 1;
                    let what = if phase == 1 { "out of" } else { "back in" };
                    eprintln!("radio network: radio {r} {what} reach at {:.2} s", z.elapsed().as_secs_f64());
                }
                let is_away = |k: usize| phase == 1 && away.as_ref().is_some_and(|(r, ..)| *r == k);
                let next = queue.lock().unwrap().pop_front();
                let Some((from, mut packet)) = next else {
                    std::thread::sleep(Duration::from_millis(1));
                    air_free = air_free.max(Instant::now());
                    continue;
                };
                if is_away(from) {
                    continue;
                }
                // One packet at a time on the shared channel.
                air_free += Duration::from_secs_f64(packet.len() as f64 / rate);
                if let Some(wait) = air_free.checked_duration_since(Instant::now()) {
                    std::thread::sleep(wait);
                }
                for b in packet.iter_mut() {
                    if uniform() < noise {
                        *b ^= 1 << (uniform() * 8.0) as u32;
                        stats.corrupted.fetch_add(1, Ordering::Relaxed);
                    }
                }
                for (k, m) in masters.iter_mut().enumerate() {
                    if k != from && !is_away(k) {
                        let _ = m.write_all(&packet);
                    }
                }
                last_packet = Instant::now();
            }
        });
    }
    (paths, stats, stop)
}

/// One team on one shared radio channel: its scenario (a file the node and `cooploc sitl`
/// read), the ranging schedule and its period, the channel's rate at real time, the speed-up.
struct RadioCase {
    scenario: Scenario,
    scenario_path: String,
    schedule: &'static str,
    period_ms: u64,
    bps: f64,
    speed: u32,
    /// One member out of reach for a while (its index, from and until, s of wall time after every
    /// node is up), and the store bytes per second each answerer sends it when it is back (at
    /// the speed-up).
    away: Option<(usize, f64, f64)>,
    store_bps: Option<u64>,
}

/// Only one team on the air of this machine at a time (each one's timing is the test).
static ONE_TEAM: Mutex<()> = Mutex::new(());

#[test]
fn the_paper_team_at_1_hz_shares_a_64_kbit_s_radio_within_its_budget() {
    // The paper team at 1 Hz on one 64 kbit/s SiK channel: 5,400 B/s shared (measured, ECC
    // off), which the team's records, reports and estimates load to 84%, at 2x (193 s of wall
    // time; at 5x a quarter slot of margin is 12 ms of wall time on a two-core machine, and the
    // runs were bimodal: docs/protocol.md, "Airtime slots"). COOPLOC_RADIO_SPEED and
    // COOPLOC_RADIO_BPS run the same test at another speed-up or channel rate (`=1` for real
    // time; `COOPLOC_RADIO_BPS=21000` for a 250 kbit/s SiK).
    let env = |name: &str, default: f64| std::env::var(name).map_or(default, |v| v.parse().expect(name));
    radio_team(RadioCase {
        scenario: Scenario::from_toml_str(PAPER_TOML).unwrap(),
        scenario_path: "sitl/scenarios/paper.toml".into(),
        schedule: "1hz",
        period_ms: 1000,
        bps: env("COOPLOC_RADIO_BPS", 5_400.0),
        speed: env("COOPLOC_RADIO_SPEED", 2.0) as u32,
        away: None,
        store_bps: None,
    });
}

/// Eight vehicles side by side, 20 m apart, each ranging to the teammates within 70 m (up to
/// six), every 2 s, on one 250 kbit/s channel, at 2x.
#[test]
fn eight_members_at_half_a_hertz_share_a_250_kbit_s_radio_within_their_budget() {
    let dir = common::TempDir::new("cooploc-radio-eight");
    radio_team(eight_members(&dir, 200.0, 2));
}

/// A member out of reach comes back on a slow shared radio and takes the team's store over
/// several epochs (issue 36, item 3): the eight vehicles above, 120 s at 4x, node 5's radio out
/// of reach from 6 s to 12 s of wall time after the nodes are up (about 24 s of the team's
/// time, twelve epochs). Back, it is left out, the two lowest ids send it the team's store (56
/// KB, about 280 fragments) paced to 2,625 B/s each at real time (an eighth of the channel,
/// `--store-bps`'s default for it, times the speed-up), and it takes the store after the epochs
/// it took to come, brought forward by them: nobody heals, and every other node applies 99% of
/// the epochs. (Without the store carried on across epochs node 5 never takes it.)
#[test]
fn a_member_back_in_reach_takes_the_store_over_several_epochs_on_a_shared_radio() {
    let dir = common::TempDir::new("cooploc-radio-away");
    let speed = 4;
    radio_team(RadioCase {
        away: Some((4, 6.0, 12.0)),
        store_bps: Some(21_000 / 8 * u64::from(speed)),
        ..eight_members(&dir, 120.0, speed)
    });
}

/// The eight vehicles side by side at 0.5 Hz on 250 kbit/s for `duration_s`, at `speed` (the
/// scenario written into `dir`).
fn eight_members(dir: &common::TempDir, duration_s: f64, speed: u32) -> RadioCase {
    let mut scenario = Scenario::from_toml_str(PAPER_TOML).unwrap().side_by_side(8, 20.0, 70.0, duration_s);
    let every = scenario.ranging.schedules[0].clone();
    scenario.ranging.schedules =
        vec![cooploc::sitl::scenario::RangeSchedule { name: "0.5hz".into(), every_s: Some(2.0), start_s: Some(2.0), ..every }];
    let path = dir.join("eight.toml");
    std::fs::write(&path, toml::to_string(&scenario).unwrap()).unwrap();
    RadioCase {
        scenario,
        scenario_path: path.display().to_string(),
        schedule: "0.5hz",
        period_ms: 2000,
        bps: 21_000.0,
        speed,
        away: None,
        store_bps: None,
    }
}

/// Runs `case`: `cooploc sitl` and one node per vehicle on one radio network, every node told
/// the schedule's period and the channel's rate (airtime slots). Every node must apply 99% of
/// the epochs, know them from the schedule, and put on the air what `cooploc budget` says
/// within 10%; the team must beat dead reckoning by far.
fn radio_team(case: RadioCase) {
    let _one = ONE_TEAM.lock().unwrap_or_else(|e| e.into_inner());
    let world = World::new(&case.scenario).unwrap();
    let ids = world.platform_ids();
    let (speed, bps) = (case.speed, case.bps);
    let epochs = world.ranges(case.schedule, 1, 0).unwrap();
    let rate = bps * f64::from(speed);
    let noise = 2e-5;
    let zero = Arc::new(std::sync::OnceLock::new());
    let away = case.away.map(|(k, from, until)| (k, Duration::from_secs_f64(from), Duration::from_secs_f64(until), zero.clone()));
    let (paths, air, stop) = radio_network(ids.len(), rate, noise, away);
    let dir = common::TempDir::new("cooploc-radio");
    let key = dir.join("team.key");
    std::fs::write(&key, "the team's radio passphrase\n").unwrap();

    let bin = env!("CARGO_BIN_EXE_cooploc");
    let mut sitl = std::process::Command::new(bin);
    sitl.args(["sitl", &case.scenario_path, "--seed", "1", "--run", "0", "--schedule", case.schedule]);
    sitl.args(["--speed", &speed.to_string(), "--base-port", "0", "--wait-for-peers", "--sim-state-hz", "1"]);
    let (child, sitl_out) = spawn_lines(sitl);
    let mut children = Kill(vec![child]);
    let mut vehicle_addr = std::collections::BTreeMap::new();
    for _ in &ids {
        let line = wait_line(&sitl_out, "vehicle ", Duration::from_secs(30));
        let words: Vec<&str> = line.split_whitespace().collect();
        vehicle_addr.insert(words[1].parse::<u16>().unwrap(), words.last().unwrap().to_string());
    }
    let mut outs = Vec::new();
    for (k, &id) in ids.iter().enumerate() {
        let (t0, state) = initial_state(&world, 1, 0, id).unwrap();
        let mut node = std::process::Command::new(bin);
        let vehicle = format!("udpout:{}", vehicle_addr[&id]);
        node.args(["node", "--scenario", &case.scenario_path, "--id", &id.to_string(), "--vehicle", &vehicle]);
        node.args(["--coop-serial", &format!("{}:57600", paths[k]), "--method", "dcl", "--encoding", "compact"]);
        // The protocol's wall-time intervals shrink with the speed-up (1 s and 3 s at real time).
        node.args(["--retry-ms", &(1000 / speed).to_string(), "--epoch-timeout-ms", &(3000 / speed).to_string()]);
        // The team's schedule and the channel's rate: each node knows every epoch from the one
        // before and sends in its own slot (the slots are in the team clock, which runs at the
        // speed-up with the vehicles: the rate at real time).
        node.args(["--epoch-period-ms", &case.period_ms.to_string(), "--airtime-bps", &format!("{bps}")]);
        node.args(["--no-range-echo", "--idle-exit-s", "2", "--init-time-us", &t0.0.to_string()]).arg("--team-key").arg(&key);
        node.args(common::init_state_args(&state));
        if let Some(bps) = case.store_bps {
            node.args(["--store-bps", &bps.to_string()]);
        }
        let (child, out) = spawn_lines(node);
        children.0.push(child);
        wait_line(&out, &format!("node {id} coop serial"), Duration::from_secs(30));
        outs.push((id, out));
    }
    // every node is up: the vehicles' clock starts now (--wait-for-peers), and an outage counts from here
    zero.set(Instant::now()).unwrap();
    // The measured window: from a tenth of the run to nine tenths.
    let run_s = case.scenario.duration_s / f64::from(speed);
    let n = epochs.len() as u64;
    let least = (0.99 * n as f64).ceil() as u64;
    std::thread::sleep(Duration::from_secs_f64(0.1 * run_s));
    let written = || air.written.iter().map(|w| w.load(Ordering::Relaxed)).collect::<Vec<u64>>();
    let (t_a, a) = (Instant::now(), written());
    std::thread::sleep(Duration::from_secs_f64(0.8 * run_s));
    let (t_b, b) = (Instant::now(), written());
    let window = (t_b - t_a).as_secs_f64();

    let mut inputs = world.run_inputs(1, 0);
    for p in &mut inputs.platforms {
        p.imu.iter_mut().for_each(|s| *s = wire::imu_as_sent(s));
        p.odometer.iter_mut().for_each(|s| *s = wire::odometer_as_sent(s));
    }
    let dr = run_filter(&world, &inputs, &[], Method::DeadReckoning).unwrap();
    let first = &epochs[0].1;
    let mut failures = Vec::new();
    let (mut node_err, mut dr_err) = (0.0, 0.0);
    for (k, (id, out)) in outs.iter().enumerate() {
        let line = wait_line(out, &format!("node {id} done:"), Duration::from_secs_f64(run_s + 120.0));
        let stats = wait_line(out, &format!("node {id} stats"), Duration::from_secs(5));
        let tx = wait_line(out, &format!("node {id} coop_tx"), Duration::from_secs(5));
        let signing = wait_line(out, &format!("node {id} signing"), Duration::from_secs(5));
        eprintln!("{line}\n{stats}\n{signing}\n{tx}");
        let pos: Vec<f64> =
            line.split('[').nth(1).unwrap().split(']').next().unwrap().split(',').map(|v| v.trim().parse().unwrap()).collect();
        let applied: u64 = line.split(" epochs_applied ").nth(1).unwrap().split_whitespace().next().unwrap().parse().unwrap();
        let truth = inputs.platforms[k].truth.last().unwrap().pos_ned_m;
        let e = ((truth[0] - pos[0]).powi(2) + (truth[1] - pos[1]).powi(2)).sqrt();
        let dr_e = dr.platforms[k].final_error().pos_err_m;
        eprintln!("node {id}: {applied} epochs applied, final error {e:.2} m, dead reckoning {dr_e:.2} m");
        let stat = |name: &str| -> u64 {
            stats.split(&format!(" {name}: ")).nth(1).unwrap().split(',').next().unwrap().trim().parse().unwrap()
        };
        if stat("heals") > 0 {
            failures.push(format!("node {id} healed with the bound"));
        }
        if case.away.is_some_and(|(away, _, _)| away == k) {
            // Back in reach: left out, then the team's store, brought forward by the epochs it
            // took to come; the rest of the run at the team's side.
            let (excluded, adopted, forward) = (stat("epochs_excluded"), stat("stores_adopted"), stat("store_epochs_replayed"));
            eprintln!("node {id}: left out of {excluded} epochs, {adopted} stores taken, brought forward by {forward} epochs");
            if excluded < 2 || adopted < 1 || forward < 1 {
                failures.push(format!("node {id} did not take a store over several epochs: {stats}"));
            }
            node_err += e;
            dr_err += dr_e;
            continue;
        }
        if applied < least {
            failures.push(format!("node {id} applied only {applied} of {n} epochs"));
        }
        // every epoch after the first known from the schedule, the rangeless node's too
        let scheduled: u64 = stats.split("epochs_scheduled: ").nth(1).unwrap().split(',').next().unwrap().trim().parse().unwrap();
        if scheduled < least {
            failures.push(format!("node {id} knew only {scheduled} epochs from the schedule"));
        }
        node_err += e;
        dr_err += dr_e;

        // The budget on a radio: one copy on the air, no IP headers; the resends that the
        // noise costs (a frame of the record's size lost with 1 - (1 - noise)^bytes).
        let shape = TeamShape {
            team: ids.len(),
            state_dim: 16,
            ranges_per_node: first.iter().filter(|r| r.from == *id).count(),
            epoch_hz: f64::from(speed) * 1000.0 / case.period_ms as f64,
            encoding: Encoding::Compact,
            signed: true,
            echo_ranges: false,
        };
        let frames = budget::epoch_frames(&shape).unwrap();
        let frame_loss = 1.0 - (1.0 - noise).powf(frames.kinds[0].2 as f64 / frames.kinds[0].1 as f64);
        let expected = budget::rates_with_loss(&shape, &frames, Medium::Radio, frame_loss).node_bytes_per_s;
        let measured = (b[k] - a[k]) as f64 / window;
        eprintln!(
            "node {id}: put {measured:.0} B/s on the air (at {speed}x), budget {expected:.0} B/s ({:+.1}%): {:.0} B/s at real time",
            100.0 * (measured / expected - 1.0),
            measured / f64::from(speed)
        );
        // (A member out of reach costs its teammates the store they send it: the budget is for
        // the team's epochs.)
        if case.away.is_none() && (measured / expected - 1.0).abs() > 0.10 {
            failures.push(format!("node {id}: {measured:.0} B/s against the budget's {expected:.0}"));
        }
    }
    stop.store(true, Ordering::Relaxed);
    let (overflow, corrupted) = (air.overflow.load(Ordering::Relaxed), air.corrupted.load(Ordering::Relaxed));
    let cut = air.cut.load(Ordering::Relaxed);
    eprintln!(
        "air: {corrupted} bytes hit by noise, {overflow} dropped by full radio buffers, {cut} frames over a {PACKET}-byte packet"
    );
    assert!(failures.is_empty(), "{failures:?}");
    assert_eq!(cut, 0, "every frame must fit one radio packet");
    assert!(corrupted > 0, "the noise must have hit something for the test to mean anything");
    assert!(node_err < 0.5 * dr_err, "the team ({node_err:.2} m) should beat dead reckoning ({dr_err:.2} m) by far");
}
