//! Routes: which remote nodes and local subscribers each offer goes to, computed from the
//! declarations on both sides (each item from its shortest path only), and type refusals.

use std::collections::{HashMap, HashSet};
use std::sync::Arc;
use std::time::Instant;

use super::declarations::RemoteItem;
use super::mailbox::{Delivery, TypeMismatch};
use super::variables::last_value;
use super::{flow, lock, LocalInterest, LocalOffer, NodeInner};
use crate::codec::encode_data_message_of_payload;
use crate::link::Outgoing;
use crate::link::PeerAddr;
use crate::name;
use crate::protocol::{ItemKind, Message, NodeId};
use crate::typeinfo::TypeInfo;
use std::sync::Mutex;

/// The remote nodes subscribed to an offer (shared: a raise takes the list with one reference
/// count, not a copy), and how many times the list was replaced, so that a reader that kept
/// the version knows without the lock whether its copy is current.
#[derive(Default)]
pub(crate) struct Routes {
    list: Mutex<Arc<[RemoteSubscriber]>>,
    version: std::sync::atomic::AtomicU64,
    /// Each peer's interests that take the offer (behind `list`): a declared or withdrawn
    /// interest updates its count, without a pass over every interest of the peer.
    takers: Mutex<HashMap<NodeId, Takers>>,
}

/// A peer's interests that take one of our offers: how many, by the service declaring them.
#[derive(Default, Clone)]
pub(crate) struct Takers(std::collections::BTreeMap<u32, u32>);

impl Takers {
    fn add(&mut self, service: u32) {
        *self.0.entry(service).or_default() += 1;
    }

    fn remove(&mut self, service: u32) {
        if let Some(n) = self.0.get_mut(&service) {
            *n -= 1;
            if *n == 0 {
                self.0.remove(&service);
            }
        }
    }
}

impl Routes {
    /// The current list.
    pub fn get(&self) -> Arc<[RemoteSubscriber]> {
        lock(&self.list).clone()
    }

    /// The current list and its version, unless the list is still the one of `version`.
    pub fn changed_since(&self, version: Option<u64>) -> Option<(Arc<[RemoteSubscriber]>, u64)> {
        use std::sync::atomic::Ordering;
        if version == Some(self.version.load(Ordering::Acquire)) {
            return None;
        }
        let list = lock(&self.list);
        // Bumped under this lock: the pair is consistent.
        Some((list.clone(), self.version.load(Ordering::Acquire)))
    }

    /// Peer `node`'s takers as last recorded.
    fn takers_of(&self, node: NodeId) -> Takers {
        lock(&self.takers).get(&node).cloned().unwrap_or_default()
    }

    /// Records peer `node`'s takers.
    fn set_takers(&self, node: NodeId, takers: Takers) {
        let mut all = lock(&self.takers);
        if takers.0.is_empty() {
            all.remove(&node);
        } else {
            all.insert(node, takers);
        }
    }

    /// Replaces every peer's takers.
    fn set_all_takers(&self, takers: HashMap<NodeId, Takers>) {
        *lock(&self.takers) = takers;
    }

    /// Replaces the list by what `make` makes, given the current one.
    pub fn replace(&self, make: impl FnOnce(&[RemoteSubscriber]) -> Arc<[RemoteSubscriber]>) {
        let mut list = lock(&self.list);
        *list = make(&list);
        self.version
            .fetch_add(1, std::sync::atomic::Ordering::Release);
    }
}

/// A remote node subscribed to an offer.
#[derive(Clone)]
pub(crate) struct RemoteSubscriber {
    pub node: NodeId,
    pub node_name: Arc<str>,
    pub link: usize,
    pub addr: PeerAddr,
    /// Services of that node with a matching interest as `node/service`, as raise reports
    /// name them (made once per route change, not per event).
    pub labels: Arc<[String]>,
    /// The peer's [`super::Peer::alive`].
    pub alive: Arc<std::sync::atomic::AtomicBool>,
    /// The peer's [`super::Peer::held`].
    pub held: Arc<flow::StreamHold>,
}

/// Where a remote offer's data goes, with the names its samples carry: the data path takes
/// one reference count per message for all of it.
pub(crate) struct Route {
    /// Local interests it is delivered to.
    pub targets: Box<[Arc<LocalInterest>]>,
    /// The item's full name.
    pub name: Arc<str>,
    /// Its type name.
    pub type_name: Arc<str>,
    /// Its type's fingerprint.
    pub fingerprint: u64,
    /// The node publishing it (the origin behind a gateway).
    pub publisher: Arc<str>,
}

impl std::ops::Deref for Route {
    type Target = [Arc<LocalInterest>];
    fn deref(&self) -> &[Arc<LocalInterest>] {
        &self.targets
    }
}

/// What a batch of a peer's declarations changed, for
/// [`NodeInner::recompute_routes_of_peer`].
#[derive(Default)]
pub(crate) struct PeerChange {
    /// Its services or offers changed, or it was reset: every route it takes part in.
    pub everything: bool,
    /// The interests it declared (`true`) or withdrew, by id, in order (a replaced one is
    /// withdrawn, then declared): only our offers they match can change subscribers.
    pub interests: Vec<(u32, RemoteItem, bool)>,
}

impl PeerChange {
    /// Whether the change can alter whether the peer subscribes to `o`.
    fn concerns(&self, o: &LocalOffer) -> bool {
        self.everything
            || self
                .interests
                .iter()
                .any(|(_, it, _)| kinds_match(o.kind, it.kind) && name::matches(&it.name, &o.name))
    }
}

/// A peer as route computation reads it: a copy, so the peer table is not held meanwhile.
struct PeerView {
    id: NodeId,
    name: Arc<str>,
    link: usize,
    addr: crate::link::PeerAddr,
    services: HashMap<u32, String>,
    interests: Vec<(u32, RemoteItem)>,
    alive: Arc<std::sync::atomic::AtomicBool>,
    held: Arc<super::flow::StreamHold>,
}

impl PeerView {
    /// A copy of `p`, with its interests when `with_interests` (a copy of thousands, for a
    /// peer at the cap).
    fn of(p: &super::Peer, with_interests: bool) -> Self {
        PeerView {
            id: p.id,
            name: p.name.clone(),
            link: p.link,
            addr: p.addr,
            services: p.services.clone(),
            interests: if with_interests {
                p.interests.iter().map(|(k, v)| (*k, v.clone())).collect()
            } else {
                Vec::new()
            },
            alive: p.alive.clone(),
            held: p.held.clone(),
        }
    }
}

/// Whether interest `iid` (`it`) of peer `p` takes our offer `o`. When `declared` (it is new),
/// an exact interest of another type gets a refusal (once per interest) in `refusals`.
fn takes(
    o: &LocalOffer,
    p: &PeerView,
    (iid, it): (u32, &RemoteItem),
    declared: bool,
    refusals: &mut Vec<(usize, crate::link::PeerAddr, Message)>,
) -> bool {
    if !kinds_match(o.kind, it.kind) || !name::matches(&it.name, &o.name) {
        return false;
    }
    if it.ty.accepts(&o.ty) {
        return true;
    }
    if declared && !name::is_wildcard(&it.name) && lock(&o.refused).insert((p.id, iid)) {
        refusals.push((
            p.link,
            p.addr,
            Message::Refused {
                interest: iid,
                name: o.name.to_string(),
                offered: o.ty.clone(),
            },
        ));
    }
    false
}

/// Peer `p` as a subscriber of our offer `o`, given its interests that take `o`.
fn subscriber(p: &PeerView, takers: &Takers) -> Option<RemoteSubscriber> {
    if takers.0.is_empty() {
        return None;
    }
    let mut labels: Vec<String> = Vec::new();
    for service in takers.0.keys() {
        let svc = p
            .services
            .get(service)
            .cloned()
            .unwrap_or_else(|| format!("#{service}"));
        let label = format!("{}/{svc}", p.name);
        if !labels.contains(&label) {
            labels.push(label);
        }
    }
    Some(RemoteSubscriber {
        node: p.id,
        node_name: p.name.clone(),
        link: p.link,
        addr: p.addr,
        labels: labels.into(),
        alive: p.alive.clone(),
        held: p.held.clone(),
    })
}

/// Peer `p`'s interests (all read: `p` was made with them) that take our offer `o`.
fn takers(
    o: &LocalOffer,
    p: &PeerView,
    refusals: &mut Vec<(usize, crate::link::PeerAddr, Message)>,
) -> Takers {
    let mut t = Takers::default();
    if o.hidden_on != Some(p.link) {
        for (iid, it) in &p.interests {
            if takes(o, p, (*iid, it), true, refusals) {
                t.add(it.service);
            }
        }
    }
    t
}

/// Peer `p`'s takers of our offer `o` after `change`, from those recorded before it.
fn takers_after(
    o: &LocalOffer,
    p: &PeerView,
    change: &PeerChange,
    refusals: &mut Vec<(usize, crate::link::PeerAddr, Message)>,
) -> Takers {
    let mut t = o.remote.takers_of(p.id);
    if o.hidden_on != Some(p.link) {
        for (iid, it, declared) in &change.interests {
            if takes(o, p, (*iid, it), *declared, refusals) {
                if *declared {
                    t.add(it.service);
                } else {
                    t.remove(it.service);
                }
            }
        }
    }
    t
}

/// Peer `p`'s routes: each of its offers not `hidden` nor denied, to the local interests
/// taking it.
fn routes_of(
    p: &super::Peer,
    hidden: &HashSet<u32>,
    interests: &[Arc<LocalInterest>],
) -> HashMap<u32, Arc<Route>, crate::sync::SeededHash> {
    p.offers
        .iter()
        .filter(|(oid, item)| !hidden.contains(oid) && !item.denied)
        .map(|(oid, item)| {
            let targets: Box<[Arc<LocalInterest>]> = interests
                .iter()
                .filter(|i| {
                    kinds_match(item.kind, i.kind)
                        && name::matches(&i.pattern, &item.name)
                        && i.ty.accepts(&item.ty)
                })
                .cloned()
                .collect();
            let route = Route {
                targets,
                name: item.name.clone(),
                type_name: item.type_name.clone(),
                fingerprint: item.ty.fingerprint,
                publisher: item.origin_name.clone().unwrap_or_else(|| p.name.clone()),
            };
            (*oid, Arc::new(route))
        })
        .collect()
}

/// One item wherever it is declared from: its source node, kind and name.
type ItemKey = (NodeId, ItemKind, Arc<str>);

/// How far a path to an item is from the best one, compared in this order: the gateways
/// between, when this node first stored it; then the peer and offer id (never reached: no two
/// items share a `seen`). Trust comes before both, at the door: where a roster is kept, only
/// a gateway whose key is listed as one gets a copy stored at all.
type PathRank = (u8, u64, NodeId, u32);

/// The shadowing rule of [`NodeInner::shadowed_offers`], one peer's offers at a time.
#[derive(Default)]
struct Shadowing {
    /// The best path to each item.
    best: HashMap<ItemKey, PathRank>,
    /// The offers to ignore, by peer.
    hidden: HashMap<NodeId, HashSet<u32>>,
}

impl Shadowing {
    /// Takes peer `p`'s offers into account (`me`: our own id).
    fn add(&mut self, me: NodeId, p: &super::Peer) {
        let peer = p.id;
        for (oid, item) in &p.offers {
            let (source, hops) = item.source(peer);
            if source == me {
                self.hidden.entry(peer).or_default().insert(*oid);
                continue;
            }
            let key = (source, item.kind, item.name.clone());
            let cand = (hops, item.seen, peer, *oid);
            match self.best.get(&key) {
                Some(cur) if *cur <= cand => {
                    self.hidden.entry(peer).or_default().insert(*oid);
                }
                Some(cur) => {
                    self.hidden.entry(cur.2).or_default().insert(cur.3);
                    self.best.insert(key, cand);
                }
                None => {
                    self.best.insert(key, cand);
                }
            }
        }
    }
}

fn kinds_match(offer: ItemKind, interest: ItemKind) -> bool {
    offer == interest && matches!(offer, ItemKind::Variable | ItemKind::Event)
}

impl NodeInner {
    /// Recomputes every route from scratch. Declarations change rarely (start-up, a service
    /// coming or going), so clarity beats incremental bookkeeping here, except for a peer's
    /// own declarations arriving: see [`NodeInner::recompute_routes_of_peer`].
    pub fn recompute_routes(&self) {
        let _serialised = lock(&self.routing);
        let interests = self.local.interests_now();
        let offers = self.local.offers_now();
        let peers: Vec<PeerView> = self
            .peers
            .by_id
            .iter()
            .map(|p| PeerView::of(&p, true))
            .collect();
        let mut refusals: Vec<(usize, crate::link::PeerAddr, Message)> = Vec::new();
        let mut late_remote: Vec<(usize, crate::link::PeerAddr, Vec<u8>)> = Vec::new();
        for o in &offers {
            // Local subscribers. A gateway's forwarded offers and forwarded interests only
            // carry traffic between links: they never meet a local item.
            let mut local = Vec::new();
            for i in &interests {
                if o.origin.is_some() || i.hidden_on.is_some() {
                    continue;
                }
                if !kinds_match(o.kind, i.kind) || !name::matches(&i.pattern, &o.name) {
                    continue;
                }
                if !i.ty.accepts(&o.ty) {
                    // A pattern takes the items of its type among those it matches; only an
                    // exact name can be "the wrong type".
                    if !name::is_wildcard(&i.pattern) {
                        i.report_mismatch(&o.name, &self.me.name, &o.ty);
                    }
                    continue;
                }
                local.push(i.clone());
            }
            // Remote subscribers.
            let mut all_takers = HashMap::new();
            let mut remote: Vec<RemoteSubscriber> = Vec::new();
            for p in &peers {
                let t = takers(o, p, &mut refusals);
                remote.extend(subscriber(p, &t));
                if !t.0.is_empty() {
                    all_takers.insert(p.id, t);
                }
            }
            o.remote.set_all_takers(all_takers);
            let last = last_value(o);
            {
                let mut cur = lock(&o.local);
                if let Some(v) = &last {
                    for i in &local {
                        if !cur.iter().any(|c| Arc::ptr_eq(c, i)) {
                            if let Some(m) = &i.mailbox {
                                m.push(o.own_sample(&self.me.name, v.clone(), Instant::now()));
                            }
                        }
                    }
                }
                o.has_local
                    .store(!local.is_empty(), std::sync::atomic::Ordering::Release);
                *cur = local;
            }
            o.remote.replace(|cur| {
                if let Some(v) = &last {
                    for r in &remote {
                        if !cur.iter().any(|c| c.node == r.node) {
                            late_remote.push((
                                r.link,
                                r.addr,
                                encode_data_message_of_payload(false, o.id, v),
                            ));
                        }
                    }
                }
                remote.into()
            });
        }
        // Routes for what peers offer, each item from its shortest path only.
        let shadowed = self.shadowed_offers();
        for mut p in self.peers.by_id.iter_mut() {
            let hidden = shadowed.get(&p.id).cloned().unwrap_or_default();
            p.routes = routes_of(&p, &hidden, &interests);
            p.shadowed = hidden;
        }
        self.send_route_news(refusals, late_remote);
    }

    /// Recomputes what peer `node`'s declarations change (after a batch of them, `change`):
    /// whether it subscribes to each of our offers its change concerns, and, when its offers
    /// or services changed, where its offers go here. An interest declared or withdrawn costs
    /// a match against each of our offers, not a pass over every interest the peer holds: an
    /// insider churning declarations at the caps (16 nodes of 4,000 interests, 200 changes a
    /// second) kept the victim at 89 % of a core when each change recomputed everything. A
    /// fleet's node applies one batch per peer at start and per peer's change after:
    /// recomputing every peer's routes for each made joining a LAN of N nodes cost N³ in all
    /// (at 200 nodes on one host, the batches kept both cores busy and acknowledgements late
    /// for good).
    ///
    /// Exact while no gateway is involved: only a gateway's offers name another node as their
    /// origin, so without one no item is declared by two peers and one peer's offers shadow
    /// nothing of another's. With a gateway (a peer or ourselves), every route is recomputed.
    ///
    /// `routing`: the routing lock, taken before the declarations changed.
    pub(super) fn recompute_routes_of_peer(
        &self,
        node: NodeId,
        change: &PeerChange,
        routing: std::sync::MutexGuard<'_, ()>,
    ) {
        if self.gateway.is_some() || self.peers.by_id.iter().any(|p| p.gateway) {
            // From scratch: nothing counted before matters.
            drop(routing);
            self.recompute_routes();
            return;
        }
        if !change.everything && change.interests.is_empty() {
            // No route changes, but what the peer declares did (a counter, a refused entry):
            // who waits on the node's state sees it.
            self.bump();
            return;
        }
        let offers = self.local.offers_now();
        let mut refusals: Vec<(usize, crate::link::PeerAddr, Message)> = Vec::new();
        let mut late_remote: Vec<(usize, crate::link::PeerAddr, Vec<u8>)> = Vec::new();
        // Read only when an offer of ours is concerned, with a copy of all its interests only
        // when they must all be read again.
        let mut peer: Option<PeerView> = None;
        for o in offers.iter().filter(|o| change.concerns(o)) {
            if peer.is_none() {
                peer = self
                    .peers
                    .by_id
                    .get(&node)
                    .map(|p| PeerView::of(&p, change.everything));
            }
            let Some(peer) = &peer else {
                return;
            };
            let t = if change.everything {
                takers(o, peer, &mut refusals)
            } else {
                takers_after(o, peer, change, &mut refusals)
            };
            let subscriber = subscriber(peer, &t);
            o.remote.set_takers(node, t);
            let had = o.remote.get().iter().any(|r| r.node == node);
            if subscriber.is_none() && !had {
                continue;
            }
            if let (Some(s), false, Some(v)) = (&subscriber, had, last_value(o)) {
                late_remote.push((
                    s.link,
                    s.addr,
                    encode_data_message_of_payload(false, o.id, &v),
                ));
            }
            o.remote.replace(|cur| {
                cur.iter()
                    .filter(|r| r.node != node)
                    .cloned()
                    .chain(subscriber)
                    .collect()
            });
        }
        if let Some(mut p) = self
            .peers
            .by_id
            .get_mut(&node)
            .filter(|_| change.everything)
        {
            let interests = self.local.interests_now();
            let mut shadowing = Shadowing::default();
            shadowing.add(self.me.id, &p);
            let hidden = shadowing.hidden.remove(&node).unwrap_or_default();
            p.routes = routes_of(&p, &hidden, &interests);
            p.shadowed = hidden;
        }
        self.send_route_news(refusals, late_remote);
    }

    /// What a route change owes peers: the type refusals found, and a late joiner's first
    /// value; then the node's state version moves on.
    fn send_route_news(
        &self,
        refusals: Vec<(usize, crate::link::PeerAddr, Message)>,
        late_remote: Vec<(usize, crate::link::PeerAddr, Vec<u8>)>,
    ) {
        for (link, addr, msg) in refusals {
            self.send_safe(link, addr, &msg);
        }
        // A late joiner's first value goes on the safe class: it must arrive (the subscriber
        // gets the last value at once) and after our declarations in the same ordered stream.
        for (link, addr, msg) in late_remote {
            tracing::debug!(%addr, "late joiner served the last value");
            let msg = msg.into();
            self.send_to(link, addr, Outgoing::Safe { msg, done: None });
        }
        self.bump();
    }

    /// The offers of each peer to ignore: where one item (same source node, kind and name) is
    /// declared by several peers (directly and through gateways), only one path counts: the
    /// one with the fewest gateways, then the one this node stored first (never an order a
    /// sender can pick, such as node ids); where a roster is kept, only gateways listed as
    /// such have copies stored at all. Our own items forwarded back to us are ignored.
    pub fn shadowed_offers(&self) -> HashMap<NodeId, HashSet<u32>> {
        let mut shadowing = Shadowing::default();
        for p in self.peers.by_id.iter() {
            shadowing.add(self.me.id, &p);
        }
        shadowing.hidden
    }

    pub fn on_refused(&self, node: NodeId, interest: u32, name: String, offered: TypeInfo) {
        // Through a gateway, the publisher is the node behind it.
        let publisher = self
            .peers
            .by_id
            .get(&node)
            .map(|p| {
                p.offers
                    .values()
                    .find(|o| *o.name == *name)
                    .and_then(|o| o.origin_name.clone())
                    .unwrap_or_else(|| p.name.clone())
                    .to_string()
            })
            .unwrap_or_else(|| format!("{node:016x}"));
        if let Some(i) = self.local.interests.get(&interest) {
            i.report_mismatch(&name, &publisher, &offered);
        }
    }
}

impl LocalInterest {
    /// Reports a type mismatch to the subscriber once per (publisher, name).
    pub fn report_mismatch(&self, name: &str, publisher: &str, offered: &TypeInfo) {
        let key = format!("{publisher}\u{0}{name}");
        if !lock(&self.reported).insert(key) {
            return;
        }
        if let Some(m) = &self.mailbox {
            m.push(Delivery::Refused(TypeMismatch {
                name: name.to_owned(),
                publisher: publisher.to_owned(),
                offered: offered.clone(),
                expected: self.ty.clone(),
            }));
        }
    }
}

/// A set type used for once-only reports.
pub(crate) type ReportedSet = HashSet<String>;
