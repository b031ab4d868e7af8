//! The shared-memory link: nodes on one host exchange node messages through iceoryx2, without
//! sockets on the data path.
//!
//! Each link owns an **inbox** made of four iceoryx2 services named after its random id:
//! `marea/<service>/<id>/fast` (publish-subscribe, safe overflow: a reader that stops reading
//! loses its oldest fast messages, the writer never waits), `.../safe` (publish-subscribe
//! without overflow: a full buffer refuses the sample, so the writer keeps it and retries),
//! `.../bulk` (like `safe`, with samples of up to [`BULK_MAX`] for large messages) and
//! `.../wake` (an event the receiver waits on; its attribute `marea.wait` says how). Peers open
//! a publisher on each and a notifier.
//!
//! - **Discovery without multicast**: the iceoryx2 node is named `marea/<service>/<id>`; listing
//!   the host's iceoryx2 nodes finds every inbox of the same `service`. A link connects to them
//!   all when it opens (so its Hello reaches them at once) and rescans every `scan` period, which
//!   also removes the stale resources of nodes whose process died (SIGKILL).
//! - **Fast** messages are written straight into the peer's fast buffer (newest wins on
//!   overflow).
//! - **Safe** messages carry a session and a sequence number; the receiver acknowledges
//!   cumulatively after each pass over its inbox, and an acknowledgement both completes `done`
//!   and tells the writer that buffer space is free again. A reader that stops reading
//!   therefore holds back only safe traffic towards itself.
//! - **Large** messages (over [`FRAME_MAX`]; fast ones ride the safe path) go in pieces of up to
//!   [`BULK_MAX`] into the bulk inbox, each followed by a small `Bulk` frame in the safe inbox
//!   that keeps it in order. A writer opens a peer's bulk inbox with its first large message:
//!   iceoryx2 gives every chunk of a publisher the size of its largest sample and zeroes the
//!   whole segment when it creates it, so small and large samples live in separate segments,
//!   and peers that never send anything large never pay for the large one.
//!
//! Waiting (`wait` in [`ShmLinkOptions`]): by default the receiver sleeps until a writer
//! notifies the wake event (iceoryx2 sends one datagram per wake-up; further notifications
//! before the reader wakes cost an atomic operation). The socket is watched by tokio's reactor,
//! so the pass over the inbox runs on the tokio worker that woke, the same one the delivered
//! message then wakes: one thread switch per message, as in plain iceoryx2. With
//! [`ShmWait::Spin`] a dedicated thread polls the inbox and writers never notify.
//!
//! Threads: sending is inline in the caller (a loan, a copy, an atomic store and maybe the
//! notification: iceoryx2's non-blocking calls); receiving never blocks. Everything that may
//! wait on the file system (opening services, listing nodes, cleaning up dead ones) runs on one
//! control thread per link, never on a tokio worker.
//!
//! Payloads are copied once into the loaned shared-memory sample and read in place by the
//! receiver (a message that fits one frame or bulk sample reaches the node as a slice of shared
//! memory).

use std::collections::{HashMap, HashSet, VecDeque};
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{mpsc, Arc, Mutex};
use std::time::{Duration, Instant};

use iceoryx2::node::{Node as IoxNode, NodeBuilder, NodeState, NodeView};
use iceoryx2::port::listener::Listener;
use iceoryx2::port::notifier::Notifier;
use iceoryx2::port::publisher::Publisher;
use iceoryx2::port::subscriber::Subscriber;
use iceoryx2::prelude::{
    ipc_threadsafe, AllocationStrategy, AttributeSpecifier, BackpressureStrategy,
    CallbackProgression, LogLevel, NodeName, ServiceName, SignalHandlingMode,
};
use iceoryx2::service::attribute::{AttributeKey, AttributeValue};
use iceoryx2::service::port_factory::PortFactory;
use tokio_util::sync::CancellationToken;
use tokio_util::task::TaskTracker;

use super::{Link, LinkHandler, LinkSendError, LinkStats, Outgoing, PeerAddr, SafeCompletion};

type Ipc = ipc_threadsafe::Service;
type Pub = Publisher<Ipc, [u8], ()>;
type Sub = Subscriber<Ipc, [u8], ()>;

/// Largest sample written to the fast and safe inboxes, header included. Longer messages go
/// through the bulk inbox (fast ones riding the safe path).
pub const FRAME_MAX: usize = 8192;
/// Largest sample written to a bulk inbox, header included; longer messages are cut into pieces
/// of this size.
pub const BULK_MAX: usize = 256 << 10;
/// Content bytes of a file chunk sent to a peer on this link: one chunk, its message header and
/// the frame header fit one bulk sample.
pub const FILE_CHUNK: usize = BULK_MAX - 1024;
/// Frames a safe inbox buffers per writer before refusing more.
const SAFE_BUFFER: usize = 128;
/// Samples a bulk inbox buffers per writer before refusing more. With [`BULK_MAX`] this bounds a
/// writer's bulk segment to a few MiB, created only once it first sends something large.
const BULK_BUFFER: usize = 8;
/// Frames a fast inbox buffers per writer before overwriting the oldest.
const FAST_BUFFER: usize = 64;
/// Most peers (same-host links of the same `service`) one inbox accepts.
const MAX_PEERS: usize = 64;
/// Fast messages kept for a peer whose inbox is not open yet, or large fast messages queued on
/// the safe path; beyond it the oldest is dropped.
const MAX_FAST_BACKLOG: usize = 1024;
/// A reassembled message larger than this is dropped as corrupt.
const MAX_MESSAGE: usize = 256 << 20;
/// How often the receive thread retries refused frames and acknowledgements.
const RETRY: Duration = Duration::from_millis(1);
/// Samples taken from one inbox buffer per pass, so acknowledgements flow during bursts.
const PASS_BUDGET: usize = 512;
/// Fast samples taken per pass. Between passes the tasks the pass woke on this worker run: a
/// subscriber would otherwise find most of its variables' values replaced by newer ones when it
/// finally runs (one variable value per sample: about a UDP datagram's worth).
const FAST_PASS_BUDGET: usize = 16;
/// Bulk bytes delivered per pass: a pass runs on a tokio worker, which it should not hold for
/// long copying large messages out.
const PASS_BULK_BYTES: usize = 4 << 20;
/// `wait="spin"`: after the last frame, poll without pause (yielding the processor between
/// passes) for this long, ...
const YIELD_UNTIL: Duration = Duration::from_millis(10);
/// ... then poll once per this period (a sleep on the wake event) until the next frame.
const PARK: Duration = Duration::from_millis(1);
/// How often the receiver asks again to open the inbox of a peer it must acknowledge.
const REOPEN: Duration = Duration::from_millis(100);
/// The wake event's attribute telling writers how the inbox's reader waits.
const WAIT_ATTRIBUTE: &str = "marea.wait";

/// How a link's receive thread waits for frames (`wait` on `<shm>`).
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub enum ShmWait {
    /// Sleep on the inbox's wake event (watched by tokio's reactor): idle costs nothing, and
    /// a writer notifies a sleeping reader (one datagram; an atomic operation while the reader
    /// has not woken yet).
    #[default]
    Event,
    /// Busy-poll the inbox from a thread of its own: writers never notify, so sending is a
    /// loan, a copy and an atomic store. While frames flow the thread polls without pause,
    /// yielding the processor between polls (so on a busy host the node's own tasks still
    /// run); after 10 ms without a frame it polls once per millisecond, so a message reaching an
    /// idle inbox may wait up to 1 ms. It keeps a core busy while traffic flows.
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

/// How the shared-memory link is set up (taken from `<shm>` in network.xml).
#[derive(Debug, Clone)]
pub struct ShmLinkOptions {
    /// Link name.
    pub name: String,
    /// Service-name prefix: links with the same prefix on this host find each other.
    pub service: String,
    /// Period of the scan for new and dead same-host nodes.
    pub scan: Duration,
    /// How the receive thread waits for frames.
    pub wait: ShmWait,
}

/// Why the shared-memory link could not be opened.
#[derive(Debug, thiserror::Error)]
pub enum ShmLinkOpenError {
    /// The iceoryx2 node could not be created.
    #[error("link {link}: cannot create the iceoryx2 node: {reason}")]
    Node {
        /// Link name.
        link: String,
        /// What iceoryx2 said.
        reason: String,
    },
    /// An inbox service or port could not be created.
    #[error("link {link}: cannot create the shared-memory inbox {what}: {reason}")]
    Inbox {
        /// Link name.
        link: String,
        /// Which service or port.
        what: String,
        /// What iceoryx2 said.
        reason: String,
    },
    /// The receive thread could not be started.
    #[error("link {link}: cannot start the receive thread: {source}")]
    Thread {
        /// Link name.
        link: String,
        /// The OS error.
        source: std::io::Error,
    },
    /// The setup task ended without a result (the runtime is shutting down).
    #[error("link {link}: setup interrupted")]
    Interrupted {
        /// Link name.
        link: String,
    },
}

/// The frames written into an inbox; every frame starts with its kind and its sender's id.
///
/// ```text
///  0      1                    9          13                   21
///  +------+--------------------+----------+--------------------+------------+
///  | kind | sender id (u64 LE) | session  | seq (u64 LE)       | body ...   |  Safe, SafeMore
///  +------+--------------------+----------+--------------------+------------+
///  | kind | sender id (u64 LE) | session  | seq (u64 LE)       |               Ack (cumulative),
///  +------+--------------------+----------+--------------------+               Bulk, BulkMore
///  | kind | sender id (u64 LE) | session  | seq (u64 LE)       | body ...   |  BulkData
///  +------+--------------------+----------+--------------------+------------+
///  | kind | sender id (u64 LE) | body ...                      |               Announce, Fast
///  +------+--------------------+-------------------------------+
/// ```
/// `SafeMore` is a fragment followed by more fragments of the same message; `Safe` ends one.
/// `Bulk` and `BulkMore` are the same in the safe inbox for a fragment whose body travels in the
/// bulk inbox as the `BulkData` sample with the same sender, session and sequence number,
/// written just before them.
mod frame {
    pub const ANNOUNCE: u8 = 1;
    pub const FAST: u8 = 2;
    pub const SAFE: u8 = 3;
    pub const SAFE_MORE: u8 = 4;
    pub const ACK: u8 = 5;
    pub const BULK: u8 = 6;
    pub const BULK_MORE: u8 = 7;
    pub const BULK_DATA: u8 = 8;
    /// Kind and sender.
    pub const BASE: usize = 9;
    /// Kind, sender, session and sequence number.
    pub const SEQUENCED: usize = 21;

    /// A parsed frame.
    #[derive(Debug, PartialEq, Eq)]
    pub enum Frame<'a> {
        Announce(&'a [u8]),
        Fast(&'a [u8]),
        Safe {
            session: u32,
            seq: u64,
            more: bool,
            body: &'a [u8],
        },
        Ack {
            session: u32,
            seq: u64,
        },
        /// A fragment whose body is in the bulk inbox.
        Bulk {
            session: u32,
            seq: u64,
            more: bool,
        },
        /// The body of a `Bulk` fragment.
        BulkData {
            session: u32,
            seq: u64,
            body: &'a [u8],
        },
    }

    /// Why a frame was dropped.
    #[derive(Debug, PartialEq, Eq, thiserror::Error)]
    pub enum FrameDecodeError {
        /// Shorter than its kind's header.
        #[error("frame of {0} bytes is truncated")]
        Truncated(usize),
        /// Unknown kind byte.
        #[error("unknown frame kind {0}")]
        UnknownKind(u8),
    }

    /// Writes the header of a frame into `out` (which must hold [`header_len`] bytes).
    pub fn write_header(out: &mut [u8], kind: u8, sender: u64, session: u32, seq: u64) {
        out[0] = kind;
        out[1..9].copy_from_slice(&sender.to_le_bytes());
        if header_len(kind) == SEQUENCED {
            out[9..13].copy_from_slice(&session.to_le_bytes());
            out[13..21].copy_from_slice(&seq.to_le_bytes());
        }
    }

    /// Header length of a frame kind.
    pub fn header_len(kind: u8) -> usize {
        match kind {
            SAFE | SAFE_MORE | ACK | BULK | BULK_MORE | BULK_DATA => SEQUENCED,
            _ => BASE,
        }
    }

    /// Splits a frame into its sender and contents.
    pub fn parse(b: &[u8]) -> Result<(u64, Frame<'_>), FrameDecodeError> {
        if b.len() < BASE {
            return Err(FrameDecodeError::Truncated(b.len()));
        }
        let mut id = [0u8; 8];
        id.copy_from_slice(&b[1..9]);
        let sender = u64::from_le_bytes(id);
        let kind = b[0];
        let sequenced = || {
            if b.len() < SEQUENCED {
                return Err(FrameDecodeError::Truncated(b.len()));
            }
            let mut s = [0u8; 4];
            s.copy_from_slice(&b[9..13]);
            let mut q = [0u8; 8];
            q.copy_from_slice(&b[13..21]);
            Ok((u32::from_le_bytes(s), u64::from_le_bytes(q)))
        };
        let f = match kind {
            ANNOUNCE => Frame::Announce(&b[BASE..]),
            FAST => Frame::Fast(&b[BASE..]),
            SAFE | SAFE_MORE => {
                let (session, seq) = sequenced()?;
                Frame::Safe {
                    session,
                    seq,
                    more: kind == SAFE_MORE,
                    body: &b[SEQUENCED..],
                }
            }
            ACK => {
                let (session, seq) = sequenced()?;
                Frame::Ack { session, seq }
            }
            BULK | BULK_MORE => {
                let (session, seq) = sequenced()?;
                Frame::Bulk {
                    session,
                    seq,
                    more: kind == BULK_MORE,
                }
            }
            BULK_DATA => {
                let (session, seq) = sequenced()?;
                Frame::BulkData {
                    session,
                    seq,
                    body: &b[SEQUENCED..],
                }
            }
            k => return Err(FrameDecodeError::UnknownKind(k)),
        };
        Ok((sender, f))
    }
}

/// The writing side of a peer's inbox.
struct Conn {
    fast: Pub,
    safe: Pub,
    wake: Notifier<Ipc>,
    /// The peer busy-polls its inbox (`wait="spin"`): never notify it.
    spins: bool,
}

impl Conn {
    /// Wakes the peer's receive thread if it sleeps on its wake event. An error means the peer
    /// is gone, which the scan and the node's lease notice.
    fn wake(&self) {
        if !self.spins {
            let _ = self.wake.notify();
        }
    }
}

/// The writing side of a peer's bulk inbox, opened when the first large message is sent (its
/// shared-memory segment is several MiB, so peers that only exchange small messages never pay
/// for it).
enum Bulk {
    Closed,
    /// The receive thread was asked to open it.
    Opening,
    Open(Pub),
    /// Opening failed: large messages are fragmented into the safe inbox instead.
    Unavailable,
}

/// A safe message not yet wholly written into the peer's inbox.
struct Pending {
    msg: Vec<u8>,
    /// Bytes already written (fragments accepted by the inbox).
    sent: usize,
    done: Option<SafeCompletion>,
    /// A large fast message riding the safe path (dropped first when the backlog is long).
    fast: bool,
    /// The body of the fragment at `sent` is in the bulk inbox; its `Bulk` frame is not yet.
    bulk_written: bool,
}

impl Pending {
    fn new(msg: Vec<u8>, done: Option<SafeCompletion>, fast: bool) -> Self {
        Pending {
            msg,
            sent: 0,
            done,
            fast,
            bulk_written: false,
        }
    }
}

/// What this link sends to one peer.
struct PeerTx {
    /// The peer's shared-memory identity.
    id: u64,
    conn: Option<Conn>,
    bulk: Bulk,
    session: u32,
    next_seq: u64,
    /// Fast messages waiting for the inbox to be opened.
    fast_backlog: VecDeque<(Option<u32>, Vec<u8>)>,
    safe_backlog: VecDeque<Pending>,
    /// Written, waiting for the peer's acknowledgement.
    unacked: VecDeque<(u64, SafeCompletion)>,
    /// The inbox refused a frame: wait for an acknowledgement (or the retry timer).
    blocked: bool,
}

impl PeerTx {
    fn new(id: u64) -> Self {
        PeerTx {
            id,
            conn: None,
            bulk: Bulk::Closed,
            session: rand::random(),
            next_seq: 0,
            fast_backlog: VecDeque::new(),
            safe_backlog: VecDeque::new(),
            unacked: VecDeque::new(),
            blocked: false,
        }
    }

    fn fail_all(&mut self, err: &LinkSendError) {
        for p in self.safe_backlog.drain(..) {
            if let Some(d) = p.done {
                let _ = d.send(Err(err.clone()));
            }
        }
        for (_, d) in self.unacked.drain(..) {
            let _ = d.send(Err(err.clone()));
        }
    }
}

/// What the receive thread knows of one sender's safe stream.
struct RxState {
    session: u32,
    expected: u64,
    /// Fragments of the message being reassembled.
    partial: Vec<u8>,
    /// Highest sequence number delivered and not yet acknowledged.
    ack: Option<u64>,
    /// A fragment of the message being reassembled went missing: drop the message at its end.
    torn: bool,
}

impl RxState {
    fn new(session: u32, expected: u64) -> Self {
        RxState {
            session,
            expected,
            partial: Vec::new(),
            ack: None,
            torn: false,
        }
    }
}

/// Requests to the receive thread.
enum Ctl {
    /// Open the inbox of this peer.
    Open(u64),
    /// Open the bulk inbox of this peer.
    OpenBulk(u64),
    /// The link shuts down.
    Stop,
}

#[derive(Default)]
struct Counters {
    frames_out: AtomicU64,
    frames_in: AtomicU64,
    bytes_out: AtomicU64,
    bytes_in: AtomicU64,
    corrupt: AtomicU64,
    retransmitted: AtomicU64,
    duplicates: AtomicU64,
    fast_dropped: AtomicU64,
}

/// The shared-memory link.
pub struct ShmLink {
    index: usize,
    options: ShmLinkOptions,
    id: u64,
    peers: Mutex<HashMap<u64, Arc<Mutex<PeerTx>>>>,
    /// Requests to the control thread.
    ctl: Mutex<mpsc::Sender<Ctl>>,
    /// Peers whose receive state the receiver must forget (they were closed), taken at the
    /// start of its next pass, before any later frame of theirs.
    forget: Mutex<mpsc::Sender<u64>>,
    /// Wakes our own receive thread (control requests, shutdown).
    self_wake: Notifier<Ipc>,
    stop: AtomicBool,
    handler: Arc<dyn LinkHandler>,
    counters: Counters,
}

use crate::sync::lock;

fn node_prefix(service: &str) -> String {
    format!("marea/{service}/")
}

fn inbox_name(service: &str, id: u64, part: &str) -> String {
    format!("marea/{service}/{id:016x}/{part}")
}

/// The receiving side, created before the link and moved into its thread.
struct Inbox {
    node: IoxNode<Ipc>,
    safe: Sub,
    fast: Sub,
    bulk: Sub,
    listener: Listener<Ipc>,
    self_wake: Notifier<Ipc>,
}

fn service_name(s: &str) -> Result<ServiceName, String> {
    ServiceName::new(s).map_err(|e| format!("invalid service name {s}: {e:?}"))
}

impl Inbox {
    fn create(options: &ShmLinkOptions, id: u64) -> Result<Inbox, ShmLinkOpenError> {
        // iceoryx2 logs to stderr; keep it to errors unless the user asks for more.
        iceoryx2::prelude::set_log_level_from_env_or(LogLevel::Error);
        let link = options.name.clone();
        let node_err = |reason: String| ShmLinkOpenError::Node {
            link: link.clone(),
            reason,
        };
        let name = NodeName::new(&format!("{}{id:016x}", node_prefix(&options.service)))
            .map_err(|e| node_err(format!("{e:?}")))?;
        let node = NodeBuilder::new()
            .name(&name)
            // The process owns its signals (tokio's ctrl_c); iceoryx2 must not take them.
            .signal_handling_mode(SignalHandlingMode::Disabled)
            .create::<Ipc>()
            .map_err(|e| node_err(format!("{e:?}")))?;
        // A process killed earlier may have left services behind: remove them before anything
        // reads them.
        let cleaned = node.try_cleanup_dead_nodes();
        if cleaned.cleanups > 0 {
            tracing::info!(link = %options.name, dead = cleaned.cleanups, "removed resources of dead shared-memory nodes");
        }
        let inbox_err = |what: &str, reason: String| ShmLinkOpenError::Inbox {
            link: options.name.clone(),
            what: what.to_owned(),
            reason,
        };
        let svc = &options.service;
        let open_pubsub = |part: &str, overflow: bool, buffer: usize| {
            let n = service_name(&inbox_name(svc, id, part)).map_err(|e| inbox_err(part, e))?;
            // The service only records its settings; the memory is the writers', allocated
            // when each opens a publisher.
            let s = pubsub_builder(&node, &n, overflow, buffer)
                .create()
                .map_err(|e| inbox_err(part, format!("{e:?}")))?;
            s.subscriber_builder()
                .buffer_size(buffer)
                .create()
                .map_err(|e| inbox_err(part, format!("{e:?}")))
        };
        let safe = open_pubsub("safe", false, SAFE_BUFFER)?;
        let fast = open_pubsub("fast", true, FAST_BUFFER)?;
        let bulk = open_pubsub("bulk", false, BULK_BUFFER)?;
        let wn = service_name(&inbox_name(svc, id, "wake")).map_err(|e| inbox_err("wake", e))?;
        // Writers read how this inbox's reader waits from the wake event's attributes.
        let attributes =
            wait_attribute(options.wait).map_err(|e| inbox_err("wake attribute", e))?;
        let wake = event_builder(&node, &wn)
            .create_with_attributes(&attributes)
            .map_err(|e| inbox_err("wake", format!("{e:?}")))?;
        let listener = wake
            .listener_builder()
            .create()
            .map_err(|e| inbox_err("wake listener", format!("{e:?}")))?;
        let self_wake = wake
            .notifier_builder()
            .create()
            .map_err(|e| inbox_err("wake notifier", format!("{e:?}")))?;
        Ok(Inbox {
            node,
            safe,
            fast,
            bulk,
            listener,
            self_wake,
        })
    }
}

fn pubsub_builder<'a>(
    node: &'a IoxNode<Ipc>,
    name: &'a ServiceName,
    overflow: bool,
    buffer: usize,
) -> iceoryx2::service::builder::publish_subscribe::Builder<[u8], (), Ipc> {
    node.service_builder(name)
        .publish_subscribe::<[u8]>()
        .enable_safe_overflow(overflow)
        .subscriber_max_buffer_size(buffer)
        .history_size(0)
        .max_subscribers(1)
        .max_publishers(MAX_PEERS + 1)
        .max_nodes(MAX_PEERS + 1)
}

fn wait_key() -> Result<AttributeKey, String> {
    AttributeKey::try_from(WAIT_ATTRIBUTE).map_err(|e| format!("{e:?}"))
}

fn wait_attribute(wait: ShmWait) -> Result<AttributeSpecifier, String> {
    let value = AttributeValue::try_from(wait.as_str()).map_err(|e| format!("{e:?}"))?;
    AttributeSpecifier::new()
        .define(&wait_key()?, &value)
        .map_err(|e| format!("{e:?}"))
}

fn event_builder<'a>(
    node: &'a IoxNode<Ipc>,
    name: &'a ServiceName,
) -> iceoryx2::service::builder::event::Builder<Ipc> {
    node.service_builder(name)
        .event()
        .max_listeners(1)
        .max_notifiers(MAX_PEERS + 2)
        .max_nodes(MAX_PEERS + 1)
}

/// Opens a publisher on part `part` of peer `id`'s inbox, its samples up to `max` bytes.
fn open_pub(
    node: &IoxNode<Ipc>,
    service: &str,
    id: u64,
    (part, overflow, buffer, max): (&str, bool, usize, usize),
) -> Result<Pub, String> {
    let n = service_name(&inbox_name(service, id, part))?;
    let s = pubsub_builder(node, &n, overflow, buffer)
        .open()
        .map_err(|e| format!("{part}: {e:?}"))?;
    s.publisher_builder()
        .initial_max_slice_len(max)
        .allocation_strategy(AllocationStrategy::Static)
        .max_loaned_samples(2)
        .backpressure_strategy(BackpressureStrategy::DiscardData)
        .create()
        .map_err(|e| format!("{part} publisher: {e:?}"))
}

/// Opens the writing side of peer `id`'s inbox (it must exist).
fn open_conn(node: &IoxNode<Ipc>, service: &str, id: u64) -> Result<Conn, String> {
    let safe = open_pub(node, service, id, ("safe", false, SAFE_BUFFER, FRAME_MAX))?;
    let fast = open_pub(node, service, id, ("fast", true, FAST_BUFFER, FRAME_MAX))?;
    let wn = service_name(&inbox_name(service, id, "wake"))?;
    let wake = event_builder(node, &wn)
        .open()
        .map_err(|e| format!("wake: {e:?}"))?;
    // An inbox without the attribute (or with a mode we do not know) is woken on every send.
    let spins = wake
        .attributes()
        .key_value(&wait_key()?, 0)
        .is_some_and(|v| v == ShmWait::Spin.as_str());
    let wake = wake
        .notifier_builder()
        .create()
        .map_err(|e| format!("wake notifier: {e:?}"))?;
    Ok(Conn {
        fast,
        safe,
        wake,
        spins,
    })
}

/// Writes one frame into `publisher`. Returns whether the inbox took it (a non-overflowing
/// inbox refuses frames while its buffer is full).
fn put(publisher: &Pub, kind: u8, sender: u64, session: u32, seq: u64, body: &[u8]) -> bool {
    let h = frame::header_len(kind);
    let Ok(mut sample) = publisher.loan_slice(h + body.len()) else {
        return false;
    };
    let out = sample.payload_mut();
    frame::write_header(out, kind, sender, session, seq);
    out[h..].copy_from_slice(body);
    matches!(sample.send(), Ok(n) if n > 0)
}

impl ShmLink {
    /// Creates this link's inbox, connects to the inboxes of the same-host nodes already there
    /// and starts the receive thread, which stops on `cancel` (a task on `tasks` waits for it).
    ///
    /// # Errors
    /// [`ShmLinkOpenError`] when iceoryx2 cannot create the node or the inbox.
    pub async fn open(
        index: usize,
        options: ShmLinkOptions,
        handler: Arc<dyn LinkHandler>,
        tasks: &TaskTracker,
        cancel: CancellationToken,
    ) -> Result<Arc<Self>, ShmLinkOpenError> {
        let id: u64 = rand::random();
        let opts = options.clone();
        // Creating files and shared memory may wait on the file system: off the workers.
        let inbox = tokio::task::spawn_blocking(move || Inbox::create(&opts, id))
            .await
            .map_err(|_| ShmLinkOpenError::Interrupted {
                link: options.name.clone(),
            })??;
        let Inbox {
            node,
            safe,
            fast,
            bulk,
            listener,
            self_wake,
        } = inbox;
        let (ctl_tx, ctl_rx) = mpsc::channel();
        let (forget_tx, forget_rx) = mpsc::channel();
        let wait = options.wait;
        let link = Arc::new(ShmLink {
            index,
            options,
            id,
            peers: Mutex::new(HashMap::new()),
            ctl: Mutex::new(ctl_tx),
            forget: Mutex::new(forget_tx),
            self_wake,
            stop: AtomicBool::new(false),
            handler,
            counters: Counters::default(),
        });
        let name = link.options.name.clone();
        let thread_err = |source| ShmLinkOpenError::Thread {
            link: name.clone(),
            source,
        };
        let mut control = Control {
            link: link.clone(),
            node,
            ctl: ctl_rx,
            next_scan: Instant::now(),
        };
        // Connect to the nodes already here before the node announces itself.
        control = tokio::task::spawn_blocking(move || {
            control.scan();
            control
        })
        .await
        .map_err(|_| ShmLinkOpenError::Interrupted { link: name.clone() })?;
        let (control_tx, control_rx) = tokio::sync::oneshot::channel::<()>();
        std::thread::Builder::new()
            .name(format!("marea-shm-ctl-{name}"))
            .spawn(move || {
                control.run();
                drop(control_tx);
            })
            .map_err(thread_err)?;
        let rx = Receiver {
            link: link.clone(),
            safe,
            fast,
            bulk,
            stash: HashMap::new(),
            forget: forget_rx,
            rx: HashMap::new(),
            ack_due: HashSet::new(),
            open_requested: HashMap::new(),
            next_retry: Instant::now(),
            pass_bulk_bytes: 0,
            backlog: false,
        };
        let (receiver_tx, receiver_rx) = tokio::sync::oneshot::channel::<()>();
        match wait {
            ShmWait::Event => {
                // Readiness of the wake event's socket, seen by tokio's reactor: the receive
                // pass then runs on the worker that woke, which is also the one the delivered
                // message wakes next (one thread switch per message, as in plain iceoryx2).
                let fd = WakeFd::watch(listener).map_err(thread_err)?;
                let cancel = cancel.clone();
                tasks.spawn(async move {
                    rx.drive_events(fd, cancel).await;
                    drop(receiver_tx);
                });
            }
            ShmWait::Spin => {
                // A task that polls and yields, so the worker running it never parks: waking
                // the task a message is for is a push onto a run queue, not a thread wake-up.
                drop(listener);
                let cancel = cancel.clone();
                tasks.spawn(async move {
                    rx.drive_polling(cancel).await;
                    drop(receiver_tx);
                });
            }
        }
        let l = link.clone();
        tasks.spawn(async move {
            cancel.cancelled().await;
            l.stop.store(true, Ordering::SeqCst);
            l.wake_self();
            l.request(Ctl::Stop);
            let _ = receiver_rx.await;
            let _ = control_rx.await;
            let peers: Vec<Arc<Mutex<PeerTx>>> = lock(&l.peers).drain().map(|(_, p)| p).collect();
            for p in peers {
                lock(&p).fail_all(&LinkSendError::Shutdown);
            }
        });
        Ok(link)
    }

    /// This link's shared-memory identity (what peers see as [`PeerAddr::Shm`]).
    pub fn id(&self) -> u64 {
        self.id
    }

    fn wake_self(&self) {
        let _ = self.self_wake.notify();
    }

    fn request(&self, c: Ctl) {
        let _ = lock(&self.ctl).send(c);
    }

    fn peer(&self, id: u64, create: bool) -> Option<Arc<Mutex<PeerTx>>> {
        let mut peers = lock(&self.peers);
        if let Some(p) = peers.get(&id) {
            return Some(p.clone());
        }
        if !create || peers.len() >= MAX_PEERS || id == self.id {
            return None;
        }
        let p = Arc::new(Mutex::new(PeerTx::new(id)));
        peers.insert(id, p.clone());
        Some(p)
    }

    fn count_out(&self, n: usize) {
        self.counters.frames_out.fetch_add(1, Ordering::Relaxed);
        self.counters
            .bytes_out
            .fetch_add(n as u64, Ordering::Relaxed);
    }

    /// Writes as much of the safe backlog as the peer's inbox takes. Returns whether anything
    /// was written (the peer then needs waking).
    ///
    /// A fragment longer than a safe frame carries its body in the bulk inbox: the body first
    /// (a `BulkData` sample), then its `Bulk` frame in the safe inbox, so the reader, meeting
    /// the frame in order, finds the body already there.
    fn flush_safe(&self, st: &mut PeerTx) -> bool {
        let PeerTx {
            id,
            conn,
            bulk,
            session,
            next_seq,
            safe_backlog,
            unacked,
            blocked,
            ..
        } = st;
        let Some(conn) = conn.as_ref() else {
            return false;
        };
        let inline_max = FRAME_MAX - frame::SEQUENCED;
        let bulk_max = BULK_MAX - frame::SEQUENCED;
        let mut wrote = false;
        while let Some(p) = safe_backlog.front_mut() {
            let left = p.msg.len() - p.sent;
            let bulk_pub = if left > inline_max {
                match bulk {
                    Bulk::Open(b) => Some(&*b),
                    Bulk::Unavailable => None,
                    Bulk::Opening => break,
                    Bulk::Closed => {
                        *bulk = Bulk::Opening;
                        self.request(Ctl::OpenBulk(*id));
                        break;
                    }
                }
            } else {
                None
            };
            let n = left.min(if bulk_pub.is_some() {
                bulk_max
            } else {
                inline_max
            });
            let more = p.sent + n < p.msg.len();
            let body = &p.msg[p.sent..p.sent + n];
            let written = match bulk_pub {
                Some(b) => {
                    if !p.bulk_written {
                        if !put(b, frame::BULK_DATA, self.id, *session, *next_seq, body) {
                            *blocked = true;
                            self.counters.retransmitted.fetch_add(1, Ordering::Relaxed);
                            break;
                        }
                        self.count_out(frame::SEQUENCED + n);
                        p.bulk_written = true;
                    }
                    let kind = if more { frame::BULK_MORE } else { frame::BULK };
                    put(&conn.safe, kind, self.id, *session, *next_seq, &[])
                        .then_some(frame::SEQUENCED)
                }
                None => {
                    let kind = if more { frame::SAFE_MORE } else { frame::SAFE };
                    put(&conn.safe, kind, self.id, *session, *next_seq, body)
                        .then_some(frame::SEQUENCED + n)
                }
            };
            let Some(bytes) = written else {
                *blocked = true;
                self.counters.retransmitted.fetch_add(1, Ordering::Relaxed);
                break;
            };
            self.count_out(bytes);
            wrote = true;
            p.sent += n;
            p.bulk_written = false;
            if !more {
                if let Some(done) = p.done.take() {
                    unacked.push_back((*next_seq, done));
                }
                safe_backlog.pop_front();
            }
            *next_seq += 1;
        }
        wrote
    }

    /// Writes what waited for the inbox to open, then wakes the peer.
    fn flush_opened(&self, st: &mut PeerTx) {
        let Some(conn) = st.conn.as_ref() else {
            return;
        };
        let mut wrote = false;
        for (_, msg) in std::mem::take(&mut st.fast_backlog) {
            if msg.len() + frame::BASE <= FRAME_MAX {
                if put(&conn.fast, frame::FAST, self.id, 0, 0, &msg) {
                    self.count_out(frame::BASE + msg.len());
                    wrote = true;
                }
            } else {
                st.safe_backlog.push_back(Pending::new(msg, None, true));
            }
        }
        st.blocked = false;
        wrote |= self.flush_safe(st);
        if wrote {
            self.notify(st);
        }
    }

    fn notify(&self, st: &PeerTx) {
        if let Some(c) = &st.conn {
            c.wake();
        }
    }

    fn fast_send(&self, st: &mut PeerTx, coalesce: Option<u32>, msg: Vec<u8>) {
        if st.conn.is_none() {
            let slot =
                coalesce.and_then(|k| st.fast_backlog.iter_mut().find(|(c, _)| *c == Some(k)));
            if let Some(slot) = slot {
                slot.1 = msg;
            } else {
                if st.fast_backlog.len() >= MAX_FAST_BACKLOG {
                    st.fast_backlog.pop_front();
                    self.counters.fast_dropped.fetch_add(1, Ordering::Relaxed);
                }
                st.fast_backlog.push_back((coalesce, msg));
            }
            return;
        }
        if msg.len() + frame::BASE <= FRAME_MAX {
            let ok = st
                .conn
                .as_ref()
                .is_some_and(|c| put(&c.fast, frame::FAST, self.id, 0, 0, &msg));
            if ok {
                self.count_out(frame::BASE + msg.len());
                self.notify(st);
            } else {
                self.counters.fast_dropped.fetch_add(1, Ordering::Relaxed);
            }
            return;
        }
        // Too large for one frame: ride the safe path, unless the reader is far behind.
        let queued_fast = st.safe_backlog.iter().filter(|p| p.fast).count();
        if queued_fast >= MAX_FAST_BACKLOG {
            self.counters.fast_dropped.fetch_add(1, Ordering::Relaxed);
            return;
        }
        st.safe_backlog.push_back(Pending::new(msg, None, true));
        if !st.blocked && self.flush_safe(st) {
            self.notify(st);
        }
    }
}

impl Link for ShmLink {
    fn name(&self) -> &str {
        &self.options.name
    }

    fn local_addr(&self) -> String {
        format!("shm://{}/{:016x}", self.options.service, self.id)
    }

    fn send(&self, to: PeerAddr, out: Outgoing) {
        let PeerAddr::Shm(id) = to else {
            if let Outgoing::Safe { done: Some(d), .. } = out {
                let _ = d.send(Err(LinkSendError::PeerClosed(to.to_string())));
            }
            return;
        };
        let Some(p) = self.peer(id, true) else {
            if let Outgoing::Safe { done: Some(d), .. } = out {
                let _ = d.send(Err(LinkSendError::PeerClosed(to.to_string())));
            }
            return;
        };
        let mut st = lock(&p);
        let unopened = st.conn.is_none();
        match out {
            Outgoing::Fast { coalesce, msg } => self.fast_send(&mut st, coalesce, msg),
            Outgoing::Safe { msg, done } => {
                st.safe_backlog.push_back(Pending::new(msg, done, false));
                if !st.blocked && self.flush_safe(&mut st) {
                    self.notify(&st);
                }
            }
        }
        drop(st);
        if unopened {
            self.request(Ctl::Open(id));
        }
    }

    fn announce(&self, msg: &[u8]) {
        if msg.len() + frame::BASE > FRAME_MAX {
            return;
        }
        let peers: Vec<Arc<Mutex<PeerTx>>> = lock(&self.peers).values().cloned().collect();
        for p in peers {
            let st = lock(&p);
            if let Some(c) = &st.conn {
                if put(&c.fast, frame::ANNOUNCE, self.id, 0, 0, msg) {
                    self.count_out(frame::BASE + msg.len());
                    c.wake();
                }
            }
        }
    }

    fn close_peer(&self, to: PeerAddr) {
        let PeerAddr::Shm(id) = to else {
            return;
        };
        let p = lock(&self.peers).remove(&id);
        if let Some(p) = p {
            lock(&p).fail_all(&LinkSendError::PeerClosed(to.to_string()));
        }
        let _ = lock(&self.forget).send(id);
    }

    fn stats(&self) -> LinkStats {
        let c = &self.counters;
        LinkStats {
            frames_out: c.frames_out.load(Ordering::Relaxed),
            frames_in: c.frames_in.load(Ordering::Relaxed),
            bytes_out: c.bytes_out.load(Ordering::Relaxed),
            bytes_in: c.bytes_in.load(Ordering::Relaxed),
            corrupt: c.corrupt.load(Ordering::Relaxed),
            retransmitted: c.retransmitted.load(Ordering::Relaxed),
            duplicates: c.duplicates.load(Ordering::Relaxed),
            fast_dropped: c.fast_dropped.load(Ordering::Relaxed),
            // Shared memory has no acknowledgements to time and hands messages over at once.
            ..LinkStats::default()
        }
    }

    fn file_chunk(&self) -> usize {
        FILE_CHUNK
    }
}

/// A bulk body found for a `Bulk` frame.
enum BulkBody {
    /// Still in shared memory.
    Sample(iceoryx2::sample::Sample<Ipc, [u8], ()>),
    /// Copied out of it earlier (stashed while looking for another writer's).
    Copy(Vec<u8>),
}

/// How a bulk sample relates to the one looked for.
enum BulkMatch {
    Match,
    /// Of a closed session, or before the one looked for: never wanted again.
    Stale,
    /// After the one looked for, which is then missing.
    Later,
    /// Another writer's.
    Other(u64),
}

/// The wake listener as tokio's reactor sees it: its socket turns readable when a writer
/// notifies.
///
/// The only `unsafe` of the crate (the workspace denies it elsewhere): iceoryx2 hands out the
/// listener's descriptor and tokio registers one only through `unsafe` functions, because
/// neither can check that a raw descriptor stays open. Here it does: the listener that owns it
/// lives inside this wrapper, which the `AsyncFd` owns until it deregisters the descriptor.
struct WakeFd(Listener<Ipc>);

impl WakeFd {
    /// Registers `listener`'s socket with the current tokio reactor for readability.
    #[allow(unsafe_code)]
    fn watch(listener: Listener<Ipc>) -> std::io::Result<tokio::io::unix::AsyncFd<WakeFd>> {
        // SAFETY: see the type's documentation; `as_raw_fd` returns the same descriptor, open
        // for as long as the wrapper (and so the AsyncFd) exists.
        unsafe {
            tokio::io::unix::AsyncFd::register_with_interest(
                WakeFd(listener),
                tokio::io::Interest::READABLE,
            )
        }
        .map_err(std::io::Error::from)
    }
}

impl std::os::fd::AsRawFd for WakeFd {
    #[allow(unsafe_code)]
    fn as_raw_fd(&self) -> std::os::fd::RawFd {
        use iceoryx2::prelude::FileDescriptorBased;
        // SAFETY: iceoryx2 asks only that the descriptor is neither closed by hand nor used
        // past the listener's life; it is only polled for readiness while the listener lives.
        unsafe { self.0.file_descriptor().native_handle() }
    }
}

/// The control thread: owns the iceoryx2 node and does what may wait on the file system
/// (opening peers' inboxes, listing nodes, removing dead ones' resources).
struct Control {
    link: Arc<ShmLink>,
    node: IoxNode<Ipc>,
    ctl: mpsc::Receiver<Ctl>,
    next_scan: Instant,
}

impl Control {
    fn run(mut self) {
        loop {
            let timeout = self.next_scan.saturating_duration_since(Instant::now());
            match self.ctl.recv_timeout(timeout) {
                Ok(Ctl::Open(id)) => self.connect(id),
                Ok(Ctl::OpenBulk(id)) => self.open_bulk(id),
                Ok(Ctl::Stop) | Err(mpsc::RecvTimeoutError::Disconnected) => break,
                Err(mpsc::RecvTimeoutError::Timeout) => {}
            }
            if self.link.stop.load(Ordering::SeqCst) {
                break;
            }
            if Instant::now() >= self.next_scan {
                self.scan();
            }
        }
    }

    /// Opens the bulk inbox of peer `id` (asked for by its first large message) and writes
    /// what waited for it; if it cannot be opened, large messages go fragmented into the safe
    /// inbox.
    fn open_bulk(&mut self, id: u64) {
        let Some(p) = self.link.peer(id, false) else {
            return;
        };
        let opened = open_pub(
            &self.node,
            &self.link.options.service,
            id,
            ("bulk", false, BULK_BUFFER, BULK_MAX),
        );
        let mut st = lock(&p);
        st.bulk = match opened {
            Ok(b) => Bulk::Open(b),
            Err(e) => {
                tracing::warn!(link = %self.link.options.name, peer = format_args!("{id:016x}"), error = %e, "cannot open the peer's bulk inbox; large messages go fragmented");
                Bulk::Unavailable
            }
        };
        st.blocked = false;
        if self.link.flush_safe(&mut st) {
            self.link.notify(&st);
        }
    }

    /// Opens peer `id`'s inbox if it is not open yet, and writes what waited for it.
    fn connect(&mut self, id: u64) {
        let Some(p) = self.link.peer(id, true) else {
            return;
        };
        if lock(&p).conn.is_some() {
            return;
        }
        // Opening may wait (iceoryx2 retries a service still being created, e.g. by a peer
        // starting up): not under the peer's lock, which every send to it takes. A publisher
        // blocked 3 s in `set` while a restarted subscriber's inbox was being opened.
        let opened = open_conn(&self.node, &self.link.options.service, id);
        let mut st = lock(&p);
        if st.conn.is_some() {
            return;
        }
        match opened {
            Ok(c) => {
                st.conn = Some(c);
                self.link.flush_opened(&mut st);
            }
            Err(e) => {
                tracing::debug!(link = %self.link.options.name, peer = format_args!("{id:016x}"), error = %e, "peer inbox not open yet");
            }
        }
    }

    /// Lists the host's iceoryx2 nodes: connects to the inboxes of the same `service` and
    /// removes what dead ones left behind.
    fn scan(&mut self) {
        let prefix = node_prefix(&self.link.options.service);
        let mut alive = Vec::new();
        let mut dead = Vec::new();
        let listed = IoxNode::<Ipc>::list(self.node.config(), |state| {
            let id_of = |details: &Option<iceoryx2::node::NodeDetails>| {
                details
                    .as_ref()
                    .and_then(|d| d.name().as_str().strip_prefix(prefix.as_str()))
                    .and_then(|hex| u64::from_str_radix(hex, 16).ok())
            };
            match state {
                NodeState::Alive(v) => {
                    if let Some(id) = id_of(v.details()) {
                        alive.push(id);
                    }
                }
                NodeState::Dead(v) => {
                    if let Some(id) = id_of(v.details()) {
                        dead.push((id, v));
                    }
                }
                NodeState::Inaccessible(_) | NodeState::Undefined(_) => {}
            }
            CallbackProgression::Continue
        });
        if let Err(e) = listed {
            tracing::warn!(link = %self.link.options.name, error = ?e, "listing shared-memory nodes failed");
        }
        for (id, view) in dead {
            match view.try_remove_stale_resources() {
                Ok(()) => {
                    tracing::info!(link = %self.link.options.name, peer = format_args!("{id:016x}"), "removed resources of a dead shared-memory node")
                }
                Err(e) => {
                    tracing::debug!(link = %self.link.options.name, error = ?e, "dead node cleanup failed")
                }
            }
            let p = lock(&self.link.peers).remove(&id);
            if let Some(p) = p {
                lock(&p).fail_all(&LinkSendError::PeerClosed(PeerAddr::Shm(id).to_string()));
            }
        }
        for id in alive {
            if id != self.link.id {
                self.connect(id);
            }
        }
        self.next_scan = Instant::now() + self.link.options.scan;
    }
}

/// The receiving side of the inbox: drains it, delivers, acknowledges and retries what peers'
/// full inboxes refused. Driven by a tokio task woken through the wake event (`wait="event"`)
/// or by a polling thread (`wait="spin"`); never blocks.
struct Receiver {
    link: Arc<ShmLink>,
    safe: Sub,
    fast: Sub,
    bulk: Sub,
    /// Bulk samples of one writer met while looking for another's (copied, so the writer gets
    /// its memory back), in the order written.
    stash: HashMap<u64, VecDeque<Vec<u8>>>,
    forget: mpsc::Receiver<u64>,
    rx: HashMap<u64, RxState>,
    ack_due: HashSet<u64>,
    /// When the receiver may ask again to open a peer's inbox.
    open_requested: HashMap<u64, Instant>,
    next_retry: Instant,
    /// Bulk bytes delivered in the current pass.
    pass_bulk_bytes: usize,
    /// Some peer's inbox refused frames at the last look.
    backlog: bool,
}

impl Receiver {
    /// One pass over the inbox. Returns how many frames it took and whether either buffer had
    /// more than its budget (another pass should follow at once).
    fn pass(&mut self, look_at_backlogs: bool) -> (usize, bool) {
        while let Ok(id) = self.forget.try_recv() {
            self.rx.remove(&id);
            self.ack_due.remove(&id);
            self.stash.remove(&id);
            self.open_requested.remove(&id);
        }
        let mut acked = Vec::new();
        let taken_safe = self.drain_safe(&mut acked);
        let taken_fast = self.drain_fast();
        if !self.ack_due.is_empty() {
            self.send_acks();
        }
        let now = Instant::now();
        let retry = now >= self.next_retry;
        if retry {
            self.next_retry = now + RETRY;
        }
        if look_at_backlogs || retry || !acked.is_empty() {
            self.backlog = self.flush_backlogs(&acked, retry);
        }
        (
            taken_safe + taken_fast,
            taken_safe == PASS_BUDGET || taken_fast == FAST_PASS_BUDGET,
        )
    }

    /// Whether something must be retried soon even if no writer wakes us.
    fn retry_due(&self) -> bool {
        self.backlog || !self.ack_due.is_empty()
    }

    /// `wait="event"`: a pass whenever a writer notifies (or a retry is due), on a tokio worker.
    async fn drive_events(
        mut self,
        fd: tokio::io::unix::AsyncFd<WakeFd>,
        cancel: CancellationToken,
    ) {
        loop {
            let (_, more) = self.pass(true);
            if more {
                // Let the node's tasks take what was delivered before the next batch.
                tokio::task::yield_now().await;
                if cancel.is_cancelled() {
                    break;
                }
                continue;
            }
            // Sleep only with the event idle. While a notification is pending iceoryx2 sends no
            // datagram for the next ones, and reading the socket may swallow the datagram of a
            // notification it leaves pending: the socket would then never turn readable again.
            // Consuming the notifications here resets that state; any notification consumed
            // (its frames may have arrived after the pass) means another pass first.
            match fd.get_ref().0.try_wait(|_| {}) {
                Ok(0) => {}
                Ok(_) => continue,
                Err(e) => {
                    tracing::warn!(link = %self.link.options.name, error = ?e, "reading the shared-memory wake event failed");
                }
            }
            let retry = self.retry_due();
            tokio::select! {
                _ = cancel.cancelled() => break,
                ready = fd.readable() => match ready {
                    // The datagram is read after the next pass; one arriving after this point
                    // makes the socket readable again.
                    Ok(mut guard) => guard.clear_ready(),
                    Err(e) => {
                        tracing::warn!(link = %self.link.options.name, error = %e, "waiting on the shared-memory inbox failed");
                        tokio::time::sleep(RETRY).await;
                    }
                },
                _ = tokio::time::sleep(RETRY), if retry => {}
            }
        }
    }

    /// `wait="spin"`: passes without pause while frames flow, yielding the worker between them
    /// (the tasks the pass woke run then), and, idle, one per [`PARK`].
    async fn drive_polling(mut self, cancel: CancellationToken) {
        let mut last_frame = Instant::now();
        while !cancel.is_cancelled() {
            // Backlogs are looked at on acknowledgements and the retry timer only: on every
            // pass they would contend with the writers' locks.
            let (taken, more) = self.pass(false);
            let now = Instant::now();
            if taken > 0 {
                last_frame = now;
            }
            if more || now.saturating_duration_since(last_frame) < YIELD_UNTIL {
                tokio::task::yield_now().await;
                continue;
            }
            tokio::select! {
                _ = cancel.cancelled() => break,
                _ = tokio::time::sleep(PARK) => {}
            }
        }
    }

    fn count_in(&self, n: usize) {
        let c = &self.link.counters;
        c.frames_in.fetch_add(1, Ordering::Relaxed);
        c.bytes_in.fetch_add(n as u64, Ordering::Relaxed);
    }

    /// Takes what the safe inbox holds, up to [`PASS_BUDGET`] frames or [`PASS_BULK_BYTES`]
    /// of bulk bodies. Returns how many frames it took ([`PASS_BUDGET`] when a budget ran out).
    fn drain_safe(&mut self, acked: &mut Vec<u64>) -> usize {
        let link = self.link.clone();
        self.pass_bulk_bytes = 0;
        for taken in 0..PASS_BUDGET {
            if self.pass_bulk_bytes >= PASS_BULK_BYTES {
                return PASS_BUDGET;
            }
            let sample = match self.safe.receive() {
                Ok(Some(s)) => s,
                Ok(None) => return taken,
                Err(e) => {
                    tracing::warn!(link = %link.options.name, error = ?e, "receiving from the safe inbox failed");
                    return taken;
                }
            };
            let bytes = sample.payload();
            self.count_in(bytes.len());
            match frame::parse(bytes) {
                Ok((
                    from,
                    frame::Frame::Safe {
                        session,
                        seq,
                        more,
                        body,
                    },
                )) => self.on_safe(from, session, seq, more, Some(body)),
                Ok((from, frame::Frame::Ack { session, seq })) => {
                    if self.on_ack(from, session, seq) {
                        acked.push(from);
                    }
                }
                Ok((from, frame::Frame::Bulk { session, seq, more })) => {
                    self.on_bulk(from, session, seq, more)
                }
                Ok((from, frame::Frame::Fast(body))) => {
                    link.handler
                        .on_message(link.index, PeerAddr::Shm(from), body)
                }
                Ok((from, frame::Frame::Announce(body))) => {
                    link.handler
                        .on_announce(link.index, PeerAddr::Shm(from), body)
                }
                Ok((_, frame::Frame::BulkData { .. })) => {
                    // Bulk bodies never use the safe inbox.
                    link.counters.corrupt.fetch_add(1, Ordering::Relaxed);
                }
                Err(e) => {
                    link.counters.corrupt.fetch_add(1, Ordering::Relaxed);
                    tracing::trace!(link = %link.options.name, error = %e, "corrupt frame dropped");
                }
            }
        }
        PASS_BUDGET
    }

    /// Takes what the fast inbox holds, up to [`FAST_PASS_BUDGET`] frames. Returns how many it
    /// took.
    fn drain_fast(&mut self) -> usize {
        let link = self.link.clone();
        for taken in 0..FAST_PASS_BUDGET {
            let sample = match self.fast.receive() {
                Ok(Some(s)) => s,
                Ok(None) => return taken,
                Err(e) => {
                    tracing::warn!(link = %link.options.name, error = ?e, "receiving from the fast inbox failed");
                    return taken;
                }
            };
            let bytes = sample.payload();
            self.count_in(bytes.len());
            match frame::parse(bytes) {
                Ok((from, frame::Frame::Fast(body))) => {
                    link.handler
                        .on_message(link.index, PeerAddr::Shm(from), body)
                }
                Ok((from, frame::Frame::Announce(body))) => {
                    link.handler
                        .on_announce(link.index, PeerAddr::Shm(from), body)
                }
                Ok(_) | Err(_) => {
                    // Safe frames never use the fast inbox.
                    link.counters.corrupt.fetch_add(1, Ordering::Relaxed);
                }
            }
        }
        FAST_PASS_BUDGET
    }

    /// A `Bulk` frame: its body is the next bulk sample of `from` (read in place when the
    /// message is that one fragment).
    fn on_bulk(&mut self, from: u64, session: u32, seq: u64, more: bool) {
        match self.take_bulk(from, session, seq) {
            Some(BulkBody::Sample(sample)) => {
                let body = &sample.payload()[frame::SEQUENCED..];
                self.count_in(body.len());
                self.pass_bulk_bytes += body.len();
                self.on_safe(from, session, seq, more, Some(body));
            }
            Some(BulkBody::Copy(frame)) => {
                let body = &frame[frame::SEQUENCED..];
                self.pass_bulk_bytes += body.len();
                self.count_in(body.len());
                self.on_safe(from, session, seq, more, Some(body));
            }
            None => {
                self.link.counters.corrupt.fetch_add(1, Ordering::Relaxed);
                self.on_safe(from, session, seq, more, None);
            }
        }
    }

    /// Finds the body written for `from`'s fragment `(session, seq)`: in the stash, or next in
    /// the bulk inbox. Bodies of other writers met on the way are stashed, older ones of `from`
    /// (a closed session's) dropped.
    fn take_bulk(&mut self, from: u64, session: u32, seq: u64) -> Option<BulkBody> {
        let wanted = |b: &[u8]| -> BulkMatch {
            match frame::parse(b) {
                Ok((
                    s,
                    frame::Frame::BulkData {
                        session: ss,
                        seq: q,
                        ..
                    },
                )) if s == from => {
                    if ss == session && q == seq {
                        BulkMatch::Match
                    } else if ss != session || q < seq {
                        BulkMatch::Stale
                    } else {
                        BulkMatch::Later
                    }
                }
                Ok((s, frame::Frame::BulkData { .. })) => BulkMatch::Other(s),
                _ => BulkMatch::Stale,
            }
        };
        if let Some(q) = self.stash.get_mut(&from) {
            while let Some(b) = q.pop_front() {
                match wanted(&b) {
                    BulkMatch::Match => return Some(BulkBody::Copy(b)),
                    BulkMatch::Later => {
                        q.push_front(b);
                        return None;
                    }
                    BulkMatch::Stale | BulkMatch::Other(_) => {}
                }
            }
        }
        loop {
            let sample = match self.bulk.receive() {
                Ok(Some(s)) => s,
                Ok(None) => return None,
                Err(e) => {
                    tracing::warn!(link = %self.link.options.name, error = ?e, "receiving from the bulk inbox failed");
                    return None;
                }
            };
            match wanted(sample.payload()) {
                BulkMatch::Match => return Some(BulkBody::Sample(sample)),
                BulkMatch::Stale => {}
                BulkMatch::Later => {
                    self.stash
                        .entry(from)
                        .or_default()
                        .push_front(sample.payload().to_vec());
                    return None;
                }
                BulkMatch::Other(writer) => {
                    // A writer's bodies in the stash never outnumber its frames the safe inbox
                    // can hold plus what it may write before them; more is corrupt input.
                    let q = self.stash.entry(writer).or_default();
                    if q.len() > SAFE_BUFFER + BULK_BUFFER {
                        q.pop_front();
                        self.link.counters.corrupt.fetch_add(1, Ordering::Relaxed);
                    }
                    q.push_back(sample.payload().to_vec());
                }
            }
        }
    }

    /// A fragment of a safe message; `body` is `None` when it went missing (a bulk body that
    /// is not there), which tears the message.
    fn on_safe(&mut self, from: u64, session: u32, seq: u64, more: bool, body: Option<&[u8]>) {
        let link = self.link.clone();
        let peer = PeerAddr::Shm(from);
        let reset = match self.rx.get_mut(&from) {
            Some(st) if st.session == session => false,
            Some(st) => {
                // The sender closed us and started over: what it had in flight is gone.
                *st = RxState::new(session, seq);
                true
            }
            None => {
                self.rx.insert(from, RxState::new(session, seq));
                false
            }
        };
        if reset {
            link.handler.on_peer_reset(link.index, peer);
        }
        let Some(st) = self.rx.get_mut(&from) else {
            return;
        };
        if seq < st.expected {
            link.counters.duplicates.fetch_add(1, Ordering::Relaxed);
            return;
        }
        if seq > st.expected {
            // Shared memory loses nothing; a gap means a torn message, which is dropped.
            st.torn = true;
            link.counters.corrupt.fetch_add(1, Ordering::Relaxed);
        }
        st.expected = seq + 1;
        st.ack = Some(seq);
        self.ack_due.insert(from);
        let Some(body) = body.filter(|_| !st.torn) else {
            st.torn = more;
            st.partial = Vec::new();
            return;
        };
        if more {
            if st.partial.len() + body.len() > MAX_MESSAGE {
                st.partial = Vec::new();
                st.torn = true;
                link.counters.corrupt.fetch_add(1, Ordering::Relaxed);
            } else {
                st.partial.extend_from_slice(body);
            }
            return;
        }
        if st.partial.is_empty() {
            link.handler.on_message(link.index, peer, body);
        } else {
            st.partial.extend_from_slice(body);
            let msg = std::mem::take(&mut st.partial);
            link.handler.on_message(link.index, peer, &msg);
        }
    }

    /// Completes what `from` acknowledged. Returns whether it refers to our current session.
    fn on_ack(&mut self, from: u64, session: u32, seq: u64) -> bool {
        let Some(p) = self.link.peer(from, false) else {
            return false;
        };
        let done: Vec<SafeCompletion> = {
            let mut st = lock(&p);
            if st.session != session {
                return false;
            }
            st.blocked = false;
            let mut v = Vec::new();
            while st.unacked.front().is_some_and(|(s, _)| *s <= seq) {
                if let Some((_, d)) = st.unacked.pop_front() {
                    v.push(d);
                }
            }
            v
        };
        for d in done {
            let _ = d.send(Ok(()));
        }
        true
    }

    fn send_acks(&mut self) {
        let due: Vec<u64> = self.ack_due.iter().copied().collect();
        for from in due {
            let Some((session, seq)) = self
                .rx
                .get(&from)
                .and_then(|st| st.ack.map(|a| (st.session, a)))
            else {
                self.ack_due.remove(&from);
                continue;
            };
            let Some(p) = self.link.peer(from, true) else {
                self.ack_due.remove(&from);
                continue;
            };
            let st = lock(&p);
            let Some(c) = &st.conn else {
                // A peer that wrote before our scan found it: the control thread opens its
                // inbox, the retry timer brings us back.
                let now = Instant::now();
                if self.open_requested.get(&from).is_none_or(|t| *t <= now) {
                    self.open_requested.insert(from, now + REOPEN);
                    self.link.request(Ctl::Open(from));
                }
                continue;
            };
            if put(&c.safe, frame::ACK, self.link.id, session, seq, &[]) {
                self.link.count_out(frame::SEQUENCED);
                c.wake();
                drop(st);
                self.ack_due.remove(&from);
                if let Some(r) = self.rx.get_mut(&from) {
                    if r.ack == Some(seq) {
                        r.ack = None;
                    }
                }
            }
        }
    }

    /// Retries refused frames towards peers that acknowledged (their buffer has room) or, on
    /// `retry`, towards every blocked peer. Returns whether some backlog remains.
    fn flush_backlogs(&mut self, acked: &[u64], retry: bool) -> bool {
        let peers: Vec<(u64, Arc<Mutex<PeerTx>>)> = lock(&self.link.peers)
            .iter()
            .map(|(id, p)| (*id, p.clone()))
            .collect();
        let mut remaining = false;
        for (id, p) in peers {
            let mut st = lock(&p);
            if st.safe_backlog.is_empty() {
                continue;
            }
            if acked.contains(&id) || retry {
                st.blocked = false;
                if self.link.flush_safe(&mut st) {
                    self.link.notify(&st);
                }
            }
            remaining |= !st.safe_backlog.is_empty() && st.conn.is_some();
        }
        remaining
    }
}

#[cfg(test)]
mod tests {
    use super::frame::{self, Frame, FrameDecodeError};
    use super::*;

    #[test]
    fn golden_safe_frame() {
        let mut b = vec![0u8; frame::SEQUENCED + 2];
        frame::write_header(
            &mut b,
            frame::SAFE_MORE,
            0x0102_0304_0506_0708,
            9,
            0x1_0000_0002,
        );
        b[21..].copy_from_slice(b"hi");
        assert_eq!(
            b,
            [
                4, // kind: SafeMore
                8, 7, 6, 5, 4, 3, 2, 1, // sender id, little endian
                9, 0, 0, 0, // session
                2, 0, 0, 0, 1, 0, 0, 0, // sequence number
                b'h', b'i', // body
            ]
        );
        assert_eq!(
            frame::parse(&b),
            Ok((
                0x0102_0304_0506_0708,
                Frame::Safe {
                    session: 9,
                    seq: 0x1_0000_0002,
                    more: true,
                    body: b"hi"
                }
            ))
        );
    }

    #[test]
    fn golden_fast_and_ack_frames() {
        let mut f = vec![0u8; frame::BASE + 1];
        frame::write_header(&mut f, frame::FAST, 1, 77, 77);
        f[9] = 0xAA;
        assert_eq!(f, [2, 1, 0, 0, 0, 0, 0, 0, 0, 0xAA]);
        assert_eq!(frame::parse(&f), Ok((1, Frame::Fast(&[0xAA]))));
        let mut a = vec![0u8; frame::SEQUENCED];
        frame::write_header(&mut a, frame::ACK, 2, 3, 4);
        assert_eq!(
            a,
            [5, 2, 0, 0, 0, 0, 0, 0, 0, 3, 0, 0, 0, 4, 0, 0, 0, 0, 0, 0, 0]
        );
        assert_eq!(frame::parse(&a), Ok((2, Frame::Ack { session: 3, seq: 4 })));
    }

    #[test]
    fn golden_bulk_frames() {
        let mut d = vec![0u8; frame::SEQUENCED];
        frame::write_header(&mut d, frame::BULK_MORE, 1, 2, 3);
        assert_eq!(
            d,
            [
                7, // kind: BulkMore (the body is in the bulk inbox, more fragments follow)
                1, 0, 0, 0, 0, 0, 0, 0, // sender id
                2, 0, 0, 0, // session
                3, 0, 0, 0, 0, 0, 0, 0, // sequence number
            ]
        );
        assert_eq!(
            frame::parse(&d),
            Ok((
                1,
                Frame::Bulk {
                    session: 2,
                    seq: 3,
                    more: true
                }
            ))
        );
        d[0] = frame::BULK;
        assert_eq!(
            frame::parse(&d),
            Ok((
                1,
                Frame::Bulk {
                    session: 2,
                    seq: 3,
                    more: false
                }
            ))
        );
        let mut b = vec![0u8; frame::SEQUENCED + 1];
        frame::write_header(&mut b, frame::BULK_DATA, 1, 2, 3);
        b[21] = 0xEE;
        assert_eq!(
            b,
            [8, 1, 0, 0, 0, 0, 0, 0, 0, 2, 0, 0, 0, 3, 0, 0, 0, 0, 0, 0, 0, 0xEE]
        );
        assert_eq!(
            frame::parse(&b),
            Ok((
                1,
                Frame::BulkData {
                    session: 2,
                    seq: 3,
                    body: &[0xEE]
                }
            ))
        );
        assert_eq!(frame::parse(&b[..20]), Err(FrameDecodeError::Truncated(20)));
    }

    #[test]
    fn malformed_frames_are_errors() {
        assert_eq!(frame::parse(&[]), Err(FrameDecodeError::Truncated(0)));
        assert_eq!(
            frame::parse(&[3, 0, 0, 0, 0, 0, 0, 0, 0, 1]),
            Err(FrameDecodeError::Truncated(10))
        );
        assert_eq!(
            frame::parse(&[99, 0, 0, 0, 0, 0, 0, 0, 0]),
            Err(FrameDecodeError::UnknownKind(99))
        );
        for len in 0..40 {
            let b: Vec<u8> = (0..len).map(|i| (i * 37 % 251) as u8).collect();
            let _ = frame::parse(&b);
        }
    }

    /// What a link delivered, in order.
    #[derive(Debug, Clone, PartialEq, Eq)]
    enum Got {
        Msg(PeerAddr, Vec<u8>),
        Announce(PeerAddr, Vec<u8>),
        Reset(PeerAddr),
    }

    struct Collect(mpsc::Sender<Got>);

    impl LinkHandler for Collect {
        fn on_message(&self, _: usize, from: PeerAddr, msg: &[u8]) {
            let _ = self.0.send(Got::Msg(from, msg.to_vec()));
        }
        fn on_announce(&self, _: usize, from: PeerAddr, msg: &[u8]) {
            let _ = self.0.send(Got::Announce(from, msg.to_vec()));
        }
        fn on_peer_reset(&self, _: usize, from: PeerAddr) {
            let _ = self.0.send(Got::Reset(from));
        }
    }

    fn unique_service(tag: &str) -> String {
        format!("t{tag}{}x{:08x}", std::process::id(), rand::random::<u32>())
    }

    async fn open_link(
        service: &str,
        tasks: &TaskTracker,
        cancel: &CancellationToken,
    ) -> (Arc<ShmLink>, mpsc::Receiver<Got>) {
        open_link_waiting(service, ShmWait::Event, tasks, cancel).await
    }

    async fn open_link_waiting(
        service: &str,
        wait: ShmWait,
        tasks: &TaskTracker,
        cancel: &CancellationToken,
    ) -> (Arc<ShmLink>, mpsc::Receiver<Got>) {
        let (tx, rx) = mpsc::channel();
        let link = ShmLink::open(
            0,
            ShmLinkOptions {
                name: "shm0".into(),
                service: service.into(),
                scan: Duration::from_millis(200),
                wait,
            },
            Arc::new(Collect(tx)),
            tasks,
            cancel.child_token(),
        )
        .await
        .expect("shm link opens");
        (link, rx)
    }

    /// Next delivery that is not an announcement, within 5 s.
    fn next_msg(rx: &mpsc::Receiver<Got>) -> Got {
        let deadline = Instant::now() + Duration::from_secs(5);
        loop {
            let left = deadline.saturating_duration_since(Instant::now());
            match rx.recv_timeout(left) {
                Ok(Got::Announce(..)) => continue,
                Ok(g) => return g,
                Err(e) => panic!("nothing delivered: {e}"),
            }
        }
    }

    fn safe(
        msg: Vec<u8>,
    ) -> (
        Outgoing,
        tokio::sync::oneshot::Receiver<Result<(), LinkSendError>>,
    ) {
        let (tx, rx) = tokio::sync::oneshot::channel();
        (
            Outgoing::Safe {
                msg,
                done: Some(tx),
            },
            rx,
        )
    }

    async fn stop(tasks: TaskTracker, cancel: CancellationToken) {
        cancel.cancel();
        tasks.close();
        tokio::time::timeout(Duration::from_secs(5), tasks.wait())
            .await
            .expect("receive threads stop");
    }

    #[tokio::test(flavor = "multi_thread", worker_threads = 2)]
    async fn announce_reaches_a_node_started_earlier_and_later() {
        let svc = unique_service("ann");
        let (tasks, cancel) = (TaskTracker::new(), CancellationToken::new());
        let (a, arx) = open_link(&svc, &tasks, &cancel).await;
        let (b, brx) = open_link(&svc, &tasks, &cancel).await;
        // b connected to a when it opened; a connects to b when it first hears from it.
        b.announce(b"hello from b");
        let got = arx.recv_timeout(Duration::from_secs(5)).expect("a hears b");
        assert_eq!(
            got,
            Got::Announce(PeerAddr::Shm(b.id()), b"hello from b".to_vec())
        );
        a.send(
            PeerAddr::Shm(b.id()),
            Outgoing::Fast {
                coalesce: None,
                msg: b"x".to_vec(),
            },
        );
        assert_eq!(
            next_msg(&brx),
            Got::Msg(PeerAddr::Shm(a.id()), b"x".to_vec())
        );
        a.announce(b"hello from a");
        let deadline = Instant::now() + Duration::from_secs(5);
        loop {
            match brx.recv_timeout(deadline.saturating_duration_since(Instant::now())) {
                Ok(Got::Announce(from, m)) if m == b"hello from a" => {
                    assert_eq!(from, PeerAddr::Shm(a.id()));
                    break;
                }
                Ok(_) => continue,
                Err(e) => panic!("b never heard a's announcement: {e}"),
            }
        }
        stop(tasks, cancel).await;
    }

    #[tokio::test(flavor = "multi_thread", worker_threads = 2)]
    async fn safe_messages_arrive_once_in_order_and_are_acknowledged() {
        let svc = unique_service("safe");
        let (tasks, cancel) = (TaskTracker::new(), CancellationToken::new());
        let (a, _arx) = open_link(&svc, &tasks, &cancel).await;
        let (b, brx) = open_link(&svc, &tasks, &cancel).await;
        let n = 5000u32;
        let mut acks = Vec::new();
        for i in 0..n {
            // Every 500th message spans several frames.
            let len = if i % 500 == 0 { 3 * FRAME_MAX + 17 } else { 8 };
            let mut m = vec![(i % 251) as u8; len];
            m[..4].copy_from_slice(&i.to_le_bytes());
            let (out, done) = safe(m);
            a.send(PeerAddr::Shm(b.id()), out);
            acks.push(done);
        }
        for i in 0..n {
            let Got::Msg(from, m) = next_msg(&brx) else {
                panic!("unexpected delivery");
            };
            assert_eq!(from, PeerAddr::Shm(a.id()));
            assert_eq!(u32::from_le_bytes([m[0], m[1], m[2], m[3]]), i);
            let len = if i % 500 == 0 { 3 * FRAME_MAX + 17 } else { 8 };
            assert_eq!(m.len(), len);
            assert!(m[4..].iter().all(|&x| x == (i % 251) as u8));
        }
        for d in acks {
            let r = tokio::time::timeout(Duration::from_secs(5), d).await;
            assert_eq!(
                r.expect("acknowledged in time").expect("completion sent"),
                Ok(())
            );
        }
        assert_eq!(b.stats().duplicates, 0);
        stop(tasks, cancel).await;
    }

    /// A message of `len` bytes tagged with the writer and its index.
    fn tagged_message(writer: u8, i: u32, len: usize) -> Vec<u8> {
        let mut m: Vec<u8> = (0..len)
            .map(|k| (k as u32).wrapping_mul(31).wrapping_add(i) as u8)
            .collect();
        m[0] = writer;
        m[1..5].copy_from_slice(&i.to_le_bytes());
        m
    }

    #[tokio::test(flavor = "multi_thread", worker_threads = 2)]
    async fn large_messages_of_two_writers_cross_the_bulk_inbox_whole_and_in_order() {
        let svc = unique_service("bulk");
        let (tasks, cancel) = (TaskTracker::new(), CancellationToken::new());
        let (a, _arx) = open_link(&svc, &tasks, &cancel).await;
        let (c, _crx) = open_link(&svc, &tasks, &cancel).await;
        let (b, brx) = open_link(&svc, &tasks, &cancel).await;
        let to = PeerAddr::Shm(b.id());
        // Sizes around every boundary: inline, one bulk sample, several, small again.
        let sizes = [
            10,
            FRAME_MAX - frame::SEQUENCED,
            FRAME_MAX - frame::SEQUENCED + 1,
            BULK_MAX - frame::SEQUENCED,
            BULK_MAX - frame::SEQUENCED + 1,
            3 * BULK_MAX + 5,
            FILE_CHUNK + 40,
            7,
        ];
        let n = 40u32;
        let mut acks = Vec::new();
        // Both writers at once, so the reader meets one writer's bodies while looking for the
        // other's.
        for i in 0..n {
            let len = sizes[i as usize % sizes.len()];
            for (tag, w) in [(b'a', &a), (b'c', &c)] {
                let (out, done) = safe(tagged_message(tag, i, len));
                w.send(to, out);
                acks.push(done);
            }
            if i % 3 == 0 {
                // Fast messages too large for a frame ride the same path.
                a.send(
                    to,
                    Outgoing::Fast {
                        coalesce: None,
                        msg: tagged_message(b'f', i, 2 * BULK_MAX),
                    },
                );
            }
        }
        let mut next = HashMap::from([(b'a', 0u32), (b'c', 0u32), (b'f', 0u32)]);
        while next[&b'a'] < n || next[&b'c'] < n {
            let Got::Msg(_, m) = next_msg(&brx) else {
                panic!("unexpected delivery");
            };
            let i = u32::from_le_bytes([m[1], m[2], m[3], m[4]]);
            let expected = next.get_mut(&m[0]).expect("a known writer");
            assert!(i >= *expected, "writer {} went back to {i}", m[0] as char);
            if m[0] != b'f' {
                assert_eq!(i, *expected, "writer {} skipped", m[0] as char);
                assert_eq!(m.len(), sizes[i as usize % sizes.len()]);
            }
            assert_eq!(m, tagged_message(m[0], i, m.len()), "content of {i}");
            *expected = i + 1;
        }
        for d in acks {
            let r = tokio::time::timeout(Duration::from_secs(10), d).await;
            assert_eq!(
                r.expect("acknowledged in time").expect("completion sent"),
                Ok(())
            );
        }
        assert_eq!(b.stats().corrupt, 0);
        assert_eq!(b.stats().duplicates, 0);
        stop(tasks, cancel).await;
    }

    #[tokio::test(flavor = "multi_thread", worker_threads = 2)]
    async fn a_sleeping_reader_never_misses_a_wake_up() {
        let svc = unique_service("wake");
        let (tasks, cancel) = (TaskTracker::new(), CancellationToken::new());
        let (a, _arx) = open_link(&svc, &tasks, &cancel).await;
        let (c, _crx) = open_link(&svc, &tasks, &cancel).await;
        let (b, _brx) = open_link(&svc, &tasks, &cancel).await;
        let to = PeerAddr::Shm(b.id());
        // Two writers, one message at a time each: the reader falls asleep between most
        // messages and the writers' notifications race with its waking. A wake-up lost for
        // good would leave a message unacknowledged.
        let writer = |w: Arc<ShmLink>| async move {
            for i in 0..3000u32 {
                let (out, done) = safe(i.to_le_bytes().to_vec());
                w.send(to, out);
                let r = tokio::time::timeout(Duration::from_secs(5), done).await;
                assert_eq!(
                    r.unwrap_or_else(|_| panic!("message {i} never acknowledged"))
                        .expect("completion sent"),
                    Ok(())
                );
            }
        };
        let (ra, rc) = tokio::join!(
            tokio::spawn(writer(a.clone())),
            tokio::spawn(writer(c.clone()))
        );
        ra.expect("writer a");
        rc.expect("writer c");
        stop(tasks, cancel).await;
    }

    #[tokio::test(flavor = "multi_thread", worker_threads = 2)]
    async fn a_polling_reader_is_never_notified_and_still_gets_everything() {
        let svc = unique_service("spin");
        let (tasks, cancel) = (TaskTracker::new(), CancellationToken::new());
        let (a, arx) = open_link(&svc, &tasks, &cancel).await;
        let (b, brx) = open_link_waiting(&svc, ShmWait::Spin, &tasks, &cancel).await;
        let (to_b, to_a) = (PeerAddr::Shm(b.id()), PeerAddr::Shm(a.id()));
        let (out, done) = safe(b"first".to_vec());
        a.send(to_b, out);
        assert_eq!(next_msg(&brx), Got::Msg(to_a, b"first".to_vec()));
        let r = tokio::time::timeout(Duration::from_secs(5), done).await;
        assert_eq!(r.expect("acknowledged").expect("completion sent"), Ok(()));
        // a learnt from b's inbox that b polls, and b that a sleeps.
        let spins = |from: &ShmLink, to: u64| {
            from.peer(to, false)
                .and_then(|p| lock(&p).conn.as_ref().map(|c| c.spins))
        };
        assert_eq!(spins(&a, b.id()), Some(true));
        b.send(
            to_a,
            Outgoing::Fast {
                coalesce: None,
                msg: b"back".to_vec(),
            },
        );
        assert_eq!(next_msg(&arx), Got::Msg(to_b, b"back".to_vec()));
        assert_eq!(spins(&b, a.id()), Some(false));
        // After an idle period (no event marks it: the reader just stops seeing frames) the
        // reader parks between polls, and still picks messages up.
        tokio::time::sleep(YIELD_UNTIL * 3).await;
        for i in 0..200u32 {
            let (out, _) = safe(i.to_le_bytes().to_vec());
            a.send(to_b, out);
        }
        a.send(
            to_b,
            Outgoing::Fast {
                coalesce: None,
                msg: vec![9; 3 * BULK_MAX],
            },
        );
        for i in 0..200u32 {
            assert_eq!(next_msg(&brx), Got::Msg(to_a, i.to_le_bytes().to_vec()));
        }
        assert_eq!(next_msg(&brx), Got::Msg(to_a, vec![9; 3 * BULK_MAX]));
        stop(tasks, cancel).await;
    }

    #[tokio::test(flavor = "multi_thread", worker_threads = 2)]
    async fn a_reader_that_stops_never_blocks_the_writer() {
        let svc = unique_service("stall");
        let (tasks, cancel) = (TaskTracker::new(), CancellationToken::new());
        let (a, _arx) = open_link(&svc, &tasks, &cancel).await;
        // b's handler blocks until released: its receive thread stops reading.
        let (gate_tx, gate_rx) = std::sync::mpsc::channel::<()>();
        let (tx, brx) = mpsc::channel();
        let (stalled_tx, stalled_rx) = std::sync::mpsc::channel::<()>();
        struct Stuck(Mutex<mpsc::Receiver<()>>, Collect, Mutex<mpsc::Sender<()>>);
        impl LinkHandler for Stuck {
            fn on_message(&self, l: usize, from: PeerAddr, msg: &[u8]) {
                if msg == b"stall" {
                    let _ = lock(&self.2).send(());
                    let _ = lock(&self.0).recv_timeout(Duration::from_secs(20));
                }
                self.1.on_message(l, from, msg);
            }
            fn on_announce(&self, _: usize, _: PeerAddr, _: &[u8]) {}
            fn on_peer_reset(&self, l: usize, from: PeerAddr) {
                self.1.on_peer_reset(l, from);
            }
        }
        let b = ShmLink::open(
            0,
            ShmLinkOptions {
                name: "shm0".into(),
                service: svc.clone(),
                scan: Duration::from_millis(200),
                wait: ShmWait::Event,
            },
            Arc::new(Stuck(
                Mutex::new(gate_rx),
                Collect(tx),
                Mutex::new(stalled_tx),
            )),
            &tasks,
            cancel.child_token(),
        )
        .await
        .expect("opens");
        let to = PeerAddr::Shm(b.id());
        a.send(
            to,
            Outgoing::Fast {
                coalesce: None,
                msg: b"stall".to_vec(),
            },
        );
        let tagged = |tag: u8, i: u32| {
            let mut m = vec![tag];
            m.extend_from_slice(&i.to_le_bytes());
            m
        };
        // Only once b's receive thread is really stuck does the burst test a stopped reader.
        stalled_rx
            .recv_timeout(Duration::from_secs(20))
            .expect("b's reader reached the stall");
        let started = Instant::now();
        for i in 0..20_000u32 {
            a.send(
                to,
                Outgoing::Fast {
                    coalesce: Some(1),
                    msg: tagged(b'f', i),
                },
            );
        }
        let mut acks = Vec::new();
        for i in 0..1000u32 {
            let (out, done) = safe(tagged(b's', i));
            a.send(to, out);
            acks.push(done);
        }
        assert!(
            started.elapsed() < Duration::from_secs(5),
            "sending blocked"
        );
        assert!(a.stats().retransmitted > 0, "the safe inbox filled up");
        let _ = gate_tx.send(());
        // Every safe message arrives once, in order; the newest fast value survives overflow.
        let mut next_safe = 0u32;
        let mut last_fast = 0u32;
        while next_safe < 1000 || last_fast < 19_999 {
            let Got::Msg(_, m) = next_msg(&brx) else {
                continue;
            };
            if m == b"stall" {
                continue;
            }
            let v = u32::from_le_bytes([m[1], m[2], m[3], m[4]]);
            match m[0] {
                b's' => {
                    assert_eq!(v, next_safe);
                    next_safe += 1;
                }
                _ => {
                    assert!(v >= last_fast);
                    last_fast = v;
                }
            }
        }
        for d in acks {
            let r = tokio::time::timeout(Duration::from_secs(5), d).await;
            assert_eq!(
                r.expect("acknowledged in time").expect("completion sent"),
                Ok(())
            );
        }
        stop(tasks, cancel).await;
    }

    #[tokio::test(flavor = "multi_thread", worker_threads = 2)]
    async fn closing_a_peer_fails_what_it_did_not_acknowledge() {
        let svc = unique_service("close");
        let (tasks, cancel) = (TaskTracker::new(), CancellationToken::new());
        let (a, _arx) = open_link(&svc, &tasks, &cancel).await;
        // A peer that never existed: the message waits for an inbox that never opens.
        let ghost = PeerAddr::Shm(0x1234);
        let (out, done) = safe(b"lost".to_vec());
        a.send(ghost, out);
        a.close_peer(ghost);
        let r = tokio::time::timeout(Duration::from_secs(5), done).await;
        assert!(matches!(r, Ok(Ok(Err(LinkSendError::PeerClosed(_))))));
        stop(tasks, cancel).await;
    }
}
