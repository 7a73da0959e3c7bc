//! The cooperative filter of paper Steps 4-5: the joint state of the platforms that broadcast
//! at a ranging epoch, its covariance rebuilt from their broadcasts and the cross-covariances
//! stored at the last event (Eq. 10), the range update (Eqs. 11-13), and the storage of the new
//! cross-covariances.
//!
//! # Why the decentralized filter is exact
//!
//! Consider one joint filter over the stacked error states of all platforms, in which a
//! platform's *local* measurement corrects that platform only (its gain is nonzero only in its
//! own rows: `K = [0 .. K_i .. 0]`, with `K_i` the optimal gain for `P_ii`). Then, in Joseph
//! form, the joint covariance evolves blockwise as
//!
//! ```text
//! time update:    P_ij <- Phi_i P_ij Phi_j^T              (+ Q_i on the diagonal block only)
//! local update:   P_ij <- (I - K_i H_i) P_ij              (j != i)
//!                 P_ii <- (I - K_i H_i) P_ii (..)^T + K_i R K_i^T
//! ```
//!
//! because the process noise and the local measurement noise of one platform are independent of
//! every other platform (paper Eq. 9). So `P_ij(now) = Psi_i C_ij Psi_j^T` with `C_ij` the cross
//! block right after the last joint update and `Psi_i` the product of every factor applied to
//! platform `i` since then (Eq. 10). Platform `i` knows `P_ii` and `Psi_i`; every node stores
//! the same `C_ij`; so at a ranging epoch every node can rebuild the joint covariance *exactly*,
//! and, running the same joint update on the same broadcasts, obtains the same posterior. This
//! is an identity, not an approximation: for linear-Gaussian models the decentralized estimates
//! equal those of that joint filter to rounding (see `tests/equivalence.rs`).
//!
//! It is *not* the full centralized EKF (see [`super::team::Method::Centralized`]): there, a
//! platform's local measurement also moves the other platforms through their correlation
//! (`K_j = P_ji H_i^T S^-1 != 0`). The decentralized filter forgoes that coupling between
//! events, so it is slightly suboptimal, but still consistent: its covariance is the true
//! covariance of its own (suboptimal) estimation error. The gap is small when local
//! measurements say little about what the correlation carries (an odometer does not observe
//! position), which the experiment measures.
//!
//! # Platforms that miss an event
//!
//! A platform that does not broadcast at an epoch is not part of the joint state: it is not
//! corrected, and its `Psi` keeps accumulating. The stored cross block `C_ik` of a participant
//! `i` with such a platform `k` must stay in `k`'s reference, so it is carried through the
//! update as a passive column `X_ik = Psi_i C_ik` and stored as `(I - K H) X`. The invariant
//! `P_ik(now) = Psi_i C_ik Psi_k^T` holds for every pair at all times.
//!
//! # When the stores differ: the covariance-intersection bound
//!
//! The exact method needs every node to hold the same store. When they do not (a node missed an
//! epoch, ran it on other records, restarted), no node knows the true cross-covariances any
//! more. [`JointPrior::Bound`] then replaces the joint prior of the participants by
//!
//! ```text
//! P_bound = blockdiag(P_11 / w_1, ..., P_NN / w_N),   w_i > 0,  sum w_i = 1
//! ```
//!
//! which bounds every joint covariance with those diagonal blocks whatever its cross blocks:
//! for any vector `x = (x_1..x_N)`, `x^T P x = E[(sum x_i^T e_i)^2] <= (sum_i x_i^T P_ii x_i / w_i)
//! (sum_i w_i)` by Cauchy-Schwarz. A participant known to be uncorrelated with everyone (a fresh
//! joiner) needs no weight: its block enters as it is and the others' weights sum to 1. A Kalman
//! update from an upper bound, in Joseph form with the gain that bound gives, keeps an upper bound
//! of the true error covariance, and so does every later step (time updates, local updates and
//! exact joint updates all map `P_computed - P_true >= 0` to a congruent, still PSD, difference):
//! the filter stays consistent, at the cost of the inflation. The weights minimise the sum of the
//! inflated position variances, `w_i ~ sqrt(tr P_ii,pos)`, computed from the broadcasts alone,
//! so every node picks the same. After a bound update the store keeps only the participants'
//! new cross blocks, and the exact method resumes at the next epoch.
//!
//! # Gating
//!
//! With [`UpdateOptions::gate_chi2`], each measurement's own innovation is tested against its
//! predicted covariance from the joint prior (`r^T S_mm^-1 r` against a chi-square quantile);
//! those that fail (a non-line-of-sight range, a forged one) are left out of the update and
//! reported. The test depends only on the broadcasts and the store, so every node leaves out
//! the same ones.

use std::collections::{BTreeMap, BTreeSet};

use nalgebra::{DMatrix, DVector};

use super::EstimationError;
use super::dense;
use super::inputs::RangeSample;
use super::kalman::{self, LinearizedMeasurement, UpdateDiagnostics};
use super::platform::{PlatformId, Snapshot};
use super::unicycle::wrap_angle;

/// A measurement that relates the states of several platforms.
#[derive(Debug, Clone, PartialEq)]
pub enum CoopMeasurement {
    /// 3-D distance between two platforms (paper Eq. 11).
    Range { from: PlatformId, to: PlatformId, range_m: f64, sigma_m: f64 },
    /// Horizontal distance (N, E only) between two platforms.
    PlanarRange { from: PlatformId, to: PlatformId, range_m: f64, sigma_m: f64 },
    /// Horizontal range and bearing of `to` seen from `from`; the bearing is measured from
    /// `from`'s heading, clockwise seen from above. `from` must have a heading state.
    RangeBearing { from: PlatformId, to: PlatformId, range_m: f64, bearing_rad: f64, sigma_range_m: f64, sigma_bearing_rad: f64 },
    /// A generic linearised measurement: `residual ~= sum_i H_i dx_i + v`, `v ~ N(0, r)`.
    Linear { blocks: Vec<(PlatformId, DMatrix<f64>)>, residual: DVector<f64>, r: DMatrix<f64> },
}

impl From<&RangeSample> for CoopMeasurement {
    /// A measured range as the paper's 3-D range measurement (Eq. 11).
    fn from(r: &RangeSample) -> Self {
        CoopMeasurement::Range { from: r.from, to: r.to, range_m: r.range_m, sigma_m: r.sigma_m }
    }
}

impl CoopMeasurement {
    /// A measurement of platform `id`'s own error state as a joint one (one block).
    pub fn local(id: PlatformId, m: &LinearizedMeasurement) -> Self {
        CoopMeasurement::Linear { blocks: vec![(id, m.h.clone())], residual: m.residual.clone(), r: m.r.clone() }
    }

    /// The platforms this measurement involves.
    pub fn platforms(&self) -> Vec<PlatformId> {
        match self {
            CoopMeasurement::Range { from, to, .. }
            | CoopMeasurement::PlanarRange { from, to, .. }
            | CoopMeasurement::RangeBearing { from, to, .. } => vec![*from, *to],
            CoopMeasurement::Linear { blocks, .. } => blocks.iter().map(|(id, _)| *id).collect(),
        }
    }

    /// Number of scalar measurements.
    pub fn len(&self) -> usize {
        match self {
            CoopMeasurement::Range { .. } | CoopMeasurement::PlanarRange { .. } => 1,
            CoopMeasurement::RangeBearing { .. } => 2,
            CoopMeasurement::Linear { residual, .. } => residual.len(),
        }
    }

    /// Always false: every variant holds at least one scalar (an empty `Linear` is rejected
    /// when linearised).
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// Linearises about the broadcast geometry: Jacobian blocks per platform, residual, noise.
    pub fn linearize<'a>(
        &self,
        snapshot: impl Fn(PlatformId) -> Option<&'a Snapshot>,
    ) -> Result<Vec<(PlatformId, LinearizedMeasurement)>, EstimationError> {
        let get = |id| snapshot(id).ok_or(EstimationError::UnknownPlatform(id));
        let sigma_ok =
            |s: f64, what| if s.is_finite() && s > 0.0 { Ok(()) } else { Err(EstimationError::InvalidValue { what, value: s }) };
        match self {
            CoopMeasurement::Range { from, to, range_m, sigma_m }
            | CoopMeasurement::PlanarRange { from, to, range_m, sigma_m } => {
                let planar = matches!(self, CoopMeasurement::PlanarRange { .. });
                if from == to {
                    return Err(EstimationError::NotApplicable("range from a platform to itself"));
                }
                if !range_m.is_finite() {
                    return Err(EstimationError::NonFinite { what: "range" });
                }
                sigma_ok(*sigma_m, "range sigma")?;
                let (a, b) = (get(*from)?, get(*to)?);
                let mut d = a.geometry.position_ned_m - b.geometry.position_ned_m;
                if planar {
                    d[2] = 0.0;
                }
                let predicted = d.norm();
                if predicted < 1e-6 {
                    return Err(EstimationError::NotApplicable("range between co-located estimates has no direction"));
                }
                let u = d / predicted;
                let mut out = Vec::with_capacity(2);
                for (snap, sign) in [(a, 1.0), (b, -1.0)] {
                    let mut h = DMatrix::zeros(1, snap.dim());
                    for (axis, idx) in snap.geometry.position_index.iter().enumerate() {
                        if let Some(i) = idx {
                            h[(0, *i)] = sign * u[axis];
                        }
                    }
                    out.push((snap.id, h));
                }
                Ok(split(out, DVector::from_element(1, range_m - predicted), DMatrix::from_element(1, 1, sigma_m * sigma_m)))
            }
            CoopMeasurement::RangeBearing { from, to, range_m, bearing_rad, sigma_range_m, sigma_bearing_rad } => {
                if from == to {
                    return Err(EstimationError::NotApplicable("bearing from a platform to itself"));
                }
                if !range_m.is_finite() || !bearing_rad.is_finite() {
                    return Err(EstimationError::NonFinite { what: "range-bearing measurement" });
                }
                sigma_ok(*sigma_range_m, "range sigma")?;
                sigma_ok(*sigma_bearing_rad, "bearing sigma")?;
                let (a, b) = (get(*from)?, get(*to)?);
                let heading =
                    a.geometry.heading.ok_or(EstimationError::NotApplicable("bearing from a platform without heading"))?;
                let dn = b.geometry.position_ned_m[0] - a.geometry.position_ned_m[0];
                let de = b.geometry.position_ned_m[1] - a.geometry.position_ned_m[1];
                let rho2 = dn * dn + de * de;
                let rho = rho2.sqrt();
                if rho < 1e-6 {
                    return Err(EstimationError::NotApplicable("bearing between co-located estimates"));
                }
                let predicted_bearing = de.atan2(dn) - heading.yaw_rad;
                // d(rho)/d(p_to) = [dn, de]/rho ; d(beta)/d(p_to) = [-de, dn]/rho^2 ; d(beta)/d(yaw_from) = -1.
                let rows = [[dn / rho, de / rho], [-de / rho2, dn / rho2]];
                let mut out = Vec::with_capacity(2);
                for (snap, sign) in [(a, -1.0), (b, 1.0)] {
                    let mut h = DMatrix::zeros(2, snap.dim());
                    for (axis, idx) in snap.geometry.position_index.iter().take(2).enumerate() {
                        if let Some(i) = *idx {
                            h[(0, i)] = sign * rows[0][axis];
                            h[(1, i)] = sign * rows[1][axis];
                        }
                    }
                    if sign < 0.0 {
                        h[(1, heading.index)] -= 1.0;
                    }
                    out.push((snap.id, h));
                }
                let residual = DVector::from_vec(vec![range_m - rho, wrap_angle(bearing_rad - predicted_bearing)]);
                let r = DMatrix::from_diagonal(&DVector::from_vec(vec![sigma_range_m.powi(2), sigma_bearing_rad.powi(2)]));
                Ok(split(out, residual, r))
            }
            CoopMeasurement::Linear { blocks, residual, r } => {
                if residual.is_empty() || blocks.is_empty() {
                    return Err(EstimationError::NotApplicable("empty linear measurement"));
                }
                let mut out = Vec::with_capacity(blocks.len());
                for (id, h) in blocks {
                    let snap = get(*id)?;
                    if out.iter().any(|(seen, _)| seen == id) {
                        return Err(EstimationError::DuplicatePlatform(*id));
                    }
                    if h.nrows() != residual.len() || h.ncols() != snap.dim() {
                        return Err(EstimationError::DimensionMismatch {
                            what: "linear measurement block",
                            expected: snap.dim(),
                            got: h.ncols(),
                        });
                    }
                    out.push((*id, h.clone()));
                }
                let meas = split(out, residual.clone(), r.clone());
                for (id, m) in &meas {
                    m.validate(get(*id)?.dim())?;
                }
                Ok(meas)
            }
        }
    }
}

/// Pairs each platform's Jacobian block with the shared residual and noise.
fn split(
    blocks: Vec<(PlatformId, DMatrix<f64>)>,
    residual: DVector<f64>,
    r: DMatrix<f64>,
) -> Vec<(PlatformId, LinearizedMeasurement)> {
    blocks.into_iter().map(|(id, h)| (id, LinearizedMeasurement { h, residual: residual.clone(), r: r.clone() })).collect()
}

/// The cross-covariance blocks `C_ij` stored after the last joint update that involved both
/// platforms (paper Step 5: "saved locally to use ... before the next collaborative
/// localization"). The current cross-covariance is `Psi_i C_ij Psi_j^T`; a missing block is zero
/// (no correlation yet: the first event, paper Step 5's closing note).
///
/// Next to the blocks, the store keeps a [`StoreRef`] per platform: which joint update last reset
/// that platform's `Psi`, as the holder of the store saw it. The blocks of platform `k` are in
/// the reference of `k`'s own `Psi` only if `k` itself last reset it at that same update; a node
/// compares the two before it trusts a store (see `node::core`).
#[derive(Debug, Clone, Default)]
pub struct CrossCovariances {
    blocks: BTreeMap<(PlatformId, PlatformId), DMatrix<f64>>,
    refs: BTreeMap<PlatformId, StoreRef>,
    /// [`Self::digest`], once computed; emptied by every change. A node takes the digest of
    /// its store several times per epoch, and a 64-member team's store is 4 MB to hash.
    digest: std::sync::OnceLock<u64>,
}

impl PartialEq for CrossCovariances {
    fn eq(&self, other: &Self) -> bool {
        self.blocks == other.blocks && self.refs == other.refs
    }
}

/// The joint update that last reset a platform's `Psi`: its epoch and a token of what it ran on
/// (participants and store digests; 0 means none: the platform started independently of the
/// team at or after `epoch`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub struct StoreRef {
    pub epoch: u32,
    pub token: u64,
}

impl StoreRef {
    /// A platform that started independently of everyone, first heard of at `epoch`.
    pub fn fresh(epoch: u32) -> Self {
        Self { epoch, token: 0 }
    }

    pub fn is_fresh(&self) -> bool {
        self.token == 0
    }

    /// A platform that started correlated with someone it cannot name (from a teammate's
    /// estimate, a hand-over), first heard of at `epoch`: a reference no store holds, so that only
    /// the bound applies to it.
    pub fn unplaced(epoch: u32) -> Self {
        Self { epoch, token: u64::MAX }
    }

    /// Before the platform's first joint update (fresh or unplaced): `epoch` is then the epoch
    /// it was first heard of at, its first broadcast.
    pub fn before_any_update(&self) -> bool {
        self.token == 0 || self.token == u64::MAX
    }

    /// The reference a joint update at `epoch` on `participants` (sorted), whose records carried
    /// `digests`, gives each participant: equal on every node that ran the same update.
    pub fn of_update(epoch: u32, participants: &[PlatformId], digests: &[u64]) -> Self {
        let mut h = Fnv::new();
        h.eat(&epoch.to_le_bytes());
        for p in participants {
            h.eat(&p.to_le_bytes());
        }
        for d in digests {
            h.eat(&d.to_le_bytes());
        }
        Self { epoch, token: h.finish() }
    }
}

/// FNV-1a, 64 bit (never 0 at the end: 0 means "none" on the wire).
struct Fnv(u64);

impl Fnv {
    fn new() -> Self {
        Self(0xcbf2_9ce4_8422_2325)
    }

    fn eat(&mut self, bytes: &[u8]) {
        for b in bytes {
            self.0 ^= u64::from(*b);
            self.0 = self.0.wrapping_mul(0x0000_0100_0000_01b3);
        }
    }

    fn finish(&self) -> u64 {
        self.0.max(1)
    }
}

/// Why a store could not be rebuilt from its parts.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum StoreError {
    #[error("store block ({0}, {1}) is not an ordered pair of two platforms")]
    Pair(PlatformId, PlatformId),
    #[error("store block ({0}, {1}) is {2}x{3}, which does not match the other blocks of those platforms")]
    Shape(PlatformId, PlatformId, usize, usize),
    #[error("store block ({0}, {1}) has a non-finite value")]
    NonFinite(PlatformId, PlatformId),
}

impl CrossCovariances {
    pub fn new() -> Self {
        Self::default()
    }

    /// `C_ij` (`n_i x n_j`), if stored.
    pub fn get(&self, i: PlatformId, j: PlatformId) -> Option<DMatrix<f64>> {
        if i < j { self.blocks.get(&(i, j)).cloned() } else { self.blocks.get(&(j, i)).map(|m| m.transpose()) }
    }

    /// `C_ij` read in place: the stored block of the pair, transposed when `i > j`.
    fn stored(&self, i: PlatformId, j: PlatformId) -> Option<dense::Strided<'_>> {
        if i < j {
            self.blocks.get(&(i, j)).map(dense::Strided::of)
        } else {
            self.blocks.get(&(j, i)).map(|m| dense::Strided::of(m).t())
        }
    }

    fn set(&mut self, i: PlatformId, j: PlatformId, c: DMatrix<f64>) {
        self.digest.take();
        if i < j {
            self.blocks.insert((i, j), c);
        } else {
            self.blocks.insert((j, i), c.transpose());
        }
    }

    /// Forgets every block that involves `id` (a platform that left the team for good).
    pub fn forget(&mut self, id: PlatformId) {
        self.digest.take();
        self.blocks.retain(|(a, b), _| *a != id && *b != id);
        self.refs.remove(&id);
    }

    /// Forgets everything.
    pub fn clear(&mut self) {
        self.digest.take();
        self.blocks.clear();
        self.refs.clear();
    }

    /// The update that last reset `id`'s `Psi`, as this store saw it.
    pub fn reference(&self, id: PlatformId) -> Option<StoreRef> {
        self.refs.get(&id).copied()
    }

    pub fn set_reference(&mut self, id: PlatformId, r: StoreRef) {
        self.digest.take();
        self.refs.insert(id, r);
    }

    /// Every platform's reference, by platform id.
    pub fn references(&self) -> impl Iterator<Item = (PlatformId, StoreRef)> + '_ {
        self.refs.iter().map(|(k, v)| (*k, *v))
    }

    /// Every stored block `((i, j), C_ij)` with `i < j`, in order.
    pub fn blocks(&self) -> impl Iterator<Item = ((PlatformId, PlatformId), &DMatrix<f64>)> + '_ {
        self.blocks.iter().map(|(k, v)| (*k, v))
    }

    /// A store from its blocks (`i < j`, finite, one dimension per platform) and references.
    pub fn from_parts(
        blocks: Vec<((PlatformId, PlatformId), DMatrix<f64>)>,
        refs: Vec<(PlatformId, StoreRef)>,
    ) -> Result<Self, StoreError> {
        let mut store = Self::new();
        let mut dims: BTreeMap<PlatformId, usize> = BTreeMap::new();
        for ((a, b), m) in blocks {
            if a >= b {
                return Err(StoreError::Pair(a, b));
            }
            let fits = |p: PlatformId, n: usize, dims: &mut BTreeMap<PlatformId, usize>| *dims.entry(p).or_insert(n) == n;
            if !fits(a, m.nrows(), &mut dims) || !fits(b, m.ncols(), &mut dims) || m.is_empty() {
                return Err(StoreError::Shape(a, b, m.nrows(), m.ncols()));
            }
            if !m.iter().all(|v| v.is_finite()) {
                return Err(StoreError::NonFinite(a, b));
            }
            store.blocks.insert((a, b), m);
        }
        store.refs = refs.into_iter().collect();
        Ok(store)
    }

    /// A 64-bit digest (FNV-1a) of every stored block, its platform pair and the bits of every
    /// value, and of every reference: two stores have the same digest when they are equal, and
    /// different ones otherwise except with probability about 2^-64. Never 0 (0 means "no store"
    /// on the wire).
    pub fn digest(&self) -> u64 {
        *self.digest.get_or_init(|| self.compute_digest())
    }

    fn compute_digest(&self) -> u64 {
        let mut h = Fnv::new();
        for ((a, b), m) in &self.blocks {
            h.eat(&a.to_le_bytes());
            h.eat(&b.to_le_bytes());
            h.eat(&(m.nrows() as u32).to_le_bytes());
            h.eat(&(m.ncols() as u32).to_le_bytes());
            for v in m.iter() {
                h.eat(&v.to_bits().to_le_bytes());
            }
        }
        for (p, r) in &self.refs {
            h.eat(&p.to_le_bytes());
            h.eat(&r.epoch.to_le_bytes());
            h.eat(&r.token.to_le_bytes());
        }
        h.finish()
    }

    /// Number of stored blocks.
    pub fn len(&self) -> usize {
        self.blocks.len()
    }

    pub fn is_empty(&self) -> bool {
        self.blocks.is_empty()
    }

    /// Every platform that appears in a stored block, with its state dimension.
    fn known_platforms(&self) -> BTreeMap<PlatformId, usize> {
        let mut out = BTreeMap::new();
        for ((a, b), m) in &self.blocks {
            out.insert(*a, m.nrows());
            out.insert(*b, m.ncols());
        }
        out
    }
}

/// Whether a joint update rebuilds the cross-covariances (the paper's method) or takes them as
/// zero (the paper's "non-covariance transfer" mode).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum CrossMode {
    /// Rebuild `P_ij = Psi_i C_ij Psi_j^T` and store the posterior cross blocks.
    Propagate,
    /// Cross blocks are zero at every event, nothing is stored.
    Ignore,
}

/// How the joint prior covariance of the participants is built.
#[derive(Debug, Clone, PartialEq, Default)]
pub enum JointPrior {
    /// From the broadcasts and the store (the paper's exact method).
    #[default]
    Exact,
    /// The covariance-intersection bound (module docs): cross blocks zero, each participant's
    /// own block inflated by its weight (see [`BoundScope`]), except those listed as known to be
    /// uncorrelated with everyone (fresh joiners), which enter as they are.
    Bound { independent: Vec<PlatformId>, scope: BoundScope },
}

/// What a bound prior inflates.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum BoundScope {
    /// The whole state: `P_ii / w_i`. Provably an upper bound, whatever the cross-covariances.
    Full,
    /// The position sub-state and what regresses on it: `P_ii + (1/w_i - 1) P_i,p P_pp^-1 P_p,i`
    /// (`p`: the position indices). An upper bound when the cross-covariances reach a platform's
    /// other states only through their correlation with its position, which is how joint range
    /// updates create them (their gain is `P_i,p (..)`); the part of a state uncorrelated with
    /// position (a bias the ranges never saw) is not inflated, so repeated heals do not compound
    /// where ranges cannot shrink the covariance back.
    #[default]
    Position,
}

/// Options of [`cooperative_update_with`].
#[derive(Debug, Clone, PartialEq)]
pub struct UpdateOptions {
    pub mode: CrossMode,
    pub prior: JointPrior,
    /// Chi-square quantile per degree of freedom count (index 1 for one scalar, 2 for two) a
    /// measurement's own innovation must stay under; `None`: no gate.
    pub gate_chi2: Option<[f64; 3]>,
    /// Huber weighting of each measurement that passes the gate: with `Some(c)`, a
    /// measurement of `m` scalars whose own NIS exceeds `c m / 2` has its noise covariance
    /// divided by the weight `w = sqrt(c m / (2 NIS))` (the Huber weight of its Mahalanobis
    /// distance), so that it pulls like a distance, not like its square. `None`: no weighting.
    pub huber_nis: Option<f64>,
    /// Platforms of the store that did not broadcast and take their own share of the update
    /// (*bystanders*: every node running the update knows they will). With the exact prior,
    /// each gets a [`BystanderShare`] and its cross blocks with every other non-broadcaster are
    /// updated too, so that the team ends where the joint filter over every platform would
    /// (`tests/equivalence.rs`). Any other platform of the store that did not broadcast is
    /// *left out*: it applies nothing, as if its gain were zero (its blocks with the
    /// broadcasters still change, its blocks with the other left-out ones do not). A platform
    /// that broadcast and is listed is refused (`DuplicatePlatform`).
    pub bystanders: Vec<PlatformId>,
}

impl UpdateOptions {
    pub fn new(mode: CrossMode) -> Self {
        Self { mode, prior: JointPrior::Exact, gate_chi2: None, huber_nis: None, bystanders: Vec::new() }
    }

    /// The gate for a false-rejection probability `p` of a consistent filter, per measurement.
    pub fn gate_for_probability(p: f64) -> Option<[f64; 3]> {
        use statrs::distribution::{ChiSquared, ContinuousCDF};
        if !(p > 0.0 && p < 1.0) {
            return None;
        }
        let q = |k: f64| ChiSquared::new(k).map(|d| d.inverse_cdf(1.0 - p)).unwrap_or(f64::INFINITY);
        Some([0.0, q(1.0), q(2.0)])
    }
}

/// One participant's share of a joint update: what its own filter writes back.
#[derive(Debug, Clone, PartialEq)]
pub struct Correction {
    pub id: PlatformId,
    /// Error-state correction to inject.
    pub dx: DVector<f64>,
    /// Posterior covariance of its own error state.
    pub p: DMatrix<f64>,
}

/// A bystander's share of a joint update it did not broadcast for ([`UpdateOptions::bystanders`]),
/// in the coordinates of its store blocks (its `Psi` since its store reference): with
/// `X = Psi_P C_Pk` its column of the participants' cross-covariances and `S` the innovation
/// covariance, `a = X^T H^T S^-1 (z - h)` and `b = X^T H^T S^-1 H X`. The bystander applies
/// `dx = Psi a` and `P - Psi b Psi^T` and keeps its `Psi`
/// ([`crate::estimation::PlatformFilter::apply_bystander`]): its gain is the joint filter's,
/// `K_k = P_kP H^T S^-1`, without its state ever entering the update.
#[derive(Debug, Clone, PartialEq)]
pub struct BystanderShare {
    pub id: PlatformId,
    pub a: DVector<f64>,
    pub b: DMatrix<f64>,
}

/// What a joint update produced.
#[derive(Debug, Clone)]
pub struct EventOutcome {
    /// One entry per broadcast, in broadcast order.
    pub corrections: Vec<Correction>,
    /// Innovation statistics of the stacked measurement.
    pub diagnostics: UpdateDiagnostics,
    /// The joint prior covariance that was used (participants in broadcast order).
    pub prior_covariance: DMatrix<f64>,
    /// Indices into the measurements of those left out by the gate.
    pub gated: Vec<usize>,
    /// The weights of the bound prior, per participant in broadcast order (1 for those not
    /// inflated); empty for the exact prior.
    pub weights: Vec<f64>,
    /// The Huber weight of each measurement ([`UpdateOptions::huber_nis`]): 1 unweighted, 0
    /// gated; empty without weighting.
    pub robust_weights: Vec<f64>,
    /// The share of each bystander the store knows ([`UpdateOptions::bystanders`]), in
    /// platform id order; one the store does not know is uncorrelated with every participant
    /// and has nothing to apply. Empty with the bound prior or without cross-covariances.
    pub bystanders: Vec<BystanderShare>,
}

/// An epoch among the platforms that ranged: the broadcasts of those `measurements` involve
/// (in the order given) and the ids of the others, the bystanders of
/// [`UpdateOptions::bystanders`]. With the exact prior the update on that split ends where the
/// update on every broadcast does (to rounding; the same bits when nobody is left over).
pub fn split_ranged(snapshots: &[Snapshot], measurements: &[CoopMeasurement]) -> (Vec<Snapshot>, Vec<PlatformId>) {
    let involved: BTreeSet<PlatformId> = measurements.iter().flat_map(|m| m.platforms()).collect();
    let (ranged, others): (Vec<&Snapshot>, Vec<&Snapshot>) = snapshots.iter().partition(|s| involved.contains(&s.id));
    (ranged.into_iter().cloned().collect(), others.into_iter().map(|s| s.id).collect())
}

/// The paper's joint update at a ranging epoch, as every node runs it.
///
/// `snapshots` are the broadcasts of the participants (each node includes its own),
/// `measurements` the ranges exchanged for this epoch. Every node that runs this on the same
/// inputs with the same `cross` gets the same result, bit for bit. On error, `cross` is
/// untouched.
pub fn cooperative_update(
    cross: &mut CrossCovariances,
    snapshots: &[Snapshot],
    measurements: &[CoopMeasurement],
    mode: CrossMode,
) -> Result<EventOutcome, EstimationError> {
    cooperative_update_with(cross, snapshots, measurements, &UpdateOptions::new(mode))
}

/// The weights of the bound prior: 1 for the independent participants, `sqrt(tr P_ii,pos)`
/// normalised over the others (or 1 when only one other is left).
fn bound_weights(snapshots: &[Snapshot], independent: &[PlatformId]) -> Vec<f64> {
    let pos_trace = |s: &Snapshot| {
        let t: f64 = s.geometry.position_index.iter().flatten().map(|&i| s.covariance[(i, i)].max(0.0)).sum();
        if t > 0.0 { t.sqrt() } else { 1.0 }
    };
    let group: Vec<usize> = (0..snapshots.len()).filter(|&k| !independent.contains(&snapshots[k].id)).collect();
    let total: f64 = group.iter().map(|&k| pos_trace(&snapshots[k])).sum();
    let mut w = vec![1.0; snapshots.len()];
    if group.len() > 1 {
        for &k in &group {
            w[k] = pos_trace(&snapshots[k]) / total;
        }
    }
    w
}

/// A participant's block of the bound prior for weight `w` (see [`BoundScope`]).
fn inflate(s: &Snapshot, w: f64, scope: BoundScope) -> Result<DMatrix<f64>, EstimationError> {
    let pos: Vec<usize> = s.geometry.position_index.iter().flatten().copied().collect();
    if scope == BoundScope::Full || pos.is_empty() {
        return Ok(&s.covariance / w);
    }
    let p = &s.covariance;
    let cols = p.select_columns(&pos); // n x k: P_i,p
    let pp = cols.select_rows(&pos); // k x k: P_pp
    let chol = pp.cholesky().ok_or(EstimationError::NotPositiveDefinite { what: "a participant's position covariance" })?;
    let g = chol.solve(&cols.transpose()); // P_pp^-1 P_p,i
    let mut out = p + (1.0 / w - 1.0) * &cols * g;
    kalman::symmetrize(&mut out);
    Ok(out)
}

/// The joint prior's cross blocks (paper Eq. 10: `Psi_i C_ij Psi_j^T`) written into `p`, and the
/// known platforms that did not broadcast, carried as passive columns (`Psi_i C_ik`) with their
/// (id, first column, dimension).
#[allow(clippy::type_complexity)]
fn cross_blocks(
    cross: &CrossCovariances,
    snapshots: &[Snapshot],
    offset: &BTreeMap<PlatformId, (usize, usize)>,
    n: usize,
    p: &mut DMatrix<f64>,
) -> Result<(Option<DMatrix<f64>>, Vec<(PlatformId, usize, usize)>), EstimationError> {
    let mut passive_ids = Vec::new();
    let mut passive = None;
    // A broadcast whose size is not the one the store holds for its platform (a forged or
    // mistaken record; a platform that changed its model without a fresh start) is refused,
    // not multiplied.
    for (id, d) in cross.known_platforms() {
        if let Some(&(_, ds)) = offset.get(&id)
            && ds != d
        {
            return Err(EstimationError::DimensionMismatch {
                what: "broadcast state against the stored cross-covariances",
                expected: d,
                got: ds,
            });
        }
    }
    for (a, sa) in snapshots.iter().enumerate() {
        for sb in &snapshots[a + 1..] {
            if let Some(c) = cross.get(sa.id, sb.id) {
                let pij = &sa.psi * c * sb.psi.transpose();
                let ((oa, da), (ob, db)) = (offset[&sa.id], offset[&sb.id]);
                p.view_mut((oa, ob), (da, db)).copy_from(&pij);
                p.view_mut((ob, oa), (db, da)).copy_from(&pij.transpose());
            }
        }
    }
    // Known platforms that did not broadcast: carry their cross blocks as passive columns.
    let absent: Vec<(PlatformId, usize)> =
        cross.known_platforms().into_iter().filter(|(id, _)| !offset.contains_key(id)).collect();
    let width: usize = absent.iter().map(|(_, d)| d).sum();
    if width > 0 {
        let mut x = DMatrix::zeros(n, width);
        let mut col = 0;
        for (k, dk) in &absent {
            for s in snapshots {
                if let Some(c) = cross.get(s.id, *k) {
                    let (o, d) = offset[&s.id];
                    x.view_mut((o, col), (d, *dk)).copy_from(&(&s.psi * c));
                }
            }
            passive_ids.push((*k, col, *dk));
            col += dk;
        }
        passive = Some(x);
    }
    Ok((passive, passive_ids))
}

/// The gate: each measurement's own innovation against its predicted covariance under the
/// joint prior `p`. Returns the measurements gated out and, with a gate or Huber weights, each
/// measurement's weight (0 for those gated out).
fn gate(
    linearized: &[Vec<(PlatformId, LinearizedMeasurement)>],
    offset: &BTreeMap<PlatformId, (usize, usize)>,
    p: &DMatrix<f64>,
    opts: &UpdateOptions,
) -> (Vec<usize>, Vec<f64>) {
    let mut gated = Vec::new();
    let mut robust_weights = Vec::new();
    if opts.gate_chi2.is_some() || opts.huber_nis.is_some() {
        let q = opts.gate_chi2.unwrap_or([f64::INFINITY; 3]);
        for (index, parts) in linearized.iter().enumerate() {
            let first = &parts[0].1;
            let k = first.len();
            let mut s = first.r.clone();
            for (ia, (a, la)) in parts.iter().enumerate() {
                for (b, lb) in &parts[ia..] {
                    let ((oa, da), (ob, db)) = (offset[a], offset[b]);
                    let block = &la.h * p.view((oa, ob), (da, db)) * lb.h.transpose();
                    if a == b {
                        s += block;
                    } else {
                        s += &block + block.transpose();
                    }
                }
            }
            let nis = s.clone().cholesky().and_then(|c| {
                let white = c.l().solve_lower_triangular(&first.residual)?;
                Some(white.norm_squared())
            });
            let limit = q.get(k).copied().unwrap_or(f64::INFINITY);
            if nis.is_none_or(|v| v.is_nan() || v > limit) {
                gated.push(index);
                robust_weights.push(0.0);
            } else {
                let c = opts.huber_nis.map_or(f64::INFINITY, |c| c * k as f64 / 2.0);
                let v = nis.unwrap_or(0.0);
                robust_weights.push(if v > c { (c / v).sqrt() } else { 1.0 });
            }
        }
    }
    (gated, robust_weights)
}

/// The measurements kept, stacked into one (a measurement with a weight under 1 gets its noise
/// divided by it).
fn stack(
    kept: Vec<(f64, &Vec<(PlatformId, LinearizedMeasurement)>)>,
    offset: &BTreeMap<PlatformId, (usize, usize)>,
    n: usize,
) -> LinearizedMeasurement {
    let m: usize = kept.iter().map(|(_, parts)| parts[0].1.len()).sum();
    let mut h = DMatrix::zeros(m, n);
    let mut residual = DVector::zeros(m);
    let mut r = DMatrix::zeros(m, m);
    let mut row = 0;
    for (w, parts) in kept {
        let k = parts[0].1.len();
        for (id, lin) in parts {
            let (off, dim) = offset[id];
            h.view_mut((row, off), (k, dim)).copy_from(&lin.h);
        }
        let first = &parts[0].1;
        residual.rows_mut(row, k).copy_from(&first.residual);
        if w < 1.0 {
            r.view_mut((row, row), (k, k)).copy_from(&(&first.r / w));
        } else {
            r.view_mut((row, row), (k, k)).copy_from(&first.r);
        }
        row += k;
    }

    LinearizedMeasurement { h, residual, r }
}

/// [`cooperative_update`] with the prior and the gate chosen (see the module docs).
/// With every measurement gated out (or none given, with the bound prior) the update still
/// "applies": the corrections are zero and the posterior is the prior, so that the nodes' stores
/// stay (or become) equal.
pub fn cooperative_update_with(
    cross: &mut CrossCovariances,
    snapshots: &[Snapshot],
    measurements: &[CoopMeasurement],
    opts: &UpdateOptions,
) -> Result<EventOutcome, EstimationError> {
    let mode = opts.mode;
    let bound = matches!(opts.prior, JointPrior::Bound { .. });
    // Layout of the joint state: participants in broadcast order.
    let mut offset = BTreeMap::new();
    let mut n = 0;
    for s in snapshots {
        s.validate()?;
        if offset.insert(s.id, (n, s.dim())).is_some() {
            return Err(EstimationError::DuplicatePlatform(s.id));
        }
        n += s.dim();
    }
    if let Some(&k) = opts.bystanders.iter().find(|k| offset.contains_key(k)) {
        return Err(EstimationError::DuplicatePlatform(k));
    }
    let find = |id: PlatformId| snapshots.iter().find(|s| s.id == id);

    // Linearised measurements (stacked once the prior is known and the gate has run).
    if measurements.is_empty() && !bound {
        return Err(EstimationError::NotApplicable("a cooperative update needs at least one measurement"));
    }
    let mut linearized = Vec::with_capacity(measurements.len());
    for meas in measurements {
        linearized.push(meas.linearize(find)?);
    }

    // Joint prior covariance (paper Step 4).
    let weights = match &opts.prior {
        JointPrior::Exact => Vec::new(),
        JointPrior::Bound { independent, .. } => bound_weights(snapshots, independent),
    };
    let mut p = DMatrix::zeros(n, n);
    for (k, s) in snapshots.iter().enumerate() {
        let (o, d) = offset[&s.id];
        let block = match (&opts.prior, weights.get(k)) {
            (JointPrior::Bound { scope, .. }, Some(&w)) if w < 1.0 => inflate(s, w, *scope)?,
            _ => s.covariance.clone(),
        };
        p.view_mut((o, o), (d, d)).copy_from(&block);
    }
    let (passive, passive_ids) = if mode == CrossMode::Propagate && !bound {
        cross_blocks(cross, snapshots, &offset, n, &mut p)?
    } else {
        (None, Vec::new())
    };

    // The gate: each measurement's own innovation against its predicted covariance.
    let (gated, mut robust_weights) = gate(&linearized, &offset, &p, opts);
    let kept: Vec<(f64, &Vec<(PlatformId, LinearizedMeasurement)>)> = linearized
        .iter()
        .enumerate()
        .filter(|(i, _)| !gated.contains(i))
        .map(|(i, l)| (robust_weights.get(i).copied().unwrap_or(1.0), l))
        .collect();
    if opts.huber_nis.is_none() {
        robust_weights.clear();
    }
    // With every measurement gated out the update still runs, as an update by nothing: the
    // joint prior becomes the posterior and the store is re-anchored on it (Psi back to the
    // reset), which every node does alike.
    let stacked = stack(kept, &offset, n);
    let m = stacked.residual.len();
    let up = if m == 0 {
        // Nothing to update with: the prior (the bound, or the exact one) is the new joint state.
        kalman::JointUpdate {
            dx: DVector::zeros(n),
            p: p.clone(),
            passive: passive.clone(),
            passive_white: None,
            white_residual: DVector::zeros(0),
            diagnostics: UpdateDiagnostics { innovation: DVector::zeros(0), innovation_cov: DMatrix::zeros(0, 0), nis: 0.0 },
        }
    } else {
        kalman::joint_update(&p, &stacked, passive.as_ref())?
    };
    let layout: Vec<(usize, usize)> = snapshots.iter().map(|s| offset[&s.id]).collect();
    let own_blocks = checked_own_blocks(&layout, &up.p)?;

    // Step 5: store the new cross blocks (only now that nothing can fail).
    if bound {
        cross.clear();
    }
    let mut bystanders = Vec::new();
    if mode == CrossMode::Propagate {
        store_pairs(cross, snapshots, &layout, &up.p);
        if let Some(x) = &up.passive {
            for (k, col, dk) in &passive_ids {
                for s in snapshots {
                    let (o, d) = offset[&s.id];
                    cross.set(s.id, *k, dense::block(x, (o, *col), (d, *dk)));
                }
            }
            bystanders = bystander_shares(cross, &opts.bystanders, &passive_ids, &up);
        }
    }
    let corrections = corrections(snapshots, &layout, &up.dx, own_blocks);
    Ok(EventOutcome { corrections, diagnostics: up.diagnostics, prior_covariance: p, gated, weights, robust_weights, bystanders })
}

/// The bystanders' shares of an exact update (see [`BystanderShare`]), and the cross blocks of
/// every pair of non-broadcasters one of which at least is a bystander: `C_km - Z_k^T Z_m`
/// with `Z = L^-1 H X` the whitened passive columns (the joint filter's
/// `P_km - K_k H P_Pm`, whoever else's gain is zero). Pairs of left-out platforms keep
/// their blocks. With nothing measured (every range gated), nothing changes.
fn bystander_shares(
    cross: &mut CrossCovariances,
    listed: &[PlatformId],
    passive_ids: &[(PlatformId, usize, usize)],
    up: &kalman::JointUpdate,
) -> Vec<BystanderShare> {
    let Some(z) = up.passive_white.as_ref().filter(|z| z.nrows() > 0) else {
        return passive_ids
            .iter()
            .filter(|(k, _, _)| listed.contains(k))
            .map(|&(id, _, d)| BystanderShare { id, a: DVector::zeros(d), b: DMatrix::zeros(d, d) })
            .collect();
    };
    let mut shares = Vec::new();
    for (i, &(k, ck, dk)) in passive_ids.iter().enumerate() {
        let zk = z.columns(ck, dk);
        let by_k = listed.contains(&k);
        if by_k {
            let mut b = zk.tr_mul(&zk);
            kalman::symmetrize(&mut b);
            shares.push(BystanderShare { id: k, a: zk.tr_mul(&up.white_residual), b });
        }
        for &(m, cm, dm) in &passive_ids[i + 1..] {
            if !(by_k || listed.contains(&m)) {
                continue;
            }
            let mut c = cross.get(k, m).unwrap_or_else(|| DMatrix::zeros(dk, dm));
            c.gemm_tr(-1.0, &zk, &z.columns(cm, dm), 1.0);
            cross.set(k, m, c);
        }
    }
    shares
}

/// Each participant's own block of the joint posterior (`layout`: its offset and dimension in
/// the joint state, in broadcast order), refused when one is not positive semi-definite: a
/// participant's covariance that is not is never handed back.
fn checked_own_blocks(layout: &[(usize, usize)], p: &DMatrix<f64>) -> Result<Vec<DMatrix<f64>>, EstimationError> {
    let mut own_blocks = Vec::with_capacity(layout.len());
    for &(o, d) in layout {
        let block = dense::block(p, (o, o), (d, d));
        if !kalman::is_psd(&block, 1e-9) {
            return Err(EstimationError::NotPositiveDefinite { what: "a participant's posterior covariance" });
        }
        own_blocks.push(block);
    }
    Ok(own_blocks)
}

/// Paper Step 5: the posterior cross block of every pair of participants, stored.
fn store_pairs(cross: &mut CrossCovariances, snapshots: &[Snapshot], layout: &[(usize, usize)], p: &DMatrix<f64>) {
    for (a, sa) in snapshots.iter().enumerate() {
        for (b, sb) in snapshots.iter().enumerate().skip(a + 1) {
            let ((oa, da), (ob, db)) = (layout[a], layout[b]);
            cross.set(sa.id, sb.id, dense::block(p, (oa, ob), (da, db)));
        }
    }
}

/// Each participant's correction: its rows of the joint correction and its own posterior block.
fn corrections(snapshots: &[Snapshot], layout: &[(usize, usize)], dx: &DVector<f64>, own: Vec<DMatrix<f64>>) -> Vec<Correction> {
    snapshots
        .iter()
        .zip(layout)
        .zip(own)
        .map(|((s, &(o, d)), p)| Correction { id: s.id, dx: dx.rows(o, d).into_owned(), p })
        .collect()
}

/// The centralized EKF's update by one epoch's local measurements, each `(platform, H, r, R)`
/// of that platform's own error state: [`cooperative_update`] with [`CrossMode::Propagate`] and
/// each measurement as a [`CoopMeasurement::Linear`] of one block, the same results and errors
/// bit for bit (a test holds the two together), without the general path's bookkeeping for a
/// case it meets ten times a second per run: no maps of the layout, the Jacobian's rows
/// written as their nonzeros, the stored cross blocks and the `Psi`s read in place and each
/// `Psi_i C_ij Psi_j^T` (Eq. 10) written straight into the joint prior.
///
/// Hands over to the general path where that one does something else: a platform of the
/// store that is not among the snapshots (its blocks are carried as passive columns), a
/// stored block whose size is not the broadcast's, or a state of 5 or fewer (nalgebra
/// multiplies those with its own loops, see [`dense::PRODUCT_KERNEL_ABOVE`]).
pub fn centralized_local_update(
    cross: &mut CrossCovariances,
    snapshots: &[Snapshot],
    batch: &[(PlatformId, &LinearizedMeasurement)],
) -> Result<EventOutcome, EstimationError> {
    let general = |cross: &mut CrossCovariances| {
        let joint: Vec<CoopMeasurement> = batch.iter().map(|(id, m)| CoopMeasurement::local(*id, m)).collect();
        cooperative_update(cross, snapshots, &joint, CrossMode::Propagate)
    };
    let position = |id: PlatformId| snapshots.iter().position(|s| s.id == id);
    let store_fits = cross.blocks.iter().all(|(&(a, b), c)| match (position(a), position(b)) {
        (Some(ia), Some(ib)) => snapshots[ia].dim() == c.nrows() && snapshots[ib].dim() == c.ncols(),
        _ => false,
    });
    if batch.is_empty() || !store_fits || snapshots.iter().any(|s| s.dim() <= dense::PRODUCT_KERNEL_ABOVE) {
        return general(cross);
    }
    // Layout and checks, in the general path's order: the broadcasts, then each measurement.
    let mut layout = Vec::with_capacity(snapshots.len());
    let mut n = 0;
    for (k, s) in snapshots.iter().enumerate() {
        s.validate()?;
        if snapshots[..k].iter().any(|o| o.id == s.id) {
            return Err(EstimationError::DuplicatePlatform(s.id));
        }
        layout.push((n, s.dim()));
        n += s.dim();
    }
    let mut at = Vec::with_capacity(batch.len());
    for (id, meas) in batch {
        if meas.residual.is_empty() {
            return Err(EstimationError::NotApplicable("empty linear measurement"));
        }
        let k = position(*id).ok_or(EstimationError::UnknownPlatform(*id))?;
        if meas.h.nrows() != meas.residual.len() || meas.h.ncols() != snapshots[k].dim() {
            return Err(EstimationError::DimensionMismatch {
                what: "linear measurement block",
                expected: snapshots[k].dim(),
                got: meas.h.ncols(),
            });
        }
        meas.validate(snapshots[k].dim())?;
        at.push(k);
    }

    // Joint prior (paper Step 4): own blocks, then Eq. 10 for every stored pair.
    let mut p = DMatrix::zeros(n, n);
    for (s, &(o, d)) in snapshots.iter().zip(&layout) {
        p.view_mut((o, o), (d, d)).copy_from(&s.covariance);
    }
    let mut psi_c = DMatrix::zeros(0, 0);
    for (a, sa) in snapshots.iter().enumerate() {
        for (b, sb) in snapshots.iter().enumerate().skip(a + 1) {
            let Some(c) = cross.stored(sa.id, sb.id) else { continue };
            let ((oa, da), (ob, db)) = (layout[a], layout[b]);
            if psi_c.shape() != (da, db) {
                psi_c = DMatrix::zeros(da, db);
            }
            dense::product_into(dense::Strided::of(&sa.psi), c, &mut psi_c, (0, 0));
            dense::product_into(dense::Strided::of(&psi_c), dense::Strided::of(&sb.psi).t(), &mut p, (oa, ob));
            for j in 0..db {
                for i in 0..da {
                    p[(ob + j, oa + i)] = p[(oa + i, ob + j)];
                }
            }
        }
    }

    // The stacked measurement: each row's nonzeros at its platform's columns, in column order.
    let m: usize = batch.iter().map(|(_, meas)| meas.len()).sum();
    let mut rows = Vec::with_capacity(m);
    let mut residual = DVector::zeros(m);
    let mut r = DMatrix::zeros(m, m);
    let mut row = 0;
    for ((_, meas), &k) in batch.iter().zip(&at) {
        let (o, d) = layout[k];
        let len = meas.len();
        for i in 0..len {
            rows.push((0..d).filter_map(|c| Some((o + c, meas.h[(i, c)])).filter(|(_, v)| *v != 0.0)).collect());
        }
        residual.rows_mut(row, len).copy_from(&meas.residual);
        r.view_mut((row, row), (len, len)).copy_from(&meas.r);
        row += len;
    }
    let up = kalman::joint_update_by_rows(&p, &rows, &residual, &r)?;
    let own_blocks = checked_own_blocks(&layout, &up.p)?;
    store_pairs(cross, snapshots, &layout, &up.p);
    let corrections = corrections(snapshots, &layout, &up.dx, own_blocks);
    Ok(EventOutcome {
        corrections,
        diagnostics: up.diagnostics,
        prior_covariance: p,
        gated: Vec::new(),
        weights: Vec::new(),
        robust_weights: Vec::new(),
        bystanders: Vec::new(),
    })
}

#[cfg(test)]
mod tests {
    use nalgebra::Vector3;
    use rand::{Rng, SeedableRng};
    use rand_chacha::ChaCha8Rng;

    use super::*;
    use crate::estimation::kalman::min_eigenvalue;
    use crate::estimation::{Geometry, Heading};

    /// A random joint covariance over `n` platforms of dimension `d` (positions first), with
    /// strong cross-correlations, and each platform's snapshot of its own block.
    fn joint(rng: &mut ChaCha8Rng, n: usize, d: usize) -> (DMatrix<f64>, Vec<Snapshot>) {
        let a = DMatrix::from_fn(n * d, n * d + 2, |_, _| rng.random_range(-1.0..1.0));
        let p = &a * a.transpose() + DMatrix::identity(n * d, n * d) * 0.05;
        let snaps = (0..n)
            .map(|i| Snapshot {
                id: i as PlatformId + 1,
                geometry: Geometry {
                    position_ned_m: Vector3::new(100.0 * i as f64, 30.0 * (i % 2) as f64, 0.0),
                    position_index: [Some(0), Some(1), Some(2)],
                    heading: Some(Heading { yaw_rad: 0.1, index: d - 1 }),
                },
                covariance: p.view((i * d, i * d), (d, d)).into_owned(),
                psi: DMatrix::identity(d, d),
            })
            .collect();
        (p, snaps)
    }

    /// The centralized EKF's local path gives what the general path gives, bit for bit: the
    /// outcome (corrections, diagnostics, prior) and the store, over random teams of 2 to 4
    /// platforms broadcasting in any order of their ids, with random `Psi`, stored cross blocks
    /// (some pairs missing, stored either way round) and 1 to 3 measurements of up to 3 rows
    /// with zero entries; the same errors for bad input; and the cases it hands to the general
    /// path (a 3-state platform, a platform of the store that does not broadcast) alike.
    #[test]
    fn the_centralized_local_path_is_the_general_path_bit_for_bit() {
        let mut rng = ChaCha8Rng::seed_from_u64(77);
        let (mut ok, mut refused) = (0, 0);
        for trial in 0..300 {
            let n = 2 + trial % 3;
            let d = if trial % 10 == 9 { 3 } else { [16, 8, 6][trial % 3] };
            let (p, mut snaps) = joint(&mut rng, n, d);
            for s in &mut snaps {
                s.psi = DMatrix::identity(d, d) + DMatrix::from_fn(d, d, |_, _| 0.1 * rng.random_range(-1.0..1.0));
            }
            // Cross blocks that make the joint prior `p` again: C_ij = Psi_i^-1 P_ij Psi_j^-T.
            let mut cross = CrossCovariances::new();
            for a in 0..n {
                for b in a + 1..n {
                    if rng.random_bool(0.15) {
                        continue;
                    }
                    let inv = |k: usize| snaps[k].psi.clone().try_inverse().unwrap();
                    let c = inv(a) * p.view((a * d, b * d), (d, d)) * inv(b).transpose();
                    let (ia, ib) = (snaps[a].id, snaps[b].id);
                    if rng.random_bool(0.5) { cross.set(ia, ib, c) } else { cross.set(ib, ia, c.transpose()) }
                }
            }
            // Broadcast order is arrival order, not id order.
            for k in (1..n).rev() {
                snaps.swap(k, rng.random_range(0..=k));
            }
            if trial % 7 == 5 {
                snaps.pop(); // its blocks stay in the store: passive columns
            }
            let mut batch = Vec::new();
            for s in &snaps {
                if rng.random_bool(0.3) && !batch.is_empty() {
                    continue;
                }
                let m = rng.random_range(1..=3);
                let a = DMatrix::from_fn(m, m, |_, _| rng.random_range(-1.0..1.0));
                let h = DMatrix::from_fn(m, d, |_, _| if rng.random_bool(0.4) { 0.0 } else { rng.random_range(-1.0..1.0) });
                let residual = DVector::from_fn(m, |_, _| rng.random_range(-1.0..1.0));
                batch.push((s.id, LinearizedMeasurement { h, residual, r: &a * a.transpose() + DMatrix::identity(m, m) * 0.01 }));
            }
            // Now and then, bad input.
            match trial % 23 {
                3 => batch[0].0 = 99,
                8 => batch[0].1.h = DMatrix::zeros(batch[0].1.len(), d + 1),
                13 => batch[0].1.residual[0] = f64::NAN,
                18 => {
                    batch[0].1 =
                        LinearizedMeasurement { h: DMatrix::zeros(0, d), residual: DVector::zeros(0), r: DMatrix::zeros(0, 0) }
                }
                _ => {}
            }
            let refs: Vec<(PlatformId, &LinearizedMeasurement)> = batch.iter().map(|(id, m)| (*id, m)).collect();
            let linear: Vec<CoopMeasurement> = batch.iter().map(|(id, m)| CoopMeasurement::local(*id, m)).collect();
            let (mut fast_store, mut general_store) = (cross.clone(), cross);
            let fast = centralized_local_update(&mut fast_store, &snaps, &refs);
            let general = cooperative_update(&mut general_store, &snaps, &linear, CrossMode::Propagate);
            match (fast, general) {
                (Ok(f), Ok(g)) => {
                    assert_eq!(format!("{:?}", f.corrections), format!("{:?}", g.corrections), "trial {trial}");
                    assert_eq!(format!("{:?}", f.diagnostics), format!("{:?}", g.diagnostics), "trial {trial}");
                    assert_eq!(format!("{:?}", f.prior_covariance), format!("{:?}", g.prior_covariance), "trial {trial}");
                    assert_eq!((f.gated, f.weights), (g.gated, g.weights));
                    ok += 1;
                }
                (Err(f), Err(g)) => {
                    assert_eq!(f, g, "trial {trial}");
                    refused += 1;
                }
                (f, g) => panic!("trial {trial}: {:?} against {:?}", f.err(), g.err()),
            }
            assert_eq!(fast_store.digest(), general_store.digest(), "trial {trial}: the stores");
        }
        assert!(ok > 200 && refused >= 40, "{ok} updates, {refused} refusals");
    }

    /// An epoch among the platforms that ranged, the others bystanders ([`split_ranged`]), ends
    /// where the update on every broadcast does: the participants' corrections, each
    /// bystander's share taken through its own `Psi`, and every cross-covariance rebuilt by
    /// Eq. 10, to 1e-9, over random teams of five with random `Psi` and range measurements
    /// among a random few.
    #[test]
    fn an_epoch_among_the_ranged_with_bystanders_equals_the_epoch_on_every_broadcast() {
        let mut rng = ChaCha8Rng::seed_from_u64(36);
        let close = |a: &DMatrix<f64>, b: &DMatrix<f64>, what: &str| {
            let scale = b.amax().max(1.0);
            assert!((a - b).amax() <= 1e-9 * scale, "{what}: {a} vs {b}");
        };
        let mut bystood = 0;
        for trial in 0..50 {
            let (n, d) = (5, 4);
            let (p, mut snaps) = joint(&mut rng, n, d);
            for s in &mut snaps {
                s.psi = DMatrix::identity(d, d) + DMatrix::from_fn(d, d, |_, _| rng.random_range(-0.3..0.3));
            }
            let inv: Vec<DMatrix<f64>> = snaps.iter().map(|s| s.psi.clone().try_inverse().unwrap()).collect();
            let mut cross = CrossCovariances::new();
            for i in 0..n {
                for j in i + 1..n {
                    let pij = p.view((i * d, j * d), (d, d)).into_owned();
                    cross.set(snaps[i].id, snaps[j].id, &inv[i] * pij * inv[j].transpose());
                }
            }
            // Ranges among two or three of them.
            let mut ids: Vec<PlatformId> = snaps.iter().map(|s| s.id).collect();
            while ids.len() > 2 + trial % 2 {
                ids.remove(rng.random_range(0..ids.len()));
            }
            let ranges: Vec<CoopMeasurement> = ids
                .windows(2)
                .map(|w| CoopMeasurement::Range {
                    from: w[0],
                    to: w[1],
                    range_m: 100.0 * f64::from(w[1] - w[0]) + 3.0,
                    sigma_m: 1.0,
                })
                .collect();
            let mut every = cross.clone();
            let all = cooperative_update(&mut every, &snaps, &ranges, CrossMode::Propagate).unwrap();
            let (ranged, bystanders) = split_ranged(&snaps, &ranges);
            assert_eq!(ranged.iter().map(|s| s.id).collect::<Vec<_>>(), ids);
            let opts = UpdateOptions { bystanders: bystanders.clone(), ..UpdateOptions::new(CrossMode::Propagate) };
            let among = cooperative_update_with(&mut cross, &ranged, &ranges, &opts).unwrap();
            assert_eq!(among.bystanders.iter().map(|b| b.id).collect::<Vec<_>>(), bystanders);
            // Each platform's correction, posterior and Psi after (identity for the participants).
            type Posterior = (DVector<f64>, DMatrix<f64>, DMatrix<f64>);
            let mut post: BTreeMap<PlatformId, Posterior> = BTreeMap::new();
            for c in &among.corrections {
                post.insert(c.id, (c.dx.clone(), c.p.clone(), DMatrix::identity(d, d)));
            }
            for b in &among.bystanders {
                let s = snaps.iter().find(|s| s.id == b.id).unwrap();
                let (dx, pk) = crate::estimation::platform::bystander_posterior(&s.covariance, &s.psi, &b.a, &b.b).unwrap();
                post.insert(b.id, (dx, pk, s.psi.clone()));
                bystood += 1;
            }
            for c in &all.corrections {
                let (dx, pk, _) = &post[&c.id];
                close(&DMatrix::from_column_slice(d, 1, dx.as_slice()), &DMatrix::from_column_slice(d, 1, c.dx.as_slice()), "dx");
                close(pk, &c.p, "P_kk");
            }
            for (a, (_, _, psi_a)) in &post {
                for (b, (_, _, psi_b)) in post.range(a + 1..) {
                    let rebuilt = psi_a * cross.get(*a, *b).unwrap() * psi_b.transpose();
                    close(&rebuilt, &every.get(*a, *b).unwrap(), &format!("trial {trial}: P_{a}{b}"));
                }
            }
        }
        assert!(bystood >= 100, "{bystood} bystanders' shares");
    }

    /// The digest is kept between changes and recomputed after every one: each change moves it,
    /// and the kept value is always the one a fresh computation gives.
    #[test]
    fn the_kept_digest_follows_every_change() {
        let mut s = CrossCovariances::new();
        let mut seen = vec![s.digest()];
        let mut check = |s: &CrossCovariances| {
            assert_eq!(s.digest(), s.compute_digest());
            assert!(!seen.contains(&s.digest()), "a change left the digest as it was");
            seen.push(s.digest());
        };
        s.set(1, 2, DMatrix::from_element(2, 2, 0.5));
        check(&s);
        s.set(2, 3, DMatrix::from_element(2, 2, 0.25));
        check(&s);
        s.set_reference(2, StoreRef { epoch: 4, token: 9 });
        check(&s);
        s.forget(3);
        check(&s);
        let copy = s.clone();
        assert_eq!(copy, s);
        s.clear();
        assert_eq!(s.digest(), s.compute_digest());
        assert_eq!(s, CrossCovariances::new(), "equality ignores what was kept");
    }

    fn bound_prior(snaps: &[Snapshot], scope: BoundScope) -> DMatrix<f64> {
        bound_prior_with(snaps, scope, Vec::new())
    }

    fn bound_prior_with(snaps: &[Snapshot], scope: BoundScope, independent: Vec<PlatformId>) -> DMatrix<f64> {
        let ranges = [CoopMeasurement::Range { from: 1, to: 2, range_m: 1e9, sigma_m: 1.0 }];
        let opts = UpdateOptions {
            prior: JointPrior::Bound { independent: independent.clone(), scope },
            gate_chi2: UpdateOptions::gate_for_probability(1e-6),
            ..UpdateOptions::new(CrossMode::Propagate)
        };
        // The absurd range is gated out: the outcome's prior is the bound itself.
        let out = cooperative_update_with(&mut CrossCovariances::new(), snaps, &ranges, &opts).unwrap();
        assert_eq!(out.gated, vec![0]);
        let correlated: f64 = out.weights.iter().zip(snaps).filter(|(_, s)| !independent.contains(&s.id)).map(|(w, _)| w).sum();
        assert!((correlated - 1.0).abs() < 1e-12, "the weights of the correlated members sum to 1");
        out.prior_covariance
    }

    /// The full-state bound is an upper bound of every joint covariance with those diagonal
    /// blocks, whatever its cross blocks (random joint covariances, 2 to 5 platforms).
    #[test]
    fn the_full_bound_bounds_any_cross_covariance() {
        let mut rng = ChaCha8Rng::seed_from_u64(7);
        for trial in 0..200 {
            let n = 2 + trial % 4;
            let (p, snaps) = joint(&mut rng, n, 6);
            let bound = bound_prior(&snaps, BoundScope::Full);
            let gap = min_eigenvalue(&(&bound - &p));
            assert!(gap >= -1e-9, "trial {trial}: bound - P has eigenvalue {gap}");
            // A platform truly uncorrelated with the others needs no weight: left as it is, the
            // bound still holds.
            let (mut q, last) = (p.clone(), (n - 1) * 6);
            q.view_mut((0, last), (last, 6)).fill(0.0);
            q.view_mut((last, 0), (6, last)).fill(0.0);
            let bound = bound_prior_with(&snaps, BoundScope::Full, vec![n as PlatformId]);
            assert_eq!(bound.view((last, last), (6, 6)), snaps[n - 1].covariance.view((0, 0), (6, 6)));
            let gap = min_eigenvalue(&(&bound - &q));
            assert!(gap >= -1e-9, "trial {trial}: bound with an independent member - P has eigenvalue {gap}");
        }
    }

    /// The position-scoped bound is an upper bound when the cross-covariances reach the other
    /// states through their regression on position (joint range updates create them so), and
    /// leaves alone what is uncorrelated with position.
    #[test]
    fn the_position_bound_bounds_cross_covariances_made_through_position() {
        let mut rng = ChaCha8Rng::seed_from_u64(11);
        for trial in 0..200 {
            let n = 2 + trial % 4;
            let d = 6;
            // e_i = G_i p_i + r_i with p jointly correlated across platforms, r_i independent.
            let (pp, _) = joint(&mut rng, n, 3);
            let mut g = DMatrix::zeros(n * d, n * 3);
            let mut r = DMatrix::zeros(n * d, n * d);
            for i in 0..n {
                g.view_mut((i * d, i * 3), (3, 3)).fill_with_identity();
                for row in 3..d {
                    for c in 0..3 {
                        g[(i * d + row, i * 3 + c)] = rng.random_range(-0.5..0.5);
                    }
                }
                let a = DMatrix::from_fn(d - 3, d - 3, |_, _| rng.random_range(-1.0..1.0));
                r.view_mut((i * d + 3, i * d + 3), (d - 3, d - 3)).copy_from(&(&a * a.transpose()));
            }
            let p = &g * pp * g.transpose() + r;
            let snaps: Vec<Snapshot> = (0..n)
                .map(|i| Snapshot {
                    id: i as PlatformId + 1,
                    geometry: Geometry {
                        position_ned_m: Vector3::new(100.0 * i as f64, 30.0 * (i % 2) as f64, 0.0),
                        position_index: [Some(0), Some(1), Some(2)],
                        heading: None,
                    },
                    covariance: p.view((i * d, i * d), (d, d)).into_owned(),
                    psi: DMatrix::identity(d, d),
                })
                .collect();
            let bound = bound_prior(&snaps, BoundScope::Position);
            let gap = min_eigenvalue(&(&bound - &p));
            assert!(gap >= -1e-9, "trial {trial}: bound - P has eigenvalue {gap}");
            // Tighter than the full bound.
            let full = bound_prior(&snaps, BoundScope::Full);
            assert!(full.trace() >= bound.trace());
        }
    }

    /// A gross outlier is gated out and the rest is used; every node gates the same one.
    #[test]
    fn the_gate_leaves_out_a_forged_range() {
        let mut rng = ChaCha8Rng::seed_from_u64(3);
        let (_, snaps) = joint(&mut rng, 3, 6);
        let d12 = (snaps[0].geometry.position_ned_m - snaps[1].geometry.position_ned_m).norm();
        let d13 = (snaps[0].geometry.position_ned_m - snaps[2].geometry.position_ned_m).norm();
        let ranges = [
            CoopMeasurement::Range { from: 1, to: 2, range_m: d12 + 0.3, sigma_m: 0.5 },
            CoopMeasurement::Range { from: 1, to: 3, range_m: d13 + 50.0, sigma_m: 0.5 },
        ];
        let opts =
            UpdateOptions { gate_chi2: UpdateOptions::gate_for_probability(1e-6), ..UpdateOptions::new(CrossMode::Propagate) };
        let a = cooperative_update_with(&mut CrossCovariances::new(), &snaps, &ranges, &opts).unwrap();
        let b = cooperative_update_with(&mut CrossCovariances::new(), &snaps, &ranges, &opts).unwrap();
        assert_eq!(a.gated, vec![1]);
        assert_eq!(a.corrections, b.corrections);
        assert_eq!(a.diagnostics.innovation.len(), 1);
        // Without the gate the forged range pulls platform 1 by metres.
        let ungated = cooperative_update(&mut CrossCovariances::new(), &snaps, &ranges, CrossMode::Propagate).unwrap();
        assert!(ungated.corrections[0].dx.rows(0, 3).norm() > 10.0 * a.corrections[0].dx.rows(0, 3).norm());
    }

    /// A moderate outlier passes the gate but is Huber-weighted: its weight is
    /// `sqrt(c / NIS)`, it pulls less than unweighted, and a consistent range keeps weight 1.
    #[test]
    fn huber_weights_soften_a_moderate_outlier() {
        let mut rng = ChaCha8Rng::seed_from_u64(3);
        let (_, snaps) = joint(&mut rng, 3, 6);
        let d12 = (snaps[0].geometry.position_ned_m - snaps[1].geometry.position_ned_m).norm();
        let d13 = (snaps[0].geometry.position_ned_m - snaps[2].geometry.position_ned_m).norm();
        let ranges = [
            CoopMeasurement::Range { from: 1, to: 2, range_m: d12 + 0.01, sigma_m: 0.5 },
            CoopMeasurement::Range { from: 1, to: 3, range_m: d13 + 14.0, sigma_m: 0.5 },
        ];
        let plain =
            UpdateOptions { gate_chi2: UpdateOptions::gate_for_probability(1e-12), ..UpdateOptions::new(CrossMode::Propagate) };
        let robust = UpdateOptions { huber_nis: Some(5.99), ..plain.clone() };
        let a = cooperative_update_with(&mut CrossCovariances::new(), &snaps, &ranges, &plain).unwrap();
        let b = cooperative_update_with(&mut CrossCovariances::new(), &snaps, &ranges, &robust).unwrap();
        assert!(a.gated.is_empty() && a.robust_weights.is_empty());
        assert_eq!(b.robust_weights.len(), 2);
        assert_eq!(b.robust_weights[0], 1.0, "a consistent range is not weighted");
        assert!(b.robust_weights[1] > 0.0 && b.robust_weights[1] < 0.5, "{:?}", b.robust_weights);
        // The outlier's target is pulled less.
        assert!(b.corrections[2].dx.norm() < a.corrections[2].dx.norm());
    }

    /// A broadcast of another size than the store holds for its platform (a forged record) is a
    /// typed error, not a panic, and leaves the store as it was.
    #[test]
    fn a_broadcast_of_the_wrong_size_is_refused() {
        let mut rng = ChaCha8Rng::seed_from_u64(9);
        let (_, snaps) = joint(&mut rng, 3, 4);
        let ranges = [CoopMeasurement::Range { from: 1, to: 2, range_m: 100.0, sigma_m: 0.1 }];
        let mut store = CrossCovariances::new();
        cooperative_update(&mut store, &snaps, &ranges, CrossMode::Propagate).unwrap();
        let before = store.digest();
        let (_, other) = joint(&mut rng, 3, 6);
        let mixed = vec![snaps[0].clone(), other[1].clone(), snaps[2].clone()];
        let e = cooperative_update(&mut store, &mixed, &ranges, CrossMode::Propagate).unwrap_err();
        assert!(matches!(e, EstimationError::DimensionMismatch { expected: 4, got: 6, .. }), "{e}");
        assert_eq!(store.digest(), before);
    }

    /// Equal stores have equal digests; any change of a block, or of its pair, changes it.
    #[test]
    fn the_store_digest_tells_stores_apart() {
        let mut rng = ChaCha8Rng::seed_from_u64(5);
        let (_, snaps) = joint(&mut rng, 3, 4);
        let ranges = [CoopMeasurement::Range { from: 1, to: 2, range_m: 100.0, sigma_m: 0.1 }];
        let mut a = CrossCovariances::new();
        let empty = a.digest();
        assert_ne!(empty, 0);
        cooperative_update(&mut a, &snaps, &ranges, CrossMode::Propagate).unwrap();
        let mut b = a.clone();
        assert_eq!(a.digest(), b.digest());
        assert_ne!(a.digest(), empty);
        let mut c = b.get(1, 2).unwrap();
        c[(0, 0)] = f64::from_bits(c[(0, 0)].to_bits() ^ 1);
        b.set(1, 2, c);
        assert_ne!(a.digest(), b.digest(), "one bit of one value");
        b = a.clone();
        b.forget(3);
        assert_ne!(a.digest(), b.digest());
    }
}
