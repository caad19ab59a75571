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
//!   innovation log-likelihood of a filter-only run over a log grid, then refine by golden
//!   section in log space. See [`maximise_log`].

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
/// then golden-section refinement around the best grid point for `refine` evaluations.
/// Non-finite values count as −∞. Returns `(x, f(x), evaluations)`.
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

/// [`maximise_log`] with the grid points and the first golden pair evaluated on parallel
/// threads ([`crate::par::map`]): the same points, compared in the same order, so the same
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
    // Golden section on [best − step, best + step].
    let g = 0.5 * (5f64.sqrt() - 1.0);
    let (mut l, mut r) = (best.0 - step, best.0 + step);
    let mut x1 = r - g * (r - l);
    let mut x2 = l + g * (r - l);
    let pair = eval_logs(&[x1, x2]);
    let (mut f1, mut f2) = (pair[0], pair[1]);
    count += 2;
    for _ in 0..refine.saturating_sub(2) {
        if f1 >= f2 {
            r = x2;
            x2 = x1;
            f2 = f1;
            x1 = r - g * (r - l);
            f1 = eval_logs(&[x1])[0];
        } else {
            l = x1;
            x1 = x2;
            f1 = f2;
            x2 = l + g * (r - l);
            f2 = eval_logs(&[x2])[0];
        }
        count += 1;
    }
    for (t, v) in [(x1, f1), (x2, f2)] {
        if v > best.1 {
            best = (t, v);
        }
    }
    (best.0.exp(), best.1, count)
}

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
        assert_eq!(count, 9 + 20);
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
