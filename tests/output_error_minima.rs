//! The output-error cost of an undamped structure oscillates in stiffness: a descent started
//! outside the global minimum's basin ends in a neighbouring minimum with a small stated
//! error. `refine_global` scans the stiffness for other minima and keeps the lowest cost.
//! Data from the model's own discretisation (2 sub-steps), 100 % noise, 1,000 samples, a
//! start 20 % low (the residual-force stage was measured 7–14 % low at 100 % noise).

mod common;

use jointid::estimate::output_error::{refine, refine_global};
use jointid::identify::{TestData, channel_noise};
use jointid::model::Model;
use jointid::setup::Setup;
use jointid::simulate::{Noise, Scenario, SimulateOptions, simulate};

const K: f64 = 3.0e5;

fn spring_setup() -> Setup {
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
                format!("truth = [{K:?}]")
            } else if t.starts_with("initial") {
                "initial = [0.0]".into()
            } else if t.starts_with("substeps") {
                "substeps = 2".into()
            } else {
                l.to_string()
            }
        })
        .collect::<Vec<_>>()
        .join("\n");
    Setup::from_toml(&text, "two-beam-spring").unwrap()
}

#[test]
fn stiffness_scan_finds_the_global_minimum_from_a_start_20_percent_low() {
    let setup = spring_setup();
    let n = 1000;
    let sim = simulate(
        &setup,
        &SimulateOptions {
            scenario: Scenario::Random { rms: 2e4 },
            steps: n,
            dt_s: setup.dt_s,
            substeps: 2,
            noise: Noise::Additive(1.0),
            seed: 1,
        },
    )
    .unwrap();
    let data = TestData {
        samples: (0..n as u64).collect(),
        t_ns: vec![0; n],
        excitation: sim.excitation,
        response: sim.response,
    };
    let model = Model::assemble(&setup).unwrap();
    let (sigma, _) = channel_noise(&setup, &data);
    let start = [0.8 * K];
    let scales = [0.01 * K];
    let args = (&data.excitation, &data.response, &sigma[..]);
    let plain = refine(
        &setup, &model, &start, &scales, args.0, args.1, args.2, 2, 20,
    )
    .unwrap();
    let global = refine_global(
        &setup, &model, &start, &scales, args.0, args.1, args.2, 2, 20,
    )
    .unwrap();
    let err = |v: f64| (v - K) / K;
    eprintln!(
        "plain {:+.3} % (cost {:.4}, se {:.3} %), global {:+.3} % (cost {:.4}, se {:.3} %)",
        100.0 * err(plain.values[0]),
        plain.report.cost_end,
        100.0 * plain.std_errors[0] / K,
        100.0 * err(global.values[0]),
        global.report.cost_end,
        100.0 * global.std_errors[0] / K
    );
    // The plain descent ends in a wrong minimum, many stated standard errors off.
    assert!(
        (plain.values[0] - K).abs() > 5.0 * plain.std_errors[0],
        "the plain descent was expected to stop in a wrong minimum"
    );
    // The scan's global minimum: within 0.5 % and within 3 stated standard errors.
    assert!(
        err(global.values[0]).abs() < 0.005,
        "{}",
        err(global.values[0])
    );
    assert!(
        (global.values[0] - K).abs() < 3.0 * global.std_errors[0],
        "truth outside 3 se: {} ± {}",
        global.values[0],
        global.std_errors[0]
    );
    assert!(global.report.cost_end < plain.report.cost_end);
    let scan = global.report.scan.as_ref().expect("scan report");
    assert!(scan.minima.len() >= 2);
}

/// On a long record the scan runs on a prefix (its basin is n/len times wider) and the
/// candidates are refined on windows growing to the whole record. A scan point next to the
/// truth that lies inside the *prefix* basin of a wrong plain minimum must still be refined:
/// 20,000 samples, 50 % noise, a start 1.5 % low (inside the prefix basin, several
/// whole-record basin half-widths off). Before the fix this ended at the plain descent's
/// wrong minimum (measured on continuous data: −1.2 %, cost 1.52 against 0.92 at the truth).
#[test]
fn long_record_scan_refines_a_candidate_inside_the_prefix_basin() {
    let setup = spring_setup();
    let n = 20_000;
    let sim = simulate(
        &setup,
        &SimulateOptions {
            scenario: Scenario::Random { rms: 2e4 },
            steps: n,
            dt_s: setup.dt_s,
            substeps: 2,
            noise: Noise::Additive(0.5),
            seed: 3,
        },
    )
    .unwrap();
    let data = TestData {
        samples: (0..n as u64).collect(),
        t_ns: vec![0; n],
        excitation: sim.excitation,
        response: sim.response,
    };
    let model = Model::assemble(&setup).unwrap();
    let (sigma, _) = channel_noise(&setup, &data);
    let start = [0.985 * K];
    let scales = [0.001 * K];
    let t0 = std::time::Instant::now();
    let plain = refine(
        &setup,
        &model,
        &start,
        &scales,
        &data.excitation,
        &data.response,
        &sigma,
        2,
        20,
    )
    .unwrap();
    let global = refine_global(
        &setup,
        &model,
        &start,
        &scales,
        &data.excitation,
        &data.response,
        &sigma,
        2,
        20,
    )
    .unwrap();
    let err = |v: f64| (v - K) / K;
    let scan = global.report.scan.as_ref().expect("scan report");
    eprintln!(
        "plain {:+.4} % (cost {:.4}, se {:.4} %), global {:+.4} % (cost {:.4}, se {:.4} %), scan {} points on {} samples, half-width {:.0}, {:.1} s",
        100.0 * err(plain.values[0]),
        plain.report.cost_end,
        100.0 * plain.std_errors[0] / K,
        100.0 * err(global.values[0]),
        global.report.cost_end,
        100.0 * global.std_errors[0] / K,
        scan.points,
        scan.samples,
        scan.basin_half_width,
        t0.elapsed().as_secs_f64()
    );
    assert!(
        (plain.values[0] - K).abs() > 5.0 * plain.std_errors[0],
        "the plain descent was expected to stop in a wrong minimum"
    );
    // The scan ran on a prefix, and the start lay inside that prefix's basin.
    assert!(scan.samples < n);
    let prefix_half_width = scan.basin_half_width * n as f64 / scan.samples as f64;
    assert!((start[0] - K).abs() < prefix_half_width);
    // The global minimum: within 0.02 % and 3 stated standard errors, not ambiguous.
    assert!(
        err(global.values[0]).abs() < 2e-4,
        "{}",
        err(global.values[0])
    );
    assert!(
        (global.values[0] - K).abs() < 3.0 * global.std_errors[0],
        "truth outside 3 se: {} ± {}",
        global.values[0],
        global.std_errors[0]
    );
    assert!(!scan.ambiguous);
}

/// The whole identification on continuous data (64 sub-steps, model 16), 100 % noise, 2,000
/// samples, for two seeds whose answers were confident and wrong before the scan skipped
/// only points within 3 standard errors (seed 23: +6.0 % with a 0.054 % stated error) and
/// spaced its points at 0.35 instead of 0.75 estimated basin half-widths (seed 98: −3.4 %
/// with 0.08 %); in both the truth's cost was lower by Δχ² ≈ 1,000–1,500. Seed 86 ended at
/// +0.40 % (4.0 se) with 32 model sub-steps: doubling to 64 lowered the cost by Δχ² = 300,
/// below the old raise threshold of 3σ of a χ² (465), and moves it to −0.04 %; the raise
/// now takes a linear law's finer model at Δχ² > 1 (`identify::substeps::raise_substeps`).
/// Now all three within 0.1 % (measured −0.038 %, −0.041 % and −0.006 %) with the truth
/// inside the stated 95 % interval.
#[test]
fn scan_reaches_narrow_true_basins_on_continuous_data() {
    use jointid::identify::{IdentifyOptions, identify};
    let setup = common::setup_variant("two-beam-spring.toml", &["u"], &[K], 16);
    let n = 2000;
    for seed in [23, 86, 98] {
        let sim = simulate(
            &setup,
            &SimulateOptions {
                scenario: Scenario::Random { rms: 2e4 },
                steps: n,
                dt_s: setup.dt_s,
                substeps: 64,
                noise: Noise::Additive(1.0),
                seed,
            },
        )
        .unwrap();
        let data = TestData {
            samples: (0..n as u64).collect(),
            t_ns: vec![0; n],
            excitation: sim.excitation,
            response: sim.response,
        };
        let opts = IdentifyOptions::from_setup(&setup);
        let id = identify(
            &setup,
            &data,
            &opts,
            Some(&[K]),
            &mut |_| {},
            &mut |_, _| {},
        )
        .unwrap();
        let p = &id.final_parameters().unwrap()[0];
        let rel = (p.value - K) / K;
        eprintln!(
            "seed {seed}: {:+.4} % (se {:.4} %)",
            100.0 * rel,
            100.0 * p.std_error / K
        );
        assert!(
            rel.abs() < 1e-3,
            "seed {seed}: spring {:+.3} %",
            100.0 * rel
        );
        assert!(
            p.ci95[0] <= K && K <= p.ci95[1],
            "seed {seed}: truth outside {:?}",
            p.ci95
        );
    }
}
