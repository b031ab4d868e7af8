//! Structure-aware fuzzing of a node's declaration table: a node without links (the one the
//! node modules' tests use) hears Hellos, heartbeats, declaration batches (mostly under the
//! peer's own namespace, some posing as another's, some with an `origin`, some floods past the
//! caps) and Byes from up to four peers at up to six addresses, in random order. After every
//! step it checks the invariants the node promises: per-peer and total declarations within
//! [`MAX_DECLS_PER_PEER`] and [`MAX_DECLS_TOTAL`]; every stored offer owned by its peer's
//! namespace unless it came with an `origin` from a gateway; every stored interest a valid
//! pattern; and the routes kept up to date per peer (see
//! [`NodeInner::recompute_routes_of_peer`]) are those a recomputation from scratch makes. The
//! node has offers and interests of its own so that routes exist. Reached through
//! [`crate::fuzzing::node_decls`] (feature `fuzzing`).

use std::sync::{Arc, Mutex};

use arbitrary::{Result, Unstructured};

use super::policy::{MAX_DECLS_PER_PEER, MAX_DECLS_TOTAL};
use super::{bare_node, LocalInterest, LocalOffer, NodeInner, OfferRole};
use crate::link::PeerAddr;
use crate::protocol::gen;
use crate::protocol::{Declaration, ItemKind, LoggedDeclaration, Message};
use crate::typeinfo::TypeInfo;

const NAMESPACES: &[&str] = &["rover1", "ground", "evil", "", "fleet/rover2"];

fn addr(port: u16) -> PeerAddr {
    PeerAddr::Udp(std::net::SocketAddr::from(([127, 0, 0, 1], port)))
}

fn check(inner: &NodeInner) {
    let mut total = 0;
    for p in inner.peers.by_id.iter() {
        let n = p.declarations();
        assert!(
            n <= MAX_DECLS_PER_PEER,
            "peer {} holds {n} declarations",
            p.id
        );
        total += n;
        for o in p.offers.values() {
            if o.origin.is_some() {
                assert!(
                    p.gateway,
                    "a non-gateway's offer {} with an origin stored",
                    o.name
                );
            } else if !p.namespace.is_empty() {
                assert!(
                    o.name.starts_with(&format!("{}/", p.namespace)),
                    "peer of namespace {:?} holds offer {}",
                    p.namespace,
                    o.name
                );
            }
        }
        for i in p.interests.values() {
            assert!(
                crate::name::validate_pattern(&i.name).is_ok(),
                "an invalid pattern {:?} stored",
                i.name
            );
        }
    }
    assert!(total <= MAX_DECLS_TOTAL, "{total} declarations in all");
    let kept = routes(inner);
    inner.recompute_routes();
    assert_eq!(
        kept,
        routes(inner),
        "routes kept per peer differ from routes recomputed from scratch"
    );
}

/// The node's routes, comparable: each local offer's remote subscribers (node and labels),
/// and each peer's routes (offer id, name, publisher, local targets) and shadowed offers.
fn routes(inner: &NodeInner) -> (Vec<String>, Vec<String>) {
    let mut offers: Vec<String> = inner
        .local
        .offers
        .iter()
        .map(|o| {
            let mut subs: Vec<String> = o
                .remote
                .get()
                .iter()
                .map(|r| format!("{:x}{:?}", r.node, r.labels))
                .collect();
            subs.sort();
            format!("{} -> {subs:?}", o.name)
        })
        .collect();
    offers.sort();
    let mut peers: Vec<String> = inner
        .peers
        .by_id
        .iter()
        .map(|p| {
            let mut routes: Vec<String> = p
                .routes
                .iter()
                .map(|(id, r)| {
                    let mut targets: Vec<u32> = r.targets.iter().map(|t| t.id).collect();
                    targets.sort_unstable();
                    format!("{id} {} {} {targets:?}", r.name, r.publisher)
                })
                .collect();
            routes.sort();
            let mut shadowed: Vec<u32> = p.shadowed.iter().copied().collect();
            shadowed.sort_unstable();
            format!("{:x}: {routes:?} shadowed {shadowed:?}", p.id)
        })
        .collect();
    peers.sort();
    (offers, peers)
}

/// Gives the node offers and interests of its own, so peers' declarations make routes both
/// ways: items peers' generated names may match, of the types they may declare.
fn local_items(inner: &Arc<NodeInner>) {
    let kinds = [ItemKind::Variable, ItemKind::Event];
    for (k, kind) in kinds.into_iter().enumerate() {
        for (t, ty) in [TypeInfo::of::<u64>(), TypeInfo::of::<u8>()]
            .into_iter()
            .enumerate()
        {
            let id = inner.local.fresh_id();
            inner.add_offer(Arc::new(LocalOffer {
                id,
                service: 1,
                kind,
                name: format!("me/s/{k}{t}").into(),
                ty: ty.clone(),
                role: match kind {
                    ItemKind::Variable => OfferRole::Variable {
                        last: Mutex::new(Some(vec![1])),
                    },
                    _ => OfferRole::Event,
                },
                remote: Default::default(),
                local: Mutex::default(),
                has_local: Default::default(),
                refused: Mutex::default(),
                origin: None,
                hidden_on: None,
            }));
            for pattern in ["**", "rover1/**", "*/s/*"] {
                inner.add_interest(Arc::new(LocalInterest {
                    id: inner.local.fresh_id(),
                    service: 1,
                    service_name: "s".into(),
                    kind,
                    pattern: pattern.into(),
                    ty: ty.clone(),
                    mailbox: None,
                    reported: Mutex::default(),
                    hidden_on: None,
                }));
            }
        }
    }
}

/// A name mostly under `ns`.
fn owned_name(u: &mut Unstructured<'_>, ns: &str) -> Result<String> {
    let rest = gen::name(u)?;
    Ok(if ns.is_empty() || u.ratio(1u8, 5)? {
        rest
    } else {
        format!("{ns}/{rest}")
    })
}

fn batch(u: &mut Unstructured<'_>, inner: &Arc<NodeInner>, id: u64, ns: &str) -> Result<()> {
    let known = inner.peers.by_id.get(&id).map_or(0, |p| p.known);
    // The ids it declares now, so that withdrawals often take one of them.
    let held: Vec<u32> = inner.peers.by_id.get(&id).map_or_else(Vec::new, |p| {
        p.interests
            .keys()
            .chain(p.offers.keys())
            .chain(p.services.keys())
            .copied()
            .collect()
    });
    let mut entries = Vec::new();
    let mut counter = known;
    let flood = u.ratio(1u8, 16)?;
    if flood {
        // Past the per-peer cap in one go.
        let n = u.int_in_range(1000u32..=MAX_DECLS_PER_PEER as u32 + 200)?;
        for i in 0..n {
            counter += 1;
            entries.push(LoggedDeclaration {
                counter,
                decl: Declaration::Offer {
                    id: 1000 + i,
                    service: 1,
                    kind: ItemKind::Variable,
                    name: format!("{ns}/s/v{i}"),
                    ty: TypeInfo::of::<u64>(),
                    origin: None,
                },
            });
        }
    } else {
        u.arbitrary_loop(Some(1), Some(32), |u| {
            counter += 1;
            let mut decl = gen::declaration(u)?;
            match &mut decl {
                Declaration::Offer { name, .. } => *name = owned_name(u, ns)?,
                // Often one taking our own items (see `local_items`), so subscriptions to
                // them come and go.
                Declaration::Interest { pattern, .. } if u.ratio(1u8, 2)? => {
                    *pattern = (*u.choose(&["**", "me/**", "me/s/*", "*/s/00"])?).to_owned();
                }
                // Often one of what it declares, so subscriptions to our items go as well.
                Declaration::Withdraw { id } if !held.is_empty() && u.ratio(1u8, 2)? => {
                    *id = *u.choose(&held)?;
                }
                _ => {}
            }
            entries.push(LoggedDeclaration { counter, decl });
            Ok(std::ops::ControlFlow::Continue(()))
        })?;
    }
    let after = if u.ratio(7u8, 8)? {
        known
    } else {
        u.int_in_range(0..=known.saturating_add(3))?
    };
    let upto = if u.ratio(7u8, 8)? {
        counter
    } else {
        u.arbitrary()?
    };
    let reset = u.ratio(1u8, 6)?;
    inner.apply_decl_batch(id, after, upto, reset, entries);
    Ok(())
}

/// One case; panics when an invariant fails.
pub(crate) fn run(data: &[u8]) -> Result<()> {
    let rt = tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()
        .expect("a current-thread runtime builds");
    let _guard = rt.enter();
    let mut u = Unstructured::new(data);
    let u = &mut u;
    let inner = bare_node(Some("me"), None);
    local_items(&inner);
    let result = u.arbitrary_loop(Some(1), Some(60), |u| {
        let id = u.int_in_range(1u64..=4)?;
        let ns = NAMESPACES[(id as usize - 1) % NAMESPACES.len()];
        let port = u.int_in_range(1u16..=6)?;
        match u.int_in_range(0u8..=9)? {
            0 | 1 => inner.on_discovery(
                0,
                addr(port),
                Message::Hello {
                    node_id: id,
                    domain: crate::config::DEFAULT_DOMAIN.into(),
                    node: format!("n{id}"),
                    namespace: if u.ratio(1u8, 8)? {
                        (*u.choose(NAMESPACES)?).into()
                    } else {
                        ns.into()
                    },
                    counter: u.int_in_range(0u32..=200)?,
                    lease_ms: u.arbitrary()?,
                    gateway: u.ratio(1u8, 4)?,
                    asks_introduction: u.ratio(1u8, 4)?,
                },
            ),
            2 => inner.on_discovery(0, addr(port), inner.heartbeat()),
            3 => inner.on_discovery(
                0,
                addr(port),
                Message::Heartbeat {
                    node_id: id,
                    domain_hash: super::discovery::domain_hash(crate::config::DEFAULT_DOMAIN),
                    counter: u.int_in_range(0u32..=300)?,
                },
            ),
            4..=8 => batch(u, &inner, id, ns)?,
            _ => inner.on_discovery(0, addr(port), Message::Bye { node_id: id }),
        }
        check(&inner);
        Ok(std::ops::ControlFlow::Continue(()))
    });
    inner.cancel.cancel();
    result
}
