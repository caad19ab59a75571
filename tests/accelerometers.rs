//! Acceleration channels (issue 4, part 3): what `simulate` writes for them, what the
//! estimators make of them, and mixed layouts. Figures and the open problem of
//! accelerometer-only layouts on continuous data: ACCURACY.md "Accelerometers only".

mod common;

use jointid::identify::{Identification, IdentifyOptions, TestData, identify};
use jointid::setup::{EstimatorKind, Setup};
use jointid::simulate::{Noise, Scenario, SimulateOptions, Simulated, simulate};

/// A shipped two-beam setup with the connection law and model sub-steps replaced.
fn setup(file: &str, basis: &[&str], truth: &[f64], model_substeps: usize) -> Setup {
    common::setup_variant(file, basis, truth, model_substeps)
}

fn sim(s: &Setup, steps: usize, data_substeps: usize, noise: Noise, seed: u64) -> Simulated {
    simulate(
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
    .unwrap()
}

fn run(s: &Setup, d: &Simulated, kind: EstimatorKind) -> Identification {
    try_run(s, d, kind).unwrap()
}

fn try_run(
    s: &Setup,
    d: &Simulated,
    kind: EstimatorKind,
) -> Result<Identification, jointid::identify::IdentifyError> {
    let n = d.response.len();
    let data = TestData {
        samples: (0..n as u64).collect(),
        t_ns: vec![0; n],
        excitation: d.excitation.clone(),
        response: d.response.clone(),
    };
    let mut opts = IdentifyOptions::from_setup(s);
    opts.estimator = kind;
    identify(s, &data, &opts, Some(&d.truth), &mut |_| {}, &mut |_, _| {})
}

fn rel(id: &Identification, j: usize) -> f64 {
    let p = &id.final_parameters().unwrap()[j];
    (p.value - p.truth.unwrap()) / p.truth.unwrap()
}

fn rms(x: impl Iterator<Item = f64>) -> f64 {
    let (s, n) = x.fold((0.0, 0usize), |(s, n), v| (s + v * v, n + 1));
    (s / n.max(1) as f64).sqrt()
}

/// `simulate` writes accelerations consistent with its velocities (64 sub-steps per
/// sample, a 50 Hz sine so that the sampling resolves the response: the central difference
/// of the velocity channel matches the acceleration channel at the same station within 15 %
/// of its RMS — measured 1–11 %, the rest being undamped high-mode transients the sampling
/// cannot difference; a sign error would be 200 % off), and additive noise is the stated fraction of each acceleration
/// channel's own RMS.
#[test]
fn simulated_acceleration_channels_are_consistent() {
    // The accelerometer setup and the displacement/velocity setup at the same stations,
    // driven by the same excitation (same seed).
    let mixed = setup("two-beam-mixed.toml", &["u"], &[3.0e5], 1);
    let accel = setup("two-beam-accel.toml", &["u"], &[3.0e5], 1);
    let spring = setup("two-beam-spring.toml", &["u"], &[3.0e5], 1);
    let (steps, sub) = (600, 64);
    let sine = |s: &Setup| {
        simulate(
            s,
            &SimulateOptions {
                scenario: Scenario::Sine {
                    freq_hz: 50.0,
                    amplitude: 2e4,
                },
                steps,
                dt_s: s.dt_s,
                substeps: sub,
                noise: Noise::None,
                seed: 3,
            },
        )
        .unwrap()
    };
    let (a, v) = (sine(&accel), sine(&spring));
    assert_eq!(a.excitation, v.excitation, "same excitation");
    let dt = accel.dt_s;
    // Station k: acceleration channel k of `accel`, velocity channel 2k+1 of `spring`.
    for k in 0..6 {
        let diff: Vec<f64> = (1..steps - 1)
            .map(|i| {
                (v.response[i + 1][2 * k + 1] - v.response[i - 1][2 * k + 1]) / (2.0 * dt)
                    - a.response[i][k]
            })
            .collect();
        let scale = rms((1..steps - 1).map(|i| a.response[i][k]));
        let err = rms(diff.into_iter()) / scale;
        eprintln!("station {k}: central difference vs acceleration {err:.3e} of RMS");
        assert!(err < 0.15, "station {k}: {err}");
    }
    let noisy = sim(&mixed, steps, sub, Noise::Additive(0.1), 4);
    for k in 0..6 {
        let clean = rms(noisy.clean_response.iter().map(|y| y[k]));
        let noise = rms(noisy
            .response
            .iter()
            .zip(&noisy.clean_response)
            .map(|(y, c)| y[k] - c[k]));
        let ratio = noise / clean;
        assert!(
            (ratio - 0.1).abs() < 0.02,
            "channel {k}: noise {ratio} of RMS"
        );
    }
}

/// Accelerometers only, noise-free data from the model's own discretisation (1 sub-step):
/// the paper's estimator (its S is well conditioned for accelerations) recovers the spring,
/// and so does the default, whose output-error stage starts from a stiffness scan (the
/// residual-force stage cannot: ACCURACY.md "Accelerometers only"). With the output-error stage
/// switched off the default refuses the layout, naming the reason.
#[test]
fn accelerometers_only_own_discretisation() {
    let s = setup("two-beam-accel.toml", &["u"], &[3.0e5], 1);
    let d = sim(&s, 800, 1, Noise::None, 1);
    let paper = run(&s, &d, EstimatorKind::Paper);
    assert!(rel(&paper, 0).abs() < 1e-6, "paper {:.3e}", rel(&paper, 0));
    let default = run(&s, &d, EstimatorKind::Kalman);
    assert!(
        rel(&default, 0).abs() < 1e-6,
        "default {:.3e}",
        rel(&default, 0)
    );
    assert!(
        default.passes[0]
            .diagnostics
            .warnings
            .iter()
            .any(|w| w.starts_with("accelerations only"))
    );
    let n = d.response.len();
    let data = TestData {
        samples: (0..n as u64).collect(),
        t_ns: vec![0; n],
        excitation: d.excitation.clone(),
        response: d.response.clone(),
    };
    let mut opts = IdentifyOptions::from_setup(&s);
    opts.output_error = false;
    let err = identify(&s, &data, &opts, None, &mut |_| {}, &mut |_, _| {})
        .expect_err("without the output-error stage the layout must be refused")
        .to_string();
    assert!(
        err.contains("all 6 measured channels are accelerations")
            && err.contains("add a displacement or velocity channel"),
        "{err}"
    );
}

/// Accelerometers only, continuous data (32 sub-steps per sample; the model starts with 8
/// and the output-error stage raises them), 10 % noise, 1,000 samples: the spring within
/// 0.2 % and the truth inside the stated 95 % interval; the noise level restated from the
/// residuals within 20 % of the true one (the high-order-difference estimate reads the
/// Nyquist-band response as noise, several times the truth).
#[test]
fn accelerometers_only_continuous_spring() {
    let s = setup("two-beam-accel.toml", &["u"], &[3.0e5], 8);
    let d = sim(&s, 1000, 32, Noise::Additive(0.1), 2);
    let id = run(&s, &d, EstimatorKind::Kalman);
    let p = &id.final_parameters().unwrap()[0];
    eprintln!(
        "spring {:+.4} % (se {:.4} %, bound {:.4} %); notes {:?}",
        100.0 * rel(&id, 0),
        100.0 * p.std_error / 3.0e5,
        100.0 * p.crlb.unwrap_or(f64::NAN) / 3.0e5,
        id.notes
    );
    assert!(rel(&id, 0).abs() < 2e-3, "spring {}", rel(&id, 0));
    assert!(
        p.ci95[0] <= 3.0e5 && 3.0e5 <= p.ci95[1],
        "truth outside {:?}",
        p.ci95
    );
    let t = &id.passes.last().unwrap().diagnostics;
    for (k, sensor) in s.sensors.iter().enumerate() {
        let est = t
            .tuning_value(&format!("noise_std_output_error[{}]", sensor.name))
            .unwrap();
        let ratio = est / d.noise_std[k];
        assert!((ratio - 1.0).abs() < 0.2, "{}: {ratio}", sensor.name);
    }
}

/// Mixed layout at 50 % noise (continuous data, 2,000 samples): the joint deformation is
/// not determined (posterior std of δ 1.6× the RMS of δ̂; the fit used to end −39 % off with
/// a 0.3 % stated error): refused with the figures.
#[test]
fn mixed_layout_at_high_noise_is_refused_as_undetermined() {
    let s = setup("two-beam-mixed.toml", &["u"], &[3.0e5], 16);
    let d = sim(&s, 2000, 64, Noise::Additive(0.5), 1);
    let err = try_run(&s, &d, EstimatorKind::Kalman)
        .expect_err("must be refused")
        .to_string();
    assert!(
        err.contains("do not determine the joint deformation") && err.contains("posterior std"),
        "{err}"
    );
}

/// Mixed layout (acceleration, velocity and displacement stations), continuous data
/// (64 sub-steps, model 16), 10 % noise, 2,000 samples: spring within 1 %.
#[test]
fn mixed_layout_continuous_spring() {
    let s = setup("two-beam-mixed.toml", &["u"], &[3.0e5], 16);
    let d = sim(&s, 2000, 64, Noise::Additive(0.1), 1);
    let id = run(&s, &d, EstimatorKind::Kalman);
    eprintln!("spring {:.4} %", 100.0 * rel(&id, 0));
    assert!(
        !id.passes[0]
            .diagnostics
            .warnings
            .iter()
            .any(|w| w.starts_with("accelerations only"))
    );
    assert!(rel(&id, 0).abs() < 0.01, "spring {}", rel(&id, 0));
}

/// Mixed layout, noise-free data from the model's own discretisation, Coulomb friction +
/// spring: recovered.
#[test]
fn mixed_layout_noise_free_friction_and_spring() {
    let s = setup(
        "two-beam-mixed.toml",
        &["sign(v)", "u"],
        &[3000.0, 3.0e5],
        1,
    );
    let d = sim(&s, 800, 1, Noise::None, 5);
    let id = run(&s, &d, EstimatorKind::Kalman);
    for j in 0..2 {
        assert!(
            rel(&id, j).abs() < 1e-4,
            "parameter {j}: {:.3e}",
            rel(&id, j)
        );
    }
}

/// Accelerometers only with the shipped setup's single model sub-step on data integrated
/// with 64 (10 % noise, 2,000 samples, seed 1): the scan must try model sub-steps well past
/// 8× the setup's. Measured before the levels reached 128: +22 % with a 0.04 % stated error;
/// after: within 0.01 %, covered.
#[test]
fn accelerometers_only_model_substeps_follow_the_data() {
    let s = setup("two-beam-accel.toml", &["u"], &[3.0e5], 1);
    let d = sim(&s, 2000, 64, Noise::Additive(0.1), 1);
    let id = run(&s, &d, EstimatorKind::Kalman);
    let p = &id.final_parameters().unwrap()[0];
    eprintln!(
        "spring {:+.4} % (se {:.4} %); notes {:?}",
        100.0 * rel(&id, 0),
        100.0 * p.std_error / 3.0e5,
        id.notes
    );
    assert!(rel(&id, 0).abs() < 1e-3, "spring {}", rel(&id, 0));
    assert!(
        p.ci95[0] <= 3.0e5 && 3.0e5 <= p.ci95[1],
        "truth outside {:?}",
        p.ci95
    );
}

/// Accelerometers only with Coulomb friction + spring (continuous data, 64 sub-steps, model
/// 16; 10 % noise, 2,000 samples, seed 6): the residual-force stage cannot start it, the
/// output-error stage starts from the 2-D friction × stiffness scan on the first 200
/// samples. Measured: before the friction scan seeds 1–2 ended spring +34 % / −104 % with
/// 0.08 % / 0.01 % stated errors; with the coordinate scan alone seed 6 ended friction
/// +12 %, spring +73 % (0.18 % stated); with the 2-D scan +0.11 % / +0.12 %, covered.
/// Asserted: both within 1 % and the truth inside the stated 95 % intervals.
#[test]
fn accelerometers_only_coulomb_friction_and_spring_from_a_scan() {
    let s = setup(
        "two-beam-accel.toml",
        &["sign(v)", "u"],
        &[3000.0, 3.0e5],
        16,
    );
    let d = sim(&s, 2000, 64, Noise::Additive(0.1), 6);
    let t0 = std::time::Instant::now();
    let id = run(&s, &d, EstimatorKind::Kalman);
    let ps = id.final_parameters().unwrap();
    for (j, p) in ps.iter().enumerate() {
        eprintln!(
            "{}: {:+.4} % (se {:.4} %)",
            p.basis,
            100.0 * rel(&id, j),
            100.0 * p.std_error / p.truth.unwrap()
        );
    }
    eprintln!("{:.1} s; notes {:?}", t0.elapsed().as_secs_f64(), id.notes);
    for (j, p) in ps.iter().enumerate() {
        assert!(rel(&id, j).abs() < 0.01, "parameter {j}: {}", rel(&id, j));
        let t = p.truth.unwrap();
        assert!(
            p.ci95[0] <= t && t <= p.ci95[1],
            "parameter {j}: truth outside {:?}",
            p.ci95
        );
    }
    assert!(
        id.passes[0]
            .diagnostics
            .warnings
            .iter()
            .any(|w| w.starts_with("accelerations only"))
    );
}

/// Accelerometers only with Coulomb friction + spring at 100 % noise (continuous data, 2,000
/// samples), seeds 3 and 6. Seed 3: the 200-sample prefix holds little signal, the scan
/// started the stage at 7,400 N/m and the answer was friction +29 %, spring **−96 % with a
/// 0.14 % stated error**; the whole-record stiffness check over the whole scanned range
/// (`RESCAN_FAR_POINTS`) finds the truth's valley: +5.9 % (se 3.2 %), −1.6 % (se 2.0 %).
/// Seed 6 was refused as unsettled (the probe moved the spring 5.7 se); restarted from the
/// probe's end it settles: +1.6 % (se 1.9 %), −1.0 % (se 1.2 %). Asserted: friction within
/// 10 %, spring within 3 %, both truths inside the stated 95 % intervals.
#[test]
fn accelerometers_only_friction_at_full_noise_far_rescan_and_settling() {
    let s = setup(
        "two-beam-accel.toml",
        &["sign(v)", "u"],
        &[3000.0, 3.0e5],
        16,
    );
    for seed in [3, 6] {
        let d = sim(&s, 2000, 64, Noise::Additive(1.0), seed);
        let id = run(&s, &d, EstimatorKind::Kalman);
        let ps = id.final_parameters().unwrap();
        for (j, p) in ps.iter().enumerate() {
            eprintln!(
                "seed {seed} {}: {:+.4} % (se {:.4} %)",
                p.basis,
                100.0 * rel(&id, j),
                100.0 * p.std_error / p.truth.unwrap()
            );
        }
        for (j, p) in ps.iter().enumerate() {
            let tol = if j == 0 { 0.10 } else { 0.03 };
            assert!(
                rel(&id, j).abs() < tol,
                "seed {seed} parameter {j}: {}",
                rel(&id, j)
            );
            let t = p.truth.unwrap();
            assert!(
                p.ci95[0] <= t && t <= p.ci95[1],
                "seed {seed} parameter {j}: truth outside {:?}",
                p.ci95
            );
        }
    }
}

/// Mixed layout, Coulomb friction + spring, 50 % noise (continuous data, 2,000 samples,
/// seed 2): the residual-force stage refuses (posterior std of δ 1.56× the RMS of δ̂ in
/// pass 2), and the output-error stage started from the friction × stiffness scan answers.
/// Measured: friction −0.24 % (se 2.6 %), spring +1.59 % (se 0.75 %: 2.1 se, outside its
/// interval — seed 1: +4.1 % (se 3.1 %), −0.87 % (se 0.70 %), both inside). Asserted:
/// friction within 5 % and inside its interval, spring within 3 %, and a note naming the
/// path.
#[test]
fn mixed_layout_coulomb_friction_at_high_noise_falls_back_to_a_scan() {
    let s = setup(
        "two-beam-mixed.toml",
        &["sign(v)", "u"],
        &[3000.0, 3.0e5],
        16,
    );
    let d = sim(&s, 2000, 64, Noise::Additive(0.5), 2);
    let id = run(&s, &d, EstimatorKind::Kalman);
    let ps = id.final_parameters().unwrap();
    for (j, p) in ps.iter().enumerate() {
        eprintln!(
            "{}: {:+.4} % (se {:.4} %)",
            p.basis,
            100.0 * rel(&id, j),
            100.0 * p.std_error / p.truth.unwrap()
        );
    }
    assert!(rel(&id, 0).abs() < 0.05, "friction {}", rel(&id, 0));
    assert!(
        ps[0].ci95[0] <= 3000.0 && 3000.0 <= ps[0].ci95[1],
        "friction truth outside {:?}",
        ps[0].ci95
    );
    assert!(rel(&id, 1).abs() < 0.03, "spring {}", rel(&id, 1));
    assert!(
        id.notes
            .iter()
            .any(|n| n.starts_with("the residual-force stage was refused")),
        "{:?}",
        id.notes
    );
}

/// The Coulomb `sign(v), u` law (truth 3,000 N, 3e5 N/m; 16 model sub-steps) on `layout`,
/// and samples 500–2,499 of a 2,500-sample simulation (64 sub-steps, additive noise at
/// `noise`, `seed`): a record cut from a test in motion.
fn coulomb_record_cut_in_motion(layout: &str, noise: f64, seed: u64) -> (Setup, Simulated) {
    let s = setup(layout, &["sign(v)", "u"], &[3000.0, 3.0e5], 16);
    let d = sim(&s, 2500, 64, Noise::Additive(noise), seed);
    let cut = Simulated {
        excitation: d.excitation[500..].to_vec(),
        response: d.response[500..].to_vec(),
        ..d
    };
    (s, cut)
}

/// Accelerometers only, Coulomb friction + spring, a record cut from a test in motion
/// (samples 500–2,499 of seed 6, 64-sub-step data, 10 % noise). No displacement or velocity
/// channel can show the motion at the first sample, and the output-error stage (from a scan:
/// the residual-force stage cannot determine the deformation) starts its free run at rest.
/// Measured (twenty-seventh session): answered `sign(v)` −3.0, `u` +2.3 standard errors off
/// (the errors widened over two minima), its normalised cost under the motion test's 2, and
/// the residuals' whiteness test failing on every channel (portmanteau ~13,000 against a
/// limit of 45) — the only sign. Since the thirty-fourth session that whiteness asks the
/// start-in-motion test (at the answer's model sub-steps and again at the likeliest), which
/// finds the motion, and the record is identified again with its start state estimated.
/// Asserted: found in motion (or refused as such), every parameter within 3 of its stated
/// errors.
#[test]
fn accelerometers_only_coulomb_record_cut_in_motion_is_found_by_its_whiteness() {
    let (s, cut) = coulomb_record_cut_in_motion("two-beam-accel.toml", 0.1, 6);
    match try_run(&s, &cut, EstimatorKind::Kalman) {
        Err(e) => {
            let text = e.to_string();
            assert!(text.contains("starts in motion"), "{text}");
        }
        Ok(id) => {
            for p in id.final_parameters().unwrap() {
                let z = (p.value - p.truth.unwrap()) / p.std_error;
                eprintln!("{}: {:.2} errors off", p.basis, z);
            }
            assert!(
                id.notes.iter().any(|n| n.contains(
                    "the record starts in motion although its first sample reads like rest"
                )),
                "not found in motion: {:?}",
                id.notes
            );
            for p in id.final_parameters().unwrap() {
                let z = (p.value - p.truth.unwrap()) / p.std_error;
                assert!(z.abs() < 3.0, "{}: {z:.2} errors off", p.basis);
            }
        }
    }
}

/// Mixed layout (accelerations, displacements and velocities), Coulomb friction + spring, a
/// record cut from a test in motion (samples 500–2,499 of seed 3, 64-sub-step data, 50 %
/// noise). At this noise the residual-force stage is refused and the output-error stage
/// starts from the friction × stiffness scan; its free run from rest misfits the cut record,
/// which the scan path hands back (`identify::scan`: `motion_in_record` set, "`identify`
/// runs again") — checked with a print on that branch when this test was made
/// (twenty-eighth session; the path had no test before). Refused, with the figure: the start
/// state refitted to an observer's innovations removes 6,716 from their whitened cost
/// against a limit of 111. Since the thirty-first session the run again estimates the start
/// state and refines by prediction error (a friction law in motion), and is refused there
/// too (the joint deformation undetermined at 50 % noise); the error says both.
#[test]
fn mixed_layout_coulomb_record_cut_in_motion_is_refused_from_the_scan_path() {
    let (s, cut) = coulomb_record_cut_in_motion("two-beam-mixed.toml", 0.5, 3);
    let text = match try_run(&s, &cut, EstimatorKind::Kalman) {
        Err(e) => e.to_string(),
        Ok(id) => panic!(
            "answered {:?}",
            id.final_parameters()
                .unwrap()
                .iter()
                .map(|p| (p.value - p.truth.unwrap()) / p.std_error)
                .collect::<Vec<_>>()
        ),
    };
    assert!(
        text.contains("starts in motion") && text.contains("record from rest"),
        "{text}"
    );
    // The figures: the cost the refitted start removes, far beyond the limit it names.
    let figure = |after: &str| -> f64 {
        text.split(after)
            .nth(1)
            .and_then(|t| t.split_whitespace().next())
            .and_then(|t| t.trim_end_matches([',', ';']).parse().ok())
            .unwrap_or_else(|| panic!("no figure after {after:?} in: {text}"))
    };
    let (removed, limit) = (figure("removes "), figure("beyond the limit "));
    assert!(removed > 10.0 * limit, "{text}");
}
