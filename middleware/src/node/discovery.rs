//! Discovery: Hello at start and towards each new peer, a small periodic heartbeat carrying the
//! declaration counter, declaration requests when a counter is ahead, and leases.

use std::collections::HashMap;
use std::sync::Arc;
use std::time::{Duration, Instant};

use super::{lock, NodeInner, Peer};
use crate::codec::encode_message;
use crate::link::PeerAddr;
use crate::protocol::{Message, NodeId};

/// The 32-bit hash of a domain name carried in heartbeats.
pub(crate) fn domain_hash(domain: &str) -> u32 {
    let d = blake3::hash(domain.as_bytes());
    let b = d.as_bytes();
    u32::from_le_bytes([b[0], b[1], b[2], b[3]])
}

/// Preference among the paths reaching one peer: shared memory (same host, no copies through
/// the kernel) over the network, the network over a point-to-point radio.
pub(crate) fn path_rank(addr: &PeerAddr) -> u8 {
    match addr {
        PeerAddr::Shm(_) => 2,
        PeerAddr::Udp(_) => 1,
        PeerAddr::PointToPoint => 0,
    }
}

impl NodeInner {
    /// The Hello sent on `link` (it carries that link's lease).
    pub fn hello(&self, link: usize) -> Message {
        self.hello_at(link, self.counter())
    }

    /// The Hello for `link` with a given declaration counter (when the log is already locked).
    pub fn hello_at(&self, link: usize, counter: u32) -> Message {
        Message::Hello {
            node_id: self.me.id,
            domain: self.me.domain.clone(),
            node: self.me.name.clone(),
            namespace: self.me.namespace.clone().unwrap_or_default(),
            counter,
            lease_ms: u32::try_from(self.me.timing(link).1.as_millis()).unwrap_or(u32::MAX),
        }
    }

    /// Announces our Hello on every link.
    pub fn announce_hello(&self) {
        for (i, l) in self.links().iter().enumerate() {
            l.announce(&encode_message(&self.hello(i)));
        }
    }

    pub fn announce(&self, msg: &Message) {
        let bytes = encode_message(msg);
        for l in self.links() {
            l.announce(&bytes);
        }
    }

    pub fn heartbeat(&self) -> Message {
        Message::Heartbeat {
            node_id: self.me.id,
            domain_hash: self.me.domain_hash,
            counter: self.counter(),
        }
    }

    /// Handles Hello, Heartbeat and Bye, whether multicast or inside a session.
    pub fn on_discovery(self: &Arc<Self>, link: usize, from: PeerAddr, msg: Message) {
        match msg {
            Message::Hello {
                node_id,
                domain,
                node,
                namespace,
                counter,
                lease_ms,
            } => {
                if node_id == self.me.id || domain != self.me.domain {
                    return;
                }
                let lease = Duration::from_millis(u64::from(lease_ms.max(1)));
                if self.peers.contains_key(&node_id) {
                    self.also_reached(node_id, link, from);
                    self.seen(node_id, counter);
                    return;
                }
                if let Some(old) = self.addrs.get(&(link, from)).map(|e| *e) {
                    if old != node_id {
                        self.drop_peer(old, "restarted with a new identity");
                    }
                }
                tracing::info!(peer = %node, node_id = format_args!("{node_id:016x}"), %from, "peer discovered");
                // Registering the peer and sending it our Hello and declarations happen under the
                // declaration log's lock, as `declare` pushes its deltas under it too: a delta
                // can then neither overtake our Hello (the peer would drop it, not knowing us)
                // nor fall between the snapshot and the push.
                let log = lock(&self.decls);
                self.peers.insert(
                    node_id,
                    Peer {
                        id: node_id,
                        name: node.as_str().into(),
                        namespace,
                        link,
                        addr: from,
                        last_seen: Instant::now(),
                        heard_ms: Default::default(),
                        lease,
                        known: 0,
                        requested: Some(Instant::now()),
                        services: HashMap::new(),
                        offers: HashMap::new(),
                        interests: HashMap::new(),
                        shadowed: Default::default(),
                        routes: HashMap::new(),
                        authenticated: self
                            .identity
                            .as_ref()
                            .and_then(|i| i.roster.as_ref())
                            .map(|_| Vec::new()),
                    },
                );
                self.addrs.insert((link, from), node_id);
                self.introduce_locked(&log, link, from);
                drop(log);
                self.send_safe(link, from, &Message::DeclRequest { since: 0 });
                self.bump();
            }
            Message::Heartbeat {
                node_id,
                domain_hash,
                counter,
            } => {
                if node_id == self.me.id || domain_hash != self.me.domain_hash {
                    return;
                }
                if self.peers.contains_key(&node_id) {
                    self.also_reached(node_id, link, from);
                    self.seen(node_id, counter);
                } else {
                    // We missed its Hello: introduce ourselves, it answers with its own.
                    self.send_safe(link, from, &self.hello(link));
                }
            }
            Message::Bye { node_id } if self.peers.contains_key(&node_id) => {
                self.drop_peer(node_id, "left");
            }
            _ => {}
        }
    }

    /// A known peer was heard on `link` at `from`, maybe not the path we use for it. We accept
    /// its messages on every path it was heard on (it may still be sending on another one), but
    /// send on one only: the best by [`path_rank`], so a same-host peer that also shares shared
    /// memory is reached over it and never twice. Both ends apply the same rule, so they agree.
    ///
    /// The move itself waits for what is in flight on the old path (`path_switch`): our Hello
    /// then opens the session on the new path, so the peer knows us there before anything
    /// else we send on it, and the safe messages sent meanwhile follow it, in order.
    fn also_reached(self: &Arc<Self>, node: NodeId, link: usize, from: PeerAddr) {
        if self.addrs.get(&(link, from)).is_none_or(|e| *e != node) {
            self.addrs.insert((link, from), node);
        }
        let (old, lease) = {
            let Some(p) = self.peers.get(&node) else {
                return;
            };
            if (p.link, p.addr) == (link, from) || path_rank(&from) <= path_rank(&p.addr) {
                return;
            }
            ((p.link, p.addr), p.lease)
        };
        self.switch_path(node, old, (link, from), lease);
    }

    /// A peer is alive; ask for declarations if its counter is ahead of ours.
    fn seen(&self, node: NodeId, counter: u32) {
        let request = {
            let Some(mut p) = self.peers.get_mut(&node) else {
                return;
            };
            p.last_seen = Instant::now();
            let heartbeat = self.me.timing(p.link).0;
            let stale = p.requested.is_none_or(|t| t.elapsed() > heartbeat * 2);
            if counter > p.known && stale {
                p.requested = Some(Instant::now());
                Some(p.known)
            } else {
                None
            }
        };
        if let Some(since) = request {
            self.send_safe_to_node(node, &Message::DeclRequest { since });
        }
    }

    /// The peer restarted its session with us: anything in flight towards it was lost, so
    /// re-introduce ourselves in the new session.
    pub fn on_peer_reset(&self, link: usize, from: PeerAddr) {
        let node = self.addrs.get(&(link, from)).map(|e| *e);
        if let Some(node) = node {
            self.calls.fail_to(node, "session reset by the peer");
        }
        // It dropped us (and our declarations) before starting over.
        let log = lock(&self.decls);
        self.introduce_locked(&log, link, from);
        drop(log);
        // What we had in flight towards it is lost, a late joiner's value among them: serve the
        // newest value of every variable it subscribes to again.
        if let Some(node) = node {
            self.resend_last_values(node, link, from);
        }
    }

    /// Forgets a peer: its subscriptions are dropped and everything pending on it completes
    /// with an error naming it.
    pub fn drop_peer(&self, node: NodeId, reason: &str) {
        let Some((_, p)) = self.peers.remove(&node) else {
            return;
        };
        if reason == "left" {
            tracing::info!(peer = %p.name, "peer left");
        } else {
            tracing::warn!(peer = %p.name, reason, "peer dropped");
        }
        // Every path it was heard on, the one we used among them.
        let paths: Vec<(usize, PeerAddr)> = self
            .addrs
            .iter()
            .filter(|e| *e.value() == node)
            .map(|e| *e.key())
            .collect();
        for (link, addr) in paths {
            self.addrs.remove(&(link, addr));
            if let Some(l) = self.links().get(link) {
                l.close_peer(addr);
            }
        }
        self.path_switches.forget(node);
        self.calls.fail_to(node, reason);
        self.transfers.peer_lost(node, &p.name, reason);
        self.gateway_peer_lost(node);
        self.recompute_routes();
        self.recompute_forwarding();
    }

    /// Sends heartbeats on `link` at that link's period and expires the leases of the peers
    /// reached over it, until the node stops. Each link has its own loop, so a slow radio link
    /// beats slowly while the LAN beats fast.
    pub async fn heartbeat_loop(self: Arc<Self>, link: usize) {
        let mut tick = tokio::time::interval(self.me.timing(link).0);
        tick.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
        loop {
            tokio::select! {
                _ = self.cancel.cancelled() => break,
                _ = tick.tick() => {}
            }
            if let Some(l) = self.links().get(link) {
                l.announce(&encode_message(&self.heartbeat()));
            }
            let now = Instant::now();
            let expired: Vec<(NodeId, Duration)> = self
                .peers
                .iter()
                .filter(|p| {
                    p.link == link
                        && now.saturating_duration_since(p.last_heard(self.me.epoch)) > p.lease
                })
                .map(|p| (p.id, p.lease))
                .collect();
            for (id, lease) in expired {
                self.drop_peer(id, &format!("lease of {} ms expired", lease.as_millis()));
            }
        }
    }
}
