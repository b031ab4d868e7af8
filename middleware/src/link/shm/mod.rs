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
//!   therefore holds back only safe traffic towards itself. Small safe messages that queue
//!   while `SAFE_FRAMES_IN_FLIGHT` (4) frames are unacknowledged go as one pack frame (written
//!   on the acknowledgement, or once a frame's worth waits): one sample for many messages.
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
//! [`ShmWait::Spin`] a task of the link polls the inbox, yielding its tokio worker between
//! polls, and writers never notify.
//!
//! Threads: sending is inline in the caller (a loan, a copy, an atomic store and maybe the
//! notification: iceoryx2's non-blocking calls); receiving never blocks. Everything that may
//! wait on the file system (creating the inbox, opening peers' inboxes, listing nodes, cleaning
//! up dead ones) runs on one control thread per link, never on a tokio worker.
//!
//! Payloads are copied once into the loaned shared-memory sample and read in place by the
//! receiver (a message that fits one frame or bulk sample reaches the node as a slice of shared
//! memory).
//!
//! Files: `frame` (the frame format), `inbox` (everything iceoryx2: creating and opening
//! inboxes, reading samples, listing nodes, the wake event), `tx` and `rx` (the sending and
//! receiving machines: pure, over small writer/reader traits and `now`, tested on the simulated
//! inboxes of `sim`), `control` (the control thread), and this file: the [`Link`] impl that ties
//! them together, and the receive task.

use std::collections::HashMap;
use std::sync::atomic::{AtomicBool, AtomicUsize, Ordering};
use std::sync::{mpsc, Arc, Mutex};
use std::time::{Duration, Instant};

use tokio_util::sync::CancellationToken;
use tokio_util::task::TaskTracker;

use super::auth::{self, AuthReject, LinkSecurity, Opener, Profile, Sealer};
use super::completion::acknowledge_all;
use super::{
    Link, LinkCounters, LinkHandler, LinkLoan, LinkSendError, LinkStats, Outgoing, PeerAddr,
    SafeCompletion,
};
use crate::sync::lock;
use control::Ctl;
use frame::Part;
use inbox::{Conn, Inbox, InboxReader, InboxSample, Pub, SelfWake, ShmLoan, WakeFd};
use rx::{AckSent, Receiver, RxIo};
use tx::{InboxWriter, PeerTx};

// Defined outside this module so configurations name it in builds without the `shm` feature.
pub use super::ShmWait;

mod control;
mod frame;
#[cfg(feature = "fuzzing")]
pub(crate) mod fuzz;
mod inbox;
mod rx;
#[cfg(test)]
mod sim;
mod tx;

/// Largest sample written to the fast and safe inboxes, header included. Longer messages go
/// through the bulk inbox (fast ones riding the safe path).
pub const FRAME_MAX: usize = 8192;
/// Largest sample written to a bulk inbox, header included; longer messages are cut into pieces
/// of this size.
pub const BULK_MAX: usize = 256 << 10;
/// Content bytes of a file chunk sent to a peer on this link: one chunk, its message header and
/// the frame header fit one bulk sample.
pub const FILE_CHUNK: usize = BULK_MAX - 1024;
/// Bulk samples a receiver lends to its node (and the application: a [`crate::Blob`] it
/// keeps) at once; past that, large messages are copied out of shared memory. Each one its
/// writers' bulk segments make room for.
pub const LENT_SAMPLES: usize = 4;
/// Largest message written in place in a peer's bulk inbox (`Link::loan`; larger ones go as
/// copies, in pieces). Every sample of a writer's bulk segment takes the size of its largest
/// one, rounded up to a power of two, and the segment has 18 (the inbox's 8, 6 its reader may
/// hold, 4 loans): frames of up to 4 MiB cost a writer 144 MiB of shared memory per peer, of up
/// to 8 MiB 288 MiB.
pub const LOAN_MAX: usize = 8 << 20;
/// Bulk samples a writer may have loaned from one peer's bulk inbox at once: one it writes a
/// fragment into, the rest lent to the node for messages written in place (`Link::loan`; a
/// raised one keeps its sample until it is written).
const BULK_LOANS: usize = 4;
/// Frames a safe inbox buffers per writer before refusing more.
const SAFE_BUFFER: usize = 128;
/// Safe frames a writer leaves unacknowledged before small messages wait to be packed (see
/// [`tx::PeerTx::send_safe`]). Bursts of up to this many go out at once; longer ones as packs.
const SAFE_FRAMES_IN_FLIGHT: usize = 4;
/// Samples a bulk inbox buffers per writer before refusing more. With [`BULK_MAX`] this bounds a
/// writer's bulk segment to a few MiB, created only once it first sends something large.
const BULK_BUFFER: usize = 8;
/// Frames a fast inbox buffers per writer before overwriting the oldest.
const FAST_BUFFER: usize = 64;
/// Fast messages kept for a peer whose inbox is not open yet, or large fast messages queued on
/// the safe path; beyond it the oldest is dropped.
const MAX_FAST_BACKLOG: usize = 1024;
/// A reassembled message larger than this is dropped as corrupt.
const MAX_MESSAGE: usize = 256 << 20;
/// How often the receive thread retries refused frames and acknowledgements.
const RETRY: Duration = Duration::from_millis(1);
/// Samples taken from one inbox buffer per pass, so acknowledgements flow during bursts.
const PASS_BUDGET: usize = 512;
/// Safe messages (or fragments) taken per pass: a pack carries up to a few hundred, and the
/// tasks they woke (the subscribers, the node telling peers it is behind) run between passes.
const PASS_MESSAGES: usize = 2048;
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
    /// Most peers (same-host links of the same `service`) this link exchanges with: its inbox
    /// admits that many writers and it writes to that many inboxes. Each costs ~11 KiB of
    /// memory from the start (iceoryx2's connection entries).
    pub max_peers: usize,
    /// The domain key: when set, every frame is sealed and only sealed ones are taken (see
    /// [`crate::link::auth`]).
    pub security: Option<LinkSecurity>,
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
    /// The control thread could not be started, or the wake event not watched.
    #[error("link {link}: cannot start the control thread or watch the wake event: {source}")]
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

/// One peer: the writing side of its inbox and what this link sends it.
struct Peer {
    id: u64,
    conn: Option<Conn>,
    /// The peer's bulk inbox, opened with the first large message.
    bulk: Option<Pub>,
    /// Samples of `bulk` lent for messages written in place, not yet sent or dropped: at
    /// most all but one of [`BULK_LOANS`], so copied fragments always find one.
    loans: Arc<AtomicUsize>,
    tx: PeerTx,
}

/// A peer's inbox as the sending machine sees it.
struct PeerWriter<'a> {
    link: &'a ShmLink,
    id: u64,
    conn: Option<&'a Conn>,
    bulk: Option<&'a Pub>,
}

impl InboxWriter for PeerWriter<'_> {
    fn is_open(&self) -> bool {
        self.conn.is_some()
    }

    fn put(&mut self, part: Part, kind: u8, session: u32, seq: u64, body: &[u8]) -> bool {
        let publisher = match part {
            Part::Bulk => self.bulk,
            Part::Fast => self.conn.map(|c| &c.fast),
            Part::Safe => self.conn.map(|c| &c.safe),
        };
        publisher.is_some_and(|p| {
            inbox::put(
                p,
                (kind, self.link.id, session, seq),
                body,
                self.link.sealer.as_ref(),
            )
        })
    }

    fn wake(&mut self) {
        if let Some(c) = self.conn {
            c.wake();
        }
    }

    fn put_loan(&mut self, loan: Box<dyn LinkLoan>, session: u32, seq: u64) -> bool {
        let Ok(loan) = loan.into_any().downcast::<ShmLoan>() else {
            return false;
        };
        // A sample of this peer's bulk inbox (`Link::send_loan` checked), open since.
        loan.peer == self.id
            && loan.send(
                (frame::BULK_DATA, self.link.id, session, seq),
                self.link.sealer.as_ref(),
            )
    }

    fn open_bulk(&mut self) {
        self.link.request(Ctl::OpenBulk(self.id));
    }
}

/// The shared-memory link.
pub struct ShmLink {
    index: usize,
    options: ShmLinkOptions,
    id: u64,
    peers: Mutex<HashMap<u64, Arc<Mutex<Peer>>>>,
    /// Requests to the control thread.
    ctl: Mutex<mpsc::Sender<Ctl>>,
    /// Peers whose receive state the receiver must forget (they were closed), taken at the
    /// start of its next pass, before any later frame of theirs.
    forget: Mutex<mpsc::Sender<u64>>,
    /// Wakes our own receive thread (control requests, shutdown).
    self_wake: SelfWake,
    stop: AtomicBool,
    handler: Arc<dyn LinkHandler>,
    counters: LinkCounters,
    /// Seals every frame written when the node has a key.
    sealer: Option<Sealer>,
    /// Checks every frame read when the node has a key (the receive thread's alone).
    opener: Option<Mutex<Opener>>,
    /// Bulk samples lent to the node (and its application) and not yet released.
    lent: Arc<AtomicUsize>,
}

/// Sender streams (a writer's fast, safe and bulk parts) a shared-memory link remembers for
/// replay detection.
const MAX_REPLAY_WINDOWS: usize = 1024;

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
        let (ctl_tx, ctl_rx) = mpsc::channel();
        let name = options.name.clone();
        let interrupted = || ShmLinkOpenError::Interrupted { link: name.clone() };
        let thread_err = |source| ShmLinkOpenError::Thread {
            link: name.clone(),
            source,
        };
        // Creating files and shared memory may wait on the file system: off the workers.
        let control = control::start(&options, id, ctl_rx).map_err(thread_err)?;
        let inbox = control.inbox.await.map_err(|_| interrupted())??;
        let Inbox {
            reader,
            listener,
            self_wake,
        } = inbox;
        let (forget_tx, forget_rx) = mpsc::channel();
        let wait = options.wait;
        let sealer = options
            .security
            .as_ref()
            .map(|s| Sealer::new(&s.key, Profile::SHM));
        let opener = options
            .security
            .as_ref()
            .map(|s| Mutex::new(Opener::new(&s.key, Profile::SHM, MAX_REPLAY_WINDOWS)));
        let link = Arc::new(ShmLink {
            sealer,
            opener,
            index,
            options,
            id,
            peers: Mutex::new(HashMap::new()),
            ctl: Mutex::new(ctl_tx),
            forget: Mutex::new(forget_tx),
            self_wake,
            stop: AtomicBool::new(false),
            handler,
            counters: LinkCounters::default(),
            lent: Arc::default(),
        });
        // Connect to the nodes already here before the node announces itself.
        let _ = control.serve.send(link.clone());
        control.scanned.await.map_err(|_| interrupted())?;
        let control_ended = control.ended;
        let rx = RxDriver {
            link: link.clone(),
            reader,
            forget: forget_rx,
            rx: Receiver::new(Instant::now(), 2 * link.options.max_peers),
            run: HeldRun::default(),
        };
        let (receiver_tx, receiver_rx) = tokio::sync::oneshot::channel::<()>();
        match wait {
            ShmWait::Event => {
                // Readiness of the wake event's socket, seen by tokio's reactor: the receive
                // pass then runs on the worker that woke, which is also the one the delivered
                // message wakes next (one thread switch per message, as in plain iceoryx2).
                let fd = WakeFd::watch(listener).map_err(thread_err)?;
                let cancel = cancel.clone();
                crate::sync::spawn_tracked(tasks, async move {
                    rx.drive_events(fd, cancel).await;
                    drop(receiver_tx);
                });
            }
            ShmWait::Spin => {
                // A task that polls and yields, so the worker running it never parks: waking
                // the task a message is for is a push onto a run queue, not a thread wake-up.
                drop(listener);
                let cancel = cancel.clone();
                crate::sync::spawn_tracked(tasks, async move {
                    rx.drive_polling(cancel).await;
                    drop(receiver_tx);
                });
            }
        }
        let l = link.clone();
        crate::sync::spawn_tracked(tasks, async move {
            cancel.cancelled().await;
            l.stop.store(true, Ordering::SeqCst);
            l.wake_self();
            l.request(Ctl::Stop);
            let _ = receiver_rx.await;
            let _ = control_ended.await;
            let peers: Vec<Arc<Mutex<Peer>>> = lock(&l.peers).drain().map(|(_, p)| p).collect();
            for p in peers {
                lock(&p).tx.fail_all(&LinkSendError::Shutdown);
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

    fn peer(&self, id: u64, create: bool) -> Option<Arc<Mutex<Peer>>> {
        let mut peers = lock(&self.peers);
        if let Some(p) = peers.get(&id) {
            return Some(p.clone());
        }
        if !create || peers.len() >= self.options.max_peers || id == self.id {
            return None;
        }
        let p = Arc::new(Mutex::new(Peer {
            id,
            conn: None,
            bulk: None,
            loans: Arc::default(),
            tx: PeerTx::new(rand::random()),
        }));
        peers.insert(id, p.clone());
        Some(p)
    }

    /// Runs `f` on a peer's sending machine with the peer's inbox as its writer.
    fn with_tx<R>(
        &self,
        st: &mut Peer,
        f: impl FnOnce(&mut PeerTx, &mut PeerWriter<'_>, &LinkCounters) -> R,
    ) -> R {
        let Peer {
            id, conn, bulk, tx, ..
        } = st;
        let mut w = PeerWriter {
            link: self,
            id: *id,
            conn: conn.as_ref(),
            bulk: bulk.as_ref(),
        };
        f(tx, &mut w, &self.counters)
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
            return out.refuse(to);
        };
        let Some(p) = self.peer(id, true) else {
            return out.refuse(to);
        };
        let mut st = lock(&p);
        let unopened = st.conn.is_none();
        self.with_tx(&mut st, |tx, w, c| match out {
            Outgoing::Fast { coalesce, msg } => tx.send_fast(w, c, coalesce, msg),
            Outgoing::Safe { msg, done } => tx.send_safe(w, c, msg, done),
        });
        drop(st);
        if unopened {
            self.request(Ctl::Open(id));
        }
    }

    fn announce(&self, msg: &[u8]) {
        if msg.len() + frame::BASE > FRAME_MAX {
            return;
        }
        let peers: Vec<Arc<Mutex<Peer>>> = lock(&self.peers).values().cloned().collect();
        for p in peers {
            let st = lock(&p);
            if let Some(c) = &st.conn {
                if inbox::put(
                    &c.fast,
                    (frame::ANNOUNCE, self.id, 0, 0),
                    msg,
                    self.sealer.as_ref(),
                ) {
                    self.counters.count_out(frame::BASE + msg.len());
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
            lock(&p)
                .tx
                .fail_all(&LinkSendError::PeerClosed(to.to_string()));
        }
        let _ = lock(&self.forget).send(id);
    }

    fn stats(&self) -> LinkStats {
        // Shared memory has no acknowledgements to time and hands messages over at once.
        self.counters.stats(LinkStats::default())
    }

    fn file_chunk(&self) -> usize {
        FILE_CHUNK
    }

    /// A sample of the peer's bulk inbox, once it is open (a first loan asks for it to be
    /// opened and is refused: that message goes as a copy).
    fn loan(&self, to: PeerAddr, len: usize) -> Option<Box<dyn LinkLoan>> {
        // A message that fits a frame gains nothing, and a variable value would go on the safe
        // path where the next one, not lent, goes fast: it could be overtaken.
        let PeerAddr::Shm(id) = to else {
            return None;
        };
        if len + frame::SEQUENCED <= FRAME_MAX || len > LOAN_MAX {
            return None;
        }
        let p = self.peer(id, false)?;
        let mut st = lock(&p);
        st.conn.as_ref()?;
        if let Some(bulk) = &st.bulk {
            return ShmLoan::new(bulk, (len, id), self.sealer.as_ref(), &st.loans)
                .map(|l| Box::new(l) as Box<dyn LinkLoan>);
        }
        self.with_tx(&mut st, |tx, w, _| tx.want_bulk(w));
        None
    }

    fn send_loan(&self, to: PeerAddr, loan: Box<dyn LinkLoan>, done: Option<SafeCompletion>) {
        let peer = match to {
            PeerAddr::Shm(id) => self.peer(id, false),
            _ => None,
        };
        let Some(p) = peer else {
            return super::refuse_done(done, to);
        };
        let mut st = lock(&p);
        self.with_tx(&mut st, |tx, w, c| tx.send_loan(w, c, loan, done));
    }
}

/// The receiving machine's I/O on a live link: the inbox's subscribers, the node's handler,
/// and the link's peers for acknowledgements and retries.
struct LinkRx<'a> {
    link: &'a ShmLink,
    reader: &'a mut InboxReader,
    /// In-order messages of this pass not yet handed to the node, all from one sender: they
    /// go as one run ([`crate::link::LinkHandler::on_messages`]), as a UDP datagram's do.
    run: &'a mut HeldRun,
}

/// Messages held for one run: their sender, their bytes end to end, and where each ends.
#[derive(Default)]
struct HeldRun {
    from: Option<u64>,
    bytes: Vec<u8>,
    ends: Vec<usize>,
}

/// Messages held for one run at most; a longer pass hands them on in several.
const RUN_MAX: usize = 256;
/// Messages longer than this are handed on at once (after the run held before them) instead
/// of being copied into the run.
const RUN_MESSAGE_MAX: usize = 4096;

impl LinkRx<'_> {
    /// Hands the held run to the node.
    fn flush(&mut self) {
        let Some(from) = self.run.from.take() else {
            return;
        };
        let mut start = 0;
        let msgs: Vec<&[u8]> = self
            .run
            .ends
            .iter()
            .map(|&end| {
                let m = &self.run.bytes[start..end];
                start = end;
                m
            })
            .collect();
        let l = self.link;
        l.handler.on_messages(l.index, PeerAddr::Shm(from), &msgs);
        self.run.bytes.clear();
        self.run.ends.clear();
    }
}

/// A sample whose seal (if the link has a key) was checked: it reads as the frame without it.
struct Opened(InboxSample, usize);

/// A bulk sample lent to the node from `at` (a whole message): counted in the link's `lent`
/// until the last view of it is dropped, which returns it to its writer.
struct Lent {
    /// Always there until dropped (first, so the count never runs ahead of the samples held).
    sample: Option<Opened>,
    at: usize,
    lent: Arc<AtomicUsize>,
}

impl AsRef<[u8]> for Lent {
    fn as_ref(&self) -> &[u8] {
        self.sample.as_ref().map_or(&[], |s| &s.as_ref()[self.at..])
    }
}

impl Drop for Lent {
    fn drop(&mut self) {
        self.sample = None;
        self.lent.fetch_sub(1, Ordering::Relaxed);
    }
}

impl AsRef<[u8]> for Opened {
    fn as_ref(&self) -> &[u8] {
        &self.0.as_ref()[..self.1]
    }
}

impl RxIo for LinkRx<'_> {
    type Sample = Opened;

    fn take(&mut self, part: Part) -> Option<Opened> {
        loop {
            let sample = self.reader.take(part)?;
            let bytes = sample.as_ref();
            let sealed = bytes.first().is_some_and(|k| k & frame::SEALED_KIND != 0);
            let Some(opener) = &self.link.opener else {
                if sealed {
                    // A keyed node's frame: nothing here can check or read it.
                    self.link.counters.count_in(bytes.len());
                    self.link.counters.corrupt.fetch_add(1, Ordering::Relaxed);
                    continue;
                }
                let len = bytes.len();
                return Some(Opened(sample, len));
            };
            // The writer's id (inside what the tag covers) and the inbox part tell the
            // streams apart: each is written in order.
            let verified = match bytes.get(1..frame::BASE).filter(|_| sealed) {
                Some(id) => {
                    let mut b = [0u8; 8];
                    b.copy_from_slice(id);
                    let stream = u64::from_le_bytes(b).wrapping_mul(4) ^ part as u64;
                    lock(opener).verify(stream, bytes)
                }
                None => Err(AuthReject::Unsealed),
            };
            match verified {
                Ok(len) => return Some(Opened(sample, len)),
                Err(why) => {
                    let l = self.link;
                    l.counters.count_in(bytes.len());
                    let total = l.counters.count_reject(why);
                    auth::log_reject(&l.options.name, "shared memory", why, total);
                }
            }
        }
    }

    fn deliver(&mut self, from: u64, msg: &[u8]) {
        if self.run.from.is_some_and(|f| f != from) || msg.len() > RUN_MESSAGE_MAX {
            self.flush();
        }
        if msg.len() > RUN_MESSAGE_MAX {
            let l = self.link;
            l.handler.on_message(l.index, PeerAddr::Shm(from), msg);
            return;
        }
        self.run.from = Some(from);
        self.run.bytes.extend_from_slice(msg);
        self.run.ends.push(self.run.bytes.len());
        if self.run.ends.len() >= RUN_MAX {
            self.flush();
        }
    }

    /// A whole message in a bulk sample goes to the node as a view of the sample while fewer
    /// than [`LENT_SAMPLES`] are lent; beyond, as a copy (the writer's shared memory for this
    /// inbox is sized for that many held).
    fn deliver_sample(&mut self, from: u64, sample: Opened, at: usize) {
        let lent = &self.link.lent;
        if lent.fetch_add(1, Ordering::Relaxed) >= LENT_SAMPLES {
            lent.fetch_sub(1, Ordering::Relaxed);
            self.deliver(from, &sample.as_ref()[at..]);
            return;
        }
        self.flush();
        let msg = bytes::Bytes::from_owner(Lent {
            sample: Some(sample),
            at,
            lent: lent.clone(),
        });
        let l = self.link;
        l.handler.on_lent_message(l.index, PeerAddr::Shm(from), msg);
    }

    fn announce(&mut self, from: u64, msg: &[u8]) {
        self.flush();
        let l = self.link;
        l.handler.on_announce(l.index, PeerAddr::Shm(from), msg);
    }

    fn peer_reset(&mut self, from: u64) {
        self.flush();
        let l = self.link;
        l.handler.on_peer_reset(l.index, PeerAddr::Shm(from));
    }

    fn acked(&mut self, from: u64, session: u32, seq: u64) -> bool {
        let Some(p) = self.link.peer(from, false) else {
            return false;
        };
        let acked = lock(&p).tx.on_ack(session, seq);
        let Some(done) = acked else {
            return false;
        };
        acknowledge_all(done);
        true
    }

    fn send_ack(&mut self, from: u64, session: u32, seq: u64) -> AckSent {
        // What is acknowledged has been dispatched by the node first.
        self.flush();
        let Some(p) = self.link.peer(from, true) else {
            return AckSent::NoPeer;
        };
        let st = lock(&p);
        let Some(c) = &st.conn else {
            return AckSent::NotOpen;
        };
        if inbox::put(
            &c.safe,
            (frame::ACK, self.link.id, session, seq),
            &[],
            self.link.sealer.as_ref(),
        ) {
            c.wake();
            AckSent::Taken
        } else {
            AckSent::Refused
        }
    }

    fn request_open(&mut self, from: u64) {
        self.link.request(Ctl::Open(from));
    }

    fn retry_backlogs(&mut self, acked: &[u64], retry: bool) -> bool {
        let peers: Vec<(u64, Arc<Mutex<Peer>>)> = lock(&self.link.peers)
            .iter()
            .map(|(id, p)| (*id, p.clone()))
            .collect();
        let mut remaining = false;
        for (id, p) in peers {
            let mut st = lock(&p);
            if !st.tx.has_backlog() {
                continue;
            }
            if acked.contains(&id) || retry {
                self.link.with_tx(&mut st, |tx, w, c| tx.retry(w, c));
            }
            remaining |= st.tx.has_backlog() && st.conn.is_some();
        }
        remaining
    }
}

/// The receive task: drives the [`Receiver`] over the inbox, woken through the wake event
/// (`wait="event"`) or polling (`wait="spin"`); never blocks.
struct RxDriver {
    link: Arc<ShmLink>,
    reader: InboxReader,
    forget: mpsc::Receiver<u64>,
    rx: Receiver,
    /// Kept from pass to pass for its buffers (empty between passes).
    run: HeldRun,
}

impl RxDriver {
    /// One pass over the inbox (see [`Receiver::pass`]).
    fn pass(&mut self, look_at_backlogs: bool) -> (usize, bool) {
        while let Ok(id) = self.forget.try_recv() {
            self.rx.forget(id);
        }
        let link = self.link.clone();
        let mut io = LinkRx {
            link: &link,
            reader: &mut self.reader,
            run: &mut self.run,
        };
        let r = self
            .rx
            .pass(Instant::now(), look_at_backlogs, &mut io, &link.counters);
        io.flush();
        r
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
            match fd.get_ref().consume() {
                Ok(0) => {}
                Ok(_) => continue,
                Err(e) => {
                    tracing::warn!(link = %self.link.options.name, error = %e, "reading the shared-memory wake event failed");
                }
            }
            let retry = self.rx.retry_due();
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
}

#[cfg(test)]
mod tests;
