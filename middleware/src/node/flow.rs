//! Flow control for lossless streams across every kind of link: a node whose event subscribers
//! fall behind while still reading (see [`super::mailbox::Congestion`]) tells its peers
//! ([`Message::Flow`]), and their [`crate::EventStream`]s wait until it says it caught up,
//! instead of its mailboxes dropping events. Links acknowledge what reached a mailbox, so a
//! stream's window alone cannot hold a publisher back for a slow reader. A gateway is behind
//! too while the events it forwards wait for a slower link or for a node whose readers are
//! behind (see [`super::forward_flow`]).

use std::sync::atomic::Ordering;
use std::sync::Arc;
use std::time::Duration;

use super::NodeInner;
use crate::protocol::{Message, NodeId};

/// While some mailbox is behind, how often the node looks again whether its reader stopped
/// (a stopped reader is not waited for: see [`super::mailbox::READER_STALLED`]).
const RECHECK: Duration = Duration::from_millis(50);

impl NodeInner {
    /// A peer says its subscribers are behind (its own `readers`, or events it forwards), or
    /// caught up: streams to it wait, or go on; a gateway forwarding events to it passes its
    /// readers' state on (see [`super::forward_flow`]).
    pub(super) fn on_flow(&self, node: NodeId, behind: bool, readers: bool) {
        let Some(p) = self.peers.get(&node) else {
            return;
        };
        let was = p.behind.swap(behind, Ordering::AcqRel);
        drop(p);
        self.relay_readers_behind(node, behind && readers);
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
    /// too.
    pub(crate) async fn tell_peers_when_behind(self: Arc<Self>) {
        // (behind, because of our own readers) as last told.
        let mut told = (false, false);
        let mut peers_changed = self.changed.subscribe();
        let mut new_peers = false;
        loop {
            let changed = self.congestion.changed();
            tokio::pin!(changed);
            changed.as_mut().enable();
            let behind = self.congestion.streams_should_wait();
            let state = (behind, behind && self.congestion.readers_behind());
            // The peer table changed while behind: tell everyone again (peers already told
            // ignore it), so a peer that came meanwhile waits too.
            if state != told || (behind && new_peers) {
                told = state;
                let (behind, readers) = state;
                let peers: Vec<NodeId> = self.peers.iter().map(|p| p.id).collect();
                for node in peers {
                    self.send_safe_to_node(node, &Message::Flow { behind, readers });
                }
            }
            new_peers = false;
            let some_behind = self.congestion.any_behind();
            tokio::select! {
                _ = self.cancel.cancelled() => return,
                _ = changed => {}
                r = peers_changed.changed(), if told.0 => {
                    if r.is_err() {
                        return;
                    }
                    new_peers = true;
                }
                _ = tokio::time::sleep(RECHECK), if some_behind => {}
            }
        }
    }
}
