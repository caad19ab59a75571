//! Input and output: MCAP recordings (`mcap`) and, for live runs, iceoryx2 shared memory.
//! The numerical core never touches these; it sees [`crate::identify::TestData`] and
//! per-sample slices.
pub mod contract;
pub mod csv;
pub mod mcap;
pub mod output;
pub mod shm;

pub use self::mcap::{Frame, FrameEncoding};

use std::io::Read;
use std::path::Path;

/// Largest setup file read (a setup is a page of TOML; anything larger is not one).
pub const MAX_SETUP_BYTES: u64 = 4 << 20;
/// Largest Matrix Market or DOF-map file read (a 100,000-DOF sparse model is tens of MB).
pub const MAX_MODEL_FILE_BYTES: u64 = 256 << 20;

/// Reads a UTF-8 text file of at most `max_bytes`, so that a wrong path (a device such as
/// `/dev/zero`, a multi-GB binary) fails with an error instead of exhausting memory.
pub fn read_text_capped(path: &Path, max_bytes: u64) -> std::io::Result<String> {
    let file = std::fs::File::open(path)?;
    let mut text = String::new();
    file.take(max_bytes + 1).read_to_string(&mut text)?;
    if text.len() as u64 > max_bytes {
        return Err(std::io::Error::other(format!(
            "larger than {} MiB: not a file of this kind",
            max_bytes >> 20
        )));
    }
    Ok(text)
}
