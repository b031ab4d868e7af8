//! `marea-radio`: a pair of 3DR-like radios emulated between two pty pairs. It prints the two
//! device paths (JSON line `{"ground": .., "air": ..}`), then carries bytes between them at the
//! air data rate, half duplex (both directions share the air time) unless told otherwise, losing
//! and corrupting bytes with seeded probabilities and going silent during scheduled outages.
//! On SIGINT/SIGTERM (and every `--stats-ms`) it prints its counters as a JSON line.
//!
//! ```text
//! marea-radio --air-rate 64000 --loss 0.005 --corrupt 0.005 --outage 20000:10000 --seed 7
//! ```

use std::collections::VecDeque;
use std::time::{Duration, Instant};

use anyhow::{bail, Context};
use clap::Parser;
use marea::link::serial::sim::{FaultInjector, Faults};
use serde::Serialize;
use serde_json::json;
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::sync::mpsc;
use tokio_serial::{SerialPort, SerialStream};

#[derive(Parser, Debug)]
#[command(about = "Emulates a pair of serial radios between two pty pairs")]
struct Args {
    /// Air data rate in bit/s (3DR default 64 kbit/s). A byte costs 8 bits of air time.
    #[arg(long, default_value_t = 64_000)]
    air_rate: u32,
    /// Give each direction its own air time instead of sharing it.
    #[arg(long)]
    full_duplex: bool,
    /// Probability that a byte is lost on air.
    #[arg(long, default_value_t = 0.0)]
    loss: f64,
    /// Probability that a byte is corrupted on air.
    #[arg(long, default_value_t = 0.0)]
    corrupt: f64,
    /// Outage `START_MS:DURATION_MS` after start (repeatable): bytes on air are lost.
    #[arg(long, value_parser = parse_outage)]
    outage: Vec<(u64, u64)>,
    /// On SIGUSR1, an outage of this many milliseconds starts at once (cut the link at a
    /// chosen moment rather than a scheduled one); each start is printed as an `outage` line.
    #[arg(long, value_name = "MS")]
    outage_on_signal: Option<u64>,
    /// Seed of the fault generator.
    #[arg(long, default_value_t = 1)]
    seed: u64,
    /// Radio buffer per direction in bytes; bytes arriving at a full buffer are dropped.
    #[arg(long, default_value_t = 4096)]
    buffer: usize,
    /// Print counters every this many ms (0: only on exit).
    #[arg(long, default_value_t = 0)]
    stats_ms: u64,
}

fn parse_outage(s: &str) -> Result<(u64, u64), String> {
    let (a, b) = s
        .split_once(':')
        .ok_or_else(|| format!("expected START_MS:DURATION_MS, got {s:?}"))?;
    let a = a.parse().map_err(|e| format!("start {a:?}: {e}"))?;
    let b = b.parse().map_err(|e| format!("duration {b:?}: {e}"))?;
    Ok((a, b))
}

/// Counters of one direction.
#[derive(Debug, Default, Clone, Copy, Serialize)]
struct DirStats {
    /// Bytes the sending side wrote.
    bytes_in: u64,
    /// Bytes delivered to the receiving side.
    bytes_out: u64,
    /// Bytes lost on air (random).
    lost: u64,
    /// Bytes corrupted on air.
    corrupted: u64,
    /// Bytes lost to outages.
    outage_lost: u64,
    /// Bytes dropped because the radio buffer was full.
    overflow: u64,
}

struct Direction {
    queue: VecDeque<u8>,
    faults: FaultInjector,
    stats: DirStats,
    out: mpsc::UnboundedSender<Vec<u8>>,
}

impl Direction {
    fn accept(&mut self, bytes: &[u8], cap: usize) {
        self.stats.bytes_in += bytes.len() as u64;
        for &b in bytes {
            if self.queue.len() < cap {
                self.queue.push_back(b);
            } else {
                self.stats.overflow += 1;
            }
        }
    }

    /// Puts up to `budget` bytes on air; returns how many were used.
    fn transmit(&mut self, budget: usize, outage: bool) -> usize {
        let n = budget.min(self.queue.len());
        if n == 0 {
            return 0;
        }
        let chunk: Vec<u8> = self.queue.drain(..n).collect();
        if outage {
            self.stats.outage_lost += n as u64;
            return n;
        }
        let before = (self.faults.lost, self.faults.corrupted);
        let delivered = self.faults.apply(&chunk);
        self.stats.lost += self.faults.lost - before.0;
        self.stats.corrupted += self.faults.corrupted - before.1;
        self.stats.bytes_out += delivered.len() as u64;
        let _ = self.out.send(delivered);
        n
    }
}

fn pty() -> anyhow::Result<(SerialStream, SerialStream, String)> {
    let (master, slave) = SerialStream::pair().context("cannot create a pty pair")?;
    let name = slave
        .name()
        .context("the pty slave has no device path")?
        .to_string();
    Ok((master, slave, name))
}

#[tokio::main(flavor = "current_thread")]
async fn main() -> anyhow::Result<()> {
    let args = Args::parse();
    if !(0.0..=1.0).contains(&args.loss) || !(0.0..=1.0).contains(&args.corrupt) {
        bail!("--loss and --corrupt are probabilities between 0 and 1");
    }
    if args.air_rate == 0 {
        bail!("--air-rate must be positive");
    }
    // The slaves stay open here so a client may come and go without the master seeing EIO.
    let (g_master, _g_slave, g_name) = pty()?;
    let (a_master, _a_slave, a_name) = pty()?;
    println!("{}", json!({ "ground": g_name, "air": a_name }));

    let (g_read, mut g_write) = tokio::io::split(g_master);
    let (a_read, mut a_write) = tokio::io::split(a_master);
    let (to_g_tx, mut to_g_rx) = mpsc::unbounded_channel::<Vec<u8>>();
    let (to_a_tx, mut to_a_rx) = mpsc::unbounded_channel::<Vec<u8>>();
    let (in_tx, mut in_rx) = mpsc::unbounded_channel::<(bool, Vec<u8>)>();

    let faults = Faults {
        loss: args.loss,
        corrupt: args.corrupt,
    };
    let mut g2a = Direction {
        queue: VecDeque::new(),
        faults: FaultInjector::new(args.seed, faults),
        stats: DirStats::default(),
        out: to_a_tx,
    };
    let mut a2g = Direction {
        queue: VecDeque::new(),
        faults: FaultInjector::new(args.seed.wrapping_mul(0x9E37_79B9_7F4A_7C15) ^ 1, faults),
        stats: DirStats::default(),
        out: to_g_tx,
    };

    let mut tasks = tokio::task::JoinSet::new();
    for (from_ground, mut r) in [(true, g_read), (false, a_read)] {
        let tx = in_tx.clone();
        tasks.spawn(async move {
            let mut buf = vec![0u8; 4096];
            loop {
                match r.read(&mut buf).await {
                    Ok(0) => break,
                    Ok(n) => {
                        if tx.send((from_ground, buf[..n].to_vec())).is_err() {
                            break;
                        }
                    }
                    // EIO while no client has the slave open: wait and retry.
                    Err(_) => tokio::time::sleep(Duration::from_millis(50)).await,
                }
            }
        });
    }
    tasks.spawn(async move {
        while let Some(b) = to_g_rx.recv().await {
            if g_write.write_all(&b).await.is_err() {
                break;
            }
        }
    });
    tasks.spawn(async move {
        while let Some(b) = to_a_rx.recv().await {
            if a_write.write_all(&b).await.is_err() {
                break;
            }
        }
    });

    let start = Instant::now();
    let tick = Duration::from_millis(2);
    let mut interval = tokio::time::interval(tick);
    interval.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
    let bytes_per_s = f64::from(args.air_rate) / 8.0;
    let mut credit = [0f64; 2];
    let mut last = Instant::now();
    let mut ground_first = true;
    let mut stats_at = (args.stats_ms > 0).then(|| start + Duration::from_millis(args.stats_ms));
    let mut sigterm = tokio::signal::unix::signal(tokio::signal::unix::SignalKind::terminate())
        .context("cannot watch SIGTERM")?;
    let mut sigusr1 = tokio::signal::unix::signal(tokio::signal::unix::SignalKind::user_defined1())
        .context("cannot watch SIGUSR1")?;
    // The end of the outage SIGUSR1 started.
    let mut signalled_until: Option<Instant> = None;
    let report = |g2a: &Direction, a2g: &Direction, event: &str| {
        println!(
            "{}",
            json!({
                "event": event,
                "elapsed_ms": start.elapsed().as_millis() as u64,
                "ground_to_air": g2a.stats,
                "air_to_ground": a2g.stats,
            })
        );
    };
    loop {
        tokio::select! {
            _ = tokio::signal::ctrl_c() => break,
            _ = sigterm.recv() => break,
            _ = sigusr1.recv() => {
                match args.outage_on_signal {
                    Some(ms) => {
                        signalled_until = Some(Instant::now() + Duration::from_millis(ms));
                        println!(
                            "{}",
                            json!({
                                "event": "outage",
                                "elapsed_ms": start.elapsed().as_millis() as u64,
                                "duration_ms": ms,
                            })
                        );
                    }
                    None => eprintln!("marea-radio: SIGUSR1 ignored (no --outage-on-signal)"),
                }
                continue;
            }
            Some((from_ground, bytes)) = in_rx.recv() => {
                let d = if from_ground { &mut g2a } else { &mut a2g };
                d.accept(&bytes, args.buffer);
                continue;
            }
            _ = interval.tick() => {}
        }
        let now = Instant::now();
        let dt = now.saturating_duration_since(last).as_secs_f64();
        last = now;
        let since = now.saturating_duration_since(start).as_millis() as u64;
        let outage = args
            .outage
            .iter()
            .any(|&(a, d)| since >= a && since < a + d)
            || signalled_until.is_some_and(|end| now < end);
        // Credit that is not used is not saved up beyond a few ticks: air time passes.
        let cap = bytes_per_s * 0.02;
        if args.full_duplex {
            for (i, d) in [&mut g2a, &mut a2g].into_iter().enumerate() {
                credit[i] = (credit[i] + bytes_per_s * dt).min(cap);
                let used = d.transmit(credit[i] as usize, outage);
                credit[i] -= used as f64;
            }
        } else {
            credit[0] = (credit[0] + bytes_per_s * dt).min(cap);
            let (first, second) = if ground_first {
                (&mut g2a, &mut a2g)
            } else {
                (&mut a2g, &mut g2a)
            };
            ground_first = !ground_first;
            let used = first.transmit(credit[0] as usize, outage);
            credit[0] -= used as f64;
            let used = second.transmit(credit[0] as usize, outage);
            credit[0] -= used as f64;
        }
        if let Some(t) = stats_at {
            if now >= t {
                report(&g2a, &a2g, "stats");
                stats_at = Some(t + Duration::from_millis(args.stats_ms));
            }
        }
    }
    report(&g2a, &a2g, "exit");
    tasks.abort_all();
    Ok(())
}
