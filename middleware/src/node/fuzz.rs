//! Structure-aware fuzzing of a node's declaration table: a node without links (the one the
//! node modules' tests use) hears Hellos, heartbeats, declaration batches (mostly under the
//! peer's own namespace, some posing as another's, some with an `origin`, some floods past the
//! caps) and Byes from up to four peers at up to six addresses, in random order. After every
//! step it checks the invariants the node promises: per-peer and total declarations within
//! [`MAX_DECLS_PER_PEER`] and [`MAX_DECLS_TOTAL`]; every stored offer owned by its peer's
//! namespace unless it came with an `origin` from a gateway; every stored interest a valid
//! pattern. Reached through [`crate::fuzzing::node_decls`] (feature `fuzzing`).

use std::sync::Arc;

use arbitrary::{Result, Unstructured};

use super::policy::{MAX_DECLS_PER_PEER, MAX_DECLS_TOTAL};
use super::{bare_node, NodeInner};
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
    for p in inner.peers.iter() {
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
    let known = inner.peers.get(&id).map_or(0, |p| p.known);
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
            if let Declaration::Offer { name, .. } = &mut decl {
                *name = owned_name(u, ns)?;
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
