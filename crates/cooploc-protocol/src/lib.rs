//! # cooploc-protocol
//!
//! The wire layer (see [`protocol`]): the cooploc MAVLink dialect generated from
//! `dialects/cooploc.xml`, the state records and their compact encoding, fragments, signing, the
//! byte budget, loss from sequence numbers, and every conversion between MAVLink messages and the
//! core's types. It uses the math and nothing above it.
//!
//! The layers below are re-exported under their module names, so a path reads the same in every
//! crate of the workspace (`crate::estimation::PlatformId`).
pub use cooploc_estimation::{estimation, geodesy, time};
pub mod protocol;

// The generated dialect code refers to `crate::utils`.
#[allow(unused_imports)]
use mavlink_core::utils;
