//! Craig–Bampton reduction of a component model for the estimators (issue 4, the
//! 50-element model).
//!
//! Why: a fine model (50 elements per beam, 101 DOFs) makes the Kalman estimator's state
//! `3n + q` ≈ 300 long; the steady-state Riccati solve is then O(n³) per doubling step and
//! the likelihood tuning needs ~50 of them (measured 170 s for 2,000 samples). Most of those
//! DOFs are interior beam nodes whose modes lie far above the sampling rate: between two
//! stations 0.4 m apart the first fixed-interface mode is at ≈ 9.8 kHz with 10 kHz
//! sampling. Craig–Bampton keeps every DOF the data and the connections touch (boundary
//! `b`: excitation, stations, connections) as a physical DOF, represents the interior by
//! the static constraint modes (exact at zero frequency, so static flexibility is not lost)
//! plus the lowest `r` fixed-interface modes:
//!
//! ```text
//! u = T (u_b; η),   T = [ I      0  ]      Φ_c = −K_ii⁻¹ K_ib,   K_ii φ = ω² M_ii φ
//!                       [ Φ_c   Φ_m ]
//! M_r = TᵀMT,  C_r = TᵀCT,  K_r = TᵀKT,  Lp_r = TᵀLp,  Lc_r = TᵀLc
//! ```
//!
//! `Lp` and `Lc` are non-zero only on boundary rows, so `δ = Lc_rᵀ(u_b; η)` is the same
//! deformation as in the full model and connection terms added to `K_r`, `C_r`, `M_r` at
//! boundary DOFs are exact. The error is the truncated interior dynamics only; the ACCURACY.md
//! states it for the 50-element model.
#![allow(non_snake_case)]

use nalgebra::{DMatrix, DVector};

use super::{Model, ModelError};
use crate::setup::{Dir, DofRef};

/// The boundary DOFs of a model: every DOF that carries excitation, a connection or a
/// station, ascending.
pub fn boundary_dofs(model: &Model) -> Vec<usize> {
    let n = model.n();
    let mut keep: Vec<bool> = (0..n)
        .map(|i| {
            model.Lp.row(i).iter().any(|&x| x != 0.0) || model.Lc.row(i).iter().any(|&x| x != 0.0)
        })
        .collect();
    for s in &model.stations {
        keep[s.dof] = true;
    }
    (0..n).filter(|&i| keep[i]).collect()
}

impl Model {
    /// The model the estimators identify with: [`Model::assemble`], reduced by
    /// [`Model::craig_bampton`] when the setup asks for it (`[estimator] reduce_modes`).
    pub fn for_identification(setup: &crate::setup::Setup) -> Result<Model, ModelError> {
        let model = Model::assemble(setup)?;
        match setup.estimator.reduce_modes {
            Some(r) => model.craig_bampton(r),
            None => Ok(model),
        }
    }

    /// Craig–Bampton reduction to the boundary DOFs (see [`boundary_dofs`]) plus the lowest
    /// `modes` fixed-interface modes (fewer when the interior has fewer DOFs). Boundary DOFs
    /// keep their labels and come first; mode `k` is labelled `node = k, dir = mode`.
    pub fn craig_bampton(&self, modes: usize) -> Result<Model, ModelError> {
        if !self.has_dense() {
            return Err(ModelError::ReductionNeedsDense { dofs: self.n() });
        }
        let n = self.n();
        let b = boundary_dofs(self);
        let interior: Vec<usize> = (0..n).filter(|i| !b.contains(i)).collect();
        let ni = interior.len();
        let nb = b.len();
        let pick = |a: &DMatrix<f64>, r: &[usize], c: &[usize]| {
            DMatrix::from_fn(r.len(), c.len(), |i, j| a[(r[i], c[j])])
        };
        let r = modes.min(ni);
        let mut T = DMatrix::zeros(n, nb + r);
        for (k, &i) in b.iter().enumerate() {
            T[(i, k)] = 1.0;
        }
        if ni > 0 {
            let Kii = pick(&self.K, &interior, &interior);
            let Kib = pick(&self.K, &interior, &b);
            let Mii = pick(&self.M, &interior, &interior);
            let chol = Kii
                .clone()
                .cholesky()
                .ok_or(ModelError::ReductionSingular { interior: ni })?;
            let Phi_c = -chol.solve(&Kib);
            // Fixed-interface modes, mass-normalised: with M_ii = L Lᵀ,
            // (L⁻¹ K_ii L⁻ᵀ) v = ω² v and φ = L⁻ᵀ v.
            let lm = Mii.cholesky().ok_or(ModelError::MassNotDefinite)?;
            let L = lm.l();
            let Linv = L.clone().try_inverse().ok_or(ModelError::MassNotDefinite)?;
            let A = &Linv * &Kii * Linv.transpose();
            let A = (&A + A.transpose()) * 0.5;
            let eig = A.symmetric_eigen();
            let mut order: Vec<usize> = (0..ni).collect();
            order.sort_by(|&x, &y| eig.eigenvalues[x].total_cmp(&eig.eigenvalues[y]));
            let Lt_inv = Linv.transpose();
            for (k, &j) in order.iter().take(r).enumerate() {
                let v: DVector<f64> = eig.eigenvectors.column(j).into_owned();
                let phi = &Lt_inv * v;
                for (ii, &row) in interior.iter().enumerate() {
                    T[(row, nb + k)] = phi[ii];
                }
            }
            for (ii, &row) in interior.iter().enumerate() {
                for k in 0..nb {
                    T[(row, k)] = Phi_c[(ii, k)];
                }
            }
        }
        let sym = |a: DMatrix<f64>| (&a + a.transpose()) * 0.5;
        let Tt = T.transpose();
        let mut dofs: Vec<DofRef> = b.iter().map(|&i| self.dofs[i]).collect();
        dofs.extend((1..=r).map(|k| DofRef {
            node: k as u32,
            dir: Dir::Mode,
        }));
        let stations = self
            .stations
            .iter()
            .map(|s| super::StationChannel {
                dof: b.iter().position(|&i| i == s.dof).unwrap_or(0),
                quantity: s.quantity,
            })
            .collect();
        Ok(Model {
            dofs,
            M: sym(&Tt * &self.M * &T),
            C: sym(&Tt * &self.C * &T),
            K: sym(&Tt * &self.K * &T),
            Lp: &Tt * &self.Lp,
            Lc: &Tt * &self.Lc,
            stations,
            rayleigh: self.rayleigh,
            step: self.step,
            sparse: None,
        })
    }
}

#[cfg(test)]
mod tests {
    use crate::setup::Setup;

    use super::*;

    const CHAIN: &str = r#"
[model]
nodes = [{ id = 1, x = 0.0 }, { id = 11, x = 1.0 }]
beams = [{ name = "A", from = 1, to = 11, elements = 10, interior_ids = [2, 3, 4, 5, 6, 7, 8, 9, 10], ei = 1.0e5, mass_per_length = 0.10 }]
springs = [{ dof = { node = 1, dir = "w" }, k = 15.0e3 }, { dof = { node = 11, dir = "w" }, k = 15.0e3 }]
[[excitation]]
name = "f"
dof = { node = 1, dir = "w" }
[[sensors]]
name = "d"
dof = { node = 4, dir = "w" }
quantity = "displacement"
[[connections]]
name = "j"
dof = { node = 11, dir = "w" }
basis = ["u"]
[integrator]
dt_s = 1.0e-4
"#;

    /// Static flexibility at the boundary is exact (constraint modes), all interior modes
    /// reproduce every natural frequency, and few modes keep the lowest ones.
    #[test]
    fn craig_bampton_is_exact_statically_and_with_all_modes() {
        let s = Setup::from_toml(CHAIN, "t").unwrap();
        let full = Model::assemble(&s).unwrap();
        let b = boundary_dofs(&full);
        assert_eq!(b.len(), 3);
        let none = full.craig_bampton(0).unwrap();
        assert_eq!(none.n(), 3);
        // Static deflection at the boundary under the excitation.
        let uf = full.K.clone().lu().solve(&full.Lp).unwrap();
        let ur = none.K.clone().lu().solve(&none.Lp).unwrap();
        for (k, &i) in b.iter().enumerate() {
            assert!((uf[i] - ur[k]).abs() <= 1e-10 * uf.amax(), "{i}");
        }
        let all = full.craig_bampton(100).unwrap();
        assert_eq!(all.n(), full.n());
        let (ff, fa) = (full.natural_frequencies_hz(), all.natural_frequencies_hz());
        for (a, c) in ff.iter().zip(&fa) {
            assert!((a - c).abs() <= 1e-8 * a.max(1.0), "{a} vs {c}");
        }
        let some = full.craig_bampton(3).unwrap();
        let fs = some.natural_frequencies_hz();
        assert!(
            (fs[0] - ff[0]).abs() <= 1e-3 * ff[0],
            "{} vs {}",
            fs[0],
            ff[0]
        );
        assert_eq!(
            some.stations[0].dof,
            b.iter().position(|&i| i == full.stations[0].dof).unwrap()
        );
        assert_eq!(some.Lc.column(0).iter().filter(|&&x| x != 0.0).count(), 1);
    }
}
