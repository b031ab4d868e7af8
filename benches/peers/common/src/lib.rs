//! What the peer binaries share: their command line, the child side of the runner's protocol,
//! and the counting of arrivals.
//!
//! Every peer binary is started by the runner (`src/main.rs`) as
//! `peer-<middleware> ROLE SIZE KEY PARAM [LINK]`:
//!
//! | role | does | prints |
//! |---|---|---|
//! | `pong` | answers every ping with the same bytes | `ready [ADDR]` |
//! | `ping` | `PARAM` timed round trips after a warm-up, one at a time | `ready`, `result P50_US P99_US` |
//! | `sub` | counts arrivals until the runner says `stop SENT` | `ready [ADDR]`, `result COUNT SPAN_S` |
//! | `pub` | publishes as fast as it may for `PARAM` seconds (reliable unless the middleware has no reliability) | `ready`, `result SENT SECS` |
//! | `idle` | sits idle beside its partner | `ready [ADDR]` |
//! | `pong-load` | answers pings (a call where the middleware has calls) and takes a bulk stream | `ready` |
//! | `ping-load` | `PARAM` round trips idle, then `PARAM` more while it streams [`BULK_FRAME`]-byte frames to the `pong-load` as fast as they go | `ready`, `result P50_US P99_US IDLE_P50_US IDLE_P99_US BULK_MB_S` |
//!
//! `KEY` names the run's channel (an address, a key expression, a service name); `SIZE` is the
//! payload in bytes. In a fan-out the runner starts several `sub`s and tells every child how
//! many through the environment ([`subscribers`]); a publisher waits for them all. A child exits when its standard input closes (the runner dropped it) and
//! after [`HARD_DEADLINE`] in any case, so no child outlives a run that went wrong.

use std::io::BufRead;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Arc, OnceLock};
use std::time::{Duration, Instant};

/// No child lives longer than this, whatever happens to the runner.
pub const HARD_DEADLINE: Duration = Duration::from_secs(120);

/// Round trips before the timed ones (at most; a tenth of the timed ones when fewer).
pub const WARMUP: usize = 300;

/// The frame of the bulk stream under which `ping-load` times its round trips: a camera's
/// 4 MiB frame.
pub const BULK_FRAME: usize = 4 << 20;

/// A peer's command line.
#[derive(Debug, Clone)]
pub struct Args {
    /// `pong`, `ping`, `sub`, `pub` or `idle`.
    pub role: String,
    /// Payload size in bytes.
    pub size: usize,
    /// The run's channel name or address.
    pub key: String,
    /// Round trips (`ping`) or seconds (`pub`).
    pub param: f64,
    /// Middleware-specific link choice (marea: `udp:PORT`, `shm`, `serial:DEV:BAUD`).
    pub link: Option<String>,
}

impl Args {
    /// Parses `ROLE SIZE KEY PARAM [LINK]`.
    pub fn parse() -> anyhow::Result<Args> {
        let v: Vec<String> = std::env::args().skip(1).collect();
        let usage = "usage: ROLE SIZE KEY PARAM [LINK]";
        let get = |i: usize| v.get(i).cloned().ok_or_else(|| anyhow::anyhow!("{usage}"));
        let role = get(0)?;
        let size = get(1)?
            .parse()
            .map_err(|e| anyhow::anyhow!("SIZE {:?}: {e}", v[1]))?;
        let key = get(2)?;
        let param = get(3)?
            .parse()
            .map_err(|e| anyhow::anyhow!("PARAM {:?}: {e}", v[3]))?;
        Ok(Args {
            role,
            size,
            key,
            param,
            link: v.get(4).cloned(),
        })
    }
}

/// The runner's word to this child: how many messages the publisher sent (`stop N`).
pub struct Control {
    stop: OnceLock<u64>,
    closed: AtomicBool,
}

impl Control {
    /// Starts watching standard input and the hard deadline. When standard input closes the
    /// process exits if `exit_on_eof`, else [`Control::closed`] turns true (for peers that must
    /// release shared-memory resources on the way out).
    pub fn start(exit_on_eof: bool) -> Arc<Control> {
        let c = Arc::new(Control {
            stop: OnceLock::new(),
            closed: AtomicBool::new(false),
        });
        let c2 = c.clone();
        std::thread::spawn(move || {
            let stdin = std::io::stdin();
            for line in stdin.lock().lines() {
                let Ok(line) = line else { break };
                if let Some(n) = line.strip_prefix("stop ") {
                    if let Ok(n) = n.trim().parse() {
                        let _ = c2.stop.set(n);
                    }
                }
            }
            if exit_on_eof {
                std::process::exit(0);
            }
            c2.closed.store(true, Ordering::Relaxed);
        });
        std::thread::spawn(|| {
            std::thread::sleep(HARD_DEADLINE);
            eprintln!("peer: hard deadline reached, exiting");
            std::process::exit(3);
        });
        c
    }

    /// Whether the runner closed this child's standard input (time to leave).
    pub fn closed(&self) -> bool {
        self.closed.load(Ordering::Relaxed)
    }

    /// How many the publisher sent, once the runner said so.
    pub fn stop(&self) -> Option<u64> {
        self.stop.get().copied()
    }
}

/// How many subscribers the run has (`PEERS_SUBSCRIBERS`, 1 when unset): a fan-out's
/// publisher waits until it reaches them all.
pub fn subscribers() -> usize {
    std::env::var("PEERS_SUBSCRIBERS")
        .ok()
        .and_then(|n| n.parse().ok())
        .filter(|&n| n >= 1)
        .unwrap_or(1)
}

/// Tells the runner this child is ready (with what the initiator needs, if anything).
pub fn ready(info: &str) {
    println!("ready {info}");
}

/// Arrivals counted from any thread without a lock: how many, first and last instant.
pub struct Arrivals {
    epoch: Instant,
    count: AtomicU64,
    /// Nanoseconds since `epoch` + 1 (0: none yet).
    first: AtomicU64,
    last: AtomicU64,
}

impl Default for Arrivals {
    fn default() -> Self {
        Arrivals {
            epoch: Instant::now(),
            count: AtomicU64::new(0),
            first: AtomicU64::new(0),
            last: AtomicU64::new(0),
        }
    }
}

impl Arrivals {
    /// One more arrival, now.
    pub fn add(&self) {
        let t = self.epoch.elapsed().as_nanos() as u64 + 1;
        self.count.fetch_add(1, Ordering::Relaxed);
        let _ = self
            .first
            .compare_exchange(0, t, Ordering::Relaxed, Ordering::Relaxed);
        self.last.store(t, Ordering::Relaxed);
    }

    /// How many so far.
    pub fn count(&self) -> u64 {
        self.count.load(Ordering::Relaxed)
    }

    /// Seconds between the first and the last arrival.
    pub fn span(&self) -> f64 {
        let (a, b) = (
            self.first.load(Ordering::Relaxed),
            self.last.load(Ordering::Relaxed),
        );
        if a == 0 || b <= a {
            0.0
        } else {
            (b - a) as f64 / 1e9
        }
    }
}

/// The end of a `sub` role: once the runner said how many were sent, waits until all arrived
/// or nothing arrived for a second (lossy transports), and prints `result COUNT SPAN`.
pub fn finish_sub(arrivals: &Arrivals, control: &Control) {
    let mut last = (arrivals.count(), Instant::now());
    loop {
        std::thread::sleep(Duration::from_millis(5));
        let n = arrivals.count();
        if n != last.0 {
            last = (n, Instant::now());
        }
        if let Some(sent) = control.stop() {
            if n >= sent || last.1.elapsed() > Duration::from_secs(1) {
                println!("result {n} {}", arrivals.span());
                return;
            }
        }
        if control.closed() {
            return;
        }
    }
}

/// Collects round-trip times after the warm-up.
pub struct Rtts {
    n: usize,
    warmup: usize,
    seen: usize,
    us: Vec<f64>,
}

impl Rtts {
    /// `n` timed round trips after [`WARMUP`].
    pub fn new(n: usize) -> Rtts {
        Rtts {
            n,
            warmup: WARMUP.min(n / 10),
            seen: 0,
            us: Vec::with_capacity(n),
        }
    }

    /// Total round trips to run (warm-up included).
    pub fn total(&self) -> usize {
        self.n + self.warmup
    }

    /// Records one round trip that started at `t`.
    pub fn push(&mut self, t: Instant) {
        self.seen += 1;
        if self.seen > self.warmup {
            self.us.push(t.elapsed().as_secs_f64() * 1e6);
        }
    }

    /// The median and 99th percentile, in µs.
    pub fn percentiles(mut self) -> (f64, f64) {
        self.us.sort_by(f64::total_cmp);
        (percentile(&self.us, 0.5), percentile(&self.us, 0.99))
    }

    /// Prints `result P50 P99`.
    pub fn finish(self) {
        let (p50, p99) = self.percentiles();
        println!("result {p50} {p99}");
    }
}

/// The `p` quantile of sorted samples (NaN when there are none).
pub fn percentile(sorted: &[f64], p: f64) -> f64 {
    if sorted.is_empty() {
        return f64::NAN;
    }
    let i = ((sorted.len() as f64 - 1.0) * p).round() as usize;
    sorted[i.min(sorted.len() - 1)]
}

/// A payload of `size` bytes whose first eight carry `i` (so a ping can recognise its pong).
pub fn payload(size: usize, i: u64) -> Vec<u8> {
    let mut v = vec![0x5au8; size.max(8)];
    v[..8].copy_from_slice(&i.to_le_bytes());
    v.truncate(size.max(8));
    v
}

/// The sequence number in a payload made by [`payload`].
pub fn seq(bytes: &[u8]) -> Option<u64> {
    Some(u64::from_le_bytes(bytes.get(..8)?.try_into().ok()?))
}

/// Counts the bytes a bulk stream moved: the publisher adds each frame as it is handed over.
#[derive(Default)]
pub struct BulkMeter {
    bytes: AtomicU64,
    stop: AtomicBool,
}

impl BulkMeter {
    /// One more frame of `len` bytes sent.
    pub fn add(&self, len: usize) {
        self.bytes.fetch_add(len as u64, Ordering::Relaxed);
    }

    /// Bytes sent so far.
    pub fn bytes(&self) -> u64 {
        self.bytes.load(Ordering::Relaxed)
    }

    /// Tells the publisher to stop.
    pub fn stop(&self) {
        self.stop.store(true, Ordering::Relaxed);
    }

    /// Whether the publisher was told to stop.
    pub fn stopped(&self) -> bool {
        self.stop.load(Ordering::Relaxed)
    }
}

/// `n` timed round trips after the warm-up ([`Rtts`]), numbered from `first`: `round_trip(i)`
/// answers with when it started.
pub async fn timed_round_trips<F, Fut>(
    n: usize,
    first: u64,
    round_trip: &mut F,
) -> anyhow::Result<Rtts>
where
    F: FnMut(u64) -> Fut,
    Fut: std::future::Future<Output = anyhow::Result<Instant>>,
{
    let mut rtts = Rtts::new(n);
    for i in 0..rtts.total() as u64 {
        rtts.push(round_trip(first + i).await?);
    }
    Ok(rtts)
}

/// The loaded half of `ping-load`: once `streamer` (publishing frames, counted on `meter`)
/// handed over its first frame, times `n` round trips (`round_trip(i)` answers with when it
/// started), stops the stream and prints the loaded and `idle` percentiles and the stream's
/// MB/s meanwhile.
pub async fn under_load<F, Fut>(
    n: usize,
    idle: (f64, f64),
    meter: &BulkMeter,
    streamer: tokio::task::JoinHandle<anyhow::Result<()>>,
    mut round_trip: F,
) -> anyhow::Result<()>
where
    F: FnMut(u64) -> Fut,
    Fut: std::future::Future<Output = anyhow::Result<Instant>>,
{
    while meter.bytes() == 0 && !streamer.is_finished() {
        tokio::time::sleep(Duration::from_millis(1)).await;
    }
    let (from, start) = (meter.bytes(), Instant::now());
    // Numbered apart from the idle ones, so a late idle answer is never taken for one.
    let loaded = timed_round_trips(n, 1 << 32, &mut round_trip).await?;
    let (moved, secs) = (meter.bytes() - from, start.elapsed().as_secs_f64());
    meter.stop();
    if streamer.is_finished() {
        streamer.await??;
        anyhow::bail!("ping-load: the bulk stream ended early");
    }
    streamer.abort();
    let (p50, p99) = loaded.percentiles();
    println!(
        "result {p50} {p99} {} {} {}",
        idle.0,
        idle.1,
        moved as f64 / 1e6 / secs.max(1e-9)
    );
    Ok(())
}

/// Waits (polling, bounded) until `cond` holds.
pub fn wait_until(
    what: &str,
    timeout: Duration,
    mut cond: impl FnMut() -> bool,
) -> anyhow::Result<()> {
    let end = Instant::now() + timeout;
    while !cond() {
        if Instant::now() > end {
            anyhow::bail!("{what}: not within {timeout:?}");
        }
        std::thread::sleep(Duration::from_millis(1));
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn payload_carries_its_sequence_number_and_size() {
        let p = payload(64, 42);
        assert_eq!(p.len(), 64);
        assert_eq!(seq(&p), Some(42));
        assert_eq!(payload(1024, u64::MAX).len(), 1024);
        assert_eq!(seq(&[1, 2, 3]), None);
    }

    #[test]
    fn percentile_of_sorted_samples() {
        let v: Vec<f64> = (1..=100).map(f64::from).collect();
        assert_eq!(percentile(&v, 0.5), 51.0);
        assert_eq!(percentile(&v, 0.99), 99.0);
        assert!(percentile(&[], 0.5).is_nan());
    }

    #[test]
    fn arrivals_count_and_span() {
        let a = Arrivals::default();
        assert_eq!((a.count(), a.span()), (0, 0.0));
        a.add();
        std::thread::sleep(Duration::from_millis(2));
        a.add();
        assert_eq!(a.count(), 2);
        assert!(a.span() >= 0.002, "span {}", a.span());
    }

    #[test]
    fn rtts_skip_the_warmup() {
        let mut r = Rtts::new(100);
        assert_eq!(r.total(), 110);
        for _ in 0..r.total() {
            r.push(Instant::now());
        }
        assert_eq!(r.us.len(), 100);
    }
}
