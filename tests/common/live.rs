//! Helpers for the live tests: real `jointid live` and `acquire-sim` processes on a per-test
//! iceoryx2 prefix, with deadlines so a hung session fails the test instead of CI.
#![allow(dead_code)]

use std::path::{Path, PathBuf};
use std::process::{Child, Command, Output, Stdio};
use std::time::{Duration, Instant};

use serde_json::Value;

pub const JOINTID: &str = env!("CARGO_BIN_EXE_jointid");
pub const ACQUIRE: &str = env!("CARGO_BIN_EXE_acquire-sim");

/// The shipped friction setup every live test runs.
pub fn setup_path() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("recordings/two-beam-friction.toml")
}

/// A service prefix unique to this test process and test.
pub fn prefix(name: &str) -> String {
    format!("jt{}{name}_", std::process::id())
}

/// A shipped setup by file name (`recordings/NAME`).
pub fn shipped_setup(name: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("recordings")
        .join(name)
}

/// `jointid live --setup <friction> --prefix P --json EXTRA…`, output captured.
pub fn spawn_live(prefix: &str, extra: &[&str]) -> Child {
    spawn_live_with(&setup_path(), prefix, extra)
}

/// `jointid live --setup SETUP --prefix P --json EXTRA…`, output captured.
pub fn spawn_live_with(setup: &Path, prefix: &str, extra: &[&str]) -> Child {
    Command::new(JOINTID)
        .arg("live")
        .arg("--setup")
        .arg(setup)
        .args(["--prefix", prefix, "--json"])
        .args(extra)
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .expect("jointid live starts")
}

/// `acquire-sim --setup <friction> --prefix P --rate 10000 EXTRA…`, output captured.
pub fn acquire(prefix: &str, extra: &[&str]) -> Command {
    acquire_with(&setup_path(), prefix, extra)
}

/// `acquire-sim --setup SETUP --prefix P --rate 10000 EXTRA…`, output captured.
pub fn acquire_with(setup: &Path, prefix: &str, extra: &[&str]) -> Command {
    acquire_at(setup, prefix, "10000", extra)
}

/// `acquire-sim --setup SETUP --prefix P --rate RATE EXTRA…` (Hz), output captured.
pub fn acquire_at(setup: &Path, prefix: &str, rate_hz: &str, extra: &[&str]) -> Command {
    let mut c = Command::new(ACQUIRE);
    c.arg("--setup")
        .arg(setup)
        .args(["--prefix", prefix, "--rate", rate_hz])
        .args(extra)
        .stdout(Stdio::piped())
        .stderr(Stdio::piped());
    c
}

/// Waits for a child with a deadline (a hung session fails the test instead of CI).
pub fn finish(mut child: Child, limit: Duration) -> Output {
    let t0 = Instant::now();
    loop {
        if child.try_wait().unwrap().is_some() {
            return child.wait_with_output().unwrap();
        }
        if t0.elapsed() > limit {
            let _ = child.kill();
            let out = child.wait_with_output().unwrap();
            panic!(
                "process did not finish within {limit:?}; stderr:\n{}",
                String::from_utf8_lossy(&out.stderr)
            );
        }
        std::thread::sleep(Duration::from_millis(20));
    }
}

/// The `live --json` report of a finished, successful session.
pub fn report(out: &Output) -> Value {
    assert!(
        out.status.success(),
        "live failed: {}\n{}",
        String::from_utf8_lossy(&out.stderr),
        String::from_utf8_lossy(&out.stdout)
    );
    serde_json::from_slice(&out.stdout).expect("live --json prints one JSON object")
}

/// No input fault of any kind was counted.
pub fn assert_no_input_faults(r: &Value) {
    for k in [
        "missing_samples",
        "late_or_duplicate",
        "unpaired",
        "non_finite",
        "transport_drops",
    ] {
        assert_eq!(r["faults"][k], 0, "{k}: {}", r["faults"]);
    }
}
