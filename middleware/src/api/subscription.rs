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

    /// A delivery if one is waiting.
    pub fn try_recv(&self) -> Option<Result<Sample<T>, RecvError>> {
        self.mailbox.try_pop().map(decode_delivery)
    }

    /// Deliveries waiting.
    pub fn pending(&self) -> usize {
        self.mailbox.len()
    }
}
