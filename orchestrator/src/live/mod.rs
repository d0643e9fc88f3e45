//! A running swarm watched and steered: the live viewer and the control plane.
//!
//! # Layout
//! - [`view`]: the live viewer's web server and page (`view.html`; `geese view`,
//!   `geese run --view`).
//! - [`watch`]: an in-process run with the viewer attached.
//! - [`control`]: `geese control`, perturbations and stop sent to a running world.
pub mod control;
pub mod view;
pub mod watch;
