//! Issue 33's process-level suite: what the sans-io fault harness (`tests/faults.rs`) claims,
//! checked on real processes and sockets. `cooploc sitl` serves the paper scenario at 5x real
//! time; three `cooploc node` processes (dcl, every protocol option at its default) reach each
//! other only through a seeded relay ([`common::LossyNet`]) that loses whole datagrams and
//! carries a spy that forges. Each case runs about 80 s of wall time; at most five teams run at
//! once ([`TEAMS_AT_ONCE`]), so that the nodes are not starved of the CPU.
//!
//! - datagram loss of 30% and 50%: the team within 1.6x of its loss-free final error (30%), no
//!   node worse than its dead reckoning (50%), and the same cost of the loss as the harness's
//!   cases at 5x (`coop loss 30%/50%, packed, 5x real time`): the team's whole-run RMS error as a
//!   ratio to its fault-free run within 20% of the harness's. (Final errors are printed but not
//!   compared: at 50% loss the processes' final ratio spread 0.89-1.29x over five runs, one of
//!   them in CI with one heal per node near the end, where the harness over 12 link seeds spread
//!   0.95-1.00x: the processes' timing, wall time on a shared CPU, varies more than the
//!   harness's link seeds, and one late heal moves a final error by a third.)
//! - a forged record (platform 2's genuine record of the epoch before, moved 30 m and labelled
//!   as the attack epoch, sent to the others before the genuine one) and a relabelled replay
//!   (platform 2's record of ten epochs earlier under the current epoch's number), on the
//!   unsigned network (`--insecure`): every node ends within max(5 cm, 1% of its clean final
//!   error) of the clean run; with a team key the forged record is refused as unsigned.
//!
//! - node 3 killed right after it reports epoch 114 (30% of the run) and restarted at once by
//!   its supervisor with the same arguments (a start state for the scenario's start time, and
//!   `--state-file`), the simulator sending no SIM_STATE (as a real vehicle has none), on a clean
//!   network and one losing 30%: it restores the state it saved, carried across the gap, and is
//!   back within 2x of its clean error within 10 epochs; the team's cost, as a ratio to its
//!   clean run, within 20% of the harness's twin of that restart (down from just after the epoch
//!   to the instant the node said it was back, restored from its saved state, packed, 5x).
//!
//! The clean run is the reference: every node starts from the experiment's initial state at the
//! scenario's start, so without loss the processes run exactly what `cooploc experiment` runs.

use std::collections::BTreeMap;
use std::process::Command;
use std::time::Duration;

mod common;

use common::{Kill, LossyNet, Spy, spawn_lines, wait_line};

use cooploc::estimation::Method;
use cooploc::experiment::faults::{Faults, run_case};
use cooploc::experiment::{initial_state, run_filter};
use cooploc::protocol::MavMessage;
use cooploc::protocol::fragment::{Fragment, Payload, fragment};
use cooploc::protocol::record::{Encoding, decode_record, encode_record};
use cooploc::protocol::{framing, wire};
use cooploc::sitl::{PAPER_TOML, Scenario, World};
use cooploc::time::TimeUs;

const SPEED: f64 = 5.0;
const SEED: u64 = 1;
/// The epoch after which node 3 is killed in the restart cases (at 114 s of the 380 s run).
const KILL_AFTER_EPOCH: u32 = 114;
/// The platform whose records the spy forges, and the epoch it strikes at.
const VICTIM: u16 = 2;
const ATTACK_EPOCH: u32 = 100;

#[derive(Clone, Copy, PartialEq, Debug)]
enum Attack {
    None,
    /// Platform 2's genuine record of the epoch before the attack epoch (the attack epoch's own
    /// is not whole yet when its first fragment passes), its position moved 30 m north, labelled
    /// as the attack epoch.
    Forged,
    /// Platform 2's genuine record of ten epochs before, relabelled as the attack epoch.
    Relabelled,
}

/// Every node's COOPLOC_ESTIMATE as the relay saw it, by (platform, epoch).
type Estimates = std::sync::Arc<std::sync::Mutex<BTreeMap<(u16, u32), wire::EstimateReport>>>;

struct Outcome {
    /// Final horizontal error per node, m.
    finals: Vec<f64>,
    /// Dead reckoning's final horizontal error on the same inputs, per node, m.
    dr: Vec<f64>,
    /// Each node's closing lines (done, stats, coop_tx, vetting, signing).
    report: Vec<String>,
    /// Datagrams the relay forwarded, dropped and injected.
    relay: (u64, u64, u64),
    /// Each node's estimates (the last process's, for a restarted node).
    estimates: BTreeMap<(u16, u32), wire::EstimateReport>,
    /// The first epoch the restarted node reported after its restart.
    restarted_at_epoch: Option<u32>,
}

impl Outcome {
    fn rms(&self) -> f64 {
        (self.finals.iter().map(|e| e * e).sum::<f64>() / self.finals.len() as f64).sqrt()
    }

    /// The team's whole-run RMS horizontal error, m: each node's error at every epoch whose
    /// record the relay saw (the estimate the record carries), root-mean-squared per node, then
    /// over the team. A final error is one draw; at 50% loss, one heal near the end moves it by
    /// a third, while the whole run's error measures what the loss cost throughout.
    fn run_rms(&self, world: &World) -> f64 {
        let mut per_node: BTreeMap<u16, (f64, u32)> = BTreeMap::new();
        for ((p, _), r) in &self.estimates {
            let truth = world.trajectory(*p).unwrap().truth_at(r.t).pos_ned_m;
            let e = per_node.entry(*p).or_default();
            e.0 += (truth - r.position_ned_m).xy().norm_squared();
            e.1 += 1;
        }
        assert_eq!(per_node.len(), self.finals.len(), "the relay saw records from {} nodes", per_node.len());
        (per_node.values().map(|(s, n)| s / f64::from(*n)).sum::<f64>() / per_node.len() as f64).sqrt()
    }

    /// Node `k`'s counter `name` in its `NodeStats` line (`name: N`).
    fn stat(&self, k: usize, name: &str) -> u64 {
        let line = self.report[k].lines().find(|l| l.contains(" stats NodeStats")).unwrap_or_else(|| panic!("no stats line"));
        line.split(&format!(" {name}: ")).nth(1).and_then(|r| r.split([',', ' ']).next()).unwrap().parse().unwrap()
    }

    /// What each node's counters say of how the epochs went: in a failure message, whose tail
    /// is what a CI log keeps.
    fn epochs_line(&self, name: &str) -> String {
        let nodes: Vec<String> = (0..self.report.len())
            .map(|k| {
                format!(
                    "node {}: partial {}, heals {}, left out {}, longest wait {:.2} s, freezes {}",
                    k + 1,
                    self.stat(k, "epochs_partial"),
                    self.stat(k, "heals"),
                    self.stat(k, "epochs_excluded"),
                    self.stat(k, "longest_wait_us") as f64 * 1e-6,
                    self.stat(k, "freezes")
                )
            })
            .collect();
        format!("{name}: {}", nodes.join("; "))
    }

    /// The number after ` name ` in node `k`'s report line starting with `prefix`.
    fn counter(&self, k: usize, prefix: &str, name: &str) -> u64 {
        let line = self.report[k].lines().find(|l| l.contains(prefix)).unwrap_or_else(|| panic!("no {prefix} line"));
        line.split(&format!(" {name} ")).nth(1).and_then(|r| r.split_whitespace().next()).unwrap().parse().unwrap()
    }
}

/// The spy: reassembles platform 2's records as they pass; when the first fragment of the attack
/// epoch comes by, it sends every other node its forgery of that epoch (once per node) before the
/// genuine datagram goes on.
fn spy(attack: Attack, estimates: Estimates) -> Spy {
    let mut parts: BTreeMap<u32, BTreeMap<u8, Fragment>> = BTreeMap::new();
    let mut records: BTreeMap<u32, (u64, Vec<u8>)> = BTreeMap::new();
    let mut struck = std::collections::BTreeSet::new();
    Box::new(move |_k, j, datagram| {
        let mut out = Vec::new();
        for frame in framing::frames(datagram) {
            if let Ok(MavMessage::COOPLOC_ESTIMATE(m)) = &frame.message
                && let Ok(r) = wire::estimate_from_message(m)
            {
                estimates.lock().unwrap().insert((r.platform, r.epoch), r);
            }
            if attack == Attack::None {
                continue;
            }
            let Ok(MavMessage::COOPLOC_STATE_FRAGMENT(m)) = &frame.message else { continue };
            let Ok(f) = wire::fragment_from_message(m) else { continue };
            if f.platform != VICTIM || f.payload != Payload::Record {
                continue;
            }
            let (epoch, time_usec) = (f.epoch, f.time_usec);
            let series = parts.entry(epoch).or_default();
            series.insert(f.index, f.clone());
            if series.len() == usize::from(f.count) && !records.contains_key(&epoch) {
                let bytes: Vec<u8> = series.values().flat_map(|p| p.data.iter().copied()).collect();
                records.insert(epoch, (time_usec, bytes));
            }
            if epoch != ATTACK_EPOCH || !struck.insert(j) {
                continue;
            }
            let forged = match attack {
                Attack::Forged => records.get(&(epoch - 1)).map(|(t, bytes)| {
                    let mut rec = decode_record(VICTIM, TimeUs(*t), bytes).unwrap();
                    rec.snapshot.geometry.position_ned_m.x += 30.0;
                    encode_record(&rec, Encoding::F64).unwrap()
                }),
                Attack::Relabelled => records.get(&(epoch - 10)).map(|(_, bytes)| bytes.clone()),
                Attack::None => None,
            };
            let Some(forged) = forged else { panic!("the spy has no record of platform {VICTIM} to forge from") };
            for piece in fragment(VICTIM, epoch, time_usec, &forged).unwrap() {
                let header = mavlink_core::MavHeader { system_id: u32::from(VICTIM), component_id: 191, sequence: piece.index };
                out.push(wire::to_frame(header, &wire::fragment_to_message(&piece).unwrap()));
            }
        }
        out
    })
}

/// How many teams run at once in this binary. Its tests run in parallel and start eleven teams
/// in all, each taking about a fifth of a core at 5x: all at once they wanted more than the two
/// cores of this machine (and CI's), the nodes starved, and an epoch that waits 0.7 s of wall
/// time at most with 50% loss on a machine that keeps up waited 2-3 s, timed out and ran
/// partial, which the harness case these runs are compared with never sees (a CI run of
/// 2026-11-28 ended node 3 at 44.7 m at 50% loss; `cooploc faults --delay-ms` shows where such
/// latency leads, docs/robustness.md). Five teams take about one core.
const TEAMS_AT_ONCE: usize = 5;

/// A place among the [`TEAMS_AT_ONCE`] teams running, held while the team runs.
struct TeamSlot;

static TEAMS_RUNNING: std::sync::Mutex<usize> = std::sync::Mutex::new(0);
static TEAM_SLOT_FREED: std::sync::Condvar = std::sync::Condvar::new();

impl TeamSlot {
    fn take() -> TeamSlot {
        let mut running = TEAMS_RUNNING.lock().unwrap_or_else(|e| e.into_inner());
        while *running >= TEAMS_AT_ONCE {
            running = TEAM_SLOT_FREED.wait(running).unwrap_or_else(|e| e.into_inner());
        }
        *running += 1;
        TeamSlot
    }
}

impl Drop for TeamSlot {
    fn drop(&mut self) {
        *TEAMS_RUNNING.lock().unwrap_or_else(|e| e.into_inner()) -= 1;
        TEAM_SLOT_FREED.notify_one();
    }
}

/// The paper team as processes at 5x, the relay losing `loss` of the datagrams, the spy
/// striking with `attack`, signed with a team key or `--insecure`; with `restart`, node 3 killed
/// at 30% of the run and started again at once with the same arguments.
fn run_team(loss: f64, attack: Attack, signed: bool, restart: bool) -> Outcome {
    let _slot = TeamSlot::take();
    let world = World::new(&Scenario::from_toml_str(PAPER_TOML).unwrap()).unwrap();
    let (run, schedule) = (0u32, "1hz");
    let mut sitl = Command::new(env!("CARGO_BIN_EXE_cooploc"));
    sitl.args(["sitl", "sitl/scenarios/paper.toml", "--seed", &SEED.to_string(), "--run", "0", "--schedule", schedule]);
    // (a restarted node has no simulator's truth to start from: it must find its own state)
    let sim_state_hz = if restart { "0" } else { "1" };
    sitl.args(["--speed", &SPEED.to_string(), "--base-port", "0", "--wait-for-peers", "--sim-state-hz", sim_state_hz]);
    // One folder per team that restarts (tests run at once, and a team with the same loss, attack
    // and signing may be another test's clean team: a shared name let that team's clean-up delete
    // node 3's state file before its restart, which then had nothing to restore).
    static TEAMS: std::sync::atomic::AtomicUsize = std::sync::atomic::AtomicUsize::new(0);
    let team = TEAMS.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
    let state_dir = common::TempDir::new(&format!("cooploc-processes-team{team}"));
    let (sitl_child, sitl_out) = spawn_lines(sitl);
    let mut vehicle_addr = BTreeMap::new();
    for _ in world.platform_ids() {
        let line = wait_line(&sitl_out, "vehicle ", Duration::from_secs(30));
        let words: Vec<&str> = line.split_whitespace().collect();
        vehicle_addr.insert(words[1].parse::<u16>().unwrap(), words.last().unwrap().to_string());
    }
    let mut children = Kill(vec![sitl_child]);
    let ids = world.platform_ids();
    let estimates = Estimates::default();
    let net = LossyNet::with_spy(ids.len(), loss, 7, Some(spy(attack, estimates.clone())));
    let node_cmd = |k: usize| {
        let id = ids[k];
        let (t0, state) = initial_state(&world, SEED, run, id).unwrap();
        let mut node = Command::new(env!("CARGO_BIN_EXE_cooploc"));
        node.args(common::paper_node_args(id, &format!("udpout:{}", vehicle_addr[&id])));
        node.args(["--idle-exit-s", "3", "--init-time-us", &t0.0.to_string()]);
        node.args(common::init_state_args(&state));
        if restart {
            node.arg("--state-file").arg(state_dir.join(format!("node{id}.state")));
        }
        if signed {
            node.args(common::team_key_args());
        } else {
            node.arg("--insecure");
        }
        for j in (0..ids.len()).filter(|&j| j != k) {
            node.args(["--peer", &net.proxy(j)]);
        }
        node
    };
    let mut outs = Vec::new();
    for (k, &id) in ids.iter().enumerate() {
        let (child, out) = spawn_lines(node_cmd(k));
        children.0.push(child);
        let line = wait_line(&out, &format!("node {id} coop udp "), Duration::from_secs(30));
        net.set_real(k, line.split_whitespace().last().unwrap());
        outs.push(out);
    }
    let mut restarted_at_epoch = None;
    if restart {
        // Killed right after it reported epoch KILL_AFTER_EPOCH (30% of the 380 s run): the
        // restart's phase against the team's epochs is what the harness's twin repeats (a kill
        // before or after a node's share of an epoch changes the rest of the run, see
        // `restart_case`).
        let k = ids.len() - 1;
        let deadline = std::time::Instant::now() + Duration::from_secs(120);
        while !estimates.lock().unwrap().contains_key(&(ids[k], KILL_AFTER_EPOCH)) {
            assert!(std::time::Instant::now() < deadline, "node {} never reported epoch {KILL_AFTER_EPOCH}", ids[k]);
            std::thread::sleep(Duration::from_millis(2));
        }
        children.0[k + 1].kill().unwrap();
        children.0[k + 1].wait().unwrap();
        let last_epoch = estimates.lock().unwrap().keys().filter(|(p, _)| *p == ids[k]).map(|(_, e)| *e).max();
        estimates.lock().unwrap().retain(|(p, _), _| *p != ids[k]);
        let (child, out) = spawn_lines(node_cmd(k));
        children.0.push(child);
        let line = wait_line(&out, &format!("node {} coop udp ", ids[k]), Duration::from_secs(30));
        net.set_real(k, line.split_whitespace().last().unwrap());
        outs[k] = out;
        restarted_at_epoch = last_epoch.map(|e| e + 1);
    }
    let inputs = world.run_inputs(SEED, run);
    let dr = run_filter(&world, &inputs, &[], Method::DeadReckoning).unwrap();
    let mut outcome = Outcome {
        finals: Vec::new(),
        dr: Vec::new(),
        report: Vec::new(),
        relay: (0, 0, 0),
        estimates: BTreeMap::new(),
        restarted_at_epoch,
    };
    for (k, (&id, out)) in ids.iter().zip(&outs).enumerate() {
        // Everything the node said, up to its done line and the summary after it.
        let (mut report, deadline) = (Vec::new(), std::time::Instant::now() + Duration::from_secs(300));
        let done = loop {
            let left = deadline.saturating_duration_since(std::time::Instant::now());
            let line = out.recv_timeout(left).unwrap_or_else(|e| panic!("node {id} never said it was done: {e}"));
            if line.starts_with(&format!("node {id} done:")) {
                break line;
            }
            if line.starts_with(&format!("node {id} ")) {
                report.push(line);
            }
        };
        report.push(done.clone());
        while let Ok(line) = out.recv_timeout(Duration::from_secs(2)) {
            if line.starts_with(&format!("node {id} ")) {
                report.push(line);
            }
        }
        let truth = inputs.platforms[k].truth.last().unwrap().pos_ned_m;
        assert!(done.contains("pos_ned_m"), "node {id} ended without an estimate; it said:\n{}", report.join("\n"));
        let pos = common::numbers_after(&done, "pos_ned_m");
        outcome.finals.push(((truth[0] - pos[0]).powi(2) + (truth[1] - pos[1]).powi(2)).sqrt());
        outcome.dr.push(dr.platforms[k].final_error().pos_err_m);
        outcome.report.push(report.join("\n"));
    }
    outcome.relay = net.counts();
    drop(state_dir);
    outcome.estimates = estimates.lock().unwrap().clone();
    drop(children);
    outcome
}

/// The harness's cost of `loss` at 5x with packed datagrams, against its fault-free run, over
/// the same seed and run as the processes (one run each, the link faults to the end): the ratio
/// of the team's final RMS and of its whole-run RMS (each node's error sampled every second).
fn harness_ratios(loss: f64) -> (f64, f64) {
    harness_case_ratio(Faults { coop_loss: loss, links_until_s: 1e9, ..Faults::default() })
}

/// The harness's team error for `faults` at 5x with packed datagrams, against its fault-free
/// run, over the same seed and run as the processes: the ratio of the team's final RMS and of
/// its whole-run RMS (each node's error sampled every second while it ran).
fn harness_case_ratio(faults: Faults) -> (f64, f64) {
    let world = World::new(&Scenario::from_toml_str(PAPER_TOML).unwrap()).unwrap();
    let team = |faults: &Faults| {
        let out = run_case(&world, faults, Method::Decentralized, "1hz", SEED, 0, Encoding::F64).unwrap();
        let rms = |f: &dyn Fn(&cooploc::experiment::faults::NodeOutcome) -> f64| {
            (out.nodes.iter().map(|n| f(n).powi(2)).sum::<f64>() / out.nodes.len() as f64).sqrt()
        };
        (rms(&|n| n.final_err_m), rms(&|n| n.rms_err_m))
    };
    let faulty = team(&Faults { packed: true, speed: SPEED, ..faults });
    let clean = team(&Faults { speed: SPEED, ..Faults::default() });
    (faulty.0 / clean.0, faulty.1 / clean.1)
}

/// The teams of `cases` (loss, attack, signed) run side by side (each takes a fifth of a core),
/// as many at once as [`TEAMS_AT_ONCE`] lets.
fn at_once<const N: usize>(cases: [(f64, Attack, bool); N]) -> [Outcome; N] {
    std::thread::scope(|s| {
        let handles = cases.map(|(loss, attack, signed)| s.spawn(move || run_team(loss, attack, signed, false)));
        handles.map(|h| h.join().unwrap())
    })
}

fn print(name: &str, o: &Outcome) {
    eprintln!(
        "== {name}: team RMS {:.2} m, per node {:.2?} m, dead reckoning {:.2?} m, relay {:?}",
        o.rms(),
        o.finals,
        o.dr,
        o.relay
    );
    for r in &o.report {
        eprintln!("{r}");
    }
}

/// 30% and 50% datagram loss on the sockets cost what the harness says they cost.
#[test]
fn datagram_loss_on_the_sockets_costs_what_the_core_harness_says() {
    let [clean, thirty, fifty] = at_once([(0.0, Attack::None, true), (0.3, Attack::None, true), (0.5, Attack::None, true)]);
    let world = World::new(&Scenario::from_toml_str(PAPER_TOML).unwrap()).unwrap();
    print("clean", &clean);
    let mut problems = Vec::new();
    for (loss, bound, lossy) in [(0.3, Some(1.6), thirty), (0.5, None, fifty)] {
        let name = format!("{:.0}% loss", loss * 100.0);
        print(&name, &lossy);
        let before = problems.len();
        let (finals, (harness_finals, harness)) = (lossy.rms() / clean.rms(), harness_ratios(loss));
        let processes = lossy.run_rms(&world) / clean.run_rms(&world);
        eprintln!(
            "{:.0}% loss: whole run processes {processes:.3}x their clean run, harness {harness:.3}x; \
             final errors processes {finals:.3}x, harness {harness_finals:.3}x",
            loss * 100.0
        );
        eprintln!("{}", lossy.epochs_line(&name));
        if let Some(bound) = bound
            && processes > bound
        {
            problems.push(format!(
                "{:.0}% loss: team RMS {:.2} m, {processes:.2}x the clean {:.2} m",
                loss * 100.0,
                lossy.rms(),
                clean.rms()
            ));
        }
        for (k, (e, dr)) in lossy.finals.iter().zip(&lossy.dr).enumerate() {
            if e > dr {
                problems.push(format!("{:.0}% loss: node {} ended {e:.2} m, its dead reckoning {dr:.2} m", loss * 100.0, k + 1));
            }
        }
        if (processes / harness - 1.0).abs() > 0.2 {
            problems.push(format!(
                "{:.0}% loss: the whole run's error processes {processes:.3}x, harness {harness:.3}x: not within 20%",
                loss * 100.0
            ));
        }
        if problems.len() > before {
            problems.push(lossy.epochs_line(&name));
        }
        let (_, dropped, _) = lossy.relay;
        assert!(dropped > 0, "the relay lost nothing");
    }
    assert!(problems.is_empty(), "{}", problems.join("\n"));
}

/// A forged record and a relabelled replay on the unsigned network change no node's end by more
/// than max(5 cm, 1%); signed, the same frames are refused as unsigned.
#[test]
fn a_forged_record_and_a_relabelled_replay_change_nothing() {
    let cases = [(Attack::Forged, false), (Attack::Relabelled, false), (Attack::Forged, true)];
    let [clean, forged, relabelled, signed_forged] =
        at_once([(0.0, Attack::None, false), (0.0, cases[0].0, false), (0.0, cases[1].0, false), (0.0, cases[2].0, true)]);
    print("clean, insecure", &clean);
    let mut problems = Vec::new();
    for ((attack, signed), o) in cases.into_iter().zip([forged, relabelled, signed_forged]) {
        let name = format!("{attack:?}, {}", if signed { "signed" } else { "insecure" });
        print(&name, &o);
        let (_, _, injected) = o.relay;
        assert!(injected > 0, "{name}: the spy sent nothing");
        for k in 0..o.finals.len() {
            let (e, c) = (o.finals[k], clean.finals[k]);
            if (e - c).abs() > (0.01 * c).max(0.05) {
                problems.push(format!("{name}: node {} ended {e:.3} m, clean {c:.3} m", k + 1));
            }
            if k + 1 == usize::from(VICTIM) {
                continue; // the spy forges the victim's records to the others only
            }
            if signed {
                if o.counter(k, "signing", "unsigned") == 0 {
                    problems.push(format!("{name}: node {} refused nothing as unsigned", k + 1));
                }
            } else {
                let refused = o.counter(k, "vetting", "records_contradicted") + o.counter(k, "vetting", "records_rival");
                if refused == 0 {
                    problems.push(format!("{name}: node {} refused no record", k + 1));
                }
            }
        }
    }
    assert!(problems.is_empty(), "{}", problems.join("\n"));
}

/// Node 3 killed at 30% of the run and restarted at once with the arguments of its first start:
/// the start state those give is 114 s old, and the simulator sends no SIM_STATE; the node
/// restores the state it saved (`--state-file`) and is back within twice its clean error within
/// 10 epochs, to the end; its teammates are not hurt.
#[test]
fn a_node_restarted_with_its_first_arguments_restores_the_state_it_saved() {
    restart_case(0.0);
}

/// The same restart with 30% of the cooperative datagrams lost. (It once ended 0.794x its clean
/// run against the harness's 1.085x: the harness killed node 3 at the instant of epoch 114, the
/// processes at whatever phase the wall clock gave. Killed after the epoch ran in both, they
/// agree: 0.850x and 0.882x in one run.)
#[test]
fn a_node_restarted_on_a_lossy_network_restores_the_state_it_saved() {
    restart_case(0.3);
}

/// Node 3 killed and restarted with its first arguments on a network losing `loss` of the
/// datagrams, against the clean (loss-free, no restart) team.
fn restart_case(loss: f64) {
    let (clean, restarted) = std::thread::scope(|s| {
        let clean = s.spawn(|| run_team(0.0, Attack::None, true, false));
        let restarted = s.spawn(|| run_team(loss, Attack::None, true, true));
        (clean.join().unwrap(), restarted.join().unwrap())
    });
    print("clean", &clean);
    print("node 3 restarted", &restarted);
    let world = World::new(&Scenario::from_toml_str(PAPER_TOML).unwrap()).unwrap();
    let truth = |r: &wire::EstimateReport| {
        let t = world.trajectory(r.platform).unwrap().truth_at(r.t).pos_ned_m;
        (t - r.position_ned_m).xy().norm()
    };
    let node3 = |o: &Outcome| -> Vec<(u32, f64)> {
        o.estimates.iter().filter(|((p, _), _)| *p == 3).map(|((_, e), r)| (*e, truth(r))).collect()
    };
    let clean3 = node3(&clean);
    let clean_rms = (clean3.iter().map(|(_, e)| e * e).sum::<f64>() / clean3.len() as f64).sqrt();
    let back_from = restarted.restarted_at_epoch.expect("node 3 reported before it was killed") + 10;
    let after = node3(&restarted);
    let first: Vec<String> = after.iter().filter(|(e, _)| *e < back_from).map(|(e, err)| format!("{e}: {err:.2} m")).collect();
    eprintln!("node 3 in its first 10 epochs after the restart: {}", first.join(", "));
    let late: Vec<(u32, f64)> = after.into_iter().filter(|(e, _)| *e >= back_from).collect();
    eprintln!(
        "node 3 clean RMS {clean_rms:.2} m over {} epochs; after the restart, from epoch {back_from}: {} epochs, worst {:.2} m",
        clean3.len(),
        late.len(),
        late.iter().map(|(_, e)| *e).fold(0.0, f64::max)
    );
    assert!(
        restarted.report[2].contains("restored from its saved state"),
        "node 3 did not restore its saved state:\n{}",
        restarted.report[2]
    );
    assert!(late.len() > 100, "node 3 reported only {} epochs from epoch {back_from} on", late.len());
    for (e, err) in &late {
        assert!(*err <= 2.0 * clean_rms, "node 3 at epoch {e}: {err:.2} m, more than twice its clean RMS {clean_rms:.2} m");
    }
    // The same restart in the harness, its twin: node 3 down from just after epoch 114 ran (its
    // record goes at the range grace, 0.1 s after the epoch) to the instant the processes' node
    // 3 restarted (its saved state's time and age, as it said), restored from the state it
    // saved: the two teams' ratios to their own clean runs within 20% of each other. (The phase
    // matters: in the harness alone, node 3 killed at an epoch's instant ends the team 1.09-1.16x
    // its clean run, before its record went 0.89-0.93x, after the epoch ran 0.83-0.86x; see
    // tests/faults.rs a_restart_costs_what_its_phase_against_the_epochs_gives.)
    let line = restarted.report[2].lines().find(|l| l.contains("restored from its saved state of t ")).unwrap();
    let words: Vec<&str> = line.split_once("saved state of t ").unwrap().1.split_whitespace().collect();
    let saved_s = words[0].parse::<f64>().unwrap() / 1e6;
    let back_s = saved_s + words[1].trim_start_matches('(').parse::<f64>().unwrap();
    let epoch_s = world.ranges("1hz", SEED, 0).unwrap()[KILL_AFTER_EPOCH as usize - 1].0.0 as f64 / 1e6;
    let from_s = (epoch_s + 0.11).min(back_s - 0.01);
    eprintln!("node 3 saved at {saved_s:.3} s, back at {back_s:.3} s; the harness's twin: down from {from_s:.3} s");
    let restore = Faults {
        kill: Some(cooploc::experiment::faults::Outage { node: 2, from_s, until_s: back_s }),
        restore: true,
        coop_loss: loss,
        links_until_s: 1e9,
        ..Faults::default()
    };
    // The whole run's error, not the final one, as for the loss cases: at 30% loss one heal
    // near the end moved the final ratio to 1.073x against the harness's 0.891x in CI.
    let (finals, (harness_finals, harness)) = (restarted.rms() / clean.rms(), harness_case_ratio(restore));
    let processes = restarted.run_rms(&world) / clean.run_rms(&world);
    eprintln!(
        "restart from the saved state: whole run, processes {processes:.3}x their clean run, harness {harness:.3}x; \
         final errors {finals:.3}x and {harness_finals:.3}x"
    );
    assert!(
        (processes / harness - 1.0).abs() <= 0.2,
        "the processes' restart costs {processes:.3}x over the whole run, the harness's {harness:.3}x: more than 20% apart"
    );
    for k in 0..2 {
        assert!(
            restarted.finals[k] <= 2.0 * clean.finals[k],
            "node {} ended {:.2} m, clean {:.2} m",
            k + 1,
            restarted.finals[k],
            clean.finals[k]
        );
    }
}
