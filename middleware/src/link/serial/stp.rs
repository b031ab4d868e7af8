//! The Serial Transport Protocol engine for one point-to-point line, as a pure state machine:
//! bytes in and `now` in, frames out one at a time (paced to the line's baud rate), plus the
//! next instant it needs attention. No I/O, no clock: the port driver feeds it, tests drive it
//! on a simulated clock.
//!
//! Queues and priorities (003 §5.5): ACK/NACK first (then the rare discovery announce), then
//! Safe (retransmissions before new frames), then Fast; a Fast message that has waited
//! [`StpConfig::fast_max_wait`] may take every other frame from Safe, so a 20 Hz control
//! variable stays fresh while bulk Safe traffic saturates the line. The Fast queue is a
//! [`CoalescingQueue`] bounded by `MaxMessageQueue` (newest value per key wins, oldest dropped).
//! Small messages of one class share a frame (a batch); a large one is fragmented by
//! `MaxPacketSize`.
//!
//! Safe frames each carry their own sequence number in the ARQ of
//! [`crate::link::arq`] (16 bits on the wire, widened back), so a lost fragment is resent
//! alone; Fast fragments share one sequence number as in the thesis.
//!
//! One file: the engine is one state machine (about 730 lines, the rest is its tests) whose
//! send and receive paths share the ARQ halves, the queues, the NACK list and the counters:
//! receiving an ACK or NACK changes what is sent next, sending decides what is acknowledged.
//! The parts that stand alone already live beside it (`frame`, `fragment`, `crc`,
//! [`crate::link::arq`], [`crate::link::coalesce`]); splitting the engine's `impl` across files
//! would only scatter one struct's invariants.

use std::collections::VecDeque;
use std::time::{Duration, Instant};

use bytes::BytesMut;

use super::fragment::{self, FastReassembler, SafeReassembler};
use super::frame::{Frame, FrameDecodeError, FrameDecoder};
use crate::link::arq::{AckInfo, ArqConfig, ArqReceiver, ArqSender, SynOutcome};
use crate::link::auth::{self, LinkSecurity, Opener, Profile, Sealer};
use crate::link::coalesce::{CoalescingQueue, Pushed};
use crate::link::{LinkSendError, LinkStats};

/// What [`Stp::set_ager`] takes: a message and how long it waited in the queue.
pub type Ager = std::sync::Arc<dyn Fn(&mut Vec<u8>, Duration) + Send + Sync>;

/// Tuning of one line.
#[derive(Debug, Clone, Copy)]
pub struct StpConfig {
    /// Line speed in bit/s (`baudRate`); a byte costs 10 bits (8N1).
    pub baud_rate: u32,
    /// Initial and ceiling resend timeout (`TimeToResend`).
    pub time_to_resend: Duration,
    /// Largest data per frame (`MaxPacketSize`).
    pub max_packet_size: usize,
    /// Fast queue bound (`MaxMessageQueue`).
    pub max_message_queue: usize,
    /// Safe frames in flight at most.
    pub window: u32,
    /// A Fast message waiting this long may take every other frame from Safe traffic.
    pub fast_max_wait: Duration,
    /// Incomplete Fast fragment sets are dropped after this long.
    pub fragment_expiry: Duration,
    /// How far output may run ahead of the line (what sits in OS and UART buffers).
    pub lead: Duration,
}

impl StpConfig {
    /// A configuration from the thesis' four parameters, other values defaulted.
    pub fn new(
        baud_rate: u32,
        time_to_resend: Duration,
        max_packet_size: usize,
        max_message_queue: usize,
    ) -> Self {
        let baud_rate = baud_rate.max(300);
        let max_packet_size = max_packet_size.max(16);
        // Keep about one resend period of line time in flight: enough to fill the line, and a
        // timeout never queues more retransmissions than the line carries before the next.
        let per_ttr = u64::from(baud_rate) / 10 * time_to_resend.as_millis() as u64 / 1000;
        let window = (per_ttr / (max_packet_size as u64 + 12)).clamp(8, 256) as u32;
        StpConfig {
            baud_rate,
            time_to_resend: time_to_resend.max(Duration::from_millis(10)),
            max_packet_size,
            max_message_queue: max_message_queue.max(1),
            window,
            fast_max_wait: Duration::from_millis(50),
            fragment_expiry: time_to_resend.max(Duration::from_millis(500)),
            lead: Duration::from_millis(10),
        }
    }

    fn arq(&self) -> ArqConfig {
        ArqConfig {
            initial_rto: self.time_to_resend,
            min_rto: Duration::from_millis(20).min(self.time_to_resend),
            max_rto: self.time_to_resend,
            max_window: self.window.min(16_384),
            initial_window: self.window.min(16_384),
            min_window: (self.window / 2).max(4),
        }
    }

    /// Time the line takes to carry `bytes`.
    pub fn line_time(&self, bytes: usize) -> Duration {
        Duration::from_nanos((bytes as u64) * 10 * 1_000_000_000 / u64::from(self.baud_rate))
    }

    /// Bytes the line carries in `time` (the inverse of [`StpConfig::line_time`]).
    pub fn line_bytes(&self, time: Duration) -> u64 {
        (u128::from(self.baud_rate) / 10 * time.as_millis() / 1000) as u64
    }

    /// Largest message the link carries (255 fragments).
    pub fn max_message(&self) -> usize {
        self.max_packet_size * fragment::MAX_FRAGMENTS
    }
}

/// Something the engine reports to its owner.
#[derive(Debug)]
pub enum StpEvent<T> {
    /// A whole message from the peer (Safe ones in order, exactly once).
    Message(Vec<u8>),
    /// Safe messages the peer acknowledged.
    Acked(Vec<T>),
    /// Safe messages that will never be acknowledged.
    Failed(Vec<T>, LinkSendError),
    /// The peer started a new Safe session while one was running (it restarted).
    PeerReset,
}

/// Counters beyond [`LinkStats`].
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
pub struct StpStats {
    /// What every link counts.
    pub link: LinkStats,
    /// ACK frames sent.
    pub acks_sent: u64,
    /// NACK frames sent.
    pub nacks_sent: u64,
    /// NACK frames received and acted on.
    pub nacks_received: u64,
    /// Incomplete Fast fragment sets dropped.
    pub fragments_expired: u64,
    /// Messages delivered (both classes).
    pub messages_in: u64,
    /// Payload bytes of delivered messages (goodput).
    pub payload_in: u64,
    /// Safe frames in flight now.
    pub in_flight: u64,
    /// Safe messages queued now.
    pub safe_queued: u64,
    /// Fast messages queued now.
    pub fast_queued: u64,
    /// Smoothed round trip in microseconds (0 before a sample).
    pub srtt_us: u64,
}

struct FastItem {
    msg: Vec<u8>,
    queued: Instant,
}

/// A prepared Safe frame body `[frag, total, data..]` and the completions it settles.
type Unit<T> = (Vec<u8>, Vec<T>);

/// The engine of one line. `T` is what a Safe message's completion is (a oneshot sender in the
/// link, anything in tests).
pub struct Stp<T> {
    cfg: StpConfig,
    tx: ArqSender<Vec<T>>,
    rx: ArqReceiver,
    /// Reliable messages not yet framed, each with when it was queued.
    safe_q: VecDeque<(Vec<u8>, Option<T>, Instant)>,
    /// Takes a message's time in `safe_q` off what it carries (a call's remaining time) as
    /// it leaves for the line; see [`Stp::set_ager`].
    ager: Option<Ager>,
    units: VecDeque<Unit<T>>,
    retx: VecDeque<u32>,
    fast: CoalescingQueue<u32, FastItem>,
    announce: Option<Vec<u8>>,
    pending_fast_frames: VecDeque<Frame>,
    nacks: VecDeque<(u16, u16)>,
    last_good_safe: u16,
    syn_sent_at: Option<Instant>,
    fast_seq: u16,
    last_was_safe: bool,
    line_free_at: Option<Instant>,
    inbuf: BytesMut,
    decoder: FrameDecoder,
    safe_reasm: SafeReassembler,
    fast_reasm: FastReassembler,
    stats: StpStats,
    /// Seals every frame written when the link has a key (the decoder checks them).
    sealer: Option<Sealer>,
    /// The link's name, for the log of rejected frames.
    name: String,
}

/// Widens a 16-bit wire sequence number to the 32-bit one nearest `reference`.
fn widen(seq: u16, reference: u32) -> u32 {
    let delta = seq.wrapping_sub(reference as u16) as i16;
    reference.wrapping_add(delta as i32 as u32)
}

const MAX_NACKS: usize = 16;

impl<T> Stp<T> {
    /// A fresh engine; `session` tells this run apart from a previous one (random in use).
    pub fn new(cfg: StpConfig, session: u16) -> Self {
        let max_body = cfg.max_packet_size + 16;
        Stp {
            cfg,
            tx: ArqSender::new(u32::from(session), cfg.arq()),
            rx: ArqReceiver::new(cfg.arq().max_window),
            safe_q: VecDeque::new(),
            ager: None,
            units: VecDeque::new(),
            retx: VecDeque::new(),
            fast: CoalescingQueue::new(cfg.max_message_queue),
            announce: None,
            pending_fast_frames: VecDeque::new(),
            nacks: VecDeque::new(),
            last_good_safe: 0,
            syn_sent_at: None,
            fast_seq: 0,
            last_was_safe: false,
            line_free_at: None,
            inbuf: BytesMut::new(),
            decoder: FrameDecoder::new(max_body),
            safe_reasm: SafeReassembler::new(cfg.max_message()),
            fast_reasm: FastReassembler::new(8, cfg.fragment_expiry, cfg.max_message()),
            stats: StpStats::default(),
            sealer: None,
            name: "serial".to_owned(),
        }
    }

    /// The same engine naming its link `name` in the log.
    pub fn named(mut self, name: &str) -> Self {
        name.clone_into(&mut self.name);
        self
    }

    /// The same engine sealing every frame it writes and accepting only sealed frames, when
    /// `security` is given (see [`crate::link::auth`]); `encrypt_radio` encrypts the data too.
    pub fn secured(mut self, security: Option<&LinkSecurity>) -> Self {
        if let Some(sec) = security {
            let profile = if sec.encrypt_radio {
                Profile::SERIAL_ENCRYPTED
            } else {
                Profile::SERIAL
            };
            self.sealer = Some(Sealer::new(&sec.key, profile));
            // One peer, but it may restart (a new epoch each time): a few windows suffice.
            let decoder = std::mem::replace(&mut self.decoder, FrameDecoder::new(0));
            self.decoder = decoder.with_opener(Opener::new(&sec.key, profile, 16));
        }
        self
    }

    /// The configuration.
    pub fn config(&self) -> &StpConfig {
        &self.cfg
    }

    /// Queues a best-effort message. With a `key`, it replaces a queued message of the same key
    /// in place (keeping its age and position); otherwise the oldest is dropped when full.
    pub fn push_fast(&mut self, now: Instant, key: Option<u32>, msg: Vec<u8>) {
        if let Some(item) = key.and_then(|k| self.fast.get_mut(&k)) {
            item.msg = msg;
            return;
        }
        let item = FastItem { msg, queued: now };
        if let Pushed::DroppedOldest(_) = self.fast.push(key, item) {
            self.stats.link.fast_dropped += 1;
        }
    }

    /// Queues a reliable message at `now`; `done` comes back in [`StpEvent::Acked`] or
    /// [`StpEvent::Failed`]. A message over the size limit fails at once (returned).
    pub fn push_safe(
        &mut self,
        now: Instant,
        msg: Vec<u8>,
        done: Option<T>,
    ) -> Option<(T, LinkSendError)> {
        if msg.len() > self.cfg.max_message() {
            return done.map(|d| (d, LinkSendError::TooLarge(msg.len())));
        }
        self.safe_q.push_back((msg, done, now));
        None
    }

    /// Called with each reliable message and the time it waited in the queue as it is
    /// framed for the line: the node takes that time off a call's remaining time (a message
    /// may only shrink), so a call never outlives its caller's wait however long the radio
    /// held it.
    pub fn set_ager(&mut self, ager: Ager) {
        self.ager = Some(ager);
    }

    /// A message leaving the queue at `now`, aged (see [`Stp::set_ager`]).
    fn aged(&self, now: Instant, mut msg: Vec<u8>, queued: Instant) -> Vec<u8> {
        if let Some(age) = &self.ager {
            age(&mut msg, now.saturating_duration_since(queued));
        }
        msg
    }

    /// Queues a discovery message; only the newest waits.
    pub fn push_announce(&mut self, msg: Vec<u8>) {
        self.announce = Some(msg);
    }

    /// Forgets the peer on both sides, as a restart would: every unacknowledged and queued
    /// Safe message fails, a new sender session (`session`) starts, and the receiver waits for
    /// the peer's next session. Because our receiver forgets the peer's session too, the
    /// peer's answering new session is taken as fresh: one round, not an endless exchange of
    /// resets.
    pub fn reset_peer(&mut self, session: u16, err: LinkSendError) -> Vec<StpEvent<T>> {
        self.rx = ArqReceiver::new(self.cfg.arq().max_window);
        self.safe_reasm.reset();
        self.reset_sender(session, err)
    }

    /// Fails every unacknowledged and queued Safe message and starts a new sender session
    /// (`session`); the receiving side is kept, so the peer's session goes on.
    pub fn reset_sender(&mut self, session: u16, err: LinkSendError) -> Vec<StpEvent<T>> {
        let mut failed: Vec<T> = Vec::new();
        let tx = std::mem::replace(
            &mut self.tx,
            ArqSender::new(u32::from(session), self.cfg.arq()),
        );
        failed.extend(tx.close().into_iter().flatten());
        failed.extend(self.units.drain(..).flat_map(|(_, t)| t));
        failed.extend(self.safe_q.drain(..).filter_map(|(_, t, _)| t));
        self.retx.clear();
        self.syn_sent_at = None;
        if failed.is_empty() {
            Vec::new()
        } else {
            vec![StpEvent::Failed(failed, err)]
        }
    }

    /// Feeds received bytes; events are appended to `out`.
    pub fn on_bytes(&mut self, now: Instant, bytes: &[u8], out: &mut Vec<StpEvent<T>>) {
        self.stats.link.bytes_in += bytes.len() as u64;
        self.inbuf.extend_from_slice(bytes);
        loop {
            match self.decoder.decode_bytes(&mut self.inbuf) {
                Ok(None) => break,
                Ok(Some(f)) => {
                    self.stats.link.frames_in += 1;
                    self.on_frame(now, f, out);
                }
                Err(FrameDecodeError::CrcMismatch { safe_seq: Some(s) }) => {
                    self.stats.link.corrupt += 1;
                    self.maybe_nack(s);
                }
                Err(FrameDecodeError::Auth(why)) => {
                    let total = if why.is_replay() {
                        &mut self.stats.link.replay_rejected
                    } else {
                        &mut self.stats.link.auth_rejected
                    };
                    *total += 1;
                    auth::log_reject(&self.name, "point-to-point", why, *total);
                }
                Err(_) => self.stats.link.corrupt += 1,
            }
        }
        // The decoder keeps partial frames itself; reclaim the buffer's consumed space.
        if self.inbuf.is_empty() && self.inbuf.capacity() > 4096 {
            self.inbuf = BytesMut::new();
        }
    }

    fn maybe_nack(&mut self, seq: u16) {
        let Some(session) = self.rx.current_ack().map(|a| a.session as u16) else {
            return;
        };
        let s32 = widen(seq, self.rx.expected());
        let ahead = s32.wrapping_sub(self.rx.expected());
        if ahead >= self.cfg.arq().max_window || self.rx.is_received(s32) {
            return;
        }
        if self.nacks.iter().any(|&(s, _)| s == seq) || self.nacks.len() >= MAX_NACKS {
            return;
        }
        self.nacks.push_back((seq, session));
    }

    fn deliver_body(&mut self, body: &[u8], out: &mut Vec<StpEvent<T>>) {
        let (Some(&frag), Some(&total)) = (body.first(), body.get(1)) else {
            return;
        };
        let data = &body[2..];
        if total == 0 {
            self.deliver_batch(data, out);
            return;
        }
        match self.safe_reasm.push(frag, total, data) {
            Ok(Some(m)) => self.emit(m, out),
            Ok(None) => {}
            Err(_) => self.stats.link.corrupt += 1,
        }
    }

    fn deliver_batch(&mut self, data: &[u8], out: &mut Vec<StpEvent<T>>) {
        match fragment::unbatch(data) {
            Ok(msgs) => {
                for m in msgs {
                    self.emit(m.to_vec(), out);
                }
            }
            Err(_) => self.stats.link.corrupt += 1,
        }
    }

    fn emit(&mut self, m: Vec<u8>, out: &mut Vec<StpEvent<T>>) {
        self.stats.messages_in += 1;
        self.stats.payload_in += m.len() as u64;
        out.push(StpEvent::Message(m));
    }

    fn on_frame(&mut self, now: Instant, f: Frame, out: &mut Vec<StpEvent<T>>) {
        match f {
            Frame::Data {
                safe: false,
                seq,
                frag,
                total,
                data,
            } => {
                if total == 0 {
                    self.deliver_batch(&data, out);
                } else if let Some(m) = self.fast_reasm.push(now, seq, frag, total, &data) {
                    self.emit(m, out);
                }
                self.stats.fragments_expired = self.fast_reasm.expired();
            }
            Frame::Data {
                safe: true,
                seq,
                frag,
                total,
                data,
            } => {
                if !self.rx.has_session() {
                    return;
                }
                let s32 = widen(seq, self.rx.expected());
                let mut body = Vec::with_capacity(data.len() + 2);
                body.push(frag);
                body.push(total);
                body.extend_from_slice(&data);
                let dups = self.rx.stats().duplicates;
                let mut ready: Vec<Vec<u8>> = Vec::new();
                self.rx.on_safe(s32, &body, |b| ready.push(b.to_vec()));
                self.stats.link.duplicates += self.rx.stats().duplicates - dups;
                self.last_good_safe = seq;
                for b in ready {
                    self.deliver_body(&b, out);
                }
            }
            Frame::Ack {
                session,
                next,
                sack,
                ..
            } => {
                if u32::from(session) != self.tx.session() {
                    return;
                }
                let next = widen(next, self.tx.next_seq());
                let done = self.tx.on_ack(
                    now,
                    AckInfo {
                        session: u32::from(session),
                        next,
                        sack,
                    },
                );
                let done: Vec<T> = done.into_iter().flatten().collect();
                if !done.is_empty() {
                    out.push(StpEvent::Acked(done));
                }
            }
            Frame::Nack { seq, session } => {
                if u32::from(session) == self.tx.session()
                    && self.tx.on_nack(now, widen(seq, self.tx.next_seq()))
                {
                    self.stats.nacks_received += 1;
                }
            }
            Frame::Syn { session } => match self.rx.on_syn(u32::from(session)) {
                SynOutcome::Same => {}
                SynOutcome::Fresh => self.safe_reasm.reset(),
                SynOutcome::Reset => {
                    self.safe_reasm.reset();
                    // The peer restarted: what we had in flight to it is lost with its old
                    // receiver, and our next messages start a new session it will accept.
                    let fresh = (self.tx.session() as u16).wrapping_add(1).max(1);
                    let failed = self.reset_sender(
                        fresh,
                        LinkSendError::PeerClosed("peer restarted".to_owned()),
                    );
                    out.extend(failed);
                    out.push(StpEvent::PeerReset);
                }
            },
        }
    }

    fn line_ready(&self, now: Instant) -> bool {
        self.line_free_at.is_none_or(|t| t <= now + self.cfg.lead)
    }

    fn prepare_units(&mut self, now: Instant) {
        if !self.units.is_empty() {
            return;
        }
        let Some((first, _, _)) = self.safe_q.front() else {
            return;
        };
        let mps = self.cfg.max_packet_size;
        if first.len() > mps {
            let Some((msg, done, queued)) = self.safe_q.pop_front() else {
                return;
            };
            let msg = self.aged(now, msg, queued);
            // push_safe refused anything over 255 fragments (ageing only shrinks).
            let Ok(parts) = fragment::split(&msg, mps) else {
                return;
            };
            let total = parts.len() as u8;
            let last = parts.len() - 1;
            let mut done = done;
            for (i, p) in parts.into_iter().enumerate() {
                let mut body = Vec::with_capacity(p.len() + 2);
                body.push(i as u8);
                body.push(total);
                body.extend_from_slice(p);
                let tokens = if i == last {
                    done.take().into_iter().collect()
                } else {
                    Vec::new()
                };
                self.units.push_back((body, tokens));
            }
            return;
        }
        // Batch whole messages while they fit one frame (ageing only shrinks them).
        let mut size = 0;
        let mut n = 0;
        for (m, _, _) in &self.safe_q {
            let c = fragment::batch_cost(m.len());
            if m.len() > mps || size + c > mps {
                break;
            }
            size += c;
            n += 1;
        }
        if n <= 1 {
            let Some((msg, done, queued)) = self.safe_q.pop_front() else {
                return;
            };
            let msg = self.aged(now, msg, queued);
            let mut body = Vec::with_capacity(msg.len() + 2);
            body.extend_from_slice(&[0, 1]);
            body.extend_from_slice(&msg);
            self.units.push_back((body, done.into_iter().collect()));
            return;
        }
        let mut body = Vec::with_capacity(size + 2);
        body.extend_from_slice(&[0, 0]);
        let mut tokens = Vec::new();
        let batch: Vec<_> = self.safe_q.drain(..n).collect();
        for (m, d, queued) in batch {
            fragment::batch_push(&mut body, &self.aged(now, m, queued));
            tokens.extend(d);
        }
        self.units.push_back((body, tokens));
    }

    fn safe_frame(&self, seq: u32, body: &[u8]) -> Frame {
        Frame::Data {
            safe: true,
            seq: seq as u16,
            frag: body.first().copied().unwrap_or(0),
            total: body.get(1).copied().unwrap_or(1),
            data: body.get(2..).unwrap_or_default().to_vec(),
        }
    }

    /// Whether a Safe frame could go out now (ignoring pacing).
    fn safe_ready(&self) -> bool {
        !self.retx.is_empty()
            || ((!self.units.is_empty() || !self.safe_q.is_empty()) && self.tx.can_push())
    }

    fn syn_due(&self, now: Instant) -> bool {
        !self.tx.session_acked()
            && (self.tx.in_flight() > 0 || self.safe_ready())
            && self
                .syn_sent_at
                .is_none_or(|t| now.saturating_duration_since(t) >= self.tx.rto().rto())
    }

    fn next_frame(&mut self, now: Instant) -> Option<Frame> {
        if let Some((seq, session)) = self.nacks.pop_front() {
            self.stats.nacks_sent += 1;
            return Some(Frame::Nack { seq, session });
        }
        if let Some(ack) = self.rx.take_ack() {
            self.stats.acks_sent += 1;
            return Some(Frame::Ack {
                seq: self.last_good_safe,
                session: ack.session as u16,
                next: ack.next as u16,
                sack: ack.sack,
            });
        }
        // Discovery is rare (one heartbeat per period) and keeps the peer's lease alive: it
        // must not starve behind bulk Safe traffic.
        if let Some(a) = self.announce.take() {
            return Some(self.fast_frame(vec![a]));
        }
        for seq in self.tx.due(now) {
            if !self.retx.contains(&seq) {
                self.retx.push_back(seq);
                self.stats.link.retransmitted += 1;
            }
        }
        if self.syn_due(now) {
            self.syn_sent_at = Some(now);
            return Some(Frame::Syn {
                session: self.tx.session() as u16,
            });
        }
        let fast_aged = self
            .fast
            .front()
            .is_some_and(|f| now.saturating_duration_since(f.queued) >= self.cfg.fast_max_wait);
        let fast_first = fast_aged && self.last_was_safe;
        if !fast_first {
            while let Some(seq) = self.retx.pop_front() {
                if let Some(body) = self.tx.message(seq) {
                    let frame = self.safe_frame(seq, body);
                    self.tx.mark_sent(seq, now);
                    self.last_was_safe = true;
                    return Some(frame);
                }
            }
            if self.tx.can_push() {
                self.prepare_units(now);
                if let Some((body, tokens)) = self.units.pop_front() {
                    let frame_body = body.clone();
                    let seq = self.tx.push(now, body, Some(tokens));
                    self.last_was_safe = true;
                    return Some(self.safe_frame(seq, &frame_body));
                }
            }
        }
        self.last_was_safe = false;
        if let Some(f) = self.pending_fast_frames.pop_front() {
            return Some(f);
        }
        if self.fast.is_empty() {
            return None;
        }
        let mps = self.cfg.max_packet_size;
        let mut size = 0;
        let mut n = 0;
        for f in self.fast.iter() {
            let c = fragment::batch_cost(f.msg.len());
            if size + c > mps {
                break;
            }
            size += c;
            n += 1;
        }
        let msgs: Vec<Vec<u8>> = (0..n.max(1))
            .map_while(|_| self.fast.pop_front())
            .map(|(_, f)| f.msg)
            .collect();
        Some(self.fast_frame(msgs))
    }

    /// One Fast frame for whole `msgs` (several: a batch), or the first fragment of one large
    /// message (its other fragments are queued at the front, sharing the sequence number).
    fn fast_frame(&mut self, mut msgs: Vec<Vec<u8>>) -> Frame {
        let seq = self.fast_seq;
        self.fast_seq = self.fast_seq.wrapping_add(1);
        if msgs.len() > 1 {
            let mut data = Vec::new();
            for m in &msgs {
                fragment::batch_push(&mut data, m);
            }
            return Frame::Data {
                safe: false,
                seq,
                frag: 0,
                total: 0,
                data,
            };
        }
        let msg = msgs.pop().unwrap_or_default();
        match fragment::split(&msg, self.cfg.max_packet_size) {
            Ok(parts) if parts.len() > 1 => {
                let total = parts.len() as u8;
                let frames: Vec<Frame> = parts
                    .iter()
                    .enumerate()
                    .map(|(i, p)| Frame::Data {
                        safe: false,
                        seq,
                        frag: i as u8,
                        total,
                        data: p.to_vec(),
                    })
                    .collect();
                self.pending_fast_frames.extend(frames);
                // `parts.len() > 1`, so there is a first fragment.
                self.pending_fast_frames
                    .pop_front()
                    .unwrap_or(Frame::Syn { session: 0 })
            }
            Err(_) => {
                // Over 255 fragments: best effort means dropping it.
                self.stats.link.fast_dropped += 1;
                Frame::Data {
                    safe: false,
                    seq,
                    frag: 0,
                    total: 0,
                    data: Vec::new(),
                }
            }
            _ => Frame::Data {
                safe: false,
                seq,
                frag: 0,
                total: 1,
                data: msg,
            },
        }
    }

    /// The next frame to write, as wire bytes, if the line (paced to the baud rate) can take it
    /// now. Call until `None`, then sleep until [`Stp::poll_at`] or new input.
    pub fn poll_transmit(&mut self, now: Instant) -> Option<Vec<u8>> {
        if !self.line_ready(now) {
            return None;
        }
        let frame = self.next_frame(now)?;
        let wire = frame.encode_sealed(self.sealer.as_ref());
        let start = self.line_free_at.map_or(now, |t| t.max(now));
        self.line_free_at = Some(start + self.cfg.line_time(wire.len()));
        self.stats.link.frames_out += 1;
        self.stats.link.bytes_out += wire.len() as u64;
        Some(wire)
    }

    fn has_output(&self) -> bool {
        !self.nacks.is_empty()
            || self.rx.ack_pending()
            || self.safe_ready()
            || self.tx.nack_pending()
            || self.announce.is_some()
            || !self.pending_fast_frames.is_empty()
            || !self.fast.is_empty()
    }

    /// When the engine next needs [`Stp::poll_transmit`] (or [`Stp::expire`]) called.
    pub fn poll_at(&self, now: Instant) -> Option<Instant> {
        let line = self
            .line_free_at
            .map_or(now, |t| t.checked_sub(self.cfg.lead).unwrap_or(t).max(now));
        let output = self.has_output().then_some(line);
        let syn = (!self.tx.session_acked() && self.tx.in_flight() > 0)
            .then(|| self.syn_sent_at.map(|t| t + self.tx.rto().rto()))
            .flatten();
        [
            output,
            self.tx.next_deadline().map(|d| d.max(line)),
            syn.map(|d| d.max(line)),
            self.fast_reasm.next_expiry(),
        ]
        .into_iter()
        .flatten()
        .min()
    }

    /// Drops expired Fast fragment sets.
    pub fn expire(&mut self, now: Instant) {
        self.fast_reasm.expire(now);
        self.stats.fragments_expired = self.fast_reasm.expired();
    }

    /// Counters and gauges.
    pub fn stats(&self) -> StpStats {
        let mut s = self.stats;
        s.in_flight = self.tx.in_flight() as u64;
        s.safe_queued = (self.safe_q.len() + self.units.len()) as u64;
        s.fast_queued = self.fast.len() as u64;
        s.srtt_us = self.tx.rto().srtt().map_or(0, |d| d.as_micros() as u64);
        s.link.rtt_us = s.srtt_us;
        s.link.safe_queued = s.safe_queued + s.in_flight;
        s.link.fast_queued = s.fast_queued;
        s
    }

    /// Whether Safe work is outstanding (queued or unacknowledged).
    pub fn safe_pending(&self) -> bool {
        !self.safe_q.is_empty() || !self.units.is_empty() || self.tx.in_flight() > 0
    }
}

#[cfg(test)]
mod tests {
    use super::super::sim::{Faults, Side, SimPair};
    use super::*;

    fn cfg(baud: u32, mps: usize) -> StpConfig {
        StpConfig::new(baud, Duration::from_millis(1500), mps, 20)
    }

    #[test]
    fn line_bytes_is_the_inverse_of_line_time() {
        let c = cfg(115_200, 64);
        assert_eq!(c.line_bytes(Duration::from_secs(4)), 46_080);
        assert_eq!(c.line_time(46_080), Duration::from_secs(4));
        assert_eq!(
            cfg(57_600, 64).line_bytes(Duration::from_millis(500)),
            2_880
        );
    }

    #[test]
    fn widen_picks_the_nearest() {
        assert_eq!(widen(5, 3), 5);
        assert_eq!(widen(0xFFFF, 0x1_0001), 0xFFFF);
        assert_eq!(widen(2, 0xFFFE), 0x1_0002);
        assert_eq!(widen(0, 0), 0);
    }

    /// Safe traffic at 1 % byte errors: every message exactly once, in order, every
    /// completion acknowledged; the line stays usable (goodput well above zero).
    #[test]
    fn safe_exactly_once_in_order_over_one_percent_byte_errors() {
        let faults = Faults {
            loss: 0.005,
            corrupt: 0.005,
        };
        let mut p = SimPair::new(cfg(57_600, 64), faults, 7, Duration::from_millis(5));
        let n = 400u64;
        for i in 0..n {
            let mut m = i.to_le_bytes().to_vec();
            m.resize(8 + (i as usize * 13) % 200, 0x10);
            assert!(p.a.push_safe(Instant::now(), m, Some(i)).is_none());
        }
        let mut got = Vec::new();
        let mut acked = Vec::new();
        let until = p.now + Duration::from_secs(120);
        p.run(
            until,
            Duration::from_millis(10),
            |_| {},
            |side, _, e| match (side, e) {
                (Side::B, StpEvent::Message(m)) => {
                    got.push(u64::from_le_bytes(m[..8].try_into().unwrap()))
                }
                (Side::A, StpEvent::Acked(t)) => acked.extend(t),
                (_, StpEvent::Failed(..)) => panic!("failed"),
                _ => {}
            },
        );
        assert_eq!(
            got.len() as u64,
            n,
            "A {:?}\nB {:?}",
            p.a.stats(),
            p.b.stats()
        );
        assert_eq!(got, (0..n).collect::<Vec<_>>());
        acked.sort_unstable();
        assert_eq!(acked, (0..n).collect::<Vec<_>>());
        let s = p.a.stats();
        assert!(s.link.retransmitted > 0);
        assert!(p.b.stats().nacks_sent > 0, "NACKs are used");
    }

    #[test]
    fn fast_queue_coalesces_by_key_and_drops_the_oldest() {
        let t0 = Instant::now();
        let mut s: Stp<u64> = Stp::new(cfg(57_600, 300), 1);
        s.push_fast(t0, Some(1), b"a1".to_vec());
        s.push_fast(t0, Some(1), b"a2".to_vec());
        assert_eq!(s.stats().fast_queued, 1);
        for i in 0..25u8 {
            s.push_fast(t0, None, vec![i]);
        }
        assert_eq!(s.stats().fast_queued, 20);
        assert_eq!(s.stats().link.fast_dropped, 6);
        // Everything left goes out in one batch frame.
        let f = s.poll_transmit(t0).unwrap();
        let mut d = FrameDecoder::new(1000);
        let mut b = BytesMut::from(&f[..]);
        let Ok(Some(Frame::Data { total: 0, data, .. })) = d.decode_bytes(&mut b) else {
            panic!("not a batch");
        };
        let msgs = fragment::unbatch(&data).unwrap();
        assert_eq!(msgs.len(), 20);
        assert_eq!(msgs[0], &[5u8][..]);
        assert!(s.poll_transmit(t0).is_none());
    }

    #[test]
    fn output_is_paced_to_the_baud_rate() {
        let t0 = Instant::now();
        let mut s: Stp<u64> = Stp::new(cfg(57_600, 300), 1);
        for _ in 0..10 {
            s.push_safe(Instant::now(), vec![1; 300], None);
        }
        let mut sent = 0;
        while let Some(f) = s.poll_transmit(t0) {
            sent += f.len();
        }
        // One frame (plus the SYN) within the 10 ms lead, not the whole queue.
        assert!(sent < 400, "{sent}");
        let at = s.poll_at(t0).unwrap();
        assert!(at > t0 + Duration::from_millis(40), "{:?}", at - t0);
    }

    #[test]
    fn priorities_ack_then_safe_then_fast() {
        let t0 = Instant::now();
        let mut p = SimPair::new(cfg(57_600, 300), Faults::default(), 1, Duration::ZERO);
        p.a.push_safe(Instant::now(), b"s".to_vec(), None);
        let until = p.now + Duration::from_millis(200);
        p.run(until, Duration::from_millis(5), |_| {}, |_, _, _| {});
        // B owes nothing now; give both classes to A and an ack to B.
        p.a.push_fast(t0, None, b"f".to_vec());
        p.a.push_safe(Instant::now(), b"s2".to_vec(), None);
        let f = p.a.poll_transmit(p.now + Duration::from_secs(1)).unwrap();
        assert_eq!(f[1], TYPE_SAFE);
        let f = p.a.poll_transmit(p.now + Duration::from_secs(2)).unwrap();
        assert_eq!(f[1], TYPE_FAST);
        use super::super::frame::TYPE_FAST;
        use super::super::frame::TYPE_SAFE;
    }

    /// A 20 Hz coalesced control variable keeps a small age while Safe bulk traffic saturates
    /// the line (the seed measured 10 s).
    #[test]
    fn control_variable_stays_fresh_under_safe_saturation() {
        let mut p = SimPair::new(
            cfg(57_600, 300),
            Faults::default(),
            3,
            Duration::from_millis(5),
        );
        let start = p.now;
        let mut next_ctl = start;
        let mut ages: Vec<Duration> = Vec::new();
        let mut safe_got = 0usize;
        let until = start + Duration::from_secs(20);
        p.run(
            until,
            Duration::from_millis(5),
            |p| {
                if p.a.stats().safe_queued < 50 {
                    for _ in 0..50 {
                        p.a.push_safe(Instant::now(), vec![0x55; 1300], None);
                    }
                }
                if p.now >= next_ctl {
                    let stamp = (p.now - start).as_micros() as u64;
                    p.a.push_fast(p.now, Some(9), stamp.to_le_bytes().to_vec());
                    next_ctl += Duration::from_millis(50);
                }
            },
            |side, now, e| {
                if let (Side::B, StpEvent::Message(m)) = (side, e) {
                    if m.len() == 8 {
                        let stamp = u64::from_le_bytes(m[..8].try_into().unwrap());
                        ages.push((now - start) - Duration::from_micros(stamp));
                    } else {
                        safe_got += 1;
                    }
                }
            },
        );
        ages.sort();
        let p99 = ages[ages.len() * 99 / 100];
        assert!(ages.len() > 150, "{}", ages.len());
        assert!(p99 < Duration::from_millis(150), "p99 {p99:?}");
        // Safe traffic still gets most of the line: > 2/3 of 46 kbit/s.
        let goodput = safe_got as f64 * 1300.0 * 8.0 / 20.0;
        assert!(goodput > 30_000.0, "{goodput}");
    }

    #[test]
    fn a_restarted_peer_is_detected_and_in_flight_messages_fail() {
        let mut p = SimPair::new(cfg(115_200, 300), Faults::default(), 3, Duration::ZERO);
        p.a.push_safe(Instant::now(), b"one".to_vec(), Some(1));
        p.b.push_safe(Instant::now(), b"from b".to_vec(), None);
        let until = p.now + Duration::from_millis(300);
        let mut ok = Vec::new();
        p.run(
            until,
            Duration::from_millis(5),
            |_| {},
            |s, _, e| {
                if let (Side::A, StpEvent::Acked(t)) = (s, e) {
                    ok.extend(t)
                }
            },
        );
        assert_eq!(ok, vec![1]);
        // B restarts (new engine, new session) and sends; A must see a reset.
        p.b = Stp::new(cfg(115_200, 300), 0x3333);
        p.b.push_safe(Instant::now(), b"hi".to_vec(), None);
        let mut resets = 0;
        let mut got = Vec::new();
        let until = p.now + Duration::from_millis(500);
        p.run(
            until,
            Duration::from_millis(5),
            |_| {},
            |s, _, e| match (s, e) {
                (Side::A, StpEvent::PeerReset) => resets += 1,
                (Side::A, StpEvent::Message(m)) => got.push(m),
                _ => {}
            },
        );
        assert_eq!(resets, 1);
        assert_eq!(got, vec![b"hi".to_vec()]);
    }

    /// A side that forgets its peer (a lease expired on a busy radio) starts over once: the
    /// peer answers with one new session, and the two do not keep resetting each other.
    #[test]
    fn forgetting_the_peer_resets_once_and_traffic_resumes() {
        let mut p = SimPair::new(cfg(115_200, 300), Faults::default(), 5, Duration::ZERO);
        p.a.push_safe(Instant::now(), b"before".to_vec(), None);
        p.b.push_safe(Instant::now(), b"before".to_vec(), None);
        let until = p.now + Duration::from_millis(300);
        p.run(until, Duration::from_millis(5), |_| {}, |_, _, _| {});
        let _ =
            p.a.reset_peer(0x4444, LinkSendError::PeerClosed("lease expired".into()));
        let mut resets = (0, 0);
        let mut got = (Vec::new(), Vec::new());
        // Both keep talking for a while after the reset.
        for round in 0..20u8 {
            p.a.push_safe(Instant::now(), vec![b'a', round], None);
            p.b.push_safe(Instant::now(), vec![b'b', round], None);
            let until = p.now + Duration::from_millis(100);
            p.run(
                until,
                Duration::from_millis(5),
                |_| {},
                |s, _, e| match (s, e) {
                    (Side::A, StpEvent::PeerReset) => resets.0 += 1,
                    (Side::B, StpEvent::PeerReset) => resets.1 += 1,
                    (Side::A, StpEvent::Message(m)) => got.0.push(m),
                    (Side::B, StpEvent::Message(m)) => got.1.push(m),
                    _ => {}
                },
            );
        }
        assert_eq!(
            resets,
            (0, 1),
            "B sees A's new session once; A's answer is fresh to it"
        );
        let expect = |c: u8| (0..20u8).map(|r| vec![c, r]).collect::<Vec<_>>();
        // Everything A sent after the reset reaches B; B's stream to A resumes from its own
        // new session (what was in flight when A forgot it failed on B's side).
        assert_eq!(got.1, expect(b'a'));
        assert!(got.0.ends_with(&expect(b'b')[5..]), "{:?}", got.0);
    }

    #[test]
    fn large_fast_messages_fragment_and_reassemble() {
        let mut p = SimPair::new(cfg(115_200, 100), Faults::default(), 3, Duration::ZERO);
        let big: Vec<u8> = (0..2500u32).map(|i| i as u8).collect();
        p.a.push_fast(p.now, None, big.clone());
        let mut got = Vec::new();
        let until = p.now + Duration::from_millis(500);
        p.run(
            until,
            Duration::from_millis(5),
            |_| {},
            |s, _, e| {
                if let (Side::B, StpEvent::Message(m)) = (s, e) {
                    got.push(m)
                }
            },
        );
        assert_eq!(got, vec![big]);
    }

    #[test]
    fn oversized_safe_messages_are_refused() {
        let mut s: Stp<u64> = Stp::new(cfg(57_600, 32), 1);
        let r = s.push_safe(Instant::now(), vec![0; 32 * 255 + 1], Some(5));
        assert!(matches!(r, Some((5, LinkSendError::TooLarge(_)))));
    }
}
