//! Kalman-filter primitives shared by every filter in the crate: the local (Joseph-form) update
//! that also yields the factor `I - K H` the recursive coefficient matrix needs, the joint update
//! used by cooperative events and the centralized EKF, and covariance propagation.
//!
//! Every routine validates its inputs first and returns a typed error without touching anything
//! when they are not finite, not of matching size, or not positive definite; callers commit the
//! returned values only on success.

use nalgebra::{DMatrix, DVector};

use super::EstimationError;

/// A measurement linearised about the current estimate: `residual = z - h(x_hat)` and
/// `z - h(x_hat) ~= H dx + v`, `v ~ N(0, R)`.
#[derive(Debug, Clone, PartialEq)]
pub struct LinearizedMeasurement {
    /// Jacobian with respect to the error state, `m x n`.
    pub h: DMatrix<f64>,
    /// Measured minus predicted, `m`.
    pub residual: DVector<f64>,
    /// Measurement noise covariance, `m x m`, positive definite.
    pub r: DMatrix<f64>,
}

impl LinearizedMeasurement {
    /// Number of scalar measurements.
    pub fn len(&self) -> usize {
        self.residual.len()
    }

    /// True when it holds no scalar measurement.
    pub fn is_empty(&self) -> bool {
        self.residual.is_empty()
    }

    /// Checks sizes against a state of dimension `n` and that every entry is finite.
    pub fn validate(&self, n: usize) -> Result<(), EstimationError> {
        let m = self.residual.len();
        if self.h.ncols() != n {
            return Err(EstimationError::DimensionMismatch {
                what: "measurement Jacobian columns",
                expected: n,
                got: self.h.ncols(),
            });
        }
        if self.h.nrows() != m {
            return Err(EstimationError::DimensionMismatch {
                what: "measurement Jacobian rows",
                expected: m,
                got: self.h.nrows(),
            });
        }
        if self.r.nrows() != m || self.r.ncols() != m {
            return Err(EstimationError::DimensionMismatch {
                what: "measurement noise covariance",
                expected: m,
                got: self.r.nrows(),
            });
        }
        check_finite(&self.h, "measurement Jacobian")?;
        check_finite(&self.residual, "measurement residual")?;
        check_finite(&self.r, "measurement noise covariance")?;
        Ok(())
    }
}

/// What an update reports about itself; the caller decides what to log.
#[derive(Debug, Clone, PartialEq)]
pub struct UpdateDiagnostics {
    /// The innovation `z - h(x_hat)`.
    pub innovation: DVector<f64>,
    /// Its predicted covariance `S = H P H^T + R`.
    pub innovation_cov: DMatrix<f64>,
    /// Normalised innovation squared `r^T S^-1 r` (chi-square with `m` degrees of freedom when the
    /// filter is consistent).
    pub nis: f64,
}

/// The result of a local update, not yet committed.
#[derive(Debug, Clone)]
pub struct LocalUpdate {
    /// Error-state correction `K r`.
    pub dx: DVector<f64>,
    /// Posterior covariance (Joseph form, symmetrised).
    pub p: DMatrix<f64>,
    /// `I - K H`: the factor that left-multiplies the recursive coefficient matrix Psi.
    pub i_minus_kh: DMatrix<f64>,
    pub diagnostics: UpdateDiagnostics,
}

/// The result of a joint update over stacked states, not yet committed.
#[derive(Debug, Clone)]
pub struct JointUpdate {
    /// Stacked error-state correction.
    pub dx: DVector<f64>,
    /// Stacked posterior covariance (symmetrised).
    pub p: DMatrix<f64>,
    /// `(I - K H) X` for the passive column block `X` given to [`joint_update`].
    pub passive: Option<DMatrix<f64>>,
    /// `L^-1 H X` (`S = L L^T`, the innovation covariance) for that block: the whitened
    /// correlation of the passive columns with the innovation, from which a passive platform's
    /// own share of the update is built ([`crate::estimation::coop`], bystanders).
    pub passive_white: Option<DMatrix<f64>>,
    /// `L^-1 (z - h)`: the whitened innovation.
    pub white_residual: DVector<f64>,
    pub diagnostics: UpdateDiagnostics,
}

/// Returns an error naming `what` when any entry is NaN or infinite.
pub fn check_finite<R: nalgebra::Dim, C: nalgebra::Dim, S: nalgebra::RawStorage<f64, R, C>>(
    m: &nalgebra::Matrix<f64, R, C, S>,
    what: &'static str,
) -> Result<(), EstimationError> {
    let finite = if m.data.is_contiguous() {
        // SAFETY: the storage says it is contiguous, so its buffer is one slice of its entries.
        all_finite(unsafe { m.data.as_slice_unchecked() })
    } else {
        m.iter().all(|v| v.is_finite())
    };
    if finite { Ok(()) } else { Err(EstimationError::NonFinite { what }) }
}

/// Whether every value is finite, without a branch per value: `x - x` is `+0` for a finite `x`
/// and NaN for an infinite or NaN one, and a sum of them is `0` exactly when none is NaN (no
/// overflow is possible). Eight running sums, so that the loop vectorises.
#[allow(clippy::eq_op)] // `x - x` is the test itself
pub fn all_finite(values: &[f64]) -> bool {
    let mut acc = [0.0f64; 8];
    let chunks = values.chunks_exact(8);
    let rest = chunks.remainder();
    for c in chunks {
        for (a, x) in acc.iter_mut().zip(c) {
            *a += x - x;
        }
    }
    let mut total: f64 = acc.iter().sum();
    for x in rest {
        total += x - x;
    }
    total == 0.0
}

/// Replaces `m` by `(m + m^T) / 2`.
pub fn symmetrize(m: &mut DMatrix<f64>) {
    let n = m.nrows();
    for j in 0..n {
        for i in (j + 1)..n {
            let v = 0.5 * (m[(i, j)] + m[(j, i)]);
            m[(i, j)] = v;
            m[(j, i)] = v;
        }
    }
}

fn check_square(p: &DMatrix<f64>, what: &'static str) -> Result<(), EstimationError> {
    if p.nrows() != p.ncols() {
        return Err(EstimationError::DimensionMismatch { what, expected: p.nrows(), got: p.ncols() });
    }
    check_finite(p, what)
}

fn innovation_factor(s: DMatrix<f64>) -> Result<(nalgebra::Cholesky<f64, nalgebra::Dyn>, DMatrix<f64>), EstimationError> {
    let chol = nalgebra::Cholesky::new(s.clone())
        .ok_or(EstimationError::NotPositiveDefinite { what: "innovation covariance H P H^T + R" })?;
    Ok((chol, s))
}

/// Local Kalman update of one platform's own state (paper Eqs. 4-5), Joseph form.
///
/// The gain is the optimal one for this platform's own covariance `p`. Returns the correction,
/// the posterior covariance and `I - K H`, which the caller folds into its recursive coefficient
/// matrix (paper Eq. 6: the coefficient in front of the state).
pub fn local_update(p: &DMatrix<f64>, meas: &LinearizedMeasurement) -> Result<LocalUpdate, EstimationError> {
    check_square(p, "covariance")?;
    let n = p.nrows();
    meas.validate(n)?;
    let ph_t = p * meas.h.transpose();
    let mut s = &meas.h * &ph_t + &meas.r;
    symmetrize(&mut s);
    let (chol, s) = innovation_factor(s)?;
    // K = P H^T S^-1, computed as K^T = S^-1 (H P) without forming an inverse.
    let k = chol.solve(&ph_t.transpose()).transpose();
    let mut a = DMatrix::<f64>::identity(n, n);
    a -= &k * &meas.h;
    let mut p_post = &a * p * a.transpose() + &k * &meas.r * k.transpose();
    symmetrize(&mut p_post);
    let dx = &k * &meas.residual;
    let nis = meas.residual.dot(&chol.solve(&meas.residual));
    check_finite(&p_post, "posterior covariance")?;
    check_finite(&dx, "state correction")?;
    Ok(LocalUpdate {
        dx,
        p: p_post,
        i_minus_kh: a,
        diagnostics: UpdateDiagnostics { innovation: meas.residual.clone(), innovation_cov: s, nis },
    })
}

/// Joint update of a stacked state (paper Step 5, Eqs. 11-13), optimal gain.
///
/// With `S = L L^T` and `U = P H^T L^-T`, the posterior is `P - U U^T`: the optimal-gain
/// covariance update written as a symmetric downdate, which costs `n^2 m` instead of the
/// Joseph form's `n^3` (the joint state of 64 platforms has ~1000 states) and cannot lose
/// symmetry. `passive` is an optional block of extra columns `X` (cross-covariances of the
/// stacked state with platforms outside the event) that the update carries as `(I - K H) X`.
pub fn joint_update(
    p: &DMatrix<f64>,
    meas: &LinearizedMeasurement,
    passive: Option<&DMatrix<f64>>,
) -> Result<JointUpdate, EstimationError> {
    check_square(p, "joint covariance")?;
    let n = p.nrows();
    meas.validate(n)?;
    if let Some(x) = passive {
        if x.nrows() != n {
            return Err(EstimationError::DimensionMismatch {
                what: "passive cross-covariance rows",
                expected: n,
                got: x.nrows(),
            });
        }
        check_finite(x, "passive cross-covariance")?;
    }
    // Range Jacobians touch a handful of columns of a joint state of hundreds: multiply by the
    // nonzeros only.
    update_by_rows(p, &row_nonzeros(&meas.h), &meas.residual, &meas.r, passive)
}

/// [`joint_update`] (no passive block) for a Jacobian given by the nonzeros `(column, value)`
/// of each row in column order, as a caller that stacks the rows of several measurements can
/// write them without forming the Jacobian: the same results bit for bit. Checks what
/// [`joint_update`] checks.
pub fn joint_update_by_rows(
    p: &DMatrix<f64>,
    rows: &[Vec<(usize, f64)>],
    residual: &DVector<f64>,
    r: &DMatrix<f64>,
) -> Result<JointUpdate, EstimationError> {
    check_square(p, "joint covariance")?;
    let (n, m) = (p.nrows(), rows.len());
    if residual.len() != m {
        return Err(EstimationError::DimensionMismatch { what: "measurement Jacobian rows", expected: m, got: residual.len() });
    }
    if r.nrows() != m || r.ncols() != m {
        return Err(EstimationError::DimensionMismatch { what: "measurement noise covariance", expected: m, got: r.nrows() });
    }
    for row in rows {
        for w in row.windows(2) {
            if w[0].0 >= w[1].0 {
                return Err(EstimationError::InvalidValue { what: "measurement Jacobian row order", value: w[1].0 as f64 });
            }
        }
        if let Some(&(c, _)) = row.last().filter(|(c, _)| *c >= n) {
            return Err(EstimationError::DimensionMismatch { what: "measurement Jacobian columns", expected: n, got: c + 1 });
        }
        if !row.iter().all(|(_, v)| v.is_finite()) {
            return Err(EstimationError::NonFinite { what: "measurement Jacobian" });
        }
    }
    check_finite(residual, "measurement residual")?;
    check_finite(r, "measurement noise covariance")?;
    update_by_rows(p, rows, residual, r, None)
}

/// The joint update on checked inputs. P H^T is built column by column from columns of P
/// (contiguous), and H P = (P H^T)^T because P is symmetric.
fn update_by_rows(
    p: &DMatrix<f64>,
    nonzeros: &[Vec<(usize, f64)>],
    residual: &DVector<f64>,
    r: &DMatrix<f64>,
    passive: Option<&DMatrix<f64>>,
) -> Result<JointUpdate, EstimationError> {
    let ph_t = sparse_mul_transposed(p, nonzeros);
    let mut s = h_times_transposed(&ph_t, nonzeros) + r;
    symmetrize(&mut s);
    let (chol, s) = innovation_factor(s)?;
    let l = chol.l();
    // W = L^-1 (H P) = U^T, so that P_post = P - W^T W and K = W^T L^-1.
    // Solved along the contiguous columns of (H P)^T = P H^T, all right-hand sides at once.
    let mut w_t = ph_t;
    if !super::dense::solve_lower_transposed(&l, &mut w_t) {
        return Err(EstimationError::NotPositiveDefinite { what: "innovation covariance factor" });
    }
    let w = w_t.transpose();
    let white_residual = l
        .solve_lower_triangular(residual)
        .ok_or(EstimationError::NotPositiveDefinite { what: "innovation covariance factor" })?;
    // P - W^T W, symmetrised: each entry computed once for both triangles (super::dense).
    let p_post = super::dense::symmetric_downdate(p, &w, &w_t);
    let dx = w.tr_mul(&white_residual);
    let nis = white_residual.norm_squared();
    let (passive, passive_white) = match passive {
        Some(x) => {
            // (I - K H) X = X - W^T L^-1 (H X)
            let hx = sparse_mul_transposed(&x.transpose(), nonzeros).transpose();
            let z = l
                .solve_lower_triangular(&hx)
                .ok_or(EstimationError::NotPositiveDefinite { what: "innovation covariance factor" })?;
            let mut out = x.clone();
            out.gemm_tr(-1.0, &w, &z, 1.0);
            (Some(out), Some(z))
        }
        None => (None, None),
    };
    check_finite(&p_post, "posterior joint covariance")?;
    check_finite(&dx, "joint state correction")?;
    Ok(JointUpdate {
        dx,
        p: p_post,
        passive,
        passive_white,
        white_residual,
        diagnostics: UpdateDiagnostics { innovation: residual.clone(), innovation_cov: s, nis },
    })
}

/// The nonzero entries `(column, value)` of each row of `h`.
fn row_nonzeros(h: &DMatrix<f64>) -> Vec<Vec<(usize, f64)>> {
    // Column by column (nalgebra's storage order): each row's nonzeros come out by column.
    let mut rows = vec![Vec::new(); h.nrows()];
    for (c, col) in h.column_iter().enumerate() {
        for (r, &v) in col.iter().enumerate() {
            if v != 0.0 {
                rows[r].push((c, v));
            }
        }
    }
    rows
}

/// `A H^T` for a sparse `H` given by its row nonzeros: column `r` is `sum_c H[r, c] A[:, c]`.
fn sparse_mul_transposed(a: &DMatrix<f64>, h_rows: &[Vec<(usize, f64)>]) -> DMatrix<f64> {
    let mut out = DMatrix::zeros(a.nrows(), h_rows.len());
    for (r, row) in h_rows.iter().enumerate() {
        let mut col = out.column_mut(r);
        for &(c, v) in row {
            col.axpy(v, &a.column(c), 1.0);
        }
    }
    out
}

/// `(A^T H^T)` for `A = P H^T` (`n x m`) and a sparse `H`: entry `(r, c)` is
/// `sum_k H[c, k] A[k, r]`, summed over the nonzeros of row `c` in order, as
/// [`sparse_mul_transposed`] of `A^T` sums it (its axpy adds `v x` to the running sum), without
/// forming `A^T`.
fn h_times_transposed(a: &DMatrix<f64>, h_rows: &[Vec<(usize, f64)>]) -> DMatrix<f64> {
    let m = h_rows.len();
    DMatrix::from_fn(a.ncols(), m, |r, c| {
        let col = a.column(r);
        h_rows[c].iter().fold(0.0, |acc, &(k, v)| v * col[k] + acc)
    })
}

/// Time update of a covariance and its recursive coefficient matrix (paper Eq. 3 and Eq. 6):
/// `P <- Phi P Phi^T + Qd`, `Psi <- Phi Psi`.
pub fn propagate(
    p: &mut DMatrix<f64>,
    psi: &mut DMatrix<f64>,
    phi: &DMatrix<f64>,
    qd: &DMatrix<f64>,
) -> Result<(), EstimationError> {
    let n = p.nrows();
    for (m, what) in [(phi, "transition matrix Phi"), (qd, "process noise Qd")] {
        if m.nrows() != n || m.ncols() != n {
            return Err(EstimationError::DimensionMismatch { what, expected: n, got: m.nrows() });
        }
        check_finite(m, what)?;
    }
    let mut p_new = phi * &*p * phi.transpose() + qd;
    symmetrize(&mut p_new);
    check_finite(&p_new, "propagated covariance")?;
    *psi = phi * &*psi;
    *p = p_new;
    Ok(())
}

/// Whether a symmetric matrix is positive semi-definite to a relative tolerance: no negative
/// diagonal entry and `P + rel_tol * max(diag) * I` has a Cholesky factor (its smallest
/// eigenvalue is above `-rel_tol * max(diag)`). Cheap enough for every broadcast.
pub fn is_psd(p: &DMatrix<f64>, rel_tol: f64) -> bool {
    if p.nrows() != p.ncols() || !all_finite(p.as_slice()) || p.diagonal().iter().any(|v| *v < 0.0) {
        return false;
    }
    let scale = p.diagonal().max().max(f64::MIN_POSITIVE);
    let mut shifted = p.clone();
    for i in 0..p.nrows() {
        shifted[(i, i)] += rel_tol * scale;
    }
    shifted.cholesky().is_some()
}

/// Smallest eigenvalue of a symmetric matrix (for PSD checks in tests and diagnostics).
pub fn min_eigenvalue(p: &DMatrix<f64>) -> f64 {
    p.clone().symmetric_eigen().eigenvalues.iter().copied().fold(f64::INFINITY, f64::min)
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::dmatrix;

    /// The finiteness check finds one bad value at any place of any length (both the 8-wide
    /// part and the tail), on contiguous matrices and on strided views, and passes values near
    /// the largest finite ones (no overflow).
    #[test]
    fn finiteness_check_finds_every_bad_value() {
        for len in [0usize, 1, 7, 8, 9, 17, 48 * 48] {
            let good: Vec<f64> = (0..len).map(|i| if i % 2 == 0 { f64::MAX } else { -f64::MAX }).collect();
            assert!(all_finite(&good), "len {len}");
            for at in [0, len / 2, len.saturating_sub(1)].into_iter().filter(|&at| at < len) {
                for bad in [f64::NAN, f64::INFINITY, f64::NEG_INFINITY] {
                    let mut v = good.clone();
                    v[at] = bad;
                    assert!(!all_finite(&v), "len {len}, {bad} at {at}");
                }
            }
        }
        let mut m = DMatrix::from_element(9, 9, 1.0);
        assert!(check_finite(&m, "m").is_ok());
        m[(6, 7)] = f64::NAN;
        assert_eq!(check_finite(&m, "m"), Err(EstimationError::NonFinite { what: "m" }));
        assert!(check_finite(&m.view((0, 0), (6, 9)), "rows").is_ok(), "a strided view without the NaN");
        assert!(check_finite(&m.view((5, 5), (3, 3)), "block").is_err(), "a strided view with it");
        assert!(check_finite(&m.column(7), "column").is_err());
    }

    fn textbook(p: &DMatrix<f64>, m: &LinearizedMeasurement) -> (DVector<f64>, DMatrix<f64>) {
        let s = &m.h * p * m.h.transpose() + &m.r;
        let k = p * m.h.transpose() * s.try_inverse().unwrap();
        let dx = &k * &m.residual;
        let p_post = (DMatrix::identity(p.nrows(), p.nrows()) - &k * &m.h) * p;
        (dx, p_post)
    }

    fn example() -> (DMatrix<f64>, LinearizedMeasurement) {
        let p = dmatrix![4.0, 1.0, 0.5; 1.0, 3.0, 0.2; 0.5, 0.2, 2.0];
        let m = LinearizedMeasurement {
            h: dmatrix![1.0, 0.0, -1.0; 0.3, 1.0, 0.0],
            residual: DVector::from_vec(vec![0.7, -0.2]),
            r: dmatrix![0.5, 0.1; 0.1, 0.4],
        };
        (p, m)
    }

    /// The update by row nonzeros is the update by the Jacobian, bit for bit, and refuses rows
    /// out of order, columns past the state, non-finite values and sizes that do not match.
    #[test]
    fn the_update_by_rows_is_the_update_by_the_jacobian() {
        let a = DMatrix::from_fn(9, 11, |r, c| ((r * 5 + c * 3) % 7) as f64 * 0.3 - 0.8);
        let p = &a * a.transpose() + DMatrix::identity(9, 9) * 0.1;
        let h = DMatrix::from_fn(4, 9, |r, c| if (r + 2 * c) % 3 == 0 { 0.4 * r as f64 - 0.13 * c as f64 + 0.05 } else { 0.0 });
        let meas = LinearizedMeasurement {
            h: h.clone(),
            residual: DVector::from_vec(vec![0.3, -0.1, 0.25, 0.02]),
            r: DMatrix::from_diagonal(&DVector::from_vec(vec![0.1, 0.2, 0.05, 0.3])),
        };
        let rows = row_nonzeros(&h);
        let want = joint_update(&p, &meas, None).unwrap();
        let got = joint_update_by_rows(&p, &rows, &meas.residual, &meas.r).unwrap();
        assert_eq!(format!("{:?}", (&got.dx, &got.p, &got.diagnostics)), format!("{:?}", (&want.dx, &want.p, &want.diagnostics)));
        let refused = |rows: &[Vec<(usize, f64)>], residual: &DVector<f64>, r: &DMatrix<f64>| {
            joint_update_by_rows(&p, rows, residual, r).expect_err("bad input goes through")
        };
        let mut swapped = rows.clone();
        swapped[0].reverse();
        assert!(matches!(refused(&swapped, &meas.residual, &meas.r), EstimationError::InvalidValue { .. }));
        let mut outside = rows.clone();
        outside[1].push((9, 1.0));
        assert!(matches!(refused(&outside, &meas.residual, &meas.r), EstimationError::DimensionMismatch { got: 10, .. }));
        let mut nan = rows.clone();
        nan[2][0].1 = f64::NAN;
        assert_eq!(refused(&nan, &meas.residual, &meas.r), EstimationError::NonFinite { what: "measurement Jacobian" });
        assert!(matches!(refused(&rows[..3], &meas.residual, &meas.r), EstimationError::DimensionMismatch { .. }));
        assert!(matches!(refused(&rows, &meas.residual, &DMatrix::identity(3, 3)), EstimationError::DimensionMismatch { .. }));
    }

    /// H (P H^T) read straight from P H^T equals, bit for bit, the product through its transpose.
    #[test]
    fn the_innovation_product_skips_the_transpose_exactly() {
        let p = DMatrix::from_fn(9, 9, |r, c| ((r * 7 + c * 3) % 11) as f64 * 0.37 - 1.3);
        let h = DMatrix::from_fn(4, 9, |r, c| if (r + c) % 3 == 0 { (r as f64 + 1.0) * 0.7 - c as f64 * 0.21 } else { 0.0 });
        let nz = row_nonzeros(&h);
        let ph_t = sparse_mul_transposed(&p, &nz);
        let want = sparse_mul_transposed(&ph_t.transpose(), &nz);
        let got = h_times_transposed(&ph_t, &nz);
        assert_eq!(want.shape(), got.shape());
        for (a, b) in want.iter().zip(got.iter()) {
            assert_eq!(a.to_bits(), b.to_bits());
        }
    }

    #[test]
    fn local_and_joint_updates_agree_with_textbook_formulas() {
        let (p, m) = example();
        let (dx_ref, p_ref) = textbook(&p, &m);
        let local = local_update(&p, &m).unwrap();
        let joint = joint_update(&p, &m, None).unwrap();
        for (dx, pp) in [(&local.dx, &local.p), (&joint.dx, &joint.p)] {
            assert!((dx - &dx_ref).amax() < 1e-12, "{dx} vs {dx_ref}");
            assert!((pp - &p_ref).amax() < 1e-12);
        }
        // NIS by hand: r^T S^-1 r.
        let s = &m.h * &p * m.h.transpose() + &m.r;
        let nis = (m.residual.transpose() * s.try_inverse().unwrap() * &m.residual)[0];
        assert!((local.diagnostics.nis - nis).abs() < 1e-12);
        assert!((joint.diagnostics.nis - nis).abs() < 1e-12);
        // I - KH applied to P gives the optimal-gain posterior.
        assert!((&local.i_minus_kh * &p - &p_ref).amax() < 1e-12);
    }

    #[test]
    fn passive_columns_follow_i_minus_kh() {
        let (p, m) = example();
        let x = dmatrix![1.0, 2.0; 0.0, -1.0; 0.5, 0.25];
        let joint = joint_update(&p, &m, Some(&x)).unwrap();
        let local = local_update(&p, &m).unwrap();
        assert!((joint.passive.unwrap() - &local.i_minus_kh * &x).amax() < 1e-12);
    }

    #[test]
    fn bad_inputs_are_typed_errors() {
        let (p, mut m) = example();
        m.residual[0] = f64::NAN;
        assert_eq!(local_update(&p, &m).unwrap_err(), EstimationError::NonFinite { what: "measurement residual" });
        let (p, mut m) = example();
        m.r = dmatrix![-10.0, 0.0; 0.0, -10.0];
        assert!(matches!(joint_update(&p, &m, None), Err(EstimationError::NotPositiveDefinite { .. })));
        let (p, mut m) = example();
        m.h = DMatrix::zeros(2, 2);
        assert!(matches!(local_update(&p, &m), Err(EstimationError::DimensionMismatch { .. })));
        let mut p2 = p.clone();
        let mut psi = DMatrix::identity(3, 3);
        let phi = DMatrix::from_element(3, 3, f64::INFINITY);
        assert!(propagate(&mut p2, &mut psi, &phi, &DMatrix::zeros(3, 3)).is_err());
        assert_eq!(p2, p, "a failed propagation leaves the covariance untouched");
    }
}
