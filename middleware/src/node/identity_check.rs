//! Checking peers' identity proofs against the domain's roster (see [`crate::identity`]): each
//! peer registered gets a challenge with a fresh nonce; a peer's declarations are applied only
//! once its answer verifies for that nonce and its key is listed for the namespace it announced.
//! A proof that does not answer a pending challenge (a replay, another nonce, another key) is
//! refused and counted.

use crate::identity::{allows, check_proof, Challenge};
use crate::link::auth::hex;
use crate::link::PeerAddr;
use crate::protocol::{Message, NodeId};

use super::policy::Refusal;
use super::NodeInner;

impl NodeInner {
    /// Whether declarations from `node` are taken: always when this node checks no identities,
    /// else only once the peer's key is authenticated for its namespace.
    pub fn identity_allows(&self, node: NodeId) -> bool {
        let Some(p) = self.peers.by_id.get(&node) else {
            return false;
        };
        let ok = match &p.authenticated {
            None => true,
            Some(ns) => allows(ns, &p.namespace),
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

    /// A peer's challenge: we answer with our proof over its nonce, if we have a key.
    pub fn on_challenge(&self, node: NodeId, nonce: [u8; 16]) {
        let Some(key) = self.identity.as_ref().and_then(|i| i.key.as_ref()) else {
            return;
        };
        let namespace = self.me.namespace.clone().unwrap_or_default();
        let signature = key.prove(
            (&self.me.domain, self.me.id, &self.me.name, &namespace),
            &Challenge {
                verifier: node,
                nonce,
            },
        );
        self.send_safe_to_node(
            node,
            &Message::Identity {
                public_key: key.public(),
                signature: signature.to_vec(),
            },
        );
    }

    /// A peer's proof: records the namespaces its key may own when it answers our pending
    /// challenge, then asks again for the declarations refused meanwhile.
    pub fn on_identity(&self, node: NodeId, public: [u8; 32], signature: &[u8]) {
        let Some(roster) = self.identity.as_ref().and_then(|i| i.roster.as_ref()) else {
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
                &Challenge {
                    verifier: self.me.id,
                    nonce,
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
        let namespaces = roster.namespaces(&public);
        if allows(&namespaces, &p.namespace) {
            tracing::info!(peer = %p.name, namespace = %p.namespace, "peer identity authenticated");
        } else {
            tracing::warn!(peer = %p.name, namespace = %p.namespace, key = %hex(&public), listed_for = ?namespaces, "identity not listed for the namespace the peer declares: its declarations are refused");
        }
        p.authenticated = Some(namespaces);
        p.challenge = None;
        let since = p.known;
        drop(p);
        // Declarations that came before the proof were refused: ask again from where we are.
        self.send_safe_to_node(node, &Message::DeclRequest { since });
        self.bump();
    }
}
