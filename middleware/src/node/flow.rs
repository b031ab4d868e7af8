//! Flow control for lossless streams across every kind of link: a node whose event subscribers
//! fall behind while still reading (see [`super::mailbox::Congestion`]) tells its peers
//! ([`Message::Flow`]), and their [`crate::EventStream`]s wait until it says it caught up,
//! instead of its mailboxes dropping events. Links acknowledge what reached a mailbox, so a
//! stream's window alone cannot hold a publisher back for a slow reader. A gateway is behind
//! too while the events it forwards wait for a slower link or for a node whose readers are
//! behind (see [`super::forward_flow`]).

use std::collections::HashMap;
use std::sync::atomic::Ordering;
use std::sync::Arc;
use std::time::Duration;

use super::NodeInner;
use crate::protocol::{Message, NodeId};

/// While some mailbox is behind, how often the node looks again whether its reader stopped
/// (a stopped reader is not waited for: see [`super::mailbox::READER_STALLED`]).
const RECHECK: Duration = Duration::from_millis(50);

impl NodeInner {
    /// A peer says its subscribers are behind (its `readers`, or events it forwards), or
    /// caught up: streams to it wait, or go on; a gateway forwarding events to it passes its
    /// readers' state on (see [`super::forward_flow`]).
    pub(super) fn on_flow(&self, node: NodeId, behind: bool, readers: Option<u8>) {
        let Some(p) = self.peers.get(&node) else {
            return;
        };
        let was = p.behind.swap(behind, Ordering::AcqRel);
        drop(p);
        self.relay_readers_behind(node, readers.filter(|_| behind));
        if was && !behind {
            // Streams waiting for it look again.
            self.bump();
        }
        if was != behind {
            tracing::debug!(peer = node, behind, "peer's subscribers behind on events");
        }
    }

    /// Tells every peer when this node's subscribers fall behind and when they catch up (or
    /// stop reading), until the node stops; a peer that comes while they are behind is told
    /// too. On a gateway, also while the events it forwards wait (see
    /// [`super::forward_flow`]): each peer is told what holds streams from it back.
    pub(crate) async fn tell_peers_when_behind(self: Arc<Self>) {
        // What each peer was last told: (behind, readers).
        let mut told: HashMap<NodeId, (bool, Option<u8>)> = HashMap::new();
        let mut peers_changed = self.changed.subscribe();
        loop {
            let changed = self.congestion.changed();
            tokio::pin!(changed);
            changed.as_mut().enable();
            let behind = self.congestion.streams_should_wait();
            let own = self.congestion.readers_behind().then_some(0);
            let peers: Vec<NodeId> = self.peers.iter().map(|p| p.id).collect();
            told.retain(|node, _| peers.contains(node));
            let mut any_behind = false;
            for node in peers {
                let readers = own.or_else(|| self.relayed_readers_behind(node));
                let state = (behind || readers.is_some(), readers);
                any_behind |= state.0;
                // A peer not told yet (one that came meanwhile) is told only while behind.
                if told.get(&node).copied().unwrap_or((false, None)) != state {
                    told.insert(node, state);
                    let (behind, readers) = state;
                    self.send_safe_to_node(node, &Message::Flow { behind, readers });
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
}
