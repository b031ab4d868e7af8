//! Variables: publishing a value (kept for late joiners, sent on the fast class, coalesced
//! while unsent) and serving a new subscriber the newest one.

use std::time::Instant;

use super::loans::MessageLoan;
use super::{lock, LocalOffer, NodeInner, OfferRole};
use crate::codec::encode_data_message_of_payload;
use crate::link::Outgoing;
use crate::protocol::NodeId;

/// The newest value of offer `o`, if it is a variable that has one.
pub(super) fn last_value(o: &LocalOffer) -> Option<Vec<u8>> {
    match &o.role {
        OfferRole::Variable { last } => lock(last).clone(),
        _ => None,
    }
}

impl NodeInner {
    /// Publishes a variable value: stored for late joiners, delivered locally, and sent to every
    /// remote subscriber on the fast class (coalesced per variable while unsent).
    pub fn publish_variable(&self, offer: &LocalOffer, bytes: Vec<u8>) {
        self.keep_and_deliver_locally(offer, &bytes);
        let remote = offer.remote.get();
        if remote.is_empty() {
            return;
        }
        let mut msg = Some(encode_data_message_of_payload(false, offer.id, &bytes));
        let n = remote.len();
        for (k, r) in remote.iter().enumerate() {
            let msg = if k + 1 == n {
                msg.take().unwrap_or_default()
            } else {
                msg.clone().unwrap_or_default()
            };
            self.send_to(
                r.link,
                r.addr,
                Outgoing::Fast {
                    coalesce: Some(offer.id),
                    msg,
                },
            );
        }
    }

    /// Publishes the variable value written in `loan` (its payload from `at`), as
    /// [`Self::publish_variable`] does; when the link of the offer's only subscriber lent the
    /// buffer, the value goes in it, without a copy and reliably (a sample written in place
    /// cannot wait to be replaced by the next one), else as a copy on the fast class.
    pub fn publish_loaned_variable(&self, offer: &LocalOffer, loan: MessageLoan, at: usize) {
        let Some(path) = loan.path_among(&offer.remote.get()) else {
            let mut payload = loan.into_vec();
            payload.drain(..at);
            return self.publish_variable(offer, payload);
        };
        let mut buf = loan.buf;
        self.keep_and_deliver_locally(offer, &buf.init()[at..]);
        self.send_loan(path, buf, None);
    }

    /// Keeps the encoded value `bytes` of `offer` for late joiners and delivers it to the
    /// local subscribers.
    fn keep_and_deliver_locally(&self, offer: &LocalOffer, bytes: &[u8]) {
        if let OfferRole::Variable { last } = &offer.role {
            // Into the previous value's buffer: no allocation per publish.
            let mut last = lock(last);
            match last.as_mut() {
                Some(v) => {
                    v.clear();
                    v.extend_from_slice(bytes);
                }
                None => *last = Some(bytes.to_vec()),
            }
        }
        for i in lock(&offer.local).iter() {
            if let Some(m) = &i.mailbox {
                m.push(offer.own_sample(&self.me.name, bytes.to_vec(), Instant::now()));
            }
        }
    }

    /// Sends `node` the newest value of every variable of ours it subscribes to (safe class).
    pub fn resend_last_values(&self, node: NodeId, link: usize, addr: crate::link::PeerAddr) {
        let offers = self.local.offers_now();
        for o in offers {
            let OfferRole::Variable { last } = &o.role else {
                continue;
            };
            if !o.remote.get().iter().any(|r| r.node == node) {
                continue;
            }
            if let Some(v) = lock(last).clone() {
                let msg = encode_data_message_of_payload(false, o.id, &v).into();
                self.send_to(link, addr, Outgoing::Safe { msg, done: None });
            }
        }
    }
}
