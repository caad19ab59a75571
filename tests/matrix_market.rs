//! The shipped Matrix Market example (`recordings/two-beam-mm/`, made by
//! `jointid export-mm recordings/two-beam-friction.toml --out recordings/two-beam-mm`)
//! identifies the same parameters as the native two-beam setup on the shipped recording,
//! with both estimators, and a fresh export reproduces the shipped files.

use std::path::{Path, PathBuf};

use jointid::app::{self, ReplayRequest};
use jointid::setup::{EstimatorKind, Setup};

fn root() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
}

fn params(setup: &Path, estimator: EstimatorKind, passes: usize) -> Vec<f64> {
    let req = ReplayRequest {
        recording: root().join("recordings/two-beam-friction.mcap"),
        setup: Some(setup.to_path_buf()),
        passes: Some(passes),
        estimator: Some(estimator),
        out: None,
        ..Default::default()
    };
    let out = app::replay(&req, &mut |_| {}).expect("replay");
    out.identification
        .final_parameters()
        .expect("parameters")
        .iter()
        .map(|p| p.value)
        .collect()
}

fn assert_close(a: &[f64], b: &[f64], what: &str) {
    assert_eq!(a.len(), b.len());
    for (x, y) in a.iter().zip(b) {
        assert!(x.is_finite() && y.is_finite(), "{what}: {a:?} vs {b:?}");
        assert!(
            (x - y).abs() <= 1e-9 * x.abs().max(y.abs()),
            "{what}: {a:?} vs {b:?}"
        );
    }
}

#[test]
fn matrix_market_setup_identifies_the_same_parameters_as_the_native_one() {
    let native = root().join("recordings/two-beam-friction.toml");
    let mm = root().join("recordings/two-beam-mm/setup.toml");
    for (est, passes) in [(EstimatorKind::Paper, 3), (EstimatorKind::Kalman, 2)] {
        let a = params(&native, est, passes);
        let b = params(&mm, est, passes);
        assert_close(&a, &b, &format!("{est}"));
    }
    // And the Kalman result is the physics, not two equal wrong numbers: the stiffness is
    // within 5 % of the truth (3e5 N/m) after two passes (the friction needs more passes).
    let k = params(&mm, EstimatorKind::Kalman, 2);
    assert!((k[1] / 3.0e5 - 1.0).abs() < 0.05, "{k:?}");
}

#[test]
fn export_reproduces_the_shipped_files_and_the_model_bit_for_bit() {
    let dir = tempfile::tempdir().unwrap();
    let native = Setup::from_file(&root().join("recordings/two-beam-friction.toml")).unwrap();
    jointid::matrix_market::export(&native, dir.path()).unwrap();
    for f in ["mass.mtx", "stiffness.mtx", "dofs.csv"] {
        let fresh = std::fs::read_to_string(dir.path().join(f)).unwrap();
        let shipped =
            std::fs::read_to_string(root().join("recordings/two-beam-mm").join(f)).unwrap();
        // The header comment names the source path; compare from the size line on.
        let body = |t: &str| {
            t.lines()
                .filter(|l| !l.starts_with('%'))
                .collect::<Vec<_>>()
                .join("\n")
        };
        assert_eq!(body(&fresh), body(&shipped), "{f}");
    }
    let a = jointid::model::Model::assemble(&native).unwrap();
    let mm = Setup::from_file(&dir.path().join("setup.toml")).unwrap();
    let b = jointid::model::Model::assemble(&mm).unwrap();
    assert_eq!(a.M, b.M);
    assert_eq!(a.K, b.K);
    assert_eq!(a.C, b.C);
    assert_eq!(a.Lp, b.Lp);
    assert_eq!(a.Lc, b.Lc);
    assert_eq!(a.dofs, b.dofs);
}

#[test]
fn bad_external_model_is_reported_with_file_and_entry() {
    let dir = tempfile::tempdir().unwrap();
    let src = root().join("recordings/two-beam-mm");
    for f in ["mass.mtx", "dofs.csv", "setup.toml"] {
        std::fs::copy(src.join(f), dir.path().join(f)).unwrap();
    }
    // Break the symmetry of K: store it as `general` with one mirrored entry changed.
    let k = std::fs::read_to_string(src.join("stiffness.mtx")).unwrap();
    let mut lines: Vec<String> = Vec::new();
    let mut n = 0;
    for l in k.lines() {
        if l.starts_with("%%") {
            lines.push("%%MatrixMarket matrix coordinate real general".into());
        } else if l.starts_with('%') {
            continue;
        } else if n == 0 {
            n += 1;
            lines.push("SIZE".into());
        } else {
            let t: Vec<&str> = l.split_whitespace().collect();
            lines.push(l.to_string());
            if t[0] != t[1] {
                let v: f64 = t[2].parse().unwrap();
                let v = if t[0] == "3" && t[1] == "2" {
                    v * 1.01
                } else {
                    v
                };
                lines.push(format!("{} {} {v:e}", t[1], t[0]));
            }
        }
    }
    let nnz = lines.len() - 2;
    let text = lines.join("\n").replace("SIZE", &format!("11 11 {nnz}"));
    std::fs::write(dir.path().join("stiffness.mtx"), text).unwrap();
    let e = Setup::from_file(&dir.path().join("setup.toml"))
        .unwrap_err()
        .to_string();
    assert!(
        e.contains("stiffness.mtx") && e.contains("(2, 3)") && e.contains("not symmetric"),
        "{e}"
    );
    // A sensor on a DOF the map does not have.
    let s = std::fs::read_to_string(src.join("setup.toml"))
        .unwrap()
        .replacen("node = 11", "node = 12", 1);
    std::fs::copy(src.join("stiffness.mtx"), dir.path().join("stiffness.mtx")).unwrap();
    std::fs::write(dir.path().join("setup.toml"), s).unwrap();
    let e = Setup::from_file(&dir.path().join("setup.toml"))
        .unwrap_err()
        .to_string();
    assert!(e.contains("node 12"), "{e}");
}

#[test]
fn external_model_with_3d_directions_array_format_and_a_massless_row() {
    // Node 1 ux and uz with mass, node 1 ry without: ry is condensed out statically,
    // K* = K_tt − K_tr K_rr⁻¹ K_rt.
    let dir = tempfile::tempdir().unwrap();
    let w = |name: &str, text: &str| std::fs::write(dir.path().join(name), text).unwrap();
    w(
        "dofs.csv",
        "# ours\nnode,direction,row\n1,ux,1\n1,ry,2\n1,uz,3\n",
    );
    w(
        "m.mtx",
        "%%MatrixMarket matrix array real symmetric\n3 3\n1.5\n0\n0\n0\n0\n2.5\n",
    );
    w(
        "k.mtx",
        "%%MatrixMarket matrix coordinate real symmetric\n3 3 5\n1 1 4e3\n2 1 1e3\n2 2 2e3\n3 2 -5e2\n3 3 3e3\n",
    );
    let base = TWO_DOF_SETUP.replace("DIR", "uz");
    w("setup.toml", &base);
    let s = Setup::from_file(&dir.path().join("setup.toml")).unwrap();
    let m = jointid::model::Model::assemble(&s).unwrap();
    assert_eq!(m.n(), 2);
    let k = [
        [4e3 - 1e3 * 1e3 / 2e3, 1e3 * 5e2 / 2e3],
        [1e3 * 5e2 / 2e3, 3e3 - 5e2 * 5e2 / 2e3],
    ];
    for (i, row) in k.iter().enumerate() {
        for (j, kij) in row.iter().enumerate() {
            assert!((m.K[(i, j)] - kij).abs() < 1e-9 * 4e3, "{}", m.K);
        }
    }
    assert_eq!(m.M[(1, 1)], 2.5);
    // A sensor on the massless rotation is refused by name.
    w(
        "setup.toml",
        &base.replace("dir = \"uz\" }\nquantity", "dir = \"ry\" }\nquantity"),
    );
    let s = Setup::from_file(&dir.path().join("setup.toml")).unwrap();
    let e = jointid::model::Model::assemble(&s).unwrap_err().to_string();
    assert!(e.contains("node 1 ry") && e.contains("no mass"), "{e}");
    // A direction the map does not have.
    w(
        "setup.toml",
        &base.replace("dir = \"uz\" }\nquantity", "dir = \"uy\" }\nquantity"),
    );
    let e = Setup::from_file(&dir.path().join("setup.toml"))
        .unwrap_err()
        .to_string();
    assert!(
        e.contains("node 1 uy") && e.contains("not in the DOF map"),
        "{e}"
    );
    // And 3-D directions are refused on a beam model.
    let native = std::fs::read_to_string(root().join("recordings/two-beam-friction.toml"))
        .unwrap()
        .replacen(
            "dof = { node = 1, dir = \"w\" }\nquantity",
            "dof = { node = 1, dir = \"ux\" }\nquantity",
            1,
        );
    let e = Setup::from_toml(&native, "t").unwrap_err().to_string();
    assert!(e.contains("only `w` and `rz`"), "{e}");
}

const TWO_DOF_SETUP: &str = r#"
[model.matrix_market]
mass = "m.mtx"
stiffness = "k.mtx"
dof_map = "dofs.csv"
[[excitation]]
name = "f"
dof = { node = 1, dir = "ux" }
[[sensors]]
name = "s"
dof = { node = 1, dir = "DIR" }
quantity = "displacement"
[[connections]]
name = "j"
dof = { node = 1, dir = "ux" }
basis = ["u"]
[integrator]
dt_s = 1e-4
"#;

/// A recording made from an external model carries the model's files: moved away from them
/// it replays with the matrices it was made with (the identified parameters near the
/// truth), and other files of the same names beside it do not change the answer (the
/// attached ones are used; `--setup` reads the files on disk instead).
#[test]
fn a_recording_of_an_external_model_carries_its_files_and_replays_anywhere() {
    use std::process::Command;
    let jointid = env!("CARGO_BIN_EXE_jointid");
    let made = tempfile::tempdir().unwrap();
    let moved = tempfile::tempdir().unwrap();
    let shipped = root().join("recordings/two-beam-mm");
    for f in ["setup.toml", "mass.mtx", "stiffness.mtx", "dofs.csv"] {
        std::fs::copy(shipped.join(f), made.path().join(f)).unwrap();
    }
    let rec = made.path().join("rec.mcap");
    let out = Command::new(jointid)
        .arg("simulate")
        .arg(made.path().join("setup.toml"))
        .arg("--out")
        .arg(&rec)
        .args([
            "--steps",
            "1500",
            "--noise",
            "additive:0.01",
            "--seed",
            "11",
        ])
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let away = moved.path().join("rec.mcap");
    std::fs::rename(&rec, &away).unwrap();
    let replay = |extra: &[&std::ffi::OsStr]| {
        let out = Command::new(jointid)
            .arg("replay")
            .arg(&away)
            .args(extra)
            .arg("--json")
            .output()
            .unwrap();
        assert!(
            out.status.success(),
            "{}",
            String::from_utf8_lossy(&out.stderr)
        );
        let v: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
        v["parameters"]
            .as_array()
            .unwrap()
            .iter()
            .map(|p| {
                (
                    p["value"].as_f64().unwrap(),
                    p["std_error"].as_f64().unwrap(),
                )
            })
            .collect::<Vec<_>>()
    };
    // Nothing beside it: the attached files are used.
    let alone = replay(&[]);
    // sign(u), u: within 4 standard errors of the truth (3e3 N, 3e5 N/m).
    for (i, truth) in [(0, 3.0e3), (1, 3.0e5)] {
        let (v, se) = alone[i];
        assert!(
            (v - truth).abs() <= 4.0 * se,
            "parameter {i}: {v} ± {se}, truth {truth}"
        );
    }
    // A stiffer model of the same names beside it: the answer is the same to the bit.
    let stiff: String = std::fs::read_to_string(shipped.join("stiffness.mtx"))
        .unwrap()
        .lines()
        .map(|l| {
            let f: Vec<&str> = l.split_whitespace().collect();
            match (l.starts_with('%'), f.as_slice()) {
                (false, [i, j, v]) if v.contains(['.', 'e']) => {
                    format!("{i} {j} {:e}\n", 1.3 * v.parse::<f64>().unwrap())
                }
                _ => format!("{l}\n"),
            }
        })
        .collect();
    for f in ["setup.toml", "mass.mtx", "dofs.csv"] {
        std::fs::copy(shipped.join(f), moved.path().join(f)).unwrap();
    }
    std::fs::write(moved.path().join("stiffness.mtx"), stiff).unwrap();
    assert_eq!(replay(&[]), alone, "the attached files must be used");
    // `--setup` reads the (stiffer) files on disk: another model, another answer.
    let setup = moved.path().join("setup.toml");
    let other = replay(&["--setup".as_ref(), setup.as_os_str()]);
    assert!(
        (other[1].0 - alone[1].0).abs() > 4.0 * alone[1].1,
        "{other:?} vs {alone:?}"
    );
    let out = Command::new(jointid)
        .arg("inspect")
        .arg(&away)
        .output()
        .unwrap();
    let text = String::from_utf8_lossy(&out.stdout);
    assert!(text.contains("model files  attached"), "{text}");
}
