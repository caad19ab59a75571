//! `jointid`: command line. Parses arguments, calls the library (`jointid::app`), prints,
//! and turns errors into a one-line cause and a non-zero exit code.

use std::path::PathBuf;
use std::process::ExitCode;

use anyhow::{Context, Result};
use clap::{Parser, Subcommand, ValueEnum};
use indicatif::{ProgressBar, ProgressStyle};
use jointid::app::{self, Progress, ReplayOutcome, ReplayRequest};
use std::sync::Arc;

use jointid::io::FrameEncoding;
use jointid::io::output::{check_output_dir, check_output_file};
use jointid::io::shm::ShmOptions;
use jointid::pipeline::live::{self, LiveOptions, LiveReport};
use jointid::setup::{EstimatorKind, Setup};
use jointid::simulate::{Noise, Scenario, SimulateOptions};

/// `println!` that ends the program quietly (exit 0) when stdout is a closed pipe
/// (`jointid inspect X | head -1`) instead of panicking.
macro_rules! println {
    () => {
        println!("")
    };
    ($($t:tt)*) => {{
        use std::io::Write as _;
        if let Err(e) = writeln!(std::io::stdout(), $($t)*) {
            if e.kind() == std::io::ErrorKind::BrokenPipe {
                std::process::exit(0);
            }
        }
    }};
}

#[derive(Parser)]
#[command(
    name = "jointid",
    version,
    about = "Identify structural connection parameters from vibration test data (NASA TM-101991, online)",
    after_help = "Examples:\n  jointid replay recordings/two-beam-friction.mcap\n  jointid simulate recordings/two-beam-friction.toml --out test.mcap --scenario random --steps 2000 --noise additive:0.01\n  jointid inspect recordings/two-beam-friction.mcap"
)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Clone, Copy, ValueEnum)]
enum ScenarioArg {
    Sine,
    Random,
    Free,
    /// Random input with the true stiffness dropping by 30 % half-way (bolt loosening).
    Loosening,
}

#[derive(Clone, Copy, ValueEnum)]
enum EncodingArg {
    Json,
    Binary,
}

#[derive(Clone, Copy, ValueEnum)]
enum EstimatorArg {
    /// Kalman joint input–state estimator with smoothing and output-error refinement (default).
    Kalman,
    /// Maximum likelihood on the exactly discretised model, discretisation chosen by
    /// likelihood, initial state estimated (laws linear in the state).
    Ml,
    /// The 1989 one-step estimator alone (reference).
    Paper,
}

#[derive(Subcommand)]
enum Command {
    /// Generate a synthetic test from a setup's true connection parameters.
    #[command(
        after_help = "Example:\n  jointid simulate recordings/two-beam-friction.toml --out t.mcap --scenario sine --steps 36 --noise cov:0.1 --seed 3"
    )]
    Simulate {
        /// Setup file (TOML) with `truth` values on its connections.
        setup: PathBuf,
        /// Output recording (MCAP).
        #[arg(long)]
        out: PathBuf,
        #[arg(long, value_enum, default_value = "random")]
        scenario: ScenarioArg,
        /// Recorded samples, including the initial one at rest.
        #[arg(long, default_value_t = 2000)]
        steps: usize,
        /// Sample interval, s (default: the setup's integrator.dt_s).
        #[arg(long, allow_negative_numbers = true)]
        dt: Option<f64>,
        /// Newmark steps per recorded sample (1 = the identification's own discretisation).
        #[arg(long, default_value_t = 1)]
        substeps: usize,
        /// none, additive:LEVEL (σ = LEVEL × channel RMS) or cov:LEVEL (the paper's).
        #[arg(long, default_value = "none")]
        noise: Noise,
        #[arg(long, default_value_t = 1)]
        seed: u64,
        /// Force amplitude (sine, free) or RMS (random), N.
        #[arg(long, default_value_t = 2.0e4)]
        amplitude: f64,
        /// Sine frequency, Hz.
        #[arg(long, default_value_t = 200.0)]
        freq: f64,
        /// Impact pulse duration for `free`, s (a half-sine; the model interpolates the
        /// excitation linearly between samples, which misses π²/(12n²) of the impulse of an
        /// n-sample pulse: 0.03 % at 50 samples, 0.2 % at 20 — visible at 1 % noise).
        #[arg(long, default_value_t = 5.0e-3)]
        pulse: f64,
        #[arg(long, value_enum, default_value = "json")]
        encoding: EncodingArg,
    },
    /// Identify the connection parameters from a recording (Steps I–VI, several passes).
    #[command(
        after_help = "Example:\n  jointid replay recordings/two-beam-friction.mcap --out results.mcap --json"
    )]
    Replay {
        recording: PathBuf,
        /// Use this setup instead of the one attached to the recording.
        #[arg(long)]
        setup: Option<PathBuf>,
        /// Maximum passes over the data (default: the setup's estimator.passes).
        #[arg(long)]
        passes: Option<usize>,
        #[arg(long, value_enum)]
        estimator: Option<EstimatorArg>,
        /// Write inputs, residual forces, connection states, parameters and diagnostics here.
        #[arg(long)]
        out: Option<PathBuf>,
        /// Track changing parameters: forgetting factor per sample, 0 < λ ≤ 1 (memory
        /// 1/(1 − λ) samples; default: the setup's estimator.forgetting).
        #[arg(long)]
        forgetting: Option<f64>,
        /// Solve the tracked fit every N samples (default: the setup's estimator.track_every);
        /// 0 = automatic: a quarter of the memory when forgetting, else a twentieth of the
        /// record.
        #[arg(long)]
        track_every: Option<usize>,
        /// Print one JSON object instead of the table.
        #[arg(long)]
        json: bool,
        /// Exit non-zero (after writing every output) when the identified model does not
        /// explain the data: residuals not white, fitted noise above the stated noise_std,
        /// or a normalised output-error cost above 2 (use it in scripts).
        #[arg(long)]
        strict: bool,
        /// Switch the output-error refinement off (the Kalman pipeline's last stage).
        #[arg(long)]
        no_refine: bool,
        /// Parametric bootstrap of an answer refined by prediction error (a `sign(u)` law, or
        /// a friction law on a record in motion) with N replicates: records simulated from
        /// the answer (and its start state, in motion) with the record's noise, identified
        /// again; the answer is corrected by their mean shift and its errors are at least
        /// their spread (~0.15 s per replicate at 2,000 samples). Default: 10 when the
        /// excitation repeats itself (a sine), is smooth between samples (an impact), the
        /// analytic errors depend on the secant they are made from (an excitation weak
        /// against the friction), or the law has a friction on the rate (`sign(v)`) — where
        /// they do not hold — else none; 0 switches it off (README, Accuracy). An answer of
        /// the free-run output error (e.g. Coulomb or a gap at rest) is bootstrapped when
        /// asked, and by itself for a friction law when the setup gives sensors'
        /// `noise_std`: each replicate is identified again by the whole procedure, and the
        /// errors are at least their spread (the answer is not corrected).
        #[arg(long, value_name = "N")]
        bootstrap: Option<usize>,
        /// The record starts in motion (cut from a running test): estimate its start state
        /// even when its first sample and the whole-record test read like rest (at high
        /// noise they can). Laws linear in the state (`--estimator ml`) always estimate it.
        #[arg(long)]
        in_motion: bool,
        /// Write SVG plots here: force–deformation loops with the identified law, measured
        /// against predicted response with fit %, parameters per pass.
        #[arg(long, value_name = "DIR")]
        plots: Option<PathBuf>,
    },
    /// Convert a CSV file of a test (a time column, one column per excitation channel and
    /// sensor of the setup, named as in the setup) into a recording with the setup attached.
    #[command(
        after_help = "Example:\n  jointid import test.csv --setup recordings/two-beam-spring.toml --out test.mcap\n  jointid replay test.mcap --plots plots/"
    )]
    Import {
        csv: PathBuf,
        /// The setup the data belong to (attached to the recording).
        #[arg(long)]
        setup: PathBuf,
        /// The recording to write.
        #[arg(long)]
        out: PathBuf,
        /// Name of the time column, in seconds (default: t, time, t_s or time_s).
        #[arg(long)]
        time_column: Option<String>,
        /// Sample interval (s) for a file without a time column (default: the setup's dt_s).
        #[arg(long)]
        dt: Option<f64>,
        /// Field delimiter, one character (default: detected from the header).
        #[arg(long)]
        delimiter: Option<char>,
        #[arg(long, value_enum, default_value = "binary")]
        encoding: EncodingArg,
        /// Print the summary as JSON.
        #[arg(long)]
        json: bool,
    },
    /// Export a setup's component model as Matrix Market (M, K, C), a DOF map and a setup
    /// that uses them.
    #[command(
        name = "export-mm",
        after_help = "Example:\n  jointid export-mm recordings/two-beam-friction.toml --out recordings/two-beam-mm"
    )]
    ExportMm {
        setup: PathBuf,
        /// Output directory (created).
        #[arg(long)]
        out: PathBuf,
    },
    /// Identify live from iceoryx2 excitation/response streams (see docs/LIVE.md).
    #[command(
        after_help = "Example:\n  jointid live --setup recordings/two-beam-friction.toml --record session.mcap\n  (then, in another terminal: acquire-sim --setup recordings/two-beam-friction.toml --rate 51200 --seconds 60)"
    )]
    Live {
        #[arg(long)]
        setup: PathBuf,
        /// Record the aligned inputs, residuals, parameters and diagnostics (MCAP).
        #[arg(long)]
        record: Option<PathBuf>,
        /// Online estimator: kalman (filter only, default) or paper (ml has no online step
        /// and is refused; the windows use the setup's `[estimator] kind`).
        #[arg(long, value_enum)]
        estimator: Option<EstimatorArg>,
        /// iceoryx2 global prefix (isolates sessions and test runs).
        #[arg(long)]
        prefix: Option<String>,
        /// Session name, the first element of every service name.
        #[arg(long, default_value = "default")]
        session: String,
        /// Publish the online fit every N samples.
        #[arg(long, default_value_t = 10_000)]
        refit_every: usize,
        /// Stop after this many aligned samples.
        #[arg(long)]
        samples: Option<u64>,
        /// Stop this many seconds after the first frame.
        #[arg(long)]
        seconds: Option<f64>,
        /// Sampling rate, Hz (default: measured from the stream).
        #[arg(long)]
        rate: Option<f64>,
        /// End this long (s) after a publisher vanished without end-of-stream and none came back.
        #[arg(long, default_value_t = 10.0)]
        idle_timeout: f64,
        /// Samples per identification window (default: the setup's `window_samples`, else
        /// 10,000; 0: no windows, the online fit alone). Each window is identified on a
        /// worker thread while the test runs; their combination is the session's answer.
        #[arg(long, alias = "buffer-samples")]
        window_samples: Option<usize>,
        /// Seconds of stream from one window's start to the next one's (default: the
        /// setup's `window_every`, else 20).
        #[arg(long)]
        window_every: Option<f64>,
        /// Tune the online Kalman filter by likelihood over the warm-up samples (better
        /// online values; stalls the stepper ~0.3 s once, see docs/LIVE.md).
        #[arg(long)]
        tune_warmup: bool,
        /// Record every k-th residual (1: all). The default keeps recordings compact (the
        /// inputs are always recorded whole, so `jointid replay` recomputes every residual).
        #[arg(long, default_value_t = 10)]
        record_residuals_every: usize,
        /// Print one JSON report at the end instead of the progress line and table.
        #[arg(long)]
        json: bool,
    },
    /// Summarise a recording: channels, samples, setup, truth, damage.
    Inspect {
        /// The recording (MCAP) to summarise.
        recording: PathBuf,
        /// Print one JSON object instead of the summary.
        #[arg(long)]
        json: bool,
    },
}

fn main() -> ExitCode {
    // iceoryx2 warns on every run that no config file was loaded (its defaults are what we
    // use); its errors still show, and `IOX2_LOG_LEVEL` overrides.
    iceoryx2::prelude::set_log_level_from_env_or(iceoryx2::prelude::LogLevel::Error);
    let cli = Cli::parse();
    match run(cli) {
        Ok(code) => code,
        Err(e) => {
            eprintln!("error: {}", jointid::app::error_line(e.as_ref()));
            ExitCode::FAILURE
        }
    }
}

fn run(cli: Cli) -> Result<ExitCode> {
    match cli.command {
        Command::ExportMm { setup, out } => {
            let s = Setup::from_file(&setup)?;
            // The setup and, for an external model, the files it reads are inputs.
            let mut inputs: Vec<&std::path::Path> = vec![&setup];
            if let Some(ext) = s.external.as_deref() {
                inputs.extend(
                    [&ext.mass.path, &ext.stiffness.path, &ext.dof_map].map(|p| p.as_path()),
                );
                inputs.extend(ext.damping.as_ref().map(|d| d.path.as_path()));
            }
            check_output_dir("--out", &out, jointid::matrix_market::EXPORT_FILES, &inputs)?;
            let sum = jointid::matrix_market::export(&s, &out)
                .with_context(|| format!("exporting {}", setup.display()))?;
            println!("exported {} DOFs:", sum.dofs);
            for f in &sum.files {
                println!("  {}", f.display());
            }
            Ok(ExitCode::SUCCESS)
        }
        Command::Simulate {
            setup,
            out,
            scenario,
            steps,
            dt,
            substeps,
            noise,
            seed,
            amplitude,
            freq,
            pulse,
            encoding,
        } => {
            check_output_file("--out", &out, &[&setup])?;
            let s = Setup::from_file(&setup)?;
            let dt_s = dt.unwrap_or(s.dt_s);
            let (sc, name) = match scenario {
                ScenarioArg::Sine => (
                    Scenario::Sine {
                        freq_hz: freq,
                        amplitude,
                    },
                    "sine",
                ),
                ScenarioArg::Random => (Scenario::Random { rms: amplitude }, "random"),
                ScenarioArg::Free => (
                    Scenario::Free {
                        amplitude,
                        pulse_s: pulse,
                    },
                    "free",
                ),
                ScenarioArg::Loosening => (
                    Scenario::RandomStiffnessDrop {
                        rms: amplitude,
                        at_s: 0.5 * steps as f64 * dt_s,
                        factor: 0.7,
                    },
                    "loosening",
                ),
            };
            let opts = SimulateOptions {
                scenario: sc,
                steps,
                dt_s,
                substeps,
                noise,
                seed,
            };
            let enc = match encoding {
                EncodingArg::Json => FrameEncoding::Json,
                EncodingArg::Binary => FrameEncoding::Binary,
            };
            let sum = app::simulate_recording(&s, &opts, &out, enc, name)
                .with_context(|| format!("simulating {}", setup.display()))?;
            println!(
                "wrote {} ({} samples, {name}, noise {noise}, {substeps} sub-steps; joint stuck {:.1} % of samples)",
                sum.out.display(),
                sum.samples,
                100.0 * sum.stuck_fraction
            );
            Ok(ExitCode::SUCCESS)
        }
        Command::Replay {
            recording,
            setup,
            passes,
            estimator,
            out,
            forgetting,
            track_every,
            json,
            strict,
            no_refine,
            bootstrap,
            plots,
            in_motion,
        } => {
            let req = ReplayRequest {
                recording,
                setup,
                passes,
                estimator: estimator.map(|e| match e {
                    EstimatorArg::Ml => EstimatorKind::Ml,
                    EstimatorArg::Paper => EstimatorKind::Paper,
                    EstimatorArg::Kalman => EstimatorKind::Kalman,
                }),
                out,
                forgetting,
                track_every,
                no_refine,
                plots,
                bootstrap,
                in_motion,
            };
            let bar = ProgressBar::new(0);
            bar.set_style(
                ProgressStyle::with_template("{prefix} [{bar:40}] {pos}/{len} samples {msg}")
                    .unwrap_or_else(|_| ProgressStyle::default_bar()),
            );
            let mut n = 0u64;
            let outcome = app::replay(&req, &mut |p| match p {
                Progress::Start { samples, .. } => {
                    n = samples as u64;
                    bar.set_length(n);
                    bar.set_prefix("pass 1");
                }
                Progress::Samples { pass, done } => {
                    bar.set_prefix(format!("pass {pass}"));
                    bar.set_position(done as u64);
                }
                Progress::Pass(r) => {
                    bar.set_position(n);
                    bar.set_prefix(format!("pass {}", r.pass + 1));
                    bar.set_message(format!(
                        "last change {:.3} se",
                        r.max_change_std_errors.unwrap_or(f64::NAN)
                    ));
                    bar.reset();
                }
            })?;
            bar.finish_and_clear();
            if json {
                println!("{}", serde_json::to_string_pretty(&outcome.to_json())?);
            } else {
                print_table(&outcome);
                if let Some(p) = &outcome.plots {
                    println!("plots: {} files", p.files.len());
                    for (sensor, fit) in &p.fit_percent {
                        println!("  predicted {sensor}: fit {fit:.1} %");
                    }
                    for note in &p.notes {
                        println!("  note: {note}");
                    }
                }
            }
            if let Some(e) = &outcome.input_error {
                anyhow::bail!(
                    "{e} (the {} samples before it were identified and written)",
                    outcome.samples
                );
            }
            if let Some(f) = &outcome.identification.failure {
                anyhow::bail!("{f}");
            }
            let inadequate = outcome.identification.inadequacy();
            if strict && !inadequate.is_empty() {
                anyhow::bail!(
                    "refused under --strict: the identified model does not explain the data ({} reason(s)): {}",
                    inadequate.len(),
                    inadequate.join("; ")
                );
            }
            Ok(ExitCode::SUCCESS)
        }
        Command::Import {
            csv,
            setup,
            out,
            time_column,
            dt,
            delimiter,
            encoding,
            json,
        } => {
            check_output_file("--out", &out, &[&csv, &setup])?;
            let s = Setup::from_file(&setup)?;
            let delimiter = match delimiter {
                None => None,
                Some(c) if c.is_ascii() => Some(c as u8),
                Some(c) => anyhow::bail!("--delimiter: {c:?} is not a single-byte character"),
            };
            let opts = jointid::io::csv::ImportOptions {
                time_column,
                dt_s: dt,
                delimiter,
                encoding: Some(match encoding {
                    EncodingArg::Json => FrameEncoding::Json,
                    EncodingArg::Binary => FrameEncoding::Binary,
                }),
            };
            let summary = jointid::io::csv::import_csv(&s, &csv, &out, &opts)?;
            if json {
                println!("{}", serde_json::to_string_pretty(&summary)?);
            } else {
                println!(
                    "wrote {}: {} samples at dt = {:e} s (from the {}){}",
                    summary.out.display(),
                    summary.samples,
                    summary.dt_s,
                    summary.dt_from,
                    if summary.setup_dt_replaced {
                        "; the attached setup's dt_s was set to the data's interval"
                    } else {
                        ""
                    }
                );
                if !summary.ignored_columns.is_empty() {
                    println!("ignored columns: {}", summary.ignored_columns.join(", "));
                }
            }
            Ok(ExitCode::SUCCESS)
        }
        Command::Live {
            setup,
            record,
            estimator,
            prefix,
            session,
            refit_every,
            samples,
            seconds,
            rate,
            idle_timeout,
            window_samples,
            window_every,
            record_residuals_every,
            tune_warmup,
            json,
        } => {
            if let Some(r) = &record {
                check_output_file("--record", r, &[&setup])?;
            }
            let s = Setup::from_file(&setup)?;
            let shm = ShmOptions {
                session,
                global_prefix: prefix,
                ..ShmOptions::default()
            };
            let mut o = LiveOptions::new(shm);
            o.estimator = match estimator {
                Some(EstimatorArg::Paper) => EstimatorKind::Paper,
                Some(EstimatorArg::Ml) => anyhow::bail!(
                    "--estimator ml: maximum likelihood has no online step; the online estimator is kalman (default) or paper (the windows are identified with the setup's [estimator] kind)"
                ),
                _ => EstimatorKind::Kalman,
            };
            o.refit_every = refit_every;
            o.max_samples = samples;
            o.max_seconds = seconds;
            o.rate_hz = rate;
            o.idle_timeout = std::time::Duration::from_secs_f64(idle_timeout.max(0.0));
            o.record = record;
            o.window_samples = window_samples;
            o.window_every_s = window_every;
            o.record_residuals_every = record_residuals_every;
            o.tune_warmup = tune_warmup;
            live(&s, o, json)
        }
        Command::Inspect { recording, json } => {
            let i = app::inspect(&recording)?;
            if json {
                println!("{}", serde_json::to_string_pretty(&i)?);
            } else {
                println!("{}", i.path.display());
                println!("  encoding     {}", i.encoding);
                println!(
                    "  setup        {}",
                    match i.setup_title.as_deref() {
                        Some("") => "(attached, untitled)",
                        Some(t) => t,
                        None if i.setup_attached => "(attached, invalid)",
                        None => "(none)",
                    }
                );
                if i.model_files_attached {
                    println!(
                        "  model files  attached (the setup's [model.matrix_market] files, as read)"
                    );
                }
                println!(
                    "  excitation   {} frames: {}",
                    i.excitation_frames,
                    i.excitation_channels.join(", ")
                );
                println!(
                    "  response     {} frames: {}",
                    i.response_frames,
                    i.response_channels.join(", ")
                );
                match (i.first_sample, i.last_sample) {
                    (Some(a), Some(b)) => {
                        println!("  samples      {a} .. {b} ({:.6} s)", i.duration_s)
                    }
                    _ => println!("  samples      none"),
                }
                for (k, v) in &i.truth {
                    println!("  truth        {k} = {v}");
                }
                for (k, v) in &i.facts {
                    println!("  fact         {k} = {v}");
                }
                if let Some(d) = &i.damage {
                    println!("  DAMAGED      {d}");
                }
                if let Some(e) = &i.error {
                    println!("  ERROR        {e}");
                }
            }
            // The summary above holds what was read before the error; the error itself
            // goes to stderr like every other command's.
            Ok(match &i.error {
                Some(e) => {
                    eprintln!("error: {e}");
                    ExitCode::FAILURE
                }
                None => ExitCode::SUCCESS,
            })
        }
    }
}

/// Runs a live session. The first SIGINT/SIGTERM/SIGQUIT sets the stop flag (the stages
/// drain and finalise, windows not yet identified are left to `replay`, so the session
/// ends within a second or two); a second one exits at once with status 130, leaving the
/// recording's `.partial` file with every chunk written so far (or the finished recording,
/// if the shutdown had already finalised it). `signal-hook` counts the
/// signals: iceoryx2's node signal handling reports one request again and again, so it
/// cannot tell a second signal from the first.
fn live(setup: &Setup, o: LiveOptions, json: bool) -> Result<ExitCode> {
    use signal_hook::consts::TERM_SIGNALS;
    for &sig in TERM_SIGNALS {
        // Order matters: the shutdown is armed by the flag the second registration sets.
        signal_hook::flag::register_conditional_shutdown(sig, 130, Arc::clone(&o.stop))
            .context("installing the signal handler")?;
        signal_hook::flag::register(sig, Arc::clone(&o.stop))
            .context("installing the signal handler")?;
    }
    if !json {
        // Until the first frame nothing else is printed: say what the session waits for.
        eprintln!(
            "waiting for frames on the iceoryx2 services {0}/jointid/excitation and {0}/jointid/response (Ctrl-C ends the session; --seconds counts from the first frame)",
            o.shm.session
        );
    }
    let worker_setup = setup.clone();
    let worker = std::thread::spawn(move || {
        let mut progress = |r: &LiveReport| {
            if !json {
                eprint!("\r\x1b[2K{}", progress_line(r));
            }
        };
        live::run(&worker_setup, &o, &mut progress)
    });
    let report = worker
        .join()
        .map_err(|_| anyhow::anyhow!("the live session panicked"))??;
    if json {
        let v = report.to_json(setup);
        println!("{}", serde_json::to_string_pretty(&v)?);
    } else {
        eprintln!();
        for w in &report.warnings {
            println!("warning: {w}");
        }
        println!("{}", progress_line(&report));
        println!("ended: {}", report.ended);
        let f = &report.faults;
        println!(
            "faults: {} missing in {} gaps, {} late/duplicate, {} unpaired, {} non-finite, {} restarts, {} segments, {} transport drops, {} outputs dropped",
            f.missing_samples,
            f.gaps,
            f.late_or_duplicate,
            f.unpaired,
            f.non_finite,
            f.restarts,
            f.segments,
            f.transport_drops,
            report.outputs_dropped
        );
        let session = report
            .final_identification
            .as_ref()
            .and_then(|i| i.session.as_ref().map(|s| (i, s)));
        if let Some((id, s)) = session {
            print_windows(s, id);
        }
        let kind = match session {
            Some((_, s)) => format!(
                "{} window(s) combined, {} samples seen",
                s.windows.iter().filter(|w| w.failure.is_none()).count(),
                s.samples_seen
            ),
            None if !report.window_parameters.is_empty() => format!(
                "combination of the {} window(s) identified before the stop",
                report.windows_identified
            ),
            None => "online fit (indicative, docs/LIVE.md)".into(),
        };
        println!("final parameters ({kind}):");
        for p in report.final_parameters() {
            println!("  {:<24} {:>14.6e} ± {:.3e}", p.key, p.value, p.std_error);
        }
        if let Some(r) = &report.recording {
            println!("recorded to {}", r.display());
        }
    }
    if let Some(e) = &report.error {
        anyhow::bail!("{e}");
    }
    Ok(ExitCode::SUCCESS)
}

fn progress_line(r: &LiveReport) -> String {
    // The windows' combination once there is one (the session's answer), else the online
    // fit, labelled.
    let (label, shown) = if r.window_parameters.is_empty() {
        ("online", &r.online_parameters)
    } else {
        ("windows", &r.window_parameters)
    };
    let params: Vec<String> = shown
        .iter()
        .map(|p| format!("{} {:.4e}±{:.1e}", p.key, p.value, p.std_error))
        .collect();
    let params = if params.is_empty() {
        String::new()
    } else {
        format!("{label}: {}", params.join(", "))
    };
    format!(
        "{} samples | {:.0} samples/s | RTF {:.2} | latency p50 {:.0} µs p99 {:.0} µs max {:.0} µs | missing {} late {} dropped-out {} | {}",
        r.samples,
        r.samples_per_s,
        r.real_time_factor,
        r.latency.median_us,
        r.latency.p99_us,
        r.latency.max_us,
        r.faults.missing_samples,
        r.faults.late_or_duplicate,
        r.outputs_dropped,
        params
    )
}

/// The windows of a windowed identification, one line each: samples and every
/// parameter's value ± standard error (or why the window gave none).
fn print_windows(s: &jointid::session::SessionReport, id: &jointid::identify::Identification) {
    let keys: Vec<String> = id
        .final_parameters()
        .map(|ps| ps.iter().map(|p| p.basis.clone()).collect())
        .unwrap_or_default();
    println!(
        "  {} window(s) of {} samples every {} ({} abandoned at a gap), combined by inverse variance:",
        s.windows.len(),
        s.window_samples,
        s.window_every,
        s.windows_abandoned
    );
    for w in &s.windows {
        let body = match &w.failure {
            Some(f) => format!("failed: {f}"),
            None => w
                .parameters
                .iter()
                .zip(&keys)
                .map(|((v, se), k)| format!("{k} {v:.5e} ± {se:.2e}"))
                .collect::<Vec<_>>()
                .join(", "),
        };
        println!(
            "  window {:>10}–{:<10} {body}",
            w.first_sample, w.last_sample
        );
    }
}

fn print_table(o: &ReplayOutcome) {
    let id = &o.identification;
    for w in &o.input_warnings {
        println!("warning: {w}");
    }
    println!(
        "{} — {} samples, estimator {}",
        o.recording.display(),
        o.samples,
        id.estimator
    );
    if let Some(s) = &id.session {
        print_windows(s, id);
    }
    if let Some(ml) = &id.maximum_likelihood {
        let worst = ml.whiteness.iter().copied().fold(0.0, f64::max);
        println!(
            "  maximum likelihood: {} iterations, {} samples, fitted noise {} (per channel), residual whiteness ≤ {worst:.2} (1 = white), fit {:.1}–{:.1} %",
            ml.iterations,
            o.samples,
            ml.noise_std
                .iter()
                .map(|s| format!("{s:.2e}"))
                .collect::<Vec<_>>()
                .join(" "),
            ml.fit_percent.iter().copied().fold(f64::INFINITY, f64::min),
            ml.fit_percent
                .iter()
                .copied()
                .fold(f64::NEG_INFINITY, f64::max),
        );
    }
    for p in id.passes.iter().filter(|_| id.maximum_likelihood.is_none()) {
        let d = &p.diagnostics;
        println!(
            "  pass {:>2}: cond(W½S) {:.3e}, |S| {:.3e}, error recursion ρ {}, fit cond {}, stuck samples excluded {:?}",
            p.pass,
            d.sensitivity_condition,
            d.sensitivity_gain,
            d.error_spectral_radius
                .map_or("-".into(), |r| format!("{r:.4}")),
            p.fit_condition
                .iter()
                .map(|c| format!("{c:.2e}"))
                .collect::<Vec<_>>()
                .join("/"),
            p.rows_excluded_stuck
        );
    }
    if let Some(last) = id.passes.last() {
        for w in &last.diagnostics.warnings {
            println!("warning: {w}");
        }
        println!();
        println!(
            "{:<12} {:<12} {:>14} {:>12} {:>12} {:>14} {:>9}  unit",
            "connection", "basis", "value", "std error", "CR bound", "truth", "error %"
        );
        for p in &last.parameters {
            let (truth, err) = match p.truth {
                Some(t) if t != 0.0 => (
                    format!("{t:.6e}"),
                    format!("{:.3}", 100.0 * (p.value - t) / t.abs()),
                ),
                Some(t) => (format!("{t:.6e}"), "-".into()),
                None => ("-".into(), "-".into()),
            };
            let bound = p.crlb.map_or("-".to_string(), |b| format!("{b:.3e}"));
            println!(
                "{:<12} {:<12} {:>14.6e} {:>12.3e} {:>12} {:>14} {:>9}  {}",
                p.connection, p.basis, p.value, p.std_error, bound, truth, err, p.unit
            );
        }
    }
    if let Some(track) = id.track.as_ref().filter(|t| t.forgetting < 1.0) {
        print_track(o, track);
    }
    if let Some(oe) = &id.output_error {
        println!(
            "output-error refinement: {} after {} iteration(s), normalised cost {:.4} -> {:.4} ({})",
            if oe.accepted {
                "accepted"
            } else {
                "not accepted"
            },
            oe.iterations,
            oe.cost_start,
            oe.cost_end,
            oe.note
        );
    }
    for n in &id.notes {
        println!("note: {n}");
    }
    println!();
    println!("{} pass(es): {}", id.passes.len(), id.stop_reason);
    if let Some(out) = &o.output {
        println!("results written to {}", out.display());
    }
}

/// The tracked parameters, at most ~20 rows spread over the record.
fn print_track(o: &ReplayOutcome, track: &jointid::track::Track) {
    let Some(last) = o.identification.passes.last() else {
        return;
    };
    println!();
    println!(
        "tracked (forgetting {} per sample, memory {:.0} samples, solved every {}):",
        track.forgetting, track.memory_samples, track.every
    );
    let labels: Vec<String> = last
        .parameters
        .iter()
        .map(|p| format!("{}.{}", p.connection, p.basis))
        .collect();
    print!("{:>10}", "sample");
    for l in &labels {
        print!(" {l:>26}");
    }
    println!();
    let stride = track.points.len().div_ceil(20).max(1);
    for (k, p) in track.points.iter().enumerate() {
        if k % stride != 0 && k + 1 != track.points.len() {
            continue;
        }
        print!("{:>10}", p.sample);
        for v in &p.parameters {
            match v {
                Some(v) => print!(" {:>14.6e} ± {:<9.2e}", v.value, v.std_error),
                None => print!(" {:>26}", "(unsolved)"),
            }
        }
        println!();
    }
}
