//! jointid — identify structural connection properties from vibration test data.
pub mod estimate;
pub mod identify;
pub mod integrate;
pub mod model;
pub mod setup;
pub mod simulate;
