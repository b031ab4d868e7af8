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
use crate::protocol::NodeId;

/// Declarations (services, offers, interests) stored for one peer; beyond, new ones are
/// refused. Far above a real node (the VAS declares a few dozen).
pub(crate) const MAX_DECLS_PER_PEER: usize = 4096;
/// Declarations stored for all peers together.
pub(crate) const MAX_DECLS_TOTAL: usize = 65_536;
/// Calls of one peer running (or waiting in their function's lane) at once; beyond, `Busy`.
pub(crate) const MAX_CALLS_PER_PEER: usize = 32;
/// Calls of all peers running at once; beyond, `Busy`.
pub(crate) const MAX_CALLS_TOTAL: usize = 256;
/// The longest a caller's remaining time is taken at its word (a peer once asked for 74 days).
pub(crate) const MAX_CALL_TIME: Duration = Duration::from_secs(600);
/// How often the same refusal (peer and item) is logged.
const LOG_EVERY: Duration = Duration::from_secs(60);
/// Refusals remembered for rate-limiting the log; past it, the oldest minute is forgotten and,
/// if still full, refusals are counted but not logged.
const LOG_MEMORY: usize = 4096;

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

/// A node's acceptance policy and what it refused.
pub(crate) struct Policy {
    pub access: Option<AccessConfig>,
    /// By link index.
    counters: Vec<RefusalCounters>,
    logged: Mutex<HashMap<(NodeId, String), Instant>>,
}

impl Policy {
    pub fn new(access: Option<AccessConfig>, links: usize) -> Self {
        Policy {
            access,
            counters: (0..links).map(|_| RefusalCounters::default()).collect(),
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

    /// Counts a refusal on `link` and logs it unless the same (peer, item) was logged within
    /// the last minute.
    pub fn refuse(&self, link: usize, peer: NodeId, peer_name: &str, item: &str, why: Refusal) {
        if let Some(c) = self.counters.get(link) {
            match why {
                Refusal::Denied(_) => c.denied.fetch_add(1, Ordering::Relaxed),
                _ => c.rejected.fetch_add(1, Ordering::Relaxed),
            };
        }
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
        let mut logged = lock(&self.logged);
        let key = (peer, item.to_owned());
        if let Some(at) = logged.get(&key) {
            if now.saturating_duration_since(*at) < LOG_EVERY {
                return false;
            }
        }
        if logged.len() >= LOG_MEMORY && !logged.contains_key(&key) {
            logged.retain(|_, at| now.saturating_duration_since(*at) < LOG_EVERY);
            if logged.len() >= LOG_MEMORY {
                return false;
            }
        }
        logged.insert(key, now);
        true
    }
}

impl super::NodeInner {
    /// Whether peer `node` may do `kind` on our item `item`; a refusal is counted and logged.
    /// An unknown peer is refused when a rule governs `kind`.
    pub fn permitted(&self, node: NodeId, kind: AccessKind, item: &str) -> bool {
        if self.policy.access.is_none() {
            return true;
        }
        let Some((link, namespace, name)) = self
            .peers
            .get(&node)
            .map(|p| (p.link, p.namespace.clone(), p.name.clone()))
        else {
            return !self
                .policy
                .access
                .as_ref()
                .is_some_and(|a| a.governs(kind));
        };
        if self.policy.allows(kind, item, &namespace, &name) {
            return true;
        }
        self.policy
            .refuse(link, node, &name, item, Refusal::Denied(kind));
        false
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

    #[test]
    fn the_log_memory_is_bounded() {
        let p = Policy::new(None, 1);
        let t0 = Instant::now();
        for i in 0..LOG_MEMORY as u64 {
            assert!(p.first_in_a_minute(i, "a", t0));
        }
        assert!(!p.first_in_a_minute(u64::MAX, "a", t0), "full: not logged");
        assert!(p.first_in_a_minute(u64::MAX, "a", t0 + LOG_EVERY * 2));
        assert_eq!(lock(&p.logged).len(), 1, "the old minute was forgotten");
    }
}
