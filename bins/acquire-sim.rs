//! `acquire-sim`: a synthetic acquisition program. Simulates a test from the setup's true
//! connection law and publishes excitation and response frames over iceoryx2, paced at the
//! sampling rate, as real acquisition software would (see docs/LIVE.md).

use std::path::PathBuf;
use std::process::ExitCode;
use std::sync::Arc;
use std::time::Duration;

use anyhow::Result;
use clap::{Parser, ValueEnum};
use jointid::io::shm::ShmOptions;
use jointid::pipeline::acquire::{self, AcquireOptions};
use jointid::setup::Setup;
use jointid::simulate::{Noise, Scenario};

#[derive(Clone, Copy, ValueEnum)]
enum ScenarioArg {
    Sine,
    Random,
    Free,
}

#[derive(Parser)]
#[command(
    name = "acquire-sim",
    version,
    about = "Publish a simulated vibration test over iceoryx2 like acquisition software",
    after_help = "Example:\n  acquire-sim --setup recordings/two-beam-friction.toml --rate 51200 --seconds 60"
)]
struct Cli {
    #[arg(long)]
    setup: PathBuf,
    /// Sampling rate, Hz.
    #[arg(long, default_value_t = 51_200.0)]
    rate: f64,
    /// Duration, s (ignored when --samples is given).
    #[arg(long, default_value_t = 10.0)]
    seconds: f64,
    /// Number of samples (overrides --seconds).
    #[arg(long)]
    samples: Option<usize>,
    #[arg(long)]
    prefix: Option<String>,
    #[arg(long, default_value = "default")]
    session: String,
    #[arg(long, value_enum, default_value = "random")]
    scenario: ScenarioArg,
    /// Force RMS (random) or amplitude (sine, free), N.
    #[arg(long, default_value_t = 2.0e4)]
    amplitude: f64,
    #[arg(long, default_value_t = 200.0)]
    freq: f64,
    /// none, additive:LEVEL or cov:LEVEL.
    #[arg(long, default_value = "additive:0.01")]
    noise: Noise,
    #[arg(long, default_value_t = 11)]
    seed: u64,
    /// Newmark steps per sample in the simulation.
    #[arg(long, default_value_t = 8)]
    substeps: usize,
    /// Publish without pacing.
    #[arg(long)]
    as_fast_as_possible: bool,
    /// Samples per published block when paced.
    #[arg(long, default_value_t = 64)]
    block: usize,
    /// Seconds to wait for `jointid live` to subscribe (0: publish at once).
    #[arg(long, default_value_t = 10.0)]
    wait_subscriber: f64,
    /// Do not send end-of-stream frames (simulates a program that just stops).
    #[arg(long)]
    no_end_of_stream: bool,
    /// Index of the first sample.
    #[arg(long, default_value_t = 0)]
    first_sample: u64,
    #[arg(long)]
    json: bool,
}

fn main() -> ExitCode {
    // As `jointid`: iceoryx2's "no config file was loaded" warning on every run silenced;
    // its errors still show, and `IOX2_LOG_LEVEL` overrides.
    iceoryx2::prelude::set_log_level_from_env_or(iceoryx2::prelude::LogLevel::Error);
    match run(Cli::parse()) {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("error: {}", jointid::app::error_line(e.as_ref()));
            ExitCode::FAILURE
        }
    }
}

fn run(c: Cli) -> Result<()> {
    let setup = Setup::from_file(&c.setup)?;
    let samples = c
        .samples
        .unwrap_or_else(|| (c.seconds * c.rate).round().max(2.0) as usize);
    let scenario = match c.scenario {
        ScenarioArg::Sine => Scenario::Sine {
            freq_hz: c.freq,
            amplitude: c.amplitude,
        },
        ScenarioArg::Random => Scenario::Random { rms: c.amplitude },
        ScenarioArg::Free => Scenario::Free {
            amplitude: c.amplitude,
            // 50 samples at 10 kHz: resolved by the samples (see `jointid simulate --pulse`).
            pulse_s: 5e-3,
        },
    };
    let o = AcquireOptions {
        shm: ShmOptions {
            session: c.session,
            global_prefix: c.prefix,
            ..ShmOptions::default()
        },
        rate_hz: c.rate,
        samples,
        scenario,
        noise: c.noise,
        seed: c.seed,
        substeps: c.substeps,
        as_fast_as_possible: c.as_fast_as_possible,
        block: c.block,
        wait_subscriber: Duration::from_secs_f64(c.wait_subscriber.max(0.0)),
        end_of_stream: !c.no_end_of_stream,
        first_sample: c.first_sample,
        stop: Arc::default(),
    };
    let r = acquire::run(&setup, &o)?;
    if c.json {
        println!("{}", serde_json::to_string_pretty(&r)?);
    } else {
        println!(
            "published {} samples at {:.0} Hz in {:.3} s ({:.0} samples/s); {} frames unsubscribed, {} backpressure discards, {} stalled readers; publishing a block of {} took median {:.0} µs, p99 {:.0} µs, max {:.0} µs",
            r.samples_published,
            r.rate_hz,
            r.elapsed_s,
            r.achieved_rate_hz,
            r.frames_unsubscribed,
            r.backpressure_discards,
            r.stall_events,
            o.block,
            r.block_publish_us[0],
            r.block_publish_us[1],
            r.block_publish_us[2]
        );
    }
    Ok(())
}
