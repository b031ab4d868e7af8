//! What the publisher handles of variables and events share: the offer and its declaration,
//! encoding a value, and the remote subscribers.

use std::sync::Arc;
use std::time::Duration;

use super::service::Declared;
use super::Payload;
use crate::node::data::PublishError;
use crate::node::{LocalOffer, NodeInner};

/// An offer a publisher handle keeps declared; dropping it withdraws the offer.
pub(crate) struct Publisher {
    pub node: Arc<NodeInner>,
    pub offer: Arc<LocalOffer>,
    _declared: Declared,
}

impl Publisher {
    pub fn new(node: Arc<NodeInner>, offer: Arc<LocalOffer>, declared: Declared) -> Self {
        Publisher {
            node,
            offer,
            _declared: declared,
        }
    }

    /// `value` encoded for the offer.
    pub fn encode<T: Payload>(&self, value: &T) -> Result<Vec<u8>, PublishError> {
        let bytes = crate::codec::encode_payload(value).map_err(|source| PublishError::Encode {
            name: self.offer.name.to_string(),
            source,
        })?;
        PublishError::check_size(&self.offer.name, bytes.len())?;
        Ok(bytes)
    }

    /// Names of the remote nodes currently subscribed.
    pub fn remote_subscribers(&self) -> Vec<String> {
        self.offer
            .remote
            .get()
            .iter()
            .map(|r| r.node_name.to_string())
            .collect()
    }

    /// Waits until at least `n` remote nodes subscribe; returns whether they did in time.
    pub async fn wait_remote_subscribers(&self, n: usize, timeout: Duration) -> bool {
        self.node
            .wait_for(timeout, || self.offer.remote.get().len() >= n)
            .await
    }
}
