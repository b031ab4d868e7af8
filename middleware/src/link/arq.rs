//! Automatic repeat request for the safe class: sequence numbers, cumulative + selective
//! acknowledgements, retransmission with an adaptive timeout, duplicate suppression, in-order
//! delivery, and a congestion window so retransmissions cannot saturate a weak link.
//!
//! Pure: no I/O, no clocks. The caller passes `now`, writes what [`ArqSender::push`] and
//! [`ArqSender::due`] return, feeds received acknowledgements and sleeps until
//! [`ArqSender::next_deadline`]. Sequence numbers are `u32` and compared with wrapping
//! arithmetic, so a link may carry fewer bits on the wire (serial uses 16) and widen them back.

use std::collections::{BTreeMap, VecDeque};
use std::time::{Duration, Instant};

/// An acknowledgement of a receiver's state for one sender session.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct AckInfo {
    /// The sender session acknowledged.
    pub session: u32,
    /// Every seq below this was received.
    pub next: u32,
    /// Bit i set: seq `next + 1 + i` was received as well.
    pub sack: u64,
}

/// Tuning of one ARQ session.
#[derive(Debug, Clone, Copy)]
pub struct ArqConfig {
    /// Retransmission timeout before any round trip is measured.
    pub initial_rto: Duration,
    /// Lower bound of the adaptive timeout.
    pub min_rto: Duration,
    /// Upper bound (the serial link's `TimeToResend`).
    pub max_rto: Duration,
    /// Most messages in flight (also the receiver's reorder buffer).
    pub max_window: u32,
    /// Congestion window at start, in messages.
    pub initial_window: u32,
    /// Smallest congestion window after a loss (a paced link such as serial cannot congest
    /// itself, so it keeps enough in flight to fill the line).
    pub min_window: u32,
}

/// When retransmission gives up: a message still unacknowledged after both this many
/// transmissions and this long since it was first sent means the peer is gone, or was never
/// there (a spoofed address), and the session is closed rather than kept forever.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct RetryLimit {
    /// Transmissions of one message (the first included).
    pub transmissions: u32,
    /// Time since its first transmission.
    pub after: Duration,
}

impl RetryLimit {
    /// Defaults for a LAN: well past any lease a LAN peer has (it would have been dropped
    /// for silence first), and many round trips with backoff.
    pub fn lan() -> Self {
        RetryLimit {
            transmissions: 8,
            after: Duration::from_secs(10),
        }
    }
}

/// Default bound on the bytes a receiver holds out of order for one sender: beyond it, a
/// message ahead of a gap is dropped and counted (the sender retransmits it), so a peer that
/// never fills its gap cannot make the node hold its whole window of large messages.
pub const MAX_REORDER_BYTES: usize = 4 << 20;

impl ArqConfig {
    /// Defaults for a LAN.
    pub fn lan() -> Self {
        ArqConfig {
            initial_rto: Duration::from_millis(200),
            // Not less: a receiver's acknowledgement waits for its thread like any task, and
            // a loaded host delays it by milliseconds now and then. At 5 ms, a loopback stream
            // timed out spuriously in about one run of three (up to 15,000 retransmissions a
            // run, each episode collapsing the congestion window); at 25 ms (QUIC's default
            // acknowledgement delay allowance) none did. A lost message ahead of later ones
            // is retransmitted sooner, when they are acknowledged (`due`'s holes).
            min_rto: Duration::from_millis(25),
            max_rto: Duration::from_secs(2),
            // A window of 4,096 held a 64 B event stream at ~3.6 M/s on loopback with the
            // sender idle a third of the time, waiting for acknowledgements; 16,384 keeps it
            // sending (~12 % more). The receiver still holds at most `MAX_REORDER_BYTES`.
            max_window: 16_384,
            initial_window: 128,
            min_window: 4,
        }
    }
}

/// Smoothed round-trip estimate (RFC 6298).
#[derive(Debug, Clone)]
pub struct RtoEstimator {
    srtt: Option<Duration>,
    rttvar: Duration,
    rto: Duration,
    min: Duration,
    max: Duration,
}

impl RtoEstimator {
    /// A new estimator.
    pub fn new(initial: Duration, min: Duration, max: Duration) -> Self {
        RtoEstimator {
            srtt: None,
            rttvar: Duration::ZERO,
            rto: initial.clamp(min, max),
            min,
            max,
        }
    }

    /// Feeds one round-trip sample (of a message sent once, per Karn's rule).
    pub fn sample(&mut self, rtt: Duration) {
        match self.srtt {
            None => {
                self.srtt = Some(rtt);
                self.rttvar = rtt / 2;
            }
            Some(srtt) => {
                let diff = srtt.abs_diff(rtt);
                self.rttvar = (self.rttvar * 3 + diff) / 4;
                self.srtt = Some((srtt * 7 + rtt) / 8);
            }
        }
        let srtt = self.srtt.unwrap_or(rtt);
        self.rto =
            (srtt + (self.rttvar * 4).max(Duration::from_millis(1))).clamp(self.min, self.max);
    }

    /// Current timeout.
    pub fn rto(&self) -> Duration {
        self.rto
    }

    /// Smoothed round trip, if measured.
    pub fn srtt(&self) -> Option<Duration> {
        self.srtt
    }
}

#[derive(Debug)]
struct InFlight<T> {
    seq: u32,
    msg: bytes::Bytes,
    sent_at: Instant,
    /// When it was first sent (`sent_at` moves with each retransmission).
    first_sent: Instant,
    transmissions: u32,
    token: Option<T>,
    acked: bool,
    nacked: bool,
}

impl<T> InFlight<T> {
    /// Retransmitted or waiting for a retransmission: its timer no longer follows the order
    /// of first transmissions (see `ArqSender::irregular`).
    fn irregular(&self) -> bool {
        !self.acked && (self.transmissions > 1 || self.nacked)
    }
}

/// Counters of a sender.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct ArqSenderStats {
    /// Messages sent for the first time.
    pub sent: u64,
    /// Retransmissions.
    pub retransmitted: u64,
    /// Messages acknowledged.
    pub acked: u64,
}

/// The sending half of a session.
#[derive(Debug)]
pub struct ArqSender<T> {
    session: u32,
    session_acked: bool,
    next_seq: u32,
    in_flight: VecDeque<InFlight<T>>,
    /// Bytes of the messages in flight not acknowledged yet.
    in_flight_bytes: usize,
    /// Bytes acknowledged since the session started.
    acked_bytes: u64,
    /// Latest send time among acknowledged messages (time-based loss detection: a message
    /// sent before one that was acknowledged is lost once a round trip has passed).
    latest_acked_sent: Option<Instant>,
    rto: RtoEstimator,
    cwnd: f64,
    ssthresh: f64,
    config: ArqConfig,
    stats: ArqSenderStats,
    /// Unacknowledged messages that were retransmitted or NACKed. While there are none (the
    /// steady state of a lossless stream), every message in flight was sent once, in order:
    /// their timers expire in queue order, so [`ArqSender::due`] and
    /// [`ArqSender::next_deadline`] look at the front only instead of the whole window (a
    /// scan of 4,096 messages per flush was most of the cost of a fast event stream).
    irregular: usize,
    /// A first transmission's time was moved by [`ArqSender::mark_sent`]: queue order no
    /// longer says timer order, so every scan is a full one.
    unordered: bool,
}

fn after(a: u32, b: u32) -> bool {
    (a.wrapping_sub(b) as i32) > 0
}

impl<T> ArqSender<T> {
    /// A sender for session `session` (random, so a restarted peer is told apart).
    pub fn new(session: u32, config: ArqConfig) -> Self {
        ArqSender {
            session,
            session_acked: false,
            next_seq: 0,
            in_flight: VecDeque::new(),
            in_flight_bytes: 0,
            acked_bytes: 0,
            latest_acked_sent: None,
            rto: RtoEstimator::new(config.initial_rto, config.min_rto, config.max_rto),
            cwnd: f64::from(config.initial_window.min(config.max_window)),
            ssthresh: f64::from(config.max_window),
            config,
            stats: ArqSenderStats::default(),
            irregular: 0,
            unordered: false,
        }
    }

    /// Whether queue order is timer order (see `irregular`).
    fn ordered(&self) -> bool {
        self.irregular == 0 && !self.unordered
    }

    /// The session id.
    pub fn session(&self) -> u32 {
        self.session
    }

    /// Whether the peer has acknowledged this session (until then every datagram carrying safe
    /// entries also carries the SYN).
    pub fn session_acked(&self) -> bool {
        self.session_acked
    }

    /// Whether the window admits another message.
    pub fn can_push(&self) -> bool {
        (self.in_flight.len() as f64) < self.cwnd.min(f64::from(self.config.max_window))
    }

    /// Messages in flight.
    pub fn in_flight(&self) -> usize {
        self.in_flight.len()
    }

    /// Bytes of the messages in flight that are not acknowledged yet.
    pub fn in_flight_bytes(&self) -> usize {
        self.in_flight_bytes
    }

    /// Bytes acknowledged since the session started.
    pub fn acked_bytes(&self) -> u64 {
        self.acked_bytes
    }

    /// Registers `msg` as sent now and returns its sequence number.
    pub fn push(&mut self, now: Instant, msg: impl Into<bytes::Bytes>, token: Option<T>) -> u32 {
        let msg = msg.into();
        let seq = self.next_seq;
        self.next_seq = self.next_seq.wrapping_add(1);
        self.in_flight_bytes += msg.len();
        self.in_flight.push_back(InFlight {
            seq,
            msg,
            sent_at: now,
            first_sent: now,
            transmissions: 1,
            token,
            acked: false,
            nacked: false,
        });
        self.stats.sent += 1;
        seq
    }

    /// The sequence number the next [`ArqSender::push`] assigns (links with narrow sequence
    /// fields widen received acknowledgements around it).
    pub fn next_seq(&self) -> u32 {
        self.next_seq
    }

    /// A negative acknowledgement: the peer received `seq` corrupt. It is retransmitted by the
    /// next [`ArqSender::due`] unless it was already resent within half a round trip (the NACK
    /// then refers to an older copy). Corruption is not congestion: the window is kept.
    /// Returns whether the NACK was taken.
    pub fn on_nack(&mut self, now: Instant, seq: u32) -> bool {
        let guard = self.rto.srtt().map_or(Duration::ZERO, |s| s / 2);
        let Some(base) = self.in_flight.front().map(|f| f.seq) else {
            return false;
        };
        let idx = seq.wrapping_sub(base) as usize;
        match self.in_flight.get_mut(idx) {
            Some(f)
                if f.seq == seq
                    && !f.acked
                    && now.saturating_duration_since(f.sent_at) >= guard =>
            {
                if !f.irregular() {
                    self.irregular += 1;
                }
                f.nacked = true;
                true
            }
            _ => false,
        }
    }

    /// Restarts the timer of `seq` at `now`: a paced link calls it when a retransmission
    /// returned by [`ArqSender::due`] actually leaves, which may be later than `due` ran.
    pub fn mark_sent(&mut self, seq: u32, now: Instant) {
        let Some(base) = self.in_flight.front().map(|f| f.seq) else {
            return;
        };
        if let Some(f) = self.in_flight.get_mut(seq.wrapping_sub(base) as usize) {
            if f.seq == seq {
                if !f.irregular() && f.sent_at != now {
                    self.unordered = true;
                }
                f.sent_at = now;
            }
        }
    }

    /// Whether some message waits for retransmission because of a NACK.
    pub fn nack_pending(&self) -> bool {
        self.irregular > 0 && self.in_flight.iter().any(|f| f.nacked && !f.acked)
    }

    /// The bytes of an in-flight message.
    pub fn message(&self, seq: u32) -> Option<&[u8]> {
        let base = self.in_flight.front()?.seq;
        let idx = seq.wrapping_sub(base) as usize;
        self.in_flight
            .get(idx)
            .filter(|f| f.seq == seq && !f.acked)
            .map(|f| &f.msg[..])
    }

    fn deadline_of(&self, f: &InFlight<T>) -> Instant {
        let backoff = 1u32 << (f.transmissions - 1).min(6);
        f.sent_at + (self.rto.rto() * backoff).min(self.config.max_rto)
    }

    /// Applies an acknowledgement; returns the tokens of newly acknowledged messages.
    pub fn on_ack(&mut self, now: Instant, ack: AckInfo) -> Vec<T> {
        let mut done = Vec::new();
        if ack.session != self.session {
            return done;
        }
        self.session_acked = true;
        let mut newly = 0u32;
        // Only the messages below `next` and the 64 after it can be acknowledged: the queue
        // holds consecutive sequence numbers, so that is a prefix of it.
        let base = self.in_flight.front().map_or(ack.next, |f| f.seq);
        let reach = (ack.next.wrapping_sub(base) as usize).saturating_add(65);
        let reach = if after(base, ack.next) { 65 } else { reach };
        let mut irregular_acked = 0;
        // One round-trip sample per acknowledgement (RFC 6298), from the newest message it
        // acknowledges that was sent once (Karn): the older ones in a cumulative ack waited for
        // the window, not the path, and sampling each cost a division per message.
        let mut newest_sent_once: Option<Instant> = None;
        for f in self.in_flight.iter_mut().take(reach) {
            if f.acked {
                continue;
            }
            let offset = f.seq.wrapping_sub(ack.next);
            let sacked = (1..=64).contains(&offset) && ack.sack & (1u64 << (offset - 1)) != 0;
            if !(after(ack.next, f.seq) || sacked) {
                continue;
            }
            if f.irregular() {
                irregular_acked += 1;
            }
            f.acked = true;
            self.in_flight_bytes = self.in_flight_bytes.saturating_sub(f.msg.len());
            self.acked_bytes += f.msg.len() as u64;
            newly += 1;
            if f.transmissions == 1 && newest_sent_once.is_none_or(|t| f.sent_at > t) {
                newest_sent_once = Some(f.sent_at);
            }
            if let Some(t) = f.token.take() {
                done.push(t);
            }
            if self.latest_acked_sent.is_none_or(|t| f.sent_at > t) {
                self.latest_acked_sent = Some(f.sent_at);
            }
        }
        self.irregular -= irregular_acked;
        if let Some(sent) = newest_sent_once {
            self.rto.sample(now.saturating_duration_since(sent));
        }
        while self.in_flight.front().is_some_and(|f| f.acked) {
            self.in_flight.pop_front();
        }
        self.stats.acked += u64::from(newly);
        // Additive increase: slow start below the threshold, then one message per window.
        for _ in 0..newly {
            if self.cwnd < self.ssthresh {
                self.cwnd += 1.0;
            } else {
                self.cwnd += 1.0 / self.cwnd;
            }
        }
        self.cwnd = self.cwnd.min(f64::from(self.config.max_window));
        done
    }

    /// Sequence numbers to retransmit now (timer expired, or a later message was acknowledged
    /// while this one has been out for longer than the smoothed round trip). Each returned
    /// message is marked as sent again at `now`.
    pub fn due(&mut self, now: Instant) -> Vec<u32> {
        let mut out = Vec::new();
        let srtt = self.rto.srtt();
        let mut timed_out = false;
        let mut congested = false;
        let latest = self.latest_acked_sent;
        // In order, the first message that is neither expired nor a hole ends the scan: every
        // later one was sent after it, once, and is not due either.
        let ordered = self.ordered();
        for i in 0..self.in_flight.len() {
            let f = &self.in_flight[i];
            if f.acked {
                continue;
            }
            let expired = now >= self.deadline_of(f);
            let hole = match (latest, srtt) {
                (Some(t), Some(srtt)) => {
                    t > f.sent_at && now.saturating_duration_since(f.sent_at) >= srtt + srtt / 4
                }
                _ => false,
            };
            let nacked = f.nacked;
            if !(expired || hole || nacked) && ordered {
                break;
            }
            if expired || hole || nacked {
                timed_out |= expired;
                congested |= expired || hole;
                if !f.irregular() {
                    self.irregular += 1;
                }
                let f = &mut self.in_flight[i];
                f.nacked = false;
                f.sent_at = now;
                f.transmissions += 1;
                out.push(f.seq);
            }
        }
        if !out.is_empty() {
            self.stats.retransmitted += out.len() as u64;
        }
        if congested {
            // Multiplicative decrease, once per loss episode.
            let floor = f64::from(self.config.min_window.max(1));
            self.ssthresh = (self.cwnd / 2.0).max(floor);
            self.cwnd = if timed_out { floor } else { self.ssthresh };
        }
        out
    }

    /// When [`ArqSender::due`] should be called next.
    pub fn next_deadline(&self) -> Option<Instant> {
        if self.ordered() {
            // The front is unacknowledged (acknowledged ones leave the front at once) and,
            // sent first and once, has the earliest timer.
            return self
                .in_flight
                .iter()
                .find(|f| !f.acked)
                .map(|f| self.deadline_of(f));
        }
        self.in_flight
            .iter()
            .filter(|f| !f.acked)
            .map(|f| {
                if f.nacked {
                    f.sent_at
                } else {
                    self.deadline_of(f)
                }
            })
            .min()
    }

    /// Whether the oldest unacknowledged message has reached `limit` at `now`: the caller
    /// closes the session (failing what is in flight with [`ArqSender::close`]).
    pub fn exhausted(&self, now: Instant, limit: RetryLimit) -> bool {
        self.in_flight.iter().find(|f| !f.acked).is_some_and(|f| {
            f.transmissions >= limit.transmissions
                && now.saturating_duration_since(f.first_sent) >= limit.after
        })
    }

    /// Ends the session; returns the tokens of everything never acknowledged.
    pub fn close(self) -> Vec<T> {
        self.in_flight.into_iter().filter_map(|f| f.token).collect()
    }

    /// The tuning this sender was created with.
    pub fn config(&self) -> ArqConfig {
        self.config
    }

    /// Counters.
    pub fn stats(&self) -> ArqSenderStats {
        self.stats
    }

    /// The round-trip estimator.
    pub fn rto(&self) -> &RtoEstimator {
        &self.rto
    }
}

/// What a SYN meant to a receiver.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum SynOutcome {
    /// First session from this peer.
    Fresh,
    /// The session already known (a retransmitted SYN).
    Same,
    /// A different session: the peer restarted its sending side.
    Reset,
}

/// Counters of a receiver.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct ArqReceiverStats {
    /// Messages delivered in order.
    pub delivered: u64,
    /// Duplicates dropped.
    pub duplicates: u64,
    /// Messages beyond the reorder window dropped.
    pub out_of_window: u64,
    /// Safe messages dropped because no session was started.
    pub without_session: u64,
    /// Messages ahead of a gap dropped because the reorder buffer held its byte bound.
    pub over_budget: u64,
}

/// The receiving half of a session.
#[derive(Debug)]
pub struct ArqReceiver {
    session: Option<u32>,
    next: u32,
    buffered: BTreeMap<u32, Vec<u8>>,
    /// Bytes of the messages in `buffered`.
    buffered_bytes: usize,
    max_buffered_bytes: usize,
    max_window: u32,
    ack_pending: bool,
    stats: ArqReceiverStats,
}

impl ArqReceiver {
    /// A receiver with a reorder buffer of `max_window` messages and at most
    /// [`MAX_REORDER_BYTES`].
    pub fn new(max_window: u32) -> Self {
        ArqReceiver {
            session: None,
            next: 0,
            buffered: BTreeMap::new(),
            buffered_bytes: 0,
            max_buffered_bytes: MAX_REORDER_BYTES,
            max_window,
            ack_pending: false,
            stats: ArqReceiverStats::default(),
        }
    }

    /// The same receiver holding at most `bytes` out of order.
    pub fn with_max_buffered_bytes(mut self, bytes: usize) -> Self {
        self.max_buffered_bytes = bytes;
        self
    }

    /// Bytes held out of order now.
    pub fn buffered_bytes(&self) -> usize {
        self.buffered_bytes
    }

    /// Handles a SYN (the sender's session id).
    pub fn on_syn(&mut self, session: u32) -> SynOutcome {
        self.ack_pending = true;
        match self.session {
            Some(s) if s == session => SynOutcome::Same,
            prev => {
                self.session = Some(session);
                self.next = 0;
                self.buffered.clear();
                self.buffered_bytes = 0;
                if prev.is_some() {
                    SynOutcome::Reset
                } else {
                    SynOutcome::Fresh
                }
            }
        }
    }

    /// The next sequence number expected in order (links with narrow sequence fields widen
    /// received numbers around it).
    pub fn expected(&self) -> u32 {
        self.next
    }

    /// Whether a session is established.
    pub fn has_session(&self) -> bool {
        self.session.is_some()
    }

    /// Whether `seq` was already received (delivered or buffered).
    pub fn is_received(&self, seq: u32) -> bool {
        ((seq.wrapping_sub(self.next)) as i32) < 0 || self.buffered.contains_key(&seq)
    }

    /// Handles one safe message; calls `deliver` for every message now deliverable in order.
    pub fn on_safe(&mut self, seq: u32, msg: &[u8], mut deliver: impl FnMut(&[u8])) {
        if self.session.is_none() {
            self.stats.without_session += 1;
            return;
        }
        self.ack_pending = true;
        let ahead = seq.wrapping_sub(self.next);
        if ahead == 0 {
            deliver(msg);
            self.stats.delivered += 1;
            self.next = self.next.wrapping_add(1);
            while let Some(m) = self.buffered.remove(&self.next) {
                self.buffered_bytes -= m.len();
                deliver(&m);
                self.stats.delivered += 1;
                self.next = self.next.wrapping_add(1);
            }
        } else if (ahead as i32) < 0 {
            self.stats.duplicates += 1;
        } else if ahead < self.max_window {
            if self.buffered.contains_key(&seq) {
                self.stats.duplicates += 1;
            } else if self.buffered_bytes + msg.len() > self.max_buffered_bytes {
                // Not acknowledged, so the sender sends it again; the message the gap waits
                // for is never buffered (it is delivered at once), so this cannot stall.
                self.stats.over_budget += 1;
            } else {
                self.buffered_bytes += msg.len();
                self.buffered.insert(seq, msg.to_vec());
            }
        } else {
            self.stats.out_of_window += 1;
        }
    }

    /// The acknowledgement to send, if one is owed (clears the flag).
    pub fn take_ack(&mut self) -> Option<AckInfo> {
        if !self.ack_pending {
            return None;
        }
        self.ack_pending = false;
        self.current_ack()
    }

    /// The receiver's state as an acknowledgement.
    pub fn current_ack(&self) -> Option<AckInfo> {
        let session = self.session?;
        let mut sack = 0u64;
        for &seq in self.buffered.keys() {
            let off = seq.wrapping_sub(self.next);
            if (1..=64).contains(&off) {
                sack |= 1 << (off - 1);
            }
        }
        Some(AckInfo {
            session,
            next: self.next,
            sack,
        })
    }

    /// Whether an acknowledgement is owed.
    pub fn ack_pending(&self) -> bool {
        self.ack_pending
    }

    /// Counters.
    pub fn stats(&self) -> ArqReceiverStats {
        self.stats
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    /// A cumulative acknowledgement of messages sent 30, 20 and 10 ms before it gives one
    /// round-trip sample, the newest message's 10 ms: the others waited in the window.
    #[test]
    fn a_cumulative_ack_samples_the_round_trip_once_from_the_newest_message() {
        let t0 = Instant::now();
        let mut tx: ArqSender<()> = ArqSender::new(7, cfg());
        for i in 0..3u64 {
            tx.push(t0 + Duration::from_millis(10 * i), vec![1], None);
        }
        let acked = tx.on_ack(
            t0 + Duration::from_millis(30),
            AckInfo {
                session: 7,
                next: tx.in_flight.back().map_or(0, |f| f.seq.wrapping_add(1)),
                sack: 0,
            },
        );
        assert!(acked.is_empty(), "no tokens were given");
        assert_eq!(tx.in_flight(), 0, "all three acknowledged");
        assert_eq!(tx.rto().srtt(), Some(Duration::from_millis(10)));
    }

    fn cfg() -> ArqConfig {
        ArqConfig {
            initial_rto: Duration::from_millis(100),
            min_rto: Duration::from_millis(10),
            max_rto: Duration::from_secs(1),
            max_window: 64,
            initial_window: 64,
            min_window: 4,
        }
    }

    #[test]
    fn in_order_delivery_with_duplicates_suppressed() {
        let mut r = ArqReceiver::new(16);
        assert_eq!(r.on_syn(7), SynOutcome::Fresh);
        let mut got = Vec::new();
        r.on_safe(1, b"b", |m| got.push(m.to_vec()));
        assert!(got.is_empty());
        assert_eq!(
            r.take_ack(),
            Some(AckInfo {
                session: 7,
                next: 0,
                sack: 1
            })
        );
        r.on_safe(0, b"a", |m| got.push(m.to_vec()));
        r.on_safe(0, b"a", |m| got.push(m.to_vec()));
        r.on_safe(1, b"b", |m| got.push(m.to_vec()));
        assert_eq!(got, vec![b"a".to_vec(), b"b".to_vec()]);
        assert_eq!(r.stats().duplicates, 2);
        assert_eq!(r.on_syn(7), SynOutcome::Same);
        assert_eq!(r.on_syn(8), SynOutcome::Reset);
    }

    #[test]
    fn timeout_retransmits_and_ack_completes() {
        let t0 = Instant::now();
        let mut s: ArqSender<u32> = ArqSender::new(1, cfg());
        let seq = s.push(t0, b"x".to_vec(), Some(42));
        assert_eq!(seq, 0);
        assert!(s.due(t0 + Duration::from_millis(50)).is_empty());
        assert_eq!(s.due(t0 + Duration::from_millis(100)), vec![0]);
        // Backoff: the second retransmission waits twice as long.
        assert!(s.due(t0 + Duration::from_millis(250)).is_empty());
        assert_eq!(s.due(t0 + Duration::from_millis(300)), vec![0]);
        let done = s.on_ack(
            t0 + Duration::from_millis(310),
            AckInfo {
                session: 1,
                next: 1,
                sack: 0,
            },
        );
        assert_eq!(done, vec![42]);
        assert_eq!(s.in_flight(), 0);
        assert_eq!(s.next_deadline(), None);
        assert_eq!(s.stats().retransmitted, 2);
    }

    /// A lossless stream keeps the timers in queue order (no full scans); a loss episode
    /// (retransmissions, a NACK) falls back to full scans and back again once acknowledged.
    #[test]
    fn timers_follow_queue_order_until_a_retransmission_and_again_after() {
        let t0 = Instant::now();
        let mut s: ArqSender<u32> = ArqSender::new(1, cfg());
        for i in 0..40 {
            s.push(t0 + Duration::from_millis(i), vec![0], Some(i as u32));
        }
        assert!(s.ordered());
        assert_eq!(s.next_deadline(), Some(t0 + Duration::from_millis(100)));
        assert!(s.due(t0 + Duration::from_millis(99)).is_empty());
        // Timers of 0..=4 expired: exactly those go (the scan stops at 5), and the order is
        // lost.
        let due = s.due(t0 + Duration::from_millis(104));
        assert_eq!(due, (0..5).collect::<Vec<u32>>());
        assert!(!s.ordered());
        // The deadline is now the earliest over all, found by a full scan: 5's first timer,
        // not the retransmitted ones (backed off).
        assert_eq!(s.next_deadline(), Some(t0 + Duration::from_millis(105)));
        // Everything up to 30 acknowledged: the retransmitted ones are gone, order is back.
        s.on_ack(
            t0 + Duration::from_millis(110),
            AckInfo {
                session: 1,
                next: 30,
                sack: 0,
            },
        );
        assert!(s.ordered());
        assert_eq!(s.in_flight(), 10);
        assert_eq!(
            s.next_deadline(),
            Some(t0 + Duration::from_millis(30) + s.rto().rto())
        );
        // A NACK makes it irregular until that message is acknowledged.
        assert!(s.on_nack(t0 + Duration::from_millis(200), 35));
        assert!(!s.ordered() && s.nack_pending());
        s.on_ack(
            t0 + Duration::from_millis(201),
            AckInfo {
                session: 1,
                next: 40,
                sack: 0,
            },
        );
        assert!(s.ordered() && !s.nack_pending());
        assert_eq!(s.in_flight(), 0);
    }

    #[test]
    fn acks_of_another_session_are_ignored_and_close_returns_pending() {
        let t0 = Instant::now();
        let mut s: ArqSender<u32> = ArqSender::new(1, cfg());
        s.push(t0, b"x".to_vec(), Some(1));
        assert!(s
            .on_ack(
                t0,
                AckInfo {
                    session: 2,
                    next: 1,
                    sack: 0
                }
            )
            .is_empty());
        assert_eq!(s.close(), vec![1]);
    }

    #[test]
    fn nack_retransmits_at_once_without_shrinking_the_window() {
        let t0 = Instant::now();
        let mut s: ArqSender<u32> = ArqSender::new(1, cfg());
        s.push(t0, b"a".to_vec(), None);
        s.push(t0, b"b".to_vec(), None);
        assert_eq!(s.next_seq(), 2);
        assert!(s.on_nack(t0, 1));
        assert!(!s.on_nack(t0, 5));
        assert!(s.nack_pending());
        assert_eq!(s.next_deadline(), Some(t0));
        assert_eq!(s.due(t0), vec![1]);
        assert!(!s.nack_pending());
        assert!(s.can_push());
        assert_eq!(s.stats().retransmitted, 1);
    }

    #[test]
    fn retransmission_gives_up_after_the_limit_and_close_fails_the_rest() {
        let t0 = Instant::now();
        let limit = RetryLimit {
            transmissions: 4,
            after: Duration::from_secs(2),
        };
        let mut s: ArqSender<u32> = ArqSender::new(1, cfg());
        s.push(t0, b"x".to_vec(), Some(1));
        s.push(t0, b"y".to_vec(), Some(2));
        let mut now = t0;
        let mut rounds = 0;
        // A peer that never acknowledges: retransmitted with backoff until the limit.
        while !s.exhausted(now, limit) {
            rounds += 1;
            assert!(rounds < 1000, "never gave up");
            now = s.next_deadline().expect("something in flight");
            s.due(now);
        }
        assert!(
            now.duration_since(t0) >= limit.after,
            "not before the time bound"
        );
        assert!(s.stats().retransmitted >= 2 * u64::from(limit.transmissions - 1));
        assert_eq!(s.close(), vec![1, 2], "everything in flight fails");

        // Acknowledged in time: never exhausted, however late it is asked.
        let mut s: ArqSender<u32> = ArqSender::new(1, cfg());
        s.push(t0, b"x".to_vec(), Some(1));
        for _ in 0..5 {
            let d = s.next_deadline().expect("in flight");
            s.due(d);
        }
        s.on_ack(
            t0 + Duration::from_secs(3),
            AckInfo {
                session: 1,
                next: 1,
                sack: 0,
            },
        );
        assert!(!s.exhausted(t0 + Duration::from_secs(3600), limit));
        // Many transmissions alone, within the time bound, are not enough either.
        let mut s: ArqSender<u32> = ArqSender::new(1, cfg());
        s.push(t0, b"x".to_vec(), None);
        s.on_nack(t0, 0);
        for i in 0..10 {
            s.on_nack(t0 + Duration::from_millis(i), 0);
            s.due(t0 + Duration::from_millis(i));
        }
        assert!(!s.exhausted(t0 + Duration::from_millis(10), limit));
    }

    #[test]
    fn the_reorder_buffer_is_bounded_in_bytes_and_the_stream_still_completes() {
        let mut r = ArqReceiver::new(4096).with_max_buffered_bytes(10_000);
        r.on_syn(3);
        let mut got: Vec<u32> = Vec::new();
        let msg = |i: u32| {
            let mut m = vec![0u8; 1000];
            m[..4].copy_from_slice(&i.to_le_bytes());
            m
        };
        let id = |m: &[u8]| u32::from_le_bytes([m[0], m[1], m[2], m[3]]);
        // Seq 0 is missing; a peer sends 3,000 large messages ahead of the gap.
        for i in 1..3000 {
            r.on_safe(i, &msg(i), |m| got.push(id(m)));
        }
        assert!(got.is_empty());
        assert!(r.buffered_bytes() <= 10_000, "{}", r.buffered_bytes());
        assert_eq!(r.stats().over_budget, 2999 - 10);
        // What was dropped is not acknowledged (the sender will resend it).
        let ack = r.take_ack().expect("ack owed");
        assert_eq!((ack.next, ack.sack), (0, (1 << 10) - 1));
        // The gap fills: what was held is delivered, and the resent rest goes through.
        r.on_safe(0, &msg(0), |m| got.push(id(m)));
        assert_eq!(got, (0..11).collect::<Vec<_>>());
        assert_eq!(r.buffered_bytes(), 0);
        for i in 11..3000 {
            r.on_safe(i, &msg(i), |m| got.push(id(m)));
        }
        assert_eq!(got, (0..3000).collect::<Vec<_>>());
    }

    #[test]
    fn rtt_adapts_the_timeout() {
        let mut e = RtoEstimator::new(
            Duration::from_millis(1000),
            Duration::from_millis(1),
            Duration::from_secs(5),
        );
        for _ in 0..20 {
            e.sample(Duration::from_millis(10));
        }
        assert!(e.rto() < Duration::from_millis(30), "rto {:?}", e.rto());
    }

    proptest! {
        /// Over a channel that drops, duplicates and reorders, every message arrives exactly
        /// once and in order.
        #[test]
        fn lossy_channel_delivers_exactly_once_in_order(seed in any::<u64>(), n in 1usize..200) {
            use rand::{Rng, SeedableRng};
            let mut rng = rand::rngs::StdRng::seed_from_u64(seed);
            let mut now = Instant::now();
            let mut s: ArqSender<usize> = ArqSender::new(9, cfg());
            let mut r = ArqReceiver::new(64);
            r.on_syn(9);
            let mut got: Vec<usize> = Vec::new();
            let mut acked = 0usize;
            let mut next_msg = 0usize;
            let mut wire: Vec<(u32, Vec<u8>)> = Vec::new();
            for _round in 0..20_000 {
                if acked == n { break; }
                while next_msg < n && s.can_push() {
                    let m = (next_msg as u64).to_le_bytes().to_vec();
                    let seq = s.push(now, m.clone(), Some(next_msg));
                    wire.push((seq, m));
                    next_msg += 1;
                }
                for seq in s.due(now) {
                    let m = s.message(seq).unwrap().to_vec();
                    wire.push((seq, m));
                }
                // Deliver a random subset in random order, maybe duplicated.
                let mut delivered = Vec::new();
                for (seq, m) in wire.drain(..) {
                    let roll: f64 = rng.random();
                    if roll < 0.3 { continue; }
                    delivered.push((seq, m.clone()));
                    if roll > 0.9 { delivered.push((seq, m)); }
                }
                for i in (1..delivered.len()).rev() {
                    let j = rng.random_range(0..=i);
                    delivered.swap(i, j);
                }
                for (seq, m) in delivered {
                    r.on_safe(seq, &m, |b| {
                        let mut a = [0u8; 8];
                        a.copy_from_slice(b);
                        got.push(u64::from_le_bytes(a) as usize);
                    });
                }
                now += Duration::from_millis(5);
                if let Some(ack) = r.take_ack() {
                    if rng.random::<f64>() > 0.3 {
                        acked += s.on_ack(now, ack).len();
                    }
                }
            }
            prop_assert_eq!(acked, n);
            prop_assert_eq!(got, (0..n).collect::<Vec<_>>());
        }
    }
}
