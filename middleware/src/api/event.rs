//! Events: every matched subscriber gets every event exactly once, in publish order; `raise`
//! reports who acknowledged.

use std::marker::PhantomData;
use std::time::Duration;

use super::publisher::Publisher;
use super::{Blob, Payload};
pub use crate::link::{STREAM_WINDOW, STREAM_WINDOW_BYTES};
use crate::node::data::PublishError;
use crate::node::events::StreamSender;
pub use crate::node::events::{PendingRaise, RaiseReport, StreamError};
use crate::node::loans::MessageLoan;

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
    pub fn loan(&self, len: usize) -> Result<BlobLoan<'_>, PublishError> {
        let offer = &self.publisher.offer;
        PublishError::check_size(&offer.name, len)?;
        let (header, at) = crate::codec::data_message_header_of_bytes(true, offer.id, len);
        let routes = offer.remote.get();
        let mut loan = self.publisher.node.loan(&routes, header.len() + len);
        loan.buf.append(&header);
        Ok(BlobLoan {
            event: self,
            loan,
            at,
            start: header.len(),
        })
    }
}

/// An event's bytes being written in place ([`Event::loan`]); raised by
/// [`BlobLoan::raise_nowait`] or [`BlobLoan::raise`], dropped without being sent otherwise.
/// What was not written when it is raised is sent as zeros.
pub struct BlobLoan<'a> {
    event: &'a Event<Blob>,
    loan: MessageLoan,
    /// Where the event's payload starts in the message.
    at: usize,
    /// Where the bytes start in the message.
    start: usize,
}

impl BlobLoan<'_> {
    /// The event's length in bytes.
    pub fn len(&self) -> usize {
        self.loan.buf.len() - self.start
    }

    /// Whether the event is empty.
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// Bytes written from the start so far.
    pub fn written(&self) -> usize {
        self.loan.buf.written() - self.start
    }

    /// Writes as much of `bytes` as fits after what was written (each byte once); returns
    /// how much.
    pub fn append(&mut self, bytes: &[u8]) -> usize {
        self.loan.buf.append(bytes)
    }

    /// The whole event's bytes, to write anywhere in them; the first call zeroes those not
    /// written yet.
    pub fn as_mut_slice(&mut self) -> &mut [u8] {
        let start = self.start;
        &mut self.loan.buf.init()[start..]
    }

    /// Whether the bytes are being written into the subscriber's shared memory.
    pub fn is_shared_memory(&self) -> bool {
        self.loan.is_lent()
    }

    /// Raises the event (see [`Event::raise_nowait`]).
    pub fn raise_nowait(self) -> PendingRaise {
        let publisher = &self.event.publisher;
        publisher
            .node
            .raise_loaned_event(&publisher.offer, self.loan, self.at)
    }

    /// Raises the event and waits for the report (see [`Event::raise`]).
    pub async fn raise(self) -> RaiseReport {
        self.raise_nowait().await
    }
}

impl std::io::Write for BlobLoan<'_> {
    /// Appends (see [`BlobLoan::append`]); a full buffer takes nothing (`write_all` then fails
    /// with [`std::io::ErrorKind::WriteZero`]).
    fn write(&mut self, buf: &[u8]) -> std::io::Result<usize> {
        Ok(self.append(buf))
    }

    fn flush(&mut self) -> std::io::Result<()> {
        Ok(())
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
