//! `cargo bench --bench ethernet`: the Ethernet link's figures as JSON lines
//! `{"metric": ..., "value": ..., "unit": ...}`, each middleware figure next to a raw UDP
//! baseline measured in the same run on the same machine.

use std::sync::Arc;
use std::time::{Duration, Instant};

use marea::codec::{encode_message, encode_payload};
use marea::config::{EthernetConfig, LinkConfig};
use marea::link::datagram::DatagramWriter;
use marea::protocol::Message;
use marea::{NetworkConfig, Node, SendFileOptions};
use tokio::net::UdpSocket;

type Payload64 = [u64; 8];

fn metric(name: &str, value: f64, unit: &str) {
    println!(
        "{}",
        serde_json::json!({"metric": name, "value": value, "unit": unit})
    );
}

fn cfg(node: &str, domain: &str, port: u16) -> NetworkConfig {
    let mut c = NetworkConfig::ethernet_loopback(node);
    c.domain = domain.into();
    c.links = vec![LinkConfig::Ethernet(EthernetConfig {
        interface: std::net::Ipv4Addr::LOCALHOST,
        bind: "127.0.0.1:0".parse().expect("literal address"),
        multicast: std::net::SocketAddrV4::new(std::net::Ipv4Addr::new(239, 255, 77, 9), port),
        ..EthernetConfig::default()
    })];
    c
}

fn percentile(sorted: &[f64], p: f64) -> f64 {
    let i = ((sorted.len() as f64 - 1.0) * p).round() as usize;
    sorted[i.min(sorted.len() - 1)]
}

async fn raw_echo_rtt(n: usize) -> Vec<f64> {
    let server = UdpSocket::bind("127.0.0.1:0").await.expect("bind");
    let client = UdpSocket::bind("127.0.0.1:0").await.expect("bind");
    let saddr = server.local_addr().expect("addr");
    let echo = tokio::spawn(async move {
        let mut buf = [0u8; 2048];
        for _ in 0..n {
            let (len, from) = server.recv_from(&mut buf).await.expect("recv");
            server.send_to(&buf[..len], from).await.expect("send");
        }
    });
    let msg = [7u8; 64];
    let mut buf = [0u8; 2048];
    let mut out = Vec::with_capacity(n);
    for _ in 0..n {
        let t = Instant::now();
        client.send_to(&msg, saddr).await.expect("send");
        client.recv_from(&mut buf).await.expect("recv");
        out.push(t.elapsed().as_secs_f64() * 1e6);
    }
    let _ = echo.await;
    out
}

/// The receiving end of a throughput measurement, in a child process (this bench binary
/// started again with `SINK_ROLE` set): it counts what arrives and reports the rate between its
/// first and last arrival.
struct Sink {
    child: std::process::Child,
    lines: std::io::Lines<std::io::BufReader<std::process::ChildStdout>>,
    /// Where a raw sink listens.
    addr: std::net::SocketAddr,
}

const SINK_ROLE: &str = "ETHERNET_BENCH_SINK";

impl Sink {
    fn start(kind: &str, domain: &str, port: u16) -> Result<Sink, Box<dyn std::error::Error>> {
        use std::io::BufRead;
        let mut child = std::process::Command::new(std::env::current_exe()?)
            .env(SINK_ROLE, format!("{kind} {domain} {port}"))
            .stdin(std::process::Stdio::piped())
            .stdout(std::process::Stdio::piped())
            .spawn()?;
        let stdout = child.stdout.take().ok_or("sink without stdout")?;
        let mut lines = std::io::BufReader::new(stdout).lines();
        let ready = lines.next().ok_or("sink ended before it was ready")??;
        let addr = ready
            .strip_prefix("ready ")
            .ok_or_else(|| format!("sink said {ready:?}"))?
            .parse()?;
        Ok(Sink { child, lines, addr })
    }

    /// Stops the sink; returns messages per second between its first and last arrival.
    fn finish(mut self) -> Result<f64, Box<dyn std::error::Error>> {
        use std::io::Write;
        if let Some(mut stdin) = self.child.stdin.take() {
            writeln!(stdin, "stop")?;
        }
        let report = self.lines.next().ok_or("sink ended without a report")??;
        let _ = self.child.wait();
        let mut it = report.split_whitespace().map(str::parse::<f64>);
        match (it.next(), it.next()) {
            (Some(Ok(count)), Some(Ok(span))) if span > 0.0 => Ok(count / span),
            _ => Err(format!("sink reported {report:?}").into()),
        }
    }
}

/// Counts arrivals: how many, and the first and last instant.
#[derive(Default)]
struct Arrivals {
    count: u64,
    first: Option<Instant>,
    last: Option<Instant>,
}

impl Arrivals {
    fn add(&mut self) {
        let now = Instant::now();
        self.count += 1;
        self.first.get_or_insert(now);
        self.last = Some(now);
    }

    fn report(&self) -> String {
        let span = match (self.first, self.last) {
            (Some(a), Some(b)) => b.duration_since(a).as_secs_f64(),
            _ => 0.0,
        };
        format!("{} {span}", self.count)
    }
}

/// The child-process side of [`Sink`].
async fn run_sink(role: &str) -> Result<(), Box<dyn std::error::Error>> {
    let mut words = role.split_whitespace();
    let (Some(kind), Some(domain), Some(port)) = (words.next(), words.next(), words.next()) else {
        return Err(format!("{SINK_ROLE}={role:?}: expected KIND DOMAIN PORT").into());
    };
    let arrivals = Arc::new(std::sync::Mutex::new(Arrivals::default()));
    let a = arrivals.clone();
    let mut node = None;
    let counter = match kind {
        "raw" => {
            let rx = UdpSocket::bind("127.0.0.1:0").await?;
            println!("ready {}", rx.local_addr()?);
            tokio::spawn(async move {
                let mut buf = [0u8; 2048];
                while rx.recv_from(&mut buf).await.is_ok() {
                    a.lock().expect("counter lock").add();
                }
            })
        }
        "var" => {
            let n = Node::open(&cfg("bench-sink", domain, port.parse()?)).await?;
            let sub = n
                .service("sink")?
                .subscribe_variable::<Payload64>("a/tm/*")?;
            node = Some(n);
            println!("ready 127.0.0.1:0");
            tokio::spawn(async move {
                while sub.recv().await.is_ok() {
                    a.lock().expect("counter lock").add();
                }
            })
        }
        other => return Err(format!("unknown sink kind {other:?}").into()),
    };
    let mut line = String::new();
    tokio::task::spawn_blocking(move || std::io::stdin().read_line(&mut line)).await??;
    println!("{}", arrivals.lock().expect("counter lock").report());
    counter.abort();
    if let Some(n) = node {
        n.shutdown().await;
    }
    Ok(())
}

#[tokio::main]
async fn main() -> Result<(), Box<dyn std::error::Error>> {
    if let Ok(role) = std::env::var(SINK_ROLE) {
        return run_sink(&role).await;
    }
    let domain = format!("bench-{}", std::process::id());
    let port = 30_000 + (std::process::id() % 20_000) as u16;

    // Bytes on the wire for one position sample sent alone: the datagram the link builds.
    let position = encode_payload(&(41.0f64, 1.9f64, 30.0f64, 90.0f32, 1.5f32))?;
    let msg = encode_message(&Message::Var {
        id: 3,
        payload: position,
    });
    let mut w = DatagramWriter::new(1400);
    w.push_fast(&msg);
    metric("wire.position.udp_bytes", w.take().len() as f64, "bytes");

    let a = Node::open(&cfg("bench-a", &domain, port)).await?;
    let b = Node::open(&cfg("bench-b", &domain, port)).await?;
    let sa = a.service("a")?;
    let sb = b.service("b")?;

    // Variable round trip: a publishes ping, b answers pong with the same value.
    let ping = sa.publish_variable::<Payload64>("ping")?;
    let pongs = sa.subscribe_variable::<Payload64>("b/pong")?;
    let pong = sb.publish_variable::<Payload64>("pong")?;
    let pings = sb.subscribe_variable::<Payload64>("a/ping")?;
    ping.wait_remote_subscribers(1, Duration::from_secs(10))
        .await;
    pong.wait_remote_subscribers(1, Duration::from_secs(10))
        .await;
    let echo = tokio::spawn(async move {
        while let Ok(s) = pings.recv().await {
            if pong.set(&s.value).is_err() {
                break;
            }
        }
    });
    let n = 20_000;
    let mut rtts = Vec::with_capacity(n);
    for i in 0..(n + 1000) {
        let v: Payload64 = [i as u64; 8];
        let t = Instant::now();
        ping.set(&v)?;
        loop {
            let s = pongs.recv().await?;
            if s.value == v {
                break;
            }
        }
        if i >= 1000 {
            rtts.push(t.elapsed().as_secs_f64() * 1e6);
        }
    }
    echo.abort();
    rtts.sort_by(f64::total_cmp);
    let mut raw = raw_echo_rtt(n).await;
    raw.sort_by(f64::total_cmp);
    metric("udp.var64.rtt_p50_us", percentile(&rtts, 0.5), "us");
    metric("udp.var64.rtt_p99_us", percentile(&rtts, 0.99), "us");
    metric("udp.raw_echo64.rtt_p50_us", percentile(&raw, 0.5), "us");
    metric("udp.raw_echo64.rtt_p99_us", percentile(&raw, 0.99), "us");
    metric(
        "udp.var64.rtt_ratio_to_raw",
        percentile(&rtts, 0.5) / percentile(&raw, 0.5),
        "ratio",
    );

    // Variable throughput: 100 telemetry variables published round robin, received and counted
    // by another process (as in a deployment: the receive path gets its own process).
    let vars: Vec<_> = (0..100)
        .map(|i| sa.publish_variable::<Payload64>(&format!("tm/v{i}")))
        .collect::<Result<_, _>>()?;
    let secs = 3.0;
    let sink = Sink::start("var", &domain, port)?;
    for v in &vars {
        v.wait_remote_subscribers(1, Duration::from_secs(10)).await;
    }
    let start = Instant::now();
    let mut i = 0u64;
    while start.elapsed().as_secs_f64() < secs {
        for _ in 0..64 {
            vars[(i % 100) as usize].set(&[i; 8])?;
            i += 1;
        }
        tokio::task::yield_now().await;
    }
    let sets = i as f64 / start.elapsed().as_secs_f64();
    let var_rate = sink.finish()?;
    let sink = Sink::start("raw", &domain, port)?;
    let raw_rate = {
        let tx = UdpSocket::bind("127.0.0.1:0").await?;
        let msg = [7u8; 64];
        let start = Instant::now();
        while start.elapsed().as_secs_f64() < secs {
            let _ = tx.send_to(&msg, sink.addr).await;
        }
        sink.finish()?
    };
    metric("udp.var64.sets_per_s", sets, "msgs/s");
    metric("udp.var64.msgs_per_s", var_rate, "msgs/s");
    metric("udp.raw64.msgs_per_s", raw_rate, "msgs/s");
    metric("udp.var64.rate_ratio_to_raw", var_rate / raw_rate, "ratio");

    // Reliable events: a window of raises in flight, counted at the subscriber.
    let ev = sa.publish_event::<Payload64>("ev")?;
    let evsub = sb.subscribe_event::<Payload64>("a/ev")?;
    ev.wait_remote_subscribers(1, Duration::from_secs(10)).await;
    let total = 300_000u64;
    let start = Instant::now();
    let recv = tokio::spawn(async move {
        let mut n = 0u64;
        while n < total {
            if evsub.recv().await.is_err() {
                break;
            }
            n += 1;
        }
        n
    });
    let mut inflight = std::collections::VecDeque::new();
    for i in 0..total {
        inflight.push_back(ev.raise_nowait(&[i; 8])?);
        if inflight.len() >= 4096 {
            if let Some(p) = inflight.pop_front() {
                p.await;
            }
        }
    }
    while let Some(p) = inflight.pop_front() {
        p.await;
    }
    let got = recv.await?;
    metric(
        "udp.event64.msgs_per_s",
        got as f64 / start.elapsed().as_secs_f64(),
        "msgs/s",
    );

    // File transfer.
    let dir = tempfile::tempdir()?;
    let path = dir.path().join("f20mb.bin");
    let data: Vec<u8> = (0..20_000_000u32)
        .map(|i| (i.wrapping_mul(2_654_435_761) >> 11) as u8)
        .collect();
    std::fs::write(&path, &data)?;
    let sink = sb.file_sink("files", dir.path().join("in"))?;
    tokio::time::sleep(Duration::from_millis(300)).await;
    let start = Instant::now();
    let report = sa
        .send_file(&path, "b/files", SendFileOptions::default())
        .wait()
        .await?;
    let secs = start.elapsed().as_secs_f64();
    let _ = sink.recv_timeout(Duration::from_secs(5)).await;
    metric(
        "file.udp_20mb.mb_per_s",
        report.size as f64 / 1e6 / secs,
        "MB/s",
    );
    drop((vars, ev, ping, pongs, sink));
    drop((sa, sb));
    a.shutdown().await;
    b.shutdown().await;

    // Idle discovery: 10 services with 10 items each, another node listening, nobody subscribing.
    let idle = Node::open(&cfg("idle", &domain, port + 1)).await?;
    let listener = Node::open(&cfg("listener", &domain, port + 1)).await?;
    let mut keep = Vec::new();
    let mut svcs = Vec::new();
    for s in 0..10 {
        let svc = idle.service(&format!("svc{s}"))?;
        for i in 0..10 {
            keep.push(svc.publish_variable::<Payload64>(&format!("item{i}"))?);
        }
        svcs.push(svc);
    }
    tokio::time::sleep(Duration::from_millis(2500)).await;
    let before: u64 = idle.link_stats().iter().map(|(_, s)| s.bytes_out).sum();
    let window = Duration::from_secs(10);
    tokio::time::sleep(window).await;
    let after: u64 = idle.link_stats().iter().map(|(_, s)| s.bytes_out).sum();
    metric(
        "discovery.idle_bytes_per_s",
        (after - before) as f64 / window.as_secs_f64(),
        "bytes/s",
    );
    drop((keep, svcs));
    idle.shutdown().await;
    listener.shutdown().await;
    Ok(())
}
