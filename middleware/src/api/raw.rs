//! Type-agnostic access for tools (`usal echo`, `usal call`): subscribe to any type and get the
//! encoded bytes with the publisher's type name; call a function with encoded arguments.

use std::sync::Arc;
use std::time::{Duration, Instant};

use super::errors::{DeclareError, RecvError};
use super::service::{Declared, Service};
use crate::node::calls::CallError;
use crate::node::mailbox::{Delivery, Mailbox};
use crate::protocol::{ItemKind, NodeId, Origin};
use crate::typeinfo::TypeInfo;

/// A value as it travelled: still encoded (postcard), with the publisher's type name.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct RawValue {
    /// Full name of the item.
    pub name: String,
    /// Publishing node.
    pub publisher: String,
    /// The publisher's payload type (`std::any::type_name`).
    pub type_name: String,
    /// Its fingerprint ([`TypeInfo::fingerprint`]: the name and the shape): tells two types
    /// of one name apart.
    pub fingerprint: u64,
    /// postcard bytes.
    pub payload: Vec<u8>,
    /// When it arrived.
    pub received: Instant,
}

/// A subscription that accepts any payload type.
pub struct RawSubscription {
    mailbox: Arc<Mailbox>,
    _declared: Declared,
}

impl RawSubscription {
    /// The next value.
    ///
    /// # Errors
    /// [`RecvError::Closed`] at shutdown.
    pub async fn recv(&self) -> Result<RawValue, RecvError> {
        loop {
            match self.mailbox.pop().await {
                Some(Delivery::Sample(s)) => {
                    return Ok(RawValue {
                        name: s.name.to_string(),
                        publisher: s.publisher.to_string(),
                        type_name: s.type_name.to_string(),
                        fingerprint: s.fingerprint,
                        payload: Vec::from(s.payload.bytes),
                        received: s.received,
                    })
                }
                // A type-agnostic interest is never refused; skip defensively.
                Some(Delivery::Refused(_)) => continue,
                None => return Err(RecvError::Closed),
            }
        }
    }

    /// Like [`RawSubscription::recv`] with a time limit.
    ///
    /// # Errors
    /// [`RecvError::Closed`] or [`RecvError::Timeout`].
    pub async fn recv_timeout(&self, timeout: Duration) -> Result<RawValue, RecvError> {
        match tokio::time::timeout(timeout, self.recv()).await {
            Ok(r) => r,
            Err(_) => Err(RecvError::Timeout(timeout)),
        }
    }
}

impl Service {
    /// Subscribes to variables or events matching `pattern`, whatever their type.
    ///
    /// # Errors
    /// [`DeclareError`] for an invalid pattern or a stopping node.
    pub fn subscribe_raw(
        &self,
        kind: ItemKind,
        pattern: &str,
    ) -> Result<RawSubscription, DeclareError> {
        let (mailbox, declared) = self.mailbox_interest(pattern, kind, TypeInfo::any())?;
        Ok(RawSubscription {
            mailbox,
            _declared: declared,
        })
    }

    /// The declared type (`fn(A) -> R`) of the provider of function `name`, if one is known.
    pub fn function_type(&self, name: &str) -> Option<TypeInfo> {
        self.node()
            .find_provider(name, None)
            .ok()
            .map(|p| p.ty().clone())
    }

    /// Calls function `name` with postcard-encoded `args`, whatever its type, and returns the
    /// encoded result.
    ///
    /// # Errors
    /// As [`super::Function::call`], without the type check.
    pub async fn call_raw(
        &self,
        name: &str,
        args: Vec<u8>,
        timeout: Duration,
    ) -> Result<Vec<u8>, CallError> {
        self.node().call(name, None, args, timeout).await
    }

    /// Calls function `name` with postcard-encoded `args` for `namespace/caller`, a party this
    /// node speaks for that is no marea node (the Zenoh bridge's clients, `zenoh/<identity>`):
    /// the call travels as one a gateway relays, so the provider's `<access>` rules match
    /// `namespace/caller`, and the provider accepts it only from a gateway: a node whose Hello
    /// says it forwards (`gateway="true"`), whose identity key the provider's roster lists as
    /// a gateway where it keeps one, and that its `<access kind="gateway">` rules, if any,
    /// allow.
    /// A function this node provides itself runs directly, as any local call.
    ///
    /// # Errors
    /// As [`Service::call_raw`]; [`CallError::Denied`] when the provider refuses the caller or
    /// does not take this node for a gateway.
    pub async fn call_raw_for(
        &self,
        namespace: &str,
        caller: &str,
        name: &str,
        args: Vec<u8>,
        timeout: Duration,
    ) -> Result<Vec<u8>, CallError> {
        let node = self.node();
        let provider = node.find_provider(name, None)?;
        let origin = Origin {
            node: stand_in_id(namespace, caller),
            name: caller.to_owned(),
            hops: 1,
            namespace: namespace.to_owned(),
        };
        node.invoke(name, provider, args, timeout, Some(origin))
            .await
    }
}

/// The node id a relayed call names `namespace/caller` by: stable for a name, so the provider
/// keeps one call lane per function for it (see [`Service::call_raw_for`]).
fn stand_in_id(namespace: &str, caller: &str) -> NodeId {
    let h = blake3::hash(format!("{namespace}/{caller}").as_bytes());
    let b = h.as_bytes();
    u64::from_le_bytes([b[0], b[1], b[2], b[3], b[4], b[5], b[6], b[7]])
}
