//! Identify one window of a recording and print everything the identification says (its
//! notes, passes and failure): the diagnostic for a window that `jointid replay` or
//! `jointid live` reports as failed, where only the last window's notes are shown.
//! `cargo run --release --example window_probe -- RECORDING FIRST_SAMPLE [SAMPLES]
//! [--prior V1,V2,…:SE1,SE2,…]` (SAMPLES defaults to the recording's window length, else
//! 20,000; `--prior` starts the window from those values, as a session starts a window
//! from the combination of the earlier ones).
use std::path::Path;

use anyhow::{Context, bail};
use jointid::identify::{IdentifyOptions, TestData};
use jointid::io::mcap::read_recording;
use jointid::session::identify_window;
use jointid::setup::Setup;

fn main() -> anyhow::Result<()> {
    let a: Vec<String> = std::env::args().collect();
    let (Some(path), Some(first)) = (a.get(1), a.get(2)) else {
        bail!("usage: window_probe RECORDING FIRST_SAMPLE [SAMPLES]");
    };
    let first: u64 = first.parse().context("FIRST_SAMPLE")?;
    let rec = read_recording(Path::new(path))?;
    let toml = rec
        .setup_toml
        .as_deref()
        .context("the recording has no attached setup")?;
    let setup = Setup::from_toml(toml, path)?;
    let len: usize = match a.get(3).filter(|s| !s.starts_with("--")) {
        Some(s) => s.parse().context("SAMPLES")?,
        None => setup.estimator.window_samples.unwrap_or(20_000),
    };
    let start = rec
        .excitation
        .iter()
        .position(|f| f.sample == first)
        .with_context(|| format!("sample {first} is not in {path}"))?;
    let end = (start + len)
        .min(rec.excitation.len())
        .min(rec.response.len());
    let data = TestData {
        samples: rec.excitation[start..end]
            .iter()
            .map(|f| f.sample)
            .collect(),
        t_ns: rec.excitation[start..end].iter().map(|f| f.t_ns).collect(),
        excitation: rec.excitation[start..end]
            .iter()
            .map(|f| f.values.clone())
            .collect(),
        response: rec.response[start..end]
            .iter()
            .map(|f| f.values.clone())
            .collect(),
    };
    let truth: Option<Vec<f64>> = setup.truth_params();
    let mut opts = IdentifyOptions::from_setup(&setup);
    if let Some(i) = a.iter().position(|x| x == "--prior") {
        let spec = a.get(i + 1).context("--prior V1,V2,…:SE1,SE2,…")?;
        let (v, e) = spec.split_once(':').context("--prior V1,V2,…:SE1,SE2,…")?;
        let list = |s: &str| -> anyhow::Result<Vec<f64>> {
            s.split(',')
                .map(|x| x.trim().parse::<f64>().context("--prior"))
                .collect()
        };
        opts.prior = Some(jointid::identify::Prior {
            values: list(v)?,
            std_errors: list(e)?,
            source: "--prior".into(),
        });
    }
    let record_first = rec.excitation.first().map(|f| f.sample);
    let t = std::time::Instant::now();
    let (est, id) = identify_window(
        &setup,
        &data,
        &opts,
        truth.as_deref(),
        record_first,
        &[],
        &mut |p| {
            let v: Vec<String> = p
                .parameters
                .iter()
                .map(|e| format!("{:.4e} ± {:.2e}", e.value, e.std_error))
                .collect();
            println!(
                "pass {}: {} (fit residual RMS {:?} N, rows {:?}, stuck {:?})",
                p.pass,
                v.join(", "),
                p.fit_rms_residual,
                p.rows_used,
                p.rows_excluded_stuck
            );
        },
    );
    println!(
        "window {}–{} identified in {:.2} s",
        est.first_sample,
        est.last_sample,
        t.elapsed().as_secs_f64()
    );
    match id {
        Ok(i) => {
            for p in i.final_parameters().unwrap_or(&[]) {
                println!(
                    "  {}.{:<12} {:.6e} ± {:.3e}",
                    p.connection, p.basis, p.value, p.std_error
                );
            }
            if let Some(f) = &i.failure {
                println!("failure: {f}");
            }
            for n in &i.notes {
                println!("note: {n}");
            }
        }
        Err(e) => println!("error: {e}"),
    }
    Ok(())
}
