//! The decentralized filter against brute force, on random linear-Gaussian teams.
//!
//! Reference: one joint filter over the stacked states of all platforms in which a local
//! measurement (random, or a GNSS fix of its position) corrects its own platform only (gain nonzero in that platform's rows), a
//! cooperative event corrects the platforms that broadcast and the bystanders (gain nonzero in
//! their rows; a bystander takes its share without broadcasting, see
//! `cooploc::estimation::BystanderShare`), and every covariance update is the textbook Joseph form on the whole stacked covariance. The
//! decentralized filter never forms that matrix: each platform keeps `P_ii` and `Psi_i`, the
//! team keeps the cross blocks of the last event, and Eq. 10 rebuilds the rest. Why the two are
//! equal is explained in `crates/cooploc-estimation/src/estimation/coop.rs`.

use cooploc::estimation::PositionFixSample;
use cooploc::estimation::fix::{FixOutcome, position_fix_measurement, update_position_fix};
use cooploc::estimation::linear::LinearPlatform;
use cooploc::estimation::{
    CoopMeasurement, CrossCovariances, CrossMode, PlatformFilter, UpdateOptions, cooperative_update, cooperative_update_with,
};
use cooploc::time::TimeUs;
use nalgebra::{DMatrix, DVector, Vector3};
use proptest::prelude::*;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

fn random_matrix(rng: &mut ChaCha8Rng, r: usize, c: usize, scale: f64) -> DMatrix<f64> {
    DMatrix::from_fn(r, c, |_, _| rng.random_range(-1.0..1.0) * scale)
}

/// A random symmetric positive-definite matrix with eigenvalues roughly in [floor, floor + scale].
fn random_spd(rng: &mut ChaCha8Rng, n: usize, scale: f64, floor: f64) -> DMatrix<f64> {
    let a = random_matrix(rng, n, n, 1.0);
    (&a * a.transpose()) * (scale / n as f64) + DMatrix::identity(n, n) * floor
}

/// Brute-force joint filter over stacked states.
struct Joint {
    x: DVector<f64>,
    p: DMatrix<f64>,
    offsets: Vec<(usize, usize)>,
}

impl Joint {
    fn block(&self, i: usize, j: usize) -> DMatrix<f64> {
        let ((oi, ni), (oj, nj)) = (self.offsets[i], self.offsets[j]);
        self.p.view((oi, oj), (ni, nj)).into_owned()
    }

    fn propagate(&mut self, i: usize, phi: &DMatrix<f64>, q: &DMatrix<f64>) {
        let n = self.x.len();
        let (o, d) = self.offsets[i];
        let mut big_phi = DMatrix::identity(n, n);
        big_phi.view_mut((o, o), (d, d)).copy_from(phi);
        let mut big_q = DMatrix::zeros(n, n);
        big_q.view_mut((o, o), (d, d)).copy_from(q);
        self.x = &big_phi * &self.x;
        self.p = &big_phi * &self.p * big_phi.transpose() + big_q;
    }

    /// Update with a stacked `h` (m x n), restricting the gain to the rows of `active` platforms.
    fn update(&mut self, h: &DMatrix<f64>, z: &DVector<f64>, r: &DMatrix<f64>, active: &[usize]) {
        let n = self.x.len();
        let s = h * &self.p * h.transpose() + r;
        let s_inv = s.try_inverse().expect("S invertible");
        let mut k = &self.p * h.transpose() * s_inv;
        for (i, &(o, d)) in self.offsets.iter().enumerate() {
            if !active.contains(&i) {
                k.rows_mut(o, d).fill(0.0);
            }
        }
        let a = DMatrix::identity(n, n) - &k * h;
        self.x += &k * (z - h * &self.x);
        self.p = &a * &self.p * a.transpose() + &k * r * k.transpose();
    }
}

fn rel_close(a: &DMatrix<f64>, b: &DMatrix<f64>, tol: f64) -> bool {
    let scale = b.amax().max(1.0);
    (a - b).amax() <= tol * scale
}

/// A random team's run; at each cooperative event every platform that does not broadcast is
/// a bystander with probability `bystander_p` (0: none, the others are left out).
fn run_random_team(seed: u64, platforms: usize, ops: usize, bystander_p: f64) -> Result<(), TestCaseError> {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let dims: Vec<usize> = (0..platforms).map(|_| rng.random_range(2..=5)).collect();
    let mut offsets = Vec::new();
    let mut total = 0;
    for &d in &dims {
        offsets.push((total, d));
        total += d;
    }
    let mut team: Vec<LinearPlatform> = Vec::new();
    let mut joint = Joint { x: DVector::zeros(total), p: DMatrix::zeros(total, total), offsets: offsets.clone() };
    for (i, &d) in dims.iter().enumerate() {
        let x0 = DVector::from_fn(d, |_, _| rng.random_range(-5.0..5.0));
        let p0 = random_spd(&mut rng, d, 2.0, 0.1);
        let (o, _) = offsets[i];
        joint.x.rows_mut(o, d).copy_from(&x0);
        joint.p.view_mut((o, o), (d, d)).copy_from(&p0);
        team.push(LinearPlatform::new(x0, p0, [Some(0), Some(1), None]).unwrap());
    }
    let mut cross = CrossCovariances::new();

    for _ in 0..ops {
        match rng.random_range(0..10) {
            // Time update of one platform.
            0..=3 => {
                let i = rng.random_range(0..platforms);
                let d = dims[i];
                let phi = DMatrix::identity(d, d) + random_matrix(&mut rng, d, d, 0.15);
                let q = random_spd(&mut rng, d, 0.05, 0.0);
                team[i].propagate(&phi, &q).unwrap();
                joint.propagate(i, &phi, &q);
            }
            // A GNSS fix of one platform (its position rows, gated): a local update like any other.
            4 => {
                let i = rng.random_range(0..platforms);
                let fix = PositionFixSample {
                    t: TimeUs(0),
                    pos_ned_m: Vector3::new(rng.random_range(-5.0..5.0), rng.random_range(-5.0..5.0), 0.0),
                    sigma_h_m: rng.random_range(0.3..3.0),
                    sigma_v_m: None,
                };
                let meas = position_fix_measurement(&team[i], &fix).unwrap();
                if let FixOutcome::Applied { .. } = update_position_fix(&mut team[i], &fix).unwrap() {
                    let (o, d) = offsets[i];
                    let mut big_h = DMatrix::zeros(2, total);
                    big_h.view_mut((0, o), (2, d)).copy_from(&meas.h);
                    joint.update(&big_h, &DVector::from_column_slice(&fix.pos_ned_m.as_slice()[..2]), &meas.r, &[i]);
                }
            }
            // Local measurement of one platform.
            5..=6 => {
                let i = rng.random_range(0..platforms);
                let m = rng.random_range(1..=2);
                let h = random_matrix(&mut rng, m, dims[i], 1.0);
                let r = random_spd(&mut rng, m, 0.5, 0.05);
                let z = DVector::from_fn(m, |_, _| rng.random_range(-3.0..3.0));
                let meas = team[i].linearize(&h, &z, &r).unwrap();
                team[i].update_local(&meas).unwrap();
                let (o, d) = offsets[i];
                let mut big_h = DMatrix::zeros(m, total);
                big_h.view_mut((0, o), (m, d)).copy_from(&h);
                joint.update(&big_h, &z, &r, &[i]);
            }
            // Cooperative event among a random subset of at least two broadcasters.
            _ => {
                let mut participants: Vec<usize> = (0..platforms).filter(|_| rng.random_bool(0.75)).collect();
                if participants.len() < 2 {
                    participants = vec![0, platforms - 1];
                }
                let snapshots: Vec<_> = participants.iter().map(|&i| team[i].snapshot(i as u16)).collect();
                let mut measurements = Vec::new();
                let mut rows: Vec<(DMatrix<f64>, DVector<f64>, DMatrix<f64>)> = Vec::new();
                for _ in 0..rng.random_range(1..=3) {
                    let m = rng.random_range(1..=2);
                    let k = rng.random_range(1..=participants.len().min(3));
                    let mut involved = participants.clone();
                    while involved.len() > k {
                        involved.remove(rng.random_range(0..involved.len()));
                    }
                    let z = DVector::from_fn(m, |_, _| rng.random_range(-3.0..3.0));
                    let r = random_spd(&mut rng, m, 0.5, 0.05);
                    let mut big_h = DMatrix::zeros(m, total);
                    let mut blocks = Vec::new();
                    let mut predicted = DVector::zeros(m);
                    for &i in &involved {
                        let h = random_matrix(&mut rng, m, dims[i], 1.0);
                        predicted += &h * team[i].state();
                        let (o, d) = offsets[i];
                        big_h.view_mut((0, o), (m, d)).copy_from(&h);
                        blocks.push((i as u16, h));
                    }
                    measurements.push(CoopMeasurement::Linear { blocks, residual: &z - predicted, r: r.clone() });
                    rows.push((big_h, z, r));
                }
                let bystanders: Vec<usize> = if bystander_p > 0.0 {
                    (0..platforms).filter(|i| !participants.contains(i) && rng.random_bool(bystander_p)).collect()
                } else {
                    Vec::new()
                };
                let opts = UpdateOptions {
                    bystanders: bystanders.iter().map(|&i| i as u16).collect(),
                    ..UpdateOptions::new(CrossMode::Propagate)
                };
                let outcome = cooperative_update_with(&mut cross, &snapshots, &measurements, &opts).unwrap();
                for c in &outcome.corrections {
                    team[c.id as usize].apply_joint(&c.dx, &c.p).unwrap();
                }
                // Each bystander the store knows takes its share; one it does not know is
                // uncorrelated with every broadcaster, and its gain in the reference is zero.
                for b in &outcome.bystanders {
                    prop_assert!(bystanders.contains(&(b.id as usize)), "a share for {} that is no bystander", b.id);
                    team[b.id as usize].apply_bystander(&b.a, &b.b).unwrap();
                }
                // The reference processes the stacked measurement in one update.
                let m_total: usize = rows.iter().map(|(_, z, _)| z.len()).sum();
                let mut h = DMatrix::zeros(m_total, total);
                let mut z = DVector::zeros(m_total);
                let mut r = DMatrix::zeros(m_total, m_total);
                let mut row = 0;
                for (hh, zz, rr) in &rows {
                    let k = zz.len();
                    h.rows_mut(row, k).copy_from(hh);
                    z.rows_mut(row, k).copy_from(zz);
                    r.view_mut((row, row), (k, k)).copy_from(rr);
                    row += k;
                }
                let active: Vec<usize> = participants.iter().chain(&bystanders).copied().collect();
                joint.update(&h, &z, &r, &active);
            }
        }
        // Every block agrees, diagonal and (through Eq. 10) off-diagonal.
        for i in 0..platforms {
            let (o, d) = offsets[i];
            let xi = DMatrix::from_column_slice(d, 1, team[i].state().as_slice());
            let xr = joint.x.rows(o, d).into_owned();
            prop_assert!(rel_close(&xi, &DMatrix::from_column_slice(d, 1, xr.as_slice()), 1e-9), "state {i}: {xi} vs {xr}");
            let pi = team[i].covariance();
            prop_assert!(rel_close(&pi, &joint.block(i, i), 1e-9), "P_{i}{i}");
            prop_assert!((&pi - pi.transpose()).amax() == 0.0, "P_{i}{i} symmetric");
            for j in (i + 1)..platforms {
                let rebuilt = match cross.get(i as u16, j as u16) {
                    Some(c) => team[i].psi() * c * team[j].psi().transpose(),
                    None => DMatrix::zeros(dims[i], dims[j]),
                };
                prop_assert!(rel_close(&rebuilt, &joint.block(i, j), 1e-9), "P_{i}{j} via Eq. 10");
            }
        }
        let sym = (&joint.p + joint.p.transpose()) * 0.5;
        let min_eig = sym.symmetric_eigen().eigenvalues.min();
        prop_assert!(min_eig > -1e-9 * joint.p.amax(), "joint covariance PSD, min eigenvalue {min_eig}");
    }
    Ok(())
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(256))]

    #[test]
    fn decentralized_equals_joint_filter_with_own_platform_local_updates(
        seed in any::<u64>(),
        platforms in 2usize..=6,
        ops in 1usize..60,
    ) {
        run_random_team(seed, platforms, ops, 0.0)?;
    }

    /// Epochs that involve only the platforms that ranged: the others take their share as
    /// bystanders (all of them, or some, the rest left out), and the team still ends where the
    /// joint filter does, to 1e-9. With every non-broadcaster a bystander, that is the joint
    /// filter over every platform, as if all had broadcast.
    #[test]
    fn subset_epochs_with_bystanders_equal_the_joint_filter_over_every_platform(
        seed in any::<u64>(),
        platforms in 3usize..=7,
        ops in 1usize..60,
        all in any::<bool>(),
    ) {
        run_random_team(seed, platforms, ops, if all { 1.0 } else { 0.5 })?;
    }
}

/// Eq. 10 on its own: the cross block of two platforms after `n` steps of their own
/// propagation and local updates is `xi_A(k+n) .. xi_A(k+1) P_AB(k) (xi_B(k+n) .. xi_B(k+1))^T`,
/// checked against the stacked system propagated by brute force.
#[test]
fn eq10_cross_block_matches_stacked_propagation() {
    let mut rng = ChaCha8Rng::seed_from_u64(10);
    let (na, nb) = (4, 3);
    let n = na + nb;
    let mut p = random_spd(&mut rng, n, 3.0, 0.2); // correlated at time k
    let p_ab_k = p.view((0, na), (na, nb)).into_owned();
    let mut xi_a = DMatrix::<f64>::identity(na, na);
    let mut xi_b = DMatrix::<f64>::identity(nb, nb);
    for _ in 0..25 {
        // Each platform: xi = (I - K H) Phi, with its own K from its own block.
        let mut big_xi = DMatrix::zeros(n, n);
        let mut big_noise = DMatrix::zeros(n, n);
        for (o, d, acc) in [(0, na, &mut xi_a), (na, nb, &mut xi_b)] {
            let phi = DMatrix::identity(d, d) + random_matrix(&mut rng, d, d, 0.2);
            let q = random_spd(&mut rng, d, 0.1, 0.0);
            let h = random_matrix(&mut rng, 1, d, 1.0);
            let r = DMatrix::from_element(1, 1, 0.3);
            let pp = &phi * p.view((o, o), (d, d)) * phi.transpose() + &q;
            let k = &pp * h.transpose() / (&h * &pp * h.transpose() + &r)[0];
            let ikh = DMatrix::identity(d, d) - &k * &h;
            let xi = &ikh * &phi;
            big_noise.view_mut((o, o), (d, d)).copy_from(&(&ikh * &q * ikh.transpose() + &k * &r * k.transpose()));
            big_xi.view_mut((o, o), (d, d)).copy_from(&xi);
            *acc = &xi * &*acc;
        }
        p = &big_xi * &p * big_xi.transpose() + big_noise; // Eq. 9 for the whole stack
    }
    let eq10 = &xi_a * p_ab_k * xi_b.transpose();
    let brute = p.view((0, na), (na, nb)).into_owned();
    assert!(rel_close(&eq10, &brute, 1e-10), "Eq. 10 {eq10} vs stacked {brute}");
}

/// Every node that runs the event on the same broadcasts with the same store gets the same
/// numbers, to the bit.
#[test]
fn nodes_running_the_same_event_agree_bit_for_bit() {
    let mut rng = ChaCha8Rng::seed_from_u64(3);
    let team: Vec<LinearPlatform> = (0..4)
        .map(|_| {
            let x0 = DVector::from_fn(3, |_, _| rng.random_range(-50.0..50.0));
            LinearPlatform::new(x0, random_spd(&mut rng, 3, 1.0, 0.1), [Some(0), Some(1), Some(2)]).unwrap()
        })
        .collect();
    let snapshots: Vec<_> = team.iter().enumerate().map(|(i, p)| p.snapshot(i as u16)).collect();
    let ranges: Vec<_> = (0..4u16)
        .flat_map(|a| ((a + 1)..4).map(move |b| CoopMeasurement::Range { from: a, to: b, range_m: 40.0, sigma_m: 0.1 }))
        .collect();
    let mut stores = vec![CrossCovariances::new(); 4];
    let outcomes: Vec<_> =
        stores.iter_mut().map(|s| cooperative_update(s, &snapshots, &ranges, CrossMode::Propagate).unwrap()).collect();
    for o in &outcomes[1..] {
        assert_eq!(o.corrections, outcomes[0].corrections);
    }
    assert!(stores.iter().all(|s| *s == stores[0]));
}

/// Bad measurements are typed errors and leave the store as it was.
#[test]
fn failed_event_leaves_store_untouched() {
    let mk =
        |x: f64| LinearPlatform::new(DVector::from_vec(vec![x, 0.0]), DMatrix::identity(2, 2), [Some(0), Some(1), None]).unwrap();
    let snapshots = vec![mk(0.0).snapshot(1), mk(10.0).snapshot(2)];
    let mut store = CrossCovariances::new();
    let good = [CoopMeasurement::Range { from: 1, to: 2, range_m: 10.2, sigma_m: 0.1 }];
    cooperative_update(&mut store, &snapshots, &good, CrossMode::Propagate).unwrap();
    let before = store.clone();
    let bad_cases = [
        CoopMeasurement::Range { from: 1, to: 2, range_m: f64::NAN, sigma_m: 0.1 },
        CoopMeasurement::Range { from: 1, to: 2, range_m: 10.0, sigma_m: -1.0 },
        CoopMeasurement::Range { from: 1, to: 9, range_m: 10.0, sigma_m: 0.1 },
        CoopMeasurement::Range { from: 1, to: 1, range_m: 10.0, sigma_m: 0.1 },
        CoopMeasurement::RangeBearing {
            from: 1,
            to: 2,
            range_m: 10.0,
            bearing_rad: 0.0,
            sigma_range_m: 0.1,
            sigma_bearing_rad: 0.01,
        },
    ];
    for bad in bad_cases {
        let err = cooperative_update(&mut store, &snapshots, std::slice::from_ref(&bad), CrossMode::Propagate);
        assert!(err.is_err(), "{bad:?} accepted");
        assert_eq!(store, before);
    }
    let mut nan_snapshot = snapshots.clone();
    nan_snapshot[1].covariance[(0, 0)] = f64::NAN;
    assert!(cooperative_update(&mut store, &nan_snapshot, &good, CrossMode::Propagate).is_err());
    let mut dup = snapshots.clone();
    dup[1].id = 1;
    assert!(cooperative_update(&mut store, &dup, &good, CrossMode::Propagate).is_err());
    assert_eq!(store, before);
}
