//! Step V: least-squares fit of the connection parameters, `f_i = V_i·p`, accumulated one
//! row at a time by Givens rotations into a square-root information form `R p = z`.
//!
//! Why QR and not plain normal equations: the basis functions of one connection differ by
//! many orders of magnitude (δ ~ 1e-4 m beside sign(·) ~ 1 and const(100)), which squares
//! into a normal matrix with a condition number near 1e16; the triangular factor keeps it at
//! the square root. Each update costs O(P²) and allocates nothing. The residual sum of
//! squares falls out of the rotations exactly. An optional forgetting factor `λ ≤ 1` scales
//! the old information by `λ` per row so a changing joint can be tracked.
//!
//! [`Fit::std_errors`] are the ordinary least-squares ones, `σ̂² (RᵀR)⁻¹` with
//! `σ̂² = RSS/(N − P)`, where the rows are treated as independent. Residual-force errors are
//! correlated in time (a smoothed random walk), so these figures understate the uncertainty,
//! by a factor of 3–30 measured on the two-beam problem. [`hac_covariance`] gives the
//! heteroscedasticity-and-autocorrelation-consistent (Newey–West) sandwich that accounts for
//! it; `identify` reports that one.

use nalgebra::{DMatrix, DVector};

#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum RefitError {
    #[error(
        "the parameter fit's normal equations are not finite or their SVD did not converge ({params} parameters): a basis scale or the data are out of range"
    )]
    SolverFailed { params: usize },
    #[error("too few usable samples: {rows} for {params} parameters")]
    TooFewRows { rows: usize, params: usize },
    #[error(
        "the parameter fit is singular: rank {rank} of {params} (condition number {condition:.3e}); the data do not excite basis `{weakest}` independently of the others"
    )]
    RankDeficient {
        rank: usize,
        params: usize,
        condition: f64,
        weakest: String,
    },
    #[error(
        "the parameter fit is ill-conditioned: condition number {condition:.3e} exceeds {limit:.1e}; basis `{weakest}` is nearly a combination of the others"
    )]
    IllConditioned {
        condition: f64,
        limit: f64,
        weakest: String,
    },
}

/// Online least squares for one connection's parameters.
#[derive(Debug, Clone)]
pub struct RecursiveLeastSquares {
    r: DMatrix<f64>,
    z: DVector<f64>,
    rss: f64,
    rows: usize,
    /// Effective number of rows with forgetting (Σ λᵏ).
    weight: f64,
    forgetting: f64,
    work: DVector<f64>,
}

/// A solved fit.
#[derive(Debug, Clone, PartialEq)]
pub struct Fit {
    pub values: Vec<f64>,
    pub std_errors: Vec<f64>,
    /// 2-norm condition number of the column-scaled design matrix.
    pub condition: f64,
    /// Root-mean-square of the fit residual (N).
    pub rms_residual: f64,
    pub rows: usize,
    /// RMS of each basis column over the rows, and of the fitted force: together they
    /// turn a parameter change into a force change for the stopping rule.
    pub column_rms: Vec<f64>,
    pub force_rms: f64,
}

impl RecursiveLeastSquares {
    pub fn new(params: usize, forgetting: f64) -> Self {
        Self {
            r: DMatrix::zeros(params, params),
            z: DVector::zeros(params),
            rss: 0.0,
            rows: 0,
            weight: 0.0,
            forgetting: forgetting.clamp(0.0, 1.0),
            work: DVector::zeros(params),
        }
    }

    pub fn params(&self) -> usize {
        self.z.len()
    }

    pub fn rows(&self) -> usize {
        self.rows
    }

    pub fn reset(&mut self) {
        self.r.fill(0.0);
        self.z.fill(0.0);
        self.rss = 0.0;
        self.rows = 0;
        self.weight = 0.0;
    }

    /// Add one row `v·p ≈ f`.
    pub fn push(&mut self, v: &[f64], f: f64) {
        let p = self.params();
        if self.forgetting < 1.0 {
            let s = self.forgetting.sqrt();
            self.r *= s;
            self.z *= s;
            self.rss *= self.forgetting;
            self.weight *= self.forgetting;
        }
        self.work.copy_from_slice(v);
        let mut f = f;
        for k in 0..p {
            let x = self.work[k];
            if x == 0.0 {
                continue;
            }
            let rkk = self.r[(k, k)];
            let h = rkk.hypot(x);
            let (c, s) = (rkk / h, x / h);
            self.r[(k, k)] = h;
            for j in k + 1..p {
                let (a, b) = (self.r[(k, j)], self.work[j]);
                self.r[(k, j)] = c * a + s * b;
                self.work[j] = -s * a + c * b;
            }
            let zk = self.z[k];
            self.z[k] = c * zk + s * f;
            f = -s * zk + c * f;
        }
        self.rss += f * f;
        self.rows += 1;
        self.weight += 1.0;
    }

    /// Solve for the parameters. `labels` name the basis functions in messages.
    pub fn solve(&self, labels: &[String], max_condition: f64) -> Result<Fit, RefitError> {
        let p = self.params();
        if self.rows < p + 1 {
            return Err(RefitError::TooFewRows {
                rows: self.rows,
                params: p,
            });
        }
        // Column scaling: R D with D = 1/‖column‖ makes the condition number meaningful.
        let mut d = DVector::zeros(p);
        for j in 0..p {
            let nrm = self.r.column(j).norm();
            d[j] = if nrm > 0.0 { 1.0 / nrm } else { 0.0 };
        }
        let rs = DMatrix::from_fn(p, p, |i, j| self.r[(i, j)] * d[j]);
        // Bounded: an SVD of non-finite or extreme entries (a `const(1e308)` basis) must end
        // in an error, not spin.
        let Some(svd) = rs
            .iter()
            .all(|v| v.is_finite())
            .then(|| rs.clone().try_svd(true, true, f64::EPSILON, 10_000))
            .flatten()
        else {
            return Err(RefitError::SolverFailed { params: p });
        };
        let smax = svd.singular_values.max();
        let smin = svd.singular_values.min();
        let condition = if smin > 0.0 {
            smax / smin
        } else {
            f64::INFINITY
        };
        let weakest =
            || -> String {
                // The column dominating the smallest right singular vector.
                let (imin, _) = svd.singular_values.iter().enumerate().fold(
                    (0, f64::INFINITY),
                    |acc, (i, &s)| if s < acc.1 { (i, s) } else { acc },
                );
                let vt = svd.v_t.as_ref().map(|v| v.row(imin).transpose());
                let j = vt.map_or(0, |v| v.iamax());
                labels.get(j).cloned().unwrap_or_default()
            };
        let tol = smax * p as f64 * f64::EPSILON * 16.0;
        let rank = svd.singular_values.iter().filter(|&&s| s > tol).count();
        if rank < p {
            return Err(RefitError::RankDeficient {
                rank,
                params: p,
                condition,
                weakest: weakest(),
            });
        }
        if condition > max_condition {
            return Err(RefitError::IllConditioned {
                condition,
                limit: max_condition,
                weakest: weakest(),
            });
        }
        // Back substitution R p = z.
        let mut x = self.z.clone();
        for i in (0..p).rev() {
            let mut s = x[i];
            for j in i + 1..p {
                s -= self.r[(i, j)] * x[j];
            }
            x[i] = s / self.r[(i, i)];
        }
        let dof = (self.weight - p as f64).max(1.0);
        let sigma2 = self.rss / dof;
        // (RᵀR)⁻¹ = R⁻¹ R⁻ᵀ: diagonal = squared row norms of R⁻¹.
        let rinv = self
            .r
            .clone()
            .solve_upper_triangular(&DMatrix::identity(p, p))
            .unwrap_or_else(|| DMatrix::from_element(p, p, f64::NAN));
        let std_errors = (0..p)
            .map(|i| (sigma2 * rinv.row(i).norm_squared()).sqrt())
            .collect();
        Ok(Fit {
            values: x.iter().copied().collect(),
            std_errors,
            condition,
            rms_residual: (self.rss / self.weight.max(1.0)).sqrt(),
            rows: self.rows,
            column_rms: (0..p)
                .map(|j| self.r.column(j).norm() / self.weight.max(1.0).sqrt())
                .collect(),
            force_rms: ((self.z.norm_squared() + self.rss) / self.weight.max(1.0)).sqrt(),
        })
    }
}

/// `Ω = Γ₀ + Σ_{l=1}^{L} (1 − l/(L+1)) (Γ_l + Γ_lᵀ)`, `Γ_l = Σᵢ gᵢ gᵢ₋ₗᵀ`: the
/// Newey–West (Bartlett) long-run covariance of the scores `g` (`n × p`, row-major), in
/// `O((n + L) p²)` instead of `O(n L p²)`.
///
/// Why: the Bartlett weight is the overlap of two windows of `L + 1` samples,
/// `(L + 1 − |i − j|)₊ = #{t : i, j ∈ [t − L, t]}`, so `(L + 1) Ω = Σ_t S_t S_tᵀ` with
/// `S_t` the sum of the scores in the window ending at `t` (`t = 0 … n + L − 1`, windows cut
/// at the record's ends). The residual forces of a pass are correlated over thousands of
/// samples (lag-one autocorrelation ~0.99, so the plug-in lag grows to `n/4`): on a
/// 100,000-sample record the direct sum over lags was a third of the whole
/// identification's time (measured 2026-11-27, `perf record`). The window sum is updated
/// by adding the entering score and subtracting the leaving one, and summed afresh every
/// `L + 1` samples so that its round-off does not build up along the record.
pub fn bartlett_long_run_covariance(g: &[f64], p: usize, lag: usize) -> DMatrix<f64> {
    let mut omega = DMatrix::<f64>::zeros(p, p);
    let n = g.len().checked_div(p).unwrap_or(0);
    if n == 0 {
        return omega;
    }
    let score = |i: usize| &g[i * p..(i + 1) * p];
    let mut window = vec![0.0; p];
    for t in 0..n + lag {
        if t % (lag + 1) == 0 {
            window.fill(0.0);
            for i in t.saturating_sub(lag)..=t.min(n - 1) {
                for (w, x) in window.iter_mut().zip(score(i)) {
                    *w += x;
                }
            }
        } else {
            if t < n {
                for (w, x) in window.iter_mut().zip(score(t)) {
                    *w += x;
                }
            }
            if t > lag {
                for (w, x) in window.iter_mut().zip(score(t - lag - 1)) {
                    *w -= x;
                }
            }
        }
        for b in 0..p {
            for a in 0..p {
                omega[(a, b)] += window[a] * window[b];
            }
        }
    }
    omega / (lag + 1) as f64
}

/// Newey–West (Bartlett kernel) covariance of least-squares parameters whose row errors are
/// correlated in time.
///
/// `rows` holds the design matrix row-major (`N × P`), `y` the targets, `values` the fitted
/// parameters. With scores `gᵢ = xᵢ eᵢ`, `eᵢ = yᵢ − xᵢᵀp`, the sandwich is
/// `(XᵀX)⁻¹ Ω (XᵀX)⁻¹`, `Ω = Γ₀ + Σ_{l=1}^{L} (1 − l/(L+1)) (Γ_l + Γ_lᵀ)`,
/// `Γ_l = Σᵢ gᵢ gᵢ₋ₗᵀ`. The lag window `L` follows Andrews (1991)'s AR(1) plug-in for the
/// Bartlett kernel, `L = 1.1447 (α N)^{1/3}`, `α = 4ρ²/((1−ρ)²(1+ρ)²)`, with ρ the lag-one
/// autocorrelation of the residuals, doubled because the plug-in is tuned for mean-square
/// error rather than interval coverage (Kiefer & Vogelsang 2005 show coverage needs longer
/// windows), and capped at N/4. Returns the standard errors and `L`; `None` when the normal
/// matrix is singular or there are fewer than `4 P` rows.
pub fn hac_covariance(rows: &[f64], y: &[f64], values: &[f64]) -> Option<(Vec<f64>, usize)> {
    let p = values.len();
    let n = y.len();
    if p == 0 || rows.len() != n * p || n < 4 * p {
        return None;
    }
    let e: Vec<f64> = (0..n)
        .map(|i| y[i] - (0..p).map(|j| rows[i * p + j] * values[j]).sum::<f64>())
        .collect();
    let (mut num, mut den) = (0.0, 0.0);
    for i in 1..n {
        num += e[i] * e[i - 1];
        den += e[i - 1] * e[i - 1];
    }
    let rho = if den > 0.0 {
        (num / den).clamp(-0.99, 0.99)
    } else {
        0.0
    };
    let alpha = 4.0 * rho * rho / ((1.0 - rho).powi(2) * (1.0 + rho).powi(2));
    let lag = ((2.0 * 1.1447 * (alpha * n as f64).cbrt()).ceil() as usize)
        .max(1)
        .min(n / 4);
    // Column scaling keeps XᵀX well conditioned for wildly scaled bases.
    let mut scale = vec![0.0; p];
    for i in 0..n {
        for j in 0..p {
            scale[j] += rows[i * p + j].powi(2);
        }
    }
    let scale: Vec<f64> = scale
        .iter()
        .map(|s| if *s > 0.0 { 1.0 / s.sqrt() } else { 0.0 })
        .collect();
    let g: Vec<f64> = (0..n * p)
        .map(|k| rows[k] * scale[k % p] * e[k / p])
        .collect();
    let mut xtx = DMatrix::<f64>::zeros(p, p);
    for i in 0..n {
        for a in 0..p {
            let xa = rows[i * p + a] * scale[a];
            for b in 0..p {
                xtx[(a, b)] += xa * rows[i * p + b] * scale[b];
            }
        }
    }
    let omega = bartlett_long_run_covariance(&g, p, lag);
    let inv = xtx.try_inverse()?;
    let cov = &inv * omega * &inv;
    let se = (0..p)
        .map(|j| cov[(j, j)].max(0.0).sqrt() * scale[j])
        .collect::<Vec<_>>();
    se.iter().all(|s| s.is_finite()).then_some((se, lag))
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The window-sum Newey–West equals the direct sum over lags (`Γ₀ + Σ w_l (Γ_l + Γ_lᵀ)`)
    /// to round-off, for autocorrelated scores, lags from 0 to beyond the record, and a
    /// record of one sample.
    #[test]
    fn bartlett_window_sum_equals_the_sum_over_lags() {
        let mut seed = 0x9e37_79b9_7f4a_7c15u64;
        let mut u = move || {
            seed ^= seed << 13;
            seed ^= seed >> 7;
            seed ^= seed << 17;
            (seed >> 11) as f64 / (1u64 << 53) as f64 - 0.5
        };
        let direct = |g: &[f64], p: usize, lag: usize| {
            let n = g.len() / p;
            let mut omega = DMatrix::<f64>::zeros(p, p);
            for l in 0..=lag.min(n.saturating_sub(1)) {
                let w = 1.0 - l as f64 / (lag + 1) as f64;
                for i in l..n {
                    for a in 0..p {
                        for b in 0..p {
                            let x = g[i * p + a] * g[(i - l) * p + b];
                            omega[(a, b)] += if l == 0 { x } else { w * x };
                            if l > 0 {
                                omega[(b, a)] += w * x;
                            }
                        }
                    }
                }
            }
            omega
        };
        for (n, p, rho) in [(500, 4, 0.99), (300, 3, -0.6), (1, 2, 0.0), (40, 1, 0.9)] {
            let mut g = Vec::with_capacity(n * p);
            let mut last = vec![0.0; p];
            for _ in 0..n {
                for (a, x) in last.iter_mut().enumerate() {
                    *x = rho * *x + u() * (1.0 + a as f64 * 1e3);
                    g.push(*x);
                }
            }
            for lag in [0, 1, 7, n / 4, n, 3 * n] {
                let want = direct(&g, p, lag);
                let got = bartlett_long_run_covariance(&g, p, lag);
                let tol = 1e-11 * want.amax().max(f64::MIN_POSITIVE);
                assert!(
                    (&got - &want).amax() <= tol,
                    "n {n}, p {p}, lag {lag}: {got} vs {want}"
                );
            }
        }
    }

    fn labels(n: usize) -> Vec<String> {
        (0..n).map(|i| format!("b{i}")).collect()
    }

    #[test]
    fn exact_recovery_with_wildly_scaled_columns() {
        let truth = [3000.0, 3.0e5, 0.5, 20.0];
        let mut ls = RecursiveLeastSquares::new(4, 1.0);
        for i in 0..500 {
            let t = i as f64 * 0.01;
            let d = 1e-4 * (3.0 * t).sin() + 2e-5 * (11.0 * t).cos();
            let v = 1e-2 * (3.0 * t).cos();
            let row = [d.signum(), d, 100.0, v];
            let f: f64 = row.iter().zip(truth).map(|(a, b)| a * b).sum();
            ls.push(&row, f);
        }
        let fit = ls.solve(&labels(4), 1e12).unwrap();
        for (x, t) in fit.values.iter().zip(truth) {
            assert!((x - t).abs() <= 1e-9 * t.abs().max(1.0), "{x} vs {t}");
        }
        assert!(fit.rms_residual < 1e-6);
    }

    #[test]
    fn standard_error_matches_ols_formula_on_a_mean() {
        // Fitting a constant: se = s/√N.
        let mut ls = RecursiveLeastSquares::new(1, 1.0);
        let data = [1.0, 2.0, 4.0, 7.0, 11.0];
        for x in data {
            ls.push(&[1.0], x);
        }
        let fit = ls.solve(&labels(1), 1e12).unwrap();
        let mean = 5.0;
        let s2: f64 = data.iter().map(|x| (x - mean).powi(2)).sum::<f64>() / 4.0;
        assert!((fit.values[0] - mean).abs() < 1e-12);
        assert!((fit.std_errors[0] - (s2 / 5.0).sqrt()).abs() < 1e-12);
    }

    #[test]
    fn hac_standard_error_of_a_mean_under_ar1_errors_is_honest() {
        // Mean of AR(1) noise with ρ = 0.9: the true variance of the sample mean is
        // ≈ σ²/(N(1−ρ)²)·(1−ρ²) = 19× the i.i.d. formula. Over many series the HAC standard
        // error must be near the spread of the means, and the OLS one far below it.
        let (n, reps, rho) = (2000, 200, 0.9);
        let mut s: u64 = 0x2545_f491_4f6c_dd1d;
        let mut u = || {
            s ^= s << 13;
            s ^= s >> 7;
            s ^= s << 17;
            ((s >> 11) as f64 + 0.5) / (1u64 << 53) as f64
        };
        let mut means = Vec::new();
        let mut hac = Vec::new();
        let mut ols = Vec::new();
        for _ in 0..reps {
            let mut e = 0.0;
            let mut y = Vec::with_capacity(n);
            for _ in 0..n {
                let z = (-2.0 * u().ln()).sqrt() * (2.0 * std::f64::consts::PI * u()).cos();
                e = rho * e + z;
                y.push(e);
            }
            let mut ls = RecursiveLeastSquares::new(1, 1.0);
            for v in &y {
                ls.push(&[1.0], *v);
            }
            let fit = ls.solve(&labels(1), 1e12).unwrap();
            let rows = vec![1.0; n];
            let (se, lag) = hac_covariance(&rows, &y, &fit.values).unwrap();
            assert!(lag > 10 && lag <= n / 4, "lag {lag}");
            means.push(fit.values[0]);
            hac.push(se[0]);
            ols.push(fit.std_errors[0]);
        }
        let spread = (means.iter().map(|m| m * m).sum::<f64>() / reps as f64).sqrt();
        let mean_hac = hac.iter().sum::<f64>() / reps as f64;
        let mean_ols = ols.iter().sum::<f64>() / reps as f64;
        assert!(
            (mean_hac / spread - 1.0).abs() < 0.25,
            "HAC {mean_hac} vs spread {spread}"
        );
        assert!(mean_ols < 0.4 * spread, "OLS {mean_ols} vs spread {spread}");
    }

    #[test]
    fn collinear_columns_are_reported_with_rank() {
        let mut ls = RecursiveLeastSquares::new(2, 1.0);
        for i in 0..10 {
            let x = i as f64;
            ls.push(&[x, 2.0 * x], 3.0 * x);
        }
        match ls.solve(&labels(2), 1e12) {
            Err(RefitError::RankDeficient { rank, params, .. }) => {
                assert_eq!((rank, params), (1, 2))
            }
            other => panic!("{other:?}"),
        }
    }

    #[test]
    fn forgetting_tracks_a_step_change() {
        let mut ls = RecursiveLeastSquares::new(1, 0.95);
        for i in 0..400 {
            let x = 1.0 + (i % 7) as f64;
            let k = if i < 200 { 10.0 } else { 7.0 };
            ls.push(&[x], k * x);
        }
        let fit = ls.solve(&labels(1), 1e12).unwrap();
        // Old information weighs 0.95^200 ≈ 3.5e-5 of the new.
        assert!((fit.values[0] - 7.0).abs() < 1e-3, "{}", fit.values[0]);
    }
}
