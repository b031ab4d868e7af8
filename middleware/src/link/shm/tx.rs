//! The sending side towards one peer, as a pure state machine over an [`InboxWriter`]: safe
//! messages get a session and sequence numbers, are cut into frames (bodies of large ones
//! going to the bulk inbox), wait while the peer's safe inbox is full, and complete when the
//! peer acknowledges them; fast messages wait in a bounded newest-wins queue until the inbox
//! is open.
//!
//! Why not [`crate::link::arq`]: shared memory loses nothing once a sample is accepted, so
//! there is no retransmission timer, no window and no selective acknowledgement. The only
//! failure is a full buffer, which refuses the frame: the writer keeps it and retries when the
//! peer acknowledges (its buffer has room again) or on the receiver's retry timer. What the two
//! share is the cumulative acknowledgement completing `done`, a few lines each.

use std::collections::VecDeque;

use bytes::Bytes;

use super::frame::{self, Part};
use super::{BULK_BUFFER, BULK_MAX, FRAME_MAX, MAX_FAST_BACKLOG, SAFE_FRAMES_IN_FLIGHT};
use crate::link::coalesce::{CoalescingQueue, Pushed};
use crate::link::{LinkCounters, LinkLoan, LinkSendError, SafeCompletion};
use std::sync::atomic::Ordering;

/// The writing side of one peer's inbox, as the sending machine sees it.
pub(crate) trait InboxWriter {
    /// Whether the peer's inbox (fast and safe parts) is open for writing.
    fn is_open(&self) -> bool;
    /// Writes one frame (from us) into `part` of the peer's inbox. Returns whether the inbox took it (a
    /// full safe or bulk buffer refuses it; a part not open refuses everything).
    fn put(&mut self, part: Part, kind: u8, session: u32, seq: u64, body: &[u8]) -> bool;
    /// Wakes the peer's reader (if it sleeps on its wake event).
    fn wake(&mut self);
    /// Asks for the peer's bulk inbox to be opened; [`PeerTx::bulk_opened`] follows.
    fn open_bulk(&mut self);
    /// Sends `loan`, a whole message written in a sample of the peer's bulk inbox, as the
    /// `BulkData` frame `(session, seq)`. Returns whether the inbox took it (the sample is
    /// spent either way).
    fn put_loan(&mut self, loan: Box<dyn LinkLoan>, session: u32, seq: u64) -> bool;
}

/// Whether large fragments can go to the peer's bulk inbox.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum BulkState {
    /// Not asked for yet: the peer never received anything large.
    Closed,
    /// Asked for; large fragments wait.
    Opening,
    Open,
    /// Opening failed: large messages are fragmented into the safe inbox instead.
    Unavailable,
}

/// A safe message not yet wholly written into the peer's inbox.
struct Pending {
    /// The message, unless it is written in a `loan` (shared with the other peers it goes to).
    msg: Bytes,
    /// A whole message written in place in a sample of the peer's bulk inbox, until the
    /// sample is sent.
    loan: Option<Box<dyn LinkLoan>>,
    /// The length of the message when it is a loan (kept once the sample is sent and its
    /// `Bulk` frame still waits).
    loan_len: Option<usize>,
    /// Bytes already written (fragments accepted by the inbox).
    sent: usize,
    done: Option<SafeCompletion>,
    /// A large fast message riding the safe path (dropped first when the backlog is long).
    fast: bool,
    /// The body of the fragment at `sent` is in the bulk inbox; its `Bulk` frame is not yet.
    bulk_written: bool,
}

impl Pending {
    fn new(msg: impl Into<Bytes>, done: Option<SafeCompletion>, fast: bool) -> Self {
        Pending {
            msg: msg.into(),
            loan: None,
            loan_len: None,
            sent: 0,
            done,
            fast,
            bulk_written: false,
        }
    }

    /// A message written in `loan`.
    fn loaned(loan: Box<dyn LinkLoan>, done: Option<SafeCompletion>) -> Self {
        let mut p = Pending::new(Bytes::new(), done, false);
        p.loan_len = Some(loan.len());
        p.loan = Some(loan);
        p
    }

    /// Its length.
    fn len(&self) -> usize {
        self.loan_len.unwrap_or(self.msg.len())
    }

    /// Whether it may go in a pack (a small whole message not yet started).
    fn packable(&self) -> bool {
        self.sent == 0 && self.loan_len.is_none() && packable(&self.msg)
    }
}

/// What this link sends to one peer.
pub(crate) struct PeerTx {
    session: u32,
    next_seq: u64,
    bulk: BulkState,
    /// Fast messages waiting for the inbox to be opened.
    fast_backlog: CoalescingQueue<u32, Vec<u8>>,
    safe_backlog: VecDeque<Pending>,
    /// Bytes of `safe_backlog`'s messages, each counted as a pack entry.
    backlog_bytes: usize,
    /// Written, waiting for the peer's acknowledgement.
    unacked: VecDeque<(u64, SafeCompletion)>,
    /// The last sequence number of each safe frame written and not yet acknowledged.
    in_flight: VecDeque<u64>,
    /// The sequence number of each bulk sample written and not yet acknowledged: a loaned
    /// sample is sent only while fewer than the bulk buffer holds are (a refused one would be
    /// lost, where a copied body is written again).
    bulk_in_flight: VecDeque<u64>,
    /// The entries of the pack being written (kept for its allocation).
    pack: Vec<u8>,
    /// The inbox refused a frame: wait for an acknowledgement (or the retry timer).
    blocked: bool,
}

/// Longest body of a safe frame written inline.
const INLINE_MAX: usize = FRAME_MAX - frame::SEQUENCED;

/// Whether a message fits a pack with others (at least two such messages fit one frame): it
/// may then wait for the acknowledgement of earlier frames to go with the messages after it.
fn packable(msg: &[u8]) -> bool {
    2 * (msg.len() + frame::PACK_ENTRY_HEADER) <= INLINE_MAX
}

impl PeerTx {
    /// A fresh sending side in session `session` (random in use, so a restarted sender is
    /// told apart).
    pub(crate) fn new(session: u32) -> Self {
        PeerTx {
            session,
            next_seq: 0,
            bulk: BulkState::Closed,
            fast_backlog: CoalescingQueue::new(MAX_FAST_BACKLOG),
            safe_backlog: VecDeque::new(),
            backlog_bytes: 0,
            unacked: VecDeque::new(),
            in_flight: VecDeque::new(),
            bulk_in_flight: VecDeque::new(),
            pack: Vec::new(),
            blocked: false,
        }
    }

    /// Whether safe frames wait to be written.
    pub(crate) fn has_backlog(&self) -> bool {
        !self.safe_backlog.is_empty()
    }

    /// Sends a best-effort message: straight into the fast inbox, or queued (newest per key
    /// wins) until the inbox opens, or (too large for a frame) on the safe path.
    pub(crate) fn send_fast(
        &mut self,
        w: &mut impl InboxWriter,
        c: &LinkCounters,
        coalesce: Option<u32>,
        msg: Vec<u8>,
    ) {
        if !w.is_open() {
            if let Pushed::DroppedOldest(_) = self.fast_backlog.push(coalesce, msg) {
                c.fast_dropped.fetch_add(1, Ordering::Relaxed);
            }
            return;
        }
        if msg.len() + frame::BASE <= FRAME_MAX {
            if w.put(Part::Fast, frame::FAST, 0, 0, &msg) {
                c.count_out(frame::BASE + msg.len());
                w.wake();
            } else {
                c.fast_dropped.fetch_add(1, Ordering::Relaxed);
            }
            return;
        }
        // Too large for one frame: ride the safe path, unless the reader is far behind.
        let queued_fast = self.safe_backlog.iter().filter(|p| p.fast).count();
        if queued_fast >= MAX_FAST_BACKLOG {
            c.fast_dropped.fetch_add(1, Ordering::Relaxed);
            return;
        }
        self.queue(Pending::new(msg, None, true));
        if !self.blocked && self.flush_safe(w, c) {
            w.wake();
        }
    }

    /// Sends a reliable message; `done` completes when the peer acknowledges it.
    ///
    /// A small message waits while [`SAFE_FRAMES_IN_FLIGHT`] frames are unacknowledged (the
    /// reader is busy with them), unless a frame's worth waits already: the acknowledgement
    /// then writes everything waiting as packs, one sample for many messages. Anything else is
    /// written at once, as far as the inbox takes it.
    pub(crate) fn send_safe(
        &mut self,
        w: &mut impl InboxWriter,
        c: &LinkCounters,
        msg: Bytes,
        done: Option<SafeCompletion>,
    ) {
        self.queue(Pending::new(msg, done, false));
        if !self.blocked && self.flush_safe_holding(w, c, true) {
            w.wake();
        }
    }

    /// Whether the front of the backlog waits for an acknowledgement: a small whole message,
    /// with less than a frame's worth waiting, behind enough unacknowledged frames.
    fn holds(&self) -> bool {
        self.in_flight.len() >= SAFE_FRAMES_IN_FLIGHT
            && self.backlog_bytes < INLINE_MAX
            && self.safe_backlog.front().is_some_and(Pending::packable)
    }

    /// Sends the whole message written in `loan` (a sample of the peer's bulk inbox, which is
    /// open); `done` completes when the peer acknowledges it. It keeps its place among the
    /// safe messages.
    pub(crate) fn send_loan(
        &mut self,
        w: &mut impl InboxWriter,
        c: &LinkCounters,
        loan: Box<dyn LinkLoan>,
        done: Option<SafeCompletion>,
    ) {
        self.queue(Pending::loaned(loan, done));
        if !self.blocked && self.flush_safe(w, c) {
            w.wake();
        }
    }

    fn queue(&mut self, p: Pending) {
        self.backlog_bytes += p.len() + frame::PACK_ENTRY_HEADER;
        self.safe_backlog.push_back(p);
    }

    fn dequeue(&mut self) -> Option<Pending> {
        let p = self.safe_backlog.pop_front()?;
        self.backlog_bytes -= p.len() + frame::PACK_ENTRY_HEADER;
        Some(p)
    }

    /// The peer's inbox was just opened: writes what waited for it, then wakes the peer.
    pub(crate) fn opened(&mut self, w: &mut impl InboxWriter, c: &LinkCounters) {
        if !w.is_open() {
            return;
        }
        let mut wrote = false;
        while let Some((_, msg)) = self.fast_backlog.pop_front() {
            if msg.len() + frame::BASE <= FRAME_MAX {
                if w.put(Part::Fast, frame::FAST, 0, 0, &msg) {
                    c.count_out(frame::BASE + msg.len());
                    wrote = true;
                }
            } else {
                self.queue(Pending::new(msg, None, true));
            }
        }
        self.blocked = false;
        wrote |= self.flush_safe(w, c);
        if wrote {
            w.wake();
        }
    }

    /// Asks for the peer's bulk inbox to be opened (if not yet asked for): messages will be
    /// written into it in place.
    pub(crate) fn want_bulk(&mut self, w: &mut impl InboxWriter) {
        if self.bulk == BulkState::Closed {
            self.bulk = BulkState::Opening;
            w.open_bulk();
        }
    }

    /// The bulk inbox asked for by [`InboxWriter::open_bulk`] is open (`ok`) or cannot be
    /// (large messages then go fragmented into the safe inbox); writes what waited for it.
    pub(crate) fn bulk_opened(&mut self, ok: bool, w: &mut impl InboxWriter, c: &LinkCounters) {
        self.bulk = if ok {
            BulkState::Open
        } else {
            BulkState::Unavailable
        };
        self.retry(w, c);
    }

    /// Tries again to write what the peer's inbox refused (it acknowledged, so it has room, or
    /// the retry timer ran out).
    pub(crate) fn retry(&mut self, w: &mut impl InboxWriter, c: &LinkCounters) {
        self.blocked = false;
        if self.flush_safe(w, c) {
            w.wake();
        }
    }

    /// Writes as much of the safe backlog as the peer's inbox takes. Returns whether anything
    /// was written (the peer then needs waking).
    ///
    /// Whole small messages one after the other go together as a pack. A fragment longer than
    /// a safe frame carries its body in the bulk inbox: the body first (a `BulkData` sample),
    /// then its `Bulk` frame in the safe inbox, so the reader, meeting the frame in order,
    /// finds the body already there.
    fn flush_safe(&mut self, w: &mut impl InboxWriter, c: &LinkCounters) -> bool {
        self.flush_safe_holding(w, c, false)
    }

    /// [`Self::flush_safe`], stopping where the backlog [`Self::holds`] when `hold`.
    fn flush_safe_holding(
        &mut self,
        w: &mut impl InboxWriter,
        c: &LinkCounters,
        hold: bool,
    ) -> bool {
        if !w.is_open() {
            return false;
        }
        let mut wrote = false;
        loop {
            if hold && self.holds() {
                break;
            }
            let packed = match self.safe_backlog.get(1) {
                Some(second) if second.packable() => self.write_pack(w, c),
                _ => None,
            };
            let written = match packed {
                Some(written) => written,
                None => match self.write_fragment(w, c) {
                    Some(written) => written,
                    None => break,
                },
            };
            if !written {
                self.blocked = true;
                c.retransmitted.fetch_add(1, Ordering::Relaxed);
                break;
            }
            wrote = true;
        }
        wrote
    }

    /// Writes the whole small messages at the front of the backlog (two at least) as one
    /// pack. Returns whether the inbox took it, or `None` when the front is not two such
    /// messages.
    fn write_pack(&mut self, w: &mut impl InboxWriter, c: &LinkCounters) -> Option<bool> {
        self.pack.clear();
        let mut n = 0u64;
        for p in &self.safe_backlog {
            let entry = frame::PACK_ENTRY_HEADER + p.msg.len();
            if !p.packable() || self.pack.len() + entry > INLINE_MAX {
                break;
            }
            frame::push_pack_entry(&mut self.pack, &p.msg);
            n += 1;
        }
        if n < 2 {
            return None;
        }
        let first = self.next_seq;
        if !w.put(
            Part::Safe,
            frame::SAFE_PACK,
            self.session,
            first,
            &self.pack,
        ) {
            return Some(false);
        }
        c.count_out(frame::SEQUENCED + self.pack.len());
        for seq in first..first + n {
            if let Some(done) = self.dequeue().and_then(|p| p.done) {
                self.unacked.push_back((seq, done));
            }
        }
        self.next_seq = first + n;
        self.in_flight.push_back(first + n - 1);
        Some(true)
    }

    /// Writes the next fragment of the message at the front of the backlog (the whole message
    /// when it fits a frame). Returns whether the inbox took it, or `None` when there is
    /// nothing to write or it waits for the bulk inbox.
    fn write_fragment(&mut self, w: &mut impl InboxWriter, c: &LinkCounters) -> Option<bool> {
        if self.safe_backlog.front()?.loan_len.is_some() {
            return Some(self.write_loan(w, c));
        }
        let bulk_max = BULK_MAX - frame::SEQUENCED;
        let session = self.session;
        let p = self.safe_backlog.front_mut()?;
        let left = p.msg.len() - p.sent;
        let use_bulk = if left > INLINE_MAX {
            match self.bulk {
                BulkState::Open => true,
                BulkState::Unavailable => false,
                BulkState::Opening => return None,
                BulkState::Closed => {
                    self.bulk = BulkState::Opening;
                    w.open_bulk();
                    return None;
                }
            }
        } else {
            false
        };
        let n = left.min(if use_bulk { bulk_max } else { INLINE_MAX });
        let more = p.sent + n < p.msg.len();
        let body = &p.msg[p.sent..p.sent + n];
        let seq = self.next_seq;
        let written = if use_bulk {
            if !p.bulk_written {
                if !w.put(Part::Bulk, frame::BULK_DATA, session, seq, body) {
                    return Some(false);
                }
                c.count_out(frame::SEQUENCED + n);
                p.bulk_written = true;
                self.bulk_in_flight.push_back(seq);
            }
            let kind = if more { frame::BULK_MORE } else { frame::BULK };
            w.put(Part::Safe, kind, session, seq, &[])
                .then_some(frame::SEQUENCED)
        } else {
            let kind = if more { frame::SAFE_MORE } else { frame::SAFE };
            w.put(Part::Safe, kind, session, seq, body)
                .then_some(frame::SEQUENCED + n)
        };
        let Some(bytes) = written else {
            return Some(false);
        };
        c.count_out(bytes);
        p.sent += n;
        p.bulk_written = false;
        if !more {
            if let Some(done) = self.dequeue().and_then(|p| p.done) {
                self.unacked.push_back((seq, done));
            }
        }
        self.next_seq += 1;
        self.in_flight.push_back(seq);
        Some(true)
    }

    /// Writes the loaned message at the front of the backlog: its sample into the bulk inbox
    /// (while the inbox surely has room for it), then its `Bulk` frame. Returns whether the
    /// frame was written; a sample the inbox refused anyway (the peer's inbox went away) is
    /// lost, and its message fails.
    fn write_loan(&mut self, w: &mut impl InboxWriter, c: &LinkCounters) -> bool {
        let (session, seq) = (self.session, self.next_seq);
        let bulk_full = self.bulk_in_flight.len() >= BULK_BUFFER;
        let Some(p) = self.safe_backlog.front_mut() else {
            return false;
        };
        if !p.bulk_written {
            if bulk_full {
                return false;
            }
            let Some(loan) = p.loan.take() else {
                return false;
            };
            let len = loan.len();
            if !w.put_loan(loan, session, seq) {
                if let Some(done) = self.dequeue().and_then(|p| p.done) {
                    let _ = done.send(Err(LinkSendError::PeerClosed(
                        "a shared-memory peer whose inbox refused a loaned sample".into(),
                    )));
                }
                return true;
            }
            c.count_out(frame::SEQUENCED + len);
            p.bulk_written = true;
            self.bulk_in_flight.push_back(seq);
        }
        if !w.put(Part::Safe, frame::BULK, session, seq, &[]) {
            return false;
        }
        c.count_out(frame::SEQUENCED);
        if let Some(done) = self.dequeue().and_then(|p| p.done) {
            self.unacked.push_back((seq, done));
        }
        self.next_seq += 1;
        self.in_flight.push_back(seq);
        true
    }

    /// The peer acknowledged everything up to `seq` of `session`: unblocks the writer and
    /// returns the completions now due, or `None` when the acknowledgement is of another
    /// session (a stale one, from before a restart of ours).
    pub(crate) fn on_ack(&mut self, session: u32, seq: u64) -> Option<Vec<SafeCompletion>> {
        if self.session != session {
            return None;
        }
        self.blocked = false;
        while self.in_flight.front().is_some_and(|s| *s <= seq) {
            self.in_flight.pop_front();
        }
        while self.bulk_in_flight.front().is_some_and(|s| *s <= seq) {
            self.bulk_in_flight.pop_front();
        }
        let mut done = Vec::new();
        while self.unacked.front().is_some_and(|(s, _)| *s <= seq) {
            if let Some((_, d)) = self.unacked.pop_front() {
                done.push(d);
            }
        }
        Some(done)
    }

    /// Fails everything queued or unacknowledged with `err`.
    pub(crate) fn fail_all(&mut self, err: &LinkSendError) {
        self.backlog_bytes = 0;
        self.in_flight.clear();
        self.bulk_in_flight.clear();
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

#[cfg(test)]
mod tests {
    use super::super::sim::{acked, SimHost};
    use super::super::{BULK_BUFFER, FAST_BUFFER, SAFE_FRAMES_IN_FLIGHT};
    use std::sync::atomic::Ordering;

    const A: u64 = 0xA;
    const B: u64 = 0xB;

    #[test]
    fn a_full_safe_buffer_holds_the_writer_back_until_acknowledged() {
        // B's safe inbox buffers 2 frames per writer; each message is too long to share one.
        let mut h = SimHost::new(&[A, B], 2);
        let msg = |i: u8| vec![i; super::INLINE_MAX / 2 + 1];
        let mut dones: Vec<_> = (0..20u8).map(|i| h.send_safe(A, B, msg(i))).collect();
        // Only what the buffer takes is written; the rest waits, and the refusal is counted.
        assert_eq!(h.inboxes[&B].safe.q.len(), 2);
        let refused = h.nodes[&A].counters.retransmitted.load(Ordering::Relaxed);
        assert!(refused >= 1, "the refusal is counted");
        assert!(
            dones.iter_mut().all(|d| !acked(d)),
            "nothing acknowledged yet"
        );
        // A does not retry on its own before B acknowledges or the retry timer runs out.
        h.send_safe(A, B, vec![99]);
        assert_eq!(h.inboxes[&B].safe.q.len(), 2, "a blocked writer waits");
        h.run(200);
        let got = h.messages(B);
        let expected: Vec<(u64, Vec<u8>)> = (0..20u8)
            .map(|i| (A, msg(i)))
            .chain(std::iter::once((A, vec![99])))
            .collect();
        assert_eq!(got, expected, "every message once, in order");
        assert!(dones.iter_mut().all(acked), "every message acknowledged");
        assert_eq!(h.nodes[&B].counters.duplicates.load(Ordering::Relaxed), 0);
        assert_eq!(h.nodes[&B].counters.corrupt.load(Ordering::Relaxed), 0);
    }

    #[test]
    fn small_messages_behind_unacknowledged_frames_go_as_packs() {
        let mut h = SimHost::standard(&[A, B]);
        let msg = |i: u32| {
            let mut m = i.to_le_bytes().to_vec();
            m.resize(4 + (i % 50) as usize, b'x');
            m
        };
        // B does not read yet: the first frames go one message each, then messages wait.
        let mut dones: Vec<_> = (0..3000u32).map(|i| h.send_safe(A, B, msg(i))).collect();
        let frames = |h: &SimHost| h.inboxes[&B].safe.q.len();
        let singles = frames(&h);
        assert!(
            singles >= SAFE_FRAMES_IN_FLIGHT,
            "a burst's first {SAFE_FRAMES_IN_FLIGHT} messages go at once, got {singles} frames"
        );
        // Waiting messages that fill a frame are written without waiting for B.
        assert!(singles < 20, "{singles} frames for 3,000 small messages");
        h.run(200);
        let got = h.messages(B);
        let expected: Vec<(u64, Vec<u8>)> = (0..3000u32).map(|i| (A, msg(i))).collect();
        assert_eq!(got, expected, "every message once, in order");
        assert!(dones.iter_mut().all(acked), "every message acknowledged");
        let c = &h.nodes[&B].counters;
        assert_eq!(c.duplicates.load(Ordering::Relaxed), 0);
        assert_eq!(c.corrupt.load(Ordering::Relaxed), 0);
        let frames_in = c.frames_in.load(Ordering::Relaxed);
        assert!(
            frames_in < 40,
            "3,000 messages of up to 53 bytes took {frames_in} frames"
        );
    }

    /// A loaned sample refused by a full bulk inbox would be lost (a copied body is written
    /// again): loaned messages wait for room, keep their place among the others, and all
    /// arrive once the reader reads.
    #[test]
    fn loaned_messages_wait_for_room_in_the_bulk_inbox_and_keep_their_place() {
        let mut h = SimHost::standard(&[A, B]);
        let mut first = h.send_safe(A, B, vec![1; super::FRAME_MAX * 2]);
        h.run(50);
        assert!(
            acked(&mut first),
            "the bulk inbox opened for a large message"
        );
        let loaned = |i: u8| vec![i; 20_000];
        let mut dones = Vec::new();
        let mut expected = Vec::new();
        // B does not read: far more loaned messages than its bulk buffer holds.
        for i in 0..(3 * BULK_BUFFER as u8) {
            dones.push(h.send_loan(A, B, &loaned(i)));
            expected.push((A, loaned(i)));
            dones.push(h.send_safe(A, B, vec![i; 10]));
            expected.push((A, vec![i; 10]));
        }
        // (A loaned sample the full bulk buffer refused would be lost, its message failed.)
        h.run(500);
        let got = h.messages(B);
        assert_eq!(&got[1..], &expected[..], "every message once, in order");
        assert!(dones.iter_mut().all(acked), "every message acknowledged");
        assert_eq!(h.nodes[&B].counters.corrupt.load(Ordering::Relaxed), 0);
    }

    /// A loaned sample written while the peer's safe inbox is full waits for its `Bulk` frame
    /// and arrives whole (not as the empty message it left behind).
    #[test]
    fn a_loaned_message_whose_frame_the_full_safe_inbox_refused_arrives_whole() {
        // B's safe inbox buffers 2 frames per writer.
        let mut h = SimHost::new(&[A, B], 2);
        let mut first = h.send_safe(A, B, vec![1; super::FRAME_MAX * 2]);
        h.run(50);
        assert!(
            acked(&mut first),
            "the bulk inbox opened for a large message"
        );
        let big = |i: u8| vec![i; super::INLINE_MAX / 2 + 1];
        let mut dones = vec![h.send_safe(A, B, big(1)), h.send_safe(A, B, big(2))];
        assert_eq!(h.inboxes[&B].safe.q.len(), 2, "B's safe inbox is full");
        let loaned = vec![3u8; 30_000];
        dones.push(h.send_loan(A, B, &loaned));
        dones.push(h.send_safe(A, B, vec![4; 10]));
        h.run(200);
        let got = h.messages(B);
        let expected = [(A, big(1)), (A, big(2)), (A, loaned), (A, vec![4; 10])];
        assert_eq!(
            &got[1..],
            &expected[..],
            "every message once, whole, in order"
        );
        assert!(dones.iter_mut().all(acked), "every message acknowledged");
        assert_eq!(h.nodes[&B].counters.corrupt.load(Ordering::Relaxed), 0);
    }

    #[test]
    fn fast_messages_overflow_the_oldest_and_large_ones_ride_the_safe_path() {
        let mut h = SimHost::standard(&[A, B]);
        for i in 0..(FAST_BUFFER as u32 + 10) {
            h.send_fast(A, B, Some(1), i.to_le_bytes().to_vec());
        }
        let big = vec![7u8; super::FRAME_MAX * 2];
        h.send_fast(A, B, None, big.clone());
        h.run(50);
        let got = h.messages(B);
        // The fast buffer kept the newest frames; the large one arrived whole.
        assert_eq!(got.len(), FAST_BUFFER + 1);
        assert!(got.contains(&(A, big)));
        let last = (FAST_BUFFER as u32 + 9).to_le_bytes().to_vec();
        assert!(got.contains(&(A, last)), "the newest fast value survives");
    }
}
