//! The noise model identified from the data's own innovations, without the ground truth.
//!
//! The ground truth of a data set is what the methods are scored on, so it must not also set the
//! figures the filters run with. What a robot team has without motion capture is its commands,
//! its observations and the map of the landmarks; a filter run over them produces innovations
//! `r` with predicted covariances `S`, and the noise model that makes those innovations most
//! likely is a maximum-likelihood estimate of it (the prediction-error method):
//!
//! ```text
//! minimise  J(theta) = sum over updates  1/2 (ln det S + rho(r^T S^-1 r))  +  sum over gated  1/2 (ln det S + rho(g))
//! ```
//!
//! (with a Huber loss on each NIS, see [`super::run::huber_nis`]: heavy tails weigh like
//! distances) over the white densities of the commanded speed and yaw rate, the random-walk densities of
//! the speed scale and the yaw-rate bias, and the range and bearing sigmas of landmark and
//! teammate observations, and the time constant of the lag with which the robots follow their
//! commands ([`super::run::lagged`]) (9 figures, searched in log space). The identification runs gate only
//! gross outliers ([`IDENTIFICATION_GATE_PROBABILITY`]); one that is gated costs the gate's loss
//! and the mean `ln det S` of its kind, so that shrinking a sigma until everything inconvenient
//! is gated does not pay. The range
//! biases are the mean range innovations, updated between the search's iterations (a fixed point,
//! the EM step for a mean). The filter that produces the innovations is the decentralized one
//! (what a robot of the team runs) with every observation (the full-map regime).
//!
//! A second stage finds the correlation time of the observation errors
//! ([`NoiseModel::observation_correlation_s`], [`fit_correlation`]), which the likelihood of
//! every innovation cannot see: it makes the NIS of the fresh observations (a target not seen by
//! its observer for [`super::run::FRESH_AFTER_S`]) 1 per scalar, as for a consistent filter.
//!
//! Left as given, not identified: the gate probability, the stale-command rule, the initial
//! sigmas (of the start pose, and the prior sigmas of the speed scale and the bias), and whether
//! first-estimate Jacobians are used. The search starts from [`start`]: round figures, none read
//! off the ground truth.
//!
//! The search: from the start, evaluate every figure moved up and down by a step (a factor
//! `10^step`), all in parallel; move to the best neighbour when it lowers `J`, else halve the
//! step; stop below [`Options::min_step`] or after [`Options::max_iterations`].

use rayon::prelude::*;

use super::Dataset;
use super::noise::NoiseModel;
use super::run::{Outcome, Regime, RunError, Settings, run};
use crate::estimation::Method;

/// How the search runs.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Options {
    /// First step in log10 units.
    pub initial_step: f64,
    /// Stop when the step falls below this.
    pub min_step: f64,
    pub max_iterations: usize,
}

impl Default for Options {
    fn default() -> Self {
        Options { initial_step: 0.5, min_step: 0.03, max_iterations: 80 }
    }
}

/// The figures searched, in order.
pub const FIGURES: [&str; 9] = [
    "speed_noise_m_s_per_sqrt_hz",
    "yaw_rate_noise_rad_s_per_sqrt_hz",
    "speed_scale_walk_per_sqrt_s",
    "yaw_rate_bias_walk_rad_s_per_sqrt_s",
    "landmark_range_sigma_m",
    "landmark_bearing_sigma_rad",
    "robot_range_sigma_m",
    "robot_bearing_sigma_rad",
    "command_lag_s",
];

fn get(m: &NoiseModel, k: usize) -> f64 {
    [
        m.speed_noise_m_s_per_sqrt_hz,
        m.yaw_rate_noise_rad_s_per_sqrt_hz,
        m.speed_scale_walk_per_sqrt_s,
        m.yaw_rate_bias_walk_rad_s_per_sqrt_s,
        m.landmark_range_sigma_m,
        m.landmark_bearing_sigma_rad,
        m.robot_range_sigma_m,
        m.robot_bearing_sigma_rad,
        m.command_lag_s,
    ][k]
}

fn set(m: &mut NoiseModel, k: usize, v: f64) {
    let f = match k {
        0 => &mut m.speed_noise_m_s_per_sqrt_hz,
        1 => &mut m.yaw_rate_noise_rad_s_per_sqrt_hz,
        2 => &mut m.speed_scale_walk_per_sqrt_s,
        3 => &mut m.yaw_rate_bias_walk_rad_s_per_sqrt_s,
        4 => &mut m.landmark_range_sigma_m,
        5 => &mut m.landmark_bearing_sigma_rad,
        6 => &mut m.robot_range_sigma_m,
        7 => &mut m.robot_bearing_sigma_rad,
        _ => &mut m.command_lag_s,
    };
    *f = v;
}

/// The starting point of the search: `base` (its gate, stale rule, initial and prior sigmas
/// and first-estimate switch kept) with round figures for the identified ones and zero biases.
pub fn start(base: &NoiseModel) -> NoiseModel {
    NoiseModel {
        speed_noise_m_s_per_sqrt_hz: 0.01,
        yaw_rate_noise_rad_s_per_sqrt_hz: 0.01,
        speed_scale_walk_per_sqrt_s: 1e-3,
        yaw_rate_bias_walk_rad_s_per_sqrt_s: 1e-4,
        landmark_range_sigma_m: 0.1,
        landmark_bearing_sigma_rad: 0.02,
        robot_range_sigma_m: 0.1,
        robot_bearing_sigma_rad: 0.02,
        command_lag_s: 0.1,
        observation_correlation_s: 0.0,
        landmark_range_bias_m: 0.0,
        robot_range_bias_m: 0.0,
        ..*base
    }
}

/// One evaluation of the objective.
#[derive(Debug, Clone, PartialEq)]
pub struct Evaluation {
    pub model: NoiseModel,
    /// `J`, nats.
    pub cost: f64,
    /// Mean NIS per scalar of the landmark and of the teammate updates (1 when consistent).
    pub landmark_nis: f64,
    pub robot_nis: f64,
    /// Mean range innovation of the landmark and teammate observations applied, m.
    pub landmark_range_mean_m: f64,
    pub robot_range_mean_m: f64,
    /// Observations gated out, landmark and teammate, and applied.
    pub landmark_gated: usize,
    pub robot_gated: usize,
    pub landmark_used: usize,
    pub robot_used: usize,
}

/// What [`identify`] found.
#[derive(Debug, Clone, PartialEq)]
pub struct Identified {
    pub start: Evaluation,
    /// The figures of the likelihood search with the correlation time found after it
    /// ([`fit_correlation`]); its other fields are those of the search's best point (white
    /// errors).
    pub best: Evaluation,
    pub iterations: usize,
    pub evaluations: usize,
    /// The fresh observations' NIS per scalar with white errors and with the correlation time
    /// found (1 when consistent).
    pub fresh_nis_white: f64,
    pub fresh_nis: f64,
}

/// The objective at `model` (module documentation).
pub fn evaluate(ds: &Dataset, model: &NoiseModel) -> Result<Evaluation, RunError> {
    Ok(evaluation(model, &identification_run(ds, model)?))
}

/// The run the identification reads its innovations from: dcl with every observation (full
/// map), gating only gross outliers, no Huber weights.
fn identification_run(ds: &Dataset, model: &NoiseModel) -> Result<Outcome, RunError> {
    let settings = Settings::new(NoiseModel { gate_probability: IDENTIFICATION_GATE_PROBABILITY, huber_nis: 0.0, ..*model });
    run(ds, &settings, Regime::FullMap, Method::Decentralized)
}

/// The gate of the identification runs: gross outliers only, so that the likelihood sees
/// (nearly) every observation, the Huber loss bounding what a large innovation costs.
pub const IDENTIFICATION_GATE_PROBABILITY: f64 = 1e-9;

fn evaluation(model: &NoiseModel, o: &Outcome) -> Evaluation {
    let g =
        crate::estimation::UpdateOptions::gate_for_probability(IDENTIFICATION_GATE_PROBABILITY).map_or(f64::INFINITY, |g| g[2]);
    let (l, r) = (&o.landmark_innovations, &o.robot_innovations);
    // A gated observation costs the gate's Huber loss and the mean log-determinant of its kind
    // (a range and bearing: two scalars).
    let gated_cost = |s: &super::run::InnovationStats, n: usize| {
        let ln_det = if s.scalars > 0 { 2.0 * s.ln_det_s_sum / s.scalars as f64 } else { 0.0 };
        n as f64 * (ln_det + super::run::huber_nis(g, 2))
    };
    let cost = 0.5
        * (l.ln_det_s_sum
            + l.nis_huber_sum
            + r.ln_det_s_sum
            + r.nis_huber_sum
            + gated_cost(l, o.landmark_gated)
            + gated_cost(r, o.robot_gated));
    Evaluation {
        model: *model,
        cost,
        landmark_nis: l.nis_per_scalar(),
        robot_nis: r.nis_per_scalar(),
        landmark_range_mean_m: l.range_sum_m / l.observations.max(1) as f64,
        robot_range_mean_m: r.range_sum_m / r.observations.max(1) as f64,
        landmark_gated: o.landmark_gated,
        robot_gated: o.robot_gated,
        landmark_used: o.landmark_updates,
        robot_used: o.robot_updates,
    }
}

/// Identifies the noise model on `ds` from `initial` (module documentation).
pub fn identify(ds: &Dataset, initial: &NoiseModel, opts: &Options) -> Result<Identified, RunError> {
    initial.validate().map_err(RunError::Settings)?;
    let initial = &NoiseModel { observation_correlation_s: 0.0, ..*initial };
    let mut best = evaluate(ds, initial)?;
    let start = best.clone();
    let mut step = opts.initial_step;
    let (mut iterations, mut evaluations) = (0, 1);
    while step >= opts.min_step && iterations < opts.max_iterations {
        iterations += 1;
        // The biases: the mean range innovation moves into the bias (a fixed point).
        let mut centre = best.model;
        centre.landmark_range_bias_m += best.landmark_range_mean_m;
        centre.robot_range_bias_m += best.robot_range_mean_m;
        let mut candidates = vec![centre];
        for k in 0..FIGURES.len() {
            for sign in [1.0, -1.0] {
                let mut m = centre;
                set(&mut m, k, (get(&centre, k) * 10f64.powf(sign * step)).max(1e-9));
                candidates.push(m);
            }
        }
        let results: Vec<Evaluation> = candidates.par_iter().map(|m| evaluate(ds, m)).collect::<Result<_, _>>()?;
        evaluations += results.len();
        let next = results.into_iter().min_by(|a, b| a.cost.total_cmp(&b.cost)).expect("candidates");
        if next.cost < best.cost - 1e-6 {
            // Keep the step while it pays; the centre alone (a bias update) does not widen it.
            best = next;
        } else {
            step *= 0.5;
        }
    }
    let fit = fit_correlation(ds, &best.model)?;
    best.model.observation_correlation_s = fit.correlation_s;
    Ok(Identified {
        start,
        best,
        iterations,
        evaluations: evaluations + fit.runs,
        fresh_nis_white: fit.white_nis,
        fresh_nis: fit.nis,
    })
}

/// The NIS per scalar of the fresh observations (landmarks and teammates pooled; see
/// [`super::run::FRESH_AFTER_S`]) in the identification's run (dcl, full map).
pub fn fresh_nis(ds: &Dataset, model: &NoiseModel) -> Result<f64, RunError> {
    let o = identification_run(ds, model)?;
    let (l, r) = (&o.landmark_fresh, &o.robot_fresh);
    Ok((l.nis_sum + r.nis_sum) / (l.scalars + r.scalars).max(1) as f64)
}

/// The correlation time of the observation errors ([`NoiseModel::observation_correlation_s`]),
/// found after the likelihood search: the likelihood of every innovation cannot see it (within
/// a burst of correlated errors the innovations after the first are small, and the search then
/// prefers white errors with small sigmas, which leaves the filter over-confident). An
/// observation of a target its observer has not seen for a while
/// ([`super::run::FRESH_AFTER_S`]) has an error nearly independent of what the filter has taken
/// in, so its innovation tests the filter's covariance: a consistent filter's NIS per scalar on
/// those is 1. The correlation time is the one that makes it 1 (bisection in log time between
/// 0.01 and [`MAX_CORRELATION_S`]; the NIS falls as the time grows, the filter trusting each
/// burst less); 0 when the white filter's is already at most 1, and the longest when even that
/// leaves it above 1 (the fit's NIS then says so).
pub fn fit_correlation(ds: &Dataset, model: &NoiseModel) -> Result<CorrelationFit, RunError> {
    let at = |t: f64| fresh_nis(ds, &NoiseModel { observation_correlation_s: t, ..*model });
    let white = at(0.0)?;
    if white <= 1.0 {
        return Ok(CorrelationFit { correlation_s: 0.0, nis: white, white_nis: white, runs: 1 });
    }
    let longest = at(MAX_CORRELATION_S)?;
    if longest > 1.0 {
        // Even errors this correlated leave the filter over-confident: the sigmas are too small
        // for the correlation to make up (the NIS says by how much).
        return Ok(CorrelationFit { correlation_s: MAX_CORRELATION_S, nis: longest, white_nis: white, runs: 2 });
    }
    let (mut lo, mut hi) = (0.01f64.ln(), MAX_CORRELATION_S.ln());
    let mut runs = 2;
    for _ in 0..20 {
        let mid = 0.5 * (lo + hi);
        runs += 1;
        if at(mid.exp())? > 1.0 {
            lo = mid;
        } else {
            hi = mid;
        }
    }
    let t = (0.5 * (lo + hi)).exp();
    Ok(CorrelationFit { correlation_s: t, nis: at(t)?, white_nis: white, runs: runs + 1 })
}

/// The longest correlation time [`fit_correlation`] tries, s.
pub const MAX_CORRELATION_S: f64 = 1000.0;

/// What [`fit_correlation`] found.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct CorrelationFit {
    /// s; 0: white.
    pub correlation_s: f64,
    /// The fresh observations' NIS per scalar there, and with white errors.
    pub nis: f64,
    pub white_nis: f64,
    /// Runs of the data set made.
    pub runs: usize,
}

/// The figures as lines of TOML with a comment each, for `--write-noise` and the committed file.
pub fn describe(id: &Identified) -> Vec<String> {
    let m = &id.best.model;
    let mut out = Vec::new();
    for (k, name) in FIGURES.iter().enumerate() {
        out.push(format!("{name} = {:.4e}   # start {:.1e}", get(m, k), get(&id.start.model, k)));
    }
    out.push(format!(
        "observation_correlation_s = {:.4e}   # fresh observations' NIS per scalar {:.2} with white errors, {:.2} with it",
        m.observation_correlation_s, id.fresh_nis_white, id.fresh_nis
    ));
    out.push(format!("landmark_range_bias_m = {:.4}", m.landmark_range_bias_m));
    out.push(format!("robot_range_bias_m = {:.4}", m.robot_range_bias_m));
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn figures_round_trip_by_index() {
        let mut m = NoiseModel::mrclam();
        for k in 0..FIGURES.len() {
            set(&mut m, k, 1.0 + k as f64);
        }
        for (k, name) in FIGURES.iter().enumerate() {
            assert_eq!(get(&m, k), 1.0 + k as f64, "{name}");
        }
        let s = start(&m);
        assert_eq!((s.gate_probability, s.first_estimates), (m.gate_probability, m.first_estimates));
        assert_eq!(s.robot_range_bias_m, 0.0);
    }
}
