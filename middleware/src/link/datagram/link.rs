//! The link every datagram medium shares: per-peer sessions with the ARQ of
//! [`crate::link::arq`] for the safe class, small messages batched into shared datagrams
//! ([`super`]'s format), the seal of [`crate::link::auth`] (the domain key's, or the keys a
//! peer and this node share once each proved its identity: [`PairSeal`]), and the table of
//! sessions that no sender of datagrams can fill ([`super::sessions`]). A [`Medium`] writes datagrams to
//! addresses of its own (UDP sockets, Zenoh key expressions); its receive tasks hand what
//! arrives to [`DatagramLink::receive`].
//!
//! Sending is inline when the link is idle (lowest latency: the caller's task writes the
//! datagram) and batched by the link's transmit task when messages arrive faster than datagrams
//! can be written (highest throughput: many messages share one datagram). Either way a peer's
//! datagrams are built under that peer's lock and written in that order under its wire's
//! ([`Wire`]), so fast messages are never reordered.

use std::collections::VecDeque;
use std::fmt;
use std::hash::Hash;
use std::io;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex, MutexGuard};
use std::time::{Duration, Instant};

use bytes::Bytes;
use tokio::sync::Notify;
use tokio_util::sync::CancellationToken;
use tokio_util::task::TaskTracker;

use super::agenda::Agenda;
use super::parts;
use super::sessions::{Lookup, SessionLimits, SessionTable};
use super::{Datagram, DatagramWriter, Entry};
use crate::link::arq::{ArqConfig, ArqReceiver, ArqSender, RetryLimit, SynOutcome};
use crate::link::auth::{self, AuthReject, LinkSecurity, Opener, Profile, Sealer};
use crate::link::coalesce::{CoalescingQueue, Pushed};
use crate::link::completion::acknowledge_all;
use crate::link::{
    Link, LinkCounters, LinkHandler, LinkSendError, LinkStats, Outgoing, PeerAddr, Precedence,
    SafeCompletion,
};
use crate::sync::lock;

/// What a [`DatagramLink`] needs of its medium: datagrams, which may be lost, to and from
/// peers at addresses of the medium's own.
pub trait Medium: Send + Sync + 'static {
    /// Where a peer is on the medium.
    type Addr: Copy + Eq + Ord + Hash + fmt::Display + fmt::Debug + Send + Sync + 'static;
    /// The node's name for a peer at `addr`.
    fn peer_addr(addr: Self::Addr) -> PeerAddr;
    /// The medium's address inside the node's name `to`, if `to` is one of this medium's.
    fn medium_addr(to: PeerAddr) -> Option<Self::Addr>;
    /// Writes datagram `d` to `to` without waiting.
    ///
    /// # Errors
    /// `WouldBlock` when the medium cannot take it now (the link writes it again, first, a
    /// moment later); any other error drops it (the ARQ resends what was safe).
    fn send_to(&self, d: &[u8], to: Self::Addr) -> io::Result<()>;
    /// How many places a discovery datagram goes to (a multicast group, static peers).
    fn announce_targets(&self) -> usize;
    /// Writes discovery datagram `d` to target `target` (< [`Medium::announce_targets`]).
    ///
    /// # Errors
    /// As [`Medium::send_to`]; an announce that fails is not written again.
    fn announce_to(&self, d: &[u8], target: usize) -> io::Result<()>;
    /// The largest datagram built for `to`.
    fn datagram_max(&self, to: Self::Addr) -> usize;
    /// A human-readable local address.
    fn local_addr(&self) -> String;
}

/// How a [`DatagramLink`] behaves over its medium.
#[derive(Debug, Clone)]
pub(crate) struct DatagramLinkOptions {
    /// Link name.
    pub name: String,
    /// ARQ tuning.
    pub arq: ArqConfig,
    /// When retransmission gives up on a session.
    pub retry_limit: RetryLimit,
    /// The domain key: when set, every datagram is sealed and only sealed ones are taken
    /// (see [`crate::link::auth`]).
    pub security: Option<LinkSecurity>,
}

/// Most sessions with addresses bound to a node (see [`sessions`]); beyond it, new nodes'
/// addresses get no session of their own.
const MAX_PEERS: usize = 4096;
/// Most sessions with addresses no node is known at (answered heartbeats, sessions opened
/// before their Hello): newer ones push out the oldest, and never a bound one.
const MAX_UNBOUND: usize = 256;
/// How long a session with an address no node is known at lives: a real node's Hello binds
/// it within a round trip.
const UNBOUND_TTL: Duration = Duration::from_secs(5);
/// Safe messages queued for an address no node is known at (our Hellos answering its
/// heartbeats): beyond it, more are refused, so heartbeats from one address cannot make the
/// node queue a Hello each for the life of the session.
const MAX_UNBOUND_SAFE: usize = 8;
/// Fast messages queued per peer before the oldest is dropped.
const MAX_FAST_QUEUE: usize = 4096;
/// A send within this long of the previous datagram is left to the transmit task to batch.
const BATCH_WINDOW: Duration = Duration::from_micros(20);
/// Datagram bytes kept beside a part for its entry header, a SYN and an acknowledgement.
const PART_HEADROOM: usize = 48;
/// Sent datagrams' buffers a peer keeps for its next datagrams: enough for one flush of a
/// fast stream.
const SPARE_BUFFERS: usize = 4;

/// A safe message waiting to leave: its bytes, its completion, since when it waits.
type QueuedSafe = (Bytes, Option<SafeCompletion>, Option<Instant>);

/// A safe message (or part) in the bulk queue, and whether urgent messages must stay behind it
/// (it is not [`Precedence::Passable`]).
type QueuedBulk = (QueuedSafe, bool);

/// How long the bytes in flight ahead of an urgent message may take to drain: the parts of
/// large messages leave only while less than that much is in flight at the rate the peer
/// acknowledges ([`PeerState::bulk_limit`]). Whatever is in flight is ahead of a call on its
/// way: the less, the sooner it arrives; the more, the faster bulk data flows (loopback needs
/// megabytes in flight for its gigabytes a second, a LAN or a WAN far less).
const BULK_DRAIN: Duration = Duration::from_millis(1);
/// The least bulk data kept in flight, whatever the rate measured (a path starts unmeasured).
const BULK_IN_FLIGHT_MIN: usize = 256 << 10;
/// The most, whatever the rate.
const BULK_IN_FLIGHT_MAX: usize = 16 << 20;
/// While urgent messages pass bulk data (one within [`URGENT_RECENT`]), bulk data in flight is
/// kept to [`BULK_IN_FLIGHT_MIN`]. Measured on loopback (`peers` bench, `rtt64_under_load`:
/// 64 B calls under a stream of 4 MiB frames), call p99 over idle p99 and the stream's rate
/// meanwhile: 256 KiB in flight, 8.3-8.9× and 550-1,060 MB/s; 1 MiB, 17× and 760-910 MB/s;
/// 4 MiB, 245× and 960 MB/s.
const URGENT_RECENT: Duration = Duration::from_secs(1);
/// How often the acknowledged rate is sampled.
const RATE_SAMPLE: Duration = Duration::from_millis(1);

/// The socket's side of a peer: its datagrams are written under this lock, not the peer's
/// state's, in the order they were built. A flush builds its datagrams under the state's lock,
/// takes this one before letting the state go (hand over hand), then writes: the socket's
/// writes (microseconds each on loopback) no longer hold up a raiser queueing its next message
/// while the receive task flushes what an acknowledgement let go (on the multi-thread runtime
/// the raiser spent most of its sleeps there).
#[derive(Default)]
struct Wire {
    /// Datagrams the socket refused (WouldBlock), written first when it is writable again.
    blocked: Mutex<VecDeque<Vec<u8>>>,
    /// Whether `blocked` holds any (read without its lock).
    is_blocked: AtomicBool,
    /// Buffers of datagrams sent, for the next ones (at most [`SPARE_BUFFERS`]).
    spare: Mutex<Vec<Vec<u8>>>,
}

impl Wire {
    fn is_blocked(&self) -> bool {
        self.is_blocked.load(Ordering::Acquire)
    }

    /// Keeps buffers for the next datagrams, up to [`SPARE_BUFFERS`].
    fn keep_spare(&self, bufs: Vec<Vec<u8>>) {
        if bufs.is_empty() {
            return;
        }
        let mut spare = lock(&self.spare);
        let room = SPARE_BUFFERS.saturating_sub(spare.len());
        spare.extend(bufs.into_iter().take(room));
    }
}

/// Datagrams a flush built under a peer's lock, to be written by [`DatagramLink::write`].
#[must_use = "built datagrams must be written"]
struct Outbound {
    wire: Arc<Wire>,
    datagrams: Vec<Vec<u8>>,
}

struct PeerState {
    tx: ArqSender<SafeCompletion>,
    rx: ArqReceiver,
    fast: CoalescingQueue<u32, Vec<u8>>,
    /// Datagram bytes the queued fast messages take.
    fast_bytes: usize,
    /// Safe messages waiting for the window, each with when it started waiting when that can
    /// be long (the window was full or others waited): it leaves aged by that wait
    /// ([`LinkHandler::age_safe`]), so a call queued behind a slow peer carries its caller's
    /// time left, not its time at the queue's door. They leave before those of `bulk`.
    safe: VecDeque<QueuedSafe>,
    /// The parts of messages larger than a datagram, and every safe message sent after them
    /// while they wait, but urgent ones ([`LinkHandler::precedence`]) while everything here is
    /// passable: those go to `safe` and so pass them. Order is kept everywhere else: a message
    /// goes to `safe` only while `bulk` is empty or it may pass all of it. Parts leave only
    /// while less than [`PeerState::bulk_limit`] bytes are unacknowledged.
    bulk: VecDeque<QueuedBulk>,
    /// Entries of `bulk` urgent messages must not pass.
    bulk_holding: usize,
    /// The last part that left was not its message's last: the rest of the message is at the
    /// head of `bulk` (dropped if the session restarts: the peer cannot join it any more).
    mid_message: bool,
    /// Where this peer's datagrams are written, outside this state's lock.
    wire: Arc<Wire>,
    last_write: Option<Instant>,
    /// The transmit task was woken for this peer and has not flushed it yet: further messages
    /// need no wake-up of their own (each one costs a syscall when the task sleeps elsewhere).
    wake_pending: bool,
    /// When this session is next on the transmit task's agenda (its retransmission timer or a
    /// blocked socket's retry), if it is.
    timer_at: Option<Instant>,
    /// The node knows who is at this address (see [`sessions`]).
    bound: bool,
    /// The peer acknowledged a session of ours: it receives at this address (our session
    /// numbers are random, read only off our datagrams), which a forged source address cannot.
    answered: bool,
    /// Datagram bytes the queued safe messages take, at most ([`queued_safe_cost`]).
    safe_bytes: usize,
    /// The peer's message being joined from its parts ([`parts`]).
    joiner: parts::Joiner,
    /// When an urgent message last passed bulk data ([`URGENT_RECENT`]).
    urgent_at: Option<Instant>,
    /// The rate the peer acknowledges at while data is in flight, bytes a second (smoothed),
    /// and the last sample's time and acknowledged total.
    acked_rate: f64,
    rate_mark: Option<(Instant, u64)>,
}

impl PeerState {
    fn new(arq: ArqConfig) -> Self {
        PeerState {
            tx: ArqSender::new(rand::random(), arq),
            rx: ArqReceiver::new(arq.max_window),
            fast: CoalescingQueue::new(MAX_FAST_QUEUE),
            fast_bytes: 0,
            safe: VecDeque::new(),
            bulk: VecDeque::new(),
            bulk_holding: 0,
            mid_message: false,
            wire: Arc::default(),
            last_write: None,
            wake_pending: false,
            timer_at: None,
            bound: false,
            answered: false,
            safe_bytes: 0,
            joiner: parts::Joiner::default(),
            urgent_at: None,
            acked_rate: 0.0,
            rate_mark: None,
        }
    }

    fn has_work(&self) -> bool {
        !self.fast.is_empty()
            || (!self.safe.is_empty() && self.tx.can_push())
            || (self.bulk_may_leave() && !self.bulk.is_empty())
            || self.rx.ack_pending()
            || self.wire.is_blocked()
    }

    /// Whether the next of `bulk` may leave now: the window admits it, and less than
    /// [`PeerState::bulk_limit`] bytes are in flight.
    fn bulk_may_leave(&self) -> bool {
        self.tx.can_push() && self.tx.in_flight_bytes() < self.bulk_limit()
    }

    /// Bytes in flight past which bulk data waits: what drains in [`BULK_DRAIN`] at the
    /// acknowledged rate, within [`BULK_IN_FLIGHT_MIN`]..[`BULK_IN_FLIGHT_MAX`]; the least
    /// while urgent messages pass it ([`URGENT_RECENT`]).
    fn bulk_limit(&self) -> usize {
        if self.urgent_at.is_some_and(|t| t.elapsed() < URGENT_RECENT) {
            return BULK_IN_FLIGHT_MIN;
        }
        let drains = (self.acked_rate * BULK_DRAIN.as_secs_f64()) as usize;
        drains.clamp(BULK_IN_FLIGHT_MIN, BULK_IN_FLIGHT_MAX)
    }

    /// Samples the acknowledged rate (after acknowledgements were applied at `now`), while
    /// bulk data waits: an idle session keeps the rate it last moved bulk data at.
    fn sample_rate(&mut self, now: Instant) {
        let acked = self.tx.acked_bytes();
        match self.rate_mark {
            // A new sending session counts from 0; after a pause, the pause is no sample.
            Some((t, before))
                if acked < before || now.saturating_duration_since(t) > 100 * RATE_SAMPLE =>
            {
                self.rate_mark = Some((now, acked));
            }
            Some((t, before)) if now.saturating_duration_since(t) >= RATE_SAMPLE => {
                let secs = now.saturating_duration_since(t).as_secs_f64();
                let sample = (acked - before) as f64 / secs;
                self.acked_rate = if self.acked_rate == 0.0 {
                    sample
                } else {
                    0.875 * self.acked_rate + 0.125 * sample
                };
                self.rate_mark = Some((now, acked));
            }
            Some(_) => {}
            None => self.rate_mark = Some((now, acked)),
        }
    }

    /// Queues `m` in `bulk`; `holds`: urgent messages must stay behind it.
    fn push_bulk(&mut self, m: QueuedSafe, holds: bool) {
        self.bulk_holding += usize::from(holds);
        self.bulk.push_back((m, holds));
    }

    /// The head of `bulk`, taken out.
    fn pop_bulk(&mut self) -> Option<QueuedSafe> {
        let (m, holds) = self.bulk.pop_front()?;
        self.bulk_holding -= usize::from(holds);
        Some(m)
    }

    /// Safe messages queued, not yet in flight.
    fn safe_queued(&self) -> usize {
        self.safe.len() + self.bulk.len()
    }
}

/// A link of ARQ sessions over a datagram [`Medium`].
pub struct DatagramLink<M: Medium> {
    index: usize,
    name: String,
    arq: ArqConfig,
    medium: M,
    /// (Seeded hashing: looked up on every send; at most [`MAX_PEERS`] + [`MAX_UNBOUND`]
    /// entries.)
    peers: Mutex<SessionTable<M::Addr, Arc<Mutex<PeerState>>>>,
    /// When retransmission gives up on a session.
    retry_limit: RetryLimit,
    wake: Notify,
    /// Which sessions the transmit task visits, and when.
    agenda: Mutex<Agenda<M::Addr>>,
    handler: Arc<dyn LinkHandler>,
    counters: LinkCounters,
    /// Seals outgoing datagrams when the node has a key: data, and discovery (announces) with
    /// an epoch of their own. Announces arrive through the multicast socket's task, which may
    /// lag the unicast one by more than the replay window under heavy traffic; in their own
    /// epoch they are never "too old" for that reason.
    sealer: Option<(Sealer, Sealer)>,
    /// Checks incoming datagrams when the node has a key (both receive tasks use it).
    opener: Option<Mutex<Opener>>,
    /// The peers whose data is sealed with the keys they share with this node.
    pairs: Mutex<std::collections::HashMap<M::Addr, Arc<PairSeal>>>,
}

/// The seal of one peer's data once it and this node proved their identities to each other
/// ([`Link::set_pair`]): what we send it is sealed with the key of our direction, what it
/// sends us opens only with the key of its. A frame is then taken as the peer's because its
/// key sealed it, not because of the address it came from: a key holder forging the peer's
/// address, or a frame of ours reflected back to us, does not open.
///
/// Each end holds the keys once it verified the other's proof, which need not happen at the
/// same moment (or at all, when a roster does not list us). So an end seals with them only
/// once the other showed it holds them: a frame sealed with them arrived (`confirmed`). To
/// show it, an end sends a probe (an empty data datagram sealed with the pair's key) when it
/// gets the keys, and again whenever data sealed with the domain key comes from the peer
/// (at most every [`PROBE_EVERY`]): the peer has not switched, maybe for want of a probe.
struct PairSeal {
    keys: Arc<crate::link::auth::PairKeys>,
    sealer: Sealer,
    opener: Mutex<Opener>,
    /// A frame sealed with the pair's key came: from now on what we send the peer is sealed
    /// with it, and data from its address sealed with the domain key is refused.
    confirmed: AtomicBool,
    /// When the last probe left.
    probed: Mutex<Option<Instant>>,
    /// When `confirmed` was set.
    confirmed_at: Mutex<Option<Instant>>,
    /// Since when data sealed with the domain key has come from the peer's address with no
    /// frame sealed with the pair's keys in between (see [`PAIR_LOST_AFTER`]).
    refused_since: Mutex<Option<Instant>>,
}

/// How long data sealed with the domain key may keep coming from a confirmed pair's address
/// with nothing sealed with the pair's keys before the peer is taken to have lost the pair
/// (it dropped us and starts over): the peer is then dropped here too, so both meet afresh
/// with a new handshake. A key holder forging that long only gets the peer dropped (it
/// cannot pass the new handshake as the peer).
const PAIR_LOST_AFTER: Duration = Duration::from_secs(3);

/// How long after a pair's switch its frames sealed with the domain key (sent before it) are
/// dropped without a warning.
const SWITCH_TIME: Duration = Duration::from_secs(2);

/// The shortest time between two probes of a pair ([`PairSeal`]).
const PROBE_EVERY: Duration = Duration::from_millis(50);

/// Sender epochs a pair's opener remembers: the peer's current one and one before (a
/// restarted peer is another pair).
const PAIR_REPLAY_WINDOWS: usize = 2;

/// Sender epochs a datagram link remembers for replay detection.
const MAX_REPLAY_WINDOWS: usize = 4096;

impl<M: Medium> DatagramLink<M> {
    /// Round trip and queue depths over the peers, for link health.
    fn gauges(&self) -> LinkStats {
        let peers: Vec<Arc<Mutex<PeerState>>> = lock(&self.peers).values().cloned().collect();
        let mut g = LinkStats::default();
        for p in peers {
            let p = lock(&p);
            let rtt = p.tx.rto().srtt().map_or(0, |d| d.as_micros() as u64);
            g.rtt_us = g.rtt_us.max(rtt);
            g.safe_queued += (p.safe_queued() + p.tx.in_flight()) as u64;
            g.fast_queued += p.fast.len() as u64;
        }
        g
    }

    /// The link over `medium`, its transmit task started on `tasks` (stopping on `cancel`).
    /// The medium's receive tasks hand it what arrives ([`DatagramLink::receive`]).
    pub(crate) fn create(
        index: usize,
        options: DatagramLinkOptions,
        medium: M,
        handler: Arc<dyn LinkHandler>,
        tasks: &TaskTracker,
        cancel: CancellationToken,
    ) -> Arc<Self> {
        let sealer = options.security.as_ref().map(|s| {
            (
                Sealer::new(&s.key, Profile::UDP),
                Sealer::new(&s.key, Profile::UDP),
            )
        });
        let opener = options
            .security
            .as_ref()
            .map(|s| Mutex::new(Opener::new(&s.key, Profile::UDP, MAX_REPLAY_WINDOWS)));
        let link = Arc::new(DatagramLink {
            index,
            name: options.name,
            arq: options.arq,
            medium,
            sealer,
            opener,
            pairs: Mutex::default(),
            peers: Mutex::new(SessionTable::new(SessionLimits {
                max_bound: MAX_PEERS,
                max_unbound: MAX_UNBOUND,
                unbound_ttl: UNBOUND_TTL,
            })),
            retry_limit: options.retry_limit,
            wake: Notify::new(),
            agenda: Mutex::default(),
            handler,
            counters: LinkCounters::default(),
        });
        let l = link.clone();
        crate::sync::spawn_tracked(tasks, async move { l.transmit_loop(cancel).await });
        link
    }

    /// The medium the link writes to.
    pub fn medium(&self) -> &M {
        &self.medium
    }

    /// The session with `addr`; made (unbound, see [`sessions`]) if there is none and
    /// `create` is set, or made or bound if `bind` is set.
    fn session(&self, addr: M::Addr, create: bool, bind: bool) -> Option<Arc<Mutex<PeerState>>> {
        let found = {
            let mut peers = lock(&self.peers);
            if let Some(p) = peers.get(&addr).filter(|_| !bind) {
                return Some(p.clone());
            }
            let arq = self.arq;
            peers.get_or_insert(addr, Instant::now(), create, bind, || {
                Arc::new(Mutex::new(PeerState::new(arq)))
            })
        };
        match found {
            Lookup::Found(p, pushed_out) => {
                if let Some((old, q)) = pushed_out {
                    self.counters
                        .sessions_expired
                        .fetch_add(1, Ordering::Relaxed);
                    fail_all(&mut lock(&q), LinkSendError::PeerClosed(old.to_string()));
                }
                Some(p)
            }
            Lookup::Refused => None,
        }
    }

    fn peer(&self, addr: M::Addr, create: bool) -> Option<Arc<Mutex<PeerState>>> {
        self.session(addr, create, false)
    }

    /// Closes the sessions with unknown addresses that outlived [`UNBOUND_TTL`] and those
    /// whose peer acknowledged nothing within the retry limit (`gave_up`), then tells the
    /// node of the latter.
    fn close_stale(&self, now: Instant, gave_up: Vec<(M::Addr, Arc<Mutex<PeerState>>)>) {
        let expired = lock(&self.peers).expire(now);
        for (addr, p) in expired {
            self.counters
                .sessions_expired
                .fetch_add(1, Ordering::Relaxed);
            fail_all(&mut lock(&p), LinkSendError::PeerClosed(addr.to_string()));
        }
        for (addr, p) in gave_up {
            {
                let mut peers = lock(&self.peers);
                // Only if it is still that session (the node may have closed it meanwhile).
                if !peers.get(&addr).is_some_and(|q| Arc::ptr_eq(q, &p)) {
                    continue;
                }
                peers.remove(&addr);
            }
            self.counters
                .sessions_given_up
                .fetch_add(1, Ordering::Relaxed);
            tracing::debug!(link = %self.name, %addr, "retransmission gave up; session closed");
            fail_all(
                &mut lock(&p),
                LinkSendError::RetriesExhausted(addr.to_string()),
            );
            self.handler
                .on_peer_unreachable(self.index, M::peer_addr(addr));
        }
    }

    /// Builds every datagram `state` has ready, for [`Self::write`]. Called with the peer
    /// locked. Builds nothing while the socket refuses this peer's datagrams: what waits stays
    /// in its queues (fast messages coalesced, safe ones out of flight) instead of piling up
    /// behind the refused ones; the write that drains them asks for the next flush.
    fn flush_locked(&self, addr: M::Addr, st: &mut PeerState, now: Instant) -> Outbound {
        if st.wire.is_blocked() {
            return Outbound {
                wire: st.wire.clone(),
                datagrams: Vec::new(),
            };
        }
        let due = st.tx.due(now);
        self.counters
            .retransmitted
            .fetch_add(due.len() as u64, Ordering::Relaxed);
        let seal = self.sealer.as_ref().map_or(0, |(s, _)| s.overhead());
        let mut w = DatagramWriter::reusing(
            self.datagram_max(addr).saturating_sub(seal),
            std::mem::take(&mut *lock(&st.wire.spare)),
        );
        let mut out: Vec<Vec<u8>> = Vec::new();
        let mut carries_safe = false;
        let syn = st.tx.session();
        let need_syn = !st.tx.session_acked();
        let finish = |w: &mut DatagramWriter, out: &mut Vec<Vec<u8>>, carries_safe: &mut bool| {
            if !w.is_empty() {
                out.push(w.take());
            }
            *carries_safe = false;
        };
        if let Some(ack) = st.rx.take_ack() {
            w.push_ack(ack);
        }
        let push_safe = |w: &mut DatagramWriter,
                         out: &mut Vec<Vec<u8>>,
                         carries_safe: &mut bool,
                         seq: u32,
                         msg: &[u8]| {
            loop {
                if need_syn && !*carries_safe {
                    if !w.push_syn(syn) {
                        finish(w, out, carries_safe);
                        continue;
                    }
                    *carries_safe = true;
                }
                if w.push_safe(seq, msg) {
                    *carries_safe = true;
                    return;
                }
                finish(w, out, carries_safe);
            }
        };
        for seq in due {
            if let Some(msg) = st.tx.message(seq) {
                push_safe(&mut w, &mut out, &mut carries_safe, seq, msg);
            }
        }
        loop {
            let next = if !st.tx.can_push() {
                None
            } else if let Some(m) = st.safe.pop_front() {
                Some(m)
            } else if st.bulk_may_leave() {
                let m = st.pop_bulk();
                st.mid_message = m
                    .as_ref()
                    .is_some_and(|m| m.0.first() == Some(&parts::PART_MORE));
                m
            } else {
                None
            };
            let Some((mut msg, done, queued)) = next else {
                break;
            };
            st.safe_bytes = st.safe_bytes.saturating_sub(queued_safe_cost(msg.len()));
            if let Some(waited) = queued.map(|t| now.saturating_duration_since(t)) {
                // A part is not a message the handler could read.
                if !waited.is_zero() && !parts::is_part(&msg) {
                    let mut aged = Vec::from(msg);
                    self.handler.age_safe(&mut aged, waited);
                    msg = aged.into();
                }
            }
            let seq = st.tx.push(now, msg, done);
            if let Some(m) = st.tx.message(seq) {
                push_safe(&mut w, &mut out, &mut carries_safe, seq, m);
            }
        }
        while let Some((_, msg)) = st.fast.pop_front() {
            if !w.push_fast(&msg) {
                finish(&mut w, &mut out, &mut carries_safe);
                w.push_fast(&msg);
            }
        }
        st.fast_bytes = 0;
        finish(&mut w, &mut out, &mut carries_safe);
        st.wire.keep_spare(w.into_spare());
        st.last_write = Some(now);
        st.wake_pending = false;
        Outbound {
            wire: st.wire.clone(),
            datagrams: out,
        }
    }

    /// Writes the datagrams `out` built for `addr` (after those the socket refused before),
    /// sealed, in the order they were built: the peer's wire is taken first, then `unlock` lets
    /// the peer's state go (a flush that can wait drops its guard there; one that must keep the
    /// state while it writes passes a no-op). Returns whether the socket refused a write: its
    /// retry must be armed ([`Self::retry_blocked`]) once the state is let go.
    #[must_use]
    fn write(&self, addr: M::Addr, out: Outbound, unlock: impl FnOnce()) -> bool {
        let Outbound { wire, datagrams } = out;
        let mut blocked = lock(&wire.blocked);
        unlock();
        if datagrams.is_empty() && blocked.is_empty() {
            return false;
        }
        let mut refused = false;
        let was_blocked = !blocked.is_empty();
        while let Some(d) = blocked.front() {
            match self.medium.send_to(d, addr) {
                Ok(_) => self.count_out(d.len()),
                Err(e) if e.kind() == io::ErrorKind::WouldBlock => {
                    refused = true;
                    break;
                }
                Err(e) => {
                    tracing::debug!(link = %self.name, %addr, error = %e, "datagram not sent");
                }
            }
            blocked.pop_front();
        }
        let mut sent = Vec::new();
        for d in datagrams {
            let d = self.seal(d, Some(addr));
            if refused {
                blocked.push_back(d);
                continue;
            }
            match self.medium.send_to(&d, addr) {
                Ok(_) => self.count_out(d.len()),
                Err(e) if e.kind() == io::ErrorKind::WouldBlock => {
                    refused = true;
                    blocked.push_back(d);
                    continue;
                }
                Err(e) => {
                    tracing::debug!(link = %self.name, %addr, error = %e, "datagram not sent");
                }
            }
            if sent.len() < SPARE_BUFFERS {
                sent.push(d);
            }
        }
        wire.is_blocked
            .store(!blocked.is_empty(), Ordering::Release);
        drop(blocked);
        // Drained: what the flushes left queued meanwhile (they build nothing while blocked)
        // goes at the transmit task's next visit.
        if was_blocked && !refused && lock(&self.agenda).flush(addr) {
            self.wake.notify_one();
        }
        wire.keep_spare(sent);
        refused
    }

    /// Flushes `addr` if it has work (or `force`), arms its next deadline, then writes with
    /// its state let go. Returns whether the transmit task must be woken ([`Self::arm`]).
    fn visit(
        &self,
        addr: M::Addr,
        mut st: MutexGuard<'_, PeerState>,
        now: Instant,
        force: bool,
    ) -> bool {
        let out = (force || st.has_work()).then(|| self.flush_locked(addr, &mut st, now));
        let wake = self.arm(addr, &mut st);
        match out {
            Some(out) => self.write_unlocking(addr, out, st),
            None => drop(st),
        }
        wake
    }

    /// [`Self::write`] that lets the peer's state `st` go, and arms a refused write's retry.
    fn write_unlocking(&self, addr: M::Addr, out: Outbound, st: MutexGuard<'_, PeerState>) {
        if self.write(addr, out, || drop(st)) {
            self.retry_blocked(addr);
        }
    }

    /// Arms the retry of `addr`'s datagrams the socket refused (see [`Self::arm`]).
    fn retry_blocked(&self, addr: M::Addr) {
        let Some(p) = self.peer(addr, false) else {
            return;
        };
        let mut st = lock(&p);
        if self.arm(addr, &mut st) {
            drop(st);
            self.wake.notify_one();
        }
    }

    /// Whether the safe messages queued for `addr` wait for the next acknowledgement instead of
    /// leaving now (Nagle's rule, per datagram): while earlier ones are unacknowledged and
    /// the queue fills less than a datagram, and nothing else is to send. The receive task
    /// flushes the peer at each acknowledgement (the retransmission timer if it is lost), so a
    /// message waits one round trip at most; a fast stream leaves in full datagrams, each
    /// acknowledged once, instead of one small datagram per wake-up, each acknowledged too
    /// (that cycle held a loopback stream of 64 B events at ~3 M/s with 100,000 datagrams a
    /// second each way). A lone message, with nothing in flight, leaves at once.
    fn gathers_safe(&self, addr: M::Addr, st: &PeerState) -> bool {
        st.tx.in_flight() > 0
            && st.fast.is_empty()
            && !st.rx.ack_pending()
            && !st.wire.is_blocked()
            && st.safe_bytes < self.datagram_max(addr)
    }

    fn datagram_max(&self, addr: M::Addr) -> usize {
        self.medium.datagram_max(addr)
    }

    /// The largest safe message that fits a datagram to `addr` with a SYN and an
    /// acknowledgement beside it: larger ones go in parts of this size.
    fn part_room(&self, addr: M::Addr) -> usize {
        let seal = self.sealer.as_ref().map_or(0, |(s, _)| s.overhead());
        self.datagram_max(addr)
            .saturating_sub(seal + PART_HEADROOM)
            .max(parts::MIN_ROOM)
    }

    fn count_out(&self, n: usize) {
        self.counters.count_out(n);
    }

    /// Data sealed with the domain key from `pair`'s peer at `addr` was refused: past
    /// [`PAIR_LOST_AFTER`] of that with no frame sealed with the pair's keys, the peer lost
    /// the pair: forgotten here and reported unreachable (the node drops it).
    fn refused_by_pair(&self, addr: M::Addr, pair: &PairSeal) {
        let now = Instant::now();
        let lost = {
            let mut since = lock(&pair.refused_since);
            let first = *since.get_or_insert(now);
            now.saturating_duration_since(first) >= PAIR_LOST_AFTER
        };
        if lost {
            lock(&self.pairs).remove(&addr);
            tracing::info!(link = %self.name, %addr, "peer seals with the domain key again: it lost our pair's keys; dropped to meet afresh");
            self.handler
                .on_peer_unreachable(self.index, M::peer_addr(addr));
        }
    }

    /// Sends `pair`'s peer at `addr` a probe (see [`PairSeal`]), unless one left within
    /// [`PROBE_EVERY`].
    fn probe(&self, addr: M::Addr, pair: &PairSeal) {
        {
            let mut last = lock(&pair.probed);
            let now = Instant::now();
            if last.is_some_and(|t| now.saturating_duration_since(t) < PROBE_EVERY) {
                return;
            }
            *last = Some(now);
        }
        // An empty data datagram: no entry to take, only the seal to check.
        let mut d = vec![super::KIND_PAIR_DATA];
        pair.sealer.seal(&mut d, usize::MAX);
        if self.medium.send_to(&d, addr).is_ok() {
            self.count_out(d.len());
        }
    }

    /// The pair seal of the peer at `addr`, if it has one.
    fn pair(&self, addr: M::Addr) -> Option<Arc<PairSeal>> {
        let pairs = lock(&self.pairs);
        if pairs.is_empty() {
            return None;
        }
        pairs.get(&addr).cloned()
    }

    /// With a key, seals a datagram built by [`datagram`] for `to` (its kind byte becoming
    /// the sealed kind): data with the keys of `to`'s pair when it has some, else (and
    /// discovery always) with the domain key; without, returns it as it is.
    fn seal(&self, mut d: Vec<u8>, to: Option<M::Addr>) -> Vec<u8> {
        let (Some((data, announce)), Some(kind)) = (&self.sealer, d.first_mut()) else {
            return d;
        };
        if *kind == super::KIND_DISCOVERY {
            *kind = super::sealed_kind(*kind);
            announce.seal(&mut d, usize::MAX);
        } else if let Some(pair) = to
            .and_then(|a| self.pair(a))
            .filter(|p| p.confirmed.load(Ordering::Relaxed))
        {
            *kind = super::KIND_PAIR_DATA;
            pair.sealer.seal(&mut d, usize::MAX);
        } else {
            *kind = super::sealed_kind(*kind);
            data.seal(&mut d, usize::MAX);
        }
        d
    }

    /// The datagram `buf` received from `from` as [`datagram::decode`] takes it: with a key,
    /// its seal checked and removed, or `None` (dropped and counted) when it fails. Data from
    /// a peer with a pair seal opens with the pair's key only, once one such frame came.
    fn unseal<'a>(&self, buf: &'a mut [u8], from: M::Addr) -> Option<&'a [u8]> {
        let Some(opener) = &self.opener else {
            return Some(buf);
        };
        let kind = buf.first().copied();
        let opened = if kind == Some(super::KIND_PAIR_DATA) {
            match self.pair(from) {
                Some(pair) => {
                    let opened = lock(&pair.opener).open(0, buf, usize::MAX);
                    if opened.is_ok() {
                        *lock(&pair.refused_since) = None;
                        if !pair.confirmed.swap(true, Ordering::Relaxed) {
                            *lock(&pair.confirmed_at) = Some(Instant::now());
                        }
                    }
                    opened.map(|n| (super::KIND_DATA, n))
                }
                None => Err(AuthReject::NoPair),
            }
        } else {
            let kind = kind.and_then(super::unsealed_kind);
            let opened = match kind {
                Some(kind) => lock(opener).open(0, buf, usize::MAX).map(|n| (kind, n)),
                None => Err(AuthReject::Unsealed),
            };
            // Data sealed with the domain key (its seal verified) from a peer with a pair:
            // show it we hold the pair's keys; once it showed it holds them too, refuse it.
            match (opened, kind == Some(super::KIND_DATA)) {
                (Ok(o), true) => match self.pair(from) {
                    Some(p) => {
                        self.probe(from, &p);
                        if p.confirmed.load(Ordering::Relaxed) {
                            self.refused_by_pair(from, &p);
                            Err(AuthReject::NotPairSealed)
                        } else {
                            Ok(o)
                        }
                    }
                    None => Ok(o),
                },
                (opened, _) => opened,
            }
        };
        match opened {
            Ok((kind, n)) => {
                buf[0] = kind;
                Some(&buf[..n])
            }
            Err(why) => {
                self.counters.count_in(buf.len());
                let total = self.counters.count_reject(why);
                // Expected while two ends switch to their pair's keys (a frame of the peer's
                // that left before it switched; a probe of a peer whose proof we refused):
                // counted, and logged as a warning only past the switch.
                let switching = match why {
                    // From a peer we hold a session with: it holds keys we do not (yet).
                    AuthReject::NoPair => self.peer(from, false).is_some(),
                    AuthReject::NotPairSealed => self.pair(from).is_some_and(|p| {
                        lock(&p.confirmed_at).is_some_and(|t| t.elapsed() < SWITCH_TIME)
                    }),
                    _ => false,
                };
                if switching {
                    tracing::debug!(link = %self.name, %from, reason = %why, total, "frame dropped while switching to pair keys");
                } else {
                    auth::log_reject(&self.name, from, why, total);
                }
                None
            }
        }
    }

    /// Tells `to` that we hold no session of its and dropped its safe message `seq` unread
    /// ([`Entry::Unknown`]): it starts a new session (and introduces itself again) at once
    /// instead of retransmitting until its retry limit and then dropping us as unreachable.
    fn tell_unknown(&self, to: M::Addr, seq: u32) {
        let seal = self.sealer.as_ref().map_or(0, |(s, _)| s.overhead());
        let mut w = DatagramWriter::new(self.datagram_max(to).saturating_sub(seal));
        if w.push_unknown(seq) {
            let d = self.seal(w.take(), Some(to));
            if self.medium.send_to(&d, to).is_ok() {
                self.count_out(d.len());
            }
        }
    }

    /// Puts session `addr` on the transmit task's agenda for its next deadline (a retransmission
    /// timer, or a blocked socket's retry shortly), unless it is there for that time or sooner.
    /// Returns whether the task must be woken for it (it became the soonest).
    fn arm(&self, addr: M::Addr, st: &mut PeerState) -> bool {
        let at = if !st.wire.is_blocked() {
            st.tx.next_deadline()
        } else {
            // The kernel's send buffer was full: retry shortly (rare; loopback drains fast).
            Some(Instant::now() + Duration::from_millis(1))
        };
        let Some(at) = at else {
            return false;
        };
        if st.timer_at.is_some_and(|t| t <= at) {
            return false;
        }
        st.timer_at = Some(at);
        lock(&self.agenda).at(at, addr)
    }

    /// Visits the sessions on the agenda as they fall due: retransmits what is due, flushes
    /// what senders left to the task, gives up on a session past the retry limit.
    async fn transmit_loop(self: Arc<Self>, cancel: CancellationToken) {
        loop {
            let now = Instant::now();
            let due = lock(&self.agenda).take_due(now);
            let mut gave_up = Vec::new();
            let visits = due
                .flush
                .into_iter()
                .map(|a| (a, None))
                .chain(due.timers.into_iter().map(|(t, a)| (a, Some(t))));
            for (addr, timer) in visits {
                let Some(p) = lock(&self.peers).get(&addr).cloned() else {
                    continue;
                };
                let mut st = lock(&p);
                if timer.is_none() {
                    // Asked by a sender: later ones ask again once this visit is done.
                    st.wake_pending = false;
                }
                if let Some(t) = timer {
                    if st.timer_at != Some(t) {
                        // An entry this session's timer replaced, or one already served.
                        continue;
                    }
                    st.timer_at = None;
                    if st.tx.exhausted(now, self.retry_limit) {
                        drop(st);
                        gave_up.push((addr, p));
                        continue;
                    }
                }
                let retransmit_due = st.tx.next_deadline().is_some_and(|d| d <= now);
                self.visit(addr, st, now, retransmit_due);
            }
            self.close_stale(now, gave_up);
            let mut sleep_until = lock(&self.agenda).next_timer();
            if let Some(d) = lock(&self.peers).next_expiry() {
                sleep_until = Some(sleep_until.map_or(d, |x| x.min(d)));
            }
            let sleep_until = sleep_until.unwrap_or(now + Duration::from_secs(3600));
            tokio::select! {
                _ = cancel.cancelled() => break,
                _ = self.wake.notified() => {}
                _ = tokio::time::sleep_until(sleep_until.into()) => {}
            }
        }
        let peers: Vec<Arc<Mutex<PeerState>>> = lock(&self.peers).drain().map(|(_, p)| p).collect();
        for p in peers {
            fail_all(&mut lock(&p), LinkSendError::Shutdown);
        }
    }

    /// Takes datagram `buf`, received from `from`: its seal checked, its entries delivered to
    /// the node, acknowledgements applied. The peers it touched are added to `touched`, for
    /// [`DatagramLink::received`] once the medium has nothing more waiting.
    pub(crate) fn receive(&self, buf: &mut [u8], from: M::Addr, touched: &mut Vec<M::Addr>) {
        if let Some(d) = self.unseal(buf, from) {
            self.handle_datagram(d, from, touched);
        }
    }

    /// After a burst of [`DatagramLink::receive`]: flushes the peers it touched (their
    /// acknowledgements may have opened the window for queued safe messages) and tells the
    /// transmit task of new retransmission timers.
    pub(crate) fn received(&self, touched: Vec<M::Addr>) {
        let now = Instant::now();
        let mut wake = false;
        for addr in touched {
            if let Some(p) = self.peer(addr, false) {
                wake |= self.visit(addr, lock(&p), now, false);
            }
        }
        // The transmit task only keeps retransmission timers and blocked sends: it is woken
        // only when one of them is sooner than it planned to wake (waking it for every
        // datagram cost a thread hop each, and it walked every session then).
        if wake {
            self.wake.notify_one();
        }
    }

    /// Takes datagram `buf` from a discovery channel (a multicast group): only a discovery
    /// datagram is taken; anything else is counted as corrupt.
    pub(crate) fn receive_announce(&self, buf: &mut [u8], from: M::Addr) {
        let n = buf.len();
        let Some(d) = self.unseal(buf, from) else {
            return;
        };
        self.counters.count_in(n);
        match super::decode(d) {
            Ok(Datagram::Discovery(msg)) => {
                self.handler
                    .on_announce(self.index, M::peer_addr(from), msg)
            }
            _ => {
                self.counters.corrupt.fetch_add(1, Ordering::Relaxed);
            }
        }
    }

    /// The safe messages delivered in order, with parts joined into the messages they make.
    fn join_parts<'a>(
        &self,
        joiner: &mut parts::Joiner,
        delivered: Vec<std::borrow::Cow<'a, [u8]>>,
        from: M::Addr,
    ) -> Vec<std::borrow::Cow<'a, [u8]>> {
        let mut whole = Vec::with_capacity(delivered.len());
        for m in delivered {
            let (joined, dropped) = joiner.take(m, crate::protocol::MAX_MESSAGE);
            if let Some(why) = dropped {
                self.counters.corrupt.fetch_add(1, Ordering::Relaxed);
                tracing::warn!(
                    link = %self.name, %from, ?why,
                    "a message sent in parts was dropped (larger than {} bytes)",
                    crate::protocol::MAX_MESSAGE
                );
            }
            whole.extend(joined);
        }
        whole
    }

    fn handle_datagram(&self, bytes: &[u8], from: M::Addr, touched: &mut Vec<M::Addr>) {
        self.counters.count_in(bytes.len());
        let entries = match super::decode(bytes) {
            Ok(Datagram::Data(e)) => e,
            Ok(Datagram::Discovery(msg)) => {
                self.handler
                    .on_announce(self.index, M::peer_addr(from), msg);
                return;
            }
            Err(e) => {
                self.counters.corrupt.fetch_add(1, Ordering::Relaxed);
                tracing::trace!(link = %self.name, %from, error = %e, "corrupt datagram dropped");
                return;
            }
        };
        let has_syn = entries.iter().any(|e| matches!(e, Entry::Syn(_)));
        let Some(p) = self.peer(from, has_syn) else {
            // No session with this address: only fast messages mean anything.
            let mut unread = None;
            for e in entries {
                match e {
                    Entry::Fast(msg) => {
                        self.handler.on_message(self.index, M::peer_addr(from), msg);
                    }
                    Entry::Safe { seq, .. } => unread = unread.or(Some(seq)),
                    _ => {}
                }
            }
            // Safe messages of a session we forgot (no SYN: the sender thinks we know it).
            // (With a SYN, we refused the session: a reply would only have it start another.)
            if let (Some(seq), false) = (unread, has_syn) {
                self.tell_unknown(from, seq);
            }
            return;
        };
        // In-order messages are handed on from the datagram itself; only those the reorder
        // buffer held are owned.
        let mut deliver: Vec<std::borrow::Cow<'_, [u8]>> = Vec::new();
        let mut fast: Vec<&[u8]> = Vec::new();
        let mut completed = Vec::new();
        let mut reset = false;
        let mut answered = false;
        let mut unread = None;
        {
            let mut st = lock(&p);
            let now = Instant::now();
            let dups_before = st.rx.stats().duplicates;
            let over_before = st.rx.stats().over_budget;
            for e in &entries {
                match *e {
                    Entry::Syn(session) => {
                        let outcome = st.rx.on_syn(session);
                        if outcome != SynOutcome::Same {
                            // A message joined from the last session's parts is not this one's.
                            st.joiner.reset();
                        }
                        if outcome == SynOutcome::Reset {
                            // The peer lost our session too: what we had in flight to it will
                            // never be acknowledged, and our next messages start a new session.
                            reset = true;
                            fail_sender(&mut st, LinkSendError::PeerClosed(from.to_string()));
                        }
                    }
                    Entry::Safe { seq, msg } => {
                        if !st.rx.has_session() {
                            // The sender's session is one we forgot (this session is ours
                            // only, made to send to it since).
                            unread = unread.or(Some(seq));
                            continue;
                        }
                        st.rx.on_safe(seq, msg, |m| {
                            deliver.push(if std::ptr::eq(m, msg) {
                                std::borrow::Cow::Borrowed(msg)
                            } else {
                                std::borrow::Cow::Owned(m.to_vec())
                            })
                        });
                    }
                    Entry::Fast(msg) => fast.push(msg),
                    Entry::Ack(ack) => {
                        completed.extend(st.tx.on_ack(now, ack));
                        if !st.answered && st.tx.session_acked() {
                            st.answered = true;
                            answered = true;
                        }
                        if !st.bulk.is_empty() {
                            st.sample_rate(now);
                        }
                    }
                    // Only about a message still in flight: a late answer to an earlier
                    // session of ours (or a made-up one) changes nothing.
                    Entry::Unknown(seq) if st.tx.message(seq).is_some() => {
                        reset = true;
                        fail_sender(&mut st, LinkSendError::PeerClosed(from.to_string()));
                    }
                    Entry::Unknown(_) => {}
                }
            }
            if !deliver.is_empty() {
                deliver = self.join_parts(&mut st.joiner, deliver, from);
            }
            let dups = st.rx.stats().duplicates - dups_before;
            self.counters.duplicates.fetch_add(dups, Ordering::Relaxed);
            let over = st.rx.stats().over_budget - over_before;
            self.counters
                .reorder_dropped
                .fetch_add(over, Ordering::Relaxed);
        }
        if let Some(seq) = unread {
            self.tell_unknown(from, seq);
        }
        if !touched.contains(&from) {
            touched.push(from);
        }
        let peer = M::peer_addr(from);
        if reset {
            self.handler.on_peer_reset(self.index, peer);
        }
        if answered {
            self.handler.on_peer_answered(self.index, peer);
        }
        // Safe messages in order, then the fast ones, as one batch for the node.
        let mut msgs: Vec<&[u8]> = Vec::with_capacity(deliver.len() + fast.len());
        msgs.extend(deliver.iter().map(|m| &**m));
        msgs.extend(fast);
        if !msgs.is_empty() {
            self.handler.on_messages(self.index, peer, &msgs);
        }
        acknowledge_all(completed);
    }
}

/// What a queued safe message of `len` bytes will take in a datagram, at most (its sequence
/// number is not known yet): counted in [`PeerState::safe_bytes`].
fn queued_safe_cost(len: usize) -> usize {
    DatagramWriter::safe_cost(u32::MAX, len)
}

fn fail_all(st: &mut PeerState, err: LinkSendError) {
    st.safe_bytes = 0;
    st.bulk_holding = 0;
    st.mid_message = false;
    let queued: Vec<QueuedSafe> = st
        .safe
        .drain(..)
        .chain(st.bulk.drain(..).map(|(m, _)| m))
        .collect();
    for (_, done, _) in queued {
        if let Some(d) = done {
            let _ = d.send(Err(err.clone()));
        }
    }
    fail_sender(st, err);
}

/// Replaces the sending session with a fresh one, failing what was in flight.
fn fail_sender(st: &mut PeerState, err: LinkSendError) {
    let config = st.tx.config();
    let tx = std::mem::replace(&mut st.tx, ArqSender::new(rand::random(), config));
    for d in tx.close() {
        let _ = d.send(Err(err.clone()));
    }
    // The rest of a message whose first parts left in that session goes too: the peer starts
    // joining afresh with the new session, and would take the tail for a whole message.
    if std::mem::take(&mut st.mid_message) {
        while let Some((part, done, _)) = st.pop_bulk() {
            st.safe_bytes = st.safe_bytes.saturating_sub(queued_safe_cost(part.len()));
            if let Some(d) = done {
                let _ = d.send(Err(err.clone()));
            }
            if part.first() == Some(&parts::PART_LAST) {
                break;
            }
        }
    }
}

impl<M: Medium> Link for DatagramLink<M> {
    fn name(&self) -> &str {
        &self.name
    }

    fn local_addr(&self) -> String {
        self.medium.local_addr()
    }

    fn send(&self, to: PeerAddr, out: Outgoing) {
        let Some(addr) = M::medium_addr(to) else {
            return;
        };
        let Some(p) = self.peer(addr, true) else {
            return out.refuse(addr);
        };
        // A message larger than a datagram goes in parts, reliably (a fast one too: a lost
        // part would lose the whole). Split before the session is locked: copying a camera
        // frame into its parts takes a while, and a call to the same peer must not wait for it.
        let room = self.part_room(addr);
        let out = match out {
            Outgoing::Fast { msg, .. } if msg.len() > room => Outgoing::Safe {
                msg: msg.into(),
                done: None,
            },
            out => out,
        };
        // (With whether urgent messages must stay behind its parts: a large call or
        // declaration batch keeps its place among them as a small one does.)
        let parts = match &out {
            Outgoing::Safe { msg, .. } if msg.len() > room => Some((
                parts::split(msg, room),
                self.handler.precedence(msg) != Precedence::Passable,
            )),
            _ => None,
        };
        let mut st = lock(&p);
        // The clock is read only where it is needed (an event behind a full window, the
        // common case of a fast event stream, needs none).
        let safe = matches!(out, Outgoing::Safe { .. });
        // A message passing bulk data leaves at once, not gathered for the next acknowledgement.
        let mut urgent = false;
        match out {
            Outgoing::Fast { coalesce, msg } => {
                let cost = DatagramWriter::fast_cost(msg.len());
                // A message that would overflow the datagram being gathered sends that datagram
                // first: a publisher faster than the transmit task fills whole datagrams itself
                // instead of having its values coalesced away while the task waits for a core.
                if 1 + st.fast_bytes + cost > self.datagram_max(addr) && !st.wire.is_blocked() {
                    // Written with the state held: the message is queued after the flush. (A
                    // refused write needs no retry armed here: the fast message queued below
                    // sends this peer to the transmit task, which writes the refused first.)
                    let out = self.flush_locked(addr, &mut st, Instant::now());
                    let _refused = self.write(addr, out, || {});
                }
                match st.fast.push(coalesce, msg) {
                    Pushed::Replaced(old) => {
                        st.fast_bytes = st
                            .fast_bytes
                            .saturating_sub(DatagramWriter::fast_cost(old.len()))
                    }
                    Pushed::DroppedOldest(dropped) => {
                        st.fast_bytes = st
                            .fast_bytes
                            .saturating_sub(DatagramWriter::fast_cost(dropped.len()));
                        self.counters.fast_dropped.fetch_add(1, Ordering::Relaxed);
                    }
                    Pushed::Queued => {}
                }
                st.fast_bytes += cost;
            }
            Outgoing::Safe { msg, done } => {
                if !st.bound && st.safe_queued() + st.tx.in_flight() >= MAX_UNBOUND_SAFE {
                    drop(st);
                    return Outgoing::Safe { msg, done }.refuse(addr);
                }
                // Only a message that ages as it waits (a call) reads the clock, and only when
                // it may wait: behind others, or gathered for the acknowledgement of one in
                // flight (or behind a full window).
                let waits = st.tx.in_flight() > 0 || st.safe_queued() > 0;
                let queued = (waits && self.handler.ages(&msg)).then(Instant::now);
                if let Some((parts, holds)) = parts {
                    // Told when its last part is acknowledged.
                    let last = parts.len() - 1;
                    let mut done = done;
                    for (k, part) in parts.into_iter().enumerate() {
                        st.safe_bytes += queued_safe_cost(part.len());
                        let done = if k == last { done.take() } else { None };
                        st.push_bulk((part.into(), done, queued), holds);
                    }
                } else if st.bulk.is_empty() {
                    st.safe_bytes += queued_safe_cost(msg.len());
                    st.safe.push_back((msg, done, queued));
                } else {
                    let precedence = self.handler.precedence(&msg);
                    urgent = precedence == Precedence::Urgent && st.bulk_holding == 0;
                    st.safe_bytes += queued_safe_cost(msg.len());
                    if urgent {
                        st.urgent_at = Some(Instant::now());
                        st.safe.push_back((msg, done, queued));
                    } else {
                        st.push_bulk((msg, done, queued), precedence != Precedence::Passable);
                    }
                }
            }
        }
        if !st.has_work() {
            // A safe message behind a full window: nothing can leave before an acknowledgement
            // opens it, and the receive task flushes the peer when one does. Waking the
            // transmit task for it cost a futex wake-up per raise in a fast event stream.
            return;
        }
        if safe && !urgent && self.gathers_safe(addr, &st) {
            return;
        }
        let now = Instant::now();
        let idle = !st.wire.is_blocked()
            && st
                .last_write
                .is_none_or(|t| now.saturating_duration_since(t) >= BATCH_WINDOW);
        if idle {
            let out = self.flush_locked(addr, &mut st, now);
            // The first safe message in flight starts a retransmission timer the transmit task
            // does not know of (it may sleep with no deadline at all): tell it, or a lost lone
            // message to a peer that sends nothing back would wait for some other wake-up.
            let wake = self.arm(addr, &mut st);
            self.write_unlocking(addr, out, st);
            if wake {
                self.wake.notify_one();
            }
        } else if !st.wake_pending {
            st.wake_pending = true;
            drop(st);
            if lock(&self.agenda).flush(addr) {
                self.wake.notify_one();
            }
        }
    }

    fn announce(&self, msg: &[u8]) {
        for t in 0..self.medium.announce_targets() {
            // Sealed once per target: a node reached both ways sees two datagrams, not a
            // replay.
            let d = self.seal(super::discovery_datagram(msg), None);
            match self.medium.announce_to(&d, t) {
                Ok(()) => self.count_out(d.len()),
                Err(e) => {
                    tracing::debug!(link = %self.name, target = t, error = %e, "announce not sent")
                }
            }
        }
    }

    fn confirm_peer(&self, to: PeerAddr) {
        if let Some(addr) = M::medium_addr(to) {
            if let Some(p) = self.session(addr, false, true) {
                if lock(&self.peers).is_bound(&addr) {
                    lock(&p).bound = true;
                }
            } else {
                tracing::warn!(link = %self.name, %addr, "no room for a session with a new peer ({MAX_PEERS} bound)");
            }
        }
    }

    fn answered(&self, to: PeerAddr) -> bool {
        M::medium_addr(to)
            .and_then(|addr| self.session(addr, false, false))
            .is_some_and(|p| lock(&p).answered)
    }

    fn close_peer(&self, to: PeerAddr) {
        let Some(addr) = M::medium_addr(to) else {
            return;
        };
        let p = lock(&self.peers).remove(&addr);
        lock(&self.pairs).remove(&addr);
        if let Some(p) = p {
            fail_all(&mut lock(&p), LinkSendError::PeerClosed(addr.to_string()));
        }
    }

    fn pair_sealed(&self, to: PeerAddr) -> bool {
        M::medium_addr(to)
            .and_then(|a| self.pair(a))
            .is_some_and(|p| p.confirmed.load(Ordering::Relaxed))
    }

    fn set_pair(&self, to: PeerAddr, keys: Option<Arc<crate::link::auth::PairKeys>>) {
        let (Some(addr), Some(_)) = (M::medium_addr(to), &self.sealer) else {
            return;
        };
        let Some(k) = keys else {
            lock(&self.pairs).remove(&addr);
            return;
        };
        let pair = {
            let mut pairs = lock(&self.pairs);
            // The same keys again: the replay window of a live pair is never reset.
            if pairs.get(&addr).is_some_and(|p| p.keys == k) {
                return;
            }
            let (out, back) = (
                auth::DomainKey::from_bytes(k.send),
                auth::DomainKey::from_bytes(k.recv),
            );
            let pair = Arc::new(PairSeal {
                sealer: Sealer::new(&out, Profile::UDP_PAIR),
                opener: Mutex::new(Opener::new(&back, Profile::UDP_PAIR, PAIR_REPLAY_WINDOWS)),
                confirmed: AtomicBool::new(false),
                probed: Mutex::new(None),
                confirmed_at: Mutex::new(None),
                refused_since: Mutex::new(None),
                keys: k,
            });
            pairs.insert(addr, pair.clone());
            pair
        };
        self.probe(addr, &pair);
    }

    fn stats(&self) -> LinkStats {
        self.counters.stats(self.gauges())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn peer() -> PeerState {
        PeerState::new(ArqConfig::lan())
    }

    #[test]
    fn bulk_in_flight_follows_the_acknowledged_rate_and_shrinks_while_urgent_messages_pass() {
        let mut st = peer();
        assert_eq!(st.bulk_limit(), BULK_IN_FLIGHT_MIN, "unmeasured: the least");
        st.acked_rate = 2e9; // 2 GB/s: 2 MB drain in 1 ms
        assert_eq!(st.bulk_limit(), 2_000_000);
        st.acked_rate = 1e12;
        assert_eq!(st.bulk_limit(), BULK_IN_FLIGHT_MAX);
        st.urgent_at = Some(Instant::now());
        assert_eq!(
            st.bulk_limit(),
            BULK_IN_FLIGHT_MIN,
            "calls about: the least"
        );
    }

    #[test]
    fn a_session_reset_drops_the_rest_of_a_half_sent_message_and_fails_it() {
        let mut st = peer();
        let (tx, mut rx) = tokio::sync::oneshot::channel();
        let mut parts = parts::split(&[7u8; 300], 100);
        let last = parts.pop().unwrap();
        // The first part left in the old session; two more, then a whole event, wait.
        let first = parts.remove(0);
        st.tx.push(Instant::now(), first, None);
        st.mid_message = true;
        for p in parts {
            st.push_bulk((p.into(), None, None), false);
        }
        st.push_bulk((last.into(), Some(SafeCompletion::Once(tx)), None), false);
        let event = vec![crate::protocol::tag::EVENT, 1];
        st.push_bulk((event.into(), None, None), false);
        fail_sender(&mut st, LinkSendError::PeerClosed("peer".into()));
        assert!(matches!(rx.try_recv(), Ok(Err(_))), "the message is failed");
        assert_eq!(st.bulk.len(), 1, "only the next message is left");
        assert_eq!(st.pop_bulk().unwrap().0[0], crate::protocol::tag::EVENT);
        assert!(!st.mid_message && st.bulk_holding == 0);
    }
}

#[cfg(test)]
mod wire_tests {
    //! The socket's side of a session, over a medium in memory that refuses writes on demand
    //! (a full send buffer; a loopback socket never refuses).

    use std::net::SocketAddr;
    use std::sync::atomic::AtomicUsize;

    use super::*;

    /// What a link wrote, for the test to carry; the next `refuse` writes are refused.
    #[derive(Default)]
    struct Written {
        datagrams: Mutex<Vec<Vec<u8>>>,
        refuse: AtomicUsize,
        changed: Notify,
    }

    #[derive(Clone, Default)]
    struct Memory(Arc<Written>);

    impl Medium for Memory {
        type Addr = SocketAddr;
        fn peer_addr(addr: SocketAddr) -> PeerAddr {
            PeerAddr::Udp(addr)
        }
        fn medium_addr(to: PeerAddr) -> Option<SocketAddr> {
            match to {
                PeerAddr::Udp(a) => Some(a),
                _ => None,
            }
        }
        fn send_to(&self, d: &[u8], _to: SocketAddr) -> io::Result<()> {
            let refused = self
                .0
                .refuse
                .fetch_update(Ordering::SeqCst, Ordering::SeqCst, |n| n.checked_sub(1));
            if refused.is_ok() {
                return Err(io::ErrorKind::WouldBlock.into());
            }
            lock(&self.0.datagrams).push(d.to_vec());
            self.0.changed.notify_one();
            Ok(())
        }
        fn announce_targets(&self) -> usize {
            0
        }
        fn announce_to(&self, _d: &[u8], _target: usize) -> io::Result<()> {
            Ok(())
        }
        fn datagram_max(&self, _to: SocketAddr) -> usize {
            1400
        }
        fn local_addr(&self) -> String {
            "memory".into()
        }
    }

    #[derive(Default)]
    struct Collect(Mutex<Vec<Vec<u8>>>);

    impl LinkHandler for Collect {
        fn on_message(&self, _link: usize, _from: PeerAddr, msg: &[u8]) {
            lock(&self.0).push(msg.to_vec());
        }
        fn on_announce(&self, _link: usize, _from: PeerAddr, _msg: &[u8]) {}
        fn on_peer_reset(&self, _link: usize, _from: PeerAddr) {}
    }

    fn link(
        name: &str,
        medium: Memory,
        handler: Arc<Collect>,
        tasks: &TaskTracker,
        cancel: &CancellationToken,
    ) -> Arc<DatagramLink<Memory>> {
        let options = DatagramLinkOptions {
            name: name.into(),
            arq: ArqConfig::lan(),
            retry_limit: RetryLimit::lan(),
            security: None,
        };
        DatagramLink::create(0, options, medium, handler, tasks, cancel.clone())
    }

    /// Hands what `from` wrote to `to`, as `to`'s receive task would.
    fn carry(from: &Memory, from_addr: SocketAddr, to: &DatagramLink<Memory>) {
        let written = std::mem::take(&mut *lock(&from.0.datagrams));
        let mut touched = Vec::new();
        for mut d in written {
            to.receive(&mut d, from_addr, &mut touched);
        }
        to.received(touched);
    }

    #[tokio::test]
    async fn datagrams_the_socket_refused_are_written_again_first_not_left_to_the_retransmission_timer(
    ) {
        let (tasks, cancel) = (TaskTracker::new(), CancellationToken::new());
        let (ma, mb) = (Memory::default(), Memory::default());
        let (ha, hb) = (Arc::new(Collect::default()), Arc::new(Collect::default()));
        let a = link("a", ma.clone(), ha, &tasks, &cancel);
        let b = link("b", mb.clone(), hb.clone(), &tasks, &cancel);
        let (addr_a, addr_b): (SocketAddr, SocketAddr) = (
            "127.0.0.1:1".parse().unwrap(),
            "127.0.0.1:2".parse().unwrap(),
        );
        // 40 messages of 300 bytes: several datagrams, the first three refused.
        let sent: Vec<Vec<u8>> = (0..40u8).map(|i| vec![i; 300]).collect();
        // Known peers (an unknown address gets only a few safe messages queued).
        a.confirm_peer(PeerAddr::Udp(addr_b));
        b.confirm_peer(PeerAddr::Udp(addr_a));
        ma.0.refuse.store(3, Ordering::SeqCst);
        for m in &sent {
            let out = Outgoing::Safe {
                msg: m.clone().into(),
                done: None,
            };
            a.send(PeerAddr::Udp(addr_b), out);
        }
        let all_arrived = async {
            while lock(&hb.0).len() < sent.len() {
                let written = ma.0.changed.notified();
                carry(&ma, addr_a, &b);
                carry(&mb, addr_b, &a);
                if lock(&hb.0).len() < sent.len() {
                    written.await;
                }
            }
        };
        let arrived = tokio::time::timeout(Duration::from_secs(10), all_arrived).await;
        cancel.cancel();
        assert!(arrived.is_ok(), "only {} of 40 arrived", lock(&hb.0).len());
        assert_eq!(*lock(&hb.0), sent, "every message, in order");
        assert_eq!(
            ma.0.refuse.load(Ordering::SeqCst),
            0,
            "three writes were refused"
        );
        assert_eq!(
            a.stats().retransmitted,
            0,
            "the refused datagrams were written from the blocked queue, not resent by the ARQ"
        );
    }
}
