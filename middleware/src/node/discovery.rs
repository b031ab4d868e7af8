//! Discovery: Hello at start and towards each new peer, a small periodic heartbeat carrying the
//! declaration counter, declaration requests when a counter is ahead, and leases.

use std::collections::HashMap;
use std::sync::atomic::Ordering;
use std::sync::Arc;
use std::time::Duration;

use tokio::time::Instant;

use dashmap::DashMap;

use super::policy::Refusal;
use super::{lock, NodeInner, Peer};
use crate::codec::encode_message;
use crate::link::{Outgoing, PeerAddr};
use crate::protocol::{Message, NodeId};
use crate::sync::SeededHash;

/// Most peers a node keeps. A Hello beyond it pushes out the oldest peer that never confirmed
/// (sent anything in a session), or is ignored when every peer has: a flood of forged Hellos
/// never costs the node a live peer.
pub(crate) const MAX_PEERS: usize = 1024;

/// The shortest lease a peer may ask for: shorter would have it dropped and found again on
/// every heartbeat of ours, each time recomputing routes.
pub(crate) const MIN_LEASE: Duration = Duration::from_millis(100);

/// The longest lease a peer may ask for unless ours on the same link is longer: a node gone
/// without its Bye is forgotten within this (a peer-chosen lease once reached 49 days).
pub(crate) const MAX_LEASE: Duration = Duration::from_secs(60);

/// The lease a peer asked for (`lease_ms` in its Hello), clamped to
/// [[`MIN_LEASE`], max([`MAX_LEASE`], `own`)] where `own` is our lease on that link (a
/// deployment that configured long leases keeps them).
pub(crate) fn clamp_lease(lease_ms: u32, own: Duration) -> Duration {
    Duration::from_millis(u64::from(lease_ms)).clamp(MIN_LEASE, MAX_LEASE.max(own))
}

/// Which peer a full table lets go for a newcomer: the one that became a peer first among
/// those never confirmed; none when all are confirmed. Takes (id, confirmed, since).
pub(crate) fn eviction_candidate(
    peers: impl Iterator<Item = (NodeId, bool, Instant)>,
) -> Option<NodeId> {
    peers
        .filter(|(_, confirmed, _)| !confirmed)
        .min_by_key(|(_, _, since)| *since)
        .map(|(id, _, _)| id)
}

/// The 32-bit hash of a domain name carried in heartbeats.
pub(crate) fn domain_hash(domain: &str) -> u32 {
    let d = blake3::hash(domain.as_bytes());
    let b = d.as_bytes();
    u32::from_le_bytes([b[0], b[1], b[2], b[3]])
}

/// Preference among the paths reaching one peer: shared memory (same host, no copies through
/// the kernel) over the LAN, the LAN over a Zenoh router (a detour, often a WAN), a router over
/// a point-to-point radio.
pub(crate) fn path_rank(addr: &PeerAddr) -> u8 {
    match addr {
        PeerAddr::Shm(_) => 3,
        PeerAddr::Udp(_) => 2,
        PeerAddr::Zenoh(_) => 1,
        PeerAddr::PointToPoint => 0,
    }
}

/// The peers: each by its id, and the id of each by the (link, address) it speaks from.
#[derive(Default)]
pub(crate) struct PeerTable {
    pub by_id: DashMap<NodeId, Peer, SeededHash>,
    pub by_addr: DashMap<(usize, PeerAddr), NodeId, SeededHash>,
}

impl NodeInner {
    /// The Hello sent on `link` (it carries that link's lease).
    pub fn hello(&self, link: usize) -> Message {
        self.hello_at(link, self.counter())
    }

    /// The Hello for `link` with a given declaration counter (when the log is already locked).
    pub fn hello_at(&self, link: usize, counter: u32) -> Message {
        self.hello_with(link, counter, false)
    }

    /// Our Hello to a node we heard a heartbeat of without knowing it: it asks that node to
    /// introduce itself again if it knows us (see [`Message::Hello`]).
    fn hello_asking_introduction(&self, link: usize) -> Message {
        self.hello_with(link, self.counter(), true)
    }

    fn hello_with(&self, link: usize, counter: u32, asks_introduction: bool) -> Message {
        Message::Hello {
            node_id: self.me.id,
            domain: self.me.domain.clone(),
            node: self.me.name.clone(),
            namespace: self.me.namespace.clone().unwrap_or_default(),
            counter,
            lease_ms: u32::try_from(self.me.timing(link).1.as_millis()).unwrap_or(u32::MAX),
            gateway: self.gateway.is_some(),
            asks_introduction,
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

    /// Whether announcement `msg`, sealed with the domain key, from `from` on `link` is a
    /// `Bye`, or a `Hello` of another node id, from the address of a peer whose frames come
    /// sealed with our pair's keys: a key holder forging its address would evict it (or take
    /// its place). Refused and counted ([`Refusal::ForgedBye`]): the peer's own `Bye` comes
    /// inside its session too ([`Self::say_bye`]), and a node restarted at the same address
    /// is met once the old one's lease has run out.
    pub fn forged_over_pair(&self, link: usize, from: PeerAddr, msg: &Message) -> bool {
        let Some(node) = self.peers.by_addr.get(&(link, from)).map(|e| *e) else {
            return false;
        };
        let forged = match msg {
            Message::Bye { .. } => true,
            Message::Hello { node_id, .. } => *node_id != node,
            _ => false,
        };
        if !forged || !self.links().get(link).is_some_and(|l| l.pair_sealed(from)) {
            return false;
        }
        let name = self.peer_name(node);
        self.policy
            .refuse(link, node, &name, "announcement", Refusal::ForgedBye);
        true
    }

    /// Tells every peer we leave, inside its session (so with our pair's keys where we share
    /// some), besides the announcement.
    pub fn say_bye(&self) {
        let msg = encode_message(&Message::Bye {
            node_id: self.me.id,
        });
        let peers: Vec<(usize, PeerAddr)> =
            self.peers.by_id.iter().map(|p| (p.link, p.addr)).collect();
        for (link, addr) in peers {
            self.send_to(
                link,
                addr,
                Outgoing::Fast {
                    coalesce: None,
                    msg: msg.clone(),
                },
            );
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
                gateway,
                asks_introduction,
            } => {
                if node_id == self.me.id || domain != self.me.domain {
                    return;
                }
                let lease = clamp_lease(lease_ms, self.me.timing(link).1);
                if self.peers.by_id.contains_key(&node_id) {
                    if self.also_reached(node_id, link, from) {
                        self.seen(node_id, counter);
                        if asks_introduction {
                            self.introduce_again(node_id, link, from);
                        }
                    }
                    return;
                }
                if !self.make_room_for_peer(&node) {
                    return;
                }
                if let Some(old) = self.peers.by_addr.get(&(link, from)).map(|e| *e) {
                    if old != node_id {
                        self.drop_peer(old, "restarted with a new identity");
                    }
                }
                // Only a gateway speaks for other nodes; our `<access>` may narrow who is one,
                // and where a roster is kept only a key listed as a gateway makes one (once its
                // proof arrives: `on_identity`). A Hello alone is a claim.
                let roster = self.identity.as_ref().and_then(|i| i.roster.as_ref());
                let claims_gateway = gateway
                    && self.policy.allows(
                        crate::config::AccessKind::Gateway,
                        "",
                        &namespace,
                        &node,
                    );
                // Registering the peer and sending it our Hello and declarations happen under the
                // declaration log's lock, as `declare` pushes its deltas under it too: a delta
                // can then neither overtake our Hello (the peer would drop it, not knowing us)
                // nor fall between the snapshot and the push.
                let log = lock(&self.local.log);
                // Two Hellos of a new peer handled at once (its multicast and its unicast one)
                // both found it unknown: the first registers it, under this lock; the second
                // must not register it again (a second challenge would void the peer's answer
                // to the first, and its proof would be refused).
                if self.peers.by_id.contains_key(&node_id) {
                    return;
                }
                tracing::info!(peer = %node, node_id = format_args!("{node_id:016x}"), %from, "peer discovered");
                let challenge: Option<[u8; 16]> = roster.map(|_| rand::random());
                self.peers.by_id.insert(
                    node_id,
                    Peer {
                        id: node_id,
                        name: node.as_str().into(),
                        namespace,
                        claims_gateway,
                        gateway: claims_gateway && roster.is_none(),
                        link,
                        addr: from,
                        last_seen: Instant::now(),
                        heard_ms: Default::default(),
                        lease,
                        known: 0,
                        since: Instant::now(),
                        // Set below, once its address is mapped.
                        confirmed: Default::default(),
                        requested: Some(Instant::now()),
                        services: HashMap::new(),
                        offers: HashMap::new(),
                        interests: HashMap::new(),
                        shadowed: Default::default(),
                        routes: HashMap::default(),
                        pair: None,
                        authenticated: roster.map(|_| Default::default()),
                        challenge,
                        handshake: super::Handshake {
                            ours: challenge,
                            ..Default::default()
                        },
                        alive: Arc::new(std::sync::atomic::AtomicBool::new(true)),
                        held: Arc::default(),
                        introduced_again: None,
                    },
                );
                self.peers.by_addr.insert((link, from), node_id);
                if let Some(l) = self.links().get(link) {
                    l.confirm_peer(from);
                }
                // A session of ours it acknowledged before it was mapped (it answered an
                // introduction we sent on its asking) counts: the link tells each peer once,
                // and may have told it while the address led nowhere.
                if self.answered_at(link, from) {
                    self.on_peer_answered(link, from);
                }
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
                if self.peers.by_id.contains_key(&node_id) {
                    if self.also_reached(node_id, link, from) {
                        self.seen(node_id, counter);
                    }
                } else {
                    // We missed its Hello: introduce ourselves, it answers with its own (or,
                    // knowing us already, introduces itself again).
                    self.send_safe(link, from, &self.hello_asking_introduction(link));
                }
            }
            Message::Bye { node_id } if self.peers.by_id.contains_key(&node_id) => {
                // Only the node itself says it leaves: from an address it was heard at.
                if self
                    .peers
                    .by_addr
                    .get(&(link, from))
                    .is_some_and(|e| *e == node_id)
                {
                    self.drop_peer(node_id, "left");
                } else {
                    let name = self.peers.by_id.get(&node_id).map(|p| p.name.to_string());
                    self.policy.refuse(
                        link,
                        node_id,
                        name.as_deref().unwrap_or("?"),
                        "Bye",
                        super::policy::Refusal::ForgedBye,
                    );
                }
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
    ///
    /// A node has one address per link: a known node "heard" at a second address on a link it
    /// already has one on is somebody else using its id, and is not mapped (it could otherwise
    /// say Bye for it, or take its traffic).
    /// Returns whether `from` is (now) a path of `node`.
    fn also_reached(self: &Arc<Self>, node: NodeId, link: usize, from: PeerAddr) -> bool {
        if self
            .peers
            .by_addr
            .get(&(link, from))
            .is_none_or(|e| *e != node)
        {
            let other = self
                .peers
                .by_addr
                .iter()
                .any(|e| e.key().0 == link && e.key().1 != from && *e.value() == node);
            if other {
                let name = self.peers.by_id.get(&node).map(|p| p.name.to_string());
                self.policy.refuse(
                    link,
                    node,
                    name.as_deref().unwrap_or("?"),
                    "second address",
                    super::policy::Refusal::SecondAddress,
                );
                return false;
            }
            self.peers.by_addr.insert((link, from), node);
            if let Some(l) = self.links().get(link) {
                l.confirm_peer(from);
            }
        }
        let (old, lease) = {
            let Some(p) = self.peers.by_id.get(&node) else {
                return true;
            };
            if (p.link, p.addr) == (link, from) || path_rank(&from) <= path_rank(&p.addr) {
                return true;
            }
            ((p.link, p.addr), p.lease)
        };
        self.switch_path(node, old, (link, from), lease);
        true
    }

    /// A known peer does not know us (its Hello answers a heartbeat of ours): our introduction
    /// to it was lost on the way. Introduces us again (Hello and every declaration), at most
    /// once per heartbeat period of the link: the peer asks at each heartbeat it hears.
    fn introduce_again(&self, node: NodeId, link: usize, from: PeerAddr) {
        let period = self.me.timing(link).0;
        {
            let Some(mut p) = self.peers.by_id.get_mut(&node) else {
                return;
            };
            if p.introduced_again.is_some_and(|t| t.elapsed() < period) {
                return;
            }
            p.introduced_again = Some(Instant::now());
            tracing::info!(peer = %p.name, "peer does not know us: introducing ourselves again");
        }
        let log = lock(&self.local.log);
        self.introduce_locked(&log, link, from);
    }

    /// Makes room in a full peer table for a new peer (`name`, for the log): pushes out the
    /// oldest unconfirmed peer, or returns false (counted) when every peer is confirmed.
    fn make_room_for_peer(&self, name: &str) -> bool {
        if self.peers.by_id.len() < MAX_PEERS {
            return true;
        }
        // With a roster, only a proven identity keeps its place.
        let proven = |p: &super::Peer| p.authenticated.is_none() || p.proven();
        let candidate = eviction_candidate(self.peers.by_id.iter().map(|p| {
            (
                p.id,
                p.confirmed.load(Ordering::Relaxed) && proven(&p),
                p.since,
            )
        }));
        match candidate {
            Some(old) => {
                let n = self
                    .policy
                    .dropped
                    .peers_evicted
                    .fetch_add(1, Ordering::Relaxed);
                if (n + 1).is_power_of_two() {
                    tracing::warn!(peer = %name, evicted = n + 1, "peer table full ({MAX_PEERS}): an unconfirmed peer pushed out for a new one");
                }
                self.drop_peer(old, "pushed out of a full peer table, never confirmed");
                true
            }
            None => {
                let n = self
                    .policy
                    .dropped
                    .peers_refused
                    .fetch_add(1, Ordering::Relaxed);
                // Logged at the 1st, 2nd, 4th, 8th... refusal: a flood is seen, not echoed.
                if (n + 1).is_power_of_two() {
                    tracing::warn!(peer = %name, refused = n + 1, "peer table full of confirmed peers ({MAX_PEERS}); new peer ignored");
                }
                false
            }
        }
    }

    /// Whether the peer at `from` on `link` has shown that it receives there.
    fn answered_at(&self, link: usize, from: PeerAddr) -> bool {
        self.links().get(link).is_some_and(|l| l.answered(from))
    }

    /// The peer at `from` acknowledged a session of ours: it is confirmed (see
    /// [`super::Peer::confirmed`]).
    pub fn on_peer_answered(&self, link: usize, from: PeerAddr) {
        if let Some(node) = self.peer_of(link, from) {
            if let Some(p) = self.peers.by_id.get(&node) {
                p.confirmed.store(true, Ordering::Relaxed);
            }
        }
    }

    /// The link closed its session with `from` after its retry limit: a peer reached there
    /// (and nowhere better) is gone, or was never there.
    pub fn on_peer_unreachable(&self, link: usize, from: PeerAddr) {
        let Some(node) = self.peers.by_addr.get(&(link, from)).map(|e| *e) else {
            return;
        };
        let current = self
            .peers
            .by_id
            .get(&node)
            .is_some_and(|p| (p.link, p.addr) == (link, from));
        if current {
            self.drop_peer(node, "acknowledged nothing within the retry limit");
        }
    }

    /// A peer is alive; ask for declarations if its counter is ahead of ours.
    fn seen(&self, node: NodeId, counter: u32) {
        let request = {
            let Some(mut p) = self.peers.by_id.get_mut(&node) else {
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
        let node = self.peers.by_addr.get(&(link, from)).map(|e| *e);
        if let Some(node) = node {
            self.calls
                .pending
                .fail_to(node, "session reset by the peer");
        }
        // It dropped us (and our declarations) before starting over.
        let log = lock(&self.local.log);
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
        let Some((_, p)) = self.peers.by_id.remove(&node) else {
            return;
        };
        p.alive.store(false, Ordering::Release);
        if reason == "left" {
            tracing::info!(peer = %p.name, "peer left");
        } else if p.confirmed.load(Ordering::Relaxed) {
            tracing::warn!(peer = %p.name, reason, "peer dropped");
        } else {
            // Never confirmed: a flood of forged Hellos would otherwise be a flood of lines
            // (evictions are counted in `Node::refusals` and logged at powers of two).
            tracing::debug!(peer = %p.name, reason, "unconfirmed peer dropped");
        }
        // Every path it was heard on, the one we used among them.
        let paths: Vec<(usize, PeerAddr)> = self
            .peers
            .by_addr
            .iter()
            .filter(|e| *e.value() == node)
            .map(|e| *e.key())
            .collect();
        for path in &paths {
            self.peers.by_addr.remove(path);
        }
        // Routes first, links second: a raise that completes with the closed session's error
        // and raises again must find the peer gone from the routes, or its next events would
        // open a fresh session with the dead address and wait there for that session's expiry
        // (seen with 4,096 raises in flight: the last ones completed 5 s after the first).
        // Raises that read the routes just before this see `alive` cleared and fail at once.
        self.recompute_routes();
        self.recompute_forwarding();
        for (link, addr) in paths {
            if let Some(l) = self.links().get(link) {
                l.close_peer(addr);
            }
        }
        self.path_switches.forget(node);
        self.calls.pending.fail_to(node, reason);
        self.transfers.peer_lost(node, &p.name, reason);
        self.gateway_peer_lost(node);
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
                .by_id
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

#[cfg(test)]
mod tests {
    use super::*;
    use crate::node::files::Control;

    /// A peer that falls silent is dropped once its lease has run out, not before, and what
    /// waited on it hears why. On paused time: the timer logic itself is checked, to the
    /// heartbeat, not a shared machine's scheduling.
    #[tokio::test(start_paused = true)]
    async fn a_silent_peer_is_dropped_when_its_lease_runs_out_and_not_before() {
        let node = crate::node::bare_node(None, None);
        let (heartbeat, _) = node.me.timing(0);
        let lease = Duration::from_millis(2_000);
        let from = PeerAddr::Udp(std::net::SocketAddr::from(([127, 0, 0, 1], 9)));
        node.on_discovery(
            0,
            from,
            Message::Hello {
                node_id: 7,
                domain: crate::config::DEFAULT_DOMAIN.into(),
                node: "air".into(),
                namespace: "rover1".into(),
                counter: 0,
                lease_ms: lease.as_millis() as u32,
                gateway: false,
                asks_introduction: false,
            },
        );
        let heard = Instant::now();
        assert!(node.peers.by_id.contains_key(&7), "the Hello made a peer");
        // A transfer to it, as a sending task registers one.
        let mut sender = node.transfers.register_sender(1, 7);
        tokio::spawn(node.clone().heartbeat_loop(0));

        tokio::time::sleep(lease).await;
        assert!(
            node.peers.by_id.contains_key(&7),
            "dropped before its lease ran out"
        );
        let why = match sender.recv().await {
            Some(Control::PeerLost(why)) => why,
            other => panic!("the transfer heard {other:?}"),
        };
        let after = heard.elapsed();
        assert!(!node.peers.by_id.contains_key(&7), "still a peer");
        assert!(why.contains("lease of 2000 ms expired"), "{why}");
        assert!(
            after > lease && after <= lease + heartbeat,
            "dropped {after:?} after it was last heard, lease {lease:?}, heartbeat {heartbeat:?}"
        );
        node.cancel.cancel();
    }

    #[test]
    fn a_peers_lease_is_clamped_on_receipt() {
        let own = Duration::from_millis(3500);
        // 49 days asked: a minute granted.
        assert_eq!(clamp_lease(u32::MAX, own), MAX_LEASE);
        assert_eq!(clamp_lease(0, own), MIN_LEASE);
        assert_eq!(clamp_lease(1, own), MIN_LEASE);
        assert_eq!(clamp_lease(3500, own), own);
        // A deployment whose own lease is longer keeps its peers that long.
        let long = Duration::from_secs(600);
        assert_eq!(clamp_lease(600_000, long), long);
        assert_eq!(clamp_lease(u32::MAX, long), long);
    }

    #[test]
    fn a_full_peer_table_lets_go_the_oldest_unconfirmed_and_never_a_confirmed_one() {
        let t0 = Instant::now();
        let at = |s: u64| t0 + Duration::from_secs(s);
        let peers = [
            (1, true, at(0)),
            (2, false, at(5)),
            (3, false, at(3)),
            (4, true, at(1)),
        ];
        assert_eq!(eviction_candidate(peers.into_iter()), Some(3));
        let all_confirmed = [(1, true, at(0)), (4, true, at(1))];
        assert_eq!(eviction_candidate(all_confirmed.into_iter()), None);
        assert_eq!(eviction_candidate(std::iter::empty()), None);
    }
}
