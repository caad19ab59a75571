//! Accuracy of the default (Kalman + output-error) estimator on the paper's two-beam
//! problem, with tolerances. The heavy grids (20,000 samples, many seeds) are in
//! `examples/accuracy.rs`, whose output is the table in ACCURACY.md; these are its light subset.

mod common;

use jointid::identify::{Identification, IdentifyOptions, TestData, identify};
use jointid::setup::Setup;
use jointid::simulate::{Noise, Scenario, SimulateOptions, Simulated, simulate};

/// The two-beam friction setup with the connection law and model sub-steps replaced.
fn two_beam(basis: &[&str], truth: &[f64], model_substeps: usize) -> Setup {
    common::setup_variant("two-beam-friction.toml", basis, truth, model_substeps)
}

fn run(
    setup: &Setup,
    steps: usize,
    data_substeps: usize,
    noise: Noise,
    seed: u64,
) -> Identification {
    run_with(setup, setup, steps, data_substeps, noise, seed)
}

/// [`run`] with the data simulated by `truth_setup` and identified with `setup`.
fn run_with(
    truth_setup: &Setup,
    setup: &Setup,
    steps: usize,
    data_substeps: usize,
    noise: Noise,
    seed: u64,
) -> Identification {
    let sim = simulate(
        truth_setup,
        &SimulateOptions {
            scenario: Scenario::Random { rms: 2e4 },
            steps,
            dt_s: truth_setup.dt_s,
            substeps: data_substeps,
            noise,
            seed,
        },
    )
    .unwrap();
    let data = TestData {
        samples: (0..steps as u64).collect(),
        t_ns: vec![0; steps],
        excitation: sim.excitation,
        response: sim.response,
    };
    let opts = IdentifyOptions::from_setup(setup);
    identify(
        setup,
        &data,
        &opts,
        Some(&sim.truth),
        &mut |_| {},
        &mut |_, _| {},
    )
    .unwrap()
}

/// Every identified parameter within `errors` of its stated standard errors of the truth.
fn assert_every_parameter_within(id: &Identification, errors: f64, what: &str) {
    for p in id.final_parameters().unwrap() {
        let t = p.truth.unwrap();
        let off = (p.value - t) / p.std_error;
        assert!(
            off.abs() < errors,
            "{what}: {} = {} ± {}, truth {t}: {off:.1} errors",
            p.basis,
            p.value,
            p.std_error
        );
    }
}

/// The shipped friction setup (`recordings/two-beam-friction.toml`).
fn shipped_friction_setup() -> Setup {
    let path = std::path::Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("recordings")
        .join("two-beam-friction.toml");
    Setup::from_file(&path).unwrap()
}

/// The prediction error's report of an identification refined by it.
fn prediction_error_report(
    id: &Identification,
) -> &jointid::estimate::prediction_error::PredictionErrorReport {
    id.output_error
        .as_ref()
        .and_then(|o| o.prediction_error.as_ref())
        .expect("refined by prediction error")
}

fn rel(id: &Identification, j: usize) -> f64 {
    let p = &id.final_parameters().unwrap()[j];
    (p.value - p.truth.unwrap()) / p.truth.unwrap()
}

/// Noise-free data from the model's own discretisation: exact recovery.
#[test]
fn noise_free_own_discretisation_is_recovered_exactly() {
    let s = two_beam(&["sign(v)", "u"], &[3000.0, 3.0e5], 1);
    let id = run(&s, 800, 1, Noise::None, 5);
    // No failure on noise-free data (a pass that blows up is taken off the passes, and the
    // refinement goes on from the one before it: `identify::discard_pass_that_diverged`).
    assert!(id.failure.is_none(), "{:?}: {}", id.failure, id.stop_reason);
    for j in 0..2 {
        assert!(
            rel(&id, j).abs() < 1e-6,
            "parameter {j}: {:.3e}",
            rel(&id, j)
        );
    }
}

/// Continuous-time data (64 sub-steps per sample) identified with 16 model sub-steps,
/// 10 % noise, 2,000 samples, Coulomb friction + spring, two seeds: friction within 5 %,
/// spring within 1 %, the truth inside the stated 95 % interval of both, and a standard
/// error not below the Cramér–Rao bound. Seed 4 ended +7.4 % with a 0.10 % stated error
/// before the output-error Jacobian of friction laws became a secant over ±1 standard error
/// (measured now: seed 2 +0.003 % (se 0.72 %), seed 4 +0.32 % (se 0.44 %)).
#[test]
fn continuous_data_coulomb_friction_and_spring() {
    let s = two_beam(&["sign(v)", "u"], &[3000.0, 3.0e5], 16);
    for seed in [2, 4] {
        let id = run(&s, 2000, 64, Noise::Additive(0.1), seed);
        let (fr, k) = (rel(&id, 0), rel(&id, 1));
        eprintln!(
            "seed {seed}: friction {:.3} %, spring {:.3} %",
            100.0 * fr,
            100.0 * k
        );
        assert!(fr.abs() < 0.05, "seed {seed}: friction {fr}");
        assert!(k.abs() < 0.01, "seed {seed}: spring {k}");
        for p in id.final_parameters().unwrap() {
            let b = p.crlb.expect("bound reported");
            let t = p.truth.unwrap();
            assert!(
                p.std_error >= 0.95 * b,
                "seed {seed}: {} se {} < bound {b}",
                p.basis,
                p.std_error
            );
            assert!(
                p.ci95[0] <= t && t <= p.ci95[1],
                "seed {seed}: {} truth {t} outside the stated interval {:?}",
                p.basis,
                p.ci95
            );
        }
    }
}

/// A Coulomb answer stopped in another valley of the friction's rough cost (data of the
/// model's own discretisation, 1 % noise, seed 9815 of a fresh sweep: `sign(v)` −0.39 %,
/// `u` +0.066 %). The likelihood-ratio walk along `sign(v)`'s profile line runs into
/// costs lower than the answer's, where the refitted `u` moves farther than `u`'s own line
/// showed (that one crossed 3.84 at 3.9 errors and left `u` 5.5 errors off). `u`'s error
/// now reaches the values it takes inside the region on the other line (measured: 1.7
/// errors off, its error 3.2× the line's own).
#[test]
fn an_error_reaches_what_another_parameters_line_found_inside_the_region() {
    let s = two_beam(&["sign(v)", "u"], &[3000.0, 3.0e5], 1);
    let id = run(&s, 2000, 1, Noise::Additive(0.01), 9815);
    assert!(
        id.notes
            .iter()
            .any(|n| n.contains("inside the region on another parameter's line")),
        "{:?}",
        id.notes
    );
    assert_every_parameter_within(&id, 3.0, "seed 9815");
}

/// The same at 100 % noise (seed 1): the first pass, run with zero joint stiffness, used to
/// be refused as an undetermined deformation (posterior std 1.23× the RMS of δ̂; 0.75–0.91
/// in the later passes) and the widened stuck band held every sample; now the first pass
/// only warns, the fit falls back to the band not widened, and the output-error stage ends
/// within 5 % (measured +1.4 %, se 5.7 %) with the truth inside the stated interval.
#[test]
fn continuous_data_coulomb_friction_at_full_noise() {
    let s = two_beam(&["sign(v)", "u"], &[3000.0, 3.0e5], 16);
    let id = run(&s, 2000, 64, Noise::Additive(1.0), 1);
    let fr = rel(&id, 0);
    eprintln!("friction {:.3} %", 100.0 * fr);
    assert!(fr.abs() < 0.05, "friction {fr}");
    let warned = |needle: &str| {
        id.passes
            .iter()
            .flat_map(|p| &p.diagnostics.warnings)
            .any(|w| w.contains(needle))
    };
    assert!(warned("run with the setup's initial parameters"));
    assert!(warned("fitted with the band not widened"));
    for p in id.final_parameters().unwrap() {
        let t = p.truth.unwrap();
        assert!(
            p.ci95[0] <= t && t <= p.ci95[1],
            "{} truth {t} outside {:?}",
            p.basis,
            p.ci95
        );
    }
}

/// The case of the shipped recording (paper's sign(u) friction, data with 8 sub-steps,
/// 1 % noise, identified with 1 sub-step): the passes now converge (the Kalman tuning is
/// frozen once it settles and the pass map is extrapolated), within the pass limit.
#[test]
fn passes_converge_on_the_shipped_friction_case() {
    let s = two_beam(
        &["sign(u)", "u", "const(100)", "v"],
        &[3000.0, 3.0e5, 0.0, 0.0],
        1,
    );
    let id = run(&s, 2000, 8, Noise::Additive(0.01), 11);
    assert!(id.converged, "{}", id.stop_reason);
    let (fr, k) = (rel(&id, 0), rel(&id, 1));
    eprintln!("friction {:.3} %, spring {:.3} %", 100.0 * fr, 100.0 * k);
    assert!(fr.abs() < 0.10, "friction {fr}");
    assert!(k.abs() < 0.02, "spring {k}");
}

/// The paper's `sign(u)` friction + spring on continuous data (64 sub-steps per sample,
/// 16 model sub-steps), 10 % noise, 2,000 samples, seed 3. The free-run output-error
/// refinement ended at −9.9 % friction with a 0.11 % stated error (its cost is rough: the
/// law is chaotic, and the descent stopped in a local minimum 89 se from the truth). The
/// prediction-error refinement (observer-corrected innovations, `estimate::prediction_error`)
/// ends within 5 % with the truth inside its stated 95 % intervals (measured +1.0 %,
/// se 2.0 %; spring −0.030 %, se 0.074 %; 21 s alone) and reports its observer tuning.
#[test]
fn continuous_data_sign_u_friction_by_prediction_error() {
    let s = two_beam(&["sign(u)", "u"], &[3000.0, 3.0e5], 16);
    let id = run(&s, 2000, 64, Noise::Additive(0.1), 3);
    let (fr, k) = (rel(&id, 0), rel(&id, 1));
    eprintln!("friction {:.3} %, spring {:.3} %", 100.0 * fr, 100.0 * k);
    assert!(fr.abs() < 0.05, "friction {fr}");
    assert!(k.abs() < 0.01, "spring {k}");
    for p in id.final_parameters().unwrap() {
        let t = p.truth.unwrap();
        assert!(
            p.ci95[0] <= t && t <= p.ci95[1],
            "{} truth {t} outside the stated interval {:?}",
            p.basis,
            p.ci95
        );
    }
    let oe = id.output_error.as_ref().expect("refinement report");
    let pe = oe
        .prediction_error
        .as_ref()
        .expect("prediction-error report");
    assert!(pe.force_std > 0.0 && pe.substeps == 64, "{pe:?}");
    assert!(
        id.notes.iter().any(|n| n.contains("process-noise force")),
        "{:?}",
        id.notes
    );
}

/// A record cut from a test in motion at 100 % noise (the shipped friction setup, 8-sub-step
/// data, samples 2,000–5,999 of seed 4): its first sample reads like rest (Σ(value/σ)² over
/// the 12 displacement and velocity channels below the at-rest limit on 100 of 100 such
/// records), so the passes run from rest. The prediction error's observer sees the start
/// state in the whole record's innovations (the cost a refitted start removes: about 2,600
/// against a limit of 59), and the identification runs again as for a record in motion.
/// Before: the joint damper `v` (truth 0) took the start's free vibration, 19 % coverage
/// over 16 seeds, up to 12 errors off; since: 95 %, worst 2.4 (2 of 16 refused by the
/// passes' observability check). On this seed every parameter is within 3 errors. The same
/// record uncut (at rest) is not flagged.
#[test]
fn a_cut_record_at_full_noise_is_seen_in_motion_by_its_innovations() {
    let setup = shipped_friction_setup();
    let sim = simulate(
        &setup,
        &SimulateOptions {
            scenario: Scenario::Random { rms: 2e4 },
            steps: 6000,
            dt_s: setup.dt_s,
            substeps: 8,
            noise: Noise::Additive(1.0),
            seed: 4,
        },
    )
    .unwrap();
    let seen = "starts in motion although its first sample reads like rest";
    for (skip, in_motion) in [(2000, true), (0, false)] {
        let data = TestData {
            samples: (0..4000).collect(),
            t_ns: vec![0; 4000],
            excitation: sim.excitation[skip..skip + 4000].to_vec(),
            response: sim.response[skip..skip + 4000].to_vec(),
        };
        let opts = IdentifyOptions::from_setup(&setup);
        let id = identify(
            &setup,
            &data,
            &opts,
            Some(&sim.truth),
            &mut |_| {},
            &mut |_, _| {},
        )
        .unwrap();
        assert_eq!(
            id.notes.iter().any(|n| n.contains(seen)),
            in_motion,
            "skip {skip}: {:?}",
            id.notes
        );
        assert!(id.failure.is_none(), "skip {skip}: {:?}", id.failure);
        assert_every_parameter_within(&id, 3.0, &format!("skip {skip}"));
    }
}

/// The Coulomb variant of the paper's setup (`sign(v), u`, the model at 1 sub-step) and
/// 2,500 samples of its random test (20,000 N RMS) with `data_substeps` sub-steps and
/// additive noise `noise` (of each channel's RMS).
fn coulomb_test(data_substeps: usize, noise: f64, seed: u64) -> (Setup, Simulated) {
    let setup = two_beam(&["sign(v)", "u"], &[3000.0, 3.0e5], 1);
    let sim = simulate(
        &setup,
        &SimulateOptions {
            scenario: Scenario::Random { rms: 2e4 },
            steps: 2500,
            dt_s: setup.dt_s,
            substeps: data_substeps,
            noise: Noise::Additive(noise),
            seed,
        },
    )
    .unwrap();
    (setup, sim)
}

/// Samples `skip .. skip + 2,000` of a test simulated at `dt_s`, numbered as in the test.
fn window(sim: &Simulated, dt_s: f64, skip: usize) -> TestData {
    TestData {
        samples: (skip as u64..skip as u64 + 2000).collect(),
        t_ns: (skip..skip + 2000)
            .map(|i| (i as f64 * dt_s * 1e9).round() as u64)
            .collect(),
        excitation: sim.excitation[skip..skip + 2000].to_vec(),
        response: sim.response[skip..skip + 2000].to_vec(),
    }
}

/// A record cut from a test in motion whose first sample reads like rest, on a law without
/// a `sign(u)` term (Coulomb `sign(v), u`; 64-sub-step data, 10 % noise, samples 500–2,499
/// of seed 5022): the free-run output error starts the model at rest, and its answer was
/// `sign(v)` +54, `u` −25 standard errors off with only a misfit note (8 of 120 fresh such
/// records, twenty-sixth session). The misfit is tested for a start in motion (the
/// prediction error's likelihood-ratio test at the answer); from the twenty-sixth session
/// such a record was refused, since the thirty-first it is identified again with its start
/// state estimated and refined by prediction error, as a `sign(u)` law's: every parameter
/// within 3 errors, and a note says why it ran twice (since the thirty-second session with
/// the parametric bootstrap, which runs for a friction on the rate refined by prediction
/// error). The same simulation from its start (at rest) is answered by the free-run output
/// error, every parameter within 3 errors.
#[test]
fn a_coulomb_record_cut_in_motion_is_identified_with_its_start_state() {
    let (setup, sim) = coulomb_test(64, 0.1, 5022);
    let cut = |skip: usize| window(&sim, setup.dt_s, skip);
    let opts = IdentifyOptions::from_setup(&setup);
    let id = identify(
        &setup,
        &cut(500),
        &opts,
        Some(&sim.truth),
        &mut |_| {},
        &mut |_, _| {},
    )
    .unwrap();
    assert!(id.failure.is_none(), "{:?}", id.failure);
    assert!(
        id.notes
            .iter()
            .any(|n| n
                .contains("so the identification was run again with the start state estimated")),
        "{:?}",
        id.notes
    );
    assert!(
        id.output_error
            .as_ref()
            .is_some_and(|o| o.prediction_error.is_some()),
        "not refined by prediction error: {:?}",
        id.notes
    );
    assert_every_parameter_within(&id, 3.0, "cut in motion");
    let id = identify(
        &setup,
        &cut(0),
        &opts,
        Some(&sim.truth),
        &mut |_| {},
        &mut |_, _| {},
    )
    .unwrap();
    assert!(id.failure.is_none(), "{:?}", id.failure);
    assert!(
        id.output_error
            .as_ref()
            .is_some_and(|o| o.prediction_error.is_none()),
        "at rest: the free-run output error"
    );
    assert_every_parameter_within(&id, 3.0, "from rest");
}

/// A Coulomb record cut from a running test at 100 % noise and said to be (as a live window
/// after the first is): refined by prediction error with its start state estimated, where
/// the observer feeds the noise into the model's rate and moves the friction's switching.
/// Until the thirty-second session `sign(v)` came out +78 % (4.0 errors) on this record
/// (seed 7305, 8-sub-step data; 14 of 15 such answers 2.5–4.8 errors off); the automatic
/// bootstrap now runs for a friction on the rate, from the answer's start state, and
/// corrects it: every parameter within 2 errors, and the note says why it ran.
#[test]
fn a_rate_friction_cut_in_motion_at_full_noise_is_corrected_by_the_bootstrap() {
    let (setup, sim) = coulomb_test(8, 1.0, 7305);
    let data = window(&sim, setup.dt_s, 500);
    let opts = IdentifyOptions {
        starts_mid_record: Some(500),
        ..IdentifyOptions::from_setup(&setup)
    };
    let id = identify(
        &setup,
        &data,
        &opts,
        Some(&sim.truth),
        &mut |_| {},
        &mut |_, _| {},
    )
    .unwrap();
    assert!(id.failure.is_none(), "{:?}", id.failure);
    let rep = prediction_error_report(&id);
    let boot = rep.bootstrap.as_ref().expect("the bootstrap ran");
    assert!(boot.used >= 5, "{boot:?}");
    assert!(
        id.notes.iter().any(|n| n.contains("friction on the rate")
            && n.contains("start state (the record starts in motion")),
        "{:?}",
        id.notes
    );
    assert_every_parameter_within(&id, 2.0, "rate friction cut in motion, 100 % noise");
}

/// The prediction error runs at the likeliest model sub-steps (the finest within Δχ² = 1 of
/// it), not the coarsest within 3 standard deviations of ½χ², the rule until the
/// fifty-seventh session. On 64-sub-step data at 100 % noise (the shipped friction setup,
/// 2,000 samples) that rule kept 16 or 32 sub-steps, whose discretisation error biased the
/// answer: seed 10328 at 16 sub-steps `u` +5.5, `sign(u)` −4.2 and `v` +4.3 errors off (over
/// seeds 10301–10350 the spring came out high on 41 of 50 records). The coarser level's slight
/// frequency error also left a beat that a start state's free vibration fits: seed 4 at rest
/// was flagged in motion at the kept level (3.1× the limit) and cleared only by a second test
/// at the likeliest. Now both are refined at 64 sub-steps, one start-at-rest test there reads
/// about 0.3× the limit, and every parameter is within 2 errors (seed 10328: 1.5 at most).
#[test]
fn the_prediction_error_runs_at_the_likeliest_model_level() {
    let setup = shipped_friction_setup();
    for seed in [10328, 4] {
        let id = run(&setup, 2000, 64, Noise::Additive(1.0), seed);
        assert!(id.failure.is_none(), "seed {seed}: {:?}", id.failure);
        assert!(id.motion_in_record.is_none(), "seed {seed}: {:?}", id.notes);
        let pem = prediction_error_report(&id);
        assert_eq!(pem.substeps, 64, "seed {seed}: {:?}", id.notes);
        let tests = &pem.start_at_rest_tests;
        assert_eq!(tests.len(), 1, "seed {seed}: {tests:?}");
        assert_eq!(tests[0].substeps, 64, "seed {seed}: {tests:?}");
        assert!(
            tests[0].statistic < 0.6 * tests[0].limit,
            "seed {seed}, at rest: {tests:?}"
        );
        assert_every_parameter_within(&id, 2.0, &format!("seed {seed}"));
    }
}

/// Long continuous records whose model level, kept on the first 2,000 samples, misfits the
/// whole record (the shipped friction setup, 20,000 samples of 64-sub-step data, 10 % noise,
/// seeds 1 and 2): under the rule before the fifty-seventh session (the coarsest level within
/// 3 standard deviations of ½χ² of the likeliest) 32 sub-steps were kept on the prefix but
/// left a normalised innovation cost of 7.9 and 1.7 on the whole record — seed 1's answer was
/// refused and the free-run output error gave the friction −51 % ± 43 % after 9 minutes,
/// seed 2's spring was 3.8 errors off. The likeliest level is now kept (and a finer one tied
/// with it on the prefix is checked again on the whole record):
/// both are refined at 64 sub-steps, their cost below 1 and every parameter within 3 errors.
#[test]
fn a_level_that_misfits_the_whole_record_gives_way_to_the_likeliest() {
    let setup = shipped_friction_setup();
    for seed in [1, 2] {
        let id = run(&setup, 20_000, 64, Noise::Additive(0.1), seed);
        assert!(id.failure.is_none(), "seed {seed}: {:?}", id.failure);
        assert!(
            !id.notes.iter().any(|n| n.contains("refinement not used")),
            "seed {seed}: {:?}",
            id.notes
        );
        let pem = prediction_error_report(&id);
        assert_eq!(pem.substeps, 64, "seed {seed}: {:?}", id.notes);
        assert!(pem.cost_end < 1.0, "seed {seed}: cost {}", pem.cost_end);
        assert_every_parameter_within(&id, 3.0, &format!("seed {seed}"));
    }
}

/// 50,000 samples of 64-sub-step data at 1 % noise are refined at 64 model sub-steps.
/// Until 2026-11-28 a budget of simulated sub-steps per run capped the level at 16 for a
/// record this long; the 16-sub-step model misfit the data (normalised cost 18.5), the
/// whole-record start test read that as a start in motion, and the answer was refused.
/// Measured now: every parameter within 0.57 errors (ACCURACY.md, fifteenth session).
#[test]
fn a_long_record_of_finely_integrated_data_is_refined_at_its_level() {
    let setup = shipped_friction_setup();
    let id = run(&setup, 50_000, 64, Noise::Additive(0.01), 1);
    assert!(id.failure.is_none(), "{:?}", id.failure);
    assert!(
        !id.notes.iter().any(|n| n.contains("starts in motion")),
        "{:?}",
        id.notes
    );
    assert_eq!(prediction_error_report(&id).substeps, 64, "{:?}", id.notes);
    // The whole record refined by the one-step round from the prefix's answer (not handed
    // back to the damped descent): `prediction_error::ONE_STEP_ITER`.
    let steps = prediction_error_report(&id).whole_record_steps;
    assert!(matches!(steps, Some(1..=4)), "{steps:?} {:?}", id.notes);
    // The passes converged on the first 10,000 samples and one ran over the whole record
    // (`identify::PASS_PREFIX_SAMPLES`).
    assert!(
        id.stop_reason.contains("first 10000 samples"),
        "{}",
        id.stop_reason
    );
    assert_every_parameter_within(&id, 2.0, "50,000 samples, 64 sub-steps, 1 %, seed 1");
}

/// A long record's passes converge on its first 10,000 samples and one pass over the whole
/// record starts the prediction-error refinement (`identify::PASS_PREFIX_SAMPLES`); when
/// that refinement does not give the answer, the passes' answer is the answer and they go
/// on over the whole record to their tolerance. Here the model misfits the data (the beams'
/// EI 10 % stiff: the prediction error's cost is 21× the noise variance and it is not
/// used), 25,000 samples: the passes after the first whole-record one must run, and the
/// last must have moved less than the tolerance. Seed 2 since 2026-11-29 (seed 5 before):
/// from the passes' re-tune searched near the first tuning, seeds 1 and 5 of this misfit
/// pass the prediction error's start-in-motion test (the note says a misfit can) and are
/// identified again with the start state estimated, a path without the prefix; seeds 2, 3,
/// 4, 6 and 7 take the one tested here.
#[test]
fn a_long_record_whose_refinement_is_not_used_has_its_passes_converged_over_all_of_it() {
    let truth_setup = shipped_friction_setup();
    let path = std::path::Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("recordings")
        .join("two-beam-friction.toml");
    let text = std::fs::read_to_string(&path)
        .unwrap()
        .replace("ei = 1.0e5", "ei = 1.1e5");
    let misfit = Setup::from_toml(&text, "misfit EI").unwrap();
    let id = run_with(&truth_setup, &misfit, 25_000, 1, Noise::Additive(0.01), 2);
    let opts = IdentifyOptions::from_setup(&misfit);
    assert!(
        id.notes.iter().any(|n| n.contains("refinement not used")),
        "{:?}",
        id.notes
    );
    let on_prefix = id
        .notes
        .iter()
        .find_map(|n| {
            n.strip_prefix("long record: pass(es) 1–")
                .and_then(|rest| rest.split(' ').next())
                .and_then(|k| k.parse::<usize>().ok())
        })
        .unwrap_or_else(|| {
            panic!(
                "the passes started on the record's prefix: {} / {:?}",
                id.stop_reason, id.notes
            )
        });
    assert!(
        id.passes.len() >= on_prefix + 2,
        "{} passes, {on_prefix} on the prefix",
        id.passes.len()
    );
    assert!(id.converged, "{}", id.stop_reason);
    assert!(
        !id.stop_reason.contains("first 10000"),
        "{}",
        id.stop_reason
    );
    let last = id.passes.last().unwrap();
    let moved = last.max_change_std_errors.unwrap();
    let relative = last.max_change_force_relative.unwrap();
    assert!(
        moved <= opts.tolerance_std_errors || relative <= opts.tolerance_relative,
        "the last pass moved {moved} errors ({relative} of the force)"
    );
}

/// The prefix's descent on a long record whose Kalman start is far off (the spring setup,
/// 8-sub-step data, 100 % noise, 50,000 samples, seed 1: the start `u` 25× the truth) ends
/// far from the whole record's minimum, and the whole round is run again with the
/// observer rebuilt at its end (`prediction_error::PREFIX_REBUILD`): without that round
/// the joint damper `v` was −2.22 errors off, with it +0.30.
#[test]
fn a_whole_round_far_from_the_prefix_is_run_again_with_the_observer_rebuilt() {
    let path = std::path::Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("recordings")
        .join("two-beam-spring.toml");
    let setup = Setup::from_file(&path).unwrap();
    let id = run(&setup, 50_000, 8, Noise::Additive(1.0), 1);
    assert!(id.failure.is_none(), "{:?}", id.failure);
    // Not the one-step round (`prediction_error::ONE_STEP_ITER`): its first step reaches
    // beyond what the prefix's errors explain and hands the record to the damped descent.
    assert_eq!(prediction_error_report(&id).whole_record_steps, None);
    assert_every_parameter_within(&id, 2.0, "spring, 50,000 samples, 100 %, seed 1");
}

/// The measurement noise's shift through the prediction error's observer is removed (see
/// `estimate::prediction_error`, `noise_bias`): the shipped friction setup, 8-sub-step data
/// at 100 % noise, 50,000 samples, seed 4. The observer force tunes to ~8e4 N per sample
/// (45× the model's force scale) and the uncorrected answer had the joint damper `v`
/// (truth 0) 5.8 standard errors off — a shift that stays while the errors shrink with the
/// record. Corrected, every parameter within 2 errors (measured 0.44 at most), the shift is
/// reported, and it moved `v` down by several of its errors. Since the passes tune twice
/// (sixteenth session) their start gives an observer force of 1.5e4 N (7.6× smaller), the
/// errors are 6× smaller, every parameter within 0.05 errors, and the shift of `v` is 1.0
/// of its errors: asserted above 0.5.
#[test]
fn the_observer_noise_shift_is_removed_on_a_long_record_at_full_noise() {
    let s = shipped_friction_setup();
    let id = run(&s, 50_000, 8, Noise::Additive(1.0), 4);
    assert_every_parameter_within(&id, 2.0, "50,000 samples, 100 % noise, seed 4");
    let pe = prediction_error_report(&id);
    let shift = pe
        .noise_shift
        .as_ref()
        .expect("the noise shift is computed");
    let keys = s.param_keys();
    let v = keys
        .iter()
        .position(|k| k.ends_with(".v"))
        .expect("a `v` term");
    let se = id.final_parameters().unwrap()[v].std_error;
    assert!(
        shift[v] > 0.5 * se,
        "the shift of `v` ({:e}) should be a sizeable part of its error ({se:e})",
        shift[v]
    );
}

/// At 1 % noise the noise shift is small and the correction does not move the answer: the
/// shipped friction recording's conditions (8-sub-step data, 1 % noise, seed 11, 2,000
/// samples). The velocity channels' difference estimate of the noise is 8–53× the true
/// noise there; a correction from it moved `v` by 0.41 of its errors (the answers at this
/// noise are unbiased over 20 seeds), from the tighter level the real innovations allow by
/// 0.06 — errors as stated until the fortieth session, when the damper's became 4.5×
/// smaller (the score covariance from the noise through the observer, ACCURACY.md): the
/// same shifts are 1.8 and 0.28 of today's errors. Every shift below 0.5 errors, every
/// parameter within 2 errors of the truth.
#[test]
fn the_noise_shift_is_small_at_low_noise() {
    let s = shipped_friction_setup();
    let id = run(&s, 2000, 8, Noise::Additive(0.01), 11);
    assert_every_parameter_within(&id, 2.0, "2,000 samples, 1 % noise, seed 11");
    let shift = prediction_error_report(&id)
        .noise_shift
        .clone()
        .expect("the noise shift is computed");
    for (p, b) in id.final_parameters().unwrap().iter().zip(&shift) {
        assert!(
            b.abs() < 0.5 * p.std_error,
            "{}: shift {b:e} against a standard error of {:e}",
            p.basis,
            p.std_error
        );
    }
}
