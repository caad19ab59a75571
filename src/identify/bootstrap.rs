//! The parametric bootstrap of a free-run output-error answer, when asked for
//! (`--bootstrap N`, `IdentifyOptions::bootstrap`), and by itself for a friction law whose
//! sensors' noise levels the setup gives ([`given_levels_sharpen_a_friction`]).
//!
//! Why: the free-run output-error cost of a law not linear in the state is rough — for a
//! friction, a zero crossing that moves by a sub-step flips its force for that sub-step —
//! and a descent over it can stop in a local minimum a few of its errors from the one the
//! truth sits in, at a cost no higher. The stated error is a sandwich, a local
//! linearisation about the minimum found, and sees neither the ripples nor the path the
//! descent took. The replicates are simulated from the answer and identified again by the
//! whole procedure (passes, free run, sub-step raise), so their spread includes the minima
//! the procedure stops in, wherever it stops.
//!
//! Why only when asked (the prediction error's runs by itself on its occasions,
//! `pem::bootstrap_occasion`): measured on the 1-DOF setup and Coulomb (ACCURACY.md,
//! thirty-ninth session), the prediction error's trigger — the final errors' sandwiches over
//! secants of ±1 and ±8 errors differing by more than 1.2× — fired on 80 % and 68 % of the
//! records, the misses among them no more than the answers that hold; run on every 1-DOF
//! record it raised coverage at 1 % noise from 73 to 86 % and 76 to 82 % at ~20× the time,
//! and the misses were mostly bias, which the sub-step rule of `raise_substeps` since
//! removes.

use super::pem::{noisy_replicate, replicates_report, student_t_975};
use super::{Identification, IdentifyOptions, TestData, identify};
use crate::estimate::prediction_error::BootstrapReport;
use crate::model::Model;
use crate::setup::Setup;

/// Bootstrap the free run's answer in `result` (identified from `data` with `opts`) when
/// asked: `replicates` records of the model at the answer's values and model sub-steps,
/// driven by the record's excitation from rest, each with white noise at the level of the
/// answer's residuals per channel, identified again with `opts` (the bootstrap off). Their spread, stated as a
/// Student's t interval of that many replicates, is a floor under each error; their mean
/// shift from the answer is reported, not subtracted (ten replicates estimate it to a third
/// of the spread, and over a rough cost it is the path's, not a smooth bias). Nothing
/// happens to an answer that is not the free run's (the prediction error has its own,
/// `pem::bootstrap`) or that it did not accept.
pub(super) fn free_run_bootstrap(
    setup: &Setup,
    data: &TestData,
    opts: &IdentifyOptions,
    result: &mut Identification,
) {
    let Some(report) = result.output_error.as_ref() else {
        return;
    };
    if report.prediction_error.is_some() || !report.accepted {
        return;
    }
    let automatic = opts.bootstrap.is_none() && given_levels_sharpen_a_friction(setup);
    let replicates = match opts.bootstrap {
        Some(n) => n,
        None if automatic => super::pem::AUTO_BOOTSTRAP_REPLICATES,
        None => 0,
    };
    if replicates == 0 {
        return;
    }
    let substeps = report.substeps;
    let Some(last) = result.passes.last() else {
        return;
    };
    let values: Vec<f64> = last.parameters.iter().map(|p| p.value).collect();
    if result.initial_state.is_some() {
        // (The free run answers only records at rest: one in motion is refined by the
        // prediction error, whose bootstrap starts from the refined start state.)
        result.notes.push(
            "parametric bootstrap of the free run not run: the record starts in motion".into(),
        );
        return;
    }
    let t0 = std::time::Instant::now();
    // Simulated with the excitation the answer was fitted with (smooth between samples or
    // not, `identify::smooth_between_samples`); each replicate decides that again.
    let fitted = super::as_fitted(data, result).excitation.clone();
    let boot =
        replicate(setup, data, &fitted, opts, &values, substeps, replicates).unwrap_or_else(|e| {
            BootstrapReport {
                replicates,
                used: 0,
                noise: Vec::new(),
                shift: Vec::new(),
                spread: Vec::new(),
                failure: Some(e),
            }
        });
    crate::par::phase("free-run bootstrap", t0);
    let why = if automatic {
        "automatic: the setup gives sensors' noise levels (`noise_std`) and the law has a friction (`sign`) term, where the sandwich and likelihood-ratio errors were measured to cover 44–56 % of the truths; `--bootstrap 0` switches it off".to_string()
    } else {
        format!("{replicates} replicates asked for")
    };
    let Some(last) = result.passes.last_mut() else {
        return;
    };
    if let Some(failure) = &boot.failure {
        result.notes.push(format!(
            "parametric bootstrap of the free run ({why}) not run: {failure}; the stated errors are the sandwich's"
        ));
    } else if boot.used < 2 || boot.used * 2 < boot.replicates {
        result.notes.push(format!(
            "parametric bootstrap of the free run ({why}): only {} of {} replicates were identified; the stated errors are the sandwich's",
            boot.used, boot.replicates
        ));
    } else {
        let t_ratio = student_t_975(boot.used.saturating_sub(1)) / 1.959_964;
        let mut words = Vec::with_capacity(values.len());
        for ((p, sp), sh) in last
            .parameters
            .iter_mut()
            .zip(&boot.spread)
            .zip(&boot.shift)
        {
            let floor = sp * t_ratio;
            words.push(format!(
                "`{}` spread {sp:.3e} ({:.2}× its sandwich error), shift {sh:+.3e}",
                p.basis,
                sp / p.std_error
            ));
            if floor > p.std_error {
                p.std_error = floor;
                p.ci95 = [p.value - 1.96 * p.std_error, p.value + 1.96 * p.std_error];
            }
        }
        result.notes.push(format!(
            "parametric bootstrap of the free run ({why}): {} of {} records simulated from the answer ({substeps} model sub-steps, noise at the residuals' level per channel) and identified again as this one was: {}; each error is at least the spread (Student's t interval of {} replicates)",
            boot.used,
            boot.replicates,
            words.join("; "),
            boot.used
        ));
    }
    if let Some(report) = result.output_error.as_mut() {
        report.bootstrap = Some(boot);
    }
}

/// Whether the setup gives any sensor's noise level for a law with a friction (`sign`)
/// term: the free-run answer is then bootstrapped by itself.
///
/// Why: the estimated noise level of a channel is the high-order-difference estimate, an
/// upper bound that overstates a channel seeing the excitation directly (an accelerometer
/// under a random force: 77×, ACCURACY.md, fifty-first session), and that weighting
/// smooths the free run's rough friction cost. Given the sensors' real levels, the cost is
/// the sharp likelihood, whose minima lie closer together than its curvature says:
/// 1-DOF friction, 1 % noise, levels given, 64-sub-step data 44 % covered (worst 47
/// errors; the truth's cost below the answer's on every record probed), 8-sub-step data
/// 56 % (55); with the bootstrap 92 % (6.0). The same records with the levels estimated
/// cover 96–100 %, and the Coulomb setup with its levels given 100 % without it, so it is
/// not run for every free-run answer (a Coulomb record takes 4–7 s instead of about 0.5).
pub(super) fn given_levels_sharpen_a_friction(setup: &Setup) -> bool {
    super::scan::has_sign_basis(setup) && setup.sensors.iter().any(|s| s.noise_std.is_some())
}

/// The replicates of [`free_run_bootstrap`] and what their answers spread by.
fn replicate(
    setup: &Setup,
    data: &TestData,
    fitted_excitation: &[Vec<f64>],
    opts: &IdentifyOptions,
    values: &[f64],
    substeps: usize,
    replicates: usize,
) -> Result<BootstrapReport, String> {
    let model = Model::for_identification(setup).map_err(|e| e.to_string())?;
    let free = crate::simulate::response_to_excitation(
        setup,
        &model,
        values,
        fitted_excitation,
        setup.dt_s,
        substeps,
    )
    .map_err(|e| format!("the free run of the answer failed: {e}"))?;
    let n = free.len().min(data.response.len());
    let m = data.response.first().map_or(0, Vec::len);
    // The residuals' RMS per channel (the answer's misfit is the noise it leaves), floored as
    // the noise estimate is (noise-free data leave round-off only).
    let noise: Vec<f64> = (0..m)
        .map(|k| {
            let mean_square = |f: &dyn Fn(usize) -> f64| {
                (0..n).map(|i| f(i).powi(2)).sum::<f64>() / n.max(1) as f64
            };
            let misfit = mean_square(&|i| data.response[i][k] - free[i][k]).sqrt();
            let rms = mean_square(&|i| data.response[i][k]).sqrt();
            misfit.max(crate::estimate::tuning::noise_floor(rms))
        })
        .collect();
    let again = IdentifyOptions {
        bootstrap: Some(0),
        ..opts.clone()
    };
    let seeds: Vec<u64> = (0..replicates as u64).collect();
    let answers: Vec<Option<Vec<f64>>> = crate::par::map(&seeds, |&b| {
        let response = noisy_replicate(&free[..n], &noise, b);
        let record = TestData {
            samples: data.samples[..n].to_vec(),
            t_ns: data.t_ns[..n].to_vec(),
            excitation: data.excitation[..n].to_vec(),
            response,
        };
        let id = identify(setup, &record, &again, None, &mut |_| {}, &mut |_, _| {}).ok()?;
        let got: Vec<f64> = id
            .passes
            .last()?
            .parameters
            .iter()
            .map(|p| p.value)
            .collect();
        (got.len() == values.len() && got.iter().all(|x| x.is_finite())).then_some(got)
    });
    let got: Vec<Vec<f64>> = answers.into_iter().flatten().collect();
    Ok(replicates_report(replicates, noise, &got, values))
}
