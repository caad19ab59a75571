//! End-to-end tests of `jointid simulate | replay | inspect`: the real binary on real
//! recordings, asserting identified parameters against the truth.

mod common;

use std::path::Path;

use common::{ok, replay_json, repo, run, setup_variant_text};

/// (basis, value, truth) of the final parameters.
fn params(v: &serde_json::Value) -> Vec<(String, f64, f64)> {
    v["parameters"]
        .as_array()
        .expect("parameters")
        .iter()
        .map(|p| {
            (
                p["basis"].as_str().unwrap_or_default().to_string(),
                p["value"].as_f64().unwrap_or(f64::NAN),
                p["truth"].as_f64().unwrap_or(f64::NAN),
            )
        })
        .collect()
}

/// Relative error, against the largest true value for parameters whose truth is zero.
fn check_recovery(v: &serde_json::Value, tol: f64, what: &str) {
    let ps = params(v);
    let scale = ps.iter().map(|p| p.2.abs()).fold(0.0, f64::max);
    for (basis, value, truth) in &ps {
        let err = if *truth != 0.0 {
            (value - truth).abs() / truth.abs()
        } else {
            // A zero parameter is judged by the force it would add at a unit basis value,
            // against the largest true parameter.
            value.abs() / scale
        };
        assert!(
            err <= tol,
            "{what}: {basis} = {value} vs truth {truth} (error {err:.3e} > {tol:e})"
        );
    }
}

/// The default estimator on noise-free data of the friction setup's own discretisation
/// (2,000 random samples): answered and exact. Seed 7207 was refused with "rank(S) = 0"
/// (the tuning had scaled the channels' noise levels, already at their floor, below it,
/// and the filter's innovation covariance lost positive definiteness in round-off) and
/// seed 7211 was answered 1 % off with an error of 2e-5 N (passes that did not converge,
/// the prediction error refused for misfit) — both where the 1989 estimator is exact.
#[test]
fn noise_free_friction_records_the_noise_floor_once_broke_are_recovered_by_default() {
    let dir = tempfile::tempdir().unwrap();
    let setup = repo("recordings/two-beam-friction.toml");
    for seed in ["7207", "7211"] {
        let extra = ["--steps", "2000", "--substeps", "1"];
        let rec = simulate_with_noise(dir.path(), &setup, seed, "none", &extra);
        let v = replay_json(&[rec.to_str().unwrap()]);
        check_recovery(&v, 1e-4, &format!("seed {seed}"));
    }
}

#[test]
fn noise_free_own_discretisation_is_recovered_to_1e_6_for_both_paper_cases_and_all_inputs() {
    let dir = tempfile::tempdir().unwrap();
    for case in ["two-beam-spring", "two-beam-friction"] {
        let setup = repo(&format!("recordings/{case}.toml"));
        for scenario in ["sine", "random", "free"] {
            let out = dir.path().join(format!("{case}-{scenario}.mcap"));
            let (amp, steps) = if scenario == "free" {
                ("5e4", "600")
            } else {
                ("2e4", "600")
            };
            let msg = ok(&[
                "simulate",
                setup.to_str().unwrap(),
                "--out",
                out.to_str().unwrap(),
                "--scenario",
                scenario,
                "--steps",
                steps,
                "--amplitude",
                amp,
                "--substeps",
                "1",
                "--noise",
                "none",
            ]);
            if case == "two-beam-friction" {
                // The friction joint starts stuck at rest and the simulator says so.
                assert!(!msg.contains("stuck 0.0 %"), "{msg}");
            }
            let v = replay_json(&[out.to_str().unwrap(), "--estimator", "paper"]);
            assert_eq!(v["converged"], true, "{case} {scenario}: {v}");
            check_recovery(&v, 1e-6, &format!("{case} {scenario}"));
        }
    }
}

#[test]
fn replay_prints_table_and_writes_results_that_replay_again() {
    let dir = tempfile::tempdir().unwrap();
    let rec = dir.path().join("t.mcap");
    let res = dir.path().join("results.mcap");
    let setup = repo("recordings/two-beam-friction.toml");
    ok(&[
        "simulate",
        setup.to_str().unwrap(),
        "--out",
        rec.to_str().unwrap(),
        "--steps",
        "300",
    ]);
    let table = ok(&[
        "replay",
        rec.to_str().unwrap(),
        "--estimator",
        "paper",
        "--out",
        res.to_str().unwrap(),
    ]);
    for needle in [
        "sign(u)",
        "std error",
        "truth",
        "error %",
        "error recursion ρ",
        "converged after",
    ] {
        assert!(table.contains(needle), "missing {needle:?} in\n{table}");
    }
    // The results file carries the inputs and the setup: it replays to the same answer.
    let v = replay_json(&[res.to_str().unwrap(), "--estimator", "paper"]);
    check_recovery(&v, 1e-6, "results file");
    let info = ok(&["inspect", res.to_str().unwrap(), "--json"]);
    let info: serde_json::Value = serde_json::from_str(&info).unwrap();
    assert_eq!(info["excitation_frames"], 300);
    assert_eq!(info["facts"]["estimator"], "paper");
    // Output topics are plain JSON messages another program can read.
    let bytes = std::fs::read(&res).unwrap();
    let mut topics = std::collections::BTreeMap::<String, usize>::new();
    for m in mcap::MessageStream::new(&bytes).unwrap() {
        let m = m.unwrap();
        *topics.entry(m.channel.topic.clone()).or_default() += 1;
        if m.channel.topic == "/jointid/parameters" {
            let j: serde_json::Value = serde_json::from_slice(&m.data).unwrap();
            assert!(j["parameters"][0]["std_error"].is_number());
        }
    }
    assert_eq!(topics["/jointid/residuals"], 299);
    assert_eq!(topics["/jointid/states"], 299);
    assert!(topics["/jointid/parameters"] >= 2);
}

/// A two-connection setup measured by a single channel: rank(S) = 1 < 2.
#[test]
fn too_few_stations_is_an_error_naming_the_rank() {
    let dir = tempfile::tempdir().unwrap();
    let text = std::fs::read_to_string(repo("recordings/two-beam-spring.toml")).unwrap();
    // Keep only the first sensor and add a second connection at node 11.
    let head = text.split("[[sensors]]").next().unwrap().to_string();
    let rest = &text[text.find("[[connections]]").unwrap()..];
    let setup = format!(
        "{head}[[sensors]]\nname = \"node1.disp\"\ndof = {{ node = 1, dir = \"w\" }}\nquantity = \"displacement\"\n\n{rest}\n[[connections]]\nname = \"joint11\"\ndof = {{ node = 11, dir = \"w\" }}\nbasis = [\"u\"]\ntruth = [1.0e4]\n"
    );
    let sp = dir.path().join("s.toml");
    std::fs::write(&sp, setup).unwrap();
    let rec = dir.path().join("r.mcap");
    ok(&[
        "simulate",
        sp.to_str().unwrap(),
        "--out",
        rec.to_str().unwrap(),
        "--steps",
        "100",
    ]);
    for est in ["paper", "kalman"] {
        let out = run(&["replay", rec.to_str().unwrap(), "--estimator", est]);
        assert!(!out.status.success());
        let err = String::from_utf8_lossy(&out.stderr);
        assert!(
            err.contains("rank(S) = 1") && err.contains("2 connection DOFs"),
            "{est}: {err}"
        );
        assert_eq!(err.lines().count(), 1, "one-line cause: {err}");
    }
}

/// (sample, t_ns, excitation, response) of one raw frame pair.
type RawFrame = (u64, u64, Vec<f64>, Vec<f64>);

/// Write a binary-encoded recording directly with the mcap crate (so it can hold what our
/// own writer refuses to write).
fn write_raw(path: &Path, setup: &str, names: &[&str], frames: &[RawFrame]) {
    use std::collections::BTreeMap;
    let mut w = mcap::Writer::new(std::io::BufWriter::new(
        std::fs::File::create(path).unwrap(),
    ))
    .unwrap();
    w.attach(&mcap::Attachment {
        log_time: 0,
        create_time: 0,
        name: "setup.toml".into(),
        media_type: "application/toml".into(),
        data: std::borrow::Cow::Borrowed(setup.as_bytes()),
    })
    .unwrap();
    let truth: BTreeMap<String, String> = [
        ("sign(u)", "0"),
        ("u", "3e5"),
        ("const(100)", "0"),
        ("v", "0"),
    ]
    .into_iter()
    .map(|(k, v)| (format!("joint6.{k}"), v.to_string()))
    .collect();
    w.write_metadata(&mcap::records::Metadata {
        name: "jointid.truth".into(),
        metadata: truth,
    })
    .unwrap();
    let meta = |n: &[&str]| -> BTreeMap<String, String> {
        [
            ("channels".to_string(), n.join(",")),
            (
                "units".to_string(),
                n.iter().map(|_| "u").collect::<Vec<_>>().join(","),
            ),
        ]
        .into()
    };
    let ce = w
        .add_channel(
            0,
            "/jointid/excitation",
            "jointid.frame.v1",
            &meta(&["node1.force"]),
        )
        .unwrap();
    let cr = w
        .add_channel(0, "/jointid/response", "jointid.frame.v1", &meta(names))
        .unwrap();
    let enc = |s: u64, t: u64, v: &[f64]| {
        let mut b = Vec::new();
        b.extend_from_slice(&s.to_le_bytes());
        b.extend_from_slice(&t.to_le_bytes());
        for x in v {
            b.extend_from_slice(&x.to_le_bytes());
        }
        b
    };
    for (s, t, e, r) in frames {
        for (ch, v) in [(ce, e), (cr, r)] {
            let h = mcap::records::MessageHeader {
                channel_id: ch,
                sequence: *s as u32,
                log_time: *t,
                publish_time: *t,
            };
            w.write_to_known_channel(&h, &enc(*s, *t, v)).unwrap();
        }
    }
    w.finish().unwrap();
}

fn good_frames(n: u64) -> (String, Vec<&'static str>, Vec<RawFrame>) {
    let dir = tempfile::tempdir().unwrap();
    let rec = dir.path().join("r.mcap");
    let setup = repo("recordings/two-beam-spring.toml");
    ok(&[
        "simulate",
        setup.to_str().unwrap(),
        "--out",
        rec.to_str().unwrap(),
        "--steps",
        &n.to_string(),
    ]);
    let bytes = std::fs::read(&rec).unwrap();
    let mut exc = Vec::new();
    let mut resp = Vec::new();
    for m in mcap::MessageStream::new(&bytes).unwrap() {
        let m = m.unwrap();
        let j: serde_json::Value = serde_json::from_slice(&m.data).unwrap();
        let v: Vec<f64> = j["values"]
            .as_array()
            .unwrap()
            .iter()
            .map(|x| x.as_f64().unwrap())
            .collect();
        let s = j["sample"].as_u64().unwrap();
        let t = j["t_ns"].as_u64().unwrap();
        if m.channel.topic == "/jointid/excitation" {
            exc.push((s, t, v));
        } else {
            resp.push(v);
        }
    }
    let names = vec![
        "node1.disp",
        "node1.vel",
        "node3.disp",
        "node3.vel",
        "node5.disp",
        "node5.vel",
        "node7.disp",
        "node7.vel",
        "node9.disp",
        "node9.vel",
        "node11.disp",
        "node11.vel",
    ];
    let frames = exc
        .into_iter()
        .zip(resp)
        .map(|((s, t, e), r)| (s, t, e, r))
        .collect();
    (std::fs::read_to_string(setup).unwrap(), names, frames)
}

#[test]
fn a_nan_is_named_by_sample_and_the_samples_before_it_are_identified_and_written() {
    let dir = tempfile::tempdir().unwrap();
    let (setup, names, mut frames) = good_frames(400);
    frames[250].3[4] = f64::NAN;
    let rec = dir.path().join("nan.mcap");
    write_raw(&rec, &setup, &names, &frames);
    let res = dir.path().join("res.mcap");
    let out = run(&[
        "replay",
        rec.to_str().unwrap(),
        "--estimator",
        "paper",
        "--out",
        res.to_str().unwrap(),
    ]);
    assert!(!out.status.success());
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(
        err.contains("sample 250") && err.contains("250 samples before it"),
        "{err}"
    );
    // Nothing already computed is lost: the results hold the 250 good samples, identified.
    let v = replay_json(&[res.to_str().unwrap(), "--estimator", "paper"]);
    assert_eq!(v["samples"], 250);
    check_recovery(&v, 1e-6, "prefix before the NaN");
}

#[test]
fn time_backwards_and_wrong_channel_count_name_the_sample() {
    let dir = tempfile::tempdir().unwrap();
    let (setup, names, frames) = good_frames(100);
    let mut back = frames.clone();
    back[60].1 = back[59].1 - 1;
    let rec = dir.path().join("back.mcap");
    write_raw(&rec, &setup, &names, &back);
    let out = run(&["replay", rec.to_str().unwrap()]);
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(
        !out.status.success() && err.contains("60") && err.to_lowercase().contains("time"),
        "{err}"
    );

    let mut short = frames.clone();
    short[70].3.pop();
    let rec = dir.path().join("short.mcap");
    write_raw(&rec, &setup, &names, &short);
    let out = run(&["replay", rec.to_str().unwrap()]);
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success() && err.contains("sample 70"), "{err}");

    // A channel missing from the recording's channel list.
    let rec = dir.path().join("missing.mcap");
    let fewer: Vec<_> = frames
        .iter()
        .map(|(s, t, e, r)| (*s, *t, e.clone(), r[..11].to_vec()))
        .collect();
    write_raw(&rec, &setup, &names[..11], &fewer);
    let out = run(&["replay", rec.to_str().unwrap()]);
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success() && err.contains("node11.vel"), "{err}");
}

#[test]
fn a_truncated_recording_is_replayed_up_to_the_damage_with_a_warning() {
    let dir = tempfile::tempdir().unwrap();
    let rec = dir.path().join("t.mcap");
    let setup = repo("recordings/two-beam-friction.toml");
    ok(&[
        "simulate",
        setup.to_str().unwrap(),
        "--out",
        rec.to_str().unwrap(),
        "--steps",
        "3000",
        "--encoding",
        "binary",
    ]);
    let bytes = std::fs::read(&rec).unwrap();
    let cut = dir.path().join("cut.mcap");
    std::fs::write(&cut, &bytes[..bytes.len() * 2 / 3]).unwrap();
    let v = replay_json(&[cut.to_str().unwrap(), "--estimator", "paper"]);
    let n = v["samples"].as_u64().unwrap();
    assert!(n > 100 && n < 3000, "{n}");
    assert!(
        v["input_warnings"][0]
            .as_str()
            .unwrap()
            .contains("truncated"),
        "{v}"
    );
    check_recovery(&v, 1e-6, "truncated");
}

/// Too few samples say how many were read and how many are needed, and a truncated file
/// says it is damaged (it said "the recording is empty" for 0 samples of a cut file and
/// for 2 samples alike, and "no channel for topic" for a file cut before its channels).
#[test]
fn too_few_samples_say_how_many_and_whether_the_file_is_damaged() {
    let dir = tempfile::tempdir().unwrap();
    let bytes = std::fs::read(repo("recordings/two-beam-friction.mcap")).unwrap();
    let fails = |args: &[&str]| {
        let out = run(args);
        assert!(!out.status.success(), "{args:?} succeeded");
        String::from_utf8_lossy(&out.stderr).into_owned()
    };
    let cut = dir.path().join("cut5000.mcap");
    std::fs::write(&cut, &bytes[..5000]).unwrap();
    let err = fails(&["replay", cut.to_str().unwrap()]);
    assert!(
        err.contains("the recording is damaged (truncated at byte")
            && err.contains(
                "only 0 usable samples were read before it (identification needs at least 3)"
            )
            && !err.contains("empty"),
        "{err}"
    );
    let cut = dir.path().join("cut3000.mcap");
    std::fs::write(&cut, &bytes[..3000]).unwrap();
    let err = fails(&["replay", cut.to_str().unwrap()]);
    assert!(
        err.contains("no channel for topic /jointid/excitation: the recording is damaged, truncated before it at byte")
            && err.contains(" of 3000 ("),
        "{err}"
    );
    let two = dir.path().join("two.mcap");
    let setup = repo("recordings/two-beam-friction.toml");
    ok(&[
        "simulate",
        setup.to_str().unwrap(),
        "--out",
        two.to_str().unwrap(),
        "--steps",
        "2",
    ]);
    let err = fails(&["replay", two.to_str().unwrap()]);
    assert!(
        err.trim_end()
            .ends_with("only 2 usable samples were read (identification needs at least 3)"),
        "{err}"
    );
}

#[test]
fn bad_setup_names_the_key() {
    let dir = tempfile::tempdir().unwrap();
    let text = std::fs::read_to_string(repo("recordings/two-beam-spring.toml")).unwrap();
    let sp = dir.path().join("s.toml");
    std::fs::write(&sp, text.replace("gamma = 0.5", "gama = 0.5")).unwrap();
    let out = run(&[
        "simulate",
        sp.to_str().unwrap(),
        "--out",
        dir.path().join("x.mcap").to_str().unwrap(),
    ]);
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success() && err.contains("gama"), "{err}");
    assert!(!dir.path().join("x.mcap").exists());
}

/// One degree of freedom, no spring (`recordings/one-dof-friction.toml`: a mass on viscous
/// damping, Coulomb friction and a constant force, K = 0): on data of the model's own
/// discretisation at 1 % noise, seeds 1–3, every parameter within 3 standard errors and 2 %
/// (measured over seeds 1–6: within 1.7 se). Continuous data: ACCURACY.md.
/// `jointid simulate SETUP` (random input, 1 % additive noise, the given seed and extra
/// options) into `dir`, then `jointid replay --json` of it: every parameter within `k`
/// standard errors of its truth. Returns the replay's JSON.
fn simulate_and_replay_within(
    dir: &Path,
    setup: &Path,
    seed: &str,
    extra: &[&str],
    k: f64,
) -> serde_json::Value {
    let rec = simulate_with(dir, setup, seed, extra);
    let v = replay_json(&[rec.to_str().unwrap()]);
    assert_within(&v, seed, k);
    v
}

/// Whether one of a replay's JSON notes contains `what`.
fn says(v: &serde_json::Value, what: &str) -> bool {
    v["notes"]
        .as_array()
        .unwrap()
        .iter()
        .any(|n| n.as_str().unwrap().contains(what))
}

/// Every parameter of a replay's JSON within `k` standard errors of its truth.
fn assert_within(v: &serde_json::Value, seed: &str, k: f64) {
    for p in v["parameters"].as_array().unwrap() {
        let (value, truth, se) = (
            p["value"].as_f64().unwrap(),
            p["truth"].as_f64().unwrap(),
            p["std_error"].as_f64().unwrap(),
        );
        assert!(
            (value - truth).abs() < k * se,
            "seed {seed}, {}: {value} ± {se} against {truth}",
            p["basis"]
        );
    }
}

/// The spring setup (the paper's four-term basis, no friction in the truth), 8-sub-step
/// data at 100 % noise, seed 10043: the passes settle on a friction of 12.8 kN that sticks
/// in half the samples, and the prediction error's descent from there ended at `sign(u)`
/// 4,826 ± 650 N with the spring −4.4 % (6.9 errors off), no note. The law without friction,
/// fitted under the same observer, is likelier than that answer; refined again from there
/// the full law ends likelier by 10.3 and is taken: the spring within 0.5 % and every
/// parameter within 2 errors, and a note says so.
#[test]
fn a_friction_minimum_the_truth_does_not_have_is_left_for_the_likelier_start_without_it() {
    let dir = tempfile::tempdir().unwrap();
    let setup = repo("recordings/two-beam-spring.toml");
    let rec = simulate_with_noise(
        dir.path(),
        &setup,
        "10043",
        "additive:1.0",
        &["--substeps", "8"],
    );
    let v = replay_json(&[rec.to_str().unwrap()]);
    assert_within(&v, "10043", 2.0);
    let spring = &v["parameters"][1];
    assert_eq!(spring["basis"], "u");
    let k = spring["value"].as_f64().unwrap();
    assert!((k / 3.0e5 - 1.0).abs() < 0.005, "spring {k}");
    assert!(
        says(&v, "less likely than the law without friction's"),
        "no note of the second start: {}",
        v["notes"]
    );
}

/// An impact on the shipped friction setup (a 5 ms half-sine and the free decay after it),
/// 64-sub-step data at 1 % noise, seed 10306: the likelihood did not find this excitation
/// smooth between samples, so the impact went unrecognised, the bootstrap did not run and the
/// sandwich errors left `sign(u)` 6.1 errors off (−4.4 %). The excitation is quiet on 98 %
/// of the samples: the impact is recognised by that, the bootstrap runs (a note says why) and
/// every parameter is within 2 errors.
#[test]
fn an_impact_is_bootstrapped_when_its_excitation_is_not_found_smooth() {
    let dir = tempfile::tempdir().unwrap();
    let setup = repo("recordings/two-beam-friction.toml");
    let rec = dir.path().join("impact.mcap");
    ok(&[
        "simulate",
        setup.to_str().unwrap(),
        "--out",
        rec.to_str().unwrap(),
        "--scenario",
        "free",
        "--substeps",
        "64",
        "--noise",
        "additive:0.01",
        "--seed",
        "10306",
    ]);
    let v = replay_json(&[rec.to_str().unwrap()]);
    assert!(
        says(
            &v,
            "under an impact (the excitation below 1 % of its peak on 98 %"
        ),
        "no impact occasion: {}",
        v["notes"]
    );
    assert!(
        !says(&v, "the excitation was taken as smooth"),
        "{}",
        v["notes"]
    );
    assert_within(&v, "10306", 2.0);
}

/// A record nobody here simulated (`recordings/two-beam-friction-rk4.mcap`: the component
/// matrices integrated by RK4 at 1,000 steps a sample under a sum of sines, 10 % noise,
/// imported from CSV; `scripts/two_beam_campaign.py`). The residual-force passes run at the
/// setup's one model sub-step and leave the stiffness +1.1 % high; the prediction error's
/// level choice compared the levels at those values and kept one sub-step, and the answer
/// was `u` 303,394 ± 126 N/m (26.9 errors off). Each level is now compared with its own
/// observer force at its own values (Gauss–Newton steps from the start): 64 sub-steps are
/// kept and every parameter is within 2 errors of the truth the script used (1.4 at most).
#[test]
fn a_continuous_record_is_refined_at_the_levels_own_best_values() {
    let rec = repo("recordings/two-beam-friction-rk4.mcap");
    let v = replay_json(&[rec.to_str().unwrap()]);
    assert!(
        says(&v, "prediction-error refinement with 64 model sub-steps"),
        "{}",
        v["notes"]
    );
    assert_every_parameter_within(&v, &[3000.0, 3.0e5, 0.0, 0.0], 2.0);
}

/// Every parameter of a replay's JSON within `errors` stated standard errors of `truth` (the
/// parameters in the setup's order; a record without its truth, as an imported one).
fn assert_every_parameter_within(v: &serde_json::Value, truth: &[f64], errors: f64) {
    let parameters = v["parameters"].as_array().unwrap();
    assert_eq!(parameters.len(), truth.len());
    for (p, truth) in parameters.iter().zip(truth) {
        let (value, se) = (
            p["value"].as_f64().unwrap(),
            p["std_error"].as_f64().unwrap(),
        );
        assert!(
            (value - truth).abs() < errors * se,
            "{}: {value} ± {se} against {truth}",
            p["basis"]
        );
    }
}

/// A record cut from a test in motion that nobody here simulated
/// (`recordings/two-beam-spring-rk4-motion.mcap`: RK4 at 1,000 steps a sample, the record
/// cut 20 ms into the test, 10 % noise, imported from CSV; `scripts/two_beam_campaign.py
/// spring 102 3 0.1 --motion`, seed 104). Its start state is estimated. The prediction
/// error's level choice stepped each level from the passes' values by Gauss–Newton on
/// innovations (and a Jacobian) that still carried the start state's error, and judged the
/// steps by the likelihood with that error refitted: the steps spent the parameters on the
/// start state's ringing, the likelihood did not reward them, one sub-step was kept, and `u`
/// came out 303,251 ± 84 N/m (38.7 errors off). With the steps' innovations and Jacobian
/// concentrated over the start state as the likelihood is, 8 sub-steps are kept and every
/// parameter is within 2 errors of the truth the script used (1.1 at most).
#[test]
fn a_continuous_record_cut_in_motion_is_refined_at_a_finer_level() {
    let rec = repo("recordings/two-beam-spring-rk4-motion.mcap");
    let v = replay_json(&[rec.to_str().unwrap()]);
    assert!(says(&v, "the record starts in motion"), "{}", v["notes"]);
    assert!(
        says(&v, "prediction-error refinement with 8 model sub-steps"),
        "{}",
        v["notes"]
    );
    assert_every_parameter_within(&v, &[0.0, 3.0e5, 0.0, 0.0], 2.0);
}

#[test]
fn one_dof_mass_on_a_friction_joint_without_a_spring() {
    let dir = tempfile::tempdir().unwrap();
    let setup = repo("recordings/one-dof-friction.toml");
    for seed in ["1", "2", "3"] {
        let extra = ["--steps", "3000", "--amplitude", "50"];
        let v = simulate_and_replay_within(dir.path(), &setup, seed, &extra, 3.0);
        for p in v["parameters"].as_array().unwrap() {
            let (value, truth) = (p["value"].as_f64().unwrap(), p["truth"].as_f64().unwrap());
            assert!(
                (value / truth - 1.0).abs() < 0.02,
                "seed {seed}, {}: {value} against {truth}",
                p["basis"]
            );
        }
    }
}

/// The 1-DOF setup at 100 % noise, read as a record in motion (`--in-motion`, the path
/// the README gives 1-DOF users): the prediction error's descent walked the damper to
/// 9.0e4 ± 1.1e5 N s/m (truth 20) — the observer followed the record whatever the damper
/// — and its bootstrap to 5.4e30 ± 2.1e31, which was printed as the answer. The refinement is
/// now refused with the figure (the damper's force error against the connection's force),
/// the exit code is non-zero, and no such value is printed.
#[test]
fn a_one_dof_damper_the_innovations_leave_free_is_refused_with_the_figure() {
    let dir = tempfile::tempdir().unwrap();
    let setup = repo("recordings/one-dof-friction.toml");
    let extra = ["--steps", "3000", "--amplitude", "50"];
    let rec = simulate_with_noise(dir.path(), &setup, "7811", "additive:1.0", &extra);
    let out = run(&["replay", rec.to_str().unwrap(), "--in-motion"]);
    let (stdout, stderr) = (
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr),
    );
    assert!(!out.status.success(), "{stdout}\n{stderr}");
    assert!(
        stdout.contains("`stage.v`") && stdout.contains("leave it free"),
        "{stdout}"
    );
    assert!(stderr.contains("was not usable"), "{stderr}");
    // The passes' own stop is reported beside the failure (it was an empty line).
    let stop = stdout
        .lines()
        .find(|l| l.contains(" pass(es): "))
        .expect("the passes' line");
    assert!(
        stop.split(" pass(es): ")
            .nth(1)
            .is_some_and(|r| !r.trim().is_empty()),
        "{stop}"
    );
    // The table shows the passes' residual-force estimate, not the refused value.
    let damper = stdout
        .lines()
        .find(|l| l.starts_with("stage") && l.split_whitespace().nth(1) == Some("v"))
        .expect("the damper's row");
    let value: f64 = damper.split_whitespace().nth(2).unwrap().parse().unwrap();
    assert!(value.abs() < 1e3, "{damper}");
}

/// The 1-DOF setup at rest (model at 1 sub-step) on data integrated 8 and 64 times finer:
/// the free run's minimum at 1 sub-step compensates that model's discretisation error, so
/// every finer model costs more *at it*, and the sub-steps were not raised — seed 7813 was
/// 12.9 errors off (`const` 1.9748 ± 0.0020 N) at 10 % noise on 8-sub-step data and 206
/// errors off at 1 % on 64-sub-step data. Each doubling is now refined from the last answer
/// (continuation; since the thirty-ninth session every doubling, the finest within Δχ² = 1
/// of the lowest taken): every parameter within 3 errors, the
/// free run's own answer at 4 sub-steps or more (measured: 4 and 64), and the note says so.
#[test]
fn one_dof_on_finer_data_raises_the_model_sub_steps_by_continuation() {
    let dir = tempfile::tempdir().unwrap();
    for (substeps, noise) in [("8", "additive:0.1"), ("64", "additive:0.01")] {
        one_dof_raised_by_continuation(dir.path(), "7813", substeps, noise, 4);
    }
}

/// Simulate the 1-DOF setup at rest (3,000 samples, 50 N RMS, `data_substeps`, `noise`),
/// replay it with the defaults and assert the answer of the free run raised by continuation:
/// every parameter within 3 errors, the free run's own answer (not the prediction error's,
/// nor errors widened to a doubling's move) at `least` model sub-steps or more, and the note.
fn one_dof_raised_by_continuation(
    dir: &Path,
    seed: &str,
    data_substeps: &str,
    noise: &str,
    least: u64,
) {
    let rec = one_dof_record(dir, seed, data_substeps, noise);
    let v = replay_json(&[rec.to_str().unwrap()]);
    let case = format!("{seed} ({data_substeps} sub-steps, {noise})");
    assert_within(&v, &case, 3.0);
    let oe = &v["output_error"];
    assert!(
        oe["prediction_error"].is_null() && oe["accepted"] == true,
        "{case}: {oe}"
    );
    assert!(oe["substeps"].as_u64().unwrap() >= least, "{case}: {oe}");
    assert!(says(&v, "raised by continuation"), "{case}: {}", v["notes"]);
    assert!(!says(&v, "did not converge"), "{case}: {}", v["notes"]);
}

/// Passes that did not converge, and a refinement that failed from their last answer: the
/// 1-DOF setup on own-discretisation data at 100 % noise, seed 9820, where the tenth pass
/// jumped to a negative damper (`v` = −24 N s/m, its free run growing to χ² ≈ 1e26). The
/// refinement from it failed and that answer was reported 5.2 errors off; it now starts
/// again from the pass answer whose free run fits best (the ninth) and every parameter is
/// within 3 errors (measured: 0.24, 0.83 and 1.13).
#[test]
fn one_dof_refinement_starts_from_the_likeliest_pass_when_the_last_is_rejected() {
    let dir = tempfile::tempdir().unwrap();
    let rec = one_dof_record(dir.path(), "9820", "1", "additive:1.0");
    let v = replay_json(&[rec.to_str().unwrap()]);
    assert!(
        says(&v, "it started again from pass 9 of 10"),
        "{}",
        v["notes"]
    );
    assert_eq!(v["output_error"]["accepted"], true, "{}", v["output_error"]);
    assert_within(&v, "seed 9820", 3.0);
}

/// The continuation's levels on 64-sub-step 1-DOF data at 1 % noise, where the refined cost
/// is not monotone in the sub-steps and levels the likelihood cannot tell apart fit with
/// different parameters. Seed 7811: from the 1-sub-step answer 2 sub-steps cost more (χ²
/// +6.8) and the loop stopped there, `const` 4 and `sign(v)` 8.6 errors off, while 4 and 32
/// cost 18–19 less; every doubling is now refined. Seed 7816: 1 and 8 sub-steps within
/// Δχ² = 0.7, the coarser (taken before) with `v` 3.9 errors off; the finest within Δχ² = 1
/// is now taken. Both fail on e90ae60; every parameter within 3 errors now.
#[test]
fn one_dof_continuation_refines_every_doubling_and_takes_the_finest_equal_level() {
    let dir = tempfile::tempdir().unwrap();
    for seed in ["7811", "7816"] {
        one_dof_raised_by_continuation(dir.path(), seed, "64", "additive:0.01", 8);
    }
}

/// The 1-DOF setup on 8-sub-step data at 1 % noise, twenty seeds (8911–8930): the free
/// run's cost is a flat, rough valley where the curvature's errors were too narrow — 80 %
/// of the parameters covered, the worst 7.4 errors off (`v`, seed 8912), before the
/// likelihood-ratio check (`identify::likelihood`). Each error is now at least where the
/// cost along its profile line rises by 3.84, over 1.96: measured 95 % covered, worst 4.7
/// (seeds 8901–8960: 81 → 96 %, worst 7.4 → 4.7). Asserted: at least 88 % and none past 6
/// errors; every parameter checked, its width in the report, and at least one error
/// widened by the check.
#[test]
fn one_dof_friction_errors_hold_where_the_free_run_cost_is_flat() {
    let dir = tempfile::tempdir().unwrap();
    let mut replays = Vec::new();
    let mut widened = 0;
    for seed in 8911..=8930 {
        let seed = seed.to_string();
        let rec = one_dof_record(dir.path(), &seed, "8", "additive:0.01");
        let v = replay_json(&[rec.to_str().unwrap()]);
        let widths = v["output_error"]["likelihood_ratio_widths"]
            .as_array()
            .unwrap_or_else(|| {
                panic!(
                    "seed {seed}: no likelihood-ratio widths: {}",
                    v["output_error"]
                )
            })
            .iter()
            .map(|w| {
                w.as_f64()
                    .unwrap_or_else(|| panic!("seed {seed}: a parameter not checked: {w}"))
            })
            .collect::<Vec<_>>();
        assert_eq!(widths.len(), 3, "seed {seed}");
        assert!(widths.iter().all(|&w| w >= 1.0), "seed {seed}: {widths:?}");
        widened += usize::from(widths.iter().any(|&w| w > 1.01));
        replays.push((seed, v));
    }
    assert!(
        widened >= 1,
        "no error widened by the likelihood-ratio check"
    );
    assert_covered(&replays, 0.88, 6.0);
}

/// A copy of `setup` in `dir` that gives every sensor its noise level (`noise_std`): `level`
/// times the channel's RMS in the recording `rec`, the level `simulate --noise
/// additive:LEVEL` added (up to the noise's own share of that RMS), as a user who knows the
/// sensors' noise would give it.
fn with_given_noise_levels(dir: &Path, setup: &Path, rec: &Path, level: f64) -> std::path::PathBuf {
    let r = jointid::io::mcap::read_recording(rec).unwrap();
    let n = r.response.len() as f64;
    let m = r.response_channels.names.len();
    let levels: Vec<f64> = (0..m)
        .map(|k| {
            let rms = (r.response.iter().map(|f| f.values[k].powi(2)).sum::<f64>() / n).sqrt();
            level * rms / (1.0 + level * level).sqrt()
        })
        .collect();
    let mut text = String::new();
    let (mut in_sensor, mut k) = (false, 0);
    for line in std::fs::read_to_string(setup).unwrap().lines() {
        text.push_str(line);
        text.push('\n');
        if line.trim() == "[[sensors]]" {
            in_sensor = true;
        } else if in_sensor && line.trim_start().starts_with("name =") {
            text.push_str(&format!("noise_std = {:e}\n", levels[k]));
            (in_sensor, k) = (false, k + 1);
        }
    }
    assert_eq!(k, m, "every sensor given a level");
    let out = dir.join(format!(
        "given-{}",
        rec.file_name()
            .unwrap()
            .to_string_lossy()
            .replace(".mcap", ".toml")
    ));
    std::fs::write(&out, text).unwrap();
    out
}

/// The sensors' noise levels given (`noise_std`) for a friction law's free run: the 1-DOF
/// setup at 1 % noise on 64-sub-step data. With the sharp likelihood the levels give, the
/// free run's errors (sandwich and likelihood ratio) covered 44 % of 30 records, worst 47
/// errors, the truth costing less than the answer on every record probed (a descent stopped
/// in one of the rough cost's minima); the difference-estimated levels, 77× the
/// accelerometer's real one, had smoothed the cost. The parametric bootstrap now runs by
/// itself there: 92 %, worst 6.0 (ACCURACY.md, fifty-first session). Without it these
/// twelve seeds were up to 31 errors off (seven beyond 6).
#[test]
fn a_friction_law_with_the_sensors_noise_given_is_bootstrapped_by_itself() {
    let dir = tempfile::tempdir().unwrap();
    let setup = repo("recordings/one-dof-friction.toml");
    let mut replays = Vec::new();
    for seed in 9501..=9512 {
        let seed = seed.to_string();
        let rec = one_dof_record(dir.path(), &seed, "64", "additive:0.01");
        let given = with_given_noise_levels(dir.path(), &setup, &rec, 0.01);
        let v = replay_json(&[rec.to_str().unwrap(), "--setup", given.to_str().unwrap()]);
        assert!(
            says(&v, "automatic: the setup gives sensors' noise levels"),
            "seed {seed}: {}",
            v["notes"]
        );
        assert!(
            v["output_error"]["bootstrap"]["used"].as_u64().unwrap_or(0) >= 5,
            "seed {seed}: {}",
            v["output_error"]
        );
        replays.push((seed, v));
    }
    // Coverage over these 12 seeds: 86 % before the fifty-second session's continuation
    // (every level refined), 75 % after: the replicates, identified the same way, now
    // search better and spread less, while the answers are the same (30 seeds, 9501–9530:
    // 92 % → 88 %, worst 6.0 → 4.2; ACCURACY.md, fifty-second session).
    assert_covered(&replays, 0.75, 6.5);
}

/// The free run's model sub-steps on 8-sub-step data with the sensors' noise levels given
/// (the 1-DOF friction setup, 1 % noise, seed 8918): the screening judged each level by its
/// cost at the passes' minima and took 16, where the answer was 21.7 errors off (`const`)
/// and the truth at the data's own 8 cost Δχ² = 51 less; only 16 and finer had been
/// refined. The continuation now refines the coarser levels too (each from the one above,
/// until one fits worse) and takes 8: within 3 errors. Over seeds 8901–8960 the levels
/// taken went from 41 to 55 of 60 at the data's 8, the worst from 21.7 to 7.0 errors
/// (ACCURACY.md, fifty-second session).
#[test]
fn a_coarser_level_the_screening_passed_over_is_refined_and_taken() {
    let v = one_dof_replayed_with_levels_given("8918", "8");
    assert!(
        says(
            &v,
            "model sub-steps lowered by continuation to 8 per sample"
        ),
        "{}",
        v["notes"]
    );
    assert_eq!(v["output_error"]["substeps"], 8, "{}", v["output_error"]);
    assert_within(&v, "8918", 4.0);
}

/// A coarser level that fits best on continuous data found a better valley of the rough
/// friction cost, not a better discretisation: the finer levels are climbed again from it.
/// The 1-DOF setup, 64-sub-step data at 1 %, the sensors' levels given, seed 9521: the first
/// answer at 16 sub-steps; refined downward, 8 cost Δχ² = 262 less than it. Without the
/// climb 8 was taken (data 64 times finer than a sample); climbed from 8, 64 costs 490 less
/// and is taken, every parameter within 2.4 errors (3.3 before this session's continuation;
/// ACCURACY.md, fifty-second session; asserted: within 3).
#[test]
fn the_finer_levels_are_climbed_again_from_a_coarser_winner() {
    let v = one_dof_replayed_with_levels_given("9521", "64");
    assert!(
        says(&v, "the finer ones climbed again from the coarser level"),
        "{}",
        v["notes"]
    );
    assert_eq!(v["output_error"]["substeps"], 64, "{}", v["output_error"]);
    assert_within(&v, "9521", 3.0);
}

/// The 1-DOF friction setup's record of `seed` (3,000 samples, 50 N RMS, `substeps` data
/// sub-steps, 1 % noise) replayed with the sensors' noise levels given, as JSON.
fn one_dof_replayed_with_levels_given(seed: &str, substeps: &str) -> serde_json::Value {
    let dir = tempfile::tempdir().unwrap();
    let rec = one_dof_record(dir.path(), seed, substeps, "additive:0.01");
    let setup = repo("recordings/one-dof-friction.toml");
    let given = with_given_noise_levels(dir.path(), &setup, &rec, 0.01);
    replay_json(&[rec.to_str().unwrap(), "--setup", given.to_str().unwrap()])
}

/// The passes' answer for a friction law can be a model the free run cannot even simulate:
/// Coulomb `sign(v), u`, 8-sub-step data at 1 % noise, the sensors' noise levels given, seed
/// 9317: the passes' random-walk force tuned far above the default's and their fit gave
/// `u` = −1.8e5 N/m, at which the free run's effective mass matrix is singular. The
/// refinement then had no start, and the passes' answer was reported (`u` 7.9 errors off;
/// on seed 9315 with levels a little low, −1.78e6 ± 1.6e5). The scan gives the start
/// instead, as when the residual-force stage is refused.
#[test]
fn a_passes_answer_the_free_run_cannot_simulate_is_replaced_by_a_scan_start() {
    let dir = tempfile::tempdir().unwrap();
    let setup = coulomb_setup(dir.path());
    let rec = simulate_with(dir.path(), &setup, "9317", &["--substeps", "8"]);
    let given = with_given_noise_levels(dir.path(), &setup, &rec, 0.01);
    let v = replay_json(&[rec.to_str().unwrap(), "--setup", given.to_str().unwrap()]);
    assert!(says(&v, "cannot be simulated"), "{}", v["notes"]);
    assert!(
        v["stop_reason"]
            .as_str()
            .unwrap()
            .contains("output-error stage from a scan"),
        "{}",
        v["stop_reason"]
    );
    assert!(
        !says(&v, "output-error refinement not run"),
        "{}",
        v["notes"]
    );
    assert_within(&v, "9317", 3.0);
}

/// `--bootstrap N` on free-run output-error answers (the 1-DOF friction law at rest, and
/// Coulomb `sign(v), u`): N records simulated from the answer, each identified again by the
/// whole procedure; the stated errors are at least their spread as a Student's t interval,
/// the answer is not moved, and the report and a note say so (before, `--bootstrap` said it
/// was not run). Measured (6 replicates): on the 1-DOF record (seed 7813, 8-sub-step data,
/// 10 % noise) `const` was floored from ± 0.00191 to ± 0.00237 N until the likelihood-ratio
/// check (fiftieth session) widened it to ± 0.00254 itself, so none is floored there now;
/// on the Coulomb record (seed 9047, own discretisation, 100 % noise, 5.2 errors off with
/// the sandwich alone) the friction's spread is 1.24× its error and is floored.
#[test]
fn bootstrap_asked_for_on_a_free_run_answer_floors_its_errors() {
    let dir = tempfile::tempdir().unwrap();
    let one_dof = repo("recordings/one-dof-friction.toml");
    let coulomb = coulomb_setup(dir.path());
    let extra = ["--steps", "3000", "--amplitude", "50", "--substeps", "8"];
    let cases = [
        (
            simulate_with_noise(dir.path(), &one_dof, "7813", "additive:0.1", &extra),
            None,
        ),
        (
            simulate_with_noise(dir.path(), &coulomb, "9047", "additive:1.0", &[]),
            Some(coulomb.to_str().unwrap()),
        ),
    ];
    let mut floored = 0;
    for (rec, setup) in &cases {
        let rec = rec.to_str().unwrap();
        let with = |n: &'static str| {
            let mut args = vec![rec, "--bootstrap", n];
            if let Some(s) = setup {
                args.extend(["--setup", s]);
            }
            replay_json(&args)
        };
        let (plain, v) = (with("0"), with("6"));
        assert_within(&v, rec, 3.0);
        let boot = &v["output_error"]["bootstrap"];
        let used = boot["used"].as_u64().unwrap() as usize;
        assert!(used >= 5 && boot["failure"].is_null(), "{rec}: {boot}");
        // Student's t with used − 1 degrees of freedom over the normal's 97.5 % quantile
        // (the tables; the code takes them up to 4 degrees and its expansion, within 0.1 %,
        // above).
        let t_ratio = [2.776, 2.571][used - 5] / 1.959964;
        for (j, p) in v["parameters"].as_array().unwrap().iter().enumerate() {
            let (value, se) = (
                p["value"].as_f64().unwrap(),
                p["std_error"].as_f64().unwrap(),
            );
            let floor = boot["spread"][j].as_f64().unwrap() * t_ratio;
            let before = &plain["parameters"][j];
            let se_before = before["std_error"].as_f64().unwrap();
            assert!(floor > 0.0, "{rec}: {boot}");
            assert!(
                se >= floor * 0.995 && se >= se_before,
                "{rec}: {p} {before} {boot}"
            );
            assert_eq!(value, before["value"].as_f64().unwrap(), "{p} {before}");
            if se > se_before && (se / floor - 1.0).abs() < 0.005 {
                floored += 1;
            }
        }
        assert!(
            says(&v, "parametric bootstrap of the free run"),
            "{rec}: {}",
            v["notes"]
        );
        assert!(!says(&v, "`--bootstrap` not run"), "{rec}: {}", v["notes"]);
    }
    assert!(floored >= 1, "no error floored by the bootstrap");
}

/// The shipped friction setup (model at 1 sub-step) replaying continuous-like data (8
/// Newmark sub-steps, 1 % noise) at `simulate`'s default excitation: the prediction-error
/// refinement tries every model sub-step level up to 64 and keeps the likeliest. Seeds 5 and
/// 6 were −32 % (6.9 se) and −6.4 % (621 se: the refinement stopped at 1 sub-step and fell
/// back to the free-run output error); every parameter is now within 3 standard errors.
/// The errors are the prediction error's sandwich, not the naive information of its
/// innovations, which was a floor under them until 2026-11-26 and overstated them 3–4×
/// (friction ± 110–130 N where the estimates of 50 seeds spread by 29 N): the friction's
/// stated error is now below 2 % of its value, and no Cramér–Rao bound is claimed.
#[test]
fn shipped_friction_setup_on_eight_substep_data() {
    let dir = tempfile::tempdir().unwrap();
    let setup = repo("recordings/two-beam-friction.toml");
    for seed in ["5", "6"] {
        let extra = ["--steps", "2000", "--substeps", "8"];
        let v = simulate_and_replay_within(dir.path(), &setup, seed, &extra, 3.0);
        let friction = &v["parameters"][0];
        let (value, se) = (
            friction["value"].as_f64().unwrap(),
            friction["std_error"].as_f64().unwrap(),
        );
        assert!((value / 3000.0 - 1.0).abs() < 0.05, "seed {seed}: {value}");
        assert!(se < 60.0, "seed {seed}: friction ± {se} N");
        assert!(friction["crlb"].is_null(), "seed {seed}: {friction}");
    }
}

/// The shipped friction setup on data of its own discretisation (1 sub-step) at 10 % noise:
/// every zero crossing of δ that moves by a sample flips the friction for a whole sample, so
/// the innovation cost is rough at the scale of the error. Seeds 41 and 45 were 25 and 14
/// errors off (friction ± 5.5 and ± 3.3 N where the estimates of 50 seeds spread by ~70 N):
/// the errors came from a secant of ±1 error, which saw single jumps of the cost. The polish
/// and the errors now use secants wide against the error
/// (`estimate::prediction_error::{POLISH_SECANT, ERROR_SECANTS}`), and the parametric
/// bootstrap runs on such records by itself (asserted).
///
/// Asserted over ten seeds (41–50), not one: on this rough cost the last digits of the
/// arithmetic move single answers (the forty-ninth session's round-off change moved seed
/// 41's `u` from −4.4 to −5.4 errors, its bootstrap errors from 598 to 488 N/m, while the
/// ten seeds' coverage went from 90 % to 88 %; ACCURACY.md). Every friction error is wide
/// (> 20 N, the regression), at least 80 % of the 40 stated 95 % intervals hold the truth
/// and none is more than 6 errors off (measured: 88 %, worst 5.4).
#[test]
fn own_discretisation_friction_at_ten_percent_noise_states_honest_errors() {
    let dir = tempfile::tempdir().unwrap();
    let setup = repo("recordings/two-beam-friction.toml");
    let mut replays = Vec::new();
    for seed in 41..=50 {
        let seed = seed.to_string();
        let rec = simulate_with_noise(dir.path(), &setup, &seed, "additive:0.1", &[]);
        let v = replay_json(&[rec.to_str().unwrap()]);
        let friction = v["parameters"][0]["std_error"].as_f64().unwrap();
        assert!(friction > 20.0, "seed {seed}: friction ± {friction} N");
        let boot = &v["output_error"]["prediction_error"]["bootstrap"];
        assert_eq!(boot["used"].as_u64(), Some(10), "seed {seed}: {boot}");
        replays.push((seed, v));
    }
    assert_covered(&replays, 0.8, 6.0);
}

/// Coulomb friction (`sign(v), u`, refined by the free-run output error) on data of its own
/// discretisation at 10 % noise, seed 29: −0.94 % with the friction ± 5.3 N, 5.3 errors off
/// (the estimates of 50 seeds spread by ~15 N) — the secant of ±1 error saw single jumps of
/// the rough cost. The final errors are now restated after the scan
/// (`identify::scan::restate_final_errors`): the sandwich of the fit at the noise levels
/// the residuals show, the larger over secants of ±1 and ±8 errors — ± 9.0 N, 3.1 errors.
/// The bound is the acceptance's 5 errors less one (the 50-seed row's worst is 3.1).
#[test]
fn own_discretisation_coulomb_at_ten_percent_noise_states_honest_errors() {
    let dir = tempfile::tempdir().unwrap();
    let setup = coulomb_setup(dir.path());
    let rec = simulate_with_noise(dir.path(), &setup, "29", "additive:0.1", &[]);
    let v = replay_json(&[rec.to_str().unwrap(), "--setup", setup.to_str().unwrap()]);
    assert_within(&v, "29", 4.0);
    let friction = v["parameters"][0]["std_error"].as_f64().unwrap();
    assert!(friction > 7.0, "friction ± {friction} N");
    let notes = v["notes"].as_array().unwrap();
    assert!(
        notes
            .iter()
            .any(|n| n.as_str().unwrap().starts_with("final standard errors")),
        "{notes:?}"
    );
}

/// A Coulomb answer stopped on a ripple of the friction level's output-error cost
/// (own-discretisation data at 1 % noise, seeds 7705 and 7745 of the thirty-fifth session's
/// acceptance sweep): `sign(v)` 3,056 ± 0.95 N and 3,026 ± 0.84 N, 59 and 31 errors off,
/// with only the whiteness note to say so (ACCURACY.md, thirty-fifth session). Asked by the
/// residuals that are not white, a free run from the prediction error's answer finds the
/// bottom of the level's bowl: every parameter within 3 errors, the residuals white, and
/// the refinement's note says where the answer came from. Fails on d96bebb (59 and 31
/// errors; the thirty-fifth session's friction-level scan, which this replaced, also passed).
#[test]
fn a_coulomb_answer_on_a_ripple_of_the_friction_cost_is_found_again_from_the_observer() {
    let dir = tempfile::tempdir().unwrap();
    let setup = coulomb_setup(dir.path());
    for seed in ["7705", "7745"] {
        let rec = simulate_with(
            dir.path(),
            &setup,
            seed,
            &["--steps", "2000", "--substeps", "1"],
        );
        let v = replay_json(&[rec.to_str().unwrap(), "--setup", setup.to_str().unwrap()]);
        assert_within(&v, seed, 3.0);
        // The minimum's own error (1.1–1.2 N), not widened to cover the ripple's answer.
        let friction_se = v["parameters"][0]["std_error"].as_f64().unwrap();
        assert!(friction_se < 2.0, "seed {seed}: ± {friction_se}");
        assert_taken_from_the_observer(&v, seed);
    }
}

/// A replay's answer came from the free run started at the prediction error's answer (the
/// refinement's note says so) and its residuals are white.
fn assert_taken_from_the_observer(v: &serde_json::Value, seed: &str) {
    assert!(
        !says(v, "the residuals are not white"),
        "seed {seed}: {}",
        v["notes"]
    );
    let note = v["output_error"]["note"].as_str().unwrap();
    assert!(
        note.contains("started at the prediction error's answer"),
        "seed {seed}: {note}"
    );
}

/// The shipped gap setup (`gap(0.02), v`) on 8-sub-step data at 10 % noise, seeds 7504 and
/// 7514 of the thirty-fourth session's gap sweep (re-run on 07936bf): the passes did not
/// converge (the last change ~7 errors) and the free-run output error from their answer stopped in a local
/// minimum — the damper 17.6 and 9.6 N s/m (truth 20) with 0.03 N s/m stated, 89 and 352
/// errors off, the gap's stiffness 29 and 64 errors off — with only the whiteness note to
/// say so (at seed 7514 the truth's free-run cost is lower by Δχ² ≈ 8,000). The prediction
/// error's descent from the same start goes to the truth's basin, and the free run from its
/// answer is taken: every parameter within 3 errors, the residuals white, and the
/// refinement's note says where the answer came from (ACCURACY.md, thirty-sixth session);
/// and the errors are the minimum's own, not widened to cover the old answer (the damper's
/// 0.04–0.10 N s/m; covering the old minimum would make it ~10).
#[test]
fn a_gap_answer_in_a_local_minimum_of_the_free_run_is_found_again_from_the_observer() {
    let dir = tempfile::tempdir().unwrap();
    let setup = repo("recordings/two-beam-gap.toml");
    for seed in ["7504", "7514"] {
        let rec = simulate_with_noise(
            dir.path(),
            &setup,
            seed,
            "additive:0.1",
            &["--steps", "2000", "--substeps", "8"],
        );
        let v = replay_json(&[rec.to_str().unwrap()]);
        assert_within(&v, seed, 3.0);
        let (damper, damper_se) = (
            v["parameters"][1]["value"].as_f64().unwrap(),
            v["parameters"][1]["std_error"].as_f64().unwrap(),
        );
        assert!(
            (damper / 20.0 - 1.0).abs() < 0.01 && damper_se < 0.3,
            "seed {seed}: {damper} ± {damper_se}"
        );
        assert_taken_from_the_observer(&v, seed);
    }
}

/// The shipped spring setup (the paper's four-term basis, friction truth 0) on 8-sub-step
/// data: the prediction-error refinement ends with the friction on its bound 0 — the truth
/// — and that is kept because the residual-force estimate had not found friction. Seeds 4
/// and 5 were refused there and fell back to the free-run output error: spring +1.08 %
/// (96 se) and +1.03 % (8 se). Now every parameter is within 3 standard errors and the
/// spring within 0.1 %. Seed 45 was refused there too until the observer stopped removing
/// its correction along a stuck joint (the innovation cost then jumped between friction 0
/// and any positive level, so the bound looked determined): spring +1.07 %, 26 se after the
/// misfit widening; now within 0.1 se.
#[test]
fn shipped_spring_setup_on_eight_substep_data() {
    let dir = tempfile::tempdir().unwrap();
    let setup = repo("recordings/two-beam-spring.toml");
    for seed in ["4", "5", "45"] {
        let extra = ["--steps", "2000", "--substeps", "8"];
        let v = simulate_and_replay_within(dir.path(), &setup, seed, &extra, 3.0);
        let spring = v["parameters"][1]["value"].as_f64().unwrap();
        assert!((spring / 3.0e5 - 1.0).abs() < 1e-3, "seed {seed}: {spring}");
    }
}

/// A component model that is not the tested structure (the beams' EI 5 % above the data's):
/// the output error explains the outputs only to about 50× the noise variance. Its standard
/// errors (already the bound scaled by the residuals' level, √cost) are then widened by √cost
/// once more — by the cost in all — and the note says so. Spring law `u, v` on the Kalman
/// pipeline, seed 3: −0.064 % ± 50 N/m (3.8 stated errors; about 190 without the widening).
/// (Seed 22 of the spring setup on 64-sub-step data was this case until the prediction
/// error stopped refusing a friction on its bound the innovations cannot tell from the
/// start's level, 2026-11-26.)
#[test]
fn output_error_that_does_not_fit_widens_its_errors() {
    let dir = tempfile::tempdir().unwrap();
    let mut text = setup_variant_text("two-beam-spring.toml", &["u", "v"], &[3.0e5, 0.0], 1);
    let truth_setup = dir.path().join("truth.toml");
    std::fs::write(&truth_setup, &text).unwrap();
    text = text.replace("ei = 1.0e5", "ei = 1.05e5");
    let wrong = dir.path().join("wrong-ei.toml");
    std::fs::write(&wrong, &text).unwrap();
    let rec = simulate_with(dir.path(), &truth_setup, "3", &["--steps", "2000"]);
    let v = replay_json(&[rec.to_str().unwrap(), "--setup", wrong.to_str().unwrap()]);
    let note = v["notes"]
        .as_array()
        .unwrap()
        .iter()
        .filter_map(|n| n.as_str())
        .find(|n| n.starts_with("the model explains the outputs only"))
        .expect("the misfit note")
        .to_string();
    assert!(note.contains("widened by the cost"), "{note}");
    let cost = v["output_error"]["cost_end"].as_f64().unwrap();
    assert!(cost > 10.0, "normalised cost {cost}");
    let p = &v["parameters"][0];
    let (value, se, bound) = (
        p["value"].as_f64().unwrap(),
        p["std_error"].as_f64().unwrap(),
        p["crlb"].as_f64().unwrap(),
    );
    assert!(
        (se / bound / cost - 1.0).abs() < 0.05,
        "std error {se} = {:.2}× the bound {bound}, cost {cost}",
        se / bound
    );
    let z = (value - 3.0e5) / se;
    assert!(
        z.abs() < 5.0,
        "spring {value} ± {se}: {z:.1} standard errors"
    );
}

/// A law linear in the state on the Kalman pipeline (the spring setup with `u, v`, `kind =
/// "kalman"` kept), 64-sub-step data, 1 % noise, seed 22: the output error's sub-step raise
/// refines the law afresh at every level and takes 64. It used to judge the finer levels
/// at the 1-sub-step minimum, took none, and stated +1.10 % ± 0.003 % (344 se).
#[test]
fn a_linear_law_on_the_kalman_pipeline_raises_its_sub_steps() {
    let dir = tempfile::tempdir().unwrap();
    let setup = dir.path().join("linear.toml");
    let text = setup_variant_text("two-beam-spring.toml", &["u", "v"], &[3.0e5, 0.0], 1);
    assert!(text.contains("kind = \"kalman\""));
    std::fs::write(&setup, text).unwrap();
    let extra = ["--steps", "2000", "--substeps", "64"];
    let v = simulate_and_replay_within(dir.path(), &setup, "22", &extra, 3.0);
    let spring = v["parameters"][0]["value"].as_f64().unwrap();
    assert!((spring / 3.0e5 - 1.0).abs() < 1e-4, "{spring}");
    assert_eq!(
        v["output_error"]["substeps"].as_u64(),
        Some(64),
        "{}",
        v["output_error"]
    );
}

/// Seeds 22 and 49 of the shipped spring setup (friction truth 0) on 64-sub-step data, 1 %
/// noise: the residual-force estimate finds a friction (97 ± 41 N, 17 ± 4 N; 100 and 27 N
/// in earlier sessions), the prediction error ends with it on its bound 0, and its
/// likelihood-ratio statistic against the start's level is small (0.83, 0.13): the result
/// stands with intervals that reach that level, whatever the sandwich says (seed 49's is
/// ± 17 N since the fortieth session's errors, ± 39 N before). Refused (as before), the
/// free-run output error put the spring +1.1 %, 26 and 21 standard errors off.
#[test]
fn a_friction_the_innovations_cannot_tell_from_zero_stands_with_wide_intervals() {
    let dir = tempfile::tempdir().unwrap();
    let setup = repo("recordings/two-beam-spring.toml");
    for seed in ["22", "49"] {
        let extra = ["--steps", "2000", "--substeps", "64"];
        let v = simulate_and_replay_within(dir.path(), &setup, seed, &extra, 3.0);
        let spring = v["parameters"][1]["value"].as_f64().unwrap();
        assert!((spring / 3.0e5 - 1.0).abs() < 1e-3, "seed {seed}: {spring}");
        let notes: Vec<&str> = v["notes"]
            .as_array()
            .unwrap()
            .iter()
            .filter_map(|n| n.as_str())
            .collect();
        assert!(
            notes
                .iter()
                .any(|n| n.contains("likelihood-ratio statistic")),
            "seed {seed}: {notes:?}"
        );
        // The start's level as the note states it: "(the start gave L ± E)".
        let start_level: f64 = notes
            .iter()
            .find_map(|n| n.split("the start gave ").nth(1))
            .and_then(|rest| rest.split(' ').next())
            .and_then(|x| x.parse().ok())
            .unwrap_or_else(|| panic!("seed {seed}: no start level in {notes:?}"));
        assert!(start_level > 10.0, "seed {seed}: start level {start_level}");
        let friction = &v["parameters"][0];
        assert!(
            friction["ci95"][1].as_f64().unwrap() >= 0.999 * start_level,
            "seed {seed}: {friction} against the start's {start_level}"
        );
    }
}

/// Coulomb friction (`sign(v), u`) on the shipped friction setup's model (1 sub-step),
/// 8-sub-step data, 1 % noise: the output-error refinement takes the likeliest sub-steps of
/// every level up to 64. Seeds 5 and 6 were −11 % friction and +3 % spring at 15–27 se when
/// it doubled them only while a doubling helped; now within 3 se and 1 %.
#[test]
fn coulomb_friction_on_eight_substep_data() {
    let dir = tempfile::tempdir().unwrap();
    let setup = coulomb_setup(dir.path());
    for seed in ["5", "6"] {
        let extra = ["--steps", "2000", "--substeps", "8"];
        let v = simulate_and_replay_within(dir.path(), &setup, seed, &extra, 3.0);
        for p in v["parameters"].as_array().unwrap() {
            let (value, truth) = (p["value"].as_f64().unwrap(), p["truth"].as_f64().unwrap());
            assert!(
                (value / truth - 1.0).abs() < 0.01,
                "seed {seed}, {}: {value} against {truth}",
                p["basis"]
            );
        }
    }
}

/// Coulomb friction (`sign(v), u`) under a 200 Hz sine, 8-sub-step data, 1 % noise (seed
/// 8301): the model held the excitation linear between samples, 0.13 % short of a sine's
/// mean over each sample, and the free run answered `sign(v)` 7.0 and `u` 11.4 of its
/// errors off. The likelier excitation between samples is now taken (the smooth one here,
/// a note says so and the report gives its gain), and both are within 2 errors; the same
/// seed's random record (piecewise linear between samples) keeps the linear one.
#[test]
fn a_coulomb_joint_under_a_sine_is_fitted_with_the_excitation_smooth_between_samples() {
    const SMOOTH: &str = "the excitation was taken as smooth between samples";
    let dir = tempfile::tempdir().unwrap();
    let setup = coulomb_setup(dir.path());
    let rec = dir.path().join("sine.mcap");
    ok(&[
        "simulate",
        setup.to_str().unwrap(),
        "--out",
        rec.to_str().unwrap(),
        "--scenario",
        "sine",
        "--substeps",
        "8",
        "--noise",
        "additive:0.01",
        "--seed",
        "8301",
    ]);
    let v = replay_json(&[rec.to_str().unwrap()]);
    assert!(says(&v, SMOOTH), "{:#?}", v["notes"]);
    assert!(
        v["output_error"]["smooth_excitation_gain"]
            .as_f64()
            .unwrap()
            > 10.0,
        "{}",
        v["output_error"]
    );
    assert_within(&v, "8301 (sine)", 2.0);
    let random = simulate_with(dir.path(), &setup, "8301", &["--substeps", "8"]);
    let v = replay_json(&[random.to_str().unwrap()]);
    assert!(!says(&v, SMOOTH), "{:#?}", v["notes"]);
    assert!(v["output_error"].get("smooth_excitation_gain").is_none());
    assert_within(&v, "8301 (random)", 3.0);
}

/// A record at rest whose residual-force stage is refused (100 % noise: the joint
/// deformation undetermined) goes to the scan fallback, whose 200-sample prefix may prefer a
/// model finer than the data's own discretisation by noise alone; the output error then
/// takes the likeliest level from the setup's up, coarser ones included. Seed 7141
/// (Coulomb, 8-sub-step data) was refused as "starts in motion" when only finer levels were
/// tried (refined at 16 sub-steps, cost 2.2× the noise, which a start state half explained);
/// now answered at 8 sub-steps, cost 0.99, within 2 errors (`sign(v)` −1.4, `u` −0.06).
#[test]
fn a_noisy_record_at_rest_is_not_taken_for_motion_by_a_too_fine_scan_level() {
    let dir = tempfile::tempdir().unwrap();
    let setup = coulomb_setup(dir.path());
    let extra = ["--steps", "2000", "--substeps", "8"];
    let rec = simulate_with_noise(dir.path(), &setup, "7141", "additive:1.0", &extra);
    let v = replay_json(&[rec.to_str().unwrap()]);
    assert_within(&v, "7141", 2.0);
    assert!(
        says(&v, "output-error refinement with 8 model sub-steps"),
        "{:#?}",
        v["notes"]
    );
}

/// `dir/coulomb.toml`: the shipped friction setup (1 model sub-step) with Coulomb friction
/// and a spring, `sign(v), u` (truth 3,000 N and 3e5 N/m).
fn coulomb_setup(dir: &Path) -> std::path::PathBuf {
    let setup = dir.join("coulomb.toml");
    let text = setup_variant_text(
        "two-beam-friction.toml",
        &["sign(v)", "u"],
        &[3000.0, 3.0e5],
        1,
    );
    std::fs::write(&setup, text).unwrap();
    setup
}

/// `jointid simulate SETUP` (random input, 1 % noise, `seed`, `extra` options) into
/// `dir/seed-SEED.mcap`.
fn simulate_with(dir: &Path, setup: &Path, seed: &str, extra: &[&str]) -> std::path::PathBuf {
    simulate_with_noise(dir, setup, seed, "additive:0.01", extra)
}

/// A record of the 1-DOF friction setup at rest in `dir` (3,000 samples, 50 N RMS random
/// force, `substeps` data sub-steps, `noise`), as the 1-DOF tests simulate it.
fn one_dof_record(dir: &Path, seed: &str, substeps: &str, noise: &str) -> std::path::PathBuf {
    let setup = repo("recordings/one-dof-friction.toml");
    let extra = [
        "--steps",
        "3000",
        "--amplitude",
        "50",
        "--substeps",
        substeps,
    ];
    simulate_with_noise(dir, &setup, seed, noise, &extra)
}

/// `jointid simulate SETUP` (random input, the given noise, seed and extra options) into
/// `dir`.
fn simulate_with_noise(
    dir: &Path,
    setup: &Path,
    seed: &str,
    noise: &str,
    extra: &[&str],
) -> std::path::PathBuf {
    let rec = dir.join(format!("seed-{seed}.mcap"));
    let mut args = vec![
        "simulate",
        setup.to_str().unwrap(),
        "--out",
        rec.to_str().unwrap(),
        "--scenario",
        "random",
        "--noise",
        noise,
        "--seed",
        seed,
    ];
    args.extend_from_slice(extra);
    ok(&args);
    rec
}

/// A setup file in `dir` from a shipped one with the law replaced, the estimator `kind` and
/// windows of `window` samples every `every` (`[estimator] window_samples`, `window_every`).
fn windowed_setup(
    dir: &Path,
    file: &str,
    basis: &[&str],
    truth: &[f64],
    kind: &str,
    window: usize,
    every: usize,
) -> std::path::PathBuf {
    let text = setup_variant_text(file, basis, truth, 1)
        .replace("kind = \"kalman\"", &format!("kind = \"{kind}\""))
        .replace(
            "[estimator]",
            &format!("[estimator]\nwindow_samples = {window}\nwindow_every = {every}"),
        );
    let p = dir.join(format!("windowed-{kind}.toml"));
    std::fs::write(&p, text).unwrap();
    p
}

/// The shipped friction setup's law (`sign(u), u, const(100), v`, truth 3000, 3e5, 0, 0) in
/// windows of `window` samples every `every`, default pipeline.
fn friction_windows(dir: &Path, window: usize, every: usize) -> std::path::PathBuf {
    windowed_setup(
        dir,
        "two-beam-friction.toml",
        &["sign(u)", "u", "const(100)", "v"],
        &[3000.0, 3.0e5, 0.0, 0.0],
        "kalman",
        window,
        every,
    )
}

/// Every window identified, and parameter `k` of each within `k_se` of its standard errors
/// of `truth`, for every `(k, truth)`.
fn windows_hold(windows: &[serde_json::Value], truths: &[(usize, f64)], k_se: f64) {
    for w in windows {
        assert!(w["failure"].is_null(), "{w}");
        for &(k, truth) in truths {
            let (value, se) = (
                w["parameters"][k][0].as_f64().unwrap(),
                w["parameters"][k][1].as_f64().unwrap(),
            );
            assert!(
                (value - truth).abs() < k_se * se,
                "parameter {k}, window {w}"
            );
        }
    }
}

fn simulate_to(dir: &Path, setup: &Path, steps: &str, seed: &str) -> std::path::PathBuf {
    simulate_with(dir, setup, seed, &["--steps", steps, "--substeps", "8"])
}

/// A record identified in windows (maximum likelihood, a spring law): three windows of
/// 2,000 samples every 3,000, each within 3 of its errors of the truth, combined by
/// inverse variance into the reported parameters — nearer the truth than 3 combined errors
/// and with an error below every window's.
#[test]
fn a_record_identified_in_windows_combines_them() {
    let dir = tempfile::tempdir().unwrap();
    let setup = windowed_setup(
        dir.path(),
        "two-beam-spring.toml",
        &["u", "v"],
        &[3.0e5, 0.0],
        "ml",
        2000,
        3000,
    );
    let rec = simulate_to(dir.path(), &setup, "8000", "4");
    let v = replay_json(&[rec.to_str().unwrap()]);
    assert_eq!(v["samples"].as_u64(), Some(8000));
    let windows = v["session"]["windows"].as_array().unwrap();
    let starts: Vec<u64> = windows
        .iter()
        .map(|w| w["first_sample"].as_u64().unwrap())
        .collect();
    assert_eq!(starts, vec![0, 3000, 6000]);
    let mut smallest = f64::INFINITY;
    for w in windows {
        assert!(w["failure"].is_null(), "{w}");
        let (value, se) = (
            w["parameters"][0][0].as_f64().unwrap(),
            w["parameters"][0][1].as_f64().unwrap(),
        );
        assert!((value - 3.0e5).abs() < 3.0 * se, "window {w}");
        smallest = smallest.min(se);
    }
    let u = &v["parameters"][0];
    let (value, se) = (
        u["value"].as_f64().unwrap(),
        u["std_error"].as_f64().unwrap(),
    );
    let combined = &v["session"]["combined"];
    assert_eq!(combined["values"][0].as_f64(), Some(value));
    assert!((value - 3.0e5).abs() < 3.0 * se, "{value} ± {se}");
    assert!(
        se > 0.0 && se < smallest,
        "combined {se}, windows down to {smallest}"
    );
}

/// Windows in motion on a structure with its own damping: the paper's model with light
/// Rayleigh damping (`alpha = 20`, `beta = 1e-6`), 9,000 samples in three windows of 3,000
/// (8-sub-step data, 1 % noise, seed 10): every parameter of every window within 2.5 of its
/// errors. Without the damping see the next test.
#[test]
fn windows_in_motion_on_a_damped_structure_hold_the_truth() {
    let dir = tempfile::tempdir().unwrap();
    let setup = friction_windows(dir.path(), 3000, 3000);
    let text = std::fs::read_to_string(&setup).unwrap();
    assert!(text.contains("hinges = [6]"));
    let damped = text.replacen(
        "hinges = [6]",
        "hinges = [6]\nrayleigh = { alpha = 20.0, beta = 1.0e-6 }",
        1,
    );
    std::fs::write(&setup, damped).unwrap();
    let rec = simulate_to(dir.path(), &setup, "9000", "10");
    let v = replay_json(&[rec.to_str().unwrap()]);
    let windows = v["session"]["windows"].as_array().unwrap();
    assert_eq!(windows.len(), 3);
    windows_hold(windows, &[(0, 3000.0), (1, 3.0e5), (2, 0.0), (3, 0.0)], 2.5);
}

/// The same windows on the shipped, undamped model: nothing but the joint dissipates, so an
/// error left in a window's start state rings through it. The window at 3,000 was 3.4
/// errors off in friction and 3.1 in the spring while the start-state fit dropped
/// well-determined velocity directions (its cut was relative to the raw, unit-mixed
/// spectrum); fitted in scaled units (`estimate::kalman::pseudo_solve`) every parameter of
/// every window is within 2.5 errors, the damper `v` included.
#[test]
fn windows_in_motion_on_the_undamped_model_hold_the_truth() {
    let dir = tempfile::tempdir().unwrap();
    let setup = friction_windows(dir.path(), 3000, 3000);
    let rec = simulate_to(dir.path(), &setup, "9000", "10");
    let v = replay_json(&[rec.to_str().unwrap()]);
    let windows = v["session"]["windows"].as_array().unwrap();
    assert_eq!(windows.len(), 3);
    windows_hold(windows, &[(0, 3000.0), (1, 3.0e5), (2, 0.0), (3, 0.0)], 2.5);
}

/// A window that starts in motion (every window but the first): the default pipeline
/// estimates its initial state and identifies it (friction and spring within 3 standard
/// errors, the note says so); the 1989 estimator, which starts at rest, refuses it with the
/// sensor and the figure, and the combination says it left it out.
#[test]
fn a_window_that_starts_in_motion_is_identified_or_refused() {
    let dir = tempfile::tempdir().unwrap();
    let setup = friction_windows(dir.path(), 2000, 2000);
    let rec = simulate_to(dir.path(), &setup, "4000", "1");
    let v = replay_json(&[rec.to_str().unwrap()]);
    let windows = v["session"]["windows"].as_array().unwrap();
    assert_eq!(windows.len(), 2);
    windows_hold(windows, &[(0, 3000.0), (1, 3.0e5)], 3.0);
    let notes: Vec<&str> = v["notes"]
        .as_array()
        .unwrap()
        .iter()
        .map(|n| n.as_str().unwrap())
        .collect();
    assert!(
        notes
            .iter()
            .any(|n| n.contains("starts in motion") && n.contains("initial state was estimated")),
        "{notes:?}"
    );
    let paper = replay_json(&[rec.to_str().unwrap(), "--estimator", "paper"]);
    let windows = paper["session"]["windows"].as_array().unwrap();
    let why = windows[1]["failure"].as_str().unwrap();
    assert!(
        why.contains("does not start at rest") && why.contains("noise std"),
        "{why}"
    );
    assert_eq!(paper["session"]["combined"]["windows"][0].as_u64(), Some(1));
    assert!(
        paper["notes"]
            .as_array()
            .unwrap()
            .iter()
            .any(|n| n.as_str().unwrap().contains("1 of 2 windows combined")),
        "{}",
        paper["notes"]
    );
}

/// The issue's acceptance "the shipped recordings replay with the default settings to
/// within 2 standard errors of their truth", on all six (random, sine and free decay, the
/// friction and the spring setup). The free-decay ones were made again twice: a 5-sample
/// impact (friction 4.6 errors off) and a 20-sample one (2.7 errors off; every one of 16
/// seeds called "in motion") were not resolved by the samples — the model's linear
/// interpolation misses π²/(12n²) of a half-sine's impulse, visible at 1 % noise; with 50
/// samples no seed is (recordings/README.md, ACCURACY.md). The sine records are held to 3
/// errors only: their acceptance is not met (see the body).
#[test]
fn every_shipped_recording_replays_within_two_standard_errors() {
    for setup in ["friction", "spring"] {
        for kind in ["", "-sine", "-free"] {
            let name = format!("recordings/two-beam-{setup}{kind}.mcap");
            let rec = repo(&name);
            let v = replay_json(&[rec.to_str().unwrap()]);
            // The sine records too: before the bootstrap was automatic under repeating or
            // smooth excitation, the sandwich errors covered 58 % over 32 seeds of the
            // friction setup's sine test (ACCURACY.md, seventeenth session).
            assert_within(&v, &name, 2.0);
            // The bootstrap runs on the sine and impact records and on no random one.
            let bootstrapped = !v["output_error"]["prediction_error"]["bootstrap"].is_null();
            assert_eq!(bootstrapped, !kind.is_empty(), "{name}: bootstrap");
            // Every one starts at rest and none is called "in motion" (every free-decay
            // seed was, with a 20-sample impact; the sine records were, before the
            // excitation could be taken as smooth between samples).
            let notes = v["notes"].as_array().unwrap();
            assert!(
                !notes
                    .iter()
                    .any(|n| n.as_str().unwrap().contains("starts in motion")),
                "{name}: {notes:?}"
            );
            // The random records' force is piecewise linear between samples (the
            // simulator's), the sine's and the impact's smooth: the likelihood tells which.
            let smooth = notes.iter().any(|n| {
                n.as_str()
                    .unwrap()
                    .contains("taken as smooth between samples")
            });
            assert_eq!(smooth, !kind.is_empty(), "{name}: {notes:?}");
        }
    }
}

/// A sine test with a friction law: over 16 fresh seeds (8-sub-step data, 1 % noise) the
/// sandwich errors covered 58 % of the truths, `sign(u)` −2.0 errors off on average; the
/// parametric bootstrap, automatic when the excitation repeats itself or is smooth between
/// samples, 95 % over 32 seeds (ACCURACY.md, seventeenth session). On the shipped friction-sine record: by
/// default every parameter within 2 of the bootstrapped errors, all 10 replicates used, the
/// friction's error at least 1.5× the sandwich's alone (the replicates spread ~2× wider than
/// it says); `--bootstrap 0` gives the sandwich's errors back with a note saying what they
/// covered.
#[test]
fn a_sine_test_with_friction_is_bootstrapped_to_its_measured_errors() {
    let rec = repo("recordings/two-beam-friction-sine.mcap");
    let rec = rec.to_str().unwrap();
    let boot = replay_json(&[rec]);
    let plain = replay_json(&[rec, "--bootstrap", "0"]);
    assert_within(&boot, "friction-sine, bootstrapped", 2.0);
    let report = &boot["output_error"]["prediction_error"]["bootstrap"];
    assert_eq!(report["replicates"].as_u64(), Some(10), "{report}");
    assert_eq!(report["used"].as_u64(), Some(10), "{report}");
    assert!(plain["output_error"]["prediction_error"]["bootstrap"].is_null());
    let error = |v: &serde_json::Value| v["parameters"][0]["std_error"].as_f64().unwrap();
    assert_eq!(boot["parameters"][0]["basis"], "sign(u)");
    assert!(
        error(&boot) > 1.5 * error(&plain),
        "sign(u) error {} with the bootstrap, {} without",
        error(&boot),
        error(&plain)
    );
    assert!(says(
        &boot,
        "parametric bootstrap (automatic: the excitation repeats itself"
    ));
    // Under a repeating excitation the sandwich keeps the residuals' lag window (the noise
    // moves the switching the same way every cycle; `Wanted::ValuesAndLagWindowErrors`).
    assert!(says(&boot, "by a Newey–West lag window of"));
    assert_eq!(
        boot["output_error"]["prediction_error"]["noise_driven_errors"].as_bool(),
        Some(false)
    );
    assert!(says(&boot, ": 10 of 10 records"));
    assert!(says(
        &plain,
        "parametric bootstrap switched off (`--bootstrap 0`)"
    ));
    assert!(!says(&boot, "switched off"));
}

/// The prediction error's stated errors against the spread of its own answers: spring setup,
/// 64-sub-step data, 1 % noise, seed 7701. A parametric bootstrap of 20 records simulated
/// from the answer (each refined again) spreads `sign(u)`, `u`, `const(100)`, `v` by 17.5,
/// 121, 0.163, 0.0034; the errors stated without it must match that spread per term (within
/// 0.7–1.5×). Until the fortieth session the sandwich's score covariance came from the
/// residuals' lag window and stated 31.7, 216, 0.117, 0.0124 — the damper 3.7× the spread;
/// now it is computed from the noise through the observer (18.6, 121, 0.148, 0.0038) and
/// the note says so.
#[test]
fn the_stated_errors_match_the_spread_of_the_bootstrap() {
    let dir = tempfile::tempdir().unwrap();
    let setup = repo("recordings/two-beam-spring.toml");
    let rec = simulate_with(
        dir.path(),
        &setup,
        "7701",
        &["--steps", "2000", "--substeps", "64"],
    );
    let rec = rec.to_str().unwrap();
    let plain = replay_json(&[rec]);
    assert!(
        plain["output_error"]["prediction_error"]["bootstrap"].is_null(),
        "no automatic bootstrap on this record: {}",
        plain["output_error"]["prediction_error"]["bootstrap"]
    );
    assert!(says(
        &plain,
        "its score covariance the measurement noise's through the observer"
    ));
    let boot = replay_json(&[rec, "--bootstrap", "20"]);
    let spread = boot["output_error"]["prediction_error"]["bootstrap"]["spread"]
        .as_array()
        .unwrap()
        .clone();
    for (p, s) in plain["parameters"].as_array().unwrap().iter().zip(&spread) {
        let ratio = p["std_error"].as_f64().unwrap() / s.as_f64().unwrap();
        assert!(
            (0.7..1.5).contains(&ratio),
            "{}: stated {} against a spread of {s} (ratio {ratio:.2})",
            p["basis"],
            p["std_error"]
        );
    }
}

/// A random test whose excitation is weak against the friction (3,000 N RMS on the shipped
/// friction setup instead of 20,000; 8-sub-step data, 1 % noise): the joint sticks often,
/// the innovations are far from linear in the parameters over their errors (the two
/// secants' sandwiches differ up to 14×) and the sandwich errors are too small, so the
/// parametric bootstrap runs by itself (asserted: ten replicates and a note that says it
/// was automatic, whichever of its triggers fired); `--bootstrap 0` gives the sandwich's
/// answer back with a note that says so (ACCURACY.md, twentieth session).
///
/// Asserted over ten seeds (801–810), not one: a `sign(u)` law amplifies the last digits,
/// so single answers move with the arithmetic's round-off (until the forty-ninth session
/// this test held seed 804 within 2 errors; the round-off change of that session put it 4.3
/// off and another seed from 5.7 to 1.0, the twenty seeds 801–820 going from 88 % to 94 %
/// coverage; ACCURACY.md). Measured on 801–810: the bootstrap covers 90 % of the 40
/// parameters, worst 4.3 errors; the sandwich alone 50 %, worst 13.1. Asserted: every
/// record bootstraps by itself, the bootstrap covers at least 80 % and no answer is more than
/// 6 errors off; the sandwich alone covers less than 70 %; and on seed 804, as before, the
/// secants disagree (> 1.2) and the sandwich alone puts `sign(u)` more than 3 errors off.
#[test]
fn a_weak_excitation_against_the_friction_is_bootstrapped() {
    let dir = tempfile::tempdir().unwrap();
    let setup = repo("recordings/two-beam-friction.toml");
    let (mut boot, mut plain) = (Vec::new(), Vec::new());
    for seed in 801..=810 {
        let seed = seed.to_string();
        let rec = simulate_with(
            dir.path(),
            &setup,
            &seed,
            &["--amplitude", "3000", "--substeps", "8"],
        );
        let rec = rec.to_str().unwrap();
        let b = replay_json(&[rec]);
        let used = &b["output_error"]["prediction_error"]["bootstrap"];
        assert_eq!(used["used"].as_u64(), Some(10), "seed {seed}: {used}");
        assert!(says(&b, "(automatic: "), "seed {seed}: {}", b["notes"]);
        let p = replay_json(&[rec, "--bootstrap", "0"]);
        assert!(
            says(&p, "parametric bootstrap switched off (`--bootstrap 0`)"),
            "seed {seed}: {}",
            p["notes"]
        );
        if seed == "804" {
            // The seed this test held alone until the forty-ninth session: the two
            // secants disagree and the sandwich's friction is confidently wrong (measured
            // 6.0 and 8.4 errors off), as asserted then.
            let pe = &b["output_error"]["prediction_error"];
            let disagreement = pe["secant_disagreement"].as_f64().unwrap();
            assert!(disagreement > 1.2, "seed 804: {disagreement}");
            let q = &p["parameters"][0];
            assert_eq!(q["basis"], "sign(u)");
            let off = (q["value"].as_f64().unwrap() - q["truth"].as_f64().unwrap()).abs()
                / q["std_error"].as_f64().unwrap();
            assert!(off > 3.0, "seed 804: sign(u) {off} errors off without");
        }
        boot.push((seed.clone(), b));
        plain.push((seed, p));
    }
    assert_covered(&boot, 0.8, 6.0);
    let (covered, _) = coverage(&plain);
    assert!(
        covered < 0.7,
        "the sandwich alone covered {:.0} % (the reason the bootstrap runs)",
        100.0 * covered
    );
}

/// The share of the replays' parameters whose stated 95 % interval (±1.96 errors) holds the
/// truth, and the largest |value − truth| / error with its seed and basis. Every replay must
/// state parameters (an empty list would make any share pass).
fn coverage(replays: &[(String, serde_json::Value)]) -> (f64, (f64, String)) {
    let (mut inside, mut total, mut worst) = (0, 0, (0.0, String::new()));
    assert!(!replays.is_empty(), "no replays");
    for (seed, v) in replays {
        let params = v["parameters"].as_array().unwrap();
        assert!(!params.is_empty(), "seed {seed}: no parameters");
        for p in params {
            let (value, truth, se) = (
                p["value"].as_f64().unwrap(),
                p["truth"].as_f64().unwrap(),
                p["std_error"].as_f64().unwrap(),
            );
            let off = (value - truth).abs() / se;
            total += 1;
            inside += usize::from(off < 1.96);
            if off.is_nan() || off > worst.0 {
                worst = (off, format!("seed {seed} {}", p["basis"]));
            }
        }
    }
    (inside as f64 / total.max(1) as f64, worst)
}

/// At least `share` of the replays' parameters covered by their 95 % intervals, and none
/// more than `k` errors off.
fn assert_covered(replays: &[(String, serde_json::Value)], share: f64, k: f64) {
    let (covered, (worst, which)) = coverage(replays);
    assert!(
        covered >= share && worst < k,
        "covered {:.0} % (at least {:.0} %), worst {worst:.2} errors at {which} (below {k})",
        100.0 * covered,
        100.0 * share
    );
}

/// Passes that do not converge can walk away from the answer: a friction one pass finds puts
/// samples in the stick band, the next pass's fit leaves them out and finds more. The shipped
/// spring setup (friction truth 0) on data of its own discretisation at 100 % noise, seed
/// 4015: `sign(u)` −174 ± 1,056 N after the first pass, ~24 kN after the tenth, `u` −20 %.
/// The prediction error's descent is local; from the last pass it stopped at `sign(u)`
/// 18 kN ± 2.2 kN and `u` 8 errors off. It now starts from the first pass's answer when that
/// is the likelier start (by 121 in log-likelihood here), and says so.
#[test]
fn passes_that_run_away_do_not_take_the_refinement_with_them() {
    let dir = tempfile::tempdir().unwrap();
    let setup = repo("recordings/two-beam-spring.toml");
    let rec = simulate_with_noise(
        dir.path(),
        &setup,
        "4015",
        "additive:1.0",
        &["--steps", "2000", "--substeps", "1"],
    );
    let v = replay_json(&[rec.to_str().unwrap(), "--bootstrap", "0"]);
    assert!(
        v["stop_reason"]
            .as_str()
            .unwrap()
            .starts_with("not converged"),
        "{}",
        v["stop_reason"]
    );
    let first = &v["pass_reports"][0]["parameters"][0]["value"];
    let start = &v["output_error"]["start_values"][0];
    assert_eq!(first, start, "the refinement starts from the first pass");
    assert!(says(
        &v,
        "the prediction error started from the first pass's answer"
    ));
    assert_within(&v, "4015", 2.0);
}

/// The 1989 estimator alone on noisy, finely integrated data (the shipped spring
/// recording) diverges in its error recursion and answers far from the truth (`v`
/// −5.5e5 ± 6.0e4 N s/m against 0): the answer's free run is checked against the noise, a
/// note gives the misfit, and `--strict` refuses it with a non-zero exit.
#[test]
fn an_unrefined_answer_that_misfits_the_record_is_flagged_and_refused_under_strict() {
    let rec = repo("recordings/two-beam-spring.mcap");
    let rec = rec.to_str().unwrap();
    let v = replay_json(&[rec, "--estimator", "paper"]);
    let notes = v["notes"].as_array().expect("notes");
    let misfit = notes
        .iter()
        .filter_map(|n| n.as_str())
        .find(|n| n.starts_with("the model explains the outputs only to"))
        .expect("a misfit note");
    assert!(misfit.contains("answer's free run"), "{misfit}");
    let out = run(&["replay", rec, "--estimator", "paper", "--strict"]);
    assert!(!out.status.success(), "--strict accepted the misfit");
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(err.contains("refused under --strict"), "{err}");
    // The default pipeline's answer on the same record is not refused.
    let out = run(&["replay", rec, "--strict"]);
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
}

/// `jointid live --estimator ml` was run as the Kalman filter without a word; maximum
/// likelihood has no online step, so it is refused, saying why, before any stream is opened
/// (a live run that started instead would wait for frames: it is killed after 30 s and the
/// test fails).
#[test]
fn live_refuses_an_estimator_without_an_online_step() {
    use std::process::{Command, Stdio};
    let setup = repo("recordings/two-beam-spring.toml");
    let mut child = Command::new(common::BIN)
        .args([
            "live",
            "--setup",
            setup.to_str().unwrap(),
            "--estimator",
            "ml",
            "--prefix",
            "jointid_test_live_ml_refused",
            "--seconds",
            "1",
        ])
        .stdout(Stdio::null())
        .stderr(Stdio::piped())
        .spawn()
        .expect("run jointid live");
    let deadline = std::time::Instant::now() + std::time::Duration::from_secs(30);
    while child.try_wait().expect("wait").is_none() {
        if std::time::Instant::now() > deadline {
            let _ = child.kill();
            panic!("`live --estimator ml` started a session instead of refusing");
        }
        std::thread::sleep(std::time::Duration::from_millis(50));
    }
    let out = child.wait_with_output().expect("output");
    assert_eq!(out.status.code(), Some(1));
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(
        err.contains("--estimator ml") && err.contains("no online step"),
        "{err}"
    );
}

/// Outputs are checked before the identification runs (a reviewer's finds): `--out` naming
/// the recording itself is refused and the recording left as it was (the writer renames its
/// finished file over `--out`), and `--plots` naming an existing file is refused up front
/// (it failed after the whole identification, without printing the results); both name the
/// option and the path, exit 1, and write nothing.
#[test]
fn outputs_over_an_input_or_a_file_are_refused_before_the_work() {
    let dir = tempfile::tempdir().unwrap();
    let rec = dir.path().join("rec.mcap");
    std::fs::copy(repo("recordings/two-beam-spring.mcap"), &rec).unwrap();
    let before = std::fs::read(&rec).unwrap();
    let o = run(&[
        "replay",
        rec.to_str().unwrap(),
        "--out",
        rec.to_str().unwrap(),
    ]);
    let err = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(1), "{err}");
    assert!(
        err.contains("--out") && err.contains("is the input"),
        "{err}"
    );
    assert!(o.stdout.is_empty(), "no identification ran");
    assert_eq!(
        std::fs::read(&rec).unwrap(),
        before,
        "the recording is untouched"
    );

    let file = dir.path().join("afile");
    std::fs::write(&file, "x").unwrap();
    let out = dir.path().join("res.mcap");
    let o = run(&[
        "replay",
        rec.to_str().unwrap(),
        "--plots",
        file.to_str().unwrap(),
        "--out",
        out.to_str().unwrap(),
    ]);
    let err = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(1), "{err}");
    assert!(
        err.contains("--plots") && err.contains("not a directory"),
        "{err}"
    );
    assert!(!out.exists(), "nothing written before the refusal");
}

/// A Coulomb record (`sign(v), u` on the friction setup, 8-sub-step data, 100 % noise, seed
/// 7319) cut at sample 500 of a running test, imported from CSV and replayed. Its first
/// sample reads like rest at this noise, and until the thirty-fourth session `replay`
/// identified it from rest: `sign(v)` 22,063 ± 263 N (truth 3,000: 72 errors off), the
/// whiteness note the only sign. Its residuals' whiteness now asks the start-in-motion test
/// (ACCURACY.md, thirty-fourth session). Asserted: by default the record is found in motion
/// and identified again with its start state estimated, and with `--in-motion` it is
/// identified so from the start; both parameters within 3 errors either way (measured −1.6
/// and +0.1); the 1989 estimator, which starts at rest, refuses the option with the reason.
#[test]
fn a_cut_record_said_to_start_in_motion_is_identified_from_its_start_state() {
    use jointid::setup::Setup;
    use jointid::simulate::{Noise, Scenario, SimulateOptions, simulate};
    use std::fmt::Write as _;
    let dir = tempfile::tempdir().unwrap();
    let text = setup_variant_text(
        "two-beam-friction.toml",
        &["sign(v)", "u"],
        &[3000.0, 3.0e5],
        1,
    );
    let setup_path = dir.path().join("coulomb.toml");
    std::fs::write(&setup_path, &text).unwrap();
    let setup = Setup::from_toml(&text, "coulomb").unwrap();
    let sim = simulate(
        &setup,
        &SimulateOptions {
            scenario: Scenario::Random { rms: 2e4 },
            steps: 2500,
            dt_s: setup.dt_s,
            substeps: 8,
            noise: Noise::Additive(1.0),
            seed: 7319,
        },
    )
    .unwrap();
    let mut csv = String::from("t");
    for name in setup
        .excitation
        .iter()
        .map(|e| &e.name)
        .chain(setup.sensors.iter().map(|s| &s.name))
    {
        write!(csv, ",{name}").unwrap();
    }
    csv.push('\n');
    for i in 500..2500 {
        write!(csv, "{:e}", (i - 500) as f64 * setup.dt_s).unwrap();
        for v in sim.excitation[i].iter().chain(&sim.response[i]) {
            write!(csv, ",{v:e}").unwrap();
        }
        csv.push('\n');
    }
    let csv_path = dir.path().join("cut.csv");
    std::fs::write(&csv_path, csv).unwrap();
    let rec = dir.path().join("cut.mcap");
    ok(&[
        "import",
        csv_path.to_str().unwrap(),
        "--setup",
        setup_path.to_str().unwrap(),
        "--out",
        rec.to_str().unwrap(),
    ]);
    let rec = rec.to_str().unwrap();
    let within = |v: &serde_json::Value, what: &str| {
        for (p, truth) in v["parameters"]
            .as_array()
            .expect("parameters")
            .iter()
            .zip([3000.0, 3.0e5])
        {
            let (value, se) = (
                p["value"].as_f64().unwrap(),
                p["std_error"].as_f64().unwrap(),
            );
            let z = (value - truth) / se;
            assert!(
                z.abs() < 3.0,
                "{what}, {}: {value} ± {se}, {z:.2} errors off",
                p["basis"]
            );
        }
    };
    let says = |v: &serde_json::Value, text: &str| -> bool {
        v["notes"]
            .as_array()
            .expect("notes")
            .iter()
            .filter_map(|n| n.as_str())
            .any(|n| n.contains(text))
    };
    let by_default = replay_json(&[rec]);
    assert!(
        says(
            &by_default,
            "the record starts in motion although its first sample reads like rest"
        ),
        "{}",
        by_default["notes"]
    );
    within(&by_default, "found in motion");
    let in_motion = replay_json(&[rec, "--in-motion"]);
    assert!(
        says(
            &in_motion,
            "the record is said to start in motion (`--in-motion`"
        ),
        "{}",
        in_motion["notes"]
    );
    within(&in_motion, "--in-motion");
    let paper = run(&["replay", rec, "--in-motion", "--estimator", "paper"]);
    assert!(!paper.status.success());
    let err = String::from_utf8_lossy(&paper.stderr);
    assert!(
        err.contains("said to start in motion") && err.contains("starts the model at rest"),
        "{err}"
    );
}

/// A `sign(u)` law kept at one model sub-step is bootstrapped automatically (forty-fourth
/// session: on fresh seeds the friction setup's own-discretisation row at 1 % noise covered
/// 86–88 % with the sandwich's errors). Seed 8150 of that row, whose `sign(u)` came out 6.2
/// sandwich errors off: the default replay now runs ten replicates, says why, and every
/// parameter is within 4 errors; the same seed's 8-sub-step data keep more model sub-steps,
/// where the sandwich holds: no bootstrap, within 4 errors.
#[test]
fn a_friction_law_at_one_model_substep_is_bootstrapped() {
    const OCCASION: &str = "at one model sub-step per sample";
    let dir = tempfile::tempdir().unwrap();
    let setup = repo("recordings/two-beam-friction.toml");
    let own = simulate_with(dir.path(), &setup, "8150", &[]);
    let v = replay_json(&[own.to_str().unwrap()]);
    assert!(
        says(&v, "parametric bootstrap (automatic"),
        "{}",
        v["notes"]
    );
    assert!(says(&v, OCCASION), "{}", v["notes"]);
    assert_eq!(v["output_error"]["prediction_error"]["substeps"], 1);
    assert_within(&v, "8150 (1 sub-step)", 4.0);
    let fine_dir = tempfile::tempdir().unwrap();
    let fine = simulate_with(fine_dir.path(), &setup, "8150", &["--substeps", "8"]);
    let v = replay_json(&[fine.to_str().unwrap()]);
    assert!(!says(&v, "parametric bootstrap"), "{}", v["notes"]);
    assert!(!says(&v, OCCASION), "{}", v["notes"]);
    assert_within(&v, "8150 (8 sub-steps)", 4.0);
}
