//! The Kalman filter's tuning for a pass: the force random walk, the model-error std and a
//! common scale of the channels' noise levels, chosen by the filter's innovation likelihood
//! over (a prefix of) the record, and re-searched around the previous pass's tuning
//! (`tune_kalman`). Moved out of `identify` whole; the reasons for each choice are with the
//! constants and in ACCURACY.md.

use super::*;

/// Kalman tuning chosen for one pass.
#[derive(Debug, Clone)]
pub struct KalmanTuning {
    pub force_walk_std: f64,
    pub model_error_std: f64,
    pub noise_scale: f64,
    /// Channel noise levels after scaling.
    pub sigma: Vec<f64>,
    pub log_likelihood: f64,
    pub runs: usize,
    /// The model-error std was taken by the likelihood (not the default nor given).
    pub model_error_taken: bool,
}

/// A filter-only Kalman run over (a prefix of) the data, for its innovation log-likelihood
/// (plain, or concentrated over a common scale of the noise covariances); `None` when the
/// filter cannot be built or diverges.
#[allow(clippy::too_many_arguments)]
fn kalman_filter_run(
    setup: &Setup,
    with_terms: &Model,
    params: &[f64],
    opts: &IdentifyOptions,
    sigma: &[f64],
    data: &TestData,
    walk: f64,
    model_error: f64,
) -> Option<crate::estimate::kalman::KalmanEstimator> {
    use crate::estimate::kalman::{KalmanEstimator, KalmanOptions};
    let inputs = EstimatorInputs {
        model: with_terms,
        law: ConnectionLaw::new(setup, params),
        dt_s: setup.dt_s,
        substeps: opts.substeps,
        newmark: setup.newmark,
        weighting: opts.weighting,
        channel_sigma: sigma.to_vec(),
        spectral_diagnostics: false,
    };
    let len = if opts.tune_samples > 0 {
        data.len().min(opts.tune_samples)
    } else {
        data.len()
    };
    let ko = KalmanOptions {
        force_walk_std: walk,
        model_error_std: model_error,
        smooth: false,
        semi_implicit: opts.semi_implicit,
        likelihood_only: true,
        horizon: Some(len),
    };
    let mut est = KalmanEstimator::with_options(inputs, ko, 0).ok()?;
    if let Some(x) = &opts.initial_state {
        est.set_initial_state(x);
    }
    let mut out = StepOutput::new(setup.connections.len());
    est.start(data.samples[0], &data.excitation[0]);
    for i in 1..len {
        est.step(
            data.samples[i],
            &data.excitation[i],
            &data.response[i],
            &mut out,
        )
        .ok()?;
    }
    Some(est)
}

/// Samples on which the Kalman tuning's likelihood is evaluated (a prefix of longer records):
/// the random-walk std and the noise scale are properties of the model's error and of the
/// sensors, the same along a stationary record, and 10,000 samples (a live window) fix them
/// well inside the precision the passes need. Why: each tuning runs the filter ~56 times;
/// on a 100,000-sample record the two tunings were a third of the identification's time.
/// The passes themselves, the parameters and their errors use the whole record.
pub const TUNE_SAMPLES: usize = 10_000;

/// Half-width, in decades, of a re-tune's search of the random-walk std around the previous
/// tuning's (a 1-decade grid of 7 points, then Brent). Measured between the first two
/// tunings of the shipped friction replay: 3.1e4 → 978 N (1.5 decades); the noise scale the
/// same to 1e-4.
pub const RETUNE_WALK_DECADES: f64 = 3.0;

/// Range of the common scale of the estimated noise levels the tuning admits (the noise
/// levels from the data's differences can be too high, not by more than 10×, and too low by
/// far on noise-free data, whose levels sit at their floor). The scale is further bounded
/// below so that no estimated channel's level falls under its floor
/// ([`crate::estimate::tuning::NOISE_FLOOR_RELATIVE`] of the channel's RMS; see
/// [`noise_scale_range`]).
const NOISE_SCALE_RANGE: (f64, f64) = (1e-8, 1e1);

/// [`NOISE_SCALE_RANGE`] for this record: its lower end raised so that the scaled level of
/// every estimated channel stays at or above that channel's floor
/// (`NOISE_FLOOR_RELATIVE` × its RMS), the level below which the filter's innovation
/// covariance loses positive definiteness in round-off.
///
/// Why (thirty-first session): on noise-free data the levels sit at their floor and the
/// tuning scaled them down further (the concentrated scale, ~0.1 and below); the pass's
/// innovation covariance then had an eigenvalue of −5e-20 against a largest of 6e-3, its
/// Cholesky factor failed, and the record was refused with "rank(S) = 0" (friction setup,
/// noise-free own-discretisation data, 2,000 samples, seed 7207) where the 1989 estimator
/// answers it exactly.
fn noise_scale_range(sigma: &[f64], estimated: &[bool], data: &TestData) -> (f64, f64) {
    let m = sigma.len();
    let mut sum_sq = vec![0.0f64; m];
    for y in &data.response {
        for (a, v) in sum_sq.iter_mut().zip(y) {
            *a += v * v;
        }
    }
    let n = data.response.len().max(1) as f64;
    let lowest = sigma
        .iter()
        .zip(estimated)
        .zip(&sum_sq)
        .filter(|((s, e), _)| **e && **s > 0.0)
        .map(|((s, _), ss)| crate::estimate::tuning::noise_floor((ss / n).sqrt()) / s)
        .filter(|x| x.is_finite())
        .fold(NOISE_SCALE_RANGE.0, f64::max);
    (lowest.min(NOISE_SCALE_RANGE.1), NOISE_SCALE_RANGE.1)
}

/// Range, in decades of the force scale, of the first tuning's search of the random-walk
/// std per unit noise scale when the scale is concentrated out (a grid of one point per
/// decade, then Brent). Why this wide: the coordinate search it replaces reached the walk
/// over 1e-6…1e2 of the force scale at noise scales 1e-8…1e1 and ±30× around; the ratio
/// of the two spans more than either — a noise level overestimated by the data's
/// differences puts it above 1e2 (measured on the benchmark record: 6.7 at noise scale
/// 4.6, 1.6e5 N per unit scale, the scale 1.75e3 N).
const CONCENTRATED_WALK_DECADES: (f64, f64) = (-6.0, 4.0);

/// Log-likelihood gain of a re-tune's noise scale or model-error std above which σ_R is
/// searched again at it (half of the 95 % point of χ²₁, 3.84: a smaller gain is no evidence
/// the other tunings moved, and σ_R's optimum with them moves less than its tolerance).
const RETUNE_SIGNIFICANT_GAIN: f64 = 1.92;

/// Choose the Kalman estimator's random-walk std σ_R (and, when `opts.tune_noise_scale`, a
/// common scale of the estimated channel noise levels) by maximising the innovation
/// likelihood of filter-only runs.
///
/// When every channel's noise level is estimated (the default) and the model-error std is
/// neither given nor tuned, the common scale is concentrated out exactly: scaling every
/// noise covariance by λ leaves the filter's gain and innovations unchanged, so the
/// likelihood's maximum over λ is closed-form
/// ([`crate::estimate::kalman::KalmanEstimator::concentrated_log_likelihood`]) and one
/// search remains, of σ_R per unit scale over [`CONCENTRATED_WALK_DECADES`] of the force
/// scale (a re-tune: ± [`RETUNE_WALK_DECADES`] around the previous ratio); σ_R, the noise
/// scale and the model-error std are then the ratio's values times `√λ̂`. Why: the
/// coordinate search below (σ_R, then the scale, then σ_R again) came near the same joint
/// maximum in 41 filter runs at the first tuning and 24 at a re-tune; this reaches it in 17
/// and 15 (measured on the benchmark record: σ_R 30,980 vs 30,988 N, scale 4.618 vs 4.635,
/// log-likelihood −55,505.07 vs −55,505.38; BENCHMARKS.md and ACCURACY.md, thirtieth
/// session).
///
/// Otherwise (a channel's noise level given, or the model-error std tuned): σ_R over a log
/// grid of 1e-6…1e2 × the force scale with Brent's method
/// ([`crate::estimate::tuning::maximise_log`]), then the noise scale over the record's
/// range ([`noise_scale_range`]: 1e-8…1e1, its lower end raised to keep every estimated
/// channel at or above its floor), then σ_R again around the new optimum.
///
/// `previous`: a tuning made at earlier parameters of the same record (the passes re-tune at
/// each pass's answer until they settle). The search then starts from it: σ_R over
/// ± [`RETUNE_WALK_DECADES`], the noise scale and a model-error std the previous tuning
/// took over ± 30× (each a 5-point grid), σ_R again ± 30× when either moved; a model-error
/// std the previous tuning did not take (its likelihood was no better with one) is not
/// searched again. Why: the noise scale is a property of the sensors and σ_R of the
/// model's distance from the data, which the pass before has only narrowed; the full
/// search (41–45 filter runs) was the second tuning's cost again, a sixth of a
/// 2,000-sample identification (BENCHMARKS.md, twenty-fourth session).
#[allow(clippy::too_many_arguments)]
pub fn tune_kalman(
    setup: &Setup,
    model: &Model,
    params: &[f64],
    opts: &IdentifyOptions,
    sigma: &[f64],
    estimated: &[bool],
    data: &TestData,
    previous: Option<&KalmanTuning>,
) -> Result<KalmanTuning, EstimateError> {
    use crate::estimate::tuning::maximise_log_parallel as maximise_log;
    let with_terms = model.with_connection_terms(setup, params);
    let scale = crate::estimate::kalman::force_scale_of(&with_terms);
    let mut model_error = opts
        .model_error_std
        .unwrap_or(crate::estimate::kalman::MODEL_ERROR_RELATIVE * scale);
    let mut runs = 0;
    let scaled = |s: f64| -> Vec<f64> {
        sigma
            .iter()
            .zip(estimated)
            .map(|(x, e)| if *e { x * s } else { *x })
            .collect()
    };
    // The innovation log-likelihood at a noise scale, random-walk std and model-error std
    // (the searches come back to points they have run: remembered).
    let remembered = crate::estimate::tuning::Remembered::default();
    let likelihood = |s: f64, w: f64, e: f64| {
        remembered.value(&[s, w, e], || {
            kalman_filter_run(setup, &with_terms, params, opts, &scaled(s), data, w, e)
                .map_or(f64::NEG_INFINITY, |est| est.log_likelihood())
        })
    };
    let tunes_scale = opts.tune_noise_scale && estimated.iter().any(|&e| e);
    let (lo_scale, hi_scale) = noise_scale_range(sigma, estimated, data);
    // Every noise level free to scale (every channel's estimated, the model-error std the
    // small default): the common scale is concentrated out exactly (see
    // [`CONCENTRATED_WALK_DECADES`]) and one search of the walk's ratio to it remains.
    if tunes_scale
        && estimated.iter().all(|&e| e)
        && opts.model_error_std.is_none()
        && !opts.tune_model_error
    {
        let remembered = crate::estimate::tuning::Remembered::<(f64, f64)>::default();
        let concentrated = |w: f64| {
            remembered.value(&[w], || {
                kalman_filter_run(
                    setup,
                    &with_terms,
                    params,
                    opts,
                    sigma,
                    data,
                    w,
                    model_error,
                )
                .map_or((f64::NEG_INFINITY, f64::NAN), |est| {
                    est.concentrated_log_likelihood()
                })
            })
        };
        let (lo, hi, grid) = match previous {
            Some(prev) => {
                let reach = 10f64.powf(RETUNE_WALK_DECADES);
                let w0 = prev.force_walk_std / prev.noise_scale;
                (
                    w0 / reach,
                    w0 * reach,
                    2 * RETUNE_WALK_DECADES.round() as usize + 1,
                )
            }
            None => (
                10f64.powf(CONCENTRATED_WALK_DECADES.0) * scale,
                10f64.powf(CONCENTRATED_WALK_DECADES.1) * scale,
                (CONCENTRATED_WALK_DECADES.1 - CONCENTRATED_WALK_DECADES.0).round() as usize + 1,
            ),
        };
        let (ratio, ll, concentrated_runs) = maximise_log(lo, hi, grid, 12, &|w| concentrated(w).0);
        runs += concentrated_runs;
        let noise_scale = concentrated(ratio).1.sqrt();
        // Taken when the scale lies in the range the coordinate search admits; outside it
        // the constrained maximum is on that range's bound, which the closed form does not
        // give, and the coordinate search below runs. Measured (noise-free spring data,
        // `tests/import_and_plots.rs`): the re-tune's scale fell below 1e-8, and clamped
        // with the walk's ratio kept (1e9) the third pass diverged.
        if ll.is_finite() && (lo_scale..=hi_scale).contains(&noise_scale) {
            return Ok(KalmanTuning {
                model_error_std: model_error * noise_scale,
                force_walk_std: ratio * noise_scale,
                noise_scale,
                sigma: scaled(noise_scale),
                log_likelihood: ll,
                runs,
                model_error_taken: false,
            });
        }
    }
    // A search within a factor of 30 either way of a value already found (half-decade grid of
    // five points, then at most `refine` steps of Brent's method).
    let around = |x: f64, refine: usize, f: &(dyn Fn(f64) -> f64 + Sync)| {
        maximise_log(x / 30.0, x * 30.0, 5, refine, f)
    };
    // The same for the noise scale, within its range.
    let around_scale = |x: f64, refine: usize, f: &(dyn Fn(f64) -> f64 + Sync)| {
        maximise_log(
            (x / 30.0).max(lo_scale),
            (x * 30.0).min(hi_scale).max(lo_scale),
            5,
            refine,
            f,
        )
    };
    if let Some(prev) = previous {
        // (A tuning made on a long record's prefix has that prefix's range.)
        let mut noise_scale = prev.noise_scale.clamp(lo_scale, hi_scale);
        let error_taken = opts.model_error_std.is_none() && prev.model_error_taken;
        if error_taken {
            model_error = prev.model_error_std;
        }
        let reach = 10f64.powf(RETUNE_WALK_DECADES);
        let grid = 2 * RETUNE_WALK_DECADES.round() as usize + 1;
        let w0 = prev.force_walk_std;
        let (mut walk, mut ll, n) = maximise_log(w0 / reach, w0 * reach, grid, 10, &|w| {
            likelihood(noise_scale, w, model_error)
        });
        runs += n;
        let mut moved = false;
        if tunes_scale {
            let (s, l, n) = around_scale(noise_scale, 8, &|s| likelihood(s, walk, model_error));
            runs += n;
            if l > ll {
                moved |= l > ll + RETUNE_SIGNIFICANT_GAIN;
                (noise_scale, ll) = (s, l);
            }
        }
        if error_taken {
            let (e, l, n) = around(model_error, 8, &|e| likelihood(noise_scale, walk, e));
            runs += n;
            if l > ll {
                moved |= l > ll + RETUNE_SIGNIFICANT_GAIN;
                (model_error, ll) = (e, l);
            }
        }
        if moved {
            let (w, l, n) = around(walk, 8, &|w| likelihood(noise_scale, w, model_error));
            runs += n;
            if l > ll {
                (walk, ll) = (w, l);
            }
        }
        return Ok(KalmanTuning {
            model_error_std: model_error,
            force_walk_std: walk,
            noise_scale,
            sigma: scaled(noise_scale),
            log_likelihood: ll,
            runs,
            model_error_taken: error_taken,
        });
    }
    let mut noise_scale = 1.0f64.clamp(lo_scale, hi_scale);
    let mut model_error_taken = false;
    let (mut walk, mut ll, n) = maximise_log(1e-6 * scale, 1e2 * scale, 9, 12, &|w| {
        likelihood(noise_scale, w, model_error)
    });
    runs += n;
    if tunes_scale {
        let (s, l, n) = maximise_log(lo_scale, hi_scale, 10, 10, &|s| {
            likelihood(s, walk, model_error)
        });
        runs += n;
        if l > ll {
            noise_scale = s;
            ll = l;
            let (w, l, n) = around(walk, 10, &|w| likelihood(noise_scale, w, model_error));
            runs += n;
            if l > ll {
                walk = w;
                ll = l;
            }
        }
    }
    if opts.model_error_std.is_none() && opts.tune_model_error {
        let (e, l, n) = maximise_log(1e-9 * scale, 1e-1 * scale, 9, 8, &|e| {
            likelihood(noise_scale, walk, e)
        });
        runs += n;
        if l > ll {
            model_error = e;
            model_error_taken = true;
            ll = l;
            if tunes_scale {
                let (s, l, n) = around_scale(noise_scale, 8, &|s| likelihood(s, walk, model_error));
                runs += n;
                if l > ll {
                    noise_scale = s;
                    ll = l;
                }
            }
            let (w, l, n) = around(walk, 8, &|w| likelihood(noise_scale, w, model_error));
            runs += n;
            if l > ll {
                walk = w;
                ll = l;
            }
        }
    }
    Ok(KalmanTuning {
        model_error_std: model_error,
        force_walk_std: walk,
        noise_scale,
        sigma: scaled(noise_scale),
        log_likelihood: ll,
        runs,
        model_error_taken,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The noise scale's range: an estimated channel at its floor (noise-free data) keeps
    /// the scale at or above 1, a channel at 1 % noise bounds it at 1e-5 (far below the
    /// scales the tuning takes), and a channel whose level was given (not estimated) does
    /// not bound it.
    #[test]
    fn the_noise_scale_keeps_estimated_channels_at_or_above_their_floor() {
        let data = TestData {
            samples: vec![0, 1],
            t_ns: vec![0, 1],
            excitation: vec![vec![0.0], vec![0.0]],
            response: vec![vec![2.0, 4.0], vec![-2.0, -4.0]],
        };
        let floor = crate::estimate::tuning::NOISE_FLOOR_RELATIVE;
        // Channel RMS 2 and 4: floors 2e-7 and 4e-7.
        let at_floor = [2.0 * floor, 4.0 * floor];
        let (lo, hi) = noise_scale_range(&at_floor, &[true, true], &data);
        assert!(
            (lo - 1.0).abs() < 1e-12 && hi == NOISE_SCALE_RANGE.1,
            "{lo} {hi}"
        );
        let (lo, hi) = noise_scale_range(&[0.02, 0.04], &[true, true], &data);
        assert!(
            (lo - 1e-5).abs() < 1e-18 && hi == NOISE_SCALE_RANGE.1,
            "{lo} {hi}"
        );
        // Far above every floor: the range's own lower end.
        let (lo, _) = noise_scale_range(&[1e3, 1e3], &[true, true], &data);
        assert_eq!(lo, NOISE_SCALE_RANGE.0);
        // Channel 0 given at the floor: only channel 1 (at 1e3 × its floor) bounds it.
        let (lo, _) = noise_scale_range(&[2.0 * floor, 4e3 * floor], &[false, true], &data);
        assert!((lo - 1e-3).abs() < 1e-15, "{lo}");
    }
}
