//! What variables and events share: a value as a local subscriber gets it, the error of a value
//! that cannot be encoded, and the data path from peers (runs of their messages to the local
//! subscribers of each one's route).

use std::sync::Arc;
use std::time::Instant;

use super::mailbox::{Delivery, Encoded, RawSample};
use super::policy::Refusal;
use super::NodeInner;
use crate::config::AccessKind;
use crate::protocol::NodeId;

/// Pushes (and empties) `payloads`, received at `received`, into the mailbox of every local
/// subscriber on `route`: one push of the whole run per mailbox (the last one takes the
/// payloads, the others clones of them: the same buffers).
fn push_to_route(route: &super::Route, payloads: &mut Vec<Encoded>, received: Instant) {
    let sample = |payload: Encoded| {
        Delivery::Sample(RawSample {
            name: route.name.clone(),
            publisher: route.publisher.clone(),
            type_name: route.type_name.clone(),
            fingerprint: route.fingerprint,
            payload,
            received,
        })
    };
    let mailboxes: Vec<_> = route
        .targets
        .iter()
        .filter_map(|i| i.mailbox.as_ref())
        .collect();
    if let Some((last, others)) = mailboxes.split_last() {
        for m in others {
            m.deliver_run(payloads.iter().cloned().map(sample));
        }
        last.deliver_run(payloads.drain(..).map(sample));
    }
    payloads.clear();
}

impl NodeInner {
    /// Delivers a run of data messages from `node` (in order) to the local subscribers of each
    /// one's route. The clock is read and the peer marked heard once for the run; consecutive
    /// messages of one offer (a stream) share one route lookup and one push per mailbox.
    pub fn deliver_remote_run(&self, node: NodeId, run: impl Iterator<Item = (u32, Encoded)>) {
        let received = Instant::now();
        if let Some(p) = self.peers.by_id.get(&node) {
            p.heard_at(self.me.epoch, tokio::time::Instant::from_std(received));
        }
        let mut current: Option<(u32, Arc<super::Route>)> = None;
        let mut payloads: Vec<Encoded> = Vec::new();
        for (id, payload) in run {
            if self.gateway.is_some() {
                self.forward_data(node, id, &payload.bytes);
            }
            if current.as_ref().map(|(i, _)| *i) != Some(id) {
                if let Some((_, route)) = &current {
                    push_to_route(route, &mut payloads, received);
                }
                current = self
                    .peers
                    .by_id
                    .get(&node)
                    .and_then(|p| p.routes.get(&id).cloned())
                    .map(|r| (id, r));
                if current.is_none() {
                    self.undeliverable(node, id);
                    continue;
                }
            }
            payloads.push(payload);
        }
        if let Some((_, route)) = &current {
            push_to_route(route, &mut payloads, received);
        }
    }

    /// Data for an offer with no route here: refused by our `<access>` rules (reported), or
    /// unknown (a declaration not yet applied, or a subscription just closed).
    fn undeliverable(&self, node: NodeId, id: u32) {
        let denied = self.peers.by_id.get(&node).and_then(|p| {
            let o = p.offers.get(&id).filter(|o| o.denied)?;
            Some((p.link, p.name.clone(), o.name.clone()))
        });
        match denied {
            Some((link, peer, name)) => self.policy.refuse(
                link,
                node,
                &peer,
                &name,
                Refusal::Denied(AccessKind::Publish),
            ),
            None => tracing::debug!(
                peer = format_args!("{node:016x}"),
                id,
                "data for an unknown or unrouted offer dropped"
            ),
        }
    }
}

/// Why a value could not be published.
#[derive(Debug, thiserror::Error)]
pub enum PublishError {
    /// The value could not be encoded.
    #[error("cannot encode value for '{name}': {source}")]
    Encode {
        /// Item name.
        name: String,
        /// postcard's error.
        source: postcard::Error,
    },
    /// The value encodes to more than marea carries ([`crate::protocol::MAX_PAYLOAD`]):
    /// nothing was sent. Send it as a file instead, or in pieces.
    #[error("'{name}': a value of {size} bytes is larger than the {max} bytes marea carries")]
    TooLarge {
        /// Item name.
        name: String,
        /// Its encoded size.
        size: usize,
        /// [`crate::protocol::MAX_PAYLOAD`].
        max: usize,
    },
}

impl PublishError {
    /// [`PublishError::TooLarge`] for a payload of `size` bytes over the limit.
    pub(crate) fn check_size(name: &str, size: usize) -> Result<(), PublishError> {
        let max = crate::protocol::MAX_PAYLOAD;
        if size > max {
            return Err(PublishError::TooLarge {
                name: name.to_owned(),
                size,
                max,
            });
        }
        Ok(())
    }
}

impl super::LocalOffer {
    /// A value of this offer of ours (published by node `me`, received at `received`) as a
    /// local subscriber's mailbox takes it.
    pub(crate) fn own_sample(&self, me: &str, payload: Vec<u8>, received: Instant) -> Delivery {
        let payload = payload.into();
        Delivery::Sample(RawSample {
            name: self.name.clone(),
            publisher: me.into(),
            type_name: self.ty.name.as_str().into(),
            fingerprint: self.ty.fingerprint,
            payload,
            received,
        })
    }
}
