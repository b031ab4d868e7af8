//! Variables: best effort, latest value, late joiners served at once.

use std::marker::PhantomData;
use std::sync::Arc;
use std::time::{Duration, Instant};

use super::errors::{PublishError, RecvError};
use super::service::Declared;
use super::Payload;
use crate::node::mailbox::{Delivery, RawSample};
use crate::node::{lock, LocalOffer, NodeInner};

/// A received value with where it came from.
#[derive(Debug, Clone, PartialEq)]
pub struct Sample<T> {
    /// Full name of the item.
    pub name: String,
    /// Publishing node.
    pub publisher: String,
    /// The value.
    pub value: T,
    /// When it arrived.
    pub received: Instant,
}

pub(crate) fn decode_delivery<T: Payload>(d: Delivery) -> Result<Sample<T>, RecvError> {
    match d {
        Delivery::Refused(m) => Err(RecvError::TypeMismatch(m)),
        Delivery::Sample(RawSample {
            name,
            publisher,
            payload,
            received,
            ..
        }) => match crate::codec::decode_payload::<T>(&payload) {
            Ok(value) => Ok(Sample {
                name: name.to_string(),
                publisher: publisher.to_string(),
                value,
                received,
            }),
            Err(e) => Err(RecvError::Decode {
                name: name.to_string(),
                publisher: publisher.to_string(),
                reason: e.to_string(),
            }),
        },
    }
}

/// Publisher handle of a variable. Dropping it withdraws the variable.
pub struct Variable<T> {
    node: Arc<NodeInner>,
    offer: Arc<LocalOffer>,
    _declared: Declared,
    _t: PhantomData<fn(T)>,
}

impl<T: Payload> Variable<T> {
    pub(crate) fn new(node: Arc<NodeInner>, offer: Arc<LocalOffer>, declared: Declared) -> Self {
        Variable {
            node,
            offer,
            _declared: declared,
            _t: PhantomData,
        }
    }

    /// Full name.
    pub fn name(&self) -> &str {
        &self.offer.name
    }

    /// Publishes a new value. Never blocks: if a previous value for this variable is still
    /// waiting to be sent, it is replaced.
    ///
    /// # Errors
    /// [`PublishError::Encode`] when the value cannot be serialised.
    pub fn set(&self, value: &T) -> Result<(), PublishError> {
        let bytes = crate::codec::encode_payload(value).map_err(|source| PublishError::Encode {
            name: self.offer.name.to_string(),
            source,
        })?;
        self.node.publish_variable(&self.offer, bytes);
        Ok(())
    }

    /// Names of the remote nodes currently subscribed.
    pub fn remote_subscribers(&self) -> Vec<String> {
        lock(&self.offer.remote)
            .iter()
            .map(|r| r.node_name.to_string())
            .collect()
    }

    /// Waits until at least `n` remote nodes subscribe; returns whether they did in time.
    pub async fn wait_remote_subscribers(&self, n: usize, timeout: Duration) -> bool {
        wait_remote(&self.node, &self.offer, n, timeout).await
    }
}

pub(crate) async fn wait_remote(
    node: &Arc<NodeInner>,
    offer: &Arc<LocalOffer>,
    n: usize,
    timeout: Duration,
) -> bool {
    node.wait_for(timeout, || lock(&offer.remote).len() >= n)
        .await
}
