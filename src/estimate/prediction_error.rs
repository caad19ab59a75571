//! Prediction-error refinement of the connection parameters: the model with its connection
//! law, its state corrected from the measured outputs after every sample by a fixed
//! steady-state observer gain, and the parameters fitted to the one-step-ahead innovations.
//!
//! Why (issue 4): with the paper's `sign(u)` friction the model is chaotic — a joint that
//! sticks at δ = 0 or slips through it decides the later motion — so the output-error cost
//! (a free-run simulation from rest over the whole record, [`super::output_error`]) is rough
//! at every scale, and its descent from the residual-force estimate stops in local minima
//! (measured at 10 % noise, 2,000 samples, seeds 1–4: +1.1, −2.6, −9.9, −0.09 % with a
//! stated 0.09 %). The observer keeps the model on the measured trajectory, so a parameter
//! change only acts over the observer's memory (a few samples) and cannot be amplified over
//! the record: the innovation cost is smooth enough for a Gauss–Newton descent.
//!
//! Predictor: `x = (u; u̇; ü)` is stepped by the implicit Newmark sub-steps with the full
//! connection law (friction solved as in [`crate::simulate`]); after sample `i`,
//! `x ← x + K (y_i − H x)` with `K = P Hᵀ S⁻¹` from the steady-state Riccati equation of the
//! model's *linear part* (the law's `u`, `v`, `a` terms folded into K, C, M at the start
//! values; friction left out) with process noise a white force at every connection of std
//! `force_std` N per sample, plus 1e-6 of that at every DOF so that every mode is
//! stabilisable. `S = H P Hᵀ + diag σ²`. The cost is `Σᵢ |S^{-1/2} eᵢ|²`.
//!
//! Standard errors: the observer gain is not the optimal one for the data (the true
//! system has no process noise), so the normalised innovations are neither white nor of
//! unit variance; the errors are the sandwich `A⁻¹ B A⁻¹` with `A = JᵀJ` and `B` the
//! covariance of the score `Σ J_iᵀ r_i` — computed from the measurement noise through the
//! observer at rest ([`noise_driven_errors`]), the Newey–West (Bartlett) long-run
//! covariance of the per-sample scores in motion or under a repeating or smooth excitation.

#![allow(non_snake_case)]

use nalgebra::{DMatrix, DVector};

use super::kalman::{force_scale_of, solve_filter_dare_factored, spectral_radius_by_powers};
use super::output_error::scaled_inverse;
use crate::integrate::Stepper;
use crate::model::Model;
use crate::setup::{Basis, Setup};
use crate::simulate::{SimulateError, each_prediction_with_observer};

/// The fixed observer of the predictor.
#[derive(Debug, Clone)]
pub struct Predictor {
    /// `K`, `3n × m`.
    pub gain: DMatrix<f64>,
    /// `S^{-1/2}` (inverse Cholesky factor of the innovation covariance), `m × m`.
    pub whiten: DMatrix<f64>,
    /// Process-noise force std per sample at every connection, N.
    pub force_std: f64,
    /// The linear part's closed loop `(I − K H) Φ`, for [`Predictor::spectral_radius`].
    closed: DMatrix<f64>,
    /// The state `(u; u̇; ü)` the predictions start from, as offsets from rest (a record
    /// that starts in motion; `IdentifyOptions::initial_state`). `None`: at rest.
    pub initial: Option<Vec<f64>>,
    /// `Ψᵀ` with `Ψ = Φ (I − K H)` (the prediction's error recursion), and `W H` with its
    /// transpose (`W` = `whiten`): the initial-state fit's matrices for whitened
    /// innovations (`(W H)ᵀ W e = Hᵀ S⁻¹ e`, `(W H)ᵀ W H = Hᵀ S⁻¹ H`).
    psi_t: DMatrix<f64>,
    wh: DMatrix<f64>,
    wh_t: DMatrix<f64>,
    /// `(Φ K)ᵀ` (`m × 3n`): how a channel's measurement noise enters the next prediction's
    /// state through the observer; and the state index each channel reads (`H`'s one
    /// entry per row). For [`noise_driven_errors`].
    phi_gain_t: DMatrix<f64>,
    channel_state: Vec<usize>,
    /// Set by [`Predictor::concentrate`]: the pseudo-inverse of the initial state's
    /// information over a record of that many samples; [`innovations`] then returns the
    /// innovations with the initial state refitted (concentrated out).
    concentration: Option<(usize, DMatrix<f64>)>,
}

impl Predictor {
    /// Spectral radius of the linear part's closed loop `(I − K H) Φ` (< 1: the observer
    /// forgets an error; its memory is about `1/(1 − ρ)` samples). Computed when asked (24
    /// squarings of the `3n × 3n` loop, a third of building the observer): only the report
    /// of the answer's observer states it, not the likelihood tunings' dozens of observers.
    pub fn spectral_radius(&self) -> f64 {
        spectral_radius_by_powers(&self.closed)
    }

    /// From now on, [`innovations`] over records of `samples` samples returns the
    /// innovations *concentrated over the initial state*: `e − W H Ψᵏ δ̂(e)`, the
    /// residuals with the start state refitted by least squares (exact for the linear
    /// part, whose innovations are affine in it). A descent on them is variable projection
    /// (Golub & Pereyra 1973): the parameters and the start state are estimated jointly,
    /// not in alternation. Why: on an undamped structure an error in the start state rings
    /// for the whole record, and a descent with the start state held lets the joint damper
    /// absorb what the held state leaves (measured, cut records: `v` up to 6.9 errors off;
    /// ACCURACY.md).
    pub fn concentrate(&mut self, samples: usize) -> Option<()> {
        self.concentration = None;
        let m = self.whiten.nrows();
        let zeros = vec![0.0; samples * m];
        let (_, sum) = crate::estimate::kalman::initial_state_information(
            &self.psi_t,
            &self.wh_t,
            &self.wh,
            &zeros,
        );
        let pinv = crate::estimate::kalman::pseudo_inverse(&sum)?;
        self.concentration = Some((samples, pinv));
        Some(())
    }

    /// Whether [`Predictor::concentrate`] is in effect.
    pub fn is_concentrated(&self) -> bool {
        self.concentration.is_some()
    }

    /// `r ← r − W H Ψᵏ N⁺ λ(r)` (see [`Predictor::concentrate`]); nothing when not
    /// concentrated for this length.
    fn project(&self, r: &mut [f64]) {
        let m = self.whiten.nrows();
        let Some((len, pinv)) = self.concentration.as_ref() else {
            return;
        };
        if r.len() != len * m {
            return;
        }
        let nz = self.psi_t.nrows();
        let (mut lam, mut tmp) = (DVector::zeros(nz), DVector::zeros(nz));
        for i in (0..*len).rev() {
            let e = nalgebra::DVectorView::from_slice(&r[i * m..(i + 1) * m], m);
            tmp.gemv(1.0, &self.psi_t, &lam, 0.0);
            tmp.gemv(1.0, &self.wh_t, &e, 1.0);
            std::mem::swap(&mut lam, &mut tmp);
        }
        let mut v = pinv * lam;
        let psi = self.psi_t.transpose();
        let mut g = DVector::zeros(m);
        for w in r.chunks_mut(m) {
            g.gemv(1.0, &self.wh, &v, 0.0);
            for (x, y) in w.iter_mut().zip(g.iter()) {
                *x -= y;
            }
            tmp.gemv(1.0, &psi, &v, 0.0);
            std::mem::swap(&mut v, &mut tmp);
        }
    }

    /// Project the whitened innovation sensitivities `cols` (one column per parameter,
    /// `m` per sample) onto the complement of the initial state's (`W H Ψᵏ`): the
    /// Jacobian of the likelihood concentrated over the initial state, so the standard
    /// errors include its uncertainty (a parameter that trades off against the start's
    /// transient gets the wider error it deserves).
    pub fn project_out_initial_state(&self, cols: &mut [Vec<f64>]) {
        let m = self.whiten.nrows();
        let psi = self.psi_t.transpose();
        let (mut v, mut next) = (DVector::zeros(psi.nrows()), DVector::zeros(psi.nrows()));
        let mut g = DVector::zeros(m);
        for col in cols.iter_mut() {
            let Some((a, _)) = self.initial_state_solve(col) else {
                continue;
            };
            v.copy_from(&a);
            for w in col.chunks_mut(m) {
                g.gemv(1.0, &self.wh, &v, 0.0);
                for (x, y) in w.iter_mut().zip(g.iter()) {
                    *x -= y;
                }
                next.gemv(1.0, &psi, &v, 0.0);
                std::mem::swap(&mut v, &mut next);
            }
        }
    }

    /// The least-squares initial-state error `δ` of whitened innovations (or of any
    /// whitened column of the same shape) and `λ`, the right-hand side of its normal
    /// equations (`λᵀδ` is the cost it removes); see
    /// `kalman::initial_state_information`.
    fn initial_state_solve(&self, whitened: &[f64]) -> Option<(DVector<f64>, DVector<f64>)> {
        let (lam, sum) = crate::estimate::kalman::initial_state_information(
            &self.psi_t,
            &self.wh_t,
            &self.wh,
            whitened,
        );
        let (delta, _) = crate::estimate::kalman::pseudo_solve(&sum, &lam)?;
        Some((delta, lam))
    }

    /// What whitened innovations `r` of a run from rest say about the start: the cost a
    /// refitted start state would remove (`λᵀδ`, the likelihood-ratio statistic of "at
    /// rest", χ² under it when the innovations are white) and the rank of its information.
    pub fn start_state_reduction(&self, r: &[f64]) -> Option<(f64, usize)> {
        let (lam, sum) = crate::estimate::kalman::initial_state_information(
            &self.psi_t,
            &self.wh_t,
            &self.wh,
            r,
        );
        let (delta, rank) = crate::estimate::kalman::pseudo_solve(&sum, &lam)?;
        let reduction = lam.dot(&delta);
        reduction.is_finite().then_some((reduction.max(0.0), rank))
    }

    /// Refit the initial state from whitened innovations `r` (as [`innovations`] returns
    /// them) of a run that started from `self.initial`: the least-squares correction of
    /// the predicted state at the first sample (the innovations are affine in it for the
    /// linear part, `e_k = e⁰_k − H Ψᵏ δ`, `Ψ = Φ (I − K H)`; see
    /// `kalman::initial_state_information`), added to `self.initial`. Returns the
    /// whitened cost it removes.
    pub fn refit_initial_state(&mut self, r: &[f64]) -> Option<f64> {
        if self.concentration.is_some() {
            // Concentrated innovations hold no initial-state error left to fit.
            return None;
        }
        let (delta, lam) = self.initial_state_solve(r)?;
        let reduction = lam.dot(&delta);
        if !(reduction.is_finite() && delta.iter().all(|x| x.is_finite())) {
            return None;
        }
        let x = self.initial.get_or_insert_with(|| vec![0.0; delta.len()]);
        for (a, d) in x.iter_mut().zip(delta.iter()) {
            *a += d;
        }
        Some(reduction)
    }
}

fn is_sign(b: &Basis) -> bool {
    matches!(b, Basis::SignU | Basis::SignV)
}

/// Friction levels below zero are not a law the simulator can run; clamp them.
pub(crate) fn feasible(basis: &[Basis], p: &[f64]) -> Vec<f64> {
    p.iter()
        .zip(basis)
        .map(|(v, b)| if is_sign(b) { v.max(0.0) } else { *v })
        .collect()
}

/// The Gauss–Newton (or damped) step `A⁻¹g` with every friction level that sits on its
/// bound 0 and whose step would go below it held at 0 (an active set): the other parameters'
/// step is solved with it held, not taken from the unconstrained step and the level then
/// clipped. Why: on data without friction (the spring setup, truth 0) the unconstrained step
/// kept pushing the level below 0, the clip put it back, the step never fell below the
/// convergence tolerance, and the descent and the polish ran to their iteration limits
/// (measured: 24 Jacobians, 3.4 s of a 4.1 s identification at 64 sub-steps), each time
/// moving the other parameters by their correlation with a level that cannot move.
/// `None` if the free block is singular.
fn bounded_step(
    A: &DMatrix<f64>,
    g: &DVector<f64>,
    p: &[f64],
    basis: &[Basis],
) -> Option<DVector<f64>> {
    active_set_step(A, g, p, basis, false)
}

/// [`bounded_step`], and with `crossing` also every friction level above its bound whose step
/// would cross it: held at exactly 0 (its step `−p`), the others solved with that move. Why
/// (used by [`one_step_round`]): its steps start from the averaged model's centre, where a
/// level on the bound sits above it by its one-sided secant's mean displacement; stepped
/// freely and clipped, the other parameters moved with a level the answer does not have —
/// measured on the spring setup (friction truth 0, on the bound), `u` +0.08 to +0.19 errors
/// from the damped descent's answer on average in every row (ACCURACY.md, twenty-second
/// session). The damped descent and the polish keep the rule above (their sweeps were
/// measured with it).
fn active_set_step(
    A: &DMatrix<f64>,
    g: &DVector<f64>,
    p: &[f64],
    basis: &[Basis],
    crossing: bool,
) -> Option<DVector<f64>> {
    let n = p.len();
    let mut held = vec![false; n];
    loop {
        let free: Vec<usize> = (0..n).filter(|&j| !held[j]).collect();
        let mut dp = DVector::zeros(n);
        // A held level moves to its bound (from on it: not at all).
        for j in (0..n).filter(|&j| held[j]) {
            dp[j] = -p[j].max(0.0);
        }
        if free.is_empty() {
            return Some(dp);
        }
        let Af = DMatrix::from_fn(free.len(), free.len(), |a, b| A[(free[a], free[b])]);
        // The free block's right-hand side with the held moves taken out.
        let gf = DVector::from_fn(free.len(), |a, _| {
            g[free[a]]
                - (0..n)
                    .filter(|&h| held[h])
                    .map(|h| A[(free[a], h)] * dp[h])
                    .sum::<f64>()
        });
        let step = scaled_inverse(&Af)? * gf;
        for (a, &j) in free.iter().enumerate() {
            dp[j] = step[a];
        }
        let pinned: Vec<usize> = free
            .into_iter()
            .filter(|&j| {
                is_sign(&basis[j])
                    && if crossing && p[j] > 0.0 {
                        p[j] + dp[j] < 0.0
                    } else {
                        p[j] <= 0.0 && dp[j] < 0.0
                    }
            })
            .collect();
        if pinned.is_empty() {
            return Some(dp);
        }
        for j in pinned {
            held[j] = true;
        }
    }
}

/// The observer for the law `params` (its linear terms) with process-noise force `force_std`
/// (N per sample) at the connections and channel noise `sigma`, for a record of `samples`
/// samples (its gain's Riccati horizon, [`super::kalman::DARE_HORIZON_RECORDS`]).
pub fn predictor(
    setup: &Setup,
    model: &Model,
    params: &[f64],
    sigma: &[f64],
    substeps: usize,
    force_std: f64,
    samples: usize,
) -> Result<Predictor, SimulateError> {
    let n = model.n();
    let m = model.stations.len();
    if sigma.len() != m || !sigma.iter().all(|s| s.is_finite() && *s > 0.0) {
        return Err(SimulateError::Options(
            "prediction error: a positive noise std per channel is needed".into(),
        ));
    }
    let lin = model.with_connection_terms(setup, params);
    let mut stepper = Stepper::new(&lin, setup.dt_s, substeps, setup.newmark)
        .map_err(|_| SimulateError::Singular)?;
    let phi = stepper.transition();
    let gamma = stepper.force_response();
    let mut all = lin.clone();
    all.Lc = DMatrix::identity(n, n);
    let gamma_all = Stepper::new(&all, setup.dt_s, substeps, setup.newmark)
        .map_err(|_| SimulateError::Singular)?
        .force_response();
    let model_error = 1e-6 * force_std.max(force_scale_of(model));
    let Q = &gamma * gamma.transpose() * force_std.powi(2)
        + &gamma_all * gamma_all.transpose() * model_error.powi(2);
    let H = DMatrix::from_fn(m, 3 * n, |k, j| {
        let st = &model.stations[k];
        if st.quantity.block() * n + st.dof == j {
            1.0
        } else {
            0.0
        }
    });
    let V = DMatrix::from_diagonal(&DVector::from_iterator(m, sigma.iter().map(|s| s * s)));
    // Φ reads the state only through the first sub-step's predictors (rank 2n).
    let P = solve_filter_dare_factored(&phi, &stepper.predictor_map(), &H, &Q, &V, Some(samples));
    let S = &H * &P * H.transpose() + &V;
    let S = (&S + S.transpose()) * 0.5;
    let chol = S.cholesky().ok_or(SimulateError::Singular)?;
    let sinv = chol.inverse();
    let linv = chol.l().try_inverse().ok_or(SimulateError::Singular)?;
    let gain = &P * H.transpose() * &sinv;
    let closed = (DMatrix::identity(3 * n, 3 * n) - &gain * &H) * &phi;
    if !gain.iter().all(|x| x.is_finite()) {
        return Err(SimulateError::Singular);
    }
    let psi_t = (&phi * (DMatrix::identity(3 * n, 3 * n) - &gain * &H)).transpose();
    let wh = &linv * &H;
    let phi_gain_t = (&phi * &gain).transpose();
    let channel_state = model
        .stations
        .iter()
        .map(|st| st.quantity.block() * n + st.dof)
        .collect();
    Ok(Predictor {
        phi_gain_t,
        channel_state,
        psi_t,
        wh_t: wh.transpose(),
        wh,
        initial: None,
        concentration: None,
        gain,
        whiten: linv,
        force_std,
        closed,
    })
}

/// Normalised innovations `S^{-1/2}(y_i − ŷ_{i|i−1})`, stacked sample-major, and their sum of
/// squares.
pub fn innovations(
    setup: &Setup,
    model: &Model,
    params: &[f64],
    pred: &Predictor,
    excitation: &[Vec<f64>],
    response: &[Vec<f64>],
    substeps: usize,
) -> Result<(Vec<f64>, f64), SimulateError> {
    let basis = setup.param_basis();
    let m = pred.whiten.nrows();
    let mut r = Vec::with_capacity(excitation.len() * m);
    let (mut e, mut w) = (DVector::zeros(m), DVector::zeros(m));
    each_prediction_with_observer(
        setup,
        model,
        &feasible(&basis, params),
        excitation,
        response,
        setup.dt_s,
        substeps,
        &pred.gain,
        pred.initial.as_deref(),
        &mut |i, yi| {
            for ((d, z), y) in e.as_mut_slice().iter_mut().zip(&response[i]).zip(yi) {
                *d = z - y;
            }
            crate::dense::gemv(&mut w, &pred.whiten, &e, crate::dense::Op::Set);
            r.extend_from_slice(w.as_slice());
        },
    )?;
    pred.project(&mut r);
    let cost: f64 = r.iter().map(|x| x * x).sum();
    if !cost.is_finite() {
        return Err(SimulateError::Diverged(0));
    }
    Ok((r, cost))
}

/// Finite-difference step of the innovation sensitivities in the descent, in standard
/// errors: a secant over ±½ standard error. The innovations of a set-valued friction law are
/// piecewise smooth in the parameters (a zero crossing of δ moves by a sub-step as a
/// parameter moves); with the observer these steps are small and local, and a half-error
/// secant follows the cost's trend over the interval that matters (as
/// `output_error::SIGN_LAW_STEP` does for the free run). The polish and the stated errors
/// use wider ones ([`POLISH_SECANT`], [`ERROR_SECANTS`]).
const SECANT: f64 = 0.5;

/// Whether the descent's Jacobians in this round are forward differences over the same
/// width (`[p, p + 2h]` instead of `[p − h, p + h]`: one run per parameter instead of two):
/// in a round that another follows (the first of the two whole-record rounds, or a long
/// record's prefix round). Why: that round's end point is only where the next round starts
/// and builds its observer — the answer, its Jacobian, the polish and the error secants all
/// come from the last round, whose differences stay central — and a forward difference is
/// still a descent direction that the Levenberg–Marquardt test (a step is taken only when
/// the cost goes down) guards. Measured on the benchmark record: the refinement's predictor
/// runs 63 → 45; paired over 360 records (friction and spring setups, seeds 7001–7020, data
/// sub-steps 1, 8, 64, noise 1, 10, 100 %) coverage per row within one estimate of the
/// central differences', the median shift 0.00–0.26 errors (ACCURACY.md, thirtieth
/// session).
fn forward_differences(on_prefix: bool, whole_rounds_left: usize) -> bool {
    on_prefix || whole_rounds_left == 2
}

/// Damped steps tried per Levenberg–Marquardt iteration (μ raised tenfold after each that
/// does not lower the cost) before the descent stops.
const LM_TRIES: usize = 8;

/// The descent has converged when a step moves every parameter by at most this fraction of
/// its naive standard error.
const LM_TOL: f64 = 0.05;

/// Secant Gauss–Newton iterations after the Levenberg–Marquardt descent, without its
/// "the cost must go down" test: the innovation cost is still rough at a fraction of a
/// standard error (each zero crossing of δ that moves across a sub-step boundary is a small
/// jump), so a descent that only accepts lower costs stops wherever such a jump blocks it —
/// measured 10 % noise, seeds 1–4, a process-noise force of ~1,000 N: the end point moved by
/// up to ~1 standard error with a 0.03 % change of that force. The Gauss–Newton step on the
/// secant Jacobian (±2 errors, [`POLISH_SECANT`]) goes to the zero of the *smoothed*
/// gradient instead. Steps are clipped to `POLISH_TRUST` naive errors; it stops below
/// `POLISH_TOL` of them.
const POLISH_ITER: usize = 8;
const POLISH_TRUST: f64 = 2.0;
const POLISH_TOL: f64 = 0.05;

/// Half-width of the polish's secant, in naive standard errors. The derivative that governs
/// a prediction-error estimate on a non-smooth cost is that of the *expected* cost, which a
/// difference estimates only with a step large against the standard error (Pakes & Pollard
/// 1989; Newey & McFadden 1994, §7.3); a step of the order of the error sees single jumps.
/// Measured over 50 seeds (friction setup, data of the model's own discretisation, where
/// every zero crossing of δ that moves by a sample flips the friction for a whole sample),
/// with the errors of [`ERROR_SECANTS`], coverage at 10 % and 1 % noise (worst errors): ±½
/// error 92 % (5.0) and 90 % (4.6); ±2 errors 92 % (3.2) and 95 % (4.6); ±4 errors 90 %
/// (3.2) and 96 % (4.6), no better. On continuous data, where the cost is smooth at these
/// scales, the width hardly matters (8 sub-steps, 10 % noise: 96 → 98 %).
const POLISH_SECANT: f64 = 2.0;

/// Half-widths, in naive standard errors, of the two secants the stated errors come from;
/// each parameter's error is the larger of the two sandwiches. Where the cost is smooth they
/// agree (8-sub-step data: within 5 % from ±1 to ±8 errors). Where it is rough at the
/// error's scale (own-discretisation data with friction) the narrow secant sees single jumps
/// and overstates the slope: measured at 10 % noise, seed 41, the friction's error was 5.5 N
/// at ±1, 28 N at ±8, against a spread of ~70 N over seeds (it was 25 errors off). Where the
/// innovations curve over the wide range (100 % noise, ±8 errors reach far) the wide secant
/// can overstate the slope instead (friction worst 4.7 errors with it alone, 2.3 with the
/// larger of the two). Same sweeps as [`POLISH_SECANT`].
const ERROR_SECANTS: [f64; 2] = [1.0, 8.0];

/// Samples of the first descent round on a record longer than twice this: the
/// Levenberg–Marquardt descent from the start values runs on the record's first samples,
/// and the second round (the observer rebuilt at that point) refines the whole record from
/// there (since the twenty-second session by the one-step round, [`ONE_STEP_ITER`]). Why:
/// from the Kalman passes' values the descent needs several steps, each a
/// whole-record Jacobian (9 runs of the predictor) and its trials; on the prefix they cost
/// a fraction, and the whole record then starts within about `√(N/10,000)` of its errors
/// from its minimum, which a step or two reaches. The answer is still the whole record's
/// minimum with the observer built at a point near it, as before (the second round rebuilt
/// it at the first round's end point on the whole record). Measured (100,000 samples,
/// BENCHMARKS.md): the refinement's 52 whole-record predictor runs became 32 and 45 runs
/// on the prefix (about 5 whole-record runs' worth), 4.5 → 3.0 s. The whole round moved
/// 2.6 of its naive errors from the prefix's end point there; see [`PREFIX_REBUILD`] for
/// when it moves far more.
pub const DESCENT_PREFIX_SAMPLES: usize = 10_000;

/// After the prefix's round, the whole round's observer was built at the prefix's end,
/// whose own errors are `√(N/10,000)` times the whole record's: a whole round that moves
/// more than this many times that from it shows the prefix did not represent the record,
/// and a second whole round runs with the observer rebuilt at its end (as the second round
/// without a prefix always does). Why: the answer depends on where the observer was built,
/// slightly near the answer and much far from it. Measured: 100,000 samples (friction,
/// 8-sub-step data, 1 %): moved 2.6 errors, a rebuilt round changed no parameter by 0.005
/// errors and cost 0.9 s; 50,000 samples (spring, 8-sub-step data, 100 % noise, seed 1,
/// the Kalman passes' start `u` 25× the truth): moved 1,154 errors, `v` −2.22 errors off
/// without the rebuilt round, +0.30 with it (+0.22 before the prefix).
const PREFIX_REBUILD: f64 = 4.0;

/// After a long record's prefix round, the whole record is refined by the polish's steps
/// alone — secant Gauss–Newton on ±2-error secants ([`POLISH_SECANT`]) from the innovations'
/// model averaged over the round's Jacobians ([`PolishModel`]) — instead of a damped descent
/// followed by the polish, and stops at a looser tolerance ([`ONE_STEP_TOL`]) with its last
/// step added unrun. Why: the prefix's answer is within about `√(N/10,000)` whole-record
/// errors of the whole record's minimum, a start from which one Gauss–Newton step is already
/// as precise as the minimiser to first order (the one-step estimator: Le Cam 1956; Lehmann
/// & Casella, *Theory of Point Estimation*, §6.4); the damped descent's cost test is what a
/// rough cost defeats (it refused up to 6 damped trials in a row on the 100,000-sample
/// record of BENCHMARKS.md before the polish took over). At most [`ONE_STEP_ITER`] steps;
/// a first step beyond what the prefix's own errors explain ([`PREFIX_REBUILD`]) hands the
/// record back to the damped descent. Measured against the damped descent (ACCURACY.md,
/// twenty-second session): whole-record runs of the predictor 40–50 → 25–34; on 25,000-sample
/// records of continuous data every parameter within 0.42 errors of the former answer (most
/// within 0.2), coverage 100 % in every row either way; on data of the model's own
/// discretisation (the rough cost, where the answer depends on the path to it) ±2-error
/// secants (the polish's) moved answers by up to 1.1 errors where no bootstrap ran (24 seeds:
/// coverage 91–94 % against 94–96 %), ±1-error ones by up to 1.8 (not kept).
const ONE_STEP_ITER: usize = 4;

/// The Gauss–Newton step (in naive errors) under which the whole record's one-step round
/// ([`ONE_STEP_ITER`]) ends: well within its secants' ±2 errors, where their linear model of
/// the innovations holds. The polish's own tolerance (0.05) gave the same coverage on data of
/// the model's own discretisation (97–100 % against 97 %, 8 seeds per row) at 1.3–1.6× the
/// time.
pub const ONE_STEP_TOL: f64 = 0.5;

/// What the prediction-error refinement did (reported in the identification's
/// output-error report).
#[derive(Debug, Clone, serde::Serialize)]
pub struct PredictionErrorReport {
    /// Process-noise force std per sample at the connections, N (the observer's tuning).
    pub force_std: f64,
    /// Spectral radius of the observer's linear closed loop.
    pub spectral_radius: f64,
    /// Model sub-steps of the final refinement.
    pub substeps: usize,
    pub iterations: usize,
    /// Normalised innovation cost `Σ|S^{-1/2}e|²/(N m)` at the start values (over the
    /// first descent round's samples: a long record's prefix, [`DESCENT_PREFIX_SAMPLES`])
    /// and at the end (the whole record).
    pub cost_start: f64,
    pub cost_end: f64,
    /// A long record refined by the one-step round after its prefix ([`ONE_STEP_ITER`]):
    /// the whole record's Gauss–Newton steps it took; `None` for a short record, or a long
    /// one whose prefix did not represent it (the damped descent ran on the whole record).
    pub whole_record_steps: Option<usize>,
    /// Newey–West lag window of the sandwich's score covariance, samples (used for the
    /// errors of a record in motion, and for the noise shift's error).
    pub hac_lag: usize,
    /// Whether the sandwich's score covariance is the measurement noise's through the
    /// observer ([`noise_driven_errors`]: a record at rest) rather than the lag window's
    /// estimate from the residuals (a record in motion, an excitation that repeats itself or
    /// is smooth between samples — [`Wanted::ValuesAndLagWindowErrors`] — or where the free
    /// run failed).
    pub noise_driven_errors: bool,
    /// Stated (sandwich, the larger over [`ERROR_SECANTS`]) standard error over the naive
    /// `(JᵀJ)^{-1/2}` one of the ±1-error secant, per parameter.
    pub sandwich_ratio: Vec<f64>,
    /// How much the sandwich depends on the secant it is made from: the largest, over the
    /// parameters, of the ratio (≥ 1) between the errors over secants of ±1 and of ±8
    /// errors ([`ERROR_SECANTS`]); `None` when the wide secant could not be made. Near 1
    /// the innovations are linear in the parameters over their errors, which the sandwich
    /// (a linearisation) assumes; far above, the errors are the parametric bootstrap's
    /// (`identify::pem::BOOTSTRAP_SECANT_DISAGREEMENT`).
    pub secant_disagreement: Option<f64>,
    /// The innovation tests of "the record starts at rest" run after the refinement (at the
    /// kept level, and again at the likeliest when the first passed its limit); empty for a
    /// record identified as in motion.
    pub start_at_rest_tests: Vec<StartAtRestTest>,
    /// The shift of the estimate that the measurement noise causes through the observer,
    /// per parameter (its units), subtracted from the answer (see `noise_bias`); `None` when
    /// it could not be computed (the answer is then uncorrected) or the law has no term
    /// linear in the state.
    pub noise_shift: Option<Vec<f64>>,
    /// Why the noise shift could not be computed, when it could not (said in a note: the
    /// uncorrected answer can be biased).
    pub noise_shift_failure: Option<String>,
    /// When the excitation between samples was taken as smooth (`identify::pem`,
    /// "moment-matched" samples) rather than linear: the log-likelihood it gained (on the
    /// samples the observer force was tuned on: a long record's first 10,000).
    pub smooth_excitation_gain: Option<f64>,
    /// When the excitation repeats itself (`identify::pem::excitation_periodicity`): the
    /// autocorrelation of its strongest repeat and that repeat's lag in samples.
    pub periodic_excitation: Option<(f64, usize)>,
    /// When the excitation is an impact's (`identify::pem::excitation_impulse`): the share of
    /// the samples on which it is quiet (below 1 % of its peak on every channel).
    pub impulsive_excitation: Option<f64>,
    /// The parametric bootstrap, when asked for or automatic (`identify::pem::bootstrap`).
    pub bootstrap: Option<BootstrapReport>,
    /// When the refinement from the law without friction's answer was taken
    /// (`identify::pem::without_friction`): what it replaced and by how much.
    pub frictionless_refit: Option<FrictionlessRefit>,
}

/// A prediction-error answer replaced by the refinement from the law without friction's
/// answer (`identify::pem::without_friction`).
#[derive(Debug, Clone, serde::Serialize)]
pub struct FrictionlessRefit {
    /// How much likelier the refit ended than the replaced answer, in log-likelihood under
    /// the same observer, on the whole record.
    pub gain: f64,
    /// The replaced answer (the descent from the residual-force estimate), per parameter.
    pub replaced: Vec<f64>,
}

/// What the parametric bootstrap of a prediction-error answer found: `replicates` records
/// simulated from the answer with the noise levels `noise` (per channel), `used` of them
/// identified; per parameter the mean shift of their answers from the one they were
/// simulated from (`shift`, subtracted from the answer) and their spread (`spread`, a floor
/// under the errors).
#[derive(Debug, Clone, serde::Serialize)]
pub struct BootstrapReport {
    pub replicates: usize,
    pub used: usize,
    pub noise: Vec<f64>,
    pub shift: Vec<f64>,
    pub spread: Vec<f64>,
    /// Why no replicate was simulated, when none was.
    pub failure: Option<String>,
}

/// One likelihood-ratio test of a start at rest on the innovations: the cost a refitted start
/// state removes (`statistic`), against `limit` (the χ² quantile of `rank` degrees of freedom
/// at 1e-3, times the run's normalised cost when above 1), with `substeps` model sub-steps.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize)]
pub struct StartAtRestTest {
    pub substeps: usize,
    pub statistic: f64,
    pub limit: f64,
    pub rank: usize,
}

/// Result of [`refine`].
#[derive(Debug, Clone)]
pub struct PemRefined {
    pub values: Vec<f64>,
    /// Sandwich standard errors (see [`noise_driven_errors`]), widened for a friction on its
    /// bound.
    pub std_errors: Vec<f64>,
    /// Naive `(JᵀJ)^{-1/2}` of the normalised innovations (the error if the innovations had
    /// the variance the filter predicts: not a bound, reported as a diagnostic).
    pub naive: Vec<f64>,
    pub report: PredictionErrorReport,
    /// A record in motion: the initial state `(u; u̇; ü)` (offsets from rest) the last
    /// round's observer refitted, which the predicted response starts from.
    pub initial_state: Option<Vec<f64>>,
    /// The refinement's own answer: `values` before the bootstrap's mean shift was removed
    /// (`identify::pem`); the noise's shift through the observer is already removed here
    /// (as it has been since the field was added, though this note said otherwise until
    /// the fifty-sixth session's review; `Wanted::Descent` has no noise shift). Whether a
    /// friction ended on its bound is judged here: a level the descent left inside and the
    /// bootstrap's shift then took to 0 was determined by the innovations, and its
    /// likelihood ratio (`bound_likelihood_ratio`) was not computed.
    pub refined: Vec<f64>,
    /// Per parameter: for a friction level that ended on its bound 0 while the start had it
    /// positive, the likelihood-ratio statistic of the start's level against the bound — the
    /// rise of the innovation sum of squares when the level is set back to the start's (the
    /// other parameters as found, or moved by one Gauss–Newton step with the level held,
    /// whichever costs less), over the residual variance `max(cost_end, 1)`. About χ²₁ if the
    /// start's level were the truth; near 0 when the observer absorbs the friction (the cost
    /// is flat). `None` for every other parameter.
    pub bound_likelihood_ratio: Vec<Option<f64>>,
}

struct Jac {
    r: Vec<f64>,
    cols: Vec<Vec<f64>>,
    cost: f64,
    /// The mean of the innovations of every run the Jacobian was made from (the base and
    /// the displaced points) and the mean of those points: the innovations smoothed over
    /// the secants' width, for the polish's averaged model ([`PolishModel`]).
    r_mean: Vec<f64>,
    p_mean: Vec<f64>,
}

/// The polish's model of the innovations, `r(p) ≈ r̄ − J̄ (p − p̄)`: the mean of its
/// Jacobians' secant columns `J̄`, and the mean `r̄` of the innovations of every run they
/// were made from at the mean `p̄` of those points. Why: on a rough cost (friction whose
/// stick–slip switches move by sub-steps as the parameters move) each secant Jacobian and
/// the innovations at its point carry their own draw of the roughness, and the Gauss–Newton
/// step from one of them wandered by 0.3–2 naive errors per step without converging (the
/// shipped free-decay and sine friction records: all eight polish steps used, the answer
/// where the eighth happened to stop, 2.8 errors apart between two start points of equal
/// cost). The averaged model is a linear regression of the innovations on the parameters
/// over every point the polish ran (the points lie within a few errors, where the
/// innovations are nearly linear): its minimiser settles as the draws average out, and
/// where the cost is smooth it is the Gauss–Newton step itself (a linear model's average is
/// itself).
struct PolishModel {
    count: f64,
    r: Vec<f64>,
    p: Vec<f64>,
    cols: Vec<Vec<f64>>,
}

impl PolishModel {
    fn new(j: &Jac) -> Self {
        Self {
            count: 1.0,
            r: j.r_mean.clone(),
            p: j.p_mean.clone(),
            cols: j.cols.clone(),
        }
    }

    fn add(&mut self, j: &Jac) {
        let sum = |a: &mut [f64], b: &[f64]| a.iter_mut().zip(b).for_each(|(x, y)| *x += y);
        let c = self.count;
        // Running sums, scaled back to means below (all vectors by the same count).
        for v in self.r.iter_mut().chain(self.p.iter_mut()) {
            *v *= c;
        }
        for col in &mut self.cols {
            col.iter_mut().for_each(|x| *x *= c);
        }
        sum(&mut self.r, &j.r_mean);
        sum(&mut self.p, &j.p_mean);
        for (col, new) in self.cols.iter_mut().zip(&j.cols) {
            sum(col, new);
        }
        self.count = c + 1.0;
        let inv = 1.0 / self.count;
        for v in self.r.iter_mut().chain(self.p.iter_mut()) {
            *v *= inv;
        }
        for col in &mut self.cols {
            col.iter_mut().for_each(|x| *x *= inv);
        }
    }

    /// `J̄ᵀJ̄`, `J̄ᵀr̄` and `p̄`: the Gauss–Newton step from `p̄` is the model's minimiser.
    fn normal(&self) -> (DMatrix<f64>, DVector<f64>, Vec<f64>) {
        let (F, g) = normal_of(&self.cols, &self.r);
        (F, g, self.p.clone())
    }
}

#[allow(clippy::too_many_arguments)]
fn jacobian(
    setup: &Setup,
    model: &Model,
    basis: &[Basis],
    p: &[f64],
    scales: &[f64],
    pred: &Predictor,
    exc: &[Vec<f64>],
    resp: &[Vec<f64>],
    substeps: usize,
    base: Option<(Vec<f64>, f64)>,
    forward: bool,
) -> Result<Jac, SimulateError> {
    // The base point and every displaced point are independent simulations: run them on
    // parallel threads (`crate::par`), then difference. `base`: the innovations and cost at
    // `p` with this predictor when the caller has them (an accepted descent step's trial
    // run, the Jacobian just made at the same point) — the same run, not made twice: four
    // parameters' central differences are then 8 runs, 4 rounds on two cores instead of 5.
    let steps = super::difference_steps(SECANT, scales, p);
    // Forward differences over the same width (`[p, p + 2h]`).
    let steps: Vec<f64> = if forward {
        steps.iter().map(|h| 2.0 * h).collect()
    } else {
        steps
    };
    let t0 = std::time::Instant::now();
    let have_base = base.is_some();
    let mut points: Vec<Vec<f64>> = if have_base {
        Vec::new()
    } else {
        vec![p.to_vec()]
    };
    // One-sided at a friction level's bound 0 (the simulator cannot run a negative one).
    if forward {
        points.extend((0..p.len()).map(|j| {
            let mut plus = p.to_vec();
            plus[j] += steps[j];
            plus
        }));
    } else {
        points.extend(super::difference_points(basis, p, &steps));
    }
    let mut runs = crate::par::map(&points, |q| {
        innovations(setup, model, q, pred, exc, resp, substeps)
    })
    .into_iter();
    let (r, cost) = match base {
        Some(known) => known,
        None => runs.next().ok_or(SimulateError::Singular)??,
    };
    let mut r_mean = r.clone();
    let mut p_mean = p.to_vec();
    let mut count = 1.0;
    let mut add = |q: &[f64], rq: &[f64]| {
        for (a, b) in r_mean.iter_mut().zip(rq) {
            *a += b;
        }
        for (a, b) in p_mean.iter_mut().zip(q) {
            *a += b;
        }
        count += 1.0;
    };
    let mut cols = Vec::with_capacity(p.len());
    for j in 0..p.len() {
        let h = steps[j];
        let (rp, _) = runs.next().ok_or(SimulateError::Singular)??;
        let mut plus = p.to_vec();
        plus[j] += h;
        add(&plus, &rp);
        // Columns of ∂ŷ/∂p in normalised units: the residual is y − ŷ, so −∂r/∂p.
        let col: Vec<f64> = if forward || super::one_sided_difference(&basis[j], p[j], h) {
            rp.iter().zip(&r).map(|(a, b)| -(a - b) / h).collect()
        } else {
            let (rm, _) = runs.next().ok_or(SimulateError::Singular)??;
            let mut minus = p.to_vec();
            minus[j] -= h;
            add(&minus, &rm);
            rp.iter()
                .zip(&rm)
                .map(|(a, b)| -(a - b) / (2.0 * h))
                .collect()
        };
        cols.push(col);
    }
    for a in r_mean.iter_mut().chain(p_mean.iter_mut()) {
        *a /= count;
    }
    crate::par::phase(
        if have_base {
            "jacobian (base known)"
        } else {
            "jacobian"
        },
        t0,
    );
    Ok(Jac {
        r,
        cols,
        cost,
        r_mean,
        p_mean,
    })
}

/// The whitened innovations at `p` and the central-difference columns of `∂ŷ/∂p` (in the
/// innovations' whitened units, secants of [`SECANT`] of `scales`) with the observer `pred`:
/// what a Gauss–Newton step from `p` needs ([`gauss_newton_step`]). For the model sub-step
/// choice (`identify::pem`), which compares every level at its own best values, not at a
/// start fitted at one of them.
#[allow(clippy::too_many_arguments)]
pub(crate) fn innovation_jacobian(
    setup: &Setup,
    model: &Model,
    p: &[f64],
    scales: &[f64],
    pred: &Predictor,
    excitation: &[Vec<f64>],
    response: &[Vec<f64>],
    substeps: usize,
) -> Result<(Vec<f64>, Vec<Vec<f64>>), SimulateError> {
    let basis = setup.param_basis();
    let j = jacobian(
        setup, model, &basis, p, scales, pred, excitation, response, substeps, None, false,
    )?;
    Ok((j.r, j.cols))
}

/// The Gauss–Newton step `δ = (JᵀJ)⁻¹ Jᵀ r` that takes whitened innovations `r` towards
/// their least squares along the columns `cols` of `∂ŷ/∂p` (`r(p + δ) ≈ r − J δ`); `None`
/// when `JᵀJ`, scaled to a unit diagonal, has a condition number above 1e12 (a column
/// the others nearly repeat: the step along it is not determined), or the step is not finite.
pub(crate) fn gauss_newton_step(cols: &[Vec<f64>], r: &[f64]) -> Option<Vec<f64>> {
    let (F, g) = normal_of(cols, r);
    let d: Vec<f64> = (0..F.nrows()).map(|j| F[(j, j)]).collect();
    if d.iter().any(|x| x.is_nan() || *x <= 0.0) {
        return None;
    }
    let scaled = DMatrix::from_fn(F.nrows(), F.ncols(), |a, b| {
        F[(a, b)] / (d[a] * d[b]).sqrt()
    });
    let eig = scaled.symmetric_eigenvalues();
    let (lo, hi) = eig.iter().fold((f64::INFINITY, 0.0f64), |(lo, hi), &x| {
        (lo.min(x), hi.max(x))
    });
    if lo.is_nan() || hi.is_nan() || lo <= 1e-12 * hi {
        return None;
    }
    let inv = scaled_inverse(&F)?;
    let step: Vec<f64> = (&inv * g).iter().copied().collect();
    step.iter().all(|x| x.is_finite()).then_some(step)
}

/// The largest move from `from` to `p` in naive standard errors of `j` (∞ when its normal
/// matrix is singular).
fn moved_beyond(j: &Jac, p: &[f64], from: &[f64]) -> f64 {
    let Some(inv) = scaled_inverse(&normal(j).0) else {
        return f64::INFINITY;
    };
    p.iter()
        .zip(from)
        .enumerate()
        .map(|(a, (x, b))| (x - b).abs() / inv[(a, a)].max(0.0).sqrt())
        .fold(0.0, f64::max)
}

fn normal(j: &Jac) -> (DMatrix<f64>, DVector<f64>) {
    normal_of(&j.cols, &j.r)
}

/// Per channel, the variance of the measurement noise the answer `p` leaves in the record:
/// the mean square of the record less the model's free run from rest at `p`, at most
/// `sigma²` (the channels' noise estimate) — the levels of the parametric bootstrap's
/// records (`identify::pem::bootstrap`, there after the noise shift), about the same. A misfit of the model
/// counts as noise: conservative. The free run through the sample maps (an observer of
/// gain 0), whose round-off does not matter to a mean square. `None` when it fails.
fn residual_noise_variance(
    setup: &Setup,
    model: &Model,
    p: &[f64],
    excitation: &[Vec<f64>],
    response: &[Vec<f64>],
    sigma: &[f64],
    substeps: usize,
) -> Option<Vec<f64>> {
    let m = sigma.len();
    let free = crate::simulate::predictions_with_observer(
        setup,
        model,
        &feasible(&setup.param_basis(), p),
        excitation,
        response,
        setup.dt_s,
        substeps,
        &DMatrix::zeros(3 * model.n(), m),
        None,
    )
    .ok()?;
    let n = free.len().min(response.len());
    let var: Vec<f64> = (0..m)
        .map(|k| {
            let ms = (0..n)
                .map(|i| (response[i].get(k).copied().unwrap_or(0.0) - free[i][k]).powi(2))
                .sum::<f64>()
                / n.max(1) as f64;
            ms.min(sigma[k] * sigma[k])
        })
        .collect();
    (n > 0 && var.iter().all(|v| v.is_finite() && *v > 0.0)).then_some(var)
}

/// Standard errors of a prediction-error answer from the measurement noise that drives it:
/// `√diag(F⁻¹ B F⁻¹)`, `F = JᵀJ`, with the score's covariance `B` computed exactly from
/// white channel noise of variances `noise_var` (data units) through the observer, instead
/// of estimated from the residuals by a lag window. `None` when `F` is singular or a
/// figure is not finite.
///
/// How: near the answer the innovations' noise part is `e = 𝓗 v` — `v` the measurement
/// noise, `𝓗` the observer's linear filter (`x_{i+1} = Φ(I − KH) x_i + Φ K v_i`,
/// `e_i = v_i − H x_i`) — and the Gauss–Newton score is `s = Σ_i ψ_iᵀ W e_i` (`ψ_i` the
/// whitened Jacobian rows of sample `i`, `W` the whitening). So `s = Σ_j φ_jᵀ v_j` with
/// `φ_j = g_j − (Φ K)ᵀ μ_j`, `g_j = Wᵀ ψ_j`, and `μ` the adjoint run backwards,
/// `μ_{j−1} = (Φ(I − KH))ᵀ μ_j + Hᵀ g_j` from `μ_{N−1} = 0`; `B = Σ_j φ_jᵀ V φ_j` — one
/// backward pass of the record, no lag window, the observer's whole memory included.
///
/// Why (fortieth session): the Newey–West sandwich of the residuals' scores stated
/// `v`'s error 3–4× and `sign(u)`'s and `u`'s about 1.8× the spread of the estimates, and
/// `const`'s 0.7× — the observer's closed loop has a mode at the unit circle (spectral
/// radius 1.000001), so the scores' autocovariance reaches far beyond any lag window and
/// the window keeps the wrong part of it. Measured on the spring setup, 64-sub-step data,
/// 1 % noise, seed 7701: the sandwich 31.7, 216, 0.117, 0.0124; a parametric bootstrap's
/// spread (20 records simulated from the answer, each refined again) 17.5, 121, 0.163,
/// 0.00335; this 18.6, 121, 0.148, 0.00377 (ACCURACY.md, fortieth session).
fn noise_driven_errors(pred: &Predictor, j: &Jac, m: usize, noise_var: &[f64]) -> Option<Vec<f64>> {
    let p = j.cols.len();
    let score = noise_score_covariance(pred, j, m, noise_var)?;
    // F⁻¹ B F⁻¹ in the parameters scaled by F's diagonal (as `sandwich`).
    let (F, _) = normal(j);
    let inv = scaled_inverse(&F)?;
    let scale: Vec<f64> = (0..p).map(|a| F[(a, a)].sqrt()).collect();
    let inv_s = DMatrix::from_fn(p, p, |a, b| inv[(a, b)] * scale[a] * scale[b]);
    let score_s = DMatrix::from_fn(p, p, |a, b| score[(a, b)] / (scale[a] * scale[b]));
    let cov_s = &inv_s * score_s * &inv_s;
    let se: Vec<f64> = (0..p)
        .map(|a| cov_s[(a, a)].max(0.0).sqrt() / scale[a])
        .collect();
    se.iter().all(|x| x.is_finite()).then_some(se)
}

/// The covariance `B = Σ_j φ_jᵀ V φ_j` of the score `Σ_i ψ_iᵀ r_i` (`ψ_i` the rows of
/// `j`'s columns for sample `i`, `r` whitened innovations) that white channel noise of
/// variances `noise_var` gives through the observer `pred` (see [`noise_driven_errors`]).
fn noise_score_covariance(
    pred: &Predictor,
    j: &Jac,
    m: usize,
    noise_var: &[f64],
) -> Option<DMatrix<f64>> {
    use crate::dense::{Op, gemv, gemv_slices};
    let p = j.cols.len();
    if m == 0 || noise_var.len() != m || pred.channel_state.len() != m || p == 0 {
        return None;
    }
    let n = j.r.len() / m;
    let nz = pred.psi_t.nrows();
    let w_t = pred.whiten.transpose();
    let mut mu: Vec<DVector<f64>> = vec![DVector::zeros(nz); p];
    let mut next = DVector::zeros(nz);
    let mut psi = DVector::zeros(m);
    let mut g: Vec<DVector<f64>> = vec![DVector::zeros(m); p];
    let mut phi: Vec<DVector<f64>> = vec![DVector::zeros(m); p];
    let mut score = DMatrix::<f64>::zeros(p, p);
    for i in (0..n).rev() {
        for a in 0..p {
            psi.copy_from_slice(&j.cols[a][i * m..(i + 1) * m]);
            gemv(&mut g[a], &w_t, &psi, Op::Set);
            phi[a].copy_from(&g[a]);
            gemv(&mut phi[a], &pred.phi_gain_t, &mu[a], Op::Subtract);
        }
        for a in 0..p {
            for b in a..p {
                let v: f64 = (0..m).map(|k| phi[a][k] * noise_var[k] * phi[b][k]).sum();
                score[(a, b)] += v;
            }
        }
        for a in 0..p {
            gemv_slices(next.as_mut_slice(), &pred.psi_t, mu[a].as_slice(), Op::Set);
            for (k, &state) in pred.channel_state.iter().enumerate() {
                next[state] += g[a][k];
            }
            std::mem::swap(&mut mu[a], &mut next);
        }
    }
    for a in 0..p {
        for b in 0..a {
            score[(a, b)] = score[(b, a)];
        }
    }
    score.iter().all(|x| x.is_finite()).then_some(score)
}

/// `JᵀJ` and `Jᵀr` of columns `cols` and innovations `r`.
fn normal_of(cols: &[Vec<f64>], r: &[f64]) -> (DMatrix<f64>, DVector<f64>) {
    let p = cols.len();
    // Each product once: `cols[b]·cols[a]` is `cols[a]·cols[b]` bit for bit.
    let mut F = DMatrix::zeros(p, p);
    for a in 0..p {
        for b in a..p {
            let v: f64 = cols[a].iter().zip(&cols[b]).map(|(x, y)| x * y).sum();
            F[(a, b)] = v;
            F[(b, a)] = v;
        }
    }
    let g = DVector::from_fn(p, |a, _| cols[a].iter().zip(r).map(|(x, y)| x * y).sum());
    (F, g)
}

/// Sandwich `A⁻¹ B A⁻¹` with `A = JᵀJ` and `B` the Bartlett-weighted long-run covariance of
/// the per-sample scores `sᵢ = Σ_k J_ikᵀ r_ik` (lag window: Andrews' AR(1) plug-in on the
/// scores, doubled for coverage and capped at N/4, as `refit::hac_covariance`). Returns the
/// standard errors, the naive ones and the lag.
fn sandwich(j: &Jac, m: usize) -> Option<(Vec<f64>, Vec<f64>, usize)> {
    let p = j.cols.len();
    let n = j.r.len() / m;
    let (F, _) = normal(j);
    let inv = scaled_inverse(&F)?;
    let naive: Vec<f64> = (0..p).map(|a| inv[(a, a)].max(0.0).sqrt()).collect();
    // Scores in the scaled parameters (each column over its norm).
    let scale: Vec<f64> = (0..p).map(|a| 1.0 / F[(a, a)].sqrt()).collect();
    let s: Vec<Vec<f64>> = (0..n)
        .map(|i| {
            (0..p)
                .map(|a| {
                    (0..m)
                        .map(|k| j.cols[a][i * m + k] * j.r[i * m + k])
                        .sum::<f64>()
                        * scale[a]
                })
                .collect()
        })
        .collect();
    // Lag-one autocorrelation of the scores (largest over the parameters).
    let mut rho: f64 = 0.0;
    for a in 0..p {
        let (mut num, mut den) = (0.0, 0.0);
        for w in s.windows(2) {
            num += w[1][a] * w[0][a];
            den += w[0][a] * w[0][a];
        }
        if den > 0.0 {
            let r = (num / den).clamp(-0.99, 0.99);
            if r.abs() > rho.abs() {
                rho = r;
            }
        }
    }
    let alpha = 4.0 * rho * rho / ((1.0 - rho).powi(2) * (1.0 + rho).powi(2));
    let lag = ((2.0 * 1.1447 * (alpha * n as f64).cbrt()).ceil() as usize)
        .max(1)
        .min(n / 4);
    let flat: Vec<f64> = s.iter().flatten().copied().collect();
    let B = crate::estimate::refit::bartlett_long_run_covariance(&flat, p, lag);
    // F⁻¹ in the scaled coordinates: D⁻¹ F⁻¹ D⁻¹ with D = diag(scale).
    let inv_s = DMatrix::from_fn(p, p, |a, b| inv[(a, b)] / (scale[a] * scale[b]));
    let cov_s = &inv_s * B * &inv_s;
    let se: Vec<f64> = (0..p)
        .map(|a| cov_s[(a, a)].max(0.0).sqrt() * scale[a])
        .collect();
    se.iter()
        .chain(&naive)
        .all(|x| x.is_finite())
        .then_some((se, naive, lag))
}

/// The innovation sum of squares with friction level `j` set back to `level` (the start's):
/// the smaller of two points — the other parameters as in `p`, and moved by the
/// Gauss–Newton step of the final Jacobian `jac` with level `j` held (an approximate
/// profile: the stiffness a friction trades with follows it), and that point. `None` if
/// both runs fail.
#[allow(clippy::too_many_arguments)]
fn back_to_start_level(
    setup: &Setup,
    model: &Model,
    basis: &[Basis],
    p: &[f64],
    j: usize,
    level: f64,
    jac: &Jac,
    pred: &Predictor,
    exc: &[Vec<f64>],
    resp: &[Vec<f64>],
    substeps: usize,
) -> Option<(f64, Vec<f64>)> {
    let mut held = p.to_vec();
    held[j] = level;
    let mut points = vec![held.clone()];
    // Linearised residual with the level moved: r − J_j·Δ; the others' step solves
    // min |r − J_j·Δ − J_o·δ|² (columns are −∂r/∂p).
    let others: Vec<usize> = (0..p.len()).filter(|&k| k != j).collect();
    if !others.is_empty() {
        let delta = level - p[j];
        let r: Vec<f64> = jac
            .r
            .iter()
            .zip(&jac.cols[j])
            .map(|(a, c)| a - c * delta)
            .collect();
        let F = DMatrix::from_fn(others.len(), others.len(), |a, b| {
            jac.cols[others[a]]
                .iter()
                .zip(&jac.cols[others[b]])
                .map(|(x, y)| x * y)
                .sum()
        });
        let g = DVector::from_fn(others.len(), |a, _| {
            jac.cols[others[a]].iter().zip(&r).map(|(x, y)| x * y).sum()
        });
        if let Some(inv) = scaled_inverse(&F) {
            let step = inv * g;
            let mut profiled = held;
            for (a, &k) in others.iter().enumerate() {
                profiled[k] += step[a];
            }
            points.push(feasible(basis, &profiled));
        }
    }
    crate::par::map(&points, |q| {
        innovations(setup, model, q, pred, exc, resp, substeps).map(|x| x.1)
    })
    .into_iter()
    .zip(points)
    .filter_map(|(c, q)| c.ok().map(|c| (c, q)))
    .min_by(|a, b| a.0.total_cmp(&b.0))
}

/// Below this likelihood-ratio statistic (χ²₁ at 95 %) the innovations do not tell a
/// friction level on its bound 0 from the start's level: the result stands, with intervals
/// that reach the start's point. Why not refuse (as before): the fallback, the free-run
/// output error, misfits data finer than the model. Measured on the shipped spring setup
/// (friction truth 0), 64-sub-step data, 1 % noise, seeds 22 and 49: starts of 100 ± 42 N
/// and 27 ± 9 N, the prediction error on the bound, statistics 0.77 and 0.25; refused, the
/// output error (normalised cost 9.1) put the spring 26 and 21 se off.
pub const FLAT_BOUND_LR: f64 = 3.84;

/// Narrowest secant of a parameter relative to the start's standard error. Why: the widths
/// follow the naive errors of the last Jacobian, and a friction level on its bound 0 in a
/// window in motion collapsed them — a one-sided secant of a few newtons met the switching
/// of `sign(u)`, gave a large column and a small error, the next secant was narrower, and
/// after a few iterations a 1e-18 N step differenced round-off (`sign(u)` 0 ± 2.4e-17 N,
/// shipped spring setup, live at 10 kHz, window 200,000); a column of round-off corrupts
/// the other parameters' errors through the sandwich.
const MIN_SECANT_OF_START: f64 = 1e-3;

/// A Gauss–Newton step of a secant model of the innovations (`F = JᵀJ`, `g = Jᵀr` at
/// `centre`), as the polish and the one-step round take it.
struct ModelStep {
    /// Where the model's minimum is (feasible; friction levels held by the active set,
    /// [`active_set_step`] with its `crossing`).
    target: Vec<f64>,
    /// The naive errors `(JᵀJ)^{-1/2}` of the model.
    naive: Vec<f64>,
    /// The largest move from the point stepped from to `target`, in those errors.
    worst: f64,
}

/// The step of [`ModelStep`] from `from`; `None` when the model (or its free block) is
/// singular.
fn model_step(
    F: &DMatrix<f64>,
    g: &DVector<f64>,
    centre: &[f64],
    from: &[f64],
    basis: &[Basis],
    crossing: bool,
) -> Option<ModelStep> {
    let inv = scaled_inverse(F)?;
    let naive: Vec<f64> = (0..from.len())
        .map(|a| inv[(a, a)].max(0.0).sqrt())
        .collect();
    let dp = active_set_step(F, g, centre, basis, crossing)?;
    let target = feasible(
        basis,
        &centre
            .iter()
            .zip(dp.iter())
            .map(|(a, b)| a + b)
            .collect::<Vec<_>>(),
    );
    let worst = target
        .iter()
        .zip(from)
        .zip(&naive)
        .map(|((t, a), b)| (t - a).abs() / b)
        .fold(0.0, f64::max);
    Some(ModelStep {
        target,
        naive,
        worst,
    })
}

/// `from` moved toward `target`, the move clipped to [`POLISH_TRUST`] naive errors (`worst`:
/// the whole move's size in them).
fn clipped_move(basis: &[Basis], from: &[f64], target: &[f64], worst: f64) -> Vec<f64> {
    let shrink = (POLISH_TRUST / worst).min(1.0);
    feasible(
        basis,
        &from
            .iter()
            .zip(target)
            .map(|(a, t)| a + shrink * (t - a))
            .collect::<Vec<_>>(),
    )
}

/// How a whole record's one-step round ([`one_step_round`]) ended.
enum OneStep {
    /// A step under [`ONE_STEP_TOL`] naive errors: the last Jacobian (a ±2-error secant),
    /// the point it was made at, and the answer (that point plus the step, unrun).
    Settled {
        jac: Jac,
        at: Vec<f64>,
        answer: Vec<f64>,
        steps: usize,
    },
    /// The first step reached beyond what the prefix's own errors explain, or the steps did
    /// not settle: the prefix did not represent the record, and the damped descent goes on
    /// from `at` (the last point run).
    Unsettled { at: Vec<f64> },
}

/// The whole record's Gauss–Newton steps after a long record's prefix round (see
/// [`ONE_STEP_ITER`]): from `start`, the ±2-error secant Jacobian (widths from `scales`,
/// the expected naive errors), a step, and again while the step moved more than
/// [`ONE_STEP_TOL`] naive errors. Steps are clipped to [`POLISH_TRUST`] errors, as the
/// polish's. A first step beyond `representative` errors means the prefix's answer is not
/// near the whole record's minimum (the one-step estimator's premise): the round stops at
/// once.
#[allow(clippy::too_many_arguments)]
fn one_step_round(
    setup: &Setup,
    model: &Model,
    basis: &[Basis],
    start: &[f64],
    scales: &[f64],
    at_least: &dyn Fn(&[f64]) -> Vec<f64>,
    pred: &Predictor,
    excitation: &[Vec<f64>],
    response: &[Vec<f64>],
    substeps: usize,
    representative: f64,
    iterations: &mut usize,
) -> Result<OneStep, SimulateError> {
    let width = |naive: &[f64]| -> Vec<f64> {
        at_least(naive)
            .iter()
            .map(|x| x * POLISH_SECANT / SECANT)
            .collect()
    };
    let mut at = start.to_vec();
    let mut jac = jacobian(
        setup,
        model,
        basis,
        &at,
        &width(scales),
        pred,
        excitation,
        response,
        substeps,
        None,
        false,
    )?;
    // The steps come from the innovations' model averaged over the round's Jacobians, as
    // the polish's ([`PolishModel`]): on a rough cost (data of the model's own
    // discretisation with friction) the innovations at one point are one draw of the
    // roughness, and a step from them scattered the answer by up to 2 errors from the
    // polish's (ACCURACY.md).
    let mut averaged = PolishModel::new(&jac);
    for step in 1..=ONE_STEP_ITER {
        *iterations += 1;
        let (F, g, centre) = averaged.normal();
        let Some(ModelStep {
            target,
            naive,
            worst,
        }) = model_step(&F, &g, &centre, &at, basis, true)
        else {
            break;
        };
        if !worst.is_finite() || (step == 1 && worst > representative) {
            break;
        }
        if worst <= ONE_STEP_TOL {
            return Ok(OneStep::Settled {
                jac,
                at,
                answer: target,
                steps: step,
            });
        }
        if step == ONE_STEP_ITER {
            break;
        }
        at = clipped_move(basis, &at, &target, worst);
        jac = jacobian(
            setup,
            model,
            basis,
            &at,
            &width(&naive),
            pred,
            excitation,
            response,
            substeps,
            None,
            false,
        )?;
        averaged.add(&jac);
    }
    Ok(OneStep::Unsettled { at })
}

/// What a [`refine`] call is for.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Wanted {
    /// The answer and its stated errors (the sandwich over both error secants, the bound
    /// rule's likelihood ratio).
    ValuesAndErrors,
    /// The same, the sandwich's score covariance estimated from the residuals by a
    /// Newey–West lag window (as for a record in motion) instead of computed from the noise
    /// through the observer ([`noise_driven_errors`]): for an excitation that repeats
    /// itself or is smooth between samples (`identify::pem`), where the noise moves a
    /// friction's switching the same way in every cycle — an effect of the noise that is not
    /// linear, which the computed covariance leaves out and the residuals carry — and where
    /// the automatic bootstrap's floor was measured on the lag window's errors. Measured
    /// (fortieth session): the shipped sine recording's damper came out 2.05 of the
    /// computed errors off, 1.26 of the lag window's (bootstrap spread 0.022, error 0.065).
    ValuesAndLagWindowErrors,
    /// The answer's values alone: a parametric bootstrap replicate, whose stated errors
    /// nobody reads (the bootstrap takes the replicates' spread). The same values to the bit
    /// — the descent, the polish, the narrow error secant (whose Jacobian and lag the noise
    /// shift uses) and the noise shift all run — without the runs that only state errors:
    /// the wide error secant (8 predictor runs of a four-parameter law, ~12 % of a
    /// replicate) and the bound rule's look back at the start's friction level.
    Values,
    /// The descent's end alone (after the polish): no error secant, no noise shift (so
    /// `refined` and `values` are the descent's point, where the other variants' have the
    /// noise shift removed), no errors (`std_errors`, `naive` and `sandwich_ratio` NaN, no
    /// bound likelihood ratio), the start state not made explicit, `cost_end` the last point
    /// run's. For the law without friction's answer (`identify::pem::without_friction`),
    /// from which the full law is refined again when it is likelier.
    Descent,
}

/// Levenberg–Marquardt on the innovation cost from `start` with the observer built at
/// `start` (process-noise force `force_std` N per sample), at most `max_iter` Jacobians,
/// then once more with the observer rebuilt at the result; standard errors by the sandwich.
/// `scales` are the start's standard errors (the first secant widths). A record longer than
/// twice [`DESCENT_PREFIX_SAMPLES`] descends on its prefix, then takes the one-step round on
/// the whole record ([`ONE_STEP_ITER`]).
#[allow(clippy::too_many_arguments)]
pub fn refine(
    setup: &Setup,
    model: &Model,
    start: &[f64],
    scales: &[f64],
    excitation: &[Vec<f64>],
    response: &[Vec<f64>],
    sigma: &[f64],
    substeps: usize,
    force_std: f64,
    max_iter: usize,
    initial: Option<&[f64]>,
    wanted: Wanted,
) -> Result<PemRefined, SimulateError> {
    let basis = setup.param_basis();
    let m = sigma.len();
    let nobs = (excitation.len() * m) as f64;
    let mut p = feasible(&basis, start);
    let mut scales: Vec<f64> = scales
        .iter()
        .zip(&p)
        .map(|(s, v)| {
            let s = s.abs().max(1e-6 * v.abs());
            if s.is_finite() && s > 0.0 { s } else { 1e-6 }
        })
        .collect();
    let start_errors = scales.clone();
    // No secant narrower than 1e-3 of the start's error ([`MIN_SECANT_OF_START`]).
    let floor: Vec<f64> = scales.iter().map(|s| MIN_SECANT_OF_START * s).collect();
    let at_least =
        |w: &[f64]| -> Vec<f64> { w.iter().zip(&floor).map(|(a, b)| a.max(*b)).collect() };
    let mut iterations = 0;
    let mut cost_start = None;
    // Rounds on the whole record: the second (the observer rebuilt at the first's end) runs
    // when the first moved. A long record's first round descends on its first
    // [`DESCENT_PREFIX_SAMPLES`] instead, and one whole round follows — a second only when
    // the first moved far beyond what the prefix's own errors explain (see there).
    let record_len = excitation.len();
    let mut on_prefix = record_len > 2 * DESCENT_PREFIX_SAMPLES;
    let mut whole_rounds_left = if on_prefix { 1 } else { 2 };
    let mut after_prefix = false;
    // The whole round after a prefix is a one-step round ([`ONE_STEP_ITER`]); the point
    // its last Jacobian was made at (where the error secants are made).
    let mut one_step = on_prefix;
    let mut secant_at: Option<Vec<f64>> = None;
    let mut whole_record_steps = None;
    let (mut J, pred) = loop {
        let built_at = p.clone();
        let len = if on_prefix {
            DESCENT_PREFIX_SAMPLES
        } else {
            excitation.len()
        };
        let (excitation, response) = (&excitation[..len], &response[..len]);
        let mut pred = predictor(setup, model, &p, sigma, substeps, force_std, len)?;
        pred.initial = initial.map(<[f64]>::to_vec);
        // A record in motion: refit the start state with this observer (twice: the
        // friction's switching makes the innovations only nearly affine in it).
        if pred.initial.is_some() {
            for _ in 0..2 {
                let (r0, _) = innovations(setup, model, &p, &pred, excitation, response, substeps)?;
                if pred.refit_initial_state(&r0).is_none() {
                    break;
                }
            }
            // Then the parameters and the start state jointly (variable projection).
            pred.concentrate(excitation.len());
        }
        // Whole-record errors the prefix's answer may be off by (see [`PREFIX_REBUILD`]).
        let representative = PREFIX_REBUILD * (len as f64 / DESCENT_PREFIX_SAMPLES as f64).sqrt();
        let settled = if one_step && !on_prefix {
            // Tried once: an unsettled round leaves the record to the damped descent, with
            // the observer rebuilt as before when it moves far.
            one_step = false;
            match one_step_round(
                setup,
                model,
                &basis,
                &p,
                &scales,
                &at_least,
                &pred,
                excitation,
                response,
                substeps,
                representative,
                &mut iterations,
            )? {
                OneStep::Settled {
                    jac,
                    at,
                    answer,
                    steps,
                } => {
                    whole_record_steps = Some(steps);
                    Some((jac, at, answer))
                }
                // The descent below goes on from the last point run.
                OneStep::Unsettled { at } => {
                    p = at;
                    None
                }
            }
        } else {
            None
        };
        if let Some((J, at, answer)) = settled {
            p = answer;
            secant_at = Some(at);
            whole_rounds_left -= 1;
            if whole_rounds_left == 0 {
                break (J, pred);
            }
            continue;
        }
        // A round that another follows only brings the next one's observer near the
        // answer: its Jacobians by forward differences (see there).
        let forward = forward_differences(on_prefix, whole_rounds_left);
        let mut J = jacobian(
            setup, model, &basis, &p, &scales, &pred, excitation, response, substeps, None, forward,
        )?;
        if cost_start.is_none() {
            cost_start = Some(J.cost / (len * m) as f64);
        }
        let mut mu = 1e-3;
        let mut moved = false;
        for _ in 0..max_iter {
            iterations += 1;
            let (F, g) = normal(&J);
            // The damped steps of the Levenberg–Marquardt sequence (μ, 10μ, … at most
            // [`LM_TRIES`]; a singular damped matrix skips its μ), tried in that order: the
            // first whose cost is lower is taken. Damping only shortens the step, so the
            // sequence ends at the first step below the convergence tolerance (every
            // parameter within 0.05 of its naive error, the test that ends the descent after
            // a step is taken): a shorter one would not count as a move. Measured (100,000
            // samples): near the optimum the Gauss–Newton step was 0.002–0.05 errors, the
            // rough cost refused every damped step, and the 15 refused runs were 1.4 s of
            // the descent's 6.1 s.
            // (Evaluated one after the other: trying two at once on the two cores was no
            // faster — measured in the eleventh session and again in the thirty-fifth, when a
            // round of two trials took 1.2–1.6 ms against 0.8 ms for one, BENCHMARKS.md —
            // and wastes the second when the first succeeds.)
            let bound: Vec<f64> = scaled_inverse(&F)
                .map(|i| (0..p.len()).map(|a| i[(a, a)].max(0.0).sqrt()).collect())
                .unwrap_or_else(|| vec![f64::INFINITY; p.len()]);
            let is_small = |dp: &DVector<f64>| {
                dp.iter()
                    .zip(&bound)
                    .all(|(d, b): (&f64, &f64)| d.abs() <= LM_TOL * b)
            };
            let mut candidates = Vec::new();
            let mut damping = mu;
            for _ in 0..LM_TRIES {
                let mut A = F.clone();
                for d in 0..A.nrows() {
                    A[(d, d)] *= 1.0 + damping;
                }
                if let Some(dp) = bounded_step(&A, &g, &p, &basis) {
                    let trial = feasible(
                        &basis,
                        &p.iter()
                            .zip(dp.iter())
                            .map(|(a, b)| a + b)
                            .collect::<Vec<_>>(),
                    );
                    let small = is_small(&dp);
                    candidates.push((trial, small, damping));
                    if small {
                        break;
                    }
                }
                damping *= 10.0;
            }
            let mut stepped = None;
            for (trial, small, used) in candidates {
                let t0 = std::time::Instant::now();
                let run =
                    innovations(setup, model, &trial, &pred, excitation, response, substeps).ok();
                crate::par::phase("descent trial", t0);
                if let Some(run) = run.filter(|r| r.1 < J.cost) {
                    stepped = Some((trial, small, run));
                    mu = (used / 10.0).max(1e-9);
                    break;
                }
            }
            let Some((trial, small, run)) = stepped else {
                break;
            };
            p = trial;
            moved = true;
            if small {
                // The descent ends here: the end point's innovations are the trial run's,
                // and the last Jacobian's columns, a step of under `LM_TOL` errors away,
                // serve what follows (the polish's first step, the widths of the error
                // secants); those secants are made at this point. Why: the Jacobian made
                // here only to be replaced was a seventh of a 100,000-sample refinement.
                (J.r, J.cost) = run;
                break;
            }
            if let Some((_, naive, _)) = sandwich(&J, m) {
                scales = at_least(&naive);
            }
            J = jacobian(
                setup,
                model,
                &basis,
                &p,
                &scales,
                &pred,
                excitation,
                response,
                substeps,
                Some(run),
                forward,
            )?;
        }
        if on_prefix {
            on_prefix = false;
            after_prefix = true;
            // The whole record's errors are about `√(10,000/N)` of the prefix's: the
            // one-step round's first secant is ±1 of those.
            if let Some((_, naive, _)) = sandwich(&J, m) {
                let shrink = (len as f64 / record_len as f64).sqrt();
                scales = at_least(&naive.iter().map(|x| x * shrink).collect::<Vec<_>>());
            }
            continue;
        }
        whole_rounds_left -= 1;
        if std::mem::take(&mut after_prefix)
            && moved_beyond(&J, &p, &built_at)
                > PREFIX_REBUILD * (excitation.len() as f64 / DESCENT_PREFIX_SAMPLES as f64).sqrt()
        {
            whole_rounds_left = 1;
        }
        if whole_rounds_left == 0 || !moved {
            break (J, pred);
        }
    };
    // Secant Gauss–Newton to the zero of the smoothed gradient (see `POLISH_ITER`), from
    // the second step on with the innovations' model averaged over the polish's Jacobians
    // (see [`PolishModel`]).
    let mut polished = 0;
    let mut averaged: Option<PolishModel> = None;
    // The point `J` was made at (`p` unless the averaged model's answer was never run).
    let mut evaluated = p.clone();
    // (A one-step round has no polish: its steps were the secant Gauss–Newton steps.)
    for step in (0..=POLISH_ITER).take_while(|_| secant_at.is_none()) {
        let (F, g, centre) = match &averaged {
            Some(a) => a.normal(),
            None => {
                let (F, g) = normal(&J);
                (F, g, p.clone())
            }
        };
        let Some(ModelStep {
            target,
            naive,
            worst,
        }) = model_step(&F, &g, &centre, &p, &basis, false)
        else {
            break;
        };
        if !worst.is_finite() {
            break;
        }
        // The move clipped to POLISH_TRUST naive errors (the secant is only a local model).
        let next = clipped_move(&basis, &p, &target, worst);
        if worst <= POLISH_TOL || step == POLISH_ITER {
            // The answer is the averaged model's minimiser (the last Jacobian's point is one
            // draw of the rough cost's scatter around it).
            if averaged.is_some() {
                p = next;
            }
            break;
        }
        let width: Vec<f64> = at_least(&naive)
            .iter()
            .map(|x| x * POLISH_SECANT / SECANT)
            .collect();
        let Ok(J2) = jacobian(
            setup, model, &basis, &next, &width, &pred, excitation, response, substeps, None, false,
        ) else {
            break;
        };
        match averaged.as_mut() {
            Some(a) => a.add(&J2),
            None => averaged = Some(PolishModel::new(&J2)),
        }
        p = next;
        evaluated = p.clone();
        J = J2;
        polished += 1;
    }
    iterations += polished;
    // What every answer reports of the descent; the errors' fields are filled below.
    let descent_report = PredictionErrorReport {
        force_std,
        spectral_radius: pred.spectral_radius(),
        substeps,
        iterations,
        cost_start: cost_start.unwrap_or(f64::NAN),
        cost_end: J.cost / nobs,
        whole_record_steps,
        hac_lag: 0,
        noise_driven_errors: false,
        sandwich_ratio: vec![f64::NAN; p.len()],
        secant_disagreement: None,
        noise_shift: None,
        noise_shift_failure: None,
        smooth_excitation_gain: None,
        periodic_excitation: None,
        impulsive_excitation: None,
        bootstrap: None,
        frictionless_refit: None,
        start_at_rest_tests: Vec::new(),
    };
    if wanted == Wanted::Descent {
        let n = p.len();
        return Ok(PemRefined {
            refined: p.clone(),
            bound_likelihood_ratio: vec![None; n],
            initial_state: pred.initial.clone(),
            report: descent_report,
            values: p,
            std_errors: vec![f64::NAN; n],
            naive: vec![f64::NAN; n],
        });
    }
    // The errors from secants at least as wide as the error itself (see `ERROR_SECANTS`): a
    // narrower one sees single jumps of the rough cost and gave errors varying 10× between
    // seeds.
    let mut wide_jacobian = None;
    if let Some((_, naive, _)) = sandwich(&J, m) {
        let width =
            |k: f64| -> Vec<f64> { at_least(&naive).iter().map(|x| x * k / SECANT).collect() };
        // The averaged polish's answer has not been run yet: its base run is made here.
        let base = (evaluated == p).then(|| (J.r.clone(), J.cost));
        // A secant of half-width `k` errors at `at` (its base run `base` when known).
        let secant = |at: &[f64], k: f64, base: Option<(Vec<f64>, f64)>| {
            jacobian(
                setup,
                model,
                &basis,
                at,
                &width(k),
                &pred,
                excitation,
                response,
                substeps,
                base,
                false,
            )
        };
        match secant_at.as_ref() {
            // A one-step round's answer is its last step from `at`, under [`ONE_STEP_TOL`]
            // errors away and not run: the error secants are made at `at`, on its run (a
            // failure keeps the round's own ±2-error secant there).
            Some(at) => {
                if let Ok(J2) = secant(at, ERROR_SECANTS[0], Some((J.r.clone(), J.cost))) {
                    J = J2;
                }
            }
            None => match secant(&p, ERROR_SECANTS[0], base) {
                Ok(J2) => J = J2,
                // Without a run at the averaged answer, the last point run is the answer.
                Err(_) => p = evaluated.clone(),
            },
        }
        // Only for the stated errors: a bootstrap replicate ([`Wanted::Values`]) skips it.
        wide_jacobian = (wanted != Wanted::Values)
            .then(|| {
                secant(
                    secant_at.as_deref().unwrap_or(&p),
                    ERROR_SECANTS[1],
                    Some((J.r.clone(), J.cost)),
                )
                .ok()
            })
            .flatten();
    }
    // Columns of concentrated innovations are already projected (the projection is linear).
    if pred.initial.is_some() && !pred.is_concentrated() {
        pred.project_out_initial_state(&mut J.cols);
        if let Some(w) = wide_jacobian.as_mut() {
            pred.project_out_initial_state(&mut w.cols);
        }
    }
    let (mut se, naive, lag) = sandwich(&J, m).ok_or(SimulateError::SingularInformation)?;
    // At rest, the errors from the measurement noise through the observer (see
    // [`noise_driven_errors`]); a record in motion (the start state concentrated out of the
    // innovations) and a repeating or smooth excitation (`Wanted`) keep the lag window.
    let noise_driven = if wanted == Wanted::ValuesAndErrors && pred.initial.is_none() {
        residual_noise_variance(setup, model, &p, excitation, response, sigma, substeps).and_then(
            |var| {
                let both = crate::par::map(&[Some(&J), wide_jacobian.as_ref()], |j| {
                    j.and_then(|j| noise_driven_errors(&pred, j, m, &var))
                });
                both[0].clone().map(|narrow| (narrow, both[1].clone()))
            },
        )
    } else {
        None
    };
    // How far the two secants' lag-window sandwiches disagree (the automatic bootstrap's
    // occasion, `identify::pem::BOOTSTRAP_SECANT_DISAGREEMENT`, measured on them).
    let noise_driven_errors = noise_driven.is_some();
    let lag_window_wide = wide_jacobian
        .as_ref()
        .and_then(|w| sandwich(w, m))
        .map(|w| w.0);
    let secant_disagreement = lag_window_wide.as_ref().map(|wide| {
        se.iter()
            .zip(wide)
            .map(|(a, b)| (a / b).max(b / a))
            .fold(1.0f64, |acc, x| if x.is_nan() { acc } else { acc.max(x) })
    });
    // The stated errors: the larger of the two secants' sandwiches, both by the same score
    // covariance (the one that failed leaves the other alone). The sandwich is the error
    // (Ljung's covariance of a prediction-error estimate whose predictor is not the true
    // conditional mean: the observer's process noise is a device, the data have none) — at
    // rest its score covariance computed from the noise through the observer
    // (`noise_driven_errors`), in motion or under a repeating or smooth excitation
    // estimated by the lag window. The naive error assumes the innovations have the
    // variance the filter predicts; they come out smaller (normalised cost 0.2 on the
    // shipped recording), so it overstates the error; it was once a floor under the
    // sandwich (ACCURACY.md, "The sandwich is the error"). On data of the model's own
    // discretisation with friction, where the cost is rough, the wide secant of
    // `ERROR_SECANTS` is needed (ACCURACY.md, "Secants wide against the error").
    let wide_se = match noise_driven {
        Some((narrow, wide)) => {
            se = narrow;
            wide
        }
        None => lag_window_wide,
    };
    if let Some(wide_se) = wide_se {
        for (a, b) in se.iter_mut().zip(&wide_se) {
            *a = a.max(*b);
        }
    }
    let mut std_errors: Vec<f64> = se.clone();
    // The measurement noise's shift through the observer, removed, its error added (see
    // [`noise_bias`]).
    let widths: Vec<f64> = at_least(&naive)
        .iter()
        .map(|x| x * POLISH_SECANT / SECANT)
        .collect();
    let t0 = std::time::Instant::now();
    let shift = noise_bias(
        setup,
        model,
        &basis,
        &p,
        &pred,
        excitation.len(),
        sigma,
        substeps,
        &widths,
        lag,
        &normal(&J).0,
        &J.r,
    );
    crate::par::phase("noise bias", t0);
    let mut noise_shift_failure = None;
    let noise_shift = match shift {
        Ok(None) => None,
        Ok(Some((shift, shift_se))) => {
            p = feasible(
                &basis,
                &p.iter().zip(&shift).map(|(a, b)| a - b).collect::<Vec<_>>(),
            );
            for (e, b) in std_errors.iter_mut().zip(&shift_se) {
                *e = e.hypot(*b);
            }
            Some(shift)
        }
        Err(e) => {
            noise_shift_failure = Some(e.to_string());
            None
        }
    };
    // A friction level on its bound 0: the estimate is one-sided and the sandwich's
    // curvature is not its error (a boundary estimate is not normal). Its error is kept at
    // the start's: the data pushed it to the bound without narrowing it. Measured before the
    // observer's stuck-joint rule was removed (`simulate::predictions_with_observer`), when
    // the cost jumped at any positive level: the sandwich gave 2.4e-17 N, which outweighed
    // every other window's friction in a live session's combination.
    for j in 0..p.len() {
        if is_sign(&basis[j]) && p[j] <= 0.0 {
            std_errors[j] = std_errors[j].max(start_errors[j]);
        }
    }
    // A friction level on its bound that the start had positive: how much worse is the
    // start's level? (see `PemRefined::bound_likelihood_ratio`, [`FLAT_BOUND_LR`])
    let variance = (J.cost / nobs).max(1.0);
    let mut bound_likelihood_ratio: Vec<Option<f64>> = vec![None; p.len()];
    for j in (0..p.len()).filter(|_| wanted != Wanted::Values) {
        let level = start.get(j).copied().unwrap_or(0.0);
        if !(is_sign(&basis[j]) && p[j] <= 0.0 && level > 0.0) {
            continue;
        }
        let Some((cost, at)) = back_to_start_level(
            setup, model, &basis, &p, j, level, &J, &pred, excitation, response, substeps,
        ) else {
            continue;
        };
        let lr = (cost - J.cost).max(0.0) / variance;
        bound_likelihood_ratio[j] = Some(lr);
        if lr < FLAT_BOUND_LR {
            // The innovations fit the start's level as well as the bound: every value
            // between is an answer, so the 95 % intervals reach the start's point.
            for (k, se) in std_errors.iter_mut().enumerate() {
                *se = se.max((at[k] - p[k]).abs() / 1.96);
            }
        }
    }
    // The start state that goes with the answer: the concentrated innovations' refit,
    // made explicit (one more run).
    let initial_state = if pred.is_concentrated() {
        let mut plain = pred.clone();
        plain.concentration = None;
        if let Ok((r0, _)) = innovations(setup, model, &p, &plain, excitation, response, substeps) {
            plain.refit_initial_state(&r0);
        }
        plain.initial
    } else {
        pred.initial.clone()
    };
    Ok(PemRefined {
        refined: p.clone(),
        bound_likelihood_ratio,
        initial_state,
        report: PredictionErrorReport {
            // (At the error secant's run, which may have replaced the polish's `J`.)
            cost_end: J.cost / nobs,
            hac_lag: lag,
            noise_driven_errors,
            sandwich_ratio: se.iter().zip(&naive).map(|(a, b)| a / b).collect(),
            secant_disagreement,
            noise_shift,
            noise_shift_failure,
            ..descent_report
        },
        values: p,
        std_errors,
        naive,
    })
}

/// Per parameter: the noise shift and its standard error ([`noise_bias`]).
type NoiseShift = (Vec<f64>, Vec<f64>);

/// Seed of the synthetic measurement noise of [`noise_bias`] (fixed: the same record gives
/// the same answer on every run).
const NOISE_BIAS_SEED: u64 = 0x006a_6f69_6e74_6964;

/// The model of a record of the measurement noise alone ([`noise_level`], [`noise_bias`]):
/// the law `p` with friction levels and constant forces at 0, so that without excitation
/// the model stays at rest and its innovations are the noise's alone, and the observer
/// `pred` for a start at rest.
fn noise_record_model(basis: &[Basis], p: &[f64], pred: &Predictor) -> (Vec<f64>, Predictor) {
    let quiet: Vec<f64> = p
        .iter()
        .zip(basis)
        .map(|(v, b)| {
            if is_sign(b) || matches!(b, Basis::Const(_)) {
                0.0
            } else {
                *v
            }
        })
        .collect();
    let mut observer = pred.clone();
    observer.initial = None;
    observer.concentration = None;
    (quiet, observer)
}

/// `samples × m` standard normal draws of the noise record (fixed seed: the same record
/// every time).
fn noise_draws(samples: usize, m: usize) -> Vec<f64> {
    use rand::{RngExt, SeedableRng};
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(NOISE_BIAS_SEED);
    (0..samples * m)
        .map(|_| rng.sample::<f64, _>(rand_distr::StandardNormal))
        .collect()
}

/// The noise record at channel levels `level`.
fn noise_record(draws: &[f64], level: &[f64]) -> Vec<Vec<f64>> {
    draws
        .chunks_exact(level.len().max(1))
        .map(|z| z.iter().zip(level).map(|(a, s)| a * s).collect())
        .collect()
}

/// The measurement noise's level per channel at the answer `p`: `sigma` (the channels'
/// difference estimate, an upper bound where the signal has content near the Nyquist
/// frequency), lowered per channel where the real innovations are smaller than what that
/// much noise alone gives through the observer — the real innovations carry the noise and
/// the model's misfit, so their variance bounds the noise's share from above too; the
/// tighter of the two bounds is taken. Cost: one run of the predictor on a noise record.
/// Why: measured on the shipped friction setup, 8-sub-step data, the difference estimate
/// of the velocity channels was 8–53× the true noise at 1 % noise and 1.3–5× at 10 %
/// (accurate at 100 %); with it alone the shift of the shipped recording's `v` (1 % noise)
/// came out 0.41 of its errors, with the tighter bound 0.06 (the true noise's shift there
/// is of that order: it scales with the noise's variance).
#[allow(clippy::too_many_arguments)]
/// `quiet`, `observer`, `still` and `draws`: the noise record's model, observer, (zero)
/// excitation and standard normal draws ([`noise_record_model`], [`noise_draws`]).
fn noise_level(
    setup: &Setup,
    model: &Model,
    (quiet, observer): (&[f64], &Predictor),
    still: &[Vec<f64>],
    draws: &[f64],
    sigma: &[f64],
    substeps: usize,
    real_innovations: &[f64],
) -> Result<Vec<f64>, SimulateError> {
    let m = sigma.len();
    let record = |level: &[f64]| noise_record(draws, level);
    let level: Vec<f64> = {
        let (r_noise, _) = innovations(
            setup,
            model,
            quiet,
            observer,
            still,
            &record(sigma),
            substeps,
        )?;
        let unwhiten = observer
            .whiten
            .clone()
            .try_inverse()
            .ok_or(SimulateError::Singular)?;
        let channel_power = |r: &[f64]| -> Vec<f64> {
            let mut power = vec![0.0; m];
            let (mut w, mut e) = (DVector::zeros(m), DVector::zeros(m));
            for chunk in r.chunks_exact(m) {
                w.copy_from_slice(chunk);
                crate::dense::gemv(&mut e, &unwhiten, &w, crate::dense::Op::Set);
                for (p, x) in power.iter_mut().zip(e.iter()) {
                    *p += x * x;
                }
            }
            power
        };
        let (real, noise) = (channel_power(real_innovations), channel_power(&r_noise));
        sigma
            .iter()
            .zip(real.iter().zip(&noise))
            .map(|(s, (a, b))| {
                let ratio = (a / b).sqrt();
                s * if ratio.is_finite() {
                    ratio.min(1.0)
                } else {
                    1.0
                }
            })
            .collect()
    };
    Ok(level)
}

/// The shift of the prediction-error estimate that the measurement noise causes through the
/// observer, and the standard error of that figure, at `p` (both per parameter; zero for
/// every term but those linear in the state; `None` when the law has none).
///
/// Why: the observer feeds the measurement noise into the model's state, and the noise's
/// share of the innovations depends on the parameters: for a law linear in the state the
/// innovations are `e(θ) = H(θ)(y − G(θ)u)` with `H(θ) = (I + C(qI − Φ(θ))⁻¹K)⁻¹`, so the
/// expected cost is `|H(θ)(G₀ − G(θ))u|² + E|H(θ)v|²` and its minimum moves off the truth by
/// the second term's slope, `−F⁻¹ ½∇E|H v|²`. That shift grows with the observer force and
/// the noise and does not shrink with the record (the errors do): measured on the two-beam
/// model, 50,000 samples at 100 % noise, the joint damper `v` +3 to +40 standard errors off
/// (ACCURACY.md, "The observer-force bias"). A fixed-gain predictor is unbiased only when
/// its noise model is the true one (Ljung, *System Identification*, 1999, ch. 8), and the
/// true system has no process noise, whose observer (gain 0) is the rough free-run output
/// error.
///
/// How: the slope is measured on a record of the noise alone (`samples` samples of white
/// noise, fixed seed) through the same observer, the model at rest — no excitation, no
/// start state, friction levels and constant forces at 0, so that the innovations are
/// `H(θ)v` and nothing else, and the score `Jᵀr` of the terms linear in the state (`u`,
/// `v`, `a`) is `−½∇|H v|²` exactly (central secants of `widths`). The estimate solves
/// `Jᵀr = 0` on the real record, so the shift is `F⁻¹ ḡ` with `F = JᵀJ` of the real record
/// (`information`) over those terms and `ḡ` that score; the other terms are held at the
/// answer (a constant force's sensitivity does not depend on the noise; a friction's
/// noise-triggered switching is left out). Its standard error is the sandwich of the
/// demeaned per-sample scores (Bartlett window of `lag` samples). The noise level is the
/// smaller, per channel, of `sigma` and the level the real innovations allow (see the
/// body). Cost: six runs of the predictor.
///
/// Measured (ACCURACY.md, "The observer-force bias, corrected"): 50,000 samples at 100 %
/// noise, `v` +2.96…+39.7 errors off before, +0.10…+3.27 after; 20 fresh seeds per row at
/// 2,000 samples, the damper's mean error at 100 % noise +0.27…+0.44 before, about 0 after,
/// coverage and worst errors unchanged.
///
/// Tried first and not kept: records of the model at `p` driven by the real excitation
/// (the nonlinear law included) with their own `JᵀJ` — their free run did not follow the
/// measured motion (channels near the joint at 57 % of its amplitude, `JᵀJ` of `u` and `v`
/// 12–17× smaller) and `v` was over-corrected by 9–43 errors; with the real `F` but the
/// excitation kept, the friction's noise-triggered switching left a part odd in the noise
/// that an antithetic pair did not cancel, and `v` moved by −0.4 errors on average at every
/// noise level. Iterating the correction (the shift evaluated again at the corrected point)
/// over-corrected: `v` −2.6 and −13.8 errors on the two largest-force records of the table.
#[allow(clippy::too_many_arguments)]
fn noise_bias(
    setup: &Setup,
    model: &Model,
    basis: &[Basis],
    p: &[f64],
    pred: &Predictor,
    samples: usize,
    sigma: &[f64],
    substeps: usize,
    widths: &[f64],
    lag: usize,
    information: &DMatrix<f64>,
    real_innovations: &[f64],
) -> Result<Option<NoiseShift>, SimulateError> {
    let n_par = p.len();
    let m = sigma.len();
    // The terms linear in the state, whose noise scores are measured.
    let scored: Vec<usize> = (0..n_par)
        .filter(|&a| matches!(basis[a], Basis::U | Basis::V | Basis::A))
        .collect();
    if scored.is_empty() || samples == 0 {
        return Ok(None);
    }
    let (quiet, observer) = noise_record_model(basis, p, pred);
    let still = vec![vec![0.0; model.Lp.ncols()]; samples];
    let draws = noise_draws(samples, m);
    let level = noise_level(
        setup,
        model,
        (&quiet, &observer),
        &still,
        &draws,
        sigma,
        substeps,
        real_innovations,
    )?;
    let y = noise_record(&draws, &level);
    // The record at `quiet` and displaced along each scored parameter (central secants of
    // `widths`), on parallel threads.
    let mut points = vec![quiet.clone()];
    for &a in &scored {
        for sign in [1.0, -1.0] {
            let mut q = quiet.clone();
            q[a] += sign * widths[a];
            points.push(q);
        }
    }
    let runs: Vec<Vec<f64>> = crate::par::map(&points, |q| {
        innovations(setup, model, q, &observer, &still, &y, substeps).map(|x| x.0)
    })
    .into_iter()
    .collect::<Result<_, _>>()?;
    let r = &runs[0];
    // Per-sample scores `J_iᵀ r_i` of the scored parameters.
    let k = scored.len();
    let mut scores = vec![0.0; samples * k];
    for (at, &a) in scored.iter().enumerate() {
        let (plus, minus) = (&runs[1 + 2 * at], &runs[2 + 2 * at]);
        let h = widths[a];
        for i in 0..samples {
            let mut s = 0.0;
            for ch in 0..m {
                let idx = i * m + ch;
                // Columns are −∂r/∂p (as [`jacobian`]).
                s += -(plus[idx] - minus[idx]) / (2.0 * h) * r[idx];
            }
            scores[i * k + at] = s;
        }
    }
    // The shift of the scored parameters with the others held at the answer. Why held (and
    // not moved along with them through `F`, their noise scores taken as zero): the
    // friction's noise score is not zero — it is left out, not absent — and moving the
    // friction by correlation alone put it 9 errors off on the 480× record of the table
    // (ACCURACY.md), where holding it leaves it where the data put it (0.06 errors).
    let F = DMatrix::from_fn(k, k, |a, b| information[(scored[a], scored[b])]);
    let inv = scaled_inverse(&F).ok_or(SimulateError::SingularInformation)?;
    let g = DVector::from_fn(k, |a, _| {
        (0..samples).map(|i| scores[i * k + a]).sum::<f64>()
    });
    let shift = &inv * &g;
    // The spread of the scores about their mean: the shift's own error.
    for a in 0..k {
        let mean = g[a] / samples as f64;
        for i in 0..samples {
            scores[i * k + a] -= mean;
        }
    }
    let B = crate::estimate::refit::bartlett_long_run_covariance(&scores, k, lag);
    let cov = &inv * B * &inv;
    let (mut out, mut se) = (vec![0.0; n_par], vec![0.0; n_par]);
    for (a, &fa) in scored.iter().enumerate() {
        out[fa] = shift[a];
        se[fa] = cov[(a, a)].max(0.0).sqrt();
    }
    if out.iter().chain(&se).all(|x| x.is_finite()) {
        Ok(Some((out, se)))
    } else {
        Err(SimulateError::Singular)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{RngExt, SeedableRng};
    use rand_chacha::ChaCha8Rng;
    use rand_distr::StandardNormal;

    /// On innovations linear in the parameters, `r(p) = y − A p`, one Gauss–Newton step from
    /// any point reaches their least squares (the law the level choice's first-order profile
    /// rests on); a singular `AᵀA` gives no step.
    #[test]
    fn one_gauss_newton_step_reaches_the_least_squares_of_linear_innovations() {
        let mut rng = ChaCha8Rng::seed_from_u64(58);
        for _ in 0..20 {
            let (n, p) = (40, 3);
            let a: Vec<Vec<f64>> = (0..p)
                .map(|_| (0..n).map(|_| rng.sample(StandardNormal)).collect())
                .collect();
            let y: Vec<f64> = (0..n).map(|_| rng.sample(StandardNormal)).collect();
            let at = |q: &[f64]| -> Vec<f64> {
                (0..n)
                    .map(|i| y[i] - (0..p).map(|j| a[j][i] * q[j]).sum::<f64>())
                    .collect()
            };
            let from: Vec<f64> = (0..p).map(|_| 10.0 * rng.random::<f64>()).collect();
            let step = gauss_newton_step(&a, &at(&from)).expect("a step");
            let reached: Vec<f64> = from.iter().zip(&step).map(|(x, d)| x + d).collect();
            // The least squares from the origin: the same point whatever the start.
            let ls = gauss_newton_step(&a, &at(&[0.0; 3])).expect("a step");
            for (x, l) in reached.iter().zip(&ls) {
                assert!(
                    (x - l).abs() < 1e-9 * (1.0 + l.abs()),
                    "{reached:?} against {ls:?}"
                );
            }
            // At the least squares the residuals are orthogonal to every column.
            let r = at(&reached);
            for col in &a {
                let g: f64 = col.iter().zip(&r).map(|(c, e)| c * e).sum();
                assert!(g.abs() < 1e-8, "gradient {g}");
            }
        }
        let dependent = vec![vec![1.0, 2.0, 3.0], vec![2.0, 4.0, 6.0]];
        assert!(gauss_newton_step(&dependent, &[1.0, 0.0, 1.0]).is_none());
    }

    /// A secant Jacobian of innovations `r(p) = y − A p (+ roughness)` made at `centre` the
    /// way [`jacobian`] makes it (central differences of half-width `h`, the mean of the
    /// runs and of their points).
    fn secant_jacobian(
        A: &DMatrix<f64>,
        y: &DVector<f64>,
        centre: &[f64],
        h: f64,
        rough: &dyn Fn(&[f64]) -> DVector<f64>,
    ) -> Jac {
        let run = |q: &[f64]| -> Vec<f64> {
            let p = DVector::from_column_slice(q);
            (y - A * &p + rough(q)).iter().copied().collect()
        };
        let r = run(centre);
        let (mut r_mean, mut p_mean, mut count) = (r.clone(), centre.to_vec(), 1.0);
        let mut cols = Vec::new();
        for j in 0..centre.len() {
            let (mut plus, mut minus) = (centre.to_vec(), centre.to_vec());
            plus[j] += h;
            minus[j] -= h;
            let (rp, rm) = (run(&plus), run(&minus));
            cols.push(
                rp.iter()
                    .zip(&rm)
                    .map(|(a, b)| -(a - b) / (2.0 * h))
                    .collect(),
            );
            for (q, rq) in [(&plus, &rp), (&minus, &rm)] {
                r_mean.iter_mut().zip(rq).for_each(|(a, b)| *a += b);
                p_mean.iter_mut().zip(q.iter()).for_each(|(a, b)| *a += b);
                count += 1.0;
            }
        }
        r_mean
            .iter_mut()
            .chain(p_mean.iter_mut())
            .for_each(|a| *a /= count);
        let cost = r.iter().map(|x| x * x).sum();
        Jac {
            r,
            cols,
            cost,
            r_mean,
            p_mean,
        }
    }

    /// The polish's averaged model of linear innovations is the linear model itself: its
    /// minimiser is the least-squares solution whatever points the Jacobians were made at.
    /// With a rough term added (a sawtooth in the parameters, the friction's sub-step
    /// switching in miniature), the single Jacobian's Gauss–Newton answer lands off the
    /// least-squares solution by the roughness's draw, and the average of twelve Jacobians
    /// made around it lands closer (the scatter averages out).
    #[test]
    fn the_polish_model_averages_out_the_roughness_and_keeps_a_linear_model() {
        let mut rng = ChaCha8Rng::seed_from_u64(7);
        let (rows, k) = (400, 2);
        let A = DMatrix::from_fn(rows, k, |_, _| rng.sample::<f64, _>(StandardNormal));
        let truth = [1.5, -0.7];
        let y = &A * DVector::from_column_slice(&truth)
            + DVector::from_fn(rows, |_, _| 0.1 * rng.sample::<f64, _>(StandardNormal));
        let ls = (A.transpose() * &A).try_inverse().unwrap() * A.transpose() * &y;
        let answer = |m: &PolishModel| -> Vec<f64> {
            let (F, g, centre) = m.normal();
            let dp = F.try_inverse().unwrap() * g;
            centre.iter().zip(dp.iter()).map(|(c, d)| c + d).collect()
        };
        let smooth = |_: &[f64]| DVector::zeros(rows);
        let centres = [[0.0, 0.0], [1.4, -0.6], [1.7, -0.9], [1.2, -0.4]];
        let mut model = PolishModel::new(&secant_jacobian(&A, &y, &centres[0], 0.05, &smooth));
        for c in &centres[1..] {
            model.add(&secant_jacobian(&A, &y, c, 0.05, &smooth));
        }
        let a = answer(&model);
        for (x, l) in a.iter().zip(ls.iter()) {
            assert!((x - l).abs() < 1e-9, "linear: {a:?} against {ls:?}");
        }
        // Rough: each row jumps by ±0.3 as a parameter crosses its own random grid offset.
        let phase: Vec<f64> = (0..rows).map(|_| rng.random::<f64>()).collect();
        let rough = |q: &[f64]| {
            DVector::from_fn(rows, |i, _| {
                let t = (q[0] + 2.0 * q[1]) / 0.02 + phase[i];
                0.3 * (2.0 * (t - t.floor()) - 1.0)
            })
        };
        let off = |p: &[f64]| -> f64 {
            p.iter()
                .zip(ls.iter())
                .map(|(a, b)| (a - b).powi(2))
                .sum::<f64>()
                .sqrt()
        };
        let single: Vec<f64> = (0..12)
            .map(|i| {
                let c = [ls[0] + 0.003 * i as f64, ls[1] - 0.002 * i as f64];
                off(&answer(&PolishModel::new(&secant_jacobian(
                    &A, &y, &c, 0.01, &rough,
                ))))
            })
            .collect();
        let mut model = PolishModel::new(&secant_jacobian(&A, &y, &[ls[0], ls[1]], 0.01, &rough));
        for i in 1..12 {
            let c = [ls[0] + 0.003 * i as f64, ls[1] - 0.002 * i as f64];
            model.add(&secant_jacobian(&A, &y, &c, 0.01, &rough));
        }
        let averaged = off(&answer(&model));
        let typical = single.iter().sum::<f64>() / single.len() as f64;
        assert!(
            averaged < 0.5 * typical,
            "averaged {averaged:.2e}, single Jacobians {typical:.2e} on average"
        );
    }

    /// A friction level on its bound whose step would go below it is held at 0 and the
    /// other parameter's step is the reduced system's (not the unconstrained step's); off
    /// the bound, or stepping up, the step is the plain one.
    #[test]
    fn a_level_on_its_bound_is_held_and_the_others_step_without_it() {
        let A = DMatrix::from_row_slice(2, 2, &[2.0, 1.0, 1.0, 2.0]);
        let g = DVector::from_row_slice(&[-3.0, 1.0]);
        let basis = [Basis::SignU, Basis::U];
        // Unconstrained: A⁻¹g = (−7/3, 5/3).
        let free = bounded_step(&A, &g, &[1.0, 0.0], &basis).unwrap();
        assert!((free[0] + 7.0 / 3.0).abs() < 1e-12 && (free[1] - 5.0 / 3.0).abs() < 1e-12);
        // On the bound: held; the stiffness solves 2·d = 1.
        let held = bounded_step(&A, &g, &[0.0, 0.0], &basis).unwrap();
        assert_eq!(held[0], 0.0);
        assert!((held[1] - 0.5).abs() < 1e-12);
        // On the bound but stepping up: free.
        let g_up = DVector::from_row_slice(&[3.0, 1.0]);
        let up = bounded_step(&A, &g_up, &[0.0, 0.0], &basis).unwrap();
        assert!((up[0] - 5.0 / 3.0).abs() < 1e-12 && (up[1] + 1.0 / 3.0).abs() < 1e-12);
    }

    /// With `crossing`, a level above its bound whose step would cross it moves exactly to 0
    /// and the other parameter's step is solved with that move: from (1, 0) the free step
    /// (−7/3, 5/3) crosses; held at −1, the stiffness solves `2·d = 1 − 1·(−1)`, d = 1.
    /// Without `crossing` the step is the free one (the level clipped later by `feasible`,
    /// the stiffness moved with a level the answer does not have).
    #[test]
    fn a_level_that_would_cross_its_bound_is_held_on_it_by_the_one_step_round() {
        let A = DMatrix::from_row_slice(2, 2, &[2.0, 1.0, 1.0, 2.0]);
        let g = DVector::from_row_slice(&[-3.0, 1.0]);
        let basis = [Basis::SignU, Basis::U];
        let held = active_set_step(&A, &g, &[1.0, 0.0], &basis, true).unwrap();
        assert_eq!(held[0], -1.0);
        assert!((held[1] - 1.0).abs() < 1e-12, "{held}");
        // The held move is the constrained least-squares step: its stiffness row is solved.
        assert!((A[(1, 0)] * held[0] + A[(1, 1)] * held[1] - g[1]).abs() < 1e-12);
        let free = active_set_step(&A, &g, &[1.0, 0.0], &basis, false).unwrap();
        assert!((free[0] + 7.0 / 3.0).abs() < 1e-12 && (free[1] - 5.0 / 3.0).abs() < 1e-12);
        // A step that stays above the bound is the free one either way.
        let small = active_set_step(&A, &g, &[5.0, 0.0], &basis, true).unwrap();
        assert!((small[0] + 7.0 / 3.0).abs() < 1e-12 && (small[1] - 5.0 / 3.0).abs() < 1e-12);
    }

    /// The shipped spring setup, its model, and a 300-sample record of random input
    /// (2e4 N RMS per channel) at `params` with 5 % noise on every channel, and those noise
    /// levels.
    #[allow(clippy::type_complexity)]
    fn spring_record(
        params: impl Fn(&Basis) -> f64,
        seed: u64,
    ) -> (
        Setup,
        Model,
        Vec<f64>,
        Vec<Vec<f64>>,
        Vec<Vec<f64>>,
        Vec<f64>,
    ) {
        let toml = std::fs::read_to_string(concat!(
            env!("CARGO_MANIFEST_DIR"),
            "/recordings/two-beam-spring.toml"
        ))
        .unwrap();
        let setup = Setup::from_toml(&toml, "two-beam-spring.toml").unwrap();
        let model = Model::assemble(&setup).unwrap();
        let params: Vec<f64> = setup.param_basis().iter().map(params).collect();
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        let ne = model.Lp.ncols();
        let exc: Vec<Vec<f64>> = (0..300)
            .map(|_| {
                (0..ne)
                    .map(|_| 2e4 * rng.sample::<f64, _>(StandardNormal))
                    .collect()
            })
            .collect();
        let clean =
            crate::simulate::response_to_excitation(&setup, &model, &params, &exc, setup.dt_s, 1)
                .unwrap();
        let m = model.stations.len();
        let rms: Vec<f64> = (0..m)
            .map(|k| (clean.iter().map(|y| y[k] * y[k]).sum::<f64>() / 300.0).sqrt())
            .collect();
        let resp: Vec<Vec<f64>> = clean
            .iter()
            .map(|y| {
                (0..m)
                    .map(|k| y[k] + 0.05 * rms[k] * rng.sample::<f64, _>(StandardNormal))
                    .collect()
            })
            .collect();
        let sigma: Vec<f64> = rms.iter().map(|r| 0.05 * r).collect();
        (setup, model, params, exc, resp, sigma)
    }

    /// A forward-difference Jacobian (the first of two rounds, [`forward_differences`]) is
    /// the secant over `[p, p + 2h]`, the central one's width, from the same base run (the
    /// same innovations and cost); where the innovations are affine in a parameter (the
    /// constant force, the friction level at a fixed switching pattern, nearly the damper)
    /// the two agree to 1e-3 of the column's norm. The stiffness's column differs by a
    /// quarter on this record (the innovations are curved in it at this width): why forward
    /// differences are kept to the round whose end only places the next observer.
    #[test]
    fn forward_and_central_jacobians_agree() {
        let (setup, model, params, exc, resp, sigma) = spring_record(
            |b| match b {
                Basis::U => 3e5,
                Basis::V => 20.0,
                Basis::SignU => 500.0,
                _ => 1.0,
            },
            12,
        );
        let basis = setup.param_basis();
        let scales: Vec<f64> = params.iter().map(|p| 1e-3 * p).collect();
        let pred = predictor(&setup, &model, &params, &sigma, 1, 100.0, resp.len()).unwrap();
        let make = |forward: bool| {
            jacobian(
                &setup, &model, &basis, &params, &scales, &pred, &exc, &resp, 1, None, forward,
            )
            .unwrap()
        };
        let (central, forward) = (make(false), make(true));
        assert_eq!(central.cost.to_bits(), forward.cost.to_bits());
        assert_eq!(central.r, forward.r);
        let steps = super::super::difference_steps(SECANT, &scales, &params);
        for (j, (c, f)) in central.cols.iter().zip(&forward.cols).enumerate() {
            let norm = c.iter().map(|x| x * x).sum::<f64>().sqrt();
            let diff = c
                .iter()
                .zip(f)
                .map(|(a, b)| (a - b).powi(2))
                .sum::<f64>()
                .sqrt();
            assert!(norm > 0.0, "column {j} is zero");
            if basis[j] != Basis::U {
                assert!(diff <= 1e-3 * norm, "column {j}: |Δ| {diff:e} of {norm:e}");
            }
            // The forward column is −(r(p + 2h e_j) − r(p)) / 2h.
            let mut plus = params.clone();
            plus[j] += 2.0 * steps[j];
            let (rp, _) = innovations(&setup, &model, &plus, &pred, &exc, &resp, 1).unwrap();
            for (k, (x, (a, b))) in f.iter().zip(rp.iter().zip(&central.r)).enumerate() {
                let want = -(a - b) / (2.0 * steps[j]);
                assert!(
                    (x - want).abs() <= 1e-12 * want.abs().max(norm),
                    "column {j} row {k}: {x:e} vs {want:e}"
                );
            }
        }
    }

    /// The score covariance the measurement noise gives through the observer, by the
    /// adjoint pass of [`noise_score_covariance`], against Monte Carlo: 400 records of white
    /// noise alone (channel levels `sigma`) run through the same observer with the model at
    /// rest (a law linear in the state: the innovations are exactly the noise's filtered
    /// image), each one's score `Σ ψᵢᵀ rᵢ` with the real record's Jacobian rows. The
    /// variances agree within 20 % (the Monte Carlo's own spread is ~7 %), and the lag
    /// window's estimate from one record is not what is compared: the adjoint needs none.
    #[test]
    fn the_noise_score_covariance_matches_monte_carlo() {
        let (setup, model, params, exc, resp, sigma) = spring_record(
            |b| match b {
                Basis::U => 3e5,
                Basis::V => 20.0,
                _ => 0.0,
            },
            21,
        );
        let basis = setup.param_basis();
        let scales: Vec<f64> = params.iter().map(|p| 1e-3 * p.abs().max(1.0)).collect();
        let pred = predictor(&setup, &model, &params, &sigma, 1, 300.0, resp.len()).unwrap();
        let jac = jacobian(
            &setup, &model, &basis, &params, &scales, &pred, &exc, &resp, 1, None, false,
        )
        .unwrap();
        let m = sigma.len();
        let var: Vec<f64> = sigma.iter().map(|s| s * s).collect();
        let exact = noise_score_covariance(&pred, &jac, m, &var).unwrap();
        let p = params.len();
        let still = vec![vec![0.0; model.Lp.ncols()]; resp.len()];
        let mut rng = ChaCha8Rng::seed_from_u64(77);
        let replicates = 400;
        let mut second = DMatrix::<f64>::zeros(p, p);
        for _ in 0..replicates {
            let noise: Vec<Vec<f64>> = (0..resp.len())
                .map(|_| {
                    sigma
                        .iter()
                        .map(|s| s * rng.sample::<f64, _>(StandardNormal))
                        .collect()
                })
                .collect();
            let (r, _) = innovations(&setup, &model, &params, &pred, &still, &noise, 1).unwrap();
            let score: DVector<f64> = DVector::from_fn(p, |a, _| {
                jac.cols[a].iter().zip(&r).map(|(c, x)| c * x).sum::<f64>()
            });
            second += (&score * score.transpose()) * (1.0 / replicates as f64);
        }
        for a in 0..p {
            let ratio = second[(a, a)] / exact[(a, a)];
            assert!(
                (0.8..1.25).contains(&ratio),
                "{:?}: Monte Carlo {:e} against {:e} (ratio {ratio:.3})",
                basis[a],
                second[(a, a)],
                exact[(a, a)]
            );
        }
    }

    /// A bootstrap replicate's refinement ([`Wanted::Values`]) skips only runs that state
    /// errors: its values are the full refinement's to the bit, and it has no wide error
    /// secant (no secant disagreement) while the full one has; the refinement whose errors
    /// are the residuals' lag window's ([`Wanted::ValuesAndLagWindowErrors`], a sine or an
    /// impact) has the same values to the bit and other errors from rest. Three cases on noisy
    /// 300-sample records, started 2 % off: a friction law from rest; the same with a start
    /// state fitted (a record in motion, as the bootstrap now refines them); and a law whose
    /// friction is 0, started at 50 N (where the full refinement can look back at the
    /// start's level from the bound and a replicate does not).
    #[test]
    fn a_replicate_refinement_gives_the_same_values_without_the_error_runs() {
        for (friction, in_motion) in [(500.0, false), (500.0, true), (0.0, false)] {
            let truth = |b: &Basis| match b {
                Basis::U => 3e5,
                Basis::V => 20.0,
                Basis::SignU => friction,
                _ => 1.0,
            };
            let (setup, model, params, exc, resp, sigma) = spring_record(truth, 13);
            let start: Vec<f64> = params
                .iter()
                .map(|p| if *p == 0.0 { 50.0 } else { 1.02 * p })
                .collect();
            let scales: Vec<f64> = params.iter().map(|p| 1e-2 * p.abs().max(1.0)).collect();
            let initial = vec![0.0; 3 * model.n()];
            let run = |wanted: Wanted| {
                refine(
                    &setup,
                    &model,
                    &start,
                    &scales,
                    &exc,
                    &resp,
                    &sigma,
                    1,
                    300.0,
                    10,
                    in_motion.then_some(initial.as_slice()),
                    wanted,
                )
                .unwrap()
            };
            let (full, replicate) = (run(Wanted::ValuesAndErrors), run(Wanted::Values));
            let lag_window = run(Wanted::ValuesAndLagWindowErrors);
            let bits = |v: &[f64]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
            let case = format!("friction {friction}, in motion {in_motion}");
            assert_eq!(bits(&full.values), bits(&replicate.values), "{case}");
            // The lag window changes the stated errors only: the same values to the bit,
            // and from rest errors of another covariance (in motion both are the window's).
            assert_eq!(bits(&full.values), bits(&lag_window.values), "{case}");
            assert!(!lag_window.report.noise_driven_errors, "{case}");
            assert_eq!(full.report.noise_driven_errors, !in_motion, "{case}");
            if !in_motion {
                assert_ne!(
                    bits(&full.std_errors),
                    bits(&lag_window.std_errors),
                    "{case}"
                );
            }
            assert!(full.report.secant_disagreement.is_some(), "{case}");
            assert!(replicate.report.secant_disagreement.is_none(), "{case}");
            // It is an answer: the stiffness back within 1 % of the truth from 2 % off.
            let k = setup
                .param_basis()
                .iter()
                .position(|b| *b == Basis::U)
                .unwrap();
            assert!(
                (full.values[k] / params[k] - 1.0).abs() < 0.01,
                "{case}: stiffness {} against {}",
                full.values[k],
                params[k]
            );
        }
    }

    /// Variable projection is exact for a law linear in the state: the innovations
    /// concentrated over the start state from a wrong start equal those of a run from the
    /// least-squares refitted start (spring, dashpot, no friction, on the paper's two-beam
    /// model; random excitation and noisy outputs, 300 samples), and the concentrated cost is
    /// no larger than the raw one.
    #[test]
    fn concentrated_innovations_equal_a_run_from_the_refitted_start() {
        let (setup, model, params, exc, resp, sigma) = spring_record(
            |b| match b {
                Basis::U => 3e5,
                Basis::V => 20.0,
                _ => 0.0,
            },
            11,
        );
        let mut pred = predictor(&setup, &model, &params, &sigma, 1, 100.0, resp.len()).unwrap();
        let nz = 3 * model.n();
        let start: Vec<f64> = (0..nz)
            .map(|i| {
                if i < model.n() {
                    1e-4 * ((i % 5) as f64 - 2.0)
                } else {
                    0.0
                }
            })
            .collect();
        pred.initial = Some(start);
        let (raw, raw_cost) = innovations(&setup, &model, &params, &pred, &exc, &resp, 1).unwrap();
        let mut refitted = pred.clone();
        refitted.refit_initial_state(&raw).unwrap();
        let (want, want_cost) =
            innovations(&setup, &model, &params, &refitted, &exc, &resp, 1).unwrap();
        pred.concentrate(exc.len()).unwrap();
        assert!(pred.refit_initial_state(&raw).is_none());
        let (got, got_cost) = innovations(&setup, &model, &params, &pred, &exc, &resp, 1).unwrap();
        let norm = want.iter().map(|x| x * x).sum::<f64>().sqrt();
        let diff = got
            .iter()
            .zip(&want)
            .map(|(a, b)| (a - b).powi(2))
            .sum::<f64>()
            .sqrt();
        assert!(
            diff < 1e-6 * norm,
            "concentrated differs by {diff:e} of {norm:e}"
        );
        assert!(got_cost <= raw_cost, "{got_cost} > {raw_cost}");
        assert!((got_cost - want_cost).abs() < 1e-6 * want_cost);
        // The start error was visible: refitting it removed cost.
        assert!(raw_cost > 1.01 * got_cost, "{raw_cost} vs {got_cost}");
    }
}
