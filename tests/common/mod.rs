//! Helpers shared by the end-to-end tests: run the real `jointid` binary and read its JSON.
#![allow(dead_code)]

pub mod live;

use std::path::{Path, PathBuf};
use std::process::{Command, Output};

pub const BIN: &str = env!("CARGO_BIN_EXE_jointid");

/// A path inside the repository.
pub fn repo(p: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join(p)
}

pub fn run(args: &[&str]) -> Output {
    Command::new(BIN).args(args).output().expect("run jointid")
}

/// Run `jointid` and return its standard output; fail the test with both streams if it
/// exits non-zero.
pub fn ok(args: &[&str]) -> String {
    let out = run(args);
    assert!(
        out.status.success(),
        "jointid {args:?} failed:\n{}\n{}",
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr)
    );
    String::from_utf8_lossy(&out.stdout).into_owned()
}

/// `jointid replay ARGS --json`, parsed.
pub fn replay_json(args: &[&str]) -> serde_json::Value {
    let mut a = vec!["replay"];
    a.extend_from_slice(args);
    a.push("--json");
    serde_json::from_str(&ok(&a)).expect("replay --json prints JSON")
}

/// A shipped setup (`recordings/FILE`) with the connection law (`basis`, `truth`, zero
/// `initial`) and the model's sub-steps per sample replaced: the accuracy tests vary these
/// over one problem.
pub fn setup_variant(
    file: &str,
    basis: &[&str],
    truth: &[f64],
    model_substeps: usize,
) -> jointid::setup::Setup {
    let path = repo(&format!("recordings/{file}"));
    let text = setup_variant_text(file, basis, truth, model_substeps);
    jointid::setup::Setup::from_toml(&text, &path.display().to_string()).expect("valid variant")
}

/// The TOML text of [`setup_variant`], for tests that hand a setup file to the binary.
pub fn setup_variant_text(
    file: &str,
    basis: &[&str],
    truth: &[f64],
    model_substeps: usize,
) -> String {
    let path = repo(&format!("recordings/{file}"));
    let text = std::fs::read_to_string(&path).expect("shipped setup");
    let list = |v: Vec<String>| v.join(", ");
    let text: String = text
        .lines()
        .map(|l| {
            let t = l.trim_start();
            if t.starts_with("basis") {
                format!(
                    "basis = [{}]",
                    list(basis.iter().map(|b| format!("\"{b}\"")).collect())
                )
            } else if t.starts_with("truth") {
                format!(
                    "truth = [{}]",
                    list(truth.iter().map(|x| format!("{x:?}")).collect())
                )
            } else if t.starts_with("initial") {
                format!("initial = [{}]", list(vec!["0.0".into(); basis.len()]))
            } else if t.starts_with("substeps") {
                format!("substeps = {model_substeps}")
            } else {
                l.to_string()
            }
        })
        .collect::<Vec<_>>()
        .join("\n");
    text
}
