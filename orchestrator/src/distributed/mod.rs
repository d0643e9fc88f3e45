//! The distributed mode: the world and agent processes over Zenoh, and the security of
//! a run across processes and hosts.
//!
//! # Layout
//! - [`launch`]: `geese run --processes N` and `geese router`: starts the world and agent
//!   processes, follows the run, runs campaign trials over Zenoh.
//! - [`bench_net`]: the distributed benchmark (lock-step rate over Zenoh, bare and
//!   learning; `geese bench-net`).
//! - [`secure`]: `geese secure init`, the credentials and access-control list of a run
//!   started by hand or across hosts.
pub mod bench_net;
pub mod launch;
pub mod secure;
