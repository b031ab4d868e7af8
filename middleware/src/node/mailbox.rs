//! Where a subscription's deliveries wait for the application: FIFO for events, newest value
//! per name for variables.
//!
//! Bounded: a mailbox holds at most [`MAILBOX_CAP`] deliveries. A subscriber that stops
//! reading while a publisher keeps raising events would otherwise grow it without limit; at the
//! bound the oldest delivery is dropped (the newest ones matter most to a vehicle), counted
//! ([`Mailbox::dropped`]) and logged (at the first drop and then at each power of two).

use std::sync::{Arc, Mutex};
use std::time::Instant;

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
    /// postcard bytes.
    pub payload: Vec<u8>,
    /// When it arrived.
    pub received: Instant,
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

#[derive(Debug)]
struct Inner {
    /// Samples are keyed by name when the mailbox coalesces (variables); refusals never are.
    queue: CoalescingQueue<Arc<str>, Delivery>,
    closed: bool,
    /// Readers between finding the queue empty and being woken.
    waiting: usize,
}

/// A subscription's queue.
#[derive(Debug)]
pub(crate) struct Mailbox {
    inner: Mutex<Inner>,
    notify: Notify,
    /// Variables keep only the newest undelivered value per name.
    coalesce: bool,
}

impl Mailbox {
    pub fn new(coalesce: bool) -> Self {
        Mailbox {
            inner: Mutex::new(Inner {
                queue: CoalescingQueue::new(MAILBOX_CAP),
                closed: false,
                waiting: 0,
            }),
            notify: Notify::new(),
            coalesce,
        }
    }

    fn lock(&self) -> std::sync::MutexGuard<'_, Inner> {
        crate::sync::lock(&self.inner)
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
            was_empty && !g.queue.is_empty()
        };
        // The reader waits only on an empty queue (checked under the lock), so only the push
        // that ends the emptiness needs to wake it: one wake-up per burst, not one per value.
        if was_empty {
            self.notify.notify_one();
        }
    }

    pub fn try_pop(&self) -> Option<Delivery> {
        self.lock().queue.pop_front().map(|(_, d)| d)
    }

    /// Waits for the next delivery; `None` once closed and drained.
    pub async fn pop(&self) -> Option<Delivery> {
        loop {
            {
                let mut g = self.lock();
                if let Some((_, d)) = g.queue.pop_front() {
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
        self.lock().closed = true;
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
            payload: vec![1],
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
