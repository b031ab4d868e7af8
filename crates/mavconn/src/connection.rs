//! [`Connection`]: one open MAVLink 2 link (UDP, TCP, serial device or a pty it creates), decoded
//! frames in through a channel, encoded frames out without waiting.
//!
//! Reads happen in a task per connection that feeds a channel, so the owner's loop only awaits
//! cancel-safe receives and never blocks a tokio worker (the `mavlink` crate's own connections
//! are blocking). The framing is the `mavlink` crate's: [`AsyncMavlinkReader`] on byte streams,
//! [`MavlinkReader`] over each UDP datagram, [`mavlink::write_versioned_msg`] out. Frames with a
//! bad CRC are skipped by that reader (it does not report them); frames that pass the CRC but do
//! not parse (a bad enum value...) are counted in [`Counters::parse_errors`] and skipped. I/O
//! errors are never swallowed: they end the stream with `Some(Err(..))`.

use std::io;
use std::net::{Ipv6Addr, SocketAddr};
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex, PoisonError};

use mavlink::dialects::ardupilotmega::MavMessage;
use mavlink::error::{MessageReadError, MessageWriteError};
use mavlink::{
    AsyncMavlinkReader, MAVLinkMessageRaw, MavHeader, MavlinkReader, MavlinkVersion, Message,
};
use tokio::io::{AsyncRead, AsyncWrite, AsyncWriteExt};
use tokio::net::{lookup_host, TcpStream, UdpSocket};
use tokio::sync::mpsc;
use tokio::task::JoinSet;
use tokio_serial::{SerialPort, SerialPortBuilderExt, SerialStream};
use tokio_util::sync::CancellationToken;

use crate::endpoint::Endpoint;
use crate::security::{is_autopilot_heartbeat, Pin, Pinned, Signing};

/// The longest MAVLink 2 frame: 10 header + 255 payload + 2 CRC + 13 signature bytes.
pub const RESYNC_BYTES: usize = 280;

/// One decoded message and, on UDP, who sent it.
#[derive(Debug)]
pub struct Frame {
    /// MAVLink header of the frame.
    pub header: MavHeader,
    /// The message.
    pub msg: MavMessage,
    /// Sender address (UDP only).
    pub peer: Option<SocketAddr>,
}

/// What a connection counts; shareable so a caller that reopens keeps one running total.
#[derive(Debug, Default)]
pub struct Counters {
    parse_errors: AtomicU64,
    dropped: AtomicU64,
    rejected_signatures: AtomicU64,
    foreign: AtomicU64,
}

impl Counters {
    /// Frames that passed the CRC but could not be parsed.
    pub fn parse_errors(&self) -> u64 {
        self.parse_errors.load(Ordering::Relaxed)
    }

    /// Frames not sent because the output was congested (full queue, full socket buffer, or
    /// an ICMP error left by an earlier datagram).
    pub fn dropped(&self) -> u64 {
        self.dropped.load(Ordering::Relaxed)
    }

    /// Frames refused by signing: unsigned, MAVLink 1, a wrong signature or a replayed
    /// timestamp (only with [`OpenOptions::signing`]).
    pub fn rejected_signatures(&self) -> u64 {
        self.rejected_signatures.load(Ordering::Relaxed)
    }

    /// Frames dropped by pinning: from another system, component or address than the pinned
    /// one, or anything but the pinning heartbeat before it (only with [`OpenOptions::pin`]).
    pub fn foreign(&self) -> u64 {
        self.foreign.load(Ordering::Relaxed)
    }
}

/// How to open a connection beyond its [`Endpoint`].
#[derive(Clone, Debug)]
pub struct OpenOptions {
    /// UDP only: also send everything to this address (like SITL `--out`), besides the peer.
    pub also_send_to: Option<SocketAddr>,
    /// Depth of the decoded-frame channel and, on byte streams, of the output queue: a serial
    /// line slower than the sender drops frames beyond it, as a radio would.
    pub queue_depth: usize,
    /// Where to count parse errors and drops.
    pub counters: Arc<Counters>,
    /// MAVLink 2 signing: sign every frame, accept only correctly signed ones.
    pub signing: Option<Signing>,
    /// Pin the other end (system, component, UDP address) at its first heartbeat.
    pub pin: Option<Pin>,
}

impl Default for OpenOptions {
    fn default() -> Self {
        Self {
            also_send_to: None,
            queue_depth: 512,
            counters: Arc::default(),
            signing: None,
            pin: None,
        }
    }
}

/// Errors opening a connection.
#[derive(Debug, thiserror::Error)]
pub enum ConnectionOpenError {
    /// The host name did not resolve to an address.
    #[error("cannot resolve {addr}: {source}")]
    Resolve {
        /// Requested `HOST:PORT`.
        addr: String,
        /// Cause.
        source: io::Error,
    },
    /// The UDP socket could not be bound.
    #[error("cannot bind UDP {addr}: {source}")]
    UdpBind {
        /// Requested address.
        addr: SocketAddr,
        /// Cause.
        source: io::Error,
    },
    /// The TCP server could not be reached.
    #[error("cannot connect to TCP {addr}: {source}")]
    TcpConnect {
        /// Requested `HOST:PORT`.
        addr: String,
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

/// Errors sending one message.
#[derive(Debug, thiserror::Error)]
pub enum SendError {
    /// The message could not be encoded; nothing was sent.
    #[error("cannot encode the message: {0}")]
    Encode(#[source] MessageWriteError),
    /// The connection's writer has stopped (its byte stream failed).
    #[error("the connection's writer has stopped")]
    Closed,
    /// The socket refused the datagram for a reason other than congestion.
    #[error("UDP send failed: {0}")]
    Io(#[source] io::Error),
}

impl From<SendError> for io::Error {
    fn from(e: SendError) -> Self {
        match e {
            SendError::Io(e) => e,
            SendError::Closed => io::ErrorKind::BrokenPipe.into(),
            SendError::Encode(e) => io::Error::other(e),
        }
    }
}

type PeerSlot = Arc<Mutex<Option<SocketAddr>>>;

fn get_peer(slot: &PeerSlot) -> Option<SocketAddr> {
    // A poisoned slot still holds a valid address: a panic cannot tear a Copy value.
    *slot.lock().unwrap_or_else(PoisonError::into_inner)
}

fn set_peer(slot: &PeerSlot, addr: SocketAddr) {
    *slot.lock().unwrap_or_else(PoisonError::into_inner) = Some(addr);
}

enum Writer {
    Udp {
        sock: Arc<UdpSocket>,
        /// Fixed destination (udpout) or the last sender (udpin).
        peer: PeerSlot,
        also: Option<SocketAddr>,
    },
    Stream(mpsc::Sender<Vec<u8>>),
}

/// Signing and pinning of one connection, shared by its reader and its sender.
struct Guard {
    signing: Option<mavlink::SigningData>,
    pin: Option<Pin>,
    /// What is pinned and when it was last heard.
    pinned: Mutex<Option<(Pinned, std::time::Instant)>>,
}

/// Logs the 1st, 10th, 100th... refusal of a kind: visible, but a flood does not flood the log.
fn note_refusal(counter: &AtomicU64, what: &str, from: Option<SocketAddr>, sys: u32) {
    let n = counter.fetch_add(1, Ordering::Relaxed) + 1;
    if n.checked_ilog10().is_some_and(|e| 10u64.pow(e) == n) {
        tracing::warn!("MAVLink frame refused ({what}) from system {sys} at {from:?}: {n} so far");
    }
}

impl Guard {
    fn new(opts: &OpenOptions) -> Self {
        Self {
            signing: opts.signing.as_ref().map(Signing::data),
            pin: opts.pin.clone(),
            pinned: Mutex::new(None),
        }
    }

    fn pinned(&self) -> Option<Pinned> {
        self.pinned
            .lock()
            .unwrap_or_else(PoisonError::into_inner)
            .map(|(p, _)| p)
    }

    /// Checks the signature of `raw` (when signing), decodes it and checks it against the
    /// pin (when pinning; the first matching heartbeat pins and, on `udpin`, sets `learn`).
    /// `None` when refused or unparsable, counted.
    fn admit(
        &self,
        raw: &MAVLinkMessageRaw,
        from: Option<SocketAddr>,
        learn: Option<&PeerSlot>,
        counters: &Counters,
    ) -> Option<(MavHeader, MavMessage)> {
        if let Some(signing) = &self.signing {
            let ok = match raw {
                MAVLinkMessageRaw::V1(_) => false,
                MAVLinkMessageRaw::V2(v2) => signing.verify_signature(v2),
            };
            if !ok {
                let what = "unsigned, wrongly signed or replayed";
                note_refusal(&counters.rejected_signatures, what, from, raw.system_id());
                return None;
            }
        }
        let Ok(msg) = MavMessage::parse(raw.version(), raw.message_id(), raw.payload()) else {
            counters.parse_errors.fetch_add(1, Ordering::Relaxed);
            return None;
        };
        let header = MavHeader {
            system_id: raw.system_id(),
            component_id: raw.component_id(),
            sequence: raw.sequence(),
        };
        let Some(pin) = &self.pin else {
            if let (Some(slot), Some(from)) = (learn, from) {
                // Learnt before the frame is handed on, so an answer goes back to its sender.
                set_peer(slot, from);
            }
            return Some((header, msg));
        };
        let mut pinned = self.pinned.lock().unwrap_or_else(PoisonError::into_inner);
        let now = std::time::Instant::now();
        // A pin whose peer stayed silent past `release_after` is open again (an autopilot
        // restarted from another port); until then nobody else is listened to.
        let current = pinned.filter(|(_, seen)| {
            pin.release_after
                .is_none_or(|d| now.saturating_duration_since(*seen) <= d)
        });
        let admitted = match current {
            Some((p, _)) => {
                let ok = p.system_id == header.system_id
                    && p.component_id == header.component_id
                    && p.addr == from;
                if ok {
                    *pinned = Some((p, now));
                }
                ok
            }
            None => {
                let fits = matches!(&msg, MavMessage::HEARTBEAT(hb) if is_autopilot_heartbeat(hb))
                    && pin
                        .system_id
                        .is_none_or(|s| u32::from(s) == header.system_id)
                    && pin.component_id.is_none_or(|c| c == header.component_id)
                    && (pin.peer.is_none() || pin.peer == from);
                if fits {
                    let p = Pinned {
                        system_id: header.system_id,
                        component_id: header.component_id,
                        addr: from,
                    };
                    *pinned = Some((p, now));
                    if let (Some(slot), Some(from)) = (learn, from) {
                        set_peer(slot, from);
                    }
                    tracing::info!(
                        "MAVLink peer pinned: system {} component {} at {from:?}",
                        header.system_id,
                        header.component_id
                    );
                }
                fits
            }
        };
        if !admitted {
            let what = "not the pinned peer";
            note_refusal(&counters.foreign, what, from, header.system_id);
            return None;
        }
        Some((header, msg))
    }
}

/// An open connection: decoded frames in, frames out. Dropping it stops its tasks;
/// [`Connection::close`] also waits for them.
pub struct Connection {
    rx: mpsc::Receiver<io::Result<Frame>>,
    writer: Writer,
    local_addr: Option<SocketAddr>,
    counters: Arc<Counters>,
    guard: Arc<Guard>,
    cancel: CancellationToken,
    tasks: JoinSet<()>,
    // Keeps a created pty's slave open so the master never sees EIO/HUP while no client has
    // the device open, and so clients can come and go.
    _pty_slave: Option<SerialStream>,
}

async fn resolve(addr: &str) -> Result<SocketAddr, ConnectionOpenError> {
    let err = |source| ConnectionOpenError::Resolve {
        addr: addr.to_owned(),
        source,
    };
    lookup_host(addr).await.map_err(err)?.next().ok_or_else(|| {
        err(io::Error::new(
            io::ErrorKind::NotFound,
            format!("no address for {addr}"),
        ))
    })
}

async fn bind_udp(addr: SocketAddr) -> Result<(UdpSocket, SocketAddr), ConnectionOpenError> {
    let err = |source| ConnectionOpenError::UdpBind { addr, source };
    let sock = UdpSocket::bind(addr).await.map_err(err)?;
    let local = sock.local_addr().map_err(err)?;
    // try_send_to only succeeds once the reactor has reported the socket writable; without
    // this the first frames sent right after opening would be dropped as congestion.
    sock.writable().await.map_err(err)?;
    Ok((sock, local))
}

impl Connection {
    /// Opens `endpoint` and starts its reader (and, on byte streams, writer) task.
    ///
    /// `udpin` replies to the last sender of a valid frame (and nobody until one came);
    /// `udpout` always sends to its address. A serial device is opened non-exclusively, so a
    /// pty kept open by its creator stays reopenable.
    ///
    /// # Errors
    /// When the address does not resolve, or the socket, server or device cannot be opened.
    pub async fn open(endpoint: &Endpoint, opts: OpenOptions) -> Result<Self, ConnectionOpenError> {
        let mut conn = Self::new(&opts);
        match endpoint {
            Endpoint::UdpOut(addr) => {
                let dest = resolve(addr).await?;
                let any: SocketAddr = if dest.is_ipv4() {
                    ([0, 0, 0, 0], 0).into()
                } else {
                    (Ipv6Addr::UNSPECIFIED, 0).into()
                };
                conn.start_udp(bind_udp(any).await?, Some(dest), false, &opts);
            }
            Endpoint::UdpIn(addr) => {
                let bound = bind_udp(resolve(addr).await?).await?;
                conn.start_udp(bound, None, true, &opts);
            }
            Endpoint::TcpOut(addr) => {
                let err = |source| ConnectionOpenError::TcpConnect {
                    addr: addr.clone(),
                    source,
                };
                let stream = TcpStream::connect(addr).await.map_err(err)?;
                stream.set_nodelay(true).map_err(err)?;
                conn.local_addr = stream.local_addr().ok();
                conn.start_stream(stream, &opts);
            }
            Endpoint::Serial { path, baud } => {
                let err = |source| ConnectionOpenError::Serial {
                    path: path.clone(),
                    source,
                };
                let mut port = tokio_serial::new(path, *baud)
                    .open_native_async()
                    .map_err(err)?;
                port.set_exclusive(false).map_err(err)?;
                conn.start_stream(port, &opts);
            }
        }
        Ok(conn)
    }

    /// Creates a pty pair and speaks on its master side; clients open the slave, whose path
    /// is returned. The connection keeps the slave open so clients can come and go.
    ///
    /// # Errors
    /// When no pty pair can be created.
    pub fn create_pty(opts: OpenOptions) -> Result<(Self, String), ConnectionOpenError> {
        let (master, slave) = SerialStream::pair().map_err(ConnectionOpenError::Pty)?;
        let name = slave.name().unwrap_or_default();
        let mut conn = Self::new(&opts);
        conn._pty_slave = Some(slave);
        conn.start_stream(master, &opts);
        Ok((conn, name))
    }

    fn new(opts: &OpenOptions) -> Self {
        // Replaced by the start_* call that follows; a closed channel until then.
        let (_, rx) = mpsc::channel(1);
        let (idle, _) = mpsc::channel(1);
        Self {
            rx,
            writer: Writer::Stream(idle),
            local_addr: None,
            counters: opts.counters.clone(),
            guard: Arc::new(Guard::new(opts)),
            cancel: CancellationToken::new(),
            tasks: JoinSet::new(),
            _pty_slave: None,
        }
    }

    fn start_udp(
        &mut self,
        (sock, local): (UdpSocket, SocketAddr),
        dest: Option<SocketAddr>,
        learn_peer: bool,
        opts: &OpenOptions,
    ) {
        let (tx, rx) = mpsc::channel(opts.queue_depth.max(1));
        let sock = Arc::new(sock);
        // A configured peer is answered from the start, before its first heartbeat.
        let configured = opts.pin.as_ref().and_then(|p| p.peer);
        let peer: PeerSlot = Arc::new(Mutex::new(dest.or(configured)));
        self.tasks.spawn(udp_reader(
            sock.clone(),
            learn_peer.then(|| peer.clone()),
            tx,
            self.counters.clone(),
            self.guard.clone(),
            self.cancel.clone(),
        ));
        self.rx = rx;
        self.local_addr = Some(local);
        self.writer = Writer::Udp {
            sock,
            peer,
            also: opts.also_send_to,
        };
    }

    fn start_stream<S>(&mut self, stream: S, opts: &OpenOptions)
    where
        S: AsyncRead + AsyncWrite + Send + 'static,
    {
        let depth = opts.queue_depth.max(1);
        let (tx, rx) = mpsc::channel(depth);
        let (out_tx, out_rx) = mpsc::channel(depth);
        let (rd, wr) = tokio::io::split(stream);
        self.tasks.spawn(stream_reader(
            rd,
            tx,
            self.counters.clone(),
            self.guard.clone(),
            self.cancel.clone(),
        ));
        self.tasks
            .spawn(stream_writer(wr, out_rx, self.cancel.clone()));
        self.rx = rx;
        self.writer = Writer::Stream(out_tx);
    }

    /// The local socket address (UDP, TCP); `None` on serial devices and ptys.
    pub fn local_addr(&self) -> Option<SocketAddr> {
        self.local_addr
    }

    /// The counters this connection updates.
    pub fn counters(&self) -> &Arc<Counters> {
        &self.counters
    }

    /// The next frame; `None` or `Some(Err)` when the connection is gone. Cancel-safe.
    pub async fn recv(&mut self) -> Option<io::Result<Frame>> {
        self.rx.recv().await
    }

    /// Encodes `msg` as MAVLink 2 with `header` and sends it without waiting: on UDP to the
    /// peer (if known) and to [`OpenOptions::also_send_to`]; on a byte stream through the
    /// writer's queue. A congested output drops the frame and counts it in
    /// [`Counters::dropped`], like a radio.
    ///
    /// # Errors
    /// [`SendError::Encode`] when the message cannot be encoded, [`SendError::Closed`] when the
    /// stream writer has stopped, [`SendError::Io`] when a UDP send fails for a reason other
    /// than congestion.
    pub fn send(&mut self, header: MavHeader, msg: &MavMessage) -> Result<(), SendError> {
        let mut buf = Vec::with_capacity(64);
        mavlink::write_versioned_msg_signed(
            &mut buf,
            MavlinkVersion::V2,
            header,
            msg,
            self.guard.signing.as_ref(),
        )
        .map_err(SendError::Encode)?;
        self.send_bytes(buf)
    }

    /// Writes [`RESYNC_BYTES`] zero bytes on a byte stream (nothing on UDP, where every
    /// datagram starts a fresh parse): a receiver waiting for the rest of a frame whose length
    /// byte was corrupted completes it, fails its CRC and looks for the next start marker.
    ///
    /// # Errors
    /// [`SendError::Closed`] when the stream writer has stopped.
    pub fn resync(&mut self) -> Result<(), SendError> {
        match self.writer {
            Writer::Udp { .. } => Ok(()),
            Writer::Stream(_) => self.send_bytes(vec![0; RESYNC_BYTES]),
        }
    }

    fn send_bytes(&self, buf: Vec<u8>) -> Result<(), SendError> {
        let drop_one = || {
            self.counters.dropped.fetch_add(1, Ordering::Relaxed);
        };
        match &self.writer {
            Writer::Udp { sock, peer, also } => {
                let peer = get_peer(peer);
                let mut result = Ok(());
                for dest in peer.iter().chain(also.iter().filter(|a| Some(**a) != peer)) {
                    match sock.try_send_to(&buf, *dest) {
                        Ok(_) => {}
                        Err(e) if e.kind() == io::ErrorKind::WouldBlock || is_transient(&e) => {
                            drop_one();
                        }
                        Err(e) => result = Err(SendError::Io(e)),
                    }
                }
                result
            }
            Writer::Stream(tx) => match tx.try_send(buf) {
                Ok(()) => Ok(()),
                Err(mpsc::error::TrySendError::Full(_)) => {
                    drop_one();
                    Ok(())
                }
                Err(mpsc::error::TrySendError::Closed(_)) => Err(SendError::Closed),
            },
        }
    }

    /// What the pin fixed (see [`OpenOptions::pin`]); `None` before the first matching
    /// heartbeat or without pinning.
    pub fn pinned(&self) -> Option<Pinned> {
        self.guard.pinned()
    }

    /// Stops the reader and writer tasks and waits for them.
    pub async fn close(mut self) {
        self.cancel.cancel();
        while self.tasks.join_next().await.is_some() {}
    }
}

impl Drop for Connection {
    fn drop(&mut self) {
        self.cancel.cancel();
        self.tasks.abort_all();
    }
}

fn is_transient(e: &io::Error) -> bool {
    // An ICMP "port unreachable" from an earlier send surfaces on the next socket call.
    matches!(
        e.kind(),
        io::ErrorKind::ConnectionRefused
            | io::ErrorKind::ConnectionReset
            | io::ErrorKind::Interrupted
    )
}

async fn udp_reader(
    sock: Arc<UdpSocket>,
    learn_peer: Option<PeerSlot>,
    tx: mpsc::Sender<io::Result<Frame>>,
    counters: Arc<Counters>,
    guard: Arc<Guard>,
    cancel: CancellationToken,
) {
    let mut buf = vec![0u8; 65_536];
    loop {
        let (n, from) = tokio::select! {
            _ = cancel.cancelled() => return,
            r = sock.recv_from(&mut buf) => match r {
                Ok(x) => x,
                // ICMP port unreachable while the other side is down: keep listening.
                Err(e) if is_transient(&e) => continue,
                Err(e) => {
                    let _ = tx.send(Err(e)).await;
                    return;
                }
            },
        };
        let mut reader = MavlinkReader::new(&buf[..n]);
        loop {
            let raw = match reader.read_any_raw_message::<MavMessage>() {
                Ok(x) => x,
                Err(MessageReadError::Parse(_)) => {
                    counters.parse_errors.fetch_add(1, Ordering::Relaxed);
                    continue;
                }
                Err(MessageReadError::Io(_)) => break,
            };
            let Some((header, msg)) = guard.admit(&raw, Some(from), learn_peer.as_ref(), &counters)
            else {
                continue;
            };
            let frame = Frame {
                header,
                msg,
                peer: Some(from),
            };
            if tx.send(Ok(frame)).await.is_err() {
                return;
            }
        }
    }
}

async fn stream_reader<R: AsyncRead + Unpin>(
    rd: R,
    tx: mpsc::Sender<io::Result<Frame>>,
    counters: Arc<Counters>,
    guard: Arc<Guard>,
    cancel: CancellationToken,
) {
    let mut reader = AsyncMavlinkReader::new(rd);
    loop {
        // The reader keeps partial frames buffered when this select drops the read.
        let r = tokio::select! {
            _ = cancel.cancelled() => return,
            r = reader.read_any_raw_message::<MavMessage>() => r,
        };
        match r {
            Ok(raw) => {
                let Some((header, msg)) = guard.admit(&raw, None, None, &counters) else {
                    continue;
                };
                let frame = Frame {
                    header,
                    msg,
                    peer: None,
                };
                if tx.send(Ok(frame)).await.is_err() {
                    return;
                }
            }
            Err(MessageReadError::Parse(_)) => {
                counters.parse_errors.fetch_add(1, Ordering::Relaxed);
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
            // Later sends report SendError::Closed to the owner, who decides what to do.
            tracing::warn!("MAVLink stream write failed: {e}");
            return;
        }
    }
}

#[cfg(test)]
mod tests {
    use std::future::Future;
    use std::time::Duration;

    use mavlink::dialects::ardupilotmega::HEARTBEAT_DATA;
    use mavlink::dialects::ardupilotmega::{MavAutopilot, MavModeFlag, MavState, MavType};
    use mavlink::Message;
    use tokio::io::AsyncReadExt;
    use tokio::net::TcpListener;

    use super::*;

    const WAIT: Duration = Duration::from_secs(5);

    async fn within<T>(f: impl Future<Output = T>) -> T {
        tokio::time::timeout(WAIT, f).await.expect("timed out")
    }

    fn header(sys: u8) -> MavHeader {
        MavHeader {
            system_id: u32::from(sys),
            component_id: 1,
            sequence: 0,
        }
    }

    /// A heartbeat that carries `mark` in `custom_mode`, to tell frames apart.
    fn heartbeat(mark: u32) -> MavMessage {
        MavMessage::HEARTBEAT(HEARTBEAT_DATA {
            custom_mode: mark,
            mavtype: MavType::MAV_TYPE_GROUND_ROVER,
            autopilot: MavAutopilot::MAV_AUTOPILOT_ARDUPILOTMEGA,
            base_mode: MavModeFlag::empty(),
            system_status: MavState::MAV_STATE_ACTIVE,
            mavlink_version: 3,
        })
    }

    fn frame_bytes(mark: u32) -> Vec<u8> {
        let mut buf = Vec::new();
        mavlink::write_versioned_msg(&mut buf, MavlinkVersion::V2, header(1), &heartbeat(mark))
            .expect("a heartbeat always encodes");
        buf
    }

    /// Payload starts after STX and the 9 header bytes of MAVLink 2.
    const PAYLOAD: usize = 10;

    /// A heartbeat whose CRC does not match its payload.
    fn bad_crc_bytes(mark: u32) -> Vec<u8> {
        let mut buf = frame_bytes(mark);
        buf[PAYLOAD] ^= 0x55;
        buf
    }

    /// A heartbeat with a valid CRC whose vehicle type (payload byte 4) is no MAV_TYPE.
    fn unparsable_bytes() -> Vec<u8> {
        let mut buf = frame_bytes(9);
        let len = usize::from(buf[1]);
        buf[PAYLOAD + 4] = 0xEE;
        let crc = mavlink::calculate_crc(&buf[1..PAYLOAD + len], MavMessage::extra_crc(0));
        buf[PAYLOAD + len..PAYLOAD + len + 2].copy_from_slice(&crc.to_le_bytes());
        buf
    }

    fn mark_of(frame: &Frame) -> u32 {
        match &frame.msg {
            MavMessage::HEARTBEAT(hb) => hb.custom_mode,
            other => panic!("expected a heartbeat, got {other:?}"),
        }
    }

    async fn next(conn: &mut Connection) -> Frame {
        within(conn.recv())
            .await
            .expect("connection open")
            .expect("no I/O error")
    }

    async fn udp_in() -> (Connection, SocketAddr) {
        let conn = Connection::open(
            &"udpin:127.0.0.1:0".parse().expect("valid endpoint"),
            OpenOptions::default(),
        )
        .await
        .expect("bind loopback");
        let addr = conn.local_addr().expect("UDP has a local address");
        (conn, addr)
    }

    /// A `tcpout` connection and the server side of its stream.
    async fn tcp_pair(opts: OpenOptions) -> (Connection, tokio::net::TcpStream) {
        let listener = TcpListener::bind("127.0.0.1:0").await.expect("bind");
        let addr = listener.local_addr().expect("bound");
        // The kernel completes the handshake before accept() is called.
        let client = within(Connection::open(&Endpoint::TcpOut(addr.to_string()), opts))
            .await
            .expect("connect");
        let (server, _) = within(listener.accept()).await.expect("accept");
        (client, server)
    }

    #[tokio::test]
    async fn udpout_reaches_udpin_and_udpin_answers_the_last_sender() {
        let (mut server, addr) = udp_in().await;
        let mut client =
            Connection::open(&Endpoint::UdpOut(addr.to_string()), OpenOptions::default())
                .await
                .expect("open udpout");
        // No sender yet: udpin has nobody to answer, and says so by sending nothing.
        server.send(header(1), &heartbeat(1)).expect("send");
        client.send(header(255), &heartbeat(2)).expect("send");
        let got = next(&mut server).await;
        assert_eq!(mark_of(&got), 2);
        assert_eq!(got.header.system_id, 255);
        let client_port = client.local_addr().expect("bound").port();
        assert_eq!(got.peer.map(|p| p.port()), Some(client_port));
        server.send(header(1), &heartbeat(3)).expect("send");
        let back = next(&mut client).await;
        assert_eq!(
            mark_of(&back),
            3,
            "the frame sent before any peer must not arrive"
        );
        assert_eq!(back.peer, Some(addr));
        assert_eq!(server.counters().parse_errors(), 0);
        client.close().await;
        server.close().await;
    }

    #[tokio::test]
    async fn udpin_also_sends_to_the_extra_address() {
        let extra = UdpSocket::bind("127.0.0.1:0").await.expect("bind");
        let opts = OpenOptions {
            also_send_to: Some(extra.local_addr().expect("bound")),
            ..OpenOptions::default()
        };
        let mut server = Connection::open(&"udpin:127.0.0.1:0".parse().expect("valid"), opts)
            .await
            .expect("bind");
        server.send(header(1), &heartbeat(4)).expect("send");
        let mut buf = [0u8; 512];
        let n = within(extra.recv(&mut buf)).await.expect("recv");
        let (_, msg) = MavlinkReader::new(&buf[..n])
            .read_any_message::<MavMessage>()
            .expect("a valid frame");
        assert!(matches!(msg, MavMessage::HEARTBEAT(hb) if hb.custom_mode == 4));
    }

    #[tokio::test]
    async fn tcp_carries_frames_both_ways() {
        let (mut client, mut server) = tcp_pair(OpenOptions::default()).await;
        server.write_all(&frame_bytes(5)).await.expect("write");
        let got = next(&mut client).await;
        assert_eq!(mark_of(&got), 5);
        assert_eq!(got.peer, None);
        client.send(header(255), &heartbeat(6)).expect("send");
        let expected = frame_bytes(6).len();
        let mut buf = vec![0u8; expected];
        within(server.read_exact(&mut buf)).await.expect("read");
        let (hdr, msg) = MavlinkReader::new(&buf[..])
            .read_any_message::<MavMessage>()
            .expect("a valid frame");
        assert_eq!(hdr.system_id, 255);
        assert!(matches!(msg, MavMessage::HEARTBEAT(hb) if hb.custom_mode == 6));
        // Resync puts exactly RESYNC_BYTES zero bytes on the stream.
        client.resync().expect("resync");
        let mut zeros = vec![1u8; RESYNC_BYTES];
        within(server.read_exact(&mut zeros)).await.expect("read");
        assert!(zeros.iter().all(|&b| b == 0));
        // The peer closing the stream ends it with an error, not silently.
        drop(server);
        assert!(matches!(within(client.recv()).await, Some(Err(_))));
    }

    #[tokio::test]
    async fn a_bad_crc_frame_is_skipped_on_a_stream() {
        let (mut client, mut server) = tcp_pair(OpenOptions::default()).await;
        let mut bytes = bad_crc_bytes(7);
        bytes.extend(frame_bytes(8));
        server.write_all(&bytes).await.expect("write");
        assert_eq!(mark_of(&next(&mut client).await), 8);
        // Not a parse error: the CRC check rejected it before parsing.
        assert_eq!(client.counters().parse_errors(), 0);
    }

    #[tokio::test]
    async fn a_bad_crc_frame_is_skipped_in_a_datagram() {
        let (mut server, addr) = udp_in().await;
        let sock = UdpSocket::bind("127.0.0.1:0").await.expect("bind");
        let mut datagram = bad_crc_bytes(7);
        datagram.extend(frame_bytes(8));
        within(sock.send_to(&datagram, addr)).await.expect("send");
        assert_eq!(mark_of(&next(&mut server).await), 8);
        assert_eq!(server.counters().parse_errors(), 0);
    }

    #[tokio::test]
    async fn a_frame_that_does_not_parse_is_counted_and_skipped() {
        let (mut server, addr) = udp_in().await;
        let sock = UdpSocket::bind("127.0.0.1:0").await.expect("bind");
        let mut datagram = unparsable_bytes();
        datagram.extend(frame_bytes(10));
        within(sock.send_to(&datagram, addr)).await.expect("send");
        assert_eq!(mark_of(&next(&mut server).await), 10);
        assert_eq!(server.counters().parse_errors(), 1);

        // The same on a byte stream, with counters shared by the caller.
        let counters = Arc::new(Counters::default());
        let opts = OpenOptions {
            counters: counters.clone(),
            ..OpenOptions::default()
        };
        let (mut client, mut stream) = tcp_pair(opts).await;
        let mut bytes = unparsable_bytes();
        bytes.extend(frame_bytes(11));
        stream.write_all(&bytes).await.expect("write");
        assert_eq!(mark_of(&next(&mut client).await), 11);
        assert_eq!(counters.parse_errors(), 1);
    }

    fn signing(key: u8, link_id: u8) -> Option<Signing> {
        Some(Signing {
            key: crate::SigningKey::from_bytes([key; 32]),
            link_id,
        })
    }

    #[tokio::test]
    async fn signed_ends_talk_and_unsigned_or_wrongly_signed_frames_are_refused() {
        let opts = |key| OpenOptions {
            signing: signing(key, 1),
            ..OpenOptions::default()
        };
        let mut server = Connection::open(&"udpin:127.0.0.1:0".parse().expect("valid"), opts(9))
            .await
            .expect("bind");
        let addr = server.local_addr().expect("bound");
        // Unsigned (a plain socket), then signed with another key: both refused, counted.
        let sock = UdpSocket::bind("127.0.0.1:0").await.expect("bind");
        within(sock.send_to(&frame_bytes(1), addr))
            .await
            .expect("send");
        let mut wrong = Connection::open(&Endpoint::UdpOut(addr.to_string()), opts(8))
            .await
            .expect("open");
        wrong.send(header(255), &heartbeat(2)).expect("send");
        let mut client = Connection::open(&Endpoint::UdpOut(addr.to_string()), opts(9))
            .await
            .expect("open");
        client.send(header(255), &heartbeat(3)).expect("send");
        // Datagrams on loopback arrive in order: the first delivered is the signed one.
        let got = next(&mut server).await;
        assert_eq!(mark_of(&got), 3);
        assert_eq!(server.counters().rejected_signatures(), 2);
        // The answer is signed too: the client accepts it.
        server.send(header(1), &heartbeat(4)).expect("send");
        assert_eq!(mark_of(&next(&mut client).await), 4);
        assert_eq!(client.counters().rejected_signatures(), 0);
        // A replay of a signed frame (same timestamp) is refused.
        let mut signed = Vec::new();
        let data = signing(9, 1).expect("some").data();
        mavlink::write_versioned_msg_signed(
            &mut signed,
            MavlinkVersion::V2,
            header(255),
            &heartbeat(5),
            Some(&data),
        )
        .expect("encode");
        within(sock.send_to(&signed, addr)).await.expect("send");
        within(sock.send_to(&signed, addr)).await.expect("send");
        client.send(header(255), &heartbeat(6)).expect("send");
        assert_eq!(mark_of(&next(&mut server).await), 5);
        assert_eq!(mark_of(&next(&mut server).await), 6);
        assert_eq!(server.counters().rejected_signatures(), 3);
    }

    #[tokio::test]
    async fn udpin_pins_the_first_heartbeat_and_ignores_spoofers() {
        let opts = OpenOptions {
            pin: Some(Pin {
                component_id: None,
                system_id: Some(1),
                peer: None,
                release_after: None,
            }),
            ..OpenOptions::default()
        };
        let mut server = Connection::open(&"udpin:127.0.0.1:0".parse().expect("valid"), opts)
            .await
            .expect("bind");
        let addr = server.local_addr().expect("bound");
        let real = UdpSocket::bind("127.0.0.1:0").await.expect("bind");
        let spoof = UdpSocket::bind("127.0.0.1:0").await.expect("bind");
        // A heartbeat of another system does not pin; the expected one does.
        let mut other = Vec::new();
        mavlink::write_versioned_msg(&mut other, MavlinkVersion::V2, header(7), &heartbeat(1))
            .expect("encode");
        within(spoof.send_to(&other, addr)).await.expect("send");
        within(real.send_to(&frame_bytes(2), addr))
            .await
            .expect("send");
        let got = next(&mut server).await;
        assert_eq!(mark_of(&got), 2);
        let pinned = server.pinned().expect("pinned");
        assert_eq!(pinned.system_id, 1);
        assert_eq!(pinned.addr, real.local_addr().ok());
        // The same system id from another port: dropped, counted, not followed.
        within(spoof.send_to(&frame_bytes(3), addr))
            .await
            .expect("send");
        within(real.send_to(&frame_bytes(4), addr))
            .await
            .expect("send");
        assert_eq!(mark_of(&next(&mut server).await), 4);
        assert_eq!(server.counters().foreign(), 2);
        server.send(header(255), &heartbeat(5)).expect("send");
        let mut buf = [0u8; 512];
        let (n, from) = within(real.recv_from(&mut buf)).await.expect("recv");
        assert_eq!(from, addr);
        let (_, msg) = MavlinkReader::new(&buf[..n])
            .read_any_message::<MavMessage>()
            .expect("a valid frame");
        assert!(matches!(msg, MavMessage::HEARTBEAT(hb) if hb.custom_mode == 5));
        // The spoofer never got an answer.
        let nothing = tokio::time::timeout(Duration::from_millis(200), spoof.recv(&mut buf)).await;
        assert!(nothing.is_err(), "the spoofer got a datagram");
    }

    #[tokio::test]
    async fn a_silent_pinned_peer_is_released_for_the_next_heartbeat() {
        let release = Duration::from_millis(300);
        let opts = OpenOptions {
            pin: Some(Pin {
                component_id: None,
                system_id: Some(1),
                peer: None,
                release_after: Some(release),
            }),
            ..OpenOptions::default()
        };
        let mut server = Connection::open(&"udpin:127.0.0.1:0".parse().expect("valid"), opts)
            .await
            .expect("bind");
        let addr = server.local_addr().expect("bound");
        let old = UdpSocket::bind("127.0.0.1:0").await.expect("bind");
        let new = UdpSocket::bind("127.0.0.1:0").await.expect("bind");
        within(old.send_to(&frame_bytes(1), addr))
            .await
            .expect("send");
        assert_eq!(mark_of(&next(&mut server).await), 1);
        // While the pinned peer is live, another port is ignored.
        within(new.send_to(&frame_bytes(2), addr))
            .await
            .expect("send");
        within(old.send_to(&frame_bytes(3), addr))
            .await
            .expect("send");
        assert_eq!(mark_of(&next(&mut server).await), 3);
        // Silent past the release time (a lower bound: the point of the test is the silence):
        // the restarted autopilot's heartbeat from its new port pins again.
        tokio::time::sleep(release + Duration::from_millis(100)).await;
        within(new.send_to(&frame_bytes(4), addr))
            .await
            .expect("send");
        assert_eq!(mark_of(&next(&mut server).await), 4);
        assert_eq!(server.pinned().and_then(|p| p.addr), new.local_addr().ok());
        within(old.send_to(&frame_bytes(5), addr))
            .await
            .expect("send");
        within(new.send_to(&frame_bytes(6), addr))
            .await
            .expect("send");
        assert_eq!(mark_of(&next(&mut server).await), 6);
        assert_eq!(server.counters().foreign(), 2);
    }

    #[tokio::test]
    async fn a_configured_peer_is_answered_at_once_and_others_ignored() {
        let real = UdpSocket::bind("127.0.0.1:0").await.expect("bind");
        let spoof = UdpSocket::bind("127.0.0.1:0").await.expect("bind");
        let opts = OpenOptions {
            pin: Some(Pin {
                component_id: None,
                system_id: None,
                peer: real.local_addr().ok(),
                release_after: None,
            }),
            ..OpenOptions::default()
        };
        let mut server = Connection::open(&"udpin:127.0.0.1:0".parse().expect("valid"), opts)
            .await
            .expect("bind");
        let addr = server.local_addr().expect("bound");
        server.send(header(255), &heartbeat(1)).expect("send");
        let mut buf = [0u8; 512];
        within(real.recv(&mut buf))
            .await
            .expect("answered before any heartbeat");
        within(spoof.send_to(&frame_bytes(2), addr))
            .await
            .expect("send");
        within(real.send_to(&frame_bytes(3), addr))
            .await
            .expect("send");
        assert_eq!(mark_of(&next(&mut server).await), 3);
        assert_eq!(server.counters().foreign(), 1);
    }

    #[tokio::test]
    async fn a_full_stream_queue_drops_and_counts() {
        let opts = OpenOptions {
            queue_depth: 1,
            ..OpenOptions::default()
        };
        let (mut client, _server) = tcp_pair(opts).await;
        // Without awaiting, the writer task cannot run: the first frame fills the queue.
        for mark in 0..3 {
            client
                .send(header(255), &heartbeat(mark))
                .expect("send never fails on congestion");
        }
        assert_eq!(client.counters().dropped(), 2);
    }
}
