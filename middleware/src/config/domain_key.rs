//! Domain keys found by domain name: `usal run` puts its mission's key at
//! [`domain_key_path`] for the run, and a node opened without `<security>` in that domain is
//! sealed with it ([`with_domain_key`]). Every tool and service of the same user then joins a
//! running mission's domain with no configuration, and another user (another state directory)
//! finds nothing.

use std::borrow::Cow;
use std::path::PathBuf;

use super::{NetworkConfig, SecurityConfig};

/// Where the key of `domain` is while a mission of it runs: `<state dir>/domains/<hash>.key`
/// (the name hashed: any string is a domain name, not every string a file name). `None`
/// without a state directory (see [`crate::process::state_dir`]).
pub fn domain_key_path(domain: &str) -> Option<PathBuf> {
    let hash = blake3::hash(domain.as_bytes()).to_hex();
    Some(
        crate::process::state_dir()?
            .join("domains")
            .join(format!("{}.key", &hash[..32])),
    )
}

/// `config`, sealed with its domain's key when it names no `<security>` and that key is at
/// [`domain_key_path`]; as it is otherwise. Says which: a node that stays unsealed is told
/// what that means, once, as a warning.
pub fn with_domain_key(config: &NetworkConfig) -> Cow<'_, NetworkConfig> {
    if config.security.is_some() {
        return Cow::Borrowed(config);
    }
    match domain_key_path(&config.domain).filter(|p| p.is_file()) {
        Some(key_file) => {
            tracing::info!(node = %config.node, domain = %config.domain, key = %key_file.display(),
                "sealed with the domain key of a running mission");
            let mut sealed = config.clone();
            sealed.security = Some(SecurityConfig {
                key_file,
                encrypt_radio: false,
                identity_file: None,
                identities: None,
            });
            Cow::Owned(sealed)
        }
        None => {
            tracing::warn!(node = %config.node, domain = %config.domain,
                "not sealed: any host on this node's networks can read its items, publish to it and call its functions; give its network.xml <security keyFile=\"...\"/> (usal keygen), or run it with usal run");
            Cow::Borrowed(config)
        }
    }
}
