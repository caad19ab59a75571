//! Development probe of the maximum-likelihood estimator on one synthetic test.
//! `cargo run --release --example ml_probe -- SETUP [--substeps 8] [--noise 0.01] [--seed 1] [--steps 2000] [--scenario random]`
#[path = "common/args.rs"]
mod args;
use jointid::estimate::ml::{MlOptions, identify_ml};
use jointid::identify::TestData;
use jointid::model::Model;
use jointid::simulate::{Noise, Scenario, SimulateOptions, simulate};

fn main() -> anyhow::Result<()> {
    let a = args::Args::from_env();
    let get = |k: &str, d: &str| a.get(k, d);
    let (_, setup) = a.setup("ml_probe")?;
    let substeps: usize = get("--substeps", "8").parse()?;
    let noise: f64 = get("--noise", "0.01").parse()?;
    let seed: u64 = get("--seed", "1").parse()?;
    let steps: usize = get("--steps", "2000").parse()?;
    let scenario = match get("--scenario", "random").as_str() {
        "sine" => Scenario::Sine {
            freq_hz: 50.0,
            amplitude: 1000.0,
        },
        "free" => Scenario::Free {
            amplitude: 1000.0,
            pulse_s: 5e-4,
        },
        _ => Scenario::Random { rms: 1000.0 },
    };
    let sim = simulate(
        &setup,
        &SimulateOptions {
            scenario,
            steps,
            dt_s: setup.dt_s,
            substeps,
            noise: if noise > 0.0 {
                Noise::Additive(noise)
            } else {
                Noise::None
            },
            seed,
        },
    )?;
    let skip: usize = get("--skip", "0").parse()?;
    let data = TestData {
        samples: (0..(steps - skip) as u64).collect(),
        t_ns: (0..(steps - skip) as u64).map(|i| i * 100_000).collect(),
        excitation: sim.excitation[skip..].to_vec(),
        response: sim.response[skip..].to_vec(),
    };
    let model = Model::for_identification(&setup)?;
    if a.flag("--bench") {
        let d = jointid::estimate::ml::Discretisation {
            scheme: jointid::estimate::ml::Scheme::Exact,
            substeps: 1,
        };
        let t = std::time::Instant::now();
        for _ in 0..50 {
            let _ = jointid::estimate::ml::predict(&setup, &model, &data, &sim.truth, None, d)?;
        }
        println!(
            "predict (discretise + simulate, full): {:.3} ms",
            t.elapsed().as_secs_f64() * 1e3 / 50.0
        );
        return Ok(());
    }
    if a.flag("--check") {
        let ms: usize = get("--model-substeps", "1").parse()?;
        let scheme = if a.flag("--newmark") {
            jointid::estimate::ml::Scheme::Newmark
        } else {
            jointid::estimate::ml::Scheme::Exact
        };
        let tr = jointid::estimate::ml::predict(
            &setup,
            &model,
            &data,
            &sim.truth,
            None,
            jointid::estimate::ml::Discretisation {
                scheme,
                substeps: ms,
            },
        )?;
        let m = setup.sensors.len();
        for k in 0..m {
            let (mut d2, mut y2) = (0.0, 0.0);
            for i in 0..data.len() {
                let y = sim.clean_response[i + skip][k];
                d2 += (tr.y[i * m + k] - y).powi(2);
                y2 += y * y;
            }
            println!(
                "{}: rel err {:.3e}",
                setup.sensors[k].name,
                (d2 / y2).sqrt()
            );
        }
        for i in [1usize, 2, 10, 100] {
            println!(
                "i={i} model {:.6e} sim {:.6e}",
                tr.y[i * m],
                sim.clean_response[i][0]
            );
        }
        return Ok(());
    }
    let t = std::time::Instant::now();
    let r = identify_ml(&setup, &model, &data, &MlOptions::default());
    let el = t.elapsed().as_secs_f64();
    match r {
        Ok((fit, _)) => {
            println!(
                "time {el:.3} s, iterations {}, stages {:?}\n  {}",
                fit.iterations, fit.stages, fit.discretisation
            );
            for (k, key) in setup.param_keys().iter().enumerate() {
                let tr = sim.truth[k];
                println!(
                    "{key:>14}: {:>12.5e} se {:>10.3e} crlb {:>10.3e} truth {:>10.3e}  err/se {:>7.2}",
                    fit.params[k],
                    fit.std_errors[k],
                    fit.crlb[k],
                    tr,
                    (fit.params[k] - tr) / fit.std_errors[k]
                );
            }
            println!(
                "whiteness {:?}",
                fit.whiteness
                    .iter()
                    .map(|w| format!("{w:.2}"))
                    .collect::<Vec<_>>()
            );
            println!(
                "fit% {:?}",
                fit.fit_percent
                    .iter()
                    .map(|w| format!("{w:.1}"))
                    .collect::<Vec<_>>()
            );
            for w in &fit.warnings {
                println!("warn: {w}");
            }
        }
        Err(e) => println!("time {el:.3} s, error: {e}"),
    }
    Ok(())
}
