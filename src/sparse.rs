//! Sparse matrices for big models: compressed-row storage (CSR) and an envelope (profile)
//! Cholesky factorisation `P A Pᵀ = L Lᵀ` with a reverse Cuthill–McKee ordering.
//!
//! Why our own ~300 lines and not a crate: the step needs only symmetric CSR mat-vecs and one
//! Cholesky of `M + γhC + βh²K` with two triangular solves per sub-step into preallocated
//! vectors. Structural FE matrices (chains, beams, shells from a mesh) are banded after a
//! bandwidth-reducing ordering, so an envelope factor — each row of `L` stored contiguously
//! from its first non-zero — has little fill and its solves stream memory in order.
//! `nalgebra-sparse`'s `CscCholesky` has no fill-reducing ordering and would have been a new
//! dependency for the same two loops. The ordering: natural when its envelope is no larger
//! than that of reverse Cuthill–McKee (RCM), else RCM (George & Liu 1981); both envelope
//! sizes are kept for the report.
#![allow(non_snake_case)]

use nalgebra::DMatrix;

/// A square sparse matrix in compressed-row form (column indices ascending in each row,
/// duplicates summed). Symmetric matrices keep both triangles.
#[derive(Debug, Clone, PartialEq)]
pub struct CsrMatrix {
    pub n: usize,
    pub row_ptr: Vec<usize>,
    pub col: Vec<usize>,
    pub val: Vec<f64>,
}

impl CsrMatrix {
    pub fn zeros(n: usize) -> Self {
        Self {
            n,
            row_ptr: vec![0; n + 1],
            col: Vec::new(),
            val: Vec::new(),
        }
    }

    pub fn identity(n: usize) -> Self {
        Self {
            n,
            row_ptr: (0..=n).collect(),
            col: (0..n).collect(),
            val: vec![1.0; n],
        }
    }

    /// From `(row, col, value)` entries, duplicates summed in the given order. Entries that
    /// sum to exactly zero are kept (the pattern is structural).
    pub fn from_triplets(n: usize, entries: &[(usize, usize, f64)]) -> Self {
        let mut count = vec![0usize; n + 1];
        for &(i, _, _) in entries {
            count[i + 1] += 1;
        }
        for i in 0..n {
            count[i + 1] += count[i];
        }
        let mut next = count.clone();
        let mut tmp: Vec<(usize, f64)> = vec![(0, 0.0); entries.len()];
        for &(i, j, v) in entries {
            tmp[next[i]] = (j, v);
            next[i] += 1;
        }
        let mut row_ptr = Vec::with_capacity(n + 1);
        let mut col = Vec::with_capacity(entries.len());
        let mut val = Vec::with_capacity(entries.len());
        row_ptr.push(0);
        for i in 0..n {
            let row = &mut tmp[count[i]..count[i + 1]];
            // Stable: duplicates are summed in input order.
            row.sort_by_key(|e| e.0);
            let mut k = 0;
            while k < row.len() {
                let (j, mut v) = row[k];
                k += 1;
                while k < row.len() && row[k].0 == j {
                    v += row[k].1;
                    k += 1;
                }
                col.push(j);
                val.push(v);
            }
            row_ptr.push(col.len());
        }
        Self {
            n,
            row_ptr,
            col,
            val,
        }
    }

    /// The non-zeros of a dense square matrix (O(n²), for models that have the dense form).
    pub fn from_dense(a: &DMatrix<f64>) -> Self {
        let n = a.nrows();
        let mut row_ptr = vec![0];
        let (mut col, mut val) = (Vec::new(), Vec::new());
        for i in 0..n {
            for j in 0..n {
                let v = a[(i, j)];
                if v != 0.0 {
                    col.push(j);
                    val.push(v);
                }
            }
            row_ptr.push(col.len());
        }
        Self {
            n,
            row_ptr,
            col,
            val,
        }
    }

    pub fn to_dense(&self) -> DMatrix<f64> {
        let mut a = DMatrix::zeros(self.n, self.n);
        for i in 0..self.n {
            for k in self.row_ptr[i]..self.row_ptr[i + 1] {
                a[(i, self.col[k])] += self.val[k];
            }
        }
        a
    }

    pub fn nnz(&self) -> usize {
        self.val.len()
    }

    pub fn get(&self, i: usize, j: usize) -> f64 {
        let r = self.row_ptr[i]..self.row_ptr[i + 1];
        match self.col[r.clone()].binary_search(&j) {
            Ok(k) => self.val[r.start + k],
            Err(_) => 0.0,
        }
    }

    /// Whether row `i` has a non-zero value.
    pub fn row_is_zero(&self, i: usize) -> bool {
        self.val[self.row_ptr[i]..self.row_ptr[i + 1]]
            .iter()
            .all(|v| *v == 0.0)
    }

    /// `a·self + b·other` on the union of the patterns.
    pub fn lin_comb(&self, a: f64, other: &CsrMatrix, b: f64) -> CsrMatrix {
        let mut e = Vec::with_capacity(self.nnz() + other.nnz());
        for (m, s) in [(self, a), (other, b)] {
            for i in 0..m.n {
                for k in m.row_ptr[i]..m.row_ptr[i + 1] {
                    e.push((i, m.col[k], s * m.val[k]));
                }
            }
        }
        CsrMatrix::from_triplets(self.n, &e)
    }

    /// `y = β y + α A x` (slices, allocation-free).
    #[inline]
    pub fn mul_add(&self, beta: f64, y: &mut [f64], alpha: f64, x: &[f64]) {
        for (i, yi) in y.iter_mut().enumerate() {
            let (s, e) = (self.row_ptr[i], self.row_ptr[i + 1]);
            let mut acc = 0.0;
            for (v, &c) in self.val[s..e].iter().zip(&self.col[s..e]) {
                acc += v * x[c];
            }
            *yi = if beta == 0.0 {
                alpha * acc
            } else {
                beta * *yi + alpha * acc
            };
        }
    }

    /// Largest absolute value (0 for an empty matrix).
    pub fn amax(&self) -> f64 {
        self.val.iter().fold(0.0, |m, v| m.max(v.abs()))
    }
}

/// `P A Pᵀ = L Lᵀ` with `L` in envelope form: row `i` of `L` holds columns `first[i]..=i`
/// contiguously.
#[derive(Debug, Clone)]
pub struct EnvelopeCholesky {
    pub n: usize,
    /// `perm[new] = old`.
    pub perm: Vec<usize>,
    first: Vec<usize>,
    start: Vec<usize>,
    l: Vec<f64>,
    /// The solves' operators, without divisions on their dependency chains: `1/L_ii`; the
    /// strictly lower part of `L` with row `i` scaled by `1/L_ii` (forward solve, rows in
    /// envelope form); and `Lᵀ`'s strictly upper part with row `k` scaled by `1/L_kk`,
    /// row `k` holding columns `k+1..=last[k]` (backward solve). Both solves are then
    /// row-oriented dot products whose only dependency on the previous row is one
    /// multiply-add on a value kept in a register.
    dinv: Vec<f64>,
    lrow: Vec<f64>,
    last: Vec<usize>,
    ustart: Vec<usize>,
    uval: Vec<f64>,
    /// Whether the RCM ordering was used (else natural).
    pub rcm: bool,
    /// Stored entries of `L` with the natural ordering and with RCM (what the choice saw).
    pub envelope_natural: usize,
    pub envelope_rcm: usize,
}

/// First column of each row's envelope (lower triangle) under ordering `perm`.
fn envelope_first(a: &CsrMatrix, perm: &[usize], inv: &[usize]) -> Vec<usize> {
    (0..a.n)
        .map(|i| {
            let old = perm[i];
            let mut f = i;
            for k in a.row_ptr[old]..a.row_ptr[old + 1] {
                if a.val[k] != 0.0 {
                    f = f.min(inv[a.col[k]]);
                }
            }
            f
        })
        .collect()
}

fn envelope_size(first: &[usize]) -> usize {
    first.iter().enumerate().map(|(i, f)| i - f + 1).sum()
}

/// Reverse Cuthill–McKee of the symmetric pattern of `a` (each connected component from a
/// pseudo-peripheral start of minimum degree).
pub fn reverse_cuthill_mckee(a: &CsrMatrix) -> Vec<usize> {
    let n = a.n;
    let deg: Vec<usize> = (0..n).map(|i| a.row_ptr[i + 1] - a.row_ptr[i]).collect();
    let mut visited = vec![false; n];
    let mut order = Vec::with_capacity(n);
    let bfs = |start: usize, visited: &mut Vec<bool>, out: &mut Vec<usize>| {
        let s0 = out.len();
        out.push(start);
        visited[start] = true;
        let mut head = s0;
        let mut nb: Vec<usize> = Vec::new();
        while head < out.len() {
            let v = out[head];
            head += 1;
            nb.clear();
            for k in a.row_ptr[v]..a.row_ptr[v + 1] {
                let w = a.col[k];
                if !visited[w] {
                    visited[w] = true;
                    nb.push(w);
                }
            }
            nb.sort_by_key(|&w| deg[w]);
            out.extend_from_slice(&nb);
        }
        s0
    };
    for s in 0..n {
        if visited[s] {
            continue;
        }
        // Pseudo-peripheral start: a few BFS sweeps from the last level's min-degree node.
        let mut start = s;
        let mut scratch_vis = visited.clone();
        let mut tmp = Vec::new();
        bfs(start, &mut scratch_vis, &mut tmp);
        for _ in 0..2 {
            let last = *tmp.last().unwrap_or(&start);
            let cand = tmp
                .iter()
                .rev()
                .take(8)
                .copied()
                .min_by_key(|&w| deg[w])
                .unwrap_or(last);
            if cand == start {
                break;
            }
            start = cand;
            scratch_vis.copy_from_slice(&visited);
            tmp.clear();
            bfs(start, &mut scratch_vis, &mut tmp);
        }
        bfs(start, &mut visited, &mut order);
    }
    order.reverse();
    order
}

impl EnvelopeCholesky {
    /// Factorise the symmetric positive definite `a`; `None` if a pivot is not positive.
    pub fn factor(a: &CsrMatrix) -> Option<Self> {
        let n = a.n;
        let natural: Vec<usize> = (0..n).collect();
        let f_nat = envelope_first(a, &natural, &natural);
        let env_nat = envelope_size(&f_nat);
        let rcm = reverse_cuthill_mckee(a);
        let mut inv_rcm = vec![0; n];
        for (new, &old) in rcm.iter().enumerate() {
            inv_rcm[old] = new;
        }
        let f_rcm = envelope_first(a, &rcm, &inv_rcm);
        let env_rcm = envelope_size(&f_rcm);
        let (perm, inv, first, use_rcm) = if env_rcm < env_nat {
            (rcm, inv_rcm, f_rcm, true)
        } else {
            (natural.clone(), natural, f_nat, false)
        };
        let mut start = Vec::with_capacity(n + 1);
        start.push(0);
        for (i, f) in first.iter().enumerate() {
            start.push(start[i] + i - f + 1);
        }
        let mut l = vec![0.0; start[n]];
        // Scatter P A Pᵀ's lower triangle into the envelope.
        for i in 0..n {
            let old = perm[i];
            for k in a.row_ptr[old]..a.row_ptr[old + 1] {
                let j = inv[a.col[k]];
                if j <= i {
                    l[start[i] + j - first[i]] += a.val[k];
                }
            }
        }
        // Row-by-row (bordering) Cholesky: L[i][j] = (A[i][j] − Σ_k L[i][k] L[j][k]) / L[j][j].
        for i in 0..n {
            let fi = first[i];
            for j in fi..i {
                let fj = first[j];
                let k0 = fi.max(fj);
                let mut s = l[start[i] + j - fi];
                let ri = &l[start[i] + k0 - fi..start[i] + j - fi];
                let rj = &l[start[j] + k0 - fj..start[j] + j - fj];
                for (x, y) in ri.iter().zip(rj) {
                    s -= x * y;
                }
                let djj = l[start[j + 1] - 1];
                l[start[i] + j - fi] = s / djj;
            }
            let row = &l[start[i]..start[i + 1] - 1];
            let d = l[start[i + 1] - 1] - row.iter().map(|x| x * x).sum::<f64>();
            if d.is_nan() || d <= 0.0 {
                return None;
            }
            l[start[i + 1] - 1] = d.sqrt();
        }
        let dinv: Vec<f64> = (0..n).map(|i| 1.0 / l[start[i + 1] - 1]).collect();
        let mut lrow = l.clone();
        let mut last: Vec<usize> = (0..n).collect();
        for i in 0..n {
            for k in first[i]..i {
                lrow[start[i] + k - first[i]] *= dinv[i];
                last[k] = last[k].max(i);
            }
        }
        let mut ustart = Vec::with_capacity(n + 1);
        ustart.push(0);
        for (k, lk) in last.iter().enumerate() {
            ustart.push(ustart[k] + lk - k);
        }
        let mut uval = vec![0.0; ustart[n]];
        for i in 0..n {
            for k in first[i]..i {
                uval[ustart[k] + i - k - 1] = l[start[i] + k - first[i]] * dinv[k];
            }
        }
        Some(Self {
            n,
            perm,
            first,
            start,
            l,
            dinv,
            lrow,
            last,
            ustart,
            uval,
            rcm: use_rcm,
            envelope_natural: env_nat,
            envelope_rcm: env_rcm,
        })
    }

    /// Stored entries of `L`.
    pub fn nnz(&self) -> usize {
        self.l.len()
    }

    /// Bytes the solves read: the two scaled copies of `L`, `1/L_ii`, the envelope index
    /// and the permutation.
    pub fn solve_bytes(&self) -> usize {
        (self.lrow.len() + self.uval.len() + self.n) * std::mem::size_of::<f64>()
            + 5 * self.n * std::mem::size_of::<usize>()
    }

    /// Solve `A x = b` in place on `x` (holding `b`), with `work` of length n. Allocation-free.
    pub fn solve_in_place(&self, x: &mut [f64], work: &mut [f64]) {
        let n = self.n;
        for i in 0..n {
            work[i] = x[self.perm[i]] * self.dinv[i];
        }
        // L y = Pb: y_i = b_i/L_ii − Σ_k (L_ik/L_ii) y_k; y_{i−1} stays in a register.
        let mut prev = 0.0;
        for i in 0..n {
            let fi = self.first[i];
            let row = &self.lrow[self.start[i]..self.start[i + 1] - 1];
            let mut s = work[i];
            if let Some((l_last, rest)) = row.split_last() {
                for (lk, yk) in rest.iter().zip(&work[fi..i - 1]) {
                    s -= lk * yk;
                }
                s -= l_last * prev;
            }
            work[i] = s;
            prev = s;
        }
        // Lᵀ z = y: z_i = y_i/L_ii − Σ_{k>i} (L_ki/L_ii) z_k; z_{i+1} stays in a register.
        for (w, d) in work.iter_mut().zip(&self.dinv) {
            *w *= d;
        }
        let mut next = 0.0;
        for i in (0..n).rev() {
            let row = &self.uval[self.ustart[i]..self.ustart[i + 1]];
            let mut s = work[i];
            if let Some((u_first, rest)) = row.split_first() {
                for (uk, zk) in rest.iter().zip(&work[i + 2..self.last[i] + 1]) {
                    s -= uk * zk;
                }
                s -= u_first * next;
            }
            work[i] = s;
            next = s;
        }
        for i in 0..n {
            x[self.perm[i]] = work[i];
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{RngExt, SeedableRng};
    use rand_chacha::ChaCha8Rng;

    #[test]
    fn envelope_cholesky_solves_a_shuffled_banded_system() {
        let mut rng = ChaCha8Rng::seed_from_u64(3);
        let n = 60;
        // A banded SPD matrix with its DOFs shuffled, so RCM has something to undo.
        let mut shuffle: Vec<usize> = (0..n).collect();
        for i in (1..n).rev() {
            let j = rng.random_range(0..=i);
            shuffle.swap(i, j);
        }
        let mut e = Vec::new();
        for i in 0..n {
            e.push((shuffle[i], shuffle[i], 10.0 + rng.random_range(0.0..1.0)));
            for d in 1..=2 {
                if i + d < n {
                    let v = rng.random_range(-1.0..1.0);
                    e.push((shuffle[i], shuffle[i + d], v));
                    e.push((shuffle[i + d], shuffle[i], v));
                }
            }
        }
        let a = CsrMatrix::from_triplets(n, &e);
        let ch = EnvelopeCholesky::factor(&a).unwrap();
        assert!(ch.rcm && ch.envelope_rcm <= 3 * n, "{ch:?}");
        let b: Vec<f64> = (0..n).map(|i| (i as f64).sin()).collect();
        let mut x = b.clone();
        let mut w = vec![0.0; n];
        ch.solve_in_place(&mut x, &mut w);
        let mut r = vec![0.0; n];
        a.mul_add(0.0, &mut r, 1.0, &x);
        let err = r
            .iter()
            .zip(&b)
            .map(|(p, q)| (p - q).abs())
            .fold(0.0, f64::max);
        assert!(err < 1e-12, "{err}");
        // Against the dense form.
        let xd = a
            .to_dense()
            .lu()
            .solve(&nalgebra::DVector::from_vec(b))
            .unwrap();
        for i in 0..n {
            assert!((x[i] - xd[i]).abs() < 1e-12);
        }
    }

    #[test]
    fn indefinite_matrix_is_refused() {
        let a = CsrMatrix::from_triplets(2, &[(0, 0, 1.0), (0, 1, 2.0), (1, 0, 2.0), (1, 1, 1.0)]);
        assert!(EnvelopeCholesky::factor(&a).is_none());
    }
}
