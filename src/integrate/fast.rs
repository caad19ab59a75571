//! The one-sample Newmark map in mass-normalised modal coordinates: the same linear map as
//! [`super::Stepper`], at a per-sample cost linear in the number of modes.
//!
//! # What is computed
//!
//! One sample of `s` Newmark sub-steps, excitation interpolated linearly and connection
//! force held (see the parent module), is an exact linear map on `x = (u, u̇, ü)`:
//! `x⁺ = Φ x + Γ₀ p_prev + Γ₁ p_next + Γ_f f`. With the modes of `K ψ = ω² M ψ`, normalised
//! `ΨᵀMΨ = I`, and `u = Ψ η`, the Newmark recursion is the same recursion on `η` (Newmark is
//! linear and `Ψ` is constant), with `ΨᵀKΨ = Ω²` diagonal and `ΨᵀCΨ`:
//!
//! - **classical damping** (none, Rayleigh `αM + βK`): `ΨᵀCΨ = diag(α + βω²)`, the modes
//!   decouple and the whole sample (all `s` sub-steps) is, per mode, a 3 × 3 matrix `T` and
//!   three 3-vectors `c₀, c₁, c_f` composed once at set-up: per sample
//!   `η⁺ = T η + c₀ P₀ + c₁ P₁ + c_f F` with the modal loads `P = ΨᵀLp p`, `F = ΨᵀLc f`.
//!   Cost per sample `O(modes · (inputs + connections))`, independent of `s`.
//! - **classical plus a localised part** (dashpots, the `v` terms of connections, a damping
//!   matrix from a file whose non-Rayleigh part sits on a few DOFs): `C − αM − βK` is
//!   non-zero on a small DOF set `S` only, so `ΨᵀCΨ = D + U Σ Uᵀ` with `U = Ψ_Sᵀ V |λ|^½`
//!   of rank `k ≤ |S|` (`Σ = sign λ`). The modes do not decouple; each sub-step solves
//!   `(A + γh U Σ Uᵀ) η̈ = r` with `A` diagonal by Sherman–Morrison–Woodbury, cost
//!   `O(modes · k)`; per sample `O(s · modes · (k + inputs + connections))`.
//! - otherwise (a full non-proportional damping matrix, `|S|` above [`MAX_LOCAL_DAMPING`])
//!   there is no exact cheap form and [`ModalStep::new`] says why; `step = "auto"` then uses
//!   the dense stepper.
//!
//! No mode is dropped: the map is exact up to the round-off of the eigen-decomposition
//! (the tests compare it with the dense map to 1e-10 relative). Modes far above the
//! Nyquist frequency are kept: Newmark's average-acceleration rule is unconditionally
//! stable and handles them exactly as the dense stepper does.
//!
//! # Why this and not a sparse factorisation
//!
//! A sparse Cholesky of `M + γhC + βh²K` ([`super::sparse`]) makes a sub-step `O(nnz)`,
//! but the estimators still take `s` sub-steps per sample and form the full state. In
//! modal form the sub-steps collapse into one 3 × 3 map per mode and the
//! stations need only their own rows of `Ψ` (`O(channels · modes)`), which is what the
//! paper estimator consumes. Measured (`examples/bench_model.rs`, `BENCHMARKS.md`): 5–16×
//! the dense step at 240 DOFs, 90–2,400× at 2,400 DOFs; at 24 DOFs within a factor 2
//! either way. The price is the dense eigen-decomposition at set-up, `O(n³)`: 23–32 s at
//! 2,400 DOFs on one core, infeasible at 24,000 DOFs with dense storage (that needs a
//! sparse Lanczos basis, not implemented); there the sparse step is the one that runs.
//! Which is faster per sample depends on channels and connections (`BENCHMARKS.md`;
//! `step = "auto"` picks by operation count, `estimate::paper::choose_auto`).
#![allow(non_snake_case)]

use nalgebra::{DMatrix, DVector};

use crate::model::Model;
use crate::setup::{Newmark, Quantity};

/// Largest number of DOFs carrying non-proportional damping that the low-rank form accepts.
pub const MAX_LOCAL_DAMPING: usize = 64;

#[derive(Debug, thiserror::Error)]
pub enum FastError {
    #[error(
        "the damping is not classical: C − αM − βK is non-zero on {dofs} DOFs (the modal step accepts at most {max}); use the dense step"
    )]
    NonClassicalDamping { dofs: usize, max: usize },
    #[error("the mass matrix is not positive definite (Cholesky failed)")]
    MassNotDefinite,
    #[error("the modal effective mass is singular (Woodbury capacitance not invertible)")]
    Singular,
}

/// Modal state: `η, η̇, η̈` (mass-normalised modal coordinates, kg^½·m etc.).
#[derive(Debug, Clone, PartialEq)]
pub struct ModalState {
    pub q: DVector<f64>,
    pub qd: DVector<f64>,
    pub qdd: DVector<f64>,
}

impl ModalState {
    pub fn zeros(r: usize) -> Self {
        Self {
            q: DVector::zeros(r),
            qd: DVector::zeros(r),
            qdd: DVector::zeros(r),
        }
    }

    pub fn is_finite(&self) -> bool {
        self.q
            .iter()
            .chain(self.qd.iter())
            .chain(self.qdd.iter())
            .all(|x| x.is_finite())
    }

    /// `self += Γ · f` with `Γ` a stacked (η; η̇; η̈) response, 3r × q.
    pub fn add_response(&mut self, gamma: &DMatrix<f64>, f: &DVector<f64>) {
        let r = self.q.len();
        self.q.gemv(1.0, &gamma.rows(0, r), f, 1.0);
        self.qd.gemv(1.0, &gamma.rows(r, r), f, 1.0);
        self.qdd.gemv(1.0, &gamma.rows(2 * r, r), f, 1.0);
    }

    pub fn copy_from(&mut self, o: &ModalState) {
        self.q.copy_from(&o.q);
        self.qd.copy_from(&o.qd);
        self.qdd.copy_from(&o.qdd);
    }
}

/// Per-mode composed map of one sample (classical damping): `T` row-major, `c₀, c₁, c_f`.
#[derive(Debug, Clone, Copy)]
struct ModeMap {
    t: [f64; 9],
    c0: [f64; 3],
    c1: [f64; 3],
    cf: [f64; 3],
}

#[derive(Debug, Clone)]
enum Kind {
    Composed(Vec<ModeMap>),
    /// Sub-step recursion with Woodbury: `a` = diag(A), `u` (r × k), `w = A⁻¹U`,
    /// `cap_inv` (k × k).
    LowRank {
        a: DVector<f64>,
        u: DMatrix<f64>,
        sign: DVector<f64>,
        w: DMatrix<f64>,
        cap_inv: DMatrix<f64>,
    },
}

/// The exact one-sample map in modal coordinates (see the module docs).
#[derive(Debug, Clone)]
pub struct ModalStep {
    pub dt_s: f64,
    pub substeps: usize,
    pub newmark: Newmark,
    /// Mass-normalised mode shapes (n × r), columns in ascending frequency.
    pub psi: DMatrix<f64>,
    /// `ω²` per mode, rad²/s².
    pub omega2: DVector<f64>,
    /// Classical (Rayleigh) modal damping `α + βω²` per mode, 1/s.
    pub d: DVector<f64>,
    /// `ΨᵀLp` (r × excitation channels) and `ΨᵀLc` (r × connections).
    pub bp: DMatrix<f64>,
    pub bc: DMatrix<f64>,
    kind: Kind,
    // Work vectors (no allocation per sample).
    p0: DVector<f64>,
    p1: DVector<f64>,
    fm: DVector<f64>,
    pin: DVector<f64>,
    ut: DVector<f64>,
    vt: DVector<f64>,
    rhs: DVector<f64>,
    z: DVector<f64>,
    z2: DVector<f64>,
}

impl ModalStep {
    pub fn new(
        model: &Model,
        dt_s: f64,
        substeps: usize,
        newmark: Newmark,
    ) -> Result<Self, FastError> {
        let n = model.n();
        // Non-proportional part of the damping and where it sits.
        let (alpha, beta) = model.rayleigh;
        let cnc = &model.C - &model.M * alpha - &model.K * beta;
        let scale = model.C.amax().max(f64::MIN_POSITIVE);
        let support: Vec<usize> = (0..n)
            .filter(|&i| cnc.row(i).iter().any(|v| v.abs() > 1e-13 * scale))
            .collect();
        if support.len() > MAX_LOCAL_DAMPING {
            return Err(FastError::NonClassicalDamping {
                dofs: support.len(),
                max: MAX_LOCAL_DAMPING,
            });
        }
        // Generalised eigenproblem through the Cholesky factor of M, `A = L⁻¹ K L⁻ᵀ`,
        // `Ψ = L⁻ᵀ V`. A diagonal (lumped) M needs no factorisation: `L = diag(√m)`, and the
        // two O(n³) triangular solves (a third of the set-up at 1,200 DOFs, measured with
        // perf) become O(n²) scalings.
        let diagonal = (0..n).all(|j| (0..n).all(|i| i == j || model.M[(i, j)] == 0.0));
        let (a, l) = if diagonal {
            let s = DVector::from_fn(n, |i, _| model.M[(i, i)]);
            if s.iter().any(|m| m.is_nan() || *m <= 0.0) {
                return Err(FastError::MassNotDefinite);
            }
            let s = s.map(|m| 1.0 / m.sqrt());
            (
                DMatrix::from_fn(n, n, |i, j| model.K[(i, j)] * s[i] * s[j]),
                Err(s),
            )
        } else {
            let chol = model
                .M
                .clone()
                .cholesky()
                .ok_or(FastError::MassNotDefinite)?;
            let l = chol.l();
            let linv_k = l
                .solve_lower_triangular(&model.K)
                .ok_or(FastError::MassNotDefinite)?;
            let a = l
                .solve_lower_triangular(&linv_k.transpose())
                .ok_or(FastError::MassNotDefinite)?;
            (a, Ok(l))
        };
        let a = (&a + a.transpose()) * 0.5;
        let eig = a.symmetric_eigen();
        let mut order: Vec<usize> = (0..n).collect();
        order.sort_by(|&i, &j| eig.eigenvalues[i].total_cmp(&eig.eigenvalues[j]));
        let v = DMatrix::from_fn(n, n, |i, j| eig.eigenvectors[(i, order[j])]);
        let omega2 = DVector::from_fn(n, |j, _| eig.eigenvalues[order[j]].max(0.0));
        let psi = match l {
            Err(s) => DMatrix::from_fn(n, n, |i, j| v[(i, j)] * s[i]),
            Ok(l) => l
                .transpose()
                .solve_upper_triangular(&v)
                .ok_or(FastError::MassNotDefinite)?,
        };
        let bp = psi.transpose() * &model.Lp;
        let bc = psi.transpose() * &model.Lc;
        let r = n;
        let h = dt_s / substeps as f64;
        let Newmark { gamma, beta: nb } = newmark;
        let d = DVector::from_fn(r, |j, _| alpha + beta * omega2[j]);
        let kind = if support.is_empty() {
            Kind::Composed(
                (0..r)
                    .map(|j| compose(d[j], omega2[j], h, substeps, newmark))
                    .collect(),
            )
        } else {
            let ns = support.len();
            let css = DMatrix::from_fn(ns, ns, |i, j| cnc[(support[i], support[j])]);
            let css = (&css + css.transpose()) * 0.5;
            let e = css.symmetric_eigen();
            let lmax = e.eigenvalues.amax();
            let keep: Vec<usize> = (0..ns)
                .filter(|&i| e.eigenvalues[i].abs() > 1e-13 * lmax)
                .collect();
            let k = keep.len();
            let psi_s = DMatrix::from_fn(ns, r, |i, j| psi[(support[i], j)]);
            let vs = DMatrix::from_fn(ns, k, |i, c| {
                e.eigenvectors[(i, keep[c])] * e.eigenvalues[keep[c]].abs().sqrt()
            });
            let u = psi_s.transpose() * vs;
            let sign = DVector::from_fn(k, |c, _| e.eigenvalues[keep[c]].signum());
            let adiag = DVector::from_fn(r, |j, _| 1.0 + gamma * h * d[j] + nb * h * h * omega2[j]);
            let w = DMatrix::from_fn(r, k, |j, c| u[(j, c)] / adiag[j]);
            let mut cap = u.transpose() * &w;
            for c in 0..k {
                cap[(c, c)] += sign[c] / (gamma * h);
            }
            let cap_inv = cap.try_inverse().ok_or(FastError::Singular)?;
            Kind::LowRank {
                a: adiag,
                u,
                sign,
                w,
                cap_inv,
            }
        };
        let k = match &kind {
            Kind::LowRank { u, .. } => u.ncols(),
            Kind::Composed(_) => 0,
        };
        Ok(Self {
            dt_s,
            substeps,
            newmark,
            omega2,
            d,
            p0: DVector::zeros(r),
            p1: DVector::zeros(r),
            fm: DVector::zeros(r),
            pin: DVector::zeros(model.Lp.ncols()),
            ut: DVector::zeros(r),
            vt: DVector::zeros(r),
            rhs: DVector::zeros(r),
            z: DVector::zeros(k),
            z2: DVector::zeros(k),
            psi,
            bp,
            bc,
            kind,
        })
    }

    /// Number of modes kept (all of them: no truncation).
    pub fn modes(&self) -> usize {
        self.omega2.len()
    }

    /// Rank of the non-proportional damping (0: the modes decouple and sub-steps compose).
    pub fn damping_rank(&self) -> usize {
        match &self.kind {
            Kind::Composed(_) => 0,
            Kind::LowRank { u, .. } => u.ncols(),
        }
    }

    /// Bytes of the precomputed per-sample operators (mode maps, `ΨᵀLp`, `ΨᵀLc`, low-rank
    /// factors), not counting `Ψ` itself, which only the output rows need.
    pub fn operator_bytes(&self) -> usize {
        let f = std::mem::size_of::<f64>();
        let k = match &self.kind {
            Kind::Composed(v) => v.len() * std::mem::size_of::<ModeMap>(),
            Kind::LowRank { u, w, cap_inv, .. } => {
                (u.len() + w.len() + cap_inv.len() + 3 * self.modes()) * f
            }
        };
        k + (self.bp.len() + self.bc.len() + self.omega2.len()) * f
    }

    /// Modal state from a physical one: `η = ΨᵀM u` etc. (O(n²), for set-up only).
    pub fn to_modal(&self, m: &DMatrix<f64>, u: &DVector<f64>) -> DVector<f64> {
        self.psi.transpose() * (m * u)
    }

    /// Acceleration consistent with the state under excitation `p0` and connection force
    /// `f0`: `η̈ = ΨᵀLp p₀ − ΨᵀLc f₀ − ΨᵀCΨ η̇ − Ω² η`.
    pub fn initial_acceleration(&mut self, st: &mut ModalState, p0: &[f64], f0: &DVector<f64>) {
        self.pin.copy_from_slice(p0);
        st.qdd.gemv(1.0, &self.bp, &self.pin, 0.0);
        st.qdd.gemv(-1.0, &self.bc, f0, 1.0);
        st.qdd
            .zip_zip_apply(&st.q, &self.omega2, |a, q, w2| *a -= w2 * q);
        let ModalState { qd, qdd, .. } = st;
        self.damping_force(qd, qdd);
    }

    /// `out −= ΨᵀCΨ v`.
    fn damping_force(&mut self, v: &DVector<f64>, out: &mut DVector<f64>) {
        for j in 0..v.len() {
            out[j] -= self.d[j] * v[j];
        }
        if let Kind::LowRank { u, sign, .. } = &self.kind {
            self.z.gemv_tr(1.0, u, v, 0.0);
            self.z.component_mul_assign(sign);
            out.gemv(-1.0, u, &self.z, 1.0);
        }
    }

    /// Advance over one sample: excitation linear from `p_prev` to `p_next`, connection
    /// force `f` (positive resisting) held. Allocation-free.
    pub fn advance(
        &mut self,
        st: &mut ModalState,
        p_prev: &[f64],
        p_next: &[f64],
        f: &DVector<f64>,
    ) {
        self.pin.copy_from_slice(p_prev);
        self.p0.gemv(1.0, &self.bp, &self.pin, 0.0);
        self.pin.copy_from_slice(p_next);
        self.p1.gemv(1.0, &self.bp, &self.pin, 0.0);
        self.fm.gemv(1.0, &self.bc, f, 0.0);
        match &self.kind {
            Kind::Composed(maps) => {
                for (j, m) in maps.iter().enumerate() {
                    let (x0, x1, x2) = (st.q[j], st.qd[j], st.qdd[j]);
                    let (p0, p1, fj) = (self.p0[j], self.p1[j], self.fm[j]);
                    let t = &m.t;
                    st.q[j] = t[0] * x0
                        + t[1] * x1
                        + t[2] * x2
                        + m.c0[0] * p0
                        + m.c1[0] * p1
                        + m.cf[0] * fj;
                    st.qd[j] = t[3] * x0
                        + t[4] * x1
                        + t[5] * x2
                        + m.c0[1] * p0
                        + m.c1[1] * p1
                        + m.cf[1] * fj;
                    st.qdd[j] = t[6] * x0
                        + t[7] * x1
                        + t[8] * x2
                        + m.c0[2] * p0
                        + m.c1[2] * p1
                        + m.cf[2] * fj;
                }
            }
            Kind::LowRank {
                a,
                u,
                sign,
                w,
                cap_inv,
            } => {
                let h = self.dt_s / self.substeps as f64;
                let Newmark { gamma, beta } = self.newmark;
                let ns = self.substeps;
                for s in 1..=ns {
                    let t = s as f64 / ns as f64;
                    for j in 0..st.q.len() {
                        let ut = st.q[j] + h * st.qd[j] + (0.5 - beta) * h * h * st.qdd[j];
                        let vt = st.qd[j] + (1.0 - gamma) * h * st.qdd[j];
                        self.ut[j] = ut;
                        self.vt[j] = vt;
                        self.rhs[j] = self.p0[j] + t * (self.p1[j] - self.p0[j])
                            - self.fm[j]
                            - self.d[j] * vt
                            - self.omega2[j] * ut;
                    }
                    // rhs −= U Σ Uᵀ ṽ
                    self.z.gemv_tr(1.0, u, &self.vt, 0.0);
                    self.z.component_mul_assign(sign);
                    self.rhs.gemv(-1.0, u, &self.z, 1.0);
                    // η̈ = A⁻¹rhs − W cap⁻¹ Uᵀ A⁻¹ rhs
                    st.qdd.copy_from(&self.rhs);
                    st.qdd.component_div_assign(a);
                    self.z.gemv_tr(1.0, u, &st.qdd, 0.0);
                    self.z2.gemv(1.0, cap_inv, &self.z, 0.0);
                    st.qdd.gemv(-1.0, w, &self.z2, 1.0);
                    for j in 0..st.q.len() {
                        st.q[j] = self.ut[j] + beta * h * h * st.qdd[j];
                        st.qd[j] = self.vt[j] + gamma * h * st.qdd[j];
                    }
                }
            }
        }
    }

    /// Γ_f in modal coordinates: response over one sample to a unit connection force, from
    /// rest without excitation; (η; η̇; η̈) stacked, 3r × q.
    pub fn force_response(&mut self) -> DMatrix<f64> {
        let r = self.modes();
        let q = self.bc.ncols();
        let zeros = vec![0.0; self.bp.ncols()];
        let mut out = DMatrix::zeros(3 * r, q);
        let mut st = ModalState::zeros(r);
        let mut f = DVector::zeros(q);
        for j in 0..q {
            st.q.fill(0.0);
            st.qd.fill(0.0);
            st.qdd.fill(0.0);
            f.fill(0.0);
            f[j] = 1.0;
            self.advance(&mut st, &zeros, &zeros, &f);
            out.view_mut((0, j), (r, 1)).copy_from(&st.q);
            out.view_mut((r, j), (r, 1)).copy_from(&st.qd);
            out.view_mut((2 * r, j), (r, 1)).copy_from(&st.qdd);
        }
        out
    }
}

/// One sub-step of mode `(d, ω²)` as `x' = A x + b g` (g: modal load at the sub-step end),
/// composed over the `s` sub-steps of a sample with the load interpolated.
fn compose(d: f64, w2: f64, h: f64, s: usize, nm: Newmark) -> ModeMap {
    let Newmark { gamma, beta } = nm;
    let am = 1.0 + gamma * h * d + beta * h * h * w2;
    let step = |x: [f64; 3], g: f64| -> [f64; 3] {
        let ut = x[0] + h * x[1] + (0.5 - beta) * h * h * x[2];
        let vt = x[1] + (1.0 - gamma) * h * x[2];
        let acc = (g - d * vt - w2 * ut) / am;
        [ut + beta * h * h * acc, vt + gamma * h * acc, acc]
    };
    let mut a = [[0.0; 3]; 3]; // a[col] = A e_col
    for (c, col) in a.iter_mut().enumerate() {
        let mut e = [0.0; 3];
        e[c] = 1.0;
        *col = step(e, 0.0);
    }
    let b = step([0.0; 3], 1.0);
    let apply = |x: [f64; 3]| -> [f64; 3] {
        let mut y = [0.0; 3];
        for (c, col) in a.iter().enumerate() {
            for i in 0..3 {
                y[i] += col[i] * x[c];
            }
        }
        y
    };
    let mut tcols = [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]];
    let (mut c0, mut c1, mut cf) = ([0.0; 3], [0.0; 3], [0.0; 3]);
    for k in 1..=s {
        let t = k as f64 / s as f64;
        for col in tcols.iter_mut() {
            *col = apply(*col);
        }
        c0 = apply(c0);
        c1 = apply(c1);
        cf = apply(cf);
        for i in 0..3 {
            c0[i] += b[i] * (1.0 - t);
            c1[i] += b[i] * t;
            cf[i] -= b[i];
        }
    }
    let mut t = [0.0; 9];
    for (c, col) in tcols.iter().enumerate() {
        for i in 0..3 {
            t[3 * i + c] = col[i];
        }
    }
    ModeMap { t, c0, c1, cf }
}

/// Station outputs and connection deformations from a modal state: the rows of `Ψ` the
/// stations need, stored transposed so each output is one contiguous dot product.
#[derive(Debug, Clone)]
pub struct ModalOutputs {
    /// r × m: column k is `Ψ[dof_k, :]ᵀ`.
    rows_t: DMatrix<f64>,
    quantities: Vec<Quantity>,
}

impl ModalOutputs {
    pub fn new(step: &ModalStep, channels: &[(usize, Quantity)]) -> Self {
        let r = step.modes();
        let rows_t = DMatrix::from_fn(r, channels.len(), |j, k| step.psi[(channels[k].0, j)]);
        Self {
            rows_t,
            quantities: channels.iter().map(|c| c.1).collect(),
        }
    }

    pub fn bytes(&self) -> usize {
        self.rows_t.len() * std::mem::size_of::<f64>()
    }

    /// Station channel `k` of `st`.
    #[inline]
    pub fn channel(&self, st: &ModalState, k: usize) -> f64 {
        let v = match self.quantities[k] {
            Quantity::Displacement => &st.q,
            Quantity::Velocity => &st.qd,
            Quantity::Acceleration => &st.qdd,
        };
        self.rows_t.column(k).dot(v)
    }

    /// Sensitivity of the outputs to a modal response `Γ` (3r × q): `S = H Γ`, m × q.
    pub fn sensitivity(&self, gamma: &DMatrix<f64>) -> DMatrix<f64> {
        let r = self.rows_t.nrows();
        DMatrix::from_fn(self.quantities.len(), gamma.ncols(), |k, j| {
            let off = match self.quantities[k] {
                Quantity::Displacement => 0,
                Quantity::Velocity => r,
                Quantity::Acceleration => 2 * r,
            };
            self.rows_t.column(k).dot(&gamma.view((off, j), (r, 1)))
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::integrate::{State, Stepper};
    use crate::setup::StepKind;
    use rand::{RngExt, SeedableRng};
    use rand_chacha::ChaCha8Rng;

    /// A random model: SPD mass (diagonal or full), PSD stiffness of rank n or n − 1 (a rigid
    /// mode), damping none / Rayleigh / Rayleigh + two dashpots.
    fn random_model(rng: &mut ChaCha8Rng, n: usize, damping: u8, full_mass: bool) -> Model {
        let b = DMatrix::from_fn(n, n, |_, _| rng.random_range(-1.0..1.0));
        let mut M = if full_mass {
            &b * b.transpose() + DMatrix::identity(n, n) * 0.5
        } else {
            DMatrix::from_diagonal(&DVector::from_fn(n, |_, _| rng.random_range(0.5..2.0)))
        };
        M *= 0.1;
        let g = DMatrix::from_fn(n, n - 1, |_, _| rng.random_range(-1.0..1.0));
        let K = &g * g.transpose() * 1.0e5;
        let (alpha, beta) = if damping > 0 { (3.0, 2e-5) } else { (0.0, 0.0) };
        let mut C = &M * alpha + &K * beta;
        if damping > 1 {
            C[(0, 0)] += 40.0;
            C[(1, 1)] += 25.0;
            C[(1, 2)] -= 25.0;
            C[(2, 1)] -= 25.0;
            C[(2, 2)] += 25.0;
        }
        let Lp = DMatrix::from_fn(n, 2, |_, _| rng.random_range(-1.0..1.0));
        let Lc = DMatrix::from_fn(n, 2, |_, _| rng.random_range(-1.0..1.0));
        Model {
            dofs: (0..n as u32)
                .map(|node| crate::setup::DofRef {
                    node,
                    dir: crate::setup::Dir::W,
                })
                .collect(),
            M,
            C,
            K,
            Lp,
            Lc,
            stations: Vec::new(),
            rayleigh: (alpha, beta),
            step: StepKind::Auto,
            sparse: None,
        }
    }

    fn rel(a: &DVector<f64>, b: &DVector<f64>) -> f64 {
        (a - b).amax() / b.amax().max(1e-300)
    }

    #[test]
    fn modal_map_equals_the_dense_map_on_random_models_states_and_inputs() {
        let mut rng = ChaCha8Rng::seed_from_u64(5);
        let nm = Newmark {
            gamma: 0.5,
            beta: 0.25,
        };
        for case in 0..24 {
            let n = 3 + case % 7;
            let damping = (case % 3) as u8;
            let model = random_model(&mut rng, n, damping, case % 2 == 0);
            let substeps = 1 + case % 4;
            let dt = 2e-4;
            let mut dense = Stepper::new(&model, dt, substeps, nm).unwrap();
            let mut fast = ModalStep::new(&model, dt, substeps, nm).unwrap();
            assert_eq!(fast.damping_rank() > 0, damping > 1, "case {case}");
            let mut x = State::zeros(n);
            for i in 0..n {
                x.u[i] = rng.random_range(-1e-3..1e-3);
                x.v[i] = rng.random_range(-0.1..0.1);
            }
            let p0 = [rng.random_range(-10.0..10.0), rng.random_range(-10.0..10.0)];
            let f0 = DVector::from_fn(2, |_, _| rng.random_range(-5.0..5.0));
            dense.initial_acceleration(&mut x, &p0, &f0);
            let mut e = ModalState::zeros(n);
            e.q = fast.to_modal(&model.M, &x.u);
            e.qd = fast.to_modal(&model.M, &x.v);
            fast.initial_acceleration(&mut e, &p0, &f0);
            assert!(rel(&(&fast.psi * &e.qdd), &x.a) < 1e-9, "case {case}: a0");
            let mut p_prev = p0;
            for k in 0..20 {
                let p = [rng.random_range(-10.0..10.0), rng.random_range(-10.0..10.0)];
                let f = DVector::from_fn(2, |_, _| rng.random_range(-5.0..5.0));
                dense.advance(&mut x, &p_prev, &p, &f);
                fast.advance(&mut e, &p_prev, &p, &f);
                p_prev = p;
                assert!(
                    rel(&(&fast.psi * &e.q), &x.u) < 1e-9,
                    "case {case} step {k}: u"
                );
                assert!(
                    rel(&(&fast.psi * &e.qd), &x.v) < 1e-9,
                    "case {case} step {k}: v"
                );
                assert!(
                    rel(&(&fast.psi * &e.qdd), &x.a) < 1e-9,
                    "case {case} step {k}: a"
                );
            }
            // Γ_f in modal coordinates maps to the dense Γ_f.
            let gd = dense.force_response();
            let gm = fast.force_response();
            for j in 0..2 {
                for (blk, off) in [(0, 0), (1, n), (2, 2 * n)] {
                    let phys = &fast.psi * gm.view((blk * n, j), (n, 1));
                    let d: DVector<f64> = gd.view((off, j), (n, 1)).column(0).into_owned();
                    assert!(
                        rel(&phys.column(0).into_owned(), &d) < 1e-9,
                        "case {case}: Γ_f"
                    );
                }
            }
        }
    }

    #[test]
    fn modal_map_is_linear_superposition_holds() {
        // advance(x, p₀, p₁, f) = advance(x, 0, 0, 0) + advance(0, p₀, p₁, 0) + Γ_f f.
        let mut rng = ChaCha8Rng::seed_from_u64(9);
        let nm = Newmark {
            gamma: 0.6,
            beta: 0.3025,
        };
        for damping in 0..3u8 {
            let model = random_model(&mut rng, 6, damping, true);
            let mut fast = ModalStep::new(&model, 1e-4, 3, nm).unwrap();
            let g = fast.force_response();
            let mut x = ModalState::zeros(6);
            for j in 0..6 {
                x.q[j] = rng.random_range(-1.0..1.0);
                x.qd[j] = rng.random_range(-1.0..1.0);
                x.qdd[j] = rng.random_range(-1.0..1.0);
            }
            let (p0, p1) = ([1.5, -2.0], [0.5, 3.0]);
            let f = DVector::from_vec(vec![2.0, -1.0]);
            let z = DVector::zeros(2);
            let mut all = x.clone();
            fast.advance(&mut all, &p0, &p1, &f);
            let mut hom = x.clone();
            fast.advance(&mut hom, &[0.0; 2], &[0.0; 2], &z);
            let mut forced = ModalState::zeros(6);
            fast.advance(&mut forced, &p0, &p1, &z);
            let mut sum = hom.clone();
            sum.q += &forced.q;
            sum.qd += &forced.qd;
            sum.qdd += &forced.qdd;
            sum.add_response(&g, &f);
            for (a, b) in [(&all.q, &sum.q), (&all.qd, &sum.qd), (&all.qdd, &sum.qdd)] {
                assert!(rel(a, b) < 1e-11, "damping {damping}");
            }
        }
    }

    #[test]
    fn full_non_proportional_damping_is_refused_with_the_reason() {
        let mut rng = ChaCha8Rng::seed_from_u64(2);
        let mut model = random_model(&mut rng, MAX_LOCAL_DAMPING + 2, 0, false);
        let n = model.M.nrows();
        model.C = DMatrix::from_fn(n, n, |i, j| if i == j { 1.0 } else { 0.01 });
        let e = ModalStep::new(
            &model,
            1e-4,
            1,
            Newmark {
                gamma: 0.5,
                beta: 0.25,
            },
        )
        .unwrap_err()
        .to_string();
        assert!(
            e.contains("not classical") && e.contains(&format!("{n} DOFs")),
            "{e}"
        );
    }
}
