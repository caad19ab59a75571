//! Matrix Market files (the exchange format of Nastran/Abaqus/ANSYS/Code_Aster exports and
//! `scipy.io.mmwrite`) and the DOF map that names their rows by node and direction.
//!
//! Supported: `%%MatrixMarket matrix coordinate real|integer general|symmetric` and
//! `%%MatrixMarket matrix array real|integer general|symmetric`. Not supported (rejected
//! with the header named): `pattern`, `complex`, `hermitian`, `skew-symmetric` — a mass,
//! damping or stiffness matrix is real symmetric. Coordinate entries are 1-based; repeated
//! entries are summed (as `scipy.sparse` does on conversion); a `symmetric` file lists the
//! lower triangle and its mirror is implied (an upper-triangle entry in it is an error, it
//! would be silently doubled otherwise).
//!
//! Why our own reader rather than `nalgebra_sparse::io::load_coo_from_matrix_market_file`:
//! that function returns a CSC/COO without telling which line or entry was wrong, pulls in
//! a parser generator, and we then check every entry again anyway (finite, in range, in the
//! lower triangle); the format is a header line and one entry per line, ~150 lines here
//! with errors that name the file, the line and the entry `(row, col)`.
//!
//! DOF map (CSV, one line per matrix row, `#` comments and a `node,direction,row` header
//! allowed): `node,direction,row` with `node` the integer node id, `direction` one of
//! `w`, `rz`, `ux`, `uy`, `uz`, `rx`, `ry` (the setup's DOF names) and `row` the 1-based
//! matrix row. Every row must be named exactly once and every (node, direction) at most
//! once.

use std::fmt::Write as _;
use std::path::{Path, PathBuf};

use crate::setup::{Dir, DofRef};

#[derive(Debug, thiserror::Error)]
pub enum MatrixMarketError {
    #[error("cannot read {path}: {error}")]
    Io {
        path: PathBuf,
        error: std::io::Error,
    },
    #[error("{path}:{line}: {message}")]
    Syntax {
        path: PathBuf,
        line: usize,
        message: String,
    },
    #[error("{path}: entry ({row}, {col}): {message}")]
    Entry {
        path: PathBuf,
        row: usize,
        col: usize,
        message: String,
    },
    #[error("{path}: {message}")]
    Matrix { path: PathBuf, message: String },
    /// The files disagree with the setup as a set (no one file is at fault).
    #[error("{message}")]
    Files { message: String },
}

/// A real sparse matrix read from a file: `(row, col, value)` triplets, 0-based, duplicates
/// summed, symmetric storage expanded to both triangles.
#[derive(Debug, Clone, PartialEq)]
pub struct Triplets {
    pub path: PathBuf,
    pub nrows: usize,
    pub ncols: usize,
    pub entries: Vec<(usize, usize, f64)>,
}

impl Triplets {
    /// Dense copy (the model layer is dense; the file stays sparse).
    pub fn to_dense(&self) -> nalgebra::DMatrix<f64> {
        let mut m = nalgebra::DMatrix::zeros(self.nrows, self.ncols);
        for &(i, j, v) in &self.entries {
            m[(i, j)] += v;
        }
        m
    }
}

/// Largest matrix dimension accepted: far beyond what a dense or modal step can use, small
/// enough that sizes computed from it cannot overflow.
pub const MAX_DIMENSION: usize = 10_000_000;

/// Parse Matrix Market text; `path` is only used in messages.
pub fn parse_matrix(text: &str, path: &Path) -> Result<Triplets, MatrixMarketError> {
    let syntax = |line: usize, message: String| MatrixMarketError::Syntax {
        path: path.to_path_buf(),
        line,
        message,
    };
    let mut lines = text.lines().enumerate().map(|(i, l)| (i + 1, l));
    let (_, header) = lines
        .next()
        .ok_or_else(|| syntax(1, "empty file (expected a %%MatrixMarket header)".into()))?;
    let h: Vec<String> = header
        .split_whitespace()
        .map(|s| s.to_ascii_lowercase())
        .collect();
    if h.len() != 5 || h[0] != "%%matrixmarket" || h[1] != "matrix" {
        return Err(syntax(
            1,
            format!("expected `%%MatrixMarket matrix <format> <field> <symmetry>`, got `{header}`"),
        ));
    }
    let array = match h[2].as_str() {
        "coordinate" => false,
        "array" => true,
        f => {
            return Err(syntax(
                1,
                format!("format `{f}` is not supported (coordinate or array)"),
            ));
        }
    };
    match h[3].as_str() {
        "real" | "integer" | "double" => {}
        f => {
            return Err(syntax(
                1,
                format!("field `{f}` is not supported: a structural matrix is real"),
            ));
        }
    }
    let symmetric = match h[4].as_str() {
        "general" => false,
        "symmetric" => true,
        s => {
            return Err(syntax(
                1,
                format!("symmetry `{s}` is not supported (general or symmetric)"),
            ));
        }
    };
    // Skip comments and blank lines up to the size line.
    let mut data = lines.filter(|(_, l)| {
        let t = l.trim();
        !t.is_empty() && !t.starts_with('%')
    });
    let (size_line, size) = data
        .next()
        .ok_or_else(|| syntax(2, "missing the size line".into()))?;
    let nums: Vec<&str> = size.split_whitespace().collect();
    let parse_usize = |s: &str, line: usize| {
        s.parse::<usize>()
            .map_err(|_| syntax(line, format!("`{s}` is not a non-negative integer")))
    };
    let want = if array { 2 } else { 3 };
    if nums.len() != want {
        return Err(syntax(
            size_line,
            format!("size line needs {want} integers, got `{size}`"),
        ));
    }
    let nrows = parse_usize(nums[0], size_line)?;
    let ncols = parse_usize(nums[1], size_line)?;
    if nrows > MAX_DIMENSION || ncols > MAX_DIMENSION {
        return Err(syntax(
            size_line,
            format!("{nrows} × {ncols} exceeds the largest supported model ({MAX_DIMENSION} DOFs)"),
        ));
    }
    if symmetric && nrows != ncols {
        return Err(syntax(
            size_line,
            format!("a symmetric matrix must be square, header says {nrows} × {ncols}"),
        ));
    }
    let parse_value = |s: &str, line: usize, row: usize, col: usize| {
        let v = s.parse::<f64>().map_err(|_| MatrixMarketError::Entry {
            path: path.to_path_buf(),
            row,
            col,
            message: format!("line {line}: `{s}` is not a number"),
        })?;
        if !v.is_finite() {
            return Err(MatrixMarketError::Entry {
                path: path.to_path_buf(),
                row,
                col,
                message: format!("line {line}: value {v} is not finite"),
            });
        }
        Ok(v)
    };
    let mut entries = Vec::new();
    let mut push = |i: usize, j: usize, v: f64| {
        if v != 0.0 {
            entries.push((i, j, v));
            if symmetric && i != j {
                entries.push((j, i, v));
            }
        }
    };
    if array {
        // Column-major; a symmetric array lists the lower triangle column by column.
        let mut pos = 0usize;
        let total = if symmetric {
            nrows * (nrows + 1) / 2
        } else {
            nrows * ncols
        };
        let (mut i, mut j) = (0usize, 0usize);
        for (line, l) in data {
            for tok in l.split_whitespace() {
                if pos >= total {
                    return Err(syntax(
                        line,
                        format!("more than the {total} values expected"),
                    ));
                }
                let v = parse_value(tok, line, i + 1, j + 1)?;
                push(i, j, v);
                pos += 1;
                i += 1;
                if i == nrows {
                    j += 1;
                    i = if symmetric { j } else { 0 };
                }
            }
        }
        if pos != total {
            return Err(MatrixMarketError::Matrix {
                path: path.to_path_buf(),
                message: format!("{pos} values, the header promises {total}"),
            });
        }
    } else {
        let nnz = parse_usize(nums[2], size_line)?;
        let mut count = 0usize;
        for (line, l) in data {
            let t: Vec<&str> = l.split_whitespace().collect();
            if t.len() != 3 {
                return Err(syntax(line, format!("expected `row col value`, got `{l}`")));
            }
            let r = parse_usize(t[0], line)?;
            let c = parse_usize(t[1], line)?;
            if r == 0 || c == 0 || r > nrows || c > ncols {
                return Err(MatrixMarketError::Entry {
                    path: path.to_path_buf(),
                    row: r,
                    col: c,
                    message: format!(
                        "line {line}: outside the {nrows} × {ncols} matrix (indices are 1-based)"
                    ),
                });
            }
            if symmetric && c > r {
                return Err(MatrixMarketError::Entry {
                    path: path.to_path_buf(),
                    row: r,
                    col: c,
                    message: format!(
                        "line {line}: upper-triangle entry in a `symmetric` file (only the lower triangle may be stored)"
                    ),
                });
            }
            let v = parse_value(t[2], line, r, c)?;
            push(r - 1, c - 1, v);
            count += 1;
        }
        if count != nnz {
            return Err(MatrixMarketError::Matrix {
                path: path.to_path_buf(),
                message: format!("{count} entries, the size line promises {nnz}"),
            });
        }
    }
    // Sum duplicates.
    entries.sort_by_key(|e| (e.0, e.1));
    let mut merged: Vec<(usize, usize, f64)> = Vec::with_capacity(entries.len());
    for (i, j, v) in entries {
        match merged.last_mut() {
            Some(last) if last.0 == i && last.1 == j => last.2 += v,
            _ => merged.push((i, j, v)),
        }
    }
    Ok(Triplets {
        path: path.to_path_buf(),
        nrows,
        ncols,
        entries: merged,
    })
}

/// Write a symmetric dense matrix as `coordinate real symmetric` (lower triangle, zeros
/// left out). Values are written in Rust's shortest round-trip form, so reading the file
/// back gives the same `f64` bit for bit.
pub fn write_symmetric(m: &nalgebra::DMatrix<f64>, comment: &str) -> String {
    let n = m.nrows();
    let mut entries = Vec::new();
    for j in 0..n {
        for i in j..n {
            let v = m[(i, j)];
            if v != 0.0 {
                entries.push((i + 1, j + 1, v));
            }
        }
    }
    let mut s = String::from("%%MatrixMarket matrix coordinate real symmetric\n");
    for l in comment.lines() {
        let _ = writeln!(s, "% {l}");
    }
    let _ = writeln!(s, "{n} {n} {}", entries.len());
    for (i, j, v) in entries {
        let _ = writeln!(s, "{i} {j} {v:e}");
    }
    s
}

/// Name of a direction in the DOF map and the setup.
pub fn dir_name(d: Dir) -> &'static str {
    match d {
        Dir::W => "w",
        Dir::Rz => "rz",
        Dir::Ux => "ux",
        Dir::Uy => "uy",
        Dir::Uz => "uz",
        Dir::Rx => "rx",
        Dir::Ry => "ry",
        Dir::Mode => "mode",
    }
}

fn parse_dir(s: &str) -> Option<Dir> {
    Some(match s.to_ascii_lowercase().as_str() {
        "w" => Dir::W,
        "rz" => Dir::Rz,
        "ux" => Dir::Ux,
        "uy" => Dir::Uy,
        "uz" => Dir::Uz,
        "rx" => Dir::Rx,
        "ry" => Dir::Ry,
        _ => return None,
    })
}

/// Parse DOF map text; `path` is only used in messages.
pub fn parse_dof_map(text: &str, path: &Path) -> Result<Vec<DofRef>, MatrixMarketError> {
    let syntax = |line: usize, message: String| MatrixMarketError::Syntax {
        path: path.to_path_buf(),
        line,
        message,
    };
    let mut rows: Vec<(usize, DofRef, usize)> = Vec::new();
    for (i, l) in text.lines().enumerate() {
        let line = i + 1;
        let t = l.split('#').next().unwrap_or("").trim();
        if t.is_empty()
            || t.replace(' ', "")
                .eq_ignore_ascii_case("node,direction,row")
        {
            continue;
        }
        let f: Vec<&str> = t.split(',').map(str::trim).collect();
        if f.len() != 3 {
            return Err(syntax(
                line,
                format!("expected `node,direction,row`, got `{t}`"),
            ));
        }
        let node = f[0]
            .parse::<u32>()
            .map_err(|_| syntax(line, format!("node `{}` is not an integer id", f[0])))?;
        let dir = parse_dir(f[1]).ok_or_else(|| {
            syntax(
                line,
                format!(
                    "direction `{}` is not one of w, rz, ux, uy, uz, rx, ry",
                    f[1]
                ),
            )
        })?;
        let row = f[2]
            .parse::<usize>()
            .ok()
            .filter(|&r| r >= 1)
            .ok_or_else(|| syntax(line, format!("row `{}` is not a 1-based row number", f[2])))?;
        rows.push((row, DofRef { node, dir }, line));
    }
    let n = rows.len();
    let mut out: Vec<Option<DofRef>> = vec![None; n];
    let mut seen = std::collections::BTreeMap::new();
    for &(row, dof, line) in &rows {
        if row > n {
            return Err(syntax(
                line,
                format!("row {row} but the map names only {n} rows (rows are 1..={n})"),
            ));
        }
        if out[row - 1].is_some() {
            return Err(syntax(line, format!("row {row} is named twice")));
        }
        if let Some(first) = seen.insert(dof, line) {
            return Err(syntax(
                line,
                format!("{dof} is already mapped on line {first}"),
            ));
        }
        out[row - 1] = Some(dof);
    }
    // n entries, each row in 1..=n at most once: every row is named.
    Ok(out.into_iter().flatten().collect())
}

/// Write a DOF map for `dofs` in row order.
pub fn write_dof_map(dofs: &[DofRef]) -> String {
    let mut s = String::from("node,direction,row\n");
    for (i, d) in dofs.iter().enumerate() {
        let _ = writeln!(s, "{},{},{}", d.node, dir_name(d.dir), i + 1);
    }
    s
}

/// The component matrices of an external FE model, checked: square, the same size as the
/// DOF map, symmetric, finite, mass diagonal ≥ 0, stiffness diagonal ≥ 0 and every 2 × 2
/// principal minor of K non-negative (`k_ij² ≤ k_ii·k_jj`, a necessary condition of
/// positive semi-definiteness that names the entry; the full check is a Cholesky
/// factorisation in `Model::assemble`).
#[derive(Debug, Clone, PartialEq)]
pub struct ExternalModel {
    pub mass: Triplets,
    pub stiffness: Triplets,
    pub damping: Option<Triplets>,
    pub dof_map: PathBuf,
    /// Label of each row, in row order.
    pub dofs: Vec<DofRef>,
    /// The files' text as read: a recording made with this model carries them
    /// ([`crate::io::mcap`]), so it replays with the matrices it was made with wherever it
    /// is moved and whatever becomes of the files.
    pub sources: ModelFiles,
}

/// The text of an external model's files, one per `[model.matrix_market]` key.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct ModelFiles {
    pub mass: String,
    pub stiffness: String,
    pub damping: Option<String>,
    pub dof_map: String,
}

impl ModelFiles {
    /// The `[model.matrix_market]` keys and their texts, in a fixed order (the names a
    /// recording's attachments carry).
    pub fn entries(&self) -> Vec<(&'static str, &str)> {
        let mut v = vec![
            ("mass", self.mass.as_str()),
            ("stiffness", self.stiffness.as_str()),
        ];
        if let Some(d) = &self.damping {
            v.push(("damping", d.as_str()));
        }
        v.push(("dof_map", self.dof_map.as_str()));
        v
    }

    /// Read the files (capped at [`crate::io::MAX_MODEL_FILE_BYTES`] each).
    pub fn read(
        mass: &Path,
        stiffness: &Path,
        damping: Option<&Path>,
        dof_map: &Path,
    ) -> Result<Self, MatrixMarketError> {
        let read = |path: &Path| {
            crate::io::read_text_capped(path, crate::io::MAX_MODEL_FILE_BYTES).map_err(|error| {
                MatrixMarketError::Io {
                    path: path.to_path_buf(),
                    error,
                }
            })
        };
        Ok(Self {
            mass: read(mass)?,
            stiffness: read(stiffness)?,
            damping: damping.map(read).transpose()?,
            dof_map: read(dof_map)?,
        })
    }
}

/// Relative tolerance of the symmetry check, against the largest |entry| of the matrix.
pub const SYMMETRY_TOLERANCE: f64 = 1e-10;

impl ExternalModel {
    /// Read and check the files. Paths are used as given (the setup resolves them).
    pub fn load(
        mass: &Path,
        stiffness: &Path,
        damping: Option<&Path>,
        dof_map: &Path,
    ) -> Result<Self, MatrixMarketError> {
        let files = ModelFiles::read(mass, stiffness, damping, dof_map)?;
        Self::from_files(files, mass, stiffness, damping, dof_map)
    }

    /// Parse and check the files' text; the paths only name them in messages.
    pub fn from_files(
        files: ModelFiles,
        mass: &Path,
        stiffness: &Path,
        damping: Option<&Path>,
        dof_map: &Path,
    ) -> Result<Self, MatrixMarketError> {
        let dofs = parse_dof_map(&files.dof_map, dof_map)?;
        let n = dofs.len();
        let mass = parse_matrix(&files.mass, mass)?;
        let stiffness = parse_matrix(&files.stiffness, stiffness)?;
        let damping = match (&files.damping, damping) {
            (Some(text), Some(path)) => Some(parse_matrix(text, path)?),
            // A damping matrix the setup does not name would change the model unasked.
            (Some(_), None) => {
                return Err(MatrixMarketError::Files {
                    message: "the model's files include a damping matrix the setup does not name (name it as model.matrix_market.damping to use it)".into(),
                });
            }
            (None, Some(path)) => {
                return Err(MatrixMarketError::Matrix {
                    path: path.to_path_buf(),
                    message: "named by the setup but not among the model's files".into(),
                });
            }
            (None, None) => None,
        };
        for m in std::iter::once(&mass)
            .chain(std::iter::once(&stiffness))
            .chain(damping.iter())
        {
            if m.nrows != m.ncols {
                return Err(MatrixMarketError::Matrix {
                    path: m.path.clone(),
                    message: format!("not square: {} × {}", m.nrows, m.ncols),
                });
            }
            if m.nrows != n {
                return Err(MatrixMarketError::Matrix {
                    path: m.path.clone(),
                    message: format!(
                        "{} rows, but the DOF map {} names {n}",
                        m.nrows,
                        dof_map.display()
                    ),
                });
            }
            check_symmetric(m)?;
        }
        let diag = |m: &Triplets| {
            let mut d = vec![0.0; m.nrows];
            for &(i, j, v) in &m.entries {
                if i == j {
                    d[i] = v;
                }
            }
            d
        };
        let dm = diag(&mass);
        if let Some((i, v)) = dm.iter().enumerate().find(|(_, v)| **v < 0.0) {
            return Err(MatrixMarketError::Entry {
                path: mass.path.clone(),
                row: i + 1,
                col: i + 1,
                message: format!("negative mass {v} on the diagonal ({})", dofs[i]),
            });
        }
        if dm.iter().all(|v| *v == 0.0) {
            return Err(MatrixMarketError::Matrix {
                path: mass.path.clone(),
                message: "the mass matrix has no positive diagonal entry".into(),
            });
        }
        for (m, what) in
            std::iter::once((&stiffness, "stiffness")).chain(damping.iter().map(|d| (d, "damping")))
        {
            let d = diag(m);
            if let Some((i, v)) = d.iter().enumerate().find(|(_, v)| **v < 0.0) {
                return Err(MatrixMarketError::Entry {
                    path: m.path.clone(),
                    row: i + 1,
                    col: i + 1,
                    message: format!(
                        "negative {what} {v} on the diagonal ({}): not positive semi-definite",
                        dofs[i]
                    ),
                });
            }
            for &(i, j, v) in &m.entries {
                if i > j && v * v > d[i] * d[j] * (1.0 + 1e-9) {
                    return Err(MatrixMarketError::Entry {
                        path: m.path.clone(),
                        row: i + 1,
                        col: j + 1,
                        message: format!(
                            "|{v:e}| exceeds sqrt(diagonal product) = {:e}: the {what} matrix is not positive semi-definite",
                            (d[i] * d[j]).sqrt()
                        ),
                    });
                }
            }
        }
        Ok(Self {
            mass,
            stiffness,
            damping,
            dof_map: dof_map.to_path_buf(),
            dofs,
            sources: files,
        })
    }
}

fn check_symmetric(m: &Triplets) -> Result<(), MatrixMarketError> {
    let scale = m.entries.iter().fold(0.0f64, |a, e| a.max(e.2.abs()));
    let lookup: std::collections::HashMap<(usize, usize), f64> =
        m.entries.iter().map(|&(i, j, v)| ((i, j), v)).collect();
    let mut worst: Option<(usize, usize, f64, f64)> = None;
    for &(i, j, v) in &m.entries {
        if i <= j {
            continue;
        }
        let w = lookup.get(&(j, i)).copied().unwrap_or(0.0);
        let d = (v - w).abs();
        if d > SYMMETRY_TOLERANCE * scale && worst.is_none_or(|x| d > (x.2 - x.3).abs()) {
            worst = Some((i, j, v, w));
        }
    }
    // Entries whose mirror is missing from the upper side.
    for &(i, j, v) in &m.entries {
        if i < j
            && !lookup.contains_key(&(j, i))
            && v.abs() > SYMMETRY_TOLERANCE * scale
            && worst.is_none_or(|x| v.abs() > (x.2 - x.3).abs())
        {
            worst = Some((j, i, 0.0, v));
        }
    }
    match worst {
        None => Ok(()),
        Some((i, j, v, w)) => Err(MatrixMarketError::Entry {
            path: m.path.clone(),
            row: i + 1,
            col: j + 1,
            message: format!(
                "not symmetric: ({}, {}) = {v:e} but ({}, {}) = {w:e} (tolerance {SYMMETRY_TOLERANCE:e} × max |entry|)",
                i + 1,
                j + 1,
                j + 1,
                i + 1
            ),
        }),
    }
}

/// Errors of [`export`].
#[derive(Debug, thiserror::Error)]
pub enum ExportError {
    #[error(transparent)]
    Model(#[from] crate::model::ModelError),
    #[error("cannot write {path}: {source}")]
    Io {
        path: PathBuf,
        source: std::io::Error,
    },
    #[error("cannot rewrite the setup text: {0}")]
    Toml(String),
}

/// The files [`export`] may write into its directory.
pub const EXPORT_FILES: &[&str] = &[
    "mass.mtx",
    "stiffness.mtx",
    "damping.mtx",
    "dofs.csv",
    "setup.toml",
];

/// What [`export`] wrote.
#[derive(Debug, Clone)]
pub struct ExportSummary {
    pub dofs: usize,
    pub files: Vec<PathBuf>,
}

/// Export a setup's component model as Matrix Market: `mass.mtx`, `stiffness.mtx`,
/// `damping.mtx` (only when the model has dashpots or an external damping matrix; Rayleigh
/// damping stays a setup key so it is re-applied the same way), `dofs.csv` and `setup.toml`
/// (the same setup with `[model]` replaced by `[model.matrix_market]`) in `out_dir`.
///
/// The matrices are the *condensed* ones the estimators use (massless DOFs already
/// removed), written in shortest round-trip form, so the exported setup reproduces the
/// model bit for bit and identifies the same parameters.
pub fn export(setup: &crate::setup::Setup, out_dir: &Path) -> Result<ExportSummary, ExportError> {
    let io = |path: &Path| {
        let path = path.to_path_buf();
        move |source| ExportError::Io { path, source }
    };
    std::fs::create_dir_all(out_dir).map_err(io(out_dir))?;
    // The damping without its Rayleigh part: assemble once with Rayleigh switched off.
    let mut bare = setup.clone();
    bare.model.rayleigh = None;
    let model = crate::model::Model::assemble(&bare)?;
    if !model.has_dense() {
        return Err(crate::model::ModelError::SparseOnly {
            dofs: model.n(),
            what: "export-mm",
        }
        .into());
    }
    let origin = &setup.origin;
    let mut files = Vec::new();
    let mut write = |name: &str, text: String| -> Result<(), ExportError> {
        let p = out_dir.join(name);
        std::fs::write(&p, text).map_err(io(&p))?;
        files.push(p);
        Ok(())
    };
    let note = format!("exported by `jointid export-mm` from {origin}");
    write(
        "mass.mtx",
        write_symmetric(
            &model.M,
            &format!("mass matrix, kg (rotations kg·m²); {note}"),
        ),
    )?;
    write(
        "stiffness.mtx",
        write_symmetric(&model.K, &format!("stiffness matrix, N/m; {note}")),
    )?;
    let damped = model.C.iter().any(|v| *v != 0.0);
    if damped {
        write(
            "damping.mtx",
            write_symmetric(&model.C, &format!("damping matrix, N·s/m; {note}")),
        )?;
    }
    write("dofs.csv", write_dof_map(&model.dofs))?;
    let mut table: toml::Table = setup
        .toml_text
        .parse()
        .map_err(|e: toml::de::Error| ExportError::Toml(e.to_string()))?;
    let mut mm = toml::Table::new();
    mm.insert("mass".into(), "mass.mtx".into());
    mm.insert("stiffness".into(), "stiffness.mtx".into());
    if damped {
        mm.insert("damping".into(), "damping.mtx".into());
    }
    mm.insert("dof_map".into(), "dofs.csv".into());
    let mut model_t = toml::Table::new();
    model_t.insert("matrix_market".into(), toml::Value::Table(mm));
    if let Some(r) = &setup.model.rayleigh {
        let mut rt = toml::Table::new();
        rt.insert("alpha".into(), r.alpha.into());
        rt.insert("beta".into(), r.beta.into());
        model_t.insert("rayleigh".into(), toml::Value::Table(rt));
    }
    table.insert("model".into(), toml::Value::Table(model_t));
    let body = toml::to_string(&table).map_err(|e| ExportError::Toml(e.to_string()))?;
    write(
        "setup.toml",
        format!(
            "# {note}: the component model is in the Matrix Market files next to this one\n# (condensed: {} DOFs).\n{body}",
            model.n()
        ),
    )?;
    Ok(ExportSummary {
        dofs: model.n(),
        files,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn p() -> &'static Path {
        Path::new("k.mtx")
    }

    /// Files and setup must agree on the damping matrix: one the setup does not name, or
    /// one it names that the files lack, is an error naming it; agreeing files load.
    #[test]
    fn model_files_and_the_setup_agree_on_the_damping() {
        let one = "%%MatrixMarket matrix coordinate real symmetric\n1 1 1\n1 1 2.5\n";
        let files = ModelFiles {
            mass: one.into(),
            stiffness: one.into(),
            damping: Some(one.into()),
            dof_map: "node,direction,row\n1,w,1\n".into(),
        };
        let (m, k, d, map) = (
            Path::new("m"),
            Path::new("k"),
            Path::new("c"),
            Path::new("dofs"),
        );
        let ok = ExternalModel::from_files(files.clone(), m, k, Some(d), map).unwrap();
        assert_eq!(ok.damping.unwrap().to_dense()[(0, 0)], 2.5);
        let e = ExternalModel::from_files(files.clone(), m, k, None, map).unwrap_err();
        assert!(
            e.to_string()
                .contains("damping matrix the setup does not name"),
            "{e}"
        );
        // No one file is at fault: the message names none (it used to name the DOF map).
        assert!(!e.to_string().contains("dofs"), "{e}");
        let none = ModelFiles {
            damping: None,
            ..files
        };
        let e = ExternalModel::from_files(none, m, k, Some(d), map).unwrap_err();
        assert!(e.to_string().contains("named by the setup"), "{e}");
    }

    #[test]
    fn coordinate_symmetric_expands_and_sums_duplicates() {
        let t = "%%MatrixMarket matrix coordinate real symmetric\n% c\n3 3 4\n1 1 2.0\n2 1 -1\n2 1 -0.5\n3 3 4e0\n";
        let m = parse_matrix(t, p()).unwrap().to_dense();
        assert_eq!(m[(1, 0)], -1.5);
        assert_eq!(m[(0, 1)], -1.5);
        assert_eq!(m[(2, 2)], 4.0);
        assert_eq!(m[(1, 1)], 0.0);
    }

    #[test]
    fn array_symmetric_is_lower_triangle_column_major() {
        let t = "%%MatrixMarket matrix array real symmetric\n2 2\n1\n2\n3\n";
        let m = parse_matrix(t, p()).unwrap().to_dense();
        assert_eq!(
            m,
            nalgebra::DMatrix::from_row_slice(2, 2, &[1.0, 2.0, 2.0, 3.0])
        );
        let t = "%%MatrixMarket matrix array real general\n2 2\n1 2\n3 4\n";
        let m = parse_matrix(t, p()).unwrap().to_dense();
        assert_eq!(
            m,
            nalgebra::DMatrix::from_row_slice(2, 2, &[1.0, 3.0, 2.0, 4.0])
        );
    }

    #[test]
    fn errors_name_the_entry_and_line() {
        let e = parse_matrix(
            "%%MatrixMarket matrix coordinate real general\n2 2 1\n3 1 1.0\n",
            p(),
        )
        .unwrap_err()
        .to_string();
        assert!(
            e.contains("k.mtx") && e.contains("(3, 1)") && e.contains("line 3"),
            "{e}"
        );
        let e = parse_matrix(
            "%%MatrixMarket matrix coordinate real general\n2 2 1\n1 2 nan\n",
            p(),
        )
        .unwrap_err()
        .to_string();
        assert!(e.contains("(1, 2)") && e.contains("not finite"), "{e}");
        let e = parse_matrix(
            "%%MatrixMarket matrix coordinate real symmetric\n2 2 1\n1 2 1\n",
            p(),
        )
        .unwrap_err()
        .to_string();
        assert!(e.contains("upper-triangle"), "{e}");
        let e = parse_matrix(
            "%%MatrixMarket matrix coordinate complex general\n2 2 0\n",
            p(),
        )
        .unwrap_err()
        .to_string();
        assert!(e.contains("complex"), "{e}");
        let e = parse_matrix(
            "%%MatrixMarket matrix coordinate real general\n2 2 2\n1 1 1\n",
            p(),
        )
        .unwrap_err()
        .to_string();
        assert!(e.contains("1 entries") && e.contains("promises 2"), "{e}");
    }

    #[test]
    fn write_then_read_is_bit_exact() {
        let m = nalgebra::DMatrix::from_row_slice(
            3,
            3,
            &[
                1.0 / 3.0,
                -2e-17,
                0.0,
                -2e-17,
                12345.678901234567,
                7.1e300,
                0.0,
                7.1e300,
                f64::MIN_POSITIVE,
            ],
        );
        let back = parse_matrix(&write_symmetric(&m, "two\nlines"), p())
            .unwrap()
            .to_dense();
        assert_eq!(back, m);
    }

    #[test]
    fn external_model_checks_name_file_and_entry() {
        let dir = tempfile::tempdir().unwrap();
        let w = |name: &str, text: &str| {
            let p = dir.path().join(name);
            std::fs::write(&p, text).unwrap();
            p
        };
        let map = w("dofs.csv", "node,direction,row\n1,w,1\n2,w,2\n");
        let m = w(
            "m.mtx",
            "%%MatrixMarket matrix coordinate real symmetric\n2 2 2\n1 1 1\n2 2 1\n",
        );
        let k = w(
            "k.mtx",
            "%%MatrixMarket matrix coordinate real general\n2 2 4\n1 1 2\n1 2 -1\n2 1 -1\n2 2 1\n",
        );
        let ok = ExternalModel::load(&m, &k, None, &map).unwrap();
        assert_eq!(ok.stiffness.to_dense()[(0, 1)], -1.0);
        let k_asym = w(
            "ka.mtx",
            "%%MatrixMarket matrix coordinate real general\n2 2 4\n1 1 2\n1 2 -1\n2 1 -1.5\n2 2 1\n",
        );
        let e = ExternalModel::load(&m, &k_asym, None, &map)
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("ka.mtx") && e.contains("(2, 1)") && e.contains("not symmetric"),
            "{e}"
        );
        let k_ind = w(
            "ki.mtx",
            "%%MatrixMarket matrix coordinate real symmetric\n2 2 3\n1 1 1\n2 1 -3\n2 2 1\n",
        );
        let e = ExternalModel::load(&m, &k_ind, None, &map)
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("ki.mtx") && e.contains("(2, 1)") && e.contains("semi-definite"),
            "{e}"
        );
        let m_neg = w(
            "mn.mtx",
            "%%MatrixMarket matrix coordinate real symmetric\n2 2 2\n1 1 1\n2 2 -1\n",
        );
        let e = ExternalModel::load(&m_neg, &k, None, &map)
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("mn.mtx") && e.contains("(2, 2)") && e.contains("negative mass"),
            "{e}"
        );
        let m3 = w(
            "m3.mtx",
            "%%MatrixMarket matrix coordinate real symmetric\n3 3 1\n1 1 1\n",
        );
        let e = ExternalModel::load(&m3, &k, None, &map)
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("m3.mtx") && e.contains("3 rows") && e.contains("names 2"),
            "{e}"
        );
    }

    #[test]
    fn dof_map_round_trip_and_errors() {
        let dofs = vec![
            DofRef {
                node: 7,
                dir: Dir::W,
            },
            DofRef {
                node: 3,
                dir: Dir::Uz,
            },
            DofRef {
                node: 3,
                dir: Dir::Rx,
            },
        ];
        assert_eq!(parse_dof_map(&write_dof_map(&dofs), p()).unwrap(), dofs);
        let e = parse_dof_map("1,w,1\n1,w,2\n", p())
            .unwrap_err()
            .to_string();
        assert!(
            e.contains(":2:") && e.contains("already mapped on line 1"),
            "{e}"
        );
        let e = parse_dof_map("1,w,1\n2,w,3\n", p())
            .unwrap_err()
            .to_string();
        assert!(e.contains("row 3"), "{e}");
        let e = parse_dof_map("1,q,1\n", p()).unwrap_err().to_string();
        assert!(e.contains("direction `q`"), "{e}");
    }
}
