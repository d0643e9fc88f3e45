//! The orchestrator side of GEESE: run configuration, the in-process lock-step driver,
//! results and the `geese` command.
//!
//! # Layout
//! - [`config`]: raw TOML/CLI configuration validated into a [`config::RunSpec`].
//! - [`trial`]: one trial in one process over the in-memory transport.
//! - [`output`]: per-step CSV and the run manifest.
//! - [`bench`](mod@bench): throughput benchmark of the simulation core.
//! - [`launch`]: the distributed mode: world and agent processes over Zenoh.
//! - [`control`]: `geese control`, perturbations and stop sent to a running world.
//! - [`bench_net`]: the distributed benchmark (lock-step rate over Zenoh, bare and
//!   learning).
//! - [`condition`]: the knobs a campaign varies and how a condition builds a run config.
//! - [`campaign`]: campaign files, the trial plan, the [`campaign::TrialRunner`] hook and
//!   the parallel, resumable executor.
//! - [`shard`]: a campaign split into N cost-balanced shards (cluster job arrays).
//! - [`store`]: the SQLite results database (manifest, trials, step rows) and CSV export.
//! - [`merge`]: shard databases combined into one results database (`geese merge`).
//! - [`metrics`]: success rate, power, efficiency (paper and reference-code variants),
//!   summary statistics and least-squares slopes; pure functions.
//! - [`report`]: metric tables and figures from a results database.
//! - [`plot`]: PNG/SVG figures (learning curves, resilience scatters, box plots,
//!   locality maps).
//! - [`locality`]: a run's locality map read back and drawn (`geese locality`, Fig. 5).
//! - [`secure`]: `geese secure init`, the credentials and access-control list of a run
//!   started by hand or across hosts.
//! - [`view`]: the live viewer's web server and page (`geese view`, `geese run --view`).
//! - [`watch`]: an in-process run with the viewer attached.
// Doc comments of clap arguments are also `--help` text, where `<run>` or `<db>` reads
// as a placeholder; rustdoc would take them for HTML tags.
#![allow(rustdoc::invalid_html_tags)]
pub mod bench;
pub mod bench_net;
pub mod campaign;
pub mod condition;
pub mod config;
pub mod control;
pub mod launch;
pub mod locality;
pub mod merge;
pub mod metrics;
pub mod output;
pub mod plot;
pub mod report;
pub mod secure;
pub mod shard;
pub mod store;
pub mod trial;
pub mod view;
pub mod watch;

pub use config::{RunConfig, RunSpec};
pub use trial::{run_trial, Trial, TrialSummary};
