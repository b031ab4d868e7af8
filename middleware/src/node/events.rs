//! Events: raising one (every local subscriber's mailbox, and every remote subscriber's node
//! on the safe class, acknowledged end to end) and a lossless stream of them with back-pressure
//! per subscriber's node. Received events take the data path of `data`.

use std::future::Future;
use std::pin::Pin;
use std::sync::atomic::Ordering;
use std::sync::Arc;
use std::task::{Context, Poll};
use std::time::Instant;

use tokio::sync::oneshot;

use super::data::PublishError;
use super::loans::MessageLoan;
use super::{lock, LocalOffer, NodeInner, RemoteSubscriber};
use crate::link::{AckCounter, LinkSendError, Outgoing, SafeCompletion, STREAM_WINDOW_BYTES};

/// Who got an event: every subscriber that acknowledged it, and every one that did not with
/// the reason. Built without a copy of any name: the names are made when asked for (a
/// publisher keeping thousands of events in flight pays for none it does not read).
#[derive(Clone)]
pub struct RaiseReport {
    /// Subscribers on this node (`node/service`): they have it once raised.
    local: Vec<String>,
    /// The remote subscribers' nodes the event was sent to.
    routes: Arc<[RemoteSubscriber]>,
    /// Routes whose node did not acknowledge, with the reason.
    failures: Vec<(usize, String)>,
}

impl Default for RaiseReport {
    fn default() -> Self {
        RaiseReport {
            local: Vec::new(),
            routes: Arc::from([]),
            failures: Vec::new(),
        }
    }
}

impl RaiseReport {
    /// Whether every matched subscriber acknowledged.
    pub fn all_acknowledged(&self) -> bool {
        self.failures.is_empty()
    }

    /// Subscribers that acknowledged, as `node/service`, sorted.
    pub fn acknowledged(&self) -> Vec<String> {
        let mut names = self.local.clone();
        for (k, r) in self.routes.iter().enumerate() {
            if !self.failures.iter().any(|(f, _)| *f == k) {
                names.extend(r.labels.iter().cloned());
            }
        }
        names.sort();
        names
    }

    /// Subscribers that did not acknowledge, with the reason (naming the node), sorted.
    pub fn failed(&self) -> Vec<(String, String)> {
        let mut failed: Vec<(String, String)> = Vec::new();
        for (k, reason) in &self.failures {
            if let Some(r) = self.routes.get(*k) {
                let reason = format!("node '{}' did not acknowledge: {reason}", r.node_name);
                failed.extend(r.labels.iter().map(|s| (s.clone(), reason.clone())));
            }
        }
        failed.sort();
        failed
    }
}

impl std::fmt::Debug for RaiseReport {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("RaiseReport")
            .field("acknowledged", &self.acknowledged())
            .field("failed", &self.failed())
            .finish()
    }
}

impl PartialEq for RaiseReport {
    fn eq(&self, other: &Self) -> bool {
        self.acknowledged() == other.acknowledged() && self.failed() == other.failed()
    }
}

impl Eq for RaiseReport {}

/// One remote node's acknowledgement awaited: the index of its route, and the link's
/// completion.
struct AwaitedAck {
    route: usize,
    done: oneshot::Receiver<Result<(), LinkSendError>>,
}

/// An event on its way; resolves to the [`RaiseReport`] when every subscriber acknowledged
/// or was lost.
pub struct PendingRaise {
    report: RaiseReport,
    /// The acknowledgements still awaited: the first in place (an event has one subscriber's
    /// node in the common case, and then needs no list), the others in `more`.
    first: Option<AwaitedAck>,
    more: Vec<AwaitedAck>,
}

impl PendingRaise {
    /// Polls one awaited acknowledgement: `true` once settled (a failure noted in the report).
    fn settled(report: &mut RaiseReport, ack: &mut AwaitedAck, cx: &mut Context<'_>) -> bool {
        let r = match Pin::new(&mut ack.done).poll(cx) {
            Poll::Pending => return false,
            Poll::Ready(r) => r,
        };
        let failure = match r {
            Ok(Ok(())) => None,
            Ok(Err(e)) => Some(e.to_string()),
            Err(_) => Some("link closed".to_owned()),
        };
        if let Some(e) = failure {
            report.failures.push((ack.route, e));
        }
        true
    }
}

impl Future for PendingRaise {
    type Output = RaiseReport;

    fn poll(mut self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<RaiseReport> {
        let this = &mut *self;
        if let Some(ack) = &mut this.first {
            if Self::settled(&mut this.report, ack, cx) {
                this.first = None;
            }
        }
        let mut i = 0;
        while i < this.more.len() {
            if Self::settled(&mut this.report, &mut this.more[i], cx) {
                this.more.swap_remove(i);
            } else {
                i += 1;
            }
        }
        if this.first.is_none() && this.more.is_empty() {
            Poll::Ready(std::mem::take(&mut this.report))
        } else {
            Poll::Pending
        }
    }
}

/// Why an [`crate::EventStream`] reports a problem.
#[derive(Debug, thiserror::Error)]
pub enum StreamError {
    /// The value could not be encoded (nothing was sent).
    #[error(transparent)]
    Publish(#[from] PublishError),
    /// Events sent to a subscriber's node were not acknowledged: it left, was lost or reset
    /// its session. Events to the other subscribers are unaffected.
    #[error("event stream '{name}': node '{node}' did not acknowledge {lost} event(s): {reason}")]
    Lost {
        /// Item name.
        name: String,
        /// The subscriber's node.
        node: String,
        /// How many events it did not acknowledge (since the last report).
        lost: u64,
        /// Why (the first reason).
        reason: String,
    },
}

impl NodeInner {
    /// Raises the encoded event message `msg` of `offer` (its payload from `at`): into every
    /// local subscriber's mailbox, and to every remote one's node, acknowledged end to end.
    pub fn raise_event(&self, offer: &LocalOffer, msg: Vec<u8>, at: usize) -> PendingRaise {
        let mut local = Vec::new();
        let me = &self.me.name;
        self.deliver_event_locally(offer, &msg[at..], |service| {
            local.push(format!("{me}/{service}"))
        });
        let routes = offer.remote.get();
        let (mut first, mut more) = (None, Vec::new());
        self.send_event(&routes, msg, |k| {
            let (tx, rx) = oneshot::channel();
            let ack = AwaitedAck { route: k, done: rx };
            if first.is_none() {
                first = Some(ack);
            } else {
                more.push(ack);
            }
            tx.into()
        });
        PendingRaise {
            report: RaiseReport {
                local,
                routes,
                failures: Vec::new(),
            },
            first,
            more,
        }
    }

    /// Raises the event message written in `loan` (its payload from `at`), as
    /// [`Self::raise_event`] does; when the link of the offer's only subscriber lent the
    /// buffer, the message goes to it without a copy (local subscribers get theirs).
    pub fn raise_loaned_event(
        &self,
        offer: &LocalOffer,
        loan: MessageLoan,
        at: usize,
    ) -> PendingRaise {
        let routes = offer.remote.get();
        let Some(path) = loan.path_among(&routes) else {
            // The subscribers changed since the loan: the message goes as any other.
            return self.raise_event(offer, loan.into_vec(), at);
        };
        let mut buf = loan.buf;
        let mut local = Vec::new();
        let me = &self.me.name;
        self.deliver_event_locally(offer, &buf.init()[at..], |service| {
            local.push(format!("{me}/{service}"))
        });
        let (tx, rx) = oneshot::channel();
        self.send_loan(path, buf, Some(tx.into()));
        PendingRaise {
            report: RaiseReport {
                local,
                routes,
                failures: Vec::new(),
            },
            first: Some(AwaitedAck { route: 0, done: rx }),
            more: Vec::new(),
        }
    }

    /// Sends the encoded event `msg` to the node of each route, settling on the completion
    /// `done(k)` makes for route `k`. A route whose node was dropped since the routes were read
    /// fails at once rather than open a fresh session with its dead address (see `drop_peer`).
    fn send_event(
        &self,
        routes: &[RemoteSubscriber],
        msg: Vec<u8>,
        mut done: impl FnMut(usize) -> SafeCompletion,
    ) {
        // One buffer for every route: each link holds it until its peer acknowledges.
        let msgs = super::per_route(msg, routes.len());
        for ((k, r), msg) in routes.iter().enumerate().zip(msgs) {
            let done = done(k);
            if !r.alive.load(Ordering::Acquire) {
                let _ = done.send(Err(LinkSendError::PeerClosed(r.node_name.to_string())));
                continue;
            }
            let done = Some(done);
            self.send_to(r.link, r.addr, Outgoing::Safe { msg, done });
        }
    }

    /// Puts `payload`, an event of `offer`, into the mailbox of every subscriber on this node;
    /// `delivered` is told each one's service name.
    fn deliver_event_locally(
        &self,
        offer: &LocalOffer,
        payload: &[u8],
        mut delivered: impl FnMut(&str),
    ) {
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
                m.push(offer.own_sample(&self.me.name, payload.to_vec(), received));
                delivered(&i.service_name);
            }
        }
    }
}

/// What a lossless event stream ([`crate::EventStream`]) keeps: per subscriber's node, the
/// events sent and acknowledged, so it waits only when one is a window behind. Subscribers that
/// come or go while it runs are followed at the next event.
#[derive(Default)]
pub(crate) struct StreamSender {
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
    /// Events it may have unacknowledged: [`crate::link::STREAM_WINDOW`], or fewer for large events or a
    /// slow link.
    fn window(&self) -> u64 {
        let mean = (self.bytes / self.sent.max(1)).max(1);
        crate::link::stream_window(self.window_bytes, mean)
    }
}

impl StreamSender {
    /// Raises the encoded event message `msg` of `offer` (its payload from `at`) to every
    /// subscriber; waits while a subscriber's node is a window behind or says its readers are.
    pub async fn send(
        &mut self,
        node: &NodeInner,
        offer: &LocalOffer,
        msg: Vec<u8>,
        at: usize,
    ) -> Result<(), StreamError> {
        node.deliver_event_locally(offer, &msg[at..], |_| {});
        self.refresh_routes(node, offer);
        let remote: &[RemoteSubscriber] = &self.routes;
        let len = msg.len() as u64;
        let peers = &mut self.peers;
        node.send_event(remote, msg, |k| {
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
        for r in remote.iter() {
            if r.held.holds(offer.id) {
                wait_caught_up(node, r, offer.id).await;
            }
        }
        self.report_losses(offer)
    }

    /// Waits until every event sent so far is acknowledged by every subscriber (or lost).
    pub async fn flush(&mut self, offer: &LocalOffer) -> Result<(), StreamError> {
        for p in self.peers.iter().chain(&self.leaving) {
            p.acks.settled_at_least(p.sent).await;
        }
        self.report_losses(offer)
    }

    /// Makes `peers` follow the offer's routes if they changed since the last event.
    fn refresh_routes(&mut self, node: &NodeInner, offer: &LocalOffer) {
        if let Some((routes, version)) = offer.remote.changed_since(self.routes_version) {
            self.routes_version = Some(version);
            self.follow(node, routes);
        }
    }

    /// Makes `peers` match `routes`: a node still subscribed keeps its counts, a new one starts
    /// at zero, one gone waits in `leaving` until its events are settled.
    fn follow(&mut self, node: &NodeInner, routes: Arc<[RemoteSubscriber]>) {
        let mut old = std::mem::take(&mut self.peers);
        let links = node.links();
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
    fn report_losses(&mut self, offer: &LocalOffer) -> Result<(), StreamError> {
        let mut lost = None;
        for p in self.peers.iter_mut().chain(&mut self.leaving) {
            let (failed, reason) = p.acks.failures();
            if failed > p.reported && lost.is_none() {
                lost = Some(StreamError::Lost {
                    name: offer.name.to_string(),
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

/// Waits while `r`'s node says its subscribers are behind ([`crate::protocol::Message::Flow`]),
/// until it catches up or leaves.
async fn wait_caught_up(node: &NodeInner, r: &RemoteSubscriber, offer: u32) {
    let mut changed = node.changed.subscribe();
    while r.held.holds(offer) && r.alive.load(Ordering::Acquire) {
        if changed.changed().await.is_err() {
            return;
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::link::STREAM_WINDOW;

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
