//! Link health as ordinary variables: every link publishes `link/<name>/stats` (under the
//! node's namespace) once a second, so ground stations and `usal echo` can show it. Like any
//! variable it only leaves the node when someone subscribes.

use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use serde::{Deserialize, Serialize};

use super::{LocalOffer, NodeInner, OfferRole};
use crate::link::LinkStats;
use crate::protocol::{Declaration, ItemKind};
use crate::typeinfo::TypeInfo;

/// How often link health is published.
pub const PERIOD: Duration = Duration::from_secs(1);

/// Name of the pseudo-service owning the link-health variables.
pub(crate) const SERVICE_NAME: &str = "links";

/// The health of one link over the last period, as published on `link/<name>/stats`.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct LinkHealth {
    /// The link's name from network.xml.
    pub link: String,
    /// Peers reached over it now.
    pub peers: u32,
    /// Smoothed round trip of safe messages in ms, the worst over its peers (0: not measured).
    pub rtt_ms: f32,
    /// Received frames dropped as corrupt, as a fraction of the frames received, this period.
    pub loss: f32,
    /// Safe messages sent again, as a fraction of the frames sent, this period.
    pub retransmit_ratio: f32,
    /// Bytes per second received this period (framing included).
    pub in_bps: f64,
    /// Bytes per second sent this period (framing included).
    pub out_bps: f64,
    /// Safe messages waiting to be sent or acknowledged now.
    pub safe_queued: u64,
    /// Fast messages waiting to be sent now.
    pub fast_queued: u64,
    /// Counters since the link opened.
    pub totals: LinkStats,
    /// What peers on this link were refused by our `<access>` rules since the node opened
    /// (calls, files, publications, gateways).
    pub denied: u64,
    /// What peers on this link were refused otherwise since the node opened: offers outside
    /// their namespace, origins from non-gateways, forged Byes, caps reached, identity proofs
    /// answering no challenge, files a sink refused.
    pub rejected: u64,
}

impl LinkHealth {
    /// The health over the period between two readings of a link's counters.
    pub fn between(
        link: &str,
        peers: u32,
        old: &LinkStats,
        new: &LinkStats,
        period: Duration,
    ) -> Self {
        let d = |a: u64, b: u64| b.saturating_sub(a) as f64;
        let secs = period.as_secs_f64().max(1e-3);
        let frames_in = d(old.frames_in, new.frames_in);
        let corrupt = d(old.corrupt, new.corrupt);
        let frames_out = d(old.frames_out, new.frames_out);
        let ratio = |num: f64, den: f64| if den > 0.0 { (num / den) as f32 } else { 0.0 };
        LinkHealth {
            link: link.to_owned(),
            peers,
            rtt_ms: new.rtt_us as f32 / 1000.0,
            loss: ratio(corrupt, frames_in + corrupt),
            retransmit_ratio: ratio(d(old.retransmitted, new.retransmitted), frames_out),
            in_bps: d(old.bytes_in, new.bytes_in) / secs,
            out_bps: d(old.bytes_out, new.bytes_out) / secs,
            safe_queued: new.safe_queued,
            fast_queued: new.fast_queued,
            totals: *new,
            denied: 0,
            rejected: 0,
        }
    }
}

impl NodeInner {
    /// Declares the `links` pseudo-service and one health variable per link, and publishes
    /// them every [`PERIOD`] until the node stops.
    pub fn start_link_health(self: &Arc<Self>) {
        let links = self.links().to_vec();
        if links.is_empty() {
            return;
        }
        let service = self.local.fresh_id();
        self.local.services.insert(service, SERVICE_NAME.into());
        self.declare(
            Declaration::Service {
                id: service,
                name: SERVICE_NAME.into(),
            },
            None,
        );
        let prefix = self
            .me
            .namespace
            .as_ref()
            .map(|n| format!("{n}/"))
            .unwrap_or_default();
        let offers: Vec<Arc<LocalOffer>> = links
            .iter()
            .map(|l| {
                let offer = Arc::new(LocalOffer {
                    id: self.local.fresh_id(),
                    service,
                    kind: ItemKind::Variable,
                    name: format!("{prefix}link/{}/stats", l.name()).into(),
                    ty: TypeInfo::of::<LinkHealth>(),
                    role: OfferRole::Variable {
                        last: Mutex::new(None),
                    },
                    remote: Default::default(),
                    local: Mutex::default(),
                    has_local: Default::default(),
                    refused: Mutex::default(),
                    origin: None,
                    hidden_on: None,
                });
                self.add_offer(offer.clone());
                offer
            })
            .collect();
        let inner = self.clone();
        crate::sync::spawn_tracked(&self.tasks, async move {
            let mut last: Vec<(LinkStats, Instant)> =
                links.iter().map(|l| (l.stats(), Instant::now())).collect();
            let mut tick = tokio::time::interval(PERIOD);
            tick.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
            tick.tick().await;
            loop {
                tokio::select! {
                    _ = inner.cancel.cancelled() => break,
                    _ = tick.tick() => {}
                }
                for (index, (link, offer)) in links.iter().zip(&offers).enumerate() {
                    let now = Instant::now();
                    let stats = link.stats();
                    let peers = inner.peers.by_id.iter().filter(|p| p.link == index).count() as u32;
                    let (old, at) = &last[index];
                    let mut health =
                        LinkHealth::between(link.name(), peers, old, &stats, now - *at);
                    (health.denied, health.rejected) = inner.policy.counts(index);
                    last[index] = (stats, now);
                    match crate::codec::encode_payload(&health) {
                        Ok(bytes) => inner.publish_variable(offer, bytes),
                        Err(e) => {
                            tracing::warn!(link = link.name(), error = %e, "link health not encoded")
                        }
                    }
                }
            }
        });
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn health_is_computed_over_the_period() {
        let old = LinkStats {
            frames_in: 100,
            frames_out: 100,
            bytes_in: 1000,
            bytes_out: 2000,
            ..LinkStats::default()
        };
        let new = LinkStats {
            frames_in: 190,
            corrupt: 10,
            frames_out: 300,
            retransmitted: 20,
            bytes_in: 3000,
            bytes_out: 6000,
            rtt_us: 120_500,
            safe_queued: 3,
            ..LinkStats::default()
        };
        let h = LinkHealth::between("radio", 1, &old, &new, Duration::from_secs(2));
        assert_eq!(h.loss, 0.1);
        assert_eq!(h.retransmit_ratio, 0.1);
        assert_eq!(h.in_bps, 1000.0);
        assert_eq!(h.out_bps, 2000.0);
        assert_eq!(h.rtt_ms, 120.5);
        assert_eq!(h.safe_queued, 3);
        assert_eq!(h.totals, new);
        // Counters that went backwards (a link reopened) give zero, not nonsense.
        let h = LinkHealth::between("radio", 1, &new, &old, Duration::from_secs(1));
        assert_eq!((h.in_bps, h.loss), (0.0, 0.0));
    }
}
