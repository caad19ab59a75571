//! Matrix–vector products of the per-sample maps (the prediction error's and the free
//! run's simulations) and LU solves of the Riccati doubling, bit for bit those of
//! nalgebra's `gemv` and `LU::solve`, in wider registers.
//!
//! Why: after the slip map ([`crate::simulate`]) a sample of the observer's prediction is a
//! handful of small dense products (`Φx`, `33 × 33` on the paper model, the observer's
//! correction `K e`, the slip test), and a 100,000-sample identification runs ~130 of
//! these predictions. nalgebra's `gemv` is a column-by-column `axpy` compiled for the
//! baseline x86-64 (two doubles per instruction) that loads and stores `y` for every
//! column. Here the rows are blocked in AVX registers (four doubles each, up to thirty-two
//! rows per pass) that stay there across the columns, selected at run time, so one binary
//! runs on every x86-64 and is faster where AVX exists.
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
    gemv_slices(y.as_mut_slice(), a, x.as_slice(), op);
}

/// [`gemv`] on plain slices (`y` has `A`'s rows, `x` its columns): the per-sample maps keep
/// their inputs side by side in one work vector and multiply a part of it.
///
/// # Panics
/// When the shapes do not match, as nalgebra does.
pub fn gemv_slices(y: &mut [f64], a: &DMatrix<f64>, x: &[f64], op: Op) {
    let (rows, cols) = a.shape();
    assert!(
        y.len() == rows && x.len() == cols,
        "gemv: dimensions mismatch"
    );
    if rows == 1 && cols == 1 {
        // One connection's force solve (a `1 × 1` product per Newton iteration, millions per
        // identification): the one product and add, without the kernel's dispatch.
        let p = a[(0, 0)] * x[0];
        y[0] = match op {
            Op::Set => p,
            Op::Add => p + y[0],
            Op::Subtract => y[0] - p,
        };
        return;
    }
    #[cfg(target_arch = "x86_64")]
    if std::arch::is_x86_feature_detected!("avx") {
        // SAFETY: the CPU has AVX (checked above); the slices have the lengths the kernel
        // indexes (`rows`, `rows × cols` column-major, `cols`: asserted above).
        unsafe { gemv_avx(y, a.as_slice(), rows, cols, x, op) };
        return;
    }
    let mut y = nalgebra::DVectorViewMut::from_slice(y, rows);
    let x = nalgebra::DVectorView::from_slice(x, cols);
    match op {
        Op::Set => y.gemv(1.0, a, &x, 0.0),
        Op::Add => y.gemv(1.0, a, &x, 1.0),
        Op::Subtract => y.gemv(-1.0, a, &x, 1.0),
    }
}

/// `y_i = a x_i + y_i` for every `i` (equal lengths): each a rounded multiply then a
/// rounded add, element by element, so the bits do not depend on the register width (no
/// reduction, no fused multiply–add). Why: the composed sub-steps spread each sub-step's
/// connection force over the later sub-steps' free predictions with it (an `O(L²)` history
/// per sample, a chain of dependent adds when it was summed as dot products: 46 % of a
/// Coulomb identification at 128 sub-steps).
///
/// # Panics
/// When the lengths differ.
#[inline]
pub fn axpy(y: &mut [f64], a: f64, x: &[f64]) {
    assert_eq!(y.len(), x.len(), "axpy: equal lengths");
    #[cfg(target_arch = "x86_64")]
    if std::arch::is_x86_feature_detected!("avx") {
        // SAFETY: the CPU has AVX (checked above).
        unsafe { axpy_avx(y, a, x) };
        return;
    }
    axpy_plain(y, a, x);
}

#[inline(always)]
fn axpy_plain(y: &mut [f64], a: f64, x: &[f64]) {
    for (yi, xi) in y.iter_mut().zip(x) {
        *yi += a * xi;
    }
}

/// [`axpy`] compiled for AVX (four doubles per instruction): the same loop, the same
/// operations per element.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx")]
unsafe fn axpy_avx(y: &mut [f64], a: f64, x: &[f64]) {
    axpy_plain(y, a, x);
}

/// Whether every entry is finite (neither infinite nor NaN). Why not
/// `iter().all(f64::is_finite)`: that branches per entry; this reads every exponent and
/// combines them without a branch (vectorised), for the per-sample divergence checks.
pub fn all_finite(v: &[f64]) -> bool {
    const EXPONENT: u64 = 0x7ff0_0000_0000_0000;
    v.iter().fold(0u64, |bad, x| {
        bad | u64::from(x.to_bits() & EXPONENT == EXPONENT)
    }) == 0
}

/// The largest magnitude of the entries, nalgebra's `amax` to the bit (0 for none), in four
/// independent running maxima: its one chain of compares waits on the last for every entry
/// (the Riccati doubling's convergence test and the slip test's scales). nalgebra's fold
/// (`if a > |e| { a } else { |e| }`) lets a NaN entry replace the running value and the next
/// entry replace a NaN, so with a NaN present the answer depends on the order: then the fold
/// is run as nalgebra runs it.
pub fn amax(v: &[f64]) -> f64 {
    match v {
        [] => return 0.0,
        // One connection's force solve: `larger(0, |x|)` is `|x|` (a NaN's too).
        [x] => return x.abs(),
        _ => {}
    }
    let mut lanes = [0.0f64; 4];
    let mut nan = false;
    let mut chunks = v.chunks_exact(4);
    for c in &mut chunks {
        for (m, x) in lanes.iter_mut().zip(c) {
            nan |= x.is_nan();
            *m = larger(*m, x.abs());
        }
    }
    for x in chunks.remainder() {
        nan |= x.is_nan();
        lanes[0] = larger(lanes[0], x.abs());
    }
    if nan {
        return nalgebra_amax(v.iter().map(|x| x.abs()));
    }
    lanes.iter().fold(0.0, |a, b| larger(a, *b))
}

/// The larger of two numbers that are not NaN (one `max` instruction; `f64::max` adds the
/// NaN handling the callers do once for the whole slice).
#[inline(always)]
fn larger(a: f64, b: f64) -> f64 {
    if b > a { b } else { a }
}

/// nalgebra's `amax` fold over magnitudes, in order (non-empty): `if a > e { a } else { e }`.
fn nalgebra_amax(mut magnitudes: impl Iterator<Item = f64>) -> f64 {
    let first = magnitudes.next().unwrap_or(0.0);
    magnitudes.fold(first, |a, e| if a > e { a } else { e })
}

/// `a · x` (equal lengths), bit for bit nalgebra's `dot` of two dynamic vectors (eight
/// running sums over blocks of eight, combined as `(s₀ + s₄) + (s₁ + s₅) + …`, then the
/// remaining products in order), and so `y.gemv_tr(1.0, A, x, 0.0)` column by column,
/// without its views and checks (the Kalman step's connection deformations).
#[inline]
pub fn dot(a: &[f64], x: &[f64]) -> f64 {
    assert_eq!(a.len(), x.len(), "dot: equal lengths");
    let mut acc = [0.0f64; 8];
    let (mut ca, mut cx) = (a.chunks_exact(8), x.chunks_exact(8));
    for (p, q) in (&mut ca).zip(&mut cx) {
        for ((s, y), z) in acc.iter_mut().zip(p).zip(q) {
            *s += y * z;
        }
    }
    let mut res = 0.0;
    res += acc[0] + acc[4];
    res += acc[1] + acc[5];
    res += acc[2] + acc[6];
    res += acc[3] + acc[7];
    for (y, z) in ca.remainder().iter().zip(cx.remainder()) {
        res += y * z;
    }
    res
}

/// `A B`, bit for bit nalgebra's `&a * &b`, faster where nalgebra is slow. nalgebra hands a
/// product to `matrixmultiply` when both factors' rows and columns exceed 5 (then so does
/// this); otherwise it makes it column by column with its `gemv` (one `axpy` per column of
/// `A`, generic code), which [`gemv`] reproduces to the bit in wider registers. Why: the
/// per-record sample maps are built from products with a thin factor (`Tʲ Γ` with one or two
/// input columns, a friction's `1 × 3n` row through `T`), `L` of them per map, one map per
/// prediction run (2 % of a replay's CPU in nalgebra's per-column loop).
///
/// # Panics
/// When the inner dimensions differ, as nalgebra does.
pub fn product(a: &DMatrix<f64>, b: &DMatrix<f64>) -> DMatrix<f64> {
    let (rows, inner) = a.shape();
    let cols = b.ncols();
    #[cfg(target_arch = "x86_64")]
    if inner == b.nrows() && fused_path(rows, inner, cols) {
        // Written element by element by the kernel: not zeroed first (the zeroing and its
        // allocation were 2.5 % of a replay's instructions, callgrind, forty-first session).
        let mut out = Vec::<f64>::with_capacity(rows * cols);
        // SAFETY: `fused_path` accepted the shapes; the kernel writes every one of the
        // `rows × cols` elements of `out`'s capacity before the length is set.
        unsafe {
            product_fused_of(a, b, out.as_mut_ptr());
            out.set_len(rows * cols);
        }
        return DMatrix::from_vec(rows, cols, out);
    }
    let mut out = DMatrix::zeros(rows, cols);
    product_into(&mut out, a, b);
    out
}

/// Whether [`product_into`] takes the fused kernel for these dimensions.
#[cfg(target_arch = "x86_64")]
fn fused_path(rows: usize, inner: usize, cols: usize) -> bool {
    const SMALL_DIM: usize = 5;
    rows > SMALL_DIM
        && cols > SMALL_DIM
        && inner > SMALL_DIM
        && inner <= DGEMM_KC
        && fused_dgemm_kernel()
}

/// [`product`] written into `out` (resized to `A`'s rows × `B`'s columns when it has another
/// shape): the same bits, without allocating when `out` already has the shape (a product
/// per sample, as the maximum-likelihood free response's `W Φ`).
///
/// # Panics
/// When the inner dimensions differ, as nalgebra does.
pub fn product_into(out: &mut DMatrix<f64>, a: &DMatrix<f64>, b: &DMatrix<f64>) {
    let (rows, inner) = a.shape();
    assert_eq!(inner, b.nrows(), "product: dimensions mismatch");
    let cols = b.ncols();
    if out.shape() != (rows, cols) {
        *out = DMatrix::zeros(rows, cols);
    }
    #[cfg(target_arch = "x86_64")]
    if fused_path(rows, inner, cols) {
        // SAFETY: `fused_path` accepted the shapes; `out` holds `rows × cols` elements.
        unsafe { product_fused_of(a, b, out.as_mut_slice().as_mut_ptr()) };
        return;
    }
    const SMALL_DIM: usize = 5;
    if rows > SMALL_DIM && cols > SMALL_DIM && inner > SMALL_DIM {
        *out = a * b;
        return;
    }
    for j in 0..cols {
        let start = j * inner;
        gemv_slices(
            &mut out.as_mut_slice()[j * rows..(j + 1) * rows],
            a,
            &b.as_slice()[start..start + inner],
            Op::Set,
        );
    }
}

/// [`product_fused`] of two matrices into `out`.
///
/// # Safety
/// [`fused_path`] must accept the shapes, and `out` point to `a.nrows() × b.ncols()`
/// writable elements (only written).
#[cfg(target_arch = "x86_64")]
unsafe fn product_fused_of(a: &DMatrix<f64>, b: &DMatrix<f64>, out: *mut f64) {
    // SAFETY: the caller's (the features were checked by `fused_path`).
    unsafe {
        product_fused(
            a.nrows(),
            a.ncols(),
            b.ncols(),
            a.as_slice(),
            b.as_slice(),
            out,
        )
    }
}

/// matrixmultiply's block of the inner dimension (`D_KC`): a longer product is summed in
/// blocks whose partial results are added, not one chain.
#[cfg(target_arch = "x86_64")]
const DGEMM_KC: usize = 256;

/// Whether matrixmultiply (nalgebra's product of matrices with every dimension above 5)
/// runs one of its fused kernels here: AVX-512, or FMA with AVX2 — the kernels it picks
/// first. Both compute an element as one chain of fused multiply-adds over the inner index
/// in order, from zero, and store it times α = 1 (exact).
#[cfg(target_arch = "x86_64")]
fn fused_dgemm_kernel() -> bool {
    static FUSED: std::sync::OnceLock<bool> = std::sync::OnceLock::new();
    *FUSED.get_or_init(|| {
        std::arch::is_x86_feature_detected!("avx512f")
            || (std::arch::is_x86_feature_detected!("fma")
                && std::arch::is_x86_feature_detected!("avx2"))
    })
}

/// `C = A B` (column-major, `A` rows × inner, `B` inner × cols, `inner ≤` [`DGEMM_KC`]) as
/// matrixmultiply's fused kernels compute it (see [`fused_dgemm_kernel`]): every element
/// the chain `c ← fma(a_ip, b_pj, c)` for `p` in order from `c = 0`. Why: at the Riccati
/// doubling's 23 × 23 the dgemm's packing of both factors into its panels and its masked
/// edge tiles cost as much as the arithmetic (7.5 % of a 2,000-sample identification's CPU
/// in matrixmultiply); here `A`'s contiguous columns are read in place, in blocks of up to
/// 16 rows (four registers, the last one masked) for two columns of `C` at a time: eight
/// independent chains, so the fused adds' latency is hidden.
///
/// # Safety
/// The CPU must have FMA and AVX2 ([`fused_dgemm_kernel`]); the slices must hold the
/// stated shapes and `cp` point to `rows × cols` writable elements (only written, so they
/// may be uninitialised).
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma")]
unsafe fn product_fused(
    rows: usize,
    inner: usize,
    cols: usize,
    a: &[f64],
    b: &[f64],
    cp: *mut f64,
) {
    assert!(a.len() >= rows * inner && b.len() >= inner * cols);
    let (ap, bp) = (a.as_ptr(), b.as_ptr());
    let mut i0 = 0;
    while i0 < rows {
        let len = (rows - i0).min(16);
        // SAFETY: rows i0..i0+len lie in A's and C's columns (asserted above).
        unsafe {
            match (len.div_ceil(4), !len.is_multiple_of(4)) {
                (1, false) => fused_rows::<1, false>(rows, inner, cols, ap, bp, cp, i0, len),
                (1, true) => fused_rows::<1, true>(rows, inner, cols, ap, bp, cp, i0, len),
                (2, false) => fused_rows::<2, false>(rows, inner, cols, ap, bp, cp, i0, len),
                (2, true) => fused_rows::<2, true>(rows, inner, cols, ap, bp, cp, i0, len),
                (3, false) => fused_rows::<3, false>(rows, inner, cols, ap, bp, cp, i0, len),
                (3, true) => fused_rows::<3, true>(rows, inner, cols, ap, bp, cp, i0, len),
                (4, false) => fused_rows::<4, false>(rows, inner, cols, ap, bp, cp, i0, len),
                _ => fused_rows::<4, true>(rows, inner, cols, ap, bp, cp, i0, len),
            }
        }
        i0 += len;
    }
}

/// Rows `i0 .. i0 + len` of [`product_fused`] (`len ≤ 16`): `NV` registers of four rows, the
/// last one masked when `MASKED` (`len` not a multiple of four), for two columns of `C` at a
/// time (then the last one alone when `cols` is odd). The register count and the mask are
/// constants so that the inner loop is unrolled: with them read at run time the kernel
/// spent ~2.6 instructions per multiply-add on loop control (callgrind, forty-first
/// session). Every element is the same chain as before, bit for bit.
///
/// # Safety
/// As [`product_fused`]; `len ≤ 16`, `NV = ⌈len / 4⌉`, `MASKED = (len % 4 ≠ 0)`.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma")]
#[allow(clippy::too_many_arguments, clippy::needless_range_loop)]
unsafe fn fused_rows<const NV: usize, const MASKED: bool>(
    rows: usize,
    inner: usize,
    cols: usize,
    ap: *const f64,
    bp: *const f64,
    cp: *mut f64,
    i0: usize,
    len: usize,
) {
    use std::arch::x86_64::*;
    let tail = len % 4;
    // Lanes of the last, partial register (sign bit set: loaded and stored).
    let lane = |k: usize| if k < tail { -1i64 } else { 0 };
    let mask = _mm256_setr_epi64x(lane(0), lane(1), lane(2), lane(3));
    // SAFETY (every block below): rows i0..i0+len of column p of A and of columns j, j+1
    // of C, elements (p, j), (p, j+1) of B, all within the asserted shapes.
    // Macros, not closures: the intrinsics need this function's target features inlined.
    macro_rules! load {
        ($col:expr, $v:expr) => {
            unsafe {
                if MASKED && $v == NV - 1 {
                    _mm256_maskload_pd($col.add(4 * $v), mask)
                } else {
                    _mm256_loadu_pd($col.add(4 * $v))
                }
            }
        };
    }
    macro_rules! store {
        ($out:expr, $v:expr, $x:expr) => {
            unsafe {
                if MASKED && $v == NV - 1 {
                    _mm256_maskstore_pd($out.add(4 * $v), mask, $x);
                } else {
                    _mm256_storeu_pd($out.add(4 * $v), $x);
                }
            }
        };
    }
    let mut j = 0;
    while j + 1 < cols {
        let mut acc0 = [_mm256_setzero_pd(); NV];
        let mut acc1 = [_mm256_setzero_pd(); NV];
        let (b0p, b1p) = unsafe { (bp.add(j * inner), bp.add((j + 1) * inner)) };
        for p in 0..inner {
            let col = unsafe { ap.add(p * rows + i0) };
            let b0 = _mm256_set1_pd(unsafe { *b0p.add(p) });
            let b1 = _mm256_set1_pd(unsafe { *b1p.add(p) });
            for v in 0..NV {
                let x = load!(col, v);
                acc0[v] = _mm256_fmadd_pd(x, b0, acc0[v]);
                acc1[v] = _mm256_fmadd_pd(x, b1, acc1[v]);
            }
        }
        let (out0, out1) = unsafe { (cp.add(j * rows + i0), cp.add((j + 1) * rows + i0)) };
        for v in 0..NV {
            store!(out0, v, acc0[v]);
            store!(out1, v, acc1[v]);
        }
        j += 2;
    }
    if j < cols {
        let mut acc0 = [_mm256_setzero_pd(); NV];
        let b0p = unsafe { bp.add(j * inner) };
        for p in 0..inner {
            let col = unsafe { ap.add(p * rows + i0) };
            let b0 = _mm256_set1_pd(unsafe { *b0p.add(p) });
            for v in 0..NV {
                acc0[v] = _mm256_fmadd_pd(load!(col, v), b0, acc0[v]);
            }
        }
        let out0 = unsafe { cp.add(j * rows + i0) };
        for v in 0..NV {
            store!(out0, v, acc0[v]);
        }
    }
}

/// The blocks side by side, `[A₀ A₁ …]` (equal rows). Why: `[A₀ A₁] (x₀; x₁)` through
/// [`gemv`] is, element for element, `A₀ x₀` followed by `+ A₁ x₁` — the same rounded
/// products added in the same order as two calls (`Op::Set` then `Op::Add`), so a map of
/// several inputs costs one call and one pass over `y`, bit for bit the same.
pub fn side_by_side(blocks: &[&DMatrix<f64>]) -> DMatrix<f64> {
    let rows = blocks.first().map_or(0, |b| b.nrows());
    let cols = blocks.iter().map(|b| b.ncols()).sum();
    let mut out = DMatrix::zeros(rows, cols);
    let mut at = 0;
    for b in blocks {
        debug_assert_eq!(b.nrows(), rows);
        out.columns_mut(at, b.ncols()).copy_from(b);
        at += b.ncols();
    }
    out
}

/// The AVX kernel of [`gemv`]: rows in blocks of 32 (eight registers of four) while more
/// than 35 are left, the rest in one last block (up to eight registers and three single
/// rows), every element summed over the columns in order.
///
/// Why blocks this wide: an element's sum is a chain of dependent adds (four cycles each),
/// so a block's columns go no faster than one per add latency whatever its width; eight
/// independent registers fill both add ports. With four (sixteen rows, as before) the
/// paper model's `33 × 33` product took two such passes and a third for its last row; until
/// the twenty-ninth session that row still took a second pass of its own (a scalar chain of
/// one add latency per column), now it rides along in the first. Same operations per
/// element, in the same order: the bits do not change.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx")]
unsafe fn gemv_avx(y: &mut [f64], a: &[f64], rows: usize, cols: usize, x: &[f64], op: Op) {
    debug_assert!(y.len() == rows && x.len() == cols && a.len() == rows * cols);
    if cols == 0 {
        // nalgebra: `y = 0` (β = 0) or `y *= 1`.
        if op == Op::Set {
            y.fill(0.0);
        }
        return;
    }
    let (yp, ap, xp) = (y.as_mut_ptr(), a.as_ptr(), x.as_ptr());
    let mut i = 0;
    // SAFETY (every block): rows `i .. i + 4V + S` are `≤ rows` and columns `< cols`, so every
    // offset `j·rows + i + k` is inside `a`, `i + k` inside `y` and `j` inside `x`.
    unsafe {
        // Whole blocks of 32 while more than 35 rows are left; the last pass takes the rest
        // (up to 35: eight registers and three single rows — the paper model's 33 and 34
        // rows in one pass, not a second pass for their last rows' scalar chains).
        while rows - i > 35 {
            gemv_block::<8, 0>(yp, ap, xp, rows, cols, i, op);
            i += 32;
        }
        let left = rows - i;
        macro_rules! dispatch {
            ($($v:literal),*) => {
                match (left / 4, left % 4) {
                    $(
                        ($v, 0) => gemv_block::<$v, 0>(yp, ap, xp, rows, cols, i, op),
                        ($v, 1) => gemv_block::<$v, 1>(yp, ap, xp, rows, cols, i, op),
                        ($v, 2) => gemv_block::<$v, 2>(yp, ap, xp, rows, cols, i, op),
                        ($v, 3) => gemv_block::<$v, 3>(yp, ap, xp, rows, cols, i, op),
                    )*
                    _ => unreachable!("at most 35 rows are left"),
                }
            };
        }
        dispatch!(0, 1, 2, 3, 4, 5, 6, 7, 8);
    }
}

/// Rows `i .. i + 4V + S` of [`gemv_avx`]: `V` registers of four rows and `S` single rows,
/// held across the columns. Per element: `A_i0 x_0` (or `A_i0 x_0 + y_i`, `y_i − A_i0 x_0`
/// when accumulating), then `± A_ij x_j` added for `j = 1, 2, …`, each a rounded multiply then
/// a rounded add or subtract.
// Indices into the accumulator arrays read better than iterators here.
#[allow(clippy::needless_range_loop)]
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx")]
#[inline]
unsafe fn gemv_block<const V: usize, const S: usize>(
    yp: *mut f64,
    ap: *const f64,
    xp: *const f64,
    rows: usize,
    cols: usize,
    i: usize,
    op: Op,
) {
    use std::arch::x86_64::{
        __m256d, _mm256_add_pd, _mm256_loadu_pd, _mm256_mul_pd, _mm256_set1_pd, _mm256_setzero_pd,
        _mm256_storeu_pd, _mm256_sub_pd,
    };
    let accumulate = op != Op::Set;
    let subtract = op == Op::Subtract;
    // SAFETY: the caller's rows `i .. i + 4V + S` are `≤ rows`, `cols ≥ 1` (see `gemv_avx`).
    unsafe {
        let mut acc: [__m256d; V] = [_mm256_setzero_pd(); V];
        let mut one: [f64; S] = [0.0; S];
        let s0 = i + 4 * V;
        // The first column that is added to an accumulator (the first one initialises it
        // when not accumulating).
        let first = usize::from(!accumulate);
        if accumulate {
            for k in 0..V {
                acc[k] = _mm256_loadu_pd(yp.add(i + 4 * k));
            }
            for k in 0..S {
                one[k] = *yp.add(s0 + k);
            }
        } else {
            let xv = _mm256_set1_pd(*xp);
            for k in 0..V {
                acc[k] = _mm256_mul_pd(_mm256_loadu_pd(ap.add(i + 4 * k)), xv);
            }
            for k in 0..S {
                one[k] = *ap.add(s0 + k) * *xp;
            }
        }
        for j in first..cols {
            let xj = *xp.add(j);
            let xv = _mm256_set1_pd(xj);
            let c = ap.add(j * rows + i);
            for k in 0..V {
                let prod = _mm256_mul_pd(_mm256_loadu_pd(c.add(4 * k)), xv);
                acc[k] = if subtract {
                    _mm256_sub_pd(acc[k], prod)
                } else {
                    _mm256_add_pd(prod, acc[k])
                };
            }
            for k in 0..S {
                let prod = *c.add(4 * V + k) * xj;
                if subtract {
                    one[k] -= prod;
                } else {
                    one[k] += prod;
                }
            }
        }
        for k in 0..V {
            _mm256_storeu_pd(yp.add(i + 4 * k), acc[k]);
        }
        for k in 0..S {
            *yp.add(s0 + k) = one[k];
        }
    }
}

/// An LU factorisation with partial pivoting and its solves, bit for bit nalgebra's
/// `a.lu()` and `lu.solve(b)`, without their per-element overhead.
///
/// Why: the Riccati doubling of the Kalman filter and of the prediction error's observer
/// factors `I + G H` and solves `(I + G H) X = A` twice per step on `22 × 22` to `34 × 34`
/// matrices, about a thousand times per identification; nalgebra's triangular solves make
/// an `axpy` call (views, shape checks, a generic loop of two doubles per instruction) for
/// every element of the diagonal and every column, one column at a time, and were a fifth
/// of the shipped replay's CPU time. Here, where the CPU has AVX, four columns are solved
/// together and four rows' sums stay in registers ([`substitute_avx`]): 21 → 6.5 µs for a
/// `34 × 34` solve; elsewhere plain loops over slices. The factorisation is done here too
/// ([`Self::factor`]): nalgebra's `LU::new` and the unpacking of its `L` and `U` were
/// another 4 % of a replay's instructions (callgrind, forty-first session).
///
/// The arithmetic is nalgebra's, operation for operation (`LU::new`: the first largest
/// magnitude of the column as pivot, a zero pivot skipped, the multipliers times the
/// pivot's reciprocal, each update `a_rk + (−a_ik)·l_ri`; `LU::solve_mut`: the row
/// swaps in order, then forward substitution with the unit lower factor, then back
/// substitution dividing by `U`'s diagonal; each update `b_r = b_r − c·L_ri` a rounded
/// multiply then a rounded subtract, in the same order of `i`), so the answers do not
/// change by a bit. Unit test: the bits against nalgebra for every size up to 40.
pub struct LuSolver {
    /// `L` (strictly below the diagonal, unit diagonal implied) and `U` packed, column-major.
    packed: DMatrix<f64>,
    /// Its transpose (`L` and `U` row by row: the AVX kernel's order of reads).
    packed_t: DMatrix<f64>,
    /// The row swaps `(i, pivot)` in the order they were made.
    swaps: Vec<(usize, usize)>,
    singular: bool,
}

impl LuSolver {
    /// Factor the square matrix `a` (nalgebra's `a.lu()`, bit for bit).
    ///
    /// # Panics
    /// When `a` is not square.
    pub fn factor(mut a: DMatrix<f64>) -> Self {
        let n = a.nrows();
        assert!(a.is_square(), "LU: a square matrix");
        let m = a.as_mut_slice();
        let mut swaps = Vec::new();
        for i in 0..n {
            let column = &m[i * n..(i + 1) * n];
            let mut pivot = i;
            let mut largest = column[i].abs();
            for (r, v) in column.iter().enumerate().skip(i + 1) {
                // `>`: the first of equal magnitudes, and never a NaN (as `icamax`).
                if v.abs() > largest {
                    largest = v.abs();
                    pivot = r;
                }
            }
            let diag = column[pivot];
            if diag == 0.0 {
                // No non-zero entry on this column: nalgebra goes on to the next.
                continue;
            }
            if pivot != i {
                swaps.push((i, pivot));
                for k in 0..n {
                    m.swap(k * n + i, k * n + pivot);
                }
            }
            let inv_diag = 1.0 / diag;
            for v in &mut m[i * n + i + 1..(i + 1) * n] {
                *v *= inv_diag;
            }
            let (left, right) = m.split_at_mut((i + 1) * n);
            let coeffs = &left[i * n + i + 1..(i + 1) * n];
            for col in right.chunks_exact_mut(n) {
                let p = -col[i];
                for (y, x) in col[i + 1..].iter_mut().zip(coeffs) {
                    // nalgebra's `axpy`: `a·x·1 + 1·y` with `a = −pivot_row[k]` (IEEE
                    // addition commutes, so `y + a·x` is the same bits).
                    *y += p * *x;
                }
            }
        }
        // nalgebra stops (and `solve` returns `None`) at an exactly zero pivot.
        let singular = (0..n).any(|i| a[(i, i)] == 0.0);
        Self {
            packed_t: transposed(&a),
            packed: a,
            swaps,
            singular,
        }
    }

    /// `A⁻¹ B`; `None` when a pivot of `U` is exactly zero (as `lu.solve`).
    ///
    /// # Panics
    /// When `B` has not `A`'s rows, as nalgebra does.
    pub fn solve(&self, b: &DMatrix<f64>) -> Option<DMatrix<f64>> {
        let n = self.packed.nrows();
        assert!(b.nrows() == n, "LU solve: dimensions mismatch");
        if self.singular {
            return None;
        }
        let mut x = b.clone();
        if n == 0 {
            return Some(x);
        }
        for &(i, pivot) in &self.swaps {
            x.swap_rows(i, pivot);
        }
        #[cfg(target_arch = "x86_64")]
        if std::arch::is_x86_feature_detected!("avx") {
            // SAFETY: the CPU has AVX (checked above); the kernel only indexes slices.
            unsafe {
                substitute_avx(
                    self.packed_t.as_slice(),
                    self.packed_t.as_slice(),
                    n,
                    x.as_mut_slice(),
                )
            };
            return Some(x);
        }
        substitute(
            self.packed.as_slice(),
            self.packed.as_slice(),
            n,
            x.as_mut_slice(),
        );
        Some(x)
    }
}

/// `Aᵀ` (a plain loop: nalgebra's `transpose` indexes element by element).
pub fn transposed(a: &DMatrix<f64>) -> DMatrix<f64> {
    let (rows, cols) = a.shape();
    let src = a.as_slice();
    if src.is_empty() {
        return DMatrix::zeros(cols, rows);
    }
    // Column `i` of the transpose is row `i` of `A`: every `rows`-th element from `i`.
    let mut t = Vec::with_capacity(src.len());
    for i in 0..rows {
        t.extend(src[i..].iter().step_by(rows));
    }
    DMatrix::from_vec(cols, rows, t)
}

/// `(A + Aᵀ)/2` for a square `A`, bit for bit nalgebra's `(&a + a.transpose()) * 0.5`
/// (each element `(a_ij + a_ji) · 0.5`) without its two temporaries.
pub fn symmetrized(a: &DMatrix<f64>) -> DMatrix<f64> {
    let n = a.nrows();
    assert!(a.is_square(), "symmetrized: a square matrix");
    let src = a.as_slice();
    if n == 0 {
        return DMatrix::zeros(0, 0);
    }
    let mut out = Vec::with_capacity(src.len());
    for (j, column) in src.chunks_exact(n).enumerate() {
        let row = src[j..].iter().step_by(n);
        out.extend(
            column
                .iter()
                .zip(row)
                .map(|(a_ij, a_ji)| (a_ij + a_ji) * 0.5),
        );
    }
    DMatrix::from_vec(n, n, out)
}

/// [`substitute`] in AVX registers: [`LANES`] columns solved together (their elements of
/// one row side by side in one register), and each row's updates summed in a register, four
/// rows at a time, in nalgebra's order (row `r` takes `L_ri x_i` for `i = 0, 1, …` then,
/// backwards, `U_ri x_i` for `i = n−1, n−2, …` and the division by `U_rr`). Why: nalgebra
/// solves one column at a time and stores every partial sum, ~1.5 GFLOP/s. `lt`, `ut` are
/// `L`, `U` row-major. The last group of columns is padded with zeros, whose lanes are
/// dropped.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx")]
unsafe fn substitute_avx(lt: &[f64], ut: &[f64], n: usize, x: &mut [f64]) {
    use std::arch::x86_64::{
        __m256d, _mm256_div_pd, _mm256_loadu_pd, _mm256_mul_pd, _mm256_set1_pd, _mm256_storeu_pd,
        _mm256_sub_pd,
    };
    /// Rows `r0..r0+K` of the forward (`back == false`) or back substitution: their sums
    /// over the rows already solved (`done`), then among themselves.
    // The row index `j` also offsets the pointers: ranges read better than iterators.
    #[allow(clippy::needless_range_loop)]
    #[inline(always)]
    unsafe fn rows<const K: usize>(t: *mut f64, m: *const f64, n: usize, r0: usize, back: bool) {
        const W: usize = LANES;
        // SAFETY: the caller's rows `r0..r0+K` and the solved ones are `< n`, so every
        // offset is inside `t` (`W·n`) or `m` (`n²`).
        unsafe {
            let mut acc: [__m256d; K] = [_mm256_set1_pd(0.0); K];
            for j in 0..K {
                acc[j] = _mm256_loadu_pd(t.add(W * (r0 + j)));
            }
            if back {
                for i in (r0 + K..n).rev() {
                    let xi = _mm256_loadu_pd(t.add(W * i));
                    for j in 0..K {
                        let a = _mm256_set1_pd(*m.add((r0 + j) * n + i));
                        acc[j] = _mm256_sub_pd(acc[j], _mm256_mul_pd(xi, a));
                    }
                }
                for jj in (0..K).rev() {
                    let d = _mm256_set1_pd(*m.add((r0 + jj) * n + r0 + jj));
                    acc[jj] = _mm256_div_pd(acc[jj], d);
                    for j in 0..jj {
                        let a = _mm256_set1_pd(*m.add((r0 + j) * n + r0 + jj));
                        acc[j] = _mm256_sub_pd(acc[j], _mm256_mul_pd(acc[jj], a));
                    }
                }
            } else {
                for i in 0..r0 {
                    let xi = _mm256_loadu_pd(t.add(W * i));
                    for j in 0..K {
                        let a = _mm256_set1_pd(*m.add((r0 + j) * n + i));
                        acc[j] = _mm256_sub_pd(acc[j], _mm256_mul_pd(xi, a));
                    }
                }
                for ii in 0..K {
                    for j in ii + 1..K {
                        let a = _mm256_set1_pd(*m.add((r0 + j) * n + r0 + ii));
                        acc[j] = _mm256_sub_pd(acc[j], _mm256_mul_pd(acc[ii], a));
                    }
                }
            }
            for j in 0..K {
                _mm256_storeu_pd(t.add(W * (r0 + j)), acc[j]);
            }
        }
    }
    debug_assert!(lt.len() == n * n && ut.len() == n * n && x.len().is_multiple_of(n));
    let cols = x.len() / n;
    let mut t = vec![0.0f64; LANES * n];
    let full = n / 4 * 4;
    for first in (0..cols).step_by(LANES) {
        let width = LANES.min(cols - first);
        for r in 0..n {
            for w in 0..LANES {
                t[LANES * r + w] = if w < width {
                    x[(first + w) * n + r]
                } else {
                    0.0
                };
            }
        }
        let tp = t.as_mut_ptr();
        // SAFETY: every block's rows are `< n` (blocks of four up to `full`, then single rows).
        unsafe {
            for r0 in (0..full).step_by(4) {
                rows::<4>(tp, lt.as_ptr(), n, r0, false);
            }
            for r0 in full..n {
                rows::<1>(tp, lt.as_ptr(), n, r0, false);
            }
            for r0 in (full..n).rev() {
                rows::<1>(tp, ut.as_ptr(), n, r0, true);
            }
            for r0 in (0..full).step_by(4).rev() {
                rows::<4>(tp, ut.as_ptr(), n, r0, true);
            }
        }
        for r in 0..n {
            for w in 0..width {
                x[(first + w) * n + r] = t[LANES * r + w];
            }
        }
    }
}

/// Columns [`substitute_avx`] solves together (one AVX register).
#[cfg(target_arch = "x86_64")]
const LANES: usize = 4;

/// Forward then back substitution of every column of `x` (`n` rows, column-major) with the
/// unit lower `l` and the upper `u` (`n × n`, column-major): nalgebra's loops.
fn substitute(l: &[f64], u: &[f64], n: usize, x: &mut [f64]) {
    for col in x.chunks_exact_mut(n) {
        for i in 0..n - 1 {
            let coeff = col[i];
            let below = &l[i * n + i + 1..(i + 1) * n];
            for (y, a) in col[i + 1..].iter_mut().zip(below) {
                *y -= coeff * a;
            }
        }
        for i in (0..n).rev() {
            let coeff = col[i] / u[i * n + i];
            col[i] = coeff;
            let above = &u[i * n..i * n + i];
            for (y, a) in col[..i].iter_mut().zip(above) {
                *y -= coeff * a;
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{RngExt, SeedableRng};
    use rand_chacha::ChaCha8Rng;

    /// The bits of [`gemv`] equal nalgebra's `gemv` for every shape up to 40 × 40 and taller
    /// ones (several 32-row blocks), every [`Op`], with values spanning 40 decades, signed
    /// zeros and exact cancellations.
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
        for rows in (0..=40).chain([63, 64, 65, 70, 99]) {
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

    /// A product of blocks side by side is, to the bit, the first block's product followed
    /// by the others' accumulated (`Op::Set` then `Op::Add`): the per-sample maps' one call
    /// changes no answer.
    #[test]
    fn a_product_side_by_side_equals_the_products_in_turn_to_the_bit() {
        let mut rng = ChaCha8Rng::seed_from_u64(13);
        let mut value = || {
            let e: i32 = rng.random_range(-12..12);
            rng.random_range(-1.0..1.0) * 10f64.powi(e)
        };
        for rows in [1, 8, 33, 34, 35, 36, 41] {
            let widths = [33, 1, 1, 2];
            let blocks: Vec<DMatrix<f64>> = widths
                .iter()
                .map(|&c| DMatrix::from_fn(rows, c, |_, _| value()))
                .collect();
            let inputs: Vec<DVector<f64>> = widths
                .iter()
                .map(|&c| DVector::from_fn(c, |_, _| value()))
                .collect();
            let mut want = DVector::zeros(rows);
            for (k, (b, x)) in blocks.iter().zip(&inputs).enumerate() {
                gemv(&mut want, b, x, if k == 0 { Op::Set } else { Op::Add });
            }
            let joined = side_by_side(&blocks.iter().collect::<Vec<_>>());
            let x = DVector::from_iterator(
                widths.iter().sum(),
                inputs.iter().flat_map(|v| v.iter().copied()),
            );
            let mut got = DVector::zeros(rows);
            gemv(&mut got, &joined, &x, Op::Set);
            let bits = |v: &DVector<f64>| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
            assert_eq!(bits(&got), bits(&want), "{rows} rows");
        }
    }

    /// [`product`] is nalgebra's `&a * &b` to the bit, on both sides of its switch to
    /// `matrixmultiply` (any dimension ≤ 5, or all above).
    #[test]
    fn product_equals_nalgebra_to_the_bit() {
        let mut rng = ChaCha8Rng::seed_from_u64(16);
        for (rows, inner, cols) in [
            (33, 33, 1),
            (33, 33, 2),
            (1, 33, 33),
            (2, 11, 33),
            (24, 33, 1),
            (5, 5, 5),
            (6, 6, 6),
            (33, 33, 33),
            (23, 23, 23),
            (16, 8, 7),
            (12, 6, 9),
            (40, 23, 23),
            (25, 36, 33),
            (7, 256, 9),
            (9, 257, 8),
            (0, 3, 2),
            (3, 0, 2),
        ] {
            // Signed zeros too: a chain that starts from +0 keeps `0 · x + (−0)` as nalgebra does.
            let mut value = || match rng.random_range(0..8) {
                0 => -0.0,
                1 => 0.0,
                _ => rng.random_range(-1.0..1.0) * 10f64.powi(rng.random_range(-9..9)),
            };
            let a = DMatrix::from_fn(rows, inner, |_, _| value());
            let b = DMatrix::from_fn(inner, cols, |_, _| value());
            let want = &a * &b;
            let got = product(&a, &b);
            let bits = |m: &DMatrix<f64>| m.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
            assert_eq!(bits(&got), bits(&want), "{rows}×{inner} · {inner}×{cols}");
            // Into a buffer that held something else (every entry is written).
            let mut reused = DMatrix::from_element(rows, cols, f64::NAN);
            product_into(&mut reused, &a, &b);
            assert_eq!(
                bits(&reused),
                bits(&want),
                "into {rows}×{inner} · {inner}×{cols}"
            );
        }
    }

    /// [`axpy`] is the element-by-element `y + a x` (a rounded multiply, then a rounded add)
    /// to the bit for every length up to 40, signed zeros and a NaN included, whichever
    /// register width it runs in.
    #[test]
    fn axpy_equals_the_plain_loop_to_the_bit() {
        for len in 0..=40usize {
            let x: Vec<f64> = (0..len)
                .map(|i| match i % 7 {
                    0 => -0.0,
                    3 => f64::NAN,
                    _ => (i as f64 * 0.37).sin() * 1e3,
                })
                .collect();
            let y0: Vec<f64> = (0..len).map(|i| (i as f64 * 1.3).cos() - 0.5).collect();
            for a in [0.0, -0.0, 1.7e-3, -2.5e8] {
                let mut fast = y0.clone();
                axpy(&mut fast, a, &x);
                let plain: Vec<f64> = y0.iter().zip(&x).map(|(y, x)| y + a * x).collect();
                let bits = |v: &[f64]| v.iter().map(|z| z.to_bits()).collect::<Vec<_>>();
                assert_eq!(bits(&fast), bits(&plain), "length {len}, a = {a}");
            }
        }
    }

    /// [`dot`] is nalgebra's `dot` (and `gemv_tr`'s column) to the bit for every length up to
    /// 40, signed zeros included.
    #[test]
    fn dot_equals_nalgebra_to_the_bit() {
        let mut rng = ChaCha8Rng::seed_from_u64(15);
        for len in 0..=40 {
            for _ in 0..20 {
                let mut value = || match rng.random_range(0..6) {
                    0 => -0.0,
                    1 => 0.0,
                    _ => rng.random_range(-1.0..1.0) * 10f64.powi(rng.random_range(-15..15)),
                };
                let a: Vec<f64> = (0..len).map(|_| value()).collect();
                let x: Vec<f64> = (0..len).map(|_| value()).collect();
                let (va, vx) = (DVector::from_vec(a.clone()), DVector::from_vec(x.clone()));
                assert_eq!(dot(&a, &x).to_bits(), va.dot(&vx).to_bits(), "{len}");
                let m = DMatrix::from_column_slice(len, 1, &a);
                let mut y = DVector::zeros(1);
                y.gemv_tr(1.0, &m, &vx, 0.0);
                assert_eq!(dot(&a, &x).to_bits(), y[0].to_bits(), "{len}");
            }
        }
    }

    /// [`amax`] is nalgebra's `amax` to the bit, NaN entries
    /// (skipped; NaN only when all are), signed zeros and empty slices included; and
    /// [`all_finite`] tells an infinity or a NaN anywhere.
    #[test]
    fn amax_and_finiteness_equal_the_plain_definitions() {
        let mut rng = ChaCha8Rng::seed_from_u64(14);
        for len in 0..=13 {
            for _ in 0..50 {
                let a: Vec<f64> = (0..len)
                    .map(|_| match rng.random_range(0..8) {
                        0 => f64::NAN,
                        1 => -0.0,
                        _ => rng.random_range(-1e3..1e3),
                    })
                    .collect();
                let b: Vec<f64> = (0..len).map(|_| rng.random_range(-1e3..1e3)).collect();
                let (ma, mb) = (
                    DMatrix::from_column_slice(len, 1, &a),
                    DMatrix::from_column_slice(len, 1, &b),
                );
                assert_eq!(amax(&a).to_bits(), ma.amax().to_bits(), "{a:?}");
                assert_eq!(
                    amax((&ma - &mb).as_slice()).to_bits(),
                    (&ma - &mb).amax().to_bits(),
                    "{a:?} − {b:?}"
                );
                let finite = a.iter().all(|x| x.is_finite());
                assert_eq!(all_finite(&a), finite);
            }
        }
        assert!(amax(&[f64::NAN, f64::NAN]).is_nan());
        assert!(!all_finite(&[1.0, f64::INFINITY]));
        assert!(!all_finite(&[f64::NEG_INFINITY]));
        assert!(all_finite(&[f64::MAX, -f64::MAX, f64::MIN_POSITIVE, 0.0]));
    }

    /// [`LuSolver::factor`] gives the bits of nalgebra's `lu.l()`, `lu.u()`, and
    /// [`LuSolver::solve`] (and its portable kernel) those of `lu.solve`, for every size up to 40
    /// (right-hand sides of 0–3 columns, 5 and of the matrix's size), and `None` on an exactly
    /// singular matrix as nalgebra.
    #[test]
    fn lu_solve_equals_nalgebra_to_the_bit() {
        let mut rng = ChaCha8Rng::seed_from_u64(12);
        // (nalgebra's own solve fails on a 0 × 0 matrix.)
        for n in 1..=40 {
            let a = DMatrix::from_fn(n, n, |i, j| {
                let v: f64 = rng.random_range(-1.0..1.0);
                if i == j {
                    v + 2.0
                } else {
                    v * 10f64.powi(rng.random_range(-3..3))
                }
            });
            let lu = a.clone().lu();
            let solver = LuSolver::factor(a.clone());
            // The factors themselves, bit for bit.
            let (l, u) = (lu.l(), lu.u());
            for i in 0..n {
                for j in 0..n {
                    let want = if i > j { l[(i, j)] } else { u[(i, j)] };
                    let got = solver.packed[(i, j)];
                    assert_eq!(got.to_bits(), want.to_bits(), "{n}: factor ({i}, {j})");
                }
            }
            for cols in [0, 1, 2, 3, 5, n] {
                let b = DMatrix::from_fn(n, cols, |_, _| match rng.random_range(0..8) {
                    0 => 0.0,
                    1 => -0.0,
                    _ => rng.random_range(-1.0..1.0) * 10f64.powi(rng.random_range(-20..20)),
                });
                let want = lu.solve(&b).expect("regular");
                let got = solver.solve(&b).expect("regular");
                // The portable kernel too (the one a CPU without AVX runs).
                let mut plain = b.clone();
                lu.p().permute_rows(&mut plain);
                substitute(
                    solver.packed.as_slice(),
                    solver.packed.as_slice(),
                    n,
                    plain.as_mut_slice(),
                );
                for ((g, p), w) in got.iter().zip(plain.iter()).zip(want.iter()) {
                    assert_eq!(g.to_bits(), w.to_bits(), "{n}×{cols}: {g:e} vs {w:e}");
                    assert_eq!(p.to_bits(), w.to_bits(), "portable {n}×{cols}");
                }
            }
        }
        let singular =
            DMatrix::from_row_slice(3, 3, &[1.0, 2.0, 3.0, 2.0, 4.0, 6.0, 1.0, 0.0, 1.0]);
        let lu = singular.clone().lu();
        let b = DMatrix::from_element(3, 2, 1.0);
        assert_eq!(
            lu.solve(&b).is_none(),
            LuSolver::factor(singular).solve(&b).is_none()
        );
    }

    /// [`transposed`] and [`symmetrized`] equal nalgebra's `transpose` and
    /// `(&a + a.transpose()) * 0.5` to the bit.
    #[test]
    fn transpose_and_symmetrize_equal_nalgebra_to_the_bit() {
        let mut rng = ChaCha8Rng::seed_from_u64(13);
        for n in 0..=12 {
            for cols in [0, 1, n, n + 3] {
                let a = DMatrix::from_fn(n, cols, |_, _| rng.random_range(-1.0..1.0));
                assert_eq!(transposed(&a), a.transpose(), "{n}×{cols}");
            }
            let a = DMatrix::from_fn(n, n, |_, _| {
                rng.random_range(-1.0..1.0) * 10f64.powi(rng.random_range(-20..20))
            });
            assert_eq!(transposed(&a), a.transpose());
            let want = (&a + a.transpose()) * 0.5;
            for (g, w) in symmetrized(&a).iter().zip(want.iter()) {
                assert_eq!(g.to_bits(), w.to_bits());
            }
        }
    }
}
