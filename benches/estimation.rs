//! Criterion benchmarks of the estimation core. Run: `cargo bench --bench estimation`.
//!
//! - `ins/imu_step_with_psi`, `ins/imu_step_without_psi`: one 200 Hz strapdown step of the
//!   16-state INS (mechanization, covariance and, first, the Psi update), driving a turn.
//! - `ins/imu_step_with_psi_covariance_every_4`: the same with the covariance and Psi stepped
//!   every 4th sample (50 Hz, as the paper scenario runs), amortised over the samples.
//! - `ins/odometer_update`: one odometer + non-holonomic update (3 rows), Psi included.
//! - `cooperative_event/N`: one joint range update of N 16-state platforms, each ranging to up
//!   to 6 neighbours (a ring: i ranges to i+1, i+2, i+3), cross blocks rebuilt from Psi and
//!   stored (the paper's method), starting from a store filled by a previous event.

use std::hint::black_box;

use cooploc::estimation::ins::{InsConfig, InsFilter, InsInitialSigma, InsState};
use cooploc::estimation::linear::LinearPlatform;
use cooploc::estimation::{CoopMeasurement, CrossCovariances, CrossMode, PlatformFilter, Snapshot, cooperative_update};
use cooploc::estimation::{ImuSample, OdometerSample};
use cooploc::time::TimeUs;
use criterion::{BatchSize, Criterion, criterion_group, criterion_main};
use nalgebra::{DMatrix, DVector, UnitQuaternion, Vector3};

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

fn ins_filter(track_psi: bool, covariance_decimation: u32) -> InsFilter {
    let config = InsConfig { latitude_deg: 34.7, covariance_decimation, ..InsConfig::default() };
    let sigma = InsInitialSigma {
        pos_ned_m: Vector3::repeat(0.1),
        vel_ned_m_s: Vector3::repeat(0.05),
        att_ned_rad: Vector3::new(2e-4, 2e-4, 1e-3),
        accel_bias_frd_m_s2: Vector3::repeat(5e-3),
        gyro_bias_frd_rad_s: Vector3::repeat(1.5e-5),
        odometer_scale: 1e-3,
    };
    let mut state = InsState::at_rest(UnitQuaternion::from_euler_angles(0.0, 0.0, 0.5));
    state.vel_ned_m_s = state.att_frd_to_ned * Vector3::new(10.0, 0.0, 0.0);
    let mut f = InsFilter::new(config, TimeUs(0), state, sigma).unwrap();
    f.set_track_psi(track_psi);
    f
}

fn imu_sample(k: u64) -> ImuSample {
    ImuSample {
        t: TimeUs(5_000 * k),
        specific_force_frd_m_s2: Vector3::new(0.01, 1.0, -9.80665),
        angular_rate_frd_rad_s: Vector3::new(1e-5, -2e-5, 0.1),
    }
}

fn ins(c: &mut Criterion) {
    let mut group = c.benchmark_group("ins");
    for (name, psi, decimation) in
        [("imu_step_with_psi", true, 1), ("imu_step_without_psi", false, 1), ("imu_step_with_psi_covariance_every_4", true, 4)]
    {
        let mut f = ins_filter(psi, decimation);
        let mut k = 0u64;
        group.bench_function(name, |b| {
            b.iter(|| {
                k += 1;
                f.propagate(black_box(&imu_sample(k))).unwrap();
            })
        });
    }
    let mut f = ins_filter(true, 1);
    for k in 1..=20 {
        f.propagate(&imu_sample(k)).unwrap();
    }
    let odo = OdometerSample { t: f.time(), speed_m_s: 10.05 };
    group.bench_function("odometer_update", |b| {
        b.iter_batched(|| f, |mut f| black_box(f.update_odometer(black_box(&odo)).unwrap()), BatchSize::SmallInput)
    });
    group.finish();
}

fn cooperative_event(c: &mut Criterion) {
    let mut group = c.benchmark_group("cooperative_event");
    group.sample_size(20);
    for n in [3usize, 8, 16, 32, 64] {
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

criterion_group!(benches, ins, cooperative_event);
criterion_main!(benches);
