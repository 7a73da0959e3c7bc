//! The noise model of a data set run, and how figures can be estimated from the data against
//! the ground truth ([`estimate`]).
//!
//! The MRCLAM figures live in `mrclam_noise.toml` next to this file ([`NoiseModel::mrclam`]);
//! they are identified from data set 6's own innovations, **without its ground truth**
//! ([`super::identify`], `cooploc dataset mrclam DIR --identify`), or chosen a priori; the file
//! says which for each. The same figures serve every method and every regime: nothing is tuned
//! per method.
//!
//! [`estimate`] (`cooploc dataset mrclam DIR --estimate-noise`) measures the errors against the
//! ground truth instead: a diagnostic to compare the identified figures with, not a source of
//! figures (the truth is what the methods are scored on).
//!
//! How:
//! - **Observations**: each observation's residual against the ground truth (the observer's
//!   pose and the target's position interpolated at the observation's time; observations in a
//!   ground-truth gap skipped): measured minus true range, and wrapped measured minus true
//!   bearing, separately for landmarks and teammates. Mis-detections are removed first (more
//!   than 5 robust sigmas from the median, the robust sigma being 1.4826 times the median
//!   absolute deviation); the bias is the mean of the rest and the sigma their standard
//!   deviation.
//! - **Motion**: the commands against the ground truth over consecutive 1-s windows in which the
//!   robot was commanded to move: the distance travelled along the mean heading minus the
//!   commanded distance, and the heading change minus the commanded one. A white input noise of
//!   density `q` gives an error of variance `q T` over a window of `T`, so the density is the
//!   residuals' standard deviation over `sqrt(T)` (outliers removed as above: Vicon glitches).

use serde::{Deserialize, Serialize};

use super::run::drive_samples;
use super::{Dataset, MAX_TRUTH_GAP_US, Target, truth_at};
use crate::estimation::unicycle::wrap_angle;
use crate::time::TimeUs;

/// The noise figures of a data set run.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct NoiseModel {
    /// White-noise density of the commanded forward speed, m/s/sqrt(Hz).
    pub speed_noise_m_s_per_sqrt_hz: f64,
    /// White-noise density of the commanded yaw rate, rad/s/sqrt(Hz).
    pub yaw_rate_noise_rad_s_per_sqrt_hz: f64,
    /// A command older than this means the robot stopped, s.
    pub stale_command_s: f64,
    pub landmark_range_sigma_m: f64,
    /// Mean range error to landmarks, subtracted from every landmark range, m.
    pub landmark_range_bias_m: f64,
    pub landmark_bearing_sigma_rad: f64,
    pub robot_range_sigma_m: f64,
    /// Mean range error to teammates, subtracted from every teammate range, m.
    pub robot_range_bias_m: f64,
    pub robot_bearing_sigma_rad: f64,
    /// Initial position sigma per axis (the filters start at the ground truth), m.
    pub initial_position_sigma_m: f64,
    pub initial_yaw_sigma_rad: f64,
    /// False-rejection probability of the chi-square gate on every observation.
    pub gate_probability: f64,
    /// Random-walk density of each robot's speed scale, 1/sqrt(s) (see
    /// [`crate::estimation::commanded`]); 0 with a zero initial sigma: no scale is learnt (a
    /// noise file without the field).
    #[serde(default)]
    pub speed_scale_walk_per_sqrt_s: f64,
    /// Random-walk density of each robot's yaw-rate bias, rad/s/sqrt(s).
    #[serde(default)]
    pub yaw_rate_bias_walk_rad_s_per_sqrt_s: f64,
    /// Prior sigma of each robot's speed scale (0.1: 10%).
    #[serde(default)]
    pub initial_speed_scale_sigma: f64,
    /// Prior sigma of each robot's yaw-rate bias, rad/s.
    #[serde(default)]
    pub initial_yaw_rate_bias_sigma_rad_s: f64,
    /// First-estimate Jacobians for the motion and the teammate observations (see
    /// [`crate::estimation::commanded`]).
    #[serde(default)]
    pub first_estimates: bool,
    /// Huber weighting of the observations that pass the gate: the NIS (of a range and
    /// bearing) above which an observation's noise is inflated (its weight `sqrt(c / NIS)`; see
    /// [`crate::estimation::UpdateOptions::huber_nis`]); 0: none.
    #[serde(default)]
    pub huber_nis: f64,
    /// Time constant of the first-order lag with which the robots execute their commands, s
    /// (see [`super::run::lagged`]); 0: none.
    #[serde(default)]
    pub command_lag_s: f64,
    /// Correlation time of an observer's errors on one target (landmark or teammate), s: the
    /// errors of successive observations of the same target are taken as correlated by
    /// `exp(-dt / T)`, and each observation's noise is inflated by the variance inflation factor
    /// of that correlation with the target's earlier observations (see
    /// [`super::run::CorrelatedErrors`]); 0: white errors, no inflation.
    #[serde(default)]
    pub observation_correlation_s: f64,
}

/// The MRCLAM figures, as committed.
pub const MRCLAM_NOISE_TOML: &str = include_str!("mrclam_noise.toml");

impl NoiseModel {
    /// The Huber threshold, `None` when off.
    pub fn huber(&self) -> Option<f64> {
        (self.huber_nis > 0.0).then_some(self.huber_nis)
    }

    /// The committed MRCLAM figures.
    pub fn mrclam() -> NoiseModel {
        NoiseModel::from_toml_str(MRCLAM_NOISE_TOML).expect("the committed mrclam_noise.toml is valid")
    }

    pub fn from_toml_str(s: &str) -> Result<NoiseModel, String> {
        let m: NoiseModel = toml::from_str(s).map_err(|e| e.to_string())?;
        m.validate()?;
        Ok(m)
    }

    /// Every figure finite, sigmas positive, the gate probability in (0, 1).
    pub fn validate(&self) -> Result<(), String> {
        let positive = [
            ("speed_noise_m_s_per_sqrt_hz", self.speed_noise_m_s_per_sqrt_hz),
            ("yaw_rate_noise_rad_s_per_sqrt_hz", self.yaw_rate_noise_rad_s_per_sqrt_hz),
            ("stale_command_s", self.stale_command_s),
            ("landmark_range_sigma_m", self.landmark_range_sigma_m),
            ("landmark_bearing_sigma_rad", self.landmark_bearing_sigma_rad),
            ("robot_range_sigma_m", self.robot_range_sigma_m),
            ("robot_bearing_sigma_rad", self.robot_bearing_sigma_rad),
            ("initial_position_sigma_m", self.initial_position_sigma_m),
            ("initial_yaw_sigma_rad", self.initial_yaw_sigma_rad),
        ];
        for (name, v) in positive {
            if !(v.is_finite() && v > 0.0) {
                return Err(format!("{name} = {v}: must be a positive number"));
            }
        }
        for (name, v) in [("landmark_range_bias_m", self.landmark_range_bias_m), ("robot_range_bias_m", self.robot_range_bias_m)]
        {
            if !(v.is_finite() && v.abs() < 10.0) {
                return Err(format!("{name} = {v}: must be a finite bias under 10 m"));
            }
        }
        for (name, v) in [
            ("speed_scale_walk_per_sqrt_s", self.speed_scale_walk_per_sqrt_s),
            ("yaw_rate_bias_walk_rad_s_per_sqrt_s", self.yaw_rate_bias_walk_rad_s_per_sqrt_s),
            ("initial_speed_scale_sigma", self.initial_speed_scale_sigma),
            ("initial_yaw_rate_bias_sigma_rad_s", self.initial_yaw_rate_bias_sigma_rad_s),
            ("huber_nis", self.huber_nis),
            ("command_lag_s", self.command_lag_s),
            ("observation_correlation_s", self.observation_correlation_s),
        ] {
            if !(v.is_finite() && v >= 0.0) {
                return Err(format!("{name} = {v}: must be a number >= 0"));
            }
        }
        if !(self.gate_probability > 0.0 && self.gate_probability < 1.0) {
            return Err(format!("gate_probability = {}: must be in (0, 1)", self.gate_probability));
        }
        Ok(())
    }
}

/// Robust statistics of residuals.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct Stat {
    /// Residuals used (outliers removed).
    pub n: usize,
    /// Residuals removed as outliers.
    pub outliers: usize,
    pub mean: f64,
    pub sigma: f64,
}

/// Mean and standard deviation of `v` after removing what lies more than 5 robust sigmas from
/// the median.
pub fn robust_stat(v: &[f64]) -> Stat {
    if v.is_empty() {
        return Stat { mean: f64::NAN, sigma: f64::NAN, ..Stat::default() };
    }
    let median = |x: &mut Vec<f64>| {
        x.sort_by(f64::total_cmp);
        let n = x.len();
        if n % 2 == 1 { x[n / 2] } else { 0.5 * (x[n / 2 - 1] + x[n / 2]) }
    };
    let med = median(&mut v.to_vec());
    let mad = median(&mut v.iter().map(|x| (x - med).abs()).collect());
    let limit = 5.0 * 1.4826 * mad;
    let kept: Vec<f64> = v.iter().copied().filter(|x| (x - med).abs() <= limit || mad == 0.0).collect();
    let n = kept.len();
    let mean = kept.iter().sum::<f64>() / n as f64;
    let var = kept.iter().map(|x| (x - mean).powi(2)).sum::<f64>() / (n.max(2) - 1) as f64;
    Stat { n, outliers: v.len() - n, mean, sigma: var.sqrt() }
}

/// What [`estimate`] finds.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct NoiseEstimate {
    pub landmark_range_m: Stat,
    pub landmark_bearing_rad: Stat,
    pub robot_range_m: Stat,
    pub robot_bearing_rad: Stat,
    /// Distance along the heading minus the commanded distance over 1-s windows, m.
    pub window_distance_m: Stat,
    /// Heading change minus the commanded one over 1-s windows, rad.
    pub window_heading_rad: Stat,
    pub window_s: f64,
    /// Mean commanded distance of those windows, m (the distance residual's mean over it is the
    /// speed's scale error).
    pub window_commanded_m: f64,
}

impl NoiseEstimate {
    pub fn speed_density(&self) -> f64 {
        self.window_distance_m.sigma / self.window_s.sqrt()
    }
    pub fn yaw_rate_density(&self) -> f64 {
        self.window_heading_rad.sigma / self.window_s.sqrt()
    }
}

/// Estimates the noise figures from the data against its ground truth (module documentation);
/// `stale_command_s` as the model holds commands.
pub fn estimate(ds: &Dataset, stale_command_s: f64, window_s: f64) -> NoiseEstimate {
    let (mut lr, mut lb, mut rr, mut rb) = (Vec::new(), Vec::new(), Vec::new(), Vec::new());
    for r in &ds.robots {
        for o in &r.observations {
            let Some(me) = truth_at(&r.truth, o.t, MAX_TRUTH_GAP_US) else { continue };
            let (tn, te) = match o.target {
                Target::Landmark(l) => match ds.landmark(l) {
                    Some(lm) => (lm.n_m, lm.e_m),
                    None => continue,
                },
                Target::Robot(id) => match ds.robot(id).and_then(|t| truth_at(&t.truth, o.t, MAX_TRUTH_GAP_US)) {
                    Some(p) => (p.n_m, p.e_m),
                    None => continue,
                },
            };
            let (dn, de) = (tn - me.n_m, te - me.e_m);
            let range = (dn * dn + de * de).sqrt();
            let bearing = wrap_angle(o.bearing_rad - (de.atan2(dn) - me.yaw_rad));
            match o.target {
                Target::Landmark(_) => {
                    lr.push(o.range_m - range);
                    lb.push(bearing);
                }
                Target::Robot(_) => {
                    rr.push(o.range_m - range);
                    rb.push(bearing);
                }
            }
        }
    }
    let window_us = (window_s * 1e6) as u64;
    let (mut dd, mut dh) = (Vec::new(), Vec::new());
    let mut commanded = Vec::new();
    for r in &ds.robots {
        let drive = drive_samples(&r.commands, ds.t0, ds.t_end, (stale_command_s * 1e6) as u64);
        let mut k = 0;
        let mut prev_t = ds.t0;
        let mut a = ds.t0;
        while a.0 + window_us <= ds.t_end.0 {
            let b = TimeUs(a.0 + window_us);
            // Commanded distance and heading change over (a, b]; moving at any time in it.
            let (mut dist, mut turn, mut moving) = (0.0, 0.0, false);
            while let Some(s) = drive.get(k) {
                let from = prev_t.max(a);
                let to = s.t.min(b);
                if to > from {
                    let dt = to.secs_since(from);
                    dist += s.speed_m_s * dt;
                    turn += s.yaw_rate_rad_s * dt;
                    moving |= s.speed_m_s != 0.0 || s.yaw_rate_rad_s != 0.0;
                }
                if s.t > b {
                    break;
                }
                prev_t = s.t;
                k += 1;
            }
            if moving
                && let (Some(pa), Some(pb)) = (truth_at(&r.truth, a, MAX_TRUTH_GAP_US), truth_at(&r.truth, b, MAX_TRUTH_GAP_US))
            {
                let dyaw = wrap_angle(pb.yaw_rad - pa.yaw_rad);
                let mid = pa.yaw_rad + 0.5 * dyaw;
                let along = (pb.n_m - pa.n_m) * mid.cos() + (pb.e_m - pa.e_m) * mid.sin();
                dd.push(along - dist);
                commanded.push(dist);
                dh.push(wrap_angle(dyaw - turn));
            }
            a = b;
        }
    }
    NoiseEstimate {
        landmark_range_m: robust_stat(&lr),
        landmark_bearing_rad: robust_stat(&lb),
        robot_range_m: robust_stat(&rr),
        robot_bearing_rad: robust_stat(&rb),
        window_distance_m: robust_stat(&dd),
        window_heading_rad: robust_stat(&dh),
        window_s,
        window_commanded_m: commanded.iter().sum::<f64>() / commanded.len().max(1) as f64,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_committed_figures_are_valid() {
        let m = NoiseModel::mrclam();
        assert!(m.robot_range_bias_m > 0.0);
        let bad = MRCLAM_NOISE_TOML.replace("gate_probability = ", "gate_probability = 2.0 #");
        assert!(NoiseModel::from_toml_str(&bad).unwrap_err().contains("gate_probability"));
    }

    #[test]
    fn robust_stat_drops_gross_outliers_only() {
        let mut v: Vec<f64> = (0..1000).map(|k| ((k * 7919) % 1000) as f64 / 1000.0 - 0.5).collect();
        let plain = robust_stat(&v);
        assert_eq!(plain.outliers, 0);
        assert!((plain.sigma - (1.0f64 / 12.0).sqrt()).abs() < 0.01, "{plain:?}");
        v.extend([50.0, -80.0]);
        let s = robust_stat(&v);
        assert_eq!((s.n, s.outliers), (1000, 2));
        assert!((s.mean - plain.mean).abs() < 1e-12);
    }
}
