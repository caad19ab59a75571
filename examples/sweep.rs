//! Seed sweep of an estimator over synthetic tests: per row (data sub-steps × noise), the
//! coverage of the stated 95 % intervals, the largest |error|/se, the failures, the time per
//! identification (mean, median, 90th percentile) and how many records ran the parametric
//! bootstrap (which multiplies it).
//!
//! ```text
//! cargo run --release --example sweep -- SETUP [--estimator ml|kalman|paper] [--seeds 50]
//!     [--substeps 1,8,64] [--noise 0.01,0.1] [--steps 2000] [--skip 0] [--rms 2e4] [--verbose]
//!     [--from 1] [--true-sigma] [--notes] [--mid-record] [--bootstrap N]
//!     [--scenario random|sine|free] [--freq 200] [--pulse 0.005]
//! ```
//! The excitation is `jointid simulate`'s random input with RMS `--rms` N (default 2e4, the
//! command's default: what a user who follows the README gets; a law linear in the state
//! gives the same relative figures at any level, a friction law does not). `--scenario
//! sine` is a sine of `--freq` Hz and amplitude `--rms` N; `--scenario free` an impact
//! (a half-sine of `--pulse` s and peak `--rms` N) and the free decay after it.
//! `--skip K` drops the first K samples (a record that starts in motion); with `--mid-record`
//! the identification is told so (as a live window after the first is), otherwise it finds
//! out or not. `--bootstrap N` asks for N replicates (default: automatic). The setup's truth
//! is the reference; every parameter of every seed counts toward coverage.
#[path = "common/args.rs"]
mod args;
use jointid::identify::{IdentifyOptions, TestData, identify};
use jointid::setup::EstimatorKind;
use jointid::simulate::{Noise, Scenario, SimulateOptions, simulate};

fn main() -> anyhow::Result<()> {
    let a = args::Args::from_env();
    let get = |k: &str, d: &str| a.get(k, d);
    let (path, setup) = a.setup("sweep")?;
    let kind: EstimatorKind = get("--estimator", "ml")
        .parse()
        .map_err(anyhow::Error::msg)?;
    let seeds: u64 = get("--seeds", "50").parse()?;
    let from: u64 = get("--from", "1").parse()?;
    let steps: usize = get("--steps", "2000").parse()?;
    let skip: usize = get("--skip", "0").parse()?;
    if a.flag("--mid-record") && skip == 0 {
        anyhow::bail!("--mid-record says the record is cut: give --skip K > 0");
    }
    let rms: f64 = get("--rms", "2e4").parse()?;
    let scenario = match get("--scenario", "random").as_str() {
        "random" => Scenario::Random { rms },
        "sine" => Scenario::Sine {
            freq_hz: get("--freq", "200").parse()?,
            amplitude: rms,
        },
        "free" => Scenario::Free {
            amplitude: rms,
            pulse_s: get("--pulse", "0.005").parse()?,
        },
        other => anyhow::bail!("--scenario {other}: expected random, sine or free"),
    };
    let subs: Vec<usize> = get("--substeps", "1,8,64")
        .split(',')
        .map(|s| s.parse())
        .collect::<Result<_, _>>()?;
    let noises: Vec<f64> = get("--noise", "0.01")
        .split(',')
        .map(|s| s.parse())
        .collect::<Result<_, _>>()?;
    let keys = setup.param_keys();
    println!(
        "setup {path}, estimator {kind}, {seeds} seeds, {steps} samples (first {skip} dropped), excitation {scenario:?}"
    );
    println!(
        "| data sub-steps | noise | answered | failed | coverage 95 % | max abs(err)/se | mean time s | median time s | 90th pct time s | bootstrapped |"
    );
    println!("|---|---|---|---|---|---|---|---|---|---|");
    for &s in &subs {
        for &noise in &noises {
            let (mut inside, mut total, mut failed, mut answered) =
                (0usize, 0usize, 0usize, 0usize);
            let mut worst: f64 = 0.0;
            let mut time = 0.0;
            // Per record: its identification time (s), and how many ran the parametric
            // bootstrap (automatic or asked for), which multiplies it.
            let mut times: Vec<f64> = Vec::new();
            let mut bootstrapped = 0usize;
            let mut fails = Vec::new();
            for seed in from..from + seeds {
                let sim = simulate(
                    &setup,
                    &SimulateOptions {
                        scenario,
                        steps: steps + skip,
                        dt_s: setup.dt_s,
                        substeps: s,
                        noise: if noise > 0.0 {
                            Noise::Additive(noise)
                        } else {
                            Noise::None
                        },
                        seed,
                    },
                )?;
                let n = steps;
                let data = TestData {
                    samples: (0..n as u64).collect(),
                    t_ns: (0..n as u64)
                        .map(|i| (i as f64 * setup.dt_s * 1e9) as u64)
                        .collect(),
                    excitation: sim.excitation[skip..].to_vec(),
                    response: sim.response[skip..].to_vec(),
                };
                // `--true-sigma`: the sensors' noise levels given (the simulation's), not
                // estimated from the data.
                let given;
                let setup = if a.flag("--true-sigma") {
                    let mut g = setup.clone();
                    for (sensor, sd) in g.sensors.iter_mut().zip(&sim.noise_std) {
                        sensor.noise_std = Some(*sd);
                    }
                    given = g;
                    &given
                } else {
                    &setup
                };
                let mut opts = IdentifyOptions::from_setup(setup);
                opts.estimator = kind;
                // `--bootstrap N`: the parametric bootstrap's replicates (0: none; the
                // default: automatic, as `jointid replay`).
                if a.flag("--bootstrap") {
                    opts.bootstrap = Some(a.get("--bootstrap", "0").parse()?);
                }
                // `--mid-record`: the record is said to be cut from a longer one (as a live
                // window is), so it is identified with its initial state estimated.
                if a.flag("--mid-record") {
                    opts.starts_mid_record = Some(skip as u64);
                }
                let t = std::time::Instant::now();
                let r = identify(
                    setup,
                    &data,
                    &opts,
                    Some(&sim.truth),
                    &mut |_| {},
                    &mut |_, _| {},
                );
                let took = t.elapsed().as_secs_f64();
                time += took;
                times.push(took);
                if let Ok(id) = &r
                    && let Some(o) = id.output_error.as_ref()
                    && (o.bootstrap.is_some()
                        || o.prediction_error
                            .as_ref()
                            .is_some_and(|p| p.bootstrap.is_some()))
                {
                    bootstrapped += 1;
                }
                if a.flag("--verbose") {
                    println!("  seed {seed} time {took:.3} s");
                }
                match r {
                    // A failed identification (what `jointid replay` exits 1 on) counts as a
                    // failure even when it shows the passes' parameters.
                    Ok(id) if id.failure.is_some() => {
                        failed += 1;
                        if a.flag("--verbose") {
                            for n in id.notes.iter().filter(|n| n.contains("not used")) {
                                println!("  seed {seed} failed: {n}");
                            }
                        }
                        fails.push(format!("seed {seed}: {}", id.failure.unwrap_or_default()));
                    }
                    Ok(id) => match id.final_parameters() {
                        Some(ps) => {
                            answered += 1;
                            if a.flag("--notes") {
                                println!("  seed {seed} stop: {}", id.stop_reason);
                                for n in &id.notes {
                                    println!("  seed {seed} note: {n}");
                                }
                            }
                            for (k, p) in ps.iter().enumerate() {
                                let e =
                                    (p.value - sim.truth[k]) / p.std_error.max(f64::MIN_POSITIVE);
                                if e.abs() > worst.abs() {
                                    worst = e;
                                }
                                total += 1;
                                if e.abs() <= 1.96 {
                                    inside += 1;
                                }
                                if a.flag("--verbose") {
                                    // The prediction error's sandwich/naive ratio and
                                    // normalised cost, or the Cramér–Rao bound.
                                    let pem = id
                                        .output_error
                                        .as_ref()
                                        .and_then(|o| o.prediction_error.as_ref());
                                    let extra = match (pem, p.crlb) {
                                        (Some(rep), _) => format!(
                                            " sandwich/naive {:.3} cost {:.4} sub-steps {} secants {:.2} bootstrap {} stuck {}",
                                            rep.sandwich_ratio.get(k).copied().unwrap_or(f64::NAN),
                                            rep.cost_end,
                                            rep.substeps,
                                            rep.secant_disagreement.unwrap_or(f64::NAN),
                                            rep.bootstrap.as_ref().map_or(0, |b| b.used),
                                            id.passes.last().map_or(0, |p| p
                                                .rows_excluded_stuck
                                                .iter()
                                                .sum::<usize>())
                                        ),
                                        // …and the likelihood-ratio width over the
                                        // stated 95 % interval (> 1: widened to it).
                                        (None, Some(b)) => format!(
                                            " bound {b:.3e}{}",
                                            id.output_error
                                                .as_ref()
                                                .and_then(|o| o.likelihood_ratio_widths.as_ref())
                                                .and_then(|w| w.get(k).copied().flatten())
                                                .map(|w| format!(" lr {w:.2}"))
                                                .unwrap_or_default()
                                        ),
                                        _ => String::new(),
                                    };
                                    println!(
                                        "  seed {seed} {}: {:.6e} se {:.3e} err/se {e:.2} err {:.4e}{extra}",
                                        keys[k],
                                        p.value,
                                        p.std_error,
                                        p.value - sim.truth[k]
                                    );
                                }
                            }
                        }
                        None => {
                            failed += 1;
                        }
                    },
                    Err(e) => {
                        failed += 1;
                        fails.push(format!("seed {seed}: {e}"));
                    }
                }
            }
            times.sort_by(f64::total_cmp);
            // Nearest-rank percentiles of the records' times.
            let pct = |q: f64| {
                let k = ((q * times.len() as f64).ceil() as usize).clamp(1, times.len().max(1));
                times.get(k - 1).copied().unwrap_or(f64::NAN)
            };
            println!(
                "| {s} | {:.0} % | {answered} | {failed} | {:.0} % | {:.1} | {:.2} | {:.2} | {:.2} | {bootstrapped} |",
                noise * 100.0,
                100.0 * inside as f64 / total.max(1) as f64,
                worst.abs(),
                time / seeds as f64,
                pct(0.5),
                pct(0.9)
            );
            for f in fails.iter().take(3) {
                println!("    {f}");
            }
        }
    }
    Ok(())
}
