//! Tuning from the data: the measurement noise level of each channel (when the setup gives
//! none) and the Kalman estimator's random-walk std of the residual force.
//!
//! - **Noise level.** The k-th difference of white noise of std σ has variance
//!   `C(2k, k) σ²`, while a signal that is smooth at the sampling rate is nearly removed by
//!   it. A robust scale (1.4826 × median absolute deviation) of the k-th differences, divided
//!   by `√C(2k, k)`, estimates σ without being thrown off by the occasional large signal
//!   difference. Signal content near the Nyquist frequency is indistinguishable from noise
//!   by this test, so the smallest estimate over k = 1..=6 is taken (each order is unbiased
//!   for white noise; the signal only adds), with a floor of `1e-7 × RMS` so noise-free data
//!   still give finite weights. The estimate is an upper bound on σ for densely sampled
//!   data; the likelihood tuning below can scale it down.
//! - **Random-walk std σ_R** (and a scale factor of the noise levels): maximise the
//!   innovation log-likelihood of a filter-only run over a log grid, then refine by Brent's
//!   method in log space. See [`maximise_log`].

/// `C(2k, k)`.
fn central_binomial(k: usize) -> f64 {
    (1..=k).fold(1.0, |acc, i| acc * (k + i) as f64 / i as f64)
}

/// Median of a slice (reorders it). `None` when empty or holding a non-finite value.
fn median(x: &mut [f64]) -> Option<f64> {
    if x.is_empty() || x.iter().any(|v| !v.is_finite()) {
        return None;
    }
    let mid = x.len() / 2;
    x.select_nth_unstable_by(mid, f64::total_cmp);
    let hi = x[mid];
    if x.len() % 2 == 1 {
        return Some(hi);
    }
    let lo = x[..mid].iter().copied().fold(f64::NEG_INFINITY, f64::max);
    Some(0.5 * (lo + hi))
}

/// Robust white-noise std from the `order`-th differences of `y`. `None` when there are
/// too few samples or the data are not finite.
pub fn difference_noise_std(y: &[f64], order: usize) -> Option<f64> {
    if order == 0 || y.len() < order + 8 {
        return None;
    }
    let mut d = y.to_vec();
    for k in 0..order {
        for i in 0..d.len() - 1 - k {
            d[i] = d[i + 1] - d[i];
        }
    }
    d.truncate(y.len() - order);
    let med = median(&mut d.clone())?;
    for v in d.iter_mut() {
        *v = (*v - med).abs();
    }
    let mad = median(&mut d)?;
    Some(1.4826 * mad / central_binomial(order).sqrt())
}

/// Highest difference order tried by [`channel_noise_std`].
pub const MAX_DIFFERENCE_ORDER: usize = 6;
/// Floor of the noise estimate relative to the channel RMS.
/// (1e-7: below it the Kalman innovation covariance of noise-free data loses positive
/// definiteness in round-off — measured on the two-beam problem at 1e-9.)
pub const NOISE_FLOOR_RELATIVE: f64 = 1e-7;

/// Noise std of one channel: the smallest difference estimate over orders
/// `1..=MAX_DIFFERENCE_ORDER`, floored at `NOISE_FLOOR_RELATIVE × RMS` (and at the smallest
/// positive number, so it is always usable as a weight).
pub fn channel_noise_std(y: &[f64]) -> f64 {
    let rms = (y.iter().map(|v| v * v).sum::<f64>() / y.len().max(1) as f64).sqrt();
    let floor = if rms.is_finite() {
        (NOISE_FLOOR_RELATIVE * rms).max(f64::MIN_POSITIVE)
    } else {
        1.0
    };
    (1..=MAX_DIFFERENCE_ORDER)
        .filter_map(|k| difference_noise_std(y, k))
        .fold(f64::INFINITY, f64::min)
        .max(floor)
        .min(if rms.is_finite() && rms > 0.0 {
            rms
        } else {
            f64::INFINITY
        })
}

/// Maximise `f(x)` over `x ∈ [lo, hi]` (both > 0) in log space: a grid of `grid` points,
/// then Brent's refinement around the best grid point, at most `refine` evaluations (fewer
/// when it reaches [`BRENT_TOL`]). Non-finite values count as −∞. Returns
/// `(x, f(x), evaluations)`.
pub fn maximise_log(
    lo: f64,
    hi: f64,
    grid: usize,
    refine: usize,
    f: &mut dyn FnMut(f64) -> f64,
) -> (f64, f64, usize) {
    maximise_log_batched(lo, hi, grid, refine, &mut |xs: &[f64]| {
        xs.iter().map(|&x| f(x)).collect()
    })
}

/// [`maximise_log`] with the grid points evaluated on parallel threads
/// ([`crate::par::map`]): the same points, compared in the same order, so the same
/// answer. Why: the Kalman filter's likelihood tuning evaluates its grids one filter run
/// after another while the second core idles (a quarter of the shipped replay's time).
pub fn maximise_log_parallel(
    lo: f64,
    hi: f64,
    grid: usize,
    refine: usize,
    f: &(dyn Fn(f64) -> f64 + Sync),
) -> (f64, f64, usize) {
    maximise_log_batched(lo, hi, grid, refine, &mut |xs: &[f64]| {
        crate::par::map(xs, |&x| f(x))
    })
}

/// [`maximise_log`] with `eval` evaluating a batch of points `x` (not log).
fn maximise_log_batched(
    lo: f64,
    hi: f64,
    grid: usize,
    refine: usize,
    eval: &mut dyn FnMut(&[f64]) -> Vec<f64>,
) -> (f64, f64, usize) {
    let (a, b) = (lo.ln(), hi.ln());
    let grid = grid.max(2);
    let step = (b - a) / (grid - 1) as f64;
    let finite = |v: f64| if v.is_finite() { v } else { f64::NEG_INFINITY };
    let mut eval_logs = |ts: &[f64]| -> Vec<f64> {
        let xs: Vec<f64> = ts.iter().map(|t| t.exp()).collect();
        eval(&xs).into_iter().map(finite).collect()
    };
    let mut best = (a, f64::NEG_INFINITY);
    let ts: Vec<f64> = (0..grid).map(|i| a + step * i as f64).collect();
    for (t, v) in ts.iter().zip(eval_logs(&ts)) {
        if v > best.1 {
            best = (*t, v);
        }
    }
    let mut count = grid;
    // Brent's method on [best − step, best + step]: parabolic steps through the three best
    // points, each safeguarded by a golden-section step when it would leave the bracket or
    // not shrink it (Brent, *Algorithms for Minimization without Derivatives*, 1973, ch. 5;
    // Numerical Recipes §10.3), until the bracket is narrower than 4 × `BRENT_TOL` or
    // `refine` evaluations were made. Why not golden section alone (as before): its bracket
    // shrinks by 0.618 per evaluation whatever the function, and the likelihoods tuned here
    // are smooth near their peak, where parabolic steps converge superlinearly — the same
    // precision in about half the filter runs (BENCHMARKS.md, fifteenth session).
    let cgold = 0.5 * (3.0 - 5f64.sqrt());
    let tol = BRENT_TOL * std::f64::consts::LN_10;
    let (mut lo, mut hi) = (best.0 - step, best.0 + step);
    // Minimise −f: x the best point, w the second best, v the previous w.
    let (mut x, mut w, mut v) = (best.0, best.0, best.0);
    let (mut fx, mut fw, mut fv) = (-best.1, -best.1, -best.1);
    let (mut d, mut e): (f64, f64) = (0.0, 0.0);
    for _ in 0..refine {
        let xm = 0.5 * (lo + hi);
        if (x - xm).abs() <= 2.0 * tol - 0.5 * (hi - lo) {
            break;
        }
        let mut golden = true;
        if e.abs() > tol && fx.is_finite() && fw.is_finite() && fv.is_finite() {
            let r = (x - w) * (fx - fv);
            let q0 = (x - v) * (fx - fw);
            let mut p = (x - v) * q0 - (x - w) * r;
            let mut q = 2.0 * (q0 - r);
            if q > 0.0 {
                p = -p;
            }
            q = q.abs();
            let e_before = e;
            e = d;
            // Accept the parabola's vertex if it lies inside the bracket and moves less
            // than half the step before last (else the parabola is not to be trusted).
            if p.abs() < (0.5 * q * e_before).abs() && p > q * (lo - x) && p < q * (hi - x) {
                d = p / q;
                let u = x + d;
                if u - lo < 2.0 * tol || hi - u < 2.0 * tol {
                    d = tol.copysign(xm - x);
                }
                golden = false;
            }
        }
        if golden {
            e = if x >= xm { lo - x } else { hi - x };
            d = cgold * e;
        }
        let u = if d.abs() >= tol {
            x + d
        } else {
            x + tol.copysign(d)
        };
        let fu = -eval_logs(&[u])[0];
        count += 1;
        if fu <= fx {
            if u >= x {
                lo = x;
            } else {
                hi = x;
            }
            (v, fv) = (w, fw);
            (w, fw) = (x, fx);
            (x, fx) = (u, fu);
        } else {
            if u < x {
                lo = u;
            } else {
                hi = u;
            }
            if fu <= fw || w == x {
                (v, fv) = (w, fw);
                (w, fw) = (u, fu);
            } else if fu <= fv || v == x || v == w {
                (v, fv) = (u, fu);
            }
        }
    }
    (x.exp(), -fx, count)
}

/// Precision of [`maximise_log`]'s refinement, in decades of `x`: it stops when the
/// bracket is narrower than 4× this (0.02 decades, a 5 % band of `x`; the golden section
/// that it replaced ended with brackets of 0.016–0.04 decades at the Kalman tuning's
/// evaluation counts).
const BRENT_TOL: f64 = 0.005;

#[cfg(test)]
mod tests {
    use super::*;

    /// Deterministic standard normal samples (xorshift + Box–Muller).
    fn normals(n: usize, mut s: u64) -> Vec<f64> {
        let mut u = || {
            s ^= s << 13;
            s ^= s >> 7;
            s ^= s << 17;
            ((s >> 11) as f64 + 0.5) / (1u64 << 53) as f64
        };
        (0..n)
            .map(|_| (-2.0 * u().ln()).sqrt() * (2.0 * std::f64::consts::PI * u()).cos())
            .collect()
    }

    #[test]
    fn central_binomials() {
        assert_eq!(central_binomial(1), 2.0);
        assert_eq!(central_binomial(2), 6.0);
        assert_eq!(central_binomial(4), 70.0);
    }

    #[test]
    fn noise_estimate_recovers_sigma_on_sine_plus_noise() {
        // 100 Hz sine of amplitude 1 sampled at 10 kHz plus white noise of σ = 0.01.
        let n = 4000;
        let e = normals(n, 0x9e37_79b9_7f4a_7c15);
        let sigma = 0.01;
        let y: Vec<f64> = (0..n)
            .map(|i| (2.0 * std::f64::consts::PI * 100.0 * i as f64 * 1e-4).sin() + sigma * e[i])
            .collect();
        let est = channel_noise_std(&y);
        assert!(
            (est / sigma - 1.0).abs() < 0.10,
            "estimated {est}, true {sigma}"
        );
        // Noise-free: the estimate is tiny against the signal (≤ 1e-3 of the RMS).
        let clean: Vec<f64> = (0..n)
            .map(|i| (2.0 * std::f64::consts::PI * 100.0 * i as f64 * 1e-4).sin())
            .collect();
        let est = channel_noise_std(&clean);
        assert!(est > 0.0 && est < 1e-3, "noise-free estimate {est}");
    }

    #[test]
    fn maximise_log_finds_the_peak() {
        let (x, _, count) = maximise_log(1e-4, 1e4, 9, 20, &mut |x: f64| {
            -(x.ln() - 3f64.ln()).powi(2)
        });
        assert!((x / 3.0 - 1.0).abs() < 1e-3, "{x}");
        // A parabola in log x: Brent's refinement stops long before its budget.
        assert!(count < 9 + 10, "{count} evaluations");
    }

    /// An asymmetric smooth peak (not a parabola in log x): Brent's refinement reaches its
    /// tolerance in fewer evaluations than the 12 golden-section steps it replaced, and to
    /// at least their precision (0.016 decades).
    #[test]
    fn brent_refinement_is_precise_in_fewer_evaluations() {
        // −(e^{1.5t} − 1.5t), t = log10 x − 0.37: the maximum at x = 10^0.37, steep on one
        // side and nearly linear on the other.
        let truth = 0.37f64;
        let f = |x: f64| {
            let t = x.log10() - truth;
            -((1.5 * t).exp() - 1.5 * t)
        };
        let (x, fx, count) = maximise_log(1e-4, 1e4, 9, 12, &mut |x| f(x));
        assert!(
            (x.log10() - truth).abs() < 0.008,
            "{} vs {truth}",
            x.log10()
        );
        assert!(fx >= f(10f64.powf(truth)) - 1e-4, "{fx}");
        assert!(count <= 9 + 8, "{count} evaluations");
    }

    /// The parallel version evaluates the same points and returns the same answer, to the
    /// bit, on a bumpy function (two peaks, a non-finite region).
    #[test]
    fn maximise_log_parallel_equals_the_sequential_one() {
        let f = |x: f64| {
            if x > 5e3 {
                f64::NAN
            } else {
                -(x.ln() - 3f64.ln()).powi(2) + 0.3 * (5.0 * x.ln()).sin()
            }
        };
        for (grid, refine) in [(9, 12), (6, 2), (5, 10)] {
            let a = maximise_log(1e-4, 1e4, grid, refine, &mut |x| f(x));
            let b = maximise_log_parallel(1e-4, 1e4, grid, refine, &f);
            assert_eq!(a.0.to_bits(), b.0.to_bits(), "{a:?} vs {b:?}");
            assert_eq!(a.1.to_bits(), b.1.to_bits(), "{a:?} vs {b:?}");
            assert_eq!(a.2, b.2);
        }
    }
}
