//! The 1989 estimator (Lawrence & Huckelbridge, NASA TM-101991, Eq. 3), kept as the
//! reference.
//!
//! Per sample `i`: predict the model one sample ahead with the current connection-force
//! estimate (`R = 0`), then choose the residual force that best explains the measured
//! station outputs in the weighted least-squares sense,
//!
//! ```text
//! R_i = (SᵀWS)⁻¹SᵀW (y_measured,i − y_predicted,i),     S = ∂y_i/∂R_i = H Γ_f,
//! ```
//!
//! and advance the model with it (Step IV). Because `y` is affine in `R_i` one evaluation
//! is exact (the paper iterates Eq. 3; here the iteration converges in one step). `S` is
//! constant and computed once per model.
//!
//! Its weakness, reported rather than hidden: nothing corrects the model *state* from the
//! measurements, so the state error obeys `e_i = (I − Γ_f G H) Φ e_{i−1} + Γ_f G n_i`. The
//! spectral radius of that recursion is reported in the diagnostics; at or above 1 the
//! errors (noise, discretisation mismatch) accumulate step after step.
//!
//! The model is advanced either by the dense [`Stepper`] (the baseline) or, per
//! `[integrator] step`, by the exact modal map [`ModalStep`] or the sparse step
//! [`SparseStep`]; with the modal map the state is kept in modal coordinates and per sample
//! only the station outputs (their rows of `Ψ`) and the connection deformations (`ΨᵀLc`) are
//! formed, never the physical state; the sparse step keeps the physical state and picks the
//! stations from it. `auto`: see [`choose_auto`].

#![allow(non_snake_case)]

use nalgebra::{DMatrix, DVector};

use super::{
    ConnectionLaw, EstimateError, EstimatorDiagnostics, ResidualEstimator, Stations, StepOutput,
    rank_and_condition, spectral_radius,
};
use crate::integrate::fast::{ModalOutputs, ModalState, ModalStep};
use crate::integrate::sparse::SparseStep;
use crate::integrate::{State, Stepper};
use crate::model::Model;
use crate::setup::{Newmark, StepKind, Weighting};

/// Smallest model for which `step = "auto"` chooses the modal map. Below it the dense step
/// is as fast (measured with `examples/bench_model.rs`, see `BENCHMARKS.md`) and keeps the
/// shipped results bit-identical to the reference implementation.
pub const AUTO_MODAL_MIN_DOFS: usize = 48;

/// Multiply-adds per sample of the sparse step: per sub-step the two mat-vecs, two
/// triangular solves and ~8n of predictor/corrector work; per sample `3nq` for `Γ_f R`.
pub fn sparse_cost(step: &SparseStep, q: usize) -> usize {
    let n = step.n;
    step.substeps * (step.C.nnz() + step.K.nnz() + 2 * step.meff.nnz() + 8 * n) + 3 * n * q
}

/// Multiply-adds per sample of the composed modal map, a lower bound (the low-rank damping
/// path costs more): per mode the 3 × 3 map and loads, the stations' rows of Ψ, `ΨᵀLc`
/// three times and `Γ_f R`.
pub fn modal_cost_lower_bound(n: usize, channels: usize, q: usize) -> usize {
    n * (15 + channels + 6 * q)
}

/// Measured weight of one sparse multiply-add against one of the modal map's dense ones
/// (indirect addressing, and the triangular solves' row-to-row dependency): on the 240-DOF
/// chains of `examples/bench_model.rs` a sparse operation took 1.7 ns, a modal one
/// 0.5–0.9 ns (BENCHMARKS.md).
pub const SPARSE_OP_WEIGHT: usize = 2;

/// `step = "auto"`: the dense step below [`AUTO_MODAL_MIN_DOFS`] (as fast there, and the
/// shipped results stay bit-identical to the reference); the sparse step when the model has
/// no dense form; otherwise the sparse step when its weighted operation count per sample
/// (`SPARSE_OP_WEIGHT ×` [`sparse_cost`]) is at most the modal map's lower bound
/// ([`modal_cost_lower_bound`]) — banded models with many channels, where it also saves
/// the O(n³) eigen-decomposition — else the modal map when the damping allows it, else the
/// sparse step. Checked against the measured steps/s of `examples/bench_model.rs`
/// (BENCHMARKS.md).
pub enum AutoChoice {
    Dense,
    Modal(ModalStep),
    Sparse(SparseStep),
}

pub fn choose_auto(
    model: &Model,
    dt_s: f64,
    substeps: usize,
    newmark: Newmark,
) -> Result<AutoChoice, EstimateError> {
    let n = model.n();
    if model.has_dense() && n < AUTO_MODAL_MIN_DOFS {
        return Ok(AutoChoice::Dense);
    }
    let sparse = SparseStep::new(model, dt_s, substeps, newmark)?;
    let q = model.Lc.ncols();
    if !model.has_dense()
        || SPARSE_OP_WEIGHT * sparse_cost(&sparse, q)
            <= modal_cost_lower_bound(n, model.stations.len(), q)
    {
        return Ok(AutoChoice::Sparse(sparse));
    }
    Ok(match ModalStep::new(model, dt_s, substeps, newmark) {
        Ok(m) => AutoChoice::Modal(m),
        Err(_) => AutoChoice::Sparse(sparse),
    })
}

/// How the model is advanced: the dense baseline or the exact modal map.
#[allow(clippy::large_enum_variant)] // one per estimator, never moved per sample
enum Engine {
    Dense {
        stepper: Stepper,
        gamma_u: DMatrix<f64>,
        gamma_v: DMatrix<f64>,
        gamma_a: DMatrix<f64>,
        state: State,
        pred: State,
    },
    Modal {
        step: ModalStep,
        outputs: ModalOutputs,
        /// Modal Γ_f, 3r × q.
        gamma: DMatrix<f64>,
        state: ModalState,
        pred: ModalState,
    },
    /// The state is advanced in place (prediction), then `Γ_f R` is added: no copies of
    /// the n-vectors per sample.
    Sparse {
        step: SparseStep,
        gamma_u: DMatrix<f64>,
        gamma_v: DMatrix<f64>,
        gamma_a: DMatrix<f64>,
        state: State,
    },
}

pub struct PaperEstimator {
    engine: Engine,
    law: ConnectionLaw,
    stations: Stations,
    /// `(SᵀWS)⁻¹SᵀW`, q × m.
    gain: DMatrix<f64>,
    p_prev: Vec<f64>,
    g: DVector<f64>,
    lin: DVector<f64>,
    innov: DVector<f64>,
    r: DVector<f64>,
    diag: EstimatorDiagnostics,
}

/// Options shared by the estimators' constructors.
#[derive(Debug, Clone)]
pub struct EstimatorInputs<'a> {
    /// The component model *with* the linear connection terms of the current parameters.
    pub model: &'a Model,
    pub law: ConnectionLaw,
    pub dt_s: f64,
    pub substeps: usize,
    pub newmark: Newmark,
    pub weighting: Weighting,
    /// Noise standard deviation (or, failing that, a scale) per channel, in channel units.
    pub channel_sigma: Vec<f64>,
    /// Compute the error-recursion spectral radius (needs the 3n × 3n transition matrix).
    pub spectral_diagnostics: bool,
}

impl PaperEstimator {
    pub fn new(inp: EstimatorInputs<'_>) -> Result<Self, EstimateError> {
        let model = inp.model;
        let n = model.n();
        let q = inp.law.q();
        let stations = Stations::from_model(model);
        let m = stations.m();
        let choice = match model.step {
            StepKind::Dense => AutoChoice::Dense,
            StepKind::Modal => AutoChoice::Modal(
                ModalStep::new(model, inp.dt_s, inp.substeps, inp.newmark)
                    .map_err(crate::integrate::IntegrateError::from)?,
            ),
            StepKind::Sparse => {
                AutoChoice::Sparse(SparseStep::new(model, inp.dt_s, inp.substeps, inp.newmark)?)
            }
            StepKind::Auto => choose_auto(model, inp.dt_s, inp.substeps, inp.newmark)?,
        };
        if !model.has_dense() && !matches!(choice, AutoChoice::Sparse(_)) {
            return Err(EstimateError::NeedsDense { dofs: n });
        }
        let (mut engine, S) = match choice {
            AutoChoice::Sparse(mut step) => {
                let gamma = step.force_response();
                let S = stations.pick_rows(&gamma, n);
                (
                    Engine::Sparse {
                        step,
                        gamma_u: gamma.rows(0, n).into_owned(),
                        gamma_v: gamma.rows(n, n).into_owned(),
                        gamma_a: gamma.rows(2 * n, n).into_owned(),
                        state: State::zeros(n),
                    },
                    S,
                )
            }
            AutoChoice::Modal(mut step) => {
                let gamma = step.force_response();
                let outputs = ModalOutputs::new(&step, &stations.channels);
                let S = outputs.sensitivity(&gamma);
                let r = step.modes();
                (
                    Engine::Modal {
                        step,
                        outputs,
                        gamma,
                        state: ModalState::zeros(r),
                        pred: ModalState::zeros(r),
                    },
                    S,
                )
            }
            AutoChoice::Dense => {
                let mut stepper = Stepper::new(model, inp.dt_s, inp.substeps, inp.newmark)?;
                let gamma = stepper.force_response();
                let S = stations.pick_rows(&gamma, n);
                (
                    Engine::Dense {
                        stepper,
                        gamma_u: gamma.rows(0, n).into_owned(),
                        gamma_v: gamma.rows(n, n).into_owned(),
                        gamma_a: gamma.rows(2 * n, n).into_owned(),
                        state: State::zeros(n),
                        pred: State::zeros(n),
                    },
                    S,
                )
            }
        };
        let w: Vec<f64> = match inp.weighting {
            Weighting::Unit => vec![1.0; m],
            Weighting::InverseVariance => inp.channel_sigma.iter().map(|s| 1.0 / (s * s)).collect(),
        };
        let sqrt_w = DMatrix::from_diagonal(&DVector::from_iterator(m, w.iter().map(|x| x.sqrt())));
        let ws = &sqrt_w * &S;
        let (rank, condition, gain_max) = rank_and_condition(&ws);
        if rank < q {
            return Err(EstimateError::RankDeficientSensitivity {
                rank,
                needed: q,
                stations: m,
                condition,
            });
        }
        // G = (SᵀWS)⁻¹SᵀW through the SVD of W^½S (stable even when S is badly scaled).
        let Some(svd) = ws.clone().try_svd(true, true, f64::EPSILON, 10_000) else {
            return Err(EstimateError::RankDeficientSensitivity {
                rank: 0,
                needed: q,
                stations: m,
                condition: f64::INFINITY,
            });
        };
        let pinv =
            svd.pseudo_inverse(0.0)
                .map_err(|_| EstimateError::RankDeficientSensitivity {
                    rank,
                    needed: q,
                    stations: m,
                    condition,
                })?;
        let gain = pinv * &sqrt_w;
        let (_, _, s_gain) = rank_and_condition(&S);
        let _ = gain_max;
        let mut diag = EstimatorDiagnostics {
            estimator: "paper".into(),
            sensitivity_rank: rank,
            sensitivity_condition: condition,
            sensitivity_gain: s_gain,
            ..Default::default()
        };
        if inp.spectral_diagnostics && model.has_dense() {
            // The 3n × 3n transition is formed densely whatever the engine (small models).
            let (phi, gamma) = match &mut engine {
                Engine::Dense { stepper, .. } => (stepper.transition(), stepper.force_response()),
                Engine::Modal { .. } | Engine::Sparse { .. } => {
                    let mut s = Stepper::new(model, inp.dt_s, inp.substeps, inp.newmark)?;
                    (s.transition(), s.force_response())
                }
            };
            let h = DMatrix::from_fn(m, 3 * n, |i, j| {
                if stations.state_index(i, n) == j {
                    1.0
                } else {
                    0.0
                }
            });
            let e = (DMatrix::identity(3 * n, 3 * n) - &gamma * &gain * h) * phi;
            let rho = spectral_radius(&e);
            diag.error_spectral_radius = Some(rho);
            if rho >= 1.0 - 1e-9 {
                diag.warnings.push(format!(
                    "Step III error recursion has spectral radius {rho:.6} ≥ 1: measurement noise and model mismatch accumulate from sample to sample; do not trust these residual forces on noisy data"
                ));
            }
        }
        if condition > 1e8 {
            diag.warnings.push(format!(
                "weighted sensitivity S is ill-conditioned (condition number {condition:.3e}): the residual forces amplify noise"
            ));
        }
        Ok(Self {
            engine,
            law: inp.law,
            stations,
            gain,
            p_prev: vec![0.0; model.Lp.ncols()],
            g: DVector::zeros(q),
            lin: DVector::zeros(q),
            innov: DVector::zeros(m),
            r: DVector::zeros(q),
            diag,
        })
    }
}

impl ResidualEstimator for PaperEstimator {
    fn name(&self) -> &'static str {
        "paper"
    }

    fn start(&mut self, _sample: u64, excitation: &[f64]) {
        // A pass starts at rest with zero total connection force (recordings start from
        // rest; a stuck joint at rest carries nothing). The explicit part of f̂ is still
        // evaluated so the first prediction uses the current law.
        let q = self.law.q();
        let z = DVector::zeros(q);
        self.law.explicit_force(&z, &z, &z, &mut self.g);
        match &mut self.engine {
            Engine::Dense { stepper, state, .. } => {
                *state = State::zeros(stepper.n);
                stepper.initial_acceleration(state, excitation, &z);
            }
            Engine::Modal { step, state, .. } => {
                *state = ModalState::zeros(step.modes());
                step.initial_acceleration(state, excitation, &z);
            }
            Engine::Sparse { step, state, .. } => {
                *state = State::zeros(step.n);
                step.initial_acceleration(state, excitation, &z);
            }
        }
        self.p_prev.copy_from_slice(excitation);
    }

    fn step(
        &mut self,
        sample: u64,
        excitation: &[f64],
        measured: &[f64],
        out: &mut StepOutput,
    ) -> Result<bool, EstimateError> {
        out.sample = sample;
        match &mut self.engine {
            Engine::Dense {
                stepper,
                gamma_u,
                gamma_v,
                gamma_a,
                state,
                pred,
            } => {
                // Step I: predict with R = 0 and the explicit part of f̂ from the previous
                // state.
                pred.u.copy_from(&state.u);
                pred.v.copy_from(&state.v);
                pred.a.copy_from(&state.a);
                stepper.advance(pred, &self.p_prev, excitation, &self.g);
                // Step III: R = G (y_m − y_p).
                for (k, &(dof, q)) in self.stations.channels.iter().enumerate() {
                    self.innov[k] = measured[k] - pred.channel(dof, q);
                }
                self.r.gemv(1.0, &self.gain, &self.innov, 0.0);
                // Step IV: the model advanced with R.
                state.u.copy_from(&pred.u);
                state.u.gemv(1.0, gamma_u, &self.r, 1.0);
                state.v.copy_from(&pred.v);
                state.v.gemv(1.0, gamma_v, &self.r, 1.0);
                state.a.copy_from(&pred.a);
                state.a.gemv(1.0, gamma_a, &self.r, 1.0);
                if !state.is_finite() {
                    return Err(EstimateError::Diverged { sample });
                }
                let lc = &stepper.Lc;
                out.delta.gemv_tr(1.0, lc, &state.u, 0.0);
                out.delta_v.gemv_tr(1.0, lc, &state.v, 0.0);
                out.delta_a.gemv_tr(1.0, lc, &state.a, 0.0);
            }
            Engine::Modal {
                step,
                outputs,
                gamma,
                state,
                pred,
            } => {
                pred.copy_from(state);
                step.advance(pred, &self.p_prev, excitation, &self.g);
                for (k, (i, y)) in self.innov.iter_mut().zip(measured).enumerate() {
                    *i = y - outputs.channel(pred, k);
                }
                self.r.gemv(1.0, &self.gain, &self.innov, 0.0);
                state.copy_from(pred);
                state.add_response(gamma, &self.r);
                if !state.is_finite() {
                    return Err(EstimateError::Diverged { sample });
                }
                // δ = LcᵀΨ η = (ΨᵀLc)ᵀ η.
                out.delta.gemv_tr(1.0, &step.bc, &state.q, 0.0);
                out.delta_v.gemv_tr(1.0, &step.bc, &state.qd, 0.0);
                out.delta_a.gemv_tr(1.0, &step.bc, &state.qdd, 0.0);
            }
            Engine::Sparse {
                step,
                gamma_u,
                gamma_v,
                gamma_a,
                state,
            } => {
                // As the dense engine, with the sparse step, the prediction made in place and
                // δ from the non-zeros of Lc.
                step.advance(state, &self.p_prev, excitation, &self.g);
                for (k, &(dof, q)) in self.stations.channels.iter().enumerate() {
                    self.innov[k] = measured[k] - state.channel(dof, q);
                }
                self.r.gemv(1.0, &self.gain, &self.innov, 0.0);
                state.u.gemv(1.0, gamma_u, &self.r, 1.0);
                state.v.gemv(1.0, gamma_v, &self.r, 1.0);
                state.a.gemv(1.0, gamma_a, &self.r, 1.0);
                if !state.is_finite() {
                    return Err(EstimateError::Diverged { sample });
                }
                step.deformation(&state.u, &mut out.delta);
                step.deformation(&state.v, &mut out.delta_v);
                step.deformation(&state.a, &mut out.delta_a);
            }
        }
        self.law
            .linear_force(&out.delta, &out.delta_v, &out.delta_a, &mut self.lin);
        out.residual.copy_from(&self.r);
        out.force.copy_from(&self.lin);
        out.force += &self.g;
        out.force += &self.r;
        // The explicit force for the next interval, from this state.
        self.law
            .explicit_force(&out.delta, &out.delta_v, &out.delta_a, &mut self.g);
        self.p_prev.copy_from_slice(excitation);
        Ok(true)
    }

    fn drain(&mut self, _out: &mut StepOutput) -> bool {
        false
    }

    fn diagnostics(&self) -> &EstimatorDiagnostics {
        &self.diag
    }
}
