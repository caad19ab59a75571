//! Matrix–vector products of the per-sample maps (the prediction error's and the free
//! run's simulations), bit for bit those of nalgebra's `gemv`, in wider registers.
//!
//! Why: after the slip map ([`crate::simulate`]) a sample of the observer's prediction is a
//! handful of small dense products (`Φx`, `33 × 33` on the paper model, the observer's
//! correction `K e`, the slip test), and a 100,000-sample identification runs ~130 of
//! these predictions. nalgebra's `gemv` is a column-by-column `axpy` compiled for the
//! baseline x86-64 (two doubles per instruction) that loads and stores `y` for every
//! column. Here the rows are blocked in AVX registers (four doubles each, sixteen rows per
//! pass) that stay there across the columns, selected at run time, so one binary runs on
//! every x86-64 and is faster where AVX exists.
//!
//! The arithmetic is nalgebra's, operation for operation: `y_i = A_i0 x_0` (or
//! `A_i0 x_0 + y_i` when accumulating), then `y_i = A_ij x_j + y_i` for `j = 1, 2, …` (or
//! `y_i − A_ij x_j`), each a rounded multiply then a rounded add — no fused multiply–add, no
//! reassociation. So the
//! results do not depend on the CPU (a chaotic friction law amplifies a last-bit change;
//! the identification's answers stay the same to the last digit on every machine). Unit
//! test: the bits against nalgebra's for all shapes up to 40 × 40, signed zeros included.

use nalgebra::{DMatrix, DVector};

/// What [`gemv`] does with `y`.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Op {
    /// `y = A x` (nalgebra's `y.gemv(1.0, A, x, 0.0)`).
    Set,
    /// `y = A x + y` (`y.gemv(1.0, A, x, 1.0)`).
    Add,
    /// `y = y − A x` (`y.gemv(-1.0, A, x, 1.0)`: `(−A_ij) x_j + y_i` is `y_i − A_ij x_j`
    /// exactly).
    Subtract,
}

/// `y = A x`, `y + A x` or `y − A x` as nalgebra's `gemv` computes them, to the bit.
///
/// # Panics
/// When the shapes do not match (`y` has `A`'s rows, `x` its columns), as nalgebra does.
pub fn gemv(y: &mut DVector<f64>, a: &DMatrix<f64>, x: &DVector<f64>, op: Op) {
    let (rows, cols) = a.shape();
    assert!(
        y.len() == rows && x.len() == cols,
        "gemv: dimensions mismatch"
    );
    #[cfg(target_arch = "x86_64")]
    if std::arch::is_x86_feature_detected!("avx") {
        // SAFETY: the CPU has AVX (checked above); the slices have the lengths the kernel
        // indexes (`rows`, `rows × cols` column-major, `cols`: asserted above).
        unsafe { gemv_avx(y.as_mut_slice(), a.as_slice(), rows, cols, x.as_slice(), op) };
        return;
    }
    match op {
        Op::Set => y.gemv(1.0, a, x, 0.0),
        Op::Add => y.gemv(1.0, a, x, 1.0),
        Op::Subtract => y.gemv(-1.0, a, x, 1.0),
    }
}

/// The AVX kernel of [`gemv`]: blocks of sixteen rows in four registers, then blocks of
/// four, then single rows, every element summed over the columns in order.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx")]
unsafe fn gemv_avx(y: &mut [f64], a: &[f64], rows: usize, cols: usize, x: &[f64], op: Op) {
    use std::arch::x86_64::{
        _mm256_add_pd, _mm256_loadu_pd, _mm256_mul_pd, _mm256_set1_pd, _mm256_storeu_pd,
        _mm256_sub_pd,
    };
    let accumulate = op != Op::Set;
    let subtract = op == Op::Subtract;
    // One column's term added to (or taken from) an accumulator; `col` points at four
    // readable doubles.
    macro_rules! term {
        ($acc:expr, $col:expr, $xv:expr) => {{
            let prod = _mm256_mul_pd(_mm256_loadu_pd($col), $xv);
            if subtract {
                _mm256_sub_pd($acc, prod)
            } else {
                _mm256_add_pd(prod, $acc)
            }
        }};
    }
    debug_assert!(y.len() == rows && x.len() == cols && a.len() == rows * cols);
    if cols == 0 {
        // nalgebra: `y = 0` (β = 0) or `y *= 1`.
        if !accumulate {
            y.fill(0.0);
        }
        return;
    }
    let (yp, ap, xp) = (y.as_mut_ptr(), a.as_ptr(), x.as_ptr());
    // The first column that is added to an accumulator (the first one initialises it when
    // not accumulating).
    let first = usize::from(!accumulate);
    let mut i = 0;
    // SAFETY (all blocks): `i + 16 ≤ rows` (or `i + 4`, `i < rows`) and `j < cols`, so
    // every offset `j·rows + i + k` is inside `a` and `i + k` inside `y`.
    unsafe {
        while i + 16 <= rows {
            let (mut s0, mut s1, mut s2, mut s3);
            if accumulate {
                s0 = _mm256_loadu_pd(yp.add(i));
                s1 = _mm256_loadu_pd(yp.add(i + 4));
                s2 = _mm256_loadu_pd(yp.add(i + 8));
                s3 = _mm256_loadu_pd(yp.add(i + 12));
            } else {
                let xv = _mm256_set1_pd(*xp);
                let c = ap.add(i);
                s0 = _mm256_mul_pd(_mm256_loadu_pd(c), xv);
                s1 = _mm256_mul_pd(_mm256_loadu_pd(c.add(4)), xv);
                s2 = _mm256_mul_pd(_mm256_loadu_pd(c.add(8)), xv);
                s3 = _mm256_mul_pd(_mm256_loadu_pd(c.add(12)), xv);
            }
            for j in first..cols {
                let xv = _mm256_set1_pd(*xp.add(j));
                let c = ap.add(j * rows + i);
                s0 = term!(s0, c, xv);
                s1 = term!(s1, c.add(4), xv);
                s2 = term!(s2, c.add(8), xv);
                s3 = term!(s3, c.add(12), xv);
            }
            _mm256_storeu_pd(yp.add(i), s0);
            _mm256_storeu_pd(yp.add(i + 4), s1);
            _mm256_storeu_pd(yp.add(i + 8), s2);
            _mm256_storeu_pd(yp.add(i + 12), s3);
            i += 16;
        }
        while i + 4 <= rows {
            let mut s = if accumulate {
                _mm256_loadu_pd(yp.add(i))
            } else {
                _mm256_mul_pd(_mm256_loadu_pd(ap.add(i)), _mm256_set1_pd(*xp))
            };
            for j in first..cols {
                let xv = _mm256_set1_pd(*xp.add(j));
                s = term!(s, ap.add(j * rows + i), xv);
            }
            _mm256_storeu_pd(yp.add(i), s);
            i += 4;
        }
        while i < rows {
            let mut s = if accumulate {
                *yp.add(i)
            } else {
                *ap.add(i) * *xp
            };
            for j in first..cols {
                if subtract {
                    s -= *ap.add(j * rows + i) * *xp.add(j);
                } else {
                    s += *ap.add(j * rows + i) * *xp.add(j);
                }
            }
            *yp.add(i) = s;
            i += 1;
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{RngExt, SeedableRng};
    use rand_chacha::ChaCha8Rng;

    /// The bits of [`gemv`] equal nalgebra's `gemv` for every shape up to 40 × 40, every
    /// [`Op`], with values spanning 40 decades, signed zeros and exact cancellations.
    #[test]
    fn gemv_equals_nalgebra_to_the_bit() {
        let mut rng = ChaCha8Rng::seed_from_u64(11);
        let value = |rng: &mut ChaCha8Rng| -> f64 {
            match rng.random_range(0..10) {
                0 => 0.0,
                1 => -0.0,
                2 => 1.0,
                _ => {
                    let e: i32 = rng.random_range(-20..20);
                    rng.random_range(-1.0..1.0) * 10f64.powi(e)
                }
            }
        };
        for rows in 0..=40 {
            for cols in 0..=40 {
                let a = DMatrix::from_fn(rows, cols, |_, _| value(&mut rng));
                let x = DVector::from_fn(cols, |_, _| value(&mut rng));
                let y0 = DVector::from_fn(rows, |_, _| value(&mut rng));
                for (op, alpha, beta) in [
                    (Op::Set, 1.0, 0.0),
                    (Op::Add, 1.0, 1.0),
                    (Op::Subtract, -1.0, 1.0),
                ] {
                    let mut want = y0.clone();
                    want.gemv(alpha, &a, &x, beta);
                    let mut got = y0.clone();
                    gemv(&mut got, &a, &x, op);
                    for (g, w) in got.iter().zip(&want) {
                        assert_eq!(
                            g.to_bits(),
                            w.to_bits(),
                            "{rows}×{cols}, {op:?}: {g:e} vs {w:e}"
                        );
                    }
                }
            }
        }
    }
}
