//! The one-sample Newmark map with sparse matrices: the same linear map as
//! [`super::Stepper`] (same sub-steps, excitation interpolated linearly, connection force
//! held), at a cost per sample proportional to the non-zeros of `M`, `C`, `K` and of the
//! Cholesky factor of `M + γhC + βh²K`.
//!
//! Set-up: one envelope Cholesky factorisation of the effective mass (ordering chosen in
//! [`crate::sparse`]), one of `M` (for the initial acceleration), nothing `O(n²)`. Per
//! sub-step: the predictors (`O(n)`), `rhs = Lp p − Lc f − C ṽ − K ũ` by sparse mat-vecs
//! (`O(nnz(C) + nnz(K))`), two triangular solves (`O(nnz(L))`), the correctors (`O(n)`),
//! all on preallocated vectors. Unlike the modal map the sub-steps do not compose: `s`
//! sub-steps per sample cost `s` times one. The estimator then adds `Γ_f R` (`O(3 n q)`)
//! and picks the stations' values (`O(channels)`).
#![allow(non_snake_case)]

use nalgebra::{DMatrix, DVector};

use super::{IntegrateError, State};
use crate::model::Model;
use crate::setup::Newmark;
use crate::sparse::{CsrMatrix, EnvelopeCholesky};

/// The exact one-sample map with sparse operators (see the module docs).
#[derive(Debug, Clone)]
pub struct SparseStep {
    pub n: usize,
    pub dt_s: f64,
    pub substeps: usize,
    pub newmark: Newmark,
    /// Factor of `M + γhC + βh²K`.
    pub meff: EnvelopeCholesky,
    mass: EnvelopeCholesky,
    pub C: CsrMatrix,
    pub K: CsrMatrix,
    /// Non-zeros of `Lp` and `Lc`: (DOF, column, coefficient).
    lp: Vec<(usize, usize, f64)>,
    pub lc: Vec<(usize, usize, f64)>,
    ne: usize,
    q: usize,
    // Work vectors (no allocation per sample).
    u_t: Vec<f64>,
    v_t: Vec<f64>,
    rhs: Vec<f64>,
    work: Vec<f64>,
    p_t: Vec<f64>,
}

fn nonzeros(a: &DMatrix<f64>) -> Vec<(usize, usize, f64)> {
    let mut v = Vec::new();
    for j in 0..a.ncols() {
        for i in 0..a.nrows() {
            if a[(i, j)] != 0.0 {
                v.push((i, j, a[(i, j)]));
            }
        }
    }
    v
}

impl SparseStep {
    pub fn new(
        model: &Model,
        dt_s: f64,
        substeps: usize,
        newmark: Newmark,
    ) -> Result<Self, IntegrateError> {
        let parts = model.sparse_parts();
        let n = model.n();
        let h = dt_s / substeps as f64;
        let meff_m = parts.M.lin_comb(1.0, &parts.C, newmark.gamma * h).lin_comb(
            1.0,
            &parts.K,
            newmark.beta * h * h,
        );
        let meff =
            EnvelopeCholesky::factor(&meff_m).ok_or(IntegrateError::SingularEffectiveMass)?;
        let mass =
            EnvelopeCholesky::factor(&parts.M).ok_or(IntegrateError::SingularEffectiveMass)?;
        Ok(Self {
            n,
            dt_s,
            substeps,
            newmark,
            meff,
            mass,
            C: parts.C.clone(),
            K: parts.K.clone(),
            lp: nonzeros(&model.Lp),
            lc: nonzeros(&model.Lc),
            ne: model.Lp.ncols(),
            q: model.Lc.ncols(),
            u_t: vec![0.0; n],
            v_t: vec![0.0; n],
            rhs: vec![0.0; n],
            work: vec![0.0; n],
            p_t: vec![0.0; model.Lp.ncols()],
        })
    }

    pub fn h(&self) -> f64 {
        self.dt_s / self.substeps as f64
    }

    /// Bytes of the operators the step reads: C, K (values + indices), the factor, Lp, Lc.
    pub fn operator_bytes(&self) -> usize {
        let (f, u) = (std::mem::size_of::<f64>(), std::mem::size_of::<usize>());
        (self.C.nnz() + self.K.nnz()) * (f + u)
            + 2 * (self.n + 1) * u
            + self.meff.solve_bytes()
            + (self.lp.len() + self.lc.len()) * (f + 2 * u)
    }

    /// Initial acceleration: `M a₀ = Lp p₀ − Lc f₀ − C v₀ − K u₀`.
    pub fn initial_acceleration(&mut self, state: &mut State, p0: &[f64], f0: &DVector<f64>) {
        self.rhs.fill(0.0);
        for &(i, j, c) in &self.lp {
            self.rhs[i] += c * p0[j];
        }
        for &(i, j, c) in &self.lc {
            self.rhs[i] -= c * f0[j];
        }
        self.C.mul_add(1.0, &mut self.rhs, -1.0, state.v.as_slice());
        self.K.mul_add(1.0, &mut self.rhs, -1.0, state.u.as_slice());
        self.mass.solve_in_place(&mut self.rhs, &mut self.work);
        state.a.as_mut_slice().copy_from_slice(&self.rhs);
    }

    /// Advance `state` over one sample interval with the excitation going linearly from
    /// `p_prev` to `p_next` and a constant connection force `f` (positive resisting).
    /// Allocation-free.
    pub fn advance(&mut self, state: &mut State, p_prev: &[f64], p_next: &[f64], f: &DVector<f64>) {
        let h = self.h();
        let Newmark { gamma, beta } = self.newmark;
        let ns = self.substeps;
        let (cu, cv) = ((0.5 - beta) * h * h, (1.0 - gamma) * h);
        let (bu, gv) = (beta * h * h, gamma * h);
        for s in 1..=ns {
            let t = s as f64 / ns as f64;
            for (j, pt) in self.p_t.iter_mut().enumerate() {
                *pt = p_prev[j] + t * (p_next[j] - p_prev[j]);
            }
            let (u, v, a) = (
                state.u.as_mut_slice(),
                state.v.as_mut_slice(),
                state.a.as_mut_slice(),
            );
            // Predictors ũ = u + h v + (½−β)h² a, ṽ = v + (1−γ)h a.
            for i in 0..self.n {
                self.u_t[i] = u[i] + h * v[i] + cu * a[i];
                self.v_t[i] = v[i] + cv * a[i];
            }
            // rhs = Lp p − Lc f − C ṽ − K ũ.
            self.C.mul_add(0.0, &mut self.rhs, -1.0, &self.v_t);
            self.K.mul_add(1.0, &mut self.rhs, -1.0, &self.u_t);
            for &(i, j, c) in &self.lp {
                self.rhs[i] += c * self.p_t[j];
            }
            for &(i, j, c) in &self.lc {
                self.rhs[i] -= c * f[j];
            }
            self.meff.solve_in_place(&mut self.rhs, &mut self.work);
            for i in 0..self.n {
                let ai = self.rhs[i];
                a[i] = ai;
                u[i] = self.u_t[i] + bu * ai;
                v[i] = self.v_t[i] + gv * ai;
            }
        }
    }

    /// Γ_f: response of the state over one sample to a unit connection force held over the
    /// interval, from rest with no excitation; columns (u; v; a) stacked, 3n × q. Costs q
    /// samples' worth of sub-steps.
    pub fn force_response(&mut self) -> DMatrix<f64> {
        let (n, q) = (self.n, self.q);
        let zeros = vec![0.0; self.ne];
        let mut out = DMatrix::zeros(3 * n, q);
        let mut s = State::zeros(n);
        let mut f = DVector::zeros(q);
        for j in 0..q {
            s.u.fill(0.0);
            s.v.fill(0.0);
            s.a.fill(0.0);
            f.fill(0.0);
            f[j] = 1.0;
            self.advance(&mut s, &zeros, &zeros, &f);
            out.view_mut((0, j), (n, 1)).copy_from(&s.u);
            out.view_mut((n, j), (n, 1)).copy_from(&s.v);
            out.view_mut((2 * n, j), (n, 1)).copy_from(&s.a);
        }
        out
    }

    /// `δ = Lcᵀ x` for one of u, v, a (O(non-zeros of Lc)).
    #[inline]
    pub fn deformation(&self, x: &DVector<f64>, out: &mut DVector<f64>) {
        out.fill(0.0);
        for &(i, j, c) in &self.lc {
            out[j] += c * x[i];
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::integrate::Stepper;
    use crate::integrate::fast::{ModalState, ModalStep};
    use crate::setup::{Dir, DofRef, StepKind};
    use rand::{RngExt, SeedableRng};
    use rand_chacha::ChaCha8Rng;

    /// A random banded model with its DOFs shuffled (so the RCM ordering is exercised):
    /// diagonal or banded SPD mass, banded PSD stiffness (a chain of random springs of
    /// random reach, grounded at one DOF), Rayleigh damping, optionally two dashpots.
    fn banded_model(rng: &mut ChaCha8Rng, n: usize, reach: usize, dashpots: bool) -> Model {
        let mut perm: Vec<usize> = (0..n).collect();
        for i in (1..n).rev() {
            let j = rng.random_range(0..=i);
            perm.swap(i, j);
        }
        let mut M = DMatrix::zeros(n, n);
        let mut K = DMatrix::zeros(n, n);
        for i in 0..n {
            M[(perm[i], perm[i])] += rng.random_range(0.01..0.02);
            for d in 1..=reach {
                if i + d < n {
                    let (a, b) = (perm[i], perm[i + d]);
                    let k = rng.random_range(0.5e6..1.5e6);
                    K[(a, a)] += k;
                    K[(b, b)] += k;
                    K[(a, b)] -= k;
                    K[(b, a)] -= k;
                    if d == 1 && rng.random_range(0.0..1.0) < 0.5 {
                        // A consistent-mass-like coupling keeps M banded, SPD.
                        let m = rng.random_range(0.0..0.002);
                        M[(a, a)] += 2.0 * m;
                        M[(b, b)] += 2.0 * m;
                        M[(a, b)] += m;
                        M[(b, a)] += m;
                    }
                }
            }
        }
        K[(perm[0], perm[0])] += 1e4;
        let (alpha, beta) = (2.0, 1e-7);
        let mut C = &M * alpha + &K * beta;
        if dashpots {
            C[(perm[1], perm[1])] += 3.0;
            let (a, b) = (perm[2], perm[3]);
            C[(a, a)] += 2.0;
            C[(b, b)] += 2.0;
            C[(a, b)] -= 2.0;
            C[(b, a)] -= 2.0;
        }
        let mut Lp = DMatrix::zeros(n, 2);
        Lp[(perm[0], 0)] = 1.0;
        Lp[(perm[n / 2], 1)] = 1.0;
        let mut Lc = DMatrix::zeros(n, 2);
        Lc[(perm[n / 3], 0)] = 1.0;
        Lc[(perm[n - 1], 1)] = 1.0;
        Lc[(perm[n - 2], 1)] = -1.0;
        Model {
            dofs: (0..n as u32)
                .map(|node| DofRef { node, dir: Dir::W })
                .collect(),
            M,
            C,
            K,
            Lp,
            Lc,
            stations: Vec::new(),
            rayleigh: (alpha, beta),
            step: StepKind::Sparse,
            sparse: None,
        }
    }

    fn rel(a: &DVector<f64>, b: &DVector<f64>) -> f64 {
        (a - b).amax() / b.amax().max(1e-300)
    }

    #[test]
    fn sparse_map_equals_the_dense_and_modal_maps_on_random_banded_models() {
        let mut rng = ChaCha8Rng::seed_from_u64(11);
        let nm = Newmark {
            gamma: 0.5,
            beta: 0.25,
        };
        let mut used_rcm = 0;
        for case in 0..18 {
            let n = 8 + 5 * case;
            let reach = 1 + case % 3;
            let model = banded_model(&mut rng, n, reach, case % 2 == 1);
            let substeps = 1 + case % 3;
            let dt = 1.953125e-5;
            let mut dense = Stepper::new(&model, dt, substeps, nm).unwrap();
            let mut sparse = SparseStep::new(&model, dt, substeps, nm).unwrap();
            let mut modal = ModalStep::new(&model, dt, substeps, nm).unwrap();
            used_rcm += usize::from(sparse.meff.rcm);
            // Little fill: the envelope stays within a band of a few times the reach.
            assert!(
                sparse.meff.nnz() <= n * (4 * reach + 2),
                "case {case}: envelope {} for n {n}",
                sparse.meff.nnz()
            );
            let mut xd = State::zeros(n);
            for i in 0..n {
                xd.u[i] = rng.random_range(-1e-3..1e-3);
                xd.v[i] = rng.random_range(-0.1..0.1);
                xd.a[i] = rng.random_range(-100.0..100.0);
            }
            let mut xs = xd.clone();
            let mut xm = ModalState {
                q: modal.to_modal(&model.M, &xd.u),
                qd: modal.to_modal(&model.M, &xd.v),
                qdd: modal.to_modal(&model.M, &xd.a),
            };
            for _ in 0..5 {
                let p0 = [rng.random_range(-1.0..1.0), rng.random_range(-1.0..1.0)];
                let p1 = [rng.random_range(-1.0..1.0), rng.random_range(-1.0..1.0)];
                let f = DVector::from_fn(2, |_, _| rng.random_range(-1.0..1.0));
                dense.advance(&mut xd, &p0, &p1, &f);
                sparse.advance(&mut xs, &p0, &p1, &f);
                modal.advance(&mut xm, &p0, &p1, &f);
            }
            for (a, b) in [(&xs.u, &xd.u), (&xs.v, &xd.v), (&xs.a, &xd.a)] {
                assert!(
                    rel(a, b) < 1e-10,
                    "case {case}: sparse vs dense {}",
                    rel(a, b)
                );
            }
            let um = &modal.psi * &xm.q;
            assert!(
                rel(&xs.u, &um) < 1e-9,
                "case {case}: sparse vs modal {}",
                rel(&xs.u, &um)
            );
            let (gd, gs) = (dense.force_response(), sparse.force_response());
            assert!((&gd - &gs).amax() <= 1e-10 * gd.amax(), "case {case}: Γ_f");
            // Initial acceleration.
            let mut ad = xd.clone();
            let mut as_ = xd.clone();
            let f0 = DVector::from_element(2, 0.3);
            dense.initial_acceleration(&mut ad, &[0.5, -0.2], &f0);
            sparse.initial_acceleration(&mut as_, &[0.5, -0.2], &f0);
            assert!(rel(&as_.a, &ad.a) < 1e-10, "case {case}: a₀");
        }
        assert!(
            used_rcm > 10,
            "the shuffled models should pick RCM: {used_rcm}"
        );
    }
}
