//! Regenerates the table in ACCURACY.md "What the 1989 estimator gives on the paper's problem":
//! `cargo run --release --example paper_table`. Sine input at node 1 (200 Hz, 2e4 N), data
//! from the identification's own discretisation (dt = 1e-4 s, one Newmark step per sample),
//! the paper's basis, 15 passes as in the paper, median |error| over 9 noise seeds.
use std::path::Path;

use jointid::identify::{IdentifyOptions, TestData, identify};
use jointid::setup::{EstimatorKind, Setup, Weighting};
use jointid::simulate::{Noise, Scenario, SimulateOptions, simulate};

fn main() {
    let root = Path::new(env!("CARGO_MANIFEST_DIR"));
    let est: EstimatorKind = std::env::args()
        .nth(1)
        .and_then(|s| s.parse().ok())
        .unwrap_or(EstimatorKind::Paper);
    println!(
        "| case | noise | samples | spring error % (median) | friction error % (median) | diverged/failed runs | ρ error recursion |"
    );
    println!("|---|---|---|---|---|---|---|");
    for case in ["two-beam-spring", "two-beam-friction"] {
        let setup = Setup::from_file(&root.join(format!("recordings/{case}.toml"))).expect("setup");
        for noise in [
            "cov:0.1",
            "cov:0.5",
            "cov:1.0",
            "additive:0.1",
            "additive:0.5",
            "additive:1.0",
        ] {
            for steps in [36usize, 72] {
                let mut spring = Vec::new();
                let mut fric = Vec::new();
                let mut failed = 0;
                let mut rho = f64::NAN;
                for seed in 1..=9 {
                    let sim = simulate(
                        &setup,
                        &SimulateOptions {
                            scenario: Scenario::Sine {
                                freq_hz: 200.0,
                                amplitude: 2e4,
                            },
                            steps,
                            dt_s: setup.dt_s,
                            substeps: 1,
                            noise: noise.parse::<Noise>().expect("noise"),
                            seed,
                        },
                    )
                    .expect("simulate");
                    let data = TestData {
                        samples: (0..steps as u64).collect(),
                        t_ns: (0..steps as u64).map(|i| i * 100_000).collect(),
                        excitation: sim.excitation,
                        response: sim.response,
                    };
                    let mut o = IdentifyOptions::from_setup(&setup);
                    o.estimator = est;
                    o.passes = 15;
                    o.weighting = Weighting::InverseVariance;
                    match identify(
                        &setup,
                        &data,
                        &o,
                        Some(&sim.truth),
                        &mut |_| {},
                        &mut |_, _| {},
                    ) {
                        Ok(r) if r.failure.is_none() => {
                            let p = r.final_parameters().expect("params");
                            rho = r
                                .passes
                                .last()
                                .and_then(|p| p.diagnostics.error_spectral_radius)
                                .unwrap_or(f64::NAN);
                            spring.push(100.0 * (p[1].value - 3e5).abs() / 3e5);
                            if case == "two-beam-friction" {
                                fric.push(100.0 * (p[0].value - 3000.0).abs() / 3000.0);
                            } else {
                                fric.push(p[0].value.abs());
                            }
                        }
                        _ => failed += 1,
                    }
                }
                let med = |v: &mut Vec<f64>| {
                    if v.is_empty() {
                        return f64::NAN;
                    }
                    v.sort_by(f64::total_cmp);
                    v[v.len() / 2]
                };
                let f = med(&mut fric);
                let fcol = if case == "two-beam-friction" {
                    format!("{f:.1}")
                } else {
                    format!("(true 0; got {f:.0} N)")
                };
                println!(
                    "| {case} | {noise} | {steps} | {:.1} | {fcol} | {failed}/9 | {rho:.2} |",
                    med(&mut spring)
                );
            }
        }
    }
}
