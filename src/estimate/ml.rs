//! Maximum-likelihood output error on an exactly discretised model — the default estimator.
//!
//! # Why this estimator
//! The 1989 estimator inverts the structure one step at a time and is exact only on data
//! made with its own discretisation; the Kalman stage that followed it needed tuning,
//! scans and sub-step guesses to be right on continuous data. This module does one thing
//! that is right by construction for the data a test produces: it simulates the model with
//! the candidate parameters, compares the simulated outputs with the measured ones, and
//! maximises the likelihood of the difference under Gaussian white measurement noise of an
//! unknown level per channel. Nothing is tuned by hand.
//!
//! # Model (symbols as in `model.rs`)
//! State `z = [u; u̇]` (2n). The linear connection terms go into the matrices:
//! `Mₑ = M + Lc·diag(p_a)·Lcᵀ`, `Cₑ = C + Lc·diag(p_v)·Lcᵀ`, `Kₑ = K + Lc·diag(p_u)·Lcᵀ`;
//! the rest of the law (`u³`, `sign(u)`, `sign(v)`, `gap`, `const`) is the non-linear force
//! `f_nl(δ, δ̇)`, positive resisting:
//!
//! ```text
//! Mₑ ü + Cₑ u̇ + Kₑ u = Lp·p(t) − Lc·f_nl(δ, δ̇),    δ = Lcᵀu
//! ```
//!
//! **Discretisation.** Over each step the excitation and `f_nl` are linear in time
//! (first-order hold: exactly how `simulate` interpolates its excitation, and how a
//! band-limited measured force is best read between samples), and the linear structure is
//! discretised *exactly* by the matrix exponential of Van Loan's augmented matrix
//! `exp([[F, B, 0], [0, 0, I], [0, 0, 0]]·h) = [[Φ, Γ₁, Γ₂], …]`, so
//! `z₊ = Φz + Γ₁w + (Γ₂/h)(w₊ − w)` with `w = [p; f_nl]`. For a law that is linear in the
//! state this is exact for any sample rate: no sub-steps to guess. `f_nl` at the step's end
//! is solved implicitly, set-valued at `sign(0)` (a joint that can stick, sticks), as in the
//! simulator. For non-linear laws the hold of `f_nl` is the only approximation; its effect
//! on the outputs is measured at the estimate by halving the step, and the step is halved
//! (sub-steps 1, 2, 4, … 16) until that effect is below [`MlOptions::max_discretisation_error`]
//! noise standard deviations. The report states the step used and the measured bound.
//!
//! # Estimator
//! Unknowns: the connection parameters `p` and, unless switched off, the initial state
//! `z₀` (records need not start at rest). With `σ_c` the noise level of channel `c`
//! concentrated out (`σ_c² = SSR_c/N`), the negative log-likelihood is
//! `Σ_c (N/2)·ln(SSR_c/N)`, minimised by Levenberg–Marquardt with finite-difference
//! sensitivities (central for `p`, forward for `z₀`, on which the outputs are affine for a
//! linear law). To reach the global minimum of a cost whose valleys narrow as the record
//! lengthens (a stiffness wrong by 1 % puts a mode out of phase after ~50 periods), the fit
//! is grown over prefixes of the record, doubling from [`MlOptions::first_stage_samples`]:
//! each prefix's minimum lies well inside the next one's valley. The basin it grows from is
//! chosen on a short prefix by a start grid; no one prefix length chooses it right on every
//! record, so the whole fit runs from two (`START_PREFIXES`, one after the other) and the
//! answer is the one of higher likelihood on the whole record.
//!
//! **Which model the record was made with** — the exact map or Newmark with 1, 2, … 64
//! sub-steps (what a simulation may have used), the excitation linear between samples or
//! smooth (moment-matched, `estimate::moment_matched`) — is a discrete nuisance
//! parameter: every candidate is refitted from the answer and weighed by its likelihood;
//! where the data do not single one out the answer is the posterior mean over them, its
//! errors including their spread (`average_over_models`).
//!
//! # Scope (measured, see ACCURACY.md)
//! Laws linear in the state (`u`, `v`, `a`, `const`) on the two-beam problem: right on data
//! of 1, 8 and 64 Newmark sub-steps and on records that start in motion, the errors at the
//! Cramér–Rao bound. Laws with `sign`, `u³` or `gap` terms are refused
//! ([`MlError::UnsupportedLaw`]): the implicit set-valued step below is in place, but the
//! descent does not find their global minimum (friction −95 %, cubic −26 % with 0.1 %
//! stated errors on 8-sub-step data), and a refusal is better than a confident wrong answer.
//!
//! # Standard errors that hold
//! `cov = I⁻¹` (Fisher information at the estimate, the Cramér–Rao bound, reported as `crlb`)
//! when the residuals are white; the reported standard error is the larger of that and the
//! Newey–West sandwich `I⁻¹ Ω I⁻¹`, which widens when the residuals are correlated in time
//! (the model does not explain the data). Every fit also reports a portmanteau whiteness
//! statistic per channel and, when `noise_std` is stated in the setup, the ratio of the fitted
//! noise to it; both become warnings (and refusals under `--strict`) when the model does not
//! explain the outputs.
#![allow(non_snake_case)]

use nalgebra::{DMatrix, DVector};
use serde::Serialize;

use crate::identify::TestData;
use crate::model::Model;
use crate::setup::{Basis, Quantity, Setup};

#[derive(Debug, thiserror::Error)]
pub enum MlError {
    #[error(
        "the maximum-likelihood estimator needs the dense model ({dofs} DOFs are held sparse only); set `[estimator] reduce_modes` or use `--estimator paper`"
    )]
    NeedsDense { dofs: usize },
    #[error(
        "the mass matrix with the added-mass (`a`) terms is not positive definite at parameters {params}"
    )]
    MassNotPositive { params: String },
    #[error(
        "the record holds {got} samples; the maximum-likelihood estimator needs at least {needed}"
    )]
    TooShort { got: usize, needed: usize },
    #[error(
        "the model's simulation diverged at sample {sample} with parameters {params} (state not finite); check the setup's initial values and units"
    )]
    Diverged { sample: usize, params: String },
    #[error(
        "the data do not determine the parameters: the Fisher information of the connection parameters has rank {rank} of {needed} (condition number {condition:.3e}, limit {limit:.1e}); the weakest direction is mostly `{weakest}` — the outputs barely change along it, so any value there would be a confident wrong answer (more excitation, a longer record, a station nearer the joint, or fewer basis functions)"
    )]
    Undetermined {
        rank: usize,
        needed: usize,
        condition: f64,
        limit: f64,
        weakest: String,
    },
    #[error(
        "connection `{connection}`: the maximum-likelihood estimator takes laws linear in the state (`u`, `v`, `a`, `const`); `{basis}` is not supported yet — measured on the two-beam problem its output-error cost is too rough for the descent (friction −95 %, cubic −26 % with errors of 0.1 %), so it is refused rather than answered wrongly; use `--estimator kalman` (the default)"
    )]
    UnsupportedLaw { connection: String, basis: String },
    #[error("channel `{channel}` has no finite measurements")]
    EmptyChannel { channel: String },
}

/// Options of the maximum-likelihood estimator. Defaults live here.
#[derive(Debug, Clone)]
pub struct MlOptions {
    /// Levenberg–Marquardt iterations per stage at most (default 50).
    pub max_iterations: usize,
    /// Samples in the first prefix of the homotopy; doubled until the whole record (default 100).
    pub first_stage_samples: usize,
    /// Estimate the initial state `z₀` (default true: records need not start at rest).
    pub free_initial_state: bool,
    /// Largest condition number of the column-scaled Fisher information of the connection
    /// parameters before the fit is refused as undetermined (default 1e10).
    pub max_condition: f64,
    /// Largest effect of the hold of the non-linear force on the outputs, in noise standard
    /// deviations (RMS over channels), before the step is halved (default 0.1).
    pub max_discretisation_error: f64,
    /// Sub-steps per sample at most for non-linear laws (default 16).
    pub max_substeps: usize,
    /// Choose the discretisation by likelihood among the exact map and Newmark average
    /// acceleration with 1, 2, 4, … sub-steps (default true; see the module docs).
    pub select_discretisation: bool,
    /// Largest Newmark sub-steps tried (default 64).
    pub max_newmark_substeps: usize,
    /// Iterations of each candidate's refit when choosing the discretisation (default 2).
    pub screen_iterations: usize,
}

impl Default for MlOptions {
    fn default() -> Self {
        Self {
            max_iterations: 50,
            first_stage_samples: 100,
            free_initial_state: true,
            max_condition: 1e10,
            max_discretisation_error: 0.1,
            max_substeps: 16,
            select_discretisation: true,
            max_newmark_substeps: 64,
            screen_iterations: 2,
        }
    }
}

/// What the estimator found.
#[derive(Debug, Clone, Serialize)]
pub struct MlFit {
    /// Connection parameters in `Setup::param_keys` order.
    pub params: Vec<f64>,
    /// Reported standard errors: the larger of the Cramér–Rao bound and the sandwich.
    pub std_errors: Vec<f64>,
    /// Cramér–Rao bound (inverse Fisher information at the estimate, white noise).
    pub crlb: Vec<f64>,
    /// Newey–West sandwich standard errors (residual correlation in time accounted for).
    pub std_errors_sandwich: Vec<f64>,
    /// Fitted noise standard deviation per response channel.
    pub noise_std: Vec<f64>,
    /// Estimated initial state `[u; u̇]` (zeros when not estimated).
    pub initial_state: Vec<f64>,
    /// Portmanteau statistic per channel over `whiteness_lags` lags, divided by the lags
    /// (≈ 1 for white residuals).
    pub whiteness: Vec<f64>,
    pub whiteness_lags: usize,
    /// Per channel: fitted noise / the setup's `noise_std`, when stated.
    pub noise_ratio: Vec<Option<f64>>,
    /// Fit per channel, % (`100·(1 − ‖y − ŷ‖/‖y − ȳ‖)`, as MATLAB's `compare`).
    pub fit_percent: Vec<f64>,
    /// Condition number of the column-scaled Fisher information of the parameters.
    pub condition: f64,
    /// Sub-steps per sample used by the simulation.
    pub substeps: usize,
    /// The discretisation used (chosen by likelihood, see the module docs).
    pub scheme: Scheme,
    /// How the excitation was read between samples (chosen by likelihood).
    pub between: Between,
    /// The models the answer was averaged over and their posterior weights, when the data
    /// did not single one out (empty otherwise; see `average_over_models`).
    #[serde(skip_serializing_if = "Vec::is_empty")]
    pub model_weights: Vec<(String, f64)>,
    /// Measured effect of the non-linear force's hold on the outputs at the estimate, in noise
    /// standard deviations (RMS over channels); 0 for a law linear in the state.
    pub discretisation_error: f64,
    pub discretisation: String,
    /// Levenberg–Marquardt iterations over all stages.
    pub iterations: usize,
    /// `(samples, iterations)` of each stage of the homotopy.
    pub stages: Vec<(usize, usize)>,
    /// Final negative log-likelihood (concentrated), up to a constant.
    pub cost: f64,
    /// Reasons the model does not explain the data (empty when it does).
    pub warnings: Vec<String>,
}

/// Per-sample trace of a simulation, row-major by sample.
#[derive(Debug, Clone, Default)]
pub struct Trace {
    pub n: usize,
    /// Outputs, `n × m`.
    pub y: Vec<f64>,
    /// Total connection force (linear and non-linear terms), `n × q`.
    pub force: Vec<f64>,
    pub delta: Vec<f64>,
    pub delta_v: Vec<f64>,
    pub delta_a: Vec<f64>,
}

/// The non-linear part of one connection's law.
#[derive(Debug, Clone, Default)]
struct NlLaw {
    cubic: f64,
    sign_u: f64,
    sign_v: f64,
    gaps: Vec<(f64, f64)>,
    constant: f64,
}

impl NlLaw {
    fn has_state_terms(&self) -> bool {
        self.cubic != 0.0 || self.sign_u != 0.0 || self.sign_v != 0.0 || !self.gaps.is_empty()
    }

    /// Force with the sign terms at the given signs.
    fn smooth(&self, d: f64) -> f64 {
        let mut f = self.constant + self.cubic * d * d * d;
        for &(g, p) in &self.gaps {
            f += p * gap(d, g);
        }
        f
    }

    fn smooth_slope(&self, d: f64) -> f64 {
        let mut s = 3.0 * self.cubic * d * d;
        for &(g, p) in &self.gaps {
            if d.abs() > g {
                s += p;
            }
        }
        s
    }

    /// Explicit evaluation with `sign(0) = 0`.
    fn explicit(&self, d: f64, v: f64) -> f64 {
        self.smooth(d) + self.sign_u * sgn0(d) + self.sign_v * sgn0(v)
    }

    /// Monotone (so the implicit solve has one root): every term resists.
    fn monotone(&self, g: f64, h: f64) -> bool {
        self.cubic >= 0.0
            && self.sign_u >= 0.0
            && self.sign_v >= 0.0
            && self.gaps.iter().all(|&(_, p)| p >= 0.0)
            && g <= 0.0
            && h <= 0.0
    }

    /// Solve `f = φ(a + g f, b + h f)` with set-valued signs (sticking).
    fn solve(&self, a: f64, g: f64, b: f64, h: f64, f_prev: f64) -> f64 {
        if !self.has_state_terms() {
            return self.constant;
        }
        if !self.monotone(g, h) || (g == 0.0 && h == 0.0) {
            // Not monotone (a trial point with a negative friction, say): one explicit
            // evaluation at the state the previous force predicts.
            return self.explicit(a + g * f_prev, b + h * f_prev);
        }
        // r(f) = f − φ(f) is increasing; its set-valued jumps are at δ = 0 and δ̇ = 0.
        let r = |f: f64, su: f64, sv: f64| {
            f - self.smooth(a + g * f) - self.sign_u * su - self.sign_v * sv
        };
        let side = |x: f64| {
            if x > 0.0 {
                1.0
            } else if x < 0.0 {
                -1.0
            } else {
                0.0
            }
        };
        // Breakpoints: f where δ = 0 (if g ≠ 0) and δ̇ = 0 (if h ≠ 0).
        let mut breaks: Vec<f64> = Vec::with_capacity(2);
        if self.sign_u != 0.0 && g != 0.0 {
            breaks.push(-a / g);
        }
        if self.sign_v != 0.0 && h != 0.0 {
            breaks.push(-b / h);
        }
        breaks.sort_by(f64::total_cmp);
        // Signs just left / right of f (δ, δ̇ decrease with f since g, h ≤ 0).
        let signs_at = |f: f64, eps: f64| (side(a + g * (f + eps)), side(b + h * (f + eps)));
        for &fb in &breaks {
            let tiny = 1e-12 * (1.0 + fb.abs());
            let (su_l, sv_l) = signs_at(fb, -tiny);
            let (su_r, sv_r) = signs_at(fb, tiny);
            let lo = r(fb, su_l, sv_l);
            let hi = r(fb, su_r, sv_r);
            if lo.min(hi) <= 0.0 && 0.0 <= lo.max(hi) {
                return fb;
            }
        }
        // The root is inside one interval between breakpoints, where the signs are fixed.
        let mut edges = vec![f64::NEG_INFINITY];
        edges.extend(breaks.iter().copied());
        edges.push(f64::INFINITY);
        let scale =
            1.0 + f_prev.abs() + self.constant.abs() + self.sign_u.abs() + self.sign_v.abs();
        for w in edges.windows(2) {
            let (l, u) = (w[0], w[1]);
            let mid = if l.is_finite() && u.is_finite() {
                0.5 * (l + u)
            } else if l.is_finite() {
                l + scale
            } else if u.is_finite() {
                u - scale
            } else {
                f_prev
            };
            let (su, sv) = (side(a + g * mid), side(b + h * mid));
            let rr = |f: f64| r(f, su, sv);
            // Bracket within [l, u].
            let (mut lo, mut hi) = (l, u);
            if !lo.is_finite() {
                let mut step = scale;
                lo = if u.is_finite() {
                    u - step
                } else {
                    f_prev - step
                };
                while rr(lo) > 0.0 && step < 1e300 {
                    step *= 4.0;
                    lo = if u.is_finite() {
                        u - step
                    } else {
                        f_prev - step
                    };
                }
            }
            if !hi.is_finite() {
                let mut step = scale;
                hi = if l.is_finite() {
                    l + step
                } else {
                    f_prev + step
                };
                while rr(hi) < 0.0 && step < 1e300 {
                    step *= 4.0;
                    hi = if l.is_finite() {
                        l + step
                    } else {
                        f_prev + step
                    };
                }
            }
            if !(rr(lo) <= 0.0 && rr(hi) >= 0.0) {
                continue;
            }
            // Safeguarded Newton.
            let mut f = f_prev.clamp(lo, hi);
            for _ in 0..100 {
                let v = rr(f);
                if v == 0.0 {
                    break;
                }
                if v < 0.0 {
                    lo = f;
                } else {
                    hi = f;
                }
                let slope = 1.0 - g * self.smooth_slope(a + g * f);
                let mut next = f - v / slope;
                if !(next > lo && next < hi) {
                    next = 0.5 * (lo + hi);
                }
                if (next - f).abs() <= 1e-14 * (1.0 + f.abs()) {
                    f = next;
                    break;
                }
                f = next;
            }
            return f;
        }
        self.explicit(a + g * f_prev, b + h * f_prev)
    }
}

fn sgn0(x: f64) -> f64 {
    if x > 0.0 {
        1.0
    } else if x < 0.0 {
        -1.0
    } else {
        0.0
    }
}

fn gap(d: f64, g: f64) -> f64 {
    if d > g {
        d - g
    } else if d < -g {
        d + g
    } else {
        0.0
    }
}

/// How the model is taken from continuous to discrete time.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
#[serde(rename_all = "lowercase")]
pub enum Scheme {
    /// Matrix exponential (exact for the linear structure; inputs linear over a step).
    Exact,
    /// Newmark average acceleration (the trapezoidal rule), the scheme of `jointid simulate`.
    Newmark,
}

/// A scheme and its sub-steps per sample.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
pub struct Discretisation {
    pub scheme: Scheme,
    pub substeps: usize,
}

impl std::fmt::Display for Discretisation {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self.scheme {
            Scheme::Exact => write!(f, "exact ×{}", self.substeps),
            Scheme::Newmark => write!(f, "Newmark ×{}", self.substeps),
        }
    }
}

/// How the model reads each excitation channel between samples.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
#[serde(rename_all = "lowercase")]
pub enum Between {
    /// The straight line between the two samples (exact for a piecewise-linear force, the
    /// `random` scenario's).
    Linear,
    /// The samples moment-matched to a cubic through their neighbours
    /// ([`crate::estimate::moment_matched`]): a smooth force's mean over each interval.
    Smooth,
}

/// One model the record may have been made with: the discretisation and the excitation
/// between samples. Both are nuisance parameters of the likelihood, decided by the data;
/// where the data cannot single one out, the answer is averaged over them
/// ([`average_over_models`]).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
struct Variant {
    d: Discretisation,
    between: Between,
}

impl std::fmt::Display for Variant {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self.between {
            Between::Linear => write!(f, "{}", self.d),
            Between::Smooth => write!(f, "{} smooth", self.d),
        }
    }
}

/// The discrete-time model at one parameter point.
struct Discrete {
    desc: Discretisation,
    /// Steps the simulation takes per sample: 1 when the sub-steps were composed.
    steps_per_sample: usize,
    Phi: DMatrix<f64>,
    /// `Γ₁` and `Γ₂/h` for the excitation (`ns × ne`) and the non-linear force (`ns × q`).
    G1p: DMatrix<f64>,
    G2p: DMatrix<f64>,
    G1f: DMatrix<f64>,
    G2f: DMatrix<f64>,
    /// `∂δ/∂f₊`, `∂δ̇/∂f₊` of the step's end (q × q).
    Gd: DMatrix<f64>,
    Gv: DMatrix<f64>,
    /// Acceleration read-out `ü = Au·z + Ap·p + Af·f_nl` (n × ·).
    Au: DMatrix<f64>,
    Ap: DMatrix<f64>,
    Af: DMatrix<f64>,
}

/// One sample's map from `s` sub-steps of a first-order-hold map `(Φ, Γ₁, Γ₂)` (inputs
/// linear across the sample): `Φ' = Φˢ`, `Γ₁' = Σⱼ Φʲ Γ₁`, `Γ₂' = Σₖ Φˢ⁻¹⁻ᵏ (k Γ₁ + Γ₂)/s`.
/// A power of two by doubling: with `T₀ = Σ_{j<L} Φʲ` and `T₁ = Σ_{j<L} j Φʲ` acting on the
/// input columns, `Γ₁' = T₀Γ₁` and `Γ₂' = (T₀Γ₂ + (s − 1)T₀Γ₁ − T₁Γ₁)/s` (j = s − 1 − k); a
/// doubling `L → 2L` is `T₀ ← T₀ + ΦᴸT₀`, `T₁ ← T₁ + Φᴸ(T₁ + L T₀)`, `Φᴸ ← ΦᴸΦᴸ`. Why: the
/// sub-step loop ([`compose_by_loop`], kept for other counts) made s products of the state
/// matrix per discretisation, log₂ s here; at 64 sub-steps the loop was most of a
/// likelihood evaluation's cost on short prefixes (the early choice of the discretisation).
#[allow(non_snake_case)]
fn compose_substeps(
    Phi: &DMatrix<f64>,
    g1: &DMatrix<f64>,
    g2: &DMatrix<f64>,
    substeps: usize,
) -> (DMatrix<f64>, DMatrix<f64>, DMatrix<f64>) {
    use crate::dense::product;
    if !substeps.is_power_of_two() {
        return compose_by_loop(Phi, g1, g2, substeps);
    }
    let mut P = Phi.clone();
    let mut a1 = g1.clone();
    let mut a2 = g2.clone();
    let mut b1 = DMatrix::zeros(g1.nrows(), g1.ncols());
    let mut l = 1usize;
    while l < substeps {
        let shifted_b1 = product(&P, &(&b1 + &a1 * (l as f64)));
        b1 += shifted_b1;
        let shifted_a1 = product(&P, &a1);
        a1 += shifted_a1;
        let shifted_a2 = product(&P, &a2);
        a2 += shifted_a2;
        P = product(&P, &P);
        l *= 2;
    }
    let sf = substeps as f64;
    let c2 = (&a2 + &a1 * (sf - 1.0) - &b1) * (1.0 / sf);
    (P, a1, c2)
}

/// [`compose_substeps`] one sub-step after the other.
#[allow(non_snake_case)]
fn compose_by_loop(
    Phi: &DMatrix<f64>,
    g1: &DMatrix<f64>,
    g2: &DMatrix<f64>,
    substeps: usize,
) -> (DMatrix<f64>, DMatrix<f64>, DMatrix<f64>) {
    use crate::dense::product;
    let ns = Phi.nrows();
    let mut P = DMatrix::<f64>::identity(ns, ns);
    let mut c1 = DMatrix::zeros(g1.nrows(), g1.ncols());
    let mut c2 = DMatrix::zeros(g1.nrows(), g1.ncols());
    let sf = substeps as f64;
    for k in (0..substeps).rev() {
        c1 += product(&P, g1);
        c2 += product(&P, &(g1 * (k as f64 / sf) + g2 * (1.0 / sf)));
        P = product(Phi, &P);
    }
    (P, c1, c2)
}

/// Everything fixed for one identification: model, data layout, parameter roles.
pub struct Problem<'a> {
    setup: &'a Setup,
    model: &'a Model,
    n: usize,
    ne: usize,
    q: usize,
    m: usize,
    /// Per parameter: (connection, basis).
    roles: Vec<(usize, Basis)>,
    /// Per connection: the DOFs and signs of `Lc`'s column.
    lc: Vec<Vec<(usize, f64)>>,
    dt: f64,
    excitation: Vec<f64>,
    measured: Vec<f64>,
    samples: usize,
    /// An output or a basis needs the acceleration read-out.
    needs_acc: bool,
    /// Typical displacement (m) and velocity (m/s) from the measurements: finite-difference
    /// steps of the initial state.
    u_scale: f64,
    v_scale: f64,
    /// The component model's damping and stiffness are positive semi-definite (see
    /// [`Problem::passive`]).
    passive_structure: bool,
}

impl<'a> Problem<'a> {
    /// Whether the structure with the connection law `p` is passive: damping and stiffness
    /// positive semi-definite — the component's are, and no `v` or `u` term is negative —
    /// with a positive definite mass (which [`Problem::discretise`] requires). Its
    /// eigenvalues then have no positive real part (`λ²m + λc + k = 0` with `m > 0`,
    /// `c, k ≥ 0`), so neither the exact map nor the trapezoidal (Newmark) one, nor their
    /// powers, has a spectral radius above 1: the stability test of a descent's step
    /// needs no eigenvalues. (`false` only means "not shown passive this way".) The same
    /// decisions as the eigenvalues', but where the Schur form of a rigid-body mode's Jordan
    /// block at 1 reads a radius of 1 + ~2e-7 (no joint stiffness): that test would refuse
    /// such a step on records of more than ~10⁷ sub-steps, this one does not.
    fn passive(&self, p: &[f64]) -> bool {
        self.passive_structure
            && self
                .roles
                .iter()
                .zip(p)
                .all(|(&(_, b), &v)| !matches!(b, Basis::U | Basis::V) || v >= 0.0)
    }

    pub fn new(setup: &'a Setup, model: &'a Model, data: &TestData) -> Result<Self, MlError> {
        for conn in &setup.connections {
            if let Some(b) = conn
                .basis
                .iter()
                .find(|b| matches!(b, Basis::U3 | Basis::SignU | Basis::SignV | Basis::Gap(_)))
            {
                return Err(MlError::UnsupportedLaw {
                    connection: conn.name.clone(),
                    basis: b.label(),
                });
            }
        }
        if !model.has_dense() {
            return Err(MlError::NeedsDense { dofs: model.n() });
        }
        let n = model.n();
        let ne = model.Lp.ncols();
        let q = model.Lc.ncols();
        let m = model.stations.len();
        let roles = setup
            .connections
            .iter()
            .enumerate()
            .flat_map(|(c, conn)| conn.basis.iter().map(move |b| (c, *b)))
            .collect();
        let lc = (0..q)
            .map(|c| {
                (0..n)
                    .filter(|&i| model.Lc[(i, c)] != 0.0)
                    .map(|i| (i, model.Lc[(i, c)]))
                    .collect()
            })
            .collect();
        let samples = data.len();
        let mut excitation = Vec::with_capacity(samples * ne);
        let mut measured = Vec::with_capacity(samples * m);
        for i in 0..samples {
            for k in 0..ne {
                excitation.push(data.excitation[i].get(k).copied().unwrap_or(0.0));
            }
            for k in 0..m {
                measured.push(data.response[i].get(k).copied().unwrap_or(f64::NAN));
            }
        }
        for k in 0..m {
            if !(0..samples).any(|i| measured[i * m + k].is_finite()) {
                return Err(MlError::EmptyChannel {
                    channel: setup
                        .sensors
                        .get(k)
                        .map_or(format!("{k}"), |s| s.name.clone()),
                });
            }
        }
        let needs_acc = model
            .stations
            .iter()
            .any(|s| s.quantity == Quantity::Acceleration)
            || setup
                .connections
                .iter()
                .any(|c| c.basis.contains(&Basis::A));
        let rms_of = |want: Quantity| -> Option<f64> {
            let ks: Vec<usize> = (0..m)
                .filter(|&k| model.stations[k].quantity == want)
                .collect();
            if ks.is_empty() {
                return None;
            }
            let (mut s, mut c) = (0.0, 0usize);
            for i in 0..samples {
                for &k in &ks {
                    let v = measured[i * m + k];
                    if v.is_finite() {
                        s += v * v;
                        c += 1;
                    }
                }
            }
            Some((s / c.max(1) as f64).sqrt()).filter(|v| *v > 0.0)
        };
        let dt = setup.dt_s;
        let u = rms_of(Quantity::Displacement);
        let v = rms_of(Quantity::Velocity);
        let a = rms_of(Quantity::Acceleration);
        let v_scale = v.or(u.map(|u| u / dt)).or(a.map(|a| a * dt)).unwrap_or(1.0);
        let u_scale = u.unwrap_or(v_scale * dt);
        // (Symmetric to the bit, finite, no negative eigenvalue.)
        let psd = |a: &DMatrix<f64>| {
            a.iter().all(|x| x.is_finite())
                && *a == a.transpose()
                && a.clone().symmetric_eigen().eigenvalues.min() >= 0.0
        };
        Ok(Self {
            passive_structure: psd(&model.C) && psd(&model.K),
            needs_acc,
            u_scale,
            v_scale,
            setup,
            model,
            n,
            ne,
            q,
            m,
            roles,
            lc,
            dt: setup.dt_s,
            excitation,
            measured,
            samples,
        })
    }

    fn n_params(&self) -> usize {
        self.roles.len()
    }

    fn describe(&self, p: &[f64]) -> String {
        let keys = self.setup.param_keys();
        let parts: Vec<String> = keys
            .iter()
            .zip(p)
            .map(|(k, v)| format!("{k} = {v:.4e}"))
            .collect();
        format!("[{}]", parts.join(", "))
    }

    fn laws(&self, p: &[f64]) -> Vec<NlLaw> {
        let mut laws = vec![NlLaw::default(); self.q];
        for (&(c, b), &v) in self.roles.iter().zip(p) {
            let l = &mut laws[c];
            match b {
                Basis::U3 => l.cubic += v,
                Basis::SignU => l.sign_u += v,
                Basis::SignV => l.sign_v += v,
                Basis::Gap(g) => l.gaps.push((g, v)),
                Basis::Const(k) => l.constant += v * k,
                Basis::U | Basis::V | Basis::A => {}
            }
        }
        laws
    }

    /// True when the law has terms that depend non-linearly on the state.
    fn law_is_nonlinear(&self) -> bool {
        self.roles
            .iter()
            .any(|(_, b)| matches!(b, Basis::U3 | Basis::SignU | Basis::SignV | Basis::Gap(_)))
    }

    fn add_llt(&self, a: &mut DMatrix<f64>, c: usize, v: f64) {
        for &(i, si) in &self.lc[c] {
            for &(j, sj) in &self.lc[c] {
                a[(i, j)] += v * si * sj;
            }
        }
    }

    fn discretise(&self, p: &[f64], disc: Discretisation) -> Result<Discrete, MlError> {
        // (`dense::product`: nalgebra's products to the bit, without matrixmultiply's packing.)
        use crate::dense::product;
        let Discretisation { scheme, substeps } = disc;
        let (n, ne, q) = (self.n, self.ne, self.q);
        let mut M = self.model.M.clone();
        let mut C = self.model.C.clone();
        let mut K = self.model.K.clone();
        for (&(c, b), &v) in self.roles.iter().zip(p) {
            match b {
                Basis::U => self.add_llt(&mut K, c, v),
                Basis::V => self.add_llt(&mut C, c, v),
                Basis::A => self.add_llt(&mut M, c, v),
                _ => {}
            }
        }
        let Some(ch) = M.clone().cholesky() else {
            return Err(MlError::MassNotPositive {
                params: self.describe(p),
            });
        };
        let Minv = ch.inverse();
        let A21 = -product(&Minv, &K);
        let A22 = -product(&Minv, &C);
        let Bp = product(&Minv, &self.model.Lp);
        let Bf = -product(&Minv, &self.model.Lc);
        let h = self.dt / substeps as f64;
        let nu = ne + q;
        let ns = 2 * n;
        let (Phi, g1, g2): (DMatrix<f64>, DMatrix<f64>, DMatrix<f64>) = match scheme {
            Scheme::Exact => {
                // Balance the state: z̃ = [u; u̇/ω] with ω from the stiffest term, so the
                // exponent's blocks are of one size (the matrix exponential's accuracy is
                // relative to its norm).
                let w = A21.amax().sqrt().max(A22.amax()).max(1.0 / h);
                let na = ns + 2 * nu;
                let mut E = DMatrix::zeros(na, na);
                for i in 0..n {
                    E[(i, n + i)] = w * h;
                    for j in 0..n {
                        E[(n + i, j)] = A21[(i, j)] / w * h;
                        E[(n + i, n + j)] = A22[(i, j)] * h;
                    }
                    for k in 0..ne {
                        E[(n + i, ns + k)] = Bp[(i, k)] / w * h;
                    }
                    for k in 0..q {
                        E[(n + i, ns + ne + k)] = Bf[(i, k)] / w * h;
                    }
                }
                // ẇ = r, ṙ = 0 with time scaled by h: the (2,3) block is I·h, r per second.
                for k in 0..nu {
                    E[(ns + k, ns + nu + k)] = h;
                }
                let X = E.exp();
                // Undo the balance: Φ = T Φ̃ T⁻¹, Γ = T Γ̃ with T = diag(I, ωI); Γ₂ multiplies
                // the rate (w₊ − w)/h, so store Γ₂/h.
                let sc = |i: usize| if i < n { 1.0 } else { w };
                (
                    DMatrix::from_fn(ns, ns, |i, j| X[(i, j)] * sc(i) / sc(j)),
                    DMatrix::from_fn(ns, nu, |i, k| X[(i, ns + k)] * sc(i)),
                    DMatrix::from_fn(ns, nu, |i, k| X[(i, ns + nu + k)] * sc(i) / h),
                )
            }
            Scheme::Newmark => {
                // Newmark average acceleration = the trapezoidal rule on [u; u̇] with the
                // equilibrium acceleration at both ends: (I − hF/2) z₊ = (I + hF/2) z +
                // h·B·w + (h/2)·B·(w₊ − w).
                let mut F = DMatrix::zeros(ns, ns);
                let mut B = DMatrix::zeros(ns, nu);
                for i in 0..n {
                    F[(i, n + i)] = 1.0;
                    for j in 0..n {
                        F[(n + i, j)] = A21[(i, j)];
                        F[(n + i, n + j)] = A22[(i, j)];
                    }
                    for k in 0..ne {
                        B[(n + i, k)] = Bp[(i, k)];
                    }
                    for k in 0..q {
                        B[(n + i, ne + k)] = Bf[(i, k)];
                    }
                }
                let I = DMatrix::<f64>::identity(ns, ns);
                let lhs = &I - &F * (0.5 * h);
                let Some(lu) = lhs.lu().try_inverse() else {
                    return Err(MlError::MassNotPositive {
                        params: self.describe(p),
                    });
                };
                let Phi = product(&lu, &(&I + &F * (0.5 * h)));
                let g1 = product(&lu, &B) * h;
                let g2 = &g1 * 0.5;
                (Phi, g1, g2)
            }
        };
        // Without state-dependent connection forces the sub-steps compose into one sample
        // map of the same first-order-hold form (inputs linear across the sample):
        // Φ' = Φˢ, Γ₁' = Σⱼ Φʲ Γ₁, Γ₂' = Σₖ Φˢ⁻¹⁻ᵏ (k Γ₁ + Γ₂)/s.
        let composed = substeps > 1 && !self.law_is_nonlinear();
        let (Phi, g1, g2) = if composed {
            compose_substeps(&Phi, &g1, &g2, substeps)
        } else {
            (Phi, g1, g2)
        };
        let g1 = |k: usize| g1.column(k).into_owned();
        let g2 = |k: usize| g2.column(k).into_owned();
        let G1p = DMatrix::from_columns(&(0..ne).map(g1).collect::<Vec<_>>());
        let G2p = DMatrix::from_columns(&(0..ne).map(g2).collect::<Vec<_>>());
        let G1f = DMatrix::from_columns(&(0..q).map(|k| g1(ne + k)).collect::<Vec<_>>());
        let G2f = DMatrix::from_columns(&(0..q).map(|k| g2(ne + k)).collect::<Vec<_>>());
        let G1p = if ne == 0 { DMatrix::zeros(ns, 0) } else { G1p };
        let G2p = if ne == 0 { DMatrix::zeros(ns, 0) } else { G2p };
        let G1f = if q == 0 { DMatrix::zeros(ns, 0) } else { G1f };
        let G2f = if q == 0 { DMatrix::zeros(ns, 0) } else { G2f };
        let mut Gd = DMatrix::zeros(q, q);
        let mut Gv = DMatrix::zeros(q, q);
        for c in 0..q {
            for k in 0..q {
                for &(i, s) in &self.lc[c] {
                    Gd[(c, k)] += s * G2f[(i, k)];
                    Gv[(c, k)] += s * G2f[(n + i, k)];
                }
            }
        }
        let mut Au = DMatrix::zeros(n, ns);
        Au.columns_mut(0, n).copy_from(&A21);
        Au.columns_mut(n, n).copy_from(&A22);
        Ok(Discrete {
            desc: disc,
            steps_per_sample: if composed { 1 } else { substeps },
            Phi,
            G1p,
            G2p,
            G1f,
            G2f,
            Gd,
            Gv,
            Au,
            Ap: Bp,
            Af: Bf,
        })
    }

    fn excitation_at(&self, i: usize, k: usize) -> f64 {
        self.excitation[i * self.ne + k]
    }

    /// Simulate the first `len` samples. Returns the sample where the state stopped being
    /// finite, if it did.
    fn simulate(
        &self,
        disc: &Discrete,
        p: &[f64],
        z0: &DVector<f64>,
        len: usize,
        full: bool,
        out: &mut Trace,
    ) -> Result<(), usize> {
        use crate::dense::{Op, gemv};
        let (n, ne, q, m) = (self.n, self.ne, self.q, self.m);
        let substeps = disc.steps_per_sample;
        let laws = self.laws(p);
        // Linear connection terms, for the reported total force.
        let mut lin = vec![(0.0, 0.0, 0.0); q];
        for (&(c, b), &v) in self.roles.iter().zip(p) {
            match b {
                Basis::U => lin[c].0 += v,
                Basis::V => lin[c].1 += v,
                Basis::A => lin[c].2 += v,
                _ => {}
            }
        }
        out.n = len;
        out.y.clear();
        out.y.resize(len * m, 0.0);
        for v in [
            &mut out.force,
            &mut out.delta,
            &mut out.delta_v,
            &mut out.delta_a,
        ] {
            v.clear();
            v.resize(len * q, 0.0);
        }
        let ns = 2 * n;
        let mut z = z0.clone();
        let mut zs = DVector::zeros(ns);
        let mut f = DVector::zeros(q);
        let mut f_next = DVector::zeros(q);
        let mut pe = DVector::zeros(ne);
        let mut pe_next = DVector::zeros(ne);
        let mut dp = DVector::zeros(ne);
        let mut pa = DVector::zeros(ne);
        let mut pb = DVector::zeros(ne);
        let mut acc = DVector::zeros(n);
        let d_of = |z: &DVector<f64>, c: usize, off: usize| -> f64 {
            self.lc[c].iter().map(|&(i, s)| s * z[off + i]).sum()
        };
        for c in 0..q {
            f[c] = laws[c].explicit(d_of(&z, c, 0), d_of(&z, c, n));
        }
        for k in 0..ne {
            pe[k] = if len > 0 {
                self.excitation_at(0, k)
            } else {
                0.0
            };
        }
        // A law with no non-linear term and no constant leaves the connection force's
        // non-linear part at zero: its products and its implicit solve are skipped (they
        // would add zeros).
        let force_free = laws
            .iter()
            .all(|l| !l.has_state_terms() && l.constant == 0.0);
        // Where each station reads: an entry of the state, or of the accelerations.
        let readout: Vec<(usize, bool)> = self
            .model
            .stations
            .iter()
            .map(|st| match st.quantity {
                Quantity::Displacement => (st.dof, false),
                Quantity::Velocity => (n + st.dof, false),
                Quantity::Acceleration => (st.dof, true),
            })
            .collect();
        // The sub-steps' ends as fractions of the sample (one division each, not one per
        // sample: its latency stalled the loop).
        let fractions: Vec<f64> = (1..=substeps).map(|s| s as f64 / substeps as f64).collect();
        // Not finite, or beyond 1e100: diverged. (One branch-free pass over the bits: the
        // magnitude's bits exceed 1e100's for a larger value, ±∞ and NaN alike; the two
        // passes it replaces were a third of the loop's own time.)
        const MAGNITUDE: u64 = 0x7fff_ffff_ffff_ffff;
        let limit = 1e100f64.to_bits();
        let diverged = |z: &DVector<f64>| {
            z.iter()
                .fold(false, |bad, v| bad | ((v.to_bits() & MAGNITUDE) > limit))
        };
        if force_free && substeps == 1 && !(self.needs_acc || full) {
            // One map per sample and no connection force: the loop below without its
            // sub-step bookkeeping (the same operations on the same numbers: the hold's end
            // `1·w₊` is `w₊`), which took as long as the map's product. (Its read-out and
            // traces repeat the loop's on purpose: shared through a closure, the whole
            // identification took 2 % longer.)
            for i in 0..len {
                let zv = z.as_slice();
                for (y, &(at, _)) in out.y[i * m..(i + 1) * m].iter_mut().zip(&readout) {
                    *y = zv[at];
                }
                for c in 0..q {
                    let (d, dv) = (d_of(&z, c, 0), d_of(&z, c, n));
                    let da: f64 = self.lc[c].iter().map(|&(j, s)| s * acc[j]).sum();
                    out.delta[i * q + c] = d;
                    out.delta_v[i * q + c] = dv;
                    out.delta_a[i * q + c] = da;
                    out.force[i * q + c] = f[c] + lin[c].0 * d + lin[c].1 * dv + lin[c].2 * da;
                }
                if i + 1 == len {
                    break;
                }
                for k in 0..ne {
                    pe_next[k] = self.excitation_at(i + 1, k);
                    dp[k] = pe_next[k] - pe[k];
                }
                gemv(&mut zs, &disc.Phi, &z, Op::Set);
                gemv(&mut zs, &disc.G1p, &pe, Op::Add);
                gemv(&mut zs, &disc.G2p, &dp, Op::Add);
                std::mem::swap(&mut z, &mut zs);
                pe.copy_from(&pe_next);
                if diverged(&z) {
                    return Err(i + 1);
                }
            }
            return Ok(());
        }
        for i in 0..len {
            // Read-out at sample i.
            if self.needs_acc || full {
                gemv(&mut acc, &disc.Au, &z, Op::Set);
                gemv(&mut acc, &disc.Ap, &pe, Op::Add);
                gemv(&mut acc, &disc.Af, &f, Op::Add);
            }
            let (zv, av) = (z.as_slice(), acc.as_slice());
            for (y, &(at, from_acc)) in out.y[i * m..(i + 1) * m].iter_mut().zip(&readout) {
                *y = if from_acc { av[at] } else { zv[at] };
            }
            for c in 0..q {
                let (d, dv) = (d_of(&z, c, 0), d_of(&z, c, n));
                let da: f64 = self.lc[c].iter().map(|&(j, s)| s * acc[j]).sum();
                out.delta[i * q + c] = d;
                out.delta_v[i * q + c] = dv;
                out.delta_a[i * q + c] = da;
                out.force[i * q + c] = f[c] + lin[c].0 * d + lin[c].1 * dv + lin[c].2 * da;
            }
            if i + 1 == len {
                break;
            }
            // Advance to sample i + 1 in `substeps` exact steps, excitation linear.
            for k in 0..ne {
                pe_next[k] = self.excitation_at(i + 1, k);
            }
            pa.copy_from(&pe);
            for &t in &fractions {
                pb.copy_from(&pe);
                pb.axpy(t, &pe_next, 1.0 - t);
                dp.copy_from(&pb);
                dp -= &pa;
                // (`dense::gemv`: nalgebra's `gemv` to the bit, in wider registers.)
                gemv(&mut zs, &disc.Phi, &z, Op::Set);
                gemv(&mut zs, &disc.G1p, &pa, Op::Add);
                gemv(&mut zs, &disc.G2p, &dp, Op::Add);
                if force_free {
                    std::mem::swap(&mut z, &mut zs);
                    pa.copy_from(&pb);
                    continue;
                }
                gemv(&mut zs, &disc.G1f, &f, Op::Add);
                gemv(&mut zs, &disc.G2f, &f, Op::Subtract);
                // Implicit force at the sub-step's end (Gauss–Seidel over connections).
                f_next.copy_from(&f);
                for _sweep in 0..(if q > 1 { 30 } else { 1 }) {
                    let mut change: f64 = 0.0;
                    for c in 0..q {
                        let mut a = d_of(&zs, c, 0);
                        let mut b = d_of(&zs, c, n);
                        for k in 0..q {
                            if k != c {
                                a += disc.Gd[(c, k)] * f_next[k];
                                b += disc.Gv[(c, k)] * f_next[k];
                            }
                        }
                        let new = laws[c].solve(a, disc.Gd[(c, c)], b, disc.Gv[(c, c)], f_next[c]);
                        change = change.max((new - f_next[c]).abs());
                        f_next[c] = new;
                    }
                    if change <= 1e-13 * (1.0 + f_next.amax()) {
                        break;
                    }
                }
                gemv(&mut zs, &disc.G2f, &f_next, Op::Add);
                std::mem::swap(&mut z, &mut zs);
                f.copy_from(&f_next);
                pa.copy_from(&pb);
            }
            pe.copy_from(&pe_next);
            if diverged(&z) {
                return Err(i + 1);
            }
        }
        Ok(())
    }
}

/// Weighted-fit state during the iterations.
#[derive(Clone)]
struct Point {
    p: Vec<f64>,
    z0: DVector<f64>,
}

/// Concentrated negative log-likelihood of a trace over `len` samples, and the per-channel
/// sums of squared residuals.
fn cost(prob: &Problem, tr: &Trace, len: usize) -> (f64, Vec<f64>, Vec<usize>) {
    let m = prob.m;
    let mut ssr = vec![0.0; m];
    let mut cnt = vec![0usize; m];
    for i in 0..len {
        for k in 0..m {
            let y = prob.measured[i * m + k];
            if y.is_finite() {
                let e = y - tr.y[i * m + k];
                ssr[k] += e * e;
                cnt[k] += 1;
            }
        }
    }
    let mut l = 0.0;
    for k in 0..m {
        if cnt[k] > 0 {
            let floor = 1e-300;
            l += 0.5 * cnt[k] as f64 * (ssr[k] / cnt[k] as f64).max(floor).ln();
        }
    }
    (l, ssr, cnt)
}

/// Channel noise floor: keeps a channel the model fits exactly (noise-free data) from taking
/// all the weight.
fn sigma_floor(prob: &Problem, k: usize, len: usize) -> f64 {
    let m = prob.m;
    let rms = ((0..len)
        .map(|i| prob.measured[i * m + k])
        .filter(|v| v.is_finite())
        .map(|v| v * v)
        .sum::<f64>()
        / len.max(1) as f64)
        .sqrt();
    1e-10 * rms.max(f64::MIN_POSITIVE)
}

struct Jacobian {
    /// Weighted residuals (len·m).
    r: Vec<f64>,
    /// Weighted sensitivities, column-major: `cols[j][i·m + k]`.
    cols: Vec<Vec<f64>>,
}

#[allow(clippy::too_many_arguments)]
fn jacobian(
    prob: &Problem,
    pt: &Point,
    base: &Trace,
    disc: &Discrete,
    len: usize,
    sigma: &[f64],
    active: &[usize],
    free_z0: bool,
    central: bool,
) -> Result<Jacobian, MlError> {
    let m = prob.m;
    let mut r = vec![0.0; len * m];
    for i in 0..len {
        for k in 0..m {
            let y = prob.measured[i * m + k];
            r[i * m + k] = if y.is_finite() {
                (y - base.y[i * m + k]) / sigma[k]
            } else {
                0.0
            };
        }
    }
    let column = |tr: &Trace, tr2: Option<&Trace>, step: f64| -> Vec<f64> {
        let mut col = vec![0.0; len * m];
        for i in 0..len {
            for k in 0..m {
                if prob.measured[i * m + k].is_finite() {
                    let lo = tr2.map_or(base.y[i * m + k], |t| t.y[i * m + k]);
                    col[i * m + k] = (tr.y[i * m + k] - lo) / step / sigma[k];
                }
            }
        }
        col
    };
    // The parameters' central differences and the initial state's free response are
    // independent: on every core unless already inside a parallel descent
    // (`par::map_unless_nested`); each column is computed as one after the other would be.
    let free_response = free_z0 && !prob.law_is_nonlinear() && disc.steps_per_sample == 1;
    let parts: Vec<Option<usize>> = active
        .iter()
        .map(|&j| Some(j))
        .chain(free_response.then_some(None))
        .collect();
    let computed =
        crate::par::map_unless_nested(&parts, |part| -> Result<Vec<Vec<f64>>, MlError> {
            let Some(j) = *part else {
                return Ok(free_response_columns(prob, disc, len, sigma));
            };
            let b = prob.roles[j].1;
            let typical = basis_rms_scale(prob, base, j, len);
            let step = 1e-5 * pt.p[j].abs().max(typical.min(1e300));
            let mut plus = pt.p.clone();
            plus[j] += step;
            let mut minus = pt.p.clone();
            minus[j] -= step;
            let linear = matches!(b, Basis::U | Basis::V | Basis::A);
            let dp = if linear {
                prob.discretise(&plus, disc.desc)?
            } else {
                prob.discretise(&pt.p, disc.desc)?
            };
            let mut tr = Trace::default();
            let ok1 = prob.simulate(&dp, &plus, &pt.z0, len, false, &mut tr);
            if !central {
                return Ok(vec![if ok1.is_err() {
                    vec![0.0; len * m]
                } else {
                    column(&tr, None, step)
                }]);
            }
            let dm = if linear {
                prob.discretise(&minus, disc.desc)?
            } else {
                prob.discretise(&pt.p, disc.desc)?
            };
            let mut tr2 = Trace::default();
            let ok2 = prob.simulate(&dm, &minus, &pt.z0, len, false, &mut tr2);
            Ok(vec![if ok1.is_err() || ok2.is_err() {
                vec![0.0; len * m]
            } else {
                column(&tr, Some(&tr2), 2.0 * step)
            }])
        });
    let mut cols = Vec::new();
    for part in computed {
        cols.extend(part?);
    }
    if free_z0 && !free_response {
        let ns = 2 * prob.n;
        let nz = prob.n;
        let mut tr = Trace::default();
        for s in 0..ns {
            let scale = if s < nz { prob.u_scale } else { prob.v_scale };
            let step = 1e-6 * (scale + pt.z0[s].abs());
            let mut z = pt.z0.clone();
            z[s] += step;
            if prob.simulate(disc, &pt.p, &z, len, false, &mut tr).is_err() {
                cols.push(vec![0.0; len * m]);
            } else {
                cols.push(column(&tr, None, step));
            }
        }
    }
    Ok(Jacobian { r, cols })
}

/// The stations' read-out rows `H` (m × 2n): the outputs' part that is linear in the state
/// (a displacement or velocity reads one entry; an acceleration the row of `Au`).
#[allow(non_snake_case)]
fn readout_rows(prob: &Problem, disc: &Discrete) -> DMatrix<f64> {
    let n = prob.n;
    let mut H = DMatrix::zeros(prob.m, 2 * n);
    for (k, st) in prob.model.stations.iter().enumerate() {
        match st.quantity {
            Quantity::Displacement => H[(k, st.dof)] = 1.0,
            Quantity::Velocity => H[(k, n + st.dof)] = 1.0,
            Quantity::Acceleration => H.row_mut(k).copy_from(&disc.Au.row(st.dof)),
        }
    }
    H
}

/// The outputs' sensitivities to the initial state `z₀` when they are affine in it (a law
/// linear in the state, one map per sample): the free response `y_i = H Φ^i z₀`, its
/// read-out rows `H Φ^i` (m × 2n per sample) propagated instead of 2n simulations; one
/// column per entry of `z₀`, divided by the channel's noise level.
fn free_response_columns(
    prob: &Problem,
    disc: &Discrete,
    len: usize,
    sigma: &[f64],
) -> Vec<Vec<f64>> {
    let (m, n) = (prob.m, prob.n);
    let ns = 2 * n;
    let mut W = readout_rows(prob, disc);
    let mut zc: Vec<Vec<f64>> = vec![vec![0.0; len * m]; ns];
    let mut next = DMatrix::zeros(m, ns);
    for i in 0..len {
        for k in 0..m {
            if prob.measured[i * m + k].is_finite() {
                for (s, col) in zc.iter_mut().enumerate() {
                    col[i * m + k] = W[(k, s)] / sigma[k];
                }
            }
        }
        // (`dense::product_into`: nalgebra's `W Φ` to the bit, without its packing.)
        crate::dense::product_into(&mut next, &W, &disc.Phi);
        std::mem::swap(&mut W, &mut next);
    }
    zc
}

/// The column-scaled normal equations `(JᵀJ, Jᵀr)` and the columns' scales.
type NormalEquations = (DMatrix<f64>, DVector<f64>, Vec<f64>);

/// Normal equations of the column-scaled Jacobian at `pt` over the first `len` samples:
/// [`normal`] of [`jacobian`], but without the initial state's columns where the outputs are
/// affine in it (a law linear in the state, one map per sample, every output of the prefix
/// measured). There the free response `Zᵢ = D H Φⁱ` (`D` the channels' `1/σ`) enters the
/// normal equations only through the observability Gramian `Σᵢ ZᵢᵀZᵢ`, summed by doubling
/// (`G₂ₗ = Gₗ + Φˡᵀ Gₗ Φˡ`), and the products `Σᵢ Zᵢᵀ vᵢ` with the residual and the
/// parameters' columns, one backward pass (`λ ← Φᵀλ + HᵀD vᵢ`). Why: the 2n columns of
/// length m × len and their pairwise products were half of an identification's
/// instructions (the read-out rows `H Φⁱ` propagated at every sample, then 253 dot
/// products of 24,000 terms on the two-beam problem); the same sums, taken in another
/// order, agree to rounding.
#[allow(clippy::too_many_arguments)]
#[allow(non_snake_case)]
fn normal_equations(
    prob: &Problem,
    pt: &Point,
    base: &Trace,
    disc: &Discrete,
    len: usize,
    sigma: &[f64],
    active: &[usize],
    free_z0: bool,
) -> Result<NormalEquations, MlError> {
    let m = prob.m;
    let implicit = free_z0
        && !prob.law_is_nonlinear()
        && disc.steps_per_sample == 1
        && prob.measured[..len * m].iter().all(|y| y.is_finite());
    if !implicit {
        return Ok(normal(&jacobian(
            prob, pt, base, disc, len, sigma, active, free_z0, false,
        )?));
    }
    // The residual and the parameters' columns (no initial-state columns).
    let jac = jacobian(prob, pt, base, disc, len, sigma, active, false, false)?;
    let na = jac.cols.len();
    let ns = 2 * prob.n;
    let nc = na + ns;
    // Read-out rows over the noise levels: `D H`.
    let mut H = readout_rows(prob, disc);
    for (k, s) in sigma.iter().enumerate() {
        let w = 1.0 / s;
        H.row_mut(k).iter_mut().for_each(|h| *h *= w);
    }
    // Backward pass: `λ = Σᵢ Φⁱᵀ Hᵀ D vᵢ` for every column `v` (the parameters', then the
    // residual) at once.
    // (`HᵀD vᵢ` by the read-out rows' non-zeros: a displacement or velocity station reads
    // one state.)
    let rows: Vec<Vec<(usize, f64)>> = (0..m)
        .map(|k| {
            (0..ns)
                .filter(|&s| H[(k, s)] != 0.0)
                .map(|s| (s, H[(k, s)]))
                .collect()
        })
        .collect();
    let columns: Vec<&[f64]> = jac
        .cols
        .iter()
        .map(Vec::as_slice)
        .chain(std::iter::once(jac.r.as_slice()))
        .collect();
    let PhiT = disc.Phi.transpose();
    let mut lam = DMatrix::zeros(ns, na + 1);
    let mut next = DMatrix::zeros(ns, na + 1);
    for i in (0..len).rev() {
        crate::dense::product_into(&mut next, &PhiT, &lam);
        for (k, row) in rows.iter().enumerate() {
            for (c, col) in columns.iter().enumerate() {
                let x = col[i * m + k];
                for &(s, h) in row {
                    next[(s, c)] += h * x;
                }
            }
        }
        std::mem::swap(&mut lam, &mut next);
    }
    // The Gramian `Σ_{i<len} Φⁱᵀ HᵀD²H Φⁱ` by doubling over the bits of `len`.
    // (`dense::product`: small products without matrixmultiply's packing.)
    use crate::dense::product;
    let mut block = product(&H.transpose(), &H); // G over a block of `size` samples
    let mut power = disc.Phi.clone(); // Φ^size
    let mut gram = DMatrix::zeros(ns, ns);
    let mut offset = DMatrix::identity(ns, ns); // Φ^(samples summed so far)
    let mut rest = len;
    let mut first = true;
    while rest > 0 {
        if rest & 1 == 1 {
            if first {
                // Φ⁰: the block itself.
                gram += &block;
                offset = power.clone();
                first = false;
            } else {
                gram += product(&offset.transpose(), &product(&block, &offset));
                offset = product(&offset, &power);
            }
        }
        rest >>= 1;
        if rest > 0 {
            let shifted = product(&power.transpose(), &product(&block, &power));
            block += shifted;
            power = product(&power, &power);
        }
    }
    // The unscaled normal equations in [`normal`]'s order: parameters, then `z₀`.
    let mut A = DMatrix::zeros(nc, nc);
    let mut g = DVector::zeros(nc);
    for a in 0..na {
        let others: Vec<&[f64]> = jac.cols[a..]
            .iter()
            .map(Vec::as_slice)
            .chain(std::iter::once(jac.r.as_slice()))
            .collect();
        let sums = dots(&jac.cols[a], &others);
        for b in a..na {
            A[(a, b)] = sums[b - a];
            A[(b, a)] = sums[b - a];
        }
        g[a] = sums[na - a];
        for s in 0..ns {
            A[(a, na + s)] = lam[(s, a)];
            A[(na + s, a)] = lam[(s, a)];
        }
    }
    for s in 0..ns {
        for t in 0..ns {
            A[(na + s, na + t)] = 0.5 * (gram[(s, t)] + gram[(t, s)]);
        }
        g[na + s] = lam[(s, na)];
    }
    Ok(column_scaled(A, g))
}

/// The normal equations `(A, g)` with every column scaled to unit norm (`Aₐₐ = 1`; a column
/// of zero or non-finite norm keeps scale 1), and the scales.
#[allow(non_snake_case)]
fn column_scaled(mut A: DMatrix<f64>, mut g: DVector<f64>) -> NormalEquations {
    let nc = A.nrows();
    let scale: Vec<f64> = (0..nc)
        .map(|a| {
            let s = A[(a, a)].sqrt();
            if s > 0.0 && s.is_finite() { s } else { 1.0 }
        })
        .collect();
    for a in 0..nc {
        for b in 0..nc {
            A[(a, b)] /= scale[a] * scale[b];
        }
        g[a] /= scale[a];
    }
    (A, g, scale)
}

/// Normal equations of the column-scaled Jacobian.
#[allow(non_snake_case)]
fn normal(jac: &Jacobian) -> NormalEquations {
    let nc = jac.cols.len();
    let mut A = DMatrix::zeros(nc, nc);
    let mut g = DVector::zeros(nc);
    for a in 0..nc {
        // `sums[b − a]`: `Σᵢ colₐ[i]·col_b[i]` for `b ≥ a` (`b = nc`: the residual).
        let others: Vec<&[f64]> = jac.cols[a..]
            .iter()
            .map(Vec::as_slice)
            .chain(std::iter::once(jac.r.as_slice()))
            .collect();
        let sums = dots(&jac.cols[a], &others);
        for b in a..nc {
            A[(a, b)] = sums[b - a];
            A[(b, a)] = sums[b - a];
        }
        g[a] = sums[nc - a];
    }
    column_scaled(A, g)
}

/// `Σᵢ x[i]·y[i]` for every `y` of `ys`, each the sequential chain from −0 that
/// `Iterator::sum` makes (a rounded product, then a rounded add, in the order of `i`), so
/// the same bits; four chains advance together. Why: one dependent chain per pair waits
/// on its add's latency at every term (the normal equations of a 24-column Jacobian were a
/// fifth of an identification's instructions); four independent chains fill that wait.
fn dots(x: &[f64], ys: &[&[f64]]) -> Vec<f64> {
    let mut out = Vec::with_capacity(ys.len());
    for group in ys.chunks(4) {
        if let [y0, y1, y2, y3] = group {
            let n = x
                .len()
                .min(y0.len())
                .min(y1.len())
                .min(y2.len())
                .min(y3.len());
            let (mut s0, mut s1, mut s2, mut s3) = (-0.0, -0.0, -0.0, -0.0);
            for i in 0..n {
                let xi = x[i];
                s0 += xi * y0[i];
                s1 += xi * y1[i];
                s2 += xi * y2[i];
                s3 += xi * y3[i];
            }
            out.extend([s0, s1, s2, s3]);
        } else {
            out.extend(
                group
                    .iter()
                    .map(|y| x.iter().zip(y.iter()).map(|(a, b)| a * b).sum::<f64>()),
            );
        }
    }
    out
}

/// Symmetric pseudo-inverse with a relative eigenvalue floor.
fn pinv_sym(A: &DMatrix<f64>, rel: f64) -> DMatrix<f64> {
    let e = A.clone().symmetric_eigen();
    let top = e.eigenvalues.amax();
    let mut D = DMatrix::zeros(A.nrows(), A.ncols());
    for i in 0..A.nrows() {
        let l = e.eigenvalues[i];
        if l > rel * top && l > 0.0 {
            D[(i, i)] = 1.0 / l;
        }
    }
    &e.eigenvectors * D * e.eigenvectors.transpose()
}

/// `g' A⁺ g`, the χ² decrease the undamped Gauss–Newton step predicts (times two), for the
/// convergence test. Why Cholesky first: `A` is the scaled normal matrix `J'J`, positive
/// definite whenever the data determine every active parameter; there `A⁻¹ = A⁺` and the
/// factor costs a tenth of the eigen-decomposition [`pinv_sym`] needs. Only when the factor
/// shows a condition beyond `1e12` or fails does the pseudo-inverse decide: the largest
/// pivot squared over the smallest only estimates the condition, so the cut is kept 100×
/// inside the `1e14` at which [`pinv_sym`] drops directions.
fn gn_decrement(A: &DMatrix<f64>, g: &DVector<f64>) -> f64 {
    if let Some(ch) = A.clone().cholesky() {
        let d = ch.l_dirty().diagonal();
        let (lo, hi) = d.iter().fold((f64::INFINITY, 0.0f64), |(lo, hi), &x| {
            (lo.min(x.abs()), hi.max(x.abs()))
        });
        if lo * lo > 1e-12 * hi * hi {
            return g.dot(&ch.solve(g));
        }
    }
    g.dot(&(pinv_sym(A, 1e-14) * g))
}

/// A fit has converged when even the undamped Gauss–Newton step would lower χ² by less than
/// this: 0.01 of a unit of log-likelihood, a hundredth of a standard error's worth.
const CONVERGED_DECREMENT: f64 = 0.02;

/// The same for the descents that choose a start (the start grid and its finalists, the
/// early choice of the discretisation, [`descend`]): their costs are compared, and the
/// chosen end point only starts the homotopy, which refines it to [`CONVERGED_DECREMENT`].
/// The remaining decrease is then under half a unit of log-likelihood, where the costs they
/// compare differ by tens to thousands of units. Why: on a short prefix a descent in a
/// basin that is not the truth's (a large-residual fit, where Gauss–Newton converges
/// slowly) zig-zagged for its last 30–40 iterations with the decrement at 0.03–0.3 and the cost moving by
/// 0.001–0.01 per step: the start grid's finalists and the early choice took 47–50
/// iterations (their limit) and most of an identification's time on the benchmark record.
/// The whole-record fits that make the answer keep [`CONVERGED_DECREMENT`].
const SCREEN_DECREMENT: f64 = 1.0;

/// Where along a step the parabola through the cost at its start (`at_start`), the slope
/// there (`slope`, per unit of the step) and the cost at its end (`at_end`) has its minimum,
/// as a fraction of the step; `None` when the start does not descend or the parabola is not
/// convex (no minimum ahead to take).
fn parabola_minimum(at_start: f64, slope: f64, at_end: f64) -> Option<f64> {
    let curvature = at_end - at_start - slope;
    (slope < 0.0 && curvature > 0.0).then(|| -slope / (2.0 * curvature))
}

/// Fit over the first `len` samples from `pt`, Levenberg–Marquardt on the concentrated
/// likelihood, until the Gauss–Newton decrement is below `converged_below` (χ², see
/// [`CONVERGED_DECREMENT`]) or `max_iterations`. Returns the iterations used.
#[allow(clippy::too_many_arguments)]
fn fit_stage(
    prob: &Problem,
    pt: &mut Point,
    d: Discretisation,
    len: usize,
    max_iterations: usize,
    active: &[usize],
    free_z0: bool,
    converged_below: f64,
) -> Result<usize, MlError> {
    fit_stage_costed(
        prob,
        pt,
        d,
        len,
        max_iterations,
        active,
        free_z0,
        converged_below,
    )
    .map(|(iterations, _)| iterations)
}

/// [`fit_stage`], and the cost at the point it ends (what [`pt_cost_len`] would compute
/// there, from the same simulation: one discretisation and one simulation fewer per
/// screening descent).
#[allow(clippy::too_many_arguments)]
fn fit_stage_costed(
    prob: &Problem,
    pt: &mut Point,
    d: Discretisation,
    len: usize,
    max_iterations: usize,
    active: &[usize],
    free_z0: bool,
    converged_below: f64,
) -> Result<(usize, f64), MlError> {
    let m = prob.m;
    let mut disc = prob.discretise(&pt.p, d)?;
    let mut base = Trace::default();
    prob.simulate(&disc, &pt.p, &pt.z0, len, false, &mut base)
        .map_err(|sample| MlError::Diverged {
            sample,
            params: prob.describe(&pt.p),
        })?;
    let (mut l, mut ssr, mut cnt) = cost(prob, &base, len);
    let mut lambda = 1e-3;
    let mut iters = 0;
    for _ in 0..max_iterations {
        iters += 1;
        let sigma: Vec<f64> = (0..m)
            .map(|k| {
                (ssr[k] / cnt[k].max(1) as f64)
                    .sqrt()
                    .max(sigma_floor(prob, k, len))
            })
            .collect();
        let (A, g, scale) = normal_equations(prob, pt, &base, &disc, len, &sigma, active, free_z0)?;
        let decrement = gn_decrement(&A, &g);
        if decrement < converged_below {
            return Ok((iters, l));
        }
        let mut accepted = false;
        for _try in 0..12 {
            let mut Ad = A.clone();
            for i in 0..A.nrows() {
                Ad[(i, i)] += lambda * A[(i, i)].max(1e-12);
            }
            let step = match Ad.clone().cholesky() {
                Some(ch) => ch.solve(&g),
                None => pinv_sym(&Ad, 1e-14) * &g,
            };
            let na = active.len();
            // The point `t` of the way along the step (`t = 1`: the step itself).
            let along = |t: f64| {
                let mut cand = Point {
                    p: pt.p.clone(),
                    z0: pt.z0.clone(),
                };
                for (a, &j) in active.iter().enumerate() {
                    cand.p[j] += t * step[a] / scale[a];
                }
                if free_z0 {
                    for s in 0..cand.z0.len() {
                        cand.z0[s] += t * step[na + s] / scale[na + s];
                    }
                }
                cand
            };
            // A candidate's model, outputs and cost; `None` when it cannot be discretised or
            // its simulation diverges.
            let evaluate = |cand: &Point| {
                let cd = prob.discretise(&cand.p, d).ok()?;
                let mut tr = Trace::default();
                prob.simulate(&cd, &cand.p, &cand.z0, len, false, &mut tr)
                    .ok()?;
                let (lc, ssrc, cntc) = cost(prob, &tr, len);
                Some((cd, tr, lc, ssrc, cntc))
            };
            // The tested structure was stable: a step to a model whose free response grows
            // more than tenfold over the record (a negative stiffness beyond the supports,
            // say) is not a candidate. A slightly negative damping of an undamped truth is.
            // (Tested only for a step that lowers the cost: every refusal above does the
            // same, and the eigenvalues are the dearest of the three tests; none for a
            // passive structure, [`Problem::passive`].) Tenfold over the record: `Φ` is
            // applied once per map of the record — per sample when the sub-steps are composed
            // into one map (a law linear in the state), per sub-step otherwise. (It counted
            // sub-steps for composed maps too, so a 64-sub-step model allowed a growth of
            // 10^(1/64) = 1.04 over the record: a damper a little negative, well inside its
            // errors, was a wall the descent stopped at — measured on 64-sub-step data at
            // 100 % noise, seed 8824: `v` held at −0.0196 N·s/m and the likelihood 46 units
            // short of its optimum; ACCURACY.md, forty-seventh session.)
            let unstable = |cand: &Point, cd: &Discrete| {
                let steps = (prob.samples * cd.steps_per_sample) as f64;
                !prob.passive(&cand.p)
                    && crate::estimate::spectral_radius_exceeds(
                        &cd.Phi,
                        1.0 + 10f64.ln() / steps,
                        steps,
                    )
            };
            let cand = along(1.0);
            let Some((cd, tr, lc, ssrc, cntc)) = evaluate(&cand) else {
                lambda *= 4.0;
                continue;
            };
            if lc < l && !unstable(&cand, &cd) {
                let mut taken = (cand, cd, tr, lc, ssrc, cntc);
                // An overshooting step: the parabola through the cost at the start, its slope
                // there (`−g·δ`: the cost is −ln L with the noise levels concentrated out,
                // whose gradient is `−J'r` in the normal equations' scaling) and the cost at
                // the step puts the minimum along it at `t* < 0.7`; the cost there is tried
                // and kept when lower. Why: far from the data (a start grid's basin that is
                // not the truth's) the neglected second-order term of the residuals makes
                // Gauss–Newton overshoot by about twice, and the descent zig-zagged across the
                // valley — measured on the benchmark record's grid finalists, 31 and 32
                // iterations with the stiffness alternating between 75.4 and 76.3 kN/m.
                if let Some(t) = parabola_minimum(l, -g.dot(&step), lc)
                    && t < 0.7
                {
                    let shorter = along(t);
                    if let Some(e) = evaluate(&shorter)
                        && e.2 < taken.3
                        && !unstable(&shorter, &e.0)
                    {
                        taken = (shorter, e.0, e.1, e.2, e.3, e.4);
                    }
                }
                let (cand, cd, tr, lc, ssrc, cntc) = taken;
                *pt = cand;
                disc = cd;
                base = tr;
                l = lc;
                ssr = ssrc;
                cnt = cntc;
                lambda = (lambda / 3.0).max(1e-9);
                accepted = true;
                break;
            }
            lambda *= 4.0;
        }
        if !accepted {
            break;
        }
    }
    Ok((iters, l))
}

/// Identify the connection parameters by maximum likelihood.
pub fn identify_ml(
    setup: &Setup,
    model: &Model,
    data: &TestData,
    opts: &MlOptions,
) -> Result<(MlFit, Trace), MlError> {
    let prob = Problem::new(setup, model, data)?;
    let np = prob.n_params();
    let needed = (np + 2 * prob.n + 3).max(10);
    if prob.samples < needed {
        return Err(MlError::TooShort {
            got: prob.samples,
            needed,
        });
    }
    // The fit from each start setting, the likelier answer kept: see [`START_PREFIXES`].
    // (Side by side, each on its share of the cores — `crate::par` hands a nested map the
    // threads divided by the outer map's workers, so two starts on two cores run one
    // thread each and their grids do not oversubscribe a larger machine; the same answers
    // as one after the other. Measured with the simulation's fast path: 130 → 104 ms at
    // 2,000 samples on two cores (criterion), where each start's own parallel parts had
    // used the second core for 1.5×.) A setting whose prefixes come out as an earlier
    // one's on this record, or a fit with neither a start grid (no `u` term) nor an early
    // choice (one discretisation), would repeat that fit: skipped.
    let has_grid = prob.roles.iter().any(|(_, b)| matches!(b, Basis::U));
    let has_choice = discretisation_candidates(setup, opts).len() > 1;
    let lengths = |stages: usize| prefix_len(stages, opts, needed, prob.samples);
    let mut settings: Vec<(usize, usize)> = Vec::new();
    for &(start_stages, early_stages) in &START_PREFIXES {
        let seen = settings.iter().any(|&(a, b)| {
            (!has_grid || lengths(a) == lengths(start_stages))
                && (!has_choice || lengths(b) == lengths(early_stages))
        });
        if !seen {
            settings.push((start_stages, early_stages));
        }
    }
    let mut best: Option<(f64, StartFit)> = None;
    let mut first_error = None;
    let runs = crate::par::map(&settings, |&(start_stages, early_stages)| {
        fit_from_start(&prob, setup, opts, needed, start_stages, early_stages)
            .and_then(|r| Ok((pt_cost(&prob, &r.pt, r.d)?, r)))
    });
    for (&(start_stages, early_stages), run) in settings.iter().zip(runs) {
        match run {
            Ok((cost, r)) => {
                if std::env::var_os("JOINTID_ML_DEBUG").is_some() {
                    eprintln!(
                        "start ({start_stages}, {early_stages}): {} cost {cost:.3} p = {:?}",
                        r.d, r.pt.p
                    );
                }
                if best.as_ref().is_none_or(|(c, _)| cost < *c) {
                    best = Some((cost, r));
                }
            }
            Err(e) => {
                first_error.get_or_insert(e);
            }
        }
    }
    // (At least one setting always runs, so `first_error` is set when `best` is not.)
    let Some((_, start_fit)) = best else {
        return Err(first_error.unwrap_or(MlError::TooShort {
            got: prob.samples,
            needed,
        }));
    };
    let smooth_data = TestData {
        excitation: crate::estimate::moment_matched(&data.excitation),
        ..data.clone()
    };
    let smooth = Problem::new(setup, model, &smooth_data)?;
    average_over_models([&prob, &smooth], start_fit, opts)
}

/// Models whose likelihood is more than this below the likeliest's (Δ(−ln L), a posterior
/// weight below e⁻⁷ ≈ 0.001 of its at equal priors) are left out of the average.
const MODEL_AVERAGE_SPAN: f64 = 7.0;

/// The answer over the models the record may have been made with — every candidate
/// discretisation, with the excitation linear or smooth between samples ([`Variant`]):
/// each within [`MODEL_AVERAGE_SPAN`] of the likeliest after its screening refit is refitted
/// in full, and the answer is their posterior mean at equal prior weights (weights
/// `∝ exp(−(−ln L))`, the models having the same parameters), its covariance the weighted
/// mean of theirs plus the spread of their estimates. One model far likelier than the rest
/// (the usual case: 1 % noise on the two-beam problem separates them by tens to thousands
/// of units) is that model's answer alone.
///
/// Why: which model is right is a nuisance parameter the data decide only when they can.
/// On a 1-DOF test (a mass on a spring and a damper, 10 Hz, sampled at 1 kHz, continuous
/// data driven by a sum of sines; ACCURACY.md, forty-sixth session) Newmark with one
/// sub-step per sample fits as well as the exact map (Δ(−ln L) = 0.0–0.5 at 10 % noise)
/// with a stiffness higher by its period error `(ωh)²/6` (+0.07 %); taking the likeliest
/// put the spring 3–11 standard errors off in 9 of 20 records at 10 % noise and up to 22 at
/// 1 %; and the straight line between samples left the damper 2–3 errors low at 1 %.
fn average_over_models(
    probs: [&Problem; 2],
    sf: StartFit,
    opts: &MlOptions,
) -> Result<(MlFit, Trace), MlError> {
    let n_all = probs[0].samples;
    let all: Vec<usize> = (0..probs[0].n_params()).collect();
    let prob_of = |v: &Variant| match v.between {
        Between::Linear => probs[0],
        Between::Smooth => probs[1],
    };
    let linear = |d| Variant {
        d,
        between: Between::Linear,
    };
    let chosen = linear(sf.d);
    let chosen_cost = pt_cost(probs[0], &sf.pt, sf.d)?;
    // Screening: the linear alternatives were refitted briefly in `fit_from_start`; the smooth
    // ones are, each from its discretisation's linear point.
    let smooth_starts: Vec<(Variant, &Point)> = std::iter::once((sf.d, &sf.pt))
        .chain(sf.screened.iter().map(|(d, p)| (*d, p)))
        .map(|(d, p)| {
            let smooth = Variant {
                d,
                between: Between::Smooth,
            };
            (smooth, p)
        })
        .collect();
    let smooth_screened = crate::par::map(&smooth_starts, |(v, p)| {
        let mut cand = (*p).clone();
        let (_, c) = fit_stage_costed(
            probs[1],
            &mut cand,
            v.d,
            n_all,
            opts.screen_iterations,
            &all,
            opts.free_initial_state,
            CONVERGED_DECREMENT,
        )
        .ok()?;
        Some((*v, c, cand))
    });
    let mut screened: Vec<(Variant, f64, Point)> = vec![(chosen, chosen_cost, sf.pt.clone())];
    for (d, p) in &sf.screened {
        if let Some(&(_, c)) = sf.compared.iter().find(|(cd, _)| cd == d) {
            screened.push((linear(*d), c, p.clone()));
        }
    }
    screened.extend(smooth_screened.into_iter().flatten());
    let compared: Vec<(Variant, f64)> = screened.iter().map(|(v, c, _)| (*v, *c)).collect();
    if std::env::var_os("JOINTID_ML_DEBUG").is_some() {
        for (v, c, p) in &screened {
            eprintln!("model screened: {v} cost {c:.3} p = {:?}", p.p);
        }
    }
    let lowest = compared.iter().map(|c| c.1).fold(f64::INFINITY, f64::min);
    // The contenders, refitted in full (the chosen one already is).
    let contenders: Vec<&(Variant, f64, Point)> = screened
        .iter()
        .filter(|(_, c, _)| *c <= lowest + MODEL_AVERAGE_SPAN)
        .collect();
    let refitted = crate::par::map(&contenders, |(v, c, p)| {
        if *v == chosen {
            return Some((*v, *c, p.clone(), 0));
        }
        let mut cand = p.clone();
        let (it, c) = fit_stage_costed(
            prob_of(v),
            &mut cand,
            v.d,
            n_all,
            opts.max_iterations,
            &all,
            opts.free_initial_state,
            CONVERGED_DECREMENT,
        )
        .ok()?;
        Some((*v, c, cand, it))
    });
    let mut refitted: Vec<(Variant, f64, Point, usize)> = refitted.into_iter().flatten().collect();
    if std::env::var_os("JOINTID_ML_DEBUG").is_some() {
        for (v, c, p, it) in &refitted {
            eprintln!("model refitted: {v} cost {c:.3} ({it} its) p = {:?}", p.p);
        }
    }
    let extra_iterations: usize = refitted.iter().map(|r| r.3).sum();
    let lowest = refitted.iter().map(|r| r.1).fold(f64::INFINITY, f64::min);
    refitted.retain(|r| r.1 <= lowest + MODEL_AVERAGE_SPAN);
    refitted.sort_by(|a, b| a.1.total_cmp(&b.1));
    // (The chosen model always survives its own refit, so `refitted` is not empty.)
    let mut stages = sf.stages;
    if refitted.first().is_some_and(|r| r.0 != chosen) {
        stages.push((n_all, refitted[0].3));
    }
    let iterations = sf.iterations + extra_iterations;
    let finished = crate::par::map(&refitted, |(v, _, p, _)| {
        finish(
            prob_of(v),
            p.clone(),
            *v,
            sf.disc_error,
            compared.clone(),
            opts,
            stages.clone(),
            iterations,
        )
    });
    let mut fits: Vec<(f64, MlFit, Trace, Variant)> = Vec::new();
    let mut first_error = None;
    for ((v, c, _, _), f) in refitted.iter().zip(finished) {
        match f {
            Ok((fit, tr)) => fits.push((*c, fit, tr, *v)),
            Err(e) => {
                if fits.is_empty() {
                    // The likeliest model's answer is refused: so is the average.
                    first_error.get_or_insert(e);
                    break;
                }
            }
        }
    }
    if let Some(e) = first_error {
        return Err(e);
    }
    let Some((c0, _, _, _)) = fits.first() else {
        return Err(MlError::TooShort {
            got: n_all,
            needed: n_all,
        });
    };
    let c0 = *c0;
    let weights: Vec<f64> = fits.iter().map(|f| (c0 - f.0).exp()).collect();
    let total: f64 = weights.iter().sum();
    let weights: Vec<f64> = weights.iter().map(|w| w / total).collect();
    // Drop the models below 0.001 of the weight; one left: its answer alone.
    let kept: Vec<usize> = (0..fits.len()).filter(|&i| weights[i] >= 1e-3).collect();
    let mut fits: Vec<(f64, MlFit, Trace, Variant)> = fits
        .into_iter()
        .enumerate()
        .filter(|(i, _)| kept.contains(i))
        .map(|(_, f)| f)
        .collect();
    let total: f64 = kept.iter().map(|&i| weights[i]).sum();
    let weights: Vec<f64> = kept.iter().map(|&i| weights[i] / total).collect();
    let (_, mut fit, trace, _) = fits.remove(0);
    if fits.is_empty() {
        return Ok((fit, trace));
    }
    let rest: Vec<&MlFit> = fits.iter().map(|f| &f.1).collect();
    let models: Vec<&MlFit> = std::iter::once(&fit).chain(rest.iter().copied()).collect();
    let np = fit.params.len();
    let (mean, se) = mixture(
        &models
            .iter()
            .map(|f| (f.params.as_slice(), f.std_errors.as_slice()))
            .collect::<Vec<_>>(),
        &weights,
    );
    let (widest, ratio) = (0..np)
        .map(|j| (j, se[j] / fit.std_errors[j].max(f64::MIN_POSITIVE)))
        .fold((0, 0.0), |a, b| if b.1 > a.1 { b } else { a });
    let labels: Vec<String> = std::iter::once(chosen_label(&fit))
        .chain(fits.iter().map(|f| f.3.to_string()))
        .collect();
    let keys = probs[0].setup.param_keys();
    let span = c0 - fits.last().map_or(c0, |f| f.0);
    fit.discretisation = format!(
        "{}; the data do not single out one model ({} within Δ(−ln L) = {:.1}): the answer is their likelihood-weighted mean (the weightiest: {}), its standard errors include the spread between their estimates (`{}` {:.3e} → {:.3e}, ×{ratio:.2})",
        fit.discretisation,
        labels.len(),
        -span,
        labels
            .iter()
            .zip(&weights)
            .take(3)
            .map(|(l, w)| format!("{l} {w:.2}"))
            .collect::<Vec<_>>()
            .join(", "),
        keys[widest],
        fit.std_errors[widest],
        se[widest],
    );
    fit.model_weights = labels.into_iter().zip(weights).collect();
    fit.params = mean;
    fit.std_errors = se;
    Ok((fit, trace))
}

/// Mean and standard error, per parameter, of the mixture of the models' estimates
/// `(values, standard errors)` with `weights` (summing to 1): the law of total variance,
/// `var = Σ wᵢ (seᵢ² + (θᵢ − θ̄)²)`.
fn mixture(models: &[(&[f64], &[f64])], weights: &[f64]) -> (Vec<f64>, Vec<f64>) {
    let np = models.first().map_or(0, |m| m.0.len());
    let mean: Vec<f64> = (0..np)
        .map(|j| models.iter().zip(weights).map(|(m, w)| w * m.0[j]).sum())
        .collect();
    let se = (0..np)
        .map(|j| {
            models
                .iter()
                .zip(weights)
                .map(|(m, w)| w * (m.1[j].powi(2) + (m.0[j] - mean[j]).powi(2)))
                .sum::<f64>()
                .sqrt()
        })
        .collect();
    (mean, se)
}

/// The label ([`Variant`]'s) of the model a fit was made with.
fn chosen_label(fit: &MlFit) -> String {
    Variant {
        d: Discretisation {
            scheme: fit.scheme,
            substeps: fit.substeps,
        },
        between: fit.between,
    }
    .to_string()
}

/// Candidate discretisations: the exact map first, then (when the setup's scheme is Newmark
/// average acceleration and the choice is on) that scheme with 1, 2, 4, … sub-steps up to
/// [`MlOptions::max_newmark_substeps`] — what a simulation may have used.
fn discretisation_candidates(setup: &Setup, opts: &MlOptions) -> Vec<Discretisation> {
    let mut candidates = vec![Discretisation {
        scheme: Scheme::Exact,
        substeps: 1,
    }];
    if opts.select_discretisation && setup.newmark.gamma == 0.5 && setup.newmark.beta == 0.25 {
        let mut s = 1;
        while s <= opts.max_newmark_substeps {
            candidates.push(Discretisation {
                scheme: Scheme::Newmark,
                substeps: s,
            });
            s *= 2;
        }
    }
    candidates
}

/// The first `stages` first-stage lengths of the record ([`MlOptions::first_stage_samples`]
/// each), at least `needed` samples and at most the record.
fn prefix_len(stages: usize, opts: &MlOptions, needed: usize, samples: usize) -> usize {
    (stages * opts.first_stage_samples).max(needed).min(samples)
}

/// What [`fit_from_start`] found: the point, the discretisation, the measured effect of the
/// force hold, the discretisations compared, the stages and the iterations.
struct StartFit {
    pt: Point,
    d: Discretisation,
    disc_error: f64,
    compared: Vec<(Discretisation, f64)>,
    /// The other discretisations' points after their screening refits (with `compared`'s
    /// costs): where [`average_over_models`] starts them.
    screened: Vec<(Discretisation, Point)>,
    stages: Vec<(usize, usize)>,
    iterations: usize,
}

/// The prefixes, in first-stage lengths ([`MlOptions::first_stage_samples`]), of the start
/// grid and of the early choice of the discretisation: the whole fit runs from each pair,
/// and the answer is the one of higher whole-record likelihood. Why two: they decide the
/// basin the homotopy then refines and cannot leave. On short prefixes the basins are wide
/// but at high noise or on finely integrated data the prefix may not tell them apart; on
/// long ones the noise averages out but the basins narrow (a stiffness wrong by 1 % puts a
/// mode out of phase after ~50 periods, the grid's points are a factor 2 apart). Measured on
/// fresh seeds (ACCURACY.md, thirty-third session): with (4, 2) alone 4 of 405 records (`u,
/// v` law, 1–100 % noise) ended in a local minimum 6.6–45.8 standard errors off; with (8,
/// 4) alone those were right and 3 others were wrong (12.7, 12.2, 8.3 se) — one prefix per
/// seed only moves the failures; the likelihood of the whole record decides between them.
const START_PREFIXES: [(usize, usize); 2] = [(4, 2), (8, 4)];

/// Iterations of each candidate's descent in the early choice of the discretisation.
const EARLY_CHOICE_ITERATIONS: usize = 10;

/// The fit from the setup's initial values: the start grid on a prefix of `start_stages`
/// first-stage lengths, the early choice of the discretisation on `early_stages`, the
/// homotopy over doubling prefixes, the discretisation chosen on the whole record.
fn fit_from_start(
    prob: &Problem,
    setup: &Setup,
    opts: &MlOptions,
    needed: usize,
    start_stages: usize,
    early_stages: usize,
) -> Result<StartFit, MlError> {
    let np = prob.n_params();
    let mut pt = Point {
        p: setup.initial_params(),
        z0: DVector::zeros(2 * prob.n),
    };
    let n_all = prob.samples;
    let mut stages = Vec::new();
    let mut iterations = 0;
    let exact = Discretisation {
        scheme: Scheme::Exact,
        substeps: 1,
    };
    let all: Vec<usize> = (0..np).collect();
    let linear: Vec<usize> = (0..np)
        .filter(|&j| {
            !matches!(
                prob.roles[j].1,
                Basis::U3 | Basis::SignU | Basis::SignV | Basis::Gap(_)
            )
        })
        .collect();
    // 1. The exact model, grown over doubling prefixes of the record: first its best
    //    linear approximation (the terms non-linear in the state held at their initial
    //    values), then every parameter, again from the shortest prefix.
    let phases: Vec<&[usize]> = if linear.len() < np {
        vec![&linear, &all]
    } else {
        vec![&all]
    };
    // The data pick the discretisation by likelihood, first on the first prefix (a Newmark
    // simulation's high modes dominate its velocities, so the wrong family hides the
    // joint), then again on the whole record.
    let candidates = discretisation_candidates(setup, opts);
    let clock = std::time::Instant::now();
    let debug = std::env::var_os("JOINTID_ML_DEBUG").is_some();
    let mut exact = exact;
    // 0. A start in the right basin. The output-error likelihood of a vibrating structure
    //    has a local minimum wherever a resonance of the model lines up with another one of
    //    the data, and the setup's initial values (often 0) may sit in any of them: the
    //    stiffness-like parameters (basis `u`) start from the likeliest of a log-spaced grid
    //    around the force-per-deformation scale of the record (the other linear parameters
    //    refitted at every grid point, the three best descended in full), on the exact map
    //    over a short prefix.
    let mut fitted_len = 0;
    {
        let len = prefix_len(start_stages, opts, needed, n_all);
        for &j in linear
            .iter()
            .filter(|&&j| matches!(prob.roles[j].1, Basis::U))
        {
            let others: Vec<usize> = linear.iter().copied().filter(|&k| k != j).collect();
            let typical = typical_value(prob, &pt, j, len)?;
            // Screen: the grid (factor 2 apart, 0.1 to 100 times the scale) with the other
            // parameters refitted briefly; then the three likeliest descend in full.
            let mut screened: Vec<(f64, Point)> = pt_cost_len(prob, &pt, exact, len)
                .ok()
                .map(|c| (c, pt.clone()))
                .into_iter()
                .collect();
            // (The grid's descents are independent: on every core, `crate::par`, in the
            // grid's order — the same result as one after the other.)
            let grid: Vec<Point> = (0..11)
                .map(|i| {
                    let mut cand = pt.clone();
                    cand.p[j] = 0.1 * f64::powi(2.0, i) * typical;
                    cand
                })
                .collect();
            let its = opts.screen_iterations + 3;
            // Each point's brief descent over the other linear parameters.
            let screen = |points: &[Point]| {
                crate::par::map(points, |cand| {
                    descend(
                        prob,
                        cand.clone(),
                        exact,
                        len,
                        its,
                        &others,
                        opts.free_initial_state,
                    )
                })
                .into_iter()
                .flatten()
                .collect::<Vec<_>>()
            };
            screened.extend(screen(&grid));
            screened.sort_by(|a, b| a.0.total_cmp(&b.0));
            // Zoom: between the likeliest point's grid neighbours, a grid 2^(1/4) apart
            // (six more points, refitted as the grid's). At high noise the prefix's basins
            // are narrower than the grid's factor 2: measured (spring `u, v`, 64-sub-step
            // data, 100 % noise, seed 8411) the 400-sample prefix costs 20 units less at the
            // truth than at the grid's best point (251,641 N/m, a basin of its own), the
            // 800-sample one 376 less, where the grid's points flank the truth at 207,415
            // and 414,830; the homotopy from either cannot leave it and the answer was 21.6
            // standard errors off. The zoom puts a point at 299,253 and the answer at
            // +0.04 %. (ACCURACY.md, forty-seventh session.)
            if let Some(centre) = screened.first().map(|(_, c)| c.p[j]) {
                let fine: Vec<Point> = [-3, -2, -1, 1, 2, 3]
                    .iter()
                    .map(|&k| {
                        let mut cand = pt.clone();
                        cand.p[j] = centre * f64::powf(2.0, f64::from(k) / 4.0);
                        cand
                    })
                    .collect();
                screened.extend(screen(&fine));
                screened.sort_by(|a, b| a.0.total_cmp(&b.0));
            }
            screened.truncate(3);
            if debug {
                for (c, s) in &screened {
                    eprintln!("grid finalist: cost {c:.3}, p = {:?}", s.p);
                }
            }
            let best = crate::par::map(&screened, |(_, cand)| {
                descend(
                    prob,
                    cand.clone(),
                    exact,
                    len,
                    opts.max_iterations,
                    &linear,
                    opts.free_initial_state,
                )
            })
            .into_iter()
            .flatten()
            .min_by(|a, b| a.0.total_cmp(&b.0));
            if let Some((_, b)) = best {
                pt = b;
                fitted_len = len;
            }
        }
        if debug {
            eprintln!(
                "start grid: p = {:?}, {:.3} s",
                pt.p,
                clock.elapsed().as_secs_f64()
            );
        }
    }
    if candidates.len() > 1 {
        let len = prefix_len(early_stages, opts, needed, n_all);
        let best = crate::par::map(&candidates, |&d| {
            let (c, _) = descend(
                prob,
                pt.clone(),
                d,
                len,
                EARLY_CHOICE_ITERATIONS,
                &linear,
                opts.free_initial_state,
            )?;
            Some((c, d))
        })
        .into_iter()
        .flatten()
        .min_by(|a, b| a.0.total_cmp(&b.0));
        if let Some((_, d)) = best {
            exact = d;
        }
    }
    if debug {
        eprintln!(
            "early selection {exact}: {:.3} s",
            clock.elapsed().as_secs_f64()
        );
    }
    // The first prefix is the shortest (from `first_stage_samples`, doubling) over which the
    // data determine the linear parameters to a quarter of their size: shorter, the cost is
    // flat and a descent wanders off.
    let mut first = opts.first_stage_samples.max(needed).min(n_all);
    while first < n_all && !determined(prob, &pt, exact, first, &linear, opts.free_initial_state)? {
        first = (first * 2).min(n_all);
    }
    // Never back to a shorter prefix than the start grid settled the basin on: on a noisy
    // record a shorter one lets the descent wander into another basin.
    first = first.max(fitted_len).min(n_all);
    for (phase, active) in phases.into_iter().enumerate() {
        if phase == 1 {
            // Profile likelihood over each non-linear parameter on a short prefix: the
            // cost of a friction level is rough and its basin narrow, so the descent starts
            // from the best of a grid (the other parameters refitted at every point).
            let len = (4 * first).max(needed).min(n_all);
            for &j in all.iter().filter(|j| !linear.contains(j)) {
                let others: Vec<usize> = all.iter().copied().filter(|&k| k != j).collect();
                let typical = typical_value(prob, &pt, j, len)?;
                let grid: Vec<f64> = match prob.roles[j].1 {
                    Basis::SignU | Basis::SignV => [0.0, 0.03, 0.1, 0.3, 1.0, 3.0, 10.0]
                        .iter()
                        .map(|g| g * typical)
                        .collect(),
                    _ => [0.0, 0.01, -0.01, 0.1, -0.1, 1.0, -1.0]
                        .iter()
                        .map(|g| g * typical)
                        .collect(),
                };
                let mut best: Option<(f64, Point)> = None;
                for g in grid {
                    let mut cand = pt.clone();
                    cand.p[j] = g;
                    let Ok(it) = fit_stage(
                        prob,
                        &mut cand,
                        exact,
                        len,
                        opts.screen_iterations + 3,
                        &others,
                        opts.free_initial_state,
                        CONVERGED_DECREMENT,
                    ) else {
                        continue;
                    };
                    iterations += it;
                    let Ok(c) = pt_cost_len(prob, &cand, exact, len) else {
                        continue;
                    };
                    if best.as_ref().is_none_or(|b| c < b.0) {
                        best = Some((c, cand));
                    }
                }
                if let Some((_, b)) = best {
                    pt = b;
                }
            }
        }
        let mut len = first;
        loop {
            let it = fit_stage(
                prob,
                &mut pt,
                exact,
                len,
                opts.max_iterations,
                active,
                opts.free_initial_state,
                CONVERGED_DECREMENT,
            )?;
            if debug {
                eprintln!("stage len {len}: {} its, p = {:?}", it, pt.p);
            }
            iterations += it;
            stages.push((len, it));
            if len == n_all {
                break;
            }
            len = (len * 2).min(n_all);
            if n_all - len < len / 4 {
                len = n_all;
            }
        }
    }
    // 2. The discretisation the data were made with is a nuisance parameter of the
    //    likelihood: measured data select the exact map; a Newmark simulation its own
    //    sub-steps. Each candidate is refitted from the exact fit and the likeliest kept.
    if debug {
        eprintln!("homotopy: {:.3} s", clock.elapsed().as_secs_f64());
    }
    let mut best = (exact, pt_cost(prob, &pt, exact)?, None::<Point>);
    let exact_pt = pt.clone();
    let mut compared = vec![(exact, best.1)];
    // (Each candidate's refit is independent: on every core, taken in the candidates' order.)
    let others: Vec<Discretisation> = candidates.iter().copied().filter(|&d| d != exact).collect();
    let refits = crate::par::map(&others, |&d| {
        let mut cand = pt.clone();
        fit_stage_costed(
            prob,
            &mut cand,
            d,
            n_all,
            opts.screen_iterations,
            &all,
            opts.free_initial_state,
            CONVERGED_DECREMENT,
        )
        .ok()
        .map(|(it, c)| (it, Ok::<f64, MlError>(c), cand))
    });
    let mut screened = Vec::new();
    for (&d, refit) in others.iter().zip(refits) {
        if let Some((it, c, cand)) = refit {
            iterations += it;
            let c = c?;
            compared.push((d, c));
            if c < best.1 {
                best = (d, c, Some(cand.clone()));
            }
            screened.push((d, cand));
        }
    }
    if debug {
        eprintln!("screening: {:.3} s", clock.elapsed().as_secs_f64());
    }
    let mut d = best.0;
    if let Some(p) = best.2 {
        pt = p;
        let it = fit_stage(
            prob,
            &mut pt,
            d,
            n_all,
            opts.max_iterations,
            &all,
            opts.free_initial_state,
            CONVERGED_DECREMENT,
        )?;
        iterations += it;
        stages.push((n_all, it));
    }
    // 3. Non-linear law on the exact map: the hold of the connection force is the one
    //    approximation left; halve the step until its effect on the outputs is negligible.
    let mut disc_error = 0.0;
    if prob.law_is_nonlinear() {
        loop {
            disc_error = discretisation_effect(prob, &pt, d)?;
            if disc_error <= opts.max_discretisation_error || d.substeps >= opts.max_substeps {
                break;
            }
            if d.scheme == Scheme::Newmark {
                // The data's own scheme: refining it would leave the data's discretisation.
                break;
            }
            d.substeps *= 2;
            let it = fit_stage(
                prob,
                &mut pt,
                d,
                n_all,
                opts.max_iterations,
                &all,
                opts.free_initial_state,
                CONVERGED_DECREMENT,
            )?;
            iterations += it;
            stages.push((n_all, it));
        }
    }
    // The exact fit is a screened alternative when another discretisation was taken.
    if d != exact {
        screened.retain(|(sd, _)| *sd != d);
        screened.push((exact, exact_pt));
    }
    Ok(StartFit {
        pt,
        d,
        disc_error,
        compared,
        screened,
        stages,
        iterations,
    })
}

fn pt_cost(prob: &Problem, pt: &Point, d: Discretisation) -> Result<f64, MlError> {
    pt_cost_len(prob, pt, d, prob.samples)
}

fn pt_cost_len(prob: &Problem, pt: &Point, d: Discretisation, len: usize) -> Result<f64, MlError> {
    let disc = prob.discretise(&pt.p, d)?;
    let mut tr = Trace::default();
    prob.simulate(&disc, &pt.p, &pt.z0, len, false, &mut tr)
        .map_err(|sample| MlError::Diverged {
            sample,
            params: prob.describe(&pt.p),
        })?;
    Ok(cost(prob, &tr, len).0)
}

/// Whether the first `len` samples determine the parameters `active` at `pt` to a quarter
/// of their size (current value or force-scaled typical value, whichever is larger).
fn determined(
    prob: &Problem,
    pt: &Point,
    d: Discretisation,
    len: usize,
    active: &[usize],
    free_z0: bool,
) -> Result<bool, MlError> {
    let m = prob.m;
    let disc = prob.discretise(&pt.p, d)?;
    let mut base = Trace::default();
    if prob
        .simulate(&disc, &pt.p, &pt.z0, len, false, &mut base)
        .is_err()
    {
        return Ok(false);
    }
    let (_, ssr, cnt) = cost(prob, &base, len);
    let sigma: Vec<f64> = (0..m)
        .map(|k| {
            (ssr[k] / cnt[k].max(1) as f64)
                .sqrt()
                .max(sigma_floor(prob, k, len))
        })
        .collect();
    let (A, _, scale) = normal_equations(prob, pt, &base, &disc, len, &sigma, active, free_z0)?;
    let cov = pinv_sym(&A, 1e-15);
    Ok(active.iter().enumerate().all(|(a, &j)| {
        let se = cov[(a, a)].max(0.0).sqrt() / scale[a];
        let size = pt.p[j].abs().max(basis_rms_scale(prob, &base, j, len));
        se <= 0.25 * size
    }))
}

/// A force-scaled magnitude of parameter `j`: excitation RMS / RMS of its basis function
/// along the current simulation (the force it would carry at the excitation's size).
/// Descends from `start` over the `active` parameters (at most `iterations`, until the
/// decrement is below [`SCREEN_DECREMENT`]) on the first `len` samples with discretisation
/// `d`: the cost there and the point reached, or `None` when the descent or the cost fails
/// (a diverging start is skipped, not an error).
fn descend(
    prob: &Problem,
    start: Point,
    d: Discretisation,
    len: usize,
    iterations: usize,
    active: &[usize],
    free_initial_state: bool,
) -> Option<(f64, Point)> {
    let mut pt = start;
    let (its, cost) = fit_stage_costed(
        prob,
        &mut pt,
        d,
        len,
        iterations,
        active,
        free_initial_state,
        SCREEN_DECREMENT,
    )
    .ok()?;
    if std::env::var_os("JOINTID_ML_DEBUG").is_some() {
        eprintln!("descent {d}, {len} samples: {its} iterations, cost {cost:.3}");
    }
    Some((cost, pt))
}

fn typical_value(prob: &Problem, pt: &Point, j: usize, len: usize) -> Result<f64, MlError> {
    let disc = prob.discretise(
        &pt.p,
        Discretisation {
            scheme: Scheme::Exact,
            substeps: 1,
        },
    )?;
    let mut tr = Trace::default();
    prob.simulate(&disc, &pt.p, &pt.z0, len, false, &mut tr)
        .map_err(|sample| MlError::Diverged {
            sample,
            params: prob.describe(&pt.p),
        })?;
    Ok(basis_rms_scale(prob, &tr, j, len))
}

fn basis_rms_scale(prob: &Problem, base: &Trace, j: usize, len: usize) -> f64 {
    let (c, b) = prob.roles[j];
    let q = prob.q;
    let f_rms = {
        let s: f64 = prob.excitation[..len * prob.ne].iter().map(|v| v * v).sum();
        (s / (len * prob.ne).max(1) as f64).sqrt().max(1e-12)
    };
    let rms_of = |v: &[f64], pow: i32| {
        ((0..len).map(|i| v[i * q + c].powi(2 * pow)).sum::<f64>() / len as f64).sqrt()
    };
    let basis_rms = match b {
        Basis::U | Basis::Gap(_) => rms_of(&base.delta, 1),
        Basis::V => rms_of(&base.delta_v, 1),
        Basis::A => rms_of(&base.delta_a, 1),
        Basis::U3 => rms_of(&base.delta, 3),
        Basis::SignU | Basis::SignV => 1.0,
        Basis::Const(k) => k.abs(),
    };
    (f_rms / basis_rms.max(1e-300)).min(1e300)
}

/// RMS over channels of (outputs with `d` − outputs with twice its sub-steps)/σ.
fn discretisation_effect(prob: &Problem, pt: &Point, d: Discretisation) -> Result<f64, MlError> {
    let n_all = prob.samples;
    let m = prob.m;
    let d1 = prob.discretise(&pt.p, d)?;
    let d2 = prob.discretise(
        &pt.p,
        Discretisation {
            substeps: 2 * d.substeps,
            ..d
        },
    )?;
    let (mut a, mut b) = (Trace::default(), Trace::default());
    let diverged = |sample| MlError::Diverged {
        sample,
        params: prob.describe(&pt.p),
    };
    prob.simulate(&d1, &pt.p, &pt.z0, n_all, false, &mut a)
        .map_err(diverged)?;
    prob.simulate(&d2, &pt.p, &pt.z0, n_all, false, &mut b)
        .map_err(diverged)?;
    let (_, ssr, cnt) = cost(prob, &a, n_all);
    let mut acc = 0.0;
    for k in 0..m {
        let s2 = (ssr[k] / cnt[k].max(1) as f64).max(sigma_floor(prob, k, n_all).powi(2));
        let d: f64 = (0..n_all)
            .map(|i| (a.y[i * m + k] - b.y[i * m + k]).powi(2))
            .sum::<f64>()
            / n_all as f64;
        acc += d / s2;
    }
    Ok((acc / m as f64).sqrt())
}

#[allow(clippy::too_many_arguments)]
fn finish(
    prob: &Problem,
    pt: Point,
    variant: Variant,
    disc_error: f64,
    compared: Vec<(Variant, f64)>,
    opts: &MlOptions,
    stages: Vec<(usize, usize)>,
    iterations: usize,
) -> Result<(MlFit, Trace), MlError> {
    let d = variant.d;
    let n_all = prob.samples;
    let m = prob.m;
    let np = prob.n_params();
    let disc = prob.discretise(&pt.p, d)?;
    let mut base = Trace::default();
    prob.simulate(&disc, &pt.p, &pt.z0, n_all, true, &mut base)
        .map_err(|sample| MlError::Diverged {
            sample,
            params: prob.describe(&pt.p),
        })?;
    let (l, ssr, cnt) = cost(prob, &base, n_all);
    let sigma: Vec<f64> = (0..m)
        .map(|k| {
            (ssr[k] / cnt[k].max(1) as f64)
                .sqrt()
                .max(sigma_floor(prob, k, n_all))
        })
        .collect();
    let all: Vec<usize> = (0..np).collect();
    let jac = jacobian(
        prob,
        &pt,
        &base,
        &disc,
        n_all,
        &sigma,
        &all,
        opts.free_initial_state,
        true,
    )?;
    let (A, _, scale) = normal(&jac);
    let nc = A.nrows();
    // Parameter block of the inverse via the Schur complement (z₀ marginalised).
    let Ainv = pinv_sym(&A, 1e-15);
    let cov_p = Ainv.view((0, 0), (np, np)).into_owned();
    let info_p = pinv_sym(&cov_p, 1e-300);
    let eig = info_p.clone().symmetric_eigen();
    let top = eig.eigenvalues.amax();
    let (imin, low) =
        eig.eigenvalues
            .iter()
            .enumerate()
            .fold(
                (0, f64::INFINITY),
                |acc, (i, &v)| if v < acc.1 { (i, v) } else { acc },
            );
    let condition = if low > 0.0 { top / low } else { f64::INFINITY };
    if np > 0 && (condition.is_nan() || condition > opts.max_condition) {
        let rank = eig
            .eigenvalues
            .iter()
            .filter(|&&v| v > top * 1e-12 && v > 0.0)
            .count();
        let v = eig.eigenvectors.column(imin);
        let (jmax, _) =
            v.iter().enumerate().fold(
                (0, 0.0),
                |acc, (i, &x)| if x.abs() > acc.1 { (i, x.abs()) } else { acc },
            );
        return Err(MlError::Undetermined {
            rank,
            needed: np,
            condition,
            limit: opts.max_condition,
            weakest: prob.setup.param_keys()[jmax].clone(),
        });
    }
    // Sandwich on per-sample scores (scaled columns), the long-run covariance of their sum
    // by overlapping batch means (the Bartlett-kernel HAC) over a window as long as the
    // residuals stay correlated: the first lag where every channel's autocorrelation is
    // within 3/√N, at least the Newey–West default. A wrong model leaves residuals
    // correlated over hundreds of samples, and the window — and the error — grows with them.
    let nw = (4.0 * (n_all as f64 / 100.0).powf(2.0 / 9.0)).ceil() as usize;
    let window = correlation_length(prob, &base, n_all).max(nw) + 1;
    let mut scores = vec![DVector::zeros(nc); n_all];
    for (i, s) in scores.iter_mut().enumerate() {
        for j in 0..nc {
            let mut acc = 0.0;
            for k in 0..m {
                acc += jac.cols[j][i * m + k] * jac.r[i * m + k];
            }
            s[j] = acc / scale[j];
        }
    }
    let b = window.min(n_all);
    let mut run = DVector::zeros(nc);
    for s in scores.iter().take(b) {
        run += s;
    }
    let mut omega = DMatrix::zeros(nc, nc);
    let batches = n_all - b + 1;
    for t in 0..batches {
        if t > 0 {
            run += &scores[t + b - 1];
            run -= &scores[t - 1];
        }
        omega.ger(1.0, &run, &run, 1.0);
    }
    omega *= n_all as f64 / (b as f64 * batches as f64);
    let cov_sw = &Ainv * omega * &Ainv;
    let mut crlb = Vec::with_capacity(np);
    let mut se_sw = Vec::with_capacity(np);
    let mut se = Vec::with_capacity(np);
    for j in 0..np {
        let a = cov_p[(j, j)].max(0.0).sqrt() / scale[j];
        let b = cov_sw[(j, j)].max(0.0).sqrt() / scale[j];
        crlb.push(a);
        se_sw.push(b);
        se.push(a.max(b));
    }
    // Whiteness: portmanteau per channel.
    let wl = 20.min(n_all / 10).max(1);
    let mut whiteness = Vec::with_capacity(m);
    let mut fit_percent = Vec::with_capacity(m);
    let mut noise_ratio = Vec::with_capacity(m);
    let mut warnings = Vec::new();
    let chi2_999 = chi2_quantile_999(wl);
    let mut not_white: Vec<(f64, String)> = Vec::new();
    for k in 0..m {
        let e: Vec<f64> = (0..n_all)
            .map(|i| {
                let y = prob.measured[i * m + k];
                if y.is_finite() {
                    y - base.y[i * m + k]
                } else {
                    0.0
                }
            })
            .collect();
        let qstat = portmanteau(&e, wl);
        whiteness.push(qstat / wl as f64);
        let name = &prob.setup.sensors[k].name;
        if qstat > chi2_999 {
            not_white.push((qstat, name.clone()));
        }
        let mean = (0..n_all)
            .map(|i| prob.measured[i * m + k])
            .filter(|v| v.is_finite())
            .sum::<f64>()
            / cnt[k].max(1) as f64;
        let dev: f64 = (0..n_all)
            .map(|i| prob.measured[i * m + k])
            .filter(|v| v.is_finite())
            .map(|v| (v - mean).powi(2))
            .sum();
        fit_percent.push(100.0 * (1.0 - (ssr[k] / dev.max(1e-300)).sqrt()));
        let ratio = prob.setup.sensors[k].noise_std.map(|s| sigma[k] / s);
        if let Some(r) = ratio
            && r > 1.5
        {
            warnings.push(format!(
                "channel `{name}`: the model explains the outputs only to {r:.2}× the stated noise_std ({:.3e}); fitted noise {:.3e}",
                prob.setup.sensors[k].noise_std.unwrap_or(0.0),
                sigma[k]
            ));
        }
        noise_ratio.push(ratio);
    }
    if let Some((q, name)) = not_white.iter().max_by(|a, b| a.0.total_cmp(&b.0)) {
        warnings.insert(
            0,
            format!(
                "the residuals are not white in {} of {m} channels (worst `{name}`: portmanteau {q:.1} over {wl} lags, 99.9 % limit {chi2_999:.1}): the model does not explain the data (or the fit ended in a local minimum: with few sensors for several connections the likelihood has many; give `initial` values near the expected ones); the standard errors include the residual correlation (Newey–West) but not the bias it may cause",
                not_white.len()
            ),
        );
    }
    let best = compared.iter().map(|c| c.1).fold(f64::INFINITY, f64::min);
    // The other models, nearest first: five named, the rest counted.
    let mut nearest: Vec<&(Variant, f64)> = compared.iter().filter(|c| c.0 != variant).collect();
    nearest.sort_by(|a, b| a.1.total_cmp(&b.1));
    let mut others: Vec<String> = nearest
        .iter()
        .take(5)
        .map(|(dd, c)| format!("{dd}: Δ(−ln L) = {:+.1}", c - best))
        .collect();
    if let Some((_, c)) = nearest.get(5) {
        others.push(format!(
            "{} more at Δ(−ln L) ≥ {:+.1}",
            nearest.len() - 5,
            c - best
        ));
    }
    let excitation = match variant.between {
        Between::Linear => "excitation linear between samples",
        Between::Smooth => {
            "excitation smooth between samples (its samples moment-matched to a cubic through their neighbours, then linear)"
        }
    };
    let chosen = match d.scheme {
        Scheme::Exact => format!(
            "exact (matrix exponential) with {excitation}{}, {} sub-step(s) per sample",
            if prob.law_is_nonlinear() {
                " and the non-linear connection force linear over each sub-step"
            } else {
                ""
            },
            d.substeps
        ),
        Scheme::Newmark => format!(
            "Newmark average acceleration with {} sub-step(s) per sample (the scheme a simulation may have used), {excitation}",
            d.substeps
        ),
    };
    let bound = if d.scheme == Scheme::Newmark {
        "exact for data made with it".into()
    } else if prob.law_is_nonlinear() {
        format!("measured effect of the step on the outputs {disc_error:.3} noise std")
    } else if d.scheme == Scheme::Exact {
        "no discretisation error for this law".into()
    } else {
        "exact for data made with it".into()
    };
    let discretisation = if others.is_empty() {
        format!("{chosen}; {bound}")
    } else {
        format!(
            "{chosen}; {bound}; chosen by likelihood over {}",
            others.join(", ")
        )
    };
    let substeps = d.substeps;
    let fit = MlFit {
        params: pt.p.clone(),
        std_errors: se,
        crlb,
        std_errors_sandwich: se_sw,
        noise_std: sigma,
        initial_state: pt.z0.iter().copied().collect(),
        whiteness,
        whiteness_lags: wl,
        noise_ratio,
        fit_percent,
        condition,
        substeps,
        scheme: d.scheme,
        between: variant.between,
        model_weights: Vec::new(),
        discretisation_error: disc_error,
        discretisation,
        iterations,
        stages,
        cost: l,
        warnings,
    };
    Ok((fit, base))
}

/// Lags over which the output residuals stay correlated: the first lag at which every
/// channel's autocorrelation is within 3/√N (searched up to N/4).
fn correlation_length(prob: &Problem, tr: &Trace, n: usize) -> usize {
    let m = prob.m;
    let res: Vec<Vec<f64>> = (0..m)
        .map(|k| {
            (0..n)
                .map(|i| {
                    let y = prob.measured[i * m + k];
                    if y.is_finite() {
                        y - tr.y[i * m + k]
                    } else {
                        0.0
                    }
                })
                .collect()
        })
        .collect();
    let c0: Vec<f64> = res
        .iter()
        .map(|e| e.iter().map(|v| v * v).sum::<f64>().max(1e-300))
        .collect();
    let limit = 3.0 / (n as f64).sqrt();
    for l in 1..(n / 4).max(2) {
        let worst = res
            .iter()
            .zip(&c0)
            .map(|(e, c)| ((l..n).map(|i| e[i] * e[i - l]).sum::<f64>() / c).abs())
            .fold(0.0, f64::max);
        if worst < limit {
            return l - 1;
        }
    }
    n / 4
}

/// Box–Pierce portmanteau statistic `N Σ_{l=1..lags} ρ_l²` of a residual series: χ² with
/// `lags` degrees of freedom when the series is white (the model explains the data and the
/// rest is sensor noise).
pub(crate) fn portmanteau(e: &[f64], lags: usize) -> f64 {
    let n = e.len();
    let c0: f64 = e.iter().map(|v| v * v).sum::<f64>().max(1e-300);
    let mut q = 0.0;
    for l in 1..=lags.min(n.saturating_sub(1)) {
        let cl: f64 = (l..n).map(|i| e[i] * e[i - l]).sum();
        let rho = cl / c0;
        q += rho * rho;
    }
    q * n as f64
}

/// 99.9 % quantile of χ² with `k` degrees of freedom (Wilson–Hilferty).
pub(crate) fn chi2_quantile_999(k: usize) -> f64 {
    let k = k as f64;
    let z = 3.090_232;
    let a = 2.0 / (9.0 * k);
    k * (1.0 - a + z * a.sqrt()).powi(3)
}

/// Outputs of the model with parameters `params` from the initial state `z0` (`None`: at
/// rest) over the whole record, discretised by `d`: the predicted
/// response of an identification, for comparisons and plots.
pub fn predict(
    setup: &Setup,
    model: &Model,
    data: &TestData,
    params: &[f64],
    z0: Option<&[f64]>,
    d: Discretisation,
) -> Result<Trace, MlError> {
    let prob = Problem::new(setup, model, data)?;
    let disc = prob.discretise(params, d)?;
    let z0 = match z0 {
        Some(z) => DVector::from_column_slice(z),
        None => DVector::zeros(2 * prob.n),
    };
    let mut tr = Trace::default();
    prob.simulate(&disc, params, &z0, prob.samples, true, &mut tr)
        .map_err(|sample| MlError::Diverged {
            sample,
            params: prob.describe(params),
        })?;
    Ok(tr)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The mixture of two equally likely models one error apart on each side of their mean
    /// has that mean and √2 errors (within-model variance 1 plus between-model variance 1);
    /// one model alone is itself; unequal weights pull the mean.
    #[test]
    fn the_model_average_is_the_mixture_by_total_variance() {
        let (a, b) = ([0.0, 10.0], [2.0, 10.0]);
        let se = [1.0, 0.5];
        let (mean, err) = mixture(&[(&a, &se), (&b, &se)], &[0.5, 0.5]);
        assert_eq!(mean, vec![1.0, 10.0]);
        assert!((err[0] - 2f64.sqrt()).abs() < 1e-12 && (err[1] - 0.5).abs() < 1e-12);
        let (mean, err) = mixture(&[(&a, &se)], &[1.0]);
        assert_eq!((mean, err), (a.to_vec(), se.to_vec()));
        let (mean, _) = mixture(&[(&a, &se), (&b, &se)], &[0.75, 0.25]);
        assert!((mean[0] - 0.5).abs() < 1e-12);
    }

    /// The paper's two-beam setup with the connection law `u, v`.
    fn spring_uv() -> Setup {
        let path = std::path::Path::new(env!("CARGO_MANIFEST_DIR"))
            .join("recordings/two-beam-spring.toml");
        let text: String = std::fs::read_to_string(path)
            .expect("shipped setup")
            .lines()
            .map(|l| match l.trim_start() {
                t if t.starts_with("basis") => "basis = [\"u\", \"v\"]\n".to_string(),
                t if t.starts_with("initial") => "initial = [0.0, 0.0]\n".to_string(),
                t if t.starts_with("truth") => "truth = [3.0e5, 0.0]\n".to_string(),
                _ => format!("{l}\n"),
            })
            .collect();
        Setup::from_toml(&text, "spring_uv").expect("setup")
    }

    /// The Gauss–Newton decrement by the Cholesky factor is the pseudo-inverse's on a well
    /// conditioned normal matrix, and a singular one (a parameter the data leave free, its
    /// column zero) falls back to the pseudo-inverse, which ignores that direction.
    #[test]
    fn the_decrement_by_cholesky_is_the_pseudo_inverses_and_a_singular_matrix_falls_back() {
        let j = DMatrix::from_row_slice(
            4,
            3,
            &[1.0, 0.2, 0.0, 0.3, 1.0, 0.1, 0.0, 0.4, 1.0, 0.5, 0.0, 0.2],
        );
        let a = j.transpose() * &j;
        let g = DVector::from_vec(vec![0.7, -1.1, 0.4]);
        let by_pinv = g.dot(&(pinv_sym(&a, 1e-14) * &g));
        let by_chol = gn_decrement(&a, &g);
        assert!(
            (by_chol - by_pinv).abs() <= 1e-12 * by_pinv,
            "{by_chol} vs {by_pinv}"
        );
        let mut singular = a.clone();
        singular.row_mut(2).fill(0.0);
        singular.column_mut(2).fill(0.0);
        let expected = {
            let top = singular.view((0, 0), (2, 2)).into_owned();
            let g2 = DVector::from_vec(vec![0.7, -1.1]);
            g2.dot(&(top.try_inverse().expect("invertible") * &g2))
        };
        let got = gn_decrement(&singular, &g);
        assert!(
            (got - expected).abs() <= 1e-9 * expected,
            "{got} vs {expected}"
        );
    }

    /// The parabola through a quadratic's value at 0, its slope there and its value at 1 is
    /// the quadratic: its minimum is found exactly, at every position, for every convex
    /// quadratic that descends at 0; none for a concave one or one that rises at 0.
    #[test]
    fn the_parabola_of_a_quadratic_puts_its_minimum_where_the_quadratic_has_it() {
        for &(a, b, c) in &[
            (10.0, -4.0, 1.0),
            (-3.0, -1.0, 8.0),
            (4332.8, -9.3, 4.7),
            (0.0, -1e-6, 1e-3),
            (1e5, -2e3, 1.5e3),
        ] {
            let q = |t: f64| a + b * t + c * t * t;
            let t = parabola_minimum(q(0.0), b, q(1.0)).expect("a convex descent");
            let exact = -b / (2.0 * c);
            assert!(
                (t - exact).abs() <= 1e-9 * exact.abs().max(1.0),
                "{t} vs {exact}"
            );
            assert!(q(t) <= q(0.0) && q(t) <= q(1.0));
        }
        // Concave along the step, or not descending at its start: no minimum ahead.
        assert_eq!(parabola_minimum(1.0, -1.0, -0.5), None);
        assert_eq!(parabola_minimum(1.0, 0.5, 3.0), None);
        assert_eq!(parabola_minimum(1.0, -1.0, f64::NAN), None);
    }

    /// The sub-steps composed by doubling are the sub-step loop's map to rounding (a
    /// damped 4-state map, two inputs, 2 to 64 sub-steps).
    #[test]
    fn substeps_composed_by_doubling_are_the_loops_map() {
        let phi = DMatrix::from_row_slice(
            4,
            4,
            &[
                0.98, 0.05, 0.0, 0.01, -0.05, 0.97, 0.02, 0.0, 0.0, -0.02, 0.99, 0.04, 0.01, 0.0,
                -0.04, 0.985,
            ],
        );
        let g1 = DMatrix::from_row_slice(4, 2, &[0.1, 0.0, 0.2, -0.1, 0.0, 0.3, -0.2, 0.05]);
        let g2 = DMatrix::from_row_slice(4, 2, &[0.02, 0.01, -0.03, 0.0, 0.04, 0.02, 0.0, -0.01]);
        for s in [2, 4, 8, 64] {
            let by_doubling = compose_substeps(&phi, &g1, &g2, s);
            let by_loop = compose_by_loop(&phi, &g1, &g2, s);
            for (a, b) in [
                (&by_doubling.0, &by_loop.0),
                (&by_doubling.1, &by_loop.1),
                (&by_doubling.2, &by_loop.2),
            ] {
                let err = (a - b).amax() / b.amax();
                assert!(err < 1e-12, "{s} sub-steps: relative difference {err:e}");
            }
        }
    }

    /// The initial state's block of the normal equations by its Gramian and a backward
    /// pass ([`normal_equations`]) is the normal equations of its 2n columns ([`normal`]
    /// of [`jacobian`]) to rounding, on the exact map and on a composed Newmark ×8.
    #[test]
    fn the_initial_states_block_by_its_gramian_is_that_of_its_columns() {
        use crate::simulate::{Noise, Scenario, SimulateOptions, simulate};
        let setup = spring_uv();
        let model = Model::for_identification(&setup).expect("model");
        let n = 300;
        let sim = simulate(
            &setup,
            &SimulateOptions {
                scenario: Scenario::Random { rms: 1000.0 },
                steps: n,
                dt_s: setup.dt_s,
                substeps: 8,
                noise: Noise::Additive(0.1),
                seed: 3,
            },
        )
        .expect("simulate");
        let data = TestData {
            samples: (0..n as u64).collect(),
            t_ns: (0..n as u64).map(|i| i * 100_000).collect(),
            excitation: sim.excitation,
            response: sim.response,
        };
        let prob = Problem::new(&setup, &model, &data).expect("problem");
        // Off the truth, with an initial state, so the residual is not noise alone.
        let mut z0 = DVector::zeros(2 * prob.n);
        z0[3] = 1e-6;
        z0[prob.n + 2] = -2e-4;
        let pt = Point {
            p: vec![2.9e5, 0.5],
            z0,
        };
        for d in [
            Discretisation {
                scheme: Scheme::Exact,
                substeps: 1,
            },
            Discretisation {
                scheme: Scheme::Newmark,
                substeps: 8,
            },
        ] {
            let disc = prob.discretise(&pt.p, d).expect("discretise");
            let mut base = Trace::default();
            prob.simulate(&disc, &pt.p, &pt.z0, n, false, &mut base)
                .expect("simulate");
            let (_, ssr, cnt) = cost(&prob, &base, n);
            let sigma: Vec<f64> = (0..prob.m)
                .map(|k| (ssr[k] / cnt[k] as f64).sqrt())
                .collect();
            let (a1, g1, s1) =
                normal_equations(&prob, &pt, &base, &disc, n, &sigma, &[0, 1], true).unwrap();
            let jac = jacobian(&prob, &pt, &base, &disc, n, &sigma, &[0, 1], true, false).unwrap();
            let (a2, g2, s2) = normal(&jac);
            assert_eq!(a1.shape(), a2.shape());
            let err_a = (&a1 - &a2).amax();
            let err_g = (&g1 - &g2).amax() / g2.amax();
            let err_s = s1
                .iter()
                .zip(&s2)
                .map(|(x, y)| (x - y).abs() / y)
                .fold(0.0, f64::max);
            assert!(
                err_a < 1e-9 && err_g < 1e-9 && err_s < 1e-9,
                "{d}: A {err_a:e}, g {err_g:e}, scales {err_s:e}"
            );
        }
    }

    /// `Problem::passive` lets a descent's step skip the eigenvalues only where they cannot
    /// exceed 1: for stiffness and damping terms ≥ 0 the spectral radius of the exact map and
    /// of Newmark ×1 and ×4 is at most 1 (to round-off: 1 + 2.4e-7 with no joint stiffness,
    /// where a rigid-body mode makes a Jordan block at 1); a negative stiffness beyond the
    /// supports, which makes the structure unstable, is not taken for passive (nor is any
    /// negative term).
    #[test]
    fn a_passive_law_has_no_eigenvalue_outside_the_unit_circle() {
        let setup = spring_uv();
        let model = Model::for_identification(&setup).expect("model");
        let n = 50;
        let data = TestData {
            samples: (0..n as u64).collect(),
            t_ns: (0..n as u64).map(|i| i * 100_000).collect(),
            excitation: vec![vec![0.0]; n],
            response: vec![vec![1e-3; model.stations.len()]; n],
        };
        let prob = Problem::new(&setup, &model, &data).expect("problem");
        let schemes = [
            Discretisation {
                scheme: Scheme::Exact,
                substeps: 1,
            },
            Discretisation {
                scheme: Scheme::Newmark,
                substeps: 1,
            },
            Discretisation {
                scheme: Scheme::Newmark,
                substeps: 4,
            },
        ];
        for p in [[0.0, 0.0], [3e5, 0.0], [3e7, 0.0], [3e5, 50.0], [0.0, 1e3]] {
            assert!(prob.passive(&p), "{p:?}");
            for d in schemes {
                let rho = crate::estimate::spectral_radius(&prob.discretise(&p, d).unwrap().Phi);
                assert!(rho <= 1.0 + 1e-6, "{p:?} {d}: spectral radius {rho}");
            }
        }
        for p in [[-1e5, 0.0], [3e5, -1e-3]] {
            assert!(!prob.passive(&p), "{p:?}");
        }
        // A stiffness negative enough to overcome the supports: unstable, so it must not be
        // taken for passive (the test it replaces would refuse it).
        let unstable = [-1e12, 0.0];
        let rho =
            crate::estimate::spectral_radius(&prob.discretise(&unstable, schemes[0]).unwrap().Phi);
        assert!(rho > 1.0 + 1e-3, "spectral radius {rho}");
        assert!(!prob.passive(&unstable));
    }
}
