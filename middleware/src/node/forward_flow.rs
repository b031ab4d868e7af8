//! Flow control through a gateway: the events a gateway forwards to a node count on a window
//! per node, and while more of them than a stream's window for that node's link are
//! unacknowledged, the gateway counts itself as behind (see [`super::mailbox::Congestion`]):
//! it tells its peers ([`crate::protocol::Message::Flow`]), whose streams wait, until half of
//! them are acknowledged. A LAN stream forwarded onto a radio is so held to the radio's pace
//! instead of queueing at the gateway without bound (and delaying everything else on the
//! radio by as much).
//!
//! A node the gateway forwards events to whose readers are behind (its
//! [`crate::protocol::Message::Flow`] says `readers`: its own, or ones `n` gateways beyond it)
//! holds the gateway back too: the gateway tells its other peers that readers `n + 1` gateways
//! beyond it are behind, so a reader slower than the links is waited for across gateways.
//! A readers' state is never told back to the node it came from (two gateways with events
//! crossing both ways would otherwise hold each other for ever, each behind because the other
//! is), and is passed across at most [`super::gateway::MAX_HOPS`] gateways (a ring of them
//! forgets a reader that caught up within as many `Flow`s).

use std::collections::HashMap;
use std::sync::atomic::{AtomicBool, AtomicU64, AtomicU8, Ordering};
use std::sync::{Arc, Mutex};

use super::gateway::MAX_HOPS;
use super::{NodeInner, RemoteSubscriber};
use crate::link::{stream_window, STREAM_WINDOW_BYTES};
use crate::link::{AckCounter, SafeCompletion};
use crate::protocol::NodeId;
use crate::sync::lock;

/// [`Window::reader_hops`] while the node's readers are not behind.
const NO_READERS_BEHIND: u8 = u8::MAX;

/// The events forwarded to one node and how many of them it acknowledged.
struct Window {
    acks: Arc<AckCounter>,
    sent: AtomicU64,
    /// Over its limit: the gateway counts as behind until half of it is acknowledged.
    behind: AtomicBool,
    /// The node said readers this many gateways beyond it are behind (0: its own), or
    /// [`NO_READERS_BEHIND`]; kept from before the first event forwarded to it, and counted
    /// from then on. Changed, and `sent` first raised, under the table's lock.
    reader_hops: AtomicU8,
}

impl Default for Window {
    fn default() -> Self {
        Window {
            acks: Arc::default(),
            sent: AtomicU64::new(0),
            behind: AtomicBool::new(false),
            reader_hops: AtomicU8::new(NO_READERS_BEHIND),
        }
    }
}

impl Window {
    /// An event was forwarded to the node (its readers' state counts from then on).
    fn forwarded_to(&self) -> bool {
        self.sent.load(Ordering::Acquire) > 0
    }

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
    /// fails what it had; its readers hold nothing back any more.
    pub(super) fn forget_forward_window(&self, windows: &ForwardWindows, node: NodeId) {
        let w = lock(&windows.0).remove(&node);
        if w.is_some_and(|w| w.reader_hops.load(Ordering::Acquire) != NO_READERS_BEHIND) {
            self.congestion.relayed_readers_changed();
        }
    }

    /// `node` says readers `hops` gateways beyond it are behind (0: its own), or that none are
    /// (`None`): if this gateway forwards events to it, its other peers are told; if it has not
    /// yet, they are told when it first does (a node may be behind, fed by others, long before).
    pub(super) fn relay_readers_behind(&self, node: NodeId, hops: Option<u8>) {
        let Some(gw) = &self.gateway else { return };
        let hops = hops.unwrap_or(NO_READERS_BEHIND);
        let mut windows = lock(&gw.windows.0);
        let w = if hops == NO_READERS_BEHIND {
            let Some(w) = windows.get(&node) else {
                return;
            };
            w
        } else {
            windows.entry(node).or_default()
        };
        if w.reader_hops.swap(hops, Ordering::AcqRel) == hops || !w.forwarded_to() {
            return;
        }
        tracing::debug!(peer = node, hops, "readers behind a node forwarded to");
        self.congestion.relayed_readers_changed();
    }

    /// How many gateways beyond this one the nearest readers that are behind are, as told to
    /// `peer`: from the nodes this gateway forwards events to, except `peer` itself, within
    /// [`MAX_HOPS`]. `None` on a node that is no gateway.
    pub(super) fn relayed_readers_behind(&self, peer: NodeId) -> Option<u8> {
        let gw = self.gateway.as_ref()?;
        lock(&gw.windows.0)
            .iter()
            .filter(|(node, w)| **node != peer && w.forwarded_to())
            .map(|(_, w)| w.reader_hops.load(Ordering::Acquire))
            .filter(|&hops| hops != NO_READERS_BEHIND && hops + 1 < MAX_HOPS)
            .min()
            .map(|hops| hops + 1)
    }

    /// The completion of one event of `len` bytes forwarded to `to`'s node, counted on that
    /// node's window; the gateway falls behind when the window is over its limit.
    pub(super) fn forwarded_event_done(
        &self,
        windows: &ForwardWindows,
        to: &RemoteSubscriber,
        len: usize,
    ) -> SafeCompletion {
        let w = {
            let mut table = lock(&windows.0);
            let w = table.entry(to.node).or_default().clone();
            let first = w.sent.fetch_add(1, Ordering::AcqRel) == 0;
            if first && w.reader_hops.load(Ordering::Acquire) != NO_READERS_BEHIND {
                // Its readers were behind before: the other peers are told now.
                self.congestion.relayed_readers_changed();
            }
            w
        };
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
