//! # cooploc-estimation
//!
//! The pure math of cooploc (the bottom layer, docs/architecture.md): per-platform filters (a
//! strapdown INS with odometer and non-holonomic constraints, a planar unicycle, a generic linear
//! model), the recursive coefficient matrix Psi, the cooperative joint update, the baselines
//! (dead reckoning, no-propagation, centralized EKF, covariance intersection), consistency
//! measures, and the vehicle's description in numbers ([`estimation::spec`]). No sockets, files,
//! clocks or async: state in, state out.
//!
//! - [`estimation`]: the filters and the update.
//! - [`geodesy`]: the team's origin on the Earth and NED <-> latitude/longitude.
//! - [`time`]: the typed timestamp every layer shares.
//!
//! The modules keep the names they have in the `cooploc` crate (`cooploc::estimation` is this
//! crate's `estimation`), so a path reads the same in every crate of the workspace.
pub mod estimation;
pub mod geodesy;
pub mod time;
