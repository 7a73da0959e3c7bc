//! The per-vehicle companion node.
//!
//! | module | what |
//! |---|---|
//! | [`core`] | the whole cooperative protocol as a pure state machine (inputs in, messages out, no sockets, no clocks) |
//! | [`profile`] | the vehicle profile (`--vehicle-config`): sensor figures, which messages to read, what to send back |
//! | [`inputs`] | what an autopilot sends (ArduPilot, PX4, the simulator), as the core's samples in the team's clock |
//! | [`autopilot`] | rate requests (SET_MESSAGE_INTERVAL) and the estimate fed back as ODOMETRY |
//! | [`coop_link`] | the cooperative link: UDP (packed datagrams, unicast peers, a multicast group) or a serial radio |
//! | [`peers`] | where the cooperative traffic goes: given peers, team members, a few ground stations, bounded and expiring |
//! | [`cadence`] | the retry interval, following the team's epoch cadence in wall time |
//! | [`shell`] | the node between its sockets and its core, sans-io: datagrams and vehicle frames split, checked and decoded, the start, the ticks, what goes back; bytes and clock readings in, ordered outputs out |
//! | [`files`] | the files a node keeps across restarts (signing timestamp, navigation state), written whole or not at all |
//! | [`saved`] | the node's last navigation state on disk (`--state-file`): what a restarted node starts from |
//! | [`runner`] | the tokio runner that owns the sockets and the clock and carries out the shell's outputs |
//! | [`error`] | what can stop a node (`NodeError`): links that do not open, settings, a vehicle that goes away |
//! | [`vehicle_link`] | the MAVLink connection to the vehicle (UDP, TCP, serial) |
//! | [`survey`] | `cooploc check`: what an autopilot sends against what a profile needs, and the parameters to set |
//! | [`vetting`] | which records an epoch runs on: refused when the teammates' ranges contradict them, or when a platform sent two different ones |
//! | [`ranging`] | a ranging device on the companion (a UWB module): its line stream, as the core's own ranges |
//! | [`range_link`] | the ranging device's serial line or UDP socket, read on its own task |
pub mod autopilot;
pub mod cadence;
pub mod coop_link;
pub mod core;
pub mod error;
pub mod files;
pub mod handover;
pub mod inputs;
pub mod log;
pub mod peers;
pub mod profile;
pub mod range_link;
pub mod ranging;
pub mod runner;
pub mod saved;
pub mod shell;
pub mod survey;
pub mod vehicle_link;
pub mod vetting;
