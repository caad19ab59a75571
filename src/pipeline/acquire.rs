//! A synthetic acquisition program (`acquire-sim`): simulates a test from the setup's true
//! connection law ([`crate::simulate`]) and publishes excitation and response frames over
//! iceoryx2 exactly as acquisition software would (contract in [`crate::io::shm`]), paced
//! at the sampling rate in blocks, then ends both streams with an end-of-stream frame.
//!
//! Time stamps: `t_ns` of sample `i` is the wall clock (Unix epoch, ns) at which the
//! sample is *acquired*, `t0 + i·dt`. Paced runs publish a block of `block` samples when
//! its last sample is due, like a DAQ card delivering blocks, so a sample waits up to one
//! block before publication; `jointid live` measures latency from `t_ns`, so that wait is
//! part of the reported latency. With `as_fast_as_possible`, `t0` is the start and the
//! stamps run ahead of the wall clock; latency is then not meaningful.
//!
//! The whole test is simulated before publishing starts (the implicit friction solver is
//! not real-time, and simulating first keeps the publication timing clean). Memory is
//! therefore about 0.4 kB per sample (60 s at 51.2 kHz ≈ 1.3 GB): use shorter runs or a
//! lower rate on small machines.

use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::{Duration, Instant, SystemTime, UNIX_EPOCH};

use serde::Serialize;

use crate::io::shm::{Frame, FramePublisher, ShmError, ShmOptions};
use crate::setup::Setup;
use crate::simulate::{Noise, Scenario, SimulateOptions, simulate};

#[derive(Debug, thiserror::Error)]
pub enum AcquireError {
    #[error(transparent)]
    Shm(#[from] ShmError),
    #[error(transparent)]
    Setup(#[from] crate::setup::SetupError),
    #[error(transparent)]
    Simulate(#[from] crate::simulate::SimulateError),
    #[error("invalid acquire-sim option: {0}")]
    Options(String),
    #[error(
        "no subscriber on `{stream}` within {waited:?} (is `jointid live` running with the same --prefix and --session?)"
    )]
    NoSubscriber {
        stream: &'static str,
        waited: Duration,
    },
}

#[derive(Debug, Clone)]
pub struct AcquireOptions {
    pub shm: ShmOptions,
    pub rate_hz: f64,
    pub samples: usize,
    pub scenario: Scenario,
    pub noise: Noise,
    pub seed: u64,
    /// Newmark steps per sample in the simulation (8: behaves like a continuous structure).
    pub substeps: usize,
    /// Publish as fast as possible instead of at the sampling rate.
    pub as_fast_as_possible: bool,
    /// Samples per published block (paced runs).
    pub block: usize,
    /// Wait this long for a subscriber on each input stream before publishing (0: don't).
    pub wait_subscriber: Duration,
    /// Send the end-of-stream frames at the end.
    pub end_of_stream: bool,
    /// First sample index (a restarted acquisition normally starts again at 0).
    pub first_sample: u64,
    /// Set to stop early (the end-of-stream frames are still sent).
    pub stop: Arc<AtomicBool>,
}

#[derive(Debug, Clone, Serialize)]
pub struct AcquireReport {
    pub samples_published: usize,
    pub rate_hz: f64,
    pub elapsed_s: f64,
    pub achieved_rate_hz: f64,
    /// Frames no subscriber received (published before anyone subscribed).
    pub frames_unsubscribed: u64,
    /// Per-subscriber deliveries dropped by the bounded backpressure (a stalled reader).
    pub backpressure_discards: u64,
    /// Subscribers waited for up to the backpressure timeout, then skipped as stalled.
    pub stall_events: u64,
    /// Wall time to publish one block (both streams and the notifications), µs: median,
    /// 99th percentile and maximum. What a slow or hung reader costs the acquisition loop.
    pub block_publish_us: [f64; 3],
    pub truth: Vec<(String, f64)>,
    pub stuck_fraction: f64,
}

fn unix_ns() -> u64 {
    SystemTime::now()
        .duration_since(UNIX_EPOCH)
        .map_or(0, |d| d.as_nanos() as u64)
}

/// Simulate and publish; see the module docs.
pub fn run(setup: &Setup, o: &AcquireOptions) -> Result<AcquireReport, AcquireError> {
    if !(o.rate_hz.is_finite() && o.rate_hz > 0.0) {
        return Err(AcquireError::Options(format!(
            "--rate {}: must be > 0 Hz",
            o.rate_hz
        )));
    }
    if o.samples < 2 {
        return Err(AcquireError::Options(
            "at least 2 samples are needed".into(),
        ));
    }
    let dt = 1.0 / o.rate_hz;
    let s = setup.at_rate(dt)?;
    let sim = simulate(
        &s,
        &SimulateOptions {
            scenario: o.scenario,
            steps: o.samples,
            dt_s: dt,
            substeps: o.substeps.max(1),
            noise: o.noise,
            seed: o.seed,
        },
    )?;
    let exc = FramePublisher::new(&o.shm, "excitation")?;
    let resp = FramePublisher::new(&o.shm, "response")?;
    if !o.wait_subscriber.is_zero() {
        for (stream, p) in [("excitation", &exc), ("response", &resp)] {
            if !p.wait_for_subscribers(1, o.wait_subscriber) {
                return Err(AcquireError::NoSubscriber {
                    stream,
                    waited: o.wait_subscriber,
                });
            }
        }
        // Let the subscriber threads connect to us before the first frame.
        std::thread::sleep(Duration::from_millis(100));
    }
    let block = o.block.max(1);
    let t0 = Instant::now();
    let unix0 = unix_ns();
    let mut unsubscribed = 0u64;
    let mut published = 0usize;
    let dt_ns = dt * 1e9;
    let mut i = 0usize;
    let mut block_us: Vec<f64> = Vec::with_capacity(sim.excitation.len() / block + 1);
    while i < sim.excitation.len() {
        if o.stop.load(Ordering::Acquire) {
            break;
        }
        let end = (i + block).min(sim.excitation.len());
        if !o.as_fast_as_possible {
            let due = Duration::from_secs_f64((end - 1) as f64 * dt);
            let now = t0.elapsed();
            if due > now {
                std::thread::sleep(due - now);
            }
        }
        let publishing = Instant::now();
        for k in i..end {
            let sample = o.first_sample + k as u64;
            let t_ns = unix0 + (k as f64 * dt_ns).round() as u64;
            let fe = Frame {
                sample,
                t_ns,
                values: sim.excitation[k].clone(),
            };
            let fr = Frame {
                sample,
                t_ns,
                values: sim.response[k].clone(),
            };
            if exc.publish(&fe)? == 0 {
                unsubscribed += 1;
            }
            if resp.publish(&fr)? == 0 {
                unsubscribed += 1;
            }
            published += 1;
        }
        exc.notify()?;
        resp.notify()?;
        block_us.push(publishing.elapsed().as_secs_f64() * 1e6);
        i = end;
    }
    block_us.sort_by(f64::total_cmp);
    let pct = |q: f64| {
        block_us
            .get(((block_us.len() as f64 - 1.0) * q).round() as usize)
            .copied()
            .unwrap_or(0.0)
    };
    let block_publish_us = [pct(0.5), pct(0.99), pct(1.0)];
    if o.end_of_stream {
        let eos = Frame {
            sample: o.first_sample + published as u64,
            t_ns: unix0 + (published as f64 * dt_ns).round() as u64,
            values: Vec::new(),
        };
        exc.publish(&eos)?;
        resp.publish(&eos)?;
        exc.notify()?;
        resp.notify()?;
    }
    let elapsed = t0.elapsed().as_secs_f64();
    Ok(AcquireReport {
        samples_published: published,
        rate_hz: o.rate_hz,
        elapsed_s: elapsed,
        achieved_rate_hz: published as f64 / elapsed.max(1e-9),
        frames_unsubscribed: unsubscribed,
        backpressure_discards: exc.backpressure_discards() + resp.backpressure_discards(),
        stall_events: exc.stall_events() + resp.stall_events(),
        block_publish_us,
        truth: setup.param_keys().into_iter().zip(sim.truth).collect(),
        stuck_fraction: sim.stuck_fraction,
    })
}
