//! The simulator's end of a MAVLink connection: which transport (`--udp`/`--out`, `--serial`,
//! `--pty`) and the vehicle's own header and sequence numbers on every frame it sends.
//!
//! The transport itself (reader task feeding a channel, framing, UDP reply-to-last-sender,
//! dropping on a congested line) is [`mavconn::Connection`], shared with the VAS.

use std::io;
use std::net::SocketAddr;

use mavconn::{Connection, Endpoint, OpenOptions, SendError, Signing};
use mavlink::dialects::ardupilotmega::MavMessage;
use mavlink::MavHeader;

pub use mavconn::ConnectionOpenError as LinkOpenError;
pub use mavconn::Frame as Inbound;

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

/// An open link: decoded messages in, frames out.
pub struct Link {
    info: LinkInfo,
    conn: Connection,
    header: MavHeader,
    /// Sends the connection refused outright (its writer stopped, a UDP error), counted as
    /// drops: the simulator carries on like a vehicle whose radio failed.
    failed_sends: u64,
}

/// Decoded-frame and output queue depth: a congested serial line drops beyond it.
const CHANNEL_DEPTH: usize = 256;

impl Link {
    /// Opens the transport and starts its reader (and writer) task.
    ///
    /// # Errors
    /// When the socket, device or pty cannot be opened.
    pub async fn open(cfg: &LinkConfig, sysid: u8) -> Result<Self, LinkOpenError> {
        Self::open_signed(cfg, sysid, None).await
    }

    /// [`Link::open`] with MAVLink 2 signing: every frame sent is signed and only correctly
    /// signed frames are accepted (the others are counted, see [`Link::rejected_signatures`]).
    ///
    /// # Errors
    /// When the socket, device or pty cannot be opened.
    pub async fn open_signed(
        cfg: &LinkConfig,
        sysid: u8,
        signing: Option<Signing>,
    ) -> Result<Self, LinkOpenError> {
        let opts = OpenOptions {
            queue_depth: CHANNEL_DEPTH,
            signing,
            ..OpenOptions::default()
        };
        let (info, conn) = match cfg {
            LinkConfig::Udp { bind, out } => {
                let opts = OpenOptions {
                    also_send_to: *out,
                    ..opts
                };
                let conn = Connection::open(&Endpoint::UdpIn(bind.to_string()), opts).await?;
                let local = conn.local_addr().unwrap_or(*bind);
                (LinkInfo::Udp(local), conn)
            }
            LinkConfig::Serial { path, baud } => {
                let endpoint = Endpoint::Serial {
                    path: path.clone(),
                    baud: *baud,
                };
                let conn = Connection::open(&endpoint, opts).await?;
                (LinkInfo::Serial(path.clone()), conn)
            }
            LinkConfig::Pty => {
                let (conn, name) = Connection::create_pty(opts)?;
                (LinkInfo::Pty(name), conn)
            }
        };
        Ok(Self {
            info,
            conn,
            header: MavHeader {
                system_id: u32::from(sysid),
                component_id: 1,
                sequence: 0,
            },
            failed_sends: 0,
        })
    }

    /// What was opened.
    pub fn info(&self) -> &LinkInfo {
        &self.info
    }

    /// Frames that passed the CRC but could not be parsed.
    pub fn parse_errors(&self) -> u64 {
        self.conn.counters().parse_errors()
    }

    /// Frames refused for a missing, wrong or replayed signature (with signing only).
    pub fn rejected_signatures(&self) -> u64 {
        self.conn.counters().rejected_signatures()
    }

    /// Frames dropped because the output was congested or refused them.
    pub fn dropped(&self) -> u64 {
        self.conn.counters().dropped() + self.failed_sends
    }

    /// The next decoded message; `None` when the reader stopped. Cancel-safe.
    pub async fn recv(&mut self) -> Option<io::Result<Inbound>> {
        self.conn.recv().await
    }

    /// Sends `msg` without waiting; drops it when the output is congested.
    pub fn send(&mut self, msg: &MavMessage) {
        match self.conn.send(self.header, msg) {
            Ok(()) => {}
            // Never on the wire: the sequence number stays free.
            Err(SendError::Encode(_)) => return,
            Err(SendError::Closed | SendError::Io(_)) => self.failed_sends += 1,
        }
        self.header.sequence = self.header.sequence.wrapping_add(1);
    }

    /// Stops the reader and writer tasks.
    pub async fn close(self) {
        self.conn.close().await;
    }
}
