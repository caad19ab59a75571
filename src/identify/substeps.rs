//! The free run's model sub-steps (`raise_substeps`): after the output-error refinement,
//! every doubling from the setup's level up to [`MAX_RAISED_LEVEL`] (or 8× the setup's),
//! within the step budget, is tried — a law linear in the state refined afresh at each, any
//! other screened at the minima found and then refined by continuation outward from the
//! answer's level, the finest the likelihood cannot tell from the best taken; where the
//! sub-steps have not converged, the errors are widened to the last doubling's move. Moved
//! out of `identify` whole.

use super::*;

/// Most simulated sub-steps per output-error run when the refinement raises the model's
/// sub-steps (a time budget: a refinement takes about a hundred runs). Not applied to a
/// linear law, whose runs cost one composed map per sample. 1.4 M lets a 20,000-sample
/// record reach 64 sub-steps (was 700,000, 32): Coulomb + spring, 100 % noise, seed 3,
/// stopped at 32 with a normalised cost of 1.57, and the model error it left made another
/// start look equivalent, so the stated errors were widened to 134 % (friction) and 5.2 %
/// (spring); at 64: −1.09 % (se 2.1 %) and −0.093 % (se 0.11 %), 260 s instead of 165 s.
pub(super) const MAX_RAISED_STEPS: usize = 1_400_000;

/// Finest model sub-steps the output-error refinement tries (the finest data scheme of the
/// sweeps is 64 sub-steps), unless 8× the setup's is finer.
const MAX_RAISED_LEVEL: usize = 64;

/// Data from a continuous structure are followed only approximately by the model's Newmark
/// sub-steps; on an undamped structure the mismatch accumulates and, at high noise, moves
/// the output-error cost's global minimum to a wrong stiffness (measured: 16 model sub-steps
/// on 64-sub-step data, 100 % noise, seed 2: +27 %, cost 1.14 against 0.97 at the truth
/// with 64). So after the refinement: the cost at the minima found is evaluated at the
/// setup's level and every doubling of it (except the level refined at, coarser ones
/// included when the scan fallback refined at a finer one) up to [`MAX_RAISED_LEVEL`] (or
/// 8× the setup's) and
/// [`MAX_RAISED_STEPS`]; when the likeliest level lowers it by more than Δχ² = 1, the
/// refinement is redone at the coarsest level within that of it. For a law not linear in the
/// state every level from the setup's up to the cap is then refined by continuation,
/// outward from the answer's (each from its neighbour nearer it), and the finest within
/// Δχ² = 1 of the lowest refined cost is taken (see the loop's comment).
#[allow(clippy::too_many_arguments)]
pub(super) fn raise_substeps(
    setup: &Setup,
    model: &Model,
    data: &TestData,
    opts: &IdentifyOptions,
    sigma: &[f64],
    start: &[f64],
    scales: &[f64],
    mut r: crate::estimate::output_error::Refined,
    notes: &mut Vec<String>,
) -> crate::estimate::output_error::Refined {
    use crate::estimate::output_error::refine_global;
    let nobs = (data.len() * sigma.len()) as f64;
    // A linear law costs one composed map per sample whatever the sub-steps: only the 8×
    // cap applies.
    let linear = crate::simulate::law_is_linear(setup);
    // What counts as a cost drop worth a finer model. The doubled model is the same data
    // fitted with a smaller discretisation error, so its cost drop is not a χ² fluctuation
    // between noise draws but a systematic gain: a drop of Δχ² = 1 (one unit of the
    // unnormalised cost) already moves a parameter by about one standard error. Measured
    // (spring, 100 % noise, 2,000 samples, data 64 sub-steps, seed 86): 32 → 64 sub-steps
    // lowered the normalised cost by 0.025 (Δχ² = 300), below the old threshold of 3σ of a
    // χ² (0.039), and moved the spring from +0.40 % (4.0 se) to −0.04 %. Every level has the
    // same parameters, so the likelihood alone decides between them: Δχ² > 1 for every law
    // (non-linear laws kept the 3σ threshold until the thirty-eighth session, as a
    // refinement budget — the per-run budget is [`MAX_RAISED_STEPS`]; measured since: on
    // 64-sub-step data at 100 % noise the 3σ rule, Δχ² = 657 there, took 32 sub-steps where
    // 64 cost Δχ² = 186 less (Coulomb seed 7730; gap seed 7510: 120); ACCURACY.md,
    // thirty-eighth session).
    let significant = 1.0 / nobs;
    let t_screen = std::time::Instant::now();
    let mut sub = opts.substeps;
    // The estimate one doubling coarser than `r`, and whether a finer level than the one
    // taken was tried and did not help (the sub-steps have converged).
    let mut coarser: Option<Vec<f64>> = None;
    let mut settled = false;
    // Every level from the setup's (but the one refined at) up to [`MAX_RAISED_LEVEL`] (or
    // 8× the setup's) within the step budget is tried at every minimum found (at a wrong
    // stiffness finer steps do not help), and the coarsest level within `significant` of the lowest
    // cost is taken. Doubling only while a doubling helped (as before) stopped short: the
    // cost is not monotone in the sub-steps (a Newmark model resonates with the data's own
    // scheme); the same change in the prediction-error refinement took the friction sweep on
    // 8-sub-step data from 50 % to 100 % coverage.
    let points: Vec<(Vec<f64>, f64)> = match &r.report.scan {
        Some(scan) => scan
            .minima
            .iter()
            .map(|m| (m.values.clone(), m.cost))
            .collect(),
        None => vec![(r.values.clone(), r.report.cost_end)],
    };
    let current = points.iter().map(|p| p.1).fold(f64::INFINITY, f64::min);
    let cap = MAX_RAISED_LEVEL.max(8 * opts.substeps);
    let mut levels: Vec<(usize, f64)> = Vec::new();
    // From `coarsest_substeps` (the setup's level), not only finer ones: the scan fallback
    // refines at the level of its prefix's lowest cost, which on a noisy prefix can be
    // finer than the data's own (accelerometer-only scans keep theirs, see `scan.rs`).
    // Measured (Coulomb `sign(v), u`, 8-sub-step data, 100 % noise, seed 7141): the scan's
    // 200 samples put 16 sub-steps 0.0007 below 8 in normalised cost; refined at 16 and
    // raised only to finer levels, the answer misfit the record by 2.2× the noise (the
    // 8-sub-step Newmark data's period error carried through an undamped structure), and
    // the start-motion test took that misfit for motion and refused a record at rest. With
    // 8 among the levels: cost 0.99, `sign(v)` −1.4 and `u` −0.06 errors.
    let mut l = opts.coarsest_substeps.min(opts.substeps);
    // A linear law is refined afresh at every level (its runs are cheap): its coarse minimum
    // can sit where the finer models cost more. Measured (spring `u, v`, Kalman pipeline, 1
    // model sub-step, 64-sub-step data, 1 % noise, seed 22): every level's cost at the
    // 1-sub-step minimum (+1.1 %) was above its 9.09, so no level was taken and the answer
    // stayed 344 standard errors off.
    let refine_at = |level: usize| {
        refine_global(
            setup,
            model,
            start,
            scales,
            &data.excitation,
            &data.response,
            sigma,
            level,
            opts.output_error_iterations,
        )
    };
    let mut refined_at: Vec<(usize, crate::estimate::output_error::Refined)> = Vec::new();
    // The step budget of a law not linear in the state: simulated sub-steps per run.
    let within_budget = |level: usize| data.len().saturating_mul(level) <= MAX_RAISED_STEPS;
    let mut tried = Vec::new();
    while l <= cap && (linear || within_budget(l)) {
        if l != opts.substeps {
            tried.push(l);
        }
        l *= 2;
    }
    // Every level (a linear law's refinements; another law's free runs at every minimum
    // found) is independent of the others: run on parallel threads ([`crate::par`]), the
    // results the same as one after the other.
    if linear {
        let fits = crate::par::map(&tried, |&level| refine_at(level));
        for (&level, fit) in tried.iter().zip(fits) {
            if let Ok(fresh) = fit
                && fresh.report.accepted
            {
                levels.push((level, fresh.report.cost_end));
                refined_at.push((level, fresh));
            }
        }
    } else {
        let runs: Vec<(usize, &[f64])> = tried
            .iter()
            .flat_map(|&level| points.iter().map(move |(p, _)| (level, p.as_slice())))
            .collect();
        let costs = crate::par::map(&runs, |&(level, p)| {
            data.free_run(setup, model, p, sigma, level)
                .ok()
                .map(|(_, c2)| c2 / nobs)
        });
        for (&level, at_level) in tried.iter().zip(costs.chunks(points.len().max(1))) {
            let best_here = at_level
                .iter()
                .flatten()
                .copied()
                .fold(f64::INFINITY, f64::min);
            if best_here.is_finite() {
                levels.push((level, best_here));
            }
        }
    }
    let lowest = levels.iter().map(|x| x.1).fold(current, f64::min);
    let chosen = if current <= lowest + significant {
        None
    } else {
        levels
            .iter()
            .copied()
            .find(|&(_, c)| c <= lowest + significant)
    };
    match chosen {
        None => settled = !levels.is_empty(),
        Some((level, after)) => {
            let done = refined_at
                .iter()
                .position(|x| x.0 == level)
                .map(|i| refined_at.swap_remove(i).1);
            if let Ok(r2) = done.map_or_else(|| refine_at(level), Ok)
                && r2.report.cost_end < r.report.cost_end
            {
                // A finer model whose best fit is worse than the coarser one's is not taken
                // (measured on the shipped friction recording: 2 sub-steps ended at 42.6× the
                // noise where 1 sub-step ended at 25×).
                notes.push(format!(
                    "output-error refinement with {level} model sub-steps per sample instead of {sub}: the likeliest of the levels tried up to {} {} (normalised cost {current:.4} → {after:.4}, Δχ² = {:.0}, threshold {:.0}); the passes (or the scan) ran with {}",
                    levels.last().map_or(sub, |x| x.0),
                    if linear {
                        "(the law is linear: refined afresh at each level)"
                    } else {
                        "at the minima found"
                    },
                    (current - after) * nobs,
                    significant * nobs,
                    opts.substeps
                ));
                let previous = std::mem::replace(&mut r, r2).values;
                coarser = (level == 2 * sub).then_some(previous);
                sub = level;
                settled = levels.iter().any(|x| x.0 > level);
            }
        }
    }
    // Continuation (laws not linear in the state): from the answer, every doubling up to
    // the cap (within the step budget) and every halving down to the setup's level is
    // refined again, each starting at its neighbour's answer nearer the first, and the
    // finest level whose refined cost is within `significant` of the
    // lowest is taken. Why refined: the levels above were judged by their cost at the
    // minima found with the coarser model, and such a minimum has moved to compensate that
    // model's discretisation error — at it every finer model costs more, although refined
    // they cost less. Measured (1-DOF `v, sign(v), const`, 8-sub-step data, 10 % noise,
    // seed 7813): at the 1-sub-step minimum (`const` 12.9 errors off) the finer levels cost
    // 0.578–0.663 against its 0.528; refined from it, 2 sub-steps cost 0.5229 and 4 cost
    // 0.5227 (every parameter within 1.8 errors), 8 no less.
    //
    // Why every doubling, not only while one helps (the thirty-eighth session's loop): the
    // refined cost is not monotone in the sub-steps either (a Newmark model resonates with
    // the data's own scheme). Measured (the same setup, 64-sub-step data, 1 % noise, seed
    // 7811): refined from the 1-sub-step answer (`const` 4 errors off, χ² 2950.6), 2
    // sub-steps cost 2957.4 and the loop stopped there, while 4 cost 2932.3 and 32 2931.4.
    //
    // Why the finest within Δχ² = 1 and not the coarsest (the screening's rule above, a
    // budget there): levels the likelihood cannot tell apart fit the record equally well
    // with different parameters — the coarser one's compensating its discretisation error —
    // and the structure is continuous, so the finer model is the one whose parameters mean
    // what they say. Measured (seed 7816, 64-sub-step data, 1 %): 1 sub-step χ² 3152.8 at
    // `v` +3.9 errors, 8 sub-steps 3152.1 at +1.1. (ACCURACY.md, thirty-ninth session.)
    //
    // A linear law was refined afresh at every level above. A plain descent, not
    // `refine_global`'s scan: it follows the minimum as the model is refined; the screening
    // above is the global search.
    let mut continued: Vec<String> = Vec::new();
    // Why the coarser levels too, each refined from the one above it: the screening judged
    // them by their cost at the minima found with the passes' model, which compensate that
    // model's discretisation error, and took the first finer level that looked better; the
    // levels between the passes' and the one taken were never refined. Measured (1-DOF
    // `v, sign(v), const`, 8-sub-step data, 1 % noise, the sensors' levels given, seed 8918):
    // the screening took 16 sub-steps (χ² 6161 at `const` 21.7 errors off) where the truth
    // at the data's 8 costs 6110; no level but 16 had been refined.
    let first_level = sub;
    let mut climbed_again = false;
    crate::par::phase("sub-step screening", t_screen);
    let t_continue = std::time::Instant::now();
    if !linear {
        let first_note = r.report.note.clone();
        let base_cost = r.report.cost_end;
        let refine_from = |from: &[f64], level: usize| {
            crate::estimate::output_error::refine(
                setup,
                model,
                from,
                scales,
                &data.excitation,
                &data.response,
                sigma,
                level,
                opts.output_error_iterations,
            )
            .ok()
            // (A cost that is not finite decides nothing: the levels stop there. `accepted`
            // is not asked: from a start that already costs less at the other level, a
            // descent that takes no step is "not accepted" and still the better fit.)
            .filter(|finer| finer.report.cost_end.is_finite())
        };
        // Every halving down to the setup's level, not only while one helps: the refined
        // cost is not monotone downward either. Measured (1-DOF, own-discretisation data,
        // 1 % noise, seed 9323, first answer at 8): 4 sub-steps Δχ² = 12 lower, 2 sub-steps
        // 18 higher, 1 (the data's own) 38 lower — stopping at 2 took 4 and `sign(v)` 10
        // errors off; all the way down, 1 and 0.6 errors.
        let floor = opts.coarsest_substeps.min(opts.substeps).max(1);
        let mut downward = Vec::new();
        let mut lower = sub;
        while lower.is_multiple_of(2) && lower / 2 >= floor {
            lower /= 2;
            downward.push(lower);
        }
        let mut upward = Vec::new();
        let mut next = sub * 2;
        while next <= cap && within_budget(next) {
            upward.push(next);
            next *= 2;
        }
        // The two chains start from the answer and do not meet: run side by side (their
        // results do not depend on the threads).
        let chains = crate::par::map(&[downward, upward], |levels| {
            let mut fits: Vec<(usize, Option<crate::estimate::output_error::Refined>)> = Vec::new();
            for &level in levels {
                let from = fits
                    .last()
                    .and_then(|t| t.1.as_ref())
                    .map_or(&r.values, |t| &t.values);
                let Some(fit) = refine_from(from, level) else {
                    break;
                };
                fits.push((level, Some(fit)));
            }
            fits
        });
        let mut chains = chains.into_iter();
        let (below, above) = (
            chains.next().unwrap_or_default(),
            chains.next().unwrap_or_default(),
        );
        // Every level, coarsest first, with `r` itself as `None` (its level is `sub`).
        let mut ladder: Vec<(usize, Option<crate::estimate::output_error::Refined>)> =
            below.into_iter().rev().collect();
        ladder.push((sub, None));
        ladder.extend(above);
        let cost_of = |t: &Option<crate::estimate::output_error::Refined>| {
            t.as_ref().map_or(base_cost, |f| f.report.cost_end)
        };
        // The finest level within `significant` of the lowest cost.
        let finest_within =
            |ladder: &[(usize, Option<crate::estimate::output_error::Refined>)]| {
                let lowest = ladder
                    .iter()
                    .map(|t| cost_of(&t.1))
                    .fold(base_cost, f64::min);
                ladder
                    .iter()
                    .rposition(|t| cost_of(&t.1) <= lowest + significant)
                    .unwrap_or(0)
            };
        let mut taken = finest_within(&ladder);
        // A coarser level that fits better than every finer one may have found a better
        // valley of the rough friction cost, not a better discretisation: the finer levels
        // are climbed again from it (each from the one below), each keeping the better of
        // its two fits. On data of the coarser level's own scheme the finer models still
        // cost more and it stays taken; on continuous data they inherit its valley and the
        // finest is taken. Measured (1-DOF, 64-sub-step data, 1 %, the levels given, seeds
        // 9501–9530): without the climb 8 and 16 sub-steps were taken on two records.
        let own = ladder.iter().position(|t| t.1.is_none()).unwrap_or(0);
        if taken < own {
            let mut from = ladder[taken]
                .1
                .as_ref()
                .map_or_else(|| r.values.clone(), |t| t.values.clone());
            for (level, kept) in ladder.iter_mut().skip(taken + 1) {
                let Some(fit) = refine_from(&from, *level) else {
                    break;
                };
                from.clone_from(&fit.values);
                if fit.report.cost_end < cost_of(kept) {
                    *kept = Some(fit);
                    climbed_again = true;
                }
            }
            taken = finest_within(&ladder);
        }
        for (i, (level, fit)) in ladder.iter().enumerate() {
            continued.push(match fit {
                None => format!("{level}: the first answer"),
                Some(fit) => format!(
                    "{level}: Δχ² = {:.1}{}",
                    (base_cost - fit.report.cost_end) * nobs,
                    if taken == i { ", taken" } else { "" }
                ),
            });
        }
        // A finer level than the one taken was tried and did not help: the sub-steps have
        // converged.
        let finer_tried = taken + 1 < ladder.len();
        // One doubling coarser than the level taken, when it was fitted.
        let previous = taken.checked_sub(1).and_then(|j| {
            (ladder[j].0 * 2 == ladder[taken].0).then(|| {
                ladder[j]
                    .1
                    .as_ref()
                    .map_or(&r.values, |t| &t.values)
                    .clone()
            })
        });
        let (level, fit) = ladder.swap_remove(taken);
        // The descents of the other levels count among the refinement's iterations.
        let others: usize = ladder
            .iter()
            .filter_map(|t| t.1.as_ref())
            .map(|t| t.report.iterations)
            .sum();
        match fit {
            // The answer's own level.
            None => {
                settled = settled || finer_tried;
                r.report.iterations += others;
            }
            Some(mut fit) => {
                settled = finer_tried;
                // The report describes the whole refinement (its start, its iterations, the
                // scan's minima); the errors are the new level's own (the model taken).
                take_over_start(&mut fit, &r);
                fit.report.iterations += others;
                fit.report.note = format!(
                    "{}; {} by continuation to {level} model sub-steps: {}",
                    first_note,
                    moved_word(level, sub),
                    fit.report.note
                );
                fit.report.accepted = true;
                r = fit;
                coarser = previous;
                sub = level;
            }
        }
    }
    crate::par::phase("sub-step continuation", t_continue);
    if continued.iter().any(|c| c.ends_with(", taken")) {
        notes.push(format!(
            "model sub-steps {} by continuation to {sub} per sample: every doubling from {} up to {} refined from its neighbour nearer the first answer's {first_level}{}, the finest within Δχ² = {:.0} of the lowest cost taken ({}); the other levels' costs at the minima found had not shown it (such a minimum compensates its model's discretisation error)",
            moved_word(sub, first_level),
            continued
                .first()
                .and_then(|c| c.split(':').next())
                .unwrap_or("the setup's level"),
            continued
                .last()
                .and_then(|c| c.split(':').next())
                .unwrap_or("the cap"),
            if climbed_again {
                ", the finer ones climbed again from the coarser level that fitted best (each keeping its better fit)"
            } else {
                ""
            },
            significant * nobs,
            continued.join("; ")
        ));
    }
    // Raised, but not to where one more doubling stops mattering (the cap, the step budget,
    // or a finer fit that ended worse): the estimate still moves with the sub-steps, and its
    // standard errors do not contain that. The last doubling's move is the figure of the
    // discretisation error left (Richardson: about a third of it for Newmark's second order;
    // the whole move is stated because the minima need not move monotonically). Measured on
    // accelerometer-only data (64 sub-steps, setup at 1): 8 → 16 sub-steps ended at +22 %
    // with a 0.04 % stated error.
    //
    // When the loop stopped at the cap or the budget, one more doubling at the estimate
    // decides (measured: 64-sub-step data at the cap of 64 showed no drop; without this check
    // a 4 % move from a 32-level wrong minimum was stated as the error of a right answer).
    // This is a cost at the estimate, which the continuation's comment above says a
    // compensating minimum biases upward: it can call settled what a descent would not (so
    // it widens seldom: in none of the thirty-ninth session's 270 1-DOF and 180 Coulomb
    // records); where a finer level than the one taken was tried, `settled` is that
    // finding and this check does not run.
    let more = sub * 2;
    if !settled
        && (linear || data.len() * more <= 2 * MAX_RAISED_STEPS)
        && let Ok((_, c2)) = data.free_run(setup, model, &r.values, sigma, more)
    {
        settled = r.report.cost_end - c2 / nobs <= significant;
    }
    if let (false, Some(prev)) = (settled, coarser) {
        let keys = setup.param_keys();
        let mut widened = Vec::new();
        for (j, (v, p)) in r.values.iter().zip(&prev).enumerate() {
            let moved = (v - p).abs();
            if moved > r.std_errors[j] {
                r.std_errors[j] = moved;
                widened.push(format!("{} by {moved:.4e}", keys[j]));
            }
        }
        notes.push(format!(
            "the model sub-steps did not converge: {sub} sub-steps, the finest tried, were taken and one more doubling did not show the cost settled (threshold Δχ² = {:.0}); {}set [integrator] substeps nearer the data's time step",
            significant * nobs,
            if widened.is_empty() {
                "the estimate moved by less than its standard errors; ".to_string()
            } else {
                format!(
                    "standard errors widened to the last doubling's move ({}); ",
                    widened.join(", ")
                )
            }
        ));
    }
    r
}

/// How the model sub-steps moved from `from` to `to`, for the notes.
fn moved_word(to: usize, from: usize) -> &'static str {
    match to.cmp(&from) {
        std::cmp::Ordering::Greater => "raised",
        std::cmp::Ordering::Less => "lowered",
        std::cmp::Ordering::Equal => "refined again",
    }
}
