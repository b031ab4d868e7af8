//! Forwarding between links: what makes a node with several links a gateway.
//!
//! The gateway re-declares, on its other links, what the peers of one link want and offer,
//! as items of its own (a pseudo-service named `gateway`):
//! - every interest (subscription) of a peer becomes a forwarded interest declared on the
//!   other links, so publishers there send to the gateway;
//! - a peer's variable or event becomes a forwarded offer on the other links only while a peer
//!   on another link subscribes to it (interest-based: nothing crosses a radio unasked); the
//!   data the gateway receives for it is published again from the forwarded offer, and a
//!   forwarded variable keeps its last value, so a late subscriber is served by the nearest
//!   gateway without crossing the radio again;
//! - functions and file sinks are always forwarded (they are few and callers must find them):
//!   calls are relayed with the caller's deadline (by the call protocol, `node::call`), file
//!   transfers chunk by chunk with the receiver's acknowledgements relayed back, so both stay
//!   end to end.
//!
//! A forwarded item is never declared on the link it came from, and a forwarded offer names
//! its origin node and the gateways crossed, so a node reaching the same item by several paths
//! keeps the shortest (`NodeInner::shadowed_offers`) and nothing is delivered twice.

use std::collections::{HashMap, HashSet};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use dashmap::DashMap;

use super::policy::Refusal;
use super::{lock, LocalInterest, LocalOffer, NodeInner, OfferRole};
use crate::codec::encode_data_message_of_payload;
use crate::link::Outgoing;
use crate::name;
use crate::protocol::{Declaration, ItemKind, Message, NodeId, Origin};
use crate::typeinfo::TypeInfo;

/// Gateways an offer may cross; stops forwarding loops in meshes of gateways.
pub(super) const MAX_HOPS: u8 = 8;

/// Name of the pseudo-service owning the forwarded items.
pub(crate) const SERVICE_NAME: &str = "gateway";

/// An offer of a peer forwarded on our other links.
pub(crate) struct Forwarded {
    pub offer: Arc<LocalOffer>,
    /// When the last value or event passed through.
    pub updated: Mutex<Option<Instant>>,
}

/// A forwarded interest, by where it came from and what it asks for.
#[derive(Clone, PartialEq, Eq, Hash)]
struct InterestKey {
    link: usize,
    kind: ItemKind,
    pattern: String,
    ty: TypeInfo,
}

/// A file transfer relayed through this node.
#[derive(Clone, Copy)]
pub(crate) struct FileRelay {
    /// The sending node (behind one link).
    pub sender: NodeId,
    /// The receiving node (behind another).
    pub receiver: NodeId,
}

/// A gateway's state.
pub(crate) struct Gateway {
    /// Id of the `gateway` pseudo-service.
    pub service: u32,
    /// (peer, its offer id) -> our forwarded copy; read on the data path.
    pub offers: DashMap<(NodeId, u32), Arc<Forwarded>>,
    /// Forwarded interests -> our interest id.
    interests: Mutex<HashMap<InterestKey, u32>>,
    /// Serialises recomputations.
    recompute: Mutex<()>,
    /// File transfers in progress through this node, by transfer id.
    pub files: DashMap<u64, FileRelay>,
    /// The events forwarded to each node, acknowledged or not (flow control).
    pub windows: super::forward_flow::ForwardWindows,
}

impl Gateway {
    pub fn new(service: u32) -> Self {
        Gateway {
            service,
            offers: DashMap::new(),
            interests: Mutex::default(),
            recompute: Mutex::new(()),
            files: DashMap::new(),
            windows: Default::default(),
        }
    }
}

/// A forwarded offer wanted now.
struct WantedOffer {
    kind: ItemKind,
    name: Arc<str>,
    ty: TypeInfo,
    origin: Origin,
    from_link: usize,
}

/// A forwarded item currently cached, for listings.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct ForwardedItem {
    /// Full name.
    pub name: String,
    /// Kind of item.
    pub kind: ItemKind,
    /// The node really offering it.
    pub origin: String,
    /// Age of the newest value or event that passed through (`None` before the first).
    pub age: Option<Duration>,
    /// Whether a last value is cached for late subscribers.
    pub cached: bool,
}

impl NodeInner {
    /// Brings the forwarded items in line with what the peers declare now. Called whenever a
    /// peer's declarations, or the peer table, change.
    pub fn recompute_forwarding(&self) {
        let Some(gw) = &self.gateway else { return };
        let _serialised = lock(&gw.recompute);
        let links = self.links().len();
        let shadowed = self.shadowed_offers();

        // Interests wanted: every subscription of every peer, forwarded onto the other links.
        let mut wanted_interests: HashSet<InterestKey> = HashSet::new();
        // Interests by link, for the offers' interest test below.
        let mut interests_by_link: Vec<(usize, ItemKind, Arc<str>, TypeInfo)> = Vec::new();
        let mut wanted_offers: HashMap<(NodeId, u32), WantedOffer> = HashMap::new();
        for p in self.peers.by_id.iter() {
            for it in p.interests.values() {
                if !matches!(it.kind, ItemKind::Variable | ItemKind::Event) {
                    continue;
                }
                interests_by_link.push((p.link, it.kind, it.name.clone(), it.ty.clone()));
                if links > 1 {
                    wanted_interests.insert(InterestKey {
                        link: p.link,
                        kind: it.kind,
                        pattern: it.name.to_string(),
                        ty: it.ty.clone(),
                    });
                }
            }
        }
        for p in self.peers.by_id.iter() {
            let hidden = shadowed.get(&p.id);
            for (oid, item) in &p.offers {
                if hidden.is_some_and(|h| h.contains(oid)) {
                    continue;
                }
                let (source, hops) = item.source(p.id);
                if source == self.me.id || hops >= MAX_HOPS {
                    continue;
                }
                let wanted = match item.kind {
                    ItemKind::Function | ItemKind::File => links > 1,
                    ItemKind::Variable | ItemKind::Event => {
                        // A pattern wants the items of its type; an exact name of another
                        // type is forwarded anyway, so the refusal reaches the subscriber.
                        interests_by_link.iter().any(|(link, kind, pattern, ty)| {
                            *link != p.link
                                && *kind == item.kind
                                && name::matches(pattern, &item.name)
                                && (ty.accepts(&item.ty) || !name::is_wildcard(pattern))
                        })
                    }
                };
                if !wanted {
                    continue;
                }
                // Never forwarded: what our own `<access>` refuses to deliver.
                if item.denied {
                    continue;
                }
                let (origin_name, origin_namespace) = item.origin.as_ref().map_or_else(
                    || (p.name.to_string(), p.namespace.clone()),
                    |o| (o.name.clone(), o.namespace.clone()),
                );
                wanted_offers.insert(
                    (p.id, *oid),
                    WantedOffer {
                        kind: item.kind,
                        name: item.name.clone(),
                        ty: item.ty.clone(),
                        origin: Origin {
                            node: source,
                            name: origin_name,
                            hops: hops + 1,
                            namespace: origin_namespace,
                        },
                        from_link: p.link,
                    },
                );
            }
        }

        // Withdraw what is no longer wanted (or changed shape).
        let mut withdrawn = Vec::new();
        gw.offers.retain(|key, f| {
            let keep = wanted_offers.get(key).is_some_and(|w| {
                w.kind == f.offer.kind
                    && w.name == f.offer.name
                    && w.ty == f.offer.ty
                    && Some(&w.origin) == f.offer.origin.as_ref()
                    && Some(w.from_link) == f.offer.hidden_on
            });
            if !keep {
                withdrawn.push(f.offer.id);
            }
            keep
        });
        {
            let mut cur = lock(&gw.interests);
            cur.retain(|key, id| {
                let keep = wanted_interests.contains(key);
                if !keep {
                    withdrawn.push(*id);
                }
                keep
            });
        }

        // Add what is new: every item into the tables first, routes once, then declarations
        // (routes before declarations, as for local items).
        let mut added_offers: Vec<(Declaration, Option<usize>)> = Vec::new();
        for (key, w) in wanted_offers {
            if gw.offers.contains_key(&key) {
                continue;
            }
            let id = self.local.fresh_id();
            let role = match w.kind {
                ItemKind::Variable => OfferRole::Variable {
                    last: Mutex::new(None),
                },
                ItemKind::Event => OfferRole::Event,
                ItemKind::Function | ItemKind::File => OfferRole::Relay {
                    origin: key.0,
                    remote_id: key.1,
                },
            };
            let offer = Arc::new(LocalOffer {
                id,
                service: gw.service,
                kind: w.kind,
                name: w.name.clone(),
                ty: w.ty.clone(),
                role,
                remote: Default::default(),
                local: Mutex::default(),
                has_local: Default::default(),
                refused: Mutex::default(),
                origin: Some(w.origin.clone()),
                hidden_on: Some(w.from_link),
            });
            added_offers.push((
                Declaration::Offer {
                    id,
                    service: gw.service,
                    kind: w.kind,
                    name: w.name.to_string(),
                    ty: w.ty,
                    origin: Some(w.origin),
                },
                Some(w.from_link),
            ));
            self.local.offers.insert(id, offer.clone());
            gw.offers.insert(
                key,
                Arc::new(Forwarded {
                    offer,
                    updated: Mutex::new(None),
                }),
            );
        }
        let mut added_interests: Vec<(Declaration, Option<usize>)> = Vec::new();
        {
            let mut cur = lock(&gw.interests);
            for key in wanted_interests {
                if cur.contains_key(&key) {
                    continue;
                }
                let id = self.local.fresh_id();
                self.local.interests.insert(
                    id,
                    Arc::new(LocalInterest {
                        id,
                        service: gw.service,
                        service_name: SERVICE_NAME.into(),
                        kind: key.kind,
                        pattern: key.pattern.clone(),
                        ty: key.ty.clone(),
                        mailbox: None,
                        reported: Mutex::default(),
                        hidden_on: Some(key.link),
                    }),
                );
                added_interests.push((
                    Declaration::Interest {
                        id,
                        service: gw.service,
                        kind: key.kind,
                        pattern: key.pattern.clone(),
                        ty: key.ty.clone(),
                    },
                    Some(key.link),
                ));
                cur.insert(key, id);
            }
        }
        for id in &withdrawn {
            self.local.offers.remove(id);
            self.local.interests.remove(id);
        }
        if added_offers.is_empty() && added_interests.is_empty() && withdrawn.is_empty() {
            return;
        }
        tracing::debug!(
            added = added_offers.len() + added_interests.len(),
            withdrawn = withdrawn.len(),
            "gateway forwarding updated"
        );
        self.recompute_routes();
        // Batches, not a message per item: a change of interest on one side can forward tens
        // of items, each a message of its own over a radio otherwise. The offers reach every
        // peer before the interests do: an interest forwarded to a publisher brings its value
        // or events back at once, and the offer they are forwarded under must be known by
        // then on the other side (or they are dropped there as data for an unknown offer).
        let offers = withdrawn
            .into_iter()
            .map(|id| (Declaration::Withdraw { id }, None))
            .chain(added_offers)
            .collect();
        self.declare_all(offers);
        self.declare_all(added_interests);
    }

    /// Publishes again, on our other links, a value or event that `node` sent for its offer
    /// `id`, if we forward that offer.
    pub fn forward_data(&self, node: NodeId, id: u32, payload: &[u8]) {
        let Some(gw) = &self.gateway else { return };
        let Some(f) = gw.offers.get(&(node, id)).map(|f| f.clone()) else {
            return;
        };
        *lock(&f.updated) = Some(Instant::now());
        match f.offer.kind {
            ItemKind::Variable => {
                let OfferRole::Variable { last } = &f.offer.role else {
                    return;
                };
                let first = {
                    let mut last = lock(last);
                    let first = last.is_none();
                    if first {
                        *last = Some(payload.to_vec());
                    }
                    first
                };
                if !first {
                    self.publish_variable(&f.offer, payload.to_vec());
                    return;
                }
                // The first value through goes on the safe class, as a late joiner's does: it
                // must arrive, and after our declaration of the forwarded offer (a fast value
                // can overtake it on a radio and be dropped as unknown). A variable published
                // once would otherwise never cross.
                self.send_safe_to_subscribers(&f.offer, None, payload);
            }
            ItemKind::Event => self.send_safe_to_subscribers(&f.offer, Some(&gw.windows), payload),
            ItemKind::Function | ItemKind::File => {}
        }
    }

    /// Sends a value, or an event (counted on its node's window in `windows`), of `offer` to
    /// each of its remote subscribers on the safe class.
    fn send_safe_to_subscribers(
        &self,
        offer: &LocalOffer,
        windows: Option<&super::forward_flow::ForwardWindows>,
        payload: &[u8],
    ) {
        let remote = offer.remote.get();
        if remote.is_empty() {
            return;
        }
        let msg = encode_data_message_of_payload(windows.is_some(), offer.id, payload);
        for (r, msg) in remote.iter().zip(super::per_route(msg, remote.len())) {
            let done = windows.map(|w| self.forwarded_event_done(w, r, msg.len()));
            self.send_to(r.link, r.addr, Outgoing::Safe { msg, done });
        }
    }

    /// Whether peer `node` may relay a call or file for `caller`: it is a gateway (see
    /// [`super::Peer::gateway`]), and `caller` is another node at least one gateway away,
    /// within [`MAX_HOPS`].
    pub(super) fn relays_for(&self, node: NodeId, caller: &Origin) -> bool {
        let gateway = self.peers.by_id.get(&node).is_some_and(|p| p.gateway);
        gateway && caller.node != node && (1..MAX_HOPS).contains(&caller.hops)
    }

    /// Whether this gateway may relay a call or file from `node` to `item`'s node: the next
    /// node takes the name we pass on as proven, so where a roster is kept only a peer whose
    /// key proved its namespace and node name (or a proven gateway relaying further) is
    /// relayed; a refusal is counted and logged.
    pub(super) fn may_relay_for(&self, node: NodeId, item: &str) -> bool {
        if self.identity_allows(node) {
            return true;
        }
        let (link, name) = (self.peer_link(node), self.peer_name(node));
        self.policy
            .refuse(link, node, &name, item, Refusal::RelayUnproven);
        false
    }

    /// Who a call or file from `node` (relayed for `caller`, if given) is from, as this
    /// gateway names it to the next node: one gateway further.
    pub(super) fn caller_to_relay(&self, node: NodeId, caller: Option<&Origin>) -> Origin {
        match caller {
            Some(o) => Origin {
                hops: o.hops.saturating_add(1),
                ..o.clone()
            },
            None => {
                let (name, namespace) = self.peers.by_id.get(&node).map_or_else(
                    || (format!("{node:016x}"), String::new()),
                    |p| (p.name.to_string(), p.namespace.clone()),
                );
                Origin {
                    node,
                    name,
                    hops: 1,
                    namespace,
                }
            }
        }
    }

    /// Starts relaying a file offered by `sender` to `receiver`: `offer` is the sender's
    /// FileOffer with the sink rewritten to the receiver's.
    pub fn relay_file_offer(
        &self,
        sender: NodeId,
        receiver: NodeId,
        transfer: u64,
        offer: &Message,
    ) {
        let Some(gw) = &self.gateway else { return };
        gw.files.insert(transfer, FileRelay { sender, receiver });
        if !self.send_safe_to_node(receiver, offer) {
            gw.files.remove(&transfer);
            self.send_safe_to_node(
                sender,
                &Message::FileDone {
                    transfer,
                    verdict: crate::protocol::FileVerdict::Failed(
                        "the receiving node is no longer reachable through the gateway".into(),
                    ),
                },
            );
        }
    }

    /// Relays a file-transfer message of a relayed transfer to the other end; returns whether
    /// it was one. The sender's messages (chunks, cancel) go to the receiver; the receiver's
    /// (accept/progress, verdict) to the sender.
    pub fn relay_file_message(&self, from: NodeId, transfer: u64, msg: &Message) -> bool {
        let Some(gw) = &self.gateway else {
            return false;
        };
        let Some(r) = gw.files.get(&transfer).map(|r| *r) else {
            return false;
        };
        let to = if from == r.sender {
            r.receiver
        } else if from == r.receiver {
            r.sender
        } else {
            return false;
        };
        if matches!(msg, Message::FileDone { .. } | Message::FileCancel { .. }) {
            gw.files.remove(&transfer);
        }
        self.send_safe_to_node(to, msg);
        true
    }

    /// A peer is gone: its forwarding window goes (a catch-up waiting on it ends as the link
    /// fails what was in flight); relayed transfers through it end; a receiver still waiting
    /// for chunks from a lost sender is told the transfer was cancelled (it keeps what it has,
    /// for a resume).
    pub fn gateway_peer_lost(&self, node: NodeId) {
        let Some(gw) = &self.gateway else { return };
        self.forget_forward_window(&gw.windows, node);
        let mut lost = Vec::new();
        gw.files.retain(|transfer, r| {
            let keep = r.sender != node && r.receiver != node;
            if !keep {
                lost.push((*transfer, *r));
            }
            keep
        });
        for (transfer, r) in lost {
            if r.sender == node {
                self.send_safe_to_node(r.receiver, &Message::FileCancel { transfer });
            }
        }
    }

    /// The items this gateway forwards, with the age of what last passed through.
    pub fn forwarded_items(&self) -> Vec<ForwardedItem> {
        let Some(gw) = &self.gateway else {
            return Vec::new();
        };
        let mut v: Vec<ForwardedItem> = gw
            .offers
            .iter()
            .map(|f| ForwardedItem {
                name: f.offer.name.to_string(),
                kind: f.offer.kind,
                origin: f
                    .offer
                    .origin
                    .as_ref()
                    .map(|o| o.name.clone())
                    .unwrap_or_default(),
                age: lock(&f.updated).map(|t| t.elapsed()),
                cached: matches!(&f.offer.role, OfferRole::Variable { last } if lock(last).is_some()),
            })
            .collect();
        v.sort_by(|a, b| a.name.cmp(&b.name));
        v
    }
}
