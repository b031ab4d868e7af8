//! The node: one per process. Holds the local services and their declarations, the peer table,
//! the routes (which peer wants which offer) and the links, and dispatches what arrives.
//!
//! Local deliveries go straight into the local subscribers' mailboxes; a message goes to a link
//! only where a remote node declared a matching interest (interest-based routing).

pub(crate) mod calls;
pub(crate) mod data;
pub(crate) mod declarations;
pub(crate) mod discovery;
pub(crate) mod events;
pub(crate) mod files;
pub(crate) mod flow;
mod forward_flow;
#[cfg(feature = "fuzzing")]
pub(crate) mod fuzz;
pub(crate) mod gateway;
pub(crate) mod health;
pub(crate) mod identity_check;
pub(crate) mod loans;
pub(crate) mod mailbox;
pub(crate) mod path_switch;
pub(crate) mod policy;
pub(crate) mod reassembly;
pub(crate) mod routes;
mod variables;

use std::collections::HashMap;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex, OnceLock, Weak};
use std::time::Duration;

// The node's clock for leases and peers' timing: tokio's, so timer logic runs on paused time in
// tests (outside a paused runtime it is the system's monotonic clock).
use tokio::time::Instant;

use tokio::sync::watch;
use tokio_util::sync::CancellationToken;
use tokio_util::task::TaskTracker;

use crate::codec::{decode_message, encode_message};
use crate::link::{Link, LinkHandler, Outgoing, PeerAddr, Precedence};
use crate::protocol::{tag, ItemKind, Message, NodeId, Origin};
use crate::sync::SeededHash;
use crate::typeinfo::TypeInfo;
use mailbox::{Encoded, Mailbox};
pub(crate) use routes::{RemoteSubscriber, Route, Routes};

pub(crate) use crate::sync::lock;

/// A boxed future returned by function handlers.
pub(crate) type BoxFuture<T> = std::pin::Pin<Box<dyn std::future::Future<Output = T> + Send>>;

/// What an offer does with what it is given.
pub(crate) enum OfferRole {
    /// A variable: keeps the last value for late joiners.
    Variable { last: Mutex<Option<Vec<u8>>> },
    /// An event publisher.
    Event,
    /// A function provider.
    Function { handler: calls::RawHandler },
    /// A file sink: its directory, limits and counters, and the files stored.
    File {
        state: Arc<files::SinkState>,
        mailbox: Arc<files::SinkMailbox>,
    },
    /// A gateway's stand-in for a function or file sink of a node behind another link: calls
    /// and transfers are relayed to offer `remote_id` of node `origin`.
    Relay { origin: NodeId, remote_id: u32 },
}

/// Something this node offers (publishes, provides, accepts).
pub(crate) struct LocalOffer {
    pub id: u32,
    pub service: u32,
    pub kind: ItemKind,
    pub name: Arc<str>,
    pub ty: TypeInfo,
    pub role: OfferRole,
    /// Remote nodes with a matching interest of the same type.
    pub remote: Routes,
    /// Local interests with a matching pattern of the same type.
    pub local: Mutex<Vec<Arc<LocalInterest>>>,
    /// Whether `local` has any (read on every raise without taking the lock).
    pub has_local: std::sync::atomic::AtomicBool,
    /// (node, interest) pairs already told that the types differ.
    pub refused: Mutex<std::collections::HashSet<(NodeId, u32)>>,
    /// For an offer a gateway forwards: the node that really offers it.
    pub origin: Option<Origin>,
    /// A forwarded offer is not declared on the link it came from.
    pub hidden_on: Option<usize>,
}

/// Something this node wants: a subscription or a function it calls.
pub(crate) struct LocalInterest {
    pub id: u32,
    pub service: u32,
    pub service_name: Arc<str>,
    pub kind: ItemKind,
    pub pattern: String,
    pub ty: TypeInfo,
    pub mailbox: Option<Arc<Mailbox>>,
    /// Type mismatches already reported to the subscriber.
    pub reported: Mutex<routes::ReportedSet>,
    /// A gateway's forwarded interest is not declared on the link it came from.
    pub hidden_on: Option<usize>,
}

/// The parts of one registration's identity handshake the pair's keys are made of.
#[derive(Default)]
pub(crate) struct Handshake {
    pub ours: Option<[u8; 16]>,
    pub theirs: Option<[u8; 16]>,
    pub agreement: Option<[u8; 32]>,
}

/// What this node knows of a remote node.
pub(crate) struct Peer {
    pub id: NodeId,
    pub name: Arc<str>,
    pub namespace: String,
    /// Whether its Hello says it forwards and our `<access>` rules let a node of its name do
    /// so: a claim, which a node keeping a roster takes only from a key listed as a gateway.
    pub claims_gateway: bool,
    /// Whether it may declare offers of other nodes (`origin`) and relay their calls and
    /// files: it claims to, and where a roster is kept its key proved to be listed as a
    /// gateway ([`crate::identity::Grant::gateway`]).
    pub gateway: bool,
    pub link: usize,
    pub addr: PeerAddr,
    /// When its last heartbeat or Hello arrived.
    pub last_seen: Instant,
    /// When anything last arrived from it, in ms since the node's epoch (updated on the data
    /// path without the peer table's write lock): a peer whose heartbeats are lost on a busy,
    /// lossy radio is still alive while its data comes through.
    pub heard_ms: AtomicU64,
    pub lease: Duration,
    /// Declarations applied up to this counter.
    pub known: u32,
    /// When its Hello made it a peer.
    pub since: Instant,
    /// It showed that it receives at its address (it acknowledged a session of ours:
    /// [`crate::link::Link::answered`]), which a forged source address cannot: with its
    /// identity proven where a roster is kept, never pushed out of a full peer table.
    pub confirmed: std::sync::atomic::AtomicBool,
    /// When declarations were last requested, if an answer is outstanding.
    pub requested: Option<Instant>,
    pub services: HashMap<u32, String>,
    pub offers: HashMap<u32, declarations::RemoteItem>,
    pub interests: HashMap<u32, declarations::RemoteItem>,
    /// Offers of this peer ignored because the same item is reached by a shorter path (a
    /// gateway's copy of an offer we also get directly, or our own offer forwarded back).
    pub shadowed: std::collections::HashSet<u32>,
    /// Local interests each remote offer is delivered to.
    /// Shared so the data path takes a reference count, not a copy, per message.
    pub routes: HashMap<u32, Arc<Route>, SeededHash>,
    /// The keys we share with it, once its proof bound its key agreement half to a listed
    /// identity key (`None` before, and where no roster is kept).
    pub pair: Option<Arc<crate::identity::PairKeys>>,
    /// What its identity key is listed for: `None` when this node checks no identities,
    /// nothing until a valid proof arrives.
    pub authenticated: Option<crate::identity::Grant>,
    /// The nonce of our identity challenge to it, until a proof answers it (`None` when this
    /// node checks no identities, or once answered).
    pub challenge: Option<[u8; 16]>,
    /// The nonces of this registration's handshake: of our challenge to it (kept once
    /// answered), of its challenge to us; and its key agreement half, once its proof verified
    /// for what it announces. With all three, the pair's keys ([`Peer::pair`]).
    pub handshake: Handshake,
    /// Cleared when the peer is dropped: routes copied before that (a raise in progress)
    /// see it without a table lookup and fail at once instead of sending.
    pub alive: Arc<std::sync::atomic::AtomicBool>,
    /// What its last [`Message::Flow`] holds back: streams to it (of the offers it named)
    /// wait while its event subscribers are behind.
    pub held: Arc<flow::StreamHold>,
    /// When we last introduced ourselves again because it said it does not know us.
    pub introduced_again: Option<Instant>,
}

impl Peer {
    /// Declarations stored for it (services, offers, interests).
    pub fn declarations(&self) -> usize {
        self.services.len() + self.offers.len() + self.interests.len()
    }

    /// Records that something arrived from this peer now.
    pub fn heard(&self, epoch: Instant) {
        self.heard_at(epoch, Instant::now());
    }

    /// Records that something arrived from this peer at `now` (a clock read the caller
    /// already made: the data path reads it once per message).
    pub fn heard_at(&self, epoch: Instant, now: Instant) {
        let ms = now.saturating_duration_since(epoch).as_millis() as u64;
        self.heard_ms.store(ms, Ordering::Relaxed);
    }

    /// Whether the roster proved its key for its namespace and node name (false where no
    /// roster is kept: everything it says is a claim).
    pub fn proven(&self) -> bool {
        self.authenticated
            .as_ref()
            .is_some_and(|g| g.covers(&self.namespace, &self.name))
    }

    /// When it was last heard from at all.
    pub fn last_heard(&self, epoch: Instant) -> Instant {
        let data = epoch + Duration::from_millis(self.heard_ms.load(Ordering::Relaxed));
        self.last_seen.max(data)
    }
}

/// Static facts about this node.
pub(crate) struct Identity {
    pub id: NodeId,
    pub name: String,
    pub namespace: Option<String>,
    pub domain: String,
    pub domain_hash: u32,
    pub heartbeat: Duration,
    pub lease: Duration,
    /// Heartbeat period and lease of each link, by link index.
    pub link_timing: Vec<(Duration, Duration)>,
    /// When the node opened (the origin of `Peer::heard_ms`).
    pub epoch: Instant,
}

impl Identity {
    /// Heartbeat period and lease on `link` (the node's defaults for an unknown index).
    pub fn timing(&self, link: usize) -> (Duration, Duration) {
        self.link_timing
            .get(link)
            .copied()
            .unwrap_or((self.heartbeat, self.lease))
    }
}

/// The shared state of a node, by the part that owns each piece.
pub(crate) struct NodeInner {
    /// Who this node is (fixed at open).
    pub me: Identity,
    /// The links, by index (set once, when all are open).
    pub links: OnceLock<Vec<Arc<dyn Link>>>,
    /// Peers being moved to a better path, whose safe messages wait for the old one to drain
    /// (`path_switch`).
    pub path_switches: path_switch::PathSwitches,
    /// What this node declares and the log peers learn it from (`declarations`).
    pub local: declarations::LocalItems,
    /// Held for a whole route computation (`routes`): two computations interleaving could write
    /// routes from an older snapshot over newer ones (a subscriber would then miss a publisher).
    pub routing: Mutex<()>,
    /// The peers, by id and by address (`discovery`).
    pub peers: discovery::PeerTable,
    /// Our calls waiting for replies, and peers' calls running or waiting (`calls`).
    pub calls: calls::Calls,
    /// File transfers in progress (`files`).
    pub transfers: files::Transfers,
    /// Event mailboxes whose readers are behind: links may then hold senders back (`flow`).
    pub congestion: Arc<mailbox::Congestion>,
    /// Forwarding between links, when this node is a gateway (`gateway`).
    pub gateway: Option<gateway::Gateway>,
    /// What this node accepts from peers, the refusals and the dropped input counted (`policy`).
    pub policy: policy::Policy,
    /// Per-node identity keys, when configured (`<security identityFile=.. identities=..>`;
    /// `identity_check`).
    pub identity: Option<IdentityLayer>,
    /// Bumped whenever routes or the peer table change, so waiters can re-check.
    pub changed: watch::Sender<u64>,
    /// The node's tasks, and what stops them at shutdown.
    pub tasks: TaskTracker,
    pub cancel: CancellationToken,
}

/// This node's identity proof and the domain's roster (see [`crate::identity`]).
pub(crate) struct IdentityLayer {
    /// Our identity key, to answer peers' challenges.
    pub key: Option<crate::identity::IdentityKey>,
    /// Which key may own which namespaces; `None`: peers are not checked.
    pub roster: Option<crate::identity::Roster>,
    /// Our key agreement half of this run, which our challenges and proofs carry.
    pub agreement: crate::identity::KeyAgreement,
}

impl NodeInner {
    pub fn links(&self) -> &[Arc<dyn Link>] {
        self.links.get().map(|v| v.as_slice()).unwrap_or(&[])
    }

    /// Waits until `pred` holds, re-checking whenever the peer table or the routes change;
    /// returns whether it held within `timeout`.
    pub async fn wait_for(&self, timeout: Duration, mut pred: impl FnMut() -> bool) -> bool {
        let mut rx = self.changed.subscribe();
        let deadline = tokio::time::Instant::now() + timeout;
        while !pred() {
            if !matches!(
                tokio::time::timeout_at(deadline, rx.changed()).await,
                Ok(Ok(()))
            ) {
                return pred();
            }
        }
        true
    }

    pub fn bump(&self) {
        self.changed.send_modify(|v| *v += 1);
    }

    /// Sends a message to a peer on its link.
    pub fn send_to(&self, link: usize, addr: PeerAddr, out: Outgoing) {
        self.path_switches.send(self.links(), (link, addr), out);
    }

    /// Sends a safe message and forgets about its acknowledgement (a Hello as
    /// [`Self::send_safe_in_sequence`] sends it, with our challenge after it).
    pub fn send_safe(&self, link: usize, addr: PeerAddr, msg: &Message) {
        if matches!(msg, Message::Hello { .. }) {
            return self.send_safe_in_sequence(link, addr, std::slice::from_ref(msg));
        }
        self.send_to(
            link,
            addr,
            Outgoing::Safe {
                msg: encode_message(msg).into(),
                done: None,
            },
        );
    }

    /// Sends safe messages one after the other with no other safe message between them (see
    /// [`path_switch::PathSwitches::send_in_sequence`]). A Hello to a peer whose identity we
    /// still wait for is followed by our challenge, so the peer answers it before the
    /// declarations we ask for after it.
    pub fn send_safe_in_sequence(&self, link: usize, addr: PeerAddr, msgs: &[Message]) {
        let safe = |msg: &Message| Outgoing::Safe {
            msg: encode_message(msg).into(),
            done: None,
        };
        let mut outs = Vec::with_capacity(msgs.len() + 1);
        for msg in msgs {
            outs.push(safe(msg));
            if matches!(msg, Message::Hello { .. }) {
                if let Some(nonce) = self.pending_challenge(link, addr) {
                    outs.push(safe(&Message::Challenge {
                        nonce,
                        agreement: self.agreement_public(),
                    }));
                }
            }
        }
        self.path_switches
            .send_in_sequence(self.links(), (link, addr), outs);
    }

    /// Sends a safe message to a known peer.
    pub fn send_safe_to_node(&self, node: NodeId, msg: &Message) -> bool {
        let Some((link, addr)) = self.peers.by_id.get(&node).map(|p| (p.link, p.addr)) else {
            return false;
        };
        self.send_safe(link, addr, msg);
        true
    }

    fn peer_of(&self, link: usize, from: PeerAddr) -> Option<NodeId> {
        self.peers.by_addr.get(&(link, from)).map(|e| *e)
    }

    /// Handles `msgs` from `from`, in order. A run of data messages (variables, events) is
    /// delivered together: one sender lookup, one clock read and one wake-up per subscriber for
    /// the run, where a datagram of a fast stream carries hundreds.
    ///
    /// Data messages are decoded as they are delivered, a run at a time; a call, a reply or
    /// flow control behind a run that holds a large message ([`PASSED_DATA_BYTES`]) is handled
    /// before it, as the sender lets those pass the large messages it sends in parts and what
    /// queued behind them ([`precedence`]): a camera frame's decoding and delivery do not hold
    /// up a command that arrived with it. Behind small data, order is kept (a variable set
    /// before a reply is read after it).
    fn dispatch_all(self: &Arc<Self>, link: usize, from: PeerAddr, msgs: &[&[u8]]) {
        let mut data: Vec<&[u8]> = Vec::new();
        let mut large = false;
        for bytes in msgs {
            if matches!(bytes.first(), Some(&(tag::VAR | tag::EVENT))) {
                large |= bytes.len() > PASSED_DATA_BYTES;
                data.push(bytes);
                continue;
            }
            if !(large && precedence(bytes) == Precedence::Urgent) {
                self.deliver_encoded_data(link, from, &mut data);
                large = false;
            }
            match decode_message(bytes) {
                Ok(msg) => self.handle(link, from, msg),
                Err(e) => self.drop_undecodable(from, &e),
            }
        }
        self.deliver_encoded_data(link, from, &mut data);
    }

    fn drop_undecodable(&self, from: PeerAddr, e: &impl std::fmt::Display) {
        self.policy
            .dropped
            .undecodable
            .fetch_add(1, Ordering::Relaxed);
        tracing::debug!(%from, error = %e, "undecodable message dropped");
    }

    /// Decodes and delivers (and empties) a run of data messages from `from`.
    fn deliver_encoded_data(&self, link: usize, from: PeerAddr, run: &mut Vec<&[u8]>) {
        if run.is_empty() {
            return;
        }
        let mut data = Vec::with_capacity(run.len());
        for bytes in run.drain(..) {
            match decode_message(bytes) {
                Ok(Message::Var { id, payload } | Message::Event { id, payload }) => {
                    data.push((id, payload.into()))
                }
                Ok(_) => self.drop_undecodable(from, &"not the data its tag says"),
                Err(e) => self.drop_undecodable(from, &e),
            }
        }
        self.deliver_data(link, from, &mut data);
    }

    /// Delivers (and empties) a run of data messages from `from`.
    fn deliver_data(&self, link: usize, from: PeerAddr, data: &mut Vec<(u32, Encoded)>) {
        if data.is_empty() {
            return;
        }
        match self.peer_of(link, from) {
            Some(node) => self.deliver_remote_run(node, data.drain(..)),
            None => {
                self.policy
                    .dropped
                    .unknown_sender
                    .fetch_add(data.len() as u64, Ordering::Relaxed);
                tracing::trace!(%from, "data from an unknown sender dropped");
                data.clear();
            }
        }
    }

    /// Handles one decoded message other than data.
    fn handle(self: &Arc<Self>, link: usize, from: PeerAddr, msg: Message) {
        // Discovery messages may come from anyone; everything else only from a known peer.
        if matches!(
            msg,
            Message::Hello { .. } | Message::Heartbeat { .. } | Message::Bye { .. }
        ) {
            self.on_discovery(link, from, msg);
            return;
        }
        let Some(node) = self.peer_of(link, from) else {
            self.policy
                .dropped
                .unknown_sender
                .fetch_add(1, Ordering::Relaxed);
            tracing::trace!(%from, "message from an unknown sender dropped");
            return;
        };
        // Anything from a peer shows it alive (its heartbeats may be lost on a busy radio):
        // an atomic under the peer table's read lock (the data path refreshes it once per run
        // in its own lookup).
        if !matches!(msg, Message::Var { .. } | Message::Event { .. }) {
            if let Some(p) = self.peers.by_id.get(&node) {
                p.heard(self.me.epoch);
            }
        }
        match msg {
            Message::Var { id, payload } | Message::Event { id, payload } => {
                self.deliver_remote_run(node, std::iter::once((id, payload.into())))
            }
            Message::DeclRequest { since } => self.answer_decl_request(node, since),
            Message::DeclBatch {
                after,
                upto,
                reset,
                entries,
            } => {
                if self.identity_allows(node) {
                    self.apply_decl_batch(node, after, upto, reset, entries)
                }
            }
            Message::Identity {
                public_key,
                signature,
                agreement,
            } => self.on_identity(node, public_key, &signature, agreement),
            Message::Challenge { nonce, agreement } => self.on_challenge(node, nonce, agreement),
            Message::Flow {
                behind,
                readers,
                offers,
            } => self.on_flow(node, behind, readers, offers),
            Message::Refused {
                interest,
                name,
                offered,
            } => self.on_refused(node, interest, name, offered),
            Message::Call {
                call_id,
                id,
                remaining_ms,
                args,
                caller,
            } => self.on_call(node, call_id, id, remaining_ms, args, caller),
            Message::Reply { call_id, result } => self.on_reply(node, call_id, result),
            Message::FileOffer(offer) => self.on_file_offer(node, offer),
            Message::FileChunk { transfer, .. }
            | Message::FileAccept { transfer, .. }
            | Message::FileDone { transfer, .. }
            | Message::FileCancel { transfer }
                if self.relay_file_message(node, transfer, &msg) => {}
            Message::FileChunk {
                transfer,
                offset,
                data,
            } => self.on_file_chunk(node, transfer, offset, data),
            Message::FileAccept { transfer, offset } => self
                .transfers
                .to_sender(transfer, files::Control::Accept(offset)),
            Message::FileDone { transfer, verdict } => self
                .transfers
                .to_sender(transfer, files::Control::Done(verdict)),
            Message::FileCancel { transfer } => self.on_file_cancel(node, transfer),
            Message::Hello { .. } | Message::Heartbeat { .. } | Message::Bye { .. } => {}
        }
    }
}

/// The safe message `msg` once for each of `n` routes: one buffer, shared; the last route
/// takes it (the first clone of a buffer made from a `Vec` allocates its shared count, which a
/// lone subscriber's message would pay for nothing).
pub(crate) fn per_route(msg: Vec<u8>, n: usize) -> std::iter::RepeatN<bytes::Bytes> {
    std::iter::repeat_n(bytes::Bytes::from(msg), n)
}

/// Adapts the node to the links' callback interface without a reference cycle.
///
/// A link receives as soon as it is opened, while `Node::open` still opens the others: what
/// arrives before the node has its links (a serial peer's Hello waiting in the port, say) is
/// dropped and counted as from an unknown sender. Handled then, it would make a peer of the
/// sender while our answer (our Hello and declarations) had no link to leave by: the peer
/// would never learn of us, and we, knowing it, would never introduce ourselves again. Dropped,
/// the sender's next heartbeat makes us introduce ourselves as to any new node.
pub(crate) struct Handler(pub Weak<NodeInner>);

impl Handler {
    /// The node, once it has its links.
    fn node(&self) -> Option<Arc<NodeInner>> {
        let n = self.0.upgrade()?;
        if n.links.get().is_none() {
            n.policy
                .dropped
                .unknown_sender
                .fetch_add(1, Ordering::Relaxed);
            tracing::debug!("message before the node's links are set dropped");
            return None;
        }
        Some(n)
    }
}

impl LinkHandler for Handler {
    fn on_message(&self, link: usize, from: PeerAddr, msg: &[u8]) {
        self.on_messages(link, from, &[msg]);
    }

    fn age_safe(&self, msg: &mut Vec<u8>, waited: std::time::Duration) {
        calls::age_call(msg, waited);
    }

    /// Calls alone carry their remaining time.
    fn ages(&self, msg: &[u8]) -> bool {
        msg.first() == Some(&crate::protocol::tag::CALL)
    }

    /// Calls, replies and flow control pass data (variables, events, file chunks): no order is
    /// promised between them, and a command must not wait behind a camera frame. Nothing
    /// passes an introduction or a declaration: a call there before its caller's Hello or
    /// identity would be refused.
    fn precedence(&self, msg: &[u8]) -> Precedence {
        precedence(msg)
    }

    fn on_messages(&self, link: usize, from: PeerAddr, msgs: &[&[u8]]) {
        if let Some(n) = self.node() {
            n.dispatch_all(link, from, msgs);
        }
    }

    /// A value or event reaches its subscribers as a slice of the lent sample (a `Blob` is
    /// then a view of shared memory); anything else is decoded as usual.
    fn on_lent_message(&self, link: usize, from: PeerAddr, msg: bytes::Bytes) {
        let Some(n) = self.node() else { return };
        match crate::codec::data_message_payload(&msg) {
            Some((id, payload)) => {
                let payload = Encoded {
                    bytes: msg.slice(payload),
                    lent: true,
                };
                n.deliver_data(link, from, &mut vec![(id, payload)]);
            }
            None => n.dispatch_all(link, from, &[&msg]),
        }
    }

    fn on_announce(&self, link: usize, from: PeerAddr, msg: &[u8]) {
        let Some(n) = self.node() else { return };
        match decode_message(msg) {
            Ok(m) if n.forged_over_pair(link, from, &m) => {}
            Ok(m) => n.on_discovery(link, from, m),
            Err(_) => {
                n.policy.dropped.undecodable.fetch_add(1, Ordering::Relaxed);
            }
        }
    }

    fn on_peer_reset(&self, link: usize, from: PeerAddr) {
        if let Some(n) = self.node() {
            n.on_peer_reset(link, from);
        }
    }

    fn on_peer_unreachable(&self, link: usize, from: PeerAddr) {
        if let Some(n) = self.node() {
            n.on_peer_unreachable(link, from);
        }
    }

    fn on_peer_answered(&self, link: usize, from: PeerAddr) {
        if let Some(n) = self.node() {
            n.on_peer_answered(link, from);
        }
    }
}

/// A node without links for the node modules' unit tests: peers are made up by feeding it
/// their messages directly (what it sends goes nowhere); also the structured fuzzer's.
#[cfg(any(test, feature = "fuzzing"))]
pub(crate) fn bare_node(
    namespace: Option<&str>,
    access: Option<crate::config::AccessConfig>,
) -> Arc<NodeInner> {
    bare_node_with_identity(namespace, access, None)
}

/// The Hello of peer `id` (node `node` of `namespace`, a 60 s lease) for the node modules'
/// unit tests to feed a [`bare_node`].
#[cfg(test)]
pub(crate) fn test_hello(id: NodeId, node: &str, namespace: &str, gateway: bool) -> Message {
    Message::Hello {
        node_id: id,
        domain: crate::config::DEFAULT_DOMAIN.into(),
        node: node.into(),
        namespace: namespace.into(),
        counter: 0,
        lease_ms: 60_000,
        gateway,
        asks_introduction: false,
    }
}

/// [`bare_node`] checking peers' identities with `identity`'s roster.
#[cfg(any(test, feature = "fuzzing"))]
pub(crate) fn bare_node_with_identity(
    namespace: Option<&str>,
    access: Option<crate::config::AccessConfig>,
    identity: Option<IdentityLayer>,
) -> Arc<NodeInner> {
    let domain = crate::config::DEFAULT_DOMAIN;
    let (changed, _) = watch::channel(0u64);
    let inner = Arc::new(NodeInner {
        me: Identity {
            id: rand::random(),
            name: "me".into(),
            namespace: namespace.map(str::to_owned),
            domain: domain.into(),
            domain_hash: discovery::domain_hash(domain),
            heartbeat: Duration::from_secs(1),
            lease: Duration::from_millis(3500),
            link_timing: Vec::new(),
            epoch: Instant::now(),
        },
        links: OnceLock::new(),
        local: Default::default(),
        peers: Default::default(),
        calls: Default::default(),
        transfers: Default::default(),
        changed,
        tasks: TaskTracker::new(),
        cancel: CancellationToken::new(),
        gateway: None,
        routing: Mutex::new(()),
        path_switches: Default::default(),
        policy: policy::Policy::new(access, 1),
        identity,
        congestion: Arc::default(),
    });
    let _ = inner.links.set(Vec::new());
    inner
}

/// A data message larger than this (one no datagram carries whole) may be passed by a call, a
/// reply or flow control that arrives behind it ([`NodeInner::dispatch_all`]).
const PASSED_DATA_BYTES: usize = 64 << 10;

/// Which messages may pass which on their way (see [`Precedence`]): calls, replies and flow
/// control pass data; introductions and declarations keep their place.
fn precedence(msg: &[u8]) -> Precedence {
    match msg.first() {
        Some(&(tag::CALL | tag::REPLY | tag::FLOW)) => Precedence::Urgent,
        Some(&(tag::VAR | tag::EVENT | tag::FILE_CHUNK)) => Precedence::Passable,
        _ => Precedence::InOrder,
    }
}
