//! The orchestrator side of GEESE: run configuration, the in-process lock-step driver,
//! campaigns and their results, reports and figures, the live viewer and the distributed
//! launcher behind the `geese` command.
//!
//! # Layout
//! Grouped by what each part serves; each group's own `# Layout` lists its modules.
//! - [`run`]: one trial — configuration validated into a [`RunSpec`], the in-process
//!   driver ([`run_trial`], [`Trial`]), per-step CSV and the manifest, the core
//!   benchmark.
//! - [`campaigns`]: experiments of many trials — campaign files and conditions, the
//!   parallel, resumable executor, shards, the SQLite results store and its merge.
//! - [`analysis`]: what a results database or a run directory amounts to — metrics,
//!   tables and figures, the locality map.
//! - [`live`]: a running swarm watched and steered — the web viewer, an in-process run
//!   with it attached, `geese control`.
//! - [`distributed`]: world and agent processes over Zenoh — the launcher, its
//!   benchmark, the credentials of a run started by hand.
//!
//! The `geese` binary (`main.rs`, and `campaign_cli.rs` for `geese campaign`, `merge`,
//! `report` and `export`) parses arguments and prints around these.
// Doc comments of clap arguments are also `--help` text, where `<run>` or `<db>` reads
// as a placeholder; rustdoc would take them for HTML tags.
#![allow(rustdoc::invalid_html_tags)]
pub mod analysis;
pub mod campaigns;
pub mod distributed;
pub mod live;
pub mod run;

pub use run::config::{RunConfig, RunSpec};
pub use run::trial::{run_trial, Trial, TrialSummary};
