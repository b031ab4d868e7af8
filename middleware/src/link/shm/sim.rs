//! A simulated host for the shared-memory machines ([`super::tx`], [`super::rx`]): inboxes are
//! bounded queues with iceoryx2's per-writer buffers (a full safe or bulk buffer refuses, a
//! full fast buffer loses its oldest frame), the clock is a number the test advances, and
//! opening a bulk inbox is answered on the next step. No iceoryx2, no threads, no sleeps.

use std::collections::{HashMap, VecDeque};
use std::time::{Duration, Instant};

use tokio::sync::oneshot;

use super::frame::{self, Part};
use super::rx::{AckSent, Receiver, RxIo};
use super::tx::{InboxWriter, PeerTx};
use super::{BULK_BUFFER, FAST_BUFFER, SAFE_BUFFER};
use crate::link::{LinkCounters, LinkSendError};

/// A completion as a test holds it.
pub(super) type Done = oneshot::Receiver<Result<(), LinkSendError>>;

/// One part of an inbox: samples in the order written, each with its writer.
pub(super) struct SimPart {
    pub(super) q: VecDeque<(u64, Vec<u8>)>,
    /// Samples buffered per writer.
    cap: usize,
    /// Full: lose the writer's oldest sample (fast) instead of refusing the new one.
    overflow: bool,
}

impl SimPart {
    fn new(cap: usize, overflow: bool) -> Self {
        SimPart {
            q: VecDeque::new(),
            cap,
            overflow,
        }
    }

    fn push(&mut self, writer: u64, sample: Vec<u8>) -> bool {
        if self.q.iter().filter(|(w, _)| *w == writer).count() >= self.cap {
            if !self.overflow {
                return false;
            }
            if let Some(i) = self.q.iter().position(|(w, _)| *w == writer) {
                self.q.remove(i);
            }
        }
        self.q.push_back((writer, sample));
        true
    }

    /// Removes the first sample matching `pred` (a frame lost, or never written by a writer
    /// that died).
    pub(super) fn remove_first(&mut self, pred: impl Fn(&[u8]) -> bool) -> Option<Vec<u8>> {
        let i = self.q.iter().position(|(_, s)| pred(s))?;
        self.q.remove(i).map(|(_, s)| s)
    }
}

/// A node's inbox.
pub(super) struct SimInbox {
    pub(super) safe: SimPart,
    pub(super) fast: SimPart,
    pub(super) bulk: SimPart,
}

impl SimInbox {
    fn new(safe_cap: usize) -> Self {
        SimInbox {
            safe: SimPart::new(safe_cap, false),
            fast: SimPart::new(FAST_BUFFER, true),
            bulk: SimPart::new(BULK_BUFFER, false),
        }
    }

    fn part(&mut self, part: Part) -> &mut SimPart {
        match part {
            Part::Safe => &mut self.safe,
            Part::Fast => &mut self.fast,
            Part::Bulk => &mut self.bulk,
        }
    }
}

fn encode(kind: u8, sender: u64, session: u32, seq: u64, body: &[u8]) -> Vec<u8> {
    let h = frame::header_len(kind);
    let mut b = vec![0u8; h + body.len()];
    frame::write_header(&mut b, kind, sender, session, seq);
    b[h..].copy_from_slice(body);
    b
}

/// `me` writing into a peer's inbox.
struct SimWriter<'a> {
    me: u64,
    to: &'a mut SimInbox,
    bulk_open: bool,
    bulk_requested: &'a mut bool,
}

impl InboxWriter for SimWriter<'_> {
    fn is_open(&self) -> bool {
        true
    }

    fn put(&mut self, part: Part, kind: u8, session: u32, seq: u64, body: &[u8]) -> bool {
        if part == Part::Bulk && !self.bulk_open {
            return false;
        }
        let sample = encode(kind, self.me, session, seq, body);
        self.to.part(part).push(self.me, sample)
    }

    fn wake(&mut self) {}

    fn open_bulk(&mut self) {
        *self.bulk_requested = true;
    }

    /// A loan of the simulation is a [`crate::link::HeapLoan`]: its bytes are copied.
    fn put_loan(
        &mut self,
        mut loan: Box<dyn crate::link::LinkLoan>,
        session: u32,
        seq: u64,
    ) -> bool {
        let body = loan.init().to_vec();
        self.put(Part::Bulk, super::frame::BULK_DATA, session, seq, &body)
    }
}

/// What a node's receiver handed over.
#[derive(Debug, Clone, PartialEq, Eq)]
pub(super) enum Got {
    Msg(u64, Vec<u8>),
    Announce(u64, Vec<u8>),
    Reset(u64),
}

/// What one node sends to one peer.
struct SimPeer {
    tx: PeerTx,
    /// Answer to a bulk-inbox request, given on the next step.
    bulk_requested: bool,
    bulk_open: bool,
}

/// A node: its sending machines (one per peer) and its receiving machine.
pub(super) struct SimNode {
    peers: HashMap<u64, SimPeer>,
    rx: Receiver,
    pub(super) got: Vec<Got>,
    pub(super) counters: LinkCounters,
}

/// The receiving machine's I/O in the simulation.
struct SimRxIo<'a> {
    me: u64,
    inboxes: &'a mut HashMap<u64, SimInbox>,
    peers: &'a mut HashMap<u64, SimPeer>,
    got: &'a mut Vec<Got>,
    counters: &'a LinkCounters,
}

impl RxIo for SimRxIo<'_> {
    type Sample = Vec<u8>;

    fn take(&mut self, part: Part) -> Option<Vec<u8>> {
        let inbox = self.inboxes.get_mut(&self.me)?;
        inbox.part(part).q.pop_front().map(|(_, s)| s)
    }

    fn deliver(&mut self, from: u64, msg: &[u8]) {
        self.got.push(Got::Msg(from, msg.to_vec()));
    }

    fn announce(&mut self, from: u64, msg: &[u8]) {
        self.got.push(Got::Announce(from, msg.to_vec()));
    }

    fn peer_reset(&mut self, from: u64) {
        self.got.push(Got::Reset(from));
    }

    fn acked(&mut self, from: u64, session: u32, seq: u64) -> bool {
        let Some(p) = self.peers.get_mut(&from) else {
            return false;
        };
        let Some(done) = p.tx.on_ack(session, seq) else {
            return false;
        };
        for d in done {
            let _ = d.send(Ok(()));
        }
        true
    }

    fn send_ack(&mut self, from: u64, session: u32, seq: u64) -> AckSent {
        let Some(inbox) = self.inboxes.get_mut(&from) else {
            return AckSent::NotOpen;
        };
        let ack = encode(frame::ACK, self.me, session, seq, &[]);
        if inbox.safe.push(self.me, ack) {
            AckSent::Taken
        } else {
            AckSent::Refused
        }
    }

    fn request_open(&mut self, _from: u64) {}

    fn retry_backlogs(&mut self, acked: &[u64], retry: bool) -> bool {
        let mut remaining = false;
        for (id, p) in self.peers.iter_mut() {
            if !p.tx.has_backlog() {
                continue;
            }
            if acked.contains(id) || retry {
                if let Some(to) = self.inboxes.get_mut(id) {
                    let mut w = SimWriter {
                        me: self.me,
                        to,
                        bulk_open: p.bulk_open,
                        bulk_requested: &mut p.bulk_requested,
                    };
                    p.tx.retry(&mut w, self.counters);
                }
            }
            remaining |= p.tx.has_backlog();
        }
        remaining
    }
}

/// A host of simulated nodes, each with an inbox.
pub(super) struct SimHost {
    pub(super) inboxes: HashMap<u64, SimInbox>,
    pub(super) nodes: HashMap<u64, SimNode>,
    pub(super) now: Instant,
    /// Whether bulk inboxes can be opened (else large messages go fragmented inline).
    pub(super) bulk_available: bool,
    next_session: u32,
}

impl SimHost {
    /// Nodes `ids`, each inbox's safe part buffering `safe_cap` frames per writer.
    pub(super) fn new(ids: &[u64], safe_cap: usize) -> Self {
        let now = Instant::now();
        SimHost {
            inboxes: ids.iter().map(|&i| (i, SimInbox::new(safe_cap))).collect(),
            nodes: ids
                .iter()
                .map(|&i| {
                    let node = SimNode {
                        peers: HashMap::new(),
                        rx: Receiver::new(now, super::rx::TEST_MAX_WRITERS),
                        got: Vec::new(),
                        counters: LinkCounters::default(),
                    };
                    (i, node)
                })
                .collect(),
            now,
            bulk_available: true,
            next_session: 1,
        }
    }

    /// Nodes with the real buffer sizes.
    pub(super) fn standard(ids: &[u64]) -> Self {
        Self::new(ids, SAFE_BUFFER)
    }

    /// Runs `f` on `from`'s sending machine towards `to`, writing into `to`'s inbox.
    fn with_tx<R>(
        &mut self,
        from: u64,
        to: u64,
        f: impl FnOnce(&mut PeerTx, &mut SimWriter<'_>, &LinkCounters) -> R,
    ) -> R {
        let node = self.nodes.get_mut(&from).expect("a simulated node");
        let next_session = &mut self.next_session;
        let p = node.peers.entry(to).or_insert_with(|| {
            *next_session += 1;
            SimPeer {
                tx: PeerTx::new(*next_session),
                bulk_requested: false,
                bulk_open: false,
            }
        });
        let inbox = self.inboxes.get_mut(&to).expect("a simulated inbox");
        let mut w = SimWriter {
            me: from,
            to: inbox,
            bulk_open: p.bulk_open,
            bulk_requested: &mut p.bulk_requested,
        };
        f(&mut p.tx, &mut w, &node.counters)
    }

    /// `from` sends a safe message to `to`; the returned receiver completes on its ack.
    pub(super) fn send_safe(&mut self, from: u64, to: u64, msg: Vec<u8>) -> Done {
        let (done, rx) = oneshot::channel();
        self.with_tx(from, to, |tx, w, c| {
            tx.send_safe(w, c, msg.into(), Some(done.into()))
        });
        rx
    }

    /// `from` sends `msg` to `to` as a message written in place (a heap loan here); the
    /// returned receiver completes on its ack.
    pub(super) fn send_loan(&mut self, from: u64, to: u64, msg: &[u8]) -> Done {
        use crate::link::LinkLoan;
        let (done, rx) = oneshot::channel();
        let mut loan = crate::link::HeapLoan::new(msg.len());
        loan.append(msg);
        self.with_tx(from, to, |tx, w, c| {
            tx.send_loan(w, c, Box::new(loan), Some(done.into()))
        });
        rx
    }

    /// `from` sends a fast message to `to`.
    pub(super) fn send_fast(&mut self, from: u64, to: u64, key: Option<u32>, msg: Vec<u8>) {
        self.with_tx(from, to, |tx, w, c| tx.send_fast(w, c, key, msg));
    }

    /// `from` forgets `to` and starts a new session with it (what closing a peer does: the
    /// next message is a fresh session). What was in flight fails.
    pub(super) fn restart_sender(&mut self, from: u64, to: u64) {
        let node = self.nodes.get_mut(&from).expect("a simulated node");
        if let Some(mut p) = node.peers.remove(&to) {
            p.tx.fail_all(&LinkSendError::PeerClosed(format!("{to:x}")));
        }
    }

    /// Answers the requests to open a bulk inbox (writing what waited for it).
    pub(super) fn open_bulk_inboxes(&mut self) {
        let ids: Vec<u64> = self.nodes.keys().copied().collect();
        for &id in &ids {
            let requested: Vec<u64> = self.nodes[&id]
                .peers
                .iter()
                .filter(|(_, p)| p.bulk_requested && !p.bulk_open)
                .map(|(to, _)| *to)
                .collect();
            for to in requested {
                let ok = self.bulk_available;
                if let Some(p) = self.nodes.get_mut(&id).and_then(|n| n.peers.get_mut(&to)) {
                    p.bulk_requested = false;
                    p.bulk_open = ok;
                }
                self.with_tx(id, to, |tx, w, c| tx.bulk_opened(ok, w, c));
            }
        }
    }

    /// One step: requests to open bulk inboxes are answered, then every node makes one
    /// receive pass; the clock advances by a millisecond. Returns whether any pass took a
    /// frame.
    pub(super) fn step(&mut self) -> bool {
        self.open_bulk_inboxes();
        let ids: Vec<u64> = self.nodes.keys().copied().collect();
        let mut busy = false;
        for &id in &ids {
            let node = self.nodes.get_mut(&id).expect("a simulated node");
            let SimNode {
                peers,
                rx,
                got,
                counters,
            } = node;
            let mut io = SimRxIo {
                me: id,
                inboxes: &mut self.inboxes,
                peers,
                got,
                counters,
            };
            let (taken, _) = rx.pass(self.now, true, &mut io, counters);
            busy |= taken > 0;
        }
        self.now += Duration::from_millis(1);
        busy
    }

    /// Steps until a step takes no frame, at most `max` steps. Returns the steps run.
    pub(super) fn run(&mut self, max: usize) -> usize {
        for i in 0..max {
            if !self.step() && self.inboxes.values().all(|b| b.safe.q.is_empty()) {
                return i + 1;
            }
        }
        max
    }

    /// The messages `at` received, in order.
    pub(super) fn messages(&self, at: u64) -> Vec<(u64, Vec<u8>)> {
        self.nodes[&at]
            .got
            .iter()
            .filter_map(|g| match g {
                Got::Msg(from, m) => Some((*from, m.clone())),
                _ => None,
            })
            .collect()
    }

    /// The number of resets `at` saw from `from`.
    pub(super) fn resets(&self, at: u64, from: u64) -> usize {
        self.nodes[&at]
            .got
            .iter()
            .filter(|g| **g == Got::Reset(from))
            .count()
    }
}

/// Whether a completion resolved successfully (without waiting).
pub(super) fn acked(done: &mut Done) -> bool {
    matches!(done.try_recv(), Ok(Ok(())))
}

/// The frame's kind, sender, session and sequence number.
pub(super) fn header(b: &[u8]) -> Option<(u8, u64, u32, u64)> {
    let (sender, f) = frame::parse(b).ok()?;
    let (session, seq) = match f {
        frame::Frame::Safe { session, seq, .. }
        | frame::Frame::Ack { session, seq }
        | frame::Frame::Bulk { session, seq, .. }
        | frame::Frame::BulkData { session, seq, .. } => (session, seq),
        _ => (0, 0),
    };
    Some((b[0], sender, session, seq))
}
