use jointid::identify::*;
use jointid::setup::*;
use jointid::simulate::*;
fn main() {
    let args: Vec<String> = std::env::args().collect();
    let s = Setup::from_file(std::path::Path::new(&args[1])).unwrap();
    let m = jointid::model::Model::assemble(&s).unwrap();
    println!("n = {} freqs {:?}", m.n(), &m.natural_frequencies_hz());
    let mt = m.with_connection_terms(&s, &s.truth_params().unwrap());
    println!("with joint freqs {:?}", &mt.natural_frequencies_hz());
    let steps: usize = args[2].parse().unwrap();
    let noise: Noise = args[3].parse().unwrap();
    let kind: EstimatorKind = args[4].parse().unwrap();
    let sub: usize = args.get(5).map(|x| x.parse().unwrap()).unwrap_or(1);
    let sc = match args.get(6).map(|s| s.as_str()) { Some("sine") => Scenario::Sine{freq_hz: 200.0, amplitude: 2e4}, Some("free") => Scenario::Free{amplitude: 5e4, pulse_s: 5e-4}, _ => Scenario::Random{rms: 2e4}};
    let sim = simulate(&s, &SimulateOptions{scenario: sc, steps, dt_s: s.dt_s, substeps: sub, noise, seed: 7}).unwrap();
    println!("stuck fraction {}", sim.stuck_fraction);
    let (tf, td) = (sim.force.clone(), sim.delta.clone());
    let data = TestData{samples: (0..steps as u64).collect(), t_ns: vec![0; steps], excitation: sim.excitation, response: sim.response};
    let mut o = IdentifyOptions::from_setup(&s);
    o.estimator = kind;
    let t = std::time::Instant::now();
    let r = identify(&s, &data, &o, Some(&sim.truth), &mut |p| {
        println!("pass {} {:?} cond {:?} rho {:?} condS {:.3e} excl {:?}", p.pass, p.parameters.iter().map(|x| (x.value, x.std_error)).collect::<Vec<_>>(), p.fit_condition, p.diagnostics.error_spectral_radius, p.diagnostics.sensitivity_condition, p.rows_excluded_stuck);
    }, &mut |pass, o| { let i = o.sample as usize; if pass <= 2 && (i < 5 || i % 50 == 0) { println!("  p{} i{} d {:.6e} vs {:.6e}  f {:.6e} vs {:.6e}", pass, i, o.delta[0], td[i][0], o.force[0], tf[i][0]); } });
    println!("{:?} {:?}", r.as_ref().map(|r| r.stop_reason.clone()), r.as_ref().err().map(|e| e.to_string()));
    println!("elapsed {:?}", t.elapsed());
}
