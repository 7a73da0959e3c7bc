//! The command-driven robot of `estimation::commanded` (pose, speed scale, yaw-rate bias) in a
//! team: the decentralized filter against one brute-force joint EKF over the stacked 5-state
//! errors of every robot, on random teams, random commands and random range-and-bearing events
//! among them (no landmark, so no local update: where the paper's method is exact). With and
//! without first-estimate Jacobians.

use cooploc::estimation::commanded::{CommandedConfig, CommandedFilter, CommandedSigma, DIM};
use cooploc::estimation::{CoopMeasurement, Method, PlatformFilter, Team, WheelSample};
use cooploc::time::TimeUs;
use nalgebra::{DMatrix, DVector, Vector3};
use proptest::prelude::*;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

fn config(first_estimates: bool) -> CommandedConfig {
    CommandedConfig {
        speed_noise_m_s_per_sqrt_hz: 0.02,
        yaw_rate_noise_rad_s_per_sqrt_hz: 0.03,
        speed_scale_walk_per_sqrt_s: 2e-3,
        yaw_rate_bias_walk_rad_s_per_sqrt_s: 5e-4,
        max_gap_s: 1.0,
        first_estimates,
    }
}

/// A range and bearing of `to` seen from `from`, its Jacobian at the filters' linearization
/// points and its residual at their estimates (as `dataset::run` builds it).
fn range_bearing(a: &CommandedFilter, b: &CommandedFilter, ia: u16, ib: u16, range: f64, bearing: f64) -> CoopMeasurement {
    let (pa, pb) = (a.position_ned_m(), b.position_ned_m());
    let (dn, de) = (pb[0] - pa[0], pb[1] - pa[1]);
    let (la, lb) = (a.linearization_position_ned_m(), b.linearization_position_ned_m());
    let (ln, le) = (lb[0] - la[0], lb[1] - la[1]);
    let lr2 = ln * ln + le * le;
    let lr = lr2.sqrt();
    let rows = [[ln / lr, le / lr], [-le / lr2, ln / lr2]];
    let (mut ha, mut hb) = (DMatrix::zeros(2, DIM), DMatrix::zeros(2, DIM));
    for r in 0..2 {
        for c in 0..2 {
            ha[(r, c)] = -rows[r][c];
            hb[(r, c)] = rows[r][c];
        }
    }
    ha[(1, 2)] = -1.0;
    let residual = DVector::from_vec(vec![
        range - (dn * dn + de * de).sqrt(),
        cooploc::estimation::unicycle::wrap_angle(bearing - (de.atan2(dn) - a.yaw_rad())),
    ]);
    CoopMeasurement::Linear {
        blocks: vec![(ia, ha), (ib, hb)],
        residual,
        r: DMatrix::from_diagonal(&DVector::from_vec(vec![0.01, 1e-4])),
    }
}

/// Brute force: copies of the robots for the nominal states, one stacked covariance.
struct Joint {
    robots: Vec<CommandedFilter>,
    p: DMatrix<f64>,
}

impl Joint {
    fn propagate(&mut self, i: usize, s: &WheelSample) {
        let (phi, q) = self.robots[i].transition(s).unwrap();
        let (phi, q) = (DMatrix::from_column_slice(DIM, DIM, phi.as_slice()), DMatrix::from_column_slice(DIM, DIM, q.as_slice()));
        let n = self.p.nrows();
        let mut big = DMatrix::identity(n, n);
        big.view_mut((DIM * i, DIM * i), (DIM, DIM)).copy_from(&phi);
        let mut big_q = DMatrix::zeros(n, n);
        big_q.view_mut((DIM * i, DIM * i), (DIM, DIM)).copy_from(&q);
        self.p = &big * &self.p * big.transpose() + big_q;
        self.robots[i].propagate(s).unwrap();
    }

    fn update(&mut self, meas: &[CoopMeasurement], ids: &[u16]) {
        let n = self.p.nrows();
        let m: usize = meas.iter().map(|x| x.len()).sum();
        let (mut h, mut z, mut r) = (DMatrix::zeros(m, n), DVector::zeros(m), DMatrix::zeros(m, m));
        let mut row = 0;
        for x in meas {
            let CoopMeasurement::Linear { blocks, residual, r: rx } = x else { unreachable!() };
            for (id, hb) in blocks {
                let i = ids.iter().position(|j| j == id).unwrap();
                h.view_mut((row, DIM * i), (residual.len(), DIM)).copy_from(hb);
            }
            z.rows_mut(row, residual.len()).copy_from(residual);
            r.view_mut((row, row), (residual.len(), residual.len())).copy_from(rx);
            row += residual.len();
        }
        let s = &h * &self.p * h.transpose() + &r;
        let k = &self.p * h.transpose() * s.try_inverse().unwrap();
        let a = DMatrix::identity(n, n) - &k * &h;
        let dx = &k * z;
        self.p = &a * &self.p * a.transpose() + &k * r * k.transpose();
        for (i, f) in self.robots.iter_mut().enumerate() {
            let block = self.p.view((DIM * i, DIM * i), (DIM, DIM)).into_owned();
            f.apply_joint(&dx.rows(DIM * i, DIM).into_owned(), &block).unwrap();
        }
    }
}

fn rel_close(a: &DMatrix<f64>, b: &DMatrix<f64>, tol: f64) -> bool {
    (a - b).amax() <= tol * b.amax().max(1.0)
}

fn run_random_team(seed: u64, n: usize, steps: usize, first_estimates: bool) -> Result<(), TestCaseError> {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let ids: Vec<u16> = (1..=n as u16).collect();
    let sigma = CommandedSigma { pos_m: 0.05, yaw_rad: 0.02, speed_scale: 0.1, yaw_rate_bias_rad_s: 0.01 };
    let robots: Vec<CommandedFilter> = ids
        .iter()
        .map(|_| {
            let pos = Vector3::new(rng.random_range(-5.0..5.0), rng.random_range(-5.0..5.0), 0.0);
            CommandedFilter::new(config(first_estimates), TimeUs(0), pos, rng.random_range(-3.0..3.0), sigma).unwrap()
        })
        .collect();
    let mut team = Team::new(Method::Decentralized, ids.iter().copied().zip(robots.clone()).collect()).unwrap();
    let mut central = Team::new(Method::Centralized, ids.iter().copied().zip(robots.clone()).collect()).unwrap();
    let mut joint = Joint { p: DMatrix::zeros(DIM * n, DIM * n), robots };
    for (i, f) in joint.robots.iter().enumerate() {
        joint.p.view_mut((DIM * i, DIM * i), (DIM, DIM)).copy_from(&f.covariance());
    }
    let mut t = 0u64;
    let mut events = 0;
    for _ in 0..steps {
        t += rng.random_range(20_000..200_000);
        for (i, &id) in ids.iter().enumerate() {
            // Standing still now and then (no bias, no noise), else a random command.
            let s = if rng.random_bool(0.2) {
                WheelSample { t: TimeUs(t), speed_m_s: 0.0, yaw_rate_rad_s: 0.0 }
            } else {
                WheelSample { t: TimeUs(t), speed_m_s: rng.random_range(0.0..0.5), yaw_rate_rad_s: rng.random_range(-0.5..0.5) }
            };
            team.filter_mut(id).unwrap().propagate(&s).unwrap();
            central.filter_mut(id).unwrap().propagate(&s).unwrap();
            joint.propagate(i, &s);
        }
        if rng.random_bool(0.4) {
            // One observer sees one or two teammates.
            let a = rng.random_range(0..n);
            let mut meas = Vec::new();
            for _ in 0..rng.random_range(1..=2usize) {
                let b = (a + rng.random_range(1..n)) % n;
                if meas.iter().any(|m: &CoopMeasurement| m.platforms()[1] == ids[b]) {
                    continue;
                }
                let (range, bearing) = (rng.random_range(1.0..8.0), rng.random_range(-1.0..1.0));
                meas.push(range_bearing(
                    team.filter(ids[a]).unwrap(),
                    team.filter(ids[b]).unwrap(),
                    ids[a],
                    ids[b],
                    range,
                    bearing,
                ));
            }
            team.cooperative_event(&meas).unwrap();
            central.cooperative_event(&meas).unwrap();
            joint.update(&meas, &ids);
            events += 1;
        }
    }
    prop_assume!(events > 0);
    for (i, &id) in ids.iter().enumerate() {
        let (d, c, j) = (team.filter(id).unwrap(), central.filter(id).unwrap(), &joint.robots[i]);
        let (xd, xj) = (DMatrix::from_row_slice(1, DIM, &d.state()), DMatrix::from_row_slice(1, DIM, &j.state()));
        prop_assert!(rel_close(&xd, &xj, 1e-9), "robot {id} state {xd} vs {xj}");
        prop_assert!(rel_close(&d.covariance(), &j.covariance(), 1e-9), "robot {id} covariance");
        // With range-bearing events only (no local update) the decentralized team is the
        // centralized one; its events run among the robots they involve, the others bystanders
        // (the same update, another order of the sums): equal to the last bits.
        let xc = DMatrix::from_row_slice(1, DIM, &c.state());
        prop_assert!(rel_close(&xd, &xc, 1e-12), "robot {id}: decentralized {xd} vs centralized {xc}");
        // Cross-covariances of the paper's Eq. 10 against the stacked matrix.
        for (k, &other) in ids.iter().enumerate().skip(i + 1) {
            let stored = team.cross().get(id, other).unwrap_or_else(|| DMatrix::zeros(DIM, DIM));
            let rebuilt = d.psi() * stored * team.filter(other).unwrap().psi().transpose();
            let brute = joint.p.view((DIM * i, DIM * k), (DIM, DIM)).into_owned();
            prop_assert!(rel_close(&rebuilt, &brute, 1e-9), "cross {id}-{other}: {rebuilt} vs {brute}");
        }
    }
    Ok(())
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(48))]

    #[test]
    fn decentralized_equals_the_stacked_ekf_with_speed_scale_and_bias_states(
        seed in any::<u64>(), n in 2usize..=5, steps in 5usize..60, fej in any::<bool>()
    ) {
        run_random_team(seed, n, steps, fej)?;
    }
}
