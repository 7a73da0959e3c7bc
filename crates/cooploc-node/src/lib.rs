//! # cooploc-node
//!
//! `cooploc node` without its sockets (see [`node`]): the protocol as a state machine (`core`),
//! the shell between the sockets and the core (`shell`: bytes and clock readings in, ordered
//! outputs out), the vehicle profile and the autopilots' messages decoded, the peers, the log's
//! schema and the saved state. Its tokio runner and links live in the `cooploc` crate
//! (`cooploc::node::runner`); the simulated world is not a dependency.
//!
//! The layers below are re-exported under their module names, so a path reads the same in every
//! crate of the workspace (`crate::protocol::MavMessage`).
pub use cooploc_estimation::{estimation, geodesy, time};
pub use cooploc_protocol::protocol;
pub mod node;
