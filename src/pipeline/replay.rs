//! `jointid replay` through the pipeline stages: **MCAP source → strict aligner →
//! identification stage → sink** (the calling thread: progress, the last pass's per-sample
//! outputs, then the results file).
//!
//! # Why the passes run over buffered data
//!
//! The identification stage buffers the aligned samples and runs
//! [`crate::identify::identify`] when the stream has ended. Even the first pass cannot
//! stream for the default Kalman estimator: its channel noise levels are estimated from
//! the whole record's high-order differences, its random-walk and noise scale are tuned by
//! the innovation likelihood of whole-record filter runs, and its smoother runs backwards
//! from the last sample. Passes 2… need the whole record anyway. Running exactly
//! `identify` over exactly the aligned data keeps the numbers identical (bit for bit) to
//! the replay before the pipeline existed, which `tests/live_pipeline.rs` checks on the
//! shipped recordings. The live path ([`super::live`]) streams its first pass through a
//! filter-only estimator instead and identifies its windows with the same code
//! ([`crate::session`]).

use std::path::{Path, PathBuf};
use std::thread;

use crossbeam_channel::bounded;

use super::{AlignedItem, CHANNEL_CAPACITY, Msg, SourceItem, panic_message, strict_align_stage};
use crate::align::{AlignError, Aligner};
use crate::app::{
    AppError, Progress, ReplayOutcome, ReplayRequest, excitation_channels, response_channels,
};
use crate::estimate::StepOutput;
use crate::identify::{
    Identification, IdentifyError, IdentifyOptions, MIN_SAMPLES, PassReport, TestData, identify,
};
use crate::io::mcap::{FrameStream, RecordingHeader, stream_frames};
use crate::setup::EstimatorKind;
use crate::setup::Setup;

/// Samples between two progress reports of a pass.
const PROGRESS_EVERY: usize = 4096;

/// What the identification stage sends to the sink.
enum StageOut {
    Start {
        samples: usize,
        passes: usize,
    },
    Sample(usize, StepOutput),
    /// Samples done in a pass, for the progress display, when the outputs themselves are
    /// not wanted (no results file, no plots).
    Done {
        pass: usize,
        done: usize,
    },
    Pass(Box<PassReport>),
}

/// What the identification stage returns when joined.
struct StageResult {
    data: TestData,
    input_warnings: Vec<String>,
    input_error: Option<String>,
    identification: Result<Identification, IdentifyError>,
}

/// The MCAP source stage: every frame in log-time order, then a warning if the file was
/// truncated, then `Flush` (clean end) or `Quit` with the read error.
fn mcap_source(
    mut stream: FrameStream,
    path: PathBuf,
    tx: crossbeam_channel::Sender<Msg<SourceItem>>,
) {
    let mut end = Msg::Flush;
    for item in stream.by_ref() {
        match item {
            Ok((topic, f)) => {
                if tx.send(Msg::Data(SourceItem::Frame(topic, f))).is_err() {
                    return;
                }
            }
            Err(e) => {
                end = Msg::Quit {
                    error: Some(e.to_string()),
                };
                break;
            }
        }
    }
    if let Some(d) = stream.damage() {
        let _ = tx.send(Msg::Data(SourceItem::Warning(format!(
            "{}: {d}",
            path.display()
        ))));
    }
    let _ = tx.send(end);
}

/// The input policy for an aligner fault: a ragged end (one topic one frame longer) after
/// a truncation or a read error is expected; any other fault is the input error (unless
/// there already is one).
fn fault_ends_input(
    e: AlignError,
    input_error: &mut Option<String>,
    input_warnings: &[String],
    path: &Path,
) {
    let cut = input_error.is_some() || !input_warnings.is_empty();
    let ragged = matches!(e, AlignError::Unpaired { .. }) && cut;
    if !ragged && input_error.is_none() {
        *input_error = Some(format!("{}: {e}", path.display()));
    }
}

/// The error for an input with fewer samples than identification needs: how many were read
/// and why the input ended early, if it did: the read error, else `damage`, the reader's
/// note on a truncated or damaged file (the only warning an MCAP source sends). Without
/// either the recording is complete and that short.
fn too_little_data(
    path: &Path,
    samples: usize,
    input_error: Option<String>,
    damage: Option<String>,
) -> AppError {
    let cause = match (input_error, damage) {
        (Some(e), _) => Some(format!("the input ended at an error: {e}")),
        (None, Some(d)) => {
            // The note is worded for the warnings list, after the file's name.
            let prefix = format!("{}: ", path.display());
            let d = d.strip_prefix(&prefix).unwrap_or(&d);
            Some(format!("the recording is damaged ({d})"))
        }
        (None, None) => None,
    };
    AppError::TooLittleData {
        path: path.to_path_buf(),
        samples,
        needed: MIN_SAMPLES,
        cause,
    }
}

/// The identification stage: buffer, then identify (see the module docs). The input
/// policy is the one replay always had: an input error ends the data there, the samples
/// before it are identified, and a ragged end (one topic one frame longer) after a
/// truncation or a read error is expected rather than an error.
///
/// `keep_outputs`: send every sample's output to the sink (for the results file and the
/// plots); otherwise only a count every [`PROGRESS_EVERY`] samples. Why: the per-sample
/// copies (five vectors each, every pass) were ~5 % of a 100,000-sample replay's CPU time,
/// for outputs nobody asked for.
fn identify_stage(
    rx: crossbeam_channel::Receiver<Msg<AlignedItem>>,
    tx: crossbeam_channel::Sender<Msg<StageOut>>,
    setup: &Setup,
    opts: &IdentifyOptions,
    truth: Option<&[f64]>,
    path: &Path,
    keep_outputs: bool,
) -> Result<StageResult, AppError> {
    if let Some(spec) = setup.window_spec() {
        return identify_windows_stage(rx, tx, setup, opts, truth, path, spec);
    }
    let mut data = TestData::default();
    let mut input_warnings = Vec::new();
    let mut fault: Option<AlignError> = None;
    let mut input_error: Option<String> = None;
    loop {
        match rx.recv() {
            Ok(Msg::Data(AlignedItem::Sample(a))) => {
                data.samples.push(a.sample);
                data.t_ns.push(a.t_ns);
                data.excitation.push(a.excitation);
                data.response.push(a.response);
            }
            Ok(Msg::Data(AlignedItem::Warning(w))) => input_warnings.push(w),
            Ok(Msg::Data(AlignedItem::Fault(e))) => {
                fault.get_or_insert(e);
            }
            Ok(Msg::Flush) => break,
            Ok(Msg::Quit { error }) => {
                input_error = error;
                break;
            }
            Err(_) => {
                input_error = Some("the aligner stage ended without an end message".into());
                break;
            }
        }
    }
    // The warnings so far are the source's: the damage note of a truncated file.
    let damage = input_warnings.first().cloned();
    if let Some(AlignError::Gap { prev, got }) = fault {
        // Lost frames or a restarted acquisition in a live recording: the time stepping
        // cannot cross it, so the first segment is identified (a setup with windows, as
        // `jointid live` attaches, lets gaps through instead: its windows restart after them).
        input_warnings.push(format!(
            "{}: the recording continues after a gap (sample {prev} is followed by {got}: frames lost, or the acquisition restarted); the first segment, samples {}–{prev} ({} samples), was identified and the rest was not",
            path.display(),
            data.samples.first().copied().unwrap_or(0),
            data.len()
        ));
    } else if let Some(e) = fault {
        fault_ends_input(e, &mut input_error, &input_warnings, path);
    }
    if data.len() < MIN_SAMPLES {
        return Err(too_little_data(path, data.len(), input_error, damage));
    }
    let _ = tx.send(Msg::Data(StageOut::Start {
        samples: data.len(),
        passes: opts.passes,
    }));
    let mut counted = (0usize, 0usize);
    let t_identify = std::time::Instant::now();
    let identification = identify(
        setup,
        &data,
        opts,
        truth,
        &mut |r| {
            let _ = tx.send(Msg::Data(StageOut::Pass(Box::new(r.clone()))));
        },
        &mut |pass, o| {
            if keep_outputs {
                let _ = tx.send(Msg::Data(StageOut::Sample(pass, o.clone())));
                return;
            }
            if pass != counted.0 {
                counted = (pass, 0);
            }
            counted.1 += 1;
            if counted.1.is_multiple_of(PROGRESS_EVERY) {
                let _ = tx.send(Msg::Data(StageOut::Done {
                    pass,
                    done: counted.1,
                }));
            }
        },
    );
    crate::par::phase("identify (whole call)", t_identify);
    // `--bootstrap` acts on the refinements (the prediction error's, the free run's).
    let identification = identification.map(|mut id| {
        let bootstrapped = id.output_error.as_ref().is_some_and(|r| {
            r.bootstrap.is_some() || r.prediction_error.as_ref().is_some_and(|p| p.bootstrap.is_some())
        });
        let said = id.notes.iter().any(|n| n.contains("parametric bootstrap"));
        if opts.bootstrap.is_some_and(|n| n > 0) && !bootstrapped && !said {
            id.notes.push(
                "`--bootstrap` not run: it applies to the output-error refinements (the prediction error's and the free run's), which did not give this answer".into(),
            );
        }
        id
    });
    let _ = tx.send(Msg::Flush);
    Ok(StageResult {
        data,
        input_warnings,
        input_error,
        identification,
    })
}

/// The identification stage of a record identified in windows (the setup's `[estimator]
/// window_samples`, see [`crate::session`]): each window is identified as it completes,
/// holding one window in memory; a gap restarts the window (the aligner lets gaps through);
/// the result is the last window's identification carrying the combination of all. A
/// record shorter than one window is identified whole, as one window. The windows' passes
/// are reported as they finish; per-sample outputs are not kept (a results file of a
/// windowed replay has the parameters, not the residual-force history).
fn identify_windows_stage(
    rx: crossbeam_channel::Receiver<Msg<AlignedItem>>,
    tx: crossbeam_channel::Sender<Msg<StageOut>>,
    setup: &Setup,
    opts: &IdentifyOptions,
    truth: Option<&[f64]>,
    path: &Path,
    spec: crate::session::WindowSpec,
) -> Result<StageResult, AppError> {
    use crate::session::{WindowCollector, WindowedSession, identify_window};
    let mut collector = WindowCollector::new(spec);
    let mut session: WindowedSession<IdentifyError> = WindowedSession::new(spec);
    let mut input_warnings = Vec::new();
    let mut input_error: Option<String> = None;
    let mut fault: Option<AlignError> = None;
    let run = |data: TestData,
               record_first: Option<u64>,
               session: &mut WindowedSession<IdentifyError>| {
        let _ = tx.send(Msg::Data(StageOut::Start {
            samples: data.len(),
            passes: opts.passes,
        }));
        let earlier = &session.report.windows;
        let (est, id) =
            identify_window(setup, &data, opts, truth, record_first, earlier, &mut |r| {
                let _ = tx.send(Msg::Data(StageOut::Pass(Box::new(r.clone()))));
            });
        session.add(est, id, data);
    };
    loop {
        match rx.recv() {
            Ok(Msg::Data(AlignedItem::Sample(a))) => {
                session.report.samples_seen += 1;
                if let Some(w) = collector.push(a.sample, a.t_ns, a.excitation, a.response) {
                    run(w, collector.record_first(), &mut session);
                }
            }
            Ok(Msg::Data(AlignedItem::Warning(w))) => input_warnings.push(w),
            Ok(Msg::Data(AlignedItem::Fault(e))) => {
                // Every fault but a gap (which the aligner lets through) ends the data here.
                fault.get_or_insert(e);
            }
            Ok(Msg::Flush) => break,
            Ok(Msg::Quit { error }) => {
                if error.is_some() {
                    input_error = error;
                }
                break;
            }
            Err(_) => {
                input_error = Some("the aligner stage ended without an end message".into());
                break;
            }
        }
    }
    if let Some(e) = fault {
        fault_ends_input(e, &mut input_error, &input_warnings, path);
    }
    session.report.windows_abandoned = collector.abandoned;
    if session.windows() == 0 {
        let partial = collector.take_partial();
        if partial.len() < MIN_SAMPLES {
            let damage = input_warnings.first().cloned();
            return Err(too_little_data(path, partial.len(), input_error, damage));
        }
        input_warnings.push(format!(
            "{}: {} samples, fewer than one window of {}: identified whole",
            path.display(),
            partial.len(),
            spec.samples
        ));
        run(partial, collector.record_first(), &mut session);
    }
    let _ = tx.send(Msg::Flush);
    let Some((data, identification)) = session.finish() else {
        return Err(AppError::Pipeline {
            msg: "windowed identification ended without a window".into(),
        });
    };
    Ok(StageResult {
        data,
        input_warnings,
        input_error,
        identification,
    })
}

/// The note for tracking asked for (by option, else by the setup's keys) that the answer
/// does not have: the track comes from the residual-force passes, and an answer without
/// them (maximum likelihood fits the whole record at once) has none, which `"track": null`
/// alone does not explain. As the `--bootstrap` note does for its option.
fn tracking_not_run(req: &ReplayRequest, setup: &Setup, estimator: &str) -> Option<String> {
    let keys = &setup.estimator;
    let asked: Vec<&str> = [
        (req.forgetting.is_some(), "`--forgetting`"),
        (
            req.forgetting.is_none() && keys.forgetting < 1.0,
            "`estimator.forgetting`",
        ),
        (req.track_every.is_some(), "`--track-every`"),
        (
            req.track_every.is_none() && keys.track_every > 0,
            "`estimator.track_every`",
        ),
    ]
    .into_iter()
    .filter_map(|(asked, name)| asked.then_some(name))
    .collect();
    (!asked.is_empty()).then(|| {
        format!(
            "{} not run: the parameter track comes from the residual-force passes (`--estimator kalman` or `paper`), and the `{estimator}` estimator's answer has none",
            asked.join(" and ")
        )
    })
}

/// The setup a replay uses: `--setup` if given, else the attached one; the channel names
/// must match the recording's.
pub(crate) fn replay_setup(
    req_setup: Option<&Path>,
    header: &RecordingHeader,
    path: &Path,
) -> Result<Setup, AppError> {
    let setup = match req_setup {
        Some(p) => Setup::from_file(p)?,
        None => {
            let text = header.setup_toml.clone().ok_or(AppError::NoSetup {
                path: path.to_path_buf(),
            })?;
            // The model's files the recording carries, if any (else read beside it).
            Setup::from_toml_with_model_files(
                &text,
                &format!("{} (attached setup.toml)", path.display()),
                header.model_files.as_ref(),
            )?
        }
    };
    let exc = excitation_channels(&setup);
    let resp = response_channels(&setup);
    for (topic, want, got) in [
        ("excitation", &exc.names, &header.excitation_channels.names),
        ("response", &resp.names, &header.response_channels.names),
    ] {
        if want != got {
            return Err(AppError::ChannelNames {
                path: path.to_path_buf(),
                topic,
                expected: want.clone(),
                got: got.clone(),
            });
        }
    }
    Ok(setup)
}

/// Replay a recording through the pipeline stages and write the results (see
/// [`crate::app::replay`], which calls this).
pub fn run(
    req: &ReplayRequest,
    progress: &mut dyn FnMut(Progress<'_>),
) -> Result<ReplayOutcome, AppError> {
    let path = req.recording.clone();
    // Where the outputs go is checked before the work: an output that is an input, or in a
    // directory that does not exist, would fail (or replace the input) only at the end.
    let mut inputs: Vec<&Path> = vec![&path];
    inputs.extend(req.setup.as_deref());
    if let Some(out) = &req.out {
        crate::io::output::check_output_file("--out", out, &inputs)?;
    }
    if let Some(dir) = &req.plots {
        crate::io::output::check_output_dir("--plots", dir, &[], &inputs)?;
    }
    let stream = stream_frames(&path)?;
    let header = stream.header.clone();
    let setup = replay_setup(req.setup.as_deref(), &header, &path)?;
    let mut opts = IdentifyOptions::from_setup(&setup);
    if let Some(p) = req.passes {
        if p == 0 {
            return Err(AppError::BadOption {
                option: "--passes",
                reason: "must be at least 1 (a pass is one run of Steps I–V over the record)"
                    .into(),
            });
        }
        opts.passes = p;
    }
    if let Some(k) = req.estimator {
        opts.estimator = k;
        opts.estimator_by_default = false;
        // The output-error refinement belongs to the Kalman pipeline: `--estimator paper`
        // is the 1989 method alone.
        opts.output_error = setup.estimator.output_error && k == EstimatorKind::Kalman;
    }
    if req.no_refine {
        opts.output_error = false;
    }
    opts.bootstrap = req.bootstrap;
    opts.in_motion = req.in_motion;
    if let Some(l) = req.forgetting {
        if !(l > 0.0 && l <= 1.0) {
            return Err(AppError::BadOption {
                option: "--forgetting",
                reason: format!("must be in (0, 1] (memory 1/(1 − λ) samples), got {l}"),
            });
        }
        opts.forgetting = l;
    }
    if let Some(n) = req.track_every {
        opts.track_every = n;
    }
    let keys = setup.param_keys();
    let truth: Option<Vec<f64>> =
        if keys.iter().all(|k| header.truth.contains_key(k)) && !header.truth.is_empty() {
            Some(keys.iter().map(|k| header.truth[k]).collect())
        } else {
            None
        };
    let aligner = Aligner::new(setup.excitation.len(), setup.sensors.len(), setup.dt_s);
    // Windows restart after a gap; a whole-record identification stops at it.
    let aligner = if setup.window_spec().is_some() {
        aligner.allowing_gaps()
    } else {
        aligner
    };

    let (src_tx, src_rx) = bounded(CHANNEL_CAPACITY);
    let (al_tx, al_rx) = bounded(CHANNEL_CAPACITY);
    let (out_tx, out_rx) = bounded(CHANNEL_CAPACITY);
    let mut last_pass: Vec<(usize, StepOutput)> = Vec::new();
    let mut current_pass = 0usize;
    let mut current: Vec<StepOutput> = Vec::new();
    let stage = thread::scope(|scope| {
        let p = path.clone();
        let source = scope.spawn(move || mcap_source(stream, p, src_tx));
        let align = scope.spawn(move || strict_align_stage(src_rx, al_tx, aligner));
        let (setup, opts, truth, p) = (&setup, &opts, truth.as_deref(), path.as_path());
        let keep_outputs = req.out.is_some() || req.plots.is_some();
        let ident =
            scope.spawn(move || identify_stage(al_rx, out_tx, setup, opts, truth, p, keep_outputs));
        // The sink: progress and the per-sample outputs of the latest pass.
        while let Ok(msg) = out_rx.recv() {
            match msg {
                Msg::Data(StageOut::Start { samples, passes }) => {
                    current.reserve(samples);
                    progress(Progress::Start { samples, passes });
                }
                Msg::Data(StageOut::Sample(pass, o)) => {
                    if pass != current_pass {
                        current.clear();
                        current_pass = pass;
                    }
                    current.push(o);
                    if current.len().is_multiple_of(PROGRESS_EVERY) {
                        progress(Progress::Samples {
                            pass,
                            done: current.len(),
                        });
                    }
                }
                Msg::Data(StageOut::Done { pass, done }) => {
                    progress(Progress::Samples { pass, done })
                }
                Msg::Data(StageOut::Pass(r)) => progress(Progress::Pass(&r)),
                Msg::Flush | Msg::Quit { .. } => break,
            }
        }
        // Drain so the stage never blocks on a full channel, then join everything.
        while out_rx.recv().is_ok() {}
        let r = ident.join().map_err(|p| panic_message("identify", p));
        let s = source.join().map_err(|p| panic_message("source", p));
        let a = align.join().map_err(|p| panic_message("align", p));
        s.and(a).and(r)
    });
    let stage = stage.map_err(|msg| AppError::Pipeline { msg })??;
    let mut identification = stage.identification.map_err(|source| AppError::Identify {
        path: path.clone(),
        source,
    })?;
    if identification.track.is_none() {
        identification
            .notes
            .extend(tracking_not_run(req, &setup, &identification.estimator));
    }
    // The outputs of the last *reported* pass: if a later pass failed half-way its samples
    // are dropped, the reported pass's are kept.
    if let Some(last) = identification.passes.last()
        && last.pass == current_pass
    {
        last_pass = current.drain(..).map(|o| (current_pass, o)).collect();
    }
    let mut outcome = ReplayOutcome {
        recording: path.clone(),
        samples: identification
            .session
            .as_ref()
            .map_or(stage.data.len(), |s| s.samples_seen),
        identification,
        input_warnings: stage.input_warnings,
        input_error: stage.input_error,
        output: None,
        plots: None,
    };
    // The identified model's predicted response, once, for the results file and the plots.
    let prediction = if req.out.is_some() || req.plots.is_some() {
        crate::report::predicted_response(&setup, &stage.data, &outcome.identification)
    } else {
        Err("not requested".into())
    };
    if let Some(out) = &req.out {
        crate::app::write_results(
            out,
            &setup,
            &header,
            &stage.data,
            &outcome,
            &last_pass,
            &prediction,
        )?;
        outcome.output = Some(out.clone());
    }
    if let Some(dir) = &req.plots {
        outcome.plots = Some(crate::report::write_plots(
            dir,
            &setup,
            &stage.data,
            &outcome.identification,
            &last_pass,
            &header.truth,
            &prediction,
        )?);
    }
    Ok(outcome)
}
