//! Checks on where outputs go, made before any work starts: an output must not be one of
//! the command's inputs (it would be replaced: a measured CSV, a setup, a recording), its
//! directory must exist, and a plots directory must not be an existing file.
//!
//! Why up front: the writers create `<out>.partial` and rename it over `<out>` only when
//! complete, so an output that is an input replaces the input at the end without a word,
//! and an output in a missing directory fails with the temporary name after the whole
//! identification has run.

use std::path::{Path, PathBuf};

/// Why an output path was refused.
#[derive(Debug, thiserror::Error)]
#[error("{option} {path}: {reason}")]
pub struct OutputPathError {
    pub option: &'static str,
    pub path: PathBuf,
    pub reason: String,
}

/// Whether two paths name the same existing file (through links and relative parts).
fn same_file(a: &Path, b: &Path) -> bool {
    match (a.canonicalize(), b.canonicalize()) {
        (Ok(x), Ok(y)) => x == y,
        _ => false,
    }
}

/// An output file `out` (given with `option`): not any of `inputs`, in a directory that
/// exists, not an existing directory itself.
pub fn check_output_file(
    option: &'static str,
    out: &Path,
    inputs: &[&Path],
) -> Result<(), OutputPathError> {
    let refuse = |reason: String| OutputPathError {
        option,
        path: out.to_path_buf(),
        reason,
    };
    if let Some(input) = inputs.iter().find(|i| same_file(out, i)) {
        return Err(refuse(format!(
            "is the input {} — writing it would replace the input; give another output name",
            input.display()
        )));
    }
    if out.is_dir() {
        return Err(refuse("is a directory; give a file name".into()));
    }
    if let Some(dir) = out.parent().filter(|d| !d.as_os_str().is_empty())
        && !dir.is_dir()
    {
        return Err(refuse(format!(
            "the directory {} does not exist",
            dir.display()
        )));
    }
    Ok(())
}

/// An output directory `dir` (given with `option`; created if missing) into which files
/// named `names` will be written: not an existing file, and none of its files any of
/// `inputs`.
pub fn check_output_dir(
    option: &'static str,
    dir: &Path,
    names: &[&str],
    inputs: &[&Path],
) -> Result<(), OutputPathError> {
    let refuse = |reason: String| OutputPathError {
        option,
        path: dir.to_path_buf(),
        reason,
    };
    if dir.exists() && !dir.is_dir() {
        return Err(refuse("exists and is not a directory".into()));
    }
    for name in names {
        let file = dir.join(name);
        if let Some(input) = inputs.iter().find(|i| same_file(&file, i)) {
            return Err(refuse(format!(
                "would hold {name}, which is the input {} — writing it would replace the input; give another directory",
                input.display()
            )));
        }
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    fn scratch(name: &str) -> PathBuf {
        let d = std::env::temp_dir().join(format!("jointid-output-{name}-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&d);
        std::fs::create_dir_all(&d).expect("scratch dir");
        d
    }

    #[test]
    fn an_output_that_is_an_input_is_refused_by_any_spelling() {
        let d = scratch("same");
        let input = d.join("data.csv");
        std::fs::write(&input, "t,x\n0,1\n").expect("write");
        let other = d.join("sub").join("..").join("data.csv");
        std::fs::create_dir_all(d.join("sub")).expect("sub");
        let e = check_output_file("--out", &other, &[&input]).unwrap_err();
        assert!(e.to_string().contains("is the input"), "{e}");
        assert!(e.to_string().starts_with("--out "), "{e}");
        // Another name in the same directory is fine.
        check_output_file("--out", &d.join("data.mcap"), &[&input]).expect("other name");
        let _ = std::fs::remove_dir_all(&d);
    }

    #[test]
    fn an_output_in_a_missing_directory_names_the_directory() {
        let d = scratch("missing");
        let out = d.join("nodir").join("x.mcap");
        let e = check_output_file("--out", &out, &[]).unwrap_err();
        let text = e.to_string();
        assert!(text.contains("does not exist"), "{text}");
        assert!(text.contains("nodir"), "{text}");
        assert!(!text.contains(".partial"), "{text}");
        let e = check_output_file("--out", &d, &[]).unwrap_err();
        assert!(e.to_string().contains("is a directory"), "{e}");
        let _ = std::fs::remove_dir_all(&d);
    }

    #[test]
    fn a_plots_directory_that_is_a_file_or_holds_an_input_is_refused() {
        let d = scratch("dir");
        let file = d.join("afile");
        std::fs::write(&file, "x").expect("write");
        let e = check_output_dir("--plots", &file, &[], &[]).unwrap_err();
        assert!(e.to_string().contains("not a directory"), "{e}");
        let setup = d.join("setup.toml");
        std::fs::write(&setup, "x").expect("write");
        let e = check_output_dir("--out", &d, &["mass.mtx", "setup.toml"], &[&setup]).unwrap_err();
        assert!(e.to_string().contains("setup.toml"), "{e}");
        check_output_dir("--out", &d.join("new"), &["setup.toml"], &[&setup]).expect("new dir");
        let _ = std::fs::remove_dir_all(&d);
    }
}
