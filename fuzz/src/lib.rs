//! The fuzz targets of GEESE and their seed corpus (issues 17 and 31).
//!
//! The fuzzing is done by a coverage-guided engine, AFL++ through `cargo afl` (it runs
//! on stable Rust and builds AFL++ itself), from the harness in `fuzz/afl`; this crate
//! holds what the engine needs and what the test suite replays without it. Each target
//! hands arbitrary bytes to the very function a GEESE binary calls on what it receives
//! or reads; a panic, or an input that does not return quickly, is a bug. The seeds are
//! made in code with the crates' own encoders, so they follow the wire format; `geese-fuzz
//! seeds DIR` writes them out as the engine's input directory.
//!
//! (Until issue 31 a hand-written, coverage-blind mutator drove the targets here; the
//! engine replaced it, with more edges covered on the same budget: fuzz/README.md.)
//!
//! # Layout
//! - [`targets`]: the registry of named targets, each a `fn(&[u8]) -> bool` that decodes
//!   or parses exactly as the world, agent and orchestrator binaries do.
//! - [`protocol`]: targets that drive the protocol modules themselves (the world's
//!   `Server`, an agent process's `Host`) with a hostile message in the middle of a step.
//! - [`corpus`]: the seed inputs and dictionary of each target (real values encoded, the
//!   shipped grammars, the campaign files, run configurations), and their export as files.
//! - [`replay`]: inputs run through a target with panics caught and timed: the seeds,
//!   kept crash inputs (`fuzz/regressions`), an engine's queue or crashes.
pub mod corpus;
pub mod protocol;
pub mod replay;
pub mod targets;

pub use targets::{by_name, Target, TARGETS};
