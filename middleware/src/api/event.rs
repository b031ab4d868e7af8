//! Events: every matched subscriber gets every event exactly once, in publish order; `raise`
//! reports who acknowledged.

use std::future::Future;
use std::marker::PhantomData;
use std::pin::Pin;
use std::sync::atomic::Ordering;
use std::sync::Arc;
use std::task::{Context, Poll};
use std::time::{Duration, Instant};

use tokio::sync::oneshot;

use super::errors::{PublishError, StreamError};
use super::publisher::Publisher;
use super::Payload;
use crate::link::{AckCounter, LinkSendError, Outgoing, SafeCompletion};
use crate::node::mailbox::{Delivery, RawSample};
use crate::node::{lock, RemoteSubscriber};

/// Who got an event.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct RaiseReport {
    /// Subscribers that acknowledged, as `node/service`.
    pub acknowledged: Vec<String>,
    /// Subscribers that did not, with the reason (naming the node).
    pub failed: Vec<(String, String)>,
}

impl RaiseReport {
    /// Whether every matched subscriber acknowledged.
    pub fn all_acknowledged(&self) -> bool {
        self.failed.is_empty()
    }
}

/// One remote node's acknowledgement awaited: its subscribers (`node/service`, shared with the
/// route), its name, and the link's completion. Nothing here is allocated per event but the
/// completion itself.
struct AwaitedAck {
    /// Its index in [`PendingRaise::routes`].
    route: usize,
    done: oneshot::Receiver<Result<(), LinkSendError>>,
}

/// An event on its way; resolves to the [`RaiseReport`] when every subscriber acknowledged
/// or was lost.
pub struct PendingRaise {
    report: RaiseReport,
    waiting: Vec<AwaitedAck>,
    /// The routes the event was sent on (one reference count for all of them).
    routes: Arc<[RemoteSubscriber]>,
}

impl Future for PendingRaise {
    type Output = RaiseReport;

    fn poll(mut self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<RaiseReport> {
        let this = &mut *self;
        let mut i = 0;
        while i < this.waiting.len() {
            match Pin::new(&mut this.waiting[i].done).poll(cx) {
                Poll::Pending => i += 1,
                Poll::Ready(r) => {
                    let route = this.waiting.swap_remove(i).route;
                    let Some(RemoteSubscriber {
                        labels,
                        node_name: node,
                        ..
                    }) = this.routes.get(route)
                    else {
                        continue;
                    };
                    let failure = match r {
                        Ok(Ok(())) => None,
                        Ok(Err(e)) => Some(e.to_string()),
                        Err(_) => Some("link closed".to_owned()),
                    };
                    match failure {
                        None => this.report.acknowledged.extend(labels.iter().cloned()),
                        Some(e) => {
                            let reason = format!("node '{node}' did not acknowledge: {e}");
                            this.report
                                .failed
                                .extend(labels.iter().map(|s| (s.clone(), reason.clone())));
                        }
                    }
                }
            }
        }
        if this.waiting.is_empty() {
            let mut r = std::mem::take(&mut this.report);
            r.acknowledged.sort();
            r.failed.sort();
            Poll::Ready(r)
        } else {
            Poll::Pending
        }
    }
}

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
        Ok(self.raise_encoded(msg, at))
    }

    /// The wire message of `value`, encoded once straight from it, and where its payload
    /// starts (local subscribers get that part).
    fn encode(&self, value: &T) -> Result<(Vec<u8>, usize), PublishError> {
        let offer = &self.publisher.offer;
        crate::codec::encode_data_message(true, offer.id, value).map_err(|source| {
            PublishError::Encode {
                name: offer.name.to_string(),
                source,
            }
        })
    }

    /// Sends the encoded event message `msg` (its payload from `at`) to every subscriber.
    fn raise_encoded(&self, msg: Vec<u8>, at: usize) -> PendingRaise {
        let Publisher { node, offer, .. } = &self.publisher;
        let mut report = RaiseReport::default();
        let me = &node.me.name;
        self.deliver_locally(&msg[at..], |service| {
            report.acknowledged.push(format!("{me}/{service}"))
        });
        let remote = offer.remote.get();
        let mut waiting = Vec::with_capacity(remote.len());
        self.send_on_routes(&remote, msg, |k| {
            let (tx, rx) = oneshot::channel();
            waiting.push(AwaitedAck { route: k, done: rx });
            tx.into()
        });
        PendingRaise {
            report,
            waiting,
            routes: remote,
        }
    }

    /// Sends the encoded event `msg` to the node of each route, settling on the completion
    /// `done(k)` makes for route `k`. A route whose node was dropped since the routes were read
    /// fails at once rather than open a fresh session with its dead address (see `drop_peer`).
    fn send_on_routes(
        &self,
        routes: &[RemoteSubscriber],
        msg: Vec<u8>,
        mut done: impl FnMut(usize) -> SafeCompletion,
    ) {
        let node = &self.publisher.node;
        let mut msg = Some(msg);
        let n = routes.len();
        for (k, r) in routes.iter().enumerate() {
            let done = done(k);
            if !r.alive.load(Ordering::Acquire) {
                let _ = done.send(Err(LinkSendError::PeerClosed(r.node_name.to_string())));
                continue;
            }
            let m = if k + 1 == n { msg.take() } else { msg.clone() };
            node.send_to(
                r.link,
                r.addr,
                Outgoing::Safe {
                    msg: m.unwrap_or_default(),
                    done: Some(done),
                },
            );
        }
    }

    /// Puts `payload` into the mailbox of every subscriber on this node; `delivered` is told
    /// each one's service name.
    fn deliver_locally(&self, payload: &[u8], mut delivered: impl FnMut(&str)) {
        let Publisher { node, offer, .. } = &self.publisher;
        if !offer.has_local.load(Ordering::Acquire) {
            return;
        }
        let local = lock(&offer.local);
        if local.is_empty() {
            return;
        }
        let received = Instant::now();
        for i in local.iter() {
            if let Some(m) = &i.mailbox {
                m.push(Delivery::Sample(RawSample {
                    name: offer.name.clone(),
                    publisher: node.me.name.as_str().into(),
                    type_name: offer.ty.name.as_str().into(),
                    fingerprint: offer.ty.fingerprint,
                    payload: payload.to_vec(),
                    received,
                }));
                delivered(&i.service_name);
            }
        }
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
            routes: Arc::default(),
            routes_version: None,
            peers: Vec::new(),
            leaving: Vec::new(),
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
    /// None today (bytes always encode); the `Result` matches [`Event::raise_nowait`].
    pub fn raise_bytes_nowait(&self, bytes: &[u8]) -> Result<PendingRaise, PublishError> {
        let (msg, at) =
            crate::codec::encode_data_message_from_bytes(true, self.publisher.offer.id, bytes);
        Ok(self.raise_encoded(msg, at))
    }

    /// [`Event::raise`] of borrowed bytes (see [`Event::raise_bytes_nowait`]).
    ///
    /// # Errors
    /// As [`Event::raise_bytes_nowait`].
    pub async fn raise_bytes(&self, bytes: &[u8]) -> Result<RaiseReport, PublishError> {
        Ok(self.raise_bytes_nowait(bytes)?.await)
    }
}

pub use crate::link::{STREAM_WINDOW, STREAM_WINDOW_BYTES};

/// A lossless stream of an [`Event`] (see [`Event::stream`]): every subscriber gets every event
/// exactly once, in order, with back-pressure instead of a report per event. Subscribers that
/// come or go while it runs are followed at the next event.
pub struct EventStream<'a, T> {
    event: &'a Event<T>,
    /// The routes `peers` was made for.
    routes: Arc<[RemoteSubscriber]>,
    /// Their version ([`crate::node::Routes`]; `None` before the first event): while the
    /// offer's stays the same, an event goes on `routes` without taking the offer's lock.
    routes_version: Option<u64>,
    /// One per route, in the routes' order.
    peers: Vec<StreamPeer>,
    /// Nodes no longer subscribed, until their last events are settled (and any loss reported).
    leaving: Vec<StreamPeer>,
}

/// What a stream sent to one subscriber's node, and what came of it.
struct StreamPeer {
    node: crate::protocol::NodeId,
    name: Arc<str>,
    acks: Arc<AckCounter>,
    sent: u64,
    /// Bytes of the events sent.
    bytes: u64,
    /// Failures already reported.
    reported: u64,
    /// Bytes it may have unacknowledged: [`STREAM_WINDOW_BYTES`], or less on a slow link
    /// ([`crate::link::Link::stream_window_bytes`]).
    window_bytes: u64,
}

impl StreamPeer {
    /// Events it may have unacknowledged: [`STREAM_WINDOW`], or fewer for large events or a
    /// slow link.
    fn window(&self) -> u64 {
        let mean = (self.bytes / self.sent.max(1)).max(1);
        crate::link::stream_window(self.window_bytes, mean)
    }
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
        for p in self.peers.iter().chain(&self.leaving) {
            p.acks.settled_at_least(p.sent).await;
        }
        self.report_losses()
    }

    async fn send_encoded(&mut self, msg: Vec<u8>, at: usize) -> Result<(), StreamError> {
        self.event.deliver_locally(&msg[at..], |_| {});
        self.refresh_routes();
        let event = self.event;
        let remote: &[RemoteSubscriber] = &self.routes;
        let len = msg.len() as u64;
        let peers = &mut self.peers;
        event.send_on_routes(remote, msg, |k| {
            // `follow` made `peers` match `remote`, one per route in its order.
            let p = &mut peers[k];
            p.sent += 1;
            p.bytes += len;
            SafeCompletion::Counted(p.acks.clone())
        });
        // A stream that never waits would hold its thread until the window fills: on a
        // current-thread runtime the link could not read an acknowledgement before then.
        // Yielding once in a while (tokio's task budget) keeps acknowledgements, and the
        // datagrams they release, flowing while the stream runs.
        tokio::task::consume_budget().await;
        for p in &self.peers {
            let window = p.window();
            if p.sent - p.acks.settled() > window {
                p.acks.settled_at_least(p.sent - window / 2).await;
            }
        }
        let offer = self.event.publisher.offer.id;
        for r in remote.iter() {
            if r.held.holds(offer) {
                self.wait_caught_up(r, offer).await;
            }
        }
        self.report_losses()
    }

    /// Makes `peers` follow the offer's routes if they changed since the last event.
    fn refresh_routes(&mut self) {
        let changed = self
            .event
            .publisher
            .offer
            .remote
            .changed_since(self.routes_version);
        if let Some((routes, version)) = changed {
            self.routes_version = Some(version);
            self.follow(routes);
        }
    }

    /// Waits while `r`'s node says its subscribers are behind ([`crate::protocol::Message::Flow`]),
    /// until it catches up or leaves.
    async fn wait_caught_up(&self, r: &RemoteSubscriber, offer: u32) {
        let mut changed = self.event.publisher.node.changed.subscribe();
        while r.held.holds(offer) && r.alive.load(Ordering::Acquire) {
            if changed.changed().await.is_err() {
                return;
            }
        }
    }

    /// Makes `peers` match `routes`: a node still subscribed keeps its counts, a new one starts
    /// at zero, one gone waits in `leaving` until its events are settled.
    fn follow(&mut self, routes: Arc<[RemoteSubscriber]>) {
        let mut old = std::mem::take(&mut self.peers);
        let links = self.event.publisher.node.links();
        for r in routes.iter() {
            let window_bytes = links
                .get(r.link)
                .and_then(|l| l.stream_window_bytes())
                .unwrap_or(STREAM_WINDOW_BYTES);
            let p = match old.iter().position(|p| p.node == r.node) {
                Some(i) => StreamPeer {
                    window_bytes,
                    ..old.swap_remove(i)
                },
                None => StreamPeer {
                    node: r.node,
                    name: r.node_name.clone(),
                    acks: Arc::default(),
                    sent: 0,
                    bytes: 0,
                    reported: 0,
                    window_bytes,
                },
            };
            self.peers.push(p);
        }
        self.leaving.extend(old);
        self.routes = routes;
    }

    /// The first node with losses not yet reported, as an error; forgets left nodes whose
    /// events are all settled.
    fn report_losses(&mut self) -> Result<(), StreamError> {
        let mut lost = None;
        for p in self.peers.iter_mut().chain(&mut self.leaving) {
            let (failed, reason) = p.acks.failures();
            if failed > p.reported && lost.is_none() {
                lost = Some(StreamError::Lost {
                    name: self.event.publisher.offer.name.to_string(),
                    node: p.name.to_string(),
                    lost: failed - p.reported,
                    reason: reason.map_or_else(|| "unknown".to_owned(), |e| e.to_string()),
                });
                p.reported = failed;
            }
        }
        if !self.leaving.is_empty() {
            self.leaving
                .retain(|p| p.acks.settled() < p.sent || p.acks.failures().0 > p.reported);
        }
        lost.map_or(Ok(()), Err)
    }
}

impl EventStream<'_, Vec<u8>> {
    /// [`EventStream::send`] of borrowed bytes (see [`Event::raise_bytes_nowait`]).
    ///
    /// # Errors
    /// [`StreamError::Lost`] as [`EventStream::send`].
    pub async fn send_bytes(&mut self, bytes: &[u8]) -> Result<(), StreamError> {
        let (msg, at) = crate::codec::encode_data_message_from_bytes(
            true,
            self.event.publisher.offer.id,
            bytes,
        );
        self.send_encoded(msg, at).await
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn peer(sent: u64, bytes: u64) -> StreamPeer {
        StreamPeer {
            node: 1,
            name: "n".into(),
            acks: Arc::default(),
            sent,
            bytes,
            reported: 0,
            window_bytes: STREAM_WINDOW_BYTES,
        }
    }

    #[test]
    fn the_stream_window_shrinks_for_large_events_down_to_64() {
        assert_eq!(peer(0, 0).window(), STREAM_WINDOW, "nothing sent yet");
        assert_eq!(peer(100, 100 * 16).window(), STREAM_WINDOW, "8 B events");
        assert_eq!(peer(100, 100 * 72).window(), STREAM_WINDOW, "64 B events");
        assert_eq!(peer(100, 100 * 1024).window(), 2048, "1 KiB events");
        assert_eq!(peer(10, 10 << 20).window(), 64, "1 MiB events");
        let radio = StreamPeer {
            window_bytes: 46_080,
            ..peer(100, 100 * 72)
        };
        assert_eq!(
            radio.window(),
            640,
            "64 B events, 4 s of a 115,200 baud line"
        );
    }
}
