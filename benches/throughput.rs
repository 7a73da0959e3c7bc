//! Criterion benchmarks of what users wait for. Run: `cargo bench --bench throughput`.
//!
//! - `experiment/paper_run`: one Monte Carlo run of the paper scenario (`sitl/scenarios/paper.toml`,
//!   380 s, three vehicles): its inputs drawn, then every method under both ranging schedules, as
//!   `cooploc experiment` runs each of its runs (no files, no plots). The 50-run command is about
//!   25 of these per core.
//! - `replay/nodes_30s`: `cooploc replay`'s work on the committed 30 s demo log
//!   (`logs/demo-dcl-30s.mcap`): read and decode the log, rerun every node's core on its
//!   recorded inputs. Real time divided by this is the replay speed.

use std::hint::black_box;
use std::path::Path;

use cooploc::estimation::Method;
use cooploc::experiment::{ExperimentSpec, InputSource, run_once};
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

criterion_group!(benches, experiment, replay);
criterion_main!(benches);
