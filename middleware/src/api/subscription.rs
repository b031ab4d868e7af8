//! Subscriptions to variables and events: one handle type, the mailbox behind it decides the
//! delivery (newest value per name for variables, every event in order for events).

use std::marker::PhantomData;
use std::sync::Arc;
use std::time::Duration;

use super::errors::RecvError;
use super::service::Declared;
use super::variable::{decode_delivery, Sample};
use super::Payload;
use crate::node::mailbox::Mailbox;

/// A subscription; dropping it withdraws the interest.
pub struct Subscription<T> {
    mailbox: Arc<Mailbox>,
    _declared: Declared,
    _t: PhantomData<fn() -> T>,
}

/// A subscription running a callback for each delivery ([`crate::Service::subscribe_event_with`],
/// [`crate::Service::subscribe_variable_with`]); dropping it withdraws the interest and the
/// callback runs no more (but for a delivery already under way on another task).
pub struct CallbackSubscription {
    _declared: Declared,
}

impl CallbackSubscription {
    pub(crate) fn new(declared: Declared) -> Self {
        CallbackSubscription {
            _declared: declared,
        }
    }
}

/// Subscriber of variables: holds the newest undelivered value of each matching name.
pub type VariableSubscriber<T> = Subscription<T>;
/// Subscriber of events: every event, in publish order per publisher.
pub type EventSubscriber<T> = Subscription<T>;

impl<T: Payload> Subscription<T> {
    pub(crate) fn new(mailbox: Arc<Mailbox>, declared: Declared) -> Self {
        Subscription {
            mailbox,
            _declared: declared,
            _t: PhantomData,
        }
    }

    /// The next delivery.
    ///
    /// # Errors
    /// [`RecvError::TypeMismatch`] when a matching publisher has another type,
    /// [`RecvError::Decode`] for an undecodable value, [`RecvError::Closed`] at shutdown.
    pub async fn recv(&self) -> Result<Sample<T>, RecvError> {
        match self.mailbox.pop().await {
            Some(d) => decode_delivery(d),
            None => Err(RecvError::Closed),
        }
    }

    /// Like [`Subscription::recv`] with a time limit.
    ///
    /// # Errors
    /// As `recv`, plus [`RecvError::Timeout`].
    pub async fn recv_timeout(&self, timeout: Duration) -> Result<Sample<T>, RecvError> {
        match tokio::time::timeout(timeout, self.recv()).await {
            Ok(r) => r,
            Err(_) => Err(RecvError::Timeout(timeout)),
        }
    }

    /// A delivery if one is waiting; never blocks, needs no async runtime.
    ///
    /// ```no_run
    /// # fn f(sub: marea::EventSubscriber<u64>) -> Result<(), marea::RecvError> {
    /// while let Some(sample) = sub.try_recv() {
    ///     let s = sample?;
    ///     println!("{} from {}: {}", s.name, s.publisher, s.value);
    /// }
    /// # Ok(()) }
    /// ```
    pub fn try_recv(&self) -> Option<Result<Sample<T>, RecvError>> {
        self.mailbox.try_pop().map(decode_delivery)
    }

    /// The next delivery, blocking the calling thread until it comes: for a plain thread
    /// without an async runtime (the node itself runs on one elsewhere). Calling it from a
    /// task of a runtime blocks that runtime's worker; use [`Subscription::recv`] there.
    ///
    /// ```no_run
    /// # fn f(node: &marea::Node) -> Result<(), Box<dyn std::error::Error>> {
    /// // `node` was opened on a runtime running on another thread.
    /// let sub = node.service("log")?.subscribe_event::<String>("**/alarm")?;
    /// std::thread::spawn(move || {
    ///     while let Ok(s) = sub.recv_blocking() {
    ///         println!("{} from {}: {}", s.name, s.publisher, s.value);
    ///     }
    /// });
    /// # Ok(()) }
    /// ```
    ///
    /// # Errors
    /// As [`Subscription::recv`].
    pub fn recv_blocking(&self) -> Result<Sample<T>, RecvError> {
        match block_on(self.mailbox.pop(), None) {
            Some(Some(d)) => decode_delivery(d),
            _ => Err(RecvError::Closed),
        }
    }

    /// Like [`Subscription::recv_blocking`] with a time limit.
    ///
    /// # Errors
    /// As `recv_blocking`, plus [`RecvError::Timeout`].
    pub fn recv_blocking_timeout(&self, timeout: Duration) -> Result<Sample<T>, RecvError> {
        match block_on(self.mailbox.pop(), Some(timeout)) {
            Some(Some(d)) => decode_delivery(d),
            Some(None) => Err(RecvError::Closed),
            None => Err(RecvError::Timeout(timeout)),
        }
    }

    /// Deliveries waiting.
    pub fn pending(&self) -> usize {
        self.mailbox.len()
    }
}

/// Wakes a parked thread.
struct ThreadWaker(std::thread::Thread);

impl std::task::Wake for ThreadWaker {
    fn wake(self: Arc<Self>) {
        self.0.unpark();
    }

    fn wake_by_ref(self: &Arc<Self>) {
        self.0.unpark();
    }
}

/// Runs `fut` on the calling thread, parking it between polls; `None` when `timeout` passed
/// first. The mailbox's future needs no reactor (only a waker), so no runtime is involved.
fn block_on<F: std::future::Future>(fut: F, timeout: Option<Duration>) -> Option<F::Output> {
    let deadline = timeout.map(|t| std::time::Instant::now() + t);
    let waker = std::task::Waker::from(Arc::new(ThreadWaker(std::thread::current())));
    let mut cx = std::task::Context::from_waker(&waker);
    let mut fut = std::pin::pin!(fut);
    loop {
        if let std::task::Poll::Ready(v) = fut.as_mut().poll(&mut cx) {
            return Some(v);
        }
        // A wake-up between the poll and the park leaves the token set: park returns at once.
        match deadline {
            None => std::thread::park(),
            Some(d) => {
                let left = d.saturating_duration_since(std::time::Instant::now());
                if left.is_zero() {
                    return None;
                }
                std::thread::park_timeout(left);
            }
        }
    }
}
