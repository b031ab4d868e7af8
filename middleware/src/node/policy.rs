//! What a node accepts from its peers: owned names (a node declares only under its own
//! namespace; only gateways speak for other nodes), the `<access>` rules of `network.xml`
//! (`config::access`), and the caps that keep a peer from making the node store or run an
//! unbounded amount. Every refusal is counted per link (published in link health) and logged at
//! most once per peer and item per minute, so a flood of refused input cannot flood the log.

use std::collections::HashMap;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::Mutex;
use std::time::{Duration, Instant};

use super::lock;
use crate::config::access::{peer_path, AccessConfig, AccessKind};
use crate::protocol::{NodeId, Origin};

/// Declarations (services, offers, interests) stored for one peer; beyond, new ones are
/// refused. Far above a real node (the VAS declares a few dozen).
pub(crate) const MAX_DECLS_PER_PEER: usize = 4096;
/// Declarations stored for all peers together.
pub(crate) const MAX_DECLS_TOTAL: usize = 65_536;
/// Calls of one caller (a peer, or a node a gateway relays for) running or waiting in their
/// function's lane at once; beyond, `Busy`.
pub(crate) const MAX_CALLS_PER_CALLER: usize = 32;
/// Calls of all peers running at once; beyond, `Busy`.
pub(crate) const MAX_CALLS_TOTAL: usize = 256;
/// The longest a caller's remaining time is taken at its word (a peer once asked for 74 days).
pub(crate) const MAX_CALL_TIME: Duration = Duration::from_secs(600);
/// How often the same refusal (peer and item) is logged.
const LOG_EVERY: Duration = Duration::from_secs(60);
/// Refusals remembered for rate-limiting the log; past it, the oldest minute is forgotten and,
/// if still full, refusals are counted but not logged.
const LOG_MEMORY: usize = 4096;
/// Refusal lines logged per minute in all: an attacker varying item names cannot flood the
/// log either (the counters still count everything).
const LOG_LINES_PER_MINUTE: u32 = 120;

/// Why something from a peer was refused.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) enum Refusal {
    /// The `<access>` rules do not allow it.
    Denied(AccessKind),
    /// An offer outside the declaring node's namespace.
    NotOwned,
    /// An offer naming another node as its origin, from a node that is no gateway (or a
    /// gateway claiming to be zero hops away).
    ForeignOrigin,
    /// A `Bye` for a node from an address not mapped to it.
    ForgedBye,
    /// A known node heard at a second address on the same link.
    SecondAddress,
    /// The per-peer or total declaration cap is reached.
    TooManyDeclarations,
    /// The per-peer or total concurrent-call cap is reached.
    Busy,
    /// An identity proof that answers no challenge of ours (replayed, made for another nonce
    /// or node, or by another key).
    IdentityUnproven,
    /// A peer announcing itself a gateway whose key the roster does not list as one: it
    /// speaks for no other node.
    GatewayNotListed,
    /// A call or file to relay from a peer whose identity is not proven (where a roster is
    /// kept): the next node would take the name we pass on as proven.
    RelayUnproven,
    /// A file a sink refused (bad name, too large, past its announced size, over the quota,
    /// too many at once, wrong content, no such sink).
    File,
}

impl Refusal {
    fn as_str(self) -> &'static str {
        match self {
            Refusal::Denied(AccessKind::Call) => "call denied by <access>",
            Refusal::Denied(AccessKind::File) => "file denied by <access>",
            Refusal::Denied(AccessKind::Publish) => "publication denied by <access>",
            Refusal::Denied(AccessKind::Gateway) => "gateway denied by <access>",
            Refusal::NotOwned => "offer outside the node's namespace",
            Refusal::ForeignOrigin => "origin claimed by a node that is no gateway",
            Refusal::ForgedBye => "Bye from an address not mapped to that node",
            Refusal::SecondAddress => "known node at a second address on the same link",
            Refusal::TooManyDeclarations => "declaration cap reached",
            Refusal::Busy => "concurrent-call cap reached",
            Refusal::IdentityUnproven => "identity proof answering no challenge of ours",
            Refusal::GatewayNotListed => "gateway role its identity key is not listed for",
            Refusal::RelayUnproven => "relay for a peer whose identity is not proven",
            Refusal::File => "file refused by the sink",
        }
    }
}

/// Refusals counted on one link.
#[derive(Debug, Default)]
pub(crate) struct RefusalCounters {
    /// Refused by the `<access>` rules.
    pub denied: AtomicU64,
    /// Refused otherwise (owned names, origins, forged Bye, caps).
    pub rejected: AtomicU64,
}

/// Everything a node refused from its peers since it opened, in one place (see
/// [`crate::Node::refusals`]): each count is a thing dropped, never delivered or acted on.
/// Per link, `denied`/`rejected` and the seal counts are also in [`crate::LinkHealth`].
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct RefusalReport {
    /// Refused by the `<access>` rules (calls, files, publications, gateways).
    pub denied: u64,
    /// Refused by the node's own rules: offers outside their namespace, origins from
    /// non-gateways, forged Byes, a known node at a second address, caps reached, identity
    /// proofs answering no challenge, files a sink refused.
    pub rejected: u64,
    /// Frames whose seal did not verify (no key, another key, tampering).
    pub auth_rejected: u64,
    /// Frames refused as replays.
    pub replay_rejected: u64,
    /// Messages that could not be decoded.
    pub undecodable: u64,
    /// Messages from an address no peer is known at.
    pub unknown_sender: u64,
    /// Peers' declarations ignored for a malformed or oversized name or pattern.
    pub bad_declarations: u64,
    /// New peers ignored because the peer table was full of confirmed peers.
    pub peers_refused: u64,
    /// Unconfirmed peers forgotten to make room for new ones.
    pub peers_evicted: u64,
}

impl RefusalReport {
    /// Every refusal counted, whatever the reason.
    pub fn total(&self) -> u64 {
        self.denied
            + self.rejected
            + self.auth_rejected
            + self.replay_rejected
            + self.undecodable
            + self.unknown_sender
            + self.bad_declarations
            + self.peers_refused
            + self.peers_evicted
    }
}

/// A node's acceptance policy and what it refused.
pub(crate) struct Policy {
    pub access: Option<AccessConfig>,
    /// By link index.
    counters: Vec<RefusalCounters>,
    logged: Mutex<LogMemory>,
    /// Input dropped before any rule applied (undecodable, unknown senders, bad declarations,
    /// a full peer table).
    pub dropped: DroppedInput,
}

/// Input a node dropped, counted.
#[derive(Default)]
pub(crate) struct DroppedInput {
    pub undecodable: AtomicU64,
    pub unknown_sender: AtomicU64,
    /// Peers' declarations ignored for a malformed or oversized name or pattern.
    pub bad_declarations: AtomicU64,
    /// Hellos of new peers ignored because the peer table was full of confirmed peers.
    pub peers_refused: AtomicU64,
    /// Unconfirmed peers forgotten to make room for a new one.
    pub peers_evicted: AtomicU64,
}

impl DroppedInput {
    /// Adds the counters now to `report`.
    pub fn add_to(&self, report: &mut RefusalReport) {
        let get = |c: &AtomicU64| c.load(Ordering::Relaxed);
        report.undecodable += get(&self.undecodable);
        report.unknown_sender += get(&self.unknown_sender);
        report.bad_declarations += get(&self.bad_declarations);
        report.peers_refused += get(&self.peers_refused);
        report.peers_evicted += get(&self.peers_evicted);
    }
}

/// What was logged lately.
#[derive(Default)]
struct LogMemory {
    last: HashMap<(NodeId, String), Instant>,
    /// Start of the current minute and lines logged in it.
    window: Option<(Instant, u32)>,
}

impl Policy {
    pub fn new(access: Option<AccessConfig>, links: usize) -> Self {
        Policy {
            access,
            // At least one, so a node without links (tests) still counts.
            dropped: DroppedInput::default(),
            counters: (0..links.max(1))
                .map(|_| RefusalCounters::default())
                .collect(),
            logged: Mutex::default(),
        }
    }

    /// Whether peer `namespace/node` may do `kind` on `item`.
    pub fn allows(&self, kind: AccessKind, item: &str, namespace: &str, node: &str) -> bool {
        self.access
            .as_ref()
            .is_none_or(|a| a.allows(kind, item, &peer_path(namespace, node)))
    }

    /// The (denied, rejected) counts of `link`.
    pub fn counts(&self, link: usize) -> (u64, u64) {
        self.counters.get(link).map_or((0, 0), |c| {
            (
                c.denied.load(Ordering::Relaxed),
                c.rejected.load(Ordering::Relaxed),
            )
        })
    }

    /// Counts a refusal on `link` without logging it (the caller logs its own way).
    pub fn count(&self, link: usize, why: Refusal) {
        if let Some(c) = self.counters.get(link) {
            match why {
                Refusal::Denied(_) => c.denied.fetch_add(1, Ordering::Relaxed),
                _ => c.rejected.fetch_add(1, Ordering::Relaxed),
            };
        }
    }

    /// Counts a refusal on `link` and logs it unless the same (peer, item) was logged within
    /// the last minute.
    pub fn refuse(&self, link: usize, peer: NodeId, peer_name: &str, item: &str, why: Refusal) {
        self.count(link, why);
        if self.first_in_a_minute(peer, item, Instant::now()) {
            tracing::warn!(
                peer = %peer_name,
                node_id = format_args!("{peer:016x}"),
                item,
                reason = why.as_str(),
                "refused (logged once per peer and item per minute)"
            );
        }
    }

    fn first_in_a_minute(&self, peer: NodeId, item: &str, now: Instant) -> bool {
        let mut memory = lock(&self.logged);
        let m = &mut *memory;
        let key = (peer, item.to_owned());
        if let Some(at) = m.last.get(&key) {
            if now.saturating_duration_since(*at) < LOG_EVERY {
                return false;
            }
        }
        if m.last.len() >= LOG_MEMORY && !m.last.contains_key(&key) {
            m.last
                .retain(|_, at| now.saturating_duration_since(*at) < LOG_EVERY);
            if m.last.len() >= LOG_MEMORY {
                return false;
            }
        }
        let (start, lines) = m.window.get_or_insert((now, 0));
        if now.saturating_duration_since(*start) >= LOG_EVERY {
            (*start, *lines) = (now, 0);
        }
        if *lines >= LOG_LINES_PER_MINUTE {
            return false;
        }
        *lines += 1;
        m.last.insert(key, now);
        true
    }
}

impl super::NodeInner {
    /// Whether peer `node` may do `kind` on our item `item`, or, for what gateway `node`
    /// relays, `caller`; a refusal is counted and logged, and says why. Only a gateway may
    /// speak for another node (see [`Self::relays_for`]): anyone else naming a `caller` is
    /// refused whatever the rules say ([`Refusal::ForeignOrigin`]). An unknown peer is refused
    /// when a rule governs `kind`. When this node checks identities, the rules see a peer's
    /// namespace only once its identity key proved it: until then (or when its key is not
    /// listed for it) the peer is refused whatever a rule governs. A relayed caller's namespace
    /// and name are as the gateway names them, the gateway's own identity proved.
    pub fn permitted(
        &self,
        node: NodeId,
        caller: Option<&Origin>,
        kind: AccessKind,
        item: &str,
    ) -> Result<(), Refusal> {
        if caller.is_some_and(|o| !self.relays_for(node, o)) {
            let (link, name) = (self.peer_link(node), self.peer_name(node));
            self.policy
                .refuse(link, node, &name, item, Refusal::ForeignOrigin);
            return Err(Refusal::ForeignOrigin);
        }
        let Some(access) = self.policy.access.as_ref() else {
            return Ok(());
        };
        let governs = access.governs(kind);
        let Some((link, peer_namespace, peer_name)) = self
            .peers
            .by_id
            .get(&node)
            .map(|p| (p.link, p.namespace.clone(), p.name.clone()))
        else {
            return if governs {
                Err(Refusal::Denied(kind))
            } else {
                Ok(())
            };
        };
        let (namespace, name) = caller.map_or((peer_namespace.as_str(), &*peer_name), |o| {
            (o.namespace.as_str(), o.name.as_str())
        });
        // A claimed namespace is no credential where identities are checked.
        let proven = self.identity_allows(node);
        if (proven || !governs) && self.policy.allows(kind, item, namespace, name) {
            return Ok(());
        }
        let shown = match caller {
            Some(o) => format!("{} (via {peer_name})", o.name),
            None => peer_name.to_string(),
        };
        self.policy
            .refuse(link, node, &shown, item, Refusal::Denied(kind));
        Err(Refusal::Denied(kind))
    }
}

/// Whether a node of `namespace` may offer `name`.
///
/// A node with a namespace owns the names under it (`rover1/...`). A node without one (the
/// zero-configuration demo) owns the names outside every namespace known to be taken
/// (`others`: ours and our peers'), so it cannot pose as `rover1/vas/...` next to a `rover1`.
pub(crate) fn owns(namespace: &str, name: &str, others: &[String]) -> bool {
    let under = |ns: &str| {
        name.len() > ns.len() + 1 && name.starts_with(ns) && name.as_bytes()[ns.len()] == b'/'
    };
    if namespace.is_empty() {
        !others.iter().any(|ns| !ns.is_empty() && under(ns))
    } else {
        under(namespace)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_namespace_owns_the_names_under_it_only() {
        let others = vec!["rover1".to_owned(), "fleet/rover2".to_owned()];
        assert!(owns("rover1", "rover1/vas/position", &others));
        assert!(!owns("evil", "rover1/vas/position", &others));
        assert!(!owns("rover1", "rover1", &others));
        assert!(!owns("rover1", "rover10/vas/position", &others));
        assert!(owns("fleet/rover2", "fleet/rover2/vas/x", &others));
        assert!(!owns("fleet", "fleet2/vas/x", &others));
        // Without a namespace: anything outside the namespaces taken.
        assert!(owns("", "probe/position", &others));
        assert!(!owns("", "rover1/vas/position", &others));
        assert!(!owns("", "fleet/rover2/vas/x", &others));
        assert!(owns("", "rover10/vas/x", &others));
    }

    #[test]
    fn a_refusal_is_counted_always_and_logged_once_a_minute() {
        let p = Policy::new(None, 2);
        let t0 = Instant::now();
        assert!(p.first_in_a_minute(1, "a", t0));
        assert!(!p.first_in_a_minute(1, "a", t0 + Duration::from_secs(59)));
        assert!(p.first_in_a_minute(1, "b", t0), "another item");
        assert!(p.first_in_a_minute(2, "a", t0), "another peer");
        assert!(p.first_in_a_minute(1, "a", t0 + Duration::from_secs(61)));
        p.refuse(1, 9, "x", "i", Refusal::Denied(AccessKind::Call));
        p.refuse(1, 9, "x", "i", Refusal::NotOwned);
        p.refuse(1, 9, "x", "i", Refusal::NotOwned);
        p.refuse(7, 9, "x", "i", Refusal::NotOwned);
        assert_eq!(p.counts(1), (1, 2));
        assert_eq!(p.counts(0), (0, 0));
    }

    use super::super::{bare_node as bare, LocalInterest, NodeInner};
    use crate::config::{AccessConfig, AccessRule};
    use crate::link::PeerAddr;
    use crate::protocol::{Declaration, ItemKind, LoggedDeclaration, Message, Origin};
    use crate::typeinfo::TypeInfo;
    use std::sync::Arc;

    fn addr(port: u16) -> PeerAddr {
        PeerAddr::Udp(std::net::SocketAddr::from(([127, 0, 0, 1], port)))
    }

    use super::super::test_hello as hello;

    fn offer(id: u32, kind: ItemKind, name: &str, origin: Option<Origin>) -> Declaration {
        Declaration::Offer {
            id,
            service: 1,
            kind,
            name: name.into(),
            ty: TypeInfo::of::<u64>(),
            origin,
        }
    }

    /// Applies `decls` as peer `id`'s next declarations.
    fn declare(inner: &Arc<NodeInner>, id: NodeId, decls: Vec<Declaration>) {
        let known = inner.peers.by_id.get(&id).map_or(0, |p| p.known);
        let entries: Vec<LoggedDeclaration> = decls
            .into_iter()
            .enumerate()
            .map(|(k, decl)| LoggedDeclaration {
                counter: known + 1 + k as u32,
                decl,
            })
            .collect();
        let upto = known + entries.len() as u32;
        inner.apply_decl_batch(id, known, upto, false, entries);
    }

    fn offered(inner: &NodeInner, id: NodeId) -> Vec<String> {
        let mut v: Vec<String> = inner
            .peers
            .by_id
            .get(&id)
            .map(|p| p.offers.values().map(|o| o.name.to_string()).collect())
            .unwrap_or_default();
        v.sort();
        v
    }

    #[tokio::test]
    async fn a_node_offers_only_under_its_own_namespace() {
        let inner = bare(Some("ground"), None);
        inner.on_discovery(0, addr(1), hello(1, "air", "rover1", false));
        inner.on_discovery(0, addr(2), hello(2, "evil", "evil", false));
        inner.on_discovery(0, addr(3), hello(3, "plain", "", false));
        declare(
            &inner,
            1,
            vec![offer(10, ItemKind::Variable, "rover1/vas/position", None)],
        );
        declare(
            &inner,
            2,
            vec![
                offer(10, ItemKind::Variable, "rover1/vas/position", None),
                offer(11, ItemKind::Function, "rover1/vas/push_waypoints", None),
                offer(12, ItemKind::Variable, "evil/x/y", None),
            ],
        );
        declare(
            &inner,
            3,
            vec![
                offer(10, ItemKind::Variable, "rover1/vas/position", None),
                offer(11, ItemKind::Variable, "ground/fmo/manual_control", None),
                offer(12, ItemKind::Variable, "probe/position", None),
            ],
        );
        assert_eq!(offered(&inner, 1), ["rover1/vas/position"]);
        assert_eq!(offered(&inner, 2), ["evil/x/y"]);
        assert_eq!(offered(&inner, 3), ["probe/position"]);
        assert_eq!(inner.policy.counts(0), (0, 4));
        // The refused offers left no gap: a later declaration still applies.
        declare(
            &inner,
            2,
            vec![offer(13, ItemKind::Event, "evil/x/z", None)],
        );
        assert_eq!(offered(&inner, 2), ["evil/x/y", "evil/x/z"]);
        inner.cancel.cancel();
    }

    /// Of two copies of one item through gateways, the one with fewer gateways counts, then
    /// the one stored first: a gateway that picks a low node id (the old tie-break) wins
    /// nothing by it.
    #[tokio::test]
    async fn copies_through_gateways_go_by_hops_then_first_seen_never_by_node_id() {
        let inner = bare(Some("ground"), None);
        let from_air = |hops| Origin {
            node: 77,
            name: "vas".into(),
            hops,
            namespace: "rover1".into(),
        };
        let copy = |hops| {
            vec![offer(
                10,
                ItemKind::Function,
                "rover1/vas/arm",
                Some(from_air(hops)),
            )]
        };
        let shown = |inner: &NodeInner| {
            let hidden = inner.shadowed_offers();
            let mut v: Vec<NodeId> = [9, 1, 5]
                .into_iter()
                .filter(|p| inner.peers.by_id.contains_key(p))
                .filter(|p| !hidden.get(p).is_some_and(|h| h.contains(&10)))
                .collect();
            v.sort();
            v
        };
        inner.on_discovery(0, addr(9), hello(9, "gw", "", true));
        declare(&inner, 9, copy(2));
        inner.on_discovery(0, addr(1), hello(1, "low", "", true));
        declare(&inner, 1, copy(2));
        assert_eq!(
            shown(&inner),
            [9],
            "as far: the first seen, not the lowest id"
        );
        inner.on_discovery(0, addr(5), hello(5, "near", "", true));
        declare(&inner, 5, copy(1));
        assert_eq!(shown(&inner), [5], "fewer gateways first");
        inner.cancel.cancel();
    }

    #[tokio::test]
    async fn only_a_gateway_speaks_for_another_node_and_never_as_the_node_itself() {
        let inner = bare(Some("ground"), None);
        inner.on_discovery(0, addr(1), hello(1, "air", "rover1", false));
        inner.on_discovery(0, addr(2), hello(2, "evil", "evil", false));
        inner.on_discovery(0, addr(3), hello(3, "relay", "relay", true));
        let from_air = |hops| Origin {
            node: 1,
            name: "air".into(),
            hops,
            namespace: "rover1".into(),
        };
        // The forged origin: another node's id, 0 hops, from a non-gateway.
        declare(
            &inner,
            2,
            vec![
                offer(
                    10,
                    ItemKind::Variable,
                    "rover1/vas/position",
                    Some(from_air(0)),
                ),
                offer(
                    11,
                    ItemKind::Variable,
                    "rover1/vas/attitude",
                    Some(from_air(1)),
                ),
            ],
        );
        assert!(offered(&inner, 2).is_empty());
        // A gateway: at least one hop, and only names the origin owns.
        declare(
            &inner,
            3,
            vec![
                offer(
                    10,
                    ItemKind::Variable,
                    "rover1/vas/position",
                    Some(from_air(0)),
                ),
                offer(
                    11,
                    ItemKind::Variable,
                    "rover1/vas/attitude",
                    Some(from_air(1)),
                ),
                offer(12, ItemKind::Variable, "ground/fmo/x", Some(from_air(1))),
            ],
        );
        assert_eq!(offered(&inner, 3), ["rover1/vas/attitude"]);
        assert_eq!(inner.policy.counts(0), (0, 4));
        // A gateway our <access> does not name is no gateway.
        let g = bare(
            Some("ground"),
            Some(AccessConfig {
                rules: vec![AccessRule {
                    kind: AccessKind::Gateway,
                    item: "**".into(),
                    from: "trusted/*".into(),
                }],
                closed: vec![],
                trust_claims: false,
            }),
        );
        g.on_discovery(0, addr(3), hello(3, "relay", "relay", true));
        g.on_discovery(0, addr(4), hello(4, "relay", "trusted", true));
        for peer in [3, 4] {
            declare(
                &g,
                peer,
                vec![offer(
                    11,
                    ItemKind::Variable,
                    "rover1/vas/attitude",
                    Some(from_air(1)),
                )],
            );
        }
        assert!(offered(&g, 3).is_empty());
        assert_eq!(offered(&g, 4), ["rover1/vas/attitude"]);
        inner.cancel.cancel();
        g.cancel.cancel();
    }

    #[tokio::test]
    async fn bye_and_a_second_address_count_only_from_the_node_itself() {
        let inner = bare(None, None);
        inner.on_discovery(0, addr(1), hello(1, "air", "rover1", false));
        // A forged Bye from another address: ignored, counted.
        inner.on_discovery(0, addr(9), Message::Bye { node_id: 1 });
        assert!(
            inner.peers.by_id.contains_key(&1),
            "a forged Bye evicted the peer"
        );
        // Heard at a second address on the same link: not mapped, so its Bye is no better.
        inner.on_discovery(0, addr(9), hello(1, "air", "rover1", false));
        assert!(inner.peers.by_addr.get(&(0, addr(9))).is_none());
        inner.on_discovery(0, addr(9), Message::Bye { node_id: 1 });
        assert!(inner.peers.by_id.contains_key(&1));
        assert_eq!(inner.policy.counts(0), (0, 3));
        // The node's own Bye.
        inner.on_discovery(0, addr(1), Message::Bye { node_id: 1 });
        assert!(!inner.peers.by_id.contains_key(&1));
        inner.cancel.cancel();
    }

    /// Found by the structured fuzzer: ids already used by one kind of declaration, declared
    /// again as another kind, were not counted against the cap, so a peer could store more.
    #[tokio::test]
    async fn reusing_ids_across_kinds_does_not_pass_the_cap() {
        let inner = bare(None, None);
        inner.on_discovery(0, addr(1), hello(1, "air", "rover1", false));
        let n = MAX_DECLS_PER_PEER as u32;
        let offers: Vec<Declaration> = (0..n)
            .map(|i| offer(i, ItemKind::Variable, &format!("rover1/s/v{i}"), None))
            .collect();
        declare(&inner, 1, offers);
        let services: Vec<Declaration> = (0..10)
            .map(|i| Declaration::Service {
                id: i,
                name: format!("s{i}"),
            })
            .collect();
        declare(&inner, 1, services);
        let stored = inner.peers.by_id.get(&1).map(|p| p.declarations());
        assert_eq!(stored, Some(MAX_DECLS_PER_PEER));
        inner.cancel.cancel();
    }

    #[tokio::test]
    async fn declarations_per_peer_are_capped_and_a_reset_replaces_them() {
        let inner = bare(None, None);
        inner.on_discovery(0, addr(1), hello(1, "air", "rover1", false));
        let many: Vec<Declaration> = (0..MAX_DECLS_PER_PEER as u32 + 10)
            .map(|i| offer(i + 10, ItemKind::Variable, &format!("rover1/s/v{i}"), None))
            .collect();
        declare(&inner, 1, many);
        let stored = inner.peers.by_id.get(&1).map(|p| p.declarations());
        assert_eq!(stored, Some(MAX_DECLS_PER_PEER));
        assert_eq!(inner.policy.counts(0), (0, 10));
        // A reset batch: the peer's whole state, replacing what we held.
        let known = inner.peers.by_id.get(&1).map_or(0, |p| p.known);
        inner.apply_decl_batch(
            1,
            0,
            known + 5,
            true,
            vec![LoggedDeclaration {
                counter: known + 3,
                decl: offer(1, ItemKind::Variable, "rover1/s/only", None),
            }],
        );
        assert_eq!(offered(&inner, 1), ["rover1/s/only"]);
        assert_eq!(inner.peers.by_id.get(&1).map(|p| p.known), Some(known + 5));
        inner.cancel.cancel();
    }

    #[tokio::test]
    async fn a_publisher_access_does_not_allow_is_never_routed() {
        let access = AccessConfig {
            rules: vec![AccessRule {
                kind: AccessKind::Publish,
                item: "**/manual_control".into(),
                from: "ground/fmo".into(),
            }],
            closed: vec![],
            trust_claims: false,
        };
        let inner = bare(Some("rover1"), Some(access));
        inner.add_interest(Arc::new(LocalInterest {
            id: inner.local.fresh_id(),
            service: 0,
            service_name: "vas".into(),
            kind: ItemKind::Variable,
            pattern: "*/fmo/manual_control".into(),
            ty: TypeInfo::of::<u64>(),
            mailbox: Some(Arc::new(super::super::mailbox::Mailbox::new(true))),
            reported: Default::default(),
            hidden_on: None,
        }));
        inner.on_discovery(0, addr(1), hello(1, "fmo", "ground", false));
        inner.on_discovery(0, addr(2), hello(2, "fmo", "evil", false));
        declare(
            &inner,
            1,
            vec![offer(
                10,
                ItemKind::Variable,
                "ground/fmo/manual_control",
                None,
            )],
        );
        declare(
            &inner,
            2,
            vec![offer(
                10,
                ItemKind::Variable,
                "evil/fmo/manual_control",
                None,
            )],
        );
        let routed = |id: NodeId| {
            inner
                .peers
                .by_id
                .get(&id)
                .and_then(|p| p.routes.get(&10).map(|r| r.len()))
                .unwrap_or(0)
        };
        assert_eq!(routed(1), 1, "the allowed station is routed");
        assert_eq!(routed(2), 0, "the other one is not");
        inner.deliver_remote_run(2, std::iter::once((10, vec![1].into())));
        assert_eq!(
            inner.policy.counts(0),
            (2, 0),
            "declaration and sample denied"
        );
        inner.cancel.cancel();
    }

    #[test]
    fn the_log_is_bounded_in_lines_and_memory() {
        let p = Policy::new(None, 1);
        let t0 = Instant::now();
        for i in 0..LOG_LINES_PER_MINUTE as u64 {
            assert!(p.first_in_a_minute(i, "a", t0));
        }
        assert!(
            !p.first_in_a_minute(u64::MAX, "a", t0),
            "over the minute's budget"
        );
        let t1 = t0 + LOG_EVERY;
        assert!(p.first_in_a_minute(u64::MAX, "a", t1), "a new minute");
        // Memory: keys older than a minute are forgotten when it fills.
        {
            let mut m = lock(&p.logged);
            for i in 0..LOG_MEMORY as u64 {
                m.last.insert((i, "b".into()), t0);
            }
        }
        let t2 = t1 + LOG_EVERY;
        assert!(p.first_in_a_minute(7, "c", t2));
        assert_eq!(
            lock(&p.logged).last.len(),
            1,
            "the old minute was forgotten"
        );
    }
}
