//! How a link tells the sender of a safe message that the peer acknowledged it (or never will):
//! a channel of its own per message ([`SafeCompletion::Once`], what a single `raise` or a call
//! waits on), or a counter shared by every message of a stream ([`SafeCompletion::Counted`]),
//! which costs a reference count per message instead of a channel.

use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex};

use tokio::sync::{oneshot, Notify};

use super::LinkSendError;

/// Completion of a safe message: resolved when the peer acknowledges it (after the peer's node
/// has dispatched it), or with the reason it never will be.
#[derive(Debug)]
pub enum SafeCompletion {
    /// The message's own channel.
    Once(oneshot::Sender<Result<(), LinkSendError>>),
    /// One message of a stream to one peer, settled on the stream's counter.
    Counted(Arc<AckCounter>),
}

impl SafeCompletion {
    /// Settles the message with `result`. `Err` returns the result when nobody waits for it any
    /// more (the channel's receiver is gone), as a channel's send does.
    pub fn send(self, result: Result<(), LinkSendError>) -> Result<(), Result<(), LinkSendError>> {
        match self {
            SafeCompletion::Once(tx) => tx.send(result),
            SafeCompletion::Counted(c) => {
                c.settle(result);
                Ok(())
            }
        }
    }
}

/// Settles acknowledged messages, in order: a run of messages counted on one stream's counter
/// with one update of it instead of one per message (a datagram acknowledges hundreds).
#[cfg_attr(
    not(any(feature = "udp", feature = "shm", feature = "serial")),
    allow(dead_code)
)]
pub fn acknowledge_all(done: impl IntoIterator<Item = SafeCompletion>) {
    let mut run: Option<(Arc<AckCounter>, u64)> = None;
    for d in done {
        match d {
            SafeCompletion::Counted(c) => match &mut run {
                Some((r, n)) if Arc::ptr_eq(r, &c) => *n += 1,
                _ => {
                    if let Some((r, n)) = run.replace((c, 1)) {
                        r.settle_acknowledged(n);
                    }
                }
            },
            SafeCompletion::Once(tx) => {
                let _ = tx.send(Ok(()));
            }
        }
    }
    if let Some((r, n)) = run {
        r.settle_acknowledged(n);
    }
}

impl From<oneshot::Sender<Result<(), LinkSendError>>> for SafeCompletion {
    fn from(tx: oneshot::Sender<Result<(), LinkSendError>>) -> Self {
        SafeCompletion::Once(tx)
    }
}

/// The settled messages of a stream to one peer: how many were acknowledged or failed, the
/// failures' count and first reason, and a wake-up for the sender waiting for a number of them.
#[derive(Debug, Default)]
pub struct AckCounter {
    settled: AtomicU64,
    failed: AtomicU64,
    first_failure: Mutex<Option<LinkSendError>>,
    /// The sender waits until `settled` reaches this (`0`: nobody waits).
    wake_at: AtomicU64,
    wake: Notify,
}

impl AckCounter {
    fn settle(&self, result: Result<(), LinkSendError>) {
        if let Err(e) = result {
            let mut first = crate::sync::lock(&self.first_failure);
            if first.is_none() {
                *first = Some(e);
            }
            self.failed.fetch_add(1, Ordering::SeqCst);
        }
        self.settle_acknowledged(1);
    }

    /// `n` more messages acknowledged.
    fn settle_acknowledged(&self, n: u64) {
        let settled = self.settled.fetch_add(n, Ordering::SeqCst) + n;
        let at = self.wake_at.load(Ordering::SeqCst);
        if at != 0 && settled >= at {
            self.wake_at.store(0, Ordering::SeqCst);
            self.wake.notify_one();
        }
    }

    /// Messages settled so far.
    pub fn settled(&self) -> u64 {
        self.settled.load(Ordering::SeqCst)
    }

    /// Messages that failed so far, and the first reason.
    pub fn failures(&self) -> (u64, Option<LinkSendError>) {
        let n = self.failed.load(Ordering::SeqCst);
        let first = if n > 0 {
            crate::sync::lock(&self.first_failure).clone()
        } else {
            None
        };
        (n, first)
    }

    /// Waits until at least `n` messages are settled.
    pub async fn settled_at_least(&self, n: u64) {
        loop {
            let woken = self.wake.notified();
            tokio::pin!(woken);
            woken.as_mut().enable();
            // Published before the check: a settle after the check sees it and wakes us; one
            // before it is seen by the check.
            self.wake_at.store(n.max(1), Ordering::SeqCst);
            if self.settled() >= n {
                self.wake_at.store(0, Ordering::SeqCst);
                return;
            }
            woken.await;
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::time::Duration;

    #[tokio::test]
    async fn a_waiting_sender_wakes_when_enough_messages_are_settled_and_failures_are_kept() {
        let c = Arc::new(AckCounter::default());
        let waiter = {
            let c = c.clone();
            tokio::spawn(async move { c.settled_at_least(3).await })
        };
        let done = |c: &Arc<AckCounter>| SafeCompletion::Counted(c.clone());
        assert!(done(&c).send(Ok(())).is_ok());
        assert!(done(&c)
            .send(Err(LinkSendError::PeerClosed("a".into())))
            .is_ok());
        assert!(!waiter.is_finished(), "woken before the third");
        assert!(done(&c).send(Err(LinkSendError::Shutdown)).is_ok());
        tokio::time::timeout(Duration::from_secs(5), waiter)
            .await
            .expect("woken within 5 s")
            .expect("waiter task");
        assert_eq!(c.settled(), 3);
        assert_eq!(
            c.failures(),
            (2, Some(LinkSendError::PeerClosed("a".into()))),
            "two failures, the first reason kept"
        );
    }

    #[tokio::test]
    async fn acknowledging_runs_of_counted_messages_settles_each_counter_once_per_message() {
        let (a, b) = (
            Arc::new(AckCounter::default()),
            Arc::new(AckCounter::default()),
        );
        let (tx, rx) = oneshot::channel();
        let counted = |c: &Arc<AckCounter>| SafeCompletion::Counted(c.clone());
        let waiter = {
            let a = a.clone();
            tokio::spawn(async move { a.settled_at_least(5).await })
        };
        let done = vec![
            counted(&a),
            counted(&a),
            SafeCompletion::from(tx),
            counted(&b),
            counted(&a),
            counted(&a),
            counted(&a),
        ];
        acknowledge_all(done);
        assert_eq!((a.settled(), b.settled()), (5, 1));
        assert_eq!(a.failures(), (0, None));
        assert_eq!(rx.await, Ok(Ok(())));
        tokio::time::timeout(Duration::from_secs(5), waiter)
            .await
            .expect("the waiter for 5 woken")
            .expect("waiter task");
        assert_eq!(Arc::strong_count(&a), 1, "no reference left behind");
    }

    #[test]
    fn a_channel_completion_reports_a_receiver_that_is_gone() {
        let (tx, rx) = oneshot::channel();
        drop(rx);
        assert!(SafeCompletion::from(tx).send(Ok(())).is_err());
    }
}
