//! # cooploc-sitl
//!
//! The simulated world (see [`sitl`]): truth trajectories, sensor error models and the scenario
//! files of the top-level `sitl/scenarios/` folder. Above the math, beside the wire; the node
//! does not depend on it (its tests do).
//!
//! The layers below are re-exported under their module names, so a path reads the same in every
//! crate of the workspace (`crate::estimation::PlatformId`).
pub use cooploc_estimation::{estimation, geodesy, time};
pub mod sitl;
