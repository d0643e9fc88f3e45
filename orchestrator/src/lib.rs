//! The orchestrator side of GEESE: run configuration, the in-process lock-step driver,
//! results and the `geese` command.
//!
//! # Layout
//! - [`config`]: raw TOML/CLI configuration validated into a [`config::RunSpec`].
//! - [`trial`]: one trial in one process over the in-memory transport.
//! - [`output`]: per-step CSV and the run manifest.
//! - [`bench`]: throughput benchmark of the simulation core.
pub mod bench;
pub mod config;
pub mod output;
pub mod trial;

pub use config::{RunConfig, RunSpec};
pub use trial::{run_trial, Trial, TrialSummary};
