//! Fault injection: a team of nodes run over a simulated network and simulated vehicle links
//! that lose, delay, reorder and damage, with nodes that stall, die and restart, join late and
//! leave. Each node is the node shell a process runs ([`crate::node::shell`]), fed the bytes of
//! the cooperative datagrams (so a fault can damage bytes, and the shell's framing and checks
//! are what meets it) and the vehicle's samples as decoded inputs. Deterministic: every random
//! choice comes from the seed, and wall time is the vehicle's time divided by [`Faults::speed`],
//! so a case and a seed always give the same numbers.
//!
//! What a run measures, per node: the horizontal error and its 2-D NEES against the truth at the
//! end of the fault window and at the end of the run, the dead-reckoning error of the same inputs,
//! the node's counters; for the team: the epochs at which the nodes that ran them hold different
//! store digests (a disagreement, seen from outside), the detections the nodes counted
//! themselves, and the last epoch at which they still disagreed.

use std::cmp::Reverse;
use std::collections::{BTreeMap, BinaryHeap};

use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use serde::Serialize;

use super::{ExperimentError, nav_model, run_filter, state_from};
use crate::estimation::nav::NavState;
use crate::estimation::{Method, PlatformId};
use crate::node::core::{NodeConfig, NodeCore, NodeInput, NodeStats};
use crate::node::peers::Source;
use crate::node::profile::VehicleProfile;
use crate::node::shell::{LinkFacts, NodeInit, NodeShell, Now, ShellConfig, ShellOutput};
use crate::protocol::budget;
use crate::protocol::record::Encoding;
use crate::sitl::world::{SimEvent, World};
use crate::time::TimeUs;

/// A window of vehicle time during which one node (index into the team) is affected.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct Outage {
    pub node: usize,
    pub from_s: f64,
    pub until_s: f64,
}

impl Outage {
    fn covers(&self, node: usize, t: TimeUs) -> bool {
        node == self.node && t.as_secs_f64() >= self.from_s && t.as_secs_f64() < self.until_s
    }
}

/// What goes wrong in one case. Link faults apply from 0 s to `links_until_s`.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Faults {
    /// Probability that a datagram on the cooperative network is lost (per receiver).
    pub coop_loss: f64,
    /// Probability that a frame on a vehicle link (IMU, odometer, range) is lost.
    pub vehicle_loss: f64,
    /// Latency of each cooperative datagram, uniform in this range, ms (random latencies
    /// reorder datagrams).
    pub delay_ms: (u64, u64),
    /// The end of the link faults (loss, delay), s of vehicle time.
    pub links_until_s: f64,
    /// The IMU frame at this epoch's instant never reaches this node: (node, epoch).
    pub drop_imu_at_epoch: Option<(usize, u32)>,
    /// The node is frozen (SIGSTOP): what it would have received waits in its sockets.
    pub stall: Option<Outage>,
    /// The node is dead: what is sent to it is lost; it restarts from an independent fix, or
    /// with `restore` from the state it saved (`cooploc node --state-file`).
    pub kill: Option<Outage>,
    /// A killed node restarts from the state it last saved (every second of vehicle time, as
    /// the node writes it), carried across the gap ([`crate::node::saved`]), not from a fix.
    pub restore: bool,
    /// The node starts only at this time, s.
    pub join: Option<(usize, f64)>,
    /// What a node sends at one step travels as the runner sends it on UDP: a record's first
    /// fragment alone, the rest packed into datagrams of up to [`budget::MAX_DATAGRAM`] bytes;
    /// loss and delay strike whole datagrams (as a lossy network does), not single messages.
    pub packed: bool,
    /// Nodes whose cooperative radio is out of range (both ways) for a while; their vehicle
    /// links are not.
    pub leave: Vec<Outage>,
    /// How many times faster than real time the vehicles run (`cooploc sitl --speed`): the
    /// nodes' wall-clock timers (retries, epoch timeouts) and the network's delays are wall
    /// time, so in vehicle time they last `speed` times longer. 1: real time.
    pub speed: f64,
    /// Probability that a cooperative datagram arrives damaged (per receiver, while the link
    /// faults last): one byte changed, or the datagram cut short at a random length.
    pub corrupt: f64,
    /// The link faults' own seed: the same world run (seed, run) under another draw of which
    /// datagrams are lost, delayed or damaged and which vehicle frames are lost, as a relay with
    /// its own seed draws them. None: drawn from the run's seed.
    pub link_seed: Option<u64>,
    /// The nodes run as an unsigned team does (`cooploc node --insecure`): they believe nothing
    /// a record says of its sender before vetting ([`crate::node::core::NodeConfig::authenticated_peers`]).
    /// False: as the signed team `cooploc node` runs by default (the harness's network carries
    /// only its nodes' own records: it has no forger).
    pub unsigned: bool,
    /// One node's team clock is off (node index, ms; its clock ahead of the others'): a TIMESYNC
    /// mapping or a companion's NTP that is wrong by that much. Its vehicle's samples reach it
    /// stamped that much later than the instant they were taken, and its ranges are named by the
    /// instant of the epoch grid ([`EPOCH_GRID_US`], the profiles' `epoch_grid_ms = 100`)
    /// nearest to theirs (the epoch's own up to half the grid). Its errors are scored against
    /// the truth at the instant its clock names (so what is measured is what the offset does to
    /// the team's updates, not the offset itself).
    pub clock_offset: Option<(usize, f64)>,
    /// Store bytes per second each answerer sends a left-out teammate
    /// ([`crate::node::core::NodeConfig::store_bps`], `cooploc node --store-bps`): a store larger
    /// than that in an epoch comes over several epochs and is brought forward by them. 0: the
    /// whole store at each answer.
    pub store_bps: u64,
}

/// The grid on which a node names its ranges' epochs (the vehicle profiles' `epoch_grid_ms`),
/// us: clocks that agree to half of it name every epoch alike.
pub const EPOCH_GRID_US: u64 = 100_000;

impl Default for Faults {
    fn default() -> Self {
        Faults {
            coop_loss: 0.0,
            vehicle_loss: 0.0,
            delay_ms: (0, 0),
            links_until_s: 0.0,
            drop_imu_at_epoch: None,
            stall: None,
            kill: None,
            restore: false,
            join: None,
            packed: false,
            leave: Vec::new(),
            speed: 1.0,
            corrupt: 0.0,
            link_seed: None,
            unsigned: false,
            clock_offset: None,
            store_bps: 0,
        }
    }
}

impl Faults {
    /// How far node `k`'s team clock is ahead of the truth, us.
    pub fn clock_offset_us(&self, k: usize) -> u64 {
        match self.clock_offset {
            Some((n, ms)) if n == k && ms > 0.0 => (ms * 1000.0).round() as u64,
            _ => 0,
        }
    }

    /// When the last fault ends (0 for none), s.
    pub fn end_s(&self) -> f64 {
        let faulty = self.coop_loss > 0.0 || self.vehicle_loss > 0.0 || self.delay_ms.1 > 0 || self.corrupt > 0.0;
        let link = if faulty { self.links_until_s } else { 0.0 };
        [self.stall, self.kill]
            .iter()
            .flatten()
            .chain(&self.leave)
            .map(|o| o.until_s)
            .chain(self.join.map(|(_, t)| t))
            .fold(link, f64::max)
    }
}

impl Faults {
    /// Whether every outage and join of the case is over before `duration_s` (the scenario's
    /// end): a case whose node comes back after the end says nothing about recovery. Link faults
    /// fit any scenario (they last to its end when it is shorter than `links_until_s`).
    pub fn fits(&self, duration_s: f64) -> bool {
        [self.stall, self.kill].iter().flatten().chain(&self.leave).all(|o| o.until_s < duration_s)
            && self.join.is_none_or(|(_, t)| t < duration_s)
    }
}

/// When the standard cases' link faults end on the paper scenario (380 s), s: recovery can be
/// seen before the end.
pub const LINK_FAULTS_UNTIL_S: f64 = 340.0;

/// A named case.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct FaultCase {
    pub name: &'static str,
    pub faults: Faults,
}

/// The cases of issue 10's fault-injection table, on the paper scenario (380 s, 1 Hz ranging).
/// Link faults last until 340 s so that recovery can be seen before the end.
pub fn standard_cases() -> Vec<FaultCase> {
    let links = |coop_loss, vehicle_loss, delay_ms| Faults {
        coop_loss,
        vehicle_loss,
        delay_ms,
        links_until_s: LINK_FAULTS_UNTIL_S,
        ..Faults::default()
    };
    let node3 = |from_s, until_s| Some(Outage { node: 2, from_s, until_s });
    vec![
        FaultCase { name: "fault-free", faults: Faults::default() },
        FaultCase { name: "coop loss 1%", faults: links(0.01, 0.0, (0, 0)) },
        FaultCase { name: "coop loss 10%", faults: links(0.10, 0.0, (0, 0)) },
        FaultCase { name: "coop loss 30%", faults: links(0.30, 0.0, (0, 0)) },
        FaultCase { name: "coop loss 50%", faults: links(0.50, 0.0, (0, 0)) },
        FaultCase { name: "coop loss 30%, packed datagrams", faults: Faults { packed: true, ..links(0.30, 0.0, (0, 0)) } },
        FaultCase { name: "coop loss 50%, packed datagrams", faults: Faults { packed: true, ..links(0.50, 0.0, (0, 0)) } },
        FaultCase {
            name: "coop loss 30%, packed, 5x real time",
            faults: Faults { packed: true, speed: 5.0, ..links(0.30, 0.0, (0, 0)) },
        },
        FaultCase {
            name: "coop loss 50%, packed, 5x real time",
            faults: Faults { packed: true, speed: 5.0, ..links(0.50, 0.0, (0, 0)) },
        },
        FaultCase { name: "damaged datagrams 10%", faults: Faults { corrupt: 0.10, ..links(0.0, 0.0, (0, 0)) } },
        FaultCase {
            name: "damaged datagrams 30%, packed",
            faults: Faults { corrupt: 0.30, packed: true, ..links(0.0, 0.0, (0, 0)) },
        },
        FaultCase { name: "vehicle loss 0.5%", faults: links(0.0, 0.005, (0, 0)) },
        FaultCase { name: "vehicle loss 5%", faults: links(0.0, 0.05, (0, 0)) },
        FaultCase {
            name: "IMU frame lost at an epoch",
            faults: Faults { drop_imu_at_epoch: Some((0, 50)), ..Faults::default() },
        },
        FaultCase { name: "delay 0-300 ms, reordered", faults: links(0.0, 0.0, (0, 300)) },
        FaultCase { name: "node 3 stalled 3 s", faults: Faults { stall: node3(150.0, 153.0), ..Faults::default() } },
        FaultCase { name: "node 3 stalled 10 s", faults: Faults { stall: node3(150.0, 160.0), ..Faults::default() } },
        FaultCase { name: "node 3 killed, back after 20 s", faults: Faults { kill: node3(114.0, 134.0), ..Faults::default() } },
        FaultCase {
            name: "node 3 killed, restarted at once from its saved state",
            faults: Faults { kill: node3(114.0, 114.3), restore: true, ..Faults::default() },
        },
        FaultCase { name: "node 3 joins at 100 s", faults: Faults { join: Some((2, 100.0)), ..Faults::default() } },
        FaultCase {
            name: "node 3 leaves for 60 s",
            faults: Faults { leave: node3(150.0, 210.0).into_iter().collect(), ..Faults::default() },
        },
        FaultCase {
            name: "node 3 leaves for 60 s, 10% loss, delay 0-300 ms",
            faults: Faults { leave: node3(150.0, 210.0).into_iter().collect(), ..links(0.10, 0.0, (0, 300)) },
        },
    ]
}

/// The offsets of the clock sweep ([`clock_offset_cases`]), ms.
pub const CLOCK_OFFSETS_MS: [f64; 9] = [1.0, 2.0, 5.0, 10.0, 20.0, 30.0, 45.0, 55.0, 100.0];

/// What a team clock that is off costs (issue 31, item 2): fault-free, then one node's clock
/// ahead of its teammates' by each of [`CLOCK_OFFSETS_MS`] for the whole run: node 1's, whose
/// radio measures two of the three ranges, then node 3's, which measures none (it learns each
/// epoch from its teammates). Up to half the epoch grid (50 ms) every node names each epoch
/// alike and the offset only moves where the node's state is taken (v x offset along its
/// track); past it node 1 names every epoch by another instant than its teammates do.
pub fn clock_offset_cases() -> Vec<FaultCase> {
    let mut cases = vec![FaultCase { name: "fault-free", faults: Faults::default() }];
    for (node, names) in [(0, &CLOCK_NAMES[0]), (2, &CLOCK_NAMES[1])] {
        for (&name, ms) in names.iter().zip(CLOCK_OFFSETS_MS) {
            cases.push(FaultCase { name, faults: Faults { clock_offset: Some((node, ms)), ..Faults::default() } });
        }
    }
    cases
}

/// The clock sweep's case names (static, as every case's).
const CLOCK_NAMES: [[&str; 9]; 2] = [
    [
        "node 1's clock 1 ms ahead",
        "node 1's clock 2 ms ahead",
        "node 1's clock 5 ms ahead",
        "node 1's clock 10 ms ahead",
        "node 1's clock 20 ms ahead",
        "node 1's clock 30 ms ahead",
        "node 1's clock 45 ms ahead",
        "node 1's clock 55 ms ahead",
        "node 1's clock 100 ms ahead",
    ],
    [
        "node 3's clock 1 ms ahead",
        "node 3's clock 2 ms ahead",
        "node 3's clock 5 ms ahead",
        "node 3's clock 10 ms ahead",
        "node 3's clock 20 ms ahead",
        "node 3's clock 30 ms ahead",
        "node 3's clock 45 ms ahead",
        "node 3's clock 55 ms ahead",
        "node 3's clock 100 ms ahead",
    ],
];

/// The cases for a large team spread out ([`crate::sitl::scenario::Scenario::side_by_side`]) of
/// `n` members over `duration_s`: loss-free, 10% datagram loss, four members
/// (at a fifth, two, three and four fifths of the line) out of radio range for a fifth of the
/// run each, one after the other from a fifth of the run on, overlapping by half, without and
/// with the 10% loss. Link faults last until nine tenths of the run.
pub fn large_team_cases(n: usize, duration_s: f64) -> Vec<FaultCase> {
    let until = 0.9 * duration_s;
    let lossy = Faults { coop_loss: 0.10, links_until_s: until, ..Faults::default() };
    let out = duration_s / 5.0;
    let leave: Vec<Outage> = (1..=4)
        .map(|k| {
            let from_s = out + (k - 1) as f64 * out / 2.0;
            Outage { node: (k * n / 5).min(n - 1), from_s, until_s: from_s + out }
        })
        .collect();
    vec![
        FaultCase { name: "fault-free", faults: Faults::default() },
        FaultCase { name: "coop loss 10%", faults: lossy.clone() },
        FaultCase { name: "four members leave and come back", faults: Faults { leave: leave.clone(), ..Faults::default() } },
        FaultCase { name: "coop loss 10%, four members leave and come back", faults: Faults { leave, ..lossy } },
    ]
}

/// One node's outcome.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct NodeOutcome {
    pub id: PlatformId,
    /// Horizontal error at the end of the fault window (the end of the run when there is no
    /// window), m, and its 2-D NEES.
    pub fault_end_err_m: f64,
    pub fault_end_nees: f64,
    /// Horizontal error and 2-D NEES at the end of the run.
    pub final_err_m: f64,
    pub final_nees: f64,
    /// Square root of the trace of the final horizontal covariance, m.
    pub final_sigma_m: f64,
    /// Dead reckoning's final horizontal error on the same inputs, m.
    pub dr_final_err_m: f64,
    /// RMS of the horizontal error sampled every second of vehicle time while the node ran, m:
    /// the whole run's error, where the final one is a single draw.
    pub rms_err_m: f64,
    #[serde(skip)]
    pub stats: NodeStats,
    /// Cooperative datagrams the node's shell refused whole (no valid frame in them).
    pub coop_refused: u64,
}

/// One run of one case.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct RunOutcome {
    pub nodes: Vec<NodeOutcome>,
    /// Epochs after which the nodes that resolved them held different store digests.
    pub divergent_epochs: u32,
    /// The last such epoch.
    pub last_divergent_epoch: Option<u32>,
    /// The last epoch at or before the end of the faults (0: none).
    pub fault_end_epoch: u32,
    /// The team's joint horizontal NEES at the end (see `team_nees`).
    pub team_nees: f64,
    /// Disagreements the nodes detected themselves (reported disagreements plus store
    /// mismatches, summed over nodes).
    pub detections: u64,
}

struct Node {
    shell: Option<NodeShell>,
    /// What waits in the sockets while the node is frozen.
    backlog: Vec<Arrival>,
    /// Epoch -> store digest, recorded when the node resolves it.
    digests: BTreeMap<u32, u64>,
    last_seen: Option<u32>,
    /// The state it last saved (with `restore`).
    saved: Option<crate::node::saved::SavedState>,
}

impl Node {
    fn core(&self) -> Option<&NodeCore> {
        self.shell.as_ref().and_then(NodeShell::core)
    }
}

/// What reaches a node: a vehicle sample (decoded) or a cooperative datagram from node `from`.
enum Arrival {
    Input(NodeInput),
    Datagram { from: usize, bytes: Vec<u8> },
}

/// Node `k`'s cooperative address (what its teammates' shells learn it by).
fn address(k: usize) -> Source {
    Source::Unicast(std::net::SocketAddr::from(([127, 0, 0, 1], 7000 + k as u16)))
}

/// The team, its network and the fault schedule.
struct Sim<'a> {
    case: &'a Faults,
    ids: Vec<PlatformId>,
    nodes: Vec<Node>,
    rng: ChaCha8Rng,
    /// (deliver at, sequence, receiver): the datagram in `in_flight` under that sequence.
    net: BinaryHeap<Reverse<(u64, u64, usize)>>,
    in_flight: BTreeMap<u64, (usize, Vec<u8>)>,
    seq: u64,
}

impl Sim<'_> {
    fn links_active(&self, t: TimeUs) -> bool {
        t.as_secs_f64() < self.case.links_until_s
    }

    fn cut(&self, k: usize, t: TimeUs) -> bool {
        self.case.leave.iter().any(|o| o.covers(k, t))
    }

    fn stalled(&self, k: usize, t: TimeUs) -> bool {
        self.case.stall.is_some_and(|o| o.covers(k, t))
    }

    /// Puts what node `k`'s shell sent by `now` on the network, to every receiver: one frame
    /// per datagram, or packed as the link packs them ([`Faults::packed`]).
    fn send(&mut self, k: usize, now: TimeUs) {
        let outputs = self.nodes[k].shell.as_mut().map(NodeShell::take_outputs).unwrap_or_default();
        for output in outputs {
            let ShellOutput::Coop { frames, .. } = output else { continue };
            for datagram in self.datagrams(frames) {
                for j in (0..self.ids.len()).filter(|&j| j != k) {
                    self.transmit(k, j, &datagram, now);
                }
            }
        }
    }

    /// One datagram from `k` to `j`: lost, delayed or damaged while the link faults last.
    fn transmit(&mut self, k: usize, j: usize, datagram: &[u8], now: TimeUs) {
        if self.cut(k, now) || self.cut(j, now) {
            return;
        }
        let mut at = now.0;
        let mut bytes = datagram.to_vec();
        if self.links_active(now) {
            if self.case.coop_loss > 0.0 && self.rng.random::<f64>() < self.case.coop_loss {
                return;
            }
            let (lo, hi) = self.case.delay_ms;
            if hi > 0 {
                at += (self.rng.random_range(lo..=hi) as f64 * 1000.0 * self.case.speed) as u64;
            }
            if self.case.corrupt > 0.0 && self.rng.random::<f64>() < self.case.corrupt {
                damage(&mut bytes, &mut self.rng);
            }
        }
        self.seq += 1;
        self.in_flight.insert(self.seq, (k, bytes));
        self.net.push(Reverse((at, self.seq, j)));
    }

    /// The datagrams one batch of frames travels in (see [`Faults::packed`]; the shell already
    /// sends a record's first fragment alone): the link's own packing.
    fn datagrams(&self, frames: Vec<Vec<u8>>) -> Vec<Vec<u8>> {
        if self.case.packed { budget::pack(&frames, budget::MAX_DATAGRAM) } else { frames }
    }

    fn clock(&self, now: TimeUs) -> Now {
        clock(self.case, now)
    }

    /// Hands what arrived to node `k` at `now`: lost if it is dead, queued if it is frozen.
    fn deliver(&mut self, k: usize, arrival: Arrival, now: TimeUs) {
        if self.stalled(k, now) {
            if self.nodes[k].shell.is_some() {
                self.nodes[k].backlog.push(arrival);
            }
            return;
        }
        let clock = self.clock(now);
        let Some(shell) = self.nodes[k].shell.as_mut() else { return };
        match arrival {
            Arrival::Input(input) => shell.input(input, clock),
            Arrival::Datagram { from, bytes } => shell.coop_datagram(&bytes, address(from), clock),
        }
        self.send(k, now);
    }

    fn poll(&mut self, k: usize, now: TimeUs) {
        let clock = self.clock(now);
        if let Some(shell) = self.nodes[k].shell.as_mut() {
            shell.poll(clock);
            self.send(k, now);
        }
    }

    /// Delivers every datagram due by `now`.
    fn network(&mut self, now: TimeUs) {
        while let Some(Reverse((at, s, j))) = self.net.peek().copied() {
            if at > now.0 {
                break;
            }
            self.net.pop();
            if let Some((from, bytes)) = self.in_flight.remove(&s) {
                self.deliver(j, Arrival::Datagram { from, bytes }, TimeUs(at));
            }
        }
    }

    /// The end of the run: every node closes its last instant, what is in flight is delivered,
    /// and every node runs what is still open.
    fn finish(&mut self, end: TimeUs) {
        let clock = self.clock(end);
        for k in 0..self.ids.len() {
            if let Some(shell) = self.nodes[k].shell.as_mut() {
                shell.end_of_input(clock);
                self.send(k, end);
            }
        }
        self.network(TimeUs(u64::MAX));
        for node in self.nodes.iter_mut() {
            if let Some(shell) = node.shell.as_mut() {
                shell.run_pending(clock);
            }
            if let Some(core) = node.core()
                && let Some(e) = core.last_epoch()
            {
                let digest = core.store_digest();
                node.digests.insert(e, digest);
            }
        }
    }

    fn lose_vehicle_frame(&mut self, t: TimeUs) -> bool {
        self.links_active(t) && self.case.vehicle_loss > 0.0 && self.rng.random::<f64>() < self.case.vehicle_loss
    }
}

/// The nodes' clocks at vehicle time `now`: wall time (see [`Faults::speed`]) and a Unix time
/// that follows it.
fn clock(case: &Faults, now: TimeUs) -> Now {
    let wall_us = (now.0 as f64 / case.speed) as u64;
    Now { wall_us, unix_ns: 1_700_000_000_000_000_000 + wall_us as i64 * 1000 }
}

/// Damages a datagram as a radio or a bad cable would: one byte changed, or the end cut off.
fn damage(bytes: &mut Vec<u8>, rng: &mut ChaCha8Rng) {
    if bytes.is_empty() {
        return;
    }
    if rng.random::<bool>() {
        let i = rng.random_range(0..bytes.len());
        bytes[i] ^= rng.random_range(1..=255u8);
    } else {
        bytes.truncate(rng.random_range(0..bytes.len()));
    }
}

/// Horizontal error (truth minus estimate) and its 2-D NEES.
fn horizontal_error(world: &World, id: PlatformId, core: &NodeCore, clock_offset_us: u64) -> (f64, f64) {
    let f = core.filter();
    let truth = world.trajectory(id).expect("team member").truth_at(TimeUs(f.time().0.saturating_sub(clock_offset_us)));
    let e = truth.pos_ned_m - f.position_ned_m();
    let p = f.output_covariances().position();
    let cov = nalgebra::DMatrix::from_fn(2, 2, |r, c| p[(r, c)]);
    let nees = crate::estimation::consistency::nees(&nalgebra::DVector::from_column_slice(e.xy().as_slice()), &cov);
    (e.xy().norm(), nees.unwrap_or(f64::INFINITY))
}

/// The team's joint horizontal NEES at the end (`2 x members` degrees of freedom): the errors
/// stacked, against the joint covariance the decentralized filter implies, each node's own block
/// and the cross blocks `Psi_i C_ij Psi_j^T` of the store the nodes hold (the store of the most
/// nodes; they agree at the end of every case). Unlike the per-node NEES of one run, whose values
/// are strongly correlated (ranges leave the team's common position unobserved, so the nodes'
/// errors move together), this is one chi-square sample per run, so its run average has an exact
/// band. NaN for methods that keep no store.
fn team_nees(world: &World, ids: &[PlatformId], cores: &[&NodeCore], offsets_us: &[u64]) -> f64 {
    use crate::estimation::PlatformFilter;
    use nalgebra::{DMatrix, DVector};
    if cores.iter().any(|c| c.config().method != Method::Decentralized) {
        return f64::NAN;
    }
    let mut counts: BTreeMap<u64, usize> = BTreeMap::new();
    for c in cores {
        *counts.entry(c.store_digest()).or_default() += 1;
    }
    let common = counts.iter().max_by_key(|(d, n)| (**n, Reverse(**d))).map(|(d, _)| *d);
    let Some(store) = cores.iter().find(|c| Some(c.store_digest()) == common).map(|c| c.store()) else {
        return f64::NAN;
    };
    let snaps: Vec<_> = cores.iter().zip(ids).map(|(c, &id)| c.filter().snapshot(id)).collect();
    let pos =
        |k: usize| -> Option<[usize; 2]> { Some([snaps[k].geometry.position_index[0]?, snaps[k].geometry.position_index[1]?]) };
    let n = ids.len();
    let mut p = DMatrix::zeros(2 * n, 2 * n);
    let mut e = DVector::zeros(2 * n);
    for i in 0..n {
        let Some(pi) = pos(i) else { return f64::NAN };
        let f = cores[i].filter();
        let truth = world.trajectory(ids[i]).expect("team member").truth_at(TimeUs(f.time().0.saturating_sub(offsets_us[i])));
        let err = truth.pos_ned_m - f.position_ned_m();
        e[2 * i] = err.x;
        e[2 * i + 1] = err.y;
        for j in 0..n {
            let Some(pj) = pos(j) else { return f64::NAN };
            let block = if i == j {
                snaps[i].covariance.clone()
            } else {
                match store.get(ids[i], ids[j]) {
                    Some(c) => &snaps[i].psi * c * snaps[j].psi.transpose(),
                    None => continue,
                }
            };
            for (a, &ra) in pi.iter().enumerate() {
                for (b, &cb) in pj.iter().enumerate() {
                    p[(2 * i + a, 2 * j + b)] = block[(ra, cb)];
                }
            }
        }
    }
    crate::estimation::consistency::nees(&e, &p).unwrap_or(f64::INFINITY)
}

/// The origin of the harness's NED frame for saved states (any fixed one: the states are saved
/// and restored about it).
const HARNESS_ORIGIN: crate::geodesy::GeoOrigin = crate::geodesy::GeoOrigin { lat_deg: 0.0, lon_deg: 0.0, alt_m: 0.0 };

/// Makes the nodes of a run: a core from the run's initial estimate (or an independent fix at a
/// restart or a late join, or the state it saved), inside the shell a process would run.
struct Maker<'a> {
    world: &'a World,
    case: &'a Faults,
    method: Method,
    encoding: Encoding,
    seed: u64,
    run: u32,
    ids: Vec<PlatformId>,
}

impl Maker<'_> {
    fn shell(
        &self,
        id: PlatformId,
        at: Option<TimeUs>,
        saved: Option<&crate::node::saved::SavedState>,
    ) -> Result<NodeShell, ExperimentError> {
        let model = nav_model(self.world, id);
        let mut cfg = NodeConfig::for_model(id, self.method, model, self.encoding, self.ids.clone());
        cfg.authenticated_peers = !self.case.unsigned;
        // as `cooploc node` with a profile's range grid (the harness puts ranges on it too)
        cfg.range_snap_us = EPOCH_GRID_US;
        cfg.store_bps = self.case.store_bps;
        let restored = match (saved, at) {
            (Some(saved), Some(t)) => saved
                .restore_at(id, &model, &HARNESS_ORIGIN, t, &crate::estimation::coast::CoastBounds::LAND)
                .ok()
                .map(|(state, p)| (t, state, p)),
            _ => None,
        };
        let core = match restored {
            Some((t, state, p)) => NodeCore::restored(cfg, t, state, &p),
            None => {
                let init = match at {
                    None => self.world.initial_estimate(self.seed, self.run, id)?,
                    Some(t) => self.world.estimate_at(self.seed, self.run, id, t, 1)?,
                };
                let (t0, state) = state_from(init)?;
                // (a node whose clock is off names its start instant by its clock too)
                let k = self.ids.iter().position(|&p| p == id).unwrap_or(0);
                let t0 = TimeUs(t0.0 + self.case.clock_offset_us(k));
                NodeCore::new(cfg, t0, NavState::for_model(&model, state))
            }
        }
        .map_err(|e| ExperimentError::Settings(format!("node {id}: {e}")))?;
        // What the team sees of the autopilot is not measured here, so nothing goes back to it
        // (no ODOMETRY, GPS_INPUT or LOCAL_POSITION_NED).
        let mut profile = VehicleProfile::from_spec(&self.world.scenario().vehicle_of(id));
        profile.output.odometry_rate_hz = 0.0;
        profile.output.gps_input_rate_hz = 0.0;
        profile.output.local_position_ned = false;
        let config = ShellConfig::bare(profile);
        let mut shell = NodeShell::new(NodeInit::Ready(Box::new(core)), config, clock(self.case, at.unwrap_or(TimeUs(0))))
            .map_err(|e| ExperimentError::Settings(format!("node shell: {e}")))?;
        shell.take_outputs(); // its HEARTBEAT to the vehicle
        Ok(shell)
    }
}

/// Runs one case once (`seed`, `run`) with method `method` on `schedule`, the nodes'
/// records in `encoding`.
pub fn run_case(
    world: &World,
    case: &Faults,
    method: Method,
    schedule: &str,
    seed: u64,
    run: u32,
    encoding: Encoding,
) -> Result<RunOutcome, ExperimentError> {
    let ids = world.platform_ids();
    let maker = Maker { world, case, method, encoding, seed, run, ids: ids.clone() };
    let mut nodes = Vec::new();
    for (k, &id) in ids.iter().enumerate() {
        let late = case.join.is_some_and(|(n, _)| n == k);
        let shell = if late { None } else { Some(maker.shell(id, None, None)?) };
        nodes.push(Node { shell, backlog: Vec::new(), digests: BTreeMap::new(), last_seen: None, saved: None });
    }
    let epoch_times: Vec<TimeUs> = world.ranges(schedule, seed, run)?.into_iter().map(|(t, _)| t).collect();
    let dropped_imu = case.drop_imu_at_epoch.and_then(|(k, e)| Some((k, *epoch_times.get((e as usize).checked_sub(1)?)?)));
    let mut sim = Sim {
        case,
        ids: ids.clone(),
        nodes,
        rng: ChaCha8Rng::seed_from_u64(case.link_seed.unwrap_or(seed ^ (u64::from(run) << 32)) ^ 0x5eed_fa17),
        net: BinaryHeap::new(),
        in_flight: BTreeMap::new(),
        seq: 0,
    };
    let index = |id: PlatformId| ids.iter().position(|&p| p == id).expect("team member");
    let fault_end = TimeUs((case.end_s() * 1e6) as u64);
    let mut at_fault_end: Vec<Option<(f64, f64)>> = vec![None; ids.len()];
    // (sum of squared horizontal errors, samples) of each node, every second
    let mut sampled: Vec<(f64, u64)> = vec![(0.0, 0); ids.len()];
    let (mut epoch, mut last_poll, mut next_second, mut restarted) = (0u32, 0u64, 1u64, false);

    for event in world.events(schedule, seed, run)? {
        let now = event.time();
        sim.network(now);
        // Membership: kills, restarts, joins, wake-ups.
        for (k, &id) in ids.iter().enumerate() {
            if case.kill.is_some_and(|o| o.covers(k, now)) {
                sim.nodes[k].shell = None;
            }
            let restart = case.kill.is_some_and(|o| o.node == k && !restarted && now.as_secs_f64() >= o.until_s);
            let join = case.join.is_some_and(|(n, t)| n == k && sim.nodes[k].shell.is_none() && now.as_secs_f64() >= t);
            if restart || join {
                restarted |= restart;
                let saved = if restart && case.restore { sim.nodes[k].saved.as_ref() } else { None };
                sim.nodes[k].shell = Some(maker.shell(id, Some(now), saved)?);
                sim.nodes[k].last_seen = None;
            }
            if !sim.stalled(k, now) && !sim.nodes[k].backlog.is_empty() {
                // Awake: the timers fire first, then what waited in the sockets.
                sim.poll(k, now);
                for input in std::mem::take(&mut sim.nodes[k].backlog) {
                    sim.deliver(k, input, now);
                }
            }
        }
        if now.0 >= last_poll + 10_000 {
            last_poll = now.0;
            for k in 0..ids.len() {
                if !sim.stalled(k, now) {
                    sim.poll(k, now);
                }
            }
        }
        if now.0 >= next_second * 1_000_000 {
            next_second += 1;
            for (k, node) in sim.nodes.iter().enumerate() {
                if let Some(core) = node.core() {
                    let (err, _) = horizontal_error(world, ids[k], core, case.clock_offset_us(k));
                    sampled[k] = (sampled[k].0 + err * err, sampled[k].1 + 1);
                }
            }
            if case.restore {
                for node in sim.nodes.iter_mut() {
                    if let Some(core) = node.core() {
                        node.saved = Some(crate::node::saved::SavedState::of(core.id(), &HARNESS_ORIGIN, core.filter()));
                    }
                }
            }
            if fault_end.0 > 0 && now >= fault_end {
                for k in 0..ids.len() {
                    if at_fault_end[k].is_none()
                        && let Some(core) = sim.nodes[k].core()
                    {
                        at_fault_end[k] = Some(horizontal_error(world, ids[k], core, case.clock_offset_us(k)));
                    }
                }
            }
        }
        // A node whose clock is off stamps its vehicle's samples by it (`Faults::clock_offset`).
        let later = |k: usize, t: TimeUs| TimeUs(t.0 + case.clock_offset_us(k));
        match event {
            SimEvent::Imu(id, mut s) => {
                let k = index(id);
                if dropped_imu != Some((k, s.t)) && !sim.lose_vehicle_frame(s.t) {
                    s.t = later(k, s.t);
                    sim.deliver(k, Arrival::Input(NodeInput::Imu(s)), now);
                }
            }
            SimEvent::Odometer(id, mut s) => {
                let k = index(id);
                if !sim.lose_vehicle_frame(s.t) {
                    s.t = later(k, s.t);
                    sim.deliver(k, Arrival::Input(NodeInput::Odometer(s)), now);
                }
            }
            SimEvent::Wheel(id, mut s) => {
                let k = index(id);
                if dropped_imu != Some((k, s.t)) && !sim.lose_vehicle_frame(s.t) {
                    s.t = later(k, s.t);
                    sim.deliver(k, Arrival::Input(NodeInput::Wheel(s)), now);
                }
            }
            SimEvent::Ranges(t, samples) => {
                epoch += 1;
                for mut r in samples {
                    if !sim.lose_vehicle_frame(t) {
                        let k = index(r.from);
                        if case.clock_offset_us(k) > 0 {
                            r.t = crate::node::inputs::snap_to_grid(later(k, r.t), EPOCH_GRID_US).0;
                        }
                        sim.deliver(k, Arrival::Input(NodeInput::OwnRange { epoch, range: r }), now);
                    }
                }
            }
        }
        for node in sim.nodes.iter_mut() {
            if let Some(core) = node.core()
                && core.last_epoch() != node.last_seen
            {
                let (last, digest) = (core.last_epoch(), core.store_digest());
                node.last_seen = last;
                if let Some(e) = last {
                    node.digests.insert(e, digest);
                }
            }
        }
    }
    sim.finish(world.end());
    let at_end = AtFaultEnd { fault_end, epoch_times: &epoch_times, errors: &at_fault_end, sampled: &sampled };
    outcome(world, &sim, seed, run, &at_end)
}

/// When the faults ended and what each node's error was then.
struct AtFaultEnd<'a> {
    fault_end: TimeUs,
    epoch_times: &'a [TimeUs],
    errors: &'a [Option<(f64, f64)>],
    /// Each node's (sum of squared errors, samples), every second it ran.
    sampled: &'a [(f64, u64)],
}

/// What a finished run measured.
fn outcome(world: &World, sim: &Sim<'_>, seed: u64, run: u32, at: &AtFaultEnd<'_>) -> Result<RunOutcome, ExperimentError> {
    let ids = &sim.ids;
    let inputs = world.run_inputs(seed, run);
    let dr = run_filter(world, &inputs, &[], Method::DeadReckoning)?;
    let mut outcomes = Vec::new();
    let mut detections = 0;
    for (k, node) in sim.nodes.iter().enumerate() {
        let Some(core) = node.core() else {
            return Err(ExperimentError::Settings(format!("node {} never ran", ids[k])));
        };
        let (final_err_m, final_nees) = horizontal_error(world, ids[k], core, sim.case.clock_offset_us(k));
        let (fault_end_err_m, fault_end_nees) = at.errors[k].unwrap_or((final_err_m, final_nees));
        let p = core.filter().output_covariances().position();
        detections += core.stats.epoch_disagreements + core.stats.store_mismatches;
        outcomes.push(NodeOutcome {
            id: ids[k],
            fault_end_err_m,
            fault_end_nees,
            final_err_m,
            final_nees,
            final_sigma_m: (p[(0, 0)] + p[(1, 1)]).sqrt(),
            dr_final_err_m: dr.platforms[k].final_error().pos_err_m,
            rms_err_m: (at.sampled[k].0 / at.sampled[k].1.max(1) as f64).sqrt(),
            stats: core.stats.clone(),
            coop_refused: node.shell.as_ref().map_or(0, |sh| sh.summary(LinkFacts::default()).coop_rejected),
        });
    }
    // Disagreements seen from outside: epochs whose digests differ between the nodes that
    // resolved them.
    let mut all: BTreeMap<u32, Vec<u64>> = BTreeMap::new();
    for node in &sim.nodes {
        for (e, d) in &node.digests {
            all.entry(*e).or_default().push(*d);
        }
    }
    let divergent: Vec<u32> = all.iter().filter(|(_, d)| d.windows(2).any(|w| w[0] != w[1])).map(|(e, _)| *e).collect();
    let fault_end_epoch = at.epoch_times.iter().filter(|t| **t <= at.fault_end).count() as u32;
    let cores: Vec<&NodeCore> = sim.nodes.iter().filter_map(Node::core).collect();
    let offsets: Vec<u64> = (0..ids.len()).map(|k| sim.case.clock_offset_us(k)).collect();
    let team_nees = team_nees(world, ids, &cores, &offsets);
    Ok(RunOutcome {
        nodes: outcomes,
        divergent_epochs: divergent.len() as u32,
        last_divergent_epoch: divergent.last().copied(),
        fault_end_epoch,
        team_nees,
        detections,
    })
}

/// A case over many runs: what the table in docs/robustness.md shows and the tests check.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct CaseSummary {
    pub name: String,
    pub runs: usize,
    /// RMS over runs and nodes of the final horizontal error, m.
    pub final_rms_m: f64,
    /// RMS over runs and nodes of the horizontal error at the end of the faults, m.
    pub fault_end_rms_m: f64,
    /// RMS of dead reckoning's final error on the same inputs, m.
    pub dr_rms_m: f64,
    /// RMS over runs and nodes of each node's whole-run RMS error (sampled every second), m:
    /// what a small, steady cost shows in, where the final error is one draw.
    pub run_rms_m: f64,
    /// Average final 2-D NEES over runs and nodes, and the 95% band it would have if the nodes'
    /// errors were independent (they are not: see `team_nees`).
    pub avg_nees: f64,
    pub nees_band: (f64, f64),
    /// Average over runs of the team's joint NEES (`2 x nodes` degrees of freedom), and its 95%
    /// band for a consistent filter.
    pub team_nees: f64,
    pub team_nees_band: (f64, f64),
    /// Nodes (over all runs) that ended worse than dead reckoning by more than their own 3-sigma.
    pub worse_than_dr: usize,
    /// Runs in which the nodes' stores diverged at some epoch, and those among them in which the
    /// nodes detected it themselves.
    pub runs_diverged: usize,
    pub runs_detected: usize,
    /// Runs still diverged more than 3 epochs after the faults ended.
    pub runs_not_recovered: usize,
    /// Sums over runs and nodes: epochs a node was left out of (its store not valid for the
    /// participants) and stores it then adopted from them, heals with the bound, ...
    pub excluded: u64,
    pub stores_adopted: u64,
    /// Epochs a node that had been frozen ran as the others had run them without it.
    pub bystood: u64,
    pub heals: u64,
    pub partial: u64,
    pub applied: u64,
    pub failed: u64,
    pub gated: u64,
    /// Epochs refused as implausible (an id that does not fit its instant: clocks apart).
    pub implausible: u64,
}

/// Sums up runs of one case.
pub fn summarize(name: &str, runs: &[RunOutcome]) -> CaseSummary {
    let nodes: Vec<&NodeOutcome> = runs.iter().flat_map(|r| &r.nodes).collect();
    let rms =
        |f: &dyn Fn(&NodeOutcome) -> f64| (nodes.iter().map(|n| f(n).powi(2)).sum::<f64>() / nodes.len().max(1) as f64).sqrt();
    let sum = |f: &dyn Fn(&NodeStats) -> u64| nodes.iter().map(|n| f(&n.stats)).sum::<u64>();
    let diverged: Vec<&RunOutcome> = runs.iter().filter(|r| r.divergent_epochs > 0).collect();
    CaseSummary {
        name: name.to_string(),
        runs: runs.len(),
        final_rms_m: rms(&|n| n.final_err_m),
        fault_end_rms_m: rms(&|n| n.fault_end_err_m),
        dr_rms_m: rms(&|n| n.dr_final_err_m),
        run_rms_m: rms(&|n| n.rms_err_m),
        avg_nees: nodes.iter().map(|n| n.final_nees).sum::<f64>() / nodes.len().max(1) as f64,
        nees_band: crate::estimation::consistency::average_nees_band(2, nodes.len(), 0.95),
        team_nees: runs.iter().map(|r| r.team_nees).sum::<f64>() / runs.len().max(1) as f64,
        team_nees_band: crate::estimation::consistency::average_nees_band(
            2 * runs.first().map_or(0, |r| r.nodes.len()),
            runs.len(),
            0.95,
        ),
        worse_than_dr: nodes.iter().filter(|n| n.final_err_m > n.dr_final_err_m + 3.0 * n.final_sigma_m).count(),
        runs_diverged: diverged.len(),
        runs_detected: diverged.iter().filter(|r| r.detections > 0).count(),
        runs_not_recovered: runs.iter().filter(|r| r.last_divergent_epoch.is_some_and(|e| e > r.fault_end_epoch + 3)).count(),
        excluded: sum(&|s| s.epochs_excluded),
        stores_adopted: sum(&|s| s.stores_adopted),
        bystood: sum(&|s| s.epochs_bystood),
        heals: sum(&|s| s.heals),
        partial: sum(&|s| s.epochs_partial),
        applied: sum(&|s| s.epochs_applied),
        failed: sum(&|s| s.epochs_failed),
        gated: sum(&|s| s.ranges_gated),
        implausible: sum(&|s| s.epochs_implausible),
    }
}
