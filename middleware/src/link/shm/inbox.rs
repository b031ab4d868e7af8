//! Everything that touches iceoryx2: creating this link's inbox (its node, the fast, safe and
//! bulk publish-subscribe services and the wake event), opening peers' inboxes for writing,
//! reading samples, listing the host's nodes and watching the wake event from tokio. The
//! machines in [`super::tx`] and [`super::rx`] see it only through their writer and I/O traits.

use std::mem::MaybeUninit;
use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::Arc;

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

use super::frame::{self, Part};
use super::{
    ShmLinkOpenError, ShmLinkOptions, ShmWait, BULK_BUFFER, BULK_LOANS, BULK_MAX, FAST_BUFFER,
    FRAME_MAX, LENT_SAMPLES, SAFE_BUFFER,
};
use crate::link::auth::{Profile, Sealer};

pub(super) type Ipc = ipc_threadsafe::Service;
pub(super) type Pub = Publisher<Ipc, [u8], ()>;
type Sub = Subscriber<Ipc, [u8], ()>;
type PubSubService = iceoryx2::service::port_factory::publish_subscribe::PortFactory<Ipc, [u8], ()>;
type EventService = iceoryx2::service::port_factory::event::PortFactory<Ipc>;
/// The iceoryx2 node of a link.
pub(super) type Node = IoxNode<Ipc>;

/// The wake event's attribute telling writers how the inbox's reader waits.
const WAIT_ATTRIBUTE: &str = "marea.wait";

/// The writing side of a peer's inbox.
pub(super) struct Conn {
    pub(super) fast: Pub,
    pub(super) safe: Pub,
    wake: Notifier<Ipc>,
    /// The peer busy-polls its inbox (`wait="spin"`): never notify it.
    pub(super) spins: bool,
}

impl Conn {
    pub(super) fn wake(&self) {
        if !self.spins {
            let _ = self.wake.notify();
        }
    }
}

pub(super) fn node_prefix(service: &str) -> String {
    format!("marea/{service}/")
}

fn inbox_name(service: &str, id: u64, part: &str) -> String {
    format!("marea/{service}/{id:016x}/{part}")
}

/// The receiving side, created by the control thread (which keeps the node) before the link:
/// the reader and the listener go to the receive task.
pub(super) struct Inbox {
    pub(super) reader: InboxReader,
    pub(super) listener: Listener<Ipc>,
    /// Wakes our own receiver (control requests, shutdown).
    pub(super) self_wake: Notifier<Ipc>,
}

/// A notifier of our own wake event.
pub(super) type SelfWake = Notifier<Ipc>;

/// The subscribers of this link's inbox.
pub(super) struct InboxReader {
    safe: Sub,
    fast: Sub,
    bulk: Sub,
    /// Link name, for the log.
    link: String,
}

/// A sample read in place from the inbox.
pub(super) struct InboxSample(iceoryx2::sample::Sample<Ipc, [u8], ()>);

impl AsRef<[u8]> for InboxSample {
    fn as_ref(&self) -> &[u8] {
        self.0.payload()
    }
}

impl InboxReader {
    /// Takes the oldest sample of `part`. A failure to read is logged and reads as empty.
    pub(super) fn take(&mut self, part: Part) -> Option<InboxSample> {
        let sub = match part {
            Part::Safe => &self.safe,
            Part::Fast => &self.fast,
            Part::Bulk => &self.bulk,
        };
        match sub.receive() {
            Ok(s) => s.map(InboxSample),
            Err(e) => {
                tracing::warn!(link = %self.link, part = ?part, error = ?e, "receiving from the shared-memory inbox failed");
                None
            }
        }
    }
}

/// Departed writers whose unread frames an inbox part keeps until the next pass: iceoryx2's
/// least (the samples a subscriber may borrow, 2). Each one more costs ~3.6 KiB of heap per
/// part, and more than two peers leaving between two passes is rare (a peer whose last
/// frames are lost is still found gone by the next scan).
const EXPIRED_CONNECTIONS: usize = 2;

fn service_name(s: &str) -> Result<ServiceName, String> {
    ServiceName::new(s).map_err(|e| format!("invalid service name {s}: {e:?}"))
}

impl Inbox {
    /// Creates the iceoryx2 node and the inbox of link `id`.
    pub(super) fn create(
        options: &ShmLinkOptions,
        id: u64,
    ) -> Result<(Node, Inbox), ShmLinkOpenError> {
        let node = create_node(&options.service, id).map_err(|reason| ShmLinkOpenError::Node {
            link: options.name.clone(),
            reason,
        })?;
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
        let (svc, writers) = (&options.service, options.max_peers);
        let safe = create_part(&node, (svc, id, "safe"), false, SAFE_BUFFER, writers)
            .map_err(|e| inbox_err("safe", e))?;
        let fast = create_part(&node, (svc, id, "fast"), true, FAST_BUFFER, writers)
            .map_err(|e| inbox_err("fast", e))?;
        let bulk = create_part(&node, (svc, id, "bulk"), false, BULK_BUFFER, writers)
            .map_err(|e| inbox_err("bulk", e))?;
        let wake = create_wake(&node, (svc, id), options.wait, writers)
            .map_err(|(what, e)| inbox_err(what, e))?;
        let (listener, self_wake) = wake_ports(&wake).map_err(|(what, e)| inbox_err(what, e))?;
        let inbox = Inbox {
            reader: InboxReader {
                safe,
                fast,
                bulk,
                link: options.name.clone(),
            },
            listener,
            self_wake,
        };
        Ok((node, inbox))
    }
}

// iceoryx2's builders carry service configurations by value, tens of KiB each; every step
// below is kept out of line so that their stack frames follow one another rather than add up
// in one caller's frame (the control thread's stack: ~220 -> ~176 KiB resident).

/// The iceoryx2 node of inbox `id` of `service`.
#[inline(never)]
fn create_node(service: &str, id: u64) -> Result<Node, String> {
    // iceoryx2 logs to stderr; keep it to errors unless the user asks for more.
    iceoryx2::prelude::set_log_level_from_env_or(LogLevel::Error);
    let name = NodeName::new(&format!("{}{id:016x}", node_prefix(service)))
        .map_err(|e| format!("{e:?}"))?;
    // iceoryx2's defaults (and any iceoryx2 config file), with a subscriber's table of
    // departed publishers' connections cut from 128 entries to EXPIRED_CONNECTIONS.
    let mut config = iceoryx2::config::Config::global_config().clone();
    config
        .defaults
        .publish_subscribe
        .subscriber_expired_connection_buffer = EXPIRED_CONNECTIONS;
    NodeBuilder::new()
        .config(&config)
        .name(&name)
        // The process owns its signals (tokio's ctrl_c); iceoryx2 must not take them.
        .signal_handling_mode(SignalHandlingMode::Disabled)
        .create::<Ipc>()
        .map_err(|e| format!("{e:?}"))
}

/// Creates part `part` of inbox `id` of `service` and its subscriber: a writer per peer (a
/// restarted peer removed its dead predecessor's when it started); the nodes are theirs and
/// ours.
#[inline(never)]
fn create_part(
    node: &Node,
    (service, id, part): (&str, u64, &str),
    overflow: bool,
    buffer: usize,
    writers: usize,
) -> Result<Sub, String> {
    let name = service_name(&inbox_name(service, id, part))?;
    let created = create_part_service(node, &name, part, overflow, buffer, writers)?;
    create_subscriber(&created, buffer)
}

#[inline(never)]
fn create_part_service(
    node: &Node,
    name: &ServiceName,
    part: &str,
    overflow: bool,
    buffer: usize,
    writers: usize,
) -> Result<PubSubService, String> {
    // The service only records its settings; the memory is the writers', allocated when each
    // opens a publisher.
    // The bulk part's reader may hold LENT_SAMPLES lent to its node besides the ones it
    // reads. Set by the creator alone: a writer's segment follows the service's setting, and
    // a writer asking for it would not open an inbox made with another.
    let borrowed = if part == "bulk" {
        LENT_SAMPLES + READER_BORROWS
    } else {
        READER_BORROWS
    };
    pubsub_builder(node, name, overflow, buffer)
        .subscriber_max_borrowed_samples(borrowed)
        .max_publishers(writers)
        .max_nodes(writers + 1)
        .create()
        .map_err(|e| format!("{e:?}"))
}

#[inline(never)]
fn create_subscriber(service: &PubSubService, buffer: usize) -> Result<Sub, String> {
    service
        .subscriber_builder()
        .buffer_size(buffer)
        .create()
        .map_err(|e| format!("{e:?}"))
}

/// Creates the wake event of inbox `id` of `service`: its attributes tell writers how the
/// reader `wait`s. On failure, says what failed and why.
#[inline(never)]
fn create_wake(
    node: &Node,
    (service, id): (&str, u64),
    wait: ShmWait,
    writers: usize,
) -> Result<EventService, (&'static str, String)> {
    let name = service_name(&inbox_name(service, id, "wake")).map_err(|e| ("wake", e))?;
    let attributes = wait_attribute(wait).map_err(|e| ("wake attribute", e))?;
    event_builder(node, &name)
        // ... and our own notifier (the receive task's wake-up).
        .max_notifiers(writers + 1)
        .max_nodes(writers + 1)
        .create_with_attributes(&attributes)
        .map_err(|e| ("wake", format!("{e:?}")))
}

/// The reader's ports of its wake event: the listener and its own notifier.
#[inline(never)]
fn wake_ports(wake: &EventService) -> Result<(Listener<Ipc>, SelfWake), (&'static str, String)> {
    let listener = wake
        .listener_builder()
        .create()
        .map_err(|e| ("wake listener", format!("{e:?}")))?;
    let notifier = wake
        .notifier_builder()
        .create()
        .map_err(|e| ("wake notifier", format!("{e:?}")))?;
    Ok((listener, notifier))
}

/// An inbox part's service as its creator and its writers both describe it. Its capacities
/// (`max_publishers`, `max_nodes`) are the creator's `maxPeers` alone: a writer opening it
/// requires none, so nodes with different `maxPeers` meet.
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
}

/// Samples of one part the reader holds at once while reading (iceoryx2's default).
const READER_BORROWS: usize = 2;

fn wait_key() -> Result<AttributeKey, String> {
    AttributeKey::try_from(WAIT_ATTRIBUTE).map_err(|e| format!("{e:?}"))
}

fn wait_attribute(wait: ShmWait) -> Result<AttributeSpecifier, String> {
    let value = AttributeValue::try_from(wait.as_str()).map_err(|e| format!("{e:?}"))?;
    AttributeSpecifier::new()
        .define(&wait_key()?, &value)
        .map_err(|e| format!("{e:?}"))
}

/// The wake event as its creator and its writers both describe it (capacities as for
/// [`pubsub_builder`]).
fn event_builder<'a>(
    node: &'a IoxNode<Ipc>,
    name: &'a ServiceName,
) -> iceoryx2::service::builder::event::Builder<Ipc> {
    node.service_builder(name).event().max_listeners(1)
}

/// Why a peer's inbox could not be opened for writing.
#[derive(Debug)]
pub(super) enum OpenError {
    /// It admits no more writers: its `maxPeers` are taken.
    Full(String),
    /// Anything else (e.g. it is still being created).
    Other(String),
}

impl std::fmt::Display for OpenError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            OpenError::Full(what) => write!(
                f,
                "{what}: the peer's inbox admits no more writers (raise maxPeers in its <shm>)"
            ),
            OpenError::Other(what) => f.write_str(what),
        }
    }
}

impl OpenError {
    /// What iceoryx2 said (`error`) when opening `what`: [`OpenError::Full`] if `full`.
    fn from_iceoryx2(what: &str, error: impl std::fmt::Debug, full: bool) -> Self {
        let what = format!("{what}: {error:?}");
        if full {
            OpenError::Full(what)
        } else {
            OpenError::Other(what)
        }
    }
}

impl From<String> for OpenError {
    fn from(what: String) -> Self {
        OpenError::Other(what)
    }
}

/// Opens a publisher on part `part` of peer `id`'s inbox, its samples up to `max` bytes.
fn open_pub(
    node: &IoxNode<Ipc>,
    service: &str,
    id: u64,
    (part, overflow, buffer, max): (&str, bool, usize, usize),
) -> Result<Pub, OpenError> {
    let n = service_name(&inbox_name(service, id, part))?;
    let s = open_part_service(node, &n, part, overflow, buffer)?;
    create_publisher(&s, part, max)
}

#[inline(never)]
fn open_part_service(
    node: &Node,
    name: &ServiceName,
    part: &str,
    overflow: bool,
    buffer: usize,
) -> Result<PubSubService, OpenError> {
    use iceoryx2::service::builder::publish_subscribe::PublishSubscribeOpenError;
    pubsub_builder(node, name, overflow, buffer)
        .open()
        .map_err(|e| {
            let full = matches!(e, PublishSubscribeOpenError::ExceedsMaxNumberOfNodes);
            OpenError::from_iceoryx2(part, e, full)
        })
}

#[inline(never)]
fn create_publisher(service: &PubSubService, part: &str, max: usize) -> Result<Pub, OpenError> {
    use iceoryx2::port::publisher::PublisherCreateError;
    // The bulk part's samples grow (to the next power of two) when a whole large message is
    // loaned into one: the segment is made only by a writer of large messages.
    let (strategy, loans) = if part == "bulk" {
        (AllocationStrategy::PowerOfTwo, BULK_LOANS)
    } else {
        (AllocationStrategy::Static, 2)
    };
    service
        .publisher_builder()
        // Room for a seal whether or not this node has a key (a sealed frame is that much
        // longer than the limits the senders split messages by).
        .initial_max_slice_len(max + Profile::SHM.overhead())
        .allocation_strategy(strategy)
        .max_loaned_samples(loans)
        .backpressure_strategy(BackpressureStrategy::DiscardData)
        .create()
        .map_err(|e| {
            let full = matches!(e, PublisherCreateError::ExceedsMaxSupportedPublishers);
            OpenError::from_iceoryx2(&format!("{part} publisher"), e, full)
        })
}

/// Opens the writing side of peer `id`'s bulk inbox.
pub(super) fn open_bulk(node: &Node, service: &str, id: u64) -> Result<Pub, OpenError> {
    open_pub(node, service, id, ("bulk", false, BULK_BUFFER, BULK_MAX))
}

/// Opens the writing side of peer `id`'s inbox (it must exist).
pub(super) fn open_conn(node: &IoxNode<Ipc>, service: &str, id: u64) -> Result<Conn, OpenError> {
    let safe = open_pub(node, service, id, ("safe", false, SAFE_BUFFER, FRAME_MAX))?;
    let fast = open_pub(node, service, id, ("fast", true, FAST_BUFFER, FRAME_MAX))?;
    let (wake, spins) = open_wake(node, service, id)?;
    Ok(Conn {
        fast,
        safe,
        wake,
        spins,
    })
}

/// Opens peer `id`'s wake event and a notifier on it; says whether the peer spins.
#[inline(never)]
fn open_wake(node: &Node, service: &str, id: u64) -> Result<(Notifier<Ipc>, bool), OpenError> {
    use iceoryx2::port::notifier::NotifierCreateError;
    use iceoryx2::service::builder::event::EventOpenError;
    let wn = service_name(&inbox_name(service, id, "wake"))?;
    let wake = event_builder(node, &wn).open().map_err(|e| {
        let full = matches!(e, EventOpenError::ExceedsMaxNumberOfNodes);
        OpenError::from_iceoryx2("wake", e, full)
    })?;
    // An inbox without the attribute (or with a mode we do not know) is woken on every send.
    let spins = wake
        .attributes()
        .key_value(&wait_key()?, 0)
        .is_some_and(|v| v == ShmWait::Spin.as_str());
    let notifier = wake.notifier_builder().create().map_err(|e| {
        let full = matches!(e, NotifierCreateError::ExceedsMaxSupportedNotifiers);
        OpenError::from_iceoryx2("wake notifier", e, full)
    })?;
    Ok((notifier, spins))
}

/// Writes one frame into `publisher`. Returns whether the inbox took it (a non-overflowing
/// inbox refuses frames while its buffer is full).
/// With a `sealer`, the frame is sealed in place (see [`crate::link::auth`]).
pub(super) fn put(
    publisher: &Pub,
    (kind, sender, session, seq): (u8, u64, u32, u64),
    body: &[u8],
    sealer: Option<&Sealer>,
) -> bool {
    let h = frame::header_len(kind);
    let seal = sealer.map_or(0, Sealer::overhead);
    let Ok(mut sample) = publisher.loan_slice(h + body.len() + seal) else {
        return false;
    };
    let out = sample.payload_mut();
    frame::write_header(out, kind, sender, session, seq);
    out[h..h + body.len()].copy_from_slice(body);
    if let Some(s) = sealer {
        out[0] |= frame::SEALED_KIND;
        s.seal_slice(out, h + body.len());
    }
    matches!(sample.send(), Ok(n) if n > 0)
}

/// A bulk sample lent for one whole safe message to one peer (`Link::loan`): the message
/// is written in place, after room for the frame header, which is written (and the seal after
/// the message made) when it is sent ([`ShmLoan::send`]).
pub(crate) struct ShmLoan {
    sample: Option<LoanedSample>,
    /// The message's length.
    len: usize,
    /// Message bytes written from its start.
    written: usize,
    /// The peer whose inbox the sample is for.
    pub(super) peer: u64,
    /// The peer's loans not yet sent or dropped (this one counted while it lives).
    loans: Arc<AtomicUsize>,
}

impl Drop for ShmLoan {
    fn drop(&mut self) {
        self.sample = None;
        self.loans.fetch_sub(1, Ordering::Relaxed);
    }
}

enum LoanedSample {
    Uninit(iceoryx2::sample_mut_uninit::SampleMutUninit<Ipc, [MaybeUninit<u8>], ()>),
    Init(iceoryx2::sample_mut::SampleMut<Ipc, [u8], ()>),
}

impl ShmLoan {
    /// Loans from `publisher` (a peer's bulk inbox) a sample for a message of `len` bytes,
    /// its frame header and the seal of `sealer`, counted in `loans`. `None` when it has none
    /// to lend, or `loans` already holds all but the one the peer's copied fragments need.
    pub(super) fn new(
        publisher: &Pub,
        (len, peer): (usize, u64),
        sealer: Option<&Sealer>,
        loans: &Arc<AtomicUsize>,
    ) -> Option<Self> {
        if loans.fetch_add(1, Ordering::Relaxed) >= BULK_LOANS - 1 {
            loans.fetch_sub(1, Ordering::Relaxed);
            return None;
        }
        let loan = |sample| ShmLoan {
            sample: Some(LoanedSample::Uninit(sample)),
            len,
            written: 0,
            peer,
            loans: loans.clone(),
        };
        let total = frame::SEQUENCED + len + sealer.map_or(0, Sealer::overhead);
        // On failure no ShmLoan was made: its count is given back here.
        match publisher.loan_slice_uninit(total) {
            Ok(sample) => Some(loan(sample)),
            Err(_) => {
                loans.fetch_sub(1, Ordering::Relaxed);
                None
            }
        }
    }

    /// The whole sample, initialised.
    fn sample(&mut self) -> &mut iceoryx2::sample_mut::SampleMut<Ipc, [u8], ()> {
        if let Some(LoanedSample::Uninit(mut s)) = self
            .sample
            .take_if(|s| matches!(s, LoanedSample::Uninit(_)))
        {
            let (header, rest) = s.payload_mut().split_at_mut(frame::SEQUENCED);
            for b in header.iter_mut().chain(&mut rest[self.written..]) {
                b.write(0);
            }
            // SAFETY: every byte of the sample is initialised: the message's first `written`
            // by `append` (which counts only what it wrote, from the message's start), every
            // other one just above.
            #[allow(unsafe_code)]
            let s = unsafe { s.assume_init() };
            self.written = self.len;
            self.sample = Some(LoanedSample::Init(s));
        }
        match &mut self.sample {
            Some(LoanedSample::Init(s)) => s,
            // Only `sample` takes it, and it puts an initialised one back.
            _ => unreachable!("a loaned sample is always present"),
        }
    }

    /// Writes the frame header (`kind`, `sender`, `session`, `seq`), seals the frame with
    /// `sealer` and sends it. Returns whether the inbox took it (the sample is spent either way).
    pub(super) fn send(
        mut self,
        (kind, sender, session, seq): (u8, u64, u32, u64),
        sealer: Option<&Sealer>,
    ) -> bool {
        let end = frame::SEQUENCED + self.len;
        let sample = self.sample();
        let out = sample.payload_mut();
        frame::write_header(out, kind, sender, session, seq);
        if let Some(s) = sealer {
            out[0] |= frame::SEALED_KIND;
            s.seal_slice(out, end);
        }
        let Some(LoanedSample::Init(s)) = self.sample.take() else {
            return false;
        };
        matches!(s.send(), Ok(n) if n > 0)
    }
}

impl crate::link::LinkLoan for ShmLoan {
    fn len(&self) -> usize {
        self.len
    }

    fn written(&self) -> usize {
        self.written
    }

    fn append(&mut self, bytes: &[u8]) -> usize {
        let n = bytes.len().min(self.len - self.written);
        let at = frame::SEQUENCED + self.written;
        match &mut self.sample {
            Some(LoanedSample::Uninit(s)) => {
                for (d, b) in s.payload_mut()[at..at + n].iter_mut().zip(bytes) {
                    d.write(*b);
                }
            }
            Some(LoanedSample::Init(s)) => s.payload_mut()[at..at + n].copy_from_slice(&bytes[..n]),
            None => return 0,
        }
        self.written += n;
        n
    }

    fn init(&mut self) -> &mut [u8] {
        let len = self.len;
        &mut self.sample().payload_mut()[frame::SEQUENCED..frame::SEQUENCED + len]
    }

    fn into_any(self: Box<Self>) -> Box<dyn std::any::Any + Send> {
        self
    }
}

/// The wake listener as tokio's reactor sees it: its socket turns readable when a writer
/// notifies.
///
/// With [`ShmLoan`]'s, the only `unsafe` of the crate (the workspace denies it elsewhere): iceoryx2 hands out the
/// listener's descriptor and tokio registers one only through `unsafe` functions, because
/// neither can check that a raw descriptor stays open. Here it does: the listener that owns it
/// lives inside this wrapper, which the `AsyncFd` owns until it deregisters the descriptor.
pub(super) struct WakeFd(Listener<Ipc>);

impl WakeFd {
    /// Registers `listener`'s socket with the current tokio reactor for readability.
    #[allow(unsafe_code)]
    pub(super) fn watch(
        listener: Listener<Ipc>,
    ) -> std::io::Result<tokio::io::unix::AsyncFd<WakeFd>> {
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

impl WakeFd {
    /// Consumes the pending notifications; returns how many there were.
    pub(super) fn consume(&self) -> Result<u64, String> {
        self.0.try_wait(|_| {}).map_err(|e| format!("{e:?}"))
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

/// A dead node's leftovers, found by [`list_nodes`].
pub(super) struct DeadNode(iceoryx2::node::DeadNodeView<Ipc>);

impl DeadNode {
    /// Removes what the dead node left behind.
    pub(super) fn remove_stale(self) -> Result<(), String> {
        self.0
            .try_remove_stale_resources()
            .map_err(|e| format!("{e:?}"))
    }
}

/// The host's iceoryx2 nodes of one service.
pub(super) struct Listing {
    /// Ids of live inboxes (ours included).
    pub(super) alive: Vec<u64>,
    /// Dead nodes and their ids.
    pub(super) dead: Vec<(u64, DeadNode)>,
    /// Listing stopped early: what is listed is what was seen before.
    pub(super) error: Option<String>,
}

/// Lists the host's iceoryx2 nodes of `service`.
pub(super) fn list_nodes(node: &Node, service: &str) -> Listing {
    let prefix = node_prefix(service);
    let mut alive = Vec::new();
    let mut dead = Vec::new();
    let listed = IoxNode::<Ipc>::list(node.config(), |state| {
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
                    dead.push((id, DeadNode(v)));
                }
            }
            NodeState::Inaccessible(_) | NodeState::Undefined(_) => {}
        }
        CallbackProgression::Continue
    });
    Listing {
        alive,
        dead,
        error: listed.err().map(|e| format!("{e:?}")),
    }
}
