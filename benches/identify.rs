//! Time of a whole identification (`identify`) on the paper's two-beam model: the
//! maximum-likelihood estimator on a law linear in the state (`u`, `v`), 2,000 and 20,000
//! samples of 8-sub-step data at 1 % noise, the default Kalman pipeline on the shipped
//! spring setup for comparison, and the default pipeline on the shipped friction setup at
//! 2,000 and 100,000 samples (the two sizes issue 13 sets targets for: < 100 ms and < 5 s),
//! and a Coulomb law on the friction setup (the free-run output error's path).
//! `cargo bench --bench identify`; figures go to BENCHMARKS.md.
use std::path::Path;

use criterion::{Criterion, criterion_group, criterion_main};
use jointid::identify::{IdentifyOptions, TestData, identify};
use jointid::setup::{EstimatorKind, Setup};
use jointid::simulate::{Noise, Scenario, SimulateOptions, simulate};

fn setup_with_basis(basis: Option<(&str, &str)>) -> Setup {
    shipped_with_basis("two-beam-spring.toml", basis)
}

/// A shipped setup with its connection's basis and truth replaced (`None`: as it is).
fn shipped_with_basis(name: &str, basis: Option<(&str, &str)>) -> Setup {
    let path = Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("recordings")
        .join(name);
    let text = std::fs::read_to_string(&path).expect("setup");
    let Some((basis, truth)) = basis else {
        return Setup::from_toml(&text, name).expect("setup");
    };
    let n = basis.split(',').count();
    let text: String = text
        .lines()
        .map(|l| {
            let t = l.trim_start();
            if t.starts_with("basis") {
                format!("basis = [{basis}]\n")
            } else if t.starts_with("initial") {
                format!("initial = [{}]\n", vec!["0.0"; n].join(", "))
            } else if t.starts_with("truth") {
                format!("truth = [{truth}]\n")
            } else {
                format!("{l}\n")
            }
        })
        .collect();
    Setup::from_toml(&text, &format!("{name} with basis [{basis}]")).expect("setup")
}

/// A shipped setup as it is.
fn shipped(name: &str) -> Setup {
    shipped_with_basis(name, None)
}

fn data(setup: &Setup, n: usize) -> TestData {
    data_from(setup, n, 1000.0, 4)
}

/// `n` samples of random excitation of RMS `rms` N, 8-sub-step data, 1 % noise.
fn data_from(setup: &Setup, n: usize, rms: f64, seed: u64) -> TestData {
    let sim = simulate(
        setup,
        &SimulateOptions {
            scenario: Scenario::Random { rms },
            steps: n,
            dt_s: setup.dt_s,
            substeps: 8,
            noise: Noise::Additive(0.01),
            seed,
        },
    )
    .expect("simulate");
    TestData {
        samples: (0..n as u64).collect(),
        t_ns: (0..n as u64).map(|i| i * 100_000).collect(),
        excitation: sim.excitation,
        response: sim.response,
    }
}

fn bench_identify(c: &mut Criterion) {
    let mut group = c.benchmark_group("identify");
    group.sample_size(10);
    let uv = setup_with_basis(Some(("\"u\", \"v\"", "3.0e5, 0.0")));
    for n in [2_000, 20_000] {
        let d = data(&uv, n);
        let mut opts = IdentifyOptions::from_setup(&uv);
        opts.estimator = EstimatorKind::Ml;
        group.bench_function(format!("ml_u_v_{n}_samples"), |b| {
            b.iter(|| identify(&uv, &d, &opts, None, &mut |_| {}, &mut |_, _| {}).expect("ml"))
        });
    }
    let paper = setup_with_basis(None);
    let d = data(&paper, 2_000);
    let opts = IdentifyOptions::from_setup(&paper);
    group.bench_function("kalman_paper_basis_2000_samples", |b| {
        b.iter(|| identify(&paper, &d, &opts, None, &mut |_| {}, &mut |_, _| {}).expect("kalman"))
    });
    // The shipped friction setup's default pipeline (the `jointid replay` of a recording
    // made with `jointid simulate recordings/two-beam-friction.toml --substeps 8 --noise
    // additive:0.01`), at its default excitation (20,000 N RMS).
    let friction = shipped("two-beam-friction.toml");
    let opts = IdentifyOptions::from_setup(&friction);
    for n in [2_000, 100_000] {
        let d = data_from(&friction, n, 20_000.0, 8);
        group.bench_function(format!("kalman_friction_{n}_samples"), |b| {
            b.iter(|| {
                identify(&friction, &d, &opts, None, &mut |_| {}, &mut |_, _| {}).expect("kalman")
            })
        });
    }
    // Coulomb friction (`sign(v), u` on the friction setup): the residual-force stage is
    // refused and the free-run output error from a scan does the work — the slowest of the
    // default pipelines (issue 13's "most Kalman records").
    let coulomb = shipped_with_basis(
        "two-beam-friction.toml",
        Some(("\"sign(v)\", \"u\"", "3000.0, 3.0e5")),
    );
    let d = data_from(&coulomb, 2_000, 20_000.0, 8);
    let opts = IdentifyOptions::from_setup(&coulomb);
    group.bench_function("kalman_coulomb_2000_samples", |b| {
        b.iter(|| identify(&coulomb, &d, &opts, None, &mut |_| {}, &mut |_, _| {}).expect("kalman"))
    });
    group.finish();
}

criterion_group!(benches, bench_identify);
criterion_main!(benches);
