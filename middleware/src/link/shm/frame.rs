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
//!  | kind | sender id (u64 LE) | body ...                      |               Announce, Fast
//!  +------+--------------------+-------------------------------+
//! ```
//! `SafeMore` is a fragment followed by more fragments of the same message; `Safe` ends one.
//! `Bulk` and `BulkMore` are the same in the safe inbox for a fragment whose body travels in the
//! bulk inbox as the `BulkData` sample with the same sender, session and sequence number,
//! written just before them.

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
        SAFE | SAFE_MORE | ACK | BULK | BULK_MORE | BULK_DATA => SEQUENCED,
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
        k => return Err(FrameDecodeError::UnknownKind(k)),
    };
    Ok((sender, f))
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
