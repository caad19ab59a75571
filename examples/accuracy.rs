//! Accuracy campaign of the estimators on the paper's two-beam problem: synthetic tests over
//! many noise seeds, each identified, summarised as the tables of ACCURACY.md (error of the mean,
//! spread over seeds, mean stated standard error, mean Cramér–Rao bound, coverage of the
//! stated 95 % intervals).
//!
//! ```text
//! cargo run --release --example accuracy -- [--setup FILE] [--basis u,sign(v)] [--truth 3e5,3000]
//!     [--noise 0.1] [--samples 2000] [--seeds 20] [--data-substeps 64] [--model-substeps 16]
//!     [--estimator kalman|paper] [--no-output-error] [--passes 10] [--grid]
//!     [--grid-samples 2000,20000] [--first-seed 1] [--verbose]
//! ```
//!
//! `--grid` runs the ACCURACY.md grid (noise 10/50/100 %, 2,000 and 20,000 samples, both
//! estimators) for the chosen connection law.

use anyhow::{Context, Result, bail};
use jointid::identify::{IdentifyOptions, TestData, identify};
use jointid::setup::{EstimatorKind, Setup};
use jointid::simulate::{Noise, Scenario, SimulateOptions, simulate};

#[derive(Clone)]
struct Config {
    setup: String,
    basis: Option<String>,
    truth: Option<String>,
    noise: f64,
    samples: usize,
    seeds: u64,
    data_substeps: usize,
    model_substeps: usize,
    estimator: EstimatorKind,
    output_error: bool,
    passes: usize,
    first_seed: u64,
    /// Print every seed's result and the output-error report (`--verbose`).
    verbose: bool,
}

/// The setup text with the connection's basis / truth / initial replaced (the two-beam
/// setups have one connection written on single lines).
fn setup_text(c: &Config) -> Result<String> {
    let text = std::fs::read_to_string(&c.setup).with_context(|| c.setup.clone())?;
    let mut out = String::new();
    let nb = c.basis.as_ref().map(|b| b.split(',').count());
    for line in text.lines() {
        let t = line.trim_start();
        if let (Some(b), true) = (&c.basis, t.starts_with("basis")) {
            let items: Vec<String> = b.split(',').map(|x| format!("\"{}\"", x.trim())).collect();
            out.push_str(&format!("basis = [{}]\n", items.join(", ")));
        } else if let (Some(tr), true) = (&c.truth, t.starts_with("truth")) {
            out.push_str(&format!("truth = [{tr}]\n"));
        } else if let (Some(n), true) = (nb, t.starts_with("initial")) {
            out.push_str(&format!("initial = [{}]\n", vec!["0.0"; n].join(", ")));
        } else if t.starts_with("substeps") {
            out.push_str(&format!("substeps = {}\n", c.model_substeps));
        } else {
            out.push_str(line);
            out.push('\n');
        }
    }
    Ok(out)
}

#[derive(Default)]
struct Stats {
    errors: Vec<Vec<f64>>,
    se: Vec<Vec<f64>>,
    crlb: Vec<Vec<f64>>,
    covered: Vec<usize>,
    runs: usize,
    converged: usize,
    oe_accepted: usize,
    failures: usize,
}

fn run(c: &Config) -> Result<(Setup, Vec<f64>, Stats)> {
    let text = setup_text(c)?;
    let setup = Setup::from_toml(&text, &c.setup)?;
    let truth: Vec<f64> = setup
        .connections
        .iter()
        .flat_map(|k| k.truth.clone().unwrap_or_default())
        .collect();
    let p = truth.len();
    let mut st = Stats {
        errors: vec![Vec::new(); p],
        se: vec![Vec::new(); p],
        crlb: vec![Vec::new(); p],
        covered: vec![0; p],
        ..Default::default()
    };
    for seed in c.first_seed..c.first_seed + c.seeds {
        let sim = simulate(
            &setup,
            &SimulateOptions {
                scenario: Scenario::Random { rms: 2e4 },
                steps: c.samples,
                dt_s: setup.dt_s,
                substeps: c.data_substeps,
                noise: if c.noise > 0.0 {
                    Noise::Additive(c.noise)
                } else {
                    Noise::None
                },
                seed,
            },
        )?;
        let data = TestData {
            samples: (0..c.samples as u64).collect(),
            t_ns: (0..c.samples as u64)
                .map(|i| (i as f64 * setup.dt_s * 1e9) as u64)
                .collect(),
            excitation: sim.excitation,
            response: sim.response,
        };
        let mut o = IdentifyOptions::from_setup(&setup);
        o.estimator = c.estimator;
        o.passes = c.passes;
        o.output_error = c.output_error && c.estimator == EstimatorKind::Kalman;
        let t0 = std::time::Instant::now();
        let r = match identify(&setup, &data, &o, Some(&truth), &mut |_| {}, &mut |_, _| {}) {
            Ok(r) => r,
            Err(e) => {
                eprintln!("seed {seed}: {e}");
                st.failures += 1;
                continue;
            }
        };
        st.runs += 1;
        st.converged += usize::from(r.converged);
        st.oe_accepted += usize::from(r.output_error.as_ref().is_some_and(|x| x.accepted));
        let Some(params) = r.final_parameters() else {
            st.failures += 1;
            continue;
        };
        if c.verbose {
            let errs: Vec<String> = params
                .iter()
                .zip(&truth)
                .map(|(q, t)| {
                    format!(
                        "{:+.5} % (se {:.5} %)",
                        100.0 * (q.value - t) / t,
                        100.0 * q.std_error / t
                    )
                })
                .collect();
            eprintln!(
                "seed {seed}: {} ({:.1} s)",
                errs.join(", "),
                t0.elapsed().as_secs_f64()
            );
            if let Some(oe) = &r.output_error {
                eprintln!(
                    "  output error: cost {:.4} → {:.4}, {}",
                    oe.cost_start, oe.cost_end, oe.note
                );
                if let Some(scan) = &oe.scan {
                    for m in &scan.minima {
                        eprintln!(
                            "  minimum from {}: {:?} cost {:.5}",
                            m.from, m.values, m.cost
                        );
                    }
                    eprintln!(
                        "  scan: {} points on {} samples over {:?}, basin half-width {:.4e}",
                        scan.points, scan.samples, scan.range, scan.basin_half_width
                    );
                }
            }
            for n in &r.notes {
                eprintln!("  note: {n}");
            }
        }
        for (j, q) in params.iter().enumerate() {
            st.errors[j].push(q.value - truth[j]);
            st.se[j].push(q.std_error);
            if let Some(b) = q.crlb {
                st.crlb[j].push(b);
            }
            if q.ci95[0] <= truth[j] && truth[j] <= q.ci95[1] {
                st.covered[j] += 1;
            }
        }
    }
    Ok((setup, truth, st))
}

fn mean(x: &[f64]) -> f64 {
    x.iter().sum::<f64>() / x.len().max(1) as f64
}

fn rms(x: &[f64]) -> f64 {
    (x.iter().map(|v| v * v).sum::<f64>() / x.len().max(1) as f64).sqrt()
}

fn print_rows(c: &Config, setup: &Setup, truth: &[f64], st: &Stats) {
    let labels = setup.param_keys();
    for j in 0..truth.len() {
        let scale = if truth[j] != 0.0 { truth[j].abs() } else { 1.0 };
        let unit = if truth[j] != 0.0 { "%" } else { "abs" };
        let f = |x: f64| {
            if unit == "%" {
                format!("{:.5}", 100.0 * x / scale)
            } else {
                format!("{x:.3e}")
            }
        };
        let crlb = if st.crlb[j].is_empty() {
            "-".to_string()
        } else {
            f(mean(&st.crlb[j]))
        };
        let spread = rms(&st.errors[j]);
        let ratio = if st.crlb[j].is_empty() {
            "-".to_string()
        } else {
            format!("{:.2}", spread / mean(&st.crlb[j]))
        };
        println!(
            "| {} | {:.0} % | {} | {} | {} | {} ({unit}) | {} | {} | {} | {} | {} | {:.0} % | {}/{} |",
            c.estimator,
            100.0 * c.noise,
            c.samples,
            c.data_substeps,
            c.model_substeps,
            labels[j],
            f(mean(&st.errors[j])),
            f(spread),
            f(mean(&st.se[j])),
            crlb,
            ratio,
            100.0 * st.covered[j] as f64 / st.runs.max(1) as f64,
            st.converged,
            st.runs,
        );
    }
    if st.failures > 0 || c.estimator == EstimatorKind::Kalman {
        eprintln!(
            "  runs {} failures {} output-error accepted {}",
            st.runs, st.failures, st.oe_accepted
        );
    }
}

fn header() {
    println!(
        "| estimator | noise | samples | data substeps | model substeps | parameter | mean error | spread (rms over seeds) | mean stated se | mean CR bound | spread / bound | 95 % coverage | converged |"
    );
    println!("|---|---|---|---|---|---|---|---|---|---|---|---|---|");
}

fn main() -> Result<()> {
    let mut c = Config {
        setup: "recordings/two-beam-spring.toml".into(),
        basis: Some("u".into()),
        truth: Some("3.0e5".into()),
        noise: 0.1,
        samples: 2000,
        seeds: 20,
        data_substeps: 64,
        model_substeps: 16,
        estimator: EstimatorKind::Kalman,
        output_error: true,
        passes: 10,
        first_seed: 1,
        verbose: false,
    };
    let mut grid = false;
    let mut grid_samples = vec![2000, 20000];
    let args: Vec<String> = std::env::args().skip(1).collect();
    let mut i = 0;
    while i < args.len() {
        let val = || args.get(i + 1).cloned().context("missing value");
        match args[i].as_str() {
            "--setup" => c.setup = val()?,
            "--basis" => c.basis = Some(val()?),
            "--truth" => c.truth = Some(val()?),
            "--noise" => c.noise = val()?.parse()?,
            "--samples" => c.samples = val()?.parse()?,
            "--seeds" => c.seeds = val()?.parse()?,
            "--first-seed" => c.first_seed = val()?.parse()?,
            "--data-substeps" => c.data_substeps = val()?.parse()?,
            "--model-substeps" => c.model_substeps = val()?.parse()?,
            "--passes" => c.passes = val()?.parse()?,
            "--estimator" => {
                c.estimator = match val()?.as_str() {
                    "kalman" => EstimatorKind::Kalman,
                    "paper" => EstimatorKind::Paper,
                    x => bail!("unknown estimator {x}"),
                }
            }
            "--grid-samples" => {
                grid_samples = val()?
                    .split(',')
                    .map(|x| x.trim().parse())
                    .collect::<Result<_, _>>()?
            }
            "--no-output-error" => {
                c.output_error = false;
                i -= 1;
            }
            "--verbose" => {
                c.verbose = true;
                i -= 1;
            }
            "--grid" => {
                grid = true;
                i -= 1;
            }
            x => bail!("unknown argument {x}"),
        }
        i += 2;
    }
    header();
    if grid {
        for &samples in &grid_samples {
            for noise in [0.1, 0.5, 1.0] {
                for est in [EstimatorKind::Paper, EstimatorKind::Kalman] {
                    let mut g = c.clone();
                    g.samples = samples;
                    g.noise = noise;
                    g.estimator = est;
                    let (s, t, st) = run(&g)?;
                    print_rows(&g, &s, &t, &st);
                }
            }
        }
    } else {
        let (s, t, st) = run(&c)?;
        print_rows(&c, &s, &t, &st);
    }
    Ok(())
}
