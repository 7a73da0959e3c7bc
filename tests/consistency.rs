//! Seeded Monte Carlo consistency of the cooperative methods on a team of planar unicycle robots.
//!
//! Four robots drive noisy-odometry paths; robot 0 gets an absolute position fix every 10 s,
//! robot 1 a compass heading every 2 s (local measurements, so that the centralized EKF and the
//! decentralized filter differ), and all pairs range every second. The truth integrates the
//! true inputs with the filters' own discrete model, so every method's only approximation is
//! its own linearisation. The NEES of the joint state (dimension 12), as each method believes
//! its joint covariance to be, is averaged over runs at each ranging epoch:
//! - decentralized and centralized must sit inside the 95% chi-square band of that average,
//!   in each third of the run;
//! - no-propagation must be over-confident (above the band) once events have repeated.

use cooploc::estimation::consistency::{average_nees_band, nees};
use cooploc::estimation::kalman::LinearizedMeasurement;
use cooploc::estimation::unicycle::{UnicycleFilter, UnicycleNoise, wrap_angle};
use cooploc::estimation::{CoopMeasurement, Method, PlatformFilter, Team};
use nalgebra::{DMatrix, DVector, Matrix3, Vector3};
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use rand_distr::{Distribution, Normal};

const ROBOTS: usize = 4;
const DT: f64 = 0.1;
const STEPS: usize = 1200; // 120 s
const RUNS: usize = 100;
const NOISE: UnicycleNoise = UnicycleNoise { sigma_speed_m_s: 0.05, sigma_yaw_rate_rad_s: 0.01 };

fn true_inputs(i: usize, t: f64) -> (f64, f64) {
    let phase = i as f64;
    (1.0 + 0.3 * (0.05 * t + phase).sin(), 0.1 * (0.07 * t + 2.0 * phase).sin())
}

fn step(x: &Vector3<f64>, v: f64, w: f64) -> Vector3<f64> {
    let (s, c) = x[2].sin_cos();
    Vector3::new(x[0] + v * c * DT, x[1] + v * s * DT, wrap_angle(x[2] + w * DT))
}

/// The joint covariance each method believes: own blocks, plus rebuilt cross blocks when the
/// method keeps them.
fn believed_joint_covariance(team: &Team<UnicycleFilter>) -> DMatrix<f64> {
    let mut p = DMatrix::zeros(3 * ROBOTS, 3 * ROBOTS);
    for i in 0..ROBOTS {
        let fi = team.filter(i as u16).unwrap();
        p.view_mut((3 * i, 3 * i), (3, 3)).copy_from(&fi.covariance());
        for j in (i + 1)..ROBOTS {
            if let Some(c) = team.cross().get(i as u16, j as u16) {
                let fj = team.filter(j as u16).unwrap();
                let pij = fi.psi() * c * fj.psi().transpose();
                p.view_mut((3 * i, 3 * j), (3, 3)).copy_from(&pij);
                p.view_mut((3 * j, 3 * i), (3, 3)).copy_from(&pij.transpose());
            }
        }
    }
    p
}

/// NEES at every ranging epoch of one run.
fn run(method: Method, seed: u64) -> Vec<f64> {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let std = Normal::new(0.0, 1.0).unwrap();
    let p0 = Matrix3::from_diagonal(&Vector3::new(0.25, 0.25, 0.0025));
    let mut truth: Vec<Vector3<f64>> =
        (0..ROBOTS).map(|i| Vector3::new(15.0 * (i % 2) as f64, 15.0 * (i / 2) as f64, 0.5 * i as f64)).collect();
    let members = truth
        .iter()
        .enumerate()
        .map(|(i, x)| {
            let x0 = x + Vector3::new(0.5 * std.sample(&mut rng), 0.5 * std.sample(&mut rng), 0.05 * std.sample(&mut rng));
            (i as u16, UnicycleFilter::new(x0, p0, 0.0, NOISE).unwrap())
        })
        .collect();
    let mut team = Team::new(method, members).unwrap();
    let mut out = Vec::new();
    for k in 1..=STEPS {
        let t = k as f64 * DT;
        for (i, x) in truth.iter_mut().enumerate() {
            let (v, w) = true_inputs(i, t);
            *x = step(x, v, w);
            let vm = v + NOISE.sigma_speed_m_s * std.sample(&mut rng);
            let wm = w + NOISE.sigma_yaw_rate_rad_s * std.sample(&mut rng);
            team.filter_mut(i as u16).unwrap().propagate(vm, wm, DT).unwrap();
        }
        if k % 100 == 0 {
            let f = team.filter(0).unwrap();
            let z = truth[0].fixed_rows::<2>(0)
                + Vector3::new(0.5 * std.sample(&mut rng), 0.5 * std.sample(&mut rng), 0.0).fixed_rows::<2>(0);
            let meas = LinearizedMeasurement {
                h: DMatrix::from_row_slice(2, 3, &[1.0, 0.0, 0.0, 0.0, 1.0, 0.0]),
                residual: DVector::from_column_slice((z - f.state().fixed_rows::<2>(0)).as_slice()),
                r: DMatrix::identity(2, 2) * 0.25,
            };
            team.local_update(0, &meas).unwrap();
        }
        if k % 20 == 0 {
            let f = team.filter(1).unwrap();
            let z = truth[1][2] + 0.02 * std.sample(&mut rng);
            let meas = LinearizedMeasurement {
                h: DMatrix::from_row_slice(1, 3, &[0.0, 0.0, 1.0]),
                residual: DVector::from_element(1, wrap_angle(z - f.state()[2])),
                r: DMatrix::from_element(1, 1, 0.02f64.powi(2)),
            };
            team.local_update(1, &meas).unwrap();
        }
        if k % 10 == 0 {
            let mut ranges = Vec::new();
            for a in 0..ROBOTS {
                for b in (a + 1)..ROBOTS {
                    let d = (truth[a].fixed_rows::<2>(0) - truth[b].fixed_rows::<2>(0)).norm();
                    ranges.push(CoopMeasurement::PlanarRange {
                        from: a as u16,
                        to: b as u16,
                        range_m: d + 0.1 * std.sample(&mut rng),
                        sigma_m: 0.1,
                    });
                }
            }
            team.cooperative_event(&ranges).unwrap();
            let mut e = DVector::zeros(3 * ROBOTS);
            for (i, x) in truth.iter().enumerate() {
                let est = team.filter(i as u16).unwrap().state();
                let d = x - est;
                e.fixed_rows_mut::<3>(3 * i).copy_from(&Vector3::new(d[0], d[1], wrap_angle(d[2])));
            }
            out.push(nees(&e, &believed_joint_covariance(&team)).unwrap());
        }
    }
    out
}

/// Run-averaged NEES at each epoch.
fn average_nees(method: Method) -> Vec<f64> {
    let mut sum = vec![0.0; STEPS / 10];
    for r in 0..RUNS {
        for (s, v) in sum.iter_mut().zip(run(method, 1000 + r as u64)) {
            *s += v;
        }
    }
    sum.into_iter().map(|s| s / RUNS as f64).collect()
}

fn thirds(v: &[f64]) -> [f64; 3] {
    let n = v.len() / 3;
    [0, 1, 2].map(|k| v[k * n..(k + 1) * n].iter().sum::<f64>() / n as f64)
}

#[test]
fn decentralized_and_centralized_are_consistent_no_propagation_is_overconfident() {
    let (lo, hi) = average_nees_band(3 * ROBOTS, RUNS, 0.95);
    let dcl = thirds(&average_nees(Method::Decentralized));
    let cen = thirds(&average_nees(Method::Centralized));
    let naive = thirds(&average_nees(Method::NoPropagation));
    eprintln!("95% band of the run-averaged NEES (dim {}): [{lo:.2}, {hi:.2}]", 3 * ROBOTS);
    eprintln!("decentralized, by thirds of the run: {dcl:.2?}");
    eprintln!("centralized:                         {cen:.2?}");
    eprintln!("no-propagation:                      {naive:.2?}");
    for (name, avg) in [("decentralized", dcl), ("centralized", cen)] {
        for v in avg {
            assert!(v > lo && v < hi, "{name} average NEES {v:.2} outside [{lo:.2}, {hi:.2}]");
        }
    }
    assert!(naive[1] > hi && naive[2] > hi, "no-propagation should be over-confident: {naive:.2?} vs upper bound {hi:.2}");
}
