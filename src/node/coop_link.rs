//! The node's cooperative link: how its frames reach the team and theirs reach it.
//!
//! - **UDP** ([`CoopLink::Udp`]): one socket for everything the node sends (its unicast
//!   address, so peers tell the nodes of one machine apart) and, with a multicast group, a
//!   second socket that only receives the group. Each batch of frames (an epoch's record, its
//!   ranges, its estimate) is packed into datagrams of at most `max_datagram` bytes
//!   ([`crate::protocol::budget::pack`], the rule `cooploc budget` counts) and each datagram
//!   goes once to the group and once to each unicast peer.
//! - **Multicast** ([`Multicast`]): the plug-and-play LAN transport. Nodes need no peer list:
//!   every frame goes once to the group (a radio-like medium: one copy per frame, whatever the
//!   team size), with a TTL (1: this subnet) and an interface. Loopback is on so several nodes of
//!   one machine hear each other. A peer heard on the group is not also sent to by unicast (see
//!   [`super::peers::PeerTable`]); a given peer never heard there (another subnet, a routed link)
//!   always is.
//! - **Serial** ([`CoopLink::Serial`]): a telemetry radio's serial port (`PATH:BAUD`), a byte
//!   stream shared by the team (a multipoint SiK or mesh firmware). Frames are written as they
//!   are (no packing, no addresses); what comes in is cut back into frames by a
//!   [`StreamFramer`] that resynchronises after noise, so a corrupted byte costs its frame only.
//!   Writes go through a bounded queue: a radio slower than the node drops whole batches
//!   (counted), it never stalls the filter.

use super::error::NodeError;
pub use super::peers::Source;
use std::net::{Ipv4Addr, SocketAddr, SocketAddrV4};

use tokio::io::{AsyncReadExt as _, AsyncWriteExt as _};
use tokio::net::UdpSocket;

use crate::protocol::budget;

/// Default multicast group of the cooperative network (administratively scoped, 239/8).
pub const DEFAULT_GROUP: SocketAddrV4 = SocketAddrV4::new(Ipv4Addr::new(239, 255, 76, 67), 14_660);

/// A multicast group to send to and listen on.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Multicast {
    pub group: SocketAddrV4,
    /// Hops a datagram may cross (1: this subnet only).
    pub ttl: u32,
    /// Address of the interface to send and join on (unspecified: the bound address's, or the
    /// kernel's choice).
    pub interface: Ipv4Addr,
    /// Asked for by name: failing to join is an error. Otherwise (the LAN default) the node
    /// says why and goes on with its unicast peers.
    pub required: bool,
}

impl Default for Multicast {
    fn default() -> Self {
        Multicast { group: DEFAULT_GROUP, ttl: 1, interface: Ipv4Addr::UNSPECIFIED, required: true }
    }
}

/// What the node was asked to use for its cooperative traffic.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum CoopSpec {
    /// A UDP socket bound to `bind`, with an optional multicast group; datagrams of at most
    /// `max_datagram` bytes (0 or a single frame's size: one frame per datagram).
    Udp { bind: SocketAddr, multicast: Option<Multicast>, max_datagram: usize },
    /// A serial device (a telemetry radio), `baud` bits per second.
    Serial { path: String, baud: u32 },
}

impl CoopSpec {
    /// UDP on `bind`, frames packed into Ethernet-sized datagrams, no group.
    pub fn udp(bind: SocketAddr) -> Self {
        CoopSpec::Udp { bind, multicast: None, max_datagram: budget::MAX_DATAGRAM }
    }

    /// Parses `PATH:BAUD` of a serial radio.
    pub fn serial(text: &str) -> Result<Self, String> {
        let (path, baud) =
            text.rsplit_once(':').ok_or_else(|| format!("{text:?}: expected PATH:BAUD, e.g. /dev/ttyUSB0:57600"))?;
        let baud: u32 = baud.parse().map_err(|_| format!("{text:?}: baud {baud:?} is not a whole number"))?;
        if path.is_empty() || !(1200..=4_000_000).contains(&baud) {
            return Err(format!("{text:?}: expected a device path and a baud rate of 1200 to 4000000"));
        }
        Ok(CoopSpec::Serial { path: path.to_string(), baud })
    }
}

/// Most bytes of a serial stream kept while waiting for the end of a frame.
const FRAMER_KEEP: usize = 16 * 1024;

/// Cuts a byte stream back into MAVLink frames: skips bytes until a start marker, waits for the
/// frame's length, keeps it when it parses (CRC and a message of the dialect), and otherwise
/// skips the marker alone and looks again (a length byte hit by noise must not swallow the
/// frames behind it).
#[derive(Debug, Default)]
pub struct StreamFramer {
    buf: Vec<u8>,
    /// Bytes skipped as noise, for the summary.
    pub skipped: u64,
}

impl StreamFramer {
    /// Adds `bytes`; returns the complete valid frames now available, concatenated (a "datagram"
    /// for the verifier and the decoder).
    pub fn push(&mut self, bytes: &[u8]) -> Vec<u8> {
        self.buf.extend_from_slice(bytes);
        let mut out = Vec::new();
        let mut at = 0;
        loop {
            let Some(start) = self.buf[at..].iter().position(|&b| b == 0xFD || b == 0xFE) else {
                self.skipped += (self.buf.len() - at) as u64;
                at = self.buf.len();
                break;
            };
            self.skipped += start as u64;
            at += start;
            let Some(len) = crate::protocol::framing::frame_len(&self.buf[at..]) else {
                break; // not all there yet
            };
            // A frame of the dialect that decodes, or one of another dialect taken by its
            // length (an autopilot's own messages: see `protocol::framing`).
            let whole = crate::protocol::framing::frame_at_start(&self.buf[at..]).is_some_and(|f| !f.known || f.message.is_ok());
            if whole {
                out.extend_from_slice(&self.buf[at..at + len]);
                at += len;
            } else {
                self.skipped += 1;
                at += 1;
            }
        }
        self.buf.drain(..at);
        if self.buf.len() > FRAMER_KEEP {
            let drop = self.buf.len() - FRAMER_KEEP;
            self.skipped += drop as u64;
            self.buf.drain(..drop);
        }
        out
    }
}

/// Batches queued for a serial radio before new ones are dropped.
const SERIAL_QUEUE: usize = 64;

/// An open cooperative link.
pub enum CoopLink {
    Udp {
        socket: UdpSocket,
        /// The group's receive socket and address.
        group: Option<(UdpSocket, SocketAddr)>,
        max_datagram: usize,
    },
    Serial {
        /// Batches to write, in order.
        tx: tokio::sync::mpsc::Sender<Vec<u8>>,
        /// Byte runs read.
        rx: tokio::sync::Mutex<tokio::sync::mpsc::Receiver<Vec<u8>>>,
        framer: std::sync::Mutex<StreamFramer>,
        dropped: std::sync::atomic::AtomicU64,
        device: String,
    },
}

/// What went out.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct Sent {
    pub datagrams: u64,
    pub bytes: u64,
}

/// The datagram waiting on a readable `socket`, marked by `source`; None when it was taken
/// meanwhile (a spurious wake-up).
fn take(socket: &UdpSocket, buf: &mut [u8], source: fn(SocketAddr) -> Source) -> Option<std::io::Result<(usize, Source)>> {
    match socket.try_recv_from(buf) {
        Ok((n, a)) => Some(Ok((n, source(a)))),
        Err(e) if e.kind() == std::io::ErrorKind::WouldBlock => None,
        Err(e) => Some(Err(e)),
    }
}

/// Joins `m.group` on a socket bound to the group's port (shared with the other nodes of this
/// machine), receive-only.
fn group_socket(m: &Multicast, recv_buffer: usize) -> std::io::Result<UdpSocket> {
    use socket2::{Domain, Protocol, Socket, Type};
    let socket = Socket::new(Domain::IPV4, Type::DGRAM, Some(Protocol::UDP))?;
    socket.set_reuse_address(true)?;
    let _ = socket.set_recv_buffer_size(recv_buffer);
    socket.set_nonblocking(true)?;
    // Bound to the group address: this socket gets the group's datagrams, not unicast ones to
    // the port.
    socket.bind(&SocketAddr::V4(SocketAddrV4::new(*m.group.ip(), m.group.port())).into())?;
    socket.join_multicast_v4(m.group.ip(), &m.interface)?;
    UdpSocket::from_std(socket.into())
}

/// Sets `socket` up to send to `m.group` and opens the group's receive socket.
fn join(socket: &UdpSocket, bind: &SocketAddr, m: &Multicast, recv_buffer: usize) -> Result<(UdpSocket, SocketAddr), NodeError> {
    if !m.group.ip().is_multicast() {
        return Err(NodeError::Invalid(format!("multicast group {}: not a multicast address (224.0.0.0/4)", m.group)));
    }
    if !bind.is_ipv4() {
        return Err(NodeError::Invalid(format!("multicast group {}: the cooperative socket must be IPv4, not {bind}", m.group)));
    }
    let s = socket2::SockRef::from(socket);
    s.set_multicast_ttl_v4(m.ttl).map_err(NodeError::io("multicast TTL"))?;
    s.set_multicast_loop_v4(true).map_err(NodeError::io("multicast loopback"))?;
    let iface = match (m.interface.is_unspecified(), bind.ip()) {
        (true, std::net::IpAddr::V4(ip)) if !ip.is_unspecified() => ip,
        _ => m.interface,
    };
    s.set_multicast_if_v4(&iface).map_err(NodeError::io(format!("multicast interface {iface}")))?;
    let joined = group_socket(&Multicast { interface: iface, ..*m }, recv_buffer)
        .map_err(NodeError::io(format!("joining multicast group {} on interface {iface}", m.group)))?;
    Ok((joined, SocketAddr::V4(m.group)))
}

impl CoopLink {
    /// Opens the link: binds the sockets (with `recv_buffer` bytes of receive buffer) or the
    /// serial device.
    pub async fn open(spec: &CoopSpec, recv_buffer: usize) -> Result<Self, NodeError> {
        match spec {
            CoopSpec::Udp { bind, multicast, max_datagram } => {
                let socket = super::vehicle_link::bind_udp(*bind, recv_buffer)
                    .map_err(NodeError::io(format!("binding the cooperative socket {bind}")))?;
                let group = match multicast {
                    Some(m) => match join(&socket, bind, m, recv_buffer) {
                        Ok(g) => Some(g),
                        Err(e) if !m.required => {
                            tracing::warn!(error = %e, "no multicast on this link: sending to unicast peers only");
                            None
                        }
                        Err(e) => return Err(e),
                    },
                    None => None,
                };
                Ok(CoopLink::Udp { socket, group, max_datagram: *max_datagram })
            }
            CoopSpec::Serial { path, baud } => {
                use tokio_serial::SerialPortBuilderExt as _;
                let port = tokio_serial::new(path, *baud)
                    .open_native_async()
                    .map_err(|e| NodeError::Invalid(format!("opening the cooperative radio {path} at {baud} baud: {e}")))?;
                let (mut reader, mut writer) = tokio::io::split(port);
                let (tx, mut wrx) = tokio::sync::mpsc::channel::<Vec<u8>>(SERIAL_QUEUE);
                let (rtx, rx) = tokio::sync::mpsc::channel::<Vec<u8>>(1024);
                tokio::spawn(async move {
                    while let Some(bytes) = wrx.recv().await {
                        if let Err(e) = writer.write_all(&bytes).await {
                            tracing::warn!(error = %e, "cooperative radio write error");
                        }
                    }
                });
                tokio::spawn(async move {
                    let mut buf = vec![0u8; 4096];
                    loop {
                        match reader.read(&mut buf).await {
                            Ok(0) => tokio::time::sleep(std::time::Duration::from_millis(10)).await,
                            Ok(n) => {
                                if rtx.send(buf[..n].to_vec()).await.is_err() {
                                    return;
                                }
                            }
                            Err(e) => {
                                tracing::warn!(error = %e, "cooperative radio read error");
                                tokio::time::sleep(std::time::Duration::from_millis(100)).await;
                            }
                        }
                    }
                });
                Ok(CoopLink::Serial {
                    tx,
                    rx: tokio::sync::Mutex::new(rx),
                    framer: std::sync::Mutex::new(StreamFramer::default()),
                    dropped: 0.into(),
                    device: path.clone(),
                })
            }
        }
    }

    /// The unicast socket's address, or None for a radio.
    pub fn local_addr(&self) -> Option<SocketAddr> {
        match self {
            CoopLink::Udp { socket, .. } => socket.local_addr().ok(),
            CoopLink::Serial { .. } => None,
        }
    }

    /// The multicast group, when there is one.
    pub fn group(&self) -> Option<SocketAddr> {
        match self {
            CoopLink::Udp { group, .. } => group.as_ref().map(|(_, g)| *g),
            CoopLink::Serial { .. } => None,
        }
    }

    /// What this link is, in words (for the log).
    pub fn describe(&self) -> String {
        match self {
            CoopLink::Udp { socket, group, max_datagram } => {
                let local = socket.local_addr().map(|a| a.to_string()).unwrap_or_default();
                match group {
                    Some((_, g)) => format!("udp {local}, multicast {g}, datagrams <= {max_datagram} B"),
                    None => format!("udp {local}, datagrams <= {max_datagram} B"),
                }
            }
            CoopLink::Serial { device, .. } => format!("serial {device}"),
        }
    }

    /// Batches a radio could not take (its queue was full).
    pub fn dropped(&self) -> u64 {
        match self {
            CoopLink::Serial { dropped, .. } => dropped.load(std::sync::atomic::Ordering::Relaxed),
            CoopLink::Udp { .. } => 0,
        }
    }

    /// Sends `frames` (in order) to the group and every unicast address (UDP, packed), or onto
    /// the radio.
    pub async fn send(&self, frames: &[Vec<u8>], unicast: &[SocketAddr]) -> Sent {
        let mut sent = Sent::default();
        if frames.is_empty() {
            return sent;
        }
        match self {
            CoopLink::Udp { socket, group, max_datagram } => {
                let datagrams = budget::pack(frames, *max_datagram);
                let to = group.iter().map(|(_, g)| *g).chain(unicast.iter().copied());
                for addr in to {
                    for d in &datagrams {
                        if socket.send_to(d, addr).await.is_ok() {
                            sent.datagrams += 1;
                            sent.bytes += d.len() as u64;
                        }
                    }
                }
            }
            CoopLink::Serial { tx, dropped, .. } => {
                let bytes = frames.concat();
                let n = bytes.len() as u64;
                if tx.try_send(bytes).is_ok() {
                    sent.datagrams += 1;
                    sent.bytes += n;
                } else {
                    dropped.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
                }
            }
        }
        sent
    }

    /// Receives the next run of frames into `buf`: its length and where it came from. A radio's
    /// run holds only complete frames that parsed (possibly none).
    pub async fn recv(&self, buf: &mut Vec<u8>) -> std::io::Result<(usize, Source)> {
        match self {
            CoopLink::Udp { socket, group: None, .. } => {
                let (n, a) = socket.recv_from(buf).await?;
                Ok((n, Source::Unicast(a)))
            }
            CoopLink::Udp { socket, group: Some((g, _)), .. } => loop {
                // Whichever socket has a datagram (both readiness waits are cancel-safe).
                let got = tokio::select! {
                    r = socket.readable() => { r?; take(socket, buf, Source::Unicast) }
                    r = g.readable() => { r?; take(g, buf, Source::Group) }
                };
                if let Some(got) = got {
                    return got;
                }
            },
            CoopLink::Serial { rx, framer, .. } => {
                let Some(bytes) = rx.lock().await.recv().await else {
                    return Err(std::io::Error::new(std::io::ErrorKind::BrokenPipe, "cooperative radio closed"));
                };
                let frames = framer.lock().unwrap_or_else(|e| e.into_inner()).push(&bytes);
                buf.clear();
                buf.extend_from_slice(&frames);
                Ok((frames.len(), Source::Radio))
            }
        }
    }

    /// Noise bytes a radio's framer skipped.
    pub fn noise_bytes(&self) -> u64 {
        match self {
            CoopLink::Serial { framer, .. } => framer.lock().unwrap_or_else(|e| e.into_inner()).skipped,
            CoopLink::Udp { .. } => 0,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Links that cannot open say which step failed and why, as typed errors: a group that is
    /// not a multicast address (asked for by name), a radio device that is not there.
    #[tokio::test]
    async fn links_that_cannot_open_name_the_step() {
        let bind: SocketAddr = "127.0.0.1:0".parse().unwrap();
        let group = Multicast { group: "10.1.2.3:14550".parse().unwrap(), required: true, ..Multicast::default() };
        let spec = CoopSpec::Udp { bind, multicast: Some(group), max_datagram: 0 };
        match CoopLink::open(&spec, 1 << 16).await {
            Err(NodeError::Invalid(m)) => assert!(m.contains("not a multicast address"), "{m}"),
            Err(e) => panic!("unexpected error {e}"),
            Ok(_) => panic!("a unicast address taken as a group"),
        }
        let spec = CoopSpec::Serial { path: "/dev/cooploc-no-such-radio".into(), baud: 57_600 };
        let e = CoopLink::open(&spec, 1 << 16).await.err().expect("no such device");
        assert!(e.to_string().contains("opening the cooperative radio /dev/cooploc-no-such-radio at 57600 baud"), "{e}");
        let taken = std::net::UdpSocket::bind("127.0.0.1:0").unwrap();
        let spec = CoopSpec::udp(taken.local_addr().unwrap());
        match CoopLink::open(&spec, 1 << 16).await {
            Err(NodeError::Io { what, source }) => {
                assert!(what.starts_with("binding the cooperative socket 127.0.0.1:"), "{what}");
                assert_eq!(source.kind(), std::io::ErrorKind::AddrInUse);
            }
            Err(e) => panic!("unexpected error {e}"),
            Ok(_) => panic!("bound a port already taken"),
        }
    }
    use crate::protocol::dialect::cooploc::{MavAutopilot, MavType};
    use crate::protocol::wire;
    use mavlink_core::MavHeader;

    fn hb(seq: u8) -> Vec<u8> {
        let msg = wire::heartbeat(MavType::MAV_TYPE_GROUND_ROVER, MavAutopilot::MAV_AUTOPILOT_ARDUPILOTMEGA);
        wire::to_frame(MavHeader { system_id: 1, component_id: 1, sequence: seq }, &msg)
    }

    fn seqs(run: &[u8]) -> Vec<u8> {
        wire::frames(run).iter().map(|(h, _)| h.sequence).collect()
    }

    #[test]
    fn the_framer_cuts_a_stream_into_frames_whatever_the_chunks() {
        let stream = [hb(1), hb(2), hb(3), hb(4)].concat();
        for chunk in [1, 2, 5, 7, 13, stream.len()] {
            let mut f = StreamFramer::default();
            let mut got = Vec::new();
            for c in stream.chunks(chunk) {
                got.extend(f.push(c));
            }
            assert_eq!(got, stream, "chunks of {chunk}");
            assert_eq!(f.skipped, 0);
        }
    }

    #[test]
    fn the_framer_loses_only_the_frame_noise_hit_and_resynchronises() {
        // Noise before, a corrupted frame (its length byte hit: it claims a longer payload and
        // would swallow the frames behind it), noise between, a truncated frame's start.
        let mut bad = hb(2);
        bad[1] = 200;
        let mut stream = [b"\x00\xFD\x13noise".to_vec(), hb(1), bad, b"\xFE\x01".to_vec(), hb(3), hb(4)[..5].to_vec()].concat();
        stream.extend((5..20).flat_map(hb));
        let mut f = StreamFramer::default();
        let mut got = Vec::new();
        for c in stream.chunks(9) {
            got.extend(f.push(c));
        }
        let mut want = vec![1, 3];
        want.extend(5..20);
        assert_eq!(seqs(&got), want, "the damaged and truncated frames are lost, nothing else");
        assert!(f.skipped > 0);
        // Endless noise does not grow the buffer.
        let mut f = StreamFramer::default();
        for _ in 0..100 {
            f.push(&[0xFD, 0xFF, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00].repeat(100));
        }
        assert!(f.buf.len() <= FRAMER_KEEP);
    }

    #[test]
    fn serial_specs_name_what_is_wrong() {
        assert_eq!(CoopSpec::serial("/dev/ttyUSB0:57600"), Ok(CoopSpec::Serial { path: "/dev/ttyUSB0".into(), baud: 57_600 }));
        for bad in ["/dev/ttyUSB0", "/dev/ttyUSB0:fast", ":57600", "/dev/ttyUSB0:12"] {
            let e = CoopSpec::serial(bad).unwrap_err();
            assert!(e.contains(bad), "{e}");
        }
    }

    #[tokio::test]
    async fn udp_packs_a_batch_into_few_datagrams_and_sends_each_to_every_peer() {
        let a = CoopLink::open(&CoopSpec::udp("127.0.0.1:0".parse().unwrap()), 1 << 20).await.unwrap();
        let b = UdpSocket::bind("127.0.0.1:0").await.unwrap();
        let c = UdpSocket::bind("127.0.0.1:0").await.unwrap();
        let frames: Vec<Vec<u8>> = (0..60).map(hb).collect();
        let per = budget::datagrams(&frames.iter().map(Vec::len).collect::<Vec<_>>(), true);
        assert!(per < 60 / 4, "{per} datagrams for 60 heartbeats");
        let sent = a.send(&frames, &[b.local_addr().unwrap(), c.local_addr().unwrap()]).await;
        assert_eq!(sent.datagrams, 2 * per as u64);
        assert_eq!(sent.bytes, 2 * frames.iter().map(|f| f.len() as u64).sum::<u64>());
        let mut got = Vec::new();
        let mut buf = [0u8; 2048];
        for _ in 0..per {
            let (n, _) = b.recv_from(&mut buf).await.unwrap();
            assert!(n <= budget::MAX_DATAGRAM);
            got.extend(seqs(&buf[..n]));
        }
        assert_eq!(got, (0..60).collect::<Vec<u8>>(), "every frame once, in order");
        // One frame per datagram when asked.
        let one =
            CoopLink::open(&CoopSpec::Udp { bind: "127.0.0.1:0".parse().unwrap(), multicast: None, max_datagram: 0 }, 1 << 20)
                .await
                .unwrap();
        assert_eq!(one.send(&frames[..3], &[c.local_addr().unwrap()]).await.datagrams, 3);
    }

    #[tokio::test]
    async fn a_group_that_is_not_multicast_is_refused_by_name() {
        let spec = CoopSpec::Udp {
            bind: "127.0.0.1:0".parse().unwrap(),
            multicast: Some(Multicast { group: "10.0.0.1:14660".parse().unwrap(), ..Multicast::default() }),
            max_datagram: 1472,
        };
        let e = CoopLink::open(&spec, 1 << 20).await.err().unwrap().to_string();
        assert!(e.contains("10.0.0.1:14660") && e.contains("not a multicast address"), "{e}");
    }
}
