//! Steps V and VI: passes over a recorded test. Each pass builds the model with the current
//! parameters (linear terms into K, C, M; the rest as explicit forces), runs a residual
//! estimator over every sample, accumulates the least-squares fit online and solves it at
//! the end of the pass; passes repeat until the parameters stop moving.
//!
//! Stopping rule (the paper asks for one): stop after pass k ≥ 2 when every parameter
//! moved by less than `tolerance_std_errors` of its standard error, or its change moves
//! the fitted connection force by less than `tolerance_relative` of the force's RMS
//! (`|Δpⱼ|·rms(vⱼ) ≤ tol·rms(f)`, which catches noise-free data where standard errors are
//! round-off); otherwise stop at `passes` and say it did not converge. "Moved" is the
//! pass's output against the parameters it ran with (the fixed-point residual of the pass
//! map). For the Kalman estimator the likelihood tuning is redone each pass until a pass
//! moves every parameter by less than one standard error (at most three tunings; two when a
//! refinement follows the passes, whose start they only are), then frozen: re-tuning every
//! pass kept moving the parameters and the passes never converged.
//! With the map fixed the passes converge linearly (ratio ≈ 0.4–0.75 measured); after two
//! plain passes the next input is Aitken-extrapolated to the limit.
//!
//! Standard errors: Newey–West (HAC) on the fit residuals, never below the OLS ones. After
//! the passes, the Cramér–Rao bound of every parameter is computed from the output
//! sensitivities and, for the Kalman estimator, the parameters are refined by output error
//! (see `estimate::output_error`); an accepted refinement replaces the values and standard
//! errors of the last pass.
//!
//! Samples on a `sign` switching surface (a stuck joint: `δ̇ ≈ 0` for `sign(v)`, `δ ≈ 0` for
//! `sign(u)`) carry an unknown friction force anywhere in `[−F, F]`; they are excluded from
//! that connection's fit. "≈ 0" means within `stick_band` × the largest |δ̇| (or |δ|) seen so
//! far in the pass, plus the estimator's own uncertainty of the variable when it reports
//! one. The count of excluded samples is reported.
//!
//! Submodules: `kalman_tuning` (the filter's likelihood tuning of a pass), `substeps` (the
//! free run's model sub-step levels), `scan` (the output-error stage started from a scan
//! when the residual-force stage cannot start it), `pem` (the prediction-error refinement
//! of `sign(u)` laws), `likelihood` (the likelihood-ratio check of the free run's errors)
//! and `bootstrap`.

use nalgebra::DVector;
use serde::Serialize;

use crate::estimate::paper::{EstimatorInputs, PaperEstimator};
use crate::estimate::refit::{Fit, RecursiveLeastSquares, RefitError};
use crate::estimate::{
    ConnectionLaw, EstimateError, EstimatorDiagnostics, ResidualEstimator, StepOutput,
};
use crate::model::Model;
use crate::setup::{Basis, EstimatorKind, Quantity, Setup, Weighting};
use crate::track::{Track, TrackOptions, Tracker};

mod bootstrap;
mod kalman_tuning;
mod likelihood;
mod pem;
mod scan;
mod substeps;

pub use kalman_tuning::{KalmanTuning, RETUNE_WALK_DECADES, TUNE_SAMPLES, tune_kalman};
use substeps::{MAX_RAISED_STEPS, raise_substeps};

use pem::{PEM_MAX_COST, PemStage, pem_undetermined, refine_by_prediction_error};
use scan::{
    MAX_SCAN_PROBE_MOVE, SETTLE_ROUNDS, ScanReason, acceleration_only, has_nonlinear_term,
    has_sign_basis, has_sign_u_basis, has_spring_basis, identify_acceleration_only,
    identify_from_scan, restate_final_errors, scan_fallback_applies,
};

#[derive(Debug, thiserror::Error)]
pub enum IdentifyError {
    #[error(transparent)]
    Model(#[from] crate::model::ModelError),
    #[error(transparent)]
    Estimate(#[from] EstimateError),
    #[error("pass {pass}, connection `{connection}`: {source}")]
    Refit {
        pass: usize,
        connection: String,
        source: RefitError,
    },
    #[error(
        "pass {pass}, connection `{connection}`: the measurements do not determine the joint deformation: its posterior std {posterior_std:.3e} m is {:.2}× the RMS of its estimate ({rms:.3e} m; limit {}) — the residual force trades off against unobserved (static) deformation and any fit would be a confident wrong answer; add a displacement or velocity channel near the joint (accelerometer-only layouts: see the ACCURACY.md)",
        posterior_std / rms.max(f64::MIN_POSITIVE),
        MAX_DEFORMATION_UNCERTAINTY
    )]
    Undetermined {
        pass: usize,
        connection: String,
        posterior_std: f64,
        rms: f64,
    },
    #[error(transparent)]
    MaximumLikelihood(#[from] crate::estimate::ml::MlError),
    #[error("the data hold {0} samples; at least 3 are needed")]
    TooShort(usize),
    /// The record does not start at rest, which the Kalman and paper pipelines assume.
    #[error(
        "the record does not start at rest: at its first sample (sample {sample}) the {channels} displacement and velocity channels read Σ(value/noise std)² = {chi2:.1} (limit {chi2_limit:.1}, a false alarm on a record at rest has probability 2e-9), the largest sensor `{sensor}` {value:.4e}, {ratio:.1}× its noise std {sigma:.3e} (limit {} for one channel); this estimator starts the model at rest (the 1989 estimator, and the free-run output-error refinement of laws without a friction (`sign`) term), and on records cut from a test in motion such a start was up to millions of standard errors off (ACCURACY.md, \"Records that start in motion\"); start the record before the excitation, remove a static offset from a displacement channel, identify with `--estimator kalman --no-refine` (the Kalman passes estimate the initial state) or, for a law linear in the state, with `--estimator ml`",
        MAX_START_NOISE_RATIO
    )]
    NotAtRest {
        sensor: String,
        sample: u64,
        value: f64,
        sigma: f64,
        ratio: f64,
        /// Σ (value / noise std)² over the displacement and velocity channels.
        chi2: f64,
        channels: usize,
        chi2_limit: f64,
    },
    /// A window cut from a longer record: in motion whatever its first sample reads.
    #[error(
        "the window starts mid-record (sample {sample}), in motion, and this estimator starts the model at rest (the 1989 estimator, and the free-run output-error refinement of laws without a friction (`sign`) term; with accelerometers only a start in motion cannot even be seen in the data); identify the whole record, or windows with `--no-refine` or `[estimator] output_error = false` (the Kalman passes estimate the initial state) or, for a law linear in the state, with `--estimator ml`"
    )]
    MidRecord { sample: u64 },
    /// The user says the record starts in motion (`--in-motion`).
    #[error(
        "the record is said to start in motion (`--in-motion`; first sample {sample}), and this estimator starts the model at rest (the 1989 estimator, and the free-run output-error refinement of laws without a friction (`sign`) term); identify with `--estimator kalman --no-refine` (the Kalman passes estimate the initial state) or, for a law linear in the state, with `--estimator ml`"
    )]
    SaidInMotion { sample: u64 },
    /// A start in motion seen by the whole record's innovations, not by its first sample.
    #[error(
        "the record starts in motion although its first sample reads like rest: a start state refitted to an observer's innovations at the answer ({substeps} model sub-steps) removes {reduction:.1} from their whitened cost, beyond the limit {limit:.1}; this estimator starts the model at rest (the 1989 estimator, and the free-run output-error refinement of laws without a friction (`sign`) term), so it cannot start elsewhere; `--in-motion --estimator kalman --no-refine` estimates the start state with the Kalman passes alone, or record from rest (start the acquisition before the excitation) or cut the record where the structure is at rest, or, for a law linear in the state, identify with `--estimator ml` (it estimates the initial state)"
    )]
    MotionInRecord {
        reduction: f64,
        limit: f64,
        rank: usize,
        level: f64,
        substeps: usize,
    },
    /// A start in motion seen by the whole record's innovations, identified again with the
    /// start state estimated (a friction law: by prediction error), and refused there.
    #[error(
        "the record starts in motion although its first sample reads like rest (a start state refitted to an observer's innovations at the answer, {substeps} model sub-steps, removes {reduction:.1} from their whitened cost, beyond the limit {limit:.1}; the free run starts at rest) and, identified again with its start state estimated, it was refused ({then}); record from rest (start the acquisition before the excitation) or cut the record where the structure is at rest"
    )]
    MotionInRecordRefused {
        reduction: f64,
        limit: f64,
        substeps: usize,
        then: Box<IdentifyError>,
    },
    #[error(
        "{context}: the output-error stage started from a scan did not settle — its probes kept finding lower costs and moved `{parameter}` by {moved:.1} of the stated standard errors (limit {}; up to {} restarts from the probe's end tried); refused rather than reported with errors that would not hold",
        MAX_SCAN_PROBE_MOVE,
        SETTLE_ROUNDS
    )]
    ScanUnsettled {
        context: String,
        parameter: String,
        moved: f64,
    },
    /// The residual-force stage's answer for a friction law is a model the free run cannot
    /// simulate from rest: the data reject it outright, so the output-error stage has no
    /// start (measured: Coulomb `sign(v), u` with the sensors' true `noise_std` given,
    /// 8-sub-step data at 1 % noise, seed 9317: the passes gave `u` = −1.8e5 N/m, whose
    /// effective mass matrix is singular, and that answer was reported 7.9 errors off).
    #[error(
        "the residual-force stage's answer ({answer}) cannot be simulated: the free run from rest with it failed ({why}); it is no start for the output-error stage"
    )]
    StartRejected { answer: String, why: String },
    /// A law with friction whose residual-force stage was refused, and whose scan-started
    /// output-error fallback did not give an accepted answer either.
    #[error(
        "{refused}; the output-error stage started from a scan was tried instead and not accepted: {why}"
    )]
    ScanFallbackRejected {
        refused: Box<IdentifyError>,
        why: String,
    },
}

/// The measured test, aligned by sample: `excitation[i]` and `response[i]` belong to
/// `samples[i]`, in setup channel order.
#[derive(Debug, Clone, Default)]
pub struct TestData {
    pub samples: Vec<u64>,
    pub t_ns: Vec<u64>,
    pub excitation: Vec<Vec<f64>>,
    pub response: Vec<Vec<f64>>,
}

impl TestData {
    pub fn len(&self) -> usize {
        self.samples.len()
    }

    /// The free run of `params` over this record with `substeps` model sub-steps per
    /// sample: the output errors `(y − ŷ)/σ` normalised by the channels' noise levels
    /// `sigma`, and their sum of squares (`estimate::output_error::residuals`).
    pub(crate) fn free_run(
        &self,
        setup: &Setup,
        model: &Model,
        params: &[f64],
        sigma: &[f64],
        substeps: usize,
    ) -> Result<(Vec<f64>, f64), crate::simulate::SimulateError> {
        crate::estimate::output_error::residuals(
            setup,
            model,
            params,
            &self.excitation,
            &self.response,
            sigma,
            substeps,
        )
    }

    pub fn is_empty(&self) -> bool {
        self.samples.is_empty()
    }

    /// The first `len` samples, or `None` when the record is not longer than that.
    pub fn prefix(&self, len: usize) -> Option<TestData> {
        (self.len() > len).then(|| TestData {
            samples: self.samples[..len].to_vec(),
            t_ns: self.t_ns[..len.min(self.t_ns.len())].to_vec(),
            excitation: self.excitation[..len].to_vec(),
            response: self.response[..len].to_vec(),
        })
    }

    /// Root-mean-square of each response channel (a scale for the weights when no noise
    /// level is known).
    pub fn response_rms(&self) -> Vec<f64> {
        let m = self.response.first().map_or(0, |r| r.len());
        (0..m)
            .map(|k| {
                let s: f64 = self.response.iter().map(|y| y[k] * y[k]).sum();
                (s / self.len().max(1) as f64).sqrt().max(f64::MIN_POSITIVE)
            })
            .collect()
    }
}

#[derive(Debug, Clone)]
pub struct IdentifyOptions {
    pub estimator: EstimatorKind,
    /// The estimator was chosen by default (not by the setup or `--estimator`): when maximum
    /// likelihood cannot run (a model too large for its dense matrices, a record too short),
    /// the Kalman pipeline runs instead, with a note saying why.
    pub estimator_by_default: bool,
    pub weighting: Weighting,
    pub passes: usize,
    pub tolerance_std_errors: f64,
    pub tolerance_relative: f64,
    pub max_condition: f64,
    /// Relative width of the excluded band around a sign switching surface.
    pub stick_band: f64,
    /// Substeps of the identification model per sample.
    pub substeps: usize,
    /// Coarsest model sub-steps the refinement's level choices consider (the setup's; the
    /// scan fallback refines at the level its prefix preferred, and the choices still go
    /// down to this one — except for accelerometer-only layouts, see `scan.rs`).
    pub coarsest_substeps: usize,
    /// Random-walk std of the residual force per sample for the Kalman estimator, N. `None`:
    /// tuned per pass by maximising the innovation likelihood (see `tune_kalman`).
    pub force_walk_std: Option<f64>,
    /// Kalman tuning: also scale the estimated channel noise levels by a likelihood-tuned
    /// factor.
    pub tune_noise_scale: bool,
    /// Kalman tuning: at most this many samples per candidate run (0: all; default
    /// [`TUNE_SAMPLES`]).
    pub tune_samples: usize,
    /// The state the record starts from, as offsets `(u; u̇; ü)` (`3n`) from rest: set by
    /// [`identify`] when the record starts in motion (estimated by the Kalman filter's
    /// initial-state fit); every filter run and the prediction-error refinement start
    /// from it. `None`: at rest.
    pub initial_state: Option<Vec<f64>>,
    /// The record is a window cut from a longer one at this sample: in motion whatever
    /// its first sample reads (with accelerometers only, a start in motion cannot be seen
    /// in the data; measured: windows of an accelerometer-only record identified as if at
    /// rest were up to 180 standard errors off). `None`: a record of its own.
    pub starts_mid_record: Option<u64>,
    /// The user says the record starts in motion (`replay --in-motion`: a record cut from a
    /// running test): identified as a window cut mid-record is, the start state estimated
    /// whatever its first sample reads. Why an option: at high noise neither the first
    /// sample nor the whole record's innovations tell a start in motion from a model's own
    /// misfit reliably (ACCURACY.md, thirty-fourth session), and the user often knows.
    pub in_motion: bool,
    /// The record starts in motion although its first sample reads like rest: what the
    /// prediction error's observer saw in the whole record's innovations (set by
    /// [`identify`] for its second run, which treats the record as in motion). `None`: not
    /// seen, or not looked for yet.
    pub start_motion: Option<MotionInRecord>,
    /// Values the initial-state fit and the final refinement start from instead of the
    /// setup's `initial` and the passes' residual-force estimate: a window of a session
    /// starts from the combination of the windows before it ([`crate::session`]). Why: a
    /// window cut from a test in motion at a high sample rate gives poor residual-force
    /// estimates (measured at 51.2 kHz: `sign(u)` −1.4e5 N, spring +48 %, fit residual RMS
    /// 1.5e5 N), the observer force tuned at them absorbs the friction and the window was
    /// refused; from the session's answer so far the same window's prediction error ends
    /// within 0.5 of its standard errors. Where the refinement ends is still decided by the
    /// window's data alone. `None`: a record of its own.
    pub prior: Option<Prior>,
    /// Kalman: evaluate the non-linear connection force at the predicted state.
    pub semi_implicit: bool,
    /// Kalman: model-error force std at every DOF, N. `None`: tuned with σ_R when that is
    /// tuned, else `MODEL_ERROR_RELATIVE ×` the force scale.
    pub model_error_std: Option<f64>,
    /// Kalman: also tune the model-error std by likelihood. Off by default: measured on the
    /// two-beam problem it lets the state absorb the connection force (friction −67 %).
    pub tune_model_error: bool,
    /// Widen the stuck band by this many posterior std of δ (δ̇) when the estimator
    /// reports them (`posterior_delta_std_m[c]` in its diagnostics).
    pub stick_band_sigmas: f64,
    /// Tracking: forgetting factor per sample of the tracked fit (see [`crate::track`]).
    pub forgetting: f64,
    /// Tracking: solve the tracked fit every this many samples (0: the default interval).
    pub track_every: usize,
    /// Refine the final parameters by output error (see `estimate::output_error`).
    pub output_error: bool,
    /// Gauss–Newton iterations of the output-error refinement at most.
    pub output_error_iterations: usize,
    /// Compute the Cramér–Rao bound of every parameter.
    pub crlb: bool,
    /// Kalman tuning is re-done each pass until a pass moves every parameter by less than
    /// this many standard errors (or `max_tunings` passes were tuned); then it is frozen so
    /// the passes become a fixed-point iteration that can converge.
    pub retune_above_std_errors: f64,
    pub max_tunings: usize,
    /// `max_tunings` when the passes' answer is the start of a refinement
    /// (`output_error`): the refinement's answer is the minimiser of its own cost, and the
    /// passes only need to bring it near. Two: at the setup's initial values and at the
    /// first pass's answer — one alone, made at initial values far from the structure, was
    /// frozen with a filter whose error recursion was unstable (ρ 1.003) and made the second
    /// pass diverge at its first sample (`mixed_layout_noise_free_friction_and_spring`).
    /// Why not three: the tunings were three quarters of the passes' time; measured over
    /// seeds 371–390 (friction and spring setups, data sub-steps 1, 8, 64, noise 1, 10,
    /// 100 %) coverage and worst errors were unchanged with two and with one (ACCURACY.md,
    /// sixteenth session).
    pub max_tunings_refined: usize,
    /// Replicates of the parametric bootstrap of a prediction-error answer (`Some(0)`: none;
    /// `None`: automatic, [`pem::AUTO_BOOTSTRAP_REPLICATES`] when the excitation repeats
    /// itself, was found smooth between samples or is an impact's, the sandwich depends on its
    /// secant ([`pem::BOOTSTRAP_SECANT_DISAGREEMENT`]), the law has a friction on the rate or
    /// the refinement kept one model sub-step per sample, and none otherwise; see `identify::pem::bootstrap_occasion` and `identify::pem::bootstrap`)
    /// and of a free-run output-error answer (`None` runs none there unless a friction law's
    /// sensors have their `noise_std` given; see `identify::bootstrap`).
    pub bootstrap: Option<usize>,
    /// Options of the maximum-likelihood estimator (`EstimatorKind::Ml`).
    pub ml: crate::estimate::ml::MlOptions,
}

impl IdentifyOptions {
    pub fn from_setup(setup: &Setup) -> Self {
        let e = &setup.estimator;
        Self {
            estimator: e.kind_for(&setup.connections),
            estimator_by_default: e.kind.is_none(),
            weighting: e.weighting,
            passes: e.passes,
            tolerance_std_errors: e.tolerance_std_errors,
            tolerance_relative: e.tolerance_relative,
            max_condition: e.max_condition,
            stick_band: 1e-6,
            substeps: setup.substeps,
            coarsest_substeps: setup.substeps,
            force_walk_std: e.force_walk_std,
            tune_noise_scale: true,
            tune_samples: TUNE_SAMPLES,
            initial_state: None,
            starts_mid_record: None,
            in_motion: false,
            start_motion: None,
            prior: None,
            semi_implicit: true,
            model_error_std: None,
            tune_model_error: false,
            stick_band_sigmas: 3.0,
            forgetting: e.forgetting,
            track_every: e.track_every,
            output_error: e.output_error && e.kind_for(&setup.connections) == EstimatorKind::Kalman,
            output_error_iterations: 20,
            crlb: e.crlb,
            retune_above_std_errors: 1.0,
            max_tunings: 3,
            max_tunings_refined: 2,
            bootstrap: None,
            ml: crate::estimate::ml::MlOptions::default(),
        }
    }
}

/// Start values of an identification and their standard errors (all parameters in setup
/// order); see [`IdentifyOptions::prior`].
#[derive(Debug, Clone, PartialEq)]
pub struct Prior {
    pub values: Vec<f64>,
    pub std_errors: Vec<f64>,
    /// Where the values come from, for the notes ("the combination of 2 earlier windows").
    pub source: String,
}

impl Prior {
    /// The prior when it fits `setup` (one finite value and a positive finite error per
    /// parameter), else `None`.
    fn for_setup(&self, setup: &Setup) -> Option<&Self> {
        let n = setup.param_keys().len();
        let ok = self.values.len() == n
            && self.std_errors.len() == n
            && self.values.iter().all(|v| v.is_finite())
            && self.std_errors.iter().all(|e| e.is_finite() && *e > 0.0);
        ok.then_some(self)
    }
}

/// One parameter's estimate.
#[derive(Debug, Clone, Serialize)]
pub struct ParameterEstimate {
    pub connection: String,
    pub basis: String,
    pub unit: String,
    pub value: f64,
    pub std_error: f64,
    /// 95 % confidence interval, value ± 1.96·std_error.
    pub ci95: [f64; 2],
    /// Cramér–Rao lower bound of the standard error for this recording (output
    /// sensitivities at the estimate, the channel noise levels).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub crlb: Option<f64>,
    /// OLS standard error of the residual-force fit that treats rows as independent, for
    /// comparison (the reported one accounts for their correlation in time).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub std_error_ols: Option<f64>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub truth: Option<f64>,
}

/// What one pass found.
#[derive(Debug, Clone, Serialize)]
pub struct PassReport {
    pub pass: usize,
    pub parameters: Vec<ParameterEstimate>,
    /// Per connection: condition number of the column-scaled fit.
    pub fit_condition: Vec<f64>,
    /// Per connection: RMS of the fit residual, N.
    pub fit_rms_residual: Vec<f64>,
    pub rows_used: Vec<usize>,
    pub rows_excluded_stuck: Vec<usize>,
    pub diagnostics: EstimatorDiagnostics,
    /// Largest |Δp|/se against the previous pass.
    pub max_change_std_errors: Option<f64>,
    /// Largest |Δpⱼ|·rms(vⱼ)/rms(f) against the previous pass.
    pub max_change_force_relative: Option<f64>,
    #[serde(skip)]
    force_scales: Vec<(f64, f64)>,
}

#[derive(Debug, Clone, Serialize)]
pub struct Identification {
    pub estimator: String,
    pub passes: Vec<PassReport>,
    pub converged: bool,
    pub stop_reason: String,
    /// Set when a pass failed; the passes before it are kept.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub failure: Option<String>,
    /// The parameters' time history over the last reported pass (see [`crate::track`]).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub track: Option<Track>,
    /// The output-error refinement after the passes, when run.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub output_error: Option<crate::estimate::output_error::OutputErrorReport>,
    /// The maximum-likelihood fit (the default estimator), when it ran.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub maximum_likelihood: Option<crate::estimate::ml::MlFit>,
    /// Why the Cramér–Rao bound or the refinement could not be computed, if so.
    #[serde(skip_serializing_if = "Vec::is_empty")]
    pub notes: Vec<String>,
    /// A record identified in windows (`crate::session`): every window's estimate and
    /// their combination, which the last pass's parameters then carry. The passes, the
    /// refinement and the notes above are the last window's.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub session: Option<crate::session::SessionReport>,
    /// A record that starts in motion: the estimated initial state `(u; u̇; ü)` as offsets
    /// from rest (the Kalman passes' last fit), which the predicted response starts from.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub initial_state: Option<Vec<f64>>,
    /// Set when the prediction error saw a start in motion that the first sample had not
    /// shown: [`identify`] then runs again with the record treated as in motion.
    #[serde(skip)]
    pub motion_in_record: Option<MotionInRecord>,
    /// Set when the free-run output-error refinement could not run from the passes'
    /// answer (its simulation failed: the model those values give diverges or cannot be
    /// stepped): the reason. For a friction law at rest [`identify`] then takes the start
    /// from a scan (no report was made, so none is replaced).
    #[serde(skip)]
    pub refinement_not_run: Option<String>,
}

/// A start in motion seen in the innovations of the prediction error's observer (run
/// from rest at the refined values): the whitened cost a refitted start state removes, the
/// limit it passed (the χ² quantile of its `rank` degrees of freedom at 1e-3 times
/// `level`, the run's normalised cost when above 1) and the model sub-steps of the run.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct MotionInRecord {
    pub reduction: f64,
    pub limit: f64,
    pub rank: usize,
    pub level: f64,
    pub substeps: usize,
}

impl Identification {
    /// No pass yet, nothing refined, no notes: what an estimator's run starts from.
    pub fn started(estimator: impl Into<String>) -> Self {
        Self {
            estimator: estimator.into(),
            passes: Vec::new(),
            converged: false,
            stop_reason: String::new(),
            failure: None,
            track: None,
            output_error: None,
            maximum_likelihood: None,
            notes: Vec::new(),
            session: None,
            initial_state: None,
            motion_in_record: None,
            refinement_not_run: None,
        }
    }

    /// Reasons the identified model does not explain the data (non-white residuals, fitted
    /// noise above the stated `noise_std`, output-error cost far above the noise): what
    /// `--strict` refuses on.
    pub fn inadequacy(&self) -> Vec<String> {
        let mut out: Vec<String> = self
            .maximum_likelihood
            .as_ref()
            .map(|m| m.warnings.clone())
            .unwrap_or_default();
        out.extend(
            self.notes
                .iter()
                .filter(|n| {
                    n.starts_with("the model explains the outputs only")
                        || n.starts_with(RESIDUALS_NOT_WHITE)
                })
                .cloned(),
        );
        out
    }

    pub fn final_parameters(&self) -> Option<&[ParameterEstimate]> {
        self.passes.last().map(|p| p.parameters.as_slice())
    }
}

/// Per-sample record of the final pass, for output files.
#[derive(Debug, Clone, Serialize)]
pub struct SampleRecord {
    pub sample: u64,
    pub residual: Vec<f64>,
    pub force: Vec<f64>,
    pub delta: Vec<f64>,
    pub delta_v: Vec<f64>,
    pub delta_a: Vec<f64>,
}

/// Fewer independent measured quantities than connection DOFs cannot determine the residual
/// forces, whatever the estimator: check rank(S) once, up front.
///
/// Accelerometer-only layouts are refused for the Kalman estimator here (the live pipeline
/// runs it online, where nothing else could identify them); the batch [`identify`] lets
/// them through to its output-error path when that can run (see
/// `identify_acceleration_only`).
pub fn check_observability(
    setup: &Setup,
    model: &Model,
    opts: &IdentifyOptions,
) -> Result<(), EstimateError> {
    check_observability_with(setup, model, opts, false)
}

fn check_observability_with(
    setup: &Setup,
    model: &Model,
    opts: &IdentifyOptions,
    accel_only_by_output_error: bool,
) -> Result<(), EstimateError> {
    let stations = crate::estimate::Stations::from_model(model);
    if opts.estimator == EstimatorKind::Kalman
        && !accel_only_by_output_error
        && acceleration_only(model)
    {
        return Err(EstimateError::AccelerationOnly {
            channels: stations.m(),
        });
    }
    if !model.has_dense() {
        // Sparse-only models (thousands of DOFs): the paper estimator's construction checks
        // rank(S) itself from its sparse force response; the Kalman one refuses them.
        return Ok(());
    }
    let with_terms = model.with_connection_terms(setup, &setup.initial_params());
    let mut stepper =
        crate::integrate::Stepper::new(&with_terms, setup.dt_s, opts.substeps, setup.newmark)?;
    let s = stations.pick_rows(&stepper.force_response(), model.n());
    // Scale each channel by its largest sensitivity so units do not decide the rank.
    let scaled = nalgebra::DMatrix::from_fn(s.nrows(), s.ncols(), |i, j| {
        let m = s.row(i).amax();
        if m > 0.0 { s[(i, j)] / m } else { 0.0 }
    });
    let (rank, condition, _) = crate::estimate::rank_and_condition(&scaled);
    let q = setup.connections.len();
    if rank < q {
        return Err(EstimateError::RankDeficientSensitivity {
            rank,
            needed: q,
            stations: stations.m(),
            condition,
        });
    }
    Ok(())
}

/// Build the estimator for one pass.
pub fn build_estimator(
    setup: &Setup,
    model: &Model,
    params: &[f64],
    opts: &IdentifyOptions,
    channel_sigma: &[f64],
    samples: usize,
) -> Result<Box<dyn ResidualEstimator>, EstimateError> {
    let with_terms = model.with_connection_terms(setup, params);
    let inputs = EstimatorInputs {
        model: &with_terms,
        law: ConnectionLaw::new(setup, params),
        dt_s: setup.dt_s,
        substeps: opts.substeps,
        newmark: setup.newmark,
        weighting: opts.weighting,
        channel_sigma: channel_sigma.to_vec(),
        spectral_diagnostics: 3 * model.n() <= 600,
    };
    Ok(match opts.estimator {
        EstimatorKind::Paper => Box::new(PaperEstimator::new(inputs)?),
        // The Kalman estimator is dense (its covariance is 3n × 3n anyway).
        EstimatorKind::Kalman | EstimatorKind::Ml if !model.has_dense() => {
            return Err(EstimateError::NeedsDense { dofs: model.n() });
        }
        // The maximum-likelihood estimator is batch only: where a residual-force estimator
        // is needed per sample (the live stepper), the Kalman one runs.
        EstimatorKind::Kalman | EstimatorKind::Ml => {
            use crate::estimate::kalman::{
                KalmanEstimator, KalmanOptions, MODEL_ERROR_RELATIVE, force_scale_of,
            };
            let scale = force_scale_of(inputs.model);
            let ko = KalmanOptions {
                force_walk_std: opts.force_walk_std.unwrap_or(scale),
                model_error_std: opts.model_error_std.unwrap_or(MODEL_ERROR_RELATIVE * scale),
                smooth: true,
                semi_implicit: opts.semi_implicit,
                likelihood_only: false,
                horizon: (samples > 0).then_some(samples),
            };
            let mut est = KalmanEstimator::with_options(inputs, ko, samples)?;
            if let Some(x) = &opts.initial_state {
                est.set_initial_state(x);
            }
            Box::new(est)
        }
    })
}

/// Per channel: the noise std (the setup's `noise_std`, else estimated from the data's
/// high-order differences, see [`crate::estimate::tuning::channel_noise_std`]) and whether
/// it was estimated.
pub fn channel_noise(setup: &Setup, data: &TestData) -> (Vec<f64>, Vec<bool>) {
    let mut col = Vec::with_capacity(data.len());
    setup
        .sensors
        .iter()
        .enumerate()
        .map(|(k, s)| match s.noise_std {
            Some(sd) => (sd, false),
            None => {
                col.clear();
                col.extend(
                    data.response
                        .iter()
                        .map(|y| y.get(k).copied().unwrap_or(0.0)),
                );
                (crate::estimate::tuning::channel_noise_std(&col), true)
            }
        })
        .unzip()
}

/// Absolute floors of the stick band: 1 pm and 1 nm/s, below anything a transducer
/// resolves, so a joint stuck from the first sample is recognised before any peak is known.
const STICK_FLOOR_U: f64 = 1e-12;
const STICK_FLOOR_V: f64 = 1e-9;

/// The online Step V accumulator: one recursive least-squares fit per connection, with the
/// stuck-sample exclusion.
pub struct ParameterAccumulator {
    fits: Vec<RecursiveLeastSquares>,
    blocks: Vec<Vec<Basis>>,
    labels: Vec<Vec<String>>,
    peak_d: Vec<f64>,
    peak_v: Vec<f64>,
    excluded: Vec<usize>,
    stick_band: f64,
    row: Vec<f64>,
    extra_d: Vec<f64>,
    extra_v: Vec<f64>,
    /// Per connection: the rows and targets pushed, when kept (for the HAC covariance).
    kept: Option<Vec<(Vec<f64>, Vec<f64>)>>,
}

impl ParameterAccumulator {
    pub fn new(setup: &Setup, stick_band: f64, forgetting: f64) -> Self {
        let blocks: Vec<Vec<Basis>> = setup.connections.iter().map(|c| c.basis.clone()).collect();
        let maxp = blocks.iter().map(|b| b.len()).max().unwrap_or(0);
        Self {
            fits: blocks
                .iter()
                .map(|b| RecursiveLeastSquares::new(b.len(), forgetting))
                .collect(),
            labels: setup
                .connections
                .iter()
                .map(|c| {
                    c.basis
                        .iter()
                        .map(|b| format!("{}.{}", c.name, b.label()))
                        .collect()
                })
                .collect(),
            peak_d: vec![0.0; blocks.len()],
            peak_v: vec![0.0; blocks.len()],
            excluded: vec![0; blocks.len()],
            blocks,
            stick_band,
            row: vec![0.0; maxp],
            extra_d: vec![0.0; setup.connections.len()],
            extra_v: vec![0.0; setup.connections.len()],
            kept: None,
        }
    }

    /// Keep every row (memory: (P+1) numbers per sample and connection) so `solve` can give
    /// standard errors that account for the rows' correlation in time. Batch passes only.
    pub fn keep_rows(&mut self) {
        self.kept = Some(vec![(Vec::new(), Vec::new()); self.blocks.len()]);
    }

    /// Widen connection `c`'s stuck band by absolute amounts (the estimator's uncertainty
    /// of δ and δ̇ times a factor).
    pub fn widen_band(&mut self, c: usize, d: f64, v: f64) {
        if c < self.extra_d.len() {
            self.extra_d[c] = if d.is_finite() { d.max(0.0) } else { 0.0 };
            self.extra_v[c] = if v.is_finite() { v.max(0.0) } else { 0.0 };
        }
    }

    /// Add one sample's estimate. No allocation.
    pub fn push(&mut self, out: &StepOutput) {
        self.push_parts(
            out.delta.as_slice(),
            out.delta_v.as_slice(),
            out.delta_a.as_slice(),
            out.force.as_slice(),
        );
    }

    /// [`push`](Self::push) from the parts of a step output: per connection the deformation
    /// `delta`, its rate and acceleration, and the connection force.
    pub fn push_parts(&mut self, delta: &[f64], delta_v: &[f64], delta_a: &[f64], force: &[f64]) {
        for (c, basis) in self.blocks.iter().enumerate() {
            let (d, dv, da) = (delta[c], delta_v[c], delta_a[c]);
            self.peak_d[c] = self.peak_d[c].max(d.abs());
            self.peak_v[c] = self.peak_v[c].max(dv.abs());
            let stuck = basis.iter().any(|b| match b {
                Basis::SignV => {
                    dv.abs()
                        <= (self.stick_band * self.peak_v[c]).max(STICK_FLOOR_V) + self.extra_v[c]
                }
                Basis::SignU => {
                    d.abs()
                        <= (self.stick_band * self.peak_d[c]).max(STICK_FLOOR_U) + self.extra_d[c]
                }
                _ => false,
            });
            if stuck {
                self.excluded[c] += 1;
                continue;
            }
            let row = &mut self.row[..basis.len()];
            for (x, b) in row.iter_mut().zip(basis) {
                *x = b.eval(d, dv, da);
            }
            self.fits[c].push(row, force[c]);
            if let Some(k) = self.kept.as_mut() {
                k[c].0.extend_from_slice(row);
                k[c].1.push(force[c]);
            }
        }
    }

    pub fn solve(&self, max_condition: f64) -> Vec<Result<Fit, RefitError>> {
        self.fits
            .iter()
            .zip(&self.labels)
            .map(|(f, l)| f.solve(l, max_condition))
            .collect()
    }

    /// Newey–West standard errors and lag window of connection `c`'s fit (rows kept).
    pub fn hac(&self, c: usize, values: &[f64]) -> Option<(Vec<f64>, usize)> {
        let (rows, y) = self.kept.as_ref()?.get(c)?;
        crate::estimate::refit::hac_covariance(rows, y, values)
    }

    pub fn rows(&self) -> Vec<usize> {
        self.fits.iter().map(|f| f.rows()).collect()
    }

    pub fn excluded(&self) -> Vec<usize> {
        self.excluded.clone()
    }
}

/// The initial state `(u; u̇; ü)` (offsets from rest) of a record that starts in motion:
/// two filter passes with the setup's initial law and the untuned random walk, each started
/// from the last one's initial-state fit (`KalmanEstimator::initial_state_fit`; two,
/// because the friction's switching makes the fit only nearly linear). The passes refine
/// it further.
fn estimate_initial_state(
    setup: &Setup,
    model: &Model,
    params: &[f64],
    opts: &IdentifyOptions,
    sigma: &[f64],
    data: &TestData,
) -> Result<Vec<f64>, IdentifyError> {
    let mut x = vec![0.0; 3 * model.n()];
    let mut est = build_estimator(setup, model, params, opts, sigma, data.len())?;
    let mut out = StepOutput::new(setup.connections.len());
    for _ in 0..2 {
        est.set_initial_state(&x);
        est.start(data.samples[0], &data.excitation[0]);
        for i in 1..data.len() {
            est.step(
                data.samples[i],
                &data.excitation[i],
                &data.response[i],
                &mut out,
            )?;
        }
        let Some(correction) = est.initial_state_fit() else {
            break;
        };
        for (a, d) in x.iter_mut().zip(&correction) {
            *a += d;
        }
    }
    Ok(x)
}

/// Largest |first sample| / noise std of a displacement or velocity channel for a record
/// that starts at rest (6: a false alarm on a record at rest has probability ~2e-9 per
/// channel with Gaussian noise).
pub const MAX_START_NOISE_RATIO: f64 = 6.0;

/// Standard normal quantile of the joint at-rest test's false-alarm probability (2e-9, the
/// same as one channel's [`MAX_START_NOISE_RATIO`] two-sided).
const START_TEST_Z: f64 = 5.877_9;

/// Upper quantile of χ² with `k` degrees of freedom at the normal quantile `z`
/// (Wilson–Hilferty; on the safe side — larger than the exact quantile — for small `k`:
/// 45 against 36 for one degree at `z` = 5.88, 6 % high at 6 degrees, 3 % at 12, 1.5 % at 24).
pub(crate) fn chi2_upper_quantile(k: usize, z: f64) -> f64 {
    let k = k.max(1) as f64;
    let a = 2.0 / (9.0 * k);
    k * (1.0 - a + z * a.sqrt()).powi(3)
}

/// Refuse a record whose displacement or velocity channels are not at rest at its first
/// sample: the Kalman and 1989 pipelines start the model at rest. Two tests, each with a
/// false-alarm probability of about 2e-9 on a record at rest with Gaussian noise: one
/// channel beyond [`MAX_START_NOISE_RATIO`] noise std, or all of them together, Σ(value /
/// noise std)² beyond the χ² quantile. The joint test is the one that sees motion at
/// 10 % noise: a cut record's first sample read 5.6 noise std at most on every channel
/// (velocity noise is over-estimated 1.6–2× by the difference estimate on such data) but
/// Σ² = 115 against a limit of 68 (ACCURACY.md, "Motion seen by all channels together").
/// Measured before any test (ACCURACY.md, "Records that start in motion"): the shipped
/// friction setup on 2,000-sample records cut from the middle of a test, 8 seeds: coverage
/// 41 %, friction up to 3.3 million standard errors off. Acceleration channels are not
/// checked (at rest they read the excitation's acceleration).
fn starts_at_rest(setup: &Setup, data: &TestData, sigma: &[f64]) -> Result<(), IdentifyError> {
    let (Some(first), Some(&sample)) = (data.response.first(), data.samples.first()) else {
        return Ok(());
    };
    let mut channels = 0usize;
    let mut chi2 = 0.0;
    // The channel that reads farthest from rest: (sensor, value, sigma, ratio).
    let mut largest: Option<(&str, f64, f64, f64)> = None;
    for ((sensor, &value), &s) in setup.sensors.iter().zip(first).zip(sigma) {
        if !matches!(sensor.quantity, Quantity::Displacement | Quantity::Velocity) {
            continue;
        }
        // Noise-free data (std 0) at rest read exactly 0.
        let ratio = if s > 0.0 {
            value.abs() / s
        } else if value != 0.0 {
            f64::INFINITY
        } else {
            0.0
        };
        channels += 1;
        chi2 += ratio * ratio;
        if largest.is_none_or(|l| ratio > l.3) {
            largest = Some((&sensor.name, value, s, ratio));
        }
    }
    let Some((sensor, value, sigma, ratio)) = largest else {
        return Ok(());
    };
    let chi2_limit = chi2_upper_quantile(channels, START_TEST_Z);
    if ratio > MAX_START_NOISE_RATIO || chi2 > chi2_limit {
        return Err(IdentifyError::NotAtRest {
            sensor: sensor.to_string(),
            sample,
            value,
            sigma,
            ratio,
            chi2,
            channels,
            chi2_limit,
        });
    }
    Ok(())
}

/// Fewest samples [`identify`] accepts ([`IdentifyError::TooShort`] below).
pub const MIN_SAMPLES: usize = 3;

/// Run the identification (Steps I–VI) over recorded data.
///
/// `on_pass` is told about each finished pass (for progress and per-pass outputs);
/// `on_sample` receives `(pass, record)` for every sample of every pass.
///
/// A record whose start in motion only the prediction error's innovations show (its first
/// sample reads like rest) is identified twice: the second run treats it as in motion from
/// the start (initial-state fit in the passes, the start state refitted in every
/// prediction-error run), and its passes are reported again. Why not carry on from the
/// first run's passes: they ran from rest, and the joint damper took the start's free
/// vibration (cut records at 100 % noise: `v` 19 % coverage, 12 errors off; refined from
/// those passes with the start state fitted, still 75 % and 6.4; ACCURACY.md).
pub fn identify(
    setup: &Setup,
    data: &TestData,
    opts: &IdentifyOptions,
    truth: Option<&[f64]>,
    on_pass: &mut dyn FnMut(&PassReport),
    on_sample: &mut dyn FnMut(usize, &StepOutput),
) -> Result<Identification, IdentifyError> {
    let first = identify_once(setup, data, opts, truth, on_pass, on_sample)?;
    let mut result = match first.motion_in_record {
        Some(m) if opts.start_motion.is_none() && opts.initial_state.is_none() => {
            let again = IdentifyOptions {
                start_motion: Some(m),
                ..opts.clone()
            };
            identify_once(setup, data, &again, truth, on_pass, on_sample).map_err(|e| match e {
                // A law the run again cannot handle in motion: that refusal alone.
                IdentifyError::MotionInRecord { .. } => e,
                e => IdentifyError::MotionInRecordRefused {
                    reduction: m.reduction,
                    limit: m.limit,
                    substeps: m.substeps,
                    then: Box::new(e),
                },
            })?
        }
        _ => first,
    };
    // The free run's answer: its own parametric bootstrap, when asked for (see `bootstrap`).
    bootstrap::free_run_bootstrap(setup, data, opts, &mut result);
    // `--bootstrap` belongs to the refinements (the prediction error's, the free run's):
    // said rather than ignored without a word.
    let bootstrapped = result
        .output_error
        .as_ref()
        .is_some_and(|o| o.prediction_error.is_some() || o.bootstrap.is_some());
    if !has_sign_u_basis(setup) && !bootstrapped && opts.bootstrap.is_some_and(|n| n > 0) {
        result.notes.push(
            "`--bootstrap` not run: the parametric bootstrap belongs to the output-error refinements (the prediction error's, of `sign(u)` laws and of friction laws on records in motion, and the free run's), which did not give this answer; its errors are its estimator's own".into(),
        );
    }
    Ok(result)
}

fn identify_once(
    setup: &Setup,
    data: &TestData,
    opts: &IdentifyOptions,
    truth: Option<&[f64]>,
    on_pass: &mut dyn FnMut(&PassReport),
    on_sample: &mut dyn FnMut(usize, &StepOutput),
) -> Result<Identification, IdentifyError> {
    if data.len() < MIN_SAMPLES {
        return Err(IdentifyError::TooShort(data.len()));
    }
    let model = Model::for_identification(setup)?;
    let mut fallback_note = None;
    if opts.estimator == EstimatorKind::Ml {
        let ml =
            identify_by_maximum_likelihood(setup, &model, data, opts, truth, on_pass, on_sample);
        match ml {
            Err(IdentifyError::MaximumLikelihood(e))
                if opts.estimator_by_default
                    && matches!(
                        e,
                        crate::estimate::ml::MlError::NeedsDense { .. }
                            | crate::estimate::ml::MlError::TooShort { .. }
                    ) =>
            {
                fallback_note = Some(format!(
                    "the default estimator for this law is maximum likelihood, which cannot run here ({e}); the Kalman pipeline ran instead"
                ));
            }
            other => return other,
        }
    }
    let mut opts = if fallback_note.is_some() {
        IdentifyOptions {
            estimator: EstimatorKind::Kalman,
            ..opts.clone()
        }
    } else {
        opts.clone()
    };
    let by_output_error = opts.output_error && model.has_dense() && has_spring_basis(setup);
    check_observability_with(setup, &model, &opts, by_output_error)?;
    let (sigma, estimated) = channel_noise(setup, data);
    let prior = opts.prior.as_ref().and_then(|p| p.for_setup(setup));
    let params = prior.map_or_else(|| setup.initial_params(), |p| p.values.clone());
    let mut motion_note = None;
    // What the data show first (the channel and the figure); a window cut from a longer
    // record is in motion even when its first sample cannot show it.
    let motion = match (
        starts_at_rest(setup, data, &sigma),
        opts.starts_mid_record,
        opts.start_motion,
    ) {
        (Err(e), _, _) => Err(e),
        (Ok(()), Some(sample), _) => Err(IdentifyError::MidRecord { sample }),
        (Ok(()), None, _) if opts.in_motion => Err(IdentifyError::SaidInMotion {
            sample: data.samples.first().copied().unwrap_or(0),
        }),
        (Ok(()), None, Some(m)) => Err(IdentifyError::MotionInRecord {
            reduction: m.reduction,
            limit: m.limit,
            rank: m.rank,
            level: m.level,
            substeps: m.substeps,
        }),
        (Ok(()), None, None) => Ok(()),
    };
    if motion.is_ok()
        && !setup
            .sensors
            .iter()
            .any(|s| matches!(s.quantity, Quantity::Displacement | Quantity::Velocity))
    {
        motion_note = Some(
            "accelerometers only: whether the record starts at rest cannot be checked from its first sample; it is identified as starting at rest (a record cut from a test in motion would be biased; maximum likelihood, `--estimator ml`, estimates the initial state)".to_string(),
        );
    }
    if let Err(refusal) = motion {
        // The Kalman passes estimate the initial state, and so does the prediction-error
        // refinement that follows them for friction laws on a record in motion (see
        // `finish_with_output_error`); the free-run output error and the 1989 estimator
        // start at rest.
        let handled = opts.estimator == EstimatorKind::Kalman
            && model.has_dense()
            && (has_sign_basis(setup) || !opts.output_error);
        if !handled {
            return Err(refusal);
        }
        let x0 = estimate_initial_state(setup, &model, &params, &opts, &sigma, data)?;
        motion_note = Some(format!(
            "{refusal_short}: the initial state was estimated (the Kalman filter's initial-state fit, refined after every pass; the prediction-error refinement starts from it)",
            refusal_short = match &refusal {
                IdentifyError::NotAtRest {
                    sensor,
                    value,
                    ratio,
                    chi2,
                    chi2_limit,
                    channels,
                    ..
                } => format!(
                    "the record starts in motion (at its first sample Σ(value/noise std)² = {chi2:.1} over {channels} displacement and velocity channels, limit {chi2_limit:.1}; `{sensor}` reads {value:.4e}, {ratio:.1}× its noise std)"
                ),
                IdentifyError::MidRecord { sample } => {
                    format!("the window starts mid-record (sample {sample}), in motion")
                }
                IdentifyError::SaidInMotion { sample } => {
                    format!(
                        "the record is said to start in motion (`--in-motion`; first sample {sample})"
                    )
                }
                IdentifyError::MotionInRecord {
                    reduction,
                    limit,
                    rank,
                    level,
                    substeps,
                } => {
                    format!(
                        "the record starts in motion although its first sample reads like rest: a start state refitted to the innovations of the prediction error's observer ({} model sub-steps, run from rest at its refined values) removed {:.1} from their whitened cost, beyond the limit {:.1} (χ² of its {} degrees of freedom at 1e-3, × {:.2}, that run's normalised cost), so the identification was run again with the start state estimated (the passes are reported twice); a model that misfits the structure's free vibration can pass this test too, which is why the prediction error's test, and one asked by residuals that are not white, is repeated at the likeliest model sub-steps before it is called motion (ACCURACY.md, \"A start in motion seen by the whole record\", thirty-fourth session)",
                        substeps, reduction, limit, rank, level
                    )
                }
                other => other.to_string(),
            }
        ));
        opts.initial_state = Some(x0);
    }
    let mut result = Identification::started(opts.estimator.to_string());
    result.notes.extend(fallback_note);
    result.notes.extend(motion_note);
    if setup.estimator.reduce_modes.is_some() {
        // Say so: the reduction's bias is not in the standard errors.
        let kept = crate::model::reduce::boundary_dofs(&model).len();
        result.notes.push(format!(
            "identified on a Craig–Bampton reduction of the model: {kept} physical DOFs + {} fixed-interface modes (`reduce_modes`); the truncated modes' bias is not in the standard errors",
            model.n() - kept
        ));
    }
    if opts.estimator == EstimatorKind::Kalman && acceleration_only(&model) {
        return identify_acceleration_only(
            setup, &model, data, &opts, truth, &sigma, &estimated, result,
        );
    }
    let mut state = PassState {
        params,
        frozen: None,
        last_tuning: None,
        tunings: 0,
    };
    // A long record whose answer the prediction error gives: the passes converge on its
    // first samples, and one pass over the whole of it starts the refinement
    // ([`PASS_PREFIX_SAMPLES`]).
    let mut first_pass = 1;
    let mut prefix_passes = None;
    if let Some(prefix) = pass_prefix(setup, data, &opts) {
        let (mut trial, mut trial_opts, mut trial_state) =
            (result.clone(), opts.clone(), state.clone());
        let mut reports: Vec<PassReport> = Vec::new();
        let end = run_passes(
            setup,
            &model,
            &prefix,
            &mut trial_opts,
            (&sigma, &estimated),
            truth,
            1,
            opts.passes,
            &mut trial_state,
            &mut trial,
            &mut |r| reports.push(r.clone()),
            &mut |_, _| {},
        );
        // Only a converged prefix is a start; otherwise every pass runs over the whole
        // record from the setup's values, as on a short record (nothing of the trial kept).
        if matches!(end, PassLoopEnd::Converged) {
            reports.iter().for_each(&mut *on_pass);
            first_pass = trial.passes.len() + 1;
            prefix_passes = Some(std::mem::take(&mut trial.stop_reason));
            (result, opts, state) = (trial, trial_opts, trial_state);
            result.converged = false;
            result.notes.push(format!(
                "long record: pass(es) 1–{} ran on its first {PASS_PREFIX_SAMPLES} samples (the refinement's start needs no more), the passes from {first_pass} on over the whole record",
                first_pass - 1
            ));
        }
    }
    let whole_limit = if prefix_passes.is_some() {
        1
    } else {
        opts.passes
    };
    let end = run_passes(
        setup,
        &model,
        data,
        &mut opts,
        (&sigma, &estimated),
        truth,
        first_pass,
        whole_limit,
        &mut state,
        &mut result,
        on_pass,
        on_sample,
    );
    if let PassLoopEnd::Refused(e) = end {
        // The scan's free-run output error starts at rest: not for a record in motion.
        if by_output_error
            && opts.estimator == EstimatorKind::Kalman
            && opts.initial_state.is_none()
            && scan_fallback_applies(setup, &e)
        {
            return identify_from_scan(
                setup,
                &model,
                data,
                &opts,
                truth,
                &sigma,
                &estimated,
                result,
                ScanReason::ResidualForceRefused(e),
            );
        }
        return Err(e);
    }
    // The state to go on from if the refinement does not give the answer after all.
    let mut unfinished = None;
    if let (Some(on_prefix), PassLoopEnd::Limit) = (&prefix_passes, &end) {
        unfinished = Some((result.clone(), opts.clone(), state.clone()));
        let change = result
            .passes
            .last()
            .and_then(|p| p.max_change_std_errors)
            .unwrap_or(f64::NAN);
        result.converged = true;
        result.stop_reason = format!(
            "{on_prefix} on the record's first {PASS_PREFIX_SAMPLES} samples; pass {first_pass} ran over the whole record from their answer (moving it by up to {change:.2} of its standard errors) to start the prediction-error refinement, which descends on the same first samples"
        );
    }
    // The output-error stage starts from the last finished pass, also after a failed one.
    result.initial_state = opts.initial_state.clone();
    finish_with_output_error(setup, &model, data, &opts, &sigma, &mut result);
    let by_prediction_error = result
        .output_error
        .as_ref()
        .is_some_and(|r| r.prediction_error.is_some());
    if let Some((mut again, mut again_opts, mut again_state)) = unfinished
        && !by_prediction_error
        && result.motion_in_record.is_none()
    {
        // The passes' answer is the answer (or the free run's start): converge it over the
        // whole record as on a short one, and finish from there.
        let end = run_passes(
            setup,
            &model,
            data,
            &mut again_opts,
            (&sigma, &estimated),
            truth,
            first_pass + 1,
            opts.passes.saturating_sub(1),
            &mut again_state,
            &mut again,
            on_pass,
            on_sample,
        );
        if let PassLoopEnd::Refused(e) = end {
            return Err(e);
        }
        (result, opts) = (again, again_opts);
        result.initial_state = opts.initial_state.clone();
        finish_with_output_error(setup, &model, data, &opts, &sigma, &mut result);
    }
    // A friction law whose refinement could not start because the passes' answer cannot
    // even be simulated: that answer is rejected by the data, and the scan gives the start
    // instead, as when the residual-force stage is refused.
    if by_output_error
        && opts.estimator == EstimatorKind::Kalman
        && opts.initial_state.is_none()
        && result.motion_in_record.is_none()
        && has_sign_basis(setup)
        && let Some(e) = start_rejected(&result)
    {
        // The stage's own notes of that failure: the refusal below says it.
        result.notes.retain(|n| {
            !(n.starts_with("output-error refinement not run") || n.starts_with("Cramér–Rao bound"))
        });
        return identify_from_scan(
            setup,
            &model,
            data,
            &opts,
            truth,
            &sigma,
            &estimated,
            result,
            ScanReason::ResidualForceRefused(e),
        );
    }
    if has_sign_basis(setup)
        && let Some(sub) = result.output_error.as_ref().map(|r| r.substeps)
    {
        let t0 = std::time::Instant::now();
        let fitted = as_fitted(data, &result);
        restate_final_errors(setup, &model, &fitted, &sigma, &estimated, sub, &mut result);
        crate::par::phase("restated errors", t0);
    }
    // (Also when a later stage failed: the passes' own stop is reported beside the failure.)
    if !result.converged && result.stop_reason.is_empty() {
        let change = result.passes.last().and_then(|p| p.max_change_std_errors);
        result.stop_reason = match change {
            Some(c) => format!(
                "not converged: reached the limit of {} passes (last change {c:.3} standard errors)",
                opts.passes
            ),
            None => format!(
                "not converged: reached the limit of {} pass(es), too few to measure a change (convergence needs at least 2)",
                opts.passes
            ),
        };
    }
    Ok(result)
}

/// What the residual-force passes carry from one to the next (and from a long record's
/// prefix to the whole of it).
#[derive(Clone)]
struct PassState {
    /// The parameters the next pass runs with.
    params: Vec<f64>,
    /// The Kalman tuning once it is frozen.
    frozen: Option<KalmanTuning>,
    /// The last tuning made (a re-tune starts its search there, see [`tune_kalman`]).
    last_tuning: Option<KalmanTuning>,
    /// Tunings so far.
    tunings: usize,
}

/// How a run of passes ended.
enum PassLoopEnd {
    /// Every parameter moved less than the tolerance.
    Converged,
    /// The pass limit was reached.
    Limit,
    /// A pass failed after sound ones: `result.failure` or `stop_reason` says why.
    Stopped,
    /// No pass to answer with (or the deferred refusal of an undetermined deformation).
    Refused(IdentifyError),
}

/// Samples a long record's passes converge on when the prediction error gives its answer:
/// the Kalman tuning's prefix.
///
/// Why: the passes are a fixed-point iteration, each step a filter run over the record
/// (~0.25 s at 100,000 samples), 5–7 steps to 0.1 of their errors; when a `sign(u)` law
/// is refined by prediction error their answer is only the refinement's start, and that
/// refinement descends on the same first 10,000 samples
/// ([`crate::estimate::prediction_error::DESCENT_PREFIX_SAMPLES`]) — its answer depends on
/// where in its basin it starts only through the observer force tuned there (measured: up
/// to 0.19 errors on 100,000-sample records, ACCURACY.md). So on a record longer than
/// twice this the passes converge on the prefix (a tenth of the cost each), one pass runs
/// over the whole record from their answer (the per-sample residual forces, the track and
/// the start the refinement gets), and the refinement follows. Measured on a
/// 100,000-sample record: passes 1.7 → 0.8 s (BENCHMARKS.md, twenty-third session).
/// Should the refinement not give the answer after all (refused, misfit, not run),
/// the whole record's passes go on to their convergence and the refinement stage runs
/// again from it, as on a short record.
pub const PASS_PREFIX_SAMPLES: usize = TUNE_SAMPLES;

/// A long record's prefix for the Kalman passes ([`PASS_PREFIX_SAMPLES`]), if it has one.
fn pass_prefix(setup: &Setup, data: &TestData, opts: &IdentifyOptions) -> Option<TestData> {
    let refined =
        opts.estimator == EstimatorKind::Kalman && opts.output_error && has_sign_u_basis(setup);
    if !refined || data.len() <= 2 * PASS_PREFIX_SAMPLES {
        return None;
    }
    data.prefix(PASS_PREFIX_SAMPLES)
}

/// The residual-force passes from pass `first_pass` on, at most `limit` of them, each
/// running with the last one's answer (Aitken-extrapolated once the tuning is frozen),
/// until every parameter moves less than the tolerance. The reports go to `result`.
#[allow(clippy::too_many_arguments)]
fn run_passes(
    setup: &Setup,
    model: &Model,
    data: &TestData,
    opts: &mut IdentifyOptions,
    noise: (&[f64], &[bool]),
    truth: Option<&[f64]>,
    first_pass: usize,
    limit: usize,
    state: &mut PassState,
    result: &mut Identification,
    on_pass: &mut dyn FnMut(&PassReport),
    on_sample: &mut dyn FnMut(usize, &StepOutput),
) -> PassLoopEnd {
    let (sigma, estimated) = noise;
    let mut plain_streak = 0usize;
    let mut prev_residual: Option<Vec<f64>> = None;
    // The track and the start state that go with the pass before the last (restored when
    // the last is discarded, see [`discard_pass_that_diverged`]).
    let mut track_before: Option<Track> = None;
    let mut initial_before = opts.initial_state.clone();
    for pass in first_pass..first_pass + limit {
        let t0 = std::time::Instant::now();
        let outcome = run_pass(
            setup,
            model,
            &state.params,
            data,
            opts,
            sigma,
            estimated,
            pass,
            truth,
            state.frozen.as_ref(),
            state.last_tuning.as_ref(),
            &mut |o| on_sample(pass, o),
        );
        crate::par::phase("pass (with any tuning)", t0);
        let report = match outcome {
            Ok((r, track, tuned, initial_fit)) => {
                track_before = result.track.replace(track);
                initial_before = opts.initial_state.clone();
                if let (Some(correction), Some(x)) = (initial_fit, opts.initial_state.as_mut()) {
                    for (a, d) in x.iter_mut().zip(&correction) {
                        *a += d;
                    }
                }
                if state.frozen.is_none() && tuned.is_some() {
                    state.tunings += 1;
                    state.last_tuning.clone_from(&tuned);
                    let settled = result
                        .passes
                        .last()
                        .map(|prev: &PassReport| {
                            r.parameters.iter().zip(&prev.parameters).all(|(a, b)| {
                                (a.value - b.value).abs()
                                    <= opts.retune_above_std_errors * a.std_error
                            })
                        })
                        .unwrap_or(false);
                    let limit = if opts.output_error {
                        opts.max_tunings_refined
                    } else {
                        opts.max_tunings
                    };
                    if settled || state.tunings >= limit {
                        state.frozen = tuned;
                    }
                }
                r
            }
            Err(e) => {
                let discarded = discard_pass_that_diverged(result, &state.params, &e, pass);
                if let Some(note) = &discarded {
                    result.track = track_before.take();
                    opts.initial_state = initial_before.clone();
                    result.notes.push(note.clone());
                }
                // No partial result from an undetermined deformation after a provisional
                // first pass that was undetermined too: that is the refusal it deferred.
                let deferred = matches!(e, IdentifyError::Undetermined { .. })
                    && result.passes.len() == 1
                    && result.passes[0].diagnostics.tuning.iter().any(|(k, v)| {
                        k.starts_with("delta_uncertainty_ratio") && *v > MAX_DEFORMATION_UNCERTAINTY
                    });
                if result.passes.is_empty() || deferred {
                    return PassLoopEnd::Refused(e);
                }
                // A failure caused by a pass that blew up is that pass's: the passes stop at
                // the sound one before it, not converged, and the refinement goes on from it.
                if let (Some(note), Some(sound)) = (&discarded, result.passes.last()) {
                    result.stop_reason = format!("stopped after pass {}: {note}", sound.pass);
                    return PassLoopEnd::Stopped;
                }
                result.failure = Some(e.to_string());
                result.stop_reason = format!("pass {pass} failed: {e}");
                return PassLoopEnd::Stopped;
            }
        };
        let mut report = report;
        let mut all_converged = false;
        // Change of this pass: output against the parameters it ran with (the fixed-point
        // residual of the pass map), in standard errors.
        let fixed_map = opts.estimator != EstimatorKind::Kalman
            || opts.force_walk_std.is_some()
            || report
                .diagnostics
                .tuning
                .iter()
                .any(|(k, _)| k == "tuning_frozen");
        let residual: Vec<f64> = report
            .parameters
            .iter()
            .zip(&state.params)
            .map(|(a, b)| (a.value - b) / a.std_error.max(f64::MIN_POSITIVE))
            .collect();
        if pass >= 2 {
            let mut max_se: f64 = 0.0;
            let mut max_rel: f64 = 0.0;
            all_converged = true;
            for ((a, b), (col, frms)) in report
                .parameters
                .iter()
                .zip(&state.params)
                .zip(&report.force_scales)
            {
                let d = (a.value - b).abs();
                let in_se = d / a.std_error.max(f64::MIN_POSITIVE);
                let rel = d * col / frms.max(f64::MIN_POSITIVE);
                max_se = max_se.max(in_se);
                max_rel = max_rel.max(rel);
                if !(in_se <= opts.tolerance_std_errors || rel <= opts.tolerance_relative) {
                    all_converged = false;
                }
            }
            report.max_change_std_errors = Some(max_se);
            report.max_change_force_relative = Some(max_rel);
        }
        // Aitken extrapolation of the linearly converging pass map: with the tuning frozen
        // the passes are a fixed-point iteration p ← G(p) whose residual shrinks by a
        // steady ratio r per pass (≈ 0.65 measured on the two-beam friction recording);
        // after two plain passes jump to the limit `G(p) + r/(1−r)·(G(p) − p)`.
        let mut next: Vec<f64> = report.parameters.iter().map(|p| p.value).collect();
        let norm = |x: &[f64]| x.iter().map(|v| v * v).sum::<f64>().sqrt();
        if fixed_map {
            plain_streak += 1;
        } else {
            plain_streak = 0;
        }
        if plain_streak >= 2
            && !all_converged
            && let Some(prev) = &prev_residual
        {
            let r = norm(&residual) / norm(prev).max(f64::MIN_POSITIVE);
            if r > 0.05 && r < 0.95 {
                let w = r / (1.0 - r);
                for (x, (a, b)) in next
                    .iter_mut()
                    .zip(report.parameters.iter().zip(&state.params))
                {
                    *x += w * (a.value - b);
                }
                report.diagnostics.tuning.push(("aitken_ratio".into(), r));
                plain_streak = 0;
            }
        }
        prev_residual = Some(residual);
        on_pass(&report);
        state.params = next;
        result.passes.push(report);
        let (rel_ok, se_ok) = (all_converged, all_converged);
        if rel_ok || se_ok {
            result.converged = true;
            result.stop_reason = format!(
                "converged after {pass} passes: every parameter moved less than {} standard errors or changed the fitted force by less than {:.0e} of its RMS",
                opts.tolerance_std_errors, opts.tolerance_relative
            );
            return PassLoopEnd::Converged;
        }
    }
    PassLoopEnd::Limit
}

/// A pass whose model broke while it ran with the last pass's own answer — it diverged,
/// its integrator could not step, its stations no longer saw the residual force
/// (rank(S) = 0; the same stations did in pass 1), or its filter's innovation covariance
/// was no longer positive definite (until the thirty-first session reported as rank(S) =
/// 0) — fails because of that answer, so that
/// answer is not one: it is taken off the passes (and returned as a note), and the
/// identification goes on from the pass before it (its parameters, track and start state).
/// Why: on noise-free Coulomb data of the model's own discretisation (test
/// `noise_free_own_discretisation_is_recovered_exactly`) pass 4 blew up to `sign(v)` 3e99
/// and `u` −1.4e7 ± 6.6e4 N/m, pass 5 found rank(S) = 0 with them, and pass 4's values
/// were the answer beside the failure — seen with two tunings (the warm re-tuning of the
/// fourteenth session, Brent's refinement of the fifteenth). A pass that ran with
/// extrapolated parameters (the Aitken step) keeps the last pass: its own answer never
/// ran. Other failures (an undetermined deformation, a singular fit) say nothing against
/// the parameters they ran with.
fn discard_pass_that_diverged(
    result: &mut Identification,
    ran_with: &[f64],
    e: &IdentifyError,
    pass: usize,
) -> Option<String> {
    let diverged = matches!(
        e,
        IdentifyError::Estimate(
            EstimateError::Diverged { .. }
                | EstimateError::Overflowed { .. }
                | EstimateError::RankDeficientSensitivity { .. }
                | EstimateError::InnovationCovariance { .. }
                | EstimateError::Integrate(_)
        )
    );
    let last = result.passes.last()?;
    let its_own = last.parameters.len() == ran_with.len()
        && last
            .parameters
            .iter()
            .zip(ran_with)
            .all(|(a, b)| a.value == *b);
    if !(diverged && its_own) {
        return None;
    }
    let dropped = result.passes.pop()?;
    let values: Vec<String> = dropped
        .parameters
        .iter()
        .map(|p| format!("{} {} {:.4e}", p.connection, p.basis, p.value))
        .collect();
    Some(format!(
        "pass {} discarded: pass {pass}, run with its parameters ({}), failed ({e}); {}",
        dropped.pass,
        values.join(", "),
        match result.passes.last() {
            Some(p) => format!("the answer goes on from pass {}", p.pass),
            None => "no pass before it".into(),
        }
    ))
}

/// What replaces an unusable prediction-error refinement: the free-run output error, or
/// nothing for a record in motion (the free run starts at rest).
fn fallback_words(opts: &IdentifyOptions) -> &'static str {
    if opts.initial_state.is_some() {
        "the free-run output error starts at rest and is not used on a record in motion"
    } else {
        "the free-run output error is used"
    }
}

/// The observer force, relative to the model's force scale, above which the prediction
/// error's answer has been measured off by more than its errors even after the noise-shift
/// correction.
const OBSERVER_BIAS_SCALE: f64 = 10.0;

/// A warning when the prediction error's observer force (N per sample) exceeds
/// [`OBSERVER_BIAS_SCALE`] × the model's force scale (`kalman::force_scale_of`). Why: at
/// such forces the observer feeds much of the measurement noise into the model state; the
/// shift that causes in the law's linear terms is removed to first order
/// (`estimate::prediction_error`, the noise shift), which on the two-beam model at 100 %
/// noise (50,000 samples, ACCURACY.md "The observer-force bias, corrected") brought the
/// joint damper `v` from +3.0…+39.7 standard errors off to +0.10…+0.61 on four records
/// (19–280× the scale), but left +3.3 on the fifth (480×, started from a scan), where the
/// first-order correction is not enough (+0.77 since 2026-11-28, its force tuned on the
/// first 10,000 samples: 184×). Below 10× (every 1 and 10 % record) the answers were within
/// 0.93 errors before the correction.
fn observer_force_warning(force_std: f64, force_scale: f64) -> Option<String> {
    let ratio = force_std / force_scale;
    (ratio > OBSERVER_BIAS_SCALE).then(|| {
        format!(
            "warning: the prediction error's observer force ({force_std:.3e} N per sample) is {ratio:.0}× the model's force scale (above {OBSERVER_BIAS_SCALE}×): the measurement noise it feeds into the model shifts the law's linear terms; that shift is removed to first order (the note above), which has been measured to leave up to 3.3 standard errors on the joint damper `v` at the largest forces (two-beam model, 100 % noise; ACCURACY.md, \"The observer-force bias, corrected\") — less noise (or a sensor nearer the joint) lowers the force"
        )
    })
}

/// What the prediction error's correction of the measurement noise's shift did (see
/// `estimate::prediction_error::PredictionErrorReport::noise_shift`): the largest shift in
/// standard errors of the answer, and which parameter.
fn noise_shift_note(keys: &[String], shift: &[f64], std_errors: &[f64]) -> String {
    let (j, errors) = shift
        .iter()
        .zip(std_errors)
        .map(|(s, e)| s.abs() / e)
        .enumerate()
        .filter(|(_, x)| x.is_finite())
        .fold((0, 0.0), |a, b| if b.1 > a.1 { b } else { a });
    format!(
        "the measurement noise's shift through the observer was removed from the answer (largest {errors:.2} standard errors, `{}`; estimated on a record of the noise alone through the same observer, its error added to the stated ones)",
        keys.get(j).map_or("", String::as_str)
    )
}

/// The refinement's scale per parameter from a start and its standard errors: the error,
/// at least 1e-6 of the value (1e-6 when neither is usable).
fn start_scales(values: &[f64], errors: &[f64]) -> Vec<f64> {
    values
        .iter()
        .zip(errors)
        .map(|(v, e)| {
            let s = e.abs().max(1e-6 * v.abs());
            if s.is_finite() && s > 0.0 { s } else { 1e-6 }
        })
        .collect()
}

/// [`IdentifyError::StartRejected`] when the free-run refinement could not run from the
/// last pass's answer (`Identification::refinement_not_run`), `None` otherwise.
fn start_rejected(result: &Identification) -> Option<IdentifyError> {
    let why = result.refinement_not_run.clone()?;
    let last = result.passes.last()?;
    Some(IdentifyError::StartRejected {
        answer: last
            .parameters
            .iter()
            .map(|p| format!("{}.{} = {:.4e}", p.connection, p.basis, p.value))
            .collect::<Vec<_>>()
            .join(", "),
        why,
    })
}

/// Of `answers` (every pass's values and errors), the index of the one whose free run with
/// the setup's model sub-steps costs least on the record; `None` when no free run succeeds.
fn likeliest_pass_answer(
    setup: &Setup,
    model: &Model,
    data: &TestData,
    sigma: &[f64],
    opts: &IdentifyOptions,
    answers: &[(Vec<f64>, Vec<f64>)],
) -> Option<usize> {
    let costs = crate::par::map(answers, |(values, _)| {
        data.free_run(setup, model, values, sigma, opts.substeps)
            .map_or(f64::INFINITY, |r| r.1)
    });
    costs
        .iter()
        .enumerate()
        .filter(|(_, c)| c.is_finite())
        .min_by(|a, b| a.1.total_cmp(b.1))
        .map(|(k, _)| k)
}

/// After the passes: the Cramér–Rao bound of every parameter and, when enabled, the
/// output-error refinement (see `estimate::output_error`). Either failing leaves the
/// residual-force estimate in place with a note.
fn finish_with_output_error(
    setup: &Setup,
    model: &Model,
    data: &TestData,
    opts: &IdentifyOptions,
    sigma: &[f64],
    result: &mut Identification,
) {
    use crate::estimate::output_error::{crlb, refine_global};
    if !(opts.crlb || opts.output_error) {
        return;
    }
    // Passes that did not converge: the first pass's answer is offered to the prediction
    // error as another start (`pem::PemStage::Refined`: the likelier is taken).
    let first_answer: Option<(Vec<f64>, Vec<f64>)> =
        (!result.converged && result.passes.len() >= 2 && opts.prior.is_none()).then(|| {
            result.passes[0]
                .parameters
                .iter()
                .map(|p| (p.value, p.std_error))
                .unzip()
        });
    // Every pass's answer, for a start when the free run cannot start from the last one's.
    let pass_answers: Vec<(Vec<f64>, Vec<f64>)> = if result.converged || opts.prior.is_some() {
        Vec::new()
    } else {
        result
            .passes
            .iter()
            .map(|pass| {
                pass.parameters
                    .iter()
                    .map(|p| (p.value, p.std_error))
                    .unzip()
            })
            .collect()
    };
    let Some(last) = result.passes.last_mut() else {
        return;
    };
    // Per parameter, the RMS of its basis function and of its connection's fitted force
    // over the record (the last pass's fit): the scale [`pem_undetermined`] judges an
    // error on.
    let force_scales = last.force_scales.clone();
    let contiguous = data
        .samples
        .windows(2)
        .all(|w| w[1] == w[0].wrapping_add(1));
    if !contiguous {
        result.notes.push(
            "output-error refinement and Cramér–Rao bound skipped: the samples are not contiguous (the prediction needs the excitation at every sample)".into(),
        );
        return;
    }
    // Each sensitivity is a full implicit simulation of the record; beyond this many
    // sub-steps per simulation the stage would dominate the replay time by far.
    // A linear law runs one composed map per sample (`simulate::law_is_linear`), whatever
    // the sub-steps.
    const MAX_SUBSTEPS: usize = 4_000_000;
    let linear = crate::simulate::law_is_linear(setup);
    if !linear && data.len().saturating_mul(opts.substeps) > MAX_SUBSTEPS {
        result.notes.push(format!(
            "output-error refinement and Cramér–Rao bound skipped: {} samples × {} sub-steps exceed {MAX_SUBSTEPS} simulated steps per run",
            data.len(),
            opts.substeps
        ));
        return;
    }
    let prior = opts.prior.as_ref().and_then(|p| p.for_setup(setup));
    let (mut values, errors): (Vec<f64>, Vec<f64>) = match prior {
        Some(p) => {
            result.notes.push(format!(
                "the refinement started from {} (not from this record's residual-force estimate)",
                p.source
            ));
            (p.values.clone(), p.std_errors.clone())
        }
        None => last
            .parameters
            .iter()
            .map(|p| (p.value, p.std_error))
            .unzip(),
    };
    let mut scales = start_scales(&values, &errors);
    let (exc, resp) = (&data.excitation, &data.response);
    // The prediction error gives the answer for laws with a `sign(u)` term, and for any
    // friction law on a record that starts in motion: it starts from the estimated initial
    // state, the free-run output error from rest. Why the latter (thirty-first session):
    // Coulomb `sign(v), u` records cut from a test in motion were refused until then
    // (ACCURACY.md, twenty-sixth session); refined by prediction error with the start state
    // fitted they are answered (ACCURACY.md, thirty-first session).
    let by_prediction_error =
        has_sign_u_basis(setup) || (opts.initial_state.is_some() && has_sign_basis(setup));
    let friction_term = if has_sign_u_basis(setup) {
        "sign(u)"
    } else {
        "sign(v)"
    };
    if opts.output_error && by_prediction_error {
        let t0 = std::time::Instant::now();
        let first_scales = first_answer.as_ref().map(|(v, e)| start_scales(v, e));
        let other_start = first_answer
            .as_ref()
            .zip(first_scales.as_ref())
            .map(|((v, _), s)| (v.as_slice(), s.as_slice()));
        let refined = match refine_by_prediction_error(
            setup,
            model,
            data,
            opts,
            sigma,
            (&values, &scales),
            other_start,
        ) {
            Ok(PemStage::Refined(r, raised, other_gain)) => {
                if let (Some(gain), Some((v, _)), Some(s)) =
                    (other_gain, first_answer.as_ref(), first_scales.as_ref())
                {
                    result.notes.push(format!(
                            "the passes did not converge: the prediction error started from the first pass's answer, likelier than the last pass's by {gain:.1} in log-likelihood (observer tuned at {raised} sub-steps)"
                        ));
                    (values, scales) = (v.clone(), s.clone());
                }
                Ok((*r, raised))
            }
            // `identify` runs again with the record treated as in motion.
            Ok(PemStage::InMotion(m)) => {
                result.motion_in_record = Some(m);
                return;
            }
            Err(e) => Err(e),
        };
        crate::par::phase("prediction error (all)", t0);
        match refined {
            Ok((r, raised)) if r.report.cost_end > PEM_MAX_COST => {
                result.notes.push(format!(
                    "prediction-error refinement not used: its model explains the outputs only to {:.1}× the noise variance with {raised} model sub-steps (more than {PEM_MAX_COST}); the observer would take the model error as process noise and the friction would be undetermined; {}",
                    r.report.cost_end,
                    fallback_words(opts)
                ));
            }
            Ok((r, _))
                if let Some(why) = pem_undetermined(setup, &r, &values, &scales, &force_scales) =>
            {
                result.notes.push(format!(
                    "prediction-error refinement not used: {why}; {}",
                    fallback_words(opts)
                ));
            }
            Ok((r, raised)) => {
                let keys = setup.param_keys();
                let flat: Vec<Basis> = setup.param_basis();
                for (j, b) in flat.iter().enumerate() {
                    if matches!(b, Basis::SignU | Basis::SignV) && r.values[j] <= 0.0 {
                        let test = match r.bound_likelihood_ratio.get(j).copied().flatten() {
                            _ if let Some(f) = r.report.frictionless_refit.as_ref()
                                && f.replaced.get(j).is_some_and(|x| *x > 0.0) =>
                            {
                                format!(
                                    "the answer refined from the start, {:.4e}, was less likely by {:.1} in log-likelihood (below)",
                                    f.replaced[j], f.gain
                                )
                            }
                            Some(lr) if lr < crate::estimate::prediction_error::FLAT_BOUND_LR => {
                                format!(
                                    "the innovations fit that level about as well (likelihood-ratio statistic {lr:.2} < {}): every value between is an answer, and every interval is widened to reach that point",
                                    crate::estimate::prediction_error::FLAT_BOUND_LR
                                )
                            }
                            Some(lr) => format!(
                                "the innovations reject that level (likelihood-ratio statistic {lr:.1})"
                            ),
                            None => match r.refined.get(j) {
                                Some(x) if *x > 0.0 => format!(
                                    "the descent ended at {x:.4e} (the noise's shift through the observer removed) and the bootstrap's mean shift removed from the answer took it to 0; its standard error includes it"
                                ),
                                _ => "its standard error is the start's".into(),
                            },
                        };
                        result.notes.push(format!(
                            "`{}` ended on its bound 0: no friction detected (the start gave {:.4e} ± {:.3e}); {test}",
                            keys[j], values[j], scales[j]
                        ));
                    }
                }
                if raised != opts.substeps {
                    result.notes.push(format!(
                        "prediction-error refinement with {raised} model sub-steps per sample instead of {}: the likeliest level of the tuned innovation likelihood, each level with its own observer force at the likelier of the start values and its own, reached by Gauss–Newton steps from them (every doubling up to 64 tried; the finest within Δχ² = 1 of the best kept, on a long record checked again on the whole of it)",
                        opts.substeps
                    ));
                }
                let rep = &r.report;
                if let Some(f) = rep.frictionless_refit.as_ref() {
                    result.notes.push(format!(
                        "the answer refined from the start ({}) was less likely than the law without friction's (its other terms fitted with every friction level at 0, under the same observer{}): the full law refined again from there ended likelier by {:.1} in log-likelihood and was taken; a descent stays in the basin it starts in, and the first answer's friction was another minimum",
                        flat.iter()
                            .zip(&keys)
                            .zip(&f.replaced)
                            .filter(|((b, _), _)| matches!(b, Basis::SignU | Basis::SignV))
                            .map(|((_, k), v)| format!("`{k}` {v:.4e}"))
                            .collect::<Vec<_>>()
                            .join(", "),
                        if data.len() > crate::identify::pem::FORCE_TUNE_SAMPLES {
                            format!(
                                ", fitted on the first {} samples and likelier on those and on the whole record",
                                crate::identify::pem::FORCE_TUNE_SAMPLES
                            )
                        } else {
                            String::new()
                        },
                        f.gain
                    ));
                }
                if let Some(gain) = rep.smooth_excitation_gain {
                    result.notes.push(format!(
                        "the excitation was taken as smooth between samples (each sample's mean that of a cubic through its neighbours, not of the straight line): its innovation likelihood was higher by {gain:.1} at the start values (over the first {} samples); a force that is piecewise linear between samples would be the other way",
                        data.len().min(crate::identify::pem::FORCE_TUNE_SAMPLES)
                    ));
                }
                match rep.bootstrap.as_ref() {
                    Some(b) if b.used * 2 >= b.replicates => {
                        // In errors of the answer as stated (after the bootstrap's floor).
                        let worst = |xs: &[f64]| {
                            xs.iter()
                                .zip(&r.std_errors)
                                .enumerate()
                                .map(|(j, (x, e))| (j, x.abs() / e))
                                .fold((0, 0.0f64), |a, b| if b.1 > a.1 { b } else { a })
                        };
                        let (js, shift) = worst(&b.shift);
                        let ratio = b
                            .spread
                            .iter()
                            .zip(&rep.sandwich_ratio)
                            .zip(&r.naive)
                            .map(|((sp, ratio), naive)| sp / (ratio * naive))
                            .fold(0.0f64, f64::max);
                        result.notes.push(format!(
                            "parametric bootstrap{}: {} of {} records simulated from the answer{} with this record's noise and refined again from the same start; the answer is corrected by their mean shift (largest {shift:.2} standard errors, `{}`) and every error is at least their spread (largest {ratio:.2}× the sandwich, as a t interval of {} replicates)",
                            match (opts.bootstrap, rep.periodic_excitation, rep.smooth_excitation_gain) {
                                (Some(_), _, _) => String::new(),
                                (None, Some((rho, lag)), _) => format!(
                                    " (automatic: the excitation repeats itself, autocorrelation {rho:.2} at a lag of {lag} samples, and under a repeating excitation the sandwich errors of a `sign(u)` law were measured to cover 58 % of the truths; `--bootstrap 0` switches it off)"
                                ),
                                (None, None, Some(_)) => " (automatic: the excitation is smooth between samples, as an impact's, where the sandwich errors of a `sign(u)` law were measured to cover 91 % of the truths; `--bootstrap 0` switches it off)".to_string(),
                                // The other occasions, in the rule's own words.
                                (None, None, None) => format!(
                                    " (automatic: the sandwich errors {}; `--bootstrap 0` switches it off)",
                                    pem::bootstrap_occasion(rep, pem::has_rate_friction(setup))
                                        .unwrap_or_default()
                                ),
                            },
                            b.used,
                            b.replicates,
                            if r.initial_state.is_some() {
                                " and its start state (the record starts in motion; each replicate refits its own)"
                            } else {
                                ""
                            },
                            keys[js],
                            b.used
                        ));
                    }
                    Some(b) => result.notes.push(match &b.failure {
                        Some(why) => format!("parametric bootstrap not run: {why}"),
                        None => format!(
                            "parametric bootstrap not used: only {} of {} replicate records could be identified",
                            b.used, b.replicates
                        ),
                    }),
                    // Not run: switched off, or no occasion (a record in motion is
                    // bootstrapped from its start state as one at rest is from rest).
                    None => {
                        if let Some(why) =
                            pem::bootstrap_occasion(rep, pem::has_rate_friction(setup))
                        {
                            result.notes.push(format!(
                                "parametric bootstrap switched off (`--bootstrap 0`): the errors of this `{friction_term}` law are the sandwich's, which {why} (ACCURACY.md)"
                            ))
                        }
                    }
                }
                result.notes.push(format!(
                    "`{friction_term}` friction: refined by prediction error (the output-error cost of this chaotic law is rough and its descent stops in local minima{}): observer process-noise force {:.4e} N per sample at the connections (tuned by the innovation likelihood of the start values), closed-loop spectral radius {:.6}, normalised innovation cost {:.4} → {:.4}; standard errors by the sandwich, the larger of its values over secants of ±1 and ±8 errors, {} (stated/naive {})",
                    if has_sign_u_basis(setup) {
                        ""
                    } else {
                        "; this record starts in motion, and the free run starts at rest"
                    },
                    rep.force_std,
                    rep.spectral_radius,
                    rep.cost_start,
                    rep.cost_end,
                    if rep.noise_driven_errors {
                        "its score covariance the measurement noise's through the observer (the levels the free run's residuals show, at most the channels' estimate)".to_string()
                    } else {
                        format!("its score covariance by a Newey–West lag window of {} samples", rep.hac_lag)
                    },
                    rep.sandwich_ratio
                        .iter()
                        .map(|x| format!("{x:.2}"))
                        .collect::<Vec<_>>()
                        .join(", ")
                ));
                if let Some(steps) = rep.whole_record_steps {
                    result.notes.push(format!(
                        "long record: the prediction error descended on its first {} samples, then took {steps} Gauss–Newton step(s) on the whole record from there (the one-step estimator; the last step, under {} errors, added without a run)",
                        crate::estimate::prediction_error::DESCENT_PREFIX_SAMPLES,
                        crate::estimate::prediction_error::ONE_STEP_TOL
                    ));
                }
                if let Some(shift) = rep.noise_shift.as_ref() {
                    result
                        .notes
                        .push(noise_shift_note(&keys, shift, &r.std_errors));
                }
                if let Some(why) = rep.noise_shift_failure.as_ref() {
                    result.notes.push(format!(
                        "warning: the measurement noise's shift through the observer could not be measured ({why}): the law's linear terms are uncorrected and can be biased by it (ACCURACY.md, \"The observer-force bias, corrected\")"
                    ));
                }
                if let Some(w) = observer_force_warning(
                    rep.force_std,
                    crate::estimate::kalman::force_scale_of(model),
                ) {
                    result.notes.push(w);
                }
                if r.initial_state.is_some() {
                    result.initial_state = r.initial_state.clone();
                }
                for (j, p) in last.parameters.iter_mut().enumerate() {
                    p.value = r.values[j];
                    p.std_error = r.std_errors[j];
                    p.ci95 = [p.value - 1.96 * p.std_error, p.value + 1.96 * p.std_error];
                    // No Cramér–Rao bound: the law's predictions are not smooth in its
                    // parameters (a switch a sub-step early flips the force), and the
                    // predictor's naive error is no bound (it overstates the error 3–4×
                    // on continuous data; ACCURACY.md).
                    p.crlb = None;
                }
                result.output_error = Some(crate::estimate::output_error::OutputErrorReport {
                    accepted: true,
                    iterations: rep.iterations,
                    cost_start: rep.cost_start,
                    cost_end: rep.cost_end,
                    start_values: values.clone(),
                    note: "prediction error (observer-corrected one-step-ahead innovations) instead of the free-run output error".into(),
                    substeps: rep.substeps,
                    rough: false,
                    scan: None,
                    prediction_error: Some(r.report),
                    secant_disagreement: None,
                    likelihood_ratio_widths: None,
                    bootstrap: None,
                    smooth_excitation_gain: None,
                });
                return;
            }
            Err(e) => result.notes.push(format!(
                "prediction-error refinement not run ({e}); {}",
                fallback_words(opts)
            )),
        }
    }
    // The free-run output error and the Cramér–Rao bound's sensitivities start at rest.
    if opts.initial_state.is_some() {
        if opts.output_error {
            result.failure = Some(
                "the record starts in motion and the prediction-error refinement (which starts from the estimated initial state) was not usable — see the notes; the free-run output error starts at rest and would be biased, so no refined answer is given (the parameters shown are the passes' residual-force estimate)".into(),
            );
        } else {
            result.notes.push(
                "Cramér–Rao bound not computed: the record starts in motion and the bound's free-run sensitivities start at rest".into(),
            );
        }
        return;
    }
    if opts.output_error {
        let t0 = std::time::Instant::now();
        let mut refined = refine_global(
            setup,
            model,
            &values,
            &scales,
            exc,
            resp,
            sigma,
            opts.substeps,
            opts.output_error_iterations,
        );
        // Passes that did not converge and a refinement that failed from the start it was
        // given: the likeliest of the passes' answers is the start instead (when it is
        // another). Measured (1-DOF `v, sign(v), const`, own-discretisation data, 100 %
        // noise, seed 9820): the tenth pass jumped from `v` = 41 to −24 N s/m, a negative
        // damper whose free run grows to χ² ≈ 1e26; the refinement from it failed (its
        // Fisher information singular at its end) and that answer was reported 5.2 errors
        // off (ACCURACY.md, fifty-fourth session).
        if refined.is_err()
            && let Some(k) = likeliest_pass_answer(setup, model, data, sigma, opts, &pass_answers)
            && pass_answers[k].0 != values
        {
            let (from, e) = pass_answers[k].clone();
            let from_scales = start_scales(&from, &e);
            let again = refine_global(
                setup,
                model,
                &from,
                &from_scales,
                exc,
                resp,
                sigma,
                opts.substeps,
                opts.output_error_iterations,
            );
            if let Ok(r) = again {
                if let Err(why) = &refined {
                    result.notes.push(format!(
                        "the passes did not converge and the output-error refinement from their answer failed ({why}): it started again from pass {} of {}, the one whose free run fits the record best",
                        k + 1,
                        pass_answers.len()
                    ));
                }
                scales = from_scales;
                values = from;
                refined = Ok(r);
            }
        }
        let refined = refined.map(|r| {
            crate::par::phase("free run (passes' level)", t0);
            let t0 = std::time::Instant::now();
            let r = raise_substeps(
                setup,
                model,
                data,
                opts,
                sigma,
                &values,
                &scales,
                r,
                &mut result.notes,
            );
            crate::par::phase("free run (sub-step levels)", t0);
            r
        });
        match refined {
            Ok(mut r) => {
                // How the excitation varies between samples: linear or smooth, the likelier
                // (see [`smooth_between_samples`]); what follows uses the excitation taken.
                let smoothed = smooth_between_samples(setup, model, data, opts, sigma, &mut r);
                if let Some((_, note)) = &smoothed {
                    result.notes.push(note.clone());
                }
                let data = smoothed.as_ref().map_or(data, |(d, _)| d);
                // A refinement that converged (its last step below 0.05 of the bound) is taken;
                // one that did not is taken when its cost is lower than the start's (a lower
                // point of the likelihood is the better answer: measured on the issue-13
                // runs, 14 of 16 discarded minima were the truth), or when it stayed within 3
                // standard errors of the residual-force estimate.
                let far = r
                    .values
                    .iter()
                    .zip(&values)
                    .zip(&scales)
                    .position(|((a, b), s)| (a - b).abs() > 3.0 * s);
                let settled = r.report.note.starts_with("converged");
                let lower = r.report.cost_end < r.report.cost_start;
                if r.report.accepted
                    && !settled
                    && !lower
                    && let Some(j) = far
                {
                    r.report.accepted = false;
                    r.report.note = format!(
                        "rejected: it moved `{}` by {:.1} standard errors of the residual-force estimate (more than 3); {}",
                        last.parameters[j].basis,
                        (r.values[j] - values[j]).abs() / scales[j],
                        r.report.note
                    );
                }
                // Residuals that are not white: the model leaves structure in the record
                // that the noise cannot explain.
                let not_white = if r.report.accepted {
                    residuals_not_white(setup, model, &r.values, data, sigma, r.report.substeps)
                } else {
                    None
                };
                // A misfit from a start in motion that the first sample did not show: the
                // free run cannot start elsewhere, so `identify` runs again with the start
                // state estimated (see `pem::motion_behind_misfit`; asked by the whiteness
                // test alone, its finding is seen again at the likeliest model sub-steps
                // before it is called motion, as the prediction error's is). Asked when the
                // answer misfits (normalised cost above the misfit rule's 2) or its
                // residuals are not white: at 100 % noise a record cut in motion misfits
                // within the cost rule (the start's free vibration is small against the
                // noise) and was answered from rest up to 72 errors off, its whiteness note
                // the only sign (ACCURACY.md, thirty-fourth session). Taken only when the
                // start state accounts for the misfit: what the innovations keep after its
                // refit is within the misfit rule (a model that is not the structure — 5 %
                // off in its beams' EI — also passes the test, as a start state fits a
                // little of any misfit: there it removed 4 % of the innovation cost, which
                // stayed ~41× the noise; on a record cut in motion 60 %, down to 0.99×).
                //
                // Whiteness asks only for a law with a friction term, which is identified
                // again with its start state estimated when found in motion; the other laws
                // of this path would be refused, and a refusal is not what a whiteness
                // finding at rest should bring (measured on Coulomb records only).
                let observations = (data.len() * sigma.len()).max(1) as f64;
                let misfit = r.report.cost_end > ANSWER_MISFIT_COST;
                if r.report.accepted
                    && (misfit || (not_white.is_some() && has_sign_basis(setup)))
                    && !by_prediction_error
                    && opts.start_motion.is_none()
                    && opts.starts_mid_record.is_none()
                    && !opts.in_motion
                    && model.has_dense()
                    && let Some(m) = pem::motion_behind_misfit(
                        setup,
                        model,
                        data,
                        sigma,
                        &r.values,
                        r.report.substeps,
                        !misfit,
                    )
                    && m.level - m.reduction / observations <= ANSWER_MISFIT_COST
                {
                    result.motion_in_record = Some(m);
                    return;
                }
                // Residuals still not white at rest (after the start-in-motion test, where it
                // is asked: friction laws), for a law with a term that is not linear in the
                // state (friction, cubic, gap): the free run may have stopped in a local
                // minimum of its cost (a ripple of a friction level's or a damper's cost).
                // The prediction error's answer from the same start (see
                // `pem::observer_answer`) starts another free run, taken only when it costs
                // less and its residuals are white (`free_run_from_observer_answer`). Also
                // for a `sign(u)` law here after its prediction-error refinement was refused
                // (the same free-run cost). Only on a dense model: the predictor's observer
                // needs the dense matrices (as the motion test above).
                let lower = (not_white.is_some()
                    && r.report.accepted
                    && has_nonlinear_term(setup)
                    && model.has_dense())
                .then(|| {
                    free_run_from_observer_answer(
                        setup,
                        model,
                        data,
                        opts,
                        sigma,
                        (&values, &scales),
                        &r,
                    )
                })
                .flatten();
                let (r, not_white) = match lower {
                    Some(lower) => (lower, None),
                    None => (r, not_white),
                };
                if let Some(scan) = r.report.scan.as_ref().filter(|s| s.ambiguous) {
                    result.notes.push(format!(
                        "the output-error cost has {} local minima in the `{}` scan whose costs cannot be told apart (Δχ² < 3.84): the data do not decide between them, and the standard errors are widened to cover them",
                        scan.minima.len(),
                        last.parameters[scan.parameter].basis
                    ));
                }
                if has_sign_u_basis(setup) && r.report.accepted && !r.report.rough {
                    result.notes.push(
                        "`sign(u)` friction: its output-error cost has local minima beyond the reach of the probe (8 standard errors); on continuous data at 10 % noise the spread over seeds was measured 57× the stated standard error (ACCURACY.md, \"Friction on continuous data\"): treat these standard errors as lower limits".into(),
                    );
                }
                if r.report.rough {
                    result.notes.push(format!(
                        "the output-error cost is rough at the scale of the standard errors (after {} restarts from lower probes within 8 standard errors a lower one remained): the standard errors are widened to the distance the restarts moved the estimate and may still be too small",
                        crate::estimate::output_error::PROBE_ROUNDS
                    ));
                }
                // A model that does not explain the outputs. `r.std_errors` are already the
                // bound scaled by the residuals' level (√cost, `output_error::refine`); the
                // residuals are then a smooth misfit rather than noise, and the bias it
                // leaves in the parameters grows with it, so the errors are widened by √cost
                // once more (by the cost in all). An empirical rule, not a derivation: a
                // Newey–West sandwich of the residuals (tried 2026-11-26) came out no wider
                // than the scaled bound on these records. Measured (spring setup, 8-sub-step
                // data, 1 % noise, 50 seeds): worst 106.7 → 25.7 errors off, coverage
                // unchanged.
                let widen = if r.report.cost_end > 2.0 {
                    r.report.cost_end.sqrt()
                } else {
                    1.0
                };
                if r.report.cost_end > 2.0 {
                    result.notes.push(format!(
                        "the model explains the outputs only to {:.1}× the noise variance (normalised output-error cost): unmodelled dynamics or too few [integrator] substeps; the standard errors are widened by the cost ({:.1}×: its square root for the noise level the residuals show, and the same again, an empirical allowance for the bias a misfit leaves) and may still not include all of that bias",
                        r.report.cost_end,
                        r.report.cost_end
                    ));
                }
                if let Some(note) = not_white {
                    result.notes.push(note);
                }
                if r.report.accepted {
                    for (j, p) in last.parameters.iter_mut().enumerate() {
                        p.value = r.values[j];
                        p.std_error = r.std_errors[j] * widen;
                        p.ci95 = [p.value - 1.96 * p.std_error, p.value + 1.96 * p.std_error];
                        p.crlb = Some(r.crlb[j]);
                    }
                    result.output_error = Some(r.report);
                    return;
                }
                result.output_error = Some(r.report);
            }
            Err(e) => {
                result
                    .notes
                    .push(format!("output-error refinement not run: {e}"));
                result.refinement_not_run = Some(e.to_string());
            }
        }
    }
    // Without the refinement (`--estimator paper`, `--no-refine`) nothing else compares the
    // answer with the record: its free run is checked against the noise, with the rule and
    // the words of the refinement's misfit note, so that `--strict` refuses it too. Why: the
    // 1989 estimator on the shipped spring recording answered `v` = −5.5e5 ± 6.0e4 N s/m
    // (truth 0) and "converged", with only a warning about its error recursion.
    if !opts.output_error {
        let answer: Vec<f64> = last.parameters.iter().map(|p| p.value).collect();
        let observations = (data.len() * sigma.len()).max(1) as f64;
        match crate::estimate::output_error::residuals(
            setup,
            model,
            &answer,
            exc,
            resp,
            sigma,
            opts.substeps,
        ) {
            Ok((_, cost)) if cost / observations > ANSWER_MISFIT_COST => {
                result.notes.push(format!(
                    "the model explains the outputs only to {:.3}× the noise variance (normalised output-error cost of the answer's free run, {} model sub-step(s)): unmodelled dynamics, too few model sub-steps (the refinement, not run here, raises them) or an answer the record does not support; the standard errors do not include this misfit",
                    cost / observations,
                    opts.substeps
                ))
            }
            Ok(_) => {}
            Err(e) => result.notes.push(format!(
                "the model explains the outputs only to an unbounded multiple of the noise variance: the answer's free run failed ({e})"
            )),
        }
    }
    if opts.crlb {
        match crlb(setup, model, &values, &scales, exc, resp, sigma, opts.substeps) {
            Ok(Some(b)) => {
                for (p, b) in last.parameters.iter_mut().zip(b) {
                    p.crlb = Some(b);
                }
            }
            Ok(None) => result.notes.push(
                "Cramér–Rao bound: the Fisher information is singular (a parameter does not affect the outputs)".into(),
            ),
            Err(e) => result
                .notes
                .push(format!("Cramér–Rao bound not computed: {e}")),
        }
    }
}

/// For an accepted free-run `answer` whose residuals were not white: the free run from the
/// prediction error's answer (`pem::observer_answer`) from the same `start` and with the
/// answer's model sub-steps, taken when it costs less by Δχ² > max(cost, 1) and its own
/// residuals are white; `None` otherwise.
///
/// Why white: where the residuals stay structured neither minimum is the data's and the
/// cost's ranking of the two is no evidence (measured with the friction-level scan this
/// replaced: accelerometers only, Coulomb, 64-sub-step data at 100 % noise, seed 3 of
/// `accelerometers_only_friction_at_full_noise_far_rescan_and_settling` — a lower cost with
/// the spring −32 %, 5.9 errors off, against −1.6 % before). The errors are at least the
/// answer's (a stiffness scan's widening among them), and cover both minima when the cost
/// cannot tell them apart (Δχ² < 3.84 × max(cost, 1), the stiffness scan's rule in
/// `output_error::refine_global`). The report keeps the answer's start, scan and note.
fn free_run_from_observer_answer(
    setup: &Setup,
    model: &Model,
    data: &TestData,
    opts: &IdentifyOptions,
    sigma: &[f64],
    (start, scales): (&[f64], &[f64]),
    answer: &crate::estimate::output_error::Refined,
) -> Option<crate::estimate::output_error::Refined> {
    let substeps = answer.report.substeps;
    let observed = pem::observer_answer(
        setup,
        model,
        data,
        sigma,
        start,
        scales,
        substeps,
        opts.output_error_iterations,
    )?;
    let mut lower = crate::estimate::output_error::refine(
        setup,
        model,
        &observed,
        &answer.std_errors,
        &data.excitation,
        &data.response,
        sigma,
        substeps,
        opts.output_error_iterations,
    )
    .ok()?;
    let observations = (data.len() * sigma.len()).max(1) as f64;
    let (cost, lower_cost) = (answer.report.cost_end, lower.report.cost_end);
    let apart = (cost - lower_cost) * observations;
    // (`accepted` of the free run from the observer's answer says only that it moved; a
    // cost that is not finite compares false.)
    if apart.partial_cmp(&cost.max(1.0)) != Some(std::cmp::Ordering::Greater) {
        return None;
    }
    if residuals_not_white(
        setup,
        model,
        &lower.values,
        data,
        sigma,
        lower.report.substeps,
    )
    .is_some()
    {
        return None;
    }
    let covers = apart < 3.84 * lower_cost.max(1.0);
    for ((e, old), (a, b)) in lower
        .std_errors
        .iter_mut()
        .zip(&answer.std_errors)
        .zip(lower.values.iter().zip(&answer.values))
    {
        *e = e.max(*old);
        if covers {
            *e = e.max((a - b).abs());
        }
    }
    lower.report.note = format!(
        "{}; taken from a free run started at the prediction error's answer (an observer-corrected descent from the same start), asked by residuals that were not white (normalised cost {cost:.4} → {lower_cost:.4}; before it: {})",
        lower.report.note, answer.report.note
    );
    take_over_start(&mut lower, answer);
    lower.report.accepted = true;
    Some(lower)
}

/// `into`, a free run that replaces `from` as the answer, takes over what `from`'s report
/// says of the refinement as a whole: where it started (`cost_start`, `start_values`: the
/// residual-force estimate, which the caller's rules compare against), the iterations
/// spent, the scan's minima.
fn take_over_start(
    into: &mut crate::estimate::output_error::Refined,
    from: &crate::estimate::output_error::Refined,
) {
    into.report.cost_start = from.report.cost_start;
    into.report.start_values = from.report.start_values.clone();
    into.report.iterations += from.report.iterations;
    into.report.scan = from.report.scan.clone();
}

/// The whiteness test of the maximum-likelihood fit (a Box–Pierce portmanteau per channel
/// over 20 lags at 99.9 %), applied to the free-run output errors of the output-error
/// refinement's answer: with the model right they are the sensor noise, white. Why: a
/// reviewer's 1-DOF test with a smooth force (the model holds the force linear between
/// samples) gave `v` 19 standard errors off at a normalised cost near 1 (below the cost
/// note's 2), without a word, where `--estimator ml` said the residuals were not white.
/// Returns the note (`--strict` refuses on it).
fn residuals_not_white(
    setup: &Setup,
    model: &Model,
    values: &[f64],
    data: &TestData,
    sigma: &[f64],
    substeps: usize,
) -> Option<String> {
    use crate::estimate::ml::{chi2_quantile_999, portmanteau};
    let (r, _) = data.free_run(setup, model, values, sigma, substeps).ok()?;
    let m = sigma.len();
    let n = r.len() / m.max(1);
    let lags = 20.min(n / 10).max(1);
    let limit = chi2_quantile_999(lags);
    let mut failing: Vec<(f64, &str)> = (0..m)
        .map(|k| {
            let e: Vec<f64> = (0..n).map(|i| r[i * m + k]).collect();
            (portmanteau(&e, lags), setup.sensors[k].name.as_str())
        })
        .filter(|(q, _)| *q > limit)
        .collect();
    failing.sort_by(|a, b| b.0.total_cmp(&a.0));
    let (q, name) = failing.first()?;
    Some(format!(
        "{RESIDUALS_NOT_WHITE} in {} of {m} channels (output-error residuals of the answer; worst `{name}`: portmanteau {q:.1} over {lags} lags, 99.9 % limit {limit:.1}): the model does not explain the data (a force that is not linear between samples, unmodelled dynamics, too few model sub-steps); the standard errors do not include the bias this may cause",
        failing.len()
    ))
}

/// The record with the excitation the free run's answer was fitted with: smooth between
/// samples when [`smooth_between_samples`] took it so, as recorded otherwise.
pub(crate) fn as_fitted<'a>(
    data: &'a TestData,
    result: &Identification,
) -> std::borrow::Cow<'a, TestData> {
    let smooth = result
        .output_error
        .as_ref()
        .is_some_and(|o| o.smooth_excitation_gain.is_some());
    if smooth {
        std::borrow::Cow::Owned(TestData {
            excitation: pem::moment_matched(&data.excitation),
            ..data.clone()
        })
    } else {
        std::borrow::Cow::Borrowed(data)
    }
}

/// The free run's refined answer `r` again with the excitation smooth between samples
/// (`pem::moment_matched`: each sample interval's mean that of a cubic through the
/// neighbouring samples, not of the straight line), when that excitation explains the record
/// better: `Some((the smoothed record, a note))` with `r` replaced by the refinement from
/// `r`'s values at `r`'s model sub-steps, `None` (and `r` untouched) otherwise.
///
/// Why: the model holds each force channel linear between samples, exact for a force that
/// is piecewise linear there (the `random` scenario's) but short of a smooth force's mean
/// over each sample by `(ωh)²/12` — 0.13 % of a 200 Hz sine at 10 kHz, which 1 % noise sees
/// over a few thousand samples. The prediction error has decided between the two since the
/// seventeenth session (`pem::refine_by_prediction_error`); the free run did not, and a
/// Coulomb joint (`sign(v), u`) under a 200 Hz sine (8-sub-step data, 1 % noise, seeds
/// 8301–8303) came out 3.1–7.0 errors off in its friction and 8.8–11.4 in its stiffness;
/// refined with the smoothed excitation 0.3–0.7 and 0.3–0.7 (ACCURACY.md, forty-fifth
/// session). The rule is the prediction error's: the same parameters and model, so the
/// plain comparison of the two costs (no penalty) — here at the linear refinement's answer,
/// where the model fits (at the passes' start the free run's misfit is their error, not
/// the excitation's). Taken only when the smoothed refinement ends lower too. A force that
/// is piecewise linear between samples is never moved: at the answer its smoothed cost is
/// higher by the cubic's error, which the parameters cannot absorb.
fn smooth_between_samples(
    setup: &Setup,
    model: &Model,
    data: &TestData,
    opts: &IdentifyOptions,
    sigma: &[f64],
    r: &mut crate::estimate::output_error::Refined,
) -> Option<(TestData, String)> {
    use crate::estimate::output_error::refine_global;
    if !r.report.accepted || data.len() < 3 {
        return None;
    }
    let sub = r.report.substeps;
    let smooth = TestData {
        excitation: pem::moment_matched(&data.excitation),
        ..data.clone()
    };
    let cost = |d: &TestData, p: &[f64]| {
        d.free_run(setup, model, p, sigma, sub)
            .ok()
            .map(|(_, c)| c)
            .filter(|c| c.is_finite())
    };
    let both = crate::par::map(&[data, &smooth], |d| cost(d, &r.values));
    let (linear, smoothed) = (both[0]?, both[1]?);
    if smoothed >= linear {
        return None;
    }
    let again = refine_global(
        setup,
        model,
        &r.values,
        &r.std_errors,
        &smooth.excitation,
        &smooth.response,
        sigma,
        sub,
        opts.output_error_iterations,
    )
    .ok()?;
    let nobs = (data.len() * sigma.len()) as f64;
    let refined = again.report.cost_end * nobs;
    if !(again.report.accepted && refined < linear) {
        return None;
    }
    let note = format!(
        "the excitation was taken as smooth between samples (each sample interval's mean that of a cubic through the neighbouring samples, not of the straight line): at the refined answer with {sub} model sub-step(s) its free-run cost was lower by Δχ² = {:.1}, and refined again with it lower by Δχ² = {:.1} (normalised cost {:.4} → {:.4}); a force that is piecewise linear between samples would be the other way",
        linear - smoothed,
        linear - refined,
        linear / nobs,
        again.report.cost_end
    );
    let mut again = again;
    again.report.cost_start = r.report.cost_start;
    again.report.start_values = r.report.start_values.clone();
    again.report.iterations += r.report.iterations;
    again.report.smooth_excitation_gain = Some(0.5 * (linear - refined));
    *r = again;
    Some((smooth, note))
}

/// The start of the whiteness note (what `--strict` looks for).
const RESIDUALS_NOT_WHITE: &str = "the residuals are not white";

/// Normalised output-error cost above which an answer that was not refined is said not to
/// explain the outputs (the refinement's own rule: 2× the noise variance).
const ANSWER_MISFIT_COST: f64 = 2.0;

/// A pass's report, parameter track, the Kalman tuning it used and, for a record in
/// motion, the initial-state correction its innovations call for.
type PassOutcome = (PassReport, Track, Option<KalmanTuning>, Option<Vec<f64>>);

#[allow(clippy::too_many_arguments)]
fn run_pass(
    setup: &Setup,
    model: &Model,
    params: &[f64],
    data: &TestData,
    opts: &IdentifyOptions,
    sigma: &[f64],
    estimated: &[bool],
    pass: usize,
    truth: Option<&[f64]>,
    frozen: Option<&KalmanTuning>,
    previous: Option<&KalmanTuning>,
    on_sample: &mut dyn FnMut(&StepOutput),
) -> Result<PassOutcome, IdentifyError> {
    // The model's Newmark sub-steps per sample: reported because continuous-time data are
    // biased by too few of them (see the ACCURACY.md).
    let mut tuning: Vec<(String, f64)> = vec![("model_substeps".into(), opts.substeps as f64)];
    for ((sensor, s), est) in setup.sensors.iter().zip(sigma).zip(estimated) {
        let kind = if *est { "estimated" } else { "given" };
        tuning.push((format!("noise_std_{kind}[{}]", sensor.name), *s));
    }
    let mut used_tuning = None;
    let mut est = if opts.estimator == EstimatorKind::Kalman && opts.force_walk_std.is_none() {
        let t = match frozen {
            Some(t) => {
                tuning.push(("tuning_frozen".to_string(), 1.0));
                t.clone()
            }
            None => {
                let t0 = std::time::Instant::now();
                let t = tune_kalman(setup, model, params, opts, sigma, estimated, data, previous)?;
                crate::par::phase("kalman tuning", t0);
                t
            }
        };
        used_tuning = Some(t.clone());
        tuning.extend([
            ("tuned_force_walk_std_N".to_string(), t.force_walk_std),
            ("tuned_noise_scale".to_string(), t.noise_scale),
            ("tuned_model_error_std_N".to_string(), t.model_error_std),
            ("tuned_log_likelihood".to_string(), t.log_likelihood),
            ("tuning_runs".to_string(), t.runs as f64),
        ]);
        let mut o = opts.clone();
        o.force_walk_std = Some(t.force_walk_std);
        o.model_error_std = Some(t.model_error_std);
        build_estimator(setup, model, params, &o, &t.sigma, data.len())?
    } else {
        build_estimator(setup, model, params, opts, sigma, data.len())?
    };
    let q = setup.connections.len();
    let mut acc = ParameterAccumulator::new(setup, opts.stick_band, 1.0);
    let mut tracker = Tracker::new(
        setup,
        opts.stick_band,
        TrackOptions {
            forgetting: opts.forgetting,
            every: if opts.track_every > 0 {
                opts.track_every
            } else {
                TrackOptions::default_every(opts.forgetting, data.len())
            },
            max_condition: opts.max_condition,
        },
    );
    acc.keep_rows();
    // The same fit with the band not widened by the estimator's uncertainty: used for a
    // connection whose widened band leaves too few samples (see [`MAX_STUCK_FRACTION`]).
    // Made only then, from the pass's deformations and forces kept here (per sample and
    // connection: δ, δ̇, δ̈, force): accumulated every pass, it was an eighth of one and
    // seldom used (BENCHMARKS.md, thirty-fifth session).
    let mut narrow_parts: Option<Vec<f64>> = None;
    if opts.stick_band_sigmas > 0.0 {
        let diag = est.diagnostics();
        let find = |key: String| diag.tuning_value(&key).unwrap_or(0.0);
        for c in 0..setup.connections.len() {
            let d = find(format!("posterior_delta_std_m[{c}]"));
            let v = find(format!("posterior_delta_v_std_m_s[{c}]"));
            acc.widen_band(c, opts.stick_band_sigmas * d, opts.stick_band_sigmas * v);
            tracker.widen_band(c, opts.stick_band_sigmas * d, opts.stick_band_sigmas * v);
        }
        if setup.connections.iter().any(|c| {
            c.basis
                .iter()
                .any(|b| matches!(b, Basis::SignU | Basis::SignV))
        }) {
            narrow_parts = Some(Vec::with_capacity(4 * q * data.len()));
        }
    }
    // Without forgetting the tracked fit is the batch fit, read from `acc` as it goes.
    let follow = tracker.follows_batch();
    let mut out = StepOutput::new(q);
    let mut delta_sq = vec![0.0f64; q];
    let mut delta_rows = 0usize;
    let mut take = |out: &StepOutput| {
        for (s, d) in delta_sq.iter_mut().zip(out.delta.iter()) {
            *s += d * d;
        }
        delta_rows += 1;
    };
    let mut consume = |out: &StepOutput| {
        acc.push(out);
        if let Some(parts) = narrow_parts.as_mut() {
            for v in [&out.delta, &out.delta_v, &out.delta_a, &out.force] {
                parts.extend_from_slice(v.as_slice());
            }
        }
        if follow {
            tracker.follow(&acc, out.sample);
        } else {
            tracker.push(out);
        }
        take(out);
        on_sample(out);
    };
    est.start(data.samples[0], &data.excitation[0]);
    for i in 1..data.len() {
        if est.step(
            data.samples[i],
            &data.excitation[i],
            &data.response[i],
            &mut out,
        )? {
            diverged_at(&out)?;
            consume(&out);
        }
    }
    while est.drain(&mut out) {
        diverged_at(&out)?;
        consume(&out);
    }
    let delta_rms: Vec<f64> = delta_sq
        .iter()
        .map(|s| (s / delta_rows.max(1) as f64).sqrt())
        .collect();
    let mut warnings = Vec::new();
    deformation_determined(
        setup,
        est.diagnostics(),
        &delta_rms,
        pass,
        pass == 1 && opts.passes > 1,
        &mut tuning,
        &mut warnings,
    )?;
    let track = tracker.finish_following(follow.then_some(&acc), data.samples.last().copied());
    let fits = acc.solve(opts.max_condition);
    let narrow = narrow_parts
        .filter(|_| {
            let (used, excluded) = (acc.rows(), acc.excluded());
            fits.iter().enumerate().any(|(c, fit)| {
                fit.is_err()
                    || excluded[c] as f64 > MAX_STUCK_FRACTION * (used[c] + excluded[c]) as f64
            })
        })
        .map(|parts| {
            let mut n = ParameterAccumulator::new(setup, opts.stick_band, 1.0);
            n.keep_rows();
            for sample in parts.chunks_exact(4 * q) {
                let (delta, rest) = sample.split_at(q);
                let (delta_v, rest) = rest.split_at(q);
                let (delta_a, force) = rest.split_at(q);
                n.push_parts(delta, delta_v, delta_a, force);
            }
            n
        });
    let narrow_fits = narrow.as_ref().map(|n| n.solve(opts.max_condition));
    let mut parameters = Vec::new();
    let mut cond = Vec::new();
    let mut rms = Vec::new();
    let mut k = 0;
    let mut force_scales = Vec::new();
    let mut rows_used = acc.rows();
    let mut rows_excluded = acc.excluded();
    for (c, fit) in fits.into_iter().enumerate() {
        let conn = &setup.connections[c];
        let total = rows_used[c] + rows_excluded[c];
        let too_many = rows_excluded[c] as f64 > MAX_STUCK_FRACTION * total as f64;
        let mut source = &acc;
        let fit = match (&narrow, &narrow_fits) {
            (Some(n), Some(nf)) if (fit.is_err() || too_many) && nf[c].is_ok() => {
                warnings.push(format!(
                    "connection `{}`: the stuck band widened by {} posterior std of the deformation held {} of {total} samples ({}); fitted with the band not widened ({} held): the friction this fit gives is biased towards zero by the noisy stuck samples it now includes, and serves as the start of the output-error refinement",
                    conn.name,
                    opts.stick_band_sigmas,
                    rows_excluded[c],
                    match &fit {
                        Ok(_) => "more than half".to_string(),
                        Err(e) => e.to_string(),
                    },
                    n.excluded()[c]
                ));
                rows_used[c] = n.rows()[c];
                rows_excluded[c] = n.excluded()[c];
                source = n;
                nf[c].clone()
            }
            _ => fit,
        };
        let fit = fit.map_err(|source| IdentifyError::Refit {
            pass,
            connection: conn.name.clone(),
            source,
        })?;
        let hac = source.hac(c, &fit.values);
        if let Some((_, lag)) = &hac {
            tuning.push((format!("hac_lag_samples[{}]", conn.name), *lag as f64));
        }
        for (j, b) in conn.basis.iter().enumerate() {
            let ols = fit.std_errors[j];
            // The larger of the two: HAC can fall below OLS by chance on short records.
            let se = hac.as_ref().map_or(ols, |(h, _)| h[j].max(ols));
            let v = fit.values[j];
            parameters.push(ParameterEstimate {
                connection: conn.name.clone(),
                basis: b.label(),
                unit: b.unit().into(),
                value: v,
                std_error: se,
                ci95: [v - 1.96 * se, v + 1.96 * se],
                crlb: None,
                std_error_ols: Some(ols),
                truth: truth.map(|t| t[k]),
            });
            force_scales.push((fit.column_rms[j], fit.force_rms));
            k += 1;
        }
        cond.push(fit.condition);
        rms.push(fit.rms_residual);
    }
    let report = PassReport {
        pass,
        parameters,
        fit_condition: cond,
        fit_rms_residual: rms,
        rows_used,
        rows_excluded_stuck: rows_excluded,
        diagnostics: {
            let mut d = est.diagnostics().clone();
            d.tuning.extend(tuning);
            d.warnings.extend(warnings);
            d
        },
        max_change_std_errors: None,
        max_change_force_relative: None,
        force_scales,
    };
    // A record in motion: the initial-state correction this pass's innovations call for.
    let initial_fit = opts
        .initial_state
        .as_ref()
        .and_then(|_| est.initial_state_fit());
    Ok((report, track, used_tuning, initial_fit))
}

/// Largest fraction of a pass's samples the stuck band widened by the estimator's
/// uncertainty may exclude from a friction connection's fit; beyond it (or when the widened
/// fit is singular) the fit uses the band without the widening. Why: at high noise the
/// posterior std of δ̇ is comparable to δ̇ itself and the widened band swallows the slipping
/// samples (measured, Coulomb `sign(v)` on continuous data: 44 % excluded at 10 % noise on
/// the 50-element model where 0.8 % are truly stuck; all samples at 100 % noise, where the
/// pass failed). The residual-force fit only starts the output-error refinement, which
/// simulates the friction law exactly and needs no band.
pub const MAX_STUCK_FRACTION: f64 = 0.5;

/// Largest accepted ratio of the estimator's posterior std of a connection deformation δ to
/// the RMS of its estimate. Above it the measurements do not pin δ down and a fit of force
/// against δ̂ is a confident wrong answer. Measured on the two-beam problem (ACCURACY.md,
/// "Accelerometers only, and mixed layouts"): shipped recordings 0.01–0.09; mixed layout,
/// continuous data, 10 % noise 0.43–0.55 (spring +0.2 %); the same at 50 % noise 1.36–1.58
/// in pass 1 (spring −23 % and −39 % with a stated error of 0.3 % before the output-error
/// scan; after it one seed still ends +21 % with a 0.05 % stated error); accelerations only, 16 sub-steps,
/// noise-free 8.7 (spring −105 %).
pub const MAX_DEFORMATION_UNCERTAINTY: f64 = 1.0;

/// Refuse a pass whose joint deformations the measurements do not determine (see
/// [`MAX_DEFORMATION_UNCERTAINTY`]); the figures go into the pass diagnostics either way.
///
/// A `provisional` pass (the first of several) only warns: it runs with the setup's initial
/// parameters, typically no joint stiffness, so the filter's model of the joint is softer
/// than the structure's and its posterior std of δ larger. The next pass, with the fitted
/// parameters, is checked and refused (see [`identify`]). Measured (Coulomb `sign(v)` +
/// spring, continuous data, 100 % noise, 2,000 samples, seed 1): ratio 1.23 in pass 1,
/// 0.91 in pass 2, 0.75 from pass 4 on; refusing pass 1 had refused 3 of 4 seeds, which the
/// output-error stage identifies within 2.4 % and inside their stated intervals.
#[allow(clippy::too_many_arguments)]
fn deformation_determined(
    setup: &Setup,
    diagnostics: &crate::estimate::EstimatorDiagnostics,
    delta_rms: &[f64],
    pass: usize,
    provisional: bool,
    tuning: &mut Vec<(String, f64)>,
    warnings: &mut Vec<String>,
) -> Result<(), IdentifyError> {
    for (c, conn) in setup.connections.iter().enumerate() {
        let Some(std) = diagnostics.tuning_value(&format!("posterior_delta_std_m[{c}]")) else {
            continue;
        };
        let rms = delta_rms[c];
        let ratio = std / rms.max(f64::MIN_POSITIVE);
        tuning.push((format!("delta_rms_m[{c}]"), rms));
        tuning.push((format!("delta_uncertainty_ratio[{c}]"), ratio));
        if ratio > MAX_DEFORMATION_UNCERTAINTY && provisional {
            warnings.push(format!(
                "connection `{}`: in pass {pass}, run with the setup's initial parameters, the posterior std of the joint deformation ({std:.3e} m) is {ratio:.2}× the RMS of its estimate (limit {MAX_DEFORMATION_UNCERTAINTY}); the identification is refused if the next pass, run with the fitted parameters, exceeds it too",
                conn.name
            ));
        } else if ratio > MAX_DEFORMATION_UNCERTAINTY {
            return Err(IdentifyError::Undetermined {
                pass,
                connection: conn.name.clone(),
                posterior_std: std,
                rms,
            });
        }
    }
    Ok(())
}

/// A residual force or connection state that is not finite, or so large that its square
/// overflows (> 1e150), means the estimator's error recursion blew up (the paper's on the
/// 50-element model: ×1e14 per 100 samples): say that, rather than let the rows reach the
/// fit and report it as singular.
fn diverged_at(out: &StepOutput) -> Result<(), EstimateError> {
    const TOO_LARGE: f64 = 1e150;
    let mut worst = 0.0f64;
    for v in [&out.residual, &out.delta, &out.delta_v, &out.force] {
        for &x in v.iter() {
            if !x.is_finite() {
                return Err(EstimateError::Diverged { sample: out.sample });
            }
            worst = worst.max(x.abs());
        }
    }
    if worst > TOO_LARGE {
        return Err(EstimateError::Overflowed {
            sample: out.sample,
            magnitude: worst,
        });
    }
    Ok(())
}

/// The default estimator: maximum likelihood on the exactly discretised model (see
/// [`crate::estimate::ml`]), reported as one pass so every output path is shared.
fn identify_by_maximum_likelihood(
    setup: &Setup,
    model: &Model,
    data: &TestData,
    opts: &IdentifyOptions,
    truth: Option<&[f64]>,
    on_pass: &mut dyn FnMut(&PassReport),
    on_sample: &mut dyn FnMut(usize, &StepOutput),
) -> Result<Identification, IdentifyError> {
    use crate::estimate::ml::identify_ml;
    let (fit, trace) = identify_ml(setup, model, data, &opts.ml)?;
    let keys = setup.param_keys();
    let q = setup.connections.len();
    let mut parameters = Vec::with_capacity(keys.len());
    let mut k = 0;
    for conn in &setup.connections {
        for b in &conn.basis {
            let (v, se) = (fit.params[k], fit.std_errors[k]);
            parameters.push(ParameterEstimate {
                connection: conn.name.clone(),
                basis: b.label(),
                unit: b.unit().to_string(),
                value: v,
                std_error: se,
                ci95: [v - 1.96 * se, v + 1.96 * se],
                crlb: Some(fit.crlb[k]),
                std_error_ols: None,
                truth: truth.and_then(|t| t.get(k).copied()),
            });
            k += 1;
        }
    }
    let mut diagnostics = EstimatorDiagnostics {
        estimator: "ml".into(),
        sensitivity_rank: keys.len(),
        sensitivity_condition: fit.condition,
        sensitivity_gain: 0.0,
        error_spectral_radius: None,
        tuning: Vec::new(),
        warnings: fit.warnings.clone(),
    };
    for (name, s) in setup.sensors.iter().zip(&fit.noise_std) {
        diagnostics
            .tuning
            .push((format!("noise_std[{}]", name.name), *s));
    }
    for (name, w) in setup.sensors.iter().zip(&fit.whiteness) {
        diagnostics
            .tuning
            .push((format!("whiteness[{}]", name.name), *w));
    }
    diagnostics
        .tuning
        .push(("substeps".into(), fit.substeps as f64));
    diagnostics.tuning.push((
        "discretisation_error_noise_std".into(),
        fit.discretisation_error,
    ));
    let report = PassReport {
        pass: 1,
        parameters,
        fit_condition: vec![fit.condition; q],
        fit_rms_residual: vec![0.0; q],
        rows_used: vec![trace.n; q],
        rows_excluded_stuck: vec![0; q],
        diagnostics,
        max_change_std_errors: None,
        max_change_force_relative: None,
        force_scales: Vec::new(),
    };
    on_pass(&report);
    // Per-sample connection states and forces of the final model; the residual force is
    // what the setup's initial guess misses (`R = f − f̂` with `f̂` the initial law).
    let initial = ConnectionLaw::new(setup, &setup.initial_params());
    let mut out = StepOutput::new(q);
    let (mut guess_nl, mut guess_lin) = (DVector::zeros(q), DVector::zeros(q));
    for i in 0..trace.n {
        out.sample = data.samples[i];
        for c in 0..q {
            out.force[c] = trace.force[i * q + c];
            out.delta[c] = trace.delta[i * q + c];
            out.delta_v[c] = trace.delta_v[i * q + c];
            out.delta_a[c] = trace.delta_a[i * q + c];
        }
        initial.explicit_force(&out.delta, &out.delta_v, &out.delta_a, &mut guess_nl);
        initial.linear_force(&out.delta, &out.delta_v, &out.delta_a, &mut guess_lin);
        for c in 0..q {
            out.residual[c] = out.force[c] - guess_nl[c] - guess_lin[c];
        }
        on_sample(1, &out);
    }
    let mut notes = vec![format!("discretisation: {}", fit.discretisation)];
    notes.extend(fit.warnings.iter().cloned());
    let stop_reason = format!(
        "maximum likelihood converged: {} Levenberg–Marquardt iterations over {} stage(s) of the record ({} samples), initial state {}",
        fit.iterations,
        fit.stages.len(),
        trace.n,
        if opts.ml.free_initial_state {
            "estimated"
        } else {
            "at rest"
        }
    );
    Ok(Identification {
        passes: vec![report],
        converged: true,
        stop_reason,
        maximum_likelihood: Some(fit),
        notes,
        ..Identification::started("ml")
    })
}

/// Convert a step output to a record.
pub fn record(out: &StepOutput) -> SampleRecord {
    let v = |x: &DVector<f64>| x.iter().copied().collect();
    SampleRecord {
        sample: out.sample,
        residual: v(&out.residual),
        force: v(&out.force),
        delta: v(&out.delta),
        delta_v: v(&out.delta_v),
        delta_a: v(&out.delta_a),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn shipped_friction_setup() -> Setup {
        let path = std::path::Path::new(env!("CARGO_MANIFEST_DIR"))
            .join("recordings")
            .join("two-beam-friction.toml");
        Setup::from_file(&path).expect("the shipped setup loads")
    }

    /// A record whose first sample reads `ratio` noise std on every displacement and
    /// velocity channel (1 on the rest), all noise levels 1.
    fn first_sample_at(setup: &Setup, ratio: f64) -> (TestData, Vec<f64>) {
        let first = setup
            .sensors
            .iter()
            .map(|s| match s.quantity {
                Quantity::Displacement | Quantity::Velocity => ratio,
                _ => 1.0,
            })
            .collect::<Vec<_>>();
        let data = TestData {
            samples: vec![0],
            t_ns: vec![0],
            excitation: vec![vec![0.0; setup.excitation.len()]],
            response: vec![first],
        };
        (data, vec![1.0; setup.sensors.len()])
    }

    fn pass_with(pass: usize, values: &[f64]) -> PassReport {
        PassReport {
            pass,
            parameters: values
                .iter()
                .map(|&value| ParameterEstimate {
                    connection: "joint".into(),
                    basis: "u".into(),
                    unit: "N/m".into(),
                    value,
                    std_error: 1.0,
                    ci95: [value - 1.96, value + 1.96],
                    crlb: None,
                    std_error_ols: None,
                    truth: None,
                })
                .collect(),
            fit_condition: vec![],
            fit_rms_residual: vec![],
            rows_used: vec![],
            rows_excluded_stuck: vec![],
            diagnostics: EstimatorDiagnostics::default(),
            max_change_std_errors: None,
            max_change_force_relative: None,
            force_scales: vec![],
        }
    }

    fn two_passes() -> Identification {
        Identification {
            passes: vec![pass_with(1, &[3.0e5]), pass_with(2, &[-1.4e7])],
            ..Identification::started("kalman")
        }
    }

    #[test]
    fn a_pass_whose_answer_made_the_next_diverge_is_taken_off_the_passes() {
        let diverged = IdentifyError::Estimate(EstimateError::Diverged { sample: 17 });
        let mut result = two_passes();
        let note = discard_pass_that_diverged(&mut result, &[-1.4e7], &diverged, 3)
            .expect("pass 2's own answer diverged in pass 3");
        assert_eq!(result.passes.len(), 1);
        assert_eq!(result.final_parameters().map(|p| p[0].value), Some(3.0e5));
        assert!(note.contains("pass 2 discarded"), "{note}");
        assert!(note.contains("-1.4000e7"), "{note}");
        assert!(note.contains("from pass 1"), "{note}");
        // Extrapolated parameters diverged: pass 2's own answer never ran, it stays.
        let mut result = two_passes();
        assert!(discard_pass_that_diverged(&mut result, &[-2.0e7], &diverged, 3).is_none());
        assert_eq!(result.passes.len(), 2);
        // A failure that is not a divergence says nothing against the parameters; stations
        // that no longer see the residual force with them, or an overflow, do.
        let cases = [
            (
                IdentifyError::Undetermined {
                    pass: 3,
                    connection: "joint".into(),
                    posterior_std: 1.0,
                    rms: 1.0,
                },
                false,
            ),
            (
                IdentifyError::Estimate(EstimateError::RankDeficientSensitivity {
                    rank: 0,
                    needed: 1,
                    stations: 12,
                    condition: f64::INFINITY,
                }),
                true,
            ),
            (
                IdentifyError::Estimate(EstimateError::InnovationCovariance { channels: 12 }),
                true,
            ),
            (
                IdentifyError::Estimate(EstimateError::Overflowed {
                    sample: 3,
                    magnitude: 1e200,
                }),
                true,
            ),
        ];
        for (e, discarded) in cases {
            let mut result = two_passes();
            let note = discard_pass_that_diverged(&mut result, &[-1.4e7], &e, 3);
            assert_eq!(note.is_some(), discarded, "{e}");
            assert_eq!(result.passes.len(), if discarded { 1 } else { 2 }, "{e}");
        }
    }

    #[test]
    fn motion_below_the_one_channel_limit_on_every_channel_is_seen_by_all_together() {
        let setup = shipped_friction_setup();
        // 5 noise std on each of the 12 channels: no channel beyond 6, Σ² = 300.
        let (data, sigma) = first_sample_at(&setup, 5.0);
        match starts_at_rest(&setup, &data, &sigma) {
            Err(IdentifyError::NotAtRest {
                chi2,
                channels,
                chi2_limit,
                ratio,
                ..
            }) => {
                assert_eq!(channels, 12);
                assert!((chi2 - 300.0).abs() < 1e-9, "Σ² {chi2}");
                assert!((60.0..75.0).contains(&chi2_limit), "limit {chi2_limit}");
                assert!(ratio < MAX_START_NOISE_RATIO);
            }
            other => panic!("motion on every channel not seen: {other:?}"),
        }
        // 1.5 noise std on every channel (Σ² = 27) is what noise at rest reads.
        let (data, sigma) = first_sample_at(&setup, 1.5);
        assert!(starts_at_rest(&setup, &data, &sigma).is_ok());
    }

    #[test]
    fn one_channel_far_from_rest_is_refused_by_name() {
        let setup = shipped_friction_setup();
        let (mut data, sigma) = first_sample_at(&setup, 0.0);
        let k = setup
            .sensors
            .iter()
            .position(|s| matches!(s.quantity, Quantity::Velocity))
            .expect("the shipped setup has a velocity channel");
        data.response[0][k] = -7.0;
        match starts_at_rest(&setup, &data, &sigma) {
            Err(e @ IdentifyError::NotAtRest { .. }) => {
                let text = e.to_string();
                assert!(text.contains(&setup.sensors[k].name), "{text}");
                assert!(text.contains("7.0× its noise std"), "{text}");
            }
            other => panic!("a channel at 7 noise std not refused: {other:?}"),
        }
    }

    #[test]
    fn the_joint_limit_holds_its_false_alarm_rate() {
        // Wilson–Hilferty against exact χ² quantiles at 2e-9 (one degree: 6² = 36, on the
        // safe side; 12 degrees: 65.7 by the closed form of even degrees).
        let one = chi2_upper_quantile(1, START_TEST_Z);
        assert!((36.0..46.0).contains(&one), "{one}");
        let twelve = chi2_upper_quantile(12, START_TEST_Z);
        assert!((twelve - 65.7).abs() < 0.04 * 65.7, "{twelve}");
    }

    /// The observer-force warning starts above ten force scales and names the parameters.
    #[test]
    fn observer_force_warning_above_ten_force_scales() {
        assert!(observer_force_warning(1.6e4, 1.75e3).is_none());
        let w = observer_force_warning(3.4e4, 1.75e3).expect("19× the scale");
        assert!(w.contains("19×") && w.contains("`v`"), "{w}");
    }

    /// The noise-shift note names the parameter moved most in its own errors (not the one
    /// with the largest shift in its units), and a zero error does not win by division.
    #[test]
    fn noise_shift_note_names_the_largest_shift_in_errors() {
        let keys: Vec<String> = ["j.u", "j.v", "j.sign(u)"].map(String::from).to_vec();
        let note = noise_shift_note(&keys, &[500.0, 0.03, 0.0], &[1000.0, 0.01, 0.0]);
        assert!(note.contains("3.00 standard errors, `j.v`"), "{note}");
    }
}
