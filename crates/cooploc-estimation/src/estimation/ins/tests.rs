use nalgebra::Vector3;
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use rand_distr::{Distribution, Normal};

use super::*;

const G: f64 = STANDARD_GRAVITY_M_S2;

fn noise_free(latitude_deg: f64) -> InsConfig {
    InsConfig {
        latitude_deg,
        accel_noise_density_m_s2_per_sqrt_hz: 0.0,
        gyro_noise_density_rad_s_per_sqrt_hz: 0.0,
        ..InsConfig::default()
    }
}

fn small_sigma() -> InsInitialSigma {
    InsInitialSigma {
        pos_ned_m: Vector3::repeat(1.0),
        vel_ned_m_s: Vector3::repeat(0.1),
        att_ned_rad: Vector3::new(0.01, 0.01, 0.05),
        accel_bias_frd_m_s2: Vector3::repeat(0.02),
        gyro_bias_frd_rad_s: Vector3::repeat(1e-4),
        odometer_scale: 0.01,
    }
}

fn yaw_q(yaw: f64) -> UnitQuaternion<f64> {
    UnitQuaternion::from_axis_angle(&Vector3::z_axis(), yaw)
}

fn imu(t_us: u64, f: Vector3<f64>, w: Vector3<f64>) -> ImuSample {
    ImuSample { t: TimeUs(t_us), specific_force_frd_m_s2: f, angular_rate_frd_rad_s: w }
}

/// Five-point Gauss-Legendre mean of `f` over `[a, b]` (exact to rounding for the smooth,
/// slowly varying truth signals used here).
fn gl_mean(a: f64, b: f64, f: impl Fn(f64) -> Vector3<f64>) -> Vector3<f64> {
    const X: [f64; 5] = [0.0, -0.538_469_310_105_683_1, 0.538_469_310_105_683_1, -0.906_179_845_938_664, 0.906_179_845_938_664];
    const W: [f64; 5] = [
        0.568_888_888_888_888_9,
        0.478_628_670_499_366_5,
        0.478_628_670_499_366_5,
        0.236_926_885_056_189_1,
        0.236_926_885_056_189_1,
    ];
    let (m, h) = (0.5 * (a + b), 0.5 * (b - a));
    X.iter().zip(W).map(|(&x, w)| f(m + h * x) * w).sum::<Vector3<f64>>() * 0.5
}

fn random_spd(rng: &mut ChaCha8Rng) -> Matrix16 {
    let n = Normal::new(0.0, 1.0).unwrap();
    let l = Matrix16::from_fn(|_, _| n.sample(rng));
    let p = l * l.transpose() + Matrix16::identity();
    0.5 * (p + p.transpose())
}

fn random_matrix(rng: &mut ChaCha8Rng) -> Matrix16 {
    let n = Normal::new(0.0, 1.0).unwrap();
    Matrix16::from_fn(|_, _| n.sample(rng))
}

fn rel_err(a: &Matrix16, b: &Matrix16) -> f64 {
    (a - b).norm() / b.norm()
}

#[test]
fn positive_phi_down_increases_yaw() {
    for yaw in [-3.0, -1.0, 0.0, 0.7, 2.5] {
        let est = yaw_q(yaw);
        for d in [1e-3, -2e-3, 0.1] {
            let truth = UnitQuaternion::from_scaled_axis(Vector3::new(0.0, 0.0, d)) * est;
            let dyaw = crate::estimation::unicycle::wrap_angle(yaw_of(&truth) - yaw_of(&est));
            assert!((dyaw - d).abs() < 1e-12, "yaw {yaw} d {d}: {dyaw}");
            let phi = attitude_error_ned(&truth, &est);
            assert!((phi - Vector3::new(0.0, 0.0, d)).norm() < 1e-12);
        }
    }
    // yaw_of agrees with nalgebra's ZYX Euler angles on a tilted attitude.
    let q = UnitQuaternion::from_euler_angles(0.1, -0.2, 2.0);
    assert!((yaw_of(&q) - q.euler_angles().2).abs() < 1e-12);
    assert!((yaw_of(&q) - 2.0).abs() < 1e-12);
    // The filter advertises exactly that index.
    let f = InsFilter::new(noise_free(0.0), TimeUs(0), InsState::at_rest(yaw_q(0.3)), small_sigma()).unwrap();
    let h = f.geometry().heading.unwrap();
    assert_eq!(h.index, HEADING_INDEX);
    assert_eq!(HEADING_INDEX, 8);
    assert!((h.yaw_rad - 0.3).abs() < 1e-15);
    assert!(f.snapshot(1).validate().is_ok());
}

/// Test 1: a vehicle at rest, fed the exact specific force and Earth rate, stays put.
#[test]
fn stationary_noise_free_stays_put() {
    let cfg = noise_free(45.0);
    let r = yaw_q(0.7);
    let f_b = r.inverse_transform_vector(&-cfg.gravity_ned_m_s2());
    let w_b = r.inverse_transform_vector(&cfg.earth_rate_ned_rad_s());
    let mut f = InsFilter::new(cfg, TimeUs(0), InsState::at_rest(r), small_sigma()).unwrap();
    for k in 1..=120_000u64 {
        f.propagate(&imu(k * 5_000, f_b, w_b)).unwrap();
    }
    assert_eq!(f.time(), TimeUs(600_000_000));
    assert!(f.position_ned_m().norm() < 1e-3, "{}", f.position_ned_m());
    assert!(f.velocity_ned_m_s().norm() < 1e-5, "{}", f.velocity_ned_m_s());
    let att = attitude_error_ned(&r, &f.attitude()).norm();
    assert!(att < 1e-7, "{att}");
}

/// Analytic truth of a level constant-rate turn at constant speed on the rotating Earth.
struct Turn {
    yaw0: f64,
    rate_rad_s: f64,
    speed_m_s: f64,
    w_ie: Vector3<f64>,
    g: Vector3<f64>,
}

impl Turn {
    fn yaw(&self, t: f64) -> f64 {
        self.yaw0 + self.rate_rad_s * t
    }
    fn att(&self, t: f64) -> UnitQuaternion<f64> {
        yaw_q(self.yaw(t))
    }
    fn vel(&self, t: f64) -> Vector3<f64> {
        let (s, c) = self.yaw(t).sin_cos();
        self.speed_m_s * Vector3::new(c, s, 0.0)
    }
    fn pos(&self, t: f64) -> Vector3<f64> {
        let (s, c) = self.yaw(t).sin_cos();
        let (s0, c0) = self.yaw0.sin_cos();
        self.speed_m_s / self.rate_rad_s * Vector3::new(s - s0, c0 - c, 0.0)
    }
    fn specific_force_b(&self, t: f64) -> Vector3<f64> {
        let (s, c) = self.yaw(t).sin_cos();
        let a = self.speed_m_s * self.rate_rad_s * Vector3::new(-s, c, 0.0);
        self.att(t).inverse_transform_vector(&(a + 2.0 * self.w_ie.cross(&self.vel(t)) - self.g))
    }
    fn rate_b(&self, t: f64) -> Vector3<f64> {
        Vector3::new(0.0, 0.0, self.rate_rad_s) + self.att(t).inverse_transform_vector(&self.w_ie)
    }
    /// The IMU sample of the interval ending at `k dt`: exact means of the truth.
    fn sample(&self, k: u64, dt_us: u64) -> ImuSample {
        let (a, b) = ((k - 1) as f64 * dt_us as f64 * 1e-6, k as f64 * dt_us as f64 * 1e-6);
        imu(k * dt_us, gl_mean(a, b, |t| self.specific_force_b(t)), gl_mean(a, b, |t| self.rate_b(t)))
    }
    fn state(&self, t: f64) -> InsState {
        InsState { pos_ned_m: self.pos(t), vel_ned_m_s: self.vel(t), ..InsState::at_rest(self.att(t)) }
    }
}

/// Test 2: coning, sculling, rotation and Earth-rate corrections on a 380 s turn.
#[test]
fn constant_rate_turn_noise_free() {
    let cfg = noise_free(45.0);
    let turn = Turn { yaw0: 0.3, rate_rad_s: 0.05, speed_m_s: 10.0, w_ie: cfg.earth_rate_ned_rad_s(), g: cfg.gravity_ned_m_s2() };
    let mut f = InsFilter::new(cfg, TimeUs(0), turn.state(0.0), small_sigma()).unwrap();
    let dt_us = 5_000;
    let n = 380 * 200;
    for k in 1..=n {
        f.propagate(&turn.sample(k, dt_us)).unwrap();
    }
    let t = 380.0;
    let dp = (f.position_ned_m() - turn.pos(t)).norm();
    let dyaw = attitude_error_ned(&turn.att(t), &f.attitude()).norm();
    let dv = (f.velocity_ned_m_s() - turn.vel(t)).norm();
    assert!(dp < 0.05, "position error {dp} m");
    assert!(dyaw < 1e-5, "attitude error {dyaw} rad");
    assert!(dv < 1e-3, "velocity error {dv} m/s");
}

/// A filter with a dense random covariance and `Psi`, tilted and moving, with biases.
fn busy_filter(rng: &mut ChaCha8Rng) -> InsFilter {
    let cfg = InsConfig {
        latitude_deg: 30.0,
        accel_bias_random_walk_m_s3_per_sqrt_hz: 1e-4,
        gyro_bias_random_walk_rad_s2_per_sqrt_hz: 1e-6,
        ..InsConfig::default()
    };
    let x = InsState {
        pos_ned_m: Vector3::new(10.0, -20.0, 1.0),
        vel_ned_m_s: Vector3::new(5.0, -3.0, 0.5),
        att_frd_to_ned: UnitQuaternion::from_euler_angles(0.05, -0.08, 1.2),
        accel_bias_frd_m_s2: Vector3::new(0.02, -0.01, 0.03),
        gyro_bias_frd_rad_s: Vector3::new(1e-4, -2e-4, 5e-5),
        odometer_scale_error: 0.01,
    };
    let mut f = InsFilter::new(cfg, TimeUs(1_000_000), x, small_sigma()).unwrap();
    f.p.set(random_spd(rng));
    f.psi_t.set(random_matrix(rng));
    f
}

/// Test 3: the block-sparse time update equals the dense `Phi P Phi^T + Qd`, `Phi Psi`.
#[test]
fn sparse_propagation_equals_dense() {
    let mut rng = ChaCha8Rng::seed_from_u64(3);
    for track in [true, false] {
        let mut f = busy_filter(&mut rng);
        f.set_track_psi(track);
        if track {
            f.psi_t.set(random_matrix(&mut rng));
        }
        let (p0, psi0, x0) = (*f.p.get(), f.psi16(), f.x);
        let s = imu(1_005_000, Vector3::new(0.5, 0.3, -9.7), Vector3::new(0.02, -0.01, 0.3));
        f.propagate(&s).unwrap();
        // Dense Phi built independently from the documented F.
        let dt = 0.005;
        let r = x0.att_frd_to_ned.to_rotation_matrix().into_inner();
        let f_n = r * (s.specific_force_frd_m_s2 - x0.accel_bias_frd_m_s2);
        let w_ie = f.config.earth_rate_ned_rad_s();
        let mut fc = Matrix16::zeros();
        fc.fixed_view_mut::<3, 3>(0, 3).copy_from(&Matrix3::identity());
        fc.fixed_view_mut::<3, 3>(3, 3).copy_from(&(-2.0 * w_ie.cross_matrix()));
        fc.fixed_view_mut::<3, 3>(3, 6).copy_from(&(-f_n.cross_matrix()));
        fc.fixed_view_mut::<3, 3>(3, 9).copy_from(&-r);
        fc.fixed_view_mut::<3, 3>(6, 6).copy_from(&(-w_ie.cross_matrix()));
        fc.fixed_view_mut::<3, 3>(6, 12).copy_from(&-r);
        let phi = Matrix16::identity() + fc * dt;
        let c = f.config;
        let mut q = Vector16::zeros();
        q.fixed_rows_mut::<3>(3).fill(c.accel_noise_density_m_s2_per_sqrt_hz.powi(2) * dt);
        q.fixed_rows_mut::<3>(6).fill(c.gyro_noise_density_rad_s_per_sqrt_hz.powi(2) * dt);
        q.fixed_rows_mut::<3>(9).fill(c.accel_bias_random_walk_m_s3_per_sqrt_hz.powi(2) * dt);
        q.fixed_rows_mut::<3>(12).fill(c.gyro_bias_random_walk_rad_s2_per_sqrt_hz.powi(2) * dt);
        let p_dense = phi * p0 * phi.transpose() + Matrix16::from_diagonal(&q);
        assert!(rel_err(f.p.get(), &p_dense) < 1e-12, "{}", rel_err(f.p.get(), &p_dense));
        assert_eq!(*f.p.get(), f.p.get().transpose(), "symmetric");
        if track {
            assert!(rel_err(&f.psi16(), &(phi * psi0)) < 1e-12);
        } else {
            assert_eq!(f.psi16(), Matrix16::identity());
        }
    }
    // The routines themselves against the dense F dt they stand for.
    let w_ie = Vector3::new(0.3, -0.1, 0.2);
    let r = UnitQuaternion::from_euler_angles(0.3, -0.2, 2.0).to_rotation_matrix().into_inner();
    let f = FdtBlocks::new(0.01, &r, &Vector3::new(1.0, -2.0, -9.0), &w_ie);
    let phi = Matrix16::identity() + f.dense();
    let m = random_matrix(&mut rng);
    assert!(rel_err(&times_phi_transpose_matrix(&f, &m), &(m * phi.transpose())) < 1e-14);
    for c in 0..ERROR_DIM {
        let mut o = [0.0; ERROR_DIM];
        phi_rows(&f, &m.data.0[c], &mut o);
        let dense = phi * m.column(c);
        for r in 0..ACCEL_BIAS {
            assert!((o[r] - dense[r]).abs() < 1e-14 * dense.norm());
        }
    }
    let p = random_spd(&mut rng);
    let qd = Vector16::from_fn(|i, _| i as f64 * 1e-3);
    let p_new = propagate_covariance(&f, &p, &qd);
    assert!(rel_err(&p_new, &(phi * p * phi.transpose() + Matrix16::from_diagonal(&qd))) < 1e-12);
    // The finiteness reduction.
    assert!(sum_is_finite(&p.data.0));
    for bad in [f64::NAN, f64::INFINITY, f64::NEG_INFINITY] {
        let mut q = p;
        q[(7, 11)] = bad;
        assert!(!sum_is_finite(&q.data.0));
        q[(3, 2)] = -bad;
        assert!(!sum_is_finite(&q.data.0), "opposite infinities must not cancel");
    }
}

/// The error `x_true - x_est` in error-state coordinates.
fn state_error(truth: &InsState, est: &InsState) -> Vector16 {
    let mut e = Vector16::zeros();
    e.fixed_rows_mut::<3>(POS).copy_from(&(truth.pos_ned_m - est.pos_ned_m));
    e.fixed_rows_mut::<3>(VEL).copy_from(&(truth.vel_ned_m_s - est.vel_ned_m_s));
    e.fixed_rows_mut::<3>(ATT).copy_from(&attitude_error_ned(&truth.att_frd_to_ned, &est.att_frd_to_ned));
    e.fixed_rows_mut::<3>(ACCEL_BIAS).copy_from(&(truth.accel_bias_frd_m_s2 - est.accel_bias_frd_m_s2));
    e.fixed_rows_mut::<3>(GYRO_BIAS).copy_from(&(truth.gyro_bias_frd_rad_s - est.gyro_bias_frd_rad_s));
    e[ODO_SCALE] = truth.odometer_scale_error - est.odometer_scale_error;
    e
}

/// Test 4: the error model (F, hence Phi and Psi) against finite differences of the
/// mechanization: two noise-free copies, one started from a perturbed state, driven by the
/// same IMU samples; their difference after 1 s must be `Psi dx0` to first order. The Earth
/// rate is exaggerated (0.1 rad/s) so that its terms are visible.
#[test]
fn error_model_matches_finite_differences() {
    let mut rng = ChaCha8Rng::seed_from_u64(4);
    let mut base = busy_filter(&mut rng);
    base.w_ie_n = Vector3::new(0.07, 0.0, -0.07);
    base.psi_t.set(Matrix16::identity());
    let dt_us = 500;
    let steps = 2_000;
    let t0 = base.time().0;
    let sample = |k: u64| {
        let t = k as f64 * dt_us as f64 * 1e-6;
        imu(
            t0 + k * dt_us,
            Vector3::new(1.0 + 0.5 * t.sin(), 0.8 * (0.7 * t).cos(), -9.8 + 0.3 * (2.0 * t).sin()),
            Vector3::new(0.1 * t.sin(), 0.05 * (1.3 * t).cos(), 0.2 + 0.1 * (0.5 * t).sin()),
        )
    };
    let mut est = base;
    for k in 1..=steps {
        est.propagate(&sample(k)).unwrap();
    }
    let phi_total = est.psi16();
    // Perturbation size per block: small enough for the second-order terms to stay below
    // the tolerance.
    let eps = [1e-3, 1e-3, 1e-3, 1e-4, 1e-4, 1e-4, 1e-5, 1e-5, 1e-5, 1e-4, 1e-4, 1e-4, 1e-6, 1e-6, 1e-6, 1e-4];
    let block_of = |i: usize| if i == ODO_SCALE { ODO_SCALE..ODO_SCALE + 1 } else { (i / 3 * 3)..(i / 3 * 3 + 3) };
    for (i, &e) in eps.iter().enumerate() {
        let mut dx0 = Vector16::zeros();
        dx0[i] = e;
        let mut truth = base;
        truth.x = base.x.injected(&dx0).unwrap();
        for k in 1..=steps {
            truth.propagate(&sample(k)).unwrap();
        }
        let actual = state_error(&truth.x, &est.x);
        let predicted = phi_total * dx0;
        // Block by block: the difference relative to the block's predicted size. `Phi = I + F dt`
        // is first order, so a chain of `m` integrations (gyro bias -> attitude -> velocity ->
        // position: m = 3) differs from the exact transition by about `m dt / T` (1.5e-3 here),
        // while a wrong sign or factor in F shows as an O(1e-1) to O(1) discrepancy.
        for start in [POS, VEL, ATT, ACCEL_BIAS, GYRO_BIAS, ODO_SCALE] {
            let b = block_of(start);
            let pred = predicted.rows(b.start, b.len());
            let act = actual.rows(b.start, b.len());
            let err = (act - pred).norm();
            // Blocks the perturbation does not reach to first order must stay at second order.
            let floor = 1e-7 * e;
            assert!(
                err <= 2e-3 * pred.norm() + floor,
                "perturbing {i}: block {start}: actual {act} predicted {pred} (err {err:e}, |pred| {:e})",
                pred.norm()
            );
        }
        // And the perturbation does reach position for every non-scale state.
        if i != ODO_SCALE {
            assert!(predicted.rows(POS, 3).norm() > 1e-3 * e, "state {i} never reaches position?");
        }
    }
}

/// Test 5: odometer and constraint Jacobian against central differences of `h` under error
/// injection.
#[test]
fn odometer_jacobian_matches_numerical_derivative() {
    let mut rng = ChaCha8Rng::seed_from_u64(5);
    let f = busy_filter(&mut rng);
    let s = OdometerSample { t: f.time(), speed_m_s: 6.3 };
    let m = f.odometer_measurement(&s).unwrap();
    let h0 = odometer_prediction(&f.x);
    assert!((m.residual[0] - (6.3 - h0.x)).abs() < 1e-15);
    assert!((m.residual[1] + h0.y).abs() < 1e-15 && (m.residual[2] + h0.z).abs() < 1e-15);
    assert_eq!(m.r[(0, 0)], 0.2 * 0.2);
    let eps = 1e-6;
    for i in 0..ERROR_DIM {
        let mut dx = Vector16::zeros();
        dx[i] = eps;
        let hp = odometer_prediction(&f.x.injected(&dx).unwrap());
        let hm = odometer_prediction(&f.x.injected(&-dx).unwrap());
        let numeric = (hp - hm) / (2.0 * eps);
        for row in 0..3 {
            assert!(
                (numeric[row] - m.h[(row, i)]).abs() < 1e-6,
                "d h{row} / d x{i}: numeric {} analytic {}",
                numeric[row],
                m.h[(row, i)]
            );
        }
    }
    // Linearising changes nothing.
    let before = f;
    let _ = f.odometer_measurement(&s).unwrap();
    assert_eq!(f, before);
}

/// Reset Jacobian: `G` is the derivative of the post-reset error with respect to the remaining
/// error, and the opposite sign is wrong.
#[test]
fn reset_jacobian_is_derivative_of_the_reset() {
    let phi_hat = Vector3::new(0.03, -0.02, 0.05);
    let mut dx = Vector16::zeros();
    dx.fixed_rows_mut::<3>(ATT).copy_from(&phi_hat);
    let g = reset_jacobian(&dx);
    let g_att = g.fixed_view::<3, 3>(ATT, ATT).into_owned();
    // phi+ = Log(Exp(phi_hat + d) Exp(-phi_hat)).
    let post = |d: Vector3<f64>| {
        (UnitQuaternion::from_scaled_axis(phi_hat + d) * UnitQuaternion::from_scaled_axis(-phi_hat)).scaled_axis()
    };
    let eps = 1e-6;
    let mut numeric = Matrix3::zeros();
    for j in 0..3 {
        let mut d = Vector3::zeros();
        d[j] = eps;
        numeric.set_column(j, &((post(d) - post(-d)) / (2.0 * eps)));
    }
    assert!((numeric - g_att).amax() < 1e-9, "{numeric} vs {g_att}");
    let first_order_plus = Matrix3::identity() + 0.5 * phi_hat.cross_matrix();
    let first_order_minus = Matrix3::identity() - 0.5 * phi_hat.cross_matrix();
    assert!((numeric - first_order_plus).amax() < 1e-3);
    assert!((numeric - first_order_minus).amax() > 0.02);
    // Identity off the attitude block.
    let mut off = g;
    off.fixed_view_mut::<3, 3>(ATT, ATT).copy_from(&Matrix3::identity());
    assert_eq!(off, Matrix16::identity());
    // Small-angle branch agrees with the closed form at the switch.
    let a = Vector3::new(1e-4, 0.0, 0.0) * 0.999_999;
    let b = Vector3::new(1e-4, 0.0, 0.0) * 1.000_001;
    assert!((so3_left_jacobian(&a) - so3_left_jacobian(&b)).amax() < 1e-9);
}

/// Test 8: a joint write-back resets with `G`: `Psi = G`, `P = G p G^T`.
#[test]
fn apply_joint_uses_reset_jacobian() {
    let mut rng = ChaCha8Rng::seed_from_u64(8);
    let mut f = busy_filter(&mut rng);
    let n = Normal::new(0.0, 0.01).unwrap();
    let dx = DVector::from_fn(ERROR_DIM, |_, _| n.sample(&mut rng));
    let p = to_dmatrix(&random_spd(&mut rng));
    let before = f.x;
    f.apply_joint(&dx, &p).unwrap();
    let g = reset_jacobian(&to_vector16(&dx));
    assert_eq!(f.psi(), to_dmatrix(&g));
    let expected = to_dmatrix(&g) * &p * to_dmatrix(&g).transpose();
    assert!((f.covariance() - &expected).amax() < 1e-12 * expected.amax());
    assert_ne!(g, Matrix16::identity());
    assert_eq!(f.x, before.injected(&to_vector16(&dx)).unwrap());
    assert!((f.x.pos_ned_m - before.pos_ned_m - Vector3::new(dx[0], dx[1], dx[2])).norm() < 1e-12);
    // Without Psi tracking it stays the identity.
    f.set_track_psi(false);
    f.apply_joint(&dx, &p).unwrap();
    assert_eq!(f.psi(), DMatrix::identity(ERROR_DIM, ERROR_DIM));
    // Bad write-backs change nothing.
    let snapshot = f;
    assert!(f.apply_joint(&DVector::zeros(15), &p).is_err());
    let mut bad = p.clone();
    bad[(3, 4)] = f64::NAN;
    assert!(f.apply_joint(&DVector::zeros(ERROR_DIM), &bad).is_err());
    let mut huge = DVector::zeros(ERROR_DIM);
    huge[ATT] = 1e300;
    huge[ATT + 1] = 1e300;
    assert_eq!(f.apply_joint(&huge, &p), Err(EstimationError::NonFinite { what: "INS state after error injection" }));
    assert_eq!(f, snapshot);
}

/// A bystander's share (`coop::BystanderShare`): `Psi a` injected, `P - Psi b Psi^T` reset with
/// the injection's `G`, and `Psi` kept (times `G`), as after a local update; a share that would
/// leave the covariance indefinite, or of the wrong size, is refused and changes nothing.
#[test]
fn a_bystanders_share_keeps_psi_and_resets_with_the_injection() {
    let mut rng = ChaCha8Rng::seed_from_u64(11);
    let mut f = busy_filter(&mut rng);
    let n = Normal::new(0.0, 0.01).unwrap();
    let a = DVector::from_fn(ERROR_DIM, |_, _| n.sample(&mut rng));
    let (p0, psi0, x0) = (f.covariance(), f.psi(), f.x);
    let psi_inv = psi0.clone().try_inverse().unwrap();
    // b such that Psi b Psi^T is half the covariance
    let b = 0.5 * &psi_inv * &p0 * psi_inv.transpose();
    f.apply_bystander(&a, &b).unwrap();
    let dx = &psi0 * &a;
    let g = to_dmatrix(&reset_jacobian(&to_vector16(&dx)));
    assert_ne!(g, DMatrix::identity(ERROR_DIM, ERROR_DIM));
    let expected = &g * (0.5 * &p0) * g.transpose();
    assert!((f.covariance() - &expected).amax() < 1e-9 * expected.amax());
    assert!((f.psi() - &g * &psi0).amax() < 1e-12 * psi0.amax());
    assert_eq!(f.x, x0.injected(&to_vector16(&dx)).unwrap());
    // Refused: more taken than the covariance holds, a wrong size, a non-finite entry.
    let snapshot = f;
    let too_much = 3.0 * &b;
    assert!(matches!(f.apply_bystander(&a, &too_much), Err(EstimationError::NotPositiveDefinite { .. })));
    assert!(f.apply_bystander(&DVector::zeros(15), &b).is_err());
    let mut bad = b.clone();
    bad[(2, 2)] = f64::NAN;
    assert!(f.apply_bystander(&a, &bad).is_err());
    assert_eq!(f, snapshot);
}

/// Added noise grows the covariance by exactly `q` and leaves the state and `Psi` alone (the
/// team's cross-covariances stay exact); a wrong-sized, non-finite, asymmetric or indefinite `q`
/// is refused and changes nothing.
#[test]
fn add_noise_grows_the_covariance_and_keeps_psi() {
    let mut rng = ChaCha8Rng::seed_from_u64(10);
    let mut f = busy_filter(&mut rng);
    let (p0, psi0, x0) = (f.covariance(), f.psi(), f.x);
    let mut q = DMatrix::zeros(ERROR_DIM, ERROR_DIM);
    q[(POS, POS)] = 3600.0;
    q[(POS + 1, POS + 1)] = 3600.0;
    f.add_noise(&q).unwrap();
    assert!((f.covariance() - (&p0 + &q)).amax() < 1e-12 * 3600.0);
    assert_eq!(f.psi(), psi0);
    assert_eq!(f.x, x0);
    let snapshot = f;
    let mut asymmetric = q.clone();
    asymmetric[(POS, POS + 1)] = 1.0;
    let mut indefinite = q.clone();
    indefinite[(POS, POS)] = -1.0;
    let mut nan = q.clone();
    nan[(POS, POS)] = f64::NAN;
    for bad in [DMatrix::zeros(15, 15), asymmetric, indefinite, nan] {
        assert!(f.add_noise(&bad).is_err());
        assert_eq!(f, snapshot);
    }
}

/// A local update folds `G (I - K H)` into `Psi` and resets the covariance with `G`.
#[test]
fn update_local_resets_with_g() {
    let mut rng = ChaCha8Rng::seed_from_u64(9);
    let mut f = busy_filter(&mut rng);
    let (p0, psi0) = (*f.p.get(), f.psi16());
    let meas = f.odometer_measurement(&OdometerSample { t: f.time(), speed_m_s: 4.0 }).unwrap();
    let up = kalman::local_update(&to_dmatrix(&p0), &meas).unwrap();
    let diag = f.update_local(&meas).unwrap();
    // The INS uses the fixed-width downdate form; it agrees with the generic Joseph form to rounding.
    assert_eq!(diag.innovation, up.diagnostics.innovation);
    assert!((&diag.innovation_cov - &up.diagnostics.innovation_cov).amax() < 1e-12 * up.diagnostics.innovation_cov.amax());
    assert!((diag.nis - up.diagnostics.nis).abs() < 1e-10 * up.diagnostics.nis.max(1.0));
    let dx = to_vector16(&up.dx);
    let g = reset_jacobian(&dx);
    assert!(dx.fixed_rows::<3>(ATT).norm() > 1e-3, "the update must rotate for this test to mean anything");
    assert!(rel_err(&f.psi16(), &(g * to_matrix16(&up.i_minus_kh) * psi0)) < 1e-14);
    assert!(rel_err(f.p.get(), &(g * to_matrix16(&up.p) * g.transpose())) < 1e-13);
}

fn sample_vec(rng: &mut ChaCha8Rng, sigma: &Vector3<f64>) -> Vector3<f64> {
    Vector3::from_fn(|i, _| if sigma[i] > 0.0 { Normal::new(0.0, sigma[i]).unwrap().sample(rng) } else { 0.0 })
}

/// Test 6: IMU + odometer on a straight drive with biases and noise: errors within 4 sigma of
/// the filter's covariance, and odometer updates shrink the velocity covariance.
#[test]
fn noisy_straight_drive_is_consistent() {
    let cfg = InsConfig {
        latitude_deg: 45.0,
        accel_noise_density_m_s2_per_sqrt_hz: 2e-3,
        gyro_noise_density_rad_s_per_sqrt_hz: 1e-4,
        sigma_odometer_m_s: 0.1,
        ..InsConfig::default()
    };
    let sigma0 = InsInitialSigma {
        pos_ned_m: Vector3::repeat(0.5),
        vel_ned_m_s: Vector3::repeat(0.05),
        att_ned_rad: Vector3::new(2e-3, 2e-3, 1e-2),
        accel_bias_frd_m_s2: Vector3::repeat(0.03),
        gyro_bias_frd_rad_s: Vector3::repeat(2e-4),
        odometer_scale: 0.02,
    };
    let (w_ie, g) = (cfg.earth_rate_ned_rad_s(), cfg.gravity_ned_m_s2());
    let speed = 10.0;
    let yaw = 0.4;
    let r_true = yaw_q(yaw);
    let v_true = r_true * Vector3::new(speed, 0.0, 0.0);
    let f_true = r_true.inverse_transform_vector(&(2.0 * w_ie.cross(&v_true) - g));
    let w_true = r_true.inverse_transform_vector(&w_ie);
    let dt_us = 5_000u64;
    let dt = dt_us as f64 * 1e-6;
    let mut worst: f64 = 0.0;
    for seed in 0..6 {
        let mut rng = ChaCha8Rng::seed_from_u64(600 + seed);
        let b_a = sample_vec(&mut rng, &sigma0.accel_bias_frd_m_s2);
        let b_g = sample_vec(&mut rng, &sigma0.gyro_bias_frd_rad_s);
        let k_true = Normal::new(0.0, sigma0.odometer_scale).unwrap().sample(&mut rng);
        let phi0 = sample_vec(&mut rng, &sigma0.att_ned_rad);
        let est = InsState {
            pos_ned_m: -sample_vec(&mut rng, &sigma0.pos_ned_m),
            vel_ned_m_s: v_true - sample_vec(&mut rng, &sigma0.vel_ned_m_s),
            att_frd_to_ned: UnitQuaternion::from_scaled_axis(-phi0) * r_true,
            ..InsState::at_rest(r_true)
        };
        let mut f = InsFilter::new(cfg, TimeUs(0), est, sigma0).unwrap();
        let na = Normal::new(0.0, cfg.accel_noise_density_m_s2_per_sqrt_hz / dt.sqrt()).unwrap();
        let ng = Normal::new(0.0, cfg.gyro_noise_density_rad_s_per_sqrt_hz / dt.sqrt()).unwrap();
        let nodo = Normal::new(0.0, cfg.sigma_odometer_m_s).unwrap();
        for k in 1..=12_000u64 {
            let fm = f_true + b_a + Vector3::from_fn(|_, _| na.sample(&mut rng));
            let wm = w_true + b_g + Vector3::from_fn(|_, _| ng.sample(&mut rng));
            f.propagate(&imu(k * dt_us, fm, wm)).unwrap();
            if k % 20 == 0 {
                let vel_trace = f.p.get().fixed_view::<3, 3>(VEL, VEL).trace();
                let s = OdometerSample { t: f.time(), speed_m_s: (1.0 + k_true) * speed + nodo.sample(&mut rng) };
                f.update_odometer(&s).unwrap();
                assert!(f.p.get().fixed_view::<3, 3>(VEL, VEL).trace() < vel_trace, "an odometer update must shrink P_vv");
            }
        }
        let t = f.time().as_secs_f64();
        let truth = InsState {
            pos_ned_m: v_true * t,
            vel_ned_m_s: v_true,
            att_frd_to_ned: r_true,
            accel_bias_frd_m_s2: b_a,
            gyro_bias_frd_rad_s: b_g,
            odometer_scale_error: k_true,
        };
        let e = state_error(&truth, &f.x);
        for i in [POS, POS + 1, POS + 2, VEL, VEL + 1, VEL + 2, HEADING_INDEX, ODO_SCALE] {
            let z = e[i] / f.p.get()[(i, i)].sqrt();
            worst = worst.max(z.abs());
            assert!(z.abs() < 4.0, "seed {seed}: error state {i}: {} is {z} sigma", e[i]);
        }
        // The odometer makes the scale factor and the body-frame velocity well known (not the
        // NED velocity: the yaw error is unobservable on a straight road, V sigma_yaw ~ 0.1 m/s).
        assert!(f.p.get()[(ODO_SCALE, ODO_SCALE)].sqrt() < 0.5 * sigma0.odometer_scale);
        let h = f.odometer_measurement(&OdometerSample { t: f.time(), speed_m_s: speed }).unwrap().h;
        let p_body = &h * to_dmatrix(f.p.get()) * h.transpose();
        for axis in 0..3 {
            assert!(p_body[(axis, axis)].sqrt() < 0.03, "body velocity sigma {axis}: {}", p_body[(axis, axis)].sqrt());
        }
    }
    assert!(worst > 0.3, "errors suspiciously small: {worst}");
}

/// Test 7: bad samples are typed errors and leave the filter bit-identical.
#[test]
fn bad_imu_samples_are_rejected_without_change() {
    let cfg = noise_free(45.0);
    let r = yaw_q(0.2);
    let f_b = r.inverse_transform_vector(&-cfg.gravity_ned_m_s2());
    let w_b = r.inverse_transform_vector(&cfg.earth_rate_ned_rad_s());
    let mut f = InsFilter::new(cfg, TimeUs(1_000_000), InsState::at_rest(r), small_sigma()).unwrap();
    f.propagate(&imu(1_005_000, f_b, w_b)).unwrap();
    let before = f;
    let nan_f = Vector3::new(f64::NAN, 0.0, -G);
    let cases = [
        (imu(1_010_000, nan_f, w_b), EstimationError::NonFinite { what: "IMU specific force" }),
        (imu(1_010_000, f_b, Vector3::new(0.0, f64::INFINITY, 0.0)), EstimationError::NonFinite { what: "IMU angular rate" }),
        (
            imu(1_000_000, f_b, w_b),
            EstimationError::TimeWentBackwards { what: "IMU sample", from_us: 1_005_000, to_us: 1_000_000 },
        ),
        (imu(1_005_000, f_b, w_b), EstimationError::InvalidValue { what: "IMU time step (s)", value: 0.0 }),
        (imu(3_005_000, f_b, w_b), EstimationError::InvalidValue { what: "IMU sample gap (s)", value: 2.0 }),
        (
            imu(1_010_000, Vector3::new(0.0, 0.0, -600.0), w_b),
            EstimationError::InvalidValue { what: "IMU specific force magnitude (m/s^2)", value: 600.0 },
        ),
        (
            imu(1_010_000, f_b, Vector3::new(50.0, 0.0, 0.0)),
            EstimationError::InvalidValue { what: "IMU angular rate magnitude (rad/s)", value: 50.0 },
        ),
    ];
    for (s, expected) in cases {
        assert_eq!(f.propagate(&s), Err(expected));
        assert_eq!(f, before);
    }
    let odo = OdometerSample { t: f.time(), speed_m_s: f64::NAN };
    assert_eq!(f.update_odometer(&odo), Err(EstimationError::NonFinite { what: "odometer speed" }));
    assert_eq!(f, before);
    // And a good sample still goes through afterwards.
    f.propagate(&imu(1_010_000, f_b, w_b)).unwrap();
    assert_eq!(f.time(), TimeUs(1_010_000));
}

/// A step whose covariance overflows is refused, naming it, and leaves the filter as it was:
/// state, covariance, `Psi`, and the cached Earth turn of the new step length alike.
#[test]
fn a_covariance_that_overflows_is_refused_without_change() {
    let cfg = InsConfig { covariance_decimation: 1, ..noise_free(45.0) };
    let r = yaw_q(0.2);
    let f_b = r.inverse_transform_vector(&-cfg.gravity_ned_m_s2());
    let w_b = r.inverse_transform_vector(&cfg.earth_rate_ned_rad_s());
    // Position variances near f64::MAX: finite, but any step's sum overflows.
    let huge = InsInitialSigma { pos_ned_m: Vector3::repeat(1e154), ..small_sigma() };
    let mut f = InsFilter::new(cfg, TimeUs(1_000_000), InsState::at_rest(r), huge).unwrap();
    let before = f;
    assert_eq!(f.propagate(&imu(1_005_000, f_b, w_b)), Err(EstimationError::NonFinite { what: "propagated INS covariance" }));
    assert_eq!(f, before);
}

#[test]
fn config_parsing_defaults_and_validation() {
    let cfg: InsConfig = toml::from_str(
        "latitude_deg = 45.0\naccel_noise_density_m_s2_per_sqrt_hz = 1e-3\ngyro_noise_density_rad_s_per_sqrt_hz = 5e-5\n",
    )
    .unwrap();
    assert_eq!(cfg.gravity_m_s2, 9.80665);
    assert_eq!(cfg.sigma_odometer_m_s, 0.2);
    assert_eq!(cfg.max_imu_gap_s, 0.5);
    assert_eq!(cfg.accel_bias_random_walk_m_s3_per_sqrt_hz, 0.0);
    assert!(cfg.validate().is_ok());
    let unknown = toml::from_str::<InsConfig>(
        "latitude_deg = 45.0\naccel_noise_density_m_s2_per_sqrt_hz = 1e-3\ngyro_noise_density_rad_s_per_sqrt_hz = 5e-5\nsigma_odo = 1.0\n",
    );
    assert!(unknown.is_err());
    let bad = InsConfig { sigma_nhc_lateral_m_s: -1.0, ..cfg };
    assert_eq!(bad.validate(), Err(EstimationError::InvalidValue { what: "sigma_nhc_lateral_m_s", value: -1.0 }));
    let bad = InsConfig { gyro_noise_density_rad_s_per_sqrt_hz: f64::NAN, ..cfg };
    assert!(matches!(bad.validate(), Err(EstimationError::InvalidValue { what: "gyro_noise_density_rad_s_per_sqrt_hz", .. })));
    let bad = InsConfig { latitude_deg: 91.0, ..cfg };
    assert!(InsFilter::new(bad, TimeUs(0), InsState::at_rest(yaw_q(0.0)), small_sigma()).is_err());
    let sigma = InsInitialSigma { att_ned_rad: Vector3::new(0.0, -1.0, 0.0), ..small_sigma() };
    assert_eq!(
        InsFilter::new(cfg, TimeUs(0), InsState::at_rest(yaw_q(0.0)), sigma).unwrap_err(),
        EstimationError::InvalidValue { what: "initial attitude sigma", value: -1.0 }
    );
    let mut x = InsState::at_rest(yaw_q(0.0));
    x.vel_ned_m_s.x = f64::NAN;
    assert!(InsFilter::new(cfg, TimeUs(0), x, small_sigma()).is_err());
    // A zero quaternion (possible from a file) is rejected; a non-unit one is normalised.
    let zero = InsState {
        att_frd_to_ned: UnitQuaternion::new_unchecked(nalgebra::Quaternion::new(0.0, 0.0, 0.0, 0.0)),
        ..InsState::at_rest(yaw_q(0.0))
    };
    assert_eq!(
        InsFilter::new(cfg, TimeUs(0), zero, small_sigma()).unwrap_err(),
        EstimationError::NonFinite { what: "initial INS state" }
    );
    let long = InsState {
        att_frd_to_ned: UnitQuaternion::new_unchecked(yaw_q(0.4).into_inner() * 3.0),
        ..InsState::at_rest(yaw_q(0.0))
    };
    let f = InsFilter::new(cfg, TimeUs(0), long, small_sigma()).unwrap();
    assert!((f.attitude().into_inner().norm() - 1.0).abs() < 1e-15);
    assert!((f.yaw_rad() - 0.4).abs() < 1e-15);
    // Initial covariance: the squared sigmas on the diagonal.
    let f = InsFilter::new(cfg, TimeUs(0), InsState::at_rest(yaw_q(0.0)), small_sigma()).unwrap();
    assert_eq!(f.covariance16()[(HEADING_INDEX, HEADING_INDEX)], 0.05 * 0.05);
    assert_eq!(f.covariance16()[(ODO_SCALE, ODO_SCALE)], 0.01 * 0.01);
    assert_eq!(f.psi16(), Matrix16::identity());
}

/// Two INS vehicles in a team: odometer updates and a range event go through every method, and
/// the event shrinks the position covariance along the line of sight.
#[test]
fn works_in_a_team() {
    use crate::estimation::{CoopMeasurement, Method, Team};
    let cfg = InsConfig { latitude_deg: 45.0, ..InsConfig::default() };
    let (w_ie, g) = (cfg.earth_rate_ned_rad_s(), cfg.gravity_ned_m_s2());
    let make = |north_m: f64| {
        let x = InsState { pos_ned_m: Vector3::new(north_m, 0.0, 0.0), ..InsState::at_rest(yaw_q(0.0)) };
        InsFilter::new(cfg, TimeUs(0), x, small_sigma()).unwrap()
    };
    let f_b = -g;
    let w_b = w_ie;
    for method in Method::ALL {
        let mut team = Team::new(method, vec![(1, make(0.0)), (2, make(50.0))]).unwrap();
        for k in 1..=200u64 {
            for id in [1, 2] {
                team.filter_mut(id).unwrap().propagate(&imu(k * 5_000, f_b, w_b)).unwrap();
            }
            if k % 20 == 0 {
                for id in [1, 2] {
                    let f = team.filter(id).unwrap();
                    let meas = f.odometer_measurement(&OdometerSample { t: f.time(), speed_m_s: 0.0 }).unwrap();
                    team.local_update(id, &meas).unwrap();
                }
            }
        }
        let before = team.filter(2).unwrap().covariance16()[(0, 0)];
        let ranges = [
            CoopMeasurement::Range { from: 1, to: 2, range_m: 50.3, sigma_m: 0.1 },
            CoopMeasurement::RangeBearing {
                from: 1,
                to: 2,
                range_m: 50.3,
                bearing_rad: 0.01,
                sigma_range_m: 0.1,
                sigma_bearing_rad: 0.01,
            },
        ];
        team.cooperative_event(&ranges).unwrap();
        let after = team.filter(2).unwrap().covariance16()[(0, 0)];
        let f2 = team.filter(2).unwrap();
        match method {
            Method::DeadReckoning => assert_eq!(after, before, "{method}"),
            // Covariance intersection inflates the whole 16-state covariance by 1/w before the
            // update, so it need not shrink anything here; it only has to run.
            Method::CovarianceIntersection => {}
            _ => assert!(after < 0.6 * before, "{method}: {before} -> {after}"),
        }
        if method.needs_psi() {
            // Psi restarted at the reset Jacobian of the write-back: identity off the attitude block.
            let psi = f2.psi16();
            let mut off = psi;
            off.fixed_view_mut::<3, 3>(ATT, ATT).fill(0.0);
            let mut eye = Matrix16::identity();
            eye.fixed_view_mut::<3, 3>(ATT, ATT).fill(0.0);
            assert_eq!(off, eye, "{method}");
            assert_ne!(psi, Matrix16::identity(), "{method}: the event must have rotated the attitude");
        }
        if method != Method::DeadReckoning {
            assert!(f2.position_ned_m().x > 50.0, "{method}: moved toward the measured range");
        }
    }
}

/// With `covariance_decimation = N`, the covariance and Psi step once every N samples with the
/// summed `F dt`; reading them mid-interval brings them to the present without changing the
/// filter; and after a turn the result stays close to stepping at every sample (only
/// second-order terms in `F dt` differ).
#[test]
fn decimated_covariance_propagation() {
    let config = InsConfig { latitude_deg: 34.7, covariance_decimation: 4, ..InsConfig::default() };
    let every = InsConfig { covariance_decimation: 1, ..config };
    let start = |c: InsConfig| {
        let mut x = InsState::at_rest(yaw_q(0.3));
        x.vel_ned_m_s = x.att_frd_to_ned * Vector3::new(10.0, 0.0, 0.0);
        InsFilter::new(c, TimeUs(0), x, small_sigma()).unwrap()
    };
    let (mut a, mut b) = (start(config), start(every));
    let sample = |k: u64| imu(5_000 * k, Vector3::new(0.2, 1.0, -9.80665), Vector3::new(0.0, 0.0, 0.1));
    for k in 1..=3 {
        a.propagate(&sample(k)).unwrap();
        b.propagate(&sample(k)).unwrap();
    }
    // Mid-interval: three steps pending. Reading is pure.
    let before = a;
    let (p_mid, psi_mid) = (a.covariance16(), a.psi16());
    assert_eq!(a, before);
    // Stepping three samples at once drops the second-order products of F dt, the largest of
    // which is position-attitude: dt * dt * |f| ~ 2.5e-5 * 9.8 per pair of steps, times 3 pairs.
    let second_order = 3.0 * 0.005 * 0.005 * 9.9;
    assert!(rel_err(&p_mid, &b.covariance16()) < second_order, "{}", rel_err(&p_mid, &b.covariance16()));
    assert!(rel_err(&psi_mid, &b.psi16()) < second_order, "{}", rel_err(&psi_mid, &b.psi16()));
    assert!(rel_err(&psi_mid, &b.psi16()) > 0.0, "the summed transition is not the product");
    for k in 4..=400 {
        a.propagate(&sample(k)).unwrap();
        b.propagate(&sample(k)).unwrap();
    }
    assert_eq!(a.x, b.x, "the nominal state integrates every sample either way");
    // Over a horizon t, stepping by h = N dt is a rectangular rule of step h: the position-
    // attitude chain (~ f t^2 / 2) is off by ~ h / t relative, against dt / t stepping every
    // sample. Here h / t = 4 * 0.005 / 2 = 1% (it fades as t grows: 0.005% over 380 s).
    let h_over_t = 4.0 * 0.005 / 2.0;
    assert!(rel_err(&a.covariance16(), &b.covariance16()) < 2.0 * h_over_t, "{}", rel_err(&a.covariance16(), &b.covariance16()));
    assert!(rel_err(&a.psi16(), &b.psi16()) < 2.0 * h_over_t, "{}", rel_err(&a.psi16(), &b.psi16()));
    // A local update brings the covariance to the present first and keeps P and Psi in step.
    for k in 401..=402 {
        a.propagate(&sample(k)).unwrap();
    }
    let p_now = a.covariance16();
    let meas = a.odometer_measurement(&OdometerSample { t: a.time(), speed_m_s: 10.0 }).unwrap();
    let expected = kalman::local_update(&to_dmatrix(&p_now), &meas).unwrap();
    a.update_local(&meas).unwrap();
    let g = reset_jacobian(&to_vector16(&expected.dx));
    assert!(rel_err(&a.covariance16(), &reset_covariance(&g, &to_matrix16(&expected.p))) < 1e-9);
    assert_eq!(
        InsConfig { covariance_decimation: 0, ..config }.validate(),
        Err(EstimationError::InvalidValue { what: "covariance_decimation", value: 0.0 })
    );
}

/// The fixed-size local update gives what the general one gives, bit for bit (compared through
/// `{:?}`, which tells `-0.0` from `0.0`): every size it takes, with and without `Psi`, `H`
/// with exact zeros (as real Jacobians have) and a row of zeros, covariances at several scales.
#[test]
fn fixed_size_local_update_equals_the_general_one_bit_for_bit() {
    use nalgebra::{DMatrix, DVector};
    let mut rng = ChaCha8Rng::seed_from_u64(16);
    let n = Normal::new(0.0, 1.0).unwrap();
    let cfg = noise_free(45.0);
    let base = InsFilter::new(cfg, TimeUs(1_000_000), InsState::at_rest(yaw_q(0.3)), small_sigma()).unwrap();
    let mut compared = 0;
    for trial in 0..60 {
        let m = 1 + trial % local_update::MAX_ROWS;
        let scale = [1e-6, 1.0, 1e4][trial % 3];
        let mut f = base;
        f.p.set(random_spd(&mut rng) * scale);
        f.psi_t.set(random_matrix(&mut rng));
        f.track_psi = trial % 2 == 0;
        let mut h = DMatrix::from_fn(m, ERROR_DIM, |_, _| if n.sample(&mut rng) > 0.3 { 0.0 } else { n.sample(&mut rng) });
        if trial % 7 == 3 {
            h.row_mut(0).fill(0.0); // a row of signed-zero sums
        }
        let a = DMatrix::from_fn(m, m, |_, _| n.sample(&mut rng));
        let meas = LinearizedMeasurement {
            h,
            residual: DVector::from_fn(m, |_, _| 1e-3 * n.sample(&mut rng)),
            r: &a * a.transpose() * 0.1 + DMatrix::identity(m, m) * 0.01,
        };
        let (mut small, mut general) = (f, f);
        let (ds, dg) = (small.update_local_small(&meas), general.update_local_general(&meas));
        assert_eq!(format!("{ds:?}"), format!("{dg:?}"), "trial {trial}: diagnostics");
        assert_eq!(format!("{small:?}"), format!("{general:?}"), "trial {trial}: filter");
        compared += ds.is_ok() as usize;
    }
    assert!(compared >= 50, "only {compared} of 60 updates went through");
}

/// The covariance and `Psi` live in two slots each (the step computes into the spare one): a
/// refused update, which has written its scratch into the spare slots, leaves a filter that
/// goes on exactly as its twin that never saw it, through propagation and updates alike.
#[test]
fn a_refused_update_leaves_no_trace_in_the_spare_slots() {
    let mut rng = ChaCha8Rng::seed_from_u64(17);
    let mut a = busy_filter(&mut rng);
    let b0 = a;
    let good = a.odometer_measurement(&OdometerSample { t: a.time(), speed_m_s: 4.0 }).unwrap();
    let mut bad = good.clone();
    bad.residual[0] = 1e300; // finite, but the correction overflows the injected state
    assert_eq!(a.update_local(&bad), Err(EstimationError::NonFinite { what: "INS state after error injection" }));
    assert_eq!(a, b0);
    let mut b = b0;
    let f_b = Vector3::new(0.3, -0.2, -9.8);
    let w_b = Vector3::new(0.01, 0.02, -0.1);
    for k in 1..=9u64 {
        let s = imu(1_000_000 + 5_000 * k, f_b, w_b);
        a.propagate(&s).unwrap();
        b.propagate(&s).unwrap();
        if k % 3 == 0 {
            let meas = a.odometer_measurement(&OdometerSample { t: a.time(), speed_m_s: 4.0 }).unwrap();
            a.update_local(&meas).unwrap();
            b.update_local(&meas).unwrap();
        }
    }
    assert_eq!(format!("{a:?}"), format!("{b:?}"));
    assert_eq!(a.covariance16(), b.covariance16());
    assert_eq!(a.psi16(), b.psi16());
}

/// The INS's own snapshot (one look at the covariance and `Psi`) is the trait's composition of
/// `covariance`, `psi` and `geometry`, with and without pending propagation steps.
#[test]
fn the_snapshot_is_the_composition_of_its_parts() {
    let mut rng = ChaCha8Rng::seed_from_u64(18);
    let mut f = busy_filter(&mut rng);
    f.config.covariance_decimation = 4;
    let mut pending_seen = 0;
    for k in 1..=6u64 {
        f.propagate(&imu(1_000_000 + 5_000 * k, Vector3::new(0.3, -0.2, -9.8), Vector3::new(0.01, 0.02, -0.1))).unwrap();
        let s = f.snapshot(7);
        let want = Snapshot { id: 7, geometry: f.geometry(), covariance: f.covariance(), psi: f.psi() };
        assert_eq!(format!("{s:?}"), format!("{want:?}"), "after {k} steps (pending: {})", f.pending.is_some());
        pending_seen += f.pending.is_some() as usize;
    }
    assert_eq!(pending_seen, 5, "every step but the fourth leaves propagation pending");
}
