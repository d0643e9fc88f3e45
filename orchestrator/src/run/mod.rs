//! Running one trial: what a run is configured with, the in-process lock-step driver,
//! and what it writes.
//!
//! # Layout
//! - [`config`]: raw TOML/CLI configuration validated into a [`config::RunSpec`].
//! - [`trial`]: one trial in one process over the in-memory transport.
//! - [`output`]: per-step CSV, the locality map and the run manifest.
//! - [`bench`](mod@bench): throughput benchmark of the simulation core (`geese bench`).
pub mod bench;
pub mod config;
pub mod output;
pub mod trial;
