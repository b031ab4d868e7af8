//! Links move node messages over one medium, in two classes: **fast** (best effort, bounded
//! queue, newest value per variable wins) and **safe** (reliable, ordered, acknowledged).
//!
//! A link knows nothing of declarations or names: it carries encoded [`crate::protocol::Message`]s
//! to peer addresses and hands what it receives to a [`LinkHandler`] (the node).
//!
//! Each medium's framing lives with its link: [`udp`] and `zenoh` (cargo feature `zenoh`) share
//! the [`datagram`] link (its batching format, sessions and ARQ) and differ only in how a
//! datagram reaches an address; [`serial`] is the Serial Transport Protocol, `shm` iceoryx2
//! inboxes (cargo feature `shm`, on by default). What they share is here too: the ARQ of the
//! safe class over lossy media ([`arq`], used by the datagram links and serial; shared memory
//! loses nothing and only needs flow control, see `shm`), the bounded newest-wins queue of fast
//! messages ([`coalesce`]), and the counters behind [`LinkStats`].

pub mod arq;
pub mod auth;
pub mod coalesce;
mod completion;
// The datagram format and the link of ARQ sessions over any datagram medium (UDP, Zenoh).
#[cfg(any(feature = "udp", feature = "zenoh"))]
pub mod datagram;
// Without the feature a node refuses `<serial>` links as it refuses `<shm>` ones.
#[cfg(feature = "serial")]
pub mod serial;
// iceoryx2 and its configuration loader are most of a UDP-only node's code; a build without
// the feature refuses `<shm>` links when the node opens (`NodeOpenError::Unsupported`).
#[cfg(feature = "shm")]
pub mod shm;
// Likewise for `<ethernet>` links: a node that only talks to its own host can do without.
#[cfg(feature = "udp")]
pub mod udp;
// Zenoh is most of a build that has it: only nodes that reach beyond their LAN need it.
#[cfg(feature = "zenoh")]
pub mod zenoh;

use std::fmt;
use std::net::SocketAddr;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::Arc;

/// Where a peer is reached on a link.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum PeerAddr {
    /// A UDP unicast address.
    Udp(SocketAddr),
    /// The single peer at the other end of a point-to-point link (serial).
    PointToPoint,
    /// A same-host peer by shared-memory identity.
    Shm(u64),
    /// A peer beyond a Zenoh router, by its Zenoh link's id.
    Zenoh(u64),
}

impl fmt::Display for PeerAddr {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            PeerAddr::Udp(a) => write!(f, "udp://{a}"),
            PeerAddr::PointToPoint => write!(f, "point-to-point"),
            PeerAddr::Shm(id) => write!(f, "shm://{id:016x}"),
            PeerAddr::Zenoh(id) => write!(f, "zenoh://{id:016x}"),
        }
    }
}

/// How a shared-memory link's receive thread waits for frames (`wait` on `<shm>`). Here rather
/// than in `shm` so that a configuration names it in builds without the `shm` feature.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub enum ShmWait {
    /// Sleep on the inbox's wake event (watched by tokio's reactor): idle costs nothing, and
    /// a writer notifies a sleeping reader (one datagram; an atomic operation while the reader
    /// has not woken yet).
    #[default]
    Event,
    /// Busy-poll the inbox from a task of the link: writers never notify, so sending is a
    /// loan, a copy and an atomic store. While frames flow the task polls without pause,
    /// yielding its tokio worker between polls (so the node's other tasks still run, and the
    /// task a message is for is woken by a run-queue push, not a thread wake-up); after 10 ms
    /// without a frame it polls once per millisecond, so a message reaching an idle inbox may
    /// wait up to 1 ms. It keeps a worker busy while traffic flows.
    Spin,
}

impl ShmWait {
    /// The attribute value naming this mode.
    pub fn as_str(self) -> &'static str {
        match self {
            ShmWait::Event => "event",
            ShmWait::Spin => "spin",
        }
    }
}

/// How a Zenoh link's session joins the Zenoh network (`mode` on `<zenoh>`). Here rather than
/// in `zenoh` so that a configuration names it in builds without the `zenoh` feature.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum ZenohMode {
    /// Through the routers it connects to (`client`, the default): no multicast, no listening
    /// socket; what a vehicle behind a cellular modem or NAT needs.
    #[default]
    Client,
    /// A Zenoh peer (`peer`): connects and listens where told, and meets the other peers the
    /// routers tell it of. Multicast scouting stays off unless a `config` file turns it on.
    Peer,
}

impl ZenohMode {
    /// The attribute value naming this mode.
    pub fn as_str(self) -> &'static str {
        match self {
            ZenohMode::Client => "client",
            ZenohMode::Peer => "peer",
        }
    }
}

/// Why a safe message was not acknowledged.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum LinkSendError {
    /// The peer was closed (lease expired, node left, session reset) before acknowledging.
    #[error("peer {0} closed before acknowledging")]
    PeerClosed(String),
    /// The link is shutting down.
    #[error("link shut down")]
    Shutdown,
    /// The peer acknowledged nothing for the retry limit ([`arq::RetryLimit`]): the session
    /// was closed and the peer forgotten.
    #[error("peer {0} acknowledged nothing within the retry limit; session closed")]
    RetriesExhausted(String),
    /// The message exceeds what the link can carry (serial: 255 fragments).
    #[error("message of {0} bytes is too large for this link")]
    TooLarge(usize),
}

pub use completion::{AckCounter, SafeCompletion};

/// Events to one subscriber's node not yet acknowledged before [`crate::EventStream::send`]
/// waits; it goes on once half of them are. Large events wait sooner: see
/// [`STREAM_WINDOW_BYTES`]. (A gateway holds its forwarded events to the same window.)
pub const STREAM_WINDOW: u64 = 16_384;

/// Bytes of events to one subscriber's node not yet acknowledged before
/// [`crate::EventStream::send`] waits (at least 64 events; 2,048 of 1 KiB): 8,192 events of
/// 1 KiB in flight churned 8 MiB of memory, more than a loopback or LAN path needs to stay full,
/// and streamed 30 % slower. A node reached over a serial link gets 4 s of its line instead
/// (46,080 B at 115,200 baud: [`Link::stream_window_bytes`]).
pub const STREAM_WINDOW_BYTES: u64 = 2 << 20;

/// Events of `mean` bytes that `window_bytes` allow in flight: at least 64, at most
/// [`STREAM_WINDOW`].
pub(crate) fn stream_window(window_bytes: u64, mean: u64) -> u64 {
    (window_bytes / mean.max(1)).clamp(64, STREAM_WINDOW)
}

/// A message handed to a link.
#[derive(Debug)]
pub enum Outgoing {
    /// Best effort. Messages with the same `coalesce` key replace each other while unsent.
    Fast {
        /// Coalescing key (a variable's id), if any.
        coalesce: Option<u32>,
        /// Encoded message.
        msg: Vec<u8>,
    },
    /// Reliable and ordered.
    Safe {
        /// Encoded message (shared: one message to several peers is one buffer).
        msg: bytes::Bytes,
        /// Told when acknowledged.
        done: Option<SafeCompletion>,
    },
}

impl Outgoing {
    /// Drops a message that cannot be sent to `to` (no such peer, too many peers): a safe
    /// message's completion is told [`LinkSendError::PeerClosed`].
    pub(crate) fn refuse(self, to: impl fmt::Display) {
        if let Outgoing::Safe { done, .. } = self {
            refuse_done(done, to);
        }
    }
}

/// Tells a safe message's completion, if any, that `to` cannot be sent to
/// ([`LinkSendError::PeerClosed`]).
pub(crate) fn refuse_done(done: Option<SafeCompletion>, to: impl fmt::Display) {
    if let Some(d) = done {
        let _ = d.send(Err(LinkSendError::PeerClosed(to.to_string())));
    }
}

/// How a safe message may be reordered against those sent before it ([`LinkHandler::precedence`]).
/// An urgent message passes passable ones queued before it and nothing else; every other pair
/// keeps the order it was sent in.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Precedence {
    /// May pass passable messages (a call, a reply).
    Urgent,
    /// May be passed by urgent ones (data: a camera frame, an event, a file's chunk).
    Passable,
    /// Neither (the introductions and declarations urgent messages depend on).
    InOrder,
}

/// Receives what a link delivers. Called from the link's receive task: must not block.
pub trait LinkHandler: Send + Sync + 'static {
    /// A fast or (in order) safe message from `from`.
    fn on_message(&self, link: usize, from: PeerAddr, msg: &[u8]);
    /// A safe message of ours leaves a link's queue for the line after `waited` in it: a
    /// link whose queue can hold messages long (a radio) calls this so the message can carry
    /// its age (a call takes it off its remaining time). It may only shrink `msg`.
    fn age_safe(&self, msg: &mut Vec<u8>, waited: std::time::Duration) {
        let _ = (msg, waited);
    }
    /// Whether [`LinkHandler::age_safe`] may change `msg`: a link reads the clock when it
    /// queues only such messages (a stream of events to ten subscribers would otherwise read
    /// it ten times an event). A handler that implements `age_safe` implements this too:
    /// with the default, nothing is aged.
    fn ages(&self, msg: &[u8]) -> bool {
        let _ = msg;
        false
    }
    /// How a safe message of ours may be reordered against large ones queued before it (a
    /// command must not wait behind a camera frame): see [`Precedence`]. A link that sends
    /// large messages in parts sends an urgent message ahead of passable ones still waiting.
    fn precedence(&self, msg: &[u8]) -> Precedence {
        let _ = msg;
        Precedence::InOrder
    }
    /// Several messages from `from`, in order (a datagram's): a handler may take them as one
    /// batch.
    fn on_messages(&self, link: usize, from: PeerAddr, msgs: &[&[u8]]) {
        for m in msgs {
            self.on_message(link, from, m);
        }
    }
    /// A large safe message from `from`, in order, as a view of the shared-memory sample it
    /// arrived in: the handler may keep (slices of) it without a copy; the sample returns to
    /// its writer when the last is dropped.
    fn on_lent_message(&self, link: usize, from: PeerAddr, msg: bytes::Bytes) {
        self.on_message(link, from, &msg);
    }
    /// A discovery message (Hello, Heartbeat, Bye) from `from`.
    fn on_announce(&self, link: usize, from: PeerAddr, msg: &[u8]);
    /// `from` started a new safe session while one was running: it restarted or reset us.
    fn on_peer_reset(&self, link: usize, from: PeerAddr);
    /// `from` acknowledged a session of ours for the first time: it receives at that address
    /// ([`Link::answered`]).
    fn on_peer_answered(&self, link: usize, from: PeerAddr) {
        let _ = (link, from);
    }
    /// The link closed its session with `from`: it acknowledged nothing within the retry
    /// limit. What was in flight failed with [`LinkSendError::RetriesExhausted`].
    fn on_peer_unreachable(&self, link: usize, from: PeerAddr) {
        let _ = (link, from);
    }
}

/// Counters and gauges of a link (the node publishes them as `LinkHealth` totals).
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
pub struct LinkStats {
    /// Datagrams or frames sent.
    pub frames_out: u64,
    /// Datagrams or frames received.
    pub frames_in: u64,
    /// Bytes sent.
    pub bytes_out: u64,
    /// Bytes received.
    pub bytes_in: u64,
    /// Received frames dropped as corrupt.
    pub corrupt: u64,
    /// Safe messages retransmitted.
    pub retransmitted: u64,
    /// Duplicate safe messages dropped.
    pub duplicates: u64,
    /// Fast messages dropped because a queue was full.
    pub fast_dropped: u64,
    /// Smoothed round trip of safe messages in microseconds, the worst over the link's peers
    /// (0 before the first measurement).
    pub rtt_us: u64,
    /// Safe messages waiting to be sent or acknowledged now.
    pub safe_queued: u64,
    /// Fast messages waiting to be sent now.
    pub fast_queued: u64,
    /// Sessions with addresses no node was known at, closed unused (expired, or pushed out
    /// by newer ones).
    pub sessions_expired: u64,
    /// Sessions closed because the peer acknowledged nothing within the retry limit.
    pub sessions_given_up: u64,
    /// Safe messages ahead of a gap dropped because the sender's reorder buffer was full.
    pub reorder_dropped: u64,
    /// Received frames dropped because their seal did not verify (no key, another key,
    /// tampering); see [`auth`].
    pub auth_rejected: u64,
    /// Received frames dropped as replays (counter seen before or older than the window).
    pub replay_rejected: u64,
}

/// The counters of [`LinkStats`] as a link updates them from several tasks at once (the UDP and
/// shared-memory links'; the serial link keeps its own).
#[derive(Debug, Default)]
#[cfg_attr(not(any(feature = "udp", feature = "shm")), allow(dead_code))]
pub(crate) struct LinkCounters {
    pub(crate) frames_out: AtomicU64,
    pub(crate) frames_in: AtomicU64,
    pub(crate) bytes_out: AtomicU64,
    pub(crate) bytes_in: AtomicU64,
    pub(crate) corrupt: AtomicU64,
    pub(crate) retransmitted: AtomicU64,
    pub(crate) duplicates: AtomicU64,
    pub(crate) fast_dropped: AtomicU64,
    pub(crate) sessions_expired: AtomicU64,
    pub(crate) sessions_given_up: AtomicU64,
    pub(crate) reorder_dropped: AtomicU64,
    pub(crate) auth_rejected: AtomicU64,
    pub(crate) replay_rejected: AtomicU64,
}

#[cfg_attr(not(any(feature = "udp", feature = "shm")), allow(dead_code))]
impl LinkCounters {
    /// One frame (datagram, sample) of `bytes` sent.
    pub(crate) fn count_out(&self, bytes: usize) {
        self.frames_out.fetch_add(1, Ordering::Relaxed);
        self.bytes_out.fetch_add(bytes as u64, Ordering::Relaxed);
    }

    /// One frame of `bytes` received.
    pub(crate) fn count_in(&self, bytes: usize) {
        self.frames_in.fetch_add(1, Ordering::Relaxed);
        self.bytes_in.fetch_add(bytes as u64, Ordering::Relaxed);
    }

    /// One received frame dropped by [`auth::Opener::open`]; returns the new count of its
    /// kind (for [`auth::log_reject`]).
    pub(crate) fn count_reject(&self, why: auth::AuthReject) -> u64 {
        let c = if why.is_replay() {
            &self.replay_rejected
        } else {
            &self.auth_rejected
        };
        c.fetch_add(1, Ordering::Relaxed) + 1
    }

    /// The counters, with the gauges (round trip, queue depths) taken from `gauges`.
    pub(crate) fn stats(&self, gauges: LinkStats) -> LinkStats {
        LinkStats {
            frames_out: self.frames_out.load(Ordering::Relaxed),
            frames_in: self.frames_in.load(Ordering::Relaxed),
            bytes_out: self.bytes_out.load(Ordering::Relaxed),
            bytes_in: self.bytes_in.load(Ordering::Relaxed),
            corrupt: self.corrupt.load(Ordering::Relaxed),
            retransmitted: self.retransmitted.load(Ordering::Relaxed),
            duplicates: self.duplicates.load(Ordering::Relaxed),
            fast_dropped: self.fast_dropped.load(Ordering::Relaxed),
            sessions_expired: self.sessions_expired.load(Ordering::Relaxed),
            sessions_given_up: self.sessions_given_up.load(Ordering::Relaxed),
            reorder_dropped: self.reorder_dropped.load(Ordering::Relaxed),
            auth_rejected: self.auth_rejected.load(Ordering::Relaxed),
            replay_rejected: self.replay_rejected.load(Ordering::Relaxed),
            ..gauges
        }
    }
}

/// Content bytes per file chunk on links that do not say otherwise: a chunk and its headers fit
/// one Ethernet-sized datagram, and a serial link fragments it into a few packets.
pub const DEFAULT_FILE_CHUNK: usize = 1300;

/// A medium carrying node messages.
pub trait Link: Send + Sync + 'static {
    /// The link's name from network.xml.
    fn name(&self) -> &str;
    /// A human-readable local address.
    fn local_addr(&self) -> String;
    /// Queues `out` for `to`. Never blocks.
    fn send(&self, to: PeerAddr, out: Outgoing);
    /// Sends a discovery message to everyone reachable (multicast, point to point).
    fn announce(&self, msg: &[u8]);
    /// The node knows who is at `to` (its Hello arrived): the link keeps its session among
    /// the bound ones, which sessions with unknown addresses never push out. Links with one
    /// peer per medium (serial) or a bounded set of identities (shared memory) ignore it.
    fn confirm_peer(&self, to: PeerAddr) {
        let _ = to;
    }
    /// Whether the peer at `to` has shown that it receives there: on a medium where a source
    /// address can be forged (UDP), by acknowledging a session of ours, whose random number
    /// only our datagrams to that address carry; links with one peer per medium (serial) or a
    /// bounded set of identities (shared memory) say yes.
    fn answered(&self, to: PeerAddr) -> bool {
        let _ = to;
        true
    }
    /// Forgets a peer: its unacknowledged safe messages complete with
    /// [`LinkSendError::PeerClosed`]; a later message starts a fresh session. Keys set with
    /// [`Link::set_pair`] for it are forgotten too.
    fn close_peer(&self, to: PeerAddr);
    /// Seals data to and from `to` with `keys` (the keys this node and the peer there share
    /// once its proof verified) as soon as the peer shows it holds them too (a frame sealed
    /// with them arrives); from then on data from `to` sealed with the domain key is refused.
    /// The same keys again keep the pair's replay window; `None` goes back to the domain key.
    /// Links that do not seal per pair yet (serial, shared memory) ignore it.
    fn set_pair(&self, to: PeerAddr, keys: Option<Arc<crate::link::auth::PairKeys>>) {
        let _ = (to, keys);
    }
    /// Whether data to and from `to` is sealed with the keys of its pair now
    /// ([`Link::set_pair`], and the peer showed it holds them).
    fn pair_sealed(&self, to: PeerAddr) -> bool {
        let _ = to;
        false
    }
    /// Counters.
    fn stats(&self) -> LinkStats;
    /// Content bytes per chunk of a file sent to a peer reached directly on this link (one
    /// chunk and its headers should travel as one unit of the medium). A transfer through a
    /// gateway uses [`DEFAULT_FILE_CHUNK`], which every link carries.
    fn file_chunk(&self) -> usize {
        DEFAULT_FILE_CHUNK
    }
    /// Bytes of a lossless stream's events worth leaving unacknowledged towards a peer reached
    /// on this link, when the link is too slow for a stream's default window (`None`): a serial
    /// link answers a few seconds of its line, so a stream waits instead of queueing minutes
    /// of events behind a radio.
    fn stream_window_bytes(&self) -> Option<u64> {
        None
    }
    /// Lends a buffer of `len` bytes in which a safe message to `to` can be written in place
    /// and then sent with [`Link::send_loan`] without a copy (a shared-memory sample). `None`
    /// when this link has none to lend (the default): the message is then sent as any other.
    fn loan(&self, to: PeerAddr, len: usize) -> Option<Box<dyn LinkLoan>> {
        let _ = (to, len);
        None
    }
    /// Sends the safe message written into `loan`, which this link lent for `to`; like
    /// [`Link::send`] of [`Outgoing::Safe`] otherwise. A loan of another link or peer is
    /// refused (its completion fails).
    fn send_loan(&self, to: PeerAddr, loan: Box<dyn LinkLoan>, done: Option<SafeCompletion>) {
        drop(loan);
        refuse_done(done, to);
    }
}

/// A buffer lent for one message of a fixed length ([`Link::loan`]), written from its start:
/// appended to (each byte written once, nothing zeroed first), or made readable and writable
/// whole by [`LinkLoan::init`], which zeroes what was not written yet.
pub trait LinkLoan: Send {
    /// The message's length.
    fn len(&self) -> usize;
    /// Whether the message is empty.
    fn is_empty(&self) -> bool {
        self.len() == 0
    }
    /// Bytes written from the start so far.
    fn written(&self) -> usize;
    /// Writes as much of `bytes` as fits after what was written; returns how much.
    fn append(&mut self, bytes: &[u8]) -> usize;
    /// All the message's bytes, what was not written zeroed (once); everything counts as
    /// written afterwards.
    fn init(&mut self) -> &mut [u8];
    /// Back to the lending link's own type.
    fn into_any(self: Box<Self>) -> Box<dyn std::any::Any + Send>;
}

/// A [`LinkLoan`] on the heap: what a message is written into when no link lends a buffer.
pub(crate) struct HeapLoan {
    buf: Vec<u8>,
    len: usize,
}

impl HeapLoan {
    pub(crate) fn new(len: usize) -> Self {
        HeapLoan {
            buf: Vec::with_capacity(len),
            len,
        }
    }

    /// The message (zeroed where not written).
    pub(crate) fn into_vec(mut self) -> Vec<u8> {
        self.buf.resize(self.len, 0);
        self.buf
    }
}

impl LinkLoan for HeapLoan {
    fn len(&self) -> usize {
        self.len
    }
    fn written(&self) -> usize {
        self.buf.len()
    }
    fn append(&mut self, bytes: &[u8]) -> usize {
        let n = bytes.len().min(self.len - self.buf.len());
        self.buf.extend_from_slice(&bytes[..n]);
        n
    }
    fn init(&mut self) -> &mut [u8] {
        self.buf.resize(self.len, 0);
        &mut self.buf
    }
    fn into_any(self: Box<Self>) -> Box<dyn std::any::Any + Send> {
        self
    }
}
