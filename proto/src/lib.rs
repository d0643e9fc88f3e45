//! The wire contract between the GEESE world, its agents and the orchestrator.
//!
//! Nothing here simulates anything: these are the messages of the lock-step protocol
//! (DESIGN.md §2), the key expressions they travel on, the versioned `postcard`
//! envelope that encodes them, and the in-memory bus used when everything runs in one
//! process. Both transports carry exactly these types, which is what lets an in-process
//! run and a distributed run produce the same trajectory.
//!
//! # Layout
//! - [`geometry`]: positions, arena size and the exact grid-cell arithmetic both sides use.
//! - [`message`]: percepts, genes, intents, step reports, control commands.
//! - [`keys`]: the key expressions of every topic, defined once.
//! - [`rules`]: the rules world and agents must agree on (speed, capacity, drops).
//! - [`limits`]: limits on what crosses a trust boundary, and the checks of control
//!   commands against them.
//! - [`codec`]: the versioned envelope and its decode errors.
//! - [`seed`]: named random streams and portable digests.
//! - [`net`]: the extra messages of the distributed runtime (ticks, batches, run info).
//! - [`view`]: the frames and agent details the live viewer shows.
//! - `zenoh_bus` (feature `zenoh`): the Zenoh transport — session configuration, the
//!   command-line arguments every process shares, publication helpers.
//! - `security` (feature `zenoh`): credentials, the access-control list generated from
//!   [`keys`], and a run's secrets directory (DESIGN.md §7).
pub mod codec;
pub mod geometry;
pub mod keys;
pub mod limits;
pub mod message;
pub mod net;
pub mod rules;
#[cfg(feature = "zenoh")]
pub mod security;
pub mod seed;
pub mod view;
#[cfg(feature = "zenoh")]
pub mod zenoh_bus;

pub use codec::{decode, encode, encode_sized, CodecError, WIRE_VERSION};
pub use geometry::{CellIdx, Geometry, Pos};
pub use limits::InvalidCommand;
pub use message::*;
