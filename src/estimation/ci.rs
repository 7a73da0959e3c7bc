//! Cooperative localization by covariance intersection: the usual consistent-but-conservative
//! answer when cross-correlations are unknown.
//!
//! For a measurement between platforms `i` and `j` with unknown cross-covariance, the block
//! diagonal `diag(P_i / w, P_j / (1 - w))`, `0 < w < 1`, bounds the true joint covariance for
//! every possible correlation (the covariance-intersection bound applied to the stacked state).
//! The update runs on that bound; `w` minimises the trace of the stacked posterior (golden-section
//! search). Each platform keeps its own block; no correlation is stored. Measurements are
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
        let dims: Vec<usize> = idx.iter().map(|&i| work[i].dim()).collect();
        let n: usize = dims.iter().sum();
        let mut h = DMatrix::zeros(meas.len(), n);
        let mut off = 0;
        for ((_, lin), d) in parts.iter().zip(&dims) {
            h.view_mut((0, off), (meas.len(), *d)).copy_from(&lin.h);
            off += d;
        }
        let stacked = LinearizedMeasurement { h, residual: parts[0].1.residual.clone(), r: parts[0].1.r.clone() };
        let bound = |w: f64| {
            let mut p = DMatrix::zeros(n, n);
            let weights = if idx.len() == 1 { vec![1.0] } else { vec![w, 1.0 - w] };
            let mut off = 0;
            for ((&i, d), wt) in idx.iter().zip(&dims).zip(&weights) {
                p.view_mut((off, off), (*d, *d)).copy_from(&(&work[i].covariance / *wt));
                off += d;
            }
            p
        };
        let w = if idx.len() == 1 {
            1.0
        } else {
            golden_section(1e-3, 1.0 - 1e-3, 40, |w| {
                kalman::joint_update(&bound(w), &stacked, None).map(|u| u.p.trace()).unwrap_or(f64::INFINITY)
            })
        };
        let up = kalman::joint_update(&bound(w), &stacked, None)?;
        let mut off = 0;
        for (&i, d) in idx.iter().zip(&dims) {
            let dxi = up.dx.rows(off, *d).into_owned();
            let s = &mut work[i];
            for (axis, pi) in s.geometry.position_index.iter().enumerate() {
                if let Some(k) = pi {
                    s.geometry.position_ned_m[axis] += dxi[*k];
                }
            }
            if let Some(hd) = s.geometry.heading.as_mut() {
                hd.yaw_rad += dxi[hd.index];
            }
            s.covariance = up.p.view((off, off), (*d, *d)).into_owned();
            dx[i] += dxi;
            off += d;
        }
    }
    Ok(work.into_iter().zip(dx).map(|(s, dx)| Correction { id: s.id, dx, p: s.covariance }).collect())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn golden_section_finds_a_parabola_minimum() {
        let x = golden_section(0.0, 1.0, 60, |x| (x - 0.3).powi(2));
        assert!((x - 0.3).abs() < 1e-8);
    }
}
