//! The call protocol of remote invocations, both ends of it: finding the provider of a function
//! (local first, then remote), invoking it (the handler directly, or a `Call` message), the
//! calls waiting for their `Reply`, answering a peer's `Call`, and failing what is pending on a
//! peer that goes away. The typed handles over it are in `api::function`.

use std::collections::HashMap;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use dashmap::DashMap;
use tokio::sync::oneshot;

use super::policy::{Refusal, MAX_CALLS_PER_CALLER, MAX_CALLS_TOTAL, MAX_CALL_TIME};
use super::{lock, BoxFuture, NodeInner, OfferRole};
use crate::config::AccessKind;
use crate::protocol::{tag, ItemKind, Message, NodeId, Origin, RemoteFailure};
use crate::typeinfo::TypeInfo;

/// Why a remote invocation failed. Each cause is distinct, as callers react differently.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum CallError {
    /// No node provides the function (right now).
    #[error("no provider for function '{name}'")]
    NoProvider {
        /// Function name.
        name: String,
    },
    /// The provider did not answer within the deadline.
    #[error("call to '{name}' on node '{node}' timed out after {after:?}")]
    Timeout {
        /// Function name.
        name: String,
        /// Provider node.
        node: String,
        /// The deadline.
        after: Duration,
    },
    /// The provider's handler returned an error.
    #[error("node '{node}' answered with an error: {message}")]
    Remote {
        /// Provider node.
        node: String,
        /// The handler's message.
        message: String,
    },
    /// The provider went away before answering (lease expired, node left, session reset).
    #[error("link to node '{node}' lost before it answered: {reason}")]
    LinkLost {
        /// Provider node.
        node: String,
        /// What happened.
        reason: String,
    },
    /// The arguments encode to more than marea carries ([`crate::protocol::MAX_PAYLOAD`]):
    /// nothing was sent.
    #[error(
        "call to '{name}': arguments of {size} bytes are larger than the {max} bytes marea carries"
    )]
    TooLarge {
        /// Function name.
        name: String,
        /// Their encoded size.
        size: usize,
        /// [`crate::protocol::MAX_PAYLOAD`].
        max: usize,
    },
    /// The provider declares other argument or result types.
    #[error("function '{name}' is provided as {offered} but called as {expected}")]
    TypeMismatch {
        /// Function name.
        name: String,
        /// Provider's signature.
        offered: String,
        /// Caller's signature.
        expected: String,
    },
    /// The provider's access rules (`<access>` in its network.xml) do not let this node call
    /// the function.
    #[error("node '{node}' denied the call to '{name}'")]
    Denied {
        /// Function name.
        name: String,
        /// Provider node.
        node: String,
    },
    /// The provider runs as many calls as it accepts from this node (or in all); retry later.
    #[error("node '{node}' is busy: too many calls in progress, '{name}' not run")]
    Busy {
        /// Function name.
        name: String,
        /// Provider node.
        node: String,
    },
    /// A newer call of the same function from this node arrived at the provider before this
    /// one started: the newest command wins, this one was not run.
    #[error("call to '{name}' on node '{node}' superseded by a newer call before it ran")]
    Superseded {
        /// Function name.
        name: String,
        /// Provider node.
        node: String,
    },
    /// Arguments could not be encoded, or the result decoded.
    #[error("codec error calling '{name}': {reason}")]
    Codec {
        /// Function name.
        name: String,
        /// What failed.
        reason: String,
    },
}

impl CallError {
    /// A short name of the cause, for a tool's or a bridge's JSON (`no_provider`, `timeout`,
    /// `remote`, `link_lost`, `type_mismatch`, `codec`, `denied`, `busy`, `superseded`,
    /// `too_large`).
    pub fn kind(&self) -> &'static str {
        match self {
            CallError::NoProvider { .. } => "no_provider",
            CallError::Timeout { .. } => "timeout",
            CallError::Remote { .. } => "remote",
            CallError::LinkLost { .. } => "link_lost",
            CallError::TypeMismatch { .. } => "type_mismatch",
            CallError::Codec { .. } => "codec",
            CallError::Denied { .. } => "denied",
            CallError::Busy { .. } => "busy",
            CallError::Superseded { .. } => "superseded",
            CallError::TooLarge { .. } => "too_large",
        }
    }
}

/// A call that waited `waited` in a link's queue (a radio's) carries that much less of its
/// caller's remaining time when it leaves, so every hop's queue counts against it and a call
/// its caller has given up on is dropped unexecuted by the provider (at 0 on arrival).
/// Anything but a call is left as it is.
pub(crate) fn age_call(msg: &mut Vec<u8>, waited: Duration) {
    let waited_ms = u32::try_from(waited.as_millis()).unwrap_or(u32::MAX);
    if waited_ms == 0 || msg.first().copied() != Some(tag::CALL) {
        return;
    }
    let Ok(Message::Call {
        call_id,
        id,
        remaining_ms,
        args,
        caller,
    }) = crate::codec::decode_message(msg)
    else {
        return;
    };
    *msg = crate::codec::encode_message(&Message::Call {
        call_id,
        id,
        remaining_ms: remaining_ms.saturating_sub(waited_ms),
        args,
        caller,
    });
}

impl CallError {
    /// The caller's view of a failure reported by provider `node` of `name`.
    pub(crate) fn from_remote(node: &str, name: &str, after: Duration, f: RemoteFailure) -> Self {
        let node = node.to_owned();
        match f {
            RemoteFailure::Handler(message) => CallError::Remote { node, message },
            RemoteFailure::BadArguments(m) => CallError::Remote {
                node,
                message: format!("bad arguments: {m}"),
            },
            RemoteFailure::NotProvided => CallError::Remote {
                node,
                message: "function no longer provided".into(),
            },
            RemoteFailure::DeadlineExpired => CallError::Timeout {
                name: name.to_owned(),
                node,
                after,
            },
            RemoteFailure::Denied => CallError::Denied {
                name: name.to_owned(),
                node,
            },
            RemoteFailure::Busy => CallError::Busy {
                name: name.to_owned(),
                node,
            },
            RemoteFailure::Superseded => CallError::Superseded {
                name: name.to_owned(),
                node,
            },
        }
    }

    /// What `gateway` answers its own caller when the call it relayed failed this way (the
    /// wire way back of [`CallError::from_remote`]).
    fn relayed(self, gateway: &str) -> RemoteFailure {
        match self {
            CallError::NoProvider { .. } => RemoteFailure::NotProvided,
            CallError::Timeout { .. } => RemoteFailure::DeadlineExpired,
            CallError::Denied { .. } => RemoteFailure::Denied,
            CallError::Busy { .. } => RemoteFailure::Busy,
            CallError::Superseded { .. } => RemoteFailure::Superseded,
            CallError::Remote { node, message } => {
                RemoteFailure::Handler(format!("{message} (from node '{node}')"))
            }
            other => RemoteFailure::Handler(format!("through gateway '{gateway}': {other}")),
        }
    }
}

/// Who made a call, as the provider's access rules see it: the calling node's namespace and
/// name (through gateways, the node the call started at; proven by its identity key where the
/// domain has a roster).
#[derive(Clone, Debug, PartialEq, Eq, Hash)]
pub struct Caller {
    /// The calling node's namespace (empty: none, e.g. a `usal` tool).
    pub namespace: String,
    /// The calling node's name.
    pub node: String,
}

impl std::fmt::Display for Caller {
    /// `namespace/node`, or the node alone without a namespace.
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        if self.namespace.is_empty() {
            f.write_str(&self.node)
        } else {
            write!(f, "{}/{}", self.namespace, self.node)
        }
    }
}

/// A type-erased function handler: encoded arguments and the caller in, encoded result out.
pub(crate) type RawHandler =
    Arc<dyn Fn(Vec<u8>, Caller) -> BoxFuture<Result<Vec<u8>, RemoteFailure>> + Send + Sync>;

/// Who answers a call, with the type it declared.
pub(crate) enum Provider {
    Local(RawHandler, TypeInfo),
    Remote {
        node: NodeId,
        node_name: Arc<str>,
        id: u32,
        ty: TypeInfo,
    },
}

impl Provider {
    /// The provider's declared `fn(A) -> R` type.
    pub(crate) fn ty(&self) -> &TypeInfo {
        match self {
            Provider::Local(_, ty) | Provider::Remote { ty, .. } => ty,
        }
    }
}

/// A call waiting for its reply.
struct PendingCall {
    node: NodeId,
    node_name: Arc<str>,
    /// Function name and the caller's deadline, for the errors.
    name: String,
    timeout: Duration,
    reply: oneshot::Sender<Result<Vec<u8>, CallError>>,
}

/// The calls of this node waiting for a reply, by call id.
pub(crate) struct PendingCalls {
    next: AtomicU64,
    waiting: DashMap<u64, PendingCall>,
}

impl Default for PendingCalls {
    fn default() -> Self {
        PendingCalls {
            // Call ids start at 1.
            next: AtomicU64::new(1),
            waiting: DashMap::new(),
        }
    }
}

impl PendingCalls {
    /// Registers a call of `name` on `node`; returns its id and where its outcome arrives.
    fn register(
        &self,
        node: NodeId,
        node_name: Arc<str>,
        name: &str,
        timeout: Duration,
    ) -> (u64, oneshot::Receiver<Result<Vec<u8>, CallError>>) {
        let call_id = self.next.fetch_add(1, Ordering::Relaxed);
        let (reply, rx) = oneshot::channel();
        self.waiting.insert(
            call_id,
            PendingCall {
                node,
                node_name,
                name: name.to_owned(),
                timeout,
                reply,
            },
        );
        (call_id, rx)
    }

    /// Forgets a call nobody waits for any more.
    fn forget(&self, call_id: u64) {
        self.waiting.remove(&call_id);
    }

    /// Completes call `call_id` with the reply `node` sent; a reply from another node than the
    /// one called, or to a call no longer waiting, is ignored.
    fn complete(&self, node: NodeId, call_id: u64, result: Result<Vec<u8>, RemoteFailure>) {
        let Some((_, pending)) = self.waiting.remove_if(&call_id, |_, p| p.node == node) else {
            return;
        };
        let r = result.map_err(|f| {
            CallError::from_remote(&pending.node_name, &pending.name, pending.timeout, f)
        });
        let _ = pending.reply.send(r);
    }

    /// Fails every call waiting on `node` with [`CallError::LinkLost`] for `reason`.
    pub fn fail_to(&self, node: NodeId, reason: &str) {
        let ids: Vec<u64> = self
            .waiting
            .iter()
            .filter(|c| c.node == node)
            .map(|c| *c.key())
            .collect();
        for id in ids {
            if let Some((_, c)) = self.waiting.remove(&id) {
                let _ = c.reply.send(Err(CallError::LinkLost {
                    node: c.node_name.to_string(),
                    reason: reason.to_owned(),
                }));
            }
        }
    }
}

/// Runs one call of a lane, given the arguments and the caller's remaining time.
type LaneRun =
    Arc<dyn Fn(Vec<u8>, Duration) -> BoxFuture<Result<Vec<u8>, RemoteFailure>> + Send + Sync>;

/// A lane: the calls of one caller to one function, from the peer that sent them (the caller
/// itself, or a gateway relaying its calls).
#[derive(Clone, Copy, PartialEq, Eq, Hash)]
struct LaneKey {
    /// The peer the calls come from, and their replies go to.
    peer: NodeId,
    /// The node calling: `peer`, or the node a gateway relays for.
    caller: NodeId,
    /// The function's offer id.
    function: u32,
}

/// A peer's call accepted but not started.
struct QueuedCall {
    call_id: u64,
    args: Vec<u8>,
    /// When the caller's remaining time runs out, counted from arrival.
    expires: Instant,
}

/// What became of a call offered to its lane.
enum Admission {
    /// The lane was idle: run it now.
    Run(QueuedCall),
    /// The lane is busy: it waits, replacing the call that waited (if any).
    Queued { superseded: Option<u64> },
    /// Too many lanes of this peer, or in all.
    Busy,
}

#[derive(Default)]
struct LaneTable {
    /// Running lanes, each with the call waiting behind the one running.
    lanes: HashMap<LaneKey, Option<QueuedCall>>,
    /// Running lanes by caller.
    per_caller: HashMap<NodeId, usize>,
    total: usize,
}

impl LaneTable {
    fn admit(&mut self, key: LaneKey, call: QueuedCall) -> Admission {
        if let Some(waiting) = self.lanes.get_mut(&key) {
            let old = waiting.replace(call);
            return Admission::Queued {
                superseded: old.map(|c| c.call_id),
            };
        }
        let caller = self.per_caller.get(&key.caller).copied().unwrap_or(0);
        if caller >= MAX_CALLS_PER_CALLER || self.total >= MAX_CALLS_TOTAL {
            return Admission::Busy;
        }
        self.lanes.insert(key, None);
        *self.per_caller.entry(key.caller).or_default() += 1;
        self.total += 1;
        Admission::Run(call)
    }

    /// The call waiting in lane `key`, or `None` and the lane closes.
    fn next(&mut self, key: LaneKey) -> Option<QueuedCall> {
        if let Some(c) = self.lanes.get_mut(&key).and_then(Option::take) {
            return Some(c);
        }
        if self.lanes.remove(&key).is_some() {
            self.total = self.total.saturating_sub(1);
            if let Some(n) = self.per_caller.get_mut(&key.caller) {
                *n = n.saturating_sub(1);
                if *n == 0 {
                    self.per_caller.remove(&key.caller);
                }
            }
        }
        None
    }
}

/// The (caller, function) lanes of the calls peers make to this node.
#[derive(Default)]
pub(crate) struct Lanes {
    inner: Mutex<LaneTable>,
}

/// Both ends of the calls in progress on this node.
#[derive(Default)]
pub(crate) struct Calls {
    /// Our calls waiting for their replies.
    pub pending: PendingCalls,
    /// Peers' calls running or waiting, by (caller, function id).
    pub lanes: Lanes,
}

impl NodeInner {
    /// The provider of `name`: local first, then remote. With `expected`, a provider of another
    /// type is refused (and reported if no matching one exists); without, any type is taken.
    pub fn find_provider(
        &self,
        name: &str,
        expected: Option<&TypeInfo>,
    ) -> Result<Provider, CallError> {
        let fits = |ty: &TypeInfo| expected.is_none_or(|e| e == ty);
        let mut mismatch: Option<TypeInfo> = None;
        for o in self.local.offers.iter() {
            if o.kind == ItemKind::Function && *o.name == *name {
                if fits(&o.ty) {
                    if let OfferRole::Function { handler } = &o.role {
                        return Ok(Provider::Local(handler.clone(), o.ty.clone()));
                    }
                } else {
                    mismatch = Some(o.ty.clone());
                }
            }
        }
        for p in self.peers.by_id.iter() {
            for (id, o) in &p.offers {
                if p.shadowed.contains(id) {
                    continue;
                }
                if o.kind == ItemKind::Function && *o.name == *name {
                    if fits(&o.ty) {
                        return Ok(Provider::Remote {
                            node: p.id,
                            node_name: p.name.clone(),
                            id: *id,
                            ty: o.ty.clone(),
                        });
                    }
                    mismatch = Some(o.ty.clone());
                }
            }
        }
        match (mismatch, expected) {
            (Some(offered), Some(expected)) => Err(CallError::TypeMismatch {
                name: name.to_owned(),
                offered: offered.name,
                expected: expected.name.clone(),
            }),
            _ => Err(CallError::NoProvider {
                name: name.to_owned(),
            }),
        }
    }

    /// Calls function `name` with encoded arguments: finds its provider (of type `expected`,
    /// or of any type without) and invokes it.
    pub async fn call(
        &self,
        name: &str,
        expected: Option<&TypeInfo>,
        args: Vec<u8>,
        timeout: Duration,
    ) -> Result<Vec<u8>, CallError> {
        let provider = self.find_provider(name, expected)?;
        self.invoke(name, provider, args, timeout, None).await
    }

    /// Invokes a provider with encoded arguments and returns the encoded result; a gateway
    /// relaying another node's call names it as the `caller`.
    pub async fn invoke(
        &self,
        name: &str,
        provider: Provider,
        args: Vec<u8>,
        timeout: Duration,
        caller: Option<Origin>,
    ) -> Result<Vec<u8>, CallError> {
        let max = crate::protocol::MAX_PAYLOAD;
        if args.len() > max {
            return Err(CallError::TooLarge {
                name: name.to_owned(),
                size: args.len(),
                max,
            });
        }
        match provider {
            Provider::Local(handler, _) => match tokio::time::timeout(
                timeout,
                handler(
                    args,
                    Caller {
                        namespace: self.me.namespace.clone().unwrap_or_default(),
                        node: self.me.name.clone(),
                    },
                ),
            )
            .await
            {
                Ok(r) => r.map_err(|f| CallError::from_remote(&self.me.name, name, timeout, f)),
                Err(_) => Err(CallError::Timeout {
                    name: name.to_owned(),
                    node: self.me.name.clone(),
                    after: timeout,
                }),
            },
            Provider::Remote {
                node: peer,
                node_name,
                id,
                ..
            } => {
                let (call_id, rx) =
                    self.calls
                        .pending
                        .register(peer, node_name.clone(), name, timeout);
                let remaining_ms = u32::try_from(timeout.as_millis()).unwrap_or(u32::MAX);
                let sent = self.send_safe_to_node(
                    peer,
                    &Message::Call {
                        call_id,
                        id,
                        remaining_ms,
                        args,
                        caller,
                    },
                );
                if !sent {
                    self.calls.pending.forget(call_id);
                    return Err(CallError::LinkLost {
                        node: node_name.to_string(),
                        reason: "peer no longer known".into(),
                    });
                }
                match tokio::time::timeout(timeout, rx).await {
                    Ok(Ok(r)) => r,
                    Ok(Err(_)) => Err(CallError::LinkLost {
                        node: node_name.to_string(),
                        reason: "node shutting down".into(),
                    }),
                    Err(_) => {
                        self.calls.pending.forget(call_id);
                        Err(CallError::Timeout {
                            name: name.to_owned(),
                            node: node_name.to_string(),
                            after: timeout,
                        })
                    }
                }
            }
        }
    }

    /// Answers a peer's call of our offer `id`: checks the caller may call it, then runs its
    /// handler (or relays it, for a gateway's stand-in) in the (caller, function) lane and
    /// sends the Reply.
    ///
    /// A lane runs one call at a time; a call arriving while one runs waits, and a newer one
    /// replaces it (answered [`RemoteFailure::Superseded`]): the newest command wins. A call
    /// whose caller's remaining time ran out before it could start is dropped unexecuted and
    /// unanswered (the caller already timed out). Lanes are capped per caller and in all
    /// ([`RemoteFailure::Busy`] beyond), so a peer cannot make us spawn without bound.
    pub(super) fn on_call(
        self: &Arc<Self>,
        node: NodeId,
        call_id: u64,
        id: u32,
        remaining_ms: u32,
        args: Vec<u8>,
        caller: Option<Origin>,
    ) {
        let remaining = Duration::from_millis(u64::from(remaining_ms)).min(MAX_CALL_TIME);
        let refuse = |why: RemoteFailure| {
            self.send_safe_to_node(
                node,
                &Message::Reply {
                    call_id,
                    result: Err(why),
                },
            );
        };
        let Some(offer) = self.local.offers.get(&id).map(|o| o.clone()) else {
            return refuse(RemoteFailure::NotProvided);
        };
        let run: LaneRun = match &offer.role {
            OfferRole::Function { handler } => {
                let handler = handler.clone();
                let origin = self.caller_to_relay(node, caller.as_ref());
                let who = Caller {
                    namespace: origin.namespace,
                    node: origin.name,
                };
                Arc::new(move |args, left: Duration| {
                    let call = handler(args, who.clone());
                    // The caller gives up when its time runs out; the handler is given a
                    // little more, so the caller sees its own timeout, not a remote error.
                    let limit = left * 3 / 2 + Duration::from_millis(100);
                    Box::pin(async move {
                        tokio::time::timeout(limit, call)
                            .await
                            .unwrap_or(Err(RemoteFailure::DeadlineExpired))
                    })
                })
            }
            OfferRole::Relay { origin, remote_id } => {
                if !self.may_relay_for(node, &offer.name) {
                    return refuse(RemoteFailure::Denied);
                }
                let (origin, remote_id) = (*origin, *remote_id);
                let caller = self.caller_to_relay(node, caller.as_ref());
                let inner = self.clone();
                let name = offer.name.to_string();
                let ty = offer.ty.clone();
                // Relayed with the caller's remaining time as it is now, never more.
                Arc::new(move |args, left| {
                    let provider = Provider::Remote {
                        node: origin,
                        node_name: inner.peer_name(origin),
                        id: remote_id,
                        ty: ty.clone(),
                    };
                    let (inner, name, caller) = (inner.clone(), name.clone(), caller.clone());
                    Box::pin(async move {
                        inner
                            .invoke(&name, provider, args, left, Some(caller))
                            .await
                            .map_err(|e| e.relayed(&inner.me.name))
                    })
                })
            }
            _ => return refuse(RemoteFailure::NotProvided),
        };
        if self
            .permitted(node, caller.as_ref(), AccessKind::Call, &offer.name)
            .is_err()
        {
            return refuse(RemoteFailure::Denied);
        }
        let key = LaneKey {
            peer: node,
            caller: caller.as_ref().map_or(node, |o| o.node),
            function: id,
        };
        let queued = QueuedCall {
            call_id,
            args,
            expires: Instant::now() + remaining,
        };
        let first = match lock(&self.calls.lanes.inner).admit(key, queued) {
            Admission::Run(call) => call,
            Admission::Queued { superseded } => {
                if let Some(old) = superseded {
                    self.send_safe_to_node(
                        node,
                        &Message::Reply {
                            call_id: old,
                            result: Err(RemoteFailure::Superseded),
                        },
                    );
                }
                return;
            }
            Admission::Busy => {
                let peer = self.peer_name(node);
                self.policy.refuse(
                    self.peer_link(node),
                    node,
                    &peer,
                    &offer.name,
                    Refusal::Busy,
                );
                return refuse(RemoteFailure::Busy);
            }
        };
        let inner = self.clone();
        let name = offer.name.clone();
        crate::sync::spawn_tracked(&self.tasks, async move {
            let mut call = first;
            loop {
                let now = Instant::now();
                if now >= call.expires {
                    tracing::debug!(function = %name, call_id = call.call_id, "call expired before it ran: dropped unexecuted");
                } else {
                    let result = tokio::select! {
                        r = run(call.args, call.expires - now) => r,
                        _ = inner.cancel.cancelled() => Err(RemoteFailure::Handler("provider node shutting down".into())),
                    };
                    let result = result.and_then(|r| {
                        let max = crate::protocol::MAX_PAYLOAD;
                        if r.len() > max {
                            tracing::warn!(function = %name, "a result of {} bytes is larger than the {max} bytes marea carries: the caller is told", r.len());
                            return Err(RemoteFailure::Handler(format!(
                                "the result of {} bytes is larger than the {max} bytes marea carries",
                                r.len()
                            )));
                        }
                        Ok(r)
                    });
                    inner.send_safe_to_node(
                        node,
                        &Message::Reply {
                            call_id: call.call_id,
                            result,
                        },
                    );
                }
                if inner.cancel.is_cancelled() {
                    break;
                }
                match lock(&inner.calls.lanes.inner).next(key) {
                    Some(c) => call = c,
                    None => break,
                }
            }
        });
    }

    /// The link a peer is reached on (0 when it is no longer known).
    pub(super) fn peer_link(&self, node: NodeId) -> usize {
        self.peers.by_id.get(&node).map_or(0, |p| p.link)
    }

    /// A peer's name, or its id in hex when it is no longer known.
    pub(super) fn peer_name(&self, node: NodeId) -> Arc<str> {
        self.peers
            .by_id
            .get(&node)
            .map(|p| p.name.clone())
            .unwrap_or_else(|| format!("{node:016x}").into())
    }

    /// Handles the Reply `node` sent to our call `call_id`.
    pub(super) fn on_reply(
        &self,
        node: NodeId,
        call_id: u64,
        result: Result<Vec<u8>, RemoteFailure>,
    ) {
        self.calls.pending.complete(node, call_id, result);
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::node::gateway::MAX_HOPS;

    /// A call nobody answers fails as a timeout when its caller's time is up, not before, and
    /// is forgotten. On paused time: the timer itself is checked, to the millisecond.
    #[tokio::test(start_paused = true)]
    async fn an_unanswered_call_times_out_at_its_timeout_and_not_before() {
        let node = crate::node::bare_node(None, None);
        let from = crate::link::PeerAddr::Udp(std::net::SocketAddr::from(([127, 0, 0, 1], 9)));
        node.on_discovery(
            0,
            from,
            Message::Hello {
                node_id: PROVIDER,
                domain: crate::config::DEFAULT_DOMAIN.into(),
                node: "air".into(),
                namespace: "rover1".into(),
                counter: 0,
                lease_ms: 60_000,
                gateway: false,
                asks_introduction: false,
            },
        );
        let timeout = Duration::from_millis(1_500);
        let provider = Provider::Remote {
            node: PROVIDER,
            node_name: "air".into(),
            id: 3,
            ty: TypeInfo::of::<u64>(),
        };
        let started = tokio::time::Instant::now();
        let call = {
            let node = node.clone();
            tokio::spawn(async move {
                let r = node
                    .invoke("rover1/vas/double", provider, arg(2), timeout, None)
                    .await;
                (r, started.elapsed())
            })
        };
        tokio::time::sleep(timeout - Duration::from_millis(1)).await;
        assert!(!call.is_finished(), "the call ended before its timeout");
        let (r, after) = call.await.expect("the call's task");
        assert!(
            matches!(&r, Err(CallError::Timeout { after, .. }) if *after == timeout),
            "{r:?}"
        );
        assert_eq!(after, timeout, "ended {after:?} after it was made");
        assert_eq!(
            node.calls.pending.waiting.len(),
            0,
            "the call is still waiting"
        );
    }

    const PROVIDER: NodeId = 7;

    #[test]
    fn a_call_leaving_a_queue_carries_its_wait_off_its_remaining_time() {
        let call = |remaining_ms| {
            crate::codec::encode_message(&Message::Call {
                call_id: 9,
                id: 3,
                remaining_ms,
                args: vec![1, 2, 3],
                caller: None,
            })
        };
        let mut m = call(1_000);
        age_call(&mut m, Duration::from_millis(300));
        assert_eq!(m, call(700));
        age_call(&mut m, Duration::from_secs(5));
        assert_eq!(m, call(0), "run out: the provider drops it unexecuted");
        let mut m = call(1_000);
        age_call(&mut m, Duration::from_micros(300));
        assert_eq!(m, call(1_000), "under a millisecond: as it was");
        let reply = crate::codec::encode_message(&Message::Reply {
            call_id: 9,
            result: Ok(vec![1]),
        });
        let mut m = reply.clone();
        age_call(&mut m, Duration::from_secs(5));
        assert_eq!(m, reply, "only calls carry a remaining time");
        let mut junk = vec![tag::CALL, 0xff, 0xff];
        age_call(&mut junk, Duration::from_secs(5));
        assert_eq!(junk, [tag::CALL, 0xff, 0xff], "undecodable: left alone");
    }

    fn waiting(calls: &PendingCalls) -> (u64, oneshot::Receiver<Result<Vec<u8>, CallError>>) {
        calls.register(PROVIDER, "air".into(), "vas/double", Duration::from_secs(1))
    }

    /// The lane of `caller`'s own calls of `function`.
    fn lane(caller: NodeId, function: u32) -> LaneKey {
        LaneKey {
            peer: caller,
            caller,
            function,
        }
    }

    fn queued(call_id: u64) -> QueuedCall {
        QueuedCall {
            call_id,
            args: vec![],
            expires: Instant::now() + Duration::from_secs(1),
        }
    }

    #[test]
    fn a_lane_runs_one_call_and_the_newest_waiting_one_wins() {
        let mut t = LaneTable::default();
        let key = lane(PROVIDER, 3);
        assert!(matches!(t.admit(key, queued(1)), Admission::Run(c) if c.call_id == 1));
        assert!(matches!(
            t.admit(key, queued(2)),
            Admission::Queued { superseded: None }
        ));
        assert!(matches!(
            t.admit(key, queued(3)),
            Admission::Queued {
                superseded: Some(2)
            }
        ));
        // Call 1 done: call 3 runs next, then the lane closes.
        assert_eq!(t.next(key).map(|c| c.call_id), Some(3));
        assert!(t.next(key).is_none());
        assert_eq!((t.total, t.per_caller.len(), t.lanes.len()), (0, 0, 0));
    }

    #[test]
    fn lanes_are_capped_per_caller_and_in_all() {
        let mut t = LaneTable::default();
        for f in 0..MAX_CALLS_PER_CALLER as u32 {
            assert!(matches!(
                t.admit(lane(PROVIDER, f), queued(1)),
                Admission::Run(_)
            ));
        }
        assert!(matches!(
            t.admit(lane(PROVIDER, 9999), queued(1)),
            Admission::Busy
        ));
        // Another caller still gets in, up to the total.
        let mut other = PROVIDER + 1;
        let mut admitted = MAX_CALLS_PER_CALLER;
        while admitted < MAX_CALLS_TOTAL {
            for f in 0..MAX_CALLS_PER_CALLER as u32 {
                if admitted == MAX_CALLS_TOTAL {
                    break;
                }
                assert!(matches!(
                    t.admit(lane(other, f), queued(1)),
                    Admission::Run(_)
                ));
                admitted += 1;
            }
            other += 1;
        }
        assert!(matches!(
            t.admit(lane(other, 0), queued(1)),
            Admission::Busy
        ));
        // A lane closing frees its place.
        assert!(t.next(lane(PROVIDER, 0)).is_none());
        assert!(matches!(
            t.admit(lane(other, 0), queued(1)),
            Admission::Run(_)
        ));
    }

    /// A node without links with one function reporting each run (its argument) and then
    /// waiting for a permit of `gate`; callers are made up.
    fn provider_node() -> (
        Arc<NodeInner>,
        u32,
        tokio::sync::mpsc::UnboundedReceiver<u64>,
        Arc<tokio::sync::Semaphore>,
    ) {
        let inner = super::super::bare_node(
            Some("rover1"),
            Some(crate::config::AccessConfig {
                rules: vec![crate::config::AccessRule {
                    kind: AccessKind::Call,
                    item: "rover1/vas/*".into(),
                    from: "ground/*".into(),
                }],
                closed: vec![],
                trust_claims: false,
            }),
        );
        let (tx, ran) = tokio::sync::mpsc::unbounded_channel();
        let gate = Arc::new(tokio::sync::Semaphore::new(0));
        let g = gate.clone();
        let handler: RawHandler = Arc::new(move |args: Vec<u8>, _caller| {
            let (tx, g) = (tx.clone(), g.clone());
            Box::pin(async move {
                let x: u64 = crate::codec::decode_payload(&args)
                    .map_err(|e| RemoteFailure::BadArguments(e.to_string()))?;
                let _ = tx.send(x);
                let _ = g.acquire().await.map(|p| p.forget());
                Ok(args)
            })
        });
        let id = inner.local.fresh_id();
        inner.add_offer(Arc::new(super::super::LocalOffer {
            id,
            service: 0,
            kind: ItemKind::Function,
            name: "rover1/vas/retask".into(),
            ty: TypeInfo::of::<fn(u64) -> u64>(),
            role: OfferRole::Function { handler },
            remote: Default::default(),
            local: Default::default(),
            has_local: Default::default(),
            refused: Default::default(),
            origin: None,
            hidden_on: None,
        }));
        for (peer, ns, gateway) in [(1, "ground", false), (2, "evil", false), (3, "lab", true)] {
            inner.on_discovery(
                0,
                crate::link::PeerAddr::Udp(std::net::SocketAddr::from(([127, 0, 0, 1], peer))),
                Message::Hello {
                    node_id: u64::from(peer),
                    domain: crate::config::DEFAULT_DOMAIN.into(),
                    node: "station".into(),
                    namespace: ns.into(),
                    counter: 0,
                    lease_ms: 60_000,
                    gateway,
                    asks_introduction: false,
                },
            );
        }
        (inner, id, ran, gate)
    }

    async fn next(ran: &mut tokio::sync::mpsc::UnboundedReceiver<u64>) -> Option<u64> {
        tokio::time::timeout(Duration::from_secs(5), ran.recv())
            .await
            .expect("a call ran in time")
    }

    fn arg(x: u64) -> Vec<u8> {
        crate::codec::encode_payload(&x).expect("u64 encodes")
    }

    #[tokio::test]
    async fn expired_denied_and_superseded_calls_never_run() {
        let (inner, id, mut ran, gate) = provider_node();
        // Out of time on arrival: dropped unexecuted.
        inner.on_call(1, 1, id, 0, arg(1), None);
        // Not allowed by <access>.
        inner.on_call(2, 2, id, 5000, arg(2), None);
        // Call 3 runs and blocks; 4 waits; 5 replaces 4 (newest wins).
        inner.on_call(1, 3, id, 5000, arg(3), None);
        assert_eq!(next(&mut ran).await, Some(3));
        inner.on_call(1, 4, id, 5000, arg(4), None);
        inner.on_call(1, 5, id, 5000, arg(5), None);
        gate.add_permits(1);
        assert_eq!(next(&mut ran).await, Some(5));
        gate.add_permits(1);
        // The lane is free again: a later call runs.
        inner.on_call(1, 6, id, 5000, arg(6), None);
        assert_eq!(next(&mut ran).await, Some(6));
        gate.add_permits(1);
        assert!(ran.try_recv().is_err(), "nothing else ran");
        assert_eq!(inner.policy.counts(0), (1, 0), "the denied call counted");
        inner.cancel.cancel();
    }

    /// A node `hops` gateways away, as a gateway names it.
    fn behind_a_gateway(node: NodeId, namespace: &str, hops: u8) -> Option<Origin> {
        Some(Origin {
            node,
            name: "fmo".into(),
            hops,
            namespace: namespace.into(),
        })
    }

    #[tokio::test]
    async fn calls_a_gateway_relays_are_checked_and_laned_as_their_callers() {
        let (inner, id, mut ran, gate) = provider_node();
        // Peer 3 is a gateway of namespace `lab`, which no rule allows; the callers it
        // relays for are checked instead: `ground` may call, `evil` may not.
        inner.on_call(3, 1, id, 5000, arg(1), behind_a_gateway(10, "evil", 1));
        inner.on_call(3, 2, id, 5000, arg(2), behind_a_gateway(11, "ground", 1));
        assert_eq!(next(&mut ran).await, Some(2));
        // Another caller behind the same gateway has a lane of its own: its calls run beside
        // caller 11's, and supersede none of them.
        inner.on_call(3, 3, id, 5000, arg(3), behind_a_gateway(12, "ground", 2));
        assert_eq!(next(&mut ran).await, Some(3));
        inner.on_call(3, 4, id, 5000, arg(4), behind_a_gateway(11, "ground", 1));
        inner.on_call(3, 5, id, 5000, arg(5), behind_a_gateway(12, "ground", 2));
        gate.add_permits(2);
        let mut next_two = vec![next(&mut ran).await, next(&mut ran).await];
        next_two.sort();
        assert_eq!(next_two, [Some(4), Some(5)]);
        gate.add_permits(2);
        assert!(ran.try_recv().is_err(), "nothing else ran");
        assert_eq!(inner.policy.counts(0), (1, 0), "the denied caller counted");
        inner.cancel.cancel();
    }

    #[tokio::test]
    async fn a_call_relayed_by_a_node_that_is_no_gateway_is_refused() {
        let (inner, id, mut ran, gate) = provider_node();
        // Peer 1 (`ground`, no gateway) claims to relay for a `ground` node; peer 3, a
        // gateway, names itself, or a caller zero or too many gateways away.
        inner.on_call(1, 1, id, 5000, arg(1), behind_a_gateway(10, "ground", 1));
        inner.on_call(3, 2, id, 5000, arg(2), behind_a_gateway(3, "ground", 1));
        inner.on_call(3, 3, id, 5000, arg(3), behind_a_gateway(10, "ground", 0));
        inner.on_call(
            3,
            4,
            id,
            5000,
            arg(4),
            behind_a_gateway(10, "ground", MAX_HOPS),
        );
        // A call of its own from peer 1 still runs.
        inner.on_call(1, 5, id, 5000, arg(5), None);
        assert_eq!(next(&mut ran).await, Some(5));
        gate.add_permits(1);
        assert!(ran.try_recv().is_err(), "no relayed call ran");
        assert_eq!(inner.policy.counts(0).1, 4, "each refusal counted");
        inner.cancel.cancel();
    }

    #[test]
    fn a_reply_completes_the_call_it_answers() {
        let calls = PendingCalls::default();
        let (id, mut rx) = waiting(&calls);
        calls.complete(PROVIDER, id, Ok(vec![4]));
        assert_eq!(rx.try_recv(), Ok(Ok(vec![4])));
        assert!(calls.waiting.is_empty());
    }

    #[test]
    fn a_reply_from_another_node_is_ignored() {
        let calls = PendingCalls::default();
        let (id, mut rx) = waiting(&calls);
        calls.complete(PROVIDER + 1, id, Ok(vec![4]));
        assert!(rx.try_recv().is_err(), "nothing delivered yet");
        assert_eq!(
            calls.waiting.len(),
            1,
            "the call still waits for its provider"
        );
    }

    #[test]
    fn a_remote_deadline_is_a_timeout_and_a_handler_error_is_remote() {
        let calls = PendingCalls::default();
        let (late, mut late_rx) = waiting(&calls);
        let (failed, mut failed_rx) = waiting(&calls);
        assert_ne!(late, failed);
        calls.complete(PROVIDER, late, Err(RemoteFailure::DeadlineExpired));
        calls.complete(PROVIDER, failed, Err(RemoteFailure::Handler("odd".into())));
        assert_eq!(
            late_rx.try_recv(),
            Ok(Err(CallError::Timeout {
                name: "vas/double".into(),
                node: "air".into(),
                after: Duration::from_secs(1),
            }))
        );
        assert_eq!(
            failed_rx.try_recv(),
            Ok(Err(CallError::Remote {
                node: "air".into(),
                message: "odd".into(),
            }))
        );
    }

    #[test]
    fn failing_a_node_fails_only_its_calls() {
        let calls = PendingCalls::default();
        let (_, mut gone) = waiting(&calls);
        let (other, mut kept) = calls.register(
            PROVIDER + 1,
            "ground".into(),
            "gs/ping",
            Duration::from_secs(1),
        );
        calls.fail_to(PROVIDER, "lease expired");
        assert_eq!(
            gone.try_recv(),
            Ok(Err(CallError::LinkLost {
                node: "air".into(),
                reason: "lease expired".into(),
            }))
        );
        assert!(kept.try_recv().is_err());
        calls.complete(PROVIDER + 1, other, Ok(vec![]));
        assert_eq!(kept.try_recv(), Ok(Ok(vec![])));
    }

    #[test]
    fn a_relayed_failure_reads_back_as_the_same_cause() {
        let after = Duration::from_secs(2);
        let relay = |e: CallError| CallError::from_remote("gw", "f", after, e.relayed("gw"));
        assert!(matches!(
            relay(CallError::Timeout {
                name: "f".into(),
                node: "far".into(),
                after,
            }),
            CallError::Timeout { .. }
        ));
        assert_eq!(
            relay(CallError::Remote {
                node: "far".into(),
                message: "odd".into(),
            }),
            CallError::Remote {
                node: "gw".into(),
                message: "odd (from node 'far')".into(),
            }
        );
        assert_eq!(
            relay(CallError::NoProvider { name: "f".into() }),
            CallError::Remote {
                node: "gw".into(),
                message: "function no longer provided".into(),
            }
        );
    }
}
