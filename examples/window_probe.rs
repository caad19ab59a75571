//! Scratch: identify one window of a recording and print its notes.
use jointid::identify::{IdentifyOptions, TestData, identify};
use jointid::setup::Setup;
fn main() {
    let a: Vec<String> = std::env::args().skip(1).collect();
    let rec = jointid::io::mcap::read_recording(std::path::Path::new(&a[0])).unwrap();
    let start: usize = a[1].parse().unwrap();
    let n: usize = a[2].parse().unwrap();
    let mut text = rec.setup_toml.clone().unwrap();
    if let Some(init) = a.get(3) { text = text.replace("initial = [0.0, 0.0, 0.0, 0.0]", &format!("initial = [{init}]")); }
    let setup = Setup::from_toml(&text, "rec").unwrap();
    println!("initial {:?}", setup.initial_params());
    let mut d = TestData::default();
    for (e, r) in rec.excitation.iter().zip(&rec.response).skip(start).take(n) {
        d.samples.push(e.sample);
        d.t_ns.push(e.t_ns);
        d.excitation.push(e.values.clone());
        d.response.push(r.values.clone());
    }
    let mut opts = IdentifyOptions::from_setup(&setup);
    if start > 0 { opts.starts_mid_record = d.samples.first().copied(); }
    let id = identify(&setup, &d, &opts, setup.truth_params().as_deref(), &mut |_| {}, &mut |_, _| {});
    match id {
        Ok(i) => {
            println!("failure: {:?}", i.failure);
            for n in &i.notes { println!("note: {n}"); }
            if let Some(ps) = i.final_parameters() { for p in ps { println!("{} {} ± {}", p.basis, p.value, p.std_error); } }
        }
        Err(e) => println!("error: {e}"),
    }
}
