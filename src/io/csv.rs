//! `jointid import`: a test campaign's CSV file → a recording (MCAP) with the setup attached,
//! ready for `jointid replay`.
//!
//! # Accepted CSV
//!
//! - One header row of column names, then one row per sample. Lines starting with `#` are
//!   comments. The delimiter is `,` unless the header has none and has `;` or a tab (or it is
//!   given explicitly).
//! - Every excitation channel and every sensor of the setup has a column of the same name
//!   (`[[excitation]] name`, `[[sensors]] name`), in SI units (the setup's `unit`). Other
//!   columns are ignored and listed in the summary.
//! - Time: a column in seconds named `t`, `time`, `t_s` or `time_s` (any case), or the one
//!   given with `--time-column`. Samples must be evenly spaced: every interval within 1 % of
//!   the first. Without a time column, samples are `dt_s` apart (the setup's, or `--dt`).
//! - When the file's interval differs from the setup's `dt_s`, the attached setup gets the
//!   file's interval (the replay discretises the model at the data's rate); the summary says
//!   so. A time column whose interval is 10× the setup's or more (or a tenth or less) is
//!   refused: that is a unit slip (milliseconds), not a model made for another rate.
//!
//! Every value must parse as a finite number; an error names the file, the line and the
//! column. The recording is written to `<out>.partial` and renamed only when complete, so a
//! failed import never leaves a half-written recording at `out`. Memory is bounded: rows are
//! streamed to the writer.

use std::collections::BTreeMap;
use std::io::Read as _;
use std::path::{Path, PathBuf};

use serde::Serialize;

use crate::io::mcap::{McapIoError, RECORDING_METADATA, RecordingWriter};
use crate::io::{Frame, FrameEncoding};
use crate::setup::Setup;

/// Column names recognised as time (seconds), compared without case.
pub const TIME_COLUMN_NAMES: [&str; 4] = ["t", "time", "t_s", "time_s"];

#[derive(Debug, thiserror::Error)]
pub enum ImportError {
    #[error("{path}: {source}")]
    Io {
        path: PathBuf,
        source: std::io::Error,
    },
    #[error("{path}: line {line}: {source}")]
    Csv {
        path: PathBuf,
        line: u64,
        source: ::csv::Error,
    },
    #[error("{path}: no column {column:?} for the setup's {role} (columns: {available})")]
    MissingColumn {
        path: PathBuf,
        column: String,
        role: &'static str,
        available: String,
    },
    #[error("{path}: column {column:?} appears more than once")]
    DuplicateColumn { path: PathBuf, column: String },
    #[error("{path}: line {line}, column {column:?}: {what}")]
    BadValue {
        path: PathBuf,
        line: u64,
        column: String,
        what: String,
    },
    #[error("{path}: line {line}: {what}")]
    BadTime {
        path: PathBuf,
        line: u64,
        what: String,
    },
    #[error("{path}: {what}")]
    TooFewRows { path: PathBuf, what: String },
    #[error("{option}: {reason}")]
    BadOption {
        option: &'static str,
        reason: String,
    },
    #[error(transparent)]
    Mcap(#[from] McapIoError),
    #[error(transparent)]
    Setup(#[from] crate::setup::SetupError),
}

/// How to read the CSV.
#[derive(Debug, Clone, Default)]
pub struct ImportOptions {
    /// The time column's name; `None` looks for [`TIME_COLUMN_NAMES`], then uses `dt_s`.
    pub time_column: Option<String>,
    /// Sample interval (s) when the file has no time column; default the setup's `dt_s`.
    pub dt_s: Option<f64>,
    /// Field delimiter; `None` detects it from the header.
    pub delimiter: Option<u8>,
    pub encoding: Option<FrameEncoding>,
}

/// What an import wrote.
#[derive(Debug, Clone, Serialize)]
pub struct ImportSummary {
    pub source: PathBuf,
    pub out: PathBuf,
    pub samples: usize,
    /// Sample interval of the recording (s).
    pub dt_s: f64,
    /// Where `dt_s` came from: `time column "t"`, `--dt` or `setup`.
    pub dt_from: String,
    /// True when the attached setup's `dt_s` was set to the data's interval.
    pub setup_dt_replaced: bool,
    /// Columns of the file that are neither time nor a setup channel.
    pub ignored_columns: Vec<String>,
}

/// Reads `csv_path` and writes the recording `out` (see the module docs).
pub fn import_csv(
    setup: &Setup,
    csv_path: &Path,
    out: &Path,
    opts: &ImportOptions,
) -> Result<ImportSummary, ImportError> {
    let path = csv_path.to_path_buf();
    if let Some(dt) = opts.dt_s
        && !(dt.is_finite() && dt > 0.0)
    {
        return Err(ImportError::BadOption {
            option: "--dt",
            reason: format!("{dt} is not a positive number of seconds"),
        });
    }
    let delimiter = match opts.delimiter {
        Some(d) => d,
        None => detect_delimiter(&path)?,
    };
    let file = std::fs::File::open(&path).map_err(|source| ImportError::Io {
        path: path.clone(),
        source,
    })?;
    let mut reader = ::csv::ReaderBuilder::new()
        .delimiter(delimiter)
        .comment(Some(b'#'))
        .trim(::csv::Trim::All)
        .flexible(false)
        .from_reader(std::io::BufReader::new(file));
    let csv_error = |path: &Path, source: ::csv::Error| {
        let line = source.position().map_or(0, |p| p.line());
        ImportError::Csv {
            path: path.to_path_buf(),
            line,
            source,
        }
    };
    let header: Vec<String> = reader
        .headers()
        .map_err(|e| csv_error(&path, e))?
        .iter()
        .map(str::to_string)
        .collect();
    for (i, name) in header.iter().enumerate() {
        if header[..i].contains(name) {
            return Err(ImportError::DuplicateColumn {
                path: path.clone(),
                column: name.clone(),
            });
        }
    }
    let find = |name: &str| header.iter().position(|h| h == name);
    let available = header.join(", ");
    let column_of = |name: &str, role: &'static str| {
        find(name).ok_or_else(|| ImportError::MissingColumn {
            path: path.clone(),
            column: name.to_string(),
            role,
            available: available.clone(),
        })
    };
    let excitation: Vec<usize> = setup
        .excitation
        .iter()
        .map(|e| column_of(&e.name, "excitation channel"))
        .collect::<Result<_, _>>()?;
    let response: Vec<usize> = setup
        .sensors
        .iter()
        .map(|s| column_of(&s.name, "sensor"))
        .collect::<Result<_, _>>()?;
    let time = match &opts.time_column {
        Some(name) => Some(column_of(name, "time column (--time-column)")?),
        None => header
            .iter()
            .position(|h| TIME_COLUMN_NAMES.iter().any(|t| h.eq_ignore_ascii_case(t))),
    };
    if time.is_some() && opts.dt_s.is_some() {
        return Err(ImportError::BadOption {
            option: "--dt",
            reason: "the file has a time column; --dt is only for files without one".into(),
        });
    }
    let ignored_columns: Vec<String> = header
        .iter()
        .enumerate()
        .filter(|(i, _)| Some(*i) != time && !excitation.contains(i) && !response.contains(i))
        .map(|(_, h)| h.clone())
        .collect();

    // Parse rows lazily: the first two fix the interval, the rest stream to the writer.
    let mut records = reader.into_records();
    let next_row =
        |records: &mut ::csv::StringRecordsIntoIter<_>| -> Result<Option<Row>, ImportError> {
            let Some(record) = records.next() else {
                return Ok(None);
            };
            let record = record.map_err(|e| csv_error(&path, e))?;
            let line = record.position().map_or(0, |p| p.line());
            let value = |col: usize| -> Result<f64, ImportError> {
                let text = record.get(col).unwrap_or_default();
                let bad = |what: String| ImportError::BadValue {
                    path: path.clone(),
                    line,
                    column: header[col].clone(),
                    what,
                };
                let v: f64 = text
                    .parse()
                    .map_err(|_| bad(format!("`{text}` is not a number")))?;
                if !v.is_finite() {
                    return Err(bad(format!("{text} is not finite")));
                }
                Ok(v)
            };
            Ok(Some(Row {
                line,
                t_s: time.map(value).transpose()?,
                excitation: excitation
                    .iter()
                    .map(|&c| value(c))
                    .collect::<Result<_, _>>()?,
                response: response
                    .iter()
                    .map(|&c| value(c))
                    .collect::<Result<_, _>>()?,
            }))
        };
    let first = next_row(&mut records)?;
    let second = next_row(&mut records)?;
    let (Some(first), Some(second)) = (first, second) else {
        return Err(ImportError::TooFewRows {
            path: path.clone(),
            what: "fewer than two data rows".into(),
        });
    };
    let (dt_s, dt_from) = match (first.t_s, second.t_s) {
        (Some(t0), Some(t1)) => {
            let dt = t1 - t0;
            if dt.is_nan() || dt <= 0.0 {
                return Err(ImportError::BadTime {
                    path: path.clone(),
                    line: second.line,
                    what: format!("time {t1} s does not follow {t0} s"),
                });
            }
            let name = time.map(|c| header[c].clone()).unwrap_or_default();
            // A factor of ten or more from the setup's step is a unit slip (a column in
            // milliseconds is 1000×), not a model made for another rate: refused, as its
            // replay would identify nonsense at exit 0.
            let ratio = dt / setup.dt_s;
            // Both ends refused, with room for the round-off of times such as 0.001, 0.011.
            if ratio <= 0.1 * (1.0 + 1e-6) || ratio >= 10.0 * (1.0 - 1e-6) {
                return Err(ImportError::BadTime {
                    path: path.clone(),
                    line: second.line,
                    what: format!(
                        "the time column {name:?} gives a sample interval of {dt:e} s, {ratio:.4}× the setup's dt_s = {:e} s: the column must be in seconds (one in milliseconds gives 1000×); if the data really are at this rate, set the setup's dt_s to it",
                        setup.dt_s
                    ),
                });
            }
            (dt, format!("time column {name:?}"))
        }
        _ => match opts.dt_s {
            Some(dt) => (dt, "--dt".to_string()),
            None => (setup.dt_s, "setup".to_string()),
        },
    };
    let setup_dt_replaced = (dt_s - setup.dt_s).abs() > 1e-9 * setup.dt_s;
    let attached = setup.at_rate(dt_s)?;

    let mut writer = RecordingWriter::create(out, opts.encoding.unwrap_or(FrameEncoding::Binary))?;
    writer.attach_setup_of(&attached)?;
    let facts: BTreeMap<String, String> = [
        (
            "generator",
            format!("jointid import {}", env!("CARGO_PKG_VERSION")),
        ),
        ("source", csv_path.display().to_string()),
        ("dt_s", format!("{dt_s:e}")),
        ("dt_from", dt_from.clone()),
    ]
    .into_iter()
    .map(|(k, v)| (k.to_string(), v))
    .collect();
    writer.write_metadata(RECORDING_METADATA, &facts)?;
    writer.declare_inputs(
        &crate::app::excitation_channels(setup),
        &crate::app::response_channels(setup),
    )?;
    let t0 = first.t_s.unwrap_or(0.0);
    let mut samples = 0usize;
    let mut write = |writer: &mut RecordingWriter, row: Row| -> Result<(), ImportError> {
        let sample = samples as u64;
        if let Some(t) = row.t_s {
            let expected = t0 + samples as f64 * dt_s;
            if (t - expected).abs() > 0.01 * dt_s {
                return Err(ImportError::BadTime {
                    path: path.clone(),
                    line: row.line,
                    what: format!(
                        "time {t} s is off the even grid (sample {sample} is due at {expected} s, interval {dt_s:e} s); resample the file to a constant rate"
                    ),
                });
            }
        }
        let t_ns = (samples as f64 * dt_s * 1e9).round() as u64;
        writer.write_excitation(&Frame {
            sample,
            t_ns,
            values: row.excitation,
        })?;
        writer.write_response(&Frame {
            sample,
            t_ns,
            values: row.response,
        })?;
        samples += 1;
        Ok(())
    };
    // On any error the writer is dropped unfinished: `out` is never created (the partial
    // file stays beside it for inspection).
    write(&mut writer, first)?;
    write(&mut writer, second)?;
    while let Some(row) = next_row(&mut records)? {
        write(&mut writer, row)?;
    }
    writer.finish()?;
    Ok(ImportSummary {
        source: csv_path.to_path_buf(),
        out: out.to_path_buf(),
        samples,
        dt_s,
        dt_from,
        setup_dt_replaced,
        ignored_columns,
    })
}

struct Row {
    line: u64,
    t_s: Option<f64>,
    excitation: Vec<f64>,
    response: Vec<f64>,
}

/// `,` unless the first non-comment line has none and has `;` or a tab.
fn detect_delimiter(path: &Path) -> Result<u8, ImportError> {
    use std::io::BufRead;
    let file = std::fs::File::open(path).map_err(|source| ImportError::Io {
        path: path.to_path_buf(),
        source,
    })?;
    let mut reader = std::io::BufReader::new(file).take(1 << 20);
    let mut line = String::new();
    loop {
        line.clear();
        let n = reader
            .read_line(&mut line)
            .map_err(|source| ImportError::Io {
                path: path.to_path_buf(),
                source,
            })?;
        if n == 0 || !line.trim_start().starts_with('#') {
            break;
        }
    }
    Ok(if line.contains(',') {
        b','
    } else if line.contains(';') {
        b';'
    } else if line.contains('\t') {
        b'\t'
    } else {
        b','
    })
}
