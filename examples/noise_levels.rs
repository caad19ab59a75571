//! The channel noise levels `replay` estimates from a record's differences against the
//! noise the simulator added: the same seed simulated with and without noise.
//!
//! ```text
//! cargo run --release --example noise_levels -- SETUP [--seed 1] [--scenario sine|random]
//!     [--substeps 8] [--noise 0.01] [--steps 2000]
//! ```
//! Prints, per channel, the added noise's RMS, the estimate (`channel_noise_std`, the
//! smallest over difference orders 1–6), their ratio and every order's estimate.
#[path = "common/args.rs"]
mod args;
use jointid::estimate::tuning::{MAX_DIFFERENCE_ORDER, channel_noise_std, difference_noise_std};
use jointid::simulate::{Noise, Scenario, SimulateOptions, simulate};

fn main() -> anyhow::Result<()> {
    let a = args::Args::from_env();
    let get = |k: &str, d: &str| a.get(k, d);
    let (_, setup) = a.setup("noise_levels")?;
    let seed: u64 = get("--seed", "1").parse()?;
    let substeps: usize = get("--substeps", "8").parse()?;
    let level: f64 = get("--noise", "0.01").parse()?;
    let steps: usize = get("--steps", "2000").parse()?;
    // `jointid simulate`'s defaults: a 200 Hz sine of 2e4 N, or random input of RMS 2e4 N.
    let scenario = match get("--scenario", "sine").as_str() {
        "sine" => Scenario::Sine {
            freq_hz: 200.0,
            amplitude: 2e4,
        },
        "random" => Scenario::Random { rms: 2e4 },
        other => anyhow::bail!("--scenario {other}: sine or random"),
    };
    let run = |noise| {
        simulate(
            &setup,
            &SimulateOptions {
                scenario,
                steps,
                dt_s: setup.dt_s,
                substeps,
                noise,
                seed,
            },
        )
    };
    let noisy = run(Noise::Additive(level))?;
    let clean = run(Noise::None)?;
    println!("| channel | added noise RMS | estimate | ratio | orders 1–{MAX_DIFFERENCE_ORDER} |");
    println!("|---|---|---|---|---|");
    for (k, sensor) in setup.sensors.iter().enumerate() {
        let y: Vec<f64> = noisy.response.iter().map(|r| r[k]).collect();
        let added = (noisy
            .response
            .iter()
            .zip(&clean.response)
            .map(|(a, b)| (a[k] - b[k]).powi(2))
            .sum::<f64>()
            / y.len().max(1) as f64)
            .sqrt();
        let estimate = channel_noise_std(&y);
        let orders: Vec<String> = (1..=MAX_DIFFERENCE_ORDER)
            .map(|o| format!("{:.3e}", difference_noise_std(&y, o).unwrap_or(f64::NAN)))
            .collect();
        println!(
            "| {} | {added:.4e} | {estimate:.4e} | {:.2} | {} |",
            sensor.name,
            estimate / added,
            orders.join(" ")
        );
    }
    Ok(())
}
