//! The GEESE arena: the authoritative state of the swarm's world.
//!
//! Agents never touch this state: they send [`Intent`](geese_proto::Intent)s, and the
//! world validates and applies them in agent-id order (DESIGN.md §2 step 4). Everything
//! here is synchronous and deterministic for a given seed.
//!
//! # Layout
//! - [`config`]: the world's raw configuration and its validation.
//! - [`layout`]: task layouts (reference-code and paper variants) and placement rules.
//! - [`world`]: objects, grid registration, percepts, intent resolution, task %, hooks.
pub mod config;
pub mod layout;
pub mod world;

pub use config::{ConfigError, Layout, Start, Task, WorldConfig};
pub use world::World;
