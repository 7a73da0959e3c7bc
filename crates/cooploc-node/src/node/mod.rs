//! The per-vehicle companion node, sans-io (its sockets, files and tokio runner are the
//! `cooploc` crate's `cooploc::node`, which re-exports this module's).
//!
//! | module | what |
//! |---|---|
//! | [`core`] | the whole cooperative protocol as a pure state machine (inputs in, messages out, no sockets, no clocks): the epoch book in `core.rs`, the filter's checkpoints and replays in `core/rewind.rs`, the stores kept, wanted and given in `core/store_sync.rs`, each with its unit tests |
//! | [`profile`] | the vehicle profile (`--vehicle-config`): sensor figures, which messages to read, what to send back |
//! | [`inputs`] | what an autopilot sends (ArduPilot, PX4, the simulator), as the core's samples in the team's clock |
//! | [`autopilot`] | rate requests (SET_MESSAGE_INTERVAL) and the estimate fed back as ODOMETRY |
//! | [`autopilot_fix`] | the autopilot's own estimate as far as its EKF vouches for it: where a restarted node takes its heading (and position) from |
//! | [`peers`] | where the cooperative traffic goes: given peers, team members, a few ground stations, bounded and expiring |
//! | [`cadence`] | the retry interval, following the team's epoch cadence in wall time |
//! | [`shell`] | the node between its sockets and its core, sans-io: datagrams and vehicle frames split, checked and decoded, the start, the ticks, what goes back; bytes and clock readings in, ordered outputs out |
//! | [`saved`] | the node's last navigation state on disk (`--state-file`): what a restarted node starts from |
//! | [`error`] | what can stop a node (`NodeError`): links that do not open, settings, a vehicle that goes away |
//! | [`survey`] | `cooploc check`: what an autopilot sends against what a profile needs, and the parameters to set |
//! | [`vetting`] | which records an epoch runs on: refused when the teammates' ranges contradict them, or when a platform sent two different ones |
//! | [`ranging`] | a ranging device on the companion (a UWB module): its line stream, as the core's own ranges |
pub mod autopilot;
pub mod autopilot_fix;
pub mod cadence;
pub mod core;
pub mod error;
pub mod handover;
pub mod inputs;
pub mod log;
pub mod peers;
pub mod profile;
pub mod ranging;
pub mod saved;
pub mod shell;
pub mod survey;
pub mod vetting;
