//! Reports and figures: what a results database or a run directory amounts to
//! (`geese report`, `geese locality`).
//!
//! # Layout
//! - [`metrics`]: success rate, power, efficiency (paper and reference-code variants),
//!   summary statistics and least-squares slopes; pure functions.
//! - [`report`]: metric tables and figures from a results database.
//! - [`plot`]: PNG/SVG figures (learning curves, resilience scatters, box plots,
//!   locality maps).
//! - [`locality`]: a run's locality map read back and drawn (`geese locality`, Fig. 5).
pub mod locality;
pub mod metrics;
pub mod plot;
pub mod report;
