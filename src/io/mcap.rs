//! MCAP recording I/O: writes and reads `jointid` recordings.
//!
//! # File contract
//!
//! A recording is an [MCAP](https://mcap.dev) file. Input data:
//!
//! - Topics `/jointid/excitation` and `/jointid/response`; each message is one [`Frame`].
//!   Each channel's MCAP `metadata` map holds `channels` (comma-separated channel names, e.g.
//!   `node1.force,node2.force`) and `units` (comma-separated units, same count). Names and
//!   units are non-empty and contain no comma. Every frame carries exactly one value per
//!   listed channel.
//! - JSON encoding ([`FrameEncoding::Json`]): message encoding `json`, schema encoding
//!   `jsonschema`, schema name `jointid.Frame` (see [`frame_json_schema`]). Message bytes are
//!   `{"sample":12,"t_ns":1000,"values":[...]}`; Foxglove can plot them. JSON cannot carry
//!   NaN or infinities: writing a non-finite value is an error, and a `null` in `values` reads
//!   back as a [`McapIoError::NonFinite`] naming the sample and channel.
//! - Binary encoding ([`FrameEncoding::Binary`]): message encoding `jointid.frame.v1`, no
//!   schema (schema id 0). Little-endian `u64 sample`, `u64 t_ns`, then `N` `f64` values, so
//!   the payload is `16 + 8*N` bytes. Non-finite values are rejected on write and on read too.
//! - Every message has `log_time = publish_time = t_ns` and `sequence = sample as u32`
//!   (wrapping).
//! - Within each input topic, sample indices strictly increase and `t_ns` never decreases.
//! - The run setup (TOML text) is the attachment `setup.toml`, media type `application/toml`
//!   (log and create time 0, so identical runs give identical files). A setup with
//!   `[model.matrix_market]` also has its model's files attached as read, one per key:
//!   `model.matrix_market.mass`, `.stiffness`, `.damping` (if any), media type
//!   `text/x-matrix-market`, and `model.matrix_market.dof_map`, `text/csv`; a replay of the
//!   attached setup uses them, not the files its paths name (recordings made before
//!   2026-11-29 carry none: their matrices are read beside the recording).
//! - Metadata record `jointid.truth`: parameter key (e.g. `joint6.u`) to value as a decimal
//!   string (optional; values must parse as finite `f64`). Metadata record
//!   `jointid.recording`: free-form facts (generator, scenario, dt_s, substeps, noise, seed...).
//!
//! Output topics (`/jointid/residuals`, `/jointid/states`, `/jointid/parameters`,
//! `/jointid/diagnostics`, or any other non-input topic) are JSON messages with a `jsonschema`
//! schema each, registered on first use of the topic ([`RecordingWriter::write_output`]).
//! The readers here skip them; read them with any MCAP reader.
//!
//! # Writing
//!
//! [`RecordingWriter`] writes `<path>.partial` and renames it to `<path>` in
//! [`RecordingWriter::finish`], so a file at `<path>` is always complete. Dropped without
//! `finish`, it still finalises `<path>.partial` (summary and footer, best effort) and leaves
//! it there. Chunks are zstd-compressed (the mcap crate's default), about 1 MiB uncompressed
//! each; `declare_inputs` closes a first small chunk holding just the schema and channels, so
//! any file cut after it still identifies its frames. A process killed mid-chunk leaves that
//! chunk with a placeholder header and only what its buffers had flushed; the reader salvages
//! the complete messages in it, and loses at most that chunk.
//!
//! JSON floats round-trip bit-exactly only with `serde_json`'s `float_roundtrip` feature
//! (without it, parsing may be off by one ulp); the tests check this.
//!
//! # Reading
//!
//! [`read_recording`] loads everything; [`stream_frames`] yields frames one at a time. Both
//! read the file sequentially (no memory map: a file that is truncated while mapped faults
//! the process), holding at most one chunk in memory, and check every chunk's CRC before
//! using its messages. A truncated file (no footer, or cut mid-record) is not an error: every
//! complete message before the damage is recovered, including those at the start of a cut
//! chunk, and the damage is described in [`Recording::damage`] / [`FrameStream::damage`].
//! A CRC mismatch, a malformed frame, or a rule above being broken is an error.

use std::collections::{BTreeMap, HashMap, VecDeque};
use std::fs::{self, File};
use std::io::{BufReader, BufWriter, Read, Seek};
use std::path::{Path, PathBuf};

use ::mcap::records::{self, MessageHeader, Metadata, Record, op};
use ::mcap::sans_io::{LinearReadEvent, LinearReader, LinearReaderOptions};
use ::mcap::{Attachment, McapError, WriteOptions, Writer};
use serde::{Deserialize, Serialize};
use serde_json::Value;

/// One sample of a multi-channel stream. `values` are in channel order (SI units).
#[derive(Debug, Clone, PartialEq)]
pub struct Frame {
    pub sample: u64,
    pub t_ns: u64,
    pub values: Vec<f64>,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum FrameEncoding {
    Json,
    Binary,
}

pub const EXCITATION_TOPIC: &str = "/jointid/excitation";
pub const RESPONSE_TOPIC: &str = "/jointid/response";
pub const RESIDUALS_TOPIC: &str = "/jointid/residuals";
pub const STATES_TOPIC: &str = "/jointid/states";
pub const PARAMETERS_TOPIC: &str = "/jointid/parameters";
pub const DIAGNOSTICS_TOPIC: &str = "/jointid/diagnostics";
/// Tracked parameters over time (forgetting fit solved periodically), one message per solve.
pub const TRACK_TOPIC: &str = "/jointid/track";
pub const FRAME_SCHEMA_NAME: &str = "jointid.Frame";
pub const JSON_MESSAGE_ENCODING: &str = "json";
pub const JSON_SCHEMA_ENCODING: &str = "jsonschema";
pub const BINARY_MESSAGE_ENCODING: &str = "jointid.frame.v1";
pub const CHANNELS_KEY: &str = "channels";
pub const UNITS_KEY: &str = "units";
pub const SETUP_ATTACHMENT_NAME: &str = "setup.toml";
pub const SETUP_MEDIA_TYPE: &str = "application/toml";
/// Prefix of the attachments that carry an external model's files (the key follows).
pub const MODEL_FILE_ATTACHMENT_PREFIX: &str = "model.matrix_market.";
pub const TRUTH_METADATA: &str = "jointid.truth";
pub const RECORDING_METADATA: &str = "jointid.recording";

/// Largest chunk (compressed or decompressed) or record the reader accepts: writers use
/// ~1 MiB chunks, and a corrupt size field must not make a small file allocate gigabytes.
const CHUNK_SIZE_LIMIT: usize = 128 << 20;
/// Largest summary section read to find the chunk index (tens of bytes per chunk).
const SUMMARY_SIZE_LIMIT: u64 = 64 << 20;
/// Opcode and record length in front of every MCAP record.
const RECORD_PREFIX_LEN: u64 = 9;

/// The two input topics of a recording.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum InputTopic {
    Excitation,
    Response,
}

impl InputTopic {
    pub const ALL: [InputTopic; 2] = [InputTopic::Excitation, InputTopic::Response];

    /// The MCAP topic name.
    pub fn topic(self) -> &'static str {
        match self {
            InputTopic::Excitation => EXCITATION_TOPIC,
            InputTopic::Response => RESPONSE_TOPIC,
        }
    }

    pub fn from_topic(topic: &str) -> Option<Self> {
        Self::ALL.into_iter().find(|t| t.topic() == topic)
    }

    fn index(self) -> usize {
        match self {
            InputTopic::Excitation => 0,
            InputTopic::Response => 1,
        }
    }
}

/// Names and units of a topic's channels, in value order.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct ChannelInfo {
    pub names: Vec<String>,
    pub units: Vec<String>,
}

impl ChannelInfo {
    fn check(&self, path: &Path, topic: &str) -> Result<(), McapIoError> {
        let bad = |what: String| McapIoError::BadChannelInfo {
            path: path.to_path_buf(),
            topic: topic.to_string(),
            what,
        };
        if self.names.len() != self.units.len() {
            return Err(bad(format!(
                "{} channel names but {} units",
                self.names.len(),
                self.units.len()
            )));
        }
        for (kind, list) in [("channel name", &self.names), ("unit", &self.units)] {
            for (index, item) in list.iter().enumerate() {
                if item.is_empty() || item.contains(',') {
                    return Err(bad(format!(
                        "{kind} #{index} {item:?} is empty or contains a comma"
                    )));
                }
            }
        }
        for (index, name) in self.names.iter().enumerate() {
            if self.names[..index].contains(name) {
                return Err(bad(format!("channel name {name:?} appears twice")));
            }
        }
        Ok(())
    }

    fn to_metadata(&self) -> BTreeMap<String, String> {
        BTreeMap::from([
            (CHANNELS_KEY.to_string(), self.names.join(",")),
            (UNITS_KEY.to_string(), self.units.join(",")),
        ])
    }

    fn from_metadata(
        path: &Path,
        topic: &str,
        metadata: &BTreeMap<String, String>,
    ) -> Result<Self, McapIoError> {
        let list = |key: &str| -> Result<Vec<String>, McapIoError> {
            let text = metadata
                .get(key)
                .ok_or_else(|| McapIoError::BadChannelInfo {
                    path: path.to_path_buf(),
                    topic: topic.to_string(),
                    what: format!("channel metadata has no {key:?} key"),
                })?;
            Ok(if text.is_empty() {
                Vec::new()
            } else {
                text.split(',').map(str::to_string).collect()
            })
        };
        let info = ChannelInfo {
            names: list(CHANNELS_KEY)?,
            units: list(UNITS_KEY)?,
        };
        info.check(path, topic)?;
        Ok(info)
    }
}

/// Everything that can go wrong reading or writing a recording. Each variant names the file
/// and, where it applies, the topic, sample and channel.
#[derive(Debug, thiserror::Error)]
pub enum McapIoError {
    #[error("{path}: {source}")]
    Io {
        path: PathBuf,
        source: std::io::Error,
    },
    #[error("{path}: MCAP error: {source}")]
    Mcap { path: PathBuf, source: McapError },
    #[error("{path}: record at byte {offset} is damaged: {source}")]
    Corrupt {
        path: PathBuf,
        offset: u64,
        source: McapError,
    },
    #[error(
        "{path}: chunk at byte {offset} failed its CRC check (stored {saved:#010x}, computed {calculated:#010x})"
    )]
    ChunkCrc {
        path: PathBuf,
        offset: u64,
        saved: u32,
        calculated: u32,
    },
    /// `truncated`: where the file stops, when it was cut short before the channel (then
    /// the topic is not missing from the recording, the file is damaged).
    #[error(
        "{path}: no channel for topic {topic}{}",
        truncated.as_deref().map(|t| format!(": the recording is damaged, truncated before it at {t}")).unwrap_or_default()
    )]
    MissingTopic {
        path: PathBuf,
        topic: String,
        truncated: Option<String>,
    },
    #[error(
        "{path}: topic {topic} has message encoding {encoding:?}; expected \"json\" or \"jointid.frame.v1\""
    )]
    UnsupportedEncoding {
        path: PathBuf,
        topic: String,
        encoding: String,
    },
    #[error("{path}: topic {topic}: bad channel metadata: {what}")]
    BadChannelInfo {
        path: PathBuf,
        topic: String,
        what: String,
    },
    #[error("{path}: {topic} sample {sample}: channel {channel} (#{index}) is not finite")]
    NonFinite {
        path: PathBuf,
        topic: String,
        sample: u64,
        channel: String,
        index: usize,
    },
    #[error(
        "{path}: {topic} message with sequence {sequence} at log time {log_time} ns is {len} bytes; a binary frame is 16 + 8*N bytes"
    )]
    BadFrameLength {
        path: PathBuf,
        topic: String,
        sequence: u32,
        log_time: u64,
        len: usize,
    },
    #[error("{path}: {topic} message with sequence {sequence} at log time {log_time} ns: {what}")]
    BadFrame {
        path: PathBuf,
        topic: String,
        sequence: u32,
        log_time: u64,
        what: String,
    },
    #[error(
        "{path}: {topic} sample {sample} has {got} values but the channel metadata lists {expected} channels"
    )]
    WrongChannelCount {
        path: PathBuf,
        topic: String,
        sample: u64,
        expected: usize,
        got: usize,
    },
    #[error(
        "{path}: {topic} sample {sample}: time goes backwards ({got_ns} ns after {prev_ns} ns)"
    )]
    NonMonotonicTime {
        path: PathBuf,
        topic: String,
        sample: u64,
        prev_ns: u64,
        got_ns: u64,
    },
    #[error(
        "{path}: {topic} sample {sample} follows sample {prev}; sample indices must strictly increase"
    )]
    SampleNotIncreasing {
        path: PathBuf,
        topic: String,
        sample: u64,
        prev: u64,
    },
    #[error(
        "{path}: metadata jointid.truth: {key:?} has value {value:?}, which is not a finite number"
    )]
    BadTruth {
        path: PathBuf,
        key: String,
        value: String,
    },
    #[error("{path}: attachment setup.toml: {what}")]
    BadSetup { path: PathBuf, what: String },
    #[error("{path}: attachment {name}: {what}")]
    BadModelFile {
        path: PathBuf,
        name: String,
        what: String,
    },
    #[error("{path}: topic {topic}: cannot serialise the message as JSON: {source}")]
    Json {
        path: PathBuf,
        topic: String,
        source: serde_json::Error,
    },
    #[error("{path}: {what}")]
    Usage { path: PathBuf, what: String },
}

fn io_error(path: &Path) -> impl FnOnce(std::io::Error) -> McapIoError + '_ {
    move |source| McapIoError::Io {
        path: path.to_path_buf(),
        source,
    }
}

fn mcap_error(path: &Path) -> impl FnOnce(McapError) -> McapIoError + '_ {
    move |source| McapIoError::Mcap {
        path: path.to_path_buf(),
        source,
    }
}

fn usage(path: &Path, what: impl Into<String>) -> McapIoError {
    McapIoError::Usage {
        path: path.to_path_buf(),
        what: what.into(),
    }
}

/// The JSON Schema of a [`Frame`] message (schema `jointid.Frame`, encoding `jsonschema`).
pub fn frame_json_schema() -> Value {
    serde_json::json!({
        "title": FRAME_SCHEMA_NAME,
        "description": "One sample of a multi-channel jointid stream. values are in channel \
                        order, SI units; see the channel metadata keys channels and units.",
        "type": "object",
        "properties": {
            "sample": { "type": "integer", "minimum": 0, "description": "sample index" },
            "t_ns": { "type": "integer", "minimum": 0, "description": "time in nanoseconds" },
            "values": { "type": "array", "items": { "type": "number" } }
        },
        "required": ["sample", "t_ns", "values"]
    })
}

#[derive(Serialize)]
struct JsonFrameOut<'a> {
    sample: u64,
    t_ns: u64,
    values: &'a [f64],
}

#[derive(Deserialize)]
struct JsonFrameIn {
    sample: u64,
    t_ns: u64,
    values: Vec<Option<f64>>,
}

/// Checks a frame's value count against its channels and that every value is finite.
fn check_values(
    path: &Path,
    topic: &str,
    info: &ChannelInfo,
    frame: &Frame,
) -> Result<(), McapIoError> {
    if frame.values.len() != info.names.len() {
        return Err(McapIoError::WrongChannelCount {
            path: path.to_path_buf(),
            topic: topic.to_string(),
            sample: frame.sample,
            expected: info.names.len(),
            got: frame.values.len(),
        });
    }
    if let Some(index) = frame.values.iter().position(|v| !v.is_finite()) {
        return Err(McapIoError::NonFinite {
            path: path.to_path_buf(),
            topic: topic.to_string(),
            sample: frame.sample,
            channel: info
                .names
                .get(index)
                .cloned()
                .unwrap_or_else(|| format!("#{index}")),
            index,
        });
    }
    Ok(())
}

/// Per-topic ordering state: samples strictly increase, time never goes backwards.
#[derive(Debug, Clone, Copy, Default)]
struct TopicProgress {
    count: usize,
    last_sample: Option<u64>,
    last_t_ns: u64,
}

impl TopicProgress {
    fn check(&self, path: &Path, topic: &str, frame: &Frame) -> Result<(), McapIoError> {
        let Some(prev) = self.last_sample else {
            return Ok(());
        };
        if frame.sample <= prev {
            return Err(McapIoError::SampleNotIncreasing {
                path: path.to_path_buf(),
                topic: topic.to_string(),
                sample: frame.sample,
                prev,
            });
        }
        if frame.t_ns < self.last_t_ns {
            return Err(McapIoError::NonMonotonicTime {
                path: path.to_path_buf(),
                topic: topic.to_string(),
                sample: frame.sample,
                prev_ns: self.last_t_ns,
                got_ns: frame.t_ns,
            });
        }
        Ok(())
    }

    fn advance(&mut self, frame: &Frame) {
        self.count += 1;
        self.last_sample = Some(frame.sample);
        self.last_t_ns = frame.t_ns;
    }
}

// ---------------------------------------------------------------------------------------------
// Writing
// ---------------------------------------------------------------------------------------------

struct InputWriteState {
    channel_id: u16,
    info: ChannelInfo,
    progress: TopicProgress,
}

struct OutputChannel {
    channel_id: u16,
    schema_name: String,
    schema: Value,
    sequence: u32,
}

/// Writes a recording; see the module docs for the file contract.
pub struct RecordingWriter {
    path: PathBuf,
    partial: PathBuf,
    encoding: FrameEncoding,
    writer: Writer<BufWriter<File>>,
    inputs: Option<[InputWriteState; 2]>,
    outputs: HashMap<String, OutputChannel>,
    setup_attached: bool,
}

/// `<path>.partial`.
pub fn partial_path(path: &Path) -> PathBuf {
    let mut name = path.as_os_str().to_owned();
    name.push(".partial");
    PathBuf::from(name)
}

impl RecordingWriter {
    /// Writes to `<path>.partial` and renames to `path` in `finish()`, so a crash never leaves
    /// a file that looks complete. If dropped without finish, it still finalises the partial
    /// file (best effort) and leaves it as `<path>.partial`. An existing `path` is replaced
    /// only by `finish()`.
    pub fn create(path: &Path, encoding: FrameEncoding) -> Result<Self, McapIoError> {
        Self::create_with_options(path, encoding, WriteOptions::new())
    }

    /// Like [`Self::create`] with explicit mcap writer options (compression, chunk size).
    pub fn create_with_options(
        path: &Path,
        encoding: FrameEncoding,
        options: WriteOptions,
    ) -> Result<Self, McapIoError> {
        let partial = partial_path(path);
        // A missing directory is the output's problem, not the temporary file's.
        if let Some(dir) = path.parent().filter(|d| !d.as_os_str().is_empty())
            && !dir.is_dir()
        {
            return Err(io_error(path)(std::io::Error::new(
                std::io::ErrorKind::NotFound,
                format!("the directory {} does not exist", dir.display()),
            )));
        }
        let file = File::create(&partial).map_err(io_error(&partial))?;
        let writer = options
            .create(BufWriter::new(file))
            .map_err(mcap_error(&partial))?;
        Ok(Self {
            path: path.to_path_buf(),
            partial,
            encoding,
            writer,
            inputs: None,
            outputs: HashMap::new(),
            setup_attached: false,
        })
    }

    /// The file being written (`<path>.partial`).
    pub fn partial_path(&self) -> &Path {
        &self.partial
    }

    /// Attaches the run setup as `setup.toml` (once per recording).
    pub fn attach_setup(&mut self, setup_toml: &str) -> Result<(), McapIoError> {
        if self.setup_attached {
            return Err(usage(&self.partial, "setup.toml is already attached"));
        }
        self.writer
            .attach(&Attachment {
                log_time: 0,
                create_time: 0,
                name: SETUP_ATTACHMENT_NAME.to_string(),
                media_type: SETUP_MEDIA_TYPE.to_string(),
                data: setup_toml.as_bytes().into(),
            })
            .map_err(mcap_error(&self.partial))?;
        self.setup_attached = true;
        Ok(())
    }

    /// Attaches a setup: its text as `setup.toml` and, for an external model, its files
    /// ([`Self::attach_model_files`]) — what a recording needs to be replayed anywhere.
    pub fn attach_setup_of(&mut self, setup: &crate::setup::Setup) -> Result<(), McapIoError> {
        self.attach_setup(&setup.toml_text)?;
        match setup.model_files() {
            Some(files) => self.attach_model_files(files),
            None => Ok(()),
        }
    }

    /// Attaches the text of an external model's files (`[model.matrix_market]`), one
    /// attachment per key, after [`Self::attach_setup`] of the setup that names them.
    pub fn attach_model_files(
        &mut self,
        files: &crate::matrix_market::ModelFiles,
    ) -> Result<(), McapIoError> {
        if !self.setup_attached {
            return Err(usage(
                &self.partial,
                "model files are attached after the setup that names them",
            ));
        }
        for (key, text) in files.entries() {
            let media_type = if key == "dof_map" {
                "text/csv"
            } else {
                "text/x-matrix-market"
            };
            self.writer
                .attach(&Attachment {
                    log_time: 0,
                    create_time: 0,
                    name: format!("{MODEL_FILE_ATTACHMENT_PREFIX}{key}"),
                    media_type: media_type.to_string(),
                    data: text.as_bytes().into(),
                })
                .map_err(mcap_error(&self.partial))?;
        }
        Ok(())
    }

    /// Writes a metadata record. For `jointid.truth`, every value must parse as a finite
    /// `f64` (write them with `f64`'s `Display`, which round-trips exactly).
    pub fn write_metadata(
        &mut self,
        name: &str,
        map: &BTreeMap<String, String>,
    ) -> Result<(), McapIoError> {
        if name == TRUTH_METADATA {
            for (key, value) in map {
                parse_truth(&self.partial, key, value)?;
            }
        }
        self.writer
            .write_metadata(&Metadata {
                name: name.to_string(),
                metadata: map.clone(),
            })
            .map_err(mcap_error(&self.partial))
    }

    /// Registers the two input channels with their names and units. Call once, before any
    /// frame.
    pub fn declare_inputs(
        &mut self,
        excitation: &ChannelInfo,
        response: &ChannelInfo,
    ) -> Result<(), McapIoError> {
        if self.inputs.is_some() {
            return Err(usage(&self.partial, "input channels are already declared"));
        }
        excitation.check(&self.partial, EXCITATION_TOPIC)?;
        response.check(&self.partial, RESPONSE_TOPIC)?;
        let (schema_id, message_encoding) = match self.encoding {
            FrameEncoding::Json => {
                let schema = serde_json::to_vec(&frame_json_schema()).map_err(|source| {
                    McapIoError::Json {
                        path: self.partial.clone(),
                        topic: EXCITATION_TOPIC.to_string(),
                        source,
                    }
                })?;
                let id = self
                    .writer
                    .add_schema(FRAME_SCHEMA_NAME, JSON_SCHEMA_ENCODING, &schema)
                    .map_err(mcap_error(&self.partial))?;
                (id, JSON_MESSAGE_ENCODING)
            }
            FrameEncoding::Binary => (0, BINARY_MESSAGE_ENCODING),
        };
        let mut add = |topic: &str, info: &ChannelInfo| -> Result<InputWriteState, McapIoError> {
            let channel_id = self
                .writer
                .add_channel(schema_id, topic, message_encoding, &info.to_metadata())
                .map_err(mcap_error(&self.partial))?;
            Ok(InputWriteState {
                channel_id,
                info: info.clone(),
                progress: TopicProgress::default(),
            })
        };
        let inputs = [
            add(EXCITATION_TOPIC, excitation)?,
            add(RESPONSE_TOPIC, response)?,
        ];
        // Close the chunk holding the schema and channels, so that a file cut anywhere after
        // it still says what its frames are, even when a compressed chunk is lost whole.
        self.writer.flush().map_err(mcap_error(&self.partial))?;
        self.inputs = Some(inputs);
        Ok(())
    }

    pub fn write_excitation(&mut self, frame: &Frame) -> Result<(), McapIoError> {
        self.write_frame(InputTopic::Excitation, frame)
    }

    pub fn write_response(&mut self, frame: &Frame) -> Result<(), McapIoError> {
        self.write_frame(InputTopic::Response, frame)
    }

    /// Writes one frame after checking it against the contract (value count, finite values,
    /// increasing samples, non-decreasing time); a rejected frame writes nothing.
    pub fn write_frame(&mut self, topic: InputTopic, frame: &Frame) -> Result<(), McapIoError> {
        let Some(inputs) = self.inputs.as_mut() else {
            return Err(usage(
                &self.partial,
                "declare_inputs must be called before writing frames",
            ));
        };
        let input = &mut inputs[topic.index()];
        check_values(&self.partial, topic.topic(), &input.info, frame)?;
        input.progress.check(&self.partial, topic.topic(), frame)?;
        let data = match self.encoding {
            FrameEncoding::Json => serde_json::to_vec(&JsonFrameOut {
                sample: frame.sample,
                t_ns: frame.t_ns,
                values: &frame.values,
            })
            .map_err(|source| McapIoError::Json {
                path: self.partial.clone(),
                topic: topic.topic().to_string(),
                source,
            })?,
            FrameEncoding::Binary => {
                let mut data = Vec::with_capacity(16 + 8 * frame.values.len());
                data.extend_from_slice(&frame.sample.to_le_bytes());
                data.extend_from_slice(&frame.t_ns.to_le_bytes());
                for value in &frame.values {
                    data.extend_from_slice(&value.to_le_bytes());
                }
                data
            }
        };
        let header = MessageHeader {
            channel_id: input.channel_id,
            sequence: frame.sample as u32,
            log_time: frame.t_ns,
            publish_time: frame.t_ns,
        };
        self.writer
            .write_to_known_channel(&header, &data)
            .map_err(mcap_error(&self.partial))?;
        input.progress.advance(frame);
        Ok(())
    }

    /// Writes one JSON message on an output topic, registering the topic's schema and channel
    /// on first use. Later messages on the topic must give the same schema name and schema.
    /// Note that `serde_json` writes non-finite floats inside `msg` as `null`.
    pub fn write_output<T: Serialize>(
        &mut self,
        topic: &str,
        schema_name: &str,
        schema: &Value,
        t_ns: u64,
        msg: &T,
    ) -> Result<(), McapIoError> {
        if topic.is_empty() || InputTopic::from_topic(topic).is_some() {
            return Err(usage(
                &self.partial,
                format!("{topic:?} cannot be used as an output topic"),
            ));
        }
        let json_error = |source| McapIoError::Json {
            path: self.partial.clone(),
            topic: topic.to_string(),
            source,
        };
        if !self.outputs.contains_key(topic) {
            let schema_bytes = serde_json::to_vec(schema).map_err(json_error)?;
            let schema_id = self
                .writer
                .add_schema(schema_name, JSON_SCHEMA_ENCODING, &schema_bytes)
                .map_err(mcap_error(&self.partial))?;
            let channel_id = self
                .writer
                .add_channel(schema_id, topic, JSON_MESSAGE_ENCODING, &BTreeMap::new())
                .map_err(mcap_error(&self.partial))?;
            self.outputs.insert(
                topic.to_string(),
                OutputChannel {
                    channel_id,
                    schema_name: schema_name.to_string(),
                    schema: schema.clone(),
                    sequence: 0,
                },
            );
        }
        let Some(output) = self.outputs.get(topic) else {
            return Err(usage(&self.partial, format!("{topic} is not registered")));
        };
        if output.schema_name != schema_name || output.schema != *schema {
            return Err(usage(
                &self.partial,
                format!(
                    "topic {topic} was registered with schema {}; got schema {schema_name} or a different schema body",
                    output.schema_name
                ),
            ));
        }
        self.write_registered_output(topic, t_ns, msg)
    }

    /// Whether `topic` has been registered as an output by [`Self::write_output`].
    pub fn has_output(&self, topic: &str) -> bool {
        self.outputs.contains_key(topic)
    }

    /// Writes one JSON message on an output topic already registered by
    /// [`Self::write_output`] (no schema comparison: the per-sample path).
    pub fn write_registered_output<T: Serialize>(
        &mut self,
        topic: &str,
        t_ns: u64,
        msg: &T,
    ) -> Result<(), McapIoError> {
        let data = serde_json::to_vec(msg).map_err(|source| McapIoError::Json {
            path: self.partial.clone(),
            topic: topic.to_string(),
            source,
        })?;
        let Some(output) = self.outputs.get_mut(topic) else {
            return Err(usage(&self.partial, format!("{topic} is not registered")));
        };
        let header = MessageHeader {
            channel_id: output.channel_id,
            sequence: output.sequence,
            log_time: t_ns,
            publish_time: t_ns,
        };
        self.writer
            .write_to_known_channel(&header, &data)
            .map_err(mcap_error(&self.partial))?;
        output.sequence = output.sequence.wrapping_add(1);
        Ok(())
    }

    /// Writes the summary and footer, syncs the file and renames `<path>.partial` to `path`.
    pub fn finish(self) -> Result<(), McapIoError> {
        let RecordingWriter {
            path,
            partial,
            mut writer,
            ..
        } = self;
        writer.finish().map_err(mcap_error(&partial))?;
        let file = writer
            .into_inner()
            .into_inner()
            .map_err(|e| McapIoError::Io {
                path: partial.clone(),
                source: e.into_error(),
            })?;
        file.sync_all().map_err(io_error(&partial))?;
        drop(file);
        fs::rename(&partial, &path).map_err(io_error(&path))?;
        // Make the rename itself durable where the platform allows it (best effort).
        if let Some(dir) = path.parent().filter(|d| !d.as_os_str().is_empty())
            && let Ok(dir) = File::open(dir)
        {
            let _ = dir.sync_all();
        }
        Ok(())
    }
}

fn parse_truth(path: &Path, key: &str, value: &str) -> Result<f64, McapIoError> {
    match value.trim().parse::<f64>() {
        Ok(v) if v.is_finite() => Ok(v),
        _ => Err(McapIoError::BadTruth {
            path: path.to_path_buf(),
            key: key.to_string(),
            value: value.to_string(),
        }),
    }
}

// ---------------------------------------------------------------------------------------------
// Reading
// ---------------------------------------------------------------------------------------------

/// A recording read whole by [`read_recording`].
#[derive(Debug, Clone, PartialEq)]
pub struct Recording {
    pub path: PathBuf,
    pub setup_toml: Option<String>,
    /// The attached setup's external model files, if it has them (module docs).
    pub model_files: Option<crate::matrix_market::ModelFiles>,
    /// Parsed from `jointid.truth`; empty when the record is absent.
    pub truth: BTreeMap<String, f64>,
    /// `jointid.recording`.
    pub facts: BTreeMap<String, String>,
    pub excitation_channels: ChannelInfo,
    pub response_channels: ChannelInfo,
    pub excitation: Vec<Frame>,
    pub response: Vec<Frame>,
    /// Encoding of the excitation topic (the writer uses one encoding for both).
    pub encoding: FrameEncoding,
    /// Set when the file was truncated or damaged: what was recovered and where it stopped.
    pub damage: Option<String>,
}

/// What [`stream_frames`] knows before the first frame.
#[derive(Debug, Clone, PartialEq)]
pub struct RecordingHeader {
    pub path: PathBuf,
    pub setup_toml: Option<String>,
    pub model_files: Option<crate::matrix_market::ModelFiles>,
    pub truth: BTreeMap<String, f64>,
    pub facts: BTreeMap<String, String>,
    pub excitation_channels: ChannelInfo,
    pub response_channels: ChannelInfo,
    pub encoding: FrameEncoding,
}

/// Reads a whole recording; see the module docs for the checks and for truncated files.
pub fn read_recording(path: &Path) -> Result<Recording, McapIoError> {
    let mut stream = stream_frames(path)?;
    let mut excitation = Vec::new();
    let mut response = Vec::new();
    for item in stream.by_ref() {
        let (topic, frame) = item?;
        match topic {
            InputTopic::Excitation => excitation.push(frame),
            InputTopic::Response => response.push(frame),
        }
    }
    let damage = stream.damage.take();
    let RecordingHeader {
        path,
        setup_toml,
        model_files,
        truth,
        facts,
        excitation_channels,
        response_channels,
        encoding,
    } = stream.header;
    Ok(Recording {
        path,
        setup_toml,
        model_files,
        truth,
        facts,
        excitation_channels,
        response_channels,
        excitation,
        response,
        encoding,
        damage,
    })
}

/// Streaming variant for large files: yields `(topic, frame)` in file order (log order for
/// files written by [`RecordingWriter`]) holding at most one chunk in memory. The header
/// (setup, truth, facts, channels) is read up front by a first pass that skips chunk data
/// once both input channels are known. The iterator ends after the first error; after it
/// ends, [`FrameStream::damage`] tells whether the file was truncated.
pub fn stream_frames(path: &Path) -> Result<FrameStream, McapIoError> {
    let header = read_header(path)?;
    Ok(FrameStream {
        header,
        walker: Walker::open(path)?,
        channels: HashMap::new(),
        pending: VecDeque::new(),
        progress: [TopicProgress::default(); 2],
        damage: None,
        done: false,
    })
}

/// Iterator over the input frames of a recording; see [`stream_frames`].
pub struct FrameStream {
    pub header: RecordingHeader,
    walker: Walker,
    channels: HashMap<u16, ChannelKind>,
    pending: VecDeque<Record<'static>>,
    progress: [TopicProgress; 2],
    damage: Option<String>,
    done: bool,
}

impl FrameStream {
    /// After the iterator has ended without error: `Some` description if the file was
    /// truncated, with what was recovered.
    pub fn damage(&self) -> Option<&str> {
        self.damage.as_deref()
    }

    /// Frames yielded so far on `topic`.
    pub fn frames_read(&self, topic: InputTopic) -> usize {
        self.progress[topic.index()].count
    }

    fn handle(
        &mut self,
        record: Record<'static>,
    ) -> Result<Option<(InputTopic, Frame)>, McapIoError> {
        let path = &self.header.path;
        match record {
            Record::Channel(channel) => {
                let kind = classify_channel(path, &channel)?;
                self.channels.insert(channel.id, kind);
                Ok(None)
            }
            Record::Message { header, data } => {
                let input = match self.channels.get(&header.channel_id) {
                    Some(ChannelKind::Input(input)) => input,
                    Some(ChannelKind::Other) => return Ok(None),
                    None => {
                        return Err(McapIoError::Mcap {
                            path: path.clone(),
                            source: McapError::UnknownChannel(header.sequence, header.channel_id),
                        });
                    }
                };
                let frame = decode_frame(path, input, &header, &data)?;
                let progress = &mut self.progress[input.topic.index()];
                progress.check(path, input.topic.topic(), &frame)?;
                progress.advance(&frame);
                Ok(Some((input.topic, frame)))
            }
            _ => Ok(None),
        }
    }

    fn next_item(&mut self) -> Result<Option<(InputTopic, Frame)>, McapIoError> {
        loop {
            if let Some(record) = self.pending.pop_front() {
                if let Some(item) = self.handle(record)? {
                    return Ok(Some(item));
                }
                continue;
            }
            match self.walker.next(false)? {
                Top::Record {
                    offset,
                    opcode,
                    bytes,
                } => match read_records(&self.header.path, offset, opcode, &bytes) {
                    Ok(records) => self.pending = records,
                    // A damaged chunk (CRC, corrupt records) in a file with a chunk index:
                    // skip to the next indexed chunk and say so; without an index it ends
                    // the read with the error.
                    Err(err @ (McapIoError::ChunkCrc { .. } | McapIoError::Corrupt { .. }))
                        if opcode == op::CHUNK =>
                    {
                        let why = match &err {
                            McapIoError::ChunkCrc {
                                saved, calculated, ..
                            } => format!("CRC stored {saved:#010x}, computed {calculated:#010x}"),
                            McapIoError::Corrupt { source, .. } => source.to_string(),
                            other => other.to_string(),
                        };
                        if !self.walker.resume_after_damaged_chunk(offset, &why, true)? {
                            return Err(err);
                        }
                    }
                    Err(err) => return Err(err),
                },
                Top::PartialChunk { bytes } => self.pending = salvage_partial_chunk(&bytes),
                Top::SkippedChunk => {}
                Top::End(truncation) => {
                    let mut notes = std::mem::take(&mut self.walker.skipped);
                    if let Some(t) = truncation {
                        notes.push(self.describe_damage(&t));
                    } else if !notes.is_empty() {
                        notes.push(self.describe_recovered());
                    }
                    self.damage = (!notes.is_empty()).then(|| notes.join("; "));
                    return Ok(None);
                }
            }
        }
    }

    fn describe_recovered(&self) -> String {
        let [exc, resp] = self.progress;
        format!(
            "recovered {} excitation and {} response frames (the skipped chunks' samples are missing)",
            exc.count, resp.count
        )
    }

    fn describe_damage(&self, t: &Truncation) -> String {
        let [exc, resp] = self.progress;
        let up_to = match exc.last_sample.max(resp.last_sample) {
            Some(sample) => format!("up to sample {sample}"),
            None => "(none)".to_string(),
        };
        format!(
            "truncated at byte {} of {}: {}; recovered {} excitation and {} response frames {}",
            t.at, t.file_len, t.what, exc.count, resp.count, up_to
        )
    }
}

impl Iterator for FrameStream {
    type Item = Result<(InputTopic, Frame), McapIoError>;

    fn next(&mut self) -> Option<Self::Item> {
        if self.done {
            return None;
        }
        match self.next_item() {
            Ok(Some(item)) => Some(Ok(item)),
            Ok(None) => {
                self.done = true;
                None
            }
            Err(err) => {
                self.done = true;
                Some(Err(err))
            }
        }
    }
}

struct InputChannel {
    topic: InputTopic,
    encoding: FrameEncoding,
    info: ChannelInfo,
}

enum ChannelKind {
    Input(InputChannel),
    Other,
}

fn classify_channel(path: &Path, channel: &records::Channel) -> Result<ChannelKind, McapIoError> {
    let Some(topic) = InputTopic::from_topic(&channel.topic) else {
        return Ok(ChannelKind::Other);
    };
    let encoding = match channel.message_encoding.as_str() {
        JSON_MESSAGE_ENCODING => FrameEncoding::Json,
        BINARY_MESSAGE_ENCODING => FrameEncoding::Binary,
        other => {
            return Err(McapIoError::UnsupportedEncoding {
                path: path.to_path_buf(),
                topic: channel.topic.clone(),
                encoding: other.to_string(),
            });
        }
    };
    let info = ChannelInfo::from_metadata(path, topic.topic(), &channel.metadata)?;
    Ok(ChannelKind::Input(InputChannel {
        topic,
        encoding,
        info,
    }))
}

fn decode_frame(
    path: &Path,
    input: &InputChannel,
    header: &MessageHeader,
    data: &[u8],
) -> Result<Frame, McapIoError> {
    let topic = input.topic.topic();
    let frame = match input.encoding {
        FrameEncoding::Json => {
            let raw: JsonFrameIn =
                serde_json::from_slice(data).map_err(|e| McapIoError::BadFrame {
                    path: path.to_path_buf(),
                    topic: topic.to_string(),
                    sequence: header.sequence,
                    log_time: header.log_time,
                    what: format!("not a jointid.Frame JSON object: {e}"),
                })?;
            Frame {
                sample: raw.sample,
                t_ns: raw.t_ns,
                // JSON has no NaN: a null is a value that was not finite.
                values: raw.values.iter().map(|v| v.unwrap_or(f64::NAN)).collect(),
            }
        }
        FrameEncoding::Binary => {
            let ([sample, t_ns, values @ ..], []) = data.as_chunks::<8>() else {
                return Err(McapIoError::BadFrameLength {
                    path: path.to_path_buf(),
                    topic: topic.to_string(),
                    sequence: header.sequence,
                    log_time: header.log_time,
                    len: data.len(),
                });
            };
            Frame {
                sample: u64::from_le_bytes(*sample),
                t_ns: u64::from_le_bytes(*t_ns),
                values: values.iter().map(|v| f64::from_le_bytes(*v)).collect(),
            }
        }
    };
    check_values(path, topic, &input.info, &frame)?;
    Ok(frame)
}

/// First pass: setup, truth, facts and the input channels.
fn read_header(path: &Path) -> Result<RecordingHeader, McapIoError> {
    let mut walker = Walker::open(path)?;
    let mut setup_toml = None;
    let mut model_parts: BTreeMap<String, String> = BTreeMap::new();
    let mut truth = BTreeMap::new();
    let mut facts = BTreeMap::new();
    let mut inputs: [Option<InputChannel>; 2] = [None, None];
    // Where the file stops, if it is cut short (`None`: a complete file).
    let truncation = loop {
        let need_channels = inputs.iter().any(Option::is_none);
        let records = match walker.next(!need_channels)? {
            Top::Record {
                offset,
                opcode,
                bytes,
            } => read_records(path, offset, opcode, &bytes)?,
            Top::PartialChunk { bytes } if need_channels => salvage_partial_chunk(&bytes),
            Top::PartialChunk { .. } | Top::SkippedChunk => continue,
            Top::End(t) => break t,
        };
        for record in records {
            match record {
                Record::Channel(channel) => {
                    if let ChannelKind::Input(input) = classify_channel(path, &channel)? {
                        let slot = &mut inputs[input.topic.index()];
                        if slot.is_none() {
                            *slot = Some(input);
                        }
                    }
                }
                Record::Attachment { header, data, .. } if header.name == SETUP_ATTACHMENT_NAME => {
                    let text = String::from_utf8(data.into_owned()).map_err(|e| {
                        McapIoError::BadSetup {
                            path: path.to_path_buf(),
                            what: format!("not UTF-8: {e}"),
                        }
                    })?;
                    setup_toml = Some(text);
                }
                Record::Attachment { header, data, .. }
                    if header.name.starts_with(MODEL_FILE_ATTACHMENT_PREFIX) =>
                {
                    let key = header.name[MODEL_FILE_ATTACHMENT_PREFIX.len()..].to_string();
                    let text = String::from_utf8(data.into_owned()).map_err(|e| {
                        McapIoError::BadModelFile {
                            path: path.to_path_buf(),
                            name: header.name.clone(),
                            what: format!("not UTF-8: {e}"),
                        }
                    })?;
                    model_parts.insert(key, text);
                }
                Record::Metadata(metadata) if metadata.name == TRUTH_METADATA => {
                    for (key, value) in &metadata.metadata {
                        truth.insert(key.clone(), parse_truth(path, key, value)?);
                    }
                }
                Record::Metadata(metadata) if metadata.name == RECORDING_METADATA => {
                    facts.extend(metadata.metadata);
                }
                _ => {}
            }
        }
    };
    let [excitation, response] = inputs;
    let missing = |topic: InputTopic| McapIoError::MissingTopic {
        path: path.to_path_buf(),
        topic: topic.topic().to_string(),
        truncated: truncation
            .as_ref()
            .map(|t| format!("byte {} of {} ({})", t.at, t.file_len, t.what)),
    };
    let excitation = excitation.ok_or_else(|| missing(InputTopic::Excitation))?;
    let response = response.ok_or_else(|| missing(InputTopic::Response))?;
    let model_files = model_files_of(path, model_parts)?;
    Ok(RecordingHeader {
        path: path.to_path_buf(),
        setup_toml,
        model_files,
        truth,
        facts,
        encoding: excitation.encoding,
        excitation_channels: excitation.info,
        response_channels: response.info,
    })
}

/// The external model's files from their attachments (`key → text`): none, or `mass`,
/// `stiffness`, `dof_map` and an optional `damping` — anything else is named as an error.
fn model_files_of(
    path: &Path,
    mut parts: BTreeMap<String, String>,
) -> Result<Option<crate::matrix_market::ModelFiles>, McapIoError> {
    if parts.is_empty() {
        return Ok(None);
    }
    let bad = |name: &str, what: &str| McapIoError::BadModelFile {
        path: path.to_path_buf(),
        name: format!("{MODEL_FILE_ATTACHMENT_PREFIX}{name}"),
        what: what.to_string(),
    };
    let mut take = |key: &str| {
        parts.remove(key).ok_or_else(|| {
            bad(
                key,
                "missing (the recording carries some of its model's files but not this one)",
            )
        })
    };
    let files = crate::matrix_market::ModelFiles {
        mass: take("mass")?,
        stiffness: take("stiffness")?,
        dof_map: take("dof_map")?,
        damping: parts.remove("damping"),
    };
    if let Some(key) = parts.keys().next() {
        return Err(bad(
            key,
            "not a model file key (mass, stiffness, damping, dof_map)",
        ));
    }
    Ok(Some(files))
}

/// The records of one complete top-level record: a chunk's contents (CRC checked first), or
/// the record itself.
fn read_records(
    path: &Path,
    offset: u64,
    opcode: u8,
    bytes: &[u8],
) -> Result<VecDeque<Record<'static>>, McapIoError> {
    if opcode == op::CHUNK {
        let trimmed = without_padding(bytes);
        let (records, error) = decode_chunk(trimmed.as_deref().unwrap_or(bytes), true);
        return match error {
            None => Ok(records),
            Some(McapError::BadChunkCrc { saved, calculated }) => Err(McapIoError::ChunkCrc {
                path: path.to_path_buf(),
                offset,
                saved,
                calculated,
            }),
            Some(source) => Err(McapIoError::Corrupt {
                path: path.to_path_buf(),
                offset,
                source,
            }),
        };
    }
    let body = bytes.get(RECORD_PREFIX_LEN as usize..).unwrap_or_default();
    let record = ::mcap::parse_record(opcode, body).map_err(|source| McapIoError::Corrupt {
        path: path.to_path_buf(),
        offset,
        source,
    })?;
    Ok(VecDeque::from([record.into_owned()]))
}

/// Decodes one chunk record (`bytes` = opcode, length and body) with the mcap crate's sans-io
/// reader. With `validate`, the whole chunk is decompressed and its CRC checked before any
/// record is returned. Returns the records decoded and the error that stopped decoding, if any.
fn decode_chunk(bytes: &[u8], validate: bool) -> (VecDeque<Record<'static>>, Option<McapError>) {
    let options = LinearReaderOptions::default()
        .with_skip_start_magic(true)
        .with_skip_end_magic(true)
        .with_validate_chunk_crcs(validate)
        .with_prevalidate_chunk_crcs(validate)
        .with_record_length_limit(CHUNK_SIZE_LIMIT);
    let mut reader = LinearReader::new_with_options(options);
    let mut rest = bytes;
    let mut records = VecDeque::new();
    while let Some(event) = reader.next_event() {
        match event {
            Ok(LinearReadEvent::ReadRequest(need)) => {
                let n = need.min(rest.len());
                reader.insert(n).copy_from_slice(&rest[..n]);
                reader.notify_read(n);
                rest = &rest[n..];
            }
            Ok(LinearReadEvent::Record { data, opcode }) => {
                match ::mcap::parse_record(opcode, data) {
                    Ok(record) => records.push_back(record.into_owned()),
                    Err(err) => return (records, Some(err)),
                }
            }
            Err(err) => return (records, Some(err)),
        }
    }
    (records, None)
}

/// Where the fields of a chunk record's header sit in `bytes` (opcode, length, body).
struct ChunkLayout {
    /// Opcode, length and chunk header.
    data_start: usize,
    compressed_size: u64,
}

const PREFIX: usize = RECORD_PREFIX_LEN as usize;
/// Chunk header: start time, end time, uncompressed size, uncompressed CRC, compression string
/// length; then the compression string and the compressed size.
const CHUNK_FIXED: usize = 8 + 8 + 8 + 4 + 4;
const CHUNK_CRC_AT: usize = PREFIX + 24;

impl ChunkLayout {
    /// `None` when `bytes` does not hold the whole chunk header.
    fn parse(bytes: &[u8]) -> Option<Self> {
        let compression_len = bytes
            .get(PREFIX + CHUNK_FIXED - 4..PREFIX + CHUNK_FIXED)
            .and_then(|b| <[u8; 4]>::try_from(b).ok())
            .map(u32::from_le_bytes)
            .and_then(|n| usize::try_from(n).ok())?;
        let data_start = (PREFIX + CHUNK_FIXED)
            .checked_add(compression_len)?
            .checked_add(8)?;
        let compressed_size = bytes
            .get(data_start - 8..data_start)
            .and_then(|b| <[u8; 8]>::try_from(b).ok())
            .map(u64::from_le_bytes)?;
        Some(ChunkLayout {
            data_start,
            compressed_size,
        })
    }

    /// A copy of the chunk record cut to its header and the first `data_len` bytes of its
    /// data, with the record length and compressed size rewritten to match, and the CRC too
    /// unless `keep_crc`. `None` if `bytes` holds fewer bytes.
    fn cut(&self, bytes: &[u8], data_len: usize, keep_crc: bool) -> Option<Vec<u8>> {
        let end = self.data_start.checked_add(data_len)?;
        let mut out = bytes.get(..end)?.to_vec();
        let record_len = (end - PREFIX) as u64;
        out.get_mut(1..PREFIX)?
            .copy_from_slice(&record_len.to_le_bytes());
        out.get_mut(self.data_start - 8..self.data_start)?
            .copy_from_slice(&(data_len as u64).to_le_bytes());
        if !keep_crc {
            out.get_mut(CHUNK_CRC_AT..CHUNK_CRC_AT + 4)?
                .copy_from_slice(&0u32.to_le_bytes());
        }
        Some(out)
    }
}

/// A complete chunk record as the sans-io reader should see it. Bytes after the compressed
/// data (padding, which writers do not emit) are dropped: in an uncompressed chunk the mcap
/// crate would let a corrupt record run into them and underflow its byte count.
fn without_padding(bytes: &[u8]) -> Option<Vec<u8>> {
    let layout = ChunkLayout::parse(bytes)?;
    let present = bytes.len().checked_sub(layout.data_start)?;
    let data_len = usize::try_from(layout.compressed_size).ok()?;
    (data_len < present)
        .then(|| layout.cut(bytes, data_len, true))
        .flatten()
}

/// Recovers the complete records at the start of a chunk cut short (`bytes` = opcode, length
/// and whatever part of the body the file holds). The chunk's header is rewritten to claim
/// just the bytes present, without a CRC, and decoding stops at the first incomplete record.
/// The writer's placeholder header of an unfinished chunk (all sizes `!0`) works the same way.
fn salvage_partial_chunk(bytes: &[u8]) -> VecDeque<Record<'static>> {
    let salvaged = ChunkLayout::parse(bytes).and_then(|layout| {
        let present = bytes.len().checked_sub(layout.data_start)?;
        layout.cut(bytes, present, false)
    });
    match salvaged {
        Some(cut) => decode_chunk(&cut, false).0,
        None => VecDeque::new(),
    }
}

/// Where a truncated file stops.
#[derive(Debug, Clone)]
struct Truncation {
    /// Offset of the first byte not fully recovered (start of the incomplete record).
    at: u64,
    file_len: u64,
    what: String,
}

enum Top {
    /// A complete record in the data section; `bytes` includes the opcode and length.
    Record {
        offset: u64,
        opcode: u8,
        bytes: Vec<u8>,
    },
    SkippedChunk,
    /// A chunk cut short by the end of the file; the walk ends after it.
    PartialChunk {
        bytes: Vec<u8>,
    },
    /// End of the walk: `None` for a complete file (footer and end magic present).
    End(Option<Truncation>),
}

/// Walks the top-level records of an MCAP file sequentially, tracking byte offsets. Summary
/// records are skipped (the summary repeats what the data section holds).
struct Walker {
    path: PathBuf,
    file: BufReader<File>,
    pos: u64,
    len: u64,
    in_summary: bool,
    ending: Option<Option<Truncation>>,
    /// Start offsets of the chunks listed in the file's summary (chunk indexes), sorted;
    /// empty when the file has no readable summary. Read only when a damaged chunk needs
    /// it (`None` until then), so an intact file's summary is never read.
    chunk_starts: Option<Vec<u64>>,
    /// One line per damaged chunk skipped by way of the chunk index.
    skipped: Vec<String>,
}

impl Walker {
    fn open(path: &Path) -> Result<Self, McapIoError> {
        let file = File::open(path).map_err(io_error(path))?;
        let len = file.metadata().map_err(io_error(path))?.len();
        let mut walker = Walker {
            path: path.to_path_buf(),
            file: BufReader::with_capacity(1 << 16, file),
            pos: 0,
            len,
            in_summary: false,
            ending: None,
            chunk_starts: None,
            skipped: Vec::new(),
        };
        let magic = walker.read_magic()?;
        if magic.as_deref() != Some(::mcap::MAGIC) {
            return Err(mcap_error(path)(McapError::BadMagic));
        }
        Ok(walker)
    }

    /// After the chunk at `offset` proved unreadable (`why`): moves to the next chunk the
    /// summary's index lists after it and notes what was skipped. A damaged last chunk that
    /// was `read_whole` is skipped in place. `false` (nothing moved) when the file has no
    /// index or no later chunk.
    fn resume_after_damaged_chunk(
        &mut self,
        offset: u64,
        why: &str,
        read_whole: bool,
    ) -> Result<bool, McapIoError> {
        let (path, len) = (self.path.clone(), self.len);
        let starts = self
            .chunk_starts
            .get_or_insert_with(|| indexed_chunk_starts(&path, len).unwrap_or_default());
        let total = starts.len();
        let Some(&next) = starts.iter().find(|&&start| start > offset) else {
            if read_whole && starts.contains(&offset) {
                self.skipped.push(format!(
                    "chunk at byte {offset} (the last of {total}) is damaged ({why}): skipped"
                ));
                return Ok(true);
            }
            return Ok(false);
        };
        if next >= len {
            return Ok(false);
        }
        let later = starts.iter().filter(|&&s| s >= next).count();
        self.skipped.push(format!(
            "chunk at byte {offset} is damaged ({why}): skipped {} bytes to the next indexed chunk at byte {next} ({later} of {total} chunks follow)",
            next - offset
        ));
        self.file
            .seek(std::io::SeekFrom::Start(next))
            .map_err(io_error(&self.path))?;
        self.pos = next;
        Ok(true)
    }

    /// The next 8 bytes, or `None` if the file has fewer left.
    fn read_magic(&mut self) -> Result<Option<Vec<u8>>, McapIoError> {
        if self.len - self.pos < 8 {
            return Ok(None);
        }
        let mut magic = Vec::new();
        self.read_into(&mut magic, 8)?;
        Ok(Some(magic))
    }

    fn read_into(&mut self, buf: &mut Vec<u8>, n: u64) -> Result<(), McapIoError> {
        let got = (&mut self.file)
            .take(n)
            .read_to_end(buf)
            .map_err(io_error(&self.path))?;
        if got as u64 != n {
            return Err(McapIoError::Io {
                path: self.path.clone(),
                source: std::io::Error::new(
                    std::io::ErrorKind::UnexpectedEof,
                    format!("file shrank while being read (at byte {})", self.pos),
                ),
            });
        }
        self.pos += n;
        Ok(())
    }

    fn skip(&mut self, n: u64) -> Result<(), McapIoError> {
        let step = i64::try_from(n).map_err(|_| McapIoError::Io {
            path: self.path.clone(),
            source: std::io::Error::other("record too large to skip"),
        })?;
        self.file
            .seek_relative(step)
            .map_err(io_error(&self.path))?;
        self.pos += n;
        Ok(())
    }

    fn truncated(&mut self, at: u64, what: String) -> Top {
        let truncation = Truncation {
            at,
            file_len: self.len,
            what,
        };
        self.ending = Some(Some(truncation.clone()));
        Top::End(Some(truncation))
    }

    fn next(&mut self, skip_chunks: bool) -> Result<Top, McapIoError> {
        loop {
            if let Some(ending) = &self.ending {
                return Ok(Top::End(ending.clone()));
            }
            let offset = self.pos;
            let remaining = self.len - offset;
            let section = if self.in_summary {
                "in the summary section (all data records are intact)"
            } else {
                "in the data section"
            };
            if remaining == 0 {
                let what = if self.in_summary {
                    "the file ends in the summary section, before the footer (all data records are intact)"
                } else {
                    "the file ends without a data-end record or footer (the writer did not finish)"
                };
                return Ok(self.truncated(offset, what.to_string()));
            }
            if remaining < RECORD_PREFIX_LEN {
                return Ok(self.truncated(offset, format!("incomplete record header {section}")));
            }
            let mut head = Vec::with_capacity(RECORD_PREFIX_LEN as usize);
            self.read_into(&mut head, RECORD_PREFIX_LEN)?;
            let Ok([opcode, len @ ..]) = <[u8; 9]>::try_from(head.as_slice()) else {
                return Ok(self.truncated(offset, format!("incomplete record header {section}")));
            };
            let body_len = u64::from_le_bytes(len);
            let available = remaining - RECORD_PREFIX_LEN;
            if body_len > available {
                if opcode == op::CHUNK
                    && !self.in_summary
                    && self.resume_after_damaged_chunk(
                        offset,
                        &format!("{body_len} bytes declared, {available} left in the file"),
                        false,
                    )?
                {
                    continue;
                }
                if opcode == op::CHUNK && !self.in_summary {
                    let what = if body_len == u64::MAX {
                        format!(
                            "unfinished chunk (the writer stopped mid-chunk), {available} bytes present"
                        )
                    } else {
                        format!(
                            "incomplete chunk record, {body_len} bytes declared, {available} present"
                        )
                    };
                    let mut bytes = head;
                    self.read_into(&mut bytes, available)?;
                    self.truncated(offset, what);
                    return Ok(Top::PartialChunk { bytes });
                }
                return Ok(self.truncated(
                    offset,
                    format!(
                        "incomplete {} record {section}, {body_len} bytes declared, {available} present",
                        opcode_name(opcode)
                    ),
                ));
            }
            if self.in_summary || opcode == op::FOOTER || opcode == op::DATA_END {
                self.skip(body_len)?;
                self.in_summary = true;
                if opcode == op::FOOTER {
                    let magic_at = self.pos;
                    match self.read_magic()? {
                        None => {
                            return Ok(self.truncated(
                                magic_at,
                                "the end magic is missing (all data records are intact)"
                                    .to_string(),
                            ));
                        }
                        Some(magic) if magic != ::mcap::MAGIC => {
                            return Err(McapIoError::Corrupt {
                                path: self.path.clone(),
                                offset: magic_at,
                                source: McapError::BadMagic,
                            });
                        }
                        Some(_) => self.ending = Some(None),
                    }
                }
                continue;
            }
            // Message indexes only locate messages in the chunk before them; the walk reads
            // the chunks themselves.
            if (opcode == op::CHUNK && skip_chunks) || opcode == op::MESSAGE_INDEX {
                self.skip(body_len)?;
                if opcode == op::CHUNK {
                    return Ok(Top::SkippedChunk);
                }
                continue;
            }
            let mut bytes = head;
            self.read_into(&mut bytes, body_len)?;
            return Ok(Top::Record {
                offset,
                opcode,
                bytes,
            });
        }
    }
}

/// The chunk start offsets listed by the summary's chunk indexes (sorted), read from the
/// footer's `summary_start`; `None` when the file has no usable summary (an unfinished or
/// damaged file), which only means there is no way past a damaged chunk.
fn indexed_chunk_starts(path: &Path, len: u64) -> Option<Vec<u64>> {
    // Footer record: opcode, length (20), summary start, summary offset start, CRC; magic.
    const FOOTER_RECORD: u64 = 1 + 8 + 20;
    let footer_at = len.checked_sub(FOOTER_RECORD + 8)?;
    let mut file = File::open(path).ok()?;
    file.seek(std::io::SeekFrom::Start(footer_at)).ok()?;
    let mut footer = [0u8; (FOOTER_RECORD + 8) as usize];
    file.read_exact(&mut footer).ok()?;
    if footer[0] != op::FOOTER || &footer[FOOTER_RECORD as usize..] != ::mcap::MAGIC {
        return None;
    }
    let summary_start = u64::from_le_bytes(footer[9..17].try_into().ok()?);
    if summary_start == 0
        || summary_start >= footer_at
        || footer_at - summary_start > SUMMARY_SIZE_LIMIT
    {
        return None;
    }
    file.seek(std::io::SeekFrom::Start(summary_start)).ok()?;
    let mut summary = vec![0u8; (footer_at - summary_start) as usize];
    file.read_exact(&mut summary).ok()?;
    let mut starts = Vec::new();
    let mut rest = summary.as_slice();
    while rest.len() >= RECORD_PREFIX_LEN as usize {
        let opcode = rest[0];
        let body_len = usize::try_from(u64::from_le_bytes(rest[1..9].try_into().ok()?)).ok()?;
        let body = rest.get(9..9usize.checked_add(body_len)?)?;
        if opcode == op::CHUNK_INDEX
            && let Ok(Record::ChunkIndex(index)) = ::mcap::parse_record(opcode, body)
            && index.chunk_start_offset < summary_start
        {
            starts.push(index.chunk_start_offset);
        }
        rest = &rest[9 + body_len..];
    }
    starts.sort_unstable();
    starts.dedup();
    Some(starts)
}

fn opcode_name(opcode: u8) -> String {
    let name = match opcode {
        op::HEADER => "header",
        op::FOOTER => "footer",
        op::SCHEMA => "schema",
        op::CHANNEL => "channel",
        op::MESSAGE => "message",
        op::CHUNK => "chunk",
        op::MESSAGE_INDEX => "message index",
        op::CHUNK_INDEX => "chunk index",
        op::ATTACHMENT => "attachment",
        op::ATTACHMENT_INDEX => "attachment index",
        op::STATISTICS => "statistics",
        op::METADATA => "metadata",
        op::METADATA_INDEX => "metadata index",
        op::SUMMARY_OFFSET => "summary offset",
        op::DATA_END => "data end",
        other => return format!("opcode {other:#04x}"),
    };
    name.to_string()
}

#[cfg(test)]
mod tests {
    use super::*;
    use ::mcap::Compression;
    use std::io::Write;

    const SETUP: &str = "[run]\nscenario = \"two-joint\"\ndt_s = 0.001\n";

    fn info(names: &[&str], units: &[&str]) -> ChannelInfo {
        ChannelInfo {
            names: names.iter().map(|s| s.to_string()).collect(),
            units: units.iter().map(|s| s.to_string()).collect(),
        }
    }

    fn exc_info() -> ChannelInfo {
        info(&["node1.force", "node2.force"], &["N", "N"])
    }

    fn resp_info() -> ChannelInfo {
        info(
            &["node1.accel", "node2.accel", "joint6.disp"],
            &["m/s^2", "m/s^2", "m"],
        )
    }

    /// Frames with awkward values: tiny, huge, negative zero, non-terminating decimals.
    fn frames(n: u64, channels: usize, phase: f64) -> Vec<Frame> {
        (0..n)
            .map(|i| Frame {
                sample: i * 2 + 1,
                t_ns: 1_000 + i * 1_000_000,
                values: (0..channels)
                    .map(|c| match (i + c as u64) % 7 {
                        0 => 0.1,
                        1 => -0.0,
                        2 => 1e-300,
                        3 => f64::MAX,
                        _ => ((i * 3 + c as u64) as f64 * 0.37 + phase).sin() * 1e3,
                    })
                    .collect(),
            })
            .collect()
    }

    fn truth() -> BTreeMap<String, String> {
        BTreeMap::from([
            ("joint6.u".to_string(), 0.1.to_string()),
            ("joint6.k".to_string(), 1.25e7.to_string()),
        ])
    }

    fn facts() -> BTreeMap<String, String> {
        BTreeMap::from([
            ("generator".to_string(), "jointid-sim".to_string()),
            ("seed".to_string(), "42".to_string()),
            ("dt_s".to_string(), "0.001".to_string()),
        ])
    }

    struct Written {
        path: PathBuf,
        exc: Vec<Frame>,
        resp: Vec<Frame>,
    }

    fn write_sample(
        path: &Path,
        encoding: FrameEncoding,
        options: WriteOptions,
        n: u64,
    ) -> Written {
        let exc = frames(n, 2, 0.0);
        let resp = frames(n, 3, 1.0);
        let mut w = RecordingWriter::create_with_options(path, encoding, options).unwrap();
        w.attach_setup(SETUP).unwrap();
        w.write_metadata(TRUTH_METADATA, &truth()).unwrap();
        w.write_metadata(RECORDING_METADATA, &facts()).unwrap();
        w.declare_inputs(&exc_info(), &resp_info()).unwrap();
        for (e, r) in exc.iter().zip(&resp) {
            w.write_excitation(e).unwrap();
            w.write_response(r).unwrap();
        }
        w.finish().unwrap();
        Written {
            path: path.to_path_buf(),
            exc,
            resp,
        }
    }

    fn option_sets() -> Vec<(&'static str, WriteOptions)> {
        vec![
            ("default", WriteOptions::new()),
            (
                "uncompressed-small-chunks",
                WriteOptions::new().compression(None).chunk_size(Some(1024)),
            ),
            (
                "zstd-small-chunks",
                WriteOptions::new()
                    .compression(Some(Compression::Zstd))
                    .chunk_size(Some(1024)),
            ),
            (
                "lz4",
                WriteOptions::new().compression(Some(Compression::Lz4)),
            ),
            ("unchunked", WriteOptions::new().use_chunks(false)),
        ]
    }

    #[test]
    fn round_trip_both_encodings() {
        let dir = tempfile::tempdir().unwrap();
        for encoding in [FrameEncoding::Json, FrameEncoding::Binary] {
            for (label, options) in option_sets() {
                let path = dir.path().join(format!("{encoding:?}-{label}.mcap"));
                let w = write_sample(&path, encoding, options, 50);
                let rec = read_recording(&path).unwrap();
                assert_eq!(rec.path, path);
                assert_eq!(rec.encoding, encoding);
                assert_eq!(rec.damage, None, "{label}");
                assert_eq!(rec.setup_toml.as_deref(), Some(SETUP));
                assert_eq!(
                    rec.truth,
                    BTreeMap::from([
                        ("joint6.k".to_string(), 1.25e7),
                        ("joint6.u".to_string(), 0.1)
                    ])
                );
                assert_eq!(rec.facts, facts());
                assert_eq!(rec.excitation_channels, exc_info());
                assert_eq!(rec.response_channels, resp_info());
                assert_eq!(rec.excitation, w.exc, "{encoding:?} {label}");
                assert_eq!(rec.response, w.resp, "{encoding:?} {label}");
                // Bit-exact, including -0.0.
                let bits = |f: &[Frame]| -> Vec<u64> {
                    f.iter()
                        .flat_map(|f| f.values.iter().map(|v| v.to_bits()))
                        .collect()
                };
                assert_eq!(bits(&rec.excitation), bits(&w.exc));
            }
        }
    }

    /// An external model's files ride along as attachments and read back as written;
    /// a recording that carries only some of them is refused naming the missing one.
    #[test]
    fn model_files_round_trip_and_an_incomplete_set_is_named() {
        use crate::matrix_market::ModelFiles;
        let dir = tempfile::tempdir().unwrap();
        let files = ModelFiles {
            mass: "%%MatrixMarket matrix coordinate real symmetric\n1 1 1\n1 1 2.5\n".into(),
            stiffness: "%%MatrixMarket matrix coordinate real symmetric\n1 1 1\n1 1 4e3\n".into(),
            damping: None,
            dof_map: "node,direction,row\n1,w,1\n".into(),
        };
        let write = |path: &Path, files: &[(&str, &str)]| {
            let mut w = RecordingWriter::create(path, FrameEncoding::Json).unwrap();
            w.attach_setup(SETUP).unwrap();
            for (key, text) in files {
                w.writer
                    .attach(&Attachment {
                        log_time: 0,
                        create_time: 0,
                        name: format!("{MODEL_FILE_ATTACHMENT_PREFIX}{key}"),
                        media_type: "text/plain".into(),
                        data: text.as_bytes().into(),
                    })
                    .unwrap();
            }
            w.declare_inputs(&exc_info(), &resp_info()).unwrap();
            for f in frames(3, 2, 0.0) {
                w.write_excitation(&f).unwrap();
            }
            for f in frames(3, 3, 1.0) {
                w.write_response(&f).unwrap();
            }
            w.finish().unwrap();
        };
        // Through the writer's own method.
        let path = dir.path().join("whole.mcap");
        let mut w = RecordingWriter::create(&path, FrameEncoding::Json).unwrap();
        assert!(
            w.attach_model_files(&files).is_err(),
            "files before the setup"
        );
        w.attach_setup(SETUP).unwrap();
        w.attach_model_files(&files).unwrap();
        w.declare_inputs(&exc_info(), &resp_info()).unwrap();
        w.finish().unwrap();
        assert_eq!(
            read_recording(&path).unwrap().model_files,
            Some(files.clone())
        );
        // No model files: none read.
        let path = dir.path().join("none.mcap");
        write(&path, &[]);
        assert_eq!(read_recording(&path).unwrap().model_files, None);
        // The mass and the DOF map without the stiffness.
        let path = dir.path().join("part.mcap");
        write(&path, &[("mass", &files.mass), ("dof_map", &files.dof_map)]);
        let e = read_recording(&path).unwrap_err().to_string();
        assert!(
            e.contains("part.mcap") && e.contains("model.matrix_market.stiffness: missing"),
            "{e}"
        );
        // An unknown key.
        let path = dir.path().join("odd.mcap");
        write(
            &path,
            &[
                ("mass", &files.mass),
                ("stiffness", &files.stiffness),
                ("dof_map", &files.dof_map),
                ("gyroscopic", "x"),
            ],
        );
        let e = read_recording(&path).unwrap_err().to_string();
        assert!(
            e.contains("model.matrix_market.gyroscopic: not a model file key"),
            "{e}"
        );
    }

    #[test]
    fn stream_yields_frames_in_log_order_with_header() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("s.mcap");
        let w = write_sample(&path, FrameEncoding::Binary, WriteOptions::new(), 20);
        let mut stream = stream_frames(&path).unwrap();
        assert_eq!(stream.header.setup_toml.as_deref(), Some(SETUP));
        assert_eq!(stream.header.response_channels, resp_info());
        assert_eq!(stream.header.truth.get("joint6.u"), Some(&0.1));
        let items: Vec<_> = stream.by_ref().map(Result::unwrap).collect();
        assert_eq!(items.len(), 40);
        for (i, (topic, frame)) in items.iter().enumerate() {
            let k = i / 2;
            if i % 2 == 0 {
                assert_eq!((*topic, frame), (InputTopic::Excitation, &w.exc[k]));
            } else {
                assert_eq!((*topic, frame), (InputTopic::Response, &w.resp[k]));
            }
        }
        assert_eq!(stream.damage(), None);
        assert_eq!(stream.frames_read(InputTopic::Response), 20);
    }

    #[test]
    fn message_fields_follow_the_contract() {
        let dir = tempfile::tempdir().unwrap();
        for encoding in [FrameEncoding::Json, FrameEncoding::Binary] {
            let path = dir.path().join(format!("{encoding:?}.mcap"));
            let w = write_sample(&path, encoding, WriteOptions::new(), 3);
            let bytes = fs::read(&path).unwrap();
            let messages: Vec<_> = ::mcap::MessageStream::new(&bytes)
                .unwrap()
                .map(Result::unwrap)
                .collect();
            let first = &messages[0];
            assert_eq!(first.channel.topic, EXCITATION_TOPIC);
            assert_eq!(first.log_time, w.exc[0].t_ns);
            assert_eq!(first.publish_time, w.exc[0].t_ns);
            assert_eq!(first.sequence, w.exc[0].sample as u32);
            assert_eq!(
                first.channel.metadata.get(CHANNELS_KEY).map(String::as_str),
                Some("node1.force,node2.force")
            );
            assert_eq!(
                first.channel.metadata.get(UNITS_KEY).map(String::as_str),
                Some("N,N")
            );
            match encoding {
                FrameEncoding::Json => {
                    assert_eq!(first.channel.message_encoding, "json");
                    let schema = first.channel.schema.as_ref().unwrap();
                    assert_eq!(schema.name, FRAME_SCHEMA_NAME);
                    assert_eq!(schema.encoding, "jsonschema");
                    let parsed: Value = serde_json::from_slice(&schema.data).unwrap();
                    assert_eq!(parsed, frame_json_schema());
                    let msg: Value = serde_json::from_slice(&first.data).unwrap();
                    assert_eq!(
                        msg,
                        serde_json::json!({"sample": 1, "t_ns": 1000, "values": [0.1, -0.0]})
                    );
                }
                FrameEncoding::Binary => {
                    assert_eq!(first.channel.message_encoding, "jointid.frame.v1");
                    assert!(first.channel.schema.is_none());
                    assert_eq!(first.data.len(), 16 + 8 * 2);
                    assert_eq!(first.data[..8], 1u64.to_le_bytes());
                    assert_eq!(first.data[8..16], 1000u64.to_le_bytes());
                    assert_eq!(first.data[16..24], 0.1f64.to_le_bytes());
                }
            }
            let attachment = bytes_attachment(&bytes);
            assert_eq!(
                attachment,
                (SETUP_MEDIA_TYPE.to_string(), SETUP.as_bytes().to_vec())
            );
        }
    }

    fn bytes_attachment(bytes: &[u8]) -> (String, Vec<u8>) {
        let summary = ::mcap::Summary::read(bytes).unwrap().unwrap();
        let index = &summary.attachment_indexes[0];
        assert_eq!(index.name, SETUP_ATTACHMENT_NAME);
        let a = ::mcap::read::attachment(bytes, index).unwrap();
        (a.media_type, a.data.into_owned())
    }

    #[test]
    fn finish_renames_partial() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("run.mcap");
        let partial = dir.path().join("run.mcap.partial");
        let mut w = RecordingWriter::create(&path, FrameEncoding::Json).unwrap();
        assert_eq!(w.partial_path(), partial);
        w.declare_inputs(&exc_info(), &resp_info()).unwrap();
        w.write_excitation(&frames(1, 2, 0.0)[0]).unwrap();
        assert!(partial.exists());
        assert!(!path.exists());
        w.finish().unwrap();
        assert!(path.exists());
        assert!(!partial.exists());
        let rec = read_recording(&path).unwrap();
        assert_eq!(rec.excitation.len(), 1);
        assert!(rec.response.is_empty());
        assert_eq!(rec.setup_toml, None);
        assert!(rec.truth.is_empty());
    }

    #[test]
    fn dropped_writer_leaves_a_finalised_partial_file() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("run.mcap");
        {
            let mut w = RecordingWriter::create(&path, FrameEncoding::Binary).unwrap();
            w.declare_inputs(&exc_info(), &resp_info()).unwrap();
            for f in frames(10, 2, 0.0) {
                w.write_excitation(&f).unwrap();
            }
        }
        assert!(!path.exists());
        let rec = read_recording(&partial_path(&path)).unwrap();
        assert_eq!(rec.damage, None);
        assert_eq!(rec.excitation, frames(10, 2, 0.0));
    }

    #[test]
    fn killed_writer_recovers_what_reached_the_disk() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("run.mcap");
        let exc = frames(200, 2, 0.0);
        let resp = frames(200, 3, 1.0);
        let mut w = RecordingWriter::create_with_options(
            &path,
            FrameEncoding::Json,
            WriteOptions::new().chunk_size(Some(2048)),
        )
        .unwrap();
        w.declare_inputs(&exc_info(), &resp_info()).unwrap();
        for (e, r) in exc.iter().zip(&resp) {
            w.write_excitation(e).unwrap();
            w.write_response(r).unwrap();
        }
        // Like a kill: no destructor runs, buffered bytes never reach the file.
        std::mem::forget(w);
        let rec = read_recording(&partial_path(&path)).unwrap();
        let damage = rec.damage.unwrap();
        assert!(damage.starts_with("truncated at byte"), "{damage}");
        assert!(!rec.excitation.is_empty(), "{damage}");
        assert!(rec.excitation.len() < exc.len(), "{damage}");
        assert_eq!(rec.excitation, exc[..rec.excitation.len()]);
        assert_eq!(rec.response, resp[..rec.response.len()]);
    }

    #[test]
    fn output_topics_are_json_with_schemas() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("out.mcap");
        let schema = serde_json::json!({
            "type": "object",
            "properties": {"t": {"type": "number"}, "r": {"type": "array", "items": {"type": "number"}}}
        });
        let mut w = RecordingWriter::create(&path, FrameEncoding::Binary).unwrap();
        w.declare_inputs(&exc_info(), &resp_info()).unwrap();
        for (i, f) in frames(3, 2, 0.0).iter().enumerate() {
            w.write_excitation(f).unwrap();
            for topic in [
                RESIDUALS_TOPIC,
                STATES_TOPIC,
                PARAMETERS_TOPIC,
                DIAGNOSTICS_TOPIC,
            ] {
                let msg = serde_json::json!({"t": i as f64 * 0.5, "r": [1.0, -2.5]});
                w.write_output(topic, "jointid.Test", &schema, f.t_ns, &msg)
                    .unwrap();
            }
        }
        #[derive(Serialize)]
        struct Diag {
            iteration: u32,
            cost: f64,
        }
        w.write_output(
            DIAGNOSTICS_TOPIC,
            "jointid.Test",
            &schema,
            5,
            &Diag {
                iteration: 7,
                cost: 0.5,
            },
        )
        .unwrap();
        let err = w
            .write_output(DIAGNOSTICS_TOPIC, "jointid.Other", &schema, 6, &1)
            .unwrap_err();
        assert!(matches!(err, McapIoError::Usage { .. }), "{err}");
        let err = w
            .write_output(RESPONSE_TOPIC, "jointid.Test", &schema, 6, &1)
            .unwrap_err();
        assert!(matches!(err, McapIoError::Usage { .. }), "{err}");
        w.finish().unwrap();

        let bytes = fs::read(&path).unwrap();
        let mut per_topic: BTreeMap<String, Vec<Value>> = BTreeMap::new();
        for m in ::mcap::MessageStream::new(&bytes).unwrap() {
            let m = m.unwrap();
            if InputTopic::from_topic(&m.channel.topic).is_some() {
                continue;
            }
            assert_eq!(m.channel.message_encoding, "json");
            let s = m.channel.schema.as_ref().unwrap();
            assert_eq!(
                (s.name.as_str(), s.encoding.as_str()),
                ("jointid.Test", "jsonschema")
            );
            assert_eq!(serde_json::from_slice::<Value>(&s.data).unwrap(), schema);
            let expected_seq = per_topic.get(&m.channel.topic).map_or(0, Vec::len) as u32;
            assert_eq!(m.sequence, expected_seq);
            per_topic
                .entry(m.channel.topic.clone())
                .or_default()
                .push(serde_json::from_slice(&m.data).unwrap());
        }
        assert_eq!(per_topic.len(), 4);
        assert_eq!(
            per_topic[RESIDUALS_TOPIC][2],
            serde_json::json!({"t": 1.0, "r": [1.0, -2.5]})
        );
        assert_eq!(
            per_topic[DIAGNOSTICS_TOPIC][3],
            serde_json::json!({"iteration": 7, "cost": 0.5})
        );
        // The input readers skip output topics.
        let rec = read_recording(&path).unwrap();
        assert_eq!(rec.excitation.len(), 3);
    }

    fn flip(path: &Path, at: u64) {
        let mut bytes = fs::read(path).unwrap();
        bytes[at as usize] ^= 0x55;
        fs::write(path, bytes).unwrap();
    }

    #[test]
    fn chunk_crc_mismatch_is_skipped_by_the_index_or_reported_with_its_offset() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("crc.mcap");
        write_sample(
            &path,
            FrameEncoding::Binary,
            WriteOptions::new().compression(None).chunk_size(Some(1024)),
            40,
        );
        let summary = ::mcap::Summary::read(&fs::read(&path).unwrap())
            .unwrap()
            .unwrap();
        let chunk = &summary.chunk_indexes[2];
        // Inside the last message's values: the records still parse, only the CRC can tell.
        flip(&path, chunk.chunk_start_offset + chunk.chunk_length - 3);
        // A complete file: its summary's chunk index leads past the damaged chunk, and the
        // damage note says which chunk was skipped.
        let rec = read_recording(&path).unwrap();
        let damage = rec.damage.clone().unwrap_or_default();
        assert!(
            damage.contains(&format!("chunk at byte {}", chunk.chunk_start_offset))
                && damage.contains("CRC")
                && damage.contains("skipped"),
            "{damage}"
        );
        assert!(rec.excitation.len() < 40 && rec.excitation.len() > 20);
        // Without a summary (the file cut before it): the read stops there with the error,
        // after yielding the frames before it.
        let bytes = fs::read(&path).unwrap();
        let cut = dir.path().join("cut.mcap");
        fs::write(
            &cut,
            &bytes[..(chunk.chunk_start_offset + chunk.chunk_length) as usize],
        )
        .unwrap();
        let err = read_recording(&cut).unwrap_err();
        match &err {
            McapIoError::ChunkCrc {
                path: p, offset, ..
            } => {
                assert_eq!(p, &cut);
                assert_eq!(*offset, chunk.chunk_start_offset);
            }
            other => panic!("expected ChunkCrc, got {other}"),
        }
        let text = err.to_string();
        assert!(
            text.contains(&format!("chunk at byte {}", chunk.chunk_start_offset)),
            "{text}"
        );
        let items: Vec<_> = stream_frames(&cut).unwrap().collect();
        assert!(matches!(
            items.last(),
            Some(Err(McapIoError::ChunkCrc { .. }))
        ));
        assert!(items.len() > 1);
    }

    #[test]
    fn compressed_chunk_corruption_is_reported_with_its_offset() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("crc.mcap");
        write_sample(&path, FrameEncoding::Json, WriteOptions::new(), 40);
        let original = fs::read(&path).unwrap();
        let summary = ::mcap::Summary::read(&original).unwrap().unwrap();
        let chunk = &summary.chunk_indexes[0];
        let data_end = chunk.chunk_start_offset + chunk.chunk_length;
        for at in [
            data_end - 1,
            data_end - chunk.compressed_size / 2,
            data_end - 30,
        ] {
            fs::write(&path, &original).unwrap();
            flip(&path, at);
            match read_recording(&path).unwrap_err() {
                McapIoError::ChunkCrc { offset, .. } | McapIoError::Corrupt { offset, .. } => {
                    assert_eq!(offset, chunk.chunk_start_offset, "flip at {at}")
                }
                other => panic!("flip at {at}: expected a chunk error, got {other}"),
            }
        }
    }

    fn check_truncations(encoding: FrameEncoding, compression: Option<Compression>) {
        let dir = tempfile::tempdir().unwrap();
        let w = write_sample(
            &dir.path().join("full.mcap"),
            encoding,
            WriteOptions::new()
                .compression(compression)
                .chunk_size(Some(2048)),
            60,
        );
        let bytes = fs::read(&w.path).unwrap();
        let len = bytes.len() as u64;
        let summary = ::mcap::Summary::read(&bytes).unwrap().unwrap();
        let footer = ::mcap::read::footer(&bytes).unwrap();
        let chunks = &summary.chunk_indexes;
        assert!(
            chunks.len() >= 3,
            "want several chunks, got {}",
            chunks.len()
        );
        let last_chunk_end = chunks
            .iter()
            .map(|c| c.chunk_start_offset + c.chunk_length)
            .max()
            .unwrap();
        let mut cuts = vec![
            8,
            20,
            footer.summary_start - 5,
            footer.summary_start + 10,
            len - 8,
            len - 1,
        ];
        for c in chunks {
            let (s, l) = (c.chunk_start_offset, c.chunk_length);
            cuts.extend([s + 20, s + l / 2, s + l - 1, s + l]);
        }
        cuts.sort_unstable();
        cuts.dedup();
        let total = w.exc.len() + w.resp.len();
        let mut recovered = BTreeMap::new();
        let mut previous = 0;
        for cut in cuts {
            let path = dir.path().join(format!("cut{cut}.mcap"));
            fs::write(&path, &bytes[..cut as usize]).unwrap();
            let rec = match read_recording(&path) {
                Err(e @ McapIoError::MissingTopic { .. }) => {
                    // Only before the end of the first chunk, which holds just the channels;
                    // and the message says the file is cut, not that the topic is absent.
                    assert!(
                        cut < chunks[0].chunk_start_offset + chunks[0].chunk_length,
                        "cut {cut}"
                    );
                    let text = e.to_string();
                    assert!(
                        text.contains("damaged, truncated before it at byte")
                            && text.contains(&format!(" of {cut} (")),
                        "cut {cut}: {text}"
                    );
                    continue;
                }
                Err(e) => panic!("cut at {cut} of {len}: {e}"),
                Ok(rec) => rec,
            };
            let damage = rec
                .damage
                .clone()
                .unwrap_or_else(|| panic!("cut {cut}: no damage"));
            assert!(
                damage.starts_with("truncated at byte") && damage.contains(&format!(" of {cut}:")),
                "{damage}"
            );
            assert_eq!(rec.excitation, w.exc[..rec.excitation.len()], "cut {cut}");
            assert_eq!(rec.response, w.resp[..rec.response.len()], "cut {cut}");
            let n = rec.excitation.len() + rec.response.len();
            assert!(n >= previous, "cut {cut}: {n} < {previous}");
            assert!(
                damage.contains(&format!(
                    "recovered {} excitation and {} response frames",
                    rec.excitation.len(),
                    rec.response.len()
                )),
                "{damage}"
            );
            if cut >= last_chunk_end {
                assert_eq!(n, total, "cut {cut}: {damage}");
            }
            if cut > footer.summary_start {
                assert!(damage.contains("all data records are intact"), "{damage}");
            }
            previous = n;
            recovered.insert(cut, n);
            // The streaming reader agrees.
            let mut stream = stream_frames(&path).unwrap();
            assert_eq!(stream.by_ref().count(), n);
            assert_eq!(stream.damage(), Some(damage.as_str()));
        }
        if compression.is_none() {
            // Messages at the start of a cut chunk are salvaged, not just whole chunks.
            for c in &chunks[1..] {
                let (s, l) = (c.chunk_start_offset, c.chunk_length);
                assert!(
                    recovered[&(s + l / 2)] > recovered[&(s + 20)],
                    "chunk at {s}"
                );
            }
        }
    }

    #[test]
    fn truncation_recovery_binary_uncompressed() {
        check_truncations(FrameEncoding::Binary, None);
    }

    #[test]
    fn truncation_recovery_json_uncompressed() {
        check_truncations(FrameEncoding::Json, None);
    }

    #[test]
    fn truncation_recovery_json_zstd() {
        check_truncations(FrameEncoding::Json, Some(Compression::Zstd));
    }

    #[test]
    fn truncation_recovery_binary_lz4() {
        check_truncations(FrameEncoding::Binary, Some(Compression::Lz4));
    }

    #[test]
    fn not_an_mcap_file_is_an_error() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("x.mcap");
        fs::write(&path, b"hello").unwrap();
        let err = read_recording(&path).unwrap_err();
        assert!(
            matches!(
                err,
                McapIoError::Mcap {
                    source: McapError::BadMagic,
                    ..
                }
            ),
            "{err}"
        );
        let err = read_recording(&dir.path().join("absent.mcap")).unwrap_err();
        assert!(matches!(err, McapIoError::Io { .. }), "{err}");
    }

    #[test]
    fn non_finite_values_are_rejected_on_write() {
        let dir = tempfile::tempdir().unwrap();
        for encoding in [FrameEncoding::Json, FrameEncoding::Binary] {
            let path = dir.path().join(format!("{encoding:?}.mcap"));
            let mut w = RecordingWriter::create(&path, encoding).unwrap();
            w.declare_inputs(&exc_info(), &resp_info()).unwrap();
            let bad = Frame {
                sample: 4,
                t_ns: 10,
                values: vec![1.0, f64::NAN],
            };
            match w.write_excitation(&bad).unwrap_err() {
                McapIoError::NonFinite {
                    topic,
                    sample,
                    channel,
                    index,
                    ..
                } => {
                    assert_eq!(
                        (topic.as_str(), sample, channel.as_str(), index),
                        (EXCITATION_TOPIC, 4, "node2.force", 1)
                    );
                }
                other => panic!("{other}"),
            }
            let inf = Frame {
                values: vec![f64::INFINITY, 0.0, 0.0],
                ..bad
            };
            assert!(matches!(
                w.write_response(&inf).unwrap_err(),
                McapIoError::NonFinite { index: 0, .. }
            ));
            // A rejected frame leaves the writer usable.
            w.write_excitation(&Frame {
                sample: 4,
                t_ns: 10,
                values: vec![1.0, 2.0],
            })
            .unwrap();
            w.finish().unwrap();
            assert_eq!(read_recording(&path).unwrap().excitation.len(), 1);
        }
    }

    /// Writes a recording by hand with the mcap crate, to produce what `RecordingWriter`
    /// refuses to write.
    fn craft(
        path: &Path,
        message_encoding: &str,
        messages: &[(InputTopic, u32, u64, Vec<u8>)],
        truth: Option<BTreeMap<String, String>>,
    ) {
        let file = BufWriter::new(File::create(path).unwrap());
        let mut w = WriteOptions::new().compression(None).create(file).unwrap();
        let exc = w
            .add_channel(
                0,
                EXCITATION_TOPIC,
                message_encoding,
                &exc_info().to_metadata(),
            )
            .unwrap();
        let resp = w
            .add_channel(
                0,
                RESPONSE_TOPIC,
                message_encoding,
                &resp_info().to_metadata(),
            )
            .unwrap();
        if let Some(truth) = truth {
            w.write_metadata(&Metadata {
                name: TRUTH_METADATA.to_string(),
                metadata: truth,
            })
            .unwrap();
        }
        for (topic, sequence, t, data) in messages {
            let channel_id = match topic {
                InputTopic::Excitation => exc,
                InputTopic::Response => resp,
            };
            let header = MessageHeader {
                channel_id,
                sequence: *sequence,
                log_time: *t,
                publish_time: *t,
            };
            w.write_to_known_channel(&header, data).unwrap();
        }
        w.finish().unwrap();
        w.into_inner().flush().unwrap();
    }

    fn bin(sample: u64, t_ns: u64, values: &[f64]) -> (InputTopic, u32, u64, Vec<u8>) {
        let mut data = sample.to_le_bytes().to_vec();
        data.extend(t_ns.to_le_bytes());
        for v in values {
            data.extend(v.to_le_bytes());
        }
        (InputTopic::Excitation, sample as u32, t_ns, data)
    }

    fn json(
        topic: InputTopic,
        sample: u64,
        t_ns: u64,
        text: &str,
    ) -> (InputTopic, u32, u64, Vec<u8>) {
        (topic, sample as u32, t_ns, text.as_bytes().to_vec())
    }

    fn craft_and_read(
        message_encoding: &str,
        messages: &[(InputTopic, u32, u64, Vec<u8>)],
    ) -> McapIoError {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("crafted.mcap");
        craft(&path, message_encoding, messages, None);
        let err = read_recording(&path).unwrap_err();
        assert!(err.to_string().contains("crafted.mcap"), "{err}");
        err
    }

    #[test]
    fn binary_nan_on_read_names_sample_and_channel() {
        let err = craft_and_read(
            BINARY_MESSAGE_ENCODING,
            &[bin(1, 10, &[1.0, 2.0]), bin(2, 20, &[3.0, f64::NAN])],
        );
        match err {
            McapIoError::NonFinite {
                topic,
                sample,
                channel,
                index,
                ..
            } => assert_eq!(
                (topic.as_str(), sample, channel.as_str(), index),
                (EXCITATION_TOPIC, 2, "node2.force", 1)
            ),
            other => panic!("{other}"),
        }
    }

    #[test]
    fn json_null_on_read_is_non_finite() {
        let err = craft_and_read(
            JSON_MESSAGE_ENCODING,
            &[json(
                InputTopic::Response,
                7,
                10,
                r#"{"sample":7,"t_ns":10,"values":[1.0,null,3.0]}"#,
            )],
        );
        assert!(
            matches!(&err, McapIoError::NonFinite { sample: 7, index: 1, channel, topic, .. }
                if channel == "node2.accel" && topic == RESPONSE_TOPIC),
            "{err}"
        );
        let err = craft_and_read(
            JSON_MESSAGE_ENCODING,
            &[json(
                InputTopic::Response,
                7,
                10,
                r#"{"sample":7,"values":[]}"#,
            )],
        );
        assert!(
            matches!(err, McapIoError::BadFrame { sequence: 7, .. }),
            "{err}"
        );
    }

    #[test]
    fn wrong_channel_count_on_write_and_read() {
        let err = craft_and_read(BINARY_MESSAGE_ENCODING, &[bin(3, 10, &[1.0, 2.0, 3.0])]);
        assert!(
            matches!(
                err,
                McapIoError::WrongChannelCount {
                    sample: 3,
                    expected: 2,
                    got: 3,
                    ..
                }
            ),
            "{err}"
        );
        let dir = tempfile::tempdir().unwrap();
        let mut w =
            RecordingWriter::create(&dir.path().join("w.mcap"), FrameEncoding::Json).unwrap();
        w.declare_inputs(&exc_info(), &resp_info()).unwrap();
        let err = w
            .write_response(&Frame {
                sample: 0,
                t_ns: 0,
                values: vec![1.0],
            })
            .unwrap_err();
        assert!(
            matches!(
                err,
                McapIoError::WrongChannelCount {
                    expected: 3,
                    got: 1,
                    ..
                }
            ),
            "{err}"
        );
    }

    #[test]
    fn bad_binary_length_names_topic_and_sequence() {
        let mut short = bin(5, 50, &[1.0, 2.0]);
        short.3.pop();
        let err = craft_and_read(BINARY_MESSAGE_ENCODING, &[short]);
        assert!(
            matches!(&err, McapIoError::BadFrameLength { sequence: 5, log_time: 50, len: 31, topic, .. }
                if topic == EXCITATION_TOPIC),
            "{err}"
        );
    }

    #[test]
    fn time_going_backwards_and_repeated_samples_are_errors() {
        let err = craft_and_read(
            BINARY_MESSAGE_ENCODING,
            &[bin(1, 100, &[1.0, 2.0]), bin(2, 99, &[1.0, 2.0])],
        );
        assert!(
            matches!(
                err,
                McapIoError::NonMonotonicTime {
                    sample: 2,
                    prev_ns: 100,
                    got_ns: 99,
                    ..
                }
            ),
            "{err}"
        );
        let err = craft_and_read(
            BINARY_MESSAGE_ENCODING,
            &[bin(1, 100, &[1.0, 2.0]), bin(1, 100, &[1.0, 2.0])],
        );
        assert!(
            matches!(
                err,
                McapIoError::SampleNotIncreasing {
                    sample: 1,
                    prev: 1,
                    ..
                }
            ),
            "{err}"
        );
        // Equal times are fine, and each topic is checked on its own.
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("ok.mcap");
        let mut w = RecordingWriter::create(&path, FrameEncoding::Binary).unwrap();
        w.declare_inputs(&exc_info(), &resp_info()).unwrap();
        let f = |sample, t_ns, n| Frame {
            sample,
            t_ns,
            values: vec![0.5; n],
        };
        w.write_excitation(&f(1, 100, 2)).unwrap();
        w.write_excitation(&f(2, 100, 2)).unwrap();
        w.write_response(&f(1, 50, 3)).unwrap();
        let err = w.write_excitation(&f(3, 99, 2)).unwrap_err();
        assert!(
            matches!(err, McapIoError::NonMonotonicTime { sample: 3, .. }),
            "{err}"
        );
        let err = w.write_excitation(&f(2, 200, 2)).unwrap_err();
        assert!(
            matches!(
                err,
                McapIoError::SampleNotIncreasing {
                    sample: 2,
                    prev: 2,
                    ..
                }
            ),
            "{err}"
        );
        w.finish().unwrap();
        let rec = read_recording(&path).unwrap();
        assert_eq!((rec.excitation.len(), rec.response.len()), (2, 1));
    }

    #[test]
    fn missing_topic_bad_truth_and_bad_metadata() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("missing.mcap");
        let mut w = WriteOptions::new()
            .create(BufWriter::new(File::create(&path).unwrap()))
            .unwrap();
        w.add_channel(
            0,
            EXCITATION_TOPIC,
            BINARY_MESSAGE_ENCODING,
            &exc_info().to_metadata(),
        )
        .unwrap();
        w.finish().unwrap();
        drop(w);
        let err = read_recording(&path).unwrap_err();
        assert!(
            matches!(&err, McapIoError::MissingTopic { topic, truncated: None, .. } if topic == RESPONSE_TOPIC),
            "{err}"
        );
        assert!(
            !err.to_string().contains("damaged"),
            "a complete file: {err}"
        );

        let path = dir.path().join("truth.mcap");
        let bad = BTreeMap::from([("joint6.u".to_string(), "0.1x".to_string())]);
        craft(&path, BINARY_MESSAGE_ENCODING, &[], Some(bad.clone()));
        let err = read_recording(&path).unwrap_err();
        assert!(
            matches!(&err, McapIoError::BadTruth { key, value, .. } if key == "joint6.u" && value == "0.1x"),
            "{err}"
        );
        let mut w =
            RecordingWriter::create(&dir.path().join("t2.mcap"), FrameEncoding::Json).unwrap();
        assert!(matches!(
            w.write_metadata(TRUTH_METADATA, &bad).unwrap_err(),
            McapIoError::BadTruth { .. }
        ));
        let nan = BTreeMap::from([("k".to_string(), "NaN".to_string())]);
        assert!(w.write_metadata(TRUTH_METADATA, &nan).is_err());
        // Free-form facts are not parsed.
        w.write_metadata(RECORDING_METADATA, &bad).unwrap();

        let commas = info(&["a,b"], &["N"]);
        assert!(matches!(
            w.declare_inputs(&commas, &resp_info()).unwrap_err(),
            McapIoError::BadChannelInfo { .. }
        ));
        let mismatched = info(&["a", "b"], &["N"]);
        assert!(w.declare_inputs(&exc_info(), &mismatched).is_err());
        assert!(matches!(
            w.write_excitation(&frames(1, 2, 0.0)[0]).unwrap_err(),
            McapIoError::Usage { .. }
        ));
        w.declare_inputs(&exc_info(), &resp_info()).unwrap();
        assert!(w.declare_inputs(&exc_info(), &resp_info()).is_err());
        w.attach_setup(SETUP).unwrap();
        assert!(w.attach_setup(SETUP).is_err());
    }

    #[test]
    fn unsupported_input_encoding_is_an_error() {
        let err = craft_and_read("protobuf", &[]);
        assert!(
            matches!(&err, McapIoError::UnsupportedEncoding { encoding, .. } if encoding == "protobuf"),
            "{err}"
        );
    }

    #[test]
    fn zstd_partial_chunk_is_salvaged_with_default_options() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("big.mcap");
        let names: Vec<String> = (0..12).map(|i| format!("node{i}.accel")).collect();
        let ci = ChannelInfo {
            units: vec!["m/s^2".to_string(); names.len()],
            names,
        };
        let mut w = RecordingWriter::create(&path, FrameEncoding::Binary).unwrap();
        w.declare_inputs(&ci, &ci).unwrap();
        for i in 0..6000u64 {
            let f = Frame {
                sample: i,
                t_ns: i * 1000,
                values: (0..12).map(|c| ((i * 13 + c) as f64).sin()).collect(),
            };
            w.write_excitation(&f).unwrap();
            w.write_response(&f).unwrap();
        }
        w.finish().unwrap();
        let bytes = fs::read(&path).unwrap();
        let summary = ::mcap::Summary::read(&bytes).unwrap().unwrap();
        let chunk = &summary.chunk_indexes[1];
        assert_eq!(chunk.compression, "zstd");
        assert!(chunk.uncompressed_size > 512 * 1024, "{chunk:?}");
        let recovered = |cut: u64| {
            let p = dir.path().join("cut.mcap");
            fs::write(&p, &bytes[..cut as usize]).unwrap();
            let rec = read_recording(&p).unwrap();
            assert!(rec.damage.is_some());
            rec.excitation.len()
        };
        let start = chunk.chunk_start_offset;
        assert_eq!(recovered(start + 20), 0);
        let salvaged = recovered(start + chunk.chunk_length * 9 / 10);
        assert!(salvaged > 1000, "only {salvaged} frames salvaged");
    }

    #[test]
    fn chunk_padding_is_skipped_and_bad_records_without_crc_do_not_panic() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("pad.mcap");
        let w = write_sample(
            &path,
            FrameEncoding::Binary,
            WriteOptions::new().compression(None).chunk_size(Some(1024)),
            20,
        );
        let original = fs::read(&path).unwrap();
        let summary = ::mcap::Summary::read(&original).unwrap().unwrap();
        let chunk = &summary.chunk_indexes[1];
        let (s, l) = (
            chunk.chunk_start_offset as usize,
            chunk.chunk_length as usize,
        );
        let mut padded = original[..s + l].to_vec();
        padded.extend([0u8; 64]);
        padded.extend_from_slice(&original[s + l..]);
        let record_len = (l - 9 + 64) as u64;
        padded[s + 1..s + 9].copy_from_slice(&record_len.to_le_bytes());
        fs::write(&path, &padded).unwrap();
        let rec = read_recording(&path).unwrap();
        assert_eq!((rec.excitation, rec.response), (w.exc, w.resp));

        // No CRC, and the first message claims to run into the padding.
        let data_start = s + 9 + CHUNK_FIXED + 8;
        padded[s + 9 + 24..s + 9 + 28].copy_from_slice(&0u32.to_le_bytes());
        let claimed = chunk.compressed_size + 20;
        padded[data_start + 1..data_start + 9].copy_from_slice(&claimed.to_le_bytes());
        fs::write(&path, &padded).unwrap();
        let err = read_recording(&path).unwrap_err();
        assert!(
            matches!(err, McapIoError::Corrupt { offset, .. } if offset == s as u64),
            "{err}"
        );
    }
}
