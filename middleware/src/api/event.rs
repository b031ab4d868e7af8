//! Events: every matched subscriber gets every event exactly once, in publish order; `raise`
//! reports who acknowledged.

use std::future::Future;
use std::marker::PhantomData;
use std::pin::Pin;
use std::sync::Arc;
use std::task::{Context, Poll};
use std::time::{Duration, Instant};

use tokio::sync::oneshot;

use super::errors::PublishError;
use super::publisher::Publisher;
use super::Payload;
use crate::link::{LinkSendError, Outgoing};
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
        let offer = &self.publisher.offer;
        // The wire message is encoded once, straight from the value; local subscribers get
        // the payload part of it.
        let (msg, at) =
            crate::codec::encode_data_message(true, offer.id, value).map_err(|source| {
                PublishError::Encode {
                    name: offer.name.to_string(),
                    source,
                }
            })?;
        Ok(self.raise_encoded(msg, at))
    }

    /// Sends the encoded event message `msg` (its payload from `at`) to every subscriber.
    fn raise_encoded(&self, msg: Vec<u8>, at: usize) -> PendingRaise {
        let Publisher { node, offer, .. } = &self.publisher;
        let mut report = RaiseReport::default();
        {
            let local = lock(&offer.local);
            if !local.is_empty() {
                let me = &node.me.name;
                let received = Instant::now();
                for i in local.iter() {
                    if let Some(m) = &i.mailbox {
                        m.push(Delivery::Sample(RawSample {
                            name: offer.name.clone(),
                            publisher: me.as_str().into(),
                            type_name: offer.ty.name.as_str().into(),
                            payload: msg[at..].to_vec(),
                            received,
                        }));
                        report.acknowledged.push(format!("{me}/{}", i.service_name));
                    }
                }
            }
        }
        let remote = lock(&offer.remote).clone();
        let mut waiting = Vec::with_capacity(remote.len());
        let mut msg = Some(msg);
        let n = remote.len();
        for (k, r) in remote.iter().enumerate() {
            let (tx, rx) = oneshot::channel();
            // A subscriber whose node was dropped since the routes were read: fail now rather
            // than open a fresh session with its dead address (see `drop_peer`).
            if !r.alive.load(std::sync::atomic::Ordering::Acquire) {
                let _ = tx.send(Err(LinkSendError::PeerClosed(r.node_name.to_string())));
            } else {
                let m = if k + 1 == n { msg.take() } else { msg.clone() };
                node.send_to(
                    r.link,
                    r.addr,
                    Outgoing::Safe {
                        msg: m.unwrap_or_default(),
                        done: Some(tx),
                    },
                );
            }
            waiting.push(AwaitedAck { route: k, done: rx });
        }
        PendingRaise {
            report,
            waiting,
            routes: remote,
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
