//! Where a subscription's deliveries wait for the application: FIFO for events, newest value
//! per name for variables.
//!
//! Bounded: a mailbox holds at most [`MAILBOX_CAP`] deliveries. A subscriber that stops
//! reading while a publisher keeps raising events would otherwise grow it without limit; at the
//! bound the oldest delivery is dropped (the newest ones matter most to a vehicle), counted
//! ([`Mailbox::dropped`]) and logged (at the first drop and then at each power of two).
//!
//! Behind: an event mailbox holding more than [`MAILBOX_BEHIND`] deliveries counts in its
//! node's [`Congestion`] until its reader brings it under [`MAILBOX_CAUGHT_UP`]. While a reader
//! that is still reading is behind, the node tells its peers, whose lossless streams
//! (`Event::stream`) then wait instead of the mailbox dropping (see [`super::flow`]). A reader
//! that took nothing for [`READER_STALLED`] is not waited for: its mailbox drops its oldest
//! deliveries at the bound, as above.

use std::sync::atomic::{AtomicU64, AtomicUsize, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use tokio::sync::Notify;

use crate::link::coalesce::{CoalescingQueue, Pushed};
use crate::typeinfo::TypeInfo;

/// A received value, still encoded.
#[derive(Debug, Clone)]
pub(crate) struct RawSample {
    /// Full name of the item.
    pub name: Arc<str>,
    /// Name of the publishing node.
    pub publisher: Arc<str>,
    /// The publisher's payload type name.
    pub type_name: Arc<str>,
    /// The publisher's payload type fingerprint ([`TypeInfo::fingerprint`]).
    pub fingerprint: u64,
    /// postcard bytes.
    pub payload: Encoded,
    /// When it arrived.
    pub received: Instant,
}

/// A value's postcard bytes as they arrived: a slice of the message they came in, which a
/// shared-memory link may have lent (then they are a view of its sample: no copy was made).
#[derive(Debug, Clone)]
pub(crate) struct Encoded {
    pub bytes: bytes::Bytes,
    /// The bytes are a lent shared-memory sample's ([`crate::Blob::is_shared_memory`]).
    pub lent: bool,
}

impl From<Vec<u8>> for Encoded {
    fn from(v: Vec<u8>) -> Self {
        Encoded {
            bytes: v.into(),
            lent: false,
        }
    }
}

/// A publisher refused a subscription because the types differ.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct TypeMismatch {
    /// Full name of the publication.
    pub name: String,
    /// The node publishing it.
    pub publisher: String,
    /// What the publisher sends.
    pub offered: TypeInfo,
    /// What the subscriber expects.
    pub expected: TypeInfo,
}

impl std::fmt::Display for TypeMismatch {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(
            f,
            "'{}' published by node '{}' carries {} but this subscriber expects {}",
            self.name, self.publisher, self.offered.name, self.expected.name
        )
    }
}

#[derive(Debug)]
pub(crate) enum Delivery {
    Sample(RawSample),
    Refused(TypeMismatch),
}

/// Deliveries a mailbox holds before dropping the oldest: far more than a reader that keeps up
/// ever has waiting (ten thousand events in a burst fit).
pub(crate) const MAILBOX_CAP: usize = 65_536;
/// An event mailbox holding more than this is behind (see the module's documentation): room
/// is left for what senders already have in flight when they are told (a stream's window is
/// 16,384 events: three streams' worth fit).
pub(crate) const MAILBOX_BEHIND: usize = MAILBOX_CAP / 4;
/// A mailbox that was behind has caught up below this.
pub(crate) const MAILBOX_CAUGHT_UP: usize = MAILBOX_CAP / 8;
/// A behind mailbox's reader that took nothing for this long has stopped: senders are no
/// longer held back for it.
pub(crate) const READER_STALLED: Duration = Duration::from_millis(200);

/// A node's event mailboxes that are behind, and when one of their readers last made progress;
/// on a gateway, also the nodes its forwarded events wait for (see [`super::forward_flow`]; the
/// readers behind the nodes it forwards to are kept there, by node).
#[derive(Debug)]
pub(crate) struct Congestion {
    behind: AtomicUsize,
    /// Nodes a gateway forwards events to with more of them unacknowledged than their window.
    forwarding: AtomicUsize,
    start: Instant,
    /// Milliseconds from `start` to the last delivery taken from a behind mailbox (or to the
    /// last mailbox falling behind).
    progress_ms: AtomicU64,
    /// Told when a mailbox falls behind or catches up.
    change: Notify,
}

impl Default for Congestion {
    fn default() -> Self {
        Congestion {
            behind: AtomicUsize::new(0),
            forwarding: AtomicUsize::new(0),
            start: Instant::now(),
            progress_ms: AtomicU64::new(0),
            change: Notify::new(),
        }
    }
}

impl Congestion {
    /// Whether some mailbox is behind while its reader keeps reading.
    pub(crate) fn readers_behind(&self) -> bool {
        self.behind.load(Ordering::Relaxed) > 0
            && self
                .now_ms()
                .saturating_sub(self.progress_ms.load(Ordering::Relaxed))
                < READER_STALLED.as_millis() as u64
    }

    /// Whether events forwarded by this gateway wait for a node (see [`super::forward_flow`]).
    pub(crate) fn forwarding_behind(&self) -> bool {
        self.forwarding.load(Ordering::Relaxed) > 0
    }

    /// Whether some mailbox is behind (its reader reading or not).
    pub(crate) fn any_behind(&self) -> bool {
        self.behind.load(Ordering::Relaxed) > 0
    }

    /// Resolves at the next mailbox falling behind or catching up.
    pub(crate) fn changed(&self) -> tokio::sync::futures::Notified<'_> {
        self.change.notified()
    }

    fn now_ms(&self) -> u64 {
        u64::try_from(self.start.elapsed().as_millis()).unwrap_or(u64::MAX)
    }

    fn progress(&self) {
        self.progress_ms.store(self.now_ms(), Ordering::Relaxed);
    }

    fn fell_behind(&self) {
        self.behind.fetch_add(1, Ordering::Relaxed);
        self.progress();
        self.change.notify_waiters();
    }

    fn caught_up(&self) {
        self.behind.fetch_sub(1, Ordering::Relaxed);
        self.change.notify_waiters();
    }

    /// Forwarded events to a node went over its window.
    pub(crate) fn forwarding_fell_behind(&self) {
        self.forwarding.fetch_add(1, Ordering::Relaxed);
        self.change.notify_waiters();
    }

    /// Forwarded events to a node came back under half its window.
    pub(crate) fn forwarding_caught_up(&self) {
        self.forwarding.fetch_sub(1, Ordering::Relaxed);
        self.change.notify_waiters();
    }

    /// A node a gateway forwards to said its readers fell behind or caught up (see
    /// [`super::forward_flow`]): what the gateway tells its peers is looked at again.
    pub(crate) fn relayed_readers_changed(&self) {
        self.change.notify_waiters();
    }
}

#[derive(Debug)]
struct Inner {
    /// Samples are keyed by name when the mailbox coalesces (variables); refusals never are.
    queue: CoalescingQueue<Arc<str>, Delivery>,
    closed: bool,
    /// Readers between finding the queue empty and being woken.
    waiting: usize,
    /// Counted as behind in the node's [`Congestion`].
    behind: bool,
}

/// What a callback subscription runs for each delivery.
pub(crate) type Callback = Arc<dyn Fn(Delivery) + Send + Sync>;

/// A subscription's queue, or its callback.
pub(crate) struct Mailbox {
    inner: Mutex<Inner>,
    notify: Notify,
    /// Variables keep only the newest undelivered value per name.
    coalesce: bool,
    /// Where an event mailbox counts while it is behind.
    congestion: Option<Arc<Congestion>>,
    /// A callback subscription's (see [`Mailbox::calling`]).
    callback: Option<Callback>,
}

impl std::fmt::Debug for Mailbox {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Mailbox")
            .field("coalesce", &self.coalesce)
            .field("callback", &self.callback.is_some())
            .finish_non_exhaustive()
    }
}

impl Mailbox {
    /// A mailbox counting nowhere when behind.
    #[cfg(test)]
    pub fn new(coalesce: bool) -> Self {
        Self::counted_in(coalesce, None)
    }

    /// A mailbox that, for events, counts in `congestion` while it is behind (variables keep
    /// only their newest values and are never behind).
    pub fn counted_in(coalesce: bool, congestion: Option<Arc<Congestion>>) -> Self {
        Mailbox {
            inner: Mutex::new(Inner {
                queue: CoalescingQueue::new(MAILBOX_CAP),
                closed: false,
                waiting: 0,
                behind: false,
            }),
            notify: Notify::new(),
            coalesce,
            congestion: congestion.filter(|_| !coalesce),
            callback: None,
        }
    }

    /// A callback subscription's mailbox: a run of remote deliveries
    /// ([`Mailbox::deliver_run`]) runs `callback` at once on the link's receive task, which
    /// reads no further datagram until it returns: what comes after is not acknowledged, so a
    /// lossless stream waits for a slow callback. Other deliveries (from publishers on this node, late joiners' values,
    /// refusals) are pushed while the node holds its locks: they queue, and
    /// [`Mailbox::run_queued`] runs the callback for them on a task of its own, so a callback
    /// may publish or declare without deadlocking. A callback that panics is logged; the next
    /// delivery runs it again.
    pub fn calling(callback: Callback) -> Self {
        let mut m = Self::counted_in(false, None);
        m.callback = Some(callback);
        m
    }

    /// Runs the callback for every queued delivery until the mailbox is closed (a callback
    /// mailbox's task; returns at once for any other).
    pub async fn run_queued(&self) {
        let Some(callback) = &self.callback else {
            return;
        };
        while let Some(d) = self.pop().await {
            self.call(callback, d);
        }
    }

    /// Delivers a run from a remote publisher; called with no node lock held. A callback
    /// mailbox runs its callback here; any other queues the run ([`Mailbox::push_all`]).
    pub fn deliver_run(&self, deliveries: impl Iterator<Item = Delivery>) {
        let Some(callback) = &self.callback else {
            return self.push_all(deliveries);
        };
        if self.lock().closed {
            return;
        }
        for d in deliveries {
            self.call(callback, d);
        }
    }

    /// Runs the callback for `d`; a panic is caught so it cannot end the pushing task.
    fn call(&self, callback: &Callback, d: Delivery) {
        let run = std::panic::AssertUnwindSafe(|| callback(d));
        if let Err(panic) = std::panic::catch_unwind(run) {
            let why = panic
                .downcast_ref::<&str>()
                .map(|s| (*s).to_owned())
                .or_else(|| panic.downcast_ref::<String>().cloned())
                .unwrap_or_else(|| "a non-string panic".to_owned());
            tracing::error!(panic = %why, "a subscription's callback panicked; its delivery is lost");
        }
    }

    /// Counts the mailbox as behind once it holds more than [`MAILBOX_BEHIND`].
    fn after_push(&self, g: &mut Inner) {
        if let Some(c) = &self.congestion {
            if !g.behind && g.queue.len() > MAILBOX_BEHIND {
                g.behind = true;
                c.fell_behind();
            }
        }
    }

    /// A delivery was taken: progress, and maybe caught up.
    fn after_pop(&self, g: &mut Inner) {
        if !g.behind {
            return;
        }
        if let Some(c) = &self.congestion {
            if g.queue.len() < MAILBOX_CAUGHT_UP || g.closed {
                g.behind = false;
                c.caught_up();
            } else {
                c.progress();
            }
        }
    }

    fn lock(&self) -> std::sync::MutexGuard<'_, Inner> {
        crate::sync::lock(&self.inner)
    }

    /// Whether it counts as behind (see [`MAILBOX_BEHIND`]).
    pub(crate) fn is_behind(&self) -> bool {
        self.lock().behind
    }

    pub fn push(&self, d: Delivery) {
        self.push_all(std::iter::once(d));
    }

    /// Pushes `deliveries` in order under one lock, with at most one wake-up.
    pub fn push_all(&self, deliveries: impl Iterator<Item = Delivery>) {
        let was_empty = {
            let mut g = self.lock();
            if g.closed {
                return;
            }
            let was_empty = g.queue.is_empty();
            for d in deliveries {
                let key = match &d {
                    Delivery::Sample(s) if self.coalesce => Some(s.name.clone()),
                    _ => None,
                };
                if let Pushed::DroppedOldest(old) = g.queue.push(key, d) {
                    let dropped = g.queue.dropped();
                    if dropped.is_power_of_two() {
                        let name = match &old {
                            Delivery::Sample(s) => s.name.to_string(),
                            Delivery::Refused(r) => r.name.clone(),
                        };
                        tracing::warn!(item = %name, dropped, cap = MAILBOX_CAP, "subscriber not reading: its mailbox is full, oldest deliveries dropped");
                    }
                }
            }
            self.after_push(&mut g);
            was_empty && !g.queue.is_empty()
        };
        // The reader waits only on an empty queue (checked under the lock), so only the push
        // that ends the emptiness needs to wake it: one wake-up per burst, not one per value.
        if was_empty {
            self.notify.notify_one();
        }
    }

    pub fn try_pop(&self) -> Option<Delivery> {
        let mut g = self.lock();
        let d = g.queue.pop_front().map(|(_, d)| d);
        self.after_pop(&mut g);
        d
    }

    /// Waits for the next delivery; `None` once closed and drained.
    pub async fn pop(&self) -> Option<Delivery> {
        loop {
            {
                let mut g = self.lock();
                if let Some((_, d)) = g.queue.pop_front() {
                    self.after_pop(&mut g);
                    if !g.queue.is_empty() && g.waiting > 0 {
                        // Pushes onto a non-empty queue wake nobody: pass the wake-up on to
                        // another task waiting on this mailbox (a lone reader pays nothing).
                        self.notify.notify_one();
                    }
                    return Some(d);
                }
                if g.closed {
                    return None;
                }
                // Counted under the lock, so a pop that leaves deliveries behind sees it; a
                // wake-up sent before the wait below starts is kept by `Notify` as a permit.
                g.waiting += 1;
            }
            // Uncounted when woken, and when the wait is dropped (a receive that timed out).
            let _waiting = Waiting(self);
            self.notify.notified().await;
        }
    }

    pub fn close(&self) {
        {
            let mut g = self.lock();
            g.closed = true;
            // Nobody reads a closed mailbox: no sender waits for it.
            self.after_pop(&mut g);
        }
        self.notify.notify_waiters();
        self.notify.notify_one();
    }

    pub fn len(&self) -> usize {
        self.lock().queue.len()
    }

    /// Deliveries dropped at the bound so far.
    #[cfg_attr(not(test), allow(dead_code))]
    pub fn dropped(&self) -> u64 {
        self.lock().queue.dropped()
    }
}

impl Drop for Mailbox {
    fn drop(&mut self) {
        let inner = self.inner.get_mut().unwrap_or_else(|e| e.into_inner());
        if inner.behind {
            if let Some(c) = &self.congestion {
                c.caught_up();
            }
        }
    }
}

/// A reader counted in [`Inner::waiting`] until this is dropped.
struct Waiting<'a>(&'a Mailbox);

impl Drop for Waiting<'_> {
    fn drop(&mut self) {
        let mut g = self.0.lock();
        g.waiting = g.waiting.saturating_sub(1);
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::time::Duration;

    fn sample(name: &str) -> Delivery {
        Delivery::Sample(RawSample {
            name: name.into(),
            publisher: "p".into(),
            type_name: "u8".into(),
            fingerprint: 0,
            payload: vec![1].into(),
            received: Instant::now(),
        })
    }

    #[test]
    fn a_mailbox_nobody_reads_keeps_the_newest_deliveries_up_to_its_cap() {
        let m = Mailbox::new(false);
        for i in 0..MAILBOX_CAP + 10 {
            m.push(sample(&format!("e{i}")));
        }
        assert_eq!(m.len(), MAILBOX_CAP);
        assert_eq!(m.dropped(), 10);
        match m.try_pop() {
            Some(Delivery::Sample(s)) => assert_eq!(&*s.name, "e10", "the oldest went first"),
            other => panic!("expected a sample, got {other:?}"),
        }
    }

    #[test]
    fn an_event_mailbox_is_behind_from_half_full_until_a_quarter_while_its_reader_reads() {
        let c = Arc::new(Congestion::default());
        let m = Mailbox::counted_in(false, Some(c.clone()));
        let vars = Mailbox::counted_in(true, Some(c.clone()));
        for i in 0..MAILBOX_BEHIND {
            m.push(sample("e"));
            vars.push(sample(&format!("v{i}")));
        }
        assert!(!c.readers_behind(), "a quarter full is not behind yet");
        m.push(sample("e"));
        assert!(c.readers_behind(), "over a quarter full is behind");
        assert!(m.is_behind());
        vars.push(sample("v"));
        while m.len() >= MAILBOX_CAUGHT_UP {
            assert!(c.readers_behind(), "behind until under an eighth");
            m.try_pop();
        }
        assert!(!c.readers_behind(), "caught up");
        assert_eq!(
            c.behind.load(Ordering::Relaxed),
            0,
            "variables are never behind"
        );
        // Behind again, then dropped (its subscription ended): nobody is waited for.
        for _ in 0..MAILBOX_BEHIND {
            m.push(sample("e"));
        }
        assert!(c.readers_behind());
        drop(m);
        assert!(!c.readers_behind());
    }

    #[test]
    fn a_behind_mailbox_whose_reader_stopped_holds_nobody_back() {
        // A node started a minute ago.
        let c = Arc::new(Congestion {
            start: Instant::now() - Duration::from_secs(60),
            ..Congestion::default()
        });
        let m = Mailbox::counted_in(false, Some(c.clone()));
        for _ in 0..=MAILBOX_BEHIND {
            m.push(sample("e"));
        }
        assert!(c.readers_behind());
        // As if the last delivery was taken longer ago than a reader may pause.
        let stalled = c.now_ms() - READER_STALLED.as_millis() as u64 - 1;
        c.progress_ms.store(stalled, Ordering::Relaxed);
        assert!(!c.readers_behind(), "a stopped reader is not waited for");
        m.try_pop();
        assert!(c.readers_behind(), "reading again, it is");
    }

    /// A gateway's forwarded events waiting for a node hold streams back whatever its
    /// mailboxes do (no stall rule: the link, not a reader, settles them), until every node
    /// that fell behind caught up.
    #[test]
    fn forwarding_behind_holds_streams_until_every_node_caught_up() {
        let c = Congestion {
            start: Instant::now() - Duration::from_secs(60),
            ..Congestion::default()
        };
        assert!(!c.forwarding_behind());
        c.forwarding_fell_behind();
        c.forwarding_fell_behind();
        assert!(
            c.forwarding_behind(),
            "with no mailbox behind and no reader for minutes"
        );
        c.forwarding_caught_up();
        assert!(c.forwarding_behind(), "one node still waits");
        c.forwarding_caught_up();
        assert!(!c.forwarding_behind());
    }

    /// A run pushed at once (a datagram's events) arrives whole and in order, and wakes the
    /// reader waiting on the empty mailbox.
    #[tokio::test(flavor = "current_thread")]
    async fn a_run_pushed_at_once_wakes_the_reader_and_keeps_its_order() {
        let m = Arc::new(Mailbox::new(false));
        let reader = {
            let m = m.clone();
            tokio::spawn(async move {
                let mut names = Vec::new();
                for _ in 0..3 {
                    match m.pop().await {
                        Some(Delivery::Sample(s)) => names.push(s.name.to_string()),
                        other => panic!("expected a sample, got {other:?}"),
                    }
                }
                names
            })
        };
        tokio::task::yield_now().await;
        m.push_all(["a", "b", "c"].into_iter().map(sample));
        let names = tokio::time::timeout(Duration::from_secs(5), reader)
            .await
            .expect("the reader was woken")
            .unwrap();
        assert_eq!(names, ["a", "b", "c"]);
    }

    /// Only the push onto an empty queue wakes a reader; with two readers waiting, the one
    /// woken passes the wake-up on when it leaves items behind.
    #[tokio::test(flavor = "current_thread")]
    async fn two_waiting_readers_both_get_a_delivery() {
        let m = Arc::new(Mailbox::new(false));
        let reader = |m: Arc<Mailbox>| tokio::spawn(async move { m.pop().await.is_some() });
        let (a, b) = (reader(m.clone()), reader(m.clone()));
        // On this single-threaded runtime both readers run up to their wait here.
        tokio::task::yield_now().await;
        m.push(sample("x"));
        m.push(sample("y"));
        let both = tokio::time::timeout(Duration::from_secs(5), async {
            (a.await.unwrap(), b.await.unwrap())
        })
        .await;
        assert_eq!(both, Ok((true, true)), "a reader was left waiting");
    }
}
