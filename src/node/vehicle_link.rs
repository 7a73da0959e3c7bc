//! The node's link to its vehicle. UDP links (`udpin:`, `udpout:`) are the node's own sockets,
//! with a large receive buffer: an autopilot streams IMU samples at up to a few hundred hertz,
//! and a node busy with a joint update or a rebuild must not lose them to a full kernel buffer
//! (the mavlink crate's UDP connection keeps the system default, about 200 KiB, which a loaded
//! machine overflowed in the field). Stream links (`tcpout:`, `tcpin:`, `serial:PATH:BAUD`) are
//! the node's own too, cut into frames by the one stream framer
//! ([`super::coop_link::StreamFramer`]) and [`split_frames`], so that frames of the
//! autopilot's own dialect are skipped by their length instead of costing the frames behind
//! them (the mavlink crate resynchronises byte by byte through a frame whose CRC it cannot
//! check). `udpbcast:` goes through the mavlink crate.
//!
//! Frames lost all the same are seen as gaps in the vehicle's MAVLink sequence numbers (the
//! runner counts them) and bridged by the core.
//!
//! **Signing** ([`VehicleLink::sign`], `cooploc node --vehicle-key`): for an autopilot with
//! MAVLink 2 signing on the node's port (ArduPilot refuses unsigned frames there once a key is
//! set). Every frame the node sends is signed; only frames signed with the key are taken, the
//! others are refused and counted. UDP links use [`crate::protocol::signing`] (with its
//! reordering window); stream links the mavlink crate's own signing (a stream does not reorder).

use super::error::NodeError;
use std::net::SocketAddr;
use std::sync::Mutex;

use mavlink_core::{AsyncMavConnection, MavHeader};
use tokio::io::{AsyncRead, AsyncReadExt as _, AsyncWrite, AsyncWriteExt as _};
use tokio::net::UdpSocket;

use super::coop_link::StreamFramer;

use crate::protocol::MavMessage;
use crate::protocol::signing::{Signer, SigningCounters, TeamKey, Verifier};
use crate::protocol::wire;

/// Receive buffer asked for a UDP vehicle link (the kernel caps it at net.core.rmem_max; the
/// node warns when it got less than it asked).
pub const VEHICLE_RECV_BUFFER: usize = 4 << 20;

pub use crate::protocol::framing::{Received, split_frames};

/// A connection to the vehicle.
pub enum VehicleLink {
    /// Our own UDP socket. `udpin`: bound to the address, replies go to whoever sent last.
    /// `udpout`: bound to an ephemeral port, sends to the address.
    Udp { socket: UdpSocket, peer: Mutex<Option<SocketAddr>>, learn_peer: bool, signing: Option<Box<Mutex<(Signer, Verifier)>>> },
    /// A byte stream (TCP, serial): the reading half with its framer, the writing half.
    Stream {
        reader: tokio::sync::Mutex<(Box<dyn AsyncRead + Send + Unpin>, StreamFramer)>,
        writer: tokio::sync::Mutex<Box<dyn AsyncWrite + Send + Unpin>>,
        signing: Option<Box<Mutex<(Signer, Verifier)>>>,
    },
    /// Anything else (`udpbcast:`), through the mavlink crate.
    Crate(Box<mavlink_core::AsyncConnection<MavMessage>>),
}

/// Resolves `host:port` of a URL.
async fn resolve(url: &str, rest: &str) -> Result<SocketAddr, NodeError> {
    tokio::net::lookup_host(rest)
        .await
        .map_err(NodeError::io(format!("vehicle URL {url:?}: {rest:?} is not HOST:PORT")))?
        .next()
        .ok_or_else(|| NodeError::Invalid(format!("vehicle URL {url:?}: {rest:?} resolves to no address")))
}

/// A UDP socket with the large receive buffer, bound to `addr`.
pub fn bind_udp(addr: SocketAddr, buffer: usize) -> std::io::Result<UdpSocket> {
    use socket2::{Domain, Protocol, Socket, Type};
    let socket = Socket::new(Domain::for_address(addr), Type::DGRAM, Some(Protocol::UDP))?;
    if let Err(e) = socket.set_recv_buffer_size(buffer) {
        tracing::warn!(error = %e, "could not enlarge a socket's receive buffer");
    }
    socket.set_nonblocking(true)?;
    socket.bind(&addr.into())?;
    UdpSocket::from_std(socket.into())
}

/// The receive buffer the kernel granted a socket, bytes (Linux reports twice what it keeps for
/// data: the figure includes its bookkeeping).
pub fn recv_buffer_size(socket: &UdpSocket) -> std::io::Result<usize> {
    socket2::SockRef::from(socket).recv_buffer_size()
}

impl VehicleLink {
    /// Opens the link named by a MAVLink connection URL.
    pub async fn open(url: &str) -> Result<Self, NodeError> {
        if let Some(rest) = url.strip_prefix("udpin:") {
            let addr = resolve(url, rest).await?;
            let socket =
                bind_udp(addr, VEHICLE_RECV_BUFFER).map_err(NodeError::io(format!("binding the vehicle socket {addr}")))?;
            return Ok(Self::Udp { socket, peer: Mutex::new(None), learn_peer: true, signing: None });
        }
        if let Some(rest) = url.strip_prefix("udpout:") {
            let addr = resolve(url, rest).await?;
            // A vehicle on this machine is reached over loopback: bind there, not on every
            // interface.
            let local: SocketAddr = match (addr.is_ipv4(), addr.ip().is_loopback()) {
                (true, true) => "127.0.0.1:0",
                (true, false) => "0.0.0.0:0",
                (false, true) => "[::1]:0",
                (false, false) => "[::]:0",
            }
            .parse()
            .expect("literal");
            let socket = bind_udp(local, VEHICLE_RECV_BUFFER).map_err(NodeError::io("binding the vehicle socket"))?;
            return Ok(Self::Udp { socket, peer: Mutex::new(Some(addr)), learn_peer: false, signing: None });
        }
        if let Some(rest) = url.strip_prefix("tcpout:") {
            let addr = resolve(url, rest).await?;
            let stream =
                tokio::net::TcpStream::connect(addr).await.map_err(NodeError::io(format!("vehicle URL {url:?}: connecting")))?;
            let _ = stream.set_nodelay(true);
            let (r, w) = stream.into_split();
            return Ok(Self::stream(Box::new(r), Box::new(w)));
        }
        if let Some(rest) = url.strip_prefix("tcpin:") {
            let addr = resolve(url, rest).await?;
            let listener =
                tokio::net::TcpListener::bind(addr).await.map_err(NodeError::io(format!("vehicle URL {url:?}: listening")))?;
            let (stream, from) = listener.accept().await.map_err(NodeError::io(format!("vehicle URL {url:?}: accepting")))?;
            tracing::info!(%from, "vehicle connected");
            let _ = stream.set_nodelay(true);
            let (r, w) = stream.into_split();
            return Ok(Self::stream(Box::new(r), Box::new(w)));
        }
        if let Some(rest) = url.strip_prefix("serial:") {
            use tokio_serial::SerialPortBuilderExt as _;
            let (path, baud) = rest
                .rsplit_once(':')
                .and_then(|(p, b)| Some((p, b.parse::<u32>().ok()?)))
                .ok_or_else(|| NodeError::Invalid(format!("vehicle URL {url:?}: expected serial:PATH:BAUD")))?;
            let port = tokio_serial::new(path, baud)
                .open_native_async()
                .map_err(|e| NodeError::Invalid(format!("vehicle URL {url:?}: opening {path} at {baud} baud: {e}")))?;
            let (r, w) = tokio::io::split(port);
            return Ok(Self::stream(Box::new(r), Box::new(w)));
        }
        let conn = mavlink_core::connect_async::<MavMessage>(url).await.map_err(NodeError::io(format!("vehicle URL {url:?}")))?;
        Ok(Self::Crate(Box::new(conn)))
    }

    fn stream(reader: Box<dyn AsyncRead + Send + Unpin>, writer: Box<dyn AsyncWrite + Send + Unpin>) -> Self {
        Self::Stream {
            reader: tokio::sync::Mutex::new((reader, StreamFramer::default())),
            writer: tokio::sync::Mutex::new(writer),
            signing: None,
        }
    }

    /// Signs the link with `key` on link id `link_id`: every frame sent is signed, only signed
    /// frames are taken.
    pub fn sign(&mut self, key: &TeamKey, link_id: u8) {
        match self {
            Self::Udp { signing, .. } | Self::Stream { signing, .. } => {
                *signing = Some(Box::new(Mutex::new((Signer::new(key.clone(), link_id, 0), Verifier::new(key.clone())))));
            }
            Self::Crate(conn) => {
                use mavlink_core::AsyncMavConnection as _;
                conn.setup_signing(Some(mavlink_core::SigningConfig::new(key.bytes(), link_id, true, false)));
            }
        }
    }

    /// What signing accepted and refused on a UDP link (None: unsigned, or a stream link, whose
    /// refusals the mavlink crate does not count).
    pub fn signing_counters(&self) -> Option<SigningCounters> {
        match self {
            Self::Udp { signing: Some(s), .. } | Self::Stream { signing: Some(s), .. } => {
                Some(s.lock().unwrap_or_else(|e| e.into_inner()).1.counters.clone())
            }
            _ => None,
        }
    }

    /// The receive buffer granted to a UDP link (None for the others).
    pub fn recv_buffer(&self) -> Option<usize> {
        match self {
            Self::Udp { socket, .. } => recv_buffer_size(socket).ok(),
            Self::Stream { .. } | Self::Crate(_) => None,
        }
    }

    /// Sends one message (a link with no peer yet, an `udpin` that has heard nobody, drops it).
    pub async fn send(&self, header: &MavHeader, msg: &MavMessage) {
        match self {
            Self::Udp { socket, peer, signing, .. } => {
                let to = *peer.lock().unwrap_or_else(|e| e.into_inner());
                if let Some(to) = to {
                    let frame = match signing {
                        Some(s) => s.lock().unwrap_or_else(|e| e.into_inner()).0.frame(*header, msg, unix_now_us()),
                        None => wire::to_frame(*header, msg),
                    };
                    let _ = socket.send_to(&frame, to).await;
                }
            }
            Self::Stream { writer, signing, .. } => {
                let frame = match signing {
                    Some(s) => s.lock().unwrap_or_else(|e| e.into_inner()).0.frame(*header, msg, unix_now_us()),
                    None => wire::to_frame(*header, msg),
                };
                if let Err(e) = writer.lock().await.write_all(&frame).await {
                    tracing::debug!(error = %e, "vehicle link write error");
                }
            }
            Self::Crate(conn) => {
                let _ = conn.send(header, msg).await;
            }
        }
    }

    /// Receives the next datagram's (or stream's) frames. Bytes that are no MAVLink frame of
    /// the dialect are skipped: `Ok` with what could be read, possibly nothing.
    pub async fn recv(&self, buf: &mut [u8]) -> std::io::Result<Vec<Received>> {
        match self {
            Self::Udp { socket, peer, learn_peer, signing } => {
                let (n, from) = socket.recv_from(buf).await?;
                let frames = frames_of(&buf[..n], signing.as_deref());
                // An unsigned link answers whoever sent last; a signed one only a signed sender.
                if *learn_peer && (signing.is_none() || !frames.is_empty()) {
                    *peer.lock().unwrap_or_else(|e| e.into_inner()) = Some(from);
                }
                Ok(frames)
            }
            Self::Stream { reader, signing, .. } => {
                let mut guard = reader.lock().await;
                let (stream, framer) = &mut *guard;
                let n = stream.read(buf).await?;
                if n == 0 {
                    return Err(std::io::Error::new(std::io::ErrorKind::UnexpectedEof, "the vehicle closed the link"));
                }
                let run = framer.push(&buf[..n]);
                Ok(frames_of(&run, signing.as_deref()))
            }
            Self::Crate(conn) => match conn.recv_raw().await {
                Ok(raw) => {
                    let bytes = match &raw {
                        mavlink_core::MAVLinkMessageRaw::V1(r) => r.raw_bytes().to_vec(),
                        mavlink_core::MAVLinkMessageRaw::V2(r) => r.raw_bytes().to_vec(),
                    };
                    Ok(wire::from_any_frame(&bytes).map(|(h, m)| vec![(h, Some(m), bytes)]).unwrap_or_default())
                }
                Err(mavlink_core::error::MessageReadError::Io(e)) if e.kind() != std::io::ErrorKind::WouldBlock => Err(e),
                Err(_) => Ok(Vec::new()),
            },
        }
    }
}

/// The frames of a datagram or of a stream's run of whole frames: all of them on an unsigned
/// link ([`split_frames`]), the ones signed with the key on a signed one.
fn frames_of(bytes: &[u8], signing: Option<&Mutex<(Signer, Verifier)>>) -> Vec<Received> {
    match signing {
        Some(s) => {
            let got = s.lock().unwrap_or_else(|e| e.into_inner()).1.datagram(bytes, unix_now_us());
            got.frames.into_iter().zip(got.spans).map(|((h, m), span)| (h, Some(m), bytes[span].to_vec())).collect()
        }
        None => split_frames(bytes),
    }
}

/// Unix time, us (signing timestamps).
fn unix_now_us() -> u64 {
    std::time::SystemTime::now().duration_since(std::time::UNIX_EPOCH).map_or(0, |d| d.as_micros() as u64)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::protocol::dialect::cooploc::{MavAutopilot, MavType};
    use crate::protocol::framing::heartbeat_frame as hb;

    #[test]
    fn a_datagram_with_several_frames_gives_them_all_and_stops_at_garbage() {
        let mut d = [hb(1), hb(2), hb(3)].concat();
        let got = split_frames(&d);
        assert_eq!(got.iter().map(|f| f.0.sequence).collect::<Vec<_>>(), vec![1, 2, 3]);
        assert_eq!(got[1].2, hb(2));
        // A corrupted second frame: the first is kept, nothing after the damage is guessed at.
        let second = hb(2).len() + 5;
        d[second] ^= 0xFF;
        assert_eq!(split_frames(&d).len(), 1);
        // Truncated, empty, not MAVLink.
        assert!(split_frames(&hb(1)[..10]).is_empty());
        assert!(split_frames(&[]).is_empty());
        assert!(split_frames(b"hello world").is_empty());
    }

    /// A datagram mixing frames of the autopilot's own dialect with the node's inputs: every
    /// frame comes out, in order, the foreign ones without a message (their sequence numbers
    /// still count); the same bytes cut anywhere in a stream give the same frames.
    #[test]
    fn frames_of_another_dialect_never_stop_a_datagram_or_a_stream() {
        use crate::protocol::framing::foreign_frame;
        let d = [hb(1), foreign_frame(2, 50_123), foreign_frame(3, 12_345), hb(4), foreign_frame(5, 50_123)].concat();
        let got = split_frames(&d);
        let summary: Vec<(u8, bool)> = got.iter().map(|f| (f.0.sequence, f.1.is_some())).collect();
        assert_eq!(summary, [(1, true), (2, false), (3, false), (4, true), (5, false)]);
        assert_eq!(got.iter().map(|f| f.2.len()).sum::<usize>(), d.len());
        for cut in 1..d.len() {
            let mut framer = StreamFramer::default();
            let run = [framer.push(&d[..cut]), framer.push(&d[cut..])].concat();
            assert_eq!(run, d, "cut at {cut}");
            assert_eq!(framer.skipped, 0);
        }
    }

    /// A node on a TCP link (ArduPilot SITL's): frames cut anywhere by the stream, foreign ones
    /// among them, all arrive; what it sends reaches the other end whole.
    #[tokio::test]
    async fn a_tcp_link_cuts_the_stream_into_frames() {
        use crate::protocol::framing::foreign_frame;
        let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
        let addr = listener.local_addr().unwrap();
        let link = VehicleLink::open(&format!("tcpout:{addr}")).await.unwrap();
        let (mut vehicle, _) = listener.accept().await.unwrap();
        let d = [hb(1), foreign_frame(2, 50_123), hb(3)].concat();
        for chunk in d.chunks(7) {
            vehicle.write_all(chunk).await.unwrap();
            vehicle.flush().await.unwrap();
        }
        let mut got = Vec::new();
        let mut buf = [0u8; 2048];
        while got.len() < 3 {
            got.extend(tokio::time::timeout(std::time::Duration::from_secs(5), link.recv(&mut buf)).await.unwrap().unwrap());
        }
        assert_eq!(got.iter().map(|f| (f.0.sequence, f.1.is_some())).collect::<Vec<_>>(), [(1, true), (2, false), (3, true)]);
        let msg = wire::heartbeat(MavType::MAV_TYPE_ONBOARD_CONTROLLER, MavAutopilot::MAV_AUTOPILOT_INVALID);
        link.send(&MavHeader { system_id: 7, component_id: 191, sequence: 9 }, &msg).await;
        let mut back = vec![0u8; 64];
        let n = tokio::time::timeout(std::time::Duration::from_secs(5), vehicle.read(&mut back)).await.unwrap().unwrap();
        assert_eq!(wire::from_frame(&back[..n]).unwrap().0.sequence, 9);
        // the vehicle hangs up: the link says so
        drop(vehicle);
        let end = tokio::time::timeout(std::time::Duration::from_secs(5), link.recv(&mut buf)).await.unwrap();
        assert!(end.is_err());
    }

    #[tokio::test]
    async fn udp_links_get_a_large_receive_buffer_and_udpin_answers_the_last_sender() {
        let vehicle = UdpSocket::bind("127.0.0.1:0").await.unwrap();
        let link = VehicleLink::open(&format!("udpout:{}", vehicle.local_addr().unwrap())).await.unwrap();
        // The default is about 200 KiB; the kernel may cap what we ask at net.core.rmem_max.
        let default = recv_buffer_size(&UdpSocket::bind("127.0.0.1:0").await.unwrap()).unwrap();
        let rmem_max: usize =
            std::fs::read_to_string("/proc/sys/net/core/rmem_max").ok().and_then(|s| s.trim().parse().ok()).unwrap_or(0);
        let granted = link.recv_buffer().unwrap();
        assert!(granted >= default, "granted {granted}, default {default}");
        if rmem_max >= VEHICLE_RECV_BUFFER {
            assert!(granted >= VEHICLE_RECV_BUFFER, "granted {granted} with rmem_max {rmem_max}");
        }
        // udpout sends to the vehicle; the vehicle's reply comes back.
        let msg = wire::heartbeat(MavType::MAV_TYPE_ONBOARD_CONTROLLER, MavAutopilot::MAV_AUTOPILOT_INVALID);
        if let VehicleLink::Udp { socket, .. } = &link {
            assert!(socket.local_addr().unwrap().ip().is_loopback(), "a loopback vehicle is reached from loopback only");
        }
        link.send(&MavHeader { system_id: 7, component_id: 191, sequence: 4 }, &msg).await;
        let mut buf = [0u8; 600];
        let (n, node) = vehicle.recv_from(&mut buf).await.unwrap();
        assert_eq!(wire::from_frame(&buf[..n]).unwrap().0.system_id, 7);
        vehicle.send_to(&[hb(9), hb(10)].concat(), node).await.unwrap();
        let got = link.recv(&mut [0u8; 2048]).await.unwrap();
        assert_eq!(got.iter().map(|f| f.0.sequence).collect::<Vec<_>>(), vec![9, 10]);

        // udpin: silent until it has heard someone, then answers them.
        let probe = UdpSocket::bind("127.0.0.1:0").await.unwrap();
        let link = VehicleLink::open(&format!("udpin:{}", probe.local_addr().unwrap().ip())).await;
        assert!(link.is_err(), "udpin without a port is refused");
        let port_free = UdpSocket::bind("127.0.0.1:0").await.unwrap();
        let addr = port_free.local_addr().unwrap();
        drop(port_free);
        let link = VehicleLink::open(&format!("udpin:{addr}")).await.unwrap();
        link.send(&MavHeader::default(), &msg).await; // nobody to send to: dropped
        probe.send_to(&hb(1), addr).await.unwrap();
        assert_eq!(link.recv(&mut [0u8; 2048]).await.unwrap().len(), 1);
        link.send(&MavHeader { system_id: 3, component_id: 191, sequence: 1 }, &msg).await;
        let (n, _) = probe.recv_from(&mut buf).await.unwrap();
        assert_eq!(wire::from_frame(&buf[..n]).unwrap().0.system_id, 3);
    }

    #[tokio::test]
    async fn a_signed_vehicle_link_sends_signed_and_takes_only_signed_frames() {
        let key = TeamKey::from_passphrase("the vehicle's key");
        let vehicle = UdpSocket::bind("127.0.0.1:0").await.unwrap();
        let mut link = VehicleLink::open(&format!("udpout:{}", vehicle.local_addr().unwrap())).await.unwrap();
        link.sign(&key, 7);
        let msg = wire::heartbeat(MavType::MAV_TYPE_ONBOARD_CONTROLLER, MavAutopilot::MAV_AUTOPILOT_INVALID);
        link.send(&MavHeader { system_id: 7, component_id: 191, sequence: 1 }, &msg).await;
        let mut buf = [0u8; 600];
        let (n, node) = vehicle.recv_from(&mut buf).await.unwrap();
        // What the autopilot checks: signed with the key.
        let mut autopilot = Verifier::new(key.clone());
        assert_eq!(autopilot.datagram(&buf[..n], unix_now_us()).frames.len(), 1);
        assert_eq!(Verifier::new(TeamKey::from_passphrase("other")).datagram(&buf[..n], unix_now_us()).frames.len(), 0);
        // The autopilot's signed frames are taken; unsigned and wrongly signed ones refused.
        let mut signer = Signer::new(key, 1, 0);
        let hdr = MavHeader { system_id: 1, component_id: 1, sequence: 5 };
        let signed = signer.frame(hdr, &msg, unix_now_us());
        let wrong = Signer::new(TeamKey::from_passphrase("other"), 1, 0).frame(hdr, &msg, unix_now_us());
        vehicle.send_to(&[hb(1), wrong, signed.clone()].concat(), node).await.unwrap();
        let got = link.recv(&mut [0u8; 2048]).await.unwrap();
        assert_eq!(got.len(), 1);
        assert_eq!(got[0].2, signed, "the frame as received, signature included");
        vehicle.send_to(&signed, node).await.unwrap(); // replayed
        assert!(link.recv(&mut [0u8; 2048]).await.unwrap().is_empty());
        let c = link.signing_counters().unwrap();
        assert_eq!((c.accepted, c.unsigned, c.bad_signature, c.replayed), (1, 1, 1, 1), "{c:?}");
    }
}
