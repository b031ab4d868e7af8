//! Wire message types of the node protocol (what a message is; `codec` says how it looks).
//!
//! Every message is a postcard-encoded [`Message`]: one varint for the variant, then its fields
//! in order (integers as varints, strings and byte strings as a varint length then the bytes).
//! A link carries these messages inside its own framing (see `link::datagram` for UDP, the
//! Serial Transport Protocol for serial links).
//!
//! ```text
//! Var (fast, 35 bytes for a 32-byte position):
//! +---------+----------------+-------------+----------------------+
//! | tag = 5 | pub id (varint)| len (varint)| payload (postcard T) |
//! +---------+----------------+-------------+----------------------+
//! ```
//!
//! The tag is the message's variant ([`tag::VAR`] here); fast paths that write or read a
//! message's bytes without postcard name it by the constants of [`tag`].

use serde::{Deserialize, Serialize};

use crate::typeinfo::TypeInfo;

#[cfg(feature = "fuzzing")]
pub mod gen;

/// A node's random identity, fresh at every start.
pub type NodeId = u64;

/// What kind of item a declaration describes.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
pub enum ItemKind {
    /// A best-effort, latest-value variable.
    Variable,
    /// A reliable, ordered event.
    Event,
    /// A remote invocation.
    Function,
    /// A file sink (receives file transfers).
    File,
}

impl ItemKind {
    /// Lower-case name for listings.
    pub fn as_str(self) -> &'static str {
        match self {
            ItemKind::Variable => "variable",
            ItemKind::Event => "event",
            ItemKind::Function => "function",
            ItemKind::File => "file",
        }
    }
}

/// One declaration of a node, identified by a node-local id.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub enum Declaration {
    /// A service hosted by the node.
    Service {
        /// Node-local id.
        id: u32,
        /// Service name.
        name: String,
    },
    /// An item the node offers: a variable or event it publishes, a function it provides or a
    /// file sink it accepts files on. `id` is the small per-link id data messages carry.
    Offer {
        /// Node-local id, used in data messages instead of the name.
        id: u32,
        /// The service that declared it.
        service: u32,
        /// Kind of item.
        kind: ItemKind,
        /// Full name.
        name: String,
        /// Payload type.
        ty: TypeInfo,
        /// Set when a gateway declares, on its other links, an item it forwards: the node that
        /// really offers it. Receivers that reach that node by a shorter path ignore this copy.
        origin: Option<Origin>,
    },
    /// Interest in items: subscribing to variables/events, or calling functions.
    Interest {
        /// Node-local id.
        id: u32,
        /// The service that declared it.
        service: u32,
        /// Kind of item.
        kind: ItemKind,
        /// Name or pattern.
        pattern: String,
        /// Expected payload type.
        ty: TypeInfo,
    },
    /// Withdraws an earlier declaration (service, offer or interest) by id.
    Withdraw {
        /// The id withdrawn.
        id: u32,
    },
}

impl Declaration {
    /// The id this declaration adds or withdraws.
    pub fn id(&self) -> u32 {
        match self {
            Declaration::Service { id, .. }
            | Declaration::Offer { id, .. }
            | Declaration::Interest { id, .. }
            | Declaration::Withdraw { id } => *id,
        }
    }
}

/// Where a forwarded offer really comes from.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct Origin {
    /// The offering node.
    pub node: NodeId,
    /// Its name (for listings and reports).
    pub name: String,
    /// Gateways crossed so far (1 for an offer forwarded once).
    pub hops: u8,
    /// The offering node's namespace (what its names must start with, and what access rules
    /// match it by).
    pub namespace: String,
}

/// A file offered to a sink ([`Message::FileOffer`]).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct FileOffer {
    /// Transfer id: derived from the content hash and the name, stable across restarts.
    pub transfer: u64,
    /// Offer id of the sink on the receiver.
    pub sink: u32,
    /// File name (no directories).
    pub name: String,
    /// Size in bytes.
    pub size: u64,
    /// blake3 hash of the content.
    pub hash: [u8; 32],
    /// Set by a gateway relaying another node's file: that node, which the receiver checks
    /// its `<access>` rules against. Taken only from a gateway.
    pub sender: Option<Origin>,
}

/// A declaration with its position in the node's declaration log.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct LoggedDeclaration {
    /// Counter value after this declaration (1 for the first).
    pub counter: u32,
    /// The declaration.
    pub decl: Declaration,
}

/// Why a remote call failed on the provider's side.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub enum RemoteFailure {
    /// The provider's handler returned an error (its text).
    Handler(String),
    /// The provider could not decode the arguments (type mismatch or corrupt).
    BadArguments(String),
    /// The function id is not (or no longer) provided on that node.
    NotProvided,
    /// The deadline passed before the provider ran the handler.
    DeadlineExpired,
    /// The provider's access rules (`<access>` in its network.xml) do not let the caller call
    /// this function.
    Denied,
    /// The provider runs as many calls as it accepts (from this caller, or in all); retry later.
    Busy,
    /// A newer call of the same function from the same caller arrived before this one started:
    /// the newest command wins, this one was dropped unexecuted.
    Superseded,
}

/// Outcome of a file offer, sent by the receiver.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub enum FileVerdict {
    /// Stored, hash verified, renamed into place.
    Stored,
    /// Refused or failed, with the reason.
    Failed(String),
    /// Refused: the announced size (at the offer), or the bytes actually sent (during the
    /// transfer), exceed what the sink accepts. `size` is what was announced or reached.
    TooLarge {
        /// Bytes announced, or reached when the sender went past its announcement.
        size: u64,
        /// The most this transfer may hold.
        max: u64,
    },
    /// Refused: storing the file would take the sink's directory past its quota of bytes.
    QuotaExceeded {
        /// Bytes the sink would hold with this file (stored files, partial files, transfers in
        /// progress).
        needed: u64,
        /// The sink's quota.
        quota: u64,
    },
    /// Refused for now: the sink already receives its maximum number of files at once.
    Busy {
        /// Concurrent incoming transfers the sink allows.
        max: u32,
    },
    /// The receiver's access rules (`<access>` in its network.xml) do not let the sender send
    /// to this sink; the reason names the sink and the sender.
    Denied(String),
}

impl std::fmt::Display for FileVerdict {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            FileVerdict::Stored => write!(f, "stored"),
            FileVerdict::Failed(reason) => write!(f, "{reason}"),
            FileVerdict::TooLarge { size, max } => {
                write!(f, "too large: {size} bytes, the sink accepts at most {max}")
            }
            FileVerdict::QuotaExceeded { needed, quota } => write!(
                f,
                "quota exceeded: the sink would hold {needed} bytes, its quota is {quota}"
            ),
            FileVerdict::Denied(reason) => write!(f, "denied: {reason}"),
            FileVerdict::Busy { max } => write!(
                f,
                "busy: the sink already receives {max} files at once; try again later"
            ),
        }
    }
}

/// Every message exchanged between nodes.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub enum Message {
    /// Announces a node (multicast at start and to a new peer as the first safe message).
    Hello {
        /// Sender's identity.
        node_id: NodeId,
        /// Isolation key: nodes of different domains ignore each other.
        domain: String,
        /// Node name from network.xml.
        node: String,
        /// Namespace prefixing the node's items.
        namespace: String,
        /// Current declaration counter.
        counter: u32,
        /// How long the sender may stay silent before being declared gone, in ms.
        lease_ms: u32,
        /// Whether the sender forwards between links (a gateway): only a gateway's offers may
        /// name another node as their `origin`.
        gateway: bool,
        /// Sent because the sender heard a heartbeat of the recipient without knowing it: a
        /// recipient that knows the sender (its introduction was lost on the way) introduces
        /// itself again. (Every other Hello, a first contact's or an introduction's, says
        /// `false`, so two nodes never answer each other's introductions for ever.)
        asks_introduction: bool,
    },
    /// The small periodic liveness message (multicast / point to point).
    Heartbeat {
        /// Sender's identity.
        node_id: NodeId,
        /// Hash of the domain, to filter foreign domains cheaply.
        domain_hash: u32,
        /// Current declaration counter.
        counter: u32,
    },
    /// Asks a peer for its declarations after `since` (0 = all).
    DeclRequest {
        /// Highest counter already known.
        since: u32,
    },
    /// Declarations, in counter order: a delta as it happens, or the answer to a request.
    ///
    /// The sender's log is compacted (a withdrawn declaration is not replayed), so counters in
    /// `entries` may skip: the batch covers every counter in `after + 1 ..= upto`, and those
    /// missing were compacted away.
    DeclBatch {
        /// The batch continues from this counter (the receiver must know up to it).
        after: u32,
        /// The batch covers counters up to this one.
        upto: u32,
        /// The receiver first forgets every declaration of the sender: the batch (with those
        /// following it) is the sender's whole current state, from `after` = 0.
        reset: bool,
        /// The entries.
        entries: Vec<LoggedDeclaration>,
    },
    /// The peer's subscription `interest` cannot be served by offer `offer`: types differ.
    Refused {
        /// The interest id on the receiver's side.
        interest: u32,
        /// Full name of the offer.
        name: String,
        /// The offer's type.
        offered: TypeInfo,
    },
    /// A variable value (fast class).
    Var {
        /// Offer id on the sender.
        id: u32,
        /// postcard-encoded value.
        #[serde(with = "serde_bytes_compat")]
        payload: Vec<u8>,
    },
    /// An event (safe class).
    Event {
        /// Offer id on the sender.
        id: u32,
        /// postcard-encoded value.
        #[serde(with = "serde_bytes_compat")]
        payload: Vec<u8>,
    },
    /// A remote invocation (safe class).
    Call {
        /// Caller-chosen id.
        call_id: u64,
        /// Offer id of the function on the provider.
        id: u32,
        /// Milliseconds the caller still waits, counted when the message is made; the provider
        /// clamps it and drops the call unexecuted once it has run out.
        remaining_ms: u32,
        /// postcard-encoded arguments.
        #[serde(with = "serde_bytes_compat")]
        args: Vec<u8>,
        /// Set by a gateway relaying another node's call: that node, which the provider checks
        /// its `<access>` rules against and gives its own lanes (a call relayed for one caller
        /// never supersedes another's). Taken only from a gateway.
        caller: Option<Origin>,
    },
    /// The answer to a call (safe class).
    Reply {
        /// The call answered.
        call_id: u64,
        /// postcard-encoded result or the failure.
        result: Result<Vec<u8>, RemoteFailure>,
    },
    /// Offers a file to a sink (safe class).
    FileOffer(FileOffer),
    /// The receiver accepts and says where to resume.
    FileAccept {
        /// Transfer id.
        transfer: u64,
        /// Bytes the receiver already has.
        offset: u64,
    },
    /// A chunk of file content (safe class, windowed by the link).
    FileChunk {
        /// Transfer id.
        transfer: u64,
        /// Offset of `data` in the file.
        offset: u64,
        /// Content.
        #[serde(with = "serde_bytes_compat")]
        data: Vec<u8>,
    },
    /// The receiver's final word on a transfer.
    FileDone {
        /// Transfer id.
        transfer: u64,
        /// Result.
        verdict: FileVerdict,
    },
    /// The sender cancels a transfer.
    FileCancel {
        /// Transfer id.
        transfer: u64,
    },
    /// A node leaves cleanly; peers drop it at once instead of waiting for the lease.
    Bye {
        /// Sender's identity.
        node_id: NodeId,
    },
    /// Proof of the sender's identity key, the answer to a peer's [`Message::Challenge`]
    /// (only by nodes with an identity key; see [`crate::identity`]).
    Identity {
        /// Ed25519 public key.
        public_key: [u8; 32],
        /// Signature over domain, node id, node name and namespace, `agreement`, and the
        /// challenger's node id, nonce and key agreement half (64 bytes).
        #[serde(with = "serde_bytes_compat")]
        signature: Vec<u8>,
        /// The sender's X25519 key agreement half (new at every start): with the
        /// challenger's, the pair's keys ([`crate::identity::KeyAgreement::pair_keys`]).
        agreement: [u8; 32],
    },
    /// Asks a peer to prove its identity key over a fresh nonce (sent after our Hello by a
    /// node checking identities, once per peer it registers): a proof made for another nonce
    /// or another challenger, a recorded one, does not verify.
    Challenge {
        /// Random, new for each peer registered.
        nonce: [u8; 16],
        /// The challenger's X25519 key agreement half, which the proof signs.
        agreement: [u8; 32],
    },
    /// The sender's event subscribers are behind while still reading (`behind`), or caught up
    /// again: lossless streams to the sender wait while it is behind. Sent to every peer at
    /// each change.
    Flow {
        /// Behind (`true`) or caught up.
        behind: bool,
        /// Behind because of subscribers' mailboxes: its own (`Some(0)`), or ones this many
        /// gateways beyond it (a gateway forwarding to them passes their state on, never back
        /// to the node it came from); `None` when only events it forwards wait for a slower
        /// link, or when not behind.
        readers: Option<u8>,
        /// While behind, the streams that should wait: those of these offers of the node told
        /// (ids on it), the ones its own subscribers that are behind read; `None`: all of them.
        offers: Option<Vec<u32>>,
    },
}

/// The largest payload marea carries, encoded: an event, a variable's value, a call's
/// arguments or its result (32 MiB). `raise`, `set` and `call` refuse a larger one at once
/// ([`crate::PublishError::TooLarge`], [`crate::CallError::TooLarge`]); a file of any size
/// goes as a file transfer instead. Links carry messages up to [`MAX_MESSAGE`] whole, in
/// parts where one does not fit their frames.
pub const MAX_PAYLOAD: usize = 32 << 20;

/// The largest message a link takes: [`MAX_PAYLOAD`] and room for its header (item names,
/// call ids); a message joined from parts past it is dropped.
pub const MAX_MESSAGE: usize = MAX_PAYLOAD + (64 << 10);

/// The first byte of each encoded [`Message`]: its variant's index, which postcard writes as
/// a one-byte varint. Links mark the parts of a message too large for one frame with bytes
/// no tag takes (`0xFD`, `0xFE`). A unit test checks every constant against postcard's encoding, so a
/// variant added anywhere but at the end fails it instead of silently changing the wire.
pub mod tag {
    /// [`Message::Hello`](super::Message::Hello).
    pub const HELLO: u8 = 0;
    /// [`Message::Heartbeat`](super::Message::Heartbeat).
    pub const HEARTBEAT: u8 = 1;
    /// [`Message::DeclRequest`](super::Message::DeclRequest).
    pub const DECL_REQUEST: u8 = 2;
    /// [`Message::DeclBatch`](super::Message::DeclBatch).
    pub const DECL_BATCH: u8 = 3;
    /// [`Message::Refused`](super::Message::Refused).
    pub const REFUSED: u8 = 4;
    /// [`Message::Var`](super::Message::Var).
    pub const VAR: u8 = 5;
    /// [`Message::Event`](super::Message::Event).
    pub const EVENT: u8 = 6;
    /// [`Message::Call`](super::Message::Call).
    pub const CALL: u8 = 7;
    /// [`Message::Reply`](super::Message::Reply).
    pub const REPLY: u8 = 8;
    /// [`Message::FileOffer`](super::Message::FileOffer).
    pub const FILE_OFFER: u8 = 9;
    /// [`Message::FileAccept`](super::Message::FileAccept).
    pub const FILE_ACCEPT: u8 = 10;
    /// [`Message::FileChunk`](super::Message::FileChunk).
    pub const FILE_CHUNK: u8 = 11;
    /// [`Message::FileDone`](super::Message::FileDone).
    pub const FILE_DONE: u8 = 12;
    /// [`Message::FileCancel`](super::Message::FileCancel).
    pub const FILE_CANCEL: u8 = 13;
    /// [`Message::Bye`](super::Message::Bye).
    pub const BYE: u8 = 14;
    /// [`Message::Identity`](super::Message::Identity).
    pub const IDENTITY: u8 = 15;
    /// [`Message::Challenge`](super::Message::Challenge).
    pub const CHALLENGE: u8 = 16;
    /// [`Message::Flow`](super::Message::Flow).
    pub const FLOW: u8 = 17;
}

/// postcard already encodes `Vec<u8>` as length + bytes; this module only makes that explicit
/// and decodes through a borrowed slice so a claimed length is checked against the input before
/// anything is allocated.
mod serde_bytes_compat {
    use serde::{Deserialize, Deserializer, Serializer};

    pub fn serialize<S: Serializer>(v: &[u8], s: S) -> Result<S::Ok, S::Error> {
        s.serialize_bytes(v)
    }

    pub fn deserialize<'de, D: Deserializer<'de>>(d: D) -> Result<Vec<u8>, D::Error> {
        let b: &[u8] = <&[u8]>::deserialize(d)?;
        Ok(b.to_vec())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::codec::encode_message;

    /// The tag constant of `m`'s variant (a match that a new variant makes incomplete).
    fn tag_of(m: &Message) -> u8 {
        match m {
            Message::Hello { .. } => tag::HELLO,
            Message::Heartbeat { .. } => tag::HEARTBEAT,
            Message::DeclRequest { .. } => tag::DECL_REQUEST,
            Message::DeclBatch { .. } => tag::DECL_BATCH,
            Message::Refused { .. } => tag::REFUSED,
            Message::Var { .. } => tag::VAR,
            Message::Event { .. } => tag::EVENT,
            Message::Call { .. } => tag::CALL,
            Message::Reply { .. } => tag::REPLY,
            Message::FileOffer(_) => tag::FILE_OFFER,
            Message::FileAccept { .. } => tag::FILE_ACCEPT,
            Message::FileChunk { .. } => tag::FILE_CHUNK,
            Message::FileDone { .. } => tag::FILE_DONE,
            Message::FileCancel { .. } => tag::FILE_CANCEL,
            Message::Bye { .. } => tag::BYE,
            Message::Identity { .. } => tag::IDENTITY,
            Message::Challenge { .. } => tag::CHALLENGE,
            Message::Flow { .. } => tag::FLOW,
        }
    }

    #[test]
    fn every_tag_constant_is_the_first_byte_postcard_writes_for_its_variant() {
        let ty = TypeInfo::of::<u32>();
        let samples = [
            Message::Hello {
                node_id: 1,
                domain: "d".into(),
                node: "n".into(),
                namespace: String::new(),
                counter: 2,
                lease_ms: 3,
                gateway: false,
                asks_introduction: false,
            },
            Message::Heartbeat {
                node_id: 1,
                domain_hash: 2,
                counter: 3,
            },
            Message::DeclRequest { since: 0 },
            Message::DeclBatch {
                after: 0,
                upto: 0,
                reset: true,
                entries: Vec::new(),
            },
            Message::Refused {
                interest: 1,
                name: "x".into(),
                offered: ty.clone(),
            },
            Message::Var {
                id: 1,
                payload: vec![1],
            },
            Message::Event {
                id: 1,
                payload: vec![1],
            },
            Message::Call {
                call_id: 1,
                id: 2,
                remaining_ms: 3,
                args: Vec::new(),
                caller: None,
            },
            Message::Reply {
                call_id: 1,
                result: Ok(Vec::new()),
            },
            Message::FileOffer(FileOffer {
                transfer: 1,
                sink: 2,
                name: "f".into(),
                size: 3,
                hash: [0; 32],
                sender: None,
            }),
            Message::FileAccept {
                transfer: 1,
                offset: 0,
            },
            Message::FileChunk {
                transfer: 1,
                offset: 0,
                data: vec![1],
            },
            Message::FileDone {
                transfer: 1,
                verdict: FileVerdict::Stored,
            },
            Message::FileCancel { transfer: 1 },
            Message::Bye { node_id: 1 },
            Message::Identity {
                public_key: [0; 32],
                signature: vec![0; 64],
                agreement: [0; 32],
            },
            Message::Challenge {
                nonce: [0; 16],
                agreement: [0; 32],
            },
            Message::Flow {
                behind: false,
                readers: None,
                offers: None,
            },
        ];
        let mut seen = std::collections::BTreeSet::new();
        for m in &samples {
            assert_eq!(
                encode_message(m).first().copied(),
                Some(tag_of(m)),
                "tag of {m:?}"
            );
            seen.insert(tag_of(m));
        }
        // One sample per variant, the tags 0..n without a gap.
        assert!(seen.iter().copied().eq(0..samples.len() as u8), "{seen:?}");
    }
}
