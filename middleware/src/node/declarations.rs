//! Declarations: the node's own log (what it offers and wants, pushed to peers as it changes
//! and replayed to a newcomer), and applying peers' declarations under our policy.

use std::collections::HashMap;
use std::sync::atomic::{AtomicU32, Ordering};
use std::sync::{Arc, Mutex};

use dashmap::DashMap;

use super::policy::{self, Refusal, MAX_DECLS_PER_PEER, MAX_DECLS_TOTAL};
use super::routes::PeerChange;
use super::{lock, LocalInterest, LocalOffer, NodeInner, OfferRole};
use crate::config::AccessKind;
use crate::name;
use crate::protocol::{Declaration, ItemKind, LoggedDeclaration, Message, NodeId};
use crate::typeinfo::TypeInfo;

/// Declarations sent per DeclBatch message.
const BATCH_ENTRIES: usize = 64;

/// What this node declares: its services, offers and interests by id, and the log its peers
/// learn them from.
pub(crate) struct LocalItems {
    /// The declarations in order (peers are sent what follows the counter they know).
    pub log: Mutex<DeclarationLog>,
    /// The next id to hand out (services, offers and interests share the space).
    next_id: AtomicU32,
    pub services: DashMap<u32, Arc<str>>,
    pub offers: DashMap<u32, Arc<LocalOffer>>,
    pub interests: DashMap<u32, Arc<LocalInterest>>,
}

impl Default for LocalItems {
    fn default() -> Self {
        LocalItems {
            log: Mutex::default(),
            // 0 is no id.
            next_id: AtomicU32::new(1),
            services: DashMap::new(),
            offers: DashMap::new(),
            interests: DashMap::new(),
        }
    }
}

impl LocalItems {
    /// The offers now (a copy: route computations and resends do not hold the map meanwhile).
    pub fn offers_now(&self) -> Vec<Arc<LocalOffer>> {
        self.offers.iter().map(|e| e.value().clone()).collect()
    }

    /// The interests now (a copy, as [`LocalItems::offers_now`]).
    pub fn interests_now(&self) -> Vec<Arc<LocalInterest>> {
        self.interests.iter().map(|e| e.value().clone()).collect()
    }

    /// A new id for a service, offer or interest.
    pub fn fresh_id(&self) -> u32 {
        self.next_id.fetch_add(1, Ordering::Relaxed)
    }
}

/// The node's own declarations, in order; a peer asks for those after the counter it knows.
///
/// Compacted: a withdrawal removes the declaration it withdraws and is not stored itself, so
/// the log holds what is declared now, whatever the churn before. A peer that knows a counter
/// from before the last withdrawal (but not 0: it then holds nothing) gets the whole log
/// instead of what follows it (a reset batch), as it could otherwise miss a withdrawal.
///
/// A declaration hidden on a link (a gateway's forwarded item, never declared back on the link
/// it came from) is not sent there at all: its counter is one the peers there skip, as they
/// skip compacted ones. Over a radio that saves a message per forwarded item.
#[derive(Default)]
pub(crate) struct DeclarationLog {
    pub counter: u32,
    /// Each live declaration with the link it is hidden on.
    entries: Vec<(LoggedDeclaration, Option<usize>)>,
    /// Counter of the newest withdrawal.
    last_withdrawal: u32,
    /// While the newest entries are all hidden on one link: that link, and the counter
    /// before them (the newest its peers were sent). Every other link saw the newest entry.
    hidden_run: Option<(usize, u32)>,
}

/// What a peer is sent to bring it up to date: the entries after `after`, or everything with
/// `reset`.
pub(crate) struct LogView {
    pub after: u32,
    pub upto: u32,
    pub reset: bool,
    pub entries: Vec<LoggedDeclaration>,
}

impl DeclarationLog {
    /// Appends `decl`, hidden on `hidden_on` (a withdrawal is hidden where what it withdraws
    /// was). Returns the entry and the link it is hidden on.
    fn push(
        &mut self,
        decl: Declaration,
        hidden_on: Option<usize>,
    ) -> (LoggedDeclaration, Option<usize>) {
        let before = self.counter;
        self.counter += 1;
        let entry = LoggedDeclaration {
            counter: self.counter,
            decl,
        };
        let hidden_on = if let Declaration::Withdraw { id } = entry.decl {
            let mut hidden = hidden_on;
            self.entries.retain(|(e, h)| {
                let keep = e.decl.id() != id;
                if !keep {
                    hidden = *h;
                }
                keep
            });
            self.last_withdrawal = self.counter;
            hidden
        } else {
            self.entries.push((entry.clone(), hidden_on));
            hidden_on
        };
        self.hidden_run = match (hidden_on, self.hidden_run) {
            (Some(link), Some((run, since))) if run == link => Some((run, since)),
            (Some(link), _) => Some((link, before)),
            (None, _) => None,
        };
        (entry, hidden_on)
    }

    /// The counter of the newest entry a peer on `link` was sent: the next push there
    /// continues from it.
    fn last_seen_on(&self, link: usize) -> u32 {
        match self.hidden_run {
            Some((run, since)) if run == link => since,
            _ => self.counter,
        }
    }

    /// Live declarations held.
    #[cfg(test)]
    fn len(&self) -> usize {
        self.entries.len()
    }

    /// What a peer on `link` that knows our declarations up to `since` is sent.
    pub fn view(&self, link: usize, since: u32) -> LogView {
        // A peer that knows nothing yet (0) holds nothing a withdrawal could leave behind.
        let reset = since > 0 && (since < self.last_withdrawal || since > self.counter);
        let after = if reset { 0 } else { since };
        LogView {
            after,
            upto: self.counter,
            reset,
            entries: self
                .entries
                .iter()
                .filter(|(e, hidden)| e.counter > after && *hidden != Some(link))
                .map(|(e, _)| e.clone())
                .collect(),
        }
    }
}

/// A remote offer or interest.
#[derive(Debug, Clone)]
pub(crate) struct RemoteItem {
    pub service: u32,
    pub kind: ItemKind,
    /// Full name (offers) or pattern (interests).
    pub name: Arc<str>,
    pub ty: TypeInfo,
    /// `ty.name`, shared with every sample delivered from this item.
    pub type_name: Arc<str>,
    /// For an offer forwarded by a gateway: the node that really offers it.
    pub origin: Option<crate::protocol::Origin>,
    /// The origin's name, shared with every sample delivered from this item.
    pub origin_name: Option<Arc<str>>,
    /// A variable or event whose publisher our `<access>` rules do not let publish it: never
    /// routed to a subscriber.
    pub denied: bool,
    /// When this node first stored it, as a position in the order everything was stored
    /// ([`first_seen`]): of two copies of one item through gateways equally trusted and as
    /// far, the first seen wins (never the one whose sender picked the lowest node id).
    pub seen: u64,
}

/// The next position in the order remote items are stored (one order for the process: within
/// a node it is the node's order).
fn first_seen() -> u64 {
    static NEXT: std::sync::atomic::AtomicU64 = std::sync::atomic::AtomicU64::new(0);
    NEXT.fetch_add(1, std::sync::atomic::Ordering::Relaxed)
}

impl RemoteItem {
    /// The node really offering this item when declared by `peer`, and how many gateways lie
    /// between (0 when `peer` offers it itself).
    pub fn source(&self, peer: NodeId) -> (NodeId, u8) {
        self.origin.as_ref().map_or((peer, 0), |o| (o.node, o.hops))
    }
}

/// Checks the name a peer declares as the API checks ours: a plain name for a service or an
/// offer, a pattern for an interest, each at most [`name::MAX_NAME_LEN`] bytes.
fn check_declared_name(decl: &Declaration) -> Result<(), name::NameParseError> {
    match decl {
        Declaration::Service { name, .. } | Declaration::Offer { name, .. } => {
            name::validate_name(name)
        }
        Declaration::Interest { pattern, .. } => name::validate_pattern(pattern),
        Declaration::Withdraw { .. } => Ok(()),
    }
}

/// Declarations as batches of [`BATCH_ENTRIES`], or one empty batch when there are none, so
/// the peer knows it is up to date. Each batch continues where the previous one ended; the last
/// one covers up to the log's counter.
fn batches(view: LogView) -> Vec<Message> {
    let mut after = view.after;
    let mut reset = view.reset;
    let chunks: Vec<&[LoggedDeclaration]> = if view.entries.is_empty() {
        vec![&[]]
    } else {
        view.entries.chunks(BATCH_ENTRIES).collect()
    };
    let last = chunks.len() - 1;
    let mut out = Vec::with_capacity(chunks.len());
    for (k, chunk) in chunks.into_iter().enumerate() {
        let upto = if k == last {
            view.upto
        } else {
            chunk.last().map_or(after, |e| e.counter)
        };
        out.push(Message::DeclBatch {
            after,
            upto,
            reset,
            entries: chunk.to_vec(),
        });
        after = upto;
        reset = false;
    }
    out
}

impl NodeInner {
    /// Appends a declaration to the log and pushes it to every known peer but those on
    /// `hidden_on`.
    pub fn declare(&self, decl: Declaration, hidden_on: Option<usize>) {
        self.declare_all(vec![(decl, hidden_on)]);
    }

    /// Appends declarations to the log, in order, and pushes them to every known peer in one
    /// batch each, of those its link sees (none to a peer whose link sees none of them).
    pub fn declare_all(&self, decls: Vec<(Declaration, Option<usize>)>) {
        if decls.is_empty() {
            return;
        }
        // The log stays locked while the delta is pushed: see `introduce_locked`.
        let mut log = lock(&self.local.log);
        // Each peer's batch continues from the last entry its link saw.
        let targets: Vec<_> = self
            .peers
            .by_id
            .iter()
            .map(|p| (p.link, p.addr, log.last_seen_on(p.link)))
            .collect();
        let pushed: Vec<_> = decls
            .into_iter()
            .map(|(decl, hidden_on)| log.push(decl, hidden_on))
            .collect();
        for (link, addr, after) in targets {
            let entries: Vec<LoggedDeclaration> = pushed
                .iter()
                .filter(|(_, hidden)| *hidden != Some(link))
                .map(|(e, _)| e.clone())
                .collect();
            if entries.is_empty() {
                continue;
            }
            let view = LogView {
                after,
                upto: log.counter,
                reset: false,
                entries,
            };
            self.send_batches(link, addr, view);
        }
    }

    /// Sends a peer our Hello, then every declaration we have, with the log locked by the
    /// caller (who registered the peer under the same lock), all in one sequence: whatever we
    /// send it later (a late joiner's value, events, replies), even from another task answering
    /// the peer's own declarations (which can arrive as soon as our Hello did), comes after the
    /// declarations that give its ids a meaning.
    pub fn introduce_locked(&self, log: &DeclarationLog, link: usize, addr: crate::link::PeerAddr) {
        let mut msgs = vec![self.hello_at(link, log.counter)];
        msgs.extend(batches(log.view(link, 0)));
        self.send_safe_in_sequence(link, addr, &msgs);
    }

    /// Sends declarations as [`batches`] makes them, in one sequence.
    fn send_batches(&self, link: usize, addr: crate::link::PeerAddr, view: LogView) {
        self.send_safe_in_sequence(link, addr, &batches(view));
    }

    pub fn counter(&self) -> u32 {
        lock(&self.local.log).counter
    }

    pub fn add_offer(&self, offer: Arc<LocalOffer>) {
        let decl = Declaration::Offer {
            id: offer.id,
            service: offer.service,
            kind: offer.kind,
            name: offer.name.to_string(),
            ty: offer.ty.clone(),
            origin: offer.origin.clone(),
        };
        let hidden_on = offer.hidden_on;
        self.local.offers.insert(offer.id, offer);
        // Routes first: once peers learn of the offer they may act on it at once.
        self.recompute_routes();
        self.declare(decl, hidden_on);
    }

    pub fn add_interest(&self, interest: Arc<LocalInterest>) {
        let decl = Declaration::Interest {
            id: interest.id,
            service: interest.service,
            kind: interest.kind,
            pattern: interest.pattern.clone(),
            ty: interest.ty.clone(),
        };
        let hidden_on = interest.hidden_on;
        self.local.interests.insert(interest.id, interest);
        // Routes first: a publisher learning of this interest answers with its last value at
        // once, and that value must find the interest routed when it arrives.
        self.recompute_routes();
        self.declare(decl, hidden_on);
    }

    /// Withdraws a service, offer or interest.
    pub fn withdraw(&self, id: u32) {
        let mut any = self.local.services.remove(&id).is_some();
        if let Some((_, o)) = self.local.offers.remove(&id) {
            if let OfferRole::File { mailbox, .. } = &o.role {
                mailbox.close();
            }
            any = true;
        }
        if let Some((_, i)) = self.local.interests.remove(&id) {
            if let Some(m) = &i.mailbox {
                m.close();
            }
            any = true;
        }
        if any && !self.cancel.is_cancelled() {
            self.declare(Declaration::Withdraw { id }, None);
            self.recompute_routes();
        }
    }

    /// Closes every subscription's and file sink's mailbox (the node is stopping): a receiver
    /// waiting on one gets `Closed` instead of waiting for good.
    pub fn close_mailboxes(&self) {
        for i in self.local.interests.iter() {
            if let Some(m) = &i.mailbox {
                m.close();
            }
        }
        for o in self.local.offers.iter() {
            if let OfferRole::File { mailbox, .. } = &o.role {
                mailbox.close();
            }
        }
    }

    /// Answers a peer's request with our declarations after `since` (an empty batch when
    /// there are none, so it knows it is up to date).
    pub fn answer_decl_request(&self, node: NodeId, since: u32) {
        let Some((link, addr)) = self.peers.by_id.get(&node).map(|p| (p.link, p.addr)) else {
            return;
        };
        // Under the log's lock, as `declare` pushes its deltas: none can overtake the answer.
        let log = lock(&self.local.log);
        self.send_batches(link, addr, log.view(link, since));
    }

    /// Applies a peer's declarations: checks each against our policy (names well formed and
    /// owned, origins only from gateways, caps), and recomputes routes when anything changed.
    pub fn apply_decl_batch(
        &self,
        node: NodeId,
        after: u32,
        upto: u32,
        reset: bool,
        mut entries: Vec<LoggedDeclaration>,
    ) {
        entries.sort_by_key(|e| e.counter);
        // Held from the change to the peer's declarations until the routes follow it: a
        // recomputation from scratch in between would count the change, and the incremental
        // update after it would count it again.
        let routing = lock(&self.routing);
        // Facts about the other peers, gathered before this peer's entry is locked (the
        // peer table must not be read while one of its entries is held for writing).
        // The others' namespaces matter only to a peer without one (it owns the names no
        // namespace takes) or to a gateway (its origins' namespaces): copying them for every
        // batch of every peer cost a fleet's node N² copies at start.
        let Some(reads_namespaces) = self
            .peers
            .by_id
            .get(&node)
            .map(|p| p.namespace.is_empty() || p.gateway)
        else {
            return;
        };
        let mut namespaces: Vec<String> = self.me.namespace.iter().cloned().collect();
        let mut direct: HashMap<NodeId, String> = HashMap::new();
        let mut total = 0usize;
        for p in self.peers.by_id.iter() {
            if p.id != node {
                if reads_namespaces {
                    namespaces.push(p.namespace.clone());
                    direct.insert(p.id, p.namespace.clone());
                }
                total += p.declarations();
            }
        }
        let mut changed = false;
        // What the routes must be recomputed for (see `recompute_routes_of_peer`).
        let mut change = PeerChange::default();
        let mut request = None;
        let mut refusals: Vec<(usize, String, Refusal)> = Vec::new();
        let (peer_name, peer_link);
        {
            let Some(mut p) = self.peers.by_id.get_mut(&node) else {
                return;
            };
            peer_name = p.name.clone();
            peer_link = p.link;
            // When each offer was first stored, kept through a reset and a re-declaration of
            // the same item: its copy through a gateway keeps its place among the others.
            let mut previous: HashMap<u32, RemoteItem> = HashMap::new();
            if reset && after == 0 {
                p.services.clear();
                previous = std::mem::take(&mut p.offers);
                p.interests.clear();
                p.routes.clear();
                p.known = 0;
                changed = true;
                change.everything = true;
            }
            let gap = after > p.known;
            if !gap {
                for e in entries {
                    if e.counter <= p.known || e.counter > upto {
                        continue;
                    }
                    p.known = e.counter;
                    changed = true;
                    // A peer's names are checked as ours are: a malformed or oversized one is
                    // skipped (its counter still counts, so no gap is asked for again).
                    if let Err(err) = check_declared_name(&e.decl) {
                        self.policy
                            .dropped
                            .bad_declarations
                            .fetch_add(1, std::sync::atomic::Ordering::Relaxed);
                        tracing::debug!(peer = %p.name, error = %err, "declaration with a bad name skipped");
                        continue;
                    }
                    let id = e.decl.id();
                    // Whether it adds an entry to the map it goes into: an id already held in
                    // another map (a service id reused for an offer) still adds one, so it
                    // counts against the cap (the structured fuzzer found a peer going past
                    // the cap that way).
                    let adds = match &e.decl {
                        Declaration::Service { .. } => !p.services.contains_key(&id),
                        Declaration::Offer { .. } => !p.offers.contains_key(&id),
                        Declaration::Interest { .. } => !p.interests.contains_key(&id),
                        Declaration::Withdraw { .. } => false,
                    };
                    if adds
                        && (p.declarations() >= MAX_DECLS_PER_PEER
                            || total + p.declarations() >= MAX_DECLS_TOTAL)
                    {
                        refusals.push((
                            p.link,
                            "declarations".to_owned(),
                            Refusal::TooManyDeclarations,
                        ));
                        continue;
                    }
                    match e.decl {
                        Declaration::Service { id, name } => {
                            p.services.insert(id, name);
                            change.everything = true;
                        }
                        Declaration::Offer {
                            id,
                            service,
                            kind,
                            name,
                            ty,
                            origin,
                        } => {
                            if let Err(why) = self.offer_acceptable(
                                &p,
                                &name,
                                origin.as_ref(),
                                &namespaces,
                                &direct,
                            ) {
                                refusals.push((p.link, name, why));
                                continue;
                            }
                            let (pub_ns, pub_node) = origin
                                .as_ref()
                                .map_or((p.namespace.as_str(), &*p.name), |o| {
                                    (o.namespace.as_str(), o.name.as_str())
                                });
                            let denied = matches!(kind, ItemKind::Variable | ItemKind::Event)
                                && !self.policy.allows(
                                    AccessKind::Publish,
                                    &name,
                                    pub_ns,
                                    pub_node,
                                );
                            if denied {
                                refusals.push((
                                    p.link,
                                    name.clone(),
                                    Refusal::Denied(AccessKind::Publish),
                                ));
                            }
                            change.everything = true;
                            let same = |o: &RemoteItem| {
                                o.kind == kind
                                    && *o.name == *name
                                    && o.origin.as_ref().map(|o| o.node)
                                        == origin.as_ref().map(|o| o.node)
                            };
                            let seen = p
                                .offers
                                .get(&id)
                                .or_else(|| previous.get(&id))
                                .filter(|o| same(o))
                                .map_or_else(first_seen, |o| o.seen);
                            p.offers.insert(
                                id,
                                RemoteItem {
                                    service,
                                    kind,
                                    name: name.into(),
                                    type_name: ty.name.as_str().into(),
                                    ty,
                                    origin_name: origin.as_ref().map(|o| o.name.as_str().into()),
                                    origin,
                                    denied,
                                    seen,
                                },
                            );
                        }
                        Declaration::Interest {
                            id,
                            service,
                            kind,
                            pattern,
                            ty,
                        } => {
                            let item = RemoteItem {
                                service,
                                kind,
                                name: pattern.into(),
                                type_name: ty.name.as_str().into(),
                                ty,
                                origin: None,
                                origin_name: None,
                                denied: false,
                                seen: first_seen(),
                            };
                            let replaced = p.interests.insert(id, item.clone());
                            change
                                .interests
                                .extend(replaced.map(|old| (id, old, false)));
                            change.interests.push((id, item, true));
                        }
                        Declaration::Withdraw { id } => {
                            change.everything |= p.services.remove(&id).is_some();
                            change.everything |= p.offers.remove(&id).is_some();
                            change
                                .interests
                                .extend(p.interests.remove(&id).map(|old| (id, old, false)));
                            p.routes.remove(&id);
                        }
                    }
                }
                // Counters up to `upto` that no entry carried were compacted away.
                if upto > p.known {
                    p.known = upto;
                    changed = true;
                }
            }
            let stale = p.requested.is_none_or(|t| t.elapsed() > self.me.heartbeat);
            if gap && stale {
                p.requested = Some(tokio::time::Instant::now());
                request = Some(p.known);
            } else if !gap {
                p.requested = None;
            }
        }
        for (link, item, why) in refusals {
            self.policy.refuse(link, node, &peer_name, &item, why);
        }
        let _ = peer_link;
        tracing::debug!(peer = format_args!("{node:016x}"), changed, gap_request = ?request, "declarations applied");
        if let Some(since) = request {
            self.send_safe_to_node(node, &Message::DeclRequest { since });
        }
        if changed {
            self.recompute_routes_of_peer(node, &change, routing);
            self.recompute_forwarding();
        }
    }

    /// Whether peer `p` may offer `name`: a plain offer only under its own namespace; an offer
    /// on behalf of another node (`origin`) only from a gateway, at least one hop away, and
    /// under the origin's namespace (the one we know when we reach the origin directly too).
    fn offer_acceptable(
        &self,
        p: &super::Peer,
        name: &str,
        origin: Option<&crate::protocol::Origin>,
        namespaces: &[String],
        direct: &HashMap<NodeId, String>,
    ) -> Result<(), Refusal> {
        let Some(o) = origin else {
            return if policy::owns(&p.namespace, name, namespaces) {
                Ok(())
            } else {
                Err(Refusal::NotOwned)
            };
        };
        if !p.gateway || o.hops == 0 || o.node == p.id {
            return Err(Refusal::ForeignOrigin);
        }
        if o.node == self.me.id {
            // Our own item forwarded back: kept (and ignored by the shadowing rule).
            return Ok(());
        }
        let ns = direct.get(&o.node).unwrap_or(&o.namespace);
        let others: Vec<String> = namespaces.iter().filter(|n| *n != ns).cloned().collect();
        if policy::owns(ns, name, &others) {
            Ok(())
        } else {
            Err(Refusal::NotOwned)
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_peers_declared_names_are_checked_like_ours() {
        let interest = |pattern: &str| Declaration::Interest {
            id: 1,
            service: 1,
            kind: ItemKind::Event,
            pattern: pattern.into(),
            ty: TypeInfo::of::<u8>(),
        };
        let offer = |name: &str| Declaration::Offer {
            id: 1,
            service: 1,
            kind: ItemKind::Event,
            name: name.into(),
            ty: TypeInfo::of::<u8>(),
            origin: None,
        };
        assert!(check_declared_name(&interest("*/vas/**")).is_ok());
        assert!(check_declared_name(&offer("rover1/vas/position")).is_ok());
        // The attacker's pattern: 2,001 segments, 6 KB.
        let huge = format!("{}zz", "**/".repeat(2000));
        assert!(matches!(
            check_declared_name(&interest(&huge)),
            Err(name::NameParseError::TooLong(_))
        ));
        assert!(
            check_declared_name(&offer("rover1/vas/*")).is_err(),
            "no wildcard offer"
        );
        assert!(check_declared_name(&interest("a//b")).is_err());
        assert!(check_declared_name(&Declaration::Service {
            id: 1,
            name: "bad name".into()
        })
        .is_err());
    }

    #[test]
    fn the_log_holds_only_what_is_declared_and_replays_it_with_a_reset_after_a_withdrawal() {
        let mut log = DeclarationLog::default();
        let svc = |id| Declaration::Service {
            id,
            name: format!("s{id}"),
        };
        // A service coming and going a thousand times leaves nothing behind.
        for id in 1..=1000 {
            log.push(svc(id), None);
            log.push(Declaration::Withdraw { id }, None);
        }
        log.push(svc(5000), None);
        assert_eq!((log.len(), log.counter), (1, 2001));
        // A new peer: the whole (one-entry) log; it holds nothing to reset.
        let v = log.view(0, 0);
        assert!(!v.reset);
        assert_eq!((v.after, v.upto, v.entries.len()), (0, 2001, 1));
        // A peer up to date but for the last declaration: just that one.
        let v = log.view(0, 2000);
        assert!(!v.reset);
        assert_eq!((v.after, v.upto), (2000, 2001));
        assert_eq!(v.entries[0].decl.id(), 5000);
        // A peer from before the last withdrawal could miss it: a reset.
        let v = log.view(0, 1500);
        assert!(v.reset);
        // A counter from the future (a confused peer): a reset too.
        assert!(log.view(0, 9999).reset);
        // Hidden on link 1: not there at all (its counter skipped), the declaration elsewhere.
        log.push(svc(6000), Some(1));
        let on1 = log.view(1, 2001);
        assert_eq!((on1.upto, on1.entries.len()), (2002, 0));
        assert_eq!(log.view(0, 2001).entries[0].decl, svc(6000));
        // A push continues from the last entry the link saw: link 1 never saw 2002.
        assert_eq!((log.last_seen_on(0), log.last_seen_on(1)), (2002, 2001));
        // Its withdrawal is hidden where it was.
        let (_, hidden) = log.push(Declaration::Withdraw { id: 6000 }, None);
        assert_eq!(hidden, Some(1));
        assert_eq!((log.last_seen_on(0), log.last_seen_on(1)), (2003, 2001));
        log.push(svc(7000), None);
        assert_eq!((log.last_seen_on(0), log.last_seen_on(1)), (2004, 2004));
    }
}
