//! The parameters a recorded live session published, in order, with their distance from
//! the truth in standard errors (when the recording holds the truth): the evidence for
//! "within 2 standard errors of the truth after 10 s and stays so" (docs/LIVE.md).
//!
//! ```text
//! cargo run --release --example live_timeline -- session.mcap [--kind batch|online|all]
//! ```
//!
//! One line per `/jointid/parameters` message: seconds from the first sample's time stamp
//! to its publication (the message's log time), kind, `final`, and per parameter
//! `value ± se (z)` with `z = (value − truth)/se`. The last line summarises the worst |z|
//! of the selected kind after 10 s.

use std::process::ExitCode;

use serde_json::Value;

fn main() -> ExitCode {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let Some(path) = args.first() else {
        eprintln!("usage: live_timeline SESSION.mcap [--kind batch|online|all]");
        return ExitCode::FAILURE;
    };
    let kind = args
        .iter()
        .position(|a| a == "--kind")
        .and_then(|i| args.get(i + 1))
        .map_or("batch", String::as_str);
    match run(path, kind) {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("error: {path}: {e}");
            ExitCode::FAILURE
        }
    }
}

fn run(path: &str, kind: &str) -> Result<(), String> {
    let bytes = std::fs::read(path).map_err(|e| e.to_string())?;
    let stream = mcap::MessageStream::new(&bytes).map_err(|e| e.to_string())?;
    let mut first_t: Option<u64> = None;
    let mut worst_after_10s: f64 = 0.0;
    let mut count = 0usize;
    for m in stream {
        let m = m.map_err(|e| e.to_string())?;
        let topic = m.channel.topic.as_str();
        if topic == "/jointid/excitation" && first_t.is_none() {
            // Binary frames: sample, t_ns, values (little-endian).
            if let Some(t) = m.data.get(8..16) {
                let mut b = [0u8; 8];
                b.copy_from_slice(t);
                first_t = Some(u64::from_le_bytes(b));
            }
            continue;
        }
        if topic != "/jointid/parameters" {
            continue;
        }
        let v: Value = serde_json::from_slice(&m.data).map_err(|e| e.to_string())?;
        let k = v["kind"].as_str().unwrap_or("?");
        if kind != "all" && k != kind {
            continue;
        }
        // Publication time (`jointid live` logs parameters when it publishes them).
        let t = first_t.map_or(0.0, |f| m.log_time.saturating_sub(f) as f64 * 1e-9);
        let mut cells = Vec::new();
        for p in v["parameters"].as_array().into_iter().flatten() {
            let value = p["value"].as_f64().unwrap_or(f64::NAN);
            let se = p["std_error"].as_f64().unwrap_or(f64::NAN);
            let z = p["truth"].as_f64().map(|tr| (value - tr) / se);
            if let Some(z) = z
                && t >= 10.0
                && z.is_finite()
            {
                worst_after_10s = worst_after_10s.max(z.abs());
            }
            cells.push(format!(
                "{} {value:.5e} ± {se:.2e}{}",
                p["key"].as_str().unwrap_or("?"),
                z.map_or(String::new(), |z| format!(" ({z:+.2})"))
            ));
        }
        count += 1;
        println!(
            "{t:8.2} s  {k:<6} {}  {}",
            if v["final"].as_bool() == Some(true) {
                "final"
            } else {
                "     "
            },
            cells.join(", ")
        );
    }
    println!("{count} `{kind}` messages; worst |z| after 10 s: {worst_after_10s:.2}");
    Ok(())
}
