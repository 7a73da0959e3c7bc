//! The estimation core: pure math, no I/O.
//!
//! | module | what |
//! |---|---|
//! | [`kalman`] | shared update and propagation routines (Joseph local update, joint update, `Psi`) |
//! | [`platform`] | the [`PlatformFilter`] trait every platform model implements; broadcasts |
//! | [`fix`] | an absolute position fix (GNSS) as a gated local update |
//! | [`ins`] | strapdown INS error-state EKF for land vehicles (odometer + non-holonomic constraints) |
//! | [`unicycle`] | planar unicycle robot |
//! | [`planar`] | a wheeled robot on the team's clock, driven by wheel odometry (what a node runs without an IMU) |
//! | [`commanded`] | a robot driven by its commands: the planar pose plus its speed scale and yaw-rate bias, first-estimate Jacobians |
//! | [`nav`] | the navigation filter a node runs: the INS or the planar robot, one type |
//! | [`linear`] | generic linear-Gaussian platform |
//! | [`coop`] | the paper's cooperative joint update and the cross-covariance store (Eq. 10) |
//! | [`dense`] | the joint update's rank-m downdate, symmetric and vectorised, rounded as nalgebra rounds it |
//! | [`ci`] | covariance-intersection baseline |
//! | [`coast`] | a state carried across a gap with nothing measured (a node restarted from its saved state) |
//! | [`team`] | a team under one [`Method`]: dead reckoning, no-propagation, decentralized, centralized, CI |
//! | [`consistency`] | NEES and chi-square bands |
//!
//! Frames: one convention end to end, MAVLink's: local NED (north, east, down; metres) and body
//! FRD (forward, right, down). Yaw is from north, clockwise seen from above. Time is [`TimeUs`](crate::time::TimeUs).

pub mod ci;
pub mod coast;
pub mod commanded;
pub mod consistency;
pub mod coop;
pub mod dense;
mod error;
pub mod fix;
pub mod inputs;
pub mod ins;
pub mod kalman;
pub mod linear;
pub mod nav;
pub mod planar;
pub mod platform;
pub mod spec;
pub mod team;
pub mod unicycle;

pub use coop::{
    BoundScope, BystanderShare, CoopMeasurement, Correction, CrossCovariances, CrossMode, EventOutcome, JointPrior, StoreError,
    StoreRef, UpdateOptions, cooperative_update, cooperative_update_with, split_ranged,
};
pub use error::EstimationError;
pub use inputs::{ImuSample, OdometerSample, PositionFixSample, RangeSample, WheelSample};
pub use kalman::{LinearizedMeasurement, UpdateDiagnostics};
pub use platform::{Geometry, Heading, PlatformFilter, PlatformId, Snapshot};
pub use team::{Method, Team};
