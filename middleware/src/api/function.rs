//! Remote invocations, typed: the provider's handle and the caller's [`Function`] (request and
//! response with a deadline and distinct errors for no provider, timeout, remote error and link
//! lost). The call protocol under them is `node::call`.

use std::marker::PhantomData;
use std::sync::Arc;
use std::time::Duration;

use super::service::Declared;
use super::Payload;
use crate::node::calls::CallError;
use crate::node::{LocalOffer, NodeInner};
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

    /// Whether a provider is known right now.
    pub fn has_provider(&self) -> bool {
        self.node
            .find_provider(&self.name, Some(&TypeInfo::of_function::<A, R>()))
            .is_ok()
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
        let expected = TypeInfo::of_function::<A, R>();
        let bytes = (self.node)
            .call(&self.name, Some(&expected), bytes, timeout)
            .await?;
        crate::codec::decode_payload(&bytes).map_err(|e| CallError::Codec {
            name: self.name.clone(),
            reason: format!("result: {e}"),
        })
    }
}
