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

/// The floor of a channel's noise std: `NOISE_FLOOR_RELATIVE` × its RMS (at least the
/// smallest positive number, so it is always usable as a weight; 1 when the RMS is not
/// finite). Also the least level the Kalman tuning may scale an estimated channel to
/// (`identify::kalman_tuning::noise_scale_range`).
pub fn noise_floor(rms: f64) -> f64 {
    if rms.is_finite() {
        (NOISE_FLOOR_RELATIVE * rms).max(f64::MIN_POSITIVE)
    } else {
        1.0
    }
}

/// Noise std of one channel: the smallest difference estimate over orders
/// `1..=MAX_DIFFERENCE_ORDER`, floored at `NOISE_FLOOR_RELATIVE × RMS` (and at the smallest
/// positive number, so it is always usable as a weight).
pub fn channel_noise_std(y: &[f64]) -> f64 {
    let rms = (y.iter().map(|v| v * v).sum::<f64>() / y.len().max(1) as f64).sqrt();
    let floor = noise_floor(rms);
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
/// then Brent's method (parabolic interpolation safeguarded by golden section) around the
/// best grid point, for at most `refine` further evaluations, until the peak is known to
/// [`LOG_TOLERANCE`] in `ln x` or a step could gain less than [`LIKELIHOOD_TOLERANCE`] of
/// `f` (a log-likelihood). Non-finite values count as −∞. Returns `(x, f(x),
/// evaluations)`.
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
/// ([`crate::par::map`]): the same points, compared in the same order, so the same answer.
/// Why: the Kalman filter's likelihood tuning evaluates its grids one filter run after
/// another while the second core idles.
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

/// Precision, in `ln x`, to which [`maximise_log`] locates a peak (1 %): the likelihoods it
/// maximises are flat there to far below their sampling error (a noise level or a
/// random-walk std 1 % off changes an identified parameter by a small fraction of its
/// standard error).
///
/// Why Brent and not golden section (used until the eighteenth session): near its peak a
/// log-likelihood is close to a parabola in `ln x`, and the parabola through the best grid
/// point and its two neighbours — already evaluated — lands within a few per cent of the
/// peak; golden section ignored both the grid's values and the curvature and spent 10–12
/// sequential filter runs per search shrinking the bracket by 0.618 each. Measured on the
/// shipped friction replay: BENCHMARKS.md, eighteenth session.
pub const LOG_TOLERANCE: f64 = 0.01;

/// What a search of a log-likelihood still has to gain, in its units, when [`maximise_log`]
/// stops before the next parabolic step: the step is not run when the parabola through the
/// three best points predicts less than this above the best one. Why: a tuning's
/// log-likelihood within 0.05 of its peak is a small fraction of the tuning's own
/// uncertainty (one standard deviation is 0.5), and the `ln x` tolerance alone ran 2–4 more
/// sequential filter runs per search that each gained 0.01–0.04 (traced on the benchmark
/// record, BENCHMARKS.md thirty-fifth session).
pub const LIKELIHOOD_TOLERANCE: f64 = 0.05;

/// The fall, from `fx`, of the parabola through `(x, fx)`, `(w, fw)`, `(v, fv)` over the
/// step `d` from `x` (∞ when the three points do not make a convex parabola: no reason to
/// stop).
fn parabola_gain(x: f64, fx: f64, w: f64, fw: f64, v: f64, fv: f64, d: f64) -> f64 {
    if w == x || v == x || w == v {
        return f64::INFINITY;
    }
    // Second divided difference: half the parabola's curvature.
    let half_curvature = ((fw - fx) / (w - x) - (fv - fx) / (v - x)) / (w - v);
    if half_curvature.is_nan() || half_curvature <= 0.0 {
        return f64::INFINITY;
    }
    half_curvature * d * d
}

/// A whole-record likelihood's values remembered by the exact bits of its arguments.
///
/// Why: the tunings come back to points they have already run — Brent's step can land
/// exactly on a grid point, and a search of one tuning variable can start its grid on the
/// value another search has just run — each a whole-record filter run (measured on the
/// benchmark record, BENCHMARKS.md twenty-ninth session: 5 of 99). The same arguments give
/// the same bits, so a remembered value changes nothing but the time. The caller keys it by
/// every argument that varies while the memo lives (the data and the model it borrows for
/// that time do not).
#[derive(Debug)]
pub struct Remembered<T = f64> {
    values: std::sync::Mutex<std::collections::HashMap<Vec<u64>, T>>,
}

impl<T> Default for Remembered<T> {
    fn default() -> Self {
        Self {
            values: std::sync::Mutex::new(std::collections::HashMap::new()),
        }
    }
}

impl<T: Copy> Remembered<T> {
    /// The value at `key`: remembered, or `run()` (then remembered).
    pub fn value(&self, key: &[f64], run: impl FnOnce() -> T) -> T {
        let key: Vec<u64> = key.iter().map(|x| x.to_bits()).collect();
        if let Some(v) = self.values.lock().ok().and_then(|m| m.get(&key).copied()) {
            return v;
        }
        let v = run();
        if let Ok(mut m) = self.values.lock() {
            m.insert(key, v);
        }
        v
    }
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
    let ts: Vec<f64> = (0..grid).map(|i| a + step * i as f64).collect();
    let xs: Vec<f64> = ts.iter().map(|t| t.exp()).collect();
    let values: Vec<f64> = eval(&xs).into_iter().map(finite).collect();
    // A Brent step that lands exactly on a grid point reads its value (see [`Remembered`]).
    let on_grid = |x: f64| {
        xs.iter()
            .position(|g| g.to_bits() == x.to_bits())
            .map(|i| values[i])
    };
    let mut best = 0;
    for (i, v) in values.iter().enumerate() {
        if *v > values[best] {
            best = i;
        }
    }
    // Brent on g(t) = −f(t) over [best − step, best + step], started from the best grid
    // point with its grid neighbours as the two previous points (their values are known).
    let (peak, count) = brent_minimise(
        ts[best] - step,
        ts[best] + step,
        (ts[best], -values[best]),
        [
            best.checked_sub(1).map(|i| (ts[i], -values[i])),
            values.get(best + 1).map(|v| (ts[best + 1], -v)),
        ],
        refine,
        &mut |t| {
            let x = t.exp();
            -on_grid(x).unwrap_or_else(|| finite(eval(&[x])[0]))
        },
    );
    (peak.0.exp(), -peak.1, grid + count)
}

/// Brent's minimiser (Brent 1973, ch. 5; the `fmin` algorithm) of `g` on `[lo, hi]` from the
/// point `x` (inside, its value known) and up to two other known points, for at most
/// `max_evals` evaluations of `g`, to the absolute tolerance [`LOG_TOLERANCE`] or until,
/// after a parabolic step, the next could gain less than [`LIKELIHOOD_TOLERANCE`]. `+∞` values
/// are allowed (a failed run): the parabola is then not trusted and the step is golden.
/// Returns the best point seen and the number of evaluations.
fn brent_minimise(
    lo: f64,
    hi: f64,
    x: (f64, f64),
    known: [Option<(f64, f64)>; 2],
    max_evals: usize,
    g: &mut dyn FnMut(f64) -> f64,
) -> ((f64, f64), usize) {
    const GOLD: f64 = 0.381_966_011_250_105_1; // (3 − √5) / 2
    let tol = LOG_TOLERANCE;
    let (mut a, mut b) = (lo, hi);
    let (mut x, mut fx) = x;
    // w: the second best point, v: the previous w (Brent's notation).
    let (mut w, mut fw, mut v, mut fv) = (x, fx, x, fx);
    let mut known: Vec<(f64, f64)> = known.into_iter().flatten().collect();
    known.sort_by(|p, q| p.1.total_cmp(&q.1));
    if let Some(&(t, ft)) = known.first() {
        (w, fw) = (t, ft);
        (v, fv) = (t, ft);
    }
    if let Some(&(t, ft)) = known.get(1) {
        (v, fv) = (t, ft);
    }
    // d: the last step; e: the step before it (a parabolic step must be smaller than half of
    // it, or the iteration falls back to golden section). Seeded so that the first step may
    // be parabolic when the neighbours are known.
    let mut d = 0.0f64;
    let mut e = if w != x { b - a } else { 0.0 };
    let mut evals = 0;
    let mut last_parabolic = false;
    while evals < max_evals {
        let xm = 0.5 * (a + b);
        let tol2 = 2.0 * tol;
        if (x - xm).abs() <= tol2 - 0.5 * (b - a) {
            break;
        }
        let mut golden = true;
        if e.abs() > tol && fx.is_finite() && fw.is_finite() && fv.is_finite() {
            let r = (x - w) * (fx - fv);
            let mut q = (x - v) * (fx - fw);
            let mut p = (x - v) * q - (x - w) * r;
            q = 2.0 * (q - r);
            if q > 0.0 {
                p = -p;
            }
            q = q.abs();
            let e_prev = e;
            if q > 0.0 && p.abs() < (0.5 * q * e_prev).abs() && p > q * (a - x) && p < q * (b - x) {
                // What the step can still gain: the parabola's fall from `x` to its vertex —
                // trusted only after a parabolic step, when its three points are the search's
                // latest, close ones (through the grid's neighbours or after a golden step it
                // spans the bracket and can underestimate the gain several times over).
                if last_parabolic
                    && parabola_gain(x, fx, w, fw, v, fv, p / q) < LIKELIHOOD_TOLERANCE
                {
                    break;
                }
                e = d;
                d = p / q;
                let u = x + d;
                if u - a < tol2 || b - u < tol2 {
                    d = tol.copysign(xm - x);
                }
                golden = false;
            }
        }
        if golden {
            e = if x >= xm { a - x } else { b - x };
            d = GOLD * e;
        }
        let u = if d.abs() >= tol {
            x + d
        } else {
            x + tol.copysign(d)
        };
        last_parabolic = !golden;
        let fu = g(u);
        let fu = if fu.is_nan() { f64::INFINITY } else { fu };
        evals += 1;
        if fu <= fx {
            if u >= x {
                a = x;
            } else {
                b = x;
            }
            (v, fv) = (w, fw);
            (w, fw) = (x, fx);
            (x, fx) = (u, fu);
        } else {
            if u < x {
                a = u;
            } else {
                b = u;
            }
            if fu <= fw || w == x {
                (v, fv) = (w, fw);
                (w, fw) = (u, fu);
            } else if fu <= fv || v == x || v == w {
                (v, fv) = (u, fu);
            }
        }
    }
    ((x, fx), evals)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A remembered value is run once per key (the bits of every argument), and a search that
    /// remembers gives the answer of one that does not.
    #[test]
    fn a_remembered_likelihood_runs_once_per_key() {
        let runs = std::sync::atomic::AtomicUsize::new(0);
        let memo = Remembered::default();
        let f = |x: f64, y: f64| {
            memo.value(&[x, y], || {
                runs.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
                -(x.ln() - 1.0).powi(2) - y
            })
        };
        assert_eq!(f(2.0, 0.0), f(2.0, 0.0));
        assert_eq!(runs.load(std::sync::atomic::Ordering::Relaxed), 1);
        let _ = (f(2.0, 1.0), f(-0.0, 0.0), f(0.0, 0.0));
        assert_eq!(runs.load(std::sync::atomic::Ordering::Relaxed), 4);
        let plain = |x: f64| -(x.ln() - 1.0).powi(2);
        let remembered = |x: f64| f(x, 0.0);
        let a = maximise_log_parallel(1e-3, 1e3, 7, 12, &plain);
        let b = maximise_log_parallel(1e-3, 1e3, 7, 12, &remembered);
        assert_eq!(
            (a.0.to_bits(), a.1.to_bits(), a.2),
            (b.0.to_bits(), b.1.to_bits(), b.2)
        );
    }

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
        // A parabola in ln x: the first parabolic step lands on the peak.
        assert!(count <= 9 + 4, "{count} evaluations");
    }

    /// A peak that is not a parabola in `ln x` (skewed, and a failed region beside it) is
    /// still found to the tolerance, within the evaluation cap — as a log-likelihood of
    /// thousands of samples (a curvature of 2,000 per unit of `ln x` squared, as the
    /// tunings' are); as flat as a single sample's, it is found to within
    /// [`LIKELIHOOD_TOLERANCE`] of its peak value, in fewer evaluations. (With the stop
    /// trusted right after the first, golden step, the flat search of the peak at 3 stopped
    /// at −0.094: that parabola spanned the bracket.)
    #[test]
    fn maximise_log_finds_a_skewed_peak_to_its_tolerance() {
        for peak in [0.37f64, 3.0, 41.0, 900.0] {
            let t0 = peak.ln();
            let f = |x: f64| {
                let t = x.ln() - t0;
                if t > 1.5 {
                    f64::NAN
                } else {
                    -(t * t) + 0.4 * t * t * t - 0.2 * (t * t).powi(2)
                }
            };
            let (x, fx, count) = maximise_log(1e-4, 1e4, 9, 12, &mut |x| 1e3 * f(x));
            assert!(
                (x.ln() - t0).abs() <= 2.0 * LOG_TOLERANCE,
                "peak {peak}: found {x} ({fx}) after {count}"
            );
            assert!(count <= 9 + 12, "{count}");
            let (_, flat, flat_count) = maximise_log(1e-4, 1e4, 9, 12, &mut |x| f(x));
            assert!(flat >= -LIKELIHOOD_TOLERANCE, "peak {peak}: {flat}");
            assert!(flat_count < count, "{flat_count} against {count}");
        }
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
