//! Synthetic test models for the per-sample cost benchmarks (`examples/bench_model.rs`,
//! `benches/step.rs`): a chain of `n` lumped masses (0.01 kg each) joined by springs
//! (1e6 N/m), grounded by a spring (1e4 N/m) at both ends, Rayleigh damping α = 2 /s,
//! β = 1e-7 s. One DOF per node (`w`), so the model has exactly `n` DOFs; its frequencies
//! run from ~16 Hz to ~3.2 kHz (the top of the chain's spectrum), all below the 25.6 kHz
//! Nyquist frequency of 51.2 kHz sampling. Excitation at node 1; `channels` sensors spread
//! evenly along the chain (alternately displacement and velocity); `connections` grounded
//! connections spread evenly, basis `sign(v), u` (a friction + spring joint, whose linear
//! term keeps the damping classical). Sampled at 51.2 kHz, one Newmark step per sample.

use std::fmt::Write as _;

/// Setup TOML of the chain (see the module docs).
pub fn chain_setup_toml(n: usize, channels: usize, connections: usize) -> String {
    let n = n.max(2);
    let mut s = String::from("title = \"synthetic chain\"\n[model]\nnodes = [");
    for i in 1..=n {
        let _ = write!(s, "{{ id = {i}, x = {}.0 }},", i - 1);
    }
    s.push_str("]\nmasses = [");
    for i in 1..=n {
        let _ = write!(s, "{{ node = {i}, mass = 0.01 }},");
    }
    s.push_str("]\nsprings = [\n");
    let _ = writeln!(s, "{{ dof = {{ node = 1, dir = \"w\" }}, k = 1.0e4 }},");
    let _ = writeln!(s, "{{ dof = {{ node = {n}, dir = \"w\" }}, k = 1.0e4 }},");
    for i in 1..n {
        let _ = writeln!(
            s,
            "{{ between = [{{ node = {i}, dir = \"w\" }}, {{ node = {}, dir = \"w\" }}], k = 1.0e6 }},",
            i + 1
        );
    }
    s.push_str("]\nrayleigh = { alpha = 2.0, beta = 1.0e-7 }\n");
    s.push_str("[[excitation]]\nname = \"f\"\ndof = { node = 1, dir = \"w\" }\n");
    let spread = |k: usize, of: usize| 1 + (k * (n - 1)) / of.max(1);
    for k in 0..channels {
        let node = spread(k, channels);
        let q = if k % 2 == 0 {
            "displacement"
        } else {
            "velocity"
        };
        let _ = writeln!(
            s,
            "[[sensors]]\nname = \"s{k}\"\ndof = {{ node = {node}, dir = \"w\" }}\nquantity = \"{q}\"\nnoise_std = 1e-6"
        );
    }
    for k in 0..connections {
        let node = 1 + ((2 * k + 1) * (n - 1)) / (2 * connections.max(1));
        let _ = writeln!(
            s,
            "[[connections]]\nname = \"j{k}\"\ndof = {{ node = {node}, dir = \"w\" }}\nbasis = [\"sign(v)\", \"u\"]\ninitial = [0.0, 1.0e5]"
        );
    }
    s.push_str("[integrator]\ndt_s = 1.953125e-5\nsubsteps = 1\n[estimator]\nkind = \"paper\"\n");
    s
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::model::Model;
    use crate::setup::Setup;

    #[test]
    fn chain_has_n_dofs_and_its_spectrum_is_below_nyquist() {
        let s = Setup::from_toml(&chain_setup_toml(24, 6, 1), "chain").unwrap();
        let m = Model::assemble(&s).unwrap();
        assert_eq!(m.n(), 24);
        assert_eq!(m.stations.len(), 6);
        let f = m.natural_frequencies_hz();
        // Top of an infinite chain: (1/π)·sqrt(k/m) = 3.18 kHz.
        assert!(f[23] < 3.2e3 && f[0] > 1.0, "{} .. {}", f[0], f[23]);
    }

    #[test]
    fn sparse_only_assembly_equals_the_dense_one() {
        let s = Setup::from_toml(&chain_setup_toml(60, 6, 2), "chain").unwrap();
        let d = Model::assemble(&s).unwrap();
        let sp = Model::assemble_with(&s, 10).unwrap();
        assert!(d.has_dense() && !sp.has_dense() && sp.M.is_empty());
        let (a, b) = (d.sparse_parts(), sp.sparse_parts());
        for (x, y) in [(&a.M, &b.M), (&a.C, &b.C), (&a.K, &b.K)] {
            assert!((x.to_dense() - y.to_dense()).amax() <= 1e-15 * x.amax());
        }
        assert_eq!(d.Lp, sp.Lp);
        assert_eq!(d.Lc, sp.Lc);
        assert_eq!(d.dofs, sp.dofs);
        let dofs = |m: &Model| m.stations.iter().map(|c| c.dof).collect::<Vec<_>>();
        assert_eq!(dofs(&d), dofs(&sp));
        // Connection terms land in the same place in both forms.
        let p = [1.0, 3.0e5, 2.0, 4.0e5];
        let (dw, sw) = (
            d.with_connection_terms(&s, &p),
            sp.with_connection_terms(&s, &p),
        );
        let (a, b) = (dw.sparse_parts(), sw.sparse_parts());
        assert!((a.K.to_dense() - b.K.to_dense()).amax() <= 1e-15 * a.K.amax());
    }
}
