//! Synthetic tests with a known truth: the component model plus the *true* connection law,
//! integrated with the same Newmark scheme, the connection forces solved implicitly.
//!
//! Per Newmark sub-step the state is affine in the connection forces `f`:
//! `δ = δ₀ − βh²G f`, `δ̇ = δ̇₀ − γhG f`, `δ̈ = δ̈₀ − G f` with `G = Lcᵀ(M + γhC + βh²K)⁻¹Lc`,
//! so the implicit step reduces to `q` equations `f = φ(δ(f), δ̇(f), δ̈(f))`, solved by
//! Newton. `sign` is set-valued at zero: a joint whose friction can hold it *sticks*
//! (`δ̇ = 0` for `sign(v)`, `δ = 0` for `sign(u)`) and stays stuck until the force it must
//! carry exceeds the friction level; an active-set loop picks stick or slip per connection.
//!
//! Scenarios (decisions written down): `sine` is a force `A sin 2πf t`; `random` is
//! Gaussian white force at the sample rate, linearly interpolated between samples, first
//! sample zero; `free` is an impact — a half-sine force pulse — followed by free decay
//! (from rest, so the initial state is known without extra metadata). Every scenario starts
//! at rest. Noise goes on the responses only; the excitation is known exactly.

#![allow(non_snake_case)]

use crate::dense::product;
use nalgebra::{DMatrix, DVector};
use rand::RngExt;
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use rand_distr::StandardNormal;

use crate::integrate::State;
use crate::model::Model;
use crate::setup::{Basis, Setup};

#[derive(Debug, thiserror::Error)]
pub enum SimulateError {
    #[error("connection `{0}` has no `truth` parameters in the setup; simulate needs them")]
    NoTruth(String),
    #[error("connection `{0}`: at most one sign basis with a non-zero true value is supported")]
    TwoSignTerms(String),
    #[error("connection `{0}`: a friction level must be ≥ 0, got {1}")]
    NegativeFriction(String, f64),
    #[error("the effective mass matrix is singular")]
    Singular,
    /// A fit's sensitivities at its end: some parameter, or a combination of them, does not
    /// move the outputs there (reported by the output-error refinement, which runs on this
    /// error type).
    #[error(
        "the Fisher information of the fit is singular: a parameter, or a combination of them, does not move the outputs there"
    )]
    SingularInformation,
    #[error(
        "the simulation diverged at sample {0} (Newton did not converge or the state is not finite)"
    )]
    Diverged(usize),
    #[error(transparent)]
    Model(#[from] crate::model::ModelError),
    #[error("{0}")]
    Options(String),
}

#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Scenario {
    Sine {
        freq_hz: f64,
        amplitude: f64,
    },
    Random {
        rms: f64,
    },
    Free {
        amplitude: f64,
        pulse_s: f64,
    },
    /// Random excitation with the true linear stiffness scaled by `factor` from `at_s` on
    /// (a bolt loosening), to test tracking.
    RandomStiffnessDrop {
        rms: f64,
        at_s: f64,
        factor: f64,
    },
}

#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Noise {
    None,
    /// σ = level × RMS of each channel (the default kind).
    Additive(f64),
    /// The paper's per-sample coefficient of variation: y·(1 + level·ε).
    Cov(f64),
}

impl std::str::FromStr for Noise {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        if s == "none" {
            return Ok(Noise::None);
        }
        let (kind, level) = s.split_once(':').unwrap_or(("additive", s));
        let level: f64 = level
            .parse()
            .map_err(|_| format!("noise `{s}`: expected none, additive:LEVEL or cov:LEVEL"))?;
        if !(level.is_finite() && level >= 0.0) {
            return Err(format!("noise `{s}`: the level must be ≥ 0"));
        }
        match kind {
            "additive" => Ok(Noise::Additive(level)),
            "cov" => Ok(Noise::Cov(level)),
            _ => Err(format!(
                "noise `{s}`: unknown kind `{kind}` (additive or cov)"
            )),
        }
    }
}

impl std::fmt::Display for Noise {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Noise::None => write!(f, "none"),
            Noise::Additive(l) => write!(f, "additive:{l}"),
            Noise::Cov(l) => write!(f, "cov:{l}"),
        }
    }
}

#[derive(Debug, Clone)]
pub struct SimulateOptions {
    pub scenario: Scenario,
    /// Number of recorded samples (including the initial one at t = 0).
    pub steps: usize,
    /// Sample interval, s.
    pub dt_s: f64,
    /// Newmark steps per recorded sample.
    pub substeps: usize,
    pub noise: Noise,
    pub seed: u64,
}

/// A simulated test.
#[derive(Debug, Clone)]
pub struct Simulated {
    pub excitation: Vec<Vec<f64>>,
    pub response: Vec<Vec<f64>>,
    pub clean_response: Vec<Vec<f64>>,
    /// True connection force and deformation per sample (one entry per connection).
    pub force: Vec<Vec<f64>>,
    pub delta: Vec<Vec<f64>>,
    pub truth: Vec<f64>,
    /// Fraction of samples at which some friction joint was stuck.
    pub stuck_fraction: f64,
    /// Noise standard deviation applied per channel (additive), for reports.
    pub noise_std: Vec<f64>,
}

#[derive(Debug, Clone, Copy, PartialEq)]
enum Status {
    Free,
    Slip(f64),
    Stick,
}

struct SignTerm {
    on_velocity: bool,
    level: f64,
}

/// The true system: component model + true connection law, stepped implicitly.
pub struct TruthSystem {
    model: Model,
    meff_inv: DMatrix<f64>,
    Y: DMatrix<f64>,
    G: DMatrix<f64>,
    blocks: Vec<(Vec<Basis>, Vec<f64>, Option<SignTerm>)>,
    h: f64,
    gamma: f64,
    beta: f64,
    status: Vec<Status>,
    /// The force solve's status sets tried so far (flat, `q` per set) and the one before the
    /// last check: kept here so a sub-step allocates nothing.
    seen: Vec<Status>,
    before: Vec<Status>,
    /// Work buffers of [`TruthSystem::substep`] (a sub-step runs millions of times per
    /// identification; allocating its temporaries was a third of the time).
    work: Work,
}

/// Preallocated temporaries of one sub-step: `n`-vectors of the predictor, `q`-vectors and
/// the `q × q` Jacobian of the force solve.
#[derive(Clone)]
struct Work {
    ut: DVector<f64>,
    vt: DVector<f64>,
    rhs: DVector<f64>,
    cv: DVector<f64>,
    a0: DVector<f64>,
    tmp: DVector<f64>,
    d0: DVector<f64>,
    v0: DVector<f64>,
    da0: DVector<f64>,
    f: DVector<f64>,
    gf: DVector<f64>,
    d: DVector<f64>,
    dv: DVector<f64>,
    da: DVector<f64>,
    e: DVector<f64>,
    j: DMatrix<f64>,
}

impl Work {
    /// δ, δ̇, δ̈ at the connections with the forces `f`: `d₀ − (G f) βh²`, `v₀ − (G f) γh`,
    /// `a₀ − G f` (the product formed first, as the allocating version did).
    fn deformations(&mut self, G: &DMatrix<f64>, bh2: f64, gh: f64) {
        crate::dense::gemv(&mut self.gf, G, &self.f, crate::dense::Op::Set);
        for c in 0..self.gf.len() {
            self.d[c] = self.d0[c] - self.gf[c] * bh2;
            self.dv[c] = self.v0[c] - self.gf[c] * gh;
            self.da[c] = self.da0[c] - self.gf[c];
        }
    }

    fn new(n: usize, q: usize) -> Self {
        let (vn, vq) = (DVector::zeros(n), DVector::zeros(q));
        Self {
            ut: vn.clone(),
            vt: vn.clone(),
            rhs: vn.clone(),
            cv: vn.clone(),
            a0: vn.clone(),
            tmp: vn,
            d0: vq.clone(),
            v0: vq.clone(),
            da0: vq.clone(),
            f: vq.clone(),
            gf: vq.clone(),
            d: vq.clone(),
            dv: vq.clone(),
            da: vq.clone(),
            e: vq,
            j: DMatrix::zeros(q, q),
        }
    }
}

impl TruthSystem {
    pub fn new(setup: &Setup, model: &Model, h: f64) -> Result<Self, SimulateError> {
        let mut params = Vec::new();
        for c in &setup.connections {
            params.extend(
                c.truth
                    .as_ref()
                    .ok_or_else(|| SimulateError::NoTruth(c.name.clone()))?,
            );
        }
        Self::with_params(setup, model, h, &params)
    }

    /// The system with the connection law `params` (all connections' parameters in setup
    /// order) instead of the setup's `truth`: the output-error model of `identify`.
    pub fn with_params(
        setup: &Setup,
        model: &Model,
        h: f64,
        params: &[f64],
    ) -> Result<Self, SimulateError> {
        if !model.has_dense() {
            return Err(crate::model::ModelError::SparseOnly {
                dofs: model.n(),
                what: "simulate",
            }
            .into());
        }
        let Newmark = setup.newmark;
        let meff = &model.M + &model.C * (Newmark.gamma * h) + &model.K * (Newmark.beta * h * h);
        let meff_inv = meff.try_inverse().ok_or(SimulateError::Singular)?;
        let Y = &meff_inv * &model.Lc;
        let G = model.Lc.transpose() * &Y;
        let mut blocks = Vec::new();
        let mut off = 0;
        for c in &setup.connections {
            let truth = params
                .get(off..off + c.basis.len())
                .ok_or_else(|| SimulateError::NoTruth(c.name.clone()))?
                .to_vec();
            off += c.basis.len();
            let mut sign = None;
            for (b, &p) in c.basis.iter().zip(&truth) {
                if matches!(b, Basis::SignU | Basis::SignV) && p != 0.0 {
                    if sign.is_some() {
                        return Err(SimulateError::TwoSignTerms(c.name.clone()));
                    }
                    if p < 0.0 {
                        return Err(SimulateError::NegativeFriction(c.name.clone(), p));
                    }
                    sign = Some(SignTerm {
                        on_velocity: *b == Basis::SignV,
                        level: p,
                    });
                }
            }
            blocks.push((c.basis.clone(), truth, sign));
        }
        let q = blocks.len();
        let status: Vec<Status> = blocks
            .iter()
            .map(|b| {
                if b.2.is_some() {
                    Status::Stick
                } else {
                    Status::Free
                }
            })
            .collect();
        Ok(Self {
            work: Work::new(model.n(), q),
            model: model.clone(),
            meff_inv,
            Y,
            G,
            blocks,
            h,
            gamma: Newmark.gamma,
            beta: Newmark.beta,
            seen: Vec::with_capacity(4 * status.len()),
            before: Vec::with_capacity(status.len()),
            status,
        })
    }

    /// Scale the true linear stiffness (`u` basis) of every connection.
    /// Connection forces at rest: only the constant (preload) terms act.
    fn rest_force(&self) -> DVector<f64> {
        DVector::from_iterator(
            self.blocks.len(),
            self.blocks.iter().map(|(basis, p, _)| {
                basis
                    .iter()
                    .zip(p)
                    .map(|(b, pj)| if let Basis::Const(k) = b { k * pj } else { 0.0 })
                    .sum()
            }),
        )
    }

    pub fn scale_stiffness(&mut self, factor: f64) {
        for (basis, truth, _) in &mut self.blocks {
            for (b, p) in basis.iter().zip(truth.iter_mut()) {
                if *b == Basis::U {
                    *p *= factor;
                }
            }
        }
    }

    /// Smooth part of the law and its derivatives w.r.t. (δ, δ̇, δ̈).
    fn smooth(&self, c: usize, d: f64, dv: f64, da: f64) -> (f64, f64, f64, f64) {
        let (f, fd, fv, fa, _) = self.smooth_and_size(c, d, dv, da);
        (f, fd, fv, fa)
    }

    /// [`Self::smooth`] and the largest term `|pⱼ bⱼ(δ, δ̇, δ̈)|` of the whole law (sign terms
    /// included): the size the force solve's round-off is relative to, in the same pass.
    fn smooth_and_size(&self, c: usize, d: f64, dv: f64, da: f64) -> (f64, f64, f64, f64, f64) {
        let (basis, p, _) = &self.blocks[c];
        let mut f = 0.0;
        let (mut fd, mut fv, mut fa) = (0.0, 0.0, 0.0);
        let mut size = 0.0f64;
        for (b, &pj) in basis.iter().zip(p) {
            let term = pj * b.eval(d, dv, da);
            size = size.max(term.abs());
            match b {
                Basis::SignU | Basis::SignV => {}
                _ => f += term,
            }
            match b {
                Basis::U => fd += pj,
                Basis::U3 => fd += 3.0 * pj * d * d,
                Basis::V => fv += pj,
                Basis::A => fa += pj,
                Basis::Gap(g) if d.abs() > *g => fd += pj,
                _ => {}
            }
        }
        (f, fd, fv, fa, size)
    }

    /// Solve the connection forces for one sub-step given the free predictions
    /// (`work.d0`, `work.v0`, `work.da0`: δ, δ̇, δ̈ with no connection force); the forces are
    /// left in `work.f`. Returns `None` when Newton fails.
    fn solve_forces(&mut self) -> Option<()> {
        let q = self.blocks.len();
        let (bh2, gh) = (self.beta * self.h * self.h, self.gamma * self.h);
        // Initial status guesses.
        for c in 0..q {
            if let Some(s) = &self.blocks[c].2 {
                let x0 = if s.on_velocity {
                    self.work.v0[c]
                } else {
                    self.work.d0[c]
                };
                if self.status[c] != Status::Stick {
                    self.status[c] = Status::Slip(if x0 >= 0.0 { 1.0 } else { -1.0 });
                }
            }
        }
        self.seen.clear();
        self.work.f.fill(0.0);
        for _round in 0..16 {
            // Newton for the current statuses.
            let mut ok = false;
            let mut prev_step = f64::INFINITY;
            let mut last_step = f64::INFINITY;
            for _it in 0..60 {
                let w = &mut self.work;
                // Size of the terms that are summed: round-off in the residual is relative
                // to it, not to the (possibly much smaller) net force.
                let mut mag = 1.0 + crate::dense::amax(w.f.as_slice());
                w.deformations(&self.G, bh2, gh);
                for c in 0..q {
                    let (dc, dvc, dac) = (self.work.d[c], self.work.dv[c], self.work.da[c]);
                    match self.status[c] {
                        Status::Stick => {
                            let Some(s) = &self.blocks[c].2 else {
                                unreachable!()
                            };
                            let k = if s.on_velocity { gh } else { bh2 };
                            self.work.e[c] = if s.on_velocity { dvc } else { dc };
                            for m in 0..q {
                                self.work.j[(c, m)] = -k * self.G[(c, m)];
                            }
                        }
                        st => {
                            let (phi, fd, fv, fa, size) = self.smooth_and_size(c, dc, dvc, dac);
                            let fric = match (st, &self.blocks[c].2) {
                                (Status::Slip(s), Some(t)) => s * t.level,
                                _ => 0.0,
                            };
                            self.work.e[c] = self.work.f[c] - phi - fric;
                            mag = mag.max(fric.abs()).max(size);
                            for m in 0..q {
                                let dd = if c == m { 1.0 } else { 0.0 };
                                self.work.j[(c, m)] =
                                    dd + (fd * bh2 + fv * gh + fa) * self.G[(c, m)];
                            }
                        }
                    }
                }
                let w = &mut self.work;
                // One connection (the common case): a scalar division, no factorisation.
                let size = if q == 1 {
                    let step = w.e[0] / w.j[(0, 0)];
                    if !step.is_finite() {
                        return None;
                    }
                    w.f[0] -= step;
                    step.abs()
                } else {
                    let step = w.j.clone().lu().solve(&w.e)?;
                    w.f -= &step;
                    step.amax()
                };
                last_step = size;
                // Converged: the step is at round-off of the summed terms, or it stopped
                // shrinking at a level far below any physical force (a linear law converges
                // in one step; the next only shuffles round-off).
                if size <= 1e-14 * mag || (size >= prev_step && size <= 1e-10 * mag) {
                    ok = true;
                    break;
                }
                prev_step = size;
            }
            // A stuck joint's equation has the tiny slope γhG or βh²G, so round-off in its
            // solve is ~ε|δ̇₀|/(γhG): settle for that (the 1e-14 target alone made Newton
            // fail on stiff stuck joints with many sub-steps).
            if !ok && last_step <= 1e-8 * (1.0 + self.work.f.amax()) {
                ok = true;
            }
            if !ok {
                return None;
            }
            // Check the statuses.
            let w = &mut self.work;
            w.deformations(&self.G, bh2, gh);
            let mut changed = false;
            self.before.clear();
            self.before.extend_from_slice(&self.status);
            for c in 0..q {
                let Some(s) = &self.blocks[c].2 else { continue };
                let level = s.level;
                let (dc, dvc, dac) = (self.work.d[c], self.work.dv[c], self.work.da[c]);
                let x = if s.on_velocity { dvc } else { dc };
                match self.status[c] {
                    Status::Stick => {
                        let (phi, ..) = self.smooth(c, dc, dvc, dac);
                        let lambda = self.work.f[c] - phi;
                        if lambda.abs() > level * (1.0 + 1e-12) {
                            self.status[c] = Status::Slip(lambda.signum());
                            changed = true;
                        }
                    }
                    Status::Slip(sg) => {
                        if x * sg < 0.0 {
                            self.status[c] = Status::Stick;
                            changed = true;
                        }
                    }
                    Status::Free => {}
                }
            }
            if !changed {
                return Some(());
            }
            if q > 0 && self.seen.chunks(q).any(|set| set == self.status.as_slice()) {
                // Cycling between slip directions: the consistent answer is to stick.
                for (c, was) in self.before.iter().enumerate() {
                    if self.blocks[c].2.is_some() && *was != self.status[c] {
                        self.status[c] = Status::Stick;
                    }
                }
            }
            self.seen.extend_from_slice(&self.before);
        }
        Some(())
    }

    /// One Newmark sub-step with excitation `p`. Returns the connection forces.
    fn substep(&mut self, s: &mut State, p: &DVector<f64>) -> Option<DVector<f64>> {
        self.substep_in_place(s, p)?;
        Some(self.work.f.clone())
    }

    /// One Newmark sub-step with excitation `p`, the connection forces left in `work.f`;
    /// no allocation.
    fn substep_in_place(&mut self, s: &mut State, p: &DVector<f64>) -> Option<()> {
        let (h, g, b) = (self.h, self.gamma, self.beta);
        let m = &self.model;
        let w = &mut self.work;
        // Newmark predictors ũ = u + h u̇ + (½ − β) h² ü, ṽ = u̇ + (1 − γ) h ü.
        w.ut.copy_from(&s.u);
        w.ut.axpy(h, &s.v, 1.0);
        w.ut.axpy((0.5 - b) * h * h, &s.a, 1.0);
        w.vt.copy_from(&s.v);
        w.vt.axpy((1.0 - g) * h, &s.a, 1.0);
        // Acceleration with no connection force: M_eff a₀ = Lp p − C ṽ − K ũ. Each product
        // is formed on its own and then subtracted, in the order the allocating version
        // used, so the results are the same to the last bit (the noise-free exactness tests
        // of chaotic friction laws see a last-bit change).
        // (`dense::gemv`: nalgebra's `gemv` to the bit, in wider registers.)
        use crate::dense::{Op, gemv};
        gemv(&mut w.rhs, &m.Lp, p, Op::Set);
        gemv(&mut w.cv, &m.C, &w.vt, Op::Set);
        w.rhs -= &w.cv;
        gemv(&mut w.cv, &m.K, &w.ut, Op::Set);
        w.rhs -= &w.cv;
        gemv(&mut w.a0, &self.meff_inv, &w.rhs, Op::Set);
        // Free connection deformation, rate and acceleration. (`gemv_tr` sums by dot
        // products; an `Lc` column has one or two non-zeros, so the order cannot change a
        // bit.)
        w.tmp.copy_from(&w.ut);
        w.tmp.axpy(b * h * h, &w.a0, 1.0);
        w.d0.gemv_tr(1.0, &m.Lc, &w.tmp, 0.0);
        w.tmp.copy_from(&w.vt);
        w.tmp.axpy(g * h, &w.a0, 1.0);
        w.v0.gemv_tr(1.0, &m.Lc, &w.tmp, 0.0);
        w.da0.gemv_tr(1.0, &m.Lc, &w.a0, 0.0);
        self.solve_forces()?;
        let w = &mut self.work;
        // a = a₀ − (Y f): the product first, as the allocating version did (with two or more
        // connections the sum order matters to the last bit).
        gemv(&mut w.tmp, &self.Y, &w.f, Op::Set);
        s.a.copy_from(&w.a0);
        s.a -= &w.tmp;
        s.u.copy_from(&w.ut);
        s.u.axpy(b * h * h, &s.a, 1.0);
        s.v.copy_from(&w.vt);
        s.v.axpy(g * h, &s.a, 1.0);
        Some(())
    }

    /// One sample of `substeps` sub-steps, the excitation going linearly from `pa` (the
    /// previous sample's) to `pb` (missing channels read as 0); `pt` is the work vector of
    /// the interpolated excitation (`ne` long).
    fn sample_substeps(
        &mut self,
        s: &mut State,
        pa: &[f64],
        pb: &[f64],
        substeps: usize,
        pt: &mut DVector<f64>,
    ) -> Option<()> {
        for k in 1..=substeps {
            let t = k as f64 / substeps as f64;
            interpolate_excitation(pt.as_mut_slice(), pa, pb, t);
            self.substep_in_place(s, pt)?;
        }
        Some(())
    }

    /// One sample of `map.substeps` sub-steps through [`ComposedSubsteps`], the excitation
    /// going linearly from `pa` (the previous sample's) to `pb` (missing channels read as
    /// 0): the same sub-steps and force solves as [`Self::substep_in_place`] up to round-off.
    fn sample_composed(
        &mut self,
        map: &mut ComposedSubsteps,
        s: &mut State,
        pa: &[f64],
        pb: &[f64],
    ) -> Option<()> {
        let n = self.model.n();
        let (q, steps) = (map.q, map.substeps);
        let ne = map.ne;
        {
            let input = map.input.as_mut_slice();
            input[..n].copy_from_slice(s.u.as_slice());
            input[n..2 * n].copy_from_slice(s.v.as_slice());
            input[2 * n..3 * n].copy_from_slice(s.a.as_slice());
            for j in 0..ne {
                input[3 * n + j] = pa.get(j).copied().unwrap_or(0.0);
                input[3 * n + ne + j] = pb.get(j).copied().unwrap_or(0.0);
            }
        }
        let forces_at = 3 * n + 2 * ne;
        crate::dense::gemv_slices(
            map.free.as_mut_slice(),
            &map.free_map,
            &map.input.as_slice()[..forces_at],
            crate::dense::Op::Set,
        );
        for j in 0..steps {
            // The free prediction with every earlier sub-step's force already in it.
            for c in 0..3 * q {
                let v = map.free[c * steps + j];
                let w = &mut self.work;
                match c / q {
                    0 => w.d0[c] = v,
                    1 => w.v0[c - q] = v,
                    _ => w.da0[c - 2 * q] = v,
                }
            }
            self.solve_forces()?;
            let later = steps - 1 - j;
            for m in 0..q {
                let f = self.work.f[m];
                map.input[forces_at + q * j + m] = f;
                // Its impulse at lag k = 1…L−1−j on the later sub-steps: one `axpy` per
                // quantity (contiguous rows, no chain of dependent adds).
                if later > 0 {
                    for c in 0..3 * q {
                        let start = c * steps + j + 1;
                        crate::dense::axpy(
                            &mut map.free.as_mut_slice()[start..start + later],
                            f,
                            &map.impulse_by_lag[c * q + m][..later],
                        );
                    }
                }
            }
        }
        crate::dense::gemv(
            &mut map.next,
            &map.end_map,
            &map.input,
            crate::dense::Op::Set,
        );
        s.u.copy_from(&map.next.rows(0, n));
        s.v.copy_from(&map.next.rows(n, n));
        s.a.copy_from(&map.next.rows(2 * n, n));
        Some(())
    }

    pub fn any_stuck(&self) -> bool {
        self.status.contains(&Status::Stick)
    }
}

/// The excitation a fraction `t` of the way through the sample `pa → pb`, `pa + t (pb − pa)`
/// per channel (a missing channel reads as 0): how every sub-step path interpolates it.
fn interpolate_excitation(out: &mut [f64], pa: &[f64], pb: &[f64], t: f64) {
    for (j, o) in out.iter_mut().enumerate() {
        let (x0, x1) = (
            pa.get(j).copied().unwrap_or(0.0),
            pb.get(j).copied().unwrap_or(0.0),
        );
        *o = x0 + t * (x1 - x0);
    }
}

fn excitation_at(sc: &Scenario, t: f64, white: &[f64], dt: f64) -> f64 {
    match *sc {
        Scenario::Sine { freq_hz, amplitude } => {
            amplitude * (2.0 * std::f64::consts::PI * freq_hz * t).sin()
        }
        Scenario::Free { amplitude, pulse_s } => {
            if t < pulse_s {
                amplitude * (std::f64::consts::PI * t / pulse_s).sin()
            } else {
                0.0
            }
        }
        Scenario::Random { .. } | Scenario::RandomStiffnessDrop { .. } => {
            let x = t / dt;
            let i = x.floor() as usize;
            let fr = x - i as f64;
            let a = white.get(i).copied().unwrap_or(0.0);
            let b = white.get(i + 1).copied().unwrap_or(a);
            a + fr * (b - a)
        }
    }
}

/// Noise-free station outputs of the model with connection parameters `params`, driven by a
/// recorded excitation (linearly interpolated between samples, as the `random` scenario
/// generates it), from rest, with `substeps` implicit Newmark steps per sample. This is the
/// output-error prediction `ŷ(p)` whose sensitivities give the Cramér–Rao bound.
pub fn response_to_excitation(
    setup: &Setup,
    model: &Model,
    params: &[f64],
    excitation: &[Vec<f64>],
    dt_s: f64,
    substeps: usize,
) -> Result<Vec<Vec<f64>>, SimulateError> {
    if substeps == 0 || excitation.is_empty() {
        return Err(SimulateError::Options(
            "substeps and the excitation length must be at least 1".into(),
        ));
    }
    // Composing the map costs about 54 n³ flops per sub-step once, the implicit path about
    // 6 n² per sub-step and sample: the map pays off when the record is longer than ~9 n.
    if 9 * model.n() < excitation.len()
        && let Some(map) = LinearSampleMap::new(setup, model, params, dt_s, substeps)?
    {
        return map.run(model, excitation);
    }
    response_stepped(setup, model, params, excitation, dt_s, substeps)
}

/// The station outputs (each station's quantity at its DOF) of a state.
fn station_outputs(model: &Model, s: &State) -> Vec<f64> {
    model
        .stations
        .iter()
        .map(|st| s.channel(st.dof, st.quantity))
        .collect()
}

/// Acceleration at rest under the first sample's excitation `p0` and the connections' rest
/// force `f0` (constant terms only): `M a = Lp p0 − Lc f0`.
fn rest_acceleration(
    model: &Model,
    p0: &DVector<f64>,
    f0: &DVector<f64>,
) -> Result<DVector<f64>, SimulateError> {
    let rhs = &model.Lp * p0 - &model.Lc * f0;
    model
        .M
        .clone()
        .lu()
        .solve(&rhs)
        .ok_or(SimulateError::Singular)
}

/// The state a prediction starts from: at rest, accelerated by the first sample's excitation
/// (missing channels read as 0) and the rest force of the law in `sys`.
fn rest_state(model: &Model, sys: &TruthSystem, first: &[f64]) -> Result<State, SimulateError> {
    let ne = model.Lp.ncols();
    let mut s = State::zeros(model.n());
    let f0 = sys.rest_force();
    let p0 = DVector::from_iterator(ne, (0..ne).map(|j| first.get(j).copied().unwrap_or(0.0)));
    s.a = rest_acceleration(model, &p0, &f0)?;
    Ok(s)
}

/// [`response_to_excitation`] for any law, each sample through [`SampleStepper`]: one
/// composed map while every friction slips one way through the sample, else the force solve
/// at every sub-step around composed sub-step maps (the same sub-steps as
/// [`TruthSystem::sample_substeps`] up to round-off; unit tests against it).
///
/// Why (decided 2026-12-06): the free run of a friction law is the output-error stage's
/// whole cost, and sub-step by sub-step it took 2–22 s per Coulomb identification at 2,000
/// samples. It had kept to the sub-step path since 2026-11-27, when on one accelerometer-only
/// Coulomb record the stepper's round-off sent the descent to another valley of a rough
/// cost. Over 900 Coulomb estimates (50 seeds × 9 rows) the coverage stayed the same in
/// every row to one estimate and none moved more than 0.66 errors, at 2.6–2.7× less time
/// (1-DOF friction 6.5×, gap 1.7–2×; ACCURACY.md, the forty-ninth session). A free run's
/// answer that round-off moves is one the cost cannot tell from its neighbours; its stated
/// error has to say so, not the arithmetic's order.
fn response_stepped(
    setup: &Setup,
    model: &Model,
    params: &[f64],
    excitation: &[Vec<f64>],
    dt_s: f64,
    substeps: usize,
) -> Result<Vec<Vec<f64>>, SimulateError> {
    let mut stepper = SampleStepper::new(setup, model, params, dt_s, substeps, excitation.len())?;
    free_run(
        setup,
        model,
        params,
        excitation,
        dt_s / substeps as f64,
        |sys, s, pa, pb| stepper.step(sys, s, pa, pb),
    )
}

/// [`response_to_excitation`] sub-step by sub-step with the implicit force solve: the
/// reference the composed paths are tested against.
#[cfg(test)]
fn response_substeps(
    setup: &Setup,
    model: &Model,
    params: &[f64],
    excitation: &[Vec<f64>],
    dt_s: f64,
    substeps: usize,
) -> Result<Vec<Vec<f64>>, SimulateError> {
    let mut pt = DVector::zeros(model.Lp.ncols());
    free_run(
        setup,
        model,
        params,
        excitation,
        dt_s / substeps as f64,
        |sys, s, pa, pb| sys.sample_substeps(s, pa, pb, substeps, &mut pt),
    )
}

/// The station outputs of the law `params` from rest, each sample `pa → pb` stepped by
/// `step` (`None`: a force solve failed) on the system of sub-step `h`.
fn free_run(
    setup: &Setup,
    model: &Model,
    params: &[f64],
    excitation: &[Vec<f64>],
    h: f64,
    mut step: impl FnMut(&mut TruthSystem, &mut State, &[f64], &[f64]) -> Option<()>,
) -> Result<Vec<Vec<f64>>, SimulateError> {
    let mut sys = TruthSystem::with_params(setup, model, h, params)?;
    let mut s = rest_state(model, &sys, &excitation[0])?;
    let mut out = Vec::with_capacity(excitation.len());
    out.push(station_outputs(model, &s));
    for i in 1..excitation.len() {
        step(&mut sys, &mut s, &excitation[i - 1], &excitation[i])
            .ok_or(SimulateError::Diverged(i))?;
        if !s.is_finite() {
            return Err(SimulateError::Diverged(i));
        }
        out.push(station_outputs(model, &s));
    }
    Ok(out)
}

/// One-step-ahead predictions `ŷ_{i|i−1}` of the model with the connection law `params`
/// driven by the recorded excitation from rest, its state `x = (u; u̇; ü)` corrected after
/// every sample by a fixed observer gain: `x ← x + K (y_i − ŷ_{i|i−1})` (`gain` is `3n × m`,
/// rows in `(u; u̇; ü)` order, columns the station channels). With `K = 0` this is
/// [`response_to_excitation`]. `initial`: offsets `(u; u̇; ü)` from rest of
/// the state the record starts from (`None`: at rest).
///
/// Why: the prediction-error predictor of [`crate::estimate::prediction_error`]. The whole
/// correction is applied, stuck joints included (see the comment in the body).
#[allow(clippy::too_many_arguments)]
pub fn predictions_with_observer(
    setup: &Setup,
    model: &Model,
    params: &[f64],
    excitation: &[Vec<f64>],
    response: &[Vec<f64>],
    dt_s: f64,
    substeps: usize,
    gain: &DMatrix<f64>,
    initial: Option<&[f64]>,
) -> Result<Vec<Vec<f64>>, SimulateError> {
    let mut out = Vec::with_capacity(excitation.len());
    each_prediction_with_observer(
        setup,
        model,
        params,
        excitation,
        response,
        dt_s,
        substeps,
        gain,
        initial,
        &mut |_, y| out.push(y.to_vec()),
    )?;
    Ok(out)
}

/// [`predictions_with_observer`] handing each sample's prediction `(i, ŷ_{i|i−1})` to
/// `on_prediction` instead of collecting them (no allocation per sample: the prediction
/// error's Jacobians run this ~10⁷ times on a long record).
#[allow(clippy::too_many_arguments)]
pub fn each_prediction_with_observer(
    setup: &Setup,
    model: &Model,
    params: &[f64],
    excitation: &[Vec<f64>],
    response: &[Vec<f64>],
    dt_s: f64,
    substeps: usize,
    gain: &DMatrix<f64>,
    initial: Option<&[f64]>,
    on_prediction: &mut dyn FnMut(usize, &[f64]),
) -> Result<(), SimulateError> {
    let n = model.n();
    let m = model.stations.len();
    if substeps == 0 || excitation.is_empty() || response.len() < excitation.len() {
        return Err(SimulateError::Options(
            "substeps and the excitation length must be at least 1, and a response per sample"
                .into(),
        ));
    }
    if gain.nrows() != 3 * n || gain.ncols() != m {
        return Err(SimulateError::Options(format!(
            "observer gain is {}×{}, expected {}×{m}",
            gain.nrows(),
            gain.ncols(),
            3 * n
        )));
    }
    let h = dt_s / substeps as f64;
    let mut sys = TruthSystem::with_params(setup, model, h, params)?;
    let mut s = rest_state(model, &sys, &excitation[0])?;
    if let Some(x) = initial.filter(|x| x.len() == 3 * n) {
        for k in 0..n {
            s.u[k] += x[k];
            s.v[k] += x[n + k];
            s.a[k] += x[2 * n + k];
        }
    }
    let mut yi = vec![0.0; m];
    // Each channel as (its block of the state, its DOF).
    let channels: Vec<(usize, usize)> = model
        .stations
        .iter()
        .map(|st| (st.quantity.block(), st.dof))
        .collect();
    let record = |s: &State, y: &mut [f64]| {
        let state = [s.u.as_slice(), s.v.as_slice(), s.a.as_slice()];
        for (v, &(kind, dof)) in y.iter_mut().zip(&channels) {
            *v = state[kind][dof];
        }
    };
    let mut innov = DVector::zeros(m);
    let mut dx = DVector::zeros(3 * n);
    let mut correct = |s: &mut State, y: &[f64], yhat: &[f64]| {
        for (k, (d, p)) in innov.as_mut_slice().iter_mut().zip(yhat).enumerate() {
            *d = y.get(k).copied().unwrap_or(0.0) - p;
        }
        crate::dense::gemv(&mut dx, gain, &innov, crate::dense::Op::Set);
        // The whole correction, stuck joints included. It used to be removed along a
        // joint whose friction status was `Stick` at the sample's end (to keep it stuck),
        // which made the prediction jump between a friction level of 0 (no stick–slip
        // status) and any positive one: measured on the spring setup (truth 0), the
        // innovation cost rose by 0.5–14 (up to 25 residual variances) from 0 to 1e-3 N and
        // then hardly changed up to 100 N, so a friction on its bound looked determined to
        // 1e-17 N and the bound rule refused good answers. Without the removal the rise is
        // 4e-5; the 50-seed sweeps (ACCURACY.md) went from 92 % coverage and 71.8 errors
        // worst to 99 % and 2.7 (friction, 8 sub-steps, 10 % noise), 98 %/25.7 to 99 %/4.9
        // (spring, 8 sub-steps, 1 %).
        let dx = dx.as_slice();
        for (w, d) in [&mut s.u, &mut s.v, &mut s.a]
            .into_iter()
            .zip(dx.chunks_exact(n))
        {
            for (x, e) in w.as_mut_slice().iter_mut().zip(d) {
                *x += e;
            }
        }
    };
    record(&s, &mut yi);
    correct(&mut s, &response[0], &yi);
    on_prediction(0, &yi);
    let mut stepper = SampleStepper::new(setup, model, params, dt_s, substeps, excitation.len())?;
    for i in 1..excitation.len() {
        stepper
            .step(&mut sys, &mut s, &excitation[i - 1], &excitation[i])
            .ok_or(SimulateError::Diverged(i))?;
        if !s.is_finite() {
            return Err(SimulateError::Diverged(i));
        }
        record(&s, &mut yi);
        correct(&mut s, &response[i], &yi);
        on_prediction(i, &yi);
    }
    Ok(())
}

/// Whether every connection law of the setup is linear in the state (only `u`, `v` and
/// `const(c)` terms): then [`response_to_excitation`] runs one composed map per sample, and
/// its cost does not depend on the number of sub-steps.
pub fn law_is_linear(setup: &Setup) -> bool {
    setup.connections.iter().all(|c| {
        c.basis
            .iter()
            .all(|b| matches!(b, Basis::U | Basis::V | Basis::Const(_)))
    })
}

/// A connection law as the composed maps ([`LinearSampleMap`], [`SlipSampleMap`]) use it:
/// per connection the `u` and `v` coefficients (folded into the structure), the `const`
/// terms' force, and the active frictions `(connection, on the rate, level)`.
struct FoldedLaw {
    k: DVector<f64>,
    c: DVector<f64>,
    const_force: DVector<f64>,
    friction: Vec<(usize, bool, f64)>,
}

impl FoldedLaw {
    /// `None` when a term is not `u`, `v`, `const` or a non-negative `sign` level (`u³`,
    /// `a`, a gap, a negative friction).
    fn of(setup: &Setup, params: &[f64]) -> Result<Option<Self>, SimulateError> {
        let q = setup.connections.len();
        let mut law = Self {
            k: DVector::zeros(q),
            c: DVector::zeros(q),
            const_force: DVector::zeros(q),
            friction: Vec::new(),
        };
        let mut off = 0;
        for (ci, conn) in setup.connections.iter().enumerate() {
            let Some(p) = params.get(off..off + conn.basis.len()) else {
                return Err(SimulateError::NoTruth(conn.name.clone()));
            };
            off += conn.basis.len();
            for (b, &pj) in conn.basis.iter().zip(p) {
                match b {
                    Basis::U => law.k[ci] += pj,
                    Basis::V => law.c[ci] += pj,
                    Basis::Const(x) => law.const_force[ci] += x * pj,
                    Basis::SignU | Basis::SignV if pj == 0.0 => {}
                    Basis::SignU | Basis::SignV if pj > 0.0 => {
                        law.friction.push((ci, *b == Basis::SignV, pj));
                    }
                    _ => return Ok(None),
                }
            }
        }
        Ok(Some(law))
    }

    /// The structure with the linear terms folded in: `K' = K + Lc diag(k) Lcᵀ`,
    /// `C' = C + Lc diag(c) Lcᵀ`, and Newmark's effective mass `M + γh C' + βh² K'`.
    fn structure(
        &self,
        model: &Model,
        gamma: f64,
        beta: f64,
        h: f64,
    ) -> (DMatrix<f64>, DMatrix<f64>, DMatrix<f64>) {
        let lc = &model.Lc;
        let K = &model.K + lc * DMatrix::from_diagonal(&self.k) * lc.transpose();
        let C = &model.C + lc * DMatrix::from_diagonal(&self.c) * lc.transpose();
        let meff = &model.M + &C * (gamma * h) + &K * (beta * h * h);
        (K, C, meff)
    }
}

/// The Newmark sub-steps of one sample interval composed into one affine map, for a linear
/// connection law (`u`, `v`, `const` terms only) folded into the model:
/// `K' = K + Lc diag(k) Lcᵀ`, `C' = C + Lc diag(c) Lcᵀ`, the constant force a second input.
///
/// Why: a Newmark sub-step of a linear system is linear in the state `x = (u, v, a)` and in
/// the excitation, and the excitation is interpolated linearly across the sample, so the
/// `s` sub-steps of one sample are exactly `x_i = Φ x_{i−1} + Γ₀ p̃_{i−1} + Γ₁ p̃_i`
/// (`p̃ = (p, 1)`). One sample then costs one `3n × 3n` product whatever `s` is — the
/// output-error refinement can use as many model sub-steps as the data need (their
/// discretisation bias on an undamped structure grows with the record length) without the
/// time growing with them. Algebraically the same as the implicit per-sub-step force solve
/// of [`TruthSystem`] for such a law; they differ by round-off only.
struct LinearSampleMap {
    phi: DMatrix<f64>,
    g0: DMatrix<f64>,
    g1: DMatrix<f64>,
    /// `M⁻¹ B`: the acceleration at rest from the first input sample (as [`TruthSystem`]
    /// starts).
    start: DMatrix<f64>,
    ne: usize,
}

impl LinearSampleMap {
    /// `None` when the law is not linear at `params` (a non-zero friction level, `u³`,
    /// added mass or a gap), or when the model has no dense form.
    fn new(
        setup: &Setup,
        model: &Model,
        params: &[f64],
        dt_s: f64,
        substeps: usize,
    ) -> Result<Option<Self>, SimulateError> {
        if !model.has_dense() {
            return Ok(None);
        }
        let n = model.n();
        let q = model.Lc.ncols();
        if q != setup.connections.len() {
            return Ok(None);
        }
        let Some(law) = FoldedLaw::of(setup, params)? else {
            return Ok(None);
        };
        if !law.friction.is_empty() {
            return Ok(None);
        }
        let f_const = &law.const_force;
        let Newmark = setup.newmark;
        let (gamma, beta) = (Newmark.gamma, Newmark.beta);
        let h = dt_s / substeps as f64;
        let lc = &model.Lc;
        let (K, C, meff) = law.structure(model, gamma, beta, h);
        let meff_inv = meff.try_inverse().ok_or(SimulateError::Singular)?;
        let ne = model.Lp.ncols();
        // Inputs p̃ = (p, 1): the excitation and the constant connection force.
        let mut B = DMatrix::zeros(n, ne + 1);
        B.columns_mut(0, ne).copy_from(&model.Lp);
        B.column_mut(ne).copy_from(&(-(lc * f_const)));
        let (T, Q) = newmark_substep_map(&meff_inv, &C, &K, &B, h, gamma, beta);
        // Compose the s sub-steps with p̃(t_k) = (1 − t_k) p̃_{i−1} + t_k p̃_i, t_k = k/s.
        let mut phi = DMatrix::<f64>::identity(3 * n, 3 * n);
        let mut g0 = DMatrix::<f64>::zeros(3 * n, ne + 1);
        let mut g1 = DMatrix::<f64>::zeros(3 * n, ne + 1);
        for step in 1..=substeps {
            let t = step as f64 / substeps as f64;
            phi = &T * &phi;
            g0 = &T * &g0 + &Q * (1.0 - t);
            g1 = &T * &g1 + &Q * t;
        }
        // The starting acceleration as the implicit simulation takes it: M a₀ = B p̃₀.
        let start = model
            .M
            .clone()
            .lu()
            .solve(&B)
            .ok_or(SimulateError::Singular)?;
        Ok(Some(Self {
            phi,
            g0,
            g1,
            start,
            ne,
        }))
    }

    fn run(&self, model: &Model, excitation: &[Vec<f64>]) -> Result<Vec<Vec<f64>>, SimulateError> {
        let n = model.n();
        let ne = self.ne;
        let input = |e: &Vec<f64>| -> DVector<f64> {
            DVector::from_iterator(
                ne + 1,
                (0..ne)
                    .map(|j| e.get(j).copied().unwrap_or(0.0))
                    .chain(std::iter::once(1.0)),
            )
        };
        let mut x = DVector::zeros(3 * n);
        let mut prev = input(&excitation[0]);
        x.rows_mut(2 * n, n).copy_from(&(&self.start * &prev));
        let record = |x: &DVector<f64>| -> Vec<f64> {
            model
                .stations
                .iter()
                .map(|st| match st.quantity {
                    crate::setup::Quantity::Displacement => x[st.dof],
                    crate::setup::Quantity::Velocity => x[n + st.dof],
                    crate::setup::Quantity::Acceleration => x[2 * n + st.dof],
                })
                .collect()
        };
        let mut out = Vec::with_capacity(excitation.len());
        out.push(record(&x));
        let mut next = DVector::zeros(3 * n);
        let mut cur = DVector::zeros(ne + 1);
        for (i, e) in excitation.iter().enumerate().skip(1) {
            for j in 0..ne {
                cur[j] = e.get(j).copied().unwrap_or(0.0);
            }
            cur[ne] = 1.0;
            next.gemv(1.0, &self.phi, &x, 0.0);
            next.gemv(1.0, &self.g0, &prev, 1.0);
            next.gemv(1.0, &self.g1, &cur, 1.0);
            std::mem::swap(&mut x, &mut next);
            std::mem::swap(&mut prev, &mut cur);
            if !x.iter().all(|v| v.is_finite()) {
                return Err(SimulateError::Diverged(i));
            }
            out.push(record(&x));
        }
        Ok(out)
    }
}

/// Most model DOFs for which the simulations compose a sample's sub-steps ([`SlipSampleMap`],
/// [`ComposedSubsteps`]): they hold several `3n × 3n` matrices (7 MB each at 300 DOFs) and
/// are built with `O(n³ log L)` products; larger models step sub-step by sub-step.
const MAX_COMPOSED_DOFS: usize = 300;

/// How the observer's predictions ([`predictions_with_observer`]) and the free run of a law
/// that is not linear ([`response_to_excitation`]) step a sample: a friction
/// that slips one way through it by one composed map ([`SlipSampleMap`]); one that reverses
/// inside it (or sticks) by windows of that map around its force-solved sub-steps
/// ([`SlipWindows`]); a law the slip map does not fold by the force solve at every
/// sub-step, two or more sub-steps composed around it ([`ComposedSubsteps`], built when
/// first needed). The same sub-steps every way, up to
/// round-off (unit tests against the sub-step path).
struct SampleStepper {
    slip: Option<SlipSampleMap>,
    composed: Option<ComposedSubsteps>,
    /// Whether the composed maps are used at all (a model small enough to hold several
    /// `3n × 3n` matrices, a record long enough to pay for them).
    compose: bool,
    substeps: usize,
    pt: DVector<f64>,
}

impl SampleStepper {
    /// `samples`: the record's length (the composed maps pay for their construction only on
    /// records longer than ~9n, as [`LinearSampleMap`] measured).
    fn new(
        setup: &Setup,
        model: &Model,
        params: &[f64],
        dt_s: f64,
        substeps: usize,
        samples: usize,
    ) -> Result<Self, SimulateError> {
        let n = model.n();
        let compose = n <= MAX_COMPOSED_DOFS && 9 * n < samples;
        Ok(Self {
            slip: if compose {
                SlipSampleMap::new(setup, model, params, dt_s, substeps)?
            } else {
                None
            },
            composed: None,
            compose,
            substeps,
            pt: DVector::zeros(model.Lp.ncols()),
        })
    }

    /// One sample `pa → pb` of `sys` from `s`; `None` when a force solve fails.
    fn step(&mut self, sys: &mut TruthSystem, s: &mut State, pa: &[f64], pb: &[f64]) -> Option<()> {
        if let Some(map) = self.slip.as_mut() {
            match map.try_sample(s, pa, pb) {
                Ok(()) => {
                    for (ci, sign) in map.slips() {
                        sys.status[ci] = Status::Slip(sign);
                    }
                    return Some(());
                }
                // Every refused sample: the slip's windows around force-solved sub-steps,
                // and (once a simulation has had enough stuck sub-steps,
                // [`STUCK_WINDOWS_AFTER`]) the windows that hold a stuck joint stuck.
                Err(cleared) if map.window_parts.is_some() => {
                    return map.sample_by_windows(sys, s, pa, pb, cleared, &mut self.pt);
                }
                Err(_) => {}
            }
        }
        if self.compose && self.substeps >= 2 {
            let map = self
                .composed
                .get_or_insert_with(|| ComposedSubsteps::new(sys, self.substeps));
            sys.sample_composed(map, s, pa, pb)
        } else {
            sys.sample_substeps(s, pa, pb, self.substeps, &mut self.pt)
        }
    }
}

/// The `L` Newmark sub-steps of one sample composed into one affine map for the samples in
/// which every friction of a law linear in `δ`, `δ̇` apart from it (`u`, `v`, `const`,
/// `sign(u)`, `sign(v)` terms) keeps slipping one way: the prediction-error refinement's
/// map for most samples, with its windows ([`SlipWindows`]), [`ComposedSubsteps`] or the
/// sub-step force solve for the others.
///
/// Why: while a friction slips one way its force is the constant `±level`, so with the
/// linear terms folded into the structure (`K' = K + Lc diag(k) Lcᵀ`, `C' = C + Lc diag(c)
/// Lcᵀ`, as [`LinearSampleMap`]) the sample is `x_i = Φ x_{i−1} + Γ₀ p_{i−1} + Γ₁ p_i + Γ_b b`
/// with `b` the constant connection forces (`const` terms and `±level`). Whether the
/// friction does keep its direction is read from the deformation (or rate) of each
/// sub-step's end, `δ_j`, under that assumption: one `L × 3n` product per friction instead
/// of `L` force solves and an `O(L²)` force history. If every `δ_j` has the slip's sign by
/// more than the round-off of its terms, the slip at every sub-step is the unique solution
/// of the implicit sub-step (a set-valued friction with a positive compliance has one:
/// `δ` under `+level` is below `δ` under `−level`, and sticking needs `δ = 0`), which the
/// force solve would also have found: the same sub-steps, up to round-off. Otherwise
/// (a reversal or a stick inside the sample, a joint at rest) the sub-steps the test
/// cleared are stepped by a window map ([`SlipWindows`]), those in which a joint the last
/// sub-step left stuck stays stuck by the windows that hold it ([`SlipWindows::stuck`]),
/// the first neither could clear by the force solve, and the rest of the sample tested and
/// stepped again from there.
struct SlipSampleMap {
    /// The sample's end state from its inputs `(x; p_{i−1}; p_i; b)` ([`Self::input`]):
    /// `[Φ Γ₀ Γ₁ Γ_b]` side by side ([`crate::dense::side_by_side`]), `Γ_b` the state's
    /// response to the constant connection forces `b` (`3n × q`).
    step: DMatrix<f64>,
    /// `δ_j` (or `δ̇_j`) of each friction at the end of sub-step `j = 1…L`, stacked
    /// (`r` rows per sub-step), from the same inputs: the blocks of the start state,
    /// `p_{i−1}`, `p_i` and `b` side by side. Stored transposed (a row per column), so the
    /// test reads the rows in order and stops at the first it cannot clear.
    check_rows: DMatrix<f64>,
    /// Per check row: the absolute row sums of the four blocks (`Σ|terms| ≤ Σ rowsum·‖·‖∞`,
    /// the scale of its round-off).
    row_sums: Vec<[f64; 4]>,
    /// Their largest values over the rows.
    largest_row_sums: [f64; 4],
    /// Per friction: its connection, on the rate (`sign(v)`) or the deformation, its level.
    friction: Vec<(usize, bool, f64)>,
    /// `δ` (or `δ̇`) of each friction from the state: its non-zero coefficients
    /// `(state index, coefficient)` in the order of the index (the dense row's sum without
    /// its zero terms, which cannot change a non-zero sum).
    select: Vec<Vec<(usize, f64)>>,
    /// The `const` terms' force per connection.
    const_force: DVector<f64>,
    /// The inputs side by side, `(x; p_{i−1}; p_i; b)` (`3n + 2 ne + q`).
    input: DVector<f64>,
    /// Excitation channels `ne`.
    ne: usize,
    /// Work vectors.
    next: DVector<f64>,
    signs: Vec<f64>,
    /// The maps of windows of sub-steps inside a sample, for the samples the whole-sample
    /// test refuses: built from `window_parts` at the first such sample (a record whose
    /// frictions never reverse does not pay for them). `window_parts` is `None` with one
    /// sub-step, no active friction or a large model.
    window_parts: Option<WindowParts>,
    windows: Option<SlipWindows>,
    /// The windows that hold a set of frictions stuck ([`SlipWindows::stuck`]), by the set's
    /// bits (friction `i` stuck: bit `i`), each built at the first sample that needs it
    /// (`Some(None)`: its constraint cannot be solved for); none beyond
    /// [`MAX_STUCK_WINDOW_FRICTIONS`] frictions.
    stuck_windows: Vec<Option<Option<SlipWindows>>>,
    /// Sub-steps the force solve began and ended with a friction stuck (those a stuck window
    /// could have taken): the stuck windows are tried once they reach
    /// [`STUCK_WINDOWS_AFTER`] samples' worth.
    stuck_solves: usize,
    /// [`STUCK_WINDOWS_AFTER`]` × L` (the tests try them from the first).
    stuck_windows_after: usize,
    substeps: usize,
    /// The whole-sample test segment by segment ([`SlipEnvelope`]); `None` with fewer than 8
    /// sub-steps.
    envelope: Option<SlipEnvelope>,
    /// Each active friction's `δ` (or `δ̇`) at the sample's start, signed (work).
    starts: Vec<f64>,
    /// Sub-steps stepped by the stuck windows (the tests ask that they were used).
    #[cfg(test)]
    held_substeps: usize,
}

/// Sub-steps per segment of [`SlipEnvelope`]: 16 segments of a 64-sub-step sample.
/// Measured (fifty-ninth session, BENCHMARKS.md): segments of 8 were slower than the row
/// test where the bound rarely clears (a 100 %-noise record 1.25 s against 1.19), segments of
/// 4 nowhere slower.
const ENVELOPE_SEGMENT_SUBSTEPS: usize = 4;

/// The slip map's whole-sample test in `2K` products a friction where `δ` keeps well clear
/// of 0, instead of `L`: the sample's sub-steps cut into `K` segments; at each segment's end
/// `δ` is computed (its check row), and inside it every `δ_j` differs from the straight line
/// between the segment's two ends by at most `Σ_k m_k |input_k|`, `m` the largest absolute
/// difference of the segment's check rows from the interpolated end rows, coefficient by
/// coefficient (exact arithmetic: `δ_j = (1 − w) δ_a + w δ_b + e_j · input`, `|e_j · input| ≤
/// m · |input|`). When both ends have the slip's sign by more than that bound plus three
/// times the test's round-off scale (which covers the products' own rounding), every inner
/// `δ_j` would clear the row test; any other segment's rows are tested one by one, in order.
/// So the result is the row-by-row test's, the same `Err` (sub-steps cleared) or the same
/// map applied: the same bits.
///
/// Why: on finely sub-stepped models (64 sub-steps, the level continuous data keep) the
/// test's `L` products of the check rows were a third of a whole identification
/// (`dense::dot` 31 % of `perf record` on an RK4 record, fifty-ninth session); a segment of
/// 4 sub-steps is 1/16 of a sample, over which `δ` is nearly straight except near a
/// reversal. The bound ignores the cancellations between coefficients, so it is loose
/// (measured on a white random force: a spread of 0.1–1× `δ` a segment); it only has to
/// clear most segments.
#[derive(Debug)]
struct SlipEnvelope {
    /// Sub-step ends `b_1 < … < b_K = L` of the segments (the start, 0, before them).
    nodes: Vec<usize>,
    /// The bound's coefficients `m` per segment and friction (column `k r + i`), in the
    /// input's layout.
    bounds: DMatrix<f64>,
    /// `|input|` (work).
    abs_input: Vec<f64>,
    /// Segments tested row by row, cleared by the bound, and refused inside although both
    /// ends cleared (the tests ask that the bound fires and that it is needed).
    #[cfg(test)]
    segments: [usize; 3],
}

impl SlipEnvelope {
    /// From the check rows (`rows`: `r L` rows, a row per column, as `SlipSampleMap`) and the
    /// frictions' selection of the start state (`select`, `r × 3n`); `None` with fewer than two
    /// segments (`L < 8`: one segment is a whole sample, over which the bound is loose) or a
    /// row that is not finite (a bound made of it could not be trusted).
    fn new(rows: &DMatrix<f64>, select: &DMatrix<f64>, substeps: usize) -> Option<Self> {
        let L = substeps;
        let r = select.nrows();
        let width = rows.nrows();
        if L < 2 * ENVELOPE_SEGMENT_SUBSTEPS
            || r == 0
            || !rows.iter().chain(select.iter()).all(|x| x.is_finite())
        {
            return None;
        }
        let segments = L.div_ceil(ENVELOPE_SEGMENT_SUBSTEPS);
        let nodes: Vec<usize> = (1..=segments)
            .map(|k| ((k * L) as f64 / segments as f64).round() as usize)
            .collect();
        // The check row of friction `i` at sub-step end `j` (0: the start, its selection).
        let row_at = |j: usize, i: usize| -> Vec<f64> {
            if j == 0 {
                let mut v = vec![0.0; width];
                for (c, x) in v.iter_mut().zip(select.row(i).iter()) {
                    *c = *x;
                }
                v
            } else {
                rows.column((j - 1) * r + i).iter().copied().collect()
            }
        };
        let mut bounds = DMatrix::<f64>::zeros(width, segments * r);
        let mut a = 0;
        for (k, &b) in nodes.iter().enumerate() {
            for i in 0..r {
                let (ca, cb) = (row_at(a, i), row_at(b, i));
                let mut m = bounds.column_mut(k * r + i);
                for j in a + 1..b {
                    let w = (j - a) as f64 / (b - a) as f64;
                    for (((mc, x), ya), yb) in m
                        .iter_mut()
                        .zip(rows.column((j - 1) * r + i).iter())
                        .zip(&ca)
                        .zip(&cb)
                    {
                        *mc = mc.max((x - (1.0 - w) * ya - w * yb).abs());
                    }
                }
            }
            a = b;
        }
        Some(Self {
            nodes,
            bounds,
            abs_input: vec![0.0; width],
            #[cfg(test)]
            segments: [0; 3],
        })
    }

    /// The whole-sample test of [`SlipSampleMap::try_sample`] segment by segment: `Err` with
    /// the sub-steps cleared before the first check row that does not have its slip's sign
    /// by more than its round-off scale, as the row-by-row test
    /// ([`SlipSampleMap::check_every_substep`]) gives. A segment whose bound clears (both
    /// ends above it by `3 bound`) is passed without its inner rows (they would clear: see
    /// the type's doc); any other segment's rows are tested in order. `rows`, `row_sums`,
    /// `signs`, `input` as the map's; `starts` each friction's start `δ` times its sign;
    /// `bound` the worst row's round-off scale, `scale_of` a row's.
    #[allow(clippy::too_many_arguments)]
    fn check(
        &mut self,
        rows: &DMatrix<f64>,
        row_sums: &[[f64; 4]],
        input: &[f64],
        starts: &[f64],
        signs: &[f64],
        bound: f64,
        scale_of: &dyn Fn(&[f64; 4]) -> f64,
    ) -> Result<(), usize> {
        let r = starts.len();
        let width = input.len();
        for (a, x) in self.abs_input.iter_mut().zip(input) {
            *a = x.abs();
        }
        let (check, bounds) = (rows.as_slice(), self.bounds.as_slice());
        let margin_of = |j: usize, i: usize| {
            let row = (j - 1) * r + i;
            signs[i] * crate::dense::dot(&check[row * width..(row + 1) * width], input)
        };
        // The row test of `check_every_substep`, written so that a NaN fails.
        let clears = |j: usize, i: usize, margin: f64| {
            margin > bound || margin > SLIP_TEST_MARGIN * scale_of(&row_sums[(j - 1) * r + i])
        };
        // Room for the products' rounding over the round-off scale (see the type's doc).
        let floor = 3.0 * bound;
        #[cfg(test)]
        let mut counts = [0usize; 3];
        // The first sub-step (1-based) whose row does not clear, over the frictions.
        let mut first = usize::MAX;
        for (i, &start) in starts.iter().enumerate() {
            let (mut a, mut before) = (0, start);
            for (k, &b) in self.nodes.iter().enumerate() {
                if a + 1 >= first {
                    break;
                }
                let after = margin_of(b, i);
                let col = k * r + i;
                let spread =
                    crate::dense::dot(&bounds[col * width..(col + 1) * width], &self.abs_input)
                        * (1.0 + 1e-9);
                // Each end on its own (`f64::min` would drop a NaN); a NaN fails.
                let cleared = before - spread > floor && after - spread > floor;
                #[cfg(test)]
                {
                    counts[usize::from(cleared)] += 1;
                }
                if !cleared
                    && let Some(j) = (a + 1..=b)
                        .find(|&j| !clears(j, i, if j == b { after } else { margin_of(j, i) }))
                {
                    // A reversal inside a segment whose ends both clear: what the bound is for.
                    #[cfg(test)]
                    {
                        counts[2] += usize::from(j < b && before > floor && after > floor);
                    }
                    first = first.min(j);
                    break;
                }
                (a, before) = (b, after);
            }
        }
        #[cfg(test)]
        for (total, count) in self.segments.iter_mut().zip(counts) {
            *total += count;
        }
        if first == usize::MAX {
            Ok(())
        } else {
            Err(first - 1)
        }
    }
}

/// Samples' worth of sub-steps (`× L`) that the force solve must have begun and ended with a
/// friction stuck (those a stuck window could have taken) before a simulation tries the
/// stuck windows ([`SlipWindows::stuck`]). Their build
/// costs about as much as 4L force-solved sub-steps (about 0.2 ms on the paper model at 64
/// sub-steps, measured by `perf`: 3.7 % of a Coulomb record's identification, which has
/// ~160 stuck sub-steps a simulation and gained less than that); a joint stuck in most
/// samples reaches it within a few samples.
const STUCK_WINDOWS_AFTER: usize = 4;

/// Most frictions for which the slip map holds stuck windows (one set of windows per
/// subset of them stuck, `2ʳ − 1` at most).
const MAX_STUCK_WINDOW_FRICTIONS: usize = 4;

/// Most model DOFs for which the slip map builds window maps ([`SlipWindows`]: `L` maps of
/// `3n × (3n + 2 ne + q)` within [`MAX_WINDOW_MAP_BYTES`], else `log₂ L + 1` powers of the
/// `3n × 3n` sub-step).
const MAX_WINDOW_DOFS: usize = 100;

/// Most memory the window maps' powers `Tˡ`, `l = 1…L`, may take (8 MB: the paper model's
/// 11 DOFs at 64 sub-steps take 0.6 MB); a larger model steps a window's state by
/// `log₂ L + 1` products of `T^(2ᵏ)` instead of one.
const MAX_WINDOW_MAP_BYTES: usize = 8 << 20;

/// The slip map of a window of sub-steps `a+1 … a+l` inside a sample, `0 ≤ a < a + l ≤ L`:
/// the samples in which a friction reverses or sticks ([`SlipSampleMap::try_sample`]
/// refuses them) are stepped by these maps up to the sub-step the slip test cannot clear,
/// that one sub-step by the force solve, and the rest of the sample again by a window.
///
/// Why: where a joint's rate crosses zero in about half the samples (a Coulomb joint under
/// a broadband force), those samples took all `L` sub-steps through the force solve, most of
/// a free-run identification's time with 64 sub-steps; a reversal needs the force solve
/// only in the sub-step where it happens.
///
/// With the excitation `p_{a+k} = p_a + k Δp` over the window (linear over the sample, as
/// the sub-steps interpolate it) and the constant connection forces `b` of the slip:
/// `x_{a+l} = Tˡ x_a + S_l p_a + V_l Δp + B_l b` with `S_l = Σ_{m<l} Tᵐ Q_p`,
/// `V_l = Σ_{m<l} (l − m) Tᵐ Q_p` and `B_l = Σ_{m<l} Tᵐ Q_b`; the slip test reads `δ` (or
/// `δ̇`) at every sub-step of the window from the same sums through the friction's rows.
/// Algebraically the same sub-steps as the force solve's while the test clears them (the
/// uniqueness argument of [`SlipSampleMap`]); they differ by round-off only.
struct SlipWindows {
    /// Per lag `l = 1…L`, the window's map of [`Self::input`]: `[Tˡ S_l V_l B_l]` side by
    /// side (`3n × (3n + 2 ne + q)`), or only `[S_l V_l B_l]` where the `L` powers of `T`
    /// would take more than [`MAX_WINDOW_MAP_BYTES`], and always for the stuck windows
    /// ([`Self::stuck`]; then [`Self::powers`] step the state).
    lag_maps: Vec<DMatrix<f64>>,
    /// `T^(2ᵏ)`, k = 0, 1, … while `2ᵏ ≤ L`, when `lag_maps` hold no powers: `Tˡ x` in at
    /// most `log₂ L + 1` products; each square made when a window first needs it. Empty
    /// otherwise.
    powers: Vec<DMatrix<f64>>,
    /// The test's rows, lag `m = 1…L` and friction `i` at row `(m − 1) r + i`: a slipping
    /// friction's `δ` (or `δ̇`) row times `[Tᵐ S_m V_m B_m]`, a stuck one's force `λ` at
    /// that sub-step ([`Self::stuck`]), maps of [`Self::input`]; stored transposed (a row
    /// per column), read in order up to the first row not cleared.
    check_rows: DMatrix<f64>,
    /// Per check row: the absolute row sums of its four blocks (its round-off scale).
    row_sums: Vec<[f64; 4]>,
    /// The window's inputs side by side, `(x_a; p_a; Δp; b)`, `3n + 2 ne + q`.
    input: DVector<f64>,
    ne: usize,
    q: usize,
    /// Work vectors.
    powered: DVector<f64>,
    next: DVector<f64>,
    /// Per friction: held stuck in these windows ([`Self::stuck`]; its test row is its
    /// stuck force), else slipping (its row is its `δ` or `δ̇`).
    stuck: Vec<bool>,
    /// The frictions' levels (the stuck rows' bound; empty where none is stuck).
    levels: Vec<f64>,
}

/// The slip map's pieces that [`SlipWindows`] are built from: the folded sub-step
/// `x' = T x + Q_p p + Q_b b`, the frictions' `δ` (or `δ̇`) rows of the state, and those rows
/// through `Tʲ`, `j = 1…L` (the whole-sample test's state block).
struct WindowParts {
    T: DMatrix<f64>,
    Qp: DMatrix<f64>,
    Qb: DMatrix<f64>,
    select: DMatrix<f64>,
    check_state: DMatrix<f64>,
    /// The most the powers `Tˡ` may take ([`MAX_WINDOW_MAP_BYTES`]; the tests vary it).
    map_bytes: usize,
}

impl SlipWindows {
    /// The windows of the slip: every friction slipping, its `±level` among the inputs `b`.
    fn new(parts: &WindowParts, substeps: usize) -> Self {
        let WindowParts {
            T,
            Qp,
            Qb,
            select,
            check_state,
            map_bytes,
        } = parts;
        let (dim, r) = (T.nrows(), select.nrows());
        Self::build(
            (T, Qp, Qb),
            substeps,
            *map_bytes,
            |j, _, lag, rows| {
                let row = r * (j - 1);
                let inputs = crate::dense::side_by_side(&lag);
                rows.view_mut((0, 0), (r, dim))
                    .copy_from(&check_state.view((row, 0), (r, dim)));
                rows.view_mut((0, dim), (r, inputs.ncols()))
                    .copy_from(&product(select, &inputs));
            },
            (vec![false; r], Vec::new()),
        )
    }

    /// The windows of the frictions `stuck` held stuck (the others slipping as in
    /// [`Self::new`]); `None` when their constraint cannot be solved for (a singular
    /// compliance `S Q_b E`) or its maps are not finite. They step the state by the powers `T^(2ᵏ)` (no `L` powers of `T`):
    /// under the Newmark sub-step a stuck joint's force alternates from one sub-step to the
    /// next (the constraint on `δ` or `δ̇` flips the connection's acceleration), so its
    /// stuck runs are short — on a Coulomb record stuck in most samples, half the windows
    /// tried break loose at their first sub-step — and building the `L` powers, once per
    /// simulation, cost more than the windows saved (measured on an ordinary Coulomb
    /// record: 0.77 s with them, 0.70 s with the squares, BENCHMARKS.md).
    ///
    /// A stuck friction holds its `δ` (or `δ̇`) at 0 at every sub-step's end with the force
    /// `λ` that takes: the sub-step `x' = T x + Q_p p + Q_b b` becomes
    /// `x' = P (T x + Q_p p + Q_b b)` with `P = I − Q_b E (S Q_b E)⁻¹ S` (`S` the stuck
    /// frictions' rows of the state, `E` their connections' columns), and
    /// `λ = −(S Q_b E)⁻¹ S (T x + Q_p p + Q_b b)`. The windows of that projected sub-step
    /// are built as the slip's; the test's row of a stuck friction is its `λ` at every
    /// sub-step, cleared while `|λ|` is below the level by more than its round-off — where
    /// the force solve, which finds the one solution of a set-valued friction with a
    /// positive compliance, also keeps it stuck.
    fn stuck(
        parts: &WindowParts,
        substeps: usize,
        friction: &[(usize, bool, f64)],
        stuck: &[bool],
    ) -> Option<Self> {
        let WindowParts {
            T, Qp, Qb, select, ..
        } = parts;
        let (dim, r) = (T.nrows(), select.nrows());
        let held: Vec<usize> = (0..r).filter(|&i| stuck[i]).collect();
        let rs = held.len();
        let s_held = DMatrix::from_fn(rs, dim, |k, j| select[(held[k], j)]);
        let qb_held = DMatrix::from_fn(dim, rs, |i, k| Qb[(i, friction[held[k]].0)]);
        let compliance = product(&s_held, &qb_held);
        let inverse = compliance.try_inverse()?;
        let gs = product(&inverse, &s_held);
        let projection = DMatrix::<f64>::identity(dim, dim) - product(&qb_held, &gs);
        let (t_held, qp_held, qb_all_held) = (
            product(&projection, T),
            product(&projection, Qp),
            product(&projection, Qb),
        );
        // λ of the sub-step from lag `j − 1`: `−(W x_{a+j−1} + U p_{a+j} + U_b b)`.
        let (W, U, Ub) = (product(&gs, T), product(&gs, Qp), product(&gs, Qb));
        if [&t_held, &qp_held, &qb_all_held, &W, &U, &Ub]
            .iter()
            .any(|m| m.iter().any(|v| !v.is_finite()))
        {
            return None;
        }
        // `W` and the slipping frictions' rows carried through the projected `Tʲ`.
        let mut w_state = W.clone();
        let mut slip_state = select.clone();
        let levels = friction.iter().map(|f| f.2).collect();
        Some(Self::build(
            (&t_held, &qp_held, &qb_all_held),
            substeps,
            0,
            |j, before, lag, rows| {
                // (One friction, or all stuck: no slipping rows to carry.)
                let slipping = if rs < r {
                    slip_state = product(&slip_state, &t_held);
                    product(select, &crate::dense::side_by_side(&lag))
                } else {
                    DMatrix::zeros(r, lag.iter().map(|m| m.ncols()).sum())
                };
                let held_p0 = product(&W, before[0]) + &U;
                let held_dp = product(&W, before[1]) + &U * j as f64;
                let held_b = product(&W, before[2]) + &Ub;
                let width = dim + slipping.ncols();
                let mut k = 0;
                for i in 0..r {
                    if stuck[i] {
                        let at = |m: &DMatrix<f64>, c: usize| -m[(k, c)];
                        for c in 0..dim {
                            rows[(i, c)] = at(&w_state, c);
                        }
                        let ne = held_p0.ncols();
                        for c in 0..ne {
                            rows[(i, dim + c)] = at(&held_p0, c);
                            rows[(i, dim + ne + c)] = at(&held_dp, c);
                        }
                        for c in 0..held_b.ncols() {
                            rows[(i, dim + 2 * ne + c)] = at(&held_b, c);
                        }
                        k += 1;
                    } else {
                        rows.view_mut((i, 0), (1, dim))
                            .copy_from(&slip_state.row(i));
                        rows.view_mut((i, dim), (1, width - dim))
                            .copy_from(&slipping.row(i));
                    }
                }
                w_state = product(&w_state, &t_held);
            },
            (stuck.to_vec(), levels),
        ))
    }

    /// The windows of the sub-step `x' = T x + Q_p p + Q_b b` (`T`, `Q_p`, `Q_b`): its sums
    /// by lag and the test's rows, `check_at(j, sums at lag j − 1, sums at lag j)` for lag
    /// `j = 1…L` (the sums `S`, `V`, `B`; zero at lag 0), `r` rows of the inputs each.
    fn build(
        (T, Qp, Qb): (&DMatrix<f64>, &DMatrix<f64>, &DMatrix<f64>),
        substeps: usize,
        map_bytes: usize,
        mut check_at: impl FnMut(
            usize,
            [&DMatrix<f64>; 3],
            [&DMatrix<f64>; 3],
            &mut nalgebra::DMatrixViewMut<f64>,
        ),
        (stuck, levels): (Vec<bool>, Vec<f64>),
    ) -> Self {
        let (dim, ne, q, r) = (T.nrows(), Qp.ncols(), Qb.ncols(), stuck.len());
        // The sums at lag `j`: `S_j`, `V_j`, `B_j` side by side, and the test's rows of them.
        let (mut lag_s, mut lag_v, mut lag_b) = (Qp.clone(), Qp.clone(), Qb.clone());
        let (mut before_s, mut before_v, mut before_b) = (
            DMatrix::zeros(dim, ne),
            DMatrix::zeros(dim, ne),
            DMatrix::zeros(dim, q),
        );
        let mut lag_maps = Vec::with_capacity(substeps);
        let width = dim + 2 * ne + q;
        let mut check = DMatrix::zeros(r * substeps, width);
        for j in 1..=substeps {
            check_at(
                j,
                [&before_s, &before_v, &before_b],
                [&lag_s, &lag_v, &lag_b],
                &mut check.view_mut((r * (j - 1), 0), (r, width)),
            );
            lag_maps.push(crate::dense::side_by_side(&[&lag_s, &lag_v, &lag_b]));
            // S_{j+1} = Q_p + T S_j, V_{j+1} = V_j + S_{j+1}, B_{j+1} = Q_b + T B_j.
            let next_s = product(T, &lag_s) + Qp;
            let next_v = &lag_v + &next_s;
            let next_b = product(T, &lag_b) + Qb;
            before_s = std::mem::replace(&mut lag_s, next_s);
            before_v = std::mem::replace(&mut lag_v, next_v);
            before_b = std::mem::replace(&mut lag_b, next_b);
        }
        let mut powers = Vec::new();
        if substeps * dim * dim * std::mem::size_of::<f64>() <= map_bytes {
            let mut power = T.clone();
            for map in &mut lag_maps {
                *map = crate::dense::side_by_side(&[&power, map]);
                power = product(T, &power);
            }
        } else {
            // The squares are made as the windows need them ([`Self::advance`]).
            powers.push(T.clone());
        }
        let blocks = [(0, dim), (dim, ne), (dim + ne, ne), (dim + 2 * ne, q)];
        let row_sums = (0..check.nrows())
            .map(|row| {
                blocks.map(|(at, len)| {
                    check
                        .view((row, at), (1, len))
                        .iter()
                        .map(|v| v.abs())
                        .sum()
                })
            })
            .collect();
        Self {
            powers,
            lag_maps,
            row_sums,
            input: DVector::zeros(dim + 2 * ne + q),
            ne,
            q,
            powered: DVector::zeros(dim),
            next: DVector::zeros(dim),
            check_rows: crate::dense::transposed(&check),
            stuck,
            levels,
        }
    }

    /// Set the window's start `x_a` from `s`, `p_a` and `Δp` for a window from sub-step `a`
    /// of `L` in the sample `pa → pb` (missing channels read as 0); `b` is set apart.
    fn start(&mut self, s: &State, a: usize, substeps: usize, pa: &[f64], pb: &[f64]) {
        let n = s.u.len();
        let ne = self.ne;
        let input = self.input.as_mut_slice();
        input[..n].copy_from_slice(s.u.as_slice());
        input[n..2 * n].copy_from_slice(s.v.as_slice());
        input[2 * n..3 * n].copy_from_slice(s.a.as_slice());
        let t = a as f64 / substeps as f64;
        interpolate_excitation(&mut input[3 * n..3 * n + ne], pa, pb, t);
        for j in 0..ne {
            let (x0, x1) = (
                pa.get(j).copied().unwrap_or(0.0),
                pb.get(j).copied().unwrap_or(0.0),
            );
            input[3 * n + ne + j] = (x1 - x0) / substeps as f64;
        }
    }

    /// The constant connection forces `b` of the window (the last `q` inputs).
    fn forces_mut(&mut self) -> &mut [f64] {
        let at = self.input.len() - self.q;
        &mut self.input.as_mut_slice()[at..]
    }

    /// How many of the sub-steps `a+1 … L` the windows clear, in order from the first: a
    /// slipping friction's `δ` or `δ̇` has its slip's sign in `signs` by more than its
    /// round-off, a stuck one's force is below its level by more than its terms' round-off.
    #[inline]
    fn cleared(&mut self, a: usize, substeps: usize, signs: &[f64]) -> usize {
        use crate::dense::amax;
        let dim = self.powered.len();
        let ne = self.ne;
        let input = self.input.as_slice();
        let norms = [
            amax(&input[..dim]),
            amax(&input[dim..dim + ne]),
            amax(&input[dim + ne..dim + 2 * ne]),
            amax(&input[dim + 2 * ne..]),
        ];
        let r = signs.len();
        let rows = (substeps - a) * r;
        let deltas = self
            .check_rows
            .as_slice()
            .chunks_exact(input.len())
            .map(|row| crate::dense::dot(row, input));
        let held = !self.levels.is_empty();
        for (row, (delta, sums)) in deltas.zip(&self.row_sums).take(rows).enumerate() {
            let i = row % r;
            // Written so that a NaN fails the test too.
            let clear = if held && self.stuck[i] {
                // The stuck force's terms (`λ` is a small difference of large terms: the
                // state's response through the inverse compliance of a sub-step), each
                // taken at its size: the blocks' bound above would exceed the level.
                let terms: f64 = self.check_rows.as_slice()[row * input.len()..]
                    .iter()
                    .zip(input)
                    .map(|(a, b)| (a * b).abs())
                    .sum();
                self.levels[i] - delta.abs() > SLIP_TEST_MARGIN * terms
            } else {
                let scale: f64 = sums.iter().zip(&norms).map(|(s, v)| s * v).sum();
                signs[i] * delta > SLIP_TEST_MARGIN * scale
            };
            if !clear {
                return row / r;
            }
        }
        substeps - a
    }

    /// Step `s` over the `l ≥ 1` sub-steps of the window [`Self::start`]ed at it.
    fn advance(&mut self, s: &mut State, l: usize) {
        use crate::dense::{Op, gemv, gemv_slices};
        let n = s.u.len();
        let dim = 3 * n;
        let map = &self.lag_maps[l - 1];
        if map.ncols() == self.input.len() {
            gemv(&mut self.powered, map, &self.input, Op::Set);
            s.u.copy_from(&self.powered.rows(0, n));
            s.v.copy_from(&self.powered.rows(n, n));
            s.a.copy_from(&self.powered.rows(2 * n, n));
            return;
        }
        self.powered.copy_from(&self.input.rows(0, dim));
        let needed = (usize::BITS - l.leading_zeros()) as usize;
        while self.powers.len() < needed {
            // (`powers` holds `T` itself whenever `lag_maps` hold no powers.)
            let last = self
                .powers
                .last()
                .expect("the window's powers start with T");
            let square = product(last, last);
            self.powers.push(square);
        }
        let mut bits = l;
        for power in &self.powers {
            if bits & 1 == 1 {
                gemv(&mut self.next, power, &self.powered, Op::Set);
                std::mem::swap(&mut self.next, &mut self.powered);
            }
            bits >>= 1;
        }
        gemv_slices(
            self.powered.as_mut_slice(),
            map,
            &self.input.as_slice()[dim..],
            Op::Add,
        );
        s.u.copy_from(&self.powered.rows(0, n));
        s.v.copy_from(&self.powered.rows(n, n));
        s.a.copy_from(&self.powered.rows(2 * n, n));
    }
}

/// Margin of a slip direction's test over the round-off scale of `δ_j` (`Σ|terms|` of the
/// map's products): the folded map and the force solve compute `δ_j` in different orders,
/// and a sign is taken from the map only when it is clear of that scale. (Where `δ_j` is
/// nearly 0 the two paths' solutions nearly coincide anyway, so a call made wrong by the
/// force solve's own cancellations would cost round-off, not a different answer.)
const SLIP_TEST_MARGIN: f64 = 1e-11;

impl SlipSampleMap {
    /// `None` when the law has another term (`u³`, `a`, a gap), the folded structure is
    /// singular or, with a friction active, the connections' compliance through it is not
    /// positive definite, or the model has no dense form.
    fn new(
        setup: &Setup,
        model: &Model,
        params: &[f64],
        dt_s: f64,
        substeps: usize,
    ) -> Result<Option<Self>, SimulateError> {
        Self::with_window_bytes(setup, model, params, dt_s, substeps, MAX_WINDOW_MAP_BYTES)
    }

    /// [`Self::new`] with the window maps' powers of `T` held only within `map_bytes`
    /// ([`SlipWindows`]; the tests step both ways).
    fn with_window_bytes(
        setup: &Setup,
        model: &Model,
        params: &[f64],
        dt_s: f64,
        substeps: usize,
        map_bytes: usize,
    ) -> Result<Option<Self>, SimulateError> {
        if !model.has_dense() || substeps == 0 {
            return Ok(None);
        }
        let n = model.n();
        let q = model.Lc.ncols();
        if q != setup.connections.len() {
            return Ok(None);
        }
        let Some(law) = FoldedLaw::of(setup, params)? else {
            return Ok(None);
        };
        // No friction active (every level 0: a law on its bound, the prediction error's
        // noise record): the map has no slip to test and is the folded linear sample map.
        // Why not decline it (as before): those samples then went through the sub-step
        // composition, 1.5× the time of a run with friction.
        let Newmark = setup.newmark;
        let (gamma, beta) = (Newmark.gamma, Newmark.beta);
        let h = dt_s / substeps as f64;
        let lc = &model.Lc;
        let (K, C, meff) = law.structure(model, gamma, beta, h);
        let FoldedLaw {
            const_force,
            friction,
            ..
        } = law;
        // A singular folded structure (a trial point of a descent can make it so) only
        // declines the map: the force solve works on the unfolded one.
        let Some(meff_inv) = meff.try_inverse() else {
            return Ok(None);
        };
        // The slip test's uniqueness argument needs the connections' compliance through the
        // folded structure, `Lcᵀ M_eff⁻¹ Lc`, positive definite (a stiffness or damper term
        // negative enough to make it indefinite, as a descent may try, can make both slip
        // directions consistent): otherwise every sample goes through the force solve.
        let compliance = lc.transpose() * &meff_inv * lc;
        if !friction.is_empty()
            && ((&compliance + compliance.transpose()) * 0.5)
                .cholesky()
                .is_none()
        {
            return Ok(None);
        }
        let ne = model.Lp.ncols();
        // Inputs (p, b): the excitation and the constant connection forces (acting as −Lc b).
        let mut B = DMatrix::zeros(n, ne + q);
        B.columns_mut(0, ne).copy_from(&model.Lp);
        B.columns_mut(ne, q).copy_from(&(-lc));
        let (T, Q) = newmark_substep_map(&meff_inv, &C, &K, &B, h, gamma, beta);
        let (Qp, Qb) = (Q.columns(0, ne).into_owned(), Q.columns(ne, q).into_owned());
        let r = friction.len();
        let mut select = DMatrix::zeros(r, 3 * n);
        for (i, &(ci, on_velocity, _)) in friction.iter().enumerate() {
            let col = if on_velocity { n } else { 0 };
            for d in 0..n {
                select[(i, col + d)] = lc[(d, ci)];
            }
        }
        let select_taps = (0..r)
            .map(|i| {
                (0..3 * n)
                    .filter(|&j| select[(i, j)] != 0.0)
                    .map(|j| (j, select[(i, j)]))
                    .collect()
            })
            .collect();
        let L = substeps;
        let mut check_state = DMatrix::zeros(r * L, 3 * n);
        let mut check_p0 = DMatrix::zeros(r * L, ne);
        let mut check_p1 = DMatrix::zeros(r * L, ne);
        let mut check_b = DMatrix::zeros(r * L, q);
        let mut s = select.clone();
        let mut g0 = DMatrix::<f64>::zeros(3 * n, ne);
        let mut g1 = DMatrix::<f64>::zeros(3 * n, ne);
        let mut gb = DMatrix::<f64>::zeros(3 * n, q);
        for j in 1..=L {
            let t = j as f64 / L as f64;
            s = product(&s, &T);
            g0 = product(&T, &g0) + &Qp * (1.0 - t);
            g1 = product(&T, &g1) + &Qp * t;
            gb = product(&T, &gb) + &Qb;
            let rows = (r * (j - 1), 0);
            check_state.view_mut(rows, (r, 3 * n)).copy_from(&s);
            check_p0
                .view_mut(rows, (r, ne))
                .copy_from(&product(&select, &g0));
            check_p1
                .view_mut(rows, (r, ne))
                .copy_from(&product(&select, &g1));
            check_b
                .view_mut(rows, (r, q))
                .copy_from(&product(&select, &gb));
        }
        let check_rows = crate::dense::transposed(&crate::dense::side_by_side(&[
            &check_state,
            &check_p0,
            &check_p1,
            &check_b,
        ]));
        let envelope = SlipEnvelope::new(&check_rows, &select, L);
        // What the windows are built from, at the first sample the test refuses.
        let window_parts = (r > 0 && L >= 2 && n <= MAX_WINDOW_DOFS).then(|| WindowParts {
            T: T.clone(),
            Qp,
            Qb,
            select,
            check_state: check_state.clone(),
            map_bytes,
        });
        let abs_sum = |m: &DMatrix<f64>, row: usize| m.row(row).iter().map(|v| v.abs()).sum();
        let row_sums = (0..r * L)
            .map(|row| {
                [
                    abs_sum(&check_state, row),
                    abs_sum(&check_p0, row),
                    abs_sum(&check_p1, row),
                    abs_sum(&check_b, row),
                ]
            })
            .collect::<Vec<[f64; 4]>>();
        let largest_row_sums = row_sums.iter().fold([0.0f64; 4], |acc, s| {
            std::array::from_fn(|k| acc[k].max(s[k]))
        });
        let phi = matrix_power(T, L);
        use crate::dense::side_by_side;
        Ok(Some(Self {
            largest_row_sums,
            step: side_by_side(&[&phi, &g0, &g1, &gb]),
            envelope,
            starts: vec![0.0; r],
            check_rows,
            row_sums,
            friction,
            select: select_taps,
            const_force,
            input: DVector::zeros(3 * n + 2 * ne + q),
            ne,
            next: DVector::zeros(3 * n),
            signs: vec![0.0; r],
            stuck_windows: if window_parts.is_some() && r <= MAX_STUCK_WINDOW_FRICTIONS {
                (0..1usize << r).map(|_| None).collect()
            } else {
                Vec::new()
            },
            window_parts,
            windows: None,
            stuck_solves: 0,
            stuck_windows_after: STUCK_WINDOWS_AFTER * L,
            substeps: L,
            #[cfg(test)]
            held_substeps: 0,
        }))
    }

    /// Step the sample `pa → pb` if every friction keeps slipping the way the start state's
    /// `δ` (or `δ̇`) points through all the sub-steps. When it does not (`s` untouched), the
    /// error holds how many of the first sub-steps the test cleared (0 when a friction
    /// starts at `δ = 0`, or at a `δ` that is not finite).
    fn try_sample(&mut self, s: &mut State, pa: &[f64], pb: &[f64]) -> Result<(), usize> {
        use crate::dense::amax;
        let n = s.u.len();
        let ne = self.ne;
        let input = self.input.as_mut_slice();
        let (x, rest) = input.split_at_mut(3 * n);
        let (p0, rest) = rest.split_at_mut(ne);
        let (p1, b) = rest.split_at_mut(ne);
        x[..n].copy_from_slice(s.u.as_slice());
        x[n..2 * n].copy_from_slice(s.v.as_slice());
        x[2 * n..].copy_from_slice(s.a.as_slice());
        b.copy_from_slice(self.const_force.as_slice());
        for (i, &(ci, _, level)) in self.friction.iter().enumerate() {
            // `-0.0 + …` as the dense row's `Iterator::sum` started.
            let now = self.select[i]
                .iter()
                .fold(-0.0, |acc, &(j, coef)| acc + coef * x[j]);
            if now == 0.0 || !now.is_finite() {
                return Err(0);
            }
            self.signs[i] = now.signum();
            self.starts[i] = now.abs();
            b[ci] += self.signs[i] * level;
        }
        let b_max = b.iter().fold(0.0f64, |m, v| m.max(v.abs()));
        for j in 0..ne {
            p0[j] = pa.get(j).copied().unwrap_or(0.0);
            p1[j] = pb.get(j).copied().unwrap_or(0.0);
        }
        let norms = [amax(x), amax(p0), amax(p1), b_max];
        let scale_of =
            |sums: &[f64; 4]| -> f64 { sums.iter().zip(&norms).map(|(a, b)| a * b).sum() };
        // The round-off scale of the worst row bounds every row's: most rows clear it.
        let bound = SLIP_TEST_MARGIN * scale_of(&self.largest_row_sums);
        match self.envelope.as_mut() {
            Some(envelope) => envelope.check(
                &self.check_rows,
                &self.row_sums,
                self.input.as_slice(),
                &self.starts,
                &self.signs,
                bound,
                &scale_of,
            )?,
            None => self.check_every_substep(bound, &norms)?,
        }
        crate::dense::gemv(
            &mut self.next,
            &self.step,
            &self.input,
            crate::dense::Op::Set,
        );
        s.u.copy_from(&self.next.rows(0, n));
        s.v.copy_from(&self.next.rows(n, n));
        s.a.copy_from(&self.next.rows(2 * n, n));
        Ok(())
    }

    /// The whole-sample test of [`Self::try_sample`], every check row in order: `Err` with
    /// the sub-steps cleared before the first row that does not have its slip's sign by more
    /// than its round-off scale (`bound`: the worst row's; `norms`: the input blocks' largest
    /// values).
    fn check_every_substep(&self, bound: f64, norms: &[f64; 4]) -> Result<(), usize> {
        let scale_of =
            |sums: &[f64; 4]| -> f64 { sums.iter().zip(norms).map(|(a, b)| a * b).sum() };
        let signs = self.signs.iter().cycle();
        let r = self.signs.len();
        let width = self.input.len();
        let deltas = self
            .check_rows
            .as_slice()
            .chunks_exact(width)
            .map(|row| crate::dense::dot(row, self.input.as_slice()));
        for (row, ((delta, sums), sign)) in deltas.zip(&self.row_sums).zip(signs).enumerate() {
            let margin = sign * delta;
            // Written so that a NaN fails the test too.
            let clear = margin > bound || margin > SLIP_TEST_MARGIN * scale_of(sums);
            if !clear {
                return Err(row / r);
            }
        }
        Ok(())
    }

    /// Step a sample that [`Self::try_sample`] refused after clearing its first `cleared`
    /// sub-steps: those by a window map ([`SlipWindows`]), the sub-step the test could not
    /// clear by `sys`'s force solve, the rest again by a window from there, and so on.
    /// `None` when a force solve fails (the caller makes sure there are windows to build).
    fn sample_by_windows(
        &mut self,
        sys: &mut TruthSystem,
        s: &mut State,
        pa: &[f64],
        pb: &[f64],
        cleared: usize,
        pt: &mut DVector<f64>,
    ) -> Option<()> {
        let L = self.substeps;
        if self.windows.is_none() {
            self.windows = Some(SlipWindows::new(self.window_parts.as_ref()?, L));
        }
        let (mut a, mut cleared) = (0, cleared);
        // The whole-sample test's slip (its signs and forces) holds for the sub-steps it
        // cleared.
        if cleared > 0 {
            let windows = self.windows.as_mut()?;
            windows.start(s, 0, L, pa, pb);
            let b = &self.input.as_slice()[self.input.len() - windows.q..];
            windows.forces_mut().copy_from_slice(b);
        }
        loop {
            if cleared > 0 {
                self.windows.as_mut()?.advance(s, cleared);
                for (&(ci, ..), &sign) in self.friction.iter().zip(&self.signs) {
                    sys.status[ci] = Status::Slip(sign);
                }
                a += cleared;
            } else {
                // A friction the last sub-step left stuck: the windows that hold it stuck.
                a += self.held_stuck(sys, s, a, pa, pb);
            }
            if a == L {
                return Some(());
            }
            // The sub-step the tests could not clear: by the force solve, the excitation
            // interpolated as [`TruthSystem::sample_substeps`] does.
            let t = (a + 1) as f64 / L as f64;
            interpolate_excitation(pt.as_mut_slice(), pa, pb, t);
            let stuck = |sys: &TruthSystem| {
                self.friction
                    .iter()
                    .any(|f| sys.status[f.0] == Status::Stick)
            };
            let counted = self.stuck_solves < self.stuck_windows_after && stuck(sys);
            sys.substep_in_place(s, pt)?;
            if counted && stuck(sys) {
                self.stuck_solves += 1;
            }
            a += 1;
            if a == L {
                return Some(());
            }
            // The slip the new state points to, as the whole-sample test takes it.
            let windows = self.windows.as_mut()?;
            windows.start(s, a, L, pa, pb);
            let b = windows.forces_mut();
            b.copy_from_slice(self.const_force.as_slice());
            let mut slipping = true;
            for (i, taps) in self.select.iter().enumerate() {
                let x = windows.input.as_slice();
                let now = taps.iter().fold(-0.0, |acc, &(j, coef)| acc + coef * x[j]);
                if now == 0.0 || !now.is_finite() {
                    slipping = false;
                    break;
                }
                self.signs[i] = now.signum();
            }
            if slipping {
                let at = windows.input.len() - windows.q;
                for (&(ci, _, level), sign) in self.friction.iter().zip(&self.signs) {
                    windows.input[at + ci] += sign * level;
                }
            }
            cleared = if slipping {
                windows.cleared(a, L, &self.signs)
            } else {
                0
            };
        }
    }

    /// Step `s` from sub-step `a` of the sample `pa → pb` over the sub-steps in which the
    /// frictions `sys` left stuck stay stuck and the others keep slipping their way (the
    /// windows of [`SlipWindows::stuck`], built at the first sample that needs them);
    /// returns how many (0 when no friction is stuck, or the next sub-step breaks one
    /// loose).
    fn held_stuck(
        &mut self,
        sys: &mut TruthSystem,
        s: &mut State,
        a: usize,
        pa: &[f64],
        pb: &[f64],
    ) -> usize {
        if self.stuck_windows.is_empty() || self.stuck_solves < self.stuck_windows_after {
            return 0;
        }
        let L = self.substeps;
        let mut mask = 0;
        for (i, &(ci, ..)) in self.friction.iter().enumerate() {
            match sys.status[ci] {
                Status::Stick => mask |= 1 << i,
                Status::Slip(sign) => self.signs[i] = sign,
                Status::Free => return 0,
            }
        }
        if mask == 0 || mask >= self.stuck_windows.len() {
            return 0;
        }
        let (friction, parts) = (&self.friction, &self.window_parts);
        let slot = &mut self.stuck_windows[mask];
        let Some(windows) = slot
            .get_or_insert_with(|| {
                let stuck: Vec<bool> = (0..friction.len()).map(|i| mask >> i & 1 == 1).collect();
                parts
                    .as_ref()
                    .and_then(|parts| SlipWindows::stuck(parts, L, friction, &stuck))
            })
            .as_mut()
        else {
            return 0;
        };
        windows.start(s, a, L, pa, pb);
        let at = windows.input.len() - windows.q;
        windows.input.as_mut_slice()[at..].copy_from_slice(self.const_force.as_slice());
        for (i, &(ci, _, level)) in self.friction.iter().enumerate() {
            if mask >> i & 1 == 0 {
                windows.input[at + ci] += self.signs[i] * level;
            }
        }
        let cleared = windows.cleared(a, L, &self.signs);
        if cleared > 0 {
            windows.advance(s, cleared);
            #[cfg(test)]
            {
                self.held_substeps += cleared;
            }
            for (i, &(ci, ..)) in self.friction.iter().enumerate() {
                sys.status[ci] = if mask >> i & 1 == 1 {
                    Status::Stick
                } else {
                    Status::Slip(self.signs[i])
                };
            }
        }
        cleared
    }

    /// The slip directions per friction's connection, as the last [`Self::try_sample`] set
    /// them: read right after it succeeded.
    fn slips(&self) -> impl Iterator<Item = (usize, f64)> + '_ {
        self.friction
            .iter()
            .zip(&self.signs)
            .map(|(&(ci, ..), &s)| (ci, s))
    }
}

/// `Tᴸ` by repeated squaring (the sample map of `L` equal sub-steps).
fn matrix_power(mut base: DMatrix<f64>, mut e: usize) -> DMatrix<f64> {
    let mut power = DMatrix::<f64>::identity(base.nrows(), base.ncols());
    while e > 0 {
        if e & 1 == 1 {
            power = product(&power, &base);
        }
        e >>= 1;
        if e > 0 {
            base = product(&base, &base);
        }
    }
    power
}

/// One Newmark sub-step of step `h` as a linear map of `x = (u; u̇; ü)` and the input `p`
/// (forces `B p`), with no connection force: `x' = T x + Q p`. From the predictors
/// `ũ = u + h u̇ + (½ − β)h² ü`, `ṽ = u̇ + (1 − γ)h ü`: `ü' = Meff⁻¹(B p − C ṽ − K ũ)`,
/// `u' = ũ + βh² ü'`, `u̇' = ṽ + γh ü'`.
#[allow(clippy::too_many_arguments)]
fn newmark_substep_map(
    meff_inv: &DMatrix<f64>,
    C: &DMatrix<f64>,
    K: &DMatrix<f64>,
    B: &DMatrix<f64>,
    h: f64,
    gamma: f64,
    beta: f64,
) -> (DMatrix<f64>, DMatrix<f64>) {
    let n = K.nrows();
    let eye = DMatrix::<f64>::identity(n, n);
    let mut Pu = DMatrix::zeros(n, 3 * n);
    Pu.view_mut((0, 0), (n, n)).copy_from(&eye);
    Pu.view_mut((0, n), (n, n)).copy_from(&(&eye * h));
    Pu.view_mut((0, 2 * n), (n, n))
        .copy_from(&(&eye * ((0.5 - beta) * h * h)));
    let mut Pv = DMatrix::zeros(n, 3 * n);
    Pv.view_mut((0, n), (n, n)).copy_from(&eye);
    Pv.view_mut((0, 2 * n), (n, n))
        .copy_from(&(&eye * ((1.0 - gamma) * h)));
    let Aa = -(meff_inv * (C * &Pv + K * &Pu));
    let Ba = meff_inv * B;
    let stack = |top: &DMatrix<f64>, mid: &DMatrix<f64>, low: &DMatrix<f64>| {
        let c = top.ncols();
        let mut out = DMatrix::zeros(3 * n, c);
        out.view_mut((0, 0), (n, c)).copy_from(top);
        out.view_mut((n, 0), (n, c)).copy_from(mid);
        out.view_mut((2 * n, 0), (n, c)).copy_from(low);
        out
    };
    let T = stack(
        &(&Pu + &Aa * (beta * h * h)),
        &(&Pv + &Aa * (gamma * h)),
        &Aa,
    );
    let Q = stack(&(&Ba * (beta * h * h)), &(&Ba * (gamma * h)), &Ba);
    (T, Q)
}

/// The `L` Newmark sub-steps of one sample composed around the connection forces: the
/// prediction's map for a law that is not linear (friction, `u³`, gaps) with many sub-steps.
///
/// Why: a sub-step is linear in the state `x = (u; u̇; ü)`, the excitation and the connection
/// forces, `x' = T x + Q p + G_f f` (`G_f = −(βh² Y; γh Y; Y)`), and the force solve only
/// needs the connections' free deformation, rate and acceleration `Lc₃ᵀ(T x + Q p)` (`3q`
/// numbers). So over a sample the free deformations of all `L` sub-steps are one
/// `3qL × 3n` product of the sample's start state plus the earlier sub-steps' force
/// impulses (`Lc₃ᵀ Tᵏ G_f`, `3q × q` each), and the end state is one `3n × 3n` product plus
/// the `L` forces' responses. Per sample that is `9n² + 12qnL + 3q²L²/2` multiplications
/// instead of `~(3n² + 15n) L` (the paper model, n = 11, q = 1: 1.9× fewer at L = 8, 2.2× at
/// L = 64), in a few long products instead of many short ones. Algebraically the same
/// sub-steps as [`TruthSystem::substep_in_place`] (the same force solve on the same free
/// predictions); they differ by round-off only.
struct ComposedSubsteps {
    substeps: usize,
    q: usize,
    /// `Lc₃ᵀ Tʲ`, j = 1…L, stacked by quantity (row `c L + j − 1`: δ₀, δ̇₀, δ̈₀ of each
    /// connection `c` at sub-step `j`, contiguous over the sub-steps), side by side with the
    /// excitation's part of the same for the sample's start `p_{i−1}` and end `p_i`
    /// (linearly interpolated over the sub-steps): a map of
    /// the first `3n + 2 ne` entries of [`Self::input`].
    free_map: DMatrix<f64>,
    /// `Lc₃ᵀ Tᵏ G_f`, k = 1…L−1: entry `(c, m)` of each as one vector over k
    /// (`impulse_by_lag[c q + m][k − 1]`), so each force is spread over the later sub-steps
    /// by one contiguous `axpy`.
    impulse_by_lag: Vec<Vec<f64>>,
    /// The end state from [`Self::input`]: `T^L`, the excitation's part and
    /// `T^{L−j} G_f`, j = 1…L (`3n × qL`), side by side.
    end_map: DMatrix<f64>,
    /// The inputs side by side: the start state `x`, `p_{i−1}`, `p_i` and the forces of the
    /// sample's sub-steps (`q` per sub-step), `3n + 2 ne + qL`.
    input: DVector<f64>,
    /// Excitation channels `ne`.
    ne: usize,
    /// Work: the free predictions (row `c L + j`: quantity `c` at the 0-based sub-step `j`,
    /// the 1-based `j + 1` of [`Self::free_map`]), each sub-step's forces added to the later
    /// sub-steps' as they are solved.
    free: DVector<f64>,
    next: DVector<f64>,
}

impl ComposedSubsteps {
    fn new(sys: &TruthSystem, substeps: usize) -> Self {
        let model = &sys.model;
        let (n, q, ne) = (model.n(), model.Lc.ncols(), model.Lp.ncols());
        let (h, gamma, beta) = (sys.h, sys.gamma, sys.beta);
        let (T, Q) =
            newmark_substep_map(&sys.meff_inv, &model.C, &model.K, &model.Lp, h, gamma, beta);
        let mut Gf = DMatrix::zeros(3 * n, q);
        Gf.view_mut((0, 0), (n, q))
            .copy_from(&(&sys.Y * (-beta * h * h)));
        Gf.view_mut((n, 0), (n, q))
            .copy_from(&(&sys.Y * (-gamma * h)));
        Gf.view_mut((2 * n, 0), (n, q)).copy_from(&(-&sys.Y));
        // Lc₃ᵀ: δ, δ̇, δ̈ of each connection from x.
        let mut lc3t = DMatrix::zeros(3 * q, 3 * n);
        for b in 0..3 {
            lc3t.view_mut((b * q, b * n), (q, n))
                .copy_from(&model.Lc.transpose());
        }
        let L = substeps;
        let mut free_state = DMatrix::zeros(3 * q * L, 3 * n);
        let mut free_p0 = DMatrix::zeros(3 * q * L, ne);
        let mut free_p1 = DMatrix::zeros(3 * q * L, ne);
        let mut impulse_by_lag = vec![vec![0.0; L.saturating_sub(1)]; 3 * q * q];
        let mut s = lc3t.clone();
        let mut g0 = DMatrix::<f64>::zeros(3 * n, ne);
        let mut g1 = DMatrix::<f64>::zeros(3 * n, ne);
        for j in 1..=L {
            let t = j as f64 / L as f64;
            s = product(&s, &T);
            g0 = product(&T, &g0) + &Q * (1.0 - t);
            g1 = product(&T, &g1) + &Q * t;
            // Row `c L + j − 1`: each of δ₀, δ̇₀, δ̈₀ of each connection contiguous over the
            // sub-steps (the force history is added to it as one `axpy` per force).
            let (p0, p1) = (product(&lc3t, &g0), product(&lc3t, &g1));
            for c in 0..3 * q {
                let row = c * L + j - 1;
                free_state.row_mut(row).copy_from(&s.row(c));
                free_p0.row_mut(row).copy_from(&p0.row(c));
                free_p1.row_mut(row).copy_from(&p1.row(c));
            }
            if j < L {
                let imp = product(&s, &Gf);
                for c in 0..3 * q {
                    for m in 0..q {
                        impulse_by_lag[c * q + m][j - 1] = imp[(c, m)];
                    }
                }
            }
        }
        let mut force_to_end = DMatrix::zeros(3 * n, q * L);
        let mut col = Gf;
        for j in (1..=L).rev() {
            force_to_end
                .view_mut((0, q * (j - 1)), (3 * n, q))
                .copy_from(&col);
            if j > 1 {
                col = product(&T, &col);
            }
        }
        let phi = matrix_power(T, L);
        use crate::dense::side_by_side;
        Self {
            substeps: L,
            q,
            free_map: side_by_side(&[&free_state, &free_p0, &free_p1]),
            impulse_by_lag,
            end_map: side_by_side(&[&phi, &g0, &g1, &force_to_end]),
            input: DVector::zeros(3 * n + 2 * ne + q * L),
            ne,
            free: DVector::zeros(3 * q * L),
            next: DVector::zeros(3 * n),
        }
    }
}

/// Run a synthetic test.
pub fn simulate(setup: &Setup, opts: &SimulateOptions) -> Result<Simulated, SimulateError> {
    if opts.steps < 2 {
        return Err(SimulateError::Options("--steps must be at least 2".into()));
    }
    if !(opts.dt_s.is_finite() && opts.dt_s > 0.0) {
        return Err(SimulateError::Options(format!(
            "--dt must be finite and > 0 s, got {}",
            opts.dt_s
        )));
    }
    if opts.substeps == 0 {
        return Err(SimulateError::Options(
            "--substeps must be at least 1".into(),
        ));
    }
    // A pulse that is not positive would give an impact of no force at all (silently).
    if let Scenario::Free { pulse_s, .. } = opts.scenario
        && !(pulse_s.is_finite() && pulse_s > 0.0)
    {
        return Err(SimulateError::Options(format!(
            "--pulse must be > 0 s, got {pulse_s}"
        )));
    }
    // A force or frequency that is not finite (or a negative RMS) would otherwise show as
    // "the simulation diverged at sample 1", which names no option. A negative amplitude
    // of a sine or an impact is a force the other way, and allowed.
    match opts.scenario {
        Scenario::Sine { amplitude, .. } | Scenario::Free { amplitude, .. }
            if !amplitude.is_finite() =>
        {
            return Err(SimulateError::Options(format!(
                "--amplitude must be a finite force in N, got {amplitude}"
            )));
        }
        Scenario::Random { rms } | Scenario::RandomStiffnessDrop { rms, .. }
            if !(rms.is_finite() && rms >= 0.0) =>
        {
            return Err(SimulateError::Options(format!(
                "--amplitude is the random force's RMS: must be finite and ≥ 0 N, got {rms}"
            )));
        }
        Scenario::Sine { freq_hz, .. } if !(freq_hz.is_finite() && freq_hz > 0.0) => {
            return Err(SimulateError::Options(format!(
                "--freq must be finite and > 0 Hz, got {freq_hz}"
            )));
        }
        _ => {}
    }
    let model = Model::assemble(setup)?;
    let h = opts.dt_s / opts.substeps as f64;
    let mut sys = TruthSystem::new(setup, &model, h)?;
    let truth: Vec<f64> = sys.blocks.iter().flat_map(|b| b.1.clone()).collect();
    let ne = setup.excitation.len();
    let n = model.n();
    let mut rng = ChaCha8Rng::seed_from_u64(opts.seed);
    let rms_in = match opts.scenario {
        Scenario::Random { rms } | Scenario::RandomStiffnessDrop { rms, .. } => rms,
        _ => 0.0,
    };
    // One white sequence per excitation channel (identical shape scaled per channel is not
    // wanted: channels are independent).
    let white: Vec<Vec<f64>> = (0..ne)
        .map(|_| {
            let mut w: Vec<f64> = (0..opts.steps + 1)
                .map(|_| rms_in * rng.sample::<f64, _>(StandardNormal))
                .collect();
            w[0] = 0.0;
            w
        })
        .collect();
    let p_at = |t: f64| -> DVector<f64> {
        DVector::from_iterator(
            ne,
            (0..ne).map(|j| excitation_at(&opts.scenario, t, &white[j], opts.dt_s)),
        )
    };
    let mut s = State::zeros(n);
    let p0 = p_at(0.0);
    // At rest: f(0) holds only constant terms; with p(0) = 0 every scenario starts in
    // equilibrium (a stuck joint carries no force).
    let q = model.Lc.ncols();
    let f0 = sys.rest_force();
    s.a = rest_acceleration(&model, &p0, &f0)?;
    let lct = model.Lc.transpose();
    let record = |s: &State| station_outputs(&model, s);
    let mut excitation = vec![p0.iter().copied().collect::<Vec<_>>()];
    let mut clean = vec![record(&s)];
    let mut force = vec![f0.iter().copied().collect::<Vec<_>>()];
    let mut delta = vec![(&lct * &s.u).iter().copied().collect::<Vec<_>>()];
    let mut stuck = 0usize;
    let mut dropped = false;
    for i in 1..opts.steps {
        if let Scenario::RandomStiffnessDrop { at_s, factor, .. } = opts.scenario
            && !dropped
            && i as f64 * opts.dt_s >= at_s
        {
            sys.scale_stiffness(factor);
            dropped = true;
        }
        let mut f = DVector::zeros(q);
        for k in 1..=opts.substeps {
            let t = (i - 1) as f64 * opts.dt_s + k as f64 * h;
            f = sys
                .substep(&mut s, &p_at(t))
                .ok_or(SimulateError::Diverged(i))?;
        }
        if !s.is_finite() {
            return Err(SimulateError::Diverged(i));
        }
        if sys.any_stuck() {
            stuck += 1;
        }
        excitation.push(p_at(i as f64 * opts.dt_s).iter().copied().collect());
        clean.push(record(&s));
        force.push(f.iter().copied().collect());
        delta.push((&lct * &s.u).iter().copied().collect());
    }
    // Noise.
    let m = model.stations.len();
    let rms: Vec<f64> = (0..m)
        .map(|k| (clean.iter().map(|y| y[k] * y[k]).sum::<f64>() / clean.len() as f64).sqrt())
        .collect();
    let noise_std: Vec<f64> = match opts.noise {
        Noise::Additive(l) => rms.iter().map(|r| l * r).collect(),
        _ => vec![0.0; m],
    };
    let response = clean
        .iter()
        .map(|y| {
            y.iter()
                .enumerate()
                .map(|(k, &v)| match opts.noise {
                    Noise::None => v,
                    Noise::Additive(_) => v + noise_std[k] * rng.sample::<f64, _>(StandardNormal),
                    Noise::Cov(l) => v * (1.0 + l * rng.sample::<f64, _>(StandardNormal)),
                })
                .collect()
        })
        .collect();
    Ok(Simulated {
        excitation,
        response,
        clean_response: clean,
        force,
        delta,
        truth,
        stuck_fraction: stuck as f64 / (opts.steps - 1) as f64,
        noise_std,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The shipped friction setup's text (the paper's `sign(u)` joint).
    fn shipped_friction_toml() -> String {
        std::fs::read_to_string(concat!(
            env!("CARGO_MANIFEST_DIR"),
            "/recordings/two-beam-friction.toml"
        ))
        .unwrap()
    }

    /// The shipped friction setup with a second connection `name` at node 9 (`basis` and
    /// `truth` as TOML arrays), its model, and the truth of both connections.
    fn friction_setup_and_second_connection(
        name: &str,
        basis: &str,
        truth: &str,
    ) -> (Setup, Model, Vec<f64>) {
        let mut toml = shipped_friction_toml();
        toml.push_str(&format!(
            "\n[[connections]]\nname = \"{name}\"\ndof = {{ node = 9, dir = \"w\" }}\n\
             basis = {basis}\ntruth = {truth}\n"
        ));
        let setup = Setup::from_toml(&toml, "two-beam-friction+second.toml").unwrap();
        let model = Model::assemble(&setup).unwrap();
        assert_eq!(model.Lc.ncols(), 2);
        let params = setup
            .connections
            .iter()
            .flat_map(|c| c.truth.clone().unwrap())
            .collect();
        (setup, model, params)
    }

    /// The largest difference of two states' displacements, velocities or accelerations,
    /// relative to the first's largest value of the same kind.
    fn relative_difference(a: &State, b: &State) -> f64 {
        [(&a.u, &b.u), (&a.v, &b.v), (&a.a, &b.a)]
            .iter()
            .map(|(x, y)| (*x - *y).amax() / x.amax().max(f64::MIN_POSITIVE))
            .fold(0.0, f64::max)
    }

    /// A random excitation of `samples` samples on `ne` channels: 0 at the first sample, then
    /// normal with std `rms` (seeded).
    fn random_excitation(ne: usize, samples: usize, rms: f64, seed: u64) -> Vec<Vec<f64>> {
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        (0..samples)
            .map(|i| {
                (0..ne)
                    .map(|_| {
                        if i == 0 {
                            0.0
                        } else {
                            rms * rng.sample::<f64, _>(StandardNormal)
                        }
                    })
                    .collect()
            })
            .collect()
    }

    /// The composed one-sample map of a linear law equals the sub-step-by-sub-step implicit
    /// simulation (spring, dashpot and constant force on the paper's two-beam model, random
    /// excitation, 16 sub-steps, 300 samples): to 1e-9 of the output RMS.
    #[test]
    fn linear_sample_map_equals_the_implicit_substeps() {
        let toml = std::fs::read_to_string(concat!(
            env!("CARGO_MANIFEST_DIR"),
            "/recordings/two-beam-spring.toml"
        ))
        .unwrap();
        let setup = Setup::from_toml(&toml, "two-beam-spring.toml").unwrap();
        let model = Model::assemble(&setup).unwrap();
        let ne = model.Lp.ncols();
        let exc = random_excitation(ne, 300, 2e4, 7);
        let nb: usize = setup.connections.iter().map(|c| c.basis.len()).sum();
        let params: Vec<f64> = setup
            .connections
            .iter()
            .flat_map(|c| c.basis.iter())
            .map(|b| match b {
                Basis::U => 3e5,
                Basis::V => 20.0,
                Basis::Const(_) => 5.0,
                _ => 0.0,
            })
            .collect();
        assert_eq!(params.len(), nb);
        let fast = response_to_excitation(&setup, &model, &params, &exc, setup.dt_s, 16).unwrap();
        let slow = response_substeps(&setup, &model, &params, &exc, setup.dt_s, 16).unwrap();
        let m = slow[0].len();
        for k in 0..m {
            let rms = (slow.iter().map(|y| y[k] * y[k]).sum::<f64>() / slow.len() as f64).sqrt();
            let err = fast
                .iter()
                .zip(&slow)
                .map(|(a, b)| (a[k] - b[k]).abs())
                .fold(0.0, f64::max);
            assert!(err <= 1e-9 * rms, "channel {k}: {err:e} vs rms {rms:e}");
        }
    }

    /// The free run through [`SampleStepper`] ([`response_to_excitation`]: slip maps and
    /// composed sub-steps) equals the sub-step-by-sub-step free run over a whole record, not
    /// only sample by sample: a Coulomb joint (`sign(v), u`, 3 kN, 3e5 N/m) on the shipped
    /// two-beam model, random excitation of 20 kN RMS, 8 and 64 sub-steps, 400 samples, in
    /// which the joint's velocity keeps its sign through some samples (the slip map's) and
    /// reverses in others (the composed sub-steps'; measured 193 and 188 of 399 by the map,
    /// asserted 40–359). Without an observer the two runs' round-off is never reset; the
    /// structure's damping keeps it at round-off (measured: 2–4e-12 of each channel's RMS at
    /// 8 sub-steps, 0.7–1.3e-11 at 64; asserted 1e-9).
    #[test]
    fn the_stepped_free_run_equals_the_substeps_over_a_whole_record() {
        let toml = shipped_friction_toml()
            .replace(
                r#"basis = ["sign(u)", "u", "const(100)", "v"]"#,
                r#"basis = ["sign(v)", "u"]"#,
            )
            .replace(
                "truth = [3000.0, 3.0e5, 0.0, 0.0]",
                "truth = [3000.0, 3.0e5]",
            )
            .replace("initial = [0.0, 0.0, 0.0, 0.0]", "initial = [0.0, 0.0]");
        let setup = Setup::from_toml(&toml, "coulomb.toml").unwrap();
        let model = Model::assemble(&setup).unwrap();
        let params = [3000.0, 3.0e5];
        let exc = random_excitation(model.Lp.ncols(), 400, 2.0e4, 11);
        for substeps in [8, 64] {
            let (by_map, _) = slip_map_against_substeps(&setup, &params, substeps, &exc);
            assert!(
                (40..360).contains(&by_map),
                "{substeps} sub-steps: {by_map} of 399 samples by the slip map"
            );
            let fast = response_to_excitation(&setup, &model, &params, &exc, setup.dt_s, substeps)
                .unwrap();
            let slow =
                response_substeps(&setup, &model, &params, &exc, setup.dt_s, substeps).unwrap();
            for k in 0..slow[0].len() {
                let rms =
                    (slow.iter().map(|y| y[k] * y[k]).sum::<f64>() / slow.len() as f64).sqrt();
                let err = fast
                    .iter()
                    .zip(&slow)
                    .map(|(a, b)| (a[k] - b[k]).abs())
                    .fold(0.0, f64::max);
                assert!(
                    err <= 1e-9 * rms,
                    "{substeps} sub-steps, channel {k}: {err:e} vs rms {rms:e}"
                );
            }
        }
    }

    /// The sub-steps composed per sample ([`ComposedSubsteps`]) equal the sub-step by
    /// sub-step implicit simulation for laws that are not linear: the paper's `sign(u)`
    /// friction joint (it sticks and slips on this record) plus a second connection with a
    /// cubic spring, random excitation, 2 and 8 sub-steps, 200 samples. Each sample starts
    /// both from the sub-step path's state and status (the `sign(u)` law is chaotic: over
    /// many samples a last-bit difference can move a stick by a sub-step); the end states
    /// agree to 1e-9 of their largest values and the statuses are the same.
    #[test]
    fn composed_substeps_equal_the_implicit_substeps_for_friction_and_cubic_laws() {
        let (setup, model, params) =
            friction_setup_and_second_connection("cubic9", "[\"u\", \"u3\"]", "[2.0e4, 5.0e10]");
        let ne = model.Lp.ncols();
        let exc = random_excitation(ne, 200, 1.5e3, 3);
        for substeps in [2, 8] {
            let h = setup.dt_s / substeps as f64;
            let mut slow = TruthSystem::with_params(&setup, &model, h, &params).unwrap();
            let mut fast = TruthSystem::with_params(&setup, &model, h, &params).unwrap();
            let mut map = ComposedSubsteps::new(&fast, substeps);
            let mut a = rest_state(&model, &slow, &exc[0]).unwrap();
            let mut pt = DVector::zeros(ne);
            let (mut stuck, mut worst) = (0, 0.0f64);
            for i in 1..exc.len() {
                let mut b = a.clone();
                fast.status.clone_from(&slow.status);
                slow.sample_substeps(&mut a, &exc[i - 1], &exc[i], substeps, &mut pt)
                    .unwrap();
                fast.sample_composed(&mut map, &mut b, &exc[i - 1], &exc[i])
                    .unwrap();
                assert_eq!(slow.status, fast.status, "{substeps} sub-steps, sample {i}");
                stuck += usize::from(slow.status[0] == Status::Stick);
                worst = worst.max(relative_difference(&a, &b));
            }
            assert!(
                worst <= 1e-9,
                "{substeps} sub-steps: relative difference {worst:e}"
            );
            assert!(
                (5..195).contains(&stuck),
                "{substeps} sub-steps: the joint should stick and slip ({stuck} of 199 stuck)"
            );
        }
    }

    /// The slip map ([`SlipSampleMap`]) steps a sample only when the sub-step force solve
    /// would slip the friction one way through it, and then to the same end state: the
    /// paper's `sign(u)` joint (with `u`, `const`, `v` terms) and the same joint with a
    /// Coulomb `sign(v)` friction, random excitation that makes them stick and slip, 1, 8
    /// and 64 sub-steps, 300 samples. Each sample starts both paths from the sub-step
    /// path's state; where the map steps, the end states agree to 1e-9 of their largest
    /// value and the force solve ended slipping the same way. The map must step a good part
    /// of the samples (measured 83–180 of 299 on this vigorous excitation) and leave the
    /// others (reversals and sticks) to the force solve.
    #[test]
    fn slip_map_steps_exactly_the_samples_that_slip_one_way() {
        for (law, setup, _, params, exc) in sign_law_cases() {
            for substeps in [1, 8, 64] {
                let (stepped, worst) = slip_map_against_substeps(&setup, &params, substeps, &exc);
                assert!(
                    worst <= 1e-9,
                    "{law}, {substeps} sub-steps: relative difference {worst:e}"
                );
                assert!(
                    (60..290).contains(&stepped),
                    "{law}, {substeps} sub-steps: {stepped} of 299 samples by the slip map"
                );
            }
        }
    }

    /// The segment-wise test ([`SlipEnvelope`]) gives the row-by-row test's result: every
    /// sample steps to the same state, or is refused after the same sub-steps, with it and
    /// without it (the paper's joint with either `sign` term, and two frictions on two
    /// connections; 8, 10, 13, 16, 20 and 64 sub-steps, so segments of unequal lengths; 300
    /// samples from the sub-step path's states, and the same states scaled down 1e3-fold so
    /// that the frictions reverse inside more samples). It must be tested where it matters:
    /// its bound clears a good part of the segments where `δ` is smooth (`sign(u)`, 64
    /// sub-steps: measured 1,425 of 3,802 on this white force), and over the cases some
    /// segments whose two ends both clear have a reversal inside (measured 9), which only the
    /// bound keeps from passing: a bound of 0 would make those samples differ.
    #[test]
    fn slip_envelope_steps_the_same_samples_to_the_same_bits() {
        let two = {
            let (setup, model, params) = friction_setup_and_second_connection(
                "friction9",
                "[\"sign(v)\", \"u\"]",
                "[400.0, 2.0e4]",
            );
            let exc = random_excitation(model.Lp.ncols(), 300, 1.5e3, 5);
            ("sign(u) and sign(v)", setup, model, params, exc)
        };
        let mut dips = 0;
        for (law, setup, model, params, exc) in sign_law_cases().chain([two]) {
            for substeps in [8, 10, 13, 16, 20, 64] {
                let h = setup.dt_s / substeps as f64;
                let mut slow = TruthSystem::with_params(&setup, &model, h, &params).unwrap();
                let map = || {
                    SlipSampleMap::new(&setup, &model, &params, setup.dt_s, substeps)
                        .unwrap()
                        .unwrap()
                };
                let (mut with, mut without) = (map(), map());
                assert!(with.envelope.is_some(), "{law}, {substeps} sub-steps");
                without.envelope = None;
                let mut a = rest_state(&model, &slow, &exc[0]).unwrap();
                let mut pt = DVector::zeros(model.Lp.ncols());
                for i in 1..exc.len() {
                    for scale in [1.0, 1e-3] {
                        let mut start = a.clone();
                        for w in [&mut start.u, &mut start.v, &mut start.a] {
                            *w *= scale;
                        }
                        let (mut x, mut y) = (start.clone(), start);
                        let rx = with.try_sample(&mut x, &exc[i - 1], &exc[i]);
                        let ry = without.try_sample(&mut y, &exc[i - 1], &exc[i]);
                        assert_eq!(rx, ry, "{law}, {substeps} sub-steps, sample {i}");
                        let bits =
                            |w: &DVector<f64>| w.iter().map(|v| v.to_bits()).collect::<Vec<_>>();
                        for (p, q) in [(&x.u, &y.u), (&x.v, &y.v), (&x.a, &y.a)] {
                            assert_eq!(bits(p), bits(q), "{law}, {substeps} sub-steps, sample {i}");
                        }
                    }
                    slow.sample_substeps(&mut a, &exc[i - 1], &exc[i], substeps, &mut pt)
                        .unwrap();
                }
                let [by_rows, by_bound, inside] = with.envelope.as_ref().unwrap().segments;
                dips += inside;
                assert!(
                    law != "sign(u)" || substeps < 64 || by_bound * 3 >= by_rows,
                    "{law}, {substeps} sub-steps: {by_bound} segments cleared by the bound, {by_rows} by rows"
                );
            }
        }
        assert!(dips > 0, "no reversal inside a segment whose ends clear");
    }

    /// The samples the whole-sample slip test refuses (a friction reverses or sticks inside
    /// them) are stepped by windows of the slip map around force-solved sub-steps to the
    /// states of the sub-step force solve, to 1e-9, ending in its statuses (the paper's joint
    /// with either `sign` term, and two frictions on two connections; 8 and 64 sub-steps,
    /// 300 samples, most of them refused; the window maps holding every power of `T`, and
    /// stepping by `T^(2ᵏ)` as a large model does). The stuck windows are tried from the
    /// first stuck sub-step, and step some of them with every set of frictions stuck
    /// (measured: 33–4,131 sub-steps a case; states within 2.1e-10).
    #[test]
    fn slip_windows_step_the_refused_samples_as_the_force_solve_does() {
        // And two frictions, on two connections, stuck and slipping in every combination.
        let two = {
            let (setup, model, params) = friction_setup_and_second_connection(
                "friction9",
                "[\"sign(v)\", \"u\"]",
                "[400.0, 2.0e4]",
            );
            let exc = random_excitation(model.Lp.ncols(), 300, 1.5e3, 5);
            ("sign(u) and sign(v)", setup, model, params, exc)
        };
        for (law, setup, model, params, exc) in sign_law_cases().chain([two]) {
            // The window maps holding every power of `T`, and stepping by `T^(2ᵏ)`.
            for (substeps, map_bytes) in [
                (8, MAX_WINDOW_MAP_BYTES),
                (64, MAX_WINDOW_MAP_BYTES),
                (64, 0),
            ] {
                let h = setup.dt_s / substeps as f64;
                let mut slow = TruthSystem::with_params(&setup, &model, h, &params).unwrap();
                let mut fast = TruthSystem::with_params(&setup, &model, h, &params).unwrap();
                let mut map = SlipSampleMap::with_window_bytes(
                    &setup, &model, &params, setup.dt_s, substeps, map_bytes,
                )
                .unwrap()
                .unwrap();
                map.stuck_windows_after = 0;
                let windows = SlipWindows::new(map.window_parts.as_ref().unwrap(), substeps);
                assert_eq!(
                    windows.powers.is_empty(),
                    map_bytes > 0,
                    "{law}, {substeps} sub-steps"
                );
                let mut a = rest_state(&model, &slow, &exc[0]).unwrap();
                let mut pt = DVector::zeros(model.Lp.ncols());
                let (mut windowed, mut worst) = (0, 0.0f64);
                for i in 1..exc.len() {
                    let (pa, pb) = (&exc[i - 1], &exc[i]);
                    let mut b = a.clone();
                    fast.status.clone_from(&slow.status);
                    let refused = map.try_sample(&mut b, pa, pb);
                    slow.sample_substeps(&mut a, pa, pb, substeps, &mut pt)
                        .unwrap();
                    let Err(cleared) = refused else { continue };
                    windowed += 1;
                    map.sample_by_windows(&mut fast, &mut b, pa, pb, cleared, &mut pt)
                        .unwrap();
                    assert_eq!(
                        fast.status, slow.status,
                        "{law}, {substeps} sub-steps, sample {i}"
                    );
                    worst = worst.max(relative_difference(&a, &b));
                }
                assert!(
                    worst <= 1e-9,
                    "{law}, {substeps} sub-steps: relative difference {worst:e}"
                );
                assert!(
                    windowed >= 30,
                    "{law}, {substeps} sub-steps: only {windowed} of 299 samples refused"
                );
                // The stuck windows stepped some of them, every set of frictions stuck
                // among them (one friction: 1 set; two: 3).
                let sets = map
                    .stuck_windows
                    .iter()
                    .filter(|w| matches!(w, Some(Some(_))))
                    .count();
                assert!(
                    map.held_substeps >= 20 && sets == (1 << map.friction.len()) - 1,
                    "{law}, {substeps} sub-steps: {} sub-steps held stuck, {sets} sets",
                    map.held_substeps
                );
            }
        }
    }

    /// The shipped friction setup with the paper's joint law under either `sign` term
    /// (`sign(u)` at 3,000 N, `sign(v)` at 1,000 N), its model and parameters, and 300
    /// samples of a random excitation that makes the joint stick and slip.
    fn sign_law_cases()
    -> impl Iterator<Item = (&'static str, Setup, Model, Vec<f64>, Vec<Vec<f64>>)> {
        let toml = shipped_friction_toml();
        [("sign(u)", 3.0e3), ("sign(v)", 1.0e3)]
            .into_iter()
            .map(move |(law, level)| {
                let text = toml.replace("\"sign(u)\"", &format!("\"{law}\""));
                let setup = Setup::from_toml(&text, "two-beam-friction.toml").unwrap();
                let model = Model::assemble(&setup).unwrap();
                let params = paper_joint_params(&setup, level);
                let exc = random_excitation(model.Lp.ncols(), 300, 1.5e3, 5);
                (law, setup, model, params, exc)
            })
    }

    /// The paper's joint law with friction `level` (either `sign` term), a spring, a damper
    /// and a constant force, in the setup's parameter order.
    fn paper_joint_params(setup: &Setup, level: f64) -> Vec<f64> {
        setup
            .param_basis()
            .iter()
            .map(|b| match b {
                Basis::SignU | Basis::SignV => level,
                Basis::U => 3.0e5,
                Basis::V => 30.0,
                Basis::Const(_) => 2.0,
                _ => 0.0,
            })
            .collect()
    }

    /// Every sample of `exc` from the sub-step path's state, by the slip map where it steps
    /// and by the sub-step force solve: where the map steps, the force solve must have ended
    /// with every active friction slipping the map's way. Returns how many samples the map
    /// stepped and the largest relative difference of their end states.
    fn slip_map_against_substeps(
        setup: &Setup,
        params: &[f64],
        substeps: usize,
        exc: &[Vec<f64>],
    ) -> (usize, f64) {
        let model = Model::assemble(setup).unwrap();
        let h = setup.dt_s / substeps as f64;
        let mut slow = TruthSystem::with_params(setup, &model, h, params).unwrap();
        let mut map = SlipSampleMap::new(setup, &model, params, setup.dt_s, substeps)
            .unwrap()
            .unwrap();
        let mut a = rest_state(&model, &slow, &exc[0]).unwrap();
        let mut pt = DVector::zeros(model.Lp.ncols());
        let (mut stepped, mut worst) = (0, 0.0f64);
        for i in 1..exc.len() {
            let mut b = a.clone();
            let took = map.try_sample(&mut b, &exc[i - 1], &exc[i]).is_ok();
            slow.sample_substeps(&mut a, &exc[i - 1], &exc[i], substeps, &mut pt)
                .unwrap();
            if !took {
                continue;
            }
            stepped += 1;
            for (c, sign) in map.slips() {
                assert_eq!(
                    slow.status[c],
                    Status::Slip(sign),
                    "{substeps} sub-steps, sample {i}, connection {c}"
                );
            }
            worst = worst.max(relative_difference(&a, &b));
        }
        (stepped, worst)
    }

    /// A law whose every friction level is 0 (a level on its bound, the prediction error's
    /// record of the noise alone) runs through the slip map too, as the folded linear map:
    /// every sample stepped by it, the end states those of the sub-step force solve to 1e-9
    /// (the paper's joint with `u`, `const`, `v` terms, 1, 8 and 64 sub-steps, 300 samples).
    #[test]
    fn slip_map_without_an_active_friction_is_the_linear_map() {
        let toml = shipped_friction_toml();
        let setup = Setup::from_toml(&toml, "two-beam-friction.toml").unwrap();
        let model = Model::assemble(&setup).unwrap();
        let params = paper_joint_params(&setup, 0.0);
        let exc = random_excitation(model.Lp.ncols(), 300, 1.5e3, 5);
        for substeps in [1, 8, 64] {
            let (stepped, worst) = slip_map_against_substeps(&setup, &params, substeps, &exc);
            assert_eq!(stepped, 299, "{substeps} sub-steps");
            assert!(
                worst <= 1e-9,
                "{substeps} sub-steps: relative difference {worst:e}"
            );
        }
    }

    /// The slip map with two connections: the paper's friction joint and a second, linear
    /// one with a constant force and a friction term at level 0 (its constant enters the
    /// map's constant forces, its friction is not tested), 8 sub-steps, 300 samples: as
    /// above, and the second connection stays free of friction.
    #[test]
    fn slip_map_with_a_second_linear_connection() {
        let (setup, model, params) = friction_setup_and_second_connection(
            "spring9",
            "[\"sign(v)\", \"u\", \"const(10)\"]",
            "[0.0, 2.0e4, 1.0]",
        );
        let map = SlipSampleMap::new(&setup, &model, &params, setup.dt_s, 8)
            .unwrap()
            .unwrap();
        assert_eq!(
            map.friction.len(),
            1,
            "only the first connection's friction is active"
        );
        let exc = random_excitation(model.Lp.ncols(), 300, 1.5e3, 9);
        let (stepped, worst) = slip_map_against_substeps(&setup, &params, 8, &exc);
        assert!(worst <= 1e-9, "relative difference {worst:e}");
        assert!(
            (60..290).contains(&stepped),
            "{stepped} of 299 samples by the slip map"
        );
    }

    /// The slip map is not used where its uniqueness argument fails: a spring term negative
    /// enough to make the connection's compliance through the folded structure negative (a
    /// descent's trial point can be anywhere) leaves every sample to the force solve.
    #[test]
    fn slip_map_declines_an_indefinite_folded_compliance() {
        let toml = shipped_friction_toml();
        let setup = Setup::from_toml(&toml, "two-beam-friction.toml").unwrap();
        let model = Model::assemble(&setup).unwrap();
        let with_spring = |k: f64| -> Vec<f64> {
            setup
                .param_basis()
                .iter()
                .map(|b| match b {
                    Basis::SignU => 3.0e3,
                    Basis::U => k,
                    _ => 0.0,
                })
                .collect()
        };
        for substeps in [1, 8] {
            let map = |k: f64| {
                SlipSampleMap::new(&setup, &model, &with_spring(k), setup.dt_s, substeps).unwrap()
            };
            assert!(map(3.0e5).is_some(), "{substeps} sub-steps");
            assert!(map(-1.0e13).is_none(), "{substeps} sub-steps");
        }
    }

    const FRICTION_SDOF: &str = r#"
[model]
nodes = [{ id = 1, x = 0.0 }]
masses = [{ node = 1, mass = 1.0 }]
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
basis = ["u", "sign(v)"]
truth = [100.0, 5.0]
[integrator]
dt_s = 0.001
"#;

    #[test]
    fn coulomb_joint_sticks_below_the_friction_level_and_slips_above() {
        let s = Setup::from_toml(FRICTION_SDOF, "t").unwrap();
        let opts = |a: f64| SimulateOptions {
            scenario: Scenario::Sine {
                freq_hz: 1.0,
                amplitude: a,
            },
            steps: 400,
            dt_s: 0.001,
            substeps: 1,
            noise: Noise::None,
            seed: 1,
        };
        // 4 N < 5 N friction: never moves.
        let sim = simulate(&s, &opts(4.0)).unwrap();
        // Round-off of the stick constraint only: far below anything measurable.
        assert!(sim.clean_response.iter().all(|y| y[0].abs() < 1e-12));
        assert_eq!(sim.stuck_fraction, 1.0);
        // 20 N: moves once the force passes 5 N (t = asin(0.25)/2π ≈ 40 ms).
        let sim = simulate(&s, &opts(20.0)).unwrap();
        let first_move = sim
            .clean_response
            .iter()
            .position(|y| y[0].abs() > 1e-9)
            .unwrap();
        assert!((39..=42).contains(&first_move), "{first_move}");
        // While slipping, f = k δ + F sign(δ̇) holds to round-off.
        assert!(sim.stuck_fraction > 0.0 && sim.stuck_fraction < 1.0);
    }

    #[test]
    fn an_impact_pulse_that_is_not_positive_is_refused_by_name() {
        let s = Setup::from_toml(FRICTION_SDOF, "t").unwrap();
        for pulse_s in [0.0, -1e-3, f64::NAN] {
            let opts = SimulateOptions {
                scenario: Scenario::Free {
                    amplitude: 20.0,
                    pulse_s,
                },
                steps: 10,
                dt_s: 0.001,
                substeps: 1,
                noise: Noise::None,
                seed: 1,
            };
            match simulate(&s, &opts) {
                Err(SimulateError::Options(m)) => assert!(m.contains("--pulse"), "{m}"),
                other => panic!("pulse {pulse_s}: {:?}", other.map(|_| ())),
            }
        }
    }

    /// A force or frequency that is not finite, or a negative RMS, is refused naming the
    /// option (it was "the simulation diverged at sample 1").
    #[test]
    fn a_force_or_frequency_that_makes_no_sense_is_refused_by_name() {
        let s = Setup::from_toml(FRICTION_SDOF, "t").unwrap();
        let sine = |amplitude, freq_hz| Scenario::Sine { freq_hz, amplitude };
        let opts = |scenario, dt_s| SimulateOptions {
            scenario,
            steps: 10,
            dt_s,
            substeps: 1,
            noise: Noise::None,
            seed: 1,
        };
        let cases = [
            (
                opts(sine(f64::NAN, 5.0), 1e-3),
                "--amplitude must be a finite force in N, got NaN",
            ),
            (
                opts(sine(20.0, f64::NAN), 1e-3),
                "--freq must be finite and > 0 Hz, got NaN",
            ),
            (
                opts(sine(20.0, -5.0), 1e-3),
                "--freq must be finite and > 0 Hz, got -5",
            ),
            (
                opts(sine(20.0, 5.0), f64::INFINITY),
                "--dt must be finite and > 0 s, got inf",
            ),
            (
                opts(
                    Scenario::Free {
                        amplitude: f64::INFINITY,
                        pulse_s: 1e-3,
                    },
                    1e-3,
                ),
                "--amplitude must be a finite force in N, got inf",
            ),
            (
                opts(Scenario::Random { rms: -1.0 }, 1e-3),
                "--amplitude is the random force's RMS: must be finite and ≥ 0 N, got -1",
            ),
        ];
        for (o, want) in cases {
            match simulate(&s, &o) {
                Err(SimulateError::Options(m)) => assert_eq!(m, want),
                other => panic!("{o:?}: {:?}", other.map(|_| ())),
            }
        }
        // A sine the other way round is a force, not an error.
        assert!(simulate(&s, &opts(sine(-20.0, 5.0), 1e-3)).is_ok());
    }

    #[test]
    fn noise_parsing() {
        assert_eq!(
            "additive:0.1".parse::<Noise>().unwrap(),
            Noise::Additive(0.1)
        );
        assert_eq!("cov:0.5".parse::<Noise>().unwrap(), Noise::Cov(0.5));
        assert_eq!("none".parse::<Noise>().unwrap(), Noise::None);
        assert!("gauss:1".parse::<Noise>().is_err());
    }
}
