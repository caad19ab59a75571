//! A malformed-input corpus, generated here from a good recording and good setups: truncated
//! and bit-flipped recordings, corrupt record lengths and chunk sizes, garbage files, setups
//! with every number replaced by NaN, infinity, a negative, zero or 1e308, and a model file
//! that is a device. The real binary reads each one (`inspect`, and `replay` on a share of
//! them) under a 768 MiB address-space limit and a 30 s deadline. Required of every case: no
//! panic, no hang, no large allocation (the limit turns one into an abort, which fails the
//! test), exit 0 or 1, and on exit 1 exactly one line on stderr naming the file.

mod common;

use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

use common::{BIN, ok, repo};

/// Address-space limit of each run (KiB).
const ADDRESS_SPACE_KIB: u64 = 768 * 1024;
const DEADLINE: Duration = Duration::from_secs(30);

struct Outcome {
    code: Option<i32>,
    stderr: String,
}

/// Runs the binary under the limits; fails the test on a timeout.
fn run_limited(args: &[&str]) -> Outcome {
    let mut child = Command::new("sh")
        .arg("-c")
        .arg(format!("ulimit -v {ADDRESS_SPACE_KIB}; exec \"$0\" \"$@\""))
        .arg(BIN)
        .args(args)
        .stdin(Stdio::null())
        .stdout(Stdio::null())
        .stderr(Stdio::piped())
        .spawn()
        .expect("spawn jointid");
    let start = Instant::now();
    let status = loop {
        if let Some(status) = child.try_wait().expect("wait") {
            break status;
        }
        if start.elapsed() > DEADLINE {
            let _ = child.kill();
            let _ = child.wait();
            panic!("jointid {args:?} ran over {DEADLINE:?}");
        }
        std::thread::sleep(Duration::from_millis(20));
    };
    let mut stderr = String::new();
    if let Some(mut e) = child.stderr.take() {
        use std::io::Read;
        let _ = e.read_to_string(&mut stderr);
    }
    Outcome {
        code: status.code(),
        stderr,
    }
}

/// The contract for one malformed input: exit 0 or 1, no panic, one line naming one of
/// `names` (the file at fault).
fn check(args: &[&str], names: &[&str]) -> Option<i32> {
    let o = run_limited(args);
    assert!(
        matches!(o.code, Some(0) | Some(1)),
        "jointid {args:?}: exit {:?} (a panic, an abort or a signal):\n{}",
        o.code,
        o.stderr
    );
    assert!(!o.stderr.contains("panicked"), "{args:?}: {}", o.stderr);
    if o.code == Some(1) {
        let lines: Vec<&str> = o.stderr.trim_end().lines().collect();
        assert_eq!(lines.len(), 1, "{args:?}: one line expected:\n{}", o.stderr);
        assert!(
            names.iter().any(|n| lines[0].contains(n)),
            "{args:?}: the error names none of {names:?}: {}",
            lines[0]
        );
    }
    o.code
}

/// A small deterministic generator (the corpus is the same on every run).
struct Lcg(u64);
impl Lcg {
    fn next(&mut self) -> u64 {
        self.0 = self
            .0
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        self.0 >> 17
    }
}

/// Offsets of the top-level records of an MCAP file's data section (after the magic).
fn record_offsets(bytes: &[u8]) -> Vec<(usize, u8)> {
    let mut out = Vec::new();
    let mut at = 8;
    while at + 9 <= bytes.len() {
        let op = bytes[at];
        let len = u64::from_le_bytes(bytes[at + 1..at + 9].try_into().unwrap()) as usize;
        out.push((at, op));
        if op == 0x02 {
            break;
        }
        at += 9 + len;
    }
    out
}

fn write(dir: &Path, name: &str, bytes: &[u8]) -> PathBuf {
    let p = dir.join(name);
    std::fs::write(&p, bytes).unwrap();
    p
}

/// `jointid simulate` of the shipped friction setup into `dir/name`: random input,
/// `steps` samples, binary frames.
fn simulate(dir: &Path, name: &str, steps: usize) -> PathBuf {
    let setup = repo("recordings/two-beam-friction.toml");
    let out = dir.join(name);
    ok(&[
        "simulate",
        setup.to_str().unwrap(),
        "--out",
        out.to_str().unwrap(),
        "--scenario",
        "random",
        "--steps",
        &steps.to_string(),
        "--encoding",
        "binary",
        "--seed",
        "5",
    ]);
    out
}

#[test]
fn malformed_recordings_give_one_line_errors_without_panic_hang_or_large_allocation() {
    let dir = tempfile::tempdir().unwrap();
    let good = simulate(dir.path(), "good.mcap", 12000);
    let bytes = std::fs::read(&good).unwrap();
    let records = record_offsets(&bytes);
    let chunks: Vec<usize> = records
        .iter()
        .filter(|r| r.1 == 0x06)
        .map(|r| r.0)
        .collect();
    assert!(chunks.len() >= 3, "the corpus needs several chunks");
    let mut corpus: Vec<(String, Vec<u8>)> = vec![
        ("empty.mcap".into(), Vec::new()),
        ("seven-bytes.mcap".into(), bytes[..7].to_vec()),
        ("magic-only.mcap".into(), bytes[..8].to_vec()),
    ];
    let mut rng = Lcg(0x5eed);
    let garbage: Vec<u8> = (0..4096).map(|_| rng.next() as u8).collect();
    corpus.push(("garbage.mcap".into(), garbage.clone()));
    let mut magic_garbage = bytes[..8].to_vec();
    magic_garbage.extend_from_slice(&garbage);
    corpus.push(("magic-garbage.mcap".into(), magic_garbage));
    for k in 1..=12 {
        let cut = bytes.len() * k / 13;
        corpus.push((format!("cut-{cut}.mcap"), bytes[..cut].to_vec()));
    }
    for _ in 0..40 {
        let at = (rng.next() as usize) % bytes.len();
        let bit = rng.next() % 8;
        let mut b = bytes.clone();
        b[at] ^= 1 << bit;
        corpus.push((format!("flip-{at}-{bit}.mcap"), b));
    }
    for &(at, op) in &records {
        for (label, len) in [("ffff", u64::MAX), ("4g", 0xFFFF_FFFF), ("zero", 0)] {
            let mut b = bytes.clone();
            b[at + 1..at + 9].copy_from_slice(&len.to_le_bytes());
            corpus.push((format!("len-{label}-op{op}-at{at}.mcap"), b));
        }
    }
    for &at in &chunks {
        // Chunk body: start time, end time, uncompressed size (at +9+16).
        let mut b = bytes.clone();
        b[at + 25..at + 33].copy_from_slice(&(1u64 << 30).to_le_bytes());
        corpus.push((format!("chunk-1g-at{at}.mcap"), b));
    }
    let mut replays = 0;
    for (i, (name, b)) in corpus.iter().enumerate() {
        let path = write(dir.path(), name, b);
        let p = path.to_str().unwrap();
        check(&["inspect", p], &[name]);
        if i % 4 == 0 {
            check(
                &["replay", p, "--estimator", "paper", "--passes", "1"],
                &[name],
            );
            replays += 1;
        }
    }
    assert!(replays >= 20);
}

#[test]
fn a_damaged_chunk_is_skipped_by_way_of_the_chunk_index_and_reported() {
    let dir = tempfile::tempdir().unwrap();
    let good = simulate(dir.path(), "good.mcap", 30000);
    let bytes = std::fs::read(&good).unwrap();
    let chunks: Vec<usize> = record_offsets(&bytes)
        .iter()
        .filter(|r| r.1 == 0x06)
        .map(|r| r.0)
        .collect();
    assert!(chunks.len() >= 5, "{} chunks", chunks.len());
    // One flipped bit in the second data chunk's length field (the first chunk holds the
    // schema and channels), and one in its compressed data.
    let at = chunks[2];
    for (label, byte) in [("length", at + 6), ("data", at + 200)] {
        let mut b = bytes.clone();
        b[byte] ^= 0x10;
        let path = write(dir.path(), &format!("{label}.mcap"), &b);
        let v: serde_json::Value =
            serde_json::from_str(&ok(&["inspect", path.to_str().unwrap(), "--json"])).unwrap();
        let damage = v["damage"].as_str().unwrap_or_default();
        assert!(
            damage.contains("skipped") && damage.contains(&format!("byte {at}")),
            "{label}: {damage}"
        );
        let frames = v["excitation_frames"].as_u64().unwrap();
        assert!(
            frames > 30000 * 6 / 10 && frames < 30000,
            "{label}: {frames} of 30000 frames recovered"
        );
    }
}

#[test]
fn malformed_setups_give_one_line_errors_without_panic_hang_or_large_allocation() {
    let dir = tempfile::tempdir().unwrap();
    let setup_path = repo("recordings/two-beam-friction.toml");
    let text = std::fs::read_to_string(&setup_path).unwrap();
    let good = dir.path().join("good.mcap");
    ok(&[
        "simulate",
        setup_path.to_str().unwrap(),
        "--out",
        good.to_str().unwrap(),
        "--scenario",
        "random",
        "--steps",
        "300",
    ]);
    // Every numeric literal outside comments, one at a time.
    let is_num = |c: char| c.is_ascii_digit() || matches!(c, '.' | 'e' | 'E' | '-' | '+');
    let mut spots = Vec::new();
    let mut offset = 0;
    for line in text.split_inclusive('\n') {
        let code = line.split('#').next().unwrap_or_default();
        let b = code.as_bytes();
        let mut i = 0;
        while i < b.len() {
            let starts = b[i].is_ascii_digit() && (i == 0 || !(b[i - 1] as char).is_alphanumeric());
            if starts {
                let mut j = i;
                while j < b.len() && is_num(b[j] as char) {
                    j += 1;
                }
                spots.push((offset + i, offset + j));
                i = j;
            } else {
                i += 1;
            }
        }
        offset += line.len();
    }
    assert!(spots.len() > 20, "found {} numbers", spots.len());
    let mut cases: Vec<String> = Vec::new();
    for (k, &(a, b)) in spots.iter().enumerate() {
        for (v, replacement) in ["nan", "inf", "-1.0", "0.0", "1e308"].iter().enumerate() {
            if (k + v) % 2 == 0 {
                cases.push(format!("{}{}{}", &text[..a], replacement, &text[b..]));
            }
        }
    }
    cases.push(text.replace("const(100)", "const(1e308)"));
    cases.push(text.replace("const(100)", "const(nan)"));
    cases.push(text.replace("[integrator]", "[integrator]\nunknown_field = 1"));
    cases.push(text[..text.len() / 2].to_string());
    cases.push("\u{0}\u{1}garbage = [[[".to_string());
    for (i, case) in cases.iter().enumerate() {
        let name = format!("setup-{i}.toml");
        let path = write(dir.path(), &name, case.as_bytes());
        check(
            &[
                "replay",
                good.to_str().unwrap(),
                "--setup",
                path.to_str().unwrap(),
                "--estimator",
                "paper",
                "--passes",
                "1",
            ],
            // A setup error names the setup; an error in the data names the recording.
            &[&name, "good.mcap"],
        );
    }

    // A model file that is a device, and one whose size line is enormous.
    let mm = dir.path().join("mm");
    std::fs::create_dir(&mm).unwrap();
    for f in ["setup.toml", "mass.mtx", "stiffness.mtx", "dofs.csv"] {
        std::fs::copy(repo(&format!("recordings/two-beam-mm/{f}")), mm.join(f)).unwrap();
    }
    std::fs::remove_file(mm.join("mass.mtx")).unwrap();
    std::os::unix::fs::symlink("/dev/zero", mm.join("mass.mtx")).unwrap();
    let mm_setup = mm.join("setup.toml");
    let args = [
        "replay",
        good.to_str().unwrap(),
        "--setup",
        mm_setup.to_str().unwrap(),
        "--estimator",
        "paper",
    ];
    assert_eq!(check(&args, &["mass.mtx"]), Some(1));
    std::fs::remove_file(mm.join("mass.mtx")).unwrap();
    let original = std::fs::read_to_string(repo("recordings/two-beam-mm/mass.mtx")).unwrap();
    let mut size_line_seen = false;
    let huge: String = original
        .lines()
        .map(|l| {
            if !size_line_seen && !l.starts_with('%') && !l.trim().is_empty() {
                size_line_seen = true;
                let nnz = l.split_whitespace().nth(2).unwrap_or("1");
                format!("1000000000 1000000000 {nnz}")
            } else {
                l.to_string()
            }
        })
        .collect::<Vec<_>>()
        .join("\n");
    std::fs::write(mm.join("mass.mtx"), huge).unwrap();
    assert_eq!(check(&args, &["mass.mtx"]), Some(1));
}
