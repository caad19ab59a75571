//! Setup file: the TOML schema (serde, unknown keys rejected) and its validation into a
//! [`Setup`] that every later stage trusts ("parse, don't validate").
//!
//! Units are SI throughout: metres, seconds, newtons, kilograms. A node reference is the
//! integer id of a node; a DOF reference is `{ node = 6, dir = "w" }` where `dir` is `w`
//! (transverse translation) or `rz` (in-plane rotation).
//!
//! Decisions written down here:
//! - Beams are planar Euler–Bernoulli bending elements along a line (transverse `w` and
//!   rotation `rz` per node); axial motion is not modelled.
//! - A beam is given by its end nodes and a number of elements; its interior nodes get the
//!   ids listed in `interior_ids` so that sensors and connections can name them.
//! - With lumped mass the rotations carry no inertia and are removed by static
//!   condensation (exact for the massless DOFs). Excitation, sensors and connections must
//!   therefore sit on translations when the mass is lumped; the validation says so.

use std::collections::{BTreeMap, BTreeSet};
use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};

/// Errors while reading or validating a setup. Each names the file and the offending key.
#[derive(Debug, thiserror::Error)]
pub enum SetupError {
    #[error("cannot read setup {path}: {source}")]
    Io {
        path: PathBuf,
        source: std::io::Error,
    },
    #[error("setup {origin}: {message}")]
    Parse { origin: String, message: String },
    #[error(
        "setup {origin}: model.matrix_market: {error} (paths are relative to the setup file's directory; for a setup attached to a recording that does not carry its model's files (made before 2026-11-29), to the recording's directory: keep the files beside it or give `--setup` the setup file)"
    )]
    MatrixMarket {
        origin: String,
        error: crate::matrix_market::MatrixMarketError,
    },
    /// The model's files a recording carries (its attachments), not the files on disk.
    #[error(
        "setup {origin}: model.matrix_market: {error} (the model's files the recording carries; give `--setup` to use files on disk instead)"
    )]
    AttachedModel {
        origin: String,
        error: crate::matrix_market::MatrixMarketError,
    },
    #[error("setup {origin}: {key}: {message}")]
    Invalid {
        origin: String,
        key: String,
        message: String,
    },
}

// ---------------------------------------------------------------------------------------
// Raw schema (what the TOML says)
// ---------------------------------------------------------------------------------------

/// The setup file as written. See `recordings/two-beam-friction.toml` for an example.
#[derive(Debug, Clone, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SetupFile {
    /// Free text shown in reports.
    #[serde(default)]
    pub title: String,
    pub model: ModelSpec,
    #[serde(default)]
    pub excitation: Vec<ExcitationSpec>,
    #[serde(default)]
    pub sensors: Vec<SensorSpec>,
    #[serde(default)]
    pub connections: Vec<ConnectionSpec>,
    pub integrator: IntegratorSpec,
    #[serde(default)]
    pub estimator: EstimatorSpec,
}

#[derive(Debug, Clone, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ModelSpec {
    /// Component matrices from Matrix Market files instead of beams (see
    /// [`MatrixMarketSpec`]); then only `rayleigh` may be given besides.
    #[serde(default)]
    pub matrix_market: Option<MatrixMarketSpec>,
    #[serde(default)]
    pub nodes: Vec<NodeSpec>,
    #[serde(default)]
    pub beams: Vec<BeamSpec>,
    #[serde(default)]
    pub masses: Vec<MassSpec>,
    #[serde(default)]
    pub springs: Vec<LinkSpec>,
    #[serde(default)]
    pub dashpots: Vec<LinkSpec>,
    /// Nodes where the beams meeting there have separate rotations (a pin / revolute joint).
    #[serde(default)]
    pub hinges: Vec<u32>,
    #[serde(default)]
    pub supports: Vec<SupportSpec>,
    #[serde(default)]
    pub rayleigh: Option<RayleighSpec>,
}

/// An external FE model: `[model.matrix_market]` with `mass`, `stiffness`, optional
/// `damping` (Matrix Market files) and `dof_map` (CSV `node,direction,row`), paths relative
/// to the directory of the setup file (see [`crate::matrix_market`]). The matrices are the
/// free (unconstrained) DOFs: apply supports in the FE tool. DOFs whose mass row is zero are
/// condensed out statically, as for the beam models.
#[derive(Debug, Clone, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct MatrixMarketSpec {
    pub mass: PathBuf,
    pub stiffness: PathBuf,
    #[serde(default)]
    pub damping: Option<PathBuf>,
    pub dof_map: PathBuf,
}

#[derive(Debug, Clone, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct NodeSpec {
    pub id: u32,
    /// Position along the beam line, m.
    pub x: f64,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, Default)]
#[serde(rename_all = "lowercase")]
pub enum MassKind {
    /// Half of each element's mass at each end node, no rotary inertia.
    #[default]
    Lumped,
    /// Consistent (cubic Hermite) mass matrix.
    Consistent,
}

#[derive(Debug, Clone, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct BeamSpec {
    #[serde(default)]
    pub name: String,
    pub from: u32,
    pub to: u32,
    /// Number of elements the beam is split into.
    #[serde(default = "one")]
    pub elements: usize,
    /// Ids given to the `elements − 1` interior nodes, from `from` towards `to`.
    #[serde(default)]
    pub interior_ids: Vec<u32>,
    /// Bending stiffness EI, N·m².
    pub ei: f64,
    /// Mass per unit length, kg/m.
    pub mass_per_length: f64,
    #[serde(default)]
    pub mass: MassKind,
}

fn one() -> usize {
    1
}

#[derive(Debug, Clone, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct MassSpec {
    pub node: u32,
    /// Translational mass, kg.
    #[serde(default)]
    pub mass: f64,
    /// Rotary inertia, kg·m².
    #[serde(default)]
    pub inertia: f64,
}

/// A spring (value `k`, N/m) or dashpot (value `c`, N·s/m): grounded on `dof`, or between
/// the two DOFs of `between` (acting on `u_a − u_b`).
#[derive(Debug, Clone, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct LinkSpec {
    #[serde(default)]
    pub dof: Option<DofRef>,
    #[serde(default)]
    pub between: Option<[DofRef; 2]>,
    #[serde(alias = "k", alias = "c")]
    pub value: f64,
}

#[derive(Debug, Clone, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SupportSpec {
    pub node: u32,
    /// Directions fixed at the node: any of `w`, `rz`.
    pub fix: Vec<Dir>,
}

/// Rayleigh damping `C = alpha·M + beta·K` of the components.
#[derive(Debug, Clone, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct RayleighSpec {
    #[serde(default)]
    pub alpha: f64,
    #[serde(default)]
    pub beta: f64,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord, Hash, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Dir {
    /// Transverse translation, m.
    W,
    /// In-plane rotation, rad.
    Rz,
    /// Translations along x, y, z of an external (Matrix Market) model, m.
    Ux,
    Uy,
    Uz,
    /// Rotations about x, y of an external model, rad (about z is `rz`).
    Rx,
    Ry,
    /// Coordinate of a retained fixed-interface mode of a reduced model (`node` = mode
    /// number from 1; see `model::reduce`), kg^½·m. Not a place on the structure.
    Mode,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord, Hash, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct DofRef {
    pub node: u32,
    pub dir: Dir,
}

impl std::fmt::Display for DofRef {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(
            f,
            "node {} {}",
            self.node,
            crate::matrix_market::dir_name(self.dir)
        )
    }
}

#[derive(Debug, Clone, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ExcitationSpec {
    pub name: String,
    pub dof: DofRef,
    #[serde(default = "newton")]
    pub unit: String,
}

fn newton() -> String {
    "N".into()
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Quantity {
    Displacement,
    Velocity,
    Acceleration,
}

impl Quantity {
    /// Which block of the state `(u; u̇; ü)` a channel of this quantity reads (0, 1, 2):
    /// its index in a `3n` state is `block · n + dof`.
    pub fn block(self) -> usize {
        match self {
            Quantity::Displacement => 0,
            Quantity::Velocity => 1,
            Quantity::Acceleration => 2,
        }
    }
}

#[derive(Debug, Clone, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SensorSpec {
    pub name: String,
    pub dof: DofRef,
    pub quantity: Quantity,
    #[serde(default)]
    pub unit: Option<String>,
    /// Standard deviation of the measurement noise in the channel's unit. When absent the
    /// estimator derives it from the data (see `estimate`).
    #[serde(default)]
    pub noise_std: Option<f64>,
}

#[derive(Debug, Clone, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ConnectionSpec {
    pub name: String,
    /// Grounded connection on this DOF…
    #[serde(default)]
    pub dof: Option<DofRef>,
    /// …or a connection between two DOFs, deformation `u_a − u_b`.
    #[serde(default)]
    pub between: Option<[DofRef; 2]>,
    /// Basis functions, e.g. `["sign(u)", "u", "const(100)", "v"]`.
    pub basis: Vec<String>,
    /// Initial guesses of the parameters (default zero).
    #[serde(default)]
    pub initial: Vec<f64>,
    /// True parameters, used by `jointid simulate` to generate data.
    #[serde(default)]
    pub truth: Vec<f64>,
}

#[derive(Debug, Clone, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct IntegratorSpec {
    /// Sample interval of the data, s.
    pub dt_s: f64,
    #[serde(default = "half")]
    pub gamma: f64,
    #[serde(default = "quarter")]
    pub beta: f64,
    /// Newmark steps the identification model takes per sample.
    #[serde(default = "one")]
    pub substeps: usize,
    /// How the per-sample step is computed (see [`crate::integrate::fast`]).
    #[serde(default)]
    pub step: StepKind,
}

/// The implementation of the one-sample Newmark map. Both compute the same linear map; they
/// differ in cost and set-up (see `BENCHMARKS.md`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, Default)]
#[serde(rename_all = "lowercase")]
pub enum StepKind {
    /// `dense` below 48 DOFs; above, `sparse` or `modal`, whichever has the smaller
    /// operation count per sample (see `estimate::paper::choose_auto`); `sparse` when the
    /// model has no dense form.
    #[default]
    Auto,
    /// Dense `(M + γhC + βh²K)⁻¹` per sub-step: the straightforward baseline.
    Dense,
    /// Exact map in modal coordinates; an error when the damping does not allow it.
    Modal,
    /// Sparse `M`, `C`, `K` and a sparse Cholesky factor of `M + γhC + βh²K`: cost per
    /// sample proportional to the non-zeros (the only one for models without a dense form).
    Sparse,
}

fn half() -> f64 {
    0.5
}
fn quarter() -> f64 {
    0.25
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, Default)]
#[serde(rename_all = "lowercase")]
pub enum EstimatorKind {
    /// The 1989 one-step least-squares estimator alone (the reference).
    Paper,
    /// Steady-state Kalman joint input–state estimator with smoothing, refined by output
    /// error (the default; the residual-force pipeline the live stepper runs online).
    #[default]
    Kalman,
    /// Maximum-likelihood output error on the exactly discretised model (`estimate::ml`):
    /// exact for laws linear in the state on data of any sub-steps; not yet reliable for
    /// `sign` laws (see ACCURACY.md).
    Ml,
}

impl std::str::FromStr for EstimatorKind {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        match s {
            "paper" => Ok(Self::Paper),
            "kalman" => Ok(Self::Kalman),
            "ml" => Ok(Self::Ml),
            other => Err(format!(
                "unknown estimator `{other}` (expected `ml`, `kalman` or `paper`)"
            )),
        }
    }
}

impl std::fmt::Display for EstimatorKind {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(match self {
            Self::Paper => "paper",
            Self::Kalman => "kalman",
            Self::Ml => "ml",
        })
    }
}

/// Channel weights `W` in Step III.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, Default)]
#[serde(rename_all = "kebab-case")]
pub enum Weighting {
    /// `W = diag(1/σ²)`: balances channels of different units (default).
    #[default]
    InverseVariance,
    /// `W = I`, as the paper's sample problem.
    Unit,
}

#[derive(Debug, Clone, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct EstimatorSpec {
    /// The estimator; absent: [`EstimatorSpec::kind_for`] chooses by the law.
    #[serde(default)]
    pub kind: Option<EstimatorKind>,
    #[serde(default)]
    pub weighting: Weighting,
    /// Maximum passes over the data (Step VI).
    #[serde(default = "default_passes")]
    pub passes: usize,
    /// Stop when every parameter moved less than this many standard errors in a pass.
    #[serde(default = "default_tol_se")]
    pub tolerance_std_errors: f64,
    /// …or changed the fitted connection force by less than this fraction of its RMS.
    #[serde(default = "default_tol_rel")]
    pub tolerance_relative: f64,
    /// Largest acceptable condition number of the parameter fit.
    #[serde(default = "default_max_cond")]
    pub max_condition: f64,
    /// Kalman: random-walk standard deviation of the residual force per sample, N. When
    /// absent it is derived from the data (see `estimate::kalman`).
    #[serde(default)]
    pub force_walk_std: Option<f64>,
    /// Tracking (see `track`): forgetting factor per sample of the tracked fit,
    /// `0 < λ ≤ 1`; memory `1/(1 − λ)` samples. 1 (default) tracks the growing window.
    #[serde(default = "default_forgetting")]
    pub forgetting: f64,
    /// Tracking: solve the tracked fit every this many samples; 0 (default) = a quarter of
    /// the memory when forgetting, else a twentieth of the record.
    #[serde(default)]
    pub track_every: usize,
    /// After the passes, refine the parameters by output-error (maximum-likelihood)
    /// Gauss–Newton from the residual-force estimate (see `estimate::output_error`).
    /// Default on for `kalman`; the `paper` estimator is left as the 1989 reference.
    #[serde(default = "default_true")]
    pub output_error: bool,
    /// Compute the Cramér–Rao lower bound of every parameter for the recording.
    #[serde(default = "default_true")]
    pub crlb: bool,
    /// Identify with a Craig–Bampton reduction of the model: the DOFs that carry the
    /// excitation, a station or a connection stay physical, the rest is represented by its
    /// static constraint modes plus this many lowest fixed-interface modes (see
    /// `model::reduce`). Absent (default): the full model. `simulate` always uses the full
    /// model.
    #[serde(default)]
    pub reduce_modes: Option<usize>,
    /// Identify the record in windows of this many contiguous samples, combined (see
    /// `session`): memory and time bounded however long the record. Absent (default): the
    /// whole record at once.
    #[serde(default)]
    pub window_samples: Option<usize>,
    /// Samples from one window's start to the next one's (default: `window_samples`,
    /// back-to-back windows; raised to it if below).
    #[serde(default)]
    pub window_every: Option<usize>,
}

fn default_forgetting() -> f64 {
    1.0
}

fn default_true() -> bool {
    true
}

fn default_passes() -> usize {
    10
}
fn default_tol_se() -> f64 {
    0.1
}
fn default_tol_rel() -> f64 {
    1e-8
}
fn default_max_cond() -> f64 {
    1e12
}

impl EstimatorSpec {
    /// The estimator to run: the setup's `kind`, or by default maximum likelihood for laws
    /// linear in the state (`u`, `v`, `a`, `const` terms only: its measured scope, where its
    /// errors hold, ACCURACY.md) and the Kalman pipeline for the others (`sign`, `u^3`,
    /// `gap`), which maximum likelihood refuses.
    pub fn kind_for(&self, connections: &[Connection]) -> EstimatorKind {
        self.kind.unwrap_or_else(|| {
            let linear = connections.iter().all(|c| {
                c.basis
                    .iter()
                    .all(|b| matches!(b, Basis::U | Basis::V | Basis::A | Basis::Const(_)))
            });
            if linear {
                EstimatorKind::Ml
            } else {
                EstimatorKind::Kalman
            }
        })
    }
}

impl Default for EstimatorSpec {
    fn default() -> Self {
        Self {
            kind: None,
            weighting: Weighting::default(),
            passes: default_passes(),
            tolerance_std_errors: default_tol_se(),
            tolerance_relative: default_tol_rel(),
            max_condition: default_max_cond(),
            force_walk_std: None,
            forgetting: default_forgetting(),
            track_every: 0,
            output_error: true,
            crlb: true,
            reduce_modes: None,
            window_samples: None,
            window_every: None,
        }
    }
}

// ---------------------------------------------------------------------------------------
// Validated setup
// ---------------------------------------------------------------------------------------

/// A connection basis function `v(δ, δ̇, δ̈)`; `f = Σ pⱼ·vⱼ`, positive when it resists.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Basis {
    /// `δ` — linear spring (parameter: stiffness, N/m).
    U,
    /// `δ³` — cubic spring (N/m³).
    U3,
    /// `δ̇` — viscous damper (N·s/m).
    V,
    /// `sign(δ̇)` — Coulomb friction (N); set-valued at δ̇ = 0 (sticking).
    SignV,
    /// `sign(δ)` — the paper's friction term (N); set-valued at δ = 0.
    SignU,
    /// `c` — constant force scaled by `c` (preload / offset).
    Const(f64),
    /// `δ̈` — added mass (kg).
    A,
    /// Dead band of half-width `g` (m): `δ − g` above `g`, `δ + g` below `−g`, else 0.
    Gap(f64),
}

impl Basis {
    /// Parse `u`, `u^3`, `v`, `sign(v)`, `sign(u)`, `const(100)`, `a`, `gap(0.001)`.
    pub fn parse(s: &str) -> Result<Self, String> {
        let t: String = s.chars().filter(|c| !c.is_whitespace()).collect();
        let arg = |prefix: &str| -> Option<Result<f64, String>> {
            t.strip_prefix(prefix)
                .and_then(|r| r.strip_suffix(')'))
                .map(|x| {
                    x.parse::<f64>()
                        .map_err(|_| format!("`{s}`: `{x}` is not a number"))
                })
        };
        Ok(match t.as_str() {
            "u" => Self::U,
            "u^3" | "u3" => Self::U3,
            "v" => Self::V,
            "sign(v)" => Self::SignV,
            "sign(u)" => Self::SignU,
            "a" => Self::A,
            _ => {
                if let Some(c) = arg("const(") {
                    let c = c?;
                    if !c.is_finite() || c == 0.0 || !(1e-12..=1e12).contains(&c.abs()) {
                        return Err(format!(
                            "`{s}`: the scale must be finite, non-zero and within 1e-12..1e12 in size (it multiplies a force parameter in N)"
                        ));
                    }
                    Self::Const(c)
                } else if let Some(g) = arg("gap(") {
                    let g = g?;
                    if !(g.is_finite() && g > 0.0) {
                        return Err(format!("`{s}`: the clearance must be positive"));
                    }
                    Self::Gap(g)
                } else {
                    return Err(format!(
                        "unknown basis function `{s}` (expected u, u^3, v, sign(v), sign(u), const(c), a, gap(g))"
                    ));
                }
            }
        })
    }

    /// Value of the basis function at a connection state. `sign(0)` is 0 here: the
    /// set-valued cases are handled by the simulator and excluded from the fit.
    #[inline]
    pub fn eval(&self, d: f64, dv: f64, da: f64) -> f64 {
        match *self {
            Self::U => d,
            Self::U3 => d * d * d,
            Self::V => dv,
            Self::SignV => sign0(dv),
            Self::SignU => sign0(d),
            Self::Const(c) => c,
            Self::A => da,
            Self::Gap(g) => {
                if d > g {
                    d - g
                } else if d < -g {
                    d + g
                } else {
                    0.0
                }
            }
        }
    }

    /// Terms that are linear in the state go into the model's K, C or M (Step VI).
    pub fn is_linear(&self) -> bool {
        matches!(self, Self::U | Self::V | Self::A)
    }

    /// Short label used in tables and metadata keys.
    pub fn label(&self) -> String {
        match *self {
            Self::U => "u".into(),
            Self::U3 => "u^3".into(),
            Self::V => "v".into(),
            Self::SignV => "sign(v)".into(),
            Self::SignU => "sign(u)".into(),
            Self::Const(c) => format!("const({c})"),
            Self::A => "a".into(),
            Self::Gap(g) => format!("gap({g})"),
        }
    }

    /// Unit of the parameter multiplying this basis.
    pub fn unit(&self) -> &'static str {
        match self {
            Self::U | Self::Gap(_) => "N/m",
            Self::U3 => "N/m^3",
            Self::V => "N s/m",
            Self::SignV | Self::SignU | Self::Const(_) => "N",
            Self::A => "kg",
        }
    }
}

#[inline]
fn sign0(x: f64) -> f64 {
    if x > 0.0 {
        1.0
    } else if x < 0.0 {
        -1.0
    } else {
        0.0
    }
}

/// A connection DOF: grounded (`b = None`) or between two DOFs.
#[derive(Debug, Clone)]
pub struct Connection {
    pub name: String,
    pub a: DofRef,
    pub b: Option<DofRef>,
    pub basis: Vec<Basis>,
    pub initial: Vec<f64>,
    pub truth: Option<Vec<f64>>,
}

#[derive(Debug, Clone)]
pub struct Sensor {
    pub name: String,
    pub dof: DofRef,
    pub quantity: Quantity,
    pub unit: String,
    pub noise_std: Option<f64>,
}

#[derive(Debug, Clone)]
pub struct Excitation {
    pub name: String,
    pub dof: DofRef,
    pub unit: String,
}

/// Newmark-β parameters, checked unconditionally stable (`γ ≥ ½`, `β ≥ (γ+½)²/4`... we
/// require the usual `2β ≥ γ ≥ ½`).
#[derive(Debug, Clone, Copy)]
pub struct Newmark {
    pub gamma: f64,
    pub beta: f64,
}

/// The validated setup.
#[derive(Debug, Clone)]
pub struct Setup {
    /// Where it came from (file path or "recording attachment"), for messages.
    pub origin: String,
    /// The exact TOML text, attached to recordings so a replay needs nothing else.
    pub toml_text: String,
    pub title: String,
    pub model: ModelSpec,
    pub excitation: Vec<Excitation>,
    pub sensors: Vec<Sensor>,
    pub connections: Vec<Connection>,
    /// Sample interval, s.
    pub dt_s: f64,
    pub newmark: Newmark,
    pub substeps: usize,
    /// Implementation of the per-sample step (`[integrator] step`).
    pub step: StepKind,
    pub estimator: EstimatorSpec,
    /// The checked matrices of `[model.matrix_market]`, when the model is external.
    pub external: Option<std::sync::Arc<crate::matrix_market::ExternalModel>>,
}

/// A TOML error as one line, `line L, column C: message` (the toml crate's own text quotes
/// the source over several lines).
fn one_line_toml_error(text: &str, e: &toml::de::Error) -> String {
    let message = e.message().trim().replace('\n', " ");
    match e.span() {
        Some(span) => {
            let before = text.get(..span.start).unwrap_or(text);
            let line = before.matches('\n').count() + 1;
            let column = before.rsplit('\n').next().map_or(0, |l| l.chars().count()) + 1;
            format!("TOML parse error at line {line}, column {column}: {message}")
        }
        None => format!("TOML parse error: {message}"),
    }
}

impl Setup {
    /// The setup with `[integrator] dt_s` set to `dt_s` (data at another rate than the
    /// setup's: the model is discretised at the data's), re-read so it is checked like any
    /// setup; every other line of the text is kept. The setup itself when the rate matches.
    pub fn at_rate(&self, dt_s: f64) -> Result<Setup, SetupError> {
        if (dt_s - self.dt_s).abs() <= 1e-9 * self.dt_s {
            return Ok(self.clone());
        }
        let mut text = String::new();
        let mut in_integrator = false;
        let mut replaced = false;
        for l in self.toml_text.lines() {
            let t = l.trim_start();
            if t.starts_with('[') {
                in_integrator = t.starts_with("[integrator]");
            }
            if in_integrator && !replaced && t.starts_with("dt_s") {
                text.push_str(&format!("dt_s = {dt_s:e}\n"));
                replaced = true;
            } else {
                text.push_str(l);
                text.push('\n');
            }
        }
        Setup::from_toml_with_model_files(
            &text,
            &format!("{} at dt_s = {dt_s:e}", self.origin),
            self.model_files(),
        )
    }

    /// The windows the record is identified in (`[estimator] window_samples`,
    /// `window_every`), if any.
    pub fn window_spec(&self) -> Option<crate::session::WindowSpec> {
        let w = self.estimator.window_samples?;
        Some(crate::session::WindowSpec::new(
            w,
            self.estimator.window_every.unwrap_or(w),
        ))
    }

    /// The setup with `[estimator] window_samples` and `window_every` set to `spec`
    /// (re-read and checked; every other line kept), so that a recording whose attached
    /// setup carries them replays in the same windows.
    pub fn with_windows(&self, spec: crate::session::WindowSpec) -> Result<Setup, SetupError> {
        let keys = [
            format!("window_samples = {}", spec.samples),
            format!("window_every = {}", spec.every),
        ];
        let mut text = String::new();
        let mut in_estimator = false;
        let mut placed = false;
        for l in self.toml_text.lines() {
            let t = l.trim_start();
            if t.starts_with('[') {
                in_estimator = t.starts_with("[estimator]");
            }
            if in_estimator && (t.starts_with("window_samples") || t.starts_with("window_every")) {
                continue;
            }
            text.push_str(l);
            text.push('\n');
            if in_estimator && !placed && t.starts_with("[estimator]") {
                for k in &keys {
                    text.push_str(k);
                    text.push('\n');
                }
                placed = true;
            }
        }
        if !placed {
            text.push_str("\n[estimator]\n");
            for k in &keys {
                text.push_str(k);
                text.push('\n');
            }
        }
        Setup::from_toml_with_model_files(&text, &self.origin, self.model_files())
    }

    pub fn from_file(path: &Path) -> Result<Self, SetupError> {
        let text =
            crate::io::read_text_capped(path, crate::io::MAX_SETUP_BYTES).map_err(|source| {
                SetupError::Io {
                    path: path.to_path_buf(),
                    source,
                }
            })?;
        Self::from_toml(&text, &path.display().to_string())
    }

    pub fn from_toml(text: &str, origin: &str) -> Result<Self, SetupError> {
        Self::from_toml_with_model_files(text, origin, None)
    }

    /// [`Setup::from_toml`] with the text of the `[model.matrix_market]` files given
    /// (`files`: those a recording carries, or the ones a setup was already read with)
    /// instead of read from the paths the setup names; `None`: read them. Ignored by a
    /// setup without `[model.matrix_market]`.
    pub fn from_toml_with_model_files(
        text: &str,
        origin: &str,
        files: Option<&crate::matrix_market::ModelFiles>,
    ) -> Result<Self, SetupError> {
        let raw: SetupFile = toml::from_str(text).map_err(|e| SetupError::Parse {
            origin: origin.to_string(),
            message: one_line_toml_error(text, &e),
        })?;
        validate(raw, text, origin, files)
    }

    /// The text of the external model's files, if the model is external.
    pub fn model_files(&self) -> Option<&crate::matrix_market::ModelFiles> {
        self.external.as_deref().map(|e| &e.sources)
    }

    /// Total number of connection parameters.
    pub fn n_params(&self) -> usize {
        self.connections.iter().map(|c| c.basis.len()).sum()
    }

    /// The basis function of every parameter, in parameter order (as [`Setup::param_keys`]).
    pub fn param_basis(&self) -> Vec<Basis> {
        self.connections
            .iter()
            .flat_map(|c| c.basis.iter().copied())
            .collect()
    }

    /// `connection.basis` labels, in parameter order.
    pub fn param_keys(&self) -> Vec<String> {
        self.connections
            .iter()
            .flat_map(|c| {
                c.basis
                    .iter()
                    .map(move |b| format!("{}.{}", c.name, b.label()))
            })
            .collect()
    }

    pub fn initial_params(&self) -> Vec<f64> {
        self.connections
            .iter()
            .flat_map(|c| c.initial.iter().copied())
            .collect()
    }

    pub fn truth_params(&self) -> Option<Vec<f64>> {
        let mut out = Vec::new();
        for c in &self.connections {
            out.extend_from_slice(c.truth.as_ref()?);
        }
        Some(out)
    }
}

/// The key the value of `model.{what}[i]` was written under: `k`, `c` and `value` are all
/// accepted (serde aliases, which do not say which one was read), and a message should name
/// the one the user wrote. Read from the text again, on the error path only.
fn link_value_key(text: &str, what: &str, i: usize) -> &'static str {
    let table: toml::Table = toml::from_str(text).unwrap_or_default();
    let link = table
        .get("model")
        .and_then(|m| m.get(what))
        .and_then(|l| l.get(i));
    ["k", "c", "value"]
        .into_iter()
        .find(|k| link.is_some_and(|l| l.get(k).is_some()))
        .unwrap_or("value")
}

fn validate(
    raw: SetupFile,
    text: &str,
    origin: &str,
    files: Option<&crate::matrix_market::ModelFiles>,
) -> Result<Setup, SetupError> {
    let bad = |key: String, message: String| SetupError::Invalid {
        origin: origin.to_string(),
        key,
        message,
    };
    // A number that must be finite and ≥ 0: one wording, naming the key and the value read
    // (a NaN fails every comparison, so "must be ≥ 0" alone would not say what was wrong).
    let non_negative = |key: String, v: f64| -> Result<(), SetupError> {
        if v.is_finite() && v >= 0.0 {
            Ok(())
        } else {
            Err(bad(key, format!("must be ≥ 0, got {v}")))
        }
    };
    let m = &raw.model;
    let external = match &m.matrix_market {
        None => None,
        Some(mm) => {
            let extra = [
                ("nodes", m.nodes.is_empty()),
                ("beams", m.beams.is_empty()),
                ("masses", m.masses.is_empty()),
                ("springs", m.springs.is_empty()),
                ("dashpots", m.dashpots.is_empty()),
                ("hinges", m.hinges.is_empty()),
                ("supports", m.supports.is_empty()),
            ];
            if let Some((k, _)) = extra.iter().find(|(_, empty)| !empty) {
                return Err(bad(
                    format!("model.{k}"),
                    "not allowed with model.matrix_market: put it in the FE model (only model.rayleigh may be added)".into(),
                ));
            }
            // Relative paths are relative to the directory of the setup's origin.
            let base = Path::new(origin).parent().unwrap_or(Path::new(""));
            let at = |p: &Path| base.join(p);
            let (mass, stiffness, dof_map) = (at(&mm.mass), at(&mm.stiffness), at(&mm.dof_map));
            let damping = mm.damping.as_deref().map(at);
            let ext = match files {
                None => crate::matrix_market::ExternalModel::load(
                    &mass,
                    &stiffness,
                    damping.as_deref(),
                    &dof_map,
                )
                .map_err(|error| SetupError::MatrixMarket {
                    origin: origin.to_string(),
                    error,
                }),
                // Files a recording carries: messages name the attachment (the paths beside
                // the recording were not read).
                Some(f) => {
                    let named = |key: &str, p: &Path| {
                        PathBuf::from(format!(
                            "attachment {}{key} ({})",
                            crate::io::mcap::MODEL_FILE_ATTACHMENT_PREFIX,
                            p.display()
                        ))
                    };
                    crate::matrix_market::ExternalModel::from_files(
                        f.clone(),
                        &named("mass", &mm.mass),
                        &named("stiffness", &mm.stiffness),
                        mm.damping
                            .as_deref()
                            .map(|d| named("damping", d))
                            .as_deref(),
                        &named("dof_map", &mm.dof_map),
                    )
                    .map_err(|error| SetupError::AttachedModel {
                        origin: origin.to_string(),
                        error,
                    })
                }
            }?;
            Some(std::sync::Arc::new(ext))
        }
    };
    if external.is_none() && m.nodes.is_empty() {
        return Err(bad(
            "model.nodes".into(),
            "give the nodes (or an external model in model.matrix_market)".into(),
        ));
    }
    // Nodes: declared ones and interior ones generated by beams.
    let mut node_ids: BTreeSet<u32> = BTreeSet::new();
    if let Some(ext) = &external {
        node_ids.extend(ext.dofs.iter().map(|d| d.node));
    }
    for (i, n) in m.nodes.iter().enumerate() {
        if !n.x.is_finite() {
            return Err(bad(
                format!("model.nodes[{i}].x"),
                format!("must be finite, got {}", n.x),
            ));
        }
        if !node_ids.insert(n.id) {
            return Err(bad(
                format!("model.nodes[{i}].id"),
                format!("node {} declared twice", n.id),
            ));
        }
    }
    let declared = node_ids.clone();
    for (i, b) in m.beams.iter().enumerate() {
        let key = |f: &str| format!("model.beams[{i}].{f}");
        for (f, id) in [("from", b.from), ("to", b.to)] {
            if !declared.contains(&id) {
                return Err(bad(
                    key(f),
                    format!("node {id} is not declared in model.nodes"),
                ));
            }
        }
        if b.from == b.to {
            return Err(bad(
                key("to"),
                "a beam needs two different end nodes".into(),
            ));
        }
        if b.elements == 0 {
            return Err(bad(key("elements"), "must be at least 1".into()));
        }
        if b.interior_ids.len() != b.elements - 1 {
            return Err(bad(
                key("interior_ids"),
                format!(
                    "{} elements need {} interior node ids, got {}",
                    b.elements,
                    b.elements - 1,
                    b.interior_ids.len()
                ),
            ));
        }
        for id in &b.interior_ids {
            if !node_ids.insert(*id) {
                return Err(bad(
                    key("interior_ids"),
                    format!("node id {id} is already used"),
                ));
            }
        }
        if !(b.ei.is_finite() && b.ei > 0.0) {
            return Err(bad(key("ei"), format!("must be positive, got {}", b.ei)));
        }
        non_negative(key("mass_per_length"), b.mass_per_length)?;
    }
    let xs: BTreeMap<u32, f64> = m.nodes.iter().map(|n| (n.id, n.x)).collect();
    for (i, b) in m.beams.iter().enumerate() {
        if xs[&b.from] == xs[&b.to] {
            return Err(bad(
                format!("model.beams[{i}]"),
                "end nodes are at the same position (zero length)".into(),
            ));
        }
    }
    let check_node = |key: String, id: u32| -> Result<(), SetupError> {
        if node_ids.contains(&id) {
            Ok(())
        } else {
            Err(bad(key, format!("node {id} does not exist")))
        }
    };
    for (i, ms) in m.masses.iter().enumerate() {
        check_node(format!("model.masses[{i}].node"), ms.node)?;
        non_negative(format!("model.masses[{i}].mass"), ms.mass)?;
        non_negative(format!("model.masses[{i}].inertia"), ms.inertia)?;
    }
    for (what, links) in [("springs", &m.springs), ("dashpots", &m.dashpots)] {
        for (i, l) in links.iter().enumerate() {
            let key = format!("model.{what}[{i}]");
            match (&l.dof, &l.between) {
                (Some(d), None) => check_node(key.clone(), d.node)?,
                (None, Some([a, b])) => {
                    check_node(key.clone(), a.node)?;
                    check_node(key.clone(), b.node)?;
                }
                _ => return Err(bad(key, "give exactly one of `dof` or `between`".into())),
            }
            if !(l.value.is_finite() && l.value >= 0.0) {
                let written = link_value_key(text, what, i);
                return Err(bad(
                    format!("{key}.{written}"),
                    format!("must be ≥ 0, got {}", l.value),
                ));
            }
        }
    }
    for (i, h) in m.hinges.iter().enumerate() {
        check_node(format!("model.hinges[{i}]"), *h)?;
    }
    for (i, s) in m.supports.iter().enumerate() {
        check_node(format!("model.supports[{i}].node"), s.node)?;
    }
    if let Some(r) = &m.rayleigh {
        non_negative("model.rayleigh.alpha".into(), r.alpha)?;
        non_negative("model.rayleigh.beta".into(), r.beta)?;
    }

    let hinge_set: BTreeSet<u32> = m.hinges.iter().copied().collect();
    let check_dof = |key: String, d: &DofRef| -> Result<(), SetupError> {
        check_node(key.clone(), d.node)?;
        if let Some(ext) = &external {
            if !ext.dofs.contains(d) {
                return Err(bad(
                    key,
                    format!("{d} is not in the DOF map {}", ext.dof_map.display()),
                ));
            }
            return Ok(());
        }
        if !matches!(d.dir, Dir::W | Dir::Rz) {
            return Err(bad(
                key,
                format!("{d}: a beam model has only `w` and `rz` DOFs"),
            ));
        }
        if d.dir == Dir::Rz && hinge_set.contains(&d.node) {
            return Err(bad(
                key,
                format!(
                    "{d}: a hinge node has one rotation per beam; refer to its translation instead"
                ),
            ));
        }
        Ok(())
    };

    let mut excitation = Vec::new();
    let mut names = BTreeSet::new();
    for (i, e) in raw.excitation.iter().enumerate() {
        check_dof(format!("excitation[{i}].dof"), &e.dof)?;
        if !names.insert(e.name.clone()) {
            return Err(bad(
                format!("excitation[{i}].name"),
                format!("`{}` used twice", e.name),
            ));
        }
        excitation.push(Excitation {
            name: e.name.clone(),
            dof: e.dof,
            unit: e.unit.clone(),
        });
    }
    if excitation.is_empty() {
        return Err(bad(
            "excitation".into(),
            "at least one excitation channel is needed".into(),
        ));
    }
    let mut sensors = Vec::new();
    for (i, s) in raw.sensors.iter().enumerate() {
        check_dof(format!("sensors[{i}].dof"), &s.dof)?;
        if !names.insert(s.name.clone()) {
            return Err(bad(
                format!("sensors[{i}].name"),
                format!("`{}` used twice", s.name),
            ));
        }
        if let Some(sd) = s.noise_std
            && !(sd.is_finite() && sd > 0.0)
        {
            return Err(bad(
                format!("sensors[{i}].noise_std"),
                format!("must be > 0, got {sd}"),
            ));
        }
        let unit = s.unit.clone().unwrap_or_else(|| {
            match s.quantity {
                Quantity::Displacement => "m",
                Quantity::Velocity => "m/s",
                Quantity::Acceleration => "m/s^2",
            }
            .to_string()
        });
        sensors.push(Sensor {
            name: s.name.clone(),
            dof: s.dof,
            quantity: s.quantity,
            unit,
            noise_std: s.noise_std,
        });
    }
    if sensors.is_empty() {
        return Err(bad(
            "sensors".into(),
            "at least one sensor channel is needed".into(),
        ));
    }
    let mut connections = Vec::new();
    for (i, c) in raw.connections.iter().enumerate() {
        let key = |f: &str| format!("connections[{i}].{f}");
        let (a, b) = match (&c.dof, &c.between) {
            (Some(d), None) => {
                check_dof(key("dof"), d)?;
                (*d, None)
            }
            (None, Some([a, b])) => {
                check_dof(key("between"), a)?;
                check_dof(key("between"), b)?;
                if a == b {
                    return Err(bad(key("between"), "the two DOFs must differ".into()));
                }
                (*a, Some(*b))
            }
            _ => {
                return Err(bad(
                    format!("connections[{i}]"),
                    "give exactly one of `dof` or `between`".into(),
                ));
            }
        };
        if c.basis.is_empty() {
            return Err(bad(
                key("basis"),
                "at least one basis function is needed".into(),
            ));
        }
        let mut basis = Vec::new();
        for (j, s) in c.basis.iter().enumerate() {
            basis
                .push(Basis::parse(s).map_err(|e| bad(format!("connections[{i}].basis[{j}]"), e))?);
        }
        let nb = basis.len();
        let initial = if c.initial.is_empty() {
            vec![0.0; nb]
        } else {
            c.initial.clone()
        };
        if initial.len() != nb {
            return Err(bad(
                key("initial"),
                format!(
                    "{} basis functions but {} initial values",
                    nb,
                    initial.len()
                ),
            ));
        }
        let truth = if c.truth.is_empty() {
            None
        } else if c.truth.len() != nb {
            return Err(bad(
                key("truth"),
                format!("{} basis functions but {} true values", nb, c.truth.len()),
            ));
        } else {
            Some(c.truth.clone())
        };
        for (field, values) in [("initial", &c.initial), ("truth", &c.truth)] {
            if let Some((j, v)) = values.iter().enumerate().find(|(_, v)| !v.is_finite()) {
                return Err(bad(
                    key(&format!("{field}[{j}]")),
                    format!("must be finite, got {v}"),
                ));
            }
        }
        if !names.insert(c.name.clone()) {
            return Err(bad(key("name"), format!("`{}` used twice", c.name)));
        }
        connections.push(Connection {
            name: c.name.clone(),
            a,
            b,
            basis,
            initial,
            truth,
        });
    }
    if connections.is_empty() {
        return Err(bad(
            "connections".into(),
            "at least one connection is needed".into(),
        ));
    }
    let it = &raw.integrator;
    if !(it.dt_s.is_finite() && it.dt_s > 0.0) {
        return Err(bad(
            "integrator.dt_s".into(),
            format!("must be > 0, got {}", it.dt_s),
        ));
    }
    if !(it.gamma >= 0.5
        && 2.0 * it.beta >= it.gamma
        && it.beta.is_finite()
        && it.gamma.is_finite())
    {
        return Err(bad(
            "integrator".into(),
            format!(
                "Newmark γ = {}, β = {} is not unconditionally stable (need 2β ≥ γ ≥ ½)",
                it.gamma, it.beta
            ),
        ));
    }
    if it.substeps == 0 || it.substeps > 4096 {
        return Err(bad(
            "integrator.substeps".into(),
            format!("must be in 1..=4096, got {}", it.substeps),
        ));
    }
    let est = &raw.estimator;
    if est.passes == 0 {
        return Err(bad("estimator.passes".into(), "must be at least 1".into()));
    }
    for (key, v, min_ok) in [
        (
            "estimator.tolerance_std_errors",
            est.tolerance_std_errors,
            0.0,
        ),
        ("estimator.tolerance_relative", est.tolerance_relative, 0.0),
        ("estimator.max_condition", est.max_condition, 1.0),
    ] {
        if !(v.is_finite() && v > min_ok) {
            return Err(bad(
                key.into(),
                format!("must be a finite number > {min_ok}, got {v}"),
            ));
        }
    }
    if let Some(q) = est.force_walk_std
        && !(q.is_finite() && q > 0.0)
    {
        return Err(bad(
            "estimator.force_walk_std".into(),
            format!("must be > 0, got {q}"),
        ));
    }
    if let Some(w) = est.window_samples
        && w < crate::session::MIN_WINDOW_SAMPLES
    {
        return Err(bad(
            "estimator.window_samples".into(),
            format!(
                "must be at least {} (the identification's stiffness scan alone reads 200), got {w}",
                crate::session::MIN_WINDOW_SAMPLES
            ),
        ));
    }
    if est.window_every.is_some() && est.window_samples.is_none() {
        return Err(bad(
            "estimator.window_every".into(),
            "needs `window_samples` (the window it is the stride of)".into(),
        ));
    }
    if !(est.forgetting > 0.0 && est.forgetting <= 1.0) {
        return Err(bad(
            "estimator.forgetting".into(),
            format!(
                "must be in (0, 1] (memory 1/(1 − λ) samples), got {}",
                est.forgetting
            ),
        ));
    }
    Ok(Setup {
        origin: origin.to_string(),
        toml_text: text.to_string(),
        title: raw.title.clone(),
        model: raw.model.clone(),
        excitation,
        sensors,
        connections,
        dt_s: it.dt_s,
        newmark: Newmark {
            gamma: it.gamma,
            beta: it.beta,
        },
        substeps: it.substeps,
        step: it.step,
        estimator: raw.estimator.clone(),
        external,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    pub(crate) const TINY: &str = r#"
[model]
nodes = [{ id = 1, x = 0.0 }]
masses = [{ node = 1, mass = 2.0 }]
springs = [{ dof = { node = 1, dir = "w" }, k = 100.0 }]
[[excitation]]
name = "f"
dof = { node = 1, dir = "w" }
[[sensors]]
name = "d"
dof = { node = 1, dir = "w" }
quantity = "displacement"
[[connections]]
name = "j"
dof = { node = 1, dir = "w" }
basis = ["u", "v"]
[integrator]
dt_s = 0.01
"#;

    #[test]
    fn extreme_or_non_finite_numbers_are_errors_naming_the_key() {
        let huge = TINY.replace(
            "basis = [\"u\", \"v\"]",
            "basis = [\"u\", \"const(1e308)\"]",
        );
        let e = Setup::from_toml(&huge, "tiny").unwrap_err().to_string();
        assert!(e.contains("const(1e308)") && e.contains("1e12"), "{e}");
        for (key, v) in [
            ("max_condition", "nan"),
            ("tolerance_relative", "inf"),
            ("tolerance_std_errors", "-1.0"),
        ] {
            let text = format!("{TINY}[estimator]\n{key} = {v}\n");
            let e = Setup::from_toml(&text, "tiny").unwrap_err().to_string();
            assert!(e.contains(&format!("estimator.{key}")), "{key}: {e}");
        }
    }

    /// A NaN is reported at the key and element the user wrote, with the value read (the
    /// reviewer's cases: `connections[0]: value 2 is not finite` for `truth[0]`, a spring's
    /// `k` reported as `value`, a NaN mass as "must be ≥ 0" alone).
    #[test]
    fn non_finite_numbers_name_the_key_as_written_and_the_value() {
        let cases = [
            (
                "basis = [\"u\", \"v\"]",
                "basis = [\"u\", \"v\"]\ntruth = [nan, 4.0]",
                "connections[0].truth[0]: must be finite, got NaN",
            ),
            (
                "basis = [\"u\", \"v\"]",
                "basis = [\"u\", \"v\"]\ninitial = [1.0, inf]",
                "connections[0].initial[1]: must be finite, got inf",
            ),
            (
                "k = 100.0",
                "k = nan",
                "model.springs[0].k: must be ≥ 0, got NaN",
            ),
            (
                "k = 100.0",
                "value = -1.0",
                "model.springs[0].value: must be ≥ 0, got -1",
            ),
            (
                "mass = 2.0",
                "mass = nan",
                "model.masses[0].mass: must be ≥ 0, got NaN",
            ),
            (
                "mass = 2.0",
                "mass = 2.0, inertia = -inf",
                "model.masses[0].inertia: must be ≥ 0, got -inf",
            ),
            (
                "x = 0.0",
                "x = nan",
                "model.nodes[0].x: must be finite, got NaN",
            ),
        ];
        for (from, to, want) in cases {
            let e = Setup::from_toml(&TINY.replace(from, to), "tiny")
                .unwrap_err()
                .to_string();
            assert!(e.contains(want), "{to}: {e}");
        }
        let rayleigh = format!("{TINY}[model.rayleigh]\nbeta = nan\n");
        let e = Setup::from_toml(&rayleigh, "tiny").unwrap_err().to_string();
        assert!(
            e.contains("model.rayleigh.beta: must be ≥ 0, got NaN"),
            "{e}"
        );
    }

    #[test]
    fn parses_a_minimal_setup() {
        let s = Setup::from_toml(TINY, "tiny").unwrap();
        assert_eq!(s.n_params(), 2);
        assert_eq!(s.param_keys(), vec!["j.u", "j.v"]);
        assert_eq!(s.estimator.kind, None);
        // `u, v` is linear in the state: the default is maximum likelihood.
        assert_eq!(s.estimator.kind_for(&s.connections), EstimatorKind::Ml);
    }

    /// The window keys are read (the stride defaults to, and is raised to, the window);
    /// too small a window is an error naming the key, and a stride without a window too.
    #[test]
    fn window_keys_are_read_and_checked() {
        use crate::session::WindowSpec;
        let s = Setup::from_toml(TINY, "tiny").unwrap();
        assert_eq!(s.window_spec(), None);
        let with = |keys: &str| Setup::from_toml(&format!("{TINY}[estimator]\n{keys}\n"), "tiny");
        let w = with("window_samples = 5000\nwindow_every = 512000").unwrap();
        assert_eq!(w.window_spec(), Some(WindowSpec::new(5000, 512_000)));
        let back_to_back = with("window_samples = 800").unwrap();
        assert_eq!(back_to_back.window_spec(), Some(WindowSpec::new(800, 800)));
        let raised = with("window_samples = 800\nwindow_every = 100").unwrap();
        assert_eq!(raised.window_spec().unwrap().every, 800);
        // Written into the text (with or without an `[estimator]` section, replacing
        // earlier keys), as `jointid live` attaches them to its recording.
        let written = s.with_windows(WindowSpec::new(5000, 512_000)).unwrap();
        assert_eq!(written.window_spec(), Some(WindowSpec::new(5000, 512_000)));
        let again = written.with_windows(WindowSpec::new(800, 100)).unwrap();
        assert_eq!(again.window_spec(), Some(WindowSpec::new(800, 800)));
        assert_eq!(again.toml_text.matches("window_samples").count(), 1);
        let s2 = with("passes = 3").unwrap();
        let w2 = s2.with_windows(WindowSpec::new(1000, 2000)).unwrap();
        assert_eq!(w2.estimator.passes, 3);
        assert_eq!(w2.window_spec(), Some(WindowSpec::new(1000, 2000)));
        let small = format!("{TINY}[estimator]\nwindow_samples = 10\n");
        let e = Setup::from_toml(&small, "tiny").unwrap_err().to_string();
        assert!(e.contains("estimator.window_samples"), "{e}");
        let stride = format!("{TINY}[estimator]\nwindow_every = 1000\n");
        let e = Setup::from_toml(&stride, "tiny").unwrap_err().to_string();
        assert!(e.contains("estimator.window_every"), "{e}");
    }

    #[test]
    fn unknown_key_is_named() {
        let text = TINY.replace("dt_s = 0.01", "dt_s = 0.01\ndtt = 3");
        let e = Setup::from_toml(&text, "tiny").unwrap_err().to_string();
        assert!(e.contains("dtt"), "{e}");
    }

    #[test]
    fn bad_basis_and_unstable_newmark_are_named() {
        let e = Setup::from_toml(&TINY.replace("\"v\"]", "\"w\"]"), "t")
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("connections[0].basis[1]") && e.contains("`w`"),
            "{e}"
        );
        let e = Setup::from_toml(&TINY.replace("dt_s = 0.01", "dt_s = 0.01\nbeta = 0.1"), "t")
            .unwrap_err()
            .to_string();
        assert!(e.contains("not unconditionally stable"), "{e}");
    }

    #[test]
    fn basis_parse_and_eval() {
        assert_eq!(Basis::parse("const(100)").unwrap(), Basis::Const(100.0));
        assert_eq!(Basis::parse(" sign( v ) ").unwrap(), Basis::SignV);
        assert!(Basis::parse("const(x)").is_err());
        assert_eq!(Basis::Gap(0.1).eval(0.3, 0.0, 0.0), 0.3 - 0.1);
        assert_eq!(Basis::Gap(0.1).eval(0.05, 0.0, 0.0), 0.0);
        assert_eq!(Basis::U3.eval(2.0, 0.0, 0.0), 8.0);
    }

    /// A setup whose model files come from a recording: the intact files load, and a parse
    /// error names the attachment (not a path beside the recording, which was never read),
    /// says how to use files on disk, and drops the hint about relative paths, which is for
    /// files read from disk.
    #[test]
    fn a_bad_attached_model_file_is_named_as_the_attachment() {
        let dir = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("recordings/two-beam-mm");
        let origin = dir.join("setup.toml");
        let text = std::fs::read_to_string(&origin).unwrap();
        let setup = Setup::from_toml(&text, &origin.display().to_string()).unwrap();
        let mut files = setup.model_files().unwrap().clone();
        let fine = Setup::from_toml_with_model_files(
            &text,
            "rec.mcap (attached setup.toml)",
            Some(&files),
        );
        assert!(fine.is_ok(), "{:?}", fine.err());
        files.stiffness = files
            .stiffness
            .replacen("%%MatrixMarket", "%%MatrixMarkt", 1);
        let e = Setup::from_toml_with_model_files(
            &text,
            "rec.mcap (attached setup.toml)",
            Some(&files),
        )
        .unwrap_err()
        .to_string();
        assert!(
            e.contains("attachment model.matrix_market.stiffness (stiffness.mtx)")
                && e.contains("the recording carries")
                && !e.contains("relative to"),
            "{e}"
        );
    }
}
