//! Development probe: the free-run output-error χ² (true noise levels) of the truth, and of `--at` values, at every model level from 1 to 64 sub-steps, on one synthetic record.
//! `cargo run --release --example oe_probe -- SETUP [--substeps 8] [--noise 0.01] [--seed 1] [--steps 3000] [--rms 50] [--at v1,v2,...]` (ACCURACY.md, forty-eighth session)
#[path = "common/args.rs"]
mod args;
use jointid::model::Model;
use jointid::simulate::{Noise, Scenario, SimulateOptions, simulate};

fn main() -> anyhow::Result<()> {
    let a = args::Args::from_env();
    let get = |k: &str, d: &str| a.get(k, d);
    let (_, setup) = a.setup("oe_probe")?;
    let substeps: usize = get("--substeps", "8").parse()?;
    let noise: f64 = get("--noise", "0.01").parse()?;
    let seed: u64 = get("--seed", "1").parse()?;
    let steps: usize = get("--steps", "3000").parse()?;
    let rms: f64 = get("--rms", "50").parse()?;
    let at: Vec<f64> = get("--at", "")
        .split(',')
        .filter(|s| !s.is_empty())
        .map(|v| {
            v.trim()
                .parse()
                .map_err(|e| anyhow::anyhow!("--at: `{v}` is not a number ({e})"))
        })
        .collect::<anyhow::Result<_>>()?;
    let sim = simulate(
        &setup,
        &SimulateOptions {
            scenario: Scenario::Random { rms },
            steps,
            dt_s: setup.dt_s,
            substeps,
            noise: Noise::Additive(noise),
            seed,
        },
    )?;
    let model = Model::for_identification(&setup)?;
    let sigma = sim.noise_std.clone();
    println!("truth {:?} sigma {:?}", sim.truth, sigma);
    for lv in [1usize, 2, 4, 8, 16, 32, 64] {
        let (_, ct) = jointid::estimate::output_error::residuals(
            &setup,
            &model,
            &sim.truth,
            &sim.excitation,
            &sim.response,
            &sigma,
            lv,
        )?;
        let ca = if at.is_empty() {
            f64::NAN
        } else {
            jointid::estimate::output_error::residuals(
                &setup,
                &model,
                &at,
                &sim.excitation,
                &sim.response,
                &sigma,
                lv,
            )?
            .1
        };
        println!(
            "level {lv}: chi2 truth {ct:.1}  at {ca:.1}  (n·m = {})",
            steps * sigma.len()
        );
    }
    Ok(())
}
