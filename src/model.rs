//! Finite-element model of the components: DOF numbering, assembly of `M`, `C`, `K`, and
//! static condensation of massless DOFs.
//!
//! Symbols (SI units): `M` mass (kg), `C` damping (N·s/m), `K` stiffness (N/m) on the
//! retained DOFs; `Lp` (n × excitation channels) places the measured excitation on DOFs;
//! `Lc` (n × connections) maps DOFs to connection deformations, `δ = Lcᵀu`, with `+1` at
//! DOF `a` and `−1` at DOF `b` (a grounded connection has only the `+1`). The equation of
//! motion is `M ü + C u̇ + K u = Lp·p − Lc·f` with `f` the connection forces, positive when
//! they resist (see DESIGN.md §2).
//!
//! Massless DOFs (the rotations of a lumped-mass beam) are removed by static condensation,
//! `K* = K_tt − K_tr K_rr⁻¹ K_rt`, which is exact for DOFs without inertia or load.
//! Rayleigh damping is applied to the condensed matrices.
#![allow(non_snake_case)]

use std::collections::BTreeMap;

pub mod reduce;
pub mod synthetic;

use nalgebra::{DMatrix, DVector};

use crate::setup::{Dir, DofRef, LinkSpec, MassKind, Quantity, Setup};
use crate::sparse::{CsrMatrix, EnvelopeCholesky};

#[derive(Debug, thiserror::Error)]
pub enum ModelError {
    #[error("{what} refers to {dof}, which is supported (fixed) or does not exist")]
    NoSuchDof { what: String, dof: DofRef },
    #[error(
        "{what} sits on {dof}, which carries no mass and is condensed out; add a mass or rotary inertia there (model.masses) or use consistent beam mass"
    )]
    MasslessDof { what: String, dof: DofRef },
    #[error(
        "the massless DOFs cannot be condensed: their stiffness block is singular (is a rotation without any beam or spring?)"
    )]
    SingularCondensation,
    #[error(
        "model reduction: the stiffness of the {interior} interior DOFs with the boundary DOFs held is singular (an interior part is free to move); keep a DOF of it as a station or drop `reduce_modes`"
    )]
    ReductionSingular { interior: usize },
    #[error("the model has no DOF with mass")]
    NoMass,
    #[error(
        "{path}: the stiffness matrix is not positive semi-definite (Cholesky of K + τI failed, τ = {tau:e})"
    )]
    NotSemiDefinite { path: std::path::PathBuf, tau: f64 },
    #[error(
        "the mass matrix is not positive definite on the DOFs that carry mass (Cholesky failed)"
    )]
    MassNotDefinite,
    #[error(
        "`reduce_modes`: the model has {dofs} DOFs and is assembled in sparse form only; the Craig–Bampton reduction is dense (fixed-interface eigenproblem) and is not available at this size"
    )]
    ReductionNeedsDense { dofs: usize },
    #[error(
        "{what} needs the dense M, C, K, but this {dofs}-DOF model is assembled in sparse form only (above {max} DOFs); only the paper estimator with the sparse step runs on it",
        max = DENSE_MAX_DOFS
    )]
    SparseOnly { dofs: usize, what: &'static str },
}

/// A sensor channel mapped onto a retained DOF.
#[derive(Debug, Clone, Copy)]
pub struct StationChannel {
    pub dof: usize,
    pub quantity: Quantity,
}

/// The assembled linear model of the components (without the connections).
#[derive(Debug, Clone)]
pub struct Model {
    /// Labels of the retained DOFs, in matrix order.
    pub dofs: Vec<DofRef>,
    pub M: DMatrix<f64>,
    pub C: DMatrix<f64>,
    pub K: DMatrix<f64>,
    /// n × excitation channels.
    pub Lp: DMatrix<f64>,
    /// n × connections.
    pub Lc: DMatrix<f64>,
    /// One per sensor channel, in setup order.
    pub stations: Vec<StationChannel>,
    /// Rayleigh coefficients, re-applied when connection terms change K or M.
    pub rayleigh: (f64, f64),
    /// Implementation of the per-sample step the estimators use (`[integrator] step`).
    pub step: crate::setup::StepKind,
    /// The sparse form, held only by models assembled *without* dense matrices (more than
    /// [`DENSE_MAX_DOFS`] DOFs and nothing to condense); then `M`, `C`, `K` are 0 × 0 and
    /// only the sparse step can run. Models with the dense form build the sparse one from
    /// it on demand ([`Model::sparse_parts`]), so the two never disagree.
    pub sparse: Option<SparseParts>,
}

/// Sparse `M`, `C`, `K` of a model (same units and DOF order as the dense ones).
#[derive(Debug, Clone)]
pub struct SparseParts {
    pub M: CsrMatrix,
    pub C: CsrMatrix,
    pub K: CsrMatrix,
}

/// Above this many retained DOFs a model without massless DOFs is assembled in sparse form
/// only: three dense 5,000² matrices are already 0.6 GB, and at 24,000 DOFs they would be
/// 13.8 GB. Models that need static condensation stay dense (the condensed stiffness is
/// dense over each beam anyway).
pub const DENSE_MAX_DOFS: usize = 5_000;

/// `(row, col, value)` entries of a matrix under assembly, duplicates to be summed in order.
type Entries = Vec<(usize, usize, f64)>;

/// An element's DOFs (w1, θ1, w2, θ2; `None` when fixed), length, EI, mass/length, mass kind.
type ElementDofs = ([Option<usize>; 4], f64, f64, f64, MassKind);

/// Where a full DOF goes in assembly.
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord)]
enum FullDof {
    W(u32),
    /// Rotation of `node`, per beam index at a hinge (`usize::MAX` when shared).
    Rz(u32, usize),
}

impl Model {
    /// Assemble the setup's model. Above [`DENSE_MAX_DOFS`] DOFs, when nothing needs
    /// condensing, only the sparse form is built ([`Model::sparse`]).
    pub fn assemble(setup: &Setup) -> Result<Model, ModelError> {
        Self::assemble_with(setup, DENSE_MAX_DOFS)
    }

    /// [`Model::assemble`] with the size above which the model is kept in sparse form only
    /// (tests compare the two forms on small models).
    pub fn assemble_with(setup: &Setup, dense_max_dofs: usize) -> Result<Model, ModelError> {
        if let Some(ext) = &setup.external {
            return Self::assemble_external(setup, ext, dense_max_dofs);
        }
        let m = &setup.model;
        // Node positions, including beam interior nodes.
        let mut x: BTreeMap<u32, f64> = m.nodes.iter().map(|n| (n.id, n.x)).collect();
        let mut beam_nodes: Vec<Vec<u32>> = Vec::new();
        for b in &m.beams {
            let (x0, x1) = (x[&b.from], x[&b.to]);
            let mut ids = vec![b.from];
            for (k, id) in b.interior_ids.iter().enumerate() {
                let t = (k + 1) as f64 / b.elements as f64;
                x.insert(*id, x0 + t * (x1 - x0));
                ids.push(*id);
            }
            ids.push(b.to);
            beam_nodes.push(ids);
        }
        let hinges: std::collections::BTreeSet<u32> = m.hinges.iter().copied().collect();
        let fixed: std::collections::BTreeSet<(u32, Dir)> = m
            .supports
            .iter()
            .flat_map(|s| s.fix.iter().map(move |d| (s.node, *d)))
            .collect();

        // Full DOF list: a translation per node, a rotation per node with beams (per beam at
        // a hinge).
        let mut full: Vec<FullDof> = Vec::new();
        for id in x.keys() {
            if !fixed.contains(&(*id, Dir::W)) {
                full.push(FullDof::W(*id));
            }
        }
        let rot_of = |node: u32, beam: usize, full: &mut Vec<FullDof>| -> Option<usize> {
            if fixed.contains(&(node, Dir::Rz)) {
                return None;
            }
            let key = if hinges.contains(&node) {
                FullDof::Rz(node, beam)
            } else {
                FullDof::Rz(node, usize::MAX)
            };
            Some(match full.iter().position(|d| *d == key) {
                Some(i) => i,
                None => {
                    full.push(key);
                    full.len() - 1
                }
            })
        };
        let mut elements: Vec<ElementDofs> = Vec::new();
        let w_index =
            |full: &Vec<FullDof>, node: u32| full.iter().position(|d| *d == FullDof::W(node));
        for (bi, (b, ids)) in m.beams.iter().zip(&beam_nodes).enumerate() {
            for e in 0..b.elements {
                let (n1, n2) = (ids[e], ids[e + 1]);
                let le = (x[&n2] - x[&n1]).abs();
                let r1 = rot_of(n1, bi, &mut full);
                let r2 = rot_of(n2, bi, &mut full);
                let dofs = [w_index(&full, n1), r1, w_index(&full, n2), r2];
                // Orient the element along +x so the rotation sign convention is global.
                let dofs = if x[&n2] >= x[&n1] {
                    dofs
                } else {
                    [dofs[2], dofs[3], dofs[0], dofs[1]]
                };
                elements.push((dofs, le, b.ei, b.mass_per_length, b.mass));
            }
        }
        let nf = full.len();
        let mut M: Entries = Vec::new();
        let mut K: Entries = Vec::new();
        let mut Cd: Entries = Vec::new();
        for (dofs, l, ei, rho, kind) in &elements {
            let ke = beam_stiffness(*l, *ei);
            let me = beam_mass(*l, *rho, *kind);
            for i in 0..4 {
                let Some(gi) = dofs[i] else { continue };
                for j in 0..4 {
                    let Some(gj) = dofs[j] else { continue };
                    K.push((gi, gj, ke[i][j]));
                    M.push((gi, gj, me[i][j]));
                }
            }
        }
        let index: BTreeMap<FullDof, usize> =
            full.iter().enumerate().map(|(i, f)| (*f, i)).collect();
        let find = |d: &DofRef| -> Option<usize> {
            match d.dir {
                Dir::W => index.get(&FullDof::W(d.node)).copied(),
                Dir::Rz => index.get(&FullDof::Rz(d.node, usize::MAX)).copied(),
                // Rejected for beam models in setup validation.
                Dir::Ux | Dir::Uy | Dir::Uz | Dir::Rx | Dir::Ry | Dir::Mode => None,
            }
        };
        for ms in &m.masses {
            if let Some(i) = find(&DofRef {
                node: ms.node,
                dir: Dir::W,
            }) {
                M.push((i, i, ms.mass));
            }
            if ms.inertia > 0.0
                && let Some(i) = find(&DofRef {
                    node: ms.node,
                    dir: Dir::Rz,
                })
            {
                M.push((i, i, ms.inertia));
            }
        }
        let add_link = |mat: &mut Entries, l: &LinkSpec, what: &str| -> Result<(), ModelError> {
            let (a, b) = match (&l.dof, &l.between) {
                (Some(d), _) => (*d, None),
                (None, Some([a, b])) => (*a, Some(*b)),
                (None, None) => unreachable!("validated in setup"),
            };
            let ia = find(&a);
            let ib = b.map(|b| find(&b));
            // A link to a fixed DOF acts as grounded on the other end.
            let mut v: Vec<(usize, f64)> = Vec::new();
            if let Some(i) = ia {
                v.push((i, 1.0));
            }
            if let Some(Some(i)) = ib {
                v.push((i, -1.0));
            }
            if ia.is_none() && matches!(ib, None | Some(None)) {
                return Err(ModelError::NoSuchDof {
                    what: what.to_string(),
                    dof: a,
                });
            }
            for &(i, si) in &v {
                for &(j, sj) in &v {
                    mat.push((i, j, si * sj * l.value));
                }
            }
            Ok(())
        };
        for (i, s) in m.springs.iter().enumerate() {
            add_link(&mut K, s, &format!("model.springs[{i}]"))?;
        }
        for (i, s) in m.dashpots.iter().enumerate() {
            add_link(&mut Cd, s, &format!("model.dashpots[{i}]"))?;
        }
        let labels: Vec<DofRef> = full.iter().map(label).collect();
        let (M, K, Cd) = (
            CsrMatrix::from_triplets(nf, &M),
            CsrMatrix::from_triplets(nf, &K),
            CsrMatrix::from_triplets(nf, &Cd),
        );
        if let Some(m) = finish_sparse(setup, &labels, &M, &K, &Cd, &find, dense_max_dofs)? {
            return Ok(m);
        }
        finish(
            setup,
            labels,
            M.to_dense(),
            K.to_dense(),
            Cd.to_dense(),
            find,
        )
    }

    /// The model of `[model.matrix_market]`: the files' matrices on the DOF map's labels,
    /// then the same condensation, Rayleigh damping and channel placement as a beam model.
    /// K must be positive semi-definite: checked by a Cholesky factorisation of
    /// `K + τ·I`, `τ = 1e-9·max diag(K)` (a negative eigenvalue larger than τ fails it).
    fn assemble_external(
        setup: &Setup,
        ext: &crate::matrix_market::ExternalModel,
        dense_max_dofs: usize,
    ) -> Result<Model, ModelError> {
        let nf = ext.dofs.len();
        let labels = ext.dofs.clone();
        let find = |d: &DofRef| labels.iter().position(|l| l == d);
        {
            let M = CsrMatrix::from_triplets(nf, &ext.mass.entries);
            let K = CsrMatrix::from_triplets(nf, &ext.stiffness.entries);
            let Cd = ext.damping.as_ref().map_or_else(
                || CsrMatrix::zeros(nf),
                |c| CsrMatrix::from_triplets(nf, &c.entries),
            );
            if is_big_without_condensation(&M, dense_max_dofs) {
                let tau = 1e-9 * (0..nf).map(|i| K.get(i, i).abs()).fold(0.0, f64::max);
                let shifted = K.lin_comb(1.0, &CsrMatrix::identity(nf), tau);
                if EnvelopeCholesky::factor(&shifted).is_none() {
                    return Err(ModelError::NotSemiDefinite {
                        path: ext.stiffness.path.clone(),
                        tau,
                    });
                }
                if let Some(m) = finish_sparse(setup, &labels, &M, &K, &Cd, &find, dense_max_dofs)?
                {
                    return Ok(m);
                }
            }
        }
        let M = ext.mass.to_dense();
        let K = ext.stiffness.to_dense();
        let Cd = ext
            .damping
            .as_ref()
            .map_or_else(|| DMatrix::zeros(M.nrows(), M.ncols()), |c| c.to_dense());
        let tau = 1e-9 * K.diagonal().amax();
        let shifted = &K + DMatrix::identity(K.nrows(), K.ncols()) * tau;
        if shifted.cholesky().is_none() {
            return Err(ModelError::NotSemiDefinite {
                path: ext.stiffness.path.clone(),
                tau,
            });
        }
        finish(setup, ext.dofs.clone(), M, K, Cd, find)
    }
}

/// Condensation of massless DOFs, Rayleigh damping, and placement of excitation,
/// connections and sensors, shared by beam and external models. `full` labels the rows of
/// `M`, `K`, `Cd`; `find` maps a setup DOF to its full row.
fn finish(
    setup: &Setup,
    full: Vec<DofRef>,
    M: DMatrix<f64>,
    K: DMatrix<f64>,
    Cd: DMatrix<f64>,
    find: impl Fn(&DofRef) -> Option<usize>,
) -> Result<Model, ModelError> {
    let m = &setup.model;
    let nf = full.len();
    {
        // Static condensation of DOFs without inertia.
        let massless: Vec<usize> = (0..nf)
            .filter(|&i| (0..nf).all(|j| M[(i, j)] == 0.0 && M[(j, i)] == 0.0))
            .collect();
        let retained: Vec<usize> = (0..nf).filter(|i| !massless.contains(i)).collect();
        if retained.is_empty() {
            return Err(ModelError::NoMass);
        }
        let pick = |a: &DMatrix<f64>, r: &[usize], c: &[usize]| {
            DMatrix::from_fn(r.len(), c.len(), |i, j| a[(r[i], c[j])])
        };
        let mut Kc = pick(&K, &retained, &retained);
        if !massless.is_empty() {
            for &i in &massless {
                if (0..nf).any(|j| Cd[(i, j)] != 0.0) {
                    return Err(ModelError::MasslessDof {
                        what: "a dashpot".into(),
                        dof: full[i],
                    });
                }
            }
            let Krr = pick(&K, &massless, &massless);
            let Krt = pick(&K, &massless, &retained);
            let chol = Krr.cholesky().ok_or(ModelError::SingularCondensation)?;
            let X = chol.solve(&Krt);
            Kc -= Krt.transpose() * X;
            // Symmetrise away round-off.
            Kc = (&Kc + Kc.transpose()) * 0.5;
        }
        let Mc = pick(&M, &retained, &retained);
        if Mc.clone().cholesky().is_none() {
            return Err(ModelError::MassNotDefinite);
        }
        let (alpha, beta) = m
            .rayleigh
            .as_ref()
            .map_or((0.0, 0.0), |r| (r.alpha, r.beta));
        let Cc = pick(&Cd, &retained, &retained) + &Mc * alpha + &Kc * beta;
        let dofs: Vec<DofRef> = retained.iter().map(|&i| full[i]).collect();

        let n = dofs.len();
        let locate = |what: String, d: &DofRef| -> Result<usize, ModelError> {
            let Some(fi) = find(d) else {
                return Err(ModelError::NoSuchDof { what, dof: *d });
            };
            retained
                .iter()
                .position(|&r| r == fi)
                .ok_or(ModelError::MasslessDof { what, dof: *d })
        };
        let (Lp, Lc, stations) = place(setup, n, locate)?;
        Ok(Model {
            dofs,
            M: Mc,
            C: Cc,
            K: Kc,
            Lp,
            Lc,
            stations,
            rayleigh: (alpha, beta),
            step: setup.step,
            sparse: None,
        })
    }
}

/// Excitation and connection placement (`Lp`, `Lc`, `δ = Lcᵀu` with `+1` at `a`, `−1` at
/// `b`) and the sensor stations, with `locate` mapping a named DOF to its retained row (the
/// dense and the sparse-only assembly differ only in that map).
#[allow(clippy::type_complexity)]
fn place(
    setup: &Setup,
    n: usize,
    locate: impl Fn(String, &DofRef) -> Result<usize, ModelError>,
) -> Result<(DMatrix<f64>, DMatrix<f64>, Vec<StationChannel>), ModelError> {
    let mut Lp = DMatrix::zeros(n, setup.excitation.len());
    for (j, e) in setup.excitation.iter().enumerate() {
        Lp[(locate(format!("excitation `{}`", e.name), &e.dof)?, j)] = 1.0;
    }
    let mut Lc = DMatrix::zeros(n, setup.connections.len());
    for (j, c) in setup.connections.iter().enumerate() {
        Lc[(locate(format!("connection `{}`", c.name), &c.a)?, j)] += 1.0;
        if let Some(b) = &c.b {
            Lc[(locate(format!("connection `{}`", c.name), b)?, j)] -= 1.0;
        }
    }
    let stations = setup
        .sensors
        .iter()
        .map(|s| {
            Ok(StationChannel {
                dof: locate(format!("sensor `{}`", s.name), &s.dof)?,
                quantity: s.quantity,
            })
        })
        .collect::<Result<_, ModelError>>()?;
    Ok((Lp, Lc, stations))
}

/// Whether a model is assembled in sparse form only: more than [`DENSE_MAX_DOFS`] DOFs and
/// every DOF carries mass (nothing to condense).
fn is_big_without_condensation(M: &CsrMatrix, dense_max_dofs: usize) -> bool {
    M.n > dense_max_dofs && (0..M.n).all(|i| !M.row_is_zero(i))
}

/// The sparse-only model (see [`Model::sparse`]), or `None` when the model is small or
/// needs condensation (then [`finish`] builds the dense one). Same checks, Rayleigh damping
/// and placement as [`finish`], without any n × n dense intermediate.
fn finish_sparse(
    setup: &Setup,
    full: &[DofRef],
    M: &CsrMatrix,
    K: &CsrMatrix,
    Cd: &CsrMatrix,
    find: &impl Fn(&DofRef) -> Option<usize>,
    dense_max_dofs: usize,
) -> Result<Option<Model>, ModelError> {
    if !is_big_without_condensation(M, dense_max_dofs) {
        return Ok(None);
    }
    let n = M.n;
    if EnvelopeCholesky::factor(M).is_none() {
        return Err(ModelError::MassNotDefinite);
    }
    let (alpha, beta) = setup
        .model
        .rayleigh
        .as_ref()
        .map_or((0.0, 0.0), |r| (r.alpha, r.beta));
    let C = Cd.lin_comb(1.0, M, alpha).lin_comb(1.0, K, beta);
    let locate = |what: String, d: &DofRef| -> Result<usize, ModelError> {
        find(d).ok_or(ModelError::NoSuchDof { what, dof: *d })
    };
    let (Lp, Lc, stations) = place(setup, n, locate)?;
    Ok(Some(Model {
        dofs: full.to_vec(),
        M: DMatrix::zeros(0, 0),
        C: DMatrix::zeros(0, 0),
        K: DMatrix::zeros(0, 0),
        Lp,
        Lc,
        stations,
        rayleigh: (alpha, beta),
        step: setup.step,
        sparse: Some(SparseParts {
            M: M.clone(),
            C,
            K: K.clone(),
        }),
    }))
}

impl Model {
    pub fn n(&self) -> usize {
        self.dofs.len()
    }

    /// Whether the dense `M`, `C`, `K` exist (see [`Model::sparse`]).
    pub fn has_dense(&self) -> bool {
        self.sparse.is_none()
    }

    /// The sparse `M`, `C`, `K`: the stored form, or built from the dense one (O(n²)).
    pub fn sparse_parts(&self) -> std::borrow::Cow<'_, SparseParts> {
        match &self.sparse {
            Some(p) => std::borrow::Cow::Borrowed(p),
            None => std::borrow::Cow::Owned(SparseParts {
                M: CsrMatrix::from_dense(&self.M),
                C: CsrMatrix::from_dense(&self.C),
                K: CsrMatrix::from_dense(&self.K),
            }),
        }
    }

    /// Undamped natural frequencies, Hz, ascending.
    pub fn natural_frequencies_hz(&self) -> Vec<f64> {
        let Some(ch) = self.M.clone().cholesky() else {
            return Vec::new();
        };
        let l = ch.l();
        let Some(linv) = l.clone().try_inverse() else {
            return Vec::new();
        };
        let a = &linv * &self.K * linv.transpose();
        let a = (&a + a.transpose()) * 0.5;
        let mut w: Vec<f64> = a
            .symmetric_eigenvalues()
            .iter()
            .map(|&l| l.max(0.0).sqrt() / (2.0 * std::f64::consts::PI))
            .collect();
        w.sort_by(f64::total_cmp);
        w
    }

    /// Model with the linear connection terms of `params` added: `u` into K, `v` into C, `a`
    /// into M (Step VI of the paper). Parameters are in `Setup::param_keys` order.
    pub fn with_connection_terms(&self, setup: &Setup, params: &[f64]) -> Model {
        let mut out = self.clone();
        if let Some(sp) = &mut out.sparse {
            // Sparse-only model: the same terms on the pattern of l lᵀ.
            let mut k = 0;
            for (c, conn) in setup.connections.iter().enumerate() {
                let l: Vec<(usize, f64)> = self
                    .Lc
                    .column(c)
                    .iter()
                    .enumerate()
                    .filter(|(_, v)| **v != 0.0)
                    .map(|(i, v)| (i, *v))
                    .collect();
                let llt: Entries = l
                    .iter()
                    .flat_map(|&(i, a)| l.iter().map(move |&(j, b)| (i, j, a * b)))
                    .collect();
                let llt = CsrMatrix::from_triplets(self.n(), &llt);
                for b in &conn.basis {
                    let p = params[k];
                    k += 1;
                    let target = match b {
                        crate::setup::Basis::U => &mut sp.K,
                        crate::setup::Basis::V => &mut sp.C,
                        crate::setup::Basis::A => &mut sp.M,
                        _ => continue,
                    };
                    *target = target.lin_comb(1.0, &llt, p);
                }
            }
            return out;
        }
        let mut k = 0;
        for (c, conn) in setup.connections.iter().enumerate() {
            let l: DVector<f64> = self.Lc.column(c).into_owned();
            let llt = &l * l.transpose();
            for b in &conn.basis {
                let p = params[k];
                k += 1;
                match b {
                    crate::setup::Basis::U => out.K += &llt * p,
                    crate::setup::Basis::V => out.C += &llt * p,
                    crate::setup::Basis::A => out.M += &llt * p,
                    _ => {}
                }
            }
        }
        out
    }
}

fn label(f: &FullDof) -> DofRef {
    match *f {
        FullDof::W(n) => DofRef {
            node: n,
            dir: Dir::W,
        },
        FullDof::Rz(n, _) => DofRef {
            node: n,
            dir: Dir::Rz,
        },
    }
}

/// Euler–Bernoulli element stiffness, DOFs (w1, θ1, w2, θ2).
fn beam_stiffness(l: f64, ei: f64) -> [[f64; 4]; 4] {
    let c = ei / (l * l * l);
    let (l2, l1) = (l * l, l);
    [
        [12.0 * c, 6.0 * l1 * c, -12.0 * c, 6.0 * l1 * c],
        [6.0 * l1 * c, 4.0 * l2 * c, -6.0 * l1 * c, 2.0 * l2 * c],
        [-12.0 * c, -6.0 * l1 * c, 12.0 * c, -6.0 * l1 * c],
        [6.0 * l1 * c, 2.0 * l2 * c, -6.0 * l1 * c, 4.0 * l2 * c],
    ]
}

fn beam_mass(l: f64, rho: f64, kind: MassKind) -> [[f64; 4]; 4] {
    let m = rho * l;
    match kind {
        MassKind::Lumped => [
            [m / 2.0, 0.0, 0.0, 0.0],
            [0.0; 4],
            [0.0, 0.0, m / 2.0, 0.0],
            [0.0; 4],
        ],
        MassKind::Consistent => {
            let c = m / 420.0;
            [
                [156.0 * c, 22.0 * l * c, 54.0 * c, -13.0 * l * c],
                [
                    22.0 * l * c,
                    4.0 * l * l * c,
                    13.0 * l * c,
                    -3.0 * l * l * c,
                ],
                [54.0 * c, 13.0 * l * c, 156.0 * c, -22.0 * l * c],
                [
                    -13.0 * l * c,
                    -3.0 * l * l * c,
                    -22.0 * l * c,
                    4.0 * l * l * c,
                ],
            ]
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn cantilever(elements: usize, mass: &str) -> String {
        let ids: Vec<String> = (2..=elements).map(|i| i.to_string()).collect();
        let tip = elements + 1;
        format!(
            r#"
[model]
nodes = [{{ id = 1, x = 0.0 }}, {{ id = {tip}, x = 2.0 }}]
beams = [{{ from = 1, to = {tip}, elements = {elements}, interior_ids = [{ids}], ei = 3.0e4, mass_per_length = 1.5, mass = "{mass}" }}]
supports = [{{ node = 1, fix = ["w", "rz"] }}]
[[excitation]]
name = "f"
dof = {{ node = {tip}, dir = "w" }}
[[sensors]]
name = "d"
dof = {{ node = {tip}, dir = "w" }}
quantity = "displacement"
[[connections]]
name = "j"
dof = {{ node = {tip}, dir = "w" }}
basis = ["u"]
[integrator]
dt_s = 0.001
"#,
            ids = ids.join(",")
        )
    }

    #[test]
    fn cantilever_static_tip_deflection_matches_pl3_over_3ei() {
        // Static condensation keeps the stiffness exact for a lumped-mass model.
        for mass in ["lumped", "consistent"] {
            let s = Setup::from_toml(&cantilever(4, mass), "t").unwrap();
            let m = Model::assemble(&s).unwrap();
            let p = 10.0;
            let f = &m.Lp * DVector::from_element(1, p);
            let u = m.K.clone().lu().solve(&f).unwrap();
            let tip = m.Lp.column(0).iter().position(|&v| v == 1.0).unwrap();
            let exact = p * 2.0f64.powi(3) / (3.0 * 3.0e4);
            assert!(
                (u[tip] - exact).abs() < 1e-12 * exact.abs().max(1.0),
                "{mass}"
            );
        }
    }

    #[test]
    fn cantilever_first_frequency_converges_to_euler_bernoulli() {
        // f1 = (1.8751²/2π)·sqrt(EI/(ρA L⁴)).
        let exact = 1.875_104_068_7f64.powi(2) / (2.0 * std::f64::consts::PI)
            * (3.0e4 / (1.5 * 2.0f64.powi(4))).sqrt();
        let s = Setup::from_toml(&cantilever(40, "consistent"), "t").unwrap();
        let f1 = Model::assemble(&s).unwrap().natural_frequencies_hz()[0];
        assert!(
            (f1 / exact - 1.0).abs() < 1e-5,
            "consistent {f1} vs {exact}"
        );
        let s = Setup::from_toml(&cantilever(40, "lumped"), "t").unwrap();
        let f1 = Model::assemble(&s).unwrap().natural_frequencies_hz()[0];
        assert!((f1 / exact - 1.0).abs() < 5e-3, "lumped {f1} vs {exact}");
    }

    #[test]
    fn assembled_matrices_are_symmetric() {
        let s = Setup::from_toml(&cantilever(5, "consistent"), "t").unwrap();
        let m = Model::assemble(&s).unwrap();
        assert!((&m.K - m.K.transpose()).amax() < 1e-9 * m.K.amax());
        assert!((&m.M - m.M.transpose()).amax() < 1e-15 * m.M.amax());
    }

    #[test]
    fn sensor_on_massless_rotation_is_an_error() {
        let t = cantilever(2, "lumped").replace(
            "quantity = \"displacement\"",
            "quantity = \"displacement\"\n[[sensors]]\nname = \"r\"\ndof = { node = 2, dir = \"rz\" }\nquantity = \"displacement\"",
        );
        let s = Setup::from_toml(&t, "t").unwrap();
        let e = Model::assemble(&s).unwrap_err().to_string();
        assert!(e.contains("sensor `r`") && e.contains("no mass"), "{e}");
    }
}
