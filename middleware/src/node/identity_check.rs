//! Checking peers' identity proofs against the domain's roster (see [`crate::identity`]): a
//! peer's declarations are applied only once its proof verifies and its key is listed for the
//! namespace it announced.

use crate::identity::{allows, check_proof};
use crate::link::auth::hex;
use crate::protocol::NodeId;

use super::NodeInner;

impl NodeInner {
    /// Whether declarations from `node` are taken: always when this node checks no identities,
    /// else only once the peer's key is authenticated for its namespace.
    pub fn identity_allows(&self, node: NodeId) -> bool {
        let Some(p) = self.peers.get(&node) else {
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

    /// A peer's proof: records the namespaces its key may own when the signature verifies.
    pub fn on_identity(&self, node: NodeId, public: [u8; 32], signature: &[u8]) {
        let Some(roster) = self.identity.as_ref().and_then(|i| i.roster.as_ref()) else {
            return;
        };
        let Some(mut p) = self.peers.get_mut(&node) else {
            return;
        };
        let statement = (
            self.me.domain.as_str(),
            node,
            &*p.name,
            p.namespace.as_str(),
        );
        if !check_proof(&public, signature, statement) {
            tracing::warn!(peer = %p.name, key = %hex(&public), "identity proof does not verify: the peer's declarations are refused");
            return;
        }
        let namespaces = roster.namespaces(&public);
        if allows(&namespaces, &p.namespace) {
            tracing::info!(peer = %p.name, namespace = %p.namespace, "peer identity authenticated");
        } else {
            tracing::warn!(peer = %p.name, namespace = %p.namespace, key = %hex(&public), listed_for = ?namespaces, "identity not listed for the namespace the peer declares: its declarations are refused");
        }
        p.authenticated = Some(namespaces);
        drop(p);
        self.bump();
    }
}
