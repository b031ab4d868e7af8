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

/// Who answers a call, with the type it declared.
pub(crate) enum Provider {
    Local(crate::node::RawHandler, TypeInfo),
    Remote {
        node: u64,
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
        find_provider(
            &self.node,
            &self.name,
            Some(&TypeInfo::of_function::<A, R>()),
        )
    }

    /// Whether a provider is known right now.
    pub fn has_provider(&self) -> bool {
        self.find_provider().is_ok()
    }

    /// Waits until a provider is known; returns whether one appeared within `timeout`.
    pub async fn wait_provider(&self, timeout: Duration) -> bool {
        self.node.wait_for(timeout, || self.has_provider()).await
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
        let provider = self.find_provider()?;
        let bytes = invoke(&self.node, &self.name, provider, bytes, timeout).await?;
        crate::codec::decode_payload(&bytes).map_err(|e| CallError::Codec {
            name: self.name.clone(),
            reason: format!("result: {e}"),
        })
    }
}

/// The provider of `name`: local first, then remote. With `expected`, a provider of another
/// type is refused (and reported if no matching one exists); without, any type is taken.
pub(crate) fn find_provider(
    node: &NodeInner,
    name: &str,
    expected: Option<&TypeInfo>,
) -> Result<Provider, CallError> {
    let fits = |ty: &TypeInfo| expected.is_none_or(|e| e == ty);
    let mut mismatch: Option<TypeInfo> = None;
    for o in node.offers.iter() {
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
    for p in node.peers.iter() {
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

/// Invokes a provider with encoded arguments and returns the encoded result.
pub(crate) async fn invoke(
    node: &Arc<NodeInner>,
    name: &str,
    provider: Provider,
    args: Vec<u8>,
    timeout: Duration,
) -> Result<Vec<u8>, CallError> {
    match provider {
        Provider::Local(handler, _) => match tokio::time::timeout(timeout, handler(args)).await {
            Ok(r) => r.map_err(|f| CallError::from_remote(&node.me.name, name, timeout, f)),
            Err(_) => Err(CallError::Timeout {
                name: name.to_owned(),
                node: node.me.name.clone(),
                after: timeout,
            }),
        },
        Provider::Remote {
            node: peer,
            node_name,
            id,
            ..
        } => {
            let call_id = node.next_call.fetch_add(1, Ordering::Relaxed);
            let (tx, rx) = oneshot::channel();
            node.calls.insert(
                call_id,
                PendingCall {
                    node: peer,
                    node_name: node_name.clone(),
                    name: name.to_owned(),
                    timeout,
                    reply: tx,
                },
            );
            let deadline_ms = u32::try_from(timeout.as_millis()).unwrap_or(u32::MAX);
            let sent = node.send_safe_to_node(
                peer,
                &Message::Call {
                    call_id,
                    id,
                    deadline_ms,
                    args,
                },
            );
            if !sent {
                node.calls.remove(&call_id);
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
                    node.calls.remove(&call_id);
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
