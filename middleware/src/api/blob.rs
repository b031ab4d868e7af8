//! [`Blob`]: bytes that may stay where they arrived. A camera frame published as an
//! `Event<Blob>` or `Variable<Blob>` reaches a subscriber on the same host as a view of the
//! shared memory it crossed in (no copy), and anywhere else as an ordinary buffer; publishers
//! fill one in place with [`crate::Event::loan`].

use std::fmt;
use std::ops::Deref;

use bytes::Bytes;

use super::publisher::Publisher;
use crate::node::data::PublishError;
use crate::node::loans::MessageLoan;

/// An immutable byte buffer, cheap to clone (a reference count), that a subscriber may receive
/// without a copy: through a shared-memory link, a large [`Blob`] is a view of the sample it
/// arrived in, released to its writer when the last clone is dropped.
///
/// On the wire a `Blob` is postcard's byte string (a length, then the bytes). Publishers and
/// subscribers of one item must both use `Blob` (the type name is part of the match). A `Blob`
/// field of a larger payload (a frame's pixels beside its header) is a view of the message too,
/// and keeps the whole message's buffer alive while it lives.
///
/// Hold few received blobs at once: a subscriber's node lends at most `LENT_SAMPLES` (4)
/// samples per shared-memory link to the application; past that it copies (the writers would
/// otherwise run out of shared memory).
#[derive(Clone, Default)]
pub struct Blob {
    bytes: Bytes,
    /// A view of a shared-memory sample lent by a link.
    lent: bool,
}

impl Blob {
    /// An empty blob.
    pub fn new() -> Self {
        Blob::default()
    }

    /// A blob of a copy of `bytes`.
    pub fn copy_from_slice(bytes: &[u8]) -> Self {
        Blob::from(Bytes::copy_from_slice(bytes))
    }

    /// Whether these bytes are a view of shared memory they arrived in (not a copy).
    pub fn is_shared_memory(&self) -> bool {
        self.lent
    }

    /// The bytes as a [`Bytes`] (no copy).
    pub fn into_bytes(self) -> Bytes {
        self.bytes
    }

    /// `bytes`, which are a lent shared-memory sample's when `lent`.
    pub(crate) fn from_payload(bytes: Bytes, lent: bool) -> Self {
        Blob { bytes, lent }
    }
}

/// A value's bytes being written in place: an event's ([`crate::EventLoan`], from
/// [`crate::Event::loan`]) or a variable's ([`crate::VariableLoan`], from
/// [`crate::Variable::loan`]). Raised or set by its handle's method; dropped without being
/// sent otherwise. What was not written when it is sent goes as zeros.
pub struct BlobLoan<'a, H> {
    pub(super) handle: &'a H,
    pub(super) loan: MessageLoan,
    /// Where the value's payload starts in the message.
    pub(super) at: usize,
    /// Where the bytes start in the message.
    start: usize,
}

impl<'a, H> BlobLoan<'a, H> {
    /// A buffer for a value of `len` bytes of `publisher` (an event's when `event`), lent by
    /// the link of its only subscriber when that link lends one.
    pub(super) fn new(
        handle: &'a H,
        publisher: &Publisher,
        event: bool,
        len: usize,
    ) -> Result<Self, PublishError> {
        let offer = &publisher.offer;
        PublishError::check_size(&offer.name, len)?;
        let (header, at) = crate::codec::data_message_header_of_bytes(event, offer.id, len);
        let routes = offer.remote.get();
        let mut loan = publisher.node.loan(&routes, header.len() + len);
        loan.buf.append(&header);
        Ok(BlobLoan {
            handle,
            loan,
            at,
            start: header.len(),
        })
    }

    /// The value's length in bytes.
    pub fn len(&self) -> usize {
        self.loan.buf.len() - self.start
    }

    /// Whether the value is empty.
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// Bytes written from the start so far.
    pub fn written(&self) -> usize {
        self.loan.buf.written() - self.start
    }

    /// Writes as much of `bytes` as fits after what was written (each byte once); returns
    /// how much.
    pub fn append(&mut self, bytes: &[u8]) -> usize {
        self.loan.buf.append(bytes)
    }

    /// The whole value's bytes, to write anywhere in them; the first call zeroes those not
    /// written yet.
    pub fn as_mut_slice(&mut self) -> &mut [u8] {
        let start = self.start;
        &mut self.loan.buf.init()[start..]
    }

    /// Whether the bytes are being written into the subscriber's shared memory.
    pub fn is_shared_memory(&self) -> bool {
        self.loan.is_lent()
    }
}

impl<H> std::io::Write for BlobLoan<'_, H> {
    /// Appends (see [`BlobLoan::append`]); a full buffer takes nothing (`write_all` then fails
    /// with [`std::io::ErrorKind::WriteZero`]).
    fn write(&mut self, buf: &[u8]) -> std::io::Result<usize> {
        Ok(self.append(buf))
    }

    fn flush(&mut self) -> std::io::Result<()> {
        Ok(())
    }
}

impl Deref for Blob {
    type Target = [u8];
    fn deref(&self) -> &[u8] {
        &self.bytes
    }
}

impl AsRef<[u8]> for Blob {
    fn as_ref(&self) -> &[u8] {
        &self.bytes
    }
}

impl From<Vec<u8>> for Blob {
    fn from(v: Vec<u8>) -> Self {
        Blob::from(Bytes::from(v))
    }
}

impl From<Bytes> for Blob {
    fn from(bytes: Bytes) -> Self {
        Blob { bytes, lent: false }
    }
}

impl PartialEq for Blob {
    /// Equal bytes (wherever they are).
    fn eq(&self, other: &Self) -> bool {
        self.bytes == other.bytes
    }
}

impl Eq for Blob {}

impl fmt::Debug for Blob {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.debug_struct("Blob")
            .field("len", &self.bytes.len())
            .field("shared_memory", &self.is_shared_memory())
            .finish()
    }
}

impl serde::Serialize for Blob {
    fn serialize<S: serde::Serializer>(&self, s: S) -> Result<S::Ok, S::Error> {
        s.serialize_bytes(&self.bytes)
    }
}

impl<'de> serde::Deserialize<'de> for Blob {
    fn deserialize<D: serde::Deserializer<'de>>(d: D) -> Result<Self, D::Error> {
        struct V;
        impl serde::de::Visitor<'_> for V {
            type Value = Blob;
            fn expecting(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
                f.write_str("a byte string")
            }
            /// A slice of the message being decoded (see [`decode_payload`]) is kept as a
            /// view of it; anything else is copied.
            fn visit_bytes<E: serde::de::Error>(self, v: &[u8]) -> Result<Blob, E> {
                Ok(SOURCE.with(|source| match &*source.borrow() {
                    Some((bytes, lent)) if within(bytes, v) => {
                        Blob::from_payload(bytes.slice_ref(v), *lent)
                    }
                    _ => Blob::copy_from_slice(v),
                }))
            }
            fn visit_byte_buf<E: serde::de::Error>(self, v: Vec<u8>) -> Result<Blob, E> {
                Ok(Blob::from(v))
            }
        }
        d.deserialize_byte_buf(V)
    }
}

thread_local! {
    /// The message a payload is being decoded from, and whether it is lent shared memory: a
    /// [`Blob`] inside the payload (a field of a struct) becomes a slice of it, not a copy.
    static SOURCE: std::cell::RefCell<Option<(Bytes, bool)>> =
        const { std::cell::RefCell::new(None) };
}

/// Whether `part` lies inside `whole`'s bytes.
fn within(whole: &Bytes, part: &[u8]) -> bool {
    let range = whole.as_ptr_range();
    let p = part.as_ptr_range();
    range.start <= p.start && p.end <= range.end
}

/// Decodes a user payload held in `bytes` (a slice of the message it arrived in): a
/// [`Blob`] is that slice, without a copy (a view of shared memory when `lent`), and so is any
/// `Blob` inside another type (a frame's pixels beside its header); a `Vec<u8>` as
/// [`crate::codec::decode_payload_owned`] makes it.
///
/// # Errors
/// postcard's error when the bytes do not hold a `T`.
pub(crate) fn decode_payload<T: serde::de::DeserializeOwned + 'static>(
    bytes: bytes::Bytes,
    lent: bool,
) -> Result<T, postcard::Error> {
    let mut slot: Option<T> = None;
    if let Some(out) = (&mut slot as &mut dyn std::any::Any).downcast_mut::<Option<Blob>>() {
        let mut rest: &[u8] = &bytes;
        let len = crate::codec::varint::take_u64(&mut rest)
            .and_then(|l| usize::try_from(l).ok())
            .filter(|l| *l <= rest.len())
            .ok_or(postcard::Error::DeserializeUnexpectedEnd)?;
        let at = bytes.len() - rest.len();
        *out = Some(Blob::from_payload(bytes.slice(at..at + len), lent));
        return Ok(slot.expect("set just above"));
    }
    if std::any::TypeId::of::<T>() == std::any::TypeId::of::<Vec<u8>>() {
        return crate::codec::decode_payload_owned(Vec::from(bytes));
    }
    // The payload moves into the source for this decode alone (no clone: a first clone of
    // a buffer made from a Vec allocates) and the source is emptied after it, even if a
    // `Deserialize` panics (a lent sample left there would stay held).
    struct Emptied;
    impl Drop for Emptied {
        fn drop(&mut self) {
            SOURCE.with(|s| s.take());
        }
    }
    SOURCE.with(|s| s.replace(Some((bytes, lent))));
    let _emptied = Emptied;
    SOURCE.with(|s| match &*s.borrow() {
        Some((bytes, _)) => postcard::from_bytes(bytes),
        None => Err(postcard::Error::DeserializeUnexpectedEnd),
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A `Blob` field is a view of the payload it was decoded from, never of a buffer it
    /// was not (a plain `postcard::from_bytes` copies).
    #[test]
    fn a_blob_inside_a_struct_is_a_slice_of_the_payload() {
        #[derive(serde::Serialize, serde::Deserialize)]
        struct Frame {
            seq: u64,
            pixels: Blob,
        }
        let sent = Frame {
            seq: 7,
            pixels: Blob::from(vec![9u8; 1000]),
        };
        let payload = Bytes::from(postcard::to_allocvec(&sent).unwrap());
        let got: Frame = decode_payload(payload.clone(), true).unwrap();
        assert_eq!(got.seq, 7);
        assert_eq!(&*got.pixels, &[9u8; 1000][..]);
        assert!(within(&payload, &got.pixels), "a view of the payload");
        assert!(got.pixels.is_shared_memory(), "lent as its payload was");
        let copied: Frame = postcard::from_bytes(&payload).unwrap();
        assert!(!within(&payload, &copied.pixels) && !copied.pixels.is_shared_memory());
        SOURCE.with(|s| assert!(s.borrow().is_none(), "the source is put back"));
    }

    #[test]
    fn a_blob_encodes_as_postcard_encodes_its_bytes() {
        let b = Blob::from(vec![1u8, 2, 3]);
        let enc = postcard::to_allocvec(&b).unwrap();
        assert_eq!(enc, postcard::to_allocvec(&vec![1u8, 2, 3]).unwrap());
        let back: Blob = postcard::from_bytes(&enc).unwrap();
        assert_eq!(&*back, &[1, 2, 3]);
        assert!(!back.is_shared_memory());
    }
}
