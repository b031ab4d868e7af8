//! Errors of the public API, one enum per operation family.

use std::time::Duration;

use crate::name::NameParseError;
use crate::node::mailbox::TypeMismatch;

/// Why a node could not be opened.
#[derive(Debug, thiserror::Error)]
pub enum NodeOpenError {
    /// An Ethernet (UDP) link failed to open.
    #[cfg(feature = "udp")]
    #[error(transparent)]
    Link(#[from] crate::link::udp::LinkOpenError),
    /// A serial link could not be opened.
    #[cfg(feature = "serial")]
    #[error(transparent)]
    Serial(#[from] crate::link::serial::SerialLinkOpenError),
    /// A shared-memory link could not be opened.
    #[cfg(feature = "shm")]
    #[error(transparent)]
    Shm(#[from] crate::link::shm::ShmLinkOpenError),
    /// A Zenoh link could not be opened.
    #[cfg(feature = "zenoh")]
    #[error(transparent)]
    Zenoh(#[from] crate::link::zenoh::ZenohLinkOpenError),
    /// The configuration asks for a link kind this build of marea was compiled without.
    #[error("link {link}: this build of marea has no {kind} link (cargo feature `{feature}`)")]
    Unsupported {
        /// Link name.
        link: String,
        /// Kind of link (`Ethernet`, `shared-memory`, `serial`, `Zenoh`).
        kind: &'static str,
        /// The cargo feature of `marea` that brings it (`udp`, `shm`, `serial`, `zenoh`).
        feature: &'static str,
    },
    /// The domain key named by `<security keyFile=..>` cannot be used.
    #[error(transparent)]
    Key(#[from] crate::link::auth::KeyFileError),
    /// The domain's identities file (`<security identities=..>`) cannot be used.
    #[error(transparent)]
    Roster(#[from] crate::identity::RosterLoadError),
    /// A configuration file the node was given by its domain's running mission (its access
    /// rules) cannot be used.
    #[error(transparent)]
    Config(#[from] crate::config::ConfigLoadError),
    /// `<access>` rules without a roster to prove the names they match, and no
    /// `trustClaims="yes"` to take peers at their word.
    #[error("node {node}: its <access> rules match the namespace/node names peers claim, and no roster proves them: anyone on its links could name itself what a rule allows. Give the node a roster (<security keyFile=.. identityFile=.. identities=\"identities.xml\">: usal keygen --identity, docs/security.md), or take peers at their word with <access trustClaims=\"yes\">")]
    AccessWithoutRoster {
        /// The node.
        node: String,
    },
    /// A name in the configuration is invalid.
    #[error("invalid node name or namespace: {0}")]
    Name(#[from] NameParseError),
}

/// Why an item could not be declared.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum DeclareError {
    /// The name or pattern is malformed.
    #[error(transparent)]
    Name(#[from] NameParseError),
    /// The node is shutting down.
    #[error("node is shutting down")]
    Closed,
    /// The file sink directory cannot be used.
    #[error("file sink directory {dir}: {reason}")]
    SinkDir {
        /// The directory.
        dir: String,
        /// What went wrong.
        reason: String,
    },
}

/// Why a subscription yielded no value.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum RecvError {
    /// A publisher matching the subscription sends another type; it will not be delivered.
    #[error("subscription refused: {0}")]
    TypeMismatch(TypeMismatch),
    /// A value could not be decoded as the expected type.
    #[error("cannot decode '{name}' from node '{publisher}': {reason}")]
    Decode {
        /// Item name.
        name: String,
        /// Publishing node.
        publisher: String,
        /// postcard's message.
        reason: String,
    },
    /// The subscription was closed (node shut down).
    #[error("subscription closed")]
    Closed,
    /// Nothing arrived in time.
    #[error("nothing received within {0:?}")]
    Timeout(Duration),
}
