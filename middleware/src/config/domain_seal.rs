//! A running mission's seal, found by domain name: `usal run` links its mission's directory
//! at [`domain_seal_dir`] for the run, and a node opened without `<security>` in that domain
//! is sealed from it ([`with_domain_seal`]): the domain key, this node's identity and the
//! domain's roster, and the `<access>` rules the mission gives its namespace. Every tool and
//! service of the same user then joins a running mission's domain with no configuration, and
//! another user (another state directory) finds nothing.
//!
//! The directory, as `usal run` writes it (each key mode 0600, the directory 0700):
//!
//! | file | what |
//! |---|---|
//! | `domain.key` | the domain key (`<security keyFile>`) |
//! | `identities.xml` | the roster: each namespace's identity key, the tools' for any, the gateways' |
//! | `identities/<namespace>.id` | the identity of the mission's nodes of that namespace |
//! | `gateway.id` | the identity of the run's gateways and bridges, the only key listed as a gateway |
//! | `tools.id` | the identity of anything else of this user (`usal list/call` ...) |
//! | `access/<namespace>.xml` | the `<access>` rules of that namespace's nodes, if any |

use std::borrow::Cow;
use std::path::{Path, PathBuf};

use super::{AccessConfig, ConfigLoadError, NetworkConfig, SecurityConfig};

/// Where the seal of `domain` is while a mission of it runs: `<state dir>/domains/<hash>`
/// (the name hashed: any string is a domain name, not every string a file name). `None`
/// without a state directory (see [`crate::process::state_dir`]).
pub fn domain_seal_dir(domain: &str) -> Option<PathBuf> {
    let hash = blake3::hash(domain.as_bytes()).to_hex();
    Some(
        crate::process::state_dir()?
            .join("domains")
            .join(&hash[..32]),
    )
}

/// The identity file of a node of `namespace` in seal directory `dir`.
pub fn identity_path(dir: &Path, namespace: &str) -> PathBuf {
    dir.join("identities").join(format!("{namespace}.id"))
}

/// The identity file of the gateways (and bridges) in seal directory `dir`.
pub fn gateway_identity_path(dir: &Path) -> PathBuf {
    dir.join("gateway.id")
}

/// The access file of the nodes of `namespace` in seal directory `dir`.
pub fn access_path(dir: &Path, namespace: &str) -> PathBuf {
    dir.join("access").join(format!("{namespace}.xml"))
}

/// `config`, sealed from its domain's seal directory ([`domain_seal_dir`]) when it names no
/// `<security>` and a running mission put one there; as it is otherwise. Says which: a node
/// that stays unsealed is told what that means, once, as a warning.
///
/// # Errors
/// The mission's access file for this node's namespace cannot be read.
pub fn with_domain_seal(config: &NetworkConfig) -> Result<Cow<'_, NetworkConfig>, ConfigLoadError> {
    if config.security.is_some() {
        return Ok(Cow::Borrowed(config));
    }
    let Some(dir) = domain_seal_dir(&config.domain).filter(|d| d.join("domain.key").is_file())
    else {
        tracing::warn!(node = %config.node, domain = %config.domain,
            "not sealed: any host on this node's networks can read its items, publish to it and call its functions; give its network.xml <security keyFile=\"...\"/> (usal keygen), or run it with usal run");
        return Ok(Cow::Borrowed(config));
    };
    let existing = |p: PathBuf| p.is_file().then_some(p);
    let namespace = config.namespace.as_deref();
    // A gateway acts as one only with the key the roster lists as a gateway.
    let gateway = config
        .forwards()
        .then(|| existing(gateway_identity_path(&dir)))
        .flatten();
    let identity_file = gateway
        .or_else(|| namespace.and_then(|ns| existing(identity_path(&dir, ns))))
        .or_else(|| existing(dir.join("tools.id")));
    let mut sealed = config.clone();
    sealed.security = Some(SecurityConfig {
        key_file: dir.join("domain.key"),
        encrypt_radio: false,
        identity_file,
        identities: existing(dir.join("identities.xml")),
    });
    if sealed.access.is_none() {
        if let Some(file) = namespace.and_then(|ns| existing(access_path(&dir, ns))) {
            sealed.access = Some(AccessConfig::load(&file)?);
        }
    }
    tracing::info!(node = %config.node, domain = %config.domain, seal = %dir.display(),
        identity = sealed.security.as_ref().and_then(|s| s.identity_file.as_ref()).map(|p| p.display().to_string()),
        access = sealed.access.is_some(),
        "sealed by the running mission of its domain");
    Ok(Cow::Owned(sealed))
}
