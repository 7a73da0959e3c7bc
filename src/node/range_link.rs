//! A ranging device on the companion (a UWB module beside the vehicle link): its byte stream
//! read on its own task, each read stamped with the companion's Unix time. The lines are cut and
//! parsed by the sans-io [`super::ranging::RangeLines`] in the node shell.

use super::error::NodeError;
use std::sync::Arc;
use std::time::Duration;

/// Where a ranging device's stream comes from.
#[derive(Debug, Clone)]
pub enum RangeSource {
    /// Datagrams to this socket (bound by the caller, so that it can say where).
    Udp(Arc<std::net::UdpSocket>),
    /// A serial line.
    Serial { path: String, baud: u32 },
}

/// Reads a ranging device on its own task: each read with the companion's Unix time (us) it
/// arrived at.
pub fn spawn_range_reader(source: RangeSource) -> Result<tokio::sync::mpsc::Receiver<(Vec<u8>, u64)>, NodeError> {
    use tokio::io::AsyncReadExt as _;
    let (tx, rx) = tokio::sync::mpsc::channel::<(Vec<u8>, u64)>(1024);
    let now_us = || crate::recording::wall_now_ns() / 1000;
    match source {
        RangeSource::Udp(socket) => {
            let std_socket = socket.try_clone().map_err(NodeError::io("the ranging socket"))?;
            std_socket.set_nonblocking(true).map_err(NodeError::io("the ranging socket"))?;
            let socket = tokio::net::UdpSocket::from_std(std_socket).map_err(NodeError::io("the ranging socket"))?;
            tokio::spawn(async move {
                let mut buf = vec![0u8; 65_536];
                loop {
                    match socket.recv_from(&mut buf).await {
                        Ok((n, _)) => {
                            if tx.send((buf[..n].to_vec(), now_us())).await.is_err() {
                                return;
                            }
                        }
                        Err(e) => {
                            tracing::warn!(error = %e, "ranging socket read error");
                            tokio::time::sleep(Duration::from_millis(100)).await;
                        }
                    }
                }
            });
        }
        RangeSource::Serial { path, baud } => {
            use tokio_serial::SerialPortBuilderExt as _;
            let mut port = tokio_serial::new(&path, baud)
                .open_native_async()
                .map_err(|e| NodeError::Invalid(format!("opening the ranging device {path} at {baud} baud: {e}")))?;
            tokio::spawn(async move {
                let mut buf = vec![0u8; 4096];
                loop {
                    match port.read(&mut buf).await {
                        Ok(0) => tokio::time::sleep(Duration::from_millis(10)).await,
                        Ok(n) => {
                            if tx.send((buf[..n].to_vec(), now_us())).await.is_err() {
                                return;
                            }
                        }
                        Err(e) => {
                            tracing::warn!(error = %e, "ranging device read error");
                            tokio::time::sleep(Duration::from_millis(100)).await;
                        }
                    }
                }
            });
        }
    }
    Ok(rx)
}
