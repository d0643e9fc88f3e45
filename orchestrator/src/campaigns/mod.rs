//! Campaigns: the paper's experiments as many trials over conditions and seeds, run in
//! parallel into a resumable SQLite results database (`geese campaign`, `geese merge`,
//! `geese export`).
//!
//! # Layout
//! - [`condition`]: the knobs a campaign varies and how a condition builds a run config.
//! - [`campaign`]: campaign files, the trial plan, the [`campaign::TrialRunner`] hook and
//!   the parallel, resumable executor.
//! - [`shard`]: a campaign split into N cost-balanced shards (cluster job arrays).
//! - [`store`]: the SQLite results database (manifest, trials, step rows) and CSV export.
//! - [`merge`]: shard databases combined into one results database (`geese merge`).
pub mod campaign;
pub mod condition;
pub mod merge;
pub mod shard;
pub mod store;
