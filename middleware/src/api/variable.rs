//! Variables: best effort, latest value, late joiners served at once.

use std::marker::PhantomData;
use std::time::{Duration, Instant};

use super::blob::BlobLoan;
use super::errors::RecvError;
use super::publisher::Publisher;
use super::Blob;
use super::Payload;
use super::SharedStr;
use crate::node::data::PublishError;
use crate::node::mailbox::{Delivery, RawSample};

/// A received value with where it came from.
///
/// The names are shared with the route the value came by ([`SharedStr`] compares, prints and
/// derefs like a `&str`): receiving allocates nothing per sample for them.
#[derive(Debug, Clone, PartialEq)]
pub struct Sample<T> {
    /// Full name of the item.
    pub name: SharedStr,
    /// Publishing node.
    pub publisher: SharedStr,
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
        }) => match super::blob::decode_payload::<T>(payload.bytes, payload.lent) {
            Ok(value) => Ok(Sample {
                name: name.into(),
                publisher: publisher.into(),
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
    publisher: Publisher,
    _t: PhantomData<fn(T)>,
}

impl<T: Payload> Variable<T> {
    pub(crate) fn new(publisher: Publisher) -> Self {
        Variable {
            publisher,
            _t: PhantomData,
        }
    }

    /// Full name.
    pub fn name(&self) -> &str {
        &self.publisher.offer.name
    }

    /// Publishes a new value. Never blocks: if a previous value for this variable is still
    /// waiting to be sent, it is replaced.
    ///
    /// # Errors
    /// [`PublishError::Encode`] when the value cannot be serialised.
    pub fn set(&self, value: &T) -> Result<(), PublishError> {
        let bytes = self.publisher.encode(value)?;
        let Publisher { node, offer, .. } = &self.publisher;
        node.publish_variable(offer, bytes);
        Ok(())
    }

    /// Names of the remote nodes currently subscribed.
    pub fn remote_subscribers(&self) -> Vec<String> {
        self.publisher.remote_subscribers()
    }

    /// Waits until at least `n` remote nodes subscribe; returns whether they did in time.
    pub async fn wait_remote_subscribers(&self, n: usize, timeout: Duration) -> bool {
        self.publisher.wait_remote_subscribers(n, timeout).await
    }
}

impl Variable<Blob> {
    /// A buffer for a value of `len` bytes, to be written in place and then set: as
    /// [`crate::Event::loan`] (the buffer is the one subscriber's shared memory when it is on
    /// this host), except that the publisher keeps a copy of the value for late joiners, and
    /// a value written in place goes reliably (a copy goes as [`Variable::set`] sends it).
    ///
    /// # Errors
    /// [`PublishError::TooLarge`] above [`crate::protocol::MAX_PAYLOAD`].
    pub fn loan(&self, len: usize) -> Result<VariableLoan<'_>, PublishError> {
        BlobLoan::new(self, &self.publisher, false, len)
    }
}

/// A variable's bytes being written in place ([`Variable::loan`]).
pub type VariableLoan<'a> = BlobLoan<'a, Variable<Blob>>;

impl VariableLoan<'_> {
    /// Publishes the value (see [`Variable::set`]).
    pub fn set(self) {
        let Publisher { node, offer, .. } = &self.handle.publisher;
        node.publish_loaned_variable(offer, self.loan, self.at);
    }
}

impl Variable<Vec<u8>> {
    /// [`Variable::set`] from borrowed bytes: subscribers of `Variable<Vec<u8>>` get them as a
    /// `Vec<u8>`, and the publisher needs no owned copy of its buffer.
    ///
    /// ```no_run
    /// # fn f(var: marea::Variable<Vec<u8>>, frame: &[u8]) -> Result<(), marea::PublishError> {
    /// var.set_bytes(&frame[..64])?;
    /// # Ok(()) }
    /// ```
    ///
    /// # Errors
    /// [`PublishError::TooLarge`] above [`crate::protocol::MAX_PAYLOAD`] (nothing is sent).
    pub fn set_bytes(&self, bytes: &[u8]) -> Result<(), PublishError> {
        let Publisher { node, offer, .. } = &self.publisher;
        PublishError::check_size(&offer.name, bytes.len())?;
        node.publish_variable(offer, crate::codec::encode_bytes_payload(bytes));
        Ok(())
    }
}
