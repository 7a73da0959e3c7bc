//! The cooploc MAVLink dialect and the one place where the wire meets the core's types.
//!
//! - [`dialect`]: Rust generated at build time by mavlink-bindgen from `dialects/cooploc.xml`
//!   (which includes the vendored ardupilotmega.xml and through it common.xml): every common
//!   and ArduPilot message plus the cooploc ones.
//! - [`record`]: the state broadcast as bytes (layout, quantisation rule); [`compact`]: its
//!   16-bit correlation-form matrices.
//! - [`fragment`]: cutting records into COOPLOC_STATE_FRAGMENT payloads and reassembling them.
//! - [`budget`]: the bytes a team sends, per node and in all, and what links carry them.
//! - [`sequence`]: loss from MAVLink sequence numbers, the one rule of the node, the ground
//!   station and the MAVProxy module.
//! - [`wire`]: conversions between generated messages and the core's types (units, packing).

pub mod budget;
pub mod compact;
pub mod coop;
pub mod fragment;
pub mod framing;
pub mod record;
pub mod sequence;
pub mod signing;
pub mod wire;

/// Generated bindings of `dialects/cooploc.xml`.
#[allow(clippy::all, missing_docs, unused_imports, unexpected_cfgs)]
pub mod dialect {
    include!(concat!(env!("OUT_DIR"), "/mod.rs"));
}

pub use dialect::cooploc::MavMessage;
