//! Cooperative localization by covariance intersection: the usual consistent-but-conservative
//! answer when cross-correlations are unknown.
//!
//! For a measurement between platforms `i` and `j` whose correlation is unknown, the block
//! diagonal `diag(A_i / w, A_j / (1 - w))`, `0 < w < 1`, bounds the true joint covariance of any
//! two sub-states with marginals `A_i`, `A_j`, for every possible correlation. cooploc applies
//! that bound to the *measured sub-states only* (the error states the measurement's Jacobian
//! touches: position, and heading for a bearing), and each platform fuses for itself, as it
//! would on its own computer: platform `i` picks the `w` that minimises the trace of its own
//! measured sub-state's posterior (golden-section search), keeps its own part, and carries the
//! correction into the rest of its state by Gaussian conditioning (`dx = P_xs P_ss^-1 ds`,
//! `P <- P - P_xs P_ss^-1 (P_ss - P_ss+) P_ss^-1 P_sx`). `j` does the same with its own weight.
//!
//! Why not the bound on whole states: it inflates every state the range cannot see (an INS's
//! heading, biases) by `1 / w` at every fusion, and with ranging at 1 Hz an INS then diverges
//! exponentially. The price of the sub-state form: the fused sub-state is consistent for any
//! correlation, but the conditioning step assumes the rest of the state is correlated with the
//! other platform only through the fused sub-state. No correlation is stored. Measurements are
//! processed one at a time, each relinearised at the estimates corrected so far.

use nalgebra::{DMatrix, DVector};

use super::EstimationError;
use super::coop::{CoopMeasurement, Correction};
use super::kalman::{self, LinearizedMeasurement};
use super::platform::{PlatformId, Snapshot};

/// Golden-section search for the minimum of a unimodal `f` on `[lo, hi]`.
fn golden_section(mut lo: f64, mut hi: f64, iterations: usize, f: impl Fn(f64) -> f64) -> f64 {
    let inv_phi = (5f64.sqrt() - 1.0) / 2.0;
    let mut a = hi - inv_phi * (hi - lo);
    let mut b = lo + inv_phi * (hi - lo);
    let (mut fa, mut fb) = (f(a), f(b));
    for _ in 0..iterations {
        if fa < fb {
            hi = b;
            b = a;
            fb = fa;
            a = hi - inv_phi * (hi - lo);
            fa = f(a);
        } else {
            lo = a;
            a = b;
            fa = fb;
            b = lo + inv_phi * (hi - lo);
            fb = f(b);
        }
    }
    0.5 * (lo + hi)
}

/// The largest stacked sub-state [`scalar_trial_trace`] takes (two positions and headings).
const SCALAR_MAX_DIM: usize = 8;

/// The objective of the weight search for a scalar measurement (a range): the trace of the
/// `block` (offset, size) of the posterior of
/// `kalman::joint_update(diag(A_k / w_k), meas, None)`, or infinity where that update fails;
/// computed on the stack with every operation of that update in its order (the axpy of
/// `P H^T`, the fold of `H P H^T`, the Cholesky of the 1x1 `S`, the division by its root, the
/// Gram entries `0 + w_i w_j`, the downdate and its symmetrising average, the finiteness checks
/// of the posterior and the correction), so that it returns the same bits; the test
/// `scalar_trial_trace_equals_the_joint_update_bit_for_bit` holds it to that. `meas` must have
/// one row and pass `validate` on the stacked dimension (at most [`SCALAR_MAX_DIM`]).
fn scalar_trial_trace(marginals: &[DMatrix<f64>], weights: &[f64], meas: &LinearizedMeasurement, block: (usize, usize)) -> f64 {
    const N: usize = SCALAR_MAX_DIM;
    let n = meas.h.ncols();
    debug_assert!(meas.h.nrows() == 1 && n <= N);
    // The prior: diag(A_k / w_k), zeros elsewhere.
    let mut p = [[0.0f64; N]; N]; // p[column][row]
    let mut off = 0;
    for (a, w) in marginals.iter().zip(weights) {
        let d = a.nrows();
        for j in 0..d {
            for i in 0..d {
                p[off + j][off + i] = a[(i, j)] / *w;
            }
        }
        off += d;
    }
    // P H^T: one axpy per nonzero of H, in column order (nalgebra's axpy, `v x 1 + 1 y`, rounds
    // as `y + v x`); then H P H^T, folded over the same nonzeros.
    let mut ph_t = [0.0f64; N];
    let h = meas.h.row(0);
    for (pc, &v) in p.iter().zip(h.iter()).filter(|(_, v)| **v != 0.0) {
        for (y, x) in ph_t.iter_mut().zip(pc).take(n) {
            *y += v * *x;
        }
    }
    let mut hph = 0.0;
    for (x, &v) in ph_t.iter().zip(h.iter()).filter(|(_, v)| **v != 0.0) {
        hph += v * *x;
    }
    let s = hph + meas.r[(0, 0)];
    if s.is_nan() || s <= 0.0 {
        return f64::INFINITY; // not positive definite
    }
    let l = s.sqrt();
    let mut w = [0.0f64; N];
    for (w, x) in w.iter_mut().zip(&ph_t).take(n) {
        *w = *x / l;
    }
    let white = meas.residual[0] / l;
    let mut finite = true;
    let mut trace = 0.0;
    for j in 0..n {
        finite &= (w[j] * white).is_finite();
        for i in j..n {
            let g = 0.0 + w[i] * w[j];
            let v = if i == j { -g + p[j][i] } else { 0.5 * ((-g + p[j][i]) + (-g + p[i][j])) };
            finite &= v.is_finite();
            if i == j && j >= block.0 && j < block.0 + block.1 {
                trace += v;
            }
        }
    }
    if finite { trace } else { f64::INFINITY }
}

/// The columns of `h` that hold a nonzero entry.
fn measured_columns(h: &DMatrix<f64>) -> Vec<usize> {
    (0..h.ncols()).filter(|&c| h.column(c).iter().any(|v| *v != 0.0)).collect()
}

fn sub_matrix(p: &DMatrix<f64>, rows: &[usize], cols: &[usize]) -> DMatrix<f64> {
    DMatrix::from_fn(rows.len(), cols.len(), |r, c| p[(rows[r], cols[c])])
}

/// Applies `measurements` one by one with covariance intersection. Returns one correction per
/// snapshot (in snapshot order): the accumulated error-state correction and the final own
/// covariance.
pub fn ci_update(snapshots: &[Snapshot], measurements: &[CoopMeasurement]) -> Result<Vec<Correction>, EstimationError> {
    for (a, s) in snapshots.iter().enumerate() {
        s.validate()?;
        if snapshots[..a].iter().any(|o| o.id == s.id) {
            return Err(EstimationError::DuplicatePlatform(s.id));
        }
    }
    // Working copies: geometry moves as corrections accumulate.
    let mut work: Vec<Snapshot> = snapshots.to_vec();
    let mut dx: Vec<DVector<f64>> = snapshots.iter().map(|s| DVector::zeros(s.dim())).collect();
    let index = |id: PlatformId| snapshots.iter().position(|s| s.id == id).ok_or(EstimationError::UnknownPlatform(id));

    for meas in measurements {
        let parts = meas.linearize(|id| work.iter().find(|s| s.id == id))?;
        let idx: Vec<usize> = parts.iter().map(|(id, _)| index(*id)).collect::<Result<_, _>>()?;
        if idx.len() > 2 {
            return Err(EstimationError::NotApplicable("covariance intersection takes measurements of one or two platforms"));
        }
        let m = meas.len();
        // The measured sub-state of each involved platform, and the measurement on the stack of them.
        let cols: Vec<Vec<usize>> = parts.iter().map(|(_, lin)| measured_columns(&lin.h)).collect();
        let dims: Vec<usize> = cols.iter().map(Vec::len).collect();
        let n: usize = dims.iter().sum();
        let mut h = DMatrix::zeros(m, n);
        let mut off = 0;
        for ((_, lin), c) in parts.iter().zip(&cols) {
            for (k, &col) in c.iter().enumerate() {
                h.set_column(off + k, &lin.h.column(col));
            }
            off += c.len();
        }
        let stacked = LinearizedMeasurement { h, residual: parts[0].1.residual.clone(), r: parts[0].1.r.clone() };
        let marginals: Vec<DMatrix<f64>> = idx.iter().zip(&cols).map(|(&i, c)| sub_matrix(&work[i].covariance, c, c)).collect();
        let bound = |weights: &[f64]| {
            let mut p = DMatrix::zeros(n, n);
            let mut off = 0;
            for (a, w) in marginals.iter().zip(weights) {
                p.view_mut((off, off), (a.nrows(), a.nrows())).copy_from(&(a / *w));
                off += a.nrows();
            }
            p
        };
        let scalar_ok = m == 1 && n <= SCALAR_MAX_DIM && stacked.validate(n).is_ok();
        // Each involved platform fuses for itself, all from the same prior.
        let mut fused = Vec::with_capacity(idx.len());
        let mut off = 0;
        for (k, d) in dims.iter().enumerate() {
            let weights = |w: f64| {
                if idx.len() == 1 {
                    vec![1.0]
                } else if k == 0 {
                    vec![w, 1.0 - w]
                } else {
                    vec![1.0 - w, w]
                }
            };
            let w = if idx.len() == 1 {
                1.0
            } else if scalar_ok {
                // A range: the search's 42 trial updates on the stack (same numbers, see
                // `scalar_trial_trace`).
                golden_section(1e-3, 1.0 - 1e-3, 40, |w| {
                    let ws = if k == 0 { [w, 1.0 - w] } else { [1.0 - w, w] };
                    scalar_trial_trace(&marginals, &ws, &stacked, (off, *d))
                })
            } else {
                golden_section(1e-3, 1.0 - 1e-3, 40, |w| {
                    kalman::joint_update(&bound(&weights(w)), &stacked, None)
                        .map(|u| u.p.view((off, off), (*d, *d)).trace())
                        .unwrap_or(f64::INFINITY)
                })
            };
            let up = kalman::joint_update(&bound(&weights(w)), &stacked, None)?;
            fused.push((up.dx.rows(off, *d).into_owned(), up.p.view((off, off), (*d, *d)).into_owned()));
            off += d;
        }
        // Carry each platform's fused sub-state into its whole state by conditioning.
        for ((&i, c), (ds, p_ss_post)) in idx.iter().zip(&cols).zip(fused) {
            let s = &mut work[i];
            let all: Vec<usize> = (0..s.dim()).collect();
            let p_xs = sub_matrix(&s.covariance, &all, c);
            let p_ss = sub_matrix(&s.covariance, c, c);
            let chol = nalgebra::Cholesky::new(p_ss.clone())
                .ok_or(EstimationError::NotPositiveDefinite { what: "measured sub-state covariance" })?;
            let gain = chol.solve(&p_xs.transpose()).transpose(); // P_xs P_ss^-1
            let dxi = &gain * ds;
            let mut p = &s.covariance - &gain * (p_ss - p_ss_post) * gain.transpose();
            kalman::symmetrize(&mut p);
            kalman::check_finite(&p, "covariance-intersection posterior")?;
            kalman::check_finite(&dxi, "covariance-intersection correction")?;
            for (axis, pi) in s.geometry.position_index.iter().enumerate() {
                if let Some(k) = pi {
                    s.geometry.position_ned_m[axis] += dxi[*k];
                }
            }
            if let Some(hd) = s.geometry.heading.as_mut() {
                hd.yaw_rad += dxi[hd.index];
            }
            s.covariance = p;
            dx[i] += dxi;
        }
    }
    Ok(work.into_iter().zip(dx).map(|(s, dx)| Correction { id: s.id, dx, p: s.covariance }).collect())
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The slow objective `scalar_trial_trace` replaces.
    fn trial_trace_by_joint_update(
        marginals: &[DMatrix<f64>],
        weights: &[f64],
        meas: &LinearizedMeasurement,
        block: (usize, usize),
    ) -> f64 {
        let n: usize = marginals.iter().map(|a| a.nrows()).sum();
        let mut p = DMatrix::zeros(n, n);
        let mut off = 0;
        for (a, w) in marginals.iter().zip(weights) {
            p.view_mut((off, off), (a.nrows(), a.nrows())).copy_from(&(a / *w));
            off += a.nrows();
        }
        kalman::joint_update(&p, meas, None)
            .map(|u| u.p.view((block.0, block.0), (block.1, block.1)).trace())
            .unwrap_or(f64::INFINITY)
    }

    /// Same bits as the joint update on random priors and ranges, with zeros (and negative
    /// zeros) in the Jacobian, weights near both ends, a noise of zero, an indefinite prior,
    /// values large enough to overflow the posterior, and residuals that overflow the correction.
    #[test]
    fn scalar_trial_trace_equals_the_joint_update_bit_for_bit() {
        use rand::{Rng, SeedableRng};
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(7);
        let mut cases = 0;
        let mut infinite = 0;
        for case in 0..20_000 {
            let dims: Vec<usize> = (0..rng.random_range(1..=2)).map(|_| rng.random_range(1..=4)).collect();
            let n: usize = dims.iter().sum();
            let scale = match case % 50 {
                0 => 1e154,
                1 => 1e-160,
                _ => 10f64.powi(rng.random_range(-3..4)),
            };
            let marginals: Vec<DMatrix<f64>> = dims
                .iter()
                .map(|&d| {
                    let a = DMatrix::from_fn(d, d, |_, _| rng.random_range(-1.0..1.0) * scale);
                    let mut m = &a * a.transpose();
                    if case % 37 == 0 {
                        m[(0, 0)] = -m[(0, 0)] - 1.0; // indefinite
                    }
                    m
                })
                .collect();
            let h = DMatrix::from_fn(1, n, |_, _| match rng.random_range(0..6) {
                0 => 0.0,
                1 => -0.0,
                _ => rng.random_range(-1.0..1.0),
            });
            let r = if case % 41 == 0 { 0.0 } else { rng.random_range(1e-4..1.0) };
            let meas = LinearizedMeasurement {
                h,
                // A residual near the largest value: the correction overflows, the posterior not.
                residual: DVector::from_element(1, if case % 43 == 0 { 1.7e308 } else { rng.random_range(-5.0..5.0) }),
                r: DMatrix::from_element(1, 1, r),
            };
            let w = match case % 7 {
                0 => 1e-3,
                1 => 1.0 - 1e-3,
                _ => rng.random_range(1e-3..1.0),
            };
            let weights: Vec<f64> = if dims.len() == 1 { vec![1.0] } else { vec![w, 1.0 - w] };
            let d0 = dims[0];
            for block in [(0, d0), (d0, n - d0)] {
                let fast = scalar_trial_trace(&marginals, &weights, &meas, block);
                let slow = trial_trace_by_joint_update(&marginals, &weights, &meas, block);
                assert_eq!(fast.to_bits(), slow.to_bits(), "case {case}, block {block:?}: {fast} vs {slow}");
                cases += 1;
                infinite += usize::from(fast.is_infinite());
            }
        }
        // Both outcomes were exercised.
        assert!(infinite > 100 && infinite < cases / 2, "{infinite} of {cases} failed updates");
    }

    #[test]
    fn golden_section_finds_a_parabola_minimum() {
        let x = golden_section(0.0, 1.0, 60, |x| (x - 0.3).powi(2));
        assert!((x - 0.3).abs() < 1e-8);
    }
}
