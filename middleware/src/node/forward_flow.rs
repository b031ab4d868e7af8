//! Flow control through a gateway: the events a gateway forwards to a node count on a window
//! per node, and while more of them than a stream's window for that node's link are
//! unacknowledged, the gateway counts itself as behind (see [`super::mailbox::Congestion`]):
//! it tells its peers ([`crate::protocol::Message::Flow`]), whose streams wait, until half of
//! them are acknowledged. A LAN stream forwarded onto a radio is so held to the radio's pace
//! instead of queueing at the gateway without bound (and delaying everything else on the
//! radio by as much).
//!
//! A node the gateway forwards events to whose own readers are behind (its
//! [`crate::protocol::Message::Flow`] says `readers`) holds the gateway back the same way, so a
//! reader slower than the links behind a gateway is waited for too. Only a reader's `Flow` is
//! passed on, never one that is there because of forwarding: two gateways passing each
//! other's on would hold each other for ever when events cross both ways. (So a reader two
//! gateways away is not waited for: the nearer gateway's `Flow` does not say `readers`.)

use std::collections::HashMap;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Arc, Mutex};

use super::{NodeInner, RemoteSubscriber};
use crate::link::{stream_window, STREAM_WINDOW_BYTES};
use crate::link::{AckCounter, SafeCompletion};
use crate::protocol::NodeId;
use crate::sync::lock;

/// The events forwarded to one node and how many of them it acknowledged.
#[derive(Default)]
struct Window {
    acks: Arc<AckCounter>,
    sent: AtomicU64,
    /// Over its limit: the gateway counts as behind until half of it is acknowledged.
    behind: AtomicBool,
    /// The node said its readers are behind: the gateway counts as behind until they catch up.
    readers_behind: AtomicBool,
}

impl Window {
    fn in_flight(&self) -> u64 {
        self.sent
            .load(Ordering::Acquire)
            .saturating_sub(self.acks.settled())
    }
}

/// A gateway's windows, by the node forwarded to.
#[derive(Default)]
pub(crate) struct ForwardWindows(Mutex<HashMap<NodeId, Arc<Window>>>);

impl NodeInner {
    /// Forgets `node`'s window (it left): a wait for its acknowledgements ends as its link
    /// fails what it had, one for its readers ends here.
    pub(super) fn forget_forward_window(&self, windows: &ForwardWindows, node: NodeId) {
        let mut table = lock(&windows.0);
        let w = table.remove(&node);
        if w.is_some_and(|w| w.readers_behind.swap(false, Ordering::AcqRel)) {
            self.congestion.forwarding_caught_up();
        }
    }

    /// `node` says its readers are behind, or not (any more): if this gateway forwards events
    /// to it, it counts as behind itself until they catch up.
    pub(super) fn relay_readers_behind(&self, node: NodeId, behind: bool) {
        let Some(gw) = &self.gateway else { return };
        // Under the table's lock, as in `forget_forward_window`: a window forgotten meanwhile
        // is never left counted.
        let windows = lock(&gw.windows.0);
        let Some(w) = windows.get(&node) else {
            return;
        };
        if w.readers_behind.swap(behind, Ordering::AcqRel) == behind {
            return;
        }
        tracing::debug!(peer = node, behind, "readers of a node forwarded to");
        if behind {
            self.congestion.forwarding_fell_behind();
        } else {
            self.congestion.forwarding_caught_up();
        }
    }

    /// The completion of one event of `len` bytes forwarded to `to`'s node, counted on that
    /// node's window; the gateway falls behind when the window is over its limit.
    pub(super) fn forwarded_event_done(
        &self,
        windows: &ForwardWindows,
        to: &RemoteSubscriber,
        len: usize,
    ) -> SafeCompletion {
        let w = lock(&windows.0).entry(to.node).or_default().clone();
        w.sent.fetch_add(1, Ordering::AcqRel);
        let limit = self.forward_limit(to.link, len);
        if w.in_flight() > limit && !w.behind.swap(true, Ordering::AcqRel) {
            tracing::debug!(peer = %to.node_name, limit, "forwarded events to a node fell behind");
            self.congestion.forwarding_fell_behind();
            let (congestion, cancel, window) =
                (self.congestion.clone(), self.cancel.clone(), w.clone());
            crate::sync::spawn_tracked(&self.tasks, async move {
                // Until at most half the limit is in flight (more may be sent meanwhile).
                while window.in_flight() > limit / 2 {
                    let target = window
                        .sent
                        .load(Ordering::Acquire)
                        .saturating_sub(limit / 2);
                    tokio::select! {
                        _ = cancel.cancelled() => break,
                        _ = window.acks.settled_at_least(target) => {}
                    }
                }
                window.behind.store(false, Ordering::Release);
                congestion.forwarding_caught_up();
            });
        }
        SafeCompletion::Counted(w.acks.clone())
    }

    /// Events a gateway may have unacknowledged to a node on `link`: what a stream may (see
    /// [`crate::link::Link::stream_window_bytes`]), counted in events of `len` bytes.
    fn forward_limit(&self, link: usize, len: usize) -> u64 {
        let bytes = self
            .links()
            .get(link)
            .and_then(|l| l.stream_window_bytes())
            .unwrap_or(STREAM_WINDOW_BYTES);
        stream_window(bytes, len as u64)
    }
}
