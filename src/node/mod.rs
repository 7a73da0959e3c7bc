//! The per-vehicle companion node: [`core`] is the whole protocol as a pure state machine (inputs
//! in, messages out, no sockets, no clocks); the tokio runner that owns the sockets comes on top.
pub mod core;
pub mod inputs;
pub mod profile;
pub mod runner;
pub mod vehicle_link;
