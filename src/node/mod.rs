//! The per-vehicle companion node: the sans-io modules of the `cooploc-node` crate (re-exported
//! here under the same names: `node::core`, `node::shell`, `node::profile`, ...), and the
//! adapters that give them sockets, files and a clock.
//!
//! | module | what |
//! |---|---|
//! | [`coop_link`] | the cooperative link: UDP (packed datagrams, unicast peers, a multicast group) or a serial radio |
//! | [`files`] | the files a node keeps across restarts (signing timestamp, navigation state), written whole or not at all |
//! | [`runner`] | the tokio runner that owns the sockets and the clock and carries out the shell's outputs |
//! | [`vehicle_link`] | the MAVLink connection to the vehicle (UDP, TCP, serial) |
//! | [`range_link`] | the ranging device's serial line or UDP socket, read on its own task |
//!
//! The sans-io modules are listed in `cooploc_node::node`.
pub use cooploc_node::node::*;

pub mod coop_link;
pub mod files;
pub mod range_link;
pub mod runner;
pub mod vehicle_link;
