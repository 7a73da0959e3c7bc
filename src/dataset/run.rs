//! Every method over a real data set, scored against its ground truth. Pure computation.
//!
//! # The model
//!
//! - **Motion**: each robot is the command-driven filter of [`crate::estimation::commanded`]
//!   (pose, speed scale, yaw-rate bias; first-estimate Jacobians with
//!   [`NoiseModel::first_estimates`]) driven by its commands: a command holds until the next
//!   one, and one older than [`NoiseModel::stale_command_s`] means the robot stopped (MRCLAM's
//!   robots log commands at about 67 Hz; the longest silence is about 1 s). [`drive_samples`]
//!   turns the commands into wheel samples (none longer than 0.5 s), zero speed before the first
//!   command, and [`lagged`] passes them through the first-order lag of
//!   [`NoiseModel::command_lag_s`] with which the robots execute them.
//! - **Landmarks**: a range and bearing to a landmark of known position is a local update of the
//!   observer ([`landmark_measurement`]); the surveyed position's uncertainty adds to the noise.
//! - **Teammates**: a range and bearing to a teammate is a cooperative measurement
//!   ([`robot_measurement`]: its Jacobian at the first estimates). Each camera image that holds a teammate (one observer,
//!   one time stamp) is one **ranging epoch**: the paper's rule, every platform broadcasts its
//!   state, covariance and recursive coefficient matrix at each epoch, maps onto asynchronous
//!   observations as "every robot broadcasts whenever any robot sees a teammate". The whole team
//!   takes the joint update (dcl, centralized; the naive filter and covariance intersection
//!   update the two robots involved). [`broadcast_bytes`] is what that costs.
//! - **Gating and robust weights**: every measurement passes a chi-square gate at
//!   [`NoiseModel::gate_probability`] against the prior the method itself holds, and one that
//!   passes it with a NIS above [`NoiseModel::huber_nis`] gets a Huber weight
//!   ([`Team::robust_local_update`], [`Team::robust_cooperative_event`]): the same rule for
//!   every method, counted per kind ([`Outcome::landmark_gated`], ...).
//! - **Start**: every robot starts at its first ground-truth pose at the data set's first
//!   ground-truth time, with the initial sigmas of the noise model.
//!
//! # Regimes
//!
//! [`Regime::NoLandmarks`]: relative measurements only. [`Regime::MapBlind`]: landmarks for the
//! robots of [`Settings::map_robots`] only, the others rely on their teammates.
//! [`Regime::FullMap`]: every robot sees landmarks. Dead reckoning uses no observation at all in
//! any regime (odometry only), so it is the same run in all three.
//!
//! # Scoring
//!
//! At every [`Settings::score_period_us`] from the start, each robot's filter is brought to that
//! instant and compared with its ground truth, interpolated between samples at most
//! [`super::MAX_TRUTH_GAP_US`] apart; an instant in a longer gap, or outside the robot's ground
//! truth (Robot1 of data set 6 loses it 128 s before the end), is masked and counted. Team
//! position RMSE and heading RMSE are over every scored robot-instant; NEES is that of the
//! 3-state error `[dN, dE, dyaw]` against the filter's covariance.

use nalgebra::{DMatrix, DVector, Vector3};

use super::noise::NoiseModel;
use super::{Dataset, Landmark, MAX_TRUTH_GAP_US, Observation, Target, truth_at};
use crate::estimation::commanded::{self, CommandedConfig, CommandedFilter, CommandedSigma};
use crate::estimation::consistency::nees;
use crate::estimation::unicycle::wrap_angle;
use crate::estimation::{
    CoopMeasurement, EstimationError, LinearizedMeasurement, Method, PlatformFilter, PlatformId, Team, UpdateOptions, WheelSample,
};
use crate::time::TimeUs;

/// Which observations the robots use.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub enum Regime {
    NoLandmarks,
    MapBlind,
    FullMap,
}

impl Regime {
    pub const ALL: [Regime; 3] = [Regime::NoLandmarks, Regime::MapBlind, Regime::FullMap];

    pub fn name(self) -> &'static str {
        match self {
            Regime::NoLandmarks => "no-landmarks",
            Regime::MapBlind => "map-blind",
            Regime::FullMap => "full-map",
        }
    }

    pub fn from_name(s: &str) -> Option<Regime> {
        Regime::ALL.into_iter().find(|r| r.name() == s)
    }
}

/// How a data set is run.
#[derive(Debug, Clone, PartialEq)]
pub struct Settings {
    pub noise: NoiseModel,
    /// The robots that see landmarks in [`Regime::MapBlind`].
    pub map_robots: Vec<PlatformId>,
    /// Scoring period, µs.
    pub score_period_us: u64,
    /// Keep every robot's estimate at every scoring instant ([`Outcome::track`]).
    pub keep_track: bool,
}

impl Settings {
    /// The noise model given, landmarks for robots 1 and 2 in the map-blind regime, scored at
    /// 10 Hz.
    pub fn new(noise: NoiseModel) -> Self {
        Settings { noise, map_robots: vec![1, 2], score_period_us: 100_000, keep_track: false }
    }
}

/// One robot's score.
#[derive(Debug, Clone, PartialEq)]
pub struct RobotScore {
    pub id: PlatformId,
    pub pos_rmse_m: f64,
    pub heading_rmse_deg: f64,
    /// Scored instants.
    pub samples: usize,
    /// Instants without ground truth.
    pub masked: usize,
}

/// A robot's estimate at one scoring instant.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct TrackPoint {
    pub t: TimeUs,
    pub n_m: f64,
    pub e_m: f64,
    pub yaw_rad: f64,
    /// Covariance of `[N, E, yaw]`.
    pub cov: nalgebra::Matrix3<f64>,
}

/// One method in one regime.
#[derive(Debug, Clone, PartialEq)]
pub struct Outcome {
    pub regime: Regime,
    pub method: Method,
    pub robots: Vec<RobotScore>,
    /// Over every scored robot-instant.
    pub pos_rmse_m: f64,
    pub heading_rmse_deg: f64,
    pub avg_nees: f64,
    /// Average NEES of the position alone (2 states) and of the heading alone (1 state).
    pub avg_nees_position: f64,
    pub avg_nees_heading: f64,
    /// Share of robot-instants whose NEES is inside the 95% chi-square bound (3 states).
    pub in_bound_share: f64,
    pub samples: usize,
    pub masked: usize,
    /// Landmark observations applied and left out by the gate.
    pub landmark_updates: usize,
    pub landmark_gated: usize,
    /// Teammate observations applied and left out by the gate.
    pub robot_updates: usize,
    pub robot_gated: usize,
    /// Observations applied with a Huber weight below 1, and below 0.5 (landmarks, teammates).
    pub landmark_weighted: usize,
    pub landmark_weight_below_half: usize,
    pub robot_weighted: usize,
    pub robot_weight_below_half: usize,
    /// Ranging epochs (camera images holding a teammate) the method ran.
    pub epochs: usize,
    /// Updates refused as numerically unusable (left out, counted).
    pub refused: usize,
    /// The innovations of the landmark updates and of the teammate (joint) updates the method
    /// applied: what [`super::identify`] fits the noise to, with no ground truth.
    pub landmark_innovations: InnovationStats,
    pub robot_innovations: InnovationStats,
    /// The same for the fresh observations only ([`FRESH_AFTER_S`]; a teammate update when
    /// every observation of its image is fresh): a consistent filter's NIS per scalar is 1 on
    /// them whatever the correlation of a burst's errors.
    pub landmark_fresh: InnovationStats,
    pub robot_fresh: InnovationStats,
    /// Per robot, its estimate at every scoring instant (with [`Settings::keep_track`]).
    pub track: Vec<(PlatformId, Vec<TrackPoint>)>,
}

/// Sums over the updates of one kind of observation, each update a range and bearing (or a
/// stack of them: one joint update per image).
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct InnovationStats {
    /// Updates applied.
    pub updates: usize,
    /// Scalars in them (2 per observation).
    pub scalars: usize,
    /// Sum of the normalised innovations squared `r^T S^-1 r`.
    pub nis_sum: f64,
    /// Sum of their Huber-robustified values ([`huber_nis`]).
    pub nis_huber_sum: f64,
    /// Sum of `ln det S`.
    pub ln_det_s_sum: f64,
    /// Sum of the range innovations and of the range and bearing innovations squared over their
    /// predicted variances (`r_i^2 / S_ii`), with their count.
    pub range_sum_m: f64,
    pub range_z2_sum: f64,
    pub bearing_z2_sum: f64,
    pub observations: usize,
}

impl InnovationStats {
    fn add(&mut self, d: &crate::estimation::UpdateDiagnostics) {
        let m = d.innovation.len();
        self.updates += 1;
        self.scalars += m;
        self.nis_sum += d.nis;
        self.nis_huber_sum += huber_nis(d.nis, m);
        // S is positive definite (the update factorised it).
        self.ln_det_s_sum += d.innovation_cov.clone().cholesky().map_or(f64::NAN, |c| 2.0 * c.l().diagonal().map(f64::ln).sum());
        for k in (0..m).step_by(2) {
            self.range_sum_m += d.innovation[k];
            self.range_z2_sum += d.innovation[k].powi(2) / d.innovation_cov[(k, k)];
            if k + 1 < m {
                self.bearing_z2_sum += d.innovation[k + 1].powi(2) / d.innovation_cov[(k + 1, k + 1)];
            }
            self.observations += 1;
        }
    }

    /// Mean NIS per scalar (1 for a consistent filter).
    pub fn nis_per_scalar(&self) -> f64 {
        self.nis_sum / self.scalars.max(1) as f64
    }
}

/// The Huber loss of a NIS of `m` scalars: the NIS up to `c = 4.6 m` (the 99% quantile of a
/// chi-square of 2 degrees of freedom, per pair of scalars), `2 sqrt(c NIS) - c` above it, so
/// that a gross outlier weighs like a distance, not like its square.
pub fn huber_nis(nis: f64, m: usize) -> f64 {
    let c = 4.605 * m as f64;
    if nis <= c { nis } else { 2.0 * (c * nis).sqrt() - c }
}

/// Why a run stopped.
#[derive(Debug, thiserror::Error)]
pub enum RunError {
    #[error("{regime} {method}, robot {robot}, t = {t}: {source}")]
    Filter { regime: &'static str, method: Method, robot: PlatformId, t: TimeUs, source: EstimationError },
    #[error("{0}")]
    Settings(String),
}

/// A robot's wheel samples from `t0` to `t_end` (see the module documentation): each the
/// command in force over its interval, zero speed before the first command and once the last
/// one is older than `stale_us`, no interval longer than 0.5 s.
pub fn drive_samples(commands: &[super::Command], t0: TimeUs, t_end: TimeUs, stale_us: u64) -> Vec<WheelSample> {
    const PIECE_US: u64 = 500_000;
    let mut out = Vec::with_capacity(commands.len() + 16);
    // Constant pieces: (from, to, speed, yaw rate).
    let mut push = |from: u64, to: u64, v: f64, w: f64| {
        let mut a = from;
        while a < to {
            let b = (a + PIECE_US).min(to);
            out.push(WheelSample { t: TimeUs(b), speed_m_s: v, yaw_rate_rad_s: w });
            a = b;
        }
    };
    let start = t0.0;
    let end = t_end.0;
    let first = commands.first().map_or(end, |c| c.t.0.clamp(start, end));
    push(start, first, 0.0, 0.0);
    for (k, c) in commands.iter().enumerate() {
        let from = c.t.0.max(start);
        let next = commands.get(k + 1).map_or(end, |n| n.t.0).min(end);
        if next <= from {
            continue;
        }
        let valid_to = (c.t.0 + stale_us).clamp(from, next);
        push(from, valid_to, c.speed_m_s, c.yaw_rate_rad_s);
        push(valid_to, next, 0.0, 0.0);
    }
    out
}

/// `samples` (from [`drive_samples`], starting at `t0` at rest) as the robot executes them when
/// it follows its commands with a first-order lag of time constant `lag_s`: each interval (cut
/// in pieces of at most 0.1 s) carries the mean of the lagged speed and yaw rate over it, the
/// lag's state carried across; a lagged value under 1e-6 is zero (the robot has stopped). A
/// zero lag returns the samples unchanged.
pub fn lagged(samples: &[WheelSample], t0: TimeUs, lag_s: f64) -> Vec<WheelSample> {
    if lag_s.is_nan() || lag_s <= 0.0 {
        return samples.to_vec();
    }
    const PIECE_US: u64 = 100_000;
    let mut out = Vec::with_capacity(samples.len() + 16);
    let (mut y_v, mut y_w) = (0.0f64, 0.0f64);
    let mut prev = t0.0;
    let snap = |x: f64| if x.abs() < 1e-6 { 0.0 } else { x };
    for s in samples {
        let mut a = prev;
        while a < s.t.0 {
            let b = (a + PIECE_US).min(s.t.0);
            let dt = (b - a) as f64 * 1e-6;
            let e = (-dt / lag_s).exp();
            let k = lag_s / dt * (1.0 - e);
            let (mean_v, mean_w) = (s.speed_m_s + (y_v - s.speed_m_s) * k, s.yaw_rate_rad_s + (y_w - s.yaw_rate_rad_s) * k);
            y_v = s.speed_m_s + (y_v - s.speed_m_s) * e;
            y_w = s.yaw_rate_rad_s + (y_w - s.yaw_rate_rad_s) * e;
            out.push(WheelSample { t: TimeUs(b), speed_m_s: snap(mean_v), yaw_rate_rad_s: snap(mean_w) });
            a = b;
        }
        prev = prev.max(s.t.0);
    }
    out
}

/// The filter configuration of a run (the same for every robot, method and regime).
pub fn commanded_config(noise: &NoiseModel) -> CommandedConfig {
    CommandedConfig {
        speed_noise_m_s_per_sqrt_hz: noise.speed_noise_m_s_per_sqrt_hz,
        yaw_rate_noise_rad_s_per_sqrt_hz: noise.yaw_rate_noise_rad_s_per_sqrt_hz,
        speed_scale_walk_per_sqrt_s: noise.speed_scale_walk_per_sqrt_s,
        yaw_rate_bias_walk_rad_s_per_sqrt_s: noise.yaw_rate_bias_walk_rad_s_per_sqrt_s,
        max_gap_s: 1.0,
        first_estimates: noise.first_estimates,
    }
}

/// The initial sigmas of a run.
pub fn commanded_sigma(noise: &NoiseModel) -> CommandedSigma {
    CommandedSigma {
        pos_m: noise.initial_position_sigma_m,
        yaw_rad: noise.initial_yaw_sigma_rad,
        speed_scale: noise.initial_speed_scale_sigma,
        yaw_rate_bias_rad_s: noise.initial_yaw_rate_bias_sigma_rad_s,
    }
}

/// The range and bearing of landmark `lm` as a local measurement of the observer at `f`
/// (residual `[range - bias - predicted, wrapped bearing residual]`, Jacobian in the filter's
/// error state, zero on the speed scale and the bias); `None` when the estimate sits on the
/// landmark. The map is known, so the absolute pose is observable: the Jacobian is taken at the
/// current estimate. The noise is the model's times `inflation` ([`CorrelatedErrors`]; 1: as
/// the model says).
pub fn landmark_measurement(
    f: &CommandedFilter,
    lm: &Landmark,
    obs: &Observation,
    noise: &NoiseModel,
    inflation: f64,
) -> Option<LinearizedMeasurement> {
    let p = f.position_ned_m();
    let (dn, de) = (lm.n_m - p[0], lm.e_m - p[1]);
    let rho2 = dn * dn + de * de;
    let rho = rho2.sqrt();
    if rho < 1e-6 {
        return None;
    }
    let predicted_bearing = de.atan2(dn) - f.yaw_rad();
    let mut h = DMatrix::zeros(2, commanded::DIM);
    h.view_mut((0, 0), (2, 3)).copy_from_slice(&[-dn / rho, de / rho2, -de / rho, -dn / rho2, 0.0, -1.0]);
    let residual =
        DVector::from_vec(vec![obs.range_m - noise.landmark_range_bias_m - rho, wrap_angle(obs.bearing_rad - predicted_bearing)]);
    let lm_var = 0.5 * (lm.sigma_n_m.powi(2) + lm.sigma_e_m.powi(2));
    let r = DMatrix::from_diagonal(&DVector::from_vec(vec![
        noise.landmark_range_sigma_m.powi(2) + lm_var,
        noise.landmark_bearing_sigma_rad.powi(2) + lm_var / rho2,
    ])) * inflation;
    Some(LinearizedMeasurement { h, residual, r })
}

/// A teammate observation (`observer` at `from` sees `to` at `target`) as a cooperative
/// measurement, the range's bias removed: the residual at the current estimates, the Jacobian at
/// the filters' linearization points (their first estimates with
/// [`NoiseModel::first_estimates`], see [`crate::estimation::commanded`]), the noise the
/// model's times `inflation`. `None` when the two estimates coincide.
pub fn robot_measurement(
    from: &CommandedFilter,
    target: &CommandedFilter,
    observer: PlatformId,
    to: PlatformId,
    obs: &Observation,
    noise: &NoiseModel,
    inflation: f64,
) -> Option<CoopMeasurement> {
    let (a, b) = (from.position_ned_m(), target.position_ned_m());
    let (dn, de) = (b[0] - a[0], b[1] - a[1]);
    let rho = (dn * dn + de * de).sqrt();
    let (la, lb) = (from.linearization_position_ned_m(), target.linearization_position_ned_m());
    let (ln, le) = (lb[0] - la[0], lb[1] - la[1]);
    let lrho2 = ln * ln + le * le;
    let lrho = lrho2.sqrt();
    if rho < 1e-6 || lrho < 1e-6 {
        return None;
    }
    let residual = DVector::from_vec(vec![
        obs.range_m - noise.robot_range_bias_m - rho,
        wrap_angle(obs.bearing_rad - (de.atan2(dn) - from.yaw_rad())),
    ]);
    let rows = [[ln / lrho, le / lrho], [-le / lrho2, ln / lrho2]];
    let (mut h_from, mut h_to) = (DMatrix::zeros(2, commanded::DIM), DMatrix::zeros(2, commanded::DIM));
    for row in 0..2 {
        for axis in 0..2 {
            h_from[(row, axis)] = -rows[row][axis];
            h_to[(row, axis)] = rows[row][axis];
        }
    }
    h_from[(1, 2)] = -1.0;
    let r = DMatrix::from_diagonal(&DVector::from_vec(vec![
        noise.robot_range_sigma_m.powi(2),
        noise.robot_bearing_sigma_rad.powi(2),
    ])) * inflation;
    Some(CoopMeasurement::Linear { blocks: vec![(observer, h_from), (to, h_to)], residual, r })
}

/// An observation is fresh when its observer has not seen its target for this long, s: its error
/// is then nearly independent of the errors the filter has taken in, so its innovation tests the
/// filter's covariance (see [`Outcome::landmark_fresh`]).
pub const FRESH_AFTER_S: f64 = 10.0;

/// Errors that are correlated in time, per observer and target: the errors of an observer's
/// successive observations of one target are taken as a first-order Gauss-Markov sequence,
/// correlated by `exp(-dt / T)` ([`NoiseModel::observation_correlation_s`]). A filter that takes
/// each observation as independent counts the shared part of a burst's errors once per
/// observation; instead each observation's noise covariance is multiplied by the variance
/// inflation factor of the correlation with the target's earlier observations,
/// `1 + 2 sum_j exp(-(t - t_j) / T)` (the effective-sample-size rule: in a long regular sequence
/// with neighbour correlation `c` it tends to `(1 + c) / (1 - c)`, so that `N` observations carry
/// the information of `N (1 - c) / (1 + c)` independent ones; the first observation of a target
/// after a long gap counts fully).
#[derive(Debug)]
pub struct CorrelatedErrors {
    /// `T`, s; 0: white.
    correlation_s: f64,
    /// Per (observer, target): the last observation's time and `1 + sum_j exp(-(t_last - t_j) / T)`
    /// over the earlier ones.
    last: std::collections::HashMap<(PlatformId, Target), (TimeUs, f64)>,
}

impl CorrelatedErrors {
    /// Errors correlated over `correlation_s` ([`NoiseModel::observation_correlation_s`]).
    pub fn new(correlation_s: f64) -> Self {
        CorrelatedErrors { correlation_s, last: std::collections::HashMap::new() }
    }

    /// The factor for `observer`'s observation of `target` at `t`, which it records (1 when `T`
    /// is 0), and whether the observation is fresh: the first of that target by that observer
    /// for [`FRESH_AFTER_S`] or more. Observations of one target come in time order.
    pub fn inflation(&mut self, observer: PlatformId, target: Target, t: TimeUs) -> (f64, bool) {
        let last = self.last.get(&(observer, target)).copied();
        let gap_s = last.map_or(f64::INFINITY, |(t_last, _)| t.0.saturating_sub(t_last.0) as f64 * 1e-6);
        let earlier = match last {
            Some((_, sum)) if self.correlation_s > 0.0 => sum * (-gap_s / self.correlation_s).exp(),
            _ => 0.0,
        };
        self.last.insert((observer, target), (t, 1.0 + earlier));
        (1.0 + 2.0 * earlier, gap_s >= FRESH_AFTER_S)
    }
}

/// One camera image: an observer's observations at one time stamp.
struct Image<'a> {
    t: TimeUs,
    observer: usize,
    observations: &'a [Observation],
}

/// The images of every robot in time order (ties: by robot).
fn images(ds: &Dataset) -> Vec<Image<'_>> {
    let mut out = Vec::new();
    for (i, r) in ds.robots.iter().enumerate() {
        let obs = &r.observations;
        let mut a = 0;
        while a < obs.len() {
            let mut b = a + 1;
            while b < obs.len() && obs[b].t == obs[a].t {
                b += 1;
            }
            out.push(Image { t: obs[a].t, observer: i, observations: &obs[a..b] });
            a = b;
        }
    }
    out.sort_by_key(|im| (im.t, im.observer));
    out
}

/// Sums of the scoring samples over every robot.
struct Sums {
    nees: f64,
    nees_position: f64,
    nees_heading: f64,
    in_bound: usize,
}

impl Outcome {
    /// An outcome with nothing scored yet.
    fn empty(regime: Regime, method: Method, ids: &[PlatformId]) -> Self {
        Outcome {
            regime,
            method,
            robots: Vec::new(),
            pos_rmse_m: f64::NAN,
            heading_rmse_deg: f64::NAN,
            avg_nees: f64::NAN,
            avg_nees_position: f64::NAN,
            avg_nees_heading: f64::NAN,
            in_bound_share: f64::NAN,
            samples: 0,
            masked: 0,
            landmark_updates: 0,
            landmark_gated: 0,
            robot_updates: 0,
            robot_gated: 0,
            landmark_weighted: 0,
            landmark_weight_below_half: 0,
            robot_weighted: 0,
            robot_weight_below_half: 0,
            epochs: 0,
            refused: 0,
            landmark_innovations: InnovationStats::default(),
            robot_innovations: InnovationStats::default(),
            landmark_fresh: InnovationStats::default(),
            robot_fresh: InnovationStats::default(),
            track: ids.iter().map(|&id| (id, Vec::new())).collect(),
        }
    }

    /// The scores from each robot's (squared position errors, squared heading errors in deg,
    /// samples, masked) and the sums over all of them.
    fn score(&mut self, ids: &[PlatformId], acc: &[(f64, f64, usize, usize)], sums: Sums) {
        let out = self;
        let (mut pos2, mut head2) = (0.0, 0.0);
        for (i, &(p2, h2, n, masked)) in acc.iter().enumerate() {
            let n_f = n.max(1) as f64;
            out.robots.push(RobotScore {
                id: ids[i],
                pos_rmse_m: (p2 / n_f).sqrt(),
                heading_rmse_deg: (h2 / n_f).sqrt(),
                samples: n,
                masked,
            });
            pos2 += p2;
            head2 += h2;
            out.samples += n;
            out.masked += masked;
        }
        let n = out.samples.max(1) as f64;
        out.pos_rmse_m = (pos2 / n).sqrt();
        out.heading_rmse_deg = (head2 / n).sqrt();
        out.avg_nees = sums.nees / n;
        out.avg_nees_position = sums.nees_position / n;
        out.avg_nees_heading = sums.nees_heading / n;
        out.in_bound_share = sums.in_bound as f64 / n;
    }
}

/// One image's landmark observations, each a robust local update of the observer; true when
/// one was applied (the team's absolute pose is then observable).
fn apply_landmarks(
    team: &mut Team<CommandedFilter>,
    observer: PlatformId,
    im: &Image<'_>,
    ds: &Dataset,
    (noise, gate): (&NoiseModel, [f64; 3]),
    correlated: &mut CorrelatedErrors,
    out: &mut Outcome,
) -> bool {
    let mut applied = false;
    for o in im.observations {
        let Target::Landmark(l) = o.target else { continue };
        let Some(lm) = ds.landmark(l) else { continue };
        let (inflation, fresh) = correlated.inflation(observer, o.target, im.t);
        let Some(meas) = landmark_measurement(team.filter(observer).expect("member"), lm, o, noise, inflation) else {
            out.refused += 1;
            continue;
        };
        match team.robust_local_update(observer, &meas, gate, noise.huber()) {
            Ok(Some((d, w))) => {
                applied = true;
                out.landmark_updates += 1;
                out.landmark_weighted += usize::from(w < 1.0);
                out.landmark_weight_below_half += usize::from(w < 0.5);
                out.landmark_innovations.add(&d);
                if fresh {
                    out.landmark_fresh.add(&d);
                }
            }
            Ok(None) => out.landmark_gated += 1,
            Err(_) => out.refused += 1,
        }
    }
    applied
}

/// One image's teammate observations, one robust joint update of the team (an epoch); false when
/// none could be made into a measurement.
fn apply_teammates(
    team: &mut Team<CommandedFilter>,
    observer: PlatformId,
    im: &Image<'_>,
    (noise, gate): (&NoiseModel, [f64; 3]),
    correlated: &mut CorrelatedErrors,
    out: &mut Outcome,
) -> bool {
    let mut meas = Vec::new();
    let mut all_fresh = true;
    for o in im.observations {
        let Target::Robot(to) = o.target else { continue };
        let Some(target) = team.filter(to) else { continue };
        let (inflation, fresh) = correlated.inflation(observer, o.target, im.t);
        all_fresh &= fresh;
        match robot_measurement(team.filter(observer).expect("member"), target, observer, to, o, noise, inflation) {
            Some(m) => meas.push(m),
            None => out.refused += 1,
        }
    }
    if meas.is_empty() {
        return false;
    }
    out.epochs += 1;
    match team.robust_cooperative_event(&meas, gate, noise.huber()) {
        Ok((d, weights)) => {
            let gated = weights.iter().filter(|&&w| w == 0.0).count();
            out.robot_weighted += weights.iter().filter(|&&w| w > 0.0 && w < 1.0).count();
            out.robot_weight_below_half += weights.iter().filter(|&&w| w > 0.0 && w < 0.5).count();
            if let Some(d) = d.filter(|d| !d.innovation.is_empty()) {
                out.robot_innovations.add(&d);
                if all_fresh {
                    out.robot_fresh.add(&d);
                }
            }
            out.robot_updates += meas.len() - gated;
            out.robot_gated += gated;
        }
        Err(_) => out.refused += meas.len(),
    }
    true
}

/// Every method of `methods` in every regime of `regimes` (regime-major order), in parallel
/// (rayon), each with the seconds it took: what `cooploc dataset mrclam` prints and the Python
/// package's `mrclam` returns.
pub fn run_all(
    ds: &Dataset,
    settings: &Settings,
    regimes: &[Regime],
    methods: &[Method],
) -> Result<Vec<(Outcome, f64)>, RunError> {
    use rayon::prelude::*;
    let pairs: Vec<(Regime, Method)> = regimes.iter().flat_map(|&r| methods.iter().map(move |&m| (r, m))).collect();
    pairs
        .par_iter()
        .map(|&(r, m)| {
            let t = std::time::Instant::now();
            run(ds, settings, r, m).map(|o| (o, t.elapsed().as_secs_f64()))
        })
        .collect()
}

/// Runs `method` over the data set in `regime` (see the module documentation).
pub fn run(ds: &Dataset, settings: &Settings, regime: Regime, method: Method) -> Result<Outcome, RunError> {
    let noise = &settings.noise;
    noise.validate().map_err(RunError::Settings)?;
    if settings.score_period_us == 0 {
        return Err(RunError::Settings("the scoring period must be positive".into()));
    }
    let fail = |robot, t, source| RunError::Filter { regime: regime.name(), method, robot, t, source };
    let config = commanded_config(noise);
    let sigma = commanded_sigma(noise);
    let stale_us = (noise.stale_command_s * 1e6) as u64;
    let mut members = Vec::new();
    let mut drives = Vec::new();
    for r in &ds.robots {
        let first = r.truth.first().ok_or_else(|| RunError::Settings(format!("robot {} has no ground truth", r.id)))?;
        // Every robot starts at t0: one still before its own first truth sample.
        let pos = Vector3::new(first.n_m, first.e_m, 0.0);
        members.push((r.id, CommandedFilter::new(config, ds.t0, pos, first.yaw_rad, sigma).map_err(|e| fail(r.id, ds.t0, e))?));
        drives.push(lagged(&drive_samples(&r.commands, ds.t0, ds.t_end, stale_us), ds.t0, noise.command_lag_s));
    }
    let ids: Vec<PlatformId> = ds.robots.iter().map(|r| r.id).collect();
    let mut team = Team::new(method, members).map_err(|e| fail(0, ds.t0, e))?;
    let gate = UpdateOptions::gate_for_probability(noise.gate_probability)
        .ok_or_else(|| RunError::Settings(format!("gate probability {} is not in (0, 1)", noise.gate_probability)))?;
    let mut next = vec![0usize; ids.len()];
    // Brings robot `i`'s filter to `t`: its samples up to `t`, then the next one cut at `t`.
    let mut advance = |team: &mut Team<CommandedFilter>, i: usize, t: TimeUs| -> Result<(), RunError> {
        let f = team.filter_mut(ids[i]).expect("member");
        while let Some(s) = drives[i].get(next[i]).filter(|s| s.t <= t) {
            f.propagate(s).map_err(|e| fail(ids[i], s.t, e))?;
            next[i] += 1;
        }
        if f.time() < t
            && let Some(s) = drives[i].get(next[i])
        {
            f.propagate(&WheelSample { t, ..*s }).map_err(|e| fail(ids[i], t, e))?;
        }
        Ok(())
    };
    let mut out = Outcome::empty(regime, method, &ids);
    // Per robot: sum of squared position errors, of squared heading errors (deg), samples,
    // masked.
    let mut acc = vec![(0.0f64, 0.0f64, 0usize, 0usize); ids.len()];
    let (mut nees_sum, mut in_bound) = (0.0f64, 0usize);
    let (mut nees_pos_sum, mut nees_yaw_sum) = (0.0f64, 0.0f64);
    let bound = crate::estimation::consistency::chi2_95(3);
    let images = if method == Method::DeadReckoning { Vec::new() } else { images(ds) };
    let mut k_image = 0;
    let mut absolute_seen = false;
    let mut correlated = CorrelatedErrors::new(noise.observation_correlation_s);
    let mut t_score = ds.t0;
    while t_score <= ds.t_end || k_image < images.len() {
        let t_image = images.get(k_image).map(|im| im.t);
        if let Some(t) = t_image.filter(|&t| t <= t_score || t_score > ds.t_end) {
            let im = &images[k_image];
            k_image += 1;
            let observer = ids[im.observer];
            let sees_landmarks = match regime {
                Regime::NoLandmarks => false,
                Regime::MapBlind => settings.map_robots.contains(&observer),
                Regime::FullMap => true,
            };
            if sees_landmarks && im.observations.iter().any(|o| matches!(o.target, Target::Landmark(_))) {
                advance(&mut team, im.observer, t)?;
                absolute_seen |= apply_landmarks(&mut team, observer, im, ds, (noise, gate), &mut correlated, &mut out);
                if absolute_seen {
                    for &id in &ids {
                        team.filter_mut(id).expect("member").reanchor_first_estimate();
                    }
                }
            }
            if im.observations.iter().any(|o| matches!(o.target, Target::Robot(to) if ids.contains(&to))) {
                for i in 0..ids.len() {
                    advance(&mut team, i, t)?;
                }
                if !apply_teammates(&mut team, observer, im, (noise, gate), &mut correlated, &mut out) {
                    continue;
                }
            }
            // Once the team has observed a landmark its absolute pose is observable: no null
            // space is left for the first estimates to protect, and a first estimate far from the
            // corrected one would only add linearization error. Every robot is re-anchored after
            // every update from then on (without landmarks, never).
            if absolute_seen {
                for &id in &ids {
                    team.filter_mut(id).expect("member").reanchor_first_estimate();
                }
            }
            continue;
        }
        if t_score > ds.t_end {
            break;
        }
        for (i, r) in ds.robots.iter().enumerate() {
            advance(&mut team, i, t_score)?;
            if settings.keep_track {
                let f = team.filter(r.id).expect("member");
                let p = f.position_ned_m();
                let cov = f.pose_covariance();
                out.track[i].1.push(TrackPoint { t: t_score, n_m: p[0], e_m: p[1], yaw_rad: f.yaw_rad(), cov });
            }
            let Some(truth) = truth_at(&r.truth, t_score, MAX_TRUTH_GAP_US) else {
                acc[i].3 += 1;
                continue;
            };
            let f = team.filter(r.id).expect("member");
            let p = f.position_ned_m();
            let e = DVector::from_vec(vec![truth.n_m - p[0], truth.e_m - p[1], wrap_angle(truth.yaw_rad - f.yaw_rad())]);
            let cov = f.covariance().view((0, 0), (3, 3)).into_owned();
            let v = nees(&e, &cov).map_err(|err| fail(r.id, t_score, err))?;
            nees_pos_sum += nees(&e.rows(0, 2).into_owned(), &cov.view((0, 0), (2, 2)).into_owned())
                .map_err(|err| fail(r.id, t_score, err))?;
            nees_yaw_sum += e[2] * e[2] / cov[(2, 2)];
            nees_sum += v;
            in_bound += usize::from(v <= bound);
            let pos2 = e[0] * e[0] + e[1] * e[1];
            acc[i].0 += pos2;
            acc[i].1 += e[2].to_degrees().powi(2);
            acc[i].2 += 1;
        }
        t_score = TimeUs(t_score.0 + settings.score_period_us);
    }
    out.score(&ids, &acc, Sums { nees: nees_sum, nees_position: nees_pos_sum, nees_heading: nees_yaw_sum, in_bound });
    Ok(out)
}

/// The 95% band of a time-averaged NEES of the 3-state error, taken as the band of the mean of
/// `robots` independent chi-square(3) values (the robots at one instant).
pub fn nees_band(robots: usize) -> (f64, f64) {
    crate::estimation::consistency::average_nees_band(3, robots.max(1), 0.95)
}

/// Bytes the decentralized method would have sent over the data set: at each of `epochs` every
/// one of `team` robots broadcasts its record (the 5 error states of the command-driven robot,
/// compact encoding, unsigned) with
/// its epoch report and estimate (as `cooploc budget` measures them), and the observer sends
/// each of its `observations` of teammates once as a COOPLOC_RANGE_BEARING.
pub fn broadcast_bytes(team: usize, epochs: usize, observations: usize) -> Result<u64, String> {
    use crate::protocol::budget::{TeamShape, epoch_frames};
    let shape = TeamShape {
        team,
        state_dim: commanded::DIM,
        ranges_per_node: 0,
        epoch_hz: 1.0,
        encoding: crate::protocol::record::Encoding::Compact,
        signed: false,
        echo_ranges: false,
    };
    let per_node = epoch_frames(&shape)?.bytes() as u64;
    let obs = crate::protocol::wire::to_frame(
        mavlink_core::MavHeader { system_id: 1, component_id: 191, sequence: 0 },
        &crate::protocol::wire::range_bearing_to_message(&crate::protocol::wire::RangeBearingReport {
            t: TimeUs(0),
            observer: 1,
            target: Target::Robot(2),
            range_m: 1.0,
            bearing_rad: 0.0,
        }),
    )
    .len() as u64;
    Ok(epochs as u64 * team as u64 * per_node + observations as u64 * obs)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::dataset::Command;

    fn secs(s: f64) -> TimeUs {
        TimeUs((s * 1e6).round() as u64)
    }

    #[test]
    fn correlated_errors_inflate_a_burst_and_not_its_first_observation() {
        let mut c = CorrelatedErrors::new(0.0);
        let (lm, other) = (Target::Landmark(7), Target::Landmark(8));
        let at = |s: f64| TimeUs((s * 1e6) as u64);
        // White errors: no inflation, freshness still tracked.
        assert_eq!(c.inflation(1, lm, at(0.0)), (1.0, true));
        assert_eq!(c.inflation(1, lm, at(1.0)), (1.0, false));
        let mut c = CorrelatedErrors::new(2.0);
        assert_eq!(c.inflation(1, lm, at(0.0)), (1.0, true), "the first observation counts fully");
        // Second one 1 s later: 1 + 2 exp(-1/2).
        let (f, fresh) = c.inflation(1, lm, at(1.0));
        assert!((f - (1.0 + 2.0 * (-0.5f64).exp())).abs() < 1e-12 && !fresh, "{f}");
        // Another target, and the same target by another observer, are separate sequences.
        assert_eq!(c.inflation(1, other, at(1.0)), (1.0, true));
        assert_eq!(c.inflation(2, lm, at(1.0)), (1.0, true));
        // A long regular sequence tends to (1 + c) / (1 - c), c the neighbours' correlation.
        let mut f = 0.0;
        for k in 2..400 {
            f = c.inflation(1, lm, at(k as f64)).0;
        }
        let corr = (-0.5f64).exp();
        assert!((f - (1.0 + corr) / (1.0 - corr)).abs() < 1e-9, "{f}");
        // After a gap of FRESH_AFTER_S the observation is fresh and nearly uninflated.
        let (f, fresh) = c.inflation(1, lm, at(399.0 + FRESH_AFTER_S + 20.0));
        assert!(fresh && f < 1.0 + 1e-3, "{f}");
    }

    #[test]
    fn commands_hold_until_the_next_or_until_stale() {
        let c = |t: f64, v: f64| Command { t: secs(t), speed_m_s: v, yaw_rate_rad_s: 0.1 * v };
        let commands = [c(1.0, 1.0), c(1.2, 2.0), c(4.2, 0.5)];
        let s = drive_samples(&commands, secs(0.0), secs(5.0), 1_000_000);
        let ends: Vec<u64> = s.iter().map(|s| s.t.0 / 100_000).collect();
        assert_eq!(ends, vec![5, 10, 12, 17, 22, 27, 32, 37, 42, 47, 50], "tenths of a second");
        let mut prev = 0.0;
        let mut dist = 0.0;
        for x in &s {
            dist += x.speed_m_s * (x.t.as_secs_f64() - prev);
            prev = x.t.as_secs_f64();
        }
        // 0.2 s at 1 m/s, 1 s at 2 m/s (then stale: stopped for 2 s), 0.8 s at 0.5 m/s.
        assert!((dist - 2.6).abs() < 1e-9, "{dist}");
        assert_eq!(s[0].speed_m_s, 0.0, "still before the first command");
        assert_eq!(s[5].speed_m_s, 0.0, "stopped once the command is stale");
    }

    #[test]
    fn a_lag_delays_the_command_and_keeps_the_distance() {
        let c = |t: f64, v: f64| Command { t: secs(t), speed_m_s: v, yaw_rate_rad_s: 0.0 };
        let s = drive_samples(&[c(1.0, 1.0), c(3.0, 0.0)], secs(0.0), secs(6.0), 5_000_000);
        assert_eq!(lagged(&s, secs(0.0), 0.0), s, "no lag: unchanged");
        let l = lagged(&s, secs(0.0), 0.2);
        let dist = |v: &[WheelSample]| {
            let mut prev = 0.0;
            v.iter()
                .map(|x| {
                    let d = x.speed_m_s * (x.t.as_secs_f64() - prev);
                    prev = x.t.as_secs_f64();
                    d
                })
                .sum::<f64>()
        };
        // 2 s at 1 m/s either way: the lag moves distance later, it does not lose it.
        assert!((dist(&s) - 2.0).abs() < 1e-9 && (dist(&l) - 2.0).abs() < 1e-6, "{} {}", dist(&s), dist(&l));
        // 0.1 s after the start the lagged speed averages 1 - 0.2 (1 - e^-0.5) / 0.1 = 0.213.
        let first = l.iter().find(|x| x.t == secs(1.1)).unwrap();
        assert!((first.speed_m_s - (1.0 - 2.0 * (1.0 - (-0.5f64).exp()))).abs() < 1e-9, "{first:?}");
        assert_eq!(l.last().unwrap().speed_m_s, 0.0, "stopped long after the last command");
    }

    fn filter(n: f64, e: f64, yaw: f64) -> CommandedFilter {
        let config = CommandedConfig {
            speed_noise_m_s_per_sqrt_hz: 0.01,
            yaw_rate_noise_rad_s_per_sqrt_hz: 0.01,
            speed_scale_walk_per_sqrt_s: 0.0,
            yaw_rate_bias_walk_rad_s_per_sqrt_s: 0.0,
            max_gap_s: 1.0,
            first_estimates: false,
        };
        let sigma = CommandedSigma { pos_m: 0.5, yaw_rad: 0.1, speed_scale: 0.05, yaw_rate_bias_rad_s: 0.01 };
        CommandedFilter::new(config, TimeUs(0), Vector3::new(n, e, 0.0), yaw, sigma).unwrap()
    }

    #[test]
    fn the_landmark_jacobian_is_the_derivative_of_range_and_bearing() {
        let noise = NoiseModel::mrclam();
        let lm = Landmark { id: 6, n_m: 3.0, e_m: -1.0, sigma_n_m: 0.0, sigma_e_m: 0.0 };
        let obs = Observation { t: TimeUs(0), target: Target::Landmark(6), range_m: 2.0, bearing_rad: 0.3 };
        let x0 = [0.5, 0.7, 0.4];
        let m = landmark_measurement(&filter(x0[0], x0[1], x0[2]), &lm, &obs, &noise, 1.0).unwrap();
        for k in 0..3 {
            let mut x = x0;
            x[k] += 1e-6;
            let moved = landmark_measurement(&filter(x[0], x[1], x[2]), &lm, &obs, &noise, 1.0).unwrap();
            // residual = z - h(x): d(residual)/dx = -dh/dx, and H is dh/d(truth - estimate) = dh/dx.
            for row in 0..2 {
                let numeric = -(moved.residual[row] - m.residual[row]) / 1e-6;
                assert!((numeric - m.h[(row, k)]).abs() < 1e-5, "row {row} col {k}: {numeric} vs {}", m.h[(row, k)]);
            }
        }
        // A landmark dead ahead at 2 m, seen at 2 m and bearing 0: zero residual.
        let ahead = Landmark { n_m: 2.0, e_m: 0.0, ..lm };
        let obs = Observation { range_m: 2.0 + noise.landmark_range_bias_m, bearing_rad: 0.0, ..obs };
        let m = landmark_measurement(&filter(0.0, 0.0, 0.0), &ahead, &obs, &noise, 1.0).unwrap();
        assert!(m.residual.norm() < 1e-12, "{}", m.residual);
    }

    #[test]
    fn the_gate_leaves_out_a_gross_outlier_and_keeps_the_state() {
        let noise = NoiseModel::mrclam();
        let gate = UpdateOptions::gate_for_probability(noise.gate_probability).unwrap();
        let lm = Landmark { id: 6, n_m: 2.0, e_m: 0.0, sigma_n_m: 0.0, sigma_e_m: 0.0 };
        for method in Method::ALL {
            let mut team = Team::new(method, vec![(1, filter(0.0, 0.0, 0.0)), (2, filter(5.0, 5.0, 0.0))]).unwrap();
            let good = Observation { t: TimeUs(0), target: Target::Landmark(6), range_m: 2.1, bearing_rad: 0.02 };
            let bad = Observation { range_m: 9.0, ..good };
            let before = team.filter(1).unwrap().state();
            let m = landmark_measurement(team.filter(1).unwrap(), &lm, &bad, &noise, 1.0).unwrap();
            assert!(team.gated_local_update(1, &m, gate).unwrap().is_none(), "{method}");
            assert_eq!(team.filter(1).unwrap().state(), before, "{method}");
            let m = landmark_measurement(team.filter(1).unwrap(), &lm, &good, &noise, 1.0).unwrap();
            assert!(team.gated_local_update(1, &m, gate).unwrap().is_some(), "{method}");
            // A teammate 7.07 m away reported at 1 m: gated for every cooperative method.
            let far = Observation { t: TimeUs(0), target: Target::Robot(2), range_m: 1.0, bearing_rad: 0.785 };
            let m = robot_measurement(team.filter(1).unwrap(), team.filter(2).unwrap(), 1, 2, &far, &noise, 1.0).unwrap();
            let (_, gated) = team.gated_cooperative_event(&[m], gate).unwrap();
            assert_eq!(gated, usize::from(method != Method::DeadReckoning), "{method}");
        }
    }
}
