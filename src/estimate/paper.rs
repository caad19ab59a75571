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

#![allow(non_snake_case)]

use nalgebra::{DMatrix, DVector};

use super::{
    ConnectionLaw, EstimateError, EstimatorDiagnostics, ResidualEstimator, Stations, StepOutput,
    rank_and_condition, spectral_radius,
};
use crate::integrate::{State, Stepper};
use crate::model::Model;
use crate::setup::{Newmark, Weighting};

pub struct PaperEstimator {
    stepper: Stepper,
    law: ConnectionLaw,
    stations: Stations,
    gamma_u: DMatrix<f64>,
    gamma_v: DMatrix<f64>,
    gamma_a: DMatrix<f64>,
    /// `(SᵀWS)⁻¹SᵀW`, q × m.
    gain: DMatrix<f64>,
    state: State,
    pred: State,
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
        let mut stepper = Stepper::new(model, inp.dt_s, inp.substeps, inp.newmark)?;
        let n = model.n();
        let q = inp.law.q();
        let stations = Stations::from_model(model);
        let m = stations.m();
        let gamma = stepper.force_response();
        let S = stations.pick_rows(&gamma, n);
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
        let svd = ws.clone().svd(true, true);
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
        if inp.spectral_diagnostics {
            let phi = stepper.transition();
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
            gamma_u: gamma.rows(0, n).into_owned(),
            gamma_v: gamma.rows(n, n).into_owned(),
            gamma_a: gamma.rows(2 * n, n).into_owned(),
            stepper,
            law: inp.law,
            stations,
            gain,
            state: State::zeros(n),
            pred: State::zeros(n),
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
        let n = self.stepper.n;
        self.state = State::zeros(n);
        // A pass starts at rest with zero total connection force (recordings start from
        // rest; a stuck joint at rest carries nothing). The explicit part of f̂ is still
        // evaluated so the first prediction uses the current law.
        let q = self.law.q();
        let z = DVector::zeros(q);
        self.law.explicit_force(&z, &z, &z, &mut self.g);
        self.stepper
            .initial_acceleration(&mut self.state, excitation, &z);
        self.p_prev.copy_from_slice(excitation);
    }

    fn step(
        &mut self,
        sample: u64,
        excitation: &[f64],
        measured: &[f64],
        out: &mut StepOutput,
    ) -> Result<bool, EstimateError> {
        // Step I: predict with R = 0 and the explicit part of f̂ from the previous state.
        self.pred.u.copy_from(&self.state.u);
        self.pred.v.copy_from(&self.state.v);
        self.pred.a.copy_from(&self.state.a);
        self.stepper
            .advance(&mut self.pred, &self.p_prev, excitation, &self.g);
        // Step III: R = G (y_m − y_p).
        for (k, &(dof, q)) in self.stations.channels.iter().enumerate() {
            self.innov[k] = measured[k] - self.pred.channel(dof, q);
        }
        self.r.gemv(1.0, &self.gain, &self.innov, 0.0);
        // Step IV: the model advanced with R.
        self.state.u.copy_from(&self.pred.u);
        self.state.u.gemv(1.0, &self.gamma_u, &self.r, 1.0);
        self.state.v.copy_from(&self.pred.v);
        self.state.v.gemv(1.0, &self.gamma_v, &self.r, 1.0);
        self.state.a.copy_from(&self.pred.a);
        self.state.a.gemv(1.0, &self.gamma_a, &self.r, 1.0);
        if !self.state.is_finite() {
            return Err(EstimateError::Diverged { sample });
        }
        let lc = &self.stepper.Lc;
        out.sample = sample;
        out.delta.gemv_tr(1.0, lc, &self.state.u, 0.0);
        out.delta_v.gemv_tr(1.0, lc, &self.state.v, 0.0);
        out.delta_a.gemv_tr(1.0, lc, &self.state.a, 0.0);
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
