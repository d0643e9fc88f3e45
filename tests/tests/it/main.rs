//! Cross-crate integration tests (one test binary).
mod core;
