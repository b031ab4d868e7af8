//! Per-node identity keys (Ed25519), on top of the domain key of [`crate::link::auth`]: a node
//! proves which key it holds, and the domain's roster (`identities.xml`) says what that key
//! may be: which namespaces it may own, under which node names, and whether it may act as a
//! gateway (speak for other nodes). Pure: key files, the roster, and signing and checking a
//! proof.
//!
//! ```xml
//! <identities>
//!   <identity key="64 hex digits of the public key" namespaces="rover1" nodes="vas"/>
//!   <identity key="..." namespaces="rover1 rover1/fpma"/>   <!-- any node name -->
//!   <identity key="..." namespaces="*"/>            <!-- a station allowed any namespace -->
//!   <identity key="..." namespaces="*" gateway="yes"/>     <!-- the domain's gateways -->
//! </identities>
//! ```
//! `nodes` absent (or `*`) lets the key run under any node name in its namespaces; a gateway
//! role is never taken from a node's own announcement where a roster is kept: only a key
//! listed with `gateway="yes"` forwards other nodes' items and relays their calls.
//! The proof is challenge-response: a node checking identities sends each peer it registers a
//! [`crate::protocol::Message::Challenge`] with a fresh random nonce (after its Hello, before
//! asking for the peer's declarations); the peer answers with a
//! [`crate::protocol::Message::Identity`], a signature over the domain, its node id (random at
//! every start), its name and namespace, **and the challenger's node id and nonce**. The nonce
//! is used once: a proof recorded on the LAN and replayed, to this node or another, under the
//! prover's id or any other, does not verify.
//!
//! **Pair keys.** Each node also makes an X25519 key pair at every start ([`KeyAgreement`]).
//! A challenge carries the challenger's public half and a proof the prover's, both inside the
//! signature, so once a proof verifies the challenger shares a secret with exactly the node
//! that holds the listed identity key; [`KeyAgreement::pair_keys`] derives from it one key per
//! direction, bound to the domain and both node ids. A frame sealed with the key of one
//! direction opens with no other: not reflected back to its sender, not between another
//! pair.

use std::path::{Path, PathBuf};

use ed25519_dalek::{Signature, Signer, SigningKey, Verifier, VerifyingKey};

pub use crate::link::auth::PairKeys;
use crate::link::auth::{hex, parse_hex, read_private, write_private_new, KeyFileError};
use crate::xml::{LineIndex, Reader, XmlEvent};
use zeroize::Zeroizing;

/// What the signature covers, before the fields.
const CONTEXT: &[u8] = b"usal-rs marea node identity v2\0";

/// The context of [`KeyAgreement::pair_keys`]' derivation (BLAKE3's key derivation mode).
const PAIR_CONTEXT: &str = "usal-rs marea pair key v1";

/// A node's identity key pair. Its `Debug` shows only the public half; the secret half is
/// wiped from memory when dropped (ed25519-dalek's key does that itself).
pub struct IdentityKey(SigningKey);

impl std::fmt::Debug for IdentityKey {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "IdentityKey({})", hex(&self.public()))
    }
}

/// What a proof answers: who asked, the nonce it sent, and its key agreement half.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Challenge {
    /// The challenger's node id.
    pub verifier: u64,
    /// The nonce it sent.
    pub nonce: [u8; 16],
    /// The challenger's [`KeyAgreement::public`].
    pub agreement: [u8; 32],
}

/// The bytes a node signs to answer `challenge`, its own key agreement half `agreement`
/// included.
fn statement(
    (domain, node_id, node, namespace): (&str, u64, &str, &str),
    agreement: &[u8; 32],
    challenge: &Challenge,
) -> Vec<u8> {
    let mut m =
        Vec::with_capacity(CONTEXT.len() + domain.len() + node.len() + namespace.len() + 99);
    m.extend_from_slice(CONTEXT);
    m.extend_from_slice(domain.as_bytes());
    m.push(0);
    m.extend_from_slice(&node_id.to_le_bytes());
    m.extend_from_slice(node.as_bytes());
    m.push(0);
    m.extend_from_slice(namespace.as_bytes());
    m.push(0);
    m.extend_from_slice(&challenge.verifier.to_le_bytes());
    m.extend_from_slice(&challenge.nonce);
    m.extend_from_slice(&challenge.agreement);
    m.extend_from_slice(agreement);
    m
}

/// A node's X25519 key agreement half, made fresh at every start: with a peer's public half,
/// once the peer's proof binds it ([`check_proof`]), it gives the pair's keys. The secret is
/// wiped from memory when dropped.
pub struct KeyAgreement(x25519_dalek::StaticSecret);

impl std::fmt::Debug for KeyAgreement {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "KeyAgreement({})", hex(&self.public()))
    }
}

impl KeyAgreement {
    /// A fresh key pair from the operating system's generator.
    pub fn new() -> Self {
        Self::from_bytes(rand::random())
    }

    /// A key pair from its 32 secret bytes (tests).
    pub fn from_bytes(secret: [u8; 32]) -> Self {
        KeyAgreement(x25519_dalek::StaticSecret::from(secret))
    }

    /// The public half, which challenges and proofs carry.
    pub fn public(&self) -> [u8; 32] {
        x25519_dalek::PublicKey::from(&self.0).to_bytes()
    }

    /// The keys node `me` shares with node `peer` whose public half is `peer_public`, in
    /// `domain`, for the handshake of challenges `(ours, theirs)` (the nonce of our challenge
    /// to the peer, of its to us: new at every registration, so keys are never reused across
    /// two, and nor are frames recorded under the earlier ones). `None` when that half is no
    /// key at all (a low-order point: the secret would be known to anyone), or names us.
    pub fn pair_keys(
        &self,
        peer_public: &[u8; 32],
        domain: &str,
        (me, peer): (u64, u64),
        (ours, theirs): ([u8; 16], [u8; 16]),
    ) -> Option<PairKeys> {
        if me == peer {
            return None;
        }
        let shared = self
            .0
            .diffie_hellman(&x25519_dalek::PublicKey::from(*peer_public));
        if !shared.was_contributory() {
            return None;
        }
        // The key of the direction `from` -> `to`: with the nonce `to` challenged `from`
        // with, then the one `from` challenged `to` with (both ends order them alike).
        let key = |from: u64, to: u64, to_asked: &[u8; 16], from_asked: &[u8; 16]| {
            let mut m = Zeroizing::new(Vec::with_capacity(32 + domain.len() + 49));
            m.extend_from_slice(shared.as_bytes());
            m.extend_from_slice(domain.as_bytes());
            m.push(0);
            m.extend_from_slice(&from.to_le_bytes());
            m.extend_from_slice(&to.to_le_bytes());
            m.extend_from_slice(to_asked);
            m.extend_from_slice(from_asked);
            blake3::derive_key(PAIR_CONTEXT, &m)
        };
        Some(PairKeys {
            send: key(me, peer, &theirs, &ours),
            recv: key(peer, me, &ours, &theirs),
        })
    }
}

impl Default for KeyAgreement {
    fn default() -> Self {
        Self::new()
    }
}

impl IdentityKey {
    /// A key from its 32 secret bytes (tests).
    pub fn from_bytes(secret: [u8; 32]) -> Self {
        IdentityKey(SigningKey::from_bytes(&secret))
    }

    /// Writes a fresh key pair: the secret to `path` (mode 0600, must not exist) and the public
    /// key to `path.pub` (what goes in the domain's `identities.xml`).
    ///
    /// # Errors
    /// As [`crate::link::auth::DomainKey::create_file`].
    pub fn create_files(path: &Path) -> Result<Self, KeyFileError> {
        use rand::TryRngCore;
        let mut secret = Zeroizing::new([0u8; 32]);
        rand::rngs::OsRng
            .try_fill_bytes(secret.as_mut())
            .map_err(|e| KeyFileError::Random {
                path: path.to_path_buf(),
                reason: e.to_string(),
            })?;
        let key = IdentityKey::from_bytes(*secret);
        let public = Self::public_path(path);
        if public.exists() {
            return Err(KeyFileError::Exists { path: public });
        }
        write_private_new(
            path,
            Zeroizing::new(format!("{}\n", hex(&*secret))).as_bytes(),
        )?;
        std::fs::write(&public, format!("{}\n", hex(&key.public()))).map_err(|source| {
            KeyFileError::Write {
                path: public.clone(),
                source,
            }
        })?;
        Ok(key)
    }

    /// Where [`IdentityKey::create_files`] puts the public key of `path`.
    pub fn public_path(path: &Path) -> PathBuf {
        let mut p = path.as_os_str().to_owned();
        p.push(".pub");
        PathBuf::from(p)
    }

    /// Reads a secret key file, refusing one group or others may access.
    ///
    /// # Errors
    /// [`KeyFileError`] naming the file and what is wrong.
    pub fn load(path: &Path) -> Result<Self, KeyFileError> {
        let text = read_private(path)?;
        let secret = Zeroizing::new(parse_hex::<32>(text.trim()).map_err(|reason| {
            KeyFileError::Malformed {
                path: path.to_path_buf(),
                reason,
            }
        })?);
        Ok(IdentityKey::from_bytes(*secret))
    }

    /// The public key.
    pub fn public(&self) -> [u8; 32] {
        self.0.verifying_key().to_bytes()
    }

    /// The answer to `challenge`: a signature over domain, node id, name and namespace, our
    /// key agreement half `agreement`, and the challenger's id, nonce and key agreement half.
    pub fn prove(
        &self,
        who: (&str, u64, &str, &str),
        agreement: &[u8; 32],
        challenge: &Challenge,
    ) -> [u8; 64] {
        self.0
            .sign(&statement(who, agreement, challenge))
            .to_bytes()
    }
}

/// Whether `signature` by `public` proves `node_id`'s run as `node` in `namespace`, with key
/// agreement half `agreement`, in answer to `challenge`.
pub fn check_proof(
    public: &[u8; 32],
    signature: &[u8],
    who: (&str, u64, &str, &str),
    agreement: &[u8; 32],
    challenge: &Challenge,
) -> bool {
    let Ok(key) = VerifyingKey::from_bytes(public) else {
        return false;
    };
    let Ok(sig) = Signature::from_slice(signature) else {
        return false;
    };
    key.verify(&statement(who, agreement, challenge), &sig)
        .is_ok()
}

/// The domain's roster: what each public key may be.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct Roster {
    entries: Vec<Listing>,
}

/// What one `<identity>` of a roster lets its key be.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct Listing {
    /// The public key.
    pub key: [u8; 32],
    /// The namespaces it may own (`*`: any, and none).
    pub namespaces: Vec<String>,
    /// The node names it may run under (empty: any).
    pub nodes: Vec<String>,
    /// Whether it may act as a gateway.
    pub gateway: bool,
}

impl Listing {
    /// Whether it lets a node named `node` own `namespace`.
    pub fn covers(&self, namespace: &str, node: &str) -> bool {
        allows(&self.namespaces, namespace)
            && (self.nodes.is_empty() || self.nodes.iter().any(|n| n == "*" || n == node))
    }
}

/// What a proven key may be: every listing of it ([`Roster::grant`]), each judged on its
/// own (a key listed as node `vas` of `rover1` and as any node of `gcs` is not any node of
/// `rover1`).
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct Grant {
    listings: Vec<Listing>,
}

impl Grant {
    /// Whether one listing lets a node named `node` own `namespace`.
    pub fn covers(&self, namespace: &str, node: &str) -> bool {
        self.listings.iter().any(|l| l.covers(namespace, node))
    }

    /// Whether one listing lets a node named `node` of `namespace` act as a gateway.
    pub fn gateway_for(&self, namespace: &str, node: &str) -> bool {
        self.listings
            .iter()
            .any(|l| l.gateway && l.covers(namespace, node))
    }

    /// Every namespace a listing names (`*`: any); empty when the key is not listed.
    pub fn namespaces(&self) -> Vec<String> {
        self.listings
            .iter()
            .flat_map(|l| l.namespaces.iter().cloned())
            .collect()
    }

    /// Every node name a listing binds (empty for a listing of any node name).
    pub fn nodes(&self) -> Vec<String> {
        self.listings
            .iter()
            .flat_map(|l| l.nodes.iter().cloned())
            .collect()
    }
}

/// Why a roster could not be read.
#[derive(Debug, thiserror::Error)]
pub enum RosterLoadError {
    /// The file could not be read.
    #[error("identities file {path}: cannot read: {source}")]
    Unreadable {
        /// The file.
        path: PathBuf,
        /// The OS error.
        source: std::io::Error,
    },
    /// Group or others may write the file: whoever can decides which keys own which names.
    #[error("identities file {path} has mode {mode:03o}: group or others may write it, so they could list their own key for any namespace (chmod go-w it)")]
    Writable {
        /// The file.
        path: PathBuf,
        /// Its permission bits.
        mode: u32,
    },
    /// The content is wrong, at `line`:`column`.
    #[error("{path}:{line}:{column}: {reason}")]
    Invalid {
        /// The file.
        path: PathBuf,
        /// Line, from 1.
        line: u32,
        /// Column, from 1.
        column: u32,
        /// What is wrong.
        reason: String,
    },
}

impl Roster {
    /// Reads an `identities.xml`, refusing one that group or others may write (the mode
    /// checked is the opened file's).
    ///
    /// # Errors
    /// [`RosterLoadError`] naming the file, and the line and column of what is wrong in it.
    pub fn load(path: &Path) -> Result<Self, RosterLoadError> {
        use std::io::Read;
        use std::os::unix::fs::MetadataExt;
        let unreadable = |source| RosterLoadError::Unreadable {
            path: path.to_path_buf(),
            source,
        };
        let mut f = std::fs::File::open(path).map_err(unreadable)?;
        let mode = f.metadata().map_err(unreadable)?.mode() & 0o777;
        if mode & 0o022 != 0 {
            return Err(RosterLoadError::Writable {
                path: path.to_path_buf(),
                mode,
            });
        }
        let mut text = String::new();
        f.read_to_string(&mut text).map_err(unreadable)?;
        Self::parse(&text, path)
    }

    /// Parses the text of an `identities.xml`; `path` names it in errors.
    ///
    /// # Errors
    /// [`RosterLoadError::Invalid`].
    pub fn parse(text: &str, path: &Path) -> Result<Self, RosterLoadError> {
        let index = LineIndex::new(text);
        let mut reader = Reader::new(text, &index);
        let invalid = |pos: crate::xml::Pos, reason: String| RosterLoadError::Invalid {
            path: path.to_path_buf(),
            line: pos.line,
            column: pos.col,
            reason,
        };
        let mut roster = Roster::default();
        let mut depth = 0;
        loop {
            let event = reader
                .read_event()
                .map_err(|e| invalid(e.pos, e.kind.to_string()))?;
            match event {
                XmlEvent::Eof => break,
                XmlEvent::End => depth -= 1,
                XmlEvent::Text(t) => {
                    return Err(invalid(t.pos, "unexpected text".into()));
                }
                XmlEvent::Start(tag) => {
                    match (depth, tag.name()) {
                        (0, "identities") => {}
                        (1, "identity") => {
                            let (mut key, mut namespaces) = (None, None);
                            let (mut nodes, mut gateway) = (Vec::new(), false);
                            for a in tag.attributes() {
                                let a = a.map_err(|e| invalid(e.pos, e.kind.to_string()))?;
                                let v = a.value().map_err(|e| invalid(e.pos, e.kind.to_string()))?;
                                match a.name.as_str() {
                                    "key" => {
                                        key = Some(parse_hex::<32>(v.trim()).map_err(|r| {
                                            invalid(a.pos, format!("attribute key: {r}"))
                                        })?)
                                    }
                                    "namespaces" => {
                                        namespaces = Some(
                                            v.split_whitespace()
                                                .map(str::to_owned)
                                                .collect::<Vec<_>>(),
                                        )
                                    }
                                    "nodes" => {
                                        nodes = v.split_whitespace().map(str::to_owned).collect()
                                    }
                                    "gateway" => {
                                        gateway = match v.trim() {
                                            "yes" | "true" => true,
                                            "no" | "false" => false,
                                            other => {
                                                return Err(invalid(
                                                    a.pos,
                                                    format!("attribute gateway: {other:?}; expected yes or no"),
                                                ))
                                            }
                                        }
                                    }
                                    other => {
                                        return Err(invalid(
                                            a.pos,
                                            format!("unknown attribute {other}; expected key, namespaces, nodes, gateway"),
                                        ))
                                    }
                                }
                            }
                            let key = key.ok_or_else(|| {
                                invalid(tag.pos(), "<identity> needs key=\"64 hex digits\"".into())
                            })?;
                            let namespaces = namespaces.filter(|n| !n.is_empty()).ok_or_else(|| {
                                invalid(tag.pos(), "<identity> needs namespaces=\"ns1 ns2\"".into())
                            })?;
                            roster.entries.push(Listing {
                                key,
                                namespaces,
                                nodes,
                                gateway,
                            });
                        }
                        (_, other) => {
                            return Err(invalid(
                                tag.pos(),
                                format!("unexpected element <{other}>; expected <identities> holding <identity key=.. namespaces=../>"),
                            ))
                        }
                    }
                    if !tag.is_empty() {
                        depth += 1;
                    }
                }
            }
        }
        Ok(roster)
    }

    /// Lists `public` as a key that may own `namespaces` (`*`: any, and no namespace), under
    /// any node name, and act as no gateway.
    pub fn allow(&mut self, public: [u8; 32], namespaces: Vec<String>) {
        self.list(Listing {
            key: public,
            namespaces,
            ..Listing::default()
        });
    }

    /// Adds `listing`.
    pub fn list(&mut self, listing: Listing) {
        self.entries.push(listing);
    }

    /// The roster as an `identities.xml`, which [`Roster::parse`] reads back as it is.
    pub fn to_xml(&self) -> String {
        let mut out = String::from("<identities>\n");
        for l in &self.entries {
            out.push_str(&format!(
                "  <identity key=\"{}\" namespaces=\"{}\"",
                hex(&l.key),
                l.namespaces.join(" ")
            ));
            if !l.nodes.is_empty() {
                out.push_str(&format!(" nodes=\"{}\"", l.nodes.join(" ")));
            }
            if l.gateway {
                out.push_str(" gateway=\"yes\"");
            }
            out.push_str("/>\n");
        }
        out.push_str("</identities>\n");
        out
    }

    /// The namespaces `public` may own (empty when it is not listed).
    pub fn namespaces(&self, public: &[u8; 32]) -> Vec<String> {
        self.grant(public).namespaces()
    }

    /// What `public` may be: its listings (none when it is not listed).
    pub fn grant(&self, public: &[u8; 32]) -> Grant {
        Grant {
            listings: self
                .entries
                .iter()
                .filter(|l| l.key == *public)
                .cloned()
                .collect(),
        }
    }
}

/// Whether a list of authenticated namespaces covers `namespace` (`*` covers any).
pub fn allows(authenticated: &[String], namespace: &str) -> bool {
    authenticated.iter().any(|n| n == "*" || n == namespace)
}

#[cfg(test)]
mod tests {
    use super::*;

    const C: Challenge = Challenge {
        verifier: 99,
        nonce: [5; 16],
        agreement: [6; 32],
    };
    /// The prover's key agreement half in the proofs of these tests.
    const A: [u8; 32] = [7; 32];

    #[test]
    fn both_ends_of_a_pair_derive_the_same_keys_one_per_direction() {
        let (a, b) = (
            KeyAgreement::from_bytes([1; 32]),
            KeyAgreement::from_bytes([2; 32]),
        );
        // a challenged b with nonce [1; 16], b challenged a with [2; 16].
        let (na, nb) = ([1; 16], [2; 16]);
        let ab = a.pair_keys(&b.public(), "d", (10, 20), (na, nb)).unwrap();
        let ba = b.pair_keys(&a.public(), "d", (20, 10), (nb, na)).unwrap();
        assert_eq!((ab.send, ab.recv), (ba.recv, ba.send));
        assert_ne!(
            ab.send, ab.recv,
            "a frame sent back to its sender opens with no key"
        );
        // Another domain, other ids, another peer, another handshake: other keys.
        let other = |k: &KeyAgreement, d, ids, n| a.pair_keys(&k.public(), d, ids, n).unwrap();
        assert_ne!(other(&b, "e", (10, 20), (na, nb)), ab);
        assert_ne!(other(&b, "d", (10, 21), (na, nb)), ab);
        assert_ne!(other(&b, "d", (10, 20), (na, [3; 16])), ab);
        assert_ne!(
            other(&KeyAgreement::from_bytes([3; 32]), "d", (10, 20), (na, nb)),
            ab
        );
        // A low-order point is no key: the secret would be all zeros; nor is a pair with us.
        assert!(a.pair_keys(&[0; 32], "d", (10, 20), (na, nb)).is_none());
        assert!(a.pair_keys(&b.public(), "d", (10, 10), (na, nb)).is_none());
        assert_eq!(format!("{ab:?}"), "PairKeys(..)");
    }

    #[test]
    fn a_roster_reads_back_what_to_xml_wrote() {
        let mut r = Roster::default();
        r.allow([1; 32], vec!["rover1".into()]);
        r.allow([2; 32], vec!["gcs".into(), "base".into()]);
        r.allow([3; 32], vec!["*".into()]);
        let back = Roster::parse(&r.to_xml(), Path::new("identities.xml")).unwrap();
        assert_eq!(back, r);
        assert_eq!(back.namespaces(&[2; 32]), ["gcs", "base"]);
    }

    #[test]
    fn a_roster_binds_node_names_and_the_gateway_role() {
        let text = format!(
            "<identities>\n  <identity key=\"{}\" namespaces=\"rover1\" nodes=\"vas fpma\"/>\n  <identity key=\"{}\" namespaces=\"*\" gateway=\"yes\"/>\n  <identity key=\"{}\" namespaces=\"gcs\"/>\n</identities>",
            hex(&[1; 32]),
            hex(&[2; 32]),
            hex(&[3; 32])
        );
        let r = Roster::parse(&text, Path::new("identities.xml")).unwrap();
        assert_eq!(Roster::parse(&r.to_xml(), Path::new("x")).unwrap(), r);
        let vas = r.grant(&[1; 32]);
        assert!(vas.covers("rover1", "vas") && vas.covers("rover1", "fpma"));
        assert!(
            !vas.covers("rover1", "fmo"),
            "a node name it is not listed for"
        );
        assert!(!vas.covers("rover2", "vas"));
        assert!(!vas.gateway_for("rover1", "vas"));
        let gw = r.grant(&[2; 32]);
        assert!(gw.gateway_for("rover1", "anything") && gw.covers("rover1", "anything"));
        let gcs = r.grant(&[3; 32]);
        assert!(gcs.covers("gcs", "fmo") && !gcs.gateway_for("gcs", "fmo"));
        let unknown = r.grant(&[4; 32]);
        assert!(!unknown.covers("", "x") && unknown.namespaces().is_empty());

        // Each listing on its own: bound in one namespace, free in another, a gateway in a
        // third, is none of these in the others.
        let mut r = Roster::default();
        let listing = |ns: &str, nodes: &[&str], gateway| Listing {
            key: [5; 32],
            namespaces: vec![ns.into()],
            nodes: nodes.iter().map(|n| n.to_string()).collect(),
            gateway,
        };
        r.list(listing("rover1", &["vas"], false));
        r.list(listing("gcs", &[], false));
        r.list(listing("relay", &["gw"], true));
        let g = r.grant(&[5; 32]);
        assert!(g.covers("rover1", "vas") && g.covers("gcs", "anything"));
        assert!(
            !g.covers("rover1", "fpma"),
            "gcs's free node names are not rover1's"
        );
        assert!(g.gateway_for("relay", "gw"));
        assert!(!g.gateway_for("rover1", "vas") && !g.gateway_for("gcs", "x"));
        let e = Roster::parse(
            &format!(
                "<identities><identity key=\"{}\" namespaces=\"a\" gateway=\"maybe\"/></identities>",
                hex(&[1; 32])
            ),
            Path::new("ids.xml"),
        )
        .unwrap_err()
        .to_string();
        assert!(e.contains("gateway") && e.contains("maybe"), "{e}");
    }

    #[test]
    fn proofs_bind_domain_node_id_name_and_namespace() {
        let k = IdentityKey::from_bytes([1; 32]);
        let p = k.public();
        let sig = k.prove(("d", 7, "vas", "rover1"), &A, &C);
        assert!(check_proof(&p, &sig, ("d", 7, "vas", "rover1"), &A, &C));
        for other in [
            ("e", 7, "vas", "rover1"),
            ("d", 8, "vas", "rover1"),
            ("d", 7, "vax", "rover1"),
            ("d", 7, "vas", "rover2"),
        ] {
            assert!(!check_proof(&p, &sig, other, &A, &C), "{other:?}");
        }
        let q = IdentityKey::from_bytes([2; 32]).public();
        assert!(!check_proof(&q, &sig, ("d", 7, "vas", "rover1"), &A, &C));
        assert!(!check_proof(
            &p,
            &sig[..63],
            ("d", 7, "vas", "rover1"),
            &A,
            &C
        ));
        assert!(!check_proof(
            &[0xFF; 32],
            &sig,
            ("d", 7, "vas", "rover1"),
            &A,
            &C
        ));
    }

    #[test]
    fn a_proof_answers_one_challenge_only() {
        let k = IdentityKey::from_bytes([1; 32]);
        let who = ("d", 7, "vas", "rover1");
        let sig = k.prove(who, &A, &C);
        // Replayed to another challenger, or to the same one after it sent a new nonce.
        let elsewhere = Challenge { verifier: 100, ..C };
        let later = Challenge {
            nonce: [6; 16],
            ..C
        };
        assert!(!check_proof(&k.public(), &sig, who, &A, &elsewhere));
        assert!(!check_proof(&k.public(), &sig, who, &A, &later));
        // The key agreement halves are bound: a proof passed off with another half of the
        // prover's, or answering a challenge that carried another, proves nothing.
        let swapped = Challenge {
            agreement: [8; 32],
            ..C
        };
        assert!(!check_proof(&k.public(), &sig, who, &A, &swapped));
        assert!(!check_proof(&k.public(), &sig, who, &[8; 32], &C));
        assert!(check_proof(&k.public(), &sig, who, &A, &C));
    }

    #[test]
    fn key_files_and_roster() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("vas.id");
        let k = IdentityKey::create_files(&path).unwrap();
        assert_eq!(IdentityKey::load(&path).unwrap().public(), k.public());
        let public = std::fs::read_to_string(IdentityKey::public_path(&path)).unwrap();
        assert_eq!(public.trim(), hex(&k.public()));
        assert!(matches!(
            IdentityKey::create_files(&path),
            Err(KeyFileError::Exists { .. })
        ));
        let text = format!(
            "<identities>\n  <identity key=\"{}\" namespaces=\"rover1 rover1/x\"/>\n  <identity key=\"{}\" namespaces=\"*\"/>\n</identities>",
            public.trim(),
            hex(&[9; 32])
        );
        let r = Roster::parse(&text, Path::new("identities.xml")).unwrap();
        assert_eq!(r.namespaces(&k.public()), vec!["rover1", "rover1/x"]);
        assert!(allows(&r.namespaces(&[9; 32]), "anything"));
        assert!(r.namespaces(&[8; 32]).is_empty());
        assert!(!allows(&r.namespaces(&k.public()), "rover2"));

        let e = Roster::parse(
            "<identities>\n  <identity key=\"12\" namespaces=\"a\"/>\n</identities>",
            Path::new("ids.xml"),
        )
        .unwrap_err()
        .to_string();
        assert!(e.starts_with("ids.xml:2:13:") && e.contains("64"), "{e}");
        let e = Roster::parse("<identities><who/></identities>", Path::new("ids.xml"))
            .unwrap_err()
            .to_string();
        assert!(e.starts_with("ids.xml:1:13:"), "{e}");
        let e = Roster::parse(
            &format!(
                "<identities><identity key=\"{}\"/></identities>",
                hex(&[1; 32])
            ),
            Path::new("ids.xml"),
        )
        .unwrap_err()
        .to_string();
        assert!(e.contains("namespaces"), "{e}");
    }

    #[test]
    fn a_roster_others_may_write_is_refused_naming_its_mode() {
        use std::os::unix::fs::PermissionsExt;
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("identities.xml");
        let text = format!(
            "<identities><identity key=\"{}\" namespaces=\"a\"/></identities>",
            hex(&[1; 32])
        );
        std::fs::write(&path, text).unwrap();
        let chmod = |mode| std::fs::set_permissions(&path, std::fs::Permissions::from_mode(mode));
        chmod(0o644).unwrap();
        assert_eq!(Roster::load(&path).unwrap().namespaces(&[1; 32]), vec!["a"]);
        for mode in [0o664, 0o646, 0o666] {
            chmod(mode).unwrap();
            let e = Roster::load(&path).unwrap_err();
            assert!(
                matches!(e, RosterLoadError::Writable { mode: m, .. } if m == mode),
                "{mode:o}: {e}"
            );
            let text = e.to_string();
            assert!(
                text.contains("identities.xml") && text.contains(&format!("{mode:03o}")),
                "{text}"
            );
        }
    }
}
