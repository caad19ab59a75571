//! Per-sample cost of the paper estimator with the dense, the modal and the sparse step, on
//! synthetic chains (`jointid::model::synthetic`) or on your own setup:
//!
//! ```text
//! cargo run --release --example bench_model                       # the BENCHMARKS.md table
//! cargo run --release --example bench_model -- --dofs 24000       # the 24,000-DOF rows
//! cargo run --release --example bench_model -- --dofs 24,240 --channels 6 --connections 1
//! cargo run --release --example bench_model -- --setup my-model.toml [--dense-max 3000] [--modal-max 3000]
//! ```
//!
//! Per model and engine: set-up time (assembly; estimator construction = the dense
//! inverse of `M + γhC + βh²K`, the modal eigen-decomposition or the sparse Cholesky
//! factorisation, plus Γ_f, S and the gain),
//! steps per second of `PaperEstimator::step` (predict, station outputs, Eq. 3, update,
//! connection deformations), the real-time factor at 51.2 kHz (steps/s ÷ 51,200; > 1 is
//! faster than real time), steps per second of the thread's own CPU time (the machine is
//! shared: this is what a core of its own would give), the bytes of the operators the step
//! uses, and the process RSS
//! after set-up. The data fed are zeros: the step's arithmetic does not depend on the
//! values, and zeros cannot diverge. The dense baseline runs in the same process, on the
//! same model, up to `--dense-max` DOFs (default 2,400), the modal step up to `--modal-max`
//! (default 2,400; its set-up is O(n³)); above that they are skipped. Models above 5,000
//! DOFs are assembled in sparse form only, where neither can run.
use std::time::Instant;

use jointid::estimate::StepOutput;
use jointid::identify::{IdentifyOptions, build_estimator};
use jointid::integrate::sparse::SparseStep;
use jointid::model::Model;
use jointid::setup::{EstimatorKind, Setup, StepKind};

fn rss_kib() -> (u64, u64) {
    let s = std::fs::read_to_string("/proc/self/status").unwrap_or_default();
    let get = |k: &str| {
        s.lines()
            .find(|l| l.starts_with(k))
            .and_then(|l| l.split_whitespace().nth(1))
            .and_then(|v| v.parse().ok())
            .unwrap_or(0)
    };
    (get("VmRSS:"), get("VmHWM:"))
}

/// CPU seconds (user + system) this thread has used, from /proc (10 ms ticks).
fn thread_cpu_s() -> f64 {
    let s = std::fs::read_to_string("/proc/thread-self/stat").unwrap_or_default();
    // Fields after the command name's closing parenthesis; utime, stime are 14th, 15th.
    let rest = s.rsplit_once(')').map_or("", |r| r.1);
    // rest[0] is the state (field 3), so utime is rest[11], stime rest[12].
    let f: Vec<&str> = rest.split_whitespace().collect();
    let get = |i: usize| f.get(i).and_then(|x| x.parse::<f64>().ok());
    match (get(11), get(12)) {
        (Some(u), Some(s)) => (u + s) / 100.0,
        _ => f64::NAN,
    }
}

struct Run {
    setup_s: f64,
    steps_per_s: f64,
    /// Steps per second of this thread's CPU time (what a core of its own would give).
    steps_per_cpu_s: f64,
    operator_bytes: usize,
    rss_mib: f64,
}

fn run(setup: &Setup, model: &Model, kind: StepKind, min_time_s: f64) -> Result<Run, String> {
    let mut model = model.clone();
    model.step = kind;
    let n = model.n();
    let (m, q, ne) = (model.stations.len(), model.Lc.ncols(), model.Lp.ncols());
    let mut opts = IdentifyOptions::from_setup(setup);
    opts.estimator = EstimatorKind::Paper;
    let params = setup.initial_params();
    let sigma = vec![1e-6; m];
    let t0 = Instant::now();
    let mut est =
        build_estimator(setup, &model, &params, &opts, &sigma, 0).map_err(|e| e.to_string())?;
    let setup_s = t0.elapsed().as_secs_f64();
    let rss = rss_kib().0 as f64 / 1024.0;
    let exc = vec![0.0; ne];
    let meas = vec![0.0; m];
    let mut out = StepOutput::new(q);
    est.start(0, &exc);
    let t0 = Instant::now();
    let c0 = thread_cpu_s();
    let mut i = 0u64;
    loop {
        for _ in 0..16 {
            i += 1;
            est.step(i, &exc, &meas, &mut out)
                .map_err(|e| e.to_string())?;
        }
        if t0.elapsed().as_secs_f64() > min_time_s && i >= 32 {
            break;
        }
    }
    let steps_per_s = i as f64 / t0.elapsed().as_secs_f64();
    let steps_per_cpu_s = i as f64 / (thread_cpu_s() - c0);
    let f = std::mem::size_of::<f64>();
    let operator_bytes = match kind {
        // (M+γhC+βh²K)⁻¹, C, K, M, Lp, Lc, Γ_f (u, v, a).
        StepKind::Dense => f * (4 * n * n + n * (ne + q) + 3 * n * q),
        // Sparse C, K, envelope factor, Lp, Lc (SparseStep::operator_bytes); Γ_f; state.
        StepKind::Sparse => {
            let with = model.with_connection_terms(setup, &params);
            let step = SparseStep::new(&with, setup.dt_s, opts.substeps, setup.newmark)
                .map_err(|e| e.to_string())?;
            step.operator_bytes() + f * (3 * n * q + 9 * n)
        }
        // Per mode: 3×3 map + 3 load vectors; ΨᵀLp, ΨᵀLc; station rows of Ψ; modal Γ_f.
        _ => f * (18 * n + n * (ne + q) + n * m + 3 * n * q),
    };
    Ok(Run {
        setup_s,
        steps_per_s,
        steps_per_cpu_s,
        operator_bytes,
        rss_mib: rss,
    })
}

fn list(args: &[String], key: &str, default: &[usize]) -> Vec<usize> {
    args.iter()
        .position(|a| a == key)
        .and_then(|i| args.get(i + 1))
        .map(|v| v.split(',').filter_map(|x| x.trim().parse().ok()).collect())
        .unwrap_or_else(|| default.to_vec())
}

fn main() {
    let args: Vec<String> = std::env::args().collect();
    let dense_max = list(&args, "--dense-max", &[2400])[0];
    let modal_max = list(&args, "--modal-max", &[2400])[0];
    let min_time = 1.0;
    let mut cases: Vec<(String, Setup)> = Vec::new();
    if let Some(i) = args.iter().position(|a| a == "--setup") {
        let p = std::path::PathBuf::from(args.get(i + 1).expect("--setup PATH"));
        match Setup::from_file(&p) {
            Ok(s) => cases.push((p.display().to_string(), s)),
            Err(e) => {
                eprintln!("error: {e}");
                std::process::exit(1);
            }
        }
    } else {
        for n in list(&args, "--dofs", &[24, 240, 2400]) {
            for ch in list(&args, "--channels", &[6, 64]) {
                for c in list(&args, "--connections", &[1, 8]) {
                    let text = jointid::model::synthetic::chain_setup_toml(n, ch, c);
                    let s = Setup::from_toml(&text, "synthetic chain").expect("chain setup");
                    cases.push((format!("chain {n}"), s));
                }
            }
        }
    }
    println!(
        "| model | DOFs | channels | connections | assembly s | dense set-up s | modal set-up s | sparse set-up s | dense steps/s | modal steps/s | sparse steps/s | modal RT factor @51.2 kHz | sparse RT factor @51.2 kHz | modal/dense speed | sparse/dense speed | dense operators MiB | modal operators MiB | sparse operators MiB | RSS after sparse set-up MiB | steps per CPU-s dense / modal / sparse |"
    );
    println!("|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|");
    for (name, setup) in &cases {
        let t0 = Instant::now();
        let model = match Model::assemble(setup) {
            Ok(m) => m,
            Err(e) => {
                eprintln!("{name}: {e}");
                continue;
            }
        };
        let assembly = t0.elapsed().as_secs_f64();
        let n = model.n();
        let (m, q) = (model.stations.len(), model.Lc.ncols());
        if m < q {
            // Eq. 3 needs rank(S) = q: fewer channels than connection DOFs cannot work.
            println!(
                "| {name} | {n} | {m} | {q} | {assembly:.3} | n/a: the paper estimator needs ≥ {q} independent channels for {q} connection DOFs | | | | | | | | | | | | | | |"
            );
            continue;
        }
        let dense = if n <= dense_max && model.has_dense() {
            Some(run(setup, &model, StepKind::Dense, min_time))
        } else {
            None
        };
        let modal = if n <= modal_max && model.has_dense() {
            Some(run(setup, &model, StepKind::Modal, min_time))
        } else {
            None
        };
        let sparse = run(setup, &model, StepKind::Sparse, min_time);
        let mib = |b: usize| b as f64 / (1024.0 * 1024.0);
        let (ds, dsp, dmem) = match &dense {
            Some(Ok(r)) => (
                format!("{:.3}", r.setup_s),
                format!("{:.0}", r.steps_per_s),
                format!("{:.2}", mib(r.operator_bytes)),
            ),
            Some(Err(e)) => (format!("error: {e}"), "-".into(), "-".into()),
            None => ("skipped".into(), "skipped".into(), "-".into()),
        };
        let cols = |r: &Option<Result<Run, String>>| match r {
            Some(Ok(r)) => (
                format!("{:.3}", r.setup_s),
                format!("{:.0}", r.steps_per_s),
                format!("{:.2}", r.steps_per_s / 51_200.0),
                format!("{:.3}", mib(r.operator_bytes)),
                format!("{:.0}", r.rss_mib),
            ),
            Some(Err(e)) => (
                format!("not available: {e}"),
                "-".into(),
                "-".into(),
                "-".into(),
                "-".into(),
            ),
            None => (
                "skipped".into(),
                "skipped".into(),
                "-".into(),
                "-".into(),
                "-".into(),
            ),
        };
        let (ms, msp, rt, mmem, _) = cols(&modal);
        let sparse = Some(sparse);
        let (ss, ssp, srt, smem, rss) = cols(&sparse);
        let per_cpu = |r: &Option<Result<Run, String>>| match r {
            Some(Ok(r)) => format!("{:.0}", r.steps_per_cpu_s),
            _ => "-".into(),
        };
        let cpu = format!(
            "{} / {} / {}",
            per_cpu(&dense),
            per_cpu(&modal),
            per_cpu(&sparse)
        );
        let ratio = |x: &Option<Result<Run, String>>| match (&dense, x) {
            (Some(Ok(d)), Some(Ok(m))) => format!("{:.1}×", m.steps_per_s / d.steps_per_s),
            _ => "-".into(),
        };
        let (mr, sr) = (ratio(&modal), ratio(&sparse));
        println!(
            "| {name} | {n} | {} | {} | {assembly:.3} | {ds} | {ms} | {ss} | {dsp} | {msp} | {ssp} | {rt} | {srt} | {mr} | {sr} | {dmem} | {mmem} | {smem} | {rss} | {cpu} |",
            model.stations.len(),
            model.Lc.ncols(),
        );
    }
    let (_, hwm) = rss_kib();
    println!("\npeak RSS {:.0} MiB", hwm as f64 / 1024.0);
}
