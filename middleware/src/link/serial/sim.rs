//! Fault injection for tests and benchmarks: a seeded lossy line (pure, simulated clock) and an
//! in-memory async pipe with the same faults, standing in for a serial port.

use std::collections::VecDeque;
use std::io;
use std::pin::Pin;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};
use std::task::{Context, Poll};
use std::time::{Duration, Instant};

use rand::rngs::StdRng;
use rand::{Rng, SeedableRng};
use tokio::io::{AsyncRead, AsyncWrite, ReadBuf};
use tokio::sync::mpsc;

use super::stp::{Stp, StpConfig, StpEvent};

/// Per-byte faults.
#[derive(Debug, Clone, Copy, Default)]
pub struct Faults {
    /// Probability a byte is lost.
    pub loss: f64,
    /// Probability a byte is corrupted (one random bit pattern XORed in).
    pub corrupt: f64,
}

/// Applies faults to bytes with a seeded generator.
#[derive(Debug)]
pub struct FaultInjector {
    rng: StdRng,
    faults: Faults,
    /// Bytes lost so far.
    pub lost: u64,
    /// Bytes corrupted so far.
    pub corrupted: u64,
}

impl FaultInjector {
    /// An injector with a seed.
    pub fn new(seed: u64, faults: Faults) -> Self {
        FaultInjector {
            rng: StdRng::seed_from_u64(seed),
            faults,
            lost: 0,
            corrupted: 0,
        }
    }

    /// The bytes that survive, some corrupted.
    pub fn apply(&mut self, bytes: &[u8]) -> Vec<u8> {
        let mut out = Vec::with_capacity(bytes.len());
        for &b in bytes {
            let r: f64 = self.rng.random();
            if r < self.faults.loss {
                self.lost += 1;
            } else if r < self.faults.loss + self.faults.corrupt {
                self.corrupted += 1;
                out.push(b ^ self.rng.random_range(1..=255u8));
            } else {
                out.push(b);
            }
        }
        out
    }
}

/// A one-way line on a simulated clock: bytes take their line time at `baud_rate` (8N1) plus
/// `latency`, suffer faults, and vanish during outages.
#[derive(Debug)]
pub struct SimLine {
    faults: FaultInjector,
    baud_rate: u32,
    latency: Duration,
    busy_until: Option<Instant>,
    in_transit: VecDeque<(Instant, Vec<u8>)>,
    outages: Vec<(Instant, Instant)>,
}

impl SimLine {
    /// A line.
    pub fn new(seed: u64, faults: Faults, baud_rate: u32, latency: Duration) -> Self {
        SimLine {
            faults: FaultInjector::new(seed, faults),
            baud_rate: baud_rate.max(1),
            latency,
            busy_until: None,
            in_transit: VecDeque::new(),
            outages: Vec::new(),
        }
    }

    /// Adds an outage: bytes sent within `[from, to)` are lost.
    pub fn outage(&mut self, from: Instant, to: Instant) {
        self.outages.push((from, to));
    }

    /// Sends bytes at `now`.
    pub fn send(&mut self, now: Instant, bytes: &[u8]) {
        let start = self.busy_until.map_or(now, |t| t.max(now));
        let dur = Duration::from_nanos(
            bytes.len() as u64 * 10 * 1_000_000_000 / u64::from(self.baud_rate),
        );
        let end = start + dur;
        self.busy_until = Some(end);
        if self.outages.iter().any(|&(a, b)| start >= a && start < b) {
            return;
        }
        let bytes = self.faults.apply(bytes);
        self.in_transit.push_back((end + self.latency, bytes));
    }

    /// Bytes that arrived by `now`.
    pub fn receive(&mut self, now: Instant) -> Vec<u8> {
        let mut out = Vec::new();
        while self.in_transit.front().is_some_and(|(t, _)| *t <= now) {
            if let Some((_, b)) = self.in_transit.pop_front() {
                out.extend(b);
            }
        }
        out
    }

    /// When the next bytes arrive.
    pub fn next_arrival(&self) -> Option<Instant> {
        self.in_transit.front().map(|(t, _)| *t)
    }

    /// Bytes lost and corrupted so far.
    pub fn damage(&self) -> (u64, u64) {
        (self.faults.lost, self.faults.corrupted)
    }
}

/// The writing end of an in-memory faulty pipe.
#[derive(Debug)]
pub struct PipeWriter {
    tx: mpsc::UnboundedSender<Vec<u8>>,
    faults: Arc<Mutex<FaultInjector>>,
    down: Arc<AtomicBool>,
}

/// The reading end of an in-memory faulty pipe.
#[derive(Debug)]
pub struct PipeReader {
    rx: mpsc::UnboundedReceiver<Vec<u8>>,
    pending: Vec<u8>,
}

/// Switches a pipe's outage on and off.
#[derive(Debug, Clone)]
pub struct OutageSwitch(Arc<AtomicBool>);

impl OutageSwitch {
    /// While on, written bytes are lost.
    pub fn set(&self, down: bool) {
        self.0.store(down, Ordering::Relaxed);
    }
}

/// A one-way in-memory pipe with faults.
pub fn faulty_pipe(seed: u64, faults: Faults) -> (PipeWriter, PipeReader, OutageSwitch) {
    let (tx, rx) = mpsc::unbounded_channel();
    let down = Arc::new(AtomicBool::new(false));
    (
        PipeWriter {
            tx,
            faults: Arc::new(Mutex::new(FaultInjector::new(seed, faults))),
            down: down.clone(),
        },
        PipeReader {
            rx,
            pending: Vec::new(),
        },
        OutageSwitch(down),
    )
}

impl AsyncWrite for PipeWriter {
    fn poll_write(
        self: Pin<&mut Self>,
        _cx: &mut Context<'_>,
        buf: &[u8],
    ) -> Poll<io::Result<usize>> {
        if !self.down.load(Ordering::Relaxed) {
            let bytes = crate::sync::lock(&self.faults).apply(buf);
            if self.tx.send(bytes).is_err() {
                return Poll::Ready(Err(io::ErrorKind::BrokenPipe.into()));
            }
        }
        Poll::Ready(Ok(buf.len()))
    }

    fn poll_flush(self: Pin<&mut Self>, _cx: &mut Context<'_>) -> Poll<io::Result<()>> {
        Poll::Ready(Ok(()))
    }

    fn poll_shutdown(self: Pin<&mut Self>, _cx: &mut Context<'_>) -> Poll<io::Result<()>> {
        Poll::Ready(Ok(()))
    }
}

impl AsyncRead for PipeReader {
    fn poll_read(
        mut self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        buf: &mut ReadBuf<'_>,
    ) -> Poll<io::Result<()>> {
        while self.pending.is_empty() {
            match self.rx.poll_recv(cx) {
                Poll::Ready(Some(b)) => self.pending = b,
                // Writer gone: end of stream, like a vanished port.
                Poll::Ready(None) => return Poll::Ready(Ok(())),
                Poll::Pending => return Poll::Pending,
            }
        }
        let n = self.pending.len().min(buf.remaining());
        buf.put_slice(&self.pending[..n]);
        self.pending.drain(..n);
        Poll::Ready(Ok(()))
    }
}

/// Which end of a [`SimPair`].
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Side {
    /// The first engine.
    A,
    /// The second engine.
    B,
}

/// Two [`Stp`] engines joined by two [`SimLine`]s on a simulated clock: deterministic, and a
/// minute of 57600-baud traffic runs in milliseconds.
pub struct SimPair {
    /// Engine A.
    pub a: Stp<u64>,
    /// Engine B.
    pub b: Stp<u64>,
    /// Line A to B.
    pub ab: SimLine,
    /// Line B to A.
    pub ba: SimLine,
    /// The simulated clock.
    pub now: Instant,
}

impl SimPair {
    /// A pair with the same configuration and faults in both directions.
    pub fn new(cfg: StpConfig, faults: Faults, seed: u64, latency: Duration) -> Self {
        SimPair {
            a: Stp::new(cfg, 0x1111),
            b: Stp::new(cfg, 0x2222),
            ab: SimLine::new(seed, faults, cfg.baud_rate, latency),
            ba: SimLine::new(seed ^ 0x5555, faults, cfg.baud_rate, latency),
            now: Instant::now(),
        }
    }

    /// Runs until `until`, calling `on_event(side, now, event)` for what each engine reports
    /// and `tick(pair)` before every step (to inject traffic). Steps are at most `step` apart.
    pub fn run(
        &mut self,
        until: Instant,
        step: Duration,
        mut tick: impl FnMut(&mut SimPair),
        mut on_event: impl FnMut(Side, Instant, StpEvent<u64>),
    ) {
        let mut events = Vec::new();
        while self.now < until {
            tick(self);
            let now = self.now;
            while let Some(f) = self.a.poll_transmit(now) {
                self.ab.send(now, &f);
            }
            while let Some(f) = self.b.poll_transmit(now) {
                self.ba.send(now, &f);
            }
            let bytes = self.ab.receive(now);
            if !bytes.is_empty() {
                self.b.on_bytes(now, &bytes, &mut events);
                for e in events.drain(..) {
                    on_event(Side::B, now, e);
                }
            }
            let bytes = self.ba.receive(now);
            if !bytes.is_empty() {
                self.a.on_bytes(now, &bytes, &mut events);
                for e in events.drain(..) {
                    on_event(Side::A, now, e);
                }
            }
            self.a.expire(now);
            self.b.expire(now);
            let next = [
                self.a.poll_at(now),
                self.b.poll_at(now),
                self.ab.next_arrival(),
                self.ba.next_arrival(),
                Some(now + step),
            ]
            .into_iter()
            .flatten()
            .filter(|&t| t > now)
            .min()
            .unwrap_or(now + step);
            self.now = next.min(until).max(now + Duration::from_micros(50));
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use tokio::io::{AsyncReadExt, AsyncWriteExt};

    #[test]
    fn injector_is_reproducible() {
        let f = Faults {
            loss: 0.1,
            corrupt: 0.1,
        };
        let data = vec![0u8; 10_000];
        let a = FaultInjector::new(5, f).apply(&data);
        let b = FaultInjector::new(5, f).apply(&data);
        assert_eq!(a, b);
        assert!(a.len() < 9_500 && a.len() > 8_500, "{}", a.len());
    }

    #[test]
    fn sim_line_paces_and_drops_during_outages() {
        let t0 = Instant::now();
        let mut l = SimLine::new(1, Faults::default(), 10_000, Duration::ZERO);
        l.outage(
            t0 + Duration::from_millis(100),
            t0 + Duration::from_millis(200),
        );
        l.send(t0, &[1; 100]); // 100 ms of line time
        assert!(l.receive(t0 + Duration::from_millis(99)).is_empty());
        assert_eq!(l.receive(t0 + Duration::from_millis(100)).len(), 100);
        l.send(t0 + Duration::from_millis(150), &[2; 10]);
        assert_eq!(l.next_arrival(), None);
    }

    #[tokio::test]
    async fn pipe_carries_bytes_and_honours_outage() {
        let (mut w, mut r, switch) = faulty_pipe(1, Faults::default());
        w.write_all(b"abc").await.unwrap();
        switch.set(true);
        w.write_all(b"lost").await.unwrap();
        switch.set(false);
        w.write_all(b"d").await.unwrap();
        drop(w);
        let mut got = Vec::new();
        r.read_to_end(&mut got).await.unwrap();
        assert_eq!(got, b"abcd");
    }
}
