//! Flow control for lossless streams across every kind of link: a node whose event subscribers
//! fall behind while still reading (see [`super::mailbox::Congestion`]) tells its peers
//! ([`Message::Flow`]), and their [`crate::EventStream`]s wait until it says it caught up,
//! instead of its mailboxes dropping events. Each peer is told which of its offers feed the
//! mailboxes that are behind, and only their streams wait (a gateway holding streams back for
//! its links or for readers beyond it holds all of them). Links acknowledge what reached a
//! mailbox, so a stream's window alone cannot hold a publisher back for a slow reader. A gateway is behind
//! too while the events it forwards wait for a slower link or for a node whose readers are
//! behind (see [`super::forward_flow`]).

use std::collections::HashMap;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};
use std::time::Duration;

use super::{lock, NodeInner};
use crate::protocol::{Message, NodeId};

/// What a peer's last [`Message::Flow`] holds back of this node's streams to it: nothing, all
/// of them, or those of some offers (the ones its subscribers that are behind read).
#[derive(Default)]
pub(crate) struct StreamHold {
    behind: AtomicBool,
    /// While behind: the offers held, or `None` for all.
    offers: Mutex<Option<Arc<[u32]>>>,
}

impl StreamHold {
    /// Whether streams of our offer `offer` to the peer wait (one atomic load while the peer
    /// is not behind).
    pub(crate) fn holds(&self, offer: u32) -> bool {
        self.behind.load(Ordering::Acquire)
            && lock(&self.offers)
                .as_ref()
                .is_none_or(|held| held.contains(&offer))
    }

    /// Takes the peer's new word; returns whether what it holds changed.
    fn set(&self, behind: bool, offers: Option<Vec<u32>>) -> bool {
        let offers: Option<Arc<[u32]>> = offers.filter(|_| behind).map(Into::into);
        let mut held = lock(&self.offers);
        let was = self.behind.load(Ordering::Acquire);
        let changed = was != behind || (behind && *held != offers);
        *held = offers;
        self.behind.store(behind, Ordering::Release);
        changed
    }
}

/// What a node tells a peer in a [`Message::Flow`]: (behind, readers, offers).
type FlowState = (bool, Option<u8>, Option<Vec<u32>>);

/// What a peer not told anything yet is taken to know: nothing is behind.
const NOT_BEHIND: FlowState = (false, None, None);

/// While some mailbox is behind, how often the node looks again whether its reader stopped
/// (a stopped reader is not waited for: see [`super::mailbox::READER_STALLED`]).
const RECHECK: Duration = Duration::from_millis(50);

impl NodeInner {
    /// A peer says its subscribers are behind (its `readers`, or events it forwards), or
    /// caught up: streams to it wait, or go on; a gateway forwarding events to it passes its
    /// readers' state on (see [`super::forward_flow`]).
    pub(super) fn on_flow(
        &self,
        node: NodeId,
        behind: bool,
        readers: Option<u8>,
        offers: Option<Vec<u32>>,
    ) {
        let Some(p) = self.peers.by_id.get(&node) else {
            return;
        };
        let changed = p.held.set(behind, offers);
        drop(p);
        self.relay_readers_behind(node, readers.filter(|_| behind));
        if changed {
            // Streams waiting for it look again.
            self.bump();
            tracing::debug!(peer = node, behind, "peer's subscribers behind on events");
        }
    }

    /// The offers of `peer` whose events go to one of our mailboxes that is behind (ids on
    /// the peer), in order.
    fn offers_read_behind(&self, peer: NodeId) -> Vec<u32> {
        let Some(p) = self.peers.by_id.get(&peer) else {
            return Vec::new();
        };
        let mut ids: Vec<u32> = p
            .routes
            .iter()
            .filter(|(_, route)| {
                route
                    .iter()
                    .any(|t| t.mailbox.as_ref().is_some_and(|m| m.is_behind()))
            })
            .map(|(id, _)| *id)
            .collect();
        ids.sort_unstable();
        ids
    }

    /// Tells every peer when this node's subscribers fall behind and when they catch up (or
    /// stop reading), until the node stops; a peer that comes while they are behind is told
    /// too. On a gateway, also while the events it forwards wait (see
    /// [`super::forward_flow`]): each peer is told what holds streams from it back.
    pub(crate) async fn tell_peers_when_behind(self: Arc<Self>) {
        // What each peer was last told.
        let mut told: HashMap<NodeId, FlowState> = HashMap::new();
        let mut peers_changed = self.changed.subscribe();
        loop {
            let changed = self.congestion.changed();
            tokio::pin!(changed);
            changed.as_mut().enable();
            let forwarding = self.congestion.forwarding_behind();
            let own = self.congestion.readers_behind();
            let peers: Vec<NodeId> = self.peers.by_id.iter().map(|p| p.id).collect();
            told.retain(|node, _| peers.contains(node));
            let mut any_behind = false;
            for node in peers {
                let state = self.flow_state(node, forwarding, own);
                any_behind |= state.0;
                // A peer not told yet (one that came meanwhile) is told only while behind.
                if *told.get(&node).unwrap_or(&NOT_BEHIND) != state {
                    let (behind, readers, offers) = state.clone();
                    self.send_safe_to_node(
                        node,
                        &Message::Flow {
                            behind,
                            readers,
                            offers,
                        },
                    );
                    told.insert(node, state);
                }
            }
            let some_behind = self.congestion.any_behind();
            tokio::select! {
                _ = self.cancel.cancelled() => return,
                _ = changed => {}
                r = peers_changed.changed(), if any_behind => {
                    if r.is_err() {
                        return;
                    }
                }
                _ = tokio::time::sleep(RECHECK), if some_behind => {}
            }
        }
    }

    /// What `node` is told: behind for all its streams while events this gateway forwards
    /// wait (`forwarding`) or readers beyond it are behind (relayed); else, while our own
    /// readers are behind (`own`), behind for the streams of its offers they read, if any.
    fn flow_state(&self, node: NodeId, forwarding: bool, own: bool) -> FlowState {
        let relayed = self.relayed_readers_behind(node);
        if forwarding || relayed.is_some() {
            return (true, if own { Some(0) } else { relayed }, None);
        }
        if own {
            let offers = self.offers_read_behind(node);
            if !offers.is_empty() {
                return (true, Some(0), Some(offers));
            }
        }
        NOT_BEHIND
    }
}
