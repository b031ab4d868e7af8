//! The frames written into a shared-memory inbox and their parsing (no iceoryx2 here). Every
//! frame starts with its kind and its sender's id.
//!
//! ```text
//!  0      1                    9          13                   21
//!  +------+--------------------+----------+--------------------+------------+
//!  | kind | sender id (u64 LE) | session  | seq (u64 LE)       | body ...   |  Safe, SafeMore
//!  +------+--------------------+----------+--------------------+------------+
//!  | kind | sender id (u64 LE) | session  | seq (u64 LE)       |               Ack (cumulative),
//!  +------+--------------------+----------+--------------------+               Bulk, BulkMore
//!  | kind | sender id (u64 LE) | session  | seq (u64 LE)       | body ...   |  BulkData
//!  +------+--------------------+----------+--------------------+------------+
//!  | kind | sender id (u64 LE) | session  | seq (u64 LE)       | entries ...|  SafePack
//!  +------+--------------------+----------+--------------------+------------+
//!  | kind | sender id (u64 LE) | body ...                      |               Announce, Fast
//!  +------+--------------------+-------------------------------+
//! ```
//! `SafeMore` is a fragment followed by more fragments of the same message; `Safe` ends one.
//! `Bulk` and `BulkMore` are the same in the safe inbox for a fragment whose body travels in the
//! bulk inbox as the `BulkData` sample with the same sender, session and sequence number,
//! written just before them.
//!
//! `SafePack` carries several whole safe messages, numbered `seq`, `seq + 1`, ... in order:
//! each entry is its length (u16 LE) then its bytes. A writer packs the messages that queued
//! while its earlier frames were unacknowledged, so one sample (one loan, one send, one
//! release) carries many small messages.

/// The parts of an inbox a frame is written into.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Part {
    /// Fast messages and announcements (overflowing: the oldest is lost).
    Fast,
    /// Safe fragments and acknowledgements (a full buffer refuses the frame).
    Safe,
    /// Bodies of large fragments (`BulkData`; a full buffer refuses the sample).
    Bulk,
}

pub const ANNOUNCE: u8 = 1;
pub const FAST: u8 = 2;
pub const SAFE: u8 = 3;
pub const SAFE_MORE: u8 = 4;
pub const ACK: u8 = 5;
pub const BULK: u8 = 6;
pub const BULK_MORE: u8 = 7;
pub const BULK_DATA: u8 = 8;
pub const SAFE_PACK: u8 = 9;
/// Bytes before each message of a `SafePack` (its length).
pub const PACK_ENTRY_HEADER: usize = 2;
/// Set in the kind byte of a frame sealed with the domain key (see [`crate::link::auth`]): the
/// seal follows the frame. A link without a key drops such frames (and a keyed link any other)
/// before [`parse`], which ignores the bit.
pub const SEALED_KIND: u8 = 0x80;
/// Kind and sender.
pub const BASE: usize = 9;
/// Kind, sender, session and sequence number.
pub const SEQUENCED: usize = 21;

/// A parsed frame.
#[derive(Debug, PartialEq, Eq)]
pub enum Frame<'a> {
    Announce(&'a [u8]),
    Fast(&'a [u8]),
    Safe {
        session: u32,
        seq: u64,
        more: bool,
        body: &'a [u8],
    },
    Ack {
        session: u32,
        seq: u64,
    },
    /// A fragment whose body is in the bulk inbox.
    Bulk {
        session: u32,
        seq: u64,
        more: bool,
    },
    /// The body of a `Bulk` fragment.
    BulkData {
        session: u32,
        seq: u64,
        body: &'a [u8],
    },
    /// Whole safe messages numbered from `seq` (read them with [`pack_entries`]).
    SafePack {
        session: u32,
        seq: u64,
        entries: &'a [u8],
    },
}

/// Why a frame was dropped.
#[derive(Debug, PartialEq, Eq, thiserror::Error)]
pub enum FrameDecodeError {
    /// Shorter than its kind's header.
    #[error("frame of {0} bytes is truncated")]
    Truncated(usize),
    /// Unknown kind byte.
    #[error("unknown frame kind {0}")]
    UnknownKind(u8),
}

/// Writes the header of a frame into `out` (which must hold [`header_len`] bytes).
pub fn write_header(out: &mut [u8], kind: u8, sender: u64, session: u32, seq: u64) {
    out[0] = kind;
    out[1..9].copy_from_slice(&sender.to_le_bytes());
    if header_len(kind) == SEQUENCED {
        out[9..13].copy_from_slice(&session.to_le_bytes());
        out[13..21].copy_from_slice(&seq.to_le_bytes());
    }
}

/// Header length of a frame kind.
pub fn header_len(kind: u8) -> usize {
    match kind {
        SAFE | SAFE_MORE | ACK | BULK | BULK_MORE | BULK_DATA | SAFE_PACK => SEQUENCED,
        _ => BASE,
    }
}

/// Splits a frame into its sender and contents.
pub fn parse(b: &[u8]) -> Result<(u64, Frame<'_>), FrameDecodeError> {
    if b.len() < BASE {
        return Err(FrameDecodeError::Truncated(b.len()));
    }
    let mut id = [0u8; 8];
    id.copy_from_slice(&b[1..9]);
    let sender = u64::from_le_bytes(id);
    let kind = b[0] & !SEALED_KIND;
    let sequenced = || {
        if b.len() < SEQUENCED {
            return Err(FrameDecodeError::Truncated(b.len()));
        }
        let mut s = [0u8; 4];
        s.copy_from_slice(&b[9..13]);
        let mut q = [0u8; 8];
        q.copy_from_slice(&b[13..21]);
        Ok((u32::from_le_bytes(s), u64::from_le_bytes(q)))
    };
    let f = match kind {
        ANNOUNCE => Frame::Announce(&b[BASE..]),
        FAST => Frame::Fast(&b[BASE..]),
        SAFE | SAFE_MORE => {
            let (session, seq) = sequenced()?;
            Frame::Safe {
                session,
                seq,
                more: kind == SAFE_MORE,
                body: &b[SEQUENCED..],
            }
        }
        ACK => {
            let (session, seq) = sequenced()?;
            Frame::Ack { session, seq }
        }
        BULK | BULK_MORE => {
            let (session, seq) = sequenced()?;
            Frame::Bulk {
                session,
                seq,
                more: kind == BULK_MORE,
            }
        }
        BULK_DATA => {
            let (session, seq) = sequenced()?;
            Frame::BulkData {
                session,
                seq,
                body: &b[SEQUENCED..],
            }
        }
        SAFE_PACK => {
            let (session, seq) = sequenced()?;
            Frame::SafePack {
                session,
                seq,
                entries: &b[SEQUENCED..],
            }
        }
        k => return Err(FrameDecodeError::UnknownKind(k)),
    };
    Ok((sender, f))
}

/// Appends one message to the entries of a `SafePack` being built (`msg` is at most
/// [`u16::MAX`] bytes long: the writer packs only messages that fit one frame).
pub fn push_pack_entry(entries: &mut Vec<u8>, msg: &[u8]) {
    let len = u16::try_from(msg.len()).unwrap_or(u16::MAX);
    entries.extend_from_slice(&len.to_le_bytes());
    entries.extend_from_slice(&msg[..usize::from(len)]);
}

/// The messages of a `SafePack`'s entries, in order; an entry running past the end is an
/// error and ends the walk.
pub fn pack_entries(entries: &[u8]) -> PackEntries<'_> {
    PackEntries { rest: entries }
}

/// Iterator over a `SafePack`'s messages (see [`pack_entries`]).
pub struct PackEntries<'a> {
    rest: &'a [u8],
}

impl<'a> Iterator for PackEntries<'a> {
    type Item = Result<&'a [u8], FrameDecodeError>;

    fn next(&mut self) -> Option<Self::Item> {
        if self.rest.is_empty() {
            return None;
        }
        let rest = std::mem::take(&mut self.rest);
        let Some((len, after)) = rest.split_first_chunk::<PACK_ENTRY_HEADER>() else {
            return Some(Err(FrameDecodeError::Truncated(rest.len())));
        };
        let len = usize::from(u16::from_le_bytes(*len));
        if after.len() < len {
            return Some(Err(FrameDecodeError::Truncated(rest.len())));
        }
        let (msg, tail) = after.split_at(len);
        self.rest = tail;
        Some(Ok(msg))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn golden_safe_frame() {
        let mut b = vec![0u8; SEQUENCED + 2];
        write_header(&mut b, SAFE_MORE, 0x0102_0304_0506_0708, 9, 0x1_0000_0002);
        b[21..].copy_from_slice(b"hi");
        assert_eq!(
            b,
            [
                4, // kind: SafeMore
                8, 7, 6, 5, 4, 3, 2, 1, // sender id, little endian
                9, 0, 0, 0, // session
                2, 0, 0, 0, 1, 0, 0, 0, // sequence number
                b'h', b'i', // body
            ]
        );
        assert_eq!(
            parse(&b),
            Ok((
                0x0102_0304_0506_0708,
                Frame::Safe {
                    session: 9,
                    seq: 0x1_0000_0002,
                    more: true,
                    body: b"hi"
                }
            ))
        );
    }

    #[test]
    fn golden_fast_and_ack_frames() {
        let mut f = vec![0u8; BASE + 1];
        write_header(&mut f, FAST, 1, 77, 77);
        f[9] = 0xAA;
        assert_eq!(f, [2, 1, 0, 0, 0, 0, 0, 0, 0, 0xAA]);
        assert_eq!(parse(&f), Ok((1, Frame::Fast(&[0xAA]))));
        let mut a = vec![0u8; SEQUENCED];
        write_header(&mut a, ACK, 2, 3, 4);
        assert_eq!(
            a,
            [5, 2, 0, 0, 0, 0, 0, 0, 0, 3, 0, 0, 0, 4, 0, 0, 0, 0, 0, 0, 0]
        );
        assert_eq!(parse(&a), Ok((2, Frame::Ack { session: 3, seq: 4 })));
    }

    #[test]
    fn golden_bulk_frames() {
        let mut d = vec![0u8; SEQUENCED];
        write_header(&mut d, BULK_MORE, 1, 2, 3);
        assert_eq!(
            d,
            [
                7, // kind: BulkMore (the body is in the bulk inbox, more fragments follow)
                1, 0, 0, 0, 0, 0, 0, 0, // sender id
                2, 0, 0, 0, // session
                3, 0, 0, 0, 0, 0, 0, 0, // sequence number
            ]
        );
        assert_eq!(
            parse(&d),
            Ok((
                1,
                Frame::Bulk {
                    session: 2,
                    seq: 3,
                    more: true
                }
            ))
        );
        d[0] = BULK;
        assert_eq!(
            parse(&d),
            Ok((
                1,
                Frame::Bulk {
                    session: 2,
                    seq: 3,
                    more: false
                }
            ))
        );
        let mut b = vec![0u8; SEQUENCED + 1];
        write_header(&mut b, BULK_DATA, 1, 2, 3);
        b[21] = 0xEE;
        assert_eq!(
            b,
            [8, 1, 0, 0, 0, 0, 0, 0, 0, 2, 0, 0, 0, 3, 0, 0, 0, 0, 0, 0, 0, 0xEE]
        );
        assert_eq!(
            parse(&b),
            Ok((
                1,
                Frame::BulkData {
                    session: 2,
                    seq: 3,
                    body: &[0xEE]
                }
            ))
        );
        assert_eq!(parse(&b[..20]), Err(FrameDecodeError::Truncated(20)));
    }

    #[test]
    fn golden_pack_frame() {
        let mut entries = Vec::new();
        push_pack_entry(&mut entries, b"ab");
        push_pack_entry(&mut entries, b"");
        push_pack_entry(&mut entries, b"c");
        let mut p = vec![0u8; SEQUENCED];
        write_header(&mut p, SAFE_PACK, 1, 2, 3);
        p.extend_from_slice(&entries);
        assert_eq!(
            p,
            [
                9, // kind: SafePack
                1, 0, 0, 0, 0, 0, 0, 0, // sender id
                2, 0, 0, 0, // session
                3, 0, 0, 0, 0, 0, 0, 0, // sequence number of the first message
                2, 0, b'a', b'b', // message 3
                0, 0, // message 4 (empty)
                1, 0, b'c', // message 5
            ]
        );
        let Ok((
            1,
            Frame::SafePack {
                session: 2,
                seq: 3,
                entries,
            },
        )) = parse(&p)
        else {
            panic!("not a pack: {:?}", parse(&p));
        };
        let msgs: Vec<_> = pack_entries(entries).collect();
        assert_eq!(msgs, [Ok(&b"ab"[..]), Ok(&b""[..]), Ok(&b"c"[..])]);
    }

    #[test]
    fn a_pack_entry_running_past_the_end_ends_the_walk_with_an_error() {
        // A whole entry, then one claiming 5 bytes with 2 there, then a lone length byte.
        let msgs: Vec<_> = pack_entries(&[1, 0, 7, 5, 0, 1, 2]).collect();
        assert_eq!(msgs, [Ok(&[7u8][..]), Err(FrameDecodeError::Truncated(4))]);
        let msgs: Vec<_> = pack_entries(&[1, 0, 7, 9]).collect();
        assert_eq!(msgs, [Ok(&[7u8][..]), Err(FrameDecodeError::Truncated(1))]);
    }

    #[test]
    fn malformed_frames_are_errors() {
        assert_eq!(parse(&[]), Err(FrameDecodeError::Truncated(0)));
        assert_eq!(
            parse(&[3, 0, 0, 0, 0, 0, 0, 0, 0, 1]),
            Err(FrameDecodeError::Truncated(10))
        );
        assert_eq!(
            parse(&[99, 0, 0, 0, 0, 0, 0, 0, 0]),
            Err(FrameDecodeError::UnknownKind(99))
        );
        for len in 0..40 {
            let b: Vec<u8> = (0..len).map(|i| (i * 37 % 251) as u8).collect();
            let _ = parse(&b);
        }
    }
}
