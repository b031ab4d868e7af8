//! (Feature `fuzzing`; the structured fuzz harnesses' shared generators, kept in the `protocol`
//! layer so harnesses of every layer can use them.)
//!
//! Generators of valid-shaped inputs from an [`Unstructured`]: names and patterns as services
//! use them, whole [`Message`]s of every kind, declaration batches. Most of what they make is
//! what a real peer would send; a small share is bent (a bad character, an empty segment, a
//! pattern of many `**`) so the refusal paths run too.

use arbitrary::{Result, Unstructured};

use super::{
    Declaration, FileOffer, FileVerdict, ItemKind, LoggedDeclaration, Message, Origin,
    RemoteFailure,
};
use crate::typeinfo::TypeInfo;

const WORDS: &[&str] = &[
    "rover1",
    "rover2",
    "air",
    "station",
    "vas",
    "fpma",
    "fmo",
    "position",
    "speed",
    "plans",
    "push_waypoints",
    "change_state",
    "manual_control",
    "alarm",
    "a",
    "b",
    "x.y",
    "v-2",
    "_t",
];

/// One name segment: usually a known word, sometimes random characters of the allowed set,
/// rarely a character outside it.
pub fn segment(u: &mut Unstructured<'_>) -> Result<String> {
    Ok(match u.int_in_range(0u8..=17)? {
        0..=10 => (*u.choose(WORDS)?).to_owned(),
        11..=14 => {
            const SET: &[u8] = b"abcdefghijklmnopqrstuvwxyzABCXYZ0123456789_-.";
            let len = u.int_in_range(1usize..=24)?;
            let mut s = String::with_capacity(len);
            for _ in 0..len {
                s.push(char::from(*u.choose(SET)?));
            }
            s
        }
        // Outside the set: space, slash-free punctuation, non-ASCII, empty.
        _ => (*u.choose(&["", "a b", "é", "x*", "\0", "a\\b"])?).to_owned(),
    })
}

/// A concrete name of one to six segments (`rover1/vas/position`).
pub fn name(u: &mut Unstructured<'_>) -> Result<String> {
    let n = u.int_in_range(1usize..=6)?;
    let mut segs = Vec::with_capacity(n);
    for _ in 0..n {
        segs.push(segment(u)?);
    }
    Ok(segs.join("/"))
}

/// A subscription pattern: segments, `*` and `**`, sometimes a long run of `**` (the shape
/// that once pinned a core) or a very long pattern.
pub fn pattern(u: &mut Unstructured<'_>) -> Result<String> {
    if u.ratio(1u8, 16)? {
        let stars = u.int_in_range(1usize..=600)?;
        let tail = segment(u)?;
        return Ok(format!("{}{tail}", "**/".repeat(stars)));
    }
    let n = u.int_in_range(1usize..=8)?;
    let mut segs = Vec::with_capacity(n);
    for _ in 0..n {
        segs.push(match u.int_in_range(0u8..=5)? {
            0 => "*".to_owned(),
            1 => "**".to_owned(),
            _ => segment(u)?,
        });
    }
    Ok(segs.join("/"))
}

/// A short string of any characters (domains, node names, handler errors).
pub fn text(u: &mut Unstructured<'_>, max: usize) -> Result<String> {
    let len = u.int_in_range(0..=max)?;
    let mut s = String::with_capacity(len);
    for _ in 0..len {
        s.push(u.arbitrary::<char>()?);
    }
    Ok(s)
}

/// Bytes of a payload, up to `max`.
pub fn bytes(u: &mut Unstructured<'_>, max: usize) -> Result<Vec<u8>> {
    let len = u.int_in_range(0..=max)?;
    Ok(u.bytes(len.min(u.len()))?.to_vec())
}

fn kind(u: &mut Unstructured<'_>) -> Result<ItemKind> {
    Ok(*u.choose(&[
        ItemKind::Variable,
        ItemKind::Event,
        ItemKind::Function,
        ItemKind::File,
    ])?)
}

fn type_info(u: &mut Unstructured<'_>) -> Result<TypeInfo> {
    // Half the time a real type, so that items of the same type meet.
    if u.ratio(1u8, 2)? {
        return Ok(if u.arbitrary()? {
            TypeInfo::of::<u64>()
        } else {
            TypeInfo::of::<u8>()
        });
    }
    Ok(TypeInfo {
        name: (*u.choose(&["u64", "f32", "usal_types::Position", "String", "()"])?).to_owned(),
        fingerprint: u.arbitrary()?,
    })
}

/// A node id: mostly one of a few (so declarations and byes refer to each other), sometimes any.
pub fn node_id(u: &mut Unstructured<'_>) -> Result<u64> {
    if u.ratio(3u8, 4)? {
        Ok(u.int_in_range(1u64..=4)?)
    } else {
        u.arbitrary()
    }
}

/// One declaration: services, offers with and without a gateway's origin, interests with
/// patterns, withdrawals of earlier ids.
pub fn declaration(u: &mut Unstructured<'_>) -> Result<Declaration> {
    let id = u.int_in_range(0u32..=64)?;
    Ok(match u.int_in_range(0u8..=9)? {
        0 => Declaration::Service {
            id,
            name: segment(u)?,
        },
        1..=4 => Declaration::Offer {
            id,
            service: u.int_in_range(0u32..=8)?,
            kind: kind(u)?,
            name: name(u)?,
            ty: type_info(u)?,
            origin: maybe_origin(u)?,
        },
        5..=8 => Declaration::Interest {
            id,
            service: u.int_in_range(0u32..=8)?,
            kind: kind(u)?,
            pattern: pattern(u)?,
            ty: type_info(u)?,
        },
        _ => Declaration::Withdraw { id },
    })
}

/// A declaration batch as a peer sends it: counters increasing from `after`, mostly
/// consistent (`upto` the last counter), sometimes lying.
pub fn decl_batch(u: &mut Unstructured<'_>) -> Result<Message> {
    let after = u.int_in_range(0u32..=100)?;
    let mut counter = after;
    let mut entries = Vec::new();
    u.arbitrary_loop(Some(0), Some(64), |u| {
        counter = counter.saturating_add(u.int_in_range(1u32..=3)?);
        entries.push(LoggedDeclaration {
            counter,
            decl: declaration(u)?,
        });
        Ok(std::ops::ControlFlow::Continue(()))
    })?;
    let upto = if u.ratio(7u8, 8)? {
        counter
    } else {
        u.arbitrary()?
    };
    Ok(Message::DeclBatch {
        after,
        upto,
        reset: u.arbitrary()?,
        entries,
    })
}

fn remote_failure(u: &mut Unstructured<'_>) -> Result<RemoteFailure> {
    Ok(match u.int_in_range(0u8..=6)? {
        0 => RemoteFailure::Handler(text(u, 40)?),
        1 => RemoteFailure::BadArguments(text(u, 40)?),
        2 => RemoteFailure::NotProvided,
        3 => RemoteFailure::DeadlineExpired,
        4 => RemoteFailure::Denied,
        5 => RemoteFailure::Busy,
        _ => RemoteFailure::Superseded,
    })
}

fn verdict(u: &mut Unstructured<'_>) -> Result<FileVerdict> {
    Ok(match u.int_in_range(0u8..=5)? {
        0 => FileVerdict::Stored,
        1 => FileVerdict::Failed(text(u, 40)?),
        2 => FileVerdict::TooLarge {
            size: u.arbitrary()?,
            max: u.arbitrary()?,
        },
        3 => FileVerdict::QuotaExceeded {
            needed: u.arbitrary()?,
            quota: u.arbitrary()?,
        },
        4 => FileVerdict::Busy {
            max: u.arbitrary()?,
        },
        _ => FileVerdict::Denied(text(u, 40)?),
    })
}

/// Any message, shaped as a peer would send it.
pub fn message(u: &mut Unstructured<'_>) -> Result<Message> {
    Ok(match u.int_in_range(0u8..=16)? {
        0 => Message::Hello {
            node_id: node_id(u)?,
            domain: segment(u)?,
            node: segment(u)?,
            namespace: segment(u)?,
            counter: u.arbitrary()?,
            lease_ms: u.arbitrary()?,
            gateway: u.arbitrary()?,
            asks_introduction: u.arbitrary()?,
        },
        1 => Message::Heartbeat {
            node_id: node_id(u)?,
            domain_hash: u.arbitrary()?,
            counter: u.arbitrary()?,
        },
        2 => Message::DeclRequest {
            since: u.arbitrary()?,
        },
        3 | 4 => decl_batch(u)?,
        5 => Message::Refused {
            interest: u.arbitrary()?,
            name: name(u)?,
            offered: type_info(u)?,
        },
        6 => Message::Var {
            id: u.int_in_range(0u32..=64)?,
            payload: bytes(u, 64)?,
        },
        7 => Message::Event {
            id: u.int_in_range(0u32..=64)?,
            payload: bytes(u, 256)?,
        },
        8 => Message::Call {
            call_id: u.arbitrary()?,
            id: u.int_in_range(0u32..=64)?,
            remaining_ms: u.arbitrary()?,
            args: bytes(u, 128)?,
            caller: maybe_origin(u)?,
        },
        9 => Message::Reply {
            call_id: u.arbitrary()?,
            result: if u.arbitrary()? {
                Ok(bytes(u, 128)?)
            } else {
                Err(remote_failure(u)?)
            },
        },
        10 => Message::FileOffer(FileOffer {
            transfer: u.arbitrary()?,
            sink: u.int_in_range(0u32..=64)?,
            name: text(u, 32)?,
            size: u.arbitrary()?,
            hash: u.arbitrary()?,
            sender: maybe_origin(u)?,
        }),
        11 => Message::FileAccept {
            transfer: u.arbitrary()?,
            offset: u.arbitrary()?,
        },
        12 => Message::FileChunk {
            transfer: u.arbitrary()?,
            offset: u.arbitrary()?,
            data: bytes(u, 512)?,
        },
        13 => Message::FileDone {
            transfer: u.arbitrary()?,
            verdict: verdict(u)?,
        },
        14 => Message::FileCancel {
            transfer: u.arbitrary()?,
        },
        15 => Message::Identity {
            public_key: u.arbitrary()?,
            signature: bytes(u, 64)?,
            agreement: u.arbitrary()?,
        },
        16 => Message::Challenge {
            nonce: u.arbitrary()?,
            agreement: u.arbitrary()?,
        },
        17 => Message::Flow {
            behind: u.arbitrary()?,
            readers: u.arbitrary()?,
            offers: if u.arbitrary()? {
                let n = u.int_in_range(0usize..=8)?;
                Some(
                    (0..n)
                        .map(|_| u.int_in_range(0u32..=64))
                        .collect::<Result<_>>()?,
                )
            } else {
                None
            },
        },
        _ => Message::Bye {
            node_id: node_id(u)?,
        },
    })
}

/// How a byte string is bent on its way: cut, a byte flipped, bytes appended, or left alone.
pub fn mutate(u: &mut Unstructured<'_>, b: &mut Vec<u8>) -> Result<()> {
    match u.int_in_range(0u8..=5)? {
        0 => {
            let cut = u.int_in_range(0..=b.len())?;
            b.truncate(cut);
        }
        1 if !b.is_empty() => {
            let i = u.int_in_range(0..=b.len() - 1)?;
            b[i] ^= u.int_in_range(1u8..=255)?;
        }
        2 => {
            let extra = bytes(u, 16)?;
            b.extend(extra);
        }
        3 if !b.is_empty() => {
            let i = u.int_in_range(0..=b.len() - 1)?;
            b[i] = *u.choose(&[0x00, 0x7F, 0x80, 0xFF])?;
        }
        _ => {}
    }
    Ok(())
}

/// Another node, as a gateway names it, one time in three.
fn maybe_origin(u: &mut Unstructured<'_>) -> Result<Option<Origin>> {
    Ok(if u.ratio(1u8, 3)? {
        Some(Origin {
            node: node_id(u)?,
            name: segment(u)?,
            hops: u.arbitrary()?,
            namespace: segment(u)?,
        })
    } else {
        None
    })
}
