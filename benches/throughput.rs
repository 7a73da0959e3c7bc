//! Criterion benchmarks of what users wait for. Run: `cargo bench --bench throughput`.
//!
//! - `experiment/paper_run`: one Monte Carlo run of the paper scenario (`sitl/scenarios/paper.toml`,
//!   380 s, three vehicles): its inputs drawn, then every method under both ranging schedules, as
//!   `cooploc experiment` runs each of its runs (no files, no plots). The 50-run command is about
//!   25 of these per core.
//! - `replay/nodes_30s`: `cooploc replay`'s work on the committed 30 s demo log
//!   (`logs/demo-dcl-30s.mcap`): read and decode the log, rerun every node's core on its
//!   recorded inputs. Real time divided by this is the replay speed.
//! - `team/N`: a team of N node cores (the node's whole protocol: fragments, reassembly,
//!   store digests, the joint update every node computes, the INS at 200 Hz) run in-process by
//!   [`cooploc::experiment::faults::run_case`] with no faults, for 4 s of vehicle time with
//!   ranging at 1 Hz. N vehicles 100 m apart in a line, radios reaching 310 m: each ranges to
//!   up to 6 neighbours. Divided by `4 N`, the median is one node's CPU time per second at real
//!   time: its share of a core.

use std::hint::black_box;
use std::path::Path;

use cooploc::estimation::Method;
use cooploc::experiment::faults::{Faults, run_case};
use cooploc::experiment::{ExperimentSpec, InputSource, run_once};
use cooploc::protocol::record::Encoding;
use cooploc::recording::read_log;
use cooploc::replay::replay_nodes;
use cooploc::sitl::scenario::Scenario;
use cooploc::sitl::world::World;
use criterion::{Criterion, criterion_group, criterion_main};

fn root() -> &'static Path {
    Path::new(env!("CARGO_MANIFEST_DIR"))
}

fn experiment(c: &mut Criterion) {
    let scenario = Scenario::from_path(root().join("sitl/scenarios/paper.toml")).expect("paper scenario");
    let world = World::new(&scenario).expect("world");
    let spec = ExperimentSpec {
        runs: 1,
        seed: 1,
        methods: Method::ALL.to_vec(),
        schedules: scenario.ranging.schedules.iter().map(|s| s.name.clone()).collect(),
        source: InputSource::World,
    };
    let mut group = c.benchmark_group("experiment");
    group.sample_size(10);
    group.bench_function("paper_run", |b| b.iter(|| black_box(run_once(&world, &spec, 0).expect("run"))));
    group.finish();
}

fn replay(c: &mut Criterion) {
    let path = root().join("logs/demo-dcl-30s.mcap");
    let mut group = c.benchmark_group("replay");
    group.sample_size(10);
    group.bench_function("nodes_30s", |b| {
        b.iter(|| {
            let log = read_log(&path).expect("committed log");
            let replays = replay_nodes(&log).expect("replay");
            assert!(replays.iter().all(|r| r.matches()), "replay differs from the log");
            black_box(replays)
        })
    });
    group.finish();
}

/// The paper scenario's sensors with `n` vehicles driving north side by side, 100 m apart, for
/// `duration_s`, radios reaching 310 m (three neighbours on each side).
pub fn line_team(n: usize, duration_s: f64) -> Scenario {
    let paper = Scenario::from_path(root().join("sitl/scenarios/paper.toml")).expect("paper scenario");
    paper.side_by_side(n, 100.0, 310.0, duration_s)
}

fn team(c: &mut Criterion) {
    let mut group = c.benchmark_group("team");
    group.sample_size(10);
    for n in [3usize, 8, 16, 32, 64] {
        let world = World::new(&line_team(n, 4.0)).expect("world");
        group.bench_function(format!("{n}"), |b| {
            b.iter(|| {
                let out = run_case(&world, &Faults::default(), Method::Decentralized, "1hz", 1, 0, Encoding::F64).expect("run");
                assert_eq!(out.divergent_epochs, 0, "the team disagreed");
                assert!(out.nodes.iter().all(|n| n.stats.epochs_applied >= 3), "a node missed epochs");
                black_box(out)
            })
        });
    }
    group.finish();
}

criterion_group!(benches, experiment, replay, team);
criterion_main!(benches);
