//! The datagram framing of the UDP and Zenoh links: several link entries (fast messages, safe
//! messages, session starts and acknowledgements) batched into one datagram; and [`link`], the
//! link of ARQ sessions both build on, over any datagram [`link::Medium`].
//!
//! ```text
//! datagram  := kind:u8 body
//! kind      := 0xA1 (data: entries follow) | 0xA2 (discovery: one Message follows)
//! entry     := 0x01 len:varint msg              FAST  best effort
//!            | 0x02 seq:varint len:varint msg   SAFE  reliable, ordered
//!            | 0x03 session:u32le               SYN   starts a sender session (seq 0 next)
//!            | 0x04 session:u32le next:varint sack:varint
//!                                               ACK   all seq < next received; bit i of sack
//!                                                     = seq next+1+i received too
//!            | 0x05 seq:varint                  UNKNOWN  the receiver holds no session of the
//!                                                     sender (it forgot it) and dropped safe
//!                                                     seq unread: the sender starts a new one
//! ```
//! A message larger than a datagram goes as consecutive SAFE entries, its parts (module `parts`).
//!
//! A 32-byte position sample costs 1 (kind) + 1 (FAST) + 1 (len) + 35 (message) = 38 bytes.
//!
//! With a domain key the kind is 0xA3 (data) or 0xA4 (discovery) and the datagram ends with
//! the seal of [`crate::link::auth`] (epoch, counter, tag: 16 bytes), so a position sample
//! costs 54 bytes; a node without the key sees an unknown kind and drops the datagram.

mod agenda;
pub mod link;
mod parts;
mod sessions;

use crate::codec::varint::{len_u64, put_u64, take_u64};
use crate::link::arq::AckInfo;

/// First byte of a data datagram.
pub const KIND_DATA: u8 = 0xA1;
/// First byte of a discovery datagram.
pub const KIND_DISCOVERY: u8 = 0xA2;
/// First byte of a sealed data datagram (a data datagram with the seal appended).
pub const KIND_SEALED_DATA: u8 = 0xA3;
/// First byte of a sealed discovery datagram.
pub const KIND_SEALED_DISCOVERY: u8 = 0xA4;
/// First byte of a data datagram sealed with the keys its sender and receiver share
/// ([`crate::link::auth::PairKeys`]), not the domain key.
pub const KIND_PAIR_DATA: u8 = 0xA5;
const TAG_FAST: u8 = 0x01;

/// The kind a datagram of `kind` takes once sealed.
pub fn sealed_kind(kind: u8) -> u8 {
    match kind {
        KIND_DISCOVERY => KIND_SEALED_DISCOVERY,
        _ => KIND_SEALED_DATA,
    }
}

/// The plain kind of a sealed datagram kind; `None` for a kind that is not sealed.
pub fn unsealed_kind(kind: u8) -> Option<u8> {
    match kind {
        KIND_SEALED_DATA | KIND_PAIR_DATA => Some(KIND_DATA),
        KIND_SEALED_DISCOVERY => Some(KIND_DISCOVERY),
        _ => None,
    }
}
const TAG_SAFE: u8 = 0x02;
const TAG_SYN: u8 = 0x03;
const TAG_ACK: u8 = 0x04;
const TAG_UNKNOWN: u8 = 0x05;

/// One entry of a data datagram, borrowing from the datagram.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Entry<'a> {
    /// A best-effort message.
    Fast(&'a [u8]),
    /// A reliable message with its sequence number.
    Safe {
        /// Sequence number in the sender's session.
        seq: u32,
        /// The message bytes.
        msg: &'a [u8],
    },
    /// The sender's session id; seq numbers that follow belong to it.
    Syn(u32),
    /// An acknowledgement.
    Ack(AckInfo),
    /// The receiver holds no session of ours (it forgot us, a lease or a restart) and dropped
    /// our safe message of this seq unread: without it the sender would retransmit into the
    /// void until its retry limit.
    Unknown(u32),
}

/// A datagram that could not be decoded.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum DatagramDecodeError {
    /// Empty datagram.
    #[error("empty datagram")]
    Empty,
    /// First byte is not a known kind.
    #[error("unknown datagram kind 0x{0:02x}")]
    UnknownKind(u8),
    /// An entry tag is unknown.
    #[error("unknown entry tag 0x{0:02x}")]
    UnknownTag(u8),
    /// An entry was cut short or claimed more bytes than present.
    #[error("truncated entry")]
    Truncated,
    /// A sequence number did not fit 32 bits.
    #[error("sequence number out of range")]
    SeqOutOfRange,
}

/// Builds one data datagram, refusing entries that would exceed `max` bytes.
#[derive(Debug)]
pub struct DatagramWriter {
    buf: Vec<u8>,
    max: usize,
    /// Entries written other than SYN: a datagram holding only the header and a SYN still
    /// takes one oversized entry (otherwise a large first safe message could never be sent).
    entries: usize,
    /// Buffers of datagrams already sent, taken before allocating a new one.
    spare: Vec<Vec<u8>>,
}

impl DatagramWriter {
    /// A writer for datagrams of at most `max` bytes.
    pub fn new(max: usize) -> Self {
        Self::reusing(max, Vec::new())
    }

    /// A writer for datagrams of at most `max` bytes that builds them in the `spare` buffers
    /// first: a stream's datagrams then reuse memory already grown to their size instead of
    /// growing a fresh allocation (copies and page faults) for each one.
    pub fn reusing(max: usize, spare: Vec<Vec<u8>>) -> Self {
        let mut w = DatagramWriter {
            buf: Vec::new(),
            max,
            entries: 0,
            spare,
        };
        w.buf = w.fresh();
        w
    }

    /// An empty datagram buffer: a spare one, or a new one grown as entries come (a loopback
    /// writer may take 60 KiB, most datagrams are small).
    fn fresh(&mut self) -> Vec<u8> {
        let mut buf = self
            .spare
            .pop()
            .unwrap_or_else(|| Vec::with_capacity(self.max.min(2048)));
        buf.clear();
        buf.push(KIND_DATA);
        buf
    }

    /// The spare buffers not used.
    pub fn into_spare(self) -> Vec<Vec<u8>> {
        self.spare
    }

    /// Bytes written so far.
    pub fn len(&self) -> usize {
        self.buf.len()
    }

    /// Whether only the header is written.
    pub fn is_empty(&self) -> bool {
        self.buf.len() <= 1
    }

    /// Bytes a FAST entry for `msg_len` would take.
    pub fn fast_cost(msg_len: usize) -> usize {
        1 + len_u64(msg_len as u64) + msg_len
    }

    /// Bytes a SAFE entry would take.
    pub fn safe_cost(seq: u32, msg_len: usize) -> usize {
        1 + len_u64(u64::from(seq)) + len_u64(msg_len as u64) + msg_len
    }

    fn fits(&self, cost: usize) -> bool {
        // A datagram with no entry yet (a SYN aside) accepts one oversized entry, so a large
        // message still goes out.
        self.buf.len() + cost <= self.max || self.entries == 0
    }

    /// Appends a FAST entry; `false` (nothing written) when it does not fit.
    pub fn push_fast(&mut self, msg: &[u8]) -> bool {
        if !self.fits(Self::fast_cost(msg.len())) {
            return false;
        }
        self.buf.push(TAG_FAST);
        put_u64(&mut self.buf, msg.len() as u64);
        self.buf.extend_from_slice(msg);
        self.entries += 1;
        true
    }

    /// Appends a SAFE entry; `false` when it does not fit.
    pub fn push_safe(&mut self, seq: u32, msg: &[u8]) -> bool {
        if !self.fits(Self::safe_cost(seq, msg.len())) {
            return false;
        }
        self.buf.push(TAG_SAFE);
        put_u64(&mut self.buf, u64::from(seq));
        put_u64(&mut self.buf, msg.len() as u64);
        self.buf.extend_from_slice(msg);
        self.entries += 1;
        true
    }

    /// Appends a SYN entry (5 bytes); `false` when it does not fit.
    pub fn push_syn(&mut self, session: u32) -> bool {
        if !self.fits(5) {
            return false;
        }
        self.buf.push(TAG_SYN);
        self.buf.extend_from_slice(&session.to_le_bytes());
        true
    }

    /// Appends an ACK entry; `false` when it does not fit.
    pub fn push_ack(&mut self, ack: AckInfo) -> bool {
        let cost = 5 + len_u64(u64::from(ack.next)) + len_u64(ack.sack);
        if !self.fits(cost) {
            return false;
        }
        self.buf.push(TAG_ACK);
        self.buf.extend_from_slice(&ack.session.to_le_bytes());
        put_u64(&mut self.buf, u64::from(ack.next));
        put_u64(&mut self.buf, ack.sack);
        self.entries += 1;
        true
    }

    /// Appends an UNKNOWN entry; `false` when it does not fit.
    pub fn push_unknown(&mut self, seq: u32) -> bool {
        if !self.fits(1 + len_u64(u64::from(seq))) {
            return false;
        }
        self.buf.push(TAG_UNKNOWN);
        put_u64(&mut self.buf, u64::from(seq));
        self.entries += 1;
        true
    }

    /// The finished datagram; the writer is reset for the next one.
    pub fn take(&mut self) -> Vec<u8> {
        let next = self.fresh();
        self.entries = 0;
        std::mem::replace(&mut self.buf, next)
    }
}

/// Builds a discovery datagram around one encoded message.
pub fn discovery_datagram(msg: &[u8]) -> Vec<u8> {
    let mut v = Vec::with_capacity(msg.len() + 1);
    v.push(KIND_DISCOVERY);
    v.extend_from_slice(msg);
    v
}

/// A decoded datagram.
#[derive(Debug, PartialEq, Eq)]
pub enum Datagram<'a> {
    /// Data entries.
    Data(Vec<Entry<'a>>),
    /// One discovery message (still encoded).
    Discovery(&'a [u8]),
}

fn take_u32_le(input: &mut &[u8]) -> Result<u32, DatagramDecodeError> {
    if input.len() < 4 {
        return Err(DatagramDecodeError::Truncated);
    }
    let (head, rest) = input.split_at(4);
    *input = rest;
    Ok(u32::from_le_bytes([head[0], head[1], head[2], head[3]]))
}

fn take_bytes<'a>(input: &mut &'a [u8]) -> Result<&'a [u8], DatagramDecodeError> {
    let len = take_u64(input).ok_or(DatagramDecodeError::Truncated)?;
    let len = usize::try_from(len).map_err(|_| DatagramDecodeError::Truncated)?;
    if len > input.len() {
        return Err(DatagramDecodeError::Truncated);
    }
    let (head, rest) = input.split_at(len);
    *input = rest;
    Ok(head)
}

/// Decodes a datagram. Entries borrow from `bytes`; the entry list is bounded by the datagram
/// length (every entry takes at least two bytes).
///
/// # Errors
/// [`DatagramDecodeError`] on the first malformed entry; the whole datagram is then dropped.
pub fn decode(bytes: &[u8]) -> Result<Datagram<'_>, DatagramDecodeError> {
    let (&kind, mut rest) = bytes.split_first().ok_or(DatagramDecodeError::Empty)?;
    match kind {
        KIND_DISCOVERY => Ok(Datagram::Discovery(rest)),
        KIND_DATA => {
            let mut entries = Vec::new();
            while let Some((&tag, r)) = rest.split_first() {
                rest = r;
                let entry = match tag {
                    TAG_FAST => Entry::Fast(take_bytes(&mut rest)?),
                    TAG_SAFE => {
                        let seq = take_u64(&mut rest).ok_or(DatagramDecodeError::Truncated)?;
                        let seq =
                            u32::try_from(seq).map_err(|_| DatagramDecodeError::SeqOutOfRange)?;
                        Entry::Safe {
                            seq,
                            msg: take_bytes(&mut rest)?,
                        }
                    }
                    TAG_SYN => Entry::Syn(take_u32_le(&mut rest)?),
                    TAG_ACK => {
                        let session = take_u32_le(&mut rest)?;
                        let next = take_u64(&mut rest).ok_or(DatagramDecodeError::Truncated)?;
                        let next =
                            u32::try_from(next).map_err(|_| DatagramDecodeError::SeqOutOfRange)?;
                        let sack = take_u64(&mut rest).ok_or(DatagramDecodeError::Truncated)?;
                        Entry::Ack(AckInfo {
                            session,
                            next,
                            sack,
                        })
                    }
                    TAG_UNKNOWN => {
                        let seq = take_u64(&mut rest).ok_or(DatagramDecodeError::Truncated)?;
                        Entry::Unknown(
                            u32::try_from(seq).map_err(|_| DatagramDecodeError::SeqOutOfRange)?,
                        )
                    }
                    other => return Err(DatagramDecodeError::UnknownTag(other)),
                };
                entries.push(entry);
            }
            Ok(Datagram::Data(entries))
        }
        other => Err(DatagramDecodeError::UnknownKind(other)),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn golden_bytes_for_each_entry() {
        let mut w = DatagramWriter::new(1400);
        assert!(w.push_syn(0x0403_0201));
        assert!(w.push_safe(300, &[9]));
        assert!(w.push_fast(&[7, 8]));
        assert!(w.push_ack(AckInfo {
            session: 1,
            next: 2,
            sack: 0b101,
        }));
        let d = w.take();
        assert_eq!(
            d,
            vec![
                0xA1, // data datagram
                0x03, 1, 2, 3, 4, // SYN session 0x04030201 little endian
                0x02, 0xAC, 0x02, 1, 9, // SAFE seq 300, len 1, msg [9]
                0x01, 2, 7, 8, // FAST len 2, msg [7, 8]
                0x04, 1, 0, 0, 0, 2, 5, // ACK session 1, next 2, sack 0b101
            ]
        );
        let Datagram::Data(entries) = decode(&d).unwrap() else {
            panic!("not data")
        };
        assert_eq!(
            entries,
            vec![
                Entry::Syn(0x0403_0201),
                Entry::Safe {
                    seq: 300,
                    msg: &[9]
                },
                Entry::Fast(&[7, 8]),
                Entry::Ack(AckInfo {
                    session: 1,
                    next: 2,
                    sack: 5
                })
            ]
        );
        assert_eq!(discovery_datagram(&[1, 2]), vec![0xA2, 1, 2]);
        assert_eq!(decode(&[0xA2, 1, 2]), Ok(Datagram::Discovery(&[1, 2])));
    }

    /// DESIGN §8: a position sample (3×f64 + 2×f32 = 32 bytes of payload) costs at most 40
    /// bytes of UDP payload. This is the datagram the link sends for one lone variable value.
    #[test]
    fn position_sample_is_38_bytes_of_udp_payload() {
        let payload =
            crate::codec::encode_payload(&(41.275f64, 1.987f64, 12.5f64, 90.0f32, 1.5f32))
                .expect("plain tuple encodes");
        assert_eq!(payload.len(), 32);
        let msg = crate::codec::encode_message(&crate::protocol::Message::Var { id: 7, payload });
        let mut w = DatagramWriter::new(1400);
        assert!(w.push_fast(&msg));
        assert_eq!(w.take().len(), 38);
    }

    /// Sealed with a domain key, the same sample costs at most 54 bytes.
    #[test]
    fn sealed_position_sample_is_54_bytes_of_udp_payload() {
        use crate::link::auth::{DomainKey, Opener, Profile, Sealer};
        let payload =
            crate::codec::encode_payload(&(41.275f64, 1.987f64, 12.5f64, 90.0f32, 1.5f32))
                .expect("plain tuple encodes");
        let msg = crate::codec::encode_message(&crate::protocol::Message::Var { id: 7, payload });
        let mut w = DatagramWriter::new(1400);
        assert!(w.push_fast(&msg));
        let mut d = w.take();
        d[0] = sealed_kind(d[0]);
        let key = DomainKey::from_bytes([7; 32]);
        Sealer::new(&key, Profile::UDP).seal(&mut d, usize::MAX);
        assert_eq!(d.len(), 54);
        assert_eq!(d[0], KIND_SEALED_DATA);
        // A node without the key: an unknown kind, an error, no panic.
        assert_eq!(decode(&d), Err(DatagramDecodeError::UnknownKind(0xA3)));
        let n = Opener::new(&key, Profile::UDP, 4)
            .open(0, &mut d, usize::MAX)
            .unwrap();
        assert_eq!(unsealed_kind(d[0]), Some(KIND_DATA));
        d[0] = KIND_DATA;
        assert_eq!(decode(&d[..n]), Ok(Datagram::Data(vec![Entry::Fast(&msg)])));
        assert_eq!(sealed_kind(KIND_DISCOVERY), KIND_SEALED_DISCOVERY);
        assert_eq!(unsealed_kind(KIND_DATA), None);
    }

    #[test]
    fn writer_respects_the_limit_but_takes_one_oversized_entry() {
        let mut w = DatagramWriter::new(10);
        assert!(
            w.push_fast(&[0; 20]),
            "an empty datagram takes one big entry"
        );
        assert!(!w.push_fast(&[0; 1]));
        let mut w = DatagramWriter::new(10);
        assert!(w.push_fast(&[0; 4]));
        assert!(!w.push_fast(&[0; 4]));
    }

    /// A large first safe message follows the SYN in the same datagram (an infinite loop
    /// once: SYN, no room, new datagram, SYN again...).
    #[test]
    fn a_syn_leaves_room_for_one_oversized_entry() {
        let mut w = DatagramWriter::new(100);
        assert!(w.push_syn(1));
        assert!(w.push_safe(0, &[0; 500]));
        assert!(!w.push_safe(1, &[0; 10]));
        assert_eq!(w.take().len(), 1 + 5 + 1 + 1 + 2 + 500);
        assert!(w.push_ack(AckInfo {
            session: 1,
            next: 0,
            sack: 0
        }));
        assert!(
            !w.push_safe(0, &[0; 500]),
            "an ack already takes the datagram's room"
        );
    }

    #[test]
    fn malformed_datagrams_are_errors() {
        assert_eq!(decode(&[]), Err(DatagramDecodeError::Empty));
        assert_eq!(decode(&[0x00]), Err(DatagramDecodeError::UnknownKind(0)));
        assert_eq!(
            decode(&[0xA1, 0x09]),
            Err(DatagramDecodeError::UnknownTag(9))
        );
        assert_eq!(
            decode(&[0xA1, 0x01, 5, 1]),
            Err(DatagramDecodeError::Truncated)
        );
        assert_eq!(
            decode(&[0xA1, 0x03, 1]),
            Err(DatagramDecodeError::Truncated)
        );
        assert_eq!(
            decode(&[0xA1, 0x01, 0xFF, 0xFF, 0xFF, 0xFF, 0xFF, 0xFF, 0xFF, 0xFF, 0xFF, 0x01]),
            Err(DatagramDecodeError::Truncated)
        );
    }

    proptest::proptest! {
        #[test]
        fn random_bytes_never_panic(bytes in proptest::collection::vec(proptest::num::u8::ANY, 0..200)) {
            let _ = decode(&bytes);
        }
    }
}
