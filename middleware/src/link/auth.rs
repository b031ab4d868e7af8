//! Link authentication: the domain key, the seal every frame carries when a node has a key,
//! and the per-sender replay window. Pure (no I/O but reading and writing the key file); each
//! link calls [`Sealer::seal`] where it writes a frame and [`Opener::open`] where it reads one,
//! before anything is decoded (shared memory, which writes into and reads from samples in place,
//! uses [`Sealer::seal_slice`] and [`Opener::verify`]).
//!
//! ```text
//! sealed frame := frame | epoch (E bytes LE) | counter (C bytes LE) | tag (T bytes)
//!
//! profile            E  C  T   tag                                   overhead
//! UDP datagram       4  4  8   BLAKE3 keyed hash, truncated           16 B
//! shm frame          4  4  8   BLAKE3 keyed hash, truncated           16 B
//! serial (STP) frame 3  3  5   BLAKE3 keyed hash, truncated           11 B (before DLE stuffing)
//! serial, encrypted  8  4  16  ChaCha20-Poly1305 (nonce = epoch|counter, the data encrypted)
//! ```
//! The MAC covers a medium byte (so a frame of one link kind is never accepted on another) and
//! the whole frame, epoch and counter included. With encryption, the frame's first `aad_len`
//! bytes (the STP header, which the receiver needs to NACK a corrupt frame) stay in clear and are
//! authenticated as associated data with the epoch and counter; the rest is encrypted.
//!
//! **Replay.** A sender picks a random *epoch* when it starts (and again when its counter space
//! runs out) and numbers its frames 0, 1, 2... within it. A receiver keeps, per `(stream, epoch)`,
//! a sliding window of the last [`WINDOW`] counters (RFC 6479 style): a counter seen before is a
//! replay, one older than the window is too old, one ahead moves the window. A restarted sender
//! has a new epoch, so it is accepted at once. Windows are only created for frames whose tag
//! verified, so nobody without the key can fill the table; at most `max_windows` are kept, the
//! least recently used evicted.
//!
//! **Forgery bound.** A forger without the key succeeds with probability 2^-(8·T) per frame it
//! sends: 2^-64 on UDP and shared memory, 2^-40 on serial (at 1,000 frames a second, one forged
//! frame expected in ~35 years of continuous trying, every failure counted in link health), 2^-128
//! with encryption. Epochs are random: two senders (or a restarted one) drawing the same epoch
//! have probability 2^-32 (UDP, shm) or 2^-24 (serial) per pair; the cost is the later one's first
//! frames being taken as replays until its counter passes the other's, never a forgery. With
//! encryption the epoch is 64 bits because a shared epoch would also reuse nonces (2^-64). A
//! receiver that restarts (or evicts an epoch) forgets what it saw of it: traffic recorded
//! before can then be replayed once. That is the limit of a group key without a handshake.

use std::collections::HashMap;
use std::fmt;
use std::io::Write;
use std::path::{Path, PathBuf};
use std::sync::Mutex;

use chacha20poly1305::aead::AeadInPlace;
use chacha20poly1305::{ChaCha20Poly1305, KeyInit};

use crate::sync::lock;
use zeroize::{Zeroize, Zeroizing};

/// Bytes of a domain key.
pub const KEY_LEN: usize = 32;

/// Counters a replay window remembers behind the newest (RFC 6479 blocks of 64; the newest
/// block is partly ahead, so at least `WINDOW - 64` are always remembered).
pub const WINDOW: u64 = 1024;
const BLOCKS: usize = (WINDOW / 64) as usize;

/// The secret every node of a domain shares. Its `Debug` shows nothing of it; it is wiped
/// from memory when dropped.
#[derive(Clone, PartialEq, Eq)]
pub struct DomainKey([u8; KEY_LEN]);

impl Drop for DomainKey {
    fn drop(&mut self) {
        self.0.zeroize();
    }
}

impl fmt::Debug for DomainKey {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str("DomainKey(..)")
    }
}

/// The keys of one pair of nodes, as one of them holds them: one per direction. Wiped from
/// memory when dropped; its `Debug` shows nothing of them.
#[derive(Clone, PartialEq, Eq)]
pub struct PairKeys {
    /// Seals what this node sends to the peer.
    pub send: [u8; 32],
    /// Opens what the peer sends to this node.
    pub recv: [u8; 32],
}

impl Drop for PairKeys {
    fn drop(&mut self) {
        self.send.zeroize();
        self.recv.zeroize();
    }
}

impl std::fmt::Debug for PairKeys {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str("PairKeys(..)")
    }
}

/// Why a key file could not be written or read.
#[derive(Debug, thiserror::Error)]
pub enum KeyFileError {
    /// The file exists already: a key is never overwritten.
    #[error("key file {path}: already exists; refusing to overwrite a key")]
    Exists {
        /// The file.
        path: PathBuf,
    },
    /// Creating or writing the file failed.
    #[error("key file {path}: cannot write: {source}")]
    Write {
        /// The file.
        path: PathBuf,
        /// The OS error.
        source: std::io::Error,
    },
    /// Reading the file failed.
    #[error("key file {path}: cannot read: {source}")]
    Read {
        /// The file.
        path: PathBuf,
        /// The OS error.
        source: std::io::Error,
    },
    /// Group or others may access the file: the key may have leaked.
    #[error("key file {path}: mode {mode:03o} lets group or others access it; `chmod 600` it (and consider the key leaked if others could read it)")]
    Permissions {
        /// The file.
        path: PathBuf,
        /// Its permission bits.
        mode: u32,
    },
    /// The content is not a key.
    #[error("key file {path}: malformed: {reason}")]
    Malformed {
        /// The file.
        path: PathBuf,
        /// What is wrong.
        reason: String,
    },
    /// The operating system's random source failed.
    #[error("key file {path}: no randomness from the operating system: {reason}")]
    Random {
        /// The file.
        path: PathBuf,
        /// The error.
        reason: String,
    },
}

impl DomainKey {
    /// A key from its bytes (tests, benchmarks).
    pub fn from_bytes(bytes: [u8; KEY_LEN]) -> Self {
        DomainKey(bytes)
    }

    /// Writes a fresh random key to `path` (which must not exist) with mode 0600: 64 hex
    /// digits and a newline.
    ///
    /// # Errors
    /// [`KeyFileError::Exists`] when `path` exists; [`KeyFileError::Write`] when it cannot be
    /// created; [`KeyFileError::Random`] when the OS gives no randomness.
    pub fn create_file(path: &Path) -> Result<Self, KeyFileError> {
        use rand::TryRngCore;
        let mut bytes = Zeroizing::new([0u8; KEY_LEN]);
        rand::rngs::OsRng
            .try_fill_bytes(bytes.as_mut())
            .map_err(|e| KeyFileError::Random {
                path: path.to_path_buf(),
                reason: e.to_string(),
            })?;
        write_private_new(
            path,
            Zeroizing::new(format!("{}\n", hex(&*bytes))).as_bytes(),
        )?;
        Ok(DomainKey(*bytes))
    }

    /// Reads the key at `path`, refusing a file group or others may access.
    ///
    /// # Errors
    /// [`KeyFileError::Read`], [`KeyFileError::Permissions`] or [`KeyFileError::Malformed`].
    pub fn load(path: &Path) -> Result<Self, KeyFileError> {
        let text = read_private(path)?;
        let bytes = Zeroizing::new(parse_hex::<KEY_LEN>(text.trim()).map_err(|reason| {
            KeyFileError::Malformed {
                path: path.to_path_buf(),
                reason,
            }
        })?);
        Ok(DomainKey(*bytes))
    }

    /// A subkey for one purpose, so no two uses share key material (wiped when dropped).
    fn derive(&self, context: &str) -> Zeroizing<[u8; 32]> {
        Zeroizing::new(blake3::derive_key(context, &self.0))
    }
}

/// Creates `path` (not already there) readable and writable by its owner only, with `content`.
pub(crate) fn write_private_new(path: &Path, content: &[u8]) -> Result<(), KeyFileError> {
    use std::os::unix::fs::OpenOptionsExt;
    let mut f = std::fs::OpenOptions::new()
        .write(true)
        .create_new(true)
        .mode(0o600)
        .open(path)
        .map_err(|source| match source.kind() {
            std::io::ErrorKind::AlreadyExists => KeyFileError::Exists {
                path: path.to_path_buf(),
            },
            _ => KeyFileError::Write {
                path: path.to_path_buf(),
                source,
            },
        })?;
    f.write_all(content)
        .and_then(|()| f.sync_all())
        .map_err(|source| KeyFileError::Write {
            path: path.to_path_buf(),
            source,
        })
}

/// Reads a secret file (at most 4 KiB), refusing one that group or others may access. The
/// permissions checked are those of the file opened (no race with a swap of the path); the
/// text is wiped from memory when dropped.
pub(crate) fn read_private(path: &Path) -> Result<Zeroizing<String>, KeyFileError> {
    use std::io::Read;
    use std::os::unix::fs::MetadataExt;
    let read_err = |source| KeyFileError::Read {
        path: path.to_path_buf(),
        source,
    };
    let f = std::fs::File::open(path).map_err(read_err)?;
    let mode = f.metadata().map_err(read_err)?.mode() & 0o777;
    if mode & 0o077 != 0 {
        return Err(KeyFileError::Permissions {
            path: path.to_path_buf(),
            mode,
        });
    }
    let mut bytes = Zeroizing::new(Vec::with_capacity(4096));
    f.take(4096).read_to_end(&mut bytes).map_err(read_err)?;
    match std::str::from_utf8(&bytes) {
        Ok(text) => Ok(Zeroizing::new(text.to_owned())),
        Err(_) => Err(KeyFileError::Malformed {
            path: path.to_path_buf(),
            reason: "not text (expected hexadecimal digits)".into(),
        }),
    }
}

/// Lowercase hex of `bytes`.
pub(crate) fn hex(bytes: &[u8]) -> String {
    bytes.iter().map(|b| format!("{b:02x}")).collect()
}

/// Parses exactly `N` bytes of hex.
pub(crate) fn parse_hex<const N: usize>(s: &str) -> Result<[u8; N], String> {
    if s.len() != 2 * N {
        return Err(format!(
            "expected {} hexadecimal digits, found {} characters",
            2 * N,
            s.chars().count()
        ));
    }
    let mut out = [0u8; N];
    for (i, pair) in s.as_bytes().chunks(2).enumerate() {
        let digit = |c: u8, at: usize| {
            (c as char)
                .to_digit(16)
                .ok_or_else(|| format!("character {} is not a hexadecimal digit", at + 1))
        };
        out[i] = (digit(pair[0], 2 * i)? * 16 + digit(pair[1], 2 * i + 1)?) as u8;
    }
    Ok(out)
}

/// What a node's links are given when it has a key.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct LinkSecurity {
    /// The domain key.
    pub key: DomainKey,
    /// Whether serial (radio) links encrypt their frames' data.
    pub encrypt_radio: bool,
}

/// The shape of the seal on one kind of link.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Profile {
    medium: u8,
    epoch_len: usize,
    counter_len: usize,
    tag_len: usize,
    encrypt: bool,
}

impl Profile {
    /// UDP datagrams.
    pub const UDP: Profile = Profile {
        medium: b'U',
        epoch_len: 4,
        counter_len: 4,
        tag_len: 8,
        encrypt: false,
    };
    /// UDP datagrams between two nodes sealed with their pair's keys
    /// ([`PairKeys`]): a medium byte of their own, so a frame of one kind of
    /// seal is never taken for the other.
    pub const UDP_PAIR: Profile = Profile {
        medium: b'u',
        epoch_len: 4,
        counter_len: 4,
        tag_len: 8,
        encrypt: false,
    };
    /// Shared-memory frames.
    pub const SHM: Profile = Profile {
        medium: b'M',
        epoch_len: 4,
        counter_len: 4,
        tag_len: 8,
        encrypt: false,
    };
    /// Serial (STP) frames, authenticated.
    pub const SERIAL: Profile = Profile {
        medium: b'S',
        epoch_len: 3,
        counter_len: 3,
        tag_len: 5,
        encrypt: false,
    };
    /// Serial (STP) frames, data encrypted and authenticated (ChaCha20-Poly1305).
    pub const SERIAL_ENCRYPTED: Profile = Profile {
        medium: b'R',
        epoch_len: 8,
        counter_len: 4,
        tag_len: 16,
        encrypt: true,
    };

    /// Bytes the seal adds to a frame.
    pub const fn overhead(&self) -> usize {
        self.epoch_len + self.counter_len + self.tag_len
    }

    fn max_counter(&self) -> u64 {
        (1u64 << (8 * self.counter_len)) - 1
    }

    fn fresh_epoch(&self) -> u64 {
        let e: u64 = rand::random();
        if self.epoch_len >= 8 {
            e
        } else {
            e & ((1u64 << (8 * self.epoch_len)) - 1)
        }
    }
}

/// The keys of one profile (the MAC key is wiped when dropped, as the cipher wipes its own).
struct Keys {
    profile: Profile,
    mac: [u8; 32],
    cipher: Option<ChaCha20Poly1305>,
}

impl Drop for Keys {
    fn drop(&mut self) {
        self.mac.zeroize();
    }
}

impl Keys {
    fn new(key: &DomainKey, profile: Profile) -> Self {
        let cipher = profile.encrypt.then(|| {
            let aead = key.derive("usal-rs marea serial aead v1");
            ChaCha20Poly1305::new(chacha20poly1305::Key::from_slice(&aead[..]))
        });
        Keys {
            profile,
            mac: *key.derive("usal-rs marea link mac v1"),
            cipher,
        }
    }

    fn mac(&self, covered: &[u8]) -> blake3::Hash {
        let mut h = blake3::Hasher::new_keyed(&self.mac);
        h.update(&[self.profile.medium]);
        h.update(covered);
        h.finalize()
    }

    fn nonce(&self, header: &[u8]) -> chacha20poly1305::Nonce {
        let mut n = [0u8; 12];
        let len = header.len().min(12);
        n[..len].copy_from_slice(&header[..len]);
        n.into()
    }

    fn aad(&self, clear: &[u8], header: &[u8]) -> Vec<u8> {
        let mut aad = Vec::with_capacity(1 + clear.len() + header.len());
        aad.push(self.profile.medium);
        aad.extend_from_slice(clear);
        aad.extend_from_slice(header);
        aad
    }
}

fn put_le(out: &mut Vec<u8>, v: u64, len: usize) {
    out.extend_from_slice(&v.to_le_bytes()[..len]);
}

fn get_le(b: &[u8]) -> u64 {
    let mut x = [0u8; 8];
    x[..b.len()].copy_from_slice(b);
    u64::from_le_bytes(x)
}

/// Seals outgoing frames of one link. Shared by the link's sending tasks.
pub struct Sealer {
    keys: Keys,
    /// Current epoch and the next counter in it.
    state: Mutex<(u64, u64)>,
}

impl fmt::Debug for Sealer {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.debug_struct("Sealer")
            .field("profile", &self.keys.profile)
            .finish_non_exhaustive()
    }
}

impl Sealer {
    /// A sealer with a fresh random epoch.
    pub fn new(key: &DomainKey, profile: Profile) -> Self {
        Self::with_epoch(key, profile, profile.fresh_epoch())
    }

    /// A sealer starting at `epoch` (tests: a deterministic frame).
    pub fn with_epoch(key: &DomainKey, profile: Profile, epoch: u64) -> Self {
        Sealer {
            keys: Keys::new(key, profile),
            state: Mutex::new((epoch, 0)),
        }
    }

    /// Bytes [`Sealer::seal`] adds.
    pub fn overhead(&self) -> usize {
        self.keys.profile.overhead()
    }

    /// Seals in place: `buf` holds a frame of `body_len` bytes followed by room for exactly
    /// [`Sealer::overhead`] bytes, which are filled with epoch, counter and tag. Only for
    /// profiles that do not encrypt (shared memory writes into a loaned sample).
    pub fn seal_slice(&self, buf: &mut [u8], body_len: usize) {
        let p = self.keys.profile;
        debug_assert!(!p.encrypt && buf.len() == body_len + p.overhead());
        let (epoch, counter) = self.next();
        let header_end = body_len + p.epoch_len + p.counter_len;
        buf[body_len..body_len + p.epoch_len].copy_from_slice(&epoch.to_le_bytes()[..p.epoch_len]);
        buf[body_len + p.epoch_len..header_end]
            .copy_from_slice(&counter.to_le_bytes()[..p.counter_len]);
        let tag = self.keys.mac(&buf[..header_end]);
        buf[header_end..].copy_from_slice(&tag.as_bytes()[..p.tag_len]);
    }

    /// The epoch and counter of the next frame.
    fn next(&self) -> (u64, u64) {
        let p = self.keys.profile;
        let mut st = lock(&self.state);
        if st.1 > p.max_counter() {
            *st = (p.fresh_epoch(), 0);
        }
        let taken = *st;
        st.1 += 1;
        taken
    }

    /// Appends epoch, counter and tag to `frame`. With encryption, `frame[aad_len..]` is
    /// encrypted in place (the first `aad_len` bytes stay in clear, authenticated).
    pub fn seal(&self, frame: &mut Vec<u8>, aad_len: usize) {
        let p = self.keys.profile;
        let (epoch, counter) = self.next();
        let body_len = frame.len();
        put_le(frame, epoch, p.epoch_len);
        put_le(frame, counter, p.counter_len);
        match &self.keys.cipher {
            None => {
                let tag = self.keys.mac(frame);
                frame.extend_from_slice(&tag.as_bytes()[..p.tag_len]);
            }
            Some(cipher) => {
                let clear = aad_len.min(body_len);
                let (head, rest) = frame.split_at_mut(clear);
                let (data, header) = rest.split_at_mut(body_len - clear);
                let aad = self.keys.aad(head, header);
                let nonce = self.keys.nonce(header);
                // Encryption fails only past 2^38 bytes in one frame.
                let tag = cipher
                    .encrypt_in_place_detached(&nonce, &aad, data)
                    .unwrap_or_default();
                frame.extend_from_slice(&tag);
            }
        }
    }
}

/// Why a received frame was dropped.
#[derive(Debug, Clone, Copy, PartialEq, Eq, thiserror::Error)]
pub enum AuthReject {
    /// Not sealed: sent by a node without a key, or too short to carry a seal.
    #[error("not sealed (sent without a key, or truncated)")]
    Unsealed,
    /// The tag does not verify: another key, no key, or tampering.
    #[error("bad authentication tag")]
    BadTag,
    /// The counter was seen before in this epoch.
    #[error("replayed (counter seen before)")]
    Replayed,
    /// The counter is older than the replay window.
    #[error("too old for the replay window")]
    TooOld,
    /// Sealed with the domain key by (or as) a peer whose data comes sealed with the keys it
    /// shares with this node: a key holder forging its address, or a frame of its that left
    /// before it switched.
    #[error("sealed with the domain key, not the pair's")]
    NotPairSealed,
    /// Sealed with a pair's keys this node does not hold (not yet, or not any more).
    #[error("sealed with a pair key this node does not hold")]
    NoPair,
}

impl AuthReject {
    /// Whether it is counted as a replay (else as an authentication failure).
    pub fn is_replay(self) -> bool {
        matches!(self, AuthReject::Replayed | AuthReject::TooOld)
    }
}

/// The counters of one sender epoch seen lately.
#[derive(Debug, Clone)]
pub struct ReplayWindow {
    /// Highest counter accepted.
    top: u64,
    blocks: [u64; BLOCKS],
    last_used: u64,
}

impl ReplayWindow {
    /// A window whose first accepted counter is `first`.
    pub fn new(first: u64) -> Self {
        let mut w = ReplayWindow {
            top: first,
            blocks: [0; BLOCKS],
            last_used: 0,
        };
        w.set(first);
        w
    }

    fn slot(c: u64) -> (usize, u64) {
        (((c / 64) % BLOCKS as u64) as usize, 1u64 << (c % 64))
    }

    fn set(&mut self, c: u64) {
        let (b, bit) = Self::slot(c);
        self.blocks[b] |= bit;
    }

    /// Whether `c` would be accepted.
    ///
    /// # Errors
    /// [`AuthReject::Replayed`] or [`AuthReject::TooOld`].
    pub fn check(&self, c: u64) -> Result<(), AuthReject> {
        if c > self.top {
            return Ok(());
        }
        if self.top / 64 - c / 64 >= BLOCKS as u64 {
            return Err(AuthReject::TooOld);
        }
        let (b, bit) = Self::slot(c);
        if self.blocks[b] & bit != 0 {
            Err(AuthReject::Replayed)
        } else {
            Ok(())
        }
    }

    /// Records `c`, moving the window when it is ahead.
    ///
    /// # Errors
    /// As [`ReplayWindow::check`]; nothing is recorded then.
    pub fn accept(&mut self, c: u64) -> Result<(), AuthReject> {
        self.check(c)?;
        if c > self.top {
            let (from, to) = (self.top / 64, c / 64);
            if to - from >= BLOCKS as u64 {
                self.blocks = [0; BLOCKS];
            } else {
                for block in from + 1..=to {
                    self.blocks[(block % BLOCKS as u64) as usize] = 0;
                }
            }
            self.top = c;
        }
        self.set(c);
        Ok(())
    }
}

/// Checks incoming frames of one link: tag, then replay window per `(stream, epoch)`.
pub struct Opener {
    keys: Keys,
    windows: HashMap<(u64, u64), ReplayWindow>,
    max_windows: usize,
    tick: u64,
}

impl fmt::Debug for Opener {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.debug_struct("Opener")
            .field("profile", &self.keys.profile)
            .field("windows", &self.windows.len())
            .finish_non_exhaustive()
    }
}

impl Opener {
    /// An opener remembering at most `max_windows` sender epochs.
    pub fn new(key: &DomainKey, profile: Profile, max_windows: usize) -> Self {
        Opener {
            keys: Keys::new(key, profile),
            windows: HashMap::new(),
            max_windows: max_windows.max(1),
            tick: 0,
        }
    }

    /// Bytes a seal takes.
    pub fn overhead(&self) -> usize {
        self.keys.profile.overhead()
    }

    /// Sender epochs remembered now.
    pub fn windows(&self) -> usize {
        self.windows.len()
    }

    /// Verifies the seal of `frame` from `stream` (what tells senders apart beyond the epoch: 0
    /// where the epoch alone does) and records its counter. Returns the length of the frame
    /// without its seal; with encryption, that part is decrypted in place.
    ///
    /// # Errors
    /// [`AuthReject`]: the frame must be dropped.
    pub fn open(
        &mut self,
        stream: u64,
        frame: &mut [u8],
        aad_len: usize,
    ) -> Result<usize, AuthReject> {
        let (body_len, header_end, epoch, counter) = self.parse(frame)?;
        let (covered, tag) = frame.split_at_mut(header_end);
        match &self.keys.cipher {
            None => self.check_mac(covered, tag)?,
            Some(cipher) => {
                let clear = aad_len.min(body_len);
                let (head, rest) = covered.split_at_mut(clear);
                let (data, header) = rest.split_at_mut(body_len - clear);
                let aad = self.keys.aad(head, header);
                let nonce = self.keys.nonce(header);
                let tag = chacha20poly1305::Tag::from_slice(tag);
                cipher
                    .decrypt_in_place_detached(&nonce, &aad, data, tag)
                    .map_err(|_| AuthReject::BadTag)?;
            }
        }
        self.record((stream, epoch), counter)?;
        Ok(body_len)
    }

    /// [`Opener::open`] for a frame that cannot be changed (read in place from shared
    /// memory). Profiles that encrypt refuse everything here.
    ///
    /// # Errors
    /// [`AuthReject`]: the frame must be dropped.
    pub fn verify(&mut self, stream: u64, frame: &[u8]) -> Result<usize, AuthReject> {
        if self.keys.cipher.is_some() {
            return Err(AuthReject::BadTag);
        }
        let (body_len, header_end, epoch, counter) = self.parse(frame)?;
        let (covered, tag) = frame.split_at(header_end);
        self.check_mac(covered, tag)?;
        self.record((stream, epoch), counter)?;
        Ok(body_len)
    }

    /// Body length, end of epoch and counter, epoch, counter.
    fn parse(&self, frame: &[u8]) -> Result<(usize, usize, u64, u64), AuthReject> {
        let p = self.keys.profile;
        let Some(body_len) = frame.len().checked_sub(p.overhead()) else {
            return Err(AuthReject::Unsealed);
        };
        let header_end = body_len + p.epoch_len + p.counter_len;
        let epoch = get_le(&frame[body_len..body_len + p.epoch_len]);
        let counter = get_le(&frame[body_len + p.epoch_len..header_end]);
        Ok((body_len, header_end, epoch, counter))
    }

    fn check_mac(&self, covered: &[u8], tag: &[u8]) -> Result<(), AuthReject> {
        let want = self.keys.mac(covered);
        // Constant time: the comparison does not stop at the first differing byte.
        let diff = want.as_bytes()[..self.keys.profile.tag_len]
            .iter()
            .zip(tag.iter())
            .fold(0u8, |acc, (a, b)| acc | (a ^ b));
        if diff == 0 {
            Ok(())
        } else {
            Err(AuthReject::BadTag)
        }
    }

    /// Records an authentic frame's counter in its window (created, evicting the least
    /// recently used, for a new sender epoch).
    fn record(&mut self, id: (u64, u64), counter: u64) -> Result<(), AuthReject> {
        self.tick += 1;
        let tick = self.tick;
        if let Some(w) = self.windows.get_mut(&id) {
            w.accept(counter)?;
            w.last_used = tick;
            return Ok(());
        }
        if self.windows.len() >= self.max_windows {
            if let Some(oldest) = self
                .windows
                .iter()
                .min_by_key(|(_, w)| w.last_used)
                .map(|(k, _)| *k)
            {
                self.windows.remove(&oldest);
            }
        }
        let mut w = ReplayWindow::new(counter);
        w.last_used = tick;
        self.windows.insert(id, w);
        Ok(())
    }
}

/// Logs a dropped frame: the first rejections of a link, then every power of two, so a flood
/// does not flood the log too (the counters in link health keep the exact number).
#[cfg_attr(
    not(any(feature = "udp", feature = "shm", feature = "serial")),
    allow(dead_code)
)]
pub(crate) fn log_reject(link: &str, from: impl fmt::Display, why: AuthReject, total: u64) {
    if total.is_power_of_two() {
        tracing::warn!(
            link,
            %from,
            reason = %why,
            total,
            "dropped a frame that failed authentication (link health counts every one)"
        );
    } else {
        tracing::debug!(link, %from, reason = %why, "dropped unauthenticated frame");
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn key(b: u8) -> DomainKey {
        DomainKey::from_bytes([b; KEY_LEN])
    }

    fn sealed(s: &Sealer, body: &[u8], aad: usize) -> Vec<u8> {
        let mut f = body.to_vec();
        s.seal(&mut f, aad);
        f
    }

    #[test]
    fn round_trip_on_every_profile() {
        for p in [
            Profile::UDP,
            Profile::SHM,
            Profile::SERIAL,
            Profile::SERIAL_ENCRYPTED,
        ] {
            let s = Sealer::new(&key(1), p);
            let mut o = Opener::new(&key(1), p, 8);
            for i in 0..5u8 {
                let body = vec![i; 40];
                let mut f = sealed(&s, &body, 5);
                assert_eq!(f.len(), body.len() + p.overhead());
                if p.encrypt {
                    assert_ne!(&f[5..40], &body[5..], "data encrypted");
                    assert_eq!(&f[..5], &body[..5], "header in clear");
                }
                let n = o.open(0, &mut f, 5).unwrap();
                assert_eq!(&f[..n], &body[..], "{p:?}");
            }
        }
    }

    #[test]
    fn wrong_key_and_flipped_bits_are_refused() {
        for p in [Profile::UDP, Profile::SERIAL, Profile::SERIAL_ENCRYPTED] {
            let s = Sealer::new(&key(1), p);
            let f = sealed(&s, b"hello world, a frame", 5);
            let mut other = Opener::new(&key(2), p, 8);
            assert_eq!(other.open(0, &mut f.clone(), 5), Err(AuthReject::BadTag));
            let mut o = Opener::new(&key(1), p, 8);
            for i in 0..f.len() * 8 {
                let mut g = f.clone();
                g[i / 8] ^= 1 << (i % 8);
                assert!(o.open(0, &mut g, 5).is_err(), "bit {i} of {p:?}");
            }
            // A frame of another medium does not verify either.
            let q = if p == Profile::UDP {
                Profile::SHM
            } else {
                Profile::UDP
            };
            let mut g = sealed(&Sealer::new(&key(1), q), b"hello world, a frame", 5);
            if g.len() == f.len() {
                assert!(o.open(0, &mut g, 5).is_err());
            }
            assert_eq!(o.windows(), 0, "no window for frames that did not verify");
            assert_eq!(o.open(0, &mut f.clone(), 5).map(|_| ()), Ok(()));
        }
        let mut o = Opener::new(&key(1), Profile::UDP, 8);
        assert_eq!(o.open(0, &mut [1, 2, 3], 0), Err(AuthReject::Unsealed));
    }

    #[test]
    fn replays_are_refused_and_reordering_within_the_window_is_accepted() {
        let s = Sealer::new(&key(3), Profile::UDP);
        let mut o = Opener::new(&key(3), Profile::UDP, 8);
        let frames: Vec<Vec<u8>> = (0..200u32)
            .map(|i| sealed(&s, &i.to_le_bytes(), 0))
            .collect();
        // Out of order: evens first, then odds.
        for f in frames
            .iter()
            .step_by(2)
            .chain(frames.iter().skip(1).step_by(2))
        {
            assert!(o.open(0, &mut f.clone(), 0).is_ok());
        }
        for f in &frames {
            assert_eq!(o.open(0, &mut f.clone(), 0), Err(AuthReject::Replayed));
        }
        // Move far ahead: the first frames are now too old.
        let mut last = Vec::new();
        for i in 0..2000u32 {
            last = sealed(&s, &i.to_le_bytes(), 0);
        }
        assert!(o.open(0, &mut last.clone(), 0).is_ok());
        assert_eq!(
            o.open(0, &mut frames[0].clone(), 0),
            Err(AuthReject::TooOld)
        );
        assert!(AuthReject::TooOld.is_replay() && !AuthReject::BadTag.is_replay());
    }

    #[test]
    fn a_restarted_sender_is_accepted_and_its_old_frames_stay_refused() {
        let k = key(4);
        let mut o = Opener::new(&k, Profile::SERIAL, 4);
        let first = Sealer::new(&k, Profile::SERIAL);
        let old: Vec<Vec<u8>> = (0..10u8).map(|i| sealed(&first, &[i; 8], 5)).collect();
        for f in &old {
            assert!(o.open(0, &mut f.clone(), 5).is_ok());
        }
        // The same process restarted: a new sealer, counter from 0 again.
        let second = Sealer::with_epoch(&k, Profile::SERIAL, 0xABCDEF ^ 1);
        for i in 0..10u8 {
            assert!(o.open(0, &mut sealed(&second, &[i; 8], 5), 5).is_ok());
        }
        for f in &old {
            assert_eq!(o.open(0, &mut f.clone(), 5), Err(AuthReject::Replayed));
        }
    }

    #[test]
    fn streams_have_their_own_windows_and_the_table_is_bounded() {
        let k = key(5);
        let s = Sealer::with_epoch(&k, Profile::SHM, 7);
        let f = sealed(&s, b"x", 0);
        let mut o = Opener::new(&k, Profile::SHM, 2);
        assert!(o.open(1, &mut f.clone(), 0).is_ok());
        assert!(o.open(2, &mut f.clone(), 0).is_ok(), "another stream");
        assert_eq!(o.open(2, &mut f.clone(), 0), Err(AuthReject::Replayed));
        assert!(o.open(3, &mut f.clone(), 0).is_ok());
        assert_eq!(o.windows(), 2);
    }

    #[test]
    fn the_counter_space_running_out_starts_a_new_epoch() {
        let k = key(6);
        let s = Sealer::with_epoch(&k, Profile::SERIAL, 1);
        lock(&s.state).1 = Profile::SERIAL.max_counter();
        let mut o = Opener::new(&k, Profile::SERIAL, 4);
        let a = sealed(&s, b"last", 0);
        let b = sealed(&s, b"next", 0);
        assert_eq!(get_le(&a[4..7]), 1);
        assert_eq!(get_le(&b[7..10]), 0, "counter restarts");
        assert!(o.open(0, &mut a.clone(), 0).is_ok());
        assert!(o.open(0, &mut b.clone(), 0).is_ok());
    }

    #[test]
    fn sealing_in_place_and_verifying_in_place() {
        let k = key(8);
        let s = Sealer::new(&k, Profile::SHM);
        let mut o = Opener::new(&k, Profile::SHM, 4);
        let mut buf = vec![0u8; 10 + Profile::SHM.overhead()];
        buf[..10].copy_from_slice(b"0123456789");
        s.seal_slice(&mut buf, 10);
        assert_eq!(o.verify(5, &buf), Ok(10));
        assert_eq!(o.verify(5, &buf), Err(AuthReject::Replayed));
        let mut v = b"0123456789".to_vec();
        s.seal(&mut v, 0);
        assert_eq!(o.open(5, &mut v.clone(), 0), Ok(10));
        v[3] ^= 1;
        assert_eq!(o.verify(5, &v), Err(AuthReject::BadTag));
        let mut enc = Opener::new(&k, Profile::SERIAL_ENCRYPTED, 4);
        assert!(enc.verify(0, &buf).is_err());
    }

    #[test]
    fn window_edges() {
        let mut w = ReplayWindow::new(0);
        assert_eq!(w.accept(0), Err(AuthReject::Replayed));
        assert!(w.accept(WINDOW - 64).is_ok());
        assert!(w.accept(1).is_ok(), "still inside");
        assert!(w.accept(WINDOW + 64).is_ok());
        assert_eq!(w.check(2), Err(AuthReject::TooOld));
        assert!(w.accept(u64::MAX / 2).is_ok());
        assert_eq!(w.check(WINDOW + 64), Err(AuthReject::TooOld));
    }

    #[test]
    fn key_files() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("domain.key");
        let k = DomainKey::create_file(&path).unwrap();
        assert_eq!(DomainKey::load(&path).unwrap(), k);
        assert!(matches!(
            DomainKey::create_file(&path),
            Err(KeyFileError::Exists { .. })
        ));
        use std::os::unix::fs::PermissionsExt;
        std::fs::set_permissions(&path, std::fs::Permissions::from_mode(0o640)).unwrap();
        let e = DomainKey::load(&path).unwrap_err();
        assert!(
            matches!(e, KeyFileError::Permissions { mode: 0o640, .. }),
            "{e}"
        );
        assert!(e.to_string().contains("domain.key"), "{e}");
        let bad = dir.path().join("bad.key");
        write_private_new(&bad, b"0123zz\n").unwrap();
        let e = DomainKey::load(&bad).unwrap_err();
        assert!(matches!(e, KeyFileError::Malformed { .. }), "{e}");
        assert!(
            e.to_string().contains("bad.key") && e.to_string().contains("64"),
            "{e}"
        );
        let bad2 = dir.path().join("bad2.key");
        write_private_new(&bad2, "g".repeat(64).as_bytes()).unwrap();
        let e = DomainKey::load(&bad2).unwrap_err();
        assert!(e.to_string().contains("character 1"), "{e}");
        assert!(matches!(
            DomainKey::load(&dir.path().join("none")),
            Err(KeyFileError::Read { .. })
        ));
        assert_eq!(format!("{k:?}"), "DomainKey(..)");
    }

    proptest::proptest! {
        #[test]
        fn random_frames_never_panic_nor_verify(bytes in proptest::collection::vec(proptest::num::u8::ANY, 0..100)) {
            for p in [Profile::UDP, Profile::SERIAL, Profile::SERIAL_ENCRYPTED] {
                let mut o = Opener::new(&key(9), p, 4);
                proptest::prop_assert!(o.open(0, &mut bytes.clone(), 3).is_err());
            }
        }
    }
}
