//! Residual-force estimators (Steps III–IV) and the connection law they feed (Step V).
//!
//! Every estimator implements [`ResidualEstimator`]: given one aligned sample (known
//! excitation `p_i`, measured station outputs `y_i`) it returns the residual force
//! `R_i = f_i − f̂_i` at each connection, the total connection force `f_i` and the
//! connection state `(δ, δ̇, δ̈)_i` the model reaches with it. MCAP replay, live iceoryx2 data
//! and the synthetic generator all drive this same `step`.
//!
//! - [`paper::PaperEstimator`]: the 1989 one-step weighted least squares (the reference).
//! - [`kalman::KalmanEstimator`]: joint input–state estimation with a steady-state Kalman
//!   gain and a fixed-lag smoother (the default; see its module docs for why).

#![allow(non_snake_case)]

pub mod kalman;
pub mod ml;
pub mod output_error;
pub mod paper;
pub mod prediction_error;
pub mod refit;
pub mod tuning;

use nalgebra::{DMatrix, DVector};

use crate::setup::{Basis, Quantity, Setup};

#[derive(Debug, thiserror::Error)]
pub enum EstimateError {
    #[error(
        "the stations cannot determine the residual forces: rank(S) = {rank} but {needed} connection DOFs need {needed} independent measured quantities ({stations} channels; condition number {condition:.3e})"
    )]
    RankDeficientSensitivity {
        rank: usize,
        needed: usize,
        stations: usize,
        condition: f64,
    },
    #[error(
        "the Kalman filter's innovation covariance (H P Hᵀ + V over {channels} channels) is not positive definite in floating point: either the channels' noise levels are too small against the round-off of the model's predictions (noise-free data: give `noise_std` values near the sensors' real noise, or use `--estimator paper` on data of the model's own discretisation), or the parameters the filter ran with make the model blow up"
    )]
    InnovationCovariance { channels: usize },
    #[error("the estimate diverged at sample {sample}: the model state is no longer finite")]
    Diverged { sample: u64 },
    #[error(
        "the estimate diverged at sample {sample}: the residual force or connection state reached {magnitude:.1e}, too large to square in the parameter fit (the estimator's error recursion is unstable; see its spectral radius)"
    )]
    Overflowed { sample: u64, magnitude: f64 },
    #[error(
        "all {channels} measured channels are accelerations: the residual-force (kalman) stage cannot determine the joint deformation from accelerations alone (a constant residual force and its static deflection produce no acceleration; measured on continuous data: the spring ~100 % off with a small stated error), and the output-error stage that identifies such layouts from a stiffness scan is switched off, has no spring (`u`) term to scan, or did not lower the cost; add a displacement or velocity channel near the joint, or use `--estimator paper` on noise-free data of the model's own discretisation (ACCURACY.md, \"Accelerometers only\")"
    )]
    AccelerationOnly { channels: usize },
    #[error(
        "the model has {dofs} DOFs and was assembled in sparse form only (no dense M, C, K): only the paper estimator with `[integrator] step = \"sparse\"` (or \"auto\") can run on it"
    )]
    NeedsDense { dofs: usize },
    #[error(transparent)]
    Integrate(#[from] crate::integrate::IntegrateError),
}

/// One sample's estimate. Vectors have one entry per connection.
#[derive(Debug, Clone)]
pub struct StepOutput {
    pub sample: u64,
    /// `R = f − f̂`, N.
    pub residual: DVector<f64>,
    /// Total connection force `f`, N, positive resisting.
    pub force: DVector<f64>,
    /// Connection deformation δ (m), rate δ̇ (m/s), acceleration δ̈ (m/s²).
    pub delta: DVector<f64>,
    pub delta_v: DVector<f64>,
    pub delta_a: DVector<f64>,
}

impl StepOutput {
    pub fn new(q: usize) -> Self {
        Self {
            sample: 0,
            residual: DVector::zeros(q),
            force: DVector::zeros(q),
            delta: DVector::zeros(q),
            delta_v: DVector::zeros(q),
            delta_a: DVector::zeros(q),
        }
    }
}

/// Figures an estimator reports about itself, per pass.
#[derive(Debug, Clone, Default, serde::Serialize)]
pub struct EstimatorDiagnostics {
    pub estimator: String,
    /// Rank of the weighted sensitivity `W^½ S`.
    pub sensitivity_rank: usize,
    /// 2-norm condition number of `W^½ S`.
    pub sensitivity_condition: f64,
    /// Largest singular value of `S`: output change per newton of residual force.
    pub sensitivity_gain: f64,
    /// Spectral radius of the step-to-step error recursion (≥ 1: errors do not decay).
    pub error_spectral_radius: Option<f64>,
    /// Free-form tuning facts (Kalman noise levels, lag, …).
    pub tuning: Vec<(String, f64)>,
    pub warnings: Vec<String>,
}

impl EstimatorDiagnostics {
    /// A named tuning figure (e.g. `posterior_delta_std_m[0]`), if the estimator reports it.
    pub fn tuning_value(&self, key: &str) -> Option<f64> {
        self.tuning.iter().find(|(k, _)| k == key).map(|(_, v)| *v)
    }
}

/// A residual-force estimator: Steps III and IV for one sample at a time.
pub trait ResidualEstimator: Send {
    fn name(&self) -> &'static str;
    /// Start a pass at rest with the first sample's excitation.
    fn start(&mut self, sample: u64, excitation: &[f64]);
    /// Consume sample `sample`. Returns `true` when `out` holds a finished estimate (its
    /// `out.sample` may lag behind `sample` for smoothing estimators).
    fn step(
        &mut self,
        sample: u64,
        excitation: &[f64],
        measured: &[f64],
        out: &mut StepOutput,
    ) -> Result<bool, EstimateError>;
    /// After the last sample: emit the estimates still held back, one per call.
    fn drain(&mut self, out: &mut StepOutput) -> bool;
    fn diagnostics(&self) -> &EstimatorDiagnostics;
    /// Start the next passes from this state instead of rest: `(u; u̇; ü)` offsets, `3n`
    /// long (a record that starts in motion). Estimators that cannot (the 1989 one) ignore
    /// it; `identify` refuses such records for them.
    fn set_initial_state(&mut self, _offset: &[f64]) {}
    /// After a pass: the least-squares correction of the initial state `(u; u̇; ü)` (`3n`,
    /// to add to the state the pass started from) that the pass's innovations call for
    /// (see `kalman::KalmanEstimator::initial_state_fit`).
    fn initial_state_fit(&self) -> Option<Vec<f64>> {
        None
    }
    /// The current state estimate `(u; u̇; ü)` (3n, absolute), so that a live session can
    /// swap a refined model in mid-stream ([`Self::continue_from`]). `None`: it cannot.
    fn current_state(&self) -> Option<Vec<f64>> {
        None
    }
    /// Continue from another estimator's state `x` (3n) and total connection force `force`
    /// (q, N) at the sample just stepped (excitation `excitation`), instead of from rest:
    /// the residual force starts as what this estimator's law leaves of `force`. Returns
    /// `false` when this estimator cannot.
    fn continue_from(&mut self, _x: &[f64], _force: &[f64], _excitation: &[f64]) -> bool {
        false
    }
}

/// The connection law `f = Σ pⱼ vⱼ(δ, δ̇, δ̈)` with the current parameter estimate, split
/// into the linear terms (carried by the model's K, C, M) and the rest (applied as an
/// explicit force from the previous sample's state).
#[derive(Debug, Clone)]
pub struct ConnectionLaw {
    /// Per connection: its basis functions and the offset of its first parameter.
    pub blocks: Vec<(Vec<Basis>, usize)>,
    pub params: Vec<f64>,
    pub labels: Vec<String>,
}

impl ConnectionLaw {
    pub fn new(setup: &Setup, params: &[f64]) -> Self {
        let mut blocks = Vec::new();
        let mut off = 0;
        for c in &setup.connections {
            blocks.push((c.basis.clone(), off));
            off += c.basis.len();
        }
        Self {
            blocks,
            params: params.to_vec(),
            labels: setup.param_keys(),
        }
    }

    pub fn q(&self) -> usize {
        self.blocks.len()
    }

    /// Force of the non-linear terms (everything not in K, C, M).
    pub fn explicit_force(
        &self,
        d: &DVector<f64>,
        dv: &DVector<f64>,
        da: &DVector<f64>,
        out: &mut DVector<f64>,
    ) {
        for (c, (basis, off)) in self.blocks.iter().enumerate() {
            out[c] = basis
                .iter()
                .enumerate()
                .filter(|(_, b)| !b.is_linear())
                .map(|(j, b)| self.params[off + j] * b.eval(d[c], dv[c], da[c]))
                .sum();
        }
    }

    /// Force of the linear terms (the part the model's matrices carry).
    pub fn linear_force(
        &self,
        d: &DVector<f64>,
        dv: &DVector<f64>,
        da: &DVector<f64>,
        out: &mut DVector<f64>,
    ) {
        for (c, (basis, off)) in self.blocks.iter().enumerate() {
            out[c] = basis
                .iter()
                .enumerate()
                .filter(|(_, b)| b.is_linear())
                .map(|(j, b)| self.params[off + j] * b.eval(d[c], dv[c], da[c]))
                .sum();
        }
    }
}

/// Station output map: `y = H x` with `x = (u; v; a)`, plus the channels' selection.
#[derive(Debug, Clone)]
pub struct Stations {
    pub channels: Vec<(usize, Quantity)>,
}

impl Stations {
    pub fn from_model(model: &crate::model::Model) -> Self {
        Self {
            channels: model.stations.iter().map(|s| (s.dof, s.quantity)).collect(),
        }
    }

    pub fn m(&self) -> usize {
        self.channels.len()
    }

    /// Index of a channel in the stacked state (u; v; a).
    pub fn state_index(&self, k: usize, n: usize) -> usize {
        let (dof, q) = self.channels[k];
        q.block() * n + dof
    }

    /// Rows of a stacked (3n × k) matrix picked by the channels: H·X.
    pub fn pick_rows(&self, x: &DMatrix<f64>, n: usize) -> DMatrix<f64> {
        DMatrix::from_fn(self.m(), x.ncols(), |i, j| x[(self.state_index(i, n), j)])
    }
}

/// Rank and 2-norm condition number of a matrix (tolerance relative to the largest singular
/// value).
pub fn rank_and_condition(a: &DMatrix<f64>) -> (usize, f64, f64) {
    // Bounded iterations: non-finite entries give rank 0, not a hang.
    let Some(svd) = a
        .iter()
        .all(|v| v.is_finite())
        .then(|| a.clone().try_svd(false, false, f64::EPSILON, 10_000))
        .flatten()
    else {
        return (0, f64::INFINITY, 0.0);
    };
    let sv = svd.singular_values;
    let smax = sv.max();
    let smin = sv.min();
    let tol = smax * (a.nrows().max(a.ncols()) as f64) * f64::EPSILON * 16.0;
    let rank = sv.iter().filter(|&&s| s > tol).count();
    (
        rank,
        if smin > 0.0 {
            smax / smin
        } else {
            f64::INFINITY
        },
        smax,
    )
}

/// Spectral radius of a square matrix; `+∞` when it cannot be computed (non-finite entries,
/// or the Schur iteration not converging in 10,000 sweeps on a wildly scaled matrix), which
/// every caller reads as "unstable".
pub fn spectral_radius(a: &DMatrix<f64>) -> f64 {
    if !a.iter().all(|x| x.is_finite()) {
        return f64::INFINITY;
    }
    match a.clone().try_schur(f64::EPSILON, 10_000) {
        Some(schur) => schur
            .complex_eigenvalues()
            .iter()
            .map(|z| z.norm())
            .fold(0.0, f64::max),
        None => f64::INFINITY,
    }
}

/// Whether the spectral radius of `a` exceeds `limit` (> 0): [`spectral_radius`]'s answer,
/// with a cheaper proof first for the usual case of a radius well inside it. For every
/// submultiplicative norm `ρ(A) ≤ ‖Aᵏ‖^(1/k)`, so when the Frobenius norm of `A^(2ʲ)`
/// (j squarings) is at most `limit^(2ʲ)` the radius is within the limit; `2ʲ` is taken
/// ≥ 64 × `horizon` (the steps the limit was set for) so that a radius at most the limit
/// passes whatever the transient growth of the powers (up to e⁶⁴ of the limit's allowance).
/// Otherwise (a radius above the limit, a power too large or not finite) the Schur form
/// decides. Why: the stability test of the maximum-likelihood descent ran a Schur
/// decomposition at every accepted step of a model that is not passive (a damper estimated
/// slightly negative), 14 % of such an identification's time; twenty products of the
/// matrix cost a fifth of it.
pub fn spectral_radius_exceeds(a: &DMatrix<f64>, limit: f64, horizon: f64) -> bool {
    let log_limit = limit.ln();
    if a.iter().all(|x| x.is_finite()) && log_limit > 0.0 && a.is_square() {
        let mut power = a.clone();
        let mut k = 1.0f64;
        while k < 64.0 * horizon.max(1.0) && k < 1e12 {
            power = crate::dense::product(&power, &power);
            k *= 2.0;
        }
        let norm = power.norm();
        if norm.is_finite() && norm.ln() <= k * log_limit {
            return false;
        }
    }
    spectral_radius(a) > limit
}

/// Whether a finite difference of half-width `h` at a parameter of value `value` with basis
/// function `basis` is one-sided (forward only): a friction level whose backward point would
/// be negative, a law the simulator cannot run.
pub(crate) fn one_sided_difference(basis: &Basis, value: f64, h: f64) -> bool {
    matches!(basis, Basis::SignU | Basis::SignV) && value - h < 0.0
}

/// Half-widths of a finite-difference Jacobian's steps at `p`: `frac` of each parameter's
/// scale (its standard error or a start's), at least 1e-7 of its value and √(smallest
/// positive number), so that no step vanishes. Shared by the output-error and
/// prediction-error Jacobians (their fractions differ).
pub(crate) fn difference_steps(frac: f64, scales: &[f64], p: &[f64]) -> Vec<f64> {
    scales
        .iter()
        .zip(p)
        .map(|(s, v)| {
            (frac * s.abs())
                .max(1e-7 * v.abs())
                .max(f64::MIN_POSITIVE.sqrt())
        })
        .collect()
}

/// The displaced points of a central-difference Jacobian at `p` with half-widths `steps`, in
/// the order the Jacobians difference them: per parameter `p + h e_j`, then `p − h e_j`
/// unless the difference is one-sided ([`one_sided_difference`]). The output-error and
/// prediction-error Jacobians run them on parallel threads.
pub(crate) fn difference_points(basis: &[Basis], p: &[f64], steps: &[f64]) -> Vec<Vec<f64>> {
    let mut points = Vec::with_capacity(2 * p.len());
    for j in 0..p.len() {
        let mut plus = p.to_vec();
        plus[j] += steps[j];
        points.push(plus);
        if !one_sided_difference(&basis[j], p[j], steps[j]) {
            let mut minus = p.to_vec();
            minus[j] -= steps[j];
            points.push(minus);
        }
    }
    points
}

/// Excitation samples whose linear interpolation has, over every sample interval, the mean
/// of the cubic (Catmull–Rom) interpolant of the original samples:
/// `p̃ᵢ = pᵢ − (pᵢ₋₁ − 2pᵢ + pᵢ₊₁)/12` (the end samples kept).
///
/// Why: the model interpolates each force channel linearly between samples (the sample
/// maps of `simulate` are linear in a sample's two end values), which is exact for a force
/// that is piecewise linear (the `random` scenario's) but misses `(ωh)²/12` of a smooth
/// force's mean over each sample — 0.13 % of a 200 Hz sine sampled at 10 kHz, which 1 %
/// noise sees. Measured (friction setup, `--scenario sine`, 64-sub-step data): noise-free,
/// the refinement's normalised cost stayed at 0.156 and `u` ended −0.20 % off (−6.6 of its
/// errors) with linear interpolation, at 0.0000 and −0.019 % with these samples; at 1 %
/// noise, 15 of 16 records at rest were called "in motion" (the misfit of the first
/// periods, which a start state fits) and none with them. The linear interpolation of
/// `p̃` then carries a smooth force's sample means to the model's third order in `ωh`
/// without touching the sample maps. Which of the two the record is, the data decide
/// (the likelier: `identify::pem::refine_by_prediction_error`, the free run's
/// `identify::smooth_between_samples`, and [`ml`]'s variants).
pub(crate) fn moment_matched(exc: &[Vec<f64>]) -> Vec<Vec<f64>> {
    let n = exc.len();
    (0..n)
        .map(|i| {
            if i == 0 || i + 1 == n {
                return exc[i].clone();
            }
            exc[i]
                .iter()
                .enumerate()
                .map(|(c, &x)| x - (exc[i - 1][c] - 2.0 * x + exc[i + 1][c]) / 12.0)
                .collect()
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The squaring proof never calls a radius above the limit within it, and agrees with the
    /// Schur form on either side of it — a rotation scaled just inside and just outside, and a
    /// non-normal matrix whose powers grow a thousandfold before they decay.
    #[test]
    fn a_radius_within_its_limit_is_proved_so_and_one_beyond_is_not() {
        let rotation = |r: f64| {
            let (c, s) = (0.3f64.cos(), 0.3f64.sin());
            DMatrix::from_row_slice(2, 2, &[r * c, -r * s, r * s, r * c])
        };
        let limit = 1.0 + 10f64.ln() / 2000.0;
        for (a, beyond) in [
            (rotation(0.999), false),
            (rotation(1.0), false),
            (rotation(1.0005), false),
            (rotation(1.002), true),
            (DMatrix::from_row_slice(2, 2, &[0.9, 1e3, 0.0, 0.9]), false),
            (DMatrix::from_row_slice(2, 2, &[1.01, 1e3, 0.0, 0.5]), true),
            (
                DMatrix::from_row_slice(2, 2, &[f64::NAN, 0.0, 0.0, 0.5]),
                true,
            ),
        ] {
            assert_eq!(spectral_radius_exceeds(&a, limit, 2000.0), beyond, "{a}");
            assert_eq!(spectral_radius(&a) > limit, beyond, "{a}");
        }
    }

    /// Forward and backward points per parameter in order; a friction level whose backward
    /// point would be negative gets the forward one only, and one at a positive value both.
    #[test]
    fn difference_points_are_one_sided_only_at_a_friction_bound() {
        let basis = [Basis::SignU, Basis::U, Basis::SignV];
        let p = [0.5, 10.0, 3.0];
        let steps = [1.0, 2.0, 1.0];
        let points = difference_points(&basis, &p, &steps);
        assert_eq!(
            points,
            vec![
                vec![1.5, 10.0, 3.0],
                vec![0.5, 12.0, 3.0],
                vec![0.5, 8.0, 3.0],
                vec![0.5, 10.0, 4.0],
                vec![0.5, 10.0, 2.0],
            ]
        );
        assert!(one_sided_difference(&Basis::SignV, 0.5, 1.0));
        assert!(!one_sided_difference(&Basis::U, -5.0, 1.0));
    }
}
