//! Errors of the public API, one enum per operation family.

use std::time::Duration;

use crate::name::NameParseError;
use crate::node::mailbox::TypeMismatch;
use crate::protocol::RemoteFailure;

/// Why a node could not be opened.
#[derive(Debug, thiserror::Error)]
pub enum NodeOpenError {
    /// A link failed to open.
    #[error(transparent)]
    Link(#[from] crate::link::udp::LinkOpenError),
    /// A serial link could not be opened.
    #[error(transparent)]
    Serial(#[from] crate::link::serial::SerialLinkOpenError),
    /// A shared-memory link could not be opened.
    #[error(transparent)]
    Shm(#[from] crate::link::shm::ShmLinkOpenError),
    /// The configuration asks for a link kind this build does not support yet.
    #[error("link '{link}': {kind} links are not supported by this build")]
    Unsupported {
        /// Link name.
        link: String,
        /// Kind of link.
        kind: &'static str,
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

/// Why a value could not be published.
#[derive(Debug, thiserror::Error)]
pub enum PublishError {
    /// The value could not be encoded.
    #[error("cannot encode value for '{name}': {source}")]
    Encode {
        /// Item name.
        name: String,
        /// postcard's error.
        source: postcard::Error,
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

/// Why a remote invocation failed. Each cause is distinct, as callers react differently.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum CallError {
    /// No node provides the function (right now).
    #[error("no provider for function '{name}'")]
    NoProvider {
        /// Function name.
        name: String,
    },
    /// The provider did not answer within the deadline.
    #[error("call to '{name}' on node '{node}' timed out after {after:?}")]
    Timeout {
        /// Function name.
        name: String,
        /// Provider node.
        node: String,
        /// The deadline.
        after: Duration,
    },
    /// The provider's handler returned an error.
    #[error("node '{node}' answered with an error: {message}")]
    Remote {
        /// Provider node.
        node: String,
        /// The handler's message.
        message: String,
    },
    /// The provider went away before answering (lease expired, node left, session reset).
    #[error("link to node '{node}' lost before it answered: {reason}")]
    LinkLost {
        /// Provider node.
        node: String,
        /// What happened.
        reason: String,
    },
    /// The provider declares other argument or result types.
    #[error("function '{name}' is provided as {offered} but called as {expected}")]
    TypeMismatch {
        /// Function name.
        name: String,
        /// Provider's signature.
        offered: String,
        /// Caller's signature.
        expected: String,
    },
    /// Arguments could not be encoded, or the result decoded.
    #[error("codec error calling '{name}': {reason}")]
    Codec {
        /// Function name.
        name: String,
        /// What failed.
        reason: String,
    },
}

impl CallError {
    pub(crate) fn from_remote(node: &str, name: &str, after: Duration, f: RemoteFailure) -> Self {
        let node = node.to_owned();
        match f {
            RemoteFailure::Handler(message) => CallError::Remote { node, message },
            RemoteFailure::BadArguments(m) => CallError::Remote {
                node,
                message: format!("bad arguments: {m}"),
            },
            RemoteFailure::NotProvided => CallError::Remote {
                node,
                message: "function no longer provided".into(),
            },
            RemoteFailure::DeadlineExpired => CallError::Timeout {
                name: name.to_owned(),
                node,
                after,
            },
        }
    }
}

/// Why a file could not be sent.
#[derive(Debug, thiserror::Error)]
pub enum FileSendError {
    /// No node offers a sink of that name within the retry time.
    #[error("no file sink '{to}' found within {waited:?}")]
    NoSink {
        /// Sink name.
        to: String,
        /// How long we looked.
        waited: Duration,
    },
    /// The local file could not be read.
    #[error("cannot read {path}: {source}")]
    Io {
        /// The file.
        path: String,
        /// The OS error.
        source: std::io::Error,
    },
    /// The receiver refused or failed.
    #[error("node '{node}' refused the file: {reason}")]
    Rejected {
        /// Receiving node.
        node: String,
        /// Its reason.
        reason: String,
    },
    /// The receiver kept disappearing until the retry time ran out.
    #[error("gave up sending to '{to}': {last}")]
    GaveUp {
        /// Sink name.
        to: String,
        /// The last failure.
        last: String,
    },
    /// The node shut down.
    #[error("node is shutting down")]
    Closed,
}
