//! The compact encoding of a state record's matrices (`COOPLOC_STATE_ENCODING` 2): 16-bit
//! fixed point in the *correlation form*: 916 bytes of matrices for 16 states, 58% of f32's and
//! 29% of f64's (a whole record: 1,041 B against 1,693 and 3,261), built so that the filter stays
//! consistent.
//!
//! Layout for an `n`-state record, little endian:
//!
//! | bytes | field |
//! |---|---|
//! | `n` x f32 | `sigma`: the standard deviations `sqrt(P_ii)`, each rounded *up* to f32 |
//! | f32 | `eps`: the inflation that covers the rounding of `U` (below), at most [`inflation`]`(n)` |
//! | `n(n+1)/2` x i16 | `U`, upper triangle row major: the Cholesky factor of the correlation matrix `C = S^-1 P S^-1 = U^T U`, each entry in [-1, 1] times 32767 |
//! | `n` x f32 | `m_r`: the largest magnitude in row `r` of `A = S^-1 Psi S`, rounded up |
//! | `n^2` x i16 | `A / m_r` times 32767, row major |
//!
//! (`S = diag(sigma)`; a zero `sigma_i` is taken as 1 in `S` for Psi, and gives a zero row of
//! `U`.)
//!
//! **Consistency.** Decoding gives `P_q = S (U_q^T U_q + eps I) S`. The sender computes `eps`
//! as the smallest inflation that makes `U_q^T U_q + eps I - S^-1 P S^-1` positive
//! semi-definite (minus its least eigenvalue, with a margin, rounded up): so `P_q - P` is
//! positive semi-definite, a receiver never believes a teammate better than the teammate does,
//! and `P_q` is positive semi-definite by construction whatever the bits say. `eps` is sent
//! rather than fixed because the worst case, `2 sqrt(n) e + e^2 + 4 n 2^-23` with
//! `e = sqrt(n(n+1)/2) / (2 * 32767)` (the Frobenius norm of the rounding error of `U`, the norm
//! of a factor with unit columns, the upward rounding of sigma), is 1.4e-3 for 16 states: as a
//! systematic inflation at every epoch it compounds in the directions ranges do not observe
//! (the team's common position): 20% more variance after the paper scenario's 380 epochs. The
//! actual need is about a twelfth of it for 16 states (a third for 3), and with it the variance
//! ends 1% above the f64 team's (`tests/node_core.rs`). A receiver refuses an `eps` above the
//! worst case. Psi is scaled into `A` by the same `S`, so its rounding (at most 1.5e-5 of a
//! row's largest correlation-scaled entry) is random, not systematic, and small against the
//! filter's own noise.
//!
//! Every node, the sender included, runs the joint update on the decoded matrices (the record's
//! quantisation rule), so the team agrees bit for bit whatever the encoding.

use nalgebra::DMatrix;

const Q: f64 = 32767.0;

/// Matrix bytes of an `n`-state record.
pub fn len(n: usize) -> usize {
    4 * n + 4 + 2 * (n * (n + 1) / 2) + 4 * n + 2 * n * n
}

/// The largest variance inflation (in correlation units) a record may carry: the worst case
/// of the rounding of `U`, see the module docs.
pub fn inflation(n: usize) -> f64 {
    let nf = n as f64;
    let e = (nf * (nf + 1.0) / 2.0).sqrt() / (2.0 * Q);
    2.0 * nf.sqrt() * e + e * e + 4.0 * nf * f64::from(f32::EPSILON)
}

/// The smallest f32 at or above `x` (x finite, non-negative).
fn f32_up(x: f64) -> f32 {
    let f = x as f32;
    if f64::from(f) < x { f.next_up() } else { f }
}

fn q16(x: f64) -> i16 {
    (x.clamp(-1.0, 1.0) * Q).round() as i16
}

/// Upper Cholesky factor `U` (`C = U^T U`) of a positive semi-definite matrix with unit
/// diagonal; a pivot that is not positive gives a zero row (semi-definite directions).
fn cholesky_upper(c: &DMatrix<f64>) -> DMatrix<f64> {
    let n = c.nrows();
    let mut u = DMatrix::zeros(n, n);
    for j in 0..n {
        let mut d = c[(j, j)];
        for k in 0..j {
            d -= u[(k, j)] * u[(k, j)];
        }
        if d <= 1e-15 {
            continue;
        }
        let ujj = d.sqrt();
        u[(j, j)] = ujj;
        for i in j + 1..n {
            let mut s = c[(j, i)];
            for k in 0..j {
                s -= u[(k, j)] * u[(k, i)];
            }
            u[(j, i)] = s / ujj;
        }
    }
    u
}

/// Appends the compact form of `p` (symmetric, finite, non-negative diagonal) and `psi`.
pub fn put(out: &mut Vec<u8>, p: &DMatrix<f64>, psi: &DMatrix<f64>) {
    let n = p.nrows();
    let sigma: Vec<f32> = (0..n).map(|i| f32_up(p[(i, i)].max(0.0).sqrt())).collect();
    let s: Vec<f64> = sigma.iter().map(|&x| f64::from(x)).collect();
    let mut c = DMatrix::zeros(n, n);
    for r in 0..n {
        for k in 0..n {
            c[(r, k)] = if r == k {
                1.0
            } else if s[r] > 0.0 && s[k] > 0.0 {
                (p[(r, k)] / (s[r] * s[k])).clamp(-1.0, 1.0)
            } else {
                0.0
            };
        }
    }
    let u = cholesky_upper(&c);
    let uq = DMatrix::from_fn(n, n, |r, k| if r <= k { f64::from(q16(u[(r, k)])) / Q } else { 0.0 });
    let delta = uq.transpose() * &uq - &c;
    let need = (-delta.symmetric_eigen().eigenvalues.min()).max(0.0);
    // A margin for the eigenvalue's own rounding; never above the worst case (which holds).
    let eps = f32_up((need * 1.01 + 1e-12).min(inflation(n)));
    for v in &sigma {
        out.extend_from_slice(&v.to_le_bytes());
    }
    out.extend_from_slice(&eps.to_le_bytes());
    for r in 0..n {
        for k in r..n {
            out.extend_from_slice(&q16(u[(r, k)]).to_le_bytes());
        }
    }
    let scale: Vec<f64> = s.iter().map(|&x| if x > 0.0 { x } else { 1.0 }).collect();
    let a = DMatrix::from_fn(n, n, |r, k| psi[(r, k)] * scale[k] / scale[r]);
    let m: Vec<f32> = (0..n).map(|r| f32_up((0..n).map(|k| a[(r, k)].abs()).fold(0.0, f64::max))).collect();
    for v in &m {
        out.extend_from_slice(&v.to_le_bytes());
    }
    for r in 0..n {
        let mr = f64::from(m[r]);
        for k in 0..n {
            let v = if mr > 0.0 { q16(a[(r, k)] / mr) } else { 0 };
            out.extend_from_slice(&v.to_le_bytes());
        }
    }
}

/// Why compact matrices could not be read.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum CompactError {
    /// A sigma or row scale that is negative or not finite.
    Scale,
    /// A fixed-point value of -32768 (outside [-1, 1]).
    OutOfRange,
    /// An inflation above the worst case of the rounding.
    Inflation,
}

/// Reads the compact matrices of an `n`-state record (`bytes` exactly [`len`]`(n)` long).
pub fn get(bytes: &[u8], n: usize) -> Result<(DMatrix<f64>, DMatrix<f64>), CompactError> {
    debug_assert_eq!(bytes.len(), len(n));
    let mut o = 0;
    let f32s = |count: usize, o: &mut usize| -> Result<Vec<f64>, CompactError> {
        let v: Vec<f64> = bytes[*o..*o + 4 * count]
            .chunks_exact(4)
            .map(|c| f64::from(f32::from_le_bytes(c.try_into().expect("4 bytes"))))
            .collect();
        *o += 4 * count;
        if v.iter().all(|x| x.is_finite() && *x >= 0.0) { Ok(v) } else { Err(CompactError::Scale) }
    };
    let i16s = |count: usize, o: &mut usize| -> Result<Vec<f64>, CompactError> {
        let v: Vec<i16> = bytes[*o..*o + 2 * count].chunks_exact(2).map(|c| i16::from_le_bytes([c[0], c[1]])).collect();
        *o += 2 * count;
        if v.contains(&i16::MIN) {
            return Err(CompactError::OutOfRange);
        }
        Ok(v.into_iter().map(|x| f64::from(x) / Q).collect())
    };
    let s = f32s(n, &mut o)?;
    let eps = f32s(1, &mut o)?[0];
    if eps > f64::from(f32_up(inflation(n))) {
        return Err(CompactError::Inflation);
    }
    let tri = i16s(n * (n + 1) / 2, &mut o)?;
    let m = f32s(n, &mut o)?;
    let a = i16s(n * n, &mut o)?;
    let mut u = DMatrix::zeros(n, n);
    let mut k = 0;
    for r in 0..n {
        for c in r..n {
            u[(r, c)] = tri[k];
            k += 1;
        }
    }
    let mut c = u.transpose() * &u;
    for i in 0..n {
        c[(i, i)] += eps;
    }
    let p = DMatrix::from_fn(n, n, |r, k| if r <= k { s[r] * c[(r, k)] * s[k] } else { s[k] * c[(k, r)] * s[r] });
    let scale: Vec<f64> = s.iter().map(|&x| if x > 0.0 { x } else { 1.0 }).collect();
    let psi = DMatrix::from_fn(n, n, |r, k| a[r * n + k] * m[r] * scale[r] / scale[k]);
    Ok((p, psi))
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A covariance with the INS's spread of scales (m^2 to 1e-10 rad^2) and strong
    /// correlations, and a Psi with large and small entries.
    fn ins_like(n: usize, seed: u64) -> (DMatrix<f64>, DMatrix<f64>) {
        let mut x = seed.wrapping_mul(0x9e37_79b9_7f4a_7c15) | 1;
        let mut rnd = move || {
            x ^= x << 13;
            x ^= x >> 7;
            x ^= x << 17;
            (x >> 11) as f64 / (1u64 << 53) as f64 * 2.0 - 1.0
        };
        let l = DMatrix::from_fn(n, n + 3, |_, _| rnd());
        let d = DMatrix::from_diagonal(&nalgebra::DVector::from_fn(n, |i, _| 10f64.powf(1.0 - 5.0 * (i % 4) as f64 / 3.0)));
        let p = &d * (&l * l.transpose()) * &d;
        let psi =
            DMatrix::from_fn(n, n, |r, c| if r == c { 1.0 + 0.01 * rnd() } else { 0.3 * rnd() * 10f64.powi((r % 3) as i32 - 1) });
        (p, psi)
    }

    fn encoded(p: &DMatrix<f64>, psi: &DMatrix<f64>) -> Vec<u8> {
        let mut out = Vec::new();
        put(&mut out, p, psi);
        out
    }

    fn roundtrip(p: &DMatrix<f64>, psi: &DMatrix<f64>) -> (DMatrix<f64>, DMatrix<f64>) {
        let mut out = Vec::new();
        put(&mut out, p, psi);
        assert_eq!(out.len(), len(p.nrows()));
        get(&out, p.nrows()).unwrap()
    }

    fn min_eig(m: &DMatrix<f64>) -> f64 {
        m.clone().symmetric_eigen().eigenvalues.min()
    }

    #[test]
    fn the_decoded_covariance_bounds_the_true_one_and_is_close() {
        let mut worst = [0.0f64; 17];
        for seed in 1..50 {
            for n in [3, 9, 15, 16] {
                let (p, psi) = ins_like(n, seed);
                let (pq, psiq) = roundtrip(&p, &psi);
                // P_q - P is positive semi-definite, in the scale of P (whitened by sigma).
                let s = DMatrix::from_diagonal(&p.diagonal().map(|v| 1.0 / v.sqrt()));
                let diff = &s * (&pq - &p) * &s;
                assert!(min_eig(&diff) >= 0.0, "n {n} seed {seed}: {}", min_eig(&diff));
                assert!(min_eig(&(&s * &pq * &s)) > 0.0);
                // And no more than the inflation plus the rounding.
                let rel = diff.abs().max();
                assert!(rel <= 2.0 * inflation(n), "n {n} seed {seed}: {rel} against {}", inflation(n));
                let eps = f64::from(f32::from_le_bytes(encoded(&p, &psi)[4 * n..4 * n + 4].try_into().unwrap()));
                worst[n] = worst[n].max(eps / inflation(n));
                // Psi to a few parts in 1e5 of its row's scale.
                let a = DMatrix::from_fn(n, n, |r, c| (psiq[(r, c)] - psi[(r, c)]) * p[(c, c)].sqrt() / p[(r, r)].sqrt());
                let arow = DMatrix::from_fn(n, n, |r, c| psi[(r, c)] * p[(c, c)].sqrt() / p[(r, r)].sqrt());
                for r in 0..n {
                    let m = arow.row(r).abs().max();
                    assert!(a.row(r).abs().max() <= m / 32767.0, "row {r}");
                }
            }
        }
        // The inflation sent is a fraction of the worst case (see the module docs).
        eprintln!("eps / worst case: n 3 {:.3}, 9 {:.3}, 15 {:.3}, 16 {:.3}", worst[3], worst[9], worst[15], worst[16]);
        assert!(worst[3] < 0.5 && worst[9] < 0.3 && worst[15] < 0.2 && worst[16] < 0.2, "{worst:?}");
    }

    #[test]
    fn singular_and_degenerate_covariances_decode_positive_semi_definite() {
        let n = 4;
        // Perfect correlation of states 0 and 1, a state with zero variance, a negative zero.
        let mut p = DMatrix::zeros(n, n);
        p[(0, 0)] = 4.0;
        p[(1, 1)] = 1.0;
        p[(0, 1)] = 2.0;
        p[(1, 0)] = 2.0;
        p[(3, 3)] = 1e-12;
        let psi = DMatrix::identity(n, n);
        let (pq, psiq) = roundtrip(&p, &psi);
        assert!(min_eig(&pq) >= -1e-18, "{pq}");
        assert_eq!(pq[(2, 2)], 0.0);
        assert!((psiq - psi).abs().max() < 1e-4);
    }

    #[test]
    fn hostile_bits_are_refused_or_give_a_positive_semi_definite_matrix() {
        let n = 3;
        let (p, psi) = ins_like(n, 7);
        let mut good = Vec::new();
        put(&mut good, &p, &psi);
        let mut neg = good.clone();
        neg[0..4].copy_from_slice(&(-1.0f32).to_le_bytes());
        assert_eq!(get(&neg, n), Err(CompactError::Scale));
        let mut nan = good.clone();
        nan[4 * n + 4 + 12 + 4..4 * n + 4 + 12 + 8].copy_from_slice(&f32::NAN.to_le_bytes());
        assert_eq!(get(&nan, n), Err(CompactError::Scale));
        let mut big = good.clone();
        big[4 * n..4 * n + 4].copy_from_slice(&(2.0 * inflation(n) as f32).to_le_bytes());
        assert_eq!(get(&big, n), Err(CompactError::Inflation));
        let mut min = good.clone();
        min[4 * n + 4..4 * n + 6].copy_from_slice(&i16::MIN.to_le_bytes());
        assert_eq!(get(&min, n), Err(CompactError::OutOfRange));
        // Any factor bits give a positive semi-definite covariance.
        let mut x = 12345u32;
        for _ in 0..200 {
            let mut b = good.clone();
            for k in 0..n * (n + 1) / 2 {
                x = x.wrapping_mul(1_103_515_245).wrapping_add(12345);
                let v = ((x >> 8) as i32 % 32767) as i16;
                b[4 * n + 4 + 2 * k..4 * n + 4 + 2 * k + 2].copy_from_slice(&v.to_le_bytes());
            }
            let (pq, _) = get(&b, n).unwrap();
            assert!(min_eig(&pq) >= -1e-9 * pq.abs().max(), "{pq}");
        }
    }
}
