//! Fragmentation by `MaxPacketSize` (003 §5.4.1), batching of small messages into one frame, and
//! the two reassemblers: Safe fragments arrive in order (the ARQ sees to it), Fast fragments
//! share a sequence number and may arrive partly, so incomplete sets expire.
//!
//! Pure and bounded: nothing is allocated beyond the bytes actually received, and a message
//! never grows past `255 × MaxPacketSize`.

use std::collections::VecDeque;
use std::time::{Duration, Instant};

use crate::codec::varint::{len_u64, put_u64, take_u64};

/// Most fragments of one message (the fragment total is one byte).
pub const MAX_FRAGMENTS: usize = 255;

/// Why a message cannot be fragmented.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum FragmentError {
    /// More than 255 fragments would be needed.
    #[error("message of {len} bytes needs more than 255 fragments of {max} bytes")]
    TooLarge {
        /// Message length.
        len: usize,
        /// Fragment size.
        max: usize,
    },
}

/// Splits `msg` into pieces of at most `max` bytes (at least one piece, maybe empty).
///
/// # Errors
/// [`FragmentError::TooLarge`] beyond 255 pieces.
pub fn split(msg: &[u8], max: usize) -> Result<Vec<&[u8]>, FragmentError> {
    let max = max.max(1);
    if msg.is_empty() {
        return Ok(vec![msg]);
    }
    let n = msg.len().div_ceil(max);
    if n > MAX_FRAGMENTS {
        return Err(FragmentError::TooLarge {
            len: msg.len(),
            max,
        });
    }
    Ok(msg.chunks(max).collect())
}

/// Bytes a message takes inside a batch.
pub fn batch_cost(len: usize) -> usize {
    len_u64(len as u64) + len
}

/// Appends one message to a batch.
pub fn batch_push(batch: &mut Vec<u8>, msg: &[u8]) {
    put_u64(batch, msg.len() as u64);
    batch.extend_from_slice(msg);
}

/// A batch that is not a sequence of `len | message`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, thiserror::Error)]
#[error("malformed batch")]
pub struct BatchDecodeError;

/// Splits a batch into its messages (borrowed).
///
/// # Errors
/// [`BatchDecodeError`] when a length runs past the end.
pub fn unbatch(mut data: &[u8]) -> Result<Vec<&[u8]>, BatchDecodeError> {
    let mut out = Vec::new();
    while !data.is_empty() {
        let len = take_u64(&mut data).ok_or(BatchDecodeError)?;
        let len = usize::try_from(len).map_err(|_| BatchDecodeError)?;
        if len > data.len() {
            return Err(BatchDecodeError);
        }
        let (m, rest) = data.split_at(len);
        out.push(m);
        data = rest;
    }
    Ok(out)
}

/// Why received fragments were dropped.
#[derive(Debug, Clone, Copy, PartialEq, Eq, thiserror::Error)]
pub enum ReassemblyError {
    /// A fragment out of the expected order or with another total (the set is dropped).
    #[error("fragment {frag} of {total} does not continue the message")]
    OutOfOrder {
        /// Index.
        frag: u8,
        /// Count.
        total: u8,
    },
    /// The message grew past the limit.
    #[error("reassembled message too large")]
    TooLarge,
}

/// Reassembles in-order Safe fragments.
#[derive(Debug)]
pub struct SafeReassembler {
    buf: Vec<u8>,
    next: u8,
    total: u8,
    max: usize,
}

impl SafeReassembler {
    /// A reassembler for messages up to `max` bytes.
    pub fn new(max: usize) -> Self {
        SafeReassembler {
            buf: Vec::new(),
            next: 0,
            total: 0,
            max,
        }
    }

    /// Takes the data of one Safe frame in delivery order; returns a whole message if this
    /// fragment completes one (`total == 1` messages come back at once).
    ///
    /// # Errors
    /// [`ReassemblyError`]: the partial message is dropped.
    pub fn push(
        &mut self,
        frag: u8,
        total: u8,
        data: &[u8],
    ) -> Result<Option<Vec<u8>>, ReassemblyError> {
        if frag == 0 {
            if self.total != 0 {
                // A new message started while one was unfinished: cannot happen over an
                // in-order channel unless the peer reset; start over.
                self.reset();
            }
            if total == 1 {
                return Ok(Some(data.to_vec()));
            }
            self.total = total;
        } else if frag != self.next || total != self.total {
            self.reset();
            return Err(ReassemblyError::OutOfOrder { frag, total });
        }
        if self.buf.len() + data.len() > self.max {
            self.reset();
            return Err(ReassemblyError::TooLarge);
        }
        self.buf.extend_from_slice(data);
        self.next = frag + 1;
        if self.next == self.total {
            let m = std::mem::take(&mut self.buf);
            self.reset();
            return Ok(Some(m));
        }
        Ok(None)
    }

    /// Drops any partial message.
    pub fn reset(&mut self) {
        self.buf = Vec::new();
        self.next = 0;
        self.total = 0;
    }
}

#[derive(Debug)]
struct PartialSet {
    seq: u16,
    total: u8,
    parts: Vec<Option<Vec<u8>>>,
    have: usize,
    bytes: usize,
    started: Instant,
}

/// Reassembles Fast fragments sharing a sequence number; incomplete sets expire.
#[derive(Debug)]
pub struct FastReassembler {
    sets: VecDeque<PartialSet>,
    max_sets: usize,
    expiry: Duration,
    max: usize,
    expired: u64,
}

impl FastReassembler {
    /// Keeps at most `max_sets` incomplete messages of at most `max` bytes, each for at most
    /// `expiry`.
    pub fn new(max_sets: usize, expiry: Duration, max: usize) -> Self {
        FastReassembler {
            sets: VecDeque::new(),
            max_sets: max_sets.max(1),
            expiry,
            max,
            expired: 0,
        }
    }

    /// Incomplete sets dropped so far (expired, evicted or inconsistent).
    pub fn expired(&self) -> u64 {
        self.expired
    }

    /// Takes one Fast fragment (`total >= 1`); returns the message when complete.
    pub fn push(
        &mut self,
        now: Instant,
        seq: u16,
        frag: u8,
        total: u8,
        data: &[u8],
    ) -> Option<Vec<u8>> {
        self.expire(now);
        if total <= 1 {
            return Some(data.to_vec());
        }
        let idx = match self.sets.iter().position(|s| s.seq == seq) {
            Some(i) if self.sets[i].total == total => i,
            Some(i) => {
                self.sets.remove(i);
                self.expired += 1;
                return None;
            }
            None => {
                if self.sets.len() >= self.max_sets {
                    self.sets.pop_front();
                    self.expired += 1;
                }
                self.sets.push_back(PartialSet {
                    seq,
                    total,
                    parts: vec![None; usize::from(total)],
                    have: 0,
                    bytes: 0,
                    started: now,
                });
                self.sets.len() - 1
            }
        };
        let set = &mut self.sets[idx];
        let slot = set.parts.get_mut(usize::from(frag))?;
        if slot.is_some() {
            return None;
        }
        if set.bytes + data.len() > self.max {
            self.sets.remove(idx);
            self.expired += 1;
            return None;
        }
        *slot = Some(data.to_vec());
        set.have += 1;
        set.bytes += data.len();
        if set.have < usize::from(set.total) {
            return None;
        }
        let set = self.sets.remove(idx)?;
        let mut m = Vec::with_capacity(set.bytes);
        for p in set.parts.into_iter().flatten() {
            m.extend_from_slice(&p);
        }
        Some(m)
    }

    /// Drops sets older than the expiry.
    pub fn expire(&mut self, now: Instant) {
        let before = self.sets.len();
        self.sets
            .retain(|s| now.saturating_duration_since(s.started) < self.expiry);
        self.expired += (before - self.sets.len()) as u64;
    }

    /// When the oldest incomplete set expires.
    pub fn next_expiry(&self) -> Option<Instant> {
        self.sets.iter().map(|s| s.started + self.expiry).min()
    }

    /// Incomplete sets held.
    pub fn pending(&self) -> usize {
        self.sets.len()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    #[test]
    fn split_respects_size_and_limit() {
        let m = vec![1u8; 1000];
        let parts = split(&m, 300).unwrap();
        assert_eq!(
            parts.iter().map(|p| p.len()).collect::<Vec<_>>(),
            vec![300, 300, 300, 100]
        );
        assert_eq!(split(&[], 300).unwrap().len(), 1);
        assert!(split(&vec![0; 256], 1).is_err());
        assert_eq!(split(&vec![0; 255], 1).unwrap().len(), 255);
    }

    #[test]
    fn batch_round_trip_and_malformed() {
        let mut b = Vec::new();
        batch_push(&mut b, b"abc");
        batch_push(&mut b, b"");
        batch_push(&mut b, &[9; 200]);
        assert_eq!(b.len(), batch_cost(3) + batch_cost(0) + batch_cost(200));
        let got = unbatch(&b).unwrap();
        assert_eq!(got, vec![&b"abc"[..], &b""[..], &[9u8; 200][..]]);
        assert_eq!(unbatch(&[5, 1, 2]), Err(BatchDecodeError));
        assert_eq!(unbatch(&[0xFF; 12]), Err(BatchDecodeError));
    }

    #[test]
    fn safe_reassembly_in_order_and_errors() {
        let mut r = SafeReassembler::new(100);
        assert_eq!(r.push(0, 1, b"x"), Ok(Some(b"x".to_vec())));
        assert_eq!(r.push(0, 3, b"ab"), Ok(None));
        assert_eq!(r.push(1, 3, b"cd"), Ok(None));
        assert_eq!(r.push(2, 3, b"e"), Ok(Some(b"abcde".to_vec())));
        assert_eq!(r.push(0, 2, b"ab"), Ok(None));
        assert!(r.push(1, 3, b"x").is_err());
        assert_eq!(r.push(0, 2, &[0; 60]), Ok(None));
        assert_eq!(r.push(1, 2, &[0; 60]), Err(ReassemblyError::TooLarge));
    }

    #[test]
    fn fast_sets_complete_in_any_order_and_expire() {
        let t0 = Instant::now();
        let mut r = FastReassembler::new(2, Duration::from_millis(100), 1000);
        assert_eq!(r.push(t0, 7, 1, 2, b"cd"), None);
        assert_eq!(r.push(t0, 7, 0, 2, b"ab"), Some(b"abcd".to_vec()));
        assert_eq!(r.push(t0, 8, 0, 2, b"ab"), None);
        assert_eq!(r.next_expiry(), Some(t0 + Duration::from_millis(100)));
        r.expire(t0 + Duration::from_millis(100));
        assert_eq!(r.pending(), 0);
        assert_eq!(r.expired(), 1);
        // Late fragment of the expired set does not complete anything.
        assert_eq!(
            r.push(t0 + Duration::from_millis(101), 8, 1, 2, b"cd"),
            None
        );
        // Eviction when too many sets are open.
        let t1 = t0 + Duration::from_millis(200);
        r.push(t1, 1, 0, 3, b"a");
        r.push(t1, 2, 0, 3, b"a");
        r.push(t1, 3, 0, 3, b"a");
        assert_eq!(r.pending(), 2);
    }

    proptest! {
        #[test]
        fn fast_reassembler_is_bounded_for_any_input(
            frags in proptest::collection::vec((any::<u16>(), any::<u8>(), any::<u8>(), proptest::collection::vec(any::<u8>(), 0..64)), 0..300)) {
            let t0 = Instant::now();
            let mut r = FastReassembler::new(4, Duration::from_millis(50), 256);
            for (i, (seq, frag, total, data)) in frags.into_iter().enumerate() {
                let seq = seq % 8;
                if total != 0 && frag >= total { continue; }
                let now = t0 + Duration::from_millis(i as u64);
                if let Some(m) = r.push(now, seq, frag, total, &data) {
                    prop_assert!(m.len() <= 256 || total <= 1);
                }
                prop_assert!(r.pending() <= 4);
            }
        }

        #[test]
        fn unbatch_never_panics(bytes in proptest::collection::vec(any::<u8>(), 0..500)) {
            let _ = unbatch(&bytes);
        }

        #[test]
        fn safe_reassembler_never_exceeds_its_limit(
            frags in proptest::collection::vec((any::<u8>(), any::<u8>(), proptest::collection::vec(any::<u8>(), 0..64)), 0..300)) {
            let mut r = SafeReassembler::new(200);
            for (frag, total, data) in frags {
                if total == 0 || frag >= total { continue; }
                if let Ok(Some(m)) = r.push(frag, total, &data) {
                    prop_assert!(m.len() <= 200 || total == 1);
                }
                prop_assert!(r.buf.len() <= 200);
            }
        }
    }
}
