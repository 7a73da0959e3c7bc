//! Running a whole team under one cooperative-localization method, on the same inputs and the
//! same code paths: the experiment, the replay and the tests drive a [`Team`]; a node in the field
//! runs the same [`cooperative_update`] on its own copy of the cross-covariances.
//!
//! The caller owns the platform models: it propagates each platform through
//! [`Team::filter_mut`] (the model-specific inputs: IMU samples, wheel speeds, ...) and hands
//! linearised local measurements to [`Team::local_update`] and ranges to
//! [`Team::cooperative_event`], which dispatch on the method.

use nalgebra::DVector;
use serde::{Deserialize, Serialize};

use super::EstimationError;
use super::ci::ci_update;
use super::coop::{
    CoopMeasurement, Correction, CrossCovariances, CrossMode, UpdateOptions, centralized_local_update, cooperative_update,
    cooperative_update_with,
};
use super::kalman::{self, LinearizedMeasurement, UpdateDiagnostics};
use super::platform::{PlatformFilter, PlatformId, Snapshot};

/// The cooperative-localization methods cooploc compares.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum Method {
    /// Each platform on its own sensors; ranges are ignored.
    DeadReckoning,
    /// Joint range update with cross-covariances taken as zero at every event (the paper's
    /// "non-covariance transfer" mode).
    NoPropagation,
    /// The paper's method: cross-covariances rebuilt from the recursive coefficient matrices.
    Decentralized,
    /// One joint EKF over all platforms that processes every measurement jointly, local ones
    /// included (the optimal reference; needs a central computer).
    Centralized,
    /// Pairwise covariance intersection (consistent under any unknown correlation).
    CovarianceIntersection,
}

impl Method {
    pub const ALL: [Method; 5] = [
        Method::DeadReckoning,
        Method::NoPropagation,
        Method::Decentralized,
        Method::Centralized,
        Method::CovarianceIntersection,
    ];

    /// Short name used on the command line, in files and on the wire.
    pub fn short_name(self) -> &'static str {
        match self {
            Method::DeadReckoning => "dr",
            Method::NoPropagation => "naive",
            Method::Decentralized => "dcl",
            Method::Centralized => "centralized",
            Method::CovarianceIntersection => "ci",
        }
    }

    /// Parses a [`Method::short_name`].
    pub fn from_short_name(s: &str) -> Option<Method> {
        Method::ALL.into_iter().find(|m| m.short_name() == s)
    }

    /// Whether the method needs the recursive coefficient matrices.
    pub fn needs_psi(self) -> bool {
        matches!(self, Method::Decentralized | Method::Centralized)
    }
}

impl std::fmt::Display for Method {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.short_name())
    }
}

/// A team of platforms under one method.
#[derive(Debug, Clone)]
pub struct Team<F> {
    method: Method,
    ids: Vec<PlatformId>,
    filters: Vec<F>,
    cross: CrossCovariances,
}

impl<F: PlatformFilter> Team<F> {
    /// Builds a team; ids must be distinct.
    pub fn new(method: Method, members: Vec<(PlatformId, F)>) -> Result<Self, EstimationError> {
        let mut ids = Vec::with_capacity(members.len());
        let mut filters = Vec::with_capacity(members.len());
        for (id, mut f) in members {
            if ids.contains(&id) {
                return Err(EstimationError::DuplicatePlatform(id));
            }
            f.set_track_psi(method.needs_psi());
            ids.push(id);
            filters.push(f);
        }
        Ok(Self { method, ids, filters, cross: CrossCovariances::new() })
    }

    pub fn method(&self) -> Method {
        self.method
    }

    pub fn ids(&self) -> &[PlatformId] {
        &self.ids
    }

    fn index(&self, id: PlatformId) -> Result<usize, EstimationError> {
        self.ids.iter().position(|&i| i == id).ok_or(EstimationError::UnknownPlatform(id))
    }

    pub fn filter(&self, id: PlatformId) -> Option<&F> {
        self.index(id).ok().map(|i| &self.filters[i])
    }

    /// The platform's own filter, for model-specific propagation.
    pub fn filter_mut(&mut self, id: PlatformId) -> Option<&mut F> {
        self.index(id).ok().map(|i| &mut self.filters[i])
    }

    /// Stored cross-covariances (empty unless the method propagates them).
    pub fn cross(&self) -> &CrossCovariances {
        &self.cross
    }

    fn snapshots(&self) -> Vec<Snapshot> {
        self.ids.iter().zip(&self.filters).map(|(&id, f)| f.snapshot(id)).collect()
    }

    /// The decentralized joint update as the nodes run it: among the platforms the
    /// measurements involve, each other one a bystander that takes its share
    /// ([`super::coop::split_ranged`]); the participants' corrections are returned, to write
    /// back.
    fn decentralized_event(
        &mut self,
        measurements: &[CoopMeasurement],
        opts: UpdateOptions,
    ) -> Result<super::coop::EventOutcome, EstimationError> {
        let (ranged, bystanders) = super::coop::split_ranged(&self.snapshots(), measurements);
        let opts = UpdateOptions { bystanders, ..opts };
        let out = cooperative_update_with(&mut self.cross, &ranged, measurements, &opts)?;
        for s in &out.bystanders {
            let i = self.index(s.id)?;
            self.filters[i].apply_bystander(&s.a, &s.b)?;
        }
        Ok(out)
    }

    fn write_back(&mut self, corrections: &[Correction]) -> Result<(), EstimationError> {
        for c in corrections {
            let i = self.index(c.id)?;
            self.filters[i].apply_joint(&c.dx, &c.p)?;
        }
        Ok(())
    }

    /// A measurement of platform `id`'s own error state. The centralized EKF applies it to the
    /// joint state (moving every correlated platform); every other method to that platform only.
    pub fn local_update(&mut self, id: PlatformId, meas: &LinearizedMeasurement) -> Result<UpdateDiagnostics, EstimationError> {
        let i = self.index(id)?;
        if self.method != Method::Centralized {
            return self.filters[i].update_local(meas);
        }
        meas.validate(self.filters[i].dim())?;
        let snapshots = self.snapshots();
        let outcome = centralized_local_update(&mut self.cross, &snapshots, &[(id, meas)])?;
        self.write_back(&outcome.corrections)?;
        Ok(outcome.diagnostics)
    }

    /// Several simultaneous local measurements (one epoch). The centralized EKF processes them as
    /// one stacked joint update (what a central computer does with one epoch's measurements, and
    /// equal to processing them one by one for linear models); every other method applies each to
    /// its own platform. Returns one diagnostics entry per measurement, or one for the stacked
    /// update of the centralized EKF.
    pub fn local_updates(
        &mut self,
        batch: &[(PlatformId, LinearizedMeasurement)],
    ) -> Result<Vec<UpdateDiagnostics>, EstimationError> {
        if self.method != Method::Centralized || batch.len() < 2 {
            return batch.iter().map(|(id, m)| self.local_update(*id, m)).collect();
        }
        let mut joint = Vec::with_capacity(batch.len());
        for (id, meas) in batch {
            meas.validate(self.filters[self.index(*id)?].dim())?;
            joint.push((*id, meas));
        }
        let snapshots = self.snapshots();
        let outcome = centralized_local_update(&mut self.cross, &snapshots, &joint)?;
        self.write_back(&outcome.corrections)?;
        Ok(vec![outcome.diagnostics])
    }

    /// [`Team::local_update`] behind a chi-square gate: a measurement whose normalised
    /// innovation squared against the platform's own covariance exceeds `gate[m]` (`m` its
    /// size, 1 or 2; see [`UpdateOptions::gate_for_probability`]) is not applied (`Ok(None)`).
    /// The own covariance is the prior every method uses for a local measurement (the
    /// centralized EKF's marginal included), so every method gates the same innovation alike.
    pub fn gated_local_update(
        &mut self,
        id: PlatformId,
        meas: &LinearizedMeasurement,
        gate: [f64; 3],
    ) -> Result<Option<UpdateDiagnostics>, EstimationError> {
        Ok(self.robust_local_update(id, meas, gate, None)?.map(|(d, _)| d))
    }

    /// [`Team::gated_local_update`] with Huber weighting (see [`UpdateOptions::huber_nis`]): a
    /// measurement that passes the gate but whose NIS exceeds `huber_nis * m / 2` is applied
    /// with its noise covariance divided by its weight. Returns the diagnostics and the weight
    /// (1 when unweighted), or `None` when gated.
    pub fn robust_local_update(
        &mut self,
        id: PlatformId,
        meas: &LinearizedMeasurement,
        gate: [f64; 3],
        huber_nis: Option<f64>,
    ) -> Result<Option<(UpdateDiagnostics, f64)>, EstimationError> {
        let i = self.index(id)?;
        let p = self.filters[i].covariance();
        meas.validate(p.nrows())?;
        let v = nis(&meas.h, &p, meas);
        if v > gate_for(gate, meas.len()) {
            return Ok(None);
        }
        let w = huber_weight(huber_nis, v, meas.len());
        if w < 1.0 {
            let weighted = LinearizedMeasurement { r: &meas.r / w, ..meas.clone() };
            return self.local_update(id, &weighted).map(|d| Some((d, w)));
        }
        self.local_update(id, meas).map(|d| Some((d, 1.0)))
    }

    /// [`Team::cooperative_event`] behind a chi-square gate (see [`Team::gated_local_update`]):
    /// each measurement's own innovation is tested against the prior the method uses (the
    /// rebuilt cross-covariances for dcl and the centralized EKF, zero cross-covariances for the
    /// naive filter and for covariance intersection) and left out above the gate. Returns the
    /// diagnostics and how many measurements were left out. With every measurement left out,
    /// dcl and the centralized EKF still close the epoch (posterior = prior, Psi reset), as
    /// every node does.
    pub fn gated_cooperative_event(
        &mut self,
        measurements: &[CoopMeasurement],
        gate: [f64; 3],
    ) -> Result<(Option<UpdateDiagnostics>, usize), EstimationError> {
        let (d, weights) = self.robust_cooperative_event(measurements, gate, None)?;
        Ok((d, weights.iter().filter(|&&w| w == 0.0).count()))
    }

    /// [`Team::gated_cooperative_event`] with Huber weighting of each measurement that passes
    /// the gate (see [`UpdateOptions::huber_nis`]), against the same prior. Returns the
    /// diagnostics and each measurement's weight: 0 gated, 1 unweighted (empty for dead
    /// reckoning and for no measurement).
    pub fn robust_cooperative_event(
        &mut self,
        measurements: &[CoopMeasurement],
        gate: [f64; 3],
        huber_nis: Option<f64>,
    ) -> Result<(Option<UpdateDiagnostics>, Vec<f64>), EstimationError> {
        if measurements.is_empty() || self.method == Method::DeadReckoning {
            return Ok((None, Vec::new()));
        }
        let opts = |mode| UpdateOptions { gate_chi2: Some(gate), huber_nis, ..UpdateOptions::new(mode) };
        let snapshots = self.snapshots();
        let weights_of = |out: &super::coop::EventOutcome| {
            if out.robust_weights.len() == measurements.len() {
                out.robust_weights.clone()
            } else {
                (0..measurements.len()).map(|i| if out.gated.contains(&i) { 0.0 } else { 1.0 }).collect()
            }
        };
        let (corrections, diagnostics, weights) = match self.method {
            Method::DeadReckoning => unreachable!("returned above"),
            Method::CovarianceIntersection => {
                let mut kept = Vec::with_capacity(measurements.len());
                let mut weights = Vec::with_capacity(measurements.len());
                for m in measurements {
                    let parts = m.linearize(|id| snapshots.iter().find(|s| s.id == id))?;
                    let mut s = parts[0].1.r.clone();
                    for (id, lin) in &parts {
                        let p = &snapshots[self.index(*id)?].covariance;
                        s += &lin.h * p * lin.h.transpose();
                    }
                    let v = innovation_nis(&s, &parts[0].1.residual)?;
                    if v <= gate_for(gate, m.len()) {
                        let w = huber_weight(huber_nis, v, m.len());
                        kept.push(if w < 1.0 { scale_noise(m, 1.0 / w) } else { m.clone() });
                        weights.push(w);
                    } else {
                        weights.push(0.0);
                    }
                }
                if kept.is_empty() {
                    return Ok((None, weights));
                }
                (ci_update(&snapshots, &kept)?, None, weights)
            }
            Method::NoPropagation => {
                let out =
                    cooperative_update_with(&mut CrossCovariances::new(), &snapshots, measurements, &opts(CrossMode::Ignore))?;
                let w = weights_of(&out);
                (out.corrections, Some(out.diagnostics), w)
            }
            Method::Decentralized => {
                let out = self.decentralized_event(measurements, opts(CrossMode::Propagate))?;
                let w = weights_of(&out);
                (out.corrections, Some(out.diagnostics), w)
            }
            Method::Centralized => {
                let out = cooperative_update_with(&mut self.cross, &snapshots, measurements, &opts(CrossMode::Propagate))?;
                let w = weights_of(&out);
                (out.corrections, Some(out.diagnostics), w)
            }
        };
        self.write_back(&corrections)?;
        Ok((diagnostics, weights))
    }

    /// A ranging epoch: every platform broadcasts and all take the joint update of `measurements`.
    /// Returns the innovation statistics, or `None` for dead reckoning (ranges ignored) and for
    /// covariance intersection (pairwise, no single innovation).
    pub fn cooperative_event(&mut self, measurements: &[CoopMeasurement]) -> Result<Option<UpdateDiagnostics>, EstimationError> {
        if measurements.is_empty() {
            return Ok(None);
        }
        let (corrections, diagnostics) = match self.method {
            Method::DeadReckoning => return Ok(None),
            Method::CovarianceIntersection => (ci_update(&self.snapshots(), measurements)?, None),
            Method::NoPropagation => {
                let out = cooperative_update(&mut CrossCovariances::new(), &self.snapshots(), measurements, CrossMode::Ignore)?;
                (out.corrections, Some(out.diagnostics))
            }
            Method::Decentralized => {
                let out = self.decentralized_event(measurements, UpdateOptions::new(CrossMode::Propagate))?;
                (out.corrections, Some(out.diagnostics))
            }
            Method::Centralized => {
                let snapshots = self.snapshots();
                let out = cooperative_update(&mut self.cross, &snapshots, measurements, CrossMode::Propagate)?;
                (out.corrections, Some(out.diagnostics))
            }
        };
        self.write_back(&corrections)?;
        Ok(diagnostics)
    }
}

/// The gate for a measurement of `m` scalars (larger sizes take the two-scalar quantile's
/// scaling: `gate[2] * m / 2`, close to the chi-square quantile for the probabilities used).
fn gate_for(gate: [f64; 3], m: usize) -> f64 {
    match m {
        0 | 1 => gate[1],
        2 => gate[2],
        _ => gate[2] * m as f64 / 2.0,
    }
}

/// The Huber weight of a measurement of `m` scalars with NIS `v` (see
/// [`UpdateOptions::huber_nis`]); 1 without weighting.
fn huber_weight(huber_nis: Option<f64>, v: f64, m: usize) -> f64 {
    match huber_nis {
        Some(c) if v > c * m as f64 / 2.0 => (c * m as f64 / 2.0 / v).sqrt(),
        _ => 1.0,
    }
}

/// The measurement with its noise covariance multiplied by `factor`.
fn scale_noise(m: &CoopMeasurement, factor: f64) -> CoopMeasurement {
    let k = factor.sqrt();
    match m.clone() {
        CoopMeasurement::Range { from, to, range_m, sigma_m } => {
            CoopMeasurement::Range { from, to, range_m, sigma_m: sigma_m * k }
        }
        CoopMeasurement::PlanarRange { from, to, range_m, sigma_m } => {
            CoopMeasurement::PlanarRange { from, to, range_m, sigma_m: sigma_m * k }
        }
        CoopMeasurement::RangeBearing { from, to, range_m, bearing_rad, sigma_range_m, sigma_bearing_rad } => {
            CoopMeasurement::RangeBearing {
                from,
                to,
                range_m,
                bearing_rad,
                sigma_range_m: sigma_range_m * k,
                sigma_bearing_rad: sigma_bearing_rad * k,
            }
        }
        CoopMeasurement::Linear { blocks, residual, r } => CoopMeasurement::Linear { blocks, residual, r: r * factor },
    }
}

/// `r^T S^-1 r` for the innovation covariance `H P H^T + R`.
fn nis(h: &nalgebra::DMatrix<f64>, p: &nalgebra::DMatrix<f64>, meas: &LinearizedMeasurement) -> f64 {
    let s = h * p * h.transpose() + &meas.r;
    innovation_nis(&s, &meas.residual).unwrap_or(f64::INFINITY)
}

fn innovation_nis(s: &nalgebra::DMatrix<f64>, r: &DVector<f64>) -> Result<f64, EstimationError> {
    let mut s = s.clone();
    kalman::symmetrize(&mut s);
    let chol = s.cholesky().ok_or(EstimationError::NotPositiveDefinite { what: "innovation covariance H P H^T + R" })?;
    Ok(r.dot(&chol.solve(r)))
}

/// Stacks corrections into one vector (for tests and diagnostics).
pub fn stack_corrections(corrections: &[Correction]) -> DVector<f64> {
    let n = corrections.iter().map(|c| c.dx.len()).sum();
    let mut out = DVector::zeros(n);
    let mut o = 0;
    for c in corrections {
        out.rows_mut(o, c.dx.len()).copy_from(&c.dx);
        o += c.dx.len();
    }
    out
}
