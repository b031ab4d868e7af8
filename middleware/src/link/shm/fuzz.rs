//! Structure-aware fuzzing of the shared-memory receiving machine ([`super::rx`]): frames of
//! one to three writers, built with the real header writer (safe messages cut into fragments,
//! some inline and some through the bulk inbox, fast messages, announcements and acks), then
//! in "bent" runs dropped, duplicated, swapped, flipped, or made by a writer that restarts.
//! Reached through [`crate::fuzzing::shm_frames`]; compiled only with the `fuzzing` feature.

use std::collections::{HashMap, VecDeque};
use std::time::{Duration, Instant};

use arbitrary::{Result, Unstructured};

use super::frame::{self, Part};
use super::rx::{AckSent, Receiver, RxIo, TEST_MAX_WRITERS};
use crate::link::LinkCounters;

fn encode(kind: u8, sender: u64, session: u32, seq: u64, body: &[u8]) -> Vec<u8> {
    let h = frame::header_len(kind);
    let mut b = vec![0u8; h + body.len()];
    frame::write_header(&mut b, kind, sender, session, seq);
    b[h..].copy_from_slice(body);
    b
}

/// The inbox as queues, with answers chosen by the fuzzer for acks.
#[derive(Default)]
struct FuzzIo {
    safe: VecDeque<Vec<u8>>,
    fast: VecDeque<Vec<u8>>,
    bulk: VecDeque<Vec<u8>>,
    delivered: Vec<(u64, Vec<u8>)>,
    announced: usize,
    resets: usize,
    ack_answers: Vec<u8>,
    acks_asked: usize,
}

impl RxIo for FuzzIo {
    type Sample = Vec<u8>;

    fn take(&mut self, part: Part) -> Option<Vec<u8>> {
        match part {
            Part::Safe => self.safe.pop_front(),
            Part::Fast => self.fast.pop_front(),
            Part::Bulk => self.bulk.pop_front(),
        }
    }

    fn deliver(&mut self, from: u64, msg: &[u8]) {
        self.delivered.push((from, msg.to_vec()));
    }

    fn announce(&mut self, _from: u64, _msg: &[u8]) {
        self.announced += 1;
    }

    fn peer_reset(&mut self, _from: u64) {
        self.resets += 1;
    }

    fn acked(&mut self, _from: u64, _session: u32, seq: u64) -> bool {
        seq % 2 == 0
    }

    fn send_ack(&mut self, _from: u64, _session: u32, _seq: u64) -> AckSent {
        let pick = self
            .ack_answers
            .get(self.acks_asked % self.ack_answers.len().max(1))
            .copied()
            .unwrap_or(0);
        self.acks_asked += 1;
        match pick % 8 {
            0..=4 => AckSent::Taken,
            5 => AckSent::Refused,
            6 => AckSent::NotOpen,
            _ => AckSent::NoPeer,
        }
    }

    fn request_open(&mut self, _from: u64) {}

    fn retry_backlogs(&mut self, _acked: &[u64], _retry: bool) -> bool {
        false
    }
}

/// One writer's state while frames are generated.
struct Writer {
    id: u64,
    session: u32,
    seq: u64,
}

/// Where a frame goes.
enum Out {
    Safe(Vec<u8>),
    Fast(Vec<u8>),
    Bulk(Vec<u8>),
}

/// Runs one case. Panics when a property fails:
/// - never a panic inside the machine, whatever the frames;
/// - nothing delivered is longer than the bytes fed in;
/// - with clean frames, every writer's safe messages arrive whole, in order, exactly once, and
///   its fast messages are ones it sent.
pub(crate) fn run(data: &[u8]) -> Result<()> {
    let mut u = Unstructured::new(data);
    let u = &mut u;
    let bent = u.ratio(1u8, 3)?;
    let writers_n = u.int_in_range(1usize..=3)?;
    let mut writers = Vec::new();
    for i in 0..writers_n {
        // Sequence numbers start anywhere a writer could be, the far end of u64 included.
        let seq = match u.int_in_range(0u8..=3)? {
            0 if bent => u64::MAX - u.int_in_range(0u64..=3)?,
            1 => u.int_in_range(0u64..=u64::MAX / 2)?,
            _ => u.int_in_range(0u64..=10)?,
        };
        writers.push(Writer {
            id: 100 + i as u64,
            session: u.arbitrary()?,
            seq,
        });
    }
    let mut sent_safe: HashMap<u64, Vec<Vec<u8>>> = HashMap::new();
    let mut sent_fast: HashMap<u64, Vec<Vec<u8>>> = HashMap::new();
    let mut frames: Vec<Out> = Vec::new();
    let mut fed = 0usize;
    u.arbitrary_loop(Some(1), Some(40), |u| {
        let w = u.int_in_range(0..=writers_n - 1)?;
        let w = &mut writers[w];
        match u.int_in_range(0u8..=9)? {
            0 | 1 if u.ratio(1u8, 2)? => {
                // Whole small messages packed into one frame.
                let first = w.seq;
                let mut entries = Vec::new();
                for _ in 0..u.int_in_range(1usize..=4)? {
                    let len = u.int_in_range(0usize..=200)?;
                    let mut msg = vec![b'S'];
                    msg.extend_from_slice(u.bytes(len.min(u.len()))?);
                    frame::push_pack_entry(&mut entries, &msg);
                    w.seq = w.seq.wrapping_add(1);
                    fed += msg.len();
                    sent_safe.entry(w.id).or_default().push(msg);
                }
                frames.push(Out::Safe(encode(
                    frame::SAFE_PACK,
                    w.id,
                    w.session,
                    first,
                    &entries,
                )));
            }
            0..=5 => {
                let len = u.int_in_range(0usize..=3000)?;
                let mut msg = vec![b'S'];
                msg.extend_from_slice(u.bytes(len.min(u.len()))?);
                let pieces = u.int_in_range(1usize..=4)?;
                let step = msg.len().div_ceil(pieces).max(1);
                let chunks: Vec<&[u8]> = msg.chunks(step).collect();
                for (i, chunk) in chunks.iter().enumerate() {
                    let more = i + 1 < chunks.len();
                    let seq = w.seq;
                    w.seq = w.seq.wrapping_add(1);
                    if u.ratio(1u8, 3)? {
                        frames.push(Out::Bulk(encode(
                            frame::BULK_DATA,
                            w.id,
                            w.session,
                            seq,
                            chunk,
                        )));
                        let kind = if more { frame::BULK_MORE } else { frame::BULK };
                        frames.push(Out::Safe(encode(kind, w.id, w.session, seq, &[])));
                    } else {
                        let kind = if more { frame::SAFE_MORE } else { frame::SAFE };
                        frames.push(Out::Safe(encode(kind, w.id, w.session, seq, chunk)));
                    }
                }
                fed += msg.len();
                sent_safe.entry(w.id).or_default().push(msg);
            }
            6 | 7 => {
                let len = u.int_in_range(0usize..=200)?;
                let mut msg = vec![b'F'];
                msg.extend_from_slice(u.bytes(len.min(u.len()))?);
                fed += msg.len();
                frames.push(Out::Fast(encode(frame::FAST, w.id, 0, 0, &msg)));
                sent_fast.entry(w.id).or_default().push(msg);
            }
            8 => {
                let seq = u.arbitrary()?;
                frames.push(Out::Safe(encode(frame::ACK, w.id, w.session, seq, &[])));
            }
            _ => {
                frames.push(Out::Fast(encode(frame::ANNOUNCE, w.id, 0, 0, b"hello")));
                fed += 5;
            }
        }
        Ok(std::ops::ControlFlow::Continue(()))
    })?;
    if bent {
        // Damage applied to the generated frames, as a broken or hostile writer would.
        u.arbitrary_loop(Some(1), Some(16), |u| {
            if frames.is_empty() {
                return Ok(std::ops::ControlFlow::Break(()));
            }
            let i = u.int_in_range(0..=frames.len() - 1)?;
            match u.int_in_range(0u8..=5)? {
                0 => {
                    frames.remove(i);
                }
                1 => {
                    let copy = match &frames[i] {
                        Out::Safe(b) => Out::Safe(b.clone()),
                        Out::Fast(b) => Out::Fast(b.clone()),
                        Out::Bulk(b) => Out::Bulk(b.clone()),
                    };
                    fed += frame_len(&copy);
                    frames.insert(i, copy);
                }
                2 => {
                    let j = u.int_in_range(0..=frames.len() - 1)?;
                    frames.swap(i, j);
                }
                3 => {
                    let (Out::Safe(b) | Out::Fast(b) | Out::Bulk(b)) = &mut frames[i];
                    crate::protocol::gen::mutate(u, b)?;
                    fed += 16;
                }
                4 => {
                    // Into the wrong part of the inbox.
                    let b = match frames.remove(i) {
                        Out::Safe(b) => Out::Bulk(b),
                        Out::Fast(b) => Out::Safe(b),
                        Out::Bulk(b) => Out::Fast(b),
                    };
                    frames.insert(i, b);
                }
                _ => {
                    // Raw bytes of a frame kind with a lying header.
                    let kind = u.int_in_range(0u8..=9)?;
                    let body = crate::protocol::gen::bytes(u, 64)?;
                    fed += body.len();
                    let mut b = encode(
                        kind.clamp(1, 8),
                        u.int_in_range(99u64..=103)?,
                        u.arbitrary()?,
                        u.arbitrary()?,
                        &body,
                    );
                    b[0] = kind;
                    frames.insert(i, Out::Safe(b));
                }
            }
            Ok(std::ops::ControlFlow::Continue(()))
        })?;
    }
    let mut io = FuzzIo {
        ack_answers: u.bytes(u.len().min(8))?.to_vec(),
        ..FuzzIo::default()
    };
    let c = LinkCounters::default();
    let start = Instant::now();
    let mut rx = Receiver::new(start, TEST_MAX_WRITERS);
    let mut step = 0u32;
    for f in frames {
        match f {
            Out::Safe(b) => io.safe.push_back(b),
            Out::Fast(b) => io.fast.push_back(b),
            Out::Bulk(b) => io.bulk.push_back(b),
        }
        // Passes at random moments: sometimes after every frame, sometimes after many.
        if u.ratio(1u8, 4)? {
            step += 1;
            rx.pass(
                start + Duration::from_millis(u64::from(step)),
                false,
                &mut io,
                &c,
            );
        }
    }
    for _ in 0..64 {
        step += 1;
        let (_, more) = rx.pass(
            start + Duration::from_millis(u64::from(step)),
            true,
            &mut io,
            &c,
        );
        if !more && io.safe.is_empty() && io.fast.is_empty() {
            break;
        }
    }
    let delivered: usize = io.delivered.iter().map(|(_, m)| m.len()).sum();
    assert!(
        delivered <= fed.max(1) * 2 + 64 * io.delivered.len(),
        "shm receiver delivered {delivered} bytes from {fed} fed"
    );
    if !bent {
        for w in &writers {
            let got_safe: Vec<&Vec<u8>> = io
                .delivered
                .iter()
                .filter(|(from, m)| *from == w.id && m.first() == Some(&b'S'))
                .map(|(_, m)| m)
                .collect();
            let want: Vec<&Vec<u8>> = sent_safe
                .get(&w.id)
                .map(|v| v.iter().collect())
                .unwrap_or_default();
            assert_eq!(
                got_safe.len(),
                want.len(),
                "writer {}: safe messages delivered",
                w.id
            );
            assert!(
                got_safe == want,
                "writer {}: safe messages differ or out of order",
                w.id
            );
            let fast = sent_fast.get(&w.id);
            for (from, m) in &io.delivered {
                if *from == w.id && m.first() == Some(&b'F') {
                    assert!(
                        fast.is_some_and(|f| f.contains(m)),
                        "writer {}: a fast message it never sent",
                        w.id
                    );
                }
            }
        }
        assert_eq!(io.resets, 0, "clean frames reported a peer reset");
    }
    Ok(())
}

fn frame_len(f: &Out) -> usize {
    let (Out::Safe(b) | Out::Fast(b) | Out::Bulk(b)) = f;
    b.len()
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Found by the structured fuzzer: a safe frame with the last sequence number made the
    /// receiver compute `seq + 1` and panic. It is dropped as corrupt now, and the writer's
    /// stream goes on.
    #[test]
    fn a_frame_with_the_last_sequence_number_is_dropped_not_a_panic() {
        let mut io = FuzzIo::default();
        io.safe
            .push_back(encode(frame::SAFE, 7, 1, u64::MAX, b"last"));
        io.safe.push_back(encode(frame::SAFE, 7, 1, 0, b"fresh"));
        let c = LinkCounters::default();
        let now = Instant::now();
        let mut rx = Receiver::new(now, TEST_MAX_WRITERS);
        rx.pass(now, false, &mut io, &c);
        assert!(c.corrupt.load(std::sync::atomic::Ordering::Relaxed) >= 1);
        assert!(io.delivered.iter().all(|(_, m)| m != b"last"));
    }
}
