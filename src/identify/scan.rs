//! The output-error stage started from a scan instead of from the residual-force estimate,
//! for when the residual-force (Kalman) stage cannot give a start: accelerometer-only
//! layouts (with `ü` as the only output, a constant residual force and its static
//! deflection produce no acceleration, so the filter's joint deformation drifts and its fit
//! ends at `k ≈ −k_ground`), and laws with a friction (`sign`) term whose residual-force
//! stage is refused (deformation undetermined, or no samples outside the stuck band). The
//! output-error cost has no such unobserved direction, so the start comes from log-spaced
//! stiffness and friction scans on a record prefix at each model sub-step level (and a
//! friction × stiffness grid), grown on windows to the whole record; the answer is then
//! checked (whole-record stiffness rescan, other starts within Δχ², probe moves). ACCURACY.md,
//! "Accuracy of the default estimator": "Accelerometers only, and mixed layouts" and
//! "Friction without a residual-force start".

use crate::estimate::refit::RefitError;
use crate::estimate::{EstimateError, EstimatorDiagnostics};
use crate::model::Model;
use crate::setup::{Basis, Setup};

use super::{
    Identification, IdentifyError, IdentifyOptions, MAX_RAISED_STEPS, ParameterEstimate,
    PassReport, TestData, finish_with_output_error,
};

/// Every measured channel is an acceleration.
pub(super) fn acceleration_only(model: &Model) -> bool {
    let stations = crate::estimate::Stations::from_model(model);
    stations.m() > 0
        && stations
            .channels
            .iter()
            .all(|&(_, qty)| qty == crate::setup::Quantity::Acceleration)
}

/// Some connection has a linear spring term (`u`), the parameter the accelerometer-only
/// start scan searches.
pub(super) fn has_spring_basis(setup: &Setup) -> bool {
    setup
        .connections
        .iter()
        .any(|c| c.basis.iter().any(|b| matches!(b, Basis::U)))
}

/// Some connection has a `sign(u)` friction term: the law the prediction error refines.
pub(super) fn has_sign_u_basis(setup: &Setup) -> bool {
    setup
        .connections
        .iter()
        .any(|c| c.basis.contains(&Basis::SignU))
}

/// Whether a connection's law has a `sign` term (friction).
pub(super) fn has_sign_basis(setup: &Setup) -> bool {
    setup
        .param_basis()
        .iter()
        .any(|b| matches!(b, Basis::SignU | Basis::SignV))
}

/// Whether a connection's law has a term that is not linear in the state (friction, cubic
/// stiffness, gap): its free-run output-error cost can have local minima away from the
/// stiffness the scan of `output_error::refine_global` covers.
pub(super) fn has_nonlinear_term(setup: &Setup) -> bool {
    setup
        .param_basis()
        .iter()
        .any(|b| matches!(b, Basis::SignU | Basis::SignV | Basis::U3 | Basis::Gap(_)))
}

/// Samples of the record prefix on which [`identify_acceleration_only`] scans the stiffness
/// (the output-error basin widens like 1/length: measured half-width 5–17 % of the truth
/// at 2,000 samples, so ≥ 50 % at 200).
const ACCEL_SCAN_SAMPLES: usize = 200;
/// Least signal energy of the scanned prefix, in noise units (`Σ (y² − σ²)/σ²` over its
/// samples and channels), below which a linear law's prefix is doubled (up to the whole
/// record). Why: the prefix must hold the stiffness's signature above the noise. Measured
/// on the two-beam accelerometer layout, random input, 100 % noise of the *whole record's*
/// RMS: the undamped structure's response grows over the record, so the first 200 samples
/// hold 0.2–0.46× the RMS of a 2,000-sample record (energy ≈ 100 noise units there; the
/// scan found the truth on seeds 1–5) but only 0.06–0.16× of a 20,000-sample one (≈ 10):
/// there the scan picked a start 9× the truth and the answer was **+609 % with a 0.005 %
/// stated error** (seed 2; 50 %, seed 1: −1.3 % with 0.003 %).
const SCAN_PREFIX_ENERGY: f64 = 100.0;
/// The finest model sub-step level the accelerometer-only scan tries, whatever the setup's
/// sub-steps (data of a continuous structure need the model near their own time step).
const ACCEL_MAX_SUBSTEPS: usize = 128;
/// Points of the log-spaced stiffness scan, and its range as multiples of the largest
/// diagonal stiffness of the model (two-beam problem: 3e5 N/m truth, 1.3e8 N/m largest
/// diagonal term; ratio per step 1.16).
const ACCEL_SCAN_POINTS: usize = 80;
const ACCEL_SCAN_RANGE: [f64; 2] = [1e-6, 1e-1];

/// Points of the log-spaced friction-level scan of [`scan_start`] and its range as
/// multiples of the RMS of the excitation (two-beam problem: 2e4 N RMS, Coulomb truth
/// 3000 N = 0.15×; 21 points, ratio per step 1.41). The level 0 (no friction) is tried too.
const FRICTION_SCAN_POINTS: usize = 21;
const FRICTION_SCAN_RANGE: [f64; 2] = [1e-3, 1.0];

/// Scales of the scans: the largest diagonal stiffness of the model (N/m, at least 1) and
/// the RMS of the excitation over all channels and samples (N; 1 when it is zero or not
/// finite). Stiffness and friction ranges are fractions of these.
fn scan_scales(model: &Model, exc: &[Vec<f64>]) -> (f64, f64) {
    let kmax = model.K.diagonal().amax().max(1.0);
    let cells = exc.iter().map(|e| e.len()).sum::<usize>().max(1);
    let frms = (exc.iter().flatten().map(|x| x * x).sum::<f64>() / cells as f64).sqrt();
    let frms = if frms.is_finite() && frms > 0.0 {
        frms
    } else {
        1.0
    };
    (kmax, frms)
}

/// `points` log-spaced values over `range × scale`, ends included.
fn log_grid(range: [f64; 2], scale: f64, points: usize) -> Vec<f64> {
    let (lo, hi) = ((range[0] * scale).ln(), (range[1] * scale).ln());
    (0..points)
        .map(|i| (lo + (hi - lo) * i as f64 / (points - 1).max(1) as f64).exp())
        .collect()
}

/// The prefix the start scan runs on and its signal energy in noise units: the first
/// [`ACCEL_SCAN_SAMPLES`], doubled for a linear law while its energy is below
/// [`SCAN_PREFIX_ENERGY`] (at most the whole record). A non-linear law keeps the 200
/// samples: its friction × stiffness grid (1,240 simulations) on a longer prefix would cost
/// minutes per doubling, and the measured friction cases were found from 200 (not
/// measured with a longer one).
fn scan_prefix(data: &TestData, sigma: &[f64], linear: bool) -> (usize, f64) {
    let energy = |n: usize| -> f64 {
        data.response[..n]
            .iter()
            .map(|y| {
                y.iter()
                    .zip(sigma)
                    .filter(|(_, s)| **s > 0.0 && s.is_finite())
                    .map(|(v, s)| (v * v - s * s) / (s * s))
                    .sum::<f64>()
            })
            .sum()
    };
    let mut n = data.len().min(ACCEL_SCAN_SAMPLES);
    let mut e = energy(n);
    while linear && e < SCAN_PREFIX_ENERGY && n < data.len() {
        n = (2 * n).min(data.len());
        e = energy(n);
    }
    (n, e)
}

/// The start of the output-error stage when the residual-force stage cannot give one: on
/// the record prefix `exc`/`resp`, a log-spaced scan of each spring stiffness (the others
/// at their current value), then — when the law has friction terms (`sign`) — a log-spaced
/// scan of each friction level at that stiffness, and the stiffness scan again at the
/// friction found. Returns the start and its normalised cost `Σ((y − ŷ)/σ)²/(N·m)`.
///
/// Why the friction scan: with the friction held at 0 the stiffness profile carries no
/// information about the joint. Measured (accelerations only, Coulomb `sign(v)` at 3000 N
/// with a spring of 3e5 N/m, 10 % noise, 2,000 samples): seed 1 ended at spring **+34 %
/// with a 0.08 % stated error** (friction −1.6 %; three probe restarts were still finding
/// lower costs), seed 2 at spring −104 % with 0.01 % (friction +46 %).
#[allow(clippy::too_many_arguments)]
fn scan_start(
    setup: &Setup,
    model: &Model,
    basis: &[Basis],
    initial: &[f64],
    exc: &[Vec<f64>],
    resp: &[Vec<f64>],
    sigma: &[f64],
    substeps: usize,
    stiffness_points: usize,
) -> (Vec<f64>, f64) {
    use crate::estimate::output_error::residuals;
    let nobs = (exc.len() * sigma.len()).max(1) as f64;
    let (kmax, frms) = scan_scales(model, exc);
    let cost_at = |p: &[f64]| {
        residuals(setup, model, p, exc, resp, sigma, substeps)
            .map(|r| r.1)
            .unwrap_or(f64::INFINITY)
    };
    // One parameter over its grid, the others held; keeps the lowest (the current value
    // included, so a pass never makes the start worse).
    // (The grid's points differ only in `j`, which each sets: their costs do not depend on
    // the order, so they are run on parallel threads and compared in the grid's order.)
    let scan_one = |start: &mut Vec<f64>, cost: &mut f64, j: usize, grid: &[f64]| {
        let costs = crate::par::map(grid, |&v| {
            let mut p = start.clone();
            p[j] = v;
            cost_at(&p)
        });
        for (&v, c) in grid.iter().zip(costs) {
            if c < *cost {
                *cost = c;
                start[j] = v;
            }
        }
    };
    let springs: Vec<usize> = (0..basis.len())
        .filter(|&j| matches!(basis[j], Basis::U))
        .collect();
    let frictions: Vec<usize> = (0..basis.len())
        .filter(|&j| matches!(basis[j], Basis::SignU | Basis::SignV))
        .collect();
    let kgrid = log_grid(ACCEL_SCAN_RANGE, kmax, stiffness_points);
    let fgrid = log_grid(FRICTION_SCAN_RANGE, frms, FRICTION_SCAN_POINTS);
    let mut start = initial.to_vec();
    let mut cost = cost_at(&start);
    for &j in &springs {
        scan_one(&mut start, &mut cost, j, &kgrid);
    }
    if !frictions.is_empty() {
        for &j in &frictions {
            scan_one(&mut start, &mut cost, j, &fgrid);
        }
        for &j in &springs {
            scan_one(&mut start, &mut cost, j, &kgrid);
        }
    }
    (start, cost / nobs)
}

/// Lowest local minima of the 2-D grid of [`grid_candidates`] that are refined on growing
/// windows; the lowest whole-record cost among them and the coordinate search's start
/// starts the output-error stage.
const SCAN_CANDIDATES: usize = 3;
/// The 2-D grid of [`grid_candidates`]: stiffness points over `ACCEL_SCAN_RANGE` (ratio
/// per step 1.34) and friction points over `FRICTION_SCAN_RANGE` (ratio 1.26). Measured
/// basin on a 200-sample prefix (accelerations only, seed 6, 64 sub-steps, truth 3000 N,
/// 3e5 N/m): ±30 % in friction, about ±50 % in stiffness.
const GRID_SPRING_POINTS: usize = 40;
const GRID_FRICTION_POINTS: usize = 31;

/// Start candidates for a law with friction and a spring: the prefix cost on a 2-D
/// log grid of (first friction level, first stiffness), the others held at `start`; the
/// [`SCAN_CANDIDATES`] lowest 8-neighbour local minima, each polished by two alternating
/// 9-point scans within one grid step. Returned lowest prefix cost first (normalised).
///
/// Why not the coordinate search alone: on the prefix the stiffness profile at zero
/// friction carries no information (normalised cost 1.7–3.1 over 2e5…1e6 N/m against 0.028
/// at the truth; accelerations only, 10 % noise, seed 6, 64 sub-steps), and at a friction
/// 30 % high the stiffness profile has several minima of equal cost (0.10–0.13 from 1e3 to
/// 3e5 N/m): the search (stiffness, friction, stiffness) ended at 4,563 N / 695,000 N/m,
/// cost 0.24, which grew into the wrong whole-record minimum at +12 % / +73 %. Cost: 1,240
/// prefix simulations at the chosen sub-step level (~11 ms each at 64 sub-steps).
#[allow(clippy::too_many_arguments)]
fn grid_candidates(
    setup: &Setup,
    model: &Model,
    basis: &[Basis],
    start: &[f64],
    exc: &[Vec<f64>],
    resp: &[Vec<f64>],
    sigma: &[f64],
    substeps: usize,
) -> Vec<(Vec<f64>, f64)> {
    use crate::estimate::output_error::residuals;
    let (Some(jk), Some(jf)) = (
        basis.iter().position(|b| matches!(b, Basis::U)),
        basis
            .iter()
            .position(|b| matches!(b, Basis::SignU | Basis::SignV)),
    ) else {
        return Vec::new();
    };
    let nobs = (exc.len() * sigma.len()).max(1) as f64;
    let (kmax, frms) = scan_scales(model, exc);
    let cost_at = |p: &[f64]| {
        residuals(setup, model, p, exc, resp, sigma, substeps)
            .map(|r| r.1 / nobs)
            .unwrap_or(f64::INFINITY)
    };
    let kg = log_grid(ACCEL_SCAN_RANGE, kmax, GRID_SPRING_POINTS);
    let fg = log_grid(FRICTION_SCAN_RANGE, frms, GRID_FRICTION_POINTS);
    let (nk, nf) = (kg.len(), fg.len());
    // Every point of the grid on parallel threads (independent simulations).
    let points: Vec<(usize, usize)> = (0..nk).flat_map(|a| (0..nf).map(move |b| (a, b))).collect();
    let c = crate::par::map(&points, |&(a, b)| {
        let mut p = start.to_vec();
        p[jk] = kg[a];
        p[jf] = fg[b];
        cost_at(&p)
    });
    let mut local: Vec<(usize, usize)> = Vec::new();
    for a in 0..nk {
        for b in 0..nf {
            let v = c[a * nf + b];
            if !v.is_finite() {
                continue;
            }
            let mut is_min = true;
            for da in -1i64..=1 {
                for db in -1i64..=1 {
                    let (x, y) = (a as i64 + da, b as i64 + db);
                    if (da, db) == (0, 0) || x < 0 || y < 0 || x >= nk as i64 || y >= nf as i64 {
                        continue;
                    }
                    if c[x as usize * nf + y as usize] < v {
                        is_min = false;
                    }
                }
            }
            if is_min {
                local.push((a, b));
            }
        }
    }
    local.sort_by(|x, y| c[x.0 * nf + x.1].total_cmp(&c[y.0 * nf + y.1]));
    let (rk, rf) = (kg[1] / kg[0], fg[1] / fg[0]);
    let mut out: Vec<(Vec<f64>, f64)> = local
        .into_iter()
        .take(SCAN_CANDIDATES)
        .map(|(a, b)| {
            let mut p = start.to_vec();
            p[jk] = kg[a];
            p[jf] = fg[b];
            let mut best = c[a * nf + b];
            for _ in 0..2 {
                for (j, r) in [(jk, rk), (jf, rf)] {
                    let centre = p[j];
                    for i in 0..9 {
                        let mut q = p.clone();
                        q[j] = centre * r.powf((i as f64 - 4.0) / 4.0);
                        let cq = cost_at(&q);
                        if cq < best {
                            best = cq;
                            p = q;
                        }
                    }
                }
            }
            (p, best)
        })
        .collect();
    out.sort_by(|x, y| x.1.total_cmp(&y.1));
    out
}

/// The residual-force stage's refusals after which the output-error stage is started from
/// a scan instead ([`identify_from_scan`]): the joint deformation undetermined (measured:
/// Coulomb `sign(v)` + spring, 100 % noise, 20,000 samples, posterior std of δ 1.8–2.1×
/// the RMS of δ̂ in pass 2), or no sample left for the fit outside the stuck band. Neither
/// says anything about the output-error cost, which has no residual force and so no
/// unobserved deformation.
///
/// Only for laws with a friction (`sign`) term: for a spring alone the fallback was
/// measured and is not honest enough (mixed layout, `u`, 50 % noise, 2,000 samples: seed 1
/// −0.45 % with a 0.14 % stated error, 128 model sub-steps chosen on the prefix; seed 2
/// −0.055 %, se 0.064 %), so those refusals stand (test
/// `mixed_layout_at_high_noise_is_refused_as_undetermined`).
pub(super) fn scan_fallback_applies(setup: &Setup, e: &IdentifyError) -> bool {
    let friction = setup.connections.iter().any(|c| {
        c.basis
            .iter()
            .any(|b| matches!(b, Basis::SignU | Basis::SignV))
    });
    friction
        && matches!(
            e,
            IdentifyError::Undetermined { .. }
                | IdentifyError::Refit {
                    source: RefitError::TooFewRows { .. },
                    ..
                }
        )
}

/// Largest move, in the final stated standard errors, that the probe of
/// `output_error::refine_global` may make from the best descent's end when the
/// output-error stage was started from a scan; beyond it the answer is refused
/// ([`IdentifyError::ScanUnsettled`]).
///
/// Why: from a scan start that lies in the wrong part of a friction–stiffness valley the
/// descent stops where lower costs remain along the valley, and the probe walks down it a
/// few standard errors per round. Measured (accelerations only, Coulomb `sign(v)` + spring,
/// 10 % noise, 2,000 samples): seed 6 ended friction +12 %, spring **+73 % with a 0.18 %
/// stated error** after 3 probe restarts had moved the spring by 300 standard errors;
/// seeds 1–5, whose answers were within 0.2 %, had no probe restart at all.
pub(super) const MAX_SCAN_PROBE_MOVE: f64 = 3.0;

/// Restarts of the output-error stage from the probe's end when the probe moved the answer
/// by more than [`MAX_SCAN_PROBE_MOVE`]; still moving after these, the answer is refused.
pub(super) const SETTLE_ROUNDS: usize = 3;

/// The largest move the probe made (parameter key, move in final standard errors) in an
/// accepted output-error stage, measured from the lowest minimum the descents reached
/// before probing; `None` when no probe restarted the descent.
fn probe_move(setup: &Setup, result: &Identification) -> Option<(String, f64)> {
    let oe = result.output_error.as_ref()?;
    let scan = oe.scan.as_ref()?;
    if !scan.minima.iter().any(|m| m.from == "probe") {
        return None;
    }
    let before = scan
        .minima
        .iter()
        .filter(|m| m.from != "probe")
        .min_by(|a, b| a.cost.total_cmp(&b.cost))?;
    let last = result.passes.last()?;
    let keys = setup.param_keys();
    last.parameters
        .iter()
        .zip(&before.values)
        .enumerate()
        .map(|(j, (p, b))| {
            (
                keys.get(j).cloned().unwrap_or_default(),
                (p.value - b).abs() / p.std_error.max(f64::MIN_POSITIVE),
            )
        })
        .max_by(|a, b| a.1.total_cmp(&b.1))
}

/// Refine the scan's start by output error on windows growing 4× from the scanned prefix
/// (`len` samples) while shorter than the record; the whole record is left to
/// `finish_with_output_error`. Updates `start` and `scales` (to the last window's standard
/// errors, wider than the whole record's) and returns the last window's length (`len`
/// when nothing was refined).
///
/// Why: the scan is a coordinate search (stiffness, friction, stiffness) on a grid with
/// 16 % and 41 % steps, so its start lies in the friction–stiffness valley but not at the
/// prefix's minimum; the short windows' basins are wide (∝ 1/length) and each window's
/// minimum starts the next inside its basin.
#[allow(clippy::too_many_arguments)]
fn grow_start(
    setup: &Setup,
    model: &Model,
    data: &TestData,
    opts: &IdentifyOptions,
    sigma: &[f64],
    len: usize,
    start: &mut Vec<f64>,
    scales: &mut Vec<f64>,
) -> usize {
    use crate::estimate::output_error::refine;
    let n = data.len();
    let mut w = len;
    let mut grown = len;
    while w < n {
        let Ok(r) = refine(
            setup,
            model,
            start,
            scales,
            &data.excitation[..w],
            &data.response[..w],
            sigma,
            opts.substeps,
            opts.output_error_iterations,
        ) else {
            break;
        };
        if !(r.report.accepted && r.std_errors.iter().all(|s| s.is_finite() && *s > 0.0)) {
            break;
        }
        *start = r.values;
        *scales = r.std_errors;
        grown = w;
        w *= 4;
    }
    grown
}

/// After a scan-started refinement: every other grown start candidate more than 3 stated
/// standard errors from the answer whose whole-record cost (unrefined, so an upper bound of
/// its minimum's) is within the likelihood-ratio threshold of the answer's (Δχ² = 3.84 ×
/// the normalised cost when above 1, or the cost left above the noise floor — the rule of
/// `output_error::refine_global`) cannot be told apart from it: the standard errors are
/// widened to cover it and a note says so.
///
/// Why: the candidates come from separate minima of the prefix grid and only the lowest
/// whole-record cost is refined further; without this a near-tie between two minima would
/// be reported with the errors of one (the confident wrong answer measured on the mixed
/// layout at 50 % noise: +21 % with a 0.05 % stated error).
fn widen_for_other_candidates(
    setup: &Setup,
    model: &Model,
    data: &TestData,
    sigma: &[f64],
    candidates: &[Vec<f64>],
    result: &mut Identification,
) {
    let Some((sub, c_end)) = result
        .output_error
        .as_ref()
        .map(|r| (r.substeps, r.cost_end))
    else {
        return;
    };
    let Some(last) = result.passes.last_mut() else {
        return;
    };
    let nobs = (data.len() * sigma.len()).max(1) as f64;
    let threshold = (3.84 * c_end.max(1.0)).max((c_end - 1.0) * nobs);
    let keys = setup.param_keys();
    let mut widened = Vec::new();
    for p in candidates {
        let far = p
            .iter()
            .zip(&last.parameters)
            .any(|(a, q)| (a - q.value).abs() > 3.0 * q.std_error);
        if !far {
            continue;
        }
        let Ok((_, c)) = data.free_run(setup, model, p, sigma, sub) else {
            continue;
        };
        if (c / nobs - c_end) * nobs >= threshold {
            continue;
        }
        for (j, (a, q)) in p.iter().zip(last.parameters.iter_mut()).enumerate() {
            let d = (a - q.value).abs() / 1.96;
            if d > q.std_error {
                q.std_error = d;
                q.ci95 = [q.value - 1.96 * d, q.value + 1.96 * d];
                widened.push(format!(
                    "{} to {d:.4e}",
                    keys.get(j).cloned().unwrap_or_default()
                ));
            }
        }
    }
    if !widened.is_empty() {
        result.notes.push(format!(
            "another start of the scan ends at a whole-record cost within Δχ² {threshold:.2} of the answer's, more than 3 standard errors away: the data do not decide between them, and the standard errors are widened to cover it ({})",
            widened.join(", ")
        ));
    }
}

/// A scan start that the whole-record refinement could not improve (no step, scan point or
/// probe lowered the cost: the report says "converged" but not accepted, since acceptance
/// means improving on the start) is itself the minimum: take it, with the standard errors
/// and bound of a refinement at it. Measured (accelerations only, Coulomb `sign(v)` +
/// spring, 10 % noise, 2,000 samples, seed 4): the start grown on an 800-sample window
/// (+0.32 %, −0.16 %) was refused as "did not lower the cost".
fn accept_converged_start(
    setup: &Setup,
    model: &Model,
    data: &TestData,
    opts: &IdentifyOptions,
    sigma: &[f64],
    result: &mut Identification,
) {
    use crate::estimate::output_error::refine;
    let Some(report) = result.output_error.as_mut() else {
        return;
    };
    if report.accepted || !report.note.starts_with("converged") {
        return;
    }
    let Some(last) = result.passes.last_mut() else {
        return;
    };
    let values: Vec<f64> = last.parameters.iter().map(|p| p.value).collect();
    let scales: Vec<f64> = last.parameters.iter().map(|p| p.std_error).collect();
    let Ok(r) = refine(
        setup,
        model,
        &values,
        &scales,
        &data.excitation,
        &data.response,
        sigma,
        report.substeps,
        opts.output_error_iterations,
    ) else {
        return;
    };
    if r.report.cost_end > report.cost_start || r.std_errors.iter().any(|s| !s.is_finite()) {
        return;
    }
    for (j, p) in last.parameters.iter_mut().enumerate() {
        p.value = r.values[j];
        p.std_error = r.std_errors[j];
        p.ci95 = [p.value - 1.96 * p.std_error, p.value + 1.96 * p.std_error];
        p.crlb = Some(r.crlb[j]);
    }
    report.accepted = true;
    report.cost_end = r.report.cost_end;
    report.note = format!(
        "{}; the scan's start was already the whole-record minimum (no step lowered the cost) and is the answer",
        report.note
    );
}

/// Steps of the whole-record stiffness check of [`rescan_whole_record`], as fractions of
/// the answer's stiffness: −40 % … +60 % in 2.5 % steps (the whole-record basin half-width
/// of the stiffness is 2–6 % at 2,000 samples, ACCURACY.md "Wrong minima").
const RESCAN_RANGE: [f64; 2] = [-0.4, 0.6];
const RESCAN_STEP: f64 = 0.025;
/// Points of the coarse whole-record stiffness check over the start scan's whole range
/// (log-spaced, ratio 1.34 per step), beside the ±40–60 % one. Why: accelerations only,
/// Coulomb + spring, 100 % noise, 2,000 samples, seed 3: the prefix scan (200 samples,
/// little signal) started the stage at 7,400 N/m and the answer was friction +29 %, spring
/// **−96 % with a 0.14 % stated error**; with the friction held there the whole-record cost
/// at the true 3e5 N/m is lower by Δχ² = 45 (0.9965 against 1.0003, 128 sub-steps), far
/// outside the ±40–60 % window.
const RESCAN_FAR_POINTS: usize = 40;

/// After a scan-started refinement: the first stiffness scanned over the whole record
/// around the answer (the other parameters held); when a point is lower than the answer by
/// more than Δχ² = 3.84 (× the normalised cost when above 1), the output-error descent is
/// restarted there and its end replaces the answer if lower. Returns the replaced answer
/// (for the ambiguity check of [`widen_for_other_candidates`]).
///
/// Why: at 50 % noise the 200-sample prefix hardly tells the candidates apart (prefix cost
/// 0.5347 at the truth, 0.5360 at the answer; accelerations only, Coulomb + spring, 2,000
/// samples, seed 1), and the answer ended at friction +9.3 %, spring **−26 % with a 0.42 %
/// stated error**, whole-record cost 0.5020 against 0.4930 at the truth; with the friction
/// held at the answer's the whole-record cost at the true stiffness is 0.4949 (Δχ² = 85).
/// `output_error::refine_global`'s own stiffness scan there had only 3 points (its basin
/// estimate uses the marginal bound, which the friction–stiffness correlation inflates).
fn rescan_whole_record(
    setup: &Setup,
    model: &Model,
    data: &TestData,
    opts: &IdentifyOptions,
    sigma: &[f64],
    result: &mut Identification,
) -> Option<Vec<f64>> {
    use crate::estimate::output_error::refine;
    let report = result.output_error.as_mut().filter(|r| r.accepted)?;
    let last = result.passes.last_mut()?;
    let j = setup
        .connections
        .iter()
        .flat_map(|c| c.basis.iter())
        .position(|b| matches!(b, Basis::U))?;
    let values: Vec<f64> = last.parameters.iter().map(|p| p.value).collect();
    let scales: Vec<f64> = last.parameters.iter().map(|p| p.std_error).collect();
    let nobs = (data.len() * sigma.len()).max(1) as f64;
    let sub = report.substeps;
    let c_answer = report.cost_end;
    let steps = ((RESCAN_RANGE[1] - RESCAN_RANGE[0]) / RESCAN_STEP).round() as usize;
    let near = (0..=steps).map(|i| values[j] * (1.0 + RESCAN_RANGE[0] + RESCAN_STEP * i as f64));
    // And the whole scanned stiffness range, coarsely: the answer may lie in a wrong
    // valley far from the truth (see `RESCAN_FAR_POINTS`).
    let far = log_grid(
        ACCEL_SCAN_RANGE,
        scan_scales(model, &data.excitation).0,
        RESCAN_FAR_POINTS,
    );
    // Every point's whole-record cost on parallel threads (independent simulations), the
    // lowest taken in the points' order.
    let points: Vec<Vec<f64>> = near
        .chain(far)
        .map(|k| {
            let mut p = values.clone();
            p[j] = k;
            p
        })
        .collect();
    let costs = crate::par::map(&points, |p| {
        data.free_run(setup, model, p, sigma, sub)
            .ok()
            .map(|(_, c)| c)
    });
    let mut lowest: Option<(Vec<f64>, f64)> = None;
    for (p, c) in points.into_iter().zip(costs) {
        let Some(c) = c else {
            continue;
        };
        if lowest.as_ref().is_none_or(|l| c / nobs < l.1) {
            lowest = Some((p, c / nobs));
        }
    }
    let (p, c) = lowest?;
    if (c_answer - c) * nobs <= 3.84 * c_answer.max(1.0) {
        return None;
    }
    let r = refine(
        setup,
        model,
        &p,
        &scales,
        &data.excitation,
        &data.response,
        sigma,
        sub,
        opts.output_error_iterations,
    )
    .ok()?;
    if r.report.cost_end >= c_answer || r.std_errors.iter().any(|s| !s.is_finite()) {
        return None;
    }
    for (k, q) in last.parameters.iter_mut().enumerate() {
        q.value = r.values[k];
        q.std_error = r.std_errors[k];
        q.ci95 = [q.value - 1.96 * q.std_error, q.value + 1.96 * q.std_error];
        q.crlb = Some(r.crlb[k]);
    }
    report.note = format!(
        "{}; a whole-record stiffness scan around that answer and over the scanned range (cost {c_answer:.4}) found a lower point, and the descent restarted there ended at {:.4}",
        report.note, r.report.cost_end
    );
    report.cost_end = r.report.cost_end;
    result.notes.push(format!(
        "the output-error answer from the scan start was not the lowest cost along the stiffness (normalised cost {c_answer:.4}); a whole-record scan of ±40–60 % and over the scanned stiffness range, and a descent from its lowest point, gave {:.4}, which is reported",
        r.report.cost_end
    ));
    Some(values)
}

/// Why [`identify_from_scan`] runs instead of the residual-force stage.
pub(super) enum ScanReason {
    /// Every channel is an acceleration (ACCURACY.md "Accelerometers only").
    AccelerationOnly,
    /// The residual-force stage was refused or failed before any accepted pass; the error
    /// stands when the scan-started output-error stage is not accepted either.
    ResidualForceRefused(IdentifyError),
}

/// Accelerometer-only layouts (ACCURACY.md "Accelerometers only"): the residual-force (Kalman)
/// stage cannot start them — with `ü` as the only output the augmented pair (state,
/// residual force) has an exactly unobservable eigenvalue 1 (a constant residual force and
/// its static deflection `u_s = −K⁻¹ Lc R` produce no acceleration; PBH test, measured),
/// so the filter's joint deformation drifts (posterior std 3.9 m) and its fit ends at
/// `k ≈ −k_ground`. The output-error cost has no such direction (the parameters enter the
/// model, the prediction starts at rest), so the start comes from a log-spaced scan of the
/// stiffness (and friction levels, [`scan_start`]) on a short prefix, and the output-error
/// stage (with its local scan and the sub-step raise) does the identification. Not
/// accepted → refused as before.
#[allow(clippy::too_many_arguments)]
pub(super) fn identify_acceleration_only(
    setup: &Setup,
    model: &Model,
    data: &TestData,
    opts: &IdentifyOptions,
    truth: Option<&[f64]>,
    sigma: &[f64],
    estimated: &[bool],
    result: Identification,
) -> Result<Identification, IdentifyError> {
    identify_from_scan(
        setup,
        model,
        data,
        opts,
        truth,
        sigma,
        estimated,
        result,
        ScanReason::AccelerationOnly,
    )
}

/// The output-error stage started from [`scan_start`] (with the model sub-step level chosen
/// by the scan) instead of from the residual-force estimate; see
/// [`identify_acceleration_only`] and [`ScanReason`].
#[allow(clippy::too_many_arguments)]
pub(super) fn identify_from_scan(
    setup: &Setup,
    model: &Model,
    data: &TestData,
    opts: &IdentifyOptions,
    truth: Option<&[f64]>,
    sigma: &[f64],
    estimated: &[bool],
    mut result: Identification,
    reason: ScanReason,
) -> Result<Identification, IdentifyError> {
    let accel = matches!(reason, ScanReason::AccelerationOnly);
    let refused = match &reason {
        ScanReason::ResidualForceRefused(e) => e.to_string(),
        ScanReason::AccelerationOnly => String::new(),
    };
    let refused_note = refused.clone();
    let refuse = move |why: String| match reason {
        ScanReason::AccelerationOnly => IdentifyError::Estimate(EstimateError::AccelerationOnly {
            channels: sigma.len(),
        }),
        ScanReason::ResidualForceRefused(e) => IdentifyError::ScanFallbackRejected {
            refused: Box::new(e),
            why,
        },
    };
    let basis: Vec<Basis> = setup
        .connections
        .iter()
        .flat_map(|c| c.basis.iter().cloned())
        .collect();
    let linear = crate::simulate::law_is_linear(setup);
    let (len, prefix_energy) = scan_prefix(data, sigma, linear);
    // The stiffness basins narrow like 1/length: a longer prefix gets proportionally more
    // scan points (a linear law's prefix only; its scan runs the composed one-sample map).
    let points = ACCEL_SCAN_POINTS * len.div_ceil(ACCEL_SCAN_SAMPLES).max(1);
    let (exc, resp) = (&data.excitation[..len], &data.response[..len]);
    let initial = setup.initial_params();
    let scan = |sub: usize| {
        scan_start(
            setup, model, &basis, &initial, exc, resp, sigma, sub, points,
        )
    };
    // Model sub-steps: accelerations are dominated by the highest modes, where Newmark's
    // period error is largest, and a too coarse model moves the cost's minimum (measured,
    // 50 % noise, seed 1: with 16 sub-steps on 64-sub-step data the global minimum lies at
    // +24 %, cost 0.97, and none near the truth; with 64 the truth, cost 0.40). The
    // sub-step raise of the output-error stage judged the levels only at the minima found,
    // where finer steps do not help (since the thirty-eighth session it also refines the
    // doublings by continuation from the answer, a local search). So: scan with the setup's
    // sub-steps and each doubling up to 8×
    // (within `MAX_RAISED_STEPS` over the record) and keep the level and start of the lowest
    // prefix cost (data of the model's own discretisation pick the setup's, continuous data
    // a finer one). Measured with a rule that then coarsened the level while the
    // whole-record cost at the start stayed within 3 χ²-standard deviations: at 100 % noise
    // seed 1 went back to 16 sub-steps and ended +25 % with a 0.11 % stated error.
    //
    // The finest level is at least `ACCEL_MAX_SUBSTEPS` whatever the setup's sub-steps
    // (measured: the shipped setup has 1, so levels stopped at 8 on 64-sub-step data and
    // seeds 1 and 5 at 10 % noise ended +22 % and +20 % with 0.04 % stated errors; with
    // levels to 128 they pick 64 and end within 0.01 %). A linear law's sub-steps cost one
    // composed map per sample, so the step budget does not apply to it.
    let mut level = opts.substeps;
    let (mut start, mut cost) = scan(level);
    let mut sub = level;
    let finest = (8 * opts.substeps).max(ACCEL_MAX_SUBSTEPS);
    while level * 2 <= finest && (linear || data.len() * level * 2 <= MAX_RAISED_STEPS) {
        level *= 2;
        let (s2, c2) = scan(level);
        if c2 < cost {
            (start, cost, sub) = (s2, c2, level);
        }
    }
    if !cost.is_finite() {
        return Err(refuse(format!(
            "the scan's cost on the first {len} samples is not finite at any point"
        )));
    }
    let mut opts = opts.clone();
    opts.substeps = sub;
    // Accelerations only: the refinement's level choices keep to the scan's level and finer
    // ones (the records are dominated by the highest modes, where a coarser level moved the
    // answer: the history above, and seed 3 of
    // `tests/accelerometers.rs::accelerometers_only_friction_at_full_noise_far_rescan_and_settling`,
    // which ended −46 % from 64 sub-steps where the scan's 128 and the whole-record rescan
    // find the truth's valley). After a refused residual-force stage (displacement or
    // velocity channels) they go down to the setup's (`IdentifyOptions::coarsest_substeps`).
    if accel {
        opts.coarsest_substeps = sub;
    }
    let opts = &opts;
    // The scan's step (16 %) as the scale of the start: a refinement that does not settle
    // is taken only within 3 of these (`finish_with_output_error`).
    let scale_of = |p: &[f64]| -> Vec<f64> { p.iter().map(|v| 0.16 * v.abs().max(1e-6)).collect() };
    let mut scales = scale_of(&start);
    let mut grown = grow_start(
        setup,
        model,
        data,
        opts,
        sigma,
        len,
        &mut start,
        &mut scales,
    );
    let mut candidates_tried = 1;
    // Every grown start, for the ambiguity check after the refinement.
    let mut grown_points: Vec<Vec<f64>> = Vec::new();
    if basis
        .iter()
        .any(|b| matches!(b, Basis::SignU | Basis::SignV))
    {
        let whole = |p: &[f64]| {
            data.free_run(setup, model, p, sigma, sub)
                .map(|r| r.1)
                .unwrap_or(f64::INFINITY)
        };
        let mut best = whole(&start);
        let others = grid_candidates(setup, model, &basis, &start, exc, resp, sigma, sub);
        // Each candidate grown on its own thread (its growth does not depend on the others),
        // then taken in the candidates' order: a candidate equal to the start as it stands
        // by then is passed over, as one after the other. One equal to the first start is
        // not grown ahead (it is passed over unless an earlier candidate replaced the
        // start; then it is grown in its turn).
        let first_start = start.clone();
        let todo: Vec<Vec<f64>> = others.into_iter().map(|(p, _)| p).collect();
        let grow = |raw: &Vec<f64>| {
            let mut p = raw.clone();
            let mut sc = scale_of(&p);
            let g = grow_start(setup, model, data, opts, sigma, len, &mut p, &mut sc);
            let c = whole(&p);
            (p, sc, g, c)
        };
        let grown_all = crate::par::map(&todo, |raw| (*raw != first_start).then(|| grow(raw)));
        for (raw, ahead) in todo.iter().zip(grown_all) {
            if *raw == start {
                continue;
            }
            let (p, sc, g, c) = ahead.unwrap_or_else(|| grow(raw));
            candidates_tried += 1;
            grown_points.push(p.clone());
            if c < best {
                (best, start, scales, grown) = (c, p, sc, g);
            }
        }
        grown_points.push(start.clone());
    }
    let parameters = setup
        .connections
        .iter()
        .flat_map(|c| c.basis.iter().map(move |b| (c, b)))
        .zip(start.iter().zip(&scales))
        .enumerate()
        .map(|(k, ((c, b), (&v, &se)))| ParameterEstimate {
            connection: c.name.clone(),
            basis: b.label(),
            unit: b.unit().into(),
            value: v,
            std_error: se,
            ci95: [v - 1.96 * se, v + 1.96 * se],
            crlb: None,
            std_error_ols: None,
            truth: truth.map(|t| t[k]),
        })
        .collect();
    let why = if accel {
        "accelerations only: the residual-force (Kalman) stage cannot determine the joint deformation (a constant residual force and its static deflection give no acceleration); the parameters come from the output-error stage started from a stiffness scan".to_string()
    } else {
        format!(
            "the residual-force stage was refused ({refused}); the parameters come from the output-error stage started from a scan of the stiffness and friction levels"
        )
    };
    result.passes.push(PassReport {
        pass: result.passes.len() + 1,
        parameters,
        fit_condition: Vec::new(),
        fit_rms_residual: Vec::new(),
        rows_used: Vec::new(),
        rows_excluded_stuck: Vec::new(),
        diagnostics: EstimatorDiagnostics {
            estimator: if accel {
                "output-error stiffness scan (accelerations only)".into()
            } else {
                "output-error scan (residual-force stage refused)".into()
            },
            sensitivity_rank: 0,
            sensitivity_condition: f64::NAN,
            sensitivity_gain: f64::NAN,
            error_spectral_radius: None,
            tuning: vec![
                ("scan_samples".into(), len as f64),
                ("scan_prefix_energy".into(), prefix_energy),
                ("scan_points".into(), points as f64),
                ("scan_normalised_cost".into(), cost),
                ("model_substeps".into(), opts.substeps as f64),
                ("start_grown_to_samples".into(), grown as f64),
                ("scan_candidates".into(), candidates_tried as f64),
            ],
            warnings: vec![why],
        },
        max_change_std_errors: None,
        max_change_force_relative: None,
        force_scales: Vec::new(),
    });
    finish_with_output_error(setup, model, data, opts, sigma, &mut result);
    // A free-run misfit that a start in motion explains (a law without `sign(u)`):
    // `identify` runs again and refuses the record with that figure
    // (`pem::motion_behind_misfit`), not with this path's words.
    if result.motion_in_record.is_some() && !has_sign_u_basis(setup) {
        return Ok(result);
    }
    accept_converged_start(setup, model, data, opts, sigma, &mut result);
    if let Some(old) = rescan_whole_record(setup, model, data, opts, sigma, &mut result) {
        grown_points.push(old);
    }
    let accepted_substeps = |r: &Identification| {
        r.output_error
            .as_ref()
            .filter(|r| r.accepted)
            .map(|r| r.substeps)
    };
    let Some(mut sub) = accepted_substeps(&result) else {
        let why = result.output_error.as_ref().map_or_else(
            || {
                // Why the stage gave no report is in its note.
                result
                    .notes
                    .iter()
                    .rev()
                    .find(|n| n.starts_with("output-error refinement"))
                    .cloned()
                    .unwrap_or_else(|| "no output-error result".to_string())
            },
            |r| {
                format!(
                    "{} (normalised cost {:.4} → {:.4})",
                    r.note, r.cost_start, r.cost_end
                )
            },
        );
        return Err(refuse(why));
    };
    let unsettled = |parameter: String, moved: f64| IdentifyError::ScanUnsettled {
        context: if accel {
            "accelerations only".into()
        } else {
            format!("after the residual-force stage was refused ({refused_note})")
        },
        parameter,
        moved,
    };
    // A probe that moved the answer far from where the descents ended: restart the
    // output-error stage from the probe's end (at the sub-steps reached) until its own
    // probe no longer moves it, up to `SETTLE_ROUNDS`; every abandoned answer joins the
    // ambiguity check below.
    let mut settled_after = Vec::new();
    while let Some((parameter, moved)) =
        probe_move(setup, &result).filter(|(_, m)| *m > MAX_SCAN_PROBE_MOVE)
    {
        if settled_after.len() == SETTLE_ROUNDS {
            return Err(unsettled(parameter, moved));
        }
        if let Some(last) = result.passes.last() {
            grown_points.push(last.parameters.iter().map(|p| p.value).collect());
        }
        let mut o = opts.clone();
        o.substeps = sub;
        finish_with_output_error(setup, model, data, &o, sigma, &mut result);
        if result.motion_in_record.is_some() && !has_sign_u_basis(setup) {
            return Ok(result);
        }
        // Its start may already be the whole-record minimum (no step lowers the cost).
        accept_converged_start(setup, model, data, &o, sigma, &mut result);
        let Some(s) = accepted_substeps(&result) else {
            return Err(unsettled(parameter, moved));
        };
        sub = s;
        settled_after.push(format!("`{parameter}` by {moved:.1} standard errors"));
    }
    if !settled_after.is_empty() {
        result.notes.push(format!(
            "the output-error stage's probe moved the answer far from where its descents ended ({}); the stage was restarted from the probe's end {} time(s) until its probe found no lower cost",
            settled_after.join(", then "),
            settled_after.len()
        ));
    }
    if !accel {
        result.notes.push(format!(
            "the residual-force stage was refused ({refused_note}); the output-error stage started from a scan of the stiffness and friction levels on the first {len} samples ({} model sub-steps) and its answer is reported",
            opts.substeps
        ));
    }
    if (accel && estimated.iter().any(|&e| e)) || has_sign_basis(setup) {
        restate_final_errors(setup, model, data, sigma, estimated, sub, &mut result);
    }
    widen_for_other_candidates(setup, model, data, sigma, &grown_points, &mut result);
    result.converged = true;
    result.stop_reason = if accel {
        "accelerations only: identified by the output-error stage from a stiffness scan".into()
    } else {
        "identified by the output-error stage from a scan (the residual-force stage was refused)"
            .into()
    };
    Ok(result)
}

/// One parameter's restated error: `restated` (the sandwich at the restated noise levels)
/// times the misfit allowance `misfit`, where the refinement's error `old` was its own
/// `core` (bound × noise allowance) times `misfit`. An `old` above that was widened to a
/// distance (to another minimum the cost cannot tell apart, or to where the probes of a
/// rough cost moved the estimate): a distance is not a noise level and stays the floor.
/// Scaling it with the restated noise (tried) shrank `v` of a misfitting record to 0.003 of
/// its distance, 85 errors off (ACCURACY.md).
fn restated_error(old: f64, core: f64, misfit: f64, restated: f64) -> f64 {
    let new = restated * misfit;
    if old > core * misfit * (1.0 + 1e-9) {
        new.max(old)
    } else {
        new
    }
}

/// Secants, in stated standard errors, over which the final errors of a law with a `sign`
/// term are taken (the larger bound wins); see [`restate_final_errors`].
const FINAL_SECANTS: [f64; 2] = [1.0, 8.0];

/// The stated errors of an output-error answer, restated once the descents, the scan and
/// the probes have chosen it (never inside them: they size their offsets and compare
/// minima in the refinement's own errors, and restating there moved the accelerometers-only
/// friction at 100 % noise to another minimum, ACCURACY.md).
///
/// 1. *Noise levels from the residuals.* The high-order-difference estimate
///    (`tuning::channel_noise_std`) reads the Nyquist-band response of a white-driven
///    structure as noise — measured 2–4e6 m/s² on *noise-free* two-beam accelerations, 5×
///    the true level at 10 % noise, and ≈ 1.7× on displacement and velocity channels of
///    continuous data — which leaves the parameters right but the errors too wide (Coulomb
///    rows at 1 % noise covered 100 %). Once the model explains the data, the per-channel
///    RMS of `y − ŷ` is the maximum-likelihood noise level (model error included, so it
///    errs wide); every channel whose level was estimated (not given as `noise_std`) is
///    re-estimated so, both ways, and the errors are the sandwich of the fit made with the
///    first levels at the restated ones (White 1980; see the body). This replaces the
///    refinement's own noise allowance (`√(cost/dof)` when above 1); the empirical misfit
///    widening (cost > 2) stays a factor, and an error widened to a distance (another minimum,
///    a rough cost) stays at least that distance.
/// 2. *Wide secants for `sign` laws.* The outputs of a sticking and slipping joint are
///    piecewise smooth in the parameters, so the cost is rough at the scale of the error
///    and a secant of ±1 error can span single jumps and give a small, consistent answer
///    (measured: Coulomb, own discretisation, 10 % noise, seed 29, friction ± 5.3 N where 50
///    seeds spread by 15 N). Each error is the larger of the bounds over secants of ±1
///    and ±8 stated errors — the rule of the prediction error (`FINAL_SECANTS`; Pakes &
///    Pollard 1989: the derivative of the expected cost, estimated with steps large against
///    the error).
/// 3. *The likelihood ratio* (`likelihood`). Both sandwiches are curvatures and say nothing
///    of the cost beyond their secants. Each error is widened to where the cost along the
///    parameter's profile line (the others refitted) first rises by 3.84 at the restated
///    levels, over 1.96, when that is beyond the stated 95 % interval. Measured (ACCURACY.md,
///    fiftieth session): 1-DOF friction at 8 sub-steps, 1 % noise, 60 seeds, 81 % covered
///    and 7.4 errors at worst became 96 % and 4.7; Coulomb rows 93–98 % → 95–100 %, worst
///    3.3 → 3.0. The ±8 secant stays: without it (the likelihood ratio alone on the ±1
///    sandwich) the accelerometers-only Coulomb rows at 100 % noise fell from 87 / 83 % to
///    82 / 80 %, the ±8 secant's span reaching the neighbouring valleys of that multimodal
///    cost that a profile walked from the answer stops short of.
#[allow(clippy::too_many_arguments)]
#[allow(non_snake_case)]
pub(super) fn restate_final_errors(
    setup: &Setup,
    model: &Model,
    data: &TestData,
    sigma: &[f64],
    estimated: &[bool],
    substeps: usize,
    result: &mut Identification,
) {
    use crate::estimate::output_error::{crlb_from_fisher, scaled_inverse, sensitivities};
    use nalgebra::DMatrix;
    let sign_law = has_sign_basis(setup);
    let Some(report) = result.output_error.as_ref() else {
        return;
    };
    if !report.accepted || report.prediction_error.is_some() {
        return;
    }
    let cost_end = report.cost_end;
    let Some(last) = result.passes.last_mut() else {
        return;
    };
    let values: Vec<f64> = last.parameters.iter().map(|p| p.value).collect();
    let scales: Vec<f64> = last.parameters.iter().map(|p| p.std_error).collect();
    let secants: &[f64] = if sign_law { &FINAL_SECANTS } else { &[1.0] };
    // The sensitivities at every secant, at the noise levels the estimate was fitted with;
    // the first run's residuals give the restated noise levels.
    let runs: Vec<_> = secants
        .iter()
        .filter_map(|&w| {
            let at: Vec<f64> = scales.iter().map(|s| w * s).collect();
            sensitivities(
                setup,
                model,
                &values,
                &at,
                &data.excitation,
                &data.response,
                sigma,
                substeps,
            )
            .ok()
        })
        .collect();
    let Some(r) = runs.first().map(|x| &x.residual) else {
        return;
    };
    let m = sigma.len();
    let rows = (r.len() / m.max(1)).max(1) as f64;
    let refit: Vec<f64> = (0..m)
        .map(|k| {
            if !estimated[k] {
                // The setup's `noise_std` stands.
                return sigma[k];
            }
            let ms = r.iter().skip(k).step_by(m).map(|x| x * x).sum::<f64>() / rows;
            // Floor as for the difference estimate (noise-free data of the model's own
            // discretisation leave round-off only).
            let y_rms = (data.response.iter().map(|y| y[k] * y[k]).sum::<f64>() / rows).sqrt();
            (sigma[k] * ms.sqrt()).max(crate::estimate::tuning::NOISE_FLOOR_RELATIVE * y_rms)
        })
        .collect();
    if refit.iter().any(|s| !(s.is_finite() && *s > 0.0)) {
        return;
    }
    // Per channel, the residuals' variance in units of the noise level the estimate was
    // fitted with: the estimate minimised the cost weighted by `sigma`, so its covariance
    // is the sandwich `A⁻¹ B A⁻¹`, `A = Σ_k J_kᵀJ_k`, `B = Σ_k s_k² J_kᵀJ_k` (normalised
    // columns, `s_k = refit_k/σ_k`); the Cramér–Rao bound at the refitted levels is
    // `(Σ_k J_kᵀJ_k / s_k²)^{-1/2}`.
    let s2: Vec<f64> = refit
        .iter()
        .zip(sigma)
        .map(|(r, s)| (r / s).powi(2))
        .collect();
    let np = values.len();
    let mut bound: Option<Vec<f64>> = None;
    let mut widest: Option<Vec<f64>> = None;
    let mut per_secant: Vec<Vec<f64>> = Vec::with_capacity(runs.len());
    // The first secant's Fisher information at the restated levels (`likelihood`).
    let mut fisher: Option<DMatrix<f64>> = None;
    for sens in &runs {
        let mut A = DMatrix::<f64>::zeros(np, np);
        let mut B = DMatrix::<f64>::zeros(np, np);
        let mut F = DMatrix::<f64>::zeros(np, np);
        for (k, &s2k) in s2.iter().enumerate() {
            let G = DMatrix::from_fn(np, np, |a, b| {
                sens.columns[a]
                    .iter()
                    .skip(k)
                    .step_by(m)
                    .zip(sens.columns[b].iter().skip(k).step_by(m))
                    .map(|(x, y)| x * y)
                    .sum::<f64>()
            });
            A += &G;
            B += &G * s2k;
            F += &G / s2k;
        }
        let Some(inv) = scaled_inverse(&A) else {
            continue;
        };
        let cov = &inv * &B * &inv;
        let e: Vec<f64> = (0..np).map(|j| cov[(j, j)].max(0.0).sqrt()).collect();
        if !e.iter().all(|x| x.is_finite()) {
            continue;
        }
        per_secant.push(e.clone());
        widest = Some(match widest {
            Some(x) => x.iter().zip(&e).map(|(a, c)| a.max(*c)).collect(),
            None => e,
        });
        if bound.is_none() {
            bound = crlb_from_fisher(&F);
            fisher = Some(F);
        }
    }
    let (Some(bound), Some(widest)) = (bound, widest) else {
        return;
    };
    // The refinement's errors: its bound at the first noise levels, raised by the
    // residuals' level when that was above 1 (`output_error::refine`).
    let nobs = rows * m as f64;
    let dof = (nobs - values.len() as f64).max(1.0);
    let level = (cost_end * nobs / dof).max(1.0).sqrt();
    // …and widened by the empirical misfit allowance when the cost is above 2
    // (`finish_with_output_error`), which stays.
    let misfit = if cost_end > 2.0 { cost_end.sqrt() } else { 1.0 };
    let mut ratios = Vec::with_capacity(values.len());
    for ((p, b), w) in last.parameters.iter_mut().zip(&bound).zip(&widest) {
        let core = p.crlb.unwrap_or(*b) * level;
        if !(core > 0.0 && core.is_finite()) {
            ratios.push(1.0);
            continue;
        }
        ratios.push(w / core);
        p.std_error = restated_error(p.std_error, core, misfit, *w);
        p.ci95 = [p.value - 1.96 * p.std_error, p.value + 1.96 * p.std_error];
        p.crlb = Some(*b);
    }
    // 3. The likelihood ratio: each error at least the distance at which the cost rises
    //    by 3.84 along its profile line, or at which it was found inside that region on
    //    another parameter's line, over 1.96 (`likelihood`).
    let checked = match fisher {
        Some(F) => {
            let errors: Vec<f64> = last.parameters.iter().map(|p| p.std_error).collect();
            super::likelihood::intervals(
                setup,
                model,
                data,
                (&values, &errors),
                &F,
                &refit,
                substeps,
            )
        }
        None => Err("the sensitivities gave no Fisher information".to_string()),
    };
    let likelihood_words = match &checked {
        Err(why) => format!("; not checked by the likelihood ratio ({why})"),
        Ok(intervals) => {
            let mut widths = Vec::with_capacity(intervals.len());
            let (mut widened, mut undetermined, mut unchecked, mut lower) =
                (Vec::new(), Vec::new(), Vec::new(), Vec::new());
            for (p, i) in last.parameters.iter_mut().zip(intervals) {
                let Some(i) = i else {
                    unchecked.push(format!("`{}`", p.basis));
                    widths.push(None);
                    continue;
                };
                let e = i.error(p.std_error);
                widths.push(Some(i.widening()));
                if i.lowest() < -1.0 {
                    lower.push(format!("`{}` (Δχ² = {:.1})", p.basis, -i.lowest()));
                }
                if !i.reached() {
                    undetermined.push(format!("`{}`", p.basis));
                }
                if e > p.std_error * super::likelihood::WIDEN_TOLERANCE {
                    widened.push(format!(
                        "`{}` {:.2}×{}",
                        p.basis,
                        e / p.std_error,
                        if i.reached_from_elsewhere() {
                            ", to a value it takes inside the region on another parameter's line"
                        } else {
                            ""
                        }
                    ));
                    p.std_error = e;
                    p.ci95 = [p.value - 1.96 * p.std_error, p.value + 1.96 * p.std_error];
                }
            }
            if let Some(report) = result.output_error.as_mut() {
                report.likelihood_ratio_widths = Some(widths);
            }
            if !undetermined.is_empty() {
                result.notes.push(format!(
                    "the output-error cost does not rise by 3.84 within {:.1} of the former standard errors along the profile line of {}: the record does not determine {}; the 95 % interval is set to that distance, a lower limit",
                    super::likelihood::FARTHEST,
                    undetermined.join(", "),
                    if undetermined.len() == 1 { "it" } else { "them" }
                ));
            }
            if !lower.is_empty() {
                result.notes.push(format!(
                    "the likelihood-ratio check met a cost lower than the answer's on the profile line of {} (at the restated noise levels, which the answer was not fitted with): those errors are widened to reach past it",
                    lower.join(", ")
                ));
            }
            let mut words = if widened.is_empty() {
                "; each held by the likelihood ratio (the cost along its profile line rises by 3.84, χ²₁ 95 %, within the stated 95 % interval)".to_string()
            } else {
                format!(
                    "; widened where the cost along a parameter's profile line rises by 3.84 (χ²₁ 95 %) only beyond the stated 95 % interval, to that distance over 1.96 ({}): the cost is flatter there than its curvature at the answer",
                    widened.join(", ")
                )
            };
            if !unchecked.is_empty() {
                words += &format!(
                    "; {} not checked (no finite error or information)",
                    unchecked.join(", ")
                );
            }
            words
        }
    };
    let restated = estimated.iter().any(|&e| e);
    if restated {
        for (sensor, (s0, s1)) in setup.sensors.iter().zip(sigma.iter().zip(&refit)) {
            last.diagnostics
                .tuning
                .push((format!("noise_std_differences[{}]", sensor.name), *s0));
            last.diagnostics
                .tuning
                .push((format!("noise_std_output_error[{}]", sensor.name), *s1));
        }
    }
    let noise_words = if restated {
        format!(
            "noise levels re-estimated from the output-error residuals ({substeps} model sub-steps), {:.3}–{:.3}× the high-order-difference estimate",
            sigma
                .iter()
                .zip(&refit)
                .map(|(a, b)| b / a)
                .fold(f64::INFINITY, f64::min),
            sigma
                .iter()
                .zip(&refit)
                .map(|(a, b)| b / a)
                .fold(0.0, f64::max),
        )
    } else {
        "noise levels as given (`noise_std`)".to_string()
    };
    if sign_law {
        let disagreement = secant_disagreement(&per_secant);
        if let Some(report) = result.output_error.as_mut() {
            report.secant_disagreement = disagreement;
        }
        result.notes.push(format!(
            "final standard errors: {noise_words}; the sandwich of the fit at those levels, for the `sign` law the larger over secants of ±1 and ±8 standard errors (× {} the refinement's own{}){likelihood_words}",
            ratios
                .iter()
                .map(|x| format!("{x:.2}"))
                .collect::<Vec<_>>()
                .join(", "),
            disagreement
                .map(|d| if d > 1e3 {
                    // One secant's sandwich all but vanished, and the ratio is no figure
                    // to read (seen: 2.4e60 on a 1-DOF record at 100 % noise, seed 9323).
                    "; the two secants' differ more than 1,000×".to_string()
                } else {
                    format!("; the two secants' differ up to {d:.2}×")
                })
                .unwrap_or_default()
        ));
    } else {
        result.notes.push(format!(
            "accelerations only: {noise_words}; standard errors (the sandwich of the fit at those levels) and bounds restated with them{likelihood_words}"
        ));
    }
}

/// The largest ratio (either way) between the errors of two secants' sandwiches, over the
/// parameters: 1 when the cost is linear in the parameters over the wider secant. `None`
/// unless both secants gave errors; a ratio that is not finite (an error of 0) is skipped.
fn secant_disagreement(per_secant: &[Vec<f64>]) -> Option<f64> {
    let (Some(a), Some(b)) = (per_secant.first(), per_secant.get(1)) else {
        return None;
    };
    Some(
        a.iter()
            .zip(b)
            .map(|(x, y)| (x / y).max(y / x))
            .filter(|r| r.is_finite())
            .fold(1.0f64, f64::max),
    )
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The secants' disagreement is the largest ratio either way over the parameters, none
    /// for a single secant, and a ratio that is not finite (an error of 0) counts for nothing.
    #[test]
    fn secant_disagreement_is_the_largest_ratio_either_way() {
        assert_eq!(secant_disagreement(&[vec![1.0, 2.0]]), None);
        let d = secant_disagreement(&[vec![1.0, 2.0, 0.0, 0.0], vec![1.5, 1.0, 0.0, 3.0]]);
        assert_eq!(d, Some(2.0));
        assert_eq!(secant_disagreement(&[vec![4.0], vec![1.0]]), Some(4.0));
    }

    /// The refinement's own error (bound × noise allowance × misfit allowance) is replaced
    /// by the restated one both ways, keeping the misfit allowance; an error widened to a
    /// distance stays at least that distance (it had been scaled to 0.003 of it).
    #[test]
    fn restated_errors_replace_noise_levels_and_keep_distances() {
        // Own error (core 2 × misfit 3 = 6): replaced, down or up.
        assert_eq!(restated_error(6.0, 2.0, 3.0, 0.5), 1.5);
        assert_eq!(restated_error(6.0, 2.0, 3.0, 4.0), 12.0);
        // Widened to a distance of 40: kept when the restated error is smaller…
        assert_eq!(restated_error(40.0, 2.0, 3.0, 0.01), 40.0);
        // …and the restated error wins when it is larger.
        assert_eq!(restated_error(40.0, 2.0, 3.0, 20.0), 60.0);
    }

    /// Two channels (noise σ = 1 and 2) of constant amplitude `level` and `2 level`: each
    /// sample holds `2 (level² − 1)` noise units of signal energy.
    fn constant_record(n: usize, level: f64) -> TestData {
        TestData {
            samples: (0..n as u64).collect(),
            t_ns: vec![0; n],
            excitation: vec![vec![0.0]; n],
            response: vec![vec![level, -2.0 * level]; n],
        }
    }

    /// The prefix doubles until it holds `SCAN_PREFIX_ENERGY` noise units of signal, for a
    /// linear law only, and never beyond the record.
    #[test]
    fn scan_prefix_doubles_until_the_signal_energy_suffices() {
        let sigma = [1.0, 2.0];
        // 0.3 per sample: 60 at 200 samples, 120 at 400.
        let d = constant_record(20_000, 1.15f64.sqrt());
        let (n, e) = scan_prefix(&d, &sigma, true);
        assert_eq!(n, 400);
        assert!((e - 120.0).abs() < 1e-6, "{e}");
        // 0.1 per sample: 20, 40, 80, then 160 at 1,600.
        let d = constant_record(20_000, 1.05f64.sqrt());
        assert_eq!(scan_prefix(&d, &sigma, true).0, 1_600);
        // A non-linear law keeps 200 samples.
        assert_eq!(scan_prefix(&d, &sigma, false).0, ACCEL_SCAN_SAMPLES);
        // Enough at once: 200 samples.
        let d = constant_record(20_000, 2.0);
        assert_eq!(scan_prefix(&d, &sigma, true).0, ACCEL_SCAN_SAMPLES);
        // No signal above the noise: the whole record, never more.
        let d = constant_record(5_000, 0.5);
        assert_eq!(scan_prefix(&d, &sigma, true).0, 5_000);
        // A record shorter than 200 samples is scanned whole.
        let d = constant_record(150, 3.0);
        assert_eq!(scan_prefix(&d, &sigma, true).0, 150);
    }
}
