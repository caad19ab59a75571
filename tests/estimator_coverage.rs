//! Honest uncertainty of the default estimator: over 100 noise seeds the stated 95 %
//! intervals contain the truth 90–99 % of the time, and the spread of the estimates is
//! within 1.5× the Cramér–Rao bound (spring-only joint of the paper's two-beam problem,
//! random input, 400 samples, additive noise at 100 % of each channel's RMS, data from the
//! model's own discretisation so the check isolates the statistics from the discretisation).

use jointid::identify::{IdentifyOptions, TestData, identify};
use jointid::setup::Setup;
use jointid::simulate::{Noise, Scenario, SimulateOptions, simulate};

fn spring_only() -> Setup {
    let text = std::fs::read_to_string(concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/recordings/two-beam-spring.toml"
    ))
    .unwrap();
    let text: String = text
        .lines()
        .map(|l| {
            let t = l.trim_start();
            if t.starts_with("basis") {
                "basis = [\"u\"]".to_string()
            } else if t.starts_with("truth") {
                "truth = [3.0e5]".to_string()
            } else if t.starts_with("initial") {
                "initial = [0.0]".to_string()
            } else {
                l.to_string()
            }
        })
        .collect::<Vec<_>>()
        .join("\n");
    Setup::from_toml(&text, "spring-only").unwrap()
}

#[test]
fn stated_intervals_cover_the_truth_90_to_99_percent_over_100_seeds() {
    let setup = spring_only();
    let truth = 3.0e5;
    let steps = 400;
    let seeds = 100;
    let mut covered = 0;
    let mut errors = Vec::new();
    let mut bounds = Vec::new();
    let mut converged = 0;
    for seed in 0..seeds {
        let sim = simulate(
            &setup,
            &SimulateOptions {
                scenario: Scenario::Random { rms: 2e4 },
                steps,
                dt_s: setup.dt_s,
                substeps: 1,
                noise: Noise::Additive(1.0),
                seed: 1000 + seed,
            },
        )
        .unwrap();
        let data = TestData {
            samples: (0..steps as u64).collect(),
            t_ns: vec![0; steps],
            excitation: sim.excitation,
            response: sim.response,
        };
        let opts = IdentifyOptions::from_setup(&setup);
        let r = identify(
            &setup,
            &data,
            &opts,
            Some(&[truth]),
            &mut |_| {},
            &mut |_, _| {},
        )
        .unwrap();
        converged += usize::from(r.converged);
        let p = &r.final_parameters().unwrap()[0];
        assert!(p.std_error.is_finite() && p.std_error > 0.0);
        if p.ci95[0] <= truth && truth <= p.ci95[1] {
            covered += 1;
        }
        errors.push(p.value - truth);
        bounds.push(p.crlb.expect("the Cramér–Rao bound is reported"));
    }
    let coverage = covered as f64 / seeds as f64;
    let spread = (errors.iter().map(|e| e * e).sum::<f64>() / seeds as f64).sqrt();
    let bound = bounds.iter().sum::<f64>() / seeds as f64;
    let bias = errors.iter().sum::<f64>() / seeds as f64;
    eprintln!(
        "coverage {coverage:.2}, spread {:.4} %, bound {:.4} %, bias {:.4} %, converged {converged}/{seeds}",
        100.0 * spread / truth,
        100.0 * bound / truth,
        100.0 * bias / truth
    );
    assert!(
        (0.90..=0.99).contains(&coverage),
        "coverage of the stated 95 % intervals {coverage}"
    );
    assert!(
        spread <= 1.5 * bound,
        "spread {spread} vs Cramér–Rao bound {bound}"
    );
    // No bias beyond the sampling error of the mean over 100 seeds (spread/10), with margin.
    assert!(bias.abs() <= 0.3 * spread, "bias {bias}, spread {spread}");
    assert!(
        converged >= seeds as usize / 2,
        "converged {converged}/{seeds}"
    );
}
