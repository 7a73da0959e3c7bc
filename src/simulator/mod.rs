//! `cooploc sitl`: a scenario's vehicles as MAVLink systems.
//!
//! Each platform of the world becomes one MAVLink system (sysid = platform id, compid 1,
//! MAV_TYPE_GROUND_ROVER) on its own link, and streams what its sensors measure, in simulated
//! time, paced by a speed factor. With `--autopilot ardupilot|px4` it sends what that autopilot
//! sends instead (RAW_IMU and WHEEL_DISTANCE, or averaged HIGHRES_IMU; boot clocks and
//! SYSTEM_TIME; see [`personality`]) and checks the ODOMETRY and GPS_INPUT it gets back. The
//! simulator's own message set:
//!
//! | message | when (default) |
//! |---|---|
//! | HEARTBEAT | every simulated second (fixed) |
//! | HIGHRES_IMU | at every IMU sample (200 Hz in the paper scenario) |
//! | ODOMETRY | at every odometer sample; body-frame (BODY_FRD) forward velocity, pose unknown (NaN) |
//! | SIM_STATE | 10 Hz: truth (attitude, lat/lon about the origin, NED velocity) |
//! | COOPLOC_RANGE | at every ranging epoch, one per range this vehicle's radio measured; epochs numbered from 1 |
//!
//! Each vehicle answers MAV_CMD_SET_MESSAGE_INTERVAL, MAV_CMD_GET_MESSAGE_INTERVAL and
//! MAV_CMD_REQUEST_MESSAGE (COMMAND_LONG or COMMAND_INT) with COMMAND_ACK; see [`vehicle`]. It
//! serves a small read-only parameter table (PARAM_REQUEST_LIST, PARAM_REQUEST_READ, PARAM_SET
//! answered with the unchanged value) so that a ground station's parameter fetch completes; see
//! [`params`].
//! Rates are per vehicle: every peer of a vehicle sees the same streams.
//!
//! ## Time
//!
//! Everything runs on simulated time: message timestamps (`time_usec`), the HEARTBEAT period,
//! SIM_STATE and every interval set by command. [`Speed`] only maps simulated time to wall time
//! (`--speed 1`: real time; `max`: no waiting). A run that falls behind its schedule catches up
//! without waiting. With `wait_for_peers` the clock holds at zero until every vehicle has a peer.
//!
//! - [`vehicle`]: the sans-io core of one vehicle (streams, intervals, commands, sequence numbers).
//! - [`params`]: the parameter table.
//! - [`personality`]: the autopilots' message sets, their acceptance checks, and
//!   [`personality::decoded_run`], the offline experiment of what a node decodes from them.
//! - [`Simulator`]: the tokio runner that owns the links and the clock.
//!
//! ## Links
//!
//! A UDP vehicle binds one socket (by default `--bind` address, port `--base-port + id`, PX4
//! style: vehicle 1 on 14541). It sends its streams to (a) every configured `udpout` target and
//! (b) every peer it has heard a valid MAVLink frame from (up to [`MAX_UDP_PEERS`], forgotten
//! after [`UDP_PEER_TIMEOUT`] of silence). Replies to a command go to the sender only. So a
//! client either connects to the vehicle's port and sends first (`udpout:127.0.0.1:14541` in
//! mavlink URL terms: `cooploc node --vehicle udpout:127.0.0.1:14541`, `mavproxy.py
//! --master=udpout:127.0.0.1:14541`; both send a HEARTBEAT at once), or listens and is named as
//! the vehicle's target (`--vehicle 1=udpout:127.0.0.1:14550` here, `udpin:127.0.0.1:14550` on
//! the client side). A serial link (a device or a pseudo-terminal) carries one peer.

pub mod params;
pub mod personality;
pub mod runner;
pub mod vehicle;

pub use personality::{Autopilot, Checker};
pub use runner::*;
pub use vehicle::{
    COMPONENT_ID, Destination, Interval, Outgoing, Stream, StreamDefaults, VehicleConfig, VehicleCore, VehicleCounters,
};
