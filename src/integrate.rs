//! Newmark-β time stepping of the linear model, factorised once.
//!
//! One *sample* interval `Δt` is covered by `N` Newmark sub-steps of `h = Δt/N`; the
//! excitation is interpolated linearly across the interval and the connection force `f`
//! (`−Lc·f` on the right-hand side) is held constant over it. Because the left-hand side is
//! time-invariant the map from one sample's state to the next is affine:
//!
//! ```text
//! x_i = Φ x_{i−1} + (excitation terms) + Γ_f f_i,     x = (u, u̇, ü) ∈ R³ⁿ
//! ```
//!
//! which is what makes the paper's sensitivity `S = H Γ_f` constant. The effective mass
//! `M + γhC + βh²K` is inverted once; a step is a few matrix–vector products (`gemv`) on
//! preallocated vectors and allocates nothing.
#![allow(non_snake_case)]

use nalgebra::{DMatrix, DVector};

use crate::model::Model;
use crate::setup::{Newmark, Quantity};

pub mod fast;
pub mod sparse;

#[derive(Debug, thiserror::Error)]
pub enum IntegrateError {
    #[error("the effective mass matrix M + γhC + βh²K is singular (is M positive definite?)")]
    SingularEffectiveMass,
    #[error(transparent)]
    Modal(#[from] fast::FastError),
}

/// State of the model at a sample: displacement, velocity, acceleration (m, m/s, m/s²).
#[derive(Debug, Clone, PartialEq)]
pub struct State {
    pub u: DVector<f64>,
    pub v: DVector<f64>,
    pub a: DVector<f64>,
}

impl State {
    pub fn zeros(n: usize) -> Self {
        Self {
            u: DVector::zeros(n),
            v: DVector::zeros(n),
            a: DVector::zeros(n),
        }
    }

    pub fn is_finite(&self) -> bool {
        [&self.u, &self.v, &self.a]
            .iter()
            .all(|w| crate::dense::all_finite(w.as_slice()))
    }

    /// Value of one station channel.
    #[inline]
    pub fn channel(&self, dof: usize, q: Quantity) -> f64 {
        match q {
            Quantity::Displacement => self.u[dof],
            Quantity::Velocity => self.v[dof],
            Quantity::Acceleration => self.a[dof],
        }
    }
}

/// The discrete-time model of one sample interval.
#[derive(Debug, Clone)]
pub struct Stepper {
    pub n: usize,
    pub dt_s: f64,
    pub substeps: usize,
    pub newmark: Newmark,
    /// `(M + γhC + βh²K)⁻¹`.
    meff_inv: DMatrix<f64>,
    pub C: DMatrix<f64>,
    pub K: DMatrix<f64>,
    pub M: DMatrix<f64>,
    pub Lp: DMatrix<f64>,
    pub Lc: DMatrix<f64>,
    // Work vectors (no allocation per step).
    u_t: DVector<f64>,
    v_t: DVector<f64>,
    rhs: DVector<f64>,
    p_t: DVector<f64>,
}

impl Stepper {
    pub fn new(
        model: &Model,
        dt_s: f64,
        substeps: usize,
        newmark: Newmark,
    ) -> Result<Self, IntegrateError> {
        let h = dt_s / substeps as f64;
        let meff = &model.M + &model.C * (newmark.gamma * h) + &model.K * (newmark.beta * h * h);
        let meff_inv = meff
            .try_inverse()
            .ok_or(IntegrateError::SingularEffectiveMass)?;
        let n = model.n();
        Ok(Self {
            n,
            dt_s,
            substeps,
            newmark,
            meff_inv,
            C: model.C.clone(),
            K: model.K.clone(),
            M: model.M.clone(),
            Lp: model.Lp.clone(),
            Lc: model.Lc.clone(),
            u_t: DVector::zeros(n),
            v_t: DVector::zeros(n),
            rhs: DVector::zeros(n),
            p_t: DVector::zeros(model.Lp.ncols()),
        })
    }

    /// `(M + γhC + βh²K)⁻¹`, for sensitivities.
    pub fn meff_inv(&self) -> &DMatrix<f64> {
        &self.meff_inv
    }

    pub fn h(&self) -> f64 {
        self.dt_s / self.substeps as f64
    }

    /// Initial acceleration at rest under excitation `p0` and connection force `f0`:
    /// `M a₀ = Lp p₀ − Lc f₀ − C v₀ − K u₀`.
    pub fn initial_acceleration(&self, state: &mut State, p0: &[f64], f0: &DVector<f64>) {
        let mut rhs = &self.Lp * DVector::from_column_slice(p0) - &self.Lc * f0;
        rhs -= &self.C * &state.v;
        rhs -= &self.K * &state.u;
        if let Some(x) = self.M.clone().lu().solve(&rhs) {
            state.a = x;
        }
    }

    /// Advance `state` over one sample interval with the excitation going linearly from
    /// `p_prev` to `p_next` and a constant connection force `f` (positive resisting).
    pub fn advance(&mut self, state: &mut State, p_prev: &[f64], p_next: &[f64], f: &DVector<f64>) {
        let h = self.h();
        let Newmark { gamma, beta } = self.newmark;
        let ns = self.substeps;
        for s in 1..=ns {
            let t = s as f64 / ns as f64;
            for (j, pt) in self.p_t.iter_mut().enumerate() {
                *pt = p_prev[j] + t * (p_next[j] - p_prev[j]);
            }
            // Predictors ũ = u + h v + (½−β)h² a, ṽ = v + (1−γ)h a — as nalgebra's
            // `axpy` (`y ← a x + y`) computed them, in plain loops.
            let (ca, cv) = ((0.5 - beta) * h * h, (1.0 - gamma) * h);
            for k in 0..self.n {
                let (u, v, a) = (state.u[k], state.v[k], state.a[k]);
                self.u_t[k] = ca * a + (h * v + u);
                self.v_t[k] = cv * a + v;
            }
            // rhs = Lp p − Lc f − C ṽ − K ũ
            use crate::dense::{Op, gemv};
            gemv(&mut self.rhs, &self.Lp, &self.p_t, Op::Set);
            gemv(&mut self.rhs, &self.Lc, f, Op::Subtract);
            gemv(&mut self.rhs, &self.C, &self.v_t, Op::Subtract);
            gemv(&mut self.rhs, &self.K, &self.u_t, Op::Subtract);
            gemv(&mut state.a, &self.meff_inv, &self.rhs, Op::Set);
            let (cu, cv) = (beta * h * h, gamma * h);
            for k in 0..self.n {
                let a = state.a[k];
                state.u[k] = cu * a + self.u_t[k];
                state.v[k] = cv * a + self.v_t[k];
            }
        }
    }

    /// The map `(u, u̇, ü) ↦ (ũ, ṽ)` of the first sub-step's predictors
    /// `ũ = u + h u̇ + (½−β)h² ü`, `ṽ = u̇ + (1−γ)h ü` (2n × 3n): [`Stepper::advance`] reads
    /// the state only through them, so the transition Φ factors through this map (rank 2n).
    pub fn predictor_map(&self) -> DMatrix<f64> {
        let n = self.n;
        let h = self.h();
        let Newmark { gamma, beta } = self.newmark;
        let mut r = DMatrix::zeros(2 * n, 3 * n);
        for i in 0..n {
            r[(i, i)] = 1.0;
            r[(i, n + i)] = h;
            r[(i, 2 * n + i)] = (0.5 - beta) * h * h;
            r[(n + i, n + i)] = 1.0;
            r[(n + i, 2 * n + i)] = (1.0 - gamma) * h;
        }
        r
    }

    /// Γ_f: response of the state over one sample to a unit connection force held over the
    /// interval, from rest with no excitation; columns are (u; v; a) stacked, 3n × q.
    pub fn force_response(&mut self) -> DMatrix<f64> {
        let q = self.Lc.ncols();
        let n = self.n;
        let ne = self.Lp.ncols();
        let zeros = vec![0.0; ne];
        let mut out = DMatrix::zeros(3 * n, q);
        for j in 0..q {
            let mut s = State::zeros(n);
            let mut f = DVector::zeros(q);
            f[j] = 1.0;
            self.advance(&mut s, &zeros, &zeros, &f);
            out.view_mut((0, j), (n, 1)).copy_from(&s.u);
            out.view_mut((n, j), (n, 1)).copy_from(&s.v);
            out.view_mut((2 * n, j), (n, 1)).copy_from(&s.a);
        }
        out
    }

    /// Φ: the homogeneous one-sample state map (3n × 3n), built column by column.
    pub fn transition(&mut self) -> DMatrix<f64> {
        let n = self.n;
        let q = self.Lc.ncols();
        let ne = self.Lp.ncols();
        let zeros = vec![0.0; ne];
        let f = DVector::zeros(q);
        let mut out = DMatrix::zeros(3 * n, 3 * n);
        for j in 0..3 * n {
            let mut s = State::zeros(n);
            match j / n {
                0 => s.u[j % n] = 1.0,
                1 => s.v[j % n] = 1.0,
                _ => s.a[j % n] = 1.0,
            }
            self.advance(&mut s, &zeros, &zeros, &f);
            out.view_mut((0, j), (n, 1)).copy_from(&s.u);
            out.view_mut((n, j), (n, 1)).copy_from(&s.v);
            out.view_mut((2 * n, j), (n, 1)).copy_from(&s.a);
        }
        out
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::setup::Setup;

    const SDOF: &str = r#"
[model]
nodes = [{ id = 1, x = 0.0 }]
masses = [{ node = 1, mass = 2.0 }]
springs = [{ dof = { node = 1, dir = "w" }, k = 800.0 }]
[[excitation]]
name = "f"
dof = { node = 1, dir = "w" }
[[sensors]]
name = "d"
dof = { node = 1, dir = "w" }
quantity = "displacement"
[[connections]]
name = "j"
dof = { node = 1, dir = "w" }
basis = ["u"]
[integrator]
dt_s = 0.001
"#;

    #[test]
    fn sdof_free_vibration_matches_analytic_with_newmark_period_error() {
        // ω = 20 rad/s. Average acceleration conserves energy exactly and its period error is
        // (ωh)²/12 to leading order: compare the discrete solution to cos(ω̃t) with
        // ω̃ = (2/h)·atan(ωh/2), the exact discrete frequency of the trapezoidal rule.
        let s = Setup::from_toml(SDOF, "t").unwrap();
        let m = Model::assemble(&s).unwrap();
        let mut st = Stepper::new(&m, 0.01, 1, s.newmark).unwrap();
        let mut x = State::zeros(1);
        x.u[0] = 1.0;
        x.a[0] = -400.0;
        let f = DVector::zeros(1);
        let w = 20.0f64;
        let h = 0.01;
        let wd = 2.0 / h * (w * h / 2.0).atan();
        for i in 1..=500 {
            st.advance(&mut x, &[0.0], &[0.0], &f);
            let t = i as f64 * h;
            assert!((x.u[0] - (wd * t).cos()).abs() < 1e-9, "step {i}");
            let energy = 0.5 * 2.0 * x.v[0].powi(2) + 0.5 * 800.0 * x.u[0].powi(2);
            assert!((energy - 400.0).abs() < 1e-8);
        }
    }

    #[test]
    fn substeps_converge_to_the_continuous_forced_response() {
        // Step load on an undamped SDOF from rest: u = (P/k)(1 − cos ωt).
        let s = Setup::from_toml(SDOF, "t").unwrap();
        let m = Model::assemble(&s).unwrap();
        let f = DVector::zeros(1);
        let err = |ns: usize| {
            let mut st = Stepper::new(&m, 0.01, ns, s.newmark).unwrap();
            let mut x = State::zeros(1);
            x.a[0] = 50.0;
            for _ in 0..100 {
                st.advance(&mut x, &[100.0], &[100.0], &f);
            }
            (x.u[0] - 100.0 / 800.0 * (1.0 - (20.0f64 * 1.0).cos())).abs()
        };
        let (e1, e8) = (err(1), err(8));
        assert!(e8 < e1 / 40.0, "second order: {e1} -> {e8}");
    }

    #[test]
    fn superposition_of_force_response() {
        // Linearity: advance(x, f) = advance(x, 0) + Γ_f f.
        let s = Setup::from_toml(SDOF, "t").unwrap();
        let m = Model::assemble(&s).unwrap();
        let mut st = Stepper::new(&m, 0.01, 3, s.newmark).unwrap();
        let g = st.force_response();
        let mut x0 = State::zeros(1);
        x0.u[0] = 0.3;
        x0.v[0] = -1.0;
        let mut a = x0.clone();
        let mut b = x0.clone();
        st.advance(&mut a, &[1.0], &[2.0], &DVector::from_element(1, 0.0));
        st.advance(&mut b, &[1.0], &[2.0], &DVector::from_element(1, 7.0));
        assert!((b.u[0] - a.u[0] - 7.0 * g[(0, 0)]).abs() < 1e-14);
        assert!((b.v[0] - a.v[0] - 7.0 * g[(1, 0)]).abs() < 1e-12);
        assert!((b.a[0] - a.a[0] - 7.0 * g[(2, 0)]).abs() < 1e-10);
    }
}
