//! `marea-wan`: a wide-area link emulated between a client and a server on this host, for TCP
//! (a Zenoh router's clients) or UDP. It listens, forwards what it accepts to `--to`, and gives
//! each direction a one-way delay, a bandwidth, losses and scheduled outages. It prints
//! `{"listen": "IP:PORT"}` first, then one line per outage as it starts and ends.
//!
//! ```text
//! marea-wan --listen 127.0.0.1:0 --to 127.0.0.1:7447 --delay-ms 75 --loss 0.01 --rate-kbps 2000 --outage 30000:30000
//! ```
//!
//! A TCP stream cannot lose bytes; what a lost segment costs a TCP sender is a retransmission
//! timeout, during which that segment and everything behind it in the same direction wait (head
//! of line). So on TCP, each segment of up to 1,460 bytes is lost with probability `--loss`, and
//! it and what follows it in its direction arrive one retransmission timeout (three one-way
//! delays, at least 200 ms, as Linux's minimum) later. During an outage nothing is delivered in
//! either direction: bytes wait (TCP retransmits them when the path returns) and new connections
//! wait to be forwarded. On UDP each datagram is dropped with probability `--loss`, and during
//! an outage every datagram is dropped.

use std::collections::HashMap;
use std::net::SocketAddr;
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use anyhow::{bail, Context};
use clap::Parser;
use rand::{Rng, SeedableRng};
use serde_json::json;
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::net::{TcpListener, TcpStream, UdpSocket};
use tokio::sync::mpsc;

#[derive(Parser, Debug)]
#[command(about = "Emulates a wide-area link (delay, loss, bandwidth, outages) for TCP or UDP")]
struct Args {
    /// Address to listen on (port 0: any; the chosen one is printed).
    #[arg(long, default_value = "127.0.0.1:0")]
    listen: SocketAddr,
    /// Where to forward to.
    #[arg(long)]
    to: SocketAddr,
    /// Forward UDP datagrams instead of TCP connections.
    #[arg(long)]
    udp: bool,
    /// One-way delay in ms, each direction (the round trip is twice it).
    #[arg(long, default_value_t = 0)]
    delay_ms: u64,
    /// Bandwidth of each direction in kbit/s (0: unlimited).
    #[arg(long, default_value_t = 0)]
    rate_kbps: u64,
    /// Probability that a segment (TCP) or datagram (UDP) is lost.
    #[arg(long, default_value_t = 0.0)]
    loss: f64,
    /// Outage `START_MS:DURATION_MS` after start (repeatable): nothing gets through.
    #[arg(long, value_parser = parse_outage)]
    outage: Vec<(u64, u64)>,
    /// Seed of the loss generator.
    #[arg(long, default_value_t = 1)]
    seed: u64,
}

fn parse_outage(s: &str) -> Result<(u64, u64), String> {
    let (a, b) = s
        .split_once(':')
        .ok_or_else(|| format!("expected START_MS:DURATION_MS, got {s:?}"))?;
    let a = a.trim().parse().map_err(|e| format!("start {a:?}: {e}"))?;
    let b = b
        .trim()
        .parse()
        .map_err(|e| format!("duration {b:?}: {e}"))?;
    Ok((a, b))
}

/// A TCP segment's payload: the unit a loss applies to.
const SEGMENT: usize = 1460;

/// The least retransmission timeout of a TCP sender (Linux's `TCP_RTO_MIN`).
const MIN_RTO: Duration = Duration::from_millis(200);

/// One direction of the emulated path: when each chunk written into it comes out. Pure: the
/// caller passes `now`.
struct Path {
    delay: Duration,
    /// Bytes per second (0: unlimited).
    rate: u64,
    loss: f64,
    /// The link is busy sending until then (bandwidth).
    busy_until: Instant,
    /// No chunk comes out before an earlier one (a stream keeps its order).
    last_out: Instant,
    outages: Vec<(Instant, Instant)>,
    rng: rand::rngs::StdRng,
}

impl Path {
    fn new(args: &Args, start: Instant, seed: u64) -> Path {
        Path {
            delay: Duration::from_millis(args.delay_ms),
            rate: args.rate_kbps * 1000 / 8,
            loss: args.loss.clamp(0.0, 1.0),
            busy_until: start,
            last_out: start,
            outages: args
                .outage
                .iter()
                .map(|&(s, d)| {
                    let from = start + Duration::from_millis(s);
                    (from, from + Duration::from_millis(d))
                })
                .collect(),
            rng: rand::rngs::StdRng::seed_from_u64(seed),
        }
    }

    /// The end of the outage `t` falls in, if any.
    fn outage_end(&self, t: Instant) -> Option<Instant> {
        self.outages
            .iter()
            .find(|(from, to)| (*from..*to).contains(&t))
            .map(|&(_, to)| to)
    }

    fn transmitted(&mut self, now: Instant, len: usize) -> Instant {
        let start = self.busy_until.max(now);
        let on_wire = if self.rate == 0 {
            Duration::ZERO
        } else {
            Duration::from_secs_f64(len as f64 / self.rate as f64)
        };
        self.busy_until = start + on_wire;
        self.busy_until
    }

    /// When `len` bytes of a TCP stream written at `now` come out: after their time on the
    /// wire and the delay, one retransmission timeout later for each lost segment, and after
    /// any outage they would cross; never before bytes written earlier.
    fn stream(&mut self, now: Instant, len: usize) -> Instant {
        let sent = self.transmitted(now, len);
        let rto = (self.delay * 3).max(MIN_RTO);
        let mut out = sent + self.delay;
        for _ in 0..len.div_ceil(SEGMENT) {
            if self.rng.random_bool(self.loss) {
                out += rto;
            }
        }
        // Held while the path is down: they leave when it returns (a sender retransmitting).
        loop {
            match self.outage_end(out).or_else(|| self.outage_end(sent)) {
                Some(end) if end + self.delay > out => out = end + self.delay,
                _ => break,
            }
        }
        self.last_out = out.max(self.last_out);
        self.last_out
    }

    /// When a datagram of `len` bytes sent at `now` comes out, or `None` when it is lost (by
    /// chance, or to an outage).
    fn datagram(&mut self, now: Instant, len: usize) -> Option<Instant> {
        if self.outage_end(now).is_some() {
            return None;
        }
        let sent = self.transmitted(now, len);
        if self.rng.random_bool(self.loss) {
            return None;
        }
        Some(sent + self.delay)
    }
}

fn out(v: serde_json::Value) {
    println!("{v}");
}

#[tokio::main]
async fn main() -> anyhow::Result<()> {
    let args = Args::parse();
    if !(0.0..=1.0).contains(&args.loss) {
        bail!("--loss must be within 0..1, got {}", args.loss);
    }
    let start = Instant::now();
    for &(s, d) in &args.outage {
        tokio::spawn(async move {
            tokio::time::sleep_until((start + Duration::from_millis(s)).into()).await;
            out(json!({"outage": "start", "duration_ms": d}));
            tokio::time::sleep(Duration::from_millis(d)).await;
            out(json!({"outage": "end"}));
        });
    }
    if args.udp {
        udp(args, start).await
    } else {
        tcp(args, start).await
    }
}

async fn tcp(args: Args, start: Instant) -> anyhow::Result<()> {
    let listener = TcpListener::bind(args.listen)
        .await
        .with_context(|| format!("listening on {}", args.listen))?;
    out(json!({"listen": listener.local_addr()?.to_string()}));
    let args = Arc::new(args);
    let mut seed = args.seed;
    loop {
        let (client, from) = listener.accept().await.context("accepting")?;
        let args = args.clone();
        seed = seed.wrapping_add(2);
        tokio::spawn(async move {
            if let Err(e) = connection(client, &args, start, seed).await {
                eprintln!("marea-wan: connection from {from}: {e:#}");
            }
        });
    }
}

async fn connection(
    client: TcpStream,
    args: &Args,
    start: Instant,
    seed: u64,
) -> anyhow::Result<()> {
    // A connection opened during an outage waits for the path to return.
    let probe = Path::new(args, start, seed);
    if let Some(end) = probe.outage_end(Instant::now()) {
        tokio::time::sleep_until(end.into()).await;
    }
    let server = TcpStream::connect(args.to)
        .await
        .with_context(|| format!("connecting to {}", args.to))?;
    let _ = client.set_nodelay(true);
    let _ = server.set_nodelay(true);
    let (cr, cw) = client.into_split();
    let (sr, sw) = server.into_split();
    let up = pump(cr, sw, Path::new(args, start, seed));
    let down = pump(sr, cw, Path::new(args, start, seed + 1));
    // Either side closing closes the other.
    tokio::select! {
        r = up => r,
        r = down => r,
    }
}

/// Carries one direction of a connection through `path`.
async fn pump(
    mut from: tokio::net::tcp::OwnedReadHalf,
    mut to: tokio::net::tcp::OwnedWriteHalf,
    mut path: Path,
) -> anyhow::Result<()> {
    let (tx, mut rx) = mpsc::unbounded_channel::<(Instant, Vec<u8>)>();
    let writer = async move {
        while let Some((at, bytes)) = rx.recv().await {
            tokio::time::sleep_until(at.into()).await;
            if to.write_all(&bytes).await.is_err() {
                break;
            }
        }
        let _ = to.shutdown().await;
    };
    let reader = async move {
        let mut buf = vec![0u8; 64 * 1024];
        loop {
            let n = from.read(&mut buf).await?;
            if n == 0 {
                return Ok::<(), anyhow::Error>(());
            }
            let at = path.stream(Instant::now(), n);
            if tx.send((at, buf[..n].to_vec())).is_err() {
                return Ok(());
            }
        }
    };
    let (r, ()) = tokio::join!(reader, writer);
    r
}

async fn udp(args: Args, start: Instant) -> anyhow::Result<()> {
    let front = Arc::new(
        UdpSocket::bind(args.listen)
            .await
            .with_context(|| format!("binding {}", args.listen))?,
    );
    out(json!({"listen": front.local_addr()?.to_string()}));
    let up = Arc::new(Mutex::new(Path::new(&args, start, args.seed)));
    let mut clients: HashMap<SocketAddr, Arc<UdpSocket>> = HashMap::new();
    let mut buf = vec![0u8; 65_536];
    loop {
        let (n, from) = front.recv_from(&mut buf).await?;
        let back = match clients.get(&from) {
            Some(s) => s.clone(),
            None => {
                // One socket towards the server per client, so replies find their way back.
                let s = Arc::new(UdpSocket::bind("127.0.0.1:0").await?);
                s.connect(args.to).await?;
                clients.insert(from, s.clone());
                let down = Path::new(&args, start, args.seed + clients.len() as u64 * 2);
                tokio::spawn(replies(s.clone(), front.clone(), from, down));
                s
            }
        };
        let at = marea::sync::lock(&up).datagram(Instant::now(), n);
        if let Some(at) = at {
            let bytes = buf[..n].to_vec();
            tokio::spawn(async move {
                tokio::time::sleep_until(at.into()).await;
                let _ = back.send(&bytes).await;
            });
        }
    }
}

/// Carries the server's datagrams back to client `to` through `path`.
async fn replies(back: Arc<UdpSocket>, front: Arc<UdpSocket>, to: SocketAddr, mut path: Path) {
    let mut buf = vec![0u8; 65_536];
    while let Ok(n) = back.recv(&mut buf).await {
        if let Some(at) = path.datagram(Instant::now(), n) {
            let bytes = buf[..n].to_vec();
            let front = front.clone();
            tokio::spawn(async move {
                tokio::time::sleep_until(at.into()).await;
                let _ = front.send_to(&bytes, to).await;
            });
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn args(delay_ms: u64, rate_kbps: u64, loss: f64, outage: Vec<(u64, u64)>) -> Args {
        Args {
            listen: "127.0.0.1:0".parse().unwrap(),
            to: "127.0.0.1:1".parse().unwrap(),
            udp: false,
            delay_ms,
            rate_kbps,
            loss,
            outage,
            seed: 7,
        }
    }

    #[test]
    fn bytes_take_their_time_on_the_wire_plus_the_delay_and_keep_their_order() {
        let t0 = Instant::now();
        // 2 Mbit/s: 250,000 bytes a second; 75 ms one way.
        let mut p = Path::new(&args(75, 2000, 0.0, vec![]), t0, 1);
        let a = p.stream(t0, 25_000);
        assert_eq!(a - t0, Duration::from_millis(100 + 75));
        // Written at once behind it: waits for the wire.
        let b = p.stream(t0, 25_000);
        assert_eq!(b - t0, Duration::from_millis(200 + 75));
        // Later, on an idle wire: only its own time.
        let c = p.stream(t0 + Duration::from_secs(1), 2_500);
        assert_eq!(c - t0, Duration::from_millis(1000 + 10 + 75));
    }

    #[test]
    fn a_lost_segment_costs_a_retransmission_timeout_and_holds_what_follows() {
        let t0 = Instant::now();
        let mut p = Path::new(&args(75, 0, 1.0, vec![]), t0, 1);
        // Every segment lost: one RTO (3 x 75 ms) per segment.
        assert_eq!(p.stream(t0, 100) - t0, Duration::from_millis(75 + 225));
        assert_eq!(
            p.stream(t0, 2 * SEGMENT) - t0,
            Duration::from_millis(75 + 450)
        );
        // With 1 % loss about one segment in a hundred is late.
        let mut p = Path::new(&args(10, 0, 0.01, vec![]), t0, 3);
        let late = (0..10_000)
            .filter(|i| {
                let now = t0 + Duration::from_secs(*i);
                p.stream(now, SEGMENT) - now > Duration::from_millis(10)
            })
            .count();
        assert!((50..200).contains(&late), "{late} of 10,000 segments late");
    }

    #[test]
    fn an_outage_holds_a_stream_and_drops_datagrams() {
        let t0 = Instant::now();
        let mut p = Path::new(&args(50, 0, 0.0, vec![(1000, 30_000)]), t0, 1);
        let during = t0 + Duration::from_secs(5);
        assert_eq!(
            p.stream(during, 10) - t0,
            Duration::from_millis(31_000 + 50)
        );
        assert_eq!(p.datagram(during, 10), None);
        let after = t0 + Duration::from_secs(40);
        assert_eq!(
            p.datagram(after, 10),
            Some(after + Duration::from_millis(50))
        );
        // Written just before the outage, due out inside it: held to its end.
        let before = t0 + Duration::from_millis(990);
        let mut q = Path::new(&args(50, 0, 0.0, vec![(1000, 30_000)]), t0, 1);
        assert_eq!(
            q.stream(before, 10) - t0,
            Duration::from_millis(31_000 + 50)
        );
    }
}
