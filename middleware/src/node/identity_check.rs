//! Checking peers' identity proofs against the domain's roster (see [`crate::identity`]): each
//! peer registered gets a challenge with a fresh nonce; a peer's declarations are applied only
//! once its answer verifies for that nonce and its key is listed for the namespace and node
//! name it announced; it acts as a gateway only when its key is also listed as one. A proof
//! that does not answer a pending challenge (a replay, another nonce, another key) is refused
//! and counted.

use crate::identity::{check_proof, Challenge};
use crate::link::auth::hex;
use crate::link::PeerAddr;
use crate::protocol::{Message, NodeId};

use super::policy::Refusal;
use super::NodeInner;

impl NodeInner {
    /// Whether declarations from `node` are taken: always when this node checks no identities,
    /// else only once the peer's key is authenticated for its namespace and node name.
    pub fn identity_allows(&self, node: NodeId) -> bool {
        let Some(p) = self.peers.by_id.get(&node) else {
            return false;
        };
        let ok = match &p.authenticated {
            None => true,
            Some(grant) => grant.covers(&p.namespace, &p.name),
        };
        if !ok {
            tracing::debug!(peer = %p.name, namespace = %p.namespace, "declarations of a peer not authenticated for its namespace refused");
        }
        ok
    }

    /// The nonce of our unanswered challenge to the peer at `addr` on `link`, if any.
    pub fn pending_challenge(&self, link: usize, addr: PeerAddr) -> Option<[u8; 16]> {
        self.identity.as_ref()?.roster.as_ref()?;
        let node = *self.peers.by_addr.get(&(link, addr))?;
        self.peers.by_id.get(&node)?.challenge
    }

    /// Our key agreement half of this run (zeros when we check and prove no identities: a
    /// low-order point, which gives no pair keys).
    pub fn agreement_public(&self) -> [u8; 32] {
        self.identity
            .as_ref()
            .map_or([0; 32], |i| i.agreement.public())
    }

    /// A peer's challenge: we answer with our proof over its nonce and both key agreement
    /// halves, if we have a key.
    pub fn on_challenge(&self, node: NodeId, nonce: [u8; 16], agreement: [u8; 32]) {
        let Some(layer) = self.identity.as_ref() else {
            return;
        };
        let Some(key) = layer.key.as_ref() else {
            return;
        };
        match self.peers.by_id.get_mut(&node) {
            Some(mut p) => p.handshake.theirs = Some(nonce),
            None => return,
        }
        let ours = layer.agreement.public();
        let namespace = self.me.namespace.clone().unwrap_or_default();
        let signature = key.prove(
            (&self.me.domain, self.me.id, &self.me.name, &namespace),
            &ours,
            &Challenge {
                verifier: node,
                nonce,
                agreement,
            },
        );
        self.send_safe_to_node(
            node,
            &Message::Identity {
                public_key: key.public(),
                signature: signature.to_vec(),
                agreement: ours,
            },
        );
        self.use_pair(node);
    }

    /// Makes the keys we share with `node` once its proof verified and both challenges are
    /// known, and hands them to its link (which seals with them once the peer shows it holds
    /// them too).
    fn use_pair(&self, node: NodeId) {
        let Some(layer) = self.identity.as_ref() else {
            return;
        };
        let made = {
            let Some(mut p) = self.peers.by_id.get_mut(&node) else {
                return;
            };
            let h = &p.handshake;
            let (Some(ours), Some(theirs), Some(agreement)) = (h.ours, h.theirs, h.agreement)
            else {
                return;
            };
            if p.pair.is_some() {
                return;
            }
            p.pair = layer
                .agreement
                .pair_keys(
                    &agreement,
                    &self.me.domain,
                    (self.me.id, node),
                    (ours, theirs),
                )
                .map(std::sync::Arc::new);
            p.pair.clone().map(|k| (p.link, p.addr, k))
        };
        if let Some((link, addr, keys)) = made {
            if let Some(l) = self.links().get(link) {
                l.set_pair(addr, Some(keys));
            }
        }
    }

    /// A peer's proof: records what its key is listed for when it answers our pending
    /// challenge, and the keys we share with it, then asks again for the declarations refused
    /// meanwhile.
    pub fn on_identity(
        &self,
        node: NodeId,
        public: [u8; 32],
        signature: &[u8],
        agreement: [u8; 32],
    ) {
        let Some(layer) = self.identity.as_ref() else {
            return;
        };
        let Some(roster) = layer.roster.as_ref() else {
            return;
        };
        let Some(mut p) = self.peers.by_id.get_mut(&node) else {
            return;
        };
        let (link, name) = (p.link, p.name.clone());
        let verified = p.challenge.is_some_and(|nonce| {
            check_proof(
                &public,
                signature,
                (
                    self.me.domain.as_str(),
                    node,
                    &*p.name,
                    p.namespace.as_str(),
                ),
                &agreement,
                &Challenge {
                    verifier: self.me.id,
                    nonce,
                    agreement: layer.agreement.public(),
                },
            )
        });
        if !verified {
            // A second answer to a challenge already answered (we sent our Hello, and with
            // it the challenge, more than once) is no attack.
            let answered = p.challenge.is_none();
            drop(p);
            if !answered {
                tracing::debug!(peer = %name, key = %hex(&public), "identity proof does not answer our challenge");
                self.policy
                    .refuse(link, node, &name, "identity", Refusal::IdentityUnproven);
            }
            return;
        }
        let grant = roster.grant(&public);
        let covered = grant.covers(&p.namespace, &p.name);
        // Keys shared only with a node proven to be what it announces.
        if covered {
            p.handshake.agreement = Some(agreement);
        }
        if covered {
            tracing::info!(peer = %p.name, namespace = %p.namespace, gateway = p.claims_gateway && grant.gateway_for(&p.namespace, &p.name), "peer identity authenticated");
        } else {
            tracing::warn!(peer = %p.name, namespace = %p.namespace, key = %hex(&public), listed_for = ?grant.namespaces(), nodes = ?grant.nodes(), "identity not listed for the namespace and node name the peer declares: its declarations are refused");
        }
        // A gateway's role comes from the roster, never from its own Hello.
        let listed_gateway = grant.gateway_for(&p.namespace, &p.name);
        p.gateway = p.claims_gateway && listed_gateway;
        let unlisted_gateway = p.claims_gateway && !listed_gateway;
        p.authenticated = Some(grant);
        p.challenge = None;
        let since = p.known;
        drop(p);
        if unlisted_gateway {
            self.policy
                .refuse(link, node, &name, "gateway", Refusal::GatewayNotListed);
        }
        self.use_pair(node);
        // Declarations that came before the proof were refused: ask again from where we are.
        self.send_safe_to_node(node, &Message::DeclRequest { since });
        self.bump();
    }
}

#[cfg(test)]
mod tests {
    use super::super::{bare_node_with_identity, test_hello as hello, IdentityLayer};
    use crate::identity::{Challenge, IdentityKey, KeyAgreement, Listing, Roster};
    use crate::link::PeerAddr;
    use crate::protocol::{Declaration, ItemKind, LoggedDeclaration, NodeId, Origin};
    use crate::typeinfo::TypeInfo;

    #[tokio::test]
    async fn a_peer_is_a_gateway_only_when_the_roster_lists_its_key_as_one() {
        let gateway_key = IdentityKey::from_bytes([1; 32]);
        let tools_key = IdentityKey::from_bytes([2; 32]);
        let vas_key = IdentityKey::from_bytes([3; 32]);
        let mut roster = Roster::default();
        roster.list(Listing {
            key: gateway_key.public(),
            namespaces: vec!["*".into()],
            nodes: Vec::new(),
            gateway: true,
        });
        roster.allow(tools_key.public(), vec!["*".into()]);
        roster.list(Listing {
            key: vas_key.public(),
            namespaces: vec!["rover1".into()],
            nodes: vec!["vas".into()],
            gateway: false,
        });
        let me = bare_node_with_identity(
            Some("gcs"),
            None,
            Some(IdentityLayer {
                key: Some(IdentityKey::from_bytes([8; 32])),
                roster: Some(roster),
                agreement: KeyAgreement::from_bytes([9; 32]),
            }),
        );
        // Each peer's key agreement half, from its id.
        let agreement = |id: NodeId| KeyAgreement::from_bytes([id as u8 + 100; 32]);
        let prove = |id: NodeId, key: &IdentityKey, node: &str, namespace: &str| {
            let nonce = me.peers.by_id.get(&id).and_then(|p| p.challenge).unwrap();
            let theirs = agreement(id).public();
            let sig = key.prove(
                (crate::config::DEFAULT_DOMAIN, id, node, namespace),
                &theirs,
                &Challenge {
                    verifier: me.me.id,
                    nonce,
                    agreement: me.agreement_public(),
                },
            );
            me.on_identity(id, key.public(), &sig, theirs);
        };
        let addr = |port| PeerAddr::Udp(std::net::SocketAddr::from(([127, 0, 0, 1], port)));
        // Two nodes announcing themselves gateways: the run's gateway, and a tool with a key
        // listed for any namespace but not as a gateway.
        me.on_discovery(0, addr(1), hello(1, "relay", "", true));
        me.on_discovery(0, addr(2), hello(2, "relay2", "", true));
        assert!(
            !me.peers.by_id.get(&1).unwrap().gateway,
            "a Hello alone makes no gateway where a roster is kept"
        );
        prove(1, &gateway_key, "relay", "");
        prove(2, &tools_key, "relay2", "");
        assert!(me.peers.by_id.get(&1).unwrap().gateway);
        assert!(!me.peers.by_id.get(&2).unwrap().gateway);
        let (_, rejected) = me.policy.counts(0);
        assert_eq!(rejected, 1, "the unlisted gateway counted");
        let forwarded = Declaration::Offer {
            id: 10,
            service: 1,
            kind: ItemKind::Function,
            name: "rover1/vas/arm".into(),
            ty: TypeInfo::of::<u64>(),
            origin: Some(Origin {
                node: 77,
                name: "vas".into(),
                hops: 1,
                namespace: "rover1".into(),
            }),
        };
        for peer in [1, 2] {
            me.apply_decl_batch(
                peer,
                0,
                1,
                false,
                vec![LoggedDeclaration {
                    counter: 1,
                    decl: forwarded.clone(),
                }],
            );
        }
        assert_eq!(me.peers.by_id.get(&1).unwrap().offers.len(), 1);
        assert!(
            me.peers.by_id.get(&2).unwrap().offers.is_empty(),
            "an unlisted gateway's forwarded offer is refused"
        );

        // Node names are bound: the VAS's key proves node `vas` of rover1, not `fpma`.
        me.on_discovery(0, addr(3), hello(3, "vas", "rover1", false));
        me.on_discovery(0, addr(4), hello(4, "fpma", "rover1", false));
        prove(3, &vas_key, "vas", "rover1");
        prove(4, &vas_key, "fpma", "rover1");
        assert!(me.identity_allows(3));
        assert!(
            !me.identity_allows(4),
            "a node name the key is not listed for"
        );

        // Keys shared with the proven node only, once it challenged us too (its nonce is
        // part of them), the same the node derives on its side.
        let pair_of = |id: NodeId| me.peers.by_id.get(&id).and_then(|p| p.pair.clone());
        assert!(pair_of(3).is_none(), "its nonce not known yet");
        me.on_challenge(3, [33; 16], agreement(3).public());
        me.on_challenge(4, [44; 16], agreement(4).public());
        let pair = pair_of(3).expect("a pair");
        let our_nonce = me
            .peers
            .by_id
            .get(&3)
            .and_then(|p| p.handshake.ours)
            .unwrap();
        let theirs = agreement(3)
            .pair_keys(
                &me.agreement_public(),
                crate::config::DEFAULT_DOMAIN,
                (3, me.me.id),
                ([33; 16], our_nonce),
            )
            .unwrap();
        assert_eq!((pair.send, pair.recv), (theirs.recv, theirs.send));
        assert!(pair_of(4).is_none(), "refused: no keys");
        me.cancel.cancel();
    }
}
