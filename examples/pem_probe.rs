//! Temporary probe: PEM vs OE cost along friction on the sign(u) two-beam problem.
use jointid::estimate::output_error::residuals;
use jointid::estimate::prediction_error::{innovations, predictor};
use jointid::identify::{IdentifyOptions, TestData, channel_noise, identify};
use jointid::model::Model;
use jointid::setup::Setup;
use jointid::simulate::{Noise, Scenario, SimulateOptions, simulate};

fn main() -> anyhow::Result<()> {
    let args: Vec<String> = std::env::args().collect();
    let seed: u64 = args.get(1).map(|s| s.parse().unwrap()).unwrap_or(3);
    let noise: f64 = args.get(2).map(|s| s.parse().unwrap()).unwrap_or(0.1);
    let sub: usize = args.get(4).map(|s| s.parse().unwrap()).unwrap_or(16);
    let fstds: Vec<f64> = args
        .get(3)
        .map(|s| s.split(',').map(|x| x.parse().unwrap()).collect())
        .unwrap_or(vec![30.0, 300.0, 3000.0]);
    let text = std::fs::read_to_string("recordings/two-beam-spring.toml")?
        .replace(
            "basis = [\"sign(u)\", \"u\", \"const(100)\", \"v\"]",
            "basis = [\"sign(u)\", \"u\"]",
        )
        .replace("initial = [0.0, 0.0, 0.0, 0.0]", "initial = [0.0, 0.0]")
        .replace("truth = [0.0, 3.0e5, 0.0, 0.0]", "truth = [3000.0, 3.0e5]")
        .replace("substeps = 1", "substeps = 16");
    let setup = Setup::from_toml(&text, "x")?;
    let model = Model::assemble(&setup)?;
    let n = 2000;
    let sim = simulate(
        &setup,
        &SimulateOptions {
            scenario: Scenario::Random { rms: 2e4 },
            steps: n,
            dt_s: setup.dt_s,
            substeps: 64,
            noise: Noise::Additive(noise),
            seed,
        },
    )?;
    eprintln!(
        "stuck fraction {:.3}, n dofs {}",
        sim.stuck_fraction,
        model.n()
    );
    let data = TestData {
        samples: (0..n as u64).collect(),
        t_ns: (0..n as u64)
            .map(|i| (i as f64 * setup.dt_s * 1e9) as u64)
            .collect(),
        excitation: sim.excitation.clone(),
        response: sim.response.clone(),
    };
    let (sigma, _) = channel_noise(&setup, &data);
    let mut o = IdentifyOptions::from_setup(&setup);
    o.output_error = false;
    let truth = vec![3000.0, 3e5];
    let r = identify(&setup, &data, &o, Some(&truth), &mut |_| {}, &mut |_, _| {})?;
    let start: Vec<f64> = r
        .final_parameters()
        .unwrap()
        .iter()
        .map(|p| p.value)
        .collect();
    let se: Vec<f64> = r
        .final_parameters()
        .unwrap()
        .iter()
        .map(|p| p.std_error)
        .collect();
    eprintln!("start {:?} se {:?}", start, se);
    if args.get(5).map(|s| s.as_str()) == Some("ml") {
        for at in [start.clone(), truth.clone()] {
            let mut line = String::new();
            for &fs in &fstds {
                let pred = predictor(&setup, &model, &at, &sigma, sub, fs)?;
                let c = innovations(
                    &setup,
                    &model,
                    &at,
                    &pred,
                    &data.excitation,
                    &data.response,
                    sub,
                )?
                .1;
                let logdet: f64 = -2.0
                    * pred
                        .whiten
                        .diagonal()
                        .iter()
                        .map(|x| x.abs().ln())
                        .sum::<f64>();
                let ll = -0.5 * (c + n as f64 * logdet);
                line += &format!(" {fs}:{ll:.1}");
            }
            eprintln!("loglik{line}");
        }
        return Ok(());
    }
    if args.get(5).map(|s| s.as_str()) == Some("refine") {
        for &fs in &fstds {
            let mut v = start.clone();
            let mut sc = se.clone();
            for sub in [16usize, 32, 64] {
                let t0 = std::time::Instant::now();
                let r = jointid::estimate::prediction_error::refine(
                    &setup,
                    &model,
                    &v,
                    &sc,
                    &data.excitation,
                    &data.response,
                    &sigma,
                    sub,
                    fs,
                    20,
                )?;
                eprintln!(
                    "fstd {fs} sub {sub}: friction {:+.3} % (se {:.3} %, naive {:.3} %), spring {:+.4} % (se {:.4} %, naive {:.4} %), cost {:.4}→{:.4}, it {}, lag {}, rho {:.5} ({:.1}s)",
                    100.0 * (r.values[0] / 3000.0 - 1.0),
                    100.0 * r.std_errors[0] / 3000.0,
                    100.0 * r.naive[0] / 3000.0,
                    100.0 * (r.values[1] / 3e5 - 1.0),
                    100.0 * r.std_errors[1] / 3e5,
                    100.0 * r.naive[1] / 3e5,
                    r.report.cost_start,
                    r.report.cost_end,
                    r.report.iterations,
                    r.report.hac_lag,
                    r.report.spectral_radius,
                    t0.elapsed().as_secs_f64()
                );
                v = r.values.clone();
                sc = r.std_errors.clone();
                let pred = predictor(&setup, &model, &v, &sigma, sub, fs)?;
                let ce = innovations(
                    &setup,
                    &model,
                    &v,
                    &pred,
                    &data.excitation,
                    &data.response,
                    sub,
                )?
                .1;
                let ct = innovations(
                    &setup,
                    &model,
                    &truth,
                    &pred,
                    &data.excitation,
                    &data.response,
                    sub,
                )?
                .1;
                let mut line = String::new();
                for k in 0..=10 {
                    let t = k as f64 / 10.0;
                    let p: Vec<f64> = v.iter().zip(&truth).map(|(a, b)| a + t * (b - a)).collect();
                    line += &format!(
                        " {:.1}",
                        innovations(
                            &setup,
                            &model,
                            &p,
                            &pred,
                            &data.excitation,
                            &data.response,
                            sub
                        )?
                        .1 - ce
                    );
                }
                eprintln!(
                    "   cost at estimate {ce:.2}, at truth {ct:.2}; line estimate→truth:{line}"
                );
            }
        }
        return Ok(());
    }
    let grid: Vec<f64> = (-8..=8).map(|i| i as f64 * 0.01).collect();
    for which in 0..2 {
        for &fs in &fstds {
            let t0 = std::time::Instant::now();
            let pred = predictor(&setup, &model, &start, &sigma, sub, fs)?;
            let mut line = format!(
                "param {which} fstd {fs:>6} rho {:.4}:",
                pred.spectral_radius
            );
            for &g in &grid {
                let mut p = truth.clone();
                p[which] *= 1.0 + g;
                let c = innovations(
                    &setup,
                    &model,
                    &p,
                    &pred,
                    &data.excitation,
                    &data.response,
                    sub,
                )
                .map(|x| x.1)
                .unwrap_or(f64::NAN);
                line += &format!(" {:.1}", c);
            }
            eprintln!("{line} ({:.1}s)", t0.elapsed().as_secs_f64());
        }
        let mut line = format!("param {which} OE:");
        for &g in &grid {
            let mut p = truth.clone();
            p[which] *= 1.0 + g;
            let c = residuals(
                &setup,
                &model,
                &p,
                &data.excitation,
                &data.response,
                &sigma,
                sub,
            )
            .map(|x| x.1)
            .unwrap_or(f64::NAN);
            line += &format!(" {:.1}", c);
        }
        eprintln!("{line}");
    }
    Ok(())
}
