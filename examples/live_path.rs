//! Benchmark of the whole live path on the paper model (two-beam-friction setup):
//! `acquire-sim`'s publisher and `jointid live`'s pipeline in one process, over real
//! iceoryx2 services (own global prefix). Three runs: paced at the rate (latency from a
//! sample's acquisition stamp to its residual's publication), the same with a second
//! reader of both input streams that hangs (subscribes and never reads: what it costs the
//! acquisition loop and `jointid live`), and as fast as possible (sustained samples/s,
//! real-time factor).
//!
//! `cargo run --release --example live_path -- [SECONDS] [RATE_HZ]` (defaults 10, 51200).

use std::path::Path;
use std::sync::Arc;
use std::time::Duration;

use jointid::io::shm::ShmOptions;
use jointid::pipeline::acquire::{self, AcquireOptions};
use jointid::pipeline::live::{self, LiveOptions};
use jointid::setup::Setup;
use jointid::simulate::{Noise, Scenario};

fn main() -> anyhow::Result<()> {
    let args: Vec<String> = std::env::args().collect();
    let seconds: f64 = args.get(1).map_or(Ok(10.0), |s| s.parse())?;
    let rate: f64 = args.get(2).map_or(Ok(51_200.0), |s| s.parse())?;
    let setup = Setup::from_file(
        &Path::new(env!("CARGO_MANIFEST_DIR")).join("recordings/two-beam-friction.toml"),
    )?;
    println!(
        "live path, two-beam-friction (paper model), {seconds} s at {rate} Hz = {} samples",
        (seconds * rate) as usize
    );
    println!(
        "| run | samples | lost | samples/s | RTF at {rate} Hz | latency median µs | p99 µs | max µs | publishing a 64-sample block: median / p99 / max µs | stalled readers |"
    );
    println!("|---|---|---|---|---|---|---|---|---|---|");
    for (paced, hung) in [(true, false), (true, true), (false, false)] {
        let shm = ShmOptions {
            session: "bench".into(),
            global_prefix: Some(format!("jtbench{}_", std::process::id())),
            ..ShmOptions::default()
        };
        let shm_hung = shm.clone();
        let mut lo = LiveOptions::new(shm.clone());
        lo.window_samples = Some(0);
        lo.refit_every = rate as usize;
        let ao = AcquireOptions {
            shm,
            rate_hz: rate,
            samples: (seconds * rate) as usize,
            scenario: Scenario::Random { rms: 2e4 },
            noise: Noise::Additive(0.01),
            seed: 11,
            substeps: 8,
            as_fast_as_possible: !paced,
            block: 64,
            wait_subscriber: Duration::from_secs(30),
            end_of_stream: true,
            first_sample: 0,
            stop: Arc::default(),
        };
        let s = setup.clone();
        // The hung reader: one second into the session it subscribes to both input
        // streams, reads one frame of each, and never reads again.
        let publisher = std::thread::spawn(move || acquire::run(&s, &ao));
        let done = Arc::new(std::sync::atomic::AtomicBool::new(false));
        let hung_reader = hung.then(|| {
            let (shm, done) = (shm_hung.clone(), Arc::clone(&done));
            std::thread::spawn(move || -> anyhow::Result<()> {
                std::thread::sleep(Duration::from_secs(1));
                let mut subs = Vec::new();
                for stream in ["excitation", "response"] {
                    let mut sub = jointid::io::shm::FrameSubscriber::new(&shm, stream)?;
                    let t0 = std::time::Instant::now();
                    while sub.try_recv()?.is_none() && t0.elapsed() < Duration::from_secs(5) {
                        std::thread::sleep(Duration::from_millis(1));
                    }
                    subs.push(sub);
                }
                while !done.load(std::sync::atomic::Ordering::Acquire) {
                    std::thread::sleep(Duration::from_millis(50));
                }
                Ok(())
            })
        });
        let r = live::run(&setup, &lo, &mut |_| {})?;
        let a = publisher
            .join()
            .map_err(|_| anyhow::anyhow!("publisher panicked"))??;
        let f = &r.faults;
        let lost = (a.samples_published as u64).saturating_sub(r.samples)
            + f.missing_samples
            + f.transport_drops;
        let lat = if paced {
            format!(
                "{:.0} | {:.0} | {:.0}",
                r.latency.median_us, r.latency.p99_us, r.latency.max_us
            )
        } else {
            "– | – | –".into()
        };
        println!(
            "| {} | {} | {lost} | {:.0} | {:.2} | {lat} | {:.0} / {:.0} / {:.0} | {} |",
            match (paced, hung) {
                (true, false) => "paced",
                (true, true) => "paced, a second reader hung",
                _ => "as fast as possible",
            },
            r.samples,
            r.samples_per_s,
            r.real_time_factor,
            a.block_publish_us[0],
            a.block_publish_us[1],
            a.block_publish_us[2],
            a.stall_events
        );
        done.store(true, std::sync::atomic::Ordering::Release);
        if let Some(h) = hung_reader {
            h.join()
                .map_err(|_| anyhow::anyhow!("hung reader panicked"))??;
        }
    }
    Ok(())
}
