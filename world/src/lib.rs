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
//! - [`pace`]: pause, step-rate limit and frame-rate bound of a watched run (sans IO).
//! - [`frame`]: the live viewer's picture of a world.
//! - [`locality`]: the locality map (Fig. 5): agent-steps per location and behaviour
//!   class over a window of steps, counted by the world.
//! - [`gather`]: the server's gathering of one step's intents (sans IO).
//! - [`hub`]: the server's gene hub: per-cell aggregation and forwarding of gene packs
//!   between agent processes (sans IO).
//! - [`server`]: the world server's protocol — presence, control plane, step
//!   sequencing with deadlines — driven by messages in and a clock value, returning
//!   messages to publish; the `geese-world` binary only moves bytes between Zenoh and it.
pub mod config;
pub mod frame;
pub mod gather;
pub mod hub;
pub mod layout;
pub mod locality;
pub mod pace;
pub mod server;
pub mod world;

pub use config::{ConfigError, Layout, Start, Task, WorldConfig};
pub use world::World;
