//! jointid — identify the physical properties of structural connections (bolted, pinned,
//! friction and spring joints) from vibration test data, after NASA TM-101991 (Lawrence &
//! Huckelbridge 1989).
//!
//! # Layout and data flow
//!
//! ```text
//! setup (TOML) ─► model ─► integrate ─► estimate ─► identify ─► app / bins
//!   setup.rs     model.rs   integrate.rs  estimate/     identify.rs   app.rs
//!                                          paper.rs     (Steps V–VI)
//!                                          kalman.rs
//!                                          refit.rs
//! recordings: io/mcap.rs ─► align.rs ─► identify ─► io/mcap.rs (results)
//! synthetic:  simulate.rs (true law, implicit friction) ─► io/mcap.rs
//! ```
//!
//! - [`setup`]: the TOML schema, validated into [`setup::Setup`].
//! - [`model`]: FE assembly of M, C, K, DOF map, static condensation.
//! - [`integrate`]: Newmark-β sample map (sub-steps), factorised once (dense, modal, sparse).
//! - [`sparse`]: CSR matrices and the envelope Cholesky of the sparse step.
//! - [`estimate`]: residual-force estimators behind [`estimate::ResidualEstimator`]
//!   (the 1989 one-step reference and the default Kalman joint input–state estimator) and
//!   the online least-squares refit.
//! - [`identify`]: passes over data (Step VI), stopping rule, stuck-sample handling.
//! - [`simulate`]: synthetic tests with a known truth.
//! - [`track`]: parameters as they change during a test (forgetting, periodic solves).
//! - [`par`]: order-preserving parallel map over independent simulations.
//! - [`session`]: whole-session identification in windows (bounded memory), combined.
//! - [`align`]: joins excitation and response frames, checks gaps and values.
//! - [`io`]: MCAP recordings (the data contract is in the module docs and docs/CONTRACTS.md).
//! - [`pipeline`]: source → aligner → stepper → refitter → sinks on threads (replay and live).
//! - [`app`]: what the command line does.
pub mod align;
pub mod app;
pub mod dense;
pub mod estimate;
pub mod identify;
pub mod integrate;
pub mod io;
pub mod matrix_market;
pub mod model;
pub mod par;
pub mod pipeline;
pub mod report;
pub mod session;
pub mod setup;
pub mod simulate;
pub mod sparse;
pub mod track;
