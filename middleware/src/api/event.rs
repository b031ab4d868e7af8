//! Events: every matched subscriber gets every event exactly once, in publish order; `raise`
//! reports who acknowledged.

use std::marker::PhantomData;
use std::time::Duration;

use super::blob::BlobLoan;
use super::publisher::Publisher;
use super::{Blob, Payload};
pub use crate::link::{STREAM_WINDOW, STREAM_WINDOW_BYTES};
use crate::node::data::PublishError;
use crate::node::events::StreamSender;
pub use crate::node::events::{PendingRaise, RaiseReport, StreamError};

/// Publisher handle of an event. Dropping it withdraws the event.
pub struct Event<T> {
    publisher: Publisher,
    _t: PhantomData<fn(T)>,
}

impl<T: Payload> Event<T> {
    pub(crate) fn new(publisher: Publisher) -> Self {
        Event {
            publisher,
            _t: PhantomData,
        }
    }

    /// Full name.
    pub fn name(&self) -> &str {
        &self.publisher.offer.name
    }

    /// Raises an event and waits until every matched subscriber acknowledged it end to end (or
    /// was lost, which the report names).
    ///
    /// # Errors
    /// [`PublishError::Encode`] when the value cannot be serialised.
    pub async fn raise(&self, value: &T) -> Result<RaiseReport, PublishError> {
        Ok(self.raise_nowait(value)?.await)
    }

    /// Raises an event now and returns a future for its report, so a publisher can keep many
    /// events in flight. Events are delivered in the order of these calls.
    ///
    /// # Errors
    /// [`PublishError::Encode`] when the value cannot be serialised.
    pub fn raise_nowait(&self, value: &T) -> Result<PendingRaise, PublishError> {
        let (msg, at) = self.encode(value)?;
        Ok(self
            .publisher
            .node
            .raise_event(&self.publisher.offer, msg, at))
    }

    /// The wire message of `value`, encoded once straight from it, and where its payload
    /// starts (local subscribers get that part).
    fn encode(&self, value: &T) -> Result<(Vec<u8>, usize), PublishError> {
        let offer = &self.publisher.offer;
        let (msg, at) =
            crate::codec::encode_data_message(true, offer.id, value).map_err(|source| {
                PublishError::Encode {
                    name: offer.name.to_string(),
                    source,
                }
            })?;
        PublishError::check_size(&offer.name, msg.len() - at)?;
        Ok((msg, at))
    }

    /// A lossless stream of this event: [`EventStream::send`] raises events without a report
    /// each, and waits only while a subscriber's node has [`STREAM_WINDOW`] events not yet
    /// acknowledged (back-pressure, never a drop). For a publisher of many events, where
    /// [`Event::raise_nowait`]'s report per event costs more than the event.
    ///
    /// A subscriber's node acknowledges what reached the subscription's mailbox; while a reader
    /// that keeps reading is behind (its mailbox over a quarter full) the node says so and the
    /// stream waits until it is under an eighth, so a slow reader holds the stream back instead
    /// of losing events. A reader that stopped (nothing taken for 200 ms) is not waited for.
    ///
    /// ```no_run
    /// # async fn f(ev: marea::Event<u32>) -> Result<(), marea::StreamError> {
    /// let mut stream = ev.stream();
    /// for i in 0..1_000_000 {
    ///     stream.send(&i).await?;
    /// }
    /// stream.flush().await?; // every subscriber acknowledged every event
    /// # Ok(()) }
    /// ```
    pub fn stream(&self) -> EventStream<'_, T> {
        EventStream {
            event: self,
            sender: StreamSender::default(),
        }
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

impl Event<Vec<u8>> {
    /// [`Event::raise_nowait`] of borrowed bytes: subscribers of `Event<Vec<u8>>` get them as
    /// a `Vec<u8>`, and the publisher needs no owned copy of its buffer (the wire message is
    /// built from the slice in one copy).
    ///
    /// ```no_run
    /// # fn f(ev: marea::Event<Vec<u8>>, frame: &[u8]) -> Result<(), marea::PublishError> {
    /// let pending = ev.raise_bytes_nowait(&frame[4..])?;
    /// # Ok(()) }
    /// ```
    ///
    /// # Errors
    /// [`PublishError::TooLarge`] above [`crate::protocol::MAX_PAYLOAD`] (nothing is sent).
    pub fn raise_bytes_nowait(&self, bytes: &[u8]) -> Result<PendingRaise, PublishError> {
        PublishError::check_size(&self.publisher.offer.name, bytes.len())?;
        let (msg, at) =
            crate::codec::encode_data_message_from_bytes(true, self.publisher.offer.id, bytes);
        Ok(self
            .publisher
            .node
            .raise_event(&self.publisher.offer, msg, at))
    }

    /// [`Event::raise`] of borrowed bytes (see [`Event::raise_bytes_nowait`]).
    ///
    /// # Errors
    /// As [`Event::raise_bytes_nowait`].
    pub async fn raise_bytes(&self, bytes: &[u8]) -> Result<RaiseReport, PublishError> {
        Ok(self.raise_bytes_nowait(bytes)?.await)
    }
}

impl Event<Blob> {
    /// A buffer for an event of `len` bytes, to be written in place and then raised: when the
    /// event's one subscriber is on this host (a shared-memory link), the buffer is a sample of
    /// its inbox, so the bytes are written once, where the subscriber reads them
    /// ([`Blob::is_shared_memory`] there). Otherwise (several subscribers, another link) it is
    /// an ordinary buffer and the event is sent as [`Event::raise`] sends it.
    ///
    /// A camera writes its frame with [`BlobLoan::append`] (or [`std::io::Write`]): each byte
    /// written once. [`BlobLoan::as_mut_slice`] gives the whole buffer, first zeroing what
    /// was not written (a second pass over a large one).
    ///
    /// ```no_run
    /// # fn f(ev: marea::Event<marea::Blob>, frame: &[u8]) -> Result<(), marea::PublishError> {
    /// let mut loan = ev.loan(frame.len())?;
    /// loan.append(frame);
    /// let pending = loan.raise_nowait();
    /// # Ok(()) }
    /// ```
    ///
    /// # Errors
    /// [`PublishError::TooLarge`] above [`crate::protocol::MAX_PAYLOAD`].
    pub fn loan(&self, len: usize) -> Result<EventLoan<'_>, PublishError> {
        BlobLoan::new(self, &self.publisher, true, len)
    }
}

/// An event's bytes being written in place ([`Event::loan`]).
pub type EventLoan<'a> = BlobLoan<'a, Event<Blob>>;

impl EventLoan<'_> {
    /// Raises the event (see [`Event::raise_nowait`]).
    pub fn raise_nowait(self) -> PendingRaise {
        let publisher = &self.handle.publisher;
        publisher
            .node
            .raise_loaned_event(&publisher.offer, self.loan, self.at)
    }

    /// Raises the event and waits for the report (see [`Event::raise`]).
    pub async fn raise(self) -> RaiseReport {
        self.raise_nowait().await
    }
}

/// A lossless stream of an [`Event`] (see [`Event::stream`]): every subscriber gets every event
/// exactly once, in order, with back-pressure instead of a report per event. Subscribers that
/// come or go while it runs are followed at the next event.
pub struct EventStream<'a, T> {
    event: &'a Event<T>,
    sender: StreamSender,
}

impl<T: Payload> EventStream<'_, T> {
    /// Raises `value` to every subscriber. Returns at once unless a subscriber's node has
    /// [`STREAM_WINDOW`] events (or [`STREAM_WINDOW_BYTES`]) unacknowledged; then waits for half
    /// of them.
    ///
    /// # Errors
    /// [`StreamError::Publish`] when the value cannot be encoded (nothing is sent);
    /// [`StreamError::Lost`] when a subscriber's node did not acknowledge earlier events (it left
    /// or was lost): `value` itself was still sent to every subscriber, and the stream goes on.
    pub async fn send(&mut self, value: &T) -> Result<(), StreamError> {
        let (msg, at) = self.event.encode(value)?;
        self.send_encoded(msg, at).await
    }

    /// Waits until every event sent so far is acknowledged by every subscriber (or lost).
    ///
    /// # Errors
    /// [`StreamError::Lost`] naming a subscriber's node that did not acknowledge some.
    pub async fn flush(&mut self) -> Result<(), StreamError> {
        self.sender.flush(&self.event.publisher.offer).await
    }

    async fn send_encoded(&mut self, msg: Vec<u8>, at: usize) -> Result<(), StreamError> {
        let Publisher { node, offer, .. } = &self.event.publisher;
        self.sender.send(node, offer, msg, at).await
    }
}

impl EventStream<'_, Vec<u8>> {
    /// [`EventStream::send`] of borrowed bytes (see [`Event::raise_bytes_nowait`]).
    ///
    /// # Errors
    /// [`StreamError::Lost`] as [`EventStream::send`]; [`StreamError::Publish`] above
    /// [`crate::protocol::MAX_PAYLOAD`] (nothing is sent).
    pub async fn send_bytes(&mut self, bytes: &[u8]) -> Result<(), StreamError> {
        PublishError::check_size(&self.event.publisher.offer.name, bytes.len())?;
        let (msg, at) = crate::codec::encode_data_message_from_bytes(
            true,
            self.event.publisher.offer.id,
            bytes,
        );
        self.send_encoded(msg, at).await
    }
}
