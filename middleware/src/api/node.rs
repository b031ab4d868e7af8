//! [`Node`]: one per process; opens the links of a `network.xml`, hosts services, and lists
//! what the network offers.

use std::collections::HashMap;
use std::sync::{Arc, Mutex, OnceLock};
use std::time::Duration;

use serde::{Deserialize, Serialize};
use tokio::sync::watch;
use tokio_util::sync::CancellationToken;
use tokio_util::task::TaskTracker;

use super::errors::{DeclareError, NodeOpenError};
use super::service::{IService, Service, ServiceError};
use crate::config::{LinkConfig, NetworkConfig};
#[cfg(feature = "serial")]
use crate::link::serial::{port::SerialPorts, stp::StpConfig, SerialLink};
#[cfg(feature = "shm")]
use crate::link::shm::{ShmLink, ShmLinkOptions};
#[cfg(feature = "udp")]
use crate::link::{
    arq::ArqConfig,
    udp::{UdpLink, UdpLinkOptions},
};
use crate::link::{Link, LinkStats};
use crate::name;
use crate::node::discovery::domain_hash;
use crate::node::{Handler, Identity, NodeInner};
use crate::protocol::{ItemKind, Message};

/// A middleware node. Dropping it without [`Node::shutdown`] stops its tasks too, but without
/// telling peers (they notice when the lease expires).
pub struct Node {
    pub(crate) inner: Arc<NodeInner>,
    hosted: tokio::sync::Mutex<Vec<Box<dyn IService>>>,
}

/// What a node knows of one peer.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct PeerInfo {
    /// Node name.
    pub name: String,
    /// Namespace.
    pub namespace: String,
    /// Link it is reached on.
    pub link: String,
    /// Address on that link.
    pub addr: String,
    /// Milliseconds since it was last heard.
    pub last_seen_ms: u64,
    /// The namespaces its identity key is authenticated for (`<security identities=..>`):
    /// `None` when this node checks no identities, empty until the peer proved a listed key.
    pub authenticated_namespaces: Option<Vec<String>>,
    /// How many services, offers and interests it declares now.
    pub declarations: usize,
    /// Whether what it announces (namespace, node name) is proven.
    #[serde(default)]
    pub trust: PeerTrust,
    /// Whether it acts as a gateway towards this node (speaks for other nodes).
    #[serde(default)]
    pub gateway: bool,
    /// Whether what it and this node exchange is sealed with the keys only the two of them
    /// hold (both proved their identities), so a frame is taken as its because its key sealed
    /// it, not because of the address it came from.
    #[serde(default)]
    pub pair_sealed: bool,
}

/// How far a node takes a peer at its word ([`PeerInfo::trust`]).
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize)]
pub enum PeerTrust {
    /// This node keeps no roster: what the peer announces is taken as said.
    #[default]
    Claimed,
    /// This node keeps a roster and the peer's identity proof has not come (a node without
    /// an identity key never sends one): nothing it declares is taken.
    Pending,
    /// Its key is listed for the namespace and node name it announces: its declarations are
    /// taken.
    Proven,
    /// Its proof is valid but its key is not listed for the namespace and node name it
    /// announces: nothing it declares is taken.
    Refused,
}

/// Whether an item is offered or wanted.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub enum ItemRole {
    /// Published / provided / accepted.
    Offer,
    /// Subscribed / called.
    Interest,
}

/// One item of a service, for listings.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct ItemDescription {
    /// Variable, event, function or file.
    pub kind: ItemKind,
    /// Offered or wanted.
    pub role: ItemRole,
    /// Full name (or pattern for interests).
    pub name: String,
    /// Payload type name.
    pub type_name: String,
}

/// A node and its services, for listings.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct NodeDescription {
    /// Node name.
    pub name: String,
    /// Namespace.
    pub namespace: String,
    /// Whether this is the local node.
    pub local: bool,
    /// Services with their items.
    pub services: Vec<super::service::ServiceDescription>,
}

/// Everything a node knows about the network.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct Catalog {
    /// The local node first, then peers by name.
    pub nodes: Vec<NodeDescription>,
}

/// The ports and engine tuning of a `<serial>` or `<serialduo>` link, if `lc` is one.
#[cfg(feature = "serial")]
fn serial_setup(lc: &LinkConfig) -> Option<(&str, SerialPorts, StpConfig)> {
    match lc {
        LinkConfig::SerialDuo(s) => Some((
            &s.name,
            SerialPorts::Duo {
                tx_path: s.address_tx.clone(),
                tx_baud: s.baud_rate_tx,
                rx_path: s.address_rx.clone(),
                rx_baud: s.baud_rate_rx,
            },
            StpConfig::new(
                s.baud_rate_tx,
                s.time_to_resend,
                s.max_packet_size,
                s.max_message_queue,
            ),
        )),
        LinkConfig::Serial(s) => Some((
            &s.name,
            SerialPorts::Single {
                path: s.address.clone(),
                baud: s.baud_rate,
            },
            StpConfig::new(
                s.baud_rate,
                s.time_to_resend,
                s.max_packet_size,
                s.max_message_queue,
            ),
        )),
        _ => None,
    }
}

/// The optional link kinds a build has (its cargo features).
#[derive(Debug, Clone, Copy)]
struct LinksBuilt {
    udp: bool,
    shm: bool,
    serial: bool,
    zenoh: bool,
}

/// This build's: a value rather than `cfg!`s at the check, so every answer is tested in every
/// build.
const LINKS_BUILT: LinksBuilt = LinksBuilt {
    udp: cfg!(feature = "udp"),
    shm: cfg!(feature = "shm"),
    serial: cfg!(feature = "serial"),
    zenoh: cfg!(feature = "zenoh"),
};

/// Refuses a configuration naming a link kind `built` lacks, before any link opens.
fn links_built(config: &NetworkConfig, built: LinksBuilt) -> Result<(), NodeOpenError> {
    for l in &config.links {
        let missing = match l {
            LinkConfig::Shm(_) => !built.shm,
            LinkConfig::Serial(_) | LinkConfig::SerialDuo(_) => !built.serial,
            LinkConfig::Ethernet(_) => !built.udp,
            LinkConfig::Zenoh(_) => !built.zenoh,
        };
        if missing {
            return Err(not_built(l));
        }
    }
    Ok(())
}

/// The refusal of link `link` (`<ethernet>`, `<shm>`, `<serial>`, `<serialduo>`) by a build
/// without the cargo feature that brings it.
fn not_built(link: &LinkConfig) -> NodeOpenError {
    let (kind, feature) = match link {
        LinkConfig::Ethernet(_) => ("Ethernet", "udp"),
        LinkConfig::Shm(_) => ("shared-memory", "shm"),
        LinkConfig::Serial(_) | LinkConfig::SerialDuo(_) => ("serial", "serial"),
        LinkConfig::Zenoh(_) => ("Zenoh", "zenoh"),
    };
    NodeOpenError::Unsupported {
        link: link.name().to_owned(),
        kind,
        feature,
    }
}

impl Node {
    /// Opens the links of `config`, announces the node and starts discovery. A `config`
    /// without `<security>` is sealed by its domain's running mission of the same user, when
    /// there is one: its key, identities and access rules ([`crate::config::domain_seal`]);
    /// else the node warns that it is not.
    ///
    /// # Errors
    /// [`NodeOpenError`] when a link cannot be opened, the running mission's access file for
    /// this node cannot be read ([`NodeOpenError::Config`]), or is an `<ethernet>` (`<shm>`,
    /// `<serial>`, `<serialduo>`) link and this build lacks the cargo feature `udp` (`shm`,
    /// `serial`) ([`NodeOpenError::Unsupported`]).
    // A build with no link kind at all (every link feature off) opens none: nothing uses a
    // link's index or handler there.
    #[cfg_attr(
        not(any(feature = "udp", feature = "shm", feature = "serial")),
        allow(unused_variables)
    )]
    pub async fn open(config: &NetworkConfig) -> Result<Node, NodeOpenError> {
        let config = &*crate::config::domain_seal::with_domain_seal(config)?;
        links_built(config, LINKS_BUILT)?;
        name::validate_name(&config.node)?;
        if let Some(ns) = &config.namespace {
            name::validate_name(ns)?;
        }
        let security = match &config.security {
            Some(s) => Some(crate::link::auth::LinkSecurity {
                key: crate::link::auth::DomainKey::load(&s.key_file)?,
                encrypt_radio: s.encrypt_radio,
            }),
            None => None,
        };
        let id: crate::protocol::NodeId = rand::random();
        let identity = match &config.security {
            Some(s) if s.identity_file.is_some() || s.identities.is_some() => {
                let key = match &s.identity_file {
                    Some(f) => Some(crate::identity::IdentityKey::load(f)?),
                    None => None,
                };
                let roster = match &s.identities {
                    Some(f) => Some(crate::identity::Roster::load(f)?),
                    None => None,
                };
                Some(crate::node::IdentityLayer {
                    key,
                    roster,
                    agreement: crate::identity::KeyAgreement::new(),
                })
            }
            _ => None,
        };
        let roster = identity.as_ref().is_some_and(|i| i.roster.is_some());
        if config.access.as_ref().is_some_and(|a| !a.trust_claims) && !roster {
            return Err(NodeOpenError::AccessWithoutRoster {
                node: config.node.clone(),
            });
        }
        let link_timing: Vec<(Duration, Duration)> = config
            .links
            .iter()
            .map(|l| match l {
                LinkConfig::Ethernet(e) => (e.heartbeat, e.lease),
                LinkConfig::Shm(s) => (s.heartbeat, s.lease),
                LinkConfig::Serial(s) => (s.heartbeat, s.lease),
                LinkConfig::SerialDuo(s) => (s.heartbeat, s.lease),
                LinkConfig::Zenoh(z) => (z.heartbeat, z.lease),
            })
            .collect();
        let (heartbeat, lease) = link_timing
            .iter()
            .copied()
            .min()
            .unwrap_or((Duration::from_secs(1), Duration::from_millis(3500)));
        let (changed, _) = watch::channel(0u64);
        let forwards = config.forwards();
        let inner = Arc::new(NodeInner {
            me: Identity {
                id,
                name: config.node.clone(),
                namespace: config.namespace.clone().filter(|n| !n.is_empty()),
                domain: config.domain.clone(),
                domain_hash: domain_hash(&config.domain),
                heartbeat,
                lease,
                link_timing,
                epoch: tokio::time::Instant::now(),
            },
            links: OnceLock::new(),
            local: Default::default(),
            peers: Default::default(),
            calls: Default::default(),
            transfers: Default::default(),
            changed,
            tasks: TaskTracker::new(),
            cancel: CancellationToken::new(),
            path_switches: Default::default(),
            identity,
            routing: Mutex::new(()),
            policy: crate::node::policy::Policy::new(config.access.clone(), config.links.len()),
            congestion: Arc::default(),
            // The pseudo-service id is the first id handed out (ids start at 1).
            gateway: forwards.then(|| crate::node::gateway::Gateway::new(1)),
        });
        if let Some(gw) = &inner.gateway {
            let id = inner.local.fresh_id();
            debug_assert_eq!(id, gw.service);
            inner
                .local
                .services
                .insert(id, crate::node::gateway::SERVICE_NAME.into());
            inner.declare(
                crate::protocol::Declaration::Service {
                    id,
                    name: crate::node::gateway::SERVICE_NAME.into(),
                },
                None,
            );
        }
        let mut links: Vec<Arc<dyn Link>> = Vec::new();
        for (index, lc) in config.links.iter().enumerate() {
            let handler = Arc::new(Handler(Arc::downgrade(&inner)));
            let opened: Result<Arc<dyn Link>, NodeOpenError> = match lc {
                #[cfg(feature = "udp")]
                LinkConfig::Ethernet(e) => UdpLink::open(
                    index,
                    UdpLinkOptions {
                        name: e.name.clone(),
                        bind: e.bind,
                        multicast: e.multicast,
                        interface: e.interface,
                        ttl: e.ttl,
                        peers: e.peers.clone(),
                        mtu: 1400,
                        arq: ArqConfig::lan(),
                        security: security.clone(),
                    },
                    handler,
                    &inner.tasks,
                    inner.cancel.child_token(),
                )
                .map(|l| l as Arc<dyn Link>)
                .map_err(Into::into),
                #[cfg(feature = "serial")]
                LinkConfig::Serial(_) | LinkConfig::SerialDuo(_) => {
                    let Some((name, ports, stp)) = serial_setup(lc) else {
                        continue;
                    };
                    SerialLink::open(
                        index,
                        name,
                        Arc::new(ports),
                        stp,
                        security.as_ref(),
                        handler,
                        &inner.tasks,
                        inner.cancel.child_token(),
                    )
                    .map(|l| l as Arc<dyn Link>)
                    .map_err(Into::into)
                }
                #[cfg(feature = "shm")]
                LinkConfig::Shm(s) => ShmLink::open(
                    index,
                    ShmLinkOptions {
                        name: s.name.clone(),
                        service: s.service.clone(),
                        scan: s.heartbeat,
                        wait: s.wait,
                        max_peers: s.max_peers,
                        security: security.clone(),
                    },
                    handler,
                    &inner.tasks,
                    inner.cancel.child_token(),
                )
                .await
                .map(|l| l as Arc<dyn Link>)
                .map_err(Into::into),
                #[cfg(feature = "zenoh")]
                LinkConfig::Zenoh(z) => crate::link::zenoh::ZenohLink::open(
                    index,
                    crate::link::zenoh::ZenohLinkOptions {
                        name: z.name.clone(),
                        mode: z.mode,
                        connect: z.connect.clone(),
                        listen: z.listen.clone(),
                        config_file: z.config_file.clone(),
                        lease: z.lease,
                        domain: config.domain.clone(),
                        node: config.node.clone(),
                        arq: crate::link::arq::ArqConfig::lan(),
                        security: security.clone(),
                    },
                    handler,
                    &inner.tasks,
                    inner.cancel.child_token(),
                )
                .await
                .map(|l| l as Arc<dyn Link>)
                .map_err(Into::into),
                // `links_built` refused these already; kept so the match stays exhaustive.
                #[cfg(not(feature = "udp"))]
                LinkConfig::Ethernet(_) => Err(not_built(lc)),
                #[cfg(not(feature = "shm"))]
                LinkConfig::Shm(_) => Err(not_built(lc)),
                #[cfg(not(feature = "serial"))]
                LinkConfig::Serial(_) | LinkConfig::SerialDuo(_) => Err(not_built(lc)),
                #[cfg(not(feature = "zenoh"))]
                LinkConfig::Zenoh(_) => Err(not_built(lc)),
            };
            match opened {
                Ok(l) => links.push(l),
                Err(e) => {
                    // The links opened so far stop with the node's token.
                    inner.cancel.cancel();
                    return Err(e);
                }
            }
        }
        // Only this function sets the links, once, before any task can read them.
        let _ = inner.links.set(links);
        for link in 0..inner.links().len() {
            let hb = inner.clone();
            crate::sync::spawn_tracked(&inner.tasks, hb.heartbeat_loop(link));
        }
        inner.start_link_health();
        crate::sync::spawn_tracked(&inner.tasks, inner.clone().tell_peers_when_behind());
        inner.announce_hello();
        tracing::info!(node = %config.node, id = format_args!("{:016x}", inner.me.id), authenticated = security.is_some(), "node open");
        Ok(Node {
            inner,
            hosted: tokio::sync::Mutex::new(Vec::new()),
        })
    }

    /// This node's name.
    pub fn name(&self) -> &str {
        &self.inner.me.name
    }

    /// This node's namespace, if any.
    pub fn namespace(&self) -> Option<&str> {
        self.inner.me.namespace.as_deref()
    }

    /// Declares a service on this node; its items are named `namespace/service/item`.
    ///
    /// # Errors
    /// [`DeclareError`] when the name is invalid or the node is stopping.
    pub fn service(&self, name: &str) -> Result<Service, DeclareError> {
        Service::create(self.inner.clone(), name)
    }

    /// Starts a service: creates its context and calls [`IService::start`]. The node calls
    /// [`IService::stop`] at shutdown.
    ///
    /// # Errors
    /// What the service's `start` returns, or a declaration error.
    pub async fn add_service(&self, mut service: Box<dyn IService>) -> Result<(), ServiceError> {
        let ctx = self.service(service.name())?;
        service.start(ctx).await?;
        self.hosted.lock().await.push(service);
        Ok(())
    }

    /// The peers currently known.
    pub fn peers(&self) -> Vec<PeerInfo> {
        let links = self.inner.links();
        let mut v: Vec<PeerInfo> = self
            .inner
            .peers
            .by_id
            .iter()
            .map(|p| PeerInfo {
                name: p.name.to_string(),
                namespace: p.namespace.clone(),
                link: links
                    .get(p.link)
                    .map(|l| l.name().to_owned())
                    .unwrap_or_default(),
                addr: p.addr.to_string(),
                last_seen_ms: p.last_heard(self.inner.me.epoch).elapsed().as_millis() as u64,
                authenticated_namespaces: p.authenticated.as_ref().map(|g| g.namespaces()),
                declarations: p.declarations(),
                trust: match &p.authenticated {
                    None => PeerTrust::Claimed,
                    Some(_) if p.proven() => PeerTrust::Proven,
                    Some(_) if p.challenge.is_none() => PeerTrust::Refused,
                    Some(_) => PeerTrust::Pending,
                },
                gateway: p.gateway,
                pair_sealed: links.get(p.link).is_some_and(|l| l.pair_sealed(p.addr)),
            })
            .collect();
        v.sort_by(|a, b| a.name.cmp(&b.name));
        v
    }

    /// The names of the nodes this node knows are there: its peers, and the nodes beyond
    /// gateways whose offers they forward (a node beyond a gateway that offers nothing is not
    /// seen from here). Sorted, each once.
    pub fn node_names(&self) -> Vec<String> {
        let mut names = std::collections::BTreeSet::new();
        for p in self.inner.peers.by_id.iter() {
            names.insert(p.name.to_string());
            for o in p.offers.values() {
                if let Some(origin) = &o.origin_name {
                    names.insert(origin.to_string());
                }
            }
        }
        names.into_iter().collect()
    }

    /// Waits until `pred` holds on this node's view of the network, re-checking whenever the
    /// peer table or the routes change. Returns whether it held within `timeout`.
    pub async fn wait_until(&self, timeout: Duration, mut pred: impl FnMut(&Node) -> bool) -> bool {
        self.inner.wait_for(timeout, || pred(self)).await
    }

    /// Whether some peer offers an item of `kind` whose name matches `pattern`.
    pub fn is_offered(&self, kind: ItemKind, pattern: &str) -> bool {
        self.inner.peers.by_id.iter().any(|p| {
            p.offers
                .values()
                .any(|o| o.kind == kind && name::matches(pattern, &o.name))
        }) || self
            .inner
            .local
            .offers
            .iter()
            .any(|o| o.kind == kind && name::matches(pattern, &o.name))
    }

    /// Counters of every link, by link name.
    pub fn link_stats(&self) -> Vec<(String, LinkStats)> {
        self.inner
            .links()
            .iter()
            .map(|l| (l.name().to_owned(), l.stats()))
            .collect()
    }

    /// What this node forwards as a gateway (empty when it is not one), with the age of the
    /// newest value or event that passed through each item.
    pub fn forwarded(&self) -> Vec<crate::api::ForwardedItem> {
        self.inner.forwarded_items()
    }

    /// Whether this node forwards between its links.
    pub fn is_gateway(&self) -> bool {
        self.inner.gateway.is_some()
    }

    /// Local addresses of the links (for logs).
    pub fn link_addrs(&self) -> Vec<String> {
        self.inner.links().iter().map(|l| l.local_addr()).collect()
    }

    /// Messages dropped because they could not be decoded or came from an unknown sender.
    pub fn dropped_input(&self) -> (u64, u64) {
        use std::sync::atomic::Ordering::Relaxed;
        (
            self.inner.policy.dropped.undecodable.load(Relaxed),
            self.inner.policy.dropped.unknown_sender.load(Relaxed),
        )
    }

    /// Everything this node refused from peers since it opened: by the `<access>` rules, by
    /// its own rules (owned names, origins, forged Byes, caps), at the links' seals (no key,
    /// replays), and as malformed or unbounded input. Summed over the links; per link, see
    /// [`LinkHealth`](crate::LinkHealth) and [`Node::link_stats`].
    pub fn refusals(&self) -> crate::node::policy::RefusalReport {
        let mut r = crate::node::policy::RefusalReport::default();
        for l in 0..self.inner.links().len().max(1) {
            let (denied, rejected) = self.inner.policy.counts(l);
            r.denied += denied;
            r.rejected += rejected;
        }
        for l in self.inner.links() {
            let s = l.stats();
            r.auth_rejected += s.auth_rejected;
            r.replay_rejected += s.replay_rejected;
        }
        self.inner.policy.dropped.add_to(&mut r);
        r
    }

    /// Everything this node knows: itself and every peer, with services and items.
    pub fn catalog(&self) -> Catalog {
        catalog_of(&self.inner)
    }

    /// Stops the hosted services, tells peers we leave, and waits for every task the node owns
    /// (links, discovery, transfers, service tasks) to end. Returns whether all ended within
    /// 5 s; a task that did not is logged.
    pub async fn shutdown(self) -> bool {
        let mut hosted = std::mem::take(&mut *self.hosted.lock().await);
        for s in hosted.iter_mut() {
            if let Err(e) = s.stop().await {
                tracing::warn!(service = s.name(), error = %e, "service stop failed");
            }
        }
        drop(hosted);
        self.inner.say_bye();
        self.inner.announce(&Message::Bye {
            node_id: self.inner.me.id,
        });
        self.inner.cancel.cancel();
        self.inner.close_mailboxes();
        self.inner.tasks.close();
        let clean = tokio::time::timeout(Duration::from_secs(5), self.inner.tasks.wait())
            .await
            .is_ok();
        if !clean {
            tracing::warn!(
                left = self.inner.tasks.len(),
                "some node tasks did not stop within 5 s"
            );
        }
        clean
    }
}

impl Drop for Node {
    fn drop(&mut self) {
        self.inner.cancel.cancel();
        self.inner.close_mailboxes();
        self.inner.tasks.close();
    }
}

/// Everything `node` knows: itself and every peer, with services and items.
pub(super) fn catalog_of(node: &NodeInner) -> Catalog {
    use super::node::{ItemDescription as I, ItemRole as R};
    let mut nodes = Vec::new();
    let mut services: HashMap<u32, super::service::ServiceDescription> = node
        .local
        .services
        .iter()
        .map(|e| {
            (
                *e.key(),
                super::service::ServiceDescription {
                    name: e.value().to_string(),
                    items: Vec::new(),
                },
            )
        })
        .collect();
    for o in node.local.offers.iter() {
        if let Some(s) = services.get_mut(&o.service) {
            s.items.push(I {
                kind: o.kind,
                role: R::Offer,
                name: o.name.to_string(),
                type_name: o.ty.name.clone(),
            });
        }
    }
    for i in node.local.interests.iter() {
        if let Some(s) = services.get_mut(&i.service) {
            s.items.push(I {
                kind: i.kind,
                role: R::Interest,
                name: i.pattern.clone(),
                type_name: i.ty.name.clone(),
            });
        }
    }
    for s in services.values_mut() {
        s.items.sort_by(|a, b| a.name.cmp(&b.name));
    }
    let mut svc_list: Vec<_> = services.into_values().collect();
    svc_list.sort_by(|a, b| a.name.cmp(&b.name));
    nodes.push(NodeDescription {
        name: node.me.name.clone(),
        namespace: node.me.namespace.clone().unwrap_or_default(),
        local: true,
        services: svc_list,
    });
    let mut remote: Vec<NodeDescription> = node
        .peers
        .by_id
        .iter()
        .map(|p| {
            let mut svcs: HashMap<u32, super::service::ServiceDescription> = p
                .services
                .iter()
                .map(|(id, n)| {
                    (
                        *id,
                        super::service::ServiceDescription {
                            name: n.clone(),
                            items: Vec::new(),
                        },
                    )
                })
                .collect();
            for (role, map) in [(R::Offer, &p.offers), (R::Interest, &p.interests)] {
                for it in map.values() {
                    if let Some(s) = svcs.get_mut(&it.service) {
                        s.items.push(I {
                            kind: it.kind,
                            role,
                            name: it.name.to_string(),
                            type_name: it.ty.name.clone(),
                        });
                    }
                }
            }
            let mut list: Vec<_> = svcs.into_values().collect();
            for s in &mut list {
                s.items.sort_by(|a, b| a.name.cmp(&b.name));
            }
            list.sort_by(|a, b| a.name.cmp(&b.name));
            NodeDescription {
                name: p.name.to_string(),
                namespace: p.namespace.clone(),
                local: false,
                services: list,
            }
        })
        .collect();
    remote.sort_by(|a, b| a.name.cmp(&b.name));
    nodes.extend(remote);
    Catalog { nodes }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::config::ShmConfig;

    fn with_shm() -> NetworkConfig {
        let mut c = NetworkConfig::ethernet_loopback("n");
        c.links.push(LinkConfig::Shm(ShmConfig {
            name: "local".into(),
            ..ShmConfig::default()
        }));
        c
    }

    const ALL: LinksBuilt = LinksBuilt {
        udp: true,
        shm: true,
        serial: true,
        zenoh: true,
    };

    fn with_serial() -> NetworkConfig {
        let mut c = NetworkConfig::ethernet_loopback("n");
        c.links
            .push(LinkConfig::Serial(crate::config::SerialConfig {
                name: "radio".into(),
                ..Default::default()
            }));
        c
    }

    #[test]
    fn a_build_without_shm_refuses_a_shm_link_by_name_and_feature() {
        let err = links_built(&with_shm(), LinksBuilt { shm: false, ..ALL })
            .expect_err("no shm in this build");
        assert!(matches!(
            &err,
            NodeOpenError::Unsupported { link, feature: "shm", .. } if link == "local"
        ));
        assert_eq!(
            err.to_string(),
            "link local: this build of marea has no shared-memory link (cargo feature `shm`)"
        );
    }

    #[test]
    fn a_build_without_udp_refuses_an_ethernet_link_by_name_and_feature() {
        let config = NetworkConfig::ethernet_loopback("n");
        let name = config.links[0].name().to_owned();
        let err = links_built(&config, LinksBuilt { udp: false, ..ALL })
            .expect_err("no UDP in this build");
        assert_eq!(
            err.to_string(),
            format!("link {name}: this build of marea has no Ethernet link (cargo feature `udp`)")
        );
        // A shared-memory-only configuration opens in such a build.
        let mut shm_only = with_shm();
        shm_only.links.retain(|l| matches!(l, LinkConfig::Shm(_)));
        assert!(links_built(&shm_only, LinksBuilt { udp: false, ..ALL }).is_ok());
    }

    #[test]
    fn a_build_without_serial_refuses_a_serial_link_by_name_and_feature() {
        let err = links_built(
            &with_serial(),
            LinksBuilt {
                serial: false,
                ..ALL
            },
        )
        .expect_err("no serial in this build");
        assert_eq!(
            err.to_string(),
            "link radio: this build of marea has no serial link (cargo feature `serial`)"
        );
        assert!(links_built(
            &with_shm(),
            LinksBuilt {
                serial: false,
                ..ALL
            }
        )
        .is_ok());
    }

    #[test]
    fn a_build_with_shm_takes_every_link_and_one_without_takes_the_others() {
        assert!(links_built(&with_shm(), ALL).is_ok());
        assert!(links_built(&with_serial(), ALL).is_ok());
        assert!(links_built(&with_serial(), LinksBuilt { shm: false, ..ALL }).is_ok());
        let udp = NetworkConfig::ethernet_loopback("n");
        let udp_alone = LinksBuilt {
            udp: true,
            shm: false,
            serial: false,
            zenoh: false,
        };
        assert!(links_built(&udp, udp_alone).is_ok());
        assert!(links_built(&udp, ALL).is_ok());
    }

    #[test]
    fn a_build_without_zenoh_refuses_a_zenoh_link_by_name_and_feature() {
        let mut config = NetworkConfig::ethernet_loopback("n");
        config
            .links
            .push(LinkConfig::Zenoh(crate::config::ZenohConfig {
                name: "wan".into(),
                connect: vec!["tcp/127.0.0.1:7447".into()],
                ..Default::default()
            }));
        let err = links_built(
            &config,
            LinksBuilt {
                zenoh: false,
                ..ALL
            },
        )
        .expect_err("a <zenoh> link taken by a build without Zenoh");
        let text = err.to_string();
        assert!(
            text.contains("link wan") && text.contains("cargo feature `zenoh`"),
            "{text}"
        );
        assert!(links_built(&config, ALL).is_ok());
    }

    #[cfg(not(feature = "shm"))]
    #[tokio::test]
    async fn opening_a_shm_link_without_the_feature_fails_before_any_link_opens() {
        let err = match Node::open(&with_shm()).await {
            Ok(_) => panic!("a node with a <shm> link opened without the shm feature"),
            Err(e) => e,
        };
        assert!(err.to_string().contains("cargo feature `shm`"), "{err}");
    }
}
