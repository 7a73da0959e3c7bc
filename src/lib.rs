//! # cooploc
//!
//! Decentralized cooperative localization of vehicle teams over MAVLink, after Wang et al.,
//! *Decentralized Collaborative Localization Algorithm Based on Covariance Propagation*.
//!
//! The crate is laid out by concern. The lower layers are crates of their own (docs/architecture.md,
//! "Crates"), re-exported here under the same names: `estimation`, `time` and `geodesy`
//! (`cooploc-estimation`), `sitl` (`cooploc-sitl`), `protocol` (`cooploc-protocol`), and the node's
//! sans-io modules (`cooploc-node`, under [`node`] beside the node's adapters).
//!
//! - [`estimation`]: the pure math. Per-platform filters (a strapdown INS with odometer and
//!   non-holonomic constraints, a planar unicycle, a generic linear model), the recursive
//!   coefficient matrix Psi, the cooperative joint update, and the baselines (dead reckoning,
//!   no-propagation, centralized EKF, covariance intersection). No sockets, files, clocks or
//!   async: state in, state out.
//! - [`protocol`]: the cooploc MAVLink dialect (generated), state records and their compact
//!   encoding, fragmentation and reassembly, signing, the byte budget, and every conversion
//!   between the wire and the core's types ([`protocol::wire`]).
//! - [`node`]: `cooploc node`, the per-vehicle companion: the protocol as a pure state machine
//!   (`core`), the vehicle profile and what autopilots send, decoded (`profile`, `inputs`), the
//!   peers and the cooperative link, and a tokio runner.
//! - [`experiment`]: the paper's Monte Carlo experiment (pure), its report and plots, and the
//!   fault-injection harness on the node cores.
//! - [`replay`]: `cooploc replay`, a log fed back through the node cores (bit for bit) and
//!   through every method offline.
//! - [`demo`]: `cooploc demo`, simulator, nodes and ground station in one process.
//! - [`sitl`]: the simulated world (truth trajectories, sensor error models, scenario files).
//!   Its scenario files live in the top-level `sitl/` folder.
//! - [`simulator`]: `cooploc sitl`, the world's vehicles as MAVLink systems (a sans-io vehicle
//!   core and a tokio runner).
//! - [`recording`]: MCAP logs (raw MAVLink frames, Foxglove views of the estimates, filter
//!   internals): the recorder and a reader tolerant of truncated files.
//! - [`gcs`]: `cooploc gcs`, the ground station (a sans-io core, its web page and JSON API, the
//!   Foxglove live server, and a tokio runner).
//! - [`view`]: one view of the team for every display (names, colours, frames, ellipses, the
//!   team's health; the Foxglove messages), so the page, live Foxglove and logs agree.
//! - [`dataset`]: real data sets (UTIAS MRCLAM): the reader, the model every method runs on
//!   them, their MCAP logs.
//! - [`geodesy`]: the team's origin on the Earth and NED <-> latitude/longitude.
//! - [`time`]: the typed timestamp shared by all of the above.
//!
//! The `cooploc` binary (`src/bin/cooploc/`, one file per command) only parses arguments,
//! calls the library and prints.
pub use cooploc_estimation::{estimation, geodesy, time};
pub use cooploc_protocol::protocol;
pub use cooploc_sitl::sitl;

pub mod dataset;
pub mod demo;
pub mod experiment;
pub mod gcs;
pub mod node;
pub mod recording;
pub mod replay;
pub mod simulator;
pub mod view;
