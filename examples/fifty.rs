//! The 50-element-per-beam two-beam model (issue 4): the paper's estimator on the full
//! model against the default (Kalman + output-error) estimator on a Craig–Bampton reduction
//! of it. Prints the table in ACCURACY.md "The 50-element model".
//!
//! ```text
//! cargo run --release --example fifty -- [--samples 2000] [--seeds 3] [--modes 0,4,12] [--full]
//! ```
//!
//! `--full` also runs the default estimator on the unreduced model (≈ 3 min per run).

use std::time::Instant;

use jointid::identify::{IdentifyOptions, TestData, build_estimator, channel_noise, identify};
use jointid::model::Model;
use jointid::setup::{EstimatorKind, Setup};
use jointid::simulate::{Noise, Scenario, SimulateOptions, simulate};

fn setup(file: &str, model_substeps: usize, modes: Option<usize>) -> Setup {
    let path = format!("{}/recordings/{file}", env!("CARGO_MANIFEST_DIR"));
    let text = std::fs::read_to_string(&path).expect("setup file");
    let mut s = Setup::from_toml(&text, &path).expect("setup");
    s.substeps = model_substeps;
    s.estimator.reduce_modes = modes;
    s
}

struct Case {
    name: &'static str,
    data_substeps: usize,
    model_substeps: usize,
    noise: Noise,
}

/// The paper's estimator on the full model: spectral radius of its error recursion, the
/// first sample where its residual force exceeds 100× the largest true connection force
/// (or is not finite), and the identification's outcome.
fn paper(s: &Setup, data: &TestData, truth: &[f64], peak_force: f64) -> String {
    let model = Model::assemble(s).expect("model");
    let mut opts = IdentifyOptions::from_setup(s);
    opts.estimator = EstimatorKind::Paper;
    opts.output_error = false;
    let (sigma, _) = channel_noise(s, data);
    let params = s.initial_params();
    let with = model.clone();
    let mut est = build_estimator(s, &with, &params, &opts, &sigma, data.len()).expect("paper");
    let rho = est.diagnostics().error_spectral_radius.unwrap_or(f64::NAN);
    let mut out = jointid::estimate::StepOutput::new(s.connections.len());
    est.start(data.samples[0], &data.excitation[0]);
    let mut blew = None;
    for i in 1..data.len() {
        match est.step(
            data.samples[i],
            &data.excitation[i],
            &data.response[i],
            &mut out,
        ) {
            Ok(_) => {
                let r = out.residual.amax();
                if !r.is_finite() || r > 100.0 * peak_force {
                    blew = Some(i);
                    break;
                }
            }
            Err(_) => {
                blew = Some(i);
                break;
            }
        }
    }
    let outcome = match identify(s, data, &opts, Some(truth), &mut |_| {}, &mut |_, _| {}) {
        Ok(id) => match id.final_parameters() {
            Some(p) => p
                .iter()
                .map(|p| {
                    format!(
                        "{:+.3e} %",
                        100.0 * (p.value - p.truth.unwrap_or(f64::NAN))
                            / p.truth.unwrap_or(f64::NAN)
                    )
                })
                .collect::<Vec<_>>()
                .join(", "),
            None => "no parameters".into(),
        },
        Err(e) => format!(
            "stops: {}",
            e.to_string().chars().take(90).collect::<String>()
        ),
    };
    format!(
        "ρ {rho:.4}, |R| > 100× peak force at sample {}; identification {outcome}",
        blew.map_or("never".into(), |b| b.to_string())
    )
}

fn main() {
    let args: Vec<String> = std::env::args().collect();
    let arg = |k: &str| {
        args.iter()
            .position(|a| a == k)
            .map(|i| args[i + 1].clone())
    };
    let samples: usize = arg("--samples").map_or(2000, |v| v.parse().expect("--samples"));
    let seeds: u64 = arg("--seeds").map_or(3, |v| v.parse().expect("--seeds"));
    let modes: Vec<usize> = arg("--modes").map_or(vec![0, 4, 12], |v| {
        v.split(',').map(|x| x.parse().expect("--modes")).collect()
    });
    let full = args.iter().any(|a| a == "--full");
    let file = arg("--setup").unwrap_or("two-beam-fifty.toml".into());
    let cases = [
        Case {
            name: "own discretisation, noise-free",
            data_substeps: 1,
            model_substeps: 1,
            noise: Noise::None,
        },
        Case {
            name: "continuous (data 64 sub-steps, model 16), noise-free",
            data_substeps: 64,
            model_substeps: 16,
            noise: Noise::None,
        },
        Case {
            name: "continuous (64/16), 10 % noise",
            data_substeps: 64,
            model_substeps: 16,
            noise: Noise::Additive(0.1),
        },
    ];
    let full_model = Model::assemble(&setup(&file, 1, None)).expect("model");
    println!(
        "{file}: {} DOFs; reductions: {}",
        full_model.n(),
        modes
            .iter()
            .map(|&r| format!(
                "{r} modes → {} DOFs",
                full_model.craig_bampton(r).expect("reduce").n()
            ))
            .collect::<Vec<_>>()
            .join(", ")
    );
    for case in &cases {
        let seeds_here = if matches!(case.noise, Noise::None) {
            1
        } else {
            seeds
        };
        for seed in 1..=seeds_here {
            let base = setup(&file, case.model_substeps, None);
            let sim = simulate(
                &base,
                &SimulateOptions {
                    scenario: Scenario::Random { rms: 2e4 },
                    steps: samples,
                    dt_s: base.dt_s,
                    substeps: case.data_substeps,
                    noise: case.noise,
                    seed,
                },
            )
            .expect("simulate");
            let peak = sim
                .force
                .iter()
                .flat_map(|f| f.iter())
                .fold(0.0f64, |a, &b| a.max(b.abs()));
            let data = TestData {
                samples: (0..samples as u64).collect(),
                t_ns: vec![0; samples],
                excitation: sim.excitation.clone(),
                response: sim.response.clone(),
            };
            println!("\n## {} — seed {seed}, {samples} samples", case.name);
            println!(
                "paper (full model): {}",
                paper(&base, &data, &sim.truth, peak)
            );
            let mut variants: Vec<Option<usize>> = modes.iter().map(|&r| Some(r)).collect();
            if full {
                variants.push(None);
            }
            for r in variants {
                let s = setup(&file, case.model_substeps, r);
                let opts = IdentifyOptions::from_setup(&s);
                let t0 = Instant::now();
                let res = identify(
                    &s,
                    &data,
                    &opts,
                    Some(&sim.truth),
                    &mut |_| {},
                    &mut |_, _| {},
                );
                let secs = t0.elapsed().as_secs_f64();
                let label = r.map_or("full".to_string(), |r| format!("{r} modes"));
                match res {
                    Ok(id) => {
                        let ps = id.final_parameters().unwrap_or(&[]);
                        let txt = ps
                            .iter()
                            .map(|p| {
                                let t = p.truth.unwrap_or(f64::NAN);
                                format!(
                                    "{} {:+.4} % (se {:.4} %, bound {:.4} %)",
                                    p.basis,
                                    100.0 * (p.value - t) / t,
                                    100.0 * p.std_error / t.abs(),
                                    100.0 * p.crlb.unwrap_or(f64::NAN) / t.abs()
                                )
                            })
                            .collect::<Vec<_>>()
                            .join("; ");
                        let rho = id
                            .passes
                            .last()
                            .and_then(|p| p.diagnostics.error_spectral_radius)
                            .unwrap_or(f64::NAN);
                        println!(
                            "default, {label}: {txt}; passes {} ({}), Kalman ρ {rho:.6}, {secs:.1} s",
                            id.passes.len(),
                            if id.converged {
                                "converged"
                            } else {
                                "not converged"
                            }
                        );
                    }
                    Err(e) => println!("default, {label}: error {e} ({secs:.1} s)"),
                }
            }
        }
    }
}
