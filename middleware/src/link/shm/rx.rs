//! The receiving side of an inbox, as a pure state machine over an [`RxIo`] and `now`: takes
//! frames from the inbox's parts, reassembles each sender's safe stream (fragments inline or
//! in the bulk inbox), acknowledges cumulatively, hands acknowledgements of our own messages
//! to the sending side and retries what peers' full inboxes refused.
//!
//! Shared memory loses nothing, so unlike [`crate::link::arq`] there is no reorder buffer and
//! no retransmission: a gap in a sender's sequence numbers can only mean a torn message (a
//! bulk body that is not there), which is dropped and counted as corrupt.

use std::collections::{HashMap, HashSet, VecDeque};
use std::sync::atomic::Ordering;
use std::time::Instant;

use super::frame::{self, Frame, Part};
use super::{
    BULK_BUFFER, FAST_PASS_BUDGET, MAX_MESSAGE, PASS_BUDGET, PASS_BULK_BYTES, PASS_MESSAGES,
    REOPEN, RETRY, SAFE_BUFFER,
};
use crate::link::LinkCounters;

/// Most bytes of partly reassembled messages held over all writers (each writer also holds at
/// most [`MAX_MESSAGE`]): beyond it, the message being extended is dropped as torn.
const MAX_REASSEMBLY_BYTES: usize = 2 * MAX_MESSAGE;

/// Writers the receivers of tests and fuzz targets track (twice the default `maxPeers`).
#[cfg(any(test, feature = "fuzzing"))]
pub(crate) const TEST_MAX_WRITERS: usize = 32;

/// What the receiving machine reads from and acts on.
pub(crate) trait RxIo {
    /// A sample taken from the inbox, readable in place.
    type Sample: AsRef<[u8]>;
    /// Takes the oldest sample of `part` of our inbox, if any (a failure to read is logged
    /// by the implementation and reads as empty until the next pass).
    fn take(&mut self, part: Part) -> Option<Self::Sample>;
    /// A whole message from `from` (a fast one, or a safe one in order).
    fn deliver(&mut self, from: u64, msg: &[u8]);
    /// A whole safe message from `from` that is all of `sample` from `at` (a bulk body): the
    /// implementation may hand the sample itself on instead of the bytes.
    fn deliver_sample(&mut self, from: u64, sample: Self::Sample, at: usize) {
        self.deliver(from, &sample.as_ref()[at..]);
    }
    /// A discovery message from `from`.
    fn announce(&mut self, from: u64, msg: &[u8]);
    /// `from` started a new safe session while one was running (it restarted or reset us).
    fn peer_reset(&mut self, from: u64);
    /// `from` acknowledged our safe messages up to `seq` of `session`. Returns whether that is
    /// our current session with it.
    fn acked(&mut self, from: u64, session: u32, seq: u64) -> bool;
    /// Writes an acknowledgement into `from`'s inbox (and wakes its reader when taken).
    fn send_ack(&mut self, from: u64, session: u32, seq: u64) -> AckSent;
    /// Asks for `from`'s inbox to be opened.
    fn request_open(&mut self, from: u64);
    /// Retries what peers' inboxes refused: towards the peers in `acked` (their buffer has
    /// room) or, on `retry`, towards every blocked peer. Returns whether some backlog remains.
    fn retry_backlogs(&mut self, acked: &[u64], retry: bool) -> bool;
}

/// What became of an acknowledgement.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) enum AckSent {
    /// The peer's inbox took it.
    Taken,
    /// The peer's safe buffer is full: try again on the next pass.
    Refused,
    /// The peer's inbox is not open (yet): ask for it to be opened.
    NotOpen,
    /// The peer cannot be tracked (too many peers): forget the acknowledgement.
    NoPeer,
}

/// What the receiver knows of one sender's safe stream.
struct RxState {
    session: u32,
    expected: u64,
    /// Fragments of the message being reassembled.
    partial: Vec<u8>,
    /// Highest sequence number delivered and not yet acknowledged.
    ack: Option<u64>,
    /// A fragment of the message being reassembled went missing: drop the message at its end.
    torn: bool,
    /// The receiver's frame count at its last frame (the least recent writer is pushed out
    /// first).
    last: u64,
}

impl RxState {
    fn new(session: u32, expected: u64, now: u64) -> Self {
        RxState {
            session,
            expected,
            partial: Vec::new(),
            ack: None,
            torn: false,
            last: now,
        }
    }
}

/// A bulk body found for a `Bulk` frame.
enum BulkBody<S> {
    /// Still in shared memory.
    Sample(S),
    /// Copied out of it earlier (stashed while looking for another writer's).
    Copy(Vec<u8>),
}

impl<S: AsRef<[u8]>> AsRef<[u8]> for BulkBody<S> {
    fn as_ref(&self) -> &[u8] {
        match self {
            BulkBody::Sample(s) => s.as_ref(),
            BulkBody::Copy(v) => v,
        }
    }
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

/// The receiving machine of one inbox.
pub(crate) struct Receiver {
    /// Bulk samples of one writer met while looking for another's (copied, so the writer gets
    /// its memory back), in the order written.
    stash: HashMap<u64, VecDeque<Vec<u8>>>,
    rx: HashMap<u64, RxState>,
    ack_due: HashSet<u64>,
    /// When the receiver may ask again to open a peer's inbox.
    open_requested: HashMap<u64, Instant>,
    next_retry: Instant,
    /// Bulk bytes delivered in the current pass.
    pass_bulk_bytes: usize,
    /// Safe messages and fragments taken in the current pass.
    pass_messages: usize,
    /// Some peer's inbox refused frames at the last look.
    backlog: bool,
    /// Bytes held in every writer's `partial`.
    partial_bytes: usize,
    /// Safe fragments seen (a clock ordering writers by their last one).
    fragments: u64,
    /// Most writers whose streams are tracked (writer ids are whatever a frame says, so a
    /// process on the host could invent any number): a new one beyond it pushes out the writer
    /// heard from longest ago.
    max_writers: usize,
    /// [`MAX_REASSEMBLY_BYTES`] (lower in tests).
    max_reassembly: usize,
}

impl Receiver {
    /// A receiver knowing no sender yet, tracking the streams of up to `max_writers` writers.
    pub(crate) fn new(now: Instant, max_writers: usize) -> Self {
        Receiver {
            stash: HashMap::new(),
            rx: HashMap::new(),
            ack_due: HashSet::new(),
            open_requested: HashMap::new(),
            next_retry: now,
            pass_bulk_bytes: 0,
            pass_messages: 0,
            backlog: false,
            partial_bytes: 0,
            fragments: 0,
            max_writers,
            max_reassembly: MAX_REASSEMBLY_BYTES,
        }
    }

    /// Forgets sender `id` (it was closed): its next frame starts a fresh stream.
    pub(crate) fn forget(&mut self, id: u64) {
        if let Some(st) = self.rx.remove(&id) {
            self.partial_bytes -= st.partial.len();
        }
        self.ack_due.remove(&id);
        self.stash.remove(&id);
        self.open_requested.remove(&id);
    }

    /// One pass over the inbox at `now`. Returns how many frames it took and whether either
    /// buffer had more than its budget (another pass should follow at once).
    pub(crate) fn pass(
        &mut self,
        now: Instant,
        look_at_backlogs: bool,
        io: &mut impl RxIo,
        c: &LinkCounters,
    ) -> (usize, bool) {
        let mut acked = Vec::new();
        let taken_safe = self.drain_safe(io, c, &mut acked);
        let taken_fast = drain_fast(io, c);
        if !self.ack_due.is_empty() {
            self.send_acks(now, io, c);
        }
        let retry = now >= self.next_retry;
        if retry {
            self.next_retry = now + RETRY;
        }
        if look_at_backlogs || retry || !acked.is_empty() {
            self.backlog = io.retry_backlogs(&acked, retry);
        }
        (
            taken_safe + taken_fast,
            taken_safe == PASS_BUDGET || taken_fast == FAST_PASS_BUDGET,
        )
    }

    /// Whether something must be retried soon even if no writer wakes us.
    pub(crate) fn retry_due(&self) -> bool {
        self.backlog || !self.ack_due.is_empty()
    }

    /// Takes what the safe inbox holds, up to [`PASS_BUDGET`] frames or [`PASS_BULK_BYTES`]
    /// of bulk bodies. Returns how many frames it took ([`PASS_BUDGET`] when a budget ran out).
    fn drain_safe(&mut self, io: &mut impl RxIo, c: &LinkCounters, acked: &mut Vec<u64>) -> usize {
        self.pass_bulk_bytes = 0;
        self.pass_messages = 0;
        for taken in 0..PASS_BUDGET {
            if self.pass_bulk_bytes >= PASS_BULK_BYTES || self.pass_messages >= PASS_MESSAGES {
                return PASS_BUDGET;
            }
            let Some(sample) = io.take(Part::Safe) else {
                return taken;
            };
            let bytes = sample.as_ref();
            c.count_in(bytes.len());
            match frame::parse(bytes) {
                Ok((
                    from,
                    Frame::Safe {
                        session,
                        seq,
                        more,
                        body,
                    },
                )) => {
                    if self.on_safe(io, c, from, (session, seq, more), Some(body)) {
                        io.deliver(from, body);
                    }
                }
                Ok((
                    from,
                    Frame::SafePack {
                        session,
                        seq,
                        entries,
                    },
                )) => self.on_pack(io, c, from, (session, seq), entries),
                Ok((from, Frame::Ack { session, seq })) => {
                    if io.acked(from, session, seq) {
                        acked.push(from);
                    }
                }
                Ok((from, Frame::Bulk { session, seq, more })) => {
                    self.on_bulk(io, c, from, (session, seq, more))
                }
                Ok((from, Frame::Fast(body))) => io.deliver(from, body),
                Ok((from, Frame::Announce(body))) => io.announce(from, body),
                Ok((_, Frame::BulkData { .. })) => {
                    // Bulk bodies never use the safe inbox.
                    c.corrupt.fetch_add(1, Ordering::Relaxed);
                }
                Err(e) => {
                    c.corrupt.fetch_add(1, Ordering::Relaxed);
                    tracing::trace!(error = %e, "corrupt shared-memory frame dropped");
                }
            }
        }
        PASS_BUDGET
    }

    /// A `SafePack`: whole messages numbered from `seq`. An entry running past the frame's end
    /// is corrupt and loses the rest of the pack (the gap then tears the sender's next message).
    fn on_pack(
        &mut self,
        io: &mut impl RxIo,
        c: &LinkCounters,
        from: u64,
        (session, first): (u32, u64),
        entries: &[u8],
    ) {
        let mut seq = Some(first);
        for entry in frame::pack_entries(entries) {
            let (Ok(body), Some(s)) = (entry, seq) else {
                c.corrupt.fetch_add(1, Ordering::Relaxed);
                return;
            };
            if self.on_safe(io, c, from, (session, s, false), Some(body)) {
                io.deliver(from, body);
            }
            seq = s.checked_add(1);
        }
    }

    /// A `Bulk` frame: its body is the next bulk sample of `from` (read in place when the
    /// message is that one fragment).
    fn on_bulk(
        &mut self,
        io: &mut impl RxIo,
        c: &LinkCounters,
        from: u64,
        (session, seq, more): (u32, u64, bool),
    ) {
        match self.take_bulk(io, c, from, session, seq) {
            Some(sample) => {
                let body = &sample.as_ref()[frame::SEQUENCED..];
                c.count_in(body.len());
                self.pass_bulk_bytes += body.len();
                if self.on_safe(io, c, from, (session, seq, more), Some(body)) {
                    match sample {
                        BulkBody::Sample(s) => io.deliver_sample(from, s, frame::SEQUENCED),
                        BulkBody::Copy(v) => io.deliver(from, &v[frame::SEQUENCED..]),
                    }
                }
            }
            None => {
                c.corrupt.fetch_add(1, Ordering::Relaxed);
                let whole = self.on_safe(io, c, from, (session, seq, more), None);
                debug_assert!(!whole, "no body, nothing to deliver");
            }
        }
    }

    /// Finds the body written for `from`'s fragment `(session, seq)`: in the stash, or next in
    /// the bulk inbox. Bodies of other writers met on the way are stashed, older ones of `from`
    /// (a closed session's) dropped.
    fn take_bulk<I: RxIo>(
        &mut self,
        io: &mut I,
        c: &LinkCounters,
        from: u64,
        session: u32,
        seq: u64,
    ) -> Option<BulkBody<I::Sample>> {
        let wanted = |b: &[u8]| -> BulkMatch {
            match frame::parse(b) {
                Ok((
                    s,
                    Frame::BulkData {
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
                Ok((s, Frame::BulkData { .. })) => BulkMatch::Other(s),
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
            let sample = io.take(Part::Bulk)?;
            match wanted(sample.as_ref()) {
                BulkMatch::Match => return Some(BulkBody::Sample(sample)),
                BulkMatch::Stale => {}
                BulkMatch::Later => {
                    self.stash
                        .entry(from)
                        .or_default()
                        .push_front(sample.as_ref().to_vec());
                    return None;
                }
                BulkMatch::Other(writer) => {
                    if !self.stash.contains_key(&writer) && self.stash.len() >= self.max_writers {
                        // More writers than any host runs: an invented id.
                        c.corrupt.fetch_add(1, Ordering::Relaxed);
                        continue;
                    }
                    // A writer's bodies in the stash never outnumber its frames the safe inbox
                    // can hold plus what it may write before them; more is corrupt input.
                    let q = self.stash.entry(writer).or_default();
                    if q.len() > SAFE_BUFFER + BULK_BUFFER {
                        q.pop_front();
                        c.corrupt.fetch_add(1, Ordering::Relaxed);
                    }
                    q.push_back(sample.as_ref().to_vec());
                }
            }
        }
    }

    /// A fragment of a safe message; `body` is `None` when it went missing (a bulk body that
    /// is not there), which tears the message. Returns whether `body` is a whole message the
    /// caller now delivers (a message of several fragments is delivered here).
    #[must_use]
    fn on_safe(
        &mut self,
        io: &mut impl RxIo,
        c: &LinkCounters,
        from: u64,
        (session, seq, more): (u32, u64, bool),
        body: Option<&[u8]>,
    ) -> bool {
        self.fragments += 1;
        self.pass_messages += 1;
        let now = self.fragments;
        let reset = match self.rx.get_mut(&from) {
            Some(st) if st.session == session => {
                st.last = now;
                false
            }
            Some(st) => {
                // The sender closed us and started over: what it had in flight is gone.
                self.partial_bytes -= st.partial.len();
                *st = RxState::new(session, seq, now);
                true
            }
            None => {
                if self.rx.len() >= self.max_writers {
                    self.push_out_least_recent_writer(c);
                }
                self.rx.insert(from, RxState::new(session, seq, now));
                false
            }
        };
        if reset {
            io.peer_reset(from);
        }
        let Some(st) = self.rx.get_mut(&from) else {
            return false;
        };
        if seq < st.expected {
            c.duplicates.fetch_add(1, Ordering::Relaxed);
            return false;
        }
        // No session reaches the last sequence number; a frame claiming it is corrupt (the
        // structured fuzzer found that `seq + 1` overflowed on it).
        let Some(next) = seq.checked_add(1) else {
            c.corrupt.fetch_add(1, Ordering::Relaxed);
            return false;
        };
        if more && body.is_some_and(|b| self.partial_bytes + b.len() > self.max_reassembly) {
            // Room is made by tearing the messages other writers stopped extending longest
            // ago: a writer still sending is the most recent, never the one torn.
            let needed = body.map_or(0, |b| b.len());
            self.tear_least_recent_partials(from, needed, c);
        }
        let Some(st) = self.rx.get_mut(&from) else {
            return false;
        };
        if seq > st.expected {
            // Shared memory loses nothing; a gap means a torn message, which is dropped.
            st.torn = true;
            c.corrupt.fetch_add(1, Ordering::Relaxed);
        }
        st.expected = next;
        st.ack = Some(seq);
        self.ack_due.insert(from);
        let Some(body) = body.filter(|_| !st.torn) else {
            st.torn = more;
            self.partial_bytes -= std::mem::take(&mut st.partial).len();
            return false;
        };
        if more {
            if st.partial.len() + body.len() > MAX_MESSAGE
                || self.partial_bytes + body.len() > self.max_reassembly
            {
                // Over its own bound, or alone over the total.
                self.partial_bytes -= std::mem::take(&mut st.partial).len();
                st.torn = true;
                c.corrupt.fetch_add(1, Ordering::Relaxed);
            } else {
                st.partial.extend_from_slice(body);
                self.partial_bytes += body.len();
            }
            return false;
        }
        if st.partial.is_empty() {
            return true;
        }
        st.partial.extend_from_slice(body);
        let msg = std::mem::take(&mut st.partial);
        self.partial_bytes -= msg.len() - body.len();
        io.deliver(from, &msg);
        false
    }

    /// Tears the partly reassembled messages of writers other than `from`, least recent
    /// first, until `needed` more bytes fit the total bound (or none is left to tear).
    fn tear_least_recent_partials(&mut self, from: u64, needed: usize, c: &LinkCounters) {
        while self.partial_bytes + needed > self.max_reassembly {
            let victim = self
                .rx
                .iter()
                .filter(|(id, st)| **id != from && !st.partial.is_empty())
                .min_by_key(|(_, st)| st.last)
                .map(|(id, _)| *id);
            let Some(st) = victim.and_then(|id| self.rx.get_mut(&id)) else {
                return;
            };
            self.partial_bytes -= std::mem::take(&mut st.partial).len();
            st.torn = true;
            c.corrupt.fetch_add(1, Ordering::Relaxed);
        }
    }

    /// Forgets the writer heard from longest ago (counted as a session pushed out), to make
    /// room for a new one.
    fn push_out_least_recent_writer(&mut self, c: &LinkCounters) {
        let Some(oldest) = self
            .rx
            .iter()
            .min_by_key(|(_, st)| st.last)
            .map(|(id, _)| *id)
        else {
            return;
        };
        self.forget(oldest);
        c.sessions_expired.fetch_add(1, Ordering::Relaxed);
    }

    /// Writers tracked now, and the bytes of their partly reassembled messages.
    #[cfg(test)]
    fn held(&self) -> (usize, usize) {
        (self.rx.len(), self.partial_bytes)
    }

    fn send_acks(&mut self, now: Instant, io: &mut impl RxIo, c: &LinkCounters) {
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
            match io.send_ack(from, session, seq) {
                AckSent::NoPeer => {
                    self.ack_due.remove(&from);
                }
                AckSent::NotOpen => {
                    // A peer that wrote before our scan found it: its inbox is opened on
                    // request, the retry timer brings us back.
                    if self.open_requested.get(&from).is_none_or(|t| *t <= now) {
                        self.open_requested.insert(from, now + REOPEN);
                        io.request_open(from);
                    }
                }
                AckSent::Taken => {
                    c.count_out(frame::SEQUENCED);
                    self.ack_due.remove(&from);
                    if let Some(r) = self.rx.get_mut(&from) {
                        if r.ack == Some(seq) {
                            r.ack = None;
                        }
                    }
                }
                AckSent::Refused => {}
            }
        }
    }
}

/// Takes what the fast inbox holds, up to [`FAST_PASS_BUDGET`] frames. Returns how many it
/// took.
fn drain_fast(io: &mut impl RxIo, c: &LinkCounters) -> usize {
    for taken in 0..FAST_PASS_BUDGET {
        let Some(sample) = io.take(Part::Fast) else {
            return taken;
        };
        let bytes = sample.as_ref();
        c.count_in(bytes.len());
        match frame::parse(bytes) {
            Ok((from, Frame::Fast(body))) => io.deliver(from, body),
            Ok((from, Frame::Announce(body))) => io.announce(from, body),
            Ok(_) | Err(_) => {
                // Safe frames never use the fast inbox.
                c.corrupt.fetch_add(1, Ordering::Relaxed);
            }
        }
    }
    FAST_PASS_BUDGET
}

#[cfg(test)]
mod tests {
    use super::super::sim::{acked, header, SimHost};
    use super::super::{BULK_MAX, FRAME_MAX};
    use super::*;

    const A: u64 = 0xA;
    const B: u64 = 0xB;
    const C: u64 = 0xC;

    fn tagged(writer: u8, i: u32, len: usize) -> Vec<u8> {
        let mut m: Vec<u8> = (0..len)
            .map(|k| (k as u32).wrapping_mul(31).wrapping_add(i) as u8)
            .collect();
        m[0] = writer;
        m[1..5].copy_from_slice(&i.to_le_bytes());
        m
    }

    fn count(h: &SimHost, at: u64, c: fn(&LinkCounters) -> &std::sync::atomic::AtomicU64) -> u64 {
        c(&h.nodes[&at].counters).load(Ordering::Relaxed)
    }

    /// An inbox holding only safe frames, recording what is delivered.
    #[derive(Default)]
    struct Inbox {
        safe: VecDeque<Vec<u8>>,
        delivered: Vec<(u64, Vec<u8>)>,
    }

    impl RxIo for Inbox {
        type Sample = Vec<u8>;
        fn take(&mut self, part: Part) -> Option<Vec<u8>> {
            match part {
                Part::Safe => self.safe.pop_front(),
                _ => None,
            }
        }
        fn deliver(&mut self, from: u64, msg: &[u8]) {
            self.delivered.push((from, msg.to_vec()));
        }
        fn announce(&mut self, _: u64, _: &[u8]) {}
        fn peer_reset(&mut self, _: u64) {}
        fn acked(&mut self, _: u64, _: u32, _: u64) -> bool {
            false
        }
        fn send_ack(&mut self, _: u64, _: u32, _: u64) -> AckSent {
            AckSent::Taken
        }
        fn request_open(&mut self, _: u64) {}
        fn retry_backlogs(&mut self, _: &[u64], _: bool) -> bool {
            false
        }
    }

    fn safe_frame(from: u64, seq: u64, more: bool, body: &[u8]) -> Vec<u8> {
        let mut b = vec![0u8; frame::SEQUENCED + body.len()];
        let kind = if more { frame::SAFE_MORE } else { frame::SAFE };
        frame::write_header(&mut b, kind, from, 1, seq);
        b[frame::SEQUENCED..].copy_from_slice(body);
        b
    }

    fn drain(r: &mut Receiver, io: &mut Inbox, c: &LinkCounters) {
        while !io.safe.is_empty() {
            r.pass(Instant::now(), false, io, c);
        }
    }

    #[test]
    fn invented_writers_are_bounded_in_count_and_bytes_and_a_live_writer_keeps_its_stream() {
        let c = LinkCounters::default();
        let mut r = Receiver::new(Instant::now(), TEST_MAX_WRITERS);
        // Below what the tracked writers' partial messages would hold (1000 bytes each).
        r.max_reassembly = TEST_MAX_WRITERS / 2 * 1000;
        let mut io = Inbox::default();
        let mut seq = 0;
        // 10,000 invented writer ids, each starting a message it never finishes; between
        // them a real writer (A) sends a message in two fragments now and then.
        for i in 0..10_000u64 {
            io.safe
                .push_back(safe_frame(0x1_0000 + i, 0, true, &[7u8; 1000]));
            if i % 50 == 0 {
                io.safe.push_back(safe_frame(A, seq, true, b"hel"));
                io.safe.push_back(safe_frame(A, seq + 1, false, b"lo"));
                seq += 2;
            }
            if io.safe.len() >= 256 {
                drain(&mut r, &mut io, &c);
                let (writers, bytes) = r.held();
                assert!(writers <= TEST_MAX_WRITERS, "{writers} writers tracked");
                assert!(bytes <= r.max_reassembly, "{bytes} bytes held");
            }
        }
        drain(&mut r, &mut io, &c);
        let from_a: Vec<&Vec<u8>> = io
            .delivered
            .iter()
            .filter(|(f, _)| *f == A)
            .map(|(_, m)| m)
            .collect();
        assert_eq!(from_a.len(), 200, "every message of the live writer");
        assert!(from_a.iter().all(|m| m.as_slice() == b"hello"));
        assert_eq!(io.delivered.len(), 200, "nothing of the invented writers");
        // Pushed out and counted: all but the writers still tracked.
        let pushed = c.sessions_expired.load(Ordering::Relaxed);
        assert!(pushed >= 10_000 - TEST_MAX_WRITERS as u64, "{pushed}");
        // The byte bound tore the messages that would have passed it, and counted them.
        assert!(c.corrupt.load(Ordering::Relaxed) > 0);
        // A forgotten writer's bytes are given back.
        let before = r.held();
        r.forget(0x1_0000 + 9_999);
        assert!(r.held().0 == before.0 - 1 && r.held().1 < before.1);
    }

    #[test]
    fn a_lost_safe_fragment_drops_only_its_message() {
        let mut h = SimHost::standard(&[A, B]);
        // No bulk inbox: the large message goes as inline fragments into the safe inbox.
        h.bulk_available = false;
        let big = tagged(b'a', 0, 3 * FRAME_MAX);
        let mut d1 = h.send_safe(A, B, big);
        // A learns the bulk inbox is unavailable and writes inline.
        h.open_bulk_inboxes();
        let mut d2 = h.send_safe(A, B, b"after".to_vec());
        let frames = h.inboxes[&B].safe.q.len();
        assert!(frames >= 4, "three inline fragments and the small message");
        // The second fragment of the large message is lost.
        let lost = h.inboxes.get_mut(&B).and_then(|i| {
            i.safe.remove_first(|b| {
                header(b).is_some_and(|(k, _, _, seq)| k == frame::SAFE_MORE && seq == 1)
            })
        });
        assert!(lost.is_some(), "a middle fragment was there to lose");
        h.run(50);
        // The torn message is not delivered with a hole; the stream goes on after it.
        assert_eq!(h.messages(B), vec![(A, b"after".to_vec())]);
        assert_eq!(count(&h, B, |c| &c.corrupt), 1);
        // The acknowledgement is cumulative: the writer is not held back by the torn message.
        assert!(acked(&mut d1) && acked(&mut d2));
    }

    #[test]
    fn large_messages_of_two_writers_reassemble_through_the_bulk_inbox() {
        // A safe buffer of two frames per writer: a writer's third body is in the bulk inbox
        // when its frame is refused, so the other writer's bodies land behind it, and B meets
        // bodies of one writer while looking for the other's (and stashes them). Ten bulk
        // samples each are more than a writer's bulk buffer too.
        let mut h = SimHost::new(&[A, B, C], 2);
        let sizes = [10 * BULK_MAX, 7, FRAME_MAX + 1, 2 * BULK_MAX + 5];
        let mut dones = Vec::new();
        for (i, &len) in sizes.iter().enumerate() {
            dones.push(h.send_safe(A, B, tagged(b'a', i as u32, len)));
            dones.push(h.send_safe(C, B, tagged(b'c', i as u32, len)));
        }
        h.run(500);
        let got = h.messages(B);
        for (tag, from) in [(b'a', A), (b'c', C)] {
            let mine: Vec<Vec<u8>> = got
                .iter()
                .filter(|(f, _)| *f == from)
                .map(|(_, m)| m.clone())
                .collect();
            let expected: Vec<Vec<u8>> = sizes
                .iter()
                .enumerate()
                .map(|(i, &len)| tagged(tag, i as u32, len))
                .collect();
            assert!(
                mine == expected,
                "writer {} whole and in order",
                tag as char
            );
        }
        assert!(dones.iter_mut().all(acked), "all acknowledged");
        assert_eq!(count(&h, B, |c| &c.corrupt), 0);
        assert_eq!(count(&h, B, |c| &c.duplicates), 0);
        assert!(h.inboxes[&B].bulk.q.is_empty(), "no body left behind");
    }

    #[test]
    fn a_restarted_sender_is_reported_once_and_its_new_session_delivers() {
        let mut h = SimHost::standard(&[A, B]);
        let mut d1 = h.send_safe(A, B, b"one".to_vec());
        h.run(20);
        assert!(acked(&mut d1));
        // A closes B and starts over: a new session, sequence numbers from 0 again.
        h.restart_sender(A, B);
        let mut d2 = h.send_safe(A, B, b"two".to_vec());
        h.run(20);
        assert_eq!(
            h.messages(B),
            vec![(A, b"one".to_vec()), (A, b"two".to_vec())]
        );
        assert_eq!(h.resets(B, A), 1, "the new session is reported once");
        assert!(acked(&mut d2));
        // Another message in the new session is no reset.
        let mut d3 = h.send_safe(A, B, b"three".to_vec());
        h.run(20);
        assert_eq!(h.resets(B, A), 1);
        assert!(acked(&mut d3));
        assert_eq!(count(&h, B, |c| &c.duplicates), 0);
    }

    #[test]
    fn a_stale_acknowledgement_completes_nothing() {
        let mut h = SimHost::standard(&[A, B]);
        let mut d1 = h.send_safe(A, B, b"one".to_vec());
        let old = header(&h.inboxes[&B].safe.q[0].1).expect("a frame").2;
        h.run(20);
        assert!(acked(&mut d1));
        h.restart_sender(A, B);
        let mut d2 = h.send_safe(A, B, b"two".to_vec());
        // B's frame is held back; an acknowledgement of A's old session for sequence number 0
        // (which the new message also has) arrives at A.
        let held = h.inboxes.get_mut(&B).and_then(|i| i.safe.q.pop_front());
        let mut ack = vec![0u8; frame::SEQUENCED];
        frame::write_header(&mut ack, frame::ACK, B, old, 0);
        h.inboxes
            .get_mut(&A)
            .expect("A's inbox")
            .safe
            .q
            .push_back((B, ack));
        h.step();
        assert!(
            !acked(&mut d2),
            "a stale session's acknowledgement completed a new message"
        );
        if let Some(f) = held {
            h.inboxes
                .get_mut(&B)
                .expect("B's inbox")
                .safe
                .q
                .push_front(f);
        }
        h.run(20);
        assert!(acked(&mut d2));
    }

    #[test]
    fn a_dead_senders_leftover_bulk_body_is_skipped() {
        let mut h = SimHost::standard(&[A, B]);
        let old = tagged(b'o', 0, 2 * BULK_MAX);
        let _lost = h.send_safe(A, B, old.clone());
        // The bulk inbox opens: A writes the bodies and their frames.
        h.open_bulk_inboxes();
        assert!(!h.inboxes[&B].bulk.q.is_empty());
        // A's frames vanish (it died between writing the bodies and the frames, or B forgot
        // it): the bodies of its old session stay in B's bulk inbox.
        let inbox = h.inboxes.get_mut(&B).expect("B's inbox");
        inbox.safe.q.clear();
        let stale = inbox.bulk.q.len();
        assert!(stale >= 2);
        h.restart_sender(A, B);
        let new = tagged(b'n', 1, 2 * BULK_MAX + 3);
        let mut done = h.send_safe(A, B, new.clone());
        h.run(50);
        // B skips the stale bodies and delivers the new message whole.
        assert_eq!(h.messages(B), vec![(A, new)]);
        assert!(acked(&mut done));
        assert_eq!(count(&h, B, |c| &c.corrupt), 0);
        assert!(
            h.inboxes[&B].bulk.q.is_empty(),
            "the stale bodies were dropped"
        );
    }
}
