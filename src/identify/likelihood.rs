//! The likelihood-ratio check of a free-run answer's stated errors: along each parameter's
//! profile direction, how far out the output-error cost rises by χ²₁(95 %) = 3.84, and the
//! error widened to that distance when it is farther than the stated 95 % half-width.
//!
//! Why: the stated errors are a curvature (a sandwich over secants of ±1 and ±8 errors,
//! `scan::restate_final_errors`), which describes the cost near its minimum only. Where the
//! cost is a flat valley farther out, the curvature is confidently narrow: accelerometers
//! only, Coulomb friction and a spring at 100 % noise, seed 9104 of the forty-ninth
//! session, answered `u` −28 % ± 2.6 % (15 errors off) although the truth's χ² was only 5
//! above the answer's (ACCURACY.md). A likelihood-ratio interval (Wilks 1938; the profile
//! likelihood of Venzon & Moolgavkar 1988) reads the cost itself.
//!
//! The path: the quadratic model's profile trace of parameter `j`, the straight line
//! `θ̂ + t·C e_j / C_jj` (`C` the inverse Fisher information at the restated noise levels),
//! on which the other parameters take their best values as `θ_j` moves *if* the cost is
//! quadratic. The cost on the line is at least the profile cost (the profile minimises
//! over the others), so the distance found is a lower bound of the profile interval: the
//! check can only widen an error that is too narrow, never make one narrower. The
//! evaluations are free runs, `2·p` when the stated errors hold (one at each end of each
//! 95 % interval) and a few more per end that does not.

use nalgebra::DMatrix;

use crate::model::Model;
use crate::setup::Setup;

use super::TestData;

/// χ²₁ at 95 %: the rise of `Σ((y − ŷ)/σ)²` that bounds a 95 % likelihood-ratio interval of
/// one parameter (Wilks).
pub(super) const CHI2_95: f64 = 3.84;

/// 1.96: the 95 % half-width in standard errors of a normal estimate.
const Z_95: f64 = 1.96;

/// The farthest the walk goes, in stated standard errors: 32 × the 95 % half-width. A cost
/// that has not risen by 3.84 there leaves the parameter undetermined along its profile.
pub(super) const FARTHEST: f64 = 32.0 * Z_95;

/// Interpolations of the bracket once the walk has crossed the level: regula falsi in
/// `√rise`, exact for a quadratic cost (whose `√rise` is linear in the distance).
const INTERPOLATIONS: usize = 2;

/// Where the cost along one end of one parameter's line first reaches the level.
#[derive(Debug, Clone, Copy, PartialEq)]
pub(super) struct Crossing {
    /// Distance from the answer, in stated standard errors of the parameter.
    pub distance: f64,
    /// `false` when the cost stayed below the level out to [`FARTHEST`].
    pub reached: bool,
    /// The lowest rise seen on the way (negative: a lower cost than the answer's).
    pub lowest: f64,
}

/// Walks out from `start` (doubling) until `rise(t) ≥ level` or `t > farthest`, then
/// places the crossing in the last bracket by [`INTERPOLATIONS`] steps of regula falsi in
/// `√rise` (a negative rise counts as 0). `rise` is `None` where the free run failed (a
/// diverging model: the data reject it, taken as above the level). Never inside `start`:
/// the check widens an error, it does not narrow one (see the module's note).
pub(super) fn crossing(
    mut rise: impl FnMut(f64) -> Option<f64>,
    start: f64,
    level: f64,
    farthest: f64,
) -> Crossing {
    let mut lowest = f64::INFINITY;
    let mut below = (0.0, 0.0);
    let mut t = start;
    let above = loop {
        let r = rise(t).unwrap_or(f64::INFINITY);
        lowest = lowest.min(r);
        if r >= level {
            break (t, r);
        }
        below = (t, r);
        if t >= farthest {
            return Crossing {
                distance: farthest,
                reached: false,
                lowest,
            };
        }
        t = (2.0 * t).min(farthest);
    };
    if below.0 == 0.0 {
        // Already above at the start: the stated interval holds.
        return Crossing {
            distance: start,
            reached: true,
            lowest,
        };
    }
    let root = |r: f64| r.max(0.0).sqrt();
    let target = level.sqrt();
    // The crossing of the line through the bracket's ends in `√rise` (the midpoint when
    // the upper end's free run failed).
    let between = |lo: (f64, f64), hi: (f64, f64)| {
        if hi.1.is_finite() && root(hi.1) > root(lo.1) {
            lo.0 + (hi.0 - lo.0) * (target - root(lo.1)) / (root(hi.1) - root(lo.1))
        } else {
            0.5 * (lo.0 + hi.0)
        }
    };
    let (mut lo, mut hi) = (below, above);
    for _ in 0..INTERPOLATIONS {
        let t = between(lo, hi);
        let r = rise(t).unwrap_or(f64::INFINITY);
        lowest = lowest.min(r);
        if r >= level {
            hi = (t, r);
        } else {
            lo = (t, r);
        }
    }
    Crossing {
        distance: between(lo, hi).clamp(lo.0, hi.0),
        reached: true,
        lowest,
    }
}

/// One parameter's check: the crossings below and above the answer.
#[derive(Debug, Clone, Copy)]
pub(super) struct ParameterInterval {
    pub below: Crossing,
    pub above: Crossing,
}

impl ParameterInterval {
    /// The standard error the likelihood ratio implies: the farther end's distance over
    /// 1.96, in the parameter's unit (`stated` is the error the distances are counted in).
    pub fn error(&self, stated: f64) -> f64 {
        self.below.distance.max(self.above.distance) * stated / Z_95
    }

    pub fn reached(&self) -> bool {
        self.below.reached && self.above.reached
    }

    pub fn lowest(&self) -> f64 {
        self.below.lowest.min(self.above.lowest)
    }
}

/// The crossings of every parameter, both ends, of the answer `values` with stated errors
/// `errors`, on the lines of the inverse Fisher information `fisher` at the noise levels
/// `sigma` (the restated ones: the likelihood's), from the record `data` with `substeps`
/// model sub-steps. `None` when the answer's own free run fails or `fisher` is singular.
#[allow(non_snake_case)]
pub(super) fn intervals(
    setup: &Setup,
    model: &Model,
    data: &TestData,
    (values, errors): (&[f64], &[f64]),
    fisher: &DMatrix<f64>,
    sigma: &[f64],
    substeps: usize,
) -> Option<Vec<ParameterInterval>> {
    use crate::estimate::output_error::{residuals, scaled_inverse};
    let C = scaled_inverse(fisher)?;
    let cost = |p: &[f64]| {
        residuals(
            setup,
            model,
            p,
            &data.excitation,
            &data.response,
            sigma,
            substeps,
        )
        .ok()
        .map(|(_, c)| c)
    };
    let at_answer = cost(values)?;
    let np = values.len();
    let ends: Vec<(usize, f64)> = (0..np).flat_map(|j| [(j, -1.0), (j, 1.0)]).collect();
    let crossings = crate::par::map_unless_nested(&ends, |&(j, side)| {
        let cjj = C[(j, j)];
        if !(cjj > 0.0 && cjj.is_finite() && errors[j] > 0.0 && errors[j].is_finite()) {
            return None;
        }
        let rise = |t: f64| {
            // θ̂ + s·t·e_j·C e_j / C_jj: parameter j moves by t stated errors, the others
            // start on the quadratic's profile trace and are then fitted.
            let step = side * t * errors[j] / cjj;
            let p: Vec<f64> = (0..np).map(|i| values[i] + step * C[(i, j)]).collect();
            profile_cost(setup, model, data, &p, j, errors, sigma, substeps).map(|c| c - at_answer)
        };
        Some(crossing(rise, Z_95, CHI2_95, FARTHEST))
    });
    crossings
        .chunks(2)
        .map(|c| {
            Some(ParameterInterval {
                below: c[0]?,
                above: c[1]?,
            })
        })
        .collect()
}

/// Gauss–Newton iterations of the profile fit (the other parameters at a fixed `θ_j`).
const PROFILE_ITERATIONS: usize = 3;

/// The lowest cost found with parameter `fixed` held at `start[fixed]` and the others
/// fitted from `start` by Gauss–Newton on forward secants of one stated error (the
/// piecewise-smooth outputs of a friction law, `output_error::SIGN_LAW_STEP`), each step
/// taken only if it lowers the cost (halved once otherwise). The cost at `start` when no
/// step lowers it; `None` when the free run at `start` fails.
#[allow(clippy::too_many_arguments)]
#[allow(non_snake_case)]
fn profile_cost(
    setup: &Setup,
    model: &Model,
    data: &TestData,
    start: &[f64],
    fixed: usize,
    errors: &[f64],
    sigma: &[f64],
    substeps: usize,
) -> Option<f64> {
    use crate::estimate::output_error::residuals;
    use nalgebra::DVector;
    let run = |p: &[f64]| {
        residuals(
            setup,
            model,
            p,
            &data.excitation,
            &data.response,
            sigma,
            substeps,
        )
        .ok()
    };
    let free: Vec<usize> = (0..start.len()).filter(|&i| i != fixed).collect();
    let mut p = start.to_vec();
    let (mut r, mut cost) = run(&p)?;
    if free.is_empty() {
        return Some(cost);
    }
    for _ in 0..PROFILE_ITERATIONS {
        // Forward secants of the normalised residuals, one column per free parameter.
        let mut columns = Vec::with_capacity(free.len());
        for &i in &free {
            let h = errors[i];
            let mut q = p.clone();
            q[i] += h;
            let Some((rq, _)) = run(&q) else {
                return Some(cost);
            };
            columns.push(DVector::from_iterator(
                r.len(),
                rq.iter().zip(&r).map(|(a, b)| (a - b) / h),
            ));
        }
        let n = free.len();
        let JtJ = DMatrix::from_fn(n, n, |a, b| columns[a].dot(&columns[b]));
        let rv = DVector::from_column_slice(&r);
        let Jtr = DVector::from_fn(n, |a, _| columns[a].dot(&rv));
        let Some(delta) = JtJ.lu().solve(&(-Jtr)) else {
            return Some(cost);
        };
        let mut taken = false;
        for scale in [1.0, 0.5] {
            let mut q = p.clone();
            for (a, &i) in free.iter().enumerate() {
                q[i] += scale * delta[a];
            }
            if let Some((rq, cq)) = run(&q)
                && cq < cost
            {
                let gain = cost - cq;
                (p, r, cost) = (q, rq, cq);
                taken = gain > 0.05;
                break;
            }
        }
        if !taken {
            break;
        }
    }
    Some(cost)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A quadratic rise `t²` (the stated error right): one evaluation, the stated 1.96.
    #[test]
    fn a_quadratic_cost_keeps_the_stated_interval() {
        let mut calls = 0;
        let c = crossing(
            |t| {
                calls += 1;
                Some(t * t)
            },
            Z_95,
            CHI2_95,
            FARTHEST,
        );
        assert_eq!(calls, 1);
        assert!(c.reached);
        assert_eq!(c.distance, Z_95);
    }

    /// A cost four times flatter (the error half the truth's): the crossing at 2 × 1.96
    /// is found exactly (the walk's second point); ten times flatter, within 1 % after the
    /// interpolations; a cost that is not quadratic (linear, then steep) to a few %.
    #[test]
    fn a_flat_cost_is_walked_out_to_its_crossing() {
        let c = crossing(|t| Some(t * t / 4.0), Z_95, CHI2_95, FARTHEST);
        assert!(c.reached);
        let exact = 2.0 * CHI2_95.sqrt();
        assert!((c.distance - exact).abs() < 1e-9, "{c:?}");
        let c = crossing(|t| Some(t * t / 40.0), Z_95, CHI2_95, FARTHEST);
        let exact = 40f64.sqrt() * CHI2_95.sqrt();
        assert!((c.distance / exact - 1.0).abs() < 1e-9, "{c:?}");
        // Linear: rise = t / 4 crosses 3.84 at 15.36.
        let c = crossing(|t| Some(t / 4.0), Z_95, CHI2_95, FARTHEST);
        assert!((c.distance / 15.36 - 1.0).abs() < 0.03, "{c:?}");
    }

    /// A cost that never rises by 3.84 leaves the parameter undetermined at the farthest
    /// point; a lower cost on the way is reported; a failed free run counts as above.
    #[test]
    fn a_cost_that_never_rises_is_undetermined_and_lower_costs_are_seen() {
        let c = crossing(|t| Some(1.0 - t / 10.0), Z_95, CHI2_95, FARTHEST);
        assert!(!c.reached);
        assert_eq!(c.distance, FARTHEST);
        assert!(c.lowest < -5.0, "{c:?}");
        let c = crossing(
            |t| if t > 5.0 { None } else { Some(0.1) },
            Z_95,
            CHI2_95,
            FARTHEST,
        );
        assert!(c.reached);
        assert!(c.distance > 3.92 && c.distance <= 7.84, "{c:?}");
    }

    /// The implied error is the farther end's distance over 1.96.
    #[test]
    fn the_error_is_the_farther_end_over_the_normal_quantile() {
        let end = |d| Crossing {
            distance: d,
            reached: true,
            lowest: 0.0,
        };
        let i = ParameterInterval {
            below: end(Z_95),
            above: end(4.0 * Z_95),
        };
        assert!((i.error(2.5) - 10.0).abs() < 1e-12);
    }
}
