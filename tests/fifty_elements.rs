//! Issue 4 acceptance: "A 50-element-per-beam model with 6 stations, where the paper's
//! estimator diverges, is identified by the default one." The setups are
//! `recordings/two-beam-fifty*.toml` (101 DOFs; the default estimator identifies on their
//! Craig–Bampton reduction, `reduce_modes = 12`, 19 DOFs). Figures over seeds are made by
//! `cargo run --release --example fifty` (ACCURACY.md "The 50-element model").

use jointid::estimate::StepOutput;
use jointid::identify::{
    Identification, IdentifyOptions, TestData, build_estimator, channel_noise, identify,
};
use jointid::model::Model;
use jointid::setup::{EstimatorKind, Setup};
use jointid::simulate::{Noise, Scenario, SimulateOptions, Simulated, simulate};

fn setup(file: &str, model_substeps: usize) -> Setup {
    let path = format!("{}/recordings/{file}", env!("CARGO_MANIFEST_DIR"));
    let text = std::fs::read_to_string(&path).unwrap();
    let mut s = Setup::from_toml(&text, &path).unwrap();
    s.substeps = model_substeps;
    s
}

fn data(
    s: &Setup,
    steps: usize,
    data_substeps: usize,
    noise: Noise,
    seed: u64,
) -> (Simulated, TestData) {
    let sim = simulate(
        s,
        &SimulateOptions {
            scenario: Scenario::Random { rms: 2e4 },
            steps,
            dt_s: s.dt_s,
            substeps: data_substeps,
            noise,
            seed,
        },
    )
    .unwrap();
    let d = TestData {
        samples: (0..steps as u64).collect(),
        t_ns: vec![0; steps],
        excitation: sim.excitation.clone(),
        response: sim.response.clone(),
    };
    (sim, d)
}

fn run(s: &Setup, d: &TestData, truth: &[f64]) -> Identification {
    let opts = IdentifyOptions::from_setup(s);
    identify(s, d, &opts, Some(truth), &mut |_| {}, &mut |_, _| {}).unwrap()
}

fn rel(id: &Identification, j: usize) -> f64 {
    let p = &id.final_parameters().unwrap()[j];
    (p.value - p.truth.unwrap()) / p.truth.unwrap()
}

/// The paper's estimator on the full 101-DOF model, noise-free data from that model's own
/// discretisation (the case where the 5-element model is exact): its error recursion has a
/// spectral radius ≥ 1 (measured 8.0) and within 500 samples its residual force exceeds
/// 100× the largest true connection force (measured at sample ≈ 100).
#[test]
fn paper_estimator_diverges_on_the_fifty_element_model() {
    let mut s = setup("two-beam-fifty.toml", 1);
    s.estimator.reduce_modes = None;
    let (sim, d) = data(&s, 500, 1, Noise::None, 1);
    let peak = sim.force.iter().map(|f| f[0].abs()).fold(0.0, f64::max);
    let model = Model::assemble(&s).unwrap();
    assert_eq!(model.n(), 101);
    let mut opts = IdentifyOptions::from_setup(&s);
    opts.estimator = EstimatorKind::Paper;
    let (sigma, _) = channel_noise(&s, &d);
    let mut est = build_estimator(&s, &model, &s.initial_params(), &opts, &sigma, d.len()).unwrap();
    let rho = est.diagnostics().error_spectral_radius.unwrap();
    assert!(rho >= 1.0, "paper error recursion ρ = {rho}");
    let mut out = StepOutput::new(1);
    est.start(d.samples[0], &d.excitation[0]);
    let mut blew = None;
    for i in 1..d.len() {
        let ok = est.step(d.samples[i], &d.excitation[i], &d.response[i], &mut out);
        let r = out.residual.amax();
        if ok.is_err() || !r.is_finite() || r > 100.0 * peak {
            blew = Some(i);
            break;
        }
    }
    eprintln!("paper: ρ {rho:.3}, blew up at sample {blew:?}");
    assert!(
        blew.is_some(),
        "the paper's residual force stayed bounded (ρ {rho})"
    );
    // And the identification with it gives no usable spring.
    let res = identify(&s, &d, &opts, Some(&sim.truth), &mut |_| {}, &mut |_, _| {});
    if let Ok(id) = res {
        let e = rel(&id, 0);
        assert!(e.is_nan() || e.abs() >= 0.5, "paper spring error {e}");
    }
}

/// The default estimator on the reduced model, noise-free data of the full model's own
/// discretisation: spring within 0.01 % (measured −0.0001 %; the reduction's bias).
#[test]
fn default_identifies_the_spring_on_own_discretisation_data() {
    let s = setup("two-beam-fifty.toml", 1);
    assert_eq!(s.estimator.reduce_modes, Some(12));
    let (sim, d) = data(&s, 1000, 1, Noise::None, 1);
    let id = run(&s, &d, &sim.truth);
    let k = rel(&id, 0);
    eprintln!("spring {:.5} %", 100.0 * k);
    assert!(k.abs() < 1e-4, "spring {k}");
}

/// Continuous-time data (64 Newmark sub-steps per sample on the full model) with 10 %
/// additive noise, identified on the reduced model with 16 sub-steps, Coulomb friction +
/// spring: friction within 5 % and spring within 1 % (measured seeds 1–3: friction +0.02,
/// +1.5, +0.8 %; spring −0.10, +0.22, −0.09 %, on an older build; seed 1, the one run
/// here, −0.91 % and −0.15 % on the thirty-seventh and thirty-eighth sessions' builds
/// alike), where the paper's estimator has ρ in the tens of thousands and is off by over
/// 100 %.
#[test]
fn default_identifies_friction_and_spring_on_noisy_continuous_data() {
    let s = setup("two-beam-fifty-friction.toml", 16);
    let (sim, d) = data(&s, 2000, 64, Noise::Additive(0.1), 1);
    let id = run(&s, &d, &sim.truth);
    let (fr, k) = (rel(&id, 0), rel(&id, 1));
    eprintln!("friction {:.3} %, spring {:.3} %", 100.0 * fr, 100.0 * k);
    assert!(fr.abs() < 0.05, "friction {fr}");
    assert!(k.abs() < 0.01, "spring {k}");
    for p in id.final_parameters().unwrap() {
        assert!(
            p.std_error.is_finite() && p.std_error > 0.0,
            "{} se",
            p.basis
        );
    }
}
