//! The maximum-likelihood estimator (`--estimator ml`) on the paper's two-beam model with a
//! law linear in the state (`u`, `v`): exact on data of any discretisation it can name,
//! records that start in motion, the discretisation chosen by likelihood, and `--strict`.
use jointid::estimate::ml::{MlOptions, Scheme, identify_ml};
use jointid::identify::TestData;
use jointid::model::Model;
use jointid::setup::Setup;
use jointid::simulate::{Noise, Scenario, SimulateOptions, simulate};

/// The shipped spring setup with the connection's basis replaced by `u, v`.
fn spring_uv() -> Setup {
    let text = std::fs::read_to_string("recordings/two-beam-spring.toml").unwrap();
    let mut out = String::new();
    for line in text.lines() {
        let t = line.trim_start();
        if t.starts_with("basis") {
            out.push_str("basis = [\"u\", \"v\"]\n");
        } else if t.starts_with("initial") {
            out.push_str("initial = [0.0, 0.0]\n");
        } else if t.starts_with("truth") {
            out.push_str("truth = [3.0e5, 0.0]\n");
        } else {
            out.push_str(line);
            out.push('\n');
        }
    }
    Setup::from_toml(&out, "spring_uv").unwrap()
}

fn data(setup: &Setup, substeps: usize, noise: f64, seed: u64, skip: usize, n: usize) -> TestData {
    let sim = simulate(
        setup,
        &SimulateOptions {
            scenario: Scenario::Random { rms: 1000.0 },
            steps: n + skip,
            dt_s: setup.dt_s,
            substeps,
            noise: if noise > 0.0 {
                Noise::Additive(noise)
            } else {
                Noise::None
            },
            seed,
        },
    )
    .unwrap();
    TestData {
        samples: (0..n as u64).collect(),
        t_ns: (0..n as u64).map(|i| i * 100_000).collect(),
        excitation: sim.excitation[skip..].to_vec(),
        response: sim.response[skip..].to_vec(),
    }
}

#[test]
fn noise_free_newmark_data_are_identified_exactly_with_their_own_scheme_chosen() {
    let setup = spring_uv();
    let model = Model::for_identification(&setup).unwrap();
    let d = data(&setup, 1, 0.0, 1, 0, 1000);
    let (fit, _) = identify_ml(&setup, &model, &d, &MlOptions::default()).unwrap();
    assert_eq!((fit.scheme, fit.substeps), (Scheme::Newmark, 1));
    assert!(
        (fit.params[0] / 3e5 - 1.0).abs() < 1e-6,
        "u = {}",
        fit.params[0]
    );
    assert!(fit.params[1].abs() < 1e-6, "v = {}", fit.params[1]);
}

#[test]
fn data_of_eight_substeps_at_one_percent_noise_within_three_standard_errors() {
    let setup = spring_uv();
    let model = Model::for_identification(&setup).unwrap();
    let d = data(&setup, 8, 0.01, 4, 0, 2000);
    let (fit, _) = identify_ml(&setup, &model, &d, &MlOptions::default()).unwrap();
    assert_eq!(
        (fit.scheme, fit.substeps),
        (Scheme::Newmark, 8),
        "{}",
        fit.discretisation
    );
    for (k, truth) in [3e5, 0.0].iter().enumerate() {
        let z = (fit.params[k] - truth) / fit.std_errors[k];
        assert!(
            z.abs() < 3.0,
            "param {k}: {} ± {} ({z:.1} se)",
            fit.params[k],
            fit.std_errors[k]
        );
    }
    // The error is close to the bound for a right model: 0.0002 % of the stiffness here.
    assert!(fit.std_errors[0] / 3e5 < 1e-4, "se {}", fit.std_errors[0]);
    assert!(fit.warnings.is_empty(), "{:?}", fit.warnings);
}

#[test]
fn a_record_that_starts_in_motion_is_identified_with_its_initial_state() {
    let setup = spring_uv();
    let model = Model::for_identification(&setup).unwrap();
    // Cut the first 700 samples of a test: the record starts mid-motion.
    let d = data(&setup, 1, 0.01, 2, 700, 1500);
    let (fit, _) = identify_ml(&setup, &model, &d, &MlOptions::default()).unwrap();
    for (k, truth) in [3e5, 0.0].iter().enumerate() {
        let z = (fit.params[k] - truth) / fit.std_errors[k];
        assert!(
            z.abs() < 3.0,
            "param {k}: {} ± {} ({z:.1} se)",
            fit.params[k],
            fit.std_errors[k]
        );
    }
    let moving = fit.initial_state.iter().any(|v| v.abs() > 1e-9);
    assert!(moving, "the estimated initial state should not be rest");
    // Held at rest instead, the same record is not explained: the check says so.
    let at_rest = MlOptions {
        free_initial_state: false,
        ..MlOptions::default()
    };
    if let Ok((f, _)) = identify_ml(&setup, &model, &d, &at_rest) {
        assert!(
            !f.warnings.is_empty(),
            "a wrong initial state must be flagged"
        );
    }
}

#[test]
fn replay_with_ml_and_strict_refuses_a_model_that_does_not_explain_the_data() {
    use std::process::Command;
    let dir = tempfile::tempdir().unwrap();
    let jointid = env!("CARGO_BIN_EXE_jointid");
    // A `u, v` law fitted to a friction joint: the residuals cannot be white.
    let rec = dir.path().join("friction.mcap");
    let st = Command::new(jointid)
        .args(["simulate", "recordings/two-beam-friction.toml", "--out"])
        .arg(&rec)
        .args(["--scenario", "random", "--steps", "1500", "--substeps", "1"])
        .args(["--noise", "additive:0.01", "--seed", "3"])
        .output()
        .unwrap();
    assert!(
        st.status.success(),
        "{}",
        String::from_utf8_lossy(&st.stderr)
    );
    let text = std::fs::read_to_string("recordings/two-beam-friction.toml")
        .unwrap()
        .lines()
        .map(|l| {
            let t = l.trim_start();
            if t.starts_with("basis") {
                "basis = [\"u\", \"v\"]".to_string()
            } else if t.starts_with("initial") {
                "initial = [0.0, 0.0]".to_string()
            } else if t.starts_with("truth") {
                "truth = [3.0e5, 0.0]".to_string()
            } else {
                l.to_string()
            }
        })
        .collect::<Vec<_>>()
        .join("\n");
    let setup = dir.path().join("uv.toml");
    std::fs::write(&setup, text).unwrap();
    let out = Command::new(jointid)
        .args(["replay"])
        .arg(&rec)
        .arg("--setup")
        .arg(&setup)
        .args(["--estimator", "ml", "--strict"])
        .output()
        .unwrap();
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success(), "--strict must refuse: {err}");
    assert!(
        err.contains("refused under --strict") && err.contains("not white"),
        "{err}"
    );
    // The table was still printed (nothing computed is lost).
    assert!(String::from_utf8_lossy(&out.stdout).contains("joint6"));
}

#[test]
fn laws_with_sign_terms_are_refused_with_the_reason() {
    let setup =
        Setup::from_file(std::path::Path::new("recordings/two-beam-friction.toml")).unwrap();
    let model = Model::for_identification(&setup).unwrap();
    let d = data(&setup, 1, 0.01, 1, 0, 200);
    let err = identify_ml(&setup, &model, &d, &MlOptions::default())
        .unwrap_err()
        .to_string();
    assert!(
        err.contains("`sign(u)` is not supported") && err.contains("--estimator kalman"),
        "{err}"
    );
}

/// The seeds whose fits once ended in a wrong resonance basin (33–155 standard errors off,
/// ACCURACY.md) and a few fresh ones of each condition: every estimate within 3.5 standard
/// errors. The full 50-seed table is `examples/sweep.rs`.
#[test]
fn seeds_that_once_fell_into_wrong_minima_are_within_three_and_a_half_standard_errors() {
    let setup = spring_uv();
    let model = Model::for_identification(&setup).unwrap();
    let truth = [3.0e5, 0.0];
    for (substeps, noise, seed) in [
        (8, 0.01, 39),
        (64, 0.01, 5),
        (64, 1.0, 48),
        (1, 1.0, 41),
        (64, 0.1, 101),
        (8, 1.0, 102),
        // Fresh seeds of the thirty-third session: a start grid on 400 samples alone left
        // the first three in a local minimum (45.8, 18.6, 9.4 se off); one on 800 samples
        // alone the last two (12.7, 8.3 se). Both run; the likelier answer is kept.
        (64, 1.0, 7511),
        (8, 1.0, 7514),
        (64, 1.0, 7617),
        (64, 0.01, 7602),
        (64, 0.1, 7630),
        // Fresh seeds of the forty-seventh session: the start grid's points, a factor 2
        // apart, flanked the truth's basin on both prefixes (21.6 and 21.7 se off); the
        // zoom between the best point's neighbours finds it (0.97 and −1.86 se).
        (64, 1.0, 8411),
        (64, 1.0, 8762),
        // The stability test counted sub-steps for a composed 64-sub-step map, so a damper a
        // little negative was a wall the descent stopped at; the smooth reading of the
        // excitation then won with a positive damper (3.97 and 4.43 se off).
        (64, 1.0, 8748),
        (64, 1.0, 8824),
    ] {
        let d = data(&setup, substeps, noise, seed, 0, 2000);
        let (fit, _) = identify_ml(&setup, &model, &d, &MlOptions::default()).unwrap();
        for (k, t) in truth.iter().enumerate() {
            let z = (fit.params[k] - t) / fit.std_errors[k];
            assert!(
                z.abs() < 3.5,
                "{substeps} sub-steps, noise {noise}, seed {seed}: param {k} = {} ± {} ({z:.1} se)",
                fit.params[k],
                fit.std_errors[k]
            );
        }
    }
}

/// Without `[estimator] kind`, a law linear in the state runs maximum likelihood (right on
/// 8-sub-step data), and a record too short for it falls back to the Kalman pipeline with a
/// note that says why.
#[test]
fn the_default_for_a_linear_law_is_maximum_likelihood_with_a_kalman_fallback() {
    use jointid::identify::{IdentifyOptions, identify};
    let with_kind = spring_uv();
    let text: String = with_kind
        .toml_text
        .lines()
        .filter(|l| !l.trim_start().starts_with("kind"))
        .map(|l| format!("{l}\n"))
        .collect();
    let setup = Setup::from_toml(&text, "spring_uv without kind").unwrap();
    assert_eq!(setup.estimator.kind, None);
    let opts = IdentifyOptions::from_setup(&setup);
    let d = data(&setup, 8, 0.01, 7, 0, 2000);
    let truth = [3.0e5, 0.0];
    let id = identify(&setup, &d, &opts, Some(&truth), &mut |_| {}, &mut |_, _| {}).unwrap();
    assert_eq!(id.estimator, "ml");
    let fit = id
        .maximum_likelihood
        .as_ref()
        .expect("maximum likelihood ran");
    for (k, t) in truth.iter().enumerate() {
        let z = (fit.params[k] - t) / fit.std_errors[k];
        assert!(z.abs() < 3.0, "param {k}: {} ({z:.1} se)", fit.params[k]);
    }
    // 20 samples: fewer than maximum likelihood needs for 2 parameters and 22 states.
    let short = data(&setup, 1, 0.01, 7, 0, 20);
    let id = identify(
        &setup,
        &short,
        &opts,
        Some(&truth),
        &mut |_| {},
        &mut |_, _| {},
    )
    .unwrap();
    assert_eq!(id.estimator, "kalman");
    assert!(id.maximum_likelihood.is_none());
    assert!(
        id.notes
            .iter()
            .any(|n| n.contains("the Kalman pipeline ran instead")),
        "{:?}",
        id.notes
    );
}
