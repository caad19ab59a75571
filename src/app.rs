//! What the command line does, as library functions the binaries and tests call:
//! `simulate` a test into a recording, `replay` a recording through the identification,
//! `inspect` a recording. Binaries only parse arguments and print.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use serde::Serialize;
use serde_json::json;

use crate::align::AlignError;
use crate::estimate::StepOutput;
use crate::identify::{Identification, PassReport};
use crate::io::contract::{
    self, CONTRACT_VERSION, LOG_TOPIC, LogLevel, LogMsg, PREDICTED_TOPIC, ParametersKind, Source,
    Time,
};
use crate::io::mcap::{
    ChannelInfo, DIAGNOSTICS_TOPIC, McapIoError, PARAMETERS_TOPIC, RECORDING_METADATA,
    RESIDUALS_TOPIC, RecordingWriter, STATES_TOPIC, TRACK_TOPIC, TRUTH_METADATA, stream_frames,
};
use crate::io::{Frame, FrameEncoding};
use crate::setup::{EstimatorKind, Setup, SetupError};
use crate::simulate::{SimulateOptions, simulate};

#[derive(Debug, thiserror::Error)]
pub enum AppError {
    #[error(transparent)]
    Setup(#[from] SetupError),
    #[error(transparent)]
    Mcap(#[from] McapIoError),
    #[error(transparent)]
    Simulate(#[from] crate::simulate::SimulateError),
    #[error("{path}: {source}")]
    Identify {
        path: PathBuf,
        source: crate::identify::IdentifyError,
    },
    #[error("{path}: {source}")]
    Align { path: PathBuf, source: AlignError },
    #[error("{path}: no setup attached and none given with --setup")]
    NoSetup { path: PathBuf },
    #[error("{path}: {topic} channels {got:?} do not match the setup's {expected:?}")]
    ChannelNames {
        path: PathBuf,
        topic: &'static str,
        expected: Vec<String>,
        got: Vec<String>,
    },
    #[error("{msg}")]
    Pipeline { msg: String },
    /// Fewer samples than identification needs: how many were read and, when the input
    /// ended early, why (the read error, or the damage of a truncated file), so that a short
    /// recording is not mistaken for an empty one.
    #[error(
        "{path}: {}only {samples} usable samples were read{} (identification needs at least {needed})",
        cause.as_deref().map(|c| format!("{c}: ")).unwrap_or_default(),
        if cause.is_some() { " before it" } else { "" }
    )]
    TooLittleData {
        path: PathBuf,
        samples: usize,
        needed: usize,
        cause: Option<String>,
    },
    #[error(transparent)]
    Report(#[from] crate::report::ReportError),
    #[error("{option}: {reason}")]
    BadOption {
        option: &'static str,
        reason: String,
    },
    #[error(transparent)]
    OutputPath(#[from] crate::io::output::OutputPathError),
}

fn channel_info(names: impl Iterator<Item = (String, String)>) -> ChannelInfo {
    let (names, units) = names.unzip();
    ChannelInfo { names, units }
}

/// One line for an error and its causes, each cause only where the message before it does
/// not already say it (our errors embed their source, `"{path}: {source}"`, so anyhow's
/// `{:#}` would print it twice).
pub fn error_line(e: &(dyn std::error::Error + 'static)) -> String {
    let mut line = e.to_string();
    let mut cause = e.source();
    while let Some(c) = cause {
        let text = c.to_string();
        if !line.contains(&text) {
            line.push_str(": ");
            line.push_str(&text);
        }
        cause = c.source();
    }
    one_line(&line)
}

/// `text` on one line: terminal colour codes and box-drawing characters (which the mcap
/// crate's parse errors carry) removed, every run of white space one space.
pub fn one_line(text: &str) -> String {
    let mut out = String::with_capacity(text.len());
    let mut chars = text.chars().peekable();
    while let Some(c) = chars.next() {
        if c == '\u{1b}' {
            // CSI sequence: ESC [ parameters final-byte.
            if chars.peek() == Some(&'[') {
                chars.next();
                for d in chars.by_ref() {
                    if ('@'..='~').contains(&d) {
                        break;
                    }
                }
            }
            continue;
        }
        if ('\u{2500}'..='\u{257f}').contains(&c) {
            continue;
        }
        out.push(if c.is_whitespace() { ' ' } else { c });
    }
    out.split_whitespace().collect::<Vec<_>>().join(" ")
}

pub fn excitation_channels(setup: &Setup) -> ChannelInfo {
    channel_info(
        setup
            .excitation
            .iter()
            .map(|e| (e.name.clone(), e.unit.clone())),
    )
}

pub fn response_channels(setup: &Setup) -> ChannelInfo {
    channel_info(
        setup
            .sensors
            .iter()
            .map(|s| (s.name.clone(), s.unit.clone())),
    )
}

/// Summary of a simulated recording.
#[derive(Debug, Clone, Serialize)]
pub struct SimulateSummary {
    pub out: PathBuf,
    pub samples: usize,
    pub truth: BTreeMap<String, f64>,
    pub stuck_fraction: f64,
}

/// Simulate a test and write it as a recording (setup attached, truth in the metadata).
pub fn simulate_recording(
    setup: &Setup,
    opts: &SimulateOptions,
    out: &Path,
    encoding: FrameEncoding,
    scenario_name: &str,
) -> Result<SimulateSummary, AppError> {
    let sim = simulate(setup, opts)?;
    let mut w = RecordingWriter::create(out, encoding)?;
    // Keep the attached setup true to the data: the replay reads dt_s from it.
    w.attach_setup_of(&setup.at_rate(opts.dt_s)?)?;
    let truth: BTreeMap<String, f64> = setup
        .param_keys()
        .into_iter()
        .zip(sim.truth.iter().copied())
        .collect();
    w.write_metadata(
        TRUTH_METADATA,
        &truth
            .iter()
            .map(|(k, v)| (k.clone(), format!("{v:e}")))
            .collect(),
    )?;
    let facts: BTreeMap<String, String> = [
        (
            "generator",
            format!("jointid simulate {}", env!("CARGO_PKG_VERSION")),
        ),
        ("scenario", scenario_name.to_string()),
        ("steps", opts.steps.to_string()),
        ("dt_s", format!("{:e}", opts.dt_s)),
        ("substeps", opts.substeps.to_string()),
        ("noise", opts.noise.to_string()),
        ("seed", opts.seed.to_string()),
        ("stuck_fraction", format!("{:.4}", sim.stuck_fraction)),
    ]
    .into_iter()
    .map(|(k, v)| (k.to_string(), v))
    .collect();
    let mut facts = facts;
    if let crate::simulate::Scenario::RandomStiffnessDrop { at_s, factor, .. } = opts.scenario {
        // The truth metadata hold the values before the drop; these say what changed.
        facts.insert("stiffness_drop_at_s".into(), format!("{at_s:e}"));
        facts.insert("stiffness_drop_factor".into(), format!("{factor}"));
    }
    w.write_metadata(RECORDING_METADATA, &facts)?;
    w.declare_inputs(&excitation_channels(setup), &response_channels(setup))?;
    for i in 0..sim.excitation.len() {
        let t_ns = (i as f64 * opts.dt_s * 1e9).round() as u64;
        w.write_excitation(&Frame {
            sample: i as u64,
            t_ns,
            values: sim.excitation[i].clone(),
        })?;
        w.write_response(&Frame {
            sample: i as u64,
            t_ns,
            values: sim.response[i].clone(),
        })?;
    }
    w.finish()?;
    Ok(SimulateSummary {
        out: out.to_path_buf(),
        samples: sim.excitation.len(),
        truth,
        stuck_fraction: sim.stuck_fraction,
    })
}

/// What `replay` is asked to do.
#[derive(Debug, Clone, Default)]
pub struct ReplayRequest {
    pub recording: PathBuf,
    /// Overrides the attached setup.
    pub setup: Option<PathBuf>,
    pub passes: Option<usize>,
    pub estimator: Option<EstimatorKind>,
    pub out: Option<PathBuf>,
    /// Tracking: forgetting factor per sample (overrides the setup's `estimator.forgetting`).
    pub forgetting: Option<f64>,
    /// Tracking: solve interval in samples (overrides `estimator.track_every`); 0: automatic
    /// (`TrackOptions::default_every`).
    pub track_every: Option<usize>,
    /// Switch the output-error refinement of the Kalman pipeline off (`--no-refine`).
    pub no_refine: bool,
    /// Write SVG plots here (`--plots DIR`, see [`crate::report`]).
    pub plots: Option<PathBuf>,
    /// Replicates of the parametric bootstrap of a refined answer (`--bootstrap N`, 0: none;
    /// `None`: automatic for a prediction-error answer, see `IdentifyOptions::bootstrap`).
    pub bootstrap: Option<usize>,
    /// The record starts in motion (`--in-motion`: cut from a running test): its start state
    /// is estimated whatever its first sample reads (`IdentifyOptions::in_motion`).
    pub in_motion: bool,
}

/// What `replay` found.
#[derive(Debug, Clone)]
pub struct ReplayOutcome {
    pub recording: PathBuf,
    pub samples: usize,
    pub identification: Identification,
    /// Problems with the input that did not stop the replay (truncation, a bad sample after
    /// which the data were cut).
    pub input_warnings: Vec<String>,
    /// The input error that cut the data short, if any: the replay used what came before
    /// it, and the command exits with an error after writing its outputs.
    pub input_error: Option<String>,
    pub output: Option<PathBuf>,
    /// The plots written (`--plots`), with the fit of the predicted response.
    pub plots: Option<crate::report::PlotSummary>,
}

impl ReplayOutcome {
    /// The `--json` object: `parameters` (final, with `connection`, `basis`, `value`,
    /// `std_error`, `ci95`, `truth` when known), `passes` (count), `converged`, and the
    /// per-pass reports under `pass_reports`.
    pub fn to_json(&self) -> serde_json::Value {
        let id = &self.identification;
        json!({
            "version": CONTRACT_VERSION,
            "recording": self.recording,
            "samples": self.samples,
            "estimator": id.estimator,
            "parameters": contract::parameters_from_estimates(id.final_parameters().unwrap_or(&[])),
            "passes": id.passes.len(),
            "converged": id.converged,
            "stop_reason": id.stop_reason,
            "failure": id.failure,
            "output_error": id.output_error,
            "maximum_likelihood": id.maximum_likelihood,
            "notes": id.notes,
            "input_warnings": self.input_warnings,
            "input_error": self.input_error,
            "output": self.output,
            "plots": self.plots,
            "track": id.track,
            "session": id.session,
            "pass_reports": id.passes,
        })
    }
}

/// Progress events for a progress bar.
pub enum Progress<'a> {
    Start { samples: usize, passes: usize },
    Samples { pass: usize, done: usize },
    Pass(&'a PassReport),
}

/// Replay a recording through the identification (Steps I–VI) and write the results. The
/// work runs through the pipeline stages (source → aligner → identification → sink, see
/// [`crate::pipeline::replay`]); the numbers are those of [`identify`] over the aligned data.
pub fn replay(
    req: &ReplayRequest,
    progress: &mut dyn FnMut(Progress<'_>),
) -> Result<ReplayOutcome, AppError> {
    crate::pipeline::replay::run(req, progress)
}

/// JSON Schemas of the output topics, so Foxglove and other tools can read them.
pub(crate) fn write_results(
    out: &Path,
    setup: &Setup,
    header: &crate::io::mcap::RecordingHeader,
    data: &crate::identify::TestData,
    outcome: &ReplayOutcome,
    last_pass: &[(usize, StepOutput)],
    prediction: &Result<Vec<Vec<f64>>, String>,
) -> Result<(), AppError> {
    let mut w = RecordingWriter::create(out, FrameEncoding::Json)?;
    w.attach_setup_of(setup)?;
    if !header.truth.is_empty() {
        w.write_metadata(
            TRUTH_METADATA,
            &header
                .truth
                .iter()
                .map(|(k, v)| (k.clone(), format!("{v:e}")))
                .collect(),
        )?;
    }
    let mut facts = header.facts.clone();
    facts.insert(
        "replayed_from".into(),
        outcome.recording.display().to_string(),
    );
    facts.insert("estimator".into(), outcome.identification.estimator.clone());
    w.write_metadata(RECORDING_METADATA, &facts)?;
    w.declare_inputs(&excitation_channels(setup), &response_channels(setup))?;
    let names: Vec<String> = setup.connections.iter().map(|c| c.name.clone()).collect();
    let t_of = |s: u64| -> u64 {
        data.samples
            .iter()
            .position(|&x| x == s)
            .map_or(0, |i| data.t_ns[i])
    };
    let first = data.samples[0];
    for i in 0..data.len() {
        let (s, t) = (data.samples[i], data.t_ns[i]);
        w.write_excitation(&Frame {
            sample: s,
            t_ns: t,
            values: data.excitation[i].clone(),
        })?;
        w.write_response(&Frame {
            sample: s,
            t_ns: t,
            values: data.response[i].clone(),
        })?;
    }
    let connections: Vec<String> = names;
    let v = |x: &nalgebra::DVector<f64>| x.iter().copied().collect::<Vec<f64>>();
    for (pass, o) in last_pass {
        // Samples are consecutive from `first`, so the time is found by offset.
        let idx = (o.sample - first) as usize;
        let t = data
            .t_ns
            .get(idx)
            .copied()
            .unwrap_or_else(|| t_of(o.sample));
        contract::write(
            &mut w,
            RESIDUALS_TOPIC,
            t,
            &contract::ResidualsMsg {
                version: CONTRACT_VERSION,
                timestamp: Time::from_ns(t),
                sample: o.sample,
                t_ns: t,
                source: Source::Replay,
                pass: *pass,
                connections: connections.clone(),
                residual: v(&o.residual),
                force: v(&o.force),
            },
        )?;
        contract::write(
            &mut w,
            STATES_TOPIC,
            t,
            &contract::StatesMsg {
                version: CONTRACT_VERSION,
                timestamp: Time::from_ns(t),
                sample: o.sample,
                t_ns: t,
                source: Source::Replay,
                pass: *pass,
                connections: connections.clone(),
                delta: v(&o.delta),
                delta_v: v(&o.delta_v),
                delta_a: v(&o.delta_a),
            },
        )?;
    }
    let t_end = data.t_ns.last().copied().unwrap_or(0);
    let id = &outcome.identification;
    let mut log = Vec::new();
    // The identified model's response to the measured excitation, for comparison with
    // the measured one (Foxglove plots both topics).
    match prediction {
        Ok(predicted) => {
            let sensors: Vec<String> = setup.sensors.iter().map(|s| s.name.clone()).collect();
            for i in 0..data.len() {
                let t = data.t_ns[i];
                contract::write(
                    &mut w,
                    PREDICTED_TOPIC,
                    t,
                    &contract::PredictedMsg {
                        version: CONTRACT_VERSION,
                        timestamp: Time::from_ns(t),
                        sample: data.samples[i],
                        t_ns: t,
                        sensors: sensors.clone(),
                        values: predicted.iter().map(|ch| ch[i]).collect(),
                    },
                )?;
            }
        }
        Err(why) => log.push((LogLevel::Warning, format!("no predicted response: {why}"))),
    }
    let n = id.passes.len();
    for (k, p) in id.passes.iter().enumerate() {
        let last = k + 1 == n;
        contract::write(
            &mut w,
            PARAMETERS_TOPIC,
            t_end,
            &contract::ParametersMsg {
                version: CONTRACT_VERSION,
                timestamp: Time::from_ns(t_end),
                sample: data.samples.last().copied().unwrap_or(0),
                t_ns: t_end,
                source: Source::Replay,
                kind: ParametersKind::Pass,
                pass: Some(p.pass),
                is_final: last,
                converged: last.then_some(id.converged),
                parameters: contract::parameters_from_estimates(if last {
                    id.final_parameters().unwrap_or(&p.parameters)
                } else {
                    &p.parameters
                }),
            },
        )?;
        contract::write(
            &mut w,
            DIAGNOSTICS_TOPIC,
            t_end,
            &contract::DiagnosticsMsg {
                version: CONTRACT_VERSION,
                timestamp: Time::from_ns(t_end),
                t_ns: t_end,
                source: Source::Replay,
                kind: contract::DiagnosticsKind::Pass,
                pass: Some(contract::PassDiagnostics::from_pass(p)),
                summary: None,
                live: None,
            },
        )?;
    }
    if let Some(track) = &id.track {
        let keys = setup.param_keys();
        for p in &track.points {
            let t = data
                .t_ns
                .get((p.sample - first) as usize)
                .copied()
                .unwrap_or_else(|| t_of(p.sample));
            contract::write(
                &mut w,
                TRACK_TOPIC,
                t,
                &contract::TrackMsg {
                    version: CONTRACT_VERSION,
                    timestamp: Time::from_ns(t),
                    sample: p.sample,
                    t_ns: t,
                    forgetting: track.forgetting,
                    keys: keys.clone(),
                    parameters: p
                        .parameters
                        .iter()
                        .map(|v| {
                            v.as_ref().map(|v| contract::TrackedValueMsg {
                                value: v.value,
                                std_error: contract::finite(v.std_error),
                            })
                        })
                        .collect(),
                    unsolved: p.unsolved.clone(),
                },
            )?;
        }
    }
    let inadequacy = id.inadequacy();
    contract::write(
        &mut w,
        DIAGNOSTICS_TOPIC,
        t_end,
        &contract::DiagnosticsMsg {
            version: CONTRACT_VERSION,
            timestamp: Time::from_ns(t_end),
            t_ns: t_end,
            source: Source::Replay,
            kind: contract::DiagnosticsKind::Summary,
            pass: None,
            summary: Some(contract::RunSummary {
                converged: id.converged,
                stop_reason: id.stop_reason.clone(),
                failure: id.failure.clone(),
                input_warnings: outcome.input_warnings.clone(),
                input_error: outcome.input_error.clone(),
                inadequacy: inadequacy.clone(),
            }),
            live: None,
        },
    )?;
    // Notes, warnings and errors on the log topic (Foxglove's Log panel).
    log.extend(id.notes.iter().map(|n| (LogLevel::Info, n.clone())));
    if let Some(ml) = &id.maximum_likelihood {
        log.extend(ml.warnings.iter().map(|n| (LogLevel::Warning, n.clone())));
    }
    log.extend(
        outcome
            .input_warnings
            .iter()
            .map(|n| (LogLevel::Warning, n.clone())),
    );
    log.extend(
        id.failure
            .iter()
            .chain(&outcome.input_error)
            .map(|e| (LogLevel::Error, e.clone())),
    );
    log.push((LogLevel::Info, format!("stopped: {}", id.stop_reason)));
    for (level, message) in log {
        contract::write(
            &mut w,
            LOG_TOPIC,
            t_end,
            &LogMsg::new(t_end, level, "jointid.replay", message),
        )?;
    }
    w.finish()?;
    Ok(())
}

/// Summary of a recording for `jointid inspect`.
#[derive(Debug, Clone, Serialize)]
pub struct Inspection {
    pub path: PathBuf,
    pub encoding: String,
    pub excitation_channels: Vec<String>,
    pub response_channels: Vec<String>,
    pub excitation_frames: usize,
    pub response_frames: usize,
    pub first_sample: Option<u64>,
    pub last_sample: Option<u64>,
    pub duration_s: f64,
    pub setup_attached: bool,
    /// The attached setup's external model files (`[model.matrix_market]`) are attached too.
    pub model_files_attached: bool,
    pub setup_title: Option<String>,
    pub truth: BTreeMap<String, f64>,
    pub facts: BTreeMap<String, String>,
    pub damage: Option<String>,
    pub error: Option<String>,
}

pub fn inspect(path: &Path) -> Result<Inspection, AppError> {
    let mut stream = stream_frames(path)?;
    let h = stream.header.clone();
    let (mut ne, mut nr) = (0, 0);
    let (mut first, mut last, mut t0, mut t1) = (None, None, 0u64, 0u64);
    let mut error = None;
    for item in stream.by_ref() {
        match item {
            Ok((topic, f)) => {
                if topic == crate::io::mcap::InputTopic::Excitation {
                    ne += 1;
                } else {
                    nr += 1;
                }
                if first.is_none() {
                    first = Some(f.sample);
                    t0 = f.t_ns;
                }
                last = Some(f.sample);
                t1 = f.t_ns;
            }
            Err(e) => {
                error = Some(e.to_string());
                break;
            }
        }
    }
    let title = h
        .setup_toml
        .as_deref()
        .and_then(|t| Setup::from_toml_with_model_files(t, "attached", h.model_files.as_ref()).ok())
        .map(|s| s.title);
    Ok(Inspection {
        path: path.to_path_buf(),
        encoding: format!("{:?}", h.encoding).to_lowercase(),
        excitation_channels: h.excitation_channels.names.clone(),
        response_channels: h.response_channels.names.clone(),
        excitation_frames: ne,
        response_frames: nr,
        first_sample: first,
        last_sample: last,
        duration_s: (t1.saturating_sub(t0)) as f64 * 1e-9,
        setup_attached: h.setup_toml.is_some(),
        model_files_attached: h.model_files.is_some(),
        setup_title: title,
        truth: h.truth.clone(),
        facts: h.facts.clone(),
        damage: stream.damage().map(str::to_string),
        error,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn error_line_says_each_cause_once() {
        let e = AppError::Identify {
            path: "x.mcap".into(),
            source: crate::identify::IdentifyError::TooShort(2),
        };
        let line = error_line(&e);
        assert_eq!(line.matches("at least 3 are needed").count(), 1, "{line}");
        assert!(line.starts_with("x.mcap: "), "{line}");
    }
}
