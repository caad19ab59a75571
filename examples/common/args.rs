//! The `--key value` options and `--flag`s of the sweep and probe examples (not a clap
//! interface: these are developer tools whose options change with the experiment).
// Each example includes this file as its own module and uses only part of it.
#![allow(dead_code)]

/// The command line, as given.
pub struct Args(Vec<String>);

impl Args {
    pub fn from_env() -> Self {
        Self(std::env::args().collect())
    }

    /// The `i`-th word (0 is the program).
    pub fn positional(&self, i: usize) -> Option<&str> {
        self.0.get(i).map(String::as_str)
    }

    /// The setup file named by the first word, and that word; the usage line of `example`
    /// when there is none.
    pub fn setup(&self, example: &str) -> anyhow::Result<(String, jointid::setup::Setup)> {
        let path = self
            .positional(1)
            .ok_or_else(|| anyhow::anyhow!("usage: {example} SETUP [options]"))?;
        let setup = jointid::setup::Setup::from_file(std::path::Path::new(path))?;
        Ok((path.to_string(), setup))
    }

    /// The word after `key`, or `default` when `key` is absent or last.
    pub fn get(&self, key: &str, default: &str) -> String {
        self.0
            .iter()
            .position(|x| x == key)
            .and_then(|i| self.0.get(i + 1))
            .cloned()
            .unwrap_or_else(|| default.to_string())
    }

    /// Whether `flag` was given.
    pub fn flag(&self, flag: &str) -> bool {
        self.0.iter().any(|x| x == flag)
    }
}
