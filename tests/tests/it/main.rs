//! Cross-crate integration tests (one test binary).
mod campaign;
mod core;
mod distributed;
mod docs;
mod footprint;
mod fusion;
mod fuzz;
mod multihost;
mod protocol;
mod security;
mod view;
