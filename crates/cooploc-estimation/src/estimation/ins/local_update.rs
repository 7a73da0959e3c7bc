//! The INS filter's local update (the odometer's path: 10 Hz per vehicle, once per local
//! measurement for every method of every Monte Carlo run) on fixed-size arrays, with no heap
//! work beyond what the caller is handed back.
//!
//! Every sum is taken in the order nalgebra's dynamic-size routines take it, so the results
//! are the ones the general path ([`InsFilter::update_local_general`]) gives, bit for bit
//! (tested on random inputs, and by the experiment's golden files):
//!
//! - `H B` for `H` with up to [`MAX_ROWS`] rows and a 16x16 `B` (nalgebra's `gemm` below its
//!   `matrixmultiply` threshold of more than 5 rows: column by column, `y = h b + y` from
//!   `k = 0`);
//! - the dot product of two `m`-long columns, `m < 8` (nalgebra's `dot` for a dynamic length
//!   below its 8-way unrolling: `+0` plus the four empty partial sums, then each product in
//!   order);
//! - the dot product of two 16-long rows (one product per column, each after four empty
//!   partial sums);
//! - forward substitution by a lower-triangular `L` as `solve_lower_triangular` does it.
//!
//! Compiled twice, like the covariance step: for the baseline x86-64 (SSE2) and for AVX2,
//! chosen at run time; separate multiplies and adds either way, so both round alike.

use nalgebra::DMatrix;

use super::{ERROR_DIM, InsFilter, Matrix16, Vector16};
use crate::estimation::{EstimationError, LinearizedMeasurement, UpdateDiagnostics, dense, kalman};

/// The most rows the fixed-size path takes: from 6 rows on, nalgebra hands `H P` to
/// `matrixmultiply`, which sums in blocks (the odometer's update has 3).
pub(super) const MAX_ROWS: usize = 5;

/// Up to [`MAX_ROWS`] rows of 16 (the rows past the measurement's size are unused).
type Rows = [[f64; ERROR_DIM]; MAX_ROWS];

/// `H B` (`m` rows), given `B^T`: row `r` of the product is `sum_k H[r, k] B^T[:, k]` along
/// contiguous columns of `B^T` (each entry summed in nalgebra's order).
#[inline(always)]
fn rows_times(h: &Rows, m: usize, b_t: &Matrix16) -> Rows {
    let mut out = [[0.0; ERROR_DIM]; MAX_ROWS];
    let cols = &b_t.data.0;
    for (hr, o) in h.iter().zip(out.iter_mut()).take(m) {
        for (oj, bj) in o.iter_mut().zip(&cols[0]) {
            *oj = hr[0] * bj;
        }
        for k in 1..ERROR_DIM {
            let hk = hr[k];
            for (oj, bj) in o.iter_mut().zip(&cols[k]) {
                *oj += hk * bj;
            }
        }
    }
    out
}

/// Column `j` of `A^T B` (`m` rows each, `m < 8`, as [`MAX_ROWS`] is): entry `i` is the dot
/// product of column `i` of `A` and column `j` of `B`.
#[inline(always)]
fn gram_column(a: &Rows, b: &Rows, j: usize, m: usize) -> [f64; ERROR_DIM] {
    let mut out = [0.0; ERROR_DIM];
    for k in 0..m {
        let bk = b[k][j];
        for (o, x) in out.iter_mut().zip(&a[k]) {
            *o += x * bk;
        }
    }
    out
}

/// The dot product of two 16-long rows.
#[inline(always)]
fn row_dot(a: &[f64; ERROR_DIM], b: &[f64; ERROR_DIM]) -> f64 {
    let mut res = 0.0;
    for (x, y) in a.iter().zip(b) {
        res += 0.0;
        res += x * y;
    }
    res
}

/// `L^-1 v` in place for one column `v` of `m`; false when a diagonal entry is zero.
#[inline(always)]
fn solve_column(l: &DMatrix<f64>, v: &mut [f64], m: usize) -> bool {
    for i in 0..m {
        let diag = l[(i, i)];
        if diag == 0.0 {
            return false;
        }
        let coeff = v[i] / diag;
        v[i] = coeff;
        for k in i + 1..m {
            v[k] += -coeff * l[(k, i)];
        }
    }
    true
}

/// `L^-1 B` in place for the 16 columns of `B` (`m` rows), all columns at once along the rows.
#[inline(always)]
fn solve_rows(l: &DMatrix<f64>, b: &mut Rows, m: usize) -> bool {
    for i in 0..m {
        let diag = l[(i, i)];
        if diag == 0.0 {
            return false;
        }
        let (done, rest) = b.split_at_mut(i + 1);
        let bi = &mut done[i];
        for v in bi.iter_mut() {
            *v /= diag;
        }
        for (k, bk) in rest.iter_mut().enumerate().take(m - i - 1) {
            let lk = l[(i + 1 + k, i)];
            for (y, x) in bk.iter_mut().zip(bi.iter()) {
                *y += -x * lk;
            }
        }
    }
    true
}

impl InsFilter {
    /// [`InsFilter::update_local_general`] for a measurement of at most [`MAX_ROWS`] rows, on
    /// fixed-size arrays: the same results bit for bit. The caller has validated `meas` and
    /// flushed any pending propagation.
    pub(super) fn update_local_small(&mut self, meas: &LinearizedMeasurement) -> Result<UpdateDiagnostics, EstimationError> {
        #[cfg(target_arch = "x86_64")]
        if dense::has_avx2() {
            // SAFETY: the processor has AVX2 (checked just above).
            return unsafe { self.update_local_small_avx2(meas) };
        }
        self.update_local_small_body(meas)
    }

    /// The same body compiled for AVX2 (four lanes where SSE2 has two; separate multiplies and
    /// adds either way, so the results are the same bit for bit), as the covariance step is.
    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx2")]
    fn update_local_small_avx2(&mut self, meas: &LinearizedMeasurement) -> Result<UpdateDiagnostics, EstimationError> {
        self.update_local_small_body(meas)
    }

    #[inline(always)]
    fn update_local_small_body(&mut self, meas: &LinearizedMeasurement) -> Result<UpdateDiagnostics, EstimationError> {
        let m = meas.len();
        debug_assert!(m <= MAX_ROWS && meas.h.ncols() == ERROR_DIM);
        let mut h = [[0.0; ERROR_DIM]; MAX_ROWS];
        for (r, row) in h.iter_mut().enumerate().take(m) {
            for (c, v) in row.iter_mut().enumerate() {
                *v = meas.h[(r, c)];
            }
        }
        let hp = rows_times(&h, m, &self.p.get().transpose());
        let mut s = DMatrix::from_fn(m, m, |r, c| row_dot(&hp[r], &h[c]) + meas.r[(r, c)]);
        kalman::symmetrize(&mut s);
        let chol = nalgebra::Cholesky::new(s.clone())
            .ok_or(EstimationError::NotPositiveDefinite { what: "innovation covariance H P H^T + R" })?;
        let l = chol.l();
        let not_pd = EstimationError::NotPositiveDefinite { what: "innovation covariance factor" };
        let mut w = hp;
        if !solve_rows(&l, &mut w, m) {
            return Err(not_pd);
        }
        let mut white = [[0.0; ERROR_DIM]; MAX_ROWS];
        let mut v = [0.0; MAX_ROWS];
        v[..m].copy_from_slice(meas.residual.as_slice());
        if !solve_column(&l, &mut v, m) {
            return Err(not_pd);
        }
        for (row, x) in white.iter_mut().zip(v).take(m) {
            row[0] = x;
        }
        let dx = Vector16::from(gram_column(&w, &white, 0, m));
        // P+ = P - W^T W and Psi^T+ = Psi^T - (L^-1 H Psi)^T W, into the spare slots.
        let (p, p_post) = self.p.split();
        for (j, (c, out)) in p.data.0.iter().zip(p_post.data.0.iter_mut()).enumerate() {
            for ((o, v), g) in out.iter_mut().zip(c).zip(gram_column(&w, &w, j, m)) {
                *o = v - g;
            }
        }
        if self.track_psi {
            let (psi_t, psi_post) = self.psi_t.split();
            let mut z = rows_times(&h, m, psi_t);
            if !solve_rows(&l, &mut z, m) {
                return Err(not_pd);
            }
            for (j, (c, out)) in psi_t.data.0.iter().zip(psi_post.data.0.iter_mut()).enumerate() {
                for ((o, v), g) in out.iter_mut().zip(c).zip(gram_column(&z, &w, j, m)) {
                    *o = v - g;
                }
            }
        }
        self.finish_local_update(&dx)?;
        let nis = gram_column(&white, &white, 0, m)[0];
        Ok(UpdateDiagnostics { innovation: meas.residual.clone(), innovation_cov: s, nis })
    }
}
