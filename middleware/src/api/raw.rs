//! Type-agnostic access for tools (`usal echo`, `usal call`): subscribe to any type and get the
//! encoded bytes with the publisher's type name; call a function with encoded arguments.

use std::sync::Arc;
use std::time::{Duration, Instant};

use super::errors::{DeclareError, RecvError};
use super::service::{Declared, Service};
use crate::node::call::CallError;
use crate::node::mailbox::{Delivery, Mailbox};
use crate::protocol::ItemKind;
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
                        payload: s.payload,
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
}
