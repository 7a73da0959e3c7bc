//! Dense kernels of the joint update that keep nalgebra's rounding.
//!
//! The joint update of a large team is a rank-`m` downdate of the `16 N` joint covariance,
//! `P - W^T W` (see [`super::kalman::joint_update`]): about `(16 N)^2 m` multiply-adds, the cost
//! of a cooperative event of 32 or 64 platforms. nalgebra computes it as a general product,
//! every entry of both triangles, one dot product at a time. Here the result is symmetric by
//! construction, so each dot product is computed once for both triangles, four at a time
//! against one shared column, on AVX2 where the processor has it.
//!
//! Every entry is rounded exactly as `p.clone().gemm_tr(-1.0, w, w, 1.0)` followed by
//! [`super::kalman::symmetrize`] rounds it: each dot product sums in nalgebra's order (eight
//! interleaved partial sums, then `(s0 + s4) + (s1 + s5) + ...`, then the tail), with separate
//! multiplies and adds (Rust never fuses them), so the vector width changes nothing. The
//! experiment's outputs are unchanged bit for bit (tests/golden), and the tests below compare
//! with nalgebra exactly, not to a tolerance.

use nalgebra::DMatrix;

/// `a . b` summed as nalgebra's `dot` sums a dynamic column pair.
#[inline(always)]
fn dot_body(a: &[f64], b: &[f64]) -> f64 {
    let m = a.len().min(b.len());
    let mut acc = [0.0f64; 8];
    let full = m - m % 8;
    for (ca, cb) in a[..full].chunks_exact(8).zip(b[..full].chunks_exact(8)) {
        for k in 0..8 {
            acc[k] += ca[k] * cb[k];
        }
    }
    finish(&acc, &a[full..m], &b[full..m])
}

#[inline(always)]
fn finish(acc: &[f64; 8], a_tail: &[f64], b_tail: &[f64]) -> f64 {
    let mut res = 0.0;
    res += acc[0] + acc[4];
    res += acc[1] + acc[5];
    res += acc[2] + acc[6];
    res += acc[3] + acc[7];
    for (x, y) in a_tail.iter().zip(b_tail) {
        res += x * y;
    }
    res
}

/// `[a . b0, a . b1, a . b2, a . b3]`, each summed as [`dot_body`] sums it; `a` is loaded once.
#[inline(always)]
fn dots4_body(a: &[f64], b: [&[f64]; 4]) -> [f64; 4] {
    let m = a.len();
    let full = m - m % 8;
    let mut acc = [[0.0f64; 8]; 4];
    let mut c = 0;
    while c < full {
        let ca = &a[c..c + 8];
        for (acc, b) in acc.iter_mut().zip(&b) {
            let cb = &b[c..c + 8];
            for k in 0..8 {
                acc[k] += ca[k] * cb[k];
            }
        }
        c += 8;
    }
    std::array::from_fn(|q| finish(&acc[q], &a[full..m], &b[q][full..m]))
}

/// The dot products `W[:, i] . W[:, j]` for `i >= j`, into the lower triangle of `out`
/// (column `j` from row `j` down, contiguous).
#[inline(always)]
fn lower_gram_body(w: &DMatrix<f64>, out: &mut DMatrix<f64>) {
    let (n, m) = (w.ncols(), w.nrows());
    let ws = w.as_slice();
    let col = |i: usize| &ws[i * m..(i + 1) * m];
    let os = out.as_mut_slice();
    for j in 0..n {
        let cj = col(j);
        let oj = &mut os[j * n..(j + 1) * n];
        oj[j] = dot_body(cj, cj);
        let mut i = j + 1;
        while i + 4 <= n {
            let d = dots4_body(cj, [col(i), col(i + 1), col(i + 2), col(i + 3)]);
            oj[i..i + 4].copy_from_slice(&d);
            i += 4;
        }
        while i < n {
            oj[i] = dot_body(col(i), cj);
            i += 1;
        }
    }
}

/// [`dots4_body`] with AVX2 intrinsics: partial sums 0..3 in one register, 4..7 in another,
/// each lane the scalar partial sum it replaces (separate multiplies and adds, as the scalar
/// code; the finish is the scalar one).
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
fn dots4_avx2(a: &[f64], b: [&[f64]; 4]) -> [f64; 4] {
    use std::arch::x86_64::{__m256d, _mm256_add_pd, _mm256_loadu_pd, _mm256_mul_pd, _mm256_setzero_pd, _mm256_storeu_pd};
    let m = a.len();
    assert!(b.iter().all(|b| b.len() == m), "dots4: columns of different lengths");
    let full = m - m % 8;
    let mut lo: [__m256d; 4] = [_mm256_setzero_pd(); 4];
    let mut hi: [__m256d; 4] = [_mm256_setzero_pd(); 4];
    let mut c = 0;
    while c < full {
        // SAFETY: c + 8 <= full <= m, the length of `a` and of every `b` (asserted above).
        unsafe {
            let a_lo = _mm256_loadu_pd(a.as_ptr().add(c));
            let a_hi = _mm256_loadu_pd(a.as_ptr().add(c + 4));
            for q in 0..4 {
                lo[q] = _mm256_add_pd(lo[q], _mm256_mul_pd(a_lo, _mm256_loadu_pd(b[q].as_ptr().add(c))));
                hi[q] = _mm256_add_pd(hi[q], _mm256_mul_pd(a_hi, _mm256_loadu_pd(b[q].as_ptr().add(c + 4))));
            }
        }
        c += 8;
    }
    // A plain loop, not `array::from_fn`'s closure: LLVM may leave the closure out of line,
    // which cost a 64-platform event about 15 % once (measured).
    let mut out = [0.0; 4];
    for (q, o) in out.iter_mut().enumerate() {
        let mut acc = [0.0f64; 8];
        // SAFETY: `acc` holds 8 doubles, two stores of 4.
        unsafe {
            _mm256_storeu_pd(acc.as_mut_ptr(), lo[q]);
            _mm256_storeu_pd(acc.as_mut_ptr().add(4), hi[q]);
        }
        *o = finish(&acc, &a[full..m], &b[q][full..m]);
    }
    out
}

/// [`lower_gram_body`] with [`dots4_avx2`], in blocks of eight columns `j` (12 kB at 192 rows,
/// kept in L1) against every column `i` below them, which is then read once per block instead
/// of once per column.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
fn lower_gram_avx2(w: &DMatrix<f64>, out: &mut DMatrix<f64>) {
    const BLOCK: usize = 8;
    let (n, m) = (w.ncols(), w.nrows());
    let ws = w.as_slice();
    let col = |i: usize| &ws[i * m..(i + 1) * m];
    let os = out.as_mut_slice();
    for j0 in (0..n).step_by(BLOCK) {
        let j1 = (j0 + BLOCK).min(n);
        for i in j0..n {
            let ci = col(i);
            let top = j1.min(i + 1);
            let mut j = j0;
            while j + 4 <= top {
                let d = dots4_avx2(ci, [col(j), col(j + 1), col(j + 2), col(j + 3)]);
                for (q, d) in d.into_iter().enumerate() {
                    os[(j + q) * n + i] = d;
                }
                j += 4;
            }
            while j < top {
                os[j * n + i] = dot_body(ci, col(j));
                j += 1;
            }
        }
    }
}

/// `out = P - G`, symmetrised, from the lower triangle of the Gram matrix `G` in `out`
/// (see [`downdate_from_lower_gram_body`]; on AVX2, 4x4 blocks off the diagonal are read,
/// computed and written four entries at a time, the upper one transposed in registers).
fn downdate_from_lower_gram(p: &DMatrix<f64>, out: &mut DMatrix<f64>) {
    #[cfg(target_arch = "x86_64")]
    if has_avx2() {
        // SAFETY: the processor has AVX2 (checked just above).
        unsafe { downdate_from_lower_gram_avx2(p, out) };
        return;
    }
    downdate_from_lower_gram_body(p, out);
}

/// One entry `(i, j)`, `i >= j`, of [`downdate_from_lower_gram_body`].
#[inline(always)]
fn downdate_entry(ps: &[f64], os: &mut [f64], n: usize, i: usize, j: usize) {
    // (i, j) of the lower triangle is at j n + i, its mirror (j, i) at i n + j.
    let (lo, up) = (j * n + i, i * n + j);
    let d = os[lo];
    if i == j {
        // gemm_tr writes alpha * d + beta * p with alpha = -1, beta = 1.
        os[lo] = -d + ps[lo];
    } else {
        // ... and symmetrize averages the two triangles.
        let v = 0.5 * ((-d + ps[lo]) + (-d + ps[up]));
        os[lo] = v;
        os[up] = v;
    }
}

/// [`downdate_from_lower_gram_body`] with the 4x4 blocks below the diagonal blocks in AVX2
/// registers: each lane computes `0.5 * ((-d + p_lo) + (-d + p_up))` as the scalar entry does
/// (a negation, adds and a multiply: the same rounding); the diagonal blocks and the rows
/// past the last multiple of four go entry by entry.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
fn downdate_from_lower_gram_avx2(p: &DMatrix<f64>, out: &mut DMatrix<f64>) {
    use std::arch::x86_64::{
        __m256d, _mm256_add_pd, _mm256_loadu_pd, _mm256_mul_pd, _mm256_permute2f128_pd, _mm256_set1_pd, _mm256_storeu_pd,
        _mm256_sub_pd, _mm256_unpackhi_pd, _mm256_unpacklo_pd,
    };
    // The transpose of four rows of four.
    let transpose4 = |r: [__m256d; 4]| -> [__m256d; 4] {
        let t0 = _mm256_unpacklo_pd(r[0], r[1]);
        let t1 = _mm256_unpackhi_pd(r[0], r[1]);
        let t2 = _mm256_unpacklo_pd(r[2], r[3]);
        let t3 = _mm256_unpackhi_pd(r[2], r[3]);
        [
            _mm256_permute2f128_pd::<0x20>(t0, t2),
            _mm256_permute2f128_pd::<0x20>(t1, t3),
            _mm256_permute2f128_pd::<0x31>(t0, t2),
            _mm256_permute2f128_pd::<0x31>(t1, t3),
        ]
    };
    let n = p.nrows();
    assert!(p.ncols() == n && out.nrows() == n && out.ncols() == n, "downdate: shapes");
    let n4 = n - n % 4;
    let (ps, os) = (p.as_slice(), out.as_mut_slice());
    let half = _mm256_set1_pd(0.5);
    // In tiles of TILE x TILE (both triangles' tiles stay in L1 for a large team), 4x4 blocks
    // strictly below the diagonal blocks.
    const TILE: usize = 32;
    for j0 in (0..n4).step_by(TILE) {
        for i0 in (j0..n4).step_by(TILE) {
            for jb in (j0..(j0 + TILE).min(n4)).step_by(4) {
                for ib in (i0.max(jb + 4)..(i0 + TILE).min(n4)).step_by(4) {
                    // SAFETY: jb + 4 <= ib + 4 <= n4 <= n: every load and store reads or writes
                    // four entries (rows ib..ib + 4 of a column jb + q, or rows jb..jb + 4 of
                    // a column ib + q) of the n x n matrices (shapes asserted above).
                    unsafe {
                        let lower = |base: *const f64, q: usize| _mm256_loadu_pd(base.add((jb + q) * n + ib));
                        let upper = |base: *const f64, q: usize| _mm256_loadu_pd(base.add((ib + q) * n + jb));
                        let d: [__m256d; 4] = std::array::from_fn(|q| lower(os.as_ptr(), q));
                        let p_lo: [__m256d; 4] = std::array::from_fn(|q| lower(ps.as_ptr(), q));
                        let p_up = transpose4(std::array::from_fn(|q| upper(ps.as_ptr(), q)));
                        let v: [__m256d; 4] = std::array::from_fn(|q| {
                            // -d + x is x - d exactly (the negation is exact, addition commutes).
                            let a = _mm256_sub_pd(p_lo[q], d[q]);
                            let b = _mm256_sub_pd(p_up[q], d[q]);
                            _mm256_mul_pd(half, _mm256_add_pd(a, b))
                        });
                        let vt = transpose4(v);
                        for q in 0..4 {
                            _mm256_storeu_pd(os.as_mut_ptr().add((jb + q) * n + ib), v[q]);
                            _mm256_storeu_pd(os.as_mut_ptr().add((ib + q) * n + jb), vt[q]);
                        }
                    }
                }
            }
        }
    }
    // The diagonal blocks.
    for jb in (0..n4).step_by(4) {
        for j in jb..jb + 4 {
            for i in j..jb + 4 {
                downdate_entry(ps, os, n, i, j);
            }
        }
    }
    // The rows past n4, in every column.
    for j in 0..n {
        for i in n4.max(j)..n {
            downdate_entry(ps, os, n, i, j);
        }
    }
}

/// `out = P - G`, symmetrised, from the lower triangle of the Gram matrix `G` in `out`: square
/// tiles, so that both triangles are read and written a cache line at a time.
fn downdate_from_lower_gram_body(p: &DMatrix<f64>, out: &mut DMatrix<f64>) {
    const TILE: usize = 32;
    let n = p.nrows();
    let (ps, os) = (p.as_slice(), out.as_mut_slice());
    for j0 in (0..n).step_by(TILE) {
        for i0 in (j0..n).step_by(TILE) {
            for j in j0..(j0 + TILE).min(n) {
                for i in i0.max(j)..(i0 + TILE).min(n) {
                    downdate_entry(ps, os, n, i, j);
                }
            }
        }
    }
}

/// A copy of the `shape` block of `m` that starts at `start`, column slice by column slice
/// (nalgebra's `view(..).into_owned()` goes entry by entry through an iterator).
pub fn block(m: &DMatrix<f64>, start: (usize, usize), shape: (usize, usize)) -> DMatrix<f64> {
    let ((r, c), (nr, nc)) = (start, shape);
    assert!(
        r + nr <= m.nrows() && c + nc <= m.ncols(),
        "block {shape:?} at {start:?} outside a {}x{} matrix",
        m.nrows(),
        m.ncols()
    );
    let mut out = DMatrix::zeros(nr, nc);
    if nr > 0 {
        let src = m.as_slice();
        for (j, col) in out.as_mut_slice().chunks_exact_mut(nr).enumerate() {
            let from = (c + j) * m.nrows() + r;
            col.copy_from_slice(&src[from..from + nr]);
        }
    }
    out
}

/// A matrix operand read in place: `rows x cols` entries, entry `(r, c)` at
/// `data[r * rs + c * cs]`. [`Strided::t`] is the transpose, by swapping the strides (no copy).
#[derive(Debug, Clone, Copy)]
pub struct Strided<'a> {
    data: &'a [f64],
    rows: usize,
    cols: usize,
    rs: usize,
    cs: usize,
}

impl<'a> Strided<'a> {
    /// A column-major matrix as it is stored.
    pub fn of(m: &'a DMatrix<f64>) -> Self {
        Self { data: m.as_slice(), rows: m.nrows(), cols: m.ncols(), rs: 1, cs: m.nrows() }
    }

    /// The transpose.
    pub fn t(self) -> Self {
        Self { rows: self.cols, cols: self.rows, rs: self.cs, cs: self.rs, ..self }
    }

    fn fits(&self) -> bool {
        self.rows == 0 || self.cols == 0 || (self.rows - 1) * self.rs + (self.cols - 1) * self.cs < self.data.len()
    }
}

/// Above this size in every dimension nalgebra multiplies dynamic matrices with
/// `matrixmultiply` (its `SMALL_DIM`); at or below it, with its own loops.
pub const PRODUCT_KERNEL_ABOVE: usize = 5;

/// `A B` written into the `A.rows x B.cols` block of `out` that starts at `at`, computed by
/// `matrixmultiply` exactly as nalgebra's product of dynamic matrices computes it when every
/// dimension exceeds [`PRODUCT_KERNEL_ABOVE`]: the same result bit for bit (`matrixmultiply`
/// packs both operands before its kernel runs, so their strides change nothing; the result is
/// written column-major, as nalgebra's is). Where nalgebra needs `&a * b.transpose()` and two
/// copies, this reads `b` in place.
///
/// Panics when a dimension is [`PRODUCT_KERNEL_ABOVE`] or less (nalgebra would not use this
/// kernel), when the inner dimensions differ or when an operand or the block does not fit.
pub fn product_into(a: Strided, b: Strided, out: &mut DMatrix<f64>, at: (usize, usize)) {
    let (m, k, n) = (a.rows, a.cols, b.cols);
    assert!(k == b.rows, "product_into: {}x{} times {}x{}", a.rows, a.cols, b.rows, b.cols);
    assert!(
        m > PRODUCT_KERNEL_ABOVE && k > PRODUCT_KERNEL_ABOVE && n > PRODUCT_KERNEL_ABOVE,
        "product_into: {m}x{k} times {k}x{n} is nalgebra's small product"
    );
    assert!(a.fits() && b.fits(), "product_into: an operand's strides run past its data");
    let ld = out.nrows();
    assert!(
        at.0 + m <= ld && at.1 + n <= out.ncols(),
        "product_into: a {m}x{n} block at {at:?} outside a {}x{} matrix",
        ld,
        out.ncols()
    );
    let c = &mut out.as_mut_slice()[at.0 + at.1 * ld..];
    // SAFETY: every entry read is inside its operand's slice (`fits`, checked above), every
    // entry written inside `c`: row `at.0 + i < ld` of column `at.1 + j < ncols`, at offset
    // `i + j * ld` from the block's start, the last at `(m - 1) + (n - 1) * ld`, inside the
    // slice from the start to the end of `out`. beta = 0: `c` is written, not read.
    unsafe {
        matrixmultiply::dgemm(
            m,
            k,
            n,
            1.0,
            a.data.as_ptr(),
            a.rs as isize,
            a.cs as isize,
            b.data.as_ptr(),
            b.rs as isize,
            b.cs as isize,
            0.0,
            c.as_mut_ptr(),
            1,
            ld as isize,
        );
    }
}

/// Whether this processor has AVX2: the estimation core's hand kernels are compiled twice
/// (baseline x86-64 and AVX2) and pick one with this, at run time. The standard library caches
/// the answer.
pub(crate) fn has_avx2() -> bool {
    #[cfg(target_arch = "x86_64")]
    return std::arch::is_x86_feature_detected!("avx2");
    #[cfg(not(target_arch = "x86_64"))]
    false
}

/// `P - W^T W`, symmetrised, for a symmetric-shaped `P` (`n x n`) and `W` (`m x n`), given
/// with its transpose `w_t` (the joint update has both): equal bit for bit to
/// `p.clone().gemm_tr(-1.0, w, w, 1.0)` followed by [`super::kalman::symmetrize`], in about
/// half the work.
pub fn symmetric_downdate(p: &DMatrix<f64>, w: &DMatrix<f64>, w_t: &DMatrix<f64>) -> DMatrix<f64> {
    let n = p.nrows();
    assert!(p.ncols() == n && w.ncols() == n, "symmetric_downdate: P is {}x{}, W is {}x{}", n, p.ncols(), w.nrows(), w.ncols());
    assert!(w_t.nrows() == n && w_t.ncols() == w.nrows(), "symmetric_downdate: W^T is {}x{}", w_t.nrows(), w_t.ncols());
    let mut out = DMatrix::zeros(n, n);
    lower_gram(w, w_t, &mut out);
    downdate_from_lower_gram(p, &mut out);
    out
}

/// Up to this many rows of `W`, [`lower_gram_lanes_avx2`] computes four entries per vector
/// instead of one dot product's partial sums per vector (a short dot product is mostly its
/// finish).
const LANES_MAX_ROWS: usize = 16;

#[cfg_attr(not(target_arch = "x86_64"), allow(unused_variables))] // w_t feeds the AVX2 kernel only
fn lower_gram(w: &DMatrix<f64>, w_t: &DMatrix<f64>, out: &mut DMatrix<f64>) {
    #[cfg(target_arch = "x86_64")]
    if has_avx2() {
        if w.nrows() <= LANES_MAX_ROWS {
            // SAFETY: the processor has AVX2 (checked just above).
            unsafe { lower_gram_lanes_avx2(w, w_t, out) };
        } else {
            // SAFETY: the processor has AVX2 (checked just above).
            unsafe { lower_gram_avx2(w, out) };
        }
        return;
    }
    lower_gram_body(w, out);
}

/// [`lower_gram_body`] for a short `W` (`m` rows, `W^T` given too): four entries `(i..i+4, j)`
/// of a column at once, one lane each, every lane running [`dot_body`]'s sums for its own
/// entry (the eight partial sums, their pairing, the tail; separate multiplies and adds), so
/// each rounds as the scalar dot product does. Rows of a column left over at the bottom take
/// [`dot_body`] itself.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
fn lower_gram_lanes_avx2(w: &DMatrix<f64>, w_t: &DMatrix<f64>, out: &mut DMatrix<f64>) {
    use std::arch::x86_64::{
        __m256d, _mm256_add_pd, _mm256_loadu_pd, _mm256_mul_pd, _mm256_set1_pd, _mm256_setzero_pd, _mm256_storeu_pd,
    };
    let (n, m) = (w.ncols(), w.nrows());
    assert!(w_t.nrows() == n && w_t.ncols() == m && out.nrows() == n && out.ncols() == n, "lower_gram_lanes: shapes");
    let full = m - m % 8;
    let (ws, ts) = (w.as_slice(), w_t.as_slice());
    let col = |i: usize| &ws[i * m..(i + 1) * m];
    let os = out.as_mut_slice();
    for j in 0..n {
        let cj = col(j);
        let mut i = j;
        while i + 4 <= n {
            // SAFETY: every load reads W^T[i..i + 4, k] = ts[k n + i..k n + i + 4] with
            // k < m and i + 4 <= n, inside the n m entries of `ts` (its shape is asserted).
            let res = unsafe {
                let lanes = |k: usize| _mm256_loadu_pd(ts.as_ptr().add(k * n + i));
                let mut acc: [__m256d; 8] = [_mm256_setzero_pd(); 8];
                let mut c = 0;
                while c < full {
                    for (k, a) in acc.iter_mut().enumerate() {
                        *a = _mm256_add_pd(*a, _mm256_mul_pd(lanes(c + k), _mm256_set1_pd(cj[c + k])));
                    }
                    c += 8;
                }
                let mut res = _mm256_setzero_pd();
                for k in 0..4 {
                    res = _mm256_add_pd(res, _mm256_add_pd(acc[k], acc[k + 4]));
                }
                for (t, b) in cj.iter().enumerate().skip(full) {
                    res = _mm256_add_pd(res, _mm256_mul_pd(lanes(t), _mm256_set1_pd(*b)));
                }
                res
            };
            // SAFETY: i + 4 <= n: entries (i..i + 4, j) of the n x n output.
            unsafe { _mm256_storeu_pd(os.as_mut_ptr().add(j * n + i), res) };
            i += 4;
        }
        while i < n {
            os[j * n + i] = dot_body(col(i), cj);
            i += 1;
        }
    }
}

/// `B^T <- (L^-1 B)^T` in place, for a lower-triangular `L` (`m x m`) and `B^T` (`n x m`):
/// every column of `B` solved as nalgebra's `solve_lower_triangular` solves it (divide by the
/// diagonal, then `b[k] = -b[i] L[k, i] + b[k]` for `k > i`, in that order), but all `n` at
/// once along the contiguous columns of `B^T`. False, with `bt` partly solved, when a diagonal
/// entry is zero (nalgebra's `None`).
pub fn solve_lower_transposed(l: &DMatrix<f64>, bt: &mut DMatrix<f64>) -> bool {
    assert!(
        l.nrows() == l.ncols() && bt.ncols() == l.nrows(),
        "solve_lower_transposed: L is {}x{}, B^T is {}x{}",
        l.nrows(),
        l.ncols(),
        bt.nrows(),
        bt.ncols()
    );
    #[cfg(target_arch = "x86_64")]
    if has_avx2() {
        // SAFETY: the processor has AVX2 (checked just above).
        return unsafe { solve_lower_transposed_avx2(l, bt) };
    }
    solve_lower_transposed_body(l, bt)
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
fn solve_lower_transposed_avx2(l: &DMatrix<f64>, bt: &mut DMatrix<f64>) -> bool {
    solve_lower_transposed_body(l, bt)
}

#[inline(always)]
fn solve_lower_transposed_body(l: &DMatrix<f64>, bt: &mut DMatrix<f64>) -> bool {
    let (m, n) = (l.nrows(), bt.nrows());
    let data = bt.as_mut_slice();
    for i in 0..m {
        let diag = l[(i, i)];
        if diag == 0.0 {
            return false;
        }
        let (done, rest) = data.split_at_mut((i + 1) * n);
        let ci = &mut done[i * n..];
        for v in ci.iter_mut() {
            *v /= diag;
        }
        for (k, ck) in rest.chunks_exact_mut(n).enumerate() {
            let lk = l[(i + 1 + k, i)];
            for (y, x) in ck.iter_mut().zip(ci.iter()) {
                *y += -*x * lk;
            }
        }
    }
    true
}

#[cfg(test)]
mod tests {
    use rand::{Rng, SeedableRng};
    use rand_chacha::ChaCha8Rng;

    use super::*;
    use crate::estimation::kalman::symmetrize;

    /// The product read in place equals nalgebra's product of the copies, bit for bit, for
    /// either operand transposed or not, written into a block of a larger matrix (the rest of
    /// which it leaves alone), over shapes on both sides of the kernel's blocking.
    #[test]
    fn product_into_is_nalgebras_product_bit_for_bit() {
        let mut rng = ChaCha8Rng::seed_from_u64(41);
        for (m, k, n) in [(6, 6, 6), (16, 16, 16), (7, 13, 9), (48, 16, 33), (16, 70, 16), (9, 300, 6)] {
            let scale = 10f64.powi(rng.random_range(-6..6));
            let mut rand = |r: usize, c: usize| DMatrix::from_fn(r, c, |_, _| scale * (rng.random::<f64>() - 0.5));
            let (a, at, b, bt) = (rand(m, k), rand(k, m), rand(k, n), rand(n, k));
            for (lhs, rhs, want) in [
                (Strided::of(&a), Strided::of(&b), &a * &b),
                (Strided::of(&a), Strided::of(&bt).t(), &a * bt.transpose()),
                (Strided::of(&at).t(), Strided::of(&b), at.transpose() * &b),
                (Strided::of(&at).t(), Strided::of(&bt).t(), at.transpose() * bt.transpose()),
            ] {
                let mut out = DMatrix::from_element(m + 3, n + 2, 7.0);
                product_into(lhs, rhs, &mut out, (2, 1));
                assert_eq!(out.view((2, 1), (m, n)), want, "{m}x{k}x{n}");
                let untouched = out.iter().filter(|&&v| v == 7.0).count();
                assert_eq!(untouched, (m + 3) * (n + 2) - m * n, "{m}x{k}x{n}: outside the block");
            }
        }
    }

    #[test]
    #[should_panic(expected = "small product")]
    fn product_into_refuses_what_nalgebra_multiplies_itself() {
        let a = DMatrix::from_element(5, 16, 1.0);
        product_into(Strided::of(&a), Strided::of(&a).t(), &mut DMatrix::zeros(5, 5), (0, 0));
    }

    /// Every block of a few shapes, empty ones and the whole included: what nalgebra's view
    /// copies.
    #[test]
    fn block_copies_what_the_view_holds() {
        let m = DMatrix::from_fn(7, 5, |r, c| (10 * r + c) as f64);
        for (r, c, nr, nc) in [(0, 0, 7, 5), (2, 1, 3, 4), (6, 4, 1, 1), (3, 2, 0, 2), (1, 1, 4, 0)] {
            assert_eq!(block(&m, (r, c), (nr, nc)), m.view((r, c), (nr, nc)).into_owned(), "{nr}x{nc} at ({r}, {c})");
        }
    }

    fn reference(p: &DMatrix<f64>, w: &DMatrix<f64>) -> DMatrix<f64> {
        let mut out = p.clone();
        out.gemm_tr(-1.0, w, w, 1.0);
        symmetrize(&mut out);
        out
    }

    /// Every shape around the kernels' edges (tails of the 8-long sums, of the 4-wide blocks,
    /// the short-`W` lanes kernel and the long one), signed zeros in `W`, a `P` that is not
    /// exactly symmetric, every code path: equal bit for bit.
    #[test]
    fn the_downdate_rounds_exactly_as_nalgebra_and_symmetrize() {
        let mut rng = ChaCha8Rng::seed_from_u64(5);
        for n in [1, 2, 3, 4, 5, 7, 8, 9, 16, 17, 48, 50, 70] {
            for m in [1, 2, 3, 7, 8, 9, 15, 16, 17, 24] {
                let w = DMatrix::from_fn(m, n, |_, _| match rng.random_range(0..12) {
                    0 => 0.0,
                    1 => -0.0,
                    _ => rng.random_range(-1.0..1.0) * 10f64.powi(rng.random_range(-3..3)),
                });
                let p = DMatrix::from_fn(n, n, |_, _| rng.random_range(-5.0..5.0));
                let want = reference(&p, &w);
                let got = symmetric_downdate(&p, &w, &w.transpose());
                let mut portable = DMatrix::zeros(n, n);
                lower_gram_body(&w, &mut portable);
                downdate_from_lower_gram_body(&p, &mut portable);
                for (k, (a, b)) in want.iter().zip(got.iter()).enumerate() {
                    assert_eq!(a.to_bits(), b.to_bits(), "n {n}, m {m}, entry {k}: {a:e} vs {b:e}");
                }
                assert_eq!(got.as_slice(), portable.as_slice(), "n {n}, m {m}: the portable path differs");
            }
        }
    }

    /// Triangular solves of many right-hand sides at once: equal bit for bit to nalgebra's, and
    /// a zero diagonal refused as nalgebra refuses it.
    #[test]
    fn the_transposed_solve_rounds_exactly_as_nalgebra() {
        let mut rng = ChaCha8Rng::seed_from_u64(3);
        for m in [1, 2, 3, 5, 9, 24] {
            for n in [1, 3, 4, 7, 48, 130] {
                let a = DMatrix::from_fn(m, m, |_, _| rng.random_range(-1.0..1.0));
                let l = (&a * a.transpose() + DMatrix::identity(m, m)).cholesky().unwrap().l();
                let b = DMatrix::from_fn(m, n, |_, _| rng.random_range(-1e3..1e3));
                let want = l.solve_lower_triangular(&b).unwrap();
                let mut bt = b.transpose();
                assert!(solve_lower_transposed(&l, &mut bt));
                let mut portable = b.transpose();
                assert!(solve_lower_transposed_body(&l, &mut portable));
                for (k, (x, y)) in want.transpose().iter().zip(bt.iter()).enumerate() {
                    assert_eq!(x.to_bits(), y.to_bits(), "m {m}, n {n}, entry {k}");
                }
                assert_eq!(bt.as_slice(), portable.as_slice());
                let mut singular = l.clone();
                singular[(m - 1, m - 1)] = 0.0;
                assert_eq!(singular.solve_lower_triangular(&b).is_none(), !solve_lower_transposed(&singular, &mut b.transpose()));
            }
        }
    }

    #[test]
    fn dot_sums_in_nalgebras_order() {
        let mut rng = ChaCha8Rng::seed_from_u64(9);
        for m in 0..40 {
            let a = nalgebra::DVector::from_fn(m, |_, _| rng.random_range(-1.0..1.0) * 1e3);
            let b = nalgebra::DVector::from_fn(m, |_, _| rng.random_range(-1.0..1.0) * 1e-3);
            assert_eq!(dot_body(a.as_slice(), b.as_slice()).to_bits(), a.dot(&b).to_bits(), "m {m}");
        }
    }
}
