//! Per-sample cost of the paper estimator's step with the dense baseline, the modal step
//! and the sparse step, on the synthetic chains of `jointid::model::synthetic` (24 and 240
//! DOFs, 64 channels, 8 connection DOFs, all three; 2,400 and 24,000 DOFs with the sparse
//! step only; the 2,400-DOF dense/modal rows of BENCHMARKS.md come from
//! `cargo run --release --example bench_model`, whose set-up takes minutes).
//! `cargo bench --bench model_size`.
use std::hint::black_box;

use criterion::{Criterion, Throughput, criterion_group, criterion_main};
use jointid::estimate::StepOutput;
use jointid::identify::{IdentifyOptions, build_estimator};
use jointid::model::Model;
use jointid::model::synthetic::chain_setup_toml;
use jointid::setup::{EstimatorKind, Setup, StepKind};

fn bench_model_size(c: &mut Criterion) {
    let mut group = c.benchmark_group("paper_step");
    group.throughput(Throughput::Elements(1));
    for n in [24usize, 240, 2400, 24000] {
        let setup = Setup::from_toml(&chain_setup_toml(n, 64, 8), "chain").expect("setup");
        let model = Model::assemble(&setup).expect("model");
        let kinds: &[StepKind] = if n <= 240 {
            &[StepKind::Dense, StepKind::Modal, StepKind::Sparse]
        } else {
            &[StepKind::Sparse]
        };
        for &kind in kinds {
            let mut model = model.clone();
            model.step = kind;
            let mut opts = IdentifyOptions::from_setup(&setup);
            opts.estimator = EstimatorKind::Paper;
            let sigma = vec![1e-6; setup.sensors.len()];
            let mut est =
                build_estimator(&setup, &model, &setup.initial_params(), &opts, &sigma, 0)
                    .expect("estimator");
            let exc = [0.0];
            let meas = vec![0.0; setup.sensors.len()];
            let mut out = StepOutput::new(setup.connections.len());
            est.start(0, &exc);
            let mut i = 0u64;
            group.bench_function(format!("{n}dof_64ch_8conn/{kind:?}"), |b| {
                b.iter(|| {
                    i += 1;
                    let r = est.step(i, &exc, &meas, &mut out);
                    black_box((&r, &out));
                })
            });
        }
    }
    group.finish();
}

criterion_group!(benches, bench_model_size);
criterion_main!(benches);
