//! The output contract: one Rust type per output topic, written by `replay --out` and by
//! `live --record` alike, its JSON Schema generated from the type (`schemars`), so the schema
//! in a recording and the messages under it cannot drift apart (every message type denies
//! unknown fields, and a test validates every message of a replay and of a live session
//! against its channel's schema).
//!
//! | topic | schema | one message per |
//! |---|---|---|
//! | `/jointid/residuals` | `jointid.Residuals` | sample (live: every `--record-residuals-every`-th) |
//! | `/jointid/states` | `jointid.ConnectionStates` | sample (replay) |
//! | `/jointid/predicted` | `jointid.PredictedResponse` | sample (replay): the identified model's response |
//! | `/jointid/parameters` | `jointid.Parameters` | pass (replay), online or batch refit (live) |
//! | `/jointid/track` | `jointid.Track` | tracking solve |
//! | `/jointid/diagnostics` | `jointid.Diagnostics` | pass, run summary, live progress |
//! | `/jointid/log` | `foxglove.Log` | note, warning or error (Foxglove's Log panel shows them) |
//!
//! Every message carries `version` ([`CONTRACT_VERSION`], raised on any incompatible change)
//! and `timestamp` as Foxglove time `{sec, nsec}` besides the `t_ns` integer. Numbers that
//! can be undefined (a condition number of a singular fit) are `null` rather than NaN,
//! which JSON cannot carry.

use std::collections::BTreeMap;

use schemars::JsonSchema;
use serde::{Deserialize, Serialize};
use serde_json::Value;

use crate::setup::Setup;

/// Version of the message types below and of the `--json` outputs.
pub const CONTRACT_VERSION: u32 = 1;

pub const PREDICTED_TOPIC: &str = "/jointid/predicted";
pub const LOG_TOPIC: &str = "/jointid/log";

/// Foxglove time: seconds and nanoseconds since the epoch of `t_ns`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct Time {
    pub sec: u64,
    pub nsec: u32,
}

impl Time {
    pub fn from_ns(t_ns: u64) -> Self {
        Time {
            sec: t_ns / 1_000_000_000,
            nsec: (t_ns % 1_000_000_000) as u32,
        }
    }
}

/// Which command wrote the message.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, JsonSchema)]
#[serde(rename_all = "snake_case")]
pub enum Source {
    Replay,
    Live,
}

/// `None` for NaN and infinities (JSON has no such numbers).
pub fn finite(x: f64) -> Option<f64> {
    x.is_finite().then_some(x)
}

/// Residual forces at one sample. Sign convention: `residual = force − f̂`, N; `force` is the
/// total connection force, positive resisting the deformation.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields)]
#[schemars(title = "jointid.Residuals")]
pub struct ResidualsMsg {
    pub version: u32,
    pub timestamp: Time,
    pub sample: u64,
    pub t_ns: u64,
    pub source: Source,
    /// Pass of the identification that produced it (live: 0, the online filter).
    pub pass: usize,
    pub connections: Vec<String>,
    /// `R = f − f̂` per connection, N.
    pub residual: Vec<f64>,
    /// Total connection force `f` per connection, N, positive resisting.
    pub force: Vec<f64>,
}

/// Connection deformations at one sample.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields)]
#[schemars(title = "jointid.ConnectionStates")]
pub struct StatesMsg {
    pub version: u32,
    pub timestamp: Time,
    pub sample: u64,
    pub t_ns: u64,
    pub source: Source,
    pub pass: usize,
    pub connections: Vec<String>,
    /// Deformation δ, m.
    pub delta: Vec<f64>,
    /// Rate δ̇, m/s.
    pub delta_v: Vec<f64>,
    /// Acceleration δ̈, m/s².
    pub delta_a: Vec<f64>,
}

/// The response the identified model predicts from the measured excitation (simulation),
/// in the setup's sensor order and units.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields)]
#[schemars(title = "jointid.PredictedResponse")]
pub struct PredictedMsg {
    pub version: u32,
    pub timestamp: Time,
    pub sample: u64,
    pub t_ns: u64,
    pub sensors: Vec<String>,
    pub values: Vec<f64>,
}

/// What a parameters message reports.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, JsonSchema)]
#[serde(rename_all = "snake_case")]
pub enum ParametersKind {
    /// The result of one identification pass (replay).
    Pass,
    /// The live online fit.
    Online,
    /// Live: the combination of the windows identified so far (final: of all).
    Batch,
}

/// One connection parameter.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct ParameterMsg {
    /// `connection.basis`, e.g. `joint6.u`.
    pub key: String,
    pub connection: String,
    pub basis: String,
    /// SI unit of the parameter (force per basis unit).
    pub unit: String,
    pub value: f64,
    /// Standard error; `null` when it could not be computed.
    pub std_error: Option<f64>,
    /// 95 % interval `value ± 1.96 std_error`.
    pub ci95: Option<[f64; 2]>,
    /// Cramér–Rao lower bound of the standard error, when computed.
    pub crlb: Option<f64>,
    /// Standard error of the residual-force fit treating samples as independent (for
    /// comparison; the reported one accounts for their correlation), when computed.
    pub std_error_ols: Option<f64>,
    /// The true value, when the recording holds it (simulated tests).
    pub truth: Option<f64>,
}

/// Parameter estimates.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields)]
#[schemars(title = "jointid.Parameters")]
pub struct ParametersMsg {
    pub version: u32,
    pub timestamp: Time,
    /// Last sample the estimate uses.
    pub sample: u64,
    pub t_ns: u64,
    pub source: Source,
    pub kind: ParametersKind,
    /// Pass number (kind `pass`).
    pub pass: Option<usize>,
    /// The run's final answer.
    #[serde(rename = "final")]
    pub is_final: bool,
    /// With `final`: whether the passes converged.
    pub converged: Option<bool>,
    pub parameters: Vec<ParameterMsg>,
}

/// What names a parameter in the messages: its key, connection, basis function and unit,
/// and the setup's true value when the setup states one for every connection.
#[derive(Debug, Clone, PartialEq)]
pub struct ParameterLabel {
    pub key: String,
    pub connection: String,
    pub basis: String,
    pub unit: String,
    pub truth: Option<f64>,
}

impl ParameterLabel {
    /// The message for an estimate of this parameter (`std_error` may be non-finite: then
    /// it and the interval are `null`).
    pub fn message(&self, value: f64, std_error: f64) -> ParameterMsg {
        let std_error = finite(std_error);
        ParameterMsg {
            key: self.key.clone(),
            connection: self.connection.clone(),
            basis: self.basis.clone(),
            unit: self.unit.clone(),
            value,
            std_error,
            ci95: std_error.map(|s| [value - 1.96 * s, value + 1.96 * s]),
            crlb: None,
            std_error_ols: None,
            truth: self.truth,
        }
    }
}

/// The labels of every parameter of a setup, in setup order.
pub fn parameter_labels(setup: &Setup) -> Vec<ParameterLabel> {
    let truth = setup.truth_params();
    setup
        .connections
        .iter()
        .flat_map(|c| c.basis.iter().map(move |b| (c, b)))
        .enumerate()
        .map(|(k, (c, b))| ParameterLabel {
            key: format!("{}.{}", c.name, b.label()),
            connection: c.name.clone(),
            basis: b.label(),
            unit: b.unit().to_string(),
            truth: truth.as_ref().and_then(|t| t.get(k).copied()),
        })
        .collect()
}

/// Messages for estimates known by key (the live session's online and final values),
/// labelled from `labels`; a key the setup does not have keeps only its key.
pub fn parameters_by_key(
    labels: &[ParameterLabel],
    estimates: &[crate::pipeline::live::LiveParameter],
) -> Vec<ParameterMsg> {
    estimates
        .iter()
        .map(|p| {
            let label = labels
                .iter()
                .find(|l| l.key == p.key)
                .cloned()
                .unwrap_or_else(|| ParameterLabel {
                    key: p.key.clone(),
                    connection: String::new(),
                    basis: String::new(),
                    unit: String::new(),
                    truth: None,
                });
            label.message(p.value, p.std_error)
        })
        .collect()
}

/// Parameters from an identification's estimates.
pub fn parameters_from_estimates(
    estimates: &[crate::identify::ParameterEstimate],
) -> Vec<ParameterMsg> {
    estimates
        .iter()
        .map(|p| {
            let std_error = finite(p.std_error);
            ParameterMsg {
                key: format!("{}.{}", p.connection, p.basis),
                connection: p.connection.clone(),
                basis: p.basis.clone(),
                unit: p.unit.clone(),
                value: p.value,
                std_error,
                ci95: std_error.map(|_| p.ci95),
                crlb: p.crlb.and_then(finite),
                std_error_ols: p.std_error_ols.and_then(finite),
                truth: p.truth,
            }
        })
        .collect()
}

/// One tracked value.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct TrackedValueMsg {
    pub value: f64,
    pub std_error: Option<f64>,
}

/// The tracked (forgetting-factor) parameters at one sample.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields)]
#[schemars(title = "jointid.Track")]
pub struct TrackMsg {
    pub version: u32,
    pub timestamp: Time,
    pub sample: u64,
    pub t_ns: u64,
    /// Forgetting factor per sample.
    pub forgetting: f64,
    pub keys: Vec<String>,
    /// One per key; `null` where the connection's fit could not be solved.
    pub parameters: Vec<Option<TrackedValueMsg>>,
    pub unsolved: Vec<String>,
}

/// Figures of one identification pass.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct PassDiagnostics {
    pub pass: usize,
    pub estimator: String,
    /// Rank of the weighted sensitivity `W½ S`.
    pub sensitivity_rank: usize,
    pub sensitivity_condition: Option<f64>,
    /// Largest singular value of `S`: output change per newton of residual force.
    pub sensitivity_gain: Option<f64>,
    pub error_spectral_radius: Option<f64>,
    /// Estimator tuning figures (Kalman noise levels, lag, …).
    pub tuning: BTreeMap<String, Option<f64>>,
    pub warnings: Vec<String>,
    /// Per connection: condition number of the column-scaled fit.
    pub fit_condition: Vec<Option<f64>>,
    /// Per connection: RMS of the fit residual, N.
    pub fit_rms_residual_n: Vec<Option<f64>>,
    pub rows_used: Vec<usize>,
    pub rows_excluded_stuck: Vec<usize>,
    /// Largest |Δp|/se against the previous pass.
    pub max_change_std_errors: Option<f64>,
}

impl PassDiagnostics {
    pub fn from_pass(p: &crate::identify::PassReport) -> Self {
        let d = &p.diagnostics;
        PassDiagnostics {
            pass: p.pass,
            estimator: d.estimator.clone(),
            sensitivity_rank: d.sensitivity_rank,
            sensitivity_condition: finite(d.sensitivity_condition),
            sensitivity_gain: finite(d.sensitivity_gain),
            error_spectral_radius: d.error_spectral_radius.and_then(finite),
            tuning: d
                .tuning
                .iter()
                .map(|(k, v)| (k.clone(), finite(*v)))
                .collect(),
            warnings: d.warnings.clone(),
            fit_condition: p.fit_condition.iter().map(|&x| finite(x)).collect(),
            fit_rms_residual_n: p.fit_rms_residual.iter().map(|&x| finite(x)).collect(),
            rows_used: p.rows_used.clone(),
            rows_excluded_stuck: p.rows_excluded_stuck.clone(),
            max_change_std_errors: p.max_change_std_errors.and_then(finite),
        }
    }
}

/// How a run ended.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct RunSummary {
    pub converged: bool,
    pub stop_reason: String,
    pub failure: Option<String>,
    pub input_warnings: Vec<String>,
    pub input_error: Option<String>,
    /// Reasons the identified model does not explain the data (what `--strict` refuses on).
    pub inadequacy: Vec<String>,
}

/// Progress of a live session.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct LiveDiagnostics {
    pub samples: u64,
    pub first_sample: Option<u64>,
    pub last_sample: Option<u64>,
    pub rate_hz: Option<f64>,
    pub elapsed_s: Option<f64>,
    pub samples_per_s: Option<f64>,
    pub real_time_factor: Option<f64>,
    pub latency_count: u64,
    pub latency_median_us: Option<f64>,
    pub latency_p99_us: Option<f64>,
    pub latency_max_us: Option<f64>,
    pub missing_samples: u64,
    pub gaps: u64,
    pub late_or_duplicate: u64,
    pub unpaired: u64,
    pub non_finite: u64,
    pub restarts: u64,
    pub segments: u64,
    pub transport_drops: u64,
    pub outputs_dropped: u64,
    pub viewer_discards: u64,
    pub refits: u64,
    pub warnings: Vec<String>,
    /// Empty while running; why the session ended once it has.
    pub ended: String,
    pub error: Option<String>,
}

impl LiveDiagnostics {
    pub fn from_report(r: &crate::pipeline::live::LiveReport) -> Self {
        let f = &r.faults;
        LiveDiagnostics {
            samples: r.samples,
            first_sample: r.first_sample,
            last_sample: r.last_sample,
            rate_hz: finite(r.rate_hz),
            elapsed_s: finite(r.elapsed_s),
            samples_per_s: finite(r.samples_per_s),
            real_time_factor: finite(r.real_time_factor),
            latency_count: r.latency.count,
            latency_median_us: finite(r.latency.median_us),
            latency_p99_us: finite(r.latency.p99_us),
            latency_max_us: finite(r.latency.max_us),
            missing_samples: f.missing_samples,
            gaps: f.gaps,
            late_or_duplicate: f.late_or_duplicate,
            unpaired: f.unpaired,
            non_finite: f.non_finite,
            restarts: f.restarts,
            segments: f.segments,
            transport_drops: f.transport_drops,
            outputs_dropped: r.outputs_dropped,
            viewer_discards: r.viewer_discards,
            refits: r.refits,
            warnings: r.warnings.clone(),
            ended: r.ended.clone(),
            error: r.error.clone(),
        }
    }
}

/// What a diagnostics message holds.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, JsonSchema)]
#[serde(rename_all = "snake_case")]
pub enum DiagnosticsKind {
    Pass,
    Summary,
    Live,
}

/// Diagnostics: exactly one of `pass`, `summary`, `live` is set, as `kind` says.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields)]
#[schemars(title = "jointid.Diagnostics")]
pub struct DiagnosticsMsg {
    pub version: u32,
    pub timestamp: Time,
    pub t_ns: u64,
    pub source: Source,
    pub kind: DiagnosticsKind,
    pub pass: Option<PassDiagnostics>,
    pub summary: Option<RunSummary>,
    pub live: Option<LiveDiagnostics>,
}

/// Foxglove's log levels.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum LogLevel {
    Info = 2,
    Warning = 3,
    Error = 4,
}

/// A note, warning or error as Foxglove's `foxglove.Log` message (its schema exactly, so the
/// Log panel shows it).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields)]
#[schemars(title = "foxglove.Log")]
pub struct LogMsg {
    pub timestamp: Time,
    /// 1 debug, 2 info, 3 warning, 4 error, 5 fatal.
    #[schemars(range(min = 1, max = 5))]
    pub level: u8,
    pub message: String,
    /// The component that logged it (`jointid.replay`, `jointid.live`).
    pub name: String,
    pub file: String,
    pub line: u32,
}

impl LogMsg {
    pub fn new(t_ns: u64, level: LogLevel, name: &str, message: String) -> Self {
        LogMsg {
            timestamp: Time::from_ns(t_ns),
            level: level as u8,
            message,
            name: name.to_string(),
            file: String::new(),
            line: 0,
        }
    }
}

/// The JSON Schema of a message type, as written into recordings.
pub fn schema_of<T: JsonSchema>() -> Value {
    schemars::schema_for!(T).to_value()
}

/// Schema name (MCAP schema record) and JSON Schema of an output topic; `None` for a topic
/// that is not part of the contract.
pub fn topic_schema(topic: &str) -> Option<(&'static str, &'static Value)> {
    static SCHEMAS: std::sync::OnceLock<BTreeMap<&'static str, (&'static str, Value)>> =
        std::sync::OnceLock::new();
    let all = SCHEMAS.get_or_init(|| {
        TOPICS
            .iter()
            .filter_map(|&t| Some((t, build_topic_schema(t)?)))
            .collect()
    });
    all.get(topic).map(|(name, schema)| (*name, schema))
}

/// Every output topic of the contract.
pub const TOPICS: [&str; 7] = [
    crate::io::mcap::RESIDUALS_TOPIC,
    crate::io::mcap::STATES_TOPIC,
    PREDICTED_TOPIC,
    crate::io::mcap::PARAMETERS_TOPIC,
    crate::io::mcap::TRACK_TOPIC,
    crate::io::mcap::DIAGNOSTICS_TOPIC,
    LOG_TOPIC,
];

fn build_topic_schema(topic: &str) -> Option<(&'static str, Value)> {
    use crate::io::mcap::{
        DIAGNOSTICS_TOPIC, PARAMETERS_TOPIC, RESIDUALS_TOPIC, STATES_TOPIC, TRACK_TOPIC,
    };
    Some(match topic {
        RESIDUALS_TOPIC => ("jointid.Residuals", schema_of::<ResidualsMsg>()),
        STATES_TOPIC => ("jointid.ConnectionStates", schema_of::<StatesMsg>()),
        PREDICTED_TOPIC => ("jointid.PredictedResponse", schema_of::<PredictedMsg>()),
        PARAMETERS_TOPIC => ("jointid.Parameters", schema_of::<ParametersMsg>()),
        TRACK_TOPIC => ("jointid.Track", schema_of::<TrackMsg>()),
        DIAGNOSTICS_TOPIC => ("jointid.Diagnostics", schema_of::<DiagnosticsMsg>()),
        LOG_TOPIC => ("foxglove.Log", schema_of::<LogMsg>()),
        _ => return None,
    })
}

/// Writes one contract message on `topic` (its schema from [`topic_schema`]).
pub fn write<T: Serialize>(
    w: &mut crate::io::mcap::RecordingWriter,
    topic: &str,
    t_ns: u64,
    msg: &T,
) -> Result<(), crate::io::mcap::McapIoError> {
    if w.has_output(topic) {
        return w.write_registered_output(topic, t_ns, msg);
    }
    let (name, schema) =
        topic_schema(topic).ok_or_else(|| crate::io::mcap::McapIoError::Usage {
            path: w.partial_path().to_path_buf(),
            what: format!("{topic} is not an output topic of the contract"),
        })?;
    w.write_output(topic, name, schema, t_ns, msg)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn schemas_deny_unknown_fields_and_carry_their_titles() {
        let s = schema_of::<ParametersMsg>();
        assert_eq!(s["title"], "jointid.Parameters");
        assert_eq!(s["additionalProperties"], false);
        assert!(
            s["required"]
                .as_array()
                .unwrap()
                .iter()
                .any(|r| r == "final")
        );
        let log = schema_of::<LogMsg>();
        assert_eq!(log["title"], "foxglove.Log");
    }

    #[test]
    fn time_splits_nanoseconds() {
        assert_eq!(Time::from_ns(12_000_000_123), Time { sec: 12, nsec: 123 });
    }
}
