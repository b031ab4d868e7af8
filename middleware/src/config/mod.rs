//! `network.xml` loader: turns one node's link configuration file into a typed [`NetworkConfig`],
//! with errors that point at `file:line:column` and say what was expected.
//!
//! The file names the node, its namespace and discovery domain, and the links it talks on:
//!
//! ```xml
//! <network node="air" namespace="rover1" domain="usal">
//!   <ethernet name="lan" bind="0.0.0.0:0" multicast="239.255.77.1:7477" interface="127.0.0.1"
//!             heartbeatMs="1000" leaseMs="3500" ttl="1">
//!     <peer address="192.0.2.10:7400"/>
//!   </ethernet>
//!   <shm name="local" service="usal" wait="event"/>
//!   <serial name="radio" address="/dev/ttyUSB0" baudRate="57600" TimeToResend="1500"
//!           MaxPacketSize="300" MaxMessageQueue="20" heartbeatMs="5000" leaseMs="20000"/>
//!   <serialduo name="duo" addressTx="/dev/ttyUSB0" baudRateTx="115200" addressRx="/dev/ttyUSB1"
//!              baudRateRx="115200" TimeToResend="1500" MaxPacketSize="300" MaxMessageQueue="20"/>
//! </network>
//! ```
//!
//! The serial attribute names are the MAREA thesis' own, so a MAREA user recognises them. Every
//! link element also takes `enabled="false"` to switch it off without deleting or commenting it.
//! `config/network.xml` at the repository root is a fully commented example.
//!
//! The parser walks quick-xml's event reader by hand rather than using its serde deserializer,
//! because only the event reader gives byte positions for every element and attribute, and the
//! positions are what make a configuration error quick to fix.
//!
//! The module: `model` (the typed configuration and its defaults), `error` (what can be wrong and
//! where), `values` (defaults, limits and the syntax of attribute values), `parser` (the walk
//! over the elements with [`crate::xml::Reader`], validating in document order).

use std::net::Ipv4Addr;
use std::path::Path;

use crate::xml::LineIndex;

pub mod access;
pub mod domain_seal;
mod error;
mod model;
mod parser;
mod values;

pub use access::{AccessConfig, AccessKind, AccessRule};
pub use error::{ConfigLoadError, Location};
pub use model::*;

/// The environment a launcher (`usal run`) hands a service it starts, read by
/// [`NetworkConfig::from_env`].
pub mod env {
    /// Path of the node's network.xml.
    pub const NETWORK: &str = "MAREA_NETWORK";
    /// The node name to use when there is no network file.
    pub const NODE: &str = "MAREA_NODE";
    /// The discovery domain (the mission's).
    pub const DOMAIN: &str = "MAREA_DOMAIN";
    /// The namespace of the node's items (`rover1`).
    pub const NAMESPACE: &str = "MAREA_NAMESPACE";
}

/// The discovery domain used when `<network>` has no `domain` attribute.
pub const DEFAULT_DOMAIN: &str = "usal";

impl NetworkConfig {
    /// Whether a node of this configuration forwards between its links (is a gateway): as
    /// `gateway` says, else when a serial link sits beside another link (the radio gateway).
    pub fn forwards(&self) -> bool {
        let has_serial = self
            .links
            .iter()
            .any(|l| matches!(l, LinkConfig::Serial(_) | LinkConfig::SerialDuo(_)));
        self.gateway.unwrap_or(has_serial && self.links.len() > 1)
    }

    /// Reads and parses a `network.xml` file; [`NetworkConfig::source`] records `path`.
    ///
    /// # Errors
    /// [`ConfigLoadError::Unreadable`] when the file cannot be read,
    /// [`ConfigLoadError::NotUtf8`] when it is not UTF-8, and otherwise whatever
    /// [`NetworkConfig::parse`] reports.
    pub fn load(path: impl AsRef<Path>) -> Result<Self, ConfigLoadError> {
        let path = path.as_ref();
        let bytes = std::fs::read(path).map_err(|source| ConfigLoadError::Unreadable {
            path: path.to_path_buf(),
            source,
        })?;
        Self::parse_bytes(&bytes, Some(path))
    }

    /// Parses the text of a `network.xml`. `source` only names the text in errors and in
    /// [`NetworkConfig::source`]; nothing is read from it.
    ///
    /// # Errors
    /// Every other [`ConfigLoadError`] variant: malformed XML, an unexpected element, attribute
    /// or text, a missing or invalid value, or an inconsistent set of links. Each one carries the
    /// line and column of the offending element or attribute.
    pub fn parse(text: &str, source: Option<&Path>) -> Result<Self, ConfigLoadError> {
        let index = LineIndex::new(text);
        parser::Parser::new(text, &index, source).document()
    }

    /// What a service process runs with: the file `network` when given, else
    /// [`NetworkConfig::ethernet_loopback`] for `node`; then `domain` and `namespace`, when
    /// given, override the file's (a launcher keeps one file per node and one domain per run).
    ///
    /// # Errors
    /// The file's [`ConfigLoadError`].
    pub fn for_service(
        network: Option<&Path>,
        node: &str,
        domain: Option<&str>,
        namespace: Option<&str>,
    ) -> Result<Self, ConfigLoadError> {
        let mut config = match network {
            Some(path) => Self::load(path)?,
            None => Self::ethernet_loopback(node),
        };
        if let Some(d) = domain {
            d.clone_into(&mut config.domain);
        }
        if let Some(ns) = namespace {
            config.namespace = Some(ns.to_owned());
        }
        Ok(config)
    }

    /// What a service started by a launcher runs with, from the environment it was handed:
    /// [`env::NETWORK`] (a network.xml), [`env::NODE`] (the node name when there is no file;
    /// else `default_node`), [`env::DOMAIN`] and [`env::NAMESPACE`] (overriding the file's), as
    /// [`NetworkConfig::for_service`] combines them. Outside a launcher, with none set: Ethernet
    /// on loopback as `default_node`, in the default domain. The mission's seal (domain key,
    /// identity) is found by the domain's name, as for the built-in services.
    ///
    /// # Errors
    /// The network file's [`ConfigLoadError`].
    pub fn from_env(default_node: &str) -> Result<Self, ConfigLoadError> {
        Self::from_vars(default_node, |name| {
            std::env::var_os(name).filter(|v| !v.is_empty())
        })
    }

    fn from_vars(
        default_node: &str,
        var: impl Fn(&str) -> Option<std::ffi::OsString>,
    ) -> Result<Self, ConfigLoadError> {
        let text = |name| var(name).map(|v| v.to_string_lossy().into_owned());
        let network = var(env::NETWORK).map(std::path::PathBuf::from);
        let node = text(env::NODE).unwrap_or_else(|| default_node.to_owned());
        Self::for_service(
            network.as_deref(),
            &node,
            text(env::DOMAIN).as_deref(),
            text(env::NAMESPACE).as_deref(),
        )
    }

    /// A configuration for `node` with one Ethernet link on the loopback interface (127.0.0.1)
    /// and defaults otherwise: handy for tests and single-host demos. `node` is not validated.
    pub fn ethernet_loopback(node: &str) -> Self {
        Self {
            node: node.to_owned(),
            namespace: None,
            domain: DEFAULT_DOMAIN.to_owned(),
            links: vec![LinkConfig::Ethernet(EthernetConfig {
                interface: Ipv4Addr::LOCALHOST,
                ..EthernetConfig::default()
            })],
            gateway: None,
            source: None,
            access: None,
            security: None,
        }
    }

    fn parse_bytes(bytes: &[u8], source: Option<&Path>) -> Result<Self, ConfigLoadError> {
        match std::str::from_utf8(bytes) {
            Ok(text) => Self::parse(text, source),
            Err(err) => {
                let valid = bytes.get(..err.valid_up_to()).unwrap_or_default();
                let valid = std::str::from_utf8(valid).unwrap_or_default();
                let pos = LineIndex::new(valid).pos(valid.len());
                Err(ConfigLoadError::NotUtf8 {
                    at: Location {
                        file: source.map(Box::from),
                        line: pos.line as usize,
                        column: pos.col as usize,
                    },
                    source: err,
                })
            }
        }
    }
}

#[cfg(test)]
mod tests;
