//! Encoding and decoding of protocol types: synchronous, no I/O, no allocation sized by
//! untrusted lengths.

pub mod varint;

use crate::protocol::{tag, Message};

/// A message that could not be decoded.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum MessageDecodeError {
    /// postcard refused the bytes (unknown tag, truncated, bad varint...).
    #[error("corrupt message: {0}")]
    Corrupt(String),
    /// The bytes decoded but some were left over.
    #[error("{0} trailing bytes after message")]
    TrailingBytes(usize),
}

/// Encodes a message with postcard.
pub fn encode_message(msg: &Message) -> Vec<u8> {
    // Serialising our own enum into a Vec cannot fail: every field type is supported by postcard
    // and the output grows as needed.
    postcard::to_stdvec(msg).expect("postcard encoding of a protocol message cannot fail")
}

/// Decodes one message, refusing trailing bytes.
///
/// # Errors
/// [`MessageDecodeError`] when the bytes are not exactly one message.
pub fn decode_message(bytes: &[u8]) -> Result<Message, MessageDecodeError> {
    let (msg, rest) = postcard::take_from_bytes::<Message>(bytes)
        .map_err(|e| MessageDecodeError::Corrupt(e.to_string()))?;
    if rest.is_empty() {
        Ok(msg)
    } else {
        Err(MessageDecodeError::TrailingBytes(rest.len()))
    }
}

/// Where the payload of a data message (`Message::Var` or `Message::Event`) lies in `msg`,
/// found without decoding or copying it: its offer id and byte range. `None` for any other
/// message, or one that does not end where its payload does.
pub(crate) fn data_message_payload(msg: &[u8]) -> Option<(u32, std::ops::Range<usize>)> {
    let (&t, mut rest) = msg.split_first()?;
    if t != tag::VAR && t != tag::EVENT {
        return None;
    }
    let id = u32::try_from(varint::take_u64(&mut rest)?).ok()?;
    let len = usize::try_from(varint::take_u64(&mut rest)?).ok()?;
    (len == rest.len()).then(|| (id, msg.len() - len..msg.len()))
}

/// Encodes a user payload.
///
/// # Errors
/// postcard's error when the type cannot be serialised (e.g. a map with non-string keys is fine,
/// but a type whose `Serialize` fails is reported).
pub fn encode_payload<T: serde::Serialize + ?Sized>(value: &T) -> Result<Vec<u8>, postcard::Error> {
    postcard::to_stdvec(value)
}

/// Decodes a user payload.
///
/// # Errors
/// postcard's error when the bytes do not hold a `T`.
pub fn decode_payload<T: serde::de::DeserializeOwned>(bytes: &[u8]) -> Result<T, postcard::Error> {
    postcard::from_bytes(bytes)
}

/// Encodes a user payload as `Message::Var` (`event` false) or `Message::Event` with offer id
/// `id`, in one buffer sized once; returns it with where the payload starts in it. The bytes
/// are postcard's for the message holding the payload (a unit test checks it).
///
/// A `Vec<u8>` payload (the common "raw bytes" case) is written as postcard writes it, a
/// length and the bytes, with one copy instead of serde's byte-by-byte sequence.
///
/// # Errors
/// postcard's error when the value cannot be serialised.
pub fn encode_data_message<T: serde::Serialize + 'static>(
    event: bool,
    id: u32,
    value: &T,
) -> Result<(Vec<u8>, usize), postcard::Error> {
    let tag = data_tag(event);
    if let Some(b) = (value as &dyn std::any::Any).downcast_ref::<Vec<u8>>() {
        return Ok(data_message_from_bytes(tag, id, b));
    }
    thread_local! {
        static SCRATCH: std::cell::RefCell<Vec<u8>> = const { std::cell::RefCell::new(Vec::new()) };
    }
    SCRATCH.with(|s| {
        let mut scratch = s.borrow_mut();
        scratch.clear();
        let r = postcard::to_extend(value, std::mem::take(&mut *scratch));
        match r {
            Ok(v) => {
                let out = data_message_with_payload(tag, id, &v);
                *scratch = v;
                // Kept for the next message, unless one huge value made it huge.
                if scratch.capacity() > 64 << 10 {
                    *scratch = Vec::new();
                }
                Ok(out)
            }
            Err(e) => Err(e),
        }
    })
}

/// `encode_data_message` of a `Vec<u8>` holding `bytes`, without the `Vec`.
pub(crate) fn encode_data_message_from_bytes(
    event: bool,
    id: u32,
    bytes: &[u8],
) -> (Vec<u8>, usize) {
    data_message_from_bytes(data_tag(event), id, bytes)
}

/// `Message::Var` (`event` false) or `Message::Event` with offer id `id` carrying the already
/// encoded `payload`, without first copying it into a `Message`; the bytes are postcard's (a
/// unit test checks it).
pub(crate) fn encode_data_message_of_payload(event: bool, id: u32, payload: &[u8]) -> Vec<u8> {
    data_message_with_payload(data_tag(event), id, payload).0
}

/// The tag of a data message.
fn data_tag(event: bool) -> u8 {
    if event {
        tag::EVENT
    } else {
        tag::VAR
    }
}

/// `encode_payload` of a `Vec<u8>` holding `bytes`, without the `Vec` (same bytes).
pub(crate) fn encode_bytes_payload(bytes: &[u8]) -> Vec<u8> {
    let mut out = Vec::with_capacity(varint::len_u64(bytes.len() as u64) + bytes.len());
    varint::put_u64(&mut out, bytes.len() as u64);
    out.extend_from_slice(bytes);
    out
}

/// A data message whose payload is the postcard encoding of the byte string `b`.
fn data_message_from_bytes(tag: u8, id: u32, b: &[u8]) -> (Vec<u8>, usize) {
    let (mut out, at) = bytes_message_header(tag, id, b.len(), b.len());
    out.extend_from_slice(b);
    (out, at)
}

/// The bytes before the `len` bytes of a byte string in a data message (`Message::Event`
/// when `event`, else `Message::Var`) of offer `id`, and where its payload starts in them:
/// a message written in place is these, then the bytes.
pub(crate) fn data_message_header_of_bytes(event: bool, id: u32, len: usize) -> (Vec<u8>, usize) {
    bytes_message_header(data_tag(event), id, len, 0)
}

/// [`data_message_header_of_bytes`] with room for `reserve` more bytes.
fn bytes_message_header(tag: u8, id: u32, len: usize, reserve: usize) -> (Vec<u8>, usize) {
    let inner = varint::len_u64(len as u64) + len;
    // Exactly the message's length (with `reserve` = `len`): a buffer without spare room
    // becomes a `Bytes` without an allocation.
    let id_len = varint::len_u64(u64::from(id));
    let mut out =
        Vec::with_capacity(1 + id_len + varint::len_u64(inner as u64) + inner - len + reserve);
    out.push(tag);
    varint::put_u64(&mut out, u64::from(id));
    varint::put_u64(&mut out, inner as u64);
    let at = out.len();
    varint::put_u64(&mut out, len as u64);
    (out, at)
}

/// A data message carrying the already encoded `payload`.
fn data_message_with_payload(tag: u8, id: u32, payload: &[u8]) -> (Vec<u8>, usize) {
    let id_len = varint::len_u64(u64::from(id));
    let mut out =
        Vec::with_capacity(1 + id_len + varint::len_u64(payload.len() as u64) + payload.len());
    out.push(tag);
    varint::put_u64(&mut out, u64::from(id));
    varint::put_u64(&mut out, payload.len() as u64);
    let at = out.len();
    out.extend_from_slice(payload);
    (out, at)
}

/// Decodes a user payload the caller owns, reusing its buffer when `T` is `Vec<u8>` (the
/// length prefix is dropped in place: no allocation, no byte-by-byte sequence).
///
/// # Errors
/// postcard's error when the bytes do not hold a `T`.
pub fn decode_payload_owned<T: serde::de::DeserializeOwned + 'static>(
    mut bytes: Vec<u8>,
) -> Result<T, postcard::Error> {
    let mut slot: Option<T> = None;
    if let Some(out) = (&mut slot as &mut dyn std::any::Any).downcast_mut::<Option<Vec<u8>>>() {
        let mut rest: &[u8] = &bytes;
        let len = varint::take_u64(&mut rest)
            .and_then(|l| usize::try_from(l).ok())
            .filter(|l| *l <= rest.len())
            .ok_or(postcard::Error::DeserializeUnexpectedEnd)?;
        // Trailing bytes are ignored, as postcard's `from_bytes` ignores them.
        let at = bytes.len() - rest.len();
        bytes.truncate(at + len);
        bytes.drain(..at);
        *out = Some(bytes);
        return Ok(slot.expect("set just above"));
    }
    postcard::from_bytes(&bytes)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::protocol::*;
    use crate::typeinfo::TypeInfo;

    /// A message without spare room becomes the `Bytes` links share without an allocation.
    #[test]
    fn a_data_message_fills_its_buffer_exactly() {
        for id in [1u32, 300, u32::MAX] {
            let (m, _) = encode_data_message(true, id, &vec![7u8; 1000]).unwrap();
            assert_eq!(m.capacity(), m.len(), "bytes, id {id}");
            let (m, _) = encode_data_message(false, id, &(1u64, "x".to_string())).unwrap();
            assert_eq!(m.capacity(), m.len(), "a value, id {id}");
        }
    }

    #[test]
    fn a_data_message_payload_is_found_in_place() {
        let payload: Vec<u8> = (0..=255u8).cycle().take(70_000).collect();
        for msg in [
            Message::Event {
                id: 300,
                payload: payload.clone(),
            },
            Message::Var {
                id: 7,
                payload: payload.clone(),
            },
        ] {
            let bytes = encode_message(&msg);
            let (id, range) = data_message_payload(&bytes).expect("a data message");
            assert_eq!(
                id,
                if matches!(msg, Message::Event { .. }) {
                    300
                } else {
                    7
                }
            );
            assert_eq!(&bytes[range], &payload[..]);
            assert_eq!(
                data_message_payload(&bytes[..bytes.len() - 1]),
                None,
                "cut short"
            );
        }
        let reply = encode_message(&Message::Reply {
            call_id: 1,
            result: Ok(vec![1, 2]),
        });
        assert_eq!(data_message_payload(&reply), None, "not data");
        assert_eq!(data_message_payload(&[]), None);
    }

    #[test]
    fn fast_data_encoding_equals_postcard() {
        for event in [false, true] {
            let payload: Vec<u8> = (0..200u8).collect();
            let msg = if event {
                Message::Event {
                    id: 300,
                    payload: payload.clone(),
                }
            } else {
                Message::Var {
                    id: 300,
                    payload: payload.clone(),
                }
            };
            assert_eq!(
                encode_data_message_of_payload(event, 300, &payload),
                encode_message(&msg)
            );
        }
    }

    fn ti() -> TypeInfo {
        TypeInfo {
            name: "T".into(),
            fingerprint: 0x0102,
        }
    }

    /// Golden bytes, field by field, for every message type.
    #[test]
    fn golden_bytes_for_every_message() {
        let cases: Vec<(Message, Vec<u8>)> = vec![
            (
                Message::Hello {
                    node_id: 1,
                    domain: "d".into(),
                    node: "n".into(),
                    namespace: "".into(),
                    counter: 3,
                    lease_ms: 300,
                    gateway: true,
                    asks_introduction: false,
                },
                // tag 0, node_id 1, "d", "n", "", counter 3, lease 300 = 0xAC 0x02, gateway,
                // asks_introduction
                vec![0, 1, 1, b'd', 1, b'n', 0, 3, 0xAC, 0x02, 1, 0],
            ),
            (
                Message::Heartbeat {
                    node_id: 2,
                    domain_hash: 5,
                    counter: 7,
                },
                vec![1, 2, 5, 7],
            ),
            (Message::DeclRequest { since: 4 }, vec![2, 4]),
            (
                Message::DeclBatch {
                    after: 0,
                    upto: 5,
                    reset: true,
                    entries: vec![
                        LoggedDeclaration {
                            counter: 1,
                            decl: Declaration::Service {
                                id: 1,
                                name: "s".into(),
                            },
                        },
                        LoggedDeclaration {
                            counter: 2,
                            decl: Declaration::Offer {
                                id: 2,
                                service: 1,
                                kind: ItemKind::Variable,
                                name: "s/v".into(),
                                ty: ti(),
                                origin: None,
                            },
                        },
                        LoggedDeclaration {
                            counter: 3,
                            decl: Declaration::Interest {
                                id: 3,
                                service: 1,
                                kind: ItemKind::Event,
                                pattern: "*".into(),
                                ty: ti(),
                            },
                        },
                        LoggedDeclaration {
                            counter: 4,
                            decl: Declaration::Withdraw { id: 2 },
                        },
                    ],
                },
                vec![
                    3, 0, 5, 1, 4, // tag, after 0, upto 5, reset, 4 entries
                    1, 0, 1, 1, b's', // counter 1, Service{1,"s"}
                    2, 1, 2, 1, 0, 3, b's', b'/', b'v', 1, b'T', 0x82, 0x02,
                    0, // Offer, no origin
                    3, 2, 3, 1, 1, 1, b'*', 1, b'T', 0x82, 0x02, // Interest
                    4, 3, 2, // Withdraw{2}
                ],
            ),
            (
                Message::Refused {
                    interest: 9,
                    name: "a".into(),
                    offered: ti(),
                },
                vec![4, 9, 1, b'a', 1, b'T', 0x82, 0x02],
            ),
            (
                Message::Var {
                    id: 5,
                    payload: vec![0xAA, 0xBB],
                },
                vec![5, 5, 2, 0xAA, 0xBB],
            ),
            (
                Message::Event {
                    id: 6,
                    payload: vec![0xCC],
                },
                vec![6, 6, 1, 0xCC],
            ),
            (
                Message::Call {
                    call_id: 1,
                    id: 2,
                    remaining_ms: 1000,
                    args: vec![7],
                    caller: None,
                },
                vec![7, 1, 2, 0xE8, 0x07, 1, 7, 0],
            ),
            (
                Message::Reply {
                    call_id: 1,
                    result: Err(RemoteFailure::Denied),
                },
                // Err, RemoteFailure variant 4
                vec![8, 1, 1, 4],
            ),
            (
                Message::Reply {
                    call_id: 1,
                    result: Ok(vec![8]),
                },
                vec![8, 1, 0, 1, 8],
            ),
            (
                Message::Reply {
                    call_id: 1,
                    result: Err(RemoteFailure::Handler("x".into())),
                },
                vec![8, 1, 1, 0, 1, b'x'],
            ),
            (
                Message::FileOffer(FileOffer {
                    transfer: 1,
                    sink: 2,
                    name: "f".into(),
                    size: 3,
                    hash: [0; 32],
                    sender: None,
                }),
                {
                    let mut v = vec![9, 1, 2, 1, b'f', 3];
                    v.extend([0u8; 32]);
                    v.push(0);
                    v
                },
            ),
            (
                Message::FileAccept {
                    transfer: 1,
                    offset: 128,
                },
                vec![10, 1, 0x80, 0x01],
            ),
            (
                Message::FileChunk {
                    transfer: 1,
                    offset: 0,
                    data: vec![1, 2],
                },
                vec![11, 1, 0, 2, 1, 2],
            ),
            (
                Message::FileDone {
                    transfer: 1,
                    verdict: FileVerdict::Stored,
                },
                vec![12, 1, 0],
            ),
            (
                Message::FileDone {
                    transfer: 1,
                    verdict: FileVerdict::Failed("h".into()),
                },
                vec![12, 1, 1, 1, b'h'],
            ),
            // tag 12, transfer 1, verdict TooLarge (2): size 5, max 3
            (
                Message::FileDone {
                    transfer: 1,
                    verdict: FileVerdict::TooLarge { size: 5, max: 3 },
                },
                vec![12, 1, 2, 5, 3],
            ),
            // verdict QuotaExceeded (3): needed 300 (varint 0xac 0x02), quota 3
            (
                Message::FileDone {
                    transfer: 1,
                    verdict: FileVerdict::QuotaExceeded {
                        needed: 300,
                        quota: 3,
                    },
                },
                vec![12, 1, 3, 0xac, 0x02, 3],
            ),
            // verdict Busy (4): max 4
            (
                Message::FileDone {
                    transfer: 1,
                    verdict: FileVerdict::Busy { max: 4 },
                },
                vec![12, 1, 4, 4],
            ),
            (
                Message::FileDone {
                    transfer: 1,
                    verdict: FileVerdict::Denied("d".into()),
                },
                vec![12, 1, 5, 1, b'd'],
            ),
            (Message::FileCancel { transfer: 3 }, vec![13, 3]),
            (Message::Bye { node_id: 4 }, vec![14, 4]),
            // Challenge (16): the 16 nonce bytes and the 32 of the key agreement half as they
            // are (fixed-size arrays)
            (
                Message::Challenge {
                    nonce: [5; 16],
                    agreement: [6; 32],
                },
                [&[16u8][..], &[5; 16], &[6; 32]].concat(),
            ),
            // Flow (17): a bool is one byte
            (
                Message::Flow {
                    behind: true,
                    readers: Some(2),
                    offers: Some(vec![3]),
                },
                // behind, readers Some (1) of 2 gateways beyond, offers Some (1) [3]
                vec![17, 1, 1, 2, 1, 1, 3],
            ),
        ];
        for (msg, bytes) in cases {
            assert_eq!(encode_message(&msg), bytes, "encoding of {msg:?}");
            assert_eq!(decode_message(&bytes).as_ref(), Ok(&msg));
        }
    }

    #[test]
    fn position_sample_is_35_bytes_as_a_message() {
        let payload = encode_payload(&(1.0f64, 2.0f64, 3.0f64, 4.0f32, 5.0f32)).unwrap();
        assert_eq!(payload.len(), 32);
        let msg = Message::Var { id: 3, payload };
        assert_eq!(encode_message(&msg).len(), 35);
    }

    #[test]
    fn trailing_and_truncated_bytes_are_errors() {
        assert_eq!(
            decode_message(&[2, 4, 0]),
            Err(MessageDecodeError::TrailingBytes(1))
        );
        assert!(matches!(
            decode_message(&[5, 5, 200]),
            Err(MessageDecodeError::Corrupt(_))
        ));
        assert!(decode_message(&[]).is_err());
        assert!(decode_message(&[200]).is_err());
    }

    use proptest::prelude::{any, prop_assert_eq};
    proptest::proptest! {
        #[test]
        fn random_bytes_never_panic(bytes in proptest::collection::vec(proptest::num::u8::ANY, 0..300)) {
            let _ = decode_message(&bytes);
        }

        /// The one-copy encoding of data messages is postcard's, for raw bytes and for other
        /// payload types, and the owned decoding gives the value back.
        #[test]
        fn data_messages_are_postcards_and_decode_back(
            bytes in proptest::collection::vec(proptest::num::u8::ANY, 0..2000),
            id in any::<u32>(),
            event in any::<bool>(),
            words in proptest::collection::vec(any::<u64>(), 0..50),
        ) {
            let (msg, at) = encode_data_message(event, id, &bytes).unwrap();
            let payload = encode_payload(&bytes).unwrap();
            let expected = if event {
                Message::Event { id, payload: payload.clone() }
            } else {
                Message::Var { id, payload: payload.clone() }
            };
            prop_assert_eq!(&msg, &encode_message(&expected));
            prop_assert_eq!(&msg[at..], &payload[..]);
            prop_assert_eq!(decode_payload_owned::<Vec<u8>>(payload).unwrap(), bytes);

            let (msg, at) = encode_data_message(event, id, &words).unwrap();
            let payload = encode_payload(&words).unwrap();
            let expected = Message::Event { id, payload: payload.clone() };
            if event {
                prop_assert_eq!(&msg, &encode_message(&expected));
            }
            prop_assert_eq!(&msg[at..], &payload[..]);
            prop_assert_eq!(decode_payload_owned::<Vec<u64>>(payload).unwrap(), words);
        }

        /// Truncated or garbage raw-byte payloads are refused, never a panic.
        #[test]
        fn raw_byte_payloads_decode_or_fail_like_postcard(
            bytes in proptest::collection::vec(proptest::num::u8::ANY, 0..40),
        ) {
            let ours = decode_payload_owned::<Vec<u8>>(bytes.clone()).ok();
            let theirs = decode_payload::<Vec<u8>>(&bytes).ok();
            prop_assert_eq!(ours, theirs);
        }
    }
}
