//! Fuzzing on stable Rust (issue 17, item 5).
//!
//! `cargo fuzz` and libFuzzer need a nightly compiler, which the machines that build
//! GEESE do not have. This crate is a small driver that runs on stable instead: no
//! coverage feedback, but every target is fed a deterministic stream of inputs that are
//! mostly mutations of *valid* encodings and files (so that they get past the first
//! length or version check and reach the deep parts of a decoder), plus some random
//! bytes. Each input goes through the very function a GEESE binary calls on what it
//! receives or reads; a panic, or an input that takes longer than the hang limit, is a
//! failure, and the input is saved so that it can be kept as a regression.
//!
//! Inputs are a pure function of (seed, target name, input index), so that any input of
//! a run can be made again from those three numbers, and the watchdog can save the input
//! of a worker that never returns without the worker's help.
//!
//! # Layout
//! - [`targets`]: the registry of named targets, each a `fn(&[u8])` that decodes or parses
//!   exactly as the world, agent and orchestrator binaries do.
//! - [`corpus`]: the seed inputs of each target: real values encoded, the shipped
//!   grammars, the campaign files, run configurations.
//! - [`protocol`]: targets that drive the protocol modules themselves (the world's
//!   `Server`, an agent process's `Host`) with a hostile message in the middle of a step.
//! - [`mutate`]: the input generator (random bytes; bit flips, byte inserts and deletes,
//!   splices, interesting integers, dictionary tokens and truncation of seed inputs).
//! - [`driver`]: runs a target for N inputs with panics caught and a hang watchdog,
//!   saves failing inputs, and replays kept regressions.
pub mod corpus;
pub mod driver;
pub mod mutate;
pub mod protocol;
pub mod targets;

pub use driver::{replay_regressions, run_target, Failure, FailureKind, Options, Report};
pub use targets::{by_name, Target, TARGETS};
