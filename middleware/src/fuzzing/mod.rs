//! Structure-aware fuzzing harnesses (feature `fuzzing`, off by default).
//!
//! Random bytes almost never form a valid message, so a byte-level fuzzer never gets past the
//! first decoder. Each harness here turns its input into VALID-shaped traffic with
//! [`arbitrary::Unstructured`] (names and patterns as services use them, whole messages, frames
//! built by the real encoders), then bends part of it (cut, flipped, duplicated, reordered,
//! split) and feeds it to the real machine, checking properties that must hold for any input.
//! A harness panics when a property fails; that is what the fuzzer reports.
//!
//! The same functions run from `fuzz/` (cargo-fuzz, nightly) and, on stable, from
//! `middleware/tests/structured_fuzz.rs` over a bounded number of seeded inputs.
//!
//! | harness | feeds | checks |
//! |---|---|---|
//! | [`message`] | any [`Message`], encoded, then bent | round trip; a bent encoding decodes to a message no longer than itself |
//! | [`decl_batch`] | declaration batches (offers with and without origin, interests with `*`/`**`) | round trip; the pattern matcher agrees with a quadratic reference, within the name caps |
//! | [`udp_datagrams`] | datagrams from [`DatagramWriter`], dropped/duplicated/reordered/cut/flipped, into the decoder and the ARQ receiver | writer → decoder round trip; safe messages arrive as a prefix of those sent, in order, exactly once |
//! | [`stp_frames`] | two serial engines over a line that drops, duplicates, reorders, splits, joins and corrupts frames | safe messages in order exactly once and all of them once the line heals; nothing longer than the message limit |
//! | [`node_decls`] | Hellos, heartbeats, declaration batches (own names, foreign names, origins, floods past the caps) and Byes of four peers into a node | declarations per peer and in all within the caps; stored offers owned by their peer (or from a gateway with an origin); stored patterns valid |
//! | `shm_frames` (with the `shm` feature) | shared-memory frames of up to three writers (inline and bulk fragments) | safe messages whole and in order per writer; nothing invented |
//! | [`file_chunks`] | a file's chunks (resumed or not) over a line that drops, duplicates, reorders, goes back to the last acknowledgement, and forges chunks (any offset and length, empty, wrong bytes) into the receiver's reassembly machine | what is written is contiguous and never past the announced size; genuine chunks only ⇒ the original bytes; acknowledgements rise, never pass what is written, come at least every 16 chunks and at the end; once the line heals the file completes |

pub use crate::protocol::gen;

use std::collections::VecDeque;
use std::time::{Duration, Instant};

use arbitrary::{Result, Unstructured};

use crate::codec::{decode_message, encode_message};
use crate::link::arq::ArqReceiver;
use crate::link::datagram::{self, Datagram, DatagramWriter, Entry};
use crate::link::serial::stp::{Stp, StpConfig, StpEvent};
use crate::name;
use crate::protocol::{Declaration, Message};

pub use arbitrary;

/// Encodes `msg`, checks it decodes back, then bends the bytes and checks the decoder's answer.
fn check_codec(u: &mut Unstructured<'_>, msg: &Message) -> Result<()> {
    let bytes = encode_message(msg);
    match decode_message(&bytes) {
        Ok(back) => assert_eq!(&back, msg, "message did not round-trip"),
        Err(e) => panic!("an encoded message did not decode: {e}: {msg:?}"),
    }
    let mut bent = bytes;
    gen::mutate(u, &mut bent)?;
    if let Ok(m) = decode_message(&bent) {
        // Whatever decodes is no larger than the bytes it came from (no amplification), and
        // is itself a message that round-trips.
        let again = encode_message(&m);
        assert!(
            again.len() <= bent.len(),
            "{} bytes decoded into a message of {} bytes",
            bent.len(),
            again.len()
        );
        assert_eq!(decode_message(&again).as_ref(), Ok(&m));
    }
    Ok(())
}

/// Any message: encode, decode, bend.
pub fn message(data: &[u8]) {
    let mut u = Unstructured::new(data);
    let _ = (|| -> Result<()> {
        let msg = gen::message(&mut u)?;
        check_codec(&mut u, &msg)
    })();
}

/// The matcher answer computed the slow, obviously right way: a table over (pattern segments ×
/// name segments).
pub fn reference_match(pattern: &str, name: &str) -> bool {
    let p: Vec<&str> = pattern.split('/').collect();
    let n: Vec<&str> = name.split('/').collect();
    // ok[j] = p[i..] matches n[j..], for i going down.
    let mut ok = vec![false; n.len() + 1];
    ok[n.len()] = true;
    for seg in p.iter().rev() {
        let mut next = vec![false; n.len() + 1];
        for j in (0..=n.len()).rev() {
            next[j] = match *seg {
                "**" => ok[j] || (j < n.len() && next[j + 1]),
                s => j < n.len() && (s == "*" || s == n[j]) && ok[j + 1],
            };
        }
        ok = next;
    }
    ok[0]
}

/// A declaration batch: round trip, and every interest's pattern against every offered name
/// (and a few more names) answers as the reference does; a pattern the validator accepts is
/// within [`name::MAX_NAME_LEN`].
pub fn decl_batch(data: &[u8]) {
    let mut u = Unstructured::new(data);
    let _ = (|| -> Result<()> {
        let batch = gen::decl_batch(&mut u)?;
        check_codec(&mut u, &batch)?;
        let Message::DeclBatch { entries, .. } = &batch else {
            unreachable!("gen::decl_batch makes a DeclBatch")
        };
        let mut names = vec![gen::name(&mut u)?, gen::name(&mut u)?];
        let mut patterns = Vec::new();
        for e in entries {
            match &e.decl {
                Declaration::Offer { name, .. } => names.push(name.clone()),
                Declaration::Interest { pattern, .. } => patterns.push(pattern.clone()),
                Declaration::Service { .. } | Declaration::Withdraw { .. } => {}
            }
        }
        for p in &patterns {
            if name::validate_pattern(p).is_ok() {
                assert!(p.len() <= name::MAX_NAME_LEN);
            }
            for n in &names {
                assert_eq!(
                    name::matches(p, n),
                    reference_match(p, n),
                    "matcher disagrees: {p:?} ~ {n:?}"
                );
            }
        }
        Ok(())
    })();
}

/// What the sender put into one datagram (to compare with what the decoder reads).
#[derive(Debug, PartialEq, Eq)]
enum Sent {
    Fast(Vec<u8>),
    Safe(u32, Vec<u8>),
    Syn(u32),
    Ack(u32, u32, u64),
    Unknown(u32),
}

fn owned(e: &Entry<'_>) -> Sent {
    match *e {
        Entry::Fast(m) => Sent::Fast(m.to_vec()),
        Entry::Safe { seq, msg } => Sent::Safe(seq, msg.to_vec()),
        Entry::Syn(s) => Sent::Syn(s),
        Entry::Ack(a) => Sent::Ack(a.session, a.next, a.sack),
        Entry::Unknown(seq) => Sent::Unknown(seq),
    }
}

/// A sequence of UDP datagrams of one sender session, built by [`DatagramWriter`], through a
/// network that drops, duplicates, reorders, cuts and (in bent runs) flips bytes, into the
/// decoder and an [`ArqReceiver`].
pub fn udp_datagrams(data: &[u8]) {
    let mut u = Unstructured::new(data);
    let _ = udp_case(&mut u);
}

fn udp_case(u: &mut Unstructured<'_>) -> Result<()> {
    let session: u32 = u.arbitrary()?;
    let max = u.int_in_range(48usize..=1500)?;
    let window = u.int_in_range(1u32..=64)?;
    let n_safe = u.int_in_range(0usize..=40)?;
    let mut safe: Vec<Vec<u8>> = Vec::with_capacity(n_safe);
    for i in 0..n_safe {
        let mut m = (i as u32).to_le_bytes().to_vec();
        m.extend(gen::bytes(u, 300)?);
        safe.push(m);
    }
    // The sender's datagrams: a SYN first (and again later), safe messages in order and
    // retransmitted, fast messages and acks between them.
    let mut datagrams: Vec<Vec<u8>> = Vec::new();
    let mut w = DatagramWriter::new(max);
    let mut written: Vec<Sent> = Vec::new();
    let mut next_safe = 0usize;
    let flush = |w: &mut DatagramWriter, written: &mut Vec<Sent>, out: &mut Vec<Vec<u8>>| {
        if w.is_empty() {
            return;
        }
        let d = w.take();
        match datagram::decode(&d) {
            Ok(Datagram::Data(entries)) => {
                let got: Vec<Sent> = entries.iter().map(owned).collect();
                assert_eq!(&got, written, "datagram writer → decoder round trip");
            }
            other => panic!("a written datagram decoded as {other:?}"),
        }
        written.clear();
        out.push(d);
    };
    w.push_syn(session);
    written.push(Sent::Syn(session));
    u.arbitrary_loop(Some(0), Some(120), |u| {
        let pushed = match u.int_in_range(0u8..=10)? {
            0..=4 if next_safe < safe.len() => {
                let (seq, m) = (next_safe as u32, &safe[next_safe]);
                let ok = w.push_safe(seq, m);
                if ok {
                    written.push(Sent::Safe(seq, m.clone()));
                    next_safe += 1;
                }
                ok
            }
            5 if next_safe > 0 => {
                // A retransmission of something already sent.
                let seq = u.int_in_range(0..=next_safe - 1)?;
                let ok = w.push_safe(seq as u32, &safe[seq]);
                if ok {
                    written.push(Sent::Safe(seq as u32, safe[seq].clone()));
                }
                ok
            }
            6 => {
                let m = gen::bytes(u, 200)?;
                let ok = w.push_fast(&m);
                if ok {
                    written.push(Sent::Fast(m));
                }
                ok
            }
            7 => {
                let a = crate::link::arq::AckInfo {
                    session: u.arbitrary()?,
                    next: u.arbitrary()?,
                    sack: u.arbitrary()?,
                };
                let ok = w.push_ack(a);
                if ok {
                    written.push(Sent::Ack(a.session, a.next, a.sack));
                }
                ok
            }
            8 => {
                let ok = w.push_syn(session);
                if ok {
                    written.push(Sent::Syn(session));
                }
                ok
            }
            9 => {
                let seq = u.arbitrary()?;
                let ok = w.push_unknown(seq);
                if ok {
                    written.push(Sent::Unknown(seq));
                }
                ok
            }
            _ => {
                flush(&mut w, &mut written, &mut datagrams);
                true
            }
        };
        if !pushed {
            flush(&mut w, &mut written, &mut datagrams);
        }
        Ok(std::ops::ControlFlow::Continue(()))
    })?;
    flush(&mut w, &mut written, &mut datagrams);
    // The network.
    let mut bent = false;
    u.arbitrary_loop(Some(0), Some(24), |u| {
        if datagrams.is_empty() {
            return Ok(std::ops::ControlFlow::Break(()));
        }
        let i = u.int_in_range(0..=datagrams.len() - 1)?;
        match u.int_in_range(0u8..=5)? {
            0 => {
                datagrams.remove(i);
            }
            1 => {
                let d = datagrams[i].clone();
                datagrams.insert(i, d);
            }
            2 => {
                let j = u.int_in_range(0..=datagrams.len() - 1)?;
                datagrams.swap(i, j);
            }
            3 => {
                // Cut: the decoder refuses it whole, or it ends on an entry boundary.
                let cut = u.int_in_range(0..=datagrams[i].len())?;
                datagrams[i].truncate(cut);
            }
            _ => {
                bent = true;
                gen::mutate(u, &mut datagrams[i])?;
            }
        }
        Ok(std::ops::ControlFlow::Continue(()))
    })?;
    let mut rx = ArqReceiver::new(window);
    let mut delivered: Vec<Vec<u8>> = Vec::new();
    let mut received_bytes = 0usize;
    for d in &datagrams {
        received_bytes += d.len();
        let Ok(Datagram::Data(entries)) = datagram::decode(d) else {
            continue;
        };
        assert!(
            entries.len() <= d.len() / 2,
            "more entries than bytes allow"
        );
        for e in entries {
            match e {
                Entry::Syn(s) => {
                    rx.on_syn(s);
                }
                Entry::Safe { seq, msg } => rx.on_safe(seq, msg, |m| delivered.push(m.to_vec())),
                Entry::Fast(_) | Entry::Ack(_) | Entry::Unknown(_) => {}
            }
        }
        let _ = rx.take_ack();
    }
    let total: usize = delivered.iter().map(Vec::len).sum();
    assert!(
        total <= received_bytes,
        "{total} bytes delivered from {received_bytes} received"
    );
    if !bent {
        assert!(
            delivered.len() <= safe.len(),
            "more safe messages than sent"
        );
        for (i, m) in delivered.iter().enumerate() {
            assert_eq!(m, &safe[i], "safe message {i} out of order or altered");
        }
    }
    Ok(())
}

/// What happens to the bytes of one frame on the line.
fn line_op(
    u: &mut Unstructured<'_>,
    frame: Vec<u8>,
    clean: bool,
    out: &mut VecDeque<Vec<u8>>,
) -> Result<bool> {
    let mut bent = false;
    match u.int_in_range(0u8..=9)? {
        0 => {}
        1 => {
            out.push_back(frame.clone());
            out.push_back(frame);
        }
        2 => {
            // Reordered: goes in front of what waits.
            out.push_front(frame);
        }
        3 | 4 => {
            // Split into pieces fed separately.
            let cut = u.int_in_range(0..=frame.len())?;
            out.push_back(frame[..cut].to_vec());
            out.push_back(frame[cut..].to_vec());
        }
        5 if !clean => {
            bent = true;
            let mut f = frame;
            gen::mutate(u, &mut f)?;
            out.push_back(f);
        }
        6 if !clean => {
            bent = true;
            out.push_back(gen::bytes(u, 24)?);
            out.push_back(frame);
        }
        _ => out.push_back(frame),
    }
    Ok(bent)
}

/// Two serial engines over a line that drops, duplicates, reorders, splits and (in bent runs)
/// corrupts frames and adds noise; then the line heals and every safe message must arrive.
pub fn stp_frames(data: &[u8]) {
    let mut u = Unstructured::new(data);
    let _ = stp_case(&mut u);
}

fn stp_case(u: &mut Unstructured<'_>) -> Result<()> {
    let cfg = StpConfig::new(
        *u.choose(&[9_600, 57_600, 115_200, 1_000_000])?,
        Duration::from_millis(u.int_in_range(20u64..=500)?),
        u.int_in_range(16usize..=255)?,
        u.int_in_range(1usize..=32)?,
    );
    let clean = u.ratio(1u8, 2)?;
    let mut a: Stp<usize> = Stp::new(cfg, u.arbitrary()?);
    let mut b: Stp<usize> = Stp::new(cfg, u.arbitrary()?);
    let start = Instant::now();
    let mut now = start;
    let mut safe_sent: Vec<Vec<u8>> = Vec::new();
    let mut failed = 0usize;
    let mut delivered_safe: Vec<Vec<u8>> = Vec::new();
    let mut bent = false;
    let (mut ab, mut ba) = (VecDeque::<Vec<u8>>::new(), VecDeque::<Vec<u8>>::new());
    let max = cfg.max_message();
    let mut check = |events: Vec<StpEvent<usize>>, at_a: bool, failed: &mut usize| {
        for e in events {
            match e {
                StpEvent::Message(m) => {
                    assert!(
                        m.len() <= max,
                        "a message of {} bytes over the limit {max}",
                        m.len()
                    );
                    if !at_a && m.first() == Some(&b'S') {
                        delivered_safe.push(m);
                    }
                }
                StpEvent::Failed(t, _) => *failed += t.len(),
                StpEvent::Acked(_) | StpEvent::PeerReset => {}
            }
        }
    };
    u.arbitrary_loop(Some(1), Some(200), |u| {
        match u.int_in_range(0u8..=9)? {
            0 | 1 => {
                let len = u.int_in_range(0usize..=cfg.max_packet_size * 3)?;
                let mut m = vec![b'S'];
                m.extend_from_slice(&(safe_sent.len() as u32).to_le_bytes());
                m.extend(gen::bytes(u, len)?);
                if a.push_safe(start, m.clone(), Some(safe_sent.len()))
                    .is_some()
                {
                    failed += 1;
                }
                safe_sent.push(m);
            }
            2 => {
                let mut m = vec![b'F'];
                m.extend(gen::bytes(u, cfg.max_packet_size * 2)?);
                let key = if u.arbitrary()? {
                    Some(u.int_in_range(0u32..=3)?)
                } else {
                    None
                };
                a.push_fast(now, key, m);
            }
            3..=5 => {
                // The line carries what each side has to send now.
                while let Some(f) = a.poll_transmit(now) {
                    bent |= line_op(u, f, clean, &mut ab)?;
                }
                while let Some(f) = b.poll_transmit(now) {
                    bent |= line_op(u, f, clean, &mut ba)?;
                }
            }
            6 | 7 => {
                let mut ev = Vec::new();
                let n = u.int_in_range(0..=ab.len())?;
                for f in ab.drain(..n) {
                    b.on_bytes(now, &f, &mut ev);
                }
                check(ev, false, &mut failed);
                let mut ev = Vec::new();
                let n = u.int_in_range(0..=ba.len())?;
                for f in ba.drain(..n) {
                    a.on_bytes(now, &f, &mut ev);
                }
                check(ev, true, &mut failed);
            }
            8 => {
                // Lost in transit.
                ab.pop_front();
                ba.pop_front();
            }
            _ => {
                now += Duration::from_millis(u.int_in_range(1u64..=600)?);
                a.expire(now);
                b.expire(now);
            }
        }
        Ok(std::ops::ControlFlow::Continue(()))
    })?;
    // The line heals: what is in transit arrives, then both sides run until quiet.
    for _ in 0..20_000 {
        let mut ev = Vec::new();
        for f in ab.drain(..) {
            b.on_bytes(now, &f, &mut ev);
        }
        check(ev, false, &mut failed);
        let mut ev = Vec::new();
        for f in ba.drain(..) {
            a.on_bytes(now, &f, &mut ev);
        }
        check(ev, true, &mut failed);
        while let Some(f) = a.poll_transmit(now) {
            ab.push_back(f);
        }
        while let Some(f) = b.poll_transmit(now) {
            ba.push_back(f);
        }
        if ab.is_empty() && ba.is_empty() {
            match [a.poll_at(now), b.poll_at(now)].into_iter().flatten().min() {
                Some(t) if t < start + Duration::from_secs(3600) => {
                    now = t.max(now + Duration::from_micros(1));
                    a.expire(now);
                    b.expire(now);
                }
                _ => break,
            }
        }
    }
    if !bent {
        for (i, m) in delivered_safe.iter().enumerate() {
            assert!(i < safe_sent.len(), "more safe messages than sent");
            assert_eq!(m, &safe_sent[i], "safe message {i} out of order or altered");
        }
        if failed == 0 {
            assert_eq!(
                delivered_safe.len(),
                safe_sent.len(),
                "the line healed but safe messages never arrived"
            );
        }
    }
    Ok(())
}

/// Hellos, heartbeats, declaration batches and Byes of up to four peers into a node's
/// declaration table; the caps and ownership invariants hold after every step.
pub fn node_decls(data: &[u8]) {
    let _ = crate::node::fuzz::run(data);
}

/// Shared-memory frames of up to three writers into the receiving machine.
#[cfg(feature = "shm")]
pub fn shm_frames(data: &[u8]) {
    let _ = crate::link::shm::fuzz::run(data);
}

/// A file's chunks over a hostile line into the receiver's reassembly machine
/// (`node::reassembly`), with a model of the part file.
pub fn file_chunks(data: &[u8]) {
    let mut u = Unstructured::new(data);
    let _ = file_chunks_case(&mut u);
}

/// The receiver of [`file_chunks`]: the machine and a model of the part file it writes.
struct ChunkReceiver<'a> {
    machine: crate::node::reassembly::Reassembly,
    original: &'a [u8],
    file: Vec<u8>,
    /// Whether a forged chunk with bytes other than the original's was written.
    forged_written: bool,
    last_ack: u64,
    writes_since_ack: u32,
}

impl ChunkReceiver<'_> {
    /// Feeds one chunk, checking the machine's answer; `false` once the transfer is over.
    fn feed(&mut self, at: u64, bytes: &[u8], forged: bool) -> bool {
        use crate::node::reassembly::{ChunkStep, PROGRESS_EVERY};
        let size = self.original.len() as u64;
        let before = self.machine.expected();
        match self.machine.on_chunk(at, bytes.len()) {
            ChunkStep::Skip => {
                assert_eq!(
                    self.machine.expected(),
                    before,
                    "a skipped chunk moved the file"
                );
                true
            }
            ChunkStep::Overrun { reached } => {
                assert!(reached > size, "overrun at {reached} within {size} bytes");
                assert_eq!(at, before, "an overrun not at the end of the file");
                assert!(self.machine.is_overrun() && !self.machine.is_complete());
                false
            }
            ChunkStep::Write { ack } => {
                assert_eq!(
                    at,
                    self.file.len() as u64,
                    "a chunk written away from the end"
                );
                self.file.extend_from_slice(bytes);
                let end = self.file.len();
                assert!(end as u64 <= size, "written past the announced size");
                assert_eq!(self.machine.expected(), end as u64);
                self.forged_written |= forged && bytes != &self.original[at as usize..end];
                self.writes_since_ack += 1;
                match ack {
                    Some(a) => {
                        assert!(a >= self.last_ack, "acknowledgement went back");
                        assert_eq!(a, end as u64, "acknowledged what is not written");
                        self.last_ack = a;
                        self.writes_since_ack = 0;
                    }
                    None => {
                        assert!(
                            self.writes_since_ack < PROGRESS_EVERY,
                            "no acknowledgement in {PROGRESS_EVERY} chunks"
                        );
                        assert!((end as u64) < size, "the last chunk not acknowledged");
                    }
                }
                true
            }
        }
    }
}

fn file_chunks_case(u: &mut Unstructured<'_>) -> Result<()> {
    use crate::node::reassembly::{ChunkStep, Reassembly};

    let size = u.int_in_range(0u64..=4096)?;
    // The original bytes: a pattern, so a chunk carrying other bytes shows in the result.
    let original: Vec<u8> = (0..size)
        .map(|i| (i.wrapping_mul(31) ^ (i >> 8)) as u8)
        .collect();
    let on_disk = if u.arbitrary()? {
        u.int_in_range(0..=size)?
    } else {
        0
    };
    let chunk = u.int_in_range(1u64..=600)?;
    let mut rx = ChunkReceiver {
        machine: Reassembly::new(size, on_disk),
        original: &original,
        file: original[..on_disk as usize].to_vec(),
        forged_written: false,
        last_ack: on_disk,
        writes_since_ack: 0,
    };
    // The sender: where it sends from next, and the chunks it sent (for duplicates).
    let mut next = on_disk;
    let mut sent: Vec<(u64, Vec<u8>)> = Vec::new();
    let genuine = |at: u64| -> (u64, Vec<u8>) {
        let end = at.saturating_add(chunk).min(size);
        (at, original[at as usize..end as usize].to_vec())
    };

    let steps = u.int_in_range(0u16..=400)?;
    for _ in 0..steps {
        if rx.machine.is_complete() || rx.machine.is_overrun() {
            break;
        }
        let going = match u.int_in_range(0u8..=9)? {
            // The next chunk, in order.
            0..=3 if next < size => {
                let (at, bytes) = genuine(next);
                next += bytes.len() as u64;
                sent.push((at, bytes.clone()));
                rx.feed(at, &bytes, false)
            }
            // A chunk sent before, again.
            4 if !sent.is_empty() => {
                let (at, bytes) = sent[u.choose_index(sent.len())?].clone();
                rx.feed(at, &bytes, false)
            }
            // A chunk lost: the sender moves on.
            5 if next < size => {
                next = next.saturating_add(chunk).min(size);
                true
            }
            // The sender goes back to the last acknowledgement (its timer).
            6 => {
                next = rx.last_ack;
                true
            }
            // A later chunk first.
            7 if next < size => {
                let skip = u.int_in_range(1u64..=4)?.saturating_mul(chunk);
                let (at, bytes) = genuine(next.saturating_add(skip).min(size));
                rx.feed(at, &bytes, false)
            }
            // A forged chunk: at the end of the file or anywhere near it, any length, any
            // bytes.
            8 => {
                let at = if u.arbitrary()? {
                    rx.machine.expected()
                } else {
                    u.int_in_range(0..=size.saturating_add(64))?
                };
                let len = u.int_in_range(0usize..=700)?;
                let bytes = u.bytes(len.min(u.len()))?.to_vec();
                rx.feed(at, &bytes, true)
            }
            // A huge claimed length (the machine sees only lengths).
            _ => {
                let at = rx.machine.expected();
                match rx.machine.on_chunk(at, usize::MAX) {
                    ChunkStep::Overrun { .. } => false,
                    other => panic!("a chunk of usize::MAX bytes taken: {other:?}"),
                }
            }
        };
        if !going {
            break;
        }
    }
    if rx.machine.is_overrun() {
        return Ok(());
    }
    if !rx.forged_written {
        assert_eq!(
            rx.file,
            &original[..rx.file.len()],
            "genuine chunks made other bytes"
        );
    }
    // The line heals: the sender resends from the last acknowledgement, in order.
    let mut at = rx.last_ack;
    let mut rounds = 0;
    while !rx.machine.is_complete() {
        let (from, bytes) = genuine(at);
        assert!(rx.feed(from, &bytes, false), "a genuine chunk overran");
        at = rx.machine.expected();
        rounds += 1;
        assert!(
            rounds <= size / chunk + 2,
            "the file never completes once the line heals"
        );
    }
    assert_eq!(rx.file.len() as u64, size);
    assert_eq!(rx.last_ack, size, "completion not acknowledged");
    if !rx.forged_written {
        assert_eq!(rx.file, original, "genuine chunks made another file");
    }
    Ok(())
}
