//! Byte transports for the simulator (UDP, serial device, self-created pty) and
//! MAVLink 2 framing on them.
//!
//! Each transport gets a reader task that decodes frames into a channel, so the
//! simulator's loop only ever awaits cancel-safe channel receives. Frames with a
//! bad CRC are skipped by the decoder; frames that do not parse (unknown id,
//! bad enum) are counted and skipped. Sending never blocks the simulator: a
//! congested serial line drops frames, as a real radio would.

use std::io;
use std::net::SocketAddr;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::Arc;

use mavlink::dialects::ardupilotmega::MavMessage;
use mavlink::error::MessageReadError;
use mavlink::{AsyncMavlinkReader, MavHeader, MavlinkReader, MavlinkVersion};
use tokio::io::{AsyncRead, AsyncWrite, AsyncWriteExt};
use tokio::net::UdpSocket;
use tokio::sync::mpsc;
use tokio::task::JoinSet;
use tokio_serial::{SerialPort, SerialPortBuilderExt, SerialStream};
use tokio_util::sync::CancellationToken;

/// Where the simulator speaks MAVLink.
#[derive(Clone, Debug)]
pub enum LinkConfig {
    /// Bind a UDP socket; reply to whoever sent last, and also to `out` if given.
    Udp {
        /// Local address to bind (port 0 picks a free port).
        bind: SocketAddr,
        /// Extra destination that gets everything (like SITL `--out`).
        out: Option<SocketAddr>,
    },
    /// An existing serial device or pty slave.
    Serial {
        /// Device path.
        path: String,
        /// Baud rate (ignored by ptys).
        baud: u32,
    },
    /// Create a pty pair and speak on the master side; clients open the slave.
    Pty,
}

/// What was opened, for the user.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum LinkInfo {
    /// The bound UDP address.
    Udp(SocketAddr),
    /// The serial device path.
    Serial(String),
    /// The pty slave path clients should open.
    Pty(String),
}

/// Errors opening a link.
#[derive(Debug, thiserror::Error)]
pub enum LinkOpenError {
    /// The UDP socket could not be bound.
    #[error("cannot bind UDP {addr}: {source}")]
    UdpBind {
        /// Requested address.
        addr: SocketAddr,
        /// Cause.
        source: io::Error,
    },
    /// The serial device could not be opened.
    #[error("cannot open serial device {path}: {source}")]
    Serial {
        /// Device path.
        path: String,
        /// Cause.
        source: tokio_serial::Error,
    },
    /// No pty pair could be created.
    #[error("cannot create a pty pair: {0}")]
    Pty(tokio_serial::Error),
}

/// One decoded message and, on UDP, who sent it.
#[derive(Debug)]
pub struct Inbound {
    /// MAVLink header of the frame.
    pub header: MavHeader,
    /// The message.
    pub msg: MavMessage,
    /// Sender address (UDP only).
    pub peer: Option<SocketAddr>,
}

enum Writer {
    Udp {
        sock: Arc<UdpSocket>,
        peer: Option<SocketAddr>,
        out: Option<SocketAddr>,
    },
    Stream(mpsc::Sender<Vec<u8>>),
}

/// An open link: decoded messages in, frames out.
pub struct Link {
    info: LinkInfo,
    rx: mpsc::Receiver<io::Result<Inbound>>,
    writer: Writer,
    header: MavHeader,
    parse_errors: Arc<AtomicU64>,
    dropped: u64,
    // Keeps the pty slave open so the master never sees EIO/HUP while no
    // client has the device open, and so clients can come and go.
    _pty_slave: Option<SerialStream>,
    tasks: JoinSet<()>,
}

const CHANNEL_DEPTH: usize = 256;

impl Link {
    /// Opens the transport and starts its reader (and writer) task.
    ///
    /// # Errors
    /// When the socket, device or pty cannot be opened.
    pub async fn open(
        cfg: &LinkConfig,
        sysid: u8,
        cancel: CancellationToken,
    ) -> Result<Self, LinkOpenError> {
        let (tx, rx) = mpsc::channel(CHANNEL_DEPTH);
        let parse_errors = Arc::new(AtomicU64::new(0));
        let mut tasks = JoinSet::new();
        let mut pty_slave = None;
        let (info, writer) = match cfg {
            LinkConfig::Udp { bind, out } => {
                let sock =
                    UdpSocket::bind(bind)
                        .await
                        .map_err(|source| LinkOpenError::UdpBind {
                            addr: *bind,
                            source,
                        })?;
                let local = sock.local_addr().map_err(|source| LinkOpenError::UdpBind {
                    addr: *bind,
                    source,
                })?;
                let sock = Arc::new(sock);
                tasks.spawn(udp_reader(sock.clone(), tx, parse_errors.clone(), cancel));
                (
                    LinkInfo::Udp(local),
                    Writer::Udp {
                        sock,
                        peer: None,
                        out: *out,
                    },
                )
            }
            LinkConfig::Serial { path, baud } => {
                let port =
                    tokio_serial::new(path, *baud)
                        .open_native_async()
                        .map_err(|source| LinkOpenError::Serial {
                            path: path.clone(),
                            source,
                        })?;
                let writer = spawn_stream(&mut tasks, port, tx, parse_errors.clone(), cancel);
                (LinkInfo::Serial(path.clone()), writer)
            }
            LinkConfig::Pty => {
                let (master, slave) = SerialStream::pair().map_err(LinkOpenError::Pty)?;
                let name = slave.name().unwrap_or_default();
                pty_slave = Some(slave);
                let writer = spawn_stream(&mut tasks, master, tx, parse_errors.clone(), cancel);
                (LinkInfo::Pty(name), writer)
            }
        };
        Ok(Self {
            info,
            rx,
            writer,
            header: MavHeader {
                system_id: u32::from(sysid),
                component_id: 1,
                sequence: 0,
            },
            parse_errors,
            dropped: 0,
            _pty_slave: pty_slave,
            tasks,
        })
    }

    /// What was opened.
    pub fn info(&self) -> &LinkInfo {
        &self.info
    }

    /// Frames that passed the CRC but could not be parsed.
    pub fn parse_errors(&self) -> u64 {
        self.parse_errors.load(Ordering::Relaxed)
    }

    /// Frames dropped because the output was congested.
    pub fn dropped(&self) -> u64 {
        self.dropped
    }

    /// The next decoded message; `None` when the reader stopped. Cancel-safe.
    pub async fn recv(&mut self) -> Option<io::Result<Inbound>> {
        let inbound = self.rx.recv().await;
        if let (Some(Ok(Inbound { peer: Some(p), .. })), Writer::Udp { peer, .. }) =
            (&inbound, &mut self.writer)
        {
            *peer = Some(*p);
        }
        inbound
    }

    /// Sends `msg` without waiting; drops it when the output is congested.
    pub fn send(&mut self, msg: &MavMessage) {
        let mut buf = Vec::with_capacity(64);
        if mavlink::write_versioned_msg(&mut buf, MavlinkVersion::V2, self.header, msg).is_err() {
            return;
        }
        self.header.sequence = self.header.sequence.wrapping_add(1);
        match &self.writer {
            Writer::Udp { sock, peer, out } => {
                for dest in peer.iter().chain(out.iter().filter(|o| Some(**o) != *peer)) {
                    if sock.try_send_to(&buf, *dest).is_err() {
                        self.dropped += 1;
                    }
                }
            }
            Writer::Stream(tx) => {
                if tx.try_send(buf).is_err() {
                    self.dropped += 1;
                }
            }
        }
    }

    /// Stops the reader and writer tasks.
    pub async fn close(mut self) {
        self.tasks.abort_all();
        while self.tasks.join_next().await.is_some() {}
    }
}

fn is_transient(e: &io::Error) -> bool {
    // An ICMP "port unreachable" from an earlier send surfaces on the next recv.
    matches!(
        e.kind(),
        io::ErrorKind::ConnectionRefused
            | io::ErrorKind::ConnectionReset
            | io::ErrorKind::Interrupted
    )
}

async fn udp_reader(
    sock: Arc<UdpSocket>,
    tx: mpsc::Sender<io::Result<Inbound>>,
    parse_errors: Arc<AtomicU64>,
    cancel: CancellationToken,
) {
    let mut buf = vec![0u8; 65_536];
    loop {
        let (n, peer) = tokio::select! {
            _ = cancel.cancelled() => return,
            r = sock.recv_from(&mut buf) => match r {
                Ok(x) => x,
                Err(e) if is_transient(&e) => continue,
                Err(e) => {
                    let _ = tx.send(Err(e)).await;
                    return;
                }
            },
        };
        let mut reader = MavlinkReader::new(&buf[..n]);
        loop {
            match reader.read_any_message::<MavMessage>() {
                Ok((header, msg)) => {
                    if tx
                        .send(Ok(Inbound {
                            header,
                            msg,
                            peer: Some(peer),
                        }))
                        .await
                        .is_err()
                    {
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
    tx: mpsc::Sender<io::Result<Inbound>>,
    parse_errors: Arc<AtomicU64>,
    cancel: CancellationToken,
) -> Writer
where
    S: AsyncRead + AsyncWrite + Send + 'static,
{
    let (rd, wr) = tokio::io::split(stream);
    let (out_tx, out_rx) = mpsc::channel(CHANNEL_DEPTH);
    tasks.spawn(stream_reader(rd, tx, parse_errors, cancel.clone()));
    tasks.spawn(stream_writer(wr, out_rx, cancel));
    Writer::Stream(out_tx)
}

async fn stream_reader<R: AsyncRead + Unpin>(
    rd: R,
    tx: mpsc::Sender<io::Result<Inbound>>,
    parse_errors: Arc<AtomicU64>,
    cancel: CancellationToken,
) {
    let mut reader = AsyncMavlinkReader::new(rd);
    loop {
        // The reader keeps partial frames buffered when this select drops the read.
        let r = tokio::select! {
            _ = cancel.cancelled() => return,
            r = reader.read_any_message::<MavMessage>() => r,
        };
        match r {
            Ok((header, msg)) => {
                if tx
                    .send(Ok(Inbound {
                        header,
                        msg,
                        peer: None,
                    }))
                    .await
                    .is_err()
                {
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
}

async fn stream_writer<W: AsyncWrite + Unpin>(
    mut wr: W,
    mut rx: mpsc::Receiver<Vec<u8>>,
    cancel: CancellationToken,
) {
    loop {
        let buf = tokio::select! {
            _ = cancel.cancelled() => return,
            b = rx.recv() => match b {
                Some(b) => b,
                None => return,
            },
        };
        if let Err(e) = wr.write_all(&buf).await {
            tracing::warn!("serial write failed: {e}");
            return;
        }
    }
}
