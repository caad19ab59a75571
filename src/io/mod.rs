//! Input and output: MCAP recordings (`mcap`) and, for live runs, iceoryx2 shared memory.
//! The numerical core never touches these; it sees [`crate::identify::TestData`] and
//! per-sample slices.
pub mod mcap;
pub mod shm;

pub use self::mcap::{Frame, FrameEncoding};
