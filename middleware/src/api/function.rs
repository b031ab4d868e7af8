//! Remote invocations: request/response with a deadline and distinct errors for no provider,
//! timeout, remote error and link lost.

use std::marker::PhantomData;
use std::sync::atomic::Ordering;
use std::sync::Arc;
use std::time::Duration;

use tokio::sync::oneshot;

use super::errors::CallError;
use super::service::Declared;
use super::Payload;
use crate::node::{LocalOffer, NodeInner, OfferRole, PendingCall};
use crate::protocol::{ItemKind, Message};
use crate::typeinfo::TypeInfo;

/// Keeps a provided function declared; dropping it withdraws the function.
pub struct FunctionProvider {
    offer: Arc<LocalOffer>,
    _declared: Declared,
}

impl FunctionProvider {
    pub(crate) fn new(offer: Arc<LocalOffer>, declared: Declared) -> Self {
        FunctionProvider {
            offer,
            _declared: declared,
        }
    }

    /// Full name.
    pub fn name(&self) -> &str {
        &self.offer.name
    }
}

/// A client of one function.
pub struct Function<A, R> {
    node: Arc<NodeInner>,
    name: String,
    _declared: Declared,
    _t: PhantomData<fn(A) -> R>,
}

enum Provider {
    Local(crate::node::RawHandler),
    Remote {
        node: u64,
        node_name: Arc<str>,
        id: u32,
    },
}

impl<A: Payload, R: Payload> Function<A, R> {
    pub(crate) fn new(node: Arc<NodeInner>, name: String, declared: Declared) -> Self {
        Function {
            node,
            name,
            _declared: declared,
            _t: PhantomData,
        }
    }

    /// Full name of the function.
    pub fn name(&self) -> &str {
        &self.name
    }

    fn find_provider(&self) -> Result<Provider, CallError> {
        let expected = TypeInfo::of_function::<A, R>();
        let mut mismatch: Option<TypeInfo> = None;
        for o in self.node.offers.iter() {
            if o.kind == ItemKind::Function && *o.name == *self.name {
                if o.ty == expected {
                    if let OfferRole::Function { handler } = &o.role {
                        return Ok(Provider::Local(handler.clone()));
                    }
                } else {
                    mismatch = Some(o.ty.clone());
                }
            }
        }
        for p in self.node.peers.iter() {
            for (id, o) in &p.offers {
                if o.kind == ItemKind::Function && *o.name == *self.name {
                    if o.ty == expected {
                        return Ok(Provider::Remote {
                            node: p.id,
                            node_name: p.name.clone(),
                            id: *id,
                        });
                    }
                    mismatch = Some(o.ty.clone());
                }
            }
        }
        match mismatch {
            Some(offered) => Err(CallError::TypeMismatch {
                name: self.name.clone(),
                offered: offered.name,
                expected: expected.name,
            }),
            None => Err(CallError::NoProvider {
                name: self.name.clone(),
            }),
        }
    }

    /// Whether a provider is known right now.
    pub fn has_provider(&self) -> bool {
        self.find_provider().is_ok()
    }

    /// Waits until a provider is known; returns whether one appeared within `timeout`.
    pub async fn wait_provider(&self, timeout: Duration) -> bool {
        let mut rx = self.node.changed.subscribe();
        let deadline = tokio::time::Instant::now() + timeout;
        loop {
            if self.has_provider() {
                return true;
            }
            match tokio::time::timeout_at(deadline, rx.changed()).await {
                Ok(Ok(())) => {}
                _ => return self.has_provider(),
            }
        }
    }

    /// Calls the function and waits at most `timeout` for the answer.
    ///
    /// # Errors
    /// [`CallError::NoProvider`] at once when nobody provides it, [`CallError::Timeout`],
    /// [`CallError::Remote`] with the provider's message, [`CallError::LinkLost`] when the
    /// provider goes away first, [`CallError::TypeMismatch`], [`CallError::Codec`].
    pub async fn call(&self, args: &A, timeout: Duration) -> Result<R, CallError> {
        let bytes = crate::codec::encode_payload(args).map_err(|e| CallError::Codec {
            name: self.name.clone(),
            reason: format!("arguments: {e}"),
        })?;
        let (result, node_name) = match self.find_provider()? {
            Provider::Local(handler) => match tokio::time::timeout(timeout, handler(bytes)).await {
                Ok(r) => (
                    r.map_err(|f| CallError::from_remote(&self.node.me.name, f)),
                    self.node.me.name.clone(),
                ),
                Err(_) => {
                    return Err(CallError::Timeout {
                        name: self.name.clone(),
                        node: self.node.me.name.clone(),
                        after: timeout,
                    })
                }
            },
            Provider::Remote {
                node,
                node_name,
                id,
            } => {
                let call_id = self.node.next_call.fetch_add(1, Ordering::Relaxed);
                let (tx, rx) = oneshot::channel();
                self.node.calls.insert(
                    call_id,
                    PendingCall {
                        node,
                        node_name: node_name.clone(),
                        reply: tx,
                    },
                );
                let deadline_ms = u32::try_from(timeout.as_millis()).unwrap_or(u32::MAX);
                if !self.node.send_safe_to_node(
                    node,
                    &Message::Call {
                        call_id,
                        id,
                        deadline_ms,
                        args: bytes,
                    },
                ) {
                    self.node.calls.remove(&call_id);
                    return Err(CallError::LinkLost {
                        node: node_name.to_string(),
                        reason: "peer no longer known".into(),
                    });
                }
                match tokio::time::timeout(timeout, rx).await {
                    Ok(Ok(r)) => (r, node_name.to_string()),
                    Ok(Err(_)) => {
                        return Err(CallError::LinkLost {
                            node: node_name.to_string(),
                            reason: "node shutting down".into(),
                        })
                    }
                    Err(_) => {
                        self.node.calls.remove(&call_id);
                        return Err(CallError::Timeout {
                            name: self.name.clone(),
                            node: node_name.to_string(),
                            after: timeout,
                        });
                    }
                }
            }
        };
        let _ = node_name;
        let bytes = result?;
        crate::codec::decode_payload(&bytes).map_err(|e| CallError::Codec {
            name: self.name.clone(),
            reason: format!("result: {e}"),
        })
    }
}
