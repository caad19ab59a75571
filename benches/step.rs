//! Per-sample cost of the residual estimators on the paper's two-beam model (Steps I, III,
//! IV and the online Step V accumulation). `cargo bench --bench step`; figures go to
//! BENCHMARKS.md.
use std::hint::black_box;
use std::path::Path;

use criterion::{Criterion, Throughput, criterion_group, criterion_main};
use jointid::estimate::StepOutput;
use jointid::identify::{IdentifyOptions, ParameterAccumulator, build_estimator};
use jointid::model::Model;
use jointid::setup::{EstimatorKind, Setup};
use jointid::simulate::{Noise, Scenario, SimulateOptions, simulate};

fn bench_step(c: &mut Criterion) {
    let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("recordings/two-beam-friction.toml");
    let setup = Setup::from_file(&path).expect("setup");
    let model = Model::assemble(&setup).expect("model");
    let n = 4096;
    let sim = simulate(
        &setup,
        &SimulateOptions {
            scenario: Scenario::Random { rms: 2e4 },
            steps: n,
            dt_s: setup.dt_s,
            substeps: 1,
            noise: Noise::Additive(0.01),
            seed: 1,
        },
    )
    .expect("simulate");
    let sigma: Vec<f64> = vec![1e-3; setup.sensors.len()];
    let mut group = c.benchmark_group("step");
    group.throughput(Throughput::Elements(1));
    for kind in [EstimatorKind::Paper, EstimatorKind::Kalman] {
        let mut opts = IdentifyOptions::from_setup(&setup);
        opts.estimator = kind;
        opts.force_walk_std = Some(100.0);
        let params = setup.truth_params().expect("truth");
        // Kalman without the batch smoother: the per-sample (live) path.
        let mut est = if kind == EstimatorKind::Kalman {
            let with_terms = model.with_connection_terms(&setup, &params);
            let inputs = jointid::estimate::paper::EstimatorInputs {
                model: &with_terms,
                law: jointid::estimate::ConnectionLaw::new(&setup, &params),
                dt_s: setup.dt_s,
                substeps: 1,
                newmark: setup.newmark,
                weighting: opts.weighting,
                channel_sigma: sigma.clone(),
                spectral_diagnostics: false,
            };
            Box::new(
                jointid::estimate::kalman::KalmanEstimator::with_options(
                    inputs,
                    jointid::estimate::kalman::KalmanOptions {
                        force_walk_std: 100.0,
                        model_error_std: 1e-3,
                        smooth: false,
                        semi_implicit: true,
                        likelihood_only: false,
                        horizon: None,
                    },
                    0,
                )
                .expect("kalman"),
            ) as Box<dyn jointid::estimate::ResidualEstimator>
        } else {
            build_estimator(&setup, &model, &params, &opts, &sigma, n).expect("estimator")
        };
        let mut acc = ParameterAccumulator::new(&setup, 1e-6, 1.0);
        let mut out = StepOutput::new(1);
        let mut i = 1usize;
        est.start(0, &sim.excitation[0]);
        group.bench_function(format!("{kind}"), |b| {
            b.iter(|| {
                if i == n {
                    est.start(0, &sim.excitation[0]);
                    i = 1;
                }
                let ready = est
                    .step(i as u64, &sim.excitation[i], &sim.response[i], &mut out)
                    .unwrap_or(false);
                if ready {
                    acc.push(&out);
                }
                i += 1;
                black_box(&out);
            })
        });
    }
    group.finish();
}

criterion_group!(benches, bench_step);
criterion_main!(benches);
