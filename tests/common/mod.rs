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
