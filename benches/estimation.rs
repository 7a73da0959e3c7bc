//! Criterion benchmarks of the estimation core. Run: `cargo bench --bench estimation`.
//!
//! - `cooperative_event/N`: one joint range update of N 16-state platforms, each ranging to up
//!   to 6 neighbours (a ring: i ranges to i+1, i+2, i+3), cross blocks rebuilt from Psi and
//!   stored (the paper's method), starting from a store filled by a previous event.

use std::hint::black_box;

use cooploc::estimation::linear::LinearPlatform;
use cooploc::estimation::{CoopMeasurement, CrossCovariances, CrossMode, PlatformFilter, Snapshot, cooperative_update};
use criterion::{BatchSize, Criterion, criterion_group, criterion_main};
use nalgebra::{DMatrix, DVector};

const DIM: usize = 16;

fn team_snapshots(n: usize) -> Vec<Snapshot> {
    (0..n)
        .map(|i| {
            let angle = i as f64 / n as f64 * std::f64::consts::TAU;
            let mut x0 = DVector::zeros(DIM);
            x0[0] = 200.0 * angle.cos();
            x0[1] = 200.0 * angle.sin();
            let a = DMatrix::from_fn(DIM, DIM, |r, c| ((r * 7 + c * 3 + i) % 11) as f64 * 0.01);
            let p0 = &a * a.transpose() + DMatrix::identity(DIM, DIM);
            let mut s = LinearPlatform::new(x0, p0, [Some(0), Some(1), Some(2)]).unwrap().snapshot(i as u16);
            s.psi += DMatrix::from_fn(DIM, DIM, |r, c| if r < c { 0.01 } else { 0.0 });
            s
        })
        .collect()
}

fn ring_ranges(n: usize) -> Vec<CoopMeasurement> {
    let mut out = Vec::new();
    for i in 0..n {
        for k in 1..=3.min(n - 1) {
            let j = (i + k) % n;
            if n <= 3 && j < i {
                continue; // with 3 platforms the ring repeats pairs
            }
            out.push(CoopMeasurement::Range { from: i as u16, to: j as u16, range_m: 50.0, sigma_m: 0.1 });
        }
    }
    out
}

fn cooperative_event(c: &mut Criterion) {
    let mut group = c.benchmark_group("cooperative_event");
    group.sample_size(20);
    for n in [3usize, 16, 64] {
        let snapshots = team_snapshots(n);
        let ranges = ring_ranges(n);
        let mut store = CrossCovariances::new();
        cooperative_update(&mut store, &snapshots, &ranges, CrossMode::Propagate).unwrap();
        group.bench_function(format!("{n}"), |b| {
            b.iter_batched(
                || store.clone(),
                |mut s| black_box(cooperative_update(&mut s, black_box(&snapshots), &ranges, CrossMode::Propagate).unwrap()),
                BatchSize::LargeInput,
            )
        });
    }
    group.finish();
}

criterion_group!(benches, cooperative_event);
criterion_main!(benches);
