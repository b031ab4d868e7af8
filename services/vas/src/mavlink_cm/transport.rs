//! Opens an [`Endpoint`] and runs MAVLink 2 framing on it.
//!
//! mavsim has its own, simpler copy of this (it only binds); the two crates
//! stay independent so the VAS never depends on the simulator. Reads happen
//! in a task per connection that feeds a channel: the manager's loop then only
//! awaits cancel-safe receives and never blocks a tokio worker (the `mavlink`
//! crate's own connections are blocking). Bad-CRC frames are skipped by the
//! decoder; frames that fail to parse are counted and skipped.

use std::io;
use std::net::SocketAddr;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::Arc;

use mavlink::dialects::ardupilotmega::MavMessage;
use mavlink::error::MessageReadError;
use mavlink::{AsyncMavlinkReader, MavHeader, MavlinkReader, MavlinkVersion};
use tokio::io::{AsyncRead, AsyncWrite, AsyncWriteExt};
use tokio::net::{lookup_host, TcpStream, UdpSocket};
use tokio::sync::mpsc;
use tokio::task::JoinSet;
use tokio_serial::SerialPortBuilderExt;

use super::endpoint::Endpoint;

/// A decoded frame.
pub(crate) struct Frame {
    pub header: MavHeader,
    pub msg: MavMessage,
}

enum Writer {
    Udp {
        sock: Arc<UdpSocket>,
        /// Fixed destination (udpout) or the last sender (udpin).
        peer: Arc<std::sync::Mutex<Option<SocketAddr>>>,
    },
    Stream(mpsc::Sender<Vec<u8>>),
}

/// An open connection; dropping it stops its tasks.
pub(crate) struct Connection {
    rx: mpsc::Receiver<io::Result<Frame>>,
    writer: Writer,
    tasks: JoinSet<()>,
}

const DEPTH: usize = 512;

async fn resolve(addr: &str) -> io::Result<SocketAddr> {
    lookup_host(addr)
        .await?
        .next()
        .ok_or_else(|| io::Error::new(io::ErrorKind::NotFound, format!("no address for {addr}")))
}

impl Connection {
    /// Opens `endpoint`.
    pub(crate) async fn open(
        endpoint: &Endpoint,
        parse_errors: Arc<AtomicU64>,
    ) -> io::Result<Self> {
        let (tx, rx) = mpsc::channel(DEPTH);
        let mut tasks = JoinSet::new();
        let writer = match endpoint {
            Endpoint::UdpOut(addr) => {
                let dest = resolve(addr).await?;
                let bind: SocketAddr = if dest.is_ipv4() {
                    ([0, 0, 0, 0], 0).into()
                } else {
                    (std::net::Ipv6Addr::UNSPECIFIED, 0).into()
                };
                let sock = Arc::new(UdpSocket::bind(bind).await?);
                let peer = Arc::new(std::sync::Mutex::new(Some(dest)));
                tasks.spawn(udp_reader(sock.clone(), None, tx, parse_errors));
                Writer::Udp { sock, peer }
            }
            Endpoint::UdpIn(addr) => {
                let sock = Arc::new(UdpSocket::bind(resolve(addr).await?).await?);
                let peer = Arc::new(std::sync::Mutex::new(None));
                tasks.spawn(udp_reader(
                    sock.clone(),
                    Some(peer.clone()),
                    tx,
                    parse_errors,
                ));
                Writer::Udp { sock, peer }
            }
            Endpoint::TcpOut(addr) => {
                let stream = TcpStream::connect(addr).await?;
                stream.set_nodelay(true)?;
                spawn_stream(&mut tasks, stream, tx, parse_errors)
            }
            Endpoint::Serial { path, baud } => {
                let mut port = tokio_serial::new(path, *baud)
                    .open_native_async()
                    .map_err(io::Error::other)?;
                // Not exclusive: a pty kept open by its creator must stay reopenable.
                port.set_exclusive(false).map_err(io::Error::other)?;
                spawn_stream(&mut tasks, port, tx, parse_errors)
            }
        };
        Ok(Self { rx, writer, tasks })
    }

    /// The next frame; `None` or `Some(Err)` when the connection is gone. Cancel-safe.
    pub(crate) async fn recv(&mut self) -> Option<io::Result<Frame>> {
        self.rx.recv().await
    }

    /// Sends one message; never waits (a congested link drops, like a radio).
    pub(crate) fn send(&mut self, header: MavHeader, msg: &MavMessage) -> io::Result<()> {
        let mut buf = Vec::with_capacity(64);
        mavlink::write_versioned_msg(&mut buf, MavlinkVersion::V2, header, msg)
            .map_err(io::Error::other)?;
        match &self.writer {
            Writer::Udp { sock, peer } => {
                let dest = *marea::sync::lock(peer);
                if let Some(dest) = dest {
                    match sock.try_send_to(&buf, dest) {
                        Ok(_) => {}
                        Err(e) if e.kind() == io::ErrorKind::WouldBlock || is_transient(&e) => {}
                        Err(e) => return Err(e),
                    }
                }
                Ok(())
            }
            Writer::Stream(tx) => match tx.try_send(buf) {
                Ok(()) | Err(mpsc::error::TrySendError::Full(_)) => Ok(()),
                Err(mpsc::error::TrySendError::Closed(_)) => Err(io::ErrorKind::BrokenPipe.into()),
            },
        }
    }
}

impl Connection {
    /// Writes [`RESYNC_BYTES`] zero bytes on a byte stream (nothing on UDP, where every
    /// datagram starts a fresh parse): a receiver waiting for the rest of a frame whose length
    /// byte was corrupted completes it, fails its CRC and looks for the next start marker.
    pub(crate) fn resync(&mut self) -> io::Result<()> {
        match &self.writer {
            Writer::Udp { .. } => Ok(()),
            Writer::Stream(tx) => match tx.try_send(vec![0; RESYNC_BYTES]) {
                Ok(()) | Err(mpsc::error::TrySendError::Full(_)) => Ok(()),
                Err(mpsc::error::TrySendError::Closed(_)) => Err(io::ErrorKind::BrokenPipe.into()),
            },
        }
    }
}

/// The longest MAVLink 2 frame: 10 header + 255 payload + 2 CRC + 13 signature bytes.
const RESYNC_BYTES: usize = 280;

impl Drop for Connection {
    fn drop(&mut self) {
        self.tasks.abort_all();
    }
}

fn is_transient(e: &io::Error) -> bool {
    matches!(
        e.kind(),
        io::ErrorKind::ConnectionRefused
            | io::ErrorKind::ConnectionReset
            | io::ErrorKind::Interrupted
    )
}

async fn udp_reader(
    sock: Arc<UdpSocket>,
    learn_peer: Option<Arc<std::sync::Mutex<Option<SocketAddr>>>>,
    tx: mpsc::Sender<io::Result<Frame>>,
    parse_errors: Arc<AtomicU64>,
) {
    let mut buf = vec![0u8; 65_536];
    loop {
        let (n, from) = match sock.recv_from(&mut buf).await {
            Ok(x) => x,
            // ICMP port unreachable while the autopilot is down: keep listening.
            Err(e) if is_transient(&e) => continue,
            Err(e) => {
                let _ = tx.send(Err(e)).await;
                return;
            }
        };
        if let Some(peer) = &learn_peer {
            *marea::sync::lock(peer) = Some(from);
        }
        let mut reader = MavlinkReader::new(&buf[..n]);
        loop {
            match reader.read_any_message::<MavMessage>() {
                Ok((header, msg)) => {
                    if tx.send(Ok(Frame { header, msg })).await.is_err() {
                        return;
                    }
                }
                Err(MessageReadError::Parse(_)) => {
                    parse_errors.fetch_add(1, Ordering::Relaxed);
                }
                Err(MessageReadError::Io(_)) => break,
            }
        }
    }
}

fn spawn_stream<S>(
    tasks: &mut JoinSet<()>,
    stream: S,
    tx: mpsc::Sender<io::Result<Frame>>,
    parse_errors: Arc<AtomicU64>,
) -> Writer
where
    S: AsyncRead + AsyncWrite + Send + 'static,
{
    let (rd, mut wr) = tokio::io::split(stream);
    let (out_tx, mut out_rx) = mpsc::channel::<Vec<u8>>(DEPTH);
    tasks.spawn(async move {
        let mut reader = AsyncMavlinkReader::new(rd);
        loop {
            match reader.read_any_message::<MavMessage>().await {
                Ok((header, msg)) => {
                    if tx.send(Ok(Frame { header, msg })).await.is_err() {
                        return;
                    }
                }
                Err(MessageReadError::Parse(_)) => {
                    parse_errors.fetch_add(1, Ordering::Relaxed);
                }
                Err(MessageReadError::Io(e)) => {
                    let _ = tx.send(Err(e)).await;
                    return;
                }
            }
        }
    });
    tasks.spawn(async move {
        while let Some(buf) = out_rx.recv().await {
            if wr.write_all(&buf).await.is_err() {
                return;
            }
        }
    });
    Writer::Stream(out_tx)
}
